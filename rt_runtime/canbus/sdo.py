"""SDO client (CiA 301): expedited download/upload and segmented upload, for configuration.

Role: the master configures drives through it during boot, outside the loop. It is small and
written here instead of using ``canopen.sdo.SdoClient`` because that client waits on a queue fed
by ``canopen.Network``'s notifier thread with wall-clock timeouts: a second reader of the bus,
which would race the master for the frames its loop needs, and a clock of its own. This client
reads the bus only while a transfer runs, on the caller's thread, hands every frame that is not
its response to ``on_other`` (the master's dispatcher, so heartbeats and EMCYs seen during boot
are not lost), and measures its timeouts on the injected ``now_fn``. The abort meanings come from
canopen's table.

Frames (8 bytes, zero padded; ``idx`` little endian)::

    download expedited  C->S 0x600+id  [0x23|0x27|0x2B|0x2F, idx, sub, data 4..1 bytes]
                        S->C 0x580+id  [0x60, idx, sub, 0, 0, 0, 0]
    upload initiate     C->S           [0x40, idx, sub, 0, 0, 0, 0]
                        S->C           [0x43|0x47|0x4B|0x4F, idx, sub, data]  (expedited)
                                       [0x41, idx, sub, size u32]            (segmented)
    upload segment      C->S           [0x60|t<<4, 0 x7]
                        S->C           [t<<4 | n<<1 | c, 7 - n data bytes]
    abort               either         [0x80, idx, sub, abort code u32]

Timeout rule: a transfer fails when ``now_fn()`` passes its deadline, or when one wait on the
bus returns nothing after the whole remaining time (so a frozen simulated clock cannot hang it).
On timeout or a protocol error the client sends an abort (0x05040000 or 0x05040001) to the
server before raising.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import can
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.exceptions import SdoAbortedError as _CanopenAbort

from rt_runtime.canbus.pdo import COB_SDO_RX, COB_SDO_TX, od_variable
from rt_runtime.errors import CommunicationError, ConfigurationError

__all__ = [
    "SdoAbortedError",
    "SdoClient",
    "SdoProtocolError",
    "SdoTimeoutError",
    "abort_meaning",
    "download_command",
]

ABORT_TIMED_OUT = 0x05040000
ABORT_UNKNOWN_COMMAND = 0x05040001
ABORT_TOGGLE = 0x05030000

_MUX = struct.Struct("<BHB")
_U32 = struct.Struct("<I")


def abort_meaning(code: int) -> str:
    """CiA 301 meaning of an SDO abort code ("unknown abort code" if none)."""
    return _CanopenAbort.CODES.get(code, "unknown abort code")


def download_command(size: int) -> int:
    """Command byte of an expedited download of ``size`` (1..4) bytes with size indicated."""
    if not 1 <= size <= 4:
        raise ValueError(f"an expedited SDO download carries 1..4 bytes, not {size}")
    return 0x23 | (4 - size) << 2


class SdoAbortedError(CommunicationError):
    """The server (or this client) aborted a transfer.

    Attributes:
        node_id: The server's node id.
        index: Object index.
        subindex: Object sub-index.
        code: CiA 301 abort code.
        meaning: What the code means.
    """

    def __init__(self, node_id: int, index: int, subindex: int, code: int) -> None:
        self.node_id = node_id
        self.index = index
        self.subindex = subindex
        self.code = code
        self.meaning = abort_meaning(code)
        super().__init__(
            f"node {node_id} aborted SDO transfer of 0x{index:04X} sub {subindex}: "
            f"code 0x{code:08X} ({self.meaning})"
        )


class SdoTimeoutError(CommunicationError):
    """No SDO response came in time."""


class SdoProtocolError(CommunicationError):
    """The server answered with something CiA 301 does not allow at that point."""


class SdoClient:
    """SDO client of one node on a python-can bus.

    Args:
        bus: Any python-can bus.
        node_id: The server's node id (1..127).
        on_other: Receives every frame read during a transfer that is not this server's SDO
            response, with the ``now_fn()`` time it was read at.

    Not for the loop: transfers block until answered.
    """

    def __init__(
        self,
        bus: can.BusABC,
        node_id: int,
        on_other: Callable[[can.Message, float], None] | None = None,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"SDO server node id {node_id} is outside 1..127")
        self.bus = bus
        self.node_id = node_id
        self.on_other = on_other
        self._tx_id = COB_SDO_RX + node_id
        self._rx_id = COB_SDO_TX + node_id

    def _send(self, data: bytes | bytearray) -> None:
        frame = bytearray(8)
        frame[: len(data)] = data
        try:
            self.bus.send(can.Message(arbitration_id=self._tx_id, is_extended_id=False, data=frame))
        except can.CanError as exc:
            raise CommunicationError(
                f"sending an SDO request to node {self.node_id}: {exc}"
            ) from exc

    def _abort(self, index: int, subindex: int, code: int) -> None:
        self._send(_MUX.pack(0x80, index, subindex) + _U32.pack(code))

    def _response(
        self, index: int, subindex: int, what: str, now_fn: Callable[[], float], deadline_s: float
    ) -> bytearray:
        while True:
            remaining_s = deadline_s - now_fn()
            msg = self.bus.recv(timeout=remaining_s) if remaining_s > 0.0 else None
            if msg is None:
                self._abort(index, subindex, ABORT_TIMED_OUT)
                raise SdoTimeoutError(
                    f"no SDO response from node {self.node_id} to {what} of 0x{index:04X} "
                    f"sub {subindex} in time"
                )
            if msg.arbitration_id == self._rx_id and not msg.is_extended_id:
                data = bytearray(msg.data)
                if len(data) != 8:
                    self._abort(index, subindex, ABORT_UNKNOWN_COMMAND)
                    raise SdoProtocolError(
                        f"node {self.node_id} sent a {len(data)}-byte SDO response to {what} of "
                        f"0x{index:04X} sub {subindex}; CiA 301 requires 8 bytes"
                    )
                if data[0] == 0x80:
                    raise SdoAbortedError(
                        self.node_id, index, subindex, _U32.unpack_from(data, 4)[0]
                    )
                return data
            if self.on_other is not None:
                self.on_other(msg, now_fn())

    def _check_mux(self, data: bytearray, index: int, subindex: int, expected: int) -> None:
        cmd, idx, sub = _MUX.unpack_from(data)
        if idx != index or sub != subindex or cmd & 0xE0 != expected:
            self._abort(index, subindex, ABORT_UNKNOWN_COMMAND)
            raise SdoProtocolError(
                f"node {self.node_id} answered 0x{index:04X} sub {subindex} with command "
                f"0x{cmd:02X} for 0x{idx:04X} sub {sub}"
            )

    def download(
        self,
        index: int,
        subindex: int,
        data: bytes,
        now_fn: Callable[[], float],
        timeout_s: float,
    ) -> None:
        """Write 1..4 bytes with an expedited download.

        Args:
            index: Object index.
            subindex: Object sub-index.
            data: Little-endian value, 1..4 bytes.
            now_fn: Clock for the timeout (s).
            timeout_s: Time allowed for the answer.

        Raises:
            ValueError: ``data`` is empty or longer than 4 bytes.
            SdoAbortedError: The server refused (code and meaning in the message).
            SdoTimeoutError: No answer in time.
            SdoProtocolError: A malformed or mismatched answer.
            CommunicationError: The bus refused the frame.
        """
        command = download_command(len(data))
        deadline_s = now_fn() + timeout_s
        self._send(_MUX.pack(command, index, subindex) + data)
        response = self._response(index, subindex, "download", now_fn, deadline_s)
        self._check_mux(response, index, subindex, 0x60)

    def upload(
        self, index: int, subindex: int, now_fn: Callable[[], float], timeout_s: float
    ) -> bytes:
        """Read an object, expedited or segmented (strings).

        Args:
            index: Object index.
            subindex: Object sub-index.
            now_fn: Clock for the timeout (s).
            timeout_s: Time allowed for the whole transfer.

        Returns:
            The object's bytes.

        Raises:
            SdoAbortedError: The server refused.
            SdoTimeoutError: No answer in time.
            SdoProtocolError: A malformed or mismatched answer, or a toggle error.
            CommunicationError: The bus refused a frame.
        """
        deadline_s = now_fn() + timeout_s
        self._send(_MUX.pack(0x40, index, subindex))
        response = self._response(index, subindex, "upload", now_fn, deadline_s)
        self._check_mux(response, index, subindex, 0x40)
        cmd = response[0]
        expedited, sized = bool(cmd & 0x02), bool(cmd & 0x01)
        if expedited:
            n = 4 - ((cmd >> 2) & 0x03) if sized else 4
            return bytes(response[4 : 4 + n])
        size = _U32.unpack_from(response, 4)[0] if sized else None
        out = bytearray()
        toggle = 0
        while True:
            self._send(bytes((0x60 | toggle << 4,)))
            seg = self._response(index, subindex, "segmented upload", now_fn, deadline_s)
            if seg[0] & 0xE0 != 0x00:
                self._abort(index, subindex, ABORT_UNKNOWN_COMMAND)
                raise SdoProtocolError(
                    f"node {self.node_id} answered an upload segment of 0x{index:04X} sub "
                    f"{subindex} with command 0x{seg[0]:02X}"
                )
            if (seg[0] >> 4) & 1 != toggle:
                self._abort(index, subindex, ABORT_TOGGLE)
                raise SdoProtocolError(
                    f"node {self.node_id}: toggle bit error in the upload of 0x{index:04X} "
                    f"sub {subindex}"
                )
            out += seg[1 : 8 - ((seg[0] >> 1) & 0x07)]
            if seg[0] & 0x01:
                break
            toggle ^= 1
        if size is not None and len(out) != size:
            raise SdoProtocolError(
                f"node {self.node_id} announced {size} bytes for 0x{index:04X} sub {subindex} "
                f"and sent {len(out)}"
            )
        return bytes(out)

    def write(
        self,
        od: ObjectDictionary,
        index: int,
        subindex: int,
        value: int,
        now_fn: Callable[[], float],
        timeout_s: float,
    ) -> None:
        """Download ``value`` encoded with the object's data type from the EDS.

        Raises:
            ConfigurationError: The EDS has no such object, or the value does not fit its type.
            SdoAbortedError, SdoTimeoutError, SdoProtocolError, CommunicationError: As
                :meth:`download`.
        """
        var = od_variable(od, index, subindex)
        try:
            data = var.encode_raw(value)
        except (ValueError, TypeError) as exc:
            raise ConfigurationError(
                f"value {value} does not fit 0x{index:04X} sub {subindex} ({var.name}): {exc}"
            ) from exc
        self.download(index, subindex, bytes(data), now_fn, timeout_s)

    def read(
        self,
        od: ObjectDictionary,
        index: int,
        subindex: int,
        now_fn: Callable[[], float],
        timeout_s: float,
    ) -> int | float | str | bytes:
        """Upload an object and decode it with its data type from the EDS.

        Raises:
            ConfigurationError: The EDS has no such object, or the answer does not fit its type.
            SdoAbortedError, SdoTimeoutError, SdoProtocolError, CommunicationError: As
                :meth:`upload`.
        """
        var = od_variable(od, index, subindex)
        data = self.upload(index, subindex, now_fn, timeout_s)
        if var.fixed_size and len(data) > len(var) // 8:
            # CiA 301 lets a server answer a short object with 4 bytes; keep the object's size.
            data = data[: len(var) // 8]
        try:
            value = var.decode_raw(data)
        except Exception as exc:  # canopen raises its own ObjectDictionaryError here
            raise ConfigurationError(
                f"node {self.node_id} sent {data.hex()} for 0x{index:04X} sub {subindex} "
                f"({var.name}), which does not decode: {exc}"
            ) from exc
        return bytes(value) if isinstance(value, bytearray) else value
