/* vk_retime: time-optimal retiming along a fixed path (kernel.h, "Time-optimal retiming"). */
#include "kernel.h"

/*
 * Fill the unit-time cache of one input row.
 *   K:      out, the kept shape term -a6 T^6 per joint (as oneshot.particle_from_a6)
 *   trig:   NULL, or cos then sin of the absolute angles of the row's path (6 arrays of m:
 *           cos phi_0, phi_1, phi_2, sin phi_0, ...) that the caller already has
 *   qd_pk, qdd_pk: out, max |q'| and max |q''| per joint over the samples
 * Returns -1 for a row that run() rejects or whose K is not finite, 0 for a finite cache, 1
 * when the cache overflowed (absurd but finite inputs).
 */
int vk_prepare(const double *p, const double *s, int m, const double *in, double *K,
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
double vk_retime_T(const double *p, const double *c, int m, const double *qd_pk,
                   const double *qdd_pk, int *found, int need_best, double *window, int *bind)
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
void vk_retime_finish(const double *p, const double *s, int m, const double *in,
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
void vk_retime(const double *p, const double *s, int m, const double *in, double *out,
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

