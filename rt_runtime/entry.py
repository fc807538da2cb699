"""The ``excavator-rt`` console script: the ``job`` client without the rest of the CLI.

A ``job`` command (``excavator-rt job status``, ``cancel``, ...) imports only the control
socket's client, so it starts in about a tenth of a second and a ``cancel`` is not late;
every other command is :func:`rt_runtime.cli.main`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``excavator-rt``; returns the exit code."""
    words = list(sys.argv[1:] if argv is None else argv)
    if words[:1] != ["job"]:
        from rt_runtime.cli import main as full_main

        return full_main(words)
    import argparse

    from rt_runtime.errors import ExcavatorRtError
    from rt_runtime.service import client

    parser = argparse.ArgumentParser(prog="excavator-rt")
    client.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(words)
    try:
        return int(args.handler(args))
    except ExcavatorRtError as e:
        print(f"excavator-rt: error: {e}", file=sys.stderr)
        return 2
