"""Runtime one-shot planner: the PINN through onnxruntime, verified, repaired or refused.

Yao 4.3 replaces the PSO with a forward pass of a network mapping (entry pose, exit pose, H) to
the sextic's (a16, a26, a36, T). A network's answer is a guess, so here every answer is checked
before anyone may execute it:

1. **Domain.** The inputs must be finite and inside the model card's domain (the range of the
   training inputs); outside it a network extrapolates, so the planner refuses
   (:class:`~rt_runtime.errors.PlanningError` naming the input and the range) or, when the caller
   allows it, hands the problem to the PSO teacher.
2. **Inference.** One onnxruntime session per dig type, tuned for latency: one thread, sequential
   execution, every graph optimisation, inputs and outputs bound once to preallocated buffers
   (IOBinding) and no RunOptions argument.
3. **Verification** of every hard limit of Yao eq 12 (joint range, velocity, acceleration,
   torque, power, initial digging angle, volume, time) on a dense grid (101 samples by default)
   by :class:`rt_runtime.planning.verify.Verifier`, the compiled twin of the numpy evaluation.
4. **Fill and retime** (the normal path, :meth:`rt_runtime.planning.verify.Verifier.plan_into`,
   in the C kernel): the network's path direction is kept and its bulge scaled, K = c K_net,
   to the largest volume within V_max and the path-only limits (joint range, theta_p), then
   the path is run at its smallest feasible T. Both steps move the answer to where the PSO's
   optima lie (on the volume cap and the time-dependent limits), which a regression network
   can only approach from inside. What they cannot make feasible falls back to the network's
   own path retimed, then to step 5.

   4a. **Solution library** (when the model card ships one, ``<model>_library.npz``: the
   teacher's answers to training problems, never the held-out ones). Where the teacher has two
   families of optima a regression network answers their average, whose bulges partly cancel,
   so the fill scales the averaged bulge up. Where the fill scale c reaches the card's
   ``trigger_bulge_scale``, the ``k`` nearest library problems' teacher paths (nearest in inputs
   scaled per input by the library's standard deviation: a ``scipy.spatial.cKDTree``,
   :meth:`_Library.nearest`) are filled and retimed for this problem like the network's, in one
   ``Kernel.plan`` call (:meth:`_from_library`), and the best verified one replaces the
   network's plan when its objective is smaller (:attr:`PlanStatus.LIBRARY`). The exporter's
   defaults (:data:`rt_runtime.training.export.LIBRARY_K`,
   :data:`~rt_runtime.training.export.LIBRARY_TRIGGER_BULGE_SCALE`,
   :data:`~rt_runtime.training.export.LIBRARY_KEEP_BULGE_SCALE`) set what a card carries
   (design notes, O7 and V6).
5. **Repair**, when that still fails (or with ``retime=False``, whenever the raw answer fails).
   Time scaling first, where only time-dependent limits fail (velocity, acceleration, torque,
   power, t_min): the kernel's exact retiming keeps the path (so angles, theta_p and volume)
   and takes the smallest T in [t_min, t_max] at which every limit holds. What time scaling
   cannot fix (a joint range, theta_p or volume violation, or no T in range) goes first to the
   **fast repair** (:meth:`PinnPlanner._fast_repair`, at most :data:`FAST_REPAIR_CALLS` kernel
   calls, tens of microseconds), then, when that fails too, to a bounded local refinement (SLSQP
   from the network's answer, :data:`REFINE_ITERATIONS` iterations, milliseconds), when enabled.
   Otherwise :class:`~rt_runtime.errors.PlanningError` names the violated limit.

   The fast repair changes the path's direction where scaling it cannot help. The path is
   ``theta(s) = theta1 + D q(s) + K p(s)``, linear in K, so (a) each joint's range on the
   verification grid is an interval of its K_i in closed form: a violating joint's K_i is
   clamped into it; (b) a dig that starts on the surface enters along ``J(q0) (10 D + K)``, so
   each theta_p limit is a half-space of K: K is projected onto it; (c) V_p is not linear: where
   V_min fails, one secant per free joint (on a coarse grid of :data:`_REPAIR_SECANT_SAMPLES`
   samples) linearises it and K moves to the nearest point (in joint ranges, the joint that
   sets T weighted 100x heavier) meeting V_min and the theta_p half-spaces, with one chord
   correction when needed; that vertex (a joint at its limit, theta_p at its maximum, V_p at
   V_min) is where the teacher's optima on such problems lie. The kernel's fill and retiming
   (retiming alone where a joint was clamped: its limit caps the fill) then time the repaired
   path and verify it as on the normal path. Where the fast repair finds no path within the
   path-only limits near the network's answer, the refinement, which starts from the same
   answer, is skipped unless ``refine_no_path``.

Nothing unverified leaves :meth:`PinnPlanner.plan`: every returned plan has passed step 3 on
the dense grid. The model card must name the rig the planner serves (name and
:attr:`rt_runtime.rig.Rig.planning_fingerprint`) and the model file's SHA-256; anything else is
refused at load time with a :class:`~rt_runtime.errors.ConfigurationError`.

``plan`` is the cheap path (tens of microseconds when no repair is needed, no allocation of
large arrays, no I/O); loading is the expensive one and happens once. The reasons and numbers
behind steps 2-5 are in docs/design-notes.md, decisions O2-O7.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import operator
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType, Problem
from rt_runtime.planning.verify import (
    COL_OBJECTIVE,
    COL_TOTAL,
    N_OUT,
    PLAN_C_RANGE,
    Verifier,
    VerifyResult,
    pack_inputs,
)
from rt_runtime.rig import Rig
from rt_runtime.trajectory.sextic import SexticTrajectory

FloatArray = NDArray[np.float64]

CARD_FORMAT = "excavator-rt-pinn-card/1"

#: Bound on a solution library's k (each candidate is a full plan, ~12 us).
LIBRARY_K_MAX = 64
#: The network's inputs and outputs (DESIGN.md "Models"): rad, rad, ..., m; rad/s^6 x 3, s.
INPUT_NAMES = ("theta11", "theta12", "theta13", "theta21", "theta22", "theta23", "H")
OUTPUT_NAMES = ("a16", "a26", "a36", "T")
#: The shipped models: the repository's top-level ``onnx/`` directory.
DEFAULT_MODEL_DIR = Path(__file__).resolve().parents[2] / "onnx"
#: SLSQP iterations of the bounded local refinement.
REFINE_ITERATIONS = 15
#: Most kernel calls of one fast repair: an evaluation of the repaired path, three on a coarse
#: grid for the volume secants, the fill and retiming, and a second one after a chord
#: correction of V_p.
FAST_REPAIR_CALLS = 6
# The fast repair's targets, normalised as the constraint values (:data:`CONSTRAINT_NAMES`):
# clamped joints this far inside their range, theta_p inside its range, V_p above V_min. They
# keep the repaired path feasible after the kernel's own arithmetic and the fill's scale search.
_REPAIR_JOINT_MARGIN = 1e-4
_REPAIR_THETA_P_MARGIN = 1e-3
_REPAIR_VOLUME_MARGIN = 1e-3
# The joint that sets the retimed T (acceleration, velocity or torque) moves this much less
# (its weight in the nearest-point metric): moving it lengthens the dig, which eq 11 punishes
# most (design notes, O6).
_REPAIR_BINDING_WEIGHT = 0.01
# Step of the volume secants, per joint range (K / 64 is the mid-path bulge): about the distance
# the repair moves, so that the chord correction is rarely needed (design notes, O6).
_REPAIR_GRADIENT_STEP = 2.0
# Samples of the coarse grid on which the volume secants are taken (as good as 21 or 101 samples
# for the repaired plans; design notes, O6).
_REPAIR_SECANT_SAMPLES = 11
_VOLUME_MIN = CONSTRAINT_NAMES.index("volume_min")
# Path-only constraints (they need the path, not T): joint ranges, theta_p, volume.
_ANGLES = slice(CONSTRAINT_NAMES.index("angle_min_boom"), CONSTRAINT_NAMES.index("velocity_boom"))
_PATH_SHAPE = slice(CONSTRAINT_NAMES.index("theta_p_min"), CONSTRAINT_NAMES.index("time_min"))
_VOLUME_MAX = CONSTRAINT_NAMES.index("volume_max")
_THETA_P = (CONSTRAINT_NAMES.index("theta_p_min"), CONSTRAINT_NAMES.index("theta_p_max"))
# Constraint columns time scaling can fix (it leaves the path, so angles, theta_p, volume alone).
_TIME_FIXABLE = frozenset(
    i
    for i, n in enumerate(CONSTRAINT_NAMES)
    if n.startswith(("velocity", "acceleration", "torque", "power")) or n == "time_min"
)


def _path_fails(ev: list[float]) -> bool:
    """A path-only limit (joint range, theta_p, volume) fails in the verifier row ``ev``."""
    return max(ev[_ANGLES]) > 0.0 or max(ev[_PATH_SHAPE]) > 0.0


def _path_fails_beyond_v_min(ev: list[float]) -> bool:
    """A path-only limit other than volume_min fails (what the V_min step cannot mend)."""
    return (
        max(ev[_ANGLES]) > 0.0
        or max(ev[_THETA_P[0] : _THETA_P[1] + 1]) > 0.0
        or (ev[_VOLUME_MAX] > 0.0)
    )


# Problem's slots, set directly by _problem: the frozen dataclass's __init__ sets each field
# through object.__setattr__, ~0.5 us of the cheap path's ~5 us of Python.
_new_object = object.__new__
_set_q_start = vars(Problem)["q_start_rad"].__set__
_set_q_end = vars(Problem)["q_end_rad"].__set__
_set_surface = vars(Problem)["surface_y_m"].__set__
_set_dig_type = vars(Problem)["dig_type"].__set__


def _problem(x: list[float], kind: DigType) -> Problem:
    """The problem of the planner's input row values ``x`` (entry, exit, H): equal to
    ``Problem((x[0], x[1], x[2]), (x[3], x[4], x[5]), x[6], kind)``, made in a third of the
    time."""
    problem: Problem = _new_object(Problem)
    _set_q_start(problem, (x[0], x[1], x[2]))
    _set_q_end(problem, (x[3], x[4], x[5]))
    _set_surface(problem, x[6])
    _set_dig_type(problem, kind)
    return problem


def _planned(
    x: list[float],
    kind: DigType,
    a6: tuple[float, float, float],
    T: float,
    raw_a6: tuple[float, float, float],
    raw_T: float,
    status: PlanStatus,
    evaluation: FloatArray,
    infer_us: float,
    t0: float,
    scale: float = 1.0,
) -> PinnPlan:
    """A returned plan; its ``plan_us`` runs from ``t0`` (perf_counter) to now."""
    return PinnPlan(
        _problem(x, kind), a6, T, raw_a6, raw_T, status, evaluation, infer_us,
        (time.perf_counter() - t0) * 1e6, scale,
    )  # fmt: skip


def fill_c_range(c_max: float) -> tuple[float, float]:
    """The fill step's range of bulge scales with its top capped at ``c_max`` (> 0)."""
    if not c_max > 0.0:
        raise ValueError(f"c_max must be > 0; got {c_max!r}")
    return (min(PLAN_C_RANGE[0], c_max), c_max)


def _nearest(
    K: list[float], w: list[float], cons: list[tuple[list[float], float]]
) -> list[float] | None:
    """The point nearest ``K`` meeting every half-space ``a . K' <= b`` of ``cons``.

    Distance: ``sum((K'_j - K_j)^2 / w_j)``; a joint with ``w_j = 0`` does not move. A convex
    quadratic programme with at most three constraints, solved by a greedy active set in closed
    form: the first constraint ``K`` violates (the optimum's active set holds one, or projecting
    would return ``K``), then, when its projection violates another, both (two free joints
    meet two constraints at a point). Exact where the constraints ``K`` meets are met by the
    projection or one of them is active at the optimum, the repair's case (V_min with one
    theta_p limit). Plain floats: numpy's call overhead (~1 us) exceeds the arithmetic.

    Returns:
        The point (``K`` itself when it already meets them), or None when the greedy set gives
        no point meeting all.
    """
    K0, K1, K2 = K
    w0, w1, w2 = w
    P0, P1, P2 = K0, K1, K2
    first: tuple[float, float, float, float, float] | None = None
    for _ in range(2):
        for a, b in cons:
            a0, a1, a2 = a
            if a0 * P0 + a1 * P1 + a2 * P2 > b + 1e-12 * (1.0 + abs(b)):
                break
        else:
            return [P0, P1, P2]
        wa0, wa1, wa2 = w0 * a0, w1 * a1, w2 * a2
        m = a0 * wa0 + a1 * wa1 + a2 * wa2
        r = b - (a0 * K0 + a1 * K1 + a2 * K2)
        if first is None:
            if not m > 0.0:
                return None  # only fixed joints in it
            first = (wa0, wa1, wa2, m, r)
            f0, f1, f2 = a0, a1, a2
            lam = r / m
            P0, P1, P2 = K0 + lam * wa0, K1 + lam * wa1, K2 + lam * wa2
        else:
            v0, v1, v2, mf, rf = first
            mx = f0 * wa0 + f1 * wa1 + f2 * wa2
            det = mf * m - mx * mx
            if not abs(det) > 1e-12 * mf * m:
                return None  # parallel constraints, or only fixed joints in the second
            lf = (m * rf - mx * r) / det
            ls = (mf * r - mx * rf) / det
            P0 = K0 + lf * v0 + ls * wa0
            P1 = K1 + lf * v1 + ls * wa1
            P2 = K2 + lf * v2 + ls * wa2
    for a, b in cons:
        if a[0] * P0 + a[1] * P1 + a[2] * P2 > b + 1e-12 * (1.0 + abs(b)):
            return None
    return [P0, P1, P2]


class _Repair(IntEnum):
    """Outcome of :meth:`PinnPlanner._fast_repair`."""

    DONE = 0  # a verified plan
    SKIPPED = 1  # not its case (no path-only violation, V_max, theta_p of a late entry)
    NO_PATH = 2  # no path meeting every path-only limit found near the network's
    UNTIMED = 3  # a path meeting them, which no T in range times (torque, power)


class PlanStatus(IntEnum):
    """How a returned plan came about."""

    RETIMED = 0  # the network's path, bulge scaled to fill the bucket, at its smallest feasible T
    RAW = 1  # the network's answer as it was (retiming off), verified
    TIME_SCALED = 2  # repaired by time scaling (retiming off)
    REFINED = 3  # repaired by the bounded local refinement
    TEACHER = 4  # out of the model's domain; planned by the PSO teacher (when allowed)
    REPAIRED = 5  # path direction repaired in closed form (fast repair), then filled and retimed
    LIBRARY = 6  # a nearby teacher solution's path direction, filled and retimed (beat the network)


@dataclass(frozen=True, slots=True)
class ModelCard:
    """The parts of a model card the runtime checks (the whole card is in ``raw``)."""

    path: Path
    model_path: Path
    dig_type: DigType
    rig: str
    rig_planning_fingerprint: str
    model_sha256: str
    domain_min: tuple[float, ...]
    domain_max: tuple[float, ...]
    raw: dict[str, Any]
    card_sha256: str = ""


def _finite_number(x: object) -> bool:
    """A JSON number (not a bool) that is finite as a float."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:  # an integer beyond the float range
        return False


def _card_string(where: object, raw: dict[str, Any], key: str) -> str:
    value = raw.get(key)
    if not isinstance(value, str) or not value:
        raise ConfigurationError(f"{where}: {key} must be a non-empty string; got {value!r:.80}")
    return value


def load_card(card_path: Path) -> ModelCard:
    """Read and check a model card (not yet against a rig).

    Raises:
        ConfigurationError: Missing file, not JSON, wrong format, or a missing/ill-typed key
            (the message names the key and what it must be).
    """
    if not card_path.is_file():
        raise ConfigurationError(
            f"model card {card_path} does not exist (a model needs its card beside it)"
        )
    try:
        data = card_path.read_bytes()
        raw = json.loads(data.decode())
    # ValueError: not UTF-8, not JSON, or an integer of more than 4300 digits.
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"model card {card_path} is not valid JSON: {exc}") from exc
    if not isinstance(raw, dict) or raw.get("format") != CARD_FORMAT:
        raise ConfigurationError(f"{card_path}: format must be {CARD_FORMAT!r}")
    model_file, dig, rig, fingerprint, digest = (
        _card_string(card_path, raw, key)
        for key in ("model_file", "dig_type", "rig", "rig_planning_fingerprint", "model_sha256")
    )
    kinds = [k.name.lower() for k in DigType]
    if dig.lower() not in kinds:
        raise ConfigurationError(
            f"{card_path}: dig_type must be one of {', '.join(kinds)}; got {dig!r:.80}"
        )
    domain = raw.get("domain")
    if not isinstance(domain, dict):
        raise ConfigurationError(f"{card_path}: domain must be an object with min and max")
    bounds: list[tuple[float, ...]] = []
    for key in ("min", "max"):
        values = domain.get(key)
        if not (isinstance(values, list) and len(values) == 7 and all(map(_finite_number, values))):
            raise ConfigurationError(
                f"{card_path}: domain.{key} must be 7 finite numbers; got {values!r:.120}"
            )
        bounds.append(tuple(float(v) for v in values))
    lo, hi = bounds
    if not all(a < b for a, b in zip(lo, hi, strict=True)):
        raise ConfigurationError(f"{card_path}: domain.min/max must be 7 increasing pairs")
    return ModelCard(
        path=card_path,
        model_path=card_path.parent / model_file,
        dig_type=DigType[dig.upper()],
        rig=rig,
        rig_planning_fingerprint=fingerprint,
        model_sha256=digest,
        domain_min=lo,
        domain_max=hi,
        raw=raw,
        card_sha256=hashlib.sha256(data).hexdigest(),
    )


class _Library:
    """A dig type's solution library: the teacher's answers to its training problems.

    Module docstring, step 4a. ``X`` are the problems, ``Y`` the teacher's ``(a16, a26, a36,
    T)``; nearest neighbours are found in inputs scaled by the library's own per-input
    standard deviation, by a k-d tree over the scaled problems (design notes, "The library
    search in scipy"). The scratch rows for the ``k`` candidates are allocated once.
    """

    def __init__(self, card: ModelCard) -> None:
        entry = card.raw["library"]
        where = str(card.path)
        if not isinstance(entry, dict):
            raise ConfigurationError(f"{where}: library must be an object; got {entry!r:.80}")
        name = _card_string(f"{where}: library", entry, "name")
        digest = _card_string(f"{where}: library", entry, "sha256")
        trigger, k = entry.get("trigger_bulge_scale"), entry.get("k")
        if not _finite_number(trigger):
            raise ConfigurationError(
                f"{where}: library trigger_bulge_scale must be a finite number; got {trigger!r:.80}"
            )
        if isinstance(k, bool) or not isinstance(k, int):
            raise ConfigurationError(f"{where}: library k must be an integer; got {k!r:.80}")
        path = card.path.parent / name
        self.path, self.sha256 = path, digest
        self.trigger = float(trigger)  # type: ignore[arg-type]
        self.k = k
        check_file(where, "library", path, digest)
        with np.load(path, allow_pickle=False) as z:
            X = np.array(z["X"], dtype=np.float64)
            Y = np.array(z["Y"], dtype=np.float64)
        n = X.shape[0]
        if X.shape != (n, 7) or Y.shape != (n, 4) or n < 1:
            raise ConfigurationError(
                f"library {path}: X and Y must be (N, 7) and (N, 4), N >= 1; got {X.shape}, "
                f"{Y.shape}"
            )
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y)) and np.all(Y[:, 3] > 0.0)):
            raise ConfigurationError(f"library {path}: values must be finite, T > 0")
        if not (1 <= self.k <= min(n, LIBRARY_K_MAX) and self.trigger > 0.0):
            raise ConfigurationError(
                f"{where}: library k must be in [1, {min(n, LIBRARY_K_MAX)}] and "
                f"trigger_bulge_scale > 0; got {self.k}, {self.trigger}"
            )
        self.inv_std = 1.0 / np.maximum(X.std(axis=0), 1e-12)
        self.tree = cKDTree(X * self.inv_std)
        self.Y = Y
        self.rows = np.zeros((self.k, 12), dtype=np.float64)
        self.out = np.zeros((self.k, N_OUT), dtype=np.float64)
        self.retimed = np.zeros((self.k, 4), dtype=np.float64)
        self.scale = np.ones(self.k, dtype=np.float64)

    def nearest(self, x: list[float]) -> NDArray[np.intp]:
        """Rows of the ``k`` problems nearest to ``x`` (7 inputs, unscaled), nearest first."""
        _, rows = self.tree.query(np.multiply(x, self.inv_std), k=self.k)
        return np.atleast_1d(np.asarray(rows, dtype=np.intp))


def check_file(where: str, what: str, path: Path, expected_sha256: str) -> None:
    """Raise ConfigurationError unless the file a card names (``what``: model, library) exists
    and has the card's SHA-256 (``where``: the card)."""
    if not path.is_file():
        raise ConfigurationError(f"{where}: {what} file {path} does not exist")
    digest = sha256_file(path)
    if digest != expected_sha256:
        raise ConfigurationError(
            f"{what} {path} is corrupt or was replaced: SHA-256 {digest[:12]}... differs from "
            f"its card's {expected_sha256[:12]}..."
        )


def sha256_file(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes (model files against their cards)."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class PinnPlan(NamedTuple):
    """A verified one-shot plan (immutable; a named tuple, not a frozen dataclass, because the
    latter's construction costs ~0.8 us more per plan).

    Attributes:
        problem: What was planned.
        a6: Sixth-order coefficients (rad/s^6) of the verified trajectory.
        T_s: Its duration.
        raw_a6, raw_T_s: The network's answer before retiming or repair.
        status: How the plan came about.
        evaluation: The verifier's output row for the returned trajectory (columns of
            :mod:`rt_runtime.planning.verify`); always feasible.
        infer_us: Inference time (onnxruntime call).
        plan_us: Whole planning time (domain check, inference, verification, repair).
        bulge_scale: c of the executed path K = c K_net (1.0: the network's own path); for
            :attr:`PlanStatus.REPAIRED`, c of the fill relative to the repaired direction; for
            :attr:`PlanStatus.LIBRARY`, relative to the library answer's bulge.
    """

    problem: Problem
    a6: tuple[float, float, float]
    T_s: float
    raw_a6: tuple[float, float, float]
    raw_T_s: float  # noqa: N815 (T is the paper's symbol)
    status: PlanStatus
    evaluation: FloatArray
    infer_us: float
    plan_us: float
    bulge_scale: float = 1.0

    @property
    def verification(self) -> VerifyResult:
        """The verification of the returned trajectory."""
        return VerifyResult.from_row(self.evaluation)

    def trajectory(self) -> SexticTrajectory:
        """The verified joint trajectory."""
        return SexticTrajectory(
            np.asarray(self.problem.q_start_rad),
            np.asarray(self.problem.q_end_rad),
            np.asarray(self.a6),
            self.T_s,
        )


class _Session:
    """One dig type's network: a latency-tuned session bound to preallocated buffers."""

    def __init__(self, card: ModelCard) -> None:
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(
                str(card.model_path), so, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph/... types
            raise ConfigurationError(
                f"model {card.model_path} cannot be loaded by onnxruntime: {exc}"
            ) from exc
        inputs = self.session.get_inputs()
        outputs = self.session.get_outputs()
        if (
            len(inputs) != 1
            or len(outputs) != 1
            or inputs[0].shape[-1] != 7
            or outputs[0].shape[-1] != 4
        ):
            raise ConfigurationError(
                f"model {card.model_path} must map (batch, 7) to (batch, 4); it has inputs "
                f"{[(i.name, i.shape) for i in inputs]} and outputs "
                f"{[(o.name, o.shape) for o in outputs]}"
            )
        self.input_name = inputs[0].name
        self.output_name = outputs[0].name
        self.x = np.zeros((1, 7), dtype=np.float32)
        self.y = np.zeros((1, 4), dtype=np.float32)
        self.binding = self.session.io_binding()
        self._x_ort = ort.OrtValue.ortvalue_from_numpy(self.x)
        self._y_ort = ort.OrtValue.ortvalue_from_numpy(self.y)
        self.binding.bind_ortvalue_input(self.input_name, self._x_ort)
        self.binding.bind_ortvalue_output(self.output_name, self._y_ort)
        # The C-level call, without the Python wrapper's WebGPU capture bookkeeping (~1 us) and
        # with no RunOptions; the public wrapper where the private names ever change.
        sess_c = getattr(self.session, "_sess", None)
        bind_c = getattr(self.binding, "_iobinding", None)
        run: Callable[[], Any]
        if sess_c is not None and bind_c is not None:
            run = functools.partial(sess_c.run_with_iobinding, bind_c, None)
        else:

            def run() -> None:
                self.session.run_with_iobinding(self.binding)

        self.run = run
        for _ in range(3):  # warm up (the first runs allocate)
            self.run()

    def batch(self, X: FloatArray) -> FloatArray:
        """Inference on many inputs (allocates; for planners and reports, not the loop)."""
        y = self.session.run([self.output_name], {self.input_name: X.astype(np.float32)})[0]
        return np.asarray(y, dtype=np.float64)


class PinnPlanner:
    """Plans one-shot digs with the shipped networks, verifying every answer.

    Args:
        rig: The rig; must match both model cards.
        model_dir: Directory holding ``pinn_downward.onnx``/``.json`` and
            ``pinn_backward.onnx``/``.json``.
        n_verify: Samples of the verification grid.
        retime: Fill and retime the network's path (step 4 above,
            :meth:`rt_runtime.planning.verify.Verifier.plan_into`); off, the network's answer
            is kept when it verifies.
        fast_repair: Allow the fast repair (module docstring, step 5) before the refinement.
        refine: Allow the bounded local refinement when neither time scaling nor the fast
            repair can repair a plan.
        refine_no_path: Run the refinement also where the fast repair found no path meeting the
            path-only limits near the network's answer. Off by default: the refinement starts
            from the same answer, takes milliseconds, and its memory traffic slows the plans
            after it (design notes, O6).
        teacher_fallback: Plan out-of-domain problems with the PSO teacher instead of refusing
            them (seconds, not microseconds: never inside the loop).
        library: Load the solution libraries the cards name (module docstring, step 4a);
            False plans with the networks alone.

    Raises:
        ConfigurationError: The C kernel is not built (the plan, retiming and repair run in
            it); a missing or corrupt model or card, a card for another rig or
            another set of rig values, a model file whose hash differs from its card; a
            library file that is missing, differs from its card's hash or holds bad arrays.
    """

    def __init__(
        self,
        rig: Rig,
        model_dir: Path | str = DEFAULT_MODEL_DIR,
        *,
        n_verify: int = oneshot.DEFAULT_SAMPLES,
        retime: bool = True,
        fast_repair: bool = True,
        refine: bool = True,
        refine_no_path: bool = False,
        teacher_fallback: bool = False,
        library: bool = True,
    ) -> None:
        planning = oneshot.require_planning(rig)
        self.rig = rig
        self.retime = retime
        self.fast_repair = fast_repair
        self.refine = refine
        self.refine_no_path = refine_no_path
        self.teacher_fallback = teacher_fallback
        self.verifier = Verifier(rig, n_verify, backend="c")
        self.cards: dict[DigType, ModelCard] = {}
        self._sessions: dict[DigType, _Session] = {}
        self._libraries: dict[DigType, _Library] = {}
        directory = Path(model_dir)
        for kind in DigType:
            stem = f"pinn_{kind.name.lower()}"
            card = load_card(directory / f"{stem}.json")
            self._check_card(card, kind)
            self.cards[kind] = card
            self._sessions[kind] = _Session(card)
            if library and card.raw.get("library") is not None:
                self._libraries[kind] = _Library(card)
        self._row = np.zeros((1, 12), dtype=np.float64)
        self._out = np.zeros((1, N_OUT), dtype=np.float64)
        self._retimed = np.zeros((1, 4), dtype=np.float64)
        self._scale = np.ones(1, dtype=np.float64)
        self._lo = {k: c.domain_min for k, c in self.cards.items()}
        self._hi = {k: c.domain_max for k, c in self.cards.items()}
        # The cheap path's views and lookups, made once (each costs 0.1-0.3 us per call).
        self._kinds = {int(k): k for k in DigType}
        self._qs_view = self._row[0, 0:3]
        self._qe_view = self._row[0, 3:6]
        self._x_view = self._row[0, 0:7]
        self._y_view = self._row[0, 8:12]
        self._retimed_row = self._retimed[0]
        self._out_row = self._out[0]
        # plan_into, evaluate_into and retime_into without their Python wrappers (the range is
        # checked here, once per range).
        self._plan_rows = self.verifier._plan
        self._eval_rows = self.verifier._run
        self._retime_rows = self.verifier._retime
        self._c_default = (float(PLAN_C_RANGE[0]), float(PLAN_C_RANGE[1]))
        self._front: Callable[..., tuple[bool, float] | None]
        self._bind_front()
        # The fast repair's constants and scratch rows (module docstring, step 5).
        n = self.verifier.n_samples
        s = np.linspace(0.0, 1.0, n)[1:-1]  # p(s) = 0 at both ends: every K keeps them
        # K_j's bound from sample s is (c - D_j q(s)) / p(s): basis columns 1/p and -q/p.
        pinv = 1.0 / (s**3 * (1.0 - s) ** 3)
        q = 10.0 * s**3 - 15.0 * s**4 + 6.0 * s**5
        self._fr_basis = np.ascontiguousarray(np.stack([pinv, -q * pinv], axis=1))
        self._fr_v = np.zeros(2, dtype=np.float64)
        self._fr_qmin = tuple(float(v) for v in rig.q_min_rad)
        self._fr_qmax = tuple(float(v) for v in rig.q_max_rad)
        self._fr_span = tuple(float(v) for v in rig.q_max_rad - rig.q_min_rad)
        self._fr_len = tuple(float(v) for v in rig.lengths_m)
        self._fr_tp: dict[DigType, tuple[float, float, float]] = {}
        for k, (lo, hi) in (
            (DigType.DOWNWARD, planning.theta_p_downward_rad),
            (DigType.BACKWARD, planning.theta_p_backward_rad),
        ):
            self._fr_tp[k] = (float(lo), float(hi), _REPAIR_THETA_P_MARGIN * float(hi - lo))
        self._fr_row = np.zeros((1, 12), dtype=np.float64)
        self._fr_out = np.zeros((1, N_OUT), dtype=np.float64)
        self._fr_in = self._fr_row[0]
        self._fr_out_row = self._fr_out[0]
        self._coarse = Verifier(rig, _REPAIR_SECANT_SAMPLES, backend="c")
        self._coarse_rows = self._coarse._run

    def verified_files(self) -> tuple[tuple[Path, str], ...]:
        """Every file the planner was loaded and verified from, with its SHA-256: each dig
        type's card, model and solution library (see :mod:`rt_runtime.planning.filewatch`)."""
        files: list[tuple[Path, str]] = []
        for kind, card in self.cards.items():
            files += [(card.path, card.card_sha256), (card.model_path, card.model_sha256)]
            lib = self._libraries.get(kind)
            if lib is not None:
                files.append((lib.path, lib.sha256))
        return tuple(files)

    def _check_card(self, card: ModelCard, kind: DigType) -> None:
        where = str(card.path)
        if card.dig_type != kind:
            raise ConfigurationError(
                f"{where}: card is for {card.dig_type.name.lower()} digs, expected "
                f"{kind.name.lower()}"
            )
        if card.rig != self.rig.name:
            raise ConfigurationError(
                f"{where}: model trained for rig {card.rig!r}; this planner serves "
                f"{self.rig.name!r}. Train and export a model for this rig."
            )
        if card.rig_planning_fingerprint != self.rig.planning_fingerprint:
            raise ConfigurationError(
                f"{where}: model trained for other values of rig {card.rig!r} (planning "
                f"fingerprint {card.rig_planning_fingerprint[:12]}..., the profile now has "
                f"{self.rig.planning_fingerprint[:12]}...); retrain for the current profile"
            )
        check_file(where, "model", card.model_path, card.model_sha256)

    # -- the cheap path ---------------------------------------------------------------------

    def _domain_error(self, kind: DigType, x: list[float]) -> str | None:
        lo, hi = self._lo[kind], self._hi[kind]
        for i in range(7):
            v = x[i]
            if not lo[i] <= v <= hi[i]:  # also catches NaN
                name = INPUT_NAMES[i]
                unit = "m" if i == 6 else "rad"
                if not math.isfinite(v):
                    return f"input {name} is {v}; inputs must be finite"
                return (
                    f"input {name} = {v:.6g} {unit} is outside the {kind.name.lower()} model's "
                    f"domain [{lo[i]:.6g}, {hi[i]:.6g}] {unit}"
                )
        return None

    def _bind_front(self) -> None:
        """The cheap path's staging, inference and plan in one call: the C kernel's ``Front``
        bound to this planner's buffers and onnxruntime sessions (design notes, V5). Called again
        where a session is replaced."""
        kinds = list(DigType)  # indexed by value: 0 downward, 1 backward
        sessions = [self._sessions[k] for k in kinds]
        front = self.verifier.kernel.front(
            self._row, self._out, self._retimed, self._scale,
            np.array([self._lo[k] for k in kinds], dtype=np.float64),
            np.array([self._hi[k] for k in kinds], dtype=np.float64),
            tuple(s.x for s in sessions), tuple(s.y for s in sessions),
            tuple(s.run for s in sessions),
        )  # fmt: skip
        self._front = front.plan

    def _stage(
        self, q_start_rad: ArrayLike, q_end_rad: ArrayLike, surface_y_m: float, kind: DigType
    ) -> tuple[bool, float] | None:
        """The input into the row, checked against ``kind``'s domain, and the network's answer
        into the row: None outside the domain (or not finite; nothing run), else
        ``(False, infer_us)``."""
        self._qs_view[:] = q_start_rad
        self._qe_view[:] = q_end_rad
        row = self._row
        row[0, 6] = surface_y_m
        x = self._x_view.tolist()
        # Inside the domain (NaN compares False).
        if not (
            all(map(operator.le, self._lo[kind], x)) and all(map(operator.le, x, self._hi[kind]))
        ):
            return None
        sess = self._sessions[kind]
        sess.x[0] = self._x_view
        t1 = time.perf_counter()
        sess.run()
        infer_us = (time.perf_counter() - t1) * 1e6
        row[0, 7] = kind
        self._y_view[:] = sess.y[0]
        return False, infer_us

    def plan(
        self,
        q_start_rad: ArrayLike,
        q_end_rad: ArrayLike,
        surface_y_m: float,
        dig_type: DigType,
        *,
        c_max: float | None = None,
        library: bool = True,
    ) -> PinnPlan:
        """Plan one dig: domain check, inference, retiming/verification, repair if needed.

        Args:
            q_start_rad: Entry pose (3,).
            q_end_rad: Exit pose (3,).
            surface_y_m: Material surface height H.
            dig_type: Which network.
            c_max: Cap on the fill step's bulge scale (:func:`fill_c_range`); None: the
                default range :data:`rt_runtime.planning.verify.PLAN_C_RANGE`. The trench
                planner caps it where a fuller bucket would cut below the design profile.
            library: Whether a retimed plan whose fill scaled the bulge by the card's
                ``trigger_bulge_scale`` or more may be replaced by a nearby teacher solution's
                path (module docstring, step 4a; only with a model that ships a library).
                False keeps the network's path direction (the trench planner screens on it).

        Returns:
            A plan whose trajectory satisfies every limit of Yao eq 12 on the verification grid.

        Raises:
            PlanningError: Input outside the model's domain (or not finite) when the teacher
                fallback is off; a plan that neither time scaling, the fast repair nor the
                refinement could repair, naming the violated limit.
        """
        t0 = time.perf_counter()
        try:
            kind = self._kinds[dig_type]
        except (KeyError, TypeError):  # not a dig type's value: DigType names what is wrong
            kind = DigType(dig_type)
        tried: _Repair | None = None  # the fast repair's outcome, once tried
        if self.retime:
            c_lo, c_hi = self._c_default if c_max is None else fill_c_range(c_max)
            done = self._front(q_start_rad, q_end_rad, surface_y_m, kind, c_lo, c_hi)
        else:
            done = self._stage(q_start_rad, q_end_rad, surface_y_m, kind)
        x = self._x_view.tolist()
        if done is None:  # outside the domain or not finite: nothing was run
            why = self._domain_error(kind, x)
            problem = _problem(x, kind)
            if self.teacher_fallback and all(map(math.isfinite, x)):
                return self._teacher(problem, t0)
            raise PlanningError(f"refused: {why}; nothing was planned")
        ok, infer_us = done
        from_library = (
            ok
            and library
            and (lib := self._libraries.get(kind)) is not None
            and self._scale[0] >= lib.trigger
            and self._from_library(lib, x, kind, c_lo, c_hi)
        )
        y = self._y_view.tolist()
        raw_a6 = (y[0], y[1], y[2])
        raw_T = y[3]
        out = self._out
        row = self._row

        if self.retime:
            status = PlanStatus.LIBRARY if from_library else PlanStatus.RETIMED
            if not ok and self.fast_repair:
                # A failed plan reports the network's own path (scale 1): retimed, or, where a
                # path-only limit fails (no T fixes it), at the network's own T. Its path-only
                # values are the network path's either way (they do not depend on T), and its
                # time-dependent ones are at a T of that path, all the fast repair reads (to
                # find the joint that sets T).
                if self._scale[0] != 1.0:
                    self._eval_rows(row, out, None)
                tried = self._fast_repair(kind, self._out_row.tolist(), (c_lo, c_hi))
                ok = tried == _Repair.DONE
                status = PlanStatus.REPAIRED
            if ok:
                r = self._retimed_row.tolist()
                return _planned(
                    x, kind, (r[0], r[1], r[2]), r[3], raw_a6, raw_T, status,
                    self._out_row.copy(), infer_us, t0, float(self._scale[0]),
                )  # fmt: skip
            self.verifier.evaluate_into(row, out)  # back to the network's own answer
        else:
            self.verifier.evaluate_into(row, out)
            if self._out_row[COL_TOTAL] <= 0.0:
                return _planned(
                    x, kind, raw_a6, raw_T, raw_a6, raw_T, PlanStatus.RAW,
                    self._out_row.copy(), infer_us, t0,
                )  # fmt: skip
        problem = _problem(x, kind)
        a6_ok, T_ok, status = self._repair(problem, raw_a6, raw_T, tried)
        final = self._evaluation(problem, a6_ok, T_ok)
        if final[COL_TOTAL] > 0.0:  # the repair paths verify; this guards the guarantee
            raise PlanningError(
                f"refused: repaired plan fails verification ({self._worst(final)}); "
                "nothing was planned"
            )
        return _planned(x, kind, a6_ok, T_ok, raw_a6, raw_T, status, final, infer_us, t0)

    def _from_library(
        self, lib: _Library, x: list[float], kind: DigType, c_lo: float, c_hi: float
    ) -> bool:
        """Plan the ``k`` nearest library solutions' paths for the problem ``x`` (filled and
        retimed as the network's) and, where the best feasible one has a smaller objective than
        the plan in ``_out``, put it there (and in ``_retimed``, ``_scale``): True."""
        rows = lib.rows
        rows[:, 0:7] = x
        rows[:, 7] = kind
        rows[:, 8:12] = lib.Y[lib.nearest(x)]
        self._plan_rows(rows, lib.out, lib.retimed, c_lo, c_hi, None, lib.scale)
        objective = np.where(lib.out[:, COL_TOTAL] <= 0.0, lib.out[:, COL_OBJECTIVE], np.inf)
        best = int(np.argmin(objective))
        if not objective[best] < self._out_row[COL_OBJECTIVE]:
            return False
        self._out[0] = lib.out[best]
        self._retimed[0] = lib.retimed[best]
        self._scale[0] = lib.scale[best]
        return True

    # -- repair -----------------------------------------------------------------------------

    def _repair(
        self,
        problem: Problem,
        a6: tuple[float, float, float],
        T: float,
        tried: _Repair | None,
    ) -> tuple[tuple[float, float, float], float, PlanStatus]:
        """Time scaling, then the fast repair (unless ``tried``: its outcome already), then
        refinement, of the network's answer, whose evaluation is in ``self._out``;
        PlanningError naming its worst limit when none verifies."""
        ev = self._out[0].tolist()
        planning = oneshot.require_planning(self.rig)
        bad = {i for i in range(len(CONSTRAINT_NAMES)) if ev[i] > 0.0}
        if bad <= _TIME_FIXABLE:
            # The kernel's exact retiming: the path kept, the smallest T in [t_min, t_max] at
            # which every time-dependent limit holds.
            res = np.empty((1, N_OUT))
            retimed = np.empty((1, 4))
            self.verifier.retime_into(self._row, res, retimed)
            if res[0, COL_TOTAL] <= 0.0:
                r = retimed[0].tolist()
                return (r[0], r[1], r[2]), r[3], PlanStatus.TIME_SCALED
        if tried is None and self.fast_repair:
            tried = self._fast_repair(problem.dig_type, ev, None)
            if tried == _Repair.DONE:
                r = self._retimed_row.tolist()
                return (r[0], r[1], r[2]), r[3], PlanStatus.REPAIRED
        refine = self.refine and (tried != _Repair.NO_PATH or self.refine_no_path)
        if refine:
            refined = self._refine(problem, a6, T)
            if refined is not None:
                return refined[0], refined[1], PlanStatus.REFINED
        worst = max(range(len(CONSTRAINT_NAMES)), key=ev.__getitem__)
        how = [f"time scaling within T <= {planning.t_max_s:g} s"]
        if tried == _Repair.NO_PATH:
            how.append("fast repair: no path within the path-only limits near the network's")
        elif tried == _Repair.UNTIMED:
            how.append("fast repair: its path cannot be timed")
        if refine:
            how.append("local refinement")
        raise PlanningError(
            f"refused: the {problem.dig_type.name.lower()} plan violates {CONSTRAINT_NAMES[worst]} "
            f"by {ev[worst]:.4g} (normalised; <= 0 allowed) and could not be repaired "
            f"({'; '.join(how)}); nothing was planned"
        )

    def _fast_repair(
        self, kind: DigType, ev: list[float], c_range: tuple[float, float] | None
    ) -> _Repair:
        """Repair the direction of the network's path (``self._row``) in closed form and plan it.

        Module docstring, step 5: clamp each violating joint's K_i into its range's interval,
        project K onto the theta_p half-spaces, and where V_min fails, step to the nearest point
        of the linearised V_min (with one chord correction); at most
        :data:`FAST_REPAIR_CALLS` kernel calls, no allocation of arrays beyond the joint
        intervals'.

        Args:
            kind: The dig type.
            ev: The verifier's output row for the network's path (``N_OUT`` floats; its
                path-only values are used, its time-dependent ones only to find the joint that
                sets T).
            c_range: The fill's range of the final :meth:`Verifier.plan_into`; None: retime
                only (:meth:`Verifier.retime_into`), as with ``retime=False``.

        Returns:
            The outcome; for :attr:`_Repair.DONE` ``self._retimed`` holds the verified plan,
            ``self._out`` its evaluation and ``self._scale`` its fill scale (1.0 for a
            retiming).
        """
        if not _path_fails(ev) or ev[_VOLUME_MAX] > 0.0:
            return _Repair.SKIPPED  # only time-dependent limits fail (retiming's case), or V_max
        src = self._row[0].tolist()
        T = src[11]
        t6 = T**6
        K = [-src[8] * t6, -src[9] * t6, -src[10] * t6]
        if not (T > 0.0 and math.isfinite(K[0] + K[1] + K[2])):
            return _Repair.SKIPPED
        D = [src[3] - src[0], src[4] - src[1], src[5] - src[2]]
        span = self._fr_span
        # Metric of the nearest point: K_i in units of its joint's range; fixed joints weigh 0.
        w = [span[0] * span[0], span[1] * span[1], span[2] * span[2]]
        # 1. Joint ranges: q_min <= qs + D q(s) + K p(s) <= q_max at every sample with p > 0,
        # an interval of K_j; the violated end clamps K_j (the other end is left to the checks).
        clamped = False
        for j in range(3):
            low = ev[j] > 0.0
            if low or ev[3 + j] > 0.0:
                m = _REPAIR_JOINT_MARGIN * span[j]
                v = self._fr_v
                v[1] = D[j]
                if low:
                    v[0] = self._fr_qmin[j] + m - src[j]
                    K[j] = max(K[j], float(self._fr_basis.dot(v).max()))
                else:
                    v[0] = self._fr_qmax[j] - m - src[j]
                    K[j] = min(K[j], float(self._fr_basis.dot(v).min()))
                w[j] = 0.0
                clamped = True
        # The joint that sets T: the largest time factor squared (velocity ~ 1/T, the others
        # ~ 1/T^2); it moves least.
        f0 = max((1.0 + ev[6]) ** 2, 1.0 + ev[9], 1.0 + ev[12])
        f1 = max((1.0 + ev[7]) ** 2, 1.0 + ev[10], 1.0 + ev[13])
        f2 = max((1.0 + ev[8]) ** 2, 1.0 + ev[11], 1.0 + ev[14])
        binding = 0 if f0 >= f1 and f0 >= f2 else (1 if f1 >= f2 else 2)
        w[binding] *= _REPAIR_BINDING_WEIGHT
        # 2. theta_p: half-spaces of K for a dig that starts on the surface.
        cons = self._theta_p_halfspaces(kind, src, D, K)
        if cons is None:
            if ev[_THETA_P[0]] > 0.0 or ev[_THETA_P[1]] > 0.0:
                return _Repair.SKIPPED  # theta_p of a dig that enters later: not linear in K
            cons = []
        elif cons:
            K_new = _nearest(K, w, cons)
            if K_new is None:
                return _Repair.NO_PATH
            K = K_new
        fr = self._fr_in
        fr[:] = self._row[0]
        o = self._fr_evaluate(K, t6)
        g: list[float] | None = None
        if _path_fails(o):
            # 3. V_min: linearised by a secant per free joint (at most two: with three, the one
            # that sets T stays), over about the distance the repair moves.
            if _path_fails_beyond_v_min(o):
                return _Repair.NO_PATH
            if w[0] > 0.0 and w[1] > 0.0 and w[2] > 0.0:
                w[binding] = 0.0
            # The secants on a coarse grid: ~0.15x the cost of an evaluation; its bias in V_p
            # (~0.1 of the V range at 11 samples, smooth in K) cancels in the differences.
            g = [0.0, 0.0, 0.0]
            base = None
            for j in range(3):
                if w[j] > 0.0:
                    if base is None:
                        base = self._fr_evaluate_coarse(K, t6)
                    h = _REPAIR_GRADIENT_STEP * span[j]
                    K_h = K.copy()
                    K_h[j] += h
                    g[j] = (self._fr_evaluate_coarse(K_h, t6) - base) / h
            K_new = self._volume_step(K, w, g, o[_VOLUME_MIN], cons)
            if K_new is None:
                return _Repair.NO_PATH
            K = K_new
        # 4. The kernel's fill and retiming of the repaired path, verified as on the normal
        # path. A clamped joint's limit caps the fill at c ~ 1 anyway: retiming alone is the
        # same plan, 7 us cheaper.
        fill = None if clamped else c_range
        if self._fr_plan(K, t6, fill):
            return _Repair.DONE
        # The failed plan reports the repaired path itself (scale 1): its path-only values
        # are K's.
        o = self._out_row.tolist()
        if not _path_fails(o):
            return _Repair.UNTIMED  # a path that meets every path-only limit, but no T times it
        if g is None or _path_fails_beyond_v_min(o):
            return _Repair.NO_PATH
        # One chord correction with the same secants, where V_min alone still fails.
        K_new = self._volume_step(K, w, g, o[_VOLUME_MIN], cons)
        if K_new is None:
            return _Repair.NO_PATH
        if self._fr_plan(K_new, t6, fill):
            return _Repair.DONE
        o = self._out_row.tolist()
        if not _path_fails(o):
            return _Repair.UNTIMED
        return _Repair.NO_PATH

    @staticmethod
    def _volume_step(
        K: list[float],
        w: list[float],
        g: list[float],
        v: float,
        cons: list[tuple[list[float], float]],
    ) -> list[float] | None:
        """The point nearest K where the linearised volume_min value ``v + g . (K' - K)`` is
        the repair's margin below 0 and the half-spaces ``cons`` hold (None if none)."""
        b = -_REPAIR_VOLUME_MARGIN - v + (g[0] * K[0] + g[1] * K[1] + g[2] * K[2])
        return _nearest(K, w, [(g, b), *cons])

    def _fr_set(self, K: list[float], t6: float) -> None:
        """Put the shape term K (a6 = -K / T^6) into the scratch row."""
        fr = self._fr_in
        fr[8] = -K[0] / t6
        fr[9] = -K[1] / t6
        fr[10] = -K[2] / t6

    def _fr_plan(self, K: list[float], t6: float, c_range: tuple[float, float] | None) -> bool:
        """Fill (``c_range``) and retime, or retime only (None), the scratch row with shape
        term K into ``self._out``, ``self._retimed``, ``self._scale``; whether it verified."""
        self._fr_set(K, t6)
        if c_range is None:
            self._retime_rows(self._fr_row, self._out, self._retimed, None)
            self._scale[0] = 1.0
        else:
            self._plan_rows(
                self._fr_row, self._out, self._retimed, c_range[0], c_range[1], None, self._scale
            )
        return bool(self._out_row[COL_TOTAL] <= 0.0)

    def _fr_evaluate_coarse(self, K: list[float], t6: float) -> float:
        """volume_min's value for the scratch row with shape term K on the coarse grid."""
        self._fr_set(K, t6)
        self._coarse_rows(self._fr_row, self._fr_out, None)
        return float(self._fr_out_row[_VOLUME_MIN])

    def _fr_evaluate(self, K: list[float], t6: float) -> list[float]:
        """The verifier's output row for the scratch row with shape term K (path-only values
        matter: T is the network's)."""
        self._fr_set(K, t6)
        self._eval_rows(self._fr_row, self._fr_out, None)
        result: list[float] = self._fr_out[0].tolist()
        return result

    def _theta_p_halfspaces(
        self, kind: DigType, src: list[float], D: list[float], K: list[float]
    ) -> list[tuple[list[float], float]] | None:
        """theta_p's limits (with the repair's margin) as half-spaces ``a . K <= b``; None when
        the dig does not start on the surface (theta_p then depends on where the path enters,
        not linearly on K) or enters straight down.

        Where the dig starts on the surface (within 1 mm, as :func:`oneshot.evaluate`), the tip
        enters along ``e = J(q0) (10 D + K)`` and theta_p = atan2(-e_y, |e_x|); with the sign of
        e_x kept, ``theta_p <= h`` is ``-e_y <= |e_x| tan h``, linear in K.
        """
        phi0 = src[0]
        phi1 = phi0 + src[1]
        phi2 = phi1 + src[2]
        s0, s1, s2 = math.sin(phi0), math.sin(phi1), math.sin(phi2)
        l0, l1, l2 = self._fr_len
        if not (s0 * l0 + s1 * l1) + s2 * l2 <= src[6] + 1e-3:
            return None
        v2 = -s2 * l2
        v1 = v2 - s1 * l1
        v0 = v1 - s0 * l0
        u2 = math.cos(phi2) * l2
        u1 = u2 + math.cos(phi1) * l1
        u0 = u1 + math.cos(phi0) * l0
        W0, W1, W2 = 10.0 * D[0] + K[0], 10.0 * D[1] + K[1], 10.0 * D[2] + K[2]
        ex = v0 * W0 + v1 * W1 + v2 * W2
        if ex == 0.0:
            return None
        sig = 1.0 if ex > 0.0 else -1.0
        lo, hi, m = self._fr_tp[kind]
        cons: list[tuple[list[float], float]] = []
        # theta_p <= hi - m: -(sy + sig tan sx) . W <= 0; theta_p >= lo + m: the opposite.
        # theta_p lies in [-90, 90] deg: a limit there is none.
        for limit, bound, side in ((hi, hi - m, -1.0), (lo, lo + m, 1.0)):
            if abs(limit) < 0.5 * math.pi:
                t = sig * math.tan(bound)
                a = [side * (u0 + t * v0), side * (u1 + t * v1), side * (u2 + t * v2)]
                cons.append((a, -10.0 * (a[0] * D[0] + a[1] * D[1] + a[2] * D[2])))
        return cons

    def _refine(
        self, problem: Problem, a6: tuple[float, float, float], T: float
    ) -> tuple[tuple[float, float, float], float] | None:
        """Bounded SLSQP from the network's answer on the verification grid."""
        from rt_runtime.planning.pso import slsqp_polish

        if not (math.isfinite(T) and all(map(math.isfinite, a6))):
            return None
        lo, hi = oneshot.search_bounds(self.rig)
        x0 = np.clip(oneshot.particle_from_a6(np.asarray(a6), np.asarray(T)), lo, hi)
        qs, qe, h, kind = (
            np.array([problem.q_start_rad]),
            np.array([problem.q_end_rad]),
            np.array([problem.surface_y_m]),
            np.array([int(problem.dig_type)]),
        )
        n = self.verifier.n_samples

        def model(rows: NDArray[np.intp], X: FloatArray) -> tuple[FloatArray, FloatArray]:
            return oneshot._polish_model(self.rig, qs[rows], qe[rows], h[rows], kind[rows], X, n)

        res = slsqp_polish(model, lo, hi, x0[None, None, :], max_iterations=REFINE_ITERATIONS)
        xb = res.x_best[0, 0]
        a6r, Tr = oneshot.a6_from_particle(xb)
        a6t = (float(a6r[0]), float(a6r[1]), float(a6r[2]))
        check = self._evaluation(problem, a6t, float(Tr))
        return (a6t, float(Tr)) if check[COL_TOTAL] <= 0.0 else None

    def _teacher(self, problem: Problem, t0: float) -> PinnPlan:
        sol = oneshot.solve_pso(self.rig, [problem])[0]
        if not sol.feasible:
            worst = min(sol.margins, key=lambda m: m[1])
            raise PlanningError(
                f"refused: out of the model's domain and the PSO teacher found no feasible plan "
                f"({worst[0]} margin {worst[1]:.4g}); nothing was planned"
            )
        check = self._evaluation(problem, sol.a6, sol.T_s)
        if check[COL_TOTAL] > 0.0:
            raise PlanningError(
                f"refused: the teacher's plan fails verification ({self._worst(check)}); "
                "nothing was planned"
            )
        return PinnPlan(
            problem=problem,
            a6=sol.a6,
            T_s=sol.T_s,
            raw_a6=sol.a6,
            raw_T_s=sol.T_s,
            status=PlanStatus.TEACHER,
            evaluation=check,
            infer_us=0.0,
            plan_us=(time.perf_counter() - t0) * 1e6,
        )

    def _evaluation(self, problem: Problem, a6: tuple[float, float, float], T: float) -> FloatArray:
        """The verifier's output row for one trajectory (allocates; repair paths only)."""
        p = problem
        row = pack_inputs(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, a6, T)
        out = np.zeros((1, N_OUT), dtype=np.float64)
        self.verifier.evaluate_into(row, out)
        result: FloatArray = out[0]
        return result

    @staticmethod
    def _worst(evaluation: FloatArray) -> str:
        i = int(np.argmax(evaluation[: len(CONSTRAINT_NAMES)]))
        return f"{CONSTRAINT_NAMES[i]} {evaluation[i]:.4g}"

    # -- batch ------------------------------------------------------------------------------

    def infer(self, dig_type: DigType, X: ArrayLike) -> FloatArray:
        """Raw network outputs ``(N, 4)`` for inputs ``(N, 7)`` (no checks; for reports and
        for planners that verify candidates themselves)."""
        return self._sessions[DigType(dig_type)].batch(np.asarray(X, dtype=np.float64))
