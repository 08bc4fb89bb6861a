"""Soak benchmark of the monitoring daemon: 7 days of 1 Hz machine data replayed as fast as possible.

The week is generated here: every day the bundled 16 h job-shop day (its
programme sampled at ``--rate-hz``) followed by 8 h standing still, the
workshop air swinging ±1.5 K over 24 h, and sensor temperatures T1…T8 from a
structure model (a ROM of the demonstrator at ``--element-size-mm``) driven by the
trace's own BCs. The CD database holds two CD sets fitted on the first day
(referenced at the cold start and at the hottest moment); every decision
assesses the active set and these candidates over the interval and the
forecasts.

The daemon runs in a fresh process (``python benchmarks/monitor_soak.py
--child ...``): replay at ``--speed`` (0: as fast as possible), JSON-lines
sink, SQLite database, regeneration off. Measured: wall time and the replay
factor (machine time / wall time), the time of every monitoring decision
(the active set's predicted error over the interval and the forecasts → search → decision → events →
state; the observer's model steps run between decisions), and the resident
memory (``VmRSS``) at every decision; the growth is the last value minus the
value after the first simulated day. Targets: factor ≥ 1000, growth ≤ 10 MB,
every decision ≤ 1 s.

    python benchmarks/monitor_soak.py [--days 7] [--rate-hz 1] [--repeats 3] [--speed 0]

Prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hybridcomp.models import jsonio

POSE = {"X": 0.0, "Y": 0.0, "Z": 0.0}


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def generate(out: Path, days: int, rate_hz: float, element_size_mm: float) -> dict:
    """ROM, trace CSV and CD database for the soak; returns their paths and sizes."""
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import fit_cd_set
    from hybridcomp.fem.model import build_model
    from hybridcomp.histogram.gcode import parse_gcode, sample_motion
    from hybridcomp.histogram.scenarios import jobshop_ambient, jobshop_program
    from hybridcomp.histogram.trace import Samples
    from hybridcomp.models import load_machine
    from hybridcomp.rom import save_rom
    from hybridcomp.rom.machine import reduce_model
    from hybridcomp.scenario import rom_sensor_temperatures

    machine = load_machine("vmc800")
    t0 = time.perf_counter()
    model = build_model(machine, POSE, element_size_mm)
    rom = reduce_model(model, order=60, keep_basis=False)
    rom_path = save_rom(out / "soak.rom.npz", rom)
    t_rom = time.perf_counter() - t0

    motion = parse_gcode(jobshop_program(machine), machine)
    amb = jobshop_ambient(machine)
    day_s = 86400.0
    work = sample_motion(motion, rate_hz)
    t_work = work.time_s
    n_day = int(round(day_s * rate_hz))
    t_day = np.arange(n_day) / rate_hz
    idx = np.clip(np.searchsorted(t_work, t_day, side="right") - 1, 0, len(t_work) - 1)
    busy = t_day <= t_work[-1]
    P_day = np.where(busy[:, None], np.column_stack([np.interp(t_day, t_work, work.position_mm[:, a]) for a in range(3)]),
                     work.position_mm[-1])
    S_day = np.where(busy, work.spindle_rpm[idx], 0.0)
    t = np.concatenate([t_day + d * day_s for d in range(days)] + [[days * day_s]])
    P = np.vstack([P_day] * days + [P_day[-1:]])
    S = np.concatenate([S_day] * days + [[0.0]])
    A = amb(t)[:, None]
    s = Samples(t, P, None, S, ("Tamb_degC",), A, np.arange(t.size) + 2)
    T = rom_sensor_temperatures(machine, rom, s, 300.0)
    trace = out / "week.csv"
    names = ["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", *(f"{p.name}_degC" for p in machine.sensors), "Tamb_degC"]
    block = np.column_stack([t, P, S, T, A])
    np.savetxt(trace, block, delimiter=",", header=",".join(names), comments="",
               fmt=["%.3f", "%.4f", "%.4f", "%.4f", "%.1f"] + ["%.4f"] * (T.shape[1] + 1))

    # two CD sets fitted on the first day: drift linear in T1 - T8
    first = t <= day_s
    d = T[first, 0] - T[first, 7]
    table = {f"{p.name}_degC": T[first, j] for j, p in enumerate(machine.sensors)}
    db_path = out / "soak.db"
    db = CDDatabase(db_path)
    hot = int(np.argmax(T[first, 0]))
    names_s = [p.name for p in machine.sensors]
    ids = {}
    for name, gain, ref in (("cold", (0.5, -1.0, -3.0), T[0]), ("warm", (0.4, -0.8, -2.5), T[hot])):
        tab = table | {"dx_um": gain[0] * d, "dy_um": gain[1] * d, "dz_um": gain[2] * d}
        cds = fit_cd_set(tab, machine=machine.name, machine_sha256=machine.sha256, pose_mm=POSE, load_case=name,
                         t_reference_degC=dict(zip(names_s, map(float, ref))))
        ids[name] = db.add_set(cds, name)
    db.activate(machine.name, pose_key(POSE), ids["cold"], "initial")
    db.close()
    return {"rom": str(rom_path), "trace": str(trace), "db": str(db_path), "rows": int(t.size),
            "trace_MB": trace.stat().st_size / 1e6, "rom_order": rom.order, "setup_rom_s": t_rom}


def child(args) -> None:
    """One soak run in this (fresh) process; prints one JSON line."""
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.models import load_machine
    from hybridcomp.monitor.config import parse_config
    from hybridcomp.monitor.daemon import Monitor, run_monitor
    from hybridcomp.monitor.sinks import JsonlSink
    from hybridcomp.monitor.sources import ReplaySource
    from hybridcomp.monitor.store import MonitorStore
    from hybridcomp.rom import load_rom

    work = Path(args.work)
    run_dir = Path(tempfile.mkdtemp(dir=work))
    db_path = run_dir / "soak.db"
    for suffix in ("", "-wal", "-shm"):  # a private copy of the prepared database per run
        src = Path(str(work / "soak.db") + suffix)
        if src.exists():
            Path(str(db_path) + suffix).write_bytes(src.read_bytes())
    machine = load_machine("vmc800")
    rom = load_rom(work / "soak.rom.npz", machine)
    cfg = parse_config({
        "monitor": {"machine": "vmc800", "database": str(db_path), "rom": str(work / "soak.rom.npz"), "pose_mm": POSE},
        "source": {"kind": "replay", "path": str(work / "week.csv"), "speed": args.speed},
        "sink": {"kind": "jsonl", "path": str(run_dir / "offsets.jsonl")},
        "regeneration": {"enabled": False},
    }, "soak", run_dir)
    db = CDDatabase(db_path)
    mon = Monitor(cfg, machine, rom, db, pose_key(POSE))
    times, rss, machine_t = [], [], []
    process = mon.process

    def timed(r):
        """A reading that closes a monitoring interval: its time (the decision's included) and the memory then."""
        n, t0 = mon.counters.monitorings, time.perf_counter()
        out = process(r)
        if mon.counters.monitorings > n:
            times.append(time.perf_counter() - t0)
            rss.append(rss_mb())
            machine_t.append(mon.s.last_time_s)
        return out

    mon.process = timed
    rss0 = rss_mb()
    t0 = time.perf_counter()
    sink = JsonlSink(run_dir / "offsets.jsonl")
    res = asyncio.run(run_monitor(cfg, mon, ReplaySource(cfg.source.path, machine, args.speed), sink))
    wall = time.perf_counter() - t0
    mt = np.array(machine_t)
    after_day = int(np.searchsorted(mt, 86400.0))
    decisions = MonitorStore(db).events("decision")
    actions = {}
    for e in decisions:
        actions[e.payload["action"]] = actions.get(e.payload["action"], 0) + 1
    print(jsonio.dumps({
        "wall_s": wall, "machine_s": res.status["last_time_s"], "factor": res.status["last_time_s"] / wall,
        "readings": res.status["readings"], "compensations": res.status["compensations"],
        "decisions": len(times), "decision_max_s": max(times), "decision_median_s": float(np.median(times)),
        "decision_p99_s": float(np.percentile(times, 99)),
        "rss_start_MB": rss0, "rss_after_day1_MB": rss[after_day], "rss_end_MB": rss[-1], "rss_max_MB": max(rss),
        "growth_MB": rss[-1] - rss[after_day], "switches": res.status["switches"], "actions": actions,
    }))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--days", type=int, default=7)
    p.add_argument("--rate-hz", type=float, default=1.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--speed", type=float, default=0.0, help="replay speed (0: as fast as possible)")
    p.add_argument("--element-size-mm", type=float, default=150.0, help="FE element size of the ROM [mm]")
    p.add_argument("--work", type=Path, default=None, help="directory for the generated data (default: temporary)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args)
        return 0
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory()
        args.work = Path(tmp.name)
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    info = generate(args.work, args.days, args.rate_hz, args.element_size_mm)
    print(f"generated {info['rows']:,} rows ({info['trace_MB']:.0f} MB), ROM order {info['rom_order']} "
          f"in {time.perf_counter() - t0:.0f} s", flush=True)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    runs = []
    for k in range(args.repeats):
        out = subprocess.run([sys.executable, __file__, "--child", "--work", str(args.work), "--speed", str(args.speed)],
                             env=env, capture_output=True, text=True, check=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = runs[-1]
        print(f"run {k + 1}: {r['wall_s']:.1f} s, {r['factor']:.0f}x, slowest decision {r['decision_max_s'] * 1e3:.1f} ms, "
              f"memory growth {r['growth_MB']:+.2f} MB", flush=True)
    med = {k: float(np.median([r[k] for r in runs])) for k in
           ("wall_s", "factor", "decision_max_s", "decision_median_s", "decision_p99_s", "growth_MB", "rss_end_MB")}
    worst_decision = max(r["decision_max_s"] for r in runs)
    worst_growth = max(r["growth_MB"] for r in runs)
    rows = [
        ("machine time replayed",
         f"{runs[0]['machine_s'] / 86400:.2f} days, {runs[0]['readings']:,} samples at {args.rate_hz:g} Hz", ""),
        ("wall time (median)", f"{med['wall_s']:.1f} s", ""),
        ("replay factor (median)", f"{med['factor']:.0f}x", "≥ 1000x"),
        ("compensation cycles", f"{runs[0]['compensations']:,}", ""),
        ("monitoring decisions", f"{runs[0]['decisions']} ({runs[0]['actions']})", ""),
        ("decision time median / p99 / max (median of runs)",
         f"{med['decision_median_s'] * 1e3:.1f} / {med['decision_p99_s'] * 1e3:.1f} / "
         f"{med['decision_max_s'] * 1e3:.1f} ms", "≤ 1 s"),
        ("slowest decision of all runs", f"{worst_decision * 1e3:.1f} ms", "≤ 1 s"),
        ("resident memory after day 1 → end (run 1)", f"{runs[0]['rss_after_day1_MB']:.1f} → {runs[0]['rss_end_MB']:.1f} MB", ""),
        ("memory growth (median / worst)", f"{med['growth_MB']:+.2f} / {worst_growth:+.2f} MB", "≤ 10 MB"),
    ]
    w = max(len(r[0]) for r in rows)
    print(f"\nmonitor soak, {args.repeats} run(s), {platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}")
    for a, b, c in rows:
        print(f"{a:<{w}}  {b:<44} {c}")
    ok = med["factor"] >= 1000 and worst_growth <= 10 and worst_decision <= 1.0
    print(jsonio.dumps({"benchmark": "monitor_soak", "days": args.days, "rate_hz": args.rate_hz, "repeats": args.repeats,
                      "rows": info["rows"], "rom_order": info["rom_order"], "median": med,
                      "worst_decision_s": worst_decision, "worst_growth_MB": worst_growth, "runs": runs, "targets_met": ok}))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
