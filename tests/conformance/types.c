/* Types: one variable of each kind the orchestrator must handle, with exactly known values.

   Every step adds 1 to `count`; the outputs are exact functions of it and of the inputs during
   the step (see modelDescription: types.xml):
     count (Int32)      = steps taken           small (Int8)  = count % 100
     big (Int64)        = big_offset + count    flag (Boolean) = count is odd
     speed (Float64, declared type Velocity, m/s) = 0.5 * count
     distance (Float64, declared type Position, m) = 0.25 * count
     x_echo = x, n_echo = n, mode_out = mode     (the inputs' values during the last step)
     label_length = strlen(label), blob_sum = sum of blob's bytes, blob_size = its size
     label_out = label, blob_out = blob      (String and Binary outputs)
   An Enumeration input outside the items of Mode (1, 2, 3) makes the step fail. */
#include "fmu_base.h"

#define INSTANTIATION_TOKEN "{conformance-types-1}"

typedef struct {
    int32_t count;
    int8_t small;
    int64_t big, big_offset;
    int64_t mode, mode_out;
    double speed, distance, x, x_echo, position;
    int32_t n, n_echo;
    bool flag;
    Text label;
    int32_t label_length;
    Blob blob;
    int32_t blob_sum, blob_size;
    Text label_out;
    Blob blob_out;
    double time;
} Model;

#include "fmu_common.h"

static void model_start_values(Model *m) {
    memset(m, 0, sizeof *m);
    m->mode = 1;
    m->mode_out = 1;
    strcpy(m->label.text, "hello");
    const uint8_t blob[] = {0x0a, 0x0b, 0x0c, 0xff};
    memcpy(m->blob.bytes, blob, sizeof blob);
    m->blob.size = sizeof blob;
}

static void model_variables(Instance *inst) {
    SCALAR(inst, 0, "time", V_FLOAT64, C_OUTPUT, time);
    SCALAR(inst, 1, "count", V_INT32, C_OUTPUT, count);
    SCALAR(inst, 2, "small", V_INT8, C_OUTPUT, small);
    SCALAR(inst, 3, "big", V_INT64, C_OUTPUT, big);
    SCALAR(inst, 4, "big_offset", V_INT64, C_PARAMETER, big_offset);
    SCALAR(inst, 5, "mode", V_ENUMERATION, C_INPUT, mode);
    SCALAR(inst, 6, "mode_out", V_ENUMERATION, C_OUTPUT, mode_out);
    SCALAR(inst, 7, "speed", V_FLOAT64, C_OUTPUT, speed);
    SCALAR(inst, 8, "x", V_FLOAT64, C_INPUT, x);
    SCALAR(inst, 9, "x_echo", V_FLOAT64, C_OUTPUT, x_echo);
    SCALAR(inst, 10, "position", V_FLOAT64, C_INPUT, position);
    SCALAR(inst, 11, "n", V_INT32, C_INPUT, n);
    SCALAR(inst, 12, "n_echo", V_INT32, C_OUTPUT, n_echo);
    SCALAR(inst, 13, "flag", V_BOOLEAN, C_OUTPUT, flag);
    SCALAR(inst, 14, "label", V_STRING, C_PARAMETER, label);
    SCALAR(inst, 15, "label_length", V_INT32, C_OUTPUT, label_length);
    SCALAR(inst, 16, "blob", V_BINARY, C_PARAMETER, blob);
    SCALAR(inst, 17, "blob_sum", V_INT32, C_OUTPUT, blob_sum);
    SCALAR(inst, 18, "blob_size", V_INT32, C_OUTPUT, blob_size);
    SCALAR(inst, 19, "distance", V_FLOAT64, C_OUTPUT, distance);
    SCALAR(inst, 20, "label_out", V_STRING, C_OUTPUT, label_out);
    SCALAR(inst, 21, "blob_out", V_BINARY, C_OUTPUT, blob_out);
}

static void outputs(Model *m) {
    m->small = (int8_t)(m->count % 100);
    m->big = m->big_offset + m->count;
    m->flag = (m->count % 2) != 0;
    m->speed = 0.5 * m->count;
    m->distance = 0.25 * m->count;
    m->label_length = (int32_t)strlen(m->label.text);
    m->blob_size = (int32_t)m->blob.size;
    m->blob_sum = 0;
    for (size_t i = 0; i < m->blob.size; i++) m->blob_sum += m->blob.bytes[i];
    m->label_out = m->label;
    m->blob_out = m->blob;
}

static fmi3Status model_exit_initialization(Instance *inst) {
    outputs(&inst->model);
    inst->model.mode_out = inst->model.mode;
    return fmi3OK;
}

static fmi3Status model_step(Instance *inst, double t, double h, bool *terminate, bool *early, double *last) {
    (void)terminate; (void)early; (void)last;
    Model *m = &inst->model;
    if (m->mode < 1 || m->mode > 3)
        return fail(inst, "mode = %lld is not an item of Mode (Off = 1, Slow = 2, Fast = 3)", (long long)m->mode);
    m->count += 1;
    m->x_echo = m->x;
    m->n_echo = m->n;
    m->mode_out = m->mode;
    m->time = t + h;
    outputs(m);
    return fmi3OK;
}
