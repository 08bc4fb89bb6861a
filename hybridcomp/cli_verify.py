"""``hybridcomp verify``: the compensation signed off the way a machine-tool builder does it, simulated.

One job-shop day of the real machine (its planted disturbance, its own pose-aware model at every pose it visits)
with the hybrid daemon writing support-point tables, then three studies (:mod:`hybridcomp.verify`): volumetric
calibrations at thermal states of the day, a thermal volumetric model fitted on half of them and judged with the
tables on the rest; a calibration with the workshop air off working temperature, with and without its correction,
for several measurement noises; and a plate with bores cut over the day, measured without compensation, with the
daemon's offsets at one pose and with its tables.  Writes ``report.md``, ``summary.json``, ``part.png``,
``volumetric.png``, ``ambient.png``, ``thermal_map.json`` and ``calibrations.csv`` into ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hybridcomp.safeio import FORCE_HELP, start_folder

DESCRIPTION = ("The thermal compensation verified the way a machine-tool builder signs it off, on one simulated "
               "job-shop day of the real machine: volumetric calibrations at thermal states of the day (a thermal "
               "volumetric model fitted on half, judged with the daemon's support-point tables on the rest); a "
               "calibration with the workshop air off working temperature, with and without its correction; a "
               "plate with bores cut over the day, without compensation, with the offsets at one pose and with "
               "the tables. Writes report.md, summary.json, part.png, volumetric.png, ambient.png, the fitted thermal map "
               "(thermal_map.json) and every calibration point (calibrations.csv) into --out.")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp verify`` options."""
    from hybridcomp.scenario import DISTURBANCES
    from hybridcomp.verify import AmbientOptions, CalibrationPlan, MachiningOptions, VerifyOptions, VolumetricOptions

    d, v, a, m, c = VerifyOptions(), VolumetricOptions(), AmbientOptions(), MachiningOptions(), CalibrationPlan()
    p.description = DESCRIPTION
    p.add_argument("--out", required=True, type=Path, help="output directory (report.md, summary.json, plots); a "
                   "folder that holds anything is written into only with --force")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument("--machine", default=d.machine_name, help="bundled machine name or machine file (default %(default)s)")
    p.add_argument("--disturbance", default=d.disturbance, choices=list(DISTURBANCES), metavar="NAME",
                   help="what the real machine does that the models do not know (default %(default)r; one of: "
                   + ", ".join(DISTURBANCES) + ")")
    p.add_argument("--element-size-mm", type=float, default=d.element_size_mm,
                   help="FE element size of the real machine and the models [mm] (default %(default)s)")
    p.add_argument("--day-hours", type=float, default=d.day_hours, help="hours of the job-shop day (default %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of every noise (default %(default)s)")
    g = p.add_argument_group("calibrations")
    g.add_argument("--plan-levels", type=int, nargs="+", default=list(c.levels), metavar="N",
                   help="poses per axis of a calibration, machine order (default %(default)s)")
    g.add_argument("--seconds-per-point", type=float, default=c.seconds_per_point,
                   help="time from one measured pose to the next [s] (default %(default)s)")
    g.add_argument("--noise-um", type=float, default=c.noise_um,
                   help="measurement noise per direction [µm] (default %(default)s)")
    g.add_argument("--calibrate-every-hours", type=float, default=v.every_h,
                   help="a calibration every this many hours of the day (default %(default)s)")
    g.add_argument("--degree", type=int, default=v.degree, help="degree of the error functions (default %(default)s)")
    g.add_argument("--criterion", choices=("bicc", "bic"), default=v.criterion,
                   help="information criterion of the thermal map's inputs (default %(default)s)")
    g.add_argument("--lag-hours", type=float, nargs="+", default=list(v.lags_h), metavar="H",
                   help="also offer the thermal map each sensor's first-order lag of these time constants [h] (an "
                   "ARX map's inputs; default: the sensors alone)")
    g = p.add_argument_group("ambient during verification")
    g.add_argument("--ambient-K", type=float, default=a.ambient_K,
                   help="air during the calibration minus working temperature [K] (default %(default)s)")
    g.add_argument("--sigmas-um", type=float, nargs="+", default=list(a.sigmas_um), metavar="SIGMA",
                   help="measurement noises to study [µm] (default %(default)s)")
    g.add_argument("--state-hours", type=float, default=a.state_h,
                   help="the working state calibrated: hour of the day (default %(default)s)")
    g = p.add_argument_group("machined part")
    g.add_argument("--bores", type=int, nargs=2, default=[m.columns, m.rows], metavar=("COLUMNS", "ROWS"),
                   help="bores on the plate (default %(default)s)")
    g.add_argument("--bore-every-hours", type=float, default=m.every_h,
                   help="one bore every this many hours (default %(default)s)")
    g.add_argument("--first-bore-hours", type=float, default=m.first_h, help="the first bore's hour (default %(default)s)")


def options_of(args: argparse.Namespace):
    """The :class:`~hybridcomp.verify.VerifyOptions` of the command line (raises VerifyError naming the option)."""
    from hybridcomp.verify import AmbientOptions, CalibrationPlan, MachiningOptions, VerifyOptions, VolumetricOptions

    plan = CalibrationPlan(tuple(args.plan_levels), args.seconds_per_point, args.noise_um)
    return VerifyOptions(
        machine_name=args.machine, disturbance=args.disturbance, element_size_mm=args.element_size_mm,
        day_hours=args.day_hours, seed=args.seed,
        volumetric=VolumetricOptions(plan=plan, every_h=args.calibrate_every_hours, degree=args.degree,
                                     criterion=args.criterion, lags_h=tuple(args.lag_hours)),
        ambient=AmbientOptions(plan=plan, state_h=args.state_hours, ambient_K=args.ambient_K,
                               sigmas_um=tuple(args.sigmas_um), degree=args.degree),
        machining=MachiningOptions(columns=args.bores[0], rows=args.bores[1], first_h=args.first_bore_hours,
                                   every_h=args.bore_every_hours))


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp verify``; returns the exit code (bad input raises: the dispatcher names it and returns 2)."""
    from hybridcomp.histogram.scenarios import JOBSHOP_HOURS
    from hybridcomp.verify import check_options, run_verification

    if not 0 < args.day_hours <= JOBSHOP_HOURS:
        print(f"error: --day-hours must be in (0, {JOBSHOP_HOURS:g}], got {args.day_hours}", file=sys.stderr)
        return 2
    # a VerifyError or OutputPathError is bad input: the dispatcher prints it as one 'error:' line and returns 2
    opts = options_of(args)
    check_options(opts)  # before any file: a study that does not fit in the day
    start_folder(args.out, force=args.force, finals=("summary.json", "report.md"))
    s = run_verification(args.out, opts)
    h, m = s["volumetric"]["held_out"], s["machining"]["largest"]
    print(f"wrote {args.out / 'report.md'}: held-out max TCP error volumetric model "
          f"{h['volumetric model']['max_um']:.2f} µm, tables {h['support-point tables']['max_um']:.2f} µm; part: "
          f"largest bore deviation none {m['no compensation']['largest_position_um']:.1f}, one pose "
          f"{m['hybrid at one pose']['largest_position_um']:.1f}, volumetric "
          f"{m['hybrid volumetric']['largest_position_um']:.1f} µm", file=sys.stderr)
    return 0
