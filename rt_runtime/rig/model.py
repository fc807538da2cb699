"""Frozen dataclasses describing a rig: geometry, limits, masses, bucket, soil, planning, CAN,
drives, actuators and the trench task domain.

A :class:`Rig` is built only by :func:`rt_runtime.rig.load_rig`, which validates every field.
Everything is SI (m, rad, s, kg, N, N*m, W, J, m^3); the profile's edge units (deg, L, Wh,
N/cm^2) are converted by the loader.

Frames: the arm frame has its origin at the boom foot pin, x forward (away from the cab), y up.
Joint angles are counter-clockwise positive: theta1 boom from +x, theta2 stick relative to boom,
theta3 bucket relative to stick; the tip attitude is zeta = theta1 + theta2 + theta3. Link frame
i has its origin at joint i and its x axis along the link towards the next joint (for the bucket:
towards the tip), so centres of mass are given as (along, normal) in that frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from rt_runtime.rig.cylinders import Cylinders
from rt_runtime.rig.imperfections import RigImperfections

ARM_JOINTS: tuple[str, str, str] = ("boom", "stick", "bucket")
#: Reach of the scale model (Yao Table 1: l1 + l2 + l3, m): the trench planner scales its
#: figures, and the loader the default task domain, by a rig's l1 + l2 + l3 against it.
SCALE_MODEL_REACH_M = 1.31
#: Longest trench task on the scale model (m) where a profile gives no
#: ``trench.length_max_m``; other rigs scale it by reach (:data:`SCALE_MODEL_REACH_M`).
SCALE_MODEL_TRENCH_LENGTH_MAX_M = 20.0
#: The upper structure's inertia about the swing axis (kg m^2) where ``[swing]`` gives no
#: ``upper_inertia_kgm2``: the field excavator's (a 6-t class machine, assumed).
DEFAULT_SWING_UPPER_INERTIA_KGM2 = 4600.0
#: Oil volume of each of the swing motor's two lines (m^3) where ``[swing]`` gives no
#: ``motor_line_volume_l``: the field excavator's 2 L (assumed).
DEFAULT_SWING_MOTOR_LINE_VOLUME_M3 = 2e-3


@dataclass(frozen=True, slots=True)
class Joint:
    """Limits of one revolute joint.

    Attributes:
        name: ``boom``, ``stick``, ``bucket`` or ``swing``.
        min_rad: Lower angle limit.
        max_rad: Upper angle limit.
        velocity_max_rad_s: Largest allowed |angular velocity|.
        acceleration_max_rad_s2: Largest allowed |angular acceleration|.
        jerk_max_rad_s3: Largest allowed |angular jerk| (used by the limit guard).
        torque_max_nm: Largest allowed |joint torque|.
    """

    name: str
    min_rad: float
    max_rad: float
    velocity_max_rad_s: float
    acceleration_max_rad_s2: float
    jerk_max_rad_s3: float
    torque_max_nm: float


@dataclass(frozen=True, slots=True)
class Link:
    """Geometry and mass of one arm link (planar).

    Attributes:
        name: Joint name the link hangs on.
        length_m: Joint-to-next-joint distance (bucket: pivot-to-tip).
        mass_kg: Link mass.
        com_m: Centre of mass (along, normal) in the link frame.
        inertia_kgm2: Moment of inertia about the centre of mass, axis normal to the arm plane.
    """

    name: str
    length_m: float
    mass_kg: float
    com_m: tuple[float, float]
    inertia_kgm2: float


@dataclass(frozen=True, slots=True)
class Swing:
    """Swing joint, the boom foot's offsets from the swing axis (Zhao Table I) and the constants
    of the swing's dynamics (:data:`SWING_PLANT_KEYS`).

    Attributes:
        joint: Limits of the swing joint theta0 (about the vertical axis).
        base_offset_m: a1, horizontal distance from the swing axis to the boom foot pin.
        base_height_m: d1, height of the boom foot pin above the swing frame origin.
        upper_inertia_kgm2: Inertia of the upper structure (cab, engine, counterweight) about
            the swing axis, arm excluded; > 0. Not part of :attr:`Rig.planning_fingerprint`.
        motor_line_volume_m3: Oil volume of each of the hydraulic swing motor's two lines
            (motor, line and valve section); > 0, set only on a hydraulic rig (the default,
            unused, on an electric one). Not part of :attr:`Rig.planning_fingerprint`.
    """

    joint: Joint
    base_offset_m: float
    base_height_m: float
    upper_inertia_kgm2: float = DEFAULT_SWING_UPPER_INERTIA_KGM2
    motor_line_volume_m3: float = DEFAULT_SWING_MOTOR_LINE_VOLUME_M3


#: The fields of :class:`Swing` that describe the swing's dynamics, read by the HIL's swing plant
#: and what is tuned against it; no plan depends on them, so :attr:`Rig.planning_fingerprint`
#: leaves them out.
SWING_PLANT_KEYS: tuple[str, ...] = ("upper_inertia_kgm2", "motor_line_volume_m3")


@dataclass(frozen=True, slots=True)
class Bucket:
    """Bucket dimensions.

    Attributes:
        width_m: Cutting width b.
        capacity_m3: Struck (heaped-free) capacity.
        profile_m: Bucket outline for the Yang/Pan soil model as points (along, normal) in the
            bucket link frame shifted to the tip: the tip is (0, 0), the first segment is the
            separation (bottom) plane, the second the back plane. Shape (n_points, 2).
    """

    width_m: float
    capacity_m3: float
    profile_m: tuple[tuple[float, float], ...]


@dataclass(frozen=True, slots=True)
class YaoSoil:
    """Digging resistance of Yao eq 8.

    Attributes:
        k0_n_m2: Specific digging resistance K0.
        mu: Ratio of normal to tangential resistance.
    """

    k0_n_m2: float
    mu: float


@dataclass(frozen=True, slots=True)
class FluidSoil:
    """Soil of the Yang/Pan fluid model (their Table 2).

    Attributes:
        name: ``soft``, ``hard`` or a user name.
        density_kg_m3: Soil density rho.
        kp: Scale of the hydrostatic pressure term.
        kv: Scale of the velocity term (N*s/m^3).
        ks: Friction coefficient.
    """

    name: str
    density_kg_m3: float
    kp: float
    kv: float
    ks: float


@dataclass(frozen=True, slots=True)
class Soil:
    """Soil models available for this rig."""

    yao: YaoSoil
    fluid: tuple[FluidSoil, ...]

    def fluid_named(self, name: str) -> FluidSoil:
        """The fluid-model soil called ``name``.

        Raises:
            KeyError: No such soil; the message lists the known ones.
        """
        for s in self.fluid:
            if s.name == name:
                return s
        raise KeyError(f"no soil {name!r}; known: {', '.join(s.name for s in self.fluid)}")


@dataclass(frozen=True, slots=True)
class Planning:
    """Thresholds and weights of the one-shot optimisation (Yao Table 2, eq 11-12).

    Attributes:
        t_min_s, t_max_s: Digging time range.
        volume_min_m3, volume_max_m3: Excavated volume range V_p.
        energy_min_j, energy_max_j: Energy thresholds for normalisation.
        power_max_w: Largest allowed driving power.
        weights: lambda1..3 for time, energy and unfilled volume.
        theta_p_downward_rad: Initial digging angle range of downward digs.
        theta_p_backward_rad: Initial digging angle range of backward digs.
    """

    t_min_s: float
    t_max_s: float
    volume_min_m3: float
    volume_max_m3: float
    energy_min_j: float
    energy_max_j: float
    power_max_w: float
    weights: tuple[float, float, float]
    theta_p_downward_rad: tuple[float, float]
    theta_p_backward_rad: tuple[float, float]


@dataclass(frozen=True, slots=True)
class SpoilZone:
    """Where the bucket may dump between digs (profile ``[trench.spoil]``): beside the trench on
    the machine's side, in the arm frame of the machine where it stands.

    The trench planner dumps each cycle at the point of this zone, and with the attitude, that
    makes the cycle shortest, among those nearer the machine by :attr:`edge_gap_m` than the near
    edge of the section being dug and clear of the material.

    Attributes:
        x_m: ``(min, max)`` x of the bucket tip, arm frame, m.
        height_m: ``(min, max)`` height of the tip above the ground, m.
        attitude_rad: ``(min, max)`` bucket attitude zeta = theta1 + theta2 + theta3 at which
            the bucket empties, rad.
        edge_gap_m: Least distance (m) of the tip from the near edge of the section being dug,
            towards the machine.
    """

    x_m: tuple[float, float]
    height_m: tuple[float, float]
    attitude_rad: tuple[float, float]
    edge_gap_m: float


#: The scale model's spoil zone (profile ``scale_model``, ``[trench.spoil]``) where a profile
#: gives none; other rigs scale its lengths by reach (:data:`SCALE_MODEL_REACH_M`) and keep its
#: attitudes.
SCALE_MODEL_SPOIL = SpoilZone(
    x_m=(0.25, 0.45),
    height_m=(0.25, 0.40),
    attitude_rad=(math.radians(-100.0), math.radians(-60.0)),
    edge_gap_m=0.05,
)


@dataclass(frozen=True, slots=True)
class TrenchDomain:
    """The trench tasks a rig accepts (profile ``[trench]``), beyond what the planner's own
    figures bound (depth, wall slopes and where the far edge may lie; see
    :func:`rt_runtime.planning.trench.task_limits`), and where their spoil goes.

    Attributes:
        length_max_m: Longest top length L of a task (the machine travels back along it).
        spoil: Where the bucket dumps between digs.
    """

    length_max_m: float
    spoil: SpoilZone


@dataclass(frozen=True, slots=True)
class Can:
    """CAN bus settings.

    Attributes:
        bitrate: Bus bitrate in bit/s.
        node_ids: Drive node id per joint name.
        vcu_node_id: Node id of the vehicle control unit (travel and swing motors).
        vcu: Whether the VCU is on the bus (its status frame goes out on every SYNC); the id
            stays reserved without it.
    """

    bitrate: int
    node_ids: tuple[tuple[str, int], ...]
    vcu_node_id: int
    vcu: bool = True

    def node_id(self, joint: str) -> int:
        """Node id of ``joint``'s drive."""
        return dict(self.node_ids)[joint]


@dataclass(frozen=True, slots=True)
class Drives:
    """Servo drive settings shared by every axis drive of the rig (profile ``[drives]``).

    The firmware model and the master configure the drives from these; the CAN units
    (micrometres, milliseconds) are applied at the protocol edge.

    Attributes:
        encoder_resolution_m: Position resolution at the rod (motor encoder or stroke sensor).
        position_gain_1_s: Kp of the position loop: velocity demand per metre of position error.
        velocity_gain_s_m: Gain of the velocity loop: effort (in [-1, 1]) per m/s of velocity
            error (electric drives; the hydraulic cascade has no velocity loop).
        velocity_integral_gain_1_s: Integral gain of the velocity loop, 1/T_i.
        servo_period_s: Period of the drive's servo cascade (sub-step of the SYNC period).
        following_error_window_m: Largest allowed |demand - actual| stroke (0x6065).
        following_error_timeout_s: How long the window may be exceeded before FAULT (0x6066).
        heartbeat_period_s: Heartbeat producer period of the drives and the master (0x1017).
        heartbeat_timeout_s: Consumer timeout for the master's heartbeat (0x1016).
        sync_timeout_s: SYNC/RPDO watchdog: longest gap while operation is enabled.
        quick_stop_deceleration_m_s2: Stroke deceleration of quick stop and fault reactions
            (0x6085).
        load_compensation_filter_s: Valve drives: time constant of the low-pass on the
            cylinder force the drive reads from its two chamber-pressure transducers, with
            which it scales the valve's flow gain to the load (see
            :class:`firmware_models.drive.DriveParameters`); 0 for none (the no-load gain).
        pressure_feedback_gain: Valve drives, per cylinder (boom, stick, bucket): dynamic
            pressure feedback, the valve opening taken off per unit of the high-passed cylinder
            force over the extending stall force ``p_s A_A``; 0 for none.
        pressure_feedback_filter_s: Valve drives: time constant of that high-pass.
        valve_overlap_compensation: Valve drives: the amplifier's overlap compensation, a jump
            of the spool command out of the valve's dead band (fraction of full opening; object
            0x2100, written by the master at boot); 0 for none.
    """

    encoder_resolution_m: float
    position_gain_1_s: float
    velocity_gain_s_m: float
    velocity_integral_gain_1_s: float
    servo_period_s: float
    following_error_window_m: float
    following_error_timeout_s: float
    heartbeat_period_s: float
    heartbeat_timeout_s: float
    sync_timeout_s: float
    quick_stop_deceleration_m_s2: float
    load_compensation_filter_s: float = 0.0
    pressure_feedback_gain: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pressure_feedback_filter_s: float = 0.0
    valve_overlap_compensation: float = 0.0


@dataclass(frozen=True, slots=True)
class HydraulicActuator:
    """Valve-controlled differential cylinder (profile ``[actuators.hydraulic]``).

    One size for the three cylinders. Force = p_A A_A - p_B A_B with the rod-side (annulus)
    area A_B = piston_area_m2 - rod_area_m2.

    Attributes:
        supply_pressure_pa: Supply pressure p_s (tank at 0).
        piston_area_m2: Piston (cap-side) area A_A.
        rod_area_m2: Cross-section of the rod; less than the piston area.
        bulk_modulus_pa: Effective bulk modulus of oil and hoses.
        chamber_volume_m3: Dead volume of each chamber (hose and end of stroke); the swept
            volume adds to it with the stroke.
        valve_flow_m3_s: Flow of one metering edge at full opening and a 3.5 MPa drop.
        valve_time_constant_s: First-order lag of the spool.
    """

    supply_pressure_pa: float
    piston_area_m2: float
    rod_area_m2: float
    bulk_modulus_pa: float
    chamber_volume_m3: float
    valve_flow_m3_s: float
    valve_time_constant_s: float

    @property
    def annulus_area_m2(self) -> float:
        """Rod-side effective area A_B = A_A - rod cross-section."""
        return self.piston_area_m2 - self.rod_area_m2


@dataclass(frozen=True, slots=True)
class Actuators:
    """The arm's cylinders as actuators (profile ``[actuators]``), one size for all three.

    Attributes:
        force_max_n: Largest cylinder force: the motor's peak force at the rod (electric), or
            supply pressure times piston area (hydraulic).
        velocity_max_m_s: Largest stroke rate: the motor's top speed at the rod (electric), or
            the no-load extension speed at full valve opening (hydraulic: the valve's velocity
            gain per unit spool command).
        reflected_mass_kg: Mass seen at the rod of what moves with the stroke but is not the
            arm: motor and screw inertia (electric, J (2 pi / lead)^2), piston and rod
            (hydraulic).
        coulomb_friction_n: Coulomb friction of screw, seals and guides.
        viscous_friction_n_s_m: Viscous friction.
        hydraulic: Valve and cylinder data where ``cylinders.kind`` is ``hydraulic``, else None.
    """

    force_max_n: float
    velocity_max_m_s: float
    reflected_mass_kg: float
    coulomb_friction_n: float
    viscous_friction_n_s_m: float
    hydraulic: HydraulicActuator | None


def _readonly(values: list[float]) -> NDArray[np.float64]:
    a = np.array(values, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, slots=True)
class Rig:
    """A validated rig profile.

    Attributes:
        name: Profile name.
        description: One line about the machine.
        sources: Where the values come from.
        source_path: File it was loaded from.
        gravity_m_s2: Gravitational acceleration (acts along -y).
        ground_y_m: Height of the ground the machine stands on, in the arm frame.
        joints: Arm joints (boom, stick, bucket).
        links: Arm links, same order.
        swing: Swing joint, base offsets and dynamics constants, or None for a planar rig.
        bucket: Bucket dimensions.
        soil: Soil model parameters.
        cylinders: Cylinder and linkage geometry.
        planning: One-shot planning thresholds, or None where the rig has none.
        can: CAN settings.
        assumed: (key path, reason) for every value no source gives.
        drives: Servo drive settings (gains, windows, timeouts); not part of
            :attr:`planning_fingerprint`.
        actuators: Cylinder actuator data (force, speed, friction, hydraulics); not part of
            :attr:`planning_fingerprint`.
        trench: The trench task domain and spoil zone; not part of :attr:`planning_fingerprint`
            (no one-shot plan depends on it).
        hil: What the real rig does that the ideal HIL does not (profile ``[hil]``), or None;
            not part of :attr:`planning_fingerprint`.
    """

    name: str
    description: str
    sources: tuple[str, ...]
    source_path: str
    gravity_m_s2: float
    ground_y_m: float
    joints: tuple[Joint, Joint, Joint]
    links: tuple[Link, Link, Link]
    swing: Swing | None
    bucket: Bucket
    soil: Soil
    cylinders: Cylinders
    planning: Planning | None
    can: Can
    assumed: tuple[tuple[str, str], ...]
    drives: Drives
    actuators: Actuators
    trench: TrenchDomain
    hil: RigImperfections | None = None
    lengths_m: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    q_min_rad: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    q_max_rad: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    qd_max_rad_s: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    qdd_max_rad_s2: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    qddd_max_rad_s3: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    tau_max_nm: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Arrays over the three arm joints, precomputed once for the batched physics.
        put = object.__setattr__
        put(self, "lengths_m", _readonly([lk.length_m for lk in self.links]))
        put(self, "q_min_rad", _readonly([j.min_rad for j in self.joints]))
        put(self, "q_max_rad", _readonly([j.max_rad for j in self.joints]))
        put(self, "qd_max_rad_s", _readonly([j.velocity_max_rad_s for j in self.joints]))
        put(self, "qdd_max_rad_s2", _readonly([j.acceleration_max_rad_s2 for j in self.joints]))
        put(self, "qddd_max_rad_s3", _readonly([j.jerk_max_rad_s3 for j in self.joints]))
        put(self, "tau_max_nm", _readonly([j.torque_max_nm for j in self.joints]))

    @property
    def has_swing(self) -> bool:
        """Whether the rig has a swing joint (4 DOF)."""
        return self.swing is not None

    @property
    def dof(self) -> int:
        """Number of joints including swing."""
        return 4 if self.swing is not None else 3

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint names, swing first where present."""
        arm = tuple(j.name for j in self.joints)
        return ("swing", *arm) if self.swing is not None else arm

    @property
    def planning_fingerprint(self) -> str:
        """SHA-256 (hex) of every value one-shot planning depends on.

        Geometry, limits, masses, ground, bucket, soil and the planning thresholds, as canonical
        JSON (floats in their exact repr); not the name, sources, cylinders, CAN, drive or actuator
        settings, nor the swing's plant constants (:data:`SWING_PLANT_KEYS`). A model card
        records it, so a network trained for other values is refused even when the profile
        keeps its name.
        """
        import dataclasses
        import hashlib
        import json

        swing = dataclasses.asdict(self.swing) if self.swing is not None else None
        if swing is not None:
            for key in SWING_PLANT_KEYS:
                del swing[key]
        data = {
            key: dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
            for key, value in (
                ("gravity_m_s2", self.gravity_m_s2),
                ("ground_y_m", self.ground_y_m),
                ("joints", [dataclasses.asdict(j) for j in self.joints]),
                ("links", [dataclasses.asdict(lk) for lk in self.links]),
                ("swing", swing),
                ("bucket", self.bucket),
                ("soil", self.soil),
                ("planning", self.planning),
            )
        }
        text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=repr)
        return hashlib.sha256(text.encode()).hexdigest()

    def is_assumed(self, key_path: str) -> bool:
        """Whether ``key_path`` is marked assumed in the profile."""
        return any(k == key_path for k, _ in self.assumed)
