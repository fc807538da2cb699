"""A 2-D profile scanner over the trench: the HIL's emulation of a laser line that measures the
surface the bucket left, slumps and fallen-back material included.

Role: the measured surface a rig that does not dig blind plans on. :meth:`ProfileScanner.scan`
samples the terrain's true surface every ``spacing_m`` along the trench and adds a seeded
Gaussian error per sample (a laser scanner's statistical error), so runs repeat. The samples
are what the scanner publishes after each dig; the executor hands them to the trench planner
(:meth:`rt_runtime.planning.trench.TrenchSession.observe_surface`).

Not for the fixed-rate control loop (allocates; called between digs).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from hil_sim.terrain import Terrain
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Scanner

FloatArray = NDArray[np.float64]

__all__ = ["ProfileScanner"]


class ProfileScanner:
    """A profile scanner looking at a terrain (see the module docstring).

    Args:
        terrain: The terrain it sees (live: later cuts count).
        spec: Sample spacing and noise (profile ``[hil.scanner]``).
        seed: Seed of its noise.

    Raises:
        ConfigurationError: A terrain narrower than two samples.
    """

    def __init__(self, terrain: Terrain, spec: Scanner, seed: int = 0) -> None:
        x_lo, x_hi = terrain.x_range_m
        n = math.floor((x_hi - x_lo) / spec.spacing_m) + 1
        if n < 2:
            raise ConfigurationError(
                f"scanner spacing {spec.spacing_m} m: the terrain ({x_lo:g}..{x_hi:g} m) needs "
                "at least two samples"
            )
        self.terrain = terrain
        self.spec = spec
        self._x: FloatArray = x_lo + spec.spacing_m * np.arange(n, dtype=np.float64)
        self._rng = np.random.default_rng(seed)
        self.scans = 0

    def scan(self, terrain: Terrain | None = None) -> tuple[FloatArray, FloatArray]:
        """One profile: abscissae ``(n,)`` and measured heights ``(n,)`` (work-site frame), of
        its terrain or of ``terrain`` (a copy of it cut elsewhere, the same x range)."""
        y = (self.terrain if terrain is None else terrain).surface_y(self._x)
        if self.spec.noise_m > 0.0:
            y = y + self._rng.normal(0.0, self.spec.noise_m, y.shape)
        self.scans += 1
        return self._x.copy(), y
