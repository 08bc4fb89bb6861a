"""Benchmark: every compensation strategy on the job-shop day, with the disturbances a real machine brings.

One set of models (FE model, structure model, default CDs of the basic load cases) of the demonstrator at
``--element-size-mm``; for each disturbance (``hybridcomp.scenario.DISTURBANCES``: the demo day's mis-scaled
front spindle bearing, an ambient swing the trace does not measure, an unmodelled coolant pump, a mis-scaled
spindle motor, a sensor that freezes, a warmer workspace) a real machine is simulated and replayed to the
daemon twice (strategies ``hybrid`` and ``observer``). Each case of ``--diagnose`` (default: every case with a
cause a diagnosis can name — a source's power, a source the machine file lacks, the workspace air) is then
diagnosed from its recorded day, with the drift as a measuring campaign records it (noise
``--campaign-noise-um``, a dial gauge or probe). A diagnosis is correct when it names the planted cause with its
parameter within 20 % of the deviation (a missing source also within one element size of its place). After a
correct one whose cause the extended machine file holds (a source's power or place; the workspace air is a load,
not machine data), the scenario runs again with models from that file ("after diagnosis") and the issue's
after-diagnosis targets are checked.

Per case and strategy: RMS, P2P and E_P95 of the 3-D residual at 15 min, 1 h, 4 h and 15 h, activations per
16 h day and the largest offset step per 5 s cycle; then the targets of the compensation issue, each marked
met or not:

* hybrid ≤ min(static CDs, ROM direct) in RMS and at every E_P95 window;
* observer ≤ 0.5 × ROM direct in RMS where the model is wrong (ROM direct RMS > 1 µm), and its 3-D
  peak-to-peak ≤ 10 % of the uncompensated one;
* ≤ 6 activations per 16 h day unless the load case changes more often (the job-shop day changes it 8 times:
  eight 2 h blocks, each a different workpiece with its own feeds, speeds and set-up pause; the limit is
  max(6, workpiece blocks begun per 16 h)), no offset step above 0.2 µm per 5 s cycle;
* the diagnosis names the planted cause; after it (a cause in the machine file): hybrid RMS ≤ 0.5 × before
  and ≤ 2 × ROM direct after + 0.5 µm;
* along the path (every case is judged at the commanded position too: the daemons run the pose-aware structure
  model and write a support-point table every cycle, the truth is the real machine's own pose-aware model):
  the hybrid ≤ the pose-aware model used directly in RMS and E_P95 at 15 min, 1 h and 4 h, ≤ 5 % of the
  uncompensated RMS and ≤ 1.5 × its own RMS at the model's pose + 0.2 µm (there as the part sees it: its tables at
  the model's axis positions against the real structure and drives there); no table entry moves by more than
  0.2 µm per 5 s cycle.  Three disturbances act along the path only (``POSITION_DEPENDENT``: the nuts' heat into
  their screws, a scale's expansion coefficient, a screw's seized floating bearing): the daemon's probing cycles
  touch a star of poses over the workspace and it learns each drive's gains from them; the feed drives' diagnosis
  (``hybridcomp.diagnose.drives``, the scenario summary's ``along_path.drives``) names the drive effect from them.

    python benchmarks/compensation.py [--element-size-mm 150] [--cases all] [--out DIR] [--no-diagnosis]
                                      [--diagnose CASES] [--campaign-noise-um 0.3]

Prints a table and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's hybridcomp, installed or not
from hybridcomp.metrics import cell_um
from hybridcomp.models import jsonio
from hybridcomp.scenario import AT_POSE_WITH_DRIVES, POSITION_DEPENDENT

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import table

WINDOWS = {"E15min": 900.0, "E1h": 3600.0, "E4h": 14400.0, "E15h": 54000.0}
#: the cases diagnosed by default: a cause a diagnosis can name (the ambient swing's air is not in the record)
DIAGNOSED = ("demo day", "unmodelled source", "mis-scaled source", "workspace air")
STRATEGY_ROWS = ("no compensation", "static default CDs", "hybrid monitor", "observer", "ROM direct", "MLR on sensors",
                 "best sensor map (bound)")
PATH_ROWS = ("no compensation", "static default CDs", "hybrid monitor at one pose", "hybrid monitor",
             f"hybrid monitor {AT_POSE_WITH_DRIVES}", "observer", "ROM direct along the path")


def row(case: str, name: str, m: dict) -> dict:
    d = m["3d"]
    r = {"case": case, "strategy": name, "RMS": cell_um(d["rms_um"]), "P2P": cell_um(d["p2p_um"])}
    r |= {k: cell_um(d["p95_range_um"][w]) for k, w in WINDOWS.items()}  # –: a window longer than the day
    r["act/16h"] = f"{m['activations_per_16h']:.1f}" if "activations_per_16h" in m else ""
    r["max step"] = f"{m['largest_step_um']:.3f}" if "largest_step_um" in m else ""
    return r


def load_cases_per_16h(day_hours: float) -> float:
    """How often the job-shop day changes its load case, per 16 h: the workpiece blocks begun in ``day_hours``."""
    from hybridcomp.histogram.scenarios import BLOCK_S, WORKPIECES

    blocks = min(len(WORKPIECES), math.ceil(day_hours * 3600.0 / BLOCK_S - 1e-9))
    return blocks * 16.0 / day_hours


def targets(case: str, metrics: dict, load_cases: float = 0.0) -> list[dict]:
    """The issue's targets on one case, each with its numbers and whether it is met.

    ``load_cases``: load-case changes per 16 h; the activation limit is max(6, that).
    """
    m3 = {k: v["3d"] for k, v in metrics.items()}
    out = []

    def add(what, value, limit, ok=None, bound=None):
        out.append({"case": case, "target": what, "value": round(value, 3), "limit": round(limit, 3),
                    "met": bool(value <= limit + 1e-9) if ok is None else ok,
                    "bound": None if bound is None else round(bound, 3)})

    hyb, obs, bound = m3["hybrid monitor"], m3["observer"], m3.get("best sensor map (bound)")
    # bound: what the best linear map of the day's own sensors reaches in sample; no linear map does better,
    # and a target far below it asks more of the sensors than they carry (a CD can bend where it cannot)
    add("hybrid RMS <= min(static, ROM direct)", hyb["rms_um"], min(m3["static default CDs"]["rms_um"],
                                                                     m3["ROM direct"]["rms_um"]),
        bound=None if bound is None else bound["rms_um"])
    for k, w in WINDOWS.items():
        add(f"hybrid {k} <= min(static, ROM direct)", hyb["p95_range_um"][w],
            min(m3["static default CDs"]["p95_range_um"][w], m3["ROM direct"]["p95_range_um"][w]),
            bound=None if bound is None else bound["p95_range_um"][w])
    if m3["ROM direct"]["rms_um"] > 1.0 and case not in POSITION_DEPENDENT:
        add("observer RMS <= 0.5 ROM direct", obs["rms_um"], 0.5 * m3["ROM direct"]["rms_um"])
    add("observer P2P <= 10 % uncompensated", obs["p2p_um"], 0.1 * m3["no compensation"]["p2p_um"])
    for s in ("hybrid monitor", "observer"):
        add(f"{s} activations per 16 h <= max(6, load cases {load_cases:g})", metrics[s]["activations_per_16h"],
            max(6.0, load_cases))
        add(f"{s} largest step per cycle <= 0.2 µm", metrics[s]["largest_step_um"], 0.2)
    return out


def path_targets(case: str, path_metrics: dict, at_pose: dict) -> list[dict]:
    """The volumetric targets along the path (module docstring), each with its numbers and whether it is met."""
    m3 = {k: v["3d"] for k, v in path_metrics.items()}
    hyb, direct = m3["hybrid monitor"], m3["ROM direct along the path"]
    out = []

    def add(what, value, limit):
        out.append({"case": case, "target": what, "value": round(value, 3), "limit": round(limit, 3),
                    "met": bool(value <= limit + 1e-9), "bound": None})

    add("along the path: hybrid RMS <= pose-aware ROM direct", hyb["rms_um"], direct["rms_um"])
    for k in ("E15min", "E1h", "E4h"):
        w = WINDOWS[k]
        add(f"along the path: hybrid {k} <= pose-aware ROM direct", hyb["p95_range_um"][w], direct["p95_range_um"][w])
    add("along the path: hybrid RMS <= 5 % uncompensated", hyb["rms_um"], 0.05 * m3["no compensation"]["rms_um"])
    # its own figure at the model's pose: what the part sees there, drives included (the tables at the model's axis
    # positions against the real structure and drives there); the one-pose offsets against the structure alone
    # where the run wrote no tables. The structure-alone figure of a volumetric daemon is no yardstick: its probes
    # at the pose see the drives, so on a drive's disturbance it is large (12.6 µm on the seized bearing) and the
    # target could not fail
    with_drives = path_metrics.get(f"hybrid monitor {AT_POSE_WITH_DRIVES}")
    own = (with_drives or at_pose["hybrid monitor"])["3d"]["rms_um"]
    add("along the path: hybrid RMS <= 1.5 x at the pose + 0.2", hyb["rms_um"], 1.5 * own + 0.2)
    add("along the path: largest table step per cycle <= 0.2 µm", path_metrics["hybrid monitor"]["largest_step_um"], 0.2)
    return out


def main(argv=None) -> dict:
    from hybridcomp.scenario import DISTURBANCES, Scenario, build_models, check_day, run_scenario

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--element-size-mm", type=float, default=150.0, help="FE element size of every model [mm]")
    p.add_argument("--cases", default="all", help=f"comma-separated disturbances ({', '.join(DISTURBANCES)}) or all")
    p.add_argument("--day-hours", type=float, default=16.0, help="hours of the job-shop day replayed")
    p.add_argument("--out", type=Path, default=None, help="keep every case's folder here (default: a temporary one)")
    p.add_argument("--no-diagnosis", action="store_true", help="skip every diagnosis and rerun")
    p.add_argument("--diagnose", default=",".join(DIAGNOSED),
                   help="comma-separated cases to diagnose and run again with the extended models, or all "
                        f"(default: {', '.join(DIAGNOSED)}; the ambient swing's air is not in the record, and the "
                        "sensor fault is the demo day's machine)")
    p.add_argument("--no-path", action="store_true",
                   help="judge at the model's pose only (no pose-aware models, no tables, no volumetric targets)")
    p.add_argument("--dataonly", action="store_true",
                   help="also the data-only strategy for machines without an FE model: trained on the first half of "
                        "each case's recorded day ('diagnose --data-only --probe-every-hours 4'), the daemon run "
                        "with it (strategy dataonly, its coefficients updated by the probes), judged on the second "
                        "half beside the others")
    p.add_argument("--campaign-noise-um", type=float, default=0.3,
                   help="noise of the drift the diagnosis reads, as a measuring campaign records it [µm] "
                        "(default 0.3, the probes' noise; 0: the exact drift)")
    args = p.parse_args(argv)
    names = list(DISTURBANCES) if args.cases == "all" else [c.strip() for c in args.cases.split(",")]
    diagnosed = list(DISTURBANCES) if args.diagnose == "all" else [c.strip() for c in args.diagnose.split(",") if c.strip()]
    for opt, given in (("--cases", names), ("--diagnose", diagnosed)):
        for n in given:
            if n not in DISTURBANCES:
                p.error(f"{opt}: unknown disturbance {n!r} (known: {', '.join(DISTURBANCES)})")
    for n in names:  # before any model is built: a sensor fault after the replayed day cannot be run
        try:
            check_day(DISTURBANCES[n], args.day_hours, "--day-hours")
        except ValueError as exc:
            p.error(f"--cases {n!r}: {exc}")
    if not (math.isfinite(args.campaign_noise_um) and args.campaign_noise_um >= 0):
        p.error(f"--campaign-noise-um must be a finite number >= 0, got {args.campaign_noise_um}")
    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory()
        out = Path(tmp.name)
    else:
        out = args.out.resolve()
    t_all = time.perf_counter()
    base = Scenario(element_size_mm=args.element_size_mm, day_hours=args.day_hours, along_path=not args.no_path)
    models = build_models(out / "models", element_size_mm=args.element_size_mm, keep_basis=True,
                          poses=not args.no_path)
    rows, path_rows, checks, cases, dataonly_rows = [], [], [], {}, []
    for n in names:
        t0 = time.perf_counter()
        scenario = replace(base, disturbance=DISTURBANCES[n])
        res = run_scenario(scenario, out / n.replace(" ", "_"), models)
        cases[n] = {"metrics": res.metrics, "wall_s": time.perf_counter() - t0, "summary": res.summary}
        rows += [row(n, s, res.metrics[s]) for s in STRATEGY_ROWS]
        checks += targets(n, res.metrics, load_cases_per_16h(args.day_hours))
        if "along_path" in res.summary:
            pm = res.summary["along_path"]["metrics"]
            path_rows += [row(n, s, pm[s]) for s in PATH_ROWS if s in pm]
            checks += path_targets(n, pm, res.metrics)
        print(f"{n}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        if args.dataonly:
            t0 = time.perf_counter()
            held = _dataonly(out / n.replace(" ", "_"), res, models, scenario, args.campaign_noise_um,
                             seed=100 + names.index(n))
            cases[n]["dataonly"] = held
            dataonly_rows += [{"case": n, "strategy": k, "RMS": cell_um(v["rms_um"]),
                               **{w: cell_um(v["p95_range_um"][sec]) for w, sec in WINDOWS.items() if w != "E15h"}}
                              for k, v in held["held_out"].items()]
            print(f"{n}, data-only model and its daemon: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        if n in diagnosed and not args.no_diagnosis:
            t0 = time.perf_counter()
            diag, after = _after_diagnosis(out, n, res, models, scenario, args.campaign_noise_um, seed=names.index(n))
            checks.append({"case": n, "target": "diagnosis names the planted cause", "value": diag["named"],
                           "limit": diag["planted"], "met": diag["correct"]})
            cases[n]["diagnosis"] = diag
            if after is not None:
                cases[f"{n}, after diagnosis"] = {"metrics": after.metrics, "summary": after.summary}
                rows += [row(f"{n}, after diagnosis", s, after.metrics[s]) for s in STRATEGY_ROWS]
                before = res.metrics["hybrid monitor"]["3d"]["rms_um"]
                later = after.metrics["hybrid monitor"]["3d"]["rms_um"]
                rom_after = after.metrics["ROM direct"]["3d"]["rms_um"]
                for what, limit in (("hybrid RMS after diagnosis <= 0.5 before", 0.5 * before),
                                    ("hybrid RMS after diagnosis <= 2 ROM direct after + 0.5", 2 * rom_after + 0.5)):
                    checks.append({"case": n, "target": what, "value": round(later, 3), "limit": round(limit, 3),
                                   "met": bool(later <= limit + 1e-9)})
            print(f"{n}, diagnosis ({diag['verdict']}: {diag['named'] or 'nothing named'}) and rerun: "
                  f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    print(table(rows, ["case", "strategy", "RMS", "P2P", *WINDOWS, "act/16h", "max step"]))
    print()
    if path_rows:
        print("Along the path (at the commanded position):")
        print(table(path_rows, ["case", "strategy", "RMS", "P2P", *WINDOWS, "act/16h", "max step"]))
        print()
    if dataonly_rows:
        print("The data-only strategy (trained on the first half of the day's record, the probes every 4 h updating "
              "it), at the model's pose, on the held-out second half:")
        print(table(dataonly_rows, ["case", "strategy", "RMS", *[w for w in WINDOWS if w != "E15h"]]))
        print()
    print(table([{**c, "met": "yes" if c["met"] else "NO", "bound": "" if c.get("bound") is None else f"{c['bound']:.3f}"}
                 for c in checks], ["case", "target", "value", "limit", "met", "bound"]))
    summary = {
        "benchmark": "compensation", "element_size_mm": args.element_size_mm, "day_hours": args.day_hours,
        "campaign_noise_um": args.campaign_noise_um,
        "diagnoses": {n: c["diagnosis"] for n, c in cases.items() if "diagnosis" in c},
        "dataonly": {n: c["dataonly"] for n, c in cases.items() if "dataonly" in c},
        "machine": platform.processor() or platform.machine(), "wall_s": time.perf_counter() - t_all,
        "targets_met": sum(c["met"] for c in checks), "targets": len(checks), "checks": checks,
        "cases": {n: {"rms_3d_um": {k: v["3d"]["rms_um"] for k, v in c["metrics"].items()},
                      "p95_3d_um": {k: {w: v["3d"]["p95_range_um"][s] for w, s in WINDOWS.items()}
                                    for k, v in c["metrics"].items()},
                      "p2p_3d_um": {k: v["3d"]["p2p_um"] for k, v in c["metrics"].items()},
                      "activations_per_16h": {k: v.get("activations_per_16h") for k, v in c["metrics"].items()
                                              if "activations_per_16h" in v},
                      "largest_step_um": {k: v.get("largest_step_um") for k, v in c["metrics"].items()
                                          if "largest_step_um" in v},
                      "along_path": _path_summary(c["summary"].get("along_path"))}
                  for n, c in cases.items()},
    }
    print(jsonio.dumps(summary))
    if tmp is not None:
        tmp.cleanup()
    return summary


def _path_summary(along: dict | None) -> dict | None:
    """The along-path figures of a case's summary: 3-D RMS and E_P95 per strategy, the table's largest step."""
    if along is None:
        return None
    m = along["metrics"]
    return {"rms_3d_um": {k: v["3d"]["rms_um"] for k, v in m.items()},
            "p95_3d_um": {k: {w: v["3d"]["p95_range_um"][s] for w, s in WINDOWS.items()} for k, v in m.items()},
            "position_dependent_um": along["position_dependent_um"], "truth": along["truth"],
            "largest_table_step_um": along["largest_table_step_um"], "drive_gains": along.get("drive_gains")}


def planted_cause(disturbance, causes, element_size_mm: float) -> tuple[str, bool, bool]:
    """What a correct diagnosis of ``disturbance`` names, whether ``causes`` (the diagnosis's fitted effects) name
    it (the parameter within 20 % of the planted deviation, a missing source also within one element size), and
    whether the extended machine file holds it."""
    if disturbance.source_factor is not None:
        name, f = disturbance.source_factor
        ok = any(c.candidate.kind == "power_scale" and c.candidate.target == name
                 and abs(c.params[0] - f) <= 0.2 * abs(f - 1.0) for c in causes)
        return f"power of {name} x {f:g}", ok, True
    if disturbance.added_source is not None:
        a = disturbance.added_source
        from hybridcomp.diagnose.locate import located_at

        ok = any(c.candidate.kind in ("located_source", "missing_source") and "location_mm" in c.candidate.info
                 and np.linalg.norm(np.subtract(located_at(c.candidate, c.params)[0], a["position_mm"]))
                 <= element_size_mm
                 and abs(c.params[0] - a["power_W"]) <= 0.2 * a["power_W"] for c in causes)
        return f"missing source {a['power_W']:g} W at {tuple(a['position_mm'])} mm", ok, True
    if disturbance.workspace_air_K:
        dT = disturbance.workspace_air_K
        ok = any(c.candidate.kind == "workspace_offset" and abs(c.params[0] - dT) <= 0.2 * abs(dT) for c in causes)
        return f"workspace air +{dT:g} K", ok, False
    return "nothing", not causes, False


def _campaign_record(recorded: Path, noise_um: float, seed: int) -> Path:
    """The recorded day as a measuring campaign has it: the drift with a dial gauge's or probe's noise."""
    if noise_um == 0:
        return recorded
    lines = recorded.read_text().splitlines()
    head = lines[0].split(",")
    cols = [head.index(c) for c in ("dx_um", "dy_um", "dz_um")]
    rng = np.random.default_rng(seed)
    rows = []
    for line in lines[1:]:
        v = line.split(",")
        for k, e in zip(cols, rng.normal(0.0, noise_um, len(cols))):
            v[k] = f"{float(v[k]) + e:.4f}"
        rows.append(",".join(v))
    out = recorded.with_name("recorded_campaign.csv")
    out.write_text("\n".join([lines[0], *rows]) + "\n")
    return out


#: the data-only strategy's training part of the recorded day (a fraction of its time); the rest is held out
DATAONLY_TRAIN_FRACTION = 0.5
#: the columns a machine without an FE model would not feed its data-only model (the axis positions: the online
#: strategy rebuilds only spindle activities)
DATAONLY_DROP = ("x_mm", "y_mm", "z_mm")


def _dataonly(folder: Path, res, models, scenario, noise_um: float, seed: int) -> dict:
    """The data-only strategy on a case: trained on the first half of its recorded day, run by the daemon, judged on
    the second half at the model's pose beside the day's other strategies (:func:`main`, ``--dataonly``).

    The training record is the campaign's (the drift with the probes' noise), without the axis positions; the
    model is what ``hybridcomp diagnose --data-only --train 0:50% --probe-every-hours 4`` writes, and the daemon
    replays the day's monitor trace with strategy ``dataonly`` (the trace's probes update its coefficients).  No
    choice sees the second half: the family, λ and the filter's settings come from the training rows.
    """
    from hybridcomp.cli import main as cli
    from hybridcomp.metrics import drift_metrics
    from hybridcomp.scenario import NAMES, replay_strategies

    rec = _campaign_record(Path(res.files["recorded"]), noise_um, seed)
    lines = rec.read_text().splitlines()
    head = lines[0].split(",")
    keep = [i for i, c in enumerate(head) if c not in DATAONLY_DROP]
    train = folder / "dataonly_training.csv"
    train.write_text("\n".join(",".join(line.split(",")[i] for i in keep) for line in lines) + "\n")
    diag = folder / "dataonly"
    split = f"0:{100 * DATAONLY_TRAIN_FRACTION:g}%"
    code = cli(["diagnose", "--data-only", "--data", str(train), "--train", split,
                "--probe-every-hours", f"{scenario.probe_every_h:g}", "--out", str(diag)])
    model = diag / "dataonly_model.json"
    if code != 0 or not model.is_file():
        raise RuntimeError(f"the data-only diagnosis of {train} wrote no model (exit {code}): see {diag}/report.md")
    sc = replace(scenario, strategies=("dataonly",), monitor_overrides={
        **(scenario.monitor_overrides or {}),
        "compensation": {**(scenario.monitor_overrides or {}).get("compensation", {}), "dataonly_model": str(model)}})
    R = np.genfromtxt(folder / "residuals.csv", delimiter=",", names=True)  # the truth, then every prediction
    t = R["time_s"]
    truth = np.column_stack([R["dx_um"], R["dy_um"], R["dz_um"]])
    run = replay_strategies(sc, folder, models, Path(res.files["trace"]), t, {}, volumetric=False)["dataonly"]
    residual = {NAMES["dataonly"]: truth - run["at_t"]}
    for name in ("no compensation", "hybrid monitor", "observer", "ROM direct"):
        key = name.replace(" ", "_")
        residual[name] = truth - np.column_stack([R[f"{key}_{d}_um"] for d in ("dx", "dy", "dz")])
    held = t >= t[0] + DATAONLY_TRAIN_FRACTION * (t[-1] - t[0])
    return {"train": split, "model": str(model.relative_to(folder)),
            "held_out": {k: drift_metrics(t[held], r[held])["3d"] for k, r in residual.items()},
            "largest_step_um": run["largest_step_um"]}


def _after_diagnosis(out: Path, case: str, res, models, scenario, noise_um: float, seed: int):
    """Diagnose a case's recorded day (run as ``scenario``); after a correct diagnosis of a cause the machine file
    holds, the scenario again with models from the extended machine file. Returns (what the diagnosis named, the
    rerun's result or None)."""
    from hybridcomp.diagnose import diagnose, prepare_model, read_measured, write_report
    from hybridcomp.models import load_machine
    from hybridcomp.scenario import DISTURBANCES, build_models, run_scenario

    machine = models.machine
    folder = out / case.replace(" ", "_")
    rom = prepare_model(machine, rom=models.rom, element_size_mm=scenario.element_size_mm)
    # heat inputs at the real machine's own load step: a coarser histogram leaves its short-term response in the
    # residual, where it is no model error
    data = read_measured(_campaign_record(Path(res.files["recorded"]), noise_um, seed), machine,
                         increment_s=res.summary["real_dt_s"])
    # the default diagnosis (no discretisation floor, sources at their search site): the figures the README quotes
    d = diagnose(machine, data, rom=rom, discretisation=False, place="patch")
    write_report(d, folder / "diagnosis")
    planted, correct, in_file = planted_cause(DISTURBANCES[case], d.causes, scenario.element_size_mm)
    named = "; ".join(f"{c.candidate.label} ({', '.join(f'{v:.3g}' for v in c.params)})" for c in d.causes)
    diag = {"verdict": d.verdict, "named": named, "planted": planted, "correct": bool(correct)}
    if not (correct and in_file):
        return diag, None
    extended = folder / "diagnosis" / "machine_extended.toml"
    real = load_machine(res.summary["real_machine"])
    after_models = build_models(folder / "models_after", str(extended), scenario.element_size_mm)
    return diag, run_scenario(replace(scenario, real_machine=real, along_path=False), folder / "after_diagnosis",
                              after_models)


if __name__ == "__main__":
    main()
