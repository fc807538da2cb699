"""sd_notify over $NOTIFY_SOCKET: the datagrams systemd would receive, byte for byte."""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from rt_runtime.service.notify import Notifier, watchdog_interval_s


@pytest.fixture
def manager(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    """A fake service manager: a unix datagram socket bound in tmp."""
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    yield path, sock
    sock.close()


def _recv(sock: socket.socket) -> str:
    return sock.recv(4096).decode()


def test_messages_are_systemd_lines(manager: tuple[str, socket.socket]) -> None:
    path, sock = manager
    n = Notifier(path)
    assert n.enabled
    assert n.ready("drives enabled")
    assert _recv(sock) == "READY=1\nSTATUS=drives enabled"
    assert n.status("running job 1\nsecond line")
    assert _recv(sock) == "STATUS=running job 1 second line"
    assert n.watchdog()
    assert _recv(sock) == "WATCHDOG=1"
    assert n.stopping()
    assert _recv(sock) == "STOPPING=1"
    assert n.reloading()
    lines = _recv(sock).split("\n")
    assert lines[0] == "RELOADING=1"
    assert lines[1].startswith("MONOTONIC_USEC=") and int(lines[1].split("=")[1]) > 0
    assert n.sent == 5
    n.close()


def test_environment_and_abstract_namespace(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"excavator-rtd-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        n = Notifier()
        assert n.address == "\0" + name
        assert n.ready()
        assert _recv(sock) == "READY=1"
    finally:
        sock.close()


def test_without_a_manager_nothing_is_sent(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled
    assert not n.ready() and not n.watchdog()
    assert n.sent == 0


def test_a_vanished_manager_is_not_an_error(tmp_path: Path) -> None:
    n = Notifier(str(tmp_path / "gone.sock"))
    assert n.enabled
    assert not n.watchdog()
    assert n.sent == 0


def test_watchdog_interval_is_half_of_watchdog_usec() -> None:
    pid = os.getpid()
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000"}, pid) == 1.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(pid)}, pid) == 1.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, pid) is None
    assert watchdog_interval_s({}, pid) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "0"}, pid) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "soon"}, pid) is None
