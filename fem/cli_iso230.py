"""``hybridcomp iso230``: the ISO 230-3 thermal tests simulated on a machine (:mod:`hybridcomp.fem.iso230`).

``moving-axis`` writes ``moving_axis_<AXIS>.csv`` (time, the error, the drive's added share and the structure's
drift along the axis at every target), ``moving_axis_<AXIS>.png`` (error over position at every hour, error over
time per target) and ``moving_axis_<AXIS>.json`` (the summary); ``etve`` writes ``etve.csv``, ``etve.png`` and
``etve.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from hybridcomp.models import jsonio
from hybridcomp.models.cli import add_machine_argument
from hybridcomp.models.layout import DRIFT_COLUMNS
from hybridcomp.models.loader import load_machine
from hybridcomp.safeio import FORCE_HELP, atomic_path, check_output_dir, write_text_atomic


def _common(p: argparse.ArgumentParser) -> None:
    add_machine_argument(p)
    p.add_argument("--out", type=Path, required=True,
                   help="output directory; files of an earlier run in it are overwritten only with --force")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument("--element-size-mm", type=float,
                   help="largest element edge of the FE model [mm] (default: from the machine file)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp iso230`` actions and their options."""
    sub = p.add_subparsers(dest="iso_command", metavar="TEST", required=True)
    m = sub.add_parser("moving-axis", help="thermal distortion caused by a moving linear axis",
                       description="ISO 230-3 moving-axis test, simulated: the axis moves back and forth over its "
                       "travel at --feed-mm-min from the machine's standstill steady state, every other drive at rest; "
                       "the TCP-minus-table drift along the axis is recorded at the targets. A rotary-encoder axis "
                       "shows its screw's elongation growing with the distance from the fixed bearing; a linear-scale "
                       "axis only the scale's expansion with its carrier. Needs a [[drives]] entry for the axis.")
    _common(m)
    m.add_argument("--axis", required=True, help="the axis to test (e.g. X)")
    m.add_argument("--feed-mm-min", type=float,
                   help="feed of the back-and-forth motion [mm/min] (default: half the axis' max_feed_mm_min)")
    m.add_argument("--targets", type=int, default=5,
                   help="number of equally spaced target positions, 5 %% of the travel in from each end (default 5)")
    m.add_argument("--hours", type=float, default=12.0, help="duration of the test [h] (default 12)")
    m.add_argument("--step-s", type=float, default=300.0, help="recording interval [s] (default 300)")
    e = sub.add_parser("etve", help="environmental temperature variation error",
                       description="ISO 230-3 ETVE test, simulated: the machine at rest while the air of every zone "
                       "swings as T_ref + A sin(2 pi t / period); the drift at the model's pose and every drive's "
                       "positioning error at its travel ends over the test.")
    _common(e)
    e.add_argument("--hours", type=float, default=48.0, help="duration [h] (default 48)")
    e.add_argument("--amplitude-K", type=float, default=2.0, help="air amplitude [K] (default 2)")
    e.add_argument("--period-hours", type=float, default=24.0, help="period of the air swing [h] (default 24)")
    e.add_argument("--step-s", type=float, default=600.0, help="recording interval [s] (default 600)")


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp iso230``; returns the exit code (errors are raised and reported by the dispatcher)."""
    from hybridcomp.fem.iso230 import default_targets_mm

    machine = load_machine(args.machine)
    if args.element_size_mm is not None and not args.element_size_mm > 0:
        raise ValueError(f"--element-size-mm must be positive, got {args.element_size_mm}")
    if args.iso_command == "moving-axis":
        if args.axis not in [a.name for a in machine.axes]:
            raise ValueError(f"--axis {args.axis!r}: machine {machine.name!r} has axes {[a.name for a in machine.axes]}")
        if machine.drive(args.axis) is None:
            raise ValueError(f"--axis {args.axis}: {machine.source} gives no [[drives]] entry for it (its ball screw and "
                             "position feedback)")
        if args.targets < 2:
            raise ValueError(f"--targets must be at least 2, got {args.targets}")
        stem = f"moving_axis_{args.axis}"
    else:
        stem = "etve"
    files = [f"{stem}.csv", f"{stem}.json", f"{stem}.png"]
    check_output_dir(args.out, files, inputs=(machine.source,), force=args.force)

    from hybridcomp.fem.iso230 import etve_test, moving_axis_test
    from hybridcomp.fem.model import build_model

    t0 = time.perf_counter()
    progress = not args.no_progress
    if progress:
        print(f"meshing and assembling {machine.name} ...", file=sys.stderr)
    model = build_model(machine, None, args.element_size_mm)
    out: Path = args.out
    if args.iso_command == "moving-axis":
        feed = args.feed_mm_min if args.feed_mm_min is not None else 0.5 * machine.axis(args.axis).max_feed_mm_min
        targets = default_targets_mm(machine, args.axis, args.targets)
        res = moving_axis_test(model, args.axis, feed, targets, args.hours, args.step_s, progress=progress)
        summary = res.summary()
        cols = {"time_h": res.time_s / 3600}
        cols |= {f"error_um@{p:g}": res.error_um[:, j] for j, p in enumerate(targets)}
        cols |= {f"feedback_um@{p:g}": res.feedback_um[:, j] for j, p in enumerate(targets)}
        cols |= {f"structure_um@{p:g}": res.structure_um[:, j] for j, p in enumerate(targets)}
        picture = lambda tmp: plot_moving_axis(res, machine.name, tmp)  # noqa: E731
    else:
        res = etve_test(model, args.hours, args.amplitude_K, args.period_hours, args.step_s, progress=progress)
        summary = res.summary()
        cols = {"time_h": res.time_s / 3600, "air_rise_K": res.air_rise_K}
        cols |= {c: res.drift_um[:, j] for j, c in enumerate(DRIFT_COLUMNS)}
        for axis, e in res.feedback_um.items():
            lo, hi = machine.axis(axis).travel_mm
            cols |= {f"{axis}_feedback_um@{lo:g}": e[:, 0], f"{axis}_feedback_um@{hi:g}": e[:, 1]}
            err = res.error_um[axis]
            cols |= {f"{axis}_error_um@{lo:g}": err[:, 0], f"{axis}_error_um@{hi:g}": err[:, 1]}
        picture = lambda tmp: plot_etve(res, machine.name, tmp)  # noqa: E731
    summary |= {"machine": machine.name, "machine_sha256": machine.sha256, "nodes": model.n,
                "element_size_mm": model.machine.mesh.element_size_mm, "wall_s": time.perf_counter() - t0}
    out.mkdir(parents=True, exist_ok=True)
    header = ",".join(cols)
    data = np.column_stack(list(cols.values()))
    with atomic_path(out / f"{stem}.csv") as tmp:
        np.savetxt(tmp, data, delimiter=",", header=header, comments="", fmt="%.6g")
    write_text_atomic(out / f"{stem}.json", jsonio.dumps(summary, indent=2))
    try:
        with atomic_path(out / f"{stem}.png") as tmp:
            picture(tmp)
    except ImportError as exc:  # pictures are optional: the numbers are already written
        print(f"warning: no picture ({exc})", file=sys.stderr)
    print(_report(args.iso_command, summary), file=sys.stderr)
    print(f"wrote {out / (stem + '.csv')}, .json, .png", file=sys.stderr)
    return 0


def _report(kind: str, s: dict) -> str:
    if kind == "moving-axis":
        rows = "\n".join(f"  {p:>9.1f} mm  {c:>9.2f} um" for p, c in zip(s["targets_mm"], s["final_change_um"]))
        steady = "not reached" if s["steady_state_h"] is None else f"{s['steady_state_h']:.2f} h"
        return (f"moving-axis test {s['axis']} ({s['feedback']}, {s['feed_mm_min']:g} mm/min, {s['duration_h']:g} h):\n"
                f"  target          change at the end\n{rows}\n"
                f"  spread over the travel {s['spread_um']:.2f} um (feedback {s['feedback_spread_um']:.2f} um), "
                f"slope {s['final_slope_um_per_m']:.1f} um/m, steady state {steady}")
    drift = ", ".join(f"d{c} {v:.2f}" for c, v in s["drift_range_um"].items())
    fb = ", ".join(f"{a} {max(v):.2f}" for a, v in s["feedback_range_um"].items())
    return f"ETVE test ({s['duration_h']:g} h, air range {s['air_range_K']:g} K): drift range {drift} um; " \
           f"feedback error range at the travel ends {fb} um"


def plot_moving_axis(res, machine_name: str, path) -> None:
    """Error over position at every hour and over time per target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    hours = res.time_s / 3600
    change = res.error_um - res.error_um[0]
    marks = np.unique(np.searchsorted(hours, np.arange(0, hours[-1] + 1e-9, max(1.0, round(hours[-1] / 12)))))
    cmap = plt.get_cmap("viridis")
    for k, i in enumerate(marks):
        a.plot(res.targets_mm, change[i], "o-", color=cmap(k / max(1, len(marks) - 1)), ms=3, lw=1,
               label=f"{hours[i]:.0f} h" if k in (0, len(marks) - 1) or len(marks) <= 6 else None)
    a.set_xlabel(f"{res.axis} position [mm]")
    a.set_ylabel(f"error along {res.axis} (TCP - table) [µm]")
    a.set_title(f"{machine_name} {res.axis}: {res.feedback.replace('_', ' ')}, {res.feed_mm_min:g} mm/min")
    a.legend(fontsize=8)
    a.grid(alpha=0.3)
    for j, p in enumerate(res.targets_mm):
        b.plot(hours, change[:, j], label=f"{p:g} mm")
    for j in range(len(res.targets_mm)):
        b.plot(hours, res.structure_um[:, j] - res.structure_um[0, j], "k--", lw=0.8,
               label="structure at the targets" if j == 0 else None)
    b.set_xlabel("time [h]")
    b.set_ylabel("change of the error [µm]")
    b.legend(fontsize=8)
    b.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=110)
    plt.close(fig)


def plot_etve(res, machine_name: str, path) -> None:
    """Air, drift and feedback errors over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    hours = res.time_s / 3600
    for j, c in enumerate("xyz"):
        a.plot(hours, res.drift_um[:, j] - res.drift_um[0, j], label=f"d{c}")
    ax2 = a.twinx()
    ax2.plot(hours, res.air_rise_K, "k:", lw=1)
    ax2.set_ylabel("air rise [K] (dotted)")
    a.set_ylabel("drift change [µm]")
    a.set_title(f"{machine_name}: ETVE, machine at rest")
    a.legend(fontsize=8)
    for axis, e in res.feedback_um.items():
        b.plot(hours, e[:, 1] - e[0, 1], label=f"{axis} at travel end")
    b.set_xlabel("time [h]")
    b.set_ylabel("feedback error change [µm]")
    b.legend(fontsize=8)
    for ax in (a, b):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=110)
    plt.close(fig)
