/*
 * The one-shot dig verifier kernel and the trench planner's screening geometry, plain C99 with
 * no Python in it (the CPython binding is module.c and front.c; the Python side is
 * rt_runtime/planning/verify.py). One unit per job:
 *
 *   evaluate.c  vk_evaluate: what rt_runtime.planning.oneshot.evaluate computes for one
 *               candidate, looping over the samples;
 *   retime.c    vk_retime: the shortest feasible time along a candidate's path;
 *   plan.c      vk_plan: the bulge scaled to the largest volume the path-only limits allow
 *               (fill), retimed, backing off towards a smaller bulge where that cannot be timed;
 *   trench.c    the screening geometry of rt_runtime.planning.trench (over-dig, envelope,
 *               screen rows, the bucket's depth in the material) and the iterations of its
 *               profile fits (numpy's operations in numpy's order);
 *   mintorque.c mt_evaluate: the smoothed minimum-torque model of
 *               rt_runtime.planning.mintorque (Yang/Pan) for a batch of points;
 *   module.c    the extension module and its Kernel type; front.c its Front type (the single-dig
 *               path of PinnPlanner.plan in one call).
 *
 * Why C: evaluate() is numpy batched over (B, P); for a single candidate each of its numpy
 * operations on a tiny array costs 0.5-3 us, ~0.6 ms in all. vk_evaluate does the same
 * arithmetic in ~7 us at 101 samples, without allocating; retime and plan are searches of
 * dozens of such evaluations' worth of arithmetic, which only a loop over the samples makes
 * cheap enough for a plan per dig.
 *
 * Parity with the numpy reference: vk_evaluate uses the same formulas in the same association
 * order as sextic.py, kinematics.tip_state, soil.yao_resistance, dynamics._inverse_block,
 * dynamics.energy_j, oneshot.excavated_area_m2 and oneshot._entry_angle (a change there must
 * be made here too: tests/test_verify.py holds the two together). Outputs agree to ~1e-12
 * relative (numpy's matrix products and pairwise sums round differently); the only
 * discontinuities, which sample first lies below the surface and whether the start is within
 * 1 mm of it, would need a sample within an ulp of those thresholds to differ. No -ffast-math,
 * no FMA contraction (setup.py passes -ffp-contract=off). Retime and plan are searches whose
 * answers tests/test_verify.py checks by their properties (minimal, never worse than their
 * start, every limit held by the numpy evaluation).
 */
#ifndef VK_KERNEL_H
#define VK_KERNEL_H

#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

/* ---------------------------------------------------------------------------------------------
 * Layouts shared with verify.py (bump VK_ABI on any change: verify.py refuses a stale build).
 * ------------------------------------------------------------------------------------------- */
#define VK_ABI 8

enum vk_param {
    P_LEN = 0,           /* link lengths l0, l1, l2 (m) */
    P_CH_H = 3,          /* dynamics._Chain.h (kg m) */
    P_CH_B = 6,          /* dynamics._Chain.b (kg m) */
    P_CH_D = 9,          /* dynamics._Chain.d (kg m^2) */
    P_GRAVITY = 12,      /* m/s^2 */
    P_K0B = 13,          /* K0 * b (N/m^2 * m), as soil.yao_resistance groups it */
    P_MU = 14,           /* Yao mu */
    P_SPEED_REG = 15,    /* soil speed regularisation (m/s) */
    P_Q_MIN = 16,        /* joint limits (rad) */
    P_Q_MAX = 19,
    P_Q_SPAN = 22,       /* q_max - q_min as numpy computes it */
    P_QD_MAX = 25,       /* rad/s */
    P_QDD_MAX = 28,      /* rad/s^2 */
    P_TAU_MAX = 31,      /* N m */
    P_POWER_MAX = 34,    /* W */
    P_TP_DOWN = 35,      /* theta_p range of downward digs (lo, hi) rad */
    P_TP_BACK = 37,      /* theta_p range of backward digs (lo, hi) rad */
    P_VOL = 39,          /* V_p range (min, max) m^3 */
    P_TIME = 41,         /* T range (min, max) s */
    P_ENERGY = 43,       /* energy normalisation (min, max) J */
    P_WEIGHTS = 45,      /* lambda1..3 */
    P_WIDTH = 48,        /* bucket width b (m) */
    VK_N_PARAMS = 49
};

enum vk_input {
    I_Q_START = 0, I_Q_END = 3, I_SURFACE = 6, I_DIG_TYPE = 7, I_A6 = 8, I_T = 11, VK_N_IN = 12
};

#define VK_N_CONSTRAINTS 22
enum vk_output {
    O_VIOLATIONS = 0,
    O_TOTAL = 22,
    O_OBJECTIVE = 23,
    O_T = 24,
    O_VOLUME = 25,
    O_ENERGY = 26,
    O_THETA_P = 27,
    O_PEAK_POWER = 28,
    O_PEAK_TORQUE = 29,
    VK_N_OUT = 32
};

/* Samples per block: the polynomial, the trig and the rest run as three loops over a block,
 * so that no value lives across the trig calls (their register spills cost more than the
 * arithmetic) and the arrays stay on the stack (thread-safe, no allocation). */
#define VK_BLOCK 32

/* Plain max/min (maxsd/minsd). They may drop a NaN; the finiteness checks below catch it. */
static inline double vk_max(double m, double v) { return m > v ? m : v; }
static inline double vk_min(double m, double v) { return m < v ? m : v; }
static inline double vk_pos(double v) { return v > 0.0 ? v : 0.0; }

/* The area between the surface and one polyline segment whose ends lie e0 and e1 below it, dx
 * apart (oneshot.excavated_area_m2's term): the trapezoid where both ends are below, the part
 * below where one is, 0 where neither is (adding it changes no sum: sums start at +0). */
static inline double vk_segment_area(double e0, double e1, double dx)
{
    if (e0 >= 0.0 && e1 >= 0.0) return 0.5 * (e0 + e1) * dx;
    if (!(e0 >= 0.0 || e1 >= 0.0)) return 0.0;
    double denom = fabs(e0) + fabs(e1);
    if (!(denom > 0.0)) denom = 1.0;
    const double frac = (e0 > e1 ? e0 : e1) / denom;
    return 0.5 * (vk_pos(e0) + vk_pos(e1)) * frac * dx;
}

/* The tip's polyline, fed sample by sample in order (vk_polyline_add): its excavated area and
 * its entry segment, the first one ending below the surface (first_below: its end sample, -1
 * while there is none). */
typedef struct {
    double area, x_prev, y_prev, entry_dx, entry_dy;
    int first_below;
} vk_polyline;

static inline void vk_polyline_add(vk_polyline *pl, int i, double x, double y, double H)
{
    if (y < H && pl->first_below < 0) pl->first_below = i;
    if (i > 0) {
        const double dx = x - pl->x_prev;
        pl->area += vk_segment_area(H - pl->y_prev, H - y, dx);
        if (pl->first_below == i) {
            pl->entry_dx = dx;
            pl->entry_dy = y - pl->y_prev;
        }
    }
    pl->x_prev = x;
    pl->y_prev = y;
}

/* sin and cos of |r| <= pi/4: fdlibm's kernels, no reduction and no branch. */
static inline void vk_sincos_small(double r, double *sn, double *cs)
{
    const double z = r * r;
    const double S1 = -1.66666666666666324348e-01, S2 = 8.33333333332248946124e-03,
                 S3 = -1.98412698298579493134e-04, S4 = 2.75573137070700676789e-06,
                 S5 = -2.50507602534068634195e-08, S6 = 1.58969099521155010221e-10;
    const double C1 = 4.16666666666666019037e-02, C2 = -1.38888888888741095749e-03,
                 C3 = 2.48015872894767294178e-05, C4 = -2.75573143513906633035e-07,
                 C5 = 2.08757232129817482790e-09, C6 = -1.13596475577881948265e-11;
    *sn = r + r * z * (S1 + z * (S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)))));
    *cs = (1.0 - 0.5 * z) + z * z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))));
}

/* sin and cos of |x| < 1e6: fdlibm's kernels after a Cody-Waite reduction, inline and
 * branch-free, so that a loop of it vectorises (the quadrant is chosen by selects on kd mod 4
 * as a double, not by an int switch). */
static inline void vk_sincos_reduced(double x, double *sn, double *cs)
{
    const double shift = 6755399441055744.0; /* 1.5 * 2^52: adding it rounds to an integer */
    const double kd = (x * 0.63661977236758134308 + shift) - shift; /* round(x / (pi/2)) */
    /* pi/2 in two parts, the first with 33 bits so that kd times it is exact. */
    const double r = (x - kd * 1.57079632673412561417e+00) - kd * 6.07710050650619224932e-11;
    double sr, cr;
    vk_sincos_small(r, &sr, &cr);
    /* q = kd - 4 round(kd / 4) in {-2, ..., 2}: the quadrant kd mod 4 (-1 is 3, +-2 are 2) */
    const double q = kd - 4.0 * ((kd * 0.25 + shift) - shift);
    const int odd = q == 1.0 || q == -1.0;
    const double a = odd ? cr : sr, b = odd ? sr : cr;
    *sn = (q < -0.5 || q > 1.5) ? -a : a; /* quadrants 2, 3 */
    *cs = (q > 0.5 || q < -1.5) ? -b : b; /* quadrants 1, 2 */
}

/* sin and cos (|error| <= 2.3e-16 on [-20, 20], libm's class of accuracy; the parity with the
 * numpy reference stays at ~1e-11 relative). Used everywhere, vk_evaluate included (but for
 * its start sample): it measured 1.5 us less per evaluation and 1.7 us less per retiming
 * cache at 101 samples than libm's sin and cos. Outside |x| < 1e6 (and for NaN) it is libm:
 * the reduction needs a small kd. */
static inline void vk_sincos(double x, double *sn, double *cs)
{
    if (!(fabs(x) < 1e6)) {
        *sn = sin(x);
        *cs = cos(x);
        return;
    }
    vk_sincos_reduced(x, sn, cs);
}

/* vk_sincos of n values, in a form the compiler vectorises: the range check runs first over
 * the whole block instead of per value. x may not alias sn or cs. */
static inline void vk_sincos_n(const double *restrict x, double *restrict sn, double *restrict cs,
                               int n)
{
    double wide = 0.0;
    for (int t = 0; t < n; t++) wide = vk_max(wide, fabs(x[t]) < 1e6 ? 0.0 : 1.0); /* NaN: 1 */
    if (wide != 0.0) {
        for (int t = 0; t < n; t++) vk_sincos(x[t], &sn[t], &cs[t]);
        return;
    }
    for (int t = 0; t < n; t++) vk_sincos_reduced(x[t], &sn[t], &cs[t]);
}

/* Invalid candidate: total violation +inf (never chosen, never feasible), the rest NaN. */
static inline void vk_reject(int m, double *out, double *path)
{
    for (int j = 0; j < VK_N_OUT; j++) out[j] = NAN;
    out[O_TOTAL] = INFINITY;
    if (path != NULL)
        for (int i = 0; i < 2 * m; i++) path[i] = NAN;
}


/* ---------------------------------------------------------------------------------------------
 * Time-optimal retiming along a fixed path.
 *
 * With K = -a6 T^6 kept, q(s) is fixed and time scaling only divides q' = dq/ds by T and
 * q'' by T^2. At unit time (T = 1) each sample caches, per joint, the dynamic torque A (the
 * M q'' + C q' part, which scales as u = 1/T^2), the gravity torque G and the soil torque F of
 * the full (unregularised) Yao force, plus q' and the tip speed sp. At any T:
 *     tau = A u + G + F r,   r = min(1, sp / (T reg))   (the soil's speed regularisation),
 *     power = sum_j max(tau_j q'_j, 0) / T,   |qd| = |q'| / T,   |qdd| = |q''| u.
 * Velocity and acceleration bounds are closed forms in T; the torque of every sample with
 * r = 1 on the whole time range is an interval in u; what is left (power, and the torque of
 * the few slow samples in the soil near the ends) is searched on the cache.
 * ------------------------------------------------------------------------------------------- */

/* Closed-form bounds use each limit times (1 - VK_RT_MARGIN) and the search accepts a cached
 * ratio <= 1 - VK_RT_MARGIN / 2: the cache and the real evaluation round differently (~1e-15
 * relative), so the real evaluation at the answer holds with ~5e-10 to spare. */
#define VK_RT_MARGIN 1e-9
/* Relative bracket width at which the root search stops (its answer is the feasible end). */
#define VK_RT_TOL 1e-7
/* Geometric scan points between the closed-form bounds when the lower one fails the search. */
#define VK_RT_SCAN 8
#define VK_RT_ITER 60
/* Real evaluations after the first if it contradicts the cache (never seen in 12000 random
 * rows on three rigs: a safety net), T' growing by 1e-9, 1e-8, 1e-7 relative. */
#define VK_RT_BUMPS 3
#define VK_RT_BUMP 1e-9

/* Cache layout: VK_N_CACHE arrays of m doubles; those before C_QP are vk_prepare's dynamics
 * loop's, C_QP's are q' (its input). */
enum vk_cache { C_A = 0, C_G = 3, C_F = 6, C_SP = 9, C_QP = 10, VK_N_CACHE = 13 };

/* The least T that velocity, acceleration (peaks |q'| and |q''| per joint at unit time) and
 * t_min allow, each limit times 1 - VK_RT_MARGIN. */
static inline double vk_t_va(const double *p, const double *qd_pk, const double *qdd_pk)
{
    const double lim = 1.0 - VK_RT_MARGIN;
    double t_lo = p[P_TIME];
    for (int j = 0; j < 3; j++) {
        t_lo = vk_max(t_lo, qd_pk[j] / (p[P_QD_MAX + j] * lim));
        t_lo = vk_max(t_lo, sqrt(qdd_pk[j] / (p[P_QDD_MAX + j] * lim)));
    }
    return t_lo;
}

/* The interval [*l, *h] of u = 1/T^2 in which |a u + b| <= tm (a joint's torque at one sample);
 * 0, nothing written, where a is 0 (or NaN): then no u changes the torque. */
static inline int vk_u_interval(double a, double b, double tm, double *l, double *h)
{
    if (a > 0.0) {
        *l = (-tm - b) / a;
        *h = (tm - b) / a;
        return 1;
    }
    if (a < 0.0) {
        *l = (tm - b) / a;
        *h = (-tm - b) / a;
        return 1;
    }
    return 0;
}

/* The arm's link and soil constants of the unit-time dynamics (vk_unit_dynamics). */
typedef struct {
    double l0, l1, l2, h0, h1, h2, bb0, bb1, bb2, dd0, dd1, dd2, g, k0b, mu;
} vk_dyn;

static inline vk_dyn vk_dyn_of(const double *p)
{
    const vk_dyn d = {p[P_LEN],       p[P_LEN + 1],  p[P_LEN + 2],  p[P_CH_H],     p[P_CH_H + 1],
                      p[P_CH_H + 2],  p[P_CH_B],     p[P_CH_B + 1], p[P_CH_B + 2], p[P_CH_D],
                      p[P_CH_D + 1],  p[P_CH_D + 2], p[P_GRAVITY],  p[P_K0B],      p[P_MU]};
    return d;
}

/* Dynamics of one sample at unit time (T = 1), shared by vk_prepare's cache and the back-off's
 * vk_local_sample: per joint the inertial torque a (joint accelerations and velocity
 * products), gravity g and the soil's f (Yao eq 8 at depth H - y; zero at zero speed, where the
 * real force, which scales with v / reg, is zero at every T), not yet summed outwards.
 * Returns the tip speed; *depth = H - y. */
static inline double vk_unit_dynamics(const vk_dyn d, double H, const double cp[3],
                                      const double sp[3], const double qd[3], const double qdd[3],
                                      double a[3], double gv[3], double f[3], double *depth)
{
    const double lc0 = cp[0] * d.l0, lc1 = cp[1] * d.l1, lc2 = cp[2] * d.l2;
    const double ls0 = sp[0] * d.l0, ls1 = sp[1] * d.l1, ls2 = sp[2] * d.l2;
    const double y = (ls0 + ls1) + ls2;
    const double w0 = qd[0], w1 = w0 + qd[1], w2 = w1 + qd[2];
    const double vx = -((ls0 * w0 + ls1 * w1) + ls2 * w2);
    const double vy = (lc0 * w0 + lc1 * w1) + lc2 * w2;
    const double c2r = cp[1] * cp[0] + sp[1] * sp[0], s2r = sp[1] * cp[0] - cp[1] * sp[0];
    const double c3r = cp[2] * cp[1] + sp[2] * sp[1], s3r = sp[2] * cp[1] - cp[2] * sp[1];
    const double c23 = cp[2] * cp[0] + sp[2] * sp[0], s23 = sp[2] * cp[0] - cp[2] * sp[0];
    const double d01 = d.l0 * (d.h1 * c2r - d.bb1 * s2r), w01 = d.l0 * (d.bb1 * c2r + d.h1 * s2r);
    const double d02 = d.l0 * (d.h2 * c23 - d.bb2 * s23), w02 = d.l0 * (d.bb2 * c23 + d.h2 * s23);
    const double d12 = d.l1 * (d.h2 * c3r - d.bb2 * s3r), w12 = d.l1 * (d.bb2 * c3r + d.h2 * s3r);
    const double ac0 = qdd[0], ac1 = ac0 + qdd[1], ac2 = ac1 + qdd[2];
    const double ww0 = w0 * w0, ww1 = w1 * w1, ww2 = w2 * w2;
    a[0] = d.dd0 * ac0 + d01 * ac1 + d02 * ac2 - w01 * ww1 - w02 * ww2;
    a[1] = d01 * ac0 + d.dd1 * ac1 + d12 * ac2 + w01 * ww0 - w12 * ww2;
    a[2] = d02 * ac0 + d12 * ac1 + d.dd2 * ac2 + w02 * ww0 + w12 * ww1;
    gv[0] = d.g * (d.h0 * cp[0] - d.bb0 * sp[0]);
    gv[1] = d.g * (d.h1 * cp[1] - d.bb1 * sp[1]);
    gv[2] = d.g * (d.h2 * cp[2] - d.bb2 * sp[2]);
    const double speed = sqrt(vx * vx + vy * vy);
    /* Branch-free (selects, no branch: the loops that call it vectorise); out of the soil
     * the force is computed with a stand-in speed and not used. */
    *depth = H - y;
    const int soil = (*depth > 0.0) & (speed > 0.0);
    const double divisor = soil ? speed : 1.0;
    const double gain = d.k0b * *depth / divisor;
    const double tx = gain * vx, ty = gain * vy;
    const double mu_neg = -d.mu;
    const double side_mu = vx > 0.0 ? d.mu : mu_neg;
    const double fx = -tx - side_mu * ty;
    const double fy = -ty + side_mu * tx;
    const double f0 = -(d.l0 * (cp[0] * fy - sp[0] * fx));
    const double f1 = -(d.l1 * (cp[1] * fy - sp[1] * fx));
    const double f2 = -(d.l2 * (cp[2] * fy - sp[2] * fx));
    f[0] = soil ? f0 : 0.0;
    f[1] = soil ? f1 : 0.0;
    f[2] = soil ? f2 : 0.0;
    return speed;
}


/* The plan's scan grid and scratch (plan.c; the binding allocates them). */
/* The scan runs on every VK_PL_STRIDE-th sample (26 of 101): it only picks the bracket, which
 * the full grid then judges and refines (vk_plan_scale_coarse). Measured with and without it: per-row
 * minimum kernel plan time over the 400 held-out PINN rows 13.9 -> 11.4 us (AVX2). On the 1600
 * rows of the kernel check (held-out and perturbed), feasibility is the same row for row; one
 * row's fill scale lands in another bracket (c 0.008 apart, objective 6e-4 apart); the others
 * agree to ~1e-14 (the refinement starts from other probes). Set VK_PL_COARSE 0 for the
 * full-grid scan everywhere. */
#define VK_PL_STRIDE 4
#define VK_PL_COARSE 1

/* Plan scratch: VK_N_PLAN arrays of m doubles: A and B per joint, three trig buffers and a
 * rotation (6 arrays each: cos of the three absolute angles, then their sin). */
enum vk_plan_scratch {
    S_A = 0, S_B = 3, S_T0 = 6, S_T1 = 12, S_T2 = 18, S_R = 24, S_X = 30, VK_N_PLAN = 33
};

/* ---------------------------------------------------------------------------------------------
 * Trench screening (rt_runtime.planning.trench.TrenchSession._screen_kind): the geometry of
 * every candidate dig's tip path at a few bulge scales, on a coarse grid of samples.
 *
 * Why C: a screening computes ~400 candidates x 4 scales x 9 samples (~15k tip points) and
 * their excavated area, over-dig and cut on the height field; numpy spends ~1.7 ms of a 2.5 ms
 * screening on it (a dozen passes over (N, 4, 9) arrays with temporaries), the loop here
 * ~0.1 ms. The same formulas in the same association order as trench.py's numpy path
 * (_screen_paths_numpy, the reference; tests/test_trench.py holds the two together):
 * q = base + c (pf K) with base = q1 + qf (q2 - q1), kinematics.FastArm.tip_xy,
 * oneshot.excavated_area_m2 (vk_segment_area), TrenchSession._overdig_many, _on_grid and
 * _cut_estimate. Sums run in sample order (numpy's pairwise sums group 8 terms differently:
 * ~1e-16 relative).
 * ------------------------------------------------------------------------------------------- */

/* The height field and the design a screening measures against (trench.py's session state). */
typedef struct {
    const double *surface, *floor; /* on the grid, n points */
    double x0, h, machine_x;
    ptrdiff_t n;
    const double *walls;           /* 3 x 3: n_x, n_y, c of the far wall, near wall, bottom */
    double xf, xn, ground;         /* the trench's x range and the ground line */
    const double *edges;           /* E x 5: ax, ay, abx, aby, |ab|^2 (the design's edges) */
    ptrdiff_t n_edges;
} vk_field;

/* TrenchSession._on_grid: linear interpolation on the uniform grid, clamped at the ends. */

/* ---------------------------------------------------------------------------------------------
 * The minimum-torque model's constants (mintorque.c), packed by
 * rt_runtime.planning.mintorque._pack_kernel in this order.
 * ------------------------------------------------------------------------------------------- */
#define MT_N_KEY 5
#define MT_N_INTERVALS 4
#define MT_N_KP 26                                /* keypoint constraints */
#define MT_N_SPLIT (30 * MT_N_INTERVALS + MT_N_KP) /* smooth maxima, then keypoints */
#define MT_N_NAMED (18 + MT_N_KP)                 /* sampled peaks, then keypoints */
#define MT_MAX_PLATES 256                         /* bucket plates of the soil model */

enum mt_param {
    MT_LEN = 0,        /* link lengths (m) */
    MT_CH_H = 3,       /* mintorque._Chain h, b, d */
    MT_CH_B = 6,
    MT_CH_D = 9,
    MT_GRAVITY = 12,
    MT_RHO_G = 13,     /* kp * density * g (N/m^3) */
    MT_KV = 14,        /* fluid soil kv, ks */
    MT_KS = 15,
    MT_EPS = 16,       /* depth smoothing (m) */
    MT_SPEED_REG = 17, /* speed smoothing (m/s) */
    MT_SURFACE = 18,   /* H (m) */
    MT_Q_MIN = 19,     /* joint limits (rad) and their span */
    MT_Q_MAX = 22,
    MT_Q_SPAN = 25,
    MT_V_LIM = 28,     /* scaled velocity, acceleration, jerk and torque limits */
    MT_A_LIM = 31,
    MT_J_LIM = 34,
    MT_T_LIM = 37,
    MT_TAU_MAX = 40,   /* the cost's torque normalisation (N m) */
    MT_KS_RHO = 43,
    MT_VOLUME = 44,    /* volume band (m^3) */
    MT_DEPTH = 46,     /* depth band of b and c (m) */
    MT_ENTRY_X = 48,   /* entry window (m) */
    MT_BAND = 50,      /* surface band (m) */
    MT_WIDTH = 51,     /* bucket width (m) */
    MT_HEADING = 52,   /* entry cone's two normals, then the lift cone's (x, y each) */
    MT_INTERVALS = 60, /* a fixed-time problem's intervals (s) */
    MT_N_PARAMS = 64
};

/* ---------------------------------------------------------------------------------------------
 * The units' entry points.
 * ------------------------------------------------------------------------------------------- */

/* evaluate.c */
void vk_evaluate(const double *p, const double *s, int m, const double *in, double *out,
                 double *path);

/* retime.c */
int vk_prepare(const double *p, const double *s, int m, const double *in, double *K,
               const double *trig, double *cache, double *qd_pk, double *qdd_pk);
double vk_retime_T(const double *p, const double *c, int m, const double *qd_pk,
                   const double *qdd_pk, int *found, int need_best, double *window, int *bind);
void vk_retime_finish(const double *p, const double *s, int m, const double *in,
                      const double *K, double T, int found, double *out, double *retimed,
                      double *path);
void vk_retime(const double *p, const double *s, int m, const double *in, double *out,
               double *retimed, double *path, const double *trig, double *cache);

/* plan.c */
void vk_plan(const double *p, const double *s, const double *basis, int m,
             const double *basis_c, int m_c, const double *in, double c_lo, double c_hi,
             double *out, double *planned, double *path, double *scale, double *cache,
             double *sc, double *sc_c);

/* mintorque.c: X (B, n_var) points, n_var 19 (variable time) or 15; out cost (B,), named
 * (B, MT_N_NAMED), split (B, MT_N_SPLIT). -1 when the scratch cannot be allocated, -2 for more
 * than MT_MAX_PLATES plates. */
int mt_evaluate(const double *p, const double *basis, int Q, const double *plates, int P,
                const double *X, ptrdiff_t B, int n_var, double *cost, double *named,
                double *split);
/* mintorque.c: the n_var points x + step e_v (v = 0 .. n_var - 1) of one point x (forward
 * differences), recomputing only the intervals each variable moves; out cost (n_var,), split
 * (n_var, MT_N_SPLIT). */
int mt_perturbed(const double *p, const double *basis, int Q, const double *plates, int P,
                 const double *x, int n_var, double step, double *cost, double *split);
/* mintorque.c: sum_k w_k sum_j (tau_j / tau_max_j)^2 of B sampled paths, q, qd, qdd (B, n, 3)
 * and weights w (B, n) (the cost of mintorque_oneshot on any path). */
int mt_path_cost(const double *p, const double *plates, int P, const double *q,
                 const double *qd, const double *qdd, const double *w, ptrdiff_t B, ptrdiff_t n,
                 double *cost);

/* trench.c */
double vk_overdig_path(const vk_field *f, const double *path, ptrdiff_t n);
void vk_lower_envelope(const double *path, ptrdiff_t n, const double *grid, ptrdiff_t M,
                       double *env);
#define VK_SCREEN_MAX 512 /* samples x scales per candidate */
void vk_screen_row(const double *p, const double *x7, const double *K, const double *qf,
                   const double *pf, int S, const double *G, int nG, const vk_field *f,
                   double *out, ptrdiff_t stride);
void vk_depth_below(const double *grid, const double *surface, ptrdiff_t M, const double *x,
                    const double *y, const double *cap, ptrdiff_t N, double *out);
void vk_move_poses(const double *tables, const double *times, ptrdiff_t n, double *out);
int vk_bucket_depth(const double *q, ptrdiff_t n, const double *lengths, const double *outline,
                    ptrdiff_t m, double machine_x, const double *grid, const double *surface,
                    ptrdiff_t M, const double *cap, double *out);
#define VK_FIT_MAX_SAMPLES 1024 /* samples of a profile fit's path */
int vk_fit_iterate(const double *base, const double *pf, ptrdiff_t n, const double *lengths,
                   const double *edges, ptrdiff_t E, const double *jac0, const double *d_ent,
                   const double *par, double *K, double *step, double *mu, double *cost,
                   double *best, double *active, double *go, double *A, double *rhs);
#define VK_FIT_ITERATIONS 9 /* a profile fit's Gauss-Newton iterations */
void vk_fit_bulges(const double *base, const double *pf, ptrdiff_t n, const double *lengths,
                   const double *edges, ptrdiff_t E, const double *jac0, const double *d_ent,
                   const double *par, double *best, double *cost);

#endif
