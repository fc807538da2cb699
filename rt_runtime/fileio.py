"""Atomic, durable file replacement (the daemon's job store, the training data sets).

:func:`atomic_write` writes the new content to a temporary file ``.<name>.<pid>.<n>.tmp`` in the
same directory, flushes and fsyncs it, renames it over the file (``os.replace`` is atomic on
POSIX) and fsyncs the directory so the rename itself survives a power cut. A crash at any point
leaves either the old or the new file whole, never a mix; a temporary file left behind by a
crash matches ``.<name>.*.tmp`` (the callers remove those on their next start).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO

__all__ = ["atomic_write"]

_tmp_counter = iter(range(1, 1 << 62))


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, write_fn: Callable[[IO[bytes]], object], mode: int = 0o666) -> None:
    """Replace ``path`` with what ``write_fn`` writes, atomically and durably.

    Args:
        path: The file (its directory must exist).
        write_fn: Writes the whole content to the binary file it is given.
        mode: Permissions of the new file (less the umask, as for :func:`open`).

    Raises:
        OSError: The write failed (the old file is untouched; the temporary file is removed).
            Whatever ``write_fn`` raises likewise leaves the old file and no temporary one.
    """
    while True:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{next(_tmp_counter)}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, mode)
        except FileExistsError:  # left by a killed process that had this pid: take the next
            continue
        break
    try:
        with os.fdopen(fd, "wb") as f:
            write_fn(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(path.parent)
