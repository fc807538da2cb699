"""The groups every JSON report shares: percentiles, spreads, ranges and bus load.

Every ``--json`` report is a frozen dataclass with one ``to_json()`` that returns the JSON object
as a dict (README "Commands", DESIGN.md "Reports"): its attributes carry the JSON keys' names and
its nested groups are the types here, so each key has one spelling wherever it appears.

* :class:`Distribution`: ``p50``, ``p99`` and, where timing tails matter, ``p999`` and ``max``.
* :class:`Spread`: ``p50`` and ``max`` (median and worst of a figure over tasks or problems).
* :class:`Range`: ``min`` and ``max``.
* :class:`BusLoadFigures`: ``nominal``, ``realistic`` (where measured) and ``worst``.

A group's units are its sample's, named by the key that holds it (``plan_us``, ``solve_s``).
Percentiles are numpy's default (linear interpolation). Not for the loop: these allocate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["BusLoadFigures", "Distribution", "Range", "Spread"]


@dataclass(frozen=True, slots=True)
class Distribution:
    """Percentiles of a sample.

    Attributes:
        p50: Median.
        p99: 99th percentile.
        p999: 99.9th percentile, or None where the report leaves it out.
        max: Largest value, or None where the report leaves it out.
    """

    p50: float
    p99: float
    p999: float | None = None
    max: float | None = None

    @classmethod
    def of(cls, values: ArrayLike, *, tails: bool = False) -> Distribution:
        """``p50`` and ``p99`` of ``values`` (and ``p999``, ``max`` with ``tails``).

        Raises:
            IndexError: ``values`` is empty (numpy's percentile of nothing).
        """
        a = np.asarray(values, dtype=np.float64)
        p50, p99 = float(np.percentile(a, 50)), float(np.percentile(a, 99))
        if not tails:
            return cls(p50, p99)
        return cls(p50, p99, float(np.percentile(a, 99.9)), float(np.max(a)))

    @classmethod
    def spread(cls, values: ArrayLike) -> Distribution:
        """``p50``, ``p99`` and ``max`` of ``values``; each NaN when ``values`` is empty."""
        a = np.asarray(values, dtype=np.float64)
        if not a.size:
            return cls(math.nan, math.nan, max=math.nan)
        return cls(float(np.percentile(a, 50)), float(np.percentile(a, 99)), max=float(np.max(a)))

    def to_json(self) -> dict[str, float]:
        """``{"p50", "p99"}`` plus ``"p999"`` and ``"max"`` where set."""
        out = {"p50": self.p50, "p99": self.p99}
        if self.p999 is not None:
            out["p999"] = self.p999
        if self.max is not None:
            out["max"] = self.max
        return out


@dataclass(frozen=True, slots=True)
class Spread:
    """Median and largest value of a figure.

    Attributes:
        p50: Median.
        max: Largest value.
    """

    p50: float
    max: float

    @classmethod
    def of(cls, values: ArrayLike) -> Spread:
        """Median and largest of ``values``.

        Raises:
            IndexError: ``values`` is empty.
        """
        a = np.asarray(values, dtype=np.float64)
        return cls(float(np.percentile(a, 50)), float(np.max(a)))

    def to_json(self) -> dict[str, float]:
        """``{"p50", "max"}``."""
        return {"p50": self.p50, "max": self.max}


@dataclass(frozen=True, slots=True)
class Range:
    """Smallest and largest value (None where there was none).

    Attributes:
        min: Smallest value.
        max: Largest value.
    """

    min: float | None
    max: float | None

    def to_json(self) -> dict[str, float | None]:
        """``{"min", "max"}``."""
        return {"min": self.min, "max": self.max}


@dataclass(frozen=True, slots=True)
class BusLoadFigures:
    """CAN bus load of the cyclic frames, fractions of the bitrate.

    Attributes:
        nominal: Without stuff bits.
        worst: With worst-case stuff bits in every frame (the guaranteed bound).
        realistic: With the exact stuff bits of the frames as sent, or None where not measured.
    """

    nominal: float
    worst: float
    realistic: float | None = None

    def to_json(self) -> dict[str, float]:
        """``{"nominal", "realistic", "worst"}`` (``realistic`` where measured)."""
        out = {"nominal": self.nominal}
        if self.realistic is not None:
            out["realistic"] = self.realistic
        out["worst"] = self.worst
        return out
