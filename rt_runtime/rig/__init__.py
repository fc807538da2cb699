"""Rig profiles: TOML data with sources, loaded into validated frozen dataclasses."""

from rt_runtime.rig.cylinders import BucketLinkage, Cylinders, PinCylinder
from rt_runtime.rig.loader import DEFAULT_RIG, load_rig, parse_rig, profile_names
from rt_runtime.rig.model import (
    ARM_JOINTS,
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

__all__ = [
    "ARM_JOINTS",
    "DEFAULT_RIG",
    "Actuators",
    "Bucket",
    "BucketLinkage",
    "Can",
    "Cylinders",
    "Drives",
    "FluidSoil",
    "HydraulicActuator",
    "Joint",
    "Link",
    "PinCylinder",
    "Planning",
    "Rig",
    "Soil",
    "SpoilZone",
    "Swing",
    "TrenchDomain",
    "YaoSoil",
    "load_rig",
    "parse_rig",
    "profile_names",
]
