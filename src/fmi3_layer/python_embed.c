/* Run-time binding to CPython for the FMI layer (see python_embed.h for why). */
#define _GNU_SOURCE
#include "python_embed.h"

#include <dlfcn.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

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

/* First line of resources/libpython.txt (written by the build), or "" when absent. */
static void recorded_library(const char *resource_dir, char *path, size_t size) {
    path[0] = '\0';
    if (!resource_dir) return;
    char file[4096];
    snprintf(file, sizeof file, "%s/libpython.txt", resource_dir);
    FILE *f = fopen(file, "r");
    if (!f) return;
    if (fgets(path, (int)size, f)) path[strcspn(path, "\r\n")] = '\0';
    fclose(f);
}

int python_ensure(const char *resource_dir, int *started, char *reason, size_t reason_size) {
    *started = 0;
    pthread_mutex_lock(&bind_lock);
    if (!bound) {
        void *handle = NULL;
        if (dlsym(RTLD_DEFAULT, "Py_IsInitialized")) {
            handle = RTLD_DEFAULT; /* a Python importer, or libpython preloaded */
        } else {
            char path[4096];
            const char *env = getenv("AAA_COSIM_LIBPYTHON");
            if (env && *env) {
                snprintf(path, sizeof path, "%s", env);
            } else {
                recorded_library(resource_dir, path, sizeof path);
            }
            if (!path[0]) {
                snprintf(reason, reason_size,
                         "no Python library: this FMU runs Python code; set AAA_COSIM_LIBPYTHON to the "
                         "libpython3.x.so it was built with");
                pthread_mutex_unlock(&bind_lock);
                return -1;
            }
            handle = dlopen(path, RTLD_NOW | RTLD_GLOBAL);
            if (!handle) {
                snprintf(reason, reason_size,
                         "cannot load the Python library %s (%s); set AAA_COSIM_LIBPYTHON to the "
                         "libpython3.x.so the FMU was built with", path, dlerror());
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
        *started = 1;
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
