/* Terminator: asks the importer to end the simulation (terminateSimulation) at stop_at.

   y = the time reached. The step that reaches stop_at (t + h >= stop_at) sets terminateSimulation;
   with discard = true it stops exactly at stop_at inside the step instead and returns fmi3Discard
   with lastSuccessfulTime = stop_at (the standard's other way to end a run). A step after that
   is refused with fmi3Error. */
#include "fmu_base.h"

#define INSTANTIATION_TOKEN "{conformance-terminator-1}"

typedef struct {
    double stop_at, y, time;
    bool discard, stopped;
} Model;

#include "fmu_common.h"

static void model_start_values(Model *m) {
    memset(m, 0, sizeof *m);
    m->stop_at = 0.05;
}

static void model_variables(Instance *inst) {
    SCALAR(inst, 0, "time", V_FLOAT64, C_OUTPUT, time);
    SCALAR(inst, 1, "stop_at", V_FLOAT64, C_PARAMETER, stop_at);
    SCALAR(inst, 2, "discard", V_BOOLEAN, C_PARAMETER, discard);
    SCALAR(inst, 3, "y", V_FLOAT64, C_OUTPUT, y);
}

static fmi3Status model_exit_initialization(Instance *inst) { (void)inst; return fmi3OK; }

static fmi3Status model_step(Instance *inst, double t, double h, bool *terminate, bool *early, double *last) {
    (void)early;
    Model *m = &inst->model;
    if (m->stopped)
        return fail(inst, "fmi3DoStep after terminateSimulation (requested at t = %g s)", m->stop_at);
    double end = t + h;
    if (end >= m->stop_at) {
        m->stopped = true;
        *terminate = true;
        log_message(inst, fmi3OK, "the simulation is over at t = %g s: terminateSimulation", m->stop_at);
        if (m->discard) {
            m->y = m->time = m->stop_at;
            *last = m->stop_at;
            return fmi3Discard;
        }
    }
    m->y = m->time = end;
    return fmi3OK;
}
