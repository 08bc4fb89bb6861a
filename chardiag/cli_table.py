"""``hybridcomp table``: the volumetric table of a pose-aware reduced model at one time, in a CNC form.

    hybridcomp table --rom POSE_ROM.npz --loads LOADS.csv --at-hours H --form csv|json|840d|840d-cec --out FILE

The reduced model (``hybridcomp reduce --poses star``) runs the loads from the steady state of their first row up
to ``--at-hours`` (inputs linear between the rows, the ``simulate`` default), its outputs at that time become the
table over ``--points`` support points per axis (:mod:`hybridcomp.rom.volumetric`), and the table is written in
one form of :mod:`hybridcomp.chardiag.table_export`: ``csv`` (compensation per grid point), ``json`` (the table,
drift), ``840d`` (K3 setting data per axis), ``840d-cec`` (interpolatory compensation tables).  The command lives
beside the CNC export (chardiag), which reads the reduced model's package.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from hybridcomp.models.cli import add_machine_argument
from hybridcomp.safeio import FORCE_HELP, check_output_path, write_text_atomic

FORMS = ("csv", "json", "840d", "840d-cec")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp table`` options."""
    add_machine_argument(p)
    p.add_argument("--rom", required=True, type=Path, help="pose-aware reduced model (reduce --poses star|grid)")
    p.add_argument("--loads", required=True, type=Path, help="loads CSV the model runs (from its first row's steady state)")
    p.add_argument("--at-hours", required=True, type=float,
                   help="time of the table [h], within the loads' time span")
    p.add_argument("--form", required=True, choices=FORMS,
                   help="csv: compensation per grid point [µm]; json: the table (drift) as JSON; 840d: Siemens K3 "
                   "setting data SD43900/SD43910/SD43920 per axis; 840d-cec: Siemens interpolatory compensation "
                   "tables $AN_CEC (mm)")
    p.add_argument("--points", type=int, default=3,
                   help="support points per axis (default 3: travel min, model pose, travel max)")
    p.add_argument("--axis-names", help="with 840d and 840d-cec: control axis identifiers, e.g. X=X1,Y=Y1,Z=Z1")
    p.add_argument("--out", required=True, type=Path, help="file to write")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)


def state_at(rom, loads, at_s: float) -> np.ndarray:
    """The outputs (q,) of ``rom`` at ``at_s`` [s], from the steady state of the first loads row (inputs linear)."""
    t = np.asarray(loads.time_s, float)
    if not t[0] <= at_s <= t[-1]:
        raise ValueError(f"--at-hours {at_s / 3600:g} is outside the loads' time span [{t[0] / 3600:g}, "
                         f"{t[-1] / 3600:g}] h")
    U = rom.layout().inputs(loads.names, loads.values, "loads")
    k = int(np.searchsorted(t, at_s, side="right"))
    tt, UU = t[:k], U[:k]
    if tt[-1] < at_s:
        u = np.array([np.interp(at_s, t, U[:, j]) for j in range(U.shape[1])])
        tt, UU = np.r_[tt, at_s], np.vstack([UU, u])
    Y, _ = rom.integrate(tt, UU)
    return Y[-1]


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp table``; returns the exit code."""
    from hybridcomp.chardiag import table_export as tx
    from hybridcomp.models.cli import refuse_unused
    from hybridcomp.models.loader import load_machine
    from hybridcomp.models.loads import read_loads
    from hybridcomp.rom.reduced import load_rom
    from hybridcomp.rom.volumetric import default_grid, table_of, table_operator

    problem = refuse_unused(args, [("axis_names", args.form in ("csv", "json"), "applies with --form 840d|840d-cec only")])
    if problem:
        raise ValueError(problem)
    if not np.isfinite(args.at_hours):
        raise ValueError(f"--at-hours must be finite, got {args.at_hours}")
    machine = load_machine(args.machine)
    out = check_output_path(args.out, inputs=[args.rom, args.loads, machine.source], force=args.force)
    names = None
    if args.axis_names:
        try:
            names = dict(p.split("=", 1) for p in args.axis_names.split(","))
        except ValueError:
            raise ValueError(f"--axis-names must be AXIS=NAME pairs, e.g. X=X1,Y=Y1; got {args.axis_names!r}") from None
    rom = load_rom(args.rom, machine)
    loads = read_loads(args.loads, machine)
    at_s = args.at_hours * 3600.0
    op = table_operator(rom, default_grid(rom, args.points))
    table = table_of(op, state_at(rom, loads, at_s), at_s)
    header = f"machine {machine.name}, {Path(args.loads).name} at {args.at_hours:g} h, rom {rom.rom_id}"
    if args.form == "csv":
        text = tx.table_csv(table)
    elif args.form == "json":
        text = tx.table_json(table)
    elif args.form == "840d":
        text = tx.siemens_k3(table, names, header=header)
    else:
        text = tx.siemens_cec(table, names, header=header)
    write_text_atomic(out, text)
    print(f"wrote {out} ({args.form}, {op.grid.n_points} support points at {args.at_hours:g} h)", file=sys.stderr)
    return 0
