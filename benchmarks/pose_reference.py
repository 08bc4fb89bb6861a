"""Diagnostic: which point's displacement the interpolation between support poses misses at off-grid poses.

    python benchmarks/pose_reference.py [--element-size-mm 80] [--scheme star]

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

No criterion: it shows where an interpolation error at a pose comes from (``benchmarks/pose_path.py`` judges
the model).  Prints a table (error [µm] dx / dy / dz per target and way) and a final JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from hybridcomp.fem.loads import example_loads
from hybridcomp.fem.model import build_model, displacement_rows
from hybridcomp.fem.poses import SCHEMES, pose_grid
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
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    machine = load_machine("vmc800")
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

        def at(disp, first, weights):
            return sum(w * disp[first + i] for i, w in enumerate(weights))

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
    print(jsonio.dumps({"benchmark": "pose_reference", "element_size_mm": a.element_size_mm, "scheme": a.scheme,
                        "wall_s": time.perf_counter() - t0, "errors_um": out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
