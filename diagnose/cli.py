"""``hybridcomp diagnose``: what the simulation gets wrong on measured data, the named cause, the extended model, the gain."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from hybridcomp.models.cli import add_machine_argument, refuse_unused
from hybridcomp.safeio import FORCE_HELP, check_output_dir

#: the files ``diagnose`` writes into --out: on the machine's model, and with --data-only (plots last)
MODEL_FILES = ("report.md", "summary.json", "machine_extended.toml")
MODEL_PLOTS = ("residuals.png", "ep95.png", "xcorr.png")
DATA_ONLY_FILES = ("report.md", "summary.json")
DATA_ONLY_PLOTS = ("channels.png", "runs.png")
DATA_ONLY_MODEL = "dataonly_model.json"  # with --probe-every-hours: the model the monitor's strategy dataonly runs

log = logging.getLogger(__name__)


def _write_dataonly_model(d, path: Path) -> None:
    """The regularised model with its coefficient filter, for the monitor's strategy ``dataonly`` (or why not)."""
    from hybridcomp.rom.dataonly_model import model_from_diagnosis, model_to_json
    from hybridcomp.safeio import write_text_atomic

    try:
        text = model_to_json(model_from_diagnosis(d))
    except ValueError as exc:
        print(f"no {path.name}: {exc}")
        return
    write_text_atomic(path, text)
    print(f"data-only model for 'monitor' ([compensation] strategy = \"dataonly\"): {path}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp diagnose`` options."""
    p.description = (
        "Simulate a measured dataset with the machine's reduced model, analyse the residuals (RMS, P2P, fit %, "
        "E_P95(range), cross-correlation), fit a library of named physical effects by bounded least squares, select "
        "them greedily (BIC on the training part, gain on the validation part) and write DIR/report.md with plots, "
        "DIR/summary.json and DIR/machine_extended.toml. With --data-only, diagnose a regression compensation model "
        "fitted to the dataset alone."
    )
    add_machine_argument(p)
    p.add_argument("--data", required=True, type=Path, nargs="+", metavar="MEASURED.csv",
                   help="measured dataset: time_s, heat inputs <input>_W, zone air <zone>_degC (or Tamb_degC, Tws_degC), "
                   "measured sensors <sensor>_degC and dx_um, dy_um, dz_um (unit-suffix names; other names via --map); "
                   "or a trace (time_s, x_mm ..., spindle_rpm, sensors, drift), turned into heat inputs by the histogram "
                   "generator. With --data-only, several files are a campaign: one run each (its own initial state and "
                   "zero; no lag crosses a run boundary); a 'run' column does the same in one file")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory; files of an earlier run "
                   "in it are overwritten only with --force, the inputs (--machine, --data, --map, --rom) never")
    p.add_argument("--force", action="store_true", help=FORCE_HELP)
    p.add_argument("--map", type=Path, metavar="MAP.toml",
                   help="column map: [columns] project_name = \"csv column\", optional [scale] project_name = factor")
    p.add_argument("--train", default="0:60%", metavar="START:END",
                   help="training part in %%, s or h of the record (default 0:60%%); validation is the rest; for a "
                   "campaign (--data-only with several files, one run each, or a 'run' column) also runs:1-12 or "
                   "runs:1,3,5-7")
    p.add_argument("--data-only", action="store_true",
                   help="no FE model: diagnose a multiple linear regression of the *_um channels on the *_degC sensors "
                   "(greedy input selection by BIC) with data-side extensions")
    p.add_argument("--increment", type=float, default=60.0,
                   help="a trace (axis positions, no *_W columns) is turned into heat inputs per increment of this "
                   "length by the histogram generator [s] (default 60)")
    p.add_argument("--rom", type=Path, help="reduced model .npz of this machine (kept basis); default: reduce now")
    p.add_argument("--element-size-mm", type=float, help="FE element size for the reduction [mm] (default: machine file)")
    p.add_argument("--effects", help="comma-separated effect kinds to consider (default: the whole library)")
    p.add_argument("--max-effects", type=int, default=4, help="most effects to name (default 4)")
    p.add_argument("--discretisation-floor", action="store_true",
                   help="know the model's discretisation error: the machine reduced on second, coarser meshes; a "
                        "residual within the meshes' difference counts as explained, an effect the mesh alone could "
                        "make is not named (off by default: minutes more per diagnosis)")
    p.add_argument("--surface-tolerance", type=float, metavar="REL",
                   help="a source anywhere on the surface located to the evidence, not to the reduced model's error: the "
                   "order raised through 150, 200, 250, 300, 400 until the model's error at the sensors for a heat step "
                   "at every surface site is within REL of that site's own response (σ/(3A) for a source A above "
                   "sensor noise σ, e.g. 0.017); at 150 mm order 400, about 2 min more (default: off, the order from "
                   "the machine's own sources)")
    p.add_argument("--place-sources", choices=("patch", "continuous"), default="patch",
                   help="a heat source found anywhere on the surface: 'patch' (default) at the best search site, known "
                        "to the search's confidence region; 'continuous' its place fitted on the face with its power, "
                        "its uncertainty in mm from the fit (several times slower)")
    p.add_argument("--max-terms", type=int, default=16, help="--data-only: most search steps (extension terms added, "
                   "inputs dropped) per channel (default 16)")
    p.add_argument("--beam", type=int, default=16, help="--data-only: models kept per search step; 1 is greedy forward "
                   "selection (default 16)")
    p.add_argument("--selection", choices=("held-out", "assisted"), default="held-out",
                   help="--data-only: 'held-out' (default): every choice by blocked cross-validation on the training "
                   "rows, so the validation fit is held out; 'assisted': the validation rows take part in choosing the "
                   "extensions (their fit flatters; the selection check says by how much)")
    p.add_argument("--folds", type=int, default=3, help="--data-only, --selection held-out: contiguous blocks of the "
                   "training rows for the search's cross-validation and the probe filter's settings (default 3; the "
                   "regularised families are chosen on the curves of 3, 5 and 10 blocks averaged)")
    p.add_argument("--criterion", choices=("bic", "bicc"), default="bic",
                   help="--data-only: the training information criterion that selects the sensor inputs and that every "
                   "search step must lower: 'bic' (Schwarz, default) or 'bicc' (BIC with McQuarrie's small-sample "
                   "correction, for short datasets with few rows per parameter)")
    p.add_argument("--probe-every-hours", type=float, default=None, metavar="H",
                   help="--data-only: post-process gain updating. On the validation rows the drift is taken as "
                   "measured every H hours (a probe cycle in a pause) and the extended model's gain and offset are "
                   "updated from those measurements (a Kalman filter; how fast they may wander is chosen on the "
                   "training rows); the report gives the fit between probes beside the fit without them")
    p.add_argument("--probe-sd-um", type=float, default=0.5, help="--data-only --probe-every-hours: the probe's "
                   "repeatability [µm] (default 0.5)")
    p.add_argument("--no-selection-check", action="store_true", help="--data-only --selection assisted: skip the check "
                   "that repeats the selection on half the validation part and scores it on the other half")
    p.add_argument("--probes", type=Path, metavar="PROBES.csv",
                   help="drift probed at several poses of the same record: time_s, the axis positions x_mm ..., dx_um, "
                   "dy_um, dz_um (optional cycle, pred_dx_um ...), or a monitor trace with probe_dx_um ... columns; "
                   "the feed drives' diagnosis (a nut's heat, a screw's or scale's expansion coefficient, a seized "
                   "floating bearing) names what the drives get wrong, in a section of the report (needs --pose-rom)")
    p.add_argument("--pose-rom", type=Path, metavar="POSES.npz",
                   help="--probes: the machine's pose-aware reduced model with its drives (hybridcomp reduce --poses)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp diagnose``; returns the exit code (2: bad input, named on stderr)."""
    from hybridcomp.diagnose.data import DatasetError, parse_split, read_campaign
    from hybridcomp.models.machine import MachineFileError

    t0 = time.perf_counter()
    model_only = "applies to the diagnosis on the machine's model only, not with --data-only"
    data_only = "applies with --data-only only"
    bad = refuse_unused(args, [
        *((opt, args.data_only, model_only) for opt in ("machine", "increment", "rom", "element_size_mm", "effects",
                                                         "max_effects", "probes", "pose_rom",
                                                         "discretisation_floor", "place_sources",
                                                         "surface_tolerance")),
        ("surface_tolerance", args.rom is not None, "reduces the machine itself at the order it needs: give it "
         "without --rom"),
        ("pose_rom", args.probes is None, "applies with --probes only (the feed drives' diagnosis)"),
        *((opt, not args.data_only, data_only) for opt in ("max_terms", "beam", "no_selection_check", "selection",
                                                            "folds", "criterion", "probe_every_hours",
                                                            "probe_sd_um")),
        ("probe_sd_um", args.probe_every_hours is None, "applies with --probe-every-hours only"),
        ("no_selection_check", args.selection != "assisted", "applies with --selection assisted only (a held-out "
         "selection needs no check)"),
        ("folds", args.selection != "held-out", "applies with --selection held-out only"),
    ])
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    try:
        files = (DATA_ONLY_FILES + (DATA_ONLY_MODEL,) * (args.probe_every_hours is not None)
                 + DATA_ONLY_PLOTS * (not args.no_plots) if args.data_only
                 else MODEL_FILES + MODEL_PLOTS * (not args.no_plots))
        inputs = [*args.data, args.map, args.rom, args.probes, args.pose_rom]
        if not args.data_only:
            from hybridcomp.models.loader import resolve_machine_path

            inputs.append(resolve_machine_path(args.machine))
        check_output_dir(args.out, files, inputs=inputs, force=args.force)
        if args.data_only:
            ds = read_campaign(args.data, args.map)
        else:
            from hybridcomp.diagnose.core import read_measured
            from hybridcomp.models.loader import load_machine

            if not args.increment > 0:
                raise DatasetError(f"--increment must be positive, got {args.increment}")
            if args.surface_tolerance is not None and not 0 < args.surface_tolerance < 1:
                raise DatasetError(f"--surface-tolerance must be a share of a site's response in (0, 1), got "
                                   f"{args.surface_tolerance}")
            machine = load_machine(args.machine)
            if len(args.data) > 1:
                raise DatasetError("--data: the diagnosis on the machine's model takes one file (campaigns of several "
                                   "runs: --data-only)")
            ds = read_measured(args.data[0], machine, args.map, args.increment)
            if ds.runs is not None:
                raise DatasetError(f"{args.data[0]}: a campaign of runs (a 'run' column) is diagnosed with --data-only; "
                                   "the diagnosis on the machine's model takes one series")
        split = parse_split(args.train, ds.time_s, ds.runs)
        if args.max_effects < 1:
            raise DatasetError(f"--max-effects must be at least 1, got {args.max_effects}")
        if args.data_only:
            from hybridcomp.diagnose.dataonly import diagnose_data_only, write_data_only_report

            d = diagnose_data_only(ds, split, max_terms=args.max_terms, beam_width=args.beam,
                                   selection_check=not args.no_selection_check, selection=args.selection,
                                   folds=args.folds, criterion=args.criterion,
                                   probe_every_h=args.probe_every_hours, probe_sd_um=args.probe_sd_um)
            summary = write_data_only_report(d, args.out, dataset_name=", ".join(p.name for p in args.data),
                                             plots=not args.no_plots)
            fits = ", ".join(f"{c} {v['after']['fit_percent']:.1f} %" for c, v in summary["channels"].items())
            kind = "held-out" if args.selection == "held-out" else "selection-assisted validation"
            print(f"data-only diagnosis: {kind} fit {fits}; report {args.out / 'report.md'}")
            if summary["post_process_updating"]:
                pu = summary["post_process_updating"]
                fits = ", ".join(f"{c} {v['fit']['fit_percent']:.1f} %" for c, v in pu["channels"].items())
                print(f"with a probe every {pu['every_h']:g} h (gain and offset updated): fit {fits}")
            if summary["regularised"]:
                rg = summary["regularised"]["channels"]
                fits = ", ".join(f"{c} {v['held_out']['fit_percent']:.1f} %" for c, v in rg.items())
                print(f"regularised families: held-out fit {fits}")
                fits = ", ".join(f"{c} {v['spread_over_folds_and_seeds']['min']:.1f}–"
                                 f"{v['spread_over_folds_and_seeds']['max']:.1f}" for c, v in rg.items()
                                 if v["spread_over_folds_and_seeds"])
                pooled = any(v["spread_over_folds_and_seeds"] and v["spread_over_folds_and_seeds"].get("pooled_folds")
                             for v in rg.values())
                print(f"  over {'the pooled folds 3/5/10' if pooled else 'folds 3/5/10'} and seeds 0/1/2: {fits}")
                fits = ", ".join(f"{c} {v['every_row_NOT_held_out']['fit_percent']:.1f} %" for c, v in rg.items())
                print(f"  the same family fitted on every row (NOT held out): {fits}")
            if summary["coefficient_updating"]:
                cu = summary["coefficient_updating"]
                fits = ", ".join(f"{c} {v['fit']['fit_percent']:.1f} %" for c, v in cu["channels"].items())
                print(f"regularised, a probe every {cu['every_h']:g} h (coefficients updated): fit {fits}")
                _write_dataonly_model(d, args.out / DATA_ONLY_MODEL)
            return 0
        from hybridcomp.diagnose.core import diagnose, prepare_model
        from hybridcomp.diagnose.report import write_report

        kinds = [k.strip() for k in args.effects.split(",")] if args.effects else None
        if kinds:
            from hybridcomp.diagnose.effects import KINDS

            bad = [k for k in kinds if k not in KINDS]
            if bad:
                raise DatasetError(f"--effects: unknown effect {bad[0]!r} (library: {', '.join(KINDS)})")
        rom = None
        if args.rom:
            from hybridcomp.rom import load_rom

            rom = load_rom(args.rom, machine)
        probes = _read_probes(args, machine)  # before the long work: a bad file fails at once
        print(f"preparing the reduced model of {machine.name} ...", file=sys.stderr)
        if args.surface_tolerance is not None:
            from hybridcomp.diagnose.reduction import surface_order
            from hybridcomp.fem.model import build_model

            model = build_model(machine, None, args.element_size_mm)
            rom, tried = surface_order(machine, model, args.surface_tolerance)
            for t in tried:
                print(f"  {t.describe()}", file=sys.stderr)
        else:
            rom = prepare_model(machine, rom=rom, element_size_mm=args.element_size_mm)
        d = diagnose(machine, ds, split, rom=rom, kinds=kinds, max_effects=args.max_effects, progress=True,
                     discretisation=args.discretisation_floor, place=args.place_sources)
        drives = None
        if probes is not None:
            from hybridcomp.diagnose.drives import dataset_inputs, diagnose_drives, drive_candidates

            prom, pr = probes
            cands, predicted = drive_candidates(machine, prom, dataset_inputs(machine, ds), pr)
            drives = diagnose_drives(pr, cands, predicted)
        write_report(d, args.out, dataset_name=args.data[0].name, plots=not args.no_plots, drives=drives)
    except (DatasetError, MachineFileError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"verdict: {d.verdict}")
    for f in d.causes:
        print(f"  {f.candidate.describe(f.params)}; validation gain {100 * f.validation_gain:.1f} %")
    if drives is not None:
        print(f"feed drives: {drives.message}")
    print(f"report {args.out / 'report.md'} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _read_probes(args: argparse.Namespace, machine):
    """(pose-aware model, probes) of ``--probes`` and ``--pose-rom``, or None without ``--probes``."""
    if args.probes is None:
        return None
    from hybridcomp.diagnose.data import DatasetError
    from hybridcomp.diagnose.drives import read_probes
    from hybridcomp.rom import load_rom

    if args.pose_rom is None:
        raise DatasetError("--probes needs --pose-rom: the machine's pose-aware reduced model with its drives "
                           "(hybridcomp reduce --poses)")
    prom = load_rom(args.pose_rom, machine)
    if not prom.meta.get("poses"):
        raise DatasetError(f"--pose-rom {args.pose_rom}: a reduced model of one pose; the drives' diagnosis needs "
                           "the pose-aware one (hybridcomp reduce --poses)")
    return prom, read_probes(args.probes, machine)
