/* The IIR filter of scipy.signal.lfilter (direct form II transposed), for 1-D float64 data, with the state held in
 * local variables: fuelid's fits filter short polynomials (2–17 coefficients) through 10^4–10^5 samples thousands of
 * times, where scipy's generic loop over a state array in memory is the cost (fuelid.ident.filters).
 *
 * The arithmetic is scipy's, operation for operation, so the output is the same to the bit (tests/ident/test_filters.py
 * checks it against scipy): with b and a zero-padded to one length n and divided by a[0] (done by the caller),
 *
 *     y[t]       = z[0] + b[0] x[t]
 *     z[k]       = (z[k+1] + x[t] b[k+1]) − y[t] a[k+1]      k = 0 … n−3
 *     z[n−2]     = x[t] b[n−1] − y[t] a[n−1]
 *
 * from zero state. Built without contracting a·b + c into fused multiply-adds (-ffp-contract=off), which would round
 * once instead of twice. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#define MAX_TAPS 32  /* fuelid.ident.filters.MAX_TAPS */

/* One filter of N coefficients (a compile-time constant, so that the state z[] lives in registers). */
#define IIR_KERNEL(N)                                                                                   \
    static void iir_##N(const double *b, const double *a, const double *x, double *y, Py_ssize_t len) { \
        double z[N - 1] = {0.0};                                                                        \
        for (Py_ssize_t t = 0; t < len; t++) {                                                          \
            const double xt = x[t];                                                                     \
            const double yt = z[0] + b[0] * xt;                                                         \
            _Pragma("GCC unroll 32") for (int k = 0; k < N - 2; k++)                                    \
                z[k] = z[k + 1] + xt * b[k + 1] - yt * a[k + 1];                                        \
            z[N - 2] = xt * b[N - 1] - yt * a[N - 1];                                                   \
            y[t] = yt;                                                                                  \
        }                                                                                               \
    }

IIR_KERNEL(2)
IIR_KERNEL(3)
IIR_KERNEL(4)
IIR_KERNEL(5)
IIR_KERNEL(6)
IIR_KERNEL(7)
IIR_KERNEL(8)
IIR_KERNEL(9)
IIR_KERNEL(10)
IIR_KERNEL(11)
IIR_KERNEL(12)
IIR_KERNEL(13)
IIR_KERNEL(14)
IIR_KERNEL(15)
IIR_KERNEL(16)
IIR_KERNEL(17)
IIR_KERNEL(18)
IIR_KERNEL(19)
IIR_KERNEL(20)
IIR_KERNEL(21)
IIR_KERNEL(22)
IIR_KERNEL(23)
IIR_KERNEL(24)
IIR_KERNEL(25)
IIR_KERNEL(26)
IIR_KERNEL(27)
IIR_KERNEL(28)
IIR_KERNEL(29)
IIR_KERNEL(30)
IIR_KERNEL(31)
IIR_KERNEL(32)

typedef void (*kernel)(const double *, const double *, const double *, double *, Py_ssize_t);
static const kernel KERNELS[MAX_TAPS + 1] = {NULL, NULL, iir_2, iir_3, iir_4, iir_5, iir_6, iir_7, iir_8, iir_9,
                                             iir_10, iir_11, iir_12, iir_13, iir_14, iir_15, iir_16, iir_17, iir_18,
                                             iir_19, iir_20, iir_21, iir_22, iir_23, iir_24, iir_25, iir_26, iir_27,
                                             iir_28, iir_29, iir_30, iir_31, iir_32};

/* view ← obj as a C-contiguous 1-D array of doubles (writable when asked); 0 with a ValueError otherwise. */
static int doubles(PyObject *obj, Py_buffer *view, int writable, const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) != 0)
        return 0;
    if (view->ndim != 1 || view->itemsize != sizeof(double) || view->format == NULL || strcmp(view->format, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "%s: a C-contiguous 1-D float64 array is needed", name);
        return 0;
    }
    return 1;
}

/* iir(b, a, x, y): y ← the filter b/a (same length n, 2 ≤ n ≤ MAX_TAPS, a[0] = 1) applied to x, from zero state. */
static PyObject *iir(PyObject *self, PyObject *args) {
    static const char *const NAMES[4] = {"b", "a", "x", "y"};
    PyObject *objs[4];
    Py_buffer v[4];  /* b, a, x, y */
    int held = 0;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOO", &objs[0], &objs[1], &objs[2], &objs[3]))
        return NULL;
    for (; held < 4; held++)
        if (!doubles(objs[held], &v[held], held == 3, NAMES[held]))
            goto release;
    Py_ssize_t n = v[0].shape[0], len = v[2].shape[0];
    if (v[1].shape[0] != n || n < 2 || n > MAX_TAPS || v[3].shape[0] != len) {
        PyErr_Format(PyExc_ValueError, "iir: b and a of one length in 2..%d and y as long as x are needed", MAX_TAPS);
        goto release;
    }
    Py_BEGIN_ALLOW_THREADS
    const double *b = v[0].buf, *a = v[1].buf, *x = v[2].buf;
    KERNELS[n](b, a, x, (double *)v[3].buf, len);
    Py_END_ALLOW_THREADS
    result = Py_None;
    Py_INCREF(result);
release:
    while (held > 0)
        PyBuffer_Release(&v[--held]);
    return result;
}

static PyMethodDef METHODS[] = {
    {"iir", iir, METH_VARARGS, "iir(b, a, x, y): y <- scipy.signal.lfilter(b, a, x); b, a normalised, equal length."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_iir", NULL, -1, METHODS};

PyMODINIT_FUNC PyInit__iir(void) { return PyModule_Create(&MODULE); }
