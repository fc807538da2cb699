"""End to end: ``excavator-rtd`` in its own process against the real-time HIL in another.

The HIL process serves its bus on 127.0.0.1 (python-can-remote's protocol); the daemon is started
as a subprocess with a fake ``NOTIFY_SOCKET`` (a unix datagram socket bound here) and a
configuration whose bus is python-can's ``remote`` interface to that port. The test

1. waits for READY=1, submits a job (Yao's task A, stopped after ``MAX_DIGS`` digs so the run stays
   short) through the control socket; the job runs;
2. sends SIGTERM in the middle of the second dig: exit 0, STOPPING=1, and the daemon's bus trace
   shows every commanded RPDO1 step, frame to frame, within the limit guard's velocity,
   acceleration and jerk limits (to the micrometre rounding), and the drives disabled at the end
   (controlword 0x0000/0x0006 last, the drives' statusword confirming it);
3. restarts the daemon: it resumes the job at the interrupted dig (the next undone one) and
   finishes it; the trace of the second run is checked the same way;
4. throughout, a poller parses the job store every 20 ms: it is never half-written.

The settings are the shipped ones: the ``scale_model`` profile as shipped (the drives' SYNC
watchdog 20 ms, heartbeat timeout 150 ms, following-error window 5 mm) in the HIL and the
daemon, and the example configuration ``rt_runtime/service/excavator-rtd.example.toml`` with
only the bus (python-can's ``remote`` interface to the HIL's port) and the paths changed
(:func:`stock_config` checks that every other key is the example's: SCHED_FIFO 80, mlockall,
5 overruns in a row, 10 stale cycles). ``EXCAVATOR_E2E_RUNS=5`` runs the scenario five times
(each with a new HIL) to measure how often the stock settings hold on a machine. The HIL has no
terrain here: its terrain is cut only on explicit commands of a scenario runner, which the daemon
(like a rig) does not send, so a terrain would push back on every later dig as virgin soil; the
daemon's own material model follows the measured tip path either way. Timing figures (SYNC gaps,
round trips) are printed, not asserted. Skipped, with the reason, only if the HIL cannot start.

Host stalls. The drives' watchdog is right to stop the arm when the master falls silent for longer
than it, and a shared build machine can stop any process for tens of milliseconds. A latched
fault is therefore judged on the daemon's and the HIL's own evidence (:func:`conftest.host_stall`):
if the daemon's trace shows the master sent no SYNC for longer than the drives' watchdog and the
fault is that watchdog's EMCY, or the fault is the loop's own overrun stop, the host stalled the
master; if the fault is stale feedback and the HIL process's statistics show it answered a SYNC
the stale window or more after the master sent it, the host stalled the drives' stand-in. Either
way the daemon did what it must (fault latched, daemon up and answering, the job marked failed
with the fault); that attempt is printed and the scenario runs again with a new HIL, up to
``STALL_ATTEMPTS`` times. Any other fault fails the test at once, with the TPDO1 gaps of the
daemon's trace and the HIL's statistics.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from conftest import host_stall, max_sync_gap_s

from hil_sim.harness.realtime import RealtimeHilProcess
from rt_runtime.canbus.cia402 import DriveState, decode_state
from rt_runtime.canbus.pdo import RPDO1, RPDO2, TPDO2
from rt_runtime.canbus.traced import TracedBus
from rt_runtime.control.guard import StrokeLimits
from rt_runtime.errors import CommunicationError
from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import Rig, load_rig
from rt_runtime.service.config import DaemonConfig, load_config
from rt_runtime.service.control import request
from rt_runtime.service.daemon import TraceRecorder
from rt_runtime.service.jobstore import read_store

RIG = "scale_model"
PERIOD_S = 0.002
MAX_DIGS = 3
#: The HIL process stops by itself after this long, whatever happens to the test.
MAX_WALL_S = 600.0
NODES = (1, 2, 3)
#: The shipped example configuration the test runs with.
EXAMPLE_CONFIG = (
    Path(__file__).resolve().parents[1] / "rt_runtime/service/excavator-rtd.example.toml"
)
#: How many times the end-to-end scenario runs (``EXCAVATOR_E2E_RUNS``; default once).
E2E_RUNS = int(os.environ.get("EXCAVATOR_E2E_RUNS", "1"))
#: Scenario attempts when the host stalls the master beyond the drives' watchdog.
STALL_ATTEMPTS = 5
#: The keys :func:`stock_config` changes: the bus and the paths.
CHANGED_KEYS = ("bus.interface", "bus.channel", "paths.state_dir", "paths.socket", "paths.trace")


class Daemon:
    """``excavator-rtd`` as a subprocess with its own fake service manager."""

    def __init__(self, config: Path, tmp: Path, n: int) -> None:
        self.log_path = tmp / f"daemon-{n}.log"
        notify_path = tmp / f"notify-{n}.sock"
        self.manager = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.manager.bind(str(notify_path))
        self.messages: list[str] = []
        env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"}
        env.pop("WATCHDOG_PID", None)
        self._log = self.log_path.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rt_runtime.service.daemon", "--config", str(config)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
        )

    def log(self) -> str:
        return self.log_path.read_text()

    def drain(self, timeout_s: float = 0.0) -> None:
        self.manager.settimeout(timeout_s if timeout_s > 0 else 1e-3)
        try:
            while True:
                self.messages.append(self.manager.recv(4096).decode())
                self.manager.settimeout(1e-3)
        except (TimeoutError, BlockingIOError):
            pass

    def idle(self, seconds: float) -> None:
        """Let ``seconds`` pass, reading the notifications (:meth:`drain` returns at the first
        quiet millisecond after one arrives, so it is no sleep)."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0.0:
            self.drain(min(left, 0.1))

    def wait_for(self, line: str, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not any(line in m.split("\n") for m in self.messages):
            if self.proc.poll() is not None:
                pytest.fail(f"daemon exited ({self.proc.returncode}):\n{self.log()}")
            if time.monotonic() > end:
                pytest.fail(f"no {line} within {timeout_s} s:\n{self.log()}")
            self.drain(0.2)

    def stop(self, timeout_s: float = 60.0) -> int:
        self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            pytest.fail(f"daemon did not stop within {timeout_s} s:\n{self.log()}")
        self.drain(0.2)
        return code

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.manager.close()
        self._log.close()


class StorePoller:
    """Parses the job store every 20 ms on a thread; any failure is kept."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.reads = 0
        self.failures: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            if not self.path.exists():
                continue
            try:
                json.loads(self.path.read_bytes())
                read_store(self.path)
                self.reads += 1
            except Exception as exc:
                self.failures.append(repr(exc))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


def _until(pred: Callable[[], bool], timeout_s: float, what: str, daemon: Daemon) -> None:
    """Wait for ``pred`` (the daemon must stay up; its notifications are read meanwhile)."""
    end = time.monotonic() + timeout_s
    while not pred():
        if daemon.proc.poll() is not None:
            pytest.fail(f"daemon exited ({daemon.proc.returncode}) waiting for {what}:\n"
                        f"{daemon.log()}")  # fmt: skip
        if time.monotonic() > end:
            pytest.fail(f"{what}: not within {timeout_s} s:\n{daemon.log()}")
        daemon.drain(0.1)


def _job(store_path: Path) -> dict[str, Any]:
    doc = json.loads(store_path.read_text())
    job: dict[str, Any] = doc["jobs"][0]
    return job


def check_trace(path: Path, rig: Rig, enable_syncs: int) -> dict[str, float]:
    """Every commanded step within the guard's limits; the drives disabled at the end.

    The daemon commands from the end of ``CanMaster.enable`` on (its last target included:
    the daemon's hold must continue it without a step); what enable itself sends before (the
    drives' actual positions while they switch on) is measured and printed, not checked here.

    Returns:
        Printed figures: frames, the largest SYNC gap (s), enable's largest target step (um).
    """
    msgs = list(can.BLFReader(str(path)))
    assert msgs, f"empty trace {path}"
    v, a, j = StrokeLimits.from_rig(rig).as_arrays()
    T = PERIOD_S
    syncs = [i for i, m in enumerate(msgs) if m.arbitration_id == 0x080]
    last_enable_sync = syncs[enable_syncs - 1]
    enable_step_um = 0.0
    for axis, node in enumerate(NODES):
        ids = [i for i, m in enumerate(msgs) if m.arbitration_id == RPDO1.cob_id(node)]
        first = max(k for k, i in enumerate(ids) if i < last_enable_sync)  # enable's last
        rp1 = [msgs[i] for i in ids[first:]]
        assert len(rp1) > 100, (node, len(rp1))
        during = [RPDO1.codec.unpack(bytes(msgs[i].data))[0] for i in ids[: first + 1]]
        if len(during) > 1:
            enable_step_um = max(enable_step_um, float(np.abs(np.diff(during)).max()))
        pos = np.array([RPDO1.codec.unpack(bytes(m.data))[0] for m in rp1], np.float64) * 1e-6
        # Targets are rounded to 1 um: differences k carry up to 2^(k-1) um of rounding.
        for k, (limit, rounding) in enumerate(
            ((v[axis] * T, 1e-6), (a[axis] * T**2, 2e-6), (j[axis] * T**3, 4e-6)), start=1
        ):
            step = np.abs(np.diff(pos, k))
            worst = int(np.argmax(step))
            assert step[worst] <= limit + rounding + 1e-12, (
                f"{path.name}: node {node} difference {k} at RPDO1 #{worst}: "
                f"{step[worst] * 1e6:.3f} um > {limit * 1e6:.3f} um + rounding"
            )
        rp2 = [m for m in msgs if m.arbitration_id == RPDO2.cob_id(node)]
        controlword = RPDO2.codec.unpack(bytes(rp2[-1].data))[0]
        assert controlword in (0x0000, 0x0006), f"node {node}: last controlword {controlword:#06x}"
        after = [m for m in rp1 if m.timestamp > rp2[-1].timestamp]
        held = {RPDO1.codec.unpack(bytes(m.data))[0] for m in after}
        assert len(held) <= 1, f"node {node}: the target moved after the disable: {held}"
        tp2 = [m for m in msgs if m.arbitration_id == TPDO2.cob_id(node)]
        state = decode_state(TPDO2.codec.unpack(bytes(tp2[-1].data))[0])
        assert state not in (DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE), (
            f"node {node}: the drive still reports {state}"
        )
    sync_t = np.array([m.timestamp for m in msgs if m.arbitration_id == 0x080])
    return {
        "frames": float(len(msgs)),
        "max_sync_gap_s": round(float(np.diff(sync_t).max()), 4),
        "enable_step_um": enable_step_um,
    }


def _enable_syncs(daemon: Daemon) -> int:
    found = re.search(r"drives enabled after (\d+) SYNC", daemon.log())
    assert found, daemon.log()
    return int(found.group(1))


def test_trace_records_what_was_sent_and_received(tmp_path: Path) -> None:
    """The daemon's trace (fast, no HIL): both directions, the bytes at send time, an existing
    file kept, a SIGHUP reopen to another file."""
    path = tmp_path / "t" / "can.blf"
    path.parent.mkdir()
    path.write_bytes(b"old")
    recorder = TraceRecorder(path)
    assert (tmp_path / "t" / "can.1.blf").read_bytes() == b"old"
    # A name python-can reads a channel number out of (trailing digits) that no BLF field holds.
    channel = f"trace-{uuid.uuid4().hex}-99999999"
    peer = can.Bus(interface="virtual", channel=channel)
    bus = TracedBus(can.Bus(interface="virtual", channel=channel), recorder)
    try:
        msg = can.Message(arbitration_id=0x201, data=bytearray(8), is_extended_id=False)
        bus.send(msg)
        msg.data[0] = 7  # the master packs its next setpoint into the same message
        peer.send(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False))
        received = bus.recv(1.0)
        assert received is not None and received.arbitration_id == 0x181
        recorder.reopen(tmp_path / "t" / "second.asc")
        bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
    finally:
        recorder.close()
        bus.shutdown()
        peer.shutdown()
    frames = [(m.arbitration_id, bytes(m.data), m.is_rx) for m in can.BLFReader(str(path))]
    assert frames == [(0x201, bytes(8), False), (0x181, b"\x01\x02", True)]
    assert [m.arbitration_id for m in can.ASCReader(str(tmp_path / "t" / "second.asc"))] == [0x080]


def test_trace_rotates_and_keeps_a_bounded_number_of_files(tmp_path: Path) -> None:
    """The trace rotates at its size and keeps the newest ``keep`` old files: its disk use is
    bounded however long the daemon runs and however often it restarts."""
    path = tmp_path / "t" / "can.asc"
    path.parent.mkdir()
    for n in (1, 2, 3):  # earlier starts' traces
        path.with_name(f"can.{n}.asc").write_text(f"start {n}")
    path.write_text("last start")
    recorder = TraceRecorder(path, max_mb=0.02, keep=3)
    try:
        for k in range(3000):  # ~130 kB of ASC: several rotations
            recorder.queue.put((1e9 + k * 1e-3, 0x181, b"\x01\x02\x03\x04\x05\x06\x07\x08", True))
    finally:
        recorder.close()
    old = sorted(p.name for p in path.parent.glob("can.*.asc"))
    assert len(old) == 3, old
    # The oldest went first: the earlier starts' files and the last start's are gone.
    assert all(p.read_text().startswith("date") for p in path.parent.glob("can.*.asc")), old
    sizes = [p.stat().st_size for p in path.parent.glob("can*.asc")]
    assert max(sizes) < 0.02e6 + 200, sizes
    frames = sum(1 for p in path.parent.glob("can*.asc") for _ in can.ASCReader(str(p)))
    assert 0 < frames < 3000


def stock_config(path: Path, port: int, state: Path, sock: Path, trace: Path) -> DaemonConfig:
    """Write the example configuration to ``path`` with the bus (``remote`` to the HIL's port
    on 127.0.0.1) and the paths changed, and check that nothing else differs from it.

    Returns:
        The configuration as the daemon loads it.
    """
    text = EXAMPLE_CONFIG.read_text()
    for old, new in (
        ('interface = "socketcan"', 'interface = "remote"'),
        ('channel = "can0"', f'channel = "ws://127.0.0.1:{port}/"'),
        ('state_dir = "/var/lib/excavator-rtd"', f'state_dir = "{state}"'),
        ('socket = "/run/excavator-rtd/control.sock"', f'socket = "{sock}"'),
        ('# trace = "/var/log/excavator-rtd/can.blf"', f'trace = "{trace}"'),
    ):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path.write_text(text)
    got, shipped = load_config(path).flat(), load_config(EXAMPLE_CONFIG).flat()
    differ = sorted(k for k in shipped if got[k] != shipped[k])
    assert differ == sorted(CHANGED_KEYS), differ
    return load_config(path)


class HostStall(Exception):
    """A fault that is the host's doing (:func:`conftest.host_stall`)."""


def _judge_failure(
    daemon: Daemon,
    sock: Path,
    trace_dir: Path,
    rig: Rig,
    fault: str,
    hil: RealtimeHilProcess,
    config: DaemonConfig,
) -> None:
    """A latched fault: raise :class:`HostStall` where it is the host's doing
    (:func:`conftest.host_stall`, with the HIL process's statistics); fail otherwise.

    The daemon has stayed up and answered on its socket with the fault; the job is marked
    ``failed`` with the fault's text (a ``reset-fault`` would queue it again).
    """
    _until(
        lambda: request(sock, {"cmd": "status", "id": 1})["job"]["status"] != "running",
        30.0,
        "the faulted job to stop",
        daemon,
    )
    job = request(sock, {"cmd": "status", "id": 1})["job"]
    assert job["status"] == "failed" and job["fault"] and job["fault"] in fault, (job, fault)
    assert daemon.stop() == 0, daemon.log()  # closes the trace
    hil_process = hil.finish()[3]["hil_process"]
    stale_window_s = config.stale_cycles * config.loop.period_s
    why = host_stall(fault, trace_dir, rig, hil_process, stale_window_s)
    if why is not None:
        raise HostStall(why)
    tpdo1_gaps = {node: max_sync_gap_s(trace_dir, 0x180 + node) * 1e3 for node in NODES}
    pytest.fail(f"fault (largest SYNC gap {max_sync_gap_s(trace_dir) * 1e3:.1f} ms, TPDO1 "
                f"gaps by node {tpdo1_gaps} ms, HIL process {hil_process}): {fault}\n"
                f"{daemon.log()}")  # fmt: skip


@contextmanager
def _hil_process() -> Iterator[RealtimeHilProcess]:
    """The real-time HIL process at the planner's home pose, no terrain; skips if it cannot
    start."""
    rig = load_rig(RIG)
    q_home = TrenchPlanner(rig).home_pose_rad
    try:
        proc = RealtimeHilProcess.start(
            rig_name=RIG,
            q0_rad=q_home,
            terrain=None,
            period_s=PERIOD_S,
            max_wall_s=MAX_WALL_S,
        )
    except (CommunicationError, OSError) as exc:
        pytest.skip(f"the real-time HIL process cannot start here: {exc}")
    proc.master_bus.shutdown()  # the daemon is the master; this end would only queue frames
    try:
        yield proc
    finally:
        proc.close()


@pytest.mark.parametrize("attempt", range(E2E_RUNS))
def test_daemon_end_to_end(tmp_path: Path, attempt: int) -> None:
    stalls: list[str] = []
    for k in range(STALL_ATTEMPTS):
        with _hil_process() as hil:
            try:
                summary = _scenario(hil, tmp_path / f"try-{k}")
            except HostStall as stall:
                stalls.append(str(stall))
                print(f"\ndaemon e2e #{attempt + 1}, try {k + 1}: host stall: {stall}")
                continue
        print(f"\ndaemon e2e #{attempt + 1}, try {k + 1}: {summary}")
        return
    pytest.fail(f"the host stalled the master in all {STALL_ATTEMPTS} tries: {stalls}")


def _scenario(hil: RealtimeHilProcess, tmp_path: Path) -> str:
    """Run 1, SIGTERM mid-dig, run 2 to the end; every check of the module docstring.

    Returns:
        The printed figures.

    Raises:
        HostStall: The job failed because the host stalled the master (:func:`_judge_failure`).
    """
    tmp_path.mkdir()
    rig = load_rig(RIG)
    state = tmp_path / "state"
    sock = tmp_path / "run" / "c.sock"
    trace = tmp_path / "trace" / "can.blf"
    config = tmp_path / "rtd.toml"
    loaded = stock_config(config, hil.port, state, sock, trace)
    assert loaded.loop.period_s == PERIOD_S
    store = state / "jobs.json"
    poller = StorePoller(store)
    t0 = time.monotonic()
    first = Daemon(config, tmp_path, 1)
    second: Daemon | None = None
    try:
        # -- run 1: READY, submit, SIGTERM in the middle of the second dig
        first.wait_for("READY=1", 120.0)
        t_ready = time.monotonic() - t0
        reply = request(sock, {"cmd": "submit", "task": "A", "max_digs": MAX_DIGS})
        assert reply["ok"], reply
        assert reply["job"]["id"] == 1

        def in_second_dig() -> bool:
            st = request(sock, {"cmd": "status"})
            if st["daemon"]["fault"]:
                _judge_failure(
                    first, sock, trace.parent, rig, st["daemon"]["fault"], hil, loaded
                )
            progress = st.get("progress") or {}
            return progress.get("phase") == "dig" and progress.get("dig") == 1

        _until(in_second_dig, 150.0, "the second dig", first)
        time.sleep(1.5)  # well inside the dig (a dig lasts ~5 s)
        assert request(sock, {"cmd": "status"})["progress"]["phase"] == "dig"
        assert first.stop() == 0, first.log()
        # Every native object freed before the interpreter's end (nanobind reports leaks).
        assert "nanobind: leaked" not in first.log(), first.log()[-3000:]
        assert any(m.startswith("STOPPING=1") for m in first.messages), first.messages
        assert "WATCHDOG=1" in first.messages
        assert any(m.startswith("STATUS=running job 1") for m in first.messages)
        job = _job(store)
        assert job["status"] == "queued", job  # left resumable
        assert [d["index"] for d in job["digs"]] == [0], job["digs"]
        assert job["session_state"]["digs_done"] == 1
        figures1 = check_trace(trace, rig, _enable_syncs(first))
        assert not sock.exists()

        # -- run 2: the restarted daemon resumes at the interrupted dig and finishes the job
        second = Daemon(config, tmp_path, 2)
        second.wait_for("READY=1", 120.0)

        def finished() -> bool:
            fault = request(sock, {"cmd": "status"})["daemon"]["fault"]
            if fault:
                assert second is not None
                _judge_failure(second, sock, trace.parent, rig, fault, hil, loaded)
            return bool(_job(store)["status"] == "done")

        _until(finished, 200.0, "job 1 done", second)
        job = _job(store)
        assert [d["index"] for d in job["digs"]] == list(range(MAX_DIGS)), job["digs"]
        assert "job 1: running (task A, 1 dig(s) done)" in second.log()
        assert all(d["measured_volume_m3"] > 0.0 for d in job["digs"]), job["digs"]
        st = request(sock, {"cmd": "status"})
        assert st["daemon"]["healthy"], st
        assert second.stop() == 0, second.log()
        assert "nanobind: leaked" not in second.log(), second.log()[-3000:]
        figures2 = check_trace(trace, rig, _enable_syncs(second))
        assert (trace.parent / "can.1.blf").exists()  # the first run's trace is kept
    finally:
        poller.close()
        first.close()
        if second is not None:
            second.close()
    assert poller.failures == [], poller.failures[:3]
    assert poller.reads > 100
    _truth, _material, _frames, extra = hil.finish()
    # Each daemon's loop: its overruns over its life (the timing self-test's own run excluded).
    runs = [
        m.group(1)
        for d in (first, second)
        for m in re.finditer(r"loop: (\d+ overrun\(s\) in \d{4,} cycles.*)", d.log())
    ]
    return (
        f"READY after {t_ready:.1f} s; run 1 {figures1}; run 2 {figures2}; "
        f"{'; '.join(runs)}; "
        f"store parsed {poller.reads} times; total {time.monotonic() - t0:.1f} s; "
        f"{extra['hil_process']}"
    )


def test_stale_feedback_is_the_hosts_doing_only_where_the_hil_answered_that_late(
    tmp_path: Path,
) -> None:
    """The judge of a stale-feedback fault: a host stall where the HIL's own statistics show a
    SYNC answered the stale window or more after it was sent; the daemon's fault otherwise (and
    without the HIL's statistics)."""
    rig = load_rig(RIG)
    fault = "job 1: fault: stale feedback: no TPDO1 from the boom drive for 10 cycles"

    def stats(max_us: float) -> dict[str, Any]:
        return {"sync_handling_us": {"p50": 300.0, "p99": 900.0, "max": max_us}}

    why = host_stall(fault, tmp_path, rig, stats(24_000.0), 0.020)
    assert why is not None and "24.0 ms" in why and "stale window 20 ms" in why, why
    assert host_stall(fault, tmp_path, rig, stats(19_000.0), 0.020) is None
    assert host_stall(fault, tmp_path, rig) is None
    other = "job 1: fault: following error on the boom drive"
    assert host_stall(other, tmp_path, rig, stats(50_000.0), 0.020) is None
