"""``hybridcomp simulate``: a load case on the FE model → ``DIR/outputs.csv``.

Everything is checked (machine file, pose, loads CSV) before anything is
written, so a bad input leaves no half-written output directory.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from hybridcomp.fem.loads import LoadsFileError, read_loads, write_outputs
from hybridcomp.fem.stepping import DEFAULT_THETA, DEFAULT_TOLERANCE, TimeTolerance
from hybridcomp.models import jsonio
from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.models.loader import load_machine
from hybridcomp.models.loads import check_outputs
from hybridcomp.models.machine import MachineFileError
from hybridcomp.models.pose import parse_pose
from hybridcomp.safeio import FORCE_HELP, atomic_path, check_output_dir, write_text_atomic

log = logging.getLogger(__name__)


SCHEME_HELP = (
    f"Default time scheme: TR-BDF2 (second order, L-stable: no ringing after a step in power) in sub-steps of the "
    f"loads intervals, refined until the estimated time error is within {DEFAULT_TOLERANCE.sensor_K} K and "
    f"{DEFAULT_TOLERANCE.drift_um} um at the loads times; --dt and/or --theta choose the θ-method instead (θ = 1, "
    f"backward Euler, unless --theta says otherwise): cheaper per run, without error control."
)
"""What the help of every command that runs the FE model says of its default time scheme (one default for all)."""


def add_scheme_arguments(p: argparse.ArgumentParser, dt_help: str) -> None:
    """``--dt`` and ``--theta`` of a command whose default scheme is TR-BDF2 (:data:`SCHEME_HELP`)."""
    p.add_argument("--dt", type=float, help=f"θ-method at this time step [s] ({dt_help}); default: TR-BDF2, see the "
                   "description")
    p.add_argument("--theta", type=float, help="θ of the θ-method, in [0.5, 1]: 1 backward Euler (with --dt alone), "
                   "0.5 Crank-Nicolson; default: TR-BDF2, see the description")


def chosen_scheme(args: argparse.Namespace) -> tuple[str, float | None]:
    """The time scheme and θ that ``--dt`` and ``--theta`` choose: TR-BDF2 without either, else the θ-method.

    Raises ``ValueError`` naming the option for a ``--dt`` that is not positive or a ``--theta`` outside [0.5, 1].
    """
    if args.dt is not None and not args.dt > 0:
        raise ValueError(f"--dt must be positive, got {args.dt}")
    if args.theta is not None and not 0.5 <= args.theta <= 1.0:
        raise ValueError(f"--theta must be in [0.5, 1], got {args.theta}")
    if args.dt is None and args.theta is None:
        return "trbdf2", None
    return "theta", DEFAULT_THETA if args.theta is None else float(args.theta)


def time_tolerance(args: argparse.Namespace) -> TimeTolerance | None:
    """The tolerance of the default, error-controlled scheme, or None when ``--dt``/``--theta`` choose the θ-method."""
    tols = {"--time-tol-K": args.time_tol_K, "--time-tol-um": args.time_tol_um}
    for flag, v in tols.items():
        if not v > 0:
            raise ValueError(f"{flag} must be positive, got {v}")
    if args.dt is None and args.theta is None:
        return TimeTolerance(sensor_K=args.time_tol_K, drift_um=args.time_tol_um)
    changed = [flag for flag, v, d in (("--time-tol-K", args.time_tol_K, DEFAULT_TOLERANCE.sensor_K),
                                       ("--time-tol-um", args.time_tol_um, DEFAULT_TOLERANCE.drift_um)) if v != d]
    if changed:
        chosen = "--dt" if args.dt is not None else "--theta"
        raise ValueError(f"{changed[0]} applies to the default error-controlled scheme, not with {chosen} (the θ-method "
                         "at a chosen step has no error control)")
    return None


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp simulate`` options."""
    add_machine_argument(p)
    p.add_argument("--loads", required=True, type=Path,
                   help="BC time series CSV: time_s, <source>[<segment>]_W, <zone>_degC; a missing column is zero power "
                   "or the reference temperature, an unknown column is an error")
    p.add_argument("--out", required=True, type=Path,
                   help="output directory (outputs.csv, run.json, fields, picture); files of an earlier run in it are "
                   "overwritten only with --force, an input never")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument("--pose", help="axis positions in mm, e.g. X=100,Y=-50,Z=0 (default: mid travel)")
    p.add_argument("--element-size-mm", type=float, help="largest element edge [mm] (default: from the machine file)")
    p.add_argument("--dt", type=float,
                   help="time step [s] of the θ-method (loads resampled linearly); with --dt or --theta the run uses "
                   "the θ-method and reports no time-error estimate. Default: TR-BDF2 (second order, L-stable: no "
                   "ringing after steps in power) in equal sub-steps of the loads CSV's intervals, doubled until the "
                   "estimated error bound of every output at the loads times (the difference between runs with 2m and m "
                   "sub-steps, about 3x the error of the 2m run that is written) is within "
                   "--time-tol-K and --time-tol-um; run.json reports the estimate, the steps and step sizes")
    p.add_argument("--theta", type=float,
                   help="θ of the θ-method, in [0.5, 1]: 1 backward Euler, 0.5 Crank-Nicolson; without --dt at the "
                   "loads CSV's own times; --dt alone means θ = 1")
    p.add_argument("--time-tol-K", type=float, default=DEFAULT_TOLERANCE.sensor_K,
                   help=f"accepted time-discretisation error of the sensor temperatures [K] (default "
                   f"{DEFAULT_TOLERANCE.sensor_K}; the default scheme only)")
    p.add_argument("--time-tol-um", type=float, default=DEFAULT_TOLERANCE.drift_um,
                   help=f"accepted time-discretisation error of the drift dx, dy, dz [µm] (default "
                   f"{DEFAULT_TOLERANCE.drift_um}; the default scheme only)")
    p.add_argument("--initial", choices=("steady", "reference"), default="steady",
                   help="initial state: steady state of the first loads row (default) or the reference temperature")
    p.add_argument("--fields", type=int, default=0, metavar="N",
                   help="also write the full temperature and displacement field at N evenly spaced steps")
    p.add_argument("--field-format", choices=("vtu", "xdmf"), default="vtu", help="field file format (xdmf needs h5py)")
    p.add_argument("--png", action="store_true",
                   help="render temperature on the deformed machine at the last step (needs pyvista)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--rom", type=Path, metavar="ROM.npz",
                   help="simulate with this reduced model (from 'hybridcomp reduce') instead of FE: exact stepping, "
                   "same outputs.csv (the sensors and the drift at the model's pose); a pose-aware model (reduce "
                   "--poses) also writes poses.csv (pose<k>_dx_um, _dy_um, _dz_um: the drift at support pose k, "
                   "whose axis positions run.json lists under support_poses_mm) and feedback.csv "
                   "(<axis>_feedback_um@<x>: each drive's positioning error at axis position x [mm]); every table's "
                   "header names its columns. The ROM must come from the --machine file as it is now")


def stored_steps(args: argparse.Namespace, nt: int) -> tuple[int, ...]:
    """The steps whose full fields are kept: ``--fields N`` evenly spaced ones, and the last with ``--png``."""
    store = set()
    if args.fields > 0:
        store = set(np.linspace(0, nt - 1, args.fields).round().astype(int).tolist())
    if args.png:
        store.add(nt - 1)
    return tuple(sorted(store))


def output_files(args: argparse.Namespace, nt: int) -> list[str]:
    """The files ``simulate`` writes into ``--out`` for a loads series of ``nt`` rows, relative to it."""
    files = ["outputs.csv", "run.json"]
    if args.fields > 0:
        if args.field_format == "vtu":  # every stored step (with --png the last one too)
            files += [f"fields/field_{k:05d}.vtu" for k in stored_steps(args, nt)]
        else:
            files += ["fields/fields.xdmf", "fields/fields.h5"]
    if args.png:
        files.append("machine.png")
    return files


def run(args: argparse.Namespace, reduced=None) -> int:
    """Run ``hybridcomp simulate``; returns the exit code (2: bad input, named on stderr).

    ``reduced(args, machine, pose, loads) -> int`` runs the checked inputs on ``--rom``'s reduced model
    (:func:`hybridcomp.rom.cli_simulate.run_rom`, which the ``simulate`` subcommand passes; fem knows no rom).
    """
    bad = refuse_unused(args, [("field_format", args.fields <= 0, "applies with --fields N only")])
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    try:
        machine = load_machine(args.machine)
        pose = machine.check_pose(parse_pose(args.pose))
        loads = read_loads(args.loads, machine)
        chosen_scheme(args)  # --dt and --theta checked before any work
        if args.dt is not None:
            loads = loads.resample(args.dt)
        if len(loads.time_s) < 2:
            raise LoadsFileError(f"{args.loads}: needs at least two rows (a start and an end time)")
        if args.element_size_mm is not None and not args.element_size_mm > 0:
            raise ValueError(f"--element-size-mm must be positive, got {args.element_size_mm}")
        tolerance = time_tolerance(args)
        check_output_dir(args.out, output_files(args, len(loads.time_s)),
                         inputs=(args.loads, machine.source, getattr(args, "rom", None)), force=args.force)
    except (MachineFileError, LoadsFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if getattr(args, "rom", None) is not None:
        if reduced is None:
            raise TypeError("--rom needs the reduced-model path: run(args, reduced=hybridcomp.rom.cli_simulate.run_rom)")
        return reduced(args, machine, pose, loads)

    from hybridcomp.fem.model import build_model
    from hybridcomp.fem.stepping import solver_backends

    t0 = time.perf_counter()
    progress = not args.no_progress
    if progress:
        print(f"meshing and assembling {machine.name} at {pose} ...", file=sys.stderr)
    try:
        model = build_model(machine, pose, args.element_size_mm)
    except MachineFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    nt = len(loads.time_s)
    store = stored_steps(args, nt)
    if tolerance is not None:
        res = model.simulate(loads, args.initial, scheme="trbdf2", tolerance=tolerance, store_steps=store,
                             progress=progress)
        time_info = res.time_error
        if not time_info["met"]:
            print(f"warning: estimated time error {time_info['estimate_sensor_K']:.3g} K, "
                  f"{time_info['estimate_drift_um']:.3g} um exceeds the tolerance ({tolerance.sensor_K} K, "
                  f"{tolerance.drift_um} um) at {time_info['substeps_per_interval']} sub-steps per loads interval",
                  file=sys.stderr)
    else:
        _, theta = chosen_scheme(args)
        res = model.simulate(loads, args.initial, scheme="theta", theta=theta, store_steps=store, progress=progress)
        time_info = {
            "scheme": "theta-method", "theta": theta,
            "steps": nt - 1, "step_sizes_s": sorted(set(np.round(np.diff(loads.time_s), 9).tolist())),
            "estimate_sensor_K": None, "estimate_drift_um": None,
            "estimate": "none: the θ-method at a chosen --dt/--theta is not error-controlled",
        }
    check_outputs(res.time_s, model.sensor_names, res.sensors_degC, res.drift_um, f"simulate {machine.source}")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "outputs.csv") as tmp:
        write_outputs(tmp, res.time_s, model.sensor_names, res.sensors_degC, res.drift_um)
    files = ["outputs.csv"]
    if args.fields > 0:
        from hybridcomp.fem.export import write_fields

        paths = write_fields(model, out / "fields", {k: res.fields_K[k] for k in store if k in res.fields_K},
                             res.time_s, fmt=args.field_format)
        files += [str(p.relative_to(out)) for p in paths]
    if args.png:
        from hybridcomp.fem.export import render_png

        try:
            with atomic_path(out / "machine.png") as tmp:
                render_png(model, res.fields_K[nt - 1], tmp,
                           title=f"{machine.name} at t = {res.time_s[-1] / 3600:.2f} h, pose {pose}")
            files.append("machine.png")
        except RuntimeError as exc:  # pictures are optional: the numbers are already written
            print(f"warning: {exc}", file=sys.stderr)
    info = {
        "machine": machine.name,
        "machine_file": Path(machine.source).name,
        "machine_sha256": machine.sha256,
        "pose_mm": pose,
        "nodes": model.n,
        "elements": int(model.mesh.mesh.t.shape[1]),
        "steps": time_info["steps"],
        "time": time_info,
        "timings_s": {**model.timings_s, **res.timings_s, "total": time.perf_counter() - t0},
        "solvers": solver_backends(model),
        "files": files,
    }
    write_text_atomic(out / "run.json", jsonio.dumps(info, indent=2))
    print(f"wrote {out / 'outputs.csv'} ({nt} rows, {model.n} nodes, {info['timings_s']['total']:.1f} s)", file=sys.stderr)
    return 0
