"""The real-time HIL's bus bridge: python-can-remote's websocket protocol, served in the HIL's loop.

Role: the server end of the 127.0.0.1 bridge, the only one: the real-time HIL process
(:mod:`hil_sim.harness.realtime`) serves its drives through it, the transport contract test and
the bridge benchmark (``benchmarks/bridge_rtt.py``) put their far end on it. The runtime connects
with :class:`hil_sim.bridge.BridgeBus` or python-can's ``remote`` interface
(``can_remote.RemoteBus``, channel ``ws://127.0.0.1:<port>/``); this module serves that protocol
in one single-threaded loop instead of python-can-remote's ``RemoteServer`` (a thread per client
and per direction, each frame a ``can.Message`` deep-copied through a ``virtual`` bus). The
protocol's constants and websocket framing are :mod:`hil_sim.bridge`'s.

Wire protocol (python-can-remote 0.2, subprotocol ``can.binary+json.v1``, or ``can.json.v1`` for
a client that offers only that): an HTTP upgrade, then websocket frames. A text frame is a JSON
event ``{"type": ..., "payload": ...}``: the client's ``bus_request`` is answered with a
``bus_response``; ``message`` carries a frame as JSON (``can.json.v1``); other events are answered
with an ``error`` event. A binary frame of type 1 is one CAN frame: ``>dIBB`` (timestamp,
arbitration id, DLC, flags: extended, remote, error, FD, BRS, ESI) and the data bytes. Client
frames are masked (RFC 6455), server frames are not.

Bus semantics: a frame a client sends reaches the HIL, flags and stamp as sent, and every other
client (as on the ``virtual`` bus the bridge replaces: no client receives its own frames); a
frame the HIL sends reaches every client, stamped with ``time.time()`` at sending unless the
HIL gives a stamp. Nothing is copied per receiver: the HIL's frame is packed once, into one
preallocated buffer per data length, and appended to each client's output buffer; the frames a
loop iteration produces leave in one ``send`` per client (:meth:`Bridge.flush`). A remote
frame's DLC reaches the HIL as no data (as python-can-remote's client reads it).

Sockets are non-blocking and bound to 127.0.0.1 only. A client that does not read (its kernel
buffer full) keeps up to :data:`MAX_PENDING_BYTES` queued; frames beyond that are dropped for
that client alone and counted (:attr:`Bridge.dropped`), as a CAN controller with a full receive
buffer drops them, so no client can stall the HIL.

Not thread-safe: one owner, the HIL's loop.
"""

from __future__ import annotations

import json
import select
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from can_remote.websocket import get_accept_key

from hil_sim.bridge import (
    BINARY_MESSAGE_TYPE,
    FLAG_BRS,
    FLAG_ERROR,
    FLAG_ESI,
    FLAG_EXTENDED,
    FLAG_FD,
    FLAG_REMOTE,
    FRAME,
    HOST,
    OP_BINARY,
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    PROTOCOL,
    PROTOCOL_JSON,
    RxFrame,
    ws_frame,
    ws_messages,
)

__all__ = ["MAX_DATA_BYTES", "MAX_PENDING_BYTES", "Bridge", "RxFrame"]

#: Output bytes queued for one client before its further frames are dropped.
MAX_PENDING_BYTES = 1 << 20
#: Longest data field the HIL sends (a CAN FD frame's).
MAX_DATA_BYTES = 64

#: A whole server websocket frame of a CAN frame: websocket opcode byte and length (<= 125: no
#: mask, no extended length), then :data:`hil_sim.bridge.FRAME`; the data follows.
_WS_CAN = struct.Struct(">BB" + FRAME.format.lstrip(">"))
_WS_CAN_SIZE = _WS_CAN.size
_HTTP_END = b"\r\n\r\n"
_MAX_HTTP_BYTES = 16384
#: JSON message fields and the flag each sets (python-can-remote's ``can.json.v1``).
_JSON_FLAGS = (
    ("is_extended_id", FLAG_EXTENDED),
    ("is_remote_frame", FLAG_REMOTE),
    ("is_error_frame", FLAG_ERROR),
    ("is_fd", FLAG_FD),
    ("bitrate_switch", FLAG_BRS),
    ("error_state_indicator", FLAG_ESI),
)


@dataclass(slots=True, eq=False)
class _Client:
    sock: socket.socket
    inbuf: bytearray = field(default_factory=bytearray)
    out: bytearray = field(default_factory=bytearray)
    upgraded: bool = False
    #: The client's bus is open (its ``bus_request`` answered): only then does it get frames;
    #: python-can-remote's client takes the first event after its request for the response.
    bus_open: bool = False
    binary: bool = True
    closing: bool = False


class Bridge:
    """The websocket bridge of the real-time HIL: listening socket and its clients.

    One iteration of the owner's loop: :meth:`wait`, :meth:`receive` (frames to a callback),
    :meth:`send` (queued), :meth:`flush` (one ``send`` per client).

    Args:
        port: TCP port on 127.0.0.1 (0: any free one).
        channel_info: Text the ``bus_response`` names the bus by.

    Attributes:
        port: The port bound.
        dropped: Frames dropped for clients that did not read.

    Raises:
        OSError: The port cannot be bound.
    """

    HOST = HOST

    def __init__(self, port: int = 0, channel_info: str = "excavator-rt HIL") -> None:
        self._listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listen.bind((self.HOST, port))
        self._listen.listen(4)
        self._listen.setblocking(False)
        self.port: int = self._listen.getsockname()[1]
        self.dropped = 0
        self._channel_info = channel_info
        self._clients: dict[int, _Client] = {}
        # select() rather than poll()/epoll(): their timeouts are whole milliseconds (rounded
        # up), too coarse to wake for a 250 us servo tick; a handful of sockets is all there is.
        self._fds: list[int] = [self._listen.fileno()]
        self._ready: list[int] = []
        # One reusable buffer per data length: a HIL frame is packed once into it.
        self._packed = [bytearray(_WS_CAN_SIZE + n) for n in range(MAX_DATA_BYTES + 1)]

    @property
    def clients(self) -> int:
        """Clients whose bus is open (they receive frames)."""
        return sum(1 for c in self._clients.values() if c.bus_open)

    # -- receiving ----------------------------------------------------------------------------

    def wait(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a connection or bytes from a client; True if any came."""
        self._ready = select.select(self._fds, (), (), max(0.0, timeout_s))[0]
        return bool(self._ready)

    def receive(self, on_frame: Callable[[RxFrame], None]) -> None:
        """Read what :meth:`wait` found ready and hand every whole CAN frame to ``on_frame``, in
        arrival order; each is forwarded to the other clients first (bus semantics)."""
        ready, self._ready = self._ready, []
        listen_fd = self._listen.fileno()
        for fd in ready:
            if fd == listen_fd:
                self._accept()
                continue
            client = self._clients.get(fd)
            if client is None:
                continue
            try:
                chunk = client.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                chunk = b""
            if not chunk:
                self._drop(client)
                continue
            client.inbuf += chunk
            if not client.upgraded:
                self._handshake(client)
            if client.upgraded and not client.closing:
                for opcode, payload in ws_messages(client.inbuf):
                    self._message(client, opcode, payload, on_frame)
                    if client.closing:
                        break

    def _accept(self) -> None:
        try:
            sock, _ = self._listen.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._clients[sock.fileno()] = _Client(sock)
        self._fds.append(sock.fileno())

    def _handshake(self, client: _Client) -> None:
        end = client.inbuf.find(_HTTP_END)
        if end < 0:
            if len(client.inbuf) > _MAX_HTTP_BYTES:
                self._drop(client)
            return
        head = bytes(client.inbuf[:end]).decode("latin-1").split("\r\n")
        del client.inbuf[: end + len(_HTTP_END)]
        headers = {}
        for line in head[1:]:
            name, _, value = line.partition(":")
            headers[name.strip().lower()] = value.strip()
        key = headers.get("sec-websocket-key")
        if key is None or headers.get("upgrade", "").lower() != "websocket":
            client.sock.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
            self._drop(client)
            return
        offered = [p.strip() for p in headers.get("sec-websocket-protocol", "").split(",")]
        client.binary = PROTOCOL in offered
        protocol = PROTOCOL if client.binary else PROTOCOL_JSON
        reply = (
            "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Accept: {get_accept_key(key)}\r\n"
            f"Sec-WebSocket-Protocol: {protocol}\r\n\r\n"
        )
        client.out += reply.encode("ascii")
        client.upgraded = True
        self._flush_client(client)

    def _message(
        self,
        client: _Client,
        opcode: int,
        payload: bytes,
        on_frame: Callable[[RxFrame], None],
    ) -> None:
        if opcode == OP_BINARY:
            if len(payload) < FRAME.size or payload[0] != BINARY_MESSAGE_TYPE:
                return
            _, stamp, arbitration_id, _, flags = FRAME.unpack_from(payload)
            self._forward(client, payload, binary=True)
            on_frame((stamp, arbitration_id, payload[FRAME.size :], flags))
        elif opcode == OP_TEXT:
            self._event(client, payload, on_frame)
        elif opcode == OP_PING:
            self._queue_ws(client, OP_PONG, payload)
            self._flush_client(client)
        elif opcode == OP_CLOSE:
            self._queue_ws(client, OP_CLOSE, payload[:2])
            self._flush_client(client)
            self._drop(client)

    def _event(self, client: _Client, payload: bytes, on_frame: Callable[[RxFrame], None]) -> None:
        try:
            event = json.loads(payload.decode("utf-8"))
            kind = event["type"]
        except (ValueError, TypeError, KeyError):
            self._send_event(client, "error", "expected a JSON event with a 'type'")
            return
        if kind == "bus_request":
            self._send_event(client, "bus_response", {"channel_info": self._channel_info})
            client.bus_open = True
        elif kind == "message":
            msg = event.get("payload", {})
            try:
                frame = (
                    float(msg.get("timestamp", 0.0)),
                    int(msg["arbitration_id"]),
                    bytes(msg.get("data", [])),
                    _json_flags(msg),
                )
            except (KeyError, TypeError, ValueError, AttributeError):
                self._send_event(client, "error", "a message needs arbitration_id and data")
                return
            self._forward(client, payload, binary=False)
            on_frame(frame)
        else:
            self._send_event(client, "error", f"event {kind!r} is not served by the HIL bridge")

    def _forward(self, sender: _Client, payload: bytes, *, binary: bool) -> None:
        """A client's frame to every other client (re-encoded only across protocols)."""
        if len(self._clients) < 2:
            return
        for other in self._clients.values():
            if other is sender or not other.bus_open:
                continue
            if other.binary == binary:
                self._queue_ws(other, OP_BINARY if binary else OP_TEXT, payload)
            elif binary:
                _, stamp, arbitration_id, dlc, flags = FRAME.unpack_from(payload)
                frame = _json_frame(stamp, arbitration_id, dlc, flags, payload[FRAME.size :])
                self._send_event(other, "message", frame)
            else:
                msg = json.loads(payload.decode("utf-8"))["payload"]
                data = bytes(msg.get("data", []))
                head = FRAME.pack(
                    BINARY_MESSAGE_TYPE,
                    float(msg.get("timestamp", 0.0)),
                    int(msg["arbitration_id"]),
                    int(msg.get("dlc", len(data))),
                    _json_flags(msg),
                )
                self._queue_ws(other, OP_BINARY, head + data)

    # -- sending ------------------------------------------------------------------------------

    def send(
        self,
        arbitration_id: int,
        data: bytes,
        flags: int = 0,
        timestamp_s: float | None = None,
    ) -> None:
        """Queue a HIL frame for every client whose bus is open; :meth:`flush` sends.

        Args:
            arbitration_id: The frame's id (11 bits; 29 with ``FLAG_EXTENDED``).
            data: At most :data:`MAX_DATA_BYTES` bytes (more than 8 only with ``FLAG_FD``).
            flags: :data:`hil_sim.bridge.FLAG_EXTENDED` ... ``FLAG_ESI`` (0: a standard-id
                data frame).
            timestamp_s: The frame's stamp (s since the epoch); None: ``time.time()`` now.

        Raises:
            ValueError: ``data`` is longer than :data:`MAX_DATA_BYTES`.
        """
        if not self._clients:
            return
        n = len(data)
        if n > MAX_DATA_BYTES:
            raise ValueError(f"{n} data bytes; a CAN frame carries at most {MAX_DATA_BYTES}")
        buf = self._packed[n]
        stamp = time.time() if timestamp_s is None else timestamp_s
        _WS_CAN.pack_into(
            buf, 0, 0x80 | OP_BINARY, FRAME.size + n, BINARY_MESSAGE_TYPE,
            stamp, arbitration_id, n, flags,
        )  # fmt: skip
        buf[_WS_CAN_SIZE:] = data
        for client in self._clients.values():
            if not client.bus_open:
                continue
            if len(client.out) > MAX_PENDING_BYTES:
                self.dropped += 1
            elif client.binary:
                client.out += buf
            else:
                frame = _json_frame(stamp, arbitration_id, n, flags, data)
                self._send_event(client, "message", frame)

    def flush(self) -> None:
        """Send what is queued for every client (one ``send`` each)."""
        for client in list(self._clients.values()):
            if client.out:
                self._flush_client(client)

    def _flush_client(self, client: _Client) -> None:
        try:
            sent = client.sock.send(client.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(client)
            return
        del client.out[:sent]

    def _queue_ws(self, client: _Client, opcode: int, payload: bytes) -> None:
        if len(client.out) > MAX_PENDING_BYTES:
            self.dropped += 1
            return
        client.out += ws_frame(opcode, payload, mask=False)

    def _send_event(self, client: _Client, kind: str, payload: object) -> None:
        text = json.dumps({"type": kind, "payload": payload}).encode("utf-8")
        self._queue_ws(client, OP_TEXT, text)

    # -- closing ------------------------------------------------------------------------------

    def _drop(self, client: _Client) -> None:
        client.closing = True
        fd = client.sock.fileno()
        if fd >= 0:
            self._clients.pop(fd, None)
            if fd in self._fds:
                self._fds.remove(fd)
        client.sock.close()

    def close(self) -> None:
        """Close every client (a websocket close frame, best effort) and the listening socket."""
        for client in list(self._clients.values()):
            if client.upgraded:
                self._queue_ws(client, OP_CLOSE, (1001).to_bytes(2, "big"))
                self._flush_client(client)
            if not client.closing:
                self._drop(client)
        self._fds.clear()
        self._listen.close()


def _json_flags(msg: dict[str, Any]) -> int:
    """The flag byte of a JSON message (python-can-remote's ``can.json.v1`` fields)."""
    flags = 0
    for name, flag in _JSON_FLAGS:
        if msg.get(name):
            flags |= flag
    return flags


def _json_frame(
    stamp: float, arbitration_id: int, dlc: int, flags: int, data: bytes
) -> dict[str, object]:
    """A frame as python-can-remote's JSON message (the FD fields only for an FD frame)."""
    frame: dict[str, object] = {
        "timestamp": stamp,
        "arbitration_id": arbitration_id,
        "is_extended_id": bool(flags & FLAG_EXTENDED),
        "is_remote_frame": bool(flags & FLAG_REMOTE),
        "is_error_frame": bool(flags & FLAG_ERROR),
        "dlc": dlc,
        "data": list(data),
    }
    if flags & FLAG_FD:
        frame["is_fd"] = True
        frame["bitrate_switch"] = bool(flags & FLAG_BRS)
        frame["error_state_indicator"] = bool(flags & FLAG_ESI)
    return frame
