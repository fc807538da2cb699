"""HIL plant of the swing: the upper structure turning about the vertical axis on its motor.

Role: the swing degree of freedom of a rig with swing (``rig.swing`` set), composed beside the
planar :class:`~hil_sim.plant.ArmPlant` by :class:`~hil_sim.sim.HilCore`. Its emulated drive is
the same :class:`~firmware_models.drive.DriveFirmware` as the cylinders', built on the view of
the rig :func:`swing_drive_rig` gives it: the drive's "position" is the swing angle (rad, one
encoder count a microradian), its "velocity" the swing rate (rad/s).

Model, per servo sub-step (``rig.drives.servo_period_s``):

* Inertia about the vertical axis ``J(q) = J_upper + sum_i (m_i r_i^2 + I_i cos^2 phi_i)``:
  ``J_upper`` the upper structure's (``rig.swing.upper_inertia_kgm2``), the sum over the arm
  links with ``r_i`` the horizontal distance of link i's centre of mass from the swing axis
  (``a1`` plus its x in the arm frame), ``I_i`` its inertia about the centre of mass and
  ``phi_i`` its absolute angle (a link's own inertia about a vertical axis shrinks as it turns
  upright). The arm's reach therefore sets the swing's inertia: stretched out it is about twice
  that of the tucked arm on the field excavator. Angular momentum is conserved:
  ``d(J w)/dt = tau``, so ``J w' = tau - J' w`` (pulling the arm in speeds the swing up).
* Hydraulic swing motor (``rig.actuators.hydraulic`` set): a pressure-compensated valve whose
  flow follows the drive's effort (spool opening in [-1, 1]) through the same first-order spool
  lag as the cylinders' valves, ``Q = u D w_nl - K_c dp``; the motor of displacement ``D`` (per
  radian of swing, through the reduction gear) between two lines of volume ``V`` each
  (``rig.swing.motor_line_volume_m3``): ``dp/dt = 2 beta / V (Q - D w)``, torque ``D dp``
  clipped by the port relief valves to the swing's ``torque_max_nm``, minus viscous friction.
  ``K_c`` (the valve's flow-pressure coefficient with the motor's leakage) sets the damping of
  the hydraulic mode (natural frequency ``sqrt(2 beta D^2 / (V J))``, 3-4 Hz here): it is
  chosen for a damping ratio of :data:`HYDRAULIC_DAMPING` at the mean of the tucked and the
  stretched arm's inertia. ``D`` follows from the relief torque and the supply pressure;
  ``w_nl``, the swing rate at full opening without load, is 10 % above the swing's velocity
  limit, like the cylinders' valves. The swing drive's position gain is at most ``zeta w_h``
  at the stretched arm (:data:`POSITION_GAIN_OVER_MODE`; a P loop on a flow source behind a
  spring of damping zeta is stable below ``2 zeta w_h``).
* Electric swing motor (no ``hydraulic``): torque ``u tau_max``, falling linearly to zero over
  the last 20 % of ``w_nl`` while motoring; a holding brake locks the swing at effort exactly 0.0
  (as the cylinders' motors do).
* Range: the swing's joint range, with an end stop of stiffness ``tau_max / 1 mrad`` (a swing
  with a full turn has none in practice: the field excavator's range is +-180 deg).

What it leaves out, stated: the centrifugal and Coriolis loads of the swing on the arm's planar
dynamics (the arm plant runs in its own plane), and the bucket's payload in ``J``.

Parameters that no paper gives (all four listed in :data:`ASSUMED`): the upper structure's
inertia and the motor lines' volume, set by the rig profile (``[swing]`` keys
``upper_inertia_kgm2`` and ``motor_line_volume_l``, marked in its ``[assumed]`` table with their
reasons), and the cross-port leakage and the viscous friction, set here.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from rt_runtime import actuation, dynamics
from rt_runtime.axes import SWING_FOLLOWING_ERROR_WINDOW_RAD
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig
from rt_runtime.rig.model import Drives

__all__ = [
    "ASSUMED",
    "SwingParameters",
    "SwingPlant",
    "swing_drive_rig",
    "velocity_lead2_s2",
    "velocity_lead_s",
]

#: Encoder resolution of the swing drive (rad): one microradian, the bus unit.
SWING_ENCODER_RAD = 1e-6
#: Full-opening swing rate over the velocity limit (the cylinders' valves are sized alike).
NO_LOAD_OVER_LIMIT = 1.1

#: Damping ratio of the swing's hydraulic mode (valve-controlled swing drives: 0.1-0.4).
HYDRAULIC_DAMPING = 0.3
#: The swing drive's position gain over the hydraulic mode's ``zeta w_h`` at the stretched
#: arm: a P loop on a flow source behind a spring of damping zeta is stable below
#: ``2 zeta w_h``; half of that keeps a gain margin of 2 at the least favourable reach.
POSITION_GAIN_OVER_MODE = 1.0

#: Values no source gives, with the reason for each; the two the rig profile sets are marked
#: assumed, with their reasons, in the profile's ``[assumed]`` table.
ASSUMED = {
    "upper_inertia_kgm2": "from the rig profile: swing.upper_inertia_kgm2 (see its [assumed])",
    "line_volume_m3": "from the rig profile: swing.motor_line_volume_l (see its [assumed])",
    "leakage_m3_s_pa": f"valve flow-pressure coefficient and leakage for a damping ratio of "
    f"{HYDRAULIC_DAMPING} (HYDRAULIC_DAMPING)",
    "viscous_nm_s": "gear and bearing friction: 1 % of the relief torque at the velocity limit",
    "position_gain_1_s": "the swing drive's own commissioning: POSITION_GAIN_OVER_MODE",
}


@dataclass(frozen=True, slots=True)
class SwingParameters:
    """The swing plant's constants (SI).

    Attributes:
        upper_inertia_kgm2: Upper structure's inertia about the swing axis, arm excluded
            (``rig.swing.upper_inertia_kgm2``).
        torque_max_nm: Relief (hydraulic) or peak motor (electric) torque.
        no_load_rad_s: Swing rate at full valve opening without load (electric: top speed).
        displacement_m3_rad: Motor displacement per radian of swing (hydraulic).
        line_volume_m3: Oil volume per line (hydraulic; ``rig.swing.motor_line_volume_m3``).
        bulk_modulus_pa: Effective bulk modulus (hydraulic).
        leakage_m3_s_pa: Flow-pressure coefficient ``K_c`` (valve and leakage; hydraulic).
        valve_time_constant_s: Spool lag (hydraulic).
        viscous_nm_s: Viscous friction.
        hydraulic: Hydraulic motor (else electric).
        min_rad, max_rad: Swing range.
    """

    upper_inertia_kgm2: float
    torque_max_nm: float
    no_load_rad_s: float
    displacement_m3_rad: float
    line_volume_m3: float
    bulk_modulus_pa: float
    leakage_m3_s_pa: float
    valve_time_constant_s: float
    viscous_nm_s: float
    hydraulic: bool
    min_rad: float
    max_rad: float

    @classmethod
    def from_rig(cls, rig: Rig) -> SwingParameters:
        """The swing of ``rig`` (its swing joint and plant constants, its actuators' supply and
        valve lag).

        Raises:
            ConfigurationError: The rig has no swing.
        """
        if rig.swing is None:
            raise ConfigurationError(f"rig {rig.name} has no swing joint ([swing] table)")
        swing = rig.swing
        joint = swing.joint
        hyd = rig.actuators.hydraulic
        torque = joint.torque_max_nm
        no_load = NO_LOAD_OVER_LIMIT * joint.velocity_max_rad_s
        supply = hyd.supply_pressure_pa if hyd is not None else 25e6
        beta = hyd.bulk_modulus_pa if hyd is not None else 1.2e9
        upper, volume = swing.upper_inertia_kgm2, swing.motor_line_volume_m3
        d = torque / supply
        j_lo, j_hi = _inertia_range(rig, upper)
        # zeta = K_c / (2 D) sqrt(2 beta J / V)  (Merritt, with V_t = 2 V)
        k_c = 2.0 * HYDRAULIC_DAMPING * d / math.sqrt(2.0 * beta * 0.5 * (j_lo + j_hi) / volume)
        return cls(
            upper_inertia_kgm2=upper,
            torque_max_nm=torque,
            no_load_rad_s=no_load,
            displacement_m3_rad=d,
            line_volume_m3=volume,
            bulk_modulus_pa=beta,
            leakage_m3_s_pa=k_c,
            valve_time_constant_s=hyd.valve_time_constant_s if hyd is not None else 0.015,
            viscous_nm_s=0.01 * torque / joint.velocity_max_rad_s,
            hydraulic=hyd is not None,
            min_rad=joint.min_rad,
            max_rad=joint.max_rad,
        )


    def mode_rad_s(self, inertia_kgm2: float) -> float:
        """Natural frequency of the hydraulic mode at ``inertia_kgm2`` (rad/s)."""
        d = self.displacement_m3_rad
        return math.sqrt(2.0 * self.bulk_modulus_pa * d * d / (self.line_volume_m3 * inertia_kgm2))


def _inertia_range(rig: Rig, upper_kgm2: float) -> tuple[float, float]:
    """Smallest and largest ``J`` over a grid of the arm's joint ranges (kg m^2)."""
    grid = [
        [j.min_rad + (j.max_rad - j.min_rad) * k / 8.0 for k in range(9)] for j in rig.joints
    ]
    probe = _Inertia(rig, upper_kgm2)
    values = [probe(a, b, c) for a in grid[0] for b in grid[1] for c in grid[2]]
    return min(values), max(values)


class _Inertia:
    """``J(q)`` of the module docstring for one rig."""

    __slots__ = ("_com", "_icom", "_l1", "_l2", "_mass", "a1_m", "upper_kgm2")

    def __init__(self, rig: Rig, upper_kgm2: float) -> None:
        assert rig.swing is not None
        self.a1_m = rig.swing.base_offset_m
        self.upper_kgm2 = upper_kgm2
        links = rig.links
        self._l1 = links[0].length_m
        self._l2 = links[1].length_m
        self._mass = tuple(lk.mass_kg for lk in links)
        self._com = tuple(lk.com_m for lk in links)
        self._icom = tuple(lk.inertia_kgm2 for lk in links)

    def __call__(self, t1: float, t2: float, t3: float) -> float:
        phis = (t1, t1 + t2, t1 + t2 + t3)
        x1 = self._l1 * math.cos(phis[0])
        x0 = (0.0, x1, x1 + self._l2 * math.cos(phis[1]))
        j = self.upper_kgm2
        for i, phi in enumerate(phis):
            c, s = math.cos(phi), math.sin(phi)
            along, normal = self._com[i]
            r = self.a1_m + x0[i] + along * c - normal * s
            j += self._mass[i] * r * r + self._icom[i] * c * c
        return j


@dataclass(frozen=True, slots=True)
class _SwingHydraulic:
    """The swing motor as the drive firmware's valve model reads it (``HydraulicLike``): a
    symmetric actuator (no rod) of area ``D`` whose full-opening flow gives ``w_nl``."""

    supply_pressure_pa: float
    piston_area_m2: float
    rod_area_m2: float
    valve_flow_m3_s: float


@dataclass(frozen=True, slots=True)
class _SwingActuators:
    """``ActuatorsLike`` of the swing drive: velocity limit and valve in rad units."""

    velocity_max_m_s: float
    hydraulic: _SwingHydraulic | None


@dataclass(frozen=True, slots=True)
class _SwingDriveRig:
    """``RigLike`` of the swing drive (see :func:`swing_drive_rig`)."""

    drives: Drives
    actuators: _SwingActuators


def swing_drive_rig(rig: Rig) -> _SwingDriveRig:
    """The rig as the swing drive's firmware sees it: the rig's drive settings with positions in
    rad (encoder :data:`SWING_ENCODER_RAD`, following-error window and quick-stop deceleration
    of the swing, as the master configures them at boot), the velocity command limited to the
    no-load swing rate, and for a hydraulic rig a valve whose no-load gain (the firmware's
    :func:`~firmware_models.drive.valve_velocity_gains_m_s`, both ways) is that rate.

    Raises:
        ConfigurationError: The rig has no swing.
    """
    p = SwingParameters.from_rig(rig)
    assert rig.swing is not None
    gain = rig.drives.position_gain_1_s
    if p.hydraulic:
        _, j_hi = _inertia_range(rig, p.upper_inertia_kgm2)
        gain = min(gain, POSITION_GAIN_OVER_MODE * HYDRAULIC_DAMPING * p.mode_rad_s(j_hi))
    drives = dataclasses.replace(
        rig.drives,
        position_gain_1_s=gain,
        encoder_resolution_m=SWING_ENCODER_RAD,
        following_error_window_m=SWING_FOLLOWING_ERROR_WINDOW_RAD,
        quick_stop_deceleration_m_s2=rig.swing.joint.acceleration_max_rad_s2,
        load_compensation_filter_s=0.0,  # the swing motor's pressures are not read
    )
    hydraulic = None
    if p.hydraulic:
        supply = rig.actuators.hydraulic.supply_pressure_pa if rig.actuators.hydraulic else 0.0
        # No rod: a3 = 1, the gain is Q_n sqrt(p_s / 2 / 3.5 MPa) / D; solve for Q_n.
        flow = p.no_load_rad_s * p.displacement_m3_rad / math.sqrt(supply / 2.0 / 3.5e6)
        hydraulic = _SwingHydraulic(supply, p.displacement_m3_rad, 0.0, flow)
    return _SwingDriveRig(drives, _SwingActuators(p.no_load_rad_s, hydraulic))


def velocity_lead_s(rig: Rig) -> tuple[float, ...]:
    """The lag of each axis of the HIL's plant between its drive's velocity offset and its
    motion (s, axis order), as a commissioning engineer would measure it on this rig: the
    cylinders' valve spool lag; for the swing the spool lag plus the low-frequency lag of its
    hydraulic mode, ``2 zeta / w_h`` at the mean of the tucked and stretched arm's inertia. For
    ``ExecutorConfig.velocity_lead_s``. Electric rigs: 0.

    Raises:
        ConfigurationError: The rig has no swing.
    """
    valve, lag, _ = _swing_lags(rig)
    return (valve, valve, valve, valve + lag)


def velocity_lead2_s2(rig: Rig) -> tuple[float, ...]:
    """The second-order term of each axis's lead (s^2, axis order; for
    ``ExecutorConfig.velocity_lead2_s2``): for a hydraulic cylinder ``1 / w_h^2`` of its
    oil-column mode (:func:`cylinder_inverse_mode_s2`; electric: 0), for the swing
    ``1 / w_h^2 + tau_valve 2 zeta / w_h`` (the inverse of its mode behind its valve to second
    order), at the mean inertia as :func:`velocity_lead_s`.

    Raises:
        ConfigurationError: The rig has no swing.
    """
    valve, lag, inv_w2 = _swing_lags(rig)
    return (*cylinder_inverse_mode_s2(rig), inv_w2 + valve * lag)


def cylinder_velocity_lead(rig: Rig) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The arm cylinders' lead terms for ``ExecutorConfig`` on any rig, swing or not:
    ``(velocity_lead_s, velocity_lead2_s2)``, each ``(boom, stick, bucket)``: the valve's time
    constant and :func:`cylinder_inverse_mode_s2` on a hydraulic rig, zeros on an electric one
    (the servo motors' current loop is far faster than the SYNC period)."""
    hyd = rig.actuators.hydraulic
    valve = hyd.valve_time_constant_s if hyd is not None else 0.0
    return (valve, valve, valve), cylinder_inverse_mode_s2(rig)


def cylinder_inverse_mode_s2(rig: Rig) -> tuple[float, float, float]:
    """``1 / w_h^2`` of each arm cylinder's hydraulic mode (s^2; 0 on an electric rig): the oil
    columns' stiffness ``k = beta (A_A^2 / V_A + A_B^2 / V_B)`` (chamber volumes with the
    profile's dead volume at the stroke) against the arm's inertia reflected to the rod,
    ``m = M_ii(q) / (ds_i / dq_i)^2`` (the joint's diagonal of :func:`rt_runtime.dynamics.
    mass_matrix`: the other joints held by their own oil columns), averaged over a 9^3 grid
    of the joint ranges as the swing's inertia is (:func:`velocity_lead_s`). The cylinders'
    own damping is light, so their first-order term ``2 zeta / w_h`` is left out.
    """
    hyd = rig.actuators.hydraulic
    if hyd is None:
        return (0.0, 0.0, 0.0)
    grid = [np.linspace(j.min_rad, j.max_rad, 9) for j in rig.joints]
    q = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, 3)
    mass = dynamics.mass_matrix(rig, q)
    slope = actuation.stroke_jacobian(rig, q)
    stroke = actuation.joint_to_stroke(rig, q)
    piston = hyd.piston_area_m2
    annulus = piston - hyd.rod_area_m2
    out = []
    cyls = rig.cylinders
    full = (cyls.boom.stroke_max_m, cyls.stick.stroke_max_m, cyls.bucket.stroke_max_m)
    for i, stroke_max_m in enumerate(full):
        m = mass[:, i, i] / slope[:, i] ** 2
        v_a = hyd.chamber_volume_m3 + piston * stroke[:, i]
        v_b = hyd.chamber_volume_m3 + annulus * (stroke_max_m - stroke[:, i])
        k = hyd.bulk_modulus_pa * (piston**2 / v_a + annulus**2 / v_b)
        out.append(float(np.mean(m / k)))
    return (out[0], out[1], out[2])


def _swing_lags(rig: Rig) -> tuple[float, float, float]:
    """``(tau_valve, 2 zeta / w_h, 1 / w_h^2)`` of the swing at its mean inertia."""
    p = SwingParameters.from_rig(rig)
    hyd = rig.actuators.hydraulic
    valve = hyd.valve_time_constant_s if hyd is not None else 0.0
    if not p.hydraulic:
        return valve, 0.0, 0.0
    j_lo, j_hi = _inertia_range(rig, p.upper_inertia_kgm2)
    w = p.mode_rad_s(0.5 * (j_lo + j_hi))
    return valve, 2.0 * HYDRAULIC_DAMPING / w, 1.0 / (w * w)


class SwingPlant:
    """The swing degree of freedom (see the module docstring).

    Args:
        rig: A rig with swing.
        theta0_rad: Initial swing angle.
        params: The constants (default :meth:`SwingParameters.from_rig`).

    Attributes:
        theta_rad: Swing angle.
        omega_rad_s: Swing rate.
        dp_pa: Motor pressure difference (hydraulic).
        spool: Valve opening (hydraulic), in [-1, 1].
        torque_nm: Motor torque of the last sub-step.
        inertia_kgm2: ``J`` of the last sub-step.
        energy_j: Mechanical energy the motor put in (non-regenerating).

    Raises:
        ConfigurationError: No swing, or ``theta0_rad`` outside the swing range.
    """

    def __init__(self, rig: Rig, theta0_rad: float, params: SwingParameters | None = None) -> None:
        self.params = p = params if params is not None else SwingParameters.from_rig(rig)
        if not p.min_rad - 1e-9 <= theta0_rad <= p.max_rad + 1e-9:
            raise ConfigurationError(
                f"initial swing angle {math.degrees(theta0_rad):.3f} deg outside "
                f"[{math.degrees(p.min_rad):.1f}, {math.degrees(p.max_rad):.1f}] deg"
            )
        self._inertia = _Inertia(rig, p.upper_inertia_kgm2)
        self.theta_rad = float(theta0_rad)
        self.omega_rad_s = 0.0
        self.dp_pa = 0.0
        self.spool = 0.0
        self.torque_nm = 0.0
        self.inertia_kgm2 = math.nan
        self.energy_j = 0.0
        self._stop_k = p.torque_max_nm / 1e-3
        self._stop_c = 2.0 * math.sqrt(self._stop_k * p.upper_inertia_kgm2)

    def inertia(self, q_arm_rad: tuple[float, float, float]) -> float:
        """``J`` about the swing axis for the arm pose ``(theta1, theta2, theta3)`` (kg m^2)."""
        return self._inertia(*q_arm_rad)

    def step(self, h: float, effort: float, q_arm_rad: tuple[float, float, float]) -> None:
        """Advance one sub-step ``h`` (s) under the drive's ``effort`` in [-1, 1] with the arm at
        ``q_arm_rad`` (its pose at the end of the sub-step). Semi-implicit Euler: the rate
        from the torque at the start, then the angle with the new rate, then the pressures."""
        p = self.params
        j_new = self.inertia(q_arm_rad)
        j_old = self.inertia_kgm2 if self.inertia_kgm2 == self.inertia_kgm2 else j_new
        w = self.omega_rad_s
        u = -1.0 if effort < -1.0 else min(effort, 1.0)
        if p.hydraulic:
            torque = p.displacement_m3_rad * self.dp_pa
        elif effort == 0.0:  # holding brake
            self.omega_rad_s = 0.0
            self.torque_nm = 0.0
            self.inertia_kgm2 = j_new
            return
        else:
            torque = u * p.torque_max_nm
            if torque * w > 0.0:  # motoring: the speed-torque envelope
                frac = (abs(w) / p.no_load_rad_s - 0.8) / 0.2
                torque *= 1.0 - min(max(frac, 0.0), 1.0)
        stop = 0.0
        if self.theta_rad > p.max_rad:
            stop = -self._stop_k * (self.theta_rad - p.max_rad) - self._stop_c * max(w, 0.0)
        elif self.theta_rad < p.min_rad:
            stop = self._stop_k * (p.min_rad - self.theta_rad) - self._stop_c * min(w, 0.0)
        # d(J w)/dt = tau; the viscous term implicit (stable for any h).
        net = torque + stop - (j_new - j_old) / h * w
        w_new = (j_new * w + h * net) / (j_new + h * p.viscous_nm_s)
        self.omega_rad_s = w_new
        self.theta_rad += h * w_new
        self.torque_nm = torque
        self.inertia_kgm2 = j_new
        if p.hydraulic:
            self.spool += (u - self.spool) * (h / (p.valve_time_constant_s + h))
            flow = self.spool * p.displacement_m3_rad * p.no_load_rad_s
            c = 2.0 * p.bulk_modulus_pa / p.line_volume_m3
            # The flow-pressure term implicit: dp' = c (Q - D w - K_c dp).
            dp = (self.dp_pa + h * c * (flow - p.displacement_m3_rad * w_new)) / (
                1.0 + h * c * p.leakage_m3_s_pa
            )
            limit = p.torque_max_nm / p.displacement_m3_rad
            self.dp_pa = -limit if dp < -limit else min(dp, limit)
        self.energy_j += h * max(torque * w_new, 0.0)
