/* Array arguments of radiomap's C kernels (radiometry/_ckernels.c, mapping/_ckernels.c), through the buffer
 * protocol: C-contiguous, of the element kind and size each kernel names, with the dimensions it checks. Any
 * mismatch raises ValueError naming the argument, never a read past an array (these are private kernels; the
 * Python callers build their arrays, the checks keep a caller's mistake from becoming a crash).
 * Header-only: each extension includes it once. */
#ifndef RADIOMAP_BUFFERS_H
#define RADIOMAP_BUFFERS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

/* The kernels' argument contract: radiometry._native.ABI must equal it (a stale build is then not used). Bump
 * both whenever a kernel's arguments change. */
#define RM_ABI 3

#ifdef _OPENMP
#include <omp.h>
#define RM_OPENMP 1
#else
#define RM_OPENMP 0
#endif

/* 'f' float, 'i' signed integer, 'u' unsigned integer, 'b' bool; 0 for anything else */
static char rm_kind(const char *format)
{
    if (format == NULL)
        return 'u'; /* PyBUF_SIMPLE: unsigned bytes */
    while (*format == '@' || *format == '=' || *format == '<' || *format == '|')
        format++;
    if (format[0] == 0 || format[1] != 0)
        return 0;
    switch (format[0]) {
    case 'e': case 'f': case 'd': return 'f';
    case 'b': case 'h': case 'i': case 'l': case 'q': case 'n': return 'i';
    case 'B': case 'H': case 'I': case 'L': case 'Q': case 'N': return 'u';
    case '?': return 'b';
    default: return 0;
    }
}

/* The C-contiguous buffer of ``obj`` with elements of kind ``kind_a`` and ``size_a`` bytes, or (``size_b`` > 0) of
 * kind ``kind_b`` and ``size_b`` bytes; ``ndim`` < 0: any number of dimensions. ``name`` names the argument in the
 * error. On failure ``view->obj`` is NULL (rm_release skips it). */
static int rm_get_of(PyObject *obj, Py_buffer *view, char kind_a, Py_ssize_t size_a, char kind_b, Py_ssize_t size_b,
                     int ndim, int writable, const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_ValueError, "%s: needs a C-contiguous%s array", name, writable ? " writable" : "");
        view->obj = NULL;
        return -1;
    }
    char kind = rm_kind(view->format);
    int ok = (kind == kind_a && view->itemsize == size_a) || (size_b > 0 && kind == kind_b && view->itemsize == size_b);
    if (!ok || (ndim >= 0 && view->ndim != ndim)) {
        const char *format = view->format ? view->format : "B";
        if (size_b > 0)
            PyErr_Format(PyExc_ValueError, "%s: needs %c%zd or %c%zd elements, got format '%s'", name, kind_a,
                         size_a * 8, kind_b, size_b * 8, format);
        else
            PyErr_Format(PyExc_ValueError, "%s: needs %d-d %c%zd elements, got %d-d format '%s'", name, ndim, kind_a,
                         size_a * 8, view->ndim, format);
        PyBuffer_Release(view);
        view->obj = NULL;
        return -1;
    }
    return 0;
}

static int rm_get(PyObject *obj, Py_buffer *view, char kind, Py_ssize_t itemsize, int ndim, int writable,
                  const char *name)
{
    return rm_get_of(obj, view, kind, itemsize, 0, 0, ndim, writable, name);
}

/* Fails with ValueError unless dimension ``axis`` of ``view`` is ``size``. */
static int rm_dim(const Py_buffer *view, int axis, Py_ssize_t size, const char *name)
{
    if (view->shape[axis] != size) {
        PyErr_Format(PyExc_ValueError, "%s: axis %d must have %zd elements, got %zd", name, axis, size,
                     view->shape[axis]);
        return -1;
    }
    return 0;
}

static void rm_release(Py_buffer *views, int n)
{
    for (int i = 0; i < n; i++)
        if (views[i].obj != NULL)
            PyBuffer_Release(&views[i]);
}

static Py_ssize_t rm_items(const Py_buffer *view)
{
    return view->len / view->itemsize;
}

/* The threads of the parallel kernels (OpenMP; 1 when built without it). */
static PyObject *rm_get_num_threads(PyObject *self, PyObject *args)
{
#ifdef _OPENMP
    return PyLong_FromLong(omp_get_max_threads());
#else
    return PyLong_FromLong(1);
#endif
}

static PyObject *rm_set_num_threads(PyObject *self, PyObject *args)
{
    int n;
    if (!PyArg_ParseTuple(args, "i", &n))
        return NULL;
    if (n < 1) {
        PyErr_Format(PyExc_ValueError, "the number of threads must be at least 1, got %d", n);
        return NULL;
    }
#ifdef _OPENMP
    omp_set_num_threads(n);
#endif
    Py_RETURN_NONE;
}

#define RM_THREAD_METHODS \
    {"get_num_threads", rm_get_num_threads, METH_NOARGS, "Threads of the parallel kernels."}, \
    {"set_num_threads", rm_set_num_threads, METH_VARARGS, "Set the threads of the parallel kernels."}

#endif
