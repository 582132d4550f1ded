/* The master's compiled loop: a stretch of in-process FMU steps run as a flat program.
 *
 * The Python master (orchestration/compiled_loop.py) plans the stretch from its own scheduler and
 * value routing: which component steps at which time, which input is set from which value, which
 * outputs are read, copied or summed. This file only executes that plan: the same FMI calls, with
 * the same values, in the same order as the Python path makes them, without the interpreter
 * between them. It stops at the first call that fails, that logs an error, or after which
 * fmi3DoStep raised a flag (terminateSimulation, earlyReturn, eventHandlingNeeded): the master
 * then carries on from exactly there, in Python, with the error it would have reported itself.
 *
 * The caller releases the GIL (ctypes.CDLL): an FMU that runs Python takes it for its own call.
 *
 * A paced run (real-time) is paced here too: a paced step waits for its time on the wall clock
 * (sleeping until shortly before it where the master may, then spinning), and how late it ended
 * is written down for the master's pacing statistics.
 */
#include <math.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#define FMI_WARNING 1
#define FMI_DISCARD 2

typedef int (*do_step_fn)(void *, double, double, bool, bool *, bool *, bool *, double *);
typedef int (*set_get_fn)(void *, const uint32_t *, size_t, void *, size_t);

/* One component taking part: its instance and fmi3DoStep, the log's error counter. */
typedef struct {
    void *instance;
    do_step_fn do_step;
    const int64_t *logged_errors; /* error-level log messages so far (the binding's log callback counts them) */
    int64_t errors_seen;          /* the count when the program started */
    int64_t step;                 /* its communication step in ticks */
    int64_t busy_ns;              /* wall time inside its steps (set inputs, fmi3DoStep, get outputs) */
    int64_t started_ns;
    bool flags[4];                /* eventHandlingNeeded, terminateSimulation, earlyReturn */
    double last_time;             /* lastSuccessfulTime */
    int64_t *cost_bins;           /* each step's cost (OP_BEGIN to OP_END) counted in its bin (step_costs.py) */
    int64_t budget_ns;            /* a step's period in real time */
    int64_t cost_count;           /* steps timed, the longest and those over budget, since the program started */
    int64_t cost_max_ns;
    int64_t cost_over;
} Component;

/* The bin of a cost in ns, as orchestration.run.step_costs.cost_bin (LINEAR_BITS, SUB_BITS there):
 * unit bins below 2^COST_LINEAR_BITS ns, then 2^COST_SUB_BITS bins per octave (1.6 % wide). */
#define COST_LINEAR_BITS 7
#define COST_SUB_BITS 6
static int64_t cost_bin(int64_t ns) {
    const int64_t linear = (int64_t)1 << COST_LINEAR_BITS, per_octave = (int64_t)1 << COST_SUB_BITS;
    if (ns < linear) return ns < 0 ? 0 : ns;
    int k = 63 - __builtin_clzll((unsigned long long)ns);
    return linear + (int64_t)(k - COST_LINEAR_BITS) * per_octave + ((ns >> (k - COST_SUB_BITS)) & (per_octave - 1));
}

/* An input port (set from float64 values) or a group of observed ports of one type (read). */
typedef struct {
    int64_t component;
    set_get_fn function;
    const uint32_t *vrs;
    int64_t n_vrs;
    double *slot;      /* the float64 values in the binding's buffer */
    void *native;      /* what the function reads or writes (the slot itself for Float64) */
    int64_t size;
    int64_t cast;      /* CAST_* of native */
    double *last;      /* inputs: the last value set through this port's connection */
    int64_t last_valid;
    int64_t last_key;  /* inputs: the tick of the sample last taken through a keyed transition (hold) */
    int64_t has_key;
    int64_t sets;      /* inputs: the sets made through this port in this program */
} Port;

/* The running sum of one window of an "average" transition. */
typedef struct {
    double *sum;
    int64_t opened;    /* 0 until its first sample is copied in */
    int64_t count;     /* its samples from before the program */
    int64_t size;      /* values per sample */
} Window;

enum { CAST_NONE = 0, CAST_BOOL, CAST_INT8, CAST_UINT8, CAST_INT16, CAST_UINT16, CAST_INT32, CAST_UINT32,
       CAST_FLOAT32, CAST_INT64, CAST_UINT64 };

/* 64-bit integers reach the master's float64 values exactly up to this magnitude */
#define EXACT_INTEGER 9007199254740992.0

enum { OP_NOP = 0, OP_BEGIN, OP_SET, OP_STEP, OP_GET, OP_END, OP_COPY, OP_WINDOW, OP_PACE, OP_LATE, OP_MEAN };
#define NO_KEY INT64_MIN

/* Why the program stopped. */
enum { DONE = 0, CALL_FAILED = 1, ERROR_LOGGED = 2, STEP_FLAGS = 3, BAD_OP = 4, NOT_EXACT = 5 };

typedef struct {
    int64_t ops_done; /* ops completed; the op at this index stopped the program (unless DONE) */
    int64_t reason;
    int64_t status;   /* the failed call's status */
} Result;

static int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* The clock the pacing reads, in seconds (the master converts its own origin to it). */
double pacing_clock(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* Real-time pacing of a stretch (see observers.RealtimePacing). */
typedef struct {
    double origin;     /* pacing_clock() at simulated time 0 */
    int64_t started;   /* 0 until the run's first paced step starts: it sets the origin */
    int64_t pace;      /* 0: only measure how late steps end */
    int64_t sleep;     /* sleep until `spin` seconds before a due time (else spin all the way) */
    double spin;
    double *lateness;  /* per paced step: how late it ended (s; < 0: early) */
} Pacing;

static void wait_until(double due, const Pacing *pacing) {
    double ahead = due - pacing_clock();
    if (pacing->sleep && ahead > pacing->spin) {
        double rest = ahead - pacing->spin;
        struct timespec ts = {(time_t)rest, (long)((rest - (double)(time_t)rest) * 1e9)};
        nanosleep(&ts, NULL);  /* a signal cuts it short: the spin below waits the rest */
    }
    while (pacing_clock() < due) {
    }
}

/* An output group's native values into float64; -1 when a 64-bit integer is beyond 2**53 (the
 * binding then refuses it, naming the variable). */
static int to_float64(const Port *p) {
    double *out = p->slot;
    int64_t n = p->size;
    switch (p->cast) {
        case CAST_INT64: { const int64_t *in = (const int64_t *)p->native;
            for (int64_t i = 0; i < n; i++) {
                if (in[i] > (int64_t)EXACT_INTEGER || in[i] < -(int64_t)EXACT_INTEGER) return -1;
                out[i] = (double)in[i];
            } } break;
        case CAST_UINT64: { const uint64_t *in = (const uint64_t *)p->native;
            for (int64_t i = 0; i < n; i++) {
                if (in[i] > (uint64_t)EXACT_INTEGER) return -1;
                out[i] = (double)in[i];
            } } break;
#define CAST(code, type) case code: { const type *in = (const type *)p->native; for (int64_t i = 0; i < n; i++) out[i] = (double)in[i]; } break;
        CAST(CAST_BOOL, bool)
        CAST(CAST_INT8, int8_t)
        CAST(CAST_UINT8, uint8_t)
        CAST(CAST_INT16, int16_t)
        CAST(CAST_UINT16, uint16_t)
        CAST(CAST_INT32, int32_t)
        CAST(CAST_UINT32, uint32_t)
        CAST(CAST_FLOAT32, float)
#undef CAST
        default: break;
    }
    return 0;
}

/* An input's float64 values into its native type; -1 when one does not survive the cast unchanged
 * (a Boolean other than 0 or 1, an integer type given a fraction or a value out of its range). */
static int from_float64(const Port *p) {
    const double *in = p->slot;
    int64_t n = p->size;
    switch (p->cast) {
#define EXACT(code, type, low, high) case code: { type *out = (type *)p->native; \
            for (int64_t i = 0; i < n; i++) { \
                double v = in[i]; \
                if (!(v >= (low) && v <= (high) && v == trunc(v))) return -1; \
                out[i] = (type)v; \
            } } break;
        EXACT(CAST_BOOL, bool, 0.0, 1.0)
        EXACT(CAST_INT8, int8_t, INT8_MIN, INT8_MAX)
        EXACT(CAST_UINT8, uint8_t, 0.0, UINT8_MAX)
        EXACT(CAST_INT16, int16_t, INT16_MIN, INT16_MAX)
        EXACT(CAST_UINT16, uint16_t, 0.0, UINT16_MAX)
        EXACT(CAST_INT32, int32_t, INT32_MIN, INT32_MAX)
        EXACT(CAST_UINT32, uint32_t, 0.0, UINT32_MAX)
        /* as numpy's cast and the binding's check: any whole number the type holds (2**63 and 2**64 are not) */
        EXACT(CAST_INT64, int64_t, -9223372036854775808.0, 9223372036854774784.0)
        EXACT(CAST_UINT64, uint64_t, 0.0, 18446744073709549568.0)
#undef EXACT
        case CAST_FLOAT32: { float *out = (float *)p->native; for (int64_t i = 0; i < n; i++) out[i] = (float)in[i]; } break;
        default: break;
    }
    return 0;
}

/* ops: n_ops rows of 4 int64 (opcode, a, b, c); ticks in ops count from `t0`, `base` ticks a second. */
Result run_program(const int64_t *ops, int64_t n_ops, int64_t t0, int64_t base, Component *components, Port *ports,
                   Window *windows, Pacing *pacing) {
    Result result = {0, DONE, 0};
    for (int64_t k = 0; k < n_ops; k++) {
        const int64_t *op = ops + 4 * k;
        result.ops_done = k;
        switch (op[0]) {
            case OP_BEGIN:
                components[op[1]].started_ns = now_ns();
                break;
            case OP_SET: { /* port op[1] from the float64 values at address op[2], the sample of tick t0 + op[3]
                            * (NO_KEY: a value of no sample), unless it is the sample or the bits last set */
                Port *p = ports + op[1];
                if (op[3] != NO_KEY) {
                    int64_t key = t0 + op[3];
                    if (p->has_key && p->last_key == key) break;
                    p->last_key = key;
                    p->has_key = 1;
                }
                const double *values = (const double *)(uintptr_t)op[2];
                size_t bytes = (size_t)p->size * sizeof(double);
                if (p->last_valid && memcmp(values, p->last, bytes) == 0) break;
                memcpy(p->last, values, bytes);
                p->last_valid = 1;
                p->sets++;
                memcpy(p->slot, values, bytes);
                if (p->cast != CAST_NONE && from_float64(p) != 0) { result.reason = NOT_EXACT; return result; }
                Component *c = components + p->component;
                int status = p->function(c->instance, p->vrs, (size_t)p->n_vrs, p->native, (size_t)p->size);
                if (status > FMI_WARNING) { result.reason = CALL_FAILED; result.status = status; return result; }
                if (*c->logged_errors != c->errors_seen) { result.reason = ERROR_LOGGED; result.status = status; return result; }
                break;
            }
            case OP_STEP: { /* component op[1] from tick t0 + op[2] over its step (int / int: correctly rounded) */
                Component *c = components + op[1];
                double t = (double)(t0 + op[2]) / (double)base, h = (double)c->step / (double)base;
                memset(c->flags, 0, sizeof c->flags);
                c->last_time = t + h;
                int status = c->do_step(c->instance, t, h, true, c->flags, c->flags + 1, c->flags + 2, &c->last_time);
                if (status > FMI_WARNING && !(status == FMI_DISCARD && c->flags[1])) {
                    result.reason = CALL_FAILED; result.status = status; return result;
                }
                if (*c->logged_errors != c->errors_seen) { result.reason = ERROR_LOGGED; result.status = status; return result; }
                if (c->flags[0] || c->flags[1] || c->flags[2]) {
                    result.reason = STEP_FLAGS; result.status = status; return result;
                }
                break;
            }
            case OP_GET: { /* observed group op[1] into its float64 slots */
                Port *p = ports + op[1];
                Component *c = components + p->component;
                int status = p->function(c->instance, p->vrs, (size_t)p->n_vrs, p->native, (size_t)p->size);
                if (status > FMI_WARNING) { result.reason = CALL_FAILED; result.status = status; return result; }
                if (*c->logged_errors != c->errors_seen) { result.reason = ERROR_LOGGED; result.status = status; return result; }
                if (p->cast != CAST_NONE && to_float64(p) != 0) { result.reason = NOT_EXACT; return result; }
                break;
            }
            case OP_END: {
                Component *c = components + op[1];
                int64_t elapsed = now_ns() - c->started_ns;
                c->busy_ns += elapsed;
                if (c->cost_bins) {
                    c->cost_bins[cost_bin(elapsed)]++;
                    c->cost_count++;
                    if (elapsed > c->cost_max_ns) c->cost_max_ns = elapsed;
                    if (elapsed > c->budget_ns) c->cost_over++;
                }
                break;
            }
            case OP_COPY:
                memcpy((void *)(uintptr_t)op[1], (const void *)(uintptr_t)op[2], (size_t)op[3] * sizeof(double));
                break;
            case OP_WINDOW: { /* op[3] values at op[2] into window op[1]: the first copied, the others added
                               * elementwise (IEEE additions in time order, as numpy's add makes them) */
                Window *w = windows + op[1];
                const double *value = (const double *)(uintptr_t)op[2];
                if (!w->opened) {
                    memcpy(w->sum, value, (size_t)op[3] * sizeof(double));
                    w->opened = 1;
                } else {
                    for (int64_t i = 0; i < op[3]; i++) w->sum[i] += value[i];
                }
                break;
            }
            case OP_MEAN: { /* the mean of window op[1], its samples from before and op[3] of this program, into
                             * op[2] (each sum divided by their number, as numpy divides it) */
                const Window *w = windows + op[1];
                double *mean = (double *)(uintptr_t)op[2];
                double n = (double)(w->count + op[3]);
                for (int64_t i = 0; i < w->size; i++) mean[i] = w->sum[i] / n;
                break;
            }
            case OP_PACE: /* a paced step from tick t0 + op[1] starts no earlier than its time; the run's
                           * first starts the clock (what the program made before it is not it being late) */
                if (!pacing->started) {
                    pacing->origin = pacing_clock() - (double)(t0 + op[1]) / (double)base;
                    pacing->started = 1;
                } else if (pacing->pace) {
                    wait_until(pacing->origin + (double)(t0 + op[1]) / (double)base, pacing);
                }
                break;
            case OP_LATE: /* ... and ends by t0 + op[2]: how late it is, into its slot op[1] */
                pacing->lateness[op[1]] = (pacing_clock() - pacing->origin) - (double)(t0 + op[2]) / (double)base;
                break;
            case OP_NOP:
                break;
            default:
                result.reason = BAD_OP; return result;
        }
    }
    result.ops_done = n_ops;
    return result;
}
