/* The project's FMI 3.0 Co-Simulation layer: every FMI 3.0 function, one state machine, one
 * variable table. The model is Python code carried in the FMU's resources (fmi3_runtime.py and
 * the model's package); it is entered only by the calls that change the model (initialization,
 * fmi3DoStep, configuration, FMU state, reset, free). Values live in buffers that the Python
 * model sees as numpy arrays, so fmi3Get and fmi3Set copy memory and never enter Python.
 *
 * Conventions (in the style of modelica/Reference-FMUs):
 * - ALLOWED below is the one table of which call is legal in which mode; an illegal call returns
 *   fmi3Error with "illegal call sequence" and the mode it was made in, and changes nothing.
 * - A call rejected for its arguments (unknown value reference, wrong number of values, a value
 *   that may not be set now, NaN, a Float64 outside the variable's limit from the FMU's limit
 *   table) returns fmi3Error, logs why and changes nothing, so the instance stays usable. A
 *   failure of the model itself (initialization, a step) puts the
 *   instance into the Error mode: only getters, FMU state, fmi3Reset and fmi3FreeInstance remain.
 * - Python is entered with the GIL taken for the call, in a Python importer and in any other.
 * - A KeyboardInterrupt in the FMU's Python code (SIGINT while it runs) fails that call as
 *   "interrupted" (the instance goes into the Error mode) and is handed back with
 *   PyErr_SetInterrupt once the FMU's Python work of the call is done, so a Python importer still
 *   stops at its next bytecode (a non-Python importer keeps its own SIGINT handling).
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <limits.h>
#include <malloc.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"
#include "python_embed.h"
#include "remote.h"
#include "runtime_unpack.h"
#include "variables.h"

/* ---- modes and the table of legal calls ----------------------------------------------------- */
typedef enum {
    M_INSTANTIATED = 1 << 0,
    M_CONFIGURATION = 1 << 1,
    M_INITIALIZATION = 1 << 2,
    M_STEP = 1 << 3,
    M_RECONFIGURATION = 1 << 4,
    M_TERMINATED = 1 << 5,
    M_ERROR = 1 << 6,
    M_FATAL = 1 << 7,
} Mode;

#define M_NONE 0
#define M_ALIVE (M_INSTANTIATED | M_CONFIGURATION | M_INITIALIZATION | M_STEP | M_RECONFIGURATION | M_TERMINATED | M_ERROR)
#define M_HAS_VALUES (M_CONFIGURATION | M_INITIALIZATION | M_STEP | M_RECONFIGURATION | M_TERMINATED | M_ERROR)

enum {
    ALLOWED_SetDebugLogging = M_ALIVE,
    ALLOWED_EnterInitializationMode = M_INSTANTIATED,
    ALLOWED_ExitInitializationMode = M_INITIALIZATION,
    ALLOWED_Terminate = M_STEP,
    ALLOWED_Reset = M_ALIVE,
    ALLOWED_Get = M_HAS_VALUES,
    ALLOWED_Set = M_INSTANTIATED | M_CONFIGURATION | M_INITIALIZATION | M_STEP | M_RECONFIGURATION,
    ALLOWED_FMUState = M_INSTANTIATED | M_INITIALIZATION | M_STEP | M_TERMINATED | M_ERROR,
    ALLOWED_EnterConfigurationMode = M_INSTANTIATED,
    ALLOWED_ExitConfigurationMode = M_CONFIGURATION | M_RECONFIGURATION,
    ALLOWED_DoStep = M_STEP,
};

static const char *mode_name(int mode) {
    switch (mode) {
        case M_INSTANTIATED: return "Instantiated";
        case M_CONFIGURATION: return "Configuration Mode";
        case M_INITIALIZATION: return "Initialization Mode";
        case M_STEP: return "Step Mode";
        case M_RECONFIGURATION: return "Reconfiguration Mode";
        case M_TERMINATED: return "Terminated";
        case M_ERROR: return "Error";
        case M_FATAL: return "Fatal";
        default: return "an unknown mode";
    }
}

/* ---- the variable table ------------------------------------------------------------------------ */

static const char *type_name(int type) {
    static const char *names[] = {"?", "Float64", "Float32", "Int8", "UInt8", "Int16", "UInt16", "Int32",
                                  "UInt32", "Int64", "UInt64", "Boolean", "String", "Binary"};
    return (type >= T_FLOAT64 && type <= T_BINARY) ? names[type] : "?";
}

static const char *causality_name(int causality) {
    static const char *names[] = {"?", "parameter", "calculatedParameter", "structuralParameter", "input",
                                  "output", "local", "independent"};
    return (causality >= C_PARAMETER && causality <= C_INDEPENDENT) ? names[causality] : "?";
}

typedef struct {
    int declared;
    int type, causality, variability;
    void *data;      /* numeric: the model's numpy buffer; String: char*[count] owned here */
    size_t count;    /* number of scalar values (product of the dimensions) */
    char *name;
    double min, max; /* Float64: the plausible range fmi3SetFloat64 enforces (any finite number by default) */
    char *limit_text; /* "[min, max] unit: why", from the FMU's limit table; "" without a limit */
    char *size_text;  /* what sizes an array and the coupling rule its size follows; "" for a scalar */
} Variable;

typedef struct {
    uint32_t kind;        /* INSTANCE_LOCAL (remote.h: a remote instance starts with INSTANCE_REMOTE) */
    char *instance_name;
    fmi3InstanceEnvironment environment;
    fmi3LogMessageCallback logger;
    int logging_on;
    unsigned log_categories; /* bit per LOG_* category; all when none was chosen */
    int mode;
    Variable *variables;
    size_t n_variables;
    uint64_t *set_counts; /* per value reference: successful sets (the model's numpy array) */
    size_t n_set_counts;
    PyObject *model;      /* the runtime's instance object */
    PyObject *do_step;    /* its bound do_step, called with no arguments (prebound at instantiation) */
    double *step_io;      /* the runtime's step exchange: t, h, substeps in; status, steps completed out */
    double start_time, step_size;
    uint64_t steps_done;  /* whole internal steps since start_time: time without rounding drift */
    int built;            /* the model exists for the current parameter values */
    int interrupted;      /* a KeyboardInterrupt ended a Python call of the current FMI call */
    void **states;        /* the live FMU states this instance handed out (see "FMU state") */
    size_t n_states, capacity_states;
    uintptr_t next_handle; /* the handle the next state gets (never one handed out before) */
    char last_error[4096];
} Instance;

enum { LOG_ERROR = 1, LOG_WARNING = 2, LOG_EVENTS = 4 };
static const char *const LOG_CATEGORY_NAMES[] = {"logStatusError", "logStatusWarning", "logEvents"};

static double instance_time(const Instance *inst) {
    return inst->start_time + (double)inst->steps_done * inst->step_size;
}

/* ---- logging ----------------------------------------------------------------------------------- */
static void log_message(Instance *inst, fmi3Status status, const char *format, ...) {
    char message[4096];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    unsigned category = status >= fmi3Error ? LOG_ERROR : status == fmi3Warning ? LOG_WARNING : LOG_EVENTS;
    /* the reason an instance went into the Error mode is kept: calls refused there do not replace it */
    if (status >= fmi3Error && inst->mode != M_ERROR)
        snprintf(inst->last_error, sizeof inst->last_error, "%s", message);
    if (!inst->logger || !inst->logging_on || !(inst->log_categories & category)) return;
    const char *name = category == LOG_ERROR ? LOG_CATEGORY_NAMES[0]
                     : category == LOG_WARNING ? LOG_CATEGORY_NAMES[1] : LOG_CATEGORY_NAMES[2];
    inst->logger(inst->environment, status, name, message);
}

static int allowed(Instance *inst, int modes, const char *function) {
    if (inst->mode & modes) return 1;
    if (inst->mode == M_ERROR) {
        log_message(inst, fmi3Error, "%s: illegal call sequence: the instance is in the Error mode after: %s "
                    "(call fmi3Reset, or fmi3SetFMUState to restore a saved state)", function, inst->last_error);
    } else {
        log_message(inst, fmi3Error, "%s: illegal call sequence: not allowed in %s", function,
                    mode_name(inst->mode));
    }
    return 0;
}

static fmi3Status not_supported(fmi3Instance instance, const char *function, const char *why) {
    if (remote_is(instance)) return remote_not_supported(instance, function, why);
    Instance *inst = (Instance *)instance;
    if (inst) log_message(inst, fmi3Error, "%s: not supported by this FMU (%s)", function, why);
    return fmi3Error;
}

/* ---- callbacks the Python runtime calls (through ctypes, GIL released) ---------------------------- */
static int cb_register(void *instance, uint32_t vr, int type, int causality, int variability, void *data,
                       uint64_t count, const char *name, double min, double max, const char *limit_text,
                       const char *size_text) {
    Instance *inst = (Instance *)instance;
    if (vr >= inst->n_variables) {
        size_t n = (size_t)vr + 1;
        Variable *grown = realloc(inst->variables, n * sizeof(Variable));
        if (!grown) return -1;
        memset(grown + inst->n_variables, 0, (n - inst->n_variables) * sizeof(Variable));
        inst->variables = grown;
        inst->n_variables = n;
    }
    Variable *v = &inst->variables[vr];
    if (type == T_STRING) {
        char **old = (char **)v->data;
        size_t old_count = v->declared ? v->count : 0;
        char **strings = calloc(count ? count : 1, sizeof(char *));
        if (!strings) return -1;
        for (size_t i = 0; i < count; i++) {
            strings[i] = strdup(i < old_count && old && old[i] ? old[i] : "");
            if (!strings[i]) return -1;
        }
        for (size_t i = 0; i < old_count; i++) free(old ? old[i] : NULL);
        free(old);
        data = strings;
    }
    if (!v->declared || !v->name || strcmp(v->name, name) != 0) {
        free(v->name);
        v->name = strdup(name);
    }
    if (!v->limit_text || strcmp(v->limit_text, limit_text ? limit_text : "") != 0) {
        free(v->limit_text);
        v->limit_text = strdup(limit_text ? limit_text : "");
    }
    if (!v->size_text || strcmp(v->size_text, size_text ? size_text : "") != 0) {
        free(v->size_text);
        v->size_text = strdup(size_text ? size_text : "");
    }
    if (!v->name || !v->limit_text || !v->size_text) return -1;
    v->min = min;
    v->max = max;
    v->declared = 1;
    v->type = type;
    v->causality = causality;
    v->variability = variability;
    v->data = data;
    v->count = (size_t)count;
    return 0;
}

static int cb_counters(void *instance, void *data, uint64_t count) {
    Instance *inst = (Instance *)instance;
    inst->set_counts = (uint64_t *)data;
    inst->n_set_counts = (size_t)count;
    return 0;
}

/* The step exchange (a numpy array of STEP_IO_SIZE doubles owned by the runtime): fmi3DoStep writes
 * the arguments, status OK and all steps completed; the runtime's do_step writes a warning, or an
 * error and the internal steps it completed. A Python exception out of do_step is an error too. The
 * runtime also writes, once, the most internal steps one call may run (IO_MAX_SUBSTEPS). */
enum { IO_TIME, IO_STEP, IO_SUBSTEPS, IO_STATUS, IO_COMPLETED, IO_MAX_SUBSTEPS, STEP_IO_SIZE };

static int cb_step_io(void *instance, void *data, uint64_t count) {
    Instance *inst = (Instance *)instance;
    if (count < STEP_IO_SIZE) return -1;
    inst->step_io = (double *)data;
    return 0;
}

static void cb_log(void *instance, int status, const char *message) {
    Instance *inst = (Instance *)instance;
    log_message(inst, (fmi3Status)status, "%s", message);
}

static const char *cb_get_string(void *instance, uint32_t vr, uint64_t index) {
    Instance *inst = (Instance *)instance;
    if (vr >= inst->n_variables || inst->variables[vr].type != T_STRING || index >= inst->variables[vr].count)
        return NULL;
    return ((char **)inst->variables[vr].data)[index];
}

static int cb_set_string(void *instance, uint32_t vr, uint64_t index, const char *value) {
    Instance *inst = (Instance *)instance;
    if (vr >= inst->n_variables || inst->variables[vr].type != T_STRING || index >= inst->variables[vr].count)
        return -1;
    char *copy = strdup(value ? value : "");
    if (!copy) return -1;
    char **strings = (char **)inst->variables[vr].data;
    free(strings[index]);
    strings[index] = copy;
    return 0;
}

/* ---- calling the Python runtime ----------------------------------------------------------------- */
/* The runtime's module is loaded from the resources under a name unique to the FMU's build (two
 * FMUs, or two builds of one FMU, in one process never share modules). */
static const char BOOTSTRAP[] =
    "def _aaa_fmi3_entry(resources, model_identifier, token, started, *args):\n"
    "    import importlib.util, json, pathlib, site, sys\n"
    "    if started:\n"
    "        sys._aaa_cosim_embedded = started\n"
    "    embedded = getattr(sys, '_aaa_cosim_embedded', 0)\n"
    "    if embedded == 1:\n"
    "        # another installation's interpreter: the packages of the environment the FMU was built in\n"
    "        meta = json.loads((pathlib.Path(resources) / 'fmu.json').read_text())\n"
    "        for directory in meta.get('site_packages', []):\n"
    "            site.addsitedir(directory)\n"
    "    if embedded and not hasattr(sys, 'argv'):\n"
    "        sys.argv = ['']\n"
    "    name = '_fmi3_runtime_' + model_identifier + '_' + ''.join(c for c in token if c.isalnum())[:16]\n"
    "    module = sys.modules.get(name)\n"
    "    if module is None:\n"
    "        path = pathlib.Path(resources) / 'fmi3_runtime.py'\n"
    "        spec = importlib.util.spec_from_file_location(name, path)\n"
    "        module = importlib.util.module_from_spec(spec)\n"
    "        sys.modules[name] = module\n"
    "        try:\n"
    "            spec.loader.exec_module(module)\n"
    "        except BaseException:\n"
    "            del sys.modules[name]\n"
    "            raise\n"
    "    return module.instantiate(resources, model_identifier, token, *args)\n";

/* Whether the importer's own Python can host the model: "" when it has the Python version and the
 * packages, at the versions, that the FMU was built with (resources/fmu.json), else why not. */
static const char HOSTABLE[] =
    "def _aaa_fmi3_hostable(resources):\n"
    "    import importlib.metadata, json, pathlib, sys\n"
    "    meta = json.loads((pathlib.Path(resources) / 'fmu.json').read_text())\n"
    "    version = '%d.%d' % sys.version_info[:2]\n"
    "    if version != meta.get('python_version'):\n"
    "        return f\"the importer runs Python {version}, the FMU's model Python {meta.get('python_version')}\"\n"
    "    other = []\n"
    "    for name, wanted in sorted(meta.get('requirements', {}).items()):\n"
    "        try:\n"
    "            have = importlib.metadata.version(name)\n"
    "        except importlib.metadata.PackageNotFoundError:\n"
    "            have = None\n"
    "        if have != wanted:\n"
    "            other.append(f'{name} {have or \"missing\"} (the FMU needs {wanted})')\n"
    "    return ('the importer\\'s Python has ' + ', '.join(other)) if other else ''\n";

/* What a call ended by a KeyboardInterrupt logs (after the function's name). */
#define INTERRUPTED_REASON                                                                                 \
    "interrupted: a KeyboardInterrupt (SIGINT, e.g. Ctrl-C) arrived while the FMU's Python code ran; the " \
    "call was abandoned and the instance is in the Error mode (fmi3Reset or fmi3SetFMUState to go on); "   \
    "the interrupt is handed back to the importer"

/* The pending Python exception, logged as the failure of `function` (the GIL held). A
 * KeyboardInterrupt is logged as "interrupted" and marks the call for hand_back_interrupt. */
static void log_python_error(Instance *inst, const char *function) {
    char reason[2048];
    if (python_error_text(reason, sizeof reason)) {
        inst->interrupted = 1;
        log_message(inst, fmi3Error, "%s: " INTERRUPTED_REASON, function);
    } else {
        log_message(inst, fmi3Error, "%s: %s", function, reason);
    }
}

/* The interrupt a call swallowed goes back to the importer: the SIGINT flag is set again and a
 * Python importer raises KeyboardInterrupt at its next bytecode (after this call returns; the
 * FMU's Python work of this call is over). The GIL must be held. */
static void hand_back_interrupt(Instance *inst) {
    if (!inst->interrupted) return;
    inst->interrupted = 0;
    inst->mode = M_ERROR;
    py.PyErr_SetInterrupt();
}

/* Call a method of the model object; its result (new reference), or NULL with the reason logged.
 * The GIL is taken for the call only. */
#define CALL_MODEL(inst, function, method, ...)                                                   \
    ({                                                                                            \
        PyGILState_STATE gil_ = py.PyGILState_Ensure();                                            \
        PyObject *result_ = py.PyObject_CallMethod((inst)->model, method, __VA_ARGS__);           \
        if (!result_) log_python_error(inst, function);                                           \
        hand_back_interrupt(inst);                                                                \
        py.PyGILState_Release(gil_);                                                               \
        result_;                                                                                  \
    })

static void release(PyObject *object) {
    if (!object) return;
    PyGILState_STATE gil = py.PyGILState_Ensure();
    py.Py_DecRef(object);
    py.PyGILState_Release(gil);
}

/* Build the model from the current parameters (exit of Initialization Mode, or a getter in it). */
static fmi3Status build_model(Instance *inst, const char *function) {
    PyObject *result = CALL_MODEL(inst, function, "initialize", "(d)", inst->start_time);
    if (!result) {
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    PyGILState_STATE gil = py.PyGILState_Ensure();
    double step = py.PyFloat_AsDouble(result);
    int failed = py.PyErr_Occurred() != NULL;
    if (failed) py.PyErr_Clear();
    py.Py_DecRef(result);
    py.PyGILState_Release(gil);
    if (failed || !isfinite(step) || step == 0.0) {
        log_message(inst, fmi3Error, "%s: the model reported no valid internal step", function);
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    if (step < 0.0) { /* the runtime logged why the model could not be built */
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    inst->step_size = step;
    inst->built = 1;
    return fmi3OK;
}

/* ---- instantiation ------------------------------------------------------------------------------ */
static void default_resource_dir(char *buffer, size_t size) {
    /* <fmu>/binaries/<platform>/<id>.so -> <fmu>/resources */
    Dl_info info;
    buffer[0] = '\0';
    if (!dladdr((void *)&default_resource_dir, &info) || !info.dli_fname) return;
    char path[4096];
    snprintf(path, sizeof path, "%s", info.dli_fname);
    for (int up = 0; up < 3; up++) {
        char *slash = strrchr(path, '/');
        if (!slash) return;
        *slash = '\0';
    }
    snprintf(buffer, size, "%s/resources", path);
}

static void free_instance_memory(Instance *inst) {
    for (size_t i = 0; i < inst->n_variables; i++) {
        Variable *v = &inst->variables[i];
        if (v->type == T_STRING && v->data) {
            char **strings = (char **)v->data;
            for (size_t k = 0; k < v->count; k++) free(strings[k]);
            free(strings);
        }
        free(v->name);
        free(v->limit_text);
        free(v->size_text);
    }
    free(inst->variables);
    free(inst->instance_name);
    free(inst);
}

/* Whether this instance's model runs in a helper process (remote.h): asked, or because the
 * importer's own Python cannot host it (why, in `reason`). Only an FMU that carries a runtime can
 * start one. */
static int model_in_helper(const char *resources, char *reason, size_t reason_size) {
    reason[0] = '\0';
    const char *where = getenv(MODEL_PROCESS_VARIABLE);
    if (where && strcmp(where, MODEL_PROCESS_HELPER) == 0) return 1;
    if ((where && strcmp(where, MODEL_PROCESS_IMPORTER) == 0) || !runtime_carried(resources)) return 0;
    int (*initialized)(void) = (int (*)(void))dlsym(RTLD_DEFAULT, "Py_IsInitialized");
    if (!initialized || !initialized()) return 0; /* no Python here: the FMU starts its own in this process */
    int started = 0;
    if (python_ensure(resources, &started, reason, reason_size) != 0) return 1;
    PyGILState_STATE gil = py.PyGILState_Ensure();
    PyObject *globals = py.PyDict_New();
    PyObject *builtins = py.PyImport_ImportModule("builtins");
    int helper = 1;
    snprintf(reason, reason_size, "the importer's Python could not be asked whether it has the model's packages");
    if (globals && builtins && py.PyDict_SetItemString(globals, "__builtins__", builtins) == 0) {
        PyObject *done = py.PyRun_StringFlags(HOSTABLE, 257 /* Py_file_input */, globals, globals, NULL);
        PyObject *check = done ? py.PyDict_GetItemString(globals, "_aaa_fmi3_hostable") : NULL; /* borrowed */
        PyObject *answer = check ? py.PyObject_CallFunction(check, "s", resources) : NULL;
        const char *text = answer ? py.PyUnicode_AsUTF8(answer) : NULL;
        if (text) {
            helper = text[0] != '\0';
            snprintf(reason, reason_size, "%s", text);
        }
        if (py.PyErr_Occurred()) py.PyErr_Clear();
        if (answer) py.Py_DecRef(answer);
        if (done) py.Py_DecRef(done);
    }
    if (builtins) py.Py_DecRef(builtins);
    if (globals) py.Py_DecRef(globals);
    py.PyGILState_Release(gil);
    return helper;
}

fmi3Instance fmi3InstantiateCoSimulation(fmi3String instanceName, fmi3String instantiationToken,
                                         fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                         fmi3Boolean eventModeUsed, fmi3Boolean earlyReturnAllowed,
                                         const fmi3ValueReference requiredIntermediateVariables[],
                                         size_t nRequiredIntermediateVariables,
                                         fmi3InstanceEnvironment instanceEnvironment,
                                         fmi3LogMessageCallback logMessage,
                                         fmi3IntermediateUpdateCallback intermediateUpdate) {
    (void)visible; (void)earlyReturnAllowed; (void)requiredIntermediateVariables; (void)intermediateUpdate;
    Instance *inst = calloc(1, sizeof(Instance));
    if (!inst) return NULL;
    inst->kind = INSTANCE_LOCAL;
    inst->instance_name = strdup(instanceName ? instanceName : "");
    inst->environment = instanceEnvironment;
    inst->logger = logMessage;
    inst->logging_on = loggingOn;
    inst->log_categories = LOG_ERROR | LOG_WARNING | LOG_EVENTS;
    inst->mode = M_INSTANTIATED;
    if (!inst->instance_name) { free(inst); return NULL; }
    if (!instanceName || !instanceName[strspn(instanceName, " \t\r\n")]) {
        log_message(inst, fmi3Error, "fmi3InstantiateCoSimulation: instanceName must not be empty");
        free_instance_memory(inst);
        return NULL;
    }
    if (eventModeUsed || nRequiredIntermediateVariables > 0) {
        log_message(inst, fmi3Error, "fmi3InstantiateCoSimulation: this FMU has no Event Mode and no intermediate "
                    "update (hasEventMode and providesIntermediateUpdate are false): instantiate with "
                    "eventModeUsed = false and no required intermediate variables");
        free_instance_memory(inst);
        return NULL;
    }
    char resources[4096];
    if (resourcePath && *resourcePath) {
        snprintf(resources, sizeof resources, "%s", resourcePath);
    } else {
        default_resource_dir(resources, sizeof resources);
    }
    size_t length = strlen(resources);
    while (length > 1 && resources[length - 1] == '/') resources[--length] = '\0';

    char reason[2048];
    char binary[4096] = "";
    {
        Dl_info info;
        if (dladdr((void *)&fmi3InstantiateCoSimulation, &info) && info.dli_fname)
            snprintf(binary, sizeof binary, "%s", info.dli_fname);
    }
    if (model_in_helper(resources, reason, sizeof reason)) {
        if (reason[0]) log_message(inst, fmi3OK, "fmi3InstantiateCoSimulation: the model runs in a helper process: %s",
                                   reason);
        fmi3Instance remote = remote_instantiate(binary, instanceName, instantiationToken, resourcePath, loggingOn,
                                                 instanceEnvironment, logMessage);
        free_instance_memory(inst);
        return remote;
    }
    int started = 0;
    if (python_ensure(resources, &started, reason, sizeof reason) != 0) {
        log_message(inst, fmi3Error, "fmi3InstantiateCoSimulation: %s", reason);
        free_instance_memory(inst);
        return NULL;
    }
    const char *model_identifier = "";
    {
        Dl_info info;
        static char identifier[256];
        if (dladdr((void *)&fmi3InstantiateCoSimulation, &info) && info.dli_fname) {
            const char *base = strrchr(info.dli_fname, '/');
            snprintf(identifier, sizeof identifier, "%s", base ? base + 1 : info.dli_fname);
            char *dot = strrchr(identifier, '.');
            if (dot) *dot = '\0';
            model_identifier = identifier;
        }
    }
    PyGILState_STATE gil = py.PyGILState_Ensure();
    PyObject *globals = py.PyDict_New();
    PyObject *builtins = py.PyImport_ImportModule("builtins");
    PyObject *model = NULL;
    if (globals && builtins && py.PyDict_SetItemString(globals, "__builtins__", builtins) == 0) {
        PyObject *done = py.PyRun_StringFlags(BOOTSTRAP, 257 /* Py_file_input */, globals, globals, NULL);
        if (done) {
            py.Py_DecRef(done);
            PyObject *entry = py.PyDict_GetItemString(globals, "_aaa_fmi3_entry"); /* borrowed */
            if (entry) {
                model = py.PyObject_CallFunction(
                    entry, "sssisKKKKKKK", resources, model_identifier, instantiationToken ? instantiationToken : "",
                    started, inst->instance_name, (unsigned long long)(uintptr_t)inst,
                    (unsigned long long)(uintptr_t)&cb_register, (unsigned long long)(uintptr_t)&cb_counters,
                    (unsigned long long)(uintptr_t)&cb_step_io,
                    (unsigned long long)(uintptr_t)&cb_log,
                    (unsigned long long)(uintptr_t)&cb_get_string, (unsigned long long)(uintptr_t)&cb_set_string);
            }
        }
    }
    PyObject *do_step = model ? py.PyObject_GetAttrString(model, "do_step") : NULL;
    if (!do_step || !inst->step_io) {
        if (!py.PyErr_Occurred() && model) {
            snprintf(reason, sizeof reason, "the FMU's runtime registered no step exchange (resources from "
                     "another build of the FMI layer?)");
        } else if (python_error_text(reason, sizeof reason)) {
            snprintf(reason, sizeof reason, "%s (no instance was made)", INTERRUPTED_REASON);
            py.PyErr_SetInterrupt(); /* after the bootstrap: the importer's next bytecode raises it */
        }
        log_message(inst, fmi3Error, "fmi3InstantiateCoSimulation: %s", reason);
        if (do_step) py.Py_DecRef(do_step);
        if (model) py.Py_DecRef(model);
        model = do_step = NULL;
    }
    if (builtins) py.Py_DecRef(builtins);
    if (globals) py.Py_DecRef(globals);
    py.PyGILState_Release(gil);
    if (!model) {
        free_instance_memory(inst);
        return NULL;
    }
    inst->model = model;
    inst->do_step = do_step;
    return inst;
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   "fmi3InstantiateModelExchange: this FMU supports Co-Simulation only");
    return NULL;
}

fmi3Instance fmi3InstantiateScheduledExecution(fmi3String instanceName, fmi3String instantiationToken,
                                               fmi3String resourcePath, fmi3Boolean visible, fmi3Boolean loggingOn,
                                               fmi3InstanceEnvironment instanceEnvironment,
                                               fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
                                               fmi3LockPreemptionCallback lockPreemption,
                                               fmi3UnlockPreemptionCallback unlockPreemption) {
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible; (void)loggingOn;
    (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   "fmi3InstantiateScheduledExecution: this FMU supports Co-Simulation only");
    return NULL;
}

static void free_all_states(Instance *inst);

void fmi3FreeInstance(fmi3Instance instance) {
    if (remote_is(instance)) {
        remote_free_instance(instance);
        return;
    }
    Instance *inst = (Instance *)instance;
    if (!inst) return;
    free_all_states(inst); /* the importer's states die with the instance */
    if (inst->model) {
        PyObject *result = CALL_MODEL(inst, "fmi3FreeInstance", "free", NULL);
        release(result);
        release(inst->do_step);
        release(inst->model);
        inst->do_step = NULL;
        inst->model = NULL;
    }
    free_instance_memory(inst);
}

/* ---- common functions ------------------------------------------------------------------------------ */
const char *fmi3GetVersion(void) { return fmi3Version; }

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[]) {
    if (remote_is(instance)) return remote_set_debug_logging(instance, loggingOn, nCategories, categories);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_SetDebugLogging, "fmi3SetDebugLogging")) return fmi3Error;
    unsigned chosen = 0;
    if (nCategories > 0 && !categories) {
        log_message(inst, fmi3Error, "fmi3SetDebugLogging: categories is NULL but nCategories = %zu", nCategories);
        return fmi3Error;
    }
    for (size_t i = 0; i < nCategories; i++) {
        unsigned bit = 0;
        for (unsigned k = 0; k < 3; k++)
            if (categories[i] && strcmp(categories[i], LOG_CATEGORY_NAMES[k]) == 0) bit = 1u << k;
        if (!bit) {
            log_message(inst, fmi3Error, "fmi3SetDebugLogging: unknown log category '%s' (this FMU has "
                        "logStatusError, logStatusWarning, logEvents)", categories[i] ? categories[i] : "(null)");
            return fmi3Error;
        }
        chosen |= bit;
    }
    inst->logging_on = loggingOn;
    inst->log_categories = chosen ? chosen : (LOG_ERROR | LOG_WARNING | LOG_EVENTS);
    return fmi3OK;
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
                                       fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime) {
    if (remote_is(instance))
        return remote_enter_initialization_mode(instance, toleranceDefined, tolerance, startTime, stopTimeDefined,
                                                stopTime);
    (void)toleranceDefined; (void)tolerance;
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_EnterInitializationMode, "fmi3EnterInitializationMode")) return fmi3Error;
    if (!isfinite(startTime) || (stopTimeDefined && !(stopTime >= startTime))) {
        log_message(inst, fmi3Error, "fmi3EnterInitializationMode: startTime = %g and stopTime = %g: the start must "
                    "be finite and not after the stop", startTime, stopTimeDefined ? stopTime : NAN);
        return fmi3Error;
    }
    inst->start_time = startTime;
    inst->steps_done = 0;
    inst->mode = M_INITIALIZATION;
    return fmi3OK;
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance) {
    if (remote_is(instance)) return remote_simple(instance, REMOTE_OP_EXIT_INITIALIZATION);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_ExitInitializationMode, "fmi3ExitInitializationMode")) return fmi3Error;
    if (!inst->built && build_model(inst, "fmi3ExitInitializationMode") != fmi3OK) return fmi3Error;
    inst->mode = M_STEP;
    return fmi3OK;
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance) {
    return not_supported(instance, "fmi3EnterEventMode", "hasEventMode is false");
}

fmi3Status fmi3Terminate(fmi3Instance instance) {
    if (remote_is(instance)) return remote_simple(instance, REMOTE_OP_TERMINATE);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_Terminate, "fmi3Terminate")) return fmi3Error;
    PyObject *result = CALL_MODEL(inst, "fmi3Terminate", "terminate", NULL);
    if (!result) return fmi3Error;
    release(result);
    inst->mode = M_TERMINATED;
    return fmi3OK;
}

fmi3Status fmi3Reset(fmi3Instance instance) {
    if (remote_is(instance)) return remote_simple(instance, REMOTE_OP_RESET);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_Reset, "fmi3Reset")) return fmi3Error;
    PyObject *result = CALL_MODEL(inst, "fmi3Reset", "reset", NULL);
    if (!result) {
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    release(result);
    inst->mode = M_INSTANTIATED;
    inst->built = 0;
    inst->steps_done = 0;
    inst->start_time = 0.0;
    inst->last_error[0] = '\0';
    return fmi3OK;
}

/* ---- getters and setters ---------------------------------------------------------------------------- */
static const size_t TYPE_SIZES[] = {0, sizeof(fmi3Float64), sizeof(fmi3Float32), 1, 1, 2, 2, 4, 4, 8, 8,
                                    sizeof(fmi3Boolean), sizeof(fmi3String), 0};

/* Look up the variables of one call and check type and count; on success returns their total count. */
static int check_references(Instance *inst, const char *function, int type, const fmi3ValueReference vrs[],
                            size_t n_vrs, const void *values, size_t n_values) {
    if (n_vrs == 0) return 1;
    if (!vrs || !values) {
        log_message(inst, fmi3Error, "%s: %s is NULL", function, !vrs ? "valueReferences" : "values");
        return 0;
    }
    size_t total = 0;
    for (size_t i = 0; i < n_vrs; i++) {
        fmi3ValueReference vr = vrs[i];
        if (vr >= inst->n_variables || !inst->variables[vr].declared) {
            log_message(inst, fmi3Error, "%s: unknown value reference %u (valueReferences[%zu]); the model "
                        "description lists the variables", function, vr, i);
            return 0;
        }
        Variable *v = &inst->variables[vr];
        if (v->type != type) {
            log_message(inst, fmi3Error, "%s: variable '%s' (value reference %u) is a %s, not a %s", function,
                        v->name, vr, type_name(v->type), type_name(type));
            return 0;
        }
        total += v->count;
    }
    if (total != n_values) {
        char names[512] = "";
        size_t used = 0;
        for (size_t i = 0; i < n_vrs && used + 1 < sizeof names; i++) {
            const Variable *v = &inst->variables[vrs[i]];
            int written = i < 4 ? snprintf(names + used, sizeof names - used, "%s'%s' (%zu)", i ? ", " : "", v->name,
                                           v->count)
                                : snprintf(names + used, sizeof names - used, ", ...");
            if (written < 0) break;
            used += (size_t)written;
            if (i >= 4) break;
        }
        /* an array sized by a structural parameter says which, and the rule another FMU's size follows */
        const char *size_text = "";
        for (size_t i = 0; i < n_vrs && !*size_text; i++) size_text = inst->variables[vrs[i]].size_text;
        log_message(inst, fmi3Error, "%s: the %zu value reference(s) hold %zu value(s), but nValues = %zu: %s%s%s",
                    function, n_vrs, total, n_values, names, *size_text ? "; " : "", size_text);
        return 0;
    }
    return 1;
}

/* Whether `v` may be set in the current mode; logs why not. */
static int settable(Instance *inst, const char *function, const Variable *v) {
    const char *why = NULL;
    switch (v->causality) {
        case C_STRUCTURAL_PARAMETER:
            if (inst->mode == M_CONFIGURATION || (inst->mode == M_RECONFIGURATION && v->variability == V_TUNABLE))
                return 1;
            why = "structural parameters are set in Configuration Mode (call fmi3EnterConfigurationMode after "
                  "instantiation, then fmi3ExitConfigurationMode)";
            break;
        case C_PARAMETER:
            if (inst->mode == M_INSTANTIATED || inst->mode == M_INITIALIZATION) return 1;
            if (inst->mode == M_STEP && v->variability == V_TUNABLE) return 1;
            why = inst->mode == M_STEP ? "it is a fixed parameter: set it before fmi3ExitInitializationMode (a value "
                                         "set now would never reach the model)"
                                       : "only structural parameters can be set in Configuration Mode";
            break;
        case C_INPUT:
            if (inst->mode & (M_INSTANTIATED | M_INITIALIZATION | M_STEP)) return 1;
            why = "inputs are set after instantiation, in Initialization Mode and in Step Mode";
            break;
        case C_OUTPUT: why = "it is an output (computed by the FMU)"; break;
        case C_CALCULATED_PARAMETER: why = "it is a calculated parameter (computed by the FMU)"; break;
        case C_INDEPENDENT: why = "it is the independent variable (time advances through fmi3DoStep)"; break;
        default: why = "it is not settable"; break;
    }
    log_message(inst, fmi3Error, "%s: cannot set '%s' (%s) in %s: %s", function, v->name,
                causality_name(v->causality), mode_name(inst->mode), why);
    return 0;
}

/* Outputs and calculated parameters read in Initialization Mode need the model built. */
static int ensure_readable(Instance *inst, const char *function, const fmi3ValueReference vrs[], size_t n_vrs) {
    if (inst->mode != M_INITIALIZATION || inst->built) return 1;
    for (size_t i = 0; i < n_vrs; i++) {
        int causality = inst->variables[vrs[i]].causality;
        if (causality == C_OUTPUT || causality == C_CALCULATED_PARAMETER)
            return build_model(inst, function) == fmi3OK;
    }
    return 1;
}

static fmi3Status get_values(fmi3Instance instance, const char *function, int type, const fmi3ValueReference vrs[],
                             size_t n_vrs, void *values, size_t n_values) {
    if (remote_is(instance)) return remote_get(instance, type, vrs, n_vrs, values, n_values);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_Get, function)) return fmi3Error;
    if (!check_references(inst, function, type, vrs, n_vrs, values, n_values)) return fmi3Error;
    if (!ensure_readable(inst, function, vrs, n_vrs)) return fmi3Error;
    size_t size = TYPE_SIZES[type];
    char *out = (char *)values;
    for (size_t i = 0; i < n_vrs; i++) {
        const Variable *v = &inst->variables[vrs[i]];
        memcpy(out, v->data, v->count * size);
        out += v->count * size;
    }
    return fmi3OK;
}

/* Whether all `count` values lie in [min, max]; NaN compares false, so it is outside any range.
 * One flag accumulated without branches, which the compiler vectorizes with AVX2 (the 1 kHz
 * inputs are checked on every set; SSE2 code stays scalar: no unordered vector compares). */
#define ALL_WITHIN_BODY                                                                          \
    int64_t outside = 0;                                                                         \
    for (size_t k = 0; k < count; k++) {                                                         \
        double v = x[k];                                                                         \
        outside |= (int64_t)(!(v >= min)) | (int64_t)(!(v <= max));                              \
    }                                                                                            \
    return !outside;

static int all_within_default(const double *restrict x, size_t count, double min, double max) { ALL_WITHIN_BODY }

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
__attribute__((target("avx2"))) static int all_within_avx2(const double *restrict x, size_t count, double min,
                                                            double max) {
    ALL_WITHIN_BODY
}
#endif

static int has_avx2(void);

static int all_within(const double *x, size_t count, double min, double max) {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    if (has_avx2()) return all_within_avx2(x, count, min, max);
#endif
    return all_within_default(x, count, min, max);
}

/* Every Float64 value within its variable's limit (any finite number for a variable without one);
 * otherwise logs the variable, the value, the range and why, and returns 0. */
static int check_limits(Instance *inst, const char *function, const fmi3ValueReference vrs[], size_t n_vrs,
                        const double *values) {
    size_t offset = 0;
    for (size_t i = 0; i < n_vrs; i++) {
        const Variable *v = &inst->variables[vrs[i]];
        const double *x = values + offset;
        offset += v->count;
        if (all_within(x, v->count, v->min, v->max)) continue;
        size_t k = 0;
        while (k < v->count && x[k] >= v->min && x[k] <= v->max) k++;
        if (!isfinite(x[k])) {
            log_message(inst, fmi3Error, "%s: '%s' value %zu is %s: the FMU accepts only finite numbers (check "
                        "the source connected to this variable); nothing was set", function, v->name, k,
                        isnan(x[k]) ? "NaN" : x[k] > 0 ? "+infinity" : "-infinity");
        } else {
            log_message(inst, fmi3Error, "%s: '%s' value %zu = %.16g is %s the %s of its plausible range %s; "
                        "nothing was set", function, v->name, k, x[k], x[k] < v->min ? "below" : "above",
                        x[k] < v->min ? "minimum" : "maximum", v->limit_text);
        }
        return 0;
    }
    return 1;
}

static fmi3Status set_values(fmi3Instance instance, const char *function, int type, const fmi3ValueReference vrs[],
                             size_t n_vrs, const void *values, size_t n_values) {
    if (remote_is(instance)) return remote_set(instance, type, vrs, n_vrs, values, n_values);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_Set, function)) return fmi3Error;
    if (!check_references(inst, function, type, vrs, n_vrs, values, n_values)) return fmi3Error;
    for (size_t i = 0; i < n_vrs; i++)
        if (!settable(inst, function, &inst->variables[vrs[i]])) return fmi3Error;
    if (type == T_FLOAT64 && !check_limits(inst, function, vrs, n_vrs, (const double *)values)) return fmi3Error;
    if (type == T_BOOLEAN) {
        const unsigned char *flags = (const unsigned char *)values;
        for (size_t k = 0; k < n_values; k++)
            if (flags[k] > 1) {
                log_message(inst, fmi3Error, "%s: Boolean value %zu is %u, not fmi3True or fmi3False", function, k,
                            flags[k]);
                return fmi3Error;
            }
    }
    size_t size = TYPE_SIZES[type];
    const char *in = (const char *)values;
    for (size_t i = 0; i < n_vrs; i++) {
        Variable *v = &inst->variables[vrs[i]];
        memcpy(v->data, in, v->count * size);
        in += v->count * size;
        if (vrs[i] < inst->n_set_counts) inst->set_counts[vrs[i]] += 1;
        if (v->causality == C_PARAMETER && inst->mode != M_STEP) inst->built = 0;
    }
    return fmi3OK;
}

#define NUMERIC_ACCESSORS(Name, CODE)                                                                            \
    fmi3Status fmi3Get##Name(fmi3Instance instance, const fmi3ValueReference valueReferences[],                  \
                             size_t nValueReferences, fmi3##Name values[], size_t nValues) {                      \
        return get_values(instance, "fmi3Get" #Name, CODE, valueReferences, nValueReferences, values, nValues);   \
    }                                                                                                            \
    fmi3Status fmi3Set##Name(fmi3Instance instance, const fmi3ValueReference valueReferences[],                  \
                             size_t nValueReferences, const fmi3##Name values[], size_t nValues) {                \
        return set_values(instance, "fmi3Set" #Name, CODE, valueReferences, nValueReferences, values, nValues);   \
    }

NUMERIC_ACCESSORS(Float64, T_FLOAT64)
NUMERIC_ACCESSORS(Float32, T_FLOAT32)
NUMERIC_ACCESSORS(Int8, T_INT8)
NUMERIC_ACCESSORS(UInt8, T_UINT8)
NUMERIC_ACCESSORS(Int16, T_INT16)
NUMERIC_ACCESSORS(UInt16, T_UINT16)
NUMERIC_ACCESSORS(Int32, T_INT32)
NUMERIC_ACCESSORS(UInt32, T_UINT32)
NUMERIC_ACCESSORS(Int64, T_INT64)
NUMERIC_ACCESSORS(UInt64, T_UINT64)
NUMERIC_ACCESSORS(Boolean, T_BOOLEAN)

fmi3Status fmi3GetString(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         fmi3String values[], size_t nValues) {
    if (remote_is(instance)) return remote_get_string(instance, valueReferences, nValueReferences, values, nValues);
    /* the copy hands out the stored pointers, valid until the next fmi3SetString of the variable */
    return get_values(instance, "fmi3GetString", T_STRING, valueReferences, nValueReferences, values, nValues);
}

fmi3Status fmi3SetString(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         const fmi3String values[], size_t nValues) {
    if (remote_is(instance)) return remote_set_string(instance, valueReferences, nValueReferences, values, nValues);
    Instance *inst = (Instance *)instance;
    const char *function = "fmi3SetString";
    if (!inst || !allowed(inst, ALLOWED_Set, function)) return fmi3Error;
    if (!check_references(inst, function, T_STRING, valueReferences, nValueReferences, values, nValues))
        return fmi3Error;
    for (size_t i = 0; i < nValueReferences; i++)
        if (!settable(inst, function, &inst->variables[valueReferences[i]])) return fmi3Error;
    for (size_t k = 0; k < nValues; k++)
        if (!values[k]) {
            log_message(inst, fmi3Error, "%s: value %zu is a NULL pointer (give \"\" for an empty string)", function, k);
            return fmi3Error;
        }
    size_t offset = 0;
    for (size_t i = 0; i < nValueReferences; i++) {
        Variable *v = &inst->variables[valueReferences[i]];
        for (size_t k = 0; k < v->count; k++) {
            if (cb_set_string(inst, valueReferences[i], k, values[offset + k]) != 0) {
                log_message(inst, fmi3Error, "%s: out of memory", function);
                return fmi3Error;
            }
        }
        offset += v->count;
        if (valueReferences[i] < inst->n_set_counts) inst->set_counts[valueReferences[i]] += 1;
        if (v->causality == C_PARAMETER && inst->mode != M_STEP) inst->built = 0;
    }
    return fmi3OK;
}

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         size_t valueSizes[], fmi3Binary values[], size_t nValues) {
    if (remote_is(instance))
        return remote_get_binary(instance, valueReferences, nValueReferences, valueSizes, values, nValues);
    return get_values(instance, "fmi3GetBinary", T_BINARY, valueReferences, nValueReferences, values, nValues);
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                         const size_t valueSizes[], const fmi3Binary values[], size_t nValues) {
    if (remote_is(instance))
        return remote_set_binary(instance, valueReferences, nValueReferences, valueSizes, values, nValues);
    return set_values(instance, "fmi3SetBinary", T_BINARY, valueReferences, nValueReferences, values, nValues);
}

fmi3Status fmi3GetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        fmi3Clock values[]) {
    (void)valueReferences; (void)nValueReferences; (void)values;
    return not_supported(instance, "fmi3GetClock", "it has no clocks");
}

fmi3Status fmi3SetClock(fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
                        const fmi3Clock values[]) {
    (void)valueReferences; (void)nValueReferences; (void)values;
    return not_supported(instance, "fmi3SetClock", "it has no clocks");
}

/* ---- configuration --------------------------------------------------------------------------------- */
fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance) {
    if (remote_is(instance)) return remote_simple(instance, REMOTE_OP_ENTER_CONFIGURATION);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_EnterConfigurationMode, "fmi3EnterConfigurationMode")) return fmi3Error;
    inst->mode = M_CONFIGURATION;
    return fmi3OK;
}

fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance) {
    if (remote_is(instance)) return remote_simple(instance, REMOTE_OP_EXIT_CONFIGURATION);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_ExitConfigurationMode, "fmi3ExitConfigurationMode")) return fmi3Error;
    /* arrays sized by structural parameters are allocated anew (and registered again) */
    PyObject *result = CALL_MODEL(inst, "fmi3ExitConfigurationMode", "configure", NULL);
    if (!result) return fmi3Error; /* stays in Configuration Mode: fix the values and exit again */
    release(result);
    inst->built = 0;
    inst->mode = inst->mode == M_CONFIGURATION ? M_INSTANTIATED : M_STEP;
    return fmi3OK;
}

/* ---- the step ------------------------------------------------------------------------------------------ */
/* Whether any of `count` doubles is a NaN or an infinity, tested on the bits: the exponent field
 * (all ones for NaN and infinities) plus one carries into the sign bit exactly when it is all
 * ones. Plain 64-bit and/add/or in eight independent accumulators, which the compiler vectorizes
 * (SSE2, or AVX2 where the processor has it): Contact's 8073 values in about 1 us after a step
 * (0.7 us with the data in cache), where a compare and a flag per value took 5 us (the count, a
 * size_t field, could alias the data: no vectorization). The buffers are written as doubles
 * elsewhere, hence may_alias. */
typedef uint64_t __attribute__((may_alias)) Bits64;

#define ANY_NON_FINITE_BODY                                                                      \
    const uint64_t exponent = 0x7ff0000000000000ULL, carry = 0x0010000000000000ULL;             \
    uint64_t acc[8] = {0}, bad = 0;                                                              \
    size_t k = 0;                                                                                \
    for (; k + 8 <= count; k += 8)                                                               \
        for (int j = 0; j < 8; j++) acc[j] |= (bits[k + j] & exponent) + carry;                  \
    for (; k < count; k++) bad |= (bits[k] & exponent) + carry;                                  \
    for (int j = 0; j < 8; j++) bad |= acc[j];                                                   \
    return (int)(bad >> 63);

static int any_non_finite_default(const Bits64 *restrict bits, size_t count) { ANY_NON_FINITE_BODY }

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
__attribute__((target("avx2"))) static int any_non_finite_avx2(const Bits64 *restrict bits, size_t count) {
    ANY_NON_FINITE_BODY
}
#endif

static int has_avx2(void) {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    static int avx2 = -1;
    if (avx2 < 0) { /* the same answer in any thread */
        __builtin_cpu_init();
        avx2 = __builtin_cpu_supports("avx2") ? 1 : 0;
    }
    return avx2;
#else
    return 0;
#endif
}

static int any_non_finite(const Bits64 *bits, size_t count) {
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    if (has_avx2()) return any_non_finite_avx2(bits, count);
#endif
    return any_non_finite_default(bits, count);
}

/* The first Float64 output holding a NaN or an infinity, or NULL: a model never reports one as OK. */
static const Variable *non_finite_output(const Instance *inst, size_t *index) {
    const uint64_t exponent = 0x7ff0000000000000ULL;
    for (size_t i = 0; i < inst->n_variables; i++) {
        const Variable *v = &inst->variables[i];
        if (!v->declared || v->causality != C_OUTPUT || v->type != T_FLOAT64) continue;
        const Bits64 *bits = (const Bits64 *)v->data;
        size_t count = v->count;
        if (any_non_finite(bits, count)) {
            for (size_t k = 0; k < count; k++)
                if ((bits[k] & exponent) == exponent) { *index = k; break; }
            return v;
        }
    }
    return NULL;
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint, fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *eventHandlingNeeded,
                      fmi3Boolean *terminateSimulation, fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime) {
    if (remote_is(instance))
        return remote_do_step(instance, currentCommunicationPoint, communicationStepSize,
                              noSetFMUStatePriorToCurrentPoint, eventHandlingNeeded, terminateSimulation, earlyReturn,
                              lastSuccessfulTime);
    (void)noSetFMUStatePriorToCurrentPoint;
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_DoStep, "fmi3DoStep")) return fmi3Error;
    if (eventHandlingNeeded) *eventHandlingNeeded = fmi3False;
    if (terminateSimulation) *terminateSimulation = fmi3False;
    if (earlyReturn) *earlyReturn = fmi3False;
    double now = instance_time(inst);
    if (lastSuccessfulTime) *lastSuccessfulTime = now;
    double h = communicationStepSize, step = inst->step_size;
    if (!isfinite(currentCommunicationPoint) ||
        fabs(currentCommunicationPoint - now) > 1e-9 * fmax(step, fabs(now))) {
        log_message(inst, fmi3Error, "fmi3DoStep(t = %.15g, h = %.15g): the FMU is at t = %.15g; communication "
                    "points follow each other without gaps (use fmi3SetFMUState to go back in time)",
                    currentCommunicationPoint, h, now);
        return fmi3Error;
    }
    double substeps = isfinite(h) ? nearbyint(h / step) : 0.0;
    if (!(h > 0.0) || substeps < 1.0 || fabs(substeps * step - h) > 1e-9 * h) {
        log_message(inst, fmi3Error, "fmi3DoStep(t = %.15g, h = %.15g): the communication step must be a whole "
                    "multiple of the internal step %.15g s (fixedInternalStepSize, parameter internal_step)",
                    currentCommunicationPoint, h, step);
        return fmi3Error;
    }
    /* a call cannot be interrupted by a C importer: one that would run for minutes is refused */
    double most = inst->step_io[IO_MAX_SUBSTEPS];
    if (substeps > most) {
        log_message(inst, fmi3Error, "fmi3DoStep(t = %.15g, h = %.15g): that is %.15g internal steps of %.15g s; "
                    "this FMU runs at most %.15g in one call (%.15g s): split the communication step into calls "
                    "of at most that", currentCommunicationPoint, h, substeps, step, most, most * step);
        return fmi3Error;
    }
    /* The importer's own time and step go to the model, so that a step of one internal step
     * computes exactly what the model computes when called directly with those numbers. They
     * travel through the step exchange, and the runtime's do_step is the method bound at
     * instantiation: one Python call per fmi3DoStep, no argument objects, no result to parse. */
    double *io = inst->step_io;
    io[IO_TIME] = currentCommunicationPoint;
    io[IO_STEP] = h;
    io[IO_SUBSTEPS] = substeps;
    io[IO_STATUS] = fmi3OK;        /* the runtime writes a warning or a failure */
    io[IO_COMPLETED] = substeps;   /* and, on a failure, the steps it completed */
    PyGILState_STATE gil = py.PyGILState_Ensure();
    PyObject *result = py.PyObject_CallNoArgs(inst->do_step);
    if (result) {
        py.Py_DecRef(result);
    } else {
        log_python_error(inst, "fmi3DoStep");
    }
    hand_back_interrupt(inst);
    py.PyGILState_Release(gil);
    if (!result) {
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    /* the runtime wrote its status and the internal steps it completed */
    long status = (long)io[IO_STATUS];
    double completed = io[IO_COMPLETED];
    if (completed >= 1.0 && completed <= substeps) inst->steps_done += (uint64_t)completed;
    if (lastSuccessfulTime) *lastSuccessfulTime = instance_time(inst);
    size_t index = 0;
    const Variable *bad = status < fmi3Error ? non_finite_output(inst, &index) : NULL;
    if (bad) {
        log_message(inst, fmi3Error, "fmi3DoStep(t = %.15g, h = %.15g): the model produced a NaN or an infinity in "
                    "output '%s' (value %zu): its state is no longer valid (restore a saved state or reset)",
                    currentCommunicationPoint, h, bad->name, index);
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    if (status >= fmi3Error) {
        if (inst->last_error[0] == '\0')
            snprintf(inst->last_error, sizeof inst->last_error, "fmi3DoStep failed at t = %.17g", now);
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    return status == fmi3Warning ? fmi3Warning : fmi3OK;
}

fmi3Status fmi3EnterStepMode(fmi3Instance instance) {
    return not_supported(instance, "fmi3EnterStepMode", "hasEventMode is false: the FMU is in Step Mode after "
                         "fmi3ExitInitializationMode");
}

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, const fmi3Int32 orders[], fmi3Float64 values[],
                                    size_t nValues) {
    (void)valueReferences; (void)nValueReferences; (void)orders; (void)values; (void)nValues;
    return not_supported(instance, "fmi3GetOutputDerivatives", "maxOutputDerivativeOrder is 0");
}

/* ---- FMU state ------------------------------------------------------------------------------------------ */
/* A saved state: the C layer's fields and the runtime's snapshot. The importer holds a handle, not
 * the state's address: a number this instance hands out once and never again (odd, so no aligned
 * pointer of the importer's is ever one), looked up in the instance's registry of live states
 * before anything is touched. So a freed handle, a copy of one, another instance's, garbage, or
 * the state itself where a pointer to it is due (fmusim v0.0.39's fmi3FreeFMUState) is refused or
 * understood, never followed, even after the allocator reused the freed state's memory. */
typedef struct {
    uintptr_t handle;      /* what the importer holds (fmi3FMUState) */
    int mode, built;
    uint64_t steps_done;
    double start_time, step_size;
    PyObject *model_state; /* the runtime's snapshot (values, strings, model) */
    PyObject *serialized;  /* its bytes once asked for (fmi3SerializedFMUStateSize, then fmi3SerializeFMUState) */
} SavedState;

/* The modes a state can be saved in (ALLOWED_FMUState) are the ones a state may restore. */
static int is_state_mode(int mode) {
    return (mode & ALLOWED_FMUState) && (mode & (mode - 1)) == 0;
}

/* The live state a handle names, or NULL; the handle is compared, never dereferenced. */
static SavedState *registered(const Instance *inst, const void *handle) {
    for (size_t i = 0; handle && i < inst->n_states; i++) {
        SavedState *saved = (SavedState *)inst->states[i];
        if (saved->handle == (uintptr_t)handle) return saved;
    }
    return NULL;
}

static int register_state(Instance *inst, SavedState *saved) {
    if (inst->n_states == inst->capacity_states) {
        size_t capacity = inst->capacity_states ? 2 * inst->capacity_states : 8;
        void **grown = realloc(inst->states, capacity * sizeof *grown);
        if (!grown) return 0;
        inst->states = grown;
        inst->capacity_states = capacity;
    }
    /* odd numbers from an address of this instance's own: distinct across instances in the process */
    if (!inst->next_handle) inst->next_handle = ((uintptr_t)inst << 8) | 1u;
    saved->handle = inst->next_handle;
    inst->next_handle += 2;
    inst->states[inst->n_states++] = saved;
    return 1;
}

/* Release a state's snapshot and bytes; the runtime empties the snapshot first (see discard). */
static void drop_snapshot(Instance *inst, SavedState *saved) {
    release(saved->serialized);
    if (saved->model_state && inst->model)
        release(CALL_MODEL(inst, "fmi3FreeFMUState", "discard", "(O)", saved->model_state));
    release(saved->model_state);
    saved->serialized = saved->model_state = NULL;
}

static void free_state(Instance *inst, SavedState *saved) {
    for (size_t i = 0; i < inst->n_states; i++) {
        if (inst->states[i] == saved) {
            inst->states[i] = inst->states[--inst->n_states];
            break;
        }
    }
    drop_snapshot(inst, saved);
    free(saved);
    /* a state holds the model's arrays (tens of MB for the tissue): give the pages back to the
     * system now, not when the allocator happens to trim */
    malloc_trim(0);
}

static void free_all_states(Instance *inst) {
    while (inst->n_states) free_state(inst, (SavedState *)inst->states[inst->n_states - 1]);
    free(inst->states);
    inst->states = NULL;
    inst->capacity_states = 0;
}

/* The state a handle names, or NULL (logged) when it names none of this instance's live states. */
static SavedState *live_state(Instance *inst, const char *function, fmi3FMUState state) {
    SavedState *saved = registered(inst, state);
    if (saved) return saved;
    log_message(inst, fmi3Error, "%s: FMUState %p is not a live state of instance '%s' (NULL, freed, or of "
                "another instance): use a state this instance returned from fmi3GetFMUState or "
                "fmi3DeserializeFMUState and has not freed", function, state, inst->instance_name);
    return NULL;
}

/* Where fmi3GetFMUState or fmi3DeserializeFMUState put a state: into *FMUState when it is one of
 * this instance's states (overwritten, as the standard allows), else a new one. */
static SavedState *state_slot(Instance *inst, const char *function, fmi3FMUState *FMUState, int *fresh) {
    *fresh = 0;
    if (*FMUState) return live_state(inst, function, *FMUState);
    SavedState *saved = calloc(1, sizeof(SavedState));
    if (!saved || !register_state(inst, saved)) {
        free(saved);
        log_message(inst, fmi3Error, "%s: out of memory", function);
        return NULL;
    }
    *fresh = 1;
    return saved;
}

static void fill_state(Instance *inst, SavedState *saved, int mode, int built, uint64_t steps_done,
                       double start_time, double step_size, PyObject *snapshot) {
    drop_snapshot(inst, saved);
    saved->mode = mode;
    saved->built = built;
    saved->steps_done = steps_done;
    saved->start_time = start_time;
    saved->step_size = step_size;
    saved->model_state = snapshot;
}

fmi3Status fmi3GetFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    if (remote_is(instance)) return remote_get_state(instance, FMUState);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_FMUState, "fmi3GetFMUState")) return fmi3Error;
    if (!FMUState) {
        log_message(inst, fmi3Error, "fmi3GetFMUState: FMUState is NULL");
        return fmi3Error;
    }
    int fresh;
    SavedState *saved = state_slot(inst, "fmi3GetFMUState", FMUState, &fresh);
    if (!saved) return fmi3Error;
    PyObject *snapshot = CALL_MODEL(inst, "fmi3GetFMUState", "get_state", NULL);
    if (!snapshot) {
        if (fresh) free_state(inst, saved);
        return fmi3Error;
    }
    fill_state(inst, saved, inst->mode, inst->built, inst->steps_done, inst->start_time, inst->step_size, snapshot);
    *FMUState = (fmi3FMUState)saved->handle;
    return fmi3OK;
}

fmi3Status fmi3SetFMUState(fmi3Instance instance, fmi3FMUState FMUState) {
    if (remote_is(instance)) return remote_set_state(instance, FMUState);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_FMUState, "fmi3SetFMUState")) return fmi3Error;
    SavedState *saved = live_state(inst, "fmi3SetFMUState", FMUState);
    if (!saved) return fmi3Error;
    PyObject *result = CALL_MODEL(inst, "fmi3SetFMUState", "set_state", "(O)", saved->model_state);
    if (!result) { /* the restore failed part way: the instance is in no defined state */
        inst->mode = M_ERROR;
        return fmi3Error;
    }
    PyGILState_STATE gil = py.PyGILState_Ensure();
    double applied = py.PyFloat_AsDouble(result);
    if (py.PyErr_Occurred()) py.PyErr_Clear();
    py.Py_DecRef(result);
    py.PyGILState_Release(gil);
    if (applied != 1.0) return fmi3Error; /* refused before anything was set (logged): nothing changed */
    inst->mode = saved->mode;
    inst->built = saved->built;
    inst->steps_done = saved->steps_done;
    inst->start_time = saved->start_time;
    inst->step_size = saved->step_size;
    inst->last_error[0] = '\0';
    return fmi3OK;
}

fmi3Status fmi3FreeFMUState(fmi3Instance instance, fmi3FMUState *FMUState) {
    if (remote_is(instance)) return remote_free_state(instance, FMUState);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_FMUState, "fmi3FreeFMUState")) return fmi3Error;
    if (!FMUState) return fmi3OK;
    SavedState *misplaced = registered(inst, FMUState);
    if (misplaced) {
        /* The state itself where a pointer to it is due (fmusim v0.0.39): the intent is unambiguous
         * (it is one of this instance's live states), so it is freed and the call succeeds: fmusim
         * stops at any status but fmi3OK, and would not restore a state from its file otherwise. */
        log_message(inst, fmi3OK, "fmi3FreeFMUState: was given the state %p itself, not a pointer to it; freed "
                    "that state (the standard passes fmi3FMUState*)", (void *)FMUState);
        free_state(inst, misplaced);
        return fmi3OK;
    }
    if (!*FMUState) return fmi3OK;
    SavedState *saved = live_state(inst, "fmi3FreeFMUState", *FMUState);
    if (!saved) return fmi3Error;
    free_state(inst, saved);
    *FMUState = NULL;
    return fmi3OK;
}

/* The state's bytes (state_format.py), made once per saved state; a borrowed reference or NULL (logged). */
static PyObject *serialized_bytes(Instance *inst, const char *function, SavedState *saved) {
    if (saved->serialized) return saved->serialized;
    PyObject *bytes = CALL_MODEL(inst, function, "serialize", "(OiiKdd)", saved->model_state, saved->mode,
                                 saved->built, (unsigned long long)saved->steps_done, saved->start_time,
                                 saved->step_size);
    if (!bytes) return NULL;
    PyGILState_STATE gil = py.PyGILState_Ensure();
    char *data = NULL;
    Py_ssize_t length = 0;
    int ok = py.PyBytes_AsStringAndSize(bytes, &data, &length) == 0;
    if (!ok) py.PyErr_Clear();
    py.PyGILState_Release(gil);
    if (!ok) {
        release(bytes);
        log_message(inst, fmi3Error, "%s: the runtime returned no bytes", function);
        return NULL;
    }
    saved->serialized = bytes;
    return bytes;
}

fmi3Status fmi3SerializedFMUStateSize(fmi3Instance instance, fmi3FMUState FMUState, size_t *size) {
    if (remote_is(instance)) return remote_state_size(instance, FMUState, size);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_FMUState, "fmi3SerializedFMUStateSize")) return fmi3Error;
    SavedState *saved = live_state(inst, "fmi3SerializedFMUStateSize", FMUState);
    if (!saved) return fmi3Error;
    if (!size) {
        log_message(inst, fmi3Error, "fmi3SerializedFMUStateSize: size is NULL");
        return fmi3Error;
    }
    PyObject *bytes = serialized_bytes(inst, "fmi3SerializedFMUStateSize", saved);
    if (!bytes) return fmi3Error;
    PyGILState_STATE gil = py.PyGILState_Ensure();
    char *data = NULL;
    Py_ssize_t length = 0;
    if (py.PyBytes_AsStringAndSize(bytes, &data, &length) != 0) py.PyErr_Clear();
    py.PyGILState_Release(gil);
    *size = (size_t)length;
    return fmi3OK;
}

fmi3Status fmi3SerializeFMUState(fmi3Instance instance, fmi3FMUState FMUState, fmi3Byte serializedState[],
                                 size_t size) {
    if (remote_is(instance)) return remote_serialize_state(instance, FMUState, serializedState, size);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_FMUState, "fmi3SerializeFMUState")) return fmi3Error;
    SavedState *saved = live_state(inst, "fmi3SerializeFMUState", FMUState);
    if (!saved) return fmi3Error;
    if (!serializedState) {
        log_message(inst, fmi3Error, "fmi3SerializeFMUState: serializedState is NULL");
        return fmi3Error;
    }
    PyObject *bytes = serialized_bytes(inst, "fmi3SerializeFMUState", saved);
    if (!bytes) return fmi3Error;
    PyGILState_STATE gil = py.PyGILState_Ensure();
    char *data = NULL;
    Py_ssize_t length = 0;
    int ok = py.PyBytes_AsStringAndSize(bytes, &data, &length) == 0;
    if (!ok) py.PyErr_Clear();
    if (ok && (size_t)length == size) memcpy(serializedState, data, size);
    py.PyGILState_Release(gil);
    if (!ok || (size_t)length != size) {
        log_message(inst, fmi3Error, "fmi3SerializeFMUState: size = %zu does not match "
                    "fmi3SerializedFMUStateSize (%zu)", size, (size_t)length);
        return fmi3Error;
    }
    return fmi3OK;
}

fmi3Status fmi3DeserializeFMUState(fmi3Instance instance, const fmi3Byte serializedState[], size_t size,
                                   fmi3FMUState *FMUState) {
    if (remote_is(instance)) return remote_deserialize_state(instance, serializedState, size, FMUState);
    Instance *inst = (Instance *)instance;
    if (!inst || !allowed(inst, ALLOWED_FMUState, "fmi3DeserializeFMUState")) return fmi3Error;
    if (!serializedState || !FMUState || size == 0 || size > (size_t)SSIZE_MAX) {
        log_message(inst, fmi3Error, "fmi3DeserializeFMUState: no state (NULL or %zu bytes)", size);
        return fmi3Error;
    }
    if (*FMUState && !live_state(inst, "fmi3DeserializeFMUState", *FMUState)) return fmi3Error;
    PyGILState_STATE gil = py.PyGILState_Ensure();
    PyObject *bytes = py.PyBytes_FromStringAndSize((const char *)serializedState, (Py_ssize_t)size);
    if (!bytes) py.PyErr_Clear();
    py.PyGILState_Release(gil);
    if (!bytes) {
        log_message(inst, fmi3Error, "fmi3DeserializeFMUState: out of memory for %zu bytes", size);
        return fmi3Error;
    }
    /* the runtime parses the bytes as data and checks every field (state_format.py); the C layer's
     * fields come back beside the snapshot and are checked here before anything is kept */
    PyObject *parsed = CALL_MODEL(inst, "fmi3DeserializeFMUState", "deserialize", "(O)", bytes);
    release(bytes);
    if (!parsed) return fmi3Error;
    PyObject *snapshot = NULL;
    int mode = 0, built = 0;
    unsigned long long steps_done = 0;
    double start_time = 0.0, step_size = 0.0;
    gil = py.PyGILState_Ensure();
    int ok = py.PyArg_ParseTuple(parsed, "OiiKdd", &snapshot, &mode, &built, &steps_done, &start_time, &step_size);
    if (!ok) py.PyErr_Clear();
    if (ok) py.Py_IncRef(snapshot);
    py.Py_DecRef(parsed);
    py.PyGILState_Release(gil);
    if (!ok || !is_state_mode(mode) || (built != 0 && built != 1) || !isfinite(start_time) || !isfinite(step_size)
        || step_size < 0.0 || (built && step_size <= 0.0) || ((mode & (M_STEP | M_TERMINATED)) && !built)) {
        release(snapshot);
        log_message(inst, fmi3Error, "fmi3DeserializeFMUState: the state's mode (%d), step (%g s) or time is not one "
                    "an FMU state can have: it was not written by fmi3SerializeFMUState", mode, step_size);
        return fmi3Error;
    }
    int fresh;
    SavedState *saved = state_slot(inst, "fmi3DeserializeFMUState", FMUState, &fresh);
    if (!saved) {
        release(snapshot);
        return fmi3Error;
    }
    fill_state(inst, saved, mode, built, (uint64_t)steps_done, start_time, step_size, snapshot);
    *FMUState = (fmi3FMUState)saved->handle;
    return fmi3OK;
}

/* ---- what this FMU does not provide (the flags in modelDescription.xml say so) ------------------------ */
fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance, fmi3ValueReference valueReference,
                                               size_t *nDependencies) {
    (void)valueReference; (void)nDependencies;
    return not_supported(instance, "fmi3GetNumberOfVariableDependencies", "providesPerElementDependencies is false");
}

fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[], fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[], fmi3DependencyKind dependencyKinds[],
                                       size_t nDependencies) {
    (void)dependent; (void)elementIndicesOfDependent; (void)independents; (void)elementIndicesOfIndependents;
    (void)dependencyKinds; (void)nDependencies;
    return not_supported(instance, "fmi3GetVariableDependencies", "providesPerElementDependencies is false");
}

fmi3Status fmi3GetDirectionalDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                        const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                        size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed; (void)sensitivity;
    (void)nSensitivity;
    return not_supported(instance, "fmi3GetDirectionalDerivative", "providesDirectionalDerivatives is false");
}

fmi3Status fmi3GetAdjointDerivative(fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
                                    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[],
                                    size_t nSeed, fmi3Float64 sensitivity[], size_t nSensitivity) {
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed; (void)sensitivity;
    (void)nSensitivity;
    return not_supported(instance, "fmi3GetAdjointDerivative", "providesAdjointDerivatives is false");
}

#define NO_CLOCKS(Name, ...)                                                              \
    fmi3Status fmi3##Name(fmi3Instance instance, __VA_ARGS__) {                           \
        return not_supported(instance, "fmi3" #Name, "it has no clocks");                  \
    }
NO_CLOCKS(GetIntervalDecimal, const fmi3ValueReference v[], size_t n, fmi3Float64 i[], fmi3IntervalQualifier q[])
NO_CLOCKS(GetIntervalFraction, const fmi3ValueReference v[], size_t n, fmi3UInt64 c[], fmi3UInt64 r[],
          fmi3IntervalQualifier q[])
NO_CLOCKS(GetShiftDecimal, const fmi3ValueReference v[], size_t n, fmi3Float64 s[])
NO_CLOCKS(GetShiftFraction, const fmi3ValueReference v[], size_t n, fmi3UInt64 c[], fmi3UInt64 r[])
NO_CLOCKS(SetIntervalDecimal, const fmi3ValueReference v[], size_t n, const fmi3Float64 i[])
NO_CLOCKS(SetIntervalFraction, const fmi3ValueReference v[], size_t n, const fmi3UInt64 c[], const fmi3UInt64 r[])
NO_CLOCKS(SetShiftDecimal, const fmi3ValueReference v[], size_t n, const fmi3Float64 s[])
NO_CLOCKS(SetShiftFraction, const fmi3ValueReference v[], size_t n, const fmi3UInt64 c[], const fmi3UInt64 r[])
NO_CLOCKS(ActivateModelPartition, fmi3ValueReference clockReference, fmi3Float64 activationTime)

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance) {
    return not_supported(instance, "fmi3EvaluateDiscreteStates", "providesEvaluateDiscreteStates is false");
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
                                    fmi3Float64 *nextEventTime) {
    (void)discreteStatesNeedUpdate; (void)terminateSimulation; (void)nominalsOfContinuousStatesChanged;
    (void)valuesOfContinuousStatesChanged; (void)nextEventTimeDefined; (void)nextEventTime;
    return not_supported(instance, "fmi3UpdateDiscreteStates", "hasEventMode is false");
}

#define MODEL_EXCHANGE_ONLY(Name, ...)                                                      \
    fmi3Status fmi3##Name(fmi3Instance instance, __VA_ARGS__) {                             \
        return not_supported(instance, "fmi3" #Name, "it is a Co-Simulation FMU");           \
    }
fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance) {
    return not_supported(instance, "fmi3EnterContinuousTimeMode", "it is a Co-Simulation FMU");
}
MODEL_EXCHANGE_ONLY(CompletedIntegratorStep, fmi3Boolean noSetFMUStatePriorToCurrentPoint, fmi3Boolean *enterEventMode,
                    fmi3Boolean *terminateSimulation)
MODEL_EXCHANGE_ONLY(SetTime, fmi3Float64 time)
MODEL_EXCHANGE_ONLY(SetContinuousStates, const fmi3Float64 continuousStates[], size_t nContinuousStates)
MODEL_EXCHANGE_ONLY(GetContinuousStateDerivatives, fmi3Float64 derivatives[], size_t nContinuousStates)
MODEL_EXCHANGE_ONLY(GetEventIndicators, fmi3Float64 eventIndicators[], size_t nEventIndicators)
MODEL_EXCHANGE_ONLY(GetContinuousStates, fmi3Float64 continuousStates[], size_t nContinuousStates)
MODEL_EXCHANGE_ONLY(GetNominalsOfContinuousStates, fmi3Float64 nominals[], size_t nContinuousStates)
MODEL_EXCHANGE_ONLY(GetNumberOfEventIndicators, size_t *nEventIndicators)
MODEL_EXCHANGE_ONLY(GetNumberOfContinuousStates, size_t *nContinuousStates)
