"""The daemon's TOML configuration: parsing and validation, before anything touches the bus.

Validation is its own step (:func:`load_config` -> a frozen :class:`DaemonConfig`) and is pure:
it reads the file, checks every key's type and range, refuses unknown keys with the allowed
list, and resolves relative paths against the file's directory. :func:`load_planning` is the
second step, still before the bus is opened: it loads the rig profile and the PINN models and
checks that their model cards belong to that rig. Every error names the key, e.g.
``config key loop.period_s: must be in [0.0005, 0.01] s, got 0.2``.

Keys (``docs/daemon.md`` has the table with defaults)::

    [bus]       interface, channel, bitrate, boot_timeout_s
    [rig]       profile
    [loop]      period_s, sched_fifo_priority, cpu, lock_memory, max_consecutive_overruns
    [models]    dir
    [executor]  feedforward, planner, stale_cycles
    [paths]     state_dir, socket, trace
    [log]       level

What a SIGHUP may change while the daemon runs is :data:`RELOADABLE_KEYS`; the rest (bus, rig,
period, models, paths of the state and the socket) needs a restart.
"""

from __future__ import annotations

import math
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rt_runtime.errors import ConfigurationError

if TYPE_CHECKING:
    from rt_runtime.planning.trench import TrenchPlanner
    from rt_runtime.rig import Rig

__all__ = [
    "DEFAULT_SOCKET",
    "DEFAULT_STATE_DIR",
    "LOG_LEVELS",
    "PERIOD_RANGE_S",
    "PLANNERS",
    "RELOADABLE_KEYS",
    "BusSettings",
    "ConfigKeyError",
    "DaemonConfig",
    "LoopSettings",
    "PathSettings",
    "check_directory",
    "load_config",
    "load_planning",
    "parse_config",
]

#: Allowed loop periods (s): 2 kHz .. 100 Hz.
PERIOD_RANGE_S = (0.0005, 0.01)
#: Default places of the job store and the control socket (the unit's StateDirectory= and
#: RuntimeDirectory=).
DEFAULT_STATE_DIR = Path("/var/lib/excavator-rtd")
DEFAULT_SOCKET = Path("/run/excavator-rtd/control.sock")
LOG_LEVELS = ("debug", "info", "warning", "error")
#: The one-shot planners a job may name (the trench planner's ``ONESHOT_PLANNERS``, kept
#: here as a literal so that the client starts without the planning stack).
PLANNERS = ("pinn", "pso", "min_torque")
#: Keys a SIGHUP applies (the executor's for the next job; the trace at once).
RELOADABLE_KEYS = (
    "log.level",
    "executor.feedforward",
    "executor.planner",
    "executor.stale_cycles",
    "paths.trace",
    "paths.trace_max_mb",
    "paths.trace_keep",
)
_TRACE_SUFFIXES = (".blf", ".asc")
#: Defaults of ``paths.trace_max_mb`` and ``paths.trace_keep``.
_TRACE_MAX_MB = 64.0
_TRACE_KEEP = 8

# section -> key -> (kind, required); kind drives the type check.
_SCHEMA: dict[str, dict[str, tuple[str, bool]]] = {
    "bus": {
        "interface": ("str", True),
        "channel": ("str", True),
        "bitrate": ("int", False),
        "boot_timeout_s": ("float", False),
    },
    "rig": {"profile": ("str", True)},
    "loop": {
        "period_s": ("float", False),
        "sched_fifo_priority": ("int", False),
        "cpu": ("int", False),
        "lock_memory": ("bool", False),
        "max_consecutive_overruns": ("int", False),
    },
    "models": {"dir": ("str", False)},
    "executor": {
        "feedforward": ("bool", False),
        "planner": ("str", False),
        "stale_cycles": ("int", False),
    },
    "paths": {
        "state_dir": ("str", False),
        "socket": ("str", False),
        "trace": ("str", False),
        "trace_max_mb": ("float", False),
        "trace_keep": ("int", False),
    },
    "log": {"level": ("str", False)},
}
_REQUIRED_SECTIONS = ("bus", "rig")


class ConfigKeyError(ConfigurationError):
    """A key of the daemon's configuration is wrong.

    Attributes:
        key: Dotted key, e.g. ``loop.period_s`` (a section name for a bad section).
        source: The configuration file.
    """

    def __init__(self, key: str, message: str, source: str = "") -> None:
        self.key = key
        self.source = source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}config key {key}: {message}")


@dataclass(frozen=True, slots=True)
class BusSettings:
    """``[bus]``: the python-can bus of the drives.

    Attributes:
        interface: python-can interface (``socketcan``, ``kvaser``, ``pcan``, ``virtual``,
            ``remote``, ...).
        channel: Interface channel (``can0``; ``ws://127.0.0.1:PORT/`` for ``remote``).
        bitrate: Bit rate (bit/s); None takes the rig profile's ``[can] bitrate``.
        boot_timeout_s: Time allowed for each wait of the drives' boot and enable.
    """

    interface: str
    channel: str
    bitrate: int | None = None
    boot_timeout_s: float = 2.0


@dataclass(frozen=True, slots=True)
class LoopSettings:
    """``[loop]``: the fixed-rate loop and what it asks of the OS.

    Attributes:
        period_s: Cycle (SYNC) period, within :data:`PERIOD_RANGE_S`.
        sched_fifo_priority: SCHED_FIFO priority 1..99; None (``0`` in the file) leaves the
            scheduler alone.
        cpu: Pin the loop's thread to this CPU; None: no pinning.
        lock_memory: mlockall while the loop runs.
        max_consecutive_overruns: This many overruns in a row stop the job safely.
    """

    period_s: float = 0.002
    sched_fifo_priority: int | None = 80
    cpu: int | None = None
    lock_memory: bool = True
    max_consecutive_overruns: int = 5


@dataclass(frozen=True, slots=True)
class PathSettings:
    """``[paths]``: where the daemon keeps things (absolute after loading).

    Attributes:
        state_dir: Directory of the job store (created 0700 when missing).
        socket: The control socket; its directory is created 0700 when missing and must not
            be accessible to others when it exists.
        trace: A ``.blf``/``.asc`` trace of every frame the daemon sends and reads; None: no
            trace. An existing file (a previous start's) and a file that reached
            ``trace_max_mb`` are kept as ``<stem>.<n><suffix>``, the newest ``trace_keep`` of
            them; older ones are deleted.
        trace_max_mb: Size (MB, 10^6 bytes) at which the trace file is rotated.
        trace_keep: Rotated trace files kept besides the one being written.
    """

    state_dir: Path = DEFAULT_STATE_DIR
    socket: Path = DEFAULT_SOCKET
    trace: Path | None = None
    trace_max_mb: float = _TRACE_MAX_MB
    trace_keep: int = _TRACE_KEEP


@dataclass(frozen=True, slots=True)
class DaemonConfig:
    """The validated configuration of ``excavator-rtd``.

    Attributes:
        source: The file it came from (empty path for a dict).
        bus: ``[bus]``.
        rig_profile: ``[rig] profile``: a shipped profile name, or a file (``*.toml`` or a path
            with a ``/``; relative to the configuration file).
        loop: ``[loop]``.
        models_dir: ``[models] dir``: the PINN models and their cards (default: shipped).
        feedforward: ``[executor] feedforward``: send the stroke rate as velocity offset.
        planner: ``[executor] planner``: default one-shot planner of a job (``pinn``, ``pso``).
        stale_cycles: ``[executor] stale_cycles``: consecutive cycles without a drive's TPDO1
            that stop the job as a fault.
        paths: ``[paths]``.
        log_level: ``[log] level``.
    """

    source: Path
    bus: BusSettings
    rig_profile: str
    loop: LoopSettings
    models_dir: Path | None
    feedforward: bool
    planner: str
    paths: PathSettings
    stale_cycles: int
    log_level: str

    def flat(self) -> dict[str, Any]:
        """``{"section.key": value}`` of every setting (paths as strings), for diffs and status."""
        out: dict[str, Any] = {
            "rig.profile": self.rig_profile,
            "models.dir": None if self.models_dir is None else str(self.models_dir),
            "executor.feedforward": self.feedforward,
            "executor.planner": self.planner,
            "executor.stale_cycles": self.stale_cycles,
            "log.level": self.log_level,
        }
        for section, obj in (("bus", self.bus), ("loop", self.loop), ("paths", self.paths)):
            for f in fields(obj):
                v = getattr(obj, f.name)
                out[f"{section}.{f.name}"] = str(v) if isinstance(v, Path) else v
        return out

    def changes(self, new: DaemonConfig) -> tuple[list[str], list[str]]:
        """Keys that differ in ``new``, split into (reloadable, needing a restart)."""
        old_flat, new_flat = self.flat(), new.flat()
        changed = sorted(k for k in old_flat if old_flat[k] != new_flat[k])
        return (
            [k for k in changed if k in RELOADABLE_KEYS],
            [k for k in changed if k not in RELOADABLE_KEYS],
        )


def _check_type(key: str, kind: str, value: Any, source: str) -> Any:
    if kind == "bool":
        if not isinstance(value, bool):
            raise ConfigKeyError(key, f"must be true or false, got {value!r}", source)
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigKeyError(key, f"must be an integer, got {value!r}", source)
    elif kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigKeyError(key, f"must be a number, got {value!r}", source)
        try:
            value = float(value)
        except OverflowError:  # an integer beyond the float range
            value = math.inf
        if not math.isfinite(value):
            raise ConfigKeyError(key, f"must be finite, got {value!r}", source)
    elif kind == "str" and (not isinstance(value, str) or not value.strip()):
        raise ConfigKeyError(key, f"must be a non-empty string, got {value!r}", source)
    return value


def _sections(raw: Mapping[str, Any], source: str) -> dict[str, dict[str, Any]]:
    unknown = sorted(set(raw) - set(_SCHEMA))
    if unknown:
        raise ConfigKeyError(
            unknown[0],
            f"unknown section or key; allowed sections: {', '.join(_SCHEMA)}",
            source,
        )
    for name in _REQUIRED_SECTIONS:
        if name not in raw:
            raise ConfigKeyError(name, f"section [{name}] is missing", source)
    out: dict[str, dict[str, Any]] = {}
    for name, schema in _SCHEMA.items():
        table = raw.get(name, {})
        if not isinstance(table, dict):
            raise ConfigKeyError(name, f"must be a table [{name}], got {table!r}", source)
        bad = sorted(set(table) - set(schema))
        if bad:
            raise ConfigKeyError(
                f"{name}.{bad[0]}", f"unknown key; allowed in [{name}]: {', '.join(schema)}", source
            )
        values: dict[str, Any] = {}
        for key, (kind, required) in schema.items():
            dotted = f"{name}.{key}"
            if key not in table:
                if required:
                    raise ConfigKeyError(dotted, "is required", source)
                continue
            values[key] = _check_type(dotted, kind, table[key], source)
        out[name] = values
    return out


def _path(base: Path, text: str) -> Path:
    p = Path(os.path.expanduser(text))
    return p if p.is_absolute() else (base / p)


def parse_config(raw: Mapping[str, Any], source: str | Path = "") -> DaemonConfig:
    """Validate a parsed TOML document (see :func:`load_config`).

    Args:
        raw: The document.
        source: The file it came from; relative paths resolve against its directory (the
            current directory for an empty source).

    Returns:
        The configuration.

    Raises:
        ConfigKeyError: Unknown section or key, missing required key, wrong type or range.
    """
    src = str(source)
    base = Path(src).resolve().parent if src else Path.cwd()
    s = _sections(raw, src)

    b = s["bus"]
    interface = b["interface"]
    import can  # here: python-can's import is a tenth of a second the job client does not need

    if interface not in can.interfaces.VALID_INTERFACES:
        raise ConfigKeyError(
            "bus.interface",
            f"{interface!r} is not a python-can interface; allowed: "
            f"{', '.join(sorted(can.interfaces.VALID_INTERFACES))}",
            src,
        )
    bitrate = b.get("bitrate")
    if bitrate is not None and not 10_000 <= bitrate <= 1_000_000:
        raise ConfigKeyError(
            "bus.bitrate", f"must be in [10000, 1000000] bit/s (classic CAN), got {bitrate}", src
        )
    boot_timeout_s = b.get("boot_timeout_s", 2.0)
    if not 0.05 <= boot_timeout_s <= 60.0:
        raise ConfigKeyError(
            "bus.boot_timeout_s", f"must be in [0.05, 60] s, got {boot_timeout_s:g}", src
        )
    bus = BusSettings(interface, b["channel"], bitrate, boot_timeout_s)

    lo = s["loop"]
    period_s = lo.get("period_s", 0.002)
    p_lo, p_hi = PERIOD_RANGE_S
    if not p_lo <= period_s <= p_hi:
        raise ConfigKeyError(
            "loop.period_s", f"must be in [{p_lo:g}, {p_hi:g}] s, got {period_s:g}", src
        )
    prio = lo.get("sched_fifo_priority", 80)
    if not 0 <= prio <= 99:
        raise ConfigKeyError(
            "loop.sched_fifo_priority",
            f"must be in [1, 99], or 0 to leave the scheduler alone, got {prio}",
            src,
        )
    cpu = lo.get("cpu")
    if cpu is not None:
        available = sorted(os.sched_getaffinity(0))
        if cpu not in available:
            raise ConfigKeyError(
                "loop.cpu",
                f"CPU {cpu} is not available to this process; allowed: "
                f"{', '.join(map(str, available))}",
                src,
            )
    max_overruns = lo.get("max_consecutive_overruns", 5)
    if not 1 <= max_overruns <= 1000:
        raise ConfigKeyError(
            "loop.max_consecutive_overruns", f"must be in [1, 1000], got {max_overruns}", src
        )
    loop = LoopSettings(period_s, prio or None, cpu, lo.get("lock_memory", True), max_overruns)

    models = s["models"].get("dir")
    models_dir = None if models is None else _path(base, models)
    if models_dir is not None and not models_dir.is_dir():
        raise ConfigKeyError("models.dir", f"{models_dir} is not a directory", src)

    ex = s["executor"]
    planner = ex.get("planner", "pinn")
    if planner not in PLANNERS:
        raise ConfigKeyError(
            "executor.planner", f"{planner!r} is not a planner; allowed: {', '.join(PLANNERS)}", src
        )

    stale_cycles = ex.get("stale_cycles", 10)
    if not 1 <= stale_cycles <= 10_000:
        raise ConfigKeyError(
            "executor.stale_cycles", f"must be in [1, 10000] cycles, got {stale_cycles}", src
        )

    pa = s["paths"]
    trace = None if "trace" not in pa else _path(base, pa["trace"])
    if trace is not None and trace.suffix.lower() not in _TRACE_SUFFIXES:
        raise ConfigKeyError(
            "paths.trace",
            f"{trace} must end in {' or '.join(_TRACE_SUFFIXES)} (python-can's BLF or ASC logger)",
            src,
        )
    socket_path = _path(base, pa.get("socket", str(DEFAULT_SOCKET)))
    # sockaddr_un.sun_path holds 108 bytes with the terminating NUL.
    if len(os.fsencode(socket_path)) > 107:
        raise ConfigKeyError(
            "paths.socket",
            f"{socket_path} is longer than the 107 bytes a unix socket path may have",
            src,
        )
    trace_max_mb = pa.get("trace_max_mb", _TRACE_MAX_MB)
    if not 0.1 <= trace_max_mb <= 100_000.0:
        raise ConfigKeyError(
            "paths.trace_max_mb", f"must be in [0.1, 100000] MB, got {trace_max_mb}", src
        )
    trace_keep = pa.get("trace_keep", _TRACE_KEEP)
    if not 0 <= trace_keep <= 10_000:
        raise ConfigKeyError("paths.trace_keep", f"must be in [0, 10000], got {trace_keep}", src)
    paths = PathSettings(
        state_dir=_path(base, pa.get("state_dir", str(DEFAULT_STATE_DIR))),
        socket=socket_path,
        trace=trace,
        trace_max_mb=float(trace_max_mb),
        trace_keep=int(trace_keep),
    )

    level = s["log"].get("level", "info").lower()
    if level not in LOG_LEVELS:
        raise ConfigKeyError(
            "log.level", f"{level!r} is not a level; allowed: {', '.join(LOG_LEVELS)}", src
        )

    profile = s["rig"]["profile"]
    if profile.endswith(".toml") or os.sep in profile:
        profile = str(_path(base, profile))

    return DaemonConfig(
        source=Path(src) if src else Path(),
        bus=bus,
        rig_profile=profile,
        loop=loop,
        models_dir=models_dir,
        feedforward=ex.get("feedforward", True),
        planner=planner,
        paths=paths,
        log_level=level,
        stale_cycles=stale_cycles,
    )


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate the daemon's TOML configuration (no bus, no rig, no models yet).

    Args:
        path: The file.

    Returns:
        The configuration, every path absolute.

    Raises:
        ConfigurationError: The file is missing or not TOML.
        ConfigKeyError: A key is unknown, missing, of the wrong type or out of range.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigurationError(f"config file {p}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigurationError(f"config file {p}: not UTF-8 text: {exc}") from exc
    try:
        raw = tomllib.loads(text)
    except ValueError as exc:  # TOMLDecodeError, or an integer of more than 4300 digits
        raise ConfigurationError(f"config file {p}: not valid TOML: {exc}") from exc
    return parse_config(raw, p.resolve())


def check_directory(path: Path, key: str, *, create: bool, mode: int = 0o700) -> bool:
    """A directory the daemon writes in: it exists and this user may write in it, or it is
    made (``create``, with ``mode``), or it could be made (not ``create``: nothing changes; its
    nearest existing parent is a directory this user may write in).

    Args:
        path: The directory.
        key: The configuration key that names it (for the error).
        create: Make it when missing (a start); False only checks (``excavator-rtd --check``).
        mode: Mode of a directory made.

    Returns:
        True when the directory existed.

    Raises:
        ConfigKeyError: It is not a directory, or it cannot be written, made or reached.
    """
    if path.is_dir():
        if not os.access(path, os.W_OK | os.X_OK):
            raise ConfigKeyError(key, f"directory {path} is not writable by this user")
        return True
    if path.exists() or path.is_symlink():
        raise ConfigKeyError(key, f"{path} exists and is not a directory")
    if create:
        try:
            path.mkdir(mode=mode, parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigKeyError(key, f"cannot create {path}: {exc.strerror or exc}") from exc
        return False
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigKeyError(
            key, f"{path} does not exist and cannot be created: {parent} is not writable"
        )
    return False


def load_planning(
    config: DaemonConfig, planner: str | None = None
) -> tuple[Rig, TrenchPlanner | None]:
    """Load the rig and the trench planner with its PINN models, checked against the rig; a
    rig with swing has no trench planner (None: it takes taught jobs, ``job submit --teach``).

    Still before the bus: a wrong profile or a model directory for another rig stops the daemon
    here, with the key named.

    Args:
        config: The validated configuration.
        planner: One-shot planner name; default ``config.planner``.

    Returns:
        ``(rig, planner)``.

    Raises:
        ConfigKeyError: ``rig.profile`` does not load (unknown name, bad file), the rig cannot
            plan, or ``models.dir`` does not hold models whose cards match the rig;
            ``bus.bitrate`` differs from the rig's.
    """
    from rt_runtime.planning.oneshot import require_planning
    from rt_runtime.planning.trench import TrenchPlanner
    from rt_runtime.rig import load_rig

    src = str(config.source)
    try:
        rig = load_rig(config.rig_profile)
        if rig.swing is None:
            require_planning(rig)
    except ConfigurationError as exc:
        raise ConfigKeyError("rig.profile", str(exc), src) from exc
    if config.bus.bitrate is not None and config.bus.bitrate != rig.can.bitrate:
        raise ConfigKeyError(
            "bus.bitrate",
            f"{config.bus.bitrate} differs from rig {rig.name}'s [can] bitrate "
            f"{rig.can.bitrate}; leave it out or make them equal",
            src,
        )
    if rig.swing is not None:
        return rig, None
    try:
        trench = TrenchPlanner(rig, planner or config.planner, model_dir=config.models_dir)
    except ConfigurationError as exc:
        where = "models.dir" if config.models_dir is not None else "models.dir (default)"
        raise ConfigKeyError(where, f"models do not serve rig {rig.name}: {exc}", src) from exc
    return rig, trench
