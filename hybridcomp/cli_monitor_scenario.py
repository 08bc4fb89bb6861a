"""``hybridcomp monitor scenario``: the hybrid scenario, every compensation strategy on an FE 'real machine'.

The action belongs to ``hybridcomp monitor`` on the command line, but it composes every package (histogram,
FE, reduction, CDs, the monitor), so it lives here at the top, beside :mod:`hybridcomp.scenario`; the
dispatcher adds it to the actions of :mod:`hybridcomp.monitor.cli`, which imports nothing above the monitor.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hybridcomp.models import jsonio
from hybridcomp.safeio import FORCE_HELP, start_folder


def add_parser(actions: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``scenario`` action and its options to the ``hybridcomp monitor`` actions; returns its parser."""
    c = actions.add_parser("scenario", help="the hybrid scenario: job-shop day on an FE 'real machine', every strategy compared",
                             description="Replay the bundled 16 h job-shop day with the FE model plus a disturbance the models "
                             "do not know as the real machine, starting from default CDs of the basic load cases; compare no "
                             "compensation, static default CDs, the hybrid monitor, the observer, the ROM used directly and a "
                             "multiple linear regression on the sensors (RMS, peak-to-peak, 95th-percentile range over "
                             "sliding windows, activations, largest offset step).")
    c.add_argument("--out", required=True, type=Path, help="output directory (table, plot, databases, traces); a "
                   "folder that holds anything is written into only with --force")
    c.add_argument("--force", action="store_true", help=FORCE_HELP + " (an earlier run's folder: its files are "
                   "replaced, its summary.json removed first)")
    c.add_argument("--disturbance", default="workspace air", metavar="NAME",
                   help="what the real machine does that the models do not know: " + ", ".join(
                       f"'{n}'" for n in _disturbance_names()) + " (default %(default)r)")
    c.add_argument("--element-size-mm", type=float, default=80.0, help="FE element size of the 'real machine' and "
                   "the models [mm] (default 80)")
    c.add_argument("--day-hours", type=float, default=None, help="replay only the first hours of the day (default 16)")
    c.add_argument("--rom-order", type=int, default=None, help="order of the structure model (default: to tolerance)")
    c.add_argument("--basic-hours", type=float, default=8.0,
                   help="heating hours, and as many cooling hours, of each basic load case (default 8)")
    c.add_argument("--along-path", action="store_true",
                   help="also judge every strategy at the trace's commanded position at each time, where the drift "
                   "depends on the pose and the feed drives' errors on the axis positions (builds the pose-aware "
                   "structure model; writes table_along_path.md, summary 'along_path')")
    return c


def _disturbance_names() -> list[str]:
    from hybridcomp.scenario import DISTURBANCES

    return list(DISTURBANCES)


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp monitor scenario``; returns the exit code (2: bad input, named)."""
    from hybridcomp.errors import HybridcompError
    from hybridcomp.scenario import DISTURBANCES, Scenario, check_day, run_scenario

    try:
        # everything that can be checked before work starts is, so an error leaves no half-written folder
        if args.disturbance not in DISTURBANCES:
            raise ValueError(f"--disturbance: unknown disturbance {args.disturbance!r} (known: "
                             f"{', '.join(DISTURBANCES)})")
        check_day(DISTURBANCES[args.disturbance], args.day_hours, "--day-hours")
        for option, value, ok in (("--element-size-mm", args.element_size_mm, args.element_size_mm > 0),
                                  ("--basic-hours", args.basic_hours, args.basic_hours > 0),
                                  ("--rom-order", args.rom_order, args.rom_order is None or args.rom_order >= 1)):
            if not ok:
                raise ValueError(f"{option} must be positive, got {value:g}")
        start_folder(args.out, force=args.force, finals=("summary.json",))
        res = run_scenario(Scenario(disturbance=DISTURBANCES[args.disturbance],
                                    element_size_mm=args.element_size_mm, rom_order=args.rom_order,
                                    basic_hours=args.basic_hours, day_hours=args.day_hours,
                                    along_path=args.along_path), args.out)
        print(res.table)
        if args.along_path:
            print("\nalong the path:\n" + (Path(res.files["table"]).parent / "table_along_path.md").read_text())
        print(jsonio.dumps(res.summary))
        return 0
    except (ValueError, OSError, HybridcompError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
