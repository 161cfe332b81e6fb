/* The compiled hub path (docs/performance.md "The compiled hub path", issue 26).
 *
 * One call per sample does what EstimatorPipeline.stages does for a measured sample up to
 * the hub_loads record, and writes that record's JSON text:
 *
 *     I = Mf accel;  z = I (- D q);  H_static = Rinv (z - S T)
 *     buf = [x; z; T];  y = G buf;  x = y[:n]            (the load filter's fused product)
 *     e = y[n+6:n+12];  nis = |y[n+12:]|^2
 *     v = (1 - beta) v + Mb e;  q = |v|^2;  transient = q > threshold
 *     var = (Q2 T as 6 x 7) T;  sigma = sqrt|var|;  uncertain = any(var > bound2)
 *
 * and, for a design whose error gain is diagonal (estimator/filter_sigma.py, FilterSigma
 * .update: the filtered loads' own error sigma, `sigma_filter`):
 *
 *     u = Rinv' e;  Mf += beta_fast (u u' - Mf);  [Ms += beta_slow (u u' - Ms)]
 *     ex = max(diag Mf, diag Ms) - diag Bu;  s = sqrt(modelled + g2 max(ex, 0));  max(s, floor)
 *
 * Every matrix comes from Python (the designs, the angles in force); this file only knows
 * small dense matrix-vector products, elementwise operations and the record's text. The
 * products are computed by numpy's own BLAS (cblas_dgemv / cblas_ddot, their addresses
 * handed over by the Python side from the library numpy itself loaded), called with the
 * arguments numpy's `ndarray.dot` passes for a C-contiguous matrix, and the elementwise steps
 * are the same IEEE operations in the same order (built with -ffp-contract=off: no fused
 * multiply-add), so the results are bit for bit those of the numpy reference path.
 *
 * The JSON text is the stdlib encoder's (separators "," and ":", floats by float.__repr__,
 * non-finite numbers null): PyOS_double_to_string(x, 'r', ...) is what float.__repr__ calls.
 * No numpy headers: buffers through the buffer protocol.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* CBLAS enums (cblas.h values) */
#define ROW_MAJOR 101
#define COL_MAJOR 102
#define NO_TRANS 111

typedef void (*dgemv64_t)(int, int, int64_t, int64_t, double, const double *, int64_t,
                          const double *, int64_t, double, double *, int64_t);
typedef double (*ddot64_t)(int64_t, const double *, int64_t, const double *, int64_t);
typedef void (*dgemv32_t)(int, int, int32_t, int32_t, double, const double *, int32_t,
                          const double *, int32_t, double, double *, int32_t);
typedef double (*ddot32_t)(int32_t, const double *, int32_t, const double *, int32_t);

static void *g_gemv = NULL;
static void *g_ddot = NULL;
static int g_ilp64 = 0;

/* y = A x, A (m, k) as numpy's ndarray.dot passes it to cblas_dgemv: a C-contiguous A
 * row-major with lda = k, any other (one-segment, i.e. Fortran-contiguous) A column-major with
 * lda = m; alpha 1, beta 0, unit strides */
static inline void gemv_o(const double *A, Py_ssize_t m, Py_ssize_t k, int fortran,
                          const double *x, double *y) {
    int order = fortran ? COL_MAJOR : ROW_MAJOR;
    Py_ssize_t lda = fortran ? (m > 1 ? m : 1) : (k > 1 ? k : 1);
    if (g_ilp64)
        ((dgemv64_t)g_gemv)(order, NO_TRANS, m, k, 1.0, A, lda, x, 1, 0.0, y, 1);
    else
        ((dgemv32_t)g_gemv)(order, NO_TRANS, (int32_t)m, (int32_t)k, 1.0, A, (int32_t)lda, x,
                            1, 0.0, y, 1);
}

#define gemv(A, m, k, x, y) gemv_o((A), (m), (k), 0, (x), (y))

/* numpy's DOUBLE_dot: sum = 0.; sum += cblas_ddot(n, a, 1, b, 1) */
static inline double ddot(const double *a, const double *b, Py_ssize_t n) {
    double s = 0.0;
    if (g_ilp64)
        s += ((ddot64_t)g_ddot)(n, a, 1, b, 1);
    else
        s += ((ddot32_t)g_ddot)((int32_t)n, a, 1, b, 1);
    return s;
}

static PyObject *set_blas(PyObject *self, PyObject *args) {
    unsigned long long gemv_addr, ddot_addr;
    int ilp64;
    if (!PyArg_ParseTuple(args, "KKp", &gemv_addr, &ddot_addr, &ilp64))
        return NULL;
    g_gemv = (void *)(uintptr_t)gemv_addr;
    g_ddot = (void *)(uintptr_t)ddot_addr;
    g_ilp64 = ilp64;
    Py_RETURN_NONE;
}

/* -- the plan: the matrices and state arrays of one design / angles ------------------------ */
enum { B_MF, B_RINV, B_S, B_G, B_BUF, B_MB, B_V, B_Q2, B_D, B_BOUND,
       /* FilterSigma (optional): its design constants and its two averages */
       B_FRINV, B_FBU, B_FMOD, B_FG2, B_FMF, B_FMS, B_FFLOOR, NB };
static const char *B_NAMES[NB] = {"Mf", "Rinv", "S", "G", "buf", "Mb", "v", "Q2", "D",
                                  "bound2", "fs_Rinv", "fs_Bu", "fs_modelled", "fs_g2",
                                  "fs_Mf", "fs_Ms", "fs_floor"};

typedef struct {
    PyObject_HEAD
    Py_buffer b[NB];
    int have[NB];
    int fortran[NB]; /* the matrix is Fortran-ordered (numpy's dot: column-major) */
    Py_ssize_t n;      /* filter states */
    Py_ssize_t na;     /* accelerometer columns */
    Py_ssize_t nt;     /* cells (7) */
    Py_ssize_t nd;     /* drive loads (0: none) */
    Py_ssize_t ny;     /* rows of G */
    Py_ssize_t nb;     /* entries of buf = n + 6 + nt */
    Py_ssize_t nq;     /* rows of Q2 (6 * nt) */
    double one_minus_beta, threshold;
    int have_fs;                 /* FilterSigma's step in the kernel (a diagonal error gain) */
    double beta_fast, beta_slow; /* its two averages' weights */
    PyObject *frame_json; /* bytes: the frame name as a JSON string */
} Plan;

static void plan_dealloc(Plan *p) {
    for (int i = 0; i < NB; i++)
        if (p->have[i])
            PyBuffer_Release(&p->b[i]);
    Py_XDECREF(p->frame_json);
    Py_TYPE(p)->tp_free((PyObject *)p);
}

static int get_buf(Plan *p, int i, PyObject *obj, int writable, int ndim, Py_ssize_t r,
                   Py_ssize_t c) {
    int flags = PyBUF_ANY_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, &p->b[i], flags) < 0)
        return -1;
    p->have[i] = 1;
    Py_buffer *b = &p->b[i];
    if (b->itemsize != 8 || b->format == NULL || strcmp(b->format, "d") != 0 ||
        b->ndim != ndim || b->shape[0] != r || (ndim == 2 && b->shape[1] != c)) {
        PyErr_Format(PyExc_ValueError, "plan: %s has the wrong type or shape", B_NAMES[i]);
        return -1;
    }
    /* numpy's C_CONTIGUOUS flag, as its dot tests it: a 1-D or C-ordered 2-D buffer */
    p->fortran[i] = ndim == 2 && !PyBuffer_IsContiguous(b, 'C');
    if (p->fortran[i] && writable) {
        PyErr_Format(PyExc_ValueError, "plan: %s must be C-contiguous", B_NAMES[i]);
        return -1;
    }
    return 0;
}

static int dims(PyObject *obj, const char *name, Py_ssize_t *cols) {
    Py_buffer b;
    if (PyObject_GetBuffer(obj, &b, PyBUF_ANY_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    int ok = b.ndim == 2 && b.shape[0] == 6;
    *cols = ok ? b.shape[1] : 0;
    PyBuffer_Release(&b);
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "plan: %s must be (6, k)", name);
        return -1;
    }
    return 0;
}

static PyObject *plan_new(PyTypeObject *type, PyObject *args, PyObject *kw) {
    static char *kwlist[] = {"Mf", "Rinv", "S", "G", "buf", "Mb", "v", "Q2", "D", "bound2",
                             "n", "one_minus_beta", "threshold", "frame_json", "fs_Rinv",
                             "fs_Bu", "fs_modelled", "fs_g2", "fs_Mf", "fs_Ms", "fs_floor",
                             "beta_fast", "beta_slow", NULL};
    PyObject *o[NB];
    Py_ssize_t n;
    double omb, thr, bfast = 0.0, bslow = 0.0;
    PyObject *frame;
    for (int i = B_FRINV; i < NB; i++)
        o[i] = Py_None;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OOOOOOOOOOnddS|$OOOOOOOdd", kwlist, &o[0],
                                     &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8],
                                     &o[9], &n, &omb, &thr, &frame, &o[B_FRINV], &o[B_FBU],
                                     &o[B_FMOD], &o[B_FG2], &o[B_FMF], &o[B_FMS],
                                     &o[B_FFLOOR], &bfast, &bslow))
        return NULL;
    Plan *p = (Plan *)type->tp_alloc(type, 0);
    if (p == NULL)
        return NULL;
    p->n = n;
    p->one_minus_beta = omb;
    p->threshold = thr;
    Py_INCREF(frame);
    p->frame_json = frame;
    /* shapes follow from Mf (6, na), S (6, nt), D (6, nd) */
    if (dims(o[B_MF], "Mf", &p->na) || dims(o[B_S], "S", &p->nt))
        goto fail;
    p->nd = 0;
    if (o[B_D] != Py_None && dims(o[B_D], "D", &p->nd))
        goto fail;
    p->nb = n + 6 + p->nt;
    p->ny = n + 18;
    p->nq = 6 * p->nt;
    if (p->ny > 256 || p->nq > 64 || p->nt > 64 || p->na > 64 || p->nd > 64) {
        PyErr_SetString(PyExc_ValueError, "plan: design too large for the kernel");
        goto fail;
    }
    if (get_buf(p, B_MF, o[B_MF], 0, 2, 6, p->na) || get_buf(p, B_RINV, o[B_RINV], 0, 2, 6, 6) ||
        get_buf(p, B_S, o[B_S], 0, 2, 6, p->nt) || get_buf(p, B_G, o[B_G], 0, 2, p->ny, p->nb) ||
        get_buf(p, B_BUF, o[B_BUF], 1, 1, p->nb, 0) || get_buf(p, B_MB, o[B_MB], 0, 2, 6, 6) ||
        get_buf(p, B_V, o[B_V], 1, 1, 6, 0) || get_buf(p, B_Q2, o[B_Q2], 0, 2, p->nq, p->nt) ||
        get_buf(p, B_BOUND, o[B_BOUND], 0, 1, 6, 0))
        goto fail;
    if (p->nd && get_buf(p, B_D, o[B_D], 0, 2, 6, p->nd))
        goto fail;
    /* FilterSigma: all of its arrays (the floor optional) or none */
    p->have_fs = o[B_FRINV] != Py_None;
    if (p->have_fs) {
        p->beta_fast = bfast;
        p->beta_slow = bslow;
        if (get_buf(p, B_FRINV, o[B_FRINV], 0, 2, 6, 6) || get_buf(p, B_FBU, o[B_FBU], 0, 2, 6, 6) ||
            get_buf(p, B_FMOD, o[B_FMOD], 0, 1, 6, 0) || get_buf(p, B_FG2, o[B_FG2], 0, 1, 6, 0) ||
            get_buf(p, B_FMF, o[B_FMF], 1, 2, 6, 6) || get_buf(p, B_FMS, o[B_FMS], 1, 2, 6, 6))
            goto fail;
        if (p->fortran[B_FBU]) { /* read elementwise: row-major */
            PyErr_SetString(PyExc_ValueError, "plan: fs_Bu must be C-contiguous");
            goto fail;
        }
        if (o[B_FFLOOR] != Py_None && get_buf(p, B_FFLOOR, o[B_FFLOOR], 0, 1, 6, 0))
            goto fail;
    }
    return (PyObject *)p;
fail:
    Py_DECREF(p);
    return NULL;
}

/* -- JSON text ------------------------------------------------------------------------------ */
typedef struct {
    char *s;
    Py_ssize_t len, cap;
} Out;

static int out_put(Out *o, const char *s, Py_ssize_t n) {
    if (o->len + n > o->cap) {
        Py_ssize_t cap = 2 * (o->len + n);
        char *t = PyMem_Realloc(o->s, cap);
        if (t == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        o->s = t;
        o->cap = cap;
    }
    memcpy(o->s + o->len, s, n);
    o->len += n;
    return 0;
}

#define PUT(o, lit) out_put((o), (lit), (Py_ssize_t)sizeof(lit) - 1)

static int out_float(Out *o, double x) {
    if (!isfinite(x))
        return PUT(o, "null");
    char *r = PyOS_double_to_string(x, 'r', 0, Py_DTSF_ADD_DOT_0, NULL);
    if (r == NULL)
        return -1;
    int rc = out_put(o, r, (Py_ssize_t)strlen(r));
    PyMem_Free(r);
    return rc;
}

static int out_floats(Out *o, const double *x, Py_ssize_t n) {
    if (PUT(o, "["))
        return -1;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (i && PUT(o, ","))
            return -1;
        if (out_float(o, x[i]))
            return -1;
    }
    return PUT(o, "]");
}

/* a flag: plain ASCII without '"', '\\' or control characters (the vocabulary of
 * docs/telemetry.md); anything else is refused (the caller takes the reference path) */
static int out_flag(Out *o, PyObject *s) {
    Py_ssize_t n;
    const char *u = PyUnicode_AsUTF8AndSize(s, &n);
    if (u == NULL)
        return -1;
    for (Py_ssize_t i = 0; i < n; i++) {
        unsigned char c = (unsigned char)u[i];
        if (c < 0x20 || c >= 0x7f || c == '"' || c == '\\') {
            PyErr_SetString(PyExc_ValueError, "flag needs escaping");
            return -1;
        }
    }
    if (PUT(o, "\"") || out_put(o, u, n) || PUT(o, "\""))
        return -1;
    return 0;
}

/* -- the per-sample step ------------------------------------------------------------------ */
/* numpy's maximum on doubles: NaN propagates (either side), else a >= b ? a : b */
static inline double np_max(double a, double b) {
    return (a >= b || isnan(a)) ? a : b;
}

/* FilterSigma.update (estimator/filter_sigma.py) for a design with a diagonal error gain,
 * on the innovation e: the two averages updated in place, the published sigma into sf.
 * `started`: the averages hold samples (else they start at Bu); `slow`: the slow one takes
 * this sample (samples since the start >= settle). numpy's operations, in its order. */
static void filter_sigma_step(Plan *p, const double *e, int started, int slow, double *sf) {
    const int *F = p->fortran;
    const double *Bu = p->b[B_FBU].buf, *mod = p->b[B_FMOD].buf, *g2 = p->b[B_FG2].buf;
    double *Mf = p->b[B_FMF].buf, *Ms = p->b[B_FMS].buf;
    double u[6];
    gemv_o(p->b[B_FRINV].buf, 6, 6, F[B_FRINV], e, u); /* u = Rinv.dot(e) */
    if (!started) {
        memcpy(Mf, Bu, 36 * sizeof(double));
        memcpy(Ms, Bu, 36 * sizeof(double));
    }
    double bf = p->beta_fast, bs = p->beta_slow;
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) {
            double uu = u[i] * u[j]; /* np.multiply.outer(u, u) */
            double d = uu - Mf[6 * i + j];
            d = bf * d;
            Mf[6 * i + j] = Mf[6 * i + j] + d;
        }
    if (slow)
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < 6; j++) {
                double uu = u[i] * u[j];
                double d = uu - Ms[6 * i + j];
                d = bs * d;
                Ms[6 * i + j] = Ms[6 * i + j] + d;
            }
    for (int i = 0; i < 6; i++) {
        double ex = np_max(Mf[7 * i], Ms[7 * i]) - Bu[7 * i];
        double t = g2[i] * np_max(ex, 0.0);
        sf[i] = sqrt(mod[i] + t);
    }
    if (p->have[B_FFLOOR]) {
        const double *fl = p->b[B_FFLOOR].buf;
        for (int i = 0; i < 6; i++)
            sf[i] = np_max(sf[i], fl[i]);
    }
}

/* step(T, accel, q, out, seq, sync, t, omega, flags, tail[, encode[, fs]]) -> (json bytes,
 * nis, tq, transient, uncertain)
 *   T (nt,), accel (na,), q (nd,) or None: the sample's measured values (all finite);
 *   out (42 + n,) float64, fresh: written [I | H_static | H | e | sigma | z | x | sigma_filter];
 *   fs: FilterSigma's step here (bit 0; the plan must hold its arrays), its averages already
 *   started (bit 1), the slow one taking this sample (bit 2); without bit 0 sigma_filter
 *   is not written (the caller's Python computes it);
 *   flags: a list of str, the filter's flags; "transient", then the tail flags (tuple)
 *   are appended by the caller's order: this function appends "transient" and
 *   "angles_uncertain" at their places (tail: between them).
 */
static PyObject *plan_step(Plan *p, PyObject *args) {
    Py_buffer bT, bA, bQ, bO;
    PyObject *qobj, *omega, *flags, *tail, *seq, *sync;
    double t;
    int encode = 1, fs = 0;
    if (!PyArg_ParseTuple(args, "y*y*Ow*OOdOO!O!|pi", &bT, &bA, &qobj, &bO, &seq, &sync, &t,
                          &omega, &PyList_Type, &flags, &PyTuple_Type, &tail, &encode, &fs))
        return NULL;
    PyObject *result = NULL;
    int haveQ = 0;
    Out js = {NULL, 0, 0};
    Py_ssize_t n = p->n, nt = p->nt, na = p->na, nd = p->nd;
    if (bT.len != nt * 8 || bA.len != na * 8 || bO.len != (42 + n) * 8 ||
        !PyLong_Check(seq) || !PyLong_Check(sync)) {
        PyErr_SetString(PyExc_ValueError, "step: wrong sizes");
        goto done;
    }
    if ((fs & 1) && !p->have_fs) {
        PyErr_SetString(PyExc_ValueError, "step: the plan holds no FilterSigma");
        goto done;
    }
    if (encode && !(fs & 1)) {
        PyErr_SetString(PyExc_ValueError, "step: the record's text needs sigma_filter");
        goto done;
    }
    const double *T = (const double *)bT.buf, *acc = (const double *)bA.buf;
    double *out = (double *)bO.buf;
    double *I = out, *Hs = out + 6, *H = out + 12, *e = out + 18, *sig = out + 24,
           *z = out + 30, *x = out + 36, *sf = out + 36 + n;
    const double *Mf = p->b[B_MF].buf, *Rinv = p->b[B_RINV].buf, *S = p->b[B_S].buf,
                 *G = p->b[B_G].buf, *Mb = p->b[B_MB].buf, *Q2 = p->b[B_Q2].buf;
    double *buf = p->b[B_BUF].buf, *v = p->b[B_V].buf;
    const double *bound2 = p->b[B_BOUND].buf;
    const int *F = p->fortran;
    double tmp[64], y[256], q2[64];
    /* inertial loads and the static estimate */
    gemv_o(Mf, 6, na, F[B_MF], acc, I);
    if (nd) {
        if (qobj == Py_None) {
            PyErr_SetString(PyExc_ValueError, "step: drive loads missing");
            goto done;
        }
        if (PyObject_GetBuffer(qobj, &bQ, PyBUF_SIMPLE) < 0)
            goto done;
        haveQ = 1;
        if (bQ.len != nd * 8) {
            PyErr_SetString(PyExc_ValueError, "step: wrong drive size");
            goto done;
        }
        gemv_o(p->b[B_D].buf, 6, nd, F[B_D], (const double *)bQ.buf, tmp);
        for (int i = 0; i < 6; i++)
            z[i] = I[i] - tmp[i];
    } else {
        for (int i = 0; i < 6; i++)
            z[i] = I[i];
    }
    gemv_o(S, 6, nt, F[B_S], T, tmp);
    for (int i = 0; i < 6; i++)
        tmp[i] = z[i] - tmp[i];
    gemv_o(Rinv, 6, 6, F[B_RINV], tmp, Hs);
    /* the load filter: [x+; H; e; L^-1 e] = G [x; z; T] */
    for (int i = 0; i < 6; i++)
        buf[n + i] = z[i];
    for (Py_ssize_t i = 0; i < nt; i++)
        buf[n + 6 + i] = T[i];
    gemv_o(G, p->ny, p->nb, F[B_G], buf, y);
    memcpy(buf, y, n * sizeof(double));
    memcpy(x, y, n * sizeof(double));
    memcpy(H, y + n, 6 * sizeof(double));
    memcpy(e, y + n + 6, 6 * sizeof(double));
    double nis = ddot(y + n + 12, y + n + 12, 6);
    /* the transient test: v = (1 - beta) v + Mb e */
    for (int i = 0; i < 6; i++)
        v[i] *= p->one_minus_beta;
    gemv_o(Mb, 6, 6, F[B_MB], e, tmp);
    for (int i = 0; i < 6; i++)
        v[i] += tmp[i];
    double tq = ddot(v, v, 6);
    int transient = tq > p->threshold;
    /* the filtered loads' own error sigma */
    if (fs & 1)
        filter_sigma_step(p, e, fs & 2, fs & 4, sf);
    /* the angles' share of the hub-load variance */
    gemv_o(Q2, p->nq, nt, F[B_Q2], T, q2);
    gemv(q2, 6, nt, T, tmp);
    int uncertain = 0;
    for (int i = 0; i < 6; i++) {
        sig[i] = sqrt(fabs(tmp[i]));
        if (tmp[i] > bound2[i])
            uncertain = 1;
    }
    /* flags, in the reference order: filter's, transient, tail, angles_uncertain */
    if (transient) {
        PyObject *f = PyUnicode_FromString("transient");
        if (f == NULL || PyList_Append(flags, f) < 0) {
            Py_XDECREF(f);
            goto done;
        }
        Py_DECREF(f);
    }
    for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(tail); i++)
        if (PyList_Append(flags, PyTuple_GET_ITEM(tail, i)) < 0)
            goto done;
    if (uncertain) {
        PyObject *f = PyUnicode_FromString("angles_uncertain");
        if (f == NULL || PyList_Append(flags, f) < 0) {
            Py_XDECREF(f);
            goto done;
        }
        Py_DECREF(f);
    }
    if (!encode) {
        result = Py_BuildValue("(OddOO)", Py_None, nis, tq, transient ? Py_True : Py_False,
                               uncertain ? Py_True : Py_False);
        goto done;
    }
    /* the record's text: {"seq":…,"sync":…,"t":…,"frame":…,"H":[…],"H_static":[…],
     * "sigma_angles":[…],"sigma_filter":[…],"omega":…,"flags":[…]} */
    {
        char num[32];
        long long sq = PyLong_AsLongLong(seq), sy = PyLong_AsLongLong(sync);
        if (PyErr_Occurred())
            goto done;
        if (PUT(&js, "{\"seq\":"))
            goto done;
        int k = snprintf(num, sizeof num, "%lld", sq);
        if (out_put(&js, num, k) || PUT(&js, ",\"sync\":"))
            goto done;
        k = snprintf(num, sizeof num, "%lld", sy);
        if (out_put(&js, num, k) || PUT(&js, ",\"t\":") || out_float(&js, t) ||
            PUT(&js, ",\"frame\":") ||
            out_put(&js, PyBytes_AS_STRING(p->frame_json), PyBytes_GET_SIZE(p->frame_json)) ||
            PUT(&js, ",\"H\":") || out_floats(&js, H, 6) || PUT(&js, ",\"H_static\":") ||
            out_floats(&js, Hs, 6) || PUT(&js, ",\"sigma_angles\":") ||
            out_floats(&js, sig, 6) || PUT(&js, ",\"sigma_filter\":") ||
            out_floats(&js, sf, 6) || PUT(&js, ",\"omega\":"))
            goto done;
        if (omega == Py_None) {
            if (PUT(&js, "null"))
                goto done;
        } else {
            double w = PyFloat_AsDouble(omega);
            if (w == -1.0 && PyErr_Occurred())
                goto done;
            if (out_float(&js, w))
                goto done;
        }
        if (PUT(&js, ",\"flags\":["))
            goto done;
        for (Py_ssize_t i = 0; i < PyList_GET_SIZE(flags); i++) {
            if (i && PUT(&js, ","))
                goto done;
            if (out_flag(&js, PyList_GET_ITEM(flags, i)))
                goto done;
        }
        if (PUT(&js, "]}"))
            goto done;
    }
    {
        PyObject *text = PyBytes_FromStringAndSize(js.s, js.len);
        if (text == NULL)
            goto done;
        result = Py_BuildValue("(NddOO)", text, nis, tq, transient ? Py_True : Py_False,
                               uncertain ? Py_True : Py_False);
    }
done:
    PyMem_Free(js.s);
    if (haveQ)
        PyBuffer_Release(&bQ);
    PyBuffer_Release(&bT);
    PyBuffer_Release(&bA);
    PyBuffer_Release(&bO);
    return result;
}

/* sos_step(sos, zi, x, y): one sample of n channels through the biquad sections of a
 * content filter (estimator/content.py ContentFilter._step, scipy's sosfilt loop, direct
 * form II transposed), the state zi (sections, 2, n) updated in place:
 *     y = b0 x + z0;  z0 = (b1 x - a1 y) + z1;  z1 = b2 x - a2 y
 * elementwise, in that order (numpy's operations on the row, bit for bit) */
static PyObject *k_sos_step(PyObject *self, PyObject *args) {
    Py_buffer bs, bz, bx, by;
    if (!PyArg_ParseTuple(args, "y*w*y*w*", &bs, &bz, &bx, &by))
        return NULL;
    PyObject *r = NULL;
    Py_ssize_t n = bx.len / 8, ns = bs.len / 48;
    if (bs.len != ns * 48 || bx.len != n * 8 || by.len != n * 8 || bz.len != ns * 2 * n * 8 ||
        n > 256) {
        PyErr_SetString(PyExc_ValueError, "sos_step: wrong sizes");
        goto done;
    }
    {
        const double *sos = bs.buf;
        double *zi = bz.buf, *y = by.buf;
        double cur[256];
        memcpy(cur, bx.buf, n * sizeof(double));
        for (Py_ssize_t s = 0; s < ns; s++) {
            const double *c = sos + 6 * s;
            double b0 = c[0], b1 = c[1], b2 = c[2], a1 = c[4], a2 = c[5];
            double *z0 = zi + (2 * s) * n, *z1 = zi + (2 * s + 1) * n;
            for (Py_ssize_t i = 0; i < n; i++) {
                double x = cur[i];
                double yy = b0 * x;
                yy = yy + z0[i];
                double t0 = b1 * x, t1 = a1 * yy;
                t0 = t0 - t1;
                z0[i] = t0 + z1[i];
                double u0 = b2 * x, u1 = a2 * yy;
                z1[i] = u0 - u1;
                cur[i] = yy;
            }
        }
        memcpy(y, cur, n * sizeof(double));
    }
    r = Py_None;
    Py_INCREF(r);
done:
    PyBuffer_Release(&bs);
    PyBuffer_Release(&bz);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&by);
    return r;
}


/* unpack_cal(data, codes, perm, gain, offset, out, status_idx) -> status values or None:
 * a sample's TPDOs joined in bit order (daq/bus/assembler.py SampleAssembler._pass_on):
 * every channel unpacked as struct's little-endian codes (one per channel, no padding),
 * out[k] = raw[perm[k]] * gain[k] + offset[k] (numpy's *= then +=), the raw integers at
 * status_idx returned. None, nothing written: a non-finite value (the caller's Python
 * path marks it missing) or values so large that sum() could overflow. */
static PyObject *k_unpack_cal(PyObject *self, PyObject *args) {
    Py_buffer bd, bc, bp, bg, bo, bout;
    PyObject *sidx;
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*w*O!", &bd, &bc, &bp, &bg, &bo, &bout,
                          &PyTuple_Type, &sidx))
        return NULL;
    PyObject *r = NULL;
    Py_ssize_t nc = bc.len, no = bout.len / 8;
    double raw[256];
    long long iv[256];
    const unsigned char *d = bd.buf, *codes = bc.buf;
    if (nc > 256 || bp.len != no * (Py_ssize_t)sizeof(Py_ssize_t) || bg.len != no * 8 ||
        bo.len != no * 8 || bout.len != no * 8) {
        PyErr_SetString(PyExc_ValueError, "unpack_cal: wrong sizes");
        goto done;
    }
    Py_ssize_t pos = 0;
    int finite = 1;
    double mag = 0.0;
    for (Py_ssize_t i = 0; i < nc; i++) {
        int sz;
        switch (codes[i]) {
        case '?': case 'b': case 'B': sz = 1; break;
        case 'h': case 'H': sz = 2; break;
        case 'i': case 'I': case 'f': sz = 4; break;
        case 'q': case 'Q': case 'd': sz = 8; break;
        default:
            PyErr_SetString(PyExc_ValueError, "unpack_cal: unknown code");
            goto done;
        }
        if (pos + sz > bd.len) {
            PyErr_SetString(PyExc_ValueError, "unpack_cal: data too short");
            goto done;
        }
        unsigned char b[8] = {0};
        memcpy(b, d + pos, sz); /* little-endian host (x86-64, aarch64) */
        pos += sz;
        iv[i] = 0;
        switch (codes[i]) {
        case '?': raw[i] = b[0] != 0; iv[i] = b[0] != 0; break;
        case 'b': { int8_t v; memcpy(&v, b, 1); raw[i] = v; iv[i] = v; break; }
        case 'B': raw[i] = b[0]; iv[i] = b[0]; break;
        case 'h': { int16_t v; memcpy(&v, b, 2); raw[i] = v; iv[i] = v; break; }
        case 'H': { uint16_t v; memcpy(&v, b, 2); raw[i] = v; iv[i] = v; break; }
        case 'i': { int32_t v; memcpy(&v, b, 4); raw[i] = v; iv[i] = v; break; }
        case 'I': { uint32_t v; memcpy(&v, b, 4); raw[i] = v; iv[i] = v; break; }
        case 'q': { int64_t v; memcpy(&v, b, 8); raw[i] = (double)v; iv[i] = v; break; }
        case 'Q': { uint64_t v; memcpy(&v, b, 8); raw[i] = (double)v; iv[i] = (long long)v;
                    if (v > (uint64_t)INT64_MAX) { PyErr_SetString(PyExc_ValueError,
                        "unpack_cal: status too large"); goto done; } break; }
        case 'f': { float v; memcpy(&v, b, 4); raw[i] = v; break; }
        case 'd': { double v; memcpy(&v, b, 8); raw[i] = v; break; }
        }
        if (!isfinite(raw[i]))
            finite = 0;
        else
            mag += fabs(raw[i]);
    }
    /* the reference's test is sum(raw) finite: the same as every value finite while no
     * partial sum can overflow, in whatever order it adds (sum |raw| < 1e300); a sample
     * beyond that goes to the reference */
    if (!(mag < 1e300))
        finite = 0;
    if (pos != bd.len) {
        PyErr_SetString(PyExc_ValueError, "unpack_cal: data too long");
        goto done;
    }
    if (!finite) {
        r = Py_None;
        Py_INCREF(r);
        goto done;
    }
    {
        const Py_ssize_t *perm = bp.buf;
        const double *g = bg.buf, *o = bo.buf;
        double *out = bout.buf;
        for (Py_ssize_t k = 0; k < no; k++) {
            if (perm[k] < 0 || perm[k] >= nc) {
                PyErr_SetString(PyExc_ValueError, "unpack_cal: perm out of range");
                goto done;
            }
        }
        Py_ssize_t ns = PyTuple_GET_SIZE(sidx);
        PyObject *st = PyTuple_New(ns);
        if (st == NULL)
            goto done;
        for (Py_ssize_t k = 0; k < ns; k++) {
            Py_ssize_t i = PyLong_AsSsize_t(PyTuple_GET_ITEM(sidx, k));
            if (i < 0 || i >= nc || strchr("?fd", codes[i]) != NULL) {
                Py_DECREF(st);
                if (!PyErr_Occurred())
                    PyErr_SetString(PyExc_ValueError, "unpack_cal: not an integer status");
                goto done;
            }
            PyObject *v = PyLong_FromLongLong(iv[i]);
            if (v == NULL) {
                Py_DECREF(st);
                goto done;
            }
            PyTuple_SET_ITEM(st, k, v);
        }
        for (Py_ssize_t k = 0; k < no; k++) {
            double v = raw[perm[k]] * g[k];
            out[k] = v + o[k];
        }
        r = st;
    }
done:
    PyBuffer_Release(&bd);
    PyBuffer_Release(&bc);
    PyBuffer_Release(&bp);
    PyBuffer_Release(&bg);
    PyBuffer_Release(&bo);
    PyBuffer_Release(&bout);
    return r;
}

/* gemv(A, x, y): y = A x with the kernel's BLAS (tests: the same bits as numpy's dot) */
static PyObject *k_gemv(PyObject *self, PyObject *args) {
    Py_buffer bA, bx, by;
    Py_ssize_t m, k;
    int fortran;
    if (!PyArg_ParseTuple(args, "y*nnpy*w*", &bA, &m, &k, &fortran, &bx, &by))
        return NULL;
    PyObject *r = NULL;
    if (bA.len != m * k * 8 || bx.len != k * 8 || by.len != m * 8)
        PyErr_SetString(PyExc_ValueError, "gemv: wrong sizes");
    else if (g_gemv == NULL)
        PyErr_SetString(PyExc_RuntimeError, "gemv: no BLAS set");
    else {
        gemv_o(bA.buf, m, k, fortran, bx.buf, by.buf);
        r = Py_None;
        Py_INCREF(r);
    }
    PyBuffer_Release(&bA);
    PyBuffer_Release(&bx);
    PyBuffer_Release(&by);
    return r;
}

static PyMethodDef plan_methods[] = {
    {"step", (PyCFunction)plan_step, METH_VARARGS, "One measured sample's hub path."},
    {NULL, NULL, 0, NULL}};

static PyTypeObject PlanType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "rsra.daq._hubkernel.Plan",
    .tp_basicsize = sizeof(Plan),
    .tp_dealloc = (destructor)plan_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The matrices and state arrays of one design and angles (held, not copied).",
    .tp_methods = plan_methods,
    .tp_new = plan_new,
};

static PyMethodDef module_methods[] = {
    {"set_blas", set_blas, METH_VARARGS,
     "set_blas(dgemv_address, ddot_address, ilp64): numpy's CBLAS functions."},
    {"sos_step", k_sos_step, METH_VARARGS,
     "sos_step(sos, zi, x, y): one sample through a content filter's sections."},
    {"unpack_cal", k_unpack_cal, METH_VARARGS,
     "unpack_cal(data, codes, perm, gain, offset, out, status_idx): a sample's decode."},
    {"gemv", k_gemv, METH_VARARGS, "gemv(A, m, k, fortran, x, y): y = A x as numpy's dot computes it (tests)."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_hubkernel",
                                    "The compiled hub path (issue 26).", -1, module_methods};

PyMODINIT_FUNC PyInit__hubkernel(void) {
    if (PyType_Ready(&PlanType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&PlanType);
    if (PyModule_AddObject(m, "Plan", (PyObject *)&PlanType) < 0) {
        Py_DECREF(&PlanType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
