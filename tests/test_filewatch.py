"""The planner's verified files watched on disk (rt_runtime.planning.filewatch)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from rt_runtime.planning.filewatch import FileWatch, sha256_bytes
from rt_runtime.planning.pinn import DEFAULT_MODEL_DIR, PinnPlanner, sha256_file
from rt_runtime.rig import load_rig


def _watched(tmp_path: Path, data: bytes = b"model bytes") -> tuple[Path, FileWatch]:
    path = tmp_path / "m.onnx"
    path.write_bytes(data)
    return path, FileWatch([(path, sha256_bytes(data))])


def test_unchanged_touched_or_copied_over_with_the_same_bytes_is_no_change(
    tmp_path: Path,
) -> None:
    path, watch = _watched(tmp_path)
    assert watch.changed() is None
    os.utime(path, ns=(1, 1))  # another mtime: hashed again, same digest
    assert watch.changed() is None
    staged = tmp_path / "staged"
    staged.write_bytes(b"model bytes")
    os.replace(staged, path)  # another inode, same bytes
    assert watch.changed() is None


def test_other_bytes_a_missing_file_and_a_wrong_digest_are_changes(tmp_path: Path) -> None:
    path, watch = _watched(tmp_path)
    path.write_bytes(b"model bytez")
    os.utime(path, ns=(10**18, 10**18))
    text = watch.changed()
    assert text is not None and str(path) in text and "changed on disk" in text
    assert sha256_bytes(b"model bytez")[:12] in text
    path.unlink()
    text = watch.changed()
    assert text is not None and "gone or unreadable" in text
    # A file that never held what the card says is a change at the first look.
    path.write_bytes(b"model bytes")
    assert FileWatch([(path, "0" * 64)]).changed() is not None


def test_a_pinn_planner_names_every_file_it_was_verified_from(tmp_path: Path) -> None:
    models = tmp_path / "models"
    shutil.copytree(DEFAULT_MODEL_DIR, models)
    files = dict(PinnPlanner(load_rig("scale_model"), models).verified_files())
    names = {p.name for p in files}
    for kind in ("downward", "backward"):
        assert {f"pinn_{kind}.json", f"pinn_{kind}.onnx"} <= names
    assert all(sha256_file(p) == d for p, d in files.items())
    watch = FileWatch(files.items())
    assert watch.changed() is None
    card = models / "pinn_backward.json"
    card.write_text(card.read_text().replace('"rig"', ' "rig"', 1))
    assert watch.changed() is not None and "pinn_backward.json" in (watch.changed() or "")
