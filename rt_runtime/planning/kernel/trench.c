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

