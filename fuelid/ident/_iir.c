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
 * once instead of twice.
 *
 * iir_pair filters two signals, each through its own filter of the same length, side by side in the two halves of SSE2
 * registers: one instruction does both signals' operation, so the pair takes about the time of one. Each signal's
 * operations are the same ones in the same order (SSE2 rounds each like its scalar instruction), so its output is
 * the same to the bit as alone. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

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

/* Two signals side by side, each through its own filter of N coefficients (b0/a0 for x0, b1/a1 for x1), one in
 * each half of an SSE2 register (every x86-64 CPU has them): each sees the operations of iir_N, in its order.
 * Elsewhere (aarch64) one after the other. */
#if defined(__SSE2__)
#define IIR_PAIR_KERNEL(N)                                                                                    \
    static void iir_##N##x2(const double *b0, const double *a0, const double *x0, double *y0,               \
                            const double *b1, const double *a1, const double *x1, double *y1, Py_ssize_t len) { \
        __m128d z[N - 1], bb[N], aa[N];                                                                       \
        for (int k = 0; k < N; k++) {                                                                         \
            bb[k] = _mm_set_pd(b1[k], b0[k]);                                                                 \
            aa[k] = _mm_set_pd(a1[k], a0[k]);                                                                 \
        }                                                                                                     \
        for (int k = 0; k < N - 1; k++)                                                                       \
            z[k] = _mm_setzero_pd();                                                                          \
        for (Py_ssize_t t = 0; t < len; t++) {                                                                \
            const __m128d xt = _mm_set_pd(x1[t], x0[t]);                                                      \
            const __m128d yt = _mm_add_pd(z[0], _mm_mul_pd(bb[0], xt));                                       \
            _Pragma("GCC unroll 32") for (int k = 0; k < N - 2; k++)                                          \
                z[k] = _mm_sub_pd(_mm_add_pd(z[k + 1], _mm_mul_pd(xt, bb[k + 1])), _mm_mul_pd(yt, aa[k + 1])); \
            z[N - 2] = _mm_sub_pd(_mm_mul_pd(xt, bb[N - 1]), _mm_mul_pd(yt, aa[N - 1]));                      \
            _mm_storel_pd(y0 + t, yt);                                                                        \
            _mm_storeh_pd(y1 + t, yt);                                                                        \
        }                                                                                                     \
    }
#else
#define IIR_PAIR_KERNEL(N)                                                                                    \
    static void iir_##N##x2(const double *b0, const double *a0, const double *x0, double *y0,               \
                            const double *b1, const double *a1, const double *x1, double *y1, Py_ssize_t len) { \
        iir_##N(b0, a0, x0, y0, len);                                                                         \
        iir_##N(b1, a1, x1, y1, len);                                                                         \
    }
#endif

IIR_PAIR_KERNEL(2)
IIR_PAIR_KERNEL(3)
IIR_PAIR_KERNEL(4)
IIR_PAIR_KERNEL(5)
IIR_PAIR_KERNEL(6)
IIR_PAIR_KERNEL(7)
IIR_PAIR_KERNEL(8)
IIR_PAIR_KERNEL(9)
IIR_PAIR_KERNEL(10)
IIR_PAIR_KERNEL(11)
IIR_PAIR_KERNEL(12)
IIR_PAIR_KERNEL(13)
IIR_PAIR_KERNEL(14)
IIR_PAIR_KERNEL(15)
IIR_PAIR_KERNEL(16)
IIR_PAIR_KERNEL(17)
IIR_PAIR_KERNEL(18)
IIR_PAIR_KERNEL(19)
IIR_PAIR_KERNEL(20)
IIR_PAIR_KERNEL(21)
IIR_PAIR_KERNEL(22)
IIR_PAIR_KERNEL(23)
IIR_PAIR_KERNEL(24)
IIR_PAIR_KERNEL(25)
IIR_PAIR_KERNEL(26)
IIR_PAIR_KERNEL(27)
IIR_PAIR_KERNEL(28)
IIR_PAIR_KERNEL(29)
IIR_PAIR_KERNEL(30)
IIR_PAIR_KERNEL(31)
IIR_PAIR_KERNEL(32)

typedef void (*pair_kernel)(const double *, const double *, const double *, double *, const double *,
                            const double *, const double *, double *, Py_ssize_t);
static const pair_kernel PAIR_KERNELS[MAX_TAPS + 1] = {NULL, NULL, iir_2x2, iir_3x2, iir_4x2, iir_5x2, iir_6x2,
                                                       iir_7x2, iir_8x2, iir_9x2, iir_10x2, iir_11x2, iir_12x2,
                                                       iir_13x2, iir_14x2, iir_15x2, iir_16x2, iir_17x2, iir_18x2,
                                                       iir_19x2, iir_20x2, iir_21x2, iir_22x2, iir_23x2, iir_24x2,
                                                       iir_25x2, iir_26x2, iir_27x2, iir_28x2, iir_29x2, iir_30x2,
                                                       iir_31x2, iir_32x2};

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

static void release(Py_buffer *v, int count) {
    while (count > 0)
        PyBuffer_Release(&v[--count]);
}

/* v ← the buffers of args, `jobs` groups (b, a, x, y) of them: every b and a of one length n (2 ≤ n ≤ MAX_TAPS),
 * every x and y of one length, written to *len; returns n, or 0 with an exception set and no buffer held. */
static Py_ssize_t filter_jobs(PyObject *args, int jobs, Py_buffer *v, Py_ssize_t *len) {
    static const char *const NAMES[4] = {"b", "a", "x", "y"};
    if (PyTuple_GET_SIZE(args) != 4 * jobs) {
        PyErr_Format(PyExc_TypeError, "%d arguments (b, a, x, y for each signal) are needed", 4 * jobs);
        return 0;
    }
    for (int held = 0; held < 4 * jobs; held++)
        if (!doubles(PyTuple_GET_ITEM(args, held), &v[held], held % 4 == 3, NAMES[held % 4])) {
            release(v, held);
            return 0;
        }
    Py_ssize_t n = v[0].shape[0];
    *len = v[2].shape[0];
    int fits = n >= 2 && n <= MAX_TAPS;
    for (int j = 0; j < jobs; j++)
        fits &= v[4 * j].shape[0] == n && v[4 * j + 1].shape[0] == n && v[4 * j + 2].shape[0] == *len
                && v[4 * j + 3].shape[0] == *len;
    if (fits)
        return n;
    PyErr_Format(PyExc_ValueError, "every b and a of one length in 2..%d, every x and y of one length are needed",
                 MAX_TAPS);
    release(v, 4 * jobs);
    return 0;
}

/* The filters of args, one signal (jobs 1: iir_N) or two side by side (jobs 2: iir_Nx2), the GIL released. */
static PyObject *filter(PyObject *args, int jobs) {
    Py_buffer v[8];
    Py_ssize_t len, n = filter_jobs(args, jobs, v, &len);
    if (!n)
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    if (jobs == 1)
        KERNELS[n](v[0].buf, v[1].buf, v[2].buf, v[3].buf, len);
    else
        PAIR_KERNELS[n](v[0].buf, v[1].buf, v[2].buf, v[3].buf, v[4].buf, v[5].buf, v[6].buf, v[7].buf, len);
    Py_END_ALLOW_THREADS
    release(v, 4 * jobs);
    Py_RETURN_NONE;
}

/* iir(b, a, x, y): y ← the filter b/a (same length n, 2 ≤ n ≤ MAX_TAPS, a[0] = 1) applied to x, from zero state. */
static PyObject *iir(PyObject *self, PyObject *args) { return filter(args, 1); }

/* iir_pair(b0, a0, x0, y0, b1, a1, x1, y1): y0 ← the filter b0/a0 applied to x0 and y1 ← b1/a1 applied to x1, side
 * by side; every b, a of one length n (2 ≤ n ≤ MAX_TAPS, a[0] = 1), x0, x1, y0, y1 of one length. */
static PyObject *iir_pair(PyObject *self, PyObject *args) { return filter(args, 2); }

static PyMethodDef METHODS[] = {
    {"iir", iir, METH_VARARGS, "iir(b, a, x, y): y <- scipy.signal.lfilter(b, a, x); b, a normalised, equal length."},
    {"iir_pair", iir_pair, METH_VARARGS,
     "iir_pair(b0, a0, x0, y0, b1, a1, x1, y1): iir(b0, a0, x0, y0) and iir(b1, a1, x1, y1) side by side."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_iir", NULL, -1, METHODS};

PyMODINIT_FUNC PyInit__iir(void) { return PyModule_Create(&MODULE); }
