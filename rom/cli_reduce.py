"""``hybridcomp reduce``: a machine's FE model (or exported matrices) → a reduced model ``ROM.npz``.

Everything is checked before the (minutes-long) reduction starts, so a bad
input fails at once and writes nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from hybridcomp.fem.cli_batch import WORKERS_RULE, add_scheduler_arguments, check_scheduler
from hybridcomp.fem.poses import parse_levels
from hybridcomp.models import jsonio
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.loader import load_machine
from hybridcomp.models.machine import MachineFileError
from hybridcomp.safeio import FORCE_HELP, check_output_path

#: L-BFGS iterations of the h2 basis of an exported system at a stated order by default: on the public rail
#: benchmarks 1,500 leave rail_1357 at r = 40 at 2.5x balanced truncation, 20,000 bring it to 1.2x (38 s;
#: rom/README.md); the bisection of --h2-tol keeps 1,500 per order
EXTERNAL_H2_MAXITER = 20000


def _h_range(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--h-range must be LOW,HIGH factors of nominal, e.g. 0.5,2; got {text!r}") from None
    return lo, hi


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp reduce`` options."""
    add_machine_argument(p)
    p.add_argument("--matrices", type=Path, metavar="FILE",
                   help="reduce an exported system E x' = A x + B u, y = C x + D u instead: a .mat file (variables A, B, "
                   "C; E, the identity when absent, and D, zero when absent) or a directory of Matrix Market files "
                   "A.mtx, B.mtx, C.mtx (E.mtx, D.mtx optional)")
    p.add_argument("--out", required=True, type=Path, help="reduced model to write (.npz with JSON metadata); an "
                   "existing file (a model a monitor configuration reads) is replaced only with --force")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument("--pose", help="axis positions in mm, e.g. X=100,Y=-50,Z=0 (default: mid travel)")
    p.add_argument("--element-size-mm", type=float, help="largest element edge [mm] (default: from the machine file)")
    p.add_argument("--order", type=int,
                   help="reduce to exactly this order instead of to the tolerances (with --matrices beyond the "
                   "system's minimal realisation: a warning, and the best of the candidates, decoupled states added)")
    p.add_argument("--tol-K", type=float, default=0.05,
                   help="sensor-temperature tolerance [K] against FE on the check load case (default 0.05); "
                   "with --matrices: the transfer-function (H∞) tolerance per unit input, in output units (bt: the smallest "
                   "order whose bound 2 Σ of the truncated Hankel singular values is below it)")
    p.add_argument("--tol-um", type=float, default=0.2, help="TCP-drift tolerance [µm] (default 0.2)")
    p.add_argument("--h-range", type=_h_range, default=(0.5, 2.0), metavar="LOW,HIGH",
                   help="heat-transfer coefficients the model must cover, as factors of nominal (default 0.5,2)")
    p.add_argument("--check-loads", type=Path, help="loads CSV of the FE check (default: the 16 h example day at 60 s)")
    p.add_argument("--basis", choices=("auto", "bt", "irka", "krylov", "h2"),
                   help="auto (--matrices only, its default): bt, and at a stated --order up to 5,000 states also "
                   "irka, the smaller exact H2 error kept; bt: square-root balanced truncation, for any stable system "
                   "(non-symmetric A, D ≠ 0), dense Gramian factors up to 2,000 states (400 for non-symmetric A), "
                   "low-rank ADI above; irka: "
                   "two-sided IRKA from three starts (bt's model, shifts log-spaced over the spectrum and around its "
                   "fastest rate), the best kept; "
                   "krylov: greedy rational Krylov basis, then its Gramian compression; h2: the one-sided basis "
                   "with the smallest H2 error (L-BFGS inside a large Krylov surrogate), keeping the s = 0 block when "
                   "the order allows (a machine's model); krylov and h2 keep the model symmetric, stable and affine "
                   "in h (with --matrices: symmetric A only). Default: auto with --matrices, krylov for a machine")
    p.add_argument("--h2-tol", type=float, metavar="REL",
                   help="with --matrices, instead of --order: the smallest order whose exact relative H2 error is at "
                   "most REL, found by bisection")
    p.add_argument("--fastest-time-s", type=float, metavar="T",
                   help="with --matrices and --basis krylov or h2: the shortest time scale to resolve, in the "
                   "system's time unit (default: from the system, its balanced model's fastest pole)")
    p.add_argument("--h2-maxiter", type=int, metavar="N",
                   help="with the h2 basis: L-BFGS iterations per basis (default 1500; 20000 for --matrices with "
                   "--order); more iterations, smaller H2 error (150 mm mesh, --order 80: about 30 s per 1,000 "
                   "iterations; the rail benchmark, 1,357 states, order 40: 38 s for 20,000)")
    p.add_argument("--poses", choices=("star", "grid"),
                   help="also give the drift at every pose: a reduced model per support pose (star: every axis at its "
                   "levels (its travel ends, and more with --pose-levels) with the others at --pose; grid: all 3^n), "
                   "each on its own FE model, "
                   "its drift an output group beside the model pose's (simulate --rom writes it to poses.csv, the drives' "
                   "errors to feedback.csv); interpolated by hybridcomp.rom.poses.drift_along; as the daemon's "
                   "monitor.rom it compensates where the tool is. The written model keeps no basis")
    p.add_argument("--pose-levels", metavar="AXIS=N[,AXIS=N]",
                   help="with --poses: N levels along an axis instead of 3 (odd: the model's pose and evenly spaced "
                   "levels on either side down to the travel's ends, piecewise quadratic between them), e.g. Y=7 "
                   "where the drift along the table's axis kinks as the tool leaves the table; star: N-1 support "
                   "poses on that axis instead of 2; a bare N: N along every axis (3: the plain star); auto: 7 along "
                   "every axis on which the tool leaves the table (with [table_reference] under_tool) or that "
                   "carries the tool (vmc800: Y and Z, 15 support poses). Default: auto with star, 3 with grid")
    p.add_argument("--pose-enrich", type=int, metavar="N",
                   help="with --poses: Krylov directions of each support pose's own system added to the carried basis "
                   "(default 20)")
    add_scheduler_arguments(p, "with --poses, the support poses as an FE batch: ")
    p.add_argument("--no-basis", action="store_true",
                   help="do not store the basis V (smaller file, no full-field reconstruction)")


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp reduce``; returns the exit code (2: bad input, named on stderr)."""
    from hybridcomp.fem.loads import LoadsFileError, read_loads
    from hybridcomp.models.pose import parse_pose
    from hybridcomp.rom.external import MatrixFileError
    from hybridcomp.rom.reduced import save_rom

    t0 = time.perf_counter()
    matrices = args.matrices is not None
    if args.basis is None:  # balanced truncation for exported systems, krylov for a machine's model
        args.basis = "auto" if matrices else "krylov"
    fe_only = "applies to a machine's FE model only, not to --matrices"
    bad = refuse_unused(args, [
        ("machine", matrices, fe_only),
        ("pose", matrices, fe_only),
        ("element_size_mm", matrices, fe_only),
        ("tol_um", matrices, fe_only + " (exported matrices have no TCP-drift output)"),
        ("h_range", matrices, fe_only + " (exported matrices have no convection coefficients)"),
        ("check_loads", matrices, fe_only + " (the FE check runs on the machine's model)"),
        ("basis", matrices and args.basis == "h2" and args.order is None and args.h2_tol is None,
         "h2 with --matrices needs --order or --h2-tol (the H2-optimal basis is built for one order, or searched "
         "for the smallest order reaching an exact relative H2 error)"),
        ("basis", not matrices and args.basis in ("auto", "bt", "irka"),
         f"{args.basis} applies with --matrices only (a machine's model keeps the symmetric one-sided bases, affine in h)"),
        ("h2_tol", not matrices, "applies with --matrices only (a machine's model is reduced to --tol-K, --tol-um)"),
        ("h2_tol", args.order is not None, "cannot be combined with --order (the order decides)"),
        ("fastest_time_s", not matrices, "applies with --matrices only"),
        ("fastest_time_s", args.basis not in ("krylov", "h2"), "applies with --basis krylov or h2 only (bt and irka take "
         "their shifts from the system)"),
        ("h2_maxiter", args.basis != "h2", "applies with the h2 basis only"),
        ("tol_K", matrices and (args.order is not None or args.h2_tol is not None),
         "has no effect with --matrices and --order or --h2-tol (those decide)"),
        ("poses", matrices, fe_only),
        ("pose_enrich", args.poses is None, "applies with --poses only"),
        ("pose_levels", args.poses is None, "applies with --poses only"),
        ("workers", args.poses is None, "applies with --poses only (the support poses run as an FE batch)"),
        ("scheduler", args.poses is None, "applies with --poses only (the support poses run as an FE batch)"),
        ("workers", args.scheduler not in ("process", "local"), WORKERS_RULE),
        ("no_basis", args.poses is not None, "has no effect with --poses (a pose-aware model keeps no basis)"),
    ])
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    try:
        check_scheduler(args.scheduler, args.workers)
        if args.pose_enrich is not None and args.pose_enrich < 0:
            raise ValueError(f"--pose-enrich must be a non-negative integer, got {args.pose_enrich}")
        if args.order is not None and args.order < 1:
            raise ValueError(f"--order must be a positive integer, got {args.order}")
        if args.h2_maxiter is not None and args.h2_maxiter < 0:
            raise ValueError(f"--h2-maxiter must be a non-negative integer, got {args.h2_maxiter}")
        if not (args.tol_K > 0 and args.tol_um > 0):
            raise ValueError(f"--tol-K and --tol-um must be positive, got {args.tol_K} and {args.tol_um}")
        lo, hi = args.h_range
        if not 0 < lo <= 1 <= hi:
            raise ValueError(f"--h-range must satisfy 0 < LOW ≤ 1 ≤ HIGH, got {lo},{hi}")
        if args.element_size_mm is not None and not args.element_size_mm > 0:
            raise ValueError(f"--element-size-mm must be positive, got {args.element_size_mm}")
        if args.matrices is not None:
            from hybridcomp.rom.external import reduce_matrices

            _check_out(args, [args.matrices, *(_matrix_files(args.matrices))])

            rom = reduce_matrices(args.matrices, tol=None if args.order or args.h2_tol else args.tol_K, order=args.order,
                                  h2_tol=args.h2_tol, fastest_time_s=args.fastest_time_s,
                                  keep_basis=not args.no_basis, basis=args.basis, progress=True,
                                  h2_maxiter=args.h2_maxiter if args.h2_maxiter is not None else
                                  EXTERNAL_H2_MAXITER if args.order is not None else 1500)
        else:
            machine = load_machine(args.machine)
            _check_out(args, [machine.source, args.check_loads])
            pose = machine.check_pose(parse_pose(args.pose))
            ends = [a.name for a in machine.axes if args.poses and pose[a.name] in a.travel_mm]
            if ends:
                raise ValueError(f"--poses needs the model's pose inside the travel: --pose puts {ends[0]} at a travel "
                                 "end, where the support poses would coincide")
            levels = None if args.pose_levels is None else parse_levels(  # None: reduce_at_poses' default
                args.pose_levels, [a.name for a in machine.axes], machine)
            check = read_loads(args.check_loads, machine) if args.check_loads else None
            if check is not None and len(check.time_s) < 2:
                raise LoadsFileError(f"{args.check_loads}: needs at least two rows")
    except (MachineFileError, LoadsFileError, MatrixFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.matrices is None:
        from hybridcomp.fem.model import build_model
        from hybridcomp.rom.machine import reduce_model

        print(f"meshing and assembling {machine.name} at {pose} ...", file=sys.stderr)
        model = build_model(machine, pose, args.element_size_mm)
        print(f"reducing {model.n} nodes ...", file=sys.stderr)
        rom = reduce_model(model, tol_K=args.tol_K, tol_um=args.tol_um, order=args.order, h_range=args.h_range,
                           check_loads=check, keep_basis=not args.no_basis, basis=args.basis, progress=True,
                           **({} if args.h2_maxiter is None else {"h2_maxiter": args.h2_maxiter}))
        if args.poses is not None:
            from hybridcomp.rom.poses import DEFAULT_ENRICH, reduce_at_poses

            print(f"reducing at the {args.poses} support poses ...", file=sys.stderr)
            scale = None if check is None else np.abs(machine.layout().inputs(check)).max(axis=0)
            rom = reduce_at_poses(model, rom, args.poses, DEFAULT_ENRICH if args.pose_enrich is None else args.pose_enrich,
                                  input_scale=scale, workers=_workers(args),
                                  scheduler="process" if args.scheduler == "serial" else args.scheduler,
                                  progress=True, levels=levels)
    if args.matrices is not None:
        from hybridcomp.rom.external import save_external

        save_external(args.out, rom)  # atomically, as save_rom
    else:
        save_rom(args.out, rom)  # atomically: a temporary file renamed over --out
    summary = {"out": str(args.out), "order": rom.order, "seconds": round(time.perf_counter() - t0, 2)}
    if rom.meta.get("poses"):
        summary["support_poses"] = len(rom.meta["poses"]["poses"])
    if "check" in rom.meta:
        c = rom.meta["check"]
        summary.update(max_sensor_error_K=max(c["max_sensor_error_K"]), max_drift_error_um=max(c["max_drift_error_um"]),
                       passed=c["passed"])
        if not c["passed"]:
            print(f"warning: {args.out} does NOT meet the tolerances on the FE check: sensors off by up to "
                  f"{summary['max_sensor_error_K']:.3g} K (--tol-K {args.tol_K:g}), drift by up to "
                  f"{summary['max_drift_error_um']:.3g} µm (--tol-um {args.tol_um:g})"
                  + (f" at --order {args.order}" if args.order is not None else "")
                  + "; its metadata says passed = false", file=sys.stderr)
    else:
        m = rom.meta
        summary.update(basis=m["basis"], order_asked=m["order_asked"], stable=m["stable"],
                       h2_error_relative=m["h2_error_relative"], h2_error_exact=m["h2_error_exact"],
                       hinf_error_relative=m["hinf_error_relative"])
        if m.get("h2_tol") is not None:
            summary["h2_tol_met"] = m["h2_tol_met"]
            if not m["h2_tol_met"]:
                print(f"warning: relative H2 error {m['h2_error_relative']:.3g} above --h2-tol {m['h2_tol']:g} at the "
                      f"largest order with a balanced direction ({rom.order})", file=sys.stderr)
        if m.get("order_asked") is not None and m["order_asked"] > m["minimal_order"]:
            print(f"warning: --order {m['order_asked']} is beyond the system's minimal realisation: only "
                  f"{m['minimal_order']} Hankel singular values are above round-off (1e-14 σ₁), so no model of "
                  f"{m['order_asked']} states is more accurate than one of {m['minimal_order']}"
                  + (f"; {m['decoupled_states']} of its states are decoupled (B = 0, C = 0)"
                     if m["decoupled_states"] else f"; {m['method'].split(' (')[0]} gave all of them")
                  + f" (relative H2 error {m['h2_error_relative']:.3g})", file=sys.stderr)
        if not m["stable"]:
            print(f"warning: the reduced model is NOT stable (a pole with real part {m['max_pole_real_part']:.3g}); "
                  "try --basis bt, or --basis h2 / krylov for symmetric A (stable by construction)", file=sys.stderr)
        print(f"reduced {m['nodes']} states to {rom.order} ({m['method']}); relative H2 error "
              f"{m['h2_error_relative']:.3g} ({m['h2_error_note']}); relative H∞ error {m['hinf_error_relative']:.3g} "
              f"on {m['hinf_grid_rad_per_time_unit'][2]} frequencies; stable: {m['stable']}", file=sys.stderr)
    print(jsonio.dumps(summary))
    return 0


def _matrix_files(matrices: Path) -> list[Path]:
    """The Matrix Market files of a ``--matrices`` directory (inputs: --out may be none of them)."""
    return sorted(matrices.glob("*.mtx")) if matrices.is_dir() else []


def _check_out(args, inputs) -> None:
    """``--out``: never an input, a link or a folder, an existing file only with ``--force`` (before any work)."""
    check_output_path(args.out, inputs=inputs, force=args.force)


def _workers(args) -> int:
    """Worker processes of ``--scheduler``: one for serial (here, one after another), else --workers or the cores."""
    if args.scheduler == "serial":
        return 1
    return args.workers or os.cpu_count() or 1
