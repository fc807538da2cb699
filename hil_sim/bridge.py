"""The CAN bridge over 127.0.0.1: python-can-remote's wire protocol, both ends, without threads.

Role: the transport between the runtime and the real-time HIL process (DESIGN.md "Loop, HIL and
time"). It speaks python-can-remote's protocol (a websocket, subprotocol
``can.binary+json.v1``: a JSON ``bus_request`` / ``bus_response`` exchange, then one binary
websocket message per frame: type byte 1, ``>dIBB`` timestamp, arbitration id, DLC, flags, then
the data), so python-can-remote's own ``RemoteBus`` and ``RemoteServer`` talk to either end.

Why not python-can-remote's classes themselves: per frame they cost what a rig's socketcan does
not. Its server forwards each frame through python-can's ``virtual`` bus (a ``copy.deepcopy`` of
the message per receiver) and two threads that take the interpreter from the HIL's loop; its
client masks byte by byte in Python, waits in ``select`` before every frame and overrides
``recv`` (so python-can's filters never apply). Here:

* :class:`BridgeServer` is polled by the HIL's own loop (no thread): one ``recv`` takes every
  frame the socket holds, decoded to ``(timestamp, id, data, flags)`` tuples (no
  ``can.Message``), and the answers to one SYNC leave in one ``sendall``.
* :class:`BridgeBus` is the runtime's end, a python-can backend (``send``, ``_recv_internal``,
  ``shutdown``): one ``recv`` takes every frame the socket holds, ``send`` is one ``sendall``.

Binding: :class:`BridgeServer` listens on 127.0.0.1 only (:data:`HOST`); it refuses any other
address.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import hashlib
import json
import os
import select
import socket
import struct
import time
from typing import Any

import can

__all__ = [
    "FLAG_BRS",
    "FLAG_ERROR",
    "FLAG_ESI",
    "FLAG_EXTENDED",
    "FLAG_FD",
    "FLAG_REMOTE",
    "HOST",
    "PROTOCOL",
    "BridgeBus",
    "BridgeError",
    "BridgeServer",
    "RxFrame",
]

#: The only address the bridge binds or connects to.
HOST = "127.0.0.1"
#: python-can-remote's binary subprotocol.
PROTOCOL = "can.binary+json.v1"

#: ``(timestamp_s, arbitration_id, data, flags)``; flags as :data:`FLAG_EXTENDED` etc.
RxFrame = tuple[float, int, bytes, int]

FLAG_EXTENDED = 0x1
FLAG_REMOTE = 0x2
FLAG_ERROR = 0x4
FLAG_FD = 0x8
FLAG_BRS = 0x10
FLAG_ESI = 0x20

_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
_FRAME = struct.Struct(">BdIBB")  # type byte 1, timestamp, id, DLC, flags
_LEN16 = struct.Struct(">H")
_LEN64 = struct.Struct(">Q")
_BINARY, _TEXT, _CLOSE, _PING, _PONG = 0x2, 0x1, 0x8, 0x9, 0xA
_READ_SIZE = 1 << 16
#: Longest wait of :meth:`BridgeBus.shutdown` for the server's websocket close.
CLOSE_WAIT_S = 0.5


class BridgeError(can.CanOperationError):
    """The bridge's connection failed or the peer broke the protocol."""


def _accept_key(key: str) -> str:
    return base64.b64encode(hashlib.sha1(key.encode("ascii") + _GUID).digest()).decode()


def _ws_frame(opcode: int, payload: bytes, mask: bool) -> bytes:
    """One unfragmented websocket frame (RFC 6455 5.2); a client masks, a server does not."""
    n = len(payload)
    if n <= 125:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | n))
    elif n <= 0xFFFF:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | 126)) + _LEN16.pack(n)
    else:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | 127)) + _LEN64.pack(n)
    if not mask:
        return head + payload
    key = os.urandom(4)
    return head + key + _xor(payload, key)


def _xor(payload: bytes | bytearray, key: bytes) -> bytes:
    """``payload`` XOR the repeated 4-byte ``key`` (websocket masking), as one integer XOR."""
    n = len(payload)
    if n == 0:
        return b""
    pad = (key * (n // 4 + 1))[:n]
    return (int.from_bytes(payload, "big") ^ int.from_bytes(pad, "big")).to_bytes(n, "big")


def _frame_payload(msg: can.Message) -> bytes:
    """A message as python-can-remote's binary frame (the DLC is the message's: a remote frame
    has one and no data)."""
    flags = _message_flags(msg)
    return _FRAME.pack(1, msg.timestamp, msg.arbitration_id, msg.dlc, flags) + bytes(msg.data)


def _message_flags(msg: can.Message) -> int:
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


class _Reader:
    """Splits a websocket byte stream into messages ``(opcode, payload)`` (unfragmented)."""

    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray()

    def messages(self) -> list[tuple[int, bytes]]:
        """Every complete message in the buffer, removed from it."""
        buf = self.buf
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
            if masked:
                payload = _xor(payload, bytes(buf[head : head + 4]))
            out.append((b0 & 0x0F, payload))
            pos = start + n
        if pos:
            del buf[:pos]
        return out


def _decode(payload: bytes) -> RxFrame | None:
    """A binary frame message as an :data:`RxFrame`; None for any other message type."""
    if len(payload) < _FRAME.size or payload[0] != 1:
        return None
    _, timestamp_s, arbitration_id, dlc, flags = _FRAME.unpack_from(payload)
    return timestamp_s, arbitration_id, payload[_FRAME.size : _FRAME.size + dlc], flags


class _Client:
    """One connected runtime (or other python-can-remote client) at the server."""

    __slots__ = ("reader", "sock")

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.reader = _Reader()


class BridgeServer:
    """The HIL's end of the bridge: listens on 127.0.0.1, polled by the HIL's loop.

    Every frame a client sends reaches the HIL (:meth:`poll`) and every other client; frames
    the HIL sends (:meth:`send`) reach every client. Not thread-safe: one loop owns it.

    Args:
        port: TCP port on 127.0.0.1 (0: any free one, see :attr:`port`).
        channel_info: What clients are told they are connected to.

    Raises:
        OSError: The port cannot be bound.
    """

    def __init__(self, port: int = 0, channel_info: str = "excavator-rt HIL") -> None:
        self._listener = socket.create_server((HOST, port))
        self._listener.setblocking(False)
        self.port: int = self._listener.getsockname()[1]
        self.channel_info = channel_info
        self._clients: list[_Client] = []
        self.frames_in = 0
        self.frames_out = 0

    @property
    def clients(self) -> int:
        """Connected clients."""
        return len(self._clients)

    def poll(self, timeout_s: float | None) -> list[RxFrame]:
        """Wait at most ``timeout_s`` for frames (0: do not wait), accept new clients; every
        frame received since the last poll, in order (per client).

        A client that closes or breaks the protocol is dropped.
        """
        socks: list[Any] = [self._listener, *(c.sock for c in self._clients)]
        ready, _, _ = select.select(socks, [], [], timeout_s)
        if not ready:
            return []
        out: list[RxFrame] = []
        for client in list(self._clients):
            if client.sock in ready:
                self._read(client, out)
        if self._listener in ready:
            self._accept()
        return out

    def send(
        self, frames: list[tuple[int, bytes]], timestamp_s: float | None = None, flags: int = 0
    ) -> None:
        """Send frames ``(id, data)`` to every client, in one write each.

        Args:
            frames: The frames, in bus order.
            timestamp_s: Their timestamp (s since the epoch); None: ``time.time()`` now.
            flags: Their flags (:data:`FLAG_EXTENDED`, ...; 0: standard-id data frames).
        """
        if not frames or not self._clients:
            return
        stamp = time.time() if timestamp_s is None else timestamp_s
        pack = _FRAME.pack
        size = _FRAME.size
        chunks = []
        for arbitration_id, data in frames:
            n = len(data)
            chunks.append(bytes((0x80 | _BINARY, size + n)))
            chunks.append(pack(1, stamp, arbitration_id, n, flags))
            chunks.append(data)
        self._broadcast(b"".join(chunks), None)
        self.frames_out += len(frames)

    def close(self) -> None:
        """Close every connection (websocket close, then the socket) and stop listening."""
        for client in self._clients:
            self._drop(client, _ws_frame(_CLOSE, _LEN16.pack(1001), mask=False))
        self._clients = []
        self._listener.close()

    # -- connections ----------------------------------------------------------------------------

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(True)
        sock.settimeout(5.0)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            self._handshake(sock)
        except (OSError, ValueError, KeyError) as exc:
            sock.close()
            print(f"HIL bridge: a client failed to connect: {exc}", flush=True)
            return
        sock.settimeout(None)
        self._clients.append(_Client(sock))

    def _handshake(self, sock: socket.socket) -> None:
        request = b""
        while b"\r\n\r\n" not in request:
            chunk = sock.recv(4096)
            if not chunk:
                raise ValueError("closed during the handshake")
            request += chunk
        head, _, rest = request.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines)}
        if headers.get("upgrade", "").lower() != "websocket":
            raise ValueError("not a websocket request")
        offered = [p.strip() for p in headers.get("sec-websocket-protocol", "").split(",")]
        if PROTOCOL not in offered:
            raise ValueError(f"the client does not speak {PROTOCOL} (offers {offered})")
        sock.sendall(
            (
                "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
                "Connection: Upgrade\r\n"
                f"Sec-WebSocket-Accept: {_accept_key(headers['sec-websocket-key'])}\r\n"
                f"Sec-WebSocket-Protocol: {PROTOCOL}\r\n\r\n"
            ).encode("latin-1")
        )
        reader = _Reader()
        reader.buf += rest
        while not (messages := reader.messages()):
            chunk = sock.recv(4096)
            if not chunk:
                raise ValueError("closed before the bus request")
            reader.buf += chunk
        opcode, payload = messages[0]
        event = json.loads(payload) if opcode == _TEXT else {}
        if event.get("type") != "bus_request":
            raise ValueError(f"expected a bus_request, got {payload[:80]!r}")
        reply = {"type": "bus_response", "payload": {"channel_info": self.channel_info}}
        sock.sendall(_ws_frame(_TEXT, json.dumps(reply).encode(), mask=False))

    def _read(self, client: _Client, out: list[RxFrame]) -> None:
        try:
            chunk = client.sock.recv(_READ_SIZE)
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(client, b"")
            return
        client.reader.buf += chunk
        relay: list[bytes] = []
        for opcode, payload in client.reader.messages():
            if opcode == _BINARY:
                frame = _decode(payload)
                if frame is not None:
                    out.append(frame)
                    relay.append(_ws_frame(_BINARY, payload, mask=False))
            elif opcode == _PING:
                client.sock.sendall(_ws_frame(_PONG, payload, mask=False))
            elif opcode == _CLOSE:
                self._drop(client, _ws_frame(_CLOSE, payload[:2], mask=False))
                return
            # Text events (periodic tasks of python-can-remote) are not supported: ignored.
        self.frames_in += len(relay)
        if relay and len(self._clients) > 1:
            self._broadcast(b"".join(relay), client)

    def _broadcast(self, data: bytes, source: _Client | None) -> None:
        for client in list(self._clients):
            if client is source:
                continue
            try:
                client.sock.sendall(data)
            except OSError:
                self._drop(client, b"")

    def _drop(self, client: _Client, goodbye: bytes) -> None:
        if client in self._clients:
            self._clients.remove(client)
        if goodbye:
            with contextlib.suppress(OSError):
                client.sock.sendall(goodbye)
        client.sock.close()


class BridgeBus(can.BusABC):
    """The runtime's end of the bridge: a python-can bus connected to a bridge server on
    127.0.0.1 (:class:`BridgeServer`, or python-can-remote's ``RemoteServer``).

    Received frames carry the sender's timestamp (s since the epoch); sent frames carry the
    message's own (the master stamps ``time.time()`` at send). ``send`` never waits for the
    far end. Safe inside the loop: one ``sendall`` per frame sent, one ``recv`` per batch of
    frames received, one ``can.Message`` per frame received.

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
        self._reader = _Reader()
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
        if headers.get("sec-websocket-accept") != _accept_key(key):
            raise ValueError("bad Sec-WebSocket-Accept")
        if headers.get("sec-websocket-protocol") != PROTOCOL:
            raise ValueError(f"the server speaks {headers.get('sec-websocket-protocol')!r}")
        self._reader.buf += rest
        request = {"type": "bus_request", "payload": {"config": {}}}
        self._sock.sendall(_ws_frame(_TEXT, json.dumps(request).encode(), mask=True))
        while True:
            for opcode, payload in self._reader.messages():
                if opcode != _TEXT:
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
            self._reader.buf += chunk

    def fileno(self) -> int:
        """The socket's file descriptor (for ``select`` / python-can's notifier)."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame (one ``sendall``).

        Raises:
            BridgeError: The bus is shut down or the connection broke.
        """
        if self._closed or self._shut:
            raise BridgeError(f"{self.channel_info}: send on a closed bus")
        payload = _frame_payload(msg)
        try:
            self._sock.sendall(_ws_frame(_BINARY, payload, mask=True))
        except OSError as exc:
            raise BridgeError(f"{self.channel_info}: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._shut:
            raise BridgeError(f"{self.channel_info}: receive on a shut down bus")
        if self._rx:
            return self._rx.popleft(), False
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        while not self._rx:
            wait = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            ready, _, _ = select.select([self._sock], [], [], wait)
            if not ready:
                return None, False
            self._fill()
        return self._rx.popleft(), False

    def _fill(self) -> None:
        try:
            chunk = self._sock.recv(_READ_SIZE)
        except OSError as exc:
            raise BridgeError(f"{self.channel_info}: {exc}") from exc
        if not chunk:
            self._closed = True
            raise BridgeError(f"{self.channel_info}: the server closed the connection")
        self._reader.buf += chunk
        rx = self._rx
        for opcode, payload in self._reader.messages():
            if opcode == _BINARY:
                if len(payload) < _FRAME.size or payload[0] != 1:
                    continue
                _, stamp, arbitration_id, dlc, flags = _FRAME.unpack_from(payload)
                data = payload[_FRAME.size : _FRAME.size + dlc]
                rx.append(
                    can.Message(
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
                        channel=self.channel_info,
                        is_rx=True,
                        check=False,
                    )
                )
            elif opcode == _PING:
                self._sock.sendall(_ws_frame(_PONG, payload, mask=True))
            elif opcode == _CLOSE:
                self._closed = True
            elif opcode == _TEXT:
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
                self._sock.sendall(_ws_frame(_CLOSE, _LEN16.pack(1000), mask=True))
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
            self._reader.buf += chunk
            if any(opcode == _CLOSE for opcode, _ in self._reader.messages()):
                return
