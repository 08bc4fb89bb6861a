"""Effect of the increment length on the TCP drift: the job-shop day, G-code → histogram → FE.

For increments of 1, 5, 15 and 60 min the day's loads CSV is built from its
G-code (with the day's workshop air), simulated on the CSV's own times
(backward Euler applies each increment's mean over exactly that increment),
and the drift is compared at every whole hour with the 1 min case.

    python benchmarks/histogram_increments.py [--element-size-mm 80] [--power mean|factor]

Prints a table and a final JSON line.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from hybridcomp.fem.loads import Loads, input_columns
from hybridcomp.fem.model import build_model
from hybridcomp.fem.transient import simulate
from hybridcomp.histogram import boundary_conditions, increments_from_motion, parse_gcode
from hybridcomp.histogram.scenarios import jobshop_ambient, jobshop_program
from hybridcomp.models import jsonio, load_machine

INCREMENTS_S = (60, 300, 900, 3600)


def full_inputs(machine, loads: Loads) -> Loads:
    """All model input columns; an omitted zone column is the reference temperature."""
    cols = input_columns(machine)
    U = np.full((len(loads.time_s), len(cols)), machine.reference_temperature_degC)
    for j, c in enumerate(cols):
        if c in loads.names:
            U[:, j] = loads.values[:, loads.names.index(c)]
        elif c.endswith("_W"):
            U[:, j] = 0.0
    return Loads(loads.time_s, U, cols)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=80.0)
    p.add_argument("--power", choices=("mean", "factor"), default="mean")
    a = p.parse_args(argv)
    m = load_machine("vmc800")
    motion = parse_gcode(jobshop_program(m), m)
    air = {"Tamb_degC": jobshop_ambient(m)}
    model = build_model(m, None, a.element_size_mm)
    hours_s = np.arange(0.0, 16.0 + 1e-9, 1.0) * 3600
    drift_at_hours = {}
    heat_J = {}
    for inc_s in INCREMENTS_S:
        loads = full_inputs(m, boundary_conditions(m, increments_from_motion(m, motion, inc_s, air_degC=air), a.power))
        res = simulate(model, loads.time_s, m.layout().inputs(loads))
        drift_at_hours[inc_s] = np.column_stack([np.interp(hours_s, res.time_s, res.drift_um[:, j]) for j in range(3)])
        w = [j for j, c in enumerate(loads.names) if c.endswith("_W")]
        heat_J[inc_s] = float(np.sum(loads.values[1:, w].sum(axis=1) * np.diff(loads.time_s)))
    ref = drift_at_hours[60]
    print(f"histogram_increments: job-shop day, vmc800, {model.n} nodes, --power {a.power}")
    print("increment_min | heat_vs_1min_% | max_abs_ddx_um | max_abs_ddy_um | max_abs_ddz_um | end_dz_um")
    out = {}
    for inc_s in INCREMENTS_S:
        d = np.abs(drift_at_hours[inc_s] - ref).max(axis=0)
        dh = 100 * (heat_J[inc_s] / heat_J[60] - 1)
        print(f"{inc_s / 60:g} | {dh:.2f} | {d[0]:.2f} | {d[1]:.2f} | {d[2]:.2f} | {drift_at_hours[inc_s][-1, 2]:.2f}")
        out[str(inc_s)] = {"heat_vs_1min_pct": dh, "max_abs_drift_diff_um": d.round(3).tolist(),
                           "end_drift_um": drift_at_hours[inc_s][-1].round(3).tolist()}
    print(jsonio.dumps({"benchmark": "histogram_increments", "nodes": model.n, "power": a.power,
                      "max_abs_drift_um": np.abs(ref).max(axis=0).round(3).tolist(), "increments": out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
