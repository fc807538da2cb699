"""The PSO teacher dataset: real dask clusters, resumable chunks, reproducible hashes, checks."""

from __future__ import annotations

import argparse
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("tqdm")

from distributed import LocalCluster

from rt_runtime.errors import ConfigurationError
from rt_runtime.planning import oneshot
from rt_runtime.rig import load_rig
from rt_runtime.training import dataset as ds

ENV_AT_IMPORT = dict(os.environ)
TINY = {"n_particles": 8, "n_iterations": 5, "polish_starts": 1}


def tiny_spec(**changes: object) -> ds.DatasetSpec:
    """8 problems in chunks of 3 (the last one partial), a tiny swarm."""
    args: dict[str, object] = {"n_samples": 8, "n_test": 2, "chunk_size": 3, **TINY}
    args.update(changes)
    return ds.DatasetSpec.default("downward", **args)


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """A running 2-process cluster on 127.0.0.1, reached by address like a remote one."""
    with (
        ds.preserved_environ(),
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        ) as cluster,
    ):
        yield str(cluster.scheduler_address)


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ds.DatasetInfo]:
    """The tiny dataset made through the default path: generate() starts its own LocalCluster."""
    out = tmp_path_factory.mktemp("ref")
    info = ds.generate("scale_model", tiny_spec(), out, workers=2, progress=False)
    return out, info


def copy_of(reference: tuple[Path, ds.DatasetInfo], tmp_path: Path) -> Path:
    out = tmp_path / "ds"
    shutil.copytree(reference[0], out)
    return out


def test_spec_round_trip_hash_and_validation() -> None:
    spec = ds.DatasetSpec.default("backward", seed=3)
    assert spec.sampler == oneshot.SAMPLER_RANGES[oneshot.DigType.BACKWARD]
    assert ds.DatasetSpec.from_json(spec.to_json()) == spec
    assert spec.n_samples == 1800 and spec.n_test == 200 and spec.chunk_size == 50
    # The PSO defaults are the teacher's own.
    assert spec.pso_options["n_particles"] == 40 and spec.pso_options["n_samples"] == 101
    # n_samples and n_test do not change what a chunk holds; everything else does.
    assert ds.DatasetSpec.default("backward", seed=3, n_samples=99_000).hash == spec.hash
    assert ds.DatasetSpec.default("backward", seed=4).hash != spec.hash
    assert ds.DatasetSpec.default("backward", seed=3, chunk_size=49).hash != spec.hash
    wider = ds.DatasetSpec.default(
        "backward", seed=3, sampler=oneshot.SAMPLER_RANGES[oneshot.DigType.DOWNWARD]
    )
    assert wider.hash != spec.hash
    for bad, field in (
        ({"n_test": 1800}, "n_test"),
        ({"chunk_size": 0}, "chunk_size"),
        ({"seed": -1}, "seed"),
        ({"polish_starts": 41}, "polish_starts"),
        ({"n_samples": 2.5}, "n_samples"),
    ):
        with pytest.raises(ConfigurationError, match=field):
            ds.DatasetSpec.default("downward", **bad)
    with pytest.raises(ConfigurationError, match="dig type"):
        ds.DatasetSpec.default("sideways")
    data = spec.to_dict()
    data["colour"] = "red"
    with pytest.raises(ConfigurationError, match="colour"):
        ds.DatasetSpec.from_dict(data)


def test_local_cluster_run_files_metadata_and_load(
    reference: tuple[Path, ds.DatasetInfo],
) -> None:
    out, info = reference
    rig = load_rig("scale_model")
    spec = tiny_spec()
    assert info.samples == 8 and info.chunks_total == 3 and info.chunks_computed == 3
    assert sorted(p.name for p in (out / "downward").iterdir()) == [
        "chunk_00000.npz",
        "chunk_00001.npz",
        "chunk_00002.npz",
        "spec.json",
    ]
    d = ds.load(info.path)
    assert d.hash == info.hash and len(d) == 8 and d.dig_type == oneshot.DigType.DOWNWARD
    assert d.X.shape == (8, 7) and d.Y.shape == (8, 4) and d.margins.shape == (8, 22)
    assert d.feasible.dtype == np.bool_ and d.X.dtype == np.float64
    # Inputs are exactly the seeded problems; the split holds distinct feasible samples only.
    problems = oneshot.sample_problems(rig, 8, oneshot.DigType.DOWNWARD, 0, spec.sampler)
    np.testing.assert_array_equal(d.X, ds.problem_inputs(problems))
    np.testing.assert_array_equal(d.Y[:, 3], d.T_s)
    assert d.test_idx.size == 2 and d.train_idx.size == int(d.feasible.sum()) - 2
    assert not set(d.train_idx) & set(d.test_idx)
    assert d.feasible[d.train_idx].all() and d.feasible[d.test_idx].all()
    x_train, y_train = d.train_xy
    np.testing.assert_array_equal(x_train, d.X[d.train_idx])
    assert y_train.shape == (d.train_idx.size, 4)
    with pytest.raises(ValueError, match="read-only"):
        d.X[0, 0] = 1.0
    # A worker's answer is the in-process teacher's for the same chunk. Not bitwise here: this
    # test process has imported torch and others by now, which can change BLAS rounding by an
    # ulp and steer SLSQP a hair apart (seen: 1.6e-7 relative); worker against worker is
    # compared bitwise in test_reproducible_bitwise_across_clusters.
    direct = ds.solution_arrays(
        oneshot.solve_pso(rig, problems[3:6], seed=0, workers=1, **spec.pso_options)
    )
    np.testing.assert_allclose(d.Y[3:6], direct["Y"], rtol=1e-5)
    np.testing.assert_allclose(d.K_rad[3:6], direct["K_rad"], rtol=1e-5, atol=1e-9)

    meta = json.loads(info.meta_path.read_text())
    assert meta == d.meta
    assert meta["rig"]["name"] == "scale_model"
    assert meta["rig"]["profile_sha256"] == ds.rig_profile_sha256(rig)
    assert len(meta["rig"]["profile_sha256"]) == 64
    assert ds.DatasetSpec.from_dict(meta["spec"]) == spec
    assert meta["sampler"] == spec.to_dict()["sampler"]
    assert meta["pso"]["n_particles"] == 8 and meta["pso"]["n_iterations"] == 5
    assert meta["seeds"]["problems"] == 0 and meta["seeds"]["pso"] == 0
    counts = meta["counts"]
    assert counts["samples"] == 8 and counts["feasible"] + counts["infeasible"] == 8
    assert meta["feasible_fraction"] == pytest.approx(counts["feasible"] / 8)
    assert [c["problems"] for c in meta["chunks"]] == [3, 3, 2]
    assert all(c["solve_s"] > 0 and c["computed"] for c in meta["chunks"])
    assert meta["wall_s"] > 0 and meta["package_version"] == "0.1.0"
    assert (
        meta["arrays_sha256"]
        == meta["hash"]
        == info.hash
        == ds.arrays_sha256(
            {k: getattr(d, k) for k in (*ds.SAMPLE_ARRAYS, "train_idx", "test_idx")}
        )
    )
    assert meta["inputs"] == list(ds.INPUT_NAMES) and meta["outputs"] == list(ds.OUTPUT_NAMES)
    # Every worker ran the package with one BLAS thread.
    workers = meta["cluster"]["workers"]
    assert len(workers) == 2
    assert all(
        w["OPENBLAS_NUM_THREADS"] == "1" and w["rt_runtime"] == "0.1.0" for w in workers.values()
    )
    assert all(addr.startswith("tcp://127.0.0.1:") for addr in workers)


def test_local_cluster_leaves_our_environment_alone(
    reference: tuple[Path, ds.DatasetInfo],
) -> None:
    # The nannies wrote these into our os.environ to pass them to their workers.
    workers = json.loads(reference[1].meta_path.read_text())["cluster"]["workers"]
    assert all(w["MALLOC_TRIM_THRESHOLD_"] for w in workers.values())
    for key in ("MALLOC_TRIM_THRESHOLD_", "PYTHONHASHSEED"):
        assert os.environ.get(key) == ENV_AT_IMPORT.get(key), key


def test_reproducible_bitwise_across_clusters(
    reference: tuple[Path, ds.DatasetInfo], scheduler: str, tmp_path: Path
) -> None:
    info = ds.generate("scale_model", tiny_spec(), tmp_path, scheduler=scheduler, progress=False)
    assert info.hash == reference[1].hash
    a, b = ds.load(info.path), ds.load(reference[1].path)
    for name in (*ds.SAMPLE_ARRAYS, "train_idx", "test_idx"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_resume_solves_only_the_missing_chunk(
    reference: tuple[Path, ds.DatasetInfo], scheduler: str, tmp_path: Path
) -> None:
    out = copy_of(reference, tmp_path)
    (out / "downward" / "chunk_00001.npz").unlink()
    info = ds.generate("scale_model", tiny_spec(), out, scheduler=scheduler, progress=False)
    assert info.chunks_computed == 1 and info.hash == reference[1].hash
    meta = json.loads(info.meta_path.read_text())
    assert [c["computed"] for c in meta["chunks"]] == [False, True, False]
    # Nothing missing: no cluster is needed at all (this address would fail if it were used).
    again = ds.generate(
        "scale_model", tiny_spec(), out, scheduler="tcp://127.0.0.1:9", progress=False
    )
    assert again.chunks_computed == 0 and again.hash == reference[1].hash


def test_corrupt_and_partial_chunks_are_solved_again(
    reference: tuple[Path, ds.DatasetInfo], scheduler: str, tmp_path: Path
) -> None:
    out = copy_of(reference, tmp_path)
    c0, c2 = out / "downward" / "chunk_00000.npz", out / "downward" / "chunk_00002.npz"
    c0.write_bytes(b"not a zip file")
    c2.write_bytes(c2.read_bytes()[: c2.stat().st_size // 2])
    (out / "downward" / ".chunk_00001.npz.123.tmp").write_bytes(b"left by a killed run")
    info = ds.generate("scale_model", tiny_spec(), out, scheduler=scheduler, progress=False)
    assert info.chunks_computed == 2 and info.hash == reference[1].hash
    assert not list((out / "downward").glob(".*.tmp"))


def test_other_spec_in_the_same_dir_is_refused(
    reference: tuple[Path, ds.DatasetInfo], scheduler: str, tmp_path: Path
) -> None:
    out = copy_of(reference, tmp_path)
    other = tiny_spec(seed=1, n_particles=9)
    with pytest.raises(ConfigurationError) as e:
        ds.generate("scale_model", other, out, scheduler=scheduler, progress=False)
    msg = str(e.value)
    assert "seed: 0 -> 1" in msg and "pso.n_particles: 8 -> 9" in msg and "--force" in msg
    assert "chunk_size" not in msg
    info = ds.generate("scale_model", other, out, scheduler=scheduler, progress=False, force=True)
    assert info.chunks_computed == 3 and info.hash != reference[1].hash


def test_growing_reuses_every_full_chunk(
    reference: tuple[Path, ds.DatasetInfo], scheduler: str, tmp_path: Path
) -> None:
    out = copy_of(reference, tmp_path)
    grown = tiny_spec(n_samples=10)
    info = ds.generate("scale_model", grown, out, scheduler=scheduler, progress=False)
    # Chunks 0 and 1 are reused; chunk 2 grew from 2 to 3 problems; chunk 3 is new.
    assert info.chunks_total == 4 and info.chunks_computed == 2 and info.samples == 10
    big, small = ds.load(info.path), ds.load(reference[1].path)
    np.testing.assert_array_equal(big.X[:8], small.X)
    np.testing.assert_array_equal(big.Y[:6], small.Y[:6])


def test_load_refuses_a_tampered_file(
    reference: tuple[Path, ds.DatasetInfo], tmp_path: Path
) -> None:
    out = copy_of(reference, tmp_path)
    path = out / "downward.npz"
    with np.load(path) as z:
        arrays = {k: np.array(z[k]) for k in z.files}
    arrays["Y"][0, 3] += 1e-9
    np.savez(path, **arrays)
    with pytest.raises(ConfigurationError, match="modified"):
        ds.load(path)
    with pytest.raises(ConfigurationError, match="cannot read"):
        ds.load(tmp_path / "nothing.npz")


def test_split_needs_feasible_samples() -> None:
    spec = tiny_spec()
    feasible = np.array([True, False, True, False, False, False, False, False])
    with pytest.raises(ConfigurationError, match="only 2 of 8"):
        ds._split(spec, feasible)
    train, test = ds._split(tiny_spec(n_test=1), feasible)
    assert sorted([*train, *test]) == [0, 2] and test.size == 1


def test_command_line_json(
    scheduler: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    ds.add_parser(parser.add_subparsers(dest="command"))
    argv = ["dataset", "--samples", "3", "--test", "1", "--chunk", "2", "--out", str(tmp_path)]
    args = parser.parse_args([*argv, "--scheduler", scheduler, "--json"])
    assert args.handler(args) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["types"]) == {"downward", "backward"}
    for kind, t in r["types"].items():
        assert t["samples"] == 3 and t["path"] == str(tmp_path / f"{kind}.npz")
        assert ds.load(t["path"]).hash == t["hash"] and t["wall_s"] > 0
    args = parser.parse_args(
        [*argv, "--type", "backward", "--scheduler", scheduler, "--workers", "2"]
    )
    with pytest.raises(ConfigurationError, match="workers"):
        args.handler(args)


def test_one_run_per_directory(reference: tuple[Path, ds.DatasetInfo], tmp_path: Path) -> None:
    import fcntl

    out = copy_of(reference, tmp_path)
    with open(out / ".downward.lock", "a+b") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(ConfigurationError, match="another run"):
            ds.generate("scale_model", tiny_spec(), out, progress=False)
    assert ds.generate("scale_model", tiny_spec(), out, progress=False).chunks_computed == 0
