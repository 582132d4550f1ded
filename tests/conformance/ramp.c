/* Ramp: accepts any communication step (canHandleVariableCommunicationStepSize, no fixed internal
   step); its default experiment step (10 ms) is only a suggestion.

   At the end of a step from t over h: y = (t + h)^2, h_last = h, calls = steps taken,
   integral += u * h. A step longer than max_step is not taken: fmi3Discard (the FMU could not
   complete it), with a warning that says why. */
#include "fmu_base.h"

#define INSTANTIATION_TOKEN "{conformance-ramp-1}"

typedef struct {
    double u, y, h_last, integral, time, max_step;
    int32_t calls;
} Model;

#include "fmu_common.h"

static void model_start_values(Model *m) {
    memset(m, 0, sizeof *m);
    m->max_step = 1.0;
}

static void model_variables(Instance *inst) {
    SCALAR(inst, 0, "time", V_FLOAT64, C_OUTPUT, time);
    SCALAR(inst, 1, "u", V_FLOAT64, C_INPUT, u);
    SCALAR(inst, 2, "y", V_FLOAT64, C_OUTPUT, y);
    SCALAR(inst, 3, "h_last", V_FLOAT64, C_OUTPUT, h_last);
    SCALAR(inst, 4, "calls", V_INT32, C_OUTPUT, calls);
    SCALAR(inst, 5, "integral", V_FLOAT64, C_OUTPUT, integral);
    SCALAR(inst, 6, "max_step", V_FLOAT64, C_PARAMETER, max_step);
}

static fmi3Status model_exit_initialization(Instance *inst) { (void)inst; return fmi3OK; }

static fmi3Status model_step(Instance *inst, double t, double h, bool *terminate, bool *early, double *last) {
    (void)terminate; (void)early; (void)last;
    Model *m = &inst->model;
    if (h > m->max_step) {
        log_message(inst, fmi3Warning, "a step of %g s is longer than max_step = %g s: not taken", h, m->max_step);
        return fmi3Discard;
    }
    double end = t + h;
    m->y = end * end;
    m->h_last = h;
    m->calls += 1;
    m->integral += m->u * h;
    m->time = end;
    return fmi3OK;
}
