"""Cylinder and bucket-linkage geometry of a rig profile (Yang, Gao et al. 2023, eq 5-13).

Boom and stick cylinders act between two pins, one on each side of a joint, so the cylinder's
pin-to-pin length is the third side of a triangle whose included angle is an affine function of
the joint angle (Gao eq 6 and 8)::

    L(theta) = sqrt(a^2 + b^2 - 2 a b cos(phi)),   phi = sign * theta + offset

The sign is fixed by the joint, not read from the profile: +1 for the boom (eq 6), -1 for the
stick (eq 8), so that the strokes grow the way Gao Fig. 4 shows (boom with theta1, stick as
theta2 decreases).

The bucket cylinder drives the bucket through a four-bar linkage (Gao eq 9-13). Points, in the
stick's frame: G bucket pivot (stick tip), D stick pivot (boom tip), I rocker pivot on the stick,
H bucket-cylinder base pin on the stick, J the rocker/link/rod joint, K the link pin on the bucket,
L the bucket tip. The linkage sits on the stick's +y side (its counter-clockwise normal); the
side each angle opens to is stated on :class:`BucketLinkage` and derived in
:mod:`rt_runtime.actuation`, which is the only user of these numbers. The parsing lives here so
that the actuation model and its data change together; whether the geometry covers the joint
ranges is checked by :func:`rt_runtime.actuation.validate_cylinders` once the rig is built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rt_runtime.rig._schema import Table

# Sign of theta in the included angle phi, per joint (Gao eq 6 and 8).
_ANGLE_SIGN = {"boom": 1, "stick": -1}


@dataclass(frozen=True, slots=True)
class PinCylinder:
    """A cylinder between a pin on the parent link and a pin on the child link.

    Attributes:
        name: Joint it drives (``boom`` or ``stick``).
        pin_a_m: Distance from the joint axis to the cylinder pin on the parent side
            (boom: A-B, base pin on the turntable; stick: D-E, pin on the boom).
        pin_b_m: Distance from the joint axis to the cylinder pin on the child side
            (boom: A-C; stick: D-F, pin on the stick heel).
        angle_sign: +1 (boom) or -1 (stick): phi = angle_sign * theta + angle_offset_rad.
        angle_offset_rad: Included angle between the two pin rays at joint angle zero.
        retracted_length_m: Pin-to-pin length at zero stroke.
        stroke_max_m: Full stroke.
    """

    name: str
    pin_a_m: float
    pin_b_m: float
    angle_sign: int
    angle_offset_rad: float
    retracted_length_m: float
    stroke_max_m: float


@dataclass(frozen=True, slots=True)
class BucketLinkage:
    """Bucket cylinder and four-bar linkage (Gao Fig. 3, eq 9-13).

    Angles are directed (in the stick frame, x from D towards G, y its counter-clockwise
    normal) so that Gao eq 10 and 13 hold as printed.

    Attributes:
        l_hi_m: Cylinder base pin H to rocker pivot I (both on the stick).
        l_ij_m: Rocker length I-J.
        l_jk_m: Link length J-K.
        l_gk_m: Bucket pivot G to link pin K (on the bucket).
        l_ig_m: Rocker pivot I to bucket pivot G (on the stick).
        angle_hig_rad: Angle H-I-G: ray I->H is ray I->G turned counter-clockwise by it
            (measured through J; may exceed pi).
        angle_igd_rad: Angle I-G-D: ray G->I is ray G->D turned clockwise by it.
        angle_lgk_rad: Angle L-G-K on the bucket: ray G->K is ray G->L (L the tip) turned
            counter-clockwise by it.
        retracted_length_m: Cylinder pin-to-pin length H-J at zero stroke.
        stroke_max_m: Full stroke.
    """

    l_hi_m: float
    l_ij_m: float
    l_jk_m: float
    l_gk_m: float
    l_ig_m: float
    angle_hig_rad: float
    angle_igd_rad: float
    angle_lgk_rad: float
    retracted_length_m: float
    stroke_max_m: float


@dataclass(frozen=True, slots=True)
class Cylinders:
    """All cylinders of the arm.

    Attributes:
        kind: ``electric`` (servo electric cylinders) or ``hydraulic``.
        boom: Boom cylinder.
        stick: Stick cylinder.
        bucket: Bucket cylinder and linkage.
    """

    kind: str
    boom: PinCylinder
    stick: PinCylinder
    bucket: BucketLinkage


def _pin_cylinder(t: Table, name: str) -> PinCylinder:
    cyl = PinCylinder(
        name=name,
        pin_a_m=t.number("pin_a_m", gt=0.0),
        pin_b_m=t.number("pin_b_m", gt=0.0),
        angle_sign=_ANGLE_SIGN[name],
        angle_offset_rad=math.radians(t.number("angle_offset_deg", ge=-360.0, le=360.0)),
        retracted_length_m=t.number("retracted_length_m", gt=0.0),
        stroke_max_m=t.number("stroke_max_m", gt=0.0),
    )
    t.finish()
    return cyl


def _bucket_linkage(t: Table) -> BucketLinkage:
    link = BucketLinkage(
        l_hi_m=t.number("l_hi_m", gt=0.0),
        l_ij_m=t.number("l_ij_m", gt=0.0),
        l_jk_m=t.number("l_jk_m", gt=0.0),
        l_gk_m=t.number("l_gk_m", gt=0.0),
        l_ig_m=t.number("l_ig_m", gt=0.0),
        angle_hig_rad=math.radians(t.number("angle_hig_deg", gt=0.0, lt=360.0)),
        angle_igd_rad=math.radians(t.number("angle_igd_deg", ge=0.0, lt=360.0)),
        angle_lgk_rad=math.radians(t.number("angle_lgk_deg", ge=0.0, lt=360.0)),
        retracted_length_m=t.number("retracted_length_m", gt=0.0),
        stroke_max_m=t.number("stroke_max_m", gt=0.0),
    )
    t.finish()
    return link


def parse_cylinders(t: Table) -> Cylinders:
    """Read the ``[cylinders]`` table of a profile (types and ranges of each key only).

    Raises:
        RigProfileError: A key is missing, unknown or out of range.
    """
    cyl = Cylinders(
        kind=t.string("kind", choices=("electric", "hydraulic")),
        boom=_pin_cylinder(t.table("boom"), "boom"),
        stick=_pin_cylinder(t.table("stick"), "stick"),
        bucket=_bucket_linkage(t.table("bucket")),
    )
    t.finish()
    return cyl
