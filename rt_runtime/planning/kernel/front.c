#include "module.h"

#include <time.h>

/* ---------------------------------------------------------------------------------------------
 * Front: the single-dig path of PinnPlanner.plan in one call (Kernel.front makes one).
 *
 * It is bound once to the planner's buffers (the 12-value row, out, planned, scale, the two
 * networks' float32 input and output arrays) and to the networks' bound onnxruntime calls; a
 * call copies the entry and exit poses and H into the row, checks them against the dig type's
 * model domain, stages the float32 input, runs the network (the bound call, timed), copies its
 * answer into the row and plans it (vk_plan, as Kernel.plan). The same steps in Python cost
 * ~3 us more per dig, a sixth of the plan's latency goal: a numpy slice assignment or cast costs
 * 0.2-0.4 us, the kernel's argument buffers ~0.1 us each, and this does them all in C. Inputs
 * outside the domain (or not finite) return None before anything runs: the caller names the
 * bound. The buffers' views are held for the Front's life, so numpy cannot resize them.
 * Step 4a of PinnPlanner.plan (the solution library) runs in Python after the call, where the
 * plan qualifies: its nearest-neighbour search is numpy, its plans Kernel.plan.
 *
 * The network call may release the GIL; it runs before the kernel's scratch is touched, and the
 * row and network buffers are the planner's own (a planner serves one thread at a time, as
 * before).
 * ------------------------------------------------------------------------------------------- */
enum { F_ROW = 0, F_OUT, F_PLANNED, F_SCALE, F_X0, F_X1, F_Y0, F_Y1, VK_N_FRONT };

typedef struct {
    PyObject_HEAD
    KernelObject *kernel;
    PyObject *runs[2];
    Py_buffer views[VK_N_FRONT];
    int held;
    double lo[2][7], hi[2][7];
} FrontObject;

static void Front_dealloc(FrontObject *self)
{
    for (int k = 0; k < self->held; k++) PyBuffer_Release(&self->views[k]);
    Py_XDECREF(self->runs[0]);
    Py_XDECREF(self->runs[1]);
    Py_XDECREF((PyObject *)self->kernel);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* A C-contiguous writable float32 array of the given shape (the network's buffers). */
static int get_f32(PyObject *obj, Py_buffer *view, Py_ssize_t rows, Py_ssize_t cols,
                   const char *name)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) != 0) {
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous writable float32 array", name);
        return -1;
    }
    if (!vk_format_is(view, 'f', 4) || view->ndim != 2 ||
        view->shape[0] != rows || view->shape[1] != cols) {
        PyErr_Format(PyExc_ValueError, "%s must be a float32 array of shape (%zd, %zd)", name,
                     rows, cols);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* Three values of a pose into dst: a float64 vector of length 3, or any sequence of 3 numbers. */
static int front_pose(PyObject *obj, double *dst, const char *name)
{
    Py_buffer v;
    if (PyObject_CheckBuffer(obj)) {
        if (PyObject_GetBuffer(obj, &v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) == 0) {
            const int ok = vk_format_is(&v, 'd', 8) && v.ndim == 1 && v.shape[0] == 3;
            if (ok) {
                const double *b = (const double *)v.buf;
                dst[0] = b[0];
                dst[1] = b[1];
                dst[2] = b[2];
            }
            PyBuffer_Release(&v);
            if (ok) return 0;
        } else {
            PyErr_Clear(); /* strided or another layout: read it as a sequence */
        }
    }
    PyObject *seq = PySequence_Fast(obj, "");
    if (seq == NULL) {
        PyErr_Format(PyExc_TypeError, "%s must be a sequence of 3 numbers; got %.80s", name,
                     Py_TYPE(obj)->tp_name);
        return -1;
    }
    const Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    if (n != 3) {
        Py_DECREF(seq);
        PyErr_Format(PyExc_ValueError, "%s must have 3 values (joint angles, rad); got %zd", name,
                     n);
        return -1;
    }
    PyObject **items = PySequence_Fast_ITEMS(seq);
    for (int j = 0; j < 3; j++) {
        dst[j] = PyFloat_AsDouble(items[j]);
        if (dst[j] == -1.0 && PyErr_Occurred()) {
            Py_DECREF(seq);
            PyErr_Format(PyExc_TypeError, "%s must hold 3 numbers; item %d is %.80s", name, j,
                         Py_TYPE(items[j])->tp_name);
            return -1;
        }
    }
    Py_DECREF(seq);
    return 0;
}

static double front_now_us(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec * 1e6 + (double)ts.tv_nsec * 1e-3;
}

/* A dig type's value (0 downward, 1 backward), the Front's index of its per-type state. */
static int get_dig_type(PyObject *obj, long *kind)
{
    *kind = PyLong_AsLong(obj);
    if (*kind == -1 && PyErr_Occurred()) return -1;
    if (*kind != 0 && *kind != 1) {
        PyErr_Format(PyExc_ValueError, "dig_type must be 0 (downward) or 1 (backward); got %ld",
                     *kind);
        return -1;
    }
    return 0;
}

/* plan(q_start, q_end, H, dig_type, c_lo, c_hi) -> None (outside the domain: nothing ran) or
 * (feasible, infer_us). */
static PyObject *Front_plan(FrontObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError,
                        "plan(q_start, q_end, H, dig_type, c_lo, c_hi) takes 6 arguments");
        return NULL;
    }
    KernelObject *kn = self->kernel;
    double *row = (double *)self->views[F_ROW].buf;
    double H, c_lo, c_hi;
    if (front_pose(args[0], row + I_Q_START, "q_start_rad") != 0 ||
        front_pose(args[1], row + I_Q_END, "q_end_rad") != 0 ||
        get_double(args[2], &H, "surface_y_m") != 0 ||
        get_c_range(args[4], args[5], &c_lo, &c_hi) != 0)
        return NULL;
    row[I_SURFACE] = H;
    long kind;
    if (get_dig_type(args[3], &kind) != 0) return NULL;
    const double *lo = self->lo[kind], *hi = self->hi[kind];
    for (int j = 0; j < 7; j++)
        if (!(lo[j] <= row[j] && row[j] <= hi[j])) Py_RETURN_NONE; /* NaN fails too */
    float *x = (float *)self->views[F_X0 + kind].buf;
    for (int j = 0; j < 7; j++) x[j] = (float)row[j];
    const double t0 = front_now_us();
    PyObject *res = PyObject_CallNoArgs(self->runs[kind]);
    const double infer_us = front_now_us() - t0;
    if (res == NULL) return NULL;
    Py_DECREF(res);
    const float *y = (const float *)self->views[F_Y0 + kind].buf;
    row[I_DIG_TYPE] = (double)kind;
    for (int j = 0; j < 4; j++) row[I_A6 + j] = (double)y[j];
    double *out = (double *)self->views[F_OUT].buf;
    double *planned = (double *)self->views[F_PLANNED].buf;
    double *scale = (double *)self->views[F_SCALE].buf;
    vk_plan(kn->params, kn->s, kn->basis, kn->m, kn->basis_c, kn->m_c, row, c_lo, c_hi, out,
            planned, NULL, scale, kn->cache, kn->scratch, kn->scratch_c);
    const int feasible = out[O_TOTAL] <= 0.0;
    PyObject *us = PyFloat_FromDouble(infer_us);
    if (us == NULL) return NULL;
    PyObject *r = PyTuple_Pack(2, feasible ? Py_True : Py_False, us);
    Py_DECREF(us);
    return r;
}

static PyMethodDef Front_methods[] = {
    {"plan", (PyCFunction)(void (*)(void))Front_plan, METH_FASTCALL,
     "plan(q_start, q_end, H, dig_type, c_lo, c_hi) -> None (input outside the domain or not "
     "finite: nothing ran) or (feasible, infer_us)"},
    {NULL, NULL, 0, NULL},
};

PyTypeObject FrontType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "rt_runtime.planning." VK_MODULE_NAME ".Front",
    .tp_basicsize = sizeof(FrontObject),
    .tp_dealloc = (destructor)Front_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The single-dig plan path bound to a planner's buffers (Kernel.front).",
    .tp_methods = Front_methods,
};

/* front(row (1, 12), out (1, 32), planned (1, 4), scale (1,), lo (2, 7), hi (2, 7),
 *       x (float32 (1, 7), float32 (1, 7)), y (float32 (1, 4), float32 (1, 4)),
 *       runs (callable, callable)) -> Front; the pairs are indexed by dig type. */
PyObject *Kernel_front(KernelObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError,
                        "front(row, out, planned, scale, lo, hi, x, y, runs) takes 9 arguments");
        return NULL;
    }
    if (self->s == NULL || self->cache == NULL || self->scratch == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Kernel not initialised");
        return NULL;
    }
    for (int k = 6; k < 9; k++)
        if (!PyTuple_Check(args[k]) || PyTuple_GET_SIZE(args[k]) != 2) {
            PyErr_SetString(PyExc_TypeError, "x, y and runs must be tuples of 2 (one per type)");
            return NULL;
        }
    for (int k = 0; k < 2; k++)
        if (!PyCallable_Check(PyTuple_GET_ITEM(args[8], k))) {
            PyErr_SetString(PyExc_TypeError, "runs must hold 2 callables");
            return NULL;
        }
    FrontObject *f = PyObject_New(FrontObject, &FrontType);
    if (f == NULL) return NULL;
    f->held = 0;
    f->kernel = self;
    Py_INCREF(self);
    for (int k = 0; k < 2; k++) {
        f->runs[k] = PyTuple_GET_ITEM(args[8], k);
        Py_INCREF(f->runs[k]);
    }
    vk_arg b[2] = {
        {args[4], "lo", 0, 2, {2, 7}},
        {args[5], "hi", 0, 2, {2, 7}},
    };
    if (get_rows(b, 2) < 0) {
        Py_DECREF(f);
        return NULL;
    }
    const double *lo = (const double *)b[0].view.buf, *hi = (const double *)b[1].view.buf;
    for (int k = 0; k < 2; k++)
        for (int j = 0; j < 7; j++) {
            f->lo[k][j] = lo[k * 7 + j];
            f->hi[k][j] = hi[k * 7 + j];
        }
    release_rows(b, 2);
    vk_arg a[4] = {
        {args[0], "row", 1, 2, {1, VK_N_IN}},
        {args[1], "out", 1, 2, {1, VK_N_OUT}},
        {args[2], "planned", 1, 2, {1, 4}},
        {args[3], "scale", 1, 1, {1}},
    };
    if (get_rows(a, 4) < 0) {
        Py_DECREF(f);
        return NULL;
    }
    for (int k = 0; k < 4; k++) f->views[k] = a[k].view; /* held for the Front's life */
    f->held = 4;
    static const char *names[4] = {"x[0]", "x[1]", "y[0]", "y[1]"};
    for (int k = 0; k < 4; k++) {
        PyObject *obj = PyTuple_GET_ITEM(args[k < 2 ? 6 : 7], k % 2);
        if (get_f32(obj, &f->views[F_X0 + k], 1, k < 2 ? 7 : 4, names[k]) != 0) {
            Py_DECREF(f);
            return NULL;
        }
        f->held++;
    }
    return (PyObject *)f;
}

