"""The hybrid scenario: the bundled job-shop day on a simulated real machine, every compensation strategy judged.

:func:`run_scenario` replays the 16 h job-shop day. The *real machine* is an FE model that differs from the
models by a :class:`Disturbance` (a mis-scaled or unmodelled heat source in its machine file, air the trace
does not measure, a failing sensor); it is driven by the BCs of the controller's trace at a finer step than
the monitor's, and what it measures (sensors with noise, occasional probed drift) is what the monitor gets.
Compared on the residual drift (true drift − compensation), every 60 s of the day:

* no compensation;
* static default CDs: fitted on the basic load cases (each axis alone, the spindle alone; FE training runs);
* the hybrid monitor: the daemon replaying the trace, its observer keeping the structure model on the machine,
  choosing and generating CD sets (strategy ``hybrid``);
* the observer: the same daemon writing the corrected structure model's drift (strategy ``observer``);
* the ROM used directly: the structure model on the trace's BCs, uncorrected;
* a multiple linear regression of the drift on the eight sensors, fitted on the basic load cases.

Metrics (:mod:`hybridcomp.metrics`): RMS, peak-to-peak, E_P95 over 15 min … 15 h, activations per 16 h day (those
within the day's half-open span, :func:`activations_within`) and the largest offset step per compensation cycle.
"""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import logging
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.histogram.trace import position_column
from hybridcomp.metrics import DIRS, drift_metrics, largest_step_um, metrics_table
from hybridcomp.models import jsonio
from hybridcomp.models.layout import PROBE_COLUMNS, in_model_order, temperature_column
from hybridcomp.models.toml import open_text
from hybridcomp.monitor.example import rom_outputs
from hybridcomp.safeio import write_text_atomic

log = logging.getLogger(__name__)

STRATEGIES = ("hybrid", "observer")
#: every strategy a scenario can run: ``"dataonly"`` needs the data-only model in ``monitor_overrides``
#: (``{"compensation": {"dataonly_model": path}}``, ``hybridcomp diagnose --data-only --probe-every-hours``)
ALL_STRATEGIES = STRATEGIES + ("dataonly",)
BOUND = "best sensor map (bound)"
NAMES = {"hybrid": "hybrid monitor", "observer": "observer", "dataonly": "data-only + probes"}


class ScenarioFileError(HybridcompError, ValueError):
    """A trace file of a scenario cannot be read; the message names the file."""


@dataclass(frozen=True)
class Disturbance:
    """What the real machine does that the models do not know.

    Attributes
    ----------
    name : short name (a table row, a folder)
    description : one sentence
    source_factor : (heat source, factor): the real machine dissipates factor × the source's power
    added_source : a heat source the models lack (a machine-file ``[[heat_sources]]`` table)
    workspace_air_K : the workspace zones' air runs this much warmer than the trace says, ramped in over 2 h [K]
    ambient_swing_K : every zone's air swings by ± this around what the trace says [K] ...
    swing_period_h : ... with this period [h]
    sensor_fault : (sensor, from [h], kind): ``"stuck"`` (the reading freezes) or ``"open"`` (it reads NaN)
    drive_edits : (axis, field, value) edits of the real machine's ``[[drives]]`` tables (a nut that puts more heat
        into its screw, a scale of another expansion coefficient, a seized floating bearing: ``mounting`` set to
        ``"pre-stretched"``): position-dependent errors that the drift at the model's pose hardly shows
    """

    name: str
    description: str
    source_factor: tuple[str, float] | None = None
    added_source: dict | None = None
    workspace_air_K: float = 0.0
    ambient_swing_K: float = 0.0
    swing_period_h: float = 6.0
    sensor_fault: tuple[str, float, str] | None = None
    drive_edits: tuple[tuple[str, str, float | str], ...] = ()

    def machine_edits(self) -> bool:
        return self.source_factor is not None or self.added_source is not None or bool(self.drive_edits)


NOMINAL = Disturbance("nominal", "the real machine is the model")

#: the benchmark's disturbances (the demo day is the mis-scaled front spindle bearing)
DISTURBANCES = {
    d.name: d for d in (
        Disturbance("demo day", "the front spindle bearing dissipates 1.6 × its nominal power",
                    source_factor=("spindle_bearing_front", 1.6)),
        Disturbance("ambient swing", "the air around the machine swings ±1.5 K with a 6 h period that the trace "
                    "does not measure", ambient_swing_K=1.5, swing_period_h=6.0),
        Disturbance("unmodelled source", "a coolant pump on the column's back (60 W, on while the spindle runs) "
                    "that the machine file lacks",
                    added_source={"name": "coolant_pump", "body": "column", "position_mm": [0.0, 1090.0, 600.0],
                                  "size_mm": [300.0, 20.0, 300.0], "power_W": 60.0, "driver": "spindle",
                                  "exponent": 0.05}),
        Disturbance("mis-scaled source", "the spindle motor leaves 0.6 × the heat the model assumes in the "
                    "structure (a better cooling jacket)", source_factor=("spindle_motor", 0.6)),
        Disturbance("sensor fault", "the demo day, and sensor T1 (spindle housing) freezes at 8 h",
                    source_factor=("spindle_bearing_front", 1.6), sensor_fault=("T1", 8.0, "stuck")),
        Disturbance("workspace air", "the workspace air behind the enclosure runs 2 K warmer than the workshop "
                    "air the trace measures", workspace_air_K=2.0),
        Disturbance("nut heat", "the X and Y nuts, preloaded harder than the machine file says, put 2.5 x the heat "
                    "into their screws", drive_edits=(("X", "nut_screw_W", 37.5), ("Y", "nut_screw_W", 37.5))),
        Disturbance("scale expansion", "the Z scale is a steel scale (11.5e-6 1/K), not the glass scale of the machine "
                    "file (8e-6 1/K)", drive_edits=(("Z", "scale_expansion_1_K", 11.5e-6),)),
        Disturbance("bearing seized", "the Y screw's floating bearing has seized: its bearings hold the screw at both "
                    "ends like a pre-stretched one (the machine file says fixed-floating)",
                    drive_edits=(("Y", "mounting", "pre-stretched"),)),
    )
}
#: the disturbances whose effect depends on the pose: judged along the path only (at the model's pose they are small)
POSITION_DEPENDENT = ("nut heat", "scale expansion", "bearing seized")


def real_machine_file(machine, disturbance: Disturbance, path: Path) -> Path:
    """Write the real machine's file: the machine file with the disturbance's source and drive edits."""
    from hybridcomp.models.toml import dumps_toml, read_toml

    data, _ = read_toml(machine.source)
    sources = {s["name"]: s for s in data.get("heat_sources", [])}
    notes = []
    if disturbance.source_factor is not None:
        name, factor = disturbance.source_factor
        if name not in sources:
            raise ValueError(f"disturbance {disturbance.name!r}: machine {machine.name!r} has no heat source {name!r} "
                             f"(sources: {', '.join(sources)})")
        if not factor > 0:
            raise ValueError(f"disturbance {disturbance.name!r}: the power factor must be positive, got {factor}")
        sources[name]["power_W"] = float(sources[name]["power_W"]) * factor
        notes.append(f"{name} at {factor:g} x its power")
    if disturbance.added_source is not None:
        data.setdefault("heat_sources", []).append(dict(disturbance.added_source))
        notes.append(f"an added source {disturbance.added_source['name']!r}")
    drives = {d["axis"]: d for d in data.get("drives", [])}
    for axis, name, value in disturbance.drive_edits:
        if axis not in drives:
            raise ValueError(f"disturbance {disturbance.name!r}: machine {machine.name!r} has no drive of axis {axis!r} "
                             f"(drives: {', '.join(drives) or 'none'})")
        drives[axis][name] = value
        notes.append(f"drive {axis} {name} = {value:g}" if isinstance(value, float) else f"drive {axis} {name} = {value}")
    data["machine"]["name"] = f"{machine.name}_real"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# the real machine of the scenario: {machine.name} with {', '.join(notes) or 'no change'}\n\n"
                    + dumps_toml(data))
    return path


def low_pass(time_s: np.ndarray, X: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order low-pass of the columns of ``X`` (the daemon's sensor filter), NaN held over."""
    X = np.asarray(X, float)
    if tau_s <= 0:
        return X.copy()
    out = np.empty_like(X)
    y = X[0].copy()
    out[0] = y
    a = -np.expm1(-np.diff(time_s) / tau_s)
    for k in range(1, len(X)):
        x = X[k]
        ok = np.isfinite(x) & np.isfinite(y)
        y = np.where(ok, y + a[k - 1] * (x - y), np.where(np.isfinite(x), x, y))
        out[k] = y
    return out


def fit_mlr(T_degC: np.ndarray, drift_um: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of ``drift = c0 + Σ c_i T_i`` per direction ((1 + n_sensors) × 3)."""
    X = np.column_stack([np.ones(len(T_degC)), T_degC])
    coef, *_ = np.linalg.lstsq(X, drift_um, rcond=None)
    return coef


def predict_mlr(coef: np.ndarray, T_degC: np.ndarray) -> np.ndarray:
    """The drift [µm] the coefficients of :func:`fit_mlr` give for sensor rows [°C]."""
    return np.column_stack([np.ones(len(T_degC)), T_degC]) @ coef


def rom_sensor_temperatures(machine, rom, samples, increment_s: float = 300.0) -> np.ndarray:
    """Sensor temperatures [°C] at the sample times of a trace (see :func:`rom_outputs`)."""
    return rom_outputs(machine, rom, samples, increment_s)[0]


@dataclass(frozen=True)
class Models:
    """What the scenario's monitor knows, built once per machine file and mesh.

    The FE model, the structure model (saved), the default CDs of the basic load cases and a CD database holding
    them (activated); with ``poses`` also the pose-aware structure model (:mod:`hybridcomp.rom.poses`: the drift at
    every pose and the feed drives' errors) for the evaluation along the path.
    """

    machine: object
    pose_mm: dict
    model: object
    rom: object
    rom_path: Path
    default: dict
    train: object
    database: Path
    timings_s: dict
    pose_rom: object | None = None
    pose_rom_path: Path | None = None


def build_models(out_dir, machine_name: str = "vmc800", element_size_mm: float = 80.0, rom_order: int | None = None,
                 basic_hours: float = 8.0, dt_s: float = 60.0, keep_basis: bool = False, poses: bool = False) -> Models:
    """The models of a scenario (see :class:`Models`), written into ``out_dir``."""
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import fit_cd_set
    from hybridcomp.chardiag.training import simulate_load_cases, standard_load_cases
    from hybridcomp.fem.model import build_model
    from hybridcomp.models import load_machine
    from hybridcomp.rom import save_rom
    from hybridcomp.rom.machine import reduce_model

    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    machine = load_machine(machine_name)
    pose = machine.default_pose_mm()
    timings = {}
    t0 = time.perf_counter()
    model = build_model(machine, pose, element_size_mm)
    rom = reduce_model(model, order=rom_order, keep_basis=keep_basis or poses)
    pose_rom = None
    if poses:
        from hybridcomp.rom.poses import reduce_at_poses

        t1 = time.perf_counter()
        pose_rom = reduce_at_poses(model, rom, "star")
        timings["pose_reduction_s"] = time.perf_counter() - t1
        if not keep_basis:
            rom = dataclasses.replace(rom, V=None, _cache={})
    rom_path = save_rom(out / "structure.rom.npz", rom)
    pose_rom_path = save_rom(out / "structure_poses.rom.npz", pose_rom) if pose_rom is not None else None
    timings["reduction_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cases = standard_load_cases(machine, ("basic",), heat_h=basic_hours, cool_h=basic_hours)
    train = simulate_load_cases(machine, cases, pose, element_size_mm, dt_s=dt_s, model=model, scheme="theta",
                                theta=0.5)
    timings["training_s"] = time.perf_counter() - t0
    default = fit_cd_set(train.columns, machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose,
                         load_case="basic", signature=train.signature(), source="basic load cases")
    database = out / "cd_default.db"
    _fresh_db(database)
    db = CDDatabase(database)
    try:
        db.activate(machine.name, pose_key(pose), db.add_set(default, "basic"), "default CDs of the basic load cases", 0.0)
    finally:
        db.close()
    return Models(machine, pose, model, rom, rom_path, default, train, database, timings, pose_rom, pose_rom_path)


@dataclass(frozen=True)
class ScenarioResult:
    """What :func:`run_scenario` produced: metrics per strategy, the Markdown table, events, files, a summary.

    For a study on the same day (the verification, :mod:`hybridcomp.verify`): ``path`` the real machine's drift at
    any pose and time (``along_path`` runs, else None), ``runs`` each daemon strategy's run (its offsets at the
    model's pose over time, its support-point tables), ``sensors`` what the controller read (``time_s``,
    ``degC`` with noise and fault, ``filtered_degC``) in the machine's sensor order.
    """

    metrics: dict
    table: str
    events: list
    files: dict
    summary: dict
    path: PathTruth | None = None
    runs: dict | None = None
    sensors: dict | None = None


def planted_air(machine, loads, d: Disturbance):
    """The loads with the disturbance's air: workspace zones warmer (ramped in over 2 h), every zone swinging."""
    from hybridcomp.fem.loads import Loads

    V = loads.values.copy()
    t = loads.time_s - loads.time_s[0]
    ramp = d.workspace_air_K * np.clip(t / 7200.0, 0.0, 1.0)
    swing = d.ambient_swing_K * np.sin(2 * np.pi * t / (d.swing_period_h * 3600.0))
    for z in machine.zones:
        j = loads.names.index(temperature_column(z.name))
        V[:, j] += swing + (ramp if z.air == "workspace" else 0.0)
    return Loads(loads.time_s, V, loads.names)


def check_day(disturbance: Disturbance, day_hours: float | None, option: str = "day_hours") -> None:
    """Refuse a replayed day that the disturbance does not fit in, before any work or file.

    Parameters
    ----------
    disturbance : the scenario's disturbance
    day_hours : hours of the job-shop day replayed [h] (None: the whole day)
    option : how the caller spells the hours in the message (``"--day-hours"`` on the command line)

    Raises
    ------
    ValueError
        ``day_hours`` outside (0, 16], or the day ends at or before the disturbance's sensor fault starts (a fault
        planted after the last sample cannot be seen; the fault stays where the disturbance's description puts it).
    """
    from hybridcomp.histogram.scenarios import JOBSHOP_HOURS

    hours = JOBSHOP_HOURS if day_hours is None else day_hours
    if not 0 < hours <= JOBSHOP_HOURS:
        raise ValueError(f"{option} must be in (0, {JOBSHOP_HOURS:g}], got {day_hours}")
    fault = disturbance.sensor_fault
    if fault is not None and hours <= fault[1]:
        raise ValueError(f"{option} {hours:g}: the day ends before disturbance {disturbance.name!r} plants its fault "
                         f"on sensor {fault[0]} ({fault[2]}) at {fault[1]:g} h; give {option} above {fault[1]:g} "
                         f"(at most {JOBSHOP_HOURS:g})")


@dataclass(frozen=True)
class Scenario:
    """One run of the hybrid scenario (:func:`run_scenario`): the day, the real machine, the models, the monitor.

    Attributes
    ----------
    disturbance : what the real machine does that the models do not know
    real_machine : the real machine's ``models.Machine`` (default: the models' machine with the disturbance's
        source edits)
    machine_name : the machine of the models (ROM, CDs, generation): a bundled name or a machine file
    element_size_mm : FE element size of the real machine and of every model [mm]
    rom_order : order of the structure model (None: reduce to the default tolerances)
    basic_hours : heating hours of each basic load case of the default CDs [h] (as many cooling hours follow)
    day_hours : replay only the first hours of the day [h] (default the whole 16 h)
    dt_s : evaluation grid and the models' loads step [s]
    real_dt_s : load step of the real machine's FE run [s] (finer than the models' ``dt_s`` loads)
    trace_rate_hz : sampling rate of the trace the monitor replays [Hz]
    sensor_noise_K : noise of the sensors the monitor reads [K]
    probe_every_h : a probed drift (noise ``probe_noise_um`` [µm]) at the start and every this many hours [h];
        None: no probing
    probe_noise_um : noise of a probed drift [µm]
    strategies : daemon strategies to run (``"hybrid"``, ``"observer"``; ``"dataonly"`` with its model given in
        ``monitor_overrides``, :data:`ALL_STRATEGIES`)
    plot : draw ``scenario.png``
    keep_basis : keep the ROM's projection basis in ``structure.rom.npz`` (for a diagnosis on the same model)
    seed : seed of the sensor and probe noise
    monitor_overrides : extra sections for the daemon's configuration (``{"validity": {...}}``)
    along_path : also judge every strategy at the commanded position of the trace at each time, where the drift
        depends on the pose and the feed drives' errors on the axis positions (needs the models' pose-aware
        structure model: built by :func:`run_scenario` when it is given no models, and given models must have it:
        ``build_models(..., poses=True)``); adds ``table_along_path.md`` and the summary's ``along_path``
    """

    disturbance: Disturbance = NOMINAL
    real_machine: object | None = None
    machine_name: str = "vmc800"
    element_size_mm: float = 80.0
    rom_order: int | None = None
    basic_hours: float = 8.0
    day_hours: float | None = None
    dt_s: float = 60.0
    real_dt_s: float = 20.0
    trace_rate_hz: float = 1.0
    sensor_noise_K: float = 0.02
    probe_every_h: float | None = 4.0
    probe_noise_um: float = 0.3
    strategies: tuple[str, ...] = STRATEGIES
    plot: bool = True
    keep_basis: bool = False
    seed: int = 0
    monitor_overrides: dict | None = None
    along_path: bool = False

    def __post_init__(self):

        if isinstance(self.strategies, str):
            raise ValueError(f"strategies must be a sequence of strategy names, got the string {self.strategies!r}")
        object.__setattr__(self, "strategies", tuple(self.strategies))
        for s in self.strategies:
            if s not in ALL_STRATEGIES:
                raise ValueError(f"unknown strategy {s!r} (strategies: {', '.join(ALL_STRATEGIES)})")
        if "dataonly" in self.strategies and not (self.monitor_overrides or {}).get("compensation", {}).get(
                "dataonly_model"):
            raise ValueError("strategy 'dataonly' needs its model: monitor_overrides={'compensation': "
                             "{'dataonly_model': path}} (hybridcomp diagnose --data-only --probe-every-hours H)")
        check_day(self.disturbance, self.day_hours)
        for name in ("element_size_mm", "basic_hours", "dt_s", "real_dt_s", "trace_rate_hz"):
            _check_number(name, getattr(self, name), positive=True)
        for name in ("sensor_noise_K", "probe_noise_um"):
            _check_number(name, getattr(self, name), positive=False)
        if self.probe_every_h is not None:
            _check_number("probe_every_h", self.probe_every_h, positive=True, none_is="no probing")
        if self.rom_order is not None and not (isinstance(self.rom_order, int) and self.rom_order >= 1):
            raise ValueError(f"rom_order must be a whole number >= 1 or None (the default tolerances), "
                             f"got {self.rom_order!r}")


def _check_number(name: str, value, positive: bool, none_is: str | None = None) -> None:
    """Raise ``ValueError`` naming the field unless ``value`` is a finite number > 0 (``positive``) or >= 0."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not (value > 0 if positive else value >= 0):
        bound = "> 0" if positive else ">= 0"
        alt = f" or None ({none_is})" if none_is else ""
        raise ValueError(f"{name} must be a finite number {bound}{alt}, got {value!r}")


def run_scenario(scenario: Scenario, out_dir, models: Models | None = None) -> ScenarioResult:
    """Run the hybrid scenario end to end (see the module docstring) and write table, plot and events.

    Parameters
    ----------
    scenario : the day, the disturbance, the models' settings and the monitor's (:class:`Scenario`)
    out_dir : output directory
    models : the models, built by :func:`build_models` (default: built here, into ``out_dir``, from the
        scenario's settings); several disturbances of one machine share them

    Besides the table, plot and events, ``recorded.csv`` holds what a measuring campaign would have recorded
    on the real machine: the trace (positions, spindle speed, workshop air), the sensors and the drift.
    """
    if scenario.along_path and models is not None and models.pose_rom is None:  # before any file
        raise ValueError("along_path needs the models' pose-aware structure model: build_models(..., poses=True)")
    out = Path(out_dir).resolve()  # once, against the caller's working directory (paths cross into the worker)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    models, real_machine = _models_and_real_machine(scenario, out, models)
    timings = dict(models.timings_s)
    day = _real_machine_day(scenario, out, models, real_machine, timings)
    path = None
    if scenario.along_path:
        t0 = time.perf_counter()
        path = _path_truth(models, real_machine, day)
        timings["real_pose_model_s"] = time.perf_counter() - t0
    measured = _measure(scenario, out, models.machine, day, path)
    runs = replay_strategies(scenario, out, models, measured.trace, day.t, timings, volumetric=scenario.along_path)
    preds = _predictions(models, measured, day, runs)
    metrics = _metrics(day, preds, runs)
    table = metrics_table(metrics)
    path_summary = None
    if scenario.along_path:
        t0 = time.perf_counter()
        path_summary = _along_path(out, models, day, preds, runs, path)
        if scenario.probe_every_h:
            path_summary["drives"] = drive_diagnosis(models, day.loads, measured.trace, scenario.probe_noise_um)
        timings["along_path_s"] = time.perf_counter() - t0
    files, all_events = _write_results(scenario, out, day, preds, runs, table)
    summary = _summary(scenario, models, real_machine, day, metrics, runs, timings, t_all, path_summary)
    write_text_atomic(out / "summary.json", jsonio.dumps(summary, indent=1))
    return ScenarioResult(metrics, table, all_events,
                          {**files, "recorded": measured.recorded, "rom": models.rom_path,
                           "controller": day.controller, "trace": measured.trace},
                          summary, path, runs, measured.sensors)


def _models_and_real_machine(scenario: Scenario, out: Path, models: Models | None) -> tuple[Models, object]:
    """The models (given, or built into ``out``) and the real machine (given, or the disturbance's edits)."""
    from hybridcomp.models import load_machine

    s = scenario
    if models is None:
        models = build_models(out, s.machine_name, s.element_size_mm, s.rom_order, s.basic_hours, s.dt_s,
                              s.keep_basis, s.along_path)
    real_machine, machine, disturbance = s.real_machine, models.machine, s.disturbance
    if real_machine is None:
        real_machine = (load_machine(real_machine_file(machine, disturbance, out / "real_machine.toml"))
                        if disturbance.machine_edits() else machine)
    return models, real_machine


@dataclass(frozen=True)
class _Day:
    """The day as the controller records it and as the real machine lives it (:func:`_real_machine_day`)."""

    controller: Path
    loads: object
    real_loads: object
    res: object
    t: np.ndarray
    truth: np.ndarray
    real_model: object = None


def _real_machine_day(scenario: Scenario, out: Path, models: Models, real_machine, timings: dict) -> _Day:
    """The day as the controller records it, the models' BCs of it, and the real machine's response.

    The real machine is driven by the BCs of the same record at a finer step, with the disturbance's air; adds
    ``real_machine_s`` to ``timings``.
    """
    from hybridcomp.fem.model import build_model
    from hybridcomp.histogram.bcs import boundary_conditions
    from hybridcomp.histogram.increments import increments_from_trace
    from hybridcomp.histogram.scenarios import JOBSHOP_HOURS, write_scenario

    machine, pose, model = models.machine, models.pose_mm, models.model
    dt_s, real_dt_s, element_size_mm = scenario.dt_s, scenario.real_dt_s, scenario.element_size_mm
    disturbance, trace_rate_hz, day_hours = scenario.disturbance, scenario.trace_rate_hz, scenario.day_hours
    t0 = time.perf_counter()
    files = write_scenario("jobshop", machine, out / "scenario", rate_hz=trace_rate_hz)
    t_end = (day_hours or JOBSHOP_HOURS) * 3600.0
    controller = out / "jobshop_controller_trace.csv"
    _write_trace(files["jobshop_trace.csv"], controller, trace_rate_hz, t_end=t_end)
    loads = in_model_order(boundary_conditions(machine, increments_from_trace(controller, machine, dt_s)),
                           machine).resample(dt_s)
    real_model = model if real_machine.sha256 == machine.sha256 else build_model(real_machine, pose, element_size_mm)
    real_loads = in_model_order(boundary_conditions(real_machine, increments_from_trace(controller, real_machine,
                                                                                        real_dt_s)),
                                real_machine).resample(real_dt_s)
    real_loads = planted_air(real_machine, real_loads, disturbance)
    res = real_model.simulate(real_loads, "steady", scheme="theta", theta=0.5)
    t = loads.time_s
    truth = np.column_stack([np.interp(t, res.time_s, res.drift_um[:, j]) for j in range(3)])
    timings["real_machine_s"] = time.perf_counter() - t0
    log.info("real machine: %d nodes, %d steps, |drift| up to %.1f µm", real_model.n, res.time_s.size, np.abs(truth).max())
    return _Day(controller, loads, real_loads, res, t, truth, real_model)


@dataclass(frozen=True)
class _Measured:
    """What the controller measures and a measuring campaign records (:func:`_measure`)."""

    trace: Path
    recorded: Path
    sensors: dict
    sensor_names: list


def _measure(scenario: Scenario, out: Path, machine, day: _Day, path: PathTruth | None = None) -> _Measured:
    """What the controller measures (sensors with noise and the fault, probes) and a measuring campaign records.

    With ``path`` (along the path) every probe cycle touches the support poses of a star over the workspace
    (:func:`probe_poses`), one a sample, and measures the real machine's drift there.
    """
    s = scenario
    sensor_names = [x.name for x in machine.sensors]
    trace = out / "jobshop_monitor_trace.csv"
    measured = _write_trace(day.controller, trace, s.trace_rate_hz, fe=(day.res.time_s, day.res.sensors_degC,
                                                                         day.res.drift_um),
                            sensor_names=sensor_names, noise_K=s.sensor_noise_K, rng=np.random.default_rng(s.seed),
                            fault=s.disturbance.sensor_fault, probe_every_h=s.probe_every_h,
                            probe_noise_um=s.probe_noise_um,
                            probe_cycle=None if path is None else (probe_poses(machine, path.pose_mm), path.at,
                                                                   [position_column(a.name) for a in machine.axes]))
    recorded = out / "recorded.csv"
    _write_recorded(trace, recorded, day.res, sensor_names)
    return _Measured(trace, recorded, measured, sensor_names)


def replay_strategies(scenario: Scenario, out: Path, models: Models, trace: Path, t: np.ndarray,
                       timings: dict, volumetric: bool = False) -> dict:
    """The daemon on the replay, once per strategy, each with its own copy of the database.

    Returns each strategy's run (:func:`_replay`) with its offsets [µm] at the model's pose at the times ``t`` [s]
    (``"at_t"``); adds ``<strategy>_s`` to ``timings``. ``volumetric``: the daemon runs the pose-aware structure
    model and writes a support-point table every cycle (the run's ``"tables"``).
    """
    from hybridcomp.chardiag.cd import pose_key

    machine, pose, rom, rom_path = models.machine, models.pose_mm, models.rom, models.rom_path
    if volumetric and models.pose_rom is not None:
        if models.pose_rom_path is None:
            raise ValueError("the pose-aware structure model has no file (build_models(..., poses=True) writes one)")
        rom, rom_path = models.pose_rom, models.pose_rom_path
    pkey = pose_key(pose)
    runs = {}
    for strategy in scenario.strategies:
        t0 = time.perf_counter()
        db_path = out / f"cd_{strategy}.db"
        _fresh_db(db_path)
        shutil.copyfile(models.database, db_path)
        runs[strategy] = _replay(strategy, str(machine.source), db_path, rom_path, trace, pose, pkey, machine,
                                 rom, scenario.element_size_mm, scenario.monitor_overrides)
        timings[f"{strategy}_s"] = time.perf_counter() - t0
        tt, off = runs[strategy]["time_s"], runs[strategy]["offsets_um"]
        k = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
        runs[strategy]["at_t"] = off[k]
    return runs


def _predictions(models: Models, measured: _Measured, day: _Day, runs: dict) -> dict:
    """Every strategy's drift [µm] at the day's times, and the bound.

    The daemon's runs and the others: the CDs and the regression read the sensors through the daemon's low-pass.
    """
    machine, pose, rom, t, truth = models.machine, models.pose_mm, models.rom, day.t, day.truth
    sensor_names = measured.sensor_names
    T_cd = at_times(measured.sensors["time_s"], measured.sensors["filtered_degC"], t)
    cols = {temperature_column(n): T_cd[:, j] for j, n in enumerate(sensor_names)}
    cols |= {position_column(a.name): np.full(t.size, float(pose[a.name])) for a in machine.axes}
    static = np.column_stack([models.default[d].evaluate_table(cols)[0] for d in ("X", "Y", "Z")])
    rom_drift = rom.simulate(day.loads).drift_um  # what the models know: no disturbance, no sensor
    T_train = np.column_stack([models.train.columns[temperature_column(s)] for s in sensor_names])
    D_train = np.column_stack([models.train.columns[d] for d in DIRS])
    mlr = predict_mlr(fit_mlr(T_train, D_train), T_cd)
    # a yardstick, not a strategy: the linear map of the day's own sensors that fits the day's true drift best (in
    # sample). No linear map of these sensors does better on the whole day; a CD (piecewise linear per sensor)
    # can bend where it cannot, so for CDs it indicates what the sensors allow
    ok = np.all(np.isfinite(T_cd), axis=1)
    bound = np.full_like(truth, np.nan)
    bound[ok] = predict_mlr(fit_mlr(T_cd[ok], truth[ok]), T_cd[ok])
    daemon = {NAMES[strategy]: r["at_t"] for strategy, r in runs.items()}
    return {"no compensation": np.zeros_like(truth), "static default CDs": static, **daemon, "ROM direct": rom_drift,
            "MLR on sensors": mlr, BOUND: bound}


def activations_within(events: list[dict], start_s: float, end_s: float) -> int:
    """The activations in the day ``[start_s, end_s)``: one at the last sample's time is the next day's.

    The interval decisions fall on the quarter hours, the day's first and last samples too: a set activated at the
    last sample compensates the next day, and counted over the closed span it counted in both of two days run in a
    row (the benchmark's sensor-fault day: 9 activations, one of them at 16 h 00).
    """
    return sum(1 for e in events if e["kind"] == "activation" and start_s <= e["machine_time_s"] < end_s)


def _metrics(day: _Day, preds: dict, runs: dict) -> dict:
    """The residual metrics of every strategy, the daemon's with its activations, generations and largest step."""
    t = day.t
    metrics = {k_: drift_metrics(t, day.truth - p) for k_, p in preds.items()}
    per_day = 16.0 * 3600.0 / max(t[-1] - t[0], 1.0)
    for strategy, r in runs.items():
        m = metrics[NAMES[strategy]]
        m["activations"] = r["activations"]
        m["activations_per_16h"] = activations_within(r["events"], t[0], t[-1]) * per_day
        m["largest_step_um"] = r["largest_step_um"]
        m["generations"] = r["generations"]
    return metrics


def _write_results(scenario: Scenario, out: Path, day: _Day, preds: dict, runs: dict, table: str) -> tuple[dict, list]:
    """The files: table, per-minute residuals, events, plot. Returns the files and the events of every strategy."""
    t, truth = day.t, day.truth
    disturbance = scenario.disturbance
    (out / "table.md").write_text(table + "\n")
    _write_residuals(out / "residuals.csv", t, truth, preds)
    events = {strategy: r["events"] for strategy, r in runs.items()}
    all_events = [dict(e, strategy=s) for s, ev in events.items() for e in ev]
    (out / "events.json").write_text(jsonio.dumps(all_events, indent=1))
    plot_path = _plot(out / "scenario.png", t, truth, preds, events.get("hybrid", []),
                      f"{disturbance.name}: {disturbance.description}") if scenario.plot else None
    return ({"table": out / "table.md", "plot": plot_path, "events": out / "events.json",
             "residuals": out / "residuals.csv"}, all_events)


def _write_residuals(path: Path, t: np.ndarray, truth: np.ndarray, preds: dict, positions: dict | None = None) -> None:
    """A CSV of the day: time, positions, the true drift and every prediction, (dx, dy, dz) each [µm].

    ``positions``: column name → values (e.g. the path's axis positions [mm]).
    """
    positions = positions or {}
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", *positions, *DIRS, *(f"{s.replace(' ', '_')}_{d}" for s in preds for d in DIRS)])
        for i in range(t.size):
            w.writerow([f"{t[i]:g}", *(f"{v[i]:.3f}" for v in positions.values()), *(f"{v:.4f}" for v in truth[i]),
                        *(f"{v:.4f}" for p in preds.values() for v in p[i])])


def _summary(scenario: Scenario, models: Models, real_machine, day: _Day, metrics: dict, runs: dict, timings: dict,
             t_all: float, path_summary: dict | None) -> dict:
    """``summary.json``: the run's settings, the 3-D RMS of every strategy, the daemon's counts, the timings [s]."""
    s, t = scenario, day.t
    m3 = {k_: v["3d"]["rms_um"] for k_, v in metrics.items()}
    summary = {
        "disturbance": {"name": s.disturbance.name, "description": s.disturbance.description},
        "element_size_mm": s.element_size_mm, "nodes": int(models.model.n), "rom_order": models.rom.order,
        "models_machine": str(models.machine.source), "real_machine": str(real_machine.source),
        "day_hours": float(t[-1] / 3600),
        "sensor_noise_K": s.sensor_noise_K, "probe_every_h": s.probe_every_h, "real_dt_s": s.real_dt_s,
        "rms_3d_um": m3,
        "switches": {k: r["activations"] for k, r in runs.items()},
        "generations": {k: r["generations"] for k, r in runs.items()},
        "largest_step_um": {k: r["largest_step_um"] for k, r in runs.items()},
        "timings_s": {**timings, "total": time.perf_counter() - t_all},
    }
    if path_summary is not None:
        summary["along_path"] = path_summary
    return summary


PATH_STRATEGY = "ROM direct along the path"
#: the volumetric daemons judged at the model's pose with its drives (what the part sees there): "<strategy> <this>"
AT_POSE_WITH_DRIVES = "at the model's pose, drives included"


def trace_samples(machine, trace: Path) -> tuple[np.ndarray, np.ndarray]:
    """A trace's sample times [s] (ns,) and commanded axis positions [mm] (ns × axes), read once."""
    from hybridcomp.histogram.trace import read_trace_chunks

    chunks = list(read_trace_chunks(trace, machine))
    return np.concatenate([c.time_s for c in chunks]), np.vstack([c.position_mm for c in chunks])


def trace_positions(ts: np.ndarray, P: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The commanded axis positions (nt × axes) of a trace's samples (:func:`trace_samples`) at the times ``t``.

    The last sample at or before each time.
    """
    k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 1)
    return P[k]


def trace_step_weights(grid, ts: np.ndarray, P: np.ndarray, t: np.ndarray):
    """Where the trace's machine was over every step of ``t``: a :class:`~hybridcomp.rom.poses.StepPoses` (nt × poses).

    Row k: over the step from ``t[k]`` on, the support poses' weights of the trace's samples (:func:`trace_samples`)
    in it, each for the time until the next sample (:func:`hybridcomp.rom.poses.integrate_along`), their range and
    the first one's; a step with no sample: the last sample's.
    """
    from hybridcomp.rom.poses import StepPoses

    Ws = grid.weights_along(P)
    dts = np.diff(ts, append=ts[-1])
    W, lo, hi, first = (np.empty((t.size, Ws.shape[1])) for _ in range(4))
    row = np.searchsorted(t, ts, side="right") - 1  # the step each sample falls in
    for k in range(t.size):
        mine = row == k
        if mine.any() and dts[mine].sum() > 0:
            s = StepPoses.of(Ws[mine], dts[mine])
        else:
            s = StepPoses.held(Ws[max(int(np.searchsorted(ts, t[k], side="right")) - 1, 0)])
        W[k], lo[k], hi[k], first[k] = s.weights, s.low, s.high, s.first
    return StepPoses(W, lo, hi, first)


@dataclass(frozen=True)
class PathTruth:
    """The real machine's drift at any pose over the day (``Scenario(along_path=True)``).

    The real machine's FE drift at the model's pose plus what the pose adds on the real machine: the real
    machine's OWN pose-aware structure model (its machine file, disturbance and all, reduced at the support
    poses like the models' one; the models' own when the real machine is the model) driven by the real machine's
    loads along the poses it visits (its pose history, :func:`hybridcomp.rom.poses.integrate_along`), at the pose
    less at the model's pose.  ``positions``, ``added`` and where the machine was (``poses``, the support poses'
    weights of the trace's samples, :func:`trace_step_weights`) are at the day's times ``t``.
    """

    pose_mm: dict
    t: np.ndarray
    truth: np.ndarray
    rom: object
    Y: np.ndarray
    positions: np.ndarray
    added: np.ndarray
    own: bool
    poses: object

    def at(self, t_s: float, positions_mm: np.ndarray) -> np.ndarray:
        """The real machine's drift [µm] (m × 3) at the time ``t_s`` at the poses ``positions_mm`` (m × axes)."""
        from hybridcomp.rom.poses import drift_along

        P = np.atleast_2d(np.asarray(positions_mm, float))
        y = np.array([np.interp(t_s, self.t, self.Y[:, j]) for j in range(self.Y.shape[1])])[None, :]
        at_pose = np.array([np.interp(t_s, self.t, self.truth[:, j]) for j in range(3)])
        Yr = np.repeat(y, P.shape[0], axis=0)
        return at_pose + drift_along(self.rom, Yr, P) - _tcp_um(self.rom, Yr)


def _path_truth(models: Models, real_machine, day: _Day) -> PathTruth:
    """The real machine's drift along the day's path and at any pose (:class:`PathTruth`)."""
    from hybridcomp.rom.poses import drift_along, grid_of, integrate_along

    prom, machine, t = models.pose_rom, models.machine, day.t
    ts, P = trace_samples(machine, day.controller)
    positions = trace_positions(ts, P, t)
    own = real_machine.sha256 != machine.sha256
    real_prom = real_pose_model(day.real_model, models.rom.order) if own else prom
    values = np.column_stack([np.interp(t, day.real_loads.time_s, day.real_loads.values[:, j])
                              for j in range(len(day.real_loads.names))])
    U_real = real_prom.layout().inputs(list(day.real_loads.names), values, "real machine")
    poses = trace_step_weights(grid_of(real_prom), ts, P, t)
    Y_real, _ = integrate_along(real_prom, t, U_real, positions, weights=poses)  # its pose history
    added = drift_along(real_prom, Y_real, positions) - _tcp_um(real_prom, Y_real)
    log.info("real machine along the path: its %s pose-aware model, position-dependent part up to %.1f µm",
             "own" if own else "models'", np.abs(added).max())
    return PathTruth(dict(models.pose_mm), t, day.truth, real_prom, Y_real, positions, added, own, poses)


def _along_path(out: Path, models: Models, day: _Day, preds: dict, runs: dict, path: PathTruth) -> dict:
    """Judge the strategies at the trace's commanded positions against the real machine's drift there.

    (:class:`PathTruth`.) A daemon run that wrote support-point tables (a pose-aware structure model) is judged by
    its tables evaluated at the commanded position of every time (what the control interpolates), beside its
    offsets at the model's pose (``<strategy> at one pose``); ``ROM direct along the path`` is the models'
    pose-aware model on the models' loads at the path's pose.
    """
    from hybridcomp.rom.poses import drift_along, grid_of, integrate_along

    prom, machine, t, positions = models.pose_rom, models.machine, day.t, path.positions
    truth_path = day.truth + path.added
    poses = path.poses  # where the trace's machine was (the same support poses)
    if grid_of(prom) != grid_of(path.rom):
        poses = trace_step_weights(grid_of(prom), *trace_samples(machine, day.controller), t)
    Y, _ = integrate_along(prom, t, prom.layout().inputs(day.loads.names, day.loads.values, "loads"), positions,
                           weights=poses)
    path_preds = {}
    for k, p in preds.items():
        if k == BOUND:
            continue
        strategy = next((s for s, name in NAMES.items() if name == k), None)
        tables = runs.get(strategy, {}).get("tables") if strategy else None
        if tables:
            path_preds[f"{k} at one pose"] = p
            path_preds[k] = tables_along(tables, t, positions)
        else:
            path_preds[k] = p
    path_preds[PATH_STRATEGY] = drift_along(prom, Y, positions)
    m = {k: drift_metrics(t, truth_path - p) for k, p in path_preds.items()}
    # at the model's pose as the part sees it there: the real machine's structure AND its drives at the model's axis
    # positions, against what a control applies there (the tables at that pose). The one-pose figures judge the
    # structure alone, while a volumetric daemon's probes at the pose see the drives too
    p0 = np.array([[float(models.pose_mm[a.name]) for a in machine.axes]])
    truth_p0 = day.truth + drift_along(path.rom, path.Y, p0) - _tcp_um(path.rom, path.Y)
    for strategy, r in runs.items():
        if r.get("tables"):
            m[NAMES[strategy]]["largest_step_um"] = r["table_largest_step_um"]
            pred = tables_along(r["tables"], t, np.repeat(p0, t.size, axis=0))
            m[f"{NAMES[strategy]} {AT_POSE_WITH_DRIVES}"] = drift_metrics(t, truth_p0 - pred)
    (out / "table_along_path.md").write_text(metrics_table(m) + "\n")
    _write_residuals(out / "residuals_along_path.csv", t, truth_path, path_preds,
                     {f"{a.name}_mm": positions[:, i] for i, a in enumerate(machine.axes)})
    return {
        "rms_3d_um": {k: v["3d"]["rms_um"] for k, v in m.items()},
        "p2p_3d_um": {k: v["3d"]["p2p_um"] for k, v in m.items()},
        "position_dependent_um": {d: float(np.ptp(path.added[:, j])) for j, d in enumerate(DIRS)},
        "positions_mm": {a.name: [float(positions[:, i].min()), float(positions[:, i].max())]
                         for i, a in enumerate(machine.axes)},
        "truth": "the real machine's own pose-aware model" if path.own else "the models' pose-aware model (the "
                 "real machine is the model)",
        "largest_table_step_um": {NAMES[s]: r["table_largest_step_um"] for s, r in runs.items() if r.get("tables")},
        "drive_gains": {NAMES[s]: r["drive_gains"] for s, r in runs.items() if r.get("drive_gains") is not None},
        "nut_gains": {NAMES[s]: r["nut_gains"] for s, r in runs.items() if r.get("nut_gains") is not None},
        "metrics": m,
    }


def drive_diagnosis(models: Models, loads, trace: Path, probe_noise_um: float) -> dict:
    """The feed drives' diagnosis from the probing cycles of the monitor's trace (``along_path``).

    :mod:`hybridcomp.diagnose.drives` on the probes the cycles took at the star of poses, against the models'
    pose-aware model on the models' loads: which drive effect the models lack, named with its parameter (the
    position-dependent disturbances, ``POSITION_DEPENDENT``), or none.  Returns its summary dictionary.
    """
    from hybridcomp.diagnose.drives import diagnose_drives, drive_candidates, read_probes

    probes = read_probes(trace, models.machine)
    t = loads.time_s
    probes = probes.subset((probes.time_s >= t[0]) & (probes.time_s <= t[-1]))
    if probes.n == 0:
        return {"message": "no probe within the models' loads: no drive diagnosed", "named": [], "not_drives": [],
                "fits": [], "probes": 0}
    cands, predicted = drive_candidates(models.machine, models.pose_rom, loads, probes)
    d = diagnose_drives(probes, cands, predicted, noise_um=probe_noise_um)
    log.info("feed drives: %s", d.message)
    return d.as_dict()


def _tcp_um(rom, Y: np.ndarray) -> np.ndarray:
    """The TCP drift at the model's pose [µm] (nt × 3) of a reduced model's outputs ``Y``."""
    return rom.output_layout().take(Y, "drift") * 1e6


def real_pose_model(real_model, order: int | None = None):
    """The real machine's own pose-aware structure model: its FE model reduced, then at the support poses."""
    from hybridcomp.rom.machine import reduce_model
    from hybridcomp.rom.poses import reduce_at_poses

    rom = reduce_model(real_model, order=order, keep_basis=True)
    return reduce_at_poses(real_model, rom, "star")


def tables_along(tables: list, t: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """The drift [µm] a control applies at the times ``t`` (the tables as the daemon wrote them).

    The last table written at or before each time, interpolated at that time's commanded position (nt × axes)
    [mm]; zero before the first table.
    """
    from hybridcomp.rom.volumetric import interpolate

    times = np.array([tb.time_s for tb in tables])
    k = np.searchsorted(times, t, side="right") - 1
    out = np.zeros((t.size, 3))
    for j in np.unique(k[k >= 0]):
        rows = k == j
        out[rows] = interpolate(tables[j], positions[rows])
    return out


def _fresh_db(path: Path) -> None:
    for suffix in ("", "-wal", "-shm"):
        Path(str(path) + suffix).unlink(missing_ok=True)


def _replay(strategy, machine_name, db_path, rom_path, trace, pose, pkey, machine, rom, element_size_mm, overrides):
    """One daemon run on the replay: offsets, activations, generations, the largest step, the events."""
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.config import parse_config
    from hybridcomp.monitor.daemon import Monitor, Regenerator, run_monitor
    from hybridcomp.monitor.sinks import MemorySink
    from hybridcomp.monitor.sources import ReplaySource
    from hybridcomp.monitor.store import MonitorStore

    db_path, rom_path, trace = Path(db_path).resolve(), Path(rom_path).resolve(), Path(trace).resolve()
    data = {
        "monitor": {"machine": machine_name, "database": str(db_path), "rom": str(rom_path), "pose_mm": dict(pose)},
        "compensation": {"strategy": strategy},
        "source": {"kind": "replay", "path": str(trace), "speed": 0},
        "sink": {"kind": "none"},
        "regeneration": {"enabled": True, "timeout_s": 1800.0, "element_size_mm": element_size_mm},
    }
    for sec, kv in (overrides or {}).items():
        data.setdefault(sec, {}).update({k: v for k, v in kv.items()
                                         if not (sec == "compensation" and k == "dataonly_model" and strategy != "dataonly")})
    cfg = parse_config(data, f"scenario ({strategy})", db_path.parent)
    db = CDDatabase(db_path)
    try:
        setup = max((e.id for e in MonitorStore(db).events()), default=0)  # the default set's activation is the setup's
        mon = Monitor(cfg, machine, rom, db, pkey)
        sink = MemorySink()
        asyncio.run(run_monitor(cfg, mon, ReplaySource(trace, machine, 0.0), sink,
                                regenerator=Regenerator(cfg.regeneration.job, cfg.regeneration.timeout_s),
                                await_regeneration=True))
        ev = [{"kind": e.kind, "machine_time_s": e.machine_time_s, **_event_brief(e)} for e in MonitorStore(db).events()
              if e.id > setup and (e.kind in ("activation", "generation", "observer", "probe", "sensor")
                                   or (e.kind == "decision" and e.payload["action"] != "keep"))]
    finally:
        db.close()
    # the offsets at the model's pose (a pose-aware run writes them at the commanded position, and its tables)
    off = np.array([r.pose_um if r.pose_um is not None else (r.dx_um, r.dy_um, r.dz_um) for r in sink.rows], float)
    tables = [r.table for r in sink.rows if r.table is not None]
    return {"time_s": np.array([r.time_s for r in sink.rows]), "offsets_um": off, "events": ev,
            "activations": sum(1 for e in ev if e["kind"] == "activation"),
            "generations": sum(1 for e in ev if e["kind"] == "generation" and e.get("status") == "finished"),
            "largest_step_um": largest_step_um(off), "tables": tables,
            "drive_gains": None if mon.gains is None else {a: float(g) for a, g in zip(mon.gains.axes, mon.gains.g)},
            "nut_gains": None if mon.gains is None or mon.gains.h is None else {
                a: float(h) for a, h in zip(mon.gains.axes, mon.gains.h)},
            "table_largest_step_um": table_largest_step_um(tables) if tables else None}


def table_largest_step_um(tables: list) -> float:
    """The largest change of any entry of the support-point tables from one cycle to the next [µm]."""
    def entries(tb) -> np.ndarray:  # the structure at the grid points, each drive's error over its axis
        return np.concatenate([np.ravel(tb.structure_um)] + [np.ravel(f[2]) for f in tb.feedback_um])

    E = np.array([entries(tb) for tb in tables])
    return float(np.abs(np.diff(E, axis=0)).max()) if len(E) > 1 else 0.0


def _event_brief(e) -> dict:
    p = e.payload
    if e.kind == "activation":
        return {"ids": p.get("ids"), "reason": p.get("reason")}
    if e.kind == "generation":
        return {"status": p.get("status"), "ids": p.get("ids"), "error": p.get("error"), "wall_s": p.get("wall_s"),
                "notes": p.get("notes")}
    if e.kind in ("observer", "probe", "sensor"):
        return dict(p)
    return {"action": p.get("action"), "reason": p.get("reason"), "error_um": p.get("error_um"),
            "delta_T_K": p.get("delta_T_K")}


def _write_trace(src: Path, dst: Path, rate_hz: float, t_end: float = math.inf, fe=None, sensor_names=(),
                 noise_K: float = 0.0, rng=None, fault=None, probe_every_h=None, probe_noise_um: float = 0.3,
                 probe_cycle=None) -> dict:
    """Every sample of ``src`` on the ``rate_hz`` grid up to ``t_end`` [s], with what the real machine measures.

    With ``fe`` = (times, sensors, drift) of the real machine: the sensors it measures (noise, fault) and, every
    ``probe_every_h``, a probed drift: at the model's pose, or with ``probe_cycle`` = (poses (m × axes) [mm],
    truth(t, positions) → drift [µm], the position columns) at each of those poses on ``m`` consecutive samples,
    the samples' commanded positions set to them (the probing cycle moves the axes).

    Returns the measured sensors at the samples and their low-pass (the daemon's filter), per sample time.
    """
    with open_text(src, ScenarioFileError, "trace") as fi:
        header = fi.readline().strip().split(",")
        ti = header.index("time_s")
        rows, next_t = [], -math.inf
        for line in fi:
            f = line.strip().split(",")
            tt = float(f[ti])
            if tt > t_end + 1e-9:
                break
            if tt + 1e-9 < next_t:
                continue
            next_t = tt + 1.0 / rate_hz
            rows.append((tt, f))
    if fe is None:
        with dst.open("w") as fo:
            fo.write(",".join(header) + "\n")
            fo.writelines(",".join(f) + "\n" for _, f in rows)
        return {}
    times = np.array([r[0] for r in rows])
    t_fe, T_fe, D_fe = fe
    T = np.column_stack([np.interp(times, t_fe, T_fe[:, j]) for j in range(T_fe.shape[1])])
    M = T + rng.normal(0.0, noise_K, T.shape) if noise_K > 0 else T.copy()
    if fault is not None:
        name, from_h, kind = fault
        j = list(sensor_names).index(name)
        k0 = int(np.searchsorted(times, from_h * 3600.0))
        M[k0:, j] = M[k0, j] if kind == "stuck" else math.nan
    P = np.full((len(times), 3), math.nan)
    if probe_every_h:
        D = np.column_stack([np.interp(times, t_fe, D_fe[:, j]) for j in range(3)])
        for k in np.unique(np.searchsorted(times, np.arange(times[0], times[-1], probe_every_h * 3600.0))):
            if probe_cycle is None:
                P[k] = D[k] + rng.normal(0.0, probe_noise_um, 3)
                continue
            poses, truth, columns = probe_cycle
            kk = k
            for j, pose in enumerate(probing_path(poses)):
                for _ in range(PROBE_HOLD_SAMPLES):  # the axes stand at the pose for a few samples
                    if kk >= len(times):
                        break
                    f = rows[kk][1]
                    for c, v in zip(columns, pose):
                        f[header.index(c)] = f"{v:g}"
                    kk += 1
                if (j == 0 or j % 2 == 1) and kk - 1 < len(times):  # a touch at each pose of the star, not the returns
                    P[kk - 1] = truth(times[kk - 1], np.asarray(pose, float)[None, :])[0] + rng.normal(
                        0.0, probe_noise_um, 3)
    names = [temperature_column(n) for n in sensor_names] + (list(PROBE_COLUMNS) if probe_every_h else [])
    with dst.open("w") as fo:
        fo.write(",".join(header + names) + "\n")
        for (_, f), m, p in zip(rows, M, P):
            probe = [("" if math.isnan(v) else f"{v:.4f}") for v in p] if probe_every_h else []
            fo.write(",".join(f + [("" if math.isnan(v) else f"{v:.4f}") for v in m] + probe) + "\n")
    from hybridcomp.monitor.config import MonitorConfig

    return {"time_s": times, "degC": M, "filtered_degC": low_pass(times, M, MonitorConfig.sensor_filter_s)}


#: samples the axes stand at each pose of a probing cycle (at 1 Hz: the moves between poses stay within the feeds)
PROBE_HOLD_SAMPLES = 3


def probing_path(poses: np.ndarray) -> list:
    """The poses a probing cycle visits: the star's first pose, then each other pose and back to the first.

    Every move goes between the model's pose and one axis near a travel end, half the travel at most.  The first
    entry and the odd ones are the star's poses (each touched once); the other even ones are the returns.
    """
    out = [poses[0]]
    for p in poses[1:]:
        out += [p, poses[0]]
    return out


def probe_poses(machine, pose_mm: dict) -> np.ndarray:
    """The poses of a probing cycle over the workspace (m × axes) [mm], a star like the support poses'.

    The model's pose, then each axis near its travel ends (5 % of the travel in) with the others at the model's pose.
    """
    base = np.array([float(pose_mm[a.name]) for a in machine.axes])
    out = [base]
    for i, a in enumerate(machine.axes):
        lo, hi = a.travel_mm
        for v in (lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo)):
            p = base.copy()
            p[i] = v
            out.append(p)
    return np.array(out)


def at_times(times: np.ndarray, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows of ``X`` (at ``times``) at the times ``t``: the last sample at or before each."""
    k = np.clip(np.searchsorted(times, np.asarray(t) + 1e-9, side="right") - 1, 0, len(times) - 1)
    return X[k]


def _write_recorded(trace: Path, dst: Path, res, sensor_names) -> None:
    """The monitor's trace (without probe columns) plus the real machine's drift: a measuring campaign's file."""
    with open_text(trace, ScenarioFileError, "trace") as fi, dst.open("w") as fo:
        header = fi.readline().strip().split(",")
        keep = [i for i, h in enumerate(header) if h not in PROBE_COLUMNS]
        ti = header.index("time_s")
        fo.write(",".join([header[i] for i in keep] + list(DIRS)) + "\n")
        lines = [line.strip().split(",") for line in fi]
        times = np.array([float(f[ti]) for f in lines])
        D = np.column_stack([np.interp(times, res.time_s, res.drift_um[:, j]) for j in range(3)])
        for f, d in zip(lines, D):
            fo.write(",".join([f[i] for i in keep] + [f"{v:.4f}" for v in d]) + "\n")


def _plot(path: Path, t, truth, preds, events, title: str):
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
            if name in ("no compensation", BOUND):
                continue
            ax.plot(h, truth[:, j] - p[:, j], label=name, lw=1.3 if name == "hybrid monitor" else 0.9)
        ax.set_ylabel(f"residual {d.replace('_um', '')} [µm]")
        ax.grid(alpha=0.3)
        for e in events:
            if e["kind"] == "activation" and e["machine_time_s"]:
                ax.axvline(e["machine_time_s"] / 3600.0, color="k", lw=0.5, alpha=0.4)
    axes[0].legend(ncol=3, fontsize=8)
    axes[-1].set_xlabel("time [h] (vertical lines: CD set activations by the hybrid monitor)")
    fig.suptitle(f"job-shop day on the FE real machine — {title}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
