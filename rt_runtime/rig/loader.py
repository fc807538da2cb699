"""Loading and validating rig profiles (TOML) into frozen :class:`~rt_runtime.rig.model.Rig`.

``load_rig("scale_model")`` loads a shipped profile by name; ``load_rig("path/to/rig.toml")``
loads a file. Every field is checked (type, finiteness, range, min < max, unknown keys) and any
error names the key path and what is allowed. Values no source gives must be listed in the
profile's ``[assumed]`` table with a one-line reason; the loader checks that each listed key
exists.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

from rt_runtime.errors import RigProfileError
from rt_runtime.rig._schema import Table
from rt_runtime.rig.cylinders import parse_cylinders
from rt_runtime.rig.imperfections import parse_imperfections
from rt_runtime.rig.model import (
    ARM_JOINTS,
    DEFAULT_SWING_MOTOR_LINE_VOLUME_M3,
    DEFAULT_SWING_UPPER_INERTIA_KGM2,
    SCALE_MODEL_REACH_M,
    SCALE_MODEL_SPOIL,
    SCALE_MODEL_TRENCH_LENGTH_MAX_M,
    Actuators,
    Bucket,
    Can,
    Drives,
    FluidSoil,
    HydraulicActuator,
    Joint,
    Link,
    Planning,
    Rig,
    Soil,
    SpoilZone,
    Swing,
    TrenchDomain,
    YaoSoil,
)

PROFILE_DIR = Path(__file__).parent / "profiles"
DEFAULT_RIG = "scale_model"


def profile_names() -> list[str]:
    """Names of the shipped profiles."""
    return sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))


def load_rig(name_or_path: str | Path = DEFAULT_RIG) -> Rig:
    """Load and validate a rig profile.

    Args:
        name_or_path: A shipped profile name (see :func:`profile_names`) or a TOML file path.

    Returns:
        The validated rig.

    Raises:
        RigProfileError: Unknown name, unreadable file, bad TOML, or an invalid field (the
            message names the key path and the allowed range).
    """
    text = str(name_or_path)
    path = Path(text)
    if not (text.endswith(".toml") or path.exists()):
        candidate = PROFILE_DIR / f"{text}.toml"
        if not candidate.exists():
            raise RigProfileError(
                "name", f"no rig profile {text!r}; shipped: {', '.join(profile_names())}"
            )
        path = candidate
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as e:
        raise RigProfileError("file", f"cannot read {path}: not found") from e
    except OSError as e:
        raise RigProfileError("file", f"cannot read {path}: {e.strerror}") from e
    except UnicodeDecodeError as e:
        raise RigProfileError("file", f"{path} is not UTF-8 text: {e}") from e
    except ValueError as e:  # TOMLDecodeError, or an integer of more than 4300 digits
        raise RigProfileError("file", f"{path} is not valid TOML: {e}") from e
    return parse_rig(raw, source=str(path))


def parse_rig(raw: dict[str, Any], source: str = "") -> Rig:
    """Validate an already parsed profile document.

    Raises:
        RigProfileError: An invalid field, naming its key path.
    """
    root = Table(raw, "", source)
    name = root.string("name")
    description = root.string("description")
    sources = root.strings("sources")
    gravity = root.number("gravity_m_s2", gt=0.0, le=20.0)

    ground = root.table("ground")
    ground_y = ground.number("y_m", ge=-100.0, le=100.0)
    ground.finish()

    joints_t = root.table("joints")
    links_t = root.table("links")
    joints = tuple(_joint(joints_t.table(n), n) for n in ARM_JOINTS)
    links = tuple(_link(links_t.table(n), n) for n in ARM_JOINTS)
    joints_t.finish()
    links_t.finish()

    bucket = _bucket(root.table("bucket"))
    soil = _soil(root.table("soil"))
    cylinders = parse_cylinders(root.table("cylinders"))
    swing_t = root.optional_table("swing")
    swing = _swing(swing_t, cylinders.kind) if swing_t is not None else None
    planning_t = root.optional_table("planning")
    planning = _planning(planning_t) if planning_t is not None else None
    can = _can(root.table("can"), swing is not None)
    drives = _drives(root.table("drives"), cylinders.kind)
    actuators = _actuators(root.table("actuators"), cylinders.kind)
    trench_t = root.optional_table("trench")
    reach_m = sum(link.length_m for link in links)
    trench = _trench(trench_t, reach_m) if trench_t is not None else _trench_default(reach_m)
    hil_t = root.optional_table("hil")
    hil = (
        parse_imperfections(hil_t, cylinders.kind, actuators.coulomb_friction_n)
        if hil_t is not None
        else None
    )
    valve = hil.valve if hil is not None else None
    if valve is not None and drives.valve_overlap_compensation > valve.overlap:
        raise RigProfileError(
            "drives.valve_overlap_compensation",
            f"must be <= hil.valve.overlap ({valve.overlap:g}), the valves' own overlap: a "
            "compensation above it opens them past zero flow at every sign change (got "
            f"{drives.valve_overlap_compensation:g})",
            source,
        )
    assumed = _assumed(root.table("assumed"), raw)
    root.finish()

    rig = Rig(
        name=name,
        description=description,
        sources=sources,
        source_path=source,
        gravity_m_s2=gravity,
        ground_y_m=ground_y,
        joints=(joints[0], joints[1], joints[2]),
        links=(links[0], links[1], links[2]),
        swing=swing,
        bucket=bucket,
        soil=soil,
        cylinders=cylinders,
        planning=planning,
        can=can,
        assumed=assumed,
        drives=drives,
        actuators=actuators,
        trench=trench,
        hil=hil,
    )
    # Imported here: actuation imports this package.
    from rt_runtime.actuation import validate_cylinders

    validate_cylinders(rig)
    return rig


def _joint(t: Table, name: str) -> Joint:
    lo = t.number("min_deg", ge=-360.0, le=360.0)
    hi = t.number("max_deg", ge=-360.0, le=360.0)
    t.ordered("min_deg", lo, "max_deg", hi)
    joint = Joint(
        name=name,
        min_rad=math.radians(lo),
        max_rad=math.radians(hi),
        velocity_max_rad_s=math.radians(t.number("velocity_max_deg_s", gt=0.0, le=3600.0)),
        acceleration_max_rad_s2=math.radians(
            t.number("acceleration_max_deg_s2", gt=0.0, le=36000.0)
        ),
        jerk_max_rad_s3=math.radians(t.number("jerk_max_deg_s3", gt=0.0, le=360000.0)),
        torque_max_nm=t.number("torque_max_nm", gt=0.0),
    )
    t.finish()
    return joint


def _link(t: Table, name: str) -> Link:
    length = t.number("length_m", gt=0.0, le=50.0)
    com = t.numbers("com_m", 2, ge=-50.0, le=50.0)
    link = Link(
        name=name,
        length_m=length,
        mass_kg=t.number("mass_kg", gt=0.0),
        com_m=(com[0], com[1]),
        inertia_kgm2=t.number("inertia_kgm2", gt=0.0),
    )
    t.finish()
    return link


def _swing(t: Table, kind: str) -> Swing:
    offset = t.number("base_offset_m", ge=0.0, le=50.0)
    height = t.number("base_height_m", ge=-50.0, le=50.0)
    upper = t.number("upper_inertia_kgm2", gt=0.0, default=DEFAULT_SWING_UPPER_INERTIA_KGM2)
    if kind != "hydraulic" and t.has("motor_line_volume_l"):
        raise t.error(
            "motor_line_volume_l",
            f"only for a hydraulic swing motor (cylinders.kind = 'hydraulic'), not {kind!r}; "
            "leave it out",
        )
    line_m3 = (
        t.number("motor_line_volume_l", gt=0.0, default=DEFAULT_SWING_MOTOR_LINE_VOLUME_M3 * 1e3)
        * 1e-3
    )
    joint = _joint(t, "swing")  # the same limit keys as an arm joint; finish() ran there
    return Swing(
        joint=joint,
        base_offset_m=offset,
        base_height_m=height,
        upper_inertia_kgm2=upper,
        motor_line_volume_m3=line_m3,
    )


def _bucket(t: Table) -> Bucket:
    width = t.number("width_m", gt=0.0, le=10.0)
    capacity = t.number("capacity_l", gt=0.0) * 1e-3
    raw = t.raw("profile_m")
    if not isinstance(raw, list) or len(raw) < 3:
        raise t.error("profile_m", "must list at least 3 points [along, normal] (tip first)")
    points: list[tuple[float, float]] = []
    for i, p in enumerate(raw):
        sub = Table({"point": p}, t.key_path(f"profile_m[{i}]"), t.source)
        x, y = sub.numbers("point", 2, ge=-50.0, le=50.0)
        points.append((x, y))
    if points[0] != (0.0, 0.0):
        raise t.error("profile_m", f"must start at the tip [0, 0] (got {list(points[0])})")
    t.finish()
    return Bucket(width_m=width, capacity_m3=capacity, profile_m=tuple(points))


def _soil(t: Table) -> Soil:
    y = t.table("yao")
    yao = YaoSoil(k0_n_m2=y.number("k0_n_cm2", gt=0.0) * 1e4, mu=y.number("mu", ge=0.0, le=5.0))
    y.finish()
    f = t.table("fluid")
    fluid = []
    for soil_name in f.keys():
        s = f.table(soil_name)
        fluid.append(
            FluidSoil(
                name=soil_name,
                density_kg_m3=s.number("density_kg_m3", gt=0.0, le=10000.0),
                kp=s.number("kp", ge=0.0),
                kv=s.number("kv", ge=0.0),
                ks=s.number("ks", ge=0.0, le=5.0),
            )
        )
        s.finish()
    if not fluid:
        raise t.error("fluid", "must define at least one soil (e.g. [soil.fluid.soft])")
    f.finish()
    t.finish()
    return Soil(yao=yao, fluid=tuple(fluid))


def _planning(t: Table) -> Planning:
    t_lo, t_hi = t.range("t_s", ge=0.01, le=1000.0)
    v_lo, v_hi = t.range("volume_l", ge=0.0)
    e_lo, e_hi = t.range("energy_wh", ge=0.0)
    weights = t.numbers("weights", 3, ge=0.0, le=1.0)
    if not math.isclose(sum(weights), 1.0, abs_tol=1e-9):
        raise t.error("weights", f"must sum to 1 (got {sum(weights):g})")
    down = t.range("theta_p_downward_deg", ge=0.0, le=90.0)
    back = t.range("theta_p_backward_deg", ge=0.0, le=90.0)
    planning = Planning(
        t_min_s=t_lo,
        t_max_s=t_hi,
        volume_min_m3=v_lo * 1e-3,
        volume_max_m3=v_hi * 1e-3,
        energy_min_j=e_lo * 3600.0,
        energy_max_j=e_hi * 3600.0,
        power_max_w=t.number("power_max_w", gt=0.0),
        weights=(weights[0], weights[1], weights[2]),
        theta_p_downward_rad=(math.radians(down[0]), math.radians(down[1])),
        theta_p_backward_rad=(math.radians(back[0]), math.radians(back[1])),
    )
    t.finish()
    return planning


def _spoil_default(reach_m: float) -> SpoilZone:
    """The spoil zone of a profile without ``[trench.spoil]``: the scale model's
    (:data:`SCALE_MODEL_SPOIL`), lengths scaled by the rig's reach against 1.31 m."""
    s = reach_m / SCALE_MODEL_REACH_M
    d = SCALE_MODEL_SPOIL
    return SpoilZone(
        x_m=(d.x_m[0] * s, d.x_m[1] * s),
        height_m=(d.height_m[0] * s, d.height_m[1] * s),
        attitude_rad=d.attitude_rad,
        edge_gap_m=d.edge_gap_m * s,
    )


def _trench_default(reach_m: float) -> TrenchDomain:
    """The task domain of a profile without ``[trench]``: the scale model's longest trench
    (20 m) and spoil zone scaled by the rig's reach l1 + l2 + l3 against the scale model's
    1.31 m."""
    return TrenchDomain(
        length_max_m=SCALE_MODEL_TRENCH_LENGTH_MAX_M * reach_m / SCALE_MODEL_REACH_M,
        spoil=_spoil_default(reach_m),
    )


def _trench(t: Table, reach_m: float) -> TrenchDomain:
    default = _trench_default(reach_m)
    # Bounded so that a typo (20000 for 20) is refused: a thousand times the reach is already
    # more than any crawler digs in one task.
    length_max = t.number("length_max_m", gt=0.0, le=1000.0 * reach_m, default=default.length_max_m)
    spoil_t = t.optional_table("spoil")
    spoil = _spoil(spoil_t, reach_m) if spoil_t is not None else default.spoil
    t.finish()
    return TrenchDomain(length_max_m=length_max, spoil=spoil)


def _spoil(t: Table, reach_m: float) -> SpoilZone:
    # Within the arm's reach of the boom pin: a zone beyond it has no reachable point.
    x0, x1 = t.range("x_m", ge=-reach_m, le=reach_m)
    h0, h1 = t.range("height_m", ge=0.0, le=reach_m)
    z0, z1 = t.range("attitude_deg", ge=-180.0, le=180.0)
    spoil = SpoilZone(
        x_m=(x0, x1),
        height_m=(h0, h1),
        attitude_rad=(math.radians(z0), math.radians(z1)),
        edge_gap_m=t.number("edge_gap_m", ge=0.0, le=reach_m),
    )
    t.finish()
    return spoil


def _can(t: Table, has_swing: bool) -> Can:
    bitrate = t.integer("bitrate", ge=10_000, le=1_000_000)
    ids_t = t.table("node_ids")
    wanted = (("swing",) if has_swing else ()) + ARM_JOINTS
    ids = tuple((n, ids_t.integer(n, ge=1, le=127)) for n in wanted)
    ids_t.finish()
    vcu = t.integer("vcu_node_id", ge=1, le=127)
    seen: dict[int, str] = {}
    for n, i in (*ids, ("vcu", vcu)):
        if i in seen:
            key = f"node_ids.{n}" if n != "vcu" else "vcu_node_id"
            raise t.error(key, f"node id {i} is already used by {seen[i]}; ids must be unique")
        seen[i] = n
    on_bus = t.boolean("vcu", default=True)
    t.finish()
    return Can(bitrate=bitrate, node_ids=ids, vcu_node_id=vcu, vcu=on_bus)


def _drives(t: Table, kind: str) -> Drives:
    # Integer milliseconds and micrometres where the CAN object is an integer of that unit
    # (0x1016/0x1017/0x6066 u16 ms); bounds are the objects' ranges or far beyond any rig.
    window_mm = t.number("following_error_window_mm", gt=0.0, le=1000.0)
    period_ms = t.integer("heartbeat_period_ms", ge=1, le=65535)
    timeout_ms = t.integer("heartbeat_timeout_ms", ge=1, le=65535)
    if timeout_ms <= period_ms:
        raise t.error(
            "heartbeat_timeout_ms",
            f"must be > heartbeat_period_ms ({period_ms}) so that one late heartbeat is not a "
            f"loss (got {timeout_ms})",
        )
    gain = t.numbers("pressure_feedback_gain", 3, ge=0.0, le=100.0, default=[0.0, 0.0, 0.0])
    drives = Drives(
        encoder_resolution_m=t.number("encoder_resolution_um", gt=0.0, le=1000.0) * 1e-6,
        position_gain_1_s=t.number("position_gain_1_s", gt=0.0, le=10000.0),
        velocity_gain_s_m=t.number("velocity_gain", gt=0.0, le=1e6),
        velocity_integral_gain_1_s=t.number("velocity_integral_gain_1_s", ge=0.0, le=1e5),
        servo_period_s=t.integer("servo_period_us", ge=10, le=100_000, default=250) * 1e-6,
        following_error_window_m=window_mm * 1e-3,
        following_error_timeout_s=t.integer("following_error_timeout_ms", ge=0, le=65535) * 1e-3,
        heartbeat_period_s=period_ms * 1e-3,
        heartbeat_timeout_s=timeout_ms * 1e-3,
        sync_timeout_s=t.integer("sync_timeout_ms", ge=1, le=65535) * 1e-3,
        quick_stop_deceleration_m_s2=t.number("quick_stop_deceleration_mm_s2", gt=0.0, le=1e6)
        * 1e-3,
        load_compensation_filter_s=t.number(
            "load_compensation_filter_ms", ge=0.0, le=10_000.0, default=0.0
        )
        * 1e-3,
        pressure_feedback_gain=(gain[0], gain[1], gain[2]),
        pressure_feedback_filter_s=t.number(
            "pressure_feedback_filter_ms", ge=0.0, le=10_000.0, default=0.0
        )
        * 1e-3,
        valve_overlap_compensation=t.number(
            "valve_overlap_compensation", ge=0.0, le=0.5, default=0.0
        ),
    )
    feedback = max(drives.pressure_feedback_gain) > 0.0
    valve_only = (
        ("load_compensation_filter_ms", drives.load_compensation_filter_s > 0.0),
        ("pressure_feedback_gain", feedback),
        ("valve_overlap_compensation", drives.valve_overlap_compensation > 0.0),
    )
    for key, used in valve_only:
        if used and kind != "hydraulic":
            raise t.error(
                key,
                f"only for valve drives (cylinders.kind = 'hydraulic'), not {kind!r}; "
                "0 or leave it out",
            )
    if feedback and drives.pressure_feedback_filter_s <= 0.0:
        raise t.error(
            "pressure_feedback_filter_ms",
            "must be > 0 when pressure_feedback_gain is (the high-pass that keeps the static "
            f"stiffness), got {drives.pressure_feedback_filter_s * 1e3!r}",
        )
    t.finish()
    return drives


def _actuators(t: Table, kind: str) -> Actuators:
    force_max = t.number("force_max_n", gt=0.0, le=1e8)
    coulomb = t.number("coulomb_friction_n", ge=0.0)
    if not coulomb < force_max:
        raise t.error(
            "coulomb_friction_n",
            f"must be < force_max_n ({force_max:g} N): the cylinder could not move (got "
            f"{coulomb:g})",
        )
    hyd_t = t.optional_table("hydraulic")
    if kind == "hydraulic" and hyd_t is None:
        raise t.error("hydraulic", 'missing (required for cylinders.kind = "hydraulic")')
    if kind != "hydraulic" and hyd_t is not None:
        raise t.error("hydraulic", f"not allowed for cylinders.kind = {kind!r}")
    hydraulic = _hydraulic(hyd_t) if hyd_t is not None else None
    if hydraulic is not None:
        stall_n = hydraulic.supply_pressure_pa * hydraulic.piston_area_m2
        if force_max > stall_n * (1.0 + 1e-6):
            raise t.error(
                "force_max_n",
                f"must be <= supply pressure x piston area = {stall_n:.0f} N for a hydraulic "
                f"cylinder (got {force_max:g})",
            )
    actuators = Actuators(
        force_max_n=force_max,
        velocity_max_m_s=t.number("velocity_max_mm_s", gt=0.0, le=1e5) * 1e-3,
        reflected_mass_kg=t.number("reflected_mass_kg", ge=0.0, le=1e6),
        coulomb_friction_n=coulomb,
        viscous_friction_n_s_m=t.number("viscous_friction_n_s_m", ge=0.0, le=1e9),
        hydraulic=hydraulic,
    )
    t.finish()
    return actuators


def _hydraulic(t: Table) -> HydraulicActuator:
    piston = t.number("piston_area_cm2", gt=0.0, le=1e5)
    rod = t.number("rod_area_cm2", gt=0.0, le=1e5)
    t.ordered("rod_area_cm2", rod, "piston_area_cm2", piston)
    hyd = HydraulicActuator(
        supply_pressure_pa=t.number("supply_pressure_mpa", gt=0.0, le=100.0) * 1e6,
        piston_area_m2=piston * 1e-4,
        rod_area_m2=rod * 1e-4,
        bulk_modulus_pa=t.number("bulk_modulus_mpa", gt=0.0, le=1e4) * 1e6,
        chamber_volume_m3=t.number("chamber_volume_cm3", gt=0.0, le=1e8) * 1e-6,
        valve_flow_m3_s=t.number("valve_flow_l_min", gt=0.0, le=1e5) / 60000.0,
        valve_time_constant_s=t.number("valve_time_constant_ms", gt=0.0, le=1000.0) * 1e-3,
    )
    t.finish()
    return hyd


def _assumed(t: Table, raw: dict[str, Any]) -> tuple[tuple[str, str], ...]:
    out = []
    for key in t.keys():
        reason = t.string(key)
        if not reason.strip():
            raise t.error(key, "needs a one-line reason")
        node: Any = raw
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                raise t.error(key, "names a key that the profile does not have")
            node = node[part]
        out.append((key, reason))
    t.finish()
    return tuple(out)
