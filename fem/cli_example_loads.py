"""``hybridcomp example-loads``: a reproducible example BC time series for a machine."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hybridcomp.fem.loads import example_loads, write_loads
from hybridcomp.models.cli import add_machine_argument
from hybridcomp.models.loader import load_machine
from hybridcomp.models.machine import MachineFileError
from hybridcomp.safeio import FORCE_HELP, atomic_path, check_output_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp example-loads`` options."""
    add_machine_argument(p)
    p.add_argument("--hours", type=float, default=16.0, help="duration [h] (default 16)")
    p.add_argument("--dt", type=float, default=60.0, help="row spacing [s] (default 60)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the block pattern")
    p.add_argument("--out", required=True, type=Path, help="loads CSV to write")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp example-loads``; returns the exit code (2: bad input, named on stderr)."""
    try:
        machine = load_machine(args.machine)
        if not args.hours > 0 or not args.dt > 0:
            raise ValueError(f"--hours and --dt must be positive, got {args.hours} and {args.dt}")
        check_output_path(args.out, inputs=(machine.source,), force=args.force)
    except (MachineFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    loads = example_loads(machine, args.hours, args.dt, args.seed)
    with atomic_path(args.out) as tmp:
        write_loads(tmp, loads)
    print(f"wrote {args.out} ({len(loads.time_s)} rows, {len(loads.names)} inputs)", file=sys.stderr)
    return 0
