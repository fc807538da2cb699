"""docs/daemon.md's walk-through against the real-time HIL, run as written, and
``excavator-rtd --check``: what a start checks without the bus, changing no file.

The walk-through is ``scripts/daemon-on-hil.sh``, quoted whole in the document (a test keeps the
two equal) and run here with a one-dig job (``MAX_DIGS=1``), the shipped profile and the example
configuration with only the bus and the paths changed, as an integrator would run it. Skipped,
with the reason, only if the HIL cannot start.
"""

from __future__ import annotations

import os
import re
import socket
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import host_stall

from rt_runtime.planning.trench import TrenchPlanner
from rt_runtime.rig import load_rig
from rt_runtime.service import daemon

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "daemon-on-hil.sh"
DOC = ROOT / "docs" / "daemon.md"
EXAMPLE = ROOT / "rt_runtime" / "service" / "excavator-rtd.example.toml"
BEGIN = "<!-- begin scripts/daemon-on-hil.sh -->"
END = "<!-- end scripts/daemon-on-hil.sh -->"
#: Runs of the walk-through when the host stalls the daemon (:func:`conftest.host_stall`).
STALL_ATTEMPTS = 5


def test_the_document_quotes_the_script_whole() -> None:
    text = DOC.read_text()
    assert text.count(BEGIN) == 1 and text.count(END) == 1
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    quoted = re.fullmatch(r"\s*```sh\n(.*)```\s*", block, re.S)
    assert quoted is not None, block[:200]
    assert quoted.group(1) == SCRIPT.read_text()


def test_the_script_starts_the_arm_in_the_home_pose() -> None:
    found = re.search(r"--q0 (\S+) (\S+) (\S+)", SCRIPT.read_text())
    assert found is not None
    q0 = np.array([float(v) for v in found.groups()])
    assert np.allclose(q0, TrenchPlanner(load_rig("scale_model")).home_pose_rad, atol=1e-4)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


def test_the_walk_through_runs_a_job_against_the_hil(tmp_path: Path) -> None:
    """The script as written; a run whose fault is the host's doing (:func:`conftest.host_stall`)
    is printed and the script runs again in a new directory, up to ``STALL_ATTEMPTS`` times."""
    stalls: list[str] = []
    for k in range(STALL_ATTEMPTS):
        why = _walk_through(tmp_path / f"w{k}")
        if why is None:
            return
        stalls.append(why)
        print(f"\nwalk-through, try {k + 1}: host stall: {why}")
    pytest.fail(f"the host stalled the daemon in all {STALL_ATTEMPTS} tries: {stalls}")


def _walk_through(work: Path) -> str | None:
    """Run the script in ``work`` and check what it printed and logged.

    Returns:
        None when the job was done; why, where it failed by the host's doing.
    """
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": str(ROOT),
        "WORK": str(work),
        "PORT": str(_free_port()),
        "MAX_DIGS": "1",
    }
    env.pop("EXCAVATOR_RTD_SOCKET", None)
    done = subprocess.run(
        ["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=400
    )
    hil_err = (work / "hil.err").read_text() if (work / "hil.err").exists() else ""
    if done.returncode != 0 and "READY" not in done.stdout and "Address" in hil_err:
        pytest.skip(f"the real-time HIL process cannot start here: {hil_err}")
    log = (work / "rtd.log").read_text() if (work / "rtd.log").exists() else ""
    print(f"\n{done.stdout}\n{log[-3000:]}")
    job = (work / "job.txt").read_text() if (work / "job.txt").exists() else ""
    failed = re.search(r"^job 1: failed, .*?; fault: (.*)$", job, re.M)
    if done.returncode != 0 and failed is not None:
        why = host_stall(failed.group(1), work, load_rig("scale_model"))
        if why is not None:
            return why
    assert done.returncode == 0, f"{done.stdout}\n{done.stderr}\n{log}"
    out = done.stdout
    assert re.search(r"^READY \d+$", out, re.M), out
    assert "is valid: rig scale_model" in out and "nothing was changed" in out
    assert "job 1: done, task A" in out, out
    assert "timing self-test" in log and "stopped (signal SIGTERM)" in log
    return None


# -- excavator-rtd --check ----------------------------------------------------------------------


def _config(tmp_path: Path, state: Path, sock: Path, trace: Path) -> Path:
    """The example configuration with its bus and paths changed (no bus is ever opened)."""
    text = EXAMPLE.read_text()
    for old, new in (
        ('interface = "socketcan"', 'interface = "virtual"'),
        ('channel = "can0"', 'channel = "check-only"'),
        ('state_dir = "/var/lib/excavator-rtd"', f'state_dir = "{state}"'),
        ('socket = "/run/excavator-rtd/control.sock"', f'socket = "{sock}"'),
        ('# trace = "/var/log/excavator-rtd/can.blf"', f'trace = "{trace}"'),
    ):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp_path / "rtd.toml"
    path.write_text(text)
    return path


def _tree(root: Path) -> dict[str, tuple[int, int, int]]:
    return {
        str(p.relative_to(root)): (p.lstat().st_mode, p.lstat().st_size, p.lstat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
    }


def test_check_changes_no_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """What a start would make or remove (directories, a crash's temporary store file, a dead
    daemon's socket, the previous trace to rotate) is reported and left as it is."""
    state = tmp_path / "state"
    state.mkdir(mode=0o700)
    (state / "jobs.json").write_text('{"format": "excavator-rtd-jobs/1", "next_id": 1, "jobs": []}')
    (state / ".jobs.json.123.tmp").write_text("half")
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(run / "c.sock"))
    dead.close()  # a socket file no daemon serves
    trace = tmp_path / "log" / "can.blf"
    trace.parent.mkdir()
    trace.write_bytes(b"previous start")
    config = _config(tmp_path, state, run / "c.sock", trace)
    before = _tree(tmp_path)
    assert daemon.main(["--config", str(config), "--check"]) == daemon.EXIT_OK
    out = capsys.readouterr().out
    assert _tree(tmp_path) == before
    assert "nothing was changed" in out
    assert "1 temporary file(s) a crash left, removed at start" in out
    assert "a dead daemon's socket is there, removed at start" in out
    assert "timing self-test:" in out

    # Nothing there yet: the directories a start would make are not made.
    config = _config(tmp_path, tmp_path / "new" / "state", tmp_path / "new" / "run" / "c.sock",
                     tmp_path / "new" / "log" / "can.asc")  # fmt: skip
    before = _tree(tmp_path)
    assert daemon.main(["--config", str(config), "--check"]) == daemon.EXIT_OK
    assert _tree(tmp_path) == before
    assert not (tmp_path / "new").exists()


def test_check_refuses_what_a_start_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    run.chmod(0o755)
    config = _config(tmp_path, tmp_path / "state", run / "c.sock", tmp_path / "can.blf")
    assert daemon.main(["--config", str(config), "--check"]) == daemon.EXIT_CONFIG
    err = capsys.readouterr().err
    assert "config key paths.socket" in err and "mode 0755" in err, err
    assert stat.S_IMODE(run.stat().st_mode) == 0o755

    (tmp_path / "file").write_text("")
    config = _config(tmp_path, tmp_path / "file", tmp_path / "r2" / "c.sock", tmp_path / "t.blf")
    assert daemon.main(["--config", str(config), "--check"]) == daemon.EXIT_CONFIG
    assert "config key paths.state_dir" in capsys.readouterr().err

    state = tmp_path / "bad-state"
    state.mkdir()
    (state / "jobs.json").write_text("{not json")
    config = _config(tmp_path, state, tmp_path / "r3" / "c.sock", tmp_path / "t.blf")
    assert daemon.main(["--config", str(config), "--check"]) == daemon.EXIT_CONFIG
    assert "not valid JSON" in capsys.readouterr().err
