"""Benchmark: a week of 10 Hz machine trace streamed through the histogram generator.

The trace is generated here (into a temporary directory unless ``--file`` names
one to keep or re-use): every day the 16 h job-shop day of the bundled
scenario (``hybridcomp scenario jobshop``) followed by 8 h standing still,
sampled at ``--rate-hz``, with the workshop air ``Tamb_degC`` and, with
``--sensors N``, N sensor columns ``T1_degC`` ... (read past, not used).
7 days at 10 Hz are 6,048,000 rows.

Only the processing is timed: trace CSV → increments → BCs → loads CSV, in a
fresh process, whose peak resident memory (``VmHWM``, includes the
interpreter and numpy) is reported. Targets: ≤ 10 s and ≤ 500 MB.

    python benchmarks/histogram_stream.py [--days 7] [--rate-hz 10] [--repeats 3] [--file week.csv]

Prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hybridcomp.models import jsonio


def generate(path: Path, machine_name: str, days: int, rate_hz: float, sensors: int) -> int:
    """Write the trace; returns the number of rows."""
    from hybridcomp.histogram.gcode import parse_gcode, sample_motion
    from hybridcomp.histogram.scenarios import jobshop_ambient, jobshop_program
    from hybridcomp.histogram.trace import position_column
    from hybridcomp.models import load_machine

    machine = load_machine(machine_name)
    day_prog = jobshop_program(machine).replace("M30", "G0 X0 Y0 Z0 (back to the start for the night)\nM30")
    rest = 86400.0 - parse_gcode(day_prog, machine).duration_s  # 16 h of work, then standing until the next day
    motion = parse_gcode(day_prog.replace("M30", f"G4 P{rest:.9f}\nM30"), machine)
    assert abs(motion.duration_s - 86400.0) < 1e-3, motion.duration_s
    day = sample_motion(motion, rate_hz)
    keep = day.time_s < 86400.0 - 0.5 / rate_hz  # the next day's first sample closes the day
    t_day = day.time_s[keep]
    P = day.position_mm[keep]
    r = day.spindle_rpm[keep]
    amb = jobshop_ambient(machine)
    names = ["time_s", *(position_column(a.name) for a in machine.axes), "spindle_rpm", "Tamb_degC"]
    names += [f"T{k + 1}_degC" for k in range(sensors)]
    fmt = ",".join(["%.1f"] + ["%.3f"] * len(machine.axes) + ["%.0f", "%.3f"] + ["%.3f"] * sensors)
    rows = 0
    with path.open("w") as fh:
        fh.write(",".join(names) + "\n")
        for d in range(days):
            t = t_day + d * 86400.0
            cols = [t[:, None], P, r[:, None], amb(t)[:, None]]
            if sensors:
                cols.append(20.0 + 0.1 * np.arange(sensors)[None, :] + 0 * t[:, None])
            block = np.hstack(cols)
            for i in range(0, block.shape[0], 200_000):
                np.savetxt(fh, block[i : i + 200_000], fmt=fmt)
            rows += block.shape[0]
            print(f"  day {d + 1}/{days} written", file=sys.stderr, flush=True)
    return rows


def peak_rss_MB() -> float:
    """Peak resident memory of this process [MB]: VmHWM (reset by exec, unlike ru_maxrss, which a
    child started by a big parent inherits across fork + exec); ru_maxrss where /proc is missing."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def process(path: Path, machine_name: str, increment_s: float, chunk_rows: int | None) -> dict:
    """The timed part, meant to run in a fresh process."""
    t0 = time.perf_counter()
    from hybridcomp.histogram.bcs import boundary_conditions, write_bcs
    from hybridcomp.histogram.increments import increments_from_trace
    from hybridcomp.models import load_machine

    machine = load_machine(machine_name)
    t_import = time.perf_counter() - t0
    t1 = time.perf_counter()
    inc = increments_from_trace(path, machine, increment_s, chunk_rows=chunk_rows)
    t2 = time.perf_counter()
    loads = boundary_conditions(machine, inc)
    out = path.with_name(path.stem + "_loads.csv")
    write_bcs(out, loads)
    t3 = time.perf_counter()
    return {
        "rows": inc.rows,
        "increments": len(inc),
        "import_s": t_import,
        "read_and_integrate_s": t2 - t1,
        "bcs_and_write_s": t3 - t2,
        "processing_s": t3 - t1,
        "peak_rss_MB": peak_rss_MB(),
        "mean_factors": inc.axis_factor.mean(axis=0).round(5).tolist(),
        "mean_spindle_factor": round(float(inc.spindle_factor.mean()), 5),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--days", type=int, default=7)
    p.add_argument("--rate-hz", type=float, default=10.0)
    p.add_argument("--increment", type=float, default=300.0, help="increment [s]")
    p.add_argument("--sensors", type=int, default=0, help="extra sensor columns in the trace (read past)")
    p.add_argument("--machine", default="vmc800")
    p.add_argument("--repeats", type=int, default=1, help="processing runs, each in a fresh process (median reported)")
    p.add_argument("--chunk-rows", type=int, default=None, help="rows per chunk (default: the reader's)")
    p.add_argument("--file", type=Path, help="trace CSV to keep (generated when missing) instead of a temporary one")
    p.add_argument("--_process", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._process is not None:
        print(jsonio.dumps(process(args._process, args.machine, args.increment, args.chunk_rows)))
        return 0

    with tempfile.TemporaryDirectory() as tmp:
        path = args.file or Path(tmp) / "week.csv"
        t0 = time.perf_counter()
        if not path.exists():
            print(f"generating {path} ...", file=sys.stderr)
            generate(path, args.machine, args.days, args.rate_hz, args.sensors)
        t_gen = time.perf_counter() - t0
        size_MB = path.stat().st_size / 1e6
        runs = []
        for _ in range(args.repeats):
            cmd = [sys.executable, __file__, "--_process", str(path), "--machine", args.machine,
                   "--increment", str(args.increment)]
            if args.chunk_rows:
                cmd += ["--chunk-rows", str(args.chunk_rows)]
            res = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
            if res.returncode != 0:
                print(res.stderr, file=sys.stderr)
                return 1
            runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        med = {k: float(np.median([r[k] for r in runs]))
               for k in ("read_and_integrate_s", "bcs_and_write_s", "processing_s", "peak_rss_MB")}
        r0 = runs[0]
        print(f"\nhistogram stream benchmark: {r0['rows']:,} rows ({size_MB:.0f} MB CSV), "
              f"{args.days} days at {args.rate_hz:g} Hz, "
              f"{r0['increments']} increments of {args.increment:g} s; median of {len(runs)} fresh process(es)")
        print(f"{'stage':<34}{'value':>12}")
        print(f"{'generation (not timed) [s]':<34}{t_gen:>12.1f}")
        print(f"{'read + integrate [s]':<34}{med['read_and_integrate_s']:>12.2f}")
        print(f"{'BCs + loads CSV [s]':<34}{med['bcs_and_write_s']:>12.3f}")
        print(f"{'processing total [s]  (<= 10)':<34}{med['processing_s']:>12.2f}")
        print(f"{'rows per second':<34}{r0['rows'] / med['processing_s']:>12,.0f}")
        print(f"{'peak RSS [MB]  (<= 500)':<34}{med['peak_rss_MB']:>12.0f}")
        ok = med["processing_s"] <= 10.0 and med["peak_rss_MB"] <= 500.0
        summary = {
            "benchmark": "histogram_stream",
            "rows": r0["rows"],
            "csv_MB": round(size_MB, 1),
            "days": args.days,
            "rate_hz": args.rate_hz,
            "increment_s": args.increment,
            "increments": r0["increments"],
            "processing_s": round(med["processing_s"], 3),
            "read_and_integrate_s": round(med["read_and_integrate_s"], 3),
            "peak_rss_MB": round(med["peak_rss_MB"], 1),
            "runs_processing_s": [round(r["processing_s"], 3) for r in runs],
            "mean_axis_factors": r0["mean_factors"],
            "mean_spindle_factor": r0["mean_spindle_factor"],
            "targets_met": ok,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cpus": os.cpu_count(),
        }
        print(jsonio.dumps(summary))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
