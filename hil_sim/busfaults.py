"""Bus faults between the master and the HIL's nodes: frames lost, late, swapped, cut short,
garbled or doubled, error frames, the adapter bus-off, the bus unplugged.

Role: the fault model of the wire (:class:`~hil_sim.sim.FaultKind` with ``layer == "bus"``). A
transport passes every frame through :class:`BusFaults` on its way, master to HIL
(:meth:`BusFaults.to_hil`) and HIL to master (:meth:`BusFaults.to_master`), and takes the frames
whose delay has run out (:meth:`BusFaults.due`). Clock-free (every call takes ``now_s``) and
seeded (:class:`random.Random`), so a lockstep run with a bus fault is deterministic.

Targets: a node id (1..127) or None for the whole bus. A node's frames are those whose COB-ID
carries its id (``id & 0x7F``, from 0x081 up: EMCY, PDOs, SDO, heartbeat); the broadcasts
(NMT, SYNC, the master's heartbeat) are touched only by a fault on the whole bus. A fault
injected on a node whose frames do not pass (a frame kind that is only ever sent the other way,
say) waits for the next one that does.

What each kind does (from its injection until :meth:`BusFaults.clear`):

* ``FRAME_LOSS`` (rate 0..1): each frame of the target, either way, is lost with that
  probability;
* ``FRAME_DELAY`` (ms): the target's next frame, either way, arrives that much later;
* ``FRAME_REORDER``: the target's next two frames in one direction arrive swapped;
* ``FRAME_TRUNCATED``: the target's next frame to the master arrives one byte short;
* ``FRAME_GARBAGE``: the target's next frame to the master carries random bytes (same length):
  what a faulty device sends (a frame garbled on the wire fails its CRC and is not delivered);
* ``FRAME_DUPLICATE``: the target's next frame, either way, arrives twice;
* ``ERROR_FRAMES`` (count): one error frame to the master per call of :meth:`error_frames_due`
  (the transport calls it once a period) until that many went out;
* ``BUS_OFF``: the master's adapter is bus-off: the transport makes its sends raise
  (:attr:`BusFaults.bus_off`);
* ``BUS_UNPLUGGED`` (s): nothing passes either way for that long.

Counts: :attr:`BusFaults.affected` counts the frames each kind touched (the campaign reports
them beside the master's own counts).
"""

from __future__ import annotations

import math
import random
from collections import Counter

from firmware_models.drive import Frame
from hil_sim.sim import FaultKind

__all__ = ["DEFAULT_PARAMS", "BusFaults"]

#: A bus fault's parameter when none is given: loss rate, delay (ms), error frames, unplugged (s).
DEFAULT_PARAMS = {
    FaultKind.FRAME_LOSS: 0.02,
    FaultKind.FRAME_DELAY: 5.0,
    FaultKind.ERROR_FRAMES: 5.0,
    FaultKind.BUS_UNPLUGGED: 0.2,
}
_TO_HIL, _TO_MASTER = 0, 1
#: The one-shot kinds: they act on the target's next frame(s), then are spent.
_ONE_SHOT = (
    FaultKind.FRAME_DELAY,
    FaultKind.FRAME_REORDER,
    FaultKind.FRAME_TRUNCATED,
    FaultKind.FRAME_GARBAGE,
    FaultKind.FRAME_DUPLICATE,
)


class BusFaults:
    """The wire's faults (see the module docstring). One owner (the transport).

    Args:
        seed: Seed of the loss draws and the garbage bytes.

    Attributes:
        bus_off: The master's adapter is bus-off (its sends must raise).
        affected: Frames (or error frames) each kind touched, by kind label.
    """

    def __init__(self, seed: int = 0) -> None:
        self._rng = random.Random(seed)
        self.bus_off = False
        self.affected: Counter[str] = Counter()
        self._loss: list[tuple[int | None, float]] = []
        self._armed: list[tuple[FaultKind, int | None, float]] = []
        self._held: list[tuple[float, int, Frame]] = []
        self._swap: list[tuple[int, Frame]] = []
        self._unplugged_until = -math.inf
        self._error_frames = 0

    def inject(self, kind: FaultKind, node: int | None, param: float | None, now_s: float) -> None:
        """Switch a bus fault on at ``now_s`` (``param`` None: :data:`DEFAULT_PARAMS`).

        Raises:
            ValueError: Not a bus fault, a node id outside 1..127, or a parameter outside its
                kind's range (a rate in 0..1, a delay, count or time > 0).
        """
        if kind.layer != "bus":
            raise ValueError(f"{kind.label} is a {kind.layer} fault, not the bus's")
        if node is not None and not 1 <= node <= 127:
            raise ValueError(f"node id {node} must be 1..127")
        value = DEFAULT_PARAMS.get(kind, 0.0) if param is None else float(param)
        if kind is FaultKind.FRAME_LOSS:
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"frame_loss rate {value} must be in 0..1")
            self._loss.append((node, value))
        elif kind in DEFAULT_PARAMS and not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{kind.label} parameter {value} must be finite and > 0")
        elif kind is FaultKind.ERROR_FRAMES:
            self._error_frames += max(1, round(value))
        elif kind is FaultKind.BUS_OFF:
            self.bus_off = True
        elif kind is FaultKind.BUS_UNPLUGGED:
            self._unplugged_until = now_s + value
        else:
            self._armed.append((kind, node, value))

    def clear(self) -> None:
        """Every bus fault off; frames held back are delivered at their time still."""
        self._loss.clear()
        self._armed.clear()
        self.bus_off = False
        self._unplugged_until = -math.inf
        self._error_frames = 0
        for way, frame in self._swap:
            self._held.append((-math.inf, way, frame))
        self._swap.clear()

    @property
    def active(self) -> bool:
        """Any fault is on or any frame is held back."""
        return bool(
            self._loss or self._armed or self._held or self._swap or self.bus_off
            or self._error_frames or self._unplugged_until > -math.inf
        )  # fmt: skip

    def unplugged(self, now_s: float) -> bool:
        """The bus is unplugged at ``now_s``."""
        return now_s < self._unplugged_until

    def to_hil(self, frame: Frame, now_s: float) -> list[Frame]:
        """What reaches the HIL now of one frame the master sent (none, it, or it twice)."""
        return self._pass(frame, _TO_HIL, now_s)

    def to_master(self, frame: Frame, now_s: float) -> list[Frame]:
        """What reaches the master now of one frame the HIL sent."""
        return self._pass(frame, _TO_MASTER, now_s)

    def due(self, now_s: float) -> tuple[list[Frame], list[Frame]]:
        """Frames held back whose time has come: ``(to the HIL, to the master)``."""
        if not self._held:
            return [], []
        out: tuple[list[Frame], list[Frame]] = ([], [])
        keep = []
        for entry in self._held:
            if entry[0] <= now_s:
                out[entry[1]].append(entry[2])
            else:
                keep.append(entry)
        self._held = keep
        return out

    def error_frames_due(self) -> bool:
        """One error frame goes to the master now (call once a period)."""
        if self._error_frames <= 0:
            return False
        self._error_frames -= 1
        self.affected[FaultKind.ERROR_FRAMES.label] += 1
        return True

    # -- the frame path -------------------------------------------------------------------------

    def _pass(self, frame: Frame, way: int, now_s: float) -> list[Frame]:
        if now_s < self._unplugged_until:
            self.affected[FaultKind.BUS_UNPLUGGED.label] += 1
            return []
        node = _node_of(frame[0])
        for target, rate in self._loss:
            if _hits(target, node) and self._rng.random() < rate:
                self.affected[FaultKind.FRAME_LOSS.label] += 1
                return []
        if not self._armed:
            return [frame]
        for i, (kind, target, value) in enumerate(self._armed):
            if not _hits(target, node):
                continue
            if kind in (FaultKind.FRAME_TRUNCATED, FaultKind.FRAME_GARBAGE) and way != _TO_MASTER:
                continue
            if kind is FaultKind.FRAME_REORDER:
                return self._reorder(i, frame, way)
            del self._armed[i]
            self.affected[kind.label] += 1
            cob, data = frame
            if kind is FaultKind.FRAME_DELAY:
                self._held.append((now_s + value * 1e-3, way, frame))
                return []
            if kind is FaultKind.FRAME_TRUNCATED:
                return [(cob, data[:-1])] if data else [frame]
            if kind is FaultKind.FRAME_GARBAGE:
                return [(cob, bytes(self._rng.randrange(256) for _ in data))]
            return [frame, frame]
        return [frame]

    def _reorder(self, i: int, frame: Frame, way: int) -> list[Frame]:
        """The first frame of the pair is held; the second goes, then the first."""
        for j, (held_way, held) in enumerate(self._swap):
            if held_way == way:
                del self._swap[j]
                del self._armed[i]
                self.affected[FaultKind.FRAME_REORDER.label] += 2
                return [frame, held]
        self._swap.append((way, frame))
        return []


def _node_of(cob: int) -> int | None:
    """The node id a COB-ID carries, None for the broadcasts (NMT, SYNC, 0x000-0x080)."""
    return cob & 0x7F if cob > 0x080 and cob & 0x7F else None


def _hits(target: int | None, node: int | None) -> bool:
    return target is None or target == node
