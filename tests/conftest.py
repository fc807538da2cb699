"""Fixtures shared by several test modules."""

from __future__ import annotations

from typing import Any

import pytest

from rt_runtime.planning.trench import TrenchPlanner, load_task
from rt_runtime.rig import Rig


@pytest.fixture(scope="module")
def pending(rig: Rig) -> tuple[TrenchPlanner, Any, dict[str, Any]]:
    """Task A's planner and the session state with the first dig planned and pending (on the
    module's ``rig`` fixture)."""
    planner = TrenchPlanner(rig)
    task = load_task("A", rig)
    session = planner.start(task)
    session.next_dig()
    return planner, task, session.state()
