/*
 * One-shot dig verifier kernel: what rt_runtime.planning.oneshot.evaluate computes for one
 * candidate, looping over the samples in C (the Python side is rt_runtime/planning/verify.py).
 *
 * Why C: evaluate() is numpy batched over (B, P); for a single candidate each of its numpy
 * operations on a tiny array costs 0.5-3 us, ~0.6 ms in all. This loop does the same arithmetic
 * in ~7 us at 101 samples, without allocating.
 *
 * Layout: the kernel (vk_*) is plain C99 with no Python in it; below it a minimal CPython
 * extension type `Kernel` holds the packed rig constants and the time grid, and its `run`
 * method (METH_FASTCALL, buffer protocol) is the per-call entry point: it measured 0.1 us per
 * call against 0.4 us for ctypes with cached pointers and 2.6 us for ctypes taking the
 * pointers of the caller's arrays per call. `retime` (vk_retime) keeps each candidate's path
 * and finds the shortest feasible time along it, then evaluates that with vk_evaluate. `plan`
 * (vk_plan) scales the candidate's bulge to the largest volume its path-only constraints allow
 * and retimes that path.
 *
 * Parity with the numpy reference: the same formulas in the same association order as
 * sextic.py, kinematics.tip_state, soil.yao_resistance, dynamics._inverse_block,
 * dynamics.energy_j, oneshot.excavated_area_m2 and oneshot._entry_angle (a change there must
 * be made here too: tests/test_verify.py holds the two together). Outputs agree to ~1e-12
 * relative (numpy's matrix products and pairwise sums round differently); the only
 * discontinuities, which sample first lies below the surface and whether the start is within
 * 1 mm of it, would need a sample within an ulp of those thresholds to differ. No -ffast-math,
 * no FMA contraction (setup.py passes -ffp-contract=off).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

/* One source, two modules (setup.py): "_verify" for any x86-64 (or other) CPU, and
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

#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <time.h>

/* ---------------------------------------------------------------------------------------------
 * Layouts shared with verify.py (bump VK_ABI on any change: verify.py refuses a stale build).
 * ------------------------------------------------------------------------------------------- */
#define VK_ABI 7

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
static void vk_sincos_n(const double *restrict x, double *restrict sn, double *restrict cs,
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
static void vk_reject(int m, double *out, double *path)
{
    for (int j = 0; j < VK_N_OUT; j++) out[j] = NAN;
    out[O_TOTAL] = INFINITY;
    if (path != NULL)
        for (int i = 0; i < 2 * m; i++) path[i] = NAN;
}

/*
 * Evaluate one candidate.
 *   p:    packed constants (enum vk_param)
 *   s:    normalised time grid, m >= 2 points from 0 to 1 (numpy.linspace)
 *   in:   one input row (enum vk_input)
 *   out:  one output row (enum vk_output)
 *   path: NULL or (m, 2) tip x, y at the samples
 */
static void vk_evaluate(const double *p, const double *s, int m, const double *in, double *out,
                        double *path)
{
    for (int j = 0; j < VK_N_IN; j++)
        if (!isfinite(in[j])) {
            vk_reject(m, out, path);
            return;
        }
    const double H = in[I_SURFACE];
    const double T = in[I_T];
    const double dig = in[I_DIG_TYPE];
    if (!(T > 0.0) || !(dig == 0.0 || dig == 1.0)) {
        vk_reject(m, out, path);
        return;
    }

    /* Sextic coefficients (sextic.sextic_coefficients) scaled to s (b_k = a_k T^k, as
     * sextic.evaluate does with T ** k). b1 = b2 = 0. */
    const double T2 = T * T, T3 = T2 * T;
    double Tp[7];
    Tp[0] = 1.0;
    Tp[1] = T;
    for (int k = 2; k < 7; k++) Tp[k] = pow(T, (double)k);
    double b0[3], b3[3], b4[3], b5[3], b6[3], a3[3];
    double c1[3][4], c2[3][4]; /* Horner coefficients of dq/ds and d2q/ds2 */
    for (int j = 0; j < 3; j++) {
        const double qs = in[I_Q_START + j], c6 = in[I_A6 + j];
        const double D = in[I_Q_END + j] - qs;
        a3[j] = 10.0 * D / T3 - c6 * T3;
        const double a4 = -15.0 * D / (T3 * T) + 3.0 * c6 * T2;
        const double a5 = 6.0 * D / (T3 * T2) - 3.0 * c6 * T;
        b0[j] = qs * Tp[0];
        b3[j] = a3[j] * Tp[3];
        b4[j] = a4 * Tp[4];
        b5[j] = a5 * Tp[5];
        b6[j] = c6 * Tp[6];
        c1[j][0] = 3.0 * b3[j];
        c1[j][1] = 4.0 * b4[j];
        c1[j][2] = 5.0 * b5[j];
        c1[j][3] = 6.0 * b6[j];
        c2[j][0] = 6.0 * b3[j];
        c2[j][1] = 12.0 * b4[j];
        c2[j][2] = 20.0 * b5[j];
        c2[j][3] = 30.0 * b6[j];
    }
    const double inv_T = 1.0 / T;
    const double inv_T2 = inv_T * inv_T;

    const double l0 = p[P_LEN], l1 = p[P_LEN + 1], l2 = p[P_LEN + 2];
    const double h0 = p[P_CH_H], h1 = p[P_CH_H + 1], h2 = p[P_CH_H + 2];
    const double bb0 = p[P_CH_B], bb1 = p[P_CH_B + 1], bb2 = p[P_CH_B + 2];
    const double dd0 = p[P_CH_D], dd1 = p[P_CH_D + 1], dd2 = p[P_CH_D + 2];
    const double g = p[P_GRAVITY], k0b = p[P_K0B], mu = p[P_MU], reg = p[P_SPEED_REG];

    double q_lo[3] = {INFINITY, INFINITY, INFINITY};
    double q_hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    double qd_peak[3] = {0.0, 0.0, 0.0};
    double qdd_peak[3] = {0.0, 0.0, 0.0};
    double tau_peak[3] = {0.0, 0.0, 0.0};
    double power_peak = 0.0; /* a sum of positive parts: >= 0 */
    double energy_acc = 0.0;
    vk_polyline pl = {0.0, 0.0, 0.0, 0.0, 0.0, -1};
    /* Sum of every per-sample value: non-finite exactly when one of them is (or overflows),
     * which the plain max/min above could hide. */
    double check = 0.0;
    double power_prev = 0.0, t_prev = 0.0;
    double y_first = 0.0;
    double sp_first[3] = {0.0, 0.0, 0.0}, cp_first[3] = {0.0, 0.0, 0.0};

    double qv[3][VK_BLOCK], qdv[3][VK_BLOCK], qddv[3][VK_BLOCK];
    double phi[3][VK_BLOCK], cph[3][VK_BLOCK], sph[3][VK_BLOCK];
    double bx[VK_BLOCK], by[VK_BLOCK], bt[3][VK_BLOCK], bpow[VK_BLOCK], bchk[VK_BLOCK];
    const double mu_neg = -mu;

    for (int base = 0; base < m; base += VK_BLOCK) {
        const int nb = m - base < VK_BLOCK ? m - base : VK_BLOCK;

        /* Joint angles, rates, accelerations (sextic.evaluate; a loop that vectorises) and
         * their extremes (in sample order). */
        for (int j = 0; j < 3; j++) {
            for (int k = 0; k < nb; k++) {
                const double si = s[base + k];
                const double s2 = si * si, s3 = s2 * si;
                qv[j][k] = b0[j] + s3 * (b3[j] + si * (b4[j] + si * (b5[j] + si * b6[j])));
                qdv[j][k] =
                    s2 * (c1[j][0] + si * (c1[j][1] + si * (c1[j][2] + si * c1[j][3]))) * inv_T;
                qddv[j][k] =
                    si * (c2[j][0] + si * (c2[j][1] + si * (c2[j][2] + si * c2[j][3]))) * inv_T2;
            }
            double lo = q_lo[j], hi = q_hi[j], vp = qd_peak[j], ap = qdd_peak[j];
            for (int k = 0; k < nb; k++) {
                lo = vk_min(lo, qv[j][k]);
                hi = vk_max(hi, qv[j][k]);
                vp = vk_max(vp, fabs(qdv[j][k]));
                ap = vk_max(ap, fabs(qddv[j][k]));
            }
            q_lo[j] = lo;
            q_hi[j] = hi;
            qd_peak[j] = vp;
            qdd_peak[j] = ap;
        }
        for (int k = 0; k < nb; k++) {
            phi[0][k] = qv[0][k];
            phi[1][k] = phi[0][k] + qv[1][k];
            phi[2][k] = phi[1][k] + qv[2][k];
        }
        /* Trig of the absolute angles (kinematics.tip_state), by vk_sincos; at the start
         * (q0 exactly) by libm, so that the start's tip is bit for bit numpy's: the poses are
         * solved for y = H, and "below the surface" and "within 1 mm of it" are decided there. */
        for (int j = 0; j < 3; j++) vk_sincos_n(phi[j], sph[j], cph[j], nb);
        if (base == 0)
            for (int j = 0; j < 3; j++) {
                cph[j][0] = cos(phi[j][0]);
                sph[j][0] = sin(phi[j][0]);
            }

        /* Per sample (a loop that vectorises: no branch, no carried value): the tip, the
         * torques and the power, into the block's arrays. */
        for (int k = 0; k < nb; k++) {
            const double qd0 = qdv[0][k], qd1 = qdv[1][k], qd2 = qdv[2][k];
            const double cp0 = cph[0][k], cp1 = cph[1][k], cp2 = cph[2][k];
            const double sp0 = sph[0][k], sp1 = sph[1][k], sp2 = sph[2][k];

            /* Tip pose and twist (kinematics.tip_state). */
            const double lc0 = cp0 * l0, lc1 = cp1 * l1, lc2 = cp2 * l2;
            const double ls0 = sp0 * l0, ls1 = sp1 * l1, ls2 = sp2 * l2;
            const double x = (lc0 + lc1) + lc2;
            const double y = (ls0 + ls1) + ls2;
            const double w0 = qd0, w1 = w0 + qd1, w2 = w1 + qd2;
            const double vx = -((ls0 * w0 + ls1 * w1) + ls2 * w2);
            const double vy = (lc0 * w0 + lc1 * w1) + lc2 * w2;

            /* Inverse dynamics (dynamics._inverse_block); relative-angle trig from the
             * absolute angles' by the difference formulas. */
            const double c2r = cp1 * cp0 + sp1 * sp0, s2r = sp1 * cp0 - cp1 * sp0;
            const double c3r = cp2 * cp1 + sp2 * sp1, s3r = sp2 * cp1 - cp2 * sp1;
            const double c23 = cp2 * cp0 + sp2 * sp0, s23 = sp2 * cp0 - cp2 * sp0;
            const double d01 = l0 * (h1 * c2r - bb1 * s2r), w01 = l0 * (bb1 * c2r + h1 * s2r);
            const double d02 = l0 * (h2 * c23 - bb2 * s23), w02 = l0 * (bb2 * c23 + h2 * s23);
            const double d12 = l1 * (h2 * c3r - bb2 * s3r), w12 = l1 * (bb2 * c3r + h2 * s3r);
            const double ac0 = qddv[0][k], ac1 = ac0 + qddv[1][k], ac2 = ac1 + qddv[2][k];
            const double ww0 = w0 * w0, ww1 = w1 * w1, ww2 = w2 * w2;
            double t0 = dd0 * ac0 + d01 * ac1 + d02 * ac2 - w01 * ww1 - w02 * ww2;
            t0 += g * (h0 * cp0 - bb0 * sp0);
            double t1 = d01 * ac0 + dd1 * ac1 + d12 * ac2 + w01 * ww0 - w12 * ww2;
            t1 += g * (h1 * cp1 - bb1 * sp1);
            double t2 = d02 * ac0 + d12 * ac1 + dd2 * ac2 + w02 * ww0 + w12 * ww1;
            t2 += g * (h2 * cp2 - bb2 * sp2);

            /* Yao eq 8 at the tip (soil.yao_resistance, flat surface H); none above it: the
             * force is computed either way and selected. */
            const double depth = H - y;
            const double w_q = k0b * depth;
            /* sqrt for hypot: equal to an ulp at the speeds an arm reaches, 10x faster. */
            const double speed = vk_max(sqrt(vx * vx + vy * vy), reg);
            const double gain = w_q / speed;
            const double tx = gain * vx, ty = gain * vy;
            const double side_mu = vx > 0.0 ? mu : mu_neg;
            const double fx = -tx - side_mu * ty;
            const double fy = -ty + side_mu * tx;
            const double r0 = t0 - l0 * (cp0 * fy - sp0 * fx);
            const double r1 = t1 - l1 * (cp1 * fy - sp1 * fx);
            const double r2 = t2 - l2 * (cp2 * fy - sp2 * fx);
            const int soil = depth > 0.0;
            t0 = soil ? r0 : t0;
            t1 = soil ? r1 : t1;
            t2 = soil ? r2 : t2;
            t1 += t2;
            t0 += t1;

            bx[k] = x;
            by[k] = y;
            bt[0][k] = t0;
            bt[1][k] = t1;
            bt[2][k] = t2;
            /* Positive power (no regeneration). */
            bpow[k] = (vk_pos(t0 * qd0) + vk_pos(t1 * qd1)) + vk_pos(t2 * qd2);
            bchk[k] = ((x + y) + (t0 + t1 + t2)) + ((qd0 + qd1 + qd2) + (ac0 + ac1 + ac2));
        }
        if (path != NULL)
            for (int k = 0; k < nb; k++) {
                path[2 * (base + k)] = bx[k];
                path[2 * (base + k) + 1] = by[k];
            }

        /* In sample order: the peaks, the energy by the trapezoid rule on t = s T, the
         * excavated area, the entry segment. */
        for (int k = 0; k < nb; k++) {
            const int i = base + k;
            const double x = bx[k], y = by[k], power = bpow[k];
            tau_peak[0] = vk_max(tau_peak[0], fabs(bt[0][k]));
            tau_peak[1] = vk_max(tau_peak[1], fabs(bt[1][k]));
            tau_peak[2] = vk_max(tau_peak[2], fabs(bt[2][k]));
            power_peak = vk_max(power_peak, power);
            const double t = s[i] * T;
            check += bchk[k];

            vk_polyline_add(&pl, i, x, y, H);
            if (i == 0) {
                y_first = y;
                for (int j = 0; j < 3; j++) {
                    sp_first[j] = sph[j][0];
                    cp_first[j] = cph[j][0];
                }
            } else {
                energy_acc += (power + power_prev) * (t - t_prev);
            }
            power_prev = power;
            t_prev = t;
        }
    }

    /* theta_p (oneshot._entry_angle). A start within 1 mm of the surface counts as an entry
     * whatever the last bit of y0 says (the poses are solved for y = H). */
    const int at_start = y_first <= H + 1e-3;
    double theta_p;
    if (pl.first_below < 0 && !at_start) {
        theta_p = -1.57079632679489661923; /* -pi/2: violates every theta_p range */
    } else {
        /* The entry segment (sample 0 below the surface means a start on it, which takes
         * J(q0) a3 instead). */
        double dx = pl.entry_dx, dy = pl.entry_dy;
        if (at_start) {
            /* Direction J(q0) a3, the cubic term leading; sample 0 is q0 exactly, so its trig
             * is kinematics.jacobian's. */
            const double v0 = -sp_first[0] * l0, v1 = -sp_first[1] * l1, v2 = -sp_first[2] * l2;
            const double sx2 = v2, sx1 = v2 + v1, sx0 = (v2 + v1) + v0;
            const double u0 = cp_first[0] * l0, u1 = cp_first[1] * l1, u2 = cp_first[2] * l2;
            const double sy2 = u2, sy1 = u2 + u1, sy0 = (u2 + u1) + u0;
            dx = (sx0 * a3[0] + sx1 * a3[1]) + sx2 * a3[2];
            dy = (sy0 * a3[0] + sy1 * a3[1]) + sy2 * a3[2];
        }
        theta_p = atan2(-dy, fabs(dx));
    }

    const double volume = fabs(pl.area) * p[P_WIDTH];
    const double energy = 0.5 * energy_acc;

    double *v = out + O_VIOLATIONS;
    for (int j = 0; j < 3; j++) {
        v[j] = (p[P_Q_MIN + j] - q_lo[j]) / p[P_Q_SPAN + j];
        v[3 + j] = (q_hi[j] - p[P_Q_MAX + j]) / p[P_Q_SPAN + j];
        v[6 + j] = qd_peak[j] / p[P_QD_MAX + j] - 1.0;
        v[9 + j] = qdd_peak[j] / p[P_QDD_MAX + j] - 1.0;
        v[12 + j] = tau_peak[j] / p[P_TAU_MAX + j] - 1.0;
    }
    v[15] = power_peak / p[P_POWER_MAX] - 1.0;
    const double *tp = dig == 0.0 ? p + P_TP_DOWN : p + P_TP_BACK;
    const double tp_span = tp[1] - tp[0];
    v[16] = (tp[0] - theta_p) / tp_span;
    v[17] = (theta_p - tp[1]) / tp_span;
    const double vol_min = p[P_VOL], vol_max = p[P_VOL + 1], vol_span = vol_max - vol_min;
    v[18] = (vol_min - volume) / vol_span;
    v[19] = (volume - vol_max) / vol_span;
    const double t_min = p[P_TIME], t_max = p[P_TIME + 1], t_span = t_max - t_min;
    v[20] = (t_min - T) / t_span;
    v[21] = (T - t_max) / t_span;

    const double e_min = p[P_ENERGY], e_max = p[P_ENERGY + 1];
    const double t_t = (T - t_min) / t_span;
    const double e_e = (energy - e_min) / (e_max - e_min);
    const double v_v = (vol_max - volume) / vol_span;
    out[O_OBJECTIVE] = p[P_WEIGHTS] * t_t + p[P_WEIGHTS + 1] * e_e + p[P_WEIGHTS + 2] * v_v;
    out[O_T] = T;
    out[O_VOLUME] = volume;
    out[O_ENERGY] = energy;
    out[O_THETA_P] = theta_p;
    out[O_PEAK_POWER] = power_peak;
    for (int j = 0; j < 3; j++) out[O_PEAK_TORQUE + j] = tau_peak[j];

    /* Overflow (absurd but finite inputs): where numpy's total would be inf or NaN, +inf. */
    int finite = isfinite(check);
    double total = 0.0;
    for (int j = 0; j < VK_N_CONSTRAINTS; j++) total += vk_pos(v[j]);
    for (int j = 0; j < VK_N_OUT; j++)
        if (j != O_TOTAL && !isfinite(out[j])) finite = 0;
    out[O_TOTAL] = finite ? total : INFINITY;
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

/*
 * Fill the unit-time cache of one input row.
 *   K:      out, the kept shape term -a6 T^6 per joint (as oneshot.particle_from_a6)
 *   trig:   NULL, or cos then sin of the absolute angles of the row's path (6 arrays of m:
 *           cos phi_0, phi_1, phi_2, sin phi_0, ...) that the caller already has
 *   qd_pk, qdd_pk: out, max |q'| and max |q''| per joint over the samples
 * Returns -1 for a row that run() rejects or whose K is not finite, 0 for a finite cache, 1
 * when the cache overflowed (absurd but finite inputs).
 */
static int vk_prepare(const double *p, const double *s, int m, const double *in, double *K,
                      const double *trig, double *cache, double *qd_pk, double *qdd_pk)
{
    for (int j = 0; j < VK_N_IN; j++)
        if (!isfinite(in[j])) return -1;
    const double T = in[I_T];
    const double dig = in[I_DIG_TYPE];
    if (!(T > 0.0) || !(dig == 0.0 || dig == 1.0)) return -1;
    const double T6 = pow(T, 6.0);
    double b0[3], b3[3], b4[3], b5[3], b6[3], c1[3][4], c2[3][4];
    for (int j = 0; j < 3; j++) {
        K[j] = -in[I_A6 + j] * T6;
        if (!isfinite(K[j])) return -1;
        /* Yao eq 10 (corrected) at T = 1: a6 = -K. */
        const double qs = in[I_Q_START + j], c6 = -K[j];
        const double D = in[I_Q_END + j] - qs;
        b0[j] = qs;
        b3[j] = 10.0 * D - c6;
        b4[j] = -15.0 * D + 3.0 * c6;
        b5[j] = 6.0 * D - 3.0 * c6;
        b6[j] = c6;
        c1[j][0] = 3.0 * b3[j];
        c1[j][1] = 4.0 * b4[j];
        c1[j][2] = 5.0 * b5[j];
        c1[j][3] = 6.0 * b6[j];
        c2[j][0] = 6.0 * b3[j];
        c2[j][1] = 12.0 * b4[j];
        c2[j][2] = 20.0 * b5[j];
        c2[j][3] = 30.0 * b6[j];
        qd_pk[j] = 0.0;
        qdd_pk[j] = 0.0;
    }
    const double H = in[I_SURFACE];
    const vk_dyn dyn = vk_dyn_of(p);
    double check = 0.0;

    double qv[3][VK_BLOCK], qdv[3][VK_BLOCK], qddv[3][VK_BLOCK];
    double phi[3][VK_BLOCK], cph[3][VK_BLOCK], sph[3][VK_BLOCK], chk[VK_BLOCK];
    double blk[C_QP][VK_BLOCK];
    for (int base = 0; base < m; base += VK_BLOCK) {
        const int nb = m - base < VK_BLOCK ? m - base : VK_BLOCK;
        for (int j = 0; j < 3; j++) {
            for (int k = 0; k < nb; k++) { /* vectorises */
                const double si = s[base + k];
                const double s2 = si * si, s3 = s2 * si;
                qv[j][k] = b0[j] + s3 * (b3[j] + si * (b4[j] + si * (b5[j] + si * b6[j])));
                qdv[j][k] = s2 * (c1[j][0] + si * (c1[j][1] + si * (c1[j][2] + si * c1[j][3])));
                qddv[j][k] = si * (c2[j][0] + si * (c2[j][1] + si * (c2[j][2] + si * c2[j][3])));
            }
            double vp = qd_pk[j], ap = qdd_pk[j];
            for (int k = 0; k < nb; k++) {
                vp = vk_max(vp, fabs(qdv[j][k]));
                ap = vk_max(ap, fabs(qddv[j][k]));
            }
            qd_pk[j] = vp;
            qdd_pk[j] = ap;
        }
        for (int k = 0; k < nb; k++) {
            phi[0][k] = qv[0][k];
            phi[1][k] = phi[0][k] + qv[1][k];
            phi[2][k] = phi[1][k] + qv[2][k];
        }
        if (trig != NULL)
            for (int j = 0; j < 3; j++)
                for (int k = 0; k < nb; k++) {
                    cph[j][k] = trig[j * m + base + k];
                    sph[j][k] = trig[(3 + j) * m + base + k];
                }
        else
            for (int j = 0; j < 3; j++) vk_sincos_n(phi[j], sph[j], cph[j], nb);
        for (int k = 0; k < nb; k++) {
            const double qd0 = qdv[0][k], qd1 = qdv[1][k], qd2 = qdv[2][k];
            const double cpk[3] = {cph[0][k], cph[1][k], cph[2][k]};
            const double spk[3] = {sph[0][k], sph[1][k], sph[2][k]};
            const double qdk[3] = {qd0, qd1, qd2};
            const double qddk[3] = {qddv[0][k], qddv[1][k], qddv[2][k]};
            double at[3], gt[3], ft[3], depth;
            const double speed = vk_unit_dynamics(dyn, H, cpk, spk, qdk, qddk, at, gt, ft, &depth);
            const double a0 = at[0], a1 = at[1], a2 = at[2];
            const double g0 = gt[0], g1 = gt[1], g2 = gt[2];
            const double f0 = ft[0], f1 = ft[1], f2 = ft[2];
            const double ac2 = (qddk[0] + qddk[1]) + qddk[2], w2 = (qd0 + qd1) + qd2;
            const double A1i = a1 + a2, A0i = a0 + A1i;
            const double G1i = g1 + g2, G0i = g0 + G1i;
            const double F1i = f1 + f2, F0i = f0 + F1i;
            blk[C_A][k] = A0i;
            blk[C_A + 1][k] = A1i;
            blk[C_A + 2][k] = a2;
            blk[C_G][k] = G0i;
            blk[C_G + 1][k] = G1i;
            blk[C_G + 2][k] = g2;
            blk[C_F][k] = F0i;
            blk[C_F + 1][k] = F1i;
            blk[C_F + 2][k] = f2;
            blk[C_SP][k] = speed;
            chk[k] = ((A0i + G0i) + (F0i + speed)) + (ac2 + w2);
        }
        /* Stores to the cache after the loop: within it, to the block (which nothing aliases),
         * so that it vectorises. */
        const size_t bytes = (size_t)nb * sizeof(double);
        for (int c = 0; c < C_QP; c++) memcpy(cache + c * m + base, blk[c], bytes);
        for (int j = 0; j < 3; j++) memcpy(cache + (C_QP + j) * m + base, qdv[j], bytes);
        for (int k = 0; k < nb; k++) check += chk[k]; /* in order: the loop above vectorises */
    }
    return isfinite(check) ? 0 : 1;
}

/* Time-dependent constraints at T from the cache: the largest value / limit ratio (velocity,
 * acceleration, torque, power) and the sum of the positive parts of (ratio - 1), which is
 * what evaluate's total violation holds of them. */
static void vk_timed(const double *p, const double *c, int m, const double *qd_pk,
                     const double *qdd_pk, double T, double *ratio, double *total)
{
    const double inv_T = 1.0 / T, u = inv_T * inv_T, k_reg = inv_T / p[P_SPEED_REG];
    const double *A0 = c + C_A * m, *A1 = A0 + m, *A2 = A1 + m;
    const double *G0 = c + C_G * m, *G1 = G0 + m, *G2 = G1 + m;
    const double *F0 = c + C_F * m, *F1 = F0 + m, *F2 = F1 + m;
    const double *Q0 = c + C_QP * m, *Q1 = Q0 + m, *Q2 = Q1 + m;
    const double *SP = c + C_SP * m;
    double pk0 = 0.0, pk1 = 0.0, pk2 = 0.0, ppk = 0.0;
    for (int i = 0; i < m; i++) {
        const double r = vk_min(1.0, SP[i] * k_reg);
        const double t0 = A0[i] * u + (G0[i] + F0[i] * r);
        const double t1 = A1[i] * u + (G1[i] + F1[i] * r);
        const double t2 = A2[i] * u + (G2[i] + F2[i] * r);
        pk0 = vk_max(pk0, fabs(t0));
        pk1 = vk_max(pk1, fabs(t1));
        pk2 = vk_max(pk2, fabs(t2));
        ppk = vk_max(ppk, (vk_pos(t0 * Q0[i]) + vk_pos(t1 * Q1[i])) + vk_pos(t2 * Q2[i]));
    }
    const double pk[3] = {pk0, pk1, pk2};
    double worst = ppk * inv_T / p[P_POWER_MAX];
    double sum = vk_pos(worst - 1.0);
    for (int j = 0; j < 3; j++) {
        const double rv = qd_pk[j] * inv_T / p[P_QD_MAX + j];
        const double ra = qdd_pk[j] * u / p[P_QDD_MAX + j];
        const double rt = pk[j] / p[P_TAU_MAX + j];
        worst = vk_max(worst, vk_max(rv, vk_max(ra, rt)));
        sum += (vk_pos(rv - 1.0) + vk_pos(ra - 1.0)) + vk_pos(rt - 1.0);
    }
    *ratio = worst;
    *total = sum;
}

/* Closed-form range [*lo, *hi] of T within [t_min, t_max] outside which velocity,
 * acceleration or the torque of a sample with r = 1 on the whole range fails (limits times
 * 1 - VK_RT_MARGIN). Returns 0 when that range is empty. *window (unless NULL): the width of
 * the range in u = 1/T^2 that the velocity, acceleration and t_min bounds (from above) and the
 * torque bounds leave, not cut at u = 1/t_max^2 or 0 (1/s^2): > 0 where the closed-form bounds
 * leave some T (t_max aside), < 0 where they crossed, and smooth in the path (the back-off's
 * root search runs on it). bind (unless NULL): the samples that set the window's torque ends,
 * the largest lower and the least upper bound of u (-1 where none). */
static int vk_bounds(const double *p, const double *c, int m, const double *qd_pk,
                     const double *qdd_pk, double *lo, double *hi, double *window, int *bind)
{
    const double lim = 1.0 - VK_RT_MARGIN;
    double t_lo = vk_t_va(p, qd_pk, qdd_pk), t_hi = p[P_TIME + 1];
    /* Torque: |A u + B| <= tau_max is an interval of u = 1/T^2 per sample and joint. */
    const double sp_fast = p[P_SPEED_REG] * p[P_TIME + 1];
    const double *SP = c + C_SP * m;
    double u_lo = 0.0, u_hi = INFINITY, u_lo_raw = -INFINITY;
    int i_lo = -1, i_hi = -1;
    for (int j = 0; j < 3; j++) {
        const double *A = c + (C_A + j) * m, *G = c + (C_G + j) * m, *F = c + (C_F + j) * m;
        const double tm = p[P_TAU_MAX + j] * lim;
        for (int i = 0; i < m; i++) {
            if (F[i] != 0.0 && SP[i] < sp_fast) continue; /* regularised somewhere: searched */
            const double b = G[i] + F[i];
            double l, h;
            if (!vk_u_interval(A[i], b, tm, &l, &h)) {
                if (fabs(b) > tm) u_hi = -1.0;
                continue;
            }
            u_lo = vk_max(u_lo, l);
            u_hi = vk_min(u_hi, h);
            if (l > u_lo_raw) {
                u_lo_raw = l;
                i_lo = i;
            }
            if (h <= u_hi) i_hi = i;
        }
    }
    if (window != NULL) *window = vk_min(u_hi, 1.0 / (t_lo * t_lo)) - u_lo_raw;
    if (bind != NULL) {
        bind[0] = i_lo;
        bind[1] = i_hi;
    }
    if (!(u_lo <= u_hi) || !(u_hi > 0.0)) return 0;
    if (u_hi < INFINITY) t_lo = vk_max(t_lo, 1.0 / sqrt(u_hi));
    if (u_lo > 0.0) t_hi = vk_min(t_hi, 1.0 / sqrt(u_lo));
    *lo = t_lo;
    *hi = t_hi;
    return t_lo <= t_hi;
}

/* Illinois (regula falsi with halving) on psi = ratio - threshold over [a, b], psi(a) > 0 >=
 * psi(b); returns the feasible end once the bracket is VK_RT_TOL narrow. */
static double vk_boundary(const double *p, const double *c, int m, const double *qd_pk,
                          const double *qdd_pk, double a, double fa, double b, double fb)
{
    const double threshold = 1.0 - 0.5 * VK_RT_MARGIN;
    int side = 0;
    for (int it = 0; it < VK_RT_ITER && b - a > VK_RT_TOL * b; it++) {
        double x = (a * fb - b * fa) / (fb - fa);
        if (!(x > a && x < b)) x = 0.5 * (a + b);
        double ratio, total;
        vk_timed(p, c, m, qd_pk, qdd_pk, x, &ratio, &total);
        const double fx = ratio - threshold;
        if (fx <= 0.0) {
            b = x;
            fb = fx;
            if (side == -1) fa *= 0.5;
            side = -1;
        } else {
            a = x;
            fa = fx;
            if (side == 1) fb *= 0.5;
            side = 1;
        }
    }
    return b;
}

/* The retimed T of a prepared row; *found = 1 when the cache says every time-dependent
 * constraint holds there, else 0 and T is the candidate with the least cached violation (with
 * need_best 0, when only *found matters, the search for that candidate is skipped and T is
 * NAN). *window, bind (unless NULL): vk_bounds' window and binding samples. */
static double vk_retime_T(const double *p, const double *c, int m, const double *qd_pk,
                          const double *qdd_pk, int *found, int need_best, double *window,
                          int *bind)
{
    const double threshold = 1.0 - 0.5 * VK_RT_MARGIN;
    const double t_min = p[P_TIME], t_max = p[P_TIME + 1];
    double lo = t_min, hi = t_max, ratio, total;
    double best_T = t_max, best_total = INFINITY;
    *found = 0;
    if (vk_bounds(p, c, m, qd_pk, qdd_pk, &lo, &hi, window, bind)) {
        vk_timed(p, c, m, qd_pk, qdd_pk, lo, &ratio, &total);
        if (ratio <= threshold) {
            *found = 1;
            return lo;
        }
        if (total < best_total) {
            best_T = lo;
            best_total = total;
        }
        /* The lower bound fails on power or on a slow sample's torque: scan up to the first
         * point that holds, then close in on the boundary below it. */
        const double step = pow(hi / lo, 1.0 / VK_RT_SCAN);
        double a = lo, fa = ratio - threshold;
        for (int k = 1; k <= VK_RT_SCAN; k++) {
            const double x = k == VK_RT_SCAN ? hi : a * step;
            vk_timed(p, c, m, qd_pk, qdd_pk, x, &ratio, &total);
            if (ratio <= threshold) {
                *found = 1;
                return vk_boundary(p, c, m, qd_pk, qdd_pk, a, fa, x, ratio - threshold);
            }
            if (total < best_total) {
                best_T = x;
                best_total = total;
            }
            a = x;
            fa = ratio - threshold;
        }
    }
    if (!need_best) return NAN;
    /* Nothing in range holds: the least violating of the points above and a geometric grid
     * from t_min to t_max (NaN totals never win; all NaN leaves t_max). */
    const double step = pow(t_max / t_min, 1.0 / VK_RT_SCAN);
    double x = t_min;
    for (int k = 0; k <= VK_RT_SCAN; k++, x *= step) {
        if (k == VK_RT_SCAN) x = t_max;
        vk_timed(p, c, m, qd_pk, qdd_pk, x, &ratio, &total);
        if (total < best_total) {
            best_T = x;
            best_total = total;
        }
    }
    return best_T;
}

/* Whether the time-dependent constraints of an evaluated row hold. */
static int vk_timed_ok(const double *out)
{
    for (int j = 6; j <= 15; j++)
        if (!(out[O_VIOLATIONS + j] <= 0.0)) return 0;
    return out[O_VIOLATIONS + 20] <= 0.0 && out[O_VIOLATIONS + 21] <= 0.0;
}

/* Evaluate the path K at the retimed T (found: whether the search found it feasible; then
 * T grows a little if the evaluation contradicts the cache) into out; (a6', T') into
 * retimed. in: the row (its a6 and T are replaced). */
static void vk_retime_finish(const double *p, const double *s, int m, const double *in,
                             const double *K, double T, int found, double *out, double *retimed,
                             double *path)
{
    double row[VK_N_IN];
    for (int j = 0; j < VK_N_IN; j++) row[j] = in[j];
    for (int attempt = 0;; attempt++) {
        const double T6 = pow(T, 6.0);
        for (int j = 0; j < 3; j++) row[I_A6 + j] = -K[j] / T6;
        row[I_T] = T;
        vk_evaluate(p, s, m, row, out, path);
        if (!found || attempt == VK_RT_BUMPS || T >= p[P_TIME + 1] || vk_timed_ok(out)) break;
        T = vk_min(T * (1.0 + VK_RT_BUMP * pow(10.0, attempt)), p[P_TIME + 1]);
    }
    for (int j = 0; j < 3; j++) retimed[j] = row[I_A6 + j];
    retimed[3] = T;
}

/*
 * Retime one row: the smallest T' in [t_min, t_max] where every time-dependent constraint
 * holds with the path (K) kept, evaluated for real at T'.
 *   retimed: out, (a6', T') (NaN for a rejected row)
 *   trig:    NULL or the path's trig as vk_prepare takes it
 *   cache:   VK_N_CACHE * m scratch doubles
 */
static void vk_retime(const double *p, const double *s, int m, const double *in, double *out,
                      double *retimed, double *path, const double *trig, double *cache)
{
    double K[3], qd_pk[3], qdd_pk[3];
    const int status = vk_prepare(p, s, m, in, K, trig, cache, qd_pk, qdd_pk);
    if (status < 0) {
        vk_reject(m, out, path);
        for (int j = 0; j < 4; j++) retimed[j] = NAN;
        return;
    }
    int found = 0;
    double T = p[P_TIME + 1];
    if (status == 0) T = vk_retime_T(p, cache, m, qd_pk, qdd_pk, &found, 1, NULL, NULL);
    vk_retime_finish(p, s, m, in, K, T, found, out, retimed, path);
}

/* ---------------------------------------------------------------------------------------------
 * Volume-filling path scale (plan): keep the direction of the input's bulge, scale it.
 *
 * The family theta(s) = theta1 + D q(s) + c K p(s) (K = -a6 T^6 of the input row; q, p of Yao
 * eq 10 as corrected in DESIGN.md). Joint angles, theta_p and V_p depend on the path only, so
 * the search over c needs forward kinematics on the s grid and no dynamics:
 *   - joint limits: each sample's angle is linear in c, so they hold on one interval of c,
 *     found in closed form; the scan range is cut to it;
 *   - theta_p of a dig that starts on the surface: the direction J(q0) a3, a3 ~ 10 D + c K, is
 *     linear in c (one atan2 per probe); otherwise the entry segment of the probe's path;
 *   - V_p: the polyline area of the probe's path (as vk_evaluate computes it).
 * A scan of VK_PL_SCAN points uniform in c finds the feasible point of largest V; where its
 * larger-V neighbour fails (on volume_max mostly: V grows with c and the objective rewards V up
 * to the cap), Illinois on the constraint that fails there stops once the feasible end is
 * within VK_PL_TOL of it (V within 1e-4 of the V range below V_max). That path c* is retimed
 * (vk_retime).
 *
 * A larger bulge also needs more torque (soil and gravity, which no retiming reduces), so the
 * retime at c* can fail where a smaller c would not. Back-off (vk_plan_backoff): the largest
 * c towards a path-feasible scan point of smaller V whose retiming search finds a feasible T
 * (probes: vk_prepare + vk_retime_T, no evaluation), found by a root search on the closed-form
 * bounds of that search (their window in 1/T^2 closes about linearly in c), first predicted
 * from a few samples' dynamics (one probe on most rows), to within VK_PL_BACKOFF_TOL in c (where
 * a torque bound pushes T up steeply near there, the scale where that starts competes); the
 * answer's probe is evaluated (its search's T reused). If nothing passes, the input's
 * own path (c = 1) is reported: retimed, or evaluated as it is where a path-only limit fails
 * (no retiming can fix that: 7 us instead of 14).
 *
 * Cost: trig dominates. The absolute angles are phi = A + c B (B = cumulative K times p(s)),
 * so the scan takes sin and cos once at its first point and advances them by rotation, one
 * complex product per angle and point; later probes rotate the best scan point's trig by
 * (x - c) B, with vk_sincos_small (no reduction, no branch) when that angle stays within pi/4.
 * The trig of the chosen path goes on to vk_prepare.
 * ------------------------------------------------------------------------------------------- */

/* Scan points (the range ends included): 9 on [0.5, 2] are steps of 0.17 and 0.2 in c either
 * side of 1. A feasible window narrower than a step can be missed: 13 points found 1.5 % more
 * feasible rows on a validation set for 1.6 us more per row. */
#define VK_PL_SCAN 9
/* Refinement stops when the feasible end's binding path constraint is within this of 0. */
#define VK_PL_TOL 1e-4
/* Path constraints are judged with this margin (normalised units): the probes' arithmetic
 * (angles as theta1 + D q + c K p, rotated trig) rounds differently from vk_evaluate's by
 * ~1e-15, so the real evaluation at c* holds them. */
#define VK_PL_MARGIN 1e-9
#define VK_PL_ITER 40
/* Back-off: at most VK_PL_BACKOFF probes between the bracket's ends (a root search on the
 * retiming bounds' window, vk_plan_backoff), stopping once the bracket is VK_PL_BACKOFF_TOL
 * wide in c (the objective changes ~0.3 per unit of c there: 3e-4 at the tolerance). */
#define VK_PL_BACKOFF 4
#define VK_PL_BACKOFF_TOL 1e-3
/* ... and no closing-in probe once the back-off has made this many (shots, starts included):
 * bounds its worst case (the old bisection's was 8 probes and a retime). */
#define VK_PL_PROBES 5
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

/* The path-only search of one row. */
typedef struct {
    const double *p, *in, *A, *B;
    double *buf[3], *R, *X; /* X: the angles vk_sincos_n takes (3 m) */
    int m, n3;
    double H, width, l0, l1, l2;
    double tp_lo, tp_hi, tp_span;
    double v_min, v_max, v_span;
    int at_start;
    double dx0, dy0, dx1, dy1; /* entry direction (dx0 + c dx1, dy0 + c dy1) when at_start */
    double b_max;              /* max |B| */
    /* The scan: points, g, V and the four path values (theta_p_min/max, volume_min/max). */
    int n, best, ik; /* ik: the buffer holding the best scan point's trig */
    double cc[VK_PL_SCAN], cg[VK_PL_SCAN], cv[VK_PL_SCAN], cw[VK_PL_SCAN][4];
} vk_pathscan;

/* Point a scan at an m-sample grid's scratch buffers in sc. */
static inline void vk_pathscan_grid(vk_pathscan *r, double *sc, int m) {
    r->m = m;
    r->n3 = 3 * m;
    r->A = sc + S_A * m;
    r->B = sc + S_B * m;
    r->buf[0] = sc + S_T0 * m;
    r->buf[1] = sc + S_T1 * m;
    r->buf[2] = sc + S_T2 * m;
    r->R = sc + S_R * m;
    r->X = sc + S_X * m;
}

/* g(c): the worst of theta_p_min/max and volume_min/max (normalised as in vk_evaluate) plus
 * VK_PL_MARGIN; +inf where a value is not finite. *volume gets V_p and v those four values.
 * The joint limits hold by the scan range. trig: cos then sin of the three absolute angles, m
 * each. */
static double vk_path_g(const vk_pathscan *r, double c, const double *trig, double *volume,
                        double v[4])
{
    const int m = r->m;
    const double *c0 = trig, *c1 = trig + m, *c2 = trig + 2 * m;
    const double *s0 = trig + 3 * m, *s1 = trig + 4 * m, *s2 = trig + 5 * m;
    const double H = r->H, l0 = r->l0, l1 = r->l1, l2 = r->l2;
    vk_polyline pl = {0.0, 0.0, 0.0, 0.0, 0.0, -1};
    double bx[VK_BLOCK], by[VK_BLOCK];
    for (int base = 0; base < m; base += VK_BLOCK) {
        const int nb = m - base < VK_BLOCK ? m - base : VK_BLOCK;
        for (int k = 0; k < nb; k++) { /* vectorises */
            const int i = base + k;
            bx[k] = (c0[i] * l0 + c1[i] * l1) + c2[i] * l2;
            by[k] = (s0[i] * l0 + s1[i] * l1) + s2[i] * l2;
        }
        for (int k = 0; k < nb; k++) vk_polyline_add(&pl, base + k, bx[k], by[k], H);
    }
    const double V = fabs(pl.area) * r->width;
    double theta_p;
    if (r->at_start)
        theta_p = atan2(-(r->dy0 + c * r->dy1), fabs(r->dx0 + c * r->dx1));
    else if (pl.first_below < 0)
        theta_p = -1.57079632679489661923;
    else
        theta_p = atan2(-pl.entry_dy, fabs(pl.entry_dx));
    *volume = V;
    v[0] = (r->tp_lo - theta_p) / r->tp_span;
    v[1] = (theta_p - r->tp_hi) / r->tp_span;
    v[2] = (r->v_min - V) / r->v_span;
    v[3] = (V - r->v_max) / r->v_span;
    if (!isfinite(V) || !isfinite(theta_p)) return INFINITY;
    return vk_max(vk_max(v[0], v[1]), vk_max(v[2], v[3])) + VK_PL_MARGIN;
}

/* Index of the largest of four values (the first on ties; NaN never wins). */
static int vk_argmax4(const double v[4])
{
    int k = 0;
    for (int j = 1; j < 4; j++)
        if (v[j] > v[k]) k = j;
    return k;
}

/* dst = the trig at c of the path: the best scan point's rotated by (c - its c) B. */
static void vk_path_trig(const vk_pathscan *r, double c, double *restrict dst)
{
    const int n3 = r->n3;
    const double d = c - r->cc[r->best];
    const double *restrict B = r->B;
    double *restrict rc = r->R, *restrict rs = r->R + n3;
    if (fabs(d) * r->b_max <= 0.78539816339744830962) {
        for (int t = 0; t < n3; t++) vk_sincos_small(d * B[t], &rs[t], &rc[t]);
    } else {
        for (int t = 0; t < n3; t++) r->X[t] = d * B[t];
        vk_sincos_n(r->X, rs, rc, n3);
    }
    const double *restrict src = r->buf[r->ik];
    const double *restrict c0 = src, *restrict s0 = src + n3;
    double *restrict c1 = dst, *restrict s1 = dst + n3;
    for (int t = 0; t < n3; t++) {
        c1[t] = c0[t] * rc[t] - s0[t] * rs[t];
        s1[t] = s0[t] * rc[t] + c0[t] * rs[t];
    }
}

/*
 * Illinois from scan point k_ok (passes vk_path_g) towards k_fail (fails) on the constraint
 * that fails at k_fail (g, a max of several, would converge slowly), switching to another one
 * if that fails first on the way; stops once the passing end is within VK_PL_TOL of it.
 * Returns the last passing probe's c (NAN if none passed or nothing was probed), its V_p in
 * *v_out and its trig in r->buf[*keep]; *probe, *keep: two buffers other than r->ik.
 */
static double vk_path_refine(vk_pathscan *r, int k_ok, int k_fail, int *probe, int *keep,
                             double *v_out)
{
    if (!isfinite(r->cg[k_fail])) return NAN;
    int j = vk_argmax4(r->cw[k_fail]);
    double a = r->cc[k_ok], b = r->cc[k_fail], wa[4];
    for (int k = 0; k < 4; k++) wa[k] = r->cw[k_ok][k];
    double fa = wa[j] + VK_PL_MARGIN, fb = r->cw[k_fail][j] + VK_PL_MARGIN;
    double c_pass = NAN;
    int side = 0;
    for (int it = 0; it < VK_PL_ITER && wa[j] + VK_PL_MARGIN < -VK_PL_TOL &&
                     fabs(b - a) > 1e-12 * fabs(b);
         it++) {
        double x = (a * fb - b * fa) / (fb - fa);
        if (!(x > vk_min(a, b) && x < vk_max(a, b))) x = 0.5 * (a + b);
        vk_path_trig(r, x, r->buf[*probe]);
        double vx, wx[4];
        const double gx = vk_path_g(r, x, r->buf[*probe], &vx, wx);
        if (gx <= 0.0) {
            a = x;
            for (int k = 0; k < 4; k++) wa[k] = wx[k];
            fa = wa[j] + VK_PL_MARGIN;
            c_pass = x;
            *v_out = vx;
            const int t = *probe;
            *probe = *keep;
            *keep = t;
            if (side == -1) fb *= 0.5;
            side = -1;
        } else {
            b = x;
            if (isfinite(gx) && !(wx[j] + VK_PL_MARGIN > 0.0)) {
                j = vk_argmax4(wx); /* another constraint fails first */
                fa = wa[j] + VK_PL_MARGIN;
                side = 0;
            } else if (side == 1) {
                fa *= 0.5;
            } else {
                side = 1;
            }
            fb = isfinite(gx) ? wx[j] + VK_PL_MARGIN : INFINITY;
        }
    }
    return c_pass;
}

static void vk_path_grid(vk_pathscan *r, const double *basis, const double *K);

/* Set up the row (r->p, in, m, A, B, buf, R given). Returns 0 when no c in [lo, hi] keeps
 * every joint in range, with *lo, *hi cut to the joint-limit interval otherwise. */
static int vk_path_setup(vk_pathscan *r, const double *basis, const double *K, double *lo,
                         double *hi)
{
    const double *p = r->p, *in = r->in;
    const int m = r->m;
    const double *Qb = basis, *Pinv = basis + 2 * m;
    double D[3];
    for (int j = 0; j < 3; j++) D[j] = in[I_Q_END + j] - in[I_Q_START + j];
    /* Joint limits: q_lo <= a + c K p <= q_hi at every sample with p > 0 (with the margin) is
     * an interval of c K; the ends (p = 0) are the same for every c. */
    for (int j = 0; j < 3; j++) {
        if (K[j] == 0.0) continue;
        const double marg = VK_PL_MARGIN * p[P_Q_SPAN + j];
        const double q_lo = p[P_Q_MIN + j] + marg, q_hi = p[P_Q_MAX + j] - marg;
        const double qs = in[I_Q_START + j], dj = D[j];
        double t_lo = -INFINITY, t_hi = INFINITY;
        for (int i = 1; i < m - 1; i++) { /* p = 0 at both ends */
            const double a = qs + dj * Qb[i];
            t_lo = vk_max(t_lo, (q_lo - a) * Pinv[i]);
            t_hi = vk_min(t_hi, (q_hi - a) * Pinv[i]);
        }
        if (K[j] > 0.0) {
            *lo = vk_max(*lo, t_lo / K[j]);
            *hi = vk_min(*hi, t_hi / K[j]);
        } else {
            *lo = vk_max(*lo, t_hi / K[j]);
            *hi = vk_min(*hi, t_lo / K[j]);
        }
    }
    if (!(*lo <= *hi)) return 0;
    vk_path_grid(r, basis, K);
    return 1;
}

/* The row's absolute angles phi_j = A_j + c B_j on r's grid (basis: its q(s), p(s)) and the
 * scalars of the search (r->p, in, m, A, B given). */
static void vk_path_grid(vk_pathscan *r, const double *basis, const double *K)
{
    const double *p = r->p, *in = r->in;
    const int m = r->m;
    const double *Qb = basis, *Pb = basis + m;
    double D[3];
    for (int j = 0; j < 3; j++) D[j] = in[I_Q_END + j] - in[I_Q_START + j];
    /* Absolute angles phi_j = A_j + c B_j (cumulative sums, as vk_evaluate's phi). */
    double *A = (double *)r->A, *B = (double *)r->B;
    double b_max = 0.0;
    for (int i = 0; i < m; i++) {
        double a = 0.0, b = 0.0;
        for (int j = 0; j < 3; j++) {
            a += in[I_Q_START + j] + D[j] * Qb[i];
            b += K[j] * Pb[i];
            A[j * m + i] = a;
            B[j * m + i] = b;
            b_max = vk_max(b_max, fabs(b));
        }
    }
    r->b_max = b_max;
    r->H = in[I_SURFACE];
    r->width = p[P_WIDTH];
    r->l0 = p[P_LEN];
    r->l1 = p[P_LEN + 1];
    r->l2 = p[P_LEN + 2];
    const double *tp = in[I_DIG_TYPE] == 0.0 ? p + P_TP_DOWN : p + P_TP_BACK;
    r->tp_lo = tp[0];
    r->tp_hi = tp[1];
    r->tp_span = tp[1] - tp[0];
    r->v_min = p[P_VOL];
    r->v_max = p[P_VOL + 1];
    r->v_span = r->v_max - r->v_min;
    /* The start: sample 0 is q0 exactly (p(0) = 0), with libm's trig as vk_evaluate takes it,
     * so at_start is vk_evaluate's. */
    double sp[3], cp[3];
    for (int j = 0; j < 3; j++) {
        sp[j] = sin(A[j * m]);
        cp[j] = cos(A[j * m]);
    }
    const double y0 = (sp[0] * r->l0 + sp[1] * r->l1) + sp[2] * r->l2;
    r->at_start = y0 <= r->H + 1e-3;
    /* J(q0) (10 D + c K): vk_evaluate's entry direction J(q0) a3 times T^3 > 0. */
    const double v0 = -sp[0] * r->l0, v1 = -sp[1] * r->l1, v2 = -sp[2] * r->l2;
    const double u0 = cp[0] * r->l0, u1 = cp[1] * r->l1, u2 = cp[2] * r->l2;
    const double sx[3] = {(v2 + v1) + v0, v2 + v1, v2};
    const double sy[3] = {(u2 + u1) + u0, u2 + u1, u2};
    r->dx0 = (sx[0] * (10.0 * D[0]) + sx[1] * (10.0 * D[1])) + sx[2] * (10.0 * D[2]);
    r->dy0 = (sy[0] * (10.0 * D[0]) + sy[1] * (10.0 * D[1])) + sy[2] * (10.0 * D[2]);
    r->dx1 = (sx[0] * K[0] + sx[1] * K[1]) + sx[2] * K[2];
    r->dy1 = (sy[0] * K[0] + sy[1] * K[1]) + sy[2] * K[2];
}

/*
 * The scale c* in [c_lo, c_hi] of the largest V_p whose path-only constraints hold (joint
 * limits, theta_p, volume), or NAN when the scan finds none or the row has no bulge.
 *   K:     the row's shape term; r: set up by the caller (pointers and m), filled here
 *   trig:  out, the trig of the path at c* (in r->buf), as vk_prepare takes it
 *   v_out: out, V_p at c*
 */
static double vk_plan_search(vk_pathscan *r, double lo, double hi, const double **trig,
                             double *v_out);

static double vk_plan_scale(vk_pathscan *r, const double *basis, const double *K, double c_lo,
                            double c_hi, const double **trig, double *v_out)
{
    *trig = NULL;
    r->best = -1;
    if (K[0] == 0.0 && K[1] == 0.0 && K[2] == 0.0) return NAN; /* no direction to scale */
    double lo = c_lo, hi = c_hi;
    if (!vk_path_setup(r, basis, K, &lo, &hi)) return NAN;
    return vk_plan_search(r, lo, hi, trig, v_out);
}

/* The scan of vk_plan_scale on r's grid over [lo, hi] (the joint-limit interval): r->n, cc,
 * cg, cv, cw, best and ik; the index of the best scan point, -1 if none passes. */
static int vk_plan_scan(vk_pathscan *r, double lo, double hi)
{
    const int n3 = r->n3;
    const double *A = r->A, *B = r->B;

    /* Scan: VK_PL_SCAN points from lo to hi, with c = 1 (the input's own path, often
     * feasible: it anchors a feasible window narrower than a step) among them when in range:
     * uniform steps on [lo, 1] and on [1, hi]. Trig at lo, advanced by the rotation h B per
     * point into whichever buffer holds neither the current point nor the best so far. */
    const int steps = VK_PL_SCAN - 1;
    const int n = hi > lo ? VK_PL_SCAN : 1;
    int n1 = steps; /* steps up to the first segment's end */
    if (n > 1 && lo < 1.0 && 1.0 < hi) {
        n1 = (int)floor((double)steps * (1.0 - lo) / (hi - lo) + 0.5);
        n1 = n1 < 1 ? 1 : n1 > steps - 1 ? steps - 1 : n1;
    }
    const double mid = n1 < steps ? 1.0 : hi;
    double *R = r->R, *rc = R, *rs = R + n3;
    double *first = r->buf[0];
    for (int t = 0; t < n3; t++) r->X[t] = A[t] + lo * B[t];
    vk_sincos_n(r->X, first + n3, first, n3);
    r->n = n;
    int best = -1, ic = 0, ik = -1;
    double h = 0.0, c_seg = lo;
    int k_seg = 0;
    for (int k = 0; k < n; k++) {
        if (k == 0 || k == n1 + 1) { /* a segment starts: its rotation */
            c_seg = k == 0 ? lo : mid;
            k_seg = k == 0 ? 0 : n1;
            h = k == 0 ? (mid - lo) / (double)n1 : (hi - mid) / (double)(steps - n1);
            if (n > 1 && h * r->b_max <= 0.78539816339744830962)
                for (int t = 0; t < n3; t++) vk_sincos_small(h * B[t], &rs[t], &rc[t]);
            else if (n > 1) {
                for (int t = 0; t < n3; t++) r->X[t] = h * B[t];
                vk_sincos_n(r->X, rs, rc, n3);
            }
        }
        if (k > 0) {
            int next = 0;
            while (next == ic || next == ik) next++;
            const double *restrict c0 = r->buf[ic], *restrict s0 = r->buf[ic] + n3;
            double *restrict c1 = r->buf[next], *restrict s1 = r->buf[next] + n3;
            for (int t = 0; t < n3; t++) {
                c1[t] = c0[t] * rc[t] - s0[t] * rs[t];
                s1[t] = s0[t] * rc[t] + c0[t] * rs[t];
            }
            ic = next;
        }
        r->cc[k] = k == n - 1 ? hi : k == n1 ? mid : c_seg + (double)(k - k_seg) * h;
        r->cg[k] = vk_path_g(r, r->cc[k], r->buf[ic], &r->cv[k], r->cw[k]);
        if (r->cg[k] <= 0.0 && (best < 0 || r->cv[k] > r->cv[best])) {
            best = k;
            ik = ic;
        }
    }
    r->best = best;
    r->ik = ik;
    return best;
}

/* vk_plan_scale after the setup: the scan, then the refinement towards the neighbour of
 * larger V. */
static double vk_plan_search(vk_pathscan *r, double lo, double hi, const double **trig,
                             double *v_out)
{
    const int best = vk_plan_scan(r, lo, hi), n = r->n, ik = r->ik;
    if (best < 0) return NAN;
    *trig = r->buf[ik];
    *v_out = r->cv[best];

    /* Refine towards the neighbour of larger V (it fails, since best is the largest). */
    const double *cv = r->cv;
    int nb = -1;
    if (best > 0 && cv[best - 1] > cv[best]) nb = best - 1;
    if (best < n - 1 && cv[best + 1] > cv[best] && (nb < 0 || cv[best + 1] > cv[nb]))
        nb = best + 1;
    if (nb < 0) return r->cc[best];
    int pb = ik == 0 ? 1 : 0, pk = 3 - ik - pb;
    double v_ref;
    const double c_ref = vk_path_refine(r, best, nb, &pb, &pk, &v_ref);
    if (!isnan(c_ref) && v_ref > cv[best]) {
        *trig = r->buf[pk];
        *v_out = v_ref;
        return c_ref;
    }
    return r->cc[best];
}

/*
 * vk_plan_scale with the scan on a coarse grid (rc: every VK_PL_STRIDE-th sample of rf's): the
 * joint-limit interval comes from the full grid; the best coarse scan point and its neighbour
 * of larger V are then judged on the full grid, and the refinement runs there as in
 * vk_plan_scale, so c* is the full grid's (the coarse grid only picks the bracket). Where the
 * full grid disagrees with the coarse one about the bracket (the best point fails, or the
 * neighbour passes) or the coarse scan finds nothing, the full scan decides (vk_plan_search).
 *   *scanned: out, 1 when rf holds the full scan (what vk_plan_backoff needs), else 0
 *   *lo, *hi: out, the joint-limit interval
 */
static double vk_plan_scale_coarse(vk_pathscan *rf, vk_pathscan *rc, const double *basis,
                                   const double *basis_c, const double *K, double c_lo,
                                   double c_hi, const double **trig, double *v_out, int *scanned,
                                   double *lo, double *hi)
{
    *trig = NULL;
    *scanned = 1;
    rf->best = -1;
    rf->n = 0;
    *lo = c_lo;
    *hi = c_hi;
    if (K[0] == 0.0 && K[1] == 0.0 && K[2] == 0.0) return NAN; /* no direction to scale */
    if (!vk_path_setup(rf, basis, K, lo, hi)) return NAN;
    vk_path_grid(rc, basis_c, K);
    const int best = vk_plan_scan(rc, *lo, *hi);
    if (best < 0) return vk_plan_search(rf, *lo, *hi, trig, v_out);
    /* The best coarse point on the full grid (trig from scratch, the rotation base). */
    const int n3 = rf->n3;
    double *b0 = rf->buf[0];
    const double c0 = rc->cc[best];
    for (int t = 0; t < n3; t++) rf->X[t] = rf->A[t] + c0 * rf->B[t];
    vk_sincos_n(rf->X, b0 + n3, b0, n3);
    rf->n = 1;
    rf->best = 0;
    rf->ik = 0;
    rf->cc[0] = c0;
    rf->cg[0] = vk_path_g(rf, c0, b0, &rf->cv[0], rf->cw[0]);
    if (!(rf->cg[0] <= 0.0)) return vk_plan_search(rf, *lo, *hi, trig, v_out);
    *scanned = 0;
    *trig = b0;
    *v_out = rf->cv[0];
    const double *cv = rc->cv;
    int nb = -1;
    if (best > 0 && cv[best - 1] > cv[best]) nb = best - 1;
    if (best < rc->n - 1 && cv[best + 1] > cv[best] && (nb < 0 || cv[best + 1] > cv[nb]))
        nb = best + 1;
    if (nb < 0) return c0;
    rf->n = 2;
    rf->cc[1] = rc->cc[nb];
    vk_path_trig(rf, rf->cc[1], rf->buf[1]);
    rf->cg[1] = vk_path_g(rf, rf->cc[1], rf->buf[1], &rf->cv[1], rf->cw[1]);
    if (rf->cg[1] <= 0.0) { /* passes on the full grid: the bracket is elsewhere */
        *scanned = 1;
        return vk_plan_search(rf, *lo, *hi, trig, v_out);
    }
    int pb = 1, pk = 2;
    double v_ref;
    const double c_ref = vk_path_refine(rf, 0, 1, &pb, &pk, &v_ref);
    if (!isnan(c_ref) && v_ref > rf->cv[0]) {
        *trig = rf->buf[pk];
        *v_out = v_ref;
        return c_ref;
    }
    return c0;
}

/* A back-off probe: the row's path scaled by c, whose trig is given, prepared and searched for
 * a time (vk_prepare + vk_retime_T without its least-violation search; no evaluation). Returns
 * 1 when the search finds a feasible T: then *T is it and K the path's shape term, exactly what
 * vk_retime computes for that row before vk_retime_finish. *window, bind: vk_bounds' window
 * (NAN when the row cannot be prepared) and binding samples. */
static int vk_backoff_probe(const double *p, const double *s, int m, const double *in, double c,
                            const double *trig, double *cache, double *K, double *T,
                            double *window, int *bind)
{
    double row[VK_N_IN], qd_pk[3], qdd_pk[3];
    for (int j = 0; j < VK_N_IN; j++) row[j] = in[j];
    for (int j = 0; j < 3; j++) row[I_A6 + j] = c * in[I_A6 + j];
    *window = NAN;
    bind[0] = bind[1] = -1;
    if (vk_prepare(p, s, m, row, K, trig, cache, qd_pk, qdd_pk) != 0) return 0;
    int found = 0;
    *T = vk_retime_T(p, cache, m, qd_pk, qdd_pk, &found, 0, window, bind);
    return found;
}

/* A passing back-off probe: its scale, retimed T, shape term, window, V_p, the part of the
 * objective (Yao eq 11) that T and V_p make (vk_probe_j) and the samples that bind its window. */
typedef struct {
    double c, T, K[3], w, v, j;
    int bind[2];
} vk_probe;

/* How vk_backoff_try gets the probe's trig: computed and judged by vk_path_g, computed only
 * (a path-feasible scan point), or already in r->buf[*pb]. */
enum { VK_TRY_CHECK = 0, VK_TRY_TRIG = 1, VK_TRY_READY = 2 };

/* lambda1 T_norm - lambda3 V_norm (eq 11 without its energy term and constants). */
static double vk_probe_j(const double *p, double T, double v)
{
    return p[P_WEIGHTS] * (T - p[P_TIME]) / (p[P_TIME + 1] - p[P_TIME]) -
           p[P_WEIGHTS + 2] * v / (p[P_VOL + 1] - p[P_VOL]);
}

/* One back-off probe at c (V_p v unless how is VK_TRY_CHECK, which computes it; *probes counts
 * them): 1 when the path passes vk_path_g (unless known) and the retiming search finds a time;
 * then *best is it,
 * *least too if its vk_probe_j is less, and its trig moves to r->buf[*pk] (pb and pk swap).
 * *w, bind: its window (NAN where the path fails or the row cannot be prepared) and binding
 * samples (vk_bounds). */
static int vk_backoff_try(vk_pathscan *r, const double *s, double *cache, int *probes, double c,
                          int how, double v, int *pb, int *pk, vk_probe *best, vk_probe *least,
                          double *w, int *bind)
{
    *w = NAN;
    bind[0] = bind[1] = -1;
    (*probes)++;
    if (how != VK_TRY_READY) vk_path_trig(r, c, r->buf[*pb]);
    if (how == VK_TRY_CHECK) {
        double wv[4];
        if (!(vk_path_g(r, c, r->buf[*pb], &v, wv) <= 0.0)) return 0;
    }
    vk_probe x;
    x.c = c;
    const int found = vk_backoff_probe(r->p, s, r->m, r->in, c, r->buf[*pb], cache, x.K, &x.T,
                                       &x.w, bind);
    *w = x.w;
    if (found) {
        x.v = v;
        x.j = vk_probe_j(r->p, x.T, v);
        x.bind[0] = bind[0];
        x.bind[1] = bind[1];
        *best = x;
        if (!(least->j <= x.j)) *least = x;
        const int t = *pb;
        *pb = *pk;
        *pk = t;
    }
    return found;
}

/* Whether a window value can steer the root search: finite and of the given sign. */
static inline int vk_win_pos(double w) { return isfinite(w) && w > 0.0; }
static inline int vk_win_neg(double w) { return isfinite(w) && w < 0.0; }

/* Shots of the back-off (vk_plan_backoff, step 1), and the least distance of a shot from the
 * failed end, as a fraction of the bracket. */
#define VK_PL_SHOTS 2
#define VK_PL_SHOT_NEAR 0.05
/* A back-off answer's retimed T this far (relative) above its velocity and acceleration bound
 * was raised by a torque bound (vk_plan_backoff). */
#define VK_PL_RAISED 1e-3
/* vk_local_fails' margin for rounding (1/s^2; u = 1/T^2 is ~0.01 to 0.04 here). */
#define VK_LOCAL_SAFE 1e-12
/* Steps of vk_local_bounds' climb from the last binding sample to the one that binds now. */
#define VK_LOCAL_CLIMB 24

/* vk_bounds' torque bounds of u = 1/T^2 at one sample of the row's path scaled by c (dynamics
 * as vk_prepare computes them, at unit time): *l the largest lower bound over the joints, *h
 * the least upper one (-inf and +inf for a sample in the soil slower than the regularisation
 * at t_max, whose torque the retiming searches). */
static void vk_local_sample(const vk_pathscan *r, const double *basis, const double *D,
                            const double *Kc, double c, int i, double *l, double *h)
{
    const double *p = r->p;
    const int m = r->m;
    const double *Q1 = basis + 3 * m, *Q2 = basis + 4 * m, *P1 = basis + 5 * m,
                 *P2 = basis + 6 * m;
    const double lim = 1.0 - VK_RT_MARGIN;
    const double H = r->H;
    double qd[3], qdd[3], cp[3], sp[3];
    for (int j = 0; j < 3; j++) {
        qd[j] = D[j] * Q1[i] + Kc[j] * P1[i];
        qdd[j] = D[j] * Q2[i] + Kc[j] * P2[i];
        vk_sincos(r->A[j * m + i] + c * r->B[j * m + i], &sp[j], &cp[j]);
    }
    double at[3], gt[3], ft[3], depth;
    const double speed = vk_unit_dynamics(vk_dyn_of(p), H, cp, sp, qd, qdd, at, gt, ft, &depth);
    const double a0 = at[0], a1 = at[1], a2 = at[2];
    const double g0 = gt[0], g1 = gt[1], g2 = gt[2];
    const double f0 = ft[0], f1 = ft[1], f2 = ft[2];
    *l = -INFINITY;
    *h = INFINITY;
    if (depth > 0.0 && speed > 0.0 && speed < p[P_SPEED_REG] * p[P_TIME + 1]) return;
    const double At[3] = {a0 + (a1 + a2), a1 + a2, a2};
    const double Gt[3] = {g0 + (g1 + g2), g1 + g2, g2};
    const double Ft[3] = {f0 + (f1 + f2), f1 + f2, f2};
    for (int j = 0; j < 3; j++) {
        const double tm = p[P_TAU_MAX + j] * lim, b = Gt[j] + Ft[j];
        double lj, hj;
        if (vk_u_interval(At[j], b, tm, &lj, &hj)) {
            *l = vk_max(*l, lj);
            *h = vk_min(*h, hj);
        } else if (fabs(b) > tm) {
            *h = -1.0;
        }
    }
}

/*
 * vk_bounds' quantities of the row's path scaled by c, its torque ends from two samples only:
 * from bind[0] (bind[1]), the climb over neighbouring samples to the local maximum of the
 * lower (minimum of the upper) bound of u = 1/T^2, which moves a few samples as c changes;
 * bind gets them. *u_lo, *u_hi: those bounds (-inf, +inf without a sample); *t_va: the bound
 * of T from velocity, acceleration and t_min, from every sample (they are linear in c). Never
 * tighter than vk_bounds' own, equal where the climbs end on the samples that bind it. ~1 us
 * at 101 samples (no trig arrays, no cache): the back-off predicts with it.
 *   basis: the kernel's (q, p, 1/p, q', q'', p', p'' on the grid); K: the row's shape term
 */
static double vk_local_t_va(const vk_pathscan *r, const double *basis, const double *D,
                            const double *Kc)
{
    const int m = r->m;
    const double *Q1 = basis + 3 * m, *Q2 = basis + 4 * m, *P1 = basis + 5 * m,
                 *P2 = basis + 6 * m;
    /* Six independent running maxima in one pass (one chain each would wait on the last). */
    double v0 = 0.0, v1 = 0.0, v2 = 0.0, a0 = 0.0, a1 = 0.0, a2 = 0.0;
    for (int i = 0; i < m; i++) {
        v0 = vk_max(v0, fabs(D[0] * Q1[i] + Kc[0] * P1[i]));
        v1 = vk_max(v1, fabs(D[1] * Q1[i] + Kc[1] * P1[i]));
        v2 = vk_max(v2, fabs(D[2] * Q1[i] + Kc[2] * P1[i]));
        a0 = vk_max(a0, fabs(D[0] * Q2[i] + Kc[0] * P2[i]));
        a1 = vk_max(a1, fabs(D[1] * Q2[i] + Kc[1] * P2[i]));
        a2 = vk_max(a2, fabs(D[2] * Q2[i] + Kc[2] * P2[i]));
    }
    const double qd_pk[3] = {v0, v1, v2}, qdd_pk[3] = {a0, a1, a2};
    return vk_t_va(r->p, qd_pk, qdd_pk);
}

/* D (q_end - q_start) and Kc (c K) of the row's path scaled by c. */
static void vk_local_path(const vk_pathscan *r, const double *K, double c, double *D, double *Kc)
{
    for (int j = 0; j < 3; j++) {
        D[j] = r->in[I_Q_END + j] - r->in[I_Q_START + j];
        Kc[j] = c * K[j];
    }
}

static void vk_local_bounds(const vk_pathscan *r, const double *basis, const double *K,
                            double c, int *bind, double *u_lo, double *u_hi, double *t_va)
{
    const int m = r->m;
    double D[3], Kc[3];
    vk_local_path(r, K, c, D, Kc);
    *t_va = vk_local_t_va(r, basis, D, Kc);
    double ends[2] = {-INFINITY, INFINITY}; /* u_lo, u_hi */
    for (int e = 0; e < 2; e++) {
        int i = bind[e];
        if (i < 0 || i >= m) continue;
        double l, h;
        vk_local_sample(r, basis, D, Kc, c, i, &l, &h);
        double v = e == 0 ? l : -h; /* climb to the largest v */
        int dir = 0;
        for (int step = 0; step < VK_LOCAL_CLIMB; step++) {
            int moved = 0;
            for (int d = -1; d <= 1 && !moved; d += 2) {
                if (dir == -d || i + d < 0 || i + d >= m) continue;
                vk_local_sample(r, basis, D, Kc, c, i + d, &l, &h);
                const double vn = e == 0 ? l : -h;
                if (vn > v) {
                    v = vn;
                    i += d;
                    dir = d;
                    moved = 1;
                }
            }
            if (!moved) break;
        }
        bind[e] = i;
        ends[e] = e == 0 ? v : -v;
    }
    *u_lo = ends[0];
    *u_hi = ends[1];
}

/* What the back-off's predictions root-find, from vk_local_bounds: VK_LOCAL_WINDOW, vk_bounds'
 * window (< 0: no T meets the closed-form bounds); VK_LOCAL_KINK, u_hi - 1/t_va^2 (< 0: the
 * torque bound pushes T above the velocity and acceleration bound, and it rises steeply). */
enum { VK_LOCAL_WINDOW = 0, VK_LOCAL_KINK = 1 };

static double vk_local_value(const vk_pathscan *r, const double *basis, const double *K,
                             double c, int *bind, int what)
{
    double u_lo, u_hi, t_va;
    vk_local_bounds(r, basis, K, c, bind, &u_lo, &u_hi, &t_va);
    const double u_va = 1.0 / (t_va * t_va);
    return what == VK_LOCAL_KINK ? u_hi - u_va : vk_min(u_hi, u_va) - u_lo;
}

/*
 * The back-off's prediction: Illinois on vk_local_value (what: VK_LOCAL_WINDOW or
 * VK_LOCAL_KINK) over [c_ok, c_fail] (> 0 at c_ok, < 0 at c_fail) until the bracket or the
 * step is 2e-4 in c (at most 8 steps);
 * the scale where it crosses zero (NAN if it does not change sign), and *slope its slope there.
 * bind: the binding samples at c_fail, updated as the climbs move them.
 */
static double vk_backoff_predict(const vk_pathscan *r, const double *basis, const double *K,
                                 double c_ok, double c_fail, int *bind, double *slope, int what)
{
    double a = c_ok, b = c_fail;
    double fb = vk_local_value(r, basis, K, b, bind, what);
    int bind_ok[2] = {bind[0], bind[1]};
    double fa = vk_local_value(r, basis, K, a, bind_ok, what);
    if (!(vk_win_pos(fa) && vk_win_neg(fb))) return NAN;
    double wa = fa, wb = fb, x_prev = NAN;
    int side = 0;
    for (int it = 0; it < 8 && fabs(b - a) > 2e-4; it++) {
        double x = (a * fb - b * fa) / (fb - fa);
        if (!(x > vk_min(a, b) && x < vk_max(a, b))) x = 0.5 * (a + b);
        if (fabs(x - x_prev) < 2e-4) break; /* the steps settled */
        x_prev = x;
        const double fx = vk_local_value(r, basis, K, x, bind, what);
        if (!isfinite(fx)) return NAN;
        if (fx > 0.0) {
            a = x;
            wa = fa = fx;
            if (side == -1) fb *= 0.5;
            side = -1;
        } else {
            b = x;
            wb = fb = fx;
            if (side == 1) fa *= 0.5;
            side = 1;
        }
    }
    *slope = (wb - wa) / (b - a);
    return (a * wb - b * wa) / (wb - wa);
}

/* Whether vk_local_bounds' window at c (climbs from bw) is below zero by more than rounding:
 * then the full grid's is too (every sample set's window is at least the full grid's), the
 * closed-form bounds leave no T and the retiming search cannot find one, so the probe is not
 * needed. *w: that window. */
static int vk_local_fails(const vk_pathscan *r, const double *basis, const double *K, double c,
                          const int *bw, double *w)
{
    int bl[2] = {bw[0], bw[1]};
    if (bl[0] < 0 && bl[1] < 0) return 0;
    *w = vk_local_value(r, basis, K, c, bl, VK_LOCAL_WINDOW);
    return *w < -VK_LOCAL_SAFE;
}

/*
 * The back-off's search (vk_plan_backoff): the largest-V scale found whose path passes
 * vk_path_g and whose retiming search finds a time, or NAN. Every answer is a probe whose
 * search found a time on the full grid; the window (vk_bounds': the width of the range of
 * u = 1/T^2 that the closed-form bounds leave, > 0 at every scale whose search finds a time,
 * < 0 where the bounds crossed, and close to linear in c: as the bulge grows, measured, the
 * boom's torque needs an ever shorter T against the accelerations' ever longer one) only steers.
 *
 * 1. Shots (at most VK_PL_SHOTS): where the window failed at the failed end b (c_fail at
 *    first), the samples that bind it there give vk_local_bounds, whose window's zero between b
 *    and k1 (or k2, where the local window fails at k1 too) is found by vk_backoff_predict and
 *    probed VK_PL_BACKOFF_TOL / 2 inside. If it passes within VK_PL_BACKOFF_TOL of the boundary
 *    (its window over the predicted slope), that is the answer (one probe in the common case,
 *    ~7 us); if it passes farther, it is the bracket's passing end; if it fails on the window,
 *    the next shot starts from it (the samples that bind the window far beyond the boundary are
 *    not always those that bind it there), unless it recovered less than half of the window. A zero next to b is no prediction (a sample whose
 *    dynamic torque vanishes sets a bound that diverges there).
 * 2. Otherwise start points, the first that passes brackets the boundary with the last that
 *    failed: k1, k2 (not one between a failed shot and c_fail), the path boundary beyond k2 (a
 *    smaller bulge is kinder to torque but may break volume_min or theta_p). Here and in 3, a
 *    point whose local window is negative fails without a probe (vk_local_fails).
 * 3. At most VK_PL_BACKOFF probes close in (none past VK_PL_PROBES in all): the local
 *    prediction between the ends from the samples that bind the last probe's window, aimed
 *    VK_PL_BACKOFF_TOL / 2 inside (not next to the failed end, and not again once one failed);
 *    where there is none (or an end has no window of the right sign: a path constraint or a
 *    searched limit, power or a slow sample's torque, failed), regula falsi on the window
 *    (Anderson-Bjorck) or bisection. It stops once the bracket is VK_PL_BACKOFF_TOL wide or a
 *    passing probe lies within that of the boundary (by the local slope or the ends' secant).
 * 4. c = 1 (the row's own path) if it lies between the ends and passes: never report less.
 *   k1, k2: the path-feasible scan points of smaller V than c_fail's, the largest and least V
 *   w_fail, bind: the window at c_fail and its binding samples (vk_bounds; NAN and -1 when
 *                 unknown or not what failed)
 *   best: out, the answer's probe; least: in and out, the passing probe of least vk_probe_j
 */
static double vk_backoff_search(vk_pathscan *r, const double *s, const double *basis,
                                const double *K, double *cache, double c_fail, double w_fail,
                                const int *bind, int k1, int k2, vk_probe *best,
                                vk_probe *least)
{
    const double tol = VK_PL_BACKOFF_TOL;
    /* Two buffers besides the best scan point's (the rotation base): probe and keep. */
    int pb = r->ik == 0 ? 1 : 0, pk = 3 - r->ik - pb;
    double a = NAN, b = c_fail, wa = NAN, wb = w_fail, w;
    int probes = 0;
    /* 1. The shots, from the samples that bind the window of the last failed probe. */
    int bw[2] = {bind[0], bind[1]};
    for (int shot = 0; shot < VK_PL_SHOTS && vk_win_neg(wb) && (bw[0] >= 0 || bw[1] >= 0);
         shot++) {
        double slope = NAN, c_ok = r->cc[k1];
        int bl[2] = {bw[0], bw[1]};
        double cs = vk_backoff_predict(r, basis, K, c_ok, b, bl, &slope, VK_LOCAL_WINDOW);
        if (isnan(cs) && k2 != k1) { /* k1 beyond the local boundary too */
            c_ok = r->cc[k2];
            bl[0] = bw[0];
            bl[1] = bw[1];
            cs = vk_backoff_predict(r, basis, K, c_ok, b, bl, &slope, VK_LOCAL_WINDOW);
        }
        const double c = cs + (c_ok < b ? -0.5 : 0.5) * tol;
        if (isnan(cs) || !(c > vk_min(c_ok, b) && c < vk_max(c_ok, b)) ||
            fabs(c - b) < VK_PL_SHOT_NEAR * fabs(b - c_ok))
            break;
        if (vk_backoff_try(r, s, cache, &probes, c, VK_TRY_CHECK, NAN, &pb, &pk, best, least, &w, bw)) {
            if (vk_win_pos(w) && w <= tol * fabs(slope)) return c;
            a = c;
            wa = w;
            break;
        }
        /* A shot that recovered less than half of the window: the model is poor here. */
        const int poor = !(fabs(w) < 0.5 * fabs(wb));
        if (!vk_win_neg(w)) break;
        b = c;
        wb = w;
        if (poor) break;
    }
    /* 2. Start points (not one between a failed shot and c_fail: it would fail too). */
    const double b_lo = vk_min(b, c_fail), b_hi = vk_max(b, c_fail);
    for (int u = 0; u < 2 && isnan(a); u++) {
        const int k = u == 0 ? k1 : k2;
        if ((u == 1 && k2 == k1) || (b != c_fail && b_lo <= r->cc[k] && r->cc[k] <= b_hi))
            continue;
        if (vk_local_fails(r, basis, K, r->cc[k], bw, &w)) {
            b = r->cc[k];
            wb = w;
            continue;
        }
        if (vk_backoff_try(r, s, cache, &probes, r->cc[k], VK_TRY_TRIG, r->cv[k], &pb, &pk, best, least,
                           &w, bw)) {
            a = r->cc[k];
            wa = w;
        } else {
            b = r->cc[k];
            wb = w;
        }
    }
    if (isnan(a)) {
        /* The neighbour of k2 with smaller V, if it fails the path constraints. */
        int nb = -1;
        if (k2 > 0 && !(r->cg[k2 - 1] <= 0.0) && r->cv[k2 - 1] < r->cv[k2]) nb = k2 - 1;
        if (k2 < r->n - 1 && !(r->cg[k2 + 1] <= 0.0) && r->cv[k2 + 1] < r->cv[k2] &&
            (nb < 0 || r->cv[k2 + 1] < r->cv[nb]))
            nb = k2 + 1;
        if (nb < 0) return NAN;
        double v_b;
        int q = pb; /* refine into pb and pk, then the passing probe goes to pb */
        const double c = vk_path_refine(r, k2, nb, &q, &pk, &v_b);
        if (isnan(c)) return NAN;
        pb = pk;
        pk = q;
        if (!vk_backoff_try(r, s, cache, &probes, c, VK_TRY_READY, v_b, &pb, &pk, best, least, &w, bw))
            return NAN;
        a = c;
        wa = w;
    }
    /* 3. Close in: the local prediction from the samples that bind the last probe's window
     * (vk_backoff_predict, aimed tol / 2 inside), or where there is none, regula falsi on the
     * window with the Anderson-Bjorck scaling of the end that stays (fa, fb), or bisection. */
    double fa = wa, fb = wb;
    int side = 0, predict = 1;
    for (int it = 0; it < VK_PL_BACKOFF && probes < VK_PL_PROBES && fabs(b - a) > tol; it++) {
        double c = NAN, slope = NAN;
        if (predict && vk_win_pos(wa) && vk_win_neg(wb) && (bw[0] >= 0 || bw[1] >= 0)) {
            int bl[2] = {bw[0], bw[1]};
            const double cs = vk_backoff_predict(r, basis, K, a, b, bl, &slope, VK_LOCAL_WINDOW);
            const double cp = cs + (a < b ? -0.5 : 0.5) * tol;
            if (!isnan(cs) && cp > vk_min(a, b) && cp < vk_max(a, b) &&
                fabs(cp - b) >= VK_PL_SHOT_NEAR * fabs(b - a))
                c = cp;
        }
        if (isnan(c)) {
            slope = NAN;
            c = 0.5 * (a + b);
            if (vk_win_pos(fa) && vk_win_neg(fb)) {
                const double cs = (a * fb - b * fa) / (fb - fa) + (a < b ? -0.5 : 0.5) * tol;
                if (cs > vk_min(a, b) && cs < vk_max(a, b)) c = cs;
            }
        }
        int passed = 0;
        if (!vk_local_fails(r, basis, K, c, bw, &w))
            passed = vk_backoff_try(r, s, cache, &probes, c, VK_TRY_CHECK, NAN, &pb, &pk, best, least, &w,
                                    bw);
        if (passed) {
            if (side == -1) {
                const double k = 1.0 - w / fa;
                fb *= k > 0.0 && isfinite(k) ? k : 0.5;
            }
            a = c;
            wa = fa = w;
            side = -1;
            /* The boundary within tol of a: by the local slope, or the secant of the ends. */
            if (vk_win_pos(wa) && ((isfinite(slope) && wa <= tol * fabs(slope)) ||
                                   (vk_win_neg(wb) && fabs(b - a) * wa / (wa - wb) <= tol)))
                break;
        } else {
            if (side == 1) {
                const double k = 1.0 - w / fb;
                fa *= k > 0.0 && isfinite(k) ? k : 0.5;
            }
            if (isfinite(slope)) predict = 0; /* a prediction that failed: not again */
            b = c;
            wb = fb = w;
            side = 1;
        }
    }
    /* 4. The row's own path, if it lies between the ends: never report less. */
    if (vk_min(a, b) < 1.0 && 1.0 < vk_max(a, b) &&
        vk_backoff_try(r, s, cache, &probes, 1.0, VK_TRY_CHECK, NAN, &pb, &pk, best, least, &w, bw))
        a = 1.0;
    return a;
}

/*
 * Back-off after the retime of the path at c_fail (V_p v_fail) failed: the scale of the probe
 * *best (vk_backoff_search: the largest V whose retiming search finds a time, near the
 * boundary), or NAN when nothing passes. Where the retimed T there lies above the velocity and
 * acceleration bound (by VK_PL_RAISED), a torque bound has pushed it up, and T rises steeply
 * with c near such a boundary (measured: 6.5 s to 9.8 s over the last 0.3 % of c), which eq 11
 * weighs more than the volume gained: then the kink where that started (vk_backoff_predict on
 * VK_LOCAL_KINK) is probed too, and of the passing probes the one of least vk_probe_j is the
 * answer.
 *   basis, K: the kernel's basis and the row's shape term (for vk_local_bounds)
 *   w_fail, bind: the window at c_fail and its binding samples (vk_bounds; NAN and -1 when
 *                 unknown or not what failed)
 */
static double vk_plan_backoff(vk_pathscan *r, const double *s, const double *basis,
                              const double *K, double *cache, double c_fail, double v_fail,
                              double w_fail, const int *bind, vk_probe *best)
{
    int k1 = -1, k2 = -1;
    for (int k = 0; k < r->n; k++) {
        if (!(r->cg[k] <= 0.0 && r->cv[k] < v_fail)) continue;
        if (k1 < 0 || r->cv[k] > r->cv[k1]) k1 = k;
        if (k2 < 0 || r->cv[k] < r->cv[k2]) k2 = k;
    }
    if (k1 < 0) return NAN;
    vk_probe least;
    least.j = NAN;
    const double a = vk_backoff_search(r, s, basis, K, cache, c_fail, w_fail, bind, k1, k2, best,
                                       &least);
    if (isnan(a)) return NAN;
    double D[3], Kc[3];
    vk_local_path(r, K, a, D, Kc);
    if (!(best->T > vk_local_t_va(r, basis, D, Kc) * (1.0 + VK_PL_RAISED))) return a;
    const vk_probe far = *best;
    int bl[2];
    for (int u = 0; u < 2; u++) {
        const int k = u == 0 ? k1 : k2;
        if (u == 1 && k2 == k1) break;
        const double c_ok = r->cc[k];
        double slope;
        bl[0] = far.bind[0];
        bl[1] = far.bind[1];
        const double ck = vk_backoff_predict(r, basis, K, c_ok, a, bl, &slope, VK_LOCAL_KINK);
        if (isnan(ck)) continue;
        const double c = ck + (c_ok < a ? -0.5 : 0.5) * VK_PL_BACKOFF_TOL;
        if (c > vk_min(c_ok, a) && c < vk_max(c_ok, a)) {
            int pb = r->ik == 0 ? 1 : 0, pk = 3 - r->ik - pb, bw[2], probes = 0;
            double w;
            vk_backoff_try(r, s, cache, &probes, c, VK_TRY_CHECK, NAN, &pb, &pk, best, &least,
                           &w, bw);
        }
        break;
    }
    *best = least.j < far.j ? least : far;
    return best->c;
}

/* Whether the path-only constraints (joint limits, theta_p, volume) of an evaluated row hold. */
static int vk_path_ok(const double *out)
{
    for (int j = 0; j < 6; j++)
        if (!(out[O_VIOLATIONS + j] <= 0.0)) return 0;
    for (int j = 16; j < 20; j++)
        if (!(out[O_VIOLATIONS + j] <= 0.0)) return 0;
    return 1;
}

/*
 * Plan one row: the path scale c* of vk_plan_scale retimed (vk_retime) into out and planned;
 * if that is infeasible, the back-off's; if that fails too or nothing qualifies, the row's own
 * path (c = 1): retimed, or where it breaks a path-only limit (which no T fixes), evaluated as
 * it is (planned: the row's a6 and T).
 *   scale: NULL or out, the c of the reported path (NAN for a rejected row)
 *   basis: q(s), p(s), 1/p(s), q', q'', p', p'' (7 * m); sc: VK_N_PLAN * m scratch
 */
static void vk_plan(const double *p, const double *s, const double *basis, int m,
                    const double *basis_c, int m_c, const double *in, double c_lo, double c_hi,
                    double *out, double *planned, double *path, double *scale, double *cache,
                    double *sc, double *sc_c)
{
    int valid = 1;
    for (int j = 0; j < VK_N_IN; j++)
        if (!isfinite(in[j])) valid = 0;
    const double T = in[I_T], dig = in[I_DIG_TYPE];
    if (!(T > 0.0) || !(dig == 0.0 || dig == 1.0)) valid = 0;
    double K[3] = {0.0, 0.0, 0.0};
    if (valid) {
        const double T6 = pow(T, 6.0);
        for (int j = 0; j < 3; j++) {
            K[j] = -in[I_A6 + j] * T6;
            if (!isfinite(K[j])) valid = 0;
        }
    }
    if (!valid) {
        vk_retime(p, s, m, in, out, planned, path, NULL, cache); /* rejects it */
        if (scale != NULL) *scale = NAN;
        return;
    }
    vk_pathscan r;
    r.p = p;
    r.in = in;
    r.n = 0;
    vk_pathscan_grid(&r, sc, m);
    const double *trig;
    double v = 0.0, lo = c_lo, hi = c_hi;
    int scanned = 1;
    double c;
    if (basis_c != NULL) {
        vk_pathscan rc = r;
        vk_pathscan_grid(&rc, sc_c, m_c);
        c = vk_plan_scale_coarse(&r, &rc, basis, basis_c, K, c_lo, c_hi, &trig, &v, &scanned,
                                 &lo, &hi);
    } else {
        c = vk_plan_scale(&r, basis, K, c_lo, c_hi, &trig, &v);
    }
    if (!isnan(c) && c != 1.0) {
        /* The retime of c*, evaluated only if its search finds a time (else straight to the
         * back-off: that evaluation would be thrown away). */
        double Kc[3], T_c = 0.0, w_c;
        int bind[2];
        const int found = vk_backoff_probe(p, s, m, in, c, trig, cache, Kc, &T_c, &w_c, bind);
        if (found) {
            vk_retime_finish(p, s, m, in, Kc, T_c, found, out, planned, path);
            if (out[O_TOTAL] <= 0.0) {
                if (scale != NULL) *scale = c;
                return;
            }
        }
        if (!scanned) vk_plan_scan(&r, lo, hi); /* the back-off starts from the full scan */
        vk_probe b;
        const double c2 = vk_plan_backoff(&r, s, basis, K, cache, c, v, found ? NAN : w_c, bind,
                                          &b);
        if (!isnan(c2) && c2 != 1.0) {
            /* The probe's search found b.T: what vk_retime of that path gives, evaluated
             * (vk_retime_finish sets a6 and T from b.K and b.T; the rest of the row is in's). */
            vk_retime_finish(p, s, m, in, b.K, b.T, 1, out, planned, path);
            if (out[O_TOTAL] <= 0.0) {
                if (scale != NULL) *scale = c2;
                return;
            }
        }
    }
    if (scale != NULL) *scale = 1.0;
    /* The row's own path. Unless the scan found it path-feasible, it is evaluated first: where
     * a path-only limit fails, no T can fix it, and that evaluation is the report. */
    int own_ok = 0;
    for (int k = 0; k < r.n; k++)
        if (r.cc[k] == 1.0 && r.cg[k] <= 0.0) own_ok = 1;
    if (!own_ok) {
        vk_evaluate(p, s, m, in, out, path);
        if (!vk_path_ok(out)) {
            for (int j = 0; j < 3; j++) planned[j] = in[I_A6 + j];
            planned[3] = in[I_T];
            return;
        }
    }
    /* Without the probes' trig, so that scale 1 is exactly what retime() gives. */
    vk_retime(p, s, m, in, out, planned, path, NULL, cache);
}

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
    Py_ssize_t n;
    const double *walls;           /* 3 x 3: n_x, n_y, c of the far wall, near wall, bottom */
    double xf, xn, ground;         /* the trench's x range and the ground line */
    const double *edges;           /* E x 5: ax, ay, abx, aby, |ab|^2 (the design's edges) */
    Py_ssize_t n_edges;
} vk_field;

/* TrenchSession._on_grid: linear interpolation on the uniform grid, clamped at the ends. */
static inline void vk_on_grid(const vk_field *f, double x, double *surf, double *floor)
{
    double u = (x - f->x0) / f->h;
    const double top = (double)f->n - 1.000001;
    u = u > 0.0 ? (u < top ? u : top) : 0.0; /* NaN: 0, never an index out of the grid */
    const Py_ssize_t i = (Py_ssize_t)u;
    const double w = u - (double)i;
    *surf = f->surface[i] * (1.0 - w) + f->surface[i + 1] * w;
    if (floor != NULL) *floor = f->floor[i] * (1.0 - w) + f->floor[i + 1] * w;
}

/* TrenchSession._overdig_many of one sample: its distance to the design where it lies in the
 * material and outside the design, else 0. */
static inline double vk_sample_overdig(const vk_field *f, double x, double y)
{
    double surf;
    vk_on_grid(f, x, &surf, NULL);
    if (!(y < surf)) return 0.0;
    const double *w = f->walls;
    double d = vk_max(vk_max(w[0] * x + w[1] * y - w[2], w[3] * x + w[4] * y - w[5]),
                      w[6] * x + w[7] * y - w[8]);
    if (x > f->xf || x < f->xn) d = vk_max(d, f->ground - y);
    if (!(d > 0.0)) return 0.0;
    double best = INFINITY;
    for (Py_ssize_t e = 0; e < f->n_edges; e++) {
        const double *g = f->edges + 5 * e;
        double t = ((x - g[0]) * g[2] + (y - g[1]) * g[3]) / g[4];
        t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
        const double ex = x - (g[0] + t * g[2]);
        const double ey = y - (g[1] + t * g[3]);
        best = vk_min(best, ex * ex + ey * ey);
    }
    return sqrt(best);
}

/* trench.lower_envelope: the lowest y of a polyline over each point of a uniform grid it
 * spans, +inf where it spans none (env must hold +inf on entry); the same formulas. */
static void vk_lower_envelope(const double *path, Py_ssize_t n, const double *grid, Py_ssize_t M,
                              double *env)
{
    const double x0 = grid[0], h = grid[1] - grid[0];
    for (Py_ssize_t k = 0; k + 1 < n; k++) {
        const double xa = path[2 * k], ya = path[2 * k + 1];
        const double xb = path[2 * k + 2], yb = path[2 * k + 3];
        const double lo = vk_min(xa, xb);
        double f0 = ceil((lo - x0) / h - 1e-9), f1 = floor((lo + fabs(xb - xa) - x0) / h + 1e-9) + 1;
        /* NaN: 0 (an empty span), never an index out of the grid */
        f0 = f0 > 0.0 ? (f0 < (double)M ? f0 : (double)M) : 0.0;
        f1 = f1 > 0.0 ? (f1 < (double)M ? f1 : (double)M) : 0.0;
        const Py_ssize_t i0 = (Py_ssize_t)f0, i1 = (Py_ssize_t)f1;
        const double dx = xb - xa;
        const int flat = fabs(dx) <= 1e-12;
        const double slope = flat ? 0.0 : (yb - ya) / dx;
        const double y_lo = vk_min(ya, yb), y_hi = vk_max(ya, yb);
        const double base = flat ? y_lo : ya;
        for (Py_ssize_t i = i0; i < i1; i++) {
            double y = base + slope * (grid[i] - xa);
            y = vk_min(vk_max(y, y_lo), y_hi);
            if (y < env[i]) env[i] = y;
        }
    }
}

#define VK_SCREEN_MAX 512 /* samples x scales per candidate */

/* One candidate (x7: q1, q2, H; K: the bulge direction) at nG scales G of S samples (shape
 * functions qf, pf): for each scale its V_p against H, over-dig, and total and design-inside
 * cut on the height field (m^2), written at stride `stride` apart (out[k * stride + g]). */
static void vk_screen_row(const double *p, const double *x7, const double *K, const double *qf,
                          const double *pf, int S, const double *G, int nG, const vk_field *f,
                          double *out, Py_ssize_t stride)
{
    double ang[3 * VK_SCREEN_MAX], sn[3 * VK_SCREEN_MAX], cs[3 * VK_SCREEN_MAX];
    const int n = S * nG;
    for (int g = 0; g < nG; g++)
        for (int s = 0; s < S; s++) {
            const int i = g * S + s;
            double q[3];
            for (int j = 0; j < 3; j++) {
                const double base = x7[j] + qf[s] * (x7[3 + j] - x7[j]);
                q[j] = base + G[g] * (pf[s] * K[j]);
            }
            ang[i] = q[0];
            ang[n + i] = q[0] + q[1];
            ang[2 * n + i] = (q[0] + q[1]) + q[2];
        }
    vk_sincos_n(ang, sn, cs, 3 * n);
    const double l0 = p[P_LEN], l1 = p[P_LEN + 1], l2 = p[P_LEN + 2], m = f->machine_x;
    const double H = x7[6];
    for (int g = 0; g < nG; g++) {
        double area = 0.0, over = 0.0, total = 0.0, useful = 0.0, xp = 0.0, yp = 0.0, xr = 0.0;
        for (int s = 0; s < S; s++) {
            const int i = g * S + s;
            const double xa = l0 * cs[i] + l1 * cs[n + i] + l2 * cs[2 * n + i];
            const double y = l0 * sn[i] + l1 * sn[n + i] + l2 * sn[2 * n + i];
            const double x = xa + m;
            const double xrel = x - m; /* excavated_area_m2 takes x - m, as trench.py passes */
            over = vk_max(over, vk_sample_overdig(f, x, y));
            if (s > 0) {
                area += vk_segment_area(H - yp, H - y, xrel - xr);
                const double xm = 0.5 * (x + xp), ym = 0.5 * (y + yp), dx = fabs(x - xp);
                double surf, floor;
                vk_on_grid(f, xm, &surf, &floor);
                total += vk_pos(surf - ym) * dx;
                useful += vk_pos(surf - vk_max(ym, floor)) * dx;
            }
            xp = x;
            yp = y;
            xr = xrel;
        }
        out[g] = fabs(area);
        out[stride + g] = over;
        out[2 * stride + g] = total;
        out[3 * stride + g] = useful;
    }
}

/* ---------------------------------------------------------------------------------------------
 * CPython binding.
 * ------------------------------------------------------------------------------------------- */
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

/* A C-contiguous float64 buffer of the given rank; shape[k] < 0 accepts any length. */
/* Whether a buffer holds native items of struct code ``code`` ('d' float64, 'f' float32) of
 * ``size`` bytes (an explicit native or little-endian prefix allowed). */
static int vk_format_is(const Py_buffer *view, char code, Py_ssize_t size)
{
    const char *f = view->format;
    if (f != NULL && (f[0] == '<' || f[0] == '=' || f[0] == '@')) f++;
    return view->itemsize == size && f != NULL && f[0] == code && f[1] == '\0';
}

static int get_f64(PyObject *obj, Py_buffer *view, int writable, int ndim, const Py_ssize_t *shape,
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

static void release_rows(vk_arg *a, int count)
{
    for (int k = 0; k < count; k++)
        if (a[k].held) {
            PyBuffer_Release(&a[k].view);
            a[k].held = 0;
        }
}

/* Acquire every present argument (absent: NULL or None). Returns 0, or -1 with the error set
   and nothing held. */
static int get_args(vk_arg *a, int count)
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
static Py_ssize_t get_rows(vk_arg *a, int count)
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
static int get_double(PyObject *obj, double *v, const char *name)
{
    *v = PyFloat_AsDouble(obj);
    if (*v == -1.0 && PyErr_Occurred()) {
        PyErr_Format(PyExc_TypeError, "%s must be a float", name);
        return -1;
    }
    return 0;
}

/* The fill's range of bulge scales (plan's c_lo, c_hi): finite, 0 <= c_lo <= c_hi. */
static int get_c_range(PyObject *lo, PyObject *hi, double *c_lo, double *c_hi)
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
 *
 * Where a dig type has a solution library (set_library) and the call allows it, a feasible plan
 * whose fill scaled the bulge by the library's trigger or more goes on to step 4a of
 * PinnPlanner.plan (vk_library_plan): the library's k nearest problems (brute force, in C) and
 * their teacher paths planned for this row, the best kept when it beats the network's.
 *
 * The network call may release the GIL; it runs before the kernel's scratch is touched, and the
 * row and network buffers are the planner's own (a planner serves one thread at a time, as
 * before).
 * ------------------------------------------------------------------------------------------- */
enum { F_ROW = 0, F_OUT, F_PLANNED, F_SCALE, F_X0, F_X1, F_Y0, F_Y1, VK_N_FRONT };

/* A dig type's solution library (PinnPlanner step 4a; Front.set_library): the problems scaled
 * by inv_std, one input per row of xs (7, n), so that the distance loop runs along n; the
 * teacher's answers y (n, 4); the trigger on the fill's bulge scale; k candidates and their
 * scratch rows (k * (VK_N_IN + VK_N_OUT + 4 + 2) doubles). n == 0: no library. */
typedef struct {
    Py_buffer xs, y;
    Py_ssize_t n;
    double inv_std[7];
    double trigger;
    int k;
    double *scratch;
    Py_ssize_t *idx;
} vk_library;

/* Bound on a library's k (the scratch is allocated once per library). */
#define VK_LIB_K_MAX 64
/* Rows per block of the neighbour search: their distances stay in L1. */
#define VK_LIB_BLOCK 256

typedef struct {
    PyObject_HEAD
    KernelObject *kernel;
    PyObject *runs[2];
    Py_buffer views[VK_N_FRONT];
    int held;
    double lo[2][7], hi[2][7];
    vk_library lib[2];
} FrontObject;

static void vk_library_clear(vk_library *lib)
{
    if (lib->n > 0) {
        PyBuffer_Release(&lib->xs);
        PyBuffer_Release(&lib->y);
    }
    free(lib->scratch);
    free(lib->idx);
    lib->scratch = NULL;
    lib->idx = NULL;
    lib->n = 0;
}

/* The k nearest rows of xs (7, n) to q (7), by squared distance, nearest first (ties: the lower
 * row first), into idx (k <= n); brute force in blocks (a few microseconds for 8000 rows, the
 * inner loop vectorised), the sums in the same order as numpy's ((q - xs.T) ** 2).sum(axis=1)
 * over axis 0 of xs, so that the Python path finds the same rows. */
static void vk_nearest(const double *xs, Py_ssize_t n, const double *q, int k, Py_ssize_t *idx,
                       double *best)
{
    for (int i = 0; i < k; i++) {
        best[i] = INFINITY;
        idx[i] = 0;
    }
    double d[VK_LIB_BLOCK];
    for (Py_ssize_t b = 0; b < n; b += VK_LIB_BLOCK) {
        const int m = (int)(n - b < VK_LIB_BLOCK ? n - b : VK_LIB_BLOCK);
        {
            const double *col = xs + b, q0 = q[0];
            for (int i = 0; i < m; i++) {
                const double e = q0 - col[i];
                d[i] = e * e;
            }
        }
        for (int j = 1; j < 7; j++) {
            const double *col = xs + (Py_ssize_t)j * n + b, qj = q[j];
            for (int i = 0; i < m; i++) {
                const double e = qj - col[i];
                d[i] += e * e;
            }
        }
        for (int i = 0; i < m; i++) {
            if (!(d[i] < best[k - 1])) continue;
            int pos = k - 1;
            while (pos > 0 && best[pos - 1] > d[i]) {
                best[pos] = best[pos - 1];
                idx[pos] = idx[pos - 1];
                pos--;
            }
            best[pos] = d[i];
            idx[pos] = b + i;
        }
    }
}

/* Step 4a of PinnPlanner.plan for the row just planned (feasible, in out/planned/scale): the
 * library's k nearest problems' teacher paths planned for this row (vk_plan, as the network's);
 * the best feasible one replaces out, planned and scale when its objective is smaller: 1. */
static int vk_library_plan(const KernelObject *kn, const vk_library *lib, const double *row,
                           double c_lo, double c_hi, double *out, double *planned, double *scale)
{
    double q[7];
    for (int j = 0; j < 7; j++) q[j] = row[j] * lib->inv_std[j];
    const int k = lib->k;
    double *rows = lib->scratch, *outs = rows + k * VK_N_IN, *pls = outs + k * VK_N_OUT;
    double *scs = pls + 4 * k, *best = scs + k;
    vk_nearest((const double *)lib->xs.buf, lib->n, q, k, lib->idx, best);
    const double *y = (const double *)lib->y.buf;
    int win = -1;
    double objective = out[O_OBJECTIVE];
    for (int c = 0; c < k; c++) {
        double *r = rows + c * VK_N_IN, *o = outs + c * VK_N_OUT;
        for (int j = 0; j < I_A6; j++) r[j] = row[j];
        for (int j = 0; j < 4; j++) r[I_A6 + j] = y[lib->idx[c] * 4 + j];
        vk_plan(kn->params, kn->s, kn->basis, kn->m, kn->basis_c, kn->m_c, r, c_lo, c_hi, o,
                pls + 4 * c, NULL, scs + c, kn->cache, kn->scratch, kn->scratch_c);
        if (o[O_TOTAL] <= 0.0 && o[O_OBJECTIVE] < objective) {
            objective = o[O_OBJECTIVE];
            win = c;
        }
    }
    if (win < 0) return 0;
    for (int j = 0; j < VK_N_OUT; j++) out[j] = outs[win * VK_N_OUT + j];
    for (int j = 0; j < 4; j++) planned[j] = pls[4 * win + j];
    *scale = scs[win];
    return 1;
}

static void Front_dealloc(FrontObject *self)
{
    vk_library_clear(&self->lib[0]);
    vk_library_clear(&self->lib[1]);
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

/* plan(q_start, q_end, H, dig_type, c_lo, c_hi[, library]) -> None (outside the domain: nothing
 * ran) or (feasible, infer_us, from_library). */
static PyObject *Front_plan(FrontObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 6 && nargs != 7) {
        PyErr_SetString(PyExc_TypeError,
                        "plan(q_start, q_end, H, dig_type, c_lo, c_hi, library=True) takes 6 or "
                        "7 arguments");
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
    int use_library = 1;
    if (nargs == 7 && (use_library = PyObject_IsTrue(args[6])) < 0) return NULL;
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
    const vk_library *lib = &self->lib[kind];
    const int from_library = use_library && feasible && lib->n > 0 && *scale >= lib->trigger &&
                             vk_library_plan(kn, lib, row, c_lo, c_hi, out, planned, scale);
    PyObject *us = PyFloat_FromDouble(infer_us);
    if (us == NULL) return NULL;
    PyObject *r = PyTuple_Pack(3, feasible ? Py_True : Py_False, us,
                               from_library ? Py_True : Py_False);
    Py_DECREF(us);
    return r;
}

/* set_library(dig_type, xs (7, n), inv_std (7,), y (n, 4), trigger, k) or
 * set_library(dig_type, None): bind (or unbind) a dig type's solution library; the arrays are
 * held until replaced or the Front is gone. */
static PyObject *Front_set_library(FrontObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2 && nargs != 6) {
        PyErr_SetString(PyExc_TypeError,
                        "set_library(dig_type, xs, inv_std, y, trigger, k) or "
                        "set_library(dig_type, None) takes 6 or 2 arguments");
        return NULL;
    }
    long kind;
    if (get_dig_type(args[0], &kind) != 0) return NULL;
    vk_library *lib = &self->lib[kind];
    if (nargs == 2) {
        if (args[1] != Py_None) {
            PyErr_SetString(PyExc_TypeError, "set_library(dig_type, None) unbinds; got 2 "
                                             "arguments, the second not None");
            return NULL;
        }
        vk_library_clear(lib);
        Py_RETURN_NONE;
    }
    double trigger;
    if (get_double(args[4], &trigger, "trigger") != 0) return NULL;
    const long k = PyLong_AsLong(args[5]);
    if (k == -1 && PyErr_Occurred()) return NULL;
    vk_arg a[3] = {
        {args[1], "xs", 0, 2, {7, -1}},
        {args[2], "inv_std", 0, 1, {7}},
        {args[3], "y", 0, 2, {-1, 4}},
    };
    for (int i = 0; i < 3; i++)
        if (a[i].obj == Py_None) { /* required here; get_args would skip it */
            PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous float64 array", a[i].name);
            return NULL;
        }
    if (get_args(a, 3) != 0) return NULL;
    const Py_ssize_t n = a[0].view.shape[1];
    const double *inv = (const double *)a[1].view.buf;
    int finite = isfinite(trigger) && trigger > 0.0;
    for (int j = 0; j < 7; j++)
        if (!(isfinite(inv[j]) && inv[j] > 0.0)) finite = 0;
    if (n < 1 || a[2].view.shape[0] != n || k < 1 || k > n || k > VK_LIB_K_MAX || !finite) {
        PyErr_Format(PyExc_ValueError,
                     "library: xs (7, n) and y (n, 4) with n >= 1, 1 <= k <= min(n, %d), "
                     "trigger and inv_std finite and > 0; got n %zd and %zd, k %ld, trigger %g",
                     VK_LIB_K_MAX, n, a[2].view.shape[0], k, trigger);
        release_rows(a, 3);
        return NULL;
    }
    double *scratch = malloc(sizeof(double) * (size_t)k * (VK_N_IN + VK_N_OUT + 4 + 2));
    Py_ssize_t *idx = malloc(sizeof(Py_ssize_t) * (size_t)k);
    if (scratch == NULL || idx == NULL) {
        free(scratch);
        free(idx);
        release_rows(a, 3);
        return PyErr_NoMemory();
    }
    vk_library_clear(lib);
    lib->xs = a[0].view;
    lib->y = a[2].view;
    for (int j = 0; j < 7; j++) lib->inv_std[j] = inv[j];
    PyBuffer_Release(&a[1].view);
    lib->n = n;
    lib->trigger = trigger;
    lib->k = (int)k;
    lib->scratch = scratch;
    lib->idx = idx;
    Py_RETURN_NONE;
}

static PyMethodDef Front_methods[] = {
    {"plan", (PyCFunction)(void (*)(void))Front_plan, METH_FASTCALL,
     "plan(q_start, q_end, H, dig_type, c_lo, c_hi, library=True) -> None (input outside the "
     "domain or not finite: nothing ran) or (feasible, infer_us, from_library)"},
    {"set_library", (PyCFunction)(void (*)(void))Front_set_library, METH_FASTCALL,
     "set_library(dig_type, xs (7, n), inv_std (7,), y (n, 4), trigger, k) or "
     "set_library(dig_type, None)"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject FrontType = {
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
static PyObject *Kernel_front(KernelObject *self, PyObject *const *args, Py_ssize_t nargs)
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
    for (int k = 0; k < 2; k++) {
        f->lib[k].n = 0;
        f->lib[k].scratch = NULL;
        f->lib[k].idx = NULL;
    }
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
    for (Py_ssize_t r = 0; r < N; r++) {
        double worst = 0.0;
        for (Py_ssize_t s = 0; s < n; s++) {
            const double *pt = paths + 2 * (r * n + s);
            worst = vk_max(worst, vk_sample_overdig(&f, pt[0], pt[1]));
        }
        out[r] = worst;
    }
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
static PyMethodDef verify_functions[] = {
    {"overdig", (PyCFunction)(void (*)(void))vk_py_overdig, METH_FASTCALL,
     "overdig(paths (N, n, 2), field (2, M), frame (6,), walls (3, 3), edges (E, 5), out (N,)) "
     "-> None"},
    {"envelope", (PyCFunction)(void (*)(void))vk_py_envelope, METH_FASTCALL,
     "envelope(path (n, 2), grid (M,) uniform, out (M,)) -> None"},
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
