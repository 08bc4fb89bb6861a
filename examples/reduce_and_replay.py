"""Reduce → monitor replay: the structure model watches a replayed trace and the active CDs compensate it.

The demonstrator's FE model is reduced to a structure model; a CD set is fitted on the structure model's
run of the example working day and stored as the active set of a CD database; a two-hour trace (X and the
spindle busy, sensors from the structure model) is replayed through the monitoring daemon, which writes
an offset every 5 s of machine time and checks every 15 min whether the set still fits.

    python examples/reduce_and_replay.py --out reduce_and_replay/      (needs SQLAlchemy: pip install ".[db]")
"""

from __future__ import annotations

import argparse
import asyncio
import csv
from pathlib import Path

import numpy as np

import hybridcomp as hc
from hybridcomp.chardiag import pose_key
from hybridcomp.histogram.increments import increments_from_samples
from hybridcomp.histogram.trace import samples
from hybridcomp.monitor import MemorySink, ReplaySource, parse_config


def replay_trace(path: Path, machine, rom, hours: float = 2.0) -> tuple[Path, np.ndarray, np.ndarray]:
    """A trace CSV at 10 s: X moving and the spindle at 60 % for the first hour; sensors from the structure model.

    Returns the file, the sample times [s] and the structure model's drift at them [µm] (what compensation should undo).
    """
    t = np.arange(0.0, hours * 3600.0 + 5.0, 10.0)
    busy = t < 3600.0
    x = np.where(busy, 300.0 * np.sin(2 * np.pi * t / 97.0), 0.0)
    s = samples(machine, t, {"X": x, "Y": np.zeros_like(t), "Z": np.zeros_like(t)},
                np.where(busy, 0.6 * machine.spindle_max_speed_rpm, 0.0), air_degC={"Tamb_degC": np.full(t.size, 20.0)})
    res = rom.simulate(hc.boundary_conditions(machine, increments_from_samples(machine, s, 300.0)), hold="step")
    T = np.column_stack([np.interp(t, res.time_s, res.sensors_degC[:, j]) for j in range(len(res.sensor_names))])
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", *(f"{n}_degC" for n in res.sensor_names), "Tamb_degC"])
        for k in range(t.size):
            w.writerow([f"{t[k]:g}", *(f"{v:.4f}" for v in s.position_mm[k]), f"{s.spindle_rpm[k]:g}",
                        *(f"{v:.5f}" for v in T[k]), "20"])
    return path, t, np.column_stack([np.interp(t, res.time_s, res.drift_um[:, j]) for j in range(3)])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("reduce_and_replay"), help="output folder")
    p.add_argument("--element-size-mm", type=float, default=200.0, help="FE element size [mm]")
    args = p.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)

    machine = hc.load_machine("vmc800")
    pose = machine.default_pose_mm()
    model = hc.build_model(machine, pose, element_size_mm=args.element_size_mm)
    rom = hc.reduce_model(model, order=40, keep_basis=False, check_loads=hc.example_loads(machine, 1.0, 600.0))
    rom_path = hc.save_rom(out / "structure.rom.npz", rom)

    day = rom.simulate(hc.example_loads(machine))  # the training run of the CD set
    cds = hc.fit_cd_set(day.columns(), machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose,
                        load_case="example day")
    db_path = out / "cd.db"
    db_path.unlink(missing_ok=True)
    db = hc.CDDatabase(db_path)
    db.activate(machine.name, pose_key(pose), db.add_set(cds, "example day"), "CDs of the example day", 0.0)

    trace, t, drift_um = replay_trace(out / "trace.csv", machine, rom)
    cfg = parse_config({"monitor": {"machine": "vmc800", "database": str(db_path), "rom": str(rom_path),
                                    "pose_mm": dict(pose)},
                        "source": {"kind": "replay", "path": str(trace), "speed": 0}, "sink": {"kind": "none"},
                        "regeneration": {"enabled": False}}, "example", out)
    sink = MemorySink()
    monitor = hc.Monitor(cfg, machine, rom, db, pose_key(pose))
    asyncio.run(hc.run_monitor(cfg, monitor, ReplaySource(trace, machine, 0.0), sink))
    db.close()
    offsets = np.array([[r.dx_um, r.dy_um, r.dz_um] for r in sink.rows])
    times = np.array([r.time_s for r in sink.rows])
    residual = np.column_stack([np.interp(times, t, drift_um[:, j]) for j in range(3)]) - offsets
    rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    print(f"structure model of order {rom.order}; {len(sink.rows)} offsets over {times[-1] / 3600:.1f} h, "
          f"{monitor.counters.monitorings} monitoring steps; drift up to {np.abs(drift_um).max():.1f} µm, "
          f"compensated to {rms:.2f} µm RMS (3D)")
    return {"offsets_um": offsets, "time_s": times, "drift_um": drift_um, "residual_rms_um": rms}


if __name__ == "__main__":
    main()
