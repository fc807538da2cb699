"""A simulated skilled operator digging one trenching cycle by lever (Zhao et al., Fig. 2, 4).

Role: the source of demonstrations for teach-and-plan. The operator means to dig one cycle of
a trench on a rig with swing: penetrate, drag, curl, lift, swing to the dump point, dump, swing
back (:func:`intended_cycle`, the same path for every demonstration: the ground truth). A human
does not follow that path the way a controller would. Per demonstration (all seeded):

* pace: a speed factor between 0.75 and 1.55 of the nominal pace (+-35 % about 1.15, between
  demonstrations; consecutive seeds walk through the range on the golden-ratio sequence, so 15
  demonstrations cover it evenly), modulated within the cycle by +-12 % (a slow sine of random
  phase);
* pauses: at each phase boundary, with probability 0.5, the operator's intent stops for 0.2 to
  0.6 s (hesitation before penetrating, before swinging, before dumping);
* reaction time: the operator sees the machine with a delay of 0.18 to 0.30 s and corrects what
  he saw then (proportional gain 2.5 1/s on the delayed error), on top of the lever motion he
  plans (the intended path's rate at his pace, without delay: he knows the motion);
* the hand on the lever: a second-order response to the wanted lever position (natural
  frequency 9 rad/s, damping 0.45: about 20 % overshoot) whose rate is limited (a lever takes
  at least 0.25 s from rest to full), so lever moves ramp and overshoot;
* the lever commands a joint velocity, saturating at the joint's velocity limit.

:class:`Operator` is that behaviour as a step function (one call per lever tick with the
measured joint angles, returning the lever command): the HIL's manual mode closes the loop
through its plant with it. :func:`demonstrate` closes it through a kinematic model of the
machine (for tests and the teach benchmark): the commanded velocity through the valve's
first-order lag (80 ms), plus the hydraulic jerks of a real machine (velocity pulses of 5 to 15 %
of the joint's limit lasting 40 to 120 ms, about one every two seconds per joint, seeded:
:meth:`Operator.hydraulic_jerk_rad_s`), saturated at the velocity limit and stopped at the joint
range (the cylinder's end stop); the angles recorded carry sensor noise (Gaussian, 0.05 deg,
:data:`SENSOR_NOISE_RAD`).

Files (:func:`write_csv`): the demonstration as the issue's CSV (``t_s``, ``swing_deg``,
``boom_deg``, ``stick_deg``, ``bucket_deg``, then the lever columns ``lever_<joint>_deg_s``,
which readers ignore as extra columns), and beside it ``<stem>.intended.json``: the intended
path (``t_s``, ``q_deg`` rows swing first, at the nominal pace), the seed and the operator's
parameters.

Units: SI inside (rad, rad/s, s), joints in the rig's order swing first
(:attr:`rt_runtime.rig.Rig.joint_names`); degrees only in the files. Outside the loop.
"""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicHermiteSpline, PchipInterpolator

from rt_runtime import actuation
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig

__all__ = [
    "CYCLE_KEYFRAMES_DEG",
    "CYCLE_PHASES",
    "SENSOR_NOISE_RAD",
    "Demonstration",
    "Operator",
    "OperatorParams",
    "demonstrate",
    "intended_cycle",
    "write_csv",
]

FloatArray = NDArray[np.float64]

#: Joint keyframes of the intended trenching cycle (deg, swing, boom, stick, bucket) and the
#: nominal time to reach each from the one before (s). Chosen on the field excavator (Zhao
#: Table I): the tip enters 0.6 m below the ground 4.9 m out, drags to 1.3 m deep 3.1 m out,
#: curls and lifts to 1 m above the ground, swings 70 deg to the spoil beside the trench, opens
#: the bucket and swings back to the entry pose. Every keyframe is at least 5 deg inside the
#: joint ranges and within the cylinders' travel.
CYCLE_KEYFRAMES_DEG: tuple[tuple[float, float, float, float], ...] = (
    (0.0, 35.0, -75.0, -30.0),
    (0.0, 12.0, -62.0, -40.0),
    (0.0, 2.0, -86.0, -48.0),
    (0.0, -3.0, -106.0, -75.0),
    (0.0, 10.0, -118.0, -115.0),
    (0.0, 32.0, -112.0, -120.0),
    (70.0, 34.0, -100.0, -120.0),
    (70.0, 36.0, -85.0, -40.0),
    (0.0, 35.0, -75.0, -30.0),
)
#: Nominal duration of each leg between keyframes (s) and its name.
CYCLE_PHASES: tuple[tuple[str, float], ...] = (
    ("penetrate", 1.2),
    ("drag", 1.6),
    ("curl", 0.9),
    ("lift", 0.9),
    ("raise", 1.1),
    ("swing to dump", 2.4),
    ("dump", 1.6),
    ("swing back", 2.4),
)
#: Standard deviation of the joint angle sensors' noise (rad): 0.05 deg.
SENSOR_NOISE_RAD = math.radians(0.05)
_GOLDEN = 0.6180339887498949


@dataclass(frozen=True, slots=True)
class OperatorParams:
    """One demonstration's operator (drawn by :meth:`draw` from a seed).

    Attributes:
        speed: Pace over the nominal one (0.75..1.55).
        pace_wobble: Amplitude of the within-cycle pace modulation (fraction).
        pace_period_s: Period of that modulation, s.
        pace_phase_rad: Its phase.
        reaction_s: Delay between what happens and what the operator corrects, s.
        feedback_1_s: Proportional gain on the delayed error, 1/s.
        lever_wn_rad_s: Natural frequency of the hand on the lever, rad/s.
        lever_damping: Damping ratio of the hand (< 1: overshoot).
        lever_ramp_s: Shortest time from rest to full lever, s.
        lead_s: How far ahead on his path the operator moves the lever (he knows the machine
            answers late), s of nominal pace.
        pauses_s: ``(n_phases + 1,)`` pause before each phase and after the last, s (0: none).
    """

    speed: float
    pace_wobble: float
    pace_period_s: float
    pace_phase_rad: float
    reaction_s: float
    feedback_1_s: float
    lever_wn_rad_s: float
    lever_damping: float
    lever_ramp_s: float
    lead_s: float
    pauses_s: tuple[float, ...]

    @classmethod
    def draw(cls, seed: int, *, speed: float | None = None) -> OperatorParams:
        """The operator of demonstration ``seed``; ``speed`` overrides the drawn pace.

        Raises:
            ConfigurationError: ``speed`` not in (0, 3].
        """
        rng = np.random.default_rng([seed, 0x0E7A])
        if speed is None:
            speed = 0.75 + 0.80 * ((seed * _GOLDEN) % 1.0)
        if not (math.isfinite(speed) and 0.0 < speed <= 3.0):
            raise ConfigurationError(
                f"operator speed {speed!r}: allowed (0, 3] of the nominal pace"
            )
        n = len(CYCLE_PHASES) + 1
        pauses = np.where(rng.random(n) < 0.5, rng.uniform(0.2, 0.6, n), 0.0)
        pauses[0] = pauses[-1] = 0.0  # the recording starts and ends with the motion
        return cls(
            speed=float(speed),
            pace_wobble=0.12,
            pace_period_s=float(rng.uniform(4.0, 7.0)),
            pace_phase_rad=float(rng.uniform(0.0, 2.0 * math.pi)),
            reaction_s=float(rng.uniform(0.18, 0.30)),
            feedback_1_s=1.5,
            lever_wn_rad_s=12.0,
            lever_damping=0.5,
            lever_ramp_s=0.25,
            lead_s=0.15,
            pauses_s=tuple(float(p) for p in pauses),
        )


def _joints(rig: Rig) -> tuple[FloatArray, FloatArray, FloatArray]:
    if rig.swing is None:
        raise ConfigurationError(
            f"the operator digs a trenching cycle with swing; rig {rig.name!r} has no swing "
            "joint (use a profile with a [swing] table, e.g. field_excavator)"
        )
    joints = (rig.swing.joint, *rig.joints)
    lo = np.array([j.min_rad for j in joints])
    hi = np.array([j.max_rad for j in joints])
    v = np.array([j.velocity_max_rad_s for j in joints])
    return lo, hi, v


def intended_cycle(rig: Rig, rate_hz: float = 100.0) -> tuple[FloatArray, FloatArray]:
    """The path the operator means to dig, at the nominal pace: ``(t_s (N,), q_rad (N, 4))``.

    A shape-preserving cubic (PCHIP slopes, zero at both ends: the cycle starts and ends at
    rest) through :data:`CYCLE_KEYFRAMES_DEG` at the cumulative :data:`CYCLE_PHASES` times: it
    never overshoots a keyframe, so it stays inside the ranges.

    Raises:
        ConfigurationError: The rig has no swing, or a keyframe is outside its joint ranges
            or the cylinders' travel.
    """
    return _IntendedPath(rig).sampled(rate_hz)


class _IntendedPath:
    """The intended path as a function of the operator's progress time (nominal pace)."""

    def __init__(self, rig: Rig) -> None:
        lo, hi, _ = _joints(rig)
        key = np.radians(np.array(CYCLE_KEYFRAMES_DEG))
        margin = math.radians(5.0) - 1e-12
        bad = (key < lo + margin) | (key > hi - margin)
        if np.any(bad):
            i, j = (int(v) for v in np.argwhere(bad)[0])
            raise ConfigurationError(
                f"operator keyframe {i} puts {rig.joint_names[j]} at "
                f"{math.degrees(key[i, j]):.1f} deg, not 5 deg inside its range "
                f"[{math.degrees(lo[j]):.1f}, {math.degrees(hi[j]):.1f}] deg on {rig.name}"
            )
        actuation.joint_to_stroke(rig, key[:, 1:])
        self.knots_s = np.concatenate(([0.0], np.cumsum([d for _, d in CYCLE_PHASES])))
        slopes = np.asarray(PchipInterpolator(self.knots_s, key, axis=0).derivative()(self.knots_s))
        slopes[0] = slopes[-1] = 0.0  # the cycle starts and ends at rest
        self.spline = CubicHermiteSpline(self.knots_s, key, slopes, axis=0)
        self.rate = self.spline.derivative()
        self.duration_s = float(self.knots_s[-1])

    def at(self, tau_s: float) -> tuple[FloatArray, FloatArray]:
        tau = min(max(tau_s, 0.0), self.duration_s)
        return np.asarray(self.spline(tau)), np.asarray(self.rate(tau))

    def sampled(self, rate_hz: float) -> tuple[FloatArray, FloatArray]:
        n = round(self.duration_s * rate_hz) + 1
        t = np.linspace(0.0, self.duration_s, n)
        return t, np.asarray(self.spline(t))


class Operator:
    """The operator as a step function: measured joint angles in, lever command out.

    Call :meth:`step` every ``1 / rate_hz`` seconds of machine time with the measured angles
    (swing first, rad); it returns the lever command of every joint as the joint velocity it
    asks for (rad/s, saturated at the joint's velocity limit). :attr:`finished` turns True once
    the operator's intent has reached the end of the cycle and ``settle_s`` more has passed.
    Not thread-safe; allocation per step is a few small arrays (not for a hard loop).

    Args:
        rig: A rig with swing.
        seed: Draws :class:`OperatorParams` and the hydraulic jerks.
        rate_hz: Lever tick rate, Hz (10..2000).
        speed: Pace over the nominal one (default: drawn from the seed).
        settle_s: Time after the intent's end until :attr:`finished`.

    Raises:
        ConfigurationError: No swing, a bad rate or speed.
    """

    def __init__(
        self,
        rig: Rig,
        *,
        seed: int,
        rate_hz: float = 100.0,
        speed: float | None = None,
        settle_s: float = 0.6,
    ) -> None:
        if not (math.isfinite(rate_hz) and 10.0 <= rate_hz <= 2000.0):
            raise ConfigurationError(f"operator rate {rate_hz!r} Hz: allowed 10..2000 Hz")
        self.rig = rig
        self.seed = seed
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.params = OperatorParams.draw(seed, speed=speed)
        self.path = _IntendedPath(rig)
        self.q_min_rad, self.q_max_rad, self.velocity_max_rad_s = _joints(rig)
        self.settle_s = settle_s
        self.t_s = 0.0
        self.tau_s = 0.0
        self._pause_left_s = self.params.pauses_s[0]
        self._phase = 0
        self._lever = np.zeros(4)
        self._lever_rate = np.zeros(4)
        delay = max(1, round(self.params.reaction_s * self.rate_hz))
        self._seen: deque[tuple[FloatArray, FloatArray]] = deque(maxlen=delay)
        self._end_s: float | None = None
        self._jerks = self._draw_jerks(seed)

    @property
    def finished(self) -> bool:
        """The cycle is done and the machine has had ``settle_s`` to come to rest."""
        return self._end_s is not None and self.t_s >= self._end_s + self.settle_s

    def _draw_jerks(self, seed: int) -> list[FloatArray]:
        """Per joint rows ``(start_s, length_s, fraction of V with sign)`` over a long horizon."""
        rng = np.random.default_rng([seed, 0x4A52])
        horizon = 4.0 * self.path.duration_s / self.params.speed + 10.0
        out = []
        for _ in range(4):
            n = int(rng.poisson(horizon / 2.0))
            rows = np.column_stack(
                [
                    np.sort(rng.uniform(0.0, horizon, n)),
                    rng.uniform(0.04, 0.12, n),
                    rng.choice([-1.0, 1.0], n) * rng.uniform(0.05, 0.15, n),
                ]
            )
            out.append(rows)
        return out

    def hydraulic_jerk_rad_s(self, t_s: float) -> FloatArray:
        """The machine's hydraulic jerks at machine time ``t_s``: ``(4,)`` velocity pulses,
        rad/s, to add to the commanded joint velocity (seeded; 0 between pulses)."""
        out = np.zeros(4)
        for j, rows in enumerate(self._jerks):
            k = int(np.searchsorted(rows[:, 0], t_s, side="right")) - 1
            if k >= 0 and t_s < rows[k, 0] + rows[k, 1]:
                out[j] = rows[k, 2] * self.velocity_max_rad_s[j]
        return out

    def _pace(self) -> float:
        p = self.params
        wobble = 1.0 + p.pace_wobble * math.sin(
            2.0 * math.pi * self.t_s / p.pace_period_s + p.pace_phase_rad
        )
        return p.speed * wobble

    def intended_now(self) -> FloatArray:
        """Where the operator means the joints to be now ``(4,)`` rad."""
        return self.path.at(self.tau_s)[0]

    def step(self, q_measured_rad: ArrayLike) -> FloatArray:
        """One lever tick: the measured angles ``(4,)`` rad in, lever commands ``(4,)`` rad/s
        out; advances the operator's time by ``1 / rate_hz``."""
        q_meas = np.asarray(q_measured_rad, dtype=np.float64)
        p = self.params
        dt = self.dt_s
        # The operator's intent advances at his pace, except while he pauses.
        pace = 0.0
        if self._pause_left_s > 0.0:
            self._pause_left_s -= dt
        elif self.tau_s < self.path.duration_s:
            pace = self._pace()
            knots = self.path.knots_s
            nxt = min(self.tau_s + pace * dt, self.path.duration_s)
            phase = int(np.searchsorted(knots, nxt, side="right")) - 1
            if phase > self._phase and phase < len(CYCLE_PHASES):
                self._phase = phase
                self._pause_left_s = p.pauses_s[phase]
                nxt = float(knots[phase])
            self.tau_s = nxt
        elif self._end_s is None:
            self._end_s = self.t_s
        ref = self.path.at(self.tau_s)[0]
        rate = self.path.at(self.tau_s + p.lead_s * pace)[1]
        # What he sees is a reaction time old; he corrects the error he saw then.
        self._seen.append((ref, q_meas))
        old_ref, old_q = self._seen[0]
        want = rate * pace + p.feedback_1_s * (old_ref - old_q)
        want = np.clip(want, -self.velocity_max_rad_s, self.velocity_max_rad_s)
        # The hand: second order towards the wanted lever, its rate limited (ramps).
        wn, zeta = p.lever_wn_rad_s, p.lever_damping
        acc = wn * wn * (want - self._lever) - 2.0 * zeta * wn * self._lever_rate
        ramp = self.velocity_max_rad_s / p.lever_ramp_s
        self._lever_rate = np.clip(self._lever_rate + acc * dt, -ramp, ramp)
        self._lever = np.clip(
            self._lever + self._lever_rate * dt, -self.velocity_max_rad_s, self.velocity_max_rad_s
        )
        self.t_s += dt
        return self._lever.copy()


@dataclass(frozen=True, slots=True, eq=False)
class Demonstration:
    """One recorded demonstration and the path the operator meant.

    Attributes:
        t_s: ``(N,)`` sample times from 0, s (``1 / rate_hz`` apart).
        q_rad: ``(N, 4)`` joint angles as measured (sensor noise included), swing first.
        lever: ``(N, 4)`` lever commands as joint velocities, rad/s.
        intended_t_s: ``(M,)`` times of the intended path at the nominal pace, s.
        intended_q_rad: ``(M, 4)`` the intended path (ground truth), swing first.
        seed: The seed of the demonstration.
        params: The operator that dug it.
        q_true_rad: ``(N, 4)`` the true joint angles (without sensor noise).
    """

    t_s: FloatArray
    q_rad: FloatArray
    lever: FloatArray
    intended_t_s: FloatArray
    intended_q_rad: FloatArray
    seed: int
    params: OperatorParams
    q_true_rad: FloatArray

    @property
    def duration_s(self) -> float:
        """Length of the recording, s."""
        return float(self.t_s[-1] - self.t_s[0])


def demonstrate(
    rig: Rig,
    *,
    seed: int,
    rate_hz: float = 100.0,
    speed: float | None = None,
    valve_lag_s: float = 0.08,
    noise_rad: float = SENSOR_NOISE_RAD,
    jerks: bool = True,
) -> Demonstration:
    """One demonstration by :class:`Operator` on a kinematic model of the machine.

    The machine: joint velocity = first-order lag (``valve_lag_s``) of the lever command plus
    the hydraulic jerks, saturated at the velocity limit; angles stop at the joint range. The
    recorded angles add Gaussian sensor noise of ``noise_rad``. Starts at rest on the first
    keyframe; one sample per lever tick.

    Raises:
        ConfigurationError: As :class:`Operator`; a negative noise or lag.
    """
    if not (math.isfinite(noise_rad) and noise_rad >= 0.0):
        raise ConfigurationError(f"sensor noise {noise_rad!r} rad: allowed >= 0")
    if not (math.isfinite(valve_lag_s) and valve_lag_s >= 0.0):
        raise ConfigurationError(f"valve lag {valve_lag_s!r} s: allowed >= 0")
    op = Operator(rig, seed=seed, rate_hz=rate_hz, speed=speed)
    rng = np.random.default_rng([seed, 0x5E45])
    dt = op.dt_s
    alpha = 1.0 if valve_lag_s == 0.0 else 1.0 - math.exp(-dt / valve_lag_s)
    q = op.intended_now().copy()
    qd = np.zeros(4)
    ts, qs, qt, levers = [], [], [], []
    limit = 40.0 * op.path.duration_s / op.params.speed + 60.0
    while not op.finished:
        if op.t_s > limit:
            raise ConfigurationError(f"operator seed {seed} did not finish within {limit:.0f} s")
        meas = q + rng.normal(0.0, noise_rad, 4) if noise_rad > 0.0 else q.copy()
        ts.append(op.t_s)
        qs.append(meas)
        qt.append(q.copy())
        lever = op.step(meas)
        levers.append(lever)
        cmd = lever + (op.hydraulic_jerk_rad_s(op.t_s) if jerks else 0.0)
        qd += alpha * (cmd - qd)
        qd = np.clip(qd, -op.velocity_max_rad_s, op.velocity_max_rad_s)
        q = np.clip(q + qd * dt, op.q_min_rad, op.q_max_rad)
    it, iq = op.path.sampled(rate_hz)
    return Demonstration(
        t_s=np.round(np.asarray(ts), 9),
        q_rad=np.asarray(qs),
        lever=np.asarray(levers),
        intended_t_s=it,
        intended_q_rad=iq,
        seed=seed,
        params=op.params,
        q_true_rad=np.asarray(qt),
    )


def write_csv(
    demo: Demonstration, path: str | Path, joint_names: tuple[str, ...] | None = None
) -> Path:
    """Write ``demo`` as the issue's CSV at ``path`` and its intended path beside it.

    Columns ``t_s``, ``<joint>_deg`` per joint (swing, boom, stick, bucket), then
    ``lever_<joint>_deg_s`` (extra columns a reader ignores); the intended path goes to
    ``<stem>.intended.json`` in the same directory.

    Returns:
        The path of the intended-path file.
    """
    names = joint_names or ("swing", "boom", "stick", "bucket")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ["t_s"] + [f"{n}_deg" for n in names] + [f"lever_{n}_deg_s" for n in names]
    rows = np.column_stack([demo.t_s, np.degrees(demo.q_rad), np.degrees(demo.lever)])
    with path.open("w", encoding="utf-8") as f:
        f.write(",".join(header) + "\n")
        for row in rows:
            f.write(f"{row[0]:.4f}," + ",".join(f"{v:.6f}" for v in row[1:]) + "\n")
    truth = path.with_name(path.stem + ".intended.json")
    truth.write_text(
        json.dumps(
            {
                "seed": demo.seed,
                "joints": list(names),
                "operator": {
                    "speed": demo.params.speed,
                    "reaction_s": demo.params.reaction_s,
                    "pauses_s": list(demo.params.pauses_s),
                },
                "duration_s": demo.duration_s,
                "t_s": demo.intended_t_s.round(6).tolist(),
                "q_deg": np.degrees(demo.intended_q_rad).round(6).tolist(),
            }
        ),
        encoding="utf-8",
    )
    return truth
