"""Trace → loads → FE: a machine's axis and spindle trace becomes boundary conditions and a transient FE run.

A four-hour trace is made here (X roughing at 70 % feed for two hours with the spindle at 60 %, then a
standstill), sampled at 1 Hz, and written as a trace CSV; the histogram generator turns it into heat
powers per source and rail segment every 5 min, and the FE model of the demonstrator steps through them.

    python examples/trace_to_fe.py --out trace_to_fe/
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

import hybridcomp as hc


def write_example_trace(path: Path, machine, hours: float = 4.0) -> Path:
    """A trace CSV [time_s, x_mm, y_mm, z_mm, spindle_rpm, Tamb_degC] at 1 Hz: X busy for the first half."""
    x_axis = next(a for a in machine.axes if a.name == "X")
    lo, hi = x_axis.travel_mm
    t = np.arange(0.0, hours * 3600.0 + 0.5)
    busy = t < hours * 1800.0
    period_s = 2 * (hi - lo) / (0.7 * x_axis.max_feed_mm_min / 60.0)  # back and forth at 70 % feed
    x = np.where(busy, lo + (hi - lo) * np.abs(((t / period_s) % 1.0) * 2 - 1), 0.5 * (lo + hi))
    spindle = np.where(busy, 0.6 * machine.spindle_max_speed_rpm, 0.0)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", "Tamb_degC"])
        for k in range(t.size):
            w.writerow([f"{t[k]:g}", f"{x[k]:.3f}", "0", "0", f"{spindle[k]:g}", "20.5"])
    return path


def main(argv=None) -> hc.SimulationResult:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("trace_to_fe"), help="output folder")
    p.add_argument("--element-size-mm", type=float, default=150.0, help="FE element size [mm]")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    machine = hc.load_machine("vmc800")
    trace = write_example_trace(args.out / "trace.csv", machine)
    loads = hc.boundary_conditions(machine, hc.increments_from_trace(trace, machine, 300.0))
    hc.write_loads(args.out / "loads.csv", loads)
    model = hc.build_model(machine, element_size_mm=args.element_size_mm)
    result = hc.simulate(model, loads)  # TR-BDF2, sub-steps until the time error is within tolerance
    hc.write_outputs(args.out / "outputs.csv", result.time_s, result.sensor_names, result.sensors_degC, result.drift_um)
    dz = result.drift_um[:, 2]
    print(f"{len(loads.time_s)} loads rows, {model.n} nodes; largest |dz| {np.abs(dz).max():.1f} µm "
          f"at {result.time_s[np.argmax(np.abs(dz))] / 3600:.1f} h (time error estimate "
          f"{result.time_error['estimate_drift_um']:.3f} µm); files in {args.out}")
    return result


if __name__ == "__main__":
    main()
