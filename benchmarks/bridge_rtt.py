"""Round trip and throughput of the 127.0.0.1 CAN bridge, against python-can-remote's classes.

Role: the measurement behind the bridge's design (:mod:`hil_sim.bridge`). A far-end process
answers every SYNC with seven frames (three TPDO1, three TPDO2, the VCU status), as the HIL's
drives do; the runtime's end sends one cycle as the master does (three RPDO1, one SYNC; in one
``send_many`` where the bus has it) and waits for the seven answers. Each cycle times SYNC sent
(the batch's send with ``send_many``) -> last answer received (``time.perf_counter_ns``). Two
bridges run in the same invocation, alternating in blocks so a change of machine load hits
both:

* ``remote``: python-can-remote's ``RemoteServer`` serving python-can's ``virtual`` bus, the far
  end a ``virtual`` bus on it; the runtime's end ``can_remote.RemoteBus``.
* ``bridge``: the real-time HIL's server, :class:`hil_sim.harness.bridge.Bridge`, driven as the
  HIL's loop drives it (``wait``, ``receive``, the answers to a SYNC flushed at once); the
  runtime's end :class:`hil_sim.bridge.BridgeBus`.

It prints, per bridge, the round trip's p50 / p99 in microseconds and the frames per second
(both directions) over all cycles, and the ratios (round trip remote / bridge, throughput
bridge / remote). A far end idle for ``IDLE_LIMIT`` seconds exits by itself.

Usage::

    .venv/bin/python benchmarks/bridge_rtt.py [--cycles N] [--blocks B]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

import can
import numpy as np

ANSWERS = (0x181, 0x182, 0x183, 0x281, 0x282, 0x283, 0x1F0)
REQUESTS = (0x201, 0x202, 0x203)
#: A far end with nothing to do for this many seconds exits (its parent died).
IDLE_LIMIT = 10


def _far_remote() -> None:
    import threading

    from can_remote import RemoteServer

    server = RemoteServer(
        "127.0.0.1", 0, interface="virtual", channel="bench", preserve_timestamps=True
    )
    threading.Thread(target=server.serve_forever, daemon=True).start()
    sys.setswitchinterval(2e-4)
    bus = can.Bus(interface="virtual", channel="bench")
    print(f"READY {server.server_port}", flush=True)
    payload = bytes(8)
    idle = 0
    while idle < IDLE_LIMIT:
        msg = bus.recv(1.0)
        if msg is None:
            idle += 1
            continue
        idle = 0
        if msg.arbitration_id == 0x080:
            for cob in ANSWERS:
                bus.send(can.Message(arbitration_id=cob, data=payload, is_extended_id=False))
        elif msg.arbitration_id == 0x000:
            break
    bus.shutdown()
    server.shutdown()


def _far_bridge() -> None:
    from hil_sim.bridge import RxFrame
    from hil_sim.harness.bridge import Bridge

    bridge = Bridge(0)
    print(f"READY {bridge.port}", flush=True)
    payload = bytes(8)
    running = True

    def on_frame(frame: RxFrame) -> None:
        nonlocal running
        cob = frame[1]
        if cob == 0x080:
            for answer in ANSWERS:
                bridge.send(answer, payload)
            bridge.flush()
        elif cob == 0x000:
            running = False

    idle = 0
    while running and idle < IDLE_LIMIT:
        if bridge.wait(1.0):
            idle = 0
            bridge.receive(on_frame)
            bridge.flush()
        else:
            idle += 1
    bridge.close()


def _connect(kind: str) -> tuple[subprocess.Popen[str], can.BusABC]:
    proc = subprocess.Popen(
        [sys.executable, __file__, "--far", kind], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    port = int(proc.stdout.readline().split()[1])
    if kind == "remote":
        from can_remote import RemoteBus

        return proc, RemoteBus(f"ws://127.0.0.1:{port}/")
    from hil_sim.bridge import BridgeBus

    return proc, BridgeBus(port)


def _cycles(bus: can.BusABC, n: int) -> tuple[list[float], float, int]:
    rpdo = [can.Message(arbitration_id=c, data=bytes(8), is_extended_id=False) for c in REQUESTS]
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
    rtt: list[float] = []
    frames = 0
    t0 = time.perf_counter()
    cycle = [*rpdo, sync]
    send_many = getattr(bus, "send_many", None)
    for _ in range(n):
        if send_many is not None:
            stamp = time.time()
            for msg in cycle:
                msg.timestamp = stamp
            start = time.perf_counter_ns()
            send_many(cycle)
        else:
            for msg in rpdo:
                msg.timestamp = time.time()
                bus.send(msg)
            sync.timestamp = time.time()
            start = time.perf_counter_ns()
            bus.send(sync)
        got = 0
        while got < len(ANSWERS):
            if bus.recv(1.0) is None:
                break
            got += 1
        rtt.append((time.perf_counter_ns() - start) * 1e-3)
        frames += len(REQUESTS) + 1 + got
    return rtt, time.perf_counter() - t0, frames


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cycles", type=int, default=2000, help="cycles per block")
    p.add_argument("--blocks", type=int, default=3, help="blocks per bridge, alternating")
    p.add_argument("--far", choices=("remote", "bridge"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.far == "remote":
        _far_remote()
        return
    if args.far == "bridge":
        _far_bridge()
        return
    results: dict[str, tuple[list[float], float, int]] = {
        "remote": ([], 0.0, 0),
        "bridge": ([], 0.0, 0),
    }
    ends = {kind: _connect(kind) for kind in results}
    try:
        for _proc, bus in ends.values():
            _cycles(bus, 200)  # warm-up
        for _ in range(args.blocks):
            for kind, (_proc, bus) in ends.items():
                rtt, wall, frames = _cycles(bus, args.cycles)
                old = results[kind]
                results[kind] = (old[0] + rtt, old[1] + wall, old[2] + frames)
    finally:
        for _proc, bus in ends.values():
            bus.send(can.Message(arbitration_id=0x000, data=b"\x02\x00", is_extended_id=False))
            bus.shutdown()
        for proc, _bus in ends.values():
            proc.wait(10)
    summary = {}
    for kind, (rtt, wall, frames) in results.items():
        a = np.asarray(rtt)
        summary[kind] = (np.percentile(a, 50), np.percentile(a, 99), frames / wall)
        print(
            f"{kind:7s} SYNC -> 7 answers: p50 {summary[kind][0]:7.1f} us, "
            f"p99 {summary[kind][1]:7.1f} us; {summary[kind][2]:9.0f} frames/s ({len(a)} cycles)"
        )
    r, b = summary["remote"], summary["bridge"]
    print(
        f"round trip remote/bridge: p50 {r[0] / b[0]:.2f}x, p99 {r[1] / b[1]:.2f}x; "
        f"frames/s bridge/remote {b[2] / r[2]:.2f}x"
    )


if __name__ == "__main__":
    main()
