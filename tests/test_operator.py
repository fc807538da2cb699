"""The simulated skilled operator (hil_sim.operator): seeded, human, and inside the machine."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil_sim.operator import (
    CYCLE_KEYFRAMES_DEG,
    SENSOR_NOISE_RAD,
    Demonstration,
    Operator,
    OperatorParams,
    demonstrate,
    intended_cycle,
    write_csv,
)
from rt_runtime import actuation
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig, load_rig


@pytest.fixture(scope="module")
def rig() -> Rig:
    return load_rig("field_excavator")


@pytest.fixture(scope="module")
def demos(rig: Rig) -> list[Demonstration]:
    return [demonstrate(rig, seed=s) for s in range(15)]


def test_same_seed_same_demonstration_other_seed_other(rig: Rig) -> None:
    a, b, c = demonstrate(rig, seed=7), demonstrate(rig, seed=7), demonstrate(rig, seed=8)
    np.testing.assert_array_equal(a.q_rad, b.q_rad)
    np.testing.assert_array_equal(a.lever, b.lever)
    assert a.q_rad.shape != c.q_rad.shape or not np.array_equal(a.q_rad, c.q_rad)


def test_pace_varies_by_at_least_30_percent_between_demonstrations(
    demos: list[Demonstration],
) -> None:
    speed = np.array([d.params.speed for d in demos])
    centre = 0.5 * (speed.max() + speed.min())
    assert speed.max() >= 1.3 * centre and speed.min() <= 0.7 * centre, speed
    # The pace shows in the recordings: the slowest operator takes far longer than the fastest.
    dur = np.array([d.duration_s for d in demos])
    assert dur[np.argmin(speed)] > 1.4 * dur[np.argmax(speed)]


def test_human_traits_are_drawn_per_demonstration(demos: list[Demonstration]) -> None:
    reaction = [d.params.reaction_s for d in demos]
    assert 0.18 <= min(reaction) < max(reaction) <= 0.30
    paused = [sum(d.params.pauses_s) for d in demos]
    assert sum(p > 0.0 for p in paused) >= 10  # most demonstrations hesitate somewhere
    assert all(d.params.lever_damping < 1.0 for d in demos)  # an underdamped hand: overshoot


def test_lever_ramps_and_overshoots(rig: Rig) -> None:
    """Two operators of one seed, one kept exactly on his intent, the other put 5 deg of
    bucket short of it from 0.5 s on: the difference of their levers is the hand's answer to a
    step in the wanted lever (gain times the error), which starts a reaction time after the
    step, ramps (its rate limited) and overshoots its final value."""
    on, off = Operator(rig, seed=3, speed=1.0), Operator(rig, seed=3, speed=1.0)
    step = np.radians([0.0, 0.0, 0.0, 5.0])
    diff = []
    for k in range(200):
        a = on.step(on.intended_now())
        b = off.step(off.intended_now() - (step if k >= 50 else 0.0))
        diff.append(b - a)
    d = np.array(diff)[:, 3]
    v = rig.joints[2].velocity_max_rad_s
    assert np.max(np.abs(np.diff(d))) <= v / on.params.lever_ramp_s * on.dt_s + 1e-9
    final = on.params.feedback_1_s * math.radians(5.0)
    assert d[-1] == pytest.approx(final, rel=0.02)
    assert d.max() > 1.08 * final  # overshoot
    first = int(np.argmax(np.abs(d) > 1e-9))
    assert (first - 50) * on.dt_s == pytest.approx(on.params.reaction_s, abs=0.011)


def test_sensor_noise_and_hydraulic_jerks(demos: list[Demonstration], rig: Rig) -> None:
    d = demos[4]
    noise = d.q_rad - d.q_true_rad
    assert np.std(noise) == pytest.approx(SENSOR_NOISE_RAD, rel=0.1)
    op = Operator(rig, seed=d.seed)
    t = np.arange(0.0, d.duration_s, 0.001)
    jerks = np.array([op.hydraulic_jerk_rad_s(x) for x in t])
    active = np.any(jerks != 0.0, axis=1)
    assert 0.02 < active.mean() < 0.5  # pulses now and then, not all the time


def test_demonstrations_stay_inside_the_machine(demos: list[Demonstration], rig: Rig) -> None:
    joints = (rig.swing.joint, *rig.joints) if rig.swing else rig.joints
    lo = np.array([j.min_rad for j in joints])
    hi = np.array([j.max_rad for j in joints])
    v = np.array([j.velocity_max_rad_s for j in joints])
    for d in demos:
        assert np.all(d.q_true_rad >= lo) and np.all(d.q_true_rad <= hi)
        rate = np.abs(np.diff(d.q_true_rad, axis=0)) / np.diff(d.t_s)[:, None]
        assert np.all(rate <= v * (1 + 1e-9))
        actuation.joint_to_stroke(rig, d.q_true_rad[:, 1:])  # within the cylinders' travel
        assert np.allclose(np.diff(d.t_s), 0.01)


def test_the_operator_digs_what_he_means(demos: list[Demonstration], rig: Rig) -> None:
    """Each demonstration starts at the first keyframe, passes near every keyframe (a skilled
    operator) and ends near the last."""
    key = np.radians(np.array(CYCLE_KEYFRAMES_DEG))
    for d in demos:
        gap = np.min(np.abs(d.q_true_rad[:, None, :] - key[None, :, :]).max(axis=2), axis=0)
        assert np.all(gap < math.radians(3.0)), np.degrees(gap)
    t, q = intended_cycle(rig)
    np.testing.assert_allclose(q[0], key[0])
    np.testing.assert_allclose(q[-1], key[-1])
    assert t[0] == 0.0 and np.all(np.diff(t) > 0.0)


def test_write_csv_in_the_issue_format(demos: list[Demonstration], tmp_path: Path) -> None:
    d = demos[0]
    truth = write_csv(d, tmp_path / "demo.csv")
    with (tmp_path / "demo.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0][:5] == ["t_s", "swing_deg", "boom_deg", "stick_deg", "bucket_deg"]
    assert len(rows) == d.t_s.size + 1
    np.testing.assert_allclose(np.array(rows[1:], float)[:, 1:5], np.degrees(d.q_rad), atol=1e-6)
    saved = json.loads(truth.read_text())
    assert saved["seed"] == d.seed and truth.name == "demo.intended.json"
    np.testing.assert_allclose(np.radians(saved["q_deg"]), d.intended_q_rad, atol=1e-7)


def test_bad_operator_input_is_refused(rig: Rig) -> None:
    with pytest.raises(ConfigurationError, match="no swing"):
        demonstrate(load_rig("scale_model"), seed=0)
    with pytest.raises(ConfigurationError, match="rate"):
        Operator(rig, seed=0, rate_hz=1.0)
    with pytest.raises(ConfigurationError, match="speed"):
        OperatorParams.draw(0, speed=-1.0)
    with pytest.raises(ConfigurationError, match="noise"):
        demonstrate(rig, seed=0, noise_rad=float("nan"))
