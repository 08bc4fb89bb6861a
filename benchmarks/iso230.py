"""The ISO 230-3 tests simulated on the demonstrator: moving-axis tests of X, Y and Z and the ETVE test.

    python benchmarks/iso230.py [--element-size-mm 80] [--feed-mm-min 20000] [--hours 12]

Prints a table per axis (error change at the targets at the end, spread over the travel, slope, the structure's
largest change at a target's pose, steady state), the ETVE ranges and a final JSON line; writes
``benchmarks/figures/iso230_moving_axis.png`` (error over position for every hour, X with its rotary encoder
beside Z with its linear scale).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from hybridcomp.fem.iso230 import etve_test, moving_axis_test
from hybridcomp.fem.model import build_model
from hybridcomp.models import jsonio, load_machine

from _table import table


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=80.0)
    p.add_argument("--feed-mm-min", type=float, default=20000.0)
    p.add_argument("--hours", type=float, default=12.0)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "figures" / "iso230_moving_axis.png")
    a = p.parse_args(argv)
    m = load_machine("vmc800")
    t0 = time.perf_counter()
    model = build_model(m, None, a.element_size_mm)
    build_s = time.perf_counter() - t0
    results, rows = {}, []
    for axis in ("X", "Y", "Z"):
        t0 = time.perf_counter()
        res = moving_axis_test(model, axis, a.feed_mm_min, hours=a.hours, step_s=300.0)
        s = res.summary()
        results[axis] = (res, s | {"wall_s": round(time.perf_counter() - t0, 2)})
        rows.append({"axis": axis, "feedback": s["feedback"],
                     "change_at_targets_um": " ".join(f"{v:.1f}" for v in s["final_change_um"]),
                     "spread_um": f"{s['spread_um']:.2f}", "slope_um_per_m": f"{s['final_slope_um_per_m']:.1f}",
                     "structure_um": f"{s['structure_change_um']:.2f}",
                     "steady_h": "-" if s["steady_state_h"] is None else f"{s['steady_state_h']:.2f}"})
    print(f"moving-axis tests, {a.feed_mm_min:g} mm/min for {a.hours:g} h, {model.n} nodes")
    print(table(rows, list(rows[0])))
    etve = etve_test(model, hours=48.0, amplitude_K=2.0, period_h=24.0).summary()
    print(f"ETVE (48 h, air ±2 K over 24 h): drift range {etve['drift_range_um']} um; added feedback error range at "
          f"the travel ends {etve['feedback_range_um']} um; error along the axis there {etve['error_range_um']} um")
    _figure(results, a.out, model.n, a.feed_mm_min)
    print(jsonio.dumps({"benchmark": "iso230", "nodes": model.n, "build_s": round(build_s, 2),
                        "moving_axis": {k: v[1] for k, v in results.items()}, "etve": etve, "png": str(a.out)}))
    return 0


def _figure(results, path: Path, nodes: int, feed: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    cmap = plt.get_cmap("viridis")
    for ax, axis in zip(axes, ("X", "Y", "Z")):
        res = results[axis][0]
        hours = res.time_s / 3600
        change = res.error_um - res.error_um[0]
        marks = np.unique(np.searchsorted(hours, np.arange(0, hours[-1] + 1e-9, 1.0)))
        for k, i in enumerate(marks):
            ax.plot(res.targets_mm, change[i], "o-", ms=3, lw=1, color=cmap(k / max(1, len(marks) - 1)),
                    label=f"{hours[i]:.0f} h" if k in (1, len(marks) - 1) else None)
        ax.set_title(f"{axis}: {res.feedback.replace('_', ' ')}")
        ax.set_xlabel(f"{axis} position [mm]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("error change along the axis, TCP - table [µm]")
    fig.suptitle(f"vmc800, ISO 230-3 moving-axis test simulated: {feed:g} mm/min, hourly ({nodes} nodes)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
