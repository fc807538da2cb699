"""Per-cycle telemetry in a preallocated ring buffer, written out outside the loop.

One numpy structured array of fixed ``capacity`` rows holds the last ``capacity`` cycles; when it
is full the oldest row is overwritten. The loop fills its own columns (:data:`LOOP_COLUMNS`:
``cycle``, ``t_s``, ``lateness_s``, ``exec_s``, ``overrun``); the step fills the columns its owner
declared (:class:`Column`) through a view fetched once outside the loop::

    tel = Telemetry(10_000, [Column("stroke_cmd_m", np.float64, (3,))])
    stroke = tel.column("stroke_cmd_m")          # outside the loop, once
    ...                                          # inside the step:
    stroke[tel.slot] = s_cmd                     # no allocation

Recording is allocation-free: every row is reset from a prebuilt blank row, and values go into
existing memory. :meth:`Telemetry.snapshot` and :meth:`Telemetry.write_npz` copy the rows out in
cycle order and belong outside the loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import DTypeLike, NDArray

from rt_runtime.errors import ConfigurationError

__all__ = ["LOOP_COLUMNS", "Column", "Telemetry"]


@dataclass(frozen=True, slots=True)
class Column:
    """One telemetry column.

    Attributes:
        name: Column name (a valid npz key; units as a suffix, e.g. ``stroke_fb_m``).
        dtype: numpy dtype of one element.
        shape: Per-row shape (``()`` for a scalar, ``(3,)`` for one value per axis).
        fill: Value of a row the step did not write (NaN for floats by default, else 0).
    """

    name: str
    dtype: DTypeLike = np.float64
    shape: tuple[int, ...] = ()
    fill: Any = None

    def fill_value(self) -> Any:
        """The blank value: ``fill`` if given, NaN for a float dtype, else 0."""
        if self.fill is not None:
            return self.fill
        return np.nan if np.issubdtype(np.dtype(self.dtype), np.floating) else 0


#: Columns the loop fills every cycle: the cycle's index on the period grid, its start time
#: (clock, s), lateness (start - deadline, s), step execution time (s) and overrun flag.
LOOP_COLUMNS: tuple[Column, ...] = (
    Column("cycle", np.int64, (), -1),
    Column("t_s", np.float64),
    Column("lateness_s", np.float64),
    Column("exec_s", np.float64),
    Column("overrun", np.bool_, (), False),
)


class Telemetry:
    """A fixed-capacity ring buffer of per-cycle records.

    Args:
        capacity: Rows kept (the last ``capacity`` cycles), >= 1.
        columns: The step's columns, added after :data:`LOOP_COLUMNS`.

    Raises:
        ConfigurationError: Capacity below 1, or a column name used twice (including the
            loop's own).

    Attributes:
        capacity: Rows kept.
        slot: Row of the current cycle (valid between :meth:`begin` and the next :meth:`begin`).
        count: Cycles recorded since creation or :meth:`clear`.
    """

    def __init__(self, capacity: int, columns: tuple[Column, ...] | list[Column] = ()) -> None:
        if capacity < 1:
            raise ConfigurationError(f"telemetry capacity is {capacity}; allowed: an integer >= 1")
        all_columns = tuple(LOOP_COLUMNS) + tuple(columns)
        names = [c.name for c in all_columns]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ConfigurationError(
                f"telemetry column names {dupes} are used twice; the loop owns "
                f"{[c.name for c in LOOP_COLUMNS]}"
            )
        self.capacity = int(capacity)
        self.columns: tuple[Column, ...] = all_columns
        dtype = np.dtype([(c.name, c.dtype, c.shape) for c in all_columns])
        self._data: NDArray[np.void] = np.zeros(self.capacity, dtype=dtype)
        self._blank: NDArray[np.void] = np.zeros((), dtype=dtype)
        for c in all_columns:
            self._blank[c.name] = c.fill_value()
        self._data[:] = self._blank
        self._views: dict[str, NDArray[Any]] = {c.name: self._data[c.name] for c in all_columns}
        self._cycle = self._views["cycle"]
        self._t = self._views["t_s"]
        self._lateness = self._views["lateness_s"]
        self._exec = self._views["exec_s"]
        self._overrun = self._views["overrun"]
        self.slot = 0
        self.count = 0
        self._hole = False

    def column(self, name: str) -> NDArray[Any]:
        """The writable view of one column, ``(capacity, *shape)``; fetch once, outside the loop.

        Args:
            name: Column name.

        Returns:
            A view into the ring buffer: write ``view[telemetry.slot] = value`` in the step.

        Raises:
            ConfigurationError: No such column.
        """
        try:
            return self._views[name]
        except KeyError:
            raise ConfigurationError(
                f"telemetry has no column {name!r}; columns: {sorted(self._views)}"
            ) from None

    def begin(self, cycle: int, t_s: float, lateness_s: float, overrun: bool) -> int:
        """Start the record of one cycle (the loop calls this). Safe inside the loop.

        Args:
            cycle: Cycle index on the period grid.
            t_s: Cycle start (clock, s).
            lateness_s: Start minus deadline (s).
            overrun: The cycle was an overrun.

        Returns:
            The row (:attr:`slot`) the step writes into.
        """
        slot = self.count % self.capacity
        self._data[slot] = self._blank
        self._cycle[slot] = cycle
        self._t[slot] = t_s
        self._lateness[slot] = lateness_s
        self._overrun[slot] = overrun
        self.slot = slot
        self.count += 1
        self._hole = False
        return slot

    def discard(self) -> None:
        """Drop the current record (a cycle that turned out to send nothing). Safe inside the
        loop; a later :meth:`end` of the same cycle writes into no kept row. Once the buffer
        has wrapped, the dropped row had overwritten the oldest one: that one is gone too."""
        if self.count > 0:
            self.count -= 1
            self._hole = self.count >= self.capacity

    def end(self, exec_s: float) -> None:
        """Finish the current record with the step's execution time (s). Safe inside the loop."""
        self._exec[self.slot] = exec_s

    @property
    def size(self) -> int:
        """Rows holding data (``min(count, capacity)``)."""
        return min(self.count, self.capacity)

    @property
    def dropped(self) -> int:
        """Cycles overwritten since the buffer wrapped."""
        return self.count - self.size

    def clear(self) -> None:
        """Forget every record; O(1).

        Only the counters are reset: :meth:`begin` blanks each row before it is written and
        :meth:`snapshot` reads written rows only. The loop clears when a run starts, after the
        drives are enabled, where blanking a whole task's buffer (200 000 rows: ~30 ms) would
        trip their 20 ms SYNC watchdog.
        """
        self.slot = 0
        self.count = 0
        self._hole = False

    def snapshot(self) -> dict[str, NDArray[Any]]:
        """Copies of every column in cycle order, oldest first (outside the loop).

        Returns:
            ``{name: (size, *shape) array}``.
        """
        n = self.size
        if self.count <= self.capacity:
            order = np.arange(n)
        else:
            start = self.count % self.capacity
            order = (np.arange(n) + start) % self.capacity
        if self._hole:
            order = order[1:]  # the oldest row was overwritten by a dropped one
        return {c.name: np.array(self._views[c.name][order]) for c in self.columns}

    def write_npz(self, path: str | Path) -> Path:
        """Write :meth:`snapshot` to a compressed ``.npz`` (outside the loop).

        Args:
            path: Output file.

        Returns:
            The path written (``.npz`` appended when missing, as numpy does).
        """
        out = Path(path)
        if out.suffix != ".npz":
            out = out.with_name(out.name + ".npz")
        out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out, **self.snapshot())  # type: ignore[arg-type]
        return out
