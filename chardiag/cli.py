"""``hybridcomp cd``: training data, CD fit, evaluation and CNC export, and the CD database.

Commands::

    hybridcomp cd train-data --machine vmc800 --cases basic,simultaneous --out data.csv
    hybridcomp cd fit data.csv --cases basic_X,basic_Y,basic_Z,basic_spindle --out cds/ [--db cds.sqlite --activate]
    hybridcomp cd eval cds/ --data data.csv --cases simultaneous --out pred.csv
    hybridcomp cd eval cds/ --point T1=21.3,T2=22.0,... --cnc 840d
    hybridcomp cd db list|show|search|activate|import|export --db cds.sqlite ...
    hybridcomp cd fit-grid --pose-rom POSES.rom.npz --out grid/ [--db cds.sqlite --activate]   (chardiag.cli_grid)
    hybridcomp cd db grid-activate|grid-search|grid-export ...
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from hybridcomp.fem.cli_batch import WORKERS_RULE, add_scheduler_arguments, check_scheduler
from hybridcomp.fem.cli_simulate import SCHEME_HELP, add_scheme_arguments, chosen_scheme
from hybridcomp.models import jsonio
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.pose import parse_pairs, parse_pose
from hybridcomp.safeio import FORCE_HELP, atomic_path, check_output_dir, check_output_path, write_text_atomic

log = logging.getLogger(__name__)

DEFAULT_DB = "hybridcomp-cds.sqlite"
# database actions that only read: they open the database read-only and never create one
READ_ONLY_DB_ACTIONS = ("list", "show", "search", "export", "grid-search", "grid-export")





def add_fit_options(p) -> None:
    """The CD fitter's options (:class:`hybridcomp.chardiag.fit.FitOptions`), for ``cd fit`` and ``cd fit-grid``."""
    p.add_argument("--support", type=int, default=6, help="support points per active input (default %(default)s)")
    p.add_argument("--smoothing", type=float, default=1.0, help="second-difference smoothing λ (default %(default)s)")
    p.add_argument("--min-range-K", type=float, default=0.5,
                   help="temperature inputs with a smaller range in the data are inactive [K] (default %(default)s)")
    p.add_argument("--select", choices=("threshold", "bic"), default="threshold",
                   help="input selection: range and correlation thresholds, or also greedy forward selection by BIC")
    p.add_argument("--max-inputs", type=int, help="at most this many active inputs per CD")
    p.add_argument("--max-full-dims", type=int, default=3,
                   help="up to this many active inputs one full grid; above, an additive CD (default %(default)s)")


def fit_options(args):
    """The :class:`~hybridcomp.chardiag.fit.FitOptions` of :func:`add_fit_options`' arguments."""
    from hybridcomp.chardiag.fit import FitOptions

    return FitOptions(n_support=args.support, smoothing=args.smoothing, min_range_K=args.min_range_K,
                      select=args.select, max_inputs=args.max_inputs, max_full_dims=args.max_full_dims)


def load_cases_of(machine, items, heat_hours: float, cool_hours: float) -> dict:
    """The load cases named in ``--cases``: bundled ones by name, the others read from their files."""
    from hybridcomp.chardiag.training import STANDARD_CASES, load_case_from_file, standard_load_cases

    cases = {}
    for item in items:
        if item in STANDARD_CASES:
            cases.update(standard_load_cases(machine, [item], heat_hours, cool_hours))
        else:
            lc = load_case_from_file(machine, item)
            cases[lc.name] = lc
    return cases

def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp cd`` actions and their options."""
    sub = p.add_subparsers(dest="cd_command", metavar="ACTION")
    sub.required = True

    t = sub.add_parser("train-data", help="simulate load cases on the FE model → training table CSV",
                       description="Simulate load cases on the FE model at one pose and write the training table: "
                       "load_case, time_s, T*_degC, <axis>_mm, dx_um, dy_um, dz_um (signatures in '# signature' "
                       "lines at the top). " + SCHEME_HELP)
    add_machine_argument(t)
    t.add_argument("--cases", default="basic,simultaneous,jobshop",
                   help="comma-separated: bundled groups 'basic' (each axis alone at max feed, the spindle alone, "
                   "then cooling), 'simultaneous', 'jobshop', and/or files (G-code .nc, trace CSV, loads CSV) "
                   "(default: %(default)s)")
    t.add_argument("--out", required=True, type=Path, help="training table CSV to write")
    t.add_argument("--pose", help="axis positions in mm, e.g. X=100,Y=-50,Z=0 (default: mid travel)")
    t.add_argument("--element-size-mm", type=float, help="FE element size [mm] (default: the machine file's)")
    add_scheme_arguments(t, "loads interpolated onto it, outputs at the loads rows; TR-BDF2 steps the loads rows")
    t.add_argument("--heat-hours", type=float, default=8.0, help="heating time of the basic/simultaneous cases [h]")
    t.add_argument("--cool-hours", type=float, default=8.0, help="cooling time after them [h]")
    add_scheduler_arguments(t)
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.add_argument("--force", action="store_true", help=FORCE_HELP)

    f = sub.add_parser("fit", help="fit the X, Y, Z CDs of a pose to a training table → XML files",
                       description="Fit one CD per direction to a training table and write DIR/cd_X.xml, cd_Y.xml, "
                       "cd_Z.xml (schema-valid) and DIR/fit.json; optionally store and activate them in the database.")
    f.add_argument("data", type=Path, help="training table CSV (from 'cd train-data' or any CSV with T*_degC and "
                   "dx_um/dy_um/dz_um columns)")
    add_machine_argument(f)
    f.add_argument("--out", required=True, type=Path, help="output directory")
    f.add_argument("--pose", help="pose of the training data, e.g. X=0,Y=0,Z=0 (default: mid travel)")
    f.add_argument("--cases", help="comma-separated load cases of the table to train on (default: all)")
    add_fit_options(f)
    f.add_argument("--with-positions", action="store_true", help="also offer the axis positions (*_mm) as inputs")
    f.add_argument("--db", help="also store the CDs in this database (file path or SQLAlchemy URL)")
    f.add_argument("--activate", action="store_true", help="and make them the active set of the pose")
    f.add_argument("--no-plot", action="store_true", help="no fit.png")
    f.add_argument("--force", action="store_true", help=FORCE_HELP)

    e = sub.add_parser("eval", help="evaluate CDs on a table or at one point; CNC export of the offsets",
                       description="Evaluate the CDs of a directory (cd_X.xml, cd_Y.xml, cd_Z.xml) on a table "
                       "(predictions and residuals) or at one point (offsets, optionally for the CNC).")
    e.add_argument("cds", type=Path, help="directory with cd_X.xml, cd_Y.xml, cd_Z.xml, or one CD XML file")
    add_machine_argument(e)
    e.add_argument("--data", type=Path, help="table CSV to evaluate on (T*_degC columns; dx_um... for residuals)")
    e.add_argument("--cases", help="comma-separated load cases of the table (default: all)")
    e.add_argument("--point", help="one point: T1=21.3,T2=22.1,... [°C] (and X=.. [mm] for position inputs)")
    e.add_argument("--cnc", choices=("generic", "840d"),
                   help="with --point: print the compensation as a generic per-axis table or as Siemens 840D sl "
                   "setting data (SD43900/SD43910/SD43920)")
    e.add_argument("--axis-names", help="with --cnc 840d: control axis identifiers, e.g. X=X1,Y=Y1,Z=Z1")
    e.add_argument("--out", type=Path, help="write predictions (with --data) or the CNC text (with --point) here")
    e.add_argument("--force", action="store_true", help=FORCE_HELP)

    from hybridcomp.chardiag.cli_grid import add_db_grid_arguments, add_fit_grid_arguments

    add_fit_grid_arguments(sub)

    d = sub.add_parser("db", help="the CD database: list, show, search, activate, import, export",
                       description="The CD database (SQLite file by default, any SQLAlchemy URL such as "
                       "postgresql+psycopg://user:password@host/db).")
    dsub = d.add_subparsers(dest="db_command", metavar="ACTION")
    dsub.required = True

    def db_arg(q):
        q.add_argument("--db", default=DEFAULT_DB, help="database file or SQLAlchemy URL (default %(default)s)")

    # list, show, search and export only read the database: they never create one (a missing database is an error)
    q = dsub.add_parser("list", help="stored CDs")
    db_arg(q)
    q.add_argument("--machine-name", help="only CDs of this machine")
    q = dsub.add_parser("show", help="one CD: inputs, fit, reference temperatures")
    db_arg(q)
    q.add_argument("id", type=int)
    q = dsub.add_parser("search", help="stored CD sets that fit a load case (reference temperatures within a threshold)")
    db_arg(q)
    q.add_argument("--machine-name", required=True, help="machine name")
    q.add_argument("--pose-key", required=True, help="pose key as listed, e.g. X=0,Y=0,Z=0")
    q.add_argument("--temperatures", required=True, help="current sensor temperatures: T1=21.3,T2=22.1,... [°C]")
    q.add_argument("--signature", help="current load-case signature: comma-separated numbers")
    q.add_argument("--threshold-K", type=float, default=0.5, help="max |T_reference − T| [K] (default %(default)s)")
    q = dsub.add_parser("activate", help="make three stored CDs (X, Y, Z) the active set of their pose, atomically")
    db_arg(q)
    q.add_argument("ids", help="X=ID,Y=ID,Z=ID")
    q.add_argument("--reason", default="manual activation", help="recorded in the activation event")
    q = dsub.add_parser("import", help="store CD XML files (validated; checked against --machine if given)",
                        description="Store CD XML files in one transaction: all of them or, if one is invalid, none. "
                        "A CD whose XML is already stored is not stored again.")
    db_arg(q)
    q.add_argument("files", nargs="+", type=Path)
    q.add_argument("--machine", help="check the CDs against this machine file or bundled name")
    q = dsub.add_parser("export", help="write stored CDs as XML files")
    db_arg(q)
    q.add_argument("ids", nargs="+", type=int)
    q.add_argument("--out", required=True, type=Path, help="output directory")
    q.add_argument("--force", action="store_true", help=FORCE_HELP)
    add_db_grid_arguments(dsub, db_arg)




def run(args: argparse.Namespace) -> int:
    """Run a ``hybridcomp cd`` action; returns the exit code (1: no stored set found, 2: bad input)."""
    from hybridcomp.chardiag.cd import CDError
    from hybridcomp.chardiag.cli_grid import fit_grid_command
    from hybridcomp.chardiag.db import CDDatabaseError
    from hybridcomp.chardiag.fit import CDFitError
    from hybridcomp.chardiag.training import TrainingDataError
    from hybridcomp.chardiag.xmlio import CDXmlError
    from hybridcomp.fem.loads import LoadsFileError
    from hybridcomp.models.machine import MachineFileError

    handlers = {"train-data": _train_data, "fit": _fit, "eval": _eval, "db": _db, "fit-grid": fit_grid_command}
    try:
        bad = refuse_unused(args, _unused_rules(args))
        if bad:
            raise ValueError(bad)
        return handlers[args.cd_command](args)
    except (CDError, CDFitError, CDXmlError, CDDatabaseError, TrainingDataError, MachineFileError, LoadsFileError,
            ValueError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _unused_rules(args) -> list:
    """(option, has no effect, why) of each subcommand's options that work only together with another."""
    c = args.cd_command
    if c == "train-data":
        heated = not {i.strip() for i in args.cases.split(",")}.isdisjoint({"basic", "simultaneous"})
        why = "applies to the basic and simultaneous load cases only (the job-shop day and files have their own times)"
        return [("workers", args.scheduler not in ("process", "local"), WORKERS_RULE),
                ("heat_hours", not heated, why), ("cool_hours", not heated, why)]
    if c == "fit-grid":
        from hybridcomp.chardiag.cli_grid import unused_rules

        return unused_rules(args)
    if c == "fit":
        return [("activate", args.db is None, "needs --db (the database to activate the CDs in)")]
    if c == "eval":
        return [("force", args.out is None, "applies with --out only"),
                ("cases", args.point is not None, "applies with --data only, not with --point"),
                ("cnc", args.point is None, "applies with --point only"),
                ("axis_names", args.cnc != "840d", "applies with --cnc 840d only")]
    return []


def _train_data(args) -> int:
    from hybridcomp.chardiag.training import (
        STANDARD_CASES,
        simulate_load_cases,
        write_training_csv,
    )
    from hybridcomp.models.loader import load_machine

    machine = load_machine(args.machine)
    pose = machine.check_pose(parse_pose(args.pose))
    scheme, theta = chosen_scheme(args)
    check_scheduler(args.scheduler, args.workers)
    items = [c.strip() for c in args.cases.split(",") if c.strip()]
    check_output_path(args.out, inputs=[machine.source, *(i for i in items if i not in STANDARD_CASES)],
                      force=args.force)
    cases = load_cases_of(machine, items, args.heat_hours, args.cool_hours)
    print(f"simulating {len(cases)} load case(s) on {machine.name} at {pose}: {', '.join(cases)}", file=sys.stderr)
    data = simulate_load_cases(machine, cases, pose, args.element_size_mm, args.dt, theta, scheme=scheme,
                               progress=not args.no_progress,
                               executor=None if args.scheduler == "serial" else args.scheduler, workers=args.workers)
    with atomic_path(args.out) as tmp:
        write_training_csv(tmp, data)
    print(f"wrote {args.out} ({len(data)} rows)", file=sys.stderr)
    return 0


def _fit(args) -> int:
    from hybridcomp.chardiag.cd import DIRECTIONS, pose_key
    from hybridcomp.chardiag.fit import candidate_inputs, fit_cd
    from hybridcomp.chardiag.training import read_training_csv
    from hybridcomp.chardiag.xmlio import check_machine, write_cd
    from hybridcomp.models.loader import load_machine

    machine = load_machine(args.machine)
    pose = machine.check_pose(parse_pose(args.pose))
    data = read_training_csv(args.data)
    if args.cases:
        data = data.subset([c.strip() for c in args.cases.split(",") if c.strip()])
    opts = fit_options(args)
    cands = candidate_inputs(list(data.columns), positions=args.with_positions)
    sensors = {s.name for s in machine.sensors}
    unknown = [n for n, u in cands if u == "degC" and n not in sensors]
    if unknown:
        raise ValueError(f"{args.data}: column {unknown[0]}_degC is not a sensor of machine {machine.name!r} "
                         f"(sensors: {', '.join(sorted(sensors))})")
    outputs = [f"cd_{d}.xml" for d in DIRECTIONS] + ["fit.json"] + ([] if args.no_plot else ["fit.png"])
    check_output_dir(args.out, outputs, inputs=(args.data, machine.source, _db_file(args.db)), force=args.force)
    if args.db and args.activate:  # a monitoring daemon holding the pose chooses its active set: refused before work
        _refuse_held_pose(args.db, machine.name, pose_key(pose))
    cases = ",".join(data.cases)
    sig = data.signature()
    cds = {}
    for d in DIRECTIONS:
        cds[d] = fit_cd(data.columns, d, machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose,
                        candidates=cands, options=opts, load_case=cases, signature=sig, source=str(args.data))
        check_machine(cds[d], machine, str(args.data))
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {}
    for d, cd in cds.items():
        write_cd(args.out / f"cd_{d}.xml", cd)
        summary[d] = {"active_inputs": [i.name for i in cd.active_inputs],
                      "inputs": {i.name: i.reason for i in cd.inputs}, **cd.fit_stats()}
        st = cd.fit_stats()
        print(f"{cd.target}: {len(cd.active_inputs)} active inputs ({', '.join(i.name for i in cd.active_inputs)}), "
              f"{cd.n_values} values ({cd.memory_bytes} bytes), rms residual {st['rms_residual_um']:.3f} µm of "
              f"{st['rms_target_um']:.3f} µm", file=sys.stderr)
    info = {"machine": machine.name, "pose_mm": pose, "load_cases": list(data.cases), "rows": len(data),
            "options": opts.__dict__, "directions": summary}
    if args.db:
        from hybridcomp.chardiag.db import CDDatabase

        with CDDatabase(args.db) as db:
            ids = db.add_set(cds)
            info["db_ids"] = ids
            if args.activate:
                db.activate(machine.name, cds["X"].pose_key, ids, reason=f"cd fit {args.data.name}")
        print(f"stored in {args.db}: {ids}" + (" (active)" if args.activate else ""), file=sys.stderr)
    write_text_atomic(args.out / "fit.json", jsonio.dumps(info, indent=2, default=str))
    if not args.no_plot:
        _plot_fit(args.out / "fit.png", cds, data)
    print(f"wrote {args.out}/cd_X.xml, cd_Y.xml, cd_Z.xml, fit.json", file=sys.stderr)
    return 0


def _plot_fit(path: Path, cds, data) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("note: no fit.png (matplotlib missing: pip install 'hybridcomp[plot]')", file=sys.stderr)
        return
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    x = np.arange(len(data))
    for ax, cd in zip(axes, cds.values()):
        pred, _ = cd.evaluate_table(data.columns)
        y = data.columns[cd.target]
        ax.plot(x, y, lw=1.2, label=f"FE {cd.target}")
        ax.plot(x, pred, lw=1.0, ls="--", label="CD")
        ax.plot(x, y - pred, lw=0.8, label="residual")
        ax.set_ylabel("[µm]")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    starts = [int(np.flatnonzero(data.load_case == c)[0]) for c in data.cases]
    for ax in axes:
        for s in starts[1:]:
            ax.axvline(s, color="0.7", lw=0.8)
    axes[0].set_title(f"CD fit on {', '.join(data.cases)}")
    axes[-1].set_xlabel("training row (load cases separated by grey lines)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _load_cds(path: Path, machine):
    from hybridcomp.chardiag.cd import DIRECTIONS, CDSet
    from hybridcomp.chardiag.xmlio import read_cd

    if path.is_dir():
        files = {d: path / f"cd_{d}.xml" for d in DIRECTIONS}
        missing = [str(f) for f in files.values() if not f.is_file()]
        if missing:
            raise ValueError(f"{path}: CD file(s) missing: {', '.join(missing)}")
        return CDSet({d: read_cd(f, machine) for d, f in files.items()})
    cd = read_cd(path, machine)
    return {cd.direction: cd}


def _eval(args) -> int:
    from hybridcomp.chardiag.cd import CDSet
    from hybridcomp.chardiag.export import axis_offsets, generic_table, siemens_840d
    from hybridcomp.chardiag.training import read_training_csv
    from hybridcomp.models.loader import load_machine

    machine = load_machine(args.machine)
    cds = _load_cds(args.cds, machine)
    cd_map = cds.cds if isinstance(cds, CDSet) else cds
    if (args.data is None) == (args.point is None):
        raise ValueError("give either --data TABLE.csv or --point T1=..,T2=..")
    if args.out is not None:
        cd_files = [args.cds / f"cd_{d}.xml" for d in cd_map] if args.cds.is_dir() else [args.cds]
        check_output_path(args.out, inputs=[*cd_files, args.data, machine.source], force=args.force)
    if args.point is not None:
        values = parse_pairs(args.point, "--point")
        if args.cnc:
            if not isinstance(cds, CDSet):
                raise ValueError("--cnc needs a directory with all three CDs (cd_X.xml, cd_Y.xml, cd_Z.xml)")
            offs = axis_offsets(cds, values)
            names = {k: v for k, v in (p.split("=", 1) for p in args.axis_names.split(","))} if args.axis_names else None
            text = generic_table(offs) if args.cnc == "generic" else siemens_840d(
                offs, names, header=f"machine {machine.name}, pose {cds.pose_key}")
        else:
            from hybridcomp.chardiag.guard import guard_offsets

            rows = []
            for cd in cd_map.values():
                v, out = cd.evaluate_point(values)
                v = guard_offsets({cd.target: v}, source="cd eval --point")[cd.target]
                rows.append(f"{cd.target} = {v:.4f} µm" + ("  (outside the trained range: clamped)" if out else ""))
            text = "\n".join(rows) + "\n"
        if args.out:
            write_text_atomic(args.out, text)
            print(f"wrote {args.out}", file=sys.stderr)
        else:
            sys.stdout.write(text)
        return 0
    data = read_training_csv(args.data)
    if args.cases:
        data = data.subset([c.strip() for c in args.cases.split(",") if c.strip()])
    cols = {"load_case": data.load_case}
    if "time_s" in data.columns:
        cols["time_s"] = data.columns["time_s"]
    for cd in cd_map.values():
        pred, outside = cd.evaluate_table(data.columns)
        cols[f"{cd.target[:-3]}_cd_um"] = pred
        cols[f"{cd.target[:-3]}_outside"] = outside.astype(int)
        if cd.target in data.columns:
            y = data.columns[cd.target]
            r = y - pred
            cols[f"{cd.target[:-3]}_residual_um"] = r
            rms_y = float(np.sqrt(np.mean(y**2)))
            print(f"{cd.target}: rms residual {np.sqrt(np.mean(r**2)):.3f} µm of {rms_y:.3f} µm uncompensated "
                  f"({100 * np.sqrt(np.mean(r**2)) / rms_y if rms_y else float('nan'):.1f} %), "
                  f"{int(outside.sum())} of {len(r)} rows outside the trained range", file=sys.stderr)
    if args.out:
        import csv

        with atomic_path(args.out) as tmp, tmp.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(list(cols))
            for i in range(len(data)):
                w.writerow([c[i] if k == "load_case" else repr(float(c[i])) for k, c in cols.items()])
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _db_file(db: str | None) -> Path | None:
    """The file of an SQLite ``--db`` (an input of the command), or None."""
    from hybridcomp.chardiag.db import sqlite_file

    return sqlite_file(db)


def _refuse_held_pose(db_arg: str, machine: str, pose: str) -> None:
    """Refuse (:class:`~hybridcomp.chardiag.db.CDDatabaseError`) when a monitoring daemon holds the pose."""
    from hybridcomp.chardiag.db import CDDatabase

    file = _db_file(db_arg)
    if file is not None and not file.exists():
        return  # a database yet to be made: no daemon holds anything in it
    with CDDatabase(db_arg, readonly=True) as db:
        db.check_pose_free(machine, pose)


def _db(args) -> int:
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.xmlio import read_cd, write_cd

    c = args.db_command
    if c == "import":  # every file is read and checked before the database is opened: a bad one stores nothing
        machine = None
        if args.machine:
            from hybridcomp.models.loader import load_machine

            machine = load_machine(args.machine)
        to_store = [read_cd(f, machine) for f in args.files]
    with CDDatabase(args.db, readonly=c in READ_ONLY_DB_ACTIONS) as db:
        if c.startswith("grid-"):
            from hybridcomp.chardiag.cli_grid import db_grid_command

            return db_grid_command(args, db)
        if c == "list":
            rows = db.list(args.machine_name)
            if not rows:
                print("no CDs stored")
            for r in rows:
                rms = "-" if r["rms_residual_um"] is None else f"{r['rms_residual_um']:.3f}"
                print(f"{r['id']:>5}  {r['machine']:<12} {r['pose_key']:<24} {r['direction']}  "
                      f"{r['load_case']:<40} inputs {r['n_active_inputs']:>2}  rms {rms:>8} µm  {r['created']}"
                      + ("  ACTIVE" if r["active"] else ""))
            from hybridcomp.chardiag.cli_grid import list_grids

            list_grids(db, args.machine_name)
        elif c == "show":
            cd = db.get(args.id)
            st = cd.fit_stats()
            print(f"CD {args.id}: {cd.machine} pose {cd.pose_key} {cd.target}, load case {cd.load_case}, "
                  f"created {cd.created}, hybridcomp {cd.software_version}")
            for i in cd.inputs:
                state = f"active, [{i.min:.3f}, {i.max:.3f}] {i.unit}, {i.n_support} points" if i.active else "inactive"
                print(f"  {i.name:<6} {state}: {i.reason}")
            print(f"  {len(cd.terms)} term(s), {cd.n_values} values, {cd.memory_bytes} bytes; smoothing {cd.smoothing}")
            print("  fit: " + ", ".join(f"{k} {v:.4g}" for k, v in st.items()))
            print("  T_reference: " + ", ".join(f"{k} {v:.2f} °C" for k, v in cd.t_reference_degC))
        elif c == "search":
            temps = parse_pairs(args.temperatures, "--temperatures")
            sig = np.array([float(v) for v in args.signature.split(",")]) if args.signature else None
            from hybridcomp.chardiag.cd import pose_key

            pkey = pose_key(parse_pairs(args.pose_key, "--pose-key"))  # one key however it is spelled
            found = db.search(args.machine_name, pkey, sig, temps, args.threshold_K)
            if not found:
                print(f"no stored CD set within {args.threshold_K} K")
                return 1
            for m in found:
                print(f"{m.load_case:<40} ids {m.ids}  ΔT {m.delta_T_K:.3f} K  distance {m.distance:.4f}")
        elif c == "activate":
            ids = {k: int(v) for k, v in parse_pairs(args.ids, "ids").items()}
            cd = db.get(ids.get("X", next(iter(ids.values()))))
            db.activate(cd.machine, cd.pose_key, ids, reason=args.reason)
            print(f"active for {cd.machine} {cd.pose_key}: {ids}")
        elif c == "import":
            for f, (cd_id, stored) in zip(args.files, db.add_many(to_store)):
                print(f"{f}: stored as id {cd_id}" if stored else f"{f}: already stored as id {cd_id}")
        elif c == "export":
            cds = {i: db.get(i) for i in args.ids}
            names = {i: f"cd_{i}_{cd.direction}.xml" for i, cd in cds.items()}
            check_output_dir(args.out, names.values(), inputs=(_db_file(args.db),), force=args.force)
            for i, cd in cds.items():
                p = write_cd(args.out / names[i], cd)
                print(f"wrote {p}")
    return 0
