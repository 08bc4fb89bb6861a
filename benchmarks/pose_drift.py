"""Benchmark: the drift at any pose, interpolated from support poses, against FE models built at that pose.

    python benchmarks/pose_drift.py [--element-size-mm 150] [--poses 5] [--seed 16] [--schemes star,grid]
                                    [--pose-models]

The job-shop day (16 h) is run by the pose-aware reduced model (:mod:`hybridcomp.rom.poses`: a reduced model per
support pose on its own FE model, star scheme) and its drift at 5 random off-grid poses, interpolated, is compared
with an FE model built and run at that pose.  Criterion per pose and direction: the largest error over the day
≤ 0.3 µm or ≤ 5 % of the drift's range there, whichever is larger.  Beside it: the drift of the mid pose alone
(what the model gave before), the other way of one thermal model with its field carried with the bodies to the
support poses (:func:`hybridcomp.fem.poses.pose_drift`, ``--schemes``), and with ``--pose-models`` full FE runs at
the support poses interpolated the same way (what the reduced models approximate).  Cost: building the pose-aware
reduced model against the single-pose one (FE build and reduction).  Prints a table and a final JSON line.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from hybridcomp.fem.model import build_model
from hybridcomp.fem.poses import pose_drift
from hybridcomp.histogram.scenarios import jobshop_loads
from hybridcomp.models import jsonio, load_machine
from hybridcomp.rom.machine import reduce_model
from hybridcomp.rom.poses import drift_along, grid_of, reduce_at_poses

from _table import table


def random_poses(machine, n: int, seed: int) -> list[dict[str, float]]:
    """``n`` poses uniformly inside the travel, each axis at least 10 % of its travel from the support levels."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        pose = {}
        for a in machine.axes:
            lo, hi = a.travel_mm
            x = rng.uniform(lo, hi)
            levels = (lo, a.mid_mm, hi)
            if min(abs(x - v) for v in levels) < 0.1 * (hi - lo):
                break
            pose[a.name] = round(float(x), 1)
        else:
            out.append(pose)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=150.0)
    p.add_argument("--poses", type=int, default=5)
    p.add_argument("--seed", type=int, default=16)
    p.add_argument("--schemes", default="star", help="carried-field schemes to compare (star, grid; '' for none)")
    p.add_argument("--pose-models", action="store_true",
                   help="also build a full FE model (own thermal run) at every star support pose and interpolate those")
    a = p.parse_args(argv)
    m = load_machine("vmc800")
    loads = jobshop_loads(m)
    nt = loads.time_s.size
    t0 = time.perf_counter()
    model = build_model(m, None, a.element_size_mm)
    cost = {"fe_build_s": time.perf_counter() - t0}
    t0 = time.perf_counter()
    rom = reduce_model(model)
    cost["rom_s"] = time.perf_counter() - t0
    cost["rom_order"] = rom.order
    single = cost["fe_build_s"] + cost["rom_s"]
    t0 = time.perf_counter()
    prom = reduce_at_poses(model, rom, "star")
    cost["pose_roms_s"] = time.perf_counter() - t0
    cost["pose_roms_order"] = prom.order
    cost["pose_roms_ratio"] = (single + cost["pose_roms_s"]) / single
    Y, _ = prom.integrate(loads.time_s, prom.layout().inputs(loads.names, loads.values))
    schemes = {}
    for scheme in filter(None, a.schemes.split(",")):
        t0 = time.perf_counter()
        schemes[scheme] = pose_drift(model, scheme)
        cost[f"{scheme}_s"] = time.perf_counter() - t0
        cost[f"{scheme}_poses"] = len(schemes[scheme].grid.poses)
        cost[f"{scheme}_ratio"] = (single + cost[f"{scheme}_s"]) / single
    base = model.simulate(loads, store_steps=tuple(range(nt)) if schemes else None)
    X = np.array([base.fields_K[i] for i in range(nt)]) if schemes else None
    pose_runs = None
    grid = grid_of(prom)
    if a.pose_models:
        t0 = time.perf_counter()
        pose_runs = [base.drift_um] + [build_model(m, grid.pose_mm(k), a.element_size_mm).simulate(loads).drift_um
                                       for k in range(1, len(grid.poses))]
        cost["pose_models_s"] = time.perf_counter() - t0
        cost["pose_models_ratio"] = (single + cost["pose_models_s"]) / single
    rows, records, passed = [], [], True
    for pose in random_poses(m, a.poses, a.seed):
        ref = build_model(m, pose, a.element_size_mm).simulate(loads).drift_um
        rng_um = np.ptp(ref, axis=0)
        limit = np.maximum(0.3, 0.05 * rng_um)
        cand = {"mid pose only": base.drift_um,
                "pose-aware ROM (star)": drift_along(prom, Y, np.array([[pose[n] for n in grid.axes]]), feedback=False)}
        cand |= {f"carried field ({scheme})": X @ pd.drift_rows(pose).T * 1e6 for scheme, pd in schemes.items()}
        if pose_runs is not None:
            cand["FE at the support poses (star)"] = np.tensordot(grid.weights(pose), np.array(pose_runs), axes=1)
        rec = {"pose_mm": pose, "range_um": rng_um.round(3).tolist(), "limit_um": limit.round(3).tolist()}
        for name, d in cand.items():
            err = np.abs(d - ref).max(axis=0)
            ok = bool(np.all(err <= limit))
            if name.startswith("pose-aware"):
                passed &= ok
            rec[name] = {"max_error_um": err.round(3).tolist(), "ok": ok}
            rows.append({"pose": " ".join(f"{k}={v:g}" for k, v in pose.items()), "method": name,
                         "err_dx_um": f"{err[0]:.3f}", "err_dy_um": f"{err[1]:.3f}", "err_dz_um": f"{err[2]:.3f}",
                         "range_um": " ".join(f"{v:.1f}" for v in rng_um), "ok": "yes" if ok else "no"})
        records.append(rec)
    print(f"drift at off-grid poses, job-shop day {loads.time_s[-1] / 3600:.0f} h, {model.n} nodes "
          f"(limit per direction: max(0.3 um, 5 % of the range))")
    print(table(rows, list(rows[0])))
    print("cost: " + ", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in cost.items()))
    print(jsonio.dumps({"benchmark": "pose_drift", "nodes": model.n, "element_size_mm": a.element_size_mm,
                        "pose_aware_rom_within_limit": passed, "cost": cost, "poses": records}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
