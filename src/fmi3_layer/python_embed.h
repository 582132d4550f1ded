/* The embedded Python of the project's FMUs: the few CPython C-API functions the FMI layer
 * calls, resolved at run time.
 *
 * The FMU binary links to no libpython. In a Python importer (FMPy, the orchestrator) the
 * interpreter's symbols are already in the process and are used as they are; in any other
 * importer the library named by $AAA_COSIM_LIBPYTHON, or else the runtime the FMU carries in
 * resources/runtime (orchestration/portable_runtime.py), or else the library a build without
 * one recorded in resources/libpython.txt, is loaded with RTLD_GLOBAL (extension modules such as
 * numpy's need its symbols) and an interpreter is started, its home set and the importer's
 * Python environment variables ignored. That interpreter is never finalized: finalizing an
 * interpreter that has imported numba/numpy from a shared library at process exit is what crashed
 * the hosts of the pythonfmu3-based FMUs; the process exit reclaims it.
 */
#ifndef AAA_PYTHON_EMBED_H
#define AAA_PYTHON_EMBED_H

#include <stddef.h>
#include <sys/types.h>

typedef struct _object PyObject;
typedef ssize_t Py_ssize_t;
typedef int PyGILState_STATE;

typedef struct {
    int (*Py_IsInitialized)(void);
    void (*Py_InitializeEx)(int);
    void *(*PyEval_SaveThread)(void);
    PyGILState_STATE (*PyGILState_Ensure)(void);
    void (*PyGILState_Release)(PyGILState_STATE);
    PyObject *(*PyRun_StringFlags)(const char *, int, PyObject *, PyObject *, void *);
    PyObject *(*PyDict_New)(void);
    int (*PyDict_SetItemString)(PyObject *, const char *, PyObject *);
    PyObject *(*PyDict_GetItemString)(PyObject *, const char *);
    PyObject *(*PyImport_ImportModule)(const char *);
    PyObject *(*PyObject_CallMethod)(PyObject *, const char *, const char *, ...);
    PyObject *(*PyObject_CallFunction)(PyObject *, const char *, ...);
    PyObject *(*PyObject_CallNoArgs)(PyObject *);
    double (*PyFloat_AsDouble)(PyObject *);
    PyObject *(*PyErr_Occurred)(void);
    void (*PyErr_Fetch)(PyObject **, PyObject **, PyObject **);
    void (*PyErr_NormalizeException)(PyObject **, PyObject **, PyObject **);
    void (*PyErr_Clear)(void);
    PyObject *(*PyObject_Str)(PyObject *);
    PyObject *(*PyObject_GetAttrString)(PyObject *, const char *);
    const char *(*PyUnicode_AsUTF8)(PyObject *);
    void (*Py_DecRef)(PyObject *);
    void (*Py_IncRef)(PyObject *);
    int (*PyBytes_AsStringAndSize)(PyObject *, char **, Py_ssize_t *);
    PyObject *(*PyBytes_FromStringAndSize)(const char *, Py_ssize_t);
    void (*PyErr_SetInterrupt)(void);
    int (*PyArg_ParseTuple)(PyObject *, const char *, ...);
} PythonApi;

extern PythonApi py;

/* How python_ensure found the interpreter (`*started`): the importer's own, or one it started
 * from another installation's library, or from the runtime the FMU carries. */
enum { PYTHON_IMPORTERS = 0, PYTHON_STARTED = 1, PYTHON_STARTED_CARRIED = 2 };

/* Make the interpreter usable from this thread's next PyGILState_Ensure. Returns 0 on success;
 * on failure writes a reason (naming what to set) into `reason`. `*started` tells whether this
 * call started the interpreter (a non-Python importer), and from which library (the enum above). */
int python_ensure(const char *resource_dir, int *started, char *reason, size_t reason_size);

/* The pending Python exception as text ("TypeName: message"), cleared; the GIL must be held.
 * Returns 1 when it was a KeyboardInterrupt (the caller hands the interrupt back), else 0. */
int python_error_text(char *buffer, size_t size);

#endif
