"""Quality and speed of the one-shot PSO teacher against the differential-evolution reference.

Draws seeded problems (half downward digs from ``seed``, half backward from ``seed + 1``, as
``excavator-rt bench oneshot`` does), then measures:

* single: each problem solved alone by :func:`rt_runtime.planning.oneshot.solve_pso`, timed;
* batched: all problems in one call, with one process and with ``--workers`` processes, each
  repeated ``--repeats`` times (problems per second, median over the repeats);
* the reference: :func:`rt_runtime.planning.oneshot.solve_de` per problem and DE seed; the best
  feasible objective over the seeds is the reference (``solve_de``'s default settings; more
  seeds make a stronger reference);
* the gap ``(pso - de) / |de|`` per problem; a PSO answer that beats DE counts as within.

It also reports how far a problem's answer alone differs from its answer in the batch:
:func:`solve_pso` makes them the same up to floating-point rounding (see its docstring).

The measurement lives in importable functions (:func:`run_benchmark` returns a
:class:`QualityReport`; :func:`format_report` prints it) for ``excavator-rt bench oneshot``;
``main`` is the command line::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/oneshot_quality.py --workers 2 \\
        --de-cache /tmp/de_cache.json

The DE reference takes about 2 s per problem and seed; ``--de-cache`` keeps it in a JSON file
keyed by rig, problem, DE seed and grid, so that repeated runs only time the PSO. DE runs in
``--de-workers`` processes (its timings are then per process, still one core each).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import multiprocessing
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rt_runtime.planning import oneshot
from rt_runtime.rig import Rig, load_rig

GOAL_WITHIN = 0.95
GOAL_SINGLE_S = 0.3
GOAL_PROBLEMS_PER_S = 20.0


@dataclass(frozen=True, slots=True)
class Reference:
    """DE reference of one problem.

    Attributes:
        objective: Best feasible objective over the DE seeds (least violating if none).
        feasible: Whether any seed found a feasible dig.
        objectives: Objective per DE seed.
        solve_s: Wall time per DE seed (from the cache when cached).
    """

    objective: float
    feasible: bool
    objectives: tuple[float, ...]
    solve_s: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class Row:
    """One problem of the table."""

    index: int
    dig_type: str
    pso_objective: float
    pso_feasible: bool
    de_objective: float
    de_feasible: bool
    gap: float
    single_s: float
    alone_vs_batched: float


@dataclass(frozen=True, slots=True)
class QualityReport:
    """Everything the benchmark measured.

    Attributes:
        rig: Rig name.
        rows: One per problem.
        single_s_p50: Median wall time of a problem solved alone.
        batched_per_s: Problems per second of one batched call per worker count, median over
            the repeats (``{workers: rate}``).
        within_1pct: Fraction of problems with ``gap <= 0.01``, the PSO answers taken from the
            batched run with the last entry of ``workers``.
        gap_p50: Median gap.
        gap_max: Largest gap.
        de_s_p50: Median DE wall time per problem and seed.
        pso_options: Options passed to ``solve_pso``.
        de_seeds: DE seeds of the reference.
    """

    rig: str
    rows: tuple[Row, ...]
    single_s_p50: float
    batched_per_s: dict[int, float]
    within_1pct: float
    gap_p50: float
    gap_max: float
    de_s_p50: float
    pso_options: dict[str, Any]
    de_seeds: tuple[int, ...]


def benchmark_problems(rig: Rig, n_problems: int, seed: int) -> list[oneshot.Problem]:
    """Half downward problems drawn with ``seed``, the rest backward with ``seed + 1``."""
    n_down = n_problems // 2
    problems = oneshot.sample_problems(rig, n_down, oneshot.DigType.DOWNWARD, seed=seed)
    problems += oneshot.sample_problems(
        rig, n_problems - n_down, oneshot.DigType.BACKWARD, seed=seed + 1
    )
    return problems


def _cache_key(rig: Rig, problem: oneshot.Problem, de_seed: int, n_samples: int) -> str:
    return json.dumps(
        [
            rig.name,
            problem.q_start_rad,
            problem.q_end_rad,
            problem.surface_y_m,
            int(problem.dig_type),
            de_seed,
            n_samples,
        ]
    )


def _solve_de(rig: Rig, problem: oneshot.Problem, de_seed: int, n_samples: int) -> list[Any]:
    t0 = time.perf_counter()
    d = oneshot.solve_de(rig, problem, seed=de_seed, n_samples=n_samples)
    return [d.objective, d.feasible, time.perf_counter() - t0]


def de_reference(
    rig: Rig,
    problems: Sequence[oneshot.Problem],
    de_seeds: Sequence[int] = (0,),
    *,
    n_samples: int = oneshot.DEFAULT_SAMPLES,
    workers: int = 1,
    cache: Path | None = None,
) -> list[Reference]:
    """DE reference per problem: the best over ``de_seeds`` of ``solve_de`` (default settings).

    Args:
        rig: The rig.
        problems: The problems.
        de_seeds: DE seeds; more than one makes a stronger reference.
        n_samples: Grid of the evaluation (the default of ``evaluate``).
        workers: Processes solving problems in parallel.
        cache: JSON file of earlier DE results, read and updated; None computes everything.
    """
    known: dict[str, list[Any]] = {}
    if cache is not None and cache.exists():
        known = json.loads(cache.read_text())
    jobs = [
        (i, s)
        for i in range(len(problems))
        for s in de_seeds
        if _cache_key(rig, problems[i], s, n_samples) not in known
    ]
    if jobs:
        context = multiprocessing.get_context(
            "fork" if sys.platform.startswith("linux") else "spawn"
        )
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            futures = [pool.submit(_solve_de, rig, problems[i], s, n_samples) for i, s in jobs]
            for (i, s), f in zip(jobs, futures, strict=True):
                known[_cache_key(rig, problems[i], s, n_samples)] = f.result()
        if cache is not None:
            cache.write_text(json.dumps(known))
    out = []
    for p in problems:
        runs = [known[_cache_key(rig, p, s, n_samples)] for s in de_seeds]
        feasible = [r for r in runs if r[1]]
        best = min(feasible or runs, key=lambda r: r[0])
        out.append(
            Reference(
                objective=float(best[0]),
                feasible=bool(best[1]),
                objectives=tuple(float(r[0]) for r in runs),
                solve_s=tuple(float(r[2]) for r in runs),
            )
        )
    return out


def time_single(
    rig: Rig, problems: Sequence[oneshot.Problem], **pso_options: Any
) -> tuple[list[oneshot.Solution], list[float]]:
    """Each problem solved alone in this process: solutions and wall times (s)."""
    solutions, times = [], []
    for p in problems:
        t0 = time.perf_counter()
        solutions.append(oneshot.solve_pso(rig, [p], **pso_options)[0])
        times.append(time.perf_counter() - t0)
    return solutions, times


def time_batched(
    rig: Rig,
    problems: Sequence[oneshot.Problem],
    *,
    workers: int = 1,
    repeats: int = 3,
    **pso_options: Any,
) -> tuple[list[oneshot.Solution], float]:
    """All problems in one call, ``repeats`` times: last solutions and median problems/s."""
    rates = []
    solutions: list[oneshot.Solution] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        solutions = oneshot.solve_pso(rig, list(problems), workers=workers, **pso_options)
        rates.append(len(problems) / (time.perf_counter() - t0))
    return solutions, float(np.median(rates))


def gap(pso: oneshot.Solution, ref: Reference) -> float:
    """``(pso - de) / |de|``; -inf when only PSO is feasible, +inf when PSO is not."""
    if not pso.feasible:
        return float("inf")
    if not ref.feasible:
        return float("-inf")
    return (pso.objective - ref.objective) / abs(ref.objective)


def run_benchmark(
    rig: Rig,
    problems: Sequence[oneshot.Problem],
    *,
    de_seeds: Sequence[int] = (0,),
    workers: Sequence[int] = (1, 2),
    repeats: int = 3,
    de_workers: int = 1,
    de_cache: Path | None = None,
    **pso_options: Any,
) -> QualityReport:
    """Measure single and batched PSO against the DE reference on ``problems``.

    A warm-up solve runs first, so that imports and first-call costs stay out of the timings.
    """
    oneshot.solve_pso(rig, list(problems[:2]), **pso_options)
    singles, single_s = time_single(rig, problems, **pso_options)
    rates: dict[int, float] = {}
    batched: list[oneshot.Solution] = []
    for w in workers:
        batched, rates[w] = time_batched(rig, problems, workers=w, repeats=repeats, **pso_options)
    refs = de_reference(rig, problems, de_seeds, workers=de_workers, cache=de_cache)
    rows = []
    for i, (s, b, ref, t) in enumerate(zip(singles, batched, refs, single_s, strict=True)):
        rows.append(
            Row(
                index=i,
                dig_type=s.problem.dig_type.name.lower(),
                pso_objective=b.objective,
                pso_feasible=b.feasible,
                de_objective=ref.objective,
                de_feasible=ref.feasible,
                gap=gap(b, ref),
                single_s=t,
                alone_vs_batched=abs(s.objective - b.objective) / abs(b.objective),
            )
        )
    gaps = np.array([r.gap for r in rows])
    return QualityReport(
        rig=rig.name,
        rows=tuple(rows),
        single_s_p50=float(np.median(single_s)),
        batched_per_s=rates,
        within_1pct=float(np.mean(gaps <= 0.01)),
        gap_p50=float(np.median(gaps)),
        gap_max=float(np.max(gaps)),
        de_s_p50=float(np.median([t for r in refs for t in r.solve_s])),
        pso_options=dict(pso_options),
        de_seeds=tuple(de_seeds),
    )


def format_report(report: QualityReport) -> str:
    """The per-problem table and the summary against the goals, as text."""
    lines = [
        f"rig {report.rig}, PSO options {report.pso_options or 'defaults'}, "
        f"DE seeds {list(report.de_seeds)}",
        f"{'#':>3} {'type':<8} {'PSO obj':>9} {'DE obj':>9} {'gap':>8} {'PSO s':>7}  note",
    ]
    for r in report.rows:
        notes = []
        if not r.pso_feasible:
            notes.append("PSO infeasible")
        if not r.de_feasible:
            notes.append("DE infeasible")
        if r.alone_vs_batched > 1e-6:
            notes.append(f"alone differs by {r.alone_vs_batched:.1e}")
        lines.append(
            f"{r.index:>3} {r.dig_type:<8} {r.pso_objective:>9.5f} {r.de_objective:>9.5f} "
            f"{r.gap:>+8.2%} {r.single_s:>7.3f}  {', '.join(notes)}"
        )
    within = report.within_1pct
    single_ok = "met" if report.single_s_p50 <= GOAL_SINGLE_S else "MISSED"
    alone = max(r.alone_vs_batched for r in report.rows)
    lines += [
        "",
        f"single solve, median        {report.single_s_p50:.3f} s   "
        f"(goal <= {GOAL_SINGLE_S} s: {single_ok})",
    ]
    for w, rate in report.batched_per_s.items():
        ok = "met" if rate >= GOAL_PROBLEMS_PER_S else "MISSED"
        lines.append(
            f"batched, {w} process{'es' if w > 1 else '  '}      {rate:6.1f} problems/s "
            f"(goal >= {GOAL_PROBLEMS_PER_S:.0f}/s on 2 cores: {ok})"
        )
    lines += [
        f"within 1 % of DE             {within:.0%}     "
        f"(goal >= {GOAL_WITHIN:.0%}: {'met' if within >= GOAL_WITHIN else 'MISSED'})",
        f"gap p50 {report.gap_p50:+.3%}, max {report.gap_max:+.3%}; alone vs batched "
        f"objective, largest relative difference {alone:.1e}",
        f"DE reference, median         {report.de_s_p50:.2f} s per problem and seed",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: print the table and summary; ``--json`` also writes the report."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rig", default="scale_model")
    ap.add_argument("--problems", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0, help="problem seed (backward: seed + 1)")
    ap.add_argument("--pso-seed", type=int, default=0)
    ap.add_argument("--de-seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--workers", type=int, default=2, help="processes for the batched run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--de-workers", type=int, default=2)
    ap.add_argument("--de-cache", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    rig = load_rig(args.rig)
    problems = benchmark_problems(rig, args.problems, args.seed)
    report = run_benchmark(
        rig,
        problems,
        de_seeds=args.de_seeds,
        workers=sorted({1, args.workers}),
        repeats=args.repeats,
        de_workers=args.de_workers,
        de_cache=args.de_cache,
        seed=args.pso_seed,
    )
    print(format_report(report))
    if args.json is not None:
        args.json.write_text(json.dumps(asdict(report), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
