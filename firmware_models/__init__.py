"""What the drives are: the CiA 402 drive's object dictionary (EDS), the VCU's message set (DBC)
and behaviour models of their firmware.

This module only names the data files, so the runtime (``rt_runtime.canbus``) can read the same
EDS and DBC as the emulator without importing any model code. Import the models from their
modules: ``firmware_models.drive.DriveFirmware`` and ``firmware_models.vcu.VcuModel``.

The files are found relative to this package, so they work from a source checkout and from an
installed wheel (package data ``*.eds``, ``*.dbc``).
"""

from __future__ import annotations

from pathlib import Path

#: Directory of this package (the EDS and DBC live beside this file).
PACKAGE_DIR: Path = Path(__file__).resolve().parent

#: CiA 306 EDS of every cylinder drive; read with
#: ``canopen.objectdictionary.import_od(str(CIA402_DRIVE_EDS), node_id)``.
CIA402_DRIVE_EDS: Path = PACKAGE_DIR / "cia402_drive.eds"

#: DBC message set of the vehicle control unit (travel and swing motors, Yao et al. 5.1); read
#: with ``cantools.database.load_file(str(VCU_DBC))``. Frame ids are written for node
#: ``VCU_DBC_NODE_ID``; another node id shifts every frame id by the difference.
VCU_DBC: Path = PACKAGE_DIR / "vcu.dbc"

#: Node id the frame ids in ``vcu.dbc`` are written for.
VCU_DBC_NODE_ID: int = 0x10

__all__ = ["CIA402_DRIVE_EDS", "PACKAGE_DIR", "VCU_DBC", "VCU_DBC_NODE_ID"]
