"""HIL plant: the arm's rigid-body dynamics driven by its cylinders, soil and end stops.

Role: the truth the emulated drives read and act on. Each drive's servo cascade gives an effort
in [-1, 1] per sub-step (the firmware model's contract); :meth:`ArmPlant.step` advances the arm
under those efforts and reports the true cylinder strokes and rates the drives measure.

Model, per sub-step (equations of motion in joint space, forces along the cylinders):

* Rigid body: ``M(q) qdd + C(q, qd) qd + G(q) = tau`` of :mod:`rt_runtime.dynamics` (Yao eq 7).
* Cylinders: stroke ``s_i(q_i)`` and its derivatives from :mod:`rt_runtime.actuation` (Gao eq
  5-13); a cylinder force F_i acts on its joint as ``tau_i = s_i' F_i`` (virtual work).
* Moving actuator mass ``m_r`` (motor and screw inertia reflected to the rod, or piston and
  rod): ``M + J_s^T diag(m_r) J_s`` with ``J_s = diag(s')``, plus its velocity term
  ``m_r s' s'' qd^2``.
* Friction per cylinder: smoothed Coulomb ``F_c tanh(sd / 1 mm/s)`` plus viscous ``c sd``
  (below breakaway a smoothed law creeps, at about (F / F_c) mm/s, instead of sticking).
* End stops at both ends of the cylinder travel: a spring of ``force_max_n / 1 mm`` with a
  critically damped damper, pushing only (contact force never pulls).
* Soil: a tip force ``f`` (from a :class:`~hil_sim.terrain.Terrain`, Yao eq 8, and/or given per
  step) acts through the tip Jacobian of :mod:`rt_runtime.kinematics`: ``tau += J^T f``.
* Electric cylinders (``rig.cylinders.kind == "electric"``): motor force ``effort *
  force_max_n``, falling linearly to zero over the last 20 % of ``velocity_max_m_s`` while
  motoring (the motor's speed-torque envelope); a holding brake locks an axis whose effort is
  exactly 0.0 (the CiA 402 drive engages it while its power stage is off, which the firmware
  model signals by a zero effort; ``brakes=False`` turns it off).
* Hydraulic cylinders (``kind == "hydraulic"``): per cylinder a valve whose spool follows the
  effort (spool command) with a first-order lag; orifice flows ``Q = K x sqrt(dp)`` on both
  metering edges (P->A, B->T for x > 0; P->B, A->T for x < 0), K from the rated flow at 3.5 MPa
  per edge, with a laminar transition below 0.1 MPa (the square root's infinite slope at zero
  drop is not physical and would make the pressure equations infinitely stiff) and a null
  leakage of 1 % of rated flow at full supply (real spools leak; it also sets the null
  pressures at half supply); chamber pressures ``p' = beta / V (Q -+ A sd)`` with the volumes
  changing with stroke; force ``p_A A_A - p_B A_B``; pressures clipped to [0, 1.1 p_s] (cavitation
  and port relief valves).

Imperfections of a real rig (profile ``[hil]``, applied only when ``hil.enabled``; with it off
every path and float is the ideal plant's): on a hydraulic axis the spool command passes a dead
time, a hysteresis (play operator) and the spool's lag with a slew limit, and no metering edge
opens inside the spool overlap (:func:`valve_opening`); on an electric axis the force follows
its command through the drive's current loop (first-order lag), friction falls from breakaway
to Coulomb over a Stribeck speed, and the screw's backlash is a gap the motor crosses without
pushing the rod; :meth:`ArmPlant.sensed_stroke_state` is what the drives' sensors read (motor
side of the gap, a linearity error of the sensor's class, seeded noise). Design notes, H8.

Integration: fixed sub-steps (default the drive's servo period, 250 us; ``step(dt)`` splits dt
into equal sub-steps no longer than that), semi-implicit Euler: the velocity first, with the
forces at the start of the sub-step and the efforts held (zero-order hold, as a drive applies
them), then the position with the new velocity, then the valve and pressures with the new
velocity. Why not RK4: it costs four force evaluations per sub-step for accuracy the held
(zero-order-hold) efforts cannot use, and semi-implicit Euler, symplectic for a constant mass,
keeps the energy error small and without secular drift here: a free 20 s bucket pendulum stays
within 3e-5 J between stop contacts, and a 0.5 s free fall of the whole arm (configuration-
dependent mass, tens of joules exchanged) within 8e-4 of its kinetic energy at 250 us, halving
with the step (``tests/test_plant.py``).

The stiff dissipative terms are taken linearly implicit: the damping matrix ``D = -dF/dv`` of
friction, the speed envelope, the end-stop damper and the soil (whose regularised law is a
damper of up to ~1e6 N*s/m at low speed) enters as ``(M + dt D) dv = dt f``; the pressures
likewise take their orifice slope implicitly. That keeps the scheme stable at 250 us for every
shipped rig, where an explicit step would need ~20 us in soil (2 m / gain at a ~20 kg tip mass).

Speed: everything per sub-step is plain-float arithmetic, an order of magnitude cheaper than the
batched numpy functions of rt_runtime for one state (``excavator-rt bench hil`` times the HIL's
composition; design notes, H2). The closed forms are those of :mod:`rt_runtime.dynamics` and
:mod:`rt_runtime.kinematics` written out for one state, and the stroke maps are cubic Hermite
tables built from :mod:`rt_runtime.actuation` (2049 nodes over each travel, < 0.1 deg apart: stroke
error < 1e-13 m, slope error < 1e-9 relative), evaluated by Horner's rule; ``tests/test_plant.py``
cross-checks all three against the library. Each sub-step evaluates the tables once, at its new
pose, and keeps the result for the next sub-step and the stroke properties.

Power: :attr:`ArmPlant.power_w` is the sum over axes of max(F v, 0) with F the actuator force
(motor force, or p_A A_A - p_B A_B) and v the stroke rate: what drives that do not regenerate
draw, the same reading of Yao's W_E as :func:`rt_runtime.dynamics.energy_j` ("positive"), so the
report's ``energy_Wh`` is comparable with the planner's. :attr:`power_signed_w` is the plain sum
(the change of the arm's energy plus friction and soil losses), for energy balances.

The plant is a mutable workspace, deterministic (no clock, no randomness), and not for the
fixed-rate control loop of the runtime; it raises only for wrong arguments.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil_sim.terrain import Terrain
from rt_runtime import actuation, dynamics, kinematics
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig, RigImperfections

FloatArray = NDArray[np.float64]

#: Speed scale of the smoothed Coulomb friction ``F_c tanh(v / v_c)``.
COULOMB_SMOOTHING_M_S = 1e-3
#: End-stop spring: deflects this much under ``force_max_n``.
STOP_DEFLECTION_M = 1e-3
#: Damping ratio of the end-stop damper on the axis's current effective mass.
STOP_DAMPING_RATIO = 1.0
#: Fraction of ``velocity_max_m_s`` over which an electric motor's force falls to zero.
FIELD_WEAKENING_FRACTION = 0.2
#: Pressure drop per metering edge at which the valve's rated flow is given.
RATED_VALVE_DROP_PA = 3.5e6
#: Below this drop an orifice turns laminar (Q proportional to dp).
ORIFICE_TRANSITION_PA = 1e5
#: Null leakage per edge at full supply drop, as a fraction of the rated flow.
NULL_LEAKAGE_FRACTION = 0.01
#: Port relief valves open at this multiple of the supply pressure.
PORT_RELIEF_FACTOR = 1.1

# Stroke tables: points per axis and how far beyond the cylinder travel they reach.
_TABLE_POINTS = 2049
_TABLE_MARGINS_DEG = (3.0, 2.0, 1.0, 0.5, 0.0)


class TipLoad(Protocol):
    """A tip force law the plant evaluates every sub-step (e.g. :class:`~hil_sim.YaoTipLoad`)."""

    def tip_load(
        self, x_m: float, y_m: float, vx_m_s: float, vy_m_s: float
    ) -> tuple[float, float, float, float, float, float]:
        """``(fx_n, fy_n, d_xx, d_xy, d_yx, d_yy)``: force on the tip and ``D = -dF/dv``."""
        ...


class _StrokeTable:
    """Cubic Hermite table of one cylinder's stroke over its joint angle (plain floats).

    Built from rt_runtime.actuation's stroke and slope at the nodes; between nodes the
    interpolant's own first and second derivatives are returned, so the slope is exactly the
    derivative of the stroke used (virtual work and energy stay consistent). Beyond the table
    the stroke continues linearly.
    """

    __slots__ = ("_coef", "_d", "_h", "_inv_h", "_last", "_q0", "_s")

    def __init__(self, q0: float, h: float, s: list[float], d: list[float]) -> None:
        self._q0 = q0
        self._h = h
        self._inv_h = 1.0 / h
        self._s = s
        self._d = d
        self._last = len(s) - 1
        # Per interval, the Hermite cubic in power form for Horner's rule: 16 flops per call
        # instead of 40 on the basis functions (eval runs 12k times per simulated second). The
        # same polynomial; values differ from the basis form by rounding only (~1e-16).
        # s(t) = s_i + t (m0 + t (c2 + t c3)) with t = (q - q_i) / h, then its first and second
        # q-derivatives with the 1/h factors folded in; numpy only builds the table.
        sa, da = np.asarray(s), np.asarray(d)
        dp = sa[1:] - sa[:-1]
        m0, m1 = da[:-1] * h, da[1:] * h
        c2 = 3.0 * dp - 2.0 * m0 - m1
        c3 = m0 + m1 - 2.0 * dp
        inv_h = self._inv_h
        inv_h2 = inv_h * inv_h
        columns = (
            sa[:-1],
            m0,
            c2,
            c3,
            da[:-1],
            2.0 * c2 * inv_h,
            3.0 * c3 * inv_h,
            2.0 * c2 * inv_h2,
            6.0 * c3 * inv_h2,
        )
        self._coef: list[tuple[float, ...]] = list(zip(*(c.tolist() for c in columns), strict=True))

    def eval(self, q: float) -> tuple[float, float, float]:
        """``(s, ds/dq, d2s/dq2)`` at joint angle ``q``."""
        u = (q - self._q0) * self._inv_h
        if u <= 0.0:
            return self._s[0] + self._d[0] * (q - self._q0), self._d[0], 0.0
        if u >= self._last:
            n = self._last
            return self._s[n] + self._d[n] * (q - self._q0 - n * self._h), self._d[n], 0.0
        i = int(u)
        t = u - i
        c0, c1, c2, c3, d1, d2, d3, e0, e1 = self._coef[i]
        return c0 + t * (c1 + t * (c2 + t * c3)), d1 + t * (d2 + t * d3), e0 + t * e1

    @property
    def q_range(self) -> tuple[float, float]:
        """Joint interval the table covers."""
        return self._q0, self._q0 + self._last * self._h


def _stroke_tables(rig: Rig) -> tuple[_StrokeTable, ...]:
    lo_s, hi_s = actuation.stroke_limits(rig)
    ends = actuation.stroke_to_joint(rig, np.stack([lo_s, hi_s]), check_limits=False)
    mid = 0.5 * (rig.q_min_rad + rig.q_max_rad)
    tables = []
    for axis in range(3):
        a, b = sorted((float(ends[0, axis]), float(ends[1, axis])))
        for margin_deg in _TABLE_MARGINS_DEG:
            m = math.radians(margin_deg)
            q = np.tile(mid, (_TABLE_POINTS, 1))
            q[:, axis] = np.linspace(a - m, b + m, _TABLE_POINTS)
            s = actuation.joint_to_stroke(rig, q, check_limits=False)[:, axis]
            d = actuation.stroke_jacobian(rig, q, check_limits=False)[:, axis]
            if np.isfinite(s).all() and np.isfinite(d).all():
                break
        else:  # pragma: no cover - validate_cylinders guarantees the travel assembles
            raise ConfigurationError(f"cylinder {actuation.AXES[axis]}: travel does not assemble")
        h = (b - a + 2.0 * m) / (_TABLE_POINTS - 1)
        tables.append(_StrokeTable(a - m, h, s.tolist(), d.tolist()))
    return tuple(tables)


def _vec3(x: float, y: float, z: float) -> FloatArray:
    """A new ``(3,)`` float64 array: filling ``np.empty`` costs half of ``np.array`` on a
    tuple."""
    out = np.empty(3)
    out[0] = x
    out[1] = y
    out[2] = z
    return out


def _reg_sqrt(dp: float) -> tuple[float, float]:
    """Signed square root with a laminar transition: ``dp / sqrt(|dp| + p_t)`` and its slope."""
    a = abs(dp) + ORIFICE_TRANSITION_PA
    r = math.sqrt(a)
    return dp / r, (0.5 * abs(dp) + ORIFICE_TRANSITION_PA) / (a * r)


def valve_opening(x: float, overlap: float) -> float:
    """Metering opening of a spool at ``x`` (fraction of full travel) with positive overlap.

    No metering edge opens while ``|x| <= overlap`` (the dead band); beyond it the opening
    grows linearly to 1 at full travel: ``sign(x) (|x| - overlap) / (1 - overlap)``.
    """
    a = abs(x) - overlap
    if a <= 0.0:
        return 0.0
    return math.copysign(a / (1.0 - overlap), x)


def play(y_prev: float, u: float, width: float) -> float:
    """The play (backlash) operator of total ``width``: the output stays put until the input
    has moved half the width past it, then follows it at that distance (a hysteresis loop of
    ``width`` between rising and falling input)."""
    half = 0.5 * width
    if u - y_prev > half:
        return u - half
    if y_prev - u > half:
        return u + half
    return y_prev


def sensor_error_m(
    stroke_m: float, full_scale_m: float, linearity_fs: float, phase: float
) -> float:
    """Linearity error of a stroke sensor: ``linearity_fs * FS * sin(2 pi s / FS + phase)``,
    at most ``linearity_fs`` of full scale over the travel (a smooth calibration error, the
    form a datasheet's linearity class bounds)."""
    return linearity_fs * full_scale_m * math.sin(2.0 * math.pi * stroke_m / full_scale_m + phase)


def _solve3(
    a00: float,
    a01: float,
    a02: float,
    a10: float,
    a11: float,
    a12: float,
    a20: float,
    a21: float,
    a22: float,
    b0: float,
    b1: float,
    b2: float,
) -> tuple[float, float, float]:
    """Solve the 3x3 system ``a x = b`` (``a`` row by row) by Cramer's rule."""
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    inv = 1.0 / (a00 * c00 + a01 * c01 + a02 * c02)
    x0 = (b0 * c00 + a01 * (a12 * b2 - b1 * a22) + a02 * (b1 * a21 - a11 * b2)) * inv
    x1 = (a00 * (b1 * a22 - a12 * b2) + b0 * c01 + a02 * (a10 * b2 - b1 * a20)) * inv
    x2 = (a00 * (a11 * b2 - b1 * a21) + a01 * (b1 * a20 - a10 * b2) + b0 * c02) * inv
    return x0, x1, x2


class ArmPlant:
    """The arm with its three cylinders, advanced in fixed sub-steps (a mutable workspace).

    Args:
        rig: The rig: links, cylinders (kind and geometry), actuators, Yao soil.
        q0_rad: Initial arm joint angles ``(3,)``; must lie inside the cylinder travel.
        soil: A :class:`~hil_sim.terrain.Terrain` (its Yao eq 8 soil on ``rig`` is evaluated at
            every sub-step), any :class:`TipLoad`, or None for a free arm.
        substep_s: Longest sub-step; default ``rig.drives.servo_period_s``.
        qd0_rad_s: Initial joint rates ``(3,)``; default at rest.
        brakes: Model the electric cylinders' holding brakes (engaged on an axis whose effort is
            exactly 0.0). Ignored for hydraulic rigs.

    Raises:
        ValueError: ``q0_rad`` or ``qd0_rad_s`` not shaped ``(3,)``.
        ConfigurationError: Non-finite ``q0_rad`` or ``qd0_rad_s``, a pose outside the cylinder
            travel, a bad ``substep_s``, or a hydraulic rig without ``actuators.hydraulic``.
    """

    def __init__(
        self,
        rig: Rig,
        q0_rad: ArrayLike,
        soil: Terrain | TipLoad | None = None,
        *,
        substep_s: float | None = None,
        qd0_rad_s: ArrayLike | None = None,
        brakes: bool = True,
    ) -> None:
        q0 = np.asarray(q0_rad, dtype=np.float64)
        qd0 = np.zeros(3) if qd0_rad_s is None else np.asarray(qd0_rad_s, dtype=np.float64)
        for name, value in (("q0_rad", q0), ("qd0_rad_s", qd0)):
            if value.shape != (3,):
                raise ValueError(
                    f"{name} must have shape (3,) (boom, stick, bucket); got {value.shape}"
                )
            if not np.isfinite(value).all():
                raise ConfigurationError(f"{name} must be finite; got {value.tolist()}")
        sub = rig.drives.servo_period_s if substep_s is None else float(substep_s)
        if not (math.isfinite(sub) and sub > 0.0):
            raise ConfigurationError(f"substep_s must be finite and > 0; got {substep_s!r}")
        self._rig = rig
        self._substep = sub
        self._hydraulic = rig.cylinders.kind == "hydraulic"
        act = rig.actuators
        self._fmax = act.force_max_n
        self._vmax = act.velocity_max_m_s
        self._vknee = act.velocity_max_m_s * (1.0 - FIELD_WEAKENING_FRACTION)
        self._mr = act.reflected_mass_kg
        self._fc = act.coulomb_friction_n
        self._cv = act.viscous_friction_n_s_m
        self._kstop = act.force_max_n / STOP_DEFLECTION_M
        self._brakes = brakes and not self._hydraulic
        _, hi = actuation.stroke_limits(rig)
        self._smax = [float(v) for v in hi]
        self._tables = _stroke_tables(rig)
        self._chain(rig)

        self._q = [float(v) for v in q0]
        # (s, ds/dq, d2s/dq2) per axis at self._q: the sub-step and the stroke properties read
        # it instead of evaluating the tables again (3 evaluations per sub-step, not 9).
        self._geo = (
            self._tables[0].eval(self._q[0]),
            self._tables[1].eval(self._q[1]),
            self._tables[2].eval(self._q[2]),
        )
        strokes = [g[0] for g in self._geo]
        bad = [
            actuation.AXES[i] for i in range(3) if not -1e-9 <= strokes[i] <= self._smax[i] + 1e-9
        ]
        if bad:
            raise ConfigurationError(
                f"q0_rad {np.degrees(q0).round(3).tolist()} deg puts the {', '.join(bad)} "
                f"cylinder outside its travel (strokes {[round(s, 4) for s in strokes]} m, "
                f"travel 0..{[round(s, 4) for s in self._smax]} m)"
            )

        self._qd = [float(v) for v in qd0]
        self._t = 0.0
        self._force = [0.0, 0.0, 0.0]
        self._power = 0.0
        self._power_signed = 0.0
        self._energy = 0.0
        self._energy_signed = 0.0
        self._soil_energy = 0.0
        self._soil_f = (0.0, 0.0)
        self._locked = [False, False, False]

        self._soil: TipLoad | None = soil.soil_model(rig) if isinstance(soil, Terrain) else soil
        # Hydraulic state; neutral for an electric rig, whose sub-step never reads it.
        self._pa = [0.0, 0.0, 0.0]
        self._pb = [0.0, 0.0, 0.0]
        self._aa = self._ab = 0.0

        if self._hydraulic:
            hyd = act.hydraulic
            if hyd is None:
                raise ConfigurationError(
                    "actuators.hydraulic is required for cylinders.kind = hydraulic"
                )
            self._ps = hyd.supply_pressure_pa
            self._pmax = PORT_RELIEF_FACTOR * hyd.supply_pressure_pa
            self._aa = hyd.piston_area_m2
            self._ab = hyd.annulus_area_m2
            self._beta = hyd.bulk_modulus_pa
            self._v0 = hyd.chamber_volume_m3
            self._kv = hyd.valve_flow_m3_s / math.sqrt(RATED_VALVE_DROP_PA)
            self._cl = NULL_LEAKAGE_FRACTION * hyd.valve_flow_m3_s / hyd.supply_pressure_pa
            self._tau_v = hyd.valve_time_constant_s
            self._spool = [0.0, 0.0, 0.0]
            # Start holding the arm against gravity, the two pressures summing to p_s.
            slope = actuation.stroke_jacobian(rig, q0, check_limits=False)
            hold = dynamics.gravity_torque(rig, q0) / slope
            pa = np.clip((hold + self._ps * self._ab) / (self._aa + self._ab), 0.0, self._ps)
            self._pa = [float(v) for v in pa]
            self._pb = [self._ps - float(v) for v in pa]
            self._force = [self._pa[i] * self._aa - self._pb[i] * self._ab for i in range(3)]
        self._init_imperfections(rig.hil.active() if rig.hil is not None else None)

    def _init_imperfections(self, imp: RigImperfections | None) -> None:
        """State of the profile's ``[hil]`` imperfections (all off when ``imp`` is None)."""
        self._imperfections = imp
        valve = imp.valve if imp is not None and self._hydraulic else None
        electric = imp.electric if imp is not None and not self._hydraulic else None
        sensor = imp.sensor if imp is not None else None
        self._valve_imp = valve
        #: The ideal valves' overlap per cylinder: what each valve drive compensates (0x2100),
        #: so that an ideal plant's valve is the one its drive was commissioned for and the
        #: compensation neither helps nor harms there; the HIL sets it from the drives as the
        #: master configures them (HilCore.on_frame). The profile's valve imperfections, when
        #: they apply, carry the valves' own overlap.
        self.compensated_overlap = (0.0, 0.0, 0.0)
        self._electric_imp = electric
        self._sensor_imp = sensor
        # Valve: the spool command's dead time as a ring of sub-steps, the hysteresis output.
        n_delay = round(valve.delay_s / self._substep) if valve is not None else 0
        self._delay_ring = [[0.0] * n_delay for _ in range(3)] if n_delay else []
        self._delay_at = 0
        self._play = [0.0, 0.0, 0.0]
        # Electric: the force the current loop delivers, the screw's gap and its rate.
        self._f_motor = [0.0, 0.0, 0.0]
        half = 0.5 * electric.backlash_m if electric is not None else 0.0
        self._half_gap = half
        # At rest the screw's load side is in contact: under gravity the motor holds the rod.
        self._gap = [0.0, 0.0, 0.0]
        self._gap_rate = [0.0, 0.0, 0.0]
        if electric is not None and half > 0.0:
            hold = dynamics.gravity_torque(self._rig, self._q)
            slope = [g[1] for g in self._geo]
            self._gap = [math.copysign(half, float(hold[i]) / slope[i]) for i in range(3)]
        # Sensor: a phase of the linearity error per axis and the noise generator (seeded).
        self._rng = random.Random(imp.seed if imp is not None else 0)
        self._sensor_phase = [self._rng.uniform(0.0, 2.0 * math.pi) for _ in range(3)]

    @property
    def imperfections(self) -> RigImperfections | None:
        """The ``[hil]`` imperfections applied, or None (the ideal plant)."""
        return self._imperfections

    def sensed_stroke_state(
        self,
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Strokes and stroke rates as each drive's sensor reads them: the true ones
        (:meth:`stroke_state`) on an ideal plant; with ``[hil]`` imperfections, an electric
        axis's encoder sits on the motor (the rod plus the screw's gap), and a stroke sensor
        adds its linearity error and a white noise draw per reading (seeded).

        The rates are the true ones (a drive differentiates its encoder instead)."""
        strokes, rates = self.stroke_state()
        if self._imperfections is None:
            return strokes, rates
        s = list(strokes)
        if self._electric_imp is not None:
            gap = self._gap
            s = [s[0] + gap[0], s[1] + gap[1], s[2] + gap[2]]
        sensor = self._sensor_imp
        if sensor is not None:
            lin, sigma = sensor.linearity_fs, sensor.noise_m
            phase, fs = self._sensor_phase, self._smax
            gauss = self._rng.gauss
            for i in range(3):
                err = sensor_error_m(s[i], fs[i], lin, phase[i]) if lin > 0.0 else 0.0
                s[i] += err + (gauss(0.0, sigma) if sigma > 0.0 else 0.0)
        return (s[0], s[1], s[2]), rates

    def _chain(self, rig: Rig) -> None:
        # The constants of rt_runtime.dynamics._Chain (absolute-angle form), as plain floats.
        links = rig.links
        beyond = (links[1].mass_kg + links[2].mass_kg, links[2].mass_kg, 0.0)
        self._l = tuple(lk.length_m for lk in links)
        self._h = tuple(
            lk.mass_kg * lk.com_m[0] + m * lk.length_m for lk, m in zip(links, beyond, strict=True)
        )
        self._b = tuple(lk.mass_kg * lk.com_m[1] for lk in links)
        self._d = tuple(
            lk.inertia_kgm2
            + lk.mass_kg * (lk.com_m[0] ** 2 + lk.com_m[1] ** 2)
            + m * lk.length_m**2
            for lk, m in zip(links, beyond, strict=True)
        )
        self._g = rig.gravity_m_s2

    # --- stepping -------------------------------------------------------------------------

    def step(
        self,
        dt_s: float,
        efforts: Sequence[float] | FloatArray,
        tip_force_xy_n: Sequence[float] | FloatArray | None = None,
    ) -> None:
        """Advance the arm by ``dt_s`` with the efforts held.

        Args:
            dt_s: Time to advance, > 0; split into equal sub-steps no longer than ``substep_s``.
            efforts: Per axis (boom, stick, bucket), clipped to [-1, 1]: electric, the motor
                force as a fraction of ``force_max_n`` (positive extends); hydraulic, the spool
                command as a fraction of full opening (positive extends).
            tip_force_xy_n: An extra force ``(fx_n, fy_n)`` on the tip, held over the step
                (explicit; a stiff soil law belongs in ``soil`` instead, which the plant
                integrates implicitly), or None.

        Raises:
            ValueError: ``dt_s`` not finite and > 0, or efforts / force of the wrong length or
                NaN.
        """
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s must be finite and > 0; got {dt_s!r}")
        if len(efforts) != 3:
            raise ValueError(
                f"efforts must have 3 values (boom, stick, bucket); got {len(efforts)}"
            )
        e0, e1, e2 = float(efforts[0]), float(efforts[1]), float(efforts[2])
        if e0 != e0 or e1 != e1 or e2 != e2:
            raise ValueError(f"efforts must not be NaN; got {[e0, e1, e2]}")
        # Clipping by comparisons: the same values as min(max(e, -1), 1), without two calls per
        # axis on the HIL's hot path (one step per servo sub-step).
        u = [
            -1.0 if e0 < -1.0 else 1.0 if e0 > 1.0 else e0,
            -1.0 if e1 < -1.0 else 1.0 if e1 > 1.0 else e1,
            -1.0 if e2 < -1.0 else 1.0 if e2 > 1.0 else e2,
        ]
        fx = fy = 0.0
        if tip_force_xy_n is not None:
            if len(tip_force_xy_n) != 2:
                raise ValueError(f"tip_force_xy_n must be (fx_n, fy_n); got {tip_force_xy_n!r}")
            fx, fy = float(tip_force_xy_n[0]), float(tip_force_xy_n[1])
            if not (math.isfinite(fx) and math.isfinite(fy)):
                raise ValueError(f"tip_force_xy_n must be finite; got {tip_force_xy_n!r}")
        if self._brakes:
            self._locked = [u[0] == 0.0, u[1] == 0.0, u[2] == 0.0]
        if dt_s == self._substep:  # the HIL's case: one servo sub-step per call
            self._substep_once(dt_s, u, fx, fy)
            return
        n = max(1, math.ceil(dt_s / self._substep - 1e-9))
        h = dt_s / n
        for _ in range(n):
            self._substep_once(h, u, fx, fy)

    def servo_substep(self, h: float, u: list[float]) -> None:
        """One sub-step of ``h`` (<= ``substep_s``) with efforts a drive produced: the HIL's hot
        path, :meth:`step` without its argument checks.

        Args:
            h: Sub-step, > 0 and at most ``substep_s`` (not checked).
            u: Efforts per axis, finite and within [-1, 1] (a drive's output; not checked). The
                list is kept until the next sub-step: pass a new one each time.
        """
        if self._brakes:
            self._locked = [u[0] == 0.0, u[1] == 0.0, u[2] == 0.0]
        self._substep_once(h, u, 0.0, 0.0)

    def _substep_once(self, h: float, u: list[float], fx_ext: float, fy_ext: float) -> None:
        # The HIL calls this once per servo sub-step (~600k times in a demo run), so it reads
        # each attribute once into a local, takes the stroke geometry cached at the end of the
        # previous sub-step, and forms the 3x3 system element by element instead of indexing a
        # list. The operations and their order are those of the original loops (same floats);
        # tests/test_plant.py pins a trajectory.
        q0, q1, q2 = self._q
        w0, w1, w2 = self._qd
        l0, l1, l2 = self._l
        hh0, hh1, hh2 = self._h
        bb0, bb1, bb2 = self._b
        dd0, dd1, dd2 = self._d
        g = self._g
        cos = math.cos
        sin = math.sin

        # Trigonometry of the joint and absolute angles (as rt_runtime.dynamics._trig).
        c1, s1 = cos(q0), sin(q0)
        c2, s2 = cos(q1), sin(q1)
        c3, s3 = cos(q2), sin(q2)
        c23, s23 = c2 * c3 - s2 * s3, s2 * c3 + c2 * s3
        cp1, sp1 = c1 * c2 - s1 * s2, s1 * c2 + c1 * s2
        cp2, sp2 = cp1 * c3 - sp1 * s3, sp1 * c3 + cp1 * s3

        # Mass matrix and velocity + gravity terms (rt_runtime.dynamics, eq 7).
        d01 = l0 * (hh1 * c2 - bb1 * s2)
        v01 = l0 * (bb1 * c2 + hh1 * s2)
        d02 = l0 * (hh2 * c23 - bb2 * s23)
        v02 = l0 * (bb2 * c23 + hh2 * s23)
        d12 = l1 * (hh2 * c3 - bb2 * s3)
        v12 = l1 * (bb2 * c3 + hh2 * s3)
        m22 = dd2
        m12 = dd2 + d12
        m02 = m12 + d02
        m11 = dd1 + dd2 + 2.0 * d12
        m01 = m11 + d01 + d02
        m00 = dd0 + dd1 + dd2 + 2.0 * (d01 + d02 + d12)
        a1 = w0 + w1
        a2 = a1 + w2
        aa0, aa1, aa2 = w0 * w0, a1 * a1, a2 * a2
        t0 = -v01 * aa1 - v02 * aa2 + g * (hh0 * c1 - bb0 * s1)
        t1 = v01 * aa0 - v12 * aa2 + g * (hh1 * cp1 - bb1 * sp1)
        t2 = v02 * aa0 + v12 * aa1 + g * (hh2 * cp2 - bb2 * sp2)
        bias2 = t2
        bias1 = t1 + t2
        bias0 = t0 + bias1

        # Tip position, Jacobian rows (rt_runtime.kinematics) and velocity.
        ex2, ey2 = l2 * cp2, l2 * sp2
        ex1, ey1 = l1 * cp1 + ex2, l1 * sp1 + ey2
        x_tip, y_tip = l0 * c1 + ex1, l0 * s1 + ey1
        jx0, jx1, jx2 = -y_tip, -ey1, -ey2
        jy0, jy1, jy2 = x_tip, ex1, ex2
        vx = jx0 * w0 + jx1 * w1 + jx2 * w2
        vy = jy0 * w0 + jy1 * w1 + jy2 * w2

        # Cylinders: forces along the stroke and their damping -dF/dsd, at the stroke geometry
        # cached for the current q (self._geo, refreshed at the end of every sub-step).
        mr, fc, cv = self._mr, self._fc, self._cv
        hydraulic = self._hydraulic
        fmax, vmax, vknee, kstop = self._fmax, self._vmax, self._vknee, self._kstop
        smax = self._smax
        pa, pb, aa, ab = self._pa, self._pb, self._aa, self._ab
        geo = self._geo
        force = self._force
        tanh = math.tanh
        diag_m = (m00, m11, m22)
        qd = (w0, w1, w2)
        tau = [0.0, 0.0, 0.0]
        damp = [0.0, 0.0, 0.0]
        elec = self._electric_imp
        if elec is not None:
            f_motor = self._f_motor
            cur_alpha = 1.0 - math.exp(-h * 2.0 * math.pi * elec.current_bandwidth_hz)
        for i in range(3):
            s, ds, dds = geo[i]
            w = qd[i]
            sd = ds * w
            d = cv
            if hydraulic:
                f_act = pa[i] * aa - pb[i] * ab
            else:
                ui = u[i]
                f_act = ui * fmax
                if elec is not None:
                    # The current loop: the force follows its command with a first-order lag.
                    fm = f_motor[i] + (f_act - f_motor[i]) * cur_alpha
                    f_motor[i] = f_act = fm
                    ui = fm / fmax
                if f_act * sd > 0.0 and abs(sd) > vknee:
                    span = vmax - vknee
                    scale = (vmax - abs(sd)) / span
                    if scale > 0.0:
                        f_act *= scale
                        d += abs(ui) * fmax / span
                    else:
                        f_act = 0.0
                if elec is not None and self._half_gap > 0.0:
                    f_act = self._through_screw(i, f_act, h)
            force[i] = f_act
            tf = tanh(sd / COULOMB_SMOOTHING_M_S)
            if elec is not None:
                # Stribeck: friction falls from breakaway to Coulomb over the Stribeck speed.
                r = sd / elec.stribeck_velocity_m_s
                fci = fc + (elec.breakaway_friction_n - fc) * math.exp(-r * r)
            else:
                fci = fc
            f = f_act - fci * tf - cv * sd
            d += fci * (1.0 - tf * tf) / COULOMB_SMOOTHING_M_S
            over = -s if s < 0.0 else s - smax[i]
            if over > 0.0:
                m_eff = diag_m[i] / (ds * ds) + mr
                c_stop = 2.0 * STOP_DAMPING_RATIO * math.sqrt(kstop * m_eff)
                if s < 0.0:
                    f_stop = kstop * over - c_stop * sd
                    if f_stop > 0.0:
                        f += f_stop
                        d += c_stop
                else:
                    f_stop = -kstop * over - c_stop * sd
                    if f_stop < 0.0:
                        f += f_stop
                        d += c_stop
            tau[i] = ds * f - mr * ds * dds * w * w
            damp[i] = ds * ds * d
        tau0, tau1, tau2 = tau
        (stroke0, slope0, _), (stroke1, slope1, _), (stroke2, slope2, _) = geo

        # Tip force: soil law (implicit damping) plus the given force.
        fx, fy = fx_ext, fy_ext
        dxx = dxy = dyx = dyy = 0.0
        soil = self._soil
        if soil is not None:
            sfx, sfy, dxx, dxy, dyx, dyy = soil.tip_load(x_tip, y_tip, vx, vy)
            fx += sfx
            fy += sfy
            self._soil_f = (sfx, sfy)
        tau0 += jx0 * fx + jy0 * fy
        tau1 += jx1 * fx + jy1 * fy
        tau2 += jx2 * fx + jy2 * fy

        # (M + M_r + h D) dqd = h (tau - bias - C_r); D = diag(s'^2 d) + J^T D_tip J.
        a00 = m00 + (mr * slope0 * slope0 + h * damp[0])
        a11 = m11 + (mr * slope1 * slope1 + h * damp[1])
        a22 = m22 + (mr * slope2 * slope2 + h * damp[2])
        a01 = a10 = m01
        a02 = a20 = m02
        a12 = a21 = m12
        if dxx != 0.0 or dxy != 0.0 or dyx != 0.0 or dyy != 0.0:
            # Element (i, j) adds h (jx_i (dxx jx_j + dxy jy_j) + jy_i (dyx jx_j + dyy jy_j)).
            px0, py0 = dxx * jx0 + dxy * jy0, dyx * jx0 + dyy * jy0
            px1, py1 = dxx * jx1 + dxy * jy1, dyx * jx1 + dyy * jy1
            px2, py2 = dxx * jx2 + dxy * jy2, dyx * jx2 + dyy * jy2
            a00 += h * (jx0 * px0 + jy0 * py0)
            a01 += h * (jx0 * px1 + jy0 * py1)
            a02 += h * (jx0 * px2 + jy0 * py2)
            a10 += h * (jx1 * px0 + jy1 * py0)
            a11 += h * (jx1 * px1 + jy1 * py1)
            a12 += h * (jx1 * px2 + jy1 * py2)
            a20 += h * (jx2 * px0 + jy2 * py0)
            a21 += h * (jx2 * px1 + jy2 * py1)
            a22 += h * (jx2 * px2 + jy2 * py2)
        r0 = h * (tau0 - bias0)
        r1 = h * (tau1 - bias1)
        r2 = h * (tau2 - bias2)
        if self._brakes:
            lock0, lock1, lock2 = self._locked
            if lock0:
                a00, a01, a02, r0 = 1.0, 0.0, 0.0, -w0
            if lock1:
                a10, a11, a12, r1 = 0.0, 1.0, 0.0, -w1
            if lock2:
                a20, a21, a22, r2 = 0.0, 0.0, 1.0, -w2
        dq0, dq1, dq2 = _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, r0, r1, r2)
        w0 += dq0
        w1 += dq1
        w2 += dq2
        self._qd = [w0, w1, w2]
        n0, n1, n2 = q0 + h * w0, q1 + h * w1, q2 + h * w2
        self._q = [n0, n1, n2]
        self._t += h
        tables = self._tables
        self._geo = (tables[0].eval(n0), tables[1].eval(n1), tables[2].eval(n2))

        # Power of the actuators over the sub-step (new stroke rates), soil dissipation.
        sd0, sd1, sd2 = slope0 * w0, slope1 * w1, slope2 * w2
        p0 = force[0] * sd0
        p1 = force[1] * sd1
        p2 = force[2] * sd2
        p_all = 0.0 + p0 + p1 + p2
        p_pos = 0.0
        if p0 > 0.0:
            p_pos += p0
        if p1 > 0.0:
            p_pos += p1
        if p2 > 0.0:
            p_pos += p2
        self._power = p_pos
        self._power_signed = p_all
        self._energy += h * p_pos
        self._energy_signed += h * p_all
        if soil is not None:
            vx_new = jx0 * w0 + jx1 * w1 + jx2 * w2
            vy_new = jy0 * w0 + jy1 * w1 + jy2 * w2
            sfx, sfy = self._soil_f
            self._soil_energy -= h * (sfx * vx_new + sfy * vy_new)

        if hydraulic:
            self._hydraulic_step(h, u, (stroke0, stroke1, stroke2), (sd0, sd1, sd2))

    def _through_screw(self, i: int, f_motor_n: float, h: float) -> float:
        """The force the screw passes to the rod of axis ``i`` over a sub-step of ``h``, and
        the motor's motion across the screw's gap (backlash).

        In contact on the side the motor pushes (gap at +-half the backlash), the whole force
        passes. Otherwise the motor crosses the gap under its own force against its own
        (reflected) inertia, the rod receives none of it, and contact is made (inelastically)
        at the other side: the lost motion of a reversal.
        """
        half = self._half_gap
        g = self._gap[i]
        if (g >= half and f_motor_n > 0.0) or (g <= -half and f_motor_n < 0.0):
            self._gap_rate[i] = 0.0
            return f_motor_n
        mr = self._mr
        if mr > 0.0:
            vg = self._gap_rate[i] + h * f_motor_n / mr
            g += h * vg
        else:
            vg, g = 0.0, math.copysign(half, f_motor_n) if f_motor_n else g
        if g >= half:
            g, vg = half, 0.0
        elif g <= -half:
            g, vg = -half, 0.0
        self._gap[i] = g
        self._gap_rate[i] = vg
        return 0.0

    def _hydraulic_step(
        self,
        h: float,
        u: list[float],
        strokes: tuple[float, float, float],
        sd: tuple[float, float, float],
    ) -> None:
        ps, kv, cl, beta = self._ps, self._kv, self._cl, self._beta
        aa, ab, v0, pmax, smax = self._aa, self._ab, self._v0, self._pmax, self._smax
        pa_all, pb_all, spool, force = self._pa, self._pb, self._spool, self._force
        lag = 1.0 - math.exp(-h / self._tau_v)
        valve = self._valve_imp
        if valve is not None:
            u = self._valve_command(u, valve.hysteresis)
            slew = valve.slew_1_s * h
            overlap = valve.overlap
        ideal = self.compensated_overlap
        for i in range(3):
            x = spool[i]
            if valve is not None:
                x = valve_opening(x, overlap)
            elif ideal[i] > 0.0:
                x = valve_opening(x, ideal[i])
            pa, pb = pa_all[i], pb_all[i]
            if x >= 0.0:
                ra, dra = _reg_sqrt(ps - pa)
                rb, drb = _reg_sqrt(pb)
                qa, dqa = kv * x * ra, -kv * x * dra
                qb, dqb = -kv * x * rb, -kv * x * drb
            else:
                ra, dra = _reg_sqrt(pa)
                rb, drb = _reg_sqrt(ps - pb)
                qa, dqa = kv * x * ra, kv * x * dra
                qb, dqb = -kv * x * rb, kv * x * drb
            qa += cl * (ps - 2.0 * pa)
            qb += cl * (ps - 2.0 * pb)
            dqa -= 2.0 * cl
            dqb -= 2.0 * cl
            va = max(v0 + aa * strokes[i], 0.1 * v0)
            vb = max(v0 + ab * (smax[i] - strokes[i]), 0.1 * v0)
            ga = h * beta / va
            gb = h * beta / vb
            pa += ga * (qa - aa * sd[i]) / (1.0 - ga * dqa)
            pb += gb * (qb + ab * sd[i]) / (1.0 - gb * dqb)
            pa = min(max(pa, 0.0), pmax)
            pb = min(max(pb, 0.0), pmax)
            pa_all[i] = pa
            pb_all[i] = pb
            x = spool[i]
            dx = (u[i] - x) * lag
            if valve is not None and abs(dx) > slew:
                dx = math.copysign(slew, dx)
            spool[i] = x + dx
            force[i] = pa * aa - pb * ab

    def _valve_command(self, u: list[float], hysteresis: float) -> list[float]:
        """The spool commands after the dead time (a ring of sub-steps) and the hysteresis
        (the play operator of :func:`play`)."""
        ring = self._delay_ring
        if ring:
            k = self._delay_at
            delayed = [ring[0][k], ring[1][k], ring[2][k]]
            ring[0][k], ring[1][k], ring[2][k] = u[0], u[1], u[2]
            self._delay_at = (k + 1) % len(ring[0])
            u = delayed
        if hysteresis > 0.0:
            p = self._play
            p[0] = play(p[0], u[0], hysteresis)
            p[1] = play(p[1], u[1], hysteresis)
            p[2] = play(p[2], u[2], hysteresis)
            u = [p[0], p[1], p[2]]
        return u

    # --- state ----------------------------------------------------------------------------

    @property
    def rig(self) -> Rig:
        """The rig simulated."""
        return self._rig

    @property
    def kind(self) -> str:
        """``electric`` or ``hydraulic``."""
        return "hydraulic" if self._hydraulic else "electric"

    @property
    def substep_s(self) -> float:
        """Longest integration sub-step."""
        return self._substep

    @property
    def t_s(self) -> float:
        """Simulated time since construction."""
        return self._t

    @property
    def q_rad(self) -> FloatArray:
        """Joint angles ``(3,)``."""
        return _vec3(*self._q)

    @property
    def qd_rad_s(self) -> FloatArray:
        """Joint rates ``(3,)``."""
        return _vec3(*self._qd)

    @property
    def stroke_m(self) -> FloatArray:
        """True cylinder strokes ``(3,)`` (what the drives' encoders read, before quantisation)."""
        return _vec3(*self.stroke_state()[0])

    @property
    def stroke_rate_m_s(self) -> FloatArray:
        """True stroke rates ``(3,)``."""
        return _vec3(*self.stroke_state()[1])

    def stroke_state(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """True strokes and stroke rates as floats, ``((s0, s1, s2), (sd0, sd1, sd2))``: the
        values of :attr:`stroke_m` and :attr:`stroke_rate_m_s` without building arrays (the HIL
        reads them every servo sub-step)."""
        (s0, d0, _), (s1, d1, _), (s2, d2, _) = self._geo
        qd = self._qd
        return (s0, s1, s2), (d0 * qd[0], d1 * qd[1], d2 * qd[2])

    @property
    def tip_xy_m(self) -> FloatArray:
        """Bucket tip position ``(2,)`` in the arm frame."""
        return kinematics.forward(self._rig, self._q)[:2]

    @property
    def tip_velocity_xy_m_s(self) -> FloatArray:
        """Bucket tip velocity ``(2,)``."""
        return kinematics.tip_velocity(self._rig, self._q, self._qd)[:2]

    @property
    def cylinder_force_n(self) -> FloatArray:
        """Actuator force along each cylinder ``(3,)``, positive extending, in the last sub-step:
        the motor force (electric) or ``p_A A_A - p_B A_B`` (hydraulic). Friction and end stops
        are not included."""
        return _vec3(*self._force)

    @property
    def cylinder_forces_n(self) -> tuple[float, float, float]:
        """:attr:`cylinder_force_n` as a tuple of floats (what a valve drive's chamber-pressure
        transducers read, for the servo loop without an array per sub-step)."""
        f = self._force
        return (f[0], f[1], f[2])

    @property
    def soil_force_xy_n(self) -> FloatArray:
        """The soil model's force on the tip in the last sub-step ``(2,)`` (zero without soil)."""
        return np.array(self._soil_f)

    @property
    def power_w(self) -> float:
        """Sum over axes of max(F v, 0) in the last sub-step: drawn by non-regenerating drives."""
        return self._power

    @property
    def power_signed_w(self) -> float:
        """Sum over axes of F v in the last sub-step."""
        return self._power_signed

    @property
    def energy_j(self) -> float:
        """Integral of :attr:`power_w` (Yao's W_E reading; use this one in reports)."""
        return self._energy

    @property
    def energy_signed_j(self) -> float:
        """Integral of :attr:`power_signed_w` (for energy balances)."""
        return self._energy_signed

    @property
    def soil_energy_j(self) -> float:
        """Work the arm did on the soil model (>= 0 up to rounding)."""
        return self._soil_energy

    @property
    def brakes_engaged(self) -> tuple[bool, bool, bool]:
        """Which holding brakes held their axis in the last step (always False if unmodelled)."""
        return (
            (self._locked[0], self._locked[1], self._locked[2])
            if self._brakes
            else (
                False,
                False,
                False,
            )
        )

    @property
    def spool(self) -> FloatArray | None:
        """Valve spool positions ``(3,)`` as fractions of full opening (hydraulic), else None."""
        return np.array(self._spool) if self._hydraulic else None

    @property
    def pressures_pa(self) -> FloatArray | None:
        """Chamber pressures ``(3, 2)``: (p_A, p_B) per cylinder (hydraulic), else None."""
        if not self._hydraulic:
            return None
        return np.array([self._pa, self._pb]).T.copy()

    def mechanical_energy_j(self) -> float:
        """Kinetic (links and actuator masses) plus potential energy, from rt_runtime.dynamics."""
        rig = self._rig
        ke = float(dynamics.kinetic_energy(rig, self._q, self._qd))
        pe = float(dynamics.potential_energy(rig, self._q))
        sd = self.stroke_rate_m_s
        return ke + pe + 0.5 * self._mr * float(sd @ sd)
