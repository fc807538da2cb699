"""The planner process's serving loop (``planner_worker._worker_main``) against a job side that
goes away: it ends by itself, without an exception, whatever it was doing."""

from __future__ import annotations

import multiprocessing
import threading

from rt_runtime.control.planner_worker import PlannerSpec, _worker_main
from rt_runtime.planning.trench import TrenchPlanner, load_task
from rt_runtime.rig import load_rig

RIG = load_rig("scale_model")


def _serve(requests: list[tuple[object, ...]]) -> list[BaseException]:
    """Run the loop on a pipe whose other end sends ``requests`` and closes at once."""
    spec = PlannerSpec.of(TrenchPlanner(RIG).start(load_task("A", RIG)), 0.002)
    ours, theirs = multiprocessing.Pipe()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            _worker_main(theirs, spec)
        except BaseException as exc:  # what would be the process's traceback
            errors.append(exc)

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    for r in requests:
        ours.send(r)
    ours.close()
    worker.join(120.0)
    assert not worker.is_alive(), "the planner loop did not end"
    return errors


def test_a_plan_whose_job_side_is_gone_ends_the_loop_quietly() -> None:
    # The job stopped (or the daemon ended) while its plan was being made: the reply cannot go.
    assert _serve([("init", None), ("plan", None)]) == []


def test_a_closed_pipe_before_any_request_ends_the_loop_quietly() -> None:
    assert _serve([("init", None)]) == []
    assert _serve([]) == []
