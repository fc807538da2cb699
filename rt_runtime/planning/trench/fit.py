"""Digs fitted along the design's outline: the sextic's end attitudes from a table and its bulge
by Gauss-Newton on the inward distances to the outline (a wall, the bottom, a layer's floor),
shifted inwards just enough for the over-dig limit, retimed and verified like every dig."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rt_runtime import kinematics
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.candidates import Candidate, difference_lowered
from rt_runtime.planning.trench.cycles import CyclesMixin
from rt_runtime.planning.trench.geometry import (
    GRID_STEP_M,
    JOINED_THETA_P_RAD,
    MIN_USEFUL_FRACTION,
    OVERDIG_LIMIT_M,
    FloatArray,
    _Pass,
    _total_without_volume,
)
from rt_runtime.planning.trench.state import _stage
from rt_runtime.planning.verify import (
    N_OUT,
    pack_inputs,
)

# Inward shifts of a profile pass's line tried in turn where the adaptive shift fails (m).
_PASS_OFFSETS_M = (0.0, 0.002, 0.004, 0.007)

# Profile fits shifted adaptively (the best by cost), and how far outside the outline the
# shifted path's farthest sample may lie (m; the over-dig limit is 5 mm).
_N_FIT_SHIFTS = 4

_FIT_OUTSIDE_M = 0.0025
#: Largest adaptive shift of a profile fit (scale model, m): a fit that needs more is not used.
_FIT_SHIFT_MAX_M = 0.008

# A profile fit this good (least-squares cost, m^2: ~1 mm RMS) ends the search of starts.
_GOOD_FIT_COST = 2e-4

# Samples of a profile pass's path in its fit.
_FIT_SAMPLES = 41

# Longest straight profile pass (scale model, m).
_PASS_LENGTH_M = 0.30

# Damped Gauss-Newton iterations of a profile fit (the C kernel's VK_FIT_ITERATIONS).
_FIT_ITERATIONS = 9

# A fitted profile dig to check: end poses, bulge (rad) and the fit's cost (m^2).
_Try = tuple[FloatArray, FloatArray, FloatArray, float]

#: How far the last dig's exit may lie from a profile dig's start for the dig to start there
#: instead, joined to it (scale model, m; :meth:`FitMixin._join_at`).
_JOIN_REACH_M = 0.02


#: A carried dig's start attitudes are this much (deg) more curled than the most that holds
#: the load (:meth:`~rt_runtime.planning.trench.cycles.CyclesMixin.carry_attitude_max`): the
#: moves into the entry run in joint space between poses at the entry's attitude, and the
#: attitude strays between them, past an entry at the limit itself (R8s).
_CARRY_ENTRY_MARGIN_DEG = 5.0


#: A joined profile dig is taken where it lowers the difference of dug and design (R8l) by no
#: less than the same dig from its own start, less this fraction of the design's area; where
#: it fills the bucket a finishing pass began (a dig saved), less the larger fraction.
_JOIN_DIFFERENCE_SLACK = 0.001
_JOIN_SAVING_SLACK = 0.003


@dataclass(frozen=True, slots=True)
class _Join:
    """A profile dig being fitted to continue the last dig's bucket: its exit pose ``q_rad``
    (arm frame) as the start, and the material ``bucket_m3`` (m^3) already in the bucket; or
    (``carried``) from the dig's own start, the bucket carried there."""

    q_rad: FloatArray
    bucket_m3: float
    carried: bool = False


@dataclass(frozen=True, slots=True)
class _FitMemo:
    """What :meth:`FitMixin._fit_profile_from` computed in one fit context on one material:
    bulges by offset and end poses, candidates by end poses, bulge and cost, results by ends,
    attitude table and fixed shifts."""

    fits: dict[bytes, list[tuple[float, FloatArray] | None]] = field(default_factory=dict)
    candidates: dict[bytes, Candidate | None] = field(default_factory=dict)
    results: dict[tuple[Any, ...], Candidate | None] = field(default_factory=dict)


def _solve_spd3(A: FloatArray, rhs: FloatArray) -> FloatArray:
    """``x`` ``(P, 3)`` of the damped 3 x 3 systems ``A x = rhs`` (``A`` ``(P, 3, 3)``
    symmetric positive definite: a fit's normal equations plus mu I) by Cholesky, written out
    so that the C kernel's ``vk_solve_spd3`` does the same operations in the same order; 0
    where a pivot is not positive or the answer is not finite."""
    with np.errstate(divide="ignore", invalid="ignore"):
        d0 = A[:, 0, 0]
        l00 = np.sqrt(d0)
        l10, l20 = A[:, 1, 0] / l00, A[:, 2, 0] / l00
        d1 = A[:, 1, 1] - l10 * l10
        l11 = np.sqrt(d1)
        l21 = (A[:, 2, 1] - l20 * l10) / l11
        d2 = (A[:, 2, 2] - l20 * l20) - l21 * l21
        l22 = np.sqrt(d2)
        y0 = rhs[:, 0] / l00
        y1 = (rhs[:, 1] - l10 * y0) / l11
        y2 = ((rhs[:, 2] - l20 * y0) - l21 * y1) / l22
        x2 = y2 / l22
        x1 = (y1 - l21 * x2) / l11
        x0 = ((y0 - l10 * x1) - l20 * x2) / l00
    x = np.stack([x0, x1, x2], axis=1)
    ok = (d0 > 0.0) & (d1 > 0.0) & (d2 > 0.0) & np.all(np.isfinite(x), axis=1)
    return np.where(ok[:, None], x, 0.0)


class FitMixin(CyclesMixin):
    """A session's digs fitted along the design's outline (see the module)."""

    #: The last dig's exit and its bucket's content where the next dig may continue it
    #: (:meth:`~rt_runtime.planning.trench.session.TrenchSession.record`), else None.
    joinable: tuple[FloatArray, float] | None = None
    #: Set while a profile dig is fitted from the joined exit, or with the last dig's bucket
    #: carried to its own start (:meth:`_fit_profile`).
    _joining: _Join | None = None
    #: The fits made on one material (:meth:`_fits_on_material`): the height field, the
    #: polygon and the machine's position they were made for, and per fit context (dig type,
    #: outline, joined start, good cost) the bulges fitted, the candidates checked and the
    #: results of :meth:`_fit_profile_from`.
    _fits_kept: tuple[Any, Any, float, dict[tuple[Any, ...], _FitMemo]] | None = None

    def _bottom_passes(self, far: tuple[float, float], near: tuple[float, float]) -> list[_Pass]:
        """Backward passes along the straight line from ``far`` to ``near`` (the bottom, or a
        layer): a sextic follows a straight line within a few mm over ~0.3 m (scale model), so
        a longer line is cut in equal pieces, far to near, each starting 2 mm up so that it
        enters descending (theta_p >= 0)."""
        lift = np.array([0.0, 0.002])
        n = max(1, math.ceil((far[0] - near[0]) / (_PASS_LENGTH_M * self.planner.scale)))
        a, b = np.asarray(far), np.asarray(near)
        cuts = [a + (b - a) * k / n for k in range(n + 1)]
        atts = ((-110.0, -135.0), (-150.0, -175.0))
        return [(DigType.BACKWARD, np.array([cuts[k] + lift, cuts[k + 1]]), atts) for k in range(n)]

    def _fit_pass(
        self,
        kind: DigType,
        poly: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
        offsets: tuple[float, ...] | None = None,
    ) -> Candidate | None:
        """Fit one profile pass along ``poly`` (work-site frame): 2 points, a straight line,
        or more, a convex polyline (the bottom's end and a wall, say); each segment a
        half-plane, inwards towards the design's centroid (:meth:`_fit_profile`; ``offsets``
        its fixed shifts, :data:`_PASS_OFFSETS_M` by default)."""
        pts = np.asarray(poly, dtype=np.float64)
        a, b = pts[0], pts[-1]
        on_bottom = (
            len(pts) == 2
            and abs(b[1] - self.bottom_y) < 1e-9
            and abs(a[1] - self.bottom_y) <= 0.0025
        )
        rows = []
        for p0, p1 in itertools.pairwise(pts):
            normal = self._inward_normal(p0, p1)
            # Outward normal and offset: inside is -normal . p <= -normal . p0.
            rows.append([-normal[0], -normal[1], -float(normal @ p0)])
        edge = np.array(rows)
        shifts = _PASS_OFFSETS_M if offsets is None else offsets
        found = self._fit_profile(kind, a, b, edge, atts, shifts)
        if on_bottom:
            # Along the bottom with the start lifted to enter descending, the tilted line
            # through the lifted start leaves up to 2 mm (4 % of a 0.024 m trench's design):
            # fitted to the bottom itself as well, the one that removes more design material
            # is kept.
            flat = self._fit_profile(kind, a, b, self._walls[[2]], atts, shifts)
            if flat is not None and (found is None or self._flat_kept(found, flat)):
                found = flat
        return found

    def _flat_kept(self, tilted: Candidate, flat: Candidate) -> bool:
        """Whether the bottom pass fitted to the bottom itself (``flat``) replaces the one
        along the tilted line (``tilted``): where it removes more design material; but a flat
        pass from its own start replaces a joined tilted one only where it lowers the
        difference of dug and design by more than the joined dig's slack
        (:meth:`_join_slack`), as the joined dig was chosen over its own start."""
        if tilted.joined and not flat.joined:
            return difference_lowered(flat) - self._join_slack() > difference_lowered(tilted)
        return flat.useful_m2 > tilted.useful_m2

    def _inward_normal(self, a: FloatArray, b: FloatArray) -> FloatArray:
        """The unit normal of the segment ``a``-``b`` (work-site frame) that points towards
        the design's centroid."""
        seg = b - a
        normal: FloatArray = np.array([-seg[1], seg[0]]) / math.hypot(seg[0], seg[1])
        c = self.design.centroid
        if (c.x - a[0]) * normal[0] + (c.y - a[1]) * normal[1] < 0.0:
            normal = -normal
        return normal

    @_stage("passes")
    def _fit_profile(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        edges: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
        offsets: tuple[float, ...],
        good_cost: float | None = None,
    ) -> Candidate | None:
        """Fit a profile dig from ``a`` to ``b`` (work-site frame) along the boundary of the
        half-planes ``edges`` (rows ``(nx, ny, c)``, unit outward normal, inside where
        ``nx x + ny y <= c``; a convex piece of the design's outline: a wall, the bottom, or
        a wall and the bottom).

        For each pair of end attitudes of ``atts`` the sextic's path is linear in its bulge
        ``K`` in joint space, so the inward distances of the path samples from the outline
        (the least over the half-planes, exact for a convex outline) are fitted in ``K`` by
        Gauss-Newton (:meth:`_fit_bulges`, every pair at once); a pair whose fit
        leaves the joint limits or the theta_p range is skipped. The first pair that fits
        within ``good_cost`` (m^2 on 101 samples; :data:`_GOOD_FIT_COST`, ~1 mm RMS, by
        default), or else the best, is taken; the outline
        is shifted inwards by ``offsets`` in turn (the ends with it, along the inward normal
        of the half-plane they lie on) until the over-dig limit holds. Returns the candidate
        of :meth:`_pass_candidate` with the fit's RMS distance (``fit_rms_m``), or None.

        Where the last dig may be continued and its exit lies within :data:`_JOIN_REACH_M`
        (scaled) of ``a`` (:meth:`_join_at`), the dig is also fitted from that exit as its
        start (joined: the bucket's content counts toward its fill, :class:`Candidate`
        ``bucket_m3``; adaptive shifts only; fitted to ``edges`` and the design's walls and
        bottom together, since a start it cannot choose may carry the path past its end into
        a wall), and the joined dig is taken where it lowers
        the difference of dug and design within :data:`_JOIN_DIFFERENCE_SLACK` (or
        :data:`_JOIN_SAVING_SLACK`) of the design of what the dig from its own start does.
        """
        join = self._join_at(a, b)
        if join is not None:
            self._joining = join
            try:
                # Adaptive shifts only, here and for the comparison: a joined fit that needs
                # the fixed ones is not worth their time.
                joined = self._fit_profile_from(
                    kind, a, b, np.vstack([edges, self._walls]), atts, (), good_cost
                )
            finally:
                self._joining = None
            if joined is not None:
                own = self._fit_profile_from(kind, a, b, edges, atts, (), good_cost)
                slack = self._join_slack()
                if own is not None:
                    if difference_lowered(joined) >= difference_lowered(own) - slack:
                        return joined
                    return self._carried_fit(kind, a, b, edges, atts, (), good_cost) or own
                # Nothing to compare with: the joined dig is taken where it leaves no more of
                # the design along its line than the slack (a start above the line it cannot
                # lower leaves a strip along it).
                if self._design_left_along(a, b) - joined.useful_m2 <= slack:
                    return joined
        carried = self._carried_fit(kind, a, b, edges, atts, offsets, good_cost)
        if carried is not None:
            return carried
        return self._fit_profile_from(kind, a, b, edges, atts, offsets, good_cost)

    def _join_slack(self) -> float:
        """How much less a joined dig may lower the difference of dug and design than the same
        dig from its own start and still be taken (m^2): :data:`_JOIN_DIFFERENCE_SLACK` of the
        design, or :data:`_JOIN_SAVING_SLACK` where the bucket it continues is a finishing
        pass's (a cycle saved, and a pass where the bucket stays light)."""
        saves = bool(self.digs) and self.digs[-1].finishing
        return (_JOIN_SAVING_SLACK if saves else _JOIN_DIFFERENCE_SLACK) * self.design_area

    def _carried_fit(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        edges: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
        offsets: tuple[float, ...],
        good_cost: float | None,
    ) -> Candidate | None:
        """:meth:`_fit_profile_from` with the last dig's light bucket carried to the dig's own
        start (:meth:`_carry_from`; its load counts toward the fill and the bucket's room), the
        fit's start and end poses at attitudes that hold the load (:meth:`holds_load`), the
        start :data:`_CARRY_ENTRY_MARGIN_DEG` more curled than the least that does; None
        where the bucket may not be carried or no such fit plans. The moves there are planned
        and checked when the dig is (:meth:`_carry_cycle`)."""
        carry = self._carry_from()
        if carry is None:
            return None
        # The attitude tables' ends clipped to the attitudes that hold the load, the start's
        # with a margin for the moves into it.
        most = math.degrees(self.carry_attitude_max())
        if any(min(v) > most for v in atts):
            return None
        enter = most - _CARRY_ENTRY_MARGIN_DEG
        held = (
            (min(atts[0][0], enter), min(atts[0][-1], enter)),
            (min(atts[1][0], most), min(atts[1][-1], most)),
        )
        self._joining = carry
        try:
            found = self._fit_profile_from(kind, a, b, edges, held, offsets, good_cost)
        finally:
            self._joining = None
        if found is None or not self.holds_load(np.reshape(found.x7[:6], (2, 3))):
            return None
        return found

    def _carry_from(self) -> _Join | None:
        """The last dig's bucket to carry to the next dig's own start: where the session
        allows continuing it (:attr:`joinable`), the bucket is below the fill band (a light
        bucket: a full one is dumped) and holds no more than :meth:`carry_load_max_m3`, and
        the exit's attitude holds its load; else None."""
        if self.joinable is None:
            return None
        q, bucket = self.joinable
        if bucket <= 0.0 or bucket / self.width_m >= self._fill_band()[0]:
            return None
        if bucket > self.carry_load_max_m3():
            return None
        if not self.holds_load(np.asarray(q, dtype=np.float64)[None]):
            return None
        return _Join(np.asarray(q, dtype=np.float64), bucket, carried=True)

    def _design_left_along(self, a: FloatArray, b: FloatArray) -> float:
        """The design material left (m^2, on the height field) between the abscissae of
        ``a`` and ``b`` (work-site frame)."""
        lo, hi = sorted((float(a[0]), float(b[0])))
        span = (self.grid >= lo) & (self.grid <= hi)
        left = np.clip(self.surface[span] - self.design_floor[span], 0.0, None)
        return float(np.sum(left)) * GRID_STEP_M

    def _joinable_exit(self) -> FloatArray | None:
        """The tip at the exit of the dig the next may continue (:attr:`joinable`; work-site
        frame, m), None where none may be continued."""
        if self.joinable is None:
            return None
        x, y = self.planner.arm.tip_xy(self.joinable[0])
        return np.array([float(x) + self.machine_x, float(y)])

    def _join_at(self, a: FloatArray, b: FloatArray | None = None) -> _Join | None:
        """The last dig's exit as the start of a dig that begins at ``a`` (and ends at ``b``,
        work-site frame), where the session allows continuing it (:attr:`joinable`), the
        exit's tip lies within :data:`_JOIN_REACH_M` (scaled) of ``a`` and the material above
        the segment ``a``-``b`` (on the height field) is not above 1.25 times the bucket's
        room; else None."""
        exit_ = self._joinable_exit()
        if exit_ is None or self.joinable is None:
            return None
        q, bucket = self.joinable
        gap = math.hypot(float(exit_[0] - a[0]), float(exit_[1] - a[1]))
        if gap > _JOIN_REACH_M * self.planner.scale:
            return None
        if b is not None and abs(float(b[0]) - float(a[0])) > 1e-9:
            lo, hi = sorted((float(a[0]), float(b[0])))
            span = (self.grid >= lo) & (self.grid <= hi)
            line = float(a[1]) + (self.grid[span] - float(a[0])) * (
                (float(b[1]) - float(a[1])) / (float(b[0]) - float(a[0]))
            )
            above = float(np.sum(np.clip(self.surface[span] - line, 0.0, None))) * GRID_STEP_M
            if above > 1.25 * (self.v_max_m3 - bucket) / self.width_m:
                return None
        return _Join(q, bucket)

    def _fit_profile_from(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        edges: FloatArray,
        atts: tuple[tuple[float, ...], tuple[float, ...]],
        offsets: tuple[float, ...],
        good_cost: float | None,
    ) -> Candidate | None:
        """:meth:`_fit_profile`'s fit from its own start, or from the joined exit while
        :attr:`_joining` is set."""
        arm = self.planner.arm
        qf, pf = self.planner.fit_qf, self.planner.fit_pf
        margin = math.radians(0.5)
        lo_q, hi_q = arm.q_min + margin, arm.q_max - margin
        tp_lo, tp_hi = self._theta_p_range(kind)
        good = (_GOOD_FIT_COST if good_cost is None else good_cost) * qf.shape[0] / 101.0

        def inward(p: FloatArray) -> FloatArray:
            k = int(np.argmin(edges[:, 2] - edges[:, 0:2] @ p))
            return -edges[k, 0:2]

        n_a, n_b = inward(a), inward(b)
        # Fits and candidates by their inputs, kept while the material is the same: the fixed
        # shifts start with the adaptive search's unshifted fit, and a dig's choice fits the
        # same line more than once (joined and alone, the column's ends of each try).
        memo = self._fits_on_material(kind, edges, good)
        key_r = (a.tobytes(), b.tobytes(), atts, offsets)
        if key_r in memo.results:
            return memo.results[key_r]
        fits_seen = memo.fits
        candidates_seen = memo.candidates

        def first_planned(tries: list[_Try]) -> Candidate | None:
            """The first of ``tries`` that plans, in their order: the first alone (it most
            often does), the rest checked at once (:meth:`_checked_fits`)."""
            for chunk in (tries[:1], tries[1:]):
                keys = [
                    b"".join((q1.tobytes(), q2.tobytes(), K.tobytes(), np.float64(c).tobytes()))
                    for q1, q2, K, c in chunk
                ]
                new: dict[bytes, _Try] = {}
                for key, t in zip(keys, chunk, strict=True):
                    if key not in candidates_seen:
                        new.setdefault(key, t)
                if new:
                    got = self._checked_fits(kind, list(new.values()), qf.shape[0])
                    candidates_seen.update(zip(new, got, strict=True))
                for key in keys:
                    if candidates_seen[key] is not None:
                        return candidates_seen[key]
            return None

        def fitted(
            q1s: list[FloatArray], q2s: list[FloatArray], offset: float
        ) -> list[tuple[float, FloatArray] | None]:
            """The bulges fitted for pairs of end poses ``q1s[i]``, ``q2s[i]`` (all at once),
            with their costs; None for a pair outside the joint limits or theta_p's range."""
            if not q1s:
                return []
            q1, q2 = np.asarray(q1s), np.asarray(q2s)
            key = b"".join((np.float64(offset).tobytes(), q1.tobytes(), q2.tobytes()))
            if key not in fits_seen:
                fits_seen[key] = fit_pairs(q1, q2, offset)
            return fits_seen[key]

        def fit_pairs(
            q1: FloatArray, q2: FloatArray, offset: float
        ) -> list[tuple[float, FloatArray] | None]:
            base = q1[:, None, :] + qf[None, :, None] * (q2 - q1)[:, None, :]
            K, cost = self._fit_bulges(base, q1, q2, edges, offset, kind)
            q = base + pf[None, :, None] * K[:, None, :]
            ok = np.all((q >= lo_q) & (q <= hi_q), axis=(1, 2))
            # theta_p: the entry direction J(q1) (10 D + K) in the type's range.
            jac = kinematics.jacobian(self.rig, q1)[:, :2]
            d0 = np.einsum("pij,pj->pi", jac, 10.0 * (q2 - q1) + K)
            ang = np.arctan2(-d0[:, 1], np.abs(d0[:, 0]))
            ok &= (ang >= tp_lo + 0.01) & (ang <= tp_hi - 0.01)
            return [(float(cost[i]), K[i]) if ok[i] else None for i in range(q1.shape[0])]

        # Every table pair fitted on the outline itself; the best few shifted inwards just
        # enough that the path's farthest sample outside the outline is _FIT_OUTSIDE_M out
        # (a least-squares path crosses the outline both ways), and refitted.
        mid = [
            tuple(dict.fromkeys((v[0], v[-1], *np.linspace(v[0], v[-1], 5)[1:-1].tolist())))
            for v in atts
        ]
        found = self._fit_shifted(kind, a, b, n_a, n_b, mid, edges, fitted, first_planned)
        # The fixed shifts in turn where the adaptive one found nothing.
        for offset in offsets if found is None else ():
            a_s = a + offset * n_a
            b_s = b + offset * n_b
            starts = [self._starts(a_s, mid[0]), self._pass_pose(b_s, mid[1])]
            pairs = [(qs, qe) for qs in starts[0] for qe in starts[1]]
            results = fitted([p[0] for p in pairs], [p[1] for p in pairs], offset)
            # Table pairs that fit well first, in their order; the others by cost.
            good_fits: list[_Try] = []
            fits: list[_Try] = []
            for (q1, q2), got in zip(pairs, results, strict=True):
                if got is not None:
                    cost, K = got
                    (good_fits if cost < good else fits).append((q1, q2, K, cost))
            found = first_planned(good_fits + sorted(fits, key=lambda f: f[3]))
            if found is not None:
                break
        memo.results[key_r] = found
        return found

    def _fits_on_material(self, kind: DigType, edges: FloatArray, good: float) -> _FitMemo:
        """What :meth:`_fit_profile_from` computed for fits of ``kind`` to ``edges`` (good cost
        ``good``) from the same start (its own, or the joined or carried bucket's) on this
        material: the height field, the polygon and the machine's position it was computed
        for (each replaced, never changed in place, when the material or the stand changes).
        A new material drops all of it."""
        kept = self._fits_kept
        if (
            kept is None
            or kept[0] is not self.surface
            or kept[1] is not self.material
            or kept[2] != self.machine_x
        ):
            kept = (self.surface, self.material, self.machine_x, {})
            self._fits_kept = kept
        j = self._joining
        start = None
        if j is not None:
            start = (np.asarray(j.q_rad, dtype=np.float64).tobytes(), j.bucket_m3, j.carried)
        return kept[3].setdefault((int(kind), edges.tobytes(), start, good), _FitMemo())

    def _fit_shifted(
        self,
        kind: DigType,
        a: FloatArray,
        b: FloatArray,
        n_a: FloatArray,
        n_b: FloatArray,
        table: list[tuple[float, ...]],
        edges: FloatArray,
        fitted: Callable[
            [list[FloatArray], list[FloatArray], float], list[tuple[float, FloatArray] | None]
        ],
        first_planned: Callable[[list[_Try]], Candidate | None],
    ) -> Candidate | None:
        """:meth:`_fit_profile`'s adaptive shift on one attitude table: every pair fitted on
        the outline itself (``fitted`` at offset 0), the best :data:`_N_FIT_SHIFTS` by cost
        shifted inwards (the ends along their inward normals ``n_a``, ``n_b``) just enough
        that the path's farthest sample outside the outline is :data:`_FIT_OUTSIDE_M` out,
        refitted there, and the first that plans returned (``first_planned``)."""
        arm = self.planner.arm
        m = self.machine_x
        starts = [self._starts(a, table[0]), self._pass_pose(b, table[1])]
        pairs = [(qs, qe) for qs in starts[0] for qe in starts[1]]
        results = fitted([p[0] for p in pairs], [p[1] for p in pairs], 0.0)
        fits = [
            (got[0], q1, q2, got[1])
            for (q1, q2), got in zip(pairs, results, strict=True)
            if got is not None
        ]
        fits.sort(key=lambda f: f[0])
        tries: list[_Try] = []
        for cost, q1, q2, K in fits[:_N_FIT_SHIFTS]:
            qp = self.planner.sextic_path(q1, q2, K)
            px, py = arm.tip_xy(qp)
            x = px + m
            inside = np.min(
                edges[:, 2, None] - edges[:, 0, None] * x - edges[:, 1, None] * py, axis=0
            )
            # Over the outline's own span: beyond its ends the path is in dug ground.
            span = (x >= min(a[0], b[0]) - 1e-9) & (x <= max(a[0], b[0]) + 1e-9)
            worst = float(np.min(inside[span])) if np.any(span) else 0.0
            shift = max(0.0, -worst - _FIT_OUTSIDE_M)
            if shift > _FIT_SHIFT_MAX_M * self.planner.scale:
                continue  # a path that far off the outline leaves a layer behind: the next
            if shift > 0.0:
                # A joined start stays where the dig before it ended.
                q1s = q1 if self._joined_start() else arm.ik(
                    float(a[0] + shift * n_a[0] - m),
                    float(a[1] + shift * n_a[1]),
                    float(np.sum(q1)),
                )
                q2s = arm.ik(
                    float(b[0] + shift * n_b[0] - m),
                    float(b[1] + shift * n_b[1]),
                    float(np.sum(q2)),
                )
                if q1s is None or q2s is None:
                    continue
                q1, q2 = np.asarray(q1s), np.asarray(q2s)
                got = fitted([q1], [q2], shift)[0]
                if got is None:
                    continue
                cost, K = got
            tries.append((q1, q2, K, cost))
            if len(tries) == 1:
                # The best fit alone first: it most often plans, and the others need refits.
                found = first_planned(tries)
                if found is not None:
                    return found
        return first_planned(tries[1:])

    def _theta_p_range(self, kind: DigType) -> tuple[float, float]:
        """The theta_p range of a fit of ``kind`` (rad): the type's, or
        :data:`JOINED_THETA_P_RAD` while a joined dig is fitted from the exit it continues
        (:attr:`_joining`, not carried)."""
        if self._joined_start():
            return JOINED_THETA_P_RAD
        lo, hi = oneshot.theta_p_range(self.planning, int(kind))
        return float(lo), float(hi)

    def _starts(self, point: FloatArray, attitudes_deg: tuple[float, ...]) -> list[FloatArray]:
        """A profile dig's start poses: the joined exit alone while a dig is fitted from it
        (:attr:`_joining`, not carried), else :meth:`_pass_pose`."""
        if self._joining is not None and self._joined_start():
            return [np.asarray(self._joining.q_rad, dtype=np.float64)]
        return self._pass_pose(point, attitudes_deg)

    def _joined_start(self) -> bool:
        """Whether the dig being fitted starts at the exit of the dig it continues."""
        return self._joining is not None and not self._joining.carried

    def _pass_pose(self, point: FloatArray, attitudes_deg: tuple[float, ...]) -> list[FloatArray]:
        """Joint poses of a pass end at the table's attitudes; where one is out of reach or
        limits, the nearest attitude (5 deg steps, up to 45 deg away) that is not."""
        arm = self.planner.arm
        found: list[FloatArray] = []
        for att in attitudes_deg:
            for step in range(10):
                for sign in (1.0,) if step == 0 else (1.0, -1.0):
                    q = arm.ik(
                        float(point[0]) - self.machine_x,
                        float(point[1]),
                        math.radians(att + sign * 5.0 * step),
                    )
                    if q is not None:
                        break
                if q is not None:
                    found.append(np.asarray(q))
                    break
        return found

    def _fit_bulges(
        self,
        base: FloatArray,
        q1: FloatArray,
        q2: FloatArray,
        edges: FloatArray,
        offset: float,
        kind: DigType,
    ) -> tuple[FloatArray, FloatArray]:
        """Damped Gauss-Newton fits of the bulge ``K`` of profile digs, P pairs of end poses
        at once (``base`` ``(P, n, 3)``: the joint blend on the fit's samples; ``q1``, ``q2``
        ``(P, 3)``): the inward distances of the path samples from the outline ``edges``
        (:meth:`_fit_profile`) less ``offset`` (weighted 21x where the path crosses the
        outline outwards by > 3 mm) and, while it is violated, the entry direction's theta_p
        bound as a heavily weighted row. Each pair steps, backs off and damps on its own
        (batched 3 x 3 normal equations: one fit ~25x cheaper than alone).

        Returns:
            ``(K (P, 3), cost (P,))``, each cost that of the K returned (the best evaluated).
        """
        arm = self.planner.arm
        pf = self.planner.fit_pf
        lengths = arm.lengths
        m = self.machine_x
        P = base.shape[0]
        tp_lo, tp_hi = self._theta_p_range(kind)
        jac0 = kinematics.jacobian(self.rig, q1)[:, :2]  # (P, 2, 3): d(x, y)/dq at q1
        d_ent = np.einsum("pij,pj->pi", jac0, 10.0 * (q2 - q1))
        geo = self.planner.geo_module
        if geo is not None:
            return self._fit_bulges_c(geo, base, jac0, d_ent, edges, (m, offset, tp_lo, tp_hi))
        mu = np.full(P, 1e-7)
        K = np.zeros((P, 3))
        step = np.zeros((P, 3))
        cost = np.full(P, np.inf)
        best_K = K.copy()
        active = np.ones(P, dtype=bool)
        eye = np.eye(3)
        for it in range(_FIT_ITERATIONS):
            q = base + pf[None, :, None] * K[:, None, :]
            phi = np.cumsum(q, axis=2)
            cs, sn = np.cos(phi) * lengths, np.sin(phi) * lengths
            x = cs.sum(axis=2) + m
            y = sn.sum(axis=2)
            inside = (
                edges[:, 2, None, None] - edges[:, 0, None, None] * x - edges[:, 1, None, None] * y
            )
            k = np.argmin(inside, axis=0)  # (P, n)
            d = np.take_along_axis(inside, k[None], axis=0)[0]
            w = np.where(d < -0.003, 21.0, 1.0)
            r = w * (d - offset)
            jx = -np.cumsum(sn[:, :, ::-1], axis=2)[:, :, ::-1]
            jy = np.cumsum(cs[:, :, ::-1], axis=2)[:, :, ::-1]
            J = (
                -(edges[k, 0][..., None] * jx + edges[k, 1][..., None] * jy)
                * (pf[None] * w)[..., None]
            )
            # theta_p of the entry direction d0 = J(q1) (10 D + K), linear in K.
            d0 = d_ent + np.einsum("pij,pj->pi", jac0, K)
            ang = np.arctan2(-d0[:, 1], np.abs(d0[:, 0]))
            sx = np.where(d0[:, 0] >= 0.0, 1.0, -1.0)
            AtA = np.einsum("pni,pnj->pij", J, J)
            Atb = -np.einsum("pni,pn->pi", J, r)
            pen = np.zeros(P)
            for bound, up in ((tp_lo + 0.02, False), (tp_hi - 0.02, True)):
                hit = (ang > bound) if up else (ang < bound)
                # g(K) = -d0_y cos(b) - |d0_x| sin(b): zero on the bound.
                gk = -jac0[:, 1] * math.cos(bound) - sx[:, None] * jac0[:, 0] * math.sin(bound)
                g = -d0[:, 1] * math.cos(bound) - np.abs(d0[:, 0]) * math.sin(bound)
                row = np.where(hit[:, None], 0.5 * gk, 0.0)
                rhs = np.where(hit, -0.5 * g, 0.0)
                AtA += row[:, :, None] * row[:, None, :]
                Atb += row * rhs[:, None]
                pen += np.where(hit, (0.5 * g) ** 2, 0.0)
            new_cost = np.einsum("pn,pn->p", r, r) + pen
            worse = active & (new_cost > cost)
            # The step made it worse: back off, damp harder.
            K = np.where(worse[:, None], K - 0.5 * step, K)
            step = np.where(worse[:, None], 0.5 * step, step)
            mu = np.where(worse, mu * 10.0, mu)
            better = active & ~worse
            cost = np.where(better, new_cost, cost)
            best_K = np.where(better[:, None], K, best_K)
            # Converged: the cost is that of the K returned.
            active &= ~(better & (np.einsum("pi,pi->p", step, step) < 1e-6) & (it > 0))
            go = better & active
            if not np.any(active):
                break
            sol = _solve_spd3(AtA + mu[:, None, None] * eye, Atb - mu[:, None] * K)
            step = np.where(go[:, None], sol, step)
            K = np.where(go[:, None], K + sol, K)
        return best_K, cost

    def _fit_bulges_c(
        self,
        geo: Any,
        base: FloatArray,
        jac0: FloatArray,
        d_ent: FloatArray,
        edges: FloatArray,
        par: tuple[float, float, float, float],
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`_fit_bulges` in C (``fit_bulges``: each pair's iterations, the numpy loop's
        operations in its order, its steps solved as :func:`_solve_spd3` solves them); the
        same K and costs bit for bit."""
        P = base.shape[0]
        K = np.zeros((P, 3))
        cost = np.zeros(P)
        geo.fit_bulges(
            np.ascontiguousarray(base, dtype=np.float64),
            np.ascontiguousarray(self.planner.fit_pf, dtype=np.float64),
            np.ascontiguousarray(self.planner.arm.lengths, dtype=np.float64),
            np.ascontiguousarray(edges, dtype=np.float64),
            np.ascontiguousarray(jac0, dtype=np.float64),
            np.ascontiguousarray(d_ent, dtype=np.float64),
            np.array(par, dtype=np.float64),
            K,
            cost,
        )
        return K, cost

    def _checked_fits(self, kind: DigType, tries: list[_Try], n_fit: int) -> list[Candidate | None]:
        """Fitted profile digs ``tries`` (``(q1, q2, K, cost)``: end poses, bulge and the
        fit's cost on ``n_fit`` samples) sampled on the full grid, refused over the over-dig
        limit and otherwise checked by :meth:`_pass_candidates` (all at once), each with the
        fit's RMS distance (``fit_rms_m``); None where refused."""
        arm = self.planner.arm
        q1 = np.array([t[0] for t in tries])
        q2 = np.array([t[1] for t in tries])
        K = np.array([t[2] for t in tries])
        qp = self.planner.sextic_path(q1, q2, K)
        px, py = arm.tip_xy(qp)
        tips = np.stack([px + self.machine_x, py], axis=2)
        out: list[Candidate | None] = [None] * len(tries)
        keep = np.flatnonzero(self._overdig_many(tips) <= OVERDIG_LIMIT_M)
        if keep.size == 0:
            return out
        found = self._pass_candidates(kind, q1[keep], q2[keep], K[keep], tips[keep])
        for i, c in zip(keep.tolist(), found, strict=True):
            if c is not None:
                rms = math.sqrt(tries[i][3] / n_fit)
                out[i] = dataclasses.replace(c, fit_rms_m=rms)
        return out

    def _pass_candidates(
        self, kind: DigType, qs: FloatArray, qe: FloatArray, K: FloatArray, tips: FloatArray
    ) -> list[Candidate | None]:
        """Fitted profile passes (``qs``, ``qe``, ``K`` ``(P, 3)``; their tips' paths ``tips``
        ``(P, n, 2)``, work-site frame) retimed and checked, as ranked candidates (None:
        refused); each row on its own, the verifier's rows at once."""
        out: list[Candidate | None] = [None] * qs.shape[0]
        # The real cut first: it refuses most fits, and needs no retiming.
        envelopes = [self._envelope(tip, self.grid) for tip in tips]
        areas = [self._cut_areas(env) for env in envelopes]
        floor = 0.1 * MIN_USEFUL_FRACTION * self.design_area
        # A joined dig's bucket holds the dig before it already.
        bucket = 0.0 if self._joining is None else self._joining.bucket_m3 / self.width_m
        cap = self.v_max_m3 / self.width_m - bucket
        rows = [i for i, (total, useful) in enumerate(areas) if total <= cap and useful >= floor]
        if not rows:
            return out
        # The verifier's soil model takes depth below a flat H; here the material over the
        # path is a layer along it, so H is set for the thickest chip the path cuts: the
        # material's thickness across the path's direction (its depth above the path times
        # the cosine of the path's slope: a wall's pass cuts the wedge beside the wall, not
        # the wedge's height), above the path's lowest point.
        tip = tips[rows]
        depth = np.clip(np.interp(tip[..., 0], self.grid, self.surface) - tip[..., 1], 0.0, None)
        step = np.gradient(tip, axis=1)
        across = np.abs(step[..., 0]) / np.maximum(np.hypot(step[..., 0], step[..., 1]), 1e-12)
        H = np.min(tip[..., 1], axis=1) + np.max(depth * across, axis=1)
        T0 = 0.5 * (self.planning.t_min_s + self.planning.t_max_s)
        # Below the fill band it can only be a finishing pass: timed in the passes' window.
        low = self._fill_band()[0] - bucket
        under = np.array([areas[i][0] < low for i in rows])
        table = pack_inputs(
            qs[rows], qe[rows], H, np.full(len(rows), int(kind)), -K[rows] / T0**6, T0
        )
        result = np.zeros((len(rows), N_OUT))
        retimed = np.zeros((len(rows), 4))
        for window in (False, True):
            sel = np.flatnonzero(under == window)
            if sel.size:
                r_out = np.zeros((sel.size, N_OUT))
                r_time = np.zeros((sel.size, 4))
                self.planner.verifier_for(window).retime_into(
                    np.ascontiguousarray(table[sel]), r_out, r_time
                )
                result[sel] = r_out
                retimed[sel] = r_time
        for j, i in enumerate(rows):
            if not np.isfinite(retimed[j, 3]) or _total_without_volume(
                result[j], self._joined_start()
            ) > 0.0:
                continue
            r = retimed[j]
            out[i] = Candidate(
                kind=kind,
                x7=np.concatenate([qs[i], qe[i], [H[j]]]),
                useful_m2=areas[i][1],
                total_m2=areas[i][0],
                score=areas[i][1],
                T_s=float(r[3]),
                a6=(float(r[0]), float(r[1]), float(r[2])),
                pass_window=bool(under[j]),
                envelope=envelopes[i],
                joined=self._joining is not None,
                bucket_m3=bucket * self.width_m,
                carried=self._joining is not None and self._joining.carried,
            )
        return out
