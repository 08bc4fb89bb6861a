"""Diagnostic: which point's displacement the interpolation between support poses misses at off-grid poses.

    python benchmarks/pose_reference.py [--element-size-mm 80] [--scheme star] [--sweep AXIS]

FE only, no reduction and no pose history: every support pose and every target pose (the four off-grid poses of
``benchmarks/pose_path.py``) gets its own FE model, run to the steady state of the mean loads of the example day's
second half; the drift at a target is interpolated from the support poses with the pose-aware model's weights
(:meth:`hybridcomp.fem.poses.PoseGrid.weights`) and compared with the target's own FE drift.  What is
interpolated (each point's displacement from :func:`hybridcomp.fem.model.displacement_rows`):

* ``as the model``: TCP less the table point of each support pose (under the tool, continued past the table's
  edge), what :func:`hybridcomp.rom.poses.drift_along` interpolates;
* ``target's table point``: TCP less the table point of the *target* pose, taken in every support pose's own
  field (no continuation kink between the support poses: the same table points everywhere);
* ``table reference``: TCP less the table reference (judged against the target's TCP less its table reference);
* ``TCP alone``: the TCP's displacement.

``--sweep Y``: besides, the drift (as the model takes it) along that axis with the others at the model's pose, FE
at every position, against the star's quadratic through the travel's ends and the model's pose, and against
piecewise quadratics with a node where the tool crosses the table's edge (the pose where the table point under
the tool leaves the table, found by bisection; a support pose there and one between it and the travel's end).

No criterion: it shows where an interpolation error at a pose comes from (``benchmarks/pose_path.py`` judges
the model).  Prints a table (error [µm] dx / dy / dz per target and way) and a final JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from hybridcomp.fem.loads import example_loads
from hybridcomp.fem.model import build_model, displacement_rows
from hybridcomp.fem.poses import SCHEMES, piecewise_weights, pose_grid
from hybridcomp.fem.stepping import steady_state
from hybridcomp.models import jsonio, load_machine
from hybridcomp.models.geometry import table_point_weights

from _table import table

#: the off-grid poses of benchmarks/pose_path.py's paths
TARGETS = ({"X": -250.0, "Y": 150.0, "Z": -150.0}, {"X": 280.0, "Y": -220.0, "Z": 120.0},
           {"X": 120.0, "Y": 200.0, "Z": 180.0}, {"X": -180.0, "Y": -90.0, "Z": -200.0})
WAYS = ("as the model", "target's table point", "table reference", "TCP alone")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=80.0)
    p.add_argument("--scheme", choices=SCHEMES, default="star")
    p.add_argument("--sweep", default="", help="an axis to sweep (its drift against its interpolations)")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    machine = load_machine("vmc800")
    if a.sweep and a.sweep not in [x.name for x in machine.axes]:
        p.error(f"--sweep {a.sweep!r}: the machine's axes are {', '.join(x.name for x in machine.axes)}")
    machine = dataclasses.replace(machine, mesh=dataclasses.replace(machine.mesh, element_size_mm=a.element_size_mm))
    U = machine.layout().inputs(example_loads(machine, 16.0, 60.0))
    u = U[U.shape[0] // 2:].mean(axis=0)
    mid = build_model(machine, None, a.element_size_mm)
    grid = pose_grid(mid, a.scheme)
    supports = [grid.pose_mm(k) for k in range(len(grid.poses))]
    target_points = [[q for q, _ in table_point_weights(machine, t)] for t in TARGETS]
    extra = [q for pts in target_points for q in pts]

    def run(pose, model=None):
        """Displacements [µm] of TCP, table reference, the pose's own table points, then every target's points."""
        model = model or build_model(machine, pose, a.element_size_mm)
        own = table_point_weights(machine, pose)
        R = displacement_rows(model, [machine.tcp, machine.table_reference, *(q for q, _ in own), *extra])
        d = R @ steady_state(model, u) * 1e6
        return d, [w for _, w in own]

    at_support = [run(pose, mid if k == 0 else None) for k, pose in enumerate(supports)]
    rows, out = [], {}
    for ti, target in enumerate(TARGETS):
        d, w_own = run(target)
        W = grid.weights(target)
        offset = sum(len(x) for x in target_points[:ti])  # the target's table points among every pose's extras
        truth = {"as the model": d[0] - at(d, 2, w_own), "target's table point": d[0] - at(d, 2, w_own),
                 "table reference": d[0] - d[1], "TCP alone": d[0]}
        interp = {
            "as the model": sum(W[k] * (s[0] - at(s, 2, ws)) for k, (s, ws) in enumerate(at_support)),
            "target's table point": sum(W[k] * (s[0] - at(s, 2 + len(ws) + offset, w_own))
                                        for k, (s, ws) in enumerate(at_support)),
            "table reference": sum(W[k] * (s[0] - s[1]) for k, (s, _) in enumerate(at_support)),
            "TCP alone": sum(W[k] * s[0] for k, (s, _) in enumerate(at_support)),
        }
        name = ", ".join(f"{k} {v:g}" for k, v in target.items())
        out[name] = {}
        for way in WAYS:
            err = interp[way] - truth[way]
            out[name][way] = [float(v) for v in err]
            rows.append({"target": name, "interpolated": way,
                         "error dx / dy / dz [µm]": " / ".join(f"{v:+.2f}" for v in err),
                         "drift there dx / dy / dz [µm]": " / ".join(f"{v:.2f}" for v in truth[way])})
    print(f"vmc800 at {a.element_size_mm:g} mm, {a.scheme} ({len(supports)} support poses), steady state of the "
          f"example day's second half's mean loads")
    print(table(rows, ["target", "interpolated", "error dx / dy / dz [µm]", "drift there dx / dy / dz [µm]"]))
    sweep = _sweep(machine, a.element_size_mm, u, grid, a.sweep, mid) if a.sweep else None
    print(jsonio.dumps({"benchmark": "pose_reference", "element_size_mm": a.element_size_mm, "scheme": a.scheme,
                        "wall_s": time.perf_counter() - t0, "errors_um": out, "sweep": sweep}))
    return 0


def at(disp, first: int, weights) -> object:
    """The weighted sum of the displacements ``disp[first]``, ``disp[first + 1]``, … (a drift's table point)."""
    return sum(w * disp[first + i] for i, w in enumerate(weights))


def _edge_crossing(machine, axis: str, lo: float, hi: float) -> float | None:
    """The position of ``axis`` in (lo, hi) where the tool leaves the table (others at mid travel), or None."""
    def off(x):
        return len(table_point_weights(machine, {axis: x})) > 1

    if off(lo) == off(hi):
        return None
    for _ in range(40):
        m = 0.5 * (lo + hi)
        lo, hi = (m, hi) if off(m) == off(lo) else (lo, m)
    return 0.5 * (lo + hi)


def _sweep(machine, size_mm: float, u, grid, axis: str, mid) -> dict:
    """The drift along ``axis`` (FE at every position) against the star's quadratic and piecewise quadratics."""
    i = grid.axes.index(axis)
    (lo, hi), m0 = grid.travel_mm[i], grid.model_pose_mm[i]
    edge = _edge_crossing(machine, axis, lo, m0)
    if edge is None:
        edge = _edge_crossing(machine, axis, m0, hi)
    edge = None if edge is None else round(edge, 1)
    xs = sorted(set(np.round(np.linspace(lo, hi, 27), 1).tolist()) | ({edge} if edge else set()))
    if edge is not None:
        end = lo if edge < m0 else hi
        xs = sorted(set(xs) | {0.5 * (end + edge)})

    def drift(x):
        model = mid if abs(x - m0) < 1e-9 else build_model(machine, {axis: x}, size_mm)
        return model.G @ steady_state(model, u) * 1e6

    D = {x: drift(x) for x in xs}
    D[m0] = drift(m0)

    def through(x, levels):  # the piecewise quadratic the pose-aware model interpolates with
        return sum(w * D[n] for w, n in zip(piecewise_weights(x, levels), levels))

    # with the edge: one segment from the travel's end to the edge (its midpoint between), one on to the other end
    pieces = (lo, m0, hi) if edge is None else tuple(sorted({lo, hi, m0, edge, 0.5 * ((lo if edge < m0 else hi) + edge)}))
    rows, worst = [], {"star quadratic": np.zeros(3), "piecewise, a node at the edge": np.zeros(3)}
    for x in xs:
        star, piece = through(x, (lo, m0, hi)), through(x, pieces)
        e_star, e_piece = star - D[x], piece - D[x]
        worst["star quadratic"] = np.maximum(worst["star quadratic"], np.abs(e_star))
        worst["piecewise, a node at the edge"] = np.maximum(worst["piecewise, a node at the edge"], np.abs(e_piece))
        rows.append({axis: f"{x:g}", "FE drift dx / dy / dz [µm]": " / ".join(f"{v:.3f}" for v in D[x]),
                     "star quadratic error": " / ".join(f"{v:+.2f}" for v in e_star),
                     "piecewise error": " / ".join(f"{v:+.2f}" for v in e_piece)})
    print(f"\nthe drift along {axis} (the other axes at the model's pose); the tool leaves the table at "
          + (f"{axis} = {edge:.1f} mm" if edge is not None else "no position of the travel"))
    print(table(rows, [axis, "FE drift dx / dy / dz [µm]", "star quadratic error", "piecewise error"]))
    return {"axis": axis, "edge_mm": edge, "largest_error_um": {k: [float(v) for v in w] for k, w in worst.items()}}


if __name__ == "__main__":
    sys.exit(main())
