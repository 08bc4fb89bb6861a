"""Diagnose a CSV: what the model gets wrong on measured data, the named cause and the gain.

A "measured" CSV is made here from the structure model of a machine whose front spindle bearing
dissipates 1.5 × its nominal power (with sensor and gauge noise); the diagnosis runs the nominal model on
it, names the cause with its factor, and reports the validation fit before and after.

    python examples/diagnose_csv.py --out diagnose_csv/
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

import hybridcomp as hc
from hybridcomp.diagnose import diagnose


def write_measured(path: Path, machine, rom, source: str = "spindle_bearing_front", factor: float = 1.5) -> Path:
    """Loads of the example day, sensors [°C] and drift [µm] of the machine with ``source`` at ``factor`` × power."""
    loads = hc.example_loads(machine, duration_h=16.0, dt_s=300.0)
    real = loads.values.copy()
    real[:, loads.names.index(f"{source}_W")] *= factor
    res = rom.simulate(hc.Loads(loads.time_s, real, loads.names))
    rng = np.random.default_rng(1)
    cols = {"time_s": loads.time_s, **dict(zip(loads.names, loads.values.T))}
    cols |= {c: v + rng.normal(0, 0.02 if c.endswith("_degC") else 0.3, v.size)
             for c, v in res.columns().items() if c != "time_s"}
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        w.writerows(zip(*(np.char.mod("%.6g", v) for v in cols.values())))
    return path


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("diagnose_csv"), help="output folder")
    p.add_argument("--element-size-mm", type=float, default=150.0, help="FE element size [mm]")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    machine = hc.load_machine("vmc800")
    rom = hc.prepare_model(machine, element_size_mm=args.element_size_mm)
    measured = write_measured(args.out / "measured.csv", machine, rom)
    d = diagnose(machine, hc.read_measured(measured, machine), "0:60%", rom=rom)
    summary = hc.write_report(d, args.out / "diagnosis")
    print(f"verdict: {d.verdict}")
    for c in summary.get("causes", []):
        print(f"  {c['name']} of {c['target']}: {c['parameters']}")
    return summary


if __name__ == "__main__":
    main()
