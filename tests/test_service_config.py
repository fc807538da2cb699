"""The daemon's configuration: keys validated before anything touches the bus.

Bad configurations (unknown key, bad value, missing models, a model directory for another rig,
a bad bus) make ``excavator-rtd`` exit non-zero with a message naming the key, and nothing is
sent on the bus: the daemon runs in this process on python-can's ``virtual`` interface and a
listener on the same channel sees no frame. The positive control (a valid configuration, no
drives on the bus) shows the listener does see the daemon's boot attempt.
"""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path
from typing import Any

import can
import pytest

from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR
from rt_runtime.rig.loader import PROFILE_DIR
from rt_runtime.service import daemon
from rt_runtime.service.config import (
    RELOADABLE_KEYS,
    ConfigKeyError,
    load_config,
    load_planning,
    parse_config,
)

EXAMPLE = Path(daemon.__file__).with_name("excavator-rtd.example.toml")


def _raw(**over: dict[str, Any]) -> dict[str, Any]:
    raw: dict[str, Any] = {
        "bus": {"interface": "virtual", "channel": "cfg-test"},
        "rig": {"profile": "scale_model"},
    }
    for section, values in over.items():
        raw.setdefault(section, {}).update(values)
    return raw


def _toml(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _key_error(raw: dict[str, Any]) -> ConfigKeyError:
    with pytest.raises(ConfigKeyError) as info:
        parse_config(raw, "/etc/x.toml")
    return info.value


def test_example_config_loads_with_documented_defaults() -> None:
    cfg = load_config(EXAMPLE)
    assert cfg.bus.interface == "socketcan" and cfg.bus.channel == "can0"
    assert cfg.bus.bitrate is None and cfg.bus.boot_timeout_s == 2.0
    assert cfg.rig_profile == "scale_model"
    assert cfg.loop.period_s == 0.002 and cfg.loop.sched_fifo_priority == 80
    assert cfg.loop.cpu is None and cfg.loop.lock_memory
    assert cfg.loop.max_consecutive_overruns == 5 and cfg.stale_cycles == 10
    assert cfg.models_dir is None and cfg.feedforward and cfg.planner == "pinn"
    assert str(cfg.paths.socket) == "/run/excavator-rtd/control.sock"
    assert cfg.paths.trace is None and cfg.log_level == "info"


def test_relative_paths_resolve_against_the_file(tmp_path: Path) -> None:
    (tmp_path / "models").mkdir()
    text = (
        '[bus]\ninterface = "virtual"\nchannel = "x"\n[rig]\nprofile = "scale_model"\n'
        '[models]\ndir = "models"\n[paths]\nstate_dir = "state"\nsocket = "run/c.sock"\n'
        'trace = "log/can.asc"\n[loop]\nsched_fifo_priority = 0\n'
    )
    cfg = load_config(_toml(tmp_path / "d.toml", text))
    assert cfg.models_dir == tmp_path / "models"
    assert cfg.paths.state_dir == tmp_path / "state"
    assert cfg.paths.socket == tmp_path / "run" / "c.sock"
    assert cfg.paths.trace == tmp_path / "log" / "can.asc"
    assert cfg.loop.sched_fifo_priority is None  # 0: leave the scheduler alone


def test_period_out_of_range_names_key_range_and_value() -> None:
    err = _key_error(_raw(loop={"period_s": 0.2}))
    assert err.key == "loop.period_s"
    assert "config key loop.period_s: must be in [0.0005, 0.01] s, got 0.2" in str(err)
    assert "/etc/x.toml" in str(err)


@pytest.mark.parametrize(
    ("raw", "key", "fragment"),
    [
        ({**_raw(), "watchdogs": {}}, "watchdogs", "allowed sections: bus, rig, loop"),
        (_raw(loop={"perod_s": 0.002}), "loop.perod_s", "allowed in [loop]: period_s"),
        ({"rig": {"profile": "scale_model"}}, "bus", "section [bus] is missing"),
        (_raw(bus={"channel": 5}), "bus.channel", "must be a non-empty string, got 5"),
        (_raw(loop={"period_s": "2ms"}), "loop.period_s", "must be a number"),
        (_raw(loop={"lock_memory": 1}), "loop.lock_memory", "must be true or false"),
        (_raw(loop={"sched_fifo_priority": 120}), "loop.sched_fifo_priority", "[1, 99]"),
        (_raw(loop={"cpu": 4096}), "loop.cpu", "not available to this process"),
        (_raw(bus={"interface": "sockecan"}), "bus.interface", "allowed: canalystii"),
        (_raw(bus={"bitrate": 5}), "bus.bitrate", "[10000, 1000000]"),
        (_raw(paths={"trace": "/tmp/can.log"}), "paths.trace", ".blf or .asc"),
        (_raw(paths={"socket": "/run/" + "s" * 120}), "paths.socket", "107 bytes"),
        (_raw(models={"dir": "/no/such/models"}), "models.dir", "is not a directory"),
        (_raw(executor={"planner": "de"}), "executor.planner", "allowed: pinn, pso"),
        (_raw(log={"level": "loud"}), "log.level", "allowed: debug, info"),
        (_raw(loop={"max_consecutive_overruns": 0}), "loop.max_consecutive_overruns", "[1, 1000]"),
        (_raw(executor={"stale_cycles": 0}), "executor.stale_cycles", "[1, 10000] cycles"),
    ],
)
def test_bad_keys_are_named(raw: dict[str, Any], key: str, fragment: str) -> None:
    err = _key_error(raw)
    assert err.key == key, str(err)
    assert f"config key {key}:" in str(err)
    assert fragment in str(err)


def test_unreadable_or_broken_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigurationError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigurationError, match="not valid TOML"):
        load_config(_toml(tmp_path / "bad.toml", "[bus\n"))


def test_changes_split_reloadable_from_restart() -> None:
    old = parse_config(_raw())
    new = parse_config(
        _raw(executor={"feedforward": False}, log={"level": "debug"}, loop={"period_s": 0.001})
    )
    reloadable, restart = old.changes(new)
    assert reloadable == ["executor.feedforward", "log.level"]
    assert restart == ["loop.period_s"]
    assert set(reloadable) <= set(RELOADABLE_KEYS)


def test_planning_checks_rig_models_and_bitrate(tmp_path: Path) -> None:
    rig, planner = load_planning(parse_config(_raw()))
    assert rig.name == "scale_model" and planner.rig is rig

    with pytest.raises(ConfigKeyError, match=r"config key rig\.profile: .*no rig profile"):
        load_planning(parse_config(_raw(rig={"profile": "no_such_rig"})))
    with pytest.raises(ConfigKeyError, match=r"config key rig\.profile: .*no \[planning\] table"):
        load_planning(parse_config(_raw(rig={"profile": "test_bench"})))
    with pytest.raises(ConfigKeyError, match=r"config key bus\.bitrate: 500000 differs"):
        load_planning(parse_config(_raw(bus={"bitrate": 500_000})))

    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigKeyError, match=r"config key models\.dir: .*does not exist"):
        load_planning(parse_config(_raw(models={"dir": str(empty)})))

    # A rig with planning but another name: the shipped cards are for scale_model.
    other = tmp_path / "other_rig.toml"
    text = (PROFILE_DIR / "scale_model.toml").read_text()
    other.write_text(text.replace('name = "scale_model"', 'name = "other_rig"', 1))
    with pytest.raises(ConfigKeyError) as info:
        load_planning(parse_config(_raw(rig={"profile": str(other)})))
    assert info.value.key.startswith("models.dir")
    assert "trained for rig 'scale_model'" in str(info.value)


# -- the daemon refuses before the bus -----------------------------------------------------------


def _daemon_toml(tmp_path: Path, channel: str, extra: str = "", **sections: str) -> Path:
    parts = {
        "bus": f'interface = "virtual"\nchannel = "{channel}"\nboot_timeout_s = 0.1',
        "rig": 'profile = "scale_model"',
        "loop": "sched_fifo_priority = 0\nlock_memory = false",
        "paths": f'state_dir = "{tmp_path / "state"}"\nsocket = "{tmp_path / "run" / "c.sock"}"',
    }
    parts.update(sections)
    text = "".join(f"[{k}]\n{v}\n" for k, v in parts.items()) + extra
    return _toml(tmp_path / "daemon.toml", text)


def _models_for_other_rig(tmp_path: Path) -> tuple[str, str]:
    """A rig profile file ``other_rig`` and a copy of the shipped models (cards: scale_model)."""
    other = tmp_path / "other_rig.toml"
    text = (PROFILE_DIR / "scale_model.toml").read_text()
    other.write_text(text.replace('name = "scale_model"', 'name = "other_rig"', 1))
    models = tmp_path / "models"
    shutil.copytree(DEFAULT_MODEL_DIR, models)
    return str(other), str(models)


BAD_CONFIGS = {
    "unknown key": ({"loop": "sched_fifo_priority = 0\nperiod = 0.002"}, "", "loop.period"),
    "bad period": ({"loop": "sched_fifo_priority = 0\nperiod_s = 0.2"}, "", "loop.period_s"),
    "missing model": ({}, '[models]\ndir = "{tmp}/nomodels"\n', "models.dir"),
    "wrong rig/model pairing": ({}, "PAIRING", "models.dir"),
    "bad bus interface": (
        {"bus": 'interface = "nosuchcan"\nchannel = "x"'},
        "",
        "bus.interface",
    ),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS))
def test_bad_config_exits_2_naming_the_key_and_sends_nothing(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sections, extra, key = BAD_CONFIGS[case]
    channel = f"rtd-{uuid.uuid4().hex}"
    if extra == "PAIRING":
        profile, models = _models_for_other_rig(tmp_path)
        sections = {"rig": f'profile = "{profile}"'}
        extra = f'[models]\ndir = "{models}"\n'
    if "{tmp}" in extra:
        (tmp_path / "nomodels").mkdir()
        extra = extra.replace("{tmp}", str(tmp_path))
    path = _daemon_toml(tmp_path, channel, extra, **sections)
    listener = can.Bus(interface="virtual", channel=channel)
    try:
        code = daemon.main(["--config", str(path)])
        frame = listener.recv(timeout=0.2)
    finally:
        listener.shutdown()
    err = capsys.readouterr().err
    assert code == daemon.EXIT_CONFIG, err
    assert f"config key {key}" in err, err
    assert frame is None, frame
    assert not (tmp_path / "run" / "c.sock").exists()


def test_no_drives_on_the_bus_exits_3_and_the_listener_sees_the_attempt(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    channel = f"rtd-{uuid.uuid4().hex}"
    path = _daemon_toml(tmp_path, channel)
    listener = can.Bus(interface="virtual", channel=channel)
    try:
        code = daemon.main(["--config", str(path)])
        frames = []
        while (msg := listener.recv(timeout=0.2)) is not None:
            frames.append(msg)
    finally:
        listener.shutdown()
    err = capsys.readouterr().err
    assert code == daemon.EXIT_BUS, err
    assert "drives not enabled" in err and "boot-up" in err
    # NMT reset node (COB 0x000, command 0x81) to each drive: the daemon did use the bus.
    assert any(m.arbitration_id == 0x000 and m.data[0] == 0x81 for m in frames), frames
    assert not (tmp_path / "run" / "c.sock").exists()  # the socket is removed on the way out


def test_check_mode_validates_without_the_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    channel = f"rtd-{uuid.uuid4().hex}"
    path = _daemon_toml(tmp_path, channel)
    listener = can.Bus(interface="virtual", channel=channel)
    try:
        assert daemon.main(["--config", str(path), "--check"]) == daemon.EXIT_OK
        assert listener.recv(timeout=0.1) is None
    finally:
        listener.shutdown()
    assert "is valid: rig scale_model" in capsys.readouterr().out


def test_unopenable_bus_names_interface_and_channel(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # socketcan on an interface that does not exist: valid keys, the bus does not open.
    path = _daemon_toml(tmp_path, "unused", bus='interface = "socketcan"\nchannel = "nosuchcan7"')
    assert daemon.main(["--config", str(path)]) == daemon.EXIT_BUS
    err = capsys.readouterr().err
    assert "bus.interface = 'socketcan', bus.channel = 'nosuchcan7'" in err, err


def test_every_one_shot_planner_the_trench_planner_builds_is_a_job_planner() -> None:
    # The daemon's list is a literal (the client starts without the planning stack): the
    # same names as the trench planner's, min_torque included.
    from rt_runtime.planning.trench import ONESHOT_PLANNERS
    from rt_runtime.service.config import PLANNERS

    assert PLANNERS == ONESHOT_PLANNERS
    cfg = parse_config(_raw(executor={"planner": "min_torque"}))
    assert cfg.planner == "min_torque"
    _rig, planner = load_planning(cfg)
    assert planner is not None and planner.oneshot.name == "min_torque"
    err = _key_error(_raw(executor={"planner": "mintorque"}))
    assert err.key == "executor.planner" and "pinn, pso, min_torque" in str(err)
