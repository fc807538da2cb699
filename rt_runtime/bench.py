"""Benchmarks behind ``excavator-rt bench ...``: distributions, not single numbers.

Each benchmark returns one frozen report whose ``to_json()`` is its JSON object, keys as the
README lists them (attribute names are the keys; nested groups are
:mod:`rt_runtime.reports`'s). Timing goals are checked here and reported, never asserted in
tests: the machines are shared and noisy. Percentile groups carry ``p50`` and ``p99``. The
papers' figures are given under ``paper``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import shapely

from rt_runtime.reports import BusLoadFigures, Distribution, Range, Spread
from rt_runtime.rig import Rig

if TYPE_CHECKING:
    from rt_runtime.control import RtReport
    from rt_runtime.planning.trench import TrenchPlan

YAO_PSO_SOLVE_S = (69.0, 71.0)  # Yao Table 4: PSO planning time per dig
YAO_RANGES = {"T_s": (5.0, 10.0), "volume_L": (3.74, 5.72), "energy_Wh": (0.025, 0.110)}
YAO_MEAN_OBJECTIVE = {"downward": 0.403, "backward": 0.303}  # Yao 5.2, PSO sample averages
#: Goals of ``bench oneshot``.
ONESHOT_GOALS = {
    "solve_s_p50_max": 0.3,
    "within_1pct_of_de_min": 0.95,
    "batch_problems_per_s_min": 20.0,
}


@dataclass(frozen=True, slots=True)
class DigRanges:
    """The feasible PSO digs of one type (``results`` of ``bench oneshot``).

    Attributes:
        n: Feasible digs.
        T_s: Shortest and longest duration (s).
        volume_L: Smallest and largest volume (L).
        energy_Wh: Least and most energy (Wh).
        objective_mean: Mean objective.
    """

    n: int
    T_s: tuple[float, float]
    volume_L: tuple[float, float]
    energy_Wh: tuple[float, float]
    objective_mean: float

    def to_json(self) -> dict[str, Any]:
        """The attributes, ranges as ``[min, max]``."""
        return {
            "n": self.n,
            "T_s": list(self.T_s),
            "volume_L": list(self.volume_L),
            "energy_Wh": list(self.energy_Wh),
            "objective_mean": self.objective_mean,
        }


@dataclass(frozen=True, slots=True)
class ProblemGap:
    """One problem solved by the PSO and the DE reference (``per_problem``).

    Attributes:
        pso: The PSO's objective.
        de: The reference's objective.
        gap: ``(pso - de) / |de|``; -1 where only the PSO found a feasible dig, inf where it
            found none.
    """

    pso: float
    de: float
    gap: float

    def to_json(self) -> dict[str, float]:
        """``{"pso", "de", "gap"}``."""
        return {"pso": self.pso, "de": self.de, "gap": self.gap}


@dataclass(frozen=True, slots=True)
class DeComparison:
    """The PSO against differential evolution on the same problems.

    Attributes:
        de_solve_s: The reference's solve time per problem (s; p50, p99).
        within_1pct_of_de: Fraction of the problems the PSO solved within 1 % of the reference.
        gap_to_de: Objective gap to the reference over the problems both solved (fractions;
            p50 NaN when there is none).
        per_problem: Each problem.
    """

    de_solve_s: Distribution
    within_1pct_of_de: float
    gap_to_de: Spread
    per_problem: tuple[ProblemGap, ...]


@dataclass(frozen=True, slots=True)
class OneshotBenchReport:
    """The report of ``excavator-rt bench oneshot`` (README ``bench oneshot --json``).

    Attributes:
        rig: Rig profile name.
        problems: Problems solved.
        solve_s: Solve time of one problem alone (s; p50, p99).
        batch_problems_per_s: Problems per second solved in one batch.
        batch_workers: Processes of the batch.
        feasible: Fraction solved feasibly, one at a time.
        batch_feasible: The same in the batch.
        results: Per dig type, the feasible digs' ranges.
        de: The comparison with the DE reference (JSON: its keys at the top level, with
            ``speedup_vs_de``), None when not run.
    """

    rig: str
    problems: int
    solve_s: Distribution
    batch_problems_per_s: float
    batch_workers: int
    feasible: float
    batch_feasible: float
    results: Mapping[str, DigRanges]
    de: DeComparison | None = None

    @property
    def speedup_vs_yao_pso(self) -> float:
        """Yao's PSO time (the lower figure) over our median solve time."""
        return YAO_PSO_SOLVE_S[0] / self.solve_s.p50

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object."""
        out: dict[str, Any] = {
            "rig": self.rig,
            "problems": self.problems,
            "solve_s": self.solve_s.to_json(),
            "batch_problems_per_s": self.batch_problems_per_s,
            "batch_workers": self.batch_workers,
            "feasible": self.feasible,
            "batch_feasible": self.batch_feasible,
            "results": {kind: r.to_json() for kind, r in self.results.items()},
        }
        if self.de is not None:
            out["de_solve_s"] = self.de.de_solve_s.to_json()
            out["within_1pct_of_de"] = self.de.within_1pct_of_de
            out["gap_to_de"] = self.de.gap_to_de.to_json()
            out["speedup_vs_de"] = self.de.de_solve_s.p50 / self.solve_s.p50
            out["per_problem"] = [row.to_json() for row in self.de.per_problem]
        out["goals"] = dict(ONESHOT_GOALS)
        out["paper"] = {
            "yao_pso_solve_s": list(YAO_PSO_SOLVE_S),
            "yao_ranges": {k: list(v) for k, v in YAO_RANGES.items()},
            "yao_mean_objective": dict(YAO_MEAN_OBJECTIVE),
            "speedup_vs_yao_pso": self.speedup_vs_yao_pso,
        }
        return out


def bench_oneshot(
    rig: Rig, n_problems: int = 50, seed: int = 0, de: bool = True, workers: int = 2
) -> OneshotBenchReport:
    """PSO teacher: solve time single and batched, quality against differential evolution.

    Half the problems are downward digs, half backward, drawn by
    :func:`rt_runtime.planning.oneshot.sample_problems` with ``seed``. Each problem is solved
    alone (timed, one process), then all together in one batch over ``workers`` processes
    (timed), then, with ``de``, by the DE reference (timed).
    """
    from rt_runtime.planning import oneshot

    n_down = n_problems // 2
    problems = oneshot.sample_problems(rig, n_down, oneshot.DigType.DOWNWARD, seed=seed)
    problems += oneshot.sample_problems(
        rig, n_problems - n_down, oneshot.DigType.BACKWARD, seed=seed + 1
    )

    single_s = []
    singles = []
    for p in problems:
        t0 = time.perf_counter()
        singles.append(oneshot.solve_pso(rig, [p], seed=seed)[0])
        single_s.append(time.perf_counter() - t0)

    t0 = time.perf_counter()
    batch = oneshot.solve_pso(rig, problems, seed=seed, workers=workers)
    batch_s = time.perf_counter() - t0

    by_type: dict[str, DigRanges] = {}
    for kind in oneshot.DigType:
        sols = [s for s in singles if s.problem.dig_type == kind and s.feasible]
        if not sols:
            continue
        by_type[kind.name.lower()] = DigRanges(
            n=len(sols),
            T_s=(min(s.T_s for s in sols), max(s.T_s for s in sols)),
            volume_L=(
                min(s.volume_m3 for s in sols) * 1e3,
                max(s.volume_m3 for s in sols) * 1e3,
            ),
            energy_Wh=(
                min(s.energy_j for s in sols) / 3600,
                max(s.energy_j for s in sols) / 3600,
            ),
            objective_mean=float(np.mean([s.objective for s in sols])),
        )

    comparison: DeComparison | None = None
    if de:
        de_s = []
        gaps = []
        rows = []
        for p, s in zip(problems, singles, strict=True):
            t0 = time.perf_counter()
            d = oneshot.solve_de(rig, p, seed=seed)
            de_s.append(time.perf_counter() - t0)
            if s.feasible and d.feasible:
                gap = (s.objective - d.objective) / abs(d.objective)
            elif s.feasible:
                gap = -1.0  # PSO found a feasible dig the reference did not
            else:
                gap = float("inf")
            gaps.append(gap)
            rows.append(ProblemGap(s.objective, d.objective, gap))
        finite = np.array([g for g in gaps if np.isfinite(g)])
        comparison = DeComparison(
            de_solve_s=Distribution.of(de_s),
            within_1pct_of_de=float(np.mean(np.array(gaps) <= 0.01)),
            gap_to_de=Spread(
                p50=float(np.percentile(finite, 50)) if finite.size else float("nan"),
                max=float(np.max(gaps)),
            ),
            per_problem=tuple(rows),
        )
    return OneshotBenchReport(
        rig=rig.name,
        problems=len(problems),
        solve_s=Distribution.of(single_s),
        batch_problems_per_s=len(problems) / batch_s,
        batch_workers=workers,
        feasible=float(np.mean([s.feasible for s in singles])),
        batch_feasible=float(np.mean([s.feasible for s in batch])),
        results=by_type,
        de=comparison,
    )


YAO_PINN_PLAN_MS = (4.2, 4.5)  # Yao Table 4: PINN planning time per dig
#: Yao Table 4: mean of the four task averages (Ave-A..Ave-D; t s, V_p 10^3 cm^3 = L, W_E Wh).
YAO_TABLE4_MEAN = {
    "pso": {"T_s": 6.875, "volume_L": 4.9125, "energy_Wh": 0.05925},
    "pinn": {"T_s": 6.995, "volume_L": 4.9125, "energy_Wh": 0.062},
}


#: Goals of ``bench pinn``.
PINN_GOALS = {
    "gap_mean_max": 0.03,
    "raw_feasible_min": 0.95,
    "executed_feasible": 1.0,
    "plan_us_p50_max": 20.0,
    "plan_us_p99_max": 100.0,
}
#: The paths a PINN plan can take (:class:`rt_runtime.planning.pinn.PlanStatus`, ``refused``
#: for none), in the report's order.
PINN_PATHS = (
    "retimed",
    "raw",
    "time_scaled",
    "repaired_fast",
    "refined",
    "teacher",
    "library",
    "refused",
)


@dataclass(frozen=True, slots=True)
class PinnTypeFigures:
    """The PINN planner on the held-out problems of one dig type (``types`` of ``bench pinn``).

    Attributes:
        samples: Problems.
        gap_mean: Mean objective gap of the returned plans to the teacher (fraction; NaN when
            none was returned).
        gap_max: Largest such gap.
        raw_gap_mean: Mean gap of the network's raw answers.
        raw_feasible: Fraction of raw answers feasible.
        plan_raw: Fraction of problems planned on the ``raw`` path.
        time_scaled: Fraction on the ``time_scaled`` path.
        repaired_fast: Fraction on the ``repaired_fast`` path.
        refined: Fraction on the ``refined`` path.
        refused: Fraction refused.
        paths: Problems per path (:data:`PINN_PATHS`), counts.
        refusals: The first five refusals' reasons.
        plan_us: Plan time (us; p50, p99, p999, max), None when every problem was refused.
        infer_us: Inference alone (us; p50, p99, p999, max).
    """

    samples: int
    gap_mean: float
    gap_max: float
    raw_gap_mean: float
    raw_feasible: float
    plan_raw: float
    time_scaled: float
    repaired_fast: float
    refined: float
    refused: float
    paths: Mapping[str, int]
    refusals: tuple[str, ...]
    plan_us: Distribution | None
    infer_us: Distribution

    def to_json(self) -> dict[str, Any]:
        """The attributes as JSON."""
        return {
            "samples": self.samples,
            "gap_mean": self.gap_mean,
            "gap_max": self.gap_max,
            "raw_gap_mean": self.raw_gap_mean,
            "raw_feasible": self.raw_feasible,
            "plan_raw": self.plan_raw,
            "time_scaled": self.time_scaled,
            "repaired_fast": self.repaired_fast,
            "refined": self.refined,
            "refused": self.refused,
            "paths": dict(self.paths),
            "refusals": list(self.refusals),
            "plan_us": self.plan_us.to_json() if self.plan_us is not None else None,
            "infer_us": self.infer_us.to_json(),
        }


@dataclass(frozen=True, slots=True)
class PlannerMeans:
    """Mean dig of one planner on held-out problems (a cell of Yao Table 4's form).

    Attributes:
        T_s: Mean duration (s).
        volume_L: Mean volume (L).
        energy_Wh: Mean energy (Wh).
        plan_s: Median planning time (s) where given in seconds (the PSO), else None.
        plan_ms: Median planning time (ms) where given in milliseconds (the PINN), else None.
    """

    T_s: float
    volume_L: float
    energy_Wh: float
    plan_s: float | None = None
    plan_ms: float | None = None

    def to_json(self) -> dict[str, float]:
        """``{"T_s", "volume_L", "energy_Wh"}`` and the planning time under its unit's key."""
        out = {"T_s": self.T_s, "volume_L": self.volume_L, "energy_Wh": self.energy_Wh}
        if self.plan_s is not None:
            out["plan_s"] = self.plan_s
        if self.plan_ms is not None:
            out["plan_ms"] = self.plan_ms
        return out


@dataclass(frozen=True, slots=True)
class Table4Row:
    """PSO teacher and PINN planner side by side on one dig type (``table4``).

    Attributes:
        pso: The teacher's means (its planning time in ``plan_s``).
        pinn: The PINN's means (its planning time in ``plan_ms``).
    """

    pso: PlannerMeans
    pinn: PlannerMeans

    def to_json(self) -> dict[str, Any]:
        """``{"pso", "pinn"}``."""
        return {"pso": self.pso.to_json(), "pinn": self.pinn.to_json()}


@dataclass(frozen=True, slots=True)
class PinnBenchReport:
    """The report of ``excavator-rt bench pinn`` (README ``bench pinn --json``).

    Attributes:
        rig: Rig profile name.
        verifier: ``c`` or ``numpy``.
        verifier_build: Build of the C kernel that ran (``avx2`` or ``baseline``).
        types: Per dig type.
        samples: Problems over both types.
        gap_mean: Mean objective gap of the returned plans to the teacher (fraction).
        gap_max: Largest such gap.
        raw_gap_mean: Mean gap of the raw answers.
        raw_gap_max: Largest gap of the raw answers.
        raw_feasible: Fraction of raw answers feasible.
        verified_feasible: Fraction of problems with a verified plan returned.
        refused: Fraction refused.
        executed_feasible: Fraction of the returned plans feasible by the numpy reference.
        infer_us: Inference alone (us; p50, p99, p999, max).
        plan_us: Plan time (us; p50, p99, p999, max).
        verify_only_plan_us: Plan time with fill and retime off, raw answers that verify
            (inference plus verification; us), None when none did.
        pso_solve_s: The teacher's solve time on some of the problems, same run (s; p50, p99).
        paths: Problems per path (:data:`PINN_PATHS`), counts.
        table4: Per dig type, Yao Table 4's form.
    """

    rig: str
    verifier: str
    verifier_build: str | None
    types: Mapping[str, PinnTypeFigures]
    samples: int
    gap_mean: float
    gap_max: float
    raw_gap_mean: float
    raw_gap_max: float
    raw_feasible: float
    verified_feasible: float
    refused: float
    executed_feasible: float
    infer_us: Distribution
    plan_us: Distribution
    verify_only_plan_us: Distribution | None
    pso_solve_s: Distribution
    paths: Mapping[str, int]
    table4: Mapping[str, Table4Row]

    @property
    def speedup_vs_pso(self) -> float:
        """The teacher's median solve time over the PINN's median plan time."""
        return self.pso_solve_s.p50 / (self.plan_us.p50 * 1e-6)

    @property
    def speedup_vs_yao_pinn(self) -> float:
        """Yao's PINN plan time (the lower figure) over our median plan time."""
        return YAO_PINN_PLAN_MS[0] * 1e3 / self.plan_us.p50

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object."""
        return {
            "rig": self.rig,
            "verifier": self.verifier,
            "verifier_build": self.verifier_build,
            "types": {kind: t.to_json() for kind, t in self.types.items()},
            "samples": self.samples,
            "gap_mean": self.gap_mean,
            "gap_max": self.gap_max,
            "raw_gap_mean": self.raw_gap_mean,
            "raw_gap_max": self.raw_gap_max,
            "raw_feasible": self.raw_feasible,
            "verified_feasible": self.verified_feasible,
            "refused": self.refused,
            "executed_feasible": self.executed_feasible,
            "infer_us": self.infer_us.to_json(),
            "plan_us": self.plan_us.to_json(),
            "verify_only_plan_us": (
                self.verify_only_plan_us.to_json() if self.verify_only_plan_us is not None else None
            ),
            "pso_solve_s": self.pso_solve_s.to_json(),
            "paths": dict(self.paths),
            "table4": {kind: row.to_json() for kind, row in self.table4.items()},
            "speedup_vs_pso": self.speedup_vs_pso,
            "goals": dict(PINN_GOALS),
            "paper": {
                "yao_pinn_plan_ms": list(YAO_PINN_PLAN_MS),
                "yao_pso_solve_s": list(YAO_PSO_SOLVE_S),
                "yao_gap_approx": 0.05,
                "yao_table4_mean": YAO_TABLE4_MEAN,
                "speedup_vs_yao_pinn": self.speedup_vs_yao_pinn,
            },
        }


def load_heldout(path: Any) -> dict[str, np.ndarray]:
    """A held-out set written by :func:`rt_runtime.training.export.export`."""
    from pathlib import Path

    from rt_runtime.errors import ConfigurationError

    p = Path(path)
    if not p.is_file():
        raise ConfigurationError(
            f"held-out set {p} does not exist (written by `excavator-rt export`)"
        )
    with np.load(p) as z:
        return {k: z[k] for k in z.files}


def bench_pinn(
    rig: Rig,
    model_dir: Any = None,
    *,
    limit: int | None = None,
    passes: int = 5,
    pso_problems: int = 10,
    seed: int = 0,
) -> PinnBenchReport:
    """PINN planner on the held-out sets: quality against the PSO teacher, latency.

    For each dig type, every held-out problem is planned by
    :meth:`rt_runtime.planning.pinn.PinnPlanner.plan` (domain check, inference, verification,
    repair or refusal). Quality is judged twice: the network's raw answers by the numpy
    reference evaluation (``raw_feasible``, objective gap to the teacher), and every returned
    plan again by the numpy reference (``executed_feasible``, which must be 1.0). Latency is
    measured over ``passes`` passes over the problems; inference alone over as many bare
    onnxruntime calls. The PSO teacher solves ``pso_problems`` of them per type in the same run.
    Refused problems are counted in ``refused``, not in the objective gaps.
    """
    from pathlib import Path

    from rt_runtime.errors import PlanningError
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner, PlanStatus

    directory = Path(model_dir) if model_dir is not None else DEFAULT_MODEL_DIR
    planner = PinnPlanner(rig, directory)
    verify_only = PinnPlanner(rig, directory, retime=False, refine=False)
    verify_us: list[float] = []
    types: dict[str, PinnTypeFigures] = {}
    all_infer: list[float] = []
    all_plan: list[float] = []
    all_gap: list[float] = []
    all_raw_gap: list[float] = []
    counts = {"n": 0, "raw": 0, "verified": 0, "refused": 0, "executed_ok": 0, "returned": 0}
    path_names = {
        PlanStatus.RETIMED: "retimed",
        PlanStatus.RAW: "raw",
        PlanStatus.TIME_SCALED: "time_scaled",
        PlanStatus.REPAIRED: "repaired_fast",
        PlanStatus.REFINED: "refined",
        PlanStatus.TEACHER: "teacher",
        PlanStatus.LIBRARY: "library",
    }
    all_paths = dict.fromkeys(PINN_PATHS, 0)
    pso_s: list[float] = []
    table4: dict[str, Table4Row] = {}
    for kind in oneshot.DigType:
        name = kind.name.lower()
        held = load_heldout(directory / f"pinn_{name}_heldout.npz")
        X = held["X"][:limit]
        n = X.shape[0]
        # Raw answers, judged by the numpy reference.
        Y = planner.infer(kind, X)
        ev = oneshot.evaluate(
            rig, X[:, 0:3], X[:, 3:6], X[:, 6], int(kind), Y[:, None, :3], Y[:, None, 3]
        )
        teacher = held["objective"][:n]
        raw_gap = (ev.objective[:, 0] - teacher) / np.abs(teacher)
        all_raw_gap.extend(raw_gap.tolist())
        plans: list[Any] = []
        refused: list[str] = []
        plan_us: list[float] = []
        for p in range(passes):
            for i in range(n):
                try:
                    plan = planner.plan(X[i, 0:3], X[i, 3:6], float(X[i, 6]), kind)
                except PlanningError as exc:
                    if p == 0:
                        refused.append(str(exc))
                        plans.append(None)
                    continue
                plan_us.append(plan.plan_us)
                if p == 0:
                    plans.append(plan)
        # The same problems planned without fill and retime: verification of the raw answer
        # only (DESIGN.md's "inference + verification"), refusals not timed.
        for i in range(n):
            try:
                vplan = verify_only.plan(X[i, 0:3], X[i, 3:6], float(X[i, 6]), kind)
            except PlanningError:
                continue
            if vplan.status == PlanStatus.RAW:
                verify_us.append(vplan.plan_us)
        # Inference alone: the bare bound session call.
        sess = planner._sessions[kind]
        infer_us = []
        for i in range(n * passes):
            sess.x[0] = X[i % n]
            t0 = time.perf_counter()
            sess.run()
            infer_us.append((time.perf_counter() - t0) * 1e6)
        returned = [pl for pl in plans if pl is not None]
        ok = 0
        if returned:
            a6 = np.array([pl.a6 for pl in returned])
            T = np.array([pl.T_s for pl in returned])
            idx = np.array([i for i, pl in enumerate(plans) if pl is not None])
            ev_exec = oneshot.evaluate(
                rig, X[idx, 0:3], X[idx, 3:6], X[idx, 6], int(kind), a6[:, None, :], T[:, None]
            )
            ok = int(np.sum(ev_exec.feasible[:, 0]))
            gap = (ev_exec.objective[:, 0] - teacher[idx]) / np.abs(teacher[idx])
            all_gap.extend(gap.tolist())
        else:
            gap = np.array([np.nan])
        paths = dict.fromkeys(PINN_PATHS, 0)
        for pl in returned:
            paths[path_names[pl.status]] += 1
        paths["refused"] = len(refused)
        for key, value in paths.items():
            all_paths[key] += value
        # The teacher on a few of the same problems, in the same run.
        sub = [
            oneshot.Problem(
                q_start_rad=(float(X[i, 0]), float(X[i, 1]), float(X[i, 2])),
                q_end_rad=(float(X[i, 3]), float(X[i, 4]), float(X[i, 5])),
                surface_y_m=float(X[i, 6]),
                dig_type=kind,
            )
            for i in range(min(pso_problems, n))
        ]
        for prob in sub:
            t0 = time.perf_counter()
            oneshot.solve_pso(rig, [prob], seed=seed)
            pso_s.append(time.perf_counter() - t0)
        table4[name] = Table4Row(
            pso=PlannerMeans(
                T_s=float(np.mean(held["T_s"][:n])),
                volume_L=float(np.mean(held["volume_m3"][:n]) * 1e3),
                energy_Wh=float(np.mean(held["energy_j"][:n]) / 3600.0),
                plan_s=float(np.median(pso_s[-len(sub) :])) if sub else float("nan"),
            ),
            pinn=PlannerMeans(
                T_s=float(np.mean([pl.T_s for pl in returned])) if returned else float("nan"),
                volume_L=float(np.mean([pl.verification.volume_m3 for pl in returned]) * 1e3)
                if returned
                else float("nan"),
                energy_Wh=float(np.mean([pl.verification.energy_j for pl in returned]) / 3600.0)
                if returned
                else float("nan"),
                plan_ms=float(np.median(plan_us) / 1e3) if plan_us else float("nan"),
            ),
        )
        types[name] = PinnTypeFigures(
            samples=n,
            gap_mean=float(np.mean(gap)),
            gap_max=float(np.max(gap)),
            raw_gap_mean=float(np.mean(raw_gap)),
            raw_feasible=float(np.mean(ev.feasible[:, 0])),
            plan_raw=paths["raw"] / n,
            time_scaled=paths["time_scaled"] / n,
            repaired_fast=paths["repaired_fast"] / n,
            refined=paths["refined"] / n,
            refused=len(refused) / n,
            paths=paths,
            refusals=tuple(refused[:5]),
            plan_us=Distribution.of(plan_us, tails=True) if plan_us else None,
            infer_us=Distribution.of(infer_us, tails=True),
        )
        counts["n"] += n
        counts["raw"] += int(np.sum(ev.feasible[:, 0]))
        counts["verified"] += len(returned)
        counts["refused"] += len(refused)
        counts["returned"] += len(returned)
        counts["executed_ok"] += ok
        all_infer.extend(infer_us)
        all_plan.extend(plan_us)
    return PinnBenchReport(
        rig=rig.name,
        verifier=planner.verifier.backend,
        verifier_build=planner.verifier.build,
        types=types,
        samples=counts["n"],
        gap_mean=float(np.mean(all_gap)) if all_gap else float("nan"),
        gap_max=float(np.max(all_gap)) if all_gap else float("nan"),
        raw_gap_mean=float(np.mean(all_raw_gap)),
        raw_gap_max=float(np.max(all_raw_gap)),
        raw_feasible=counts["raw"] / counts["n"],
        verified_feasible=counts["verified"] / counts["n"],
        refused=counts["refused"] / counts["n"],
        executed_feasible=counts["executed_ok"] / counts["returned"]
        if counts["returned"]
        else float("nan"),
        infer_us=Distribution.of(all_infer, tails=True),
        plan_us=Distribution.of(all_plan, tails=True),
        verify_only_plan_us=Distribution.of(verify_us, tails=True) if verify_us else None,
        pso_solve_s=Distribution.of(pso_s),
        paths=all_paths,
        table4=table4,
    )


@dataclass(frozen=True, slots=True)
class Totals:
    """Sums over the digs of a plan or of a set of dig problems.

    Attributes:
        digs: Digs summed (a float, as the totals' other figures).
        T_s: Total dig time (s).
        volume_L: Total volume (L).
        energy_Wh: Total energy (Wh).
    """

    digs: float
    T_s: float
    volume_L: float
    energy_Wh: float

    @classmethod
    def of(cls, plan: TrenchPlan) -> Totals:
        """The totals of a trench plan's digs."""
        digs = plan.digs
        return cls(
            digs=float(len(plan.buckets)),
            T_s=float(sum(d.T_s for d in digs)),
            volume_L=float(sum(d.volume_m3 * 1e3 for d in digs)),
            energy_Wh=float(sum(d.energy_j / 3600.0 for d in digs)),
        )

    def change_to(self, other: Totals, *, digs: bool = True) -> dict[str, float | None]:
        """Relative change from ``other`` to these totals per figure (``self / other - 1``;
        None where ``other``'s is 0); ``digs`` False leaves the dig count out."""
        pairs = {
            "digs": (self.digs, other.digs),
            "T_s": (self.T_s, other.T_s),
            "volume_L": (self.volume_L, other.volume_L),
            "energy_Wh": (self.energy_Wh, other.energy_Wh),
        }
        if not digs:
            del pairs["digs"]
        return {k: (a / b - 1.0) if b else None for k, (a, b) in pairs.items()}

    def to_json(self) -> dict[str, float]:
        """``{"digs", "T_s", "volume_L", "energy_Wh"}``."""
        return {
            "digs": self.digs,
            "T_s": self.T_s,
            "volume_L": self.volume_L,
            "energy_Wh": self.energy_Wh,
        }


@dataclass(frozen=True, slots=True)
class SameProblems:
    """PINN and PSO on the very roughing dig problems of the PINN's trench plan, summed.

    Attributes:
        pinn: The PINN one-shot planner's totals.
        pso: The PSO teacher's totals.
        pso_solve_s: The teacher's solve time per problem (s; p50, p99), None without a problem.
    """

    pinn: Totals
    pso: Totals
    pso_solve_s: Distribution | None

    @property
    def pinn_vs_pso(self) -> dict[str, float | None]:
        """Relative change of the PINN's totals to the teacher's (T_s, volume_L, energy_Wh)."""
        return self.pinn.change_to(self.pso, digs=False)

    def to_json(self) -> dict[str, Any]:
        """``{"pinn", "pso", "pso_solve_s", "pinn_vs_pso"}``."""
        return {
            "pinn": self.pinn.to_json(),
            "pso": self.pso.to_json(),
            "pso_solve_s": self.pso_solve_s.to_json() if self.pso_solve_s is not None else None,
            "pinn_vs_pso": self.pinn_vs_pso,
        }


@dataclass(frozen=True, slots=True)
class PsoTrench:
    """The PSO teacher beside the PINN on one task.

    Attributes:
        same_problems: Both planners on the PINN plan's own dig problems.
        pso: The whole trench planned with the PSO as the one-shot planner.
        pso_plan_s: Its planning time (s).
    """

    same_problems: SameProblems
    pso: TrenchPlan
    pso_plan_s: float


@dataclass(frozen=True, slots=True)
class CycleFigures:
    """The dig cycles (the moves between two digs) of one plan or of several
    (:class:`~rt_runtime.planning.trench.Cycle`).

    Attributes:
        cycles: Dig cycles.
        moves_per_cycle_s: Mean move time of a cycle (s), None without a cycle.
        moves_vs_bound_mean: Mean of each cycle's move time over its bound (each joint stopping
            only where it reverses through the same corners), None without a cycle.
        moves_vs_bound_max: The largest of them, None likewise.
        fallbacks: Cycles made of rest-to-rest moves (no blend clear of the material).
    """

    cycles: int
    moves_per_cycle_s: float | None
    moves_vs_bound_mean: float | None
    moves_vs_bound_max: float | None
    fallbacks: int

    @classmethod
    def of(cls, cycles: list[dict[str, Any]]) -> CycleFigures:
        """The figures of the ``cycles`` entries of plans' JSON (``plan --json``)."""
        ratios = [c["moves_s"] / c["bound_s"] for c in cycles if c["bound_s"] > 0.0]
        return cls(
            cycles=len(cycles),
            moves_per_cycle_s=float(np.mean([c["moves_s"] for c in cycles])) if cycles else None,
            moves_vs_bound_mean=float(np.mean(ratios)) if ratios else None,
            moves_vs_bound_max=float(np.max(ratios)) if ratios else None,
            fallbacks=sum(not c["blended"] for c in cycles),
        )

    def to_json(self) -> dict[str, Any]:
        """``{"cycles", "moves_per_cycle_s", "moves_vs_bound": {"mean", "max"},
        "fallbacks"}``."""
        return {
            "cycles": self.cycles,
            "moves_per_cycle_s": self.moves_per_cycle_s,
            "moves_vs_bound": {"mean": self.moves_vs_bound_mean, "max": self.moves_vs_bound_max},
            "fallbacks": self.fallbacks,
        }


#: Goals on the dig cycles (issue 26, ``goals`` of ``bench plan``): a cycle's moves over its
#: bound, the mean over the tasks' cycles and the worst.
CYCLE_GOALS = {"moves_vs_bound_mean_max": 1.10, "moves_vs_bound_max": 1.20}


@dataclass(frozen=True, slots=True)
class TaskPlanBench:
    """One named task planned (``tasks.<name>`` of ``bench plan``).

    Attributes:
        pinn: The PINN planner's plan (the last timed pass; the plans are deterministic).
        plan_us: Whole-plan time over the passes (us; p50, p99).
        plan_per_dig_ms: The same per dig (ms).
        dig_plan_per_dig_ms: The same without the dig cycles' planning (stage ``transitions``):
            each dig's choice, plan and checks (ms).
        dig_plan_each_ms: Each dig's own planning over the passes (its choice, plan and
            checks, :attr:`TrenchPlan.dig_plan_us`; ms; p50, p99, p999, max).
        fill_L: Real volume of each dig (L).
        finishing: Finishing passes.
        travel_moves: Travel moves.
        task_time_s: Digs and moves (s).
        task_time_vs_first_design: ``task_time_s`` over the first planner design's, None for a
            task it did not plan.
        stage_us: Where the whole plan's time goes (us, medians per stage).
        numpy_geometry_plan_us: Whole-plan time of the numpy geometry reference (us; p50, p99).
        speedup_vs_numpy_geometry: Median reference time over median time.
        numpy_geometry_same_plan: The reference planned the same digs.
        yao: Yao Fig. 14's figures of the task, None for a task Yao did not dig.
        pso: The PSO beside it (JSON: its keys at this level, with ``pso_totals`` and
            ``pinn_vs_pso``), None when not run.

    JSON also: ``cycles`` (the plan's dig cycles, as ``plan --json``), ``moves_per_cycle_s``,
    ``cycle_figures`` (:class:`CycleFigures`).
    """

    pinn: TrenchPlan
    plan_us: Distribution
    plan_per_dig_ms: Distribution
    dig_plan_per_dig_ms: Distribution
    dig_plan_each_ms: Distribution
    fill_L: tuple[float, ...]
    finishing: int
    travel_moves: int
    task_time_s: float
    task_time_vs_first_design: float | None
    stage_us: Mapping[str, float]
    numpy_geometry_plan_us: Distribution
    speedup_vs_numpy_geometry: float
    numpy_geometry_same_plan: bool
    yao: Mapping[str, Any] | None
    pso: PsoTrench | None = None

    @property
    def totals(self) -> Totals:
        """The PINN plan's totals."""
        return Totals.of(self.pinn)

    @property
    def pso_totals(self) -> Totals | None:
        """The PSO plan's totals, None without it."""
        return Totals.of(self.pso.pso) if self.pso is not None else None

    @property
    def pinn_vs_pso(self) -> dict[str, float | None] | None:
        """Relative change of the PINN plan's totals to the PSO plan's, None without it."""
        pso_totals = self.pso_totals
        return self.totals.change_to(pso_totals) if pso_totals is not None else None

    def to_json(self) -> dict[str, Any]:
        """The task's keys (README ``bench plan``)."""
        plan = self.pinn.to_json()
        out: dict[str, Any] = {
            "pinn": plan,
            "cycles": plan["cycles"],
            "moves_per_cycle_s": plan["moves_per_cycle_s"],
            "cycle_figures": CycleFigures.of(plan["cycles"]).to_json(),
            "plan_us": self.plan_us.to_json(),
            "plan_per_dig_ms": self.plan_per_dig_ms.to_json(),
            "dig_plan_per_dig_ms": self.dig_plan_per_dig_ms.to_json(),
            "dig_plan_each_ms": self.dig_plan_each_ms.to_json(),
            "fill_L": list(self.fill_L),
            "finishing": self.finishing,
            "travel_moves": self.travel_moves,
            "task_time_s": self.task_time_s,
            "task_time_vs_first_design": self.task_time_vs_first_design,
            "stage_us": dict(self.stage_us),
            "numpy_geometry_plan_us": self.numpy_geometry_plan_us.to_json(),
            "speedup_vs_numpy_geometry": self.speedup_vs_numpy_geometry,
            "numpy_geometry_same_plan": self.numpy_geometry_same_plan,
            "totals": self.totals.to_json(),
        }
        pso_totals = self.pso_totals
        if self.pso is not None and pso_totals is not None:
            out["same_problems"] = self.pso.same_problems.to_json()
            out["pso"] = self.pso.pso.to_json()
            out["pso_plan_s"] = self.pso.pso_plan_s
            out["pso_totals"] = pso_totals.to_json()
            out["pinn_vs_pso"] = self.totals.change_to(pso_totals)
        out["yao"] = self.yao
        return out


@dataclass(frozen=True, slots=True)
class ReferenceProblem:
    """The dig problem of a same-run PINN reference.

    Attributes:
        task: The task it belongs to.
        dig: Its dig index.
        type: ``downward`` or ``backward``.
    """

    task: str
    dig: int
    type: str

    def to_json(self) -> dict[str, Any]:
        """``{"task", "dig", "type"}``."""
        return {"task": self.task, "dig": self.dig, "type": self.type}


@dataclass(frozen=True, slots=True)
class PinnReference:
    """The PINN planner's own time on one dig problem, measured in the same run.

    Attributes:
        pinn_plan_ms: Its plan time (ms; p50, p99).
        calls: Calls timed.
        problem: Which problem.
    """

    pinn_plan_ms: Distribution
    calls: int
    problem: ReferenceProblem

    def to_json(self) -> dict[str, Any]:
        """``{"pinn_plan_ms", "calls", "problem"}``."""
        return {
            "pinn_plan_ms": self.pinn_plan_ms.to_json(),
            "calls": self.calls,
            "problem": self.problem.to_json(),
        }


@dataclass(frozen=True, slots=True)
class TrenchBench:
    """Whole-plan time over every named task (``trench`` of ``bench plan``).

    Attributes:
        geometry: The screening geometry that ran (``c`` or ``numpy``).
        plan_us: Whole-plan time over all tasks and passes (us; p50, p99).
        numpy_geometry_plan_us: The same of the numpy geometry reference.
        plan_per_dig_ms: Plan time per dig over the tasks' medians (ms; p50, p99), None without
            a task.
        reference: One PINN plan call of the same run, None without a roughing dig.
        plan_per_dig_over_pinn_plan: Median plan time per dig over the reference's median,
            None without either.
        cycles: The dig cycles of every task's plan.
        dig_plan_per_dig_ms: ``plan_per_dig_ms`` without the dig cycles' planning (the tasks'
            ``dig_plan_per_dig_ms`` medians), None without a task.
        dig_plan_each_ms: Each dig's own planning, every dig of every task and pass (ms; p50,
            p99, p999, max), None without a dig.
    """

    geometry: str
    plan_us: Distribution
    numpy_geometry_plan_us: Distribution
    plan_per_dig_ms: Distribution | None
    reference: PinnReference | None
    plan_per_dig_over_pinn_plan: float | None
    cycles: CycleFigures | None = None
    dig_plan_per_dig_ms: Distribution | None = None
    dig_plan_each_ms: Distribution | None = None

    def to_json(self) -> dict[str, Any]:
        """The block's keys (README ``bench plan``)."""
        return {
            "dig_plan_each_ms": (
                self.dig_plan_each_ms.to_json() if self.dig_plan_each_ms is not None else None
            ),
            "dig_plan_per_dig_ms": (
                self.dig_plan_per_dig_ms.to_json() if self.dig_plan_per_dig_ms is not None else None
            ),
            "cycles": self.cycles.to_json() if self.cycles is not None else None,
            "geometry": self.geometry,
            "plan_us": self.plan_us.to_json(),
            "numpy_geometry_plan_us": self.numpy_geometry_plan_us.to_json(),
            "plan_per_dig_ms": (
                self.plan_per_dig_ms.to_json() if self.plan_per_dig_ms is not None else None
            ),
            "reference": self.reference.to_json() if self.reference is not None else None,
            "plan_per_dig_over_pinn_plan": self.plan_per_dig_over_pinn_plan,
        }


#: Goal of ``bench plan``: the plan time per dig (ms).
PLAN_PER_DIG_GOAL_MS = Distribution(p50=5.0, p99=20.0)


@dataclass(frozen=True, slots=True)
class PlanBenchReport:
    """The report of ``excavator-rt bench plan`` (README ``bench plan``).

    Attributes:
        rig: Rig profile name.
        tasks: The named tasks, None when none was asked for.
        trench: Whole-plan time over them, None likewise.
        random: The random suite (``--random``), else None.
        long: The long trenches (``--long``), else None.
    """

    rig: str
    tasks: Mapping[str, TaskPlanBench] | None = None
    trench: TrenchBench | None = None
    random: RandomSuite | None = None
    long: LongTrenches | None = None

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object: ``rig``; with named tasks ``tasks``, ``trench``,
        ``goals`` and ``paper``; ``random`` and ``long`` where run."""
        out: dict[str, Any] = {"rig": self.rig}
        if self.tasks is not None and self.trench is not None:
            # Yao's figures live with the trench planner; imported here, as it is used.
            from rt_runtime.planning.trench import YAO_FIG14

            out["tasks"] = {name: t.to_json() for name, t in self.tasks.items()}
            out["trench"] = self.trench.to_json()
            out["goals"] = {
                "coverage_error_max": 0.02,
                "overdig_max_mm": 5.0,
                "digs_max": {k: v["digs"] + 1 for k, v in YAO_FIG14.items()},
                "transition_penetration_max_mm": 5.0,
                "task_time_vs_first_design_max": 0.6,
                "plan_per_dig_ms": PLAN_PER_DIG_GOAL_MS.to_json(),
                "pinn_vs_pso_totals_max": 0.05,
                **CYCLE_GOALS,
            }
            out["paper"] = {"yao_fig14": YAO_FIG14, "yao_plan_ms_per_dig": [4.2, 4.5]}
        if self.random is not None:
            out["random"] = self.random.to_json()
        if self.long is not None:
            out["long"] = self.long.to_json()
        return out


def bench_plan(
    rig: Rig,
    tasks: tuple[str, ...] = ("A", "B", "C", "D"),
    *,
    passes: int = 3,
    pso: bool = True,
    pso_options: dict[str, Any] | None = None,
    model_dir: str | None = None,
) -> PlanBenchReport:
    """Whole-trench planning on Yao's Table 3 tasks: PINN timed, PSO beside it.

    Each task is planned ``passes`` times with the PINN planner (the plans are deterministic;
    the times are the distribution) and, with ``pso``, once with the PSO teacher as the one-shot
    planner. Reported per task: digs (with T, V_p, W_E, theta_p), coverage error, maximum
    over-dig, whole-plan time (p50/p99) and where it goes (``stage_us``, medians per stage),
    the PSO plan's totals and the ratio of the totals, and (``same_problems``) both planners
    on the PINN plan's own dig problems, summed.

    The reference measured in the same run: the same planner with its geometry in numpy
    (``geometry="numpy"``, the reference of the C screening geometry), its passes interleaved
    with the timed ones; ``numpy_geometry_same_plan`` says whether it planned the same digs.
    """
    from rt_runtime.planning.trench import YAO_FIG14, TrenchPlanner, load_task

    pinn = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    ref = TrenchPlanner(rig, "pinn", model_dir=model_dir, geometry="numpy")
    geometry = "c" if pinn.geo_kernel is not None else "numpy"
    out: dict[str, TaskPlanBench] = {}
    all_us: list[float] = []
    all_ref: list[float] = []
    all_each_ms: list[float] = []
    for name in tasks:
        task = load_task(name, rig)
        times: list[float] = []
        ref_times: list[float] = []
        stages: list[dict[str, float]] = []
        each_ms: list[float] = []
        plan = ref_plan = None
        for _ in range(max(1, passes)):
            plan = pinn.plan(task)
            times.append(plan.plan_total_us)
            stages.append(plan.stage_us)
            each_ms += [t / 1e3 for t in plan.dig_plan_us]
            ref_plan = ref.plan(task)
            ref_times.append(ref_plan.plan_total_us)
        assert plan is not None and ref_plan is not None
        # Figures the plan gives in its JSON only (its moves' times, its travel moves).
        report = plan.to_json()
        all_us += times
        all_ref += ref_times
        all_each_ms += each_ms
        task_time = report["dig_time_s"] + report["transition_time_s"]
        before = FIRST_DESIGN_TASK_TIME_S.get(name)
        versus: PsoTrench | None = None
        if pso:
            same = _same_problems(rig, pinn, plan.digs, pso_options or {})
            t0 = time.perf_counter()
            pso_plan = TrenchPlanner(rig, "pso", model_dir=model_dir, pso_options=pso_options).plan(
                task
            )
            versus = PsoTrench(same, pso_plan, time.perf_counter() - t0)
        out[name] = TaskPlanBench(
            pinn=plan,
            plan_us=Distribution.of(times),
            plan_per_dig_ms=Distribution.of([t / 1e3 / max(len(plan.digs), 1) for t in times]),
            dig_plan_per_dig_ms=Distribution.of(
                [
                    (t - st["transitions"]) / 1e3 / max(len(plan.digs), 1)
                    for t, st in zip(times, stages, strict=True)
                ]
            ),
            dig_plan_each_ms=Distribution.spread(each_ms),
            fill_L=tuple(v * 1e3 for v in plan.bucket_volumes_m3),
            finishing=sum(b[0].finishing for b in plan.buckets),
            travel_moves=len(report["travel"]),
            task_time_s=task_time,
            task_time_vs_first_design=task_time / before if before else None,
            stage_us={k: float(np.median([st[k] for st in stages])) for k in stages[0]},
            numpy_geometry_plan_us=Distribution.of(ref_times),
            speedup_vs_numpy_geometry=float(np.median(ref_times) / np.median(times)),
            numpy_geometry_same_plan=len(ref_plan.digs) == len(plan.digs)
            and abs(ref_plan.coverage_error - plan.coverage_error) <= 1e-9,
            yao=YAO_FIG14.get(name),
            pso=versus,
        )
    per_dig = [e.plan_per_dig_ms.p50 for e in out.values()]
    dig_per_dig = [e.dig_plan_per_dig_ms.p50 for e in out.values()]
    first = next(
        (
            (name, d.index, d.problem)
            for name, e in out.items()
            for d in e.pinn.digs
            if d.status == "filled"
        ),
        None,
    )
    reference = _pinn_reference(pinn, first)
    return PlanBenchReport(
        rig=rig.name,
        tasks=out,
        trench=TrenchBench(
            geometry=geometry,
            plan_us=Distribution.of(all_us),
            numpy_geometry_plan_us=Distribution.of(all_ref),
            plan_per_dig_ms=Distribution.of(per_dig) if per_dig else None,
            reference=reference,
            plan_per_dig_over_pinn_plan=(
                float(np.median(per_dig) / reference.pinn_plan_ms.p50)
                if reference and per_dig
                else None
            ),
            cycles=CycleFigures.of([c for e in out.values() for c in e.pinn.to_json()["cycles"]]),
            dig_plan_per_dig_ms=Distribution.of(dig_per_dig) if dig_per_dig else None,
            dig_plan_each_ms=Distribution.of(all_each_ms, tails=True) if all_each_ms else None,
        ),
    )


def _same_problems(rig: Rig, planner: Any, digs: Any, pso_options: dict[str, Any]) -> SameProblems:
    """PINN and PSO on the very dig problems of the PINN's trench plan (Yao Table 4's pairing).

    Two whole-trench plans, one per one-shot planner, drift apart after the first dig (each
    leaves its own material, so later digs are different problems; the counts differ too).
    The like-for-like comparison of the two planners is per problem: every roughing dig of the
    PINN's plan (its entry and exit poses, surface height and type; the digs along the
    design's outline are fitted, not one-shot planned, and are the same for both) is planned by
    the PINN one-shot planner and by the PSO teacher, and T, V_p and W_E are summed over the
    task.
    """
    from rt_runtime.planning import oneshot

    sums = {"pinn": [0.0, 0.0, 0.0], "pso": [0.0, 0.0, 0.0]}
    n = 0
    pso_s: list[float] = []
    for d in digs:
        if d.status in ("profile", "profile_pass"):
            continue
        problem = d.problem
        plan = planner.pinn.plan(
            problem.q_start_rad, problem.q_end_rad, problem.surface_y_m, problem.dig_type
        )
        v = plan.verification
        t0 = time.perf_counter()
        sol = oneshot.solve_pso(rig, [problem], **pso_options)[0]
        pso_s.append(time.perf_counter() - t0)
        for key, (T, vol, e) in (
            ("pinn", (plan.T_s, v.volume_m3, v.energy_j)),
            ("pso", (sol.T_s, sol.volume_m3, sol.energy_j)),
        ):
            sums[key][0] += T
            sums[key][1] += vol * 1e3
            sums[key][2] += e / 3600.0
        n += 1
    totals = {k: Totals(float(n), t[0], t[1], t[2]) for k, t in sums.items()}
    return SameProblems(
        pinn=totals["pinn"],
        pso=totals["pso"],
        pso_solve_s=Distribution.of(pso_s) if pso_s else None,
    )


#: Whole task time (digs + moves, s) of A-D with the first trench planner design, which the
#: second design's task-time goal is measured against (<= 60 % of it).
FIRST_DESIGN_TASK_TIME_S = {"A": 158.0, "B": 113.0, "C": 137.0, "D": 216.0}
#: Long trenches of `bench plan --long` (scale model: length m, depth m; scaled by reach).
LONG_TRENCHES = ((3.0, 0.15), (8.0, 0.10), (20.0, 0.20))


@dataclass(frozen=True, slots=True)
class LongTrench:
    """One long trench dug section by section (``long.trenches.<L>m``).

    Attributes:
        length_m: Length (m).
        depth_m: Depth (m).
        sections: Sections.
        travel_moves: Travel moves.
        travel_one_way: Every travel move goes back along the trench.
        coverage_error: Coverage error of the whole trench.
        section_coverage_max: Worst section's coverage error.
        overdig_max_mm: Deepest over-dig (mm).
        digs: Digs.
        finishing_per_section_max: Most finishing passes of one section.
        fill_within_band: Fraction of roughing digs within the one-shot volume window, None
            without one.
        status: ``done`` or ``incomplete``.
        plan_s: Plan time (s).
        plan_s_per_m: Plan time per metre (s/m).
    """

    length_m: float
    depth_m: float
    sections: int
    travel_moves: int
    travel_one_way: bool
    coverage_error: float
    section_coverage_max: float
    overdig_max_mm: float
    digs: int
    finishing_per_section_max: int
    fill_within_band: float | None
    status: str
    plan_s: float
    plan_s_per_m: float

    def to_json(self) -> dict[str, Any]:
        """The trench's keys, as the attributes."""
        return {
            "length_m": self.length_m,
            "depth_m": self.depth_m,
            "sections": self.sections,
            "travel_moves": self.travel_moves,
            "travel_one_way": self.travel_one_way,
            "coverage_error": self.coverage_error,
            "section_coverage_max": self.section_coverage_max,
            "overdig_max_mm": self.overdig_max_mm,
            "digs": self.digs,
            "finishing_per_section_max": self.finishing_per_section_max,
            "fill_within_band": self.fill_within_band,
            "status": self.status,
            "plan_s": self.plan_s,
            "plan_s_per_m": self.plan_s_per_m,
        }


@dataclass(frozen=True, slots=True)
class LongTrenches:
    """The long trenches of ``bench plan --long`` (``long``).

    Attributes:
        trenches: Per trench, keyed ``"<L>m"`` by its scale-model length.
        plan_s_per_m: Least and most plan time per metre over the trenches (s/m).
    """

    trenches: Mapping[str, LongTrench]
    plan_s_per_m: Range

    def to_json(self) -> dict[str, Any]:
        """``{"trenches", "plan_s_per_m"}``."""
        return {
            "trenches": {name: t.to_json() for name, t in self.trenches.items()},
            "plan_s_per_m": self.plan_s_per_m.to_json(),
        }


def bench_plan_long(
    rig: Rig,
    trenches: tuple[tuple[float, float], ...] = LONG_TRENCHES,
    *,
    planner: Any = None,
    model_dir: str | None = None,
) -> LongTrenches:
    """Long trenches dug section by section: each planned once (walls 60/60 deg, far edge at
    the default start). Reported per trench: sections, travel moves and whether every one goes
    back along the trench, coverage (whole and worst section), over-dig, digs, finishing
    passes per section (max), fill band, status, plan time and plan time per metre (linear in
    length when the per-metre figures agree).
    """
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.trench import TravelMove, TrenchPlanner, make_task

    if planner is None:
        planner = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    scale = float(np.sum(rig.lengths_m)) / 1.31
    planning = oneshot.require_planning(rig)
    lo, hi = planning.volume_min_m3, planning.volume_max_m3
    out: dict[str, LongTrench] = {}
    per_m: list[float] = []
    for length, depth in trenches:
        task = make_task(rig, length * scale, depth * scale, 60.0, 60.0, name=f"long-{length:g}m")
        trench = planner.start(task)
        t0 = time.perf_counter()
        plan = planner.plan(task)
        wall = time.perf_counter() - t0
        travels = [s.distance_m for s in plan.steps if isinstance(s, TravelMove)]
        section_coverage: list[float] = []
        section_finishing: list[int] = []
        for k, (x0, x1) in enumerate(trench.sections):
            box = shapely.box(x0, -1e3, x1, 1e3)
            design = plan.design.intersection(box)
            dug = plan.dug.intersection(box)
            section_coverage.append(
                float(dug.symmetric_difference(design).area) / float(design.area)
            )
            section_finishing.append(
                sum(b[0].finishing for b in plan.buckets if b[0].section == k)
            )
        full = [
            v
            for v, b in zip(plan.bucket_volumes_m3, plan.buckets, strict=True)
            if not b[0].finishing
        ]
        per_m.append(wall / task.length_m)
        out[f"{length:g}m"] = LongTrench(
            length_m=task.length_m,
            depth_m=task.depth_m,
            sections=len(trench.sections),
            travel_moves=len(travels),
            travel_one_way=all(t < 0.0 for t in travels),
            coverage_error=plan.coverage_error,
            section_coverage_max=max(section_coverage),
            overdig_max_mm=plan.overdig_max_m * 1e3,
            digs=len(plan.buckets),
            finishing_per_section_max=max(section_finishing),
            fill_within_band=(
                sum(lo - 1e-12 <= v <= hi + 1e-12 for v in full) / len(full) if full else None
            ),
            status=plan.status.name.lower(),
            plan_s=wall,
            plan_s_per_m=wall / task.length_m,
        )
    return LongTrenches(out, Range(min(per_m), max(per_m)))


# ---------------------------------------------------------------------------------------------
# The random suite: `excavator-rt bench plan --random N --seed S`.

#: Lengths of the random suite's tasks (scale model, m; scaled by reach): from the domain's
#: shortest trench to one that takes two or three stands of the machine.
RANDOM_LENGTH_M = (0.30, 1.50)
#: The random suite's goals on the coverage error (fractions within which it counts tasks).
RANDOM_COVERAGE_BANDS = {"within_2pct": 0.02, "within_4pct": 0.04}
#: Tasks listed under ``worst`` in the random suite's report.
RANDOM_WORST = 5
#: Calls of the PINN planner on one dig problem for the suite's same-run reference.
RANDOM_REFERENCE_CALLS = 100


def random_tasks(rig: Rig, n: int, seed: int) -> list[Any]:
    """``n`` trench tasks drawn uniformly over the task domain of ``rig``.

    Each value is drawn uniformly and independently, in this order: length
    (:data:`RANDOM_LENGTH_M` scaled by reach, within the domain), depth, far wall, near wall
    and far edge ``start_x_m``, each over its whole range of
    :func:`rt_runtime.planning.trench.task_limits`. A draw whose walls meet above its depth is
    drawn again, all five values, from the same generator, so the suite is a function of
    ``(rig, n, seed)``.

    Returns:
        ``n`` :class:`~rt_runtime.planning.trench.TrenchTask`, named ``random-<seed>-<i>``.
    """
    from rt_runtime.planning.trench import make_task, task_limits
    from rt_runtime.rig.model import SCALE_MODEL_REACH_M

    rng = np.random.default_rng(seed)
    limits = task_limits(rig)
    s = float(np.sum(rig.lengths_m)) / SCALE_MODEL_REACH_M
    lo_l, hi_l = limits["length_m"]
    ranges = (
        (max(lo_l, RANDOM_LENGTH_M[0] * s), min(hi_l, RANDOM_LENGTH_M[1] * s)),
        limits["depth_m"],
        limits["beta1_deg"],
        limits["beta2_deg"],
        limits["start_x_m"],
    )
    tasks = []
    for i in range(n):
        while True:
            L, D, b1, b2, x = (float(rng.uniform(lo, hi)) for lo, hi in ranges)
            bottom = L - D / math.tan(math.radians(b1)) - D / math.tan(math.radians(b2))
            if bottom >= 0.0:
                break
        tasks.append(make_task(rig, L, D, b1, b2, x, name=f"random-{seed}-{i}"))
    return tasks


@dataclass(frozen=True, slots=True)
class RandomTaskPlan:
    """How one task of the random suite planned.

    Attributes:
        coverage_error: Coverage error.
        overdig_max_mm: Deepest over-dig (mm).
        digs: Digs (buckets: a dig with the digs joined to it is one).
        status: ``done`` or ``incomplete``.
        reason: The unmet goals, None when done.
        volume_left_L: Design material left (L).
        transition_penetration_max_mm: Deepest move into the material (mm).
        plan_ms: Plan time (ms).
        task_time_s: Digs and moves (s).
        cycles_plan_ms: Of ``plan_ms``, the dig cycles' planning (stage ``transitions``; ms).
        finishing_per_section: Finishing passes of each section, in order.
        moves_per_cycle_s: Mean move time of a dig cycle (s), None without one.
        moves_vs_bound_max: The largest move time of a dig cycle over its bound, None likewise.
        cycle_fallbacks: Dig cycles of rest-to-rest moves.
        pieces: Digs planned, each piece of a joined dig one (one sextic each).
    """

    coverage_error: float
    overdig_max_mm: float
    digs: int
    status: str
    reason: str | None
    volume_left_L: float
    transition_penetration_max_mm: float
    plan_ms: float
    task_time_s: float = 0.0
    cycles_plan_ms: float = 0.0
    finishing_per_section: tuple[int, ...] = ()
    moves_per_cycle_s: float | None = None
    moves_vs_bound_max: float | None = None
    cycle_fallbacks: int = 0
    pieces: int = 0


@dataclass(frozen=True, slots=True)
class RandomTask:
    """One task of the random suite, with its values so that ``plan`` can replay it.

    Attributes:
        name: ``random-<seed>-<i>``.
        length_m: Length (m).
        depth_m: Depth (m).
        beta1_deg: Far wall (deg).
        beta2_deg: Near wall (deg).
        start_x_m: Far edge (m).
        planned: How it planned (JSON: its keys at this level), None when planning raised.
        error: The exception's type and message when planning raised, else None.
    """

    name: str
    length_m: float
    depth_m: float
    beta1_deg: float
    beta2_deg: float
    start_x_m: float
    planned: RandomTaskPlan | None = None
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The task's values, then ``error`` or the plan's figures."""
        out: dict[str, Any] = {
            "name": self.name,
            "length_m": self.length_m,
            "depth_m": self.depth_m,
            "beta1_deg": self.beta1_deg,
            "beta2_deg": self.beta2_deg,
            "start_x_m": self.start_x_m,
        }
        if self.error is not None:
            out["error"] = self.error
        if self.planned is not None:
            out.update(dataclasses.asdict(self.planned))
        return out


@dataclass(frozen=True, slots=True)
class FillFigures:
    """Real volume of the random suite's roughing digs (``fill``).

    Attributes:
        min: Smallest (L), None without a roughing dig.
        p50: Median (L), None likewise.
        max: Largest (L), None likewise.
        band_L: The rig's one-shot volume window (L).
        within_band: Fraction of roughing digs inside it, None without one.
        n: Roughing digs.
    """

    min: float | None
    p50: float | None
    max: float | None
    band_L: tuple[float, float]
    within_band: float | None
    n: int

    def to_json(self) -> dict[str, Any]:
        """``{"min", "p50", "max", "band_L", "within_band", "n"}``."""
        return {
            "min": self.min,
            "p50": self.p50,
            "max": self.max,
            "band_L": list(self.band_L),
            "within_band": self.within_band,
            "n": self.n,
        }


@dataclass(frozen=True, slots=True)
class RandomSuite:
    """The random suite of ``bench plan --random`` (README ``bench plan --random``; ``random``).

    Groups over no planned task are None.

    Attributes:
        rig: Rig profile name.
        tasks: Tasks drawn.
        seed: Seed of the draw.
        within_2pct: Fraction of the tasks with a coverage error within 2 %.
        within_4pct: The same within 4 %.
        coverage_error: Over the planned tasks (p50, p99, max).
        overdig_max_mm: Deepest over-dig per task (mm; p50, max).
        digs: Digs per task (p50, max).
        fill: Real volume of the roughing digs.
        finishing_per_section_max: Most finishing passes of one section over the tasks.
        sections_within_finishing_goal: Fraction of the planned tasks' sections with at most
            the finishing passes a section may take (``MAX_FINISHING_PER_SECTION``), None
            without a planned task.
        transition_penetration_max_mm: Deepest move into the material per task (mm; p50, max).
        plan_ms: Plan time per task (ms; p50, p99).
        plan_per_dig_ms: Plan time per dig (ms; p50, p99).
        dig_plan_per_dig_ms: The same without the dig cycles' planning (stage ``transitions``):
            each dig's choice, plan and checks (ms; p50, p99).
        dig_plan_each_ms: Each dig's own planning, every dig of every planned task (its
            choice, plan and checks, :attr:`TrenchPlan.dig_plan_us`; ms; p50, p99, p999, max).
        status_done: Fraction of the tasks done.
        reference: One PINN plan call of the same run, None without a roughing dig.
        plan_per_dig_over_pinn_plan: Median plan time per dig over the reference's median.
        per_task: Every task, in draw order.
        cycles: The dig cycles of every planned task.
    """

    rig: str
    tasks: int
    seed: int
    within_2pct: float
    within_4pct: float
    coverage_error: Distribution | None
    overdig_max_mm: Spread | None
    digs: Spread | None
    fill: FillFigures
    finishing_per_section_max: int
    transition_penetration_max_mm: Spread | None
    plan_ms: Distribution | None
    plan_per_dig_ms: Distribution | None
    status_done: float
    reference: PinnReference | None
    plan_per_dig_over_pinn_plan: float | None
    per_task: tuple[RandomTask, ...]
    cycles: CycleFigures | None = None
    sections_within_finishing_goal: float | None = None
    dig_plan_per_dig_ms: Distribution | None = None
    dig_plan_each_ms: Distribution | None = None

    @property
    def error_tasks(self) -> tuple[RandomTask, ...]:
        """The tasks whose planning raised."""
        return tuple(t for t in self.per_task if t.planned is None)

    @property
    def errors(self) -> int:
        """How many tasks' planning raised."""
        return len(self.error_tasks)

    @property
    def worst(self) -> tuple[RandomTask, ...]:
        """The :data:`RANDOM_WORST` planned tasks with the largest coverage error, worst first."""
        planned = [(t.planned.coverage_error, t) for t in self.per_task if t.planned is not None]
        return tuple(t for _, t in sorted(planned, key=lambda ct: -ct[0])[:RANDOM_WORST])

    def to_json(self) -> dict[str, Any]:
        """The suite's keys (README ``bench plan --random``)."""

        def opt(group: Distribution | Spread | None) -> dict[str, float] | None:
            return group.to_json() if group is not None else None

        return {
            "rig": self.rig,
            "tasks": self.tasks,
            "seed": self.seed,
            "within_2pct": self.within_2pct,
            "within_4pct": self.within_4pct,
            "coverage_error": opt(self.coverage_error),
            "overdig_max_mm": opt(self.overdig_max_mm),
            "digs": opt(self.digs),
            "fill": self.fill.to_json(),
            "finishing_per_section_max": self.finishing_per_section_max,
            "sections_within_finishing_goal": self.sections_within_finishing_goal,
            "transition_penetration_max_mm": opt(self.transition_penetration_max_mm),
            "plan_ms": opt(self.plan_ms),
            "plan_per_dig_ms": opt(self.plan_per_dig_ms),
            "dig_plan_per_dig_ms": opt(self.dig_plan_per_dig_ms),
            "dig_plan_each_ms": opt(self.dig_plan_each_ms),
            "status_done": self.status_done,
            "errors": self.errors,
            "error_tasks": [t.to_json() for t in self.error_tasks],
            "worst": [t.to_json() for t in self.worst],
            "reference": self.reference.to_json() if self.reference is not None else None,
            "per_task": [t.to_json() for t in self.per_task],
            "plan_per_dig_over_pinn_plan": self.plan_per_dig_over_pinn_plan,
            "cycles": self.cycles.to_json() if self.cycles is not None else None,
        }


def bench_plan_random(
    rig: Rig,
    n: int,
    seed: int = 0,
    *,
    model_dir: str | None = None,
    planner: Any = None,
) -> RandomSuite:
    """The random suite: ``n`` seeded tasks over the whole domain (:func:`random_tasks`),
    each planned with the PINN planner.

    An exception while planning a task is caught and kept with the task (``error``: its type
    and message) instead of ending the run; such a task counts as neither within a coverage
    band nor done. The same-run reference is the PINN planner's own call on one dig problem
    (the first roughing dig of the first task that has one, planned
    :data:`RANDOM_REFERENCE_CALLS` times as the trench planner calls it), beside the whole
    plans' time per dig.

    Args:
        rig: The rig.
        n: Number of tasks.
        seed: Seed of the task generator.
        model_dir: PINN model directory (default: the shipped ``onnx/``).
        planner: A :class:`~rt_runtime.planning.trench.TrenchPlanner` to use (default: a PINN
            planner built for ``rig``).
    """
    from rt_runtime.planning import oneshot
    from rt_runtime.planning.trench import MAX_FINISHING_PER_SECTION, TrenchPlanner

    if planner is None:
        planner = TrenchPlanner(rig, "pinn", model_dir=model_dir)
    planning = oneshot.require_planning(rig)
    band_l = (planning.volume_min_m3 * 1e3, planning.volume_max_m3 * 1e3)
    tasks = random_tasks(rig, n, seed)
    records: list[RandomTask] = []
    all_cycles: list[dict[str, Any]] = []
    fills: list[float] = []
    each_ms: list[float] = []
    finishing_max = 0
    first_problem: Any = None
    for task in tasks:
        values = {
            "name": task.name,
            "length_m": task.length_m,
            "depth_m": task.depth_m,
            "beta1_deg": math.degrees(task.beta1_rad),
            "beta2_deg": math.degrees(task.beta2_rad),
            "start_x_m": task.start_x_m,
        }
        try:
            plan = planner.plan(task)
            # Figures the plan gives in its JSON only (its moves' penetration, the left volume).
            report = plan.to_json()
        except Exception as e:  # every failure is a result of the suite, kept with its task
            records.append(RandomTask(**values, error=f"{type(e).__name__}: {e}"))
            continue
        buckets = plan.buckets
        each_ms += [t / 1e3 for t in plan.dig_plan_us]
        fills += [
            v * 1e3
            for v, b in zip(plan.bucket_volumes_m3, buckets, strict=True)
            if not b[0].finishing
        ]
        per_section: dict[int, int] = {}
        for b in buckets:
            per_section.setdefault(b[0].section, 0)
            if b[0].finishing:
                per_section[b[0].section] += 1
        finishing_max = max(finishing_max, *per_section.values(), 0)
        if first_problem is None:
            first = next((d for d in plan.digs if d.status == "filled"), None)
            if first is not None:
                first_problem = (task.name, first.index, first.problem)
        cycles = CycleFigures.of(report["cycles"])
        all_cycles += report["cycles"]
        planned = RandomTaskPlan(
            coverage_error=plan.coverage_error,
            overdig_max_mm=plan.overdig_max_m * 1e3,
            digs=len(buckets),
            pieces=len(plan.digs),
            status=plan.status.name.lower(),
            reason=plan.reason,
            volume_left_L=report["volume_left_L"],
            transition_penetration_max_mm=report["transition_penetration_max_mm"],
            plan_ms=plan.plan_total_us / 1e3,
            task_time_s=report["dig_time_s"] + report["transition_time_s"],
            cycles_plan_ms=plan.stage_us["transitions"] / 1e3,
            finishing_per_section=tuple(per_section[k] for k in sorted(per_section)),
            moves_per_cycle_s=cycles.moves_per_cycle_s,
            moves_vs_bound_max=cycles.moves_vs_bound_max,
            cycle_fallbacks=cycles.fallbacks,
        )
        records.append(RandomTask(**values, planned=planned))
    planned_tasks = [r.planned for r in records if r.planned is not None]
    coverage = [r.coverage_error for r in planned_tasks]
    # Per dig planned: each piece of a joined dig is one (one next_dig()).
    per_dig = [r.plan_ms / r.pieces for r in planned_tasks if r.pieces]
    dig_per_dig = [(r.plan_ms - r.cycles_plan_ms) / r.pieces for r in planned_tasks if r.pieces]
    sections = [k for r in planned_tasks for k in r.finishing_per_section]
    reference = _pinn_reference(planner, first_problem)
    within = {
        k: sum(c <= v for c in coverage) / max(n, 1) for k, v in RANDOM_COVERAGE_BANDS.items()
    }

    def spread(values: list[float]) -> Spread | None:
        return Spread.of(values) if values else None

    return RandomSuite(
        rig=rig.name,
        tasks=n,
        seed=seed,
        within_2pct=within["within_2pct"],
        within_4pct=within["within_4pct"],
        coverage_error=Distribution.spread(coverage) if coverage else None,
        overdig_max_mm=spread([r.overdig_max_mm for r in planned_tasks]),
        digs=spread([float(r.digs) for r in planned_tasks]),
        fill=FillFigures(
            min=float(np.min(fills)) if fills else None,
            p50=float(np.percentile(fills, 50)) if fills else None,
            max=float(np.max(fills)) if fills else None,
            band_L=band_l,
            within_band=(
                sum(band_l[0] <= v <= band_l[1] for v in fills) / len(fills) if fills else None
            ),
            n=len(fills),
        ),
        finishing_per_section_max=finishing_max,
        transition_penetration_max_mm=spread(
            [r.transition_penetration_max_mm for r in planned_tasks]
        ),
        plan_ms=Distribution.of([r.plan_ms for r in planned_tasks]) if planned_tasks else None,
        plan_per_dig_ms=Distribution.of(per_dig) if per_dig else None,
        dig_plan_per_dig_ms=Distribution.of(dig_per_dig) if dig_per_dig else None,
        dig_plan_each_ms=Distribution.of(each_ms, tails=True) if each_ms else None,
        sections_within_finishing_goal=(
            sum(k <= MAX_FINISHING_PER_SECTION for k in sections) / len(sections)
            if sections
            else None
        ),
        status_done=sum(r.status == "done" for r in planned_tasks) / max(n, 1),
        reference=reference,
        plan_per_dig_over_pinn_plan=(
            float(np.median(per_dig) / reference.pinn_plan_ms.p50)
            if reference is not None and per_dig
            else None
        ),
        per_task=tuple(records),
        cycles=CycleFigures.of(all_cycles),
    )


def _pinn_reference(planner: Any, first: Any) -> PinnReference | None:
    """The PINN planner's own time on one dig problem (``(task, dig index, problem)``), called
    as the trench planner calls it (no solution library); None without a problem or when the
    call fails."""
    from rt_runtime.errors import PlanningError

    if first is None:
        return None
    name, index, p = first
    times: list[float] = []
    try:
        for _ in range(RANDOM_REFERENCE_CALLS):
            t0 = time.perf_counter()
            planner.pinn.plan(p.q_start_rad, p.q_end_rad, p.surface_y_m, p.dig_type, library=False)
            times.append((time.perf_counter() - t0) * 1e3)
    except PlanningError:
        return None
    return PinnReference(
        pinn_plan_ms=Distribution.of(times),
        calls=len(times),
        problem=ReferenceProblem(task=name, dig=index, type=p.dig_type.name.lower()),
    )


# ---------------------------------------------------------------------------------------------
# The full suite: `excavator-rt bench` without a subcommand.

#: Goal: loop lateness at 500 Hz, p99 (us).
LOOP_LATENESS_P99_GOAL_US = 50.0
#: A comfortable pose of the scale model for holding (boom 30, stick -90, bucket -60 deg).
_HOLD_POSE_DEG = (30.0, -90.0, -60.0)


@dataclass(frozen=True, slots=True)
class BenchSizes:
    """How much work each part of :func:`bench_full` does.

    Attributes:
        pinn_limit: Held-out problems per dig type (None: all).
        pinn_passes: Timed passes of the PINN planner over them.
        pso_problems: Problems per dig type the PSO solves in the same run.
        trench_passes: Timed whole-trench plans of task A.
        loop_seconds: Loop run per rate (s).
    """

    pinn_limit: int | None = None
    pinn_passes: int = 5
    pso_problems: int = 5
    trench_passes: int = 3
    loop_seconds: float = 10.0

    @classmethod
    def quick(cls, loop_seconds: float = 1.0) -> BenchSizes:
        """Tiny sizes for tests and a first look (seconds, not minutes)."""
        return cls(
            pinn_limit=8, pinn_passes=1, pso_problems=1, trench_passes=1, loop_seconds=loop_seconds
        )

    def to_json(self) -> dict[str, Any]:
        """``sizes`` of ``bench --json`` (``pso_problems`` as ``pso_problems_per_type``)."""
        return {
            "pinn_limit": self.pinn_limit,
            "pinn_passes": self.pinn_passes,
            "pso_problems_per_type": self.pso_problems,
            "trench_passes": self.trench_passes,
            "loop_seconds": self.loop_seconds,
        }


def _group_us(values_s: np.ndarray) -> Distribution | None:
    """Percentiles with tails of the finite values in seconds, in microseconds; None if none."""
    a = np.asarray(values_s, dtype=np.float64)
    a = a[np.isfinite(a)]
    return Distribution.of(a * 1e6, tails=True) if a.size else None


def _json(group: Distribution | None) -> dict[str, float] | None:
    return group.to_json() if group is not None else None


@dataclass(frozen=True, slots=True)
class OverrunRecord:
    """One overrun of a loop run (``overrun_events``).

    Attributes:
        cycle: Cycle index on the period grid.
        lateness_us: How late the cycle started (us).
        skipped: Deadlines skipped by the re-phase.
    """

    cycle: int
    lateness_us: float
    skipped: int

    def to_json(self) -> dict[str, Any]:
        """``{"cycle", "lateness_us", "skipped"}``."""
        return {"cycle": self.cycle, "lateness_us": self.lateness_us, "skipped": self.skipped}


@dataclass(frozen=True, slots=True)
class LoopRateBench:
    """The loop at one rate against the real-time HIL (``loop.<rate>`` of ``bench --json``).

    Timing groups are in microseconds with p50, p99, p999 and max, None where no cycle gave a
    value.

    Attributes:
        period_us: Nominal period (us).
        cycles: Cycles run.
        seconds: Run time asked for (s).
        lateness_us: Cycle start minus deadline.
        jitter_us: |actual - nominal period| between consecutive grid cycles.
        jitter_signed_us: Least and largest actual - nominal period (us).
        exec_us: The loop's step (the daemon's hold cycle).
        send_us: Sending the frames.
        wait_us: Waiting for the drives' answers.
        transport_us: ``send_us + wait_us``, per cycle.
        own_us: The runtime's own work (the step minus the transport's parts).
        overruns: Overrun cycles.
        skipped: Deadlines skipped by re-phasing.
        max_consecutive_overruns: Longest run of overruns.
        safe_stop: The overrun policy asked for a safe stop.
        overrun_events: The first ten overruns.
        sync_rtt_us: SYNC -> last TPDO1 round trip.
        stale_cycles: Cycles without a fresh answer.
        fault_cycles: Cycles whose status was EMCY or worse.
        cycle_status: Cycles per :class:`~rt_runtime.canbus.CycleStatus` name.
        bus_load: Bus load of the cyclic frames.
        rt: What the OS granted and refused (JSON: per RT item).
        hil_process: The real-time HIL's own figures as its process class reports them (a JSON
            object: the runtime never imports the HIL's types), None when it gives none.
    """

    period_us: float
    cycles: int
    seconds: float
    lateness_us: Distribution | None
    jitter_us: Distribution | None
    jitter_signed_us: Range
    exec_us: Distribution | None
    send_us: Distribution | None
    wait_us: Distribution | None
    transport_us: Distribution | None
    own_us: Distribution | None
    overruns: int
    skipped: int
    max_consecutive_overruns: int
    safe_stop: bool
    overrun_events: tuple[OverrunRecord, ...]
    sync_rtt_us: Distribution | None
    stale_cycles: int
    fault_cycles: int
    cycle_status: Mapping[str, int]
    bus_load: BusLoadFigures
    rt: RtReport
    hil_process: Mapping[str, Any] | None

    def to_json(self) -> dict[str, Any]:
        """The rate's keys (README ``bench --json`` ``loop``)."""
        return {
            "period_us": self.period_us,
            "cycles": self.cycles,
            "seconds": self.seconds,
            "lateness_us": _json(self.lateness_us),
            "jitter_us": _json(self.jitter_us),
            "jitter_signed_us": self.jitter_signed_us.to_json(),
            "exec_us": _json(self.exec_us),
            "send_us": _json(self.send_us),
            "wait_us": _json(self.wait_us),
            "transport_us": _json(self.transport_us),
            "own_us": _json(self.own_us),
            "overruns": self.overruns,
            "skipped": self.skipped,
            "max_consecutive_overruns": self.max_consecutive_overruns,
            "safe_stop": self.safe_stop,
            "overrun_events": [e.to_json() for e in self.overrun_events],
            "sync_rtt_us": _json(self.sync_rtt_us),
            "stale_cycles": self.stale_cycles,
            "fault_cycles": self.fault_cycles,
            "cycle_status": dict(self.cycle_status),
            "bus_load": self.bus_load.to_json(),
            "rt": self.rt.as_dict(),
            "hil_process": dict(self.hil_process) if self.hil_process is not None else None,
        }


#: Entry-point group of what the HIL provides to the runtime's benchmark (``realtime``: the
#: real-time HIL process class).
HIL_GROUP = "excavator_rt.hil"


def bench_loop(
    rig: Rig,
    rates_hz: tuple[float, ...] = (500.0, 1000.0),
    seconds: float = 10.0,
    *,
    rt: Any = None,
    sync_timeout_s: float = 0.1,
    hil_rig: str | None = None,
) -> tuple[dict[str, LoopRateBench], dict[str, dict[str, np.ndarray]]]:
    """Loop timing against the real-time HIL in its own process, one run per rate.

    For each rate: start the real-time HIL process (:func:`realtime_hil_process`; 127.0.0.1),
    boot and enable the drives through a :class:`~rt_runtime.canbus.CanMaster` on its bus, run the
    :class:`~rt_runtime.control.FixedRateLoop` for ``seconds`` with a step that holds position
    (RPDO1 of the reported stroke + SYNC, read the TPDOs, heartbeat), with ``rt`` applied.
    Then disable the drives and stop the process.

    Args:
        rig: Rig profile (its CAN ids, bitrate and drive set-up).
        rates_hz: Loop rates (Hz).
        seconds: Run per rate (s).
        rt: :class:`~rt_runtime.control.RtSettings` (default: all of them requested).
        sync_timeout_s: The HIL drives' SYNC/RPDO watchdog (a shared test machine stalls longer
            than a rig PC; the loop's own overruns are what is measured).
        hil_rig: Rig profile name for the HIL process (default ``rig.name``).

    Returns:
        ``(summary, raw)``: the ``loop`` section keyed by the rate as a string (``"500"``), and
        per rate the raw arrays ``lateness_s``, ``jitter_s``, ``exec_s``, ``rtt_s`` for plots.

    Raises:
        CommunicationError, DriveFault: The HIL did not start or the drives did not enable.
    """
    from rt_runtime.control import RtSettings

    hil_process = realtime_hil_process()
    settings = rt if rt is not None else RtSettings()
    summary: dict[str, LoopRateBench] = {}
    raw: dict[str, dict[str, np.ndarray]] = {}
    for rate in rates_hz:
        key = f"{rate:g}"
        summary[key], raw[key] = _bench_rate(
            hil_process, rig, float(rate), seconds, settings, sync_timeout_s, hil_rig or rig.name
        )
    return summary, raw


def realtime_hil_process() -> Any:
    """The real-time HIL process class (``start(rig_name, q0_rad, period_s, max_wall_s,
    sync_timeout_s)``), found through the ``excavator_rt.hil`` entry point ``realtime``: the
    runtime never imports ``hil_sim``.

    Raises:
        ConfigurationError: No package provides it (the HIL is not installed).
    """
    from importlib.metadata import entry_points

    from rt_runtime.errors import ConfigurationError

    found = [ep for ep in entry_points(group=HIL_GROUP) if ep.name == "realtime"]
    if not found:
        raise ConfigurationError(
            f"no real-time HIL installed: entry point {HIL_GROUP} 'realtime' not found "
            "(install the project with its hil_sim package)"
        )
    return found[0].load()


def _bench_rate(
    hil_process: Any,
    rig: Rig,
    rate_hz: float,
    seconds: float,
    settings: Any,
    sync_timeout_s: float,
    hil_rig: str,
) -> tuple[LoopRateBench, dict[str, np.ndarray]]:
    """One rate of :func:`bench_loop`: its entry and raw arrays."""
    import can

    from rt_runtime import actuation
    from rt_runtime.canbus import CanMaster, CycleStatus
    from rt_runtime.canbus.pdo import COB_TPDO1
    from rt_runtime.control import (
        FixedRateLoop,
        LimitGuard,
        LoopConfig,
        MonotonicClock,
        StrokeLimits,
    )
    from rt_runtime.control.controllers import GuardFilter, HoldController
    from rt_runtime.control.hardware import DriveInterface
    from rt_runtime.control.manager import ControllerManager, executor_telemetry

    period = 1.0 / rate_hz
    n_cycles = max(1, round(seconds * rate_hz))
    hil = hil_process.start(
        rig_name=hil_rig,
        q0_rad=np.radians(np.array(_HOLD_POSE_DEG)),
        period_s=period,
        max_wall_s=seconds + 120.0,
        sync_timeout_s=sync_timeout_s,
    )
    clock = MonotonicClock()
    loop = FixedRateLoop(
        clock, LoopConfig(period_s=period, rt=settings), executor_telemetry(n_cycles)
    )
    try:
        # RT settings first: mlockall and gc.collect take longer than the drives' watchdog.
        loop.acquire_rt()
        vcu_status: list[bytes] = []
        vcu_id = COB_TPDO1 + rig.can.vcu_node_id  # VCU_Status (vcu.dbc, 0x180 + node)

        def on_other_frame(msg: can.Message, now_s: float) -> None:
            if msg.arbitration_id == vcu_id:
                vcu_status[:] = [bytes(msg.data)]

        master = CanMaster(hil.master_bus, rig, period_s=period, on_other_frame=on_other_frame)
        master.boot(clock.now, 5.0)
        master.enable(clock.now, 5.0)
        hold_um = master.feedback.position_um.copy()
        # The daemon's cycle between jobs: the hold controller, the guard, the drives in SI; the
        # answers to a SYNC are read a period later (nothing waits; a later one is stale).
        drives = DriveInterface(master, clock, 0.0)
        s0 = drives.measured_stroke_m()
        guard = GuardFilter(LimitGuard(StrokeLimits.from_rig(rig), period))
        guard.guard.reset(s0)
        q0 = actuation.stroke_to_joint(rig, s0, check_limits=False)
        hold = HoldController(s0, q0)
        manager = ControllerManager(drives, guard, loop)
        stats = manager.run(hold, hold.command, s0, q0, max_cycles=n_cycles)
        snap = loop.telemetry.snapshot()
        master.disable()
        # The VCU counts where its status was on the bus (else as the rig says).
        load = master.bus_load(period, vcu=True if vcu_status else None)
        realistic = _realistic_bus_load(master, hold_um, period, vcu_status)
        hil_extra = hil.finish()[3]
    finally:
        loop.release_rt()
        hil.close()
    jitter = stats.period_jitter_s()
    status = snap["cycle_status"]
    wait = snap["wait_s"]
    send = snap["send_s"]
    entry = LoopRateBench(
        period_us=period * 1e6,
        cycles=stats.cycles,
        seconds=seconds,
        lateness_us=_group_us(stats.lateness_s),
        jitter_us=_group_us(np.abs(jitter)),
        jitter_signed_us=Range(
            min=float(np.min(jitter) * 1e6) if jitter.size else None,
            max=float(np.max(jitter) * 1e6) if jitter.size else None,
        ),
        exec_us=_group_us(stats.exec_s),
        # The step's parts: the transport's (sending the frames; waiting for the drives'
        # answers: bus, bridge, the HIL's response) and the runtime's own work (packing and
        # decoding, the controller, the guard, the telemetry).
        send_us=_group_us(send),
        wait_us=_group_us(wait),
        transport_us=_group_us(send + wait),
        own_us=_group_us(stats.exec_s - wait - send),
        overruns=stats.overruns,
        skipped=stats.skipped,
        max_consecutive_overruns=stats.max_consecutive_overruns,
        safe_stop=stats.safe_stop,
        overrun_events=tuple(
            OverrunRecord(e.index, e.lateness_s * 1e6, e.skipped) for e in stats.overrun_events[:10]
        ),
        sync_rtt_us=_group_us(snap["rtt_s"]),
        stale_cycles=int(np.sum(~np.isfinite(snap["rtt_s"]))),
        fault_cycles=int(np.sum(status >= int(CycleStatus.EMCY))),
        cycle_status={
            CycleStatus(v).name: int(np.sum(status == v)) for v in np.unique(status) if v >= 0
        },
        bus_load=BusLoadFigures(nominal=load.nominal, worst=load.worst_case, realistic=realistic),
        rt=stats.rt,
        hil_process=hil_extra.get("hil_process"),
    )
    arrays = {
        "lateness_s": stats.lateness_s,
        "jitter_s": jitter,
        "exec_s": stats.exec_s,
        "rtt_s": snap["rtt_s"],
    }
    return entry, arrays


def _realistic_bus_load(
    master: Any, hold_um: np.ndarray, period_s: float, vcu_status: list[bytes]
) -> float:
    """Bus load of the cyclic frames as sent in the run, with their exact stuff bits.

    Per period: RPDO1 (the held target, zero velocity offset) per drive, SYNC (0x080), TPDO1
    (packed from the last feedback) per drive, the VCU's status (the last one received, in
    ``vcu_status``; the worst-case 8-byte length when none came and the rig has a VCU);
    heartbeats at their period with the worst-case length of a 1-byte frame (0.2 % of the
    frames at 500 Hz).
    """
    from rt_runtime.canbus import RPDO1, TPDO1
    from rt_runtime.canbus.busload import VCU_FRAME_BYTES, frame_bits_exact, frame_bits_worst
    from rt_runtime.canbus.pdo import COB_TPDO1

    cfg = master.config
    fb = master.feedback
    bits = float(frame_bits_exact(0x080, b""))
    if vcu_status:
        bits += frame_bits_exact(COB_TPDO1 + master.rig.can.vcu_node_id, vcu_status[-1])
    elif master.rig.can.vcu:
        bits += frame_bits_worst(VCU_FRAME_BYTES)
    for axis, node in enumerate(cfg.node_ids):
        rpdo = RPDO1.codec.pack(int(hold_um[axis]), 0)
        bits += frame_bits_exact(RPDO1.cob_base + node, rpdo)
        tpdo = TPDO1.codec.pack(int(fb.position_um[axis]), int(fb.velocity_um_s[axis]))
        bits += frame_bits_exact(TPDO1.cob_base + node, tpdo)
    bits += frame_bits_worst(1) * (len(cfg.node_ids) + 1) * period_s / cfg.heartbeat_period_s
    return float(bits / period_s / float(cfg.bitrate))


@dataclass(frozen=True, slots=True)
class PinnSummary:
    """The PINN per dig in the full suite (``pinn`` of ``bench --json``).

    Attributes:
        infer_us: Inference alone (us; p50, p99, p999, max).
        plan_us: Inference + verification (+ repair) (us; p50, p99, p999, max).
        verify_only_plan_us: Inference + verification of the raw answer alone (us), None when
            no raw answer verified.
        samples: Held-out problems.
        refused: Fraction refused.
        executed_feasible: Fraction of the returned plans feasible by the numpy reference.
        gap_mean: Mean objective gap to the teacher (fraction).
    """

    infer_us: Distribution
    plan_us: Distribution
    verify_only_plan_us: Distribution | None
    samples: int
    refused: float
    executed_feasible: float
    gap_mean: float

    def to_json(self) -> dict[str, Any]:
        """The block's keys, as the attributes."""
        return {
            "infer_us": self.infer_us.to_json(),
            "plan_us": self.plan_us.to_json(),
            "verify_only_plan_us": _json(self.verify_only_plan_us),
            "samples": self.samples,
            "refused": self.refused,
            "executed_feasible": self.executed_feasible,
            "gap_mean": self.gap_mean,
        }


@dataclass(frozen=True, slots=True)
class PsoSummary:
    """The PSO teacher per dig on some of the same problems (``pso`` of ``bench --json``).

    Attributes:
        solve_s: Solve time (s; p50, p99).
        problems: Problems solved.
    """

    solve_s: Distribution
    problems: int

    def to_json(self) -> dict[str, Any]:
        """``{"solve_s", "problems"}``."""
        return {"solve_s": self.solve_s.to_json(), "problems": self.problems}


@dataclass(frozen=True, slots=True)
class TrenchSummary:
    """The whole plan of a task in the full suite (``trench`` of ``bench --json``).

    Attributes:
        task: The task (``A``).
        plan_us: Whole-plan time (us; p50, p99).
        digs: Digs of the plan.
        coverage_error: Its coverage error.
    """

    task: str
    plan_us: Distribution
    digs: int
    coverage_error: float

    def to_json(self) -> dict[str, Any]:
        """``{"task", "plan_us", "digs", "coverage_error"}``."""
        return {
            "task": self.task,
            "plan_us": self.plan_us.to_json(),
            "digs": self.digs,
            "coverage_error": self.coverage_error,
        }


@dataclass(frozen=True, slots=True)
class CanBench:
    """The bus in the full suite (``can`` of ``bench --json``).

    Attributes:
        sync_rtt_us: SYNC -> last TPDO1 round trip pooled over the rates (us; p50, p99, p999,
            max), None without an answer.
        bus_load: The first rate's bus load, None without a rate.
        bus_load_rate_hz: That rate (Hz), None likewise.
        bitrate: The bus bitrate (bit/s).
    """

    sync_rtt_us: Distribution | None
    bus_load: BusLoadFigures | None
    bus_load_rate_hz: float | None
    bitrate: int

    def to_json(self) -> dict[str, Any]:
        """``{"sync_rtt_us", "bus_load", "bus_load_rate_hz", "bitrate"}``."""
        return {
            "sync_rtt_us": _json(self.sync_rtt_us),
            "bus_load": self.bus_load.to_json() if self.bus_load is not None else None,
            "bus_load_rate_hz": self.bus_load_rate_hz,
            "bitrate": self.bitrate,
        }


@dataclass(frozen=True, slots=True)
class BenchReport:
    """The report of ``excavator-rt bench`` (README ``bench --json``, DESIGN.md "Reports").

    Attributes:
        rig: Rig profile name.
        sizes: The work each part did.
        pinn: The PINN per dig.
        pso: The PSO teacher per dig.
        trench: The whole plan of task A.
        wall_s: The suite's wall time (s).
        loop: Per rate (key ``"500"``), None when the loop part did not run.
        can: The bus, None likewise.
        plot: The histogram PNG written, None when none was asked for.
    """

    rig: str
    sizes: BenchSizes
    pinn: PinnSummary
    pso: PsoSummary
    trench: TrenchSummary
    wall_s: float
    loop: Mapping[str, LoopRateBench] | None = None
    can: CanBench | None = None
    plot: str | None = None

    @property
    def lateness_goal_met(self) -> bool | None:
        """500 Hz lateness p99 within :data:`LOOP_LATENESS_P99_GOAL_US`; None when not run."""
        at_500 = self.loop.get("500") if self.loop is not None else None
        if at_500 is None or at_500.lateness_us is None:
            return None
        return at_500.lateness_us.p99 <= LOOP_LATENESS_P99_GOAL_US

    @property
    def ratios(self) -> dict[str, float]:
        """PSO over PINN per dig, ours and Yao's, and Yao's figures over ours."""
        pso_p50_s = self.pso.solve_s.p50
        plan_p50_s = self.pinn.plan_us.p50 * 1e-6
        return {
            "pso_over_pinn_plan": pso_p50_s / plan_p50_s,
            "yao_pso_over_yao_pinn": YAO_PSO_SOLVE_S[0] / (YAO_PINN_PLAN_MS[1] * 1e-3),
            "yao_pinn_plan_over_ours": YAO_PINN_PLAN_MS[0] * 1e-3 / plan_p50_s,
            "yao_pso_over_ours": YAO_PSO_SOLVE_S[0] / pso_p50_s,
        }

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object."""
        goals: dict[str, Any] = {"loop_500_lateness_p99_us_max": LOOP_LATENESS_P99_GOAL_US}
        out: dict[str, Any] = {
            "rig": self.rig,
            "sizes": self.sizes.to_json(),
            "pinn": self.pinn.to_json(),
            "pso": self.pso.to_json(),
            "trench": self.trench.to_json(),
            "paper": {
                "yao_pinn_plan_ms": list(YAO_PINN_PLAN_MS),
                "yao_pso_solve_s": list(YAO_PSO_SOLVE_S),
            },
            "ratios": self.ratios,
            "goals": goals,
        }
        if self.loop is not None:
            goals["met"] = {"loop_500_lateness_p99": self.lateness_goal_met}
            out["loop"] = {rate: e.to_json() for rate, e in self.loop.items()}
        if self.can is not None:
            out["can"] = self.can.to_json()
        out["wall_s"] = self.wall_s
        if self.plot is not None:
            out["plot"] = self.plot
        return out


def bench_full(
    rig: Rig,
    *,
    sizes: BenchSizes | None = None,
    rates_hz: tuple[float, ...] = (500.0, 1000.0),
    rt: Any = None,
    model_dir: Any = None,
    hil_rig: str | None = None,
    loop: bool = True,
) -> tuple[BenchReport, dict[str, dict[str, np.ndarray]]]:
    """The whole suite of ``excavator-rt bench``: planning latency, loop timing, CAN.

    Planning: the PINN per dig on the held-out sets (:func:`bench_pinn`: inference alone and
    plan = inference + verification + repair), the PSO teacher on a few of the same problems in
    the same run, the whole trench plan of task A (:func:`bench_plan`, PINN, timed passes).
    Loop and CAN: :func:`bench_loop` at each rate against the real-time HIL. Ratios and Yao's
    figures beside ours.

    Args:
        rig: Rig profile.
        sizes: Work per part (default :class:`BenchSizes`; :meth:`BenchSizes.quick` for tests).
        rates_hz: Loop rates (Hz).
        rt: :class:`~rt_runtime.control.RtSettings` for the loop (default: all requested).
        model_dir: PINN model directory (default: the shipped ``onnx/``).
        hil_rig: Rig profile name for the HIL process (default ``rig.name``).
        loop: Run the loop and CAN part (False: planning only).

    Returns:
        ``(report, raw)``: the report (keys in the README, DESIGN.md "Reports") and the loop's
        raw arrays per rate (for :func:`plot_bench`).
    """
    sz = sizes if sizes is not None else BenchSizes()
    t_start = time.perf_counter()
    pinn = bench_pinn(
        rig,
        model_dir,
        limit=sz.pinn_limit,
        passes=sz.pinn_passes,
        pso_problems=sz.pso_problems,
    )
    trench = bench_plan(rig, ("A",), passes=sz.trench_passes, pso=False, model_dir=model_dir)
    assert trench.tasks is not None and trench.trench is not None  # named tasks were asked for
    task_a = trench.tasks["A"].pinn
    raw: dict[str, dict[str, np.ndarray]] = {}
    loop_summary: dict[str, LoopRateBench] | None = None
    can: CanBench | None = None
    if loop:
        loop_summary, raw = bench_loop(rig, rates_hz, sz.loop_seconds, rt=rt, hil_rig=hil_rig)
        rtt_all = np.concatenate([r["rtt_s"] for r in raw.values()]) if raw else np.zeros(0)
        first = next(iter(loop_summary.values())) if loop_summary else None
        can = CanBench(
            sync_rtt_us=_group_us(rtt_all),
            bus_load=first.bus_load if first is not None else None,
            bus_load_rate_hz=float(next(iter(loop_summary))) if loop_summary else None,
            bitrate=rig.can.bitrate,
        )
    return BenchReport(
        rig=rig.name,
        sizes=sz,
        pinn=PinnSummary(
            infer_us=pinn.infer_us,
            plan_us=pinn.plan_us,
            verify_only_plan_us=pinn.verify_only_plan_us,
            samples=pinn.samples,
            refused=pinn.refused,
            executed_feasible=pinn.executed_feasible,
            gap_mean=pinn.gap_mean,
        ),
        pso=PsoSummary(solve_s=pinn.pso_solve_s, problems=sz.pso_problems * 2),
        trench=TrenchSummary(
            task="A",
            plan_us=trench.trench.plan_us,
            digs=len(task_a.digs),
            coverage_error=task_a.coverage_error,
        ),
        wall_s=time.perf_counter() - t_start,
        loop=loop_summary,
        can=can,
    ), raw


def plot_bench(raw: dict[str, dict[str, np.ndarray]], path: Any) -> Any:
    """Histograms of loop lateness and SYNC -> TPDO round trip per rate (a PNG).

    Args:
        raw: The raw arrays of :func:`bench_full` / :func:`bench_loop`.
        path: Output file.

    Returns:
        The path written.

    Raises:
        ConfigurationError: matplotlib is not installed.
    """
    from pathlib import Path

    from rt_runtime.errors import ConfigurationError

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - the plot extra
        raise ConfigurationError(
            "--plot needs matplotlib: pip install 'excavator-rt[plot]'"
        ) from exc
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for rate, arrays in raw.items():
        for ax, name in zip(axes, ("lateness_s", "rtt_s"), strict=True):
            v = np.asarray(arrays[name], dtype=np.float64)
            v = v[np.isfinite(v)] * 1e6
            if v.size == 0:
                continue
            hi = max(float(np.max(v)), 1.0)
            bins = np.logspace(
                np.log10(max(float(np.min(v[v > 0])) if (v > 0).any() else 0.1, 0.1)),
                np.log10(hi * 1.01),
                60,
            )
            ax.hist(
                np.maximum(v, 0.1), bins=bins, histtype="step", label=f"{rate} Hz", linewidth=1.4
            )
    axes[0].axvline(LOOP_LATENESS_P99_GOAL_US, color="k", linestyle=":", label="goal p99 (500 Hz)")
    axes[0].set(
        xscale="log",
        yscale="log",
        xlabel="lateness (us)",
        ylabel="cycles",
        title="loop lateness (start - deadline)",
    )
    axes[1].set(
        xscale="log",
        yscale="log",
        xlabel="SYNC -> all TPDO1 (us)",
        ylabel="cycles",
        title="CAN round trip (real-time HIL, 127.0.0.1)",
    )
    for ax in axes:
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
