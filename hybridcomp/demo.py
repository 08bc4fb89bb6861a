"""``hybridcomp demo``: the whole hybrid cycle on the bundled demonstrator, from one command.

1. the machine (picture) and the bundled 16 h job-shop day (load factors and histograms, from the
   controller's trace the monitor replays);
2. a "real machine": the demonstrator with a planted effect the models do not know (by default the
   front spindle bearing dissipates 1.6 × its nominal power, a typical error of loss estimates);
3. the hybrid scenario with the nominal models: default CDs of the basic load cases (FE training),
   the structure model (ROM), the monitor replaying the day against the real machine, switching and
   generating CD sets; compared with no compensation, the static default CDs, the ROM used
   directly and a regression on the sensors;
4. the diagnosis of the recorded day (sensors and drift of the real machine): the named cause, its
   parameter and the gain on the held-out part, and the extended machine file;
5. the same scenario with the models rebuilt from the extended machine file;
6. ``DIR/report.md`` and ``DIR/summary.json``.

Everything lives in DIR (the CD databases are SQLite files there); nothing needs a server.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

from hybridcomp.metrics import cell_um
from hybridcomp.models import jsonio
from hybridcomp.safeio import FORCE_HELP, start_folder, write_text_atomic

log = logging.getLogger(__name__)

DEFAULT_EFFECT = ("spindle_bearing_front", 1.6)


@dataclass(frozen=True)
class DemoOptions:
    """What the demo runs.

    Attributes
    ----------
    element_size_mm : FE element size of the real machine and of every model [mm]
    source : heat source whose power the real machine scales (the planted effect)
    factor : that power factor [-]
    day_hours : hours of the job-shop day replayed (≤ 16)
    basic_hours : heating (and cooling) hours of each basic load case [h]
    rom_order : order of the structure models (None: reduced to the default tolerances)
    pictures : render the machine picture (needs pyvista)
    """

    element_size_mm: float = 80.0
    source: str = DEFAULT_EFFECT[0]
    factor: float = DEFAULT_EFFECT[1]
    day_hours: float = 16.0
    basic_hours: float = 8.0
    rom_order: int | None = None
    pictures: bool = True


class _Stages:
    """A progress display over the demo's stages (one line per stage on stderr, with its time)."""

    def __init__(self, names: list[str], show: bool):
        self.names, self.show, self.k, self.t0 = names, show, 0, time.perf_counter()
        self.times: dict[str, float] = {}

    def next(self) -> None:
        now = time.perf_counter()
        if self.k:
            self.times[self.names[self.k - 1]] = now - self.t0
            if self.show:
                print(f"      done in {now - self.t0:.0f} s", file=sys.stderr)
        if self.k < len(self.names) and self.show:
            print(f"[{self.k + 1}/{len(self.names)}] {self.names[self.k]} ...", file=sys.stderr)
        self.k += 1
        self.t0 = now


def run_demo(out_dir: str | Path, options: DemoOptions = DemoOptions(), progress: bool = True) -> dict:
    """Run the demo (see the module docstring) into ``out_dir``; returns the summary written to summary.json."""
    from hybridcomp.diagnose import diagnose, prepare_model, read_measured, write_report
    from hybridcomp.models import load_machine
    from hybridcomp.scenario import Disturbance, Scenario, build_models, real_machine_file, run_scenario

    out = Path(out_dir).resolve()  # once, against the caller's working directory
    out.mkdir(parents=True, exist_ok=True)
    machine = load_machine("vmc800")
    stages = _Stages(["machine picture", "real machine with the planted effect",
                      "hybrid scenario with the nominal models", "diagnosis of the recorded day",
                      "hybrid scenario with the extended machine file", "report"], progress)
    t_all = time.perf_counter()

    stages.next()
    pictures = _pictures(machine, out, options) if options.pictures else {}

    stages.next()
    planted = Disturbance("demo", f"{options.source} dissipates {options.factor:g} × its nominal power",
                          source_factor=(options.source, options.factor))
    real = load_machine(real_machine_file(machine, planted, out / "real_machine.toml"))

    stages.next()
    build = dict(element_size_mm=options.element_size_mm, rom_order=options.rom_order, basic_hours=options.basic_hours,
                 keep_basis=True)
    scenario = Scenario(disturbance=planted, real_machine=real, element_size_mm=options.element_size_mm,
                        day_hours=options.day_hours)
    models = build_models(out / "models_nominal", str(machine.source), poses=True, **build)
    nominal = run_scenario(replace(scenario, along_path=True), out / "hybrid_nominal", models)

    stages.next()
    rom = prepare_model(machine, rom=models.rom, element_size_mm=options.element_size_mm)
    # the recorded day's heat inputs at the real machine's own load step (a coarser histogram would leave its
    # short-term response in the residual, where it is no model error)
    dataset = read_measured(nominal.files["recorded"], machine, increment_s=nominal.summary["real_dt_s"])
    diag = diagnose(machine, dataset, rom=rom)
    diag_summary = write_report(diag, out / "diagnosis")
    extended = out / "diagnosis" / "machine_extended.toml"

    stages.next()
    after = run_scenario(scenario, out / "hybrid_extended", build_models(out / "models_extended", str(extended), **build))

    stages.next()
    day_plots = _day_plots(machine, nominal.files["controller"], out / "day")
    summary = _summary(options, nominal, after, diag_summary, time.perf_counter() - t_all, stages.times)
    write_text_atomic(out / "summary.json", jsonio.dumps(summary, indent=1, default=str))
    _report(out, options, summary, nominal, after, pictures, day_plots)
    stages.next()
    return summary


def _pictures(machine, out: Path, options: DemoOptions) -> dict:
    """The machine at steady state with every source at half its rated power: temperature on the deformed structure."""
    try:
        from hybridcomp.fem.export import render_png
        from hybridcomp.fem.loads import full_power_inputs
        from hybridcomp.fem.model import build_model
        from hybridcomp.fem.stepping import steady_state

        model = build_model(machine, {}, options.element_size_mm)
        x = steady_state(model, 0.5 * full_power_inputs(machine))
        p = render_png(model, x, out / "machine.png", title=f"{machine.name}: steady state at half the rated losses")
        return {"machine": p.name}
    except (ImportError, RuntimeError) as exc:  # pictures are optional
        log.warning("no machine picture: %s", exc)
        return {}


def _day_plots(machine, trace: Path, day: Path) -> dict:
    """Load factors and one increment's histograms of the replayed day, from the controller's trace."""
    from hybridcomp.histogram.increments import increments_from_trace

    try:
        from hybridcomp.histogram.plots import plot_factors, plot_increment

        inc = increments_from_trace(trace, machine, 300.0)
        paths = {"load factors of the day": plot_factors(inc, day / "factors.png")}
        k = int(len(inc) * 0.3)  # an increment in the second block
        paths[f"histograms of increment {k}"] = plot_increment(inc, k, day / "increment.png")
        return {name: str(Path(v).relative_to(day.parent)) for name, v in paths.items()}
    except (ImportError, RuntimeError) as exc:
        log.warning("no histogram plots: %s", exc)
        return {}


def _summary(options, nominal, after, diag_summary: dict, total_s: float, stage_s: dict) -> dict:
    m0 = {k: v["3d"] for k, v in nominal.metrics.items()}
    m1 = {k: v["3d"] for k, v in after.metrics.items()}
    rows = {
        "no compensation": m0["no compensation"],
        "static default CDs": m0["static default CDs"],
        "hybrid monitor": m0["hybrid monitor"],
        "hybrid after diagnosis": m1["hybrid monitor"],
        "observer": m0["observer"],
        "observer after diagnosis": m1["observer"],
        "ROM direct": m0["ROM direct"],
        "ROM direct after diagnosis": m1["ROM direct"],
        "MLR on sensors": m0["MLR on sensors"],
    }
    d = diag_summary
    planted = f"power of {options.source}"
    per_day = {k: {s: nominal.metrics[k].get(s) for s in ("activations", "activations_per_16h", "largest_step_um")}
               for k in ("hybrid monitor", "observer")}
    return {
        "planted": {"source": options.source, "factor": options.factor},
        "element_size_mm": options.element_size_mm,
        "day_hours": options.day_hours,
        "residual_3d": rows,
        "hybrid_beats_static": rows["hybrid monitor"]["rms_um"] < rows["static default CDs"]["rms_um"],
        "diagnosis": {"verdict": d.get("verdict"), "causes": d.get("causes", []),
                      "planted_cause_named": any(c.get("name") == "power_scale" and c.get("target") == options.source
                                                 for c in d.get("causes", [])),
                      "planted": planted},
        "after_beats_before": rows["hybrid after diagnosis"]["rms_um"] < rows["hybrid monitor"]["rms_um"],
        "switches": nominal.summary.get("switches"),
        "generations": nominal.summary.get("generations"),
        "activations": per_day,
        "events": [e for e in nominal.events if e.get("strategy") == "hybrid"],
        "along_path": {k: v for k, v in nominal.summary["along_path"].items() if k != "metrics"}
        | {"residual_3d": {k: v["3d"] for k, v in nominal.summary["along_path"]["metrics"].items()}},
        "timings_s": {**stage_s, "total": total_s},
    }


def _ep95_plot(path: Path, rows: dict) -> Path | None:
    """E_P95(range) against the window length, one curve per strategy, on log axes.

    The y axis is logarithmic (the compensated strategies lie one to two decades below no compensation) and the
    window ticks are the windows themselves, as a person says them (15 min, 1 h, 4 h, 15 h):
    :func:`hybridcomp.plotaxes.window_axes`, as the diagnosis report draws its own.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    from hybridcomp.plotaxes import positive, window_axes

    fig, ax = plt.subplots(figsize=(8, 4.5))
    windows_h: set[float] = set()
    for name, m in rows.items():
        w = [float(k) / 3600.0 for k in m["p95_range_um"]]
        windows_h.update(w)
        ax.plot(w, positive(m["p95_range_um"].values()), marker="o", ms=3, label=name,
                lw=2.0 if name.startswith("hybrid") else 1.0)
    window_axes(ax, windows_h, ticks_h=sorted(windows_h))
    ax.set_ylabel("E_P95(range) of the 3D residual [µm]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _cd_table(db_path: Path) -> list[str]:
    """The default CD set (the first activation): inputs, fit and reference temperatures."""
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.store import MonitorStore

    with CDDatabase(db_path) as db:
        first = next((e for e in MonitorStore(db).events("activation")), None)
        if first is None:
            return []
        cds = {d: db.get(i) for d, i in first.payload["ids"].items()}
    sensors = [k for k, _ in cds["X"].t_reference_degC]
    lines = ["| CD | load case | active inputs | values | RMS fit residual [µm] | " + " | ".join(
        f"T_ref {s} [°C]" for s in sensors) + " |", "|---" * (5 + len(sensors)) + "|"]
    for cd in cds.values():
        st = cd.fit_stats()
        tref = cd.t_reference()
        lines.append(f"| {cd.target} | {cd.load_case} | {', '.join(i.name for i in cd.active_inputs)} | {cd.n_values} | "
                     f"{_fixed(st.get('rms_residual_um'), 3)} | " + " | ".join(f"{tref[s]:.2f}" for s in sensors) + " |")
    return lines


def _fmt_row(name: str, m: dict) -> str:
    cells = [cell_um(m["rms_um"]), cell_um(m["p2p_um"])] + [cell_um(v) for v in m["p95_range_um"].values()]
    return f"| {name} | " + " | ".join(cells) + " |"


#: unit suffixes of event fields and how a reader sees them
_UNITS = {"_um": "µm", "_K": "K", "_degC": "°C", "_s": "s", "_W": "W"}


def _value(v) -> str:
    """One value of an event as a reader sees it: 3 significant digits (whole from 1000), ``–`` for NaN, lists joined."""
    if isinstance(v, bool) or v is None:
        return {True: "yes", False: "no", None: "–"}[v]
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.0f}" if abs(v) >= 1000 else f"{v:.3g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_value(x) for x in v)
    if isinstance(v, dict):
        return ", ".join(f"{k} {_value(x)}" for k, x in v.items() if x is not None)
    return str(v).replace("|", "/").replace("\n", " ")


def _fixed(v, digits: int) -> str:
    """``v`` with ``digits`` decimals; ``–`` for a missing or non-finite value."""
    return f"{v:.{digits}f}" if v is not None and math.isfinite(v) else "–"


def _split_unit(key: str, unit: str = "") -> tuple[str, str]:
    """(name, unit) of an event field: ``error_um`` → (``error``, ``µm``); no suffix keeps ``unit``."""
    for suffix, u in _UNITS.items():
        if key.endswith(suffix):
            return key.removesuffix(suffix), u
    return key, unit


def _item(key, v, unit: str = "", top: bool = False) -> str:
    """``name value unit`` of one field; a nested table as ``name: a 1 µm, b 2 µm`` (top) or ``name (...)``."""
    name, unit = _split_unit(str(key), unit)
    name = name.replace("_", " ")
    if isinstance(v, dict):
        inner = ", ".join(_item(k, x, unit) for k, x in v.items() if x is not None)
        return f"{name}: {inner}" if top else f"{name} ({inner})"
    text = _value(v)
    return f"{name}{':' if top else ''} {text}{' ' + unit if unit and text != '–' else ''}"


def event_details(event: dict) -> str:
    """The details cell of a monitoring event in the report: ``name: value unit`` items, empty fields left out.

    A field named with a unit suffix (``error_um``, ``delta_T_K``) shows the unit after its value; a nested table
    (``error_um = {interval_um: 5.47, forecast_um: 3.1}``) shows its entries the same way, so no raw Python
    (dicts, ``None``) reaches the report.
    """
    return "; ".join(_item(k, v, top=True) for k, v in event.items()
                     if k not in ("kind", "machine_time_s", "strategy") and v is not None and v != {} and v != [])


def _report(out: Path, options, summary, nominal, after, pictures, day_plots) -> Path:
    rows = summary["residual_3d"]
    windows = [f"{float(w) / 3600:g} h" for w in next(iter(rows.values()))["p95_range_um"]]
    lines = [
        "# hybridcomp demo: the hybrid cycle on the demonstrator",
        "",
        f"Machine `vmc800` at {options.element_size_mm:g} mm elements; the bundled job-shop day "
        f"({options.day_hours:g} h). The *real machine* differs from the model by a planted effect: "
        f"**{options.source} dissipates {options.factor:g} × its nominal power**.",
        "",
    ]
    if pictures.get("machine"):
        lines += [f"![the machine]({pictures['machine']})", ""]
    if day_plots:
        lines += ["## The day", ""] + [f"![{k}]({v})" for k, v in day_plots.items()] + [""]
    lines += ["## Residual TCP drift (3D, the whole day)", "",
              "| strategy | RMS [µm] | P2P [µm] | " + " | ".join(f"E_P95 {w} [µm]" for w in windows) + " |",
              "|---|---|---|" + "---|" * len(windows)]
    lines += [_fmt_row(k, v) for k, v in rows.items()]
    curve = _ep95_plot(out / "ep95.png", rows)
    if curve is not None:
        lines += ["", f"![E_P95(range) curves]({curve.name})"]
    lines += ["", f"Hybrid monitor beats the static default CDs: **{summary['hybrid_beats_static']}** "
              f"({rows['hybrid monitor']['rms_um']:.2f} against {rows['static default CDs']['rms_um']:.2f} µm RMS). "
              f"After the diagnosis the structure model predicts the real machine's drift to "
              f"{rows['ROM direct after diagnosis']['rms_um']:.2f} µm RMS (before: {rows['ROM direct']['rms_um']:.2f} µm); "
              f"the hybrid compensation goes from {rows['hybrid monitor']['rms_um']:.2f} to "
              f"{rows['hybrid after diagnosis']['rms_um']:.2f} µm RMS (the observer, "
              f"{rows['observer']['rms_um']:.2f} → {rows['observer after diagnosis']['rms_um']:.2f} µm, had corrected "
              "the model with the sensors and probes before the diagnosis named the cause).", "",
              "E_P95 w: the 95th percentile of the residual's range (max − min) over all windows of length w; "
              "for the 3D row the largest of the three directions.", ""]
    along = summary["along_path"]
    lines += ["## Along the path: the drift where the tool is", "",
              "The rows above judge every strategy at the model's pose (mid travel). At the trace's commanded "
              "position the drift also depends on the pose and on the feed drives: X and Y read rotary encoders, so "
              "their screws' elongation is a positioning error growing with the distance from the fixed bearing. "
              "Position-dependent part of the true drift over the day: " + ", ".join(
                  f"{d.removesuffix('_um')} {v:.1f} µm" for d, v in along["position_dependent_um"].items()) + ".", "",
              "| strategy (nominal models) | RMS [µm] | P2P [µm] | " + " | ".join(f"E_P95 {w} [µm]" for w in windows)
              + " |", "|---|---|---|" + "---|" * len(windows)]
    lines += [_fmt_row(k, v) for k, v in along["residual_3d"].items()]
    lines += ["", "*hybrid monitor* and *observer* are the daemons of the rows above, compensating where the tool "
              "is: besides the model pose's structure model and its observer they run the pose-aware structure model "
              "(a reduced model per support pose, the screws' thermal models) and write, every 5 s, a table of the "
              "drift at the support points of a 3 × 3 × 3 grid over the workspace and of each drive's error over its "
              "axis (the offsets at the model's pose carried to every pose); the control interpolates it at the "
              "commanded position. Their probing cycles touch a star of poses, from which they learn each drive's "
              "gain. *… at one pose* is the same run's one-pose offsets, *ROM direct along the path* the pose-aware "
              "model used directly. The true drift at the path's position is the real machine's FE drift at the "
              "model's pose plus what the pose adds on the real machine, from the real machine's own pose-aware "
              "model (its machine file with the planted effect).", ""]
    for label, res in (("nominal models", nominal), ("extended machine file", after)):
        if res.files.get("plot"):
            rel = Path(res.files["plot"]).relative_to(out)
            lines += [f"![residuals, {label}]({rel})", ""]
    cd_lines = _cd_table(out / "hybrid_nominal" / "cd_hybrid.db")
    if cd_lines:
        lines += ["## The default CDs and their reference temperatures", "",
                  "Fitted on FE runs of the basic load cases (each axis alone, the spindle alone, then cooling); "
                  "T_ref: the structure model's sensor temperatures for that load case, which the monitor compares "
                  "with the current ones.", ""] + cd_lines + [""]
    lines += ["## Monitoring decisions (nominal models)", "", "| machine time [h] | event | details |", "|---|---|---|"]
    for e in summary["events"]:
        t = e.get("machine_time_s")
        details = event_details(e)
        lines.append(f"| {'' if t is None else f'{t / 3600:.2f}'} | {e['kind']} | {details} |")
    d = summary["diagnosis"]
    lines += ["", "## Diagnosis of the recorded day", "",
              f"Verdict: **{d['verdict']}**. Planted: {d['planted']} × {options.factor:g}; named: "
              f"**{d['planted_cause_named']}**.", ""]
    for c in d["causes"]:
        par = ", ".join(f"{k} = {v:.4g}" + (f" ± {u:.2g}" if (u := c.get("uncertainty", {}).get(k)) is not None
                                             and math.isfinite(u) else "")
                        for k, v in c.get("parameters", {}).items())
        gain = c.get("gain", {}).get("validation_rss_reduction")
        said = f"; validation gain {100 * gain:.1f} %" if gain is not None else ""
        lines.append(f"* **{c.get('label', c['name'])}**: {par}{said}")
    lines += ["", "Full diagnosis report: [diagnosis/report.md](diagnosis/report.md); extended machine file: "
              "[diagnosis/machine_extended.toml](diagnosis/machine_extended.toml).", ""]
    t = summary["timings_s"]
    lines += ["## Run time", "", "| stage | [s] |", "|---|---|"] + [f"| {k} | {v:.0f} |" for k, v in t.items()]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp demo`` options."""
    p.add_argument("--out", required=True, type=Path, help="output directory (report.md, summary.json, databases, "
                   "plots); a folder that holds anything is written into only with --force")
    p.add_argument("--force", action="store_true", help=FORCE_HELP + " (an earlier run's folder: its files are "
                   "replaced, its summary.json and report.md removed first)")
    p.add_argument("--element-size-mm", type=float, default=DemoOptions.element_size_mm,
                   help="FE element size of the real machine and the models [mm] (default %(default)s)")
    p.add_argument("--plant-source", default=DEFAULT_EFFECT[0],
                   help="heat source whose power the real machine scales (default %(default)s)")
    p.add_argument("--plant-factor", type=float, default=DEFAULT_EFFECT[1],
                   help="its power factor in the real machine (default %(default)s)")
    p.add_argument("--day-hours", type=float, default=16.0, help="hours of the job-shop day to replay (default 16)")
    p.add_argument("--basic-hours", type=float, default=8.0,
                   help="heating (then cooling) hours of each basic load case (default 8)")
    p.add_argument("--rom-order", type=int, help="order of the structure models (default: to the default tolerances)")
    p.add_argument("--no-pictures", action="store_true", help="no machine picture (no pyvista needed)")
    p.add_argument("--no-progress", action="store_true", help="no stage display")


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp demo``; returns the exit code (2: bad option, named on stderr)."""
    from hybridcomp.histogram.scenarios import JOBSHOP_HOURS

    if not 0 < args.day_hours <= JOBSHOP_HOURS:
        print(f"error: --day-hours must be in (0, {JOBSHOP_HOURS:g}], got {args.day_hours}", file=sys.stderr)
        return 2
    from hybridcomp.models import load_machine

    sources = [src.name for src in load_machine("vmc800").heat_sources]
    if args.plant_source not in sources:
        print(f"error: --plant-source: the demonstrator has no heat source {args.plant_source!r} (sources: "
              f"{', '.join(sources)})", file=sys.stderr)
        return 2
    if not args.plant_factor > 0:
        print(f"error: --plant-factor must be positive, got {args.plant_factor}", file=sys.stderr)
        return 2
    start_folder(args.out, force=args.force, finals=("summary.json", "report.md"))  # refused: the dispatcher's error
    opts = DemoOptions(element_size_mm=args.element_size_mm, source=args.plant_source, factor=args.plant_factor,
                       day_hours=args.day_hours, basic_hours=args.basic_hours, rom_order=args.rom_order,
                       pictures=not args.no_pictures)
    try:
        summary = run_demo(args.out, opts, progress=not args.no_progress)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    r = summary["residual_3d"]
    print(f"wrote {args.out / 'report.md'}: residual RMS none {r['no compensation']['rms_um']:.2f} µm, static CDs "
          f"{r['static default CDs']['rms_um']:.2f}, hybrid {r['hybrid monitor']['rms_um']:.2f}, after diagnosis "
          f"{r['hybrid after diagnosis']['rms_um']:.2f}; cause named: {summary['diagnosis']['planted_cause_named']}",
          file=sys.stderr)
    return 0


