"""The hybrid scenario and the residual-drift metrics it reports.

:func:`run_scenario` replays the bundled 16 h job-shop day on the demonstrator.
The "real machine" is the FE model (``element_size_mm``, default 80 mm) with a
planted disturbance the models do not know: the workspace air behind the
enclosure runs ``disturbance_K`` warmer than the measured workshop air (reached
over the first two hours). Its sensor temperatures T1…T8 and its TCP drift are
the measurements. Five strategies are compared on the residual drift
(true drift − predicted), every 60 s of the day:

* no compensation;
* static default CDs: fitted on the basic load cases (each axis alone, the spindle alone; FE training runs);
* the hybrid monitor: starts from the default CDs; the daemon (replay of the 1 Hz trace, ROM, CD database,
  generation jobs on the FE model) switches and generates CD sets as it decides;
* the ROM used directly: the structure model on the trace's BCs predicts the drift itself;
* a multiple linear regression of the drift on the eight sensors, fitted on the same basic load cases.

Metrics per direction and for the 3-D residual (:func:`drift_metrics`): RMS,
peak-to-peak, and the 95th percentile of the range (max − min) of the residual
within sliding windows of 15 min to 15 h.
"""

from __future__ import annotations

import asyncio
import csv
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.models import jsonio
from hybridcomp.models.layout import DRIFT_COLUMNS

log = logging.getLogger(__name__)

WINDOWS_S = (900.0, 1800.0, 3600.0, 2 * 3600.0, 4 * 3600.0, 8 * 3600.0, 15 * 3600.0)
DIRS = DRIFT_COLUMNS


# --------------------------------------------------------------------------- metrics (pure)


def window_ranges(x: np.ndarray, n: int) -> np.ndarray:
    """Range (max − min) of ``x`` in every window of ``n`` consecutive samples (x.size − n + 1 values)."""
    from numpy.lib.stride_tricks import sliding_window_view

    v = sliding_window_view(np.asarray(x, float), n)
    return v.max(axis=1) - v.min(axis=1)


def drift_metrics(time_s: np.ndarray, residual_um: np.ndarray, windows_s: Sequence[float] = WINDOWS_S) -> dict:
    """RMS, peak-to-peak and windowed 95th-percentile ranges of a residual drift.

    Parameters
    ----------
    time_s : uniformly spaced times [s] (n,)
    residual_um : residual drift per direction [µm] (n × 3: dx, dy, dz)
    windows_s : sliding-window lengths [s]

    Returns
    -------
    ``{"dx_um": {...}, "dy_um": {...}, "dz_um": {...}, "3d": {...}}`` with ``rms_um``, ``p2p_um`` and
    ``p95_range_um`` (window length [s] → value); for ``"3d"`` the RMS of the vector length and, per
    window, the largest of the three directions' values.
    """
    t = np.asarray(time_s, float)
    R = np.asarray(residual_um, float)
    dt = np.diff(t)
    if not np.allclose(dt, dt[0], rtol=1e-6, atol=1e-9):
        raise ValueError("drift_metrics needs uniformly spaced samples")
    out = {}
    for j, d in enumerate(DIRS):
        x = R[:, j]
        p95 = {}
        for w in windows_s:
            n = int(round(w / dt[0])) + 1
            p95[float(w)] = float(np.percentile(window_ranges(x, n), 95.0)) if n <= x.size else math.nan
        out[d] = {"rms_um": float(np.sqrt(np.mean(x**2))), "p2p_um": float(x.max() - x.min()), "p95_range_um": p95}
    out["3d"] = {
        "rms_um": float(np.sqrt(np.mean(np.sum(R**2, axis=1)))),
        "p2p_um": max(out[d]["p2p_um"] for d in DIRS),
        "p95_range_um": {float(w): max(out[d]["p95_range_um"][float(w)] for d in DIRS) for w in windows_s},
    }
    return out


def _hms(w: float) -> str:
    return f"{w / 3600:g} h" if w >= 3600 else f"{w / 60:g} min"


def metrics_table(metrics: Mapping[str, dict], windows_s: Sequence[float] = WINDOWS_S) -> str:
    """A Markdown table: one row per strategy and direction (and the 3-D residual)."""
    head = ["strategy", "direction", "RMS [µm]", "P2P [µm]", *(f"p95 range {_hms(w)} [µm]" for w in windows_s)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, m in metrics.items():
        for d in (*DIRS, "3d"):
            r = m[d]
            lines.append("| " + " | ".join([name, d.replace("_um", ""), f"{r['rms_um']:.2f}", f"{r['p2p_um']:.2f}",
                                            *(f"{r['p95_range_um'][float(w)]:.2f}" for w in windows_s)]) + " |")
    return "\n".join(lines)


def fit_mlr(T_degC: np.ndarray, drift_um: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of ``drift = c0 + Σ c_i T_i`` per direction ((1 + n_sensors) × 3)."""
    X = np.column_stack([np.ones(len(T_degC)), T_degC])
    coef, *_ = np.linalg.lstsq(X, drift_um, rcond=None)
    return coef


def predict_mlr(coef: np.ndarray, T_degC: np.ndarray) -> np.ndarray:
    return np.column_stack([np.ones(len(T_degC)), T_degC]) @ coef


# --------------------------------------------------------------------------- the scenario


def rom_sensor_temperatures(machine, rom, samples, increment_s: float = 300.0) -> np.ndarray:
    """Sensor temperatures [°C] at the sample times of a trace: the structure model on the trace's own BCs.

    The BCs are the histogram generator's, per ``increment_s`` [s]; the ROM steps each increment with its
    loads row held constant (the backward-Euler reading of the loads: row k+1 over increment k) and the
    sensor temperatures are interpolated linearly to the sample times.
    """
    from hybridcomp.histogram.bcs import boundary_conditions
    from hybridcomp.histogram.increments import increments_from_samples

    loads = boundary_conditions(machine, increments_from_samples(machine, samples, increment_s))
    sens = rom.simulate(loads, hold="step").sensors_degC
    return np.column_stack([np.interp(samples.time_s, loads.time_s, sens[:, j]) for j in range(sens.shape[1])])


@dataclass(frozen=True)
class ScenarioResult:
    """What :func:`run_scenario` produced: metrics per strategy, the Markdown table, events, files, a summary."""

    metrics: dict
    table: str
    events: list
    files: dict
    summary: dict


def _resample_loads(loads, machine, dt_s: float):
    from hybridcomp.fem.loads import Loads, in_model_order

    L = in_model_order(loads, machine)
    t = np.arange(L.time_s[0], L.time_s[-1] + 0.5 * dt_s, dt_s)
    t = t[t <= L.time_s[-1] + 1e-9]
    V = np.column_stack([np.interp(t, L.time_s, L.values[:, j]) for j in range(L.values.shape[1])])
    return Loads(t, V, L.names)


def planted_disturbance(machine, loads, disturbance_K: float, ramp_s: float = 7200.0):
    """The loads with every workspace zone's air ``disturbance_K`` warmer, ramped in over ``ramp_s`` [K, s]."""
    from hybridcomp.fem.loads import Loads

    V = loads.values.copy()
    ramp = disturbance_K * np.clip((loads.time_s - loads.time_s[0]) / ramp_s, 0.0, 1.0)
    for z in machine.zones:
        if z.air == "workspace":
            V[:, loads.names.index(f"{z.name}_degC")] += ramp
    return Loads(loads.time_s, V, loads.names)


def run_scenario(out_dir, element_size_mm: float = 80.0, disturbance_K: float = 2.0, rom_order: int | None = None,
                 basic_hours: float = 8.0, dt_s: float = 60.0, trace_rate_hz: float = 1.0,
                 history_s: float = 4 * 3600.0, machine_name: str = "vmc800", plot: bool = True,
                 real_machine=None, day_hours: float | None = None, keep_basis: bool = False) -> ScenarioResult:
    """Run the hybrid scenario end to end (see the module docstring) and write table, plot and events.

    Parameters
    ----------
    out_dir : output directory
    element_size_mm : FE element size of the real machine and of all training runs [mm]
    disturbance_K : planted workspace-air offset [K]
    rom_order : order of the structure model (None: reduce to the default tolerances)
    basic_hours : heating hours of each basic load case [h] (followed by as many cooling hours)
    dt_s : FE time step and evaluation grid [s]
    trace_rate_hz : sampling rate of the trace the monitor replays [Hz]
    history_s : load history a generation job trains on [s]
    machine_name : the machine of the models (ROM, CDs, generation jobs): a bundled name or a machine file
    real_machine : the machine that plays the real one (``models.Machine``; default the models' machine); its
        own source powers make its loads
    day_hours : replay only the first hours of the day [h] (default the whole 16 h)
    keep_basis : keep the ROM's projection basis in ``structure.rom.npz`` (for a diagnosis on the same model)

    Besides the table, plot and events, ``recorded.csv`` holds what a measuring campaign would have recorded
    on the real machine: the trace (positions, spindle speed, workshop air), the sensors and the drift.
    """
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.store import MonitorStore
    from hybridcomp.chardiag.fit import fit_cd_set
    from hybridcomp.chardiag.training import simulate_load_cases, standard_load_cases
    from hybridcomp.fem.model import build_model
    from hybridcomp.fem.transient import simulate
    from hybridcomp.histogram.bcs import boundary_conditions
    from hybridcomp.histogram.increments import increments_from_trace
    from hybridcomp.histogram.scenarios import JOBSHOP_HOURS, write_scenario
    from hybridcomp.models import load_machine
    from hybridcomp.monitor.config import parse_config
    from hybridcomp.monitor.daemon import Monitor, Regenerator, run_monitor
    from hybridcomp.monitor.sinks import MemorySink
    from hybridcomp.monitor.sources import ReplaySource
    from hybridcomp.rom import save_rom
    from hybridcomp.rom.machine import reduce_model

    out = Path(out_dir).resolve()  # once, against the caller's working directory (paths cross into the worker)
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    t_all = time.perf_counter()
    machine = load_machine(machine_name)
    pose = machine.default_pose_mm()
    pkey = pose_key(pose)

    # 1. the day as the controller records it (trace_rate_hz samples), its BCs, and the real machine
    #    (FE + planted disturbance) driven by the same BCs the models will derive from that record
    t0 = time.perf_counter()
    files = write_scenario("jobshop", machine, out / "scenario", rate_hz=trace_rate_hz)
    if day_hours is not None and not 0 < day_hours <= JOBSHOP_HOURS:
        raise ValueError(f"day_hours must be in (0, {JOBSHOP_HOURS:g}], got {day_hours}")
    t_end = (day_hours or JOBSHOP_HOURS) * 3600.0
    controller = out / "jobshop_controller_trace.csv"
    _write_monitor_trace(files["jobshop_trace.csv"], controller, trace_rate_hz, None, None, [], t_end=t_end)
    model = build_model(machine, pose, element_size_mm)
    loads = _resample_loads(boundary_conditions(machine, increments_from_trace(controller, machine, dt_s)), machine, dt_s)
    if real_machine is None:
        real_machine, real_model, real_loads = machine, model, loads
    else:
        inc = increments_from_trace(controller, real_machine, dt_s)
        real_loads = _resample_loads(boundary_conditions(real_machine, inc), real_machine, dt_s)
        real_model = build_model(real_machine, pose, element_size_mm)
    real = planted_disturbance(real_machine, real_loads, disturbance_K)
    res = simulate(real_model, real.time_s, real.as_inputs(real_machine.reference_temperature_degC), theta=0.5)
    t = res.time_s
    T_meas = res.sensors_degC
    truth = res.drift_um
    timings["real_machine_s"] = time.perf_counter() - t0
    log.info("real machine: %d nodes, %d steps, |drift| up to %.1f µm", model.n, t.size, np.abs(truth).max())

    # 2. the trace the monitor sees: the controller's samples, sensors from the real machine; and what a
    #    measuring campaign records (the same plus the drift)
    trace = out / "jobshop_monitor_trace.csv"
    _write_monitor_trace(controller, trace, trace_rate_hz, t, T_meas, [s.name for s in machine.sensors])
    recorded = out / "recorded.csv"
    _write_monitor_trace(controller, recorded, trace_rate_hz, t, np.column_stack([T_meas, truth]),
                         [f"{s.name}_degC" for s in machine.sensors] + list(DIRS), raw_names=True)

    # 3. the structure model
    t0 = time.perf_counter()
    rom = reduce_model(model, order=rom_order, keep_basis=keep_basis)
    rom_path = save_rom(out / "structure.rom.npz", rom)
    timings["reduction_s"] = time.perf_counter() - t0

    # 4. default CDs on the basic load cases (FE training runs on the same model)
    t0 = time.perf_counter()
    cases = standard_load_cases(machine, ("basic",), heat_h=basic_hours, cool_h=basic_hours)
    train = simulate_load_cases(machine, cases, pose, element_size_mm, dt_s=dt_s, model=model)
    timings["training_s"] = time.perf_counter() - t0
    default = fit_cd_set(train.columns, machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose,
                         load_case="basic", signature=train.signature(), source="basic load cases")
    db_path = out / "cd.db"
    for suffix in ("", "-wal", "-shm"):
        Path(str(db_path) + suffix).unlink(missing_ok=True)
    db = CDDatabase(db_path)
    default_ids = db.add_set(default, "basic")
    db.activate(machine.name, pkey, default_ids, "default CDs of the basic load cases", 0.0)

    # 5. the hybrid monitor on the replay
    t0 = time.perf_counter()
    cfg = parse_config({
        "monitor": {"machine": machine_name, "database": str(db_path), "rom": str(rom_path),
                    "pose_mm": dict(pose)},
        "compensation": {"max_offset_um": 200.0, "max_step_um": 5.0},
        "source": {"kind": "replay", "path": str(trace), "speed": 0},
        "sink": {"kind": "none"},
        "regeneration": {"enabled": True, "timeout_s": 1800.0, "element_size_mm": element_size_mm,
                         "history_s": history_s, "retry_after_s": 900.0},
    }, "scenario", out)
    mon = Monitor(cfg, machine, rom, db, pkey)
    sink = MemorySink()
    asyncio.run(run_monitor(cfg, mon, ReplaySource(trace, machine, 0.0), sink,
                            regenerator=Regenerator(cfg.regeneration.job, cfg.regeneration.timeout_s),
                            await_regeneration=True))
    timings["hybrid_s"] = time.perf_counter() - t0
    tt = np.array([r.time_s for r in sink.rows])
    off = np.array([[r.dx_um, r.dy_um, r.dz_um] for r in sink.rows])
    k = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
    hybrid = off[k]

    # 6. the other strategies
    measured = {f"{s.name}_degC": T_meas[:, j] for j, s in enumerate(machine.sensors)}
    measured |= {f"{a.name.lower()}_mm": np.full(t.size, float(pose[a.name])) for a in machine.axes}
    static = np.column_stack([default[d].evaluate_table(measured)[0] for d in ("X", "Y", "Z")])
    rom_drift = rom.simulate(loads).drift_um  # what the models know: no disturbance
    T_train = np.column_stack([train.columns[f"{s.name}_degC"] for s in machine.sensors])
    D_train = np.column_stack([train.columns[d] for d in DIRS])
    mlr = predict_mlr(fit_mlr(T_train, D_train), T_meas)

    preds = {"no compensation": np.zeros_like(truth), "static default CDs": static, "hybrid monitor": hybrid,
             "ROM direct": rom_drift, "MLR on sensors": mlr}
    metrics = {k_: drift_metrics(t, truth - p) for k_, p in preds.items()}
    table = metrics_table(metrics)
    events = [{"kind": e.kind, "machine_time_s": e.machine_time_s, **_event_brief(e)} for e in MonitorStore(db).events()
              if e.kind in ("activation", "generation") or (e.kind == "decision" and e.payload["action"] != "keep")]
    db.close()

    # 7. files: table, per-minute residuals, events, plot
    (out / "table.md").write_text(table + "\n")
    with (out / "residuals.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", *DIRS, *(f"{s.replace(' ', '_')}_{d}" for s in preds for d in DIRS)])
        for i in range(t.size):
            w.writerow([f"{t[i]:g}", *(f"{v:.4f}" for v in truth[i]), *(f"{v:.4f}" for p in preds.values() for v in p[i])])
    (out / "events.json").write_text(jsonio.dumps(events, indent=1))
    what = ([f"machine file {Path(real_machine.source).name}"] if real_machine is not machine else []) + \
        ([f"workspace air {disturbance_K:+g} K"] if disturbance_K else [])
    plot_path = _plot(out / "scenario.png", t, truth, preds, events, ", ".join(what) or "the nominal model") if plot else None
    m3 = {k_: v["3d"]["rms_um"] for k_, v in metrics.items()}
    summary = {
        "element_size_mm": element_size_mm, "nodes": int(model.n), "disturbance_K": disturbance_K, "rom_order": rom.order,
        "models_machine": str(machine.source), "real_machine": str(real_machine.source), "day_hours": float(t[-1] / 3600),
        "rms_3d_um": m3,
        "hybrid_over_static": m3["hybrid monitor"] / m3["static default CDs"],
        "hybrid_over_uncompensated": m3["hybrid monitor"] / m3["no compensation"],
        "acceptance": {"hybrid <= 0.5 static": m3["hybrid monitor"] <= 0.5 * m3["static default CDs"],
                       "hybrid <= 0.2 uncompensated": m3["hybrid monitor"] <= 0.2 * m3["no compensation"]},
        "switches": sum(1 for e in events if e["kind"] == "activation") - 1,
        "generations": sum(1 for e in events if e["kind"] == "generation" and e.get("status") == "finished"),
        "timings_s": {**timings, "total": time.perf_counter() - t_all},
    }
    (out / "summary.json").write_text(jsonio.dumps(summary, indent=1))
    return ScenarioResult(metrics, table, events, {"table": out / "table.md", "plot": plot_path,
                                                    "events": out / "events.json", "residuals": out / "residuals.csv",
                                                    "recorded": recorded, "rom": rom_path, "controller": controller},
                          summary)


def _event_brief(e) -> dict:
    p = e.payload
    if e.kind == "activation":
        return {"ids": p.get("ids"), "reason": p.get("reason")}
    if e.kind == "generation":
        return {"status": p.get("status"), "ids": p.get("ids"), "error": p.get("error"), "wall_s": p.get("wall_s")}
    return {"action": p.get("action"), "reason": p.get("reason"), "delta_T_K": p.get("delta_T_K")}


def _write_monitor_trace(src: Path, dst: Path, rate_hz: float, t_fe, T_fe, sensor_names, t_end: float = math.inf,
                         raw_names: bool = False) -> None:
    """Every sample of ``src`` on the ``rate_hz`` grid up to ``t_end`` [s], plus columns interpolated from the FE
    outputs (``<sensor>_degC``, or the names as given with ``raw_names``)."""
    names = list(sensor_names) if raw_names else [f"{n}_degC" for n in sensor_names]
    with src.open() as fi, dst.open("w") as fo:
        header = fi.readline().strip().split(",")
        ti = header.index("time_s")
        fo.write(",".join(header + names) + "\n")
        next_t = -math.inf
        rows = []
        for line in fi:
            f = line.strip().split(",")
            tt = float(f[ti])
            if tt > t_end + 1e-9:
                break
            if tt + 1e-9 < next_t:
                continue
            next_t = tt + 1.0 / rate_hz
            rows.append((tt, f))
        if not names:
            fo.writelines(",".join(f) + "\n" for _, f in rows)
            return
        times = np.array([r[0] for r in rows])
        T = np.column_stack([np.interp(times, t_fe, T_fe[:, j]) for j in range(T_fe.shape[1])])
        for (tt, f), Tr in zip(rows, T):
            fo.write(",".join(f + [f"{v:.4f}" for v in Tr]) + "\n")


def _plot(path: Path, t, truth, preds, events, title: str = "a warmer workspace"):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is missing (pip install 'hybridcomp[plot]'): no scenario plot")
        return None
    fig, axes = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    h = t / 3600.0
    for j, (ax, d) in enumerate(zip(axes, DIRS)):
        for name, p in preds.items():
            ax.plot(h, truth[:, j] - p[:, j], label=name, lw=1.2 if name == "hybrid monitor" else 0.9)
        ax.set_ylabel(f"residual {d.replace('_um', '')} [µm]")
        ax.grid(alpha=0.3)
        for e in events:
            if e["kind"] == "activation" and e["machine_time_s"]:
                ax.axvline(e["machine_time_s"] / 3600.0, color="k", lw=0.5, alpha=0.4)
    axes[0].legend(ncol=3, fontsize=8)
    axes[-1].set_xlabel("time [h] (vertical lines: CD set activations by the monitor)")
    fig.suptitle(f"job-shop day on the FE 'real machine' ({title}): residual TCP drift")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
