"""``hybridcomp batch run LOADS_DIR``: many load cases on the FE model → ``OUT/<case>.csv``.

Every ``*.csv`` in LOADS_DIR is a load case named by its file stem.  The
cases run on a local process pool by default, or on Dask: ``--scheduler
local`` starts a LocalCluster on this machine, ``--scheduler tcp://HOST:8786``
uses a running ``dask scheduler`` with its ``dask worker`` processes.  All
inputs are checked before anything runs.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from hybridcomp.fem.cli_simulate import parse_pose
from hybridcomp.fem.loads import LoadsFileError
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.loader import load_machine
from hybridcomp.models.machine import MachineFileError


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp batch`` actions and their options."""
    sub = p.add_subparsers(dest="batch_command", metavar="ACTION", required=True)
    r = sub.add_parser(
        "run",
        help="simulate every loads CSV of a directory and write one outputs CSV per case",
        description="Simulate every loads CSV in LOADS_DIR (case name = file stem) on one FE model and write "
        "OUT/<case>.csv (time_s, <sensor>_degC ..., dx_um, dy_um, dz_um) plus OUT/batch.json. Each worker "
        "builds the model once and reuses it for all its cases; each output file is written atomically.",
    )
    r.add_argument("loads_dir", type=Path, metavar="LOADS_DIR", help="directory of loads CSVs (see 'hybridcomp simulate --help')")
    add_machine_argument(r)
    r.add_argument("--out", required=True, type=Path, help="output directory: one <case>.csv per load case and batch.json")
    r.add_argument("--scheduler", metavar="ADDR",
                   help="run on Dask: 'local' for a LocalCluster on this machine, or a scheduler address such as "
                   "tcp://HOST:8786 (default: a local process pool, no Dask needed)")
    r.add_argument("--workers", type=int,
                   help="worker processes of the local pool or the LocalCluster (default: the number of cores)")
    r.add_argument("--serial", action="store_true", help="run in this process, one case after another")
    r.add_argument("--pose", help="axis positions in mm, e.g. X=100,Y=-50,Z=0 (default: mid travel)")
    r.add_argument("--element-size-mm", type=float, help="largest element edge [mm] (default: from the machine file)")
    r.add_argument("--dt", type=float, help="resample every case to this time step [s]; default: each CSV's own times")
    r.add_argument("--theta", type=float, default=1.0, help="θ of the θ-method: 1 backward Euler (default), 0.5 Crank-Nicolson")
    r.add_argument("--initial", choices=("steady", "reference"), default="steady",
                   help="initial state: steady state of the first loads row (default) or the reference temperature")
    r.add_argument("--resume", action="store_true",
                   help="keep the outputs an interrupted run of the same batch (same settings in OUT/batch.json) "
                   "left in OUT and compute only the missing cases")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Run a ``hybridcomp batch`` action; returns the exit code (1: a failed batch, 2: bad input)."""
    from hybridcomp.fem.batch import BatchError, read_loads_dir, run_batch

    if args.serial and args.scheduler:
        print("error: --serial and --scheduler exclude each other", file=sys.stderr)
        return 2
    executor = "serial" if args.serial else args.scheduler or "process"
    bad = refuse_unused(args, [("workers", executor not in ("process", "local"),
                                "applies to the local process pool or --scheduler local only (a running Dask "
                                "scheduler has its own workers; --serial runs here)")])
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    try:
        if executor not in ("serial", "process", "local") and "://" not in executor:
            raise ValueError(f"--scheduler {executor!r}: use 'local' or an address such as tcp://HOST:8786")
        if args.workers is not None and args.workers < 1:
            raise ValueError(f"--workers must be at least 1, got {args.workers}")
        machine = load_machine(args.machine)
        pose = machine.check_pose(parse_pose(args.pose))
        cases = read_loads_dir(args.loads_dir, machine)
        if executor not in ("serial", "process"):
            from hybridcomp.fem.batch import _import_distributed

            _import_distributed()  # before quieting its loggers: importing distributed sets their levels
            if getattr(args, "verbose", 0) < 2:  # Dask logs every connection at INFO; keep the progress bar readable
                logging.getLogger("distributed").setLevel(logging.WARNING)
        if not args.no_progress:
            print(f"{len(cases)} load cases of {machine.name} at {pose} on {executor} ...", file=sys.stderr)
        results = run_batch(machine, cases, pose_mm=pose, element_size_mm=args.element_size_mm, theta=args.theta,
                            initial=args.initial, dt_s=args.dt, executor=executor, workers=args.workers,
                            out_dir=args.out, resume=args.resume, progress=not args.no_progress)
    except (MachineFileError, LoadsFileError, ValueError, ImportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (BatchError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {len(results)} outputs CSVs and batch.json to {args.out}", file=sys.stderr)
    return 0
