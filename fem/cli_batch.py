"""``hybridcomp batch run LOADS_DIR``: many load cases on the FE model → ``OUT/<case>.csv``.

Every ``*.csv`` in LOADS_DIR is a load case named by its file stem.  The
cases run where ``--scheduler`` says, with the one meaning it has in every
command that runs FE load cases (``batch run``, ``cd train-data``,
``reduce --poses``): ``serial`` (default) here, one after another;
``process`` a local process pool of ``--workers``; ``local`` a Dask
LocalCluster of ``--workers``; ``tcp://HOST:8786`` a running ``dask
scheduler`` with its ``dask worker`` processes.  All inputs are checked
before anything runs.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

from hybridcomp.fem.cli_simulate import SCHEME_HELP, add_scheme_arguments, chosen_scheme
from hybridcomp.fem.loads import LoadsFileError
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.loader import load_machine
from hybridcomp.models.machine import MachineFileError
from hybridcomp.models.pose import parse_pose
from hybridcomp.safeio import FORCE_HELP, check_output_dir

#: what ``--scheduler`` means in every command that runs FE load cases
SCHEDULER_HELP = ("where the FE load cases run: 'serial' (default) here, one after another; 'process' a local process "
                  "pool of --workers processes; 'local' a Dask LocalCluster of --workers processes; or the address "
                  "tcp://HOST:PORT of a running Dask scheduler (the dask extra for 'local' and addresses)")
WORKERS_HELP = "worker processes of --scheduler process or local (default: the number of cores)"
WORKERS_RULE = ("applies with --scheduler process or local only (serial runs here; a running Dask scheduler has "
                "its own workers)")


#: a Dask scheduler address: one of Dask's comm protocols, then the host (and port)
DASK_ADDRESS = r"(tcp|tls|ucx|inproc|ws|wss)://\S+"


def add_scheduler_arguments(p: argparse.ArgumentParser, what: str = "") -> None:
    """``--scheduler`` and ``--workers``, with one meaning in every command that runs FE load cases.

    Parameters
    ----------
    p : the subcommand's parser
    what : a prefix of the help text naming when the options apply (``"with --poses: "``)
    """
    p.add_argument("--scheduler", metavar="WHERE", default="serial", help=what + SCHEDULER_HELP)
    p.add_argument("--workers", type=int, metavar="N", help=what + WORKERS_HELP)


def check_scheduler(scheduler: str, workers: int | None) -> None:
    """Refuse a ``--scheduler`` value outside its one meaning and a ``--workers`` below one (ValueError)."""
    if scheduler not in ("serial", "process", "local") and not re.fullmatch(DASK_ADDRESS, scheduler):
        raise ValueError(f"--scheduler {scheduler!r}: use serial, process, local or a Dask scheduler address such as "
                         "tcp://HOST:8786")
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp batch`` actions and their options."""
    sub = p.add_subparsers(dest="batch_command", metavar="ACTION", required=True)
    r = sub.add_parser(
        "run",
        help="simulate every loads CSV of a directory and write one outputs CSV per case",
        description="Simulate every loads CSV in LOADS_DIR (case name = file stem) on one FE model and write "
        "OUT/<case>.csv (time_s, <sensor>_degC ..., dx_um, dy_um, dz_um) plus OUT/batch.json. Each worker "
        "builds the model once and reuses it for all its cases; each output file is written atomically. "
        + SCHEME_HELP,
    )
    r.add_argument("loads_dir", type=Path, metavar="LOADS_DIR", help="directory of loads CSVs (see 'hybridcomp simulate --help')")
    add_machine_argument(r)
    r.add_argument("--out", required=True, type=Path, help="output directory: one <case>.csv per load case and batch.json")
    add_scheduler_arguments(r)
    r.add_argument("--pose", help="axis positions in mm, e.g. X=100,Y=-50,Z=0 (default: mid travel)")
    r.add_argument("--element-size-mm", type=float, help="largest element edge [mm] (default: from the machine file)")
    add_scheme_arguments(r, "every case resampled linearly; TR-BDF2 keeps each CSV's own times")
    r.add_argument("--initial", choices=("steady", "reference"), default="steady",
                   help="initial state: steady state of the first loads row (default) or the reference temperature")
    r.add_argument("--resume", action="store_true",
                   help="keep the outputs an interrupted run of the same batch (same settings in OUT/batch.json) "
                   "left in OUT and compute only the missing cases")
    r.add_argument("--force", action="store_true", help=FORCE_HELP + " (outputs of an earlier batch in OUT); the "
                   "loads CSVs are never overwritten")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Run a ``hybridcomp batch`` action; returns the exit code (1: a failed batch, 2: bad input)."""
    from hybridcomp.fem.batch import BatchError, read_loads_dir, run_batch

    executor = args.scheduler
    bad = refuse_unused(args, [("workers", executor not in ("process", "local"), WORKERS_RULE)])
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    try:
        check_scheduler(executor, args.workers)
        scheme, theta = chosen_scheme(args)
        machine = load_machine(args.machine)
        pose = machine.check_pose(parse_pose(args.pose))
        cases = read_loads_dir(args.loads_dir, machine)
        # every output checked before any work: never a loads CSV (LOADS_DIR = OUT), a link or, without --force or
        # --resume, an earlier batch's file
        check_output_dir(args.out, [*(f"{name}.csv" for name in cases), "batch.json"],
                         inputs=[*sorted(args.loads_dir.glob("*.csv")), machine.source],
                         force=args.force or args.resume)
        if executor not in ("serial", "process"):
            from hybridcomp.fem.batch import _import_distributed

            _import_distributed()  # before quieting its loggers: importing distributed sets their levels
            if getattr(args, "verbose", 0) < 2:  # Dask logs every connection at INFO; keep the progress bar readable
                logging.getLogger("distributed").setLevel(logging.WARNING)
        if not args.no_progress:
            print(f"{len(cases)} load cases of {machine.name} at {pose} on {executor} ...", file=sys.stderr)
        results = run_batch(machine, cases, pose_mm=pose, element_size_mm=args.element_size_mm, scheme=scheme,
                            theta=theta,
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
