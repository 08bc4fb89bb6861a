"""TR-BDF2 and the tolerance-controlled default of ``hybridcomp simulate`` (fem/stepping.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp

from hybridcomp.cli import main
from hybridcomp.fem.loads import Loads, example_loads, read_loads, write_loads
from hybridcomp.fem.stepping import (
    DEFAULT_TOLERANCE,
    TimeTolerance,
    amplification,
    error_bound,
    integrate_controlled,
    integrate_theta,
    integrate_trbdf2,
)

COARSE = ["--element-size-mm", "150", "--no-progress"]


# -- a small SPD pair with an exact solution --------------------------------------------------------
def heat_chain(n: int = 30):
    """A 1D heat chain with a consistent mass matrix and convection at one end: M, A (SPD), one input at the other end."""
    main_m = np.full(n, 4.0)
    main_m[[0, -1]] = 2.0
    M = sp.diags([main_m, np.ones(n - 1), np.ones(n - 1)], [0, -1, 1]) / 6.0 / n
    main_a = np.full(n, 2.0)
    main_a[[0, -1]] = 1.0
    main_a[-1] += 0.5  # convection to the reference at the far end
    A = sp.diags([main_a, -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1]) * n * 0.01
    Bu = np.zeros((n, 2))
    Bu[0, 0] = 1.0
    Bu[n // 2, 1] = 0.5
    return sp.csr_matrix(M), sp.csr_matrix(A), Bu


def exact_piecewise_linear(M, A, Bu, time_s, inputs, x0):
    """The exact solution at ``time_s`` for inputs linear between the samples, by the generalised eigenproblem
    A v = λ M v (modes M-orthonormal): each mode solves q' + λq = a + sτ exactly on every interval."""
    lam, V = la.eigh(A.toarray(), M.toarray())
    q = V.T @ (M @ x0)
    out = [V @ q]
    for k in range(1, len(time_s)):
        tau = time_s[k] - time_s[k - 1]
        a = V.T @ (Bu @ inputs[k - 1])
        s = V.T @ (Bu @ (inputs[k] - inputs[k - 1])) / tau
        e = np.exp(-lam * tau)
        q = e * q + a * (1 - e) / lam + s * (tau / lam - (1 - e) / lam**2)
        out.append(V @ q)
    return np.array(out)


def kinked_inputs(time_s, seed=1):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 1, time_s.size), 0.5 + 0.5 * np.sin(time_s / 7.0)])


def test_trbdf2_is_second_order_against_the_exact_solution():
    M, A, Bu = heat_chain()
    t = np.linspace(0.0, 60.0, 13)  # loads every 5 s, kinks at every sample; modes from 0.023 to 110 1/s
    U = kinked_inputs(t)
    x0 = np.linspace(1.0, 0.0, M.shape[0])
    exact = exact_piecewise_linear(M, A, Bu, t, U, x0)
    C = sp.identity(M.shape[0], format="csr")
    errors = []
    for m in (1, 2, 4, 8, 16):
        (X,), _, _ = integrate_trbdf2(M, A, Bu, (C,), t, U, substeps=m, x0=x0)
        errors.append(np.abs(X - exact).max())
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert errors[-1] < 1e-4 * np.abs(exact).max()
    assert np.all(np.abs(rates[1:] - 2.0) <= 0.35), rates  # from 2 sub-steps on (h λ_max = 14 at 1 sub-step)


def test_dense_and_sparse_output_rows_agree():
    M, A, Bu = heat_chain(10)
    t = np.linspace(0.0, 20.0, 5)
    U = kinked_inputs(t)
    G = np.arange(20.0).reshape(2, 10)
    (Ys, Yd), _, _ = integrate_trbdf2(M, A, Bu, (sp.csr_matrix(G), G), t, U, substeps=3)
    np.testing.assert_allclose(Yd, Ys, rtol=1e-13)


# -- L-stability ------------------------------------------------------------------------------------
def test_amplification_is_l_stable():
    assert abs(amplification(-1e9)) < 1e-8  # R(−∞) = 0: stiff modes are damped in one step
    x = np.concatenate([-np.logspace(-3, 9, 200), [0.0]])
    y = np.logspace(-3, 9, 200)
    z = (x[:, None] + 1j * y[None, :]).ravel()
    assert np.all(np.abs(amplification(z)) <= 1 + 1e-12)  # A-stable on the closed left half plane
    small = np.array([-1e-2, -1e-3])
    np.testing.assert_allclose(amplification(small), np.exp(small), rtol=1e-6)  # consistent


def test_no_ringing_after_a_power_step_at_huge_steps():
    """Steady at full power, then the power drops to zero; at steps 2·10^5 times the slowest time constant the
    state must vanish, not swing to the opposite sign and back as Crank–Nicolson's does."""
    M, A, Bu = heat_chain()
    t = np.array([0.0, 1e-3, 1e7, 2e7, 3e7])
    U = np.array([[1.0, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    x0 = sp.linalg.spsolve(sp.csc_matrix(A), Bu @ U[0])
    C = sp.identity(M.shape[0], format="csr")
    (X,), _, _ = integrate_trbdf2(M, A, Bu, (C,), t[1:], U[1:], x0=x0)  # starts just after the drop
    # |R(z)| ≈ 4.8/|z| for large |z| (R → 0): 2e-5 after the first step at the slowest mode, then gone
    assert np.abs(X[1]).max() < 1e-4 * np.abs(x0).max()
    assert np.abs(X[2:]).max() < 1e-8 * np.abs(x0).max()
    # Crank-Nicolson (not L-stable) rings here: the check can fail
    (Xcn,), _, _ = integrate_theta(M, A, Bu, (C,), t[1:], U[1:], theta=0.5, x0=x0)
    assert np.abs(Xcn[1:]).max(axis=1).min() > 0.9 * np.abs(x0).max()
    assert np.all(np.sign(Xcn[1]) == -np.sign(Xcn[2])) and np.all(np.sign(Xcn[2]) == -np.sign(Xcn[3]))


# -- plain functions --------------------------------------------------------------------------------
def test_error_bound_of_first_and_second_order_sequences():
    exact, h = 1.0, 0.1
    for order, ratio in ((1, 1.0), (2, 3.0)):
        coarse, fine = exact + 3 * h**order, exact + 3 * (h / 2) ** order
        assert error_bound(np.array([fine]), np.array([coarse])) == pytest.approx(ratio * (fine - exact))
    with pytest.raises(ValueError, match=r"differ in shape: \(2,\) vs \(3,\)"):
        error_bound(np.zeros(2), np.zeros(3))


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"sensor_K": 0.0}, "sensor_K must be a positive number, got 0.0"),
    ({"drift_um": float("nan")}, "drift_um must be a positive number, got nan"),
])
def test_bad_tolerances_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TimeTolerance(**kwargs)


def test_bad_substeps_are_named():
    M, A, Bu = heat_chain(5)
    with pytest.raises(ValueError, match="substeps must be a positive integer, got 0"):
        integrate_trbdf2(M, A, Bu, (), np.array([0.0, 1.0]), np.zeros((2, 2)), substeps=0)


# -- the FE model -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def coarse_model(machine):
    from hybridcomp.fem.model import build_model

    return build_model(machine, None, 150.0)


@pytest.fixture(scope="module")
def short_day(machine):
    """2 h of the example day in 5 min samples: hourly blocks switch the powers within one sample."""
    return example_loads(machine, duration_h=2.0, dt_s=300.0)


def fine_reference(model, loads: Loads, substeps: int = 64):
    """Crank–Nicolson at 1/substeps of the loads step (a different scheme than the one checked), at the loads times."""
    fine = loads.resample(float(np.diff(loads.time_s)[0]) / substeps)
    res = model.simulate(fine, scheme="theta", theta=0.5)
    idx = np.searchsorted(fine.time_s, loads.time_s)
    np.testing.assert_allclose(fine.time_s[idx], loads.time_s)
    return res.sensors_degC[idx], res.drift_um[idx]


@pytest.fixture(scope="module")
def reference(coarse_model, short_day):
    return fine_reference(coarse_model, short_day)


@pytest.mark.slow
@pytest.mark.parametrize("tolerance", [DEFAULT_TOLERANCE, TimeTolerance(sensor_K=2e-4, drift_um=1e-3)])
def test_estimate_bounds_the_true_error_on_the_fe_model(coarse_model, short_day, reference, tolerance):
    res, est = integrate_controlled(coarse_model, short_day.time_s, coarse_model.layout().inputs(short_day), tolerance)
    true_K = np.abs(res.sensors_degC - reference[0]).max()
    true_um = np.abs(res.drift_um - reference[1]).max()
    assert est.met and est.sensor_K <= tolerance.sensor_K and est.drift_um <= tolerance.drift_um
    assert true_K <= est.sensor_K and true_um <= est.drift_um, (true_K, est.sensor_K, true_um, est.drift_um)
    # the difference of the two runs is about 3x the finer run's error once second order: an estimate, not a loose bound
    assert est.sensor_K <= 5 * true_K and est.drift_um <= 5 * true_um
    assert est.step_sizes_s == (300.0 / est.substeps,) and est.steps == 24 * est.substeps
    if tolerance is not DEFAULT_TOLERANCE:
        assert est.runs > 2  # the tight tolerance needed refinement


@pytest.mark.slow
def test_a_tolerance_out_of_reach_is_reported_not_met(coarse_model, short_day, caplog):
    _, est = integrate_controlled(coarse_model, short_day.time_s, coarse_model.layout().inputs(short_day),
                                 TimeTolerance(sensor_K=1e-12, drift_um=1e-12), max_substeps=4)
    assert not est.met and est.substeps == 4 and est.runs == 3
    assert "did not meet the time tolerance" in caplog.text


@pytest.mark.slow
def test_cli_default_meets_its_tolerance_and_reports_it(machine, coarse_model, short_day, tmp_path):
    write_loads(tmp_path / "loads.csv", short_day)
    reference = fine_reference(coarse_model, read_loads(tmp_path / "loads.csv", machine))  # the CSV rounds to 6 digits
    out = tmp_path / "run"
    assert main(["simulate", "--machine", "vmc800", "--loads", str(tmp_path / "loads.csv"), "--out", str(out), *COARSE]) == 0
    data = np.loadtxt(out / "outputs.csv", delimiter=",", skiprows=1)
    assert coarse_model.n == json.loads((out / "run.json").read_text())["nodes"]  # the same mesh as the reference
    err_K = np.abs(data[:, 1:9] - reference[0]).max()
    err_um = np.abs(data[:, 9:12] - reference[1]).max()
    info = json.loads((out / "run.json").read_text())["time"]
    assert info["scheme"] == "TR-BDF2" and info["met"] is True
    assert info["tolerance_sensor_K"] == DEFAULT_TOLERANCE.sensor_K and info["tolerance_drift_um"] == DEFAULT_TOLERANCE.drift_um
    assert err_K <= DEFAULT_TOLERANCE.sensor_K and err_um <= DEFAULT_TOLERANCE.drift_um
    assert err_K <= info["estimate_sensor_K"] and err_um <= info["estimate_drift_um"]
    assert info["steps"] == 24 * info["substeps_per_interval"] and info["step_sizes_s"] == [300.0 / info["substeps_per_interval"]]
