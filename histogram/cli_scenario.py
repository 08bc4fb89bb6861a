"""``hybridcomp scenario {basic,jobshop}``: write a bundled scenario's G-code, trace and loads CSV."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hybridcomp.histogram.increments import DEFAULT_INCREMENT_S
from hybridcomp.histogram.scenarios import SCENARIOS, scenario_files, write_scenario
from hybridcomp.histogram.trace import TraceFileError
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.loader import load_machine
from hybridcomp.models.machine import MachineFileError
from hybridcomp.safeio import FORCE_HELP, check_output_dir


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp scenario`` options."""
    p.add_argument("name", choices=SCENARIOS,
                   help="basic: each axis alone at max feed over its full travel, and the spindle alone at max speed; "
                   "jobshop: a 16 h day of eight workpieces with pauses")
    add_machine_argument(p)
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--increment", type=float, default=DEFAULT_INCREMENT_S,
                   help=f"increment of the loads CSV [s] (default {DEFAULT_INCREMENT_S:g})")
    p.add_argument("--rate-hz", type=float, default=10.0, help="sampling rate of the trace [Hz] (default 10)")
    p.add_argument("--power", choices=("factor", "mean"), default="mean",
                   help="heat power per increment (see hybridcomp histogram --help)")
    p.add_argument("--hours", type=float, default=8.0, help="basic: duration of each load case [h] (default 8)")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp scenario``; returns the exit code (2: bad input, named on stderr)."""
    try:
        bad = refuse_unused(args, [("hours", args.name != "basic", "applies to the basic scenario only "
                                    "(the job-shop day is always 16 h)")])
        if bad:
            raise ValueError(bad)
        machine = load_machine(args.machine)
        for opt in ("increment", "rate_hz", "hours"):
            if not getattr(args, opt) > 0:
                raise ValueError(f"--{opt.replace('_', '-')} must be positive, got {getattr(args, opt)}")
        check_output_dir(args.out, scenario_files(args.name, machine), inputs=(machine.source,), force=args.force)
        files = write_scenario(args.name, machine, args.out, args.increment, args.rate_hz, args.hours, args.power)
    except (MachineFileError, TraceFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for f in files.values():
        print(f"wrote {f}", file=sys.stderr)
    return 0
