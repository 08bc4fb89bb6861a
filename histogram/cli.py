"""``hybridcomp histogram``: a trace CSV or a G-code programme → the loads CSV of ``hybridcomp simulate``.

Everything is read and checked before any output is written.
"""

from __future__ import annotations

import argparse
import logging
import sys
import warnings
from pathlib import Path

import numpy as np

from hybridcomp.histogram.bcs import boundary_conditions, write_bcs
from hybridcomp.histogram.gcode import (
    GCODE_SUFFIXES,
    increments_from_motion,
    read_gcode,
)
from hybridcomp.histogram.increments import (
    DEFAULT_BINS_PER_SEGMENT,
    DEFAULT_FEED_TOLERANCE,
    DEFAULT_INCREMENT_S,
    DEFAULT_MAX_GAP_S,
    increments_from_trace,
)
from hybridcomp.histogram.signature import SignatureLayout, write_signatures
from hybridcomp.histogram.trace import TraceFileError, TraceWarning
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.loader import load_machine
from hybridcomp.models.machine import MachineFileError
from hybridcomp.safeio import FORCE_HELP, atomic_path, check_distinct, check_output_dir, check_output_path

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp histogram`` options."""
    p.add_argument("input", type=Path, metavar="TRACE_OR_GCODE",
                   help="trace CSV (time_s, x_mm, ..., spindle_rpm, optional Tamb_degC) or G-code programme "
                   f"(by suffix: .csv is a trace, {', '.join(GCODE_SUFFIXES)} G-code; see --format)")
    add_machine_argument(p)
    p.add_argument("--increment", type=float, default=DEFAULT_INCREMENT_S,
                   help=f"increment length [s] (default {DEFAULT_INCREMENT_S:g})")
    p.add_argument("--out", required=True, type=Path, help="loads CSV to write (the input of hybridcomp simulate)")
    p.add_argument("--format", choices=("auto", "trace", "gcode"), default="auto", help="input format (default: by suffix)")
    p.add_argument("--max-gap", type=float, default=DEFAULT_MAX_GAP_S,
                   help=f"trace: a sample interval longer than this [s] is a recording gap, counted as standstill "
                   f"with a warning (default {DEFAULT_MAX_GAP_S:g})")
    p.add_argument("--feed-tolerance", type=float, default=DEFAULT_FEED_TOLERANCE,
                   help=f"trace: relative excess over the max feed / spindle speed tolerated before it is an error "
                   f"(default {DEFAULT_FEED_TOLERANCE:g})")
    p.add_argument("--bins-per-segment", type=int, default=DEFAULT_BINS_PER_SEGMENT,
                   help=f"position histogram bins per rail segment (default {DEFAULT_BINS_PER_SEGMENT})")
    p.add_argument("--power", choices=("factor", "mean"), default="mean",
                   help="heat power per increment: 'mean' (default) the time average of P(f(t)), moving sources' heat "
                   "put into the segment where it was dissipated (exact heat for any increment length); 'factor' "
                   "P(mean load factor), moving sources split by the time spent per rail segment")
    p.add_argument("--signature", type=Path, metavar="CSV", help="also write the load-case signature per increment")
    p.add_argument("--signature-period", type=float, metavar="S",
                   help="signature per period of S seconds, a whole multiple of --increment (default: per increment)")
    p.add_argument("--plot", type=Path, metavar="DIR",
                   help="write factors.png (load factors over time) and histogram_K.png per --plot-increment (needs matplotlib)")
    p.add_argument("--plot-increment", type=int, action="append", metavar="K",
                   help="increment to draw as a histogram (repeatable; default: the one with the largest mean axis factor)")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)


def _fail(exc: Exception) -> int:
    print(f"error: {exc}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp histogram``; returns the exit code (2: bad input, named on stderr)."""
    try:
        machine = load_machine(args.machine)
        if not args.increment > 0:
            raise ValueError(f"--increment must be positive, got {args.increment}")
        if args.signature_period is not None:
            ratio = args.signature_period / args.increment
            if round(ratio) < 1 or abs(ratio - round(ratio)) > 1e-9:
                raise ValueError(f"--signature-period {args.signature_period:g} s must be a whole multiple of the increment "
                                 f"{args.increment:g} s")
        fmt = args.format
        if fmt == "auto":
            suffix = args.input.suffix.lower()
            fmt = "trace" if suffix == ".csv" else "gcode" if suffix in GCODE_SUFFIXES else None
            if fmt is None:
                raise ValueError(f"{args.input}: cannot tell a trace from G-code by the suffix {args.input.suffix!r}; "
                                 "give --format")
        bad = refuse_unused(args, [
            ("max_gap", fmt == "gcode", "applies to a trace only, not to G-code"),
            ("feed_tolerance", fmt == "gcode", "applies to a trace only, not to G-code"),
            ("signature_period", args.signature is None, "applies with --signature only"),
            ("plot_increment", args.plot is None, "applies with --plot only"),
        ])
        if bad:
            raise ValueError(bad)
        inputs = (args.input, machine.source)
        check_distinct({"--out": args.out, "--signature": args.signature})
        check_output_path(args.out, inputs=inputs, force=args.force)
        if args.signature is not None:
            check_output_path(args.signature, inputs=inputs, force=args.force, what="--signature")
        if args.plot is not None:
            check_output_dir(args.plot, ["factors.png"], inputs=inputs, force=args.force, what="--plot")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TraceWarning)
            if fmt == "trace":
                inc = increments_from_trace(args.input, machine, args.increment, max_gap_s=args.max_gap,
                                            feed_tolerance=args.feed_tolerance, bins_per_segment=args.bins_per_segment)
            else:
                inc = increments_from_motion(machine, read_gcode(args.input, machine), args.increment, args.bins_per_segment)
        for w in caught:
            if issubclass(w.category, TraceWarning):
                print(f"warning: {w.message}", file=sys.stderr)
            else:  # not ours: hand it on unchanged
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        loads = boundary_conditions(machine, inc, args.power)
        for k in args.plot_increment or []:
            if not -len(inc) <= k < len(inc):
                raise ValueError(f"--plot-increment {k}: there are {len(inc)} increments (0 .. {len(inc) - 1})")
        if args.plot is not None:
            ks = args.plot_increment or [int(np.argmax(inc.axis_factor.mean(axis=1)))]
            pictures = {k: f"histogram_{k % len(inc):04d}.png" for k in ks}
            check_output_dir(args.plot, ["factors.png", *pictures.values()], inputs=inputs, force=args.force,
                             what="--plot")
    except (MachineFileError, TraceFileError, ValueError) as exc:
        return _fail(exc)
    with atomic_path(args.out) as tmp:
        write_bcs(tmp, loads)
    print(f"wrote {args.out} ({len(loads.time_s)} rows: {len(inc)} increments of {args.increment:g} s, "
          f"{len(loads.names)} columns)", file=sys.stderr)
    if args.signature is not None:
        try:
            with atomic_path(args.signature) as tmp:
                write_signatures(tmp, inc, SignatureLayout.of(machine), args.signature_period)
        except ValueError as exc:
            return _fail(exc)
        print(f"wrote {args.signature}", file=sys.stderr)
    if args.plot is not None:
        from hybridcomp.histogram.plots import plot_factors, plot_increment

        try:
            files = [args.plot / "factors.png"]
            with atomic_path(files[0]) as tmp:
                plot_factors(inc, tmp)
            for k, name in pictures.items():
                files.append(args.plot / name)
                with atomic_path(files[-1]) as tmp:
                    plot_increment(inc, k, tmp)
        except (RuntimeError, IndexError) as exc:
            return _fail(exc)
        print(f"wrote {', '.join(str(f) for f in files)}", file=sys.stderr)
    return 0
