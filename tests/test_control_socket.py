"""The control socket and the daemon's commands, with a fake runner in place of the drives.

The server: owner-only socket in an owner-only directory; malformed JSON, a request that is
not an object, a missing or unknown command, an oversized line and a failing handler each get
an error reply, and the server keeps serving (the same connection where the protocol allows,
a new one after an oversized line). The service: submit validates the task with the trench
planner's checks (nothing queued on a refusal), pause/resume/cancel reach the running job,
``stop`` and SIGTERM end ``Service.run`` with exit 0 after the runner's safe stop, SIGHUP
reloads what may change; the ``excavator-rt job`` client talks to it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from rt_runtime.errors import CommunicationError, ConfigurationError
from rt_runtime.rig import load_rig
from rt_runtime.service import client
from rt_runtime.service.config import ConfigKeyError, DaemonConfig, load_config
from rt_runtime.service.control import MAX_CLIENTS, MAX_REQUEST_BYTES, ControlServer, request
from rt_runtime.service.daemon import EXIT_OK, Service
from rt_runtime.service.jobstore import JobStore
from rt_runtime.service.notify import Notifier

# -- the bare server -----------------------------------------------------------------------------


class Serving:
    """A ControlServer polled by a thread until closed."""

    def __init__(
        self, path: Path, commands: dict[str, Callable[[dict[str, Any]], Any]], **kwargs: Any
    ) -> None:
        self.server = ControlServer(path, commands, **kwargs)
        self.server.bind()
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            self.server.poll(0.02)

    def close(self) -> None:
        self._stop = True
        self._thread.join(5)
        self.server.close()


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Serving]:
    def boom(_req: dict[str, Any]) -> dict[str, Any]:
        raise RuntimeError("handler bug")

    def refuse(_req: dict[str, Any]) -> dict[str, Any]:
        raise ConfigurationError("task: depth_m = 9 is outside (0, 0.3] m")

    s = Serving(
        tmp_path / "run" / "control.sock",
        {"echo": lambda req: {"echo": req.get("x")}, "boom": boom, "refuse": refuse},
    )
    yield s
    s.close()


def _conn(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(5.0)
    sock.connect(str(path))
    return sock


def _lines(sock: socket.socket, n: int) -> list[dict[str, Any]]:
    buf = b""
    while buf.count(b"\n") < n:
        chunk = sock.recv(65536)
        if not chunk:
            break
        buf += chunk
    return [json.loads(line) for line in buf.splitlines()[:n]]


def test_socket_and_directory_are_owner_only(served: Serving) -> None:
    path = served.server.path
    assert stat.S_ISSOCK(path.stat().st_mode)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700


def test_errors_are_replies_and_the_connection_keeps_serving(served: Serving) -> None:
    sock = _conn(served.server.path)
    sock.sendall(
        b"{not json\n"
        b"[1, 2]\n"
        b'{"x": 1}\n'
        b'{"cmd": "fly"}\n'
        b"\n"
        b'{"cmd": "boom"}\n'
        b'{"cmd": "refuse"}\n'
        b'{"cmd": "echo", "x": 42}\n'
    )
    replies = _lines(sock, 7)
    sock.close()
    codes = [r.get("code") for r in replies]
    assert codes == [
        "bad_json",
        "bad_json",
        "bad_request",
        "unknown_command",
        "internal",
        "refused",
        None,
    ], replies
    assert "allowed: echo, boom, refuse" in replies[3]["error"]
    assert "RuntimeError: handler bug" in replies[4]["error"]
    assert "depth_m = 9" in replies[5]["error"]
    assert replies[6] == {"ok": True, "echo": 42}


def test_oversized_request_is_refused_and_the_server_lives_on(served: Serving) -> None:
    sock = _conn(served.server.path)
    with contextlib.suppress(OSError):  # the server may close while we still send
        sock.sendall(b'{"cmd": "echo", "x": "' + b"y" * (MAX_REQUEST_BYTES + 10))
    (reply,) = _lines(sock, 1)
    assert reply["code"] == "too_large"
    assert str(MAX_REQUEST_BYTES) in reply["error"]
    sock.settimeout(5.0)
    with pytest.raises(OSError):  # closed by the server: EOF, or a reset while we send
        while sock.recv(65536):
            pass
        sock.sendall(b'{"cmd": "echo"}\n' * 1000)
    sock.close()
    assert request(served.server.path, {"cmd": "echo", "x": 1}) == {"ok": True, "echo": 1}


def test_bind_refuses_shared_directories_and_live_sockets(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    with pytest.raises(ConfigKeyError, match=r"paths\.socket: directory .* accessible to others"):
        ControlServer(shared / "c.sock", {}).bind()
    s = Serving(tmp_path / "own" / "c.sock", {})
    try:
        with pytest.raises(ConfigKeyError, match="another daemon serves"):
            ControlServer(tmp_path / "own" / "c.sock", {}).bind()
    finally:
        s.close()
    assert not (tmp_path / "own" / "c.sock").exists()
    # A socket file left by a dead daemon is replaced.
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(tmp_path / "own" / "c.sock"))
    stale.close()
    s = Serving(tmp_path / "own" / "c.sock", {"echo": lambda req: {}})
    try:
        assert request(tmp_path / "own" / "c.sock", {"cmd": "echo"})["ok"]
    finally:
        s.close()


def _read_reply(sock: socket.socket) -> dict[str, Any]:
    sock.settimeout(5.0)
    data = b""
    while not data.endswith(b"\n"):
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    return dict(json.loads(data))


def test_idle_connections_time_out_and_never_lock_clients_out(tmp_path: Path) -> None:
    path = tmp_path / "own" / "c.sock"
    s = Serving(path, {"echo": lambda req: {}}, idle_timeout_s=1.5)
    idle: list[socket.socket] = []
    try:
        for _ in range(MAX_CLIENTS):
            c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            c.connect(str(path))
            idle.append(c)
        # Every slot taken by silent clients: a new one is served once they have been idle
        # a moment (the idlest gives up its slot), not refused until a restart.
        deadline = time.monotonic() + 10.0
        reply: dict[str, Any] = {}
        while not reply.get("ok") and time.monotonic() < deadline:
            try:
                reply = request(path, {"cmd": "echo"}, timeout_s=5.0)
            except CommunicationError:  # told "busy" and closed before the request went out
                reply = {"ok": False, "code": "busy"}
            assert reply["ok"] or reply["code"] == "busy", reply
            time.sleep(0.2)
        assert reply.get("ok"), reply
        # The one that gave up its slot was told why; the others time out after 1.5 s.
        replies = [_read_reply(c) for c in idle]
        assert all(r["code"] == "idle" for r in replies), replies
    finally:
        for c in idle:
            c.close()
        s.close()


def test_progress_reads_as_words() -> None:
    before = {"phase": "wait", "dig": -1, "digs_done": 0, "paused": False, "stopping": False,
              "status": "", "cycles": 10, "planning": True}  # fmt: skip
    assert client.format_progress(before) == (
        "waiting for the next motion; 0 dig(s) done; planning the next dig"
    )
    digging = dict(before, phase="dig", dig=2, digs_done=2, planning=False, paused=True)
    text = client.format_progress(digging)
    assert text.startswith("digging dig 3; 2 dig(s) done; paused")
    assert "-1" not in client.format_progress(dict(before, phase="lift_out"))


def test_client_without_daemon(tmp_path: Path) -> None:
    with pytest.raises(CommunicationError, match="is excavator-rtd running"):
        request(tmp_path / "none.sock", {"cmd": "status"})


def test_job_client_imports_no_numerics_and_no_bus(tmp_path: Path) -> None:
    # `excavator-rt job ...` starts in a fraction of the whole CLI's time: the console script
    # takes the client alone, without numpy, python-can or the HIL's entry points.
    code = (
        "import sys\n"
        "from rt_runtime.entry import main\n"
        f"rc = main(['job', 'status', '--socket', {str(tmp_path / 'none.sock')!r}])\n"
        "heavy = sorted(m for m in ('numpy', 'can', 'scipy', 'hil_sim') if m in sys.modules)\n"
        "print(rc, heavy)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "2 []", out.stdout + out.stderr
    assert "is excavator-rtd running" in out.stderr


# -- the service with a fake runner --------------------------------------------------------------


class FakeRunner:
    """Runs queued jobs as three 'digs' of ``dig_s`` each; pause/cancel/shutdown like the real
    one's contract (stop at the next dig boundary is enough for a fake)."""

    def __init__(self, store: JobStore, dig_s: float = 0.05) -> None:
        self.store = store
        self.dig_s = dig_s
        self.stopped = threading.Event()
        self.options: tuple[bool, int] | None = None
        self._job: int | None = None
        self._pause = threading.Event()
        self._cancel = threading.Event()
        self._thread: threading.Thread | None = None
        self.shutdown_called = False
        self.beat = time.monotonic()
        self.latched = ""
        self.resets_done = 0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self.stopped.is_set():
            self.beat = time.monotonic()
            job = self.store.next_runnable()
            if job is None:
                time.sleep(0.01)
                continue
            self._job = job.id
            self.store.set_status(job.id, "running")
            done = len(job.digs)
            while done < 3 and not self.stopped.is_set() and not self._cancel.is_set():
                self.beat = time.monotonic()
                if self._pause.is_set():
                    time.sleep(0.01)
                    continue
                time.sleep(self.dig_s)
                self.store.record_dig(
                    job.id,
                    {
                        "index": done,
                        "dig_type": "downward",
                        "T_s": self.dig_s,
                        "plan_us": 1.0,
                        "planned_volume_m3": 0.001,
                        "measured_volume_m3": 0.001,
                    },
                    {"digs_done": done + 1},
                )
                done += 1
            if self._cancel.is_set():
                self.store.set_status(job.id, "cancelled", "cancelled by request")
            elif self.stopped.is_set():
                self.store.set_status(job.id, "queued")
            else:
                self.store.set_status(job.id, "done")
            self._cancel.clear()
            self._pause.clear()
            self._job = None

    def shutdown(self, timeout_s: float) -> bool:
        self.shutdown_called = True
        self.stopped.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        return True

    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def health(self) -> tuple[bool, str]:
        return (False, f"fault latched: {self.latched}") if self.latched else (True, "")

    def watchdog(self) -> tuple[bool, str]:
        return self.alive(), ""

    def fault(self) -> str:
        return self.latched

    def reset_fault(self) -> int:
        # The fake's reset always works at once.
        self.latched = ""
        self.resets_done += 1
        return self.resets_done

    def state(self) -> str:
        if self.latched:
            return f"fault: {self.latched}; waiting for reset-fault"
        return f"running job {self._job}" if self._job else "idle"

    def current_job(self) -> int | None:
        return self._job

    def progress(self) -> dict[str, Any] | None:
        return {"phase": "dig"} if self._job else None

    def pause(self) -> None:
        self._pause.set()

    def resume(self) -> None:
        self._pause.clear()

    def cancel(self) -> None:
        self._cancel.set()

    def configure(self, feedforward: bool, stale_cycles: int) -> None:
        self.options = (feedforward, stale_cycles)


def _config(tmp_path: Path, extra: str = "") -> Path:
    path = tmp_path / "d.toml"
    path.write_text(
        '[bus]\ninterface = "virtual"\nchannel = "unused"\n[rig]\nprofile = "scale_model"\n'
        f'[paths]\nstate_dir = "state"\nsocket = "run/c.sock"\n{extra}'
    )
    return path


class RunningService:
    """``Service.run()`` on the main thread (signals), the test's requests on another."""

    def __init__(self, tmp_path: Path, notify: str | None = None) -> None:
        self.cfg_path = _config(tmp_path)
        self.cfg: DaemonConfig = load_config(self.cfg_path)
        self.store = JobStore(self.cfg.paths.state_dir)
        self.runner = FakeRunner(self.store)
        server = ControlServer(self.cfg.paths.socket, {})
        server.bind()
        self.service = Service(
            self.cfg,
            load_rig("scale_model"),
            self.store,
            server,
            self.runner,
            notifier=Notifier(notify or ""),
            watchdog_s=0.05 if notify else None,
        )
        self.sock = self.cfg.paths.socket

    def ask(self, **req: Any) -> dict[str, Any]:
        return request(self.sock, req)

    def run_with(self, script: Callable[[RunningService], None]) -> tuple[int, list[BaseException]]:
        errors: list[BaseException] = []

        def body() -> None:
            try:
                script(self)
            except BaseException as exc:
                errors.append(exc)
                self.ask(cmd="stop")

        t = threading.Thread(target=body, daemon=True)
        t.start()
        code = self.service.run()
        t.join(10)
        return code, errors


def _wait(pred: Callable[[], bool], timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < end, "condition not met in time"
        time.sleep(0.01)


def test_service_jobs_through_the_socket(tmp_path: Path) -> None:
    rs = RunningService(tmp_path)

    def script(rs: RunningService) -> None:
        bad = rs.ask(cmd="submit", task={"length_m": 0.6, "depth_m": 0.9, "beta1_deg": 60,
                                          "beta2_deg": 60})  # fmt: skip
        assert not bad["ok"] and bad["code"] == "refused"
        assert "depth_m = 0.9 is outside" in bad["error"]
        assert not rs.ask(cmd="submit", task="/etc/passwd")["ok"]
        assert not rs.ask(cmd="submit", task="A", planner="de")["ok"]
        r = rs.ask(cmd="submit", task="A", max_digs=0)
        assert not r["ok"] and "max_digs 0; allowed: an integer in [1, 1000]" in r["error"]
        r = rs.ask(cmd="submit", task="A", depth=1)
        assert (
            not r["ok"] and "unknown key(s) depth; allowed: task, planner, max_digs" in r["error"]
        )
        assert rs.ask(cmd="list")["jobs"] == []  # nothing queued by a refusal

        rs.runner.pause()  # hold the first job at its first dig boundary
        job = rs.ask(cmd="submit", task="A")["job"]
        assert job["id"] == 1 and job["status"] == "queued"
        assert job["task"]["length_m"] == 0.6 and job["task"]["start_x_m"] > 0
        on_disk = json.loads((rs.cfg.paths.state_dir / "jobs.json").read_text())
        assert on_disk["jobs"][0]["id"] == 1  # submitted means stored
        _wait(lambda: rs.runner.current_job() == 1)
        st = rs.ask(cmd="status")
        assert st["daemon"]["current_job"] == 1 and st["daemon"]["rig"] == "scale_model"
        assert st["job"]["id"] == 1 and st["progress"] == {"phase": "dig"}
        rs.ask(cmd="pause")
        assert rs.ask(cmd="status", id=1)["job"]["status"] == "paused"
        assert rs.ask(cmd="resume", id=1)["job"]["status"] == "running"
        _wait(lambda: rs.store.get(1).status.label == "done")
        assert len(rs.ask(cmd="status", id=1)["job"]["digs"]) == 3

        two = rs.ask(cmd="submit", task={"name": "small", "length_m": 0.3, "depth_m": 0.05,
                                          "beta1_deg": 60, "beta2_deg": 60})["job"]  # fmt: skip
        _wait(lambda: rs.runner.current_job() == two["id"])
        reply = rs.ask(cmd="cancel", id=two["id"])
        assert reply["cancelling"]
        _wait(lambda: rs.store.get(two["id"]).status.label == "cancelled")
        r = rs.ask(cmd="resume", id=two["id"])
        assert not r["ok"] and "only a paused job resumes" in r["error"]
        r = rs.ask(cmd="pause", id="one")
        assert not r["ok"] and '"id" must be a job id' in r["error"]
        assert rs.ask(cmd="stop") == {"ok": True, "stopping": True}

    code, errors = rs.run_with(script)
    if errors:
        raise errors[0]
    assert code == EXIT_OK
    assert rs.runner.shutdown_called
    assert not rs.sock.exists()
    statuses = [j["status"] for j in json.loads(rs.store.path.read_text())["jobs"]]
    assert statuses == ["done", "cancelled"]


def test_sigterm_stops_safely_and_leaves_the_job_resumable(tmp_path: Path) -> None:
    notify_path = tmp_path / "notify.sock"
    manager = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    manager.bind(str(notify_path))
    manager.settimeout(5.0)
    rs = RunningService(tmp_path, notify=str(notify_path))
    rs.runner.dig_s = 0.5

    def script(rs: RunningService) -> None:
        rs.ask(cmd="submit", task="B")
        _wait(lambda: rs.runner.current_job() == 1)
        time.sleep(0.3)  # a few main-loop polls: STATUS= and WATCHDOG=1 lines
        os.kill(os.getpid(), signal.SIGTERM)

    try:
        code, errors = rs.run_with(script)
        if errors:
            raise errors[0]
        assert code == EXIT_OK
        assert rs.runner.shutdown_called
        assert rs.store.get(1).status.label == "queued"  # left for the next start
        messages = []
        manager.settimeout(0.2)
        while True:
            try:
                messages.append(manager.recv(4096).decode())
            except TimeoutError:
                break
    finally:
        manager.close()
    assert messages[0] == "STATUS=booting the drives"
    assert messages[1].startswith("READY=1\nSTATUS=")
    assert "WATCHDOG=1" in messages
    assert any(m.startswith("STATUS=running job 1") for m in messages), messages
    assert messages[-1].startswith("STOPPING=1\nSTATUS=stopping (signal SIGTERM)")


def test_sighup_reloads_the_reloadable_and_keeps_a_bad_file_out(tmp_path: Path) -> None:
    rs = RunningService(tmp_path)

    def script(rs: RunningService) -> None:
        assert rs.ask(cmd="status")["ok"]  # served: Service.run has its signal handlers
        text = rs.cfg_path.read_text()
        rs.cfg_path.write_text(
            text + '[executor]\nfeedforward = false\nplanner = "pso"\n[loop]\nperiod_s = 0.001\n'
        )
        os.kill(os.getpid(), signal.SIGHUP)
        _wait(lambda: rs.runner.options == (False, 10))
        assert rs.service.config.loop.period_s == 0.002  # needs a restart: kept
        assert rs.service.config.feedforward is False
        assert rs.service.config.planner == "pso"  # the default of the next submits
        rs.cfg_path.write_text(text + "[loop]\nperiod_s = 5.0\n")
        os.kill(os.getpid(), signal.SIGHUP)
        time.sleep(0.3)
        assert rs.service.config.planner == "pso"  # the bad file changed nothing
        assert rs.ask(cmd="status")["ok"]  # and the daemon serves on
        rs.ask(cmd="stop")

    code, errors = rs.run_with(script)
    if errors:
        raise errors[0]
    assert code == EXIT_OK


def _job_command(sock: Path) -> Callable[..., int]:
    """``excavator-rt job ARGV... --socket SOCK`` in this process: its exit code."""
    parser = argparse.ArgumentParser()
    client.add_parser(parser.add_subparsers())

    def job(*argv: str) -> int:
        args = parser.parse_args(["job", *argv, "--socket", str(sock)])
        code: int = args.handler(args)
        return code

    return job


def test_client_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rs = RunningService(tmp_path)
    task_file = tmp_path / "small.toml"
    task_file.write_text("length_m = 0.3\ndepth_m = 0.05\nbeta1_deg = 60.0\nbeta2_deg = 60.0\n")
    results: dict[str, Any] = {}

    job = _job_command(rs.sock)

    def script(rs: RunningService) -> None:
        rs.runner.pause()
        results["submit"] = job("submit", "--task", str(task_file), "--json")
        _wait(lambda: rs.runner.current_job() == 1)
        results["status"] = job("status")
        results["list"] = job("list")
        results["bad"] = job("resume", "7")
        results["cancel"] = job("cancel", "1")
        rs.ask(cmd="stop")

    code, errors = rs.run_with(script)
    if errors:
        raise errors[0]
    assert code == EXIT_OK
    assert results == {"submit": 0, "status": 0, "list": 0, "bad": 1, "cancel": 0}
    out, err = capsys.readouterr()
    assert '"name": "small"' in out  # --json: the reply as is
    assert "job 1: running, task small" in out
    assert "excavator-rt job resume: no job 7" in err


def test_a_latched_fault_refuses_motion_until_reset_fault(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    notify_path = tmp_path / "notify.sock"
    manager = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    manager.bind(str(notify_path))
    rs = RunningService(tmp_path, notify=str(notify_path))
    results: dict[str, Any] = {}

    job = _job_command(rs.sock)

    def script(rs: RunningService) -> None:
        refused = rs.ask(cmd="reset-fault")
        assert not refused["ok"] and refused["code"] == "refused", refused
        assert "no fault is latched" in refused["error"]
        rs.runner.pause()
        rs.ask(cmd="submit", task="A")
        _wait(lambda: rs.runner.current_job() == 1)
        rs.ask(cmd="pause", id=1)
        rs.runner.latched = "job 1: bus_error: the bus refused frames"
        st = rs.ask(cmd="status")
        assert st["daemon"]["fault"] == rs.runner.latched
        assert not st["daemon"]["healthy"]
        resume = rs.ask(cmd="resume", id=1)
        assert not resume["ok"] and resume["code"] == "faulted", resume
        assert "job 1: bus_error" in resume["error"] and "reset-fault" in resume["error"]
        results["resume"] = job("resume", "1")
        queued = rs.ask(cmd="submit", task="B")
        assert queued["ok"] and queued["fault"] == rs.runner.latched  # queued, waits
        results["submit"] = job("submit", "--task", "B")
        time.sleep(0.3)  # main-loop polls: the watchdog is fed while the fault is latched
        results["reset"] = job("reset-fault", "--wait-s", "5")
        assert rs.ask(cmd="status")["daemon"]["fault"] == ""
        assert rs.ask(cmd="resume", id=1)["ok"]
        rs.ask(cmd="stop")

    try:
        code, errors = rs.run_with(script)
        if errors:
            raise errors[0]
        manager.settimeout(0.2)
        messages = []
        with contextlib.suppress(TimeoutError):
            while True:
                messages.append(manager.recv(4096).decode())
    finally:
        manager.close()
    assert code == EXIT_OK
    assert results == {"resume": 1, "submit": 0, "reset": 0}
    out, err = capsys.readouterr()
    assert "excavator-rt job resume: resume of job 1 refused: a fault is latched" in err
    assert "a fault is latched (job 1: bus_error" in out  # the submit's note
    assert "resetting: job 1: bus_error" in out and "fault reset: " in out
    faulted = [i for i, m in enumerate(messages) if m.startswith("STATUS=fault: ")]
    assert faulted, messages
    assert "WATCHDOG=1" in messages[faulted[0] :], messages
