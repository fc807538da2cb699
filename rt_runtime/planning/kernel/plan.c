#include "kernel.h"

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
void vk_plan(const double *p, const double *s, const double *basis, int m,
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

