"""The CAN bridge over 127.0.0.1: python-can-remote's wire protocol and the runtime's end.

Role: the transport between the runtime and the real-time HIL process (DESIGN.md "Loop, HIL and
time"). It speaks python-can-remote's protocol (a websocket, subprotocol
``can.binary+json.v1``: a JSON ``bus_request`` / ``bus_response`` exchange, then one binary
websocket message per frame: type byte 1, ``>dIBB`` timestamp, arbitration id, DLC, flags, then
the data), so python-can-remote's own ``RemoteBus`` and ``RemoteServer`` talk to either end.

This module holds the protocol's pieces both ends use (constants, frame flags, websocket
framing and parsing) and the runtime's end, :class:`BridgeBus`, a python-can backend (``send``,
``_recv_internal``, ``shutdown``). The server end is the real-time HIL's
:class:`hil_sim.harness.bridge.Bridge`, polled by the HIL's own loop.

Why not python-can-remote's classes themselves: per frame they cost what a rig's socketcan does
not. Its server forwards each frame through python-can's ``virtual`` bus (a ``copy.deepcopy`` of
the message per receiver) and two threads that take the interpreter from the HIL's loop; its
client masks byte by byte in Python, waits in ``select`` before every frame and overrides
``recv`` (so python-can's filters never apply). :class:`BridgeBus` has no thread: one ``recv``
takes every frame the socket holds (without a ``select`` when they are already there),
``send`` is one ``sendall`` and ``send_many`` one ``sendall`` for all its frames (the master's
RPDO1s and SYNC of a cycle).

Masking: RFC 6455 has a client mask every frame with a fresh, unpredictable 32-bit key. The
key protects intermediaries (caching proxies) from bytes that an untrusted script in a browser
chose (RFC 6455 10.3). None of that exists here: the bridge connects to 127.0.0.1 only
(:data:`HOST`), no proxy is between the ends, and the runtime builds every byte. So the
runtime's end masks with the constant key :data:`CLIENT_MASK_KEY` (four zero bytes): each
frame has the mask bit and a key, so any websocket server (python-can-remote's included) takes
and unmasks it, and XOR with it is the identity, so the client skips it and
:func:`ws_messages` skips it too (design notes H4 has what a fresh key cost). Frames masked
with any other key (python-can-remote's ``RemoteBus``) are unmasked as RFC 6455 says.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import json
import os
import select
import socket
import struct
import time
from collections.abc import Sequence

import can
from can_remote.websocket import get_accept_key

__all__ = [
    "BINARY_MESSAGE_TYPE",
    "CLIENT_MASK_KEY",
    "FLAG_BRS",
    "FLAG_ERROR",
    "FLAG_ESI",
    "FLAG_EXTENDED",
    "FLAG_FD",
    "FLAG_REMOTE",
    "FRAME",
    "HOST",
    "OP_BINARY",
    "OP_CLOSE",
    "OP_PING",
    "OP_PONG",
    "OP_TEXT",
    "PROTOCOL",
    "PROTOCOL_JSON",
    "BridgeBus",
    "BridgeError",
    "RxFrame",
    "flagged_message",
    "message_flags",
    "ws_frame",
    "ws_messages",
]

#: The only address the bridge binds or connects to.
HOST = "127.0.0.1"
#: python-can-remote's binary subprotocol (frames as binary messages).
PROTOCOL = "can.binary+json.v1"
#: python-can-remote's JSON-only subprotocol (frames as ``message`` events).
PROTOCOL_JSON = "can.json.v1"

#: One frame at the HIL's end: ``(timestamp_s, arbitration_id, data, flags)``; ``timestamp_s``
#: is the sender's stamp (``time.time()`` at its send, 0.0 when unstamped), ``flags`` a
#: combination of :data:`FLAG_EXTENDED` ... :data:`FLAG_ESI`.
RxFrame = tuple[float, int, bytes, int]

FLAG_EXTENDED = 0x1
FLAG_REMOTE = 0x2
FLAG_ERROR = 0x4
FLAG_FD = 0x8
FLAG_BRS = 0x10
FLAG_ESI = 0x20

#: A binary frame message's head: message type (1), timestamp, arbitration id, DLC, flags; the
#: data follows.
FRAME = struct.Struct(">BdIBB")
BINARY_MESSAGE_TYPE = 1

#: Websocket opcodes (RFC 6455 5.2).
OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x1, 0x2, 0x8, 0x9, 0xA

#: The masking key of every frame the runtime's end sends (see the module docstring): XOR with
#: it is the identity, so neither end spends work on it.
CLIENT_MASK_KEY = bytes(4)

#: A client's whole binary frame of a CAN frame: websocket opcode byte, mask bit and length
#: (<= 125), masking key, then :data:`FRAME`; the data follows.
_WS_CLIENT_FRAME = struct.Struct(">BB4s" + FRAME.format.lstrip(">"))
_LEN16 = struct.Struct(">H")
_LEN64 = struct.Struct(">Q")
_READ_SIZE = 1 << 16
#: Longest wait of :meth:`BridgeBus.shutdown` for the server's websocket close.
CLOSE_WAIT_S = 0.5


class BridgeError(can.CanOperationError):
    """The bridge's connection failed or the peer broke the protocol."""


# -- the protocol, both ends ------------------------------------------------------------------


def ws_frame(opcode: int, payload: bytes | bytearray, *, mask: bool) -> bytes:
    """One unfragmented websocket frame (RFC 6455 5.2); a client masks (with
    :data:`CLIENT_MASK_KEY`, see the module docstring), a server does not."""
    n = len(payload)
    bit = 0x80 if mask else 0
    if n <= 125:
        head = bytes((0x80 | opcode, bit | n))
    elif n <= 0xFFFF:
        head = bytes((0x80 | opcode, bit | 126)) + _LEN16.pack(n)
    else:
        head = bytes((0x80 | opcode, bit | 127)) + _LEN64.pack(n)
    return head + CLIENT_MASK_KEY + payload if mask else head + payload


def _client_frame(msg: can.Message) -> bytes:
    """A message as the client's masked binary websocket frame: one struct pack when it fits
    the one-byte websocket length (a CAN frame's does: 15 + at most 64 bytes)."""
    data = bytes(msg.data)
    n = FRAME.size + len(data)
    flags = message_flags(msg)
    if n > 125:
        head = FRAME.pack(BINARY_MESSAGE_TYPE, msg.timestamp, msg.arbitration_id, msg.dlc, flags)
        return ws_frame(OP_BINARY, head + data, mask=True)
    return _WS_CLIENT_FRAME.pack(
        0x80 | OP_BINARY, 0x80 | n, CLIENT_MASK_KEY, BINARY_MESSAGE_TYPE,
        msg.timestamp, msg.arbitration_id, msg.dlc, flags,
    ) + data  # fmt: skip


def _xor(payload: bytes | bytearray, key: bytes | bytearray) -> bytes:
    """``payload`` XOR the repeated 4-byte ``key`` (websocket masking), as one integer XOR."""
    n = len(payload)
    if n == 0:
        return b""
    pad = (bytes(key) * (n // 4 + 1))[:n]
    return (int.from_bytes(payload, "big") ^ int.from_bytes(pad, "big")).to_bytes(n, "big")


def ws_messages(buf: bytearray) -> list[tuple[int, bytes]]:
    """Every complete websocket message ``(opcode, payload)`` at the head of ``buf``, unmasked,
    in order, and removed from ``buf``; an incomplete one stays for the next call.

    Messages are unfragmented (python-can-remote never fragments).
    """
    out: list[tuple[int, bytes]] = []
    pos = 0
    end = len(buf)
    while end - pos >= 2:
        b0, b1 = buf[pos], buf[pos + 1]
        n = b1 & 0x7F
        head = pos + 2
        if n == 126:
            if end - head < 2:
                break
            (n,) = _LEN16.unpack_from(buf, head)
            head += 2
        elif n == 127:
            if end - head < 8:
                break
            (n,) = _LEN64.unpack_from(buf, head)
            head += 8
        masked = b1 & 0x80
        start = head + 4 if masked else head
        if end - start < n:
            break
        payload = bytes(buf[start : start + n])
        if masked and buf[head : head + 4] != CLIENT_MASK_KEY:
            payload = _xor(payload, buf[head : head + 4])
        out.append((b0 & 0x0F, payload))
        pos = start + n
    if pos:
        del buf[:pos]
    return out


def message_flags(msg: can.Message) -> int:
    """A python-can message's flags as the protocol's flag byte."""
    flags = 0
    if msg.is_extended_id:
        flags |= FLAG_EXTENDED
    if msg.is_remote_frame:
        flags |= FLAG_REMOTE
    if msg.is_error_frame:
        flags |= FLAG_ERROR
    if msg.is_fd:
        flags |= FLAG_FD
    if msg.bitrate_switch:
        flags |= FLAG_BRS
    if msg.error_state_indicator:
        flags |= FLAG_ESI
    return flags


def flagged_message(
    stamp: float,
    arbitration_id: int,
    data: bytes,
    flags: int,
    dlc: int | None = None,
    channel: str | None = None,
) -> can.Message:
    """A python-can message from a frame's fields and the protocol's flag byte (the inverse
    of :func:`message_flags`)."""
    return can.Message(
        timestamp=stamp,
        arbitration_id=arbitration_id,
        is_extended_id=bool(flags & FLAG_EXTENDED),
        is_remote_frame=bool(flags & FLAG_REMOTE),
        is_error_frame=bool(flags & FLAG_ERROR),
        is_fd=bool(flags & FLAG_FD),
        bitrate_switch=bool(flags & FLAG_BRS),
        error_state_indicator=bool(flags & FLAG_ESI),
        dlc=dlc,
        data=data,
        channel=channel,
        check=False,
    )


# -- the runtime's end ------------------------------------------------------------------------


class BridgeBus(can.BusABC):
    """The runtime's end of the bridge: a python-can bus connected to a bridge server on
    127.0.0.1 (:class:`hil_sim.harness.bridge.Bridge`, or python-can-remote's ``RemoteServer``).

    Received frames carry the sender's timestamp (s since the epoch); sent frames carry the
    message's own (the master stamps ``time.time()`` at send). ``send`` never waits for the
    far end. Safe inside the loop: one ``sendall`` per :meth:`send` or :meth:`send_many`, one
    ``recv`` per batch of frames received (a ``select`` only when none is there and the
    timeout allows a wait), one ``can.Message`` per frame received.

    Args:
        port: The server's TCP port on 127.0.0.1.
        connect_timeout_s: Longest wait for the connection and the server's bus response.
        can_filters: python-can filters, applied by :meth:`can.BusABC.recv`.

    Raises:
        BridgeError: No server answered as python-can-remote does.
    """

    def __init__(
        self,
        port: int,
        *,
        connect_timeout_s: float = 5.0,
        can_filters: can.typechecking.CanFilters | None = None,
    ) -> None:
        self.channel_info = f"bridge ws://{HOST}:{port}/"
        self._inbuf = bytearray()
        self._rx: collections.deque[can.Message] = collections.deque()
        #: The connection ended (the server closed it or :meth:`shutdown`).
        self._closed = False
        self._shut = False
        try:
            self._sock = socket.create_connection((HOST, port), timeout=connect_timeout_s)
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._connect(port)
        except (OSError, ValueError) as exc:
            raise BridgeError(f"{self.channel_info}: {type(exc).__name__}: {exc}") from exc
        self._sock.settimeout(None)
        self._poll = select.poll()
        self._poll.register(self._sock, select.POLLIN)
        super().__init__(channel=self.channel_info, can_filters=can_filters)

    def _connect(self, port: int) -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        self._sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: {HOST}:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {PROTOCOL}\r\n\r\n"
            ).encode("latin-1")
        )
        response = b""
        while b"\r\n\r\n" not in response:
            chunk = self._sock.recv(4096)
            if not chunk:
                raise ValueError("the server closed the connection during the handshake")
            response += chunk
        head, _, rest = response.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        if " 101 " not in lines[0] + " ":
            raise ValueError(f"the server answered {lines[0]!r}")
        headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines)}
        if headers.get("sec-websocket-accept") != get_accept_key(key):
            raise ValueError("bad Sec-WebSocket-Accept")
        if headers.get("sec-websocket-protocol") != PROTOCOL:
            raise ValueError(f"the server speaks {headers.get('sec-websocket-protocol')!r}")
        self._inbuf += rest
        request = {"type": "bus_request", "payload": {"config": {}}}
        self._sock.sendall(ws_frame(OP_TEXT, json.dumps(request).encode(), mask=True))
        while True:
            for opcode, payload in ws_messages(self._inbuf):
                if opcode != OP_TEXT:
                    continue
                event = json.loads(payload)
                if event.get("type") == "bus_response":
                    self.channel_info = f"{event['payload']['channel_info']} on {self.channel_info}"
                    return
                if event.get("type") == "error":
                    raise ValueError(f"the server refused the bus: {event.get('payload')}")
            chunk = self._sock.recv(4096)
            if not chunk:
                raise ValueError("the server closed the connection before the bus response")
            self._inbuf += chunk

    def fileno(self) -> int:
        """The socket's file descriptor (for ``select`` / python-can's notifier)."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame (one ``sendall``).

        Raises:
            BridgeError: The bus is shut down or the connection broke.
        """
        self._write(_client_frame(msg))

    def send_many(self, msgs: Sequence[can.Message]) -> None:
        """Send frames in order in one write (one ``sendall``): the master's cycle (RPDO1s and
        SYNC) costs one system call instead of one a frame. Loop safe.

        Raises:
            BridgeError: The bus is shut down or the connection broke (then none, some or all
                of the frames went out).
        """
        self._write(b"".join([_client_frame(msg) for msg in msgs]))

    def _write(self, data: bytes) -> None:
        if self._closed or self._shut:
            raise BridgeError(f"{self.channel_info}: send on a closed bus")
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise BridgeError(f"{self.channel_info}: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._shut:
            raise BridgeError(f"{self.channel_info}: receive on a shut down bus")
        if not self._rx:
            if timeout is not None and timeout <= 0.0 and not self._poll.poll(0):
                # Nothing there and no wait: one poll, cheaper than a refused recv's exception.
                return None, False
            # Take what the socket holds first: no select when the answers are already there.
            self._fill(socket.MSG_DONTWAIT)
        if self._rx:
            return self._rx.popleft(), False
        if timeout is not None and timeout <= 0.0:
            return None, False
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._rx:
            wait = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            ready, _, _ = select.select([self._sock], [], [], wait)
            if not ready:
                return None, False
            self._fill(0)
        return self._rx.popleft(), False

    def _fill(self, flags: int) -> None:
        """Read what the socket holds (``flags``: ``MSG_DONTWAIT`` or 0) and queue its frames."""
        try:
            chunk = self._sock.recv(_READ_SIZE, flags)
        except BlockingIOError:
            return
        except OSError as exc:
            raise BridgeError(f"{self.channel_info}: {exc}") from exc
        if not chunk:
            self._closed = True
            raise BridgeError(f"{self.channel_info}: the server closed the connection")
        self._inbuf += chunk
        rx = self._rx
        channel = self.channel_info
        for opcode, payload in ws_messages(self._inbuf):
            if opcode == OP_BINARY:
                if len(payload) < FRAME.size or payload[0] != BINARY_MESSAGE_TYPE:
                    continue
                _, stamp, arbitration_id, dlc, flags = FRAME.unpack_from(payload)
                data = payload[FRAME.size : FRAME.size + dlc]
                if not flags & ~FLAG_EXTENDED:
                    # A data frame, the drives' every frame: python-can's defaults for the rest
                    # (fewer keywords, the cheaper constructor call).
                    msg = can.Message(
                        timestamp=stamp,
                        arbitration_id=arbitration_id,
                        is_extended_id=bool(flags),
                        data=data,
                        channel=channel,
                        check=False,
                    )
                else:
                    msg = flagged_message(stamp, arbitration_id, data, flags, dlc, channel)
                rx.append(msg)
            elif opcode == OP_PING:
                self._write(ws_frame(OP_PONG, payload, mask=True))
            elif opcode == OP_CLOSE:
                self._closed = True
            elif opcode == OP_TEXT:
                event = json.loads(payload)
                if event.get("type") == "error":
                    said = event.get("payload")
                    raise BridgeError(f"{self.channel_info}: the server says {said}")

    def shutdown(self) -> None:
        """Close the connection (websocket close, the server's close awaited for at most
        :data:`CLOSE_WAIT_S`, then the socket); idempotent."""
        self._shut = True
        if not self._closed:
            self._closed = True
            with contextlib.suppress(OSError):
                self._sock.sendall(ws_frame(OP_CLOSE, _LEN16.pack(1000), mask=True))
                self._await_close()
        self._sock.close()
        super().shutdown()

    def _await_close(self) -> None:
        """Read until the server's close (or end of stream), so it closes first (RFC 6455 7)."""
        deadline = time.monotonic() + CLOSE_WAIT_S
        while (left := deadline - time.monotonic()) > 0.0:
            if not select.select([self._sock], [], [], left)[0]:
                return
            chunk = self._sock.recv(_READ_SIZE)
            if not chunk:
                return
            self._inbuf += chunk
            if any(opcode == OP_CLOSE for opcode, _ in ws_messages(self._inbuf)):
                return
