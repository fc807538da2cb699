"""The one exception root of the runtime and its tree.

::

    ExcavatorRtError
     +-- ConfigurationError        a rig profile, config file or argument is wrong
     |    +-- RigProfileError      names the key path and what is allowed
     +-- KinematicsError
     |    +-- UnreachableError     a Cartesian target outside the arm's reach
     |    +-- JointLimitError      a solution or command outside a joint's range
     +-- PlanningError             no plan, or a plan that failed verification
     +-- CommunicationError        the bus or a peer failed
     +-- DriveFault                a drive reported or caused a fault

Configuring code raises; code inside the fixed-rate loop returns status codes instead.
"""

from __future__ import annotations


class ExcavatorRtError(Exception):
    """Root of every error the runtime raises on purpose."""


class ConfigurationError(ExcavatorRtError):
    """A profile, configuration file or argument is invalid."""


class RigProfileError(ConfigurationError):
    """A rig profile is invalid.

    Attributes:
        key_path: Dotted path of the offending key, e.g. ``joints.boom.length_m``.
        source: File (or profile name) the key came from.
    """

    def __init__(self, key_path: str, message: str, source: str = "") -> None:
        self.key_path = key_path
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{key_path}: {message}")


class KinematicsError(ExcavatorRtError):
    """A kinematic computation has no valid answer."""


class UnreachableError(KinematicsError):
    """A Cartesian target lies outside the arm's reach."""


class JointLimitError(KinematicsError):
    """A joint value lies outside its allowed range.

    Attributes:
        joint: Joint name (``boom``, ``stick``, ``bucket``, ``swing``).
        value_rad: The offending value.
        min_rad: Lower limit.
        max_rad: Upper limit.
    """

    def __init__(self, joint: str, value_rad: float, min_rad: float, max_rad: float) -> None:
        import math

        self.joint = joint
        self.value_rad = value_rad
        self.min_rad = min_rad
        self.max_rad = max_rad
        super().__init__(
            f"{joint} joint at {math.degrees(value_rad):.3f} deg is outside its limits "
            f"[{math.degrees(min_rad):.3f}, {math.degrees(max_rad):.3f}] deg"
        )


class PlanningError(ExcavatorRtError):
    """No plan could be made, or a plan failed verification (nothing may be sent from it)."""


class CommunicationError(ExcavatorRtError):
    """The bus, a socket or a peer failed."""


class DriveFault(ExcavatorRtError):
    """A drive is in FAULT or reported an emergency."""
