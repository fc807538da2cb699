"""The real-time HIL's bus bridge: python-can-remote's websocket protocol, served in the HIL's loop.

Role: the bus between the runtime and the real-time HIL process (:mod:`hil_sim.harness.realtime`).
The runtime connects with python-can's ``remote`` interface (``can_remote.RemoteBus``, channel
``ws://127.0.0.1:<port>/``); this module is the server end of that protocol, written for one
single-threaded loop instead of python-can-remote's ``RemoteServer`` (a thread per client and
per direction, each frame a ``can.Message`` deep-copied through a ``virtual`` bus).

Wire protocol (python-can-remote 0.2, subprotocol ``can.binary+json.v1``, or ``can.json.v1`` for
a client that offers only that): an HTTP upgrade, then websocket frames. A text frame is a JSON
event ``{"type": ..., "payload": ...}``: the client's ``bus_request`` is answered with a
``bus_response``; ``message`` carries a frame as JSON (``can.json.v1``); other events are answered
with an ``error`` event. A binary frame of type 1 is one CAN frame: ``>dIBB`` (timestamp,
arbitration id, DLC, flags) and the data bytes. Client frames are masked (RFC 6455), server
frames are not.

Bus semantics: a frame a client sends reaches the HIL and every other client (as on the
``virtual`` bus the bridge replaces: no client receives its own frames); a frame the HIL sends
reaches every client, stamped with ``time.time()`` at sending. Nothing is copied per receiver:
the HIL's frame is packed once, into one preallocated buffer per frame size, and appended to
each client's output buffer; the frames a loop iteration produces leave in one ``send`` per
client (:meth:`Bridge.flush`).

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

from can_remote.websocket import get_accept_key

__all__ = ["MAX_PENDING_BYTES", "Bridge", "RxFrame"]

#: Output bytes queued for one client before its further frames are dropped.
MAX_PENDING_BYTES = 1 << 20

_BINARY_MESSAGE_TYPE = 1
#: Frame header of a binary CAN message: timestamp, arbitration id, DLC, flags.
_CAN_HEADER = struct.Struct(">dIBB")
#: A whole server websocket frame of a classic CAN frame: websocket opcode byte and length
#: (<= 125: no mask, no extended length), message type, then ``_CAN_HEADER``; the data follows.
_WS_CAN = struct.Struct(">BBBdIBB")
_WS_CAN_SIZE = _WS_CAN.size
_TEXT, _BINARY, _CLOSE, _PING, _PONG = 0x1, 0x2, 0x8, 0x9, 0xA
_FLAG_EXTENDED, _FLAG_REMOTE, _FLAG_ERROR = 0x1, 0x2, 0x4
_HTTP_END = b"\r\n\r\n"
_MAX_HTTP_BYTES = 16384

#: One frame received from a client: ``(timestamp_s, arbitration_id, data, is_error_frame)``;
#: ``timestamp_s`` is the client's stamp (``time.time()`` of its send), 0.0 when unstamped.
RxFrame = tuple[float, int, bytes, bool]


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

    Args:
        port: TCP port on 127.0.0.1 (0: any free one).
        channel_info: Text the ``bus_response`` names the bus by.

    Attributes:
        port: The port bound.
        dropped: Frames dropped for clients that did not read.
    """

    HOST = "127.0.0.1"

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
        # One reusable buffer per data length (0..8): a HIL frame is packed once into it.
        self._packed = [bytearray(_WS_CAN_SIZE + n) for n in range(9)]

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
                self._frames(client, on_frame)

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
        client.binary = "can.binary+json.v1" in offered
        protocol = "can.binary+json.v1" if client.binary else "can.json.v1"
        reply = (
            "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Accept: {get_accept_key(key)}\r\n"
            f"Sec-WebSocket-Protocol: {protocol}\r\n\r\n"
        )
        client.out += reply.encode("ascii")
        client.upgraded = True
        self._flush_client(client)

    def _frames(self, client: _Client, on_frame: Callable[[RxFrame], None]) -> None:
        """Parse every whole websocket frame in the client's buffer."""
        buf = client.inbuf
        pos = 0
        n = len(buf)
        while n - pos >= 2:
            b1, b2 = buf[pos], buf[pos + 1]
            length = b2 & 0x7F
            head = 2
            if length == 126:
                if n - pos < 4:
                    break
                length = (buf[pos + 2] << 8) | buf[pos + 3]
                head = 4
            elif length == 127:
                if n - pos < 10:
                    break
                length = int.from_bytes(buf[pos + 2 : pos + 10], "big")
                head = 10
            masked = b2 & 0x80
            start = pos + head + (4 if masked else 0)
            if n - start < length:
                break
            payload = bytearray(buf[start : start + length])
            if masked:
                mask = buf[pos + head : pos + head + 4]
                # XOR with the repeated mask as one integer operation.
                reps = (length + 3) // 4
                key = int.from_bytes((mask * reps)[:length], "little")
                payload = bytearray(
                    (int.from_bytes(payload, "little") ^ key).to_bytes(length, "little")
                )
            pos = start + length
            self._message(client, b1 & 0x0F, payload, on_frame)
            if client.closing:
                return
        del buf[:pos]

    def _message(
        self,
        client: _Client,
        opcode: int,
        payload: bytearray,
        on_frame: Callable[[RxFrame], None],
    ) -> None:
        if opcode == _BINARY:
            if len(payload) < 1 + _CAN_HEADER.size or payload[0] != _BINARY_MESSAGE_TYPE:
                return
            stamp, arbitration_id, _, flags = _CAN_HEADER.unpack_from(payload, 1)
            data = bytes(payload[1 + _CAN_HEADER.size :])
            self._forward(client, payload, binary=True)
            on_frame((stamp, arbitration_id, data, bool(flags & _FLAG_ERROR)))
        elif opcode == _TEXT:
            self._event(client, payload, on_frame)
        elif opcode == _PING:
            self._queue_ws(client, _PONG, bytes(payload))
            self._flush_client(client)
        elif opcode == _CLOSE:
            self._queue_ws(client, _CLOSE, bytes(payload[:2]))
            self._flush_client(client)
            self._drop(client)

    def _event(
        self, client: _Client, payload: bytearray, on_frame: Callable[[RxFrame], None]
    ) -> None:
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
                    bool(msg.get("is_error_frame", False)),
                )
            except (KeyError, TypeError, ValueError):
                self._send_event(client, "error", "a message needs arbitration_id and data")
                return
            self._forward(client, payload, binary=False)
            on_frame(frame)
        else:
            self._send_event(client, "error", f"event {kind!r} is not served by the HIL bridge")

    def _forward(self, sender: _Client, payload: bytearray, *, binary: bool) -> None:
        """A client's frame to every other client (re-encoded only across protocols)."""
        if len(self._clients) < 2:
            return
        for other in self._clients.values():
            if other is sender or not other.bus_open:
                continue
            if other.binary == binary:
                self._queue_ws(other, _BINARY if binary else _TEXT, payload)
            elif binary:
                stamp, arbitration_id, dlc, flags = _CAN_HEADER.unpack_from(payload, 1)
                data = bytes(payload[1 + _CAN_HEADER.size :])
                frame = _json_frame(stamp, arbitration_id, dlc, flags, data)
                self._send_event(other, "message", frame)
            else:
                msg = json.loads(payload.decode("utf-8"))["payload"]
                data = bytes(msg.get("data", []))
                flags = _FLAG_ERROR if msg.get("is_error_frame") else 0
                self._queue_ws(
                    other,
                    _BINARY,
                    bytes([_BINARY_MESSAGE_TYPE])
                    + _CAN_HEADER.pack(
                        float(msg.get("timestamp", 0.0)),
                        int(msg["arbitration_id"]),
                        len(data),
                        flags,
                    )
                    + data,
                )

    # -- sending ------------------------------------------------------------------------------

    def send(self, arbitration_id: int, data: bytes) -> None:
        """Queue a HIL frame (11-bit id, <= 8 bytes) for every client; :meth:`flush` sends."""
        if not self._clients:
            return
        n = len(data)
        buf = self._packed[n]
        stamp = time.time()
        _WS_CAN.pack_into(
            buf, 0, 0x80 | _BINARY, 1 + _CAN_HEADER.size + n, _BINARY_MESSAGE_TYPE,
            stamp, arbitration_id, n, 0,
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
                self._send_event(client, "message", _json_frame(stamp, arbitration_id, n, 0, data))

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

    def _queue_ws(self, client: _Client, opcode: int, payload: bytes | bytearray) -> None:
        if len(client.out) > MAX_PENDING_BYTES:
            self.dropped += 1
            return
        n = len(payload)
        out = client.out
        out.append(0x80 | opcode)
        if n <= 125:
            out.append(n)
        elif n <= 0xFFFF:
            out.append(126)
            out += n.to_bytes(2, "big")
        else:
            out.append(127)
            out += n.to_bytes(8, "big")
        out += payload

    def _send_event(self, client: _Client, kind: str, payload: object) -> None:
        text = json.dumps({"type": kind, "payload": payload}).encode("utf-8")
        self._queue_ws(client, _TEXT, text)

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
                self._queue_ws(client, _CLOSE, (1001).to_bytes(2, "big"))
                self._flush_client(client)
            if not client.closing:
                self._drop(client)
        self._fds.clear()
        self._listen.close()


def _json_frame(
    stamp: float, arbitration_id: int, dlc: int, flags: int, data: bytes
) -> dict[str, object]:
    return {
        "timestamp": stamp,
        "arbitration_id": arbitration_id,
        "is_extended_id": bool(flags & _FLAG_EXTENDED),
        "is_remote_frame": bool(flags & _FLAG_REMOTE),
        "is_error_frame": bool(flags & _FLAG_ERROR),
        "dlc": dlc,
        "data": list(data),
    }
