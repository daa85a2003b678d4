/* The look-up kernels of radiometry.correction, compiled at install: the C twins of its Numba kernels (same
 * arguments, same results; tests/test_native_kernels.py compares them). Why C: Numba's runtime costs ~111 MB of
 * memory in every process that calls a kernel (issue 17); see mapping/_ckernels.c. */
#include "_buffers.h"
#include "_ckernels_simd.h"
#include "_ckernels_bucket.h"

#if defined(__GNUC__) || defined(__clang__)
#define RM_UNLIKELY(x) __builtin_expect((x), 0)
#else
#define RM_UNLIKELY(x) (x)
#endif

static inline uint32_t q_at(const void *q, int wide, Py_ssize_t i)
{
    return wide ? ((const uint32_t *)q)[i] : (uint32_t)((const uint16_t *)q)[i];
}

/* the three-channel gather, one loop per width of q (an index past the table stops it: returns 1) */
#define LOOKUP_RGB_LOOP(NAME, QTYPE)                                                                               \
    static int NAME(const uint8_t *img, const QTYPE *q, const uint32_t *k, const uint8_t *table, uint64_t nt,   \
                    uint8_t *out, Py_ssize_t pixels)                                                           \
    {                                                                                                          \
        for (Py_ssize_t p = 0; p < pixels; p++) {                                                              \
            Py_ssize_t b = 3 * p;                                                                              \
            uint64_t j0 = (uint64_t)q[b] + k[img[b]];                                                          \
            uint64_t j1 = (uint64_t)q[b + 1] + k[256 + img[b + 1]];                                            \
            uint64_t j2 = (uint64_t)q[b + 2] + k[512 + img[b + 2]];                                            \
            if (RM_UNLIKELY((j0 >= nt) | (j1 >= nt) | (j2 >= nt)))                                             \
                return 1;                                                                                      \
            out[b] = table[j0];                                                                                \
            out[b + 1] = table[j1];                                                                            \
            out[b + 2] = table[j2];                                                                            \
        }                                                                                                      \
        return 0;                                                                                              \
    }
LOOKUP_RGB_LOOP(lookup_rgb_loop, uint32_t)
LOOKUP_RGB_LOOP(lookup_rgb_loop16, uint16_t)

/* out[b + c] = table[q[qi] + k[c, img[b + c]]] for pixel p (b = p * channels), qi = b + c (``per_channel``, three
 * channels) or p (one gain per pixel); fails on an index past the table */
static PyObject *lookup(PyObject *args, int per_channel)
{
    PyObject *oi, *oq, *ok, *ot, *oo;
    Py_ssize_t channels = 3;
    Py_buffer v[5] = {{0}};
    if (per_channel ? !PyArg_ParseTuple(args, "OOOOO", &oi, &oq, &ok, &ot, &oo)
                    : !PyArg_ParseTuple(args, "OOOOOn", &oi, &oq, &ok, &ot, &oo, &channels))
        return NULL;
    if (rm_get(oi, &v[0], 'u', 1, 1, 0, "img") || rm_get_of(oq, &v[1], 'u', 2, 'u', 4, -1, 0, "q")
        || rm_get(ok, &v[2], 'u', 4, 2, 0, "k")
        || rm_get(ot, &v[3], 'u', 1, 1, 0, "table") || rm_get(oo, &v[4], 'u', 1, 1, 1, "out"))
        goto fail;
    Py_ssize_t n = v[0].shape[0], pixels = channels > 0 ? n / channels : 0;
    if (channels < 1 || n % channels) {
        PyErr_Format(PyExc_ValueError, "img: %zd values are not whole pixels of %zd channels", n, channels);
        goto fail;
    }
    if (rm_items(&v[1]) != (per_channel ? n : pixels) || rm_dim(&v[2], 0, channels, "k")
        || rm_dim(&v[2], 1, 256, "k") || rm_dim(&v[4], 0, n, "out")) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "q: needs one gain index per value (per pixel when shared)");
        goto fail;
    }
    const uint8_t *img = v[0].buf, *table = v[3].buf;
    const uint32_t *k = v[2].buf;
    const void *q = v[1].buf;
    const int wide = v[1].itemsize == 4;
    uint8_t *out = v[4].buf;
    const uint64_t nt = (uint64_t)v[3].shape[0];
    int bad = 0;
    Py_BEGIN_ALLOW_THREADS
    if (per_channel && wide)
        bad = lookup_rgb_loop(img, (const uint32_t *)q, k, table, nt, out, pixels);
    else if (per_channel)
        bad = lookup_rgb_loop16(img, (const uint16_t *)q, k, table, nt, out, pixels);
    else
        for (Py_ssize_t p = 0; p < pixels && !bad; p++) {
            uint64_t level = q_at(q, wide, p);
            Py_ssize_t b = p * channels;
            for (Py_ssize_t c = 0; c < channels; c++) {
                uint64_t j = level + k[c * 256 + img[b + c]];
                if (j >= nt) {
                    bad = 1;
                    break;
                }
                out[b + c] = table[j];
            }
        }
    Py_END_ALLOW_THREADS
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "q, k: an index past the end of table");
        goto fail;
    }
    rm_release(v, 5);
    Py_RETURN_NONE;
fail:
    rm_release(v, 5);
    return NULL;
}

static PyObject *lookup_rgb(PyObject *self, PyObject *args)
{
    return lookup(args, 1);
}

static PyObject *lookup_shared(PyObject *self, PyObject *args)
{
    return lookup(args, 0);
}

/* The buffers of correct_simd / correct_bucket, checked: img, qplan (blocks, channels, q_last) of q_size-byte
 * items, plan (channels, plan_bytes), out; returns the number of whole blocks, or -1 with the error set (the
 * buffers released). */
static Py_ssize_t correct_buffers(PyObject *oi, PyObject *oq, PyObject *op, PyObject *oo, Py_ssize_t channels,
                                  int q_size, Py_ssize_t q_last, Py_ssize_t plan_bytes, Py_buffer v[4])
{
    if (rm_get(oi, &v[0], 'u', 1, 1, 0, "img") || rm_get(oq, &v[1], 'u', q_size, 3, 0, "qplan")
        || rm_get(op, &v[2], 'u', 1, 2, 0, "plan") || rm_get(oo, &v[3], 'u', 1, 1, 1, "out"))
        goto fail;
    Py_ssize_t n = v[0].shape[0];
    if ((channels != 1 && channels != 3) || n % channels) {
        PyErr_Format(PyExc_ValueError, "img: %zd values are not whole pixels of 1 or 3 channels (%zd)", n, channels);
        goto fail;
    }
    Py_ssize_t blocks = v[1].shape[0];
    if (blocks * 64 > n / channels || rm_dim(&v[1], 1, channels, "qplan") || rm_dim(&v[1], 2, q_last, "qplan")
        || rm_dim(&v[2], 0, channels, "plan") || rm_dim(&v[2], 1, plan_bytes, "plan")
        || rm_dim(&v[3], 0, n, "out")) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_ValueError, "qplan: more blocks of 64 pixels than img has");
        goto fail;
    }
    return blocks;
fail:
    rm_release(v, 4);
    return -1;
}

/* correct_simd(img, qplan, plan, out, channels, clamp): the uint8 correction of the first (pixels // 64) * 64
 * pixels with AVX-512 register look-ups (_ckernels_simd.h); returns the number of pixels done (0 where the CPU
 * lacks the instructions: the caller does the rest with lookup_rgb / lookup_shared) */
static PyObject *correct_simd(PyObject *self, PyObject *args)
{
    PyObject *oi, *oq, *op, *oo;
    Py_ssize_t channels;
    int clamp;
    Py_buffer v[4] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOOnp", &oi, &oq, &op, &oo, &channels, &clamp))
        return NULL;
    Py_ssize_t blocks = correct_buffers(oi, oq, op, oo, channels, 2, 64, RM_PLAN_BYTES, v);
    if (blocks < 0)
        return NULL;
    Py_ssize_t done = 0;
#if RM_HAVE_SIMD
    if (rm_simd_supported()) {
        Py_BEGIN_ALLOW_THREADS
        rm_correct_simd(v[0].buf, v[1].buf, v[2].buf, v[3].buf, blocks, (int)channels, clamp);
        Py_END_ALLOW_THREADS
        done = blocks * 64;
    }
#endif
    rm_release(v, 4);
    return PyLong_FromSsize_t(done);
}

/* correct_bucket(img, qplan, plan, out, channels): correct_simd with the bucket kernel (_ckernels_bucket.h);
 * qplan (blocks, channels, 128) uint8 (the low then the high bytes of q << s), plan (channels, RM_BK_PLAN_BYTES) */
static PyObject *correct_bucket(PyObject *self, PyObject *args)
{
    PyObject *oi, *oq, *op, *oo;
    Py_ssize_t channels;
    Py_buffer v[4] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOOn", &oi, &oq, &op, &oo, &channels))
        return NULL;
    Py_ssize_t blocks = correct_buffers(oi, oq, op, oo, channels, 1, 128, RM_BK_PLAN_BYTES, v);
    if (blocks < 0)
        return NULL;
    for (Py_ssize_t c = 0; c < channels; c++)
        if (((const uint8_t *)v[2].buf)[c * RM_BK_PLAN_BYTES + RM_BK_PARAMS] > RM_BK_NMAX) {
            PyErr_Format(PyExc_ValueError, "plan: channel %zd has more than %d thresholds per bucket", c, RM_BK_NMAX);
            rm_release(v, 4);
            return NULL;
        }
    Py_ssize_t done = 0;
#if RM_HAVE_SIMD
    if (rm_simd_supported()) {
        Py_BEGIN_ALLOW_THREADS
        rm_bk_correct(v[0].buf, v[1].buf, v[2].buf, v[3].buf, blocks, (int)channels);
        Py_END_ALLOW_THREADS
        done = blocks * 64;
    }
#endif
    rm_release(v, 4);
    return PyLong_FromSsize_t(done);
}

/* out[p, c] = lut[c, img[p, c]] * gain[p, 0 or c] (float32) */
static PyObject *irradiance(PyObject *self, PyObject *args)
{
    PyObject *oi, *ol, *og, *oo;
    Py_buffer v[4] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOO", &oi, &ol, &og, &oo))
        return NULL;
    if (rm_get(oi, &v[0], 'u', 1, 2, 0, "img") || rm_get(ol, &v[1], 'f', 4, 2, 0, "lut")
        || rm_get(og, &v[2], 'f', 4, 2, 0, "gain") || rm_get(oo, &v[3], 'f', 4, 2, 1, "out"))
        goto fail;
    Py_ssize_t n = v[0].shape[0], ch = v[0].shape[1], cg = v[2].shape[1];
    if (rm_dim(&v[1], 0, ch, "lut") || rm_dim(&v[1], 1, 256, "lut") || rm_dim(&v[2], 0, n, "gain")
        || rm_dim(&v[3], 0, n, "out") || rm_dim(&v[3], 1, ch, "out"))
        goto fail;
    if (cg != 1 && cg != ch) {
        PyErr_Format(PyExc_ValueError, "gain: needs 1 or %zd columns, got %zd", ch, cg);
        goto fail;
    }
    const uint8_t *img = v[0].buf;
    const float *lut = v[1].buf, *gain = v[2].buf;
    float *out = v[3].buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < n; p++)
        for (Py_ssize_t c = 0; c < ch; c++)
            out[p * ch + c] = lut[c * 256 + img[p * ch + c]] * gain[p * cg + (cg == 1 ? 0 : c)];
    Py_END_ALLOW_THREADS
    rm_release(v, 4);
    Py_RETURN_NONE;
fail:
    rm_release(v, 4);
    return NULL;
}

static PyMethodDef methods[] = {
    {"lookup_rgb", lookup_rgb, METH_VARARGS, "uint8 correction, a gain index per value (three channels)."},
    {"lookup_shared", lookup_shared, METH_VARARGS, "uint8 correction, one gain index per pixel."},
    {"correct_simd", correct_simd, METH_VARARGS, "uint8 correction with AVX-512 register look-ups (64-pixel blocks)."},
    {"correct_bucket", correct_bucket, METH_VARARGS, "correct_simd's bucket kernel (spread-out thresholds)."},
    {"irradiance", irradiance, METH_VARARGS, "Irradiance of a uint8 image: lut[c, I] * gain."},
    RM_THREAD_METHODS,
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ckernels",
                                    "radiomap's compiled correction kernels (see the C source's header).", -1,
                                    methods};

PyMODINIT_FUNC PyInit__ckernels(void)
{
    rm_simd_init();
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && (PyModule_AddIntConstant(m, "openmp", RM_OPENMP) < 0
                      || PyModule_AddIntConstant(m, "ABI", RM_ABI) < 0
                      || PyModule_AddIntConstant(m, "simd", rm_simd_supported()) < 0
                      || PyModule_AddIntConstant(m, "bucket_nmax", RM_BK_NMAX) < 0)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
