"""systemd's notify protocol (``sd_notify``) without a systemd library.

A service of ``Type=notify`` tells the service manager about itself by sending datagrams of
newline-separated ``KEY=value`` lines to the unix datagram socket named in ``$NOTIFY_SOCKET``
(a path, or an abstract-namespace name when it starts with ``@``). The daemon sends
``READY=1`` once the drives are enabled, ``WATCHDOG=1`` while its runner works as designed
(paced by ``$WATCHDOG_USEC``: the loop cycles, or it waits for a reset with a fault latched),
``STATUS=...`` on state changes, ``RELOADING=1`` / ``READY=1`` around a SIGHUP reload and
``STOPPING=1`` on shutdown. Outside systemd (no ``$NOTIFY_SOCKET``) every
call does nothing, so the daemon runs the same by hand. A send never waits: a manager that
does not read its socket loses notifications, and the daemon keeps serving.

Protocol reference: ``man 3 sd_notify``; the wire format is what systemd's own ``sd_notify()``
sends, which is short enough to write here rather than depend on a binding.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Mapping

__all__ = ["Notifier", "watchdog_interval_s"]


class Notifier:
    """Sends notifications to the service manager.

    Args:
        address: The ``$NOTIFY_SOCKET`` value; None reads the environment. Empty or unset:
            notifications are dropped.

    Attributes:
        address: The socket address (abstract names with a leading NUL), or None.
        sent: Messages sent (for tests and status).
    """

    def __init__(self, address: str | None = None) -> None:
        text = os.environ.get("NOTIFY_SOCKET", "") if address is None else address
        self.address: str | None = None
        if text:
            self.address = "\0" + text[1:] if text.startswith("@") else text
        self.sent = 0
        self._sock: socket.socket | None = None

    @property
    def enabled(self) -> bool:
        """True when there is a service manager to tell."""
        return self.address is not None

    def notify(self, *lines: str) -> bool:
        """Send one datagram of ``KEY=value`` lines.

        Args:
            lines: The lines, e.g. ``"READY=1"``, ``"STATUS=idle"``.

        Returns:
            True when sent; False without a service manager or when the send failed or would
            block (a notification is never worth stopping the daemon for: the send never waits
            for a manager that does not read its socket).
        """
        if self.address is None:
            return False
        payload = "\n".join(line.replace("\n", " ") for line in lines).encode("utf-8")
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(payload, socket.MSG_DONTWAIT, self.address)
        except OSError:
            return False
        self.sent += 1
        return True

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (with a ``STATUS=`` line when given)."""
        return self.notify("READY=1", *(() if status is None else (f"STATUS={status}",)))

    def status(self, text: str) -> bool:
        """``STATUS=text`` (one line; newlines become spaces)."""
        return self.notify(f"STATUS={text}")

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the service is alive and healthy."""
        return self.notify("WATCHDOG=1")

    def reloading(self) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC`` (as ``Type=notify-reload`` requires)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify("RELOADING=1", f"MONOTONIC_USEC={usec}")

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1`` (with a ``STATUS=`` line when given)."""
        return self.notify("STOPPING=1", *(() if status is None else (f"STATUS={status}",)))

    def close(self) -> None:
        """Close the socket (a later notification reopens it)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def watchdog_interval_s(
    env: Mapping[str, str] | None = None, pid: int | None = None
) -> float | None:
    """How often to send ``WATCHDOG=1``: half of ``$WATCHDOG_USEC``, as sd_watchdog_enabled(3)
    advises.

    Args:
        env: The environment (default ``os.environ``).
        pid: This process's id (default ``os.getpid()``); ``$WATCHDOG_PID``, when set, must
            name it, else the watchdog is meant for another process.

    Returns:
        The interval (s), or None when the watchdog is not enabled for this process.
    """
    e = os.environ if env is None else env
    try:
        usec = int(e.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    if usec <= 0:
        return None
    wpid = e.get("WATCHDOG_PID")
    if wpid:
        try:
            if int(wpid) != (os.getpid() if pid is None else pid):
                return None
        except ValueError:
            return None
    return usec * 1e-6 / 2.0
