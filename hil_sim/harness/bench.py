"""Wall time per SYNC period of the lockstep HIL's models: plant, three drives and the VCU.

Role: the measurement behind issue 7's budget (``make demo`` runs ~75k periods of 2 ms and must
finish in <= 60 s wall). It runs :class:`hil_sim.sim.HilCore` without the bus (frames by direct
call: plant, drive nodes and VCU, the servo sub-step loop of ``HilCore.advance``), drives
the three drives into OPERATION ENABLED in CSP mode, and replays a held-out verified dig of the
scale model (``onnx/pinn_downward_heldout.npz``) through the soil of a terrain, one RPDO1 per
drive, one ``VCU_Command`` and one SYNC per period, as the master does.

Per period it times two parts with ``time.perf_counter_ns``:

* ``frames``: RPDO1s, ``VCU_Command`` and SYNC delivered to every node (the drives' TPDOs and
  the VCU's status encoding), plus the nodes' time supervision;
* ``advance``: the servo sub-steps (3 drive cascades, the plant, the VCU), the part the plant
  and firmware models own.

It prints median and p99 of each part and of their sum, in microseconds per period, for each
repeat. Numbers depend on the machine and its load; compare runs on the same machine.

Usage::

    .venv/bin/python -m hil_sim.harness.bench [--digs N] [--repeats R] [--cpu]
"""

from __future__ import annotations

import argparse
import statistics
import struct
import time
from pathlib import Path

import numpy as np

from hil_sim.sim import COB_SYNC, HilCore
from hil_sim.terrain import Terrain
from rt_runtime import actuation
from rt_runtime.actuation import AXES
from rt_runtime.canbus.vcu import VcuClient, VcuCommand
from rt_runtime.rig import Rig, load_rig
from rt_runtime.trajectory import sextic

PERIOD_S = 2e-3
#: The demo's rig; the held-out digs replayed are planned for it.
RIG = "scale_model"
COB_NMT = 0x000
HELDOUT = Path(__file__).resolve().parents[2] / "onnx" / "pinn_downward_heldout.npz"


def _reference(rig: Rig, dig: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Per-period joint start, stroke targets and stroke rates of one held-out dig, and its
    ground height."""
    data = np.load(HELDOUT)
    x, y = data["X"][dig], data["Y"][dig]
    coeffs = sextic.sextic_coefficients(x[:3], x[3:6], y[:3], y[3])
    t = np.arange(0.0, float(y[3]) + 0.2, PERIOD_S)
    _, q, qd, _, _ = sextic.evaluate(coeffs, y[3], s_grid=np.clip(t / y[3], 0.0, 1.0))
    s_ref = actuation.joint_to_stroke(rig, q, check_limits=False)
    v_ref = actuation.stroke_jacobian(rig, q, check_limits=False) * qd
    return q[0], s_ref, v_ref, float(x[6])


def run(rig: Rig, digs: int, *, cpu: bool = False) -> tuple[list[int], list[int]]:
    """Replay ``digs`` held-out digs; returns per-period nanoseconds (frames, advance).

    ``cpu``: time with the thread's CPU clock instead of the wall clock (on a loaded machine
    it leaves out the time other processes held the core).
    """
    ids = [dict(rig.can.node_ids)[name] for name in AXES]
    vcu_client = VcuClient(rig.can.vcu_node_id)
    vcu_frame = vcu_client.command_frame(VcuCommand(enable=True))
    frames_ns: list[int] = []
    advance_ns: list[int] = []
    for dig in range(digs):
        q0, s_ref, v_ref, ground_y_m = _reference(rig, dig)
        terrain = Terrain(ground_y_m, (-0.5, 1.5), rig.bucket.width_m)
        m = HilCore(rig, q0, terrain, period_s=PERIOD_S)
        now = 0.0
        m.pending_frames(now)  # boot-up
        m.on_frame(COB_NMT, bytes([0x01, 0x00]), now)  # start all nodes
        for word in (0x06, 0x07, 0x0F):
            for node_id in ids:
                m.on_frame(0x300 + node_id, struct.pack("<Hb", word, 8), now)
        m.on_frame(*vcu_frame, now)
        m.advance(PERIOD_S)
        now += PERIOD_S
        targets_um = np.round(s_ref * 1e6).astype(np.int64).tolist()
        rates_um_s = np.round(v_ref * 1e6).astype(np.int64).tolist()
        clock = time.thread_time_ns if cpu else time.perf_counter_ns
        for k in range(len(targets_um)):
            t0 = clock()
            for axis, node_id in enumerate(ids):
                payload = struct.pack("<ii", targets_um[k][axis], rates_um_s[k][axis])
                m.on_frame(0x200 + node_id, payload, now)
            m.on_frame(*vcu_frame, now)
            m.on_frame(COB_SYNC, b"", now)
            m.pending_frames(now)
            t1 = clock()
            m.advance(PERIOD_S)
            t2 = clock()
            frames_ns.append(t1 - t0)
            advance_ns.append(t2 - t1)
            now += PERIOD_S
        if not all(n.firmware.state.name == "OPERATION_ENABLED" for n in m.nodes):
            raise RuntimeError(f"dig {dig}: a drive left OPERATION ENABLED; the run is not valid")
    return frames_ns, advance_ns


def _stats_us(ns: list[int]) -> tuple[float, float]:
    values = sorted(ns)
    p99 = values[min(len(values) - 1, int(0.99 * len(values)))]
    return statistics.median(values) * 1e-3, p99 * 1e-3


def main() -> None:
    """Command line: print median and p99 in microseconds per SYNC period."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--digs", type=int, default=2, help="held-out digs per repeat")
    parser.add_argument("--repeats", type=int, default=3, help="independent repeats")
    parser.add_argument(
        "--cpu", action="store_true", help="thread CPU time instead of wall time (loaded hosts)"
    )
    args = parser.parse_args()
    rig = load_rig(RIG)
    print(
        f"rig {rig.name}, servo period {rig.drives.servo_period_s * 1e6:.0f} us, "
        f"SYNC period {PERIOD_S * 1e3:.0f} ms; {'CPU' if args.cpu else 'wall'} us per period "
        "(median / p99)"
    )
    best = None
    for r in range(args.repeats):
        frames_ns, advance_ns = run(rig, args.digs, cpu=args.cpu)
        total_ns = [a + b for a, b in zip(frames_ns, advance_ns, strict=True)]
        fa, fb = _stats_us(frames_ns)
        aa, ab = _stats_us(advance_ns)
        ta, tb = _stats_us(total_ns)
        print(
            f"repeat {r}: {len(total_ns)} periods  advance {aa:7.1f} / {ab:7.1f}  "
            f"frames {fa:6.1f} / {fb:6.1f}  total {ta:7.1f} / {tb:7.1f}"
        )
        if best is None or ta < best[4]:
            best = (aa, ab, fa, fb, ta, tb)
    assert best is not None
    aa, ab, fa, fb, ta, tb = best
    print(
        f"best repeat: advance {aa:.1f} / {ab:.1f} us, frames {fa:.1f} / {fb:.1f} us, "
        f"total {ta:.1f} / {tb:.1f} us per period"
    )


if __name__ == "__main__":
    main()
