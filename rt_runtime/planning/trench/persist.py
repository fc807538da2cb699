"""The session as JSON-able data and back (a daemon restart resumes at the next undone dig)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import shapely
from shapely.errors import GEOSException

from rt_runtime.errors import ConfigurationError
from rt_runtime.planning.oneshot import DigType, Problem
from rt_runtime.planning.trench.geometry import FloatArray
from rt_runtime.planning.trench.plan import (
    Cycle,
    PlannedDig,
    Transition,
    TransitionKind,
    TravelMove,
)
from rt_runtime.planning.trench.sections import SectionsMixin
from rt_runtime.planning.trench.state import Stage

if TYPE_CHECKING:
    pass


#: The state's version written; the versions read (2 has no ``cycle`` steps, which 3 adds).
_STATE_VERSION = 3
_STATE_VERSIONS = (2, 3)


def _step_to_json(step: PlannedDig | Cycle | Transition | TravelMove) -> dict[str, Any]:
    """One session step as JSON-able data (tagged with ``type``)."""
    if isinstance(step, PlannedDig):
        p = step.problem
        return {
            "type": "dig",
            "index": step.index,
            "problem": {
                "q_start_rad": list(p.q_start_rad),
                "q_end_rad": list(p.q_end_rad),
                "surface_y_m": p.surface_y_m,
                "dig_type": p.dig_type.name.lower(),
            },
            "a6": list(step.a6),
            "T_s": step.T_s,
            "machine_x_m": step.machine_x_m,
            "tip_path_m": np.asarray(step.tip_path_m, dtype=np.float64).tolist(),
            "volume_m3": step.volume_m3,
            "design_volume_m3": step.design_volume_m3,
            "predicted_volume_m3": step.predicted_volume_m3,
            "energy_j": step.energy_j,
            "theta_p_rad": step.theta_p_rad,
            "overdig_m": step.overdig_m,
            "plan_us": step.plan_us,
            "select_us": step.select_us,
            "planner": step.planner,
            "status": step.status,
            "evaluation": np.asarray(step.evaluation, dtype=np.float64).tolist(),
            "finishing": step.finishing,
            "section": step.section,
            "joined": step.joined,
            "pass_window": step.pass_window,
            "carried": step.carried,
        }
    if isinstance(step, Cycle):
        return {
            "type": "cycle",
            "waypoints_rad": [list(q) for q in step.waypoints_rad],
            "kinds": [k.label for k in step.kinds],
            "piece_durations_s": list(step.piece_durations_s),
            "shape_knots": list(step.shape_knots),
            "shape_positions_rad": [list(q) for q in step.shape_positions_rad],
            "w_jerk": step.w_jerk,
            "moves": [_step_to_json(m) for m in step.moves],
            "duration_s": step.duration_s,
            "bound_s": step.bound_s,
            "machine_x_m": step.machine_x_m,
            "penetration_m": step.penetration_m,
            "after_dig": step.after_dig,
        }
    if isinstance(step, Transition):
        return {
            "type": "transition",
            "kind": step.kind.label,
            "q_from_rad": list(step.q_from_rad),
            "q_to_rad": list(step.q_to_rad),
            "duration_s": step.duration_s,
            "machine_x_m": step.machine_x_m,
            "penetration_m": step.penetration_m,
        }
    return {
        "type": "travel",
        "distance_m": step.distance_m,
        "machine_x_from_m": step.machine_x_from_m,
        "machine_x_to_m": step.machine_x_to_m,
    }


def _triple(values: Sequence[float]) -> tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f"expected three values, got {len(values)}")
    return (float(values[0]), float(values[1]), float(values[2]))


def _step_from_json(item: dict[str, Any]) -> PlannedDig | Cycle | Transition | TravelMove:
    """The inverse of :func:`_step_to_json` (raises KeyError/ValueError on bad data)."""
    kind = item["type"]
    if kind == "dig":
        p = item["problem"]
        path = np.asarray(item["tip_path_m"], dtype=np.float64).reshape(-1, 2)
        return PlannedDig(
            index=int(item["index"]),
            problem=Problem(
                q_start_rad=_triple(p["q_start_rad"]),
                q_end_rad=_triple(p["q_end_rad"]),
                surface_y_m=float(p["surface_y_m"]),
                dig_type=DigType[str(p["dig_type"]).upper()],
            ),
            a6=_triple(item["a6"]),
            T_s=float(item["T_s"]),
            machine_x_m=float(item["machine_x_m"]),
            tip_path_m=path,
            volume_m3=float(item["volume_m3"]),
            design_volume_m3=float(item["design_volume_m3"]),
            predicted_volume_m3=float(item["predicted_volume_m3"]),
            energy_j=float(item["energy_j"]),
            theta_p_rad=float(item["theta_p_rad"]),
            overdig_m=float(item["overdig_m"]),
            plan_us=float(item["plan_us"]),
            select_us=float(item["select_us"]),
            planner=str(item["planner"]),
            status=str(item["status"]),
            evaluation=np.asarray(item["evaluation"], dtype=np.float64),
            finishing=bool(item.get("finishing", False)),
            section=int(item.get("section", 0)),
            joined=bool(item.get("joined", False)),
            pass_window=bool(item.get("pass_window", item.get("finishing", False))),
            carried=bool(item.get("carried", False)),
        )
    if kind == "transition":
        return Transition(
            kind=TransitionKind.parse(item["kind"]),
            q_from_rad=_triple(item["q_from_rad"]),
            q_to_rad=_triple(item["q_to_rad"]),
            duration_s=float(item["duration_s"]),
            machine_x_m=float(item["machine_x_m"]),
            penetration_m=float(item["penetration_m"]),
        )
    if kind == "cycle":
        moves = tuple(_step_from_json(m) for m in item["moves"])
        transitions = tuple(m for m in moves if isinstance(m, Transition))
        if len(transitions) != len(moves):
            raise ValueError("a cycle's moves must be transitions")
        return Cycle(
            waypoints_rad=tuple(_triple(q) for q in item["waypoints_rad"]),
            kinds=tuple(TransitionKind.parse(k) for k in item["kinds"]),
            piece_durations_s=tuple(float(h) for h in item["piece_durations_s"]),
            shape_knots=tuple(int(k) for k in item["shape_knots"]),
            shape_positions_rad=tuple(_triple(q) for q in item["shape_positions_rad"]),
            w_jerk=float(item["w_jerk"]),
            moves=transitions,
            duration_s=float(item["duration_s"]),
            bound_s=float(item["bound_s"]),
            machine_x_m=float(item["machine_x_m"]),
            penetration_m=float(item["penetration_m"]),
            after_dig=bool(item["after_dig"]),
        )
    if kind == "travel":
        return TravelMove(
            float(item["distance_m"]),
            float(item["machine_x_from_m"]),
            float(item["machine_x_to_m"]),
        )
    raise ValueError(f"unknown step type {kind!r}; allowed: dig, cycle, transition, travel")


class PersistMixin(SectionsMixin):
    """A session's state as data (see the module)."""

    def state(self) -> dict[str, Any]:
        """The session as JSON-able data (``json.dumps`` takes it as it is).

        Keys: ``version``, ``rig``, ``planner``, ``task`` (name and dimensions), ``material_wkt``
        (the material polygon as WKT, full precision), ``surface_m`` (height field on the 1 mm
        grid), ``machine_x_m``, ``q_now_rad`` (the last dig's exit or None), ``phase``
        (``downward``/``backward``), ``section``, ``stage``, ``layer``, ``layer_floors_m``,
        ``wall_piece``, ``finishing_used``, ``finish_passes``, ``finishing_difference_m2``
        (where the section's digging is), ``joinable`` (the last dig's exit ``q_rad`` and its
        bucket's content ``bucket_m3`` where the next dig may continue it, else None),
        ``digs_done``,
        ``steps`` (every recorded dig, cycle, transition and travel move, each a dict with
        ``type``),
        and ``pending`` (the dig :meth:`next_dig` returned and :meth:`record` has not taken yet,
        or None; after :meth:`record` it is always None, which is the state to persist).
        """
        t = self.task
        return {
            "version": _STATE_VERSION,
            "rig": self.rig.name,
            "planner": self.planner.oneshot.name,
            "task": {
                "name": t.name,
                "length_m": t.length_m,
                "depth_m": t.depth_m,
                "beta1_rad": t.beta1_rad,
                "beta2_rad": t.beta2_rad,
                "start_x_m": t.start_x_m,
            },
            "material_wkt": shapely.to_wkt(self.material, rounding_precision=-1),
            "surface_m": [float(v) for v in self.surface],
            "machine_x_m": float(self.machine_x),
            "q_now_rad": None if self.q_now is None else [float(v) for v in self.q_now],
            "phase": self.phase.name.lower(),
            "section": int(self.section),
            "stage": self.stage.name.lower(),
            "layer": int(self.layer),
            "layer_floors_m": [float(v) for v in self.layer_floors],
            "wall_piece": int(self._wall_piece),
            "finishing_used": int(self.finishing_used),
            "finish_passes": int(self.finish_passes),
            "finishing_difference_m2": self.finishing_difference,
            "joinable": (
                None
                if self.joinable is None
                else {
                    "q_rad": [float(v) for v in self.joinable[0]],
                    "bucket_m3": float(self.joinable[1]),
                }
            ),
            "digs_done": len(self.digs),
            "steps": [_step_to_json(step) for step in self.steps],
            "pending": None if self.pending is None else _step_to_json(self.pending),
        }

    def _joinable_from(self, raw: Any) -> tuple[FloatArray, float] | None:
        """The state's ``joinable`` (None or ``{"q_rad", "bucket_m3"}``) as the session keeps
        it.

        Raises:
            ConfigurationError: Malformed, not finite, or a bucket outside 0..V_max (the
                message names the key).
        """
        if raw is None:
            return None
        try:
            q = np.asarray(_triple(raw["q_rad"]), dtype=np.float64)
            bucket = float(raw["bucket_m3"])
        except (KeyError, TypeError, ValueError):
            q, bucket = np.full(3, np.nan), math.nan
        if not (np.isfinite(q).all() and 0.0 <= bucket < self.v_max_m3):
            raise ConfigurationError(
                f"session state key 'joinable' is {raw!r}; allowed: null or finite "
                f"'q_rad' (3 values) and 'bucket_m3' in 0..{self.v_max_m3:g} m^3"
            )
        return q, bucket

    def apply_state(self, state: dict[str, Any]) -> None:
        """Replace this trench's progress by ``state`` (see :meth:`restore`).

        Raises:
            ConfigurationError: As :meth:`restore`.
        """
        try:
            version = state["version"]
            if version not in _STATE_VERSIONS:
                allowed = ", ".join(str(v) for v in _STATE_VERSIONS)
                raise ConfigurationError(f"session state version {version!r}; allowed: {allowed}")
            if state["rig"] != self.rig.name:
                raise ConfigurationError(
                    f"session state key 'rig' is {state['rig']!r}; this planner's rig is "
                    f"{self.rig.name!r}"
                )
            t = state["task"]
            mine = self.task
            same = t["name"] == mine.name and all(
                abs(float(t[k]) - float(getattr(mine, k))) <= 1e-12
                for k in ("length_m", "depth_m", "beta1_rad", "beta2_rad", "start_x_m")
            )
            if not same:
                raise ConfigurationError(
                    f"session state key 'task' is {t}; the session's task is {mine}"
                )
            material = shapely.from_wkt(state["material_wkt"])
            surface = np.asarray(state["surface_m"], dtype=np.float64)
            if surface.shape != self.surface.shape or not np.isfinite(surface).all():
                raise ConfigurationError(
                    f"session state key 'surface_m' has shape {surface.shape}; allowed: "
                    f"{self.surface.shape} finite values (the task's 1 mm grid)"
                )
            steps = [_step_from_json(item) for item in state["steps"]]
            q_now = state["q_now_rad"]
            phase = DigType[str(state["phase"]).upper()]
            machine_x = float(state["machine_x_m"])
            section = int(state["section"])
            if not 0 <= section < len(self.sections):
                raise ConfigurationError(
                    f"session state key 'section' is {section}; allowed: "
                    f"0..{len(self.sections) - 1}"
                )
            stage = Stage[str(state["stage"]).upper()]
            layer_floors = tuple(float(v) for v in state["layer_floors_m"])
            layer = int(state["layer"])
            wall_piece = int(state["wall_piece"])
            finishing_used = int(state["finishing_used"])
            # Not in the states written before it: every pass counted, as then.
            finish_passes = int(state.get("finish_passes", finishing_used))
            if not 0 <= finish_passes <= finishing_used:
                raise ConfigurationError(
                    f"session state key 'finish_passes' is {finish_passes}; allowed: "
                    f"0..{finishing_used} (finishing_used)"
                )
            # Not in the states written before it (none taken beyond the two then).
            raw = state.get("finishing_difference_m2")
            finishing_difference = None if raw is None else float(raw)
            if finishing_difference is not None and not math.isfinite(finishing_difference):
                raise ConfigurationError(
                    f"session state key 'finishing_difference_m2' is {raw!r}; allowed: a "
                    "finite area (m^2) or null"
                )
            # Not in the states written before it: no dig continues the last.
            joinable = self._joinable_from(state.get("joinable"))
            pending = state.get("pending")
            pending_dig = None if pending is None else _step_from_json(pending)
            if pending_dig is not None and not isinstance(pending_dig, PlannedDig):
                raise ConfigurationError("session state key 'pending' is not a dig")
        except ConfigurationError:
            raise
        except (KeyError, TypeError, ValueError, GEOSException) as exc:
            raise ConfigurationError(f"session state is malformed: {exc!r}") from exc
        self.material = material
        self.surface = surface
        self.steps = steps
        self.digs = [s for s in steps if isinstance(s, PlannedDig)]
        self.machine_x = machine_x
        self.q_now = None if q_now is None else np.asarray(q_now, dtype=np.float64)
        self.pending = pending_dig
        self.phase = phase
        self.section = section
        self.section_lo, self.section_hi = self.sections[section]
        self.layer_floors = layer_floors
        self.layer = layer
        self._set_layer()
        self.stage = stage
        self._wall_piece = wall_piece
        self.finishing_used = finishing_used
        self.finish_passes = finish_passes
        self.finishing_difference = finishing_difference
        self.joinable = joinable
