"""The Krylov reduced model against exact references: moments, FE steady state, analytic stepping, FE transients.

Coarse mesh (150 mm, ~4,000 nodes) and a 2 h check load case, so the whole
file runs in well under a minute.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json

import numpy as np
import pytest
import scipy.io
import scipy.linalg as la
import scipy.sparse as sp

from hybridcomp.cli import main
from hybridcomp.fem.loads import (
    example_loads,
    full_power_inputs,
    input_columns,
    write_loads,
)
from hybridcomp.fem.operators import ThermalOperators
from hybridcomp.fem.stepping import steady_state
from hybridcomp.models import load_machine
from hybridcomp.models.loader import resolve_machine_path
from hybridcomp.rom import (
    ReducedModel,
    RomFileError,
    RomInputError,
    load_rom,
    load_state,
    save_rom,
    save_state,
)
from hybridcomp.rom.external import MatrixFileError, load_external, reduce_matrices
from hybridcomp.rom.krylov import Reductor, factor_spd, project
from hybridcomp.rom.machine import (
    compare,
    fe_reference,
    inputs_from_columns,
    reduce_model,
    system_from_model,
)

H_MM = 150.0
TOL_K, TOL_UM = 0.05, 0.2


@pytest.fixture(scope="module")
def model(model_150mm):
    assert model_150mm.machine.mesh.element_size_mm == H_MM
    return model_150mm


@pytest.fixture(scope="module")
def loads(machine):
    return example_loads(machine, duration_h=2.0, dt_s=60.0)


@pytest.fixture(scope="module")
def rom(model, loads):
    return reduce_model(model, tol_K=TOL_K, tol_um=TOL_UM, check_loads=loads)


def full_power(model) -> np.ndarray:
    assert tuple(model.input_names) == input_columns(model.machine)
    return full_power_inputs(model.machine)


def rel(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


# -- reduction ----------------------------------------------------------------------------------------
@pytest.mark.slow
def test_rom_meets_tolerance_on_check_case_and_reports_it(rom):
    c = rom.meta["check"]
    assert c["passed"]
    assert max(c["max_sensor_error_K"]) <= TOL_K and max(c["max_drift_error_um"]) <= TOL_UM
    assert rom.meta["order"] == rom.order < 200
    # the error is not vacuously zero: a first block alone is measurably worse (the check can fail)
    assert rom.meta["history"][0][1] > 1.0


@pytest.mark.slow
def test_transfer_function_and_derivative_match_at_expansion_points(model):
    """Hermite interpolation: H_r(s_j) = H(s_j) and H_r'(s_j) = H'(s_j) at every complete expansion point."""
    system = system_from_model(model)
    red = Reductor(system, np.ones(11), np.ones(40), system.h[None, :], n_s=4).reduce(order=110)
    P = project(system, red.V)
    complete = [p for p in red.points if p.complete]
    assert len(complete) >= 2 and any(p.s > 0 for p in complete)
    for p in complete:
        h = np.array(p.h)
        A = p.s * system.M + system.stiffness(h)
        f = factor_spd(A, system.coords)
        X = f(system.input_matrix(h))
        H_full = system.C @ X
        dH_full = -system.C @ f(system.M @ X)
        Ar = p.s * P["M"] + P["K"] + np.einsum("i,ijk->jk", h, P["H"])
        Xr = la.solve(Ar, np.hstack([P["B"], P["Hb"] * h]))
        H_red = P["C"] @ Xr
        dH_red = -P["C"] @ la.solve(Ar, P["M"] @ Xr)
        assert rel(H_red, H_full) < 1e-8, p
        assert rel(dH_red, dH_full) < 1e-8, p
    # and away from the points it does not match exactly (the test can fail)
    s_off = 0.5 * complete[1].s
    assert rel(_reduced_tf(P, s_off, system.h), system.transfer(s_off)) > 1e-12


def _reduced_tf(P, s, h):
    Ar = s * P["M"] + P["K"] + np.einsum("i,ijk->jk", h, P["H"])
    return P["C"] @ la.solve(Ar, np.hstack([P["B"], P["Hb"] * h]))


@pytest.mark.slow
def test_basis_is_orthonormal(rom):
    np.testing.assert_allclose(rom.V.T @ rom.V, np.eye(rom.order), atol=1e-10)


@pytest.mark.slow
def test_steady_state_equals_fe(model, rom):
    for u in (full_power(model), np.r_[np.zeros(36), [1.0, 2.0, -0.5, 3.0]]):
        x_fe = steady_state(model, u)
        x_r = rom.steady_state(u)
        np.testing.assert_allclose(rom.field(x_r), x_fe, rtol=0, atol=1e-8 * np.abs(x_fe).max())
        np.testing.assert_allclose(rom.outputs(x_r)[:8], model.C @ x_fe, rtol=1e-8)
        np.testing.assert_allclose(rom.outputs(x_r)[8:], model.G @ x_fe, rtol=1e-8, atol=1e-12 * np.abs(model.G @ x_fe).max())
    assert np.abs(model.C @ steady_state(model, full_power(model))).max() > 1.0  # not vacuous


@pytest.mark.slow
def test_uniform_air_rise_is_exact_for_any_h(rom):
    """All zones +1 K heat the whole machine by 1 K whatever h is: the ROM keeps that exactly, even far outside the range."""
    u = np.r_[np.zeros(36), np.ones(4)]
    for h in ({}, {"ambient": 0.1}, {"floor": 50.0, "ambient": 30.0}):
        r = rom.with_htc(**h)
        np.testing.assert_allclose(r.outputs(r.steady_state(u))[:8], 1.0, atol=1e-9)


@pytest.mark.slow
def test_stable_for_h_across_the_range_and_beyond(rom):
    h0 = dict(zip(rom.zone_names, rom.h_W_m2K))
    rng = np.random.default_rng(1)
    for f in [0.5, 2.0, 0.01, 100.0, *rng.uniform(0.5, 2.0, 4)]:
        poles = rom.with_htc(**{z: f * h for z, h in h0.items()}).poles()
        assert np.all(poles < 0), f
    mixed = rom.with_htc(**{z: h * g for (z, h), g in zip(h0.items(), rng.uniform(0.5, 2.0, 4))})
    assert np.all(mixed.poles() < 0)


@pytest.mark.slow
def test_changed_h_within_range_stays_within_tolerance(model, rom, loads):
    """h not among the sampled values (each zone differently): ROM vs FE without a new reduction."""
    h = {"ws_table": 0.6, "ws_spindle": 1.8, "floor": 1.3, "ambient": 0.7}
    h = {z: f * rom.h_W_m2K[rom.zone_names.index(z)] for z, f in h.items() if z in rom.zone_names}
    assert len(h) == 4, rom.zone_names
    changed = rom.with_htc(**h)
    U = rom.layout().inputs(loads)
    fe = fe_reference(model.with_htc(**h), loads.time_s, U, theta=0.5)
    for theta in (0.5, None):  # same scheme (reduction error alone), then the exact ROM
        c = compare(changed, loads.time_s, U, fe, theta)
        assert c.max_sensor_error_K <= TOL_K and c.max_drift_error_um <= TOL_UM, (theta, c)
    # the change of h matters far more than the tolerance: the comparison is not vacuous
    nominal = compare(rom, loads.time_s, U, fe, 0.5)
    assert nominal.max_sensor_error_K > 10 * TOL_K


# -- exact stepping -------------------------------------------------------------------------------------
def one_mode(c=2.0e4, k=4.0) -> ReducedModel:
    """One lumped mass: c T' = -k T + q, output T."""
    return ReducedModel(ThermalOperators(M=np.array([[c]]), K=np.array([[k]]), H=np.zeros((0, 1, 1)),
                                         h_W_m2K=np.zeros(0), B=np.array([[1.0]]), Hb=np.zeros((1, 0)),
                                         C=np.array([[1.0]]), input_names=("q_W",), output_names=("T",)))


def test_exact_stepping_matches_the_analytic_ramp_response_at_any_step():
    c, k = 2.0e4, 4.0
    tau = c / k
    r = one_mode(c, k)
    # a ramp q = 0.01 t: T(t) = (a/k) (t - tau (1 - e^{-t/tau}))
    for dt in (1.0, 60.0, 3600.0, 20000.0):
        t = np.arange(0, 20001.0, dt)
        Y, _ = r.integrate(t, (0.01 * t)[:, None], initial="reference")
        exact = 0.01 / k * (t - tau * (1 - np.exp(-t / tau)))
        np.testing.assert_allclose(Y[:, 0], exact, rtol=1e-10, atol=1e-12)
    # non-uniform steps (per-step path, discretisations cached per Δt) and single steps agree
    t = np.array([0.0, 10.0, 70.0, 100.0, 3700.0, 3710.0])
    Y, x = r.integrate(t, (0.01 * t)[:, None], initial="reference")
    np.testing.assert_allclose(Y[:, 0], 0.01 / k * (t - tau * (1 - np.exp(-t / tau))), rtol=1e-10, atol=1e-12)
    x1 = np.zeros(1)
    for t0, t1 in itertools.pairwise(t):
        x1 = r.step(x1, [0.01 * t0], [0.01 * t1], t1 - t0)
    np.testing.assert_allclose(x1, x, rtol=1e-12)


def test_short_runs_stepped_over_all_modes_equal_the_per_mode_filter(small_rom, loads, monkeypatch):
    """Both exact integrations of a uniform run, one step over all modes per sample (short runs) and one filter
    per mode (long runs), agree to round-off, from a steady and from a given state (on the small shared reduced
    model: the tolerance of the reduction plays no part)."""
    import hybridcomp.rom.reduced as reduced

    rom = small_rom

    U = rom.layout().inputs(loads)
    t = loads.time_s
    x0 = rom.steady_state(U[5])
    out = {}
    for name, per_mode in (("filter", 0), ("stepwise", 10**6)):
        monkeypatch.setattr(reduced, "_STEPWISE_MAX_PER_MODE", per_mode)
        out[name] = rom.integrate(t, U), rom.integrate(t[10:40], U[10:40], initial=x0)
    for (Ya, xa), (Yb, xb) in zip(out["filter"], out["stepwise"]):
        scale = np.abs(Ya).max()
        np.testing.assert_allclose(Yb, Ya, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(xb, xa, rtol=0, atol=1e-12 * np.abs(xa).max())


@pytest.mark.slow
def test_step_size_does_not_change_the_rom_solution(rom, loads):
    """Exact discretisation: 60 s and 20 s steps of the same piecewise-linear inputs agree at common times."""
    U = rom.layout().inputs(loads)
    t_fine = np.arange(0, loads.time_s[-1] + 1, 20.0)
    U_fine = np.column_stack([np.interp(t_fine, loads.time_s, U[:, j]) for j in range(U.shape[1])])
    Y60, x60 = rom.integrate(loads.time_s, U)
    Y20, x20 = rom.integrate(t_fine, U_fine)
    np.testing.assert_allclose(Y20[::3], Y60, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(x20, x60, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_state_save_and_restore_continues_exactly(rom, loads, tmp_path):
    U = rom.layout().inputs(loads)
    t = loads.time_s
    Y_all, _ = rom.integrate(t, U)
    k = 50
    _, x_mid = rom.integrate(t[: k + 1], U[: k + 1])
    path = save_state(tmp_path / "state.json", rom.state(x_mid, t[k]))
    st = load_state(path)
    assert st.time_s == t[k]
    Y_rest, _ = rom.integrate(t[k:], U[k:], initial=rom.restore(st))
    np.testing.assert_allclose(Y_rest, Y_all[k:], rtol=1e-10, atol=1e-13)
    with pytest.raises(RomInputError, match="belongs to reduced model"):
        one_mode().restore(st)


# -- files and bad input ------------------------------------------------------------------------------
@pytest.mark.slow
def test_save_load_round_trip(rom, machine, loads, tmp_path):
    path = save_rom(tmp_path / "rom.npz", rom)
    back = load_rom(path, machine)
    assert back.order == rom.order and back.input_names == rom.input_names and back.rom_id == rom.rom_id
    U = rom.layout().inputs(loads)
    np.testing.assert_array_equal(back.integrate(loads.time_s, U)[0], rom.integrate(loads.time_s, U)[0])
    np.testing.assert_array_equal(back.V, rom.V)
    assert back.meta["machine"]["sha256"] == machine.sha256


@pytest.mark.slow
def test_rom_from_changed_machine_file_or_other_version_is_refused(rom, tmp_path):
    path = save_rom(tmp_path / "rom.npz", rom)
    changed = tmp_path / "vmc800.toml"
    changed.write_text(resolve_machine_path("vmc800").read_text() + "\n# edited\n")
    with pytest.raises(RomFileError, match=r"rom\.npz: field 'machine\.sha256' .* but machine file .*vmc800\.toml has sha256"):
        load_rom(path, load_machine(changed))
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    meta = json.loads(str(data["meta_json"]))
    meta["format_version"] = 99
    data["meta_json"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "v99.npz", **data)
    with pytest.raises(RomFileError, match=r"v99\.npz: field 'format_version' is 'hybridcomp-rom' version 99"):
        load_rom(tmp_path / "v99.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(RomFileError, match="junk.npz: cannot read reduced model"):
        load_rom(tmp_path / "junk.npz")


@pytest.mark.slow
@pytest.mark.parametrize("dt", [0.0, -60.0, float("nan")])
def test_step_size_must_be_positive(rom, dt):
    x = np.zeros(rom.order)
    u = np.zeros(rom.n_inputs)
    with pytest.raises(RomInputError, match="step size must be positive"):
        rom.step(x, u, u, dt)


@pytest.mark.slow
def test_bad_time_grid_inputs_and_columns_are_named(rom):
    U = np.zeros((3, rom.n_inputs))
    with pytest.raises(RomInputError, match="step 2 goes from 60.0 s to 60.0 s"):
        rom.integrate([0.0, 60.0, 60.0], U)
    with pytest.raises(RomInputError, match=r"inputs must be \(3, 40\)"):
        rom.integrate([0.0, 60.0, 120.0], U[:, :5])
    with pytest.raises(RomInputError, match=r"loads.csv: column 'c_axis_motor_W' is not an input of the reduced model"):
        inputs_from_columns(rom, ["x_motor_W", "c_axis_motor_W"], np.zeros((2, 2)), "loads.csv")
    U2 = inputs_from_columns(rom, ["x_motor_W", "ambient_degC"], np.array([[5.0, 21.5]]))
    assert U2[0, rom.input_names.index("x_motor_W")] == 5.0 and U2[0, rom.input_names.index("ambient_degC")] == 1.5
    assert U2[0, rom.input_names.index("floor_degC")] == 0.0


# -- command line -----------------------------------------------------------------------------------
@pytest.mark.slow
def test_reduce_and_simulate_cli_against_fe(machine, loads, tmp_path, capsys):
    short = dataclasses.replace(loads, time_s=loads.time_s[::5], values=loads.values[::5])
    write_loads(tmp_path / "loads.csv", short)
    rom_path = tmp_path / "rom.npz"
    assert main(["reduce", "--element-size-mm", "150", "--check-loads", str(tmp_path / "loads.csv"),
                 "--out", str(rom_path)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["passed"] and summary["order"] == load_rom(rom_path).order
    common = ["simulate", "--loads", str(tmp_path / "loads.csv"), "--no-progress", "--theta", "0.5"]
    assert main([*common, "--out", str(tmp_path / "fe"), "--element-size-mm", "150"]) == 0
    assert main(["simulate", "--loads", str(tmp_path / "loads.csv"), "--rom", str(rom_path), "--out", str(tmp_path / "rom")]) == 0
    rows = {}
    for name in ("fe", "rom"):
        with (tmp_path / name / "outputs.csv").open() as fh:
            rows[name] = list(csv.reader(fh))
    assert rows["rom"][0] == rows["fe"][0]
    fe, ro = (np.array(rows[n][1:], float) for n in ("fe", "rom"))
    np.testing.assert_array_equal(ro[:, 0], fe[:, 0])
    assert np.abs(ro[:, 1:9] - fe[:, 1:9]).max() <= TOL_K
    assert np.abs(ro[:, 9:] - fe[:, 9:]).max() <= TOL_UM
    assert json.loads((tmp_path / "rom" / "run.json").read_text())["rom_order"] == summary["order"]


@pytest.mark.parametrize(
    "extra,match",
    [
        (["--machine", "{changed}"], "field 'machine.sha256'"),
        (["--fields", "2"], "--fields applies to the FE path only"),
        (["--time-tol-K", "0.1"], "--time-tol-K applies to the FE path only"),
        (["--pose", "X=100"], "field 'pose_mm' is"),
        (["--dt", "0"], "--dt must be positive"),
    ],
)
@pytest.mark.slow
def test_simulate_with_bad_rom_input_writes_nothing(rom, tmp_path, capsys, extra, match):
    rom_path = save_rom(tmp_path / "rom.npz", rom)
    changed = tmp_path / "changed.toml"
    changed.write_text(resolve_machine_path("vmc800").read_text() + "\n# edited\n")
    (tmp_path / "l.csv").write_text("time_s,x_motor_W\n0,1\n60,1\n")
    out = tmp_path / "out"
    args = [a.format(changed=changed) for a in extra]
    rc = main(["simulate", "--loads", str(tmp_path / "l.csv"), "--rom", str(rom_path), "--out", str(out), *args])
    assert rc == 2
    assert match in capsys.readouterr().err
    assert not out.exists()


# -- exported matrices ------------------------------------------------------------------------------
def exported(model):
    system = system_from_model(model)
    h = system.h
    return {"E": system.M, "A": -system.stiffness(h), "B": system.input_matrix(h), "C": system.C}


@pytest.mark.slow
def test_mat_and_matrix_market_reduce_with_moments_matched(model_200mm, tmp_path, capsys):
    mats = exported(model_200mm)  # about 1,600 states: the error figure's Gramians dense
    scipy.io.savemat(tmp_path / "sys.mat", mats)
    mm = tmp_path / "mm"
    mm.mkdir()
    for k, v in mats.items():
        scipy.io.mmwrite(mm / f"{k}.mtx", sp.coo_matrix(v) if sp.issparse(v) else np.asarray(v))
    H0 = mats["C"] @ factor_spd(-mats["A"], None)(mats["B"])
    for src in (tmp_path / "sys.mat", mm):
        r = reduce_matrices(src, order=51, basis="krylov")
        assert r.order == 51
        assert rel(r.transfer(0.0), H0) < 1e-8
        assert np.all(r.poles().real < 0)
    assert main(["reduce", "--matrices", str(tmp_path / "sys.mat"), "--order", "45", "--basis", "krylov",
                 "--out", str(tmp_path / "m.npz")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["order"] == 45
    assert load_external(tmp_path / "m.npz").meta["matrices"]["file"] == "sys.mat"


@pytest.mark.slow
def test_bad_exported_matrices_are_named(model, tmp_path):
    mats = exported(model)
    scipy.io.savemat(tmp_path / "noc.mat", {k: v for k, v in mats.items() if k != "C"})
    with pytest.raises(MatrixFileError, match=r"noc\.mat: variable 'C' is missing"):
        reduce_matrices(tmp_path / "noc.mat", order=10)
    A = sp.lil_matrix(mats["A"])
    A[0, 1] += 1.0
    scipy.io.savemat(tmp_path / "asym.mat", {**mats, "A": A.tocsr()})
    with pytest.raises(MatrixFileError, match=r"asym\.mat: variable 'A' is not symmetric; the krylov basis"):
        reduce_matrices(tmp_path / "asym.mat", order=10, basis="krylov")  # balanced truncation takes it
    scipy.io.savemat(tmp_path / "pos.mat", {**mats, "A": -mats["A"]})
    with pytest.raises(MatrixFileError, match=r"pos\.mat: variable 'A' is symmetric but not negative definite"):
        reduce_matrices(tmp_path / "pos.mat", order=10)


# -- H2-optimal one-sided basis: against dense references (scipy's Lyapunov solver, no pyMOR) ---------
def small_system(model, n=240):
    """A small symmetric system from the FE mesh: the FE system projected on a rational Krylov basis of order n."""
    from hybridcomp.rom.krylov import ThermalSystem

    system = system_from_model(model)
    V = Reductor(system, np.ones(11), np.ones(40), system.h[None, :], n_s=10, fastest_time_s=5.0).reduce(order=n).V
    P = project(system, V)
    return ThermalSystem(ThermalOperators(
        M=sp.csr_matrix(P["M"]), K=sp.csr_matrix(P["K"]), H=tuple(sp.csr_matrix(H) for H in P["H"]), h_W_m2K=system.h,
        B=P["B"], Hb=P["Hb"], C=P["C"], input_names=system.input_names, output_names=system.output_names))


@pytest.fixture(scope="module")
def small(model):
    return small_system(model)


def _weights(system):
    w = np.r_[np.full(8, 1 / TOL_K), np.full(3, 1e6 / TOL_UM)]
    return w, np.ones(40)


def _dense(system, w, scale):
    """E x' = A x + B u, y = C x (dense, weighted), at nominal h."""
    h = system.h
    return system.M.toarray(), -system.stiffness(h).toarray(), system.input_matrix(h) * scale, w[:, None] * system.C


def _lyap_h2(E, A, B, C):
    """H2 norm by scipy's dense Lyapunov solver on the standard form."""
    L = la.cholesky(E, lower=True)
    Li = la.inv(L)
    As, Bs, Cs = Li @ A @ Li.T, Li @ B, C @ Li.T
    P = la.solve_continuous_lyapunov(As, -Bs @ Bs.T)
    return float(np.sqrt(np.trace(Cs @ P @ Cs.T))), (As, Bs, Cs)


def _error_h2(full, red):
    """H2 norm of the error system (block-diagonal, outputs subtracted) by scipy's Lyapunov solver."""
    (A1, B1, C1), (A2, B2, C2) = full, red
    A = la.block_diag(A1, A2)
    B = np.vstack([B1, B2])
    C = np.hstack([C1, -C2])
    P = la.solve_continuous_lyapunov(A, -B @ B.T)
    return float(np.sqrt(max(np.trace(C @ P @ C.T), 0.0)))


def _bt_dense(As, Bs, Cs, r):
    """Square-root balanced truncation from scipy's Lyapunov solutions."""
    P = la.solve_continuous_lyapunov(As, -Bs @ Bs.T)
    Q = la.solve_continuous_lyapunov(As.T, -Cs.T @ Cs)
    ep, Up = la.eigh(0.5 * (P + P.T))
    eq, Uq = la.eigh(0.5 * (Q + Q.T))
    Lp = Up * np.sqrt(np.clip(ep, 0, None))
    Lq = Uq * np.sqrt(np.clip(eq, 0, None))
    U, s, Vt = la.svd(Lq.T @ Lp)
    S = s[:r] ** -0.5
    V = Lp @ Vt[:r].T * S
    W = Lq @ U[:, :r] * S
    return W.T @ As @ V, W.T @ Bs, Cs @ V


@pytest.mark.slow
def test_h2_error_formulas_match_scipy_lyapunov(small):
    from hybridcomp.rom import h2

    w, scale = _weights(small)
    E, A, B, C = _dense(small, w, scale)
    norm, full = _lyap_h2(E, A, B, C)
    form = h2.modal_form(E, -A, B, C)
    assert form.h2_norm == pytest.approx(norm, rel=1e-9)
    V = np.linalg.qr(np.random.default_rng(3).standard_normal((small.n, 12)))[0]
    _, red = _lyap_h2(V.T @ E @ V, V.T @ A @ V, V.T @ B, C @ V)
    ref = _error_h2(full, red) / norm
    assert h2.galerkin_h2_error(form, la.solve(form.T, V)) == pytest.approx(ref, rel=1e-7)
    assert h2.general_h2_error(form, *red) == pytest.approx(ref, rel=1e-7)
    assert 0.01 < ref < 1.0  # a random basis is measurably wrong: the formulas are not compared at zero


@pytest.mark.slow
def test_h2_gradient_matches_finite_differences(small):
    from hybridcomp.rom import h2

    w, scale = _weights(small)
    E, A, B, C = _dense(small, w, scale)
    form = h2.modal_form(E, -A, B, C)
    rng = np.random.default_rng(4)
    Q = np.linalg.qr(rng.standard_normal((small.n, 6)))[0]
    D = rng.standard_normal(Q.shape)
    D -= Q @ (Q.T @ D)
    J, g = h2.galerkin_error(form, Q, gradient=True)
    eps = 1e-6
    fd = (h2.galerkin_error(form, np.linalg.qr(Q + eps * D)[0])
          - h2.galerkin_error(form, np.linalg.qr(Q - eps * D)[0])) / (2 * eps)
    assert np.sum(g * D) == pytest.approx(fd, rel=1e-5)
    assert abs(fd) > 1e-6 * J  # not compared at a stationary point
    np.testing.assert_allclose(Q.T @ g, 0.0, atol=1e-10 * np.abs(g).max())  # tangent to the Grassmann manifold


@pytest.mark.slow
def test_h2_optimal_one_sided_basis_within_twice_balanced_truncation(small):
    """The goal of the pyMOR cross-check, on a small system with a dense scipy reference: the one-sided
    (symmetric, stable) H2-optimal basis is within 2x of balanced truncation's H2 error at equal order,
    while the greedy Krylov basis of the same order is not."""
    from hybridcomp.rom import h2

    w, scale = _weights(small)
    E, A, B, C = _dense(small, w, scale)
    norm, full = _lyap_h2(E, A, B, C)
    for r in (10, 20):
        e_bt = _error_h2(full, _bt_dense(*full, r)) / norm
        V = h2.h2_optimal_basis(small, np.eye(small.n), r, [small.h], scale, w, maxiter=400)
        Mr, Kr = V.T @ E @ V, -V.T @ A @ V
        assert np.all(la.eigvalsh(Mr) > 0) and np.all(la.eigvalsh(Kr, Mr) > 0)
        _, red = _lyap_h2(Mr, -Kr, V.T @ B, C @ V)
        e_ours = _error_h2(full, red) / norm
        e_greedy = h2.galerkin_h2_error(h2.modal_form(E, -A, B, C),
                                        la.solve(h2.modal_form(E, -A, B, C).T,
                                                 Reductor(small, 1 / w, scale, small.h[None, :]).reduce(order=r).V))
        assert e_ours <= 2 * e_bt, (r, e_ours, e_bt)
        assert e_greedy > 2 * e_bt, (r, e_greedy, e_bt)  # the bar is not trivially met


@pytest.mark.slow
def test_h2_basis_keeps_the_steady_state_block_exact(small):
    """With the s = 0 block fixed, steady states stay exact (as the Krylov basis) whatever the other directions."""
    from hybridcomp.rom import h2
    from hybridcomp.rom.krylov import orthonormal_extension

    w, scale = _weights(small)
    red = Reductor(small, 1 / w, scale, small.h[None, :])
    s0 = orthonormal_extension(np.zeros((small.n, 0)), red._blocks(0.0, small.h, 1))
    V = h2.h2_optimal_basis(small, np.eye(small.n), s0.shape[1] + 8, [small.h, 2 * small.h], scale, w,
                            maxiter=40, fixed=s0)
    assert V.shape[1] == s0.shape[1] + 8
    np.testing.assert_allclose(V.T @ V, np.eye(V.shape[1]), atol=1e-10)
    np.testing.assert_allclose(s0 - V @ (V.T @ s0), 0.0, atol=1e-10)
    P = project(small, V)
    np.testing.assert_allclose(_reduced_tf(P, 0.0, small.h), small.transfer(0.0), rtol=1e-8,
                               atol=1e-12 * np.abs(small.transfer(0.0)).max())


@pytest.mark.slow
def test_reduce_model_with_h2_basis_keeps_structure_and_steady_state(model, loads):
    rom = reduce_model(model, order=56, check_loads=loads, basis="h2", h2_maxiter=20)
    assert rom.order == 56 and rom.meta["method"] == "H2-optimal one-sided basis"
    np.testing.assert_allclose(rom.M, rom.M.T, atol=0)
    assert np.all(rom.poles() < 0) and np.all(rom.with_htc(ambient=100.0).poles() < 0)
    u = full_power(model)
    np.testing.assert_allclose(rom.outputs(rom.steady_state(u))[:8], model.C @ steady_state(model, u), rtol=1e-8)
    with pytest.raises(ValueError, match="basis must be 'krylov' or 'h2', got 'bt'"):
        reduce_model(model, order=10, check_loads=loads, basis="bt")
