"""What a real rig does that an ideal one does not (profile ``[hil]``): valves, sensors,
motors and the dug material, as the HIL emulates them.

The values describe the machine, not the runtime: the HIL (``hil_sim``) applies them to its
plant and terrain when :attr:`RigImperfections.enabled` is set, and leaves its ideal models
untouched when it is not (an ideal HIL reproduces the plan's own numbers, which the runtime's
regression tests rely on). Each value carries a source or is listed in the profile's
``[assumed]`` table with a reason.

Tables (all optional but ``[hil]`` itself; a missing one is an ideal part):

* ``[hil]``: ``enabled`` (bool), ``seed`` (int, the sensor noise's generator).
* ``[hil.valve]`` (hydraulic rigs): ``overlap`` (spool overlap, the dead band, as a fraction
  of full opening), ``hysteresis`` (width of the spool's hysteresis loop, fraction of full
  opening), ``slew_1_s`` (largest spool rate, full openings per second), ``delay_ms``
  (transport delay from the drive's command to the spool: CAN plus valve driver).
* ``[hil.sensor]``: ``linearity_fs`` (largest linearity error as a fraction of the stroke's
  full scale), ``noise_um`` (standard deviation of the white noise of each reading).
* ``[hil.electric]`` (electric rigs): ``backlash_um`` (lost motion of the screw and its
  coupling), ``breakaway_friction_n`` (static friction, above the profile's Coulomb friction),
  ``stribeck_velocity_mm_s`` (speed over which friction falls from breakaway to Coulomb),
  ``current_bandwidth_hz`` (the drive's current loop as a first-order lag on the force).
* ``[hil.materials.<name>]``: granular materials the rig digs, one table each:
  ``spill_fraction`` (of the material a dig sweeps, what the bucket does not keep),
  ``fallback_fraction`` (of that spill, what falls back into the trench; the rest leaves the
  section to the sides), ``repose_deg`` (angle of repose: faces steeper than it slump),
  ``resistance_factor`` (the material's digging resistance against Yao eq 8's); ``[hil]``
  ``material`` names the one in the pit.
* ``[hil.scanner]``: a 2-D profile scanner over the trench (optional equipment of the rig):
  ``spacing_mm`` (between its samples along the trench), ``noise_mm`` (standard deviation of
  each sample's height).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from rt_runtime.errors import ConfigurationError
from rt_runtime.rig._schema import Table

__all__ = [
    "ElectricImperfections",
    "Material",
    "RigImperfections",
    "Scanner",
    "SensorImperfections",
    "ValveImperfections",
    "parse_imperfections",
]


@dataclass(frozen=True, slots=True)
class ValveImperfections:
    """The proportional valve of a hydraulic axis (``[hil.valve]``).

    Attributes:
        overlap: Spool overlap as a fraction of full opening: no metering flow while
            ``|x| <= overlap``; beyond it the opening is ``(|x| - overlap) / (1 - overlap)``.
        hysteresis: Width of the spool's hysteresis loop (fraction of full opening): the spool
            follows its command only once the command moved half of it past the spool's side.
        slew_1_s: Largest spool rate (full openings per second).
        delay_s: Dead time from the drive's command to the spool (s).
    """

    overlap: float
    hysteresis: float
    slew_1_s: float
    delay_s: float


@dataclass(frozen=True, slots=True)
class SensorImperfections:
    """The stroke sensor each drive reads (``[hil.sensor]``).

    Attributes:
        linearity_fs: Largest linearity error as a fraction of the stroke's full scale.
        noise_m: Standard deviation of the white noise on each reading (m).
    """

    linearity_fs: float
    noise_m: float


@dataclass(frozen=True, slots=True)
class ElectricImperfections:
    """Motor, drive and screw of an electric axis (``[hil.electric]``).

    Attributes:
        backlash_m: Lost motion between motor (encoder) and rod (m).
        breakaway_friction_n: Static friction at rest (>= the Coulomb friction).
        stribeck_velocity_m_s: Speed over which friction falls from breakaway to Coulomb.
        current_bandwidth_hz: -3 dB bandwidth of the current (force) loop.
    """

    backlash_m: float
    breakaway_friction_n: float
    stribeck_velocity_m_s: float
    current_bandwidth_hz: float


@dataclass(frozen=True, slots=True)
class Material:
    """A granular material the rig digs (``[hil.materials.<name>]``).

    Attributes:
        name: Its table's name (e.g. ``rubber``).
        spill_fraction: Of what a dig sweeps, the part the bucket does not keep.
        fallback_fraction: Of the spill, the part that falls back into the trench.
        repose_rad: Angle of repose; steeper faces slump to it.
        resistance_factor: Digging resistance against Yao eq 8's (1 = as eq 8).
    """

    name: str
    spill_fraction: float
    fallback_fraction: float
    repose_rad: float
    resistance_factor: float


@dataclass(frozen=True, slots=True)
class Scanner:
    """A 2-D profile scanner over the trench (``[hil.scanner]``).

    Attributes:
        spacing_m: Between its samples along the trench (m).
        noise_m: Standard deviation of each sample's height (m).
    """

    spacing_m: float
    noise_m: float


@dataclass(frozen=True, slots=True)
class RigImperfections:
    """The profile's ``[hil]`` table (see the module docstring).

    Attributes:
        enabled: Apply the imperfections (False: the HIL's ideal models).
        seed: Seed of the sensor noise (runs are reproducible).
        valve: Valve imperfections (hydraulic rigs) or None.
        sensor: Stroke sensor imperfections or None.
        electric: Electric axis imperfections (electric rigs) or None.
        material: The granular material in the pit, or None (the terrain removes what the
            tip sweeps).
        materials: Every material the profile describes, by name.
        scanner: The rig's profile scanner, or None (it digs blind).
    """

    enabled: bool
    seed: int
    valve: ValveImperfections | None
    sensor: SensorImperfections | None
    electric: ElectricImperfections | None
    material: Material | None
    scanner: Scanner | None = None
    materials: tuple[Material, ...] = ()

    def active(self) -> RigImperfections | None:
        """This table if enabled, else None (what the HIL applies)."""
        return self if self.enabled else None

    def with_material(self, name: str) -> RigImperfections:
        """The same with material ``name`` in the pit.

        Raises:
            ConfigurationError: No material of that name.
        """
        for m in self.materials:
            if m.name == name:
                return dataclasses.replace(self, material=m)
        names = ", ".join(m.name for m in self.materials) or "(none)"
        raise ConfigurationError(f"material {name!r}; the profile describes: {names}")


def parse_imperfections(t: Table, kind: str, coulomb_friction_n: float) -> RigImperfections:
    """Validate ``[hil]`` for a rig whose cylinders are ``kind``.

    Raises:
        RigProfileError: A bad value, a table for the other cylinder kind, or a breakaway
            friction below the Coulomb friction (the message names the key path).
    """
    enabled = t.boolean("enabled")
    seed = t.integer("seed", ge=0, le=2**31 - 1, default=1)
    valve_t = t.optional_table("valve")
    if valve_t is not None and kind != "hydraulic":
        raise t.error("valve", f"only for hydraulic cylinders (cylinders.kind = {kind!r})")
    electric_t = t.optional_table("electric")
    if electric_t is not None and kind != "electric":
        raise t.error("electric", f"only for electric cylinders (cylinders.kind = {kind!r})")
    valve = None
    if valve_t is not None:
        valve = ValveImperfections(
            overlap=valve_t.number("overlap", ge=0.0, lt=0.5),
            hysteresis=valve_t.number("hysteresis", ge=0.0, lt=0.5),
            slew_1_s=valve_t.number("slew_1_s", gt=0.0, le=1e4),
            delay_s=valve_t.number("delay_ms", ge=0.0, le=100.0) * 1e-3,
        )
        valve_t.finish()
    sensor = None
    sensor_t = t.optional_table("sensor")
    if sensor_t is not None:
        sensor = SensorImperfections(
            linearity_fs=sensor_t.number("linearity_fs", ge=0.0, le=0.1),
            noise_m=sensor_t.number("noise_um", ge=0.0, le=1e4) * 1e-6,
        )
        sensor_t.finish()
    electric = None
    if electric_t is not None:
        breakaway = electric_t.number("breakaway_friction_n", ge=0.0, le=1e8)
        if breakaway < coulomb_friction_n:
            raise electric_t.error(
                "breakaway_friction_n",
                f"must be >= actuators.coulomb_friction_n ({coulomb_friction_n:g} N) (got "
                f"{breakaway:g})",
            )
        electric = ElectricImperfections(
            backlash_m=electric_t.number("backlash_um", ge=0.0, le=1e4) * 1e-6,
            breakaway_friction_n=breakaway,
            stribeck_velocity_m_s=electric_t.number("stribeck_velocity_mm_s", gt=0.0, le=1e4)
            * 1e-3,
            current_bandwidth_hz=electric_t.number("current_bandwidth_hz", gt=0.0, le=1e6),
        )
        electric_t.finish()
    materials = []
    materials_t = t.optional_table("materials")
    if materials_t is not None:
        for name in materials_t.keys():
            m_t = materials_t.table(name)
            materials.append(
                Material(
                    name=name,
                    spill_fraction=m_t.number("spill_fraction", ge=0.0, lt=1.0),
                    fallback_fraction=m_t.number("fallback_fraction", ge=0.0, le=1.0),
                    repose_rad=math.radians(m_t.number("repose_deg", gt=0.0, lt=90.0)),
                    resistance_factor=m_t.number("resistance_factor", gt=0.0, le=10.0),
                )
            )
            m_t.finish()
        materials_t.finish()
    in_pit = t.string("material", default=None) if t.has("material") else None
    material = None
    if in_pit is not None:
        found = [m for m in materials if m.name == in_pit]
        if not found:
            names = ", ".join(m.name for m in materials) or "(none)"
            raise t.error("material", f"names no [hil.materials] table; described: {names}")
        material = found[0]
    scanner = None
    scanner_t = t.optional_table("scanner")
    if scanner_t is not None:
        scanner = Scanner(
            spacing_m=scanner_t.number("spacing_mm", gt=0.0, le=1e3) * 1e-3,
            noise_m=scanner_t.number("noise_mm", ge=0.0, le=1e3) * 1e-3,
        )
        scanner_t.finish()
    t.finish()
    return RigImperfections(
        enabled=enabled,
        seed=seed,
        valve=valve,
        sensor=sensor,
        electric=electric,
        material=material,
        scanner=scanner,
        materials=tuple(materials),
    )
