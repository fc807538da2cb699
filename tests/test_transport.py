"""The transport contract, written once and run against every transport the runtime drives.

After python-can's ``test/back2back_test.py``: two ends of one bus, the runtime's end under test
(the master's bus) and the far end (where the drives are). Transports:

* ``lockstep``: :class:`hil_sim.harness.lockstep.LockstepBus` on an in-process channel, simulated
  clock; the far end is another end of the channel (the lockstep HIL's own end is one).
* ``bridge``: :class:`hil_sim.bridge.BridgeBus` over 127.0.0.1 to the real-time HIL's server,
  :class:`hil_sim.harness.bridge.Bridge`, wall clock; the far end is that server as the HIL's
  loop uses it (``wait``, ``receive``, ``send``, ``flush``), adapted to a python-can bus here.

What the runtime relies on: frames both ways with their fields, in order; a copy made at send
(the master repacks one message every cycle); ``recv(timeout)`` returning None once the
transport's clock passed the timeout; python-can's filters; timestamps on
the transport's clock; error frames flagged as such (the master ignores them); shutdown.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import can
import pytest

from hil_sim.bridge import (
    BridgeBus,
    RxFrame,
    flagged_message,
    message_flags,
)
from hil_sim.harness.bridge import Bridge
from hil_sim.harness.lockstep import LockstepBus, LockstepClock
from rt_runtime.canbus.inprocess import InProcessChannel


class _ServerEnd(can.BusABC):
    """The bridge's far end as the real-time HIL drives it (``wait``, ``receive``, ``send``,
    ``flush``), as a bus: every flag and the sender's stamp both ways."""

    def __init__(self, bridge: Bridge) -> None:
        self.bridge = bridge
        self.channel_info = "HIL bridge"
        self._rx: deque[can.Message] = deque()
        super().__init__(channel="hil-bridge")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        stamp = msg.timestamp if msg.timestamp > 0.0 else None
        self.bridge.send(msg.arbitration_id, bytes(msg.data), message_flags(msg), stamp)
        self.bridge.flush()

    def _take(self, frame: RxFrame) -> None:
        self._rx.append(flagged_message(*frame))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._rx and self.bridge.wait(1.0 if timeout is None else timeout):
            self.bridge.receive(self._take)
            self.bridge.flush()
        return (self._rx.popleft() if self._rx else None), False

    def shutdown(self) -> None:
        self.bridge.close()
        super().shutdown()


@dataclass
class Pair:
    """Two ends of one transport and its clock."""

    bus: can.BusABC
    far: can.BusABC
    clock: Callable[[], float]
    simulated: bool


def _lockstep() -> Pair:
    channel = InProcessChannel("contract")
    clock = LockstepClock(lambda _t: None)
    bus = LockstepBus(channel, clock, lambda: None, 0.002)
    far = channel.open(clock=clock.now)
    return Pair(bus, far, clock.now, simulated=True)


def _bridge() -> Pair:
    bridge = Bridge(0)
    made: list[BridgeBus] = []
    connect = threading.Thread(target=lambda: made.append(BridgeBus(bridge.port)))
    connect.start()
    deadline = time.monotonic() + 10.0
    while bridge.clients == 0 and time.monotonic() < deadline:
        if bridge.wait(0.05):
            bridge.receive(lambda _frame: None)
        bridge.flush()
    connect.join(10.0)
    assert made, "the bridge did not connect"
    return Pair(made[0], _ServerEnd(bridge), time.time, simulated=False)


@pytest.fixture(params=["lockstep", "bridge"])
def pair(request: pytest.FixtureRequest) -> Iterator[Pair]:
    p = _lockstep() if request.param == "lockstep" else _bridge()
    yield p
    p.far.shutdown()
    p.bus.shutdown()


def _frame(arbitration_id: int, data: bytes, timestamp: float = 0.0) -> can.Message:
    return can.Message(
        arbitration_id=arbitration_id, data=data, is_extended_id=False, timestamp=timestamp
    )


def _same(got: can.Message | None, want: can.Message) -> None:
    assert got is not None, f"nothing received for {want}"
    assert got.arbitration_id == want.arbitration_id
    assert bytes(got.data) == bytes(want.data)
    assert got.dlc == len(want.data)
    assert got.is_extended_id == want.is_extended_id
    assert got.is_error_frame == want.is_error_frame
    assert not got.is_remote_frame


class TestTransport:
    """One contract, every transport (parametrised by the ``pair`` fixture)."""

    def test_a_frame_reaches_the_far_end(self, pair: Pair) -> None:
        sent = _frame(0x201, bytes(range(8)))
        pair.bus.send(sent)
        _same(pair.far.recv(1.0), sent)

    def test_a_frame_reaches_the_runtime(self, pair: Pair) -> None:
        sent = _frame(0x181, b"\x10\x20\x30")
        pair.far.send(sent)
        _same(pair.bus.recv(1.0), sent)

    def test_empty_and_extended_frames(self, pair: Pair) -> None:
        sync = _frame(0x080, b"")
        ext = can.Message(arbitration_id=0x1ABCDEF, data=b"\x09", is_extended_id=True)
        pair.bus.send(sync)
        pair.bus.send(ext)
        _same(pair.far.recv(1.0), sync)
        _same(pair.far.recv(1.0), ext)
        pair.far.send(ext)
        _same(pair.bus.recv(1.0), ext)

    def test_order_is_kept_both_ways(self, pair: Pair) -> None:
        frames = [_frame(0x100 + i % 0x600, i.to_bytes(2, "little")) for i in range(200)]
        for msg in frames:
            pair.bus.send(msg)
        for msg in frames:
            _same(pair.far.recv(1.0), msg)
        for msg in frames:
            pair.far.send(msg)
        for msg in frames:
            _same(pair.bus.recv(1.0), msg)

    def test_a_cycle_sent_at_once_arrives_in_order(self, pair: Pair) -> None:
        # The master's cycle through the optional send_many where the bus has it.
        frames = [_frame(0x201 + i, bytes([i]) * 8) for i in range(3)] + [_frame(0x080, b"")]
        send_many = getattr(pair.bus, "send_many", None)
        for _ in range(2):
            if send_many is not None:
                send_many(frames)
            else:
                for msg in frames:
                    pair.bus.send(msg)
        for msg in frames + frames:
            _same(pair.far.recv(1.0), msg)

    def test_the_sender_may_reuse_its_message(self, pair: Pair) -> None:
        msg = _frame(0x201, bytes(8))
        pair.bus.send(msg)
        msg.arbitration_id = 0x202
        msg.data[0] = 0xFF
        pair.bus.send(msg)
        _same(pair.far.recv(1.0), _frame(0x201, bytes(8)))
        _same(pair.far.recv(1.0), _frame(0x202, b"\xff" + bytes(7)))

    def test_an_empty_receive_returns_none_when_its_clock_has_passed_the_timeout(
        self, pair: Pair
    ) -> None:
        for timeout_s in (0.0, 0.001, 0.05):
            t0 = pair.clock()
            assert pair.bus.recv(timeout_s) is None
            waited_s = pair.clock() - t0
            assert waited_s >= timeout_s - 1e-6, (timeout_s, waited_s)
            if pair.simulated:
                # Simulated time: the clock moves by exactly the timeout.
                assert waited_s == pytest.approx(timeout_s, abs=1e-12)

    def test_a_frame_already_queued_returns_at_once(self, pair: Pair) -> None:
        pair.far.send(_frame(0x701, b"\x05"))
        time.sleep(0.01)
        t0 = pair.clock()
        _same(pair.bus.recv(0.5), _frame(0x701, b"\x05"))
        if pair.simulated:
            assert pair.clock() == t0

    def test_filters_pass_only_matching_frames(self, pair: Pair) -> None:
        pair.bus.set_filters([{"can_id": 0x180, "can_mask": 0x780, "extended": False}])
        for cob in (0x201, 0x181, 0x702, 0x182, 0x080):
            pair.far.send(_frame(cob, b"\x01"))
        got = [pair.bus.recv(1.0), pair.bus.recv(1.0)]
        assert [m.arbitration_id for m in got if m is not None] == [0x181, 0x182]
        assert pair.bus.recv(0.05) is None
        pair.bus.set_filters(None)
        pair.far.send(_frame(0x201, b"\x02"))
        _same(pair.bus.recv(1.0), _frame(0x201, b"\x02"))

    def test_timestamps_are_send_times_on_the_transport_clock(self, pair: Pair) -> None:
        # The runtime stamps what it sends on the transport's clock (the master: time.time()
        # for a bridge; the lockstep bus stamps its simulated time itself).
        before = pair.clock()
        pair.bus.send(_frame(0x080, b"", timestamp=pair.clock()))
        after = pair.clock()
        got = pair.far.recv(1.0)
        assert got is not None and before <= got.timestamp <= after
        before = pair.clock()
        pair.far.send(_frame(0x181, b"\x01"))
        after = pair.clock()
        got = pair.bus.recv(1.0)
        assert got is not None and before <= got.timestamp <= after

    def test_error_frames_arrive_flagged(self, pair: Pair) -> None:
        error = can.Message(arbitration_id=0x20000080, is_error_frame=True, data=bytes(8))
        pair.far.send(error)
        pair.far.send(_frame(0x181, b"\x01"))
        got = pair.bus.recv(1.0)
        assert got is not None and got.is_error_frame
        _same(pair.bus.recv(1.0), _frame(0x181, b"\x01"))

    def test_every_flag_arrives_both_ways(self, pair: Pair) -> None:
        frames = [
            can.Message(arbitration_id=0x123, is_fd=True, bitrate_switch=True,
                        error_state_indicator=True, data=bytes(range(12)), is_extended_id=False),
            can.Message(arbitration_id=0x1ABCDEF, is_fd=True, data=bytes(64)),
            can.Message(arbitration_id=0x201, is_remote_frame=True, is_extended_id=False),
        ]  # fmt: skip
        for send, recv in ((pair.bus, pair.far), (pair.far, pair.bus)):
            for msg in frames:
                send.send(msg)
            for msg in frames:
                got = recv.recv(1.0)
                assert got is not None, f"nothing received for {msg}"
                assert (got.arbitration_id, bytes(got.data)) == (msg.arbitration_id, msg.data)
                fields = ("is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
                          "bitrate_switch", "error_state_indicator")  # fmt: skip
                assert [getattr(got, f) for f in fields] == [getattr(msg, f) for f in fields]

    def test_shutdown_ends_the_bus(self, pair: Pair) -> None:
        pair.bus.send(_frame(0x201, b"\x01"))
        pair.bus.shutdown()
        pair.bus.shutdown()  # idempotent
        with pytest.raises(can.CanOperationError):
            pair.bus.send(_frame(0x201, b"\x02"))
        with pytest.raises(can.CanOperationError):
            pair.bus.recv(0.0)
        # What was sent before the shutdown still arrives; nothing after it.
        _same(pair.far.recv(1.0), _frame(0x201, b"\x01"))
        assert pair.far.recv(0.05) is None


def test_the_bridge_speaks_python_can_remote_protocol() -> None:
    """The runtime's end against python-can-remote's own server (python-can's ``virtual`` bus
    behind it): every frame kind both ways, the DLC of a remote frame included."""
    from can_remote import RemoteServer

    channel = f"contract-{time.monotonic_ns()}"
    server = RemoteServer(
        "127.0.0.1", 0, interface="virtual", channel=channel, preserve_timestamps=True
    )
    threading.Thread(target=server.serve_forever, daemon=True).start()
    far = can.Bus(interface="virtual", channel=channel)
    bus = BridgeBus(server.server_port)
    try:
        frames = [
            _frame(0x201, bytes(range(8)), timestamp=123.5),
            can.Message(arbitration_id=0x1ABCDEF, data=b"\x09", is_extended_id=True),
            can.Message(arbitration_id=0x200, is_remote_frame=True, dlc=4, is_extended_id=False),
            can.Message(arbitration_id=0x20000080, is_error_frame=True, data=bytes(8)),
        ]
        for msg in frames:
            bus.send(msg)
            got = far.recv(2.0)
            assert (
                got is not None
                and got.dlc == msg.dlc
                and got.is_remote_frame == (msg.is_remote_frame)
            )
            _same_kind = got.is_extended_id == msg.is_extended_id
            assert _same_kind and got.is_error_frame == msg.is_error_frame
            assert got.arbitration_id == msg.arbitration_id and got.data == msg.data
        assert far.recv(0.05) is None
        for msg in frames:
            far.send(msg)
            got = bus.recv(2.0)
            assert got is not None and got.dlc == msg.dlc
            assert got.is_remote_frame == msg.is_remote_frame
            assert got.is_extended_id == msg.is_extended_id
            assert got.is_error_frame == msg.is_error_frame
            assert got.arbitration_id == msg.arbitration_id and got.data == msg.data
        assert frames[0].timestamp == 123.5  # the sender's message is not touched
    finally:
        bus.shutdown()
        far.shutdown()
        server.shutdown()
        server.server_close()
