"""Benchmark: the observer's air walk on days it was not chosen on, against the former settings.

The observer's air defaults (``air_rate_K`` 3 K/√h, ``air_common`` 0.8, ``hybridcomp.rom.observer``) were chosen on
the compensation benchmark's ambient swing (±1.5 K, 6 h). Here four other days, with another noise seed
(``Scenario(seed=11)``), each replayed to the daemon with the defaults and with the former settings (1 K/√h, a
walk per zone): two unmeasured ambient swings of other amplitude and period (one with a mis-scaled spindle motor
beside it), a day whose air is as measured but for a warmer workspace with a mis-scaled rear bearing, and a
mis-scaled X motor. Judged as the compensation benchmark judges (the hybrid's 3-D residual at the model's pose and
at the commanded position, the truth from the real machine's own FE and pose-aware model):

    python benchmarks/observer_air.py [--element-size-mm 150] [--out DIR]

Prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's hybridcomp, installed or not
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import table

#: the former defaults: a walk per zone at 1 K/√h
FORMER = {"air_common": 0.0, "air_rate_K": 1.0}
WINDOWS = {"E15min": 900.0, "E1h": 3600.0, "E4h": 14400.0}


def days():
    from hybridcomp.scenario import Disturbance

    return (
        Disturbance("ambient ±1 K, 3 h, spindle motor 1.3 ×", "an unmeasured ambient swing of ±1 K with a 3 h "
                    "period, the spindle motor at 1.3 × its power", ambient_swing_K=1.0, swing_period_h=3.0,
                    source_factor=("spindle_motor", 1.3)),
        Disturbance("ambient ±2 K, 10 h", "an unmeasured ambient swing of ±2 K with a 10 h period",
                    ambient_swing_K=2.0, swing_period_h=10.0),
        Disturbance("rear bearing 0.7 ×, workspace air +1 K", "the rear spindle bearing at 0.7 × its power, the "
                    "workspace air 1 K warmer than measured", source_factor=("spindle_bearing_rear", 0.7),
                    workspace_air_K=1.0),
        Disturbance("X motor 1.47 ×", "the X motor at 1.47 × its power", source_factor=("x_motor", 1.47)),
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--element-size-mm", type=float, default=150.0, help="FE element size of every model [mm]")
    p.add_argument("--out", type=Path, help="keep every day's folder here (default: a temporary one)")
    args = p.parse_args(argv)
    if not args.element_size_mm > 0:
        p.error(f"--element-size-mm must be positive, got {args.element_size_mm}")
    with tempfile.TemporaryDirectory() as tmp:
        return run(args.out.resolve() if args.out is not None else Path(tmp), args.element_size_mm)


def run(out: Path, element_size_mm: float) -> int:
    """Every day with both settings, the models built in ``out``; prints the table and the JSON line."""
    from hybridcomp.scenario import Scenario, build_models, run_scenario

    t0 = time.perf_counter()
    models = build_models(out / "models", element_size_mm=element_size_mm, poses=True)
    rows, results = [], []
    for k, d in enumerate(days()):
        for name, obs in (("defaults", {}), ("former", FORMER)):
            sc = Scenario(element_size_mm=element_size_mm, along_path=True, seed=11, disturbance=d,
                          monitor_overrides={"observer": obs} if obs else None, plot=False)
            res = run_scenario(sc, out / f"day{k}_{name}", models)
            path = res.summary["along_path"]["metrics"]
            r = {"day": d.name, "settings": name,
                 "at pose": res.metrics["hybrid monitor"]["3d"]["rms_um"],
                 "ROM direct at pose": res.metrics["ROM direct"]["3d"]["rms_um"],
                 "along path": path["hybrid monitor"]["3d"]["rms_um"],
                 "ROM direct along path": path["ROM direct along the path"]["3d"]["rms_um"],
                 "uncompensated along path": path["no compensation"]["3d"]["rms_um"]}
            r |= {f"{w} along path": path["hybrid monitor"]["3d"]["p95_range_um"][s] for w, s in WINDOWS.items()}
            results.append(r)
            rows.append({k2: (f"{v:.2f}" if isinstance(v, float) else v) for k2, v in r.items()})
            print(f"{d.name}, {name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    print(table(rows, list(rows[0])))
    better = sum(1 for a, b in zip(results[::2], results[1::2]) if a["along path"] <= b["along path"])
    print(json.dumps({"benchmark": "observer_air", "element_size_mm": element_size_mm,
                      "machine": platform.machine(), "wall_s": time.perf_counter() - t0,
                      "days_defaults_not_worse_along_path": better, "days": len(results) // 2, "results": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
