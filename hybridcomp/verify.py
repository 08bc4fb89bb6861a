"""Virtual verification of the compensation: volumetric calibrations, the ambient during them, a machined part.

A machine-tool builder signs off a thermal compensation on measurements, not on a model's residual.  This module
simulates them on one job-shop day of a real machine (:func:`hybridcomp.scenario.run_scenario` with
``along_path``: the real machine's drift at any pose and time, :class:`~hybridcomp.scenario.PathTruth`, and the
daemon's compensation over the day) and runs three studies:

* **volumetric calibrations** (:func:`calibrate`): a :class:`CalibrationPlan` (a grid of poses measured one after
  the other, ``seconds_per_point`` each, noise ``noise_um`` per direction, as a laser tracker or a touch probe on an
  artefact gives them) executed at several thermal states of the day.  The volumetric model of
  :mod:`hybridcomp.chardiag.thermal_map` (ISO 230-1 error functions whose coefficients follow the sensors) is
  identified on every other calibration and judged on the ones between, which no choice saw, beside the
  daemon's support-point tables at the same times and poses (:func:`volumetric_study`);
* **the ambient during verification** (:func:`ambient_study`): a calibration taken with the workshop air
  ``ambient_K`` away from working conditions adds the machine's steady response to that air (its structure, the
  drives' scales and screws against their carriers) and the instrument's reading offset: the table top growing
  between the instrument's reference and the point under the tool, less the instrument's own growth (an
  artefact's; a laser tracker's air-compensated lengths do not grow), :func:`reading_offset_um`.  Compensation
  functions identified from it miss the machine at working temperature by that much; the correction takes the
  measured air rise times the structure model's ambient response and the reading offset off the measurements
  before identifying;
* **a machined part** (:func:`machining_study`, in the spirit of ISO 10791-10): bores cut one at a time at
  intervals over the day at several workspace positions; each bore's position deviation and the deviations of
  the distances between neighbouring bores, without compensation, with the daemon's offsets at its one pose
  applied everywhere, and with its support-point table at the bore.

Conventions.  Drift is TCP minus the table point under it [µm], the project's convention; a calibration measures
it.  A static geometric error of the machine adds to every measurement alike and is identified alike (the
identification is linear), so the studies leave it out: what they judge is the thermal part.  At working
temperature an instrument on the table reads the drift itself (the workpiece follows the table point under the
tool, the project's convention); only the soak's uniform growth of the table is added to what it reads.  The part's own
expansion at cutting time is taken out of its measurement (the CMM's job at 20 °C): a bore's deviation is the
machine's drift less the compensation at the bore's time and place.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError

log = logging.getLogger(__name__)

#: the expansion coefficient of a steel artefact [1/K]
STEEL_ALPHA = 11.5e-6


class VerifyError(HybridcompError, ValueError):
    """A verification setting that cannot be used; the message names the option and the value."""


def _positive(name: str, value, allow_zero: bool = False) -> float:
    v = float(value)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise VerifyError(f"{name} must be a finite number {'≥' if allow_zero else '>'} 0, got {value!r}")
    return v


@dataclass(frozen=True)
class CalibrationPlan:
    """A volumetric calibration: which poses, in which order, how long each takes and how precisely.

    Attributes
    ----------
    levels : positions per axis over its travel, machine order (each ≥ 2); error functions of degree 3 need 4 of a
        tool-side axis and 5 of a table-side axis (:func:`~hybridcomp.chardiag.kinematic.identify`)
    seconds_per_point : time from one measured pose to the next [s]
    noise_um : standard deviation of a measured error per direction [µm]
    margin : share of each axis' travel kept clear at either end (0 measures at the ends)
    """

    levels: tuple[int, ...] = (5, 5, 4)
    seconds_per_point: float = 20.0
    noise_um: float = 1.0
    margin: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "levels", tuple(int(n) for n in self.levels))
        if any(n < 2 for n in self.levels):
            raise VerifyError(f"calibration plan: every axis needs at least 2 levels, got {list(self.levels)}")
        _positive("seconds_per_point", self.seconds_per_point)
        _positive("noise_um", self.noise_um, allow_zero=True)
        if not 0 <= self.margin < 0.5:
            raise VerifyError(f"calibration plan: margin must be in [0, 0.5), got {self.margin!r}")

    def poses_mm(self, travel_mm) -> np.ndarray:
        """The plan's poses in measuring order (m × axes) [mm]: a serpentine, the last axis fastest."""
        travel = [tuple(map(float, t)) for t in travel_mm]
        if len(travel) != len(self.levels):
            raise VerifyError(f"calibration plan: {len(self.levels)} axis levels for {len(travel)} axes")
        axes = [np.linspace(lo + self.margin * (hi - lo), hi - self.margin * (hi - lo), n)
                for (lo, hi), n in zip(travel, self.levels)]
        rows = [[]]
        for lv in axes:  # serpentine: every other pass of an axis runs backwards
            new = []
            for i, r in enumerate(rows):
                new.extend(r + [v] for v in (lv if i % 2 == 0 else lv[::-1]))
            rows = new
        return np.array(rows)

    def duration_s(self) -> float:
        """How long the plan takes [s]."""
        return float(np.prod(self.levels)) * self.seconds_per_point


@dataclass(frozen=True)
class Measured:
    """One simulated calibration: poses, their times [s] and the measured errors (m × 3) [µm]."""

    poses_mm: np.ndarray
    time_s: np.ndarray
    error_um: np.ndarray


def calibrate(drift_at, plan: CalibrationPlan, travel_mm, start_s: float, rng: np.random.Generator) -> Measured:
    """The calibration ``plan`` executed from ``start_s`` on a machine whose drift is ``drift_at(t_s, poses)``.

    ``drift_at`` (a time [s], poses m × axes [mm]) → drift (m × 3) [µm]: e.g. :meth:`PathTruth.at`.  Each pose is
    measured at its own time (the machine keeps warming or cooling through a calibration).  Noise: ``plan.noise_um``
    per direction.
    """
    P = plan.poses_mm(travel_mm)
    t = start_s + plan.seconds_per_point * np.arange(P.shape[0])
    E = np.vstack([drift_at(float(ti), P[i:i + 1]) for i, ti in enumerate(t)])
    if plan.noise_um > 0:
        E = E + rng.normal(0.0, plan.noise_um, E.shape)
    return Measured(P, t, E)


def sensors_between(sensors: dict, start_s: float, end_s: float) -> np.ndarray:
    """The controller's sensor readings averaged over ``[start_s, end_s]`` (one per sensor) [°C]."""
    t, T = np.asarray(sensors["time_s"], float), np.asarray(sensors["degC"], float)
    rows = (t >= start_s) & (t <= end_s)
    if not rows.any():
        k = int(np.clip(np.searchsorted(t, start_s), 0, t.size - 1))
        return T[k]
    return np.nanmean(T[rows], axis=0)


def error_stats(err_um: np.ndarray) -> dict:
    """Max, RMS and 95th percentile of the 3D length of errors (… × 3) [µm]."""
    n = np.linalg.norm(np.asarray(err_um, float).reshape(-1, 3), axis=1)
    return {"max_um": float(n.max()), "rms_um": float(np.sqrt(np.mean(n ** 2))),
            "p95_um": float(np.percentile(n, 95.0))}


# -- the ambient response --------------------------------------------------------------------------------------


def ambient_response_um(prom, poses_mm: np.ndarray, rise_K: float = 1.0) -> np.ndarray:
    """The machine soaked in warmer air: steady drift [µm] (m × 3) at ``poses_mm``, every air zone ``rise_K`` up.

    A pose-aware reduced model with no heat and every air zone ``rise_K`` above the reference: its structure and
    its drives at steady state.
    """
    from hybridcomp.rom.poses import drift_along

    lay = prom.layout()
    u = np.zeros(prom.n_inputs)
    u[len(lay.heat_inputs):len(lay.heat_inputs) + len(lay.zones)] = rise_K
    y = prom.outputs(prom.steady_state(u))
    P = np.atleast_2d(np.asarray(poses_mm, float))
    return drift_along(prom, np.repeat(y[None, :], P.shape[0], axis=0), P)


def reading_offset_um(poses_mm: np.ndarray, chain, table_alpha_per_K: float, instrument_alpha_per_K: float,
                      rise_K: float) -> np.ndarray:
    """What the soak adds to the errors an instrument reads, beyond the drift (m × 3) [µm].

    The instrument stands on the table (a laser tracker's base, an artefact's reference at the workspace's centre)
    and reads the tool tip against it.  The drift is the tool tip against the table point under it; between that
    point and the instrument's reference the table top grows by ``table_alpha_per_K`` · ΔT in its plane (x, y),
    and the instrument reads against its own scale, grown by ``instrument_alpha_per_K`` · ΔT (an artefact; 0 for
    a tracker's air-compensated lengths).  With ``r`` the tool tip's place on the table about the reference
    (:func:`part_point_mm`): ``ΔT (α_table r_xy − α_instrument r)``.
    """
    r = part_point_mm(chain, np.atleast_2d(poses_mm))
    table = r.copy()
    table[:, 2] = 0.0  # the table top grows in its plane; the height above it is air
    return rise_K * (table_alpha_per_K * table - instrument_alpha_per_K * r) * 1e3  # mm · 1/K · K → µm


# -- study 1: the volumetric model against the support-point tables ----------------------------------------------


@dataclass(frozen=True)
class VolumetricOptions:
    """The volumetric-calibration study's settings.

    A calibration every ``every_h`` from ``first_h`` while the day lasts; the thermal map fitted on the
    even-numbered ones (0, 2, …), judged on the odd ones; error functions of ``degree``; inputs by ``criterion``
    (``"bicc"`` or ``"bic"``), at most ``max_inputs`` of the sensors and, with ``lags_h``, of their first-order
    lags of those time constants [h] (an ARX map's inputs: ``T1_lag1h``); judged over a grid of
    ``grid_levels`` per axis.
    """

    plan: CalibrationPlan = CalibrationPlan()
    first_h: float = 0.0
    every_h: float = 1.0
    degree: int = 3
    criterion: str = "bicc"
    max_inputs: int = 3
    grid_levels: tuple[int, ...] = (5, 5, 5)
    lags_h: tuple[float, ...] = ()

    def __post_init__(self):
        _positive("first_h", self.first_h, allow_zero=True)
        _positive("every_h", self.every_h)
        object.__setattr__(self, "lags_h", tuple(float(v) for v in self.lags_h))
        for v in self.lags_h:
            _positive("lags_h", v)
        if self.criterion not in ("bic", "bicc"):
            raise VerifyError(f"criterion must be 'bic' or 'bicc', got {self.criterion!r}")
        if self.every_h * 3600.0 < self.plan.duration_s():
            raise VerifyError(f"a calibration takes {self.plan.duration_s() / 60:g} min "
                              f"({int(np.prod(self.plan.levels))} poses, {self.plan.seconds_per_point:g} s each): "
                              f"calibrations every {self.every_h:g} h would overlap; calibrate less often, on fewer "
                              "poses or faster")

    def starts_s(self, day_end_s: float) -> list[float]:
        """The calibrations' start times within a day that ends at ``day_end_s`` [s]."""
        out, s = [], self.first_h * 3600.0
        while s + self.plan.duration_s() <= day_end_s + 1e-9:
            out.append(s)
            s += self.every_h * 3600.0
        return out


def workspace_grid(travel_mm, levels) -> np.ndarray:
    """A tensor grid over the travel, ends included (m × axes) [mm]: where a verification judges."""
    import itertools

    axes = [np.linspace(float(lo), float(hi), int(n)) for (lo, hi), n in zip(travel_mm, levels)]
    return np.array(list(itertools.product(*axes)))


def with_lags(sensors: dict, sensor_names, lags_h) -> tuple[dict, list[str]]:
    """The readings with each sensor's first-order lags of ``lags_h`` [h] as extra columns, and their names.

    ``T1_lag1h`` is T1 through a first-order low-pass of 1 h (the daemon's filter form), computed over the
    controller's whole record up to each time: what an ARX map of the sensors would take as inputs.
    """
    from hybridcomp.scenario import low_pass

    names = list(sensor_names)
    if not lags_h:
        return sensors, names
    t, T = np.asarray(sensors["time_s"], float), np.asarray(sensors["degC"], float)
    cols = [T] + [low_pass(t, T, h * 3600.0) for h in lags_h]
    names += [f"{n}_lag{h:g}h" for h in lags_h for n in sensor_names]
    return {**sensors, "degC": np.hstack(cols)}, names


def thermal_phase(path, start_s: float, end_s: float, rate_um_per_h: float = 1.0) -> str:
    """The machine's thermal phase over ``[start_s, end_s]``, from its drift at the model's pose.

    ``warming`` or ``cooling`` when the drift's length grows or shrinks faster than ``rate_um_per_h`` [µm/h],
    else ``cold`` within 5 µm of the day's first drift, ``hot`` beyond.
    """
    a = np.array([np.interp(start_s, path.t, path.truth[:, j]) for j in range(3)])
    b = np.array([np.interp(end_s, path.t, path.truth[:, j]) for j in range(3)])
    rate = float(np.linalg.norm(b) - np.linalg.norm(a)) / max((end_s - start_s) / 3600.0, 1e-9)
    if abs(rate) > rate_um_per_h:
        return "warming" if rate > 0 else "cooling"
    return "cold" if np.linalg.norm(b - path.truth[0]) < 5.0 else "hot"


def _check_calibrations(options: VolumetricOptions, day_end_s: float) -> list[float]:
    """The calibrations' start times; refuses a day that holds fewer than 4 (2 to fit, 2 to judge)."""
    starts = options.starts_s(day_end_s)
    if len(starts) < 4:
        raise VerifyError(f"the day ({day_end_s / 3600:g} h) holds {len(starts)} calibrations of "
                          f"{options.plan.duration_s() / 60:g} min every {options.every_h:g} h; the study needs 4 (2 "
                          "to fit, 2 to judge): calibrate more often or take a longer day")
    return starts


@dataclass(frozen=True)
class VolumetricResult:
    """The volumetric study: its ``summary`` (JSON-able), the fitted thermal ``model`` and the ``calibrations``."""

    summary: dict
    model: object
    calibrations: list


def volumetric_study(path, table_at, sensors: dict, sensor_names, chain, options: VolumetricOptions,
                     rng: np.random.Generator) -> VolumetricResult:
    """Calibrations over the day, the thermal volumetric model fitted on half, both compensations on the rest.

    ``path`` gives the real machine's drift (``path.at(t_s, poses)``, ``path.t`` the day's times), ``table_at`` (times
    (n,), poses n × axes) → the drift the support-point tables give there [µm], ``sensors`` the controller's
    readings (``time_s``, ``degC``).  The summary holds the states (time, label, training or held out, thermal
    phase), the fitted model's selected inputs and, per compensation
    (``volumetric model``, ``support-point tables``, and ``identified at the state``: the held-out calibration's
    own error model, what a calibration at that very moment would give), the TCP error's max, RMS and 95th
    percentile over the workspace grid and the held-out states.
    """
    from hybridcomp.chardiag.kinematic import identify, tcp_error_um
    from hybridcomp.chardiag.thermal_map import Calibration, fit_thermal_map, predict_um

    plan = options.plan
    starts = _check_calibrations(options, float(path.t[-1]))
    sensors, sensor_names = with_lags(sensors, sensor_names, options.lags_h)
    cals = []
    for s in starts:
        m = calibrate(path.at, plan, chain.travel_mm, s, rng)
        T = sensors_between(sensors, s, s + plan.duration_s())
        cals.append(Calibration(m.poses_mm, m.error_um, T, s, label=f"{s / 3600:.1f} h"))
    train, held = cals[0::2], cals[1::2]
    model = fit_thermal_map(chain, train, tuple(sensor_names), degree=options.degree, criterion=options.criterion,
                            max_inputs=options.max_inputs)
    G = workspace_grid(chain.travel_mm, options.grid_levels)
    errors = {"volumetric model": [], "support-point tables": [], "identified at the state": []}
    per_state = []
    for c in held:
        t_mid = c.time_s + plan.duration_s() / 2
        truth = path.at(t_mid, G)
        e_vol = truth - predict_um(model, c.sensors_degC, G)
        e_tab = truth - table_at(np.full(G.shape[0], t_mid), G)
        e_own = truth - tcp_error_um(identify(chain, c.poses_mm, c.error_um, options.degree), G)
        for k, e in zip(errors, (e_vol, e_tab, e_own)):
            errors[k].append(e)
        per_state.append({"state": c.label, "time_h": t_mid / 3600.0,
                          **{k: error_stats(e)["max_um"] for k, e in zip(errors, (e_vol, e_tab, e_own))}})
    return VolumetricResult({
        "calibrations": [{"state": c.label, "start_h": c.time_s / 3600.0, "role": "fit" if i % 2 == 0 else "held out",
                          "phase": thermal_phase(path, c.time_s, c.time_s + plan.duration_s())}
                         for i, c in enumerate(cals)],
        "plan": {"levels": list(plan.levels), "points": int(np.prod(plan.levels)),
                 "seconds_per_point": plan.seconds_per_point, "noise_um": plan.noise_um,
                 "duration_min": plan.duration_s() / 60.0},
        "grid_points": int(G.shape[0]),
        "model": {"inputs": list(model.inputs), "components": int(model.components), "states": int(model.n_states),
                  "criterion": model.criterion, "noise_um": float(model.noise_um),
                  "held_out_outside_training_range": sorted({n for c in held for n in model.outside(c.sensors_degC)})},
        "held_out": {k: error_stats(np.vstack(v)) for k, v in errors.items()},
        "per_state": per_state,
    }, model, cals)


# -- study 2: the ambient during verification ---------------------------------------------------------------------


@dataclass(frozen=True)
class AmbientOptions:
    """The ambient study's settings.

    A calibration of ``plan`` (its own noise replaced by each of ``sigmas_um``) at the working state at
    ``state_h`` of the day, taken with the air ``ambient_K`` off the working temperature; the air thermometer
    reads with ``air_noise_K``; artefacts of expansion coefficients ``artefacts`` (name → 1/K; 0 a laser
    tracker's absolute lengths).
    """

    plan: CalibrationPlan = CalibrationPlan()
    state_h: float = 0.0
    ambient_K: float = 3.0
    sigmas_um: tuple[float, ...] = (0.0, 1.0, 3.0)
    air_noise_K: float = 0.05
    degree: int = 3
    artefacts: tuple[tuple[str, float], ...] = (("laser tracker", 0.0), ("steel artefact", STEEL_ALPHA))
    grid_levels: tuple[int, ...] = (5, 5, 5)

    def __post_init__(self):
        _positive("state_h", self.state_h, allow_zero=True)
        if not np.isfinite(self.ambient_K):
            raise VerifyError(f"ambient_K must be finite, got {self.ambient_K!r}")
        for s in self.sigmas_um:
            _positive("sigmas_um", s, allow_zero=True)
        _positive("air_noise_K", self.air_noise_K, allow_zero=True)


def ambient_study(path, real_response, model_response, chain, table_alpha_per_K: float, options: AmbientOptions,
                  seed: int = 0) -> dict:
    """Compensation functions identified with the air off working temperature, with and without its correction.

    The real machine is calibrated at the working state at ``options.state_h`` (``path.at``) with its air
    ``ambient_K`` warmer, which adds ``ambient_K`` times ``real_response(poses)`` (its steady drift per kelvin of
    air, m × 3 [µm/K]: :func:`ambient_response_um` of its own pose-aware model); each artefact reads the errors
    against its own expansion, over the table's (:func:`reading_offset_um`, ``table_alpha_per_K`` the table's
    expansion coefficient).
    The functions (ISO 230-1, :func:`~hybridcomp.chardiag.kinematic.identify`) are judged at working temperature
    on the workspace grid: the compensation error is the real machine's drift there less the functions.  The
    reference is the same calibration taken at working temperature (same noise draw); the correction takes off
    the measured air rise times the models' ambient response (``model_response``, as ``real_response``) and the
    instrument's reading offset.
    Returns rows per artefact and σ: max / RMS of the compensation error uncorrected, corrected and the reference,
    and the corrected functions' largest distance from the reference's.
    """
    from hybridcomp.chardiag.kinematic import identify, tcp_error_um

    o = options
    t_s = o.state_h * 3600.0
    G = workspace_grid(chain.travel_mm, o.grid_levels)
    truth_G = path.at(t_s, G)
    P = o.plan.poses_mm(chain.travel_mm)  # every instrument and noise measures the plan's poses
    state = path.at(t_s, P)  # the machine at rest in its working state through the calibration
    real_per_K, model_per_K = real_response(P), model_response(P)
    rows = []
    for name, alpha in o.artefacts:
        for sigma in o.sigmas_um:
            rng = np.random.default_rng([seed, int(round(sigma * 1000)), int(alpha * 1e9)])
            noise = rng.normal(0.0, sigma, (P.shape[0], 3)) if sigma > 0 else np.zeros((P.shape[0], 3))
            measured_air_K = o.ambient_K + (rng.normal(0.0, o.air_noise_K) if o.air_noise_K > 0 else 0.0)
            added = (o.ambient_K * real_per_K
                     + reading_offset_um(P, chain, table_alpha_per_K, alpha, o.ambient_K))
            correction = (measured_air_K * model_per_K
                          + reading_offset_um(P, chain, table_alpha_per_K, alpha, measured_air_K))
            ref = identify(chain, P, state + noise, o.degree)
            raw = identify(chain, P, state + added + noise, o.degree)
            cor = identify(chain, P, state + added - correction + noise, o.degree)
            e_ref, e_raw, e_cor = (truth_G - tcp_error_um(m, G) for m in (ref, raw, cor))
            rows.append({"artefact": name, "sigma_um": sigma,
                         "uncorrected": error_stats(e_raw), "corrected": error_stats(e_cor),
                         "at working temperature": error_stats(e_ref),
                         "corrected_vs_reference_max_um": error_stats(e_cor - e_ref)["max_um"],
                         "uncorrected_vs_reference_max_um": error_stats(e_raw - e_ref)["max_um"]})
    return {"ambient_K": o.ambient_K, "state_h": o.state_h, "air_noise_K": o.air_noise_K,
            "grid_points": int(G.shape[0]), "rows": rows}


# -- study 3: a machined part -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MachiningOptions:
    """The machined part's settings.

    ``columns`` × ``rows`` bores over ``span`` of the X and Y travel (the other axes at the model's pose), one
    cut every ``every_h`` from ``first_h``, in a serpentine over the plate.
    """

    columns: int = 5
    rows: int = 3
    span: float = 0.8
    first_h: float = 0.5
    every_h: float = 1.0

    def __post_init__(self):
        if int(self.columns) < 2 or int(self.rows) < 1:
            raise VerifyError(f"the part needs at least 2 × 1 bores, got {self.columns} × {self.rows}")
        if not 0 < self.span <= 1:
            raise VerifyError(f"span must be in (0, 1], got {self.span!r}")
        _positive("first_h", self.first_h, allow_zero=True)
        _positive("every_h", self.every_h)


@dataclass(frozen=True)
class Bores:
    """The part's bores: axis positions (n × axes) [mm], the times they are cut [s], their (column, row)."""

    positions_mm: np.ndarray
    time_s: np.ndarray
    place: tuple[tuple[int, int], ...]


def bores_of(options: MachiningOptions, chain, pose_mm: dict, day_end_s: float) -> Bores:
    """Where and when the bores are cut (refuses a part that does not fit in the day)."""
    o = options
    n = int(o.columns) * int(o.rows)
    times = o.first_h * 3600.0 + o.every_h * 3600.0 * np.arange(n)
    if times[-1] > day_end_s + 1e-9:
        raise VerifyError(f"{n} bores every {o.every_h:g} h from {o.first_h:g} h end at {times[-1] / 3600:g} h, "
                          f"after the day's {day_end_s / 3600:g} h: fewer bores or a shorter interval")
    ix = [i for i, d in enumerate(chain.directions) if d == 0]
    iy = [i for i, d in enumerate(chain.directions) if d == 1]
    if not ix or not iy:
        raise VerifyError("the machined part needs an X and a Y axis")
    ix, iy = ix[0], iy[0]

    def levels(i, k):
        lo, hi = chain.travel_mm[i]
        mid, half = (lo + hi) / 2, o.span * (hi - lo) / 2
        return np.linspace(mid - half, mid + half, k)

    xs, ys = levels(ix, int(o.columns)), levels(iy, int(o.rows))
    base = np.array([float(pose_mm[a]) for a in chain.axes])
    P, place = [], []
    for r in range(int(o.rows)):
        cols = range(int(o.columns)) if r % 2 == 0 else range(int(o.columns) - 1, -1, -1)
        for c in cols:
            p = base.copy()
            p[ix], p[iy] = xs[c], ys[r]
            P.append(p)
            place.append((c, r))
    return Bores(np.array(P), times, tuple(place))


def part_point_mm(chain, positions_mm: np.ndarray) -> np.ndarray:
    """A bore's place on the part (n × 3) [mm], about the plate's centre.

    The tool tip relative to the table: each axis' move with the sign of its side.
    """
    rel = (np.asarray(positions_mm, float) - np.array([(lo + hi) / 2 for lo, hi in chain.travel_mm])) \
        * np.asarray(chain.sides)[None, :]
    out = np.zeros((rel.shape[0], 3))
    for i, d in enumerate(chain.directions):
        out[:, d] += rel[:, i]
    return out


def machining_study(path, compensations: dict, chain, pose_mm: dict, options: MachiningOptions) -> dict:
    """The bores' deviations under each compensation.

    ``compensations``: name → callable (times [s] (n,), positions (n × axes) [mm]) → the drift the control
    takes off (n × 3) [µm].  A bore's deviation is the real machine's drift at its time and place less that;
    the distances are the neighbouring bores' (along the plate's rows and columns), their length deviation the
    difference of the two bores' deviations along the line between them.
    """
    bores = bores_of(options, chain, pose_mm, float(path.t[-1]))
    truth = np.vstack([path.at(float(t), bores.positions_mm[i:i + 1]) for i, t in enumerate(bores.time_s)])
    where = part_point_mm(chain, bores.positions_mm)
    index = {pl: i for i, pl in enumerate(bores.place)}
    pairs = [(index[(c, r)], index[(c + 1, r)]) for (c, r) in bores.place if (c + 1, r) in index]
    pairs += [(index[(c, r)], index[(c, r + 1)]) for (c, r) in bores.place if (c, r + 1) in index]
    out = {}
    for name, comp in compensations.items():
        dev = truth - comp(bores.time_s, bores.positions_mm)
        lengths = []
        for i, j in pairs:
            u = (where[j] - where[i]) / np.linalg.norm(where[j] - where[i])
            lengths.append(float((dev[j] - dev[i]) @ u))
        out[name] = {"deviation_um": dev, "distance_um": np.array(lengths),
                     "largest_position_um": float(np.linalg.norm(dev, axis=1).max()),
                     "largest_xy_um": float(np.linalg.norm(dev[:, :2], axis=1).max()),
                     "largest_depth_um": float(np.abs(dev[:, 2]).max()),
                     "largest_distance_um": float(np.abs(lengths).max()) if lengths else 0.0}
    return {"bores": bores, "part_mm": where, "pairs": pairs, "truth_um": truth, "results": out}


# -- the whole verification -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VerifyOptions:
    """One verification run: the day (machine, disturbance, mesh, hours) and the three studies' settings."""

    machine_name: str = "vmc800"
    disturbance: str = "demo day"
    element_size_mm: float = 80.0
    day_hours: float = 15.0
    seed: int = 0
    volumetric: VolumetricOptions = VolumetricOptions()
    ambient: AmbientOptions = AmbientOptions()
    machining: MachiningOptions = MachiningOptions()

    def __post_init__(self):
        _positive("element_size_mm", self.element_size_mm)
        _positive("day_hours", self.day_hours)


def table_alpha(machine) -> float:
    """The expansion coefficient of the body that holds the workpiece (the table reference's) [1/K]."""
    body = machine.body(machine.table_reference.body)
    return float(machine.materials[body.material].expansion_1_K)


def compensations_of(run: dict) -> dict:
    """The machined part's compensations from a daemon run.

    None, its offsets at its one pose applied at every position, and its support-point tables interpolated at the
    position (what the control does with each).
    """
    from hybridcomp.scenario import tables_along

    t_run, off = np.asarray(run["time_s"], float), np.asarray(run["offsets_um"], float)

    def one_pose(t, P):
        k = np.clip(np.searchsorted(t_run, t, side="right") - 1, 0, len(t_run) - 1)
        return off[k]

    return {"no compensation": lambda t, P: np.zeros((len(t), 3)),
            "hybrid at one pose": one_pose,
            "hybrid volumetric": lambda t, P: tables_along(run["tables"], np.asarray(t, float), P)}


def check_options(o: VerifyOptions) -> None:
    """Refuse, before any work, a verification whose studies do not fit in its day (VerifyError naming why)."""
    from hybridcomp.models import load_machine
    from hybridcomp.scenario import DISTURBANCES

    if o.disturbance not in DISTURBANCES:
        raise VerifyError(f"unknown disturbance {o.disturbance!r} (known: {', '.join(DISTURBANCES)})")
    axes = [a.name for a in load_machine(o.machine_name).axes]
    for what, plan in (("calibration plan", o.volumetric.plan), ("ambient study's plan", o.ambient.plan)):
        if len(plan.levels) != len(axes):
            raise VerifyError(f"{what}: {len(plan.levels)} levels {list(plan.levels)} for the axes {', '.join(axes)} "
                              f"of {o.machine_name}: give one per axis")
    for what, levels in (("volumetric grid", o.volumetric.grid_levels), ("ambient grid", o.ambient.grid_levels)):
        if len(levels) != len(axes):
            raise VerifyError(f"{what}: {len(levels)} levels for the axes {', '.join(axes)}: give one per axis")
    day_end_s = o.day_hours * 3600.0
    _check_calibrations(o.volumetric, day_end_s)
    m = o.machining
    last_h = m.first_h + m.every_h * (int(m.columns) * int(m.rows) - 1)
    if last_h > o.day_hours + 1e-9:
        raise VerifyError(f"{int(m.columns) * int(m.rows)} bores every {m.every_h:g} h from {m.first_h:g} h end at "
                          f"{last_h:g} h, after the day's {o.day_hours:g} h: fewer bores or a shorter interval")
    if o.ambient.state_h > o.day_hours:
        raise VerifyError(f"the ambient study's state at {o.ambient.state_h:g} h is after the day's "
                          f"{o.day_hours:g} h")


def run_verification(out_dir, options: VerifyOptions = VerifyOptions()) -> dict:
    """Simulate the day, run the three studies, write ``report.md``, ``summary.json`` and the plots into ``out_dir``.

    Returns the summary.
    """
    import time

    from hybridcomp.chardiag.kinematic import chain_of
    from hybridcomp.chardiag.thermal_map import to_dict
    from hybridcomp.models import jsonio
    from hybridcomp.safeio import write_text_atomic
    from hybridcomp.scenario import DISTURBANCES, Scenario, build_models, run_scenario, tables_along

    o = options
    check_options(o)
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    models = build_models(out / "models", o.machine_name, o.element_size_mm, keep_basis=True, poses=True)
    day = run_scenario(Scenario(disturbance=DISTURBANCES[o.disturbance], machine_name=o.machine_name,
                                element_size_mm=o.element_size_mm, day_hours=o.day_hours, along_path=True,
                                strategies=("hybrid",), plot=False, seed=o.seed), out / "day", models)
    timings = {"day_s": time.perf_counter() - t0}
    chain = chain_of(models.machine)
    run = day.runs["hybrid"]
    sensor_names = [s.name for s in models.machine.sensors]
    t1 = time.perf_counter()
    study = volumetric_study(day.path, lambda t, P: tables_along(run["tables"], t, P), day.sensors, sensor_names,
                             chain, o.volumetric, np.random.default_rng([o.seed, 1]))
    amb = ambient_study(day.path, lambda P: ambient_response_um(day.path.rom, P),
                        lambda P: ambient_response_um(models.pose_rom, P), chain, table_alpha(models.machine),
                        o.ambient, o.seed)
    part = machining_study(day.path, compensations_of(run), chain, dict(models.pose_mm), o.machining)
    timings["studies_s"] = time.perf_counter() - t1
    vol = study.summary
    write_text_atomic(out / "thermal_map.json", jsonio.dumps(to_dict(study.model), indent=1))
    write_text_atomic(out / "calibrations.csv", calibrations_csv(study.calibrations, vol["calibrations"], chain,
                                                                  study.model.sensor_names,
                                                                  o.volumetric.plan.seconds_per_point))
    plots = {"part": _part_plot(out / "part.png", part, chain),
             "volumetric": _volumetric_plot(out / "volumetric.png", vol),
             "ambient": _ambient_plot(out / "ambient.png", amb)}
    summary = {
        "machine": models.machine.name, "disturbance": o.disturbance, "element_size_mm": o.element_size_mm,
        "day_hours": o.day_hours, "seed": o.seed,
        "truth": day.summary.get("along_path", {}).get("truth"),
        "volumetric": vol, "ambient": amb,
        "machining": _part_summary(part),
        "plots": {k: v.name for k, v in plots.items() if v is not None},
        "timings_s": timings,
    }
    write_text_atomic(out / "summary.json", jsonio.dumps(summary, indent=1, default=str))
    write_text_atomic(out / "report.md", report_text(summary, part))
    return summary


def calibrations_csv(cals: list, rows: list[dict], chain, sensor_names, seconds_per_point: float) -> str:
    """Every simulated calibration point as a measuring campaign records it (CSV text).

    Columns: ``calibration`` (its start, ``1.0 h``), ``role`` (``fit`` or ``held out``), ``time_s`` of the point
    (the calibration's start plus ``seconds_per_point`` per point before it),
    the axis positions ``<axis>_mm``, the measured ``dx_um``, ``dy_um``, ``dz_um`` and the sensors averaged over the
    calibration ``<sensor>_degC``.
    """
    head = (["calibration", "role", "time_s"] + [f"{a}_mm" for a in chain.axes] + ["dx_um", "dy_um", "dz_um"]
            + [f"{n}_degC" for n in sensor_names])
    lines = [",".join(head)]
    for c, info in zip(cals, rows):
        sec = float(c.time_s) + seconds_per_point * np.arange(c.poses_mm.shape[0])
        for i in range(c.poses_mm.shape[0]):
            vals = ([info["state"], info["role"], f"{sec[i]:.1f}"] + [f"{v:.4f}" for v in c.poses_mm[i]]
                    + [f"{v:.4f}" for v in c.error_um[i]] + [f"{v:.4f}" for v in c.sensors_degC])
            lines.append(",".join(vals))
    return "\n".join(lines) + "\n"


def _part_summary(part: dict) -> dict:
    b = part["bores"]
    res = part["results"]
    return {
        "bores": [{"bore": i + 1, "column": c + 1, "row": r + 1, "cut_h": float(b.time_s[i] / 3600.0),
                   "part_mm": [float(v) for v in part["part_mm"][i]],
                   **{k: [float(v) for v in res[k]["deviation_um"][i]] for k in res}}
                  for i, (c, r) in enumerate(b.place)],
        "distances": [{"bores": [i + 1, j + 1],
                       "nominal_mm": float(np.linalg.norm(part["part_mm"][j] - part["part_mm"][i])),
                       **{k: float(res[k]["distance_um"][n]) for k in res}}
                      for n, (i, j) in enumerate(part["pairs"])],
        "largest": {k: {m: v[m] for m in ("largest_position_um", "largest_xy_um", "largest_depth_um",
                                          "largest_distance_um")} for k, v in res.items()},
        "ratio_volumetric_to_one_pose": (res["hybrid volumetric"]["largest_position_um"]
                                         / max(res["hybrid at one pose"]["largest_position_um"], 1e-12)),
    }


def _fmt(v: float) -> str:
    return f"{v:.2f}"


def report_text(summary: dict, part: dict) -> str:
    """The verification report (Markdown): the three studies' tables and plots."""
    vol, amb, mach = summary["volumetric"], summary["ambient"], summary["machining"]
    lines = [f"# Verification of the thermal compensation: {summary['machine']}, {summary['disturbance']}", "",
             f"The real machine's drift at every pose and time comes from {summary['truth'] or 'the real machine'}; "
             f"{summary['day_hours']:g} h of the job-shop day at {summary['element_size_mm']:g} mm elements, seed "
             f"{summary['seed']}. Errors are 3D lengths [µm] of TCP minus table, thermal part only (a static "
             "geometric error is identified alike by every calibration).", ""]
    p = vol["plan"]
    lines += ["## Volumetric model against the support-point tables", "",
              f"{len(vol['calibrations'])} calibrations of {p['points']} poses ({' × '.join(map(str, p['levels']))}, "
              f"{p['seconds_per_point']:g} s a point, {p['duration_min']:.0f} min, σ = {p['noise_um']:g} µm): "
              "the thermal map is fitted on "
              + ", ".join(f"{c['state']} ({c['phase']})" for c in vol["calibrations"] if c["role"] == "fit")
              + "; judged on " + ", ".join(f"{c['state']} ({c['phase']})" for c in vol["calibrations"]
                                           if c["role"] == "held out")
              + f" (held out: no choice saw them), over a workspace grid of {vol['grid_points']} points.", ""]
    mo = vol["model"]
    lines += [f"Thermal map: {mo['components']} drift components over {mo['states']} states, inputs by "
              f"{mo['criterion'].upper().replace('BICC', 'BICc')}: {', '.join(mo['inputs']) or 'none'}; residual noise "
              f"{mo['noise_um']:.2f} µm"
              + (f"; held-out states outside the training range of {', '.join(mo['held_out_outside_training_range'])}"
                 if mo["held_out_outside_training_range"] else "") + ".", ""]
    lines += ["| compensation | max [µm] | RMS [µm] | P95 [µm] |", "|---|---|---|---|"]
    for k, s in vol["held_out"].items():
        lines.append(f"| {k} | {_fmt(s['max_um'])} | {_fmt(s['rms_um'])} | {_fmt(s['p95_um'])} |")
    lines += ["", "![held-out states](volumetric.png)", ""]
    lines += ["## The ambient during verification", "",
              f"A calibration of the working state at {amb['state_h']:g} h taken with the air {amb['ambient_K']:+g} K "
              f"off working temperature (air thermometer σ = {amb['air_noise_K']:g} K); compensation error at "
              f"working temperature over {amb['grid_points']} grid points; the reference is the calibration at "
              "working temperature (same noise).", "",
              "| instrument | σ [µm] | uncorrected max / RMS | corrected max / RMS | at working temperature max / RMS "
              "| corrected − reference max |", "|---|---|---|---|---|---|"]
    for r in amb["rows"]:
        u, c, w = r["uncorrected"], r["corrected"], r["at working temperature"]
        lines.append(f"| {r['artefact']} | {r['sigma_um']:g} | {_fmt(u['max_um'])} / {_fmt(u['rms_um'])} | "
                     f"{_fmt(c['max_um'])} / {_fmt(c['rms_um'])} | {_fmt(w['max_um'])} / {_fmt(w['rms_um'])} | "
                     f"{_fmt(r['corrected_vs_reference_max_um'])} |")
    lines += ["", "![the ambient during verification](ambient.png)"]
    lines += ["", "## The machined part", "",
              f"{len(mach['bores'])} bores, one every {part['bores'].time_s[1] / 3600 - part['bores'].time_s[0] / 3600:g}"
              " h; deviations of the bores' positions (3D, in the plate xy and depth) and of the distances between "
              "neighbouring bores.", "",
              "| compensation | largest position [µm] | largest xy [µm] | largest depth [µm] | largest distance [µm] |",
              "|---|---|---|---|---|"]
    for k, s in mach["largest"].items():
        lines.append(f"| {k} | {_fmt(s['largest_position_um'])} | {_fmt(s['largest_xy_um'])} | "
                     f"{_fmt(s['largest_depth_um'])} | {_fmt(s['largest_distance_um'])} |")
    lines += ["", f"Volumetric / one pose, largest position deviation: {mach['ratio_volumetric_to_one_pose']:.2f}.",
              "", "![the part](part.png)", "", "### Bores", "",
              "| bore | cut at [h] | on the part x, y [mm] | " + " | ".join(f"{k} dx, dy, dz [µm]"
                                                                    for k in part["results"]) + " |",
              "|---|---|---|" + "---|" * len(part["results"])]
    for b in mach["bores"]:
        cells = [", ".join(f"{v:.1f}" for v in b[k]) for k in part["results"]]
        lines.append(f"| {b['bore']} | {b['cut_h']:.1f} | {b['part_mm'][0]:.0f}, {b['part_mm'][1]:.0f} | "
                     + " | ".join(cells) + " |")
    lines += ["", "### Distances between neighbouring bores", "",
              "Length deviation of each distance (the two bores' deviations along the line between them) [µm].", "",
              "| bores | nominal [mm] | " + " | ".join(part["results"]) + " |",
              "|---|---|" + "---|" * len(part["results"])]
    for d in mach["distances"]:
        lines.append(f"| {d['bores'][0]}–{d['bores'][1]} | {d['nominal_mm']:.0f} | "
                     + " | ".join(f"{d[k]:+.2f}" for k in part["results"]) + " |")
    return "\n".join(lines) + "\n"


def _pyplot(what: str):
    """The pyplot module on the file backend, or None with a warning naming the plot (pictures are optional)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("no %s plot: matplotlib is not installed", what)
        return None
    return plt


def _part_plot(path: Path, part: dict, chain) -> Path | None:
    """The plate from above: each bore where it should be and its deviation, magnified, per compensation."""
    plt = _pyplot("part")
    if plt is None:
        return None
    res = part["results"]
    where = part["part_mm"]
    largest = max(v["largest_xy_um"] for v in res.values())
    span = np.ptp(where[:, 0]) or 1.0
    scale = 0.12 * span / max(largest, 1e-9) * 1e3  # mm of plot per mm of deviation
    fig, axes = plt.subplots(1, len(res), figsize=(5.2 * len(res), 4.2), sharey=True, constrained_layout=True)
    depth_max = max(v["largest_depth_um"] for v in res.values()) or 1.0
    for ax, (name, r) in zip(np.atleast_1d(axes), res.items()):
        d = r["deviation_um"] * 1e-3
        for i, j in part["pairs"]:
            ax.plot(where[[i, j], 0], where[[i, j], 1], color="0.85", lw=0.8, zorder=1)
        ax.scatter(where[:, 0], where[:, 1], s=90, facecolors="none", edgecolors="0.5", zorder=2, label="nominal")
        sc = ax.scatter(where[:, 0] + scale * d[:, 0], where[:, 1] + scale * d[:, 1], s=90,
                        c=r["deviation_um"][:, 2], cmap="coolwarm", vmin=-depth_max, vmax=depth_max, zorder=3,
                        edgecolors="k", label="as cut (colour: depth)")
        for i in range(where.shape[0]):
            ax.annotate("", xy=(where[i, 0] + scale * d[i, 0], where[i, 1] + scale * d[i, 1]),
                        xytext=(where[i, 0], where[i, 1]), arrowprops=dict(arrowstyle="->", color="k", lw=0.8))
            ax.text(where[i, 0] + 0.03 * span, where[i, 1] + 0.035 * span, f"{part['bores'].time_s[i] / 3600:.1f} h",
                    ha="left", va="bottom", fontsize=7, color="0.3")
        ax.set_title(f"{name}\nlargest xy {r['largest_xy_um']:.1f} µm, depth {r['largest_depth_um']:.1f} µm",
                     fontsize=10)
        ax.set_xlabel("x on the plate [mm]")
        ax.set_aspect("equal")
        ax.margins(0.15)
    np.atleast_1d(axes)[0].set_ylabel("y on the plate [mm]")
    fig.colorbar(sc, ax=axes, shrink=0.8, label="depth deviation [µm]")
    fig.legend(*np.atleast_1d(axes)[0].get_legend_handles_labels(), loc="outside lower center", ncol=2, fontsize=8)
    fig.suptitle(f"The machined plate from above: bores cut over the day (hour of each cut), deviations magnified "
                 f"×{scale:.0f} in every panel ({0.12 * span:.0f} mm of arrow = {largest:.1f} µm)", fontsize=11)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _ambient_plot(path: Path, amb: dict) -> Path | None:
    """The ambient study: largest compensation error at working temperature per instrument and noise."""
    plt = _pyplot("ambient")
    if plt is None:
        return None
    rows = amb["rows"]
    kinds = (("uncorrected", "uncorrected", "tab:red"), ("corrected", "corrected", "tab:green"),
             ("at working temperature", "identified at working temperature", "0.5"))
    fig, ax = plt.subplots(figsize=(7.5, 3.8), constrained_layout=True)
    _grouped_bars(ax, [f"{r['artefact']}\nσ = {r['sigma_um']:g} µm" for r in rows],
                  [(label, [r[key]["max_um"] for r in rows], colour) for key, label, colour in kinds], fontsize=8)
    ax.set_ylabel("largest compensation error [µm]")
    ax.set_title(f"functions identified with the air {amb['ambient_K']:+g} K, used at working temperature",
                 fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _grouped_bars(ax, groups: list[str], series: list[tuple], fontsize=None) -> None:
    """Bars side by side per group: ``series`` of (label, one value per group, colour or None); legend and grid."""
    x = np.arange(len(groups))
    w = 0.8 / len(series)
    for i, (label, values, colour) in enumerate(series):
        ax.bar(x + (i - (len(series) - 1) / 2) * w, values, w, label=label, color=colour)
    ax.set_xticks(x, groups, fontsize=fontsize)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)


def _volumetric_plot(path: Path, vol: dict) -> Path | None:
    """Largest TCP error over the workspace grid at each held-out state, per compensation."""
    plt = _pyplot("volumetric")
    if plt is None:
        return None
    rows = vol["per_state"]
    names = [k for k in rows[0] if k not in ("state", "time_h")]
    fig, ax = plt.subplots(figsize=(7.5, 3.8), constrained_layout=True)
    _grouped_bars(ax, [r["state"] for r in rows], [(k, [r[k] for r in rows], None) for k in names])
    ax.set_xlabel("held-out calibration (start of the day's hour)")
    ax.set_ylabel("largest TCP error over the grid [µm]")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
