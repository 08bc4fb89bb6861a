"""Time stepping of an assembled thermal model: the θ-method and TR-BDF2, steady states.

Every model runs through ``model.simulate(loads, initial, scheme=...)``; this module holds the schemes it
dispatches to, on the model's operators (:func:`integrate_inputs`) or on any sparse SPD pair (``M x' + A x = Bu u``,
:func:`integrate_theta`, :func:`integrate_trbdf2`).

θ-method (``scheme="theta"``) on the loads' own times::

    (M/Δt + θA) x_{k+1} = (M/Δt − (1−θ)A) x_k + Bu (θ u_{k+1} + (1−θ) u_k)

θ = 1 (backward Euler) is L-stable: no oscillation after load steps at large Δt.  θ = 0.5 (Crank–Nicolson) is
second order for smooth loads and small steps.  One factorisation per (Δt, θ), cached on the model, so repeated
calls and non-uniform time grids with a few distinct steps stay cheap.

TR-BDF2 (``scheme="trbdf2"``, the default; Bank et al. 1985; Hosea & Shampine 1996) takes a step h in two stages:
the trapezoidal rule to t + γh, then BDF2 through t, t + γh and t + h.  With γ = 2 − √2 both stages solve with
the same matrix ``M + d h A``, d = γ/2 = 1 − 1/√2, so one factorisation serves a step size.  The scheme is second
order and L-stable (its amplification factor R(z) → 0 as z → −∞): a step in power does not ring at any step size,
unlike Crank–Nicolson.

The TR-BDF2 step policy keeps the loads grid: every interval of the loads CSV is split into equal sub-steps (the
loads are linear between samples, so their kinks lie on step boundaries and the scheme keeps its order), the same
number in every interval of equal length, so a uniform loads grid needs one step size.  The error of the outputs
(sensor temperatures [K], drift [µm]) at the loads times is estimated from two runs, with 2m and with m sub-steps
per interval: ``max |y_2m − y_m|``.  If halving the step at least halves the error (order ≥ 1, which holds before
the second-order regime is reached), this difference bounds the error of the 2m run; in the second-order regime it
is about three times that error (Richardson: error ≈ |y_2m − y_m| / (2² − 1)).  While the estimate exceeds the
tolerance, m doubles; the previous fine run becomes the coarse one, so each refinement costs one run and one
factorisation.

Pure functions; the time loops use sparse products and einsum only (no dense BLAS call: OpenBLAS threads spinning
after it starve the sparse solver).  The model type is needed for annotations only: :mod:`hybridcomp.fem.model`
imports this module, never the reverse.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from hybridcomp.fem.solvers import Factor, factorize_spd
from hybridcomp.models.simulation import SimulationResult, initial_state

if TYPE_CHECKING:
    from hybridcomp.fem.model import ThermoElasticModel

log = logging.getLogger(__name__)

SCHEMES = ("trbdf2", "theta")
"""Time schemes of :meth:`ThermoElasticModel.simulate`: TR-BDF2 to a tolerance, the θ-method on the loads' times."""
DEFAULT_SCHEME = "trbdf2"
"""The default scheme of the library and of every command that runs the FE model (``simulate``, ``batch run``,
``cd train-data``): second order, L-stable, and the only one whose time error is estimated and controlled."""
DEFAULT_THETA = 1.0
"""θ of ``scheme="theta"`` when none is given: backward Euler."""

GAMMA = 2.0 - math.sqrt(2.0)
"""Stage point of TR-BDF2 [-]: the trapezoidal stage ends at t + γh."""
D = GAMMA / 2.0
"""Diagonal of TR-BDF2 with γ = 2 − √2 [-]: both stages solve (M + d h A) x = r; d = (1 − γ)/(2 − γ) as well."""
_BDF_NEW = 1.0 / (GAMMA * (2.0 - GAMMA))
_BDF_OLD = (1.0 - GAMMA) ** 2 / (GAMMA * (2.0 - GAMMA))
SCHEME = "TR-BDF2"


def _cached_factor(cache: dict, key: tuple, build, coords) -> Factor:
    """The factorisation of ``build()`` under ``key`` in ``cache``, made on first use."""
    if key not in cache:
        t0 = time.perf_counter()
        cache[key] = factorize_spd(build(), coords)
        log.debug("factorised %s in %.2f s (%s)", key, time.perf_counter() - t0, cache[key].backend)
    return cache[key]


def steady_state(model: ThermoElasticModel, u: np.ndarray) -> np.ndarray:
    """Temperature rise [K] at steady state for constant inputs ``u``."""
    f = _cached_factor(model._cache, ("steady",), model.A, model.coords_m)
    return f(model.input_matrix() @ np.asarray(u, float))


def _times_and_inputs(time_s, inputs, n_inputs: int) -> tuple[np.ndarray, np.ndarray]:
    """``time_s`` [s] and ``inputs`` (nt × n_inputs) as float arrays, checked: times a strictly increasing vector."""
    t = np.asarray(time_s, float)
    U = np.asarray(inputs, float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError("time_s must be a non-empty vector")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise ValueError(f"time_s must increase strictly; step {k} goes from {t[k - 1]} s to {t[k]} s")
    if U.shape != (t.size, n_inputs):
        raise ValueError(f"inputs must be ({t.size}, {n_inputs}), got {U.shape}")
    return t, U


def _model_inputs(model: ThermoElasticModel, inputs) -> np.ndarray:
    """``inputs`` as a float array (nt × inputs of ``model``), or ``ValueError`` naming the expected columns."""
    U = np.asarray(inputs, float)
    if U.ndim != 2 or U.shape[1] != len(model.input_names):
        raise ValueError(f"inputs must have {len(model.input_names)} columns ({model.input_names}), got shape {U.shape}")
    return U


def _check_theta(theta: float) -> None:
    """``ValueError`` unless θ is in [0.5, 1], where the θ-method is unconditionally stable."""
    if not 0.5 <= theta <= 1.0:
        raise ValueError(f"theta must be in [0.5, 1] for an unconditionally stable scheme, got {theta}")


def integrate_theta(
    M,
    A,
    Bu: np.ndarray,
    outputs: tuple,
    time_s: np.ndarray,
    inputs: np.ndarray,
    theta: float = DEFAULT_THETA,
    x0: np.ndarray | None = None,
    coords: np.ndarray | None = None,
    cache: dict | None = None,
    store_steps: tuple[int, ...] | None = None,
    progress: bool = False,
) -> tuple[list[np.ndarray], dict[int, np.ndarray], dict]:
    """θ-method for ``M x' + A x = Bu u(t)`` on any sparse SPD pair (M, A).

    Parameters
    ----------
    M, A : sparse SPD matrices (n × n)
    Bu : input matrix (n × nu); ``inputs`` (nt × nu) are its inputs at ``time_s``
    outputs : matrices (r × n) evaluated at every step
    x0 : initial state (default zero)
    coords : (n, 3) node coordinates for the fill-reducing ordering
    cache : dict for factorisations keyed by (Δt, θ), kept across calls

    Returns
    -------
    per output an (nt × r) array, the stored states, and timings [s]
    """
    t, U = _times_and_inputs(time_s, inputs, Bu.shape[1])
    _check_theta(theta)
    n = M.shape[0]
    # No dense BLAS call inside the loop: numpy's OpenBLAS threads spin after each call and starve
    # the sparse solver's own BLAS threads (measured 8x slower steps on 2 cores).  Sparse products
    # and einsum do not touch BLAS.
    Bu = sp.csr_matrix(Bu)
    nt = t.size
    st = _loop_start(n, nt, outputs, x0, cache, store_steps)
    x, cache, ys, fields = st.x, st.cache, st.ys, st.fields
    t_factor = t_solve = 0.0
    t0_all = time.perf_counter()
    bar = _progress_bar(progress, nt - 1, "transient")
    dts = np.diff(t)
    for k in range(1, nt):
        dt = float(dts[k - 1])
        key = ("step", round(dt, 9), float(theta))
        tf = time.perf_counter()
        f = _cached_factor(cache, key, lambda: M / dt + theta * A, coords)  # noqa: B023 - called at once, in this step
        if ("Mdt", key[1]) not in cache:
            cache[("Mdt", key[1])] = (M / dt).tocsr()
        Mdt = cache[("Mdt", key[1])]
        t_factor += time.perf_counter() - tf
        rhs = Mdt @ x + Bu @ (theta * U[k] + (1 - theta) * U[k - 1])
        if theta != 1.0:
            rhs -= (1 - theta) * (A @ x)
        ts = time.perf_counter()
        x = f(rhs)
        t_solve += time.perf_counter() - ts
        st.record(k, x)
        if bar is not None:
            bar.update()
    return ys, fields, _finish(bar, t0_all, t_factor, t_solve)


@dataclass(frozen=True)
class TimeTolerance:
    """Largest accepted time-discretisation error of the outputs at the loads times.

    Attributes
    ----------
    sensor_K : sensor temperatures [K]
    drift_um : TCP drift dx, dy, dz [µm]
    """

    sensor_K: float = 0.01
    drift_um: float = 0.05

    def __post_init__(self):
        for name, v in (("sensor_K", self.sensor_K), ("drift_um", self.drift_um)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"time tolerance {name} must be a positive number, got {v!r}")


DEFAULT_TOLERANCE = TimeTolerance()


@dataclass(frozen=True)
class TimeErrorEstimate:
    """What the controlled run did and how far its outputs are estimated to be from the exact time integral.

    Attributes
    ----------
    scheme : the time scheme
    tolerance : the tolerance the run was asked to meet
    sensor_K : estimated largest error of a sensor temperature at a loads time [K]
    drift_um : estimated largest error of dx, dy or dz at a loads time [µm]
    met : both estimates within the tolerance
    substeps : sub-steps per loads interval of the reported run
    steps : number of steps of the reported run
    step_sizes_s : its distinct step sizes [s] (one factorisation each)
    runs : runs made, coarsest first (the estimate compares the last two)
    """

    scheme: str
    tolerance: TimeTolerance
    sensor_K: float
    drift_um: float
    met: bool
    substeps: int
    steps: int
    step_sizes_s: tuple[float, ...]
    runs: int

    def as_dict(self) -> dict:
        return {
            "scheme": self.scheme,
            "method": "max |y_2m - y_m| at the loads times, runs with 2m and m sub-steps per loads interval: bounds the "
                      "2m run's error while halving the step at least halves the error; about 3x that error once second order",
            "tolerance_sensor_K": self.tolerance.sensor_K,
            "tolerance_drift_um": self.tolerance.drift_um,
            "estimate_sensor_K": self.sensor_K,
            "estimate_drift_um": self.drift_um,
            "met": self.met,
            "substeps_per_interval": self.substeps,
            "steps": self.steps,
            "step_sizes_s": list(self.step_sizes_s),
            "runs": self.runs,
        }


def amplification(z: np.ndarray | complex) -> np.ndarray | complex:
    """TR-BDF2's amplification factor R(z) for ``x' = λx``, z = hλ [-]: x_{n+1} = R(z) x_n.

    From the two stages: x_γ = (1 + dz)/(1 − dz) x_n, then x_{n+1} = (a x_γ − b x_n)/(1 − dz) with the BDF2
    weights a = 1/(γ(2 − γ)), b = (1 − γ)²/(γ(2 − γ)).  |R| ≤ 1 for Re z ≤ 0 and R(z) → 0 as z → −∞.
    """
    z = np.asarray(z, dtype=complex)
    x_gamma = (1 + D * z) / (1 - D * z)
    out = (_BDF_NEW * x_gamma - _BDF_OLD) / (1 - D * z)
    return out if out.ndim else complex(out)


def step_sizes_s(time_s: np.ndarray, substeps: int) -> tuple[float, ...]:
    """Distinct step sizes [s] (rounded to ns, as the factorisation cache keys them) of ``substeps`` per interval."""
    h = np.diff(np.asarray(time_s, float)) / substeps
    return tuple(sorted(set(np.round(h, 9).tolist())))


def _output_product(C):
    """``v ↦ C v`` without dense BLAS: a sparse product, or einsum for a dense ``C``."""
    if sp.issparse(C):
        return lambda v: C @ v
    C = np.asarray(C)
    return lambda v: np.einsum("ij,j->i", C, v)


@dataclass
class _LoopStart:
    """What both time loops set up before their first step: output products, state, caches, result arrays."""

    products: list
    x: np.ndarray
    cache: dict
    store: set
    ys: list
    fields: dict

    def record(self, k: int, x: np.ndarray) -> None:
        """The outputs of state ``x`` at time index ``k``, and the state itself if ``k`` is stored."""
        for y, prod in zip(self.ys, self.products):
            y[k] = prod(x)
        if k in self.store:
            self.fields[k] = x.copy()


def _finish(bar, t0_all: float, t_factor: float, t_solve: float) -> dict:
    """Close the progress bar; the loop's timings [s]."""
    if bar is not None:
        bar.close()
    total = time.perf_counter() - t0_all
    return {"factorisation": t_factor, "triangular_solves": t_solve, "stepping_total": total - t_factor}


def _loop_start(n: int, nt: int, outputs, x0, cache, store_steps) -> _LoopStart:
    """The initial state (zero or ``x0``, checked), the outputs at the first time and the stored fields."""
    products = [_output_product(C) for C in outputs]
    x = np.zeros(n) if x0 is None else np.asarray(x0, float).copy()
    if x.shape != (n,):
        raise ValueError(f"initial state must have {n} entries, got {x.shape}")
    store = set(store_steps or ())
    ys = [np.empty((nt, C.shape[0])) for C in outputs]
    for y, prod in zip(ys, products):
        y[0] = prod(x)
    fields: dict[int, np.ndarray] = {0: x.copy()} if 0 in store else {}
    return _LoopStart(products, x, {} if cache is None else cache, store, ys, fields)


def _progress_bar(show: bool, total: int, desc: str):
    """A tqdm bar over the steps, or None."""
    if not show:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="step", desc=desc, leave=False)


def integrate_trbdf2(
    M,
    A,
    Bu: np.ndarray,
    outputs: tuple,
    time_s: np.ndarray,
    inputs: np.ndarray,
    substeps: int = 1,
    x0: np.ndarray | None = None,
    coords: np.ndarray | None = None,
    cache: dict | None = None,
    store_steps: tuple[int, ...] | None = None,
    progress: bool = False,
) -> tuple[list[np.ndarray], dict[int, np.ndarray], dict]:
    """TR-BDF2 for ``M x' + A x = Bu u(t)``, ``substeps`` equal steps per interval of ``time_s``.

    The inputs are linear between the samples ``inputs`` (nt × nu) at ``time_s`` [s]; outputs and
    stored states are those at ``time_s``.  Parameters as :func:`integrate_theta`;
    factorisations of ``M + d h A`` are cached under ``("trbdf2", h)``.

    Returns
    -------
    per output an (nt × r) array, the stored states {loads index: state}, and timings [s]
    """
    t, U = _times_and_inputs(time_s, inputs, Bu.shape[1])
    if not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    n = M.shape[0]
    Bu = sp.csr_matrix(Bu)
    M = sp.csr_matrix(M)
    nt = t.size
    st = _loop_start(n, nt, outputs, x0, cache, store_steps)
    x, cache, ys, fields = st.x, st.cache, st.ys, st.fields
    t_factor = t_solve = 0.0
    t0_all = time.perf_counter()
    bar = _progress_bar(progress, (nt - 1) * substeps, "transient TR-BDF2")
    s_gamma = np.arange(substeps) + GAMMA  # stage points in sub-step units
    for k in range(1, nt):
        h = float(t[k] - t[k - 1]) / substeps
        hk = round(h, 9)
        tf = time.perf_counter()
        f = _cached_factor(cache, ("trbdf2", hk), lambda h=h: M + (D * h) * A, coords)
        if ("trbdf2-explicit", hk) not in cache:
            cache[("trbdf2-explicit", hk)] = (M - (D * h) * A).tocsr()
        explicit = cache[("trbdf2-explicit", hk)]
        t_factor += time.perf_counter() - tf
        du = U[k] - U[k - 1]
        f_old = Bu @ U[k - 1]
        dhf = D * h
        for j in range(substeps):
            f_gamma = Bu @ (U[k - 1] + du * (s_gamma[j] / substeps))
            f_new = Bu @ (U[k - 1] + du * ((j + 1) / substeps))
            ts = time.perf_counter()
            x_gamma = f(explicit @ x + dhf * (f_old + f_gamma))
            x = f(M @ (_BDF_NEW * x_gamma - _BDF_OLD * x) + dhf * f_new)
            t_solve += time.perf_counter() - ts
            f_old = f_new
            if bar is not None:
                bar.update()
        st.record(k, x)
    return ys, fields, _finish(bar, t0_all, t_factor, t_solve)


def error_bound(y_fine: np.ndarray, y_coarse: np.ndarray) -> float:
    """Estimated bound of the largest error of ``y_fine`` from a run with twice its step: max |y_fine − y_coarse|.

    With errors e(h) = c h^p the difference is (2^p − 1) |e(h/2)|: at least the fine run's error for p ≥ 1,
    three times it for p = 2.
    """
    y_fine, y_coarse = np.asarray(y_fine, float), np.asarray(y_coarse, float)
    if y_fine.shape != y_coarse.shape:
        raise ValueError(f"fine and coarse outputs differ in shape: {y_fine.shape} vs {y_coarse.shape}")
    return float(np.max(np.abs(y_fine - y_coarse), initial=0.0))


def integrate_controlled(
    model: ThermoElasticModel,
    time_s: np.ndarray,
    inputs: np.ndarray,
    tolerance: TimeTolerance = DEFAULT_TOLERANCE,
    initial: str | np.ndarray = "steady",
    store_steps: tuple[int, ...] | None = None,
    progress: bool = False,
    max_substeps: int = 256,
) -> tuple[SimulationResult, TimeErrorEstimate]:
    """Integrate the model by TR-BDF2, refining until the estimated output error meets ``tolerance``.

    Runs with m = 1, 2, 4, ... sub-steps per loads interval; stops when the
    error bound (:func:`error_bound`) of the finer of the last two runs is within the
    tolerance for both sensor temperatures [K] and drift [µm], or when m would
    exceed ``max_substeps`` (then the estimate says ``met=False`` and a warning
    is logged).  The result is the finer run.

    Parameters
    ----------
    time_s : strictly increasing loads and output times [s]
    inputs : heat powers [W] and air temperature rises over the reference [K] per time (nt × nu)
    tolerance : accepted error of the outputs
    initial : ``"steady"``, ``"reference"`` or a state [K], as :func:`integrate_inputs`
    store_steps : indices of loads times whose full field is kept
    max_substeps : largest number of sub-steps per loads interval
    """
    U = _model_inputs(model, inputs)
    if not (isinstance(max_substeps, (int, np.integer)) and max_substeps >= 2):
        raise ValueError(f"max_substeps must be an integer of at least 2, got {max_substeps!r}")
    x0 = initial_state(initial, model.n, lambda: steady_state(model, U[0]))
    t = np.asarray(time_s, float)
    G_um = np.asarray(model.G) * 1e6

    def run(m: int, store):
        (sens, drift), fields, timings = integrate_trbdf2(
            model.M, model.A(), model.input_matrix(), (model.C, G_um), t, U, substeps=m, x0=x0,
            coords=model.coords_m, cache=model._cache, store_steps=store, progress=progress)
        return sens, drift, fields, timings

    timings_all: dict[str, float] = {}

    def add(timings):
        for key, v in timings.items():
            timings_all[key] = timings_all.get(key, 0.0) + v

    m = 1
    coarse = run(m, ())
    add(coarse[3])
    runs = 1
    while True:
        fine = run(2 * m, store_steps)
        add(fine[3])
        runs += 1
        m *= 2
        est_K = error_bound(fine[0], coarse[0])
        est_um = error_bound(fine[1], coarse[1])
        met = est_K <= tolerance.sensor_K and est_um <= tolerance.drift_um
        log.info("TR-BDF2 with %d sub-steps per interval: estimated error %.2g K, %.2g um", m, est_K, est_um)
        if met or 2 * m > max_substeps:
            break
        coarse = fine
    if not met:
        log.warning("TR-BDF2 did not meet the time tolerance (%g K, %g um) with %d sub-steps per loads interval: "
                    "estimated error %.3g K, %.3g um", tolerance.sensor_K, tolerance.drift_um, m, est_K, est_um)
    sens, drift, fields, _ = fine
    result = SimulationResult(time_s=t, sensors_degC=sens + model.reference_temperature_degC, drift_um=drift,
                              fields_K=fields, timings_s=timings_all, sensor_names=model.sensor_names)
    estimate = TimeErrorEstimate(scheme=SCHEME, tolerance=tolerance, sensor_K=est_K, drift_um=est_um, met=met,
                                 substeps=m, steps=(t.size - 1) * m, step_sizes_s=step_sizes_s(t, m), runs=runs)
    return result, estimate


def check_scheme(scheme: str, theta: float | None = None, tolerance: TimeTolerance | None = None) -> float | None:
    """The θ of a run of ``scheme`` (None for TR-BDF2), after checking that its options belong to it.

    Raises
    ------
    ValueError
        an unknown scheme, a ``theta`` with TR-BDF2 or a ``tolerance`` with the θ-method (an option the scheme
        would ignore), or θ outside [0.5, 1]
    """
    if scheme not in SCHEMES:
        raise ValueError(f"unknown time scheme {scheme!r} (schemes: {', '.join(SCHEMES)})")
    if scheme == "trbdf2":
        if theta is not None:
            raise ValueError(f"theta={theta!r} applies to scheme='theta', not to the default 'trbdf2'")
        return None
    if tolerance is not None:
        raise ValueError("a time tolerance applies to scheme='trbdf2' (the θ-method at the loads' times has no error "
                         "control)")
    theta = DEFAULT_THETA if theta is None else float(theta)
    _check_theta(theta)
    return theta


def integrate_inputs(
    model: ThermoElasticModel,
    time_s: np.ndarray,
    inputs: np.ndarray,
    *,
    scheme: str = DEFAULT_SCHEME,
    theta: float | None = None,
    tolerance: TimeTolerance | None = None,
    initial: str | np.ndarray = "steady",
    store_steps: tuple[int, ...] | None = None,
    progress: bool = False,
) -> SimulationResult:
    """Integrate the model over ``time_s`` with an input array in model input order (what ``model.simulate`` runs).

    Parameters
    ----------
    model : the assembled FE model
    time_s : strictly increasing loads and output times [s]
    inputs : heat powers [W] and air temperature rises over the reference [K] per time (nt × nu)
    scheme : ``"trbdf2"`` (default): TR-BDF2 sub-steps of the loads intervals, refined until the estimated time
        error meets ``tolerance`` (the estimate is ``result.time_error``); ``"theta"``: the θ-method on the times
        ``time_s`` themselves, not error-controlled
    theta : θ of the θ-method, in [0.5, 1] (default 1, backward Euler); θ-method only
    tolerance : accepted time error of the outputs (default :data:`DEFAULT_TOLERANCE`); TR-BDF2 only
    initial : ``"steady"`` (steady state of the first inputs), ``"reference"`` (x = 0) or a state [K]
    store_steps : indices of loads times whose full field is kept
    progress : show a progress bar over the steps
    """
    theta = check_scheme(scheme, theta, tolerance)
    if theta is None:
        result, estimate = integrate_controlled(model, time_s, inputs, DEFAULT_TOLERANCE if tolerance is None else
                                                tolerance, initial=initial, store_steps=store_steps, progress=progress)
        return dataclasses.replace(result, time_error=estimate.as_dict())
    U = _model_inputs(model, inputs)
    x0 = initial_state(initial, model.n, lambda: steady_state(model, U[0]))
    (sens, drift), fields, timings = integrate_theta(
        model.M,
        model.A(),
        model.input_matrix(),
        (model.C, model.G),
        time_s,
        U,
        theta=theta,
        x0=x0,
        coords=model.coords_m,
        cache=model._cache,
        store_steps=store_steps,
        progress=progress,
    )
    return SimulationResult(
        time_s=np.asarray(time_s, float),
        sensors_degC=sens + model.reference_temperature_degC,
        drift_um=drift * 1e6,
        fields_K=fields,
        timings_s=timings,
        sensor_names=model.sensor_names,
    )


def solver_backends(model: ThermoElasticModel) -> dict[str, str]:
    """The sparse solvers a model used so far: ``{"heat": ..., "elastic": ...}``.

    ``heat`` names the backends of the cached factorisations (comma-separated when
    they differ, empty before the first solve); ``elastic`` the backend of the
    adjoint solves for the drift rows.
    """
    heat = sorted({f.backend for f in model._cache.values() if isinstance(f, Factor)})
    return {"heat": ", ".join(heat), "elastic": str(model.timings_s.get("elastic_backend", ""))}


def step_factor_for_benchmark(model: ThermoElasticModel, dt_s: float, theta: float) -> Factor:
    """The cached factorisation of M/Δt + θA that :func:`integrate_theta` used (for timing the bare solves)."""
    return model._cache[("step", round(float(dt_s), 9), float(theta))]
