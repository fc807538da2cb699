"""Fast verification of one-shot dig candidates against every hard limit of Yao eq 12.

:class:`Verifier` computes, per candidate ``(q_start, q_end, H, dig type, a6, T)``, exactly what
:func:`rt_runtime.planning.oneshot.evaluate` computes (the 22 normalised constraint values of
:data:`~rt_runtime.planning.oneshot.CONSTRAINT_NAMES`, their total violation, the eq 11
objective, V_p, W_E, theta_p, peak power and torques) on the same sample grid, but for one or a
few candidates at a time at microsecond cost: the PINN planner verifies each dig it proposes
before anything is sent.

Two backends evaluate:

- ``"c"``: :mod:`rt_runtime.planning._verify`, a C loop over the samples
  (``rt_runtime/planning/kernel/``), compiled by ``pip install -e .`` (``setup.py``). A few
  microseconds per candidate at 101 samples (design notes, V1-V4); it allocates nothing, so
  :meth:`Verifier.evaluate_into` may run in the planning step of a cycle.
- ``"numpy"``: :func:`~rt_runtime.planning.oneshot.evaluate` itself, the independent
  reference (0.6-0.8 ms for one candidate).

They agree to ~1e-12 relative (the numpy matrix products round differently; ``tests/
test_verify.py`` holds them to 1e-9). Retiming and planning (below) are searches that exist in
the C kernel only (design notes, "A C compiler is required"); the tests check their answers by
their properties against the numpy evaluation.

:meth:`Verifier.retime_into` retimes candidates instead: it keeps each one's path (the shape
term ``K = -a6 T^6``) and finds the shortest T' in the time range at which every time-dependent
constraint (:data:`TIME_DEPENDENT`) holds, then evaluates it for real. The PINN's paths are
good but its T conservative, and eq 11 is dominated by T. The C kernel does it in about twice
the cost of one evaluation.

:meth:`Verifier.plan_into` goes one step further: it keeps each candidate's path *direction*
and scales its bulge, ``K -> c K``, to the largest excavated volume that the path-only
constraints allow (Yao's objective rewards V_p up to the hard cap V_max, which a network must
aim below to stay feasible), then retimes that path; when the larger bulge cannot be timed
feasibly (torque), it backs off towards a smaller one, and as a last resort reports the
candidate's own path (retimed, unless a path-only limit fails, which no timing fixes). The C
kernel does it in about 1.6x the cost of a retiming on most rows, more where it backs off.

Input rows are ``[q_start (3) rad, q_end (3) rad, H m, dig_type (0 downward, 1 backward),
a6 (3) rad/s^6, T s]`` (columns ``IN_*``); output rows are laid out by the ``COL_*`` constants.
A row that :func:`~rt_runtime.planning.oneshot.evaluate` would refuse (a non-finite value,
``T <= 0``, a dig type other than 0 or 1) is not an error on the fast path: its total violation
is ``+inf`` and every other output is NaN, so it can never be chosen or pass as feasible.
Absurd but finite values whose arithmetic overflows get total violation ``+inf`` too (both
backends: wherever any output of the row is not finite), never a NaN that a comparison would
let through.
"""

from __future__ import annotations

import importlib
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from rt_runtime import dynamics, kinematics, soil
from rt_runtime.errors import ConfigurationError, PlanningError
from rt_runtime.planning import oneshot
from rt_runtime.planning.oneshot import CONSTRAINT_NAMES, DEFAULT_SAMPLES, DigType
from rt_runtime.rig import Rig
from rt_runtime.trajectory import sextic

FloatArray = NDArray[np.float64]

# Input columns.
IN_Q_START: Final = 0
"""First of three columns: entry pose theta1..theta3, rad."""
IN_Q_END: Final = 3
"""First of three columns: exit pose, rad."""
IN_SURFACE_Y: Final = 6
"""Material surface height H, m (arm frame)."""
IN_DIG_TYPE: Final = 7
""":class:`DigType` as a float: 0.0 downward, 1.0 backward."""
IN_A6: Final = 8
"""First of three columns: sixth-order coefficients a6, rad/s^6."""
IN_T: Final = 11
"""Digging time T, s."""
N_IN: Final = 12

# Output columns.
N_CONSTRAINTS: Final = len(CONSTRAINT_NAMES)
COL_VIOLATIONS: Final = 0
"""First of N_CONSTRAINTS columns: the normalised constraints, <= 0 satisfied."""
COL_TOTAL: Final = 22
"""Sum of the positive parts of the violations; +inf for a rejected row."""
COL_OBJECTIVE: Final = 23
"""Yao eq 11."""
COL_T_S: Final = 24
COL_VOLUME_M3: Final = 25
COL_ENERGY_J: Final = 26
COL_THETA_P_RAD: Final = 27
COL_PEAK_POWER_W: Final = 28
COL_PEAK_TORQUE_NM: Final = 29
"""First of three columns: peak |torque| of boom, stick, bucket, N*m."""
N_OUT: Final = 32

# Retimed columns (:meth:`Verifier.retime_into`).
RT_A6: Final = 0
"""First of three columns: the retimed a6' = -K / T'^6, rad/s^6."""
RT_T_S: Final = 3
"""The retimed T', s."""
N_RETIMED: Final = 4

TIME_DEPENDENT: tuple[int, ...] = (*range(6, 16), 20, 21)
"""Constraints (indices into :data:`CONSTRAINT_NAMES`) that change when a path is retimed:
velocity, acceleration, torque, power, time_min and time_max. Angles, theta_p and volume
depend on the path only."""

RETIME_RTOL: Final = 1e-6
"""Retiming returns a T' within this relative distance above the feasible boundary it finds
(about 1e-7 measured, see :meth:`Verifier.retime_into`)."""

PLAN_C_RANGE: Final = (0.5, 2.0)
"""Default range of the path scale c of :meth:`Verifier.plan_into`."""

PLAN_TOL: Final = 1e-4
"""Where a path constraint caps the path scale (volume_max mostly), :meth:`Verifier.plan_into`
lands within this of it on the feasible side, in normalised units (for volume_max: V_p within
1e-4 of the V range below V_max)."""

PLAN_MARGIN: Final = 1e-9
"""Path constraints are judged with this much to spare while searching the scale (normalised
units), so that the real evaluation of the answer holds them."""

BACKENDS: tuple[str, ...] = ("auto", "c", "numpy")

BUILD_HINT = (
    "build it with `.venv/bin/pip install -e .` from the repository root (setup.py compiles "
    "rt_runtime/planning/kernel/*.c with the machine's C compiler; it needs gcc or cc and the "
    "Python headers)"
)

# Layout of the kernel's constants; kernel.h's enum vk_param must list the same offsets.
_ABI = 8
_PARAM_FIELDS: tuple[tuple[str, int], ...] = (
    ("lengths", 3),
    ("chain_h", 3),
    ("chain_b", 3),
    ("chain_d", 3),
    ("gravity", 1),
    ("k0_b", 1),
    ("mu", 1),
    ("speed_reg", 1),
    ("q_min", 3),
    ("q_max", 3),
    ("q_span", 3),
    ("qd_max", 3),
    ("qdd_max", 3),
    ("tau_max", 3),
    ("power_max", 1),
    ("theta_p_down", 2),
    ("theta_p_back", 2),
    ("volume", 2),
    ("time", 2),
    ("energy", 2),
    ("weights", 3),
    ("width", 1),
)
N_PARAMS: Final = sum(n for _, n in _PARAM_FIELDS)


_PlanFn = Callable[
    [FloatArray, FloatArray, FloatArray, float, float, FloatArray | None, FloatArray | None], None
]


def _load_extension(avx2: bool = True) -> ModuleType | None:
    """The compiled kernel module, or None when it is not built (or built for another ABI).

    Where the CPU has AVX2 (the baseline module's ``CPU_AVX2``, asked before the other is
    imported: its code would not run elsewhere) and ``avx2``, the AVX2 build of the same
    source (``_verify_avx2``, bit for bit the same results, plan ~23 % faster); else, or when
    that one is missing or stale, the baseline build.
    """
    module = _import_kernel("rt_runtime.planning._verify")
    if module is None or not avx2 or not getattr(module, "CPU_AVX2", 0):
        return module
    return _import_kernel("rt_runtime.planning._verify_avx2") or module


def _import_kernel(name: str) -> ModuleType | None:
    """Kernel module ``name`` when it is built for this ABI, else None."""
    try:
        module = importlib.import_module(name)
    except ImportError:
        return None
    layout = (module.ABI, module.N_PARAMS, module.N_IN, module.N_OUT)
    if layout != (_ABI, N_PARAMS, N_IN, N_OUT):
        return None
    return module


def pack_params(rig: Rig) -> FloatArray:
    """Every rig constant the kernel needs, ``(N_PARAMS,)`` in ``kernel/kernel.h``'s layout.

    Raises:
        ConfigurationError: The rig has no ``[planning]`` table, or ``dynamics._Chain`` no
            longer provides the mass constants the kernel's closed form needs.
    """
    planning = oneshot.require_planning(rig)
    chain = _chain_constants(rig)
    values: dict[str, ArrayLike] = {
        "lengths": rig.lengths_m,
        "chain_h": chain["h"],
        "chain_b": chain["b"],
        "chain_d": chain["d"],
        "gravity": chain["g"],
        # Grouped as soil.yao_resistance groups it: (K0 b) h.
        "k0_b": rig.soil.yao.k0_n_m2 * rig.bucket.width_m,
        "mu": rig.soil.yao.mu,
        "speed_reg": soil.DEFAULT_SPEED_REG_M_S,
        "q_min": rig.q_min_rad,
        "q_max": rig.q_max_rad,
        "q_span": rig.q_max_rad - rig.q_min_rad,
        "qd_max": rig.qd_max_rad_s,
        "qdd_max": rig.qdd_max_rad_s2,
        "tau_max": rig.tau_max_nm,
        "power_max": planning.power_max_w,
        "theta_p_down": planning.theta_p_downward_rad,
        "theta_p_back": planning.theta_p_backward_rad,
        "volume": (planning.volume_min_m3, planning.volume_max_m3),
        "time": (planning.t_min_s, planning.t_max_s),
        "energy": (planning.energy_min_j, planning.energy_max_j),
        "weights": planning.weights,
        "width": rig.bucket.width_m,
    }
    parts = [np.asarray(values[name], dtype=np.float64).reshape(n) for name, n in _PARAM_FIELDS]
    return np.ascontiguousarray(np.concatenate(parts))


def _chain_constants(rig: Rig) -> dict[str, FloatArray]:
    """The mass constants ``h, b, d`` (3,) and ``g`` () of :class:`rt_runtime.dynamics._Chain`.

    The dynamics' own constants, so that the kernel and the numpy reference cannot drift apart;
    ``_Chain`` is private to :mod:`rt_runtime.dynamics`, so its fields are checked here (and
    :class:`Verifier` checks the whole kernel against :func:`oneshot.evaluate` once at
    construction, which catches a change of their meaning).

    Raises:
        ConfigurationError: ``_Chain`` is gone or its fields are missing, misshaped or not finite.
    """
    shapes = {"h": (3,), "b": (3,), "d": (3,), "g": ()}
    try:
        chain = dynamics._Chain(rig)
        values = {name: np.asarray(getattr(chain, name), dtype=np.float64) for name in shapes}
    except (AttributeError, TypeError, ValueError) as exc:
        raise ConfigurationError(
            "the verifier kernel reads the mass constants h, b, d (3 floats each) and g of "
            f"rt_runtime.dynamics._Chain, which failed: {exc!r}; update verify.pack_params and "
            "kernel/retime.c to the new dynamics"
        ) from exc
    for name, shape in shapes.items():
        v = values[name]
        if v.shape != shape or not np.all(np.isfinite(v)):
            raise ConfigurationError(
                f"rt_runtime.dynamics._Chain.{name} must be finite with shape {shape} for the "
                f"verifier kernel; got {v.tolist()!r}; update verify.pack_params and "
                "kernel/retime.c"
            )
    return values


def pack_inputs(
    q_start_rad: ArrayLike,
    q_end_rad: ArrayLike,
    surface_y_m: ArrayLike,
    dig_type: ArrayLike,
    a6: ArrayLike,
    T_s: ArrayLike,
) -> FloatArray:
    """Input rows ``(N, N_IN)`` from candidates broadcast over a leading axis.

    Args:
        q_start_rad: Entry poses ``(N, 3)`` or ``(3,)``.
        q_end_rad: Exit poses ``(N, 3)`` or ``(3,)``.
        surface_y_m: H ``(N,)`` or scalar.
        dig_type: :class:`DigType` ``(N,)`` or scalar.
        a6: ``(N, 3)`` or ``(3,)`` rad/s^6.
        T_s: ``(N,)`` or scalar.

    Returns:
        A new C-contiguous float64 array; no value is checked (the verifier rejects bad rows).

    Raises:
        ValueError: The arguments do not broadcast to a common N.
    """
    qs = np.asarray(q_start_rad, dtype=np.float64)
    qe = np.asarray(q_end_rad, dtype=np.float64)
    c6 = np.asarray(a6, dtype=np.float64)
    h = np.asarray(surface_y_m, dtype=np.float64)
    kind = np.asarray(dig_type, dtype=np.float64)
    T = np.asarray(T_s, dtype=np.float64)
    for name, v in (("q_start_rad", qs), ("q_end_rad", qe), ("a6", c6)):
        if v.ndim not in (1, 2) or v.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (N, 3) or (3,); got {v.shape}")
    for name, v in (("surface_y_m", h), ("dig_type", kind), ("T_s", T)):
        if v.ndim > 1:
            raise ValueError(f"{name} must have shape (N,) or be a scalar; got {v.shape}")
    try:
        n = np.broadcast_shapes(qs.shape[:-1], qe.shape[:-1], c6.shape[:-1], h.shape,
                                kind.shape, T.shape)
    except ValueError:
        raise ValueError(
            "inputs do not broadcast to one N: q_start_rad (N, 3), q_end_rad (N, 3), "
            f"surface_y_m (N,), dig_type (N,), a6 (N, 3), T_s (N,) got {qs.shape}, {qe.shape}, "
            f"{h.shape}, {kind.shape}, {c6.shape}, {T.shape}"
        ) from None
    rows = n[0] if n else 1
    out = np.empty((rows, N_IN), dtype=np.float64)
    out[:, IN_Q_START : IN_Q_START + 3] = qs
    out[:, IN_Q_END : IN_Q_END + 3] = qe
    out[:, IN_SURFACE_Y] = h
    out[:, IN_DIG_TYPE] = kind
    out[:, IN_A6 : IN_A6 + 3] = c6
    out[:, IN_T] = T
    return out


def _readonly(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, slots=True, eq=False)
class VerifyResult:
    """The verdict on one candidate (equality is identity: the fields are arrays).

    Attributes:
        violations: Normalised constraint values ``(22,)`` in :data:`CONSTRAINT_NAMES` order,
            <= 0 satisfied; read-only.
        total_violation: Sum of their positive parts (+inf for a rejected candidate).
        objective: Yao eq 11.
        T_s: Digging time.
        volume_m3: Excavated volume V_p.
        energy_j: Energy W_E.
        theta_p_rad: Initial digging angle.
        peak_power_w: Largest total positive power.
        peak_torque_nm: Largest |torque| per joint ``(3,)``; read-only.
    """

    violations: FloatArray
    total_violation: float
    objective: float
    T_s: float
    volume_m3: float
    energy_j: float
    theta_p_rad: float
    peak_power_w: float
    peak_torque_nm: FloatArray

    @property
    def feasible(self) -> bool:
        """Whether every constraint holds."""
        return self.total_violation <= 0.0

    @classmethod
    def from_row(cls, row: ArrayLike) -> VerifyResult:
        """The result held in one output row ``(N_OUT,)`` of :meth:`Verifier.evaluate_into`.

        Raises:
            ValueError: ``row`` is not shaped ``(N_OUT,)``.
        """
        r = np.array(row, dtype=np.float64)
        if r.shape != (N_OUT,):
            raise ValueError(f"row must have shape ({N_OUT},); got {r.shape}")
        return cls(
            violations=_readonly(r[COL_VIOLATIONS : COL_VIOLATIONS + N_CONSTRAINTS].copy()),
            total_violation=float(r[COL_TOTAL]),
            objective=float(r[COL_OBJECTIVE]),
            T_s=float(r[COL_T_S]),
            volume_m3=float(r[COL_VOLUME_M3]),
            energy_j=float(r[COL_ENERGY_J]),
            theta_p_rad=float(r[COL_THETA_P_RAD]),
            peak_power_w=float(r[COL_PEAK_POWER_W]),
            peak_torque_nm=_readonly(r[COL_PEAK_TORQUE_NM : COL_PEAK_TORQUE_NM + 3].copy()),
        )

    def worst(self) -> tuple[str, float]:
        """The most violated constraint (the least slack one if all hold) and its value.

        Returns:
            ``(name from CONSTRAINT_NAMES, normalised value)``; a NaN value ranks first.
        """
        v = self.violations
        i = int(np.argmax(np.where(np.isnan(v), np.inf, v)))
        return CONSTRAINT_NAMES[i], float(v[i])


class Verifier:
    """Evaluates one-shot candidates for one rig and sample grid (see the module docstring).

    Construction packs the rig's constants once, loads the backend and, for the C kernel,
    checks one probe candidate against :func:`~rt_runtime.planning.oneshot.evaluate` (about
    1 ms), so that a kernel that no longer matches the Python physics is never used. The
    instance holds no per-call state, so one verifier may serve several threads (the C kernel
    keeps its evaluation scratch on the stack and its retiming and planning scratch in the
    kernel object, and holds the GIL while it runs).

    Args:
        rig: The rig; needs a ``[planning]`` table.
        n_samples: Samples per trajectory (uniform in time, ends included), >= 2: the grid of
            :func:`~rt_runtime.planning.oneshot.evaluate`.
        backend: ``"c"``, ``"numpy"`` or ``"auto"`` (C when built and consistent, else numpy
            with a :class:`RuntimeWarning` when the kernel is built but unusable). The numpy
            backend evaluates only: its :meth:`retime_into` and :meth:`plan_into` raise
            :class:`~rt_runtime.errors.ConfigurationError` (the searches are the kernel's).

    Attributes:
        rig: The rig.
        backend: The backend in use, ``"c"`` or ``"numpy"``.
        n_samples: The grid size.

    Raises:
        ConfigurationError: The rig has no planning table, ``n_samples`` < 2, an unknown
            backend, or ``backend="c"`` without a usable compiled kernel (missing or stale: the
            message says how to build it; or disagreeing with the Python physics: the message
            names the output).
    """

    __slots__ = (
        "_plan",
        "_retime",
        "_run",
        "backend",
        "kernel",
        "module",
        "n_samples",
        "rig",
    )

    def __init__(self, rig: Rig, n_samples: int = DEFAULT_SAMPLES, backend: str = "auto") -> None:
        if backend not in BACKENDS:
            raise ConfigurationError(
                f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}"
            )
        if isinstance(n_samples, bool) or not isinstance(n_samples, int | np.integer):
            raise ConfigurationError(f"n_samples must be an int >= 2; got {n_samples!r}")
        if n_samples < 2:
            raise ConfigurationError(f"n_samples must be >= 2; got {n_samples}")
        oneshot.require_planning(rig)
        self.rig = rig
        self.n_samples = int(n_samples)
        module = _load_extension() if backend != "numpy" else None
        if backend == "c" and module is None:
            raise ConfigurationError(
                "backend 'c' needs the compiled kernel rt_runtime.planning._verify, which is "
                f"missing or stale; {BUILD_HINT}"
            )
        self._run: Callable[[FloatArray, FloatArray, FloatArray | None], None]
        self._retime: Callable[[FloatArray, FloatArray, FloatArray, FloatArray | None], None]
        self._run = self._evaluate_numpy
        self._retime = self._retime_needs_c
        self._plan: _PlanFn = self._plan_needs_c
        self.backend = "numpy"
        #: The C kernel object (None with numpy): its ``front`` binds a planner's buffers.
        self.kernel: Any = None
        #: The C kernel's module (None with numpy): the trench planner's geometry functions.
        self.module: ModuleType | None = None
        if module is not None:
            try:
                kernel = module.Kernel(pack_params(rig), self.n_samples)
                self._self_check(kernel.run)
            except ConfigurationError as exc:
                if backend == "c":
                    raise ConfigurationError(f"backend 'c' is unusable: {exc}") from exc
                warnings.warn(
                    f"falling back to the numpy verifier (~100x slower): {exc}",
                    RuntimeWarning,
                    stacklevel=2,
                )
            else:
                self._run = kernel.run
                self._retime = kernel.retime
                self._plan = kernel.plan
                self.kernel = kernel
                self.module = module
                self.backend = "c"

    @property
    def build(self) -> str | None:
        """Which build of the C kernel runs ("avx2" or "baseline"; None with numpy)."""
        if self.module is None:
            return None
        return "avx2" if self.module.__name__.endswith("_avx2") else "baseline"

    def _self_check(
        self, run: Callable[[FloatArray, FloatArray, FloatArray | None], None]
    ) -> None:
        """Compare ``run`` with the numpy reference on one probe candidate.

        The probe starts 5 cm below the surface with a bulged path in mid-range, so that
        kinematics, every dynamics term and the soil force all enter its outputs.

        Raises:
            ConfigurationError: An output differs by more than 1e-9 relative (naming it).
        """
        rig = self.rig
        planning = oneshot.require_planning(rig)
        span = rig.q_max_rad - rig.q_min_rad
        q_start = rig.q_min_rad + 0.45 * span
        tip_y = float(kinematics.forward(rig, q_start)[1])
        T = 0.5 * (planning.t_min_s + planning.t_max_s)
        a6, _ = oneshot.a6_from_particle(np.array([*(0.1 * span), T]))
        x = pack_inputs(q_start, rig.q_min_rad + 0.6 * span, tip_y + 0.05, 0, a6, T)
        got = np.empty((1, N_OUT))
        want = np.empty((1, N_OUT))
        run(x, got, None)
        self._evaluate_numpy(x, want)
        err = np.abs(got - want) <= 1e-12 + 1e-9 * np.abs(want)
        if not np.all(err):
            j = int(np.argmin(err[0]))
            raise ConfigurationError(
                f"the compiled kernel disagrees with rt_runtime.planning.oneshot.evaluate on a "
                f"probe candidate: output column {j} is {got[0, j]!r}, the reference "
                f"{want[0, j]!r}; rebuild it ({BUILD_HINT}) or bring rt_runtime/planning/kernel/ "
                "up to date with the Python physics"
            )

    def evaluate_into(
        self, inputs: FloatArray, out: FloatArray, path: FloatArray | None = None
    ) -> None:
        """Evaluate N candidates into preallocated arrays (the fast path).

        Args:
            inputs: ``(N, N_IN)`` C-contiguous float64 rows (columns ``IN_*``).
            out: ``(N, N_OUT)`` C-contiguous writable float64, overwritten (columns ``COL_*``).
            path: ``(N, n_samples, 2)`` C-contiguous writable float64 for the tip's x, y (m, arm
                frame) at the samples, or None.

        Raises:
            ValueError: Wrong shapes, dtypes or memory layout (nothing is written). Bad values
                are not errors: such rows get total violation +inf (module docstring).

        With the C backend this allocates nothing and costs ~0.2 us plus ~7 us per candidate
        at 101 samples; safe in the loop's planning step.
        """
        self._run(inputs, out, path)

    def check(
        self,
        q_start_rad: ArrayLike,
        q_end_rad: ArrayLike,
        surface_y_m: float,
        dig_type: DigType | int,
        a6: ArrayLike,
        T_s: float,
    ) -> VerifyResult:
        """Verify one candidate (convenience; allocates).

        Args:
            q_start_rad: Entry pose ``(3,)``.
            q_end_rad: Exit pose ``(3,)``.
            surface_y_m: Material surface height H, m.
            dig_type: Downward or backward.
            a6: Sixth-order coefficients ``(3,)``, rad/s^6.
            T_s: Digging time, s.

        Returns:
            The :class:`VerifyResult`.

        Raises:
            PlanningError: A non-finite input, ``T_s <= 0`` or an unknown dig type, naming it.
            ValueError: A pose or ``a6`` not shaped ``(3,)``.
        """
        inputs = _one_row(q_start_rad, q_end_rad, surface_y_m, dig_type, a6, T_s)
        out = np.empty((1, N_OUT), dtype=np.float64)
        self.evaluate_into(inputs, out)
        return VerifyResult.from_row(out[0])

    def retime_into(
        self,
        inputs: FloatArray,
        out: FloatArray,
        retimed: FloatArray,
        path: FloatArray | None = None,
    ) -> None:
        """Retime N candidates along their paths to the shortest feasible T' (the fast path).

        Each row's path is kept (its shape term ``K = -a6 T^6`` per joint, so that the joint
        angles, theta_p and V_p, which depend on the path only, do not change) and T' is the
        smallest value in ``[t_min, t_max]`` at which every time-dependent constraint
        (:data:`TIME_DEPENDENT`: velocity, acceleration, torque, power and the time range
        itself) holds. ``out`` then holds the real evaluation at ``(a6' = -K / T'^6, T')``,
        exactly what :meth:`evaluate_into` gives for the ``retimed`` row, so "feasible" means
        what it means there (the path-only constraints are reported as they are).

        Where no T' in range satisfies them all, T' is the least violating candidate found
        (among t_max, the closed-form bounds, the scan points and a 9-point geometric grid
        from t_min to t_max; t_max when no candidate evaluates finite), evaluated the same way
        so the caller sees the violation.

        How: at unit time the kernel caches per sample the dynamic torque ``A`` (scales as
        ``1/T^2``), the gravity and soil torques, ``q'`` and the tip speed; velocity and
        acceleration give closed-form lower bounds on T', each sample's torque an interval of
        ``1/T^2``; power, and the torque of the few samples slower than the soil model's 1 mm/s
        regularisation, are searched on the cache (scan, then Illinois to a bracket of 1e-7
        relative); one real evaluation follows (more only if it contradicts the cache, which
        a 1e-9 margin on every limit prevents). The answer is within :data:`RETIME_RTOL` above
        the lowest feasible boundary found (about 1e-7 measured). A feasible set made of
        several intervals is searched from its lower end, but an island narrower than one
        scan step (8 steps between the bounds) can be missed. About 1.9x the cost of an
        :meth:`evaluate_into` row (14-15 us at 101 samples); allocates nothing, safe in the
        loop's planning step.

        Args:
            inputs: ``(N, N_IN)`` C-contiguous float64 rows (columns ``IN_*``); ``IN_A6`` and
                ``IN_T`` define the path by ``K = -a6 T^6``.
            out: ``(N, N_OUT)`` C-contiguous writable float64: the evaluation at T'.
            retimed: ``(N, N_RETIMED)`` C-contiguous writable float64: ``a6'`` (columns
                ``RT_A6..RT_A6+2``) and ``T'`` (``RT_T_S``). NaN for a row that
                :meth:`evaluate_into` rejects or whose ``K`` overflows (``out`` then as for a
                rejected row).
            path: ``(N, n_samples, 2)`` for the tip path at T', or None.

        Raises:
            ValueError: Wrong shapes, dtypes or memory layout (nothing is written).
            ConfigurationError: The numpy backend (retiming runs in the C kernel only).
        """
        self._retime(inputs, out, retimed, path)

    def retime(
        self,
        q_start_rad: ArrayLike,
        q_end_rad: ArrayLike,
        surface_y_m: float,
        dig_type: DigType | int,
        a6: ArrayLike,
        T_s: float,
    ) -> tuple[FloatArray, float, VerifyResult]:
        """Retime one candidate (convenience for :meth:`retime_into`; allocates).

        Args:
            q_start_rad: Entry pose ``(3,)``.
            q_end_rad: Exit pose ``(3,)``.
            surface_y_m: Material surface height H, m.
            dig_type: Downward or backward.
            a6: Sixth-order coefficients ``(3,)``, rad/s^6, with ``T_s`` the path to keep.
            T_s: Digging time, s.

        Returns:
            ``(a6' (3,) rad/s^6, T' s, the VerifyResult at T')``.

        Raises:
            PlanningError: A non-finite input, ``T_s <= 0`` or an unknown dig type, naming it.
            ValueError: A pose or ``a6`` not shaped ``(3,)``.
        """
        inputs = _one_row(q_start_rad, q_end_rad, surface_y_m, dig_type, a6, T_s)
        out = np.empty((1, N_OUT), dtype=np.float64)
        retimed = np.empty((1, N_RETIMED), dtype=np.float64)
        self.retime_into(inputs, out, retimed)
        a6_new = retimed[0, RT_A6 : RT_A6 + 3].copy()
        return a6_new, float(retimed[0, RT_T_S]), VerifyResult.from_row(out[0])

    def plan_into(
        self,
        inputs: FloatArray,
        out: FloatArray,
        planned: FloatArray,
        c_range: tuple[float, float] = PLAN_C_RANGE,
        path: FloatArray | None = None,
        scale: FloatArray | None = None,
    ) -> None:
        """Scale each candidate's bulge to fill the volume cap, then retime (the fast path).

        Each row's path direction is kept and its bulge scaled: the family
        ``theta(s) = theta1 + D q(s) + c K p(s)`` with ``K = -a6 T^6`` of the row (``c = 1`` is
        the row's own path). Yao's objective rewards V_p up to the hard cap V_max, so a
        network that must aim below the cap to stay feasible leaves volume unused; this takes
        it back:

        1. ``c*`` in ``c_range``: the largest V_p whose path-only constraints hold (joint
           limits, theta_p, volume_min and volume_max; they need the path only, not T). Where
           a constraint caps it (volume_max mostly), ``c*`` lies within :data:`PLAN_TOL` of
           that constraint, feasible side.
        2. The path at ``c*`` retimed as :meth:`retime_into` does (shortest feasible T').
        3. If that fails (a larger bulge needs more torque, which no retiming reduces):
           back-off to the largest ``c`` found between ``c*`` and a path-feasible scale of
           smaller V_p at which the retiming search finds a time, retimed (``c = 1`` is among
           the scan points and the back-off's candidates: where the row's own path retimes
           feasibly, the plan has at least its volume, less :data:`PLAN_TOL`). The kernel lands
           within 1e-3 in ``c`` of that boundary (measured: ~0.3 of objective per unit of
           ``c`` there). The one exception:
           where a torque bound has pushed the retimed T there above the velocity and
           acceleration bound (T then rises steeply with ``c``: 6.5 s to 9.8 s over the last
           0.3 % of ``c`` on one held-out row), it also tries the scale where that started and
           keeps the better of the two in T and V_p (eq 11 less its energy term).
        4. If nothing works, the row's own path (``c = 1``, ``scale`` 1): where it breaks a
           path-only limit, which no T can fix, the row itself, exactly as
           :meth:`evaluate_into` gives it (``planned`` holds the row's own a6 and T); else
           retimed, exactly what :meth:`retime_into` gives for the row. Either way the
           path-only values in ``out`` are those of the row's own path.

        ``out`` always holds the real evaluation of what ``planned`` holds (exactly what
        :meth:`evaluate_into` gives for it), so "feasible" means what it means there; ``K`` of
        ``planned`` is ``scale`` times the row's ``K``. The largest volume is not always the
        best objective (a bigger bulge takes more time and energy), but the plan's objective
        is worse than the own path's retimed only where it buys volume (no such row among 300
        of a validation set).

        How: the path-only search needs forward kinematics on the sample grid and no
        dynamics. Joint limits give the interval of ``c`` in closed form (each sample's angle
        is linear in ``c``); theta_p of a dig that starts on the surface too (its entry
        direction ``J(q0)(10 D + c K)``); V_p and the other entries take the path. A 9-point
        scan (trig advanced by rotation) brackets the largest feasible V_p; Illinois on the
        constraint that fails at the neighbour of larger V_p closes in (2-3 probes). The
        back-off probes scales with the retiming search only (no evaluation) and steers by
        the search's closed-form bounds: the width of the range of ``1/T^2`` that velocity,
        acceleration and the torque of each sample leave, which closes (measured: the boom's
        torque needs an ever shorter T, the accelerations an ever longer one) about linearly
        in ``c``. The samples that bind it at the failed ``c*`` give a model of it on a few
        samples (~1 us) whose zero is probed; on the PINN's held-out rows 59 of 71 back-off
        rows need that one probe (1.4 on average), the rest fall back to start points (scan
        points of smaller V_p) and a root search on the bounds (at most 4 more probes); the
        answer's T is the probe's, evaluated once. About 9 us more than
        :meth:`retime_into` at 101 samples (p50 ~23 us per row); rows that take the back-off
        ~38 us (p50; 60 us p90). Allocates nothing; safe in the loop's planning step.

        Args:
            inputs: ``(N, N_IN)`` C-contiguous float64 rows (columns ``IN_*``); ``IN_A6`` and
                ``IN_T`` define the path direction by ``K = -a6 T^6``.
            out: ``(N, N_OUT)`` C-contiguous writable float64: the evaluation of the plan.
            planned: ``(N, N_RETIMED)`` C-contiguous writable float64: ``a6'`` (columns
                ``RT_A6..RT_A6+2``) and ``T'`` (``RT_T_S``); NaN for a rejected row (as
                :meth:`retime_into`).
            c_range: ``(c_lo, c_hi)``, finite, ``0 <= c_lo <= c_hi``.
            path: ``(N, n_samples, 2)`` for the tip path of the plan, or None.
            scale: ``(N,)`` C-contiguous writable float64 for the ``c`` of the plan (1.0 where
                the row's own path is reported, NaN for a rejected row), or None.

        Raises:
            ValueError: Wrong shapes, dtypes or memory layout, or a bad ``c_range`` (nothing is
                written).
            ConfigurationError: The numpy backend (planning runs in the C kernel only).
        """
        lo, hi = _c_range(c_range)
        self._plan(inputs, out, planned, lo, hi, path, scale)

    def plan(
        self,
        q_start_rad: ArrayLike,
        q_end_rad: ArrayLike,
        surface_y_m: float,
        dig_type: DigType | int,
        a6: ArrayLike,
        T_s: float,
        c_range: tuple[float, float] = PLAN_C_RANGE,
    ) -> tuple[FloatArray, float, VerifyResult, float]:
        """Plan one candidate (convenience for :meth:`plan_into`; allocates).

        Args:
            q_start_rad: Entry pose ``(3,)``.
            q_end_rad: Exit pose ``(3,)``.
            surface_y_m: Material surface height H, m.
            dig_type: Downward or backward.
            a6: Sixth-order coefficients ``(3,)``, rad/s^6, with ``T_s`` the path direction.
            T_s: Digging time, s.
            c_range: ``(c_lo, c_hi)`` of the path scale.

        Returns:
            ``(a6' (3,) rad/s^6, T' s, the VerifyResult of the plan, its path scale c)``.

        Raises:
            PlanningError: A non-finite input, ``T_s <= 0`` or an unknown dig type, naming it.
            ValueError: A pose or ``a6`` not shaped ``(3,)``, or a bad ``c_range``.
        """
        inputs = _one_row(q_start_rad, q_end_rad, surface_y_m, dig_type, a6, T_s)
        out = np.empty((1, N_OUT), dtype=np.float64)
        planned = np.empty((1, N_RETIMED), dtype=np.float64)
        scale = np.empty(1, dtype=np.float64)
        self.plan_into(inputs, out, planned, c_range, None, scale)
        a6_new = planned[0, RT_A6 : RT_A6 + 3].copy()
        return a6_new, float(planned[0, RT_T_S]), VerifyResult.from_row(out[0]), float(scale[0])

    def _retime_needs_c(
        self,
        inputs: FloatArray,
        out: FloatArray,
        retimed: FloatArray,
        path: FloatArray | None = None,
    ) -> None:
        """The numpy backend's :meth:`retime_into`: none (the search is the kernel's)."""
        raise ConfigurationError(f"retiming needs the C kernel; {BUILD_HINT}")

    def _plan_needs_c(
        self,
        inputs: FloatArray,
        out: FloatArray,
        planned: FloatArray,
        c_lo: float,
        c_hi: float,
        path: FloatArray | None = None,
        scale: FloatArray | None = None,
    ) -> None:
        """The numpy backend's :meth:`plan_into`: none (the search is the kernel's)."""
        raise ConfigurationError(f"planning (fill and retime) needs the C kernel; {BUILD_HINT}")

    def _evaluate_numpy(
        self, inputs: FloatArray, out: FloatArray, path: FloatArray | None = None
    ) -> None:
        """The numpy backend: :func:`oneshot.evaluate` on the valid rows, the rest rejected."""
        x, o, p = _checked_rows(
            (inputs, "inputs", (N_IN,), False),
            (out, "out", (N_OUT,), True),
            (path, "path", (self.n_samples, 2), True),
        )
        ok = _valid_rows(x)
        o[~ok] = np.nan
        o[~ok, COL_TOTAL] = np.inf
        if p is not None:
            p[~ok] = np.nan
        if not np.any(ok):
            return
        rows, row_path = self._numpy_rows(x[ok], p is not None)
        o[ok] = rows
        if p is not None and row_path is not None:
            p[ok] = row_path

    def _numpy_rows(
        self, v: FloatArray, want_path: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        """Output rows (and paths) of valid input rows by :func:`oneshot.evaluate`.

        A batch that evaluate refuses (absurd values whose coefficients overflow) is redone row
        by row, and the refused rows are rejected, as the C kernel rejects them.
        """
        try:
            return self._numpy_batch(v, want_path)
        except (PlanningError, ConfigurationError):
            pass
        rows = np.full((v.shape[0], N_OUT), np.nan)
        rows[:, COL_TOTAL] = np.inf
        paths = np.full((v.shape[0], self.n_samples, 2), np.nan) if want_path else None
        for i in range(v.shape[0]):
            try:
                row, row_path = self._numpy_batch(v[i : i + 1], want_path)
            except (PlanningError, ConfigurationError):
                continue
            rows[i] = row[0]
            if paths is not None and row_path is not None:
                paths[i] = row_path[0]
        return rows, paths

    def _numpy_batch(
        self, v: FloatArray, want_path: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        qs = v[:, IN_Q_START : IN_Q_START + 3]
        qe = v[:, IN_Q_END : IN_Q_END + 3]
        a6 = v[:, None, IN_A6 : IN_A6 + 3]
        T = v[:, IN_T, None]
        kind = v[:, IN_DIG_TYPE].astype(np.int64)
        with np.errstate(all="ignore"):
            ev = oneshot.evaluate(
                self.rig, qs, qe, v[:, IN_SURFACE_Y], kind, a6, T, self.n_samples
            )
        rows = np.empty((v.shape[0], N_OUT), dtype=np.float64)
        rows[:, COL_VIOLATIONS : COL_VIOLATIONS + N_CONSTRAINTS] = ev.violations[:, 0]
        rows[:, COL_TOTAL] = ev.total_violation[:, 0]
        rows[:, COL_OBJECTIVE] = ev.objective[:, 0]
        rows[:, COL_T_S] = ev.T_s[:, 0]
        rows[:, COL_VOLUME_M3] = ev.volume_m3[:, 0]
        rows[:, COL_ENERGY_J] = ev.energy_j[:, 0]
        rows[:, COL_THETA_P_RAD] = ev.theta_p_rad[:, 0]
        rows[:, COL_PEAK_POWER_W] = ev.peak_power_w[:, 0]
        rows[:, COL_PEAK_TORQUE_NM : COL_PEAK_TORQUE_NM + 3] = ev.peak_torque_nm[:, 0]
        # Overflowed arithmetic: +inf total wherever any output is not finite (as the kernel).
        rows[~np.all(np.isfinite(rows), axis=1), COL_TOTAL] = np.inf
        if not want_path:
            return rows, None
        coeffs = sextic.sextic_coefficients(qs, qe, a6[:, 0], T[:, 0])
        samples = sextic.evaluate(coeffs, T[:, 0], self.n_samples)
        pose, _ = kinematics.tip_state(self.rig, samples.q_rad, samples.qd_rad_s)
        return rows, pose[..., :2]


def _c_range(c_range: tuple[float, float]) -> tuple[float, float]:
    """``(c_lo, c_hi)`` as floats if finite with ``0 <= c_lo <= c_hi``, else ValueError."""
    try:
        lo, hi = (float(c) for c in c_range)
    except (TypeError, ValueError):
        raise ValueError(f"c_range must be two floats (c_lo, c_hi); got {c_range!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi):
        raise ValueError(f"c_range must be finite with 0 <= c_lo <= c_hi; got ({lo!r}, {hi!r})")
    return lo, hi


def _one_row(
    q_start_rad: ArrayLike,
    q_end_rad: ArrayLike,
    surface_y_m: float,
    dig_type: DigType | int,
    a6: ArrayLike,
    T_s: float,
) -> FloatArray:
    """One input row ``(1, N_IN)`` from a checked candidate.

    Raises:
        PlanningError: A non-finite input, ``T_s <= 0`` or an unknown dig type, naming it.
        ValueError: A pose or ``a6`` not shaped ``(3,)``.
    """
    vectors = {"q_start_rad": q_start_rad, "q_end_rad": q_end_rad, "a6": a6}
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in vectors.items()}
    for name, v in arrays.items():
        if v.shape != (3,):
            raise ValueError(f"{name} must have shape (3,) (boom, stick, bucket); got {v.shape}")
        if not np.all(np.isfinite(v)):
            j = int(np.argmax(~np.isfinite(v)))
            raise PlanningError(f"{name}[{j}] is {float(v[j])!r}; every input must be finite")
    h = float(surface_y_m)
    T = float(T_s)
    if not math.isfinite(h):
        raise PlanningError(f"surface_y_m is {h!r}; the surface height must be finite")
    if not (math.isfinite(T) and T > 0.0):
        raise PlanningError(f"T_s must be finite and > 0 s; got {T!r}")
    kinds = tuple(int(k) for k in DigType)
    if isinstance(dig_type, bool) or dig_type not in kinds:
        raise PlanningError(
            f"dig_type must be one of {', '.join(f'{k.name} ({int(k)})' for k in DigType)}; "
            f"got {dig_type!r}"
        )
    return pack_inputs(
        arrays["q_start_rad"], arrays["q_end_rad"], h, int(dig_type), arrays["a6"], T
    )


def _valid_rows(x: FloatArray) -> NDArray[np.bool_]:
    """Rows the kernel accepts: finite, T > 0, dig type 0 or 1."""
    T = x[:, IN_T]
    kind = x[:, IN_DIG_TYPE]
    ok: NDArray[np.bool_] = (
        np.all(np.isfinite(x), axis=1) & (T > 0.0) & ((kind == 0.0) | (kind == 1.0))
    )
    return ok


def _checked_rows(
    *args: tuple[FloatArray | None, str, tuple[int, ...], bool],
) -> list[Any]:
    """Each ``(array or None, name, tail, writable)`` checked by :func:`_checked`, all present
    ones with the rows N of the first; the same contract and messages as the C kernel's."""
    arrays = [
        None if a is None else _checked(a, name, tail, writable=w) for a, name, tail, w in args
    ]
    first = arrays[0]
    assert first is not None  # the inputs are never optional
    n = first.shape[0]
    rows = [n if a is None else a.shape[0] for a in arrays]
    if any(k != n for k in rows):
        names = [name for _, name, _, _ in args]
        raise ValueError(
            f"{', '.join(names[:-1])} and {names[-1]} must have the same number of rows N; "
            f"got {', '.join(str(k) for k in rows)}"
        )
    return arrays


def _checked(a: FloatArray, name: str, tail: tuple[int, ...], *, writable: bool) -> FloatArray:
    """``a`` if it is a C-contiguous float64 ndarray shaped ``(N, *tail)``, else ValueError.

    The same contract as the C kernel's, so the two backends accept the same arrays.
    """
    if not isinstance(a, np.ndarray) or a.dtype != np.float64 or not a.flags.c_contiguous:
        raise ValueError(f"{name} must be a C-contiguous float64 array")
    if writable and not a.flags.writeable:
        raise ValueError(f"{name} must be a C-contiguous writable float64 array")
    if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
        want = ", ".join(["N", *(str(t) for t in tail)]) if tail else "N,"
        raise ValueError(f"{name} must have shape ({want})")
    return a
