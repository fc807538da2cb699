"""Demonstrations in, as a rig records them: CSV files and CAN traces, validated.

Role: step 1 of teach-and-plan (Zhao et al., II-B). A demonstration is one trenching cycle dug
by an operator, as joint angles over time (:class:`DemoRecord`: swing first, rad). Two formats:

* CSV with a header row: ``t_s`` and one column per joint in degrees (``swing_deg``,
  ``boom_deg``, ``stick_deg``, ``bucket_deg`` on a rig with swing); other columns are ignored,
  a missing joint column is an error.
* The CAN trace of a manual run (python-can's BLF or ASC, as the project writes them): at every
  SYNC (0x080) each drive answers with TPDO1 (0x180 + node: 0x6064 position actual, 0x606C
  velocity actual, i32 each). The arm's drives report the cylinder stroke in micrometres; their
  joint angles come through the stroke-to-joint map (:func:`rt_runtime.actuation.stroke_to_joint`).
  The swing drive (its own node, 4 on the field excavator) reports the swing angle in
  microradians (the actuator of the swing axis is the swing angle itself). One sample per
  SYNC, at the SYNC's time, once every drive's TPDO1 for it is in.

Validation (:func:`validate`), the same for both formats; the first broken rule raises
:class:`DemonstrationError` naming the file, the row (CSV: the line number, header = 1; trace:
the SYNC's number from 1 and its frame index) and the rule. Rules:

* at least :data:`MIN_SAMPLES` samples;
* time strictly increasing (neither unsorted nor repeated);
* every value a finite number;
* every joint within its range;
* no jump faster than the joint can move: ``|q[i] - q[i-1]| <= V * dt + JUMP_ALLOWANCE_RAD``
  (the allowance covers the sensors' noise, 0.5 deg: ten times the noise of the rigs' angle
  sensors).

Writers (:func:`write_trace`): a demonstration as the CAN trace a rig would record (SYNC, then
each drive's TPDO1), for tests and for HIL-less runs. Outside the loop.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime import actuation
from rt_runtime.canbus.pdo import COB_SYNC, COB_TPDO1, TPDO1
from rt_runtime.errors import ConfigurationError
from rt_runtime.rig import Rig

__all__ = [
    "JUMP_ALLOWANCE_RAD",
    "MIN_SAMPLES",
    "DemoRecord",
    "DemonstrationError",
    "column_names",
    "read_csv",
    "read_demo",
    "read_trace",
    "validate",
    "write_trace",
]

FloatArray = NDArray[np.float64]

#: Fewest samples a demonstration may have (a second at 100 Hz is far less than a cycle).
MIN_SAMPLES = 50
#: Sample-to-sample change allowed beyond what the joint's velocity limit covers (rad): sensor
#: noise, 0.5 deg.
JUMP_ALLOWANCE_RAD = math.radians(0.5)
#: Actuator units on the bus: millionths of the SI unit (um of stroke, urad of swing).
_BUS_SCALE = 1e6
_TRACE_SUFFIXES = (".blf", ".asc")


class DemonstrationError(ConfigurationError):
    """A demonstration file breaks a rule; the message names the file, the row and the rule.

    Attributes:
        path: The file.
        row: Row (CSV line, header = 1; trace: SYNC number from 1), or 0 for the whole file.
        rule: Short name of the rule broken (``columns``, ``samples``, ``time``, ``number``,
            ``range``, ``jump``, ``frames``).
    """

    def __init__(self, path: str | Path, row: int, rule: str, message: str) -> None:
        self.path = str(path)
        self.row = row
        self.rule = rule
        where = f"{path}, row {row}" if row else f"{path}"
        super().__init__(f"{where}: rule '{rule}': {message}")


@dataclass(frozen=True, slots=True, eq=False)
class DemoRecord:
    """One validated demonstration.

    Attributes:
        path: Where it came from.
        t_s: ``(N,)`` sample times, s, strictly increasing (as recorded: not shifted to 0).
        q_rad: ``(N, J)`` joint angles, swing first, rad.
        rows: ``(N,)`` the row of each sample in the file (for messages).
    """

    path: str
    t_s: FloatArray
    q_rad: FloatArray
    rows: NDArray[np.int64]

    @property
    def duration_s(self) -> float:
        """Length of the demonstration, s."""
        return float(self.t_s[-1] - self.t_s[0])


def column_names(rig: Rig) -> tuple[str, ...]:
    """The CSV joint columns of ``rig``: ``<joint>_deg``, swing first."""
    return tuple(f"{n}_deg" for n in rig.joint_names)


def _joint_limits(rig: Rig) -> tuple[FloatArray, FloatArray, FloatArray]:
    joints = ((rig.swing.joint,) if rig.swing is not None else ()) + rig.joints
    return (
        np.array([j.min_rad for j in joints]),
        np.array([j.max_rad for j in joints]),
        np.array([j.velocity_max_rad_s for j in joints]),
    )


def validate(rig: Rig, path: str | Path, t_s: ArrayLike, q_rad: ArrayLike,
             rows: ArrayLike | None = None) -> DemoRecord:
    """Check one demonstration against the rules of the module; return it as a record.

    Args:
        rig: The rig it was dug on.
        path: The file (for messages).
        t_s: ``(N,)`` times, s.
        q_rad: ``(N, J)`` joint angles, swing first, rad.
        rows: ``(N,)`` the file row of each sample (default: 2, 3, ...: a CSV below its header).

    Raises:
        DemonstrationError: The first broken rule, with its row.
    """
    t = np.asarray(t_s, dtype=np.float64)
    q = np.asarray(q_rad, dtype=np.float64)
    r = np.arange(2, t.shape[0] + 2) if rows is None else np.asarray(rows, dtype=np.int64)
    names = rig.joint_names
    if q.ndim != 2 or q.shape != (t.shape[0], len(names)):
        raise DemonstrationError(
            path, 0, "columns", f"needs {len(names)} joints ({', '.join(names)}) per sample; "
            f"got shape {q.shape}"
        )
    if t.shape[0] < MIN_SAMPLES:
        raise DemonstrationError(
            path, 0, "samples", f"{t.shape[0]} samples; a demonstration needs at least "
            f"{MIN_SAMPLES}"
        )
    finite = np.isfinite(t) & np.all(np.isfinite(q), axis=1)
    if not np.all(finite):
        i = int(np.argmin(finite))
        raise DemonstrationError(
            path, int(r[i]), "number", "a value is NaN or infinite; every time and angle must "
            "be a finite number"
        )
    dt = np.diff(t)
    if np.any(dt <= 0.0):
        i = int(np.argmax(dt <= 0.0)) + 1
        kind = "repeated" if dt[i - 1] == 0.0 else "earlier than the row before"
        raise DemonstrationError(
            path, int(r[i]), "time", f"t_s {t[i]:.6g} s is {kind} ({t[i - 1]:.6g} s); time "
            "must increase strictly"
        )
    lo, hi, v = _joint_limits(rig)
    out = (q < lo) | (q > hi)
    if np.any(out):
        i, j = (int(x) for x in np.argwhere(out)[0])
        raise DemonstrationError(
            path, int(r[i]), "range", f"{names[j]} at {math.degrees(q[i, j]):.4f} deg is "
            f"outside its range [{math.degrees(lo[j]):.4f}, {math.degrees(hi[j]):.4f}] deg"
        )
    step = np.abs(np.diff(q, axis=0))
    allowed = v[None, :] * dt[:, None] + JUMP_ALLOWANCE_RAD
    jump = step > allowed
    if np.any(jump):
        i, j = (int(x) for x in np.argwhere(jump)[0])
        raise DemonstrationError(
            path, int(r[i + 1]), "jump", f"{names[j]} moves {math.degrees(step[i, j]):.4f} deg "
            f"in {dt[i]:.6g} s; the joint can move at most "
            f"{math.degrees(allowed[i, j]):.4f} deg (its velocity limit "
            f"{math.degrees(v[j]):.4g} deg/s, plus {math.degrees(JUMP_ALLOWANCE_RAD):g} deg "
            "for sensor noise)"
        )
    return DemoRecord(path=str(path), t_s=t, q_rad=q, rows=r)


def read_csv(rig: Rig, path: str | Path) -> DemoRecord:
    """Read and validate one CSV demonstration (module docstring: format and rules).

    Raises:
        DemonstrationError: Unreadable file, a missing joint column, a cell that is not a
            number, or a broken rule; names the file and the row.
    """
    p = Path(path)
    want = ("t_s", *column_names(rig))
    try:
        with p.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise DemonstrationError(p, 1, "columns", "empty file; the first row must be "
                                         f"the header {','.join(want)}")
            header = [h.strip() for h in header]
            missing = [c for c in want if c not in header]
            if missing:
                raise DemonstrationError(
                    p, 1, "columns", f"missing column(s) {', '.join(missing)}; needed "
                    f"{', '.join(want)} (others are ignored)"
                )
            idx = [header.index(c) for c in want]
            values: list[list[float]] = []
            rows: list[int] = []
            for line, cells in enumerate(reader, start=2):
                if not cells or all(not c.strip() for c in cells):
                    continue
                try:
                    values.append([float(cells[i]) for i in idx])
                except (ValueError, IndexError):
                    raise DemonstrationError(
                        p, line, "number", f"expected numbers in columns {', '.join(want)}; "
                        f"got {cells!r}"
                    ) from None
                rows.append(line)
    except OSError as e:
        raise DemonstrationError(p, 0, "file", f"cannot be read ({e.strerror or e})") from None
    except csv.Error as e:
        raise DemonstrationError(p, 0, "file", f"is not CSV text ({e})") from None
    except UnicodeDecodeError:
        raise DemonstrationError(p, 0, "file", "is not UTF-8 text (a CSV demonstration is "
                                 "text)") from None
    a = np.array(values, dtype=np.float64).reshape(-1, len(want))
    return validate(rig, p, a[:, 0], np.radians(a[:, 1:]), rows)


def _axis_nodes(rig: Rig) -> list[tuple[str, int]]:
    return [(n, rig.can.node_id(n)) for n in rig.joint_names]


def read_trace(rig: Rig, path: str | Path) -> DemoRecord:
    """Read and validate one CAN trace (BLF or ASC) of a manual run.

    A sample per SYNC: the SYNC's timestamp, and the joint angles from the TPDO1 of every drive
    that follows it before the next SYNC. TPDO1s before the first SYNC are ignored. SYNCs before
    the first one every drive answers (the drives not yet operational) and after the last one
    are skipped; one in between that a drive does not answer is an error. Rows are the SYNCs'
    numbers in the trace, from 1.

    Raises:
        DemonstrationError: Unknown suffix, unreadable file, no SYNC, a drive missing after a
            SYNC, a stroke outside its cylinder's travel, or a broken rule; names the file and
            the SYNC ("row") and the frame.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in _TRACE_SUFFIXES:
        raise DemonstrationError(p, 0, "file", f"suffix {suffix!r}: a CAN trace is .blf or .asc")
    if not p.is_file():
        raise DemonstrationError(p, 0, "file", "no such file")
    axes = _axis_nodes(rig)
    node_index = {COB_TPDO1 + node: i for i, (_, node) in enumerate(axes)}
    n = len(axes)
    times: list[float] = []
    raw: list[list[float]] = []
    frames: list[int] = []
    unpack = TPDO1.codec.unpack_from
    try:
        reader = can.BLFReader(str(p)) if suffix == ".blf" else can.ASCReader(str(p))
        with reader:
            for k, msg in enumerate(reader):
                cob = msg.arbitration_id
                if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                    continue
                if cob == COB_SYNC and len(msg.data) == 0:
                    times.append(float(msg.timestamp))
                    raw.append([math.nan] * n)
                    frames.append(k)
                elif raw and cob in node_index:
                    if len(msg.data) != TPDO1.size:
                        raise DemonstrationError(
                            p, len(times), "frames", f"frame {k}: TPDO1 0x{cob:03X} has "
                            f"{len(msg.data)} bytes; TPDO1 is {TPDO1.size} (0x6064, 0x606C)"
                        )
                    raw[-1][node_index[cob]] = float(unpack(bytes(msg.data))[0])
    except DemonstrationError:
        raise
    except Exception as e:  # python-can's readers raise any type on a malformed file
        raise DemonstrationError(p, 0, "file", f"not a readable {suffix[1:].upper()} trace "
                                 f"({type(e).__name__}: {e})") from None
    answered = np.isfinite(np.array(raw, dtype=np.float64).reshape(-1, n))
    complete = np.flatnonzero(answered.all(axis=1))
    if complete.size == 0:
        raise DemonstrationError(
            p, 0, "frames", "no SYNC (0x080) answered by every drive's TPDO1: not the trace of "
            "a run of this rig (drives on nodes "
            + ", ".join(f"{name} {node}" for name, node in axes) + ")"
        )
    # Before the first answered SYNC the drives were not yet operational (boot), after the last
    # the trace stopped; in between every drive answers every SYNC.
    first, last = int(complete[0]), int(complete[-1])
    gaps = np.flatnonzero(~answered[first : last + 1].all(axis=1))
    if gaps.size:
        i = first + int(gaps[0])
        lost = [f"{name} (node {node})" for (name, node), ok in zip(axes, answered[i], strict=True)
                if not ok]
        raise DemonstrationError(
            p, i + 1, "frames", f"SYNC at frame {frames[i]} has no TPDO1 from "
            f"{', '.join(lost)}; every drive answers every SYNC"
        )
    times = times[first : last + 1]
    raw = raw[first : last + 1]
    frames = frames[first : last + 1]
    sync_rows = np.arange(first + 1, last + 2)
    a = np.array(raw) / _BUS_SCALE
    q = np.empty_like(a)
    names = rig.joint_names
    arm = [names.index(x) for x in ("boom", "stick", "bucket")]
    strokes = a[:, arm]
    lo, hi = actuation.stroke_limits(rig)
    bad = (strokes < lo - 1e-9) | (strokes > hi + 1e-9)
    if np.any(bad):
        i, j = (int(x) for x in np.argwhere(bad)[0])
        raise DemonstrationError(
            p, int(sync_rows[i]), "range", f"frame {frames[i]}: {names[arm[j]]} cylinder stroke "
            f"{strokes[i, j] * 1e3:.3f} mm is outside its travel [0, {hi[j] * 1e3:.3f}] mm"
        )
    q[:, arm] = actuation.stroke_to_joint(rig, np.clip(strokes, lo, hi), check_limits=False)
    if rig.swing is not None:
        q[:, names.index("swing")] = a[:, names.index("swing")]
    return validate(rig, p, np.array(times), q, sync_rows)


def read_demo(rig: Rig, path: str | Path) -> DemoRecord:
    """Read one demonstration by its suffix: ``.csv``, ``.blf`` or ``.asc``.

    Raises:
        DemonstrationError: Another suffix, or as :func:`read_csv` / :func:`read_trace`.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return read_csv(rig, p)
    if suffix in _TRACE_SUFFIXES:
        return read_trace(rig, p)
    raise DemonstrationError(p, 0, "file", f"suffix {suffix!r}: a demonstration is a .csv file "
                             "or a CAN trace (.blf, .asc)")


def write_trace(rig: Rig, path: str | Path, t_s: ArrayLike, q_rad: ArrayLike,
                *, start_unix_s: float = 1.7e9) -> Path:
    """Write joint angles as the CAN trace a rig records: per sample a SYNC, then each
    drive's TPDO1 (position actual from the joint angles: stroke in um, swing in urad;
    velocity actual by finite differences), 50 us apart, in node order.

    Args:
        rig: The rig.
        path: ``.blf`` or ``.asc``.
        t_s: ``(N,)`` times, s.
        q_rad: ``(N, J)`` joint angles, swing first.
        start_unix_s: Timestamp of the first SYNC (Unix s).

    Raises:
        ConfigurationError: Another suffix or a joint outside its range.
    """
    p = Path(path)
    if p.suffix.lower() not in _TRACE_SUFFIXES:
        raise ConfigurationError(f"trace file {p}: suffix must be .blf or .asc")
    t = np.asarray(t_s, dtype=np.float64)
    q = np.asarray(q_rad, dtype=np.float64)
    names = rig.joint_names
    arm = [names.index(x) for x in ("boom", "stick", "bucket")]
    pos = np.empty_like(q)
    pos[:, arm] = actuation.joint_to_stroke(rig, q[:, arm])
    if rig.swing is not None:
        pos[:, names.index("swing")] = q[:, names.index("swing")]
    vel = np.gradient(pos, t, axis=0) if t.shape[0] > 1 else np.zeros_like(pos)
    pos_i = np.rint(pos * _BUS_SCALE).astype(np.int64)
    vel_i = np.rint(vel * _BUS_SCALE).astype(np.int64)
    order = sorted(range(len(names)), key=lambda j: rig.can.node_id(names[j]))
    p.parent.mkdir(parents=True, exist_ok=True)
    logger = can.Logger(str(p))
    try:
        for i in range(t.shape[0]):
            ts = start_unix_s + float(t[i])
            logger.on_message_received(
                can.Message(timestamp=ts, arbitration_id=COB_SYNC, is_extended_id=False,
                            data=b"", is_rx=False)
            )
            for k, j in enumerate(order):
                node = rig.can.node_id(names[j])
                logger.on_message_received(
                    can.Message(
                        timestamp=ts + 50e-6 * (k + 1),
                        arbitration_id=COB_TPDO1 + node,
                        is_extended_id=False,
                        data=TPDO1.codec.pack(int(pos_i[i, j]), int(vel_i[i, j])),
                    )
                )
    finally:
        logger.stop()
    return p
