/* The model in a helper process: an FMU instance whose calls run in another process.
 *
 * In an importer whose own Python cannot host the model (another Python version, other versions
 * of numpy/scipy/numba, or none of them: FMPy in a bare environment, a Python-hosted C++ master)
 * the instance starts a helper process (binaries/<platform>/aaa_cosim_helper) that loads this same
 * FMU binary, which there embeds the runtime the FMU carries, and forwards every FMI call to it
 * over shared memory. The importer sees an ordinary instance; the log messages of a call reach its
 * logger when the call returns.
 *
 * Where the model runs: $AAA_COSIM_MODEL_PROCESS = "importer" (always in the importer's process),
 * "helper" (always in a helper process), or unset: in the importer's process unless its Python
 * lacks the packages at the versions the FMU was built with (resources/fmu.json, "requirements").
 *
 * The channel: one memfd per instance, mapped by both processes; a request is written by the
 * importer, then `request` is incremented; the helper answers and sets `response` to the same
 * number. Each side spins briefly, then sleeps on a futex, so a 1 kHz step costs microseconds,
 * and an idle helper costs nothing. The helper ends within a second of its importer; an importer
 * waiting on a helper that died gets fmi3Fatal and a log line, never a hang.
 */
#ifndef AAA_REMOTE_H
#define AAA_REMOTE_H

#include <stddef.h>
#include <stdint.h>

#include "fmi3Functions.h"

/* The first field of every instance this FMU hands out: which kind of instance it is. */
enum { INSTANCE_LOCAL = 0x6c6f6361u, INSTANCE_REMOTE = 0x72656d6fu };

/* The environment variable and its values (see above). */
#define MODEL_PROCESS_VARIABLE "AAA_COSIM_MODEL_PROCESS"
#define MODEL_PROCESS_IMPORTER "importer"
#define MODEL_PROCESS_HELPER "helper"
/* The helper executable beside the FMU binary, and the symbol it calls in that binary. */
#define HELPER_EXECUTABLE "aaa_cosim_helper"
#define SERVE_SYMBOL "aaa_cosim_serve"

/* 1 when `instance` is a remote instance (its first field says so). */
int remote_is(fmi3Instance instance);

/* Start a helper process for one instance and instantiate there; NULL (logged through `logger`)
 * when it cannot be done. `binary` is this FMU's shared library. */
fmi3Instance remote_instantiate(const char *binary, fmi3String instanceName, fmi3String instantiationToken,
                                fmi3String resourcePath, fmi3Boolean loggingOn,
                                fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logger);

/* The forwarded FMI calls (same arguments as the FMI functions). */
void remote_free_instance(fmi3Instance instance);
fmi3Status remote_set_debug_logging(fmi3Instance, fmi3Boolean, size_t, const fmi3String[]);
fmi3Status remote_enter_initialization_mode(fmi3Instance, fmi3Boolean, fmi3Float64, fmi3Float64, fmi3Boolean,
                                            fmi3Float64);
fmi3Status remote_simple(fmi3Instance instance, int op); /* calls with the instance alone (REMOTE_OP_...) */
fmi3Status remote_get(fmi3Instance, int type, const fmi3ValueReference[], size_t, void *values, size_t nValues);
fmi3Status remote_set(fmi3Instance, int type, const fmi3ValueReference[], size_t, const void *values,
                      size_t nValues);
fmi3Status remote_get_string(fmi3Instance, const fmi3ValueReference[], size_t, fmi3String[], size_t);
fmi3Status remote_set_string(fmi3Instance, const fmi3ValueReference[], size_t, const fmi3String[], size_t);
fmi3Status remote_get_binary(fmi3Instance, const fmi3ValueReference[], size_t, size_t[], fmi3Binary[], size_t);
fmi3Status remote_set_binary(fmi3Instance, const fmi3ValueReference[], size_t, const size_t[], const fmi3Binary[],
                             size_t);
fmi3Status remote_do_step(fmi3Instance, fmi3Float64, fmi3Float64, fmi3Boolean, fmi3Boolean *, fmi3Boolean *,
                          fmi3Boolean *, fmi3Float64 *);
fmi3Status remote_get_state(fmi3Instance, fmi3FMUState *);
fmi3Status remote_set_state(fmi3Instance, fmi3FMUState);
fmi3Status remote_free_state(fmi3Instance, fmi3FMUState *);
fmi3Status remote_state_size(fmi3Instance, fmi3FMUState, size_t *);
fmi3Status remote_serialize_state(fmi3Instance, fmi3FMUState, fmi3Byte[], size_t);
fmi3Status remote_deserialize_state(fmi3Instance, const fmi3Byte[], size_t, fmi3FMUState *);
/* A call this FMU does not support, on a remote instance: logged, fmi3Error. */
fmi3Status remote_not_supported(fmi3Instance, const char *function, const char *why);

/* The calls remote_simple forwards. */
enum {
    REMOTE_OP_EXIT_INITIALIZATION = 1,
    REMOTE_OP_TERMINATE,
    REMOTE_OP_RESET,
    REMOTE_OP_ENTER_CONFIGURATION,
    REMOTE_OP_EXIT_CONFIGURATION,
};

/* The helper's side: serve the channel on file descriptor `fd` until the instance is freed or the
 * importer is gone. Exported from the FMU binary for the helper executable. Returns an exit code. */
__attribute__((visibility("default"))) int aaa_cosim_serve(int fd);

#endif
