"""The harness: ``bench hil`` (lockstep speed and whose time a period is) and the real-time HIL's
websocket bridge (python-can-remote's protocol served in one loop, 127.0.0.1 only)."""

from __future__ import annotations

import json
import math
import threading
import time
from typing import Any

import can
import numpy as np
import pytest
from can_remote import RemoteBus

from hil_sim.harness.bench import bench_hil, bench_step, format_report
from hil_sim.harness.bridge import Bridge, RxFrame
from hil_sim.harness.lockstep import LockstepHil
from rt_runtime.canbus import CanMaster
from rt_runtime.cli import build_parser, main
from rt_runtime.rig import load_rig

# -- bench hil ---------------------------------------------------------------------------------


def test_bench_hil_is_a_bench_subcommand_from_an_entry_point() -> None:
    args = build_parser().parse_args(["bench", "hil", "--task", "B", "--seconds", "2", "--json"])
    assert (args.task, args.seconds, args.json) == ("B", 2.0, True)
    assert args.handler.__module__ == "hil_sim.harness.bench"


def test_bench_hil_refuses_a_negative_duration(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "hil", "--seconds", "-1"]) == 2
    assert "--seconds" in capsys.readouterr().out


def test_bench_hil_runs_a_dig_and_says_whose_time_it_was(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["bench", "hil", "--max-digs", "1", "--seconds", "0.2", "--no-calibration", "--json"]
    assert main(argv) == 0
    r = json.loads(capsys.readouterr().out)
    task = r["task"]
    assert (task["task"], task["status"], task["digs"]) == ("A", "done", 1)
    assert task["sim_s"] > 5.0 and task["speed"] == pytest.approx(task["sim_s"] / task["wall_s"])
    assert 0.0 < task["hil_share"] < 1.0
    assert task["hil_s"] < task["wall_s"] and task["runtime_s"] > 0.0
    for part in ("hil_us", "runtime_us"):
        assert 0.0 < task[part]["p50"] <= task[part]["p99"] <= task[part]["max"], task[part]
    assert r["step"]["periods"] == 100


def test_bench_hil_text_says_whose_time_it_was() -> None:
    r = bench_hil(max_digs=1, step_seconds=0.2)
    text = format_report(r)
    assert "x real time" in text and "HIL share" in text and "models alone" in text


def test_the_step_measurement_replays_digs_for_the_machine_time_asked() -> None:
    r = bench_step(load_rig("scale_model"), 0.5)
    assert r.periods == 250 and r.digs == 1 and r.clock == "wall"
    for part in (r.frames_us, r.advance_us, r.total_us):
        assert part.max is not None
        assert 0.0 < part.p50 <= part.p99 <= part.max, part
    assert r.total_us.p50 >= r.advance_us.p50


def test_the_lockstep_hil_splits_each_period_into_its_own_time_and_the_rest() -> None:
    rig = load_rig("scale_model")
    with LockstepHil(rig, np.radians([30.0, -90.0, -60.0])) as hil:
        master = CanMaster(hil.master_bus, rig, period_s=0.002)
        master.boot(hil.clock.now, 1.0)
        master.enable(hil.clock.now, 1.0)
        hold = master.feedback.position_um.copy()
        before = len(hil.cost.sync_wall_ns)
        for k in range(200):
            master.write_setpoints(hold, np.zeros_like(hold))
            master.read_feedback(hil.clock.now(), 0.0005)
            master.heartbeat(hil.clock.now())
            hil.clock.sleep_until((k + 1) * 0.002 + 1.0)
        summary = hil.cost.summary()
    assert len(hil.cost.sync_wall_ns) - before == 200
    assert summary.periods == len(hil.cost.sync_wall_ns) - 1
    assert summary.hil_us.max is not None and 0.0 < summary.hil_us.p50 <= summary.hil_us.max
    assert summary.runtime_us.p50 > 0.0
    assert summary.hil_s + summary.runtime_s == pytest.approx(summary.wall_s, rel=1e-9)
    wall, hil_ns = hil.cost.periods()
    assert wall.shape == hil_ns.shape and bool(np.all(hil_ns <= wall))


# -- the bridge ---------------------------------------------------------------------------------


class _Served:
    """A bridge pumped by the test (the HIL's loop stands in): received frames are kept."""

    def __init__(self) -> None:
        self.bridge = Bridge(0)
        self.received: list[RxFrame] = []

    def pump(self, seconds: float = 0.05) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if self.bridge.wait(0.005):
                self.bridge.receive(self.received.append)
            self.bridge.flush()

    def connect(self) -> RemoteBus:
        """A python-can ``remote`` client; the bridge answers its handshake meanwhile."""
        box: dict[str, Any] = {}

        def client() -> None:
            box["bus"] = RemoteBus(f"ws://127.0.0.1:{self.bridge.port}/")

        t = threading.Thread(target=client)
        t.start()
        end = time.monotonic() + 5.0
        while t.is_alive() and time.monotonic() < end:
            self.pump(0.01)
        t.join(1.0)
        assert "bus" in box, "the client did not connect"
        return box["bus"]

    def shutdown(self, bus: RemoteBus) -> None:
        """Close a client: it waits for the bridge's close frame, which the pump sends."""
        t = threading.Thread(target=bus.shutdown)
        t.start()
        end = time.monotonic() + 5.0
        while t.is_alive() and time.monotonic() < end:
            self.pump(0.01)
        t.join(1.0)
        assert not t.is_alive(), "the client did not close"


@pytest.fixture
def served() -> Any:
    s = _Served()
    yield s
    s.bridge.close()


def test_the_bridge_binds_loopback_only(served: _Served) -> None:
    assert served.bridge._listen.getsockname()[0] == "127.0.0.1"


def test_a_remote_client_reaches_the_hil_and_hears_it(served: _Served) -> None:
    bus = served.connect()
    try:
        sent_at = time.time()
        bus.send(can.Message(arbitration_id=0x201, data=b"\x01\x02\x03\x04\x05\x06\x07\x08",
                             is_extended_id=False, timestamp=sent_at))  # fmt: skip
        bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        served.pump()
        assert [(f[1], f[2], f[3]) for f in served.received] == [
            (0x201, b"\x01\x02\x03\x04\x05\x06\x07\x08", 0),
            (0x080, b"", 0),
        ]
        assert served.received[0][0] == sent_at
        served.bridge.send(0x181, b"\x10\x20\x30")
        served.bridge.send(0x701, b"\x05")
        served.bridge.flush()
        first = bus.recv(1.0)
        second = bus.recv(1.0)
        assert first is not None and second is not None
        assert (first.arbitration_id, bytes(first.data), first.dlc) == (0x181, b"\x10\x20\x30", 3)
        assert (second.arbitration_id, bytes(second.data)) == (0x701, b"\x05")
        assert abs(first.timestamp - time.time()) < 5.0
    finally:
        served.shutdown(bus)


def test_frames_of_one_client_reach_the_others_but_not_itself(served: _Served) -> None:
    a = served.connect()
    b = served.connect()
    try:
        a.send(can.Message(arbitration_id=0x77E, data=b"\x05", is_extended_id=False))
        served.pump()
        got = b.recv(1.0)
        assert got is not None and (got.arbitration_id, bytes(got.data)) == (0x77E, b"\x05")
        assert a.recv(0.05) is None
        assert [f[1] for f in served.received] == [0x77E]
    finally:
        served.shutdown(a)
        served.shutdown(b)


def test_a_client_that_closes_is_let_go(served: _Served) -> None:
    served.shutdown(served.connect())
    assert served.bridge._clients == {}
    served.bridge.send(0x181, b"\x00")  # nobody to send to: nothing queued, nothing dropped
    assert served.bridge.dropped == 0


def test_a_client_that_does_not_read_never_stalls_the_hil(served: _Served) -> None:
    bus = served.connect()
    try:
        for k in range(4_000_000):
            served.bridge.send(0x181, b"\x00" * 8)
            if k % 64 == 0:
                served.bridge.flush()
                if served.bridge.dropped:
                    break
        assert served.bridge.dropped > 0  # the HIL went on sending: frames dropped, no stall
    finally:
        bus.socket.close()
        can.BusABC.shutdown(bus)


def test_unknown_events_are_answered_with_an_error(served: _Served) -> None:
    bus = served.connect()
    try:
        bus.remote_protocol.send("periodic_start", {"period": 0.01, "msg": {}})
        served.pump()
        with pytest.raises(can.CanError, match="not served"):
            bus.recv(1.0)
    finally:
        served.shutdown(bus)


def test_a_json_protocol_client_is_served_too(served: _Served) -> None:
    import base64
    import os
    import socket

    sock = socket.create_connection(("127.0.0.1", served.bridge.port))
    try:
        key = base64.b64encode(os.urandom(16)).decode()
        sock.sendall(
            (
                "GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                "Sec-WebSocket-Protocol: can.json.v1\r\n\r\n"
            ).encode()
        )
        served.pump()
        head = sock.recv(4096)
        assert head.startswith(b"HTTP/1.1 101") and b"can.json.v1" in head
        mask = b"\x01\x02\x03\x04"

        def send_event(event: dict[str, Any]) -> None:
            body = json.dumps(event).encode()
            sock.sendall(bytes([0x81, 0x80 | len(body)]) + mask
                         + bytes(c ^ mask[i % 4] for i, c in enumerate(body)))  # fmt: skip
            served.pump()

        # No frame reaches a client before its bus is open: python-can-remote's client takes
        # the first event after its bus_request for the response.
        served.bridge.send(0x701, b"\x05")
        served.bridge.flush()
        send_event({"type": "bus_request", "payload": {"config": {}}})
        sock.settimeout(1.0)
        frame = sock.recv(4096)
        n = frame[1] & 0x7F
        assert json.loads(frame[2 : 2 + n].decode())["type"] == "bus_response"
        frame_json = {"arbitration_id": 0x202, "data": [1, 2], "timestamp": 0.0}
        send_event({"type": "message", "payload": frame_json})
        assert [(f[1], f[2]) for f in served.received] == [(0x202, b"\x01\x02")]
        served.bridge.send(0x182, b"\x07")
        served.bridge.flush()
        sock.settimeout(1.0)
        frame = sock.recv(4096)
        assert frame[0] == 0x81  # a final text frame, unmasked
        n, start = (int.from_bytes(frame[2:4], "big"), 4) if frame[1] == 126 else (frame[1], 2)
        reply = json.loads(frame[start : start + n].decode())
        assert reply["type"] == "message"
        assert (reply["payload"]["arbitration_id"], reply["payload"]["data"]) == (0x182, [7])
        assert math.isfinite(reply["payload"]["timestamp"])
    finally:
        sock.close()
