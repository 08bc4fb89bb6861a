"""Reduce an assembled FE machine model and check the result against FE.

Outputs of a machine ROM: the sensor temperature rises [K] then the three
TCP-minus-table drifts dx, dy, dz [m]; :func:`split_outputs` turns them into
``sensors_degC`` and ``drift_um`` (the outputs.csv contract).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from hybridcomp.fem.operators import ThermalOperators
from hybridcomp.models.layout import DRIFT_OUTPUTS, LoadsColumnError
from hybridcomp.rom.krylov import ExpansionPoint, Reduction, Reductor, ThermalSystem, orthonormal_extension, project
from hybridcomp.rom.reduced import ReducedModel, RomInputError

log = logging.getLogger(__name__)

DRIFT_NAMES = DRIFT_OUTPUTS


def system_from_model(model) -> ThermalSystem:
    """The parametric thermal system of a :class:`~hybridcomp.fem.model.ThermoElasticModel`.

    Outputs are the sensor rows ``C`` [K/K] and the drift rows ``G`` [m/K].
    """
    C = np.vstack([model.C.toarray() if sp.issparse(model.C) else np.asarray(model.C), np.asarray(model.G)])
    return ThermalSystem(ThermalOperators(
        M=sp.csr_matrix(model.M), K=sp.csr_matrix(model.K), H=tuple(sp.csr_matrix(H) for H in model.H),
        h_W_m2K=np.asarray(model.h_W_m2K, float), B=np.asarray(model.B, float), Hb=np.asarray(model.Hb, float), C=C,
        input_names=tuple(model.input_names), output_names=tuple(model.sensor_names) + DRIFT_NAMES,
    ), coords=model.coords_m)


def h_samples(h_nominal: np.ndarray, h_range: tuple[float, float], n_random: int = 4, seed: int = 0) -> np.ndarray:
    """Nominal, all zones at the range ends, and ``n_random`` log-uniform samples inside [W/(m^2 K)]."""
    lo, hi = h_range
    if not 0 < lo <= 1 <= hi:
        raise ValueError(f"h range must satisfy 0 < low ≤ 1 ≤ high (factors of nominal), got {h_range}")
    h0 = np.asarray(h_nominal, float)
    rows = [h0]
    if hi > lo:
        rows += [lo * h0, hi * h0]
        rng = np.random.default_rng(seed)
        rows += [h0 * np.exp(rng.uniform(np.log(lo), np.log(hi), h0.size)) for _ in range(n_random)]
    return np.array(rows)


def to_reduced(system: ThermalSystem, red: Reduction, meta: dict, keep_basis: bool = True,
               disturbances: tuple[np.ndarray, tuple[str, ...]] | None = None) -> ReducedModel:
    """The reduced model of a projection basis.

    ``disturbances``: FE disturbance heat columns (n × d) and their names, projected with the basis
    (:attr:`ReducedModel.D`).
    """
    P = project(system, red.V)
    D, names = (None, ()) if disturbances is None else (red.V.T @ disturbances[0], tuple(disturbances[1]))
    return ReducedModel(
        ThermalOperators(M=P["M"], K=P["K"], H=P["H"], h_W_m2K=np.asarray(system.h, float), B=P["B"], Hb=P["Hb"],
                         C=P["C"], input_names=system.input_names, output_names=system.output_names),
        V=red.V if keep_basis else None, D=D, disturbance_names=names, meta=meta,
    )


def split_outputs(rom: ReducedModel, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Machine ROM outputs (nt × q) → sensor temperatures [°C] and drift [µm]."""
    outputs = rom.output_layout()
    return outputs.take(Y, "sensors") + rom.layout().reference_temperature_degC, outputs.take(Y, "drift") * 1e6


def inputs_from_columns(rom: ReducedModel, names, values: np.ndarray, source: str = "loads") -> np.ndarray:
    """Model inputs (nt × nu) from named columns: ``*_W`` powers [W], ``*_degC`` air temperatures [°C].

    A missing column is zero power or the reference temperature; a column the
    ROM has no input for is an error naming it (:meth:`InputLayout.inputs`).
    """
    try:
        return rom.layout().inputs(names, values, source)
    except LoadsColumnError as exc:
        raise RomInputError(str(exc)) from None


@dataclass(frozen=True)
class CheckResult:
    """Error of a ROM against FE on one load case.

    Attributes
    ----------
    max_sensor_error_K : largest sensor-temperature difference [K]
    max_drift_error_um : largest drift difference over dx, dy, dz [µm]
    fe_theta : θ of the FE reference run (and of the ROM run, when the reduction error alone is measured)
    dt_s : FE time step [s]
    """

    max_sensor_error_K: float
    max_drift_error_um: float
    fe_theta: float
    dt_s: float

    def as_dict(self) -> dict:
        return {"max_sensor_error_K": self.max_sensor_error_K, "max_drift_error_um": self.max_drift_error_um,
                "fe_theta": self.fe_theta, "dt_s": self.dt_s}


def fe_reference(model, time_s, inputs, theta: float = 0.5):
    """FE outputs (sensors [°C], drift [µm]) for the check: Crank–Nicolson by default (second order in Δt)."""
    from hybridcomp.fem.stepping import integrate_inputs

    res = integrate_inputs(model, time_s, inputs, scheme="theta", theta=theta)
    return res.sensors_degC, res.drift_um


def theta_outputs(rom: ReducedModel, time_s, inputs, theta: float) -> np.ndarray:
    """The reduced model integrated by the FE's own θ-method (uniform Δt), for isolating the reduction error.

    With the same time scheme on both sides, ROM minus FE is the reduction
    error alone; :meth:`ReducedModel.simulate` (exact) minus FE adds the FE's
    time error.
    """
    from scipy.signal import lfilter

    t = np.asarray(time_s, float)
    U = np.asarray(inputs, float)
    dt = np.diff(t)
    if not np.allclose(dt, dt[0], rtol=1e-9, atol=0.0):
        raise RomInputError("theta_outputs needs a uniform time grid")
    lam, Phi = rom._modes()
    W = U @ (Phi.T @ rom.input_matrix()).T  # modal forcing (nt × r)
    z0 = Phi.T @ (rom.M @ rom.steady_state(U[0]))
    h = dt[0]
    a = (1 - (1 - theta) * lam * h) / (1 + theta * lam * h)
    a[np.abs(a) < 1e-22] = 0.0  # no subnormal products
    F = h * (theta * W[1:] + (1 - theta) * W[:-1]) / (1 + theta * lam * h)
    Z = np.empty((t.size, rom.order))
    Z[0] = z0
    for j in range(rom.order):
        Z[1:, j], _ = lfilter([1.0], [1.0, -a[j]], F[:, j], zi=[a[j] * z0[j]])
    return Z @ (rom.C @ Phi).T


def compare(rom: ReducedModel, time_s, inputs, fe: tuple[np.ndarray, np.ndarray], theta: float | None) -> CheckResult:
    """ROM minus FE on a load case: the exact ROM (``theta=None``) or the ROM by the FE's θ-method."""
    Y = rom.integrate(time_s, inputs)[0] if theta is None else theta_outputs(rom, time_s, inputs, theta)
    s, d = split_outputs(rom, Y)
    dt = float(np.max(np.diff(time_s))) if len(time_s) > 1 else 0.0
    return CheckResult(float(np.abs(s - fe[0]).max()), float(np.abs(d - fe[1]).max()), theta, dt)


def gramian_directions(system: ThermalSystem, V: np.ndarray, h_list, input_scale: np.ndarray,
                       output_tol: np.ndarray) -> np.ndarray:
    """Directions of ``span(V)`` (n × k), most important first.

    Eigenvectors of the controllability and observability Gramians of the projected system, interleaved.

    The Gramians are summed over ``h_list``; inputs are scaled by ``input_scale``, outputs by
    ``1/output_tol``, so both are measured against the tolerances.  Any prefix of the result spans a
    one-sided (Galerkin) basis: the reduced system stays symmetric, stable and affine in h.
    """
    import scipy.linalg as la

    P = project(system, V)
    E = P["M"]
    L = la.cholesky(E, lower=True)
    Li = la.solve_triangular(L, np.eye(E.shape[0]), lower=True)
    Pc = np.zeros_like(E)
    Qo = np.zeros_like(E)
    for h in h_list:
        h = np.asarray(h, float)
        A = -Li @ (P["K"] + np.einsum("i,ijk->jk", h, P["H"])) @ Li.T
        A = 0.5 * (A + A.T)
        B = Li @ (np.hstack([P["B"], P["Hb"] * h[None, :]]) * input_scale[None, :])
        C = (P["C"] / output_tol[:, None]) @ Li.T
        Pc += la.solve_continuous_lyapunov(A, -B @ B.T)
        Qo += la.solve_continuous_lyapunov(A, -C.T @ C)
    up = la.eigh(0.5 * (Pc + Pc.T))[1][:, ::-1]
    uq = la.eigh(0.5 * (Qo + Qo.T))[1][:, ::-1]
    inter = np.empty((E.shape[0], 2 * E.shape[0]))
    inter[:, 0::2] = up
    inter[:, 1::2] = uq
    return V @ la.solve_triangular(L.T, inter, lower=False)


def _reduce_h2(system, reductor, samples, scale, tol, order, max_order, step, accept, fastest_time_s, maxiter,
               progress=False, hold_steady=True, surrogate_fastest_time_s=None):
    """The H2-optimal one-sided basis (see :func:`reduce_model`): a Reduction and the method text.

    ``hold_steady``: keep the ``s = 0`` block in the basis when the order allows (steady states exact).
    ``surrogate_fastest_time_s``: the surrogate's shortest time scale (default: 5 s or ``fastest_time_s``).
    """
    from hybridcomp.rom.h2 import h2_optimal_basis

    h_list = samples[:3]
    s0 = orthonormal_extension(np.zeros((system.n, 0)), reductor._blocks(0.0, system.h, 1), reductor.deflation_tol)
    n_first = s0.shape[1]
    # surrogate: a rational Krylov basis resolving down to 5 s, well above the reduced order (its own H2 error
    # is orders of magnitude below the reduced model's)
    sur_ft = min(5.0, fastest_time_s) if surrogate_fastest_time_s is None else surrogate_fastest_time_s
    sur_red = Reductor(system, tol, scale, h_list, n_s=12, fastest_time_s=sur_ft)

    surrogate = np.zeros((system.n, 0))

    def basis_of(r):
        nonlocal surrogate
        # (a nominal-h surrogate of the 150 mm mesh: own relative H2 error 9e-5 at order 300, 1e-7 at 500)
        N = min(system.n, max(500, 4 * r))
        if surrogate.shape[1] < N:  # the Krylov bases are nested: build once, grow only when a larger one is needed
            surrogate = sur_red.reduce(order=N).V
        V_big = surrogate[:, :N]
        fixed = s0 if hold_steady and r >= n_first else None
        return h2_optimal_basis(system, V_big, r, h_list, scale, 1.0 / tol, maxiter=maxiter, fixed=fixed,
                                progress=progress)

    point = ExpansionPoint(0.0, tuple(float(v) for v in system.h), 1)
    if order is not None:
        V = basis_of(int(order))
        pts = (point,) if hold_steady and order >= n_first else ()
        return Reduction(V, pts, float("nan"), ()), "H2-optimal one-sided basis"
    r = n_first
    while True:
        V = basis_of(r) if r > n_first else s0
        if accept(V) or r >= max_order:
            break
        r = min(max_order, r + step)
    return (Reduction(V, (point,), float("nan"), ()),
            f"s = 0 block + {V.shape[1] - n_first} H2-optimal one-sided directions")


def reduce_model(
    model,
    *,
    tol_K: float = 0.05,
    tol_um: float = 0.2,
    order: int | None = None,
    h_range: tuple[float, float] = (0.5, 2.0),
    check_loads=None,
    check_theta: float = 0.5,
    safety: float = 0.5,
    fastest_time_s: float = 60.0,
    keep_basis: bool = True,
    max_order: int = 400,
    chunk: int | None = 8,
    compress: bool = True,
    compress_step: int = 4,
    basis: str = "krylov",
    h2_maxiter: int = 1500,
    progress: bool = False,
) -> ReducedModel:
    """Reduce a machine's FE model to a tolerance or an order, checked against FE on a load case.

    Parameters
    ----------
    model : assembled :class:`~hybridcomp.fem.model.ThermoElasticModel`
    tol_K : sensor-temperature tolerance [K]
    tol_um : TCP-drift tolerance [µm]
    order : reduce to exactly this order instead of to the tolerance
    h_range : heat-transfer coefficients covered, as factors of nominal (low, high) [-]
    check_loads : :class:`~hybridcomp.fem.loads.Loads` for the FE check (default: ``example_loads`` 16 h at 60 s)
    check_theta : θ of the FE reference runs (0.5: Crank–Nicolson, second order in Δt)
    safety : the check must pass at ``safety`` × the tolerances (margin for h between the checked values) [-]
    fastest_time_s : shortest time scale to resolve [s]
    keep_basis : keep V (n × r) for reconstructing full fields
    chunk : after the first block, add directions this many at a time (None: whole blocks)
    compress : (tolerance mode) also try a second stage: a larger Krylov basis compressed, behind its
        first block, to the dominant directions of its controllability and observability Gramians
        (summed over nominal h and both range ends, inputs scaled by their range, outputs by 1/tol);
        the smaller of the two models that passes the FE check is kept
    compress_step : directions added per compression step
    basis : ``"krylov"`` (greedy rational Krylov, then the Gramian compression) or ``"h2"``: the one-sided
        basis with the smallest H2 error found by :func:`hybridcomp.rom.h2.h2_optimal_basis` inside a
        large Krylov surrogate (errors summed over nominal h and both range ends, inputs scaled by their
        range in the check case, outputs by 1/tolerance); it contains the ``s = 0`` block whenever the
        order allows (steady states exact), and in tolerance mode grows by ``chunk`` directions until the
        FE check passes.  Both are one-sided Galerkin projections: symmetric, stable, affine in h.
    h2_maxiter : L-BFGS iterations per H2-optimal basis
    progress : with ``basis="h2"``: a progress bar (stderr) over each basis's L-BFGS iterations

    Blocks are added greedily (see :class:`~hybridcomp.rom.krylov.Reductor`)
    until the reduced model, integrated by the same θ-method as FE (so that
    the difference is the reduction error alone), reproduces the FE runs of the check load case at
    nominal h and with every zone at the low and at the high end of
    ``h_range`` within ``safety`` × the tolerances, or the frequency-domain
    estimate says so over all sampled h.  The achieved errors against FE are
    in ``meta['check']``.
    """
    from hybridcomp.fem.loads import example_loads

    if not (tol_K > 0 and tol_um > 0):
        raise ValueError(f"tolerances must be positive, got tol_K={tol_K}, tol_um={tol_um}")
    if basis not in ("krylov", "h2"):
        raise ValueError(f"basis must be 'krylov' or 'h2', got {basis!r}")
    t0 = time.perf_counter()
    machine = model.machine
    system = system_from_model(model)
    loads = check_loads if check_loads is not None else example_loads(machine, 16.0, 60.0)
    U = machine.layout().inputs(loads)
    scale = np.abs(U).max(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    s_count = len(model.sensor_names)
    tol = np.r_[np.full(s_count, tol_K), np.full(3, tol_um * 1e-6)]
    samples = h_samples(model.h_W_m2K, h_range)
    reductor = Reductor(system, tol, scale, samples, fastest_time_s=fastest_time_s)
    check_h = samples[:3]
    case = _CheckCase(system, loads.time_s, U, check_h, _fe_references(model, check_h, loads.time_s, U, check_theta),
                      _base_meta(model, h_range, tol_K, tol_um), check_theta)

    def accept(V):
        res = _checks(case, V, case.theta)
        log.info("order %d: FE check %s", V.shape[1],
                 [(round(c.max_sensor_error_K, 4), round(c.max_drift_error_um, 4)) for c in res])
        return all(c.max_sensor_error_K <= safety * tol_K and c.max_drift_error_um <= safety * tol_um for c in res)

    if basis == "h2":
        red, method = _reduce_h2(system, reductor, samples, scale, tol, order, max_order, chunk or 8, accept,
                                 fastest_time_s, h2_maxiter, progress)
    else:
        red = reductor.reduce(target=0.5, order=order, max_order=max_order, accept=accept, chunk=chunk)
        method = "greedy Krylov"
    if basis == "krylov" and compress and order is None and red.points[0].complete:
        red, method = _compress(system, reductor, red, method, samples, scale, tol, max_order, compress_step, accept)
    meta = _reduction_meta(case, red, method, tol_K, tol_um)
    meta["reduction_time_s"] = time.perf_counter() - t0
    return to_reduced(system, red, meta, keep_basis, model.disturbance_columns())


@dataclass(frozen=True)
class _CheckCase:
    """The FE check of a reduction: the load case, its inputs, the checked h and the FE outputs at each."""

    system: ThermalSystem
    time_s: np.ndarray
    U: np.ndarray
    check_h: np.ndarray
    fe: list
    base_meta: dict
    theta: float


def _fe_references(model, check_h, time_s, U, theta: float) -> list:
    """FE outputs (sensors [°C], drift [µm]) of the check load case at each checked set of coefficients h."""
    fe = []
    for h in check_h:
        variant = model.with_htc(**dict(zip(model.zone_names, map(float, h))))
        fe.append(fe_reference(variant, time_s, U, theta))
    return fe


def _base_meta(model, h_range, tol_K: float, tol_um: float) -> dict:
    """What a reduced model records of its FE model and its tolerances ([K], [µm])."""
    machine = model.machine
    return {
        "machine": {"name": machine.name, "file": Path(machine.source).name, "sha256": machine.sha256},
        "pose_mm": dict(model.mesh.pose_mm),
        "nodes": model.n,
        "element_size_mm": machine.mesh.element_size_mm,
        "reference_temperature_degC": machine.reference_temperature_degC,
        "n_sensors": len(model.sensor_names),
        "h_range": list(h_range),
        "h_nominal_W_m2K": [float(v) for v in model.h_W_m2K],
        "tol_K": tol_K,
        "tol_um": tol_um,
    }


def _checks(case: _CheckCase, V: np.ndarray, theta: float | None) -> list[CheckResult]:
    """The reduced model of basis ``V`` against FE at every checked h, stepped by the θ-method (None: exactly)."""
    rom = to_reduced(case.system, Reduction(V, (), 0.0, ()), case.base_meta, keep_basis=False)
    return [compare(rom.with_operators(h_W_m2K=h), case.time_s, case.U, ref, theta)
            for h, ref in zip(case.check_h, case.fe)]


def _compress(system, reductor, red: Reduction, method: str, samples, scale, tol, max_order: int, compress_step: int,
              accept) -> tuple[Reduction, str]:
    """The second stage: a larger Krylov basis compressed to its dominant Gramian directions.

    Behind the (exact-steady-state) first block; kept only if the FE check passes at a lower order, else ``red``
    and ``method`` are returned as they are.
    """
    big = reductor.reduce(order=min(max_order, max(2 * red.V.shape[1], 200)))
    n_first = big.history[0][0] if big.points[0].complete else 0
    first = big.V[:, :n_first]
    D = gramian_directions(system, big.V, samples[:3], scale, tol)
    for k in range(compress_step, min(D.shape[1], red.V.shape[1] - n_first), compress_step):
        V = np.hstack([first, orthonormal_extension(first, D[:, :k], reductor.deflation_tol)])
        if V.shape[1] >= red.V.shape[1]:
            break
        if accept(V):
            # only the first block's point is still interpolated exactly
            red = Reduction(V, big.points[:1], red.estimate, red.history)
            method = (f"Krylov order {big.V.shape[1]} compressed to the first block + {V.shape[1] - n_first} "
                      "Gramian directions")
            break
    return red, method


def _reduction_meta(case: _CheckCase, red: Reduction, method: str, tol_K: float, tol_um: float) -> dict:
    """A reduced model's metadata: its basis, how it was found and its errors against FE ([K], [µm])."""
    res = _checks(case, red.V, case.theta)
    exact = _checks(case, red.V, None)
    return {
        **case.base_meta,
        "order": red.V.shape[1],
        "method": method,
        "expansion_points": [{"s_1_s": p.s, "h_W_m2K": list(p.h), "moments": p.moments, "complete": p.complete}
                             for p in red.points],
        "estimate": red.estimate if np.isfinite(red.estimate) else None,
        "history": [list(h) for h in red.history],
        "check": {
            "load_case": f"{len(case.time_s)} rows over {case.time_s[-1] / 3600:.3g} h",
            "fe_theta": case.theta,
            "dt_s": res[0].dt_s,
            "h_W_m2K": [list(map(float, h)) for h in case.check_h],
            "max_sensor_error_K": [c.max_sensor_error_K for c in res],
            "max_drift_error_um": [c.max_drift_error_um for c in res],
            "passed": bool(all(c.max_sensor_error_K <= tol_K and c.max_drift_error_um <= tol_um for c in res)),
            "exact_rom_vs_fe": {
                "note": "the ROM's exact stepping against the FE θ-method: adds the FE time error",
                "max_sensor_error_K": [c.max_sensor_error_K for c in exact],
                "max_drift_error_um": [c.max_drift_error_um for c in exact],
            },
        },
    }
