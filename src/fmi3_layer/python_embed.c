/* Run-time binding to CPython for the FMI layer (see python_embed.h for why). */
#define _GNU_SOURCE
#include "python_embed.h"
#include "runtime_unpack.h"

#include <dlfcn.h>
#include <errno.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <wchar.h>

PythonApi py;

static pthread_mutex_t bind_lock = PTHREAD_MUTEX_INITIALIZER;
static int bound = 0;

/* Resolve every function of PythonApi from `handle`; 0 when all were found. */
static int bind_all(void *handle, char *reason, size_t reason_size) {
#define BIND(name)                                                                         \
    do {                                                                                   \
        *(void **)(&py.name) = dlsym(handle, #name);                                       \
        if (!py.name) {                                                                    \
            snprintf(reason, reason_size, "the Python library has no symbol %s", #name);   \
            return -1;                                                                     \
        }                                                                                  \
    } while (0)
    BIND(Py_IsInitialized);
    BIND(Py_InitializeEx);
    BIND(PyEval_SaveThread);
    BIND(PyGILState_Ensure);
    BIND(PyGILState_Release);
    BIND(PyRun_StringFlags);
    BIND(PyDict_New);
    BIND(PyDict_SetItemString);
    BIND(PyDict_GetItemString);
    BIND(PyImport_ImportModule);
    BIND(PyObject_CallMethod);
    BIND(PyObject_CallFunction);
    BIND(PyObject_CallNoArgs);
    BIND(PyFloat_AsDouble);
    BIND(PyErr_Occurred);
    BIND(PyErr_Fetch);
    BIND(PyErr_NormalizeException);
    BIND(PyErr_Clear);
    BIND(PyObject_Str);
    BIND(PyObject_GetAttrString);
    BIND(PyUnicode_AsUTF8);
    BIND(Py_DecRef);
    BIND(Py_IncRef);
    BIND(PyBytes_AsStringAndSize);
    BIND(PyBytes_FromStringAndSize);
    BIND(PyErr_SetInterrupt);
    BIND(PyArg_ParseTuple);
#undef BIND
    return 0;
}

/* The first two lines of resources/libpython.txt (written by a build without a carried runtime):
 * the build machine's libpython and its Python's prefix; "" when absent. */
static void recorded_library(const char *resource_dir, char *path, size_t size, char *home, size_t home_size) {
    path[0] = home[0] = '\0';
    if (!resource_dir) return;
    char file[4096];
    snprintf(file, sizeof file, "%s/libpython.txt", resource_dir);
    FILE *f = fopen(file, "r");
    if (!f) return;
    if (fgets(path, (int)size, f)) path[strcspn(path, "\r\n")] = '\0';
    if (fgets(home, (int)home_size, f)) home[strcspn(home, "\r\n")] = '\0';
    fclose(f);
}

/* "3.11" from ".../libpython3.11.so.1.0", or "" */
static void library_version(const char *library, char *version, size_t size) {
    version[0] = '\0';
    const char *base = strrchr(library, '/');
    base = base ? base + 1 : library;
    int major = 0, minor = 0;
    if (sscanf(base, "libpython%d.%d", &major, &minor) == 2) snprintf(version, size, "%d.%d", major, minor);
}

/* 0 when <home>/lib/python<version>/os.py exists: an interpreter started with that home finds its
 * standard library (otherwise CPython aborts the whole process: "init_fs_encoding"). */
static int check_home(const char *home, const char *version, char *reason, size_t reason_size) {
    char file[4096];
    snprintf(file, sizeof file, "%s/lib/python%s/os.py", home, version);
    if (access(file, R_OK) == 0) return 0;
    snprintf(reason, reason_size, "the Python standard library is not at %s/lib/python%s (no os.py there)", home,
             version);
    return -1;
}

/* Load the runtime the FMU carries (runtime_unpack.h, orchestration/portable_runtime.py): the
 * libraries of its manifest.txt in order, then its libpython. Returns the libpython handle, or
 * NULL with a reason; `home` receives the runtime folder. No runtime carried: NULL, reason "". */
static void *load_carried_runtime(const char *resource_dir, char *home, size_t home_size, char *version,
                                  size_t version_size, char *reason, size_t reason_size) {
    reason[0] = '\0';
    if (!runtime_carried(resource_dir)) return NULL;
    if (runtime_folder(resource_dir, home, home_size, reason, reason_size) != 0) return NULL;
    char file[4096];
    snprintf(file, sizeof file, "%s/manifest.txt", home);
    FILE *f = fopen(file, "r");
    if (!f) {
        snprintf(reason, reason_size, "cannot read %s (%s)", file, strerror(errno));
        return NULL;
    }
    void *python = NULL;
    char line[4096];
    while (fgets(line, sizeof line, f)) {
        line[strcspn(line, "\r\n")] = '\0';
        char key[32], relative[2048], soname[256] = "";
        if (line[0] == '#' || sscanf(line, "%31s %2047s %255s", key, relative, soname) < 2) continue;
        if (strcmp(key, "python") == 0) {
            snprintf(version, version_size, "%.15s", relative);
            continue;
        }
        char path[4096];
        snprintf(path, sizeof path, "%s/%s", home, relative);
        if (strcmp(key, "preload") == 0) {
            /* a library the process already has is used as it is (one copy of each in a process) */
            if (soname[0] && dlopen(soname, RTLD_NOW | RTLD_GLOBAL | RTLD_NOLOAD)) continue;
            if (!dlopen(path, RTLD_NOW | RTLD_GLOBAL)) {
                snprintf(reason, reason_size, "cannot load %s, carried by the FMU (%s)", path, dlerror());
                break;
            }
        } else if (strcmp(key, "libpython") == 0) {
            python = dlopen(path, RTLD_NOW | RTLD_GLOBAL);
            if (!python) snprintf(reason, reason_size, "cannot load the FMU's Python %s (%s)", path, dlerror());
            break;
        }
    }
    fclose(f);
    if (!python && !reason[0])
        snprintf(reason, reason_size, "%s names no libpython: the FMU is damaged; build it again", file);
    if (python && check_home(home, version, reason, reason_size) != 0) python = NULL;
    return python;
}

/* Set the embedded interpreter's home; `isolate` (the carried runtime) also ignores the
 * importer's environment (its PYTHONPATH, PYTHONHOME and user site would mix another
 * installation's packages in; another installation is found through PYTHONPATH, so it keeps it).
 * The legacy globals, not PyConfig: their layout does not depend on the Python version. */
static int configure_home(void *handle, const char *home, int isolate, char *reason, size_t reason_size) {
    void (*set_home)(const wchar_t *) = (void (*)(const wchar_t *))dlsym(handle, "Py_SetPythonHome");
    wchar_t *(*decode)(const char *, size_t *) = (wchar_t * (*)(const char *, size_t *)) dlsym(handle, "Py_DecodeLocale");
    if (!set_home || !decode) {
        snprintf(reason, reason_size, "the Python library has no Py_SetPythonHome/Py_DecodeLocale");
        return -1;
    }
    static wchar_t *wide_home = NULL; /* Python keeps the pointer: never freed */
    wide_home = decode(home, NULL);
    if (!wide_home) {
        snprintf(reason, reason_size, "the path %s cannot be decoded in this locale", home);
        return -1;
    }
    set_home(wide_home);
    const char *flags[] = {"Py_IgnoreEnvironmentFlag", "Py_NoUserSiteDirectory", "Py_DontWriteBytecodeFlag"};
    for (size_t i = 0; isolate && i < sizeof flags / sizeof flags[0]; i++) {
        int *flag = (int *)dlsym(handle, flags[i]);
        if (flag) *flag = 1;
    }
    return 0;
}

int python_ensure(const char *resource_dir, int *started, char *reason, size_t reason_size) {
    *started = 0;
    pthread_mutex_lock(&bind_lock);
    static int carried = 0;
    char home[4096] = "";
    if (!bound) {
        void *handle = NULL;
        if (dlsym(RTLD_DEFAULT, "Py_IsInitialized")) {
            handle = RTLD_DEFAULT; /* a Python importer, or libpython preloaded */
        } else {
            char path[4096] = "", version[32] = "";
            const char *env = getenv("AAA_COSIM_LIBPYTHON");
            if (env && *env) {
                /* another installation: its prefix is $AAA_COSIM_PYTHONHOME, or the folder above lib/ */
                snprintf(path, sizeof path, "%s", env);
                const char *env_home = getenv("AAA_COSIM_PYTHONHOME");
                if (env_home && *env_home) {
                    snprintf(home, sizeof home, "%s", env_home);
                } else {
                    char resolved[4096];
                    snprintf(home, sizeof home, "%s", realpath(path, resolved) ? resolved : path);
                    for (int up = 0; up < 2; up++) {
                        char *slash = strrchr(home, '/');
                        if (slash) *slash = '\0';
                    }
                }
                library_version(path, version, sizeof version);
                if (check_home(home, version, reason, reason_size) != 0) {
                    size_t used = strlen(reason);
                    snprintf(reason + used, reason_size - used,
                             ": set AAA_COSIM_PYTHONHOME to the prefix of the Python whose library "
                             "AAA_COSIM_LIBPYTHON names (the folder that holds lib/python%s)", version);
                    pthread_mutex_unlock(&bind_lock);
                    return -1;
                }
            } else {
                handle = load_carried_runtime(resource_dir, home, sizeof home, version, sizeof version, reason,
                                              reason_size);
                if (handle) {
                    carried = 1;
                } else if (reason[0]) {
                    pthread_mutex_unlock(&bind_lock);
                    return -1;
                } else {
                    recorded_library(resource_dir, path, sizeof path, home, sizeof home);
                    library_version(path, version, sizeof version);
                    if (!path[0]) {
                        snprintf(reason, reason_size,
                                 "no Python library: this FMU carries no Python runtime (resources/runtime) "
                                 "and names none; build it with `python -m orchestration build`, or set "
                                 "AAA_COSIM_LIBPYTHON to a libpython3.x.so with the FMU's packages");
                        pthread_mutex_unlock(&bind_lock);
                        return -1;
                    }
                    if (home[0] && check_home(home, version, reason, reason_size) != 0) {
                        size_t used = strlen(reason);
                        snprintf(reason + used, reason_size - used,
                                 ": the Python this FMU was built with is not on this machine; set "
                                 "AAA_COSIM_LIBPYTHON (and AAA_COSIM_PYTHONHOME) to another one");
                        pthread_mutex_unlock(&bind_lock);
                        return -1;
                    }
                }
            }
            if (!handle) {
                handle = dlopen(path, RTLD_NOW | RTLD_GLOBAL);
                if (!handle) {
                    snprintf(reason, reason_size,
                             "cannot load the Python library %s (%s); set AAA_COSIM_LIBPYTHON to a "
                             "libpython3.x.so with the FMU's packages", path, dlerror());
                    pthread_mutex_unlock(&bind_lock);
                    return -1;
                }
            }
            if (home[0] && configure_home(handle, home, carried, reason, reason_size) != 0) {
                pthread_mutex_unlock(&bind_lock);
                return -1;
            }
        }
        if (bind_all(handle, reason, reason_size) != 0) {
            pthread_mutex_unlock(&bind_lock);
            return -1;
        }
        bound = 1;
    }
    if (!py.Py_IsInitialized()) {
        /* A non-Python importer: start an interpreter without Python's signal handlers (the
         * host's own stay in place) and release the GIL so any thread can take it. */
        py.Py_InitializeEx(0);
        py.PyEval_SaveThread();
        *started = carried ? PYTHON_STARTED_CARRIED : PYTHON_STARTED;
    }
    pthread_mutex_unlock(&bind_lock);
    return 0;
}

int python_error_text(char *buffer, size_t size) {
    PyObject *type = NULL, *value = NULL, *traceback = NULL;
    buffer[0] = '\0';
    if (!py.PyErr_Occurred()) {
        snprintf(buffer, size, "unknown Python error");
        return 0;
    }
    py.PyErr_Fetch(&type, &value, &traceback);
    py.PyErr_NormalizeException(&type, &value, &traceback);
    const char *type_name = "Exception";
    PyObject *name = type ? py.PyObject_GetAttrString(type, "__name__") : NULL;
    if (name) {
        const char *text = py.PyUnicode_AsUTF8(name);
        if (text) type_name = text;
    }
    PyObject *message = value ? py.PyObject_Str(value) : NULL;
    const char *message_text = message ? py.PyUnicode_AsUTF8(message) : NULL;
    /* a user's mistake (ValueError) reads as its message; anything else also names its type */
    int interrupted = strcmp(type_name, "KeyboardInterrupt") == 0;
    if (strcmp(type_name, "ValueError") == 0)
        snprintf(buffer, size, "%s", message_text ? message_text : "(no message)");
    else
        snprintf(buffer, size, "%s: %s", type_name, message_text ? message_text : "(no message)");
    if (message) py.Py_DecRef(message);
    if (name) py.Py_DecRef(name);
    if (type) py.Py_DecRef(type);
    if (value) py.Py_DecRef(value);
    if (traceback) py.Py_DecRef(traceback);
    py.PyErr_Clear();
    return interrupted;
}
