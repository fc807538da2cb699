/*
 * The CPython side of the kernel, shared by module.c and front.c.
 */
#ifndef VK_MODULE_H
#define VK_MODULE_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "kernel.h"

/* One set of sources, two modules (setup.py): "_verify" for any x86-64 (or other) CPU, and
 * "_verify_avx2", the same code compiled with -mavx2 -DVK_AVX2 (4 doubles per vector instead
 * of 2: the trig and rotation loops; plan ~23 % faster, bit for bit the same results, since
 * no FMA contraction and no reassociation are allowed either way). verify.py loads the AVX2
 * one where the baseline module's CPU_AVX2 says the CPU has it. */
#ifdef VK_AVX2
#define VK_MODULE_NAME "_verify_avx2"
#define VK_MODULE_INIT PyInit__verify_avx2
#else
#define VK_MODULE_NAME "_verify"
#define VK_MODULE_INIT PyInit__verify
#endif

typedef struct {
    PyObject_HEAD
    double params[VK_N_PARAMS];
    double *s;
    /* q(s), p(s) of Yao eq 10, 1/p(s) (0 where p is 0), q', q'', p', p'' on the grid (7 * m),
     * for plan. */
    double *basis;
    /* Retiming (VK_N_CACHE * m) and plan (VK_N_PLAN * m) scratch: one per kernel, safe because
     * no method releases the GIL, so two threads never run in the same kernel at once. */
    double *cache;
    double *scratch;
    /* The coarse grid of plan's path-scale scan (every VK_PL_STRIDE-th sample; NULL when the
     * grid is too small or m - 1 is not a multiple of the stride): its basis and scratch. */
    double *basis_c;
    double *scratch_c;
    int m;
    int m_c;
} KernelObject;

/* A row-batched buffer argument of run, retime and plan: obj NULL or None when absent. */
typedef struct {
    PyObject *obj;
    const char *name;
    int writable;
    int ndim;
    Py_ssize_t shape[3];
    Py_buffer view;
    int held;
} vk_arg;

int vk_format_is(const Py_buffer *view, char code, Py_ssize_t size);
int get_f64(PyObject *obj, Py_buffer *view, int writable, int ndim, const Py_ssize_t *shape,
            const char *name);
void release_rows(vk_arg *a, int count);
int get_args(vk_arg *a, int count);
Py_ssize_t get_rows(vk_arg *a, int count);
int get_double(PyObject *obj, double *v, const char *name);
int get_c_range(PyObject *lo, PyObject *hi, double *c_lo, double *c_hi);

/* front.c: the Front type (readied by the module's init) and Kernel.front, which makes one. */
extern PyTypeObject FrontType;
PyObject *Kernel_front(KernelObject *self, PyObject *const *args, Py_ssize_t nargs);

#endif
