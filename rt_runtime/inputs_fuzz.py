"""Property-based checks of every input a user or a device hands the runtime (hypothesis).

Role: the properties behind ``tests/test_inputs_fuzz.py`` and ``excavator-rt bench inputs``:
one :class:`InputEntry` per entry point (task files, rig profiles, the daemon's config,
control-socket requests, model cards, CAN frames into the master's receive path, SDO answers
into the master's SDO client). Each entry draws inputs over the whole domain: valid documents
mutated (a key removed, a value of a wrong type, NaN/inf/huge/negative numbers, unknown keys),
non-UTF-8 bytes and truncated text, random frames in the relevant COB-ID ranges with any length
0..8 and mutations of valid frames. Its check feeds one input through the real entry point and
says whether it was accepted or refused. The properties:

* nothing raises but the entry point's documented error (``ConfigurationError``,
  ``CommunicationError``; a control request never gets the ``internal`` code);
* every refusal's message names what was wrong (the key, the value, the file or the field);
* nothing moves after a refusal: a refused control request queues no job and calls nothing of
  the runner; a garbled frame changes no feedback value and makes the master send nothing; the
  master sends nothing but quick stop from its receive path.

A violated property raises :class:`PropertyViolation` (an ``AssertionError``). Entries from
outside the runtime (the HIL's firmware models) come through the ``excavator_rt.inputs`` entry
point group: each names a callable returning a list of :class:`InputEntry`.

hypothesis is a test and benchmark tool (the ``test`` extra); this module imports it.
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import shutil
import struct
import tempfile
import time
import tomllib
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import can
import hypothesis
from hypothesis import strategies as st

from rt_runtime.errors import CommunicationError, ConfigurationError, ExcavatorRtError

__all__ = [
    "ENTRY_GROUP",
    "EntryReport",
    "InputEntry",
    "InputsReport",
    "PropertyViolation",
    "Verdict",
    "bench_inputs",
    "mutated_document",
    "mutated_frames",
    "run_entry",
    "runtime_entries",
    "toml_text",
]

#: Entry-point group of input entries from outside the runtime; each entry point names a
#: callable returning a list of :class:`InputEntry`.
ENTRY_GROUP = "excavator_rt.inputs"


class Verdict(IntEnum):
    """What an entry point did with one input."""

    ACCEPTED = 0
    REFUSED = 1


class PropertyViolation(AssertionError):
    """An input broke a property (a refusal that names nothing, a frame sent after a refusal)."""


@dataclass(frozen=True, slots=True)
class InputEntry:
    """One entry point and its property.

    Attributes:
        name: Short name (the report's key).
        description: What is fed where.
        strategy: Builds the hypothesis strategy of inputs.
        context: A context manager factory giving what the check needs (files, a master on an
            in-process bus); entered once per run.
        check: ``check(context, example) -> Verdict``; raises :class:`PropertyViolation` when a
            property fails, and anything else it raises is a traceback.
        examples: Inputs always tried first (regressions: each once broke a property).
    """

    name: str
    description: str
    strategy: Callable[[], st.SearchStrategy[Any]]
    context: Callable[[], contextlib.AbstractContextManager[Any]]
    check: Callable[[Any, Any], Verdict]
    examples: tuple[Any, ...] = ()


@dataclass(frozen=True, slots=True)
class EntryReport:
    """The outcome of one entry point's run.

    Attributes:
        name: The entry's name.
        examples: Inputs tried.
        refused: Inputs refused with the documented error.
        accepted: Inputs accepted.
        tracebacks: Inputs that raised anything else or broke a property.
        first_traceback: The first of those (type, message, input), empty when none.
        wall_s: Wall time of the run (s).
    """

    name: str
    examples: int
    refused: int
    accepted: int
    tracebacks: int
    first_traceback: str
    wall_s: float

    def to_json(self) -> dict[str, Any]:
        """The report's JSON object."""
        return {
            "name": self.name,
            "examples": self.examples,
            "refused": self.refused,
            "accepted": self.accepted,
            "tracebacks": self.tracebacks,
            "first_traceback": self.first_traceback,
            "wall_s": round(self.wall_s, 3),
        }


@dataclass(frozen=True, slots=True)
class InputsReport:
    """``excavator-rt bench inputs``: every entry point's run.

    Attributes:
        seed: The hypothesis seed.
        examples_per_entry: Inputs asked for per entry point.
        entries: One report per entry point.
        wall_s: Wall time of all runs (s).
    """

    seed: int
    examples_per_entry: int
    entries: tuple[EntryReport, ...]
    wall_s: float

    @property
    def tracebacks(self) -> int:
        """Tracebacks over all entry points (the goal: 0)."""
        return sum(e.tracebacks for e in self.entries)

    def to_json(self) -> dict[str, Any]:
        """The report's JSON object (``--json``)."""
        return {
            "seed": self.seed,
            "examples_per_entry": self.examples_per_entry,
            "entries": [e.to_json() for e in self.entries],
            "tracebacks": self.tracebacks,
            "wall_s": round(self.wall_s, 3),
        }


# -- running ------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Tally:
    refused: int = 0
    accepted: int = 0
    tracebacks: int = 0
    first: str = ""


def run_entry(
    entry: InputEntry, examples: int, seed: int, *, raise_failures: bool = False
) -> EntryReport:
    """Feed ``examples`` inputs (plus the entry's regression examples) to one entry point.

    Args:
        entry: The entry point.
        examples: Inputs hypothesis generates (it may stop earlier when the space is exhausted).
        seed: hypothesis seed (runs are reproducible; no example database is used).
        raise_failures: Let the first failure propagate (hypothesis then shrinks it and reports
            the smallest failing input: the tests); otherwise count it and go on (the benchmark).

    Raises:
        Exception: With ``raise_failures``, the first failure (after shrinking).
    """
    tally = _Tally()
    start_s = time.perf_counter()
    with entry.context() as ctx:

        def prop(example: Any) -> None:
            try:
                verdict = entry.check(ctx, example)
            except Exception as exc:
                if raise_failures:
                    raise
                tally.tracebacks += 1
                if not tally.first:
                    tally.first = f"{type(exc).__name__}: {exc} (input {example!r:.400})"
                return
            if verdict is Verdict.ACCEPTED:
                tally.accepted += 1
            else:
                tally.refused += 1

        phases = [hypothesis.Phase.explicit, hypothesis.Phase.generate]
        if raise_failures:
            phases.append(hypothesis.Phase.shrink)
        test: Callable[..., None] = hypothesis.given(entry.strategy())(prop)
        for ex in entry.examples:
            test = hypothesis.example(ex)(test)
        test = hypothesis.settings(
            max_examples=examples,
            deadline=None,
            database=None,
            phases=phases,
            suppress_health_check=list(hypothesis.HealthCheck),
            print_blob=False,
        )(test)
        hypothesis.seed(seed)(test)()
    return EntryReport(
        name=entry.name,
        examples=tally.refused + tally.accepted + tally.tracebacks,
        refused=tally.refused,
        accepted=tally.accepted,
        tracebacks=tally.tracebacks,
        first_traceback=tally.first,
        wall_s=time.perf_counter() - start_s,
    )


def outside_entries() -> list[InputEntry]:
    """The entries registered in :data:`ENTRY_GROUP` (the HIL's firmware models)."""
    from importlib.metadata import entry_points

    out: list[InputEntry] = []
    for ep in sorted(entry_points(group=ENTRY_GROUP), key=lambda e: e.name):
        out.extend(ep.load()())
    return out


def bench_inputs(
    examples: int = 10_000,
    seed: int = 0,
    entries: Sequence[InputEntry] | None = None,
    progress: Callable[[EntryReport], None] | None = None,
) -> InputsReport:
    """Run every entry point (the runtime's and :func:`outside_entries`) with ``examples``
    inputs each; failures are counted, never raised."""
    chosen = list(entries) if entries is not None else runtime_entries() + outside_entries()
    start_s = time.perf_counter()
    reports = []
    for entry in chosen:
        r = run_entry(entry, examples, seed)
        reports.append(r)
        if progress is not None:
            progress(r)
    return InputsReport(seed, examples, tuple(reports), time.perf_counter() - start_s)


# -- documents: mutation and text -----------------------------------------------------------------

#: Values of a wrong type or out of every range: NaN, infinities, huge and negative numbers,
#: integers beyond 64 bits, empty and odd strings, booleans, lists and tables.
_ODD_VALUES: tuple[Any, ...] = (
    math.nan, math.inf, -math.inf, 0, -1, -1.0, 1e300, -1e300, 10**30, -(10**30), 10**400,
    2**63 - 1, -(2**63), 5e-324, "", "x", "1.0", True, False, [], {}, [1.0], [math.nan],
    {"a": 1}, None, "<huge-int>",
)  # fmt: skip
#: Stands for an integer of 5000 digits (rendered in place of this string, quotes included):
#: more digits than Python converts to an int by default.
HUGE_INT = "<huge-int>"
_HUGE_DIGITS = "9" * 5000


def odd_values(*, none: bool = False) -> st.SearchStrategy[Any]:
    """Any value a document may hold in place of a valid one (``none``: also None, for JSON)."""
    scalars = st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(),
        st.text(max_size=12),
        st.booleans(),
    )
    values = st.one_of(
        st.sampled_from([v for v in _ODD_VALUES if none or v is not None]),
        scalars,
        st.lists(scalars, max_size=4),
        st.dictionaries(st.text(max_size=6), scalars, max_size=2),
    )
    return values


Path_ = tuple[str | int, ...]


def _paths(doc: Any, prefix: Path_ = ()) -> list[Path_]:
    """Every key path of a document (tables' keys and list positions), depth first."""
    out: list[Path_] = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out.append((*prefix, k))
            out.extend(_paths(v, (*prefix, k)))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out.append((*prefix, i))
            out.extend(_paths(v, (*prefix, i)))
    return out


def _keys(doc: Any) -> set[str]:
    """Every table key of a document, at any depth."""
    return {k for p in _paths(doc) for k in p if isinstance(k, str)}


def _parent(doc: Any, path: Path_) -> Any:
    node = doc
    for k in path[:-1]:
        node = node[k]
    return node


def _hint(path: Path_, value: Any = None, with_value: bool = False) -> tuple[str, ...]:
    """What a refusal of a change at ``path`` may name: the nearest key, the table holding it
    (a check across the table's keys names another of them), or the value."""
    keys = [k for k in path if isinstance(k, str)]
    out = keys[-2:]
    if with_value:
        text = repr(value) if not isinstance(value, str) else value
        if text and len(text) <= 40:
            out.append(text)
    return tuple(out)


@st.composite
def mutated_document(
    draw: st.DrawFn, bases: Sequence[dict[str, Any]], *, none: bool = False
) -> tuple[dict[str, Any], tuple[str, ...]]:
    """A valid document with 0..3 changes: a key removed, a value replaced by an odd value
    (:func:`odd_values`), an unknown key added. Returns the document and what a refusal of it
    may name (empty: no change)."""
    base = draw(st.sampled_from(list(bases)))
    doc = copy.deepcopy(base)
    hints: list[str] = []
    for _ in range(draw(st.integers(0, 3))):
        paths = _paths(doc)
        op = draw(st.sampled_from(("remove", "replace", "replace", "unknown")))
        if not paths:
            op = "unknown"
        if op == "unknown":
            tables = [()] + [p for p in paths if isinstance(_parent(doc, (*p, 0)), dict)]
            where = draw(st.sampled_from(tables))
            table = doc
            for k in where:
                table = table[k]
            key = draw(st.text(min_size=1, max_size=12))
            if key in table:
                continue
            value = copy.deepcopy(draw(odd_values(none=none)))  # never a shared value
            table[key] = value
            hints.append(key)
            if value == HUGE_INT:  # refused by the parser, which names no key
                hints.append("digits")
            continue
        path = draw(st.sampled_from(paths))
        parent = _parent(doc, path)
        if op == "remove":
            del parent[path[-1]]
            hints.extend(_hint(path))
        else:
            value = copy.deepcopy(draw(odd_values(none=none)))
            parent[path[-1]] = value
            hints.extend(_hint(path, value, with_value=True))
            if value == HUGE_INT:
                hints.append("digits")
    return doc, (tuple(hints) if doc != base else ())


def _toml_string(s: str) -> str:
    # JSON's escapes are TOML's; TOML also wants DEL escaped.
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_string(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return _toml_string(str(v))  # None has no TOML form: a string in its place


def toml_text(doc: dict[str, Any]) -> str:
    """A TOML document of ``doc``: one line per top-level key, tables inline."""
    return "".join(f"{_toml_string(k)} = {_toml_value(v)}\n" for k, v in doc.items())


#: Words a refusal of a file that does not parse names (its format and why).
_SYNTAX_WORDS = ("TOML", "JSON", "UTF-8", "utf-8", "codec", "decode", "not valid")


@st.composite
def document_bytes(
    draw: st.DrawFn,
    bases: Sequence[dict[str, Any]],
    render: Callable[[dict[str, Any]], str],
    *,
    none: bool = False,
) -> tuple[bytes, tuple[str, ...]]:
    """A document's bytes: a mutated document (:func:`mutated_document`) rendered, or such
    bytes truncated, with bytes inserted (non-UTF-8 among them) or overwritten, or random
    bytes. Returns the bytes and what a refusal may name."""
    doc, hints = draw(mutated_document(bases, none=none))
    data = render(doc).replace(f'"{HUGE_INT}"', _HUGE_DIGITS).encode("utf-8")
    kind = draw(st.sampled_from(("doc", "doc", "doc", "truncate", "insert", "flip", "random")))
    if kind == "doc":
        return data, hints
    any_key = tuple(sorted(_keys(doc) | set().union(*(_keys(b) for b in bases))))
    syntax = (*hints, *any_key, *_SYNTAX_WORDS)
    if kind == "random":
        return draw(st.binary(max_size=200)), _SYNTAX_WORDS + any_key
    at = draw(st.integers(0, len(data)))
    if kind == "truncate":
        return data[:at], syntax
    junk = draw(st.one_of(st.binary(min_size=1, max_size=4), st.sampled_from([b"\xff", b"\xc3"])))
    if kind == "insert":
        return data[:at] + junk + data[at:], syntax
    return data[:at] + junk + data[at + len(junk) :], syntax


def _names(message: str, hints: Sequence[str], *always: str) -> None:
    """Raise :class:`PropertyViolation` unless ``message`` names one of ``hints`` (case
    blind) or, with no hints, is not empty; ``always`` must all be in it."""
    low = message.lower()
    for word in always:
        if word.lower() not in low:
            raise PropertyViolation(f"refusal does not name {word!r}: {message!r}")
    if not message.strip():
        raise PropertyViolation("refusal with an empty message")
    if hints and not any(h.lower() in low for h in hints):
        raise PropertyViolation(f"refusal names none of {list(hints)[:12]}: {message!r}")


def _expect_configuration_error(exc: BaseException) -> ConfigurationError:
    if not isinstance(exc, ConfigurationError):
        raise exc
    return exc


@contextlib.contextmanager
def _tmpdir() -> Iterator[Path]:
    path = Path(tempfile.mkdtemp(prefix="excavator-rt-inputs-"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


# -- task files ----------------------------------------------------------------------------------

_VALID_TASKS: tuple[dict[str, Any], ...] = (
    {"length_m": 0.6, "depth_m": 0.15, "beta1_deg": 60.0, "beta2_deg": 60.0},
    {"length_m": 0.7, "depth_m": 0.1, "beta1_deg": 65, "beta2_deg": 40, "start_x_m": 1.0},
)


@dataclass(slots=True)
class _FileContext:
    dir: Path
    rig: Any = None
    extra: dict[str, Any] = field(default_factory=dict)


@contextlib.contextmanager
def _task_context() -> Iterator[_FileContext]:
    from rt_runtime.rig import load_rig

    with _tmpdir() as d:
        yield _FileContext(d, load_rig("scale_model"))


def _check_task_file(ctx: _FileContext, example: tuple[bytes, tuple[str, ...]]) -> Verdict:
    from rt_runtime.planning.trench.task import load_task, task_limits

    data, hints = example
    path = ctx.dir / "dig.toml"
    path.write_bytes(data)
    try:
        task = load_task(path, ctx.rig)
    except Exception as exc:
        err = _expect_configuration_error(exc)
        _names(str(err), hints, path.stem)  # the task's name is its file's stem
        return Verdict.REFUSED
    lim = task_limits(ctx.rig)
    for key, value in (
        ("length_m", task.length_m),
        ("depth_m", task.depth_m),
        ("beta1_deg", math.degrees(task.beta1_rad)),
        ("beta2_deg", math.degrees(task.beta2_rad)),
        ("start_x_m", task.start_x_m),
    ):
        lo, hi = lim[key]
        if not lo - 1e-9 <= value <= hi + 1e-9:
            raise PropertyViolation(f"accepted task with {key} = {value!r} outside [{lo}, {hi}]")
    return Verdict.ACCEPTED


# -- rig profiles --------------------------------------------------------------------------------


def _profiles() -> list[dict[str, Any]]:
    from rt_runtime.rig.loader import PROFILE_DIR

    return [tomllib.loads(p.read_text("utf-8")) for p in sorted(PROFILE_DIR.glob("*.toml"))]


@contextlib.contextmanager
def _dir_context() -> Iterator[_FileContext]:
    with _tmpdir() as d:
        yield _FileContext(d)


def _check_rig(ctx: _FileContext, example: tuple[bytes, tuple[str, ...]]) -> Verdict:
    from rt_runtime.rig import load_rig

    data, hints = example
    path = ctx.dir / "rig.toml"
    path.write_bytes(data)
    try:
        rig = load_rig(path)
    except Exception as exc:
        err = _expect_configuration_error(exc)
        _names(str(err), hints, str(path))
        return Verdict.REFUSED
    numbers = [*rig.lengths_m, *rig.q_min_rad, *rig.q_max_rad, rig.gravity_m_s2]
    if not all(math.isfinite(float(x)) for x in numbers):
        raise PropertyViolation(f"accepted rig {rig.name} with a value that is not finite")
    return Verdict.ACCEPTED


# -- daemon config -------------------------------------------------------------------------------


def _configs() -> list[dict[str, Any]]:
    from rt_runtime.service import config

    example = Path(config.__file__).parent / "excavator-rtd.example.toml"
    full = tomllib.loads(example.read_text("utf-8"))
    small = {
        "bus": {"interface": "virtual", "channel": "x"},
        "rig": {"profile": "scale_model"},
        "paths": {"state_dir": "state", "socket": "run/c.sock"},
    }
    return [full, small]


def _check_config(ctx: _FileContext, example: tuple[bytes, tuple[str, ...]]) -> Verdict:
    from rt_runtime.service.config import load_config

    data, hints = example
    path = ctx.dir / "daemon.toml"
    path.write_bytes(data)
    try:
        load_config(path)
    except Exception as exc:
        err = _expect_configuration_error(exc)
        _names(str(err), hints, str(path))
        return Verdict.REFUSED
    return Verdict.ACCEPTED


# -- model cards ---------------------------------------------------------------------------------


def _cards() -> list[dict[str, Any]]:
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR

    return [json.loads(p.read_text()) for p in sorted(Path(DEFAULT_MODEL_DIR).glob("pinn_*.json"))]


@contextlib.contextmanager
def _card_context() -> Iterator[_FileContext]:
    from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR

    with _tmpdir() as d:
        for p in Path(DEFAULT_MODEL_DIR).iterdir():
            if p.suffix in (".onnx", ".npz"):
                (d / p.name).symlink_to(p.resolve())
        yield _FileContext(d)


def _json_text(doc: dict[str, Any]) -> str:
    return json.dumps(doc, allow_nan=True)


def _check_card(ctx: _FileContext, example: tuple[bytes, tuple[str, ...]]) -> Verdict:
    from rt_runtime.planning.pinn import _Library, check_file, load_card

    data, hints = example
    path = ctx.dir / "pinn_card.json"
    path.write_bytes(data)
    try:
        card = load_card(path)
        check_file(str(path), "model", card.model_path, card.model_sha256)
        if card.raw.get("library") is not None:
            _Library(card)
    except Exception as exc:
        err = _expect_configuration_error(exc)
        _names(str(err), hints)
        return Verdict.REFUSED
    if not all(math.isfinite(x) for x in (*card.domain_min, *card.domain_max)):
        raise PropertyViolation(f"accepted a card whose domain is not finite: {card.domain_min}")
    return Verdict.ACCEPTED


# -- control-socket requests -------------------------------------------------------------------


class _StubRunner:
    """The runner's contract for the control tests: records every call that would move."""

    def __init__(self) -> None:
        self.latched = ""
        self.resets_done = 0
        self.moves: list[str] = []

    def start(self) -> None: ...

    def shutdown(self, timeout_s: float) -> bool:
        return True

    def alive(self) -> bool:
        return True

    def health(self) -> tuple[bool, str]:
        return (not self.latched, self.latched)

    def watchdog(self) -> tuple[bool, str]:
        return True, ""

    def fault(self) -> str:
        return self.latched

    def reset_fault(self) -> int:
        self.moves.append("reset_fault")
        self.resets_done += 1
        return self.resets_done

    def state(self) -> str:
        return "idle"

    def current_job(self) -> int | None:
        return None

    def progress(self) -> dict[str, Any] | None:
        return None

    def pause(self) -> None:
        self.moves.append("pause")

    def resume(self) -> None:
        self.moves.append("resume")

    def cancel(self) -> None:
        self.moves.append("cancel")

    def configure(self, feedforward: bool, stale_cycles: int) -> None: ...


@dataclass(slots=True)
class _ControlContext:
    service: Any
    store: Any
    runner: _StubRunner
    server: Any


@contextlib.contextmanager
def _control_context() -> Iterator[_ControlContext]:
    from rt_runtime.rig import load_rig
    from rt_runtime.service.config import parse_config
    from rt_runtime.service.control import ControlServer
    from rt_runtime.service.daemon import Service
    from rt_runtime.service.jobstore import JobStore

    with _tmpdir() as d:
        cfg = parse_config(_configs()[1], d / "d.toml")
        store = JobStore(d / "state", keep_finished=20)
        store.start()
        server = ControlServer(d / "run" / "c.sock", {})
        runner = _StubRunner()
        service = Service(cfg, load_rig("scale_model"), store, server, runner)
        try:
            yield _ControlContext(service, store, runner, server)
        finally:
            store.close()
            for fd in (service._wake_r, service._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)


_REQUESTS: tuple[dict[str, Any], ...] = (
    {"cmd": "submit", "task": "A"},
    {"cmd": "submit", "task": {"length_m": 0.6, "depth_m": 0.15, "beta1_deg": 60,
                               "beta2_deg": 60, "name": "t"}, "planner": "pinn", "max_digs": 3},
    {"cmd": "status"},
    {"cmd": "status", "id": 1},
    {"cmd": "list"},
    {"cmd": "pause", "id": 1},
    {"cmd": "resume", "id": 1},
    {"cmd": "cancel", "id": 2},
    {"cmd": "reset-fault"},
)  # fmt: skip

#: Codes of a refusal (control module docstring); ``internal`` is a traceback in a handler.
_REFUSAL_CODES = ("bad_json", "bad_request", "unknown_command", "refused", "faulted")


@st.composite
def _control_input(draw: st.DrawFn) -> tuple[bytes, tuple[str, ...], bool]:
    kind = draw(st.sampled_from(("doc", "doc", "bytes", "json")))
    hints: tuple[str, ...]
    if kind == "json":
        value = draw(
            st.recursive(
                odd_values(none=True),
                lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=5), c),
                max_leaves=6,
            )
        )
        line, hints = json.dumps(value, allow_nan=True).encode(), ()
    elif kind == "bytes":
        line, hints = draw(document_bytes(_REQUESTS, _json_text, none=True))
    else:
        doc, hints = draw(mutated_document(_REQUESTS, none=True))
        line = _json_text(doc).replace(f'"{HUGE_INT}"', _HUGE_DIGITS).encode()
    return line.replace(b"\n", b" "), hints, draw(st.booleans())


def _check_control(ctx: _ControlContext, example: tuple[bytes, tuple[str, ...], bool]) -> Verdict:
    line, hints, faulted = example
    runner, store = ctx.runner, ctx.store
    runner.latched = "EMCY 0x8611 on boom" if faulted else ""
    before = [(j.id, str(j.status)) for j in store.jobs()]
    moves = len(runner.moves)
    reply = ctx.server.handle_line(line)
    if not isinstance(reply, dict) or not isinstance(reply.get("ok"), bool):
        raise PropertyViolation(f"reply is not an object with ok: {reply!r}")
    # Keep the store small: drop what the request queued (waiting jobs are cancelled).
    after = [(j.id, str(j.status)) for j in store.jobs()]
    if len(after) > 40:
        for job_id, _ in after[:-5]:
            with contextlib.suppress(ExcavatorRtError):
                store.cancel(job_id)
    if reply["ok"]:
        return Verdict.ACCEPTED
    code, text = reply.get("code"), str(reply.get("error", ""))
    if code not in _REFUSAL_CODES:
        raise PropertyViolation(f"refusal with code {code!r}: {text}")
    if after != before or len(runner.moves) != moves:
        raise PropertyViolation(f"a refused request ({code}: {text}) changed the jobs or moved")
    # A command refused for its job's state or the fault latch names that instead.
    if code == "refused" and "job " not in text and "fault" not in text:
        _names(text, hints)
    return Verdict.REFUSED


# -- CAN frames into the master -----------------------------------------------------------------

#: Statusword of OPERATION_ENABLED (voltage enabled, remote).
_ENABLED_STATUSWORD = 0x0237


@dataclass(slots=True)
class _MasterContext:
    master: Any
    device: Any
    rig: Any
    vcu: Any
    node_ids: tuple[int, ...]
    vcu_status: list[Any]
    now_s: float = 0.0


@contextlib.contextmanager
def _master_context() -> Iterator[_MasterContext]:
    from rt_runtime.canbus import CanMaster
    from rt_runtime.canbus.inprocess import InProcessChannel
    from rt_runtime.canbus.vcu import VcuClient
    from rt_runtime.rig import load_rig

    rig = load_rig("scale_model")
    channel = InProcessChannel("inputs")
    master_end = channel.open()
    device = channel.open()
    vcu = VcuClient.from_rig(rig)
    decoded: list[Any] = []

    def other(msg: can.Message, _now_s: float) -> None:
        decoded.append(vcu.decode_status(msg.arbitration_id, msg.data))

    master = CanMaster(master_end, rig, on_other_frame=other)
    ids = tuple(int(i) for i in master.config.node_ids)
    try:
        yield _MasterContext(master, device, rig, vcu, ids, decoded)
    finally:
        master_end.shutdown()
        device.shutdown()


_FrameIn = tuple[int, bytes, bool]  # id, data, extended


def mutated_frames(
    valid: st.SearchStrategy[tuple[int, bytes]],
) -> st.SearchStrategy[tuple[int, bytes]]:
    """Frames ``(id, data)`` of ``valid``, kept or mutated: cut short, grown (to 8 bytes at
    most) or with one byte flipped."""

    @st.composite
    def mutated(draw: st.DrawFn) -> tuple[int, bytes]:
        cob, data = draw(valid)
        how = draw(st.sampled_from(("keep", "cut", "grow", "flip")))
        if how == "cut":
            data = data[: draw(st.integers(0, max(len(data) - 1, 0)))]
        elif how == "grow":
            data = (data + draw(st.binary(min_size=1, max_size=8)))[:8]
        elif how == "flip" and data:
            i = draw(st.integers(0, len(data) - 1))
            data = data[:i] + bytes([data[i] ^ draw(st.integers(1, 255))]) + data[i + 1 :]
        return cob, data

    return mutated()


@st.composite
def _frames(draw: st.DrawFn, node_ids: Sequence[int], vcu_status_id: int) -> list[_FrameIn]:
    """1..6 frames: valid drive frames mutated, random frames in the drives' COB ranges and
    the VCU's, any id, any length 0..8, extended ids."""
    from rt_runtime.canbus.pdo import COB_EMCY, COB_HEARTBEAT, COB_SDO_TX, TPDO1, TPDO2

    def one() -> st.SearchStrategy[_FrameIn]:
        node = st.sampled_from(list(node_ids))
        base = st.sampled_from([COB_EMCY, TPDO1.cob_base, TPDO2.cob_base, COB_HEARTBEAT,
                                COB_SDO_TX])  # fmt: skip
        in_range = st.builds(lambda b, n: b + n, base, node)
        ident = st.one_of(in_range, st.just(vcu_status_id), st.integers(0, 0x7FF))
        valid = st.one_of(
            st.builds(lambda n, p, v: (TPDO1.cob_id(n), TPDO1.codec.pack(p, v)), node,
                      st.integers(-(2**31), 2**31 - 1), st.integers(-(2**31), 2**31 - 1)),
            st.builds(lambda n, s, m, e: (TPDO2.cob_id(n), TPDO2.codec.pack(s, m, e)), node,
                      st.integers(0, 0xFFFF), st.integers(-128, 127), st.integers(0, 0xFFFF)),
            st.builds(lambda n, b: (COB_HEARTBEAT + n, bytes([b])), node, st.integers(0, 255)),
            st.builds(lambda n, d: (COB_EMCY + n, d), node, st.binary(min_size=8, max_size=8)),
            st.builds(lambda d: (vcu_status_id, d), st.binary(min_size=8, max_size=8)),
        )  # fmt: skip

        @st.composite
        def mutate(draw2: st.DrawFn) -> _FrameIn:
            cob, data = draw2(mutated_frames(valid))
            return cob, data, False

        rand = st.tuples(ident, st.binary(max_size=8), st.just(False))
        ext = st.tuples(st.integers(0, 0x1FFFFFFF), st.binary(max_size=8), st.just(True))
        return st.one_of(mutate(), rand, ext)

    return draw(st.lists(one(), min_size=1, max_size=6))


def _master_strategy() -> st.SearchStrategy[Any]:
    from rt_runtime.canbus.vcu import VcuClient
    from rt_runtime.rig import load_rig

    rig = load_rig("scale_model")
    ids = [n for _, n in rig.can.node_ids]
    return _frames(ids, VcuClient.from_rig(rig).status_id)


def _well_formed(node_ids: Sequence[int], frame: _FrameIn) -> str:
    """Which drive frame ``frame`` is when the router may use it ('' for none)."""
    from rt_runtime.canbus.heartbeat import parse_heartbeat
    from rt_runtime.canbus.pdo import COB_EMCY, COB_HEARTBEAT, TPDO1, TPDO2

    cob, data, ext = frame
    if ext:
        return ""
    for n in node_ids:
        if cob == TPDO1.cob_id(n) and len(data) == TPDO1.size:
            return f"tpdo1:{n}"
        if cob == TPDO2.cob_id(n) and len(data) == TPDO2.size:
            return f"tpdo2:{n}"
        if cob == COB_EMCY + n and len(data) == 8:
            return f"emcy:{n}"
        if cob == COB_HEARTBEAT + n and parse_heartbeat(data) is not None:
            return f"hb:{n}"
    return ""


def _check_master(ctx: _MasterContext, frames: list[_FrameIn]) -> Verdict:
    from rt_runtime.canbus.cia402 import Command
    from rt_runtime.canbus.feedback import CycleStatus
    from rt_runtime.canbus.pdo import COB_HEARTBEAT, RPDO2, TPDO1, TPDO2
    from rt_runtime.canbus.vcu import VcuStatus

    master, dev = ctx.master, ctx.device
    cycle, fb = master.cycle, master.feedback
    ctx.now_s += 0.002
    # The drives enabled and answering the SYNC: every axis at a known state.
    cycle.clear_fault_latch()
    cycle.expect_enabled = True
    cycle.bus_exception = None
    cycle.send_sync()
    for axis, n in enumerate(ctx.node_ids):
        dev.send(can.Message(arbitration_id=TPDO1.cob_id(n), is_extended_id=False,
                             data=TPDO1.codec.pack(1000 * (axis + 1), 0)))  # fmt: skip
        dev.send(can.Message(arbitration_id=TPDO2.cob_id(n), is_extended_id=False,
                             data=TPDO2.codec.pack(_ENABLED_STATUSWORD, 8, 0)))  # fmt: skip
        dev.send(can.Message(arbitration_id=COB_HEARTBEAT + n, is_extended_id=False, data=b"\x05"))
    primed = master.read_feedback(ctx.now_s, 0.0)
    if primed.status != CycleStatus.OK:
        raise PropertyViolation(f"valid frames gave status {CycleStatus(primed.status).name}")
    while dev.recv(timeout=0.0) is not None:
        pass
    position = fb.position_um.copy()
    statusword = fb.statusword.copy()
    ctx.vcu_status.clear()
    for cob, data, ext in frames:
        dev.send(can.Message(arbitration_id=cob, is_extended_id=ext, data=data))
    out = master.read_feedback(ctx.now_s, 0.0)
    sent = []
    while (msg := dev.recv(timeout=0.0)) is not None:
        sent.append(msg)
    status = CycleStatus(out.status)
    if cycle.bus_exception is not None or status == CycleStatus.BUS_ERROR:
        raise PropertyViolation(f"the receive path failed: {cycle.bus_exception!r}")
    stops = {RPDO2.cob_id(n) for n in ctx.node_ids}
    for msg in sent:
        word = RPDO2.codec.unpack_from(msg.data)[0] if len(msg.data) == RPDO2.size else None
        if msg.arbitration_id not in stops or word != int(Command.QUICK_STOP):
            raise PropertyViolation(
                f"the master sent 0x{msg.arbitration_id:03X} {bytes(msg.data).hex()} from its "
                "receive path (only quick stop may go out)"
            )
    if sent and not (out.reacted and status >= CycleStatus.EMCY):
        raise PropertyViolation(f"quick stop sent at status {status.name}")
    used = [_well_formed(ctx.node_ids, f) for f in frames]
    for axis, n in enumerate(ctx.node_ids):
        if f"tpdo1:{n}" not in used and fb.position_um[axis] != position[axis]:
            raise PropertyViolation(f"a garbled frame changed node {n}'s position")
        if f"tpdo2:{n}" not in used and fb.statusword[axis] != statusword[axis]:
            raise PropertyViolation(f"a garbled frame changed node {n}'s statusword")
    if not any(used) and (sent or status != CycleStatus.OK):
        raise PropertyViolation(
            f"garbled frames alone gave status {status.name} and {len(sent)} frames sent"
        )
    for s in ctx.vcu_status:
        if s is not None and not (
            isinstance(s, VcuStatus)
            and all(map(math.isfinite, (s.travel_position_m, s.swing_angle_rad)))
            and math.isfinite(s.travel_speed_m_s)
        ):
            raise PropertyViolation(f"VCU status decoded to {s!r}")
    return Verdict.REFUSED if not any(used) else Verdict.ACCEPTED


# -- SDO answers into the master's SDO client --------------------------------------------------


class _ReplyBus(can.BusABC):
    """A bus that hands out queued answers and records what is sent; an empty wait moves its
    clock by the timeout at once (no wall-clock wait)."""

    def __init__(self) -> None:
        super().__init__(channel="inputs")
        self.queue: deque[can.Message] = deque()
        self.sent: list[can.Message] = []
        self.clock_s = 0.0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.queue:
            return self.queue.popleft(), True
        self.clock_s += timeout or 0.0
        return None, True

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg, _ = self._recv_internal(timeout)
        return msg


@dataclass(slots=True)
class _SdoContext:
    bus: _ReplyBus
    od: Any
    node_id: int


@contextlib.contextmanager
def _sdo_context() -> Iterator[_SdoContext]:
    from rt_runtime.canbus.config import DEFAULT_EDS, load_od

    bus = _ReplyBus()
    try:
        yield _SdoContext(bus, load_od(DEFAULT_EDS, 1), 1)
    finally:
        bus.shutdown()


#: Objects the master reads and writes (index, sub): statusword, device type, name string,
#: heartbeat, a PDO COB-ID.
_SDO_OBJECTS = ((0x6041, 0), (0x1000, 0), (0x1008, 0), (0x1017, 0), (0x1800, 1))


@st.composite
def _sdo_input(draw: st.DrawFn) -> tuple[str, int, int, list[bytes]]:
    op = draw(st.sampled_from(("read", "upload", "write")))
    index, sub = draw(st.sampled_from(_SDO_OBJECTS))

    def answer() -> st.SearchStrategy[bytes]:
        mux = struct.pack("<HB", index, sub)
        valid = st.one_of(
            st.builds(lambda c, d: bytes([c]) + mux + d, st.sampled_from([0x43, 0x47, 0x4B, 0x4F,
                      0x42, 0x41, 0x60, 0x80]), st.binary(min_size=4, max_size=4)),
            st.builds(lambda c, d: bytes([c]) + d, st.integers(0, 255),
                      st.binary(min_size=7, max_size=7)),
        )  # fmt: skip
        cut = st.builds(lambda d, n: d[:n], valid, st.integers(0, 8))
        return st.one_of(valid, cut, st.binary(max_size=8))

    answers = draw(st.lists(answer(), max_size=5))
    return op, index, sub, answers


def _check_sdo(ctx: _SdoContext, example: tuple[str, int, int, list[bytes]]) -> Verdict:
    from rt_runtime.canbus.pdo import COB_SDO_TX
    from rt_runtime.canbus.sdo import SdoClient

    op, index, sub, answers = example
    bus = ctx.bus
    bus.queue.clear()
    bus.sent.clear()
    for data in answers:
        bus.queue.append(can.Message(arbitration_id=COB_SDO_TX + ctx.node_id,
                                     is_extended_id=False, data=data))  # fmt: skip
    client = SdoClient(bus, ctx.node_id)

    def now_s() -> float:
        bus.clock_s += 1e-4
        return bus.clock_s

    try:
        if op == "read":
            client.read(ctx.od, index, sub, now_s, 0.01)
        elif op == "upload":
            client.upload(index, sub, now_s, 0.01)
        else:
            index, sub = 0x1017, 0
            client.write(ctx.od, index, sub, 100, now_s, 0.01)
    except (CommunicationError, ConfigurationError) as exc:
        _names(str(exc), (f"0x{index:04X}",), f"node {ctx.node_id}")
        verdict = Verdict.REFUSED
    else:
        verdict = Verdict.ACCEPTED
    for msg in bus.sent[1:]:
        if msg.data[0] & 0xE0 not in (0x60, 0x80):  # upload segment requests and aborts
            raise PropertyViolation(f"the SDO client sent {bytes(msg.data).hex()} after an answer")
    return verdict


# -- the runtime's entries -----------------------------------------------------------------------


def runtime_entries() -> list[InputEntry]:
    """The runtime's entry points, in report order."""
    return [
        InputEntry(
            "task_file",
            "trench task TOML files into load_task",
            lambda: document_bytes(_VALID_TASKS, toml_text),
            _task_context,
            _check_task_file,
        ),
        InputEntry(
            "rig_profile",
            "rig profile TOML files (the shipped ones mutated) into load_rig",
            lambda: document_bytes(_profiles(), toml_text),
            _dir_context,
            _check_rig,
        ),
        InputEntry(
            "daemon_config",
            "daemon TOML configuration files into load_config",
            lambda: document_bytes(_configs(), toml_text),
            _dir_context,
            _check_config,
        ),
        InputEntry(
            "control_request",
            "control-socket request lines into ControlServer.handle_line with the daemon's "
            "commands",
            _control_input,
            _control_context,
            _check_control,
        ),
        InputEntry(
            "model_card",
            "PINN model cards (JSON) into load_card, the model's hash check and its library",
            lambda: document_bytes(_cards(), _json_text, none=True),
            _card_context,
            _check_card,
        ),
        InputEntry(
            "master_frames",
            "CAN frames into CanMaster.read_feedback (TPDOs, EMCY, heartbeat, VCU status)",
            _master_strategy,
            _master_context,
            _check_master,
        ),
        InputEntry(
            "sdo_client",
            "SDO answers into the master's SDO client (read, upload, write)",
            _sdo_input,
            _sdo_context,
            _check_sdo,
        ),
    ]
