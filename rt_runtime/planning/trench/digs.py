"""Planning a chosen candidate for real: the one-shot planner's plan (or the fit), its
retiming on a grid finer than the verifier's, every hard limit verified, and the checks on the
material left (over-dig of the region it removes, the fill band) before it is accepted."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from rt_runtime.errors import PlanningError
from rt_runtime.planning.oneshot import Problem
from rt_runtime.planning.trench.candidates import Candidate
from rt_runtime.planning.trench.fit import FitMixin
from rt_runtime.planning.trench.geometry import (
    MIN_USEFUL_FRACTION,
    OVERDIG_LIMIT_M,
    _swept_polygon,
    _total_without_volume,
    sextic_bulge,
)
from rt_runtime.planning.trench.plan import PlannedDig
from rt_runtime.planning.trench.planners import OneShotResult, PinnOneShot
from rt_runtime.planning.trench.state import _stage
from rt_runtime.planning.verify import (
    COL_ENERGY_J,
    COL_THETA_P_RAD,
    COL_TOTAL,
    COL_VOLUME_M3,
    N_OUT,
    pack_inputs,
)


class DigsMixin(FitMixin):
    """Planning and checking a session's chosen digs (see the module)."""

    def _first_plannable(
        self, ranked: list[Candidate], remaining: Any, t0: float
    ) -> PlannedDig | None:
        """The best screened candidate the one-shot planner plans within the limits
        (``remaining``: :meth:`remaining_design` of the current material).

        The PINN plans exactly what was screened; another planner (the PSO) finds its own
        optimum for the same poses, which may cut too deep or take more than the bucket: then
        the next candidate is tried. A carried dig whose carry is refused (:meth:`_carry_cycle`)
        or that fails its checks is tried again as the same dig with a bucket of its own.
        """
        for best in ranked:
            tries = [best]
            while tries:
                chosen = tries.pop()
                try:
                    dig = self._plan_chosen(chosen, remaining, (time.perf_counter() - t0) * 1e6)
                    self._check_transition_poses(dig)
                    if dig.carried:
                        self._carry_cycle(dig)
                except PlanningError:
                    if chosen.carried:
                        tries.extend(c for c in [self._uncarried(chosen)] if c is not None)
                    continue
                return dig
        return None

    def _uncarried(self, carried: Candidate) -> Candidate | None:
        """The fitted ``carried`` dig with a bucket of its own (checked again: its fill, the
        bucket's room and its time window change), None where it does not plan so."""
        x7 = carried.x7
        assert carried.a6 is not None  # fitted
        K = sextic_bulge(carried.a6, carried.T_s)
        n_fit = self.planner.fit_qf.shape[0]
        cost = carried.fit_rms_m**2 * n_fit
        (found,) = self._checked_fits(carried.kind, [(x7[0:3], x7[3:6], K, cost)], n_fit)
        if found is None:
            return None
        return dataclasses.replace(found, may_underfill=carried.may_underfill)

    def _count_pass(self, dig: PlannedDig | None) -> bool:
        """Count ``dig`` against the section's finishing passes: a finishing pass that starts
        a bucket counts one, a joined dig none (its bucket was counted when it began); a
        joined dig that fills a bucket a pass began takes that pass back. Returns whether
        ``dig`` counted one."""
        if dig is None:
            return False
        if not dig.joined:
            if dig.finishing:
                self.finishing_used += 1
            return dig.finishing
        if not dig.finishing and self.digs and self.digs[-1].finishing:
            self.finishing_used = max(0, self.finishing_used - 1)
            self.finish_passes = min(self.finish_passes, self.finishing_used)
        return False

    def _fine_grid_time(
        self, problem: Problem, a6: tuple[float, float, float], T_s: float
    ) -> tuple[tuple[float, float, float], float]:
        """The same path, slowed just enough that the joint accelerations hold on a grid 10x
        finer than the verifier's (a retimed plan sits on the limit at the verifier's samples
        and may peak a few 1e-4 above it between them); unchanged when they already hold or
        the slower time would leave the time range. The caller verifies the result.
        """
        q1 = np.asarray(problem.q_start_rad)
        D = np.asarray(problem.q_end_rad) - q1
        K = sextic_bulge(a6, T_s)
        qdd = self.planner.fine_qf2[:, None] * D + self.planner.fine_pf2[:, None] * K
        ratio = float(np.max(np.abs(qdd) / self.planner.qdd_max)) / T_s**2
        if ratio <= 1.0:
            return a6, T_s
        T_new = T_s * math.sqrt(ratio) * (1.0 + 1e-9)
        if T_new > self.planning.t_max_s:
            return a6, T_s
        a_new = -K / T_new**6
        return (float(a_new[0]), float(a_new[1]), float(a_new[2])), T_new

    @_stage("checks")
    def _plan_chosen(self, best: Candidate, remaining: Any, select_us: float) -> PlannedDig:
        """Plan ``best`` for real and check it; ``remaining`` is :meth:`remaining_design` (the
        caller's, the material being unchanged since)."""
        x7 = best.x7
        problem = Problem(
            q_start_rad=(float(x7[0]), float(x7[1]), float(x7[2])),
            q_end_rad=(float(x7[3]), float(x7[4]), float(x7[5])),
            surface_y_m=float(x7[6]),
            dig_type=best.kind,
        )
        oneshot_planner = self.planner.oneshot
        fitted = best.a6 is not None
        # Judged on the material left (the fill band on the real cut), not on V_p against H.
        real_fill = fitted or isinstance(oneshot_planner, PinnOneShot)
        if best.a6 is not None:
            res = OneShotResult(best.a6, best.T_s, np.zeros(N_OUT), 0.0, "profile")
        else:
            t_plan = time.perf_counter()
            if isinstance(oneshot_planner, PinnOneShot) and best.K_rad is not None:
                res = oneshot_planner.plan_scaled(problem, best.K_rad, best.T_s, best.c)
            else:
                res = oneshot_planner.plan_dig(problem, best.c)
            spent = (time.perf_counter() - t_plan) * 1e6
            self.stage_us["oneshot"] += spent
            self.stage_us["checks"] -= spent
        a6, T_s = self._fine_grid_time(problem, res.a6, res.T_s)
        pb = problem
        row = pack_inputs(pb.q_start_rad, pb.q_end_rad, pb.surface_y_m, pb.dig_type, a6, T_s)
        out = np.zeros((1, N_OUT))
        verifier = self.planner.verifier_for(best.pass_window)
        path = np.zeros((1, verifier.n_samples, 2))
        verifier.evaluate_into(row, out, path=path)
        joined = best.joined and not best.carried  # no entry: no theta_p range
        violation = _total_without_volume(out[0], joined) if real_fill else out[0, COL_TOTAL]
        if violation > 0.0 and T_s != res.T_s:  # the slower plan fails: keep the verified one
            a6, T_s = res.a6, res.T_s
            row[0, 8:11] = a6
            row[0, 11] = T_s
            verifier.evaluate_into(row, out, path=path)
            violation = _total_without_volume(out[0], joined) if real_fill else out[0, COL_TOTAL]
        if violation > 0.0:
            raise PlanningError("one-shot plan fails verification; nothing was planned")
        p = path[0].copy()
        p[:, 0] += self.machine_x
        over = self.overdig_of(p)
        env = self._envelope(p, self.grid)
        total, useful = self._cut_areas(env)
        if not fitted and useful < 0.5 * MIN_USEFUL_FRACTION * self.design_area:
            raise PlanningError(
                f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} removes "
                f"{useful * self.width_m * 1e3:.3f} L of the design, less than the screening "
                "promised"
            )
        # A joined dig fills the bucket the dig before it began.
        bucket = best.bucket_m3 / self.width_m
        if over > OVERDIG_LIMIT_M or total + bucket > self.v_max_m3 / self.width_m:
            raise PlanningError(
                f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} over-digs "
                f"{over * 1e3:.1f} mm or exceeds the bucket "
                f"({(total + bucket) * self.width_m * 1e3:.2f} L)"
            )
        # The record: polygon areas (the height field above only screened and checked), and
        # the over-dig of the region the dig removes, as the finished plan measures it. The
        # samples' over-dig above counts a sample where the 1 mm height field says it is in
        # material; beside a steep face the polygon holds material the height field does not
        # (a 1.0 m x 0.12 m trench ended 5.9 mm deep with every dig's samples <= 4.9 mm).
        swept = _swept_polygon(p, self.grid, self.top_y, env, self._envelope)
        # record() of this very path (the open-loop plan) reuses the envelope and region.
        self._planned_region = (p, env, swept)
        if swept is not None:
            cut = self.material.intersection(swept)
            total = float(cut.area)
            useful = float(remaining.intersection(swept).area)
            over = max(over, self._overdig_of_region(cut))
            if over > OVERDIG_LIMIT_M:
                raise PlanningError(
                    f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} "
                    f"over-digs {over * 1e3:.1f} mm (the region it removes)"
                )
        lo_a, hi_a = self._fill_band()
        fill = total + bucket
        # A dig allowed out of the fill band is a finishing pass only where it is out of it.
        finishing_pass = best.may_underfill and not lo_a <= fill <= hi_a
        if not best.may_underfill and not lo_a <= fill <= hi_a:
            raise PlanningError(
                f"the {self.planner.oneshot.name} plan of dig {len(self.digs) + 1} carries "
                f"{fill * self.width_m * 1e3:.2f} L of material, outside the fill band "
                f"{lo_a * self.width_m * 1e3:.2f}-{hi_a * self.width_m * 1e3:.2f} L"
            )
        if best.pass_window and not finishing_pass:
            # Timed as a pass but carrying a full bucket on the polygon: a dig, in the
            # one-shot time window.
            self.planner.verifier.evaluate_into(row, out)
            if _total_without_volume(out[0], joined) > 0.0:
                raise PlanningError(
                    f"dig {len(self.digs) + 1} was timed as a finishing pass ({T_s:.2f} s) but "
                    f"carries a full bucket; a dig keeps the time window "
                    f"{self.planning.t_min_s:g}-{self.planning.t_max_s:g} s"
                )
        return PlannedDig(
            index=len(self.digs),
            problem=problem,
            a6=a6,
            T_s=T_s,
            machine_x_m=self.machine_x,
            tip_path_m=p,
            volume_m3=total * self.width_m,
            design_volume_m3=useful * self.width_m,
            predicted_volume_m3=float(out[0, COL_VOLUME_M3]),
            energy_j=float(out[0, COL_ENERGY_J]),
            theta_p_rad=float(out[0, COL_THETA_P_RAD]),
            overdig_m=over,
            plan_us=res.plan_us,
            select_us=select_us,
            planner=self.planner.oneshot.name,
            status="profile_pass" if finishing_pass else res.status,
            evaluation=out[0].copy(),
            finishing=finishing_pass,
            section=self.section,
            joined=best.joined,
            pass_window=finishing_pass,
            carried=best.carried,
        )
