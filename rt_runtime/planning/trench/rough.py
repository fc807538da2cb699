"""The network's digs (Yao Fig. 5: downward until the layer's floor, then backward): the
candidate grid through the PINN in one batch (or, with no network, a closed-form bulge per dig
type), screened on geometry with the fill on the material left, and chosen with a look-ahead
over what the layer still takes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rt_runtime import kinematics
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.candidates import (
    _CANDIDATES,
    _ENTRY_MIN_THICKNESS_M,
    _FILL_MARGIN,
    _N_ENTRY_X,
    _N_LOOKAHEAD,
    _N_RANKED,
    _N_SCALE_STEPS,
    _ROUGH_SPARE,
    _SCREEN_OVERDIG_M,
    Candidate,
)
from rt_runtime.planning.trench.digs import DigsMixin
from rt_runtime.planning.trench.geometry import (
    GRID_STEP_M,
    MIN_USEFUL_FRACTION,
    OVERDIG_LIMIT_M,
    FloatArray,
    _largest_scale_below,
    _sextic_shapes,
    runs,
)
from rt_runtime.planning.trench.plan import PlannedDig
from rt_runtime.planning.trench.state import Stage, _stage

# The sextic's bulge shape at mid-path: q(1/2) = q1 + (q2 - q1) / 2 + K pf(1/2), pf(1/2) = 1/64.
_SEXTIC_PF_MID = float(_sextic_shapes(3)[1][1])


class RoughMixin(DigsMixin):
    """A session's network digs (see the module)."""

    def _phase(self) -> DigType:
        """Fig. 5: downward until the depth is reached, then backward."""
        floor_y = self.layer_y if self.stage is Stage.ROUGH else self.bottom_y
        if (
            self.phase is DigType.DOWNWARD
            and float(np.min(self.surface)) <= floor_y + OVERDIG_LIMIT_M
        ):
            self.phase = DigType.BACKWARD
        return self.phase

    def _next_rough(self, remaining: Any, t0: float) -> PlannedDig | None:
        """The network's next dig above the profile layer (Fig. 5), filled on the material
        left, or None when none carries a full bucket there."""
        layer_left = self.layer_design.intersection(self.material)
        if float(layer_left.area) <= 0.005 * self.design_area:
            return None
        xe = self._rough_entries()
        if xe.size == 0:
            return None
        H = np.interp(xe, self.grid, self.surface)
        ranked = self._screen(xe, H)
        if not ranked and self.phase is DigType.DOWNWARD:
            self.phase = DigType.BACKWARD
            ranked = self._screen(xe, H)
        return self._first_plannable(ranked, remaining, t0)

    def _rough_entries(self) -> FloatArray:
        """Where the network's digs may enter (x, work-site frame): from the far edge of the
        material above the profile layer, and from the far end of each run of its bulk (where
        it is at least half its thickest), :data:`_N_ENTRY_X` of each 4 cm apart (scaled)
        towards the machine, within the entries' reach from where the machine stands and within the
        section."""
        s = self.planner.scale
        lo, hi = self.planner.entry_x_range
        m = self.machine_x
        x = self.grid
        t = self.surface - self._layer_floor
        sec = (x >= max(self.section_lo, m + lo)) & (x <= min(self.section_hi, m + hi))
        idx = np.flatnonzero((t > _ENTRY_MIN_THICKNESS_M * s) & sec)
        if not idx.size:
            return np.empty(0)
        edges = [float(x[idx[-1]])]
        # The far ends of the runs of bulk at least 3 cm long (scaled), farthest first.
        bulk = np.zeros(x.shape[0], dtype=bool)
        bulk[idx[t[idx] >= 0.5 * float(np.max(t[idx]))]] = True
        for i0, i1 in reversed(runs(bulk)):
            if (i1 - i0) * GRID_STEP_M >= 0.03 * s and float(x[i1 - 1]) < edges[-1] - 0.02 * s:
                edges.append(float(x[i1 - 1]))
        lo_x = float(x[idx[0]])
        step = 0.04 * s
        xs = [float(v) for e in edges for v in np.arange(e, lo_x - 1e-9, -step)[:_N_ENTRY_X]]
        return np.asarray(xs)

    @_stage("screen")
    def _screen(self, xe: FloatArray, H: FloatArray) -> list[Candidate]:
        """The best candidates of the phase's dig types, best first, entering at ``xe``
        (:meth:`_rough_entries`) where the surface is at ``H``."""
        kinds = [DigType.DOWNWARD] if self._phase() is DigType.DOWNWARD else list(DigType)
        found = [b for k in kinds for b in self._screen_kind(xe, H, k)]
        return sorted(found, key=lambda b: -b.score)[:_N_RANKED]

    def _screen_kind(self, xe: FloatArray, H: FloatArray, kind: DigType) -> list[Candidate]:
        """The best candidates of one dig type, best first, screened on their geometry.

        Every (entry, exit) pose of the grid goes through the network at once; the tip path of
        each answer is known before the kernel runs (the fill scales the bulge ``K`` along its
        direction and the retiming keeps the path), so each path is computed on a coarse grid
        of samples at a few bulge scales, and the fill's scale, V_p against H, the over-dig
        and the real cut on the height field are interpolated between them. Only the ranked
        few are planned for real (:meth:`_first_plannable`), and those are checked on the
        verifier's full grid.
        """
        arm = self.planner.arm
        cand = _CANDIDATES[kind]
        m = self.machine_x
        # Every (entry, exit) pose of the grid at once: entries (x, attitude) x exits
        # (length, rise, attitude); poses out of reach or limits are dropped.
        ea = np.radians(cand.entry_attitude_deg)
        n_x, n_a = xe.shape[0], ea.shape[0]
        qs, ok_s = arm.ik_many(np.repeat(xe - m, n_a), np.repeat(H, n_a), np.tile(ea, n_x))
        L, R, A = self.planner.exit_grid[kind]
        n_e, n_x = qs.shape[0], L.size
        ex = (np.repeat(xe, n_a)[:, None] - L[None, :]).ravel()
        ey = (np.repeat(H, n_a)[:, None] + R[None, :]).ravel()
        qe, ok_e = arm.ik_many(ex - m, ey, np.tile(A, n_e))
        X = np.empty((n_e * n_x, 7))
        X[:, 0:3] = np.repeat(qs, n_x, axis=0)
        X[:, 3:6] = qe
        X[:, 6] = np.repeat(np.repeat(H, n_a), n_x)
        ok = np.repeat(ok_s, n_x) & ok_e
        if self.planner.domain is not None:
            lo, hi = self.planner.domain[kind]
            ok &= np.all((lo <= X) & (hi >= X), axis=1)
        X = X[ok]
        if X.shape[0] == 0:
            return []
        if self.planner.pinn is not None:
            Y = self.planner.pinn.infer(kind, X)
            K = -Y[:, 0:3] * Y[:, 3:4] ** 6
            T = Y[:, 3]
        else:
            K, T = self._geometric_bulge(X, kind)
            keep = np.all(np.isfinite(K), axis=1)
            X, K, T = X[keep], K[keep], T[keep]
            if X.shape[0] == 0:
                return []
        G = self.planner.screen_c
        _, over, total, useful = self._screen_paths(X, K)
        # The fill on the material left: the largest bulge scale whose real cut stays inside
        # the bucket (V_max) and whose over-dig stays within the screening limit; kept when
        # that cut carries at least V_min (the fill rule).
        lo_area, hi_area = self._fill_band()
        c_cut = _largest_scale_below(total, hi_area * (1.0 - _FILL_MARGIN), G)
        c_over = _largest_scale_below(over, _SCREEN_OVERDIG_M, G)
        c = self._path_feasible_scale(X, K, np.minimum(c_cut, c_over), kind)
        r = np.arange(X.shape[0])
        kc = np.clip(np.searchsorted(G, c), 1, G.shape[0] - 1)
        w = np.clip((c - G[kc - 1]) / (G[kc] - G[kc - 1]), 0.0, 1.0)
        o, t, u = (a[r, kc - 1] * (1.0 - w) + a[r, kc] * w for a in (over, total, useful))
        min_useful = MIN_USEFUL_FRACTION * self.design_area
        good = np.flatnonzero(
            (c >= G[0]) & (o <= _SCREEN_OVERDIG_M) & (t >= lo_area * (1.0 + _FILL_MARGIN))
            & (u >= min_useful)
        )  # fmt: skip
        u, t, cs = u[good], t[good], c[good]
        score = u - 2.0 * (t - u)
        best = np.argsort(-score, kind="stable")[:_N_LOOKAHEAD]
        if self.stage is Stage.ROUGH and best.shape[0] > 1:
            # Look ahead: the fewest full digs the material above the layer still takes after
            # the dig, then the fullest bucket, then the score.
            rest = [
                self._rest_estimate(
                    self._screened_surface_after(X[good[b]], K[good[b]], float(cs[b]))
                )
                for b in best
            ]
            # A dig that leaves part of the layer no bucket fills is not taken: the layer's
            # columns would have to take it under-filled.
            order = sorted(
                (i for i in range(best.shape[0]) if rest[i][1] == 0),
                key=lambda i: (rest[i][0], -t[best[i]], -score[best[i]]),
            )
            best = best[order]
        best = best[:_N_RANKED]
        return [
            Candidate(
                kind=kind,
                x7=X[good[b]],
                useful_m2=float(u[b]),
                total_m2=float(t[b]),
                score=float(score[b]),
                K_rad=K[good[b]],
                c=float(cs[b]),
                T_s=float(T[good[b]]),
            )
            for b in best
        ]

    def _geometric_bulge(self, X: FloatArray, kind: DigType) -> tuple[FloatArray, FloatArray]:
        """The geometric screening's bulge of candidates ``X`` ``(N, 7)``: ``K`` ``(N, 3)``
        moving the tip at mid-path by the dig type's target (``TrenchPlanner.geometric_bulge``)
        through the arm's Jacobian at the chord's mid pose (NaN where it is singular), and the
        middle of the time range as ``T`` ``(N,)`` (the fill retimes the path)."""
        q1, q2 = X[:, 0:3], X[:, 3:6]
        jac = kinematics.jacobian(self.rig, 0.5 * (q1 + q2))
        target = self.planner.geometric_bulge[kind] / _SEXTIC_PF_MID
        K = np.full(q1.shape, np.nan)
        ok = np.abs(np.linalg.det(jac)) > 1e-9
        K[ok] = np.linalg.solve(jac[ok], np.broadcast_to(target, (int(ok.sum()), 3))[..., None])[
            ..., 0
        ]
        t_lo, t_hi = self.planning.t_min_s, self.planning.t_max_s
        return K, np.full(X.shape[0], 0.5 * (t_lo + t_hi))

    def _path_feasible_scale(
        self, X: FloatArray, K: FloatArray, c_top: FloatArray, kind: DigType
    ) -> FloatArray:
        """The largest bulge scale ``<= c_top`` (per candidate row of ``X`` ``(N, 7)`` of dig
        type ``kind`` with
        bulge ``K`` ``(N, 3)``) at which the path-only limits hold: every joint within its
        range at the screening samples (each angle is linear in the scale: an interval in
        closed form) and theta_p, the entry direction ``J(q1) (10 D + c K)``, in the dig
        type's range (on a grid of scales 1/40 apart below ``c_top``). 0 where none does."""
        arm = self.planner.arm
        qf, pf = self.planner.screen_qf, self.planner.screen_pf
        q1, q2 = X[:, 0:3], X[:, 3:6]
        base = q1[:, None] + qf[None, :, None] * (q2 - q1)[:, None]
        slope = pf[None, :, None] * K[:, None, :]
        margin = 1e-6
        lo_q = arm.q_min + margin - base
        hi_q = arm.q_max - margin - base
        with np.errstate(divide="ignore", invalid="ignore"):
            up = np.where(slope > 0, hi_q / slope, np.where(slope < 0, lo_q / slope, np.inf))
            down = np.where(slope > 0, lo_q / slope, np.where(slope < 0, hi_q / slope, -np.inf))
        inside = np.all((lo_q <= 0.0) | (slope != 0.0), axis=(1, 2)) & np.all(
            (hi_q >= 0.0) | (slope != 0.0), axis=(1, 2)
        )
        c_hi = np.where(inside, np.min(up, axis=(1, 2)), -np.inf)
        c_lo = np.max(down, axis=(1, 2))
        # theta_p on a grid of scales from c_top down (the entry direction is linear in c).
        jac = kinematics.jacobian(self.rig, q1)
        ux, uy = np.einsum("nij,nj->in", jac[:, :2], 10.0 * (q2 - q1))
        vx, vy = np.einsum("nij,nj->in", jac[:, :2], K)
        top = np.minimum(c_top, c_hi)
        steps = np.arange(_N_SCALE_STEPS + 1) / _N_SCALE_STEPS
        # From top down to 0 (no scale where top <= 0, -inf where no scale is inside).
        cg = np.where(top > 0.0, top, 0.0)[:, None] * (1.0 - steps[None, :])
        ang = np.arctan2(-(uy[:, None] + cg * vy[:, None]), np.abs(ux[:, None] + cg * vx[:, None]))
        tp_lo, tp_hi = (float(v) for v in oneshot.theta_p_range(self.planning, int(kind)))
        ok = (ang >= tp_lo + 1e-3) & (ang <= tp_hi - 1e-3) & (cg >= c_lo[:, None])
        first = np.argmax(ok, axis=1)
        found = ok[np.arange(X.shape[0]), first]
        return np.where(found & (top > 0.0), cg[np.arange(X.shape[0]), first], 0.0)

    def _screened_surface_after(self, x7: FloatArray, K: FloatArray, c: float) -> FloatArray:
        """The height field after a screened dig (poses and H ``x7``, bulge ``K`` scaled by
        ``c``), its path on the screening's samples."""
        pl = self.planner
        q1, q2 = x7[0:3], x7[3:6]
        q = q1 + pl.screen_qf[:, None] * (q2 - q1) + c * pl.screen_pf[:, None] * K
        px, py = pl.arm.tip_xy(q)
        path = np.stack([px + self.machine_x, py], axis=1)
        after: FloatArray = np.minimum(self.surface, self._envelope(path, self.grid))
        return after

    def _screen_paths(self, X: FloatArray, K: FloatArray) -> FloatArray:
        """The screening geometry of candidates ``X`` ``(N, 7)`` with bulge directions ``K``
        ``(N, 3)``: ``(4, N, G)``, for each of the G screening scales c the path's V_p against
        H, its over-dig (:meth:`_overdig_many`) and the total and design-inside cut on the
        height field (:meth:`_cut_estimate`), all m or m^2 on the coarse samples.

        The C kernel (``Kernel.screen``, ``kernel/trench.c``) computes it where the verifier runs
        on C (~0.3 ms for ~400 candidates against ~1.7 ms); :meth:`_screen_paths_numpy` is the
        reference and the fallback.
        """
        kernel = self.planner.geo_kernel
        layer = self.stage is Stage.ROUGH
        if kernel is None:
            return self._screen_paths_numpy(X, K, layer)
        pl = self.planner
        out = np.empty((4, X.shape[0], pl.screen_c.shape[0]))
        kernel.screen(
            np.ascontiguousarray(X),
            np.ascontiguousarray(K),
            pl.screen_shapes,
            pl.screen_c,
            *self._geometry_args(layer),
            out,
        )
        return out

    def _screen_paths_numpy(self, X: FloatArray, K: FloatArray, layer: bool = False) -> FloatArray:
        """:meth:`_screen_paths` in numpy (the reference of the C kernel; ``layer``: judged
        against the layer's design, :meth:`_design_arrays`)."""
        arm = self.planner.arm
        m = self.machine_x
        # Paths at the screening scales: q(s) = q1 + qf(s) (q2 - q1) + c pf(s) K.
        qf, pf = self.planner.screen_qf, self.planner.screen_pf
        base = X[:, None, 0:3] + qf[None, :, None] * (X[:, None, 3:6] - X[:, None, 0:3])
        G = self.planner.screen_c
        bulge = pf[None, :, None] * K[:, None, :]
        q = base[:, None] + G[None, :, None, None] * bulge[:, None]
        x, y = arm.tip_xy(q)
        x += m
        vp = oneshot.excavated_area_m2(x - m, y, X[:, 6, None])
        over = self._overdig_many_numpy(np.stack([x, y], axis=-1), layer)
        total, useful = self._cut_estimate(x, y, layer)
        return np.stack([vp, over, total, useful])

    def _rest_estimate(self, surface: FloatArray) -> tuple[int, int]:
        """What the current layer still takes were the surface ``surface``: per run of its
        material thicker than 1 cm (scaled), the full buckets its area fills; and the runs
        that fill none but are too big for the walls' digs and the finishing passes to take
        (a quarter of V_min or more): ``(buckets, awkward runs)``."""
        s = self.planner.scale
        lo_a, hi_a = self._fill_band()
        x = self.grid
        t = np.clip(surface - self._layer_floor, 0.0, None)
        t[(x < self.section_lo) | (x > self.section_hi)] = 0.0
        buckets = awkward = 0
        for i0, i1 in runs(t > 0.01 * s):
            area = float(np.sum(t[i0:i1])) * GRID_STEP_M
            if area < 0.25 * lo_a:
                continue
            n = math.ceil(area / (hi_a * (1.0 - _ROUGH_SPARE)))
            if area / n >= lo_a * (1.0 + _FILL_MARGIN):
                buckets += n
            else:
                awkward += 1
        return buckets, awkward
