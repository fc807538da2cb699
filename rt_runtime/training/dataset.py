"""The PSO teacher dataset for the PINN (``excavator-rt dataset``): seeded, resumable, distributed.

For each dig type, ``n_samples`` one-shot problems are drawn once, seeded, in the client
(:func:`rt_runtime.planning.oneshot.sample_problems` over :data:`~rt_runtime.planning.oneshot.
SAMPLER_RANGES`, Yao Fig. 9) and solved by the PSO teacher
(:func:`~rt_runtime.planning.oneshot.solve_pso`) in chunks of ``chunk_size``, one dask task per
chunk. The same ``submit``/``as_completed`` code runs on a :class:`distributed.LocalCluster` of
this machine's cores (bound to 127.0.0.1, no dashboard) or on a remote cluster given by its
scheduler address. Workers return arrays; only the client writes files, because a remote
cluster does not share our disk.

On disk, under ``out_dir``::

    <type>/spec.json            the spec and run identity the chunks belong to
    <type>/chunk_00000.npz ...  one per chunk, written atomically (tmp, fsync, rename)
    <type>.npz                  the consolidated arrays (see :class:`Dataset`)
    <type>.json                 metadata: rig and its profile hash, spec, seeds, sampler, PSO
                                settings, counts, timings, versions, the arrays' SHA-256

A rerun with the same spec skips the finished chunks, so a killed run resumes where it stopped;
an unreadable or partial chunk is solved again. A different spec in the same directory is
refused, naming the differing keys. ``n_samples`` and ``n_test`` are not part of a run's
identity: problems are drawn sequentially from one seeded stream, so the first problems of a
larger run are those of a smaller one, and growing a dataset (1800 -> 100k) reuses every chunk
solved before (a partial last chunk is detected by its problems and solved again).

Choices where neither the paper nor DESIGN.md says:

- Inputs are ``(theta11..theta13, theta21..theta23, H)`` and outputs ``(a16, a26, a36, T)``
  (DESIGN.md, "Models"). Each sample also keeps the teacher's particle ``K = -a6 T^6`` (the
  search variable, see :mod:`rt_runtime.planning.oneshot`), its objective, volume, energy,
  theta_p and every constraint margin.
- Infeasible teacher answers stay in the file, flagged; the split uses feasible ones only: a
  seeded permutation of all samples, its feasible members in order, the last ``n_test`` of them
  the test set. Fewer than ``n_test + 1`` feasible samples is an error.
- The dataset hash is the SHA-256 of the consolidated arrays (names, dtypes, shapes, bytes),
  not of the ``.npz`` file, whose zip headers carry timestamps: two runs of one spec give the
  same hash. :func:`load` recomputes it and refuses a file that does not match its metadata.
- The rig profile hash is the SHA-256 of the profile's parsed TOML content (canonical JSON), so
  comments and formatting do not change it, every value does.
- Reproducibility is bitwise for one spec on one platform whatever the number of workers or the
  scheduler: a chunk is always the same batch of problems, solved with ``workers=1``.

Runs outside the loop; needs the ``train`` extra (dask.distributed, tqdm), imported lazily.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import inspect
import json
import math
import os
import sys
import time
import tomllib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from rt_runtime import __version__
from rt_runtime.errors import CommunicationError, ConfigurationError, ExcavatorRtError
from rt_runtime.fileio import atomic_write
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import DigType, Problem, SamplerRanges, Solution
from rt_runtime.planning.pinn import INPUT_NAMES, OUTPUT_NAMES
from rt_runtime.rig import DEFAULT_RIG, Rig, load_rig

if TYPE_CHECKING:
    from distributed import Client

FloatArray = NDArray[np.float64]
Arrays = dict[str, NDArray[Any]]

FORMAT = "excavator-rt-dataset/1"

# Arrays of one sample each, the same in chunks and in the consolidated file: name -> shape
# after the sample axis.
SAMPLE_ARRAYS: dict[str, tuple[int, ...]] = {
    "X": (len(INPUT_NAMES),),
    "Y": (len(OUTPUT_NAMES),),
    "K_rad": (3,),
    "objective": (),
    "feasible": (),
    "volume_m3": (),
    "energy_j": (),
    "T_s": (),
    "theta_p_rad": (),
    "margins": (len(oneshot.CONSTRAINT_NAMES),),
}

# DatasetSpec field -> solve_pso keyword.
_PSO_KEYWORDS = {
    "n_particles": "n_particles",
    "n_iterations": "n_iterations",
    "search_samples": "search_samples",
    "polish_starts": "polish_starts",
    "grid_samples": "n_samples",
}
# The spec's PSO defaults are the teacher's own, so `excavator-rt dataset` follows them.
_SOLVE_PSO_PARAMETERS = inspect.signature(oneshot.solve_pso).parameters
_PSO_DEFAULTS = {f: int(_SOLVE_PSO_PARAMETERS[k].default) for f, k in _PSO_KEYWORDS.items()}
# The split's stream: SeedSequence([seed, _SPLIT_STREAM]), apart from the sampler's (seed).
_SPLIT_STREAM = 0x5B17
_SAMPLER_FIELDS = tuple(f.name for f in dataclasses.fields(SamplerRanges))


@dataclass(frozen=True, slots=True)
class DatasetSpec:
    """What to generate for one dig type; validated on construction.

    Attributes:
        rig: Rig profile name (must match the rig given to :func:`generate`).
        dig_type: Downward or backward.
        sampler: Where problems are drawn from (see :func:`DatasetSpec.default`).
        n_samples: Problems drawn and solved, >= 1 (feasible or not).
        n_test: Feasible samples held out for testing, 0 <= n_test < n_samples.
        seed: Seed of the problem draw, the PSO streams and the split, >= 0.
        chunk_size: Problems per task and per chunk file, >= 1.
        n_particles: PSO particles per problem.
        n_iterations: PSO swarm updates.
        search_samples: Trajectory samples during the swarm search.
        polish_starts: Personal bests polished by SLSQP per problem.
        grid_samples: Trajectory samples of the polish and the final answer (``n_samples`` of
            :func:`~rt_runtime.planning.oneshot.solve_pso`).

    Raises:
        ConfigurationError: A value outside the ranges above, or an empty/inverted sampler range.
    """

    rig: str
    dig_type: DigType
    sampler: SamplerRanges
    n_samples: int = 1800
    n_test: int = 200
    seed: int = 0
    chunk_size: int = 50
    n_particles: int = _PSO_DEFAULTS["n_particles"]
    n_iterations: int = _PSO_DEFAULTS["n_iterations"]
    search_samples: int = _PSO_DEFAULTS["search_samples"]
    polish_starts: int = _PSO_DEFAULTS["polish_starts"]
    grid_samples: int = _PSO_DEFAULTS["grid_samples"]

    def __post_init__(self) -> None:
        object.__setattr__(self, "dig_type", _dig_type(self.dig_type))
        ints = ("n_samples", "n_test", "seed", "chunk_size", *_PSO_KEYWORDS)
        for name in ints:
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ConfigurationError(f"dataset spec: {name} must be an integer; got {value!r}")
        checks = (
            ("n_samples", self.n_samples >= 1, ">= 1"),
            ("n_test", 0 <= self.n_test < self.n_samples, f"in [0, n_samples={self.n_samples})"),
            ("seed", self.seed >= 0, ">= 0"),
            ("chunk_size", self.chunk_size >= 1, ">= 1"),
            ("n_particles", self.n_particles >= 2, ">= 2"),
            ("n_iterations", self.n_iterations >= 1, ">= 1"),
            ("search_samples", self.search_samples >= 2, ">= 2"),
            ("grid_samples", self.grid_samples >= 2, ">= 2"),
            (
                "polish_starts",
                0 <= self.polish_starts <= self.n_particles,
                f"in [0, n_particles={self.n_particles}]",
            ),
        )
        for name, ok, allowed in checks:
            if not ok:
                raise ConfigurationError(
                    f"dataset spec: {name} must be {allowed}; got {getattr(self, name)!r}"
                )
        for name in _SAMPLER_FIELDS:
            lo, hi = getattr(self.sampler, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ConfigurationError(
                    f"dataset spec: sampler.{name} must be a finite range lo <= hi; got {(lo, hi)}"
                )

    @classmethod
    def default(
        cls, dig_type: DigType | str, rig: str = DEFAULT_RIG, **changes: Any
    ) -> DatasetSpec:
        """Yao's size (1800 samples, 200 test) with the lead's sampler ranges and PSO defaults.

        Args:
            dig_type: A :class:`DigType` or its name (``"downward"``, ``"backward"``).
            rig: Rig profile name.
            **changes: Any other field of the spec.

        Raises:
            ConfigurationError: An unknown dig type or field, or an invalid value.
        """
        kind = _dig_type(dig_type)
        unknown = set(changes) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ConfigurationError(f"dataset spec has no field(s) {sorted(unknown)}")
        sampler = changes.pop("sampler", oneshot.SAMPLER_RANGES[kind])
        return cls(rig=rig, dig_type=kind, sampler=sampler, **changes)

    @property
    def type_name(self) -> str:
        """``"downward"`` or ``"backward"``: the name used on disk and on the command line."""
        return self.dig_type.name.lower()

    @property
    def pso_options(self) -> dict[str, int]:
        """Keyword arguments of :func:`~rt_runtime.planning.oneshot.solve_pso` (besides seed)."""
        return {k: int(getattr(self, f)) for f, k in _PSO_KEYWORDS.items()}

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (sampler ranges as ``[lo, hi]`` lists, PSO settings grouped)."""
        return {
            "rig": self.rig,
            "dig_type": self.type_name,
            "n_samples": self.n_samples,
            "n_test": self.n_test,
            "seed": self.seed,
            "chunk_size": self.chunk_size,
            "sampler": {n: [float(v) for v in getattr(self.sampler, n)] for n in _SAMPLER_FIELDS},
            "pso": {f: int(getattr(self, f)) for f in _PSO_KEYWORDS},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> DatasetSpec:
        """Inverse of :meth:`to_dict`.

        Raises:
            ConfigurationError: Missing or unknown keys, or invalid values.
        """
        top = {"rig", "dig_type", "n_samples", "n_test", "seed", "chunk_size", "sampler", "pso"}
        _require_keys("dataset spec", data, top)
        _require_keys("dataset spec sampler", data["sampler"], set(_SAMPLER_FIELDS))
        _require_keys("dataset spec pso", data["pso"], set(_PSO_KEYWORDS))
        try:
            sampler = SamplerRanges(
                **{
                    n: (float(data["sampler"][n][0]), float(data["sampler"][n][1]))
                    for n in _SAMPLER_FIELDS
                }
            )
        except (TypeError, ValueError, IndexError) as e:
            raise ConfigurationError(f"dataset spec sampler: ranges must be [lo, hi]: {e}") from e
        return cls(
            rig=str(data["rig"]),
            dig_type=_dig_type(data["dig_type"]),
            sampler=sampler,
            n_samples=data["n_samples"],
            n_test=data["n_test"],
            seed=data["seed"],
            chunk_size=data["chunk_size"],
            **{f: data["pso"][f] for f in _PSO_KEYWORDS},
        )

    def to_json(self) -> str:
        """The spec as indented JSON with sorted keys."""
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> DatasetSpec:
        """Inverse of :meth:`to_json`.

        Raises:
            ConfigurationError: Not JSON, or an invalid spec.
        """
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigurationError(f"dataset spec is not valid JSON: {e}") from e
        if not isinstance(data, dict):
            raise ConfigurationError("dataset spec JSON must be an object")
        return cls.from_dict(data)

    def compat_dict(self) -> dict[str, Any]:
        """The fields that decide the chunks' contents: all but ``n_samples`` and ``n_test``."""
        d = self.to_dict()
        del d["n_samples"], d["n_test"]
        return d

    @property
    def hash(self) -> str:
        """SHA-256 of :meth:`compat_dict`: two specs with the same hash share their chunks."""
        return _sha256_json(self.compat_dict())


@dataclass(frozen=True, slots=True)
class DatasetInfo:
    """What one :func:`generate` run produced for one dig type.

    Attributes:
        dig_type: Downward or backward.
        path: The consolidated arrays (``<out>/<type>.npz``).
        meta_path: Their metadata (``<out>/<type>.json``).
        samples: Problems solved.
        feasible: Of which the teacher found a feasible plan.
        train: Training samples.
        test: Test samples.
        hash: SHA-256 of the consolidated arrays.
        wall_s: Wall time of this run for this type (start to consolidated file written).
        chunks_total: Chunks of the dataset.
        chunks_computed: Chunks solved by this run (the others were reused from disk).
    """

    dig_type: DigType
    path: Path
    meta_path: Path
    samples: int
    feasible: int
    train: int
    test: int
    hash: str
    wall_s: float
    chunks_total: int
    chunks_computed: int


@dataclass(frozen=True, slots=True)
class Dataset:
    """A consolidated dataset as :func:`load` returns it; arrays are read-only, N samples.

    Attributes:
        X: Inputs ``(N, 7)``, :data:`INPUT_NAMES` (rad, rad, m).
        Y: Teacher outputs ``(N, 4)``, :data:`OUTPUT_NAMES` (rad/s^6, s).
        K_rad: The teacher's particle ``K = -a6 T^6`` ``(N, 3)``.
        objective: Yao eq 11 ``(N,)``.
        feasible: Whether every constraint holds ``(N,)``.
        volume_m3: Excavated volume ``(N,)``.
        energy_j: Energy ``(N,)``.
        T_s: Digging time ``(N,)`` (equal to ``Y[:, 3]``).
        theta_p_rad: Initial digging angle ``(N,)``.
        margins: Constraint margins ``(N, 22)`` (>= 0 holds), names in ``meta["constraints"]``.
        train_idx: Indices of the training samples (feasible only), ascending.
        test_idx: Indices of the test samples (feasible only), ascending.
        meta: The metadata JSON.
    """

    X: FloatArray
    Y: FloatArray
    K_rad: FloatArray
    objective: FloatArray
    feasible: NDArray[np.bool_]
    volume_m3: FloatArray
    energy_j: FloatArray
    T_s: FloatArray
    theta_p_rad: FloatArray
    margins: FloatArray
    train_idx: NDArray[np.int64]
    test_idx: NDArray[np.int64]
    meta: dict[str, Any]

    def __len__(self) -> int:
        return int(self.X.shape[0])

    @property
    def dig_type(self) -> DigType:
        """The dig type the teacher solved for."""
        return _dig_type(self.meta["dig_type"])

    @property
    def hash(self) -> str:
        """SHA-256 of the arrays (verified by :func:`load`)."""
        return str(self.meta["arrays_sha256"])

    @property
    def train_xy(self) -> tuple[FloatArray, FloatArray]:
        """Training inputs ``(n_train, 7)`` and outputs ``(n_train, 4)``."""
        return self.X[self.train_idx], self.Y[self.train_idx]

    @property
    def test_xy(self) -> tuple[FloatArray, FloatArray]:
        """Test inputs ``(n_test, 7)`` and outputs ``(n_test, 4)``."""
        return self.X[self.test_idx], self.Y[self.test_idx]


# --- hashes and files ------------------------------------------------------------------------


def arrays_sha256(arrays: Mapping[str, NDArray[Any]]) -> str:
    """SHA-256 of named arrays: per name in sorted order, its name, dtype, shape and bytes.

    Byte order is normalised to little-endian, so the hash names the data, not the file.
    """
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        if a.dtype.byteorder == ">":
            a = a.astype(a.dtype.newbyteorder("<"))
        h.update(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
        h.update(b"\0")
        h.update(a.tobytes())
    return h.hexdigest()


def rig_profile_sha256(rig: Rig) -> str:
    """SHA-256 of the rig profile's parsed TOML content as canonical JSON.

    Raises:
        ConfigurationError: The rig's source file cannot be read or parsed.
    """
    path = Path(rig.source_path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigurationError(
            f"rig {rig.name!r}: cannot hash its profile {str(path)!r} ({e}); a dataset needs a "
            "rig loaded from a profile file"
        ) from e
    return _sha256_json(raw)


def _sha256_json(data: Any) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _write_npz(path: Path, arrays: Mapping[str, NDArray[Any]]) -> None:
    # Atomic (tmp, fsync, rename, fsync dir): a reader or a resumed run sees the old file or the
    # whole new one, never a partial one; likewise _write_json.
    atomic_write(path, lambda f: np.savez(f, **arrays))  # type: ignore[arg-type]


def _write_json(path: Path, data: Mapping[str, Any]) -> None:
    text = json.dumps(data, indent=2, sort_keys=True) + "\n"

    def write(f: IO[bytes]) -> None:
        f.write(text.encode())

    atomic_write(path, write)


def _require_keys(what: str, data: Any, keys: set[str]) -> None:
    if not isinstance(data, Mapping):
        raise ConfigurationError(f"{what} must be an object with keys {sorted(keys)}")
    missing, unknown = keys - set(data), set(data) - keys
    if missing or unknown:
        raise ConfigurationError(
            f"{what}: missing keys {sorted(missing)}, unknown keys {sorted(unknown)}; "
            f"allowed: {sorted(keys)}"
        )


def _dig_type(value: DigType | str | int) -> DigType:
    if isinstance(value, str):
        try:
            return DigType[value.upper()]
        except KeyError:
            pass
    else:
        try:
            return DigType(value)
        except ValueError:
            pass
    raise ConfigurationError(
        f"dig type must be one of {[t.name.lower() for t in DigType]}; got {value!r}"
    )


def _flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


# --- the task a worker runs ------------------------------------------------------------------


def problem_inputs(problems: Sequence[Problem]) -> FloatArray:
    """The PINN inputs ``(n, 7)`` of problems: entry pose, exit pose (rad), surface H (m)."""
    return np.array(
        [[*p.q_start_rad, *p.q_end_rad, p.surface_y_m] for p in problems], dtype=np.float64
    ).reshape(len(problems), len(INPUT_NAMES))


def solution_arrays(solutions: Sequence[Solution]) -> Arrays:
    """The per-sample arrays of :data:`SAMPLE_ARRAYS` from teacher solutions."""
    a6 = np.array([s.a6 for s in solutions], dtype=np.float64).reshape(-1, 3)
    T = np.array([s.T_s for s in solutions], dtype=np.float64)
    return {
        "X": problem_inputs([s.problem for s in solutions]),
        "Y": np.concatenate([a6, T[:, None]], axis=1),
        "K_rad": oneshot.particle_from_a6(a6, T)[:, :3],
        "objective": np.array([s.objective for s in solutions], dtype=np.float64),
        "feasible": np.array([s.feasible for s in solutions], dtype=np.bool_),
        "volume_m3": np.array([s.volume_m3 for s in solutions], dtype=np.float64),
        "energy_j": np.array([s.energy_j for s in solutions], dtype=np.float64),
        "T_s": T,
        "theta_p_rad": np.array([s.theta_p_rad for s in solutions], dtype=np.float64),
        "margins": np.array(
            [[m for _, m in s.margins] for s in solutions], dtype=np.float64
        ).reshape(len(solutions), len(oneshot.CONSTRAINT_NAMES)),
    }


def _solve_chunk(rig: Rig, problems: list[Problem], seed: int, pso: dict[str, int]) -> Arrays:
    """One dask task: solve a chunk with the teacher in this worker process (``workers=1``)."""
    _undo_malloc_trim_threshold()
    t0 = time.perf_counter()
    arrays = solution_arrays(oneshot.solve_pso(rig, problems, seed=seed, workers=1, **pso))
    arrays["solve_s"] = np.array(time.perf_counter() - t0)
    arrays["worker"] = np.array(_worker_name())
    return arrays


# glibc's largest mmap threshold on 64-bit systems, and twice it for trimming (glibc's own rule
# when it adapts the threshold).
_MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
_TRIM_THRESHOLD_BYTES = 2 * _MMAP_THRESHOLD_BYTES


def _undo_malloc_trim_threshold() -> None:
    """Give this process static glibc malloc thresholds again where dask's nanny set them low.

    dask starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536`` to return memory to the OS.
    Setting it also turns off glibc's adaptive mmap threshold, so every numpy temporary above
    128 KiB is mmapped and unmapped, page faults included: the teacher then runs 2.2x slower
    (0.176 against 0.081 s per problem, measured on 30 problems in one process). Large fixed
    thresholds restore the speed on any cluster. Does nothing where that variable is unset or
    the C library is not glibc.
    """
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's mallopt parameter numbers
        libc.mallopt(m_mmap_threshold, _MMAP_THRESHOLD_BYTES)
        libc.mallopt(m_trim_threshold, _TRIM_THRESHOLD_BYTES)
    except (OSError, AttributeError):
        return


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def _worker_info() -> dict[str, str]:
    """Run on every worker before any task: versions and BLAS threads (recorded in metadata)."""
    import rt_runtime

    return {
        "rt_runtime": rt_runtime.__version__,
        "numpy": np.__version__,
        "python": sys.version.split()[0],
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", ""),
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", ""),
        "MALLOC_TRIM_THRESHOLD_": os.environ.get("MALLOC_TRIM_THRESHOLD_", ""),
    }


# --- generation ------------------------------------------------------------------------------


@dataclass(slots=True)
class _Job:
    """The client's bookkeeping for one dig type while its chunks are solved."""

    spec: DatasetSpec
    chunk_dir: Path
    identity: dict[str, Any]
    run_hash: str
    problems: list[Problem]
    bounds: list[tuple[int, int]]
    chunks: dict[int, Arrays]
    computed: set[int]
    t_start: float

    @property
    def todo(self) -> list[int]:
        return [i for i in range(len(self.bounds)) if i not in self.chunks]


def _chunk_path(chunk_dir: Path, index: int) -> Path:
    return chunk_dir / f"chunk_{index:05d}.npz"


def _read_chunk(job: _Job, index: int) -> Arrays | None:
    """A finished chunk from disk, or None when missing, unreadable, partial or another run's."""
    path = _chunk_path(job.chunk_dir, index)
    if not path.exists():
        return None
    start, stop = job.bounds[index]
    n = stop - start
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: np.array(z[k]) for k in z.files}
        if str(arrays["run_hash"]) != job.run_hash or int(arrays["chunk"]) != index:
            return None
        for name, tail in SAMPLE_ARRAYS.items():
            if arrays[name].shape != (n, *tail):
                return None
        if not np.array_equal(arrays["X"], problem_inputs(job.problems[start:stop])):
            return None
        float(arrays["solve_s"])
        str(arrays["worker"])
    except Exception:  # any unreadable chunk is simply solved again
        return None
    return arrays


def _prepare(rig: Rig, rig_sha: str, spec: DatasetSpec, out_dir: Path, force: bool) -> _Job:
    """Check the directory against the spec, draw the problems and find the finished chunks."""
    t_start = time.perf_counter()
    chunk_dir = out_dir / spec.type_name
    spec_path = chunk_dir / "spec.json"
    if force:
        for p in (
            *chunk_dir.glob("chunk_*.npz"),
            *chunk_dir.glob(".*.tmp"),
            spec_path,
            out_dir / f"{spec.type_name}.npz",
            out_dir / f"{spec.type_name}.json",
        ):
            p.unlink(missing_ok=True)
    identity = {**spec.compat_dict(), "rig_sha256": rig_sha, "package_version": __version__}
    if spec_path.exists():
        try:
            old = json.loads(spec_path.read_text(encoding="utf-8"))["identity"]
        except (OSError, ValueError, KeyError, TypeError):
            old = None  # unreadable: the chunks carry their run hash and are checked one by one
        if isinstance(old, Mapping) and old != identity:
            a, b = _flatten(old), _flatten(identity)
            keys = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
            diffs = "; ".join(
                f"{k}: {a.get(k, '(none)')!r} -> {b.get(k, '(none)')!r}" for k in keys
            )
            raise ConfigurationError(
                f"{chunk_dir} holds chunks of a different {spec.type_name} dataset ({diffs}); "
                "use another --out, or --force to discard them"
            )
    chunk_dir.mkdir(parents=True, exist_ok=True)
    for p in chunk_dir.glob(".*.tmp"):  # left by a killed run
        p.unlink(missing_ok=True)
    _write_json(spec_path, {"format": FORMAT, "identity": identity, "spec": spec.to_dict()})

    problems = oneshot.sample_problems(rig, spec.n_samples, spec.dig_type, spec.seed, spec.sampler)
    starts = range(0, spec.n_samples, spec.chunk_size)
    bounds = [(s, min(s + spec.chunk_size, spec.n_samples)) for s in starts]
    job = _Job(
        spec, chunk_dir, identity, _sha256_json(identity), problems, bounds, {}, set(), t_start
    )
    for i in range(len(bounds)):
        arrays = _read_chunk(job, i)
        if arrays is not None:
            job.chunks[i] = arrays
    return job


def _store_chunk(job: _Job, index: int, arrays: Arrays) -> None:
    """Check a worker's answer against the problems sent, then write the chunk file."""
    start, stop = job.bounds[index]
    if not np.array_equal(arrays["X"], problem_inputs(job.problems[start:stop])):
        raise CommunicationError(
            f"worker {arrays['worker']} answered chunk {index} of {job.spec.type_name} with "
            "other problems than were sent; are client and workers the same rt_runtime?"
        )
    arrays = {**arrays, "run_hash": np.array(job.run_hash), "chunk": np.array(index)}
    _write_npz(_chunk_path(job.chunk_dir, index), arrays)
    job.chunks[index] = arrays
    job.computed.add(index)


def _split(spec: DatasetSpec, feasible: NDArray[np.bool_]) -> tuple[NDArray[np.int64], ...]:
    """Seeded permutation of all samples; of its feasible members, the last n_test are test."""
    rng = np.random.default_rng(np.random.SeedSequence([spec.seed, _SPLIT_STREAM]))
    perm = rng.permutation(feasible.size)
    usable = perm[feasible[perm]]
    if usable.size <= spec.n_test:
        raise ConfigurationError(
            f"{spec.type_name}: only {usable.size} of {feasible.size} teacher solutions are "
            f"feasible, which leaves nothing to train on beside {spec.n_test} test samples; "
            "lower --test, raise --samples, or check the sampler ranges"
        )
    cut = usable.size - spec.n_test
    return (
        np.sort(usable[:cut]).astype(np.int64),
        np.sort(usable[cut:]).astype(np.int64),
    )


def _consolidate(job: _Job, rig: Rig, out_dir: Path, cluster: dict[str, Any]) -> DatasetInfo:
    """Concatenate the chunks, split, write ``<type>.npz`` and ``<type>.json``."""
    spec = job.spec
    order = range(len(job.bounds))
    arrays: Arrays = {
        name: np.concatenate([job.chunks[i][name] for i in order]) for name in SAMPLE_ARRAYS
    }
    feasible = arrays["feasible"]
    train_idx, test_idx = _split(spec, feasible)
    arrays["train_idx"] = train_idx
    arrays["test_idx"] = test_idx
    digest = arrays_sha256(arrays)
    npz_path = out_dir / f"{spec.type_name}.npz"
    meta_path = out_dir / f"{spec.type_name}.json"
    _write_npz(npz_path, arrays)

    chunks: list[dict[str, Any]] = [
        {
            "index": i,
            "start": job.bounds[i][0],
            "problems": job.bounds[i][1] - job.bounds[i][0],
            "solve_s": round(float(job.chunks[i]["solve_s"]), 4),
            "worker": str(job.chunks[i]["worker"]),
            "computed": i in job.computed,
        }
        for i in order
    ]
    X_ok = arrays["X"][feasible]
    n_feasible = int(np.count_nonzero(feasible))
    wall_s = time.perf_counter() - job.t_start
    meta: dict[str, Any] = {
        "format": FORMAT,
        "dig_type": spec.type_name,
        "rig": {"name": rig.name, "profile_sha256": job.identity["rig_sha256"]},
        "spec": spec.to_dict(),
        "spec_hash": spec.hash,
        "run_hash": job.run_hash,
        "seeds": {
            "problems": spec.seed,
            "pso": spec.seed,
            "split": [spec.seed, _SPLIT_STREAM],
            "how": "problems: sample_problems(rig, n, type, seed, sampler); pso: solve_pso(..., "
            "seed=seed) per chunk, each problem's stream seeded by seed and its data; split: "
            "default_rng(SeedSequence(split)).permutation(n)",
        },
        "sampler": spec.to_dict()["sampler"],
        "pso": {**spec.to_dict()["pso"], "teacher": "rt_runtime.planning.oneshot.solve_pso"},
        "counts": {
            "samples": spec.n_samples,
            "feasible": n_feasible,
            "infeasible": spec.n_samples - n_feasible,
            "train": int(train_idx.size),
            "test": int(test_idx.size),
        },
        "feasible_fraction": n_feasible / spec.n_samples,
        "inputs": list(INPUT_NAMES),
        "outputs": list(OUTPUT_NAMES),
        "constraints": list(oneshot.CONSTRAINT_NAMES),
        "input_domain": {
            n: [float(X_ok[:, j].min()), float(X_ok[:, j].max())] for j, n in enumerate(INPUT_NAMES)
        },
        "wall_s": round(wall_s, 3),
        "compute_s": round(sum(c["solve_s"] for c in chunks), 3),
        "chunks_total": len(chunks),
        "chunks_computed": len(job.computed),
        "chunks": chunks,
        "cluster": cluster,
        "package_version": __version__,
        "numpy_version": np.__version__,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "arrays": {k: {"dtype": v.dtype.str, "shape": list(v.shape)} for k, v in arrays.items()},
        "arrays_sha256": digest,
        "hash": digest,  # the dataset hash model cards quote; the same as arrays_sha256
    }
    _write_json(meta_path, meta)
    return DatasetInfo(
        dig_type=spec.dig_type,
        path=npz_path,
        meta_path=meta_path,
        samples=spec.n_samples,
        feasible=n_feasible,
        train=int(train_idx.size),
        test=int(test_idx.size),
        hash=digest,
        wall_s=time.perf_counter() - job.t_start,
        chunks_total=len(chunks),
        chunks_computed=len(job.computed),
    )


@contextlib.contextmanager
def preserved_environ() -> Iterator[None]:
    """Restore ``os.environ`` on exit.

    A LocalCluster's nannies write their workers' variables (``MALLOC_TRIM_THRESHOLD_``,
    ``PYTHONHASHSEED``, ...) into this process's environment before spawning them; without the
    restore, every process this one starts afterwards would inherit them.
    """
    before = dict(os.environ)
    try:
        yield
    finally:
        for k in set(os.environ) - set(before):
            del os.environ[k]
        for k, v in before.items():
            if os.environ.get(k) != v:
                os.environ[k] = v


@contextlib.contextmanager
def _exclusive(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (created): one run per dataset directory at a time."""
    import fcntl

    with open(path, "a+b") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigurationError(
                f"another run is writing this dataset ({path} is locked); wait for it to end "
                "or use another --out"
            ) from None
        yield


def _local_workers(workers: int | None) -> int:
    if workers is not None:
        if workers < 1:
            raise ConfigurationError(f"workers must be >= 1; got {workers}")
        return workers
    try:
        return len(os.sched_getaffinity(0))  # the cores this process may use, not the machine's
    except AttributeError:
        return os.cpu_count() or 1


def _import_dask() -> Any:
    try:
        import distributed
    except ImportError as e:
        raise ConfigurationError(
            "excavator-rt dataset needs dask.distributed: pip install 'excavator-rt[train]'"
        ) from e
    return distributed


def _solve_all(
    client: Client, rig: Rig, jobs: list[_Job], on_done: Callable[[_Job], None], progress: bool
) -> None:
    """Submit every missing chunk, store each as it completes, call ``on_done`` per job."""
    from distributed import KilledWorker, as_completed

    try:
        from tqdm import tqdm
    except ImportError as e:
        raise ConfigurationError(
            "the progress bar needs tqdm: pip install 'excavator-rt[train]'"
        ) from e

    owner: dict[str, tuple[_Job, int]] = {}
    futures = []
    for job in jobs:
        for i in job.todo:
            start, stop = job.bounds[i]
            key = f"pso-{job.spec.type_name}-{job.run_hash[:12]}-{i:05d}"
            fut = client.submit(
                _solve_chunk,
                rig,
                job.problems[start:stop],
                job.spec.seed,
                job.spec.pso_options,
                key=key,
                pure=False,
            )
            owner[key] = (job, i)
            futures.append(fut)
    total = sum(j.spec.n_samples for j in jobs)
    done = total - sum(j.bounds[i][1] - j.bounds[i][0] for j in jobs for i in j.todo)
    bar = tqdm(
        total=total,
        initial=done,
        unit="problem",
        desc="PSO teacher",
        disable=not (progress and sys.stderr.isatty()),
        smoothing=0.05,
    )
    try:
        for fut in as_completed(futures):  # type: ignore[no-untyped-call]
            job, i = owner[str(fut.key)]
            try:
                arrays = fut.result()
            except ExcavatorRtError:
                raise
            except (OSError, TimeoutError, KilledWorker) as e:
                raise CommunicationError(
                    f"{job.spec.type_name} chunk {i} failed on the dask cluster ({e!r}); "
                    "finished chunks are kept: rerun the same command to resume"
                ) from e
            _store_chunk(job, i, arrays)
            bar.update(job.bounds[i][1] - job.bounds[i][0])
            if not job.todo:
                on_done(job)
    finally:
        bar.close()
        for fut in futures:
            fut.cancel()  # type: ignore[no-untyped-call]


def generate_many(
    rig: Rig | str,
    specs: Sequence[DatasetSpec],
    out_dir: Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    force: bool = False,
) -> list[DatasetInfo]:
    """Generate several datasets (e.g. both dig types) as one pool of tasks on one cluster.

    Args:
        rig: The rig or its profile name; its name must match every spec's ``rig``.
        specs: One spec per dig type (no type twice).
        out_dir: Output directory (created).
        scheduler: Address of a running dask scheduler (``tcp://host:port``); None starts a
            LocalCluster of ``workers`` single-threaded processes on 127.0.0.1, no dashboard.
        workers: Local worker processes; None uses every core this process may run on. Not
            allowed with ``scheduler`` (the cluster has its own workers).
        progress: Show a tqdm bar over problems (only when stderr is a terminal).
        force: Discard any earlier chunks and files of these types in ``out_dir`` first.

    Returns:
        One :class:`DatasetInfo` per spec, in the order given.

    Raises:
        ConfigurationError: Invalid arguments, a rig/spec mismatch, earlier chunks of another
            spec in ``out_dir`` (naming the differing keys), too few feasible samples, or a
            missing ``train`` extra.
        CommunicationError: The scheduler cannot be reached, has no workers, or lost a task.
        PlanningError: The sampler cannot draw enough reachable problems.
    """
    rig_obj = load_rig(rig) if isinstance(rig, str) else rig
    kinds = [s.dig_type for s in specs]
    if len(set(kinds)) != len(kinds):
        raise ConfigurationError(f"one spec per dig type; got {[s.type_name for s in specs]}")
    for s in specs:
        if s.rig != rig_obj.name:
            raise ConfigurationError(
                f"the {s.type_name} spec is for rig {s.rig!r} but the rig given is {rig_obj.name!r}"
            )
    if scheduler is not None and workers is not None:
        raise ConfigurationError(
            "workers applies to the local cluster only; a scheduler brings its own workers"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig_sha = rig_profile_sha256(rig_obj)
    with contextlib.ExitStack() as stack:
        for s in specs:
            stack.enter_context(_exclusive(out / f".{s.type_name}.lock"))
        jobs = [_prepare(rig_obj, rig_sha, s, out, force) for s in specs]
        return _generate(rig_obj, jobs, out, scheduler, workers, progress)


def _generate(
    rig_obj: Rig,
    jobs: list[_Job],
    out: Path,
    scheduler: str | None,
    workers: int | None,
    progress: bool,
) -> list[DatasetInfo]:
    """Solve the missing chunks of prepared jobs and consolidate each one."""
    infos: dict[DigType, DatasetInfo] = {}
    cluster: dict[str, Any] = {"scheduler": None, "workers": {}}

    def done(job: _Job) -> None:
        infos[job.spec.dig_type] = _consolidate(job, rig_obj, out, cluster)

    n_todo = sum(len(j.todo) for j in jobs)
    if n_todo:
        distributed = _import_dask()
        if scheduler is None:
            n_workers = min(_local_workers(workers), n_todo)
            with (
                preserved_environ(),
                distributed.LocalCluster(
                    n_workers=n_workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                    # The scheduler's HTTP server (health and metrics; no dashboard) takes a
                    # free port on 127.0.0.1 instead of 8787, which another cluster may hold.
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                ) as local,
                distributed.Client(local) as client,
            ):
                cluster["scheduler"] = f"LocalCluster ({n_workers} processes)"
                _run_on(client, rig_obj, jobs, done, progress, cluster)
        else:
            try:
                client_cm = distributed.Client(scheduler, timeout="15s")
            except (OSError, TimeoutError, ValueError) as e:
                raise CommunicationError(
                    f"cannot reach the dask scheduler at {scheduler!r}: {e}"
                ) from e
            with client_cm as client:
                cluster["scheduler"] = scheduler
                _run_on(client, rig_obj, jobs, done, progress, cluster)
    for job in jobs:
        if job.spec.dig_type not in infos:
            done(job)
    return [infos[job.spec.dig_type] for job in jobs]


def _run_on(
    client: Client,
    rig: Rig,
    jobs: list[_Job],
    done: Callable[[_Job], None],
    progress: bool,
    cluster: dict[str, Any],
) -> None:
    try:
        client.wait_for_workers(1, timeout=60)
    except TimeoutError as e:
        raise CommunicationError(
            f"the dask scheduler at {cluster['scheduler']} has no workers after 60 s"
        ) from e
    try:
        info = client.run(_worker_info)
    except Exception as e:  # the import of rt_runtime on a worker failed
        raise ConfigurationError(
            f"a dask worker cannot run the teacher ({e!r}); install the same excavator-rt there"
        ) from e
    cluster["workers"] = info
    wrong = {w: i["rt_runtime"] for w, i in info.items() if i["rt_runtime"] != __version__}
    if wrong:
        raise ConfigurationError(
            f"dask workers run another rt_runtime than this client ({__version__}): {wrong}"
        )
    _solve_all(client, rig, jobs, done, progress)


def generate(
    rig: Rig | str,
    spec: DatasetSpec,
    out_dir: Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    force: bool = False,
) -> DatasetInfo:
    """Generate (or resume, or re-consolidate) one dataset; see :func:`generate_many`."""
    return generate_many(
        rig, [spec], out_dir, scheduler=scheduler, workers=workers, progress=progress, force=force
    )[0]


# --- loading ---------------------------------------------------------------------------------


def load(path: Path | str) -> Dataset:
    """Load a consolidated dataset and verify it against its metadata.

    Args:
        path: ``<out>/<type>.npz`` or ``<out>/<type>.json`` (the other is found beside it).

    Returns:
        The :class:`Dataset`, arrays read-only.

    Raises:
        ConfigurationError: A missing or unreadable file, missing or mis-shaped arrays, a split
            that is not made of distinct feasible samples, or arrays whose SHA-256 differs from
            the metadata's (the file was modified or belongs to other metadata).
    """
    p = Path(path)
    npz_path, meta_path = p.with_suffix(".npz"), p.with_suffix(".json")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        with np.load(npz_path, allow_pickle=False) as z:
            arrays = {k: np.array(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError) as e:
        raise ConfigurationError(f"cannot read dataset {npz_path} / {meta_path}: {e}") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ConfigurationError(f"{meta_path} is not {FORMAT} metadata")
    expected = {*SAMPLE_ARRAYS, "train_idx", "test_idx"}
    if set(arrays) != expected:
        raise ConfigurationError(
            f"{npz_path}: arrays {sorted(arrays)}; a dataset has exactly {sorted(expected)}"
        )
    digest = arrays_sha256(arrays)
    if digest != meta.get("arrays_sha256") or digest != meta.get("hash"):
        raise ConfigurationError(
            f"{npz_path}: arrays hash {digest} differs from {meta.get('arrays_sha256')} in "
            f"{meta_path}; the data was modified after it was written, regenerate it"
        )
    n = arrays["X"].shape[0]
    for name, tail in SAMPLE_ARRAYS.items():
        if arrays[name].shape != (n, *tail):
            raise ConfigurationError(
                f"{npz_path}: {name} has shape {arrays[name].shape}; expected {(n, *tail)}"
            )
    train, test = arrays["train_idx"], arrays["test_idx"]
    both = np.concatenate([train, test])
    in_range = both.size == 0 or (both.min() >= 0 and both.max() < n)
    if not in_range or not np.all(arrays["feasible"][both]) or np.unique(both).size != both.size:
        raise ConfigurationError(
            f"{npz_path}: train/test indices must be distinct feasible samples in [0, {n})"
        )
    for a in arrays.values():
        a.flags.writeable = False
    return Dataset(meta=meta, **arrays)


# --- command line ----------------------------------------------------------------------------


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``dataset`` to the ``excavator-rt`` subcommands; its handler is :func:`run`."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "dataset",
        help="PSO teacher dataset for the PINN (seeded, resumable, dask-distributed)",
        description="Solve sampled one-shot problems with the PSO teacher, in chunks on disk "
        "(a rerun resumes), on every local core or on a dask cluster (--scheduler).",
    )
    p.add_argument("--rig", default=DEFAULT_RIG)
    p.add_argument("--type", choices=("downward", "backward", "both"), default="both")
    p.add_argument("--samples", type=int, default=1800, help="problems per type (default 1800)")
    p.add_argument("--test", type=int, default=200, help="feasible test samples per type")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk", type=int, default=50, help="problems per task and chunk file")
    p.add_argument("--out", type=Path, default=Path("data/pinn"), help="output directory")
    p.add_argument("--scheduler", metavar="ADDRESS", help="dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--workers", type=int, help="local worker processes (default: every core)")
    p.add_argument("--force", action="store_true", help="discard earlier chunks of these types")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=run)
    return p


def run(args: argparse.Namespace) -> int:
    """``excavator-rt dataset``: generate, print a summary (or one JSON object); exit code."""
    types = ("downward", "backward") if args.type == "both" else (args.type,)
    rig = load_rig(args.rig)
    specs = [
        DatasetSpec.default(
            t,
            rig=rig.name,
            n_samples=args.samples,
            n_test=args.test,
            seed=args.seed,
            chunk_size=args.chunk,
        )
        for t in types
    ]
    t0 = time.perf_counter()
    infos = generate_many(
        rig,
        specs,
        args.out,
        scheduler=args.scheduler,
        workers=args.workers,
        progress=True,
        force=args.force,
    )
    wall_s = time.perf_counter() - t0
    if args.json:
        out = {
            "rig": rig.name,
            "out": str(args.out),
            "wall_s": round(wall_s, 3),
            "types": {
                i.dig_type.name.lower(): {
                    "samples": i.samples,
                    "feasible": i.feasible,
                    "train": i.train,
                    "test": i.test,
                    "path": str(i.path),
                    "meta": str(i.meta_path),
                    "hash": i.hash,
                    "wall_s": round(i.wall_s, 3),
                    "chunks": i.chunks_total,
                    "chunks_computed": i.chunks_computed,
                }
                for i in infos
            },
        }
        print(json.dumps(out, indent=2))
        return 0
    for i in infos:
        print(
            f"{i.dig_type.name.lower()}: {i.samples} samples, {i.feasible} feasible "
            f"({i.feasible / i.samples:.1%}), train {i.train} / test {i.test}; "
            f"{i.chunks_computed} of {i.chunks_total} chunks solved in {i.wall_s:.1f} s "
            f"-> {i.path} (sha256 {i.hash[:16]})"
        )
    print(f"total {wall_s:.1f} s")
    return 0
