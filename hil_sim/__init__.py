"""Hardware-in-the-loop simulator: the plant, terrain, drives on the bus, scenarios and reports.

This package may import rt_runtime's physics (kinematics, dynamics, soil, actuation) and
firmware_models, never rt_runtime's control code; rt_runtime never imports it.
"""

from hil_sim.plant import ArmPlant, TipLoad
from hil_sim.terrain import CutResult, Terrain, YaoTipLoad

__all__ = ["ArmPlant", "CutResult", "Terrain", "TipLoad", "YaoTipLoad"]
