/* FixedStep: a model that computes in fixed internal steps of 2 ms (fixedInternalStepSize).

   x decays by explicit Euler with rate a over each internal step: x <- x * (1 - a * DT), from
   x = 1; `steps` counts the internal steps. A communication step that is not a whole multiple of
   DT is refused (fmi3Error, with the reason logged). */
#include "fmu_base.h"

#define INSTANTIATION_TOKEN "{conformance-fixed-step-1}"
#define DT 0.002

typedef struct {
    double a, x, time;
    int32_t steps;
} Model;

#include "fmu_common.h"

static void model_start_values(Model *m) {
    m->a = 2.0;
    m->x = 1.0;
    m->steps = 0;
    m->time = 0.0;
}

static void model_variables(Instance *inst) {
    SCALAR(inst, 0, "time", V_FLOAT64, C_OUTPUT, time);
    SCALAR(inst, 1, "a", V_FLOAT64, C_PARAMETER, a);
    SCALAR(inst, 2, "x", V_FLOAT64, C_OUTPUT, x);
    SCALAR(inst, 3, "steps", V_INT32, C_OUTPUT, steps);
}

static fmi3Status model_exit_initialization(Instance *inst) { (void)inst; return fmi3OK; }

static fmi3Status model_step(Instance *inst, double t, double h, bool *terminate, bool *early, double *last) {
    (void)terminate; (void)early; (void)last; (void)t;
    Model *m = &inst->model;
    double ratio = h / DT;
    long n = lround(ratio);
    if (n < 1 || fabs(ratio - (double)n) > 1e-9 * ratio)
        return fail(inst, "communication step %.17g s is not a whole multiple of the fixed internal step %g s", h, DT);
    for (long i = 0; i < n; i++) {
        m->x = m->x * (1.0 - m->a * DT);
        m->steps += 1;
    }
    m->time = t + h;
    return fmi3OK;
}
