"""Mixed-order piecewise polynomial interpolation through key points (Gao/Yang 2023, eq 14-55).

A joint path through ``n_points`` key points is split into ``n_segments = n_points - 1``
polynomials whose orders may differ, e.g. 3-4-5-4-3 (Gao eq 15), 3-4-7-4-3 (eq 45) or 3-3-7-3-3.
All coefficients of one joint come from ONE square linear system (Gao eq 21-24, solved for every
joint at once as multiple right-hand sides) holding

* position at both ends of every segment (eq 17),
* zero velocity and acceleration at the first and the last key point (eq 18-19),
* continuity of velocity and acceleration at every interior key point (eq 18-19),
* extra continuity of higher derivatives at interior key points, chosen by the rule below, as
  many as the orders leave unknowns over (eq 20 lists jerk at the two middle knots for 3-4-5-4-3).

Smoothness rule (where the paper is silent). With ``m`` segments of orders ``p_i`` there are
``sum(p_i + 1)`` unknowns and ``4 m + 2`` conditions above, so ``E = sum(p_i) - 3 m - 2`` extra
conditions are needed; ``E < 0`` means the orders are too low and is refused. Candidates are
"continuity of derivative ``d >= 3`` at interior knot ``j``" with ``d < max`` of the two adjacent
orders (at ``d = max`` the higher piece's ``d``-th derivative is its leading coefficient, so the
condition would merge two equal-order pieces into one polynomial or drop the higher piece's top
order; above it both sides are identically zero). They are ranked, and the first ``E`` taken:

1. genuine smoothness first: ``d <= min`` of the adjacent orders (both pieces have a non-trivial
   ``d``-th derivative) before "flatness" conditions that force the higher-order piece's ``d``-th
   derivative to zero at a knot beside a lower-order piece;
2. knots with more polynomial freedom first: larger sum of the two adjacent orders;
3. lower derivative first;
4. knots nearer the middle of the path first, then the left one;
5. a candidate that would make the conditions linearly dependent is skipped, and so is the rest
   of its knot (continuity stays contiguous in ``d``). Example: 3-4-3-7 takes jerk at knots 3
   and 2; jerk at knot 1 would then over-determine the chain (the end cubic fixes the quartic
   through C3, the quartic fixes the middle cubic, whose jerk is already tied at knot 2), so the
   third condition becomes snap at knot 3: continuity (2, 3, 4). Independence is checked with
   unit durations: it is structural, and the choice then depends on the orders alone.

Within a knot this always takes ``d = 3, 4, ...`` in order, so knot ``j`` ends up continuous up to
one derivative, reported in :attr:`PiecewisePolynomial.continuity`. The rule reproduces every
printed coefficient of Gao eq 47-55 (bar the misprints below), and the printed numbers pin the
choice down: of all full-rank sets of ``E`` conditions "derivative ``d`` continuous at knot ``j``"
(any ``3 <= d <= 7`` not above the adjacent orders), exactly one reproduces each strategy, namely

* 3-4-5-4-3 (E = 2): jerk at knots 2 and 3 (Gao eq 20) -> continuity (2, 3, 3, 2);
* 3-3-7-3-3 (E = 2): jerk at knots 2 and 3 (Gao eq 20) -> continuity (2, 3, 3, 2);
* 3-4-7-4-3 (E = 4): jerk AND snap (4th derivative) at knots 2 and 3, the two knots of the
  7th-order piece -> continuity (2, 4, 4, 2). These are the two conditions the paper's list
  (24 for 26 unknowns) leaves out.

Time. Gao eq 14 normalises time per segment, but eq 47-55 print every polynomial in GLOBAL time
``t`` (e.g. ``theta_5(t)`` for ``12 <= t <= 15``) in the key points' unit (degrees there). The
printed numbers are exactly what one gets by solving in local time ``tau = t - t_{i-1}`` (s),
rounding those local coefficients to 4 decimals and expanding them in ``t`` (every printed
coefficient but the misprints below agrees with that procedure to its last digit; the inputs were
exactly Table 2's 2-decimal angles). Here the system
is solved in normalised time ``u = (t - t_{i-1}) / (t_i - t_{i-1})`` (eq 14; keeps the matrix well
conditioned), and :meth:`PiecewisePolynomial.coefficients` returns unrounded coefficients in
global time ``t`` by default (as printed) or in local time ``tau`` with ``local=True``. Global
coefficients of high-order pieces far from ``t = 0`` are large and cancel each other; sample with
:meth:`PiecewisePolynomial.sample`, never by evaluating them.

Misprints found in Gao eq 50 and 54 (the tests check that they are misprints):

* eq 50 (3-4-7-4-3 boom) prints the constant of ``theta_5`` as -1075.2402; the same segment is
  independent of the middle orders and eq 47 and 53 print -1075.2404, which is right (-1075.2402
  would miss the key point at t = 12 s by 2e-4 deg).
* eq 54 (3-3-7-3-3 stick) prints the 9-12 s cubic in the row of ``theta_2`` (3-6 s), and in the
  row of ``theta_4`` a cubic that passes through neither of its key points.

Errors: malformed arguments (shapes, non-finite numbers, knots not strictly increasing, a wrong
number of orders, an unreadable order string) raise ``ValueError``; well-formed inputs that admit
no trajectory under these conditions (an end segment below order 3, orders too low or too high
for a square system, a singular or ill-conditioned system) raise
:class:`~rt_runtime.errors.PlanningError`.

Values are in any unit (rad by the project's convention; the paper's tests use degrees);
derivatives come out in that unit per s, s^2, s^3. :func:`interpolate` and the comparison run
outside the loop; :meth:`PiecewisePolynomial.sample` is vectorised over any time array and is
loop-safe at small sizes (it allocates only its result and a few same-sized temporaries).
"""

from __future__ import annotations

import functools
import math
import operator
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import PlanningError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

PAPER_STRATEGIES: tuple[str, ...] = ("3-4-5-4-3", "3-4-7-4-3", "3-3-7-3-3")
"""Gao's three order patterns for five segments (six key points)."""
#: Gao/Yang Table 2: joint angles (deg: boom, stick, bucket) of the six key points of their
#: digging path on the test bench, 3 s apart.
GAO_TABLE2_JOINTS_DEG: tuple[tuple[float, float, float], ...] = (
    (34.83, -40.32, -56.16),
    (34.05, -50.52, -57.47),
    (37.27, -65.58, -58.15),
    (41.75, -77.73, -60.14),
    (49.39, -89.13, -60.26),
    (58.46, -92.13, -61.07),
)

MAX_CONDITION = 1e10
"""Largest accepted 2-norm condition number of the (row-equilibrated) system.

Above it the coefficients' relative error bound ``cond * eps`` passes ~2e-6, too coarse to trust
the continuity the trajectory promises."""

_ORDER_STRING = re.compile(r"^\s*\d+(\s*-\s*\d+)*\s*$")


def parse_orders(orders: str | Sequence[int]) -> tuple[int, ...]:
    """Read a pattern of polynomial orders.

    Args:
        orders: ``"3-4-5-4-3"`` or a sequence of ints such as ``(3, 4, 5, 4, 3)``.

    Returns:
        The orders as a tuple of ints.

    Raises:
        ValueError: The string is not dash-separated non-negative integers, an entry is not an
            integer, is below 1, or the pattern is empty.
    """
    if isinstance(orders, str):
        if not _ORDER_STRING.match(orders):
            raise ValueError(
                f"orders string must be dash-separated integers like '3-4-5-4-3'; got {orders!r}"
            )
        parsed = tuple(int(part) for part in orders.split("-"))
    else:
        try:
            items = list(orders)
        except TypeError as exc:
            raise ValueError(
                f"orders must be a string or a sequence of ints; got {orders!r}"
            ) from exc
        if any(isinstance(p, bool | float) for p in items):
            raise ValueError(f"orders must be integers; got {items!r}")
        try:
            parsed = tuple(operator.index(p) for p in items)
        except TypeError as exc:
            raise ValueError(f"orders must be integers; got {items!r}") from exc
    if not parsed:
        raise ValueError("orders must name at least one segment")
    if min(parsed) < 1:
        raise ValueError(f"every order must be >= 1 (a segment joins two key points); got {parsed}")
    return parsed


def continuity_orders(orders: str | Sequence[int]) -> tuple[int, ...]:
    """Highest derivative kept continuous at each interior knot by the smoothness rule.

    See the module docstring for the rule. Velocity and acceleration are always continuous (2);
    every extra condition raises one knot's value by one. Depends on the orders only.

    Args:
        orders: Orders of the ``m`` segments (see :func:`parse_orders`).

    Returns:
        ``m - 1`` ints, each >= 2; empty for a single segment.

    Raises:
        ValueError: ``orders`` is malformed.
        PlanningError: An end segment has order < 3 (it cannot meet position at both ends plus
            zero velocity and acceleration at the path's end); the orders are too low (fewer
            unknowns than the always-imposed conditions); the always-imposed conditions are
            dependent (typically an interior piece of order 1 or 2); or the rule finds fewer
            independent extra conditions than unknowns are left (e.g. a single piece above
            order 5).
    """
    return _continuity(parse_orders(orders))


@functools.lru_cache(maxsize=256)
def _continuity(p: tuple[int, ...]) -> tuple[int, ...]:
    m = len(p)
    if p[0] < 3 or p[-1] < 3:
        raise PlanningError(
            f"orders {_name(p)}: the first and last segments need order >= 3 to meet position at "
            "both ends and zero velocity and acceleration at the path's ends"
        )
    extra = sum(p) - 3 * m - 2
    if extra < 0:
        raise PlanningError(
            f"orders {_name(p)} are too low: {sum(p) + m} unknowns for {4 * m + 2} conditions "
            f"(positions, rest at both ends, C2 at interior knots); need sum(orders) >= "
            f"{3 * m + 2} for {m} segments"
        )
    # Independence is structural, so it is checked with unit durations: the choice then
    # depends on the orders alone, and interpolate() checks the real system's conditioning.
    unit = np.ones(m)
    chosen = _conditions(m, (2,) * (m - 1))
    rank = int(np.linalg.matrix_rank(_rows(p, chosen, unit)))
    if rank < len(chosen):
        raise PlanningError(
            f"orders {_name(p)}: positions, rest at the ends and C2 at the interior knots are "
            "already dependent (a piece of order < 3 between knots?); raise the low orders"
        )
    candidates: list[tuple[bool, int, int, float, int]] = []
    for j in range(1, m):
        lo, hi = sorted((p[j - 1], p[j]))
        candidates.extend((d > lo, -(lo + hi), d, abs(j - m / 2), j) for d in range(3, hi))
    level = [2] * (m - 1)
    blocked: set[int] = set()
    for *_, d, _centre, j in sorted(candidates):
        if len(chosen) - (4 * m + 2) == extra:
            break
        if j in blocked:
            continue
        trial = [*chosen, ("continuity", j, d)]
        if int(np.linalg.matrix_rank(_rows(p, trial, unit))) == len(trial):
            chosen = trial
            level[j - 1] = d
        else:
            # Continuity must stay contiguous in d, so the knot takes nothing more.
            blocked.add(j)
    if len(chosen) - (4 * m + 2) < extra:
        raise PlanningError(
            f"orders {_name(p)} leave {extra} unknowns beyond the always-imposed conditions but "
            f"the smoothness rule finds only {len(chosen) - (4 * m + 2)} independent extra "
            "derivative continuities; lower the high orders (a single segment must be order 5)"
        )
    return tuple(level)


def expand_strategy(orders: str | Sequence[int], n_segments: int) -> tuple[int, ...]:
    """Fit an order pattern to a number of segments by repeating its central order.

    ``3-4-5-4-3`` on 7 segments becomes ``3-4-5-5-5-4-3``: the end pieces keep the pattern's
    boundary behaviour and the extra key points get the central piece's freedom. The central
    order is the one at index ``len(pattern) // 2``.

    Args:
        orders: The pattern (see :func:`parse_orders`).
        n_segments: Number of segments wanted, >= ``len(pattern)``.

    Returns:
        ``n_segments`` orders.

    Raises:
        ValueError: ``orders`` is malformed or has more segments than ``n_segments``.
    """
    p = parse_orders(orders)
    if n_segments < len(p):
        raise ValueError(
            f"pattern {_name(p)} has {len(p)} segments; it applies to >= {len(p)} segments, "
            f"not {n_segments}"
        )
    c = len(p) // 2
    return p[:c] + (p[c],) * (n_segments - len(p) + 1) + p[c + 1 :]


def _name(p: Sequence[int]) -> str:
    return "-".join(str(x) for x in p)


def _falling(max_order: int) -> FloatArray:
    """``F[d, k] = k! / (k - d)!`` (0 for k < d): d-th derivative factor of ``u**k``."""
    f = np.zeros((max_order + 1, max_order + 1))
    for d in range(max_order + 1):
        for k in range(d, max_order + 1):
            f[d, k] = math.perm(k, d)
    return f


def _derivative_order(derivative: int) -> int:
    if isinstance(derivative, bool) or not isinstance(derivative, int | np.integer):
        raise ValueError(f"derivative must be a non-negative integer; got {derivative!r}")
    if derivative < 0:
        raise ValueError(f"derivative must be >= 0; got {derivative}")
    return int(derivative)


def _readonly(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, slots=True, eq=False)
class PiecewisePolynomial:
    """A piecewise polynomial path of one or more joints through key points.

    Made by :func:`interpolate`. Equality is identity (the fields are arrays, read-only).

    Attributes:
        knots_s: Key point times, ``(n_points,)``, s, strictly increasing.
        orders: Polynomial order of each of the ``n_points - 1`` segments.
        continuity: Highest derivative continuous at each interior knot, ``n_points - 2`` ints
            (always >= 2: position, velocity, acceleration).
        u_coefficients: ``(n_segments, max_order + 1, n_joints)``: segment ``i`` as a polynomial
            in normalised time ``u = (t - knots_s[i]) / (knots_s[i+1] - knots_s[i])``, lowest
            power first, zero above the segment's order; in the values' unit.
        scalar_values: The key point values were 1-D (one joint): :meth:`sample` then drops the
            joint axis.
    """

    knots_s: FloatArray
    orders: tuple[int, ...]
    continuity: tuple[int, ...]
    u_coefficients: FloatArray
    scalar_values: bool = False
    _durations_s: FloatArray = field(init=False, repr=False)
    _tables: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        put = object.__setattr__
        knots = np.array(self.knots_s, dtype=np.float64)
        coef = np.array(self.u_coefficients, dtype=np.float64)
        m = len(self.orders)
        if m < 1:
            raise ValueError("orders must name at least one segment")
        width = max(self.orders) + 1
        if knots.shape != (m + 1,):
            raise ValueError(
                f"knots_s must have shape ({m + 1},) for {m} orders; got {knots.shape}"
            )
        if coef.ndim != 3 or coef.shape[:2] != (m, width) or coef.shape[2] < 1:
            raise ValueError(
                f"u_coefficients must have shape ({m}, {width}, n_joints); got {coef.shape}"
            )
        if len(self.continuity) != m - 1:
            raise ValueError(f"continuity must have {m - 1} entries; got {len(self.continuity)}")
        durations = np.diff(knots)
        if not (np.all(np.isfinite(knots)) and np.all(durations > 0.0)):
            raise ValueError(f"knots_s must be finite and strictly increasing; got {knots}")
        # Derivative tables in global time: tables[d, i, k] multiplies u**k in d^d/dt^d of piece i.
        f = _falling(width - 1)
        tables = np.zeros((width, m, width, coef.shape[2]))
        for d in range(width):
            scale = f[d, d:][None, :, None] / durations[:, None, None] ** d
            tables[d, :, : width - d] = coef[:, d:] * scale
        put(self, "knots_s", _readonly(knots))
        put(self, "orders", tuple(int(p) for p in self.orders))
        put(self, "continuity", tuple(int(c) for c in self.continuity))
        put(self, "u_coefficients", _readonly(coef))
        put(self, "_durations_s", _readonly(durations))
        put(self, "_tables", _readonly(tables))

    @property
    def duration_s(self) -> float:
        """Time from the first to the last key point, s."""
        return float(self.knots_s[-1] - self.knots_s[0])

    @property
    def n_joints(self) -> int:
        """Number of joints (1 for 1-D key point values)."""
        return int(self.u_coefficients.shape[2])

    @property
    def n_segments(self) -> int:
        """Number of polynomial pieces."""
        return len(self.orders)

    def _evaluate(self, seg: IntArray, u: FloatArray, derivative: int) -> FloatArray:
        """Horner on gathered coefficients; ``seg`` and ``u`` shaped ``(...)``, result
        ``(..., n_joints)``."""
        width = self._tables.shape[0]
        if derivative >= width:
            return np.zeros((*u.shape, self.n_joints))
        table = self._tables[derivative]
        uu = u[..., None]
        acc = table[seg, width - 1 - derivative]
        for k in range(width - 2 - derivative, -1, -1):
            acc = acc * uu + table[seg, k]
        return np.asarray(acc, dtype=np.float64)

    def sample(self, t_s: ArrayLike, derivative: int = 0) -> FloatArray:
        """Position or a time derivative at any array of times.

        Outside ``[knots_s[0], knots_s[-1]]`` the joints hold the nearer end value at rest
        (derivatives 0). At an interior knot the right-hand segment is used (the two agree up to
        :attr:`continuity`).

        Args:
            t_s: Times, any shape ``(...)``, s (same clock as ``knots_s``).
            derivative: 0 position, 1 velocity, 2 acceleration, 3 jerk, higher allowed.

        Returns:
            ``(..., n_joints)``, or ``(...)`` when the key point values were 1-D; in the values'
            unit per s**derivative.

        Raises:
            ValueError: A time is not finite, or ``derivative`` is not a non-negative integer.

        Loop-safe at small sizes: no Python loop over samples; allocates the result and a few
        temporaries of the same size.
        """
        d = _derivative_order(derivative)
        t = np.asarray(t_s, dtype=np.float64)
        if not np.all(np.isfinite(t)):
            raise ValueError("t_s must be finite")
        knots = self.knots_s
        seg = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, self.n_segments - 1)
        u = np.clip((t - knots[seg]) / self._durations_s[seg], 0.0, 1.0)
        out = self._evaluate(seg, u, d)
        if d > 0:
            outside = (t < knots[0]) | (t > knots[-1])
            out = np.where(outside[..., None], 0.0, out)
        return out[..., 0] if self.scalar_values else out

    def segment_samples(self, samples_per_segment: int, derivative: int = 0) -> FloatArray:
        """Every segment sampled at equally spaced points including both of its ends.

        Each piece is evaluated on its own closed interval, so a derivative that jumps at a knot
        (e.g. jerk at a C2 knot) shows both one-sided values.

        Args:
            samples_per_segment: Points per segment, >= 2.
            derivative: As in :meth:`sample`.

        Returns:
            ``(n_segments, samples_per_segment, n_joints)`` (joint axis kept even for 1-D values).

        Raises:
            ValueError: ``samples_per_segment < 2`` or a bad ``derivative``.
        """
        d = _derivative_order(derivative)
        n = operator.index(samples_per_segment)
        if n < 2:
            raise ValueError(f"samples_per_segment must be >= 2; got {n}")
        u = np.broadcast_to(np.linspace(0.0, 1.0, n), (self.n_segments, n))
        seg = np.broadcast_to(np.arange(self.n_segments)[:, None], (self.n_segments, n))
        return self._evaluate(seg, u, d)

    def coefficients(self, segment: int, joint: int = 0, *, local: bool = False) -> FloatArray:
        """One segment's polynomial coefficients, highest power first (as Gao eq 47-55 print).

        Args:
            segment: Segment index, 0-based (Gao's ``theta_1`` is segment 0).
            joint: Joint index (0 for 1-D values).
            local: False: in global time ``t`` (s), valid for ``knots_s[segment] <= t <=
                knots_s[segment + 1]``, as the paper prints them. True: in local time
                ``tau = t - knots_s[segment]`` (s), the form the paper solved and rounded.

        Returns:
            ``(orders[segment] + 1,)`` coefficients, in the values' unit per s**power.

        Raises:
            ValueError: ``segment`` or ``joint`` is out of range.
        """
        if not 0 <= segment < self.n_segments:
            raise ValueError(f"segment must be in [0, {self.n_segments - 1}]; got {segment}")
        if not 0 <= joint < self.n_joints:
            raise ValueError(f"joint must be in [0, {self.n_joints - 1}]; got {joint}")
        p = self.orders[segment]
        powers = np.arange(p + 1)
        tau = self.u_coefficients[segment, : p + 1, joint] / self._durations_s[segment] ** powers
        if local:
            return np.asarray(tau[::-1], dtype=np.float64).copy()
        # c_tau(t - a) expanded: coefficient of t**j is sum_k c_k C(k, j) (-a)**(k - j).
        a = float(self.knots_s[segment])
        binom = np.array([[math.comb(k, j) for k in range(p + 1)] for j in range(p + 1)])
        shift = binom * (-a) ** np.clip(powers[None, :] - powers[:, None], 0, None)
        return np.asarray((shift @ tau)[::-1], dtype=np.float64).copy()


_Condition = tuple[str, int, int]
"""``(kind, index, derivative)``: ``("start" | "end", segment, 0)`` position at a segment's
start or end; ``("rest", knot, d)`` zero d-th derivative at knot 0 or m;
``("continuity", j, d)`` equal d-th derivatives on both sides of interior knot j."""


def _conditions(m: int, continuity: Sequence[int]) -> list[_Condition]:
    out: list[_Condition] = []
    for i in range(m):
        out += [("start", i, 0), ("end", i, 0)]
    out += [("rest", 0, 1), ("rest", m, 1), ("rest", 0, 2), ("rest", m, 2)]
    for j, top in enumerate(continuity, start=1):
        out += [("continuity", j, d) for d in range(1, top + 1)]
    return out


def _rows(
    orders: tuple[int, ...], conditions: Sequence[_Condition], durations: FloatArray
) -> FloatArray:
    """Matrix of the conditions on the normalised-time coefficients of all segments.

    Derivative rows are scaled by ``h_ref**d / d!`` (``h_ref`` the geometric mean of the adjacent
    durations) so their entries are binomial-sized: the condition number then depends on the
    orders and the duration ratios, not on the time unit.
    """
    m = len(orders)
    offsets = np.concatenate(([0], np.cumsum(np.array(orders) + 1)))
    f = _falling(max(orders))
    rows = np.zeros((len(conditions), int(offsets[-1])))
    for r, (kind, knot, d) in enumerate(conditions):
        if kind == "start":
            rows[r, offsets[knot]] = 1.0
        elif kind == "end":
            rows[r, offsets[knot] : offsets[knot + 1]] = 1.0
        elif kind == "rest" and knot == 0:
            rows[r, offsets[0] + d] = 1.0
        elif kind == "rest":
            rows[r, offsets[m - 1] : offsets[m]] = f[d, : orders[-1] + 1] / f[d, d]
        else:
            pl, pr = orders[knot - 1], orders[knot]
            ratio = float(durations[knot] / durations[knot - 1]) ** (d / 2)
            rows[r, offsets[knot - 1] : offsets[knot]] = f[d, : pl + 1] / f[d, d] * ratio
            if d <= pr:
                rows[r, offsets[knot] + d] = -1.0 / ratio
    return rows


def _key_points(times_s: ArrayLike, values: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Validated float copies of the key point times and values."""
    t = np.array(times_s, dtype=np.float64)
    v = np.array(values, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 2:
        raise ValueError(f"times_s must have shape (n_points,) with n_points >= 2; got {t.shape}")
    if v.ndim not in (1, 2) or v.shape[0] != t.shape[0] or (v.ndim == 2 and v.shape[1] < 1):
        raise ValueError(
            f"values must have shape ({t.shape[0]},) or ({t.shape[0]}, n_joints) to match "
            f"times_s; got {v.shape}"
        )
    if not np.all(np.isfinite(t)):
        raise ValueError(f"times_s must be finite; got {t}")
    if not np.all(np.isfinite(v)):
        raise ValueError("values must be finite (no NaN or inf)")
    durations = np.diff(t)
    if not np.all(durations > 0.0):
        bad = int(np.argmin(durations))
        raise ValueError(
            f"times_s must be strictly increasing; segment {bad} lasts {durations[bad]} s "
            f"(times {t[bad]} -> {t[bad + 1]})"
        )
    return t, v


def interpolate(
    times_s: ArrayLike, values: ArrayLike, orders: str | Sequence[int]
) -> PiecewisePolynomial:
    """Mixed-order piecewise polynomial through key points, at rest at both ends (Gao eq 14-44).

    Args:
        times_s: Key point times, ``(n_points,)``, s, finite, strictly increasing, n_points >= 2.
        values: Key point values, ``(n_points,)`` or ``(n_points, n_joints)``, finite, any unit.
        orders: ``n_points - 1`` segment orders, e.g. ``(3, 4, 5, 4, 3)`` or ``"3-4-5-4-3"``.

    Returns:
        The trajectory; its :attr:`~PiecewisePolynomial.continuity` says which derivatives are
        continuous at each interior knot (module docstring: smoothness rule).

    Raises:
        ValueError: Malformed arguments: shapes, non-finite numbers, fewer than 2 points, knots
            not strictly increasing (zero or negative durations), the wrong number of orders.
        PlanningError: Orders that cannot give a square system (see :func:`continuity_orders`),
            or a system that is singular or ill-conditioned (condition number above
            :data:`MAX_CONDITION`, e.g. from wildly different segment durations).

    Not loop-safe: builds and factorises a ``sum(orders + 1)``-square matrix (~1 ms).
    """
    t, v = _key_points(times_s, values)
    durations = np.diff(t)
    p = parse_orders(orders)
    m = t.shape[0] - 1
    if len(p) != m:
        raise ValueError(f"{t.shape[0]} key points need {m} orders; got {len(p)} ({_name(p)})")
    continuity = continuity_orders(p)
    conditions = _conditions(m, continuity)
    matrix = _rows(p, conditions, durations)
    v2 = v.reshape(t.shape[0], -1)
    rhs = np.zeros((matrix.shape[0], v2.shape[1]))
    for row, (kind, segment, _d) in enumerate(conditions):
        if kind in ("start", "end"):
            rhs[row] = v2[segment + (kind == "end")]
    # One SVD gives both the conditioning verdict and a backward-stable solve for all joints.
    u_mat, sing, vt = np.linalg.svd(matrix)
    cond = float(sing[0] / sing[-1]) if sing[-1] > 0.0 else math.inf
    if not cond <= MAX_CONDITION:
        raise PlanningError(
            f"orders {_name(p)} with durations {np.round(durations, 6).tolist()} s give a "
            f"singular or ill-conditioned system (condition number {cond:.3g} > "
            f"{MAX_CONDITION:.0e}); use orders that suit the conditions or less uneven durations"
        )
    x = vt.T @ ((u_mat.T @ rhs) / sing[:, None])
    width = max(p) + 1
    coef = np.zeros((m, width, v2.shape[1]))
    offsets = np.concatenate(([0], np.cumsum(np.array(p) + 1)))
    for i, order in enumerate(p):
        coef[i, : order + 1] = x[offsets[i] : offsets[i + 1]]
    return PiecewisePolynomial(
        knots_s=t, orders=p, continuity=continuity, u_coefficients=coef,
        scalar_values=v.ndim == 1,
    )


@dataclass(frozen=True, slots=True, eq=False)
class StrategyResult:
    """One order pattern applied to the key points, and its peak derivatives.

    Peaks are maxima of the absolute value over the whole path and per joint, ``(n_joints,)``,
    in the values' unit per s, s^2 and s^3, found by dense sampling (every segment on its own
    closed interval, so one-sided values at knots count).

    Attributes:
        name: The pattern as given, e.g. ``"3-4-5-4-3"``.
        orders: The orders used (after :func:`expand_strategy`).
        trajectory: The interpolated path.
        peak_velocity: Max |velocity| per joint.
        peak_acceleration: Max |acceleration| per joint.
        peak_jerk: Max |jerk| per joint.
    """

    name: str
    orders: tuple[int, ...]
    trajectory: PiecewisePolynomial
    peak_velocity: FloatArray
    peak_acceleration: FloatArray
    peak_jerk: FloatArray


@dataclass(frozen=True, slots=True, eq=False)
class StrategyComparison:
    """Order patterns compared on one set of key points.

    Attributes:
        results: The patterns that applied and solved, in the order given.
        skipped: ``(name, reason)`` for patterns that did not apply (more segments than the key
            points give) or admit no trajectory (the PlanningError's message).
        samples_per_segment: Sampling density used for the peaks.
        key_values: The key point values, ``(n_points, n_joints)`` (joint axis always present).
    """

    results: tuple[StrategyResult, ...]
    skipped: tuple[tuple[str, str], ...]
    samples_per_segment: int
    key_values: FloatArray


def compare_strategies(
    times_s: ArrayLike,
    values: ArrayLike,
    strategies: Sequence[str | Sequence[int]] = PAPER_STRATEGIES,
    samples_per_segment: int = 1000,
) -> StrategyComparison:
    """Interpolate the key points with several order patterns and measure their peaks.

    A pattern with as many segments as the key points give is used as is; one with fewer is
    widened by repeating its central order (:func:`expand_strategy`); one with more is skipped.

    Args:
        times_s: Key point times, ``(n_points,)``, s (see :func:`interpolate`).
        values: Key point values, ``(n_points,)`` or ``(n_points, n_joints)``.
        strategies: Patterns, strings like ``"3-4-5-4-3"`` or sequences of ints.
        samples_per_segment: Dense sampling per segment for the peaks, >= 2. With 1000 the
            sampled peak of a smooth piece is within ~1e-6 (relative) of the true one.

    Returns:
        The comparison.

    Raises:
        ValueError: Malformed key points or patterns (as :func:`interpolate`, checked even when
            no pattern applies), or ``samples_per_segment < 2``.
    """
    t, v = _key_points(times_s, values)
    if operator.index(samples_per_segment) < 2:
        raise ValueError(f"samples_per_segment must be >= 2; got {samples_per_segment}")
    n_segments = t.shape[0] - 1
    results: list[StrategyResult] = []
    skipped: list[tuple[str, str]] = []
    for strategy in strategies:
        pattern = parse_orders(strategy)
        name = strategy if isinstance(strategy, str) else _name(pattern)
        if n_segments < len(pattern):
            skipped.append(
                (name, f"{len(pattern)} segments but the key points give {n_segments}")
            )
            continue
        orders = expand_strategy(pattern, n_segments)
        try:
            traj = interpolate(t, v, orders)
        except PlanningError as exc:
            skipped.append((name, str(exc)))
            continue
        vel, acc, jerk = (
            _readonly(np.max(np.abs(traj.segment_samples(samples_per_segment, d)), axis=(0, 1)))
            for d in (1, 2, 3)
        )
        results.append(StrategyResult(name, orders, traj, vel, acc, jerk))
    key_values = _readonly(v.reshape(t.shape[0], -1).copy())
    return StrategyComparison(tuple(results), tuple(skipped), samples_per_segment, key_values)


def choose_smoothest(comparison: StrategyComparison) -> StrategyResult:
    """The smoothest strategy of a comparison.

    Rule: for each joint, divide every strategy's peak |jerk| by the smallest peak |jerk| any
    strategy reaches on that joint (so joints of different size and unit weigh alike); a
    strategy's score is the largest of these ratios over the joints; the lowest score wins.
    Scores within a relative 1e-9 of the best tie, and ties go to the lowest score built the same
    way from peak |acceleration|, then to the strategy listed first. Joints whose key points are
    all equal (they do not move under any strategy) are left out of both scores.

    Args:
        comparison: From :func:`compare_strategies`.

    Returns:
        The chosen result.

    Raises:
        PlanningError: No strategy applied (all were skipped).
    """
    res = comparison.results
    if not res:
        reasons = "; ".join(f"{n}: {why}" for n, why in comparison.skipped)
        raise PlanningError(f"no interpolation strategy applied ({reasons})")
    moving = np.ptp(comparison.key_values, axis=0) > 0.0

    def scores(peaks: FloatArray) -> FloatArray:
        if not np.any(moving):
            return np.zeros(len(res))
        sel = peaks[:, moving]
        return np.asarray(np.max(sel / np.min(sel, axis=0), axis=1), dtype=np.float64)

    jerk = scores(np.array([r.peak_jerk for r in res]))
    acc = scores(np.array([r.peak_acceleration for r in res]))
    tied = np.flatnonzero(jerk <= jerk.min() * (1.0 + 1e-9))
    return res[int(tied[np.argmin(acc[tied])])]
