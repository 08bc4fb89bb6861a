"""The regeneration job: a new CD set for the states ahead, written to the database for the daemon to activate.

The daemon runs a job in a worker process (``daemon.Regenerator``) with a timeout and activates the set the
job returns, so a job that fails, hangs or dies never touches the active set. A job is any importable
function ``job(request: dict) -> {"ids": {"X": id, "Y": id, "Z": id}, "load_case": str}`` named
``"module:function"`` in the configuration; the request is the JSON form of :class:`RegenerationRequest`
(plain data: it crosses a process boundary and is stored in the database so that a restart can resubmit it).

:func:`default_job` trains the CDs on the structure model as the observer has corrected it: the estimated
history of the machine (the sensors as measured, the drift as estimated) and forecasts from its estimated
state (the current load continued, a cool-down, the history's mean and its busiest load, and each drive
alone), so that the set covers the states ahead; at the sensors' current values it continues the offsets
being written (an anchor of the fit) whenever its own fit is within ``bump_um`` of them. :func:`fe_job` is
the classic generator: the recent load history run on the FE model.

:func:`grid_job` generates a CD grid (one CD set per support point) for a daemon whose structure model knows one
pose: the same request with a ``grid`` entry naming a pose-aware model of the machine (``compensation.grid_rom``);
the corrected load history and the forecasts run through that model at every support point, one set fitted per
point, the grid stored for the daemon to activate.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import asdict, dataclass, fields

import numpy as np

from hybridcomp.models.layout import temperature_column

log = logging.getLogger(__name__)

# a CD of the default job: up to six sensors chosen by BIC, one 1-D table of four support points each (an
# additive CD: a full grid over several sensors extrapolates wildly where they do not move together)
FIT = {"n_support": 4, "select": "bic", "max_inputs": 6, "max_full_dims": 1, "min_target_range_um": 1.0, "min_range_K": 1.0}
FORECAST_STEP_S = 300.0
FORECAST_WEIGHT = 3.0  # a forecast row against a history row: the set is for the states ahead
BASIC_FACTOR = 0.6  # each drive alone at this load factor, as a forecast scenario

N_SUPPORT = 4  # FE job: support points per input; a few hours of history fill a 4 × 4 × 4 grid
MAX_INPUTS = 3  # FE job: at most this many sensors (chosen by BIC)
# The FE job runs the recent load history on FE as it was measured and with the air around the machine shifted,
# so that the CD learns how the drift follows the sensors when the air differs from what the histogram knows
# (a warmer enclosure, a draught): (zones: "workspace" | "all", offset [K]).
AIR_VARIANTS_K = (("all", 0.0), ("workspace", 2.0), ("workspace", -2.0), ("all", 1.5), ("all", -1.5))
GRID_JOB = "hybridcomp.monitor.regeneration:grid_job"  # the job of a CD grid's request
_MODELS: dict = {}  # models built in this worker process, one per kind (:func:`_cached`)


@dataclass(frozen=True)
class RegenerationRequest:
    """What a generation job needs (plain data).

    Attributes
    ----------
    machine : machine name or file
    pose_key, pose_mm : the pose of the CDs (database key, axis positions [mm])
    database : CD database path or URL
    machine_time_s : machine time of the decision [s]
    t_reference_degC : the corrected structure model's sensor temperatures at the decision [°C]
    signature : load-case signature of the last monitoring interval (or None)
    rom : the structure model's file
    observer : the observer's settings (:class:`~hybridcomp.rom.observer.ObserverSettings` fields)
    observer_x : the observer's estimate (augmented mean) at the decision
    history_time_s : times of the history rows [s]
    history_degC : the sensors as measured (low-pass filtered; the estimate where a sensor was degraded) [°C]
    history_drift_um : the drift as the observer estimated it [µm]
    loads_names : model input names (``*_W`` powers, ``*_degC`` zone air)
    loads_time_s : end times of the history's load rows [s]
    loads_inputs : mean model inputs over each of them (powers [W], air rises over the reference [K])
    anchor_degC : the sensors the CDs read now [°C]
    anchor_um : the offsets being written now (``dx_um`` ...) [µm]
    forecast_h : forecast horizon [h]
    bump_um : continue the offsets exactly when the set's own fit is within this of them [µm]
    reference_temperature_degC : the model's reference temperature [°C]
    element_size_mm : FE element size for :func:`fe_job` [mm]
    """

    machine: str
    pose_key: str
    pose_mm: dict
    database: str
    machine_time_s: float
    t_reference_degC: dict
    signature: list | None
    rom: str
    observer: dict
    observer_x: list
    history_time_s: list
    history_degC: list
    history_drift_um: list
    loads_names: list
    loads_time_s: list
    loads_inputs: list
    anchor_degC: dict
    anchor_um: dict
    forecast_h: float
    bump_um: float
    reference_temperature_degC: float
    element_size_mm: float

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> RegenerationRequest:
        """The request of a dict, every field present and no other."""
        names = {f.name for f in fields(RegenerationRequest)}
        unknown, missing = set(d) - names, names - set(d)
        if unknown or missing:
            raise ValueError(f"regeneration request: unknown field(s) {sorted(unknown)}, missing {sorted(missing)}")
        return RegenerationRequest(**d)


def request_loads(req: RegenerationRequest, dt_s: float = 60.0):
    """The request's load history as a ``fem.loads.Loads`` on a ``dt_s`` grid (°C air).

    Each history row holds the mean inputs over the increment that ends at its
    time; the grid repeats them over that increment (piecewise constant), the
    first grid row is the start of the first increment with its inputs (a
    steady start).
    """
    from hybridcomp.fem.loads import Loads

    t = np.asarray(req.loads_time_s, float)
    U = np.asarray(req.loads_inputs, float)
    if t.size < 1 or U.shape != (t.size, len(req.loads_names)):
        raise ValueError(f"regeneration request at {req.machine_time_s} s has no usable load history "
                         f"({t.size} times, inputs of shape {U.shape})")
    start = t[0] - (t[1] - t[0] if t.size > 1 else 300.0)
    V = U.copy()
    for j, n in enumerate(req.loads_names):
        if n.endswith("_degC"):
            V[:, j] += req.reference_temperature_degC
    grid = np.arange(start, t[-1], dt_s)
    grid = np.append(grid, t[-1]) if t[-1] - grid[-1] > 1e-9 else grid
    k = np.clip(np.searchsorted(t, grid, side="left"), 0, t.size - 1)  # the increment (t[k-1], t[k]] holding τ
    return Loads(grid, V[k], tuple(req.loads_names))


def forecast_scenarios(machine, loads_names, loads_inputs, horizon_h: float) -> dict[str, np.ndarray]:
    """Inputs of the forecast scenarios, each held over ``horizon_h`` hours in ``FORECAST_STEP_S`` rows.

    From the history's load rows (model inputs, the last one the most recent): the last hour continued, a
    cool-down (no heat, the air as now), the history's mean and its busiest load (per input maximum), and each
    drive alone at ``BASIC_FACTOR`` (the basic load cases), all with the air as now.
    """
    U = np.asarray(loads_inputs, float)
    layout = machine.layout()
    if U.ndim != 2 or U.shape[1] != layout.n_inputs or tuple(loads_names) != layout.columns:
        raise ValueError(f"forecast scenarios need load rows over machine {machine.name!r}'s {layout.n_inputs} inputs, "
                         f"got {U.shape} over {len(loads_names)} names")
    nh = len(layout.heat_inputs)
    n = max(1, int(round(horizon_h * 3600.0 / FORECAST_STEP_S)))
    recent = U[-max(1, int(round(3600.0 / FORECAST_STEP_S))):].mean(axis=0)
    air = recent[nh:]

    def held(heat):
        return np.tile(np.concatenate([heat, air]), (n, 1))

    out = {"load continued": np.tile(recent, (n, 1)), "cool-down": held(np.zeros(nh)),
           "history mean": held(U[:, :nh].mean(axis=0)), "history maximum": held(U[:, :nh].max(axis=0))}
    drives: dict[str, np.ndarray] = {}
    for src in machine.heat_sources:
        driver = src.driver or src.axis
        if driver is None:
            continue
        u = drives.setdefault(driver, np.zeros(nh))
        cols = list(layout.source_columns(src.name))
        u[cols] = machine.source_power_W(src, BASIC_FACTOR) / len(cols)
    out |= {f"{d} alone": held(u) for d, u in drives.items()}
    return out


def training_table(observer, x, req: RegenerationRequest, machine) -> tuple[dict[str, np.ndarray], np.ndarray, dict]:
    """The default job's training data: the history rows and the forecasts from the estimate ``x``.

    Returns the table (``<sensor>_degC`` [°C], ``dx_um`` ... [µm]), the row weights (1 per history row,
    ``FORECAST_WEIGHT`` per forecast row) and the number of rows per part.
    """
    from hybridcomp.models.layout import DRIFT_COLUMNS
    from hybridcomp.rom.observer import ObserverState

    state = ObserverState(req.machine_time_s, np.asarray(x, float), np.zeros((len(x), len(x))))
    T = [np.asarray(req.history_degC, float).reshape(-1, len(observer.sensor_names))]
    D = [np.asarray(req.history_drift_um, float).reshape(-1, 3)]
    w = [np.ones(len(T[0]))]
    parts = {"history": len(T[0])}
    for name, U in forecast_scenarios(machine, req.loads_names, req.loads_inputs, req.forecast_h).items():
        Tf, Df = observer.forecast(state, U, FORECAST_STEP_S)
        T.append(Tf)
        D.append(Df)
        w.append(np.full(len(Tf), FORECAST_WEIGHT))
        parts[name] = len(Tf)
    T, D = np.vstack(T), np.vstack(D)
    keep = np.all(np.isfinite(T), axis=1) & np.all(np.isfinite(D), axis=1)
    table = {temperature_column(s): T[keep, j] for j, s in enumerate(observer.sensor_names)}
    table |= {c: D[keep, j] for j, c in enumerate(DRIFT_COLUMNS)}
    return table, np.concatenate(w)[keep], parts


def _cached(kind: str, key: tuple, build):
    """The model of ``kind`` under ``key`` built in this worker process (the worker lives on: built once).

    One model per kind is kept: a new key of a kind replaces the former one, and models of other kinds stay (a
    grid job needs the one-pose model and the pose-aware one at once).
    """
    if (kind, key) not in _MODELS:
        for k in [k for k in _MODELS if k[0] == kind]:
            del _MODELS[k]
        _MODELS[(kind, key)] = build()
    return _MODELS[(kind, key)]


def _rom(path: str, machine):
    from hybridcomp.rom import load_rom

    def build():
        rom = load_rom(path, machine)
        if rom.meta.get("poses"):  # the daemon's observer runs on the model pose's block: so does the job
            from hybridcomp.rom.poses import model_pose_block

            rom = model_pose_block(rom)
        return rom

    return _cached("rom", (path, machine.sha256), build)


def default_job(request: dict) -> dict:
    """The corrected structure model's history and forecasts → three CDs → database (the daemon activates them).

    Each CD: up to six sensors by BIC, an additive table (``FIT``); a drift that spans less than 1 µm gets a
    constant CD. The fit is anchored at the sensors' current values to the offsets being written when its own
    value there is within ``bump_um`` of them (bumpless by construction); otherwise the daemon's blend takes
    the difference out gradually. The new set's T_reference is the corrected model's sensors at the decision.
    """
    from hybridcomp.chardiag.cd import DIRECTIONS, TARGETS
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import CDFitError, FitOptions, fit_cd
    from hybridcomp.models import load_machine
    from hybridcomp.rom.observer import ObserverSettings, build_observer

    t0 = time.monotonic()
    req = RegenerationRequest.from_dict(request)
    machine = load_machine(req.machine)
    pose = machine.check_pose(dict(req.pose_mm or {}))
    observer = build_observer(_rom(req.rom, machine), machine, ObserverSettings(**req.observer))
    table, weights, parts = training_table(observer, req.observer_x, req, machine)
    name = f"generated@{req.machine_time_s:.0f}s"
    sig = None if req.signature is None else np.asarray(req.signature, float)
    kw = dict(machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose, load_case=name, signature=sig,
              t_reference_degC=req.t_reference_degC, source=name, options=FitOptions(**FIT), weights=weights)
    anchor_T = {temperature_column(k): float(v) for k, v in req.anchor_degC.items()}
    cds, notes, at_anchor = {}, {}, {}
    constant = dataclasses.replace(FitOptions(**FIT), min_target_range_um=1e12)  # any range: constant
    for d in DIRECTIONS:
        target = TARGETS[d]
        try:
            cd = fit_cd(table, d, **kw)
        except CDFitError as exc:  # no sensor explains this direction's drift significantly: a constant CD
            log.info("%s: %s; a constant CD", target, exc)
            kw_d = {**kw, "options": constant}
            cd = fit_cd(table, d, **kw_d)
        else:
            kw_d = kw
        own = cd.evaluate_table({k: np.array([v]) for k, v in anchor_T.items()})[0][0]
        jump = float(own - req.anchor_um[target])
        bumpless = abs(jump) <= req.bump_um
        if bumpless:
            cd = fit_cd(table, d, **kw_d, anchor=(anchor_T, float(req.anchor_um[target])))
        cds[d] = cd
        at_anchor[target] = float(cd.evaluate_table({k: np.array([v]) for k, v in anchor_T.items()})[0][0])
        notes[d] = {"inputs": [i.name for i in cd.inputs if i.active], "rms_residual_um": dict(cd.fit)["rms_residual_um"],
                    "own_jump_um": jump, "bumpless": bumpless}
    db = CDDatabase(req.database)
    try:
        ids = {d: int(db.add(cds[d], load_case=name)) for d in DIRECTIONS}
    finally:
        db.close()
    return {"ids": ids, "load_case": name, "wall_s": time.monotonic() - t0, "notes": notes, "rows": parts,
            "at_anchor_um": at_anchor}


def fe_job(request: dict) -> dict:
    """BCs of the recent history → FE training run → three CDs → database (the daemon activates them).

    The classic generator: ``hybridcomp.chardiag.training`` and ``hybridcomp.chardiag.fit`` (``N_SUPPORT``
    support points per input). The load history is run from a steady start as measured and with the air
    shifted (``AIR_VARIANTS_K``), one table. The new CDs' T_reference is the structure model's temperatures at
    the decision. A direction whose drift no sensor explains in the history keeps the active set's CD
    (relabelled; noted in the result). The FE model is built once per worker process.
    """
    from hybridcomp.chardiag.cd import DIRECTIONS
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import CDFitError, FitOptions, fit_cd
    from hybridcomp.chardiag.training import LoadCase, simulate_load_cases
    from hybridcomp.fem.model import build_model
    from hybridcomp.models import load_machine

    t0 = time.monotonic()
    req = RegenerationRequest.from_dict(request)
    machine = load_machine(req.machine)
    loads = request_loads(req)
    name = f"generated@{req.machine_time_s:.0f}s"
    sig = None if req.signature is None else np.asarray(req.signature, float)
    pose = machine.check_pose(dict(req.pose_mm or {}))
    model = _cached("fe", (machine.sha256, tuple(sorted(pose.items())), req.element_size_mm),
                    lambda: build_model(machine, pose, req.element_size_mm))
    cases = {}
    for zones, dK in AIR_VARIANTS_K:
        V = loads.values.copy()
        for z in machine.zones:
            col = temperature_column(z.name)
            if dK and (zones == "all" or z.air == zones):
                if col in loads.names:
                    V[:, loads.names.index(col)] += dK
        variant = f"{name}{'' if not dK else f' {zones} {dK:+g} K'}"
        cases[variant] = LoadCase(variant, type(loads)(loads.time_s, V, loads.names), None, sig)
    data = simulate_load_cases(machine, cases, pose_mm=pose, element_size_mm=req.element_size_mm, model=model)
    kw = dict(machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose, load_case=name, signature=sig,
              t_reference_degC=req.t_reference_degC, source=name)
    db = CDDatabase(req.database)
    try:
        cds, notes = {}, {}
        for d in DIRECTIONS:
            try:
                cds[d] = fit_cd(data.columns, d, options=FitOptions(n_support=N_SUPPORT, select="bic",
                                                                   max_inputs=MAX_INPUTS), **kw)
            except CDFitError as exc:
                # no sensor explains this direction's drift in the history (e.g. a direction that hardly
                # moves): keep the active set's CD for it, labelled with the new load case
                active = db.active_set(machine.name, req.pose_key)
                if active is None:
                    raise
                notes[d] = f"kept the active CD ({exc})"
                cds[d] = dataclasses.replace(active.cds[d], load_case=name, signature=np.asarray(
                    sig if sig is not None else active.cds[d].signature, float),
                    t_reference_degC=tuple((k, float(v)) for k, v in req.t_reference_degC.items()))
        ids = {d: int(db.add(cds[d], load_case=name)) for d in DIRECTIONS}
    finally:
        db.close()
    return {"ids": ids, "load_case": name, "wall_s": time.monotonic() - t0, "notes": notes}


def grid_cases(observer, x, req: RegenerationRequest, machine) -> tuple[dict, float]:
    """A CD grid's load cases: the request's load history and each forecast scenario after it, corrected.

    The inputs as the observer's estimate ``x`` corrects them (``corrected_inputs``: its power scales and air offsets
    at the decision).

    The history (:func:`request_loads` on ``FORECAST_STEP_S`` rows) is case ``history``; each scenario of
    :func:`forecast_scenarios` is a case of the history followed by its rows over ``forecast_h`` (the history is its
    run-in: a model starts each case from the steady state of its first row).  Returns the cases
    (:class:`~hybridcomp.chardiag.training.LoadCase` by name, air in °C) and the history's end [s]: the rows of a
    forecast case up to it are the run-in, not training rows.
    """
    from hybridcomp.chardiag.training import LoadCase
    from hybridcomp.fem.loads import Loads
    from hybridcomp.rom.observer import ObserverState

    state = ObserverState(req.machine_time_s, np.asarray(x, float), np.zeros((len(x), len(x))))
    hist = request_loads(req, FORECAST_STEP_S)
    air = np.array([n.endswith("_degC") for n in hist.names])
    ref = req.reference_temperature_degC

    def corrected(V: np.ndarray, in_degC: bool) -> np.ndarray:
        U = V - ref * air if in_degC else np.array(V, float)
        return np.array([observer.corrected_inputs(state, u) for u in U]) + ref * air

    t_end = float(hist.time_s[-1])
    H = corrected(hist.values, True)
    cases = {"history": LoadCase("history", Loads(hist.time_s, H, hist.names))}
    for name, U in forecast_scenarios(machine, req.loads_names, req.loads_inputs, req.forecast_h).items():
        t = t_end + FORECAST_STEP_S * np.arange(1, len(U) + 1)
        cases[name] = LoadCase(name, Loads(np.concatenate([hist.time_s, t]), np.vstack([H, corrected(U, False)]),
                                           hist.names))
    return cases, t_end


def _pose_rom(path: str, machine):
    from hybridcomp.rom import load_rom

    def build():
        rom = load_rom(path, machine)
        if not rom.meta.get("poses"):
            raise ValueError(f"{path}: a reduced model of one pose; a CD grid needs a pose-aware one")
        return rom

    return _cached("pose rom", (path, machine.sha256), build)


def grid_job(request: dict) -> dict:
    """The corrected history and forecasts on the pose-aware model at every support point → a CD grid → database.

    The request is a :class:`RegenerationRequest`'s with ``grid`` = {``rom``: the pose-aware model's file,
    ``points``: support points per axis, ``job``}.  The cases of :func:`grid_cases` run through the pose-aware model
    (:func:`hybridcomp.chardiag.grid.grid_training_data` on its default grid of ``points`` per axis); a point's
    training rows are the history (weight 1) and the forecasts after it (weight ``FORECAST_WEIGHT``); one CD set per
    point (:func:`hybridcomp.chardiag.grid.fit_grid`, ``FIT``; a direction no sensor explains: a constant CD, as
    :func:`default_job`), its reference temperatures the corrected model's
    sensors at the decision.  Returns ``{"grid_id", "load_case", "wall_s", "notes", "rows"}``; the daemon activates
    the grid (the job never touches the active grid).
    """
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import FitOptions
    from hybridcomp.chardiag.grid import GridTrainingData, fit_grid, grid_residuals, grid_training_data
    from hybridcomp.chardiag.training import TrainingData
    from hybridcomp.models import load_machine
    from hybridcomp.rom.observer import ObserverSettings, build_observer

    t0 = time.monotonic()
    spec = dict(request["grid"])
    req = RegenerationRequest.from_dict({k: v for k, v in request.items() if k != "grid"})
    machine = load_machine(req.machine)
    observer = build_observer(_rom(req.rom, machine), machine, ObserverSettings(**req.observer))
    cases, t_end = grid_cases(observer, req.observer_x, req, machine)
    prom = _pose_rom(str(spec["rom"]), machine)
    data = grid_training_data(prom, cases, points=int(spec["points"]))
    tables = []
    for td in data.tables:  # the forecasts' run-in rows are no training rows
        keep = (td.load_case == "history") | (td.columns["time_s"] > t_end + 1e-9)
        tables.append(TrainingData(td.load_case[keep], {k: v[keep] for k, v in td.columns.items()}, td.signatures))
    data = GridTrainingData(data.grid, tuple(tables))
    rows = tables[0].load_case
    weights = np.where(rows == "history", 1.0, FORECAST_WEIGHT)
    name = f"generated grid@{req.machine_time_s:.0f}s"
    grid = fit_grid(data, machine=machine.name, machine_sha256=machine.sha256, options=FitOptions(**FIT),
                    source=name, load_case=name, t_reference_degC=req.t_reference_degC, weights=weights,
                    constant_when_unexplained=True)
    rms = grid_residuals(grid, data)
    db = CDDatabase(req.database)
    try:
        gid = int(db.add_grid(grid, load_case=name))
    finally:
        db.close()
    return {"grid_id": gid, "load_case": name, "wall_s": time.monotonic() - t0,
            "rows": {c: int(np.sum(rows == c)) for c in dict.fromkeys(rows.tolist())},
            "notes": {"points": grid.grid.n_points, "pose_rom": str(spec["rom"]),
                      "max_rms_residual_um": dict(zip(("X", "Y", "Z"), (float(v) for v in rms.max(axis=0))))}}
