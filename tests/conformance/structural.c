/* Structural: an array output sized by a structural parameter, which may only be set in
   Configuration Mode (FMI 3.0); set anywhere else the setter returns fmi3Error and says why.

   v[i] = gain * (i + 1) * (t + h) at the end of each step; `configurations` counts the times
   Configuration Mode was left with n set in it. */
#include "fmu_base.h"

#define INSTANTIATION_TOKEN "{conformance-structural-1}"
#define CAPACITY 16

typedef struct {
    uint64_t n;
    double gain, time;
    double v[CAPACITY];
    int32_t configurations;
} Model;

#include "fmu_common.h"

static void model_start_values(Model *m) {
    memset(m, 0, sizeof *m);
    m->n = 3;
    m->gain = 1.0;
}

static void model_variables(Instance *inst) {
    SCALAR(inst, 0, "time", V_FLOAT64, C_OUTPUT, time);
    SCALAR(inst, 1, "n", V_UINT64, C_STRUCTURAL, n);
    SCALAR(inst, 2, "gain", V_FLOAT64, C_PARAMETER, gain);
    add_var(inst, 3, "v", V_FLOAT64, C_OUTPUT, inst->model.v, &inst->model.n, CAPACITY);
    SCALAR(inst, 4, "configurations", V_INT32, C_OUTPUT, configurations);
}

static fmi3Status model_exit_initialization(Instance *inst) {
    Model *m = &inst->model;
    for (uint64_t i = 0; i < m->n; i++) m->v[i] = 0.0;
    m->configurations = inst->configurations;
    return fmi3OK;
}

static fmi3Status model_step(Instance *inst, double t, double h, bool *terminate, bool *early, double *last) {
    (void)terminate; (void)early; (void)last;
    Model *m = &inst->model;
    m->time = t + h;
    for (uint64_t i = 0; i < m->n; i++) m->v[i] = m->gain * (double)(i + 1) * m->time;
    return fmi3OK;
}
