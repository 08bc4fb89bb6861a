"""Benchmark: how the pose history's answer depends on the load step it runs on (60 s against 300 s loads).

    python benchmarks/pose_history_step.py --demo DEMO_FOLDER

Reads a demo folder (``hybridcomp demo --out DEMO_FOLDER``): its pose-aware structure model
(``models_nominal/structure_poses.rom.npz``) and the job-shop day's controller trace
(``hybrid_nominal/jobshop_controller_trace.csv``).  The trace's loads are made at 60 s and at 300 s steps
(the same histogram pipeline, each step's mean), the support poses' weights of every step from the trace's
samples (:func:`hybridcomp.scenario.trace_step_weights`), and the pose-aware model is run along the path with
its pose history (``history="moves"``) and without it (``"none"``).  Printed: the largest difference of the
drift at every support pose, over the day on a quarter-hour clock, between the two load steps.  There is no
truth here: the two runs describe the same machine and the same path, so a difference is the model's own
dependence on its step (the truth of ``benchmarks/compensation.py`` runs at 60 s, the daemon at 300 s).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _table import table


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demo", type=Path, required=True, help="a demo's output folder")
    ap.add_argument("--steps-s", default="60,300", help="the two load steps [s]")
    args = ap.parse_args()
    from hybridcomp.histogram.bcs import boundary_conditions
    from hybridcomp.histogram.increments import increments_from_trace
    from hybridcomp.models.layout import in_model_order
    from hybridcomp.models.loader import load_machine
    from hybridcomp.rom import poses as rp
    from hybridcomp.rom.reduced import load_rom
    from hybridcomp.scenario import trace_positions, trace_samples, trace_step_weights

    rom_path = args.demo / "models_nominal" / "structure_poses.rom.npz"
    trace = args.demo / "hybrid_nominal" / "jobshop_controller_trace.csv"
    for f in (rom_path, trace):
        if not f.is_file():
            ap.error(f"--demo {args.demo}: {f.name} is missing (run 'hybridcomp demo --out {args.demo}' first)")
    machine = load_machine("vmc800")
    prom = load_rom(rom_path, machine)
    grid = rp.grid_of(prom)
    ts, P = trace_samples(machine, trace)
    support = np.array([[grid.pose_mm(k)[a] for a in grid.axes] for k in range(len(grid.poses))])
    steps = [float(v) for v in args.steps_s.split(",")]
    drift, wall = {}, {}
    for dt in steps:
        loads = in_model_order(boundary_conditions(machine, increments_from_trace(trace, machine, dt)),
                               machine).resample(dt)
        t = loads.time_s
        U = prom.layout().inputs(list(loads.names), loads.values, "loads")
        poses = trace_step_weights(grid, ts, P, t)
        for history in ("moves", "none"):
            t0 = time.perf_counter()
            Y, _ = rp.integrate_along(prom, t, U, trace_positions(ts, P, t), history=history,
                                      weights=poses)
            wall[(dt, history)] = time.perf_counter() - t0
            tc = np.arange(0.0, t[-1] + 1.0, 900.0)
            Yc = np.column_stack([np.interp(tc, t, Y[:, j]) for j in range(Y.shape[1])])
            drift[(dt, history)] = np.stack([rp.drift_along(prom, Yc, np.repeat(s[None], tc.size, 0))
                                             for s in support])
    rows, out = [], {}
    for history in ("moves", "none"):
        d = np.abs(drift[(steps[0], history)] - drift[(steps[1], history)]).max(axis=(0, 1))
        out[history] = [float(v) for v in d]
        rows.append({"history": history, "max |diff| dx / dy / dz [µm]": " / ".join(f"{v:.2f}" for v in d),
                     "wall [s]": " / ".join(f"{wall[(dt, history)]:.1f}" for dt in steps)})
    print(table(rows, list(rows[0])))
    print(json.dumps({"benchmark": "pose_history_step", "steps_s": steps, "max_diff_um": out,
                      "support_poses": len(support)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
