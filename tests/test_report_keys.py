"""The JSON keys the README and DESIGN.md list are in the JSON the commands print.

The key lists are read from the documents themselves, so a key that disappears from a report, or
that a document names but no report has, fails here. Runs: ``excavator-rt hil`` on one dig of
task A in lockstep (with a trace and figures), and ``excavator-rt bench --quick`` at one rate.

A list is parsed as the documents write it: backticked keys (dotted for nesting, ``<rate>`` for
a key per entry), a parenthesis after a key holding its children, braces holding children by
name (``{p50, p99}``). A level keyed by data (axis names, rates) is looked through: a key under
``tracking`` is in every axis's entry.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path
from typing import Any

import pytest

from rt_runtime.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: DESIGN.md lives beside the repository (``../shared``), not in it: its lists are checked where
#: it is there; the README repeats them.
_DESIGN_PATH = ROOT.parent / "shared" / "DESIGN.md"
DESIGN = _DESIGN_PATH.read_text() if _DESIGN_PATH.is_file() else ""

_KEY = re.compile(r"^(?:[A-Za-z_]\w*|<\w+>)(?:\.(?:[A-Za-z_]\w*|<\w+>))*$")
_TOKEN = re.compile(r"`([^`]*)`|\{([^{}]*)\}|([()])")

KeyPath = tuple[str, ...]


def contract_keys(text: str) -> set[KeyPath]:
    """The key paths a key list names (see the module docstring)."""
    keys: set[KeyPath] = set()
    parent: KeyPath = ()
    last: KeyPath | None = None
    stack: list[tuple[KeyPath, KeyPath | None]] = []
    for m in _TOKEN.finditer(text):
        name, braces, paren = m.groups()
        if paren == "(":
            stack.append((parent, last))
            parent, last = (last if last is not None else parent), None
        elif paren == ")":
            if stack:
                parent, opened = stack.pop()
                last = opened
        elif braces is not None:
            owner = last if last is not None else parent
            for item in braces.split(","):
                item = item.strip().strip("`")
                if _KEY.match(item):
                    keys.add((*owner, item))
        elif name is not None and _KEY.match(name):
            last = (*parent, *name.split("."))
            keys.add(last)
    return keys


def _has(node: Any, path: KeyPath) -> bool:
    if not path:
        return True
    if isinstance(node, list):
        return bool(node) and all(_has(item, path) for item in node)
    if not isinstance(node, dict):
        return False
    head, rest = path[0], path[1:]
    if head.startswith("<"):
        return bool(node) and all(_has(v, rest) for v in node.values())
    if head in node:
        return _has(node[head], rest)
    entries = list(node.values())
    return bool(entries) and all(isinstance(v, dict) and _has(v, path) for v in entries)


def missing(report: dict[str, Any], keys: set[KeyPath]) -> list[str]:
    """The key paths of ``keys`` that ``report`` does not hold, dotted, sorted."""
    return sorted(".".join(k) for k in keys if not _has(report, k))


def _paragraph(text: str, head: str) -> str:
    """The paragraph (or list item) of ``text`` that starts with ``head``."""
    for block in re.split(r"\n\s*\n|\n(?=- )", text):
        if block.strip().startswith(head):
            return " ".join(block.split())
    raise AssertionError(f"no paragraph starts with {head!r}")


def _list_of(paragraph: str) -> str:
    """The key list of ``<what>: <keys>``: what follows the first colon outside brackets."""
    depth = 0
    for i, c in enumerate(paragraph):
        depth += c in "({"
        depth -= c in ")}"
        if c == ":" and depth == 0:
            return paragraph[i + 1 :]
    raise AssertionError(f"no key list in {paragraph[:60]!r}")


def _sentence(text: str, head: str) -> str:
    flat = " ".join(text.split())
    start = flat.index(head)
    return flat[start : flat.index(". ", start) + 1]


def _run_json(argv: list[str]) -> dict[str, Any]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(argv)
    assert code == 0, out.getvalue()[-2000:]
    report: dict[str, Any] = json.loads(out.getvalue())
    return report


#: Keys of the hil report that only a real-time run has (lockstep runs report ``hil_lockstep``).
REALTIME_ONLY = {("can", "sync_rtt_us"), ("hil_process",)}


def hil_contract() -> set[KeyPath]:
    """The keys of ``hil --json`` the documents name."""
    keys = contract_keys(_list_of(_paragraph(README, "`hil --json` (and the demo's")))
    keys |= contract_keys(_sentence(README, "`hil --json` on the lockstep HIL carries"))
    if DESIGN:
        keys |= contract_keys(_list_of(_paragraph(DESIGN, "- `excavator-rt hil --json`")))
    return keys - REALTIME_ONLY


def bench_contract() -> set[KeyPath]:
    """The keys of ``bench --json`` the documents name."""
    keys = contract_keys(_list_of(_paragraph(README, "`bench --json` (no subcommand")))
    if DESIGN:
        keys |= contract_keys(_list_of(_paragraph(DESIGN, "- `excavator-rt bench --json`")))
    return keys


def test_the_parser_reads_the_lists_as_written() -> None:
    text = (
        "`a` (per axis name: `max_mm`, `rms_mm`; `reported` {max_mm, rms_mm}), `b.c` "
        "({p50, p99}; words), `loop.<rate>.x` (view: `y` (note) and `z` ({min, max}: more)), "
        "`not a key`, `w`"
    )
    assert contract_keys(text) == {
        ("a",), ("a", "max_mm"), ("a", "rms_mm"), ("a", "reported"),
        ("a", "reported", "max_mm"), ("a", "reported", "rms_mm"),
        ("b", "c"), ("b", "c", "p50"), ("b", "c", "p99"),
        ("loop", "<rate>", "x"), ("loop", "<rate>", "x", "y"), ("loop", "<rate>", "x", "z"),
        ("loop", "<rate>", "x", "z", "min"), ("loop", "<rate>", "x", "z", "max"),
        ("w",),
    }  # fmt: skip
    report = {"a": {"boom": {"max_mm": 1.0, "rms_mm": 0.1, "reported": {}}}, "w": [{"k": 1}]}
    assert missing(report, {("a", "max_mm"), ("a", "reported", "rms_mm"), ("w", "k")}) == [
        "a.reported.rms_mm"
    ]


@pytest.fixture(scope="module")
def hil_report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("hil")
    return _run_json(
        ["hil", "--max-digs", "1", "--json", "--trace", str(out / "dig.asc"),
         "--plot", str(out)]
    )  # fmt: skip


def test_hil_json_holds_every_documented_key(hil_report: dict[str, Any]) -> None:
    keys = hil_contract()
    assert {("tracking", "reported"), ("digs", "cut_volume_L"), ("hil_lockstep", "hil_us")} <= keys
    assert missing(hil_report, keys) == []


@pytest.fixture(scope="module")
def bench_report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    png = tmp_path_factory.mktemp("bench") / "hist.png"
    return _run_json(
        ["bench", "--quick", "--seconds", "0.5", "--rates", "500", "--no-rt", "--json",
         "--plot", str(png)]
    )  # fmt: skip


def test_bench_json_holds_every_documented_key(bench_report: dict[str, Any]) -> None:
    keys = bench_contract()
    assert {
        ("pinn", "infer_us"),
        ("loop", "lateness_us"),
        ("loop", "<rate>", "hil_process", "sync_work_us", "max"),
        ("can", "bus_load"),
    } <= keys
    assert missing(bench_report, keys) == []
