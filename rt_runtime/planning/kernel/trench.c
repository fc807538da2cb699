#include "kernel.h"

static inline void vk_on_grid(const vk_field *f, double x, double *surf, double *floor)
{
    double u = (x - f->x0) / f->h;
    const double top = (double)f->n - 1.000001;
    u = u > 0.0 ? (u < top ? u : top) : 0.0; /* NaN: 0, never an index out of the grid */
    const ptrdiff_t i = (ptrdiff_t)u;
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
    for (ptrdiff_t e = 0; e < f->n_edges; e++) {
        const double *g = f->edges + 5 * e;
        double t = ((x - g[0]) * g[2] + (y - g[1]) * g[3]) / g[4];
        t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
        const double ex = x - (g[0] + t * g[2]);
        const double ey = y - (g[1] + t * g[3]);
        best = vk_min(best, ex * ex + ey * ey);
    }
    return sqrt(best);
}

/* The deepest over-dig of a path's n samples (x, y pairs): TrenchSession._overdig_many of one
 * path. */
double vk_overdig_path(const vk_field *f, const double *path, ptrdiff_t n)
{
    double worst = 0.0;
    for (ptrdiff_t s = 0; s < n; s++) worst = vk_max(worst, vk_sample_overdig(f, path[2 * s], path[2 * s + 1]));
    return worst;
}

/* trench.lower_envelope: the lowest y of a polyline over each point of a uniform grid it
 * spans, +inf where it spans none (env must hold +inf on entry); the same formulas. */
void vk_lower_envelope(const double *path, ptrdiff_t n, const double *grid, ptrdiff_t M,
                       double *env)
{
    const double x0 = grid[0], h = grid[1] - grid[0];
    for (ptrdiff_t k = 0; k + 1 < n; k++) {
        const double xa = path[2 * k], ya = path[2 * k + 1];
        const double xb = path[2 * k + 2], yb = path[2 * k + 3];
        const double lo = vk_min(xa, xb);
        double f0 = ceil((lo - x0) / h - 1e-9), f1 = floor((lo + fabs(xb - xa) - x0) / h + 1e-9) + 1;
        /* NaN: 0 (an empty span), never an index out of the grid */
        f0 = f0 > 0.0 ? (f0 < (double)M ? f0 : (double)M) : 0.0;
        f1 = f1 > 0.0 ? (f1 < (double)M ? f1 : (double)M) : 0.0;
        const ptrdiff_t i0 = (ptrdiff_t)f0, i1 = (ptrdiff_t)f1;
        const double dx = xb - xa;
        const int flat = fabs(dx) <= 1e-12;
        const double slope = flat ? 0.0 : (yb - ya) / dx;
        const double y_lo = vk_min(ya, yb), y_hi = vk_max(ya, yb);
        const double base = flat ? y_lo : ya;
        for (ptrdiff_t i = i0; i < i1; i++) {
            double y = base + slope * (grid[i] - xa);
            y = vk_min(vk_max(y, y_lo), y_hi);
            if (y < env[i]) env[i] = y;
        }
    }
}

/* One candidate (x7: q1, q2, H; K: the bulge direction) at nG scales G of S samples (shape
 * functions qf, pf): for each scale its V_p against H, over-dig, and total and design-inside
 * cut on the height field (m^2), written at stride `stride` apart (out[k * stride + g]). */
void vk_screen_row(const double *p, const double *x7, const double *K, const double *qf,
                   const double *pf, int S, const double *G, int nG, const vk_field *f,
                   double *out, ptrdiff_t stride)
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


/* trench.geometry._depth_below of N points (x, y; cap per point): how far each is inside the
 * material under the height field `surface` on the uniform grid (M points), up to its cap; the
 * same formulas, and the same window of columns (16 columns a class of reach) per point. */
void vk_depth_below(const double *grid, const double *surface, ptrdiff_t M, const double *x,
                    const double *y, const double *cap, ptrdiff_t N, double *out)
{
    const double x0 = grid[0], h = grid[1] - grid[0];
    const double top = (double)M - 1.000001;
    for (ptrdiff_t p = 0; p < N; p++) {
        double u = (x[p] - x0) / h;
        u = u > 0.0 ? (u < top ? u : top) : 0.0; /* NaN: 0, never an index out of the grid */
        const ptrdiff_t i = (ptrdiff_t)u;
        const double w = u - (double)i;
        const double vertical = surface[i] * (1.0 - w) + surface[i + 1] * w - y[p];
        if (!(vertical > 0.0)) {
            out[p] = 0.0;
            continue;
        }
        const double reach = vk_min(vertical, cap[p]);
        const double px = x[p], py = y[p];
        const double c = rint((px - x0) / h);
        const double cls = ceil(reach / (16.0 * h));
        if (!(cls >= 0.0 && cls < 1e6 && fabs(c) < 1e15)) {
            out[p] = reach; /* a NaN or an unbounded reach: no window to search */
            continue;
        }
        const ptrdiff_t col = (ptrdiff_t)c, k = 16 * (ptrdiff_t)cls;
        double best = INFINITY;
        for (ptrdiff_t j = col - k; j <= col + k; j++) {
            const ptrdiff_t cj = j < 0 ? 0 : (j > M - 1 ? M - 1 : j);
            const double dx = grid[cj] - px;
            const double dy = vk_max(surface[cj] - py, 0.0);
            best = vk_min(best, dx * dx + dy * dy);
        }
        out[p] = vk_min(sqrt(best), reach);
    }
}

/* numpy's einsum of a dot product of n contiguous doubles (sum_of_products_contig_contig_
 * outstride0_two on the X86_V2 baseline: two lanes, blocks of 8 taken last vector first, the
 * rest a vector at a time padded with zeros, the lanes added, the sum added to a zero output):
 * the same sum in the same order, so the result is numpy's bit for bit. */
static inline double vk_np_dot(const double *a, const double *b, ptrdiff_t n)
{
    double acc0 = 0.0, acc1 = 0.0;
    ptrdiff_t i = 0;
    for (; n - i >= 8; i += 8)
        for (int v = 3; v >= 0; v--) {
            acc0 = a[i + 2 * v] * b[i + 2 * v] + acc0;
            acc1 = a[i + 2 * v + 1] * b[i + 2 * v + 1] + acc1;
        }
    for (; i < n; i += 2) {
        acc0 = a[i] * b[i] + acc0;
        acc1 = (i + 1 < n ? a[i + 1] * b[i + 1] : 0.0 * 0.0) + acc1;
    }
    return 0.0 + (acc0 + acc1);
}

/* One iteration of trench.fit.FitMixin._fit_bulges's damped Gauss-Newton on one pair of end
 * poses, the numpy reference's operations in its order (libm's sin and cos are numpy's; theta_p
 * is libm's atan2, which decides only whether the angle is past a bound): base (n, 3) the joint
 * blend, pf (n,) the bulge's shape function, lengths (3,), edges (E, 3) the outline's
 * half-planes, jac0 (2, 3) and d_ent (2,) the entry direction's Jacobian at q1 and its part
 * 10 (q2 - q1); par: machine x, offset, theta_p's range lo and hi, the iteration. The state
 * (K, step, mu, cost, best, active) is updated; go is 1 where a step is to be solved, with its
 * system in A (3, 3) and rhs (3,) (A x = rhs, damped). Returns whether the pair is active. */
int vk_fit_iterate(const double *base, const double *pf, ptrdiff_t n, const double *lengths,
                   const double *edges, ptrdiff_t E, const double *jac0, const double *d_ent,
                   const double *par, double *K, double *step, double *mu, double *cost,
                   double *best, double *active, double *go, double *A, double *rhs)
{
    const double m = par[0], offset = par[1], tp_lo = par[2], tp_hi = par[3];
    const int it = (int)par[4];
    double AtA[9] = {0.0}, Atb[3] = {0.0, 0.0, 0.0};
    double rbuf[VK_FIT_MAX_SAMPLES];
    for (ptrdiff_t s = 0; s < n; s++) {
        const double *b = base + 3 * s;
        const double q0 = b[0] + pf[s] * K[0], q1 = b[1] + pf[s] * K[1], q2 = b[2] + pf[s] * K[2];
        const double phi[3] = {q0, q0 + q1, (q0 + q1) + q2};
        double sn[3], cs[3];
        for (int j = 0; j < 3; j++) {
            cs[j] = cos(phi[j]) * lengths[j];
            sn[j] = sin(phi[j]) * lengths[j];
        }
        const double x = ((cs[0] + cs[1]) + cs[2]) + m, y = (sn[0] + sn[1]) + sn[2];
        ptrdiff_t k = 0;
        double d = 0.0;
        for (ptrdiff_t e = 0; e < E; e++) {
            const double v = (edges[3 * e + 2] - edges[3 * e] * x) - edges[3 * e + 1] * y;
            if (e == 0 || v < d) {
                d = v;
                k = e;
            }
        }
        const double w = d < -0.003 ? 21.0 : 1.0;
        const double r = w * (d - offset);
        rbuf[s] = r;
        const double cx1 = sn[2] + sn[1], cy1 = cs[2] + cs[1];
        const double jx[3] = {-(cx1 + sn[0]), -cx1, -sn[2]};
        const double jy[3] = {cy1 + cs[0], cy1, cs[2]};
        const double pw = pf[s] * w;
        double J[3];
        for (int j = 0; j < 3; j++) J[j] = -(edges[3 * k] * jx[j] + edges[3 * k + 1] * jy[j]) * pw;
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) AtA[3 * i + j] += J[i] * J[j];
            Atb[i] += J[i] * r;
        }
    }
    for (int i = 0; i < 3; i++) Atb[i] = -Atb[i];
    double d0[2];
    for (int i = 0; i < 2; i++) d0[i] = d_ent[i] + vk_np_dot(jac0 + 3 * i, K, 3);
    const double ang = atan2(-d0[1], fabs(d0[0]));
    const double sx = d0[0] >= 0.0 ? 1.0 : -1.0;
    double pen = 0.0;
    for (int up = 0; up < 2; up++) {
        const double bound = up ? tp_hi - 0.02 : tp_lo + 0.02;
        const int hit = up ? ang > bound : ang < bound;
        const double cb = cos(bound), sb = sin(bound);
        double row[3];
        for (int j = 0; j < 3; j++) row[j] = hit ? 0.5 * (-jac0[3 + j] * cb - sx * jac0[j] * sb) : 0.0;
        const double g = -d0[1] * cb - fabs(d0[0]) * sb;
        const double rh = hit ? -0.5 * g : 0.0;
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) AtA[3 * i + j] += row[i] * row[j];
            Atb[i] += row[i] * rh;
        }
        pen += hit ? (0.5 * g) * (0.5 * g) : 0.0;
    }
    const double new_cost = vk_np_dot(rbuf, rbuf, n) + pen;
    const int was_active = *active != 0.0;
    const int worse = was_active && new_cost > *cost;
    if (worse) { /* the step made it worse: back off, damp harder */
        for (int j = 0; j < 3; j++) {
            K[j] = K[j] - 0.5 * step[j];
            step[j] = 0.5 * step[j];
        }
        *mu = *mu * 10.0;
    }
    const int better = was_active && !worse;
    if (better) {
        *cost = new_cost;
        for (int j = 0; j < 3; j++) best[j] = K[j];
    }
    int still = was_active;
    if (better && vk_np_dot(step, step, 3) < 1e-6 && it > 0) still = 0;
    *active = still ? 1.0 : 0.0;
    *go = (better && still) ? 1.0 : 0.0;
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) A[3 * i + j] = AtA[3 * i + j] + *mu * (i == j ? 1.0 : 0.0);
        rhs[i] = Atb[i] - *mu * K[i];
    }
    return still;
}

/* The damped 3 x 3 system A x = rhs of a fit's step (A (3, 3) row-major, symmetric positive
 * definite: the normal equations plus mu I) by Cholesky, trench.fit._solve_spd3's operations
 * in its order; x = 0 where a pivot is not positive or the answer is not finite. */
static void vk_solve_spd3(const double *A, const double *rhs, double *x)
{
    x[0] = x[1] = x[2] = 0.0;
    const double d0 = A[0];
    if (!(d0 > 0.0)) return;
    const double l00 = sqrt(d0);
    const double l10 = A[3] / l00, l20 = A[6] / l00;
    const double d1 = A[4] - l10 * l10;
    if (!(d1 > 0.0)) return;
    const double l11 = sqrt(d1);
    const double l21 = (A[7] - l20 * l10) / l11;
    const double d2 = (A[8] - l20 * l20) - l21 * l21;
    if (!(d2 > 0.0)) return;
    const double l22 = sqrt(d2);
    const double y0 = rhs[0] / l00;
    const double y1 = (rhs[1] - l10 * y0) / l11;
    const double y2 = ((rhs[2] - l20 * y0) - l21 * y1) / l22;
    const double x2 = y2 / l22;
    const double x1 = (y1 - l21 * x2) / l11;
    const double x0 = ((y0 - l10 * x1) - l20 * x2) / l00;
    if (!(isfinite(x0) && isfinite(x1) && isfinite(x2))) return;
    x[0] = x0;
    x[1] = x1;
    x[2] = x2;
}

/* trench.fit.FitMixin._fit_bulges on one pair of end poses: up to VK_FIT_ITERATIONS damped
 * Gauss-Newton iterations (vk_fit_iterate, each step solved by vk_solve_spd3) from K = 0, the
 * numpy loop's operations in its order; par (4,): machine x, offset, theta_p's range lo and hi.
 * Writes the best K evaluated (3,) and its cost. */
void vk_fit_bulges(const double *base, const double *pf, ptrdiff_t n, const double *lengths,
                   const double *edges, ptrdiff_t E, const double *jac0, const double *d_ent,
                   const double *par, double *best, double *cost)
{
    double K[3] = {0.0, 0.0, 0.0}, step[3] = {0.0, 0.0, 0.0}, mu = 1e-7, active = 1.0, go = 0.0;
    double A[9], rhs[3], sol[3];
    double par_it[5] = {par[0], par[1], par[2], par[3], 0.0};
    *cost = INFINITY;
    best[0] = best[1] = best[2] = 0.0;
    for (int it = 0; it < VK_FIT_ITERATIONS; it++) {
        par_it[4] = it;
        if (!vk_fit_iterate(base, pf, n, lengths, edges, E, jac0, d_ent, par_it, K, step, &mu,
                            cost, best, &active, &go, A, rhs))
            break;
        vk_solve_spd3(A, rhs, sol);
        if (go != 0.0) {
            for (int j = 0; j < 3; j++) {
                step[j] = sol[j];
                K[j] = K[j] + sol[j];
            }
        }
    }
}

/* trench.motion._Mover.poses of a rest-to-rest ruckig move: joint poses (n, 3) at n times from
 * each joint's seven constant-jerk pieces (tables (3, 5, 7): durations, jerk, and the
 * acceleration, velocity and position where each piece starts); the same formulas. */
void vk_move_poses(const double *tables, const double *times, ptrdiff_t n, double *out)
{
    for (int k = 0; k < 3; k++) {
        const double *t = tables + 35 * k, *jerk = t + 7, *acc = t + 14, *vel = t + 21,
                     *pos = t + 28;
        double starts[8];
        starts[0] = 0.0;
        double c = t[0];
        starts[1] = c;
        for (int i = 1; i < 7; i++) {
            c = c + t[i];
            starts[i + 1] = c;
        }
        for (ptrdiff_t s = 0; s < n; s++) {
            const double ts = times[s];
            int i = -1;
            for (int j = 0; j < 8; j++) i += starts[j] <= ts; /* searchsorted, side right */
            i = i < 0 ? 0 : (i > 6 ? 6 : i);
            const double dt = ts - starts[i];
            out[3 * s + k] = pos[i] + dt * (vel[i] + dt * (0.5 * acc[i] + dt * jerk[i] / 6.0));
        }
    }
}

/* trench.moves.MovesMixin._bucket_depth of n joint poses q (n, 3): each outline point
 * (outline (m, 2): along and normal in the bucket frame at the tip) placed as
 * trench.motion._Mover.bucket_xy places it, shifted by the machine's x, and its depth below
 * the height field (vk_depth_below, cap (m,) per outline point) into out (n, m); the same
 * formulas. Returns -1 where the scratch cannot be allocated, else 0. */
int vk_bucket_depth(const double *q, ptrdiff_t n, const double *lengths, const double *outline,
                    ptrdiff_t m, double machine_x, const double *grid, const double *surface,
                    ptrdiff_t M, const double *cap, double *out)
{
    double *buf = (double *)malloc(sizeof(double) * 3 * (size_t)(m > 0 ? m : 1));
    if (buf == NULL) return -1;
    double *xs = buf, *ys = buf + m, *caps = buf + 2 * m;
    for (ptrdiff_t j = 0; j < m; j++) caps[j] = cap[j];
    for (ptrdiff_t s = 0; s < n; s++) {
        const double *qs = q + 3 * s;
        const double p0 = qs[0], p1 = p0 + qs[1], p2 = p1 + qs[2];
        const double x = (lengths[0] * cos(p0) + lengths[1] * cos(p1)) + lengths[2] * cos(p2);
        const double y = (lengths[0] * sin(p0) + lengths[1] * sin(p1)) + lengths[2] * sin(p2);
        const double z = (qs[0] + qs[1]) + qs[2];
        const double c = cos(z), sn = sin(z);
        for (ptrdiff_t j = 0; j < m; j++) {
            const double a = outline[2 * j], b = outline[2 * j + 1];
            xs[j] = ((x + c * a) - sn * b) + machine_x;
            ys[j] = (y + sn * a) + c * b;
        }
        vk_depth_below(grid, surface, M, xs, ys, caps, m, out + m * s);
    }
    free(buf);
    return 0;
}
