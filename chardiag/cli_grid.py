"""``hybridcomp cd fit-grid`` and ``cd db grid-*``: CD sets per support point (:mod:`hybridcomp.chardiag.grid`).

Commands::

    hybridcomp cd fit-grid --pose-rom POSES.rom.npz --cases basic,simultaneous --grid-points 3 --out grid/
        [--db cds.sqlite --activate]
    hybridcomp cd db grid-activate ID --db cds.sqlite
    hybridcomp cd db grid-search --machine-name vmc800 --temperatures T1=21.3,... --db cds.sqlite
    hybridcomp cd db grid-export ID --out DIR --db cds.sqlite

``cd db list`` shows the stored grids after the CDs.  The fallback of the support-point table for a monitor that
runs a one-pose structure model: the daemon evaluates the active grid's sets every cycle (``monitor/README.md``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from hybridcomp.models import jsonio
from hybridcomp.models.cli import add_machine_argument
from hybridcomp.models.pose import parse_pairs
from hybridcomp.safeio import FORCE_HELP, atomic_path, check_output_dir, write_text_atomic

#: grid database actions that only read the database
READ_ONLY_GRID_ACTIONS = ("grid-search", "grid-export")


def add_fit_grid_arguments(sub) -> None:
    """The ``cd fit-grid`` action."""
    g = sub.add_parser("fit-grid", help="CD sets per support point of a workspace grid, from a pose-aware model",
                       description="Run load cases on a pose-aware reduced model (reduce --poses star|grid), take the "
                       "drift at every support point of a grid over the travel (the drives' errors included, the "
                       "machine standing at the point) with the sensor temperatures, fit one CD set (X, Y, Z) per "
                       "point and write DIR/grid.json and DIR/pNN/cd_X.xml, cd_Y.xml, cd_Z.xml, training.csv; "
                       "optionally store the grid in the database (and activate it: every point's set and the grid). "
                       "A monitor with a one-pose structure model and an active grid writes the support-point table "
                       "from these sets every cycle.")
    add_machine_argument(g)
    g.add_argument("--pose-rom", required=True, type=Path, help="pose-aware reduced model (reduce --poses star|grid)")
    g.add_argument("--cases", default="basic,simultaneous",
                   help="comma-separated: bundled groups 'basic', 'simultaneous', 'jobshop', and/or files (G-code "
                   ".nc, trace CSV, loads CSV) (default: %(default)s)")
    g.add_argument("--heat-hours", type=float, default=8.0, help="heating time of the basic/simultaneous cases [h]")
    g.add_argument("--cool-hours", type=float, default=8.0, help="cooling time after them [h]")
    g.add_argument("--grid-points", type=int, default=3,
                   help="support points per axis (default %(default)s: travel min, model pose, travel max)")
    from hybridcomp.chardiag.cli import add_fit_options

    add_fit_options(g)
    g.add_argument("--out", required=True, type=Path, help="output directory")
    g.add_argument("--db", help="also store the grid in this database (file path or SQLAlchemy URL)")
    g.add_argument("--activate", action="store_true", help="and make it the machine's active grid")
    g.add_argument("--force", action="store_true", help=FORCE_HELP)


def add_db_grid_arguments(dsub, db_arg) -> None:
    """The ``cd db grid-*`` actions."""
    q = dsub.add_parser("grid-activate", help="make a stored CD grid active: every support point's set and the grid")
    db_arg(q)
    q.add_argument("id", type=int, help="grid id (cd db list)")
    q.add_argument("--reason", default="manual activation", help="recorded in the grid activation event")
    q = dsub.add_parser("grid-search", help="stored CD grids that fit a load case (reference temperatures within a "
                        "threshold at every point)")
    db_arg(q)
    q.add_argument("--machine-name", required=True, help="machine name")
    q.add_argument("--temperatures", required=True, help="current sensor temperatures: T1=21.3,T2=22.1,... [°C]")
    q.add_argument("--signature", help="current load-case signature: comma-separated numbers")
    q.add_argument("--threshold-K", type=float, default=0.5, help="max |T_reference − T| [K] (default %(default)s)")
    q = dsub.add_parser("grid-export", help="write a stored CD grid: grid.json and every point's CDs as XML")
    db_arg(q)
    q.add_argument("id", type=int, help="grid id (cd db list)")
    q.add_argument("--out", required=True, type=Path, help="output directory")
    q.add_argument("--force", action="store_true", help=FORCE_HELP)


def unused_rules(args) -> list:
    """(option, has no effect, why) of ``cd fit-grid``."""
    heated = not {i.strip() for i in args.cases.split(",")}.isdisjoint({"basic", "simultaneous"})
    why = "applies to the basic and simultaneous load cases only (the job-shop day and files have their own times)"
    return [("activate", args.db is None, "needs --db (the database to store and activate the grid in)"),
            ("heat_hours", not heated, why), ("cool_hours", not heated, why)]


def _point_dir(i: int, n: int) -> str:
    return f"p{i:0{max(2, len(str(n - 1)))}d}"


def _grid_files(n: int, training: bool) -> list[str]:
    names = ["grid.json"]
    for i in range(n):
        names += [f"{_point_dir(i, n)}/cd_{d}.xml" for d in "XYZ"]
        if training:
            names.append(f"{_point_dir(i, n)}/training.csv")
    return names


def _write_grid(out: Path, grid, info: dict, data=None) -> None:
    from hybridcomp.chardiag.training import write_training_csv
    from hybridcomp.chardiag.xmlio import write_cd

    n = grid.grid.n_points
    for i, s in enumerate(grid.sets):
        d = out / _point_dir(i, n)
        d.mkdir(parents=True, exist_ok=True)
        for k, cd in s.cds.items():
            write_cd(d / f"cd_{k}.xml", cd)
        if data is not None:
            with atomic_path(d / "training.csv") as tmp:
                write_training_csv(tmp, data.tables[i])
    write_text_atomic(out / "grid.json", jsonio.dumps(info, indent=2, default=str))


def _summary(grid, residuals=None) -> dict:
    from hybridcomp.chardiag.grid import point_keys

    pts = []
    for i, (key, s) in enumerate(zip(point_keys(grid.grid), grid.sets)):
        row = {"point": i, "pose_key": key, "ids": dict(s.ids),
               "rms_residual_um": {d: s.cds[d].fit_stats().get("rms_residual_um") for d in "XYZ"},
               "active_inputs": {d: [x.name for x in s.cds[d].active_inputs] for d in "XYZ"}}
        if residuals is not None:
            row["rms_residual_um"] = dict(zip("XYZ", (float(v) for v in residuals[i])))
        pts.append(row)
    return {"machine": grid.machine, "grid": grid.grid.as_dict(), "grid_id": grid.grid_id,
            "load_case": grid.load_case, "points": pts}


def fit_grid_command(args) -> int:
    """Run ``cd fit-grid``; returns the exit code."""
    from hybridcomp.chardiag.grid import fit_grid, grid_residuals, grid_training_data
    from hybridcomp.chardiag.training import STANDARD_CASES
    from hybridcomp.chardiag.xmlio import check_machine
    from hybridcomp.models.loader import load_machine
    from hybridcomp.rom.poses import grid_of
    from hybridcomp.rom.reduced import load_rom
    from hybridcomp.rom.volumetric import default_grid

    machine = load_machine(args.machine)
    items = [c.strip() for c in args.cases.split(",") if c.strip()]
    if not items:
        raise ValueError("--cases is empty")
    from hybridcomp.chardiag.cli import _db_file, fit_options, load_cases_of

    inputs = (args.pose_rom, machine.source, _db_file(args.db), *(Path(i) for i in items if i not in STANDARD_CASES))
    check_output_dir(args.out, ["grid.json"], inputs=inputs, force=args.force)  # before any work
    prom = load_rom(args.pose_rom, machine)
    grid_of(prom)  # a one-pose model: refused with its message
    grid = default_grid(prom, args.grid_points)
    check_output_dir(args.out, _grid_files(grid.n_points, True), inputs=inputs, force=args.force)
    opts = fit_options(args)
    cases = load_cases_of(machine, items, args.heat_hours, args.cool_hours)
    print(f"running {len(cases)} load case(s) on {args.pose_rom} at {grid.n_points} support points "
          f"{'x'.join(map(str, grid.shape))}: {', '.join(cases)}", file=sys.stderr)
    data = grid_training_data(prom, cases, grid)
    cdg = fit_grid(data, machine=machine.name, machine_sha256=machine.sha256, options=opts, source=str(args.pose_rom))
    for s in cdg.sets:
        for cd in s.cds.values():
            check_machine(cd, machine, str(args.pose_rom))
    res = grid_residuals(cdg, data)
    print(f"fit residual at the support points (RMS over the training rows): largest {res.max():.3f} µm, mean "
          f"x {res[:, 0].mean():.3f}, y {res[:, 1].mean():.3f}, z {res[:, 2].mean():.3f} µm", file=sys.stderr)
    if args.db:
        from hybridcomp.chardiag.db import CDDatabase

        with CDDatabase(args.db) as db:
            gid = db.add_grid(cdg)
            if args.activate:
                db.activate_grid(gid, reason=f"cd fit-grid {args.pose_rom.name}")
            cdg = db.grid(gid)
        print(f"stored in {args.db} as grid {gid}" + (" (active)" if args.activate else ""), file=sys.stderr)
    info = _summary(cdg, res) | {"rom_id": prom.rom_id, "load_cases": list(cases), "options": opts.__dict__}
    args.out.mkdir(parents=True, exist_ok=True)
    _write_grid(args.out, cdg, info, data)
    print(f"wrote {args.out}/grid.json and {grid.n_points} point folders", file=sys.stderr)
    return 0


def list_grids(db, machine: str | None) -> None:
    """The stored grids, after ``cd db list``'s CDs."""
    rows = db.grids(machine)
    if not rows:
        print("no CD grids stored")
    for r in rows:
        rms = "-" if r["max_rms_residual_um"] is None else f"{r['max_rms_residual_um']:.3f}"
        print(f"grid {r['id']:>4}  {r['machine']:<12} {'x'.join(map(str, r['shape'])):<8} "
              f"{','.join(r['axes']):<8} {r['load_case']:<40} max rms {rms:>8} µm  {r['created']}"
              + ("  ACTIVE" if r["active"] else ""))


def db_grid_command(args, db) -> int:
    """``cd db grid-activate|grid-search|grid-export`` on an open database."""
    c = args.db_command
    if c == "grid-activate":
        db.activate_grid(args.id, reason=args.reason)
        g = db.grids()
        row = next(r for r in g if r["id"] == args.id)
        print(f"active grid for {row['machine']}: {args.id} ({'x'.join(map(str, row['shape']))} support points)")
    elif c == "grid-search":
        temps = parse_pairs(args.temperatures, "--temperatures")
        sig = np.array([float(v) for v in args.signature.split(",")]) if args.signature else None
        found = db.search_grids(args.machine_name, sig, temps, args.threshold_K)
        if not found:
            print(f"no stored CD grid within {args.threshold_K} K")
            return 1
        for m in found:
            print(f"grid {m.grid_id:>4}  {m.load_case:<40} ΔT {m.delta_T_K:.3f} K  distance {m.distance:.4f}")
    elif c == "grid-export":
        from hybridcomp.chardiag.cli import _db_file

        check_output_dir(args.out, ["grid.json"], inputs=(_db_file(args.db),), force=args.force)  # before reading
        g = db.grid(args.id)
        check_output_dir(args.out, _grid_files(g.grid.n_points, False), inputs=(_db_file(args.db),), force=args.force)
        args.out.mkdir(parents=True, exist_ok=True)
        _write_grid(args.out, g, _summary(g))
        print(f"wrote {args.out}/grid.json and {g.grid.n_points} point folders")
    return 0
