/* vk_evaluate: one candidate against every hard limit (kernel.h). */
#include "kernel.h"

/*
 * Evaluate one candidate.
 *   p:    packed constants (enum vk_param)
 *   s:    normalised time grid, m >= 2 points from 0 to 1 (numpy.linspace)
 *   in:   one input row (enum vk_input)
 *   out:  one output row (enum vk_output)
 *   path: NULL or (m, 2) tip x, y at the samples
 */
void vk_evaluate(const double *p, const double *s, int m, const double *in, double *out,
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

