"""The error the firmware models raise for a bad configuration.

``firmware_models`` depends on nothing of the runtime, so it has its own error.
:class:`FirmwareConfigurationError` is a :class:`ValueError` (a wrong argument: node id, EDS or
DBC file, drive or VCU parameter); the HIL that builds the models (``hil_sim.sim.HilCore``)
reports it as the runtime's ``ConfigurationError``.
"""

from __future__ import annotations

__all__ = ["FirmwareConfigurationError"]


class FirmwareConfigurationError(ValueError):
    """A node id, EDS or DBC file, or model parameter is invalid."""
