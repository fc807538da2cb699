"""Rig profiles: TOML data with sources, loaded into validated frozen dataclasses."""

from rt_runtime.rig.cylinders import BucketLinkage, Cylinders, PinCylinder
from rt_runtime.rig.loader import DEFAULT_RIG, load_rig, parse_rig, profile_names
from rt_runtime.rig.model import (
    ARM_JOINTS,
    Bucket,
    Can,
    FluidSoil,
    Joint,
    Link,
    Planning,
    Rig,
    Soil,
    Swing,
    YaoSoil,
)

__all__ = [
    "ARM_JOINTS",
    "DEFAULT_RIG",
    "Bucket",
    "BucketLinkage",
    "Can",
    "Cylinders",
    "FluidSoil",
    "Joint",
    "Link",
    "PinCylinder",
    "Planning",
    "Rig",
    "Soil",
    "Swing",
    "YaoSoil",
    "load_rig",
    "parse_rig",
    "profile_names",
]
