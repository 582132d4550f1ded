/* A small FMI 3.0 Co-Simulation runtime for the conformance test FMUs (tests/test_conformance.py).

   A model file includes fmu_base.h, defines `Model` (its variables as C values), then includes
   this file, then defines the hooks declared below. The runtime implements the mode state machine the tests
   rely on (Instantiated, Configuration, Initialization, Step, Terminated, Error), typed get/set
   over the model's variable table for every FMI 3.0 type (Binary and String included;
   Enumerations through the Int64 functions) and fmi3DoStep. It refuses what FMI 3.0 forbids and
   says why through the log callback:
     - a structural parameter set outside Configuration Mode,
     - a parameter set after initialization, an output or calculated parameter set at all,
     - a wrong number of values, an unknown value reference, a value of the wrong type,
     - any call but fmi3FreeInstance/fmi3Reset in the Error mode, a call in the wrong mode.
   Nothing here is specific to a model. */
#ifndef FMU_COMMON_H
#define FMU_COMMON_H

#include "fmu_base.h"

typedef struct {
    fmi3ValueReference vr;
    const char *name;
    VarType type;
    Causality causality;
    void *data;              /* the C value(s): double, int32_t, ..., int64_t (Enumeration), Text, Blob */
    const uint64_t *length;  /* NULL: a scalar; else the structural parameter holding the array length */
    size_t capacity;         /* elements the data can hold */
} Var;

typedef struct Instance {
    Mode mode;
    char name[128];
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment environment;
    Var vars[MAX_VARIABLES];
    size_t n_vars;
    bool structural_set;      /* a structural parameter was set in the current Configuration Mode */
    int32_t configurations;   /* Configuration Modes left with a structural parameter set in them */
    Model model;
} Instance;

/* -- hooks every model defines ---------------------------------------------------------------- */
static void model_start_values(Model *m);
static void model_variables(Instance *inst);                       /* fills inst->vars with add_var */
static fmi3Status model_exit_initialization(Instance *inst);
static fmi3Status model_step(Instance *inst, double t, double h, bool *terminate, bool *early_return,
                             double *last_successful_time);

/* -- helpers ---------------------------------------------------------------------------------- */
static void log_message(Instance *inst, fmi3Status status, const char *format, ...) {
    if (inst == NULL || inst->logger == NULL) return;
    char buffer[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(buffer, sizeof buffer, format, args);
    va_end(args);
    inst->logger(inst->environment, status, status >= fmi3Error ? "logStatusError" : "logEvents", buffer);
}

static void add_var(Instance *inst, fmi3ValueReference vr, const char *name, VarType type, Causality causality,
                    void *data, const uint64_t *length, size_t capacity) {
    Var *v = &inst->vars[inst->n_vars++];
    v->vr = vr; v->name = name; v->type = type; v->causality = causality; v->data = data;
    v->length = length; v->capacity = capacity ? capacity : 1;
}
#define SCALAR(inst, vr, name, type, causality, field) add_var(inst, vr, name, type, causality, &(inst)->model.field, NULL, 1)

static size_t element_size(VarType type) {
    switch (type) {
        case V_FLOAT32: return sizeof(float);
        case V_FLOAT64: return sizeof(double);
        case V_INT8: case V_UINT8: return 1;
        case V_INT16: case V_UINT16: return 2;
        case V_INT32: case V_UINT32: return 4;
        case V_INT64: case V_UINT64: case V_ENUMERATION: return 8;
        case V_BOOLEAN: return sizeof(bool);
        case V_STRING: return sizeof(Text);
        case V_BINARY: return sizeof(Blob);
    }
    return 0;
}

static size_t var_length(const Var *v) { return v->length ? (size_t)*v->length : 1; }

static Var *find_var(Instance *inst, fmi3ValueReference vr) {
    for (size_t i = 0; i < inst->n_vars; i++)
        if (inst->vars[i].vr == vr) return &inst->vars[i];
    return NULL;
}

static bool type_matches(VarType var_type, VarType function_type) {
    return var_type == function_type || (var_type == V_ENUMERATION && function_type == V_INT64);
}

static fmi3Status fail(Instance *inst, const char *format, ...) {
    char buffer[1024];
    va_list args;
    va_start(args, format);
    vsnprintf(buffer, sizeof buffer, format, args);
    va_end(args);
    log_message(inst, fmi3Error, "%s", buffer);
    return fmi3Error;
}

static fmi3Status enter_error(Instance *inst, fmi3Status status) {
    if (status >= fmi3Error) inst->mode = MODE_ERROR;
    return status;
}

static fmi3Status check_mode(Instance *inst, const char *function, unsigned allowed) {
    if (inst == NULL) return fmi3Error;
    if (inst->mode == MODE_ERROR)
        return fail(inst, "%s: the instance is in the Error mode", function);
    if (!(allowed & (1u << inst->mode)))
        return fail(inst, "%s: illegal call sequence (in %s Mode)", function, MODE_NAMES[inst->mode]);
    return fmi3OK;
}
#define IN(mode) (1u << (mode))
#define ANY_BUT_ERROR (IN(MODE_INSTANTIATED) | IN(MODE_CONFIGURATION) | IN(MODE_INITIALIZATION) | IN(MODE_STEP) | IN(MODE_TERMINATED))

/* -- get/set ---------------------------------------------------------------------------------- */
static fmi3Status get_values(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr, VarType type,
                             void *values, size_t n_values, size_t *sizes) {
    Instance *inst = (Instance *)instance;
    if (inst == NULL) return fmi3Error;  /* values stay readable in every mode, the Error mode included */
    size_t k = 0, size = element_size(type);
    for (size_t i = 0; i < nvr; i++) {
        Var *v = find_var(inst, vrs[i]);
        if (v == NULL) return fail(inst, "fmi3Get%s: no variable has value reference %u", TYPE_NAMES[type], vrs[i]);
        if (!type_matches(v->type, type))
            return fail(inst, "fmi3Get%s: %s is a %s variable", TYPE_NAMES[type], v->name, TYPE_NAMES[v->type]);
        size_t n = var_length(v);
        if (k + n > n_values)
            return fail(inst, "fmi3Get%s: nValues = %zu is too few for %s", TYPE_NAMES[type], n_values, v->name);
        for (size_t j = 0; j < n; j++, k++) {
            if (type == V_STRING) ((fmi3String *)values)[k] = ((Text *)v->data)[j].text;
            else if (type == V_BINARY) {
                ((fmi3Binary *)values)[k] = ((Blob *)v->data)[j].bytes;
                sizes[k] = ((Blob *)v->data)[j].size;
            } else memcpy((char *)values + k * size, (char *)v->data + j * size, size);
        }
    }
    if (k != n_values)
        return fail(inst, "fmi3Get%s: nValues = %zu, but the variables hold %zu values", TYPE_NAMES[type], n_values, k);
    return fmi3OK;
}

static fmi3Status set_values(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr, VarType type,
                             const void *values, size_t n_values, const size_t *sizes) {
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "set", IN(MODE_INSTANTIATED) | IN(MODE_CONFIGURATION) |
                                               IN(MODE_INITIALIZATION) | IN(MODE_STEP));
    if (status != fmi3OK) return status;
    size_t total = 0, size = element_size(type);
    for (size_t i = 0; i < nvr; i++) {  /* check everything first: a refused call changes nothing */
        Var *v = find_var(inst, vrs[i]);
        if (v == NULL) return fail(inst, "fmi3Set%s: no variable has value reference %u", TYPE_NAMES[type], vrs[i]);
        if (!type_matches(v->type, type))
            return fail(inst, "fmi3Set%s: %s is a %s variable", TYPE_NAMES[type], v->name, TYPE_NAMES[v->type]);
        if (v->causality == C_OUTPUT || v->causality == C_CALCULATED)
            return fail(inst, "fmi3Set%s: %s is an output; it cannot be set", TYPE_NAMES[type], v->name);
        if (v->causality == C_STRUCTURAL && inst->mode != MODE_CONFIGURATION)
            return fail(inst, "fmi3Set%s: structural parameter %s set outside Configuration Mode (in %s Mode)",
                        TYPE_NAMES[type], v->name, MODE_NAMES[inst->mode]);
        if (v->causality != C_STRUCTURAL && inst->mode == MODE_CONFIGURATION)
            return fail(inst, "fmi3Set%s: only structural parameters can be set in Configuration Mode, not %s",
                        TYPE_NAMES[type], v->name);
        if (v->causality == C_PARAMETER && inst->mode == MODE_STEP)
            return fail(inst, "fmi3Set%s: parameter %s is fixed after initialization", TYPE_NAMES[type], v->name);
        total += var_length(v);
    }
    if (total != n_values)
        return fail(inst, "fmi3Set%s: nValues = %zu, but the variables hold %zu values", TYPE_NAMES[type], n_values,
                    total);
    size_t k = 0;
    for (size_t i = 0; i < nvr; i++) {
        Var *v = find_var(inst, vrs[i]);
        size_t n = var_length(v);
        for (size_t j = 0; j < n; j++, k++) {
            if (type == V_STRING) {
                const char *text = ((const fmi3String *)values)[k];
                if (text == NULL || strlen(text) >= MAX_TEXT)
                    return fail(inst, "fmi3SetString: %s takes a text shorter than %d bytes", v->name, MAX_TEXT);
                strcpy(((Text *)v->data)[j].text, text);
            } else if (type == V_BINARY) {
                if (sizes[k] > MAX_TEXT)
                    return fail(inst, "fmi3SetBinary: %s takes at most %d bytes", v->name, MAX_TEXT);
                Blob *blob = &((Blob *)v->data)[j];
                if (sizes[k]) memcpy(blob->bytes, ((const fmi3Binary *)values)[k], sizes[k]);
                blob->size = sizes[k];
            } else if (type == V_UINT64 && v->causality == C_STRUCTURAL) {
                inst->structural_set = true;
                uint64_t value;
                memcpy(&value, (const char *)values + k * size, size);
                /* a structural parameter sizes arrays: it must fit every array it sizes */
                for (size_t a = 0; a < inst->n_vars; a++)
                    if (inst->vars[a].length == (const uint64_t *)v->data && value > inst->vars[a].capacity)
                        return fail(inst, "fmi3SetUInt64: %s = %llu exceeds the %zu values %s can hold", v->name,
                                    (unsigned long long)value, inst->vars[a].capacity, inst->vars[a].name);
                memcpy((char *)v->data + j * size, &value, size);
            } else memcpy((char *)v->data + j * size, (const char *)values + k * size, size);
        }
    }
    return fmi3OK;
}

#define NUMERIC_GET_SET(Name, CType, VT)                                                                           \
    FMI3_Export fmi3Status fmi3Get##Name(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr,       \
                                         CType values[], size_t nValues) {                                         \
        return get_values(instance, vrs, nvr, VT, values, nValues, NULL);                                          \
    }                                                                                                              \
    FMI3_Export fmi3Status fmi3Set##Name(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr,       \
                                         const CType values[], size_t nValues) {                                   \
        return set_values(instance, vrs, nvr, VT, values, nValues, NULL);                                          \
    }

NUMERIC_GET_SET(Float32, fmi3Float32, V_FLOAT32)
NUMERIC_GET_SET(Float64, fmi3Float64, V_FLOAT64)
NUMERIC_GET_SET(Int8, fmi3Int8, V_INT8)
NUMERIC_GET_SET(UInt8, fmi3UInt8, V_UINT8)
NUMERIC_GET_SET(Int16, fmi3Int16, V_INT16)
NUMERIC_GET_SET(UInt16, fmi3UInt16, V_UINT16)
NUMERIC_GET_SET(Int32, fmi3Int32, V_INT32)
NUMERIC_GET_SET(UInt32, fmi3UInt32, V_UINT32)
NUMERIC_GET_SET(Int64, fmi3Int64, V_INT64)
NUMERIC_GET_SET(UInt64, fmi3UInt64, V_UINT64)
NUMERIC_GET_SET(Boolean, fmi3Boolean, V_BOOLEAN)

FMI3_Export fmi3Status fmi3GetString(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr,
                                     fmi3String values[], size_t nValues) {
    return get_values(instance, vrs, nvr, V_STRING, values, nValues, NULL);
}
FMI3_Export fmi3Status fmi3SetString(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr,
                                     const fmi3String values[], size_t nValues) {
    return set_values(instance, vrs, nvr, V_STRING, values, nValues, NULL);
}
FMI3_Export fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr,
                                     size_t valueSizes[], fmi3Binary values[], size_t nValues) {
    return get_values(instance, vrs, nvr, V_BINARY, values, nValues, valueSizes);
}
FMI3_Export fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference vrs[], size_t nvr,
                                     const size_t valueSizes[], const fmi3Binary values[], size_t nValues) {
    return set_values(instance, vrs, nvr, V_BINARY, values, nValues, valueSizes);
}

/* -- lifecycle -------------------------------------------------------------------------------- */
FMI3_Export const char *fmi3GetVersion(void) { return fmi3Version; }

FMI3_Export fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                                           const fmi3String categories[]) {
    (void)loggingOn; (void)nCategories; (void)categories;
    return check_mode((Instance *)instance, "fmi3SetDebugLogging", ANY_BUT_ERROR);
}

FMI3_Export fmi3Instance fmi3InstantiateCoSimulation(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath, fmi3Boolean visible,
    fmi3Boolean loggingOn, fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
    const fmi3ValueReference requiredIntermediateVariables[], size_t nRequiredIntermediateVariables,
    fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logMessage,
    fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)resourcePath; (void)visible; (void)loggingOn; (void)earlyReturnAllowed;
    (void)requiredIntermediateVariables; (void)nRequiredIntermediateVariables; (void)intermediateUpdate;
    Instance probe = {0};
    probe.logger = logMessage;
    probe.environment = instanceEnvironment;
    if (instantiationToken == NULL || strcmp(instantiationToken, INSTANTIATION_TOKEN) != 0) {
        log_message(&probe, fmi3Error, "wrong instantiation token %s (expected %s)",
                    instantiationToken ? instantiationToken : "(null)", INSTANTIATION_TOKEN);
        return NULL;
    }
    if (eventModeUsed) {
        log_message(&probe, fmi3Error, "event mode is not supported");
        return NULL;
    }
    Instance *inst = (Instance *)calloc(1, sizeof(Instance));
    if (inst == NULL) return NULL;
    inst->logger = logMessage;
    inst->environment = instanceEnvironment;
    snprintf(inst->name, sizeof inst->name, "%s", instanceName ? instanceName : "instance");
    inst->mode = MODE_INSTANTIATED;
    model_start_values(&inst->model);
    model_variables(inst);
    return inst;
}

FMI3_Export void fmi3FreeInstance(fmi3Instance instance) { free(instance); }

FMI3_Export fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) {
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "fmi3EnterConfigurationMode", IN(MODE_INSTANTIATED));
    if (status == fmi3OK) {
        inst->mode = MODE_CONFIGURATION;
        inst->structural_set = false;
    }
    return status;
}

FMI3_Export fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) {
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "fmi3ExitConfigurationMode", IN(MODE_CONFIGURATION));
    if (status == fmi3OK) {
        inst->mode = MODE_INSTANTIATED;
        if (inst->structural_set) inst->configurations += 1;
    }
    return status;
}

FMI3_Export fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
                                                   fmi3Float64 tolerance, fmi3Float64 startTime,
                                                   fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime; (void)startTime;
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "fmi3EnterInitializationMode", IN(MODE_INSTANTIATED));
    if (status == fmi3OK) inst->mode = MODE_INITIALIZATION;
    return status;
}

FMI3_Export fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "fmi3ExitInitializationMode", IN(MODE_INITIALIZATION));
    if (status != fmi3OK) return status;
    status = model_exit_initialization(inst);
    if (status <= fmi3Warning) inst->mode = MODE_STEP;
    return enter_error(inst, status);
}

FMI3_Export fmi3Status fmi3EnterStepMode(fmi3Instance instance) {
    return check_mode((Instance *)instance, "fmi3EnterStepMode", IN(MODE_STEP));
}

FMI3_Export fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                                  fmi3Float64 communicationStepSize, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                  fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation,
                                  fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    (void)noSetFMUStatePriorToCurrentPoint;
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "fmi3DoStep", IN(MODE_STEP));
    if (status != fmi3OK) return status;
    if (!(communicationStepSize > 0))
        return enter_error(inst, fail(inst, "fmi3DoStep: communicationStepSize %g is not positive", communicationStepSize));
    bool terminate = false, early = false;
    double last = currentCommunicationPoint + communicationStepSize;
    status = model_step(inst, currentCommunicationPoint, communicationStepSize, &terminate, &early, &last);
    *eventHandlingNeeded = fmi3False;
    *terminateSimulation = terminate;
    *earlyReturn = early;
    *lastSuccessfulTime = last;
    return enter_error(inst, status);
}

FMI3_Export fmi3Status fmi3Terminate(fmi3Instance instance) {
    Instance *inst = (Instance *)instance;
    fmi3Status status = check_mode(inst, "fmi3Terminate", IN(MODE_STEP));
    if (status == fmi3OK) inst->mode = MODE_TERMINATED;
    return status;
}

FMI3_Export fmi3Status fmi3Reset(fmi3Instance instance) {
    Instance *inst = (Instance *)instance;
    if (inst == NULL) return fmi3Error;
    inst->mode = MODE_INSTANTIATED;
    inst->configurations = 0;
    model_start_values(&inst->model);
    return fmi3OK;
}

/* -- the rest of the API: Model Exchange, Scheduled Execution, clocks, FMU state, derivatives ---- */
/* Exported like every FMI 3.0 function (importers such as FMPy load them all); each refuses. */
static fmi3Status unsupported(fmi3Instance instance, const char *function) {
    if (instance != NULL) log_message((Instance *)instance, fmi3Error, "%s is not supported by this FMU", function);
    return fmi3Error;
}

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-parameter"
FMI3_Export fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logMessage) {
    return NULL;
}
FMI3_Export fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate, fmi3LockPreemptionCallback lockPreemption, fmi3UnlockPreemptionCallback unlockPreemption) {
    return NULL;
}
FMI3_Export fmi3Status fmi3EnterEventMode(fmi3Instance instance) {
    return unsupported(instance, "fmi3EnterEventMode");
}
FMI3_Export fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Clock values[]) {
    return unsupported(instance, "fmi3GetClock");
}
FMI3_Export fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Clock values[]) {
    return unsupported(instance, "fmi3SetClock");
}
FMI3_Export fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference, size_t* nDependencies) {
    return unsupported(instance, "fmi3GetNumberOfVariableDependencies");
}
FMI3_Export fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent, size_t elementIndicesOfDependent[], fmi3ValueReference independents[], size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[], size_t nDependencies) {
    return unsupported(instance, "fmi3GetVariableDependencies");
}
FMI3_Export fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState* FMUState) {
    return unsupported(instance, "fmi3GetFMUState");
}
FMI3_Export fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    return unsupported(instance, "fmi3SetFMUState");
}
FMI3_Export fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState* FMUState) {
    return unsupported(instance, "fmi3FreeFMUState");
}
FMI3_Export fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t* size) {
    return unsupported(instance, "fmi3SerializedFMUStateSize");
}
FMI3_Export fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[], size_t size) {
    return unsupported(instance, "fmi3SerializeFMUState");
}
FMI3_Export fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size, fmi3FMUState* FMUState) {
    return unsupported(instance, "fmi3DeserializeFMUState");
}
FMI3_Export fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    return unsupported(instance, "fmi3GetDirectionalDerivative");
}
FMI3_Export fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns, const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    return unsupported(instance, "fmi3GetAdjointDerivative");
}
FMI3_Export fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[]) {
    return unsupported(instance, "fmi3GetIntervalDecimal");
}
FMI3_Export fmi3Status fmi3GetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[]) {
    return unsupported(instance, "fmi3GetIntervalFraction");
}
FMI3_Export fmi3Status fmi3GetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3Float64 shifts[]) {
    return unsupported(instance, "fmi3GetShiftDecimal");
}
FMI3_Export fmi3Status fmi3GetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, fmi3UInt64 counters[], fmi3UInt64 resolutions[]) {
    return unsupported(instance, "fmi3GetShiftFraction");
}
FMI3_Export fmi3Status fmi3SetIntervalDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 intervals[]) {
    return unsupported(instance, "fmi3SetIntervalDecimal");
}
FMI3_Export fmi3Status fmi3SetIntervalFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    return unsupported(instance, "fmi3SetIntervalFraction");
}
FMI3_Export fmi3Status fmi3SetShiftDecimal(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Float64 shifts[]) {
    return unsupported(instance, "fmi3SetShiftDecimal");
}
FMI3_Export fmi3Status fmi3SetShiftFraction(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3UInt64 counters[], const fmi3UInt64 resolutions[]) {
    return unsupported(instance, "fmi3SetShiftFraction");
}
FMI3_Export fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) {
    return unsupported(instance, "fmi3EvaluateDiscreteStates");
}
FMI3_Export fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean* discreteStatesNeedUpdate, fmi3Boolean* terminateSimulation, fmi3Boolean* nominalsOfContinuousStatesChanged, fmi3Boolean* valuesOfContinuousStatesChanged, fmi3Boolean* nextEventTimeDefined, fmi3Float64* nextEventTime) {
    return unsupported(instance, "fmi3UpdateDiscreteStates");
}
FMI3_Export fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) {
    return unsupported(instance, "fmi3EnterContinuousTimeMode");
}
FMI3_Export fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean* enterEventMode, fmi3Boolean* terminateSimulation) {
    return unsupported(instance, "fmi3CompletedIntegratorStep");
}
FMI3_Export fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time) {
    return unsupported(instance, "fmi3SetTime");
}
FMI3_Export fmi3Status fmi3SetContinuousStates(fmi3Instance instance, const fmi3Float64 continuousStates[], size_t nContinuousStates) {
    return unsupported(instance, "fmi3SetContinuousStates");
}
FMI3_Export fmi3Status fmi3GetContinuousStateDerivatives(fmi3Instance instance, fmi3Float64 derivatives[], size_t nContinuousStates) {
    return unsupported(instance, "fmi3GetContinuousStateDerivatives");
}
FMI3_Export fmi3Status fmi3GetEventIndicators(fmi3Instance instance, fmi3Float64 eventIndicators[], size_t nEventIndicators) {
    return unsupported(instance, "fmi3GetEventIndicators");
}
FMI3_Export fmi3Status fmi3GetContinuousStates(fmi3Instance instance, fmi3Float64 continuousStates[], size_t nContinuousStates) {
    return unsupported(instance, "fmi3GetContinuousStates");
}
FMI3_Export fmi3Status fmi3GetNominalsOfContinuousStates(fmi3Instance instance, fmi3Float64 nominals[], size_t nContinuousStates) {
    return unsupported(instance, "fmi3GetNominalsOfContinuousStates");
}
FMI3_Export fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t* nEventIndicators) {
    return unsupported(instance, "fmi3GetNumberOfEventIndicators");
}
FMI3_Export fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t* nContinuousStates) {
    return unsupported(instance, "fmi3GetNumberOfContinuousStates");
}
FMI3_Export fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues) {
    return unsupported(instance, "fmi3GetOutputDerivatives");
}
FMI3_Export fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference, fmi3Float64 activationTime) {
    return unsupported(instance, "fmi3ActivateModelPartition");
}
#pragma GCC diagnostic pop

#endif
