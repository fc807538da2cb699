/*
 * mt_evaluate: what rt_runtime.planning.mintorque.Evaluator computes with numpy (the smoothed
 * minimum-torque model of Yang/Pan eq 6-18), for a batch of points, looping over the samples.
 *
 * A point is the five keypoints' joint angles (15) and, in a variable-time problem, the four
 * intervals (s); a fixed-time problem takes its intervals from the constants. Per point:
 *
 *   - each joint follows one quintic Hermite piece per interval (zero end accelerations,
 *     three-point knot velocities, zero at both ends), sampled at Q + 1 points per interval
 *     from the shape functions the caller passes (mintorque._hermite_basis, ends included);
 *   - joint torques by the closed-form inverse dynamics in absolute angles, with the smoothed
 *     fluid soil's wrench at the tip summed over the bucket's plates (mintorque._Model);
 *   - the cost, the trapezoid sum of sum_j (tau_j / tau_max_j)^2 weighted by each sample's
 *     share of its interval's time;
 *   - the 30 per-sample constraint columns (angle min / max, then +- velocity, acceleration,
 *     jerk and torque over their limits, 3 joints each): their peaks over all samples folded
 *     into the 18 named sampled constraints, and per interval their smooth maximum
 *     (Kreisselmeier-Steinhauser, rho = ks_rho) for the optimiser;
 *   - the 31 keypoint constraints of eq 8-11 (mintorque._Model.keypoint_constraints).
 *
 * Same formulas in the same association order as the numpy model, so the two agree to
 * rounding (~1e-12 relative; numpy's pairwise sums round differently); tests/test_mintorque.py
 * holds them together. Allocates one scratch row block per call (Q + 1 samples x 30 columns).
 */
#include "kernel.h"

#define MT_COLS 30

/* Keypoint angle of key k, joint j of the point x. */
#define KEY(x, k, j) ((x)[3 * (k) + (j)])

static void mt_keypoints(const double *p, const double *x, double *kp)
{
    const double l0 = p[MT_LEN], l1 = p[MT_LEN + 1], l2 = p[MT_LEN + 2];
    double tx[MT_N_KEY], ty[MT_N_KEY], hc[MT_N_KEY], hs[MT_N_KEY];
    for (int k = 0; k < MT_N_KEY; k++) {
        const double a0 = KEY(x, k, 0);
        const double a1 = a0 + KEY(x, k, 1);
        const double a2 = a1 + KEY(x, k, 2);
        tx[k] = l0 * cos(a0) + l1 * cos(a1) + l2 * cos(a2);
        ty[k] = l0 * sin(a0) + l1 * sin(a1) + l2 * sin(a2);
        hc[k] = cos(a2);
        hs[k] = sin(a2);
    }
    const double H = p[MT_SURFACE];
    const int quad[4] = {0, 1, 2, 4};
    double twice = 0.0;
    for (int i = 0; i < 4; i++) {
        const int a = quad[i], b = quad[(i + 1) % 4];
        twice = twice + (tx[a] * ty[b] - tx[b] * ty[a]);
    }
    const double volume = -0.5 * twice * p[MT_WIDTH];
    const double v_lo = p[MT_VOLUME], v_hi = p[MT_VOLUME + 1];
    const double z_lo = p[MT_DEPTH], z_hi = p[MT_DEPTH + 1];
    const double x_lo = p[MT_ENTRY_X], x_hi = p[MT_ENTRY_X + 1];
    const double band = p[MT_BAND];
    int o = 0;
    kp[o++] = (v_lo - volume) / (v_hi - v_lo);
    kp[o++] = (volume - v_hi) / (v_hi - v_lo);
    for (int k = 1; k <= 2; k++) {
        const double depth = H - ty[k];
        kp[o++] = (z_lo - depth) / (z_hi - z_lo);
        kp[o++] = (depth - z_hi) / (z_hi - z_lo);
    }
    kp[o++] = (H - band - ty[0]) / band;
    kp[o++] = (ty[0] - H) / band;
    kp[o++] = (x_lo - tx[0]) / (x_hi - x_lo);
    kp[o++] = (tx[0] - x_hi) / (x_hi - x_lo);
    kp[o++] = (H - ty[4]) / band;
    kp[o++] = (ty[4] - H - band) / band;
    /* Heading cones: entry a against the first two normals, exit d against the other two. */
    for (int c = 0; c < 2; c++) {
        const int k = c == 0 ? 0 : 4;
        for (int s = 0; s < 2; s++) {
            const double *n = p + MT_HEADING + 4 * c + 2 * s;
            kp[o++] = hc[k] * n[0] + hs[k] * n[1];
        }
    }
    double cx[MT_N_KEY - 1], cy[MT_N_KEY - 1];
    for (int k = 0; k < MT_N_KEY - 1; k++) {
        const double dx = tx[k + 1] - tx[k];
        const double dy = ty[k + 1] - ty[k];
        const double norm = sqrt(dx * dx + dy * dy + 1e-12);
        cx[k] = dx / norm;
        cy[k] = dy / norm;
    }
    kp[o++] = cy[0];
    kp[o++] = cx[1];
    kp[o++] = -cy[3];
    for (int k = 0; k < MT_N_KEY - 1; k++) kp[o++] = hc[k] * hs[k + 1] - hs[k] * hc[k + 1];
    for (int k = 0; k < MT_N_KEY - 2; k++) kp[o++] = cx[k] * cy[k + 1] - cy[k] * cx[k + 1];
}

/* The plates as columns: a layout the per-plate loop vectorises over. */
typedef struct {
    int P;
    double cx[MT_MAX_PLATES], cy[MT_MAX_PLATES], nx[MT_MAX_PLATES], ny[MT_MAX_PLATES];
    double tx[MT_MAX_PLATES], ty[MT_MAX_PLATES], area[MT_MAX_PLATES];
} mt_plates;

static void mt_plates_of(const double *plates, int P, mt_plates *pl)
{
    pl->P = P;
    for (int k = 0; k < P; k++) {
        const double *row = plates + 7 * k;
        pl->cx[k] = row[0];
        pl->cy[k] = row[1];
        pl->nx[k] = row[2];
        pl->ny[k] = row[3];
        pl->tx[k] = row[4];
        pl->ty[k] = row[5];
        pl->area[k] = row[6];
    }
}

/* A call's scratch: the constraint rows of one interval (Q + 1 x 30; NULL where Q < 0) and the
 * plates as columns. 0, -1 when it cannot be allocated (nothing held), -2 for more than
 * MT_MAX_PLATES plates. */
static int mt_scratch(int Q, const double *plates, int P, double **g, mt_plates **pls)
{
    if (P > MT_MAX_PLATES) return -2;
    *g = Q < 0 ? NULL : malloc(sizeof(double) * MT_COLS * (size_t)(Q + 1));
    *pls = malloc(sizeof(mt_plates));
    if ((Q >= 0 && *g == NULL) || *pls == NULL) {
        free(*g);
        free(*pls);
        return -1;
    }
    mt_plates_of(plates, P, *pls);
    return 0;
}

/* Knot velocities: zero at both ends, the three-point slope estimate inside. */
static void mt_velocities(const double *x, const double *h, double vel[MT_N_KEY][3])
{
    for (int j = 0; j < 3; j++) {
        vel[0][j] = 0.0 * h[0];
        vel[MT_N_KEY - 1][j] = 0.0 * h[0];
        for (int k = 1; k < MT_N_KEY - 1; k++) {
            const double s0 = (KEY(x, k, j) - KEY(x, k - 1, j)) / h[k - 1];
            const double s1 = (KEY(x, k + 1, j) - KEY(x, k, j)) / h[k];
            vel[k][j] = (h[k] * s0 + h[k - 1] * s1) / (h[k - 1] + h[k]);
        }
    }
}

/* Joint torques (N m) at one sample of joint angles, rates and accelerations, the smoothed
 * fluid soil's wrench at the tip included (mintorque._Model._torques and _soil). */
static void mt_sample_tau(const double *p, const mt_plates *pls, const double *q,
                          const double *qd, const double *qdd, double *tau)
{
    const double l0 = p[MT_LEN], l1 = p[MT_LEN + 1], l2 = p[MT_LEN + 2];
    const double *ch = p + MT_CH_H, *cb = p + MT_CH_B, *cd = p + MT_CH_D;
    const double grav = p[MT_GRAVITY];
    const double rho_g = p[MT_RHO_G], kv = p[MT_KV], kss = p[MT_KS];
    const double eps = p[MT_EPS], r = p[MT_SPEED_REG], H = p[MT_SURFACE];
    const int P = pls->P;
    const double *pl_cx = pls->cx, *pl_cy = pls->cy, *pl_nx = pls->nx, *pl_ny = pls->ny;
    const double *pl_tx = pls->tx, *pl_ty = pls->ty, *pl_area = pls->area;
    /* Absolute angles, rates and accelerations; tip pose and twist. */
    const double phi0 = q[0], phi1 = phi0 + q[1], phi2 = phi1 + q[2];
    const double cp0 = cos(phi0), sp0 = sin(phi0), cp1 = cos(phi1), sp1 = sin(phi1);
    const double cp2 = cos(phi2), sp2 = sin(phi2);
    const double w0 = qd[0], w1 = w0 + qd[1], w2 = w1 + qd[2];
    const double a0 = qdd[0], a1 = a0 + qdd[1], a2 = a1 + qdd[2];
    const double ty = l0 * sp0 + l1 * sp1 + l2 * sp2;
    const double vx = -(l0 * sp0 * w0 + l1 * sp1 * w1 + l2 * sp2 * w2);
    const double vy = l0 * cp0 * w0 + l1 * cp1 * w1 + l2 * cp2 * w2;
    /* The smoothed fluid soil, summed over the plates (bucket frame). */
    const double u = cp2 * vx + sp2 * vy;
    const double w = cp2 * vy - sp2 * vx;
    /* Each plate's share first (a loop the compiler vectorises: no value carried
     * between plates), then the sums in plate order, as the numpy loop adds them. */
    double sfx[MT_MAX_PLATES], sfy[MT_MAX_PLATES], smz[MT_MAX_PLATES];
    for (int pi = 0; pi < P; pi++) {
        const double pcx = pl_cx[pi], pcy = pl_cy[pi], pnx = pl_nx[pi], pny = pl_ny[pi];
        const double ptx = pl_tx[pi], pty = pl_ty[pi];
        const double depth = H - (ty + pcx * sp2 + pcy * cp2);
        const double root = sqrt(depth * depth + eps * eps);
        const double arm_n = pcx * pny - pcy * pnx;
        const double arm_t = pcx * pty - pcy * ptx;
        const double vn = u * pnx + w * pny + w2 * arm_n;
        const double vt = u * ptx + w * pty + w2 * arm_t;
        const double rn = sqrt(vn * vn + r * r);
        const double rt = sqrt(vt * vt + r * r);
        const double mag = (rho_g * 0.5 * (depth + root) + kv * (rn - r)) *
                           (pl_area[pi] * 0.5 * (1.0 + depth / root));
        const double un = vn / rn;
        const double ut = kss * vt / rt;
        sfx[pi] = mag * (un * pnx + ut * ptx);
        sfy[pi] = mag * (un * pny + ut * pty);
        smz[pi] = mag * (un * arm_n + ut * arm_t);
    }
    double fxb = 0.0, fyb = 0.0, mz = 0.0;
    for (int pi = 0; pi < P; pi++) {
        fxb = fxb - sfx[pi];
        fyb = fyb - sfy[pi];
        mz = mz - smz[pi];
    }
    const double fx = cp2 * fxb - sp2 * fyb;
    const double fy = sp2 * fxb + cp2 * fyb;
    /* Closed-form inverse dynamics in absolute angles. */
    const double cq1 = cos(q[1]), sq1 = sin(q[1]);
    const double cq2 = cos(q[2]), sq2 = sin(q[2]);
    const double c12 = cos(q[1] + q[2]), s12 = sin(q[1] + q[2]);
    const double d01 = l0 * (ch[1] * cq1 - cb[1] * sq1);
    const double w01 = l0 * (cb[1] * cq1 + ch[1] * sq1);
    const double d02 = l0 * (ch[2] * c12 - cb[2] * s12);
    const double w02 = l0 * (cb[2] * c12 + ch[2] * s12);
    const double d12 = l1 * (ch[2] * cq2 - cb[2] * sq2);
    const double w12 = l1 * (cb[2] * cq2 + ch[2] * sq2);
    const double ww0 = w0 * w0, ww1 = w1 * w1, ww2 = w2 * w2;
    double t0 = cd[0] * a0 + d01 * a1 + d02 * a2 - w01 * ww1 - w02 * ww2;
    t0 = t0 + grav * (ch[0] * cp0 - cb[0] * sp0) - l0 * (cp0 * fy - sp0 * fx);
    double t1 = d01 * a0 + cd[1] * a1 + d12 * a2 + w01 * ww0 - w12 * ww2;
    t1 = t1 + grav * (ch[1] * cp1 - cb[1] * sp1) - l1 * (cp1 * fy - sp1 * fx);
    double t2 = d02 * a0 + d12 * a1 + cd[2] * a2 + w02 * ww0 + w12 * ww1;
    t2 = t2 + grav * (ch[2] * cp2 - cb[2] * sp2) - l2 * (cp2 * fy - sp2 * fx) - mz;
    t1 = t1 + t2;
    t0 = t0 + t1;
    tau[0] = t0;
    tau[1] = t1;
    tau[2] = t2;
}

/* sum_j (tau_j / tau_max_j)^2, the cost's integrand at one sample. */
static inline double mt_sq(const double *p, const double *tau)
{
    double sq = 0.0;
    for (int j = 0; j < 3; j++) {
        const double z = tau[j] / p[MT_TAU_MAX + j];
        sq = sq + z * z;
    }
    return sq;
}

/* What one interval adds: its cost (trapezoid sum), and per constraint column its peak and
 * smooth maximum. g is scratch of (Q + 1) x 30. */
typedef struct {
    double cost;
    double peak[MT_COLS];
    double ks[MT_COLS];
} mt_part;

static void mt_interval(const double *p, const double *basis, int Q, const mt_plates *pls,
                        const double *x, const double *h, const double vel[MT_N_KEY][3],
                        int i, double *g, mt_part *out)
{
    const int n = Q + 1;
    const double *B_h0 = basis, *B_h5 = basis + n, *B_h1 = basis + 2 * n, *B_h4 = basis + 3 * n;
    const double *B_d0 = basis + 4 * n, *B_d1 = basis + 5 * n, *B_d4 = basis + 6 * n;
    const double *B_a0 = basis + 7 * n, *B_a1 = basis + 8 * n, *B_a4 = basis + 9 * n;
    const double *B_j0 = basis + 10 * n, *B_j1 = basis + 11 * n, *B_j4 = basis + 12 * n;
    const double *B_w = basis + 13 * n;
    double cost = 0.0;
    const double hi = h[i];
    double c0[3], c2[3], c3[3], e0[3], e1[3], f0[3], f1[3], f2[3];
    double g0[3], g1[3], g2[3], p0v[3], p1v[3];
    for (int j = 0; j < 3; j++) {
        const double P0 = KEY(x, i, j), P1 = KEY(x, i + 1, j);
        const double v0 = vel[i][j], v1 = vel[i + 1][j];
        p0v[j] = P0;
        p1v[j] = P1;
        c2[j] = hi * v0;
        c3[j] = hi * v1;
        c0[j] = (P1 - P0) / hi;
        e0[j] = v0;
        e1[j] = v1;
        f0[j] = (P0 - P1) / (hi * hi);
        f1[j] = v0 / hi;
        f2[j] = v1 / hi;
        g0[j] = (P0 - P1) / (hi * hi * hi);
        g1[j] = v0 / (hi * hi);
        g2[j] = v1 / (hi * hi);
    }
    for (int k = 0; k < n; k++) {
        double q[3], qd[3], qdd[3], jk[3];
        for (int j = 0; j < 3; j++) {
            q[j] = p0v[j] * B_h0[k] + p1v[j] * B_h5[k] + c2[j] * B_h1[k] + c3[j] * B_h4[k];
            qd[j] = c0[j] * -B_d0[k] + e0[j] * B_d1[k] + e1[j] * B_d4[k];
            qdd[j] = f0[j] * B_a0[k] + f1[j] * B_a1[k] + f2[j] * B_a4[k];
            jk[j] = g0[j] * B_j0[k] + g1[j] * B_j1[k] + g2[j] * B_j4[k];
        }
        double tau[3];
        mt_sample_tau(p, pls, q, qd, qdd, tau);
        const double sq = mt_sq(p, tau);
        cost = cost + hi * B_w[k] * sq;
        double *row = g + MT_COLS * k;
        for (int j = 0; j < 3; j++) {
            row[j] = (p[MT_Q_MIN + j] - q[j]) / p[MT_Q_SPAN + j];
            row[3 + j] = (q[j] - p[MT_Q_MAX + j]) / p[MT_Q_SPAN + j];
            row[6 + j] = qd[j] / p[MT_V_LIM + j] - 1.0;
            row[9 + j] = -qd[j] / p[MT_V_LIM + j] - 1.0;
            row[12 + j] = qdd[j] / p[MT_A_LIM + j] - 1.0;
            row[15 + j] = -qdd[j] / p[MT_A_LIM + j] - 1.0;
            row[18 + j] = jk[j] / p[MT_J_LIM + j] - 1.0;
            row[21 + j] = -jk[j] / p[MT_J_LIM + j] - 1.0;
            row[24 + j] = tau[j] / p[MT_T_LIM + j] - 1.0;
            row[27 + j] = -tau[j] / p[MT_T_LIM + j] - 1.0;
        }
    }
    out->cost = cost;
    const double rho = p[MT_KS_RHO];
    for (int c = 0; c < MT_COLS; c++) {
        double top = -INFINITY;
        for (int k = 0; k < n; k++) top = vk_max(top, g[MT_COLS * k + c]);
        double sum = 0.0;
        for (int k = 0; k < n; k++) sum += exp(rho * (g[MT_COLS * k + c] - top));
        out->ks[c] = top + log(sum) / rho;
        out->peak[c] = top;
    }
}

/* A point's outputs from its intervals' parts and its keypoint constraints kp (MT_N_KP). */
static double mt_assemble(const mt_part *parts, const double *kp, double *named, double *split)
{
    double cost = 0.0;
    double peak[MT_COLS];
    for (int c = 0; c < MT_COLS; c++) peak[c] = -INFINITY;
    for (int i = 0; i < MT_N_INTERVALS; i++) {
        cost = cost + parts[i].cost;
        for (int c = 0; c < MT_COLS; c++) {
            split[MT_COLS * i + c] = parts[i].ks[c];
            peak[c] = vk_max(peak[c], parts[i].peak[c]);
        }
    }
    memcpy(split + MT_COLS * MT_N_INTERVALS, kp, sizeof(double) * MT_N_KP);
    if (named != NULL) {
        for (int j = 0; j < 3; j++) {
            named[j] = peak[j];
            named[3 + j] = peak[3 + j];
            for (int pair = 1; pair < 5; pair++)
                named[3 * (pair + 1) + j] = vk_max(peak[6 * pair + j], peak[6 * pair + 3 + j]);
        }
        memcpy(named + 18, kp, sizeof(double) * MT_N_KP);
    }
    return cost;
}

static const double *mt_intervals_of(const double *p, const double *x, int n_var)
{
    return n_var > 3 * MT_N_KEY ? x + 3 * MT_N_KEY : p + MT_INTERVALS;
}

int mt_evaluate(const double *p, const double *basis, int Q, const double *plates, int P,
                const double *X, ptrdiff_t B, int n_var, double *cost, double *named,
                double *split)
{
    double *g;
    mt_plates *pls;
    const int rc = mt_scratch(Q, plates, P, &g, &pls);
    if (rc != 0) return rc;
    for (ptrdiff_t b = 0; b < B; b++) {
        const double *x = X + (ptrdiff_t)n_var * b;
        const double *h = mt_intervals_of(p, x, n_var);
        double vel[MT_N_KEY][3], kp[MT_N_KP];
        mt_part parts[MT_N_INTERVALS];
        mt_velocities(x, h, vel);
        for (int i = 0; i < MT_N_INTERVALS; i++)
            mt_interval(p, basis, Q, pls, x, h, (const double(*)[3])vel, i, g, &parts[i]);
        mt_keypoints(p, x, kp);
        cost[b] = mt_assemble(parts, kp, named + (ptrdiff_t)MT_N_NAMED * b,
                              split + (ptrdiff_t)MT_N_SPLIT * b);
    }
    free(g);
    free(pls);
    return 0;
}

/* The intervals variable v moves: keypoint k's angles enter intervals k - 1 and k and the knot
 * velocities k - 1 .. k + 1, which enter the intervals beside them (k - 2 .. k + 1); interval
 * i's length enters interval i and the knot velocities i and i + 1 (intervals i - 1 .. i + 1). */
static void mt_reach(int v, int *lo, int *hi)
{
    int a, b;
    if (v < 3 * MT_N_KEY) {
        const int k = v / 3;
        a = k - 2;
        b = k + 1;
    } else {
        const int i = v - 3 * MT_N_KEY;
        a = i - 1;
        b = i + 1;
    }
    *lo = a < 0 ? 0 : a;
    *hi = b > MT_N_INTERVALS - 1 ? MT_N_INTERVALS - 1 : b;
}

int mt_perturbed(const double *p, const double *basis, int Q, const double *plates, int P,
                 const double *x, int n_var, double step, double *cost, double *split)
{
    double *g;
    mt_plates *pls;
    const int rc = mt_scratch(Q, plates, P, &g, &pls);
    if (rc != 0) return rc;
    double vel[MT_N_KEY][3], kp0[MT_N_KP], xp[3 * MT_N_KEY + MT_N_INTERVALS];
    mt_part base[MT_N_INTERVALS];
    const double *h0 = mt_intervals_of(p, x, n_var);
    mt_velocities(x, h0, vel);
    for (int i = 0; i < MT_N_INTERVALS; i++)
        mt_interval(p, basis, Q, pls, x, h0, (const double(*)[3])vel, i, g, &base[i]);
    mt_keypoints(p, x, kp0);
    for (int v = 0; v < n_var; v++) {
        memcpy(xp, x, sizeof(double) * (size_t)n_var);
        xp[v] = x[v] + step;
        const double *h = mt_intervals_of(p, xp, n_var);
        mt_part parts[MT_N_INTERVALS];
        int lo, hi;
        mt_reach(v, &lo, &hi);
        mt_velocities(xp, h, vel);
        for (int i = 0; i < MT_N_INTERVALS; i++) {
            if (i < lo || i > hi)
                parts[i] = base[i];
            else
                mt_interval(p, basis, Q, pls, xp, h, (const double(*)[3])vel, i, g, &parts[i]);
        }
        double kp[MT_N_KP];
        if (v < 3 * MT_N_KEY)
            mt_keypoints(p, xp, kp);
        else
            memcpy(kp, kp0, sizeof kp);
        cost[v] = mt_assemble(parts, kp, NULL, split + (ptrdiff_t)MT_N_SPLIT * v);
    }
    free(g);
    free(pls);
    return 0;
}

int mt_path_cost(const double *p, const double *plates, int P, const double *q,
                 const double *qd, const double *qdd, const double *w, ptrdiff_t B, ptrdiff_t n,
                 double *cost)
{
    double *g;
    mt_plates *pls;
    const int rc = mt_scratch(-1, plates, P, &g, &pls);
    if (rc != 0) return rc;
    for (ptrdiff_t b = 0; b < B; b++) {
        double c = 0.0;
        for (ptrdiff_t k = 0; k < n; k++) {
            const ptrdiff_t at = 3 * (n * b + k);
            double tau[3];
            mt_sample_tau(p, pls, q + at, qd + at, qdd + at, tau);
            c = c + w[n * b + k] * mt_sq(p, tau);
        }
        cost[b] = c;
    }
    free(pls);
    return 0;
}
