"""Files a planner was verified from, watched for changes on disk.

A planner loads its models once and checks each file against the digest its card names
(:func:`rt_runtime.planning.pinn.check_file`). What it then plans from is what was verified;
a file replaced or corrupted later on disk (a model deployed under a running job, a failing
disk) would be loaded unchecked by nothing, but a process that loads it next (the planner
process of a resumed job) would find a mismatch only then. :class:`FileWatch` finds the change
when it happens: the planner process looks every :data:`WATCH_PERIOD_S` and before each plan.

Rules: a file's ``stat`` (inode, size, modification time in ns) is compared first; only when it
differs is the file hashed again (SHA-256), so a ``touch`` or a copy of the same bytes is no
change. A missing or unreadable file is a change.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from pathlib import Path

__all__ = ["WATCH_PERIOD_S", "FileWatch", "sha256_bytes"]

#: How often an idle planner process looks at its files (s of wall time).
WATCH_PERIOD_S = 0.5


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def _stat(path: Path) -> tuple[int, int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns)


def _digest(path: Path) -> str | None:
    try:
        return sha256_bytes(path.read_bytes())
    except OSError:
        return None


class FileWatch:
    """The files a planner was verified from and their digests.

    Args:
        files: ``(path, sha256)`` of each file as it was verified (hex digest).
    """

    def __init__(self, files: Iterable[tuple[Path, str]]) -> None:
        self._files = [(Path(p), d) for p, d in files]
        # Hashed once more here: a file that changed between its check and this watch is a
        # change at the first look (its stat is not taken as verified).
        self._stats = [
            st if (st := _stat(p)) is not None and _digest(p) == d else None
            for p, d in self._files
        ]

    @property
    def paths(self) -> tuple[Path, ...]:
        """The watched files."""
        return tuple(p for p, _ in self._files)

    def changed(self) -> str | None:
        """None while every file holds what was verified; else what changed, naming the file
        and both digests (the first changed file)."""
        for i, (path, expected) in enumerate(self._files):
            st = _stat(path)
            if st is not None and st == self._stats[i]:
                continue
            digest = None if st is None else _digest(path)
            if digest is None:
                return f"{path} is gone or unreadable since it was verified"
            if digest != expected:
                return (
                    f"{path} changed on disk since it was verified: SHA-256 "
                    f"{digest[:12]}... where {expected[:12]}... was loaded"
                )
            self._stats[i] = st  # the same bytes again (touched, copied over)
        return None
