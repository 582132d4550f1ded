/* A small FMI 3.0 Co-Simulation importer in plain C (no Python in it), for the tests.
 *
 * It does what any importer does: extracts the .fmu (a zip), reads modelDescription.xml, loads
 * binaries/x86_64-linux/<modelIdentifier>.so, instantiates, initializes, steps with inputs, reads
 * outputs, and frees everything. Optionally it saves the FMU state halfway, serializes and
 * deserializes it, replays the second half from it and checks the outputs are bit-identical.
 *
 * usage: fmu_host FMU WORKDIR STEPS STEP_SIZE [options]
 *   --input NAME:COUNT=VALUE   set COUNT Float64 values of input NAME to VALUE*(1 + k/STEPS) at step k
 *   --output NAME:COUNT        print the COUNT Float64 values of NAME after the last step (%.17g)
 *   --param NAME:COUNT=VALUE   set COUNT Float64 values of parameter NAME before initialization
 *   --state                    save, serialize, restore and replay the second half
 *   --final-state-file PATH    after the last step, save the FMU state to PATH as fmusim v0.0.39 does
 *                              (get, serialize, write, then fmi3FreeFMUState(instance, state): the state
 *                              itself where the standard passes a pointer to it); each call must return
 *                              fmi3OK, or fmusim would stop there
 *   --initial-state-file PATH  right after instantiation, restore the FMU state from PATH as fmusim does
 *                              (read, deserialize, set, free the same way) and skip initialization
 *   --from-step K              start at step K (time K*STEP_SIZE): a run that continues a saved state
 *   --stop-after K             end after step K-1 (the inputs still ramp over STEPS): a run to save from
 *   --misuse                   also make calls that must be refused (fmi3DoStep and fmi3Terminate before
 *                              initialization, a NaN input halfway) and check they return fmi3Error
 * Exit status 0 when every call succeeded and every misuse was refused.
 *
 * usage: fmu_host --serve FMU WORKDIR
 *   runs the FMI calls read from stdin, one a line, and answers each on stdout (the fuzzers'
 *   scripted sequences, tests/fuzz_hosts.py, which speaks the same protocol through FMPy):
 *     instantiate | free | enter_init | exit_init | enter_config | exit_config | terminate | reset
 *     step T H | set TYPE N VR[,VR..] V.. | get TYPE N VR[,VR..]
 *     get_state | set_state | free_state | roundtrip_state | stale_state | damaged_state | quit
 *   (stale_state: a state freed, then set and freed through a copy of its handle; damaged_state: a
 *   state serialized, one bit flipped, deserialized: both must be refused)
 *   TYPE is f64, i32, u64, bool or str (strings percent-encoded); N is nValues (the buffer always
 *   holds at least N values). Each answer is the lines the FMU logged during the call,
 *   "L <status> <message>", then "R <status> [values]" (values of a get that returned OK or
 *   Warning; lastSuccessfulTime of a step). Exit status 0 after "quit" or the end of input.
 */
#include <dlfcn.h>
#include <errno.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <zlib.h>

#include "fmi3Functions.h"

#define MAX_PORTS 8

static void die(const char *message, const char *detail) {
    fprintf(stderr, "fmu_host: %s%s%s\n", message, detail ? ": " : "", detail ? detail : "");
    exit(2);
}

/* ---- zip extraction (stored and deflated entries) ----------------------------------------------- */
static unsigned read16(const unsigned char *p) { return p[0] | (p[1] << 8); }
static unsigned long read32(const unsigned char *p) {
    return (unsigned long)p[0] | ((unsigned long)p[1] << 8) | ((unsigned long)p[2] << 16) | ((unsigned long)p[3] << 24);
}

static void make_dirs(char *path) {
    for (char *p = path + 1; *p; p++) {
        if (*p == '/') {
            *p = '\0';
            if (mkdir(path, 0755) != 0 && errno != EEXIST) die("cannot create folder", path);
            *p = '/';
        }
    }
}

static void extract(const char *zip_path, const char *dest) {
    FILE *f = fopen(zip_path, "rb");
    if (!f) die("cannot open", zip_path);
    fseek(f, 0, SEEK_END);
    long size = ftell(f);
    fseek(f, 0, SEEK_SET);
    unsigned char *zip = malloc((size_t)size);
    if (!zip || fread(zip, 1, (size_t)size, f) != (size_t)size) die("cannot read", zip_path);
    fclose(f);
    long end = size - 22;
    while (end >= 0 && read32(zip + end) != 0x06054b50UL) end--;
    if (end < 0) die("not a zip file", zip_path);
    unsigned entries = read16(zip + end + 10);
    unsigned long offset = read32(zip + end + 16);
    for (unsigned i = 0; i < entries; i++) {
        const unsigned char *c = zip + offset;
        if (read32(c) != 0x02014b50UL) die("bad central directory", zip_path);
        unsigned method = read16(c + 10);
        unsigned long compressed = read32(c + 20), uncompressed = read32(c + 24);
        unsigned name_length = read16(c + 28), extra_length = read16(c + 30), comment_length = read16(c + 32);
        unsigned long local = read32(c + 42);
        char path[4096];
        snprintf(path, sizeof path, "%s/%.*s", dest, (int)name_length, (const char *)(c + 46));
        offset += 46 + name_length + extra_length + comment_length;
        make_dirs(path);
        if (path[strlen(path) - 1] == '/') continue;
        const unsigned char *l = zip + local;
        const unsigned char *data = l + 30 + read16(l + 26) + read16(l + 28);
        unsigned char *out = malloc(uncompressed ? uncompressed : 1);
        if (!out) die("out of memory", NULL);
        if (method == 0) {
            memcpy(out, data, uncompressed);
        } else if (method == 8) {
            z_stream stream;
            memset(&stream, 0, sizeof stream);
            stream.next_in = (unsigned char *)data;
            stream.avail_in = (uInt)compressed;
            stream.next_out = out;
            stream.avail_out = (uInt)uncompressed;
            if (inflateInit2(&stream, -MAX_WBITS) != Z_OK || inflate(&stream, Z_FINISH) != Z_STREAM_END)
                die("cannot inflate", path);
            inflateEnd(&stream);
        } else {
            die("unsupported zip compression in", path);
        }
        FILE *o = fopen(path, "wb");
        if (!o || fwrite(out, 1, uncompressed, o) != uncompressed) die("cannot write", path);
        fclose(o);
        free(out);
    }
    free(zip);
}

/* ---- the model description (just what this host needs) ------------------------------------------ */
static char *read_text(const char *path) {
    FILE *f = fopen(path, "rb");
    if (!f) die("cannot open", path);
    fseek(f, 0, SEEK_END);
    long size = ftell(f);
    fseek(f, 0, SEEK_SET);
    char *text = malloc((size_t)size + 1);
    if (!text || fread(text, 1, (size_t)size, f) != (size_t)size) die("cannot read", path);
    text[size] = '\0';
    fclose(f);
    return text;
}

static void attribute(const char *text, const char *element_start, const char *name, char *value, size_t size) {
    const char *element = strstr(text, element_start);
    if (!element) die("model description has no", element_start);
    char key[128];
    snprintf(key, sizeof key, " %s=\"", name);
    const char *end = strchr(element, '>');
    const char *found = strstr(element, key);
    if (!found || (end && found > end)) die("model description element has no attribute", name);
    found += strlen(key);
    size_t length = strcspn(found, "\"");
    if (length >= size) die("attribute too long", name);
    memcpy(value, found, length);
    value[length] = '\0';
}

static fmi3ValueReference value_reference(const char *text, const char *variable) {
    char start[256], value[64];
    snprintf(start, sizeof start, " name=\"%s\"", variable);
    const char *element = strstr(text, start);
    if (!element) die("no variable", variable);
    while (element > text && *element != '<') element--;
    char prefix[300];
    size_t n = strcspn(element, " ");
    snprintf(prefix, sizeof prefix, "%.*s%s", (int)n, element, start);
    attribute(element, prefix, "valueReference", value, sizeof value);
    return (fmi3ValueReference)strtoul(value, NULL, 10);
}

/* ---- the run --------------------------------------------------------------------------------------- */
typedef struct {
    char name[128];
    size_t count;
    double value;
    fmi3ValueReference vr;
    double *buffer;
} Port;

static int failures = 0;

static void logger(fmi3InstanceEnvironment env, fmi3Status status, fmi3String category, fmi3String message) {
    (void)env;
    fprintf(stderr, "[%s] %s\n", category, message);
    if (status >= fmi3Error) failures++;
}

#define LOAD(name) name##TYPE *name = (name##TYPE *)dlsym(library, #name); if (!name) die("missing symbol", #name)
/* An error status ends the run as an importer must: no further calls but fmi3FreeInstance (none
 * after fmi3Fatal), the library unloaded, and a normal exit that reports the status on stdout. */
#define CHECK(call) do { fmi3Status s_ = (call); if (s_ > fmi3Warning) { \
    printf("run ended: %s returned %d\n", #call, s_); ended = s_; goto end; } } while (0)
/* fmusim's CALL: anything but fmi3OK stops it */
#define FMUSIM_CALL(call) do { fmi3Status s_ = (call); if (s_ != fmi3OK) { \
    printf("fmusim would stop: %s returned %d\n", #call, s_); failures++; \
    ended = s_ > fmi3Warning ? s_ : fmi3Error; goto end; } } while (0)

static int serve(const char *fmu, const char *work);

int main(int argc, char **argv) {
    if (argc == 4 && strcmp(argv[1], "--serve") == 0) return serve(argv[2], argv[3]);
    if (argc < 5) die("usage: fmu_host FMU WORKDIR STEPS STEP_SIZE [--input N:C=V] [--output N:C] [--state]", NULL);
    const char *fmu = argv[1], *work = argv[2];
    long steps = strtol(argv[3], NULL, 10);
    double h = strtod(argv[4], NULL);
    Port inputs[MAX_PORTS], outputs[MAX_PORTS];
    int n_inputs = 0, n_outputs = 0, n_params = 0, with_state = 0, misuse = 0;
    const char *final_state_file = NULL, *initial_state_file = NULL;
    long from_step = 0, stop_after = 0;
    Port params[MAX_PORTS];
    fmi3Status ended = fmi3OK;
    for (int i = 5; i < argc; i++) {
        if (strcmp(argv[i], "--state") == 0) {
            with_state = 1;
        } else if (strcmp(argv[i], "--misuse") == 0) {
            misuse = 1;
        } else if (i + 1 < argc && strcmp(argv[i], "--final-state-file") == 0) {
            final_state_file = argv[++i];
        } else if (i + 1 < argc && strcmp(argv[i], "--initial-state-file") == 0) {
            initial_state_file = argv[++i];
        } else if (i + 1 < argc && strcmp(argv[i], "--from-step") == 0) {
            from_step = strtol(argv[++i], NULL, 10);
        } else if (i + 1 < argc && strcmp(argv[i], "--stop-after") == 0) {
            stop_after = strtol(argv[++i], NULL, 10);
        } else if (i + 1 < argc && (strcmp(argv[i], "--input") == 0 || strcmp(argv[i], "--output") == 0
                                    || strcmp(argv[i], "--param") == 0)) {
            Port *port = argv[i][2] == 'i' ? &inputs[n_inputs++]
                       : argv[i][2] == 'o' ? &outputs[n_outputs++] : &params[n_params++];
            if (n_inputs > MAX_PORTS || n_outputs > MAX_PORTS || n_params > MAX_PORTS) die("too many ports", NULL);
            memset(port, 0, sizeof *port);
            const char *spec = argv[++i];
            size_t length = strcspn(spec, ":");
            snprintf(port->name, sizeof port->name, "%.*s", (int)length, spec);
            port->count = strtoul(spec + length + 1, NULL, 10);
            const char *equals = strchr(spec, '=');
            port->value = equals ? strtod(equals + 1, NULL) : 0.0;
            port->buffer = calloc(port->count, sizeof(double));
        } else {
            die("unknown argument", argv[i]);
        }
    }
    mkdir(work, 0755);
    extract(fmu, work);
    char path[4096], token[256], identifier[256];
    snprintf(path, sizeof path, "%s/modelDescription.xml", work);
    char *description = read_text(path);
    attribute(description, "<fmiModelDescription", "instantiationToken", token, sizeof token);
    attribute(description, "<CoSimulation", "modelIdentifier", identifier, sizeof identifier);
    for (int i = 0; i < n_inputs; i++) inputs[i].vr = value_reference(description, inputs[i].name);
    for (int i = 0; i < n_outputs; i++) outputs[i].vr = value_reference(description, outputs[i].name);
    for (int i = 0; i < n_params; i++) params[i].vr = value_reference(description, params[i].name);

    snprintf(path, sizeof path, "%s/binaries/x86_64-linux/%s.so", work, identifier);
    void *library = dlopen(path, RTLD_NOW | RTLD_LOCAL);
    if (!library) die("cannot load", dlerror());
    LOAD(fmi3InstantiateCoSimulation);
    LOAD(fmi3EnterInitializationMode);
    LOAD(fmi3ExitInitializationMode);
    LOAD(fmi3SetFloat64);
    LOAD(fmi3GetFloat64);
    LOAD(fmi3DoStep);
    LOAD(fmi3Terminate);
    LOAD(fmi3FreeInstance);
    LOAD(fmi3GetFMUState);
    LOAD(fmi3SetFMUState);
    LOAD(fmi3FreeFMUState);
    LOAD(fmi3SerializedFMUStateSize);
    LOAD(fmi3SerializeFMUState);
    LOAD(fmi3DeserializeFMUState);

    char resources[4096];
    snprintf(resources, sizeof resources, "%s/resources/", work);
    fmi3Instance instance = fmi3InstantiateCoSimulation("c_host", token, resources, fmi3False, fmi3True, fmi3False,
                                                        fmi3False, NULL, 0, NULL, logger, NULL);
    if (!instance) die("fmi3InstantiateCoSimulation failed", NULL);
    int refused = 0; /* errors this host provoked on purpose, and the FMU refused */
    fmi3FMUState halfway = NULL;
    double *first_run = NULL;
    for (int i = 0; i < n_params; i++) {
        for (size_t j = 0; j < params[i].count; j++) params[i].buffer[j] = params[i].value;
        CHECK(fmi3SetFloat64(instance, &params[i].vr, 1, params[i].buffer, params[i].count));
    }
    if (misuse) {
        fmi3Boolean event = 0, terminate = 0, early = 0;
        fmi3Float64 last = 0.0;
        refused += fmi3DoStep(instance, 0.0, h, fmi3True, &event, &terminate, &early, &last) == fmi3Error;
        refused += fmi3Terminate(instance) == fmi3Error;
    }
    if (initial_state_file) { /* fmusim v0.0.39's FMIRestoreFMUStateFromFile */
        FILE *file = fopen(initial_state_file, "rb");
        if (!file) die("cannot read", initial_state_file);
        fseek(file, 0L, SEEK_END);
        size_t size = (size_t)ftell(file);
        fseek(file, 0L, SEEK_SET);
        fmi3Byte *bytes = malloc(size ? size : 1);
        if (fread(bytes, 1, size, file) != size) die("cannot read", initial_state_file);
        fclose(file);
        fmi3FMUState state = NULL;
        fmi3Status deserialized = fmi3DeserializeFMUState(instance, bytes, size, &state);
        free(bytes);
        FMUSIM_CALL(deserialized);
        FMUSIM_CALL(fmi3SetFMUState(instance, state));
        FMUSIM_CALL(fmi3FreeFMUState(instance, (fmi3FMUState *)state)); /* sic: the state itself */
    } else {
        CHECK(fmi3EnterInitializationMode(instance, fmi3False, 0.0, 0.0, fmi3False, 0.0));
        CHECK(fmi3ExitInitializationMode(instance));
    }

    long half = steps / 2;
    size_t total_out = 0;
    for (int i = 0; i < n_outputs; i++) total_out += outputs[i].count;
    for (int pass = 0; pass < (with_state ? 2 : 1); pass++) {
        long last_step = stop_after > 0 && stop_after < steps ? stop_after : steps;
        for (long k = pass ? half : from_step; k < last_step; k++) {
            if (with_state && pass == 0 && k == half) CHECK(fmi3GetFMUState(instance, &halfway));
            double t = (double)k * h;
            for (int i = 0; i < n_inputs; i++) {
                for (size_t j = 0; j < inputs[i].count; j++)
                    inputs[i].buffer[j] = inputs[i].value * (1.0 + (double)k / (double)steps);
                CHECK(fmi3SetFloat64(instance, &inputs[i].vr, 1, inputs[i].buffer, inputs[i].count));
            }
            if (misuse && pass == 0 && k == half && n_inputs > 0) {
                double saved = inputs[0].buffer[0];
                inputs[0].buffer[0] = 0.0 / 0.0; /* NaN: refused, and nothing changes */
                refused += fmi3SetFloat64(instance, &inputs[0].vr, 1, inputs[0].buffer, inputs[0].count) == fmi3Error;
                inputs[0].buffer[0] = saved;
            }
            fmi3Boolean event = 0, terminate = 0, early = 0;
            fmi3Float64 last = 0.0;
            CHECK(fmi3DoStep(instance, t, h, fmi3True, &event, &terminate, &early, &last));
        }
        double *values = calloc(total_out ? total_out : 1, sizeof(double));
        size_t at = 0;
        for (int i = 0; i < n_outputs; i++) {
            CHECK(fmi3GetFloat64(instance, &outputs[i].vr, 1, values + at, outputs[i].count));
            at += outputs[i].count;
        }
        if (pass == 0) {
            first_run = values;
            at = 0;
            for (int i = 0; i < n_outputs; i++) {
                printf("%s", outputs[i].name);
                for (size_t j = 0; j < outputs[i].count; j++) printf(" %.17g", values[at + j]);
                printf("\n");
                at += outputs[i].count;
            }
            if (final_state_file) { /* fmusim v0.0.39's FMISaveFMUStateToFile */
                fmi3FMUState state = NULL;
                size_t size = 0;
                FMUSIM_CALL(fmi3GetFMUState(instance, &state));
                FMUSIM_CALL(fmi3SerializedFMUStateSize(instance, state, &size));
                fmi3Byte *bytes = malloc(size ? size : 1);
                fmi3Status serialized = fmi3SerializeFMUState(instance, state, bytes, size);
                FILE *file = serialized == fmi3OK ? fopen(final_state_file, "wb") : NULL;
                if (file) {
                    fwrite(bytes, 1, size, file);
                    fclose(file);
                }
                free(bytes);
                FMUSIM_CALL(serialized);
                FMUSIM_CALL(fmi3FreeFMUState(instance, (fmi3FMUState *)state)); /* sic: the state itself */
            }
            if (with_state) { /* through the serialized form, as a master that stores states on disk would */
                size_t size = 0;
                CHECK(fmi3SerializedFMUStateSize(instance, halfway, &size));
                fmi3Byte *bytes = malloc(size);
                CHECK(fmi3SerializeFMUState(instance, halfway, bytes, size));
                CHECK(fmi3FreeFMUState(instance, &halfway));
                fmi3FMUState restored = NULL;
                CHECK(fmi3DeserializeFMUState(instance, bytes, size, &restored));
                free(bytes);
                CHECK(fmi3SetFMUState(instance, restored));
                CHECK(fmi3FreeFMUState(instance, &restored));
            }
        } else {
            int same = memcmp(first_run, values, total_out * sizeof(double)) == 0;
            printf("state replay: %s\n", same ? "identical" : "DIFFERENT");
            if (!same) failures++;
            free(values);
        }
    }
    CHECK(fmi3Terminate(instance));
    printf("run completed\n");
end:
    free(first_run);
    if (ended != fmi3Fatal) fmi3FreeInstance(instance);
    dlclose(library);
    free(description);
    for (int i = 0; i < n_inputs; i++) free(inputs[i].buffer);
    for (int i = 0; i < n_outputs; i++) free(outputs[i].buffer);
    for (int i = 0; i < n_params; i++) free(params[i].buffer);
    if (ended != fmi3OK) return 0; /* reported above; the errors the logger counted belong to it */
    int expected = misuse ? (n_inputs > 0 ? 3 : 2) : 0;
    if (misuse) printf("misuse refused: %d of %d\n", refused, expected);
    /* the logger counted the provoked errors too: only unexpected ones fail the run */
    return failures - refused != 0 || refused != expected ? 4 : 0;
}

/* ---- --serve: scripted call sequences from stdin --------------------------------------------------- */
static void serve_logger(fmi3InstanceEnvironment env, fmi3Status status, fmi3String category, fmi3String message) {
    (void)env; (void)category;
    printf("L %d ", (int)status);
    for (const char *c = message ? message : ""; *c; c++) putchar(*c == '\n' || *c == '\r' ? ' ' : *c);
    putchar('\n');
}

static void print_encoded(const char *text) {
    putchar(' ');
    if (!*text) { fputs("%", stdout); return; } /* "%" alone: the empty string */
    for (const unsigned char *c = (const unsigned char *)text; *c; c++) {
        if ((*c >= '0' && *c <= '9') || (*c >= 'a' && *c <= 'z') || (*c >= 'A' && *c <= 'Z') || strchr("-_.~/", *c))
            putchar(*c);
        else
            printf("%%%02X", *c);
    }
}

static char *decode(const char *token) {
    char *out = malloc(strlen(token) + 1), *o = out;
    if (!out) die("out of memory", NULL);
    if (strcmp(token, "%") == 0) { *o = '\0'; return out; }
    for (const char *c = token; *c; c++) {
        if (*c == '%' && c[1] && c[2]) {
            char hex[3] = {c[1], c[2], 0};
            *o++ = (char)strtol(hex, NULL, 16);
            c += 2;
        } else {
            *o++ = *c;
        }
    }
    *o = '\0';
    return out;
}

#define SERVE_LOAD(name) name##TYPE *name = (name##TYPE *)dlsym(library, #name); if (!name) die("missing symbol", #name)

static int serve(const char *fmu, const char *work) {
    mkdir(work, 0755);
    extract(fmu, work);
    char path[4096], token[256], identifier[256], resources[4096];
    snprintf(path, sizeof path, "%s/modelDescription.xml", work);
    char *description = read_text(path);
    attribute(description, "<fmiModelDescription", "instantiationToken", token, sizeof token);
    attribute(description, "<CoSimulation", "modelIdentifier", identifier, sizeof identifier);
    snprintf(path, sizeof path, "%s/binaries/x86_64-linux/%s.so", work, identifier);
    void *library = dlopen(path, RTLD_NOW | RTLD_LOCAL);
    if (!library) die("cannot load", dlerror());
    snprintf(resources, sizeof resources, "%s/resources/", work);
    SERVE_LOAD(fmi3InstantiateCoSimulation);
    SERVE_LOAD(fmi3FreeInstance);
    SERVE_LOAD(fmi3EnterInitializationMode);
    SERVE_LOAD(fmi3ExitInitializationMode);
    SERVE_LOAD(fmi3EnterConfigurationMode);
    SERVE_LOAD(fmi3ExitConfigurationMode);
    SERVE_LOAD(fmi3Terminate);
    SERVE_LOAD(fmi3Reset);
    SERVE_LOAD(fmi3DoStep);
    SERVE_LOAD(fmi3SetFloat64);
    SERVE_LOAD(fmi3GetFloat64);
    SERVE_LOAD(fmi3SetInt32);
    SERVE_LOAD(fmi3GetInt32);
    SERVE_LOAD(fmi3SetUInt64);
    SERVE_LOAD(fmi3GetUInt64);
    SERVE_LOAD(fmi3SetBoolean);
    SERVE_LOAD(fmi3GetBoolean);
    SERVE_LOAD(fmi3SetString);
    SERVE_LOAD(fmi3GetString);
    SERVE_LOAD(fmi3GetFMUState);
    SERVE_LOAD(fmi3SetFMUState);
    SERVE_LOAD(fmi3FreeFMUState);
    SERVE_LOAD(fmi3SerializedFMUStateSize);
    SERVE_LOAD(fmi3SerializeFMUState);
    SERVE_LOAD(fmi3DeserializeFMUState);
    fmi3Instance instance = NULL;
    fmi3FMUState state = NULL;
    char *line = NULL;
    size_t capacity = 0;
    while (getline(&line, &capacity, stdin) > 0) {
        char *save = NULL, *command = strtok_r(line, " \t\r\n", &save);
        if (!command) continue;
        if (strcmp(command, "quit") == 0) break;
        int status = 0;
        if (strcmp(command, "instantiate") == 0) {
            if (!instance)
                instance = fmi3InstantiateCoSimulation("fuzz", token, resources, fmi3False, fmi3True, fmi3False,
                                                       fmi3False, NULL, 0, NULL, serve_logger, NULL);
            printf("R %d\n", instance ? 0 : 3);
            fflush(stdout);
            continue;
        }
        if (!instance) { /* the scripts never call an instance that does not exist (the importer's bug) */
            printf("R -1 no instance\n");
            fflush(stdout);
            continue;
        }
        if (strcmp(command, "free") == 0) {
            if (state) fmi3FreeFMUState(instance, &state);
            fmi3FreeInstance(instance);
            instance = NULL;
        } else if (strcmp(command, "enter_init") == 0) {
            status = fmi3EnterInitializationMode(instance, fmi3False, 0.0, 0.0, fmi3False, 0.0);
        } else if (strcmp(command, "exit_init") == 0) {
            status = fmi3ExitInitializationMode(instance);
        } else if (strcmp(command, "enter_config") == 0) {
            status = fmi3EnterConfigurationMode(instance);
        } else if (strcmp(command, "exit_config") == 0) {
            status = fmi3ExitConfigurationMode(instance);
        } else if (strcmp(command, "terminate") == 0) {
            status = fmi3Terminate(instance);
        } else if (strcmp(command, "reset") == 0) {
            status = fmi3Reset(instance);
        } else if (strcmp(command, "step") == 0) {
            double t = strtod(strtok_r(NULL, " ", &save), NULL), h = strtod(strtok_r(NULL, " \n", &save), NULL);
            fmi3Boolean event = 0, terminate = 0, early = 0;
            fmi3Float64 last = -1.0;
            status = fmi3DoStep(instance, t, h, fmi3True, &event, &terminate, &early, &last);
            printf("R %d %.17g\n", status, last);
            fflush(stdout);
            continue;
        } else if (strcmp(command, "get_state") == 0) {
            status = fmi3GetFMUState(instance, &state);
        } else if (strcmp(command, "set_state") == 0) {
            status = fmi3SetFMUState(instance, state); /* NULL when none is saved: refused */
        } else if (strcmp(command, "free_state") == 0) {
            status = fmi3FreeFMUState(instance, &state);
        } else if (strcmp(command, "roundtrip_state") == 0) { /* the saved state through its serialized bytes */
            size_t size = 0;
            status = fmi3SerializedFMUStateSize(instance, state, &size);
            if (status == fmi3OK) {
                fmi3Byte *bytes = malloc(size ? size : 1);
                status = fmi3SerializeFMUState(instance, state, bytes, size);
                if (status == fmi3OK) status = fmi3FreeFMUState(instance, &state);
                if (status == fmi3OK) status = fmi3DeserializeFMUState(instance, bytes, size, &state);
                free(bytes);
            }
        } else if (strcmp(command, "stale_state") == 0) { /* a copied handle used after its state was freed */
            fmi3FMUState fresh = NULL, copy;
            status = fmi3GetFMUState(instance, &fresh);
            copy = fresh;
            if (status == fmi3OK) status = fmi3FreeFMUState(instance, &fresh);
            if (status == fmi3OK) {
                fmi3Status set = fmi3SetFMUState(instance, copy), freed = fmi3FreeFMUState(instance, &copy);
                status = set == freed ? set : (fmi3Status)99; /* both must be refused alike */
            }
        } else if (strcmp(command, "damaged_state") == 0) { /* serialized bytes with one bit flipped */
            fmi3FMUState fresh = NULL, restored = NULL;
            size_t size = 0;
            status = fmi3GetFMUState(instance, &fresh);
            if (status == fmi3OK) status = fmi3SerializedFMUStateSize(instance, fresh, &size);
            if (status == fmi3OK) {
                fmi3Byte *bytes = malloc(size ? size : 1);
                status = fmi3SerializeFMUState(instance, fresh, bytes, size);
                if (status == fmi3OK) {
                    bytes[size / 2] ^= 0x10;
                    status = fmi3DeserializeFMUState(instance, bytes, size, &restored);
                    if (restored) fmi3FreeFMUState(instance, &restored);
                }
                free(bytes);
            }
            if (fresh) fmi3FreeFMUState(instance, &fresh);
        } else if (strcmp(command, "set") == 0 || strcmp(command, "get") == 0) {
            int set = command[0] == 's';
            const char *type = strtok_r(NULL, " ", &save);
            size_t n = strtoul(strtok_r(NULL, " ", &save), NULL, 10);
            char *refs = strtok_r(NULL, " \n", &save);
            fmi3ValueReference vrs[64];
            size_t n_vrs = 0;
            for (char *r_save = NULL, *r = strtok_r(refs, ",", &r_save); r && n_vrs < 64; r = strtok_r(NULL, ",", &r_save))
                vrs[n_vrs++] = (fmi3ValueReference)strtoul(r, NULL, 10);
            size_t capacity_values = n ? n : 1, given = 0;
            double *f64 = calloc(capacity_values, sizeof(double));
            int32_t *i32 = calloc(capacity_values, sizeof(int32_t));
            uint64_t *u64 = calloc(capacity_values, sizeof(uint64_t));
            fmi3Boolean *flags = calloc(capacity_values, sizeof(fmi3Boolean));
            fmi3String *strings = calloc(capacity_values, sizeof(fmi3String));
            char **owned = calloc(capacity_values, sizeof(char *));
            if (!f64 || !i32 || !u64 || !flags || !strings || !owned) die("out of memory", NULL);
            for (char *v = set ? strtok_r(NULL, " \n", &save) : NULL; v && given < capacity_values;
                 v = strtok_r(NULL, " \n", &save), given++) {
                f64[given] = strtod(v, NULL);
                i32[given] = (int32_t)strtoll(v, NULL, 10);
                u64[given] = strtoull(v, NULL, 10);
                flags[given] = (fmi3Boolean)strtol(v, NULL, 10);
                strings[given] = owned[given] = decode(v);
            }
            for (size_t k = given; k < capacity_values; k++) strings[k] = ""; /* never a NULL pointer */
            if (strcmp(type, "f64") == 0) {
                status = set ? fmi3SetFloat64(instance, vrs, n_vrs, f64, n) : fmi3GetFloat64(instance, vrs, n_vrs, f64, n);
            } else if (strcmp(type, "i32") == 0) {
                status = set ? fmi3SetInt32(instance, vrs, n_vrs, i32, n) : fmi3GetInt32(instance, vrs, n_vrs, i32, n);
            } else if (strcmp(type, "u64") == 0) {
                status = set ? fmi3SetUInt64(instance, vrs, n_vrs, u64, n) : fmi3GetUInt64(instance, vrs, n_vrs, u64, n);
            } else if (strcmp(type, "bool") == 0) {
                status = set ? fmi3SetBoolean(instance, vrs, n_vrs, flags, n)
                             : fmi3GetBoolean(instance, vrs, n_vrs, flags, n);
            } else {
                status = set ? fmi3SetString(instance, vrs, n_vrs, strings, n)
                             : fmi3GetString(instance, vrs, n_vrs, strings, n);
            }
            printf("R %d", status);
            if (!set && status <= fmi3Warning) {
                for (size_t k = 0; k < n; k++) {
                    if (strcmp(type, "f64") == 0) printf(" %.17g", f64[k]);
                    else if (strcmp(type, "i32") == 0) printf(" %d", i32[k]);
                    else if (strcmp(type, "u64") == 0) printf(" %llu", (unsigned long long)u64[k]);
                    else if (strcmp(type, "bool") == 0) printf(" %d", (int)flags[k]);
                    else print_encoded(strings[k] ? strings[k] : "");
                }
            }
            printf("\n");
            fflush(stdout);
            for (size_t k = 0; k < given; k++) free(owned[k]);
            free(f64); free(i32); free(u64); free(flags); free(strings); free(owned);
            continue;
        } else {
            die("unknown command", command);
        }
        printf("R %d\n", status);
        fflush(stdout);
    }
    if (instance) {
        if (state) fmi3FreeFMUState(instance, &state);
        fmi3FreeInstance(instance);
    }
    free(line);
    dlclose(library);
    free(description);
    return 0;
}
