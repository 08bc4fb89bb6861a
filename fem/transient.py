"""Transient and steady thermal solves of an assembled model (θ-method).

``(M/Δt + θA) x_{k+1} = (M/Δt − (1−θ)A) x_k + Bu (θ u_{k+1} + (1−θ) u_k)``

θ = 1 (backward Euler, the default) is L-stable: no oscillation after load
steps at large Δt.  θ = 0.5 (Crank–Nicolson) is second order for smooth loads
and small steps.  One factorisation per (Δt, θ), cached on the model, so
repeated calls and non-uniform time grids with a few distinct steps stay cheap.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from hybridcomp.fem.model import ThermoElasticModel
from hybridcomp.fem.solvers import Factor, factorize_spd
from hybridcomp.fem.timestep import _loop_start, _progress_bar
from hybridcomp.models.simulation import SimulationResult, initial_state

log = logging.getLogger(__name__)


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


def integrate(
    M,
    A,
    Bu: np.ndarray,
    outputs: tuple,
    time_s: np.ndarray,
    inputs: np.ndarray,
    theta: float = 1.0,
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
    t = np.asarray(time_s, float)
    U = np.asarray(inputs, float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError("time_s must be a non-empty vector")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise ValueError(f"time_s must increase strictly; step {k} goes from {t[k - 1]} s to {t[k]} s")
    if U.shape != (t.size, Bu.shape[1]):
        raise ValueError(f"inputs must be ({t.size}, {Bu.shape[1]}), got {U.shape}")
    if not 0.5 <= theta <= 1.0:
        raise ValueError(f"theta must be in [0.5, 1] for an unconditionally stable scheme, got {theta}")
    n = M.shape[0]
    # No dense BLAS call inside the loop: numpy's OpenBLAS threads spin after each call and starve
    # the sparse solver's own BLAS threads (measured 8x slower steps on 2 cores).  Sparse products
    # and einsum do not touch BLAS.
    Bu = sp.csr_matrix(Bu)
    nt = t.size
    st = _loop_start(n, nt, outputs, x0, cache, store_steps)
    products, x, cache, store, ys, fields = st.products, st.x, st.cache, st.store, st.ys, st.fields
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
        for y, prod in zip(ys, products):
            y[k] = prod(x)
        if k in store:
            fields[k] = x.copy()
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    total = time.perf_counter() - t0_all
    return ys, fields, {"factorisation": t_factor, "triangular_solves": t_solve, "stepping_total": total - t_factor}


def simulate(
    model: ThermoElasticModel,
    time_s: np.ndarray,
    inputs: np.ndarray,
    theta: float = 1.0,
    initial: str | np.ndarray = "steady",
    store_steps: tuple[int, ...] | None = None,
    progress: bool = False,
) -> SimulationResult:
    """Integrate the model over ``time_s`` with inputs ``inputs`` (nt × nu) in model input order.

    Parameters
    ----------
    time_s : strictly increasing output times [s]
    inputs : heat powers [W] and air temperature rises over the reference [K] per time
    theta : θ of the θ-method, in [0.5, 1]
    initial : ``"steady"`` (steady state of the first inputs), ``"reference"`` (x = 0) or a state [K]
    store_steps : indices of steps whose full field is kept
    """
    U = np.asarray(inputs, float)
    if U.ndim != 2 or U.shape[1] != len(model.input_names):
        raise ValueError(f"inputs must have {len(model.input_names)} columns ({model.input_names}), got shape {U.shape}")
    x0 = initial_state(initial, model.n, lambda: steady_state(model, U[0]))
    (sens, drift), fields, timings = integrate(
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
    """The cached factorisation of M/Δt + θA that :func:`simulate` used (for timing the bare solves)."""
    return model._cache[("step", round(float(dt_s), 9), float(theta))]
