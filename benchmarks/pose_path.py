"""Benchmark: the pose-aware structure model against FE carried along a path with moves, and at off-grid poses.

    python benchmarks/pose_path.py [--element-size-mm 80] [--fast] [--dt-s 60] [--poses 5] [--plant K]
                                   [--no-remedy] [--at-table-reference]

Truth: FE models built at the poses a path visits (one per distinct pose), stepped with Crank–Nicolson on the
loads' times (the 16 h example day, ``hybridcomp.fem.loads.example_loads``) from the steady state of its first row
at the first pose; at every move the temperature field is carried with the bodies onto the next pose's mesh
(:func:`hybridcomp.fem.poses.carry_field`) and stepping goes on with that pose's model; the drift of each row is
that pose's FE drift.  Two paths: four 4 h holds at off-grid poses, and 8 h at the Z axis' lower end then 8 h at
its upper end (support poses: no interpolation error, so what is left is the pose history).  Besides, five
off-grid poses held all day (``benchmarks/pose_drift.py``'s poses), each against an FE model built there.

Prediction: the pose-aware reduced model (:func:`hybridcomp.rom.poses.reduce_at_poses`, star) run on the same
loads, ``drift_along(..., feedback=False)`` at the path's positions.  It runs every support pose's block as if
the machine stood there all day: along a path it ignores the pose history.  Beside it on the paths:

* ``FE at the pose all day``: the truth's own FE model of each hold run all day at that pose (what "history
  ignored" costs without any reduction or interpolation);
* ``remedy: reset at moves`` (unless ``--no-remedy``): offline here, not part of the library.  At every move each
  support pose's reduced state is set to the Galerkin projection (mass-weighted) of the field the blocks gave at
  the old pose (their fields, carried to the model's pose and weighted by the old pose's interpolation weights),
  carried onto that support pose's mesh; between moves the blocks run as before.  Its cost: the support poses'
  bases (rebuilt here as :func:`hybridcomp.rom.poses.pose_block` builds them, and checked against the model's
  blocks) and one (r_k × r_j) transfer matrix per pair of support poses, applied at a move.

Criterion per case and direction: the largest error ≤ max(0.3 µm, 5 % of the local range of the truth's drift),
the local range being the range within the hold (a path) or over the day (a pose held all day).  ``--plant K``
adds a planted error beside the prediction: support pose K's drift replaced by the model pose's (its block dropped),
judged alike (``within_limit``: ``*_planted``); at support pose K itself (K = 5: the Z axis' lower end, the first
hold of the second path) it must fail where the prediction passes.  ``--at-table-reference`` takes the drift at the
table reference instead of the table point under the tool.  Prints a table and a final JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as la

sys.path.insert(0, str(Path(__file__).parent))
from pose_drift import random_poses

from hybridcomp.fem.loads import example_loads
from hybridcomp.fem.model import build_model
from hybridcomp.fem.poses import carry_field
from hybridcomp.models import jsonio, load_machine
from hybridcomp.models.layout import Loads
from hybridcomp.rom.krylov import Reductor, orthonormal_extension, project
from hybridcomp.rom.machine import h_samples, reduce_model, system_from_model
from hybridcomp.rom.poses import drift_along, grid_of, pose_output_names, reduce_at_poses

from _table import table

#: the paths: (hours, pose) holds, in order
PATHS = {
    "4 x 4 h off-grid": ((4.0, {"X": -250.0, "Y": 150.0, "Z": -150.0}), (4.0, {"X": 280.0, "Y": -220.0, "Z": 120.0}),
                         (4.0, {"X": 120.0, "Y": 200.0, "Z": 180.0}), (4.0, {"X": -180.0, "Y": -90.0, "Z": -200.0})),
    "8 h Z low, 8 h Z high": ((8.0, {"X": 0.0, "Y": 0.0, "Z": -275.0}), (8.0, {"X": 0.0, "Y": 0.0, "Z": 275.0})),
}
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
    x, prev = "steady", None
    for (_, pose), (i0, i1) in zip(holds, rows):
        fe = fe_at(pose)
        if prev is not None:
            x = carry_field(prev, fe.mesh) @ x
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


class ResetAtMoves:
    """The offline remedy (module docstring): each support pose's reduced state reset at a move.

    ``T[k][j]`` (r_k × r_j) maps block j's state to block k's: block j's field carried to the model's pose, then to
    support pose k's mesh, projected there with the mass matrix.
    """

    def __init__(self, model, rom, prom, input_scale: np.ndarray):
        t0 = time.perf_counter()
        machine, grid = model.machine, grid_of(prom)
        orders = prom.meta["poses"]["orders"]
        self.offsets = np.cumsum([0] + orders)
        ns = int(prom.meta["n_sensors"])
        tol = np.r_[np.full(ns, rom.meta.get("tol_K", 0.05)), np.full(3, rom.meta.get("tol_um", 0.2) * 1e-6)]
        scale = np.where(input_scale > 0, input_scale, 1.0)
        h_range = tuple(rom.meta.get("h_range", (0.5, 2.0)))
        to_mid, to_k = [rom.V], [np.empty(0)]
        self.mismatch = 0.0
        for k in range(1, len(grid.poses)):  # as rom.poses.pose_block builds each support pose's basis
            fe = build_model(machine, grid.pose_mm(k), machine.mesh.element_size_mm)
            system = system_from_model(fe)
            V = la.qr(carry_field(model, fe.mesh) @ rom.V, mode="economic")[0]
            enrich = int(prom.meta["poses"]["enrich"])
            if enrich > 0:
                own = Reductor(system, tol, scale, h_samples(fe.h_W_m2K, h_range))
                V = np.hstack([V, orthonormal_extension(V, own.reduce(order=enrich).V)])
            sl = slice(self.offsets[k], self.offsets[k + 1])
            Mr = project(system, V)["M"]
            self.mismatch = max(self.mismatch, float(np.abs(Mr - prom.M[sl, sl]).max() / np.abs(Mr).max()))
            to_mid.append(carry_field(fe, model.mesh) @ V)
            MV = fe.M @ V
            to_k.append(np.linalg.solve(V.T @ MV, (carry_field(model, fe.mesh).T @ MV).T))
        M0V = model.M @ rom.V  # block 0's basis is the model's own: the mass-weighted projection onto it
        to_k[0] = np.linalg.solve(rom.V.T @ M0V, M0V.T)
        self.T = [[to_k[k] @ to_mid[j] for j in range(len(to_mid))] for k in range(len(to_mid))]
        self.grid = grid
        self.build_s = time.perf_counter() - t0

    def reset(self, x: np.ndarray, old_pose: dict) -> np.ndarray:
        """The state after a move from ``old_pose``: every support pose's block from the blended field."""
        w = self.grid.weights(old_pose)
        o = self.offsets
        blocks = [x[o[j]:o[j + 1]] for j in range(len(w))]
        y = x.copy()
        for k in range(len(w)):
            y[o[k]:o[k + 1]] = sum(w[j] * (self.T[k][j] @ blocks[j]) for j in range(len(w)) if w[j] != 0.0)
        return y


def rom_path(prom, U: np.ndarray, time_s: np.ndarray, holds, rows, remedy: ResetAtMoves | None) -> np.ndarray:
    """The pose-aware model's outputs along a path, integrated hold by hold (reset at moves with ``remedy``)."""
    Y = np.empty((time_s.size, prom.C.shape[0]))
    x = "steady"
    for h, (i0, i1) in enumerate(rows):
        if h > 0 and remedy is not None:
            x = remedy.reset(x, holds[h - 1][1])
        Y[i0:i1 + 1], x = prom.integrate(time_s[i0:i1 + 1], U[i0:i1 + 1], initial=x)
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
    p.add_argument("--plant", type=int, default=None, metavar="K",
                   help="plant an error: support pose K's drift replaced by the model pose's")
    p.add_argument("--no-remedy", action="store_true", help="skip the offline reset-at-moves remedy")
    p.add_argument("--at-table-reference", action="store_true",
                   help="the drift at the table reference, not at the table point under the tool (under_tool off)")
    a = p.parse_args(argv)
    h_mm, dt_s = (200.0, 300.0) if a.fast else (a.element_size_mm, a.dt_s)
    m = load_machine("vmc800")
    if a.plant is not None and not 1 <= a.plant <= 2 * len(m.axes):  # the star's support poses after the model's
        p.error(f"--plant must name a support pose 1..{2 * len(m.axes)}, got {a.plant}")
    if a.at_table_reference:
        m = dataclasses.replace(m, table_under_tool=False)
    loads = example_loads(m, 16.0, dt_s)
    nt = loads.time_s.size
    cost = {}
    t0 = time.perf_counter()
    model = build_model(m, None, h_mm)
    rom = reduce_model(model)
    scale = np.abs(m.layout().inputs(example_loads(m, 16.0, 60.0))).max(axis=0)
    prom = reduce_at_poses(model, rom, "star", input_scale=scale)
    cost["pose_rom_s"] = time.perf_counter() - t0
    cost["pose_rom_order"] = prom.order
    grid = grid_of(prom)
    U = prom.layout().inputs(loads.names, loads.values)
    remedy = None
    if not a.no_remedy:
        remedy = ResetAtMoves(model, rom, prom, scale)
        cost["remedy_build_s"] = remedy.build_s
        cost["remedy_transfer_floats"] = int(sum(T.size for row in remedy.T for T in row))
        cost["remedy_basis_mismatch"] = remedy.mismatch
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
    ok = {"paths": True, "poses": True}
    if remedy is not None:
        ok["paths_remedy"] = True
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
        cand = {"pose-aware ROM": drift_along(prom, Y_day, P, feedback=False)}
        if a.plant is not None:
            cand[PLANTED] = drift_along(prom, planted(prom, Y_day, a.plant), P, feedback=False)
        allday = np.empty((nt, 3))
        for (_, pose), (i0, i1) in zip(holds, rows):
            allday[i0:i1 + 1] = all_day(pose)[i0:i1 + 1]
        cand["FE at the pose all day"] = allday
        if remedy is not None:
            Yr = rom_path(prom, U, loads.time_s, holds, rows, remedy)
            cand["remedy: reset at moves"] = drift_along(prom, Yr, P, feedback=False)
        for h, ((_, pose), (i0, i1)) in enumerate(zip(holds, rows)):
            s = slice(i0, i1 + (h == len(rows) - 1))  # a move's row belongs to the new hold
            label = f"{h + 1}: " + " ".join(f"{k}={v:g}" for k, v in pose.items())
            rec = judge(name, label, truth[s], {k: v[s] for k, v in cand.items()})
            ok["paths"] &= rec["pose-aware ROM"]["ok"]
            if a.plant is not None:
                ok["paths_planted"] &= rec[PLANTED]["ok"]
            if remedy is not None:
                ok["paths_remedy"] &= rec["remedy: reset at moves"]["ok"]
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
          f"{'' if a.plant is None else f', planted: support pose {a.plant} dropped'} "
          f"(limit per direction: max(0.3 um, 5 % of the local range))")
    print(table(rows_out, list(rows_out[0])))
    print("cost: " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in cost.items()))
    print(jsonio.dumps({"benchmark": "pose_path", "nodes": model.n, "element_size_mm": h_mm, "dt_s": dt_s,
                        "table_point": "under the tool" if m.table_under_tool else "table reference", "plant": a.plant,
                        "within_limit": ok, "cost": cost, "cases": records}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
