"""A dig before it is planned: the typed candidate the screening and the profile fits hand
to the planning step, the network's candidate grid per dig type, and the screening's
settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from rt_runtime.planning.oneshot import DigType
from rt_runtime.planning.trench.geometry import OVERDIG_LIMIT_M, FloatArray


@dataclass(frozen=True, slots=True)
class Candidate:
    """A dig chosen on its geometry, before it is planned for real and checked.

    Attributes:
        kind: Downward or backward.
        x7: ``(7,)`` entry pose and exit pose (rad, arm frame at the machine's position) and H
            (m, the surface the one-shot model and the soil model take).
        useful_m2: Design material it is estimated to remove (cross-section area, m^2).
        total_m2: Material it is estimated to remove in all (m^2).
        score: The ranking's score (larger first).
        K_rad: A network dig's bulge ``(3,)`` (rad, the network's answer at ``T_s``), which
            ``c`` scales; None for a dig fitted along the outline.
        c: The bulge scale that fills the bucket on the material left.
        T_s: The network's time (network digs), or the retimed time (fitted digs).
        a6: A fitted dig's retimed sixth-order coefficients (rad/s^6); None for network digs.
        fit_rms_m: RMS distance of a fitted dig's path from its outline (m).
        may_underfill: Planned even where its real cut is below the fill band (then it is a
            finishing pass); a dig without it is refused outside the band.
        pass_window: A fitted dig whose real cut is below the fill band, timed and verified
            in the finishing passes' time window (:data:`PASS_T_MIN_FRACTION`).
        envelope: A fitted dig's lowest reach on the height field's grid (m, work-site
            frame: the surface it leaves is the minimum of this and the material's); None
            for network digs.
        joined: A fitted dig that continues the bucket of the dig before it: it starts at
            that dig's exit, at rest, with no moves between, or (``carried``) at its own
            entry, the bucket carried there.
        bucket_m3: Material already in a joined dig's bucket (m^3), which counts toward its
            fill; 0 otherwise.
        carried: A joined dig that enters the ground at its own entry: the light bucket of
            the dig before it is carried there by a cycle without a dump.
    """

    kind: DigType
    x7: FloatArray
    useful_m2: float
    total_m2: float
    score: float
    K_rad: FloatArray | None = None
    c: float = 1.0
    T_s: float = 0.0
    a6: tuple[float, float, float] | None = None
    fit_rms_m: float = math.nan
    may_underfill: bool = False
    pass_window: bool = False
    envelope: FloatArray | None = field(default=None, repr=False, compare=False)
    joined: bool = False
    bucket_m3: float = 0.0
    carried: bool = False


def difference_lowered(c: Candidate) -> float:
    """How much a dig lowers the symmetric difference of dug and design (m^2, on the height
    field): the design material it removes less what it cuts outside the design."""
    return 2.0 * c.useful_m2 - c.total_m2


#: A finishing pass's shortest time as a fraction of the one-shot window's (Yao Table 2's
#: T >= 5 s on ``scale_model``: 1 s). A pass is not a one-shot dig: the window is the one-shot
#: problem's (the network's training domain, eq 11's normalisation), and a pass that trims a
#: few millimetres to centimetres is timed by the joint limits alone (velocity, acceleration,
#: torque with the soil's resistance, power), down to this floor.
PASS_T_MIN_FRACTION = 0.2


@dataclass(frozen=True, slots=True)
class _Candidates:
    """The candidate grid of one dig type (arm-frame values relative to the entry)."""

    entry_attitude_deg: tuple[float, ...]
    length_m: tuple[float, ...]
    exit_rise_m: tuple[float, ...]
    exit_attitude_deg: tuple[float, ...]


_CANDIDATES: dict[DigType, _Candidates] = {
    DigType.DOWNWARD: _Candidates(
        entry_attitude_deg=(-75.0, -90.0, -105.0, -118.0),
        length_m=(0.22, 0.34, 0.39),
        exit_rise_m=(0.01, 0.05, 0.15),
        exit_attitude_deg=(-145.0, -160.0, -175.0),
    ),
    DigType.BACKWARD: _Candidates(
        entry_attitude_deg=(-102.0, -115.0, -128.0),
        length_m=(0.28, 0.40, 0.46),
        exit_rise_m=(0.01, 0.05),
        exit_attitude_deg=(-152.0, -165.0, -180.0),
    ),
}

#: Entry x candidates per screening: from the far edge of the remaining design inwards.
_N_ENTRY_X = 4

# Bulge scales at which the screening computes each candidate's path; the fill's scale between
# them is interpolated.
_SCREEN_C = (0.3, 0.6, 1.0, 2.0)

# The geometric screening's bulge per dig type (no network): the bulge K that moves the tip at
# mid-path by (dx, dy) m on the scale model (scaled by reach) and turns the bucket by the
# attitude (deg), all at scale c = 1. The means of the network's own answers over task D's
# rough stage (162-979 candidates a screening: downward (-0.10, -0.10) m, -17 deg; backward
# (-0.12, -0.06) m, -26 deg): a dig that sinks towards the machine and curls the bucket.
_GEOMETRIC_BULGE = {
    DigType.DOWNWARD: (-0.10, -0.10, -17.0),
    DigType.BACKWARD: (-0.12, -0.06, -26.0),
}

# Samples per path in the screening (the plan is checked on the verifier's full grid).
_SCREEN_SAMPLES = 17

# Over-dig a screened path may show at its coarse samples (the plan's own check is exact).
_SCREEN_OVERDIG_M = 0.8 * OVERDIG_LIMIT_M

# Steps of the bulge scale searched for theta_p in the screening (from the top down to 0).
_N_SCALE_STEPS = 40

# Fraction of the fill band kept free at each end in the screening (its cut is interpolated).
_FILL_MARGIN = 0.03

# Candidates kept per screening, tried in order when the one-shot planner's plan fails.
_N_RANKED = 8

# Screened candidates whose material left is estimated (the look-ahead), best score first.
_N_LOOKAHEAD = 32

#: Least material above the design floor where an entry may be placed (m, scale model).
_ENTRY_MIN_THICKNESS_M = 0.01

#: Spare fraction of the fill band's ends for the upper layers in the layer choice (the
#: network's scoops do not follow the layer's floor).
_ROUGH_SPARE = 0.04
