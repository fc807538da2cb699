/*
 * The extension module (rt_runtime.planning._verify, or _verify_avx2: module.h) and its Kernel
 * type: the packed rig constants, the time grid and the scratch of one verifier, and the
 * per-call entry points run (vk_evaluate), retime (vk_retime), plan (vk_plan), screen
 * (vk_screen_row) and front (front.c); the module functions overdig, envelope, fit_bulges,
 * move_poses and bucket_depth (trench.c), mintorque (mintorque.c).
 *
 * The entry points are METH_FASTCALL and take numpy arrays by the buffer protocol: it measured
 * 0.1 us per call against 0.4 us for ctypes with cached pointers and 2.6 us for ctypes taking
 * the pointers of the caller's arrays per call. Their array arguments are tables of vk_arg
 * (name, writability, shape) acquired by get_args and get_rows, which check them and name the
 * argument and the shape expected.
 */
#include "module.h"

static void Kernel_dealloc(KernelObject *self)
{
    free(self->s);
    free(self->basis);
    free(self->cache);
    free(self->scratch);
    free(self->basis_c);
    free(self->scratch_c);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Whether a buffer holds native items of struct code ``code`` ('d' float64, 'f' float32) of
 * ``size`` bytes (an explicit native or little-endian prefix allowed). */
int vk_format_is(const Py_buffer *view, char code, Py_ssize_t size)
{
    const char *f = view->format;
    if (f != NULL && (f[0] == '<' || f[0] == '=' || f[0] == '@')) f++;
    return view->itemsize == size && f != NULL && f[0] == code && f[1] == '\0';
}

/* A C-contiguous float64 buffer of the given rank; shape[k] < 0 accepts any length. */
int get_f64(PyObject *obj, Py_buffer *view, int writable, int ndim, const Py_ssize_t *shape,
            const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) != 0) {
        PyErr_Format(PyExc_ValueError,
                     "%s must be a C-contiguous%s float64 array", name,
                     writable ? " writable" : "");
        return -1;
    }
    if (!vk_format_is(view, 'd', 8)) {
        PyErr_Format(PyExc_ValueError, "%s must have dtype float64; got buffer format '%s'", name,
                     view->format ? view->format : "B");
        PyBuffer_Release(view);
        return -1;
    }
    int ok = view->ndim == ndim;
    for (int k = 0; ok && k < ndim; k++)
        if (shape[k] >= 0 && view->shape[k] != shape[k]) ok = 0;
    if (!ok) {
        /* The expected shape, a free length as N: "(N,)", "(2, 7)", "(N, 11, 2)", "(7, N)". */
        char want[96];
        size_t l = 0;
        for (int k = 0; k < ndim; k++) {
            const char *sep = k == 0 ? "(" : ", ";
            if (shape[k] < 0)
                l += (size_t)snprintf(want + l, sizeof want - l, "%sN", sep);
            else
                l += (size_t)snprintf(want + l, sizeof want - l, "%s%zd", sep, shape[k]);
        }
        snprintf(want + l, sizeof want - l, ndim == 1 ? ",)" : ")");
        PyErr_Format(PyExc_ValueError, "%s must have shape %s", name, want);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

static int Kernel_init(KernelObject *self, PyObject *args, PyObject *kwds)
{
    static char *kwlist[] = {"params", "n_samples", NULL};
    PyObject *params;
    int m;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "Oi", kwlist, &params, &m)) return -1;
    if (m < 2) {
        PyErr_Format(PyExc_ValueError, "n_samples must be >= 2; got %d", m);
        return -1;
    }
    Py_buffer view;
    const Py_ssize_t shape[1] = {VK_N_PARAMS};
    if (get_f64(params, &view, 0, 1, shape, "params") != 0) return -1;
    const double *src = (const double *)view.buf;
    for (int k = 0; k < VK_N_PARAMS; k++) self->params[k] = src[k];
    PyBuffer_Release(&view);
    double *s = (double *)malloc((size_t)m * sizeof(double));
    double *basis = (double *)malloc((size_t)m * 7 * sizeof(double));
    double *cache = (double *)malloc((size_t)m * VK_N_CACHE * sizeof(double));
    double *scratch = (double *)malloc((size_t)m * VK_N_PLAN * sizeof(double));
    if (s == NULL || basis == NULL || cache == NULL || scratch == NULL) {
        free(s);
        free(basis);
        free(cache);
        free(scratch);
        PyErr_NoMemory();
        return -1;
    }
    /* numpy.linspace(0, 1, m): i * step, the last point exactly 1. */
    const double step = 1.0 / (double)(m - 1);
    for (int i = 0; i < m; i++) s[i] = (double)i * step;
    s[m - 1] = 1.0;
    for (int i = 0; i < m; i++) {
        const double si = s[i], s3 = si * si * si, r = 1.0 - si;
        basis[i] = s3 * (10.0 + si * (-15.0 + si * 6.0)); /* q(s) */
        basis[m + i] = s3 * (r * r * r);                   /* p(s) */
        basis[2 * m + i] = basis[m + i] > 0.0 ? 1.0 / basis[m + i] : 0.0;
        /* Their first and second derivatives (the back-off's vk_local_bounds). */
        basis[3 * m + i] = 30.0 * si * si * r * r;                    /* q'(s) */
        basis[4 * m + i] = 60.0 * si * r * (1.0 - 2.0 * si);          /* q''(s) */
        basis[5 * m + i] = 3.0 * si * si * r * r * (1.0 - 2.0 * si);  /* p'(s) */
        basis[6 * m + i] = 6.0 * si * r * (1.0 - 5.0 * si * r);       /* p''(s) */
    }
    double *basis_c = NULL, *scratch_c = NULL;
    int m_c = 0;
    if (VK_PL_COARSE && m > 2 * VK_PL_STRIDE + 1 && (m - 1) % VK_PL_STRIDE == 0) {
        m_c = (m - 1) / VK_PL_STRIDE + 1;
        basis_c = (double *)malloc((size_t)m_c * 3 * sizeof(double));
        scratch_c = (double *)malloc((size_t)m_c * VK_N_PLAN * sizeof(double));
        if (basis_c == NULL || scratch_c == NULL) {
            free(s);
            free(basis);
            free(cache);
            free(scratch);
            free(basis_c);
            free(scratch_c);
            PyErr_NoMemory();
            return -1;
        }
        for (int i = 0; i < m_c; i++)
            for (int k = 0; k < 3; k++) basis_c[k * m_c + i] = basis[k * m + i * VK_PL_STRIDE];
    }
    free(self->s);
    free(self->basis);
    free(self->cache);
    free(self->scratch);
    free(self->basis_c);
    free(self->scratch_c);
    self->basis_c = basis_c;
    self->scratch_c = scratch_c;
    self->m_c = m_c;
    self->s = s;
    self->basis = basis;
    self->cache = cache;
    self->scratch = scratch;
    self->m = m;
    return 0;
}


void release_rows(vk_arg *a, int count)
{
    for (int k = 0; k < count; k++)
        if (a[k].held) {
            PyBuffer_Release(&a[k].view);
            a[k].held = 0;
        }
}

/* Acquire every present argument (absent: NULL or None). Returns 0, or -1 with the error set
   and nothing held. */
int get_args(vk_arg *a, int count)
{
    for (int k = 0; k < count; k++) {
        a[k].held = 0;
        if (a[k].obj == NULL || a[k].obj == Py_None) continue;
        if (get_f64(a[k].obj, &a[k].view, a[k].writable, a[k].ndim, a[k].shape, a[k].name) != 0) {
            release_rows(a, k);
            return -1;
        }
        a[k].held = 1;
    }
    return 0;
}

/* Acquire every present argument; all must have the same number of rows N as a[0] (absent
   ones count as N in the message). Returns N, or -1 with the error set and nothing held. */
Py_ssize_t get_rows(vk_arg *a, int count)
{
    if (get_args(a, count) != 0) return -1;
    const Py_ssize_t n = a[0].view.shape[0];
    int bad = 0;
    for (int k = 1; k < count; k++)
        if (a[k].held && a[k].view.shape[0] != n) bad = 1;
    if (!bad) return n;
    char names[160] = "", rows[160] = "";
    size_t ln = 0, lr = 0;
    for (int k = 0; k < count; k++) {
        const char *sep = k == 0 ? "" : (k == count - 1 ? " and " : ", ");
        ln += (size_t)snprintf(names + ln, sizeof names - ln, "%s%s", sep, a[k].name);
        lr += (size_t)snprintf(rows + lr, sizeof rows - lr, "%s%zd", k == 0 ? "" : ", ",
                               a[k].held ? a[k].view.shape[0] : n);
    }
    release_rows(a, count);
    PyErr_Format(PyExc_ValueError, "%s must have the same number of rows N; got %s", names, rows);
    return -1;
}

static PyObject *Kernel_run(KernelObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs < 2 || nargs > 3) {
        PyErr_SetString(PyExc_TypeError, "run(inputs, out, path=None) takes 2 or 3 arguments");
        return NULL;
    }
    if (self->s == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Kernel not initialised");
        return NULL;
    }
    const int m = self->m;
    vk_arg a[3] = {
        {args[0], "inputs", 0, 2, {-1, VK_N_IN}},
        {args[1], "out", 1, 2, {-1, VK_N_OUT}},
        {nargs == 3 ? args[2] : NULL, "path", 1, 3, {-1, m, 2}},
    };
    const Py_ssize_t n = get_rows(a, 3);
    if (n < 0) return NULL;
    const double *in = (const double *)a[0].view.buf;
    double *out = (double *)a[1].view.buf;
    double *path = a[2].held ? (double *)a[2].view.buf : NULL;
    for (Py_ssize_t r = 0; r < n; r++)
        vk_evaluate(self->params, self->s, m, in + r * VK_N_IN, out + r * VK_N_OUT,
                    path != NULL ? path + r * 2 * m : NULL);
    release_rows(a, 3);
    Py_RETURN_NONE;
}

static PyObject *Kernel_retime(KernelObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs < 3 || nargs > 4) {
        PyErr_SetString(PyExc_TypeError,
                        "retime(inputs, out, retimed, path=None) takes 3 or 4 arguments");
        return NULL;
    }
    if (self->s == NULL || self->cache == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Kernel not initialised");
        return NULL;
    }
    const int m = self->m;
    vk_arg a[4] = {
        {args[0], "inputs", 0, 2, {-1, VK_N_IN}},
        {args[1], "out", 1, 2, {-1, VK_N_OUT}},
        {args[2], "retimed", 1, 2, {-1, 4}},
        {nargs == 4 ? args[3] : NULL, "path", 1, 3, {-1, m, 2}},
    };
    const Py_ssize_t n = get_rows(a, 4);
    if (n < 0) return NULL;
    const double *in = (const double *)a[0].view.buf;
    double *out = (double *)a[1].view.buf;
    double *rt = (double *)a[2].view.buf;
    double *path = a[3].held ? (double *)a[3].view.buf : NULL;
    for (Py_ssize_t r = 0; r < n; r++)
        vk_retime(self->params, self->s, m, in + r * VK_N_IN, out + r * VK_N_OUT, rt + r * 4,
                  path != NULL ? path + r * 2 * m : NULL, NULL, self->cache);
    release_rows(a, 4);
    Py_RETURN_NONE;
}

/* A float argument of plan. */
int get_double(PyObject *obj, double *v, const char *name)
{
    *v = PyFloat_AsDouble(obj);
    if (*v == -1.0 && PyErr_Occurred()) {
        PyErr_Format(PyExc_TypeError, "%s must be a float", name);
        return -1;
    }
    return 0;
}

/* The fill's range of bulge scales (plan's c_lo, c_hi): finite, 0 <= c_lo <= c_hi. */
int get_c_range(PyObject *lo, PyObject *hi, double *c_lo, double *c_hi)
{
    if (get_double(lo, c_lo, "c_lo") != 0 || get_double(hi, c_hi, "c_hi") != 0) return -1;
    if (!(isfinite(*c_lo) && isfinite(*c_hi) && *c_lo >= 0.0 && *c_lo <= *c_hi)) {
        PyErr_Format(PyExc_ValueError,
                     "c_range must be finite with 0 <= c_lo <= c_hi; got (%R, %R)", lo, hi);
        return -1;
    }
    return 0;
}

static PyObject *Kernel_plan(KernelObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs < 5 || nargs > 7) {
        PyErr_SetString(PyExc_TypeError,
                        "plan(inputs, out, planned, c_lo, c_hi, path=None, scale=None) takes 5 "
                        "to 7 arguments");
        return NULL;
    }
    if (self->s == NULL || self->cache == NULL || self->scratch == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Kernel not initialised");
        return NULL;
    }
    double c_lo, c_hi;
    if (get_c_range(args[3], args[4], &c_lo, &c_hi) != 0) return NULL;
    const int m = self->m;
    vk_arg a[5] = {
        {args[0], "inputs", 0, 2, {-1, VK_N_IN}},
        {args[1], "out", 1, 2, {-1, VK_N_OUT}},
        {args[2], "planned", 1, 2, {-1, 4}},
        {nargs >= 6 ? args[5] : NULL, "path", 1, 3, {-1, m, 2}},
        {nargs == 7 ? args[6] : NULL, "scale", 1, 1, {-1}},
    };
    const Py_ssize_t n = get_rows(a, 5);
    if (n < 0) return NULL;
    const double *in = (const double *)a[0].view.buf;
    double *out = (double *)a[1].view.buf;
    double *pl = (double *)a[2].view.buf;
    double *path = a[3].held ? (double *)a[3].view.buf : NULL;
    double *sc = a[4].held ? (double *)a[4].view.buf : NULL;
    for (Py_ssize_t r = 0; r < n; r++)
        vk_plan(self->params, self->s, self->basis, m, self->basis_c, self->m_c,
                in + r * VK_N_IN, c_lo, c_hi, out + r * VK_N_OUT, pl + r * 4,
                path != NULL ? path + r * 2 * m : NULL, sc != NULL ? sc + r : NULL, self->cache,
                self->scratch, self->scratch_c);
    release_rows(a, 5);
    Py_RETURN_NONE;
}


/* The height-field and design arguments of screen and overdig (field, frame, walls, edges:
 * args[0..3]) as the argument specs a[0..3]. */
static void vk_field_args(vk_arg *a, PyObject *const *args)
{
    const vk_arg spec[4] = {
        {args[0], "field", 0, 2, {2, -1}},
        {args[1], "frame", 0, 1, {6}},
        {args[2], "walls", 0, 2, {3, 3}},
        {args[3], "edges", 0, 2, {-1, 5}},
    };
    for (int k = 0; k < 4; k++) a[k] = spec[k];
}

/* Those arguments, acquired (a[0..3]), as a vk_field: NULL, or what is wrong with them. */
static const char *vk_field_of(const vk_arg *a, vk_field *f)
{
    const Py_ssize_t M = a[0].view.shape[1];
    if (M < 2) return "field must hold 2 or more grid points";
    const double *fr = (const double *)a[1].view.buf;
    const double *field = (const double *)a[0].view.buf;
    const vk_field g = {
        .surface = field, .floor = field + M, .x0 = fr[0], .h = fr[1], .machine_x = fr[2],
        .n = M, .walls = (const double *)a[2].view.buf, .xf = fr[3], .xn = fr[4],
        .ground = fr[5], .edges = (const double *)a[3].view.buf, .n_edges = a[3].view.shape[0],
    };
    *f = g;
    return NULL;
}

static PyObject *vk_py_overdig(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError,
                        "overdig(paths, field, frame, walls, edges, out) takes 6 arguments");
        return NULL;
    }
    vk_arg a[6] = {
        [4] = {args[0], "paths", 0, 3, {-1, -1, 2}},
        [5] = {args[5], "out", 1, 1, {-1}},
    };
    vk_field_args(a, args + 1);
    if (get_args(a, 6) != 0) return NULL;
    const Py_ssize_t N = a[4].view.shape[0], n = a[4].view.shape[1];
    vk_field f;
    const char *bad = vk_field_of(a, &f);
    if (bad == NULL && a[5].view.shape[0] != N) bad = "out must have one value per path (N,)";
    if (bad != NULL) {
        release_rows(a, 6);
        PyErr_SetString(PyExc_ValueError, bad);
        return NULL;
    }
    const double *paths = (const double *)a[4].view.buf;
    double *out = (double *)a[5].view.buf;
    for (Py_ssize_t r = 0; r < N; r++) out[r] = vk_overdig_path(&f, paths + 2 * r * n, n);
    release_rows(a, 6);
    Py_RETURN_NONE;
}

static PyObject *vk_py_envelope(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "envelope(path, grid, out) takes 3 arguments");
        return NULL;
    }
    vk_arg a[3] = {
        {args[0], "path", 0, 2, {-1, 2}},
        {args[1], "grid", 0, 1, {-1}},
        {args[2], "out", 1, 1, {-1}},
    };
    if (get_args(a, 3) != 0) return NULL;
    const Py_ssize_t M = a[1].view.shape[0];
    if (a[2].view.shape[0] != M || M < 2) {
        release_rows(a, 3);
        PyErr_SetString(PyExc_ValueError, "grid must hold 2 or more points and out one per point");
        return NULL;
    }
    double *env = (double *)a[2].view.buf;
    for (Py_ssize_t i = 0; i < M; i++) env[i] = INFINITY;
    vk_lower_envelope((const double *)a[0].view.buf, a[0].view.shape[0],
                      (const double *)a[1].view.buf, M, env);
    release_rows(a, 3);
    Py_RETURN_NONE;
}

static PyObject *vk_py_fit_bulges(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError,
                        "fit_bulges(base, pf, lengths, edges, jac0, d_ent, par, K, cost) takes 9 "
                        "arguments");
        return NULL;
    }
    vk_arg a[9] = {
        {args[0], "base", 0, 3, {-1, -1, 3}}, {args[1], "pf", 0, 1, {-1}},
        {args[2], "lengths", 0, 1, {3}},      {args[3], "edges", 0, 2, {-1, 3}},
        {args[4], "jac0", 0, 3, {-1, 2, 3}},  {args[5], "d_ent", 0, 2, {-1, 2}},
        {args[6], "par", 0, 1, {4}},          {args[7], "K", 1, 2, {-1, 3}},
        {args[8], "cost", 1, 1, {-1}},
    };
    if (get_args(a, 9) != 0) return NULL;
    const Py_ssize_t P = a[0].view.shape[0], n = a[0].view.shape[1], E = a[3].view.shape[0];
    const char *bad = NULL;
    if (a[1].view.shape[0] != n) bad = "pf must have one value per sample (n,)";
    else if (n > VK_FIT_MAX_SAMPLES) bad = "base has more samples than the fit takes (1024)";
    else if (E < 1) bad = "edges must hold 1 or more half-planes";
    for (int k = 4; k < 9 && bad == NULL; k++)
        if (k != 6 && a[k].view.shape[0] != P)
            bad = "base, jac0, d_ent, K and cost must have the same number of rows P";
    if (bad != NULL) {
        release_rows(a, 9);
        PyErr_SetString(PyExc_ValueError, bad);
        return NULL;
    }
    const double *base = (const double *)a[0].view.buf, *jac0 = (const double *)a[4].view.buf;
    const double *d_ent = (const double *)a[5].view.buf;
    double *K = (double *)a[7].view.buf, *cost = (double *)a[8].view.buf;
    for (Py_ssize_t p = 0; p < P; p++)
        vk_fit_bulges(base + 3 * n * p, (const double *)a[1].view.buf, n,
                      (const double *)a[2].view.buf, (const double *)a[3].view.buf, E,
                      jac0 + 6 * p, d_ent + 2 * p, (const double *)a[6].view.buf, K + 3 * p,
                      cost + p);
    release_rows(a, 9);
    Py_RETURN_NONE;
}

static PyObject *vk_py_move_poses(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "move_poses(tables, times, out) takes 3 arguments");
        return NULL;
    }
    vk_arg a[3] = {
        {args[0], "tables", 0, 3, {3, 5, 7}},
        {args[1], "times", 0, 1, {-1}},
        {args[2], "out", 1, 2, {-1, 3}},
    };
    if (get_args(a, 3) != 0) return NULL;
    const Py_ssize_t n = a[1].view.shape[0];
    if (a[2].view.shape[0] != n) {
        release_rows(a, 3);
        PyErr_SetString(PyExc_ValueError, "out must have one pose per time (n, 3)");
        return NULL;
    }
    vk_move_poses((const double *)a[0].view.buf, (const double *)a[1].view.buf, n,
                  (double *)a[2].view.buf);
    release_rows(a, 3);
    Py_RETURN_NONE;
}

static PyObject *vk_py_bucket_depth(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 8) {
        PyErr_SetString(PyExc_TypeError,
                        "bucket_depth(q, lengths, outline, machine_x, grid, surface, cap, out) "
                        "takes 8 arguments");
        return NULL;
    }
    double machine_x;
    if (get_double(args[3], &machine_x, "machine_x") != 0) return NULL;
    vk_arg a[7] = {
        {args[0], "q", 0, 2, {-1, 3}},      {args[1], "lengths", 0, 1, {3}},
        {args[2], "outline", 0, 2, {-1, 2}}, {args[4], "grid", 0, 1, {-1}},
        {args[5], "surface", 0, 1, {-1}},   {args[6], "cap", 0, 1, {-1}},
        {args[7], "out", 1, 2, {-1, -1}},
    };
    if (get_args(a, 7) != 0) return NULL;
    const Py_ssize_t n = a[0].view.shape[0], m = a[2].view.shape[0], M = a[3].view.shape[0];
    const char *bad = NULL;
    if (M < 2 || a[4].view.shape[0] != M) bad = "grid must hold 2 or more points and surface one per point";
    else if (a[5].view.shape[0] != m) bad = "cap must have one value per outline point (m,)";
    else if (a[6].view.shape[0] != n || a[6].view.shape[1] != m) bad = "out must be (n, m)";
    if (bad != NULL) {
        release_rows(a, 7);
        PyErr_SetString(PyExc_ValueError, bad);
        return NULL;
    }
    const int rc = vk_bucket_depth((const double *)a[0].view.buf, n, (const double *)a[1].view.buf,
                                   (const double *)a[2].view.buf, m, machine_x,
                                   (const double *)a[3].view.buf, (const double *)a[4].view.buf,
                                   M, (const double *)a[5].view.buf, (double *)a[6].view.buf);
    release_rows(a, 7);
    if (rc != 0) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *Kernel_screen(KernelObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError,
                        "screen(rows, K, shapes, scales, field, frame, walls, edges, out) takes 9 "
                        "arguments");
        return NULL;
    }
    vk_arg a[9] = {
        {args[0], "rows", 0, 2, {-1, 7}},
        {args[1], "K", 0, 2, {-1, 3}},
        {args[2], "shapes", 0, 2, {2, -1}},
        {args[3], "scales", 0, 1, {-1}},
        [8] = {args[8], "out", 1, 3, {4, -1, -1}},
    };
    vk_field_args(a + 4, args + 4);
    if (get_args(a, 9) != 0) return NULL;
    const Py_ssize_t n = a[0].view.shape[0];
    const Py_ssize_t S = a[2].view.shape[1], nG = a[3].view.shape[0];
    vk_field f;
    const char *bad = vk_field_of(a + 4, &f);
    if (bad == NULL && a[1].view.shape[0] != n) bad = "K must have as many rows as rows";
    if (bad == NULL && (a[8].view.shape[1] != n || a[8].view.shape[2] != nG))
        bad = "out must have shape (4, N, G): N rows, G scales";
    if (bad == NULL && (S < 2 || nG < 1 || S * nG > VK_SCREEN_MAX))
        bad = "shapes and scales must give 2 or more samples, 1 or more scales, at most 512 "
              "samples x scales";
    if (bad != NULL) {
        release_rows(a, 9);
        PyErr_SetString(PyExc_ValueError, bad);
        return NULL;
    }
    const double *shapes = (const double *)a[2].view.buf;
    const double *rows = (const double *)a[0].view.buf, *K = (const double *)a[1].view.buf;
    const double *G = (const double *)a[3].view.buf;
    double *out = (double *)a[8].view.buf;
    for (Py_ssize_t r = 0; r < n; r++)
        vk_screen_row(self->params, rows + 7 * r, K + 3 * r, shapes, shapes + S, (int)S, G,
                      (int)nG, &f, out + r * nG, n * nG);
    release_rows(a, 9);
    Py_RETURN_NONE;
}

static PyMethodDef Kernel_methods[] = {
    {"run", (PyCFunction)(void (*)(void))Kernel_run, METH_FASTCALL,
     "run(inputs (N, 12), out (N, 32), path (N, m, 2) or None) -> None"},
    {"retime", (PyCFunction)(void (*)(void))Kernel_retime, METH_FASTCALL,
     "retime(inputs (N, 12), out (N, 32), retimed (N, 4), path (N, m, 2) or None) -> None"},
    {"plan", (PyCFunction)(void (*)(void))Kernel_plan, METH_FASTCALL,
     "plan(inputs (N, 12), out (N, 32), planned (N, 4), c_lo, c_hi, path (N, m, 2) or None, "
     "scale (N,) or None) -> None"},
    {"front", (PyCFunction)(void (*)(void))Kernel_front, METH_FASTCALL,
     "front(row (1, 12), out (1, 32), planned (1, 4), scale (1,), lo (2, 7), hi (2, 7), "
     "x (2 float32 (1, 7)), y (2 float32 (1, 4)), runs (2 callables)) -> Front"},
    {"screen", (PyCFunction)(void (*)(void))Kernel_screen, METH_FASTCALL,
     "screen(rows (N, 7), K (N, 3), shapes (2, S), scales (G,), field (2, M), frame (6,), "
     "walls (3, 3), edges (E, 5), out (4, N, G)) -> None"},
    {NULL, NULL, 0, NULL},
};

static PyObject *Kernel_get_n_samples(KernelObject *self, void *closure)
{
    (void)closure;
    return PyLong_FromLong(self->m);
}

static PyGetSetDef Kernel_getset[] = {
    {"n_samples", (getter)Kernel_get_n_samples, NULL, "samples per trajectory", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject KernelType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "rt_runtime.planning." VK_MODULE_NAME ".Kernel",
    .tp_basicsize = sizeof(KernelObject),
    .tp_dealloc = (destructor)Kernel_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Kernel(params float64 (N_PARAMS,), n_samples): packed rig constants and grid.",
    .tp_methods = Kernel_methods,
    .tp_getset = Kernel_getset,
    .tp_init = (initproc)Kernel_init,
    .tp_new = PyType_GenericNew,
};

/* The trench planner's geometry (no rig constants: module functions). */
/* What a minimum-torque entry point returns for its C unit's code: None on 0, else NULL with
 * the error set (-2: too many plates, -1: no memory). */
static PyObject *mt_result(int rc)
{
    if (rc == -2) {
        PyErr_Format(PyExc_ValueError, "plates must have at most %d rows", MT_MAX_PLATES);
        return NULL;
    }
    if (rc != 0) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *vk_py_mintorque(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError,
                        "mintorque(X, params, basis, plates, cost, named, split) takes 7 arguments");
        return NULL;
    }
    vk_arg a[7] = {
        {args[0], "X", 0, 2, {-1, -1}},
        {args[1], "params", 0, 1, {MT_N_PARAMS}},
        {args[2], "basis", 0, 2, {14, -1}},
        {args[3], "plates", 0, 2, {-1, 7}},
        {args[4], "cost", 1, 1, {-1}},
        {args[5], "named", 1, 2, {-1, MT_N_NAMED}},
        {args[6], "split", 1, 2, {-1, MT_N_SPLIT}},
    };
    if (get_args(a, 7) != 0) return NULL;
    const Py_ssize_t B = a[0].view.shape[0], n_var = a[0].view.shape[1];
    const Py_ssize_t Q = a[2].view.shape[1] - 1;
    if ((n_var != 3 * MT_N_KEY && n_var != 3 * MT_N_KEY + MT_N_INTERVALS) || Q < 1 ||
        a[4].view.shape[0] != B || a[5].view.shape[0] != B || a[6].view.shape[0] != B) {
        release_rows(a, 7);
        PyErr_Format(PyExc_ValueError,
                     "X must have 15 or 19 columns, basis 2 or more samples, and cost, named and "
                     "split one row per point of X (%zd)", B);
        return NULL;
    }
    const int rc = mt_evaluate((const double *)a[1].view.buf, (const double *)a[2].view.buf,
                               (int)Q, (const double *)a[3].view.buf, (int)a[3].view.shape[0],
                               (const double *)a[0].view.buf, B, (int)n_var,
                               (double *)a[4].view.buf, (double *)a[5].view.buf,
                               (double *)a[6].view.buf);
    release_rows(a, 7);
    return mt_result(rc);
}

static PyObject *vk_py_mintorque_perturbed(PyObject *module, PyObject *const *args,
                                           Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError,
                        "mintorque_perturbed(x, step, params, basis, plates, cost, split) takes 7 "
                        "arguments");
        return NULL;
    }
    double step;
    if (get_double(args[1], &step, "step") != 0) return NULL;
    vk_arg a[6] = {
        {args[0], "x", 0, 1, {-1}},
        {args[2], "params", 0, 1, {MT_N_PARAMS}},
        {args[3], "basis", 0, 2, {14, -1}},
        {args[4], "plates", 0, 2, {-1, 7}},
        {args[5], "cost", 1, 1, {-1}},
        {args[6], "split", 1, 2, {-1, MT_N_SPLIT}},
    };
    if (get_args(a, 6) != 0) return NULL;
    const Py_ssize_t n_var = a[0].view.shape[0];
    const Py_ssize_t Q = a[2].view.shape[1] - 1;
    if ((n_var != 3 * MT_N_KEY && n_var != 3 * MT_N_KEY + MT_N_INTERVALS) || Q < 1 ||
        a[4].view.shape[0] != n_var || a[5].view.shape[0] != n_var) {
        release_rows(a, 6);
        PyErr_Format(PyExc_ValueError,
                     "x must have 15 or 19 values, basis 2 or more samples, and cost and split "
                     "one row per value of x (%zd)", n_var);
        return NULL;
    }
    const int rc = mt_perturbed((const double *)a[1].view.buf, (const double *)a[2].view.buf,
                                (int)Q, (const double *)a[3].view.buf, (int)a[3].view.shape[0],
                                (const double *)a[0].view.buf, (int)n_var, step,
                                (double *)a[4].view.buf, (double *)a[5].view.buf);
    release_rows(a, 6);
    return mt_result(rc);
}

static PyObject *vk_py_mintorque_path_cost(PyObject *module, PyObject *const *args,
                                           Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError,
                        "mintorque_path_cost(q, qd, qdd, w, params, plates, cost) takes 7 "
                        "arguments");
        return NULL;
    }
    vk_arg a[7] = {
        {args[0], "q", 0, 3, {-1, -1, 3}},
        {args[1], "qd", 0, 3, {-1, -1, 3}},
        {args[2], "qdd", 0, 3, {-1, -1, 3}},
        {args[3], "w", 0, 2, {-1, -1}},
        {args[4], "params", 0, 1, {MT_N_PARAMS}},
        {args[5], "plates", 0, 2, {-1, 7}},
        {args[6], "cost", 1, 1, {-1}},
    };
    if (get_args(a, 7) != 0) return NULL;
    const Py_ssize_t B = a[0].view.shape[0], n = a[0].view.shape[1];
    int same = a[6].view.shape[0] == B;
    for (int k = 1; k < 4; k++)
        same = same && a[k].view.shape[0] == B && a[k].view.shape[1] == n;
    if (!same) {
        release_rows(a, 7);
        PyErr_Format(PyExc_ValueError,
                     "q, qd, qdd and w must have the same (paths, samples) and cost one row per "
                     "path (%zd)", B);
        return NULL;
    }
    const int rc = mt_path_cost((const double *)a[4].view.buf, (const double *)a[5].view.buf,
                                (int)a[5].view.shape[0], (const double *)a[0].view.buf,
                                (const double *)a[1].view.buf, (const double *)a[2].view.buf,
                                (const double *)a[3].view.buf, B, n, (double *)a[6].view.buf);
    release_rows(a, 7);
    return mt_result(rc);
}

static PyMethodDef verify_functions[] = {
    {"overdig", (PyCFunction)(void (*)(void))vk_py_overdig, METH_FASTCALL,
     "overdig(paths (N, n, 2), field (2, M), frame (6,), walls (3, 3), edges (E, 5), out (N,)) "
     "-> None"},
    {"envelope", (PyCFunction)(void (*)(void))vk_py_envelope, METH_FASTCALL,
     "envelope(path (n, 2), grid (M,) uniform, out (M,)) -> None"},
    {"move_poses", (PyCFunction)(void (*)(void))vk_py_move_poses, METH_FASTCALL,
     "move_poses(tables (3, 5, 7): per joint the pieces' durations, jerk, acceleration, "
     "velocity, position; times (n,), out (n, 3)) -> None"},
    {"bucket_depth", (PyCFunction)(void (*)(void))vk_py_bucket_depth, METH_FASTCALL,
     "bucket_depth(q (n, 3), lengths (3,), outline (m, 2), machine_x, grid (M,) uniform, "
     "surface (M,), cap (m,), out (n, m)) -> None"},
    {"fit_bulges", (PyCFunction)(void (*)(void))vk_py_fit_bulges, METH_FASTCALL,
     "fit_bulges(base (P, n, 3), pf (n,), lengths (3,), edges (E, 3), jac0 (P, 2, 3), "
     "d_ent (P, 2), par (4,): machine x, offset, theta_p lo, hi; K (P, 3) out, cost (P,) out) "
     "-> None: each pair's damped Gauss-Newton fit of its bulge"},
    {"mintorque", (PyCFunction)(void (*)(void))vk_py_mintorque, METH_FASTCALL,
     "mintorque(X (B, 15 or 19), params (64,), basis (14, Q + 1), plates (P, 7), cost (B,) "
     "out, named (B, 44) out, split (B, 146) out) -> None: the smoothed minimum-torque model "
     "(mintorque.c)"},
    {"mintorque_perturbed", (PyCFunction)(void (*)(void))vk_py_mintorque_perturbed,
     METH_FASTCALL,
     "mintorque_perturbed(x (n,), step, params (64,), basis (14, Q + 1), plates (P, 7), cost "
     "(n,) out, split (n, 146) out) -> None: the model at x + step e_v for every v, each "
     "recomputing only the intervals that variable moves"},
    {"mintorque_path_cost", (PyCFunction)(void (*)(void))vk_py_mintorque_path_cost,
     METH_FASTCALL,
     "mintorque_path_cost(q (B, n, 3), qd, qdd, w (B, n), params (64,), plates (P, 7), cost "
     "(B,) out) -> None: sum_k w_k sum_j (tau_j / tau_max_j)^2 with the smoothed fluid soil"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef verify_module = {
    PyModuleDef_HEAD_INIT, VK_MODULE_NAME,
    "C kernel of rt_runtime.planning.verify (one-shot dig verification) and of the trench "
    "planner's screening geometry.", -1, verify_functions,
    NULL, NULL, NULL, NULL,
};

/* Whether this CPU runs the AVX2 build (gcc/clang on x86; 0 elsewhere). */
static int vk_cpu_avx2(void)
{
#if (defined(__GNUC__) || defined(__clang__)) && (defined(__x86_64__) || defined(__i386__))
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") ? 1 : 0;
#else
    return 0;
#endif
}

PyMODINIT_FUNC VK_MODULE_INIT(void)
{
    if (PyType_Ready(&KernelType) < 0 || PyType_Ready(&FrontType) < 0) return NULL;
    PyObject *mod = PyModule_Create(&verify_module);
    if (mod == NULL) return NULL;
    Py_INCREF(&KernelType);
    if (PyModule_AddObject(mod, "Kernel", (PyObject *)&KernelType) < 0 ||
        PyModule_AddIntConstant(mod, "ABI", VK_ABI) < 0 ||
        PyModule_AddIntConstant(mod, "N_PARAMS", VK_N_PARAMS) < 0 ||
        PyModule_AddIntConstant(mod, "N_IN", VK_N_IN) < 0 ||
        PyModule_AddIntConstant(mod, "N_OUT", VK_N_OUT) < 0 ||
        PyModule_AddIntConstant(mod, "CPU_AVX2", vk_cpu_avx2()) < 0) {
        Py_DECREF(&KernelType);
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
