"""The daemon's control socket: a local unix stream socket speaking newline-delimited JSON.

Protocol: a client connects to the socket and sends requests, one JSON object per line,
``{"cmd": "<command>", ...arguments}``; the daemon answers each with one JSON object per line,
``{"ok": true, ...}`` or ``{"ok": false, "code": "<code>", "error": "<what was wrong and what
is allowed>"}``. Error codes:

=================== =====================================================================
``bad_json``        the line is not JSON, or not a JSON object
``bad_request``     ``cmd`` is missing or not a string
``unknown_command`` ``cmd`` names no command (the reply lists them)
``too_large``       the line exceeds :data:`MAX_REQUEST_BYTES` (the connection is closed)
``refused``         the command was understood and refused (unknown job, bad task, ...)
``faulted``         the command would move the arm and a fault is latched (the reply names
                    it); ``reset-fault`` first
``internal``        the command failed unexpectedly (logged; the daemon keeps running)
``denied``          the peer is neither the daemon's user nor root
``busy``            every client slot is taken by clients active within :data:`EVICT_IDLE_S`
``idle``            the connection had no request for ``idle_timeout_s``
                    (:data:`IDLE_TIMEOUT_S`), or gave its slot to a new client while idle
=================== =====================================================================

A handler refuses with ``refused`` by raising :class:`~rt_runtime.errors.ExcavatorRtError`,
with another code by raising :class:`RefusedError`. A bad request never stops the daemon.

Access: the socket is created owner-only (0600, bound under a 0177 umask so it is never
briefly wider) in a directory that must be owner-only (0700, created so when missing); the
server also checks the peer's credentials (SO_PEERCRED) and serves only its own user and root.

The server is a single-threaded ``selectors`` loop run by the daemon's main thread
(:meth:`ControlServer.poll`); other file descriptors (the signal wake-up pipe) can share it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import selectors
import socket
import stat
import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rt_runtime.errors import CommunicationError, ExcavatorRtError
from rt_runtime.service.config import ConfigKeyError, check_directory

__all__ = [
    "MAX_REQUEST_BYTES",
    "ControlServer",
    "Handler",
    "RefusedError",
    "check_socket_path",
    "request",
]

log = logging.getLogger("excavator-rtd.control")

#: Longest request line (bytes, newline excluded).
MAX_REQUEST_BYTES = 64 * 1024
#: Most connections served at once; more are answered with an error and closed.
MAX_CLIENTS = 16
#: A connection with no request for this long is closed (s).
IDLE_TIMEOUT_S = 30.0
#: With every client slot taken, a new client takes the slot of the connection idle longest,
#: when that one has been idle for at least this long (s).
EVICT_IDLE_S = 1.0

Handler = Callable[[dict[str, Any]], dict[str, Any]]


class RefusedError(ExcavatorRtError):
    """A command refused with its own error code (``faulted``) instead of ``refused``.

    Args:
        code: The reply's ``code``.
        message: The reply's ``error``: what was refused and why.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def _encode(obj: dict[str, Any]) -> bytes:
    return (json.dumps(obj, separators=(",", ":"), default=str) + "\n").encode("utf-8")


def _error(code: str, text: str) -> dict[str, Any]:
    return {"ok": False, "code": code, "error": text}


@dataclass
class _Conn:
    sock: socket.socket
    #: ``time.monotonic()`` of its connection or its latest bytes received.
    active_s: float = 0.0
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    closing: bool = False


def check_socket_path(path: Path, *, create: bool) -> bool:
    """What the control socket needs of ``paths.socket`` before it binds: an owner-only (0700)
    directory of this user's, and the path free (or a socket a daemon that died left).

    Args:
        path: The socket's path.
        create: Make a missing directory (0700) as a start does; False changes nothing
            (``excavator-rtd --check``): a missing directory must be creatable.

    Returns:
        True when a socket that no daemon serves is at the path (a start removes it).

    Raises:
        ConfigKeyError (``paths.socket``): The directory is accessible to others, owned by
            another user, or cannot be made; the path is another kind of file or a live
            daemon serves it.
    """
    d = path.parent
    key = "paths.socket"
    if not check_directory(d, key, create=create) and not create:
        return False  # made 0700 by the start
    st = d.stat()
    if st.st_uid != os.getuid():
        raise ConfigKeyError(
            key, f"directory {d} belongs to uid {st.st_uid}, not this user ({os.getuid()})"
        )
    if st.st_mode & 0o077:
        raise ConfigKeyError(
            key,
            f"directory {d} is accessible to others (mode {stat.S_IMODE(st.st_mode):04o}); "
            "the control socket needs an owner-only directory (0700) of its own, e.g. "
            "/run/excavator-rtd",
        )
    if not (path.exists() or path.is_symlink()):
        return False
    if not stat.S_ISSOCK(path.lstat().st_mode):
        raise ConfigKeyError(key, f"{path} exists and is not a socket")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.settimeout(0.5)
        probe.connect(str(path))
    except OSError:
        return True
    finally:
        probe.close()
    raise ConfigKeyError(key, f"another daemon serves {path}")


class ControlServer:
    """Serves JSON requests on a unix stream socket.

    Args:
        path: The socket path.
        commands: ``{name: handler}``; a handler takes the request object and returns the
            reply's fields (``ok: true`` is added); it raises
            :class:`~rt_runtime.errors.ExcavatorRtError` to refuse (``refused`` reply).
        max_request_bytes: Longest request line.
        idle_timeout_s: A connection with no request for this long is closed; with every
            one of :data:`MAX_CLIENTS` slots taken, a new client takes the slot of the one
            idle longest (idle at least :data:`EVICT_IDLE_S`).

    Attributes:
        requests: Requests handled (any outcome).
    """

    def __init__(
        self,
        path: Path,
        commands: Mapping[str, Handler],
        max_request_bytes: int = MAX_REQUEST_BYTES,
        idle_timeout_s: float = IDLE_TIMEOUT_S,
    ) -> None:
        self.path = Path(path)
        self.commands = dict(commands)
        self.max_request_bytes = max_request_bytes
        self.idle_timeout_s = float(idle_timeout_s)
        self.requests = 0
        self._sel = selectors.DefaultSelector()
        self._listener: socket.socket | None = None
        self._conns: dict[int, _Conn] = {}
        self._inode: tuple[int, int] | None = None

    # -- set-up ---------------------------------------------------------------------------------

    def bind(self) -> None:
        """Create the socket (owner-only) in an owner-only directory and listen.

        Raises:
            ConfigKeyError (``paths.socket``): The directory is accessible to others or owned
                by another user, the path is taken by another file or a live daemon, or the
                bind failed.
        """
        key = "paths.socket"
        if check_socket_path(self.path, create=True):
            self.path.unlink()  # left by a daemon that died
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o177)
        try:
            sock.bind(str(self.path))
        except OSError as exc:
            sock.close()
            raise ConfigKeyError(key, f"cannot bind {self.path}: {exc.strerror or exc}") from exc
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        sock.listen(MAX_CLIENTS)
        sock.setblocking(False)
        st = self.path.stat()
        self._inode = (st.st_dev, st.st_ino)
        self._listener = sock
        self._sel.register(sock, selectors.EVENT_READ, self._accept)

    def add_reader(self, fd: int, callback: Callable[[], None]) -> None:
        """Have :meth:`poll` call ``callback()`` when ``fd`` is readable (e.g. a wake-up pipe)."""
        self._sel.register(fd, selectors.EVENT_READ, lambda _key: callback())

    def close(self) -> None:
        """Close every connection and the listener; remove the socket file if still ours."""
        for conn in list(self._conns.values()):
            self._drop(conn)
        if self._listener is not None:
            self._sel.unregister(self._listener)
            self._listener.close()
            self._listener = None
            with contextlib.suppress(OSError):
                st = self.path.stat()
                if (st.st_dev, st.st_ino) == self._inode:
                    self.path.unlink()
        self._sel.close()

    # -- serving --------------------------------------------------------------------------------

    def poll(self, timeout_s: float | None) -> None:
        """Serve what is ready within ``timeout_s`` (None: block until something is), then
        close the connections idle longer than ``idle_timeout_s``."""
        if self._conns and (timeout_s is None or timeout_s > self.idle_timeout_s):
            timeout_s = self.idle_timeout_s  # wake up to time the idle ones out
        for key, events in self._sel.select(timeout_s):
            if isinstance(key.data, _Conn):
                self._service(key.data, events)
            else:
                key.data(key)
        now = time.monotonic()
        for conn in list(self._conns.values()):
            if now - conn.active_s > self.idle_timeout_s and not conn.outbuf:
                self._reply_now(conn, _error("idle", self._idle_text()))
                self._drop(conn)

    def _idle_text(self) -> str:
        return f"no request for {self.idle_timeout_s:g} s: connection closed"

    def _accept(self, _key: selectors.SelectorKey) -> None:
        assert self._listener is not None
        try:
            sock, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        now = time.monotonic()
        conn = _Conn(sock, active_s=now)
        if len(self._conns) >= MAX_CLIENTS:
            idlest = min(self._conns.values(), key=lambda c: c.active_s)
            if now - idlest.active_s < EVICT_IDLE_S or idlest.outbuf:
                self._reply_now(conn, _error("busy", f"{MAX_CLIENTS} clients are being served"))
                sock.close()
                return
            self._reply_now(idlest, _error("idle", "connection closed to serve another client"))
            self._drop(idlest)
        if not self._peer_allowed(sock):
            self._reply_now(conn, _error("denied", "only the daemon's user and root may connect"))
            sock.close()
            return
        self._conns[sock.fileno()] = conn
        self._sel.register(sock, selectors.EVENT_READ, conn)

    @staticmethod
    def _peer_allowed(sock: socket.socket) -> bool:
        try:
            creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        except OSError:
            return False
        _pid, uid, _gid = struct.unpack("3i", creds)
        return uid in (0, os.getuid())

    @staticmethod
    def _reply_now(conn: _Conn, obj: dict[str, Any]) -> None:
        with contextlib.suppress(OSError):
            conn.sock.send(_encode(obj))

    def _drop(self, conn: _Conn) -> None:
        fd = conn.sock.fileno()
        if fd >= 0 and self._conns.pop(fd, None) is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(conn.sock)
        conn.sock.close()

    def _service(self, conn: _Conn, events: int) -> None:
        if events & selectors.EVENT_READ and not conn.closing:
            try:
                data = conn.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                self._drop(conn)
                return
            if data == b"":
                conn.closing = True
            elif data:
                conn.active_s = time.monotonic()
                conn.inbuf += data
                self._handle_lines(conn)
        if conn.outbuf:
            try:
                sent = conn.sock.send(conn.outbuf)
                del conn.outbuf[:sent]
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                self._drop(conn)
                return
        if conn.closing and not conn.outbuf:
            self._drop(conn)
            return
        want = selectors.EVENT_WRITE if conn.outbuf else 0
        if not conn.closing:
            want |= selectors.EVENT_READ
        self._sel.modify(conn.sock, want, conn)

    def _handle_lines(self, conn: _Conn) -> None:
        while True:
            nl = conn.inbuf.find(b"\n")
            if nl < 0:
                if len(conn.inbuf) > self.max_request_bytes:
                    conn.outbuf += _encode(
                        _error(
                            "too_large",
                            f"request longer than {self.max_request_bytes} bytes without a "
                            "newline; the connection is closed",
                        )
                    )
                    conn.inbuf.clear()
                    conn.closing = True
                return
            line = bytes(conn.inbuf[:nl])
            del conn.inbuf[: nl + 1]
            if len(line) > self.max_request_bytes:
                reply = _error("too_large", f"request longer than {self.max_request_bytes} bytes")
            elif not line.strip():
                continue
            else:
                reply = self.handle_line(line)
            conn.outbuf += _encode(reply)

    def handle_line(self, line: bytes) -> dict[str, Any]:
        """The reply to one request line (never raises)."""
        self.requests += 1
        try:
            req = json.loads(line)
        except (ValueError, UnicodeDecodeError) as exc:
            return _error("bad_json", f"request is not JSON: {exc}")
        if not isinstance(req, dict):
            return _error("bad_json", f"request must be a JSON object, got {type(req).__name__}")
        cmd = req.get("cmd")
        if not isinstance(cmd, str):
            return _error("bad_request", 'request needs "cmd": one of ' + ", ".join(self.commands))
        handler = self.commands.get(cmd)
        if handler is None:
            return _error(
                "unknown_command", f"unknown command {cmd!r}; allowed: {', '.join(self.commands)}"
            )
        try:
            out = handler(req)
        except RefusedError as exc:
            return _error(exc.code, str(exc))
        except ExcavatorRtError as exc:
            return _error("refused", str(exc))
        except Exception as exc:  # a bug in a handler must not take the daemon down
            log.exception("control command %s failed", cmd)
            return _error("internal", f"{cmd} failed: {type(exc).__name__}: {exc}")
        return {"ok": True, **out}


def request(path: str | Path, obj: dict[str, Any], timeout_s: float = 10.0) -> dict[str, Any]:
    """Send one request to the daemon and return its reply.

    Args:
        path: The control socket.
        obj: The request (``{"cmd": ..., ...}``).
        timeout_s: Time allowed to connect and for the reply.

    Returns:
        The reply object (check ``reply["ok"]``).

    Raises:
        CommunicationError: No daemon at ``path``, or no or a malformed reply.
    """
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    try:
        try:
            sock.connect(str(path))
        except OSError as exc:
            raise CommunicationError(
                f"cannot connect to the daemon's control socket {path}: {exc.strerror or exc} "
                "(is excavator-rtd running? see --socket)"
            ) from exc
        buf = bytearray()
        try:
            sock.sendall(_encode(obj))
            while b"\n" not in buf:
                chunk = sock.recv(65536)
                if not chunk:
                    break
                buf += chunk
        except OSError as exc:
            raise CommunicationError(f"control socket {path}: {exc}") from exc
    finally:
        sock.close()
    line = bytes(buf).split(b"\n", 1)[0]
    try:
        reply = json.loads(line)
    except ValueError as exc:
        raise CommunicationError(f"control socket {path}: malformed reply {line[:200]!r}") from exc
    if not isinstance(reply, dict):
        raise CommunicationError(f"control socket {path}: reply is not an object: {reply!r}")
    return reply
