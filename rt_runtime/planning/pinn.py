"""Runtime one-shot planner: the PINN through onnxruntime, verified, repaired or refused.

Yao 4.3 replaces the 69 s PSO with a forward pass of a network mapping (entry pose, exit pose,
H) to the sextic's (a16, a26, a36, T). A network's answer is a guess, so here every answer is
checked before anyone may execute it:

1. **Domain.** The inputs must be finite and inside the model card's domain (the range of the
   training inputs); outside it a network extrapolates, so the planner refuses
   (:class:`~rt_runtime.errors.PlanningError` naming the input and the range) or, when the caller
   allows it, hands the problem to the PSO teacher.
2. **Inference.** One onnxruntime session per dig type, tuned for latency: one thread, sequential
   execution, every graph optimisation, inputs and outputs bound once to preallocated buffers
   (IOBinding) and no RunOptions argument (it costs ~25 us per call in ORT 1.31).
3. **Verification** of every hard limit of Yao eq 12 (joint range, velocity, acceleration,
   torque, power, initial digging angle, volume, time) on a dense grid (101 samples by default)
   by :class:`rt_runtime.planning.verify.Verifier`, the compiled twin of the numpy evaluation.
4. **Fill and retime** (the normal path, :meth:`rt_runtime.planning.verify.Verifier.plan_into`,
   in the C kernel): the network's path direction is kept and its bulge scaled, K = c K_net,
   to the largest volume within V_max and the path-only limits (joint range, theta_p), then
   the path is run at its smallest feasible T. Both steps move the answer to where the PSO's
   optima lie (on the volume cap and the time-dependent limits), which a regression network
   can only approach from inside; measured, they take the mean objective gap to the teacher
   from ~20 % (raw answers) to a few per cent. What they cannot make feasible falls back to the
   network's own path retimed, then to:
5. **Repair**, when that still fails (or with ``retime=False``, whenever the raw answer fails).
   Time scaling first, where only time-dependent limits fail (velocity, acceleration, torque,
   power, t_min): the kernel's exact retiming keeps the path (so angles, theta_p and volume)
   and takes the smallest T in [t_min, t_max] at which every limit holds. What time scaling
   cannot fix (a joint range, theta_p or volume violation, or no T in range) goes to a bounded
   local refinement (SLSQP from the network's answer, :data:`REFINE_ITERATIONS` iterations),
   when enabled. Otherwise :class:`~rt_runtime.errors.PlanningError` names the violated limit.

Nothing unverified leaves :meth:`PinnPlanner.plan`: every returned plan has passed step 3 on
the dense grid. The model card must name the rig the planner serves (name and
:attr:`rt_runtime.rig.Rig.planning_fingerprint`) and the model file's SHA-256; anything else is
refused at load time with a :class:`~rt_runtime.errors.ConfigurationError`.

``plan`` is the cheap path (tens of microseconds when no repair is needed, no allocation of
large arrays, no I/O); loading is the expensive one and happens once.
"""

from __future__ import annotations

import hashlib
import json
import math
import operator
import time
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DigType, Problem
from rt_runtime.planning.verify import (
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
#: The network's inputs and outputs (DESIGN.md "Models"): rad, rad, ..., m; rad/s^6 x 3, s.
INPUT_NAMES = ("theta11", "theta12", "theta13", "theta21", "theta22", "theta23", "H")
OUTPUT_NAMES = ("a16", "a26", "a36", "T")
#: The shipped models: the repository's top-level ``onnx/`` directory.
DEFAULT_MODEL_DIR = Path(__file__).resolve().parents[2] / "onnx"
#: SLSQP iterations of the bounded local refinement.
REFINE_ITERATIONS = 15
# Constraint columns time scaling can fix (it leaves the path, so angles, theta_p, volume alone).
_TIME_FIXABLE = frozenset(
    i
    for i, n in enumerate(CONSTRAINT_NAMES)
    if n.startswith(("velocity", "acceleration", "torque", "power")) or n == "time_min"
)


def fill_c_range(c_max: float) -> tuple[float, float]:
    """The fill step's range of bulge scales with its top capped at ``c_max`` (> 0)."""
    if not c_max > 0.0:
        raise ValueError(f"c_max must be > 0; got {c_max!r}")
    return (min(PLAN_C_RANGE[0], c_max), c_max)


class PlanStatus(IntEnum):
    """How a returned plan came about."""

    RETIMED = 0  # the network's path, bulge scaled to fill the bucket, at its smallest feasible T
    RAW = 1  # the network's answer as it was (retiming off), verified
    TIME_SCALED = 2  # repaired by time scaling (retiming off)
    REFINED = 3  # repaired by the bounded local refinement
    TEACHER = 4  # out of the model's domain; planned by the PSO teacher (when allowed)


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


def load_card(card_path: Path) -> ModelCard:
    """Read and check a model card (not yet against a rig).

    Raises:
        ConfigurationError: Missing file, not JSON, wrong format, or a missing/ill-typed key.
    """
    if not card_path.is_file():
        raise ConfigurationError(
            f"model card {card_path} does not exist (a model needs its card beside it)"
        )
    try:
        raw = json.loads(card_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigurationError(f"model card {card_path} is not valid JSON: {exc}") from exc
    if not isinstance(raw, dict) or raw.get("format") != CARD_FORMAT:
        raise ConfigurationError(f"{card_path}: format must be {CARD_FORMAT!r}")
    try:
        domain = raw["domain"]
        lo = tuple(float(v) for v in domain["min"])
        hi = tuple(float(v) for v in domain["max"])
        card = ModelCard(
            path=card_path,
            model_path=card_path.parent / str(raw["model_file"]),
            dig_type=DigType[str(raw["dig_type"]).upper()],
            rig=str(raw["rig"]),
            rig_planning_fingerprint=str(raw["rig_planning_fingerprint"]),
            model_sha256=str(raw["model_sha256"]),
            domain_min=lo,
            domain_max=hi,
            raw=raw,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigurationError(f"{card_path}: missing or invalid key: {exc}") from exc
    if len(lo) != 7 or len(hi) != 7 or not all(a < b for a, b in zip(lo, hi, strict=True)):
        raise ConfigurationError(f"{card_path}: domain.min/max must be 7 increasing pairs")
    return card


def sha256_file(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes (model files against their cards)."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True, slots=True)
class PinnPlan:
    """A verified one-shot plan.

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
        bulge_scale: c of the executed path K = c K_net (1.0: the network's own path).
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
        if sess_c is not None and bind_c is not None:
            run_c = sess_c.run_with_iobinding

            def run() -> None:
                run_c(bind_c, None)
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
        refine: Allow the bounded local refinement when time scaling cannot repair a plan.
        teacher_fallback: Plan out-of-domain problems with the PSO teacher instead of refusing
            them (seconds, not microseconds: never inside the loop).
        verifier_backend: ``auto``, ``c`` or ``numpy`` (see
            :class:`rt_runtime.planning.verify.Verifier`).

    Raises:
        ConfigurationError: A missing or corrupt model or card, a card for another rig or
            another set of rig values, a model file whose hash differs from its card.
    """

    def __init__(
        self,
        rig: Rig,
        model_dir: Path | str = DEFAULT_MODEL_DIR,
        *,
        n_verify: int = oneshot.DEFAULT_SAMPLES,
        retime: bool = True,
        refine: bool = True,
        teacher_fallback: bool = False,
        verifier_backend: str = "auto",
    ) -> None:
        oneshot.require_planning(rig)
        self.rig = rig
        self.retime = retime
        self.refine = refine
        self.teacher_fallback = teacher_fallback
        self.verifier = Verifier(rig, n_verify, backend=verifier_backend)
        self.cards: dict[DigType, ModelCard] = {}
        self._sessions: dict[DigType, _Session] = {}
        directory = Path(model_dir)
        for kind in DigType:
            stem = f"pinn_{kind.name.lower()}"
            card = load_card(directory / f"{stem}.json")
            self._check_card(card, kind)
            self.cards[kind] = card
            self._sessions[kind] = _Session(card)
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
        # plan_into without its Python wrapper (the range is checked here, once per range).
        self._plan_rows = self.verifier._plan
        self._c_default = (float(PLAN_C_RANGE[0]), float(PLAN_C_RANGE[1]))

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
        if not card.model_path.is_file():
            raise ConfigurationError(f"{where}: model file {card.model_path} does not exist")
        digest = sha256_file(card.model_path)
        if digest != card.model_sha256:
            raise ConfigurationError(
                f"model {card.model_path} is corrupt or was replaced: SHA-256 {digest[:12]}... "
                f"differs from its card's {card.model_sha256[:12]}..."
            )

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

    def plan(
        self,
        q_start_rad: ArrayLike,
        q_end_rad: ArrayLike,
        surface_y_m: float,
        dig_type: DigType,
        *,
        c_max: float | None = None,
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

        Returns:
            A plan whose trajectory satisfies every limit of Yao eq 12 on the verification grid.

        Raises:
            PlanningError: Input outside the model's domain (or not finite) when the teacher
                fallback is off; a plan that neither time scaling nor refinement could repair,
                naming the violated limit.
        """
        t0 = time.perf_counter()
        try:
            kind = self._kinds.get(dig_type)
        except TypeError:  # unhashable: DigType says what is wrong with it
            kind = None
        if kind is None or isinstance(dig_type, bool):
            kind = DigType(dig_type)
        row = self._row
        self._qs_view[:] = q_start_rad
        self._qe_view[:] = q_end_rad
        row[0, 6] = surface_y_m
        x = self._x_view.tolist()
        # Inside the domain (NaN compares False, so it takes the slow path that names it).
        if not (
            all(map(operator.le, self._lo[kind], x)) and all(map(operator.le, x, self._hi[kind]))
        ):
            why = self._domain_error(kind, x)
            if why is not None:
                problem = Problem((x[0], x[1], x[2]), (x[3], x[4], x[5]), x[6], kind)
                if self.teacher_fallback and all(map(math.isfinite, x)):
                    return self._teacher(problem, t0)
                raise PlanningError(f"refused: {why}; nothing was planned")

        sess = self._sessions[kind]
        sess.x[0] = self._x_view
        t1 = time.perf_counter()
        sess.run()
        infer_us = (time.perf_counter() - t1) * 1e6
        row[0, 7] = kind
        self._y_view[:] = sess.y[0]
        y = self._y_view.tolist()
        raw_a6 = (y[0], y[1], y[2])
        raw_T = y[3]
        out = self._out

        if self.retime:
            c_lo, c_hi = self._c_default if c_max is None else fill_c_range(c_max)
            self._plan_rows(row, out, self._retimed, c_lo, c_hi, None, self._scale)
            if self._out_row[COL_TOTAL] <= 0.0:
                r = self._retimed_row.tolist()
                evaluation = self._out_row.copy()
                scale = float(self._scale[0])
                problem = Problem((x[0], x[1], x[2]), (x[3], x[4], x[5]), x[6], kind)
                return PinnPlan(
                    problem,
                    (r[0], r[1], r[2]),
                    r[3],
                    raw_a6,
                    raw_T,
                    PlanStatus.RETIMED,
                    evaluation,
                    infer_us,
                    (time.perf_counter() - t0) * 1e6,
                    scale,
                )
            self.verifier.evaluate_into(row, out)  # back to the network's own answer
        else:
            self.verifier.evaluate_into(row, out)
            if self._out_row[COL_TOTAL] <= 0.0:
                evaluation = self._out_row.copy()
                problem = Problem((x[0], x[1], x[2]), (x[3], x[4], x[5]), x[6], kind)
                return PinnPlan(
                    problem,
                    raw_a6,
                    raw_T,
                    raw_a6,
                    raw_T,
                    PlanStatus.RAW,
                    evaluation,
                    infer_us,
                    (time.perf_counter() - t0) * 1e6,
                )
        problem = Problem((x[0], x[1], x[2]), (x[3], x[4], x[5]), x[6], kind)
        a6_ok, T_ok, status = self._repair(problem, raw_a6, raw_T)
        final = self._evaluation(problem, a6_ok, T_ok)
        if final[COL_TOTAL] > 0.0:  # the repair paths verify; this guards the guarantee
            raise PlanningError(
                f"refused: repaired plan fails verification ({self._worst(final)}); "
                "nothing was planned"
            )
        return PinnPlan(
            problem,
            a6_ok,
            T_ok,
            raw_a6,
            raw_T,
            status,
            final,
            infer_us,
            (time.perf_counter() - t0) * 1e6,
        )

    # -- repair -----------------------------------------------------------------------------

    def _repair(
        self, problem: Problem, a6: tuple[float, float, float], T: float
    ) -> tuple[tuple[float, float, float], float, PlanStatus]:
        """Time scaling, then refinement, of the network's answer, whose evaluation is in
        ``self._out``; PlanningError naming its worst limit when neither verifies."""
        out = self._out[0]
        planning = oneshot.require_planning(self.rig)
        bad = {i for i in range(len(CONSTRAINT_NAMES)) if out[i] > 0.0}
        if bad <= _TIME_FIXABLE:
            # The kernel's exact retiming: the path kept, the smallest T in [t_min, t_max] at
            # which every time-dependent limit holds.
            res = np.empty((1, N_OUT))
            retimed = np.empty((1, 4))
            self.verifier.retime_into(self._row, res, retimed)
            if res[0, COL_TOTAL] <= 0.0:
                r = retimed[0].tolist()
                return (r[0], r[1], r[2]), r[3], PlanStatus.TIME_SCALED
        if self.refine:
            refined = self._refine(problem, a6, T)
            if refined is not None:
                return refined[0], refined[1], PlanStatus.REFINED
        worst = int(np.argmax(out[: len(CONSTRAINT_NAMES)]))
        raise PlanningError(
            f"refused: the {problem.dig_type.name.lower()} plan violates {CONSTRAINT_NAMES[worst]} "
            f"by {out[worst]:.4g} (normalised; <= 0 allowed) and could not be repaired "
            f"(time scaling within T <= {planning.t_max_s:g} s"
            f"{', local refinement' if self.refine else ''}); nothing was planned"
        )

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
