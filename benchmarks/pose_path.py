"""Benchmark: the pose-aware structure model against FE carried along paths with moves, and at off-grid poses.

    python benchmarks/pose_path.py [--element-size-mm 80] [--fast] [--dt-s 60] [--poses 5] [--scheme star]
                                   [--plant K] [--at-table-reference]

Truth: FE models built at the poses a path visits (one per distinct pose), stepped with Crank–Nicolson on the
loads' times (the 16 h example day, ``hybridcomp.fem.loads.example_loads``) from the steady state of its first row
at the first pose; at every move the temperature field is carried with the bodies onto the next pose's mesh
(:func:`hybridcomp.fem.poses.carry_field`) and stepping goes on with that pose's model; the drift of each row is
that pose's FE drift.  Three paths: four 4 h holds at off-grid poses; 8 h at the Z axis' lower end then 8 h at
its upper end (support poses: no interpolation error, so what is left is the pose history); four off-grid poses
visited in turn for 15 min each all day (64 moves, a job shop's pattern).  Besides, five off-grid poses held all
day (``benchmarks/pose_drift.py``'s poses), each against an FE model built there.

Prediction: the pose-aware reduced model (:func:`hybridcomp.rom.poses.reduce_at_poses`; ``--scheme``: ``star``,
the model's pose and each axis' levels with the others at the model's pose, by default seven along the axes of
:func:`hybridcomp.fem.poses.auto_levels` (vmc800: Y and Z, 15 support poses) and three along the rest
(``--levels``), or ``grid``, the full 3^n grid) along the path
with its pose history (:func:`hybridcomp.rom.poses.integrate_along`, ``history="moves"``: the support poses'
blocks blended at every move with the weights of the pose left, :func:`~hybridcomp.rom.poses.blend_history`),
``drift_along(..., feedback=False)`` at the path's positions.  Beside it on the paths:

* ``blended every step`` (``history="steps"``): the blocks blended at every step, holds too;
* ``history ignored`` (``history="none"``): every support pose's block as if the machine stood there all day,
  what the model did before it followed the poses; the planted error of the history: it must fail;
* ``FE at the pose all day``: the truth's own FE model of each pose run all day there (what "history ignored"
  costs without any reduction or interpolation).

Criterion per case and direction: the largest error ≤ max(0.3 µm, 5 % of the local range of the truth's drift),
the local range being the range within the hold (the hold paths), over the rows at that pose (the 15 min path) or
over the day (a pose held all day).  ``--plant K`` adds a planted error beside the prediction: support pose K's
drift replaced by the model pose's (its block dropped), judged alike (``within_limit``: ``*_planted``); at support
pose K itself (the Z axis' lower end, the first hold of the second path: star K = 9 with the default levels or
Y=7, 5 with three levels along every axis; grid K = 13) it must fail where the prediction passes.  Support poses
are numbered as :func:`hybridcomp.fem.poses.support_poses_of` lists them, the model's pose 0, then each axis'
levels in order without the model's (star), or 1 .. 3^n − 1 in product order (grid).  ``--at-table-reference``
takes the drift at the table reference instead of the table point under the tool.  Prints a table and a final JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from pose_drift import random_poses

from hybridcomp.fem.loads import example_loads
from hybridcomp.fem.model import build_model
from hybridcomp.fem.poses import SCHEMES, carry_field, default_levels, parse_levels, support_poses_of
from hybridcomp.models import jsonio, load_machine
from hybridcomp.models.layout import Loads
from hybridcomp.rom.machine import reduce_model
from hybridcomp.rom.poses import drift_along, grid_of, integrate_along, pose_output_names, reduce_at_poses

from _table import table

#: the paths: (hours, pose) holds, in order
PATHS = {
    "4 x 4 h off-grid": ((4.0, {"X": -250.0, "Y": 150.0, "Z": -150.0}), (4.0, {"X": 280.0, "Y": -220.0, "Z": 120.0}),
                         (4.0, {"X": 120.0, "Y": 200.0, "Z": 180.0}), (4.0, {"X": -180.0, "Y": -90.0, "Z": -200.0})),
    "8 h Z low, 8 h Z high": ((8.0, {"X": 0.0, "Y": 0.0, "Z": -275.0}), (8.0, {"X": 0.0, "Y": 0.0, "Z": 275.0})),
}
#: four off-grid poses visited in turn, 15 min each, all day (judged per pose, not per hold)
CYCLE = "4 poses in turn, 15 min each"
PATHS[CYCLE] = tuple((0.25, PATHS["4 x 4 h off-grid"][i % 4][1]) for i in range(64))
#: the candidates along the paths: label → history of :func:`hybridcomp.rom.poses.integrate_along`
HISTORY = {"pose-aware ROM": "moves", "blended every step": "steps", "history ignored": "none"}
FLOOR_UM, SHARE = 0.3, 0.05
PLANTED = "planted: a support pose dropped"


def limit_um(truth_um: np.ndarray) -> np.ndarray:
    """max(0.3 µm, 5 % of the range) per direction."""
    return np.maximum(FLOOR_UM, SHARE * np.ptp(truth_um, axis=0))


def hold_rows(time_s: np.ndarray, holds) -> list[tuple[int, int]]:
    """Row ranges [i0, i1] of the holds; the move at a hold's start time belongs to the new hold (shared row)."""
    bounds = np.cumsum([0.0] + [h for h, _ in holds]) * 3600.0
    if abs(bounds[-1] - time_s[-1]) > 1e-6:
        raise ValueError(f"the holds last {bounds[-1] / 3600:g} h, the loads {time_s[-1] / 3600:g} h")
    idx = [int(np.argmin(np.abs(time_s - b))) for b in bounds]
    return list(zip(idx[:-1], idx[1:]))


def _slice(loads: Loads, i0: int, i1: int) -> Loads:
    return Loads(loads.time_s[i0:i1 + 1], loads.values[i0:i1 + 1], loads.names)


def fe_path(machine, loads: Loads, holds, rows, fe_at) -> np.ndarray:
    """The truth along a path (nt × 3) [µm]: FE at each hold's pose, the field carried at every move."""
    out = np.empty((loads.time_s.size, 3))
    x, prev, carry = "steady", None, {}
    for (_, pose), (i0, i1) in zip(holds, rows):
        fe = fe_at(pose)
        if prev is not None:
            if (id(prev), id(fe)) not in carry:
                carry[id(prev), id(fe)] = carry_field(prev, fe.mesh)
            x = carry[id(prev), id(fe)] @ x
        res = fe.simulate(_slice(loads, i0, i1), initial=x, scheme="theta", theta=0.5, store_steps=(i1 - i0,))
        out[i0:i1 + 1] = res.drift_um
        x, prev = res.fields_K[i1 - i0], fe
    return out


def planted(prom, Y: np.ndarray, k: int | None) -> np.ndarray:
    """The outputs with support pose ``k``'s drift replaced by the model pose's (a planted error); None: as is."""
    if k is None:
        return Y
    Y = Y.copy()
    ns = int(prom.meta["n_sensors"])
    Y[:, [prom.output_names.index(n) for n in pose_output_names(k)]] = Y[:, ns:ns + 3]
    return Y


def positions(grid, holds, rows, nt: int) -> np.ndarray:
    P = np.empty((nt, len(grid.axes)))
    for (_, pose), (i0, i1) in zip(holds, rows):
        P[i0:i1 + 1] = [pose[a] for a in grid.axes]
    return P


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=80.0)
    p.add_argument("--fast", action="store_true", help="200 mm elements and 5 min steps (while developing)")
    p.add_argument("--dt-s", type=float, default=60.0, help="loads and FE step [s] (default 60)")
    p.add_argument("--poses", type=int, default=5, help="off-grid poses held all day")
    p.add_argument("--seed", type=int, default=16)
    p.add_argument("--scheme", choices=SCHEMES, default="star",
                   help="support poses of the pose-aware model: star (each axis' levels, the others at the model's "
                        "pose) or grid (3^n) (default star)")
    p.add_argument("--plant", type=int, default=None, metavar="K",
                   help="plant an error: support pose K's drift replaced by the model pose's; K numbers the scheme's "
                        "support poses after the model's (star: each axis' levels in order, the model's pose left "
                        "out; grid 1..3^n - 1 in product order; vmc800: Z low is star 9 with the default levels, 5 "
                        "with --levels 3, grid 13)")
    p.add_argument("--levels", default=None, metavar="AXIS=N[,AXIS=N]",
                   help="N levels along an axis instead of 3 (hybridcomp.fem.poses.pose_grid; e.g. Y=7; a bare N: "
                        "along every axis; auto: hybridcomp.fem.poses.auto_levels; default: auto with the star, as "
                        "reduce --poses star, 3 with the grid)")
    p.add_argument("--at-table-reference", action="store_true",
                   help="the drift at the table reference, not at the table point under the tool (under_tool off)")
    a = p.parse_args(argv)
    h_mm, dt_s = (200.0, 300.0) if a.fast else (a.element_size_mm, a.dt_s)
    m = load_machine("vmc800")
    try:
        levels = default_levels(m, a.scheme) if a.levels is None else parse_levels(a.levels, [x.name for x in m.axes], m)
    except ValueError as exc:
        p.error(str(exc))
    counts = tuple(levels.get(x.name, 3) for x in m.axes)
    n_support = len(support_poses_of(counts, a.scheme)) - 1  # the support poses after the model's
    if a.plant is not None and not 1 <= a.plant <= n_support:
        p.error(f"--plant must name a {a.scheme} support pose 1..{n_support}, got {a.plant}")
    if a.at_table_reference:
        m = dataclasses.replace(m, table_under_tool=False)
    loads = example_loads(m, 16.0, dt_s)
    nt = loads.time_s.size
    cost = {}
    t0 = time.perf_counter()
    model = build_model(m, None, h_mm)
    rom = reduce_model(model)
    scale = np.abs(m.layout().inputs(example_loads(m, 16.0, 60.0))).max(axis=0)
    prom = reduce_at_poses(model, rom, a.scheme, input_scale=scale, levels=levels)
    cost["pose_rom_s"] = time.perf_counter() - t0
    cost["pose_rom_order"] = prom.order
    grid = grid_of(prom)
    U = prom.layout().inputs(loads.names, loads.values)
    cost["pose_transfer_floats"] = int(prom.pose_transfer.size)
    cache = {}

    def fe_at(pose):
        key = tuple(sorted(pose.items()))
        if key not in cache:
            cache[key] = build_model(m, pose, h_mm)
        return cache[key]

    days = {}

    def all_day(pose):
        key = tuple(sorted(pose.items()))
        if key not in days:
            days[key] = fe_at(pose).simulate(loads, scheme="theta", theta=0.5).drift_um
        return days[key]

    t0 = time.perf_counter()
    Y_day, _ = prom.integrate(loads.time_s, U)
    cost["rom_day_s"] = time.perf_counter() - t0
    rows_out, records = [], []
    ok = {"paths": True, "poses": True, "paths_blended_every_step": True, "paths_history_ignored": True}
    if a.plant is not None:
        ok |= {"paths_planted": True, "poses_planted": True}

    def judge(case, hold, truth, cand):
        lim = limit_um(truth)
        rec = {"case": case, "hold": hold, "range_um": np.ptp(truth, axis=0).round(3).tolist(),
               "limit_um": lim.round(3).tolist()}
        for name, d in cand.items():
            err = np.abs(d - truth).max(axis=0)
            good = bool(np.all(err <= lim))
            rec[name] = {"max_error_um": err.round(3).tolist(), "ok": good}
            rows_out.append({"case": case, "hold": hold, "method": name,
                             **{f"err_{c}_um": f"{e:.3f}" for c, e in zip(("dx", "dy", "dz"), err)},
                             "limit_um": " ".join(f"{v:.2f}" for v in lim), "ok": "yes" if good else "no"})
        records.append(rec)
        return rec

    t0 = time.perf_counter()
    for name, holds in PATHS.items():
        rows = hold_rows(loads.time_s, holds)
        truth = fe_path(m, loads, holds, rows, fe_at)
        P = positions(grid, holds, rows, nt)
        cand = {}
        for label, history in HISTORY.items():
            t1 = time.perf_counter()
            Y, _ = integrate_along(prom, loads.time_s, U, P, history=history)
            cost[f"rom_path_s[{history}]"] = max(cost.get(f"rom_path_s[{history}]", 0.0), time.perf_counter() - t1)
            cand[label] = drift_along(prom, Y, P, feedback=False)
            if label == "pose-aware ROM" and a.plant is not None:
                cand[PLANTED] = drift_along(prom, planted(prom, Y, a.plant), P, feedback=False)
        allday = np.empty((nt, 3))
        for (_, pose), (i0, i1) in zip(holds, rows):
            allday[i0:i1 + 1] = all_day(pose)[i0:i1 + 1]
        cand["FE at the pose all day"] = allday
        if name == CYCLE:  # judged per pose: every row at that pose (a move's row belongs to the new pose)
            groups = {}
            for (_, pose), (i0, i1) in zip(holds, rows):
                groups.setdefault(" ".join(f"{k}={v:g}" for k, v in pose.items()), []).extend(range(i0, i1))
            groups = {k: np.array(v) for k, v in groups.items()}
        else:
            groups = {f"{h + 1}: " + " ".join(f"{k}={v:g}" for k, v in pose.items()):
                      np.arange(i0, i1 + (h == len(rows) - 1)) for h, ((_, pose), (i0, i1)) in enumerate(zip(holds, rows))}
        for label, s_ in groups.items():
            rec = judge(name, label, truth[s_], {k: v[s_] for k, v in cand.items()})
            ok["paths"] &= rec["pose-aware ROM"]["ok"]
            ok["paths_blended_every_step"] &= rec["blended every step"]["ok"]
            ok["paths_history_ignored"] &= rec["history ignored"]["ok"]
            if a.plant is not None:
                ok["paths_planted"] &= rec[PLANTED]["ok"]
    for pose in random_poses(m, a.poses, a.seed):
        truth = all_day(pose)
        at = np.array([[pose[n] for n in grid.axes]])
        cand = {"pose-aware ROM": drift_along(prom, Y_day, at, feedback=False)}
        if a.plant is not None:
            cand[PLANTED] = drift_along(prom, planted(prom, Y_day, a.plant), at, feedback=False)
        rec = judge("held all day", " ".join(f"{k}={v:g}" for k, v in pose.items()), truth, cand)
        ok["poses"] &= rec["pose-aware ROM"]["ok"]
        if a.plant is not None:
            ok["poses_planted"] &= rec[PLANTED]["ok"]
    cost["truth_s"] = time.perf_counter() - t0
    cost["fe_models"] = len(cache)
    print(f"pose-aware model along paths and at off-grid poses, example day 16 h at {dt_s:g} s, {model.n} nodes "
          f"({h_mm:g} mm), drift at the {'table point under the tool' if m.table_under_tool else 'table reference'}"
          f", {a.scheme} ({len(grid.poses)} support poses)"
          f"{'' if a.plant is None else f', planted: support pose {a.plant} {grid.pose_mm(a.plant)} dropped'} "
          f"(limit per direction: max(0.3 um, 5 % of the local range))")
    print(table(rows_out, list(rows_out[0])))
    print("cost: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in cost.items()))
    print(jsonio.dumps({"benchmark": "pose_path", "nodes": model.n, "element_size_mm": h_mm, "dt_s": dt_s,
                        "scheme": a.scheme, "levels": levels,
                        "table_point": "under the tool" if m.table_under_tool else "table reference", "plant": a.plant,
                        "within_limit": ok, "cost": cost, "cases": records}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
