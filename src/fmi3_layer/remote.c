/* The model in a helper process (see remote.h for when and why). */
#define _GNU_SOURCE
#include "remote.h"

#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <linux/futex.h>
#include <signal.h>
#include <spawn.h>
#include <stdarg.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "variables.h"

extern char **environ;

/* ---- the channel ---------------------------------------------------------------------------------- */
/* Address space reserved for one instance's channel; a memfd's pages exist only once written, so
 * this costs what the largest message needs (a serialized tissue state is the largest). */
#define CHANNEL_BYTES ((size_t)1 << 30)
#define LOG_BYTES ((size_t)1 << 16)
#define SPIN_NS 50000L     /* how long a side polls before it sleeps: a 1 kHz step stays in the microseconds */
#define ALIVE_CHECK_MS 200 /* how often a waiting importer looks whether its helper still runs */

enum {
    OP_INSTANTIATE = 100, OP_FREE, OP_DEBUG_LOGGING, OP_ENTER_INITIALIZATION, OP_SIMPLE, OP_GET, OP_SET,
    OP_GET_STRING, OP_SET_STRING, OP_GET_BINARY, OP_SET_BINARY, OP_DO_STEP, OP_GET_STATE, OP_SET_STATE,
    OP_FREE_STATE, OP_STATE_SIZE, OP_SERIALIZE, OP_DESERIALIZE,
};

typedef struct {
    _Atomic uint32_t request;  /* incremented by the importer when a request is written */
    _Atomic uint32_t response; /* set to `request` by the helper when the answer is written */
    uint32_t op;
    int32_t status;            /* the fmi3Status of the call */
    uint64_t length;           /* bytes of payload (request, then answer) */
    uint64_t log_length;       /* bytes of log records written during the call */
    unsigned char log[LOG_BYTES];
    unsigned char payload[];
} Channel;

#define PAYLOAD_BYTES (CHANNEL_BYTES - sizeof(Channel))

typedef struct {
    unsigned char *at, *end;
    int overflow;
} Cursor;

static Cursor writer(Channel *ch) { return (Cursor){ch->payload, ch->payload + PAYLOAD_BYTES, 0}; }
static Cursor reader(Channel *ch) { return (Cursor){ch->payload, ch->payload + ch->length, 0}; }

static void put(Cursor *c, const void *data, size_t n) {
    if (c->overflow || (size_t)(c->end - c->at) < n) {
        c->overflow = 1;
        return;
    }
    if (n) memcpy(c->at, data, n);
    c->at += n;
}
static const void *take(Cursor *c, size_t n) {
    if (c->overflow || (size_t)(c->end - c->at) < n) {
        c->overflow = 1;
        return NULL;
    }
    const void *data = c->at;
    c->at += n;
    return data;
}
static void put_u64(Cursor *c, uint64_t v) { put(c, &v, sizeof v); }
static void put_f64(Cursor *c, double v) { put(c, &v, sizeof v); }
static void put_bytes(Cursor *c, const void *data, size_t n) { put_u64(c, n); put(c, data, n); }
static void put_str(Cursor *c, const char *s) { put_bytes(c, s ? s : "", s ? strlen(s) + 1 : 1); }
static uint64_t take_u64(Cursor *c) { const void *p = take(c, 8); uint64_t v = 0; if (p) memcpy(&v, p, 8); return v; }
static double take_f64(Cursor *c) { const void *p = take(c, 8); double v = 0; if (p) memcpy(&v, p, 8); return v; }
static const void *take_bytes(Cursor *c, size_t *n) { *n = take_u64(c); return take(c, *n); }
static const char *take_str(Cursor *c) {
    size_t n;
    const char *s = take_bytes(c, &n);
    return s && n && s[n - 1] == '\0' ? s : (c->overflow = 1, NULL);
}

static long futex(_Atomic uint32_t *word, int op, uint32_t value, const struct timespec *timeout) {
    return syscall(SYS_futex, (uint32_t *)word, op, value, timeout, NULL, 0);
}

static long now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec * 1000000000L + t.tv_nsec;
}

/* Wait until *word != old: poll for SPIN_NS, then sleep on the futex (in slices of `slice_ms` when
 * `still_there` is given, which is asked after each slice). Returns 0, or -1 when it said no. */
static int wait_change(_Atomic uint32_t *word, uint32_t old, int slice_ms, int (*still_there)(void *), void *arg) {
    long until = now_ns() + SPIN_NS;
    while (atomic_load_explicit(word, memory_order_acquire) == old) {
        if (now_ns() < until) {
            __builtin_ia32_pause();
            continue;
        }
        struct timespec slice = {slice_ms / 1000, (slice_ms % 1000) * 1000000L};
        futex(word, FUTEX_WAIT, old, still_there ? &slice : NULL);
        if (atomic_load_explicit(word, memory_order_acquire) == old && still_there && !still_there(arg)) return -1;
    }
    return 0;
}

/* ---- the importer's side ---------------------------------------------------------------------------- */
typedef struct {
    uint32_t kind; /* INSTANCE_REMOTE: first, as in every instance of this FMU */
    Channel *ch;
    pid_t pid;
    int dead;
    char *name;
    fmi3InstanceEnvironment environment;
    fmi3LogMessageCallback logger;
    uint64_t *states; /* the live state handles the helper gave out (to recognise a misplaced one) */
    size_t n_states, capacity_states;
    char *strings;    /* what the last fmi3GetString/GetBinary returned points into this */
} Remote;

int remote_is(fmi3Instance instance) { return instance && *(const uint32_t *)instance == INSTANCE_REMOTE; }

static void say(Remote *r, fmi3Status status, const char *format, ...) {
    if (!r->logger) return;
    char message[2048];
    va_list args;
    va_start(args, format);
    vsnprintf(message, sizeof message, format, args);
    va_end(args);
    r->logger(r->environment, status, status == fmi3Error || status == fmi3Fatal ? "logStatusError" : "logEvents",
              message);
}

static int helper_alive(void *arg) {
    Remote *r = arg;
    int status = 0;
    pid_t ended = waitpid(r->pid, &status, WNOHANG);
    if (ended == r->pid) {
        r->dead = status ? status : -1;
        return 0;
    }
    /* an importer that ignores SIGCHLD has its children reaped for it: ask whether it still exists */
    if (ended < 0 && errno == ECHILD && kill(r->pid, 0) != 0 && errno == ESRCH) {
        r->dead = -1;
        return 0;
    }
    return 1;
}

/* Hand the log records of the call to the importer's logger. */
static void replay_log(Remote *r) {
    Cursor c = {r->ch->log, r->ch->log + r->ch->log_length, 0};
    while (c.at < c.end && !c.overflow) {
        fmi3Status status = (fmi3Status)take_u64(&c);
        const char *category = take_str(&c), *message = take_str(&c);
        if (!c.overflow && r->logger) r->logger(r->environment, status, category, message);
    }
}

/* Send the request written into the payload (`length` bytes) and wait for the answer. */
static fmi3Status call(Remote *r, uint32_t op, Cursor *request) {
    if (r->dead) {
        say(r, fmi3Fatal, "the helper process that ran this instance's model has ended; free the instance");
        return fmi3Fatal;
    }
    if (request->overflow) {
        say(r, fmi3Error, "the call's data exceed the %zu MiB channel to the model's helper process",
            (size_t)(PAYLOAD_BYTES >> 20));
        return fmi3Error;
    }
    Channel *ch = r->ch;
    ch->op = op;
    ch->length = (uint64_t)(request->at - ch->payload);
    ch->log_length = 0;
    uint32_t number = atomic_load(&ch->request) + 1;
    atomic_store_explicit(&ch->request, number, memory_order_release);
    futex(&ch->request, FUTEX_WAKE, 1, NULL);
    if (wait_change(&ch->response, number - 1, ALIVE_CHECK_MS, helper_alive, r) != 0) {
        replay_log(r);
        say(r, fmi3Fatal, "the helper process that ran this instance's model ended during the call (%s %d); "
            "free the instance", WIFSIGNALED(r->dead) ? "signal" : "exit status",
            WIFSIGNALED(r->dead) ? WTERMSIG(r->dead) : WEXITSTATUS(r->dead));
        return fmi3Fatal;
    }
    replay_log(r);
    return (fmi3Status)ch->status;
}

static void remember_state(Remote *r, uint64_t handle) {
    for (size_t i = 0; i < r->n_states; i++)
        if (r->states[i] == handle) return;
    if (r->n_states == r->capacity_states) {
        size_t capacity = r->capacity_states ? 2 * r->capacity_states : 8;
        uint64_t *grown = realloc(r->states, capacity * sizeof *grown);
        if (!grown) return;
        r->states = grown;
        r->capacity_states = capacity;
    }
    r->states[r->n_states++] = handle;
}

static int forget_state(Remote *r, uint64_t handle) {
    for (size_t i = 0; i < r->n_states; i++) {
        if (r->states[i] == handle) {
            r->states[i] = r->states[--r->n_states];
            return 1;
        }
    }
    return 0;
}

/* The helper executable beside `binary`, made executable (importers extract without modes). */
static int helper_path(const char *binary, char *path, size_t size) {
    snprintf(path, size, "%s", binary);
    char *slash = strrchr(path, '/');
    if (!slash) return -1;
    snprintf(slash + 1, size - (size_t)(slash + 1 - path), "%s", HELPER_EXECUTABLE);
    struct stat st;
    if (stat(path, &st) != 0) return -1;
    if (!(st.st_mode & S_IXUSR)) chmod(path, st.st_mode | S_IXUSR | S_IXGRP | S_IXOTH);
    return 0;
}

static void free_remote(Remote *r) {
    if (r->ch) munmap(r->ch, CHANNEL_BYTES);
    free(r->states);
    free(r->strings);
    free(r->name);
    free(r);
}

fmi3Instance remote_instantiate(const char *binary, fmi3String instanceName, fmi3String instantiationToken,
                                fmi3String resourcePath, fmi3Boolean loggingOn,
                                fmi3InstanceEnvironment instanceEnvironment, fmi3LogMessageCallback logger) {
    Remote *r = calloc(1, sizeof *r);
    if (!r) return NULL;
    r->kind = INSTANCE_REMOTE;
    r->environment = instanceEnvironment;
    r->logger = logger;
    r->name = strdup(instanceName ? instanceName : "");
    char helper[4096];
    if (helper_path(binary, helper, sizeof helper) != 0) {
        say(r, fmi3Error, "fmi3InstantiateCoSimulation: the model must run in a helper process here, and the "
            "helper %s is missing: the FMU is damaged; use an intact copy", HELPER_EXECUTABLE);
        free_remote(r);
        return NULL;
    }
    int fd = memfd_create("aaa-cosim-channel", MFD_CLOEXEC);
    if (fd < 0 || ftruncate(fd, (off_t)CHANNEL_BYTES) != 0) {
        say(r, fmi3Error, "fmi3InstantiateCoSimulation: cannot make the shared memory for the model's helper "
            "process (%s)", strerror(errno));
        if (fd >= 0) close(fd);
        free_remote(r);
        return NULL;
    }
    r->ch = mmap(NULL, CHANNEL_BYTES, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (r->ch == MAP_FAILED) {
        r->ch = NULL;
        say(r, fmi3Error, "fmi3InstantiateCoSimulation: cannot map the shared memory (%s)", strerror(errno));
        close(fd);
        free_remote(r);
        return NULL;
    }
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_adddup2(&actions, fd, 3); /* the helper finds its channel at descriptor 3 */
    char *argv[] = {helper, (char *)binary, "3", NULL};
    int failed = posix_spawn(&r->pid, helper, &actions, NULL, argv, environ);
    posix_spawn_file_actions_destroy(&actions);
    close(fd);
    if (failed) {
        say(r, fmi3Error, "fmi3InstantiateCoSimulation: cannot start the model's helper process %s (%s)", helper,
            strerror(failed));
        free_remote(r);
        return NULL;
    }
    Cursor c = writer(r->ch);
    put_str(&c, instanceName);
    put_str(&c, instantiationToken);
    put_str(&c, resourcePath);
    put_u64(&c, loggingOn);
    if (call(r, OP_INSTANTIATE, &c) != fmi3OK) {
        kill(r->pid, SIGKILL);
        waitpid(r->pid, NULL, 0);
        free_remote(r);
        return NULL;
    }
    return r;
}

void remote_free_instance(fmi3Instance instance) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    call(r, OP_FREE, &c);
    if (!r->dead) {
        int status;
        for (int i = 0; i < 500 && waitpid(r->pid, &status, WNOHANG) == 0; i++) usleep(10000);
        if (waitpid(r->pid, &status, WNOHANG) == 0) { /* the helper should have ended: end it */
            kill(r->pid, SIGKILL);
            waitpid(r->pid, NULL, 0);
        }
    }
    free_remote(r);
}

fmi3Status remote_set_debug_logging(fmi3Instance instance, fmi3Boolean on, size_t n, const fmi3String categories[]) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, on);
    put_u64(&c, categories ? n : 0);
    for (size_t i = 0; categories && i < n; i++) put_str(&c, categories[i]);
    return call(r, OP_DEBUG_LOGGING, &c);
}

fmi3Status remote_enter_initialization_mode(fmi3Instance instance, fmi3Boolean tolerance_defined, fmi3Float64 tolerance,
                                            fmi3Float64 start, fmi3Boolean stop_defined, fmi3Float64 stop) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, tolerance_defined);
    put_f64(&c, tolerance);
    put_f64(&c, start);
    put_u64(&c, stop_defined);
    put_f64(&c, stop);
    return call(r, OP_ENTER_INITIALIZATION, &c);
}

fmi3Status remote_simple(fmi3Instance instance, int op) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)op);
    return call(r, OP_SIMPLE, &c);
}

/* The start of every get and set request: the value references, nValues, whether values are given
 * (read back by take_access). */
static void put_access(Cursor *c, const fmi3ValueReference vrs[], size_t n_vrs, size_t n_values, int with_values) {
    put_u64(c, vrs ? n_vrs : 0);
    if (vrs) put(c, vrs, n_vrs * sizeof *vrs);
    put_u64(c, n_values);
    put_u64(c, (uint64_t)with_values);
}

static size_t type_size(int type) {
    switch (type) {
        case T_FLOAT64: case T_INT64: case T_UINT64: return 8;
        case T_FLOAT32: case T_INT32: case T_UINT32: return 4;
        case T_INT16: case T_UINT16: return 2;
        case T_INT8: case T_UINT8: return 1;
        case T_BOOLEAN: return sizeof(fmi3Boolean);
        default: return 0;
    }
}

fmi3Status remote_get(fmi3Instance instance, int type, const fmi3ValueReference vrs[], size_t n_vrs, void *values,
                      size_t n_values) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)type);
    put_access(&c, vrs, n_vrs, n_values, values != NULL);
    fmi3Status status = call(r, OP_GET, &c);
    if ((status == fmi3OK || status == fmi3Warning) && values) {
        Cursor answer = reader(r->ch);
        size_t n;
        const void *data = take_bytes(&answer, &n);
        if (!data || n != n_values * type_size(type)) {
            say(r, fmi3Error, "the helper process answered a get with %zu bytes for %zu values", n, n_values);
            return fmi3Error;
        }
        memcpy(values, data, n);
    }
    return status;
}

fmi3Status remote_set(fmi3Instance instance, int type, const fmi3ValueReference vrs[], size_t n_vrs,
                      const void *values, size_t n_values) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)type);
    put_access(&c, vrs, n_vrs, n_values, values != NULL);
    if (values) put(&c, values, n_values * type_size(type));
    return call(r, OP_SET, &c);
}

/* Copy the answer's byte strings into the instance (valid until its next get), pointed to by out[]. */
static int keep_answer(Remote *r, Cursor *answer, size_t count, const void *out[], size_t sizes[]) {
    size_t total = (size_t)(answer->end - answer->at);
    char *kept = malloc(total ? total : 1);
    if (!kept) return -1;
    memcpy(kept, answer->at, total);
    free(r->strings);
    r->strings = kept;
    Cursor c = {(unsigned char *)kept, (unsigned char *)kept + total, 0};
    for (size_t i = 0; i < count; i++) {
        size_t n;
        out[i] = take_bytes(&c, &n);
        if (sizes) sizes[i] = n;
    }
    return c.overflow ? -1 : 0;
}

fmi3Status remote_get_string(fmi3Instance instance, const fmi3ValueReference vrs[], size_t n_vrs, fmi3String values[],
                             size_t n_values) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_access(&c, vrs, n_vrs, n_values, values != NULL);
    fmi3Status status = call(r, OP_GET_STRING, &c);
    if ((status == fmi3OK || status == fmi3Warning) && values) {
        Cursor answer = reader(r->ch);
        if (keep_answer(r, &answer, n_values, (const void **)values, NULL) != 0) return fmi3Error;
    }
    return status;
}

fmi3Status remote_set_string(fmi3Instance instance, const fmi3ValueReference vrs[], size_t n_vrs,
                             const fmi3String values[], size_t n_values) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_access(&c, vrs, n_vrs, values ? n_values : 0, values != NULL);
    for (size_t i = 0; values && i < n_values; i++) {
        put_u64(&c, values[i] != NULL);
        put_str(&c, values[i]);
    }
    return call(r, OP_SET_STRING, &c);
}

fmi3Status remote_get_binary(fmi3Instance instance, const fmi3ValueReference vrs[], size_t n_vrs, size_t sizes[],
                             fmi3Binary values[], size_t n_values) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_access(&c, vrs, n_vrs, n_values, values != NULL && sizes != NULL);
    fmi3Status status = call(r, OP_GET_BINARY, &c);
    if ((status == fmi3OK || status == fmi3Warning) && values && sizes) {
        Cursor answer = reader(r->ch);
        if (keep_answer(r, &answer, n_values, (const void **)values, sizes) != 0) return fmi3Error;
    }
    return status;
}

fmi3Status remote_set_binary(fmi3Instance instance, const fmi3ValueReference vrs[], size_t n_vrs, const size_t sizes[],
                             const fmi3Binary values[], size_t n_values) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_access(&c, vrs, n_vrs, values && sizes ? n_values : 0, values != NULL && sizes != NULL);
    for (size_t i = 0; values && sizes && i < n_values; i++) put_bytes(&c, values[i], values[i] ? sizes[i] : 0);
    return call(r, OP_SET_BINARY, &c);
}

fmi3Status remote_do_step(fmi3Instance instance, fmi3Float64 t, fmi3Float64 h, fmi3Boolean no_set_prior,
                          fmi3Boolean *event, fmi3Boolean *terminate, fmi3Boolean *early, fmi3Float64 *last) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_f64(&c, t);
    put_f64(&c, h);
    put_u64(&c, no_set_prior);
    fmi3Status status = call(r, OP_DO_STEP, &c);
    Cursor answer = reader(r->ch);
    uint64_t flags = take_u64(&answer);
    double last_time = take_f64(&answer);
    if (status == fmi3Fatal || answer.overflow) return status;
    if (event) *event = (flags & 1) != 0;
    if (terminate) *terminate = (flags & 2) != 0;
    if (early) *early = (flags & 4) != 0;
    if (last) *last = last_time;
    return status;
}

fmi3Status remote_get_state(fmi3Instance instance, fmi3FMUState *state) {
    Remote *r = instance;
    if (!state) return remote_not_supported(instance, "fmi3GetFMUState", "FMUState is NULL");
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)(uintptr_t)*state);
    fmi3Status status = call(r, OP_GET_STATE, &c);
    if (status == fmi3OK) {
        Cursor answer = reader(r->ch);
        uint64_t handle = take_u64(&answer);
        remember_state(r, handle);
        *state = (fmi3FMUState)(uintptr_t)handle;
    }
    return status;
}

fmi3Status remote_set_state(fmi3Instance instance, fmi3FMUState state) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)(uintptr_t)state);
    return call(r, OP_SET_STATE, &c);
}

fmi3Status remote_free_state(fmi3Instance instance, fmi3FMUState *state) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    /* the state itself where a pointer to it is due (fmusim v0.0.39): recognised, never dereferenced */
    int misplaced = state && forget_state(r, (uint64_t)(uintptr_t)state);
    uint64_t handle = misplaced ? (uint64_t)(uintptr_t)state : state ? (uint64_t)(uintptr_t)*state : 0;
    put_u64(&c, state != NULL);
    put_u64(&c, misplaced);
    put_u64(&c, handle);
    fmi3Status status = call(r, OP_FREE_STATE, &c);
    if (!misplaced && state && *state && status == fmi3OK) {
        forget_state(r, handle);
        *state = NULL;
    }
    return status;
}

fmi3Status remote_state_size(fmi3Instance instance, fmi3FMUState state, size_t *size) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)(uintptr_t)state);
    fmi3Status status = call(r, OP_STATE_SIZE, &c);
    if (status == fmi3OK && size) {
        Cursor answer = reader(r->ch);
        *size = take_u64(&answer);
    }
    return status;
}

fmi3Status remote_serialize_state(fmi3Instance instance, fmi3FMUState state, fmi3Byte bytes[], size_t size) {
    Remote *r = instance;
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)(uintptr_t)state);
    put_u64(&c, size);
    put_u64(&c, bytes != NULL);
    fmi3Status status = call(r, OP_SERIALIZE, &c);
    if (status == fmi3OK && bytes) {
        Cursor answer = reader(r->ch);
        size_t n;
        const void *data = take_bytes(&answer, &n);
        if (!data || n != size) return fmi3Error;
        memcpy(bytes, data, n);
    }
    return status;
}

fmi3Status remote_deserialize_state(fmi3Instance instance, const fmi3Byte bytes[], size_t size, fmi3FMUState *state) {
    Remote *r = instance;
    if (!state) return remote_not_supported(instance, "fmi3DeserializeFMUState", "FMUState is NULL");
    Cursor c = writer(r->ch);
    put_u64(&c, (uint64_t)(uintptr_t)*state);
    put_u64(&c, bytes != NULL);
    put_bytes(&c, bytes, bytes ? size : 0);
    fmi3Status status = call(r, OP_DESERIALIZE, &c);
    if (status == fmi3OK) {
        Cursor answer = reader(r->ch);
        uint64_t handle = take_u64(&answer);
        remember_state(r, handle);
        *state = (fmi3FMUState)(uintptr_t)handle;
    }
    return status;
}

fmi3Status remote_not_supported(fmi3Instance instance, const char *function, const char *why) {
    say((Remote *)instance, fmi3Error, "%s: not supported by this FMU (%s)", function, why);
    return fmi3Error;
}

/* ---- the helper's side -------------------------------------------------------------------------------- */
static Channel *served;

static void log_into_channel(fmi3InstanceEnvironment environment, fmi3Status status, fmi3String category,
                             fmi3String message) {
    (void)environment;
    Cursor c = {served->log + served->log_length, served->log + LOG_BYTES, 0};
    unsigned char *start = c.at;
    put_u64(&c, (uint64_t)status);
    put_str(&c, category);
    put_str(&c, message);
    if (!c.overflow) served->log_length += (uint64_t)(c.at - start);
}

/* What put_access wrote. */
typedef struct {
    const fmi3ValueReference *vrs;
    size_t n_vrs, n_values;
    int with_values;
} Access;

static Access take_access(Cursor *in) {
    Access a;
    a.n_vrs = take_u64(in);
    a.vrs = a.n_vrs ? take(in, a.n_vrs * sizeof *a.vrs) : NULL;
    a.n_values = take_u64(in);
    a.with_values = (int)take_u64(in);
    return a;
}

static fmi3Status serve_get(fmi3Instance inst, Cursor *in, Cursor *out) {
    int type = (int)take_u64(in);
    Access a = take_access(in);
    size_t size = type_size(type);
    if (in->overflow || !size || a.n_values > (PAYLOAD_BYTES - 16) / size) return fmi3Error;
    const fmi3ValueReference *vrs = a.vrs;
    size_t n_vrs = a.n_vrs, n_values = a.n_values;
    void *values = a.with_values ? out->at + 8 : NULL; /* read into the answer, after its length */
    fmi3Status status;
    switch (type) {
#define GET(T, Name) case T: status = fmi3Get##Name(inst, vrs, n_vrs, values, n_values); break;
        GET(T_FLOAT64, Float64) GET(T_FLOAT32, Float32) GET(T_INT8, Int8) GET(T_UINT8, UInt8) GET(T_INT16, Int16)
        GET(T_UINT16, UInt16) GET(T_INT32, Int32) GET(T_UINT32, UInt32) GET(T_INT64, Int64) GET(T_UINT64, UInt64)
        GET(T_BOOLEAN, Boolean)
#undef GET
        default: status = fmi3Error;
    }
    size_t answered = values && (status == fmi3OK || status == fmi3Warning) ? n_values * size : 0;
    put_u64(out, answered);
    out->at += answered;
    return status;
}

static fmi3Status serve_set(fmi3Instance inst, Cursor *in) {
    int type = (int)take_u64(in);
    Access a = take_access(in);
    size_t size = type_size(type);
    if (in->overflow || !size || a.n_values > PAYLOAD_BYTES / size) return fmi3Error;
    const void *values = a.with_values ? take(in, a.n_values * size) : NULL;
    if (in->overflow) return fmi3Error;
    const fmi3ValueReference *vrs = a.vrs;
    size_t n_vrs = a.n_vrs, n_values = a.n_values;
    switch (type) {
#define SET(T, Name) case T: return fmi3Set##Name(inst, vrs, n_vrs, values, n_values);
        SET(T_FLOAT64, Float64) SET(T_FLOAT32, Float32) SET(T_INT8, Int8) SET(T_UINT8, UInt8) SET(T_INT16, Int16)
        SET(T_UINT16, UInt16) SET(T_INT32, Int32) SET(T_UINT32, UInt32) SET(T_INT64, Int64) SET(T_UINT64, UInt64)
        SET(T_BOOLEAN, Boolean)
#undef SET
        default: return fmi3Error;
    }
}

/* One request on the helper's side: runs the FMI call on its (local) instance. */
static fmi3Status serve_one(fmi3Instance *inst, uint32_t op, Cursor *in, Cursor *out) {
    switch (op) {
        case OP_INSTANTIATE: {
            const char *name = take_str(in), *token = take_str(in), *resources = take_str(in);
            int logging = (int)take_u64(in);
            if (in->overflow) return fmi3Error;
            *inst = fmi3InstantiateCoSimulation(name, token, resources, fmi3False, logging, fmi3False, fmi3False,
                                                NULL, 0, NULL, log_into_channel, NULL);
            return *inst ? fmi3OK : fmi3Error;
        }
        case OP_DEBUG_LOGGING: {
            int on = (int)take_u64(in);
            size_t n = take_u64(in);
            if (n > 64) return fmi3Error;
            fmi3String categories[64];
            for (size_t i = 0; i < n; i++) categories[i] = take_str(in);
            return in->overflow ? fmi3Error : fmi3SetDebugLogging(*inst, on, n, n ? categories : NULL);
        }
        case OP_ENTER_INITIALIZATION: {
            int tolerance_defined = (int)take_u64(in);
            double tolerance = take_f64(in), start = take_f64(in);
            int stop_defined = (int)take_u64(in);
            double stop = take_f64(in);
            return fmi3EnterInitializationMode(*inst, tolerance_defined, tolerance, start, stop_defined, stop);
        }
        case OP_SIMPLE:
            switch ((int)take_u64(in)) {
                case REMOTE_OP_EXIT_INITIALIZATION: return fmi3ExitInitializationMode(*inst);
                case REMOTE_OP_TERMINATE: return fmi3Terminate(*inst);
                case REMOTE_OP_RESET: return fmi3Reset(*inst);
                case REMOTE_OP_ENTER_CONFIGURATION: return fmi3EnterConfigurationMode(*inst);
                case REMOTE_OP_EXIT_CONFIGURATION: return fmi3ExitConfigurationMode(*inst);
                default: return fmi3Error;
            }
        case OP_GET: return serve_get(*inst, in, out);
        case OP_SET: return serve_set(*inst, in);
        case OP_GET_STRING: case OP_GET_BINARY: {
            Access a = take_access(in);
            size_t n_values = a.n_values;
            if (in->overflow || n_values > PAYLOAD_BYTES / 16) return fmi3Error;
            const void **values = a.with_values ? calloc(n_values + 1, sizeof *values) : NULL;
            size_t *sizes = a.with_values ? calloc(n_values + 1, sizeof *sizes) : NULL;
            fmi3Status status = op == OP_GET_STRING
                ? fmi3GetString(*inst, a.vrs, a.n_vrs, (fmi3String *)values, n_values)
                : fmi3GetBinary(*inst, a.vrs, a.n_vrs, sizes, (fmi3Binary *)values, n_values);
            for (size_t i = 0; values && (status == fmi3OK || status == fmi3Warning) && i < n_values; i++) {
                if (op == OP_GET_STRING) put_str(out, values[i]);
                else put_bytes(out, values[i], values[i] ? sizes[i] : 0);
            }
            free(values);
            free(sizes);
            return status;
        }
        case OP_SET_STRING: case OP_SET_BINARY: {
            Access a = take_access(in);
            size_t n_values = a.n_values;
            if (in->overflow || n_values > PAYLOAD_BYTES / 16) return fmi3Error;
            const void **values = a.with_values ? calloc(n_values + 1, sizeof *values) : NULL;
            size_t *sizes = a.with_values ? calloc(n_values + 1, sizeof *sizes) : NULL;
            for (size_t i = 0; values && i < n_values; i++) {
                if (op == OP_SET_STRING) {
                    int present = (int)take_u64(in);
                    const char *text = take_str(in);
                    values[i] = present ? text : NULL;
                } else {
                    values[i] = take_bytes(in, &sizes[i]);
                }
            }
            fmi3Status status = in->overflow ? fmi3Error
                : op == OP_SET_STRING ? fmi3SetString(*inst, a.vrs, a.n_vrs, (const fmi3String *)values, n_values)
                : fmi3SetBinary(*inst, a.vrs, a.n_vrs, sizes, (const fmi3Binary *)values, n_values);
            free(values);
            free(sizes);
            return status;
        }
        case OP_DO_STEP: {
            double t = take_f64(in), h = take_f64(in);
            int no_set_prior = (int)take_u64(in);
            fmi3Boolean event = fmi3False, terminate = fmi3False, early = fmi3False;
            fmi3Float64 last = t;
            fmi3Status status = fmi3DoStep(*inst, t, h, no_set_prior, &event, &terminate, &early, &last);
            put_u64(out, (uint64_t)(event ? 1 : 0) | (terminate ? 2 : 0) | (early ? 4 : 0));
            put_f64(out, last);
            return status;
        }
        case OP_GET_STATE: case OP_DESERIALIZE: {
            fmi3FMUState state = (fmi3FMUState)(uintptr_t)take_u64(in);
            fmi3Status status;
            if (op == OP_GET_STATE) {
                status = fmi3GetFMUState(*inst, &state);
            } else {
                int with_bytes = (int)take_u64(in);
                size_t size;
                const void *bytes = take_bytes(in, &size);
                status = in->overflow ? fmi3Error
                                      : fmi3DeserializeFMUState(*inst, with_bytes ? bytes : NULL, size, &state);
            }
            put_u64(out, (uint64_t)(uintptr_t)state);
            return status;
        }
        case OP_SET_STATE: return fmi3SetFMUState(*inst, (fmi3FMUState)(uintptr_t)take_u64(in));
        case OP_FREE_STATE: {
            int with_pointer = (int)take_u64(in), misplaced = (int)take_u64(in);
            fmi3FMUState state = (fmi3FMUState)(uintptr_t)take_u64(in);
            if (!with_pointer) return fmi3FreeFMUState(*inst, NULL);
            /* a misplaced state is handed on as it came: the local layer recognises and frees it */
            return fmi3FreeFMUState(*inst, misplaced ? (fmi3FMUState *)state : &state);
        }
        case OP_STATE_SIZE: {
            size_t size = 0;
            fmi3Status status = fmi3SerializedFMUStateSize(*inst, (fmi3FMUState)(uintptr_t)take_u64(in), &size);
            put_u64(out, size);
            return status;
        }
        case OP_SERIALIZE: {
            fmi3FMUState state = (fmi3FMUState)(uintptr_t)take_u64(in);
            size_t size = take_u64(in);
            int with_bytes = (int)take_u64(in);
            if (in->overflow || size > PAYLOAD_BYTES - 16) return fmi3Error;
            unsigned char *bytes = out->at + 8; /* written in place, after its length */
            fmi3Status status = fmi3SerializeFMUState(*inst, state, with_bytes ? bytes : NULL, size);
            put_u64(out, status == fmi3OK && with_bytes ? size : 0);
            if (status == fmi3OK && with_bytes) out->at += size;
            return status;
        }
        default: return fmi3Error;
    }
}

static pid_t importer;

static int importer_alive(void *arg) {
    (void)arg;
    return getppid() == importer;
}

int aaa_cosim_serve(int fd) {
    /* The importer's end is noticed by the parent changing (checked at least once a second while
     * idle), not by PR_SET_PDEATHSIG: that fires when the importer's *thread* that started the
     * helper ends, which a pool thread of the importer may do while the instance lives on. */
    importer = getppid();
    served = mmap(NULL, CHANNEL_BYTES, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (served == MAP_FAILED) return 2;
    close(fd);
    fmi3Instance inst = NULL;
    uint32_t done = atomic_load(&served->response);
    for (;;) {
        if (wait_change(&served->request, done, 1000, importer_alive, NULL) != 0) return 3;
        uint32_t number = atomic_load_explicit(&served->request, memory_order_acquire);
        uint32_t op = served->op;
        /* the request is read from the payload while the answer is written into it: a copy */
        size_t length = served->length;
        unsigned char *copy = malloc(length ? length : 1);
        if (!copy) return 4;
        memcpy(copy, served->payload, length);
        Cursor in = {copy, copy + length, 0};
        Cursor out = writer(served);
        fmi3Status status;
        if (op == OP_FREE) {
            if (inst) fmi3FreeInstance(inst);
            inst = NULL;
            status = fmi3OK;
        } else if (!inst && op != OP_INSTANTIATE) {
            status = fmi3Error;
        } else {
            status = serve_one(&inst, op, &in, &out);
        }
        free(copy);
        served->status = out.overflow ? fmi3Error : status;
        served->length = out.overflow ? 0 : (uint64_t)(out.at - served->payload);
        if (out.overflow)
            log_into_channel(NULL, fmi3Error, "logStatusError", "the answer exceeds the channel to the importer");
        done = number;
        atomic_store_explicit(&served->response, number, memory_order_release);
        futex(&served->response, FUTEX_WAKE, 1, NULL);
        if (op == OP_FREE || (op == OP_INSTANTIATE && !inst)) return 0;
    }
}
