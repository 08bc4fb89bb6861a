"""The H2-optimal one-sided basis (rom/h2.py) on small synthetic symmetric systems: seconds, no FE model.

The systems mimic the demonstrator's difficulty at a small size: decay rates over four decades, more inputs
than outputs (so the one-sided projection has to serve two different dominant subspaces).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as la

from hybridcomp.rom import h2


def _system(n=60, m=8, q=3, seed=0):
    """``M = I``, SPD ``K`` with eigenvalues over four decades (random eigenvectors), ``B``, ``C``."""
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.standard_normal((n, n)))[0]
    K = (U * np.logspace(-4, 0, n)) @ U.T
    K = 0.5 * (K + K.T)
    return K, rng.standard_normal((n, m)), rng.standard_normal((q, n)), rng


def _rel_sum(forms, Z):
    return sum(h2.galerkin_error(f, f.T.T @ Z) / f.h2_norm ** 2 for f in forms)


def _riemannian_grad_norm(forms, Z):
    g = sum(f.T @ h2.galerkin_error(f, f.T.T @ Z, gradient=True)[1] / f.h2_norm ** 2 for f in forms)
    return float(np.linalg.norm(g))


def test_cached_h2_norm_is_the_closed_form_gramian_trace():
    K, B, C, _ = _system()
    f = h2.modal_form(np.eye(K.shape[0]), K, B, C)
    P = la.solve_continuous_lyapunov(-K, -B @ B.T)
    assert f.h2_norm == pytest.approx(np.sqrt(np.trace(C @ P @ C.T)), rel=1e-9)
    assert f.h2_norm == f.h2_norm  # cached: the same value on every call


def test_optimum_over_two_forms_is_stationary_and_beats_its_start():
    """Two ``h`` values: two forms with different modal bases in one common frame.  The returned value must be
    the true summed error of the returned basis, far below the start's, at a point where the Riemannian gradient
    has (nearly) vanished: a wrong chain rule or frame map fails one of these."""
    K, B, C, rng = _system(seed=2)
    n = K.shape[0]
    K2 = K + np.diag(np.linspace(1e-3, 1e-1, n))
    forms = [h2.modal_form(np.eye(n), K, B, C), h2.modal_form(np.eye(n), K2, B, 2 * C)]
    Z0 = np.linalg.qr(rng.standard_normal((n, 6)))[0]
    Z, J = h2.optimal_subspace(forms, Z0, maxiter=3000)
    np.testing.assert_allclose(Z.T @ Z, np.eye(6), atol=1e-10)
    assert J == pytest.approx(_rel_sum(forms, Z), rel=1e-8)
    assert J < 0.05 * _rel_sum(forms, Z0)
    assert _riemannian_grad_norm(forms, Z) < 1e-3 * _riemannian_grad_norm(forms, Z0)


def test_progress_bar_reports_without_changing_the_result(capsys):
    K, B, C, rng = _system(seed=5)
    f = h2.modal_form(np.eye(K.shape[0]), K, B, C)
    Z0 = np.linalg.qr(rng.standard_normal((K.shape[0], 5)))[0]
    Z1, J1 = h2.optimal_subspace([f], Z0, maxiter=300, restart=100)
    Z2, J2 = h2.optimal_subspace([f], Z0, maxiter=300, restart=100, progress=True)
    assert J1 == J2 and np.array_equal(Z1, Z2)
    err = capsys.readouterr().err
    assert "H2-optimal basis, order 5" in err and f"relative H2 error {np.sqrt(J2):.3g}" in err


@pytest.mark.slow  # 2,400 L-BFGS iterations: seconds
def test_preconditioned_optimiser_beats_plain_lbfgs_at_equal_iterations():
    """The point of the row/column preconditioning: on a system whose decay rates span four decades it gets
    (much) closer to the optimum than plain L-BFGS on the QR parametrisation with the same number of
    iterations; the reference optimum is plain L-BFGS with four times as many."""
    K, B, C, _ = _system(n=100, m=10, q=3, seed=3)
    f = h2.modal_form(np.eye(K.shape[0]), K, B, C)
    Z0 = f.T @ h2.initial_basis(f, 10)
    J_start = _rel_sum([f], Z0)
    _, J_pre = h2.optimal_subspace([f], Z0, maxiter=400, restart=200)
    _, J_plain = h2.optimal_subspace([f], Z0, maxiter=400, precondition=False)
    _, J_long = h2.optimal_subspace([f], Z0, maxiter=1600, precondition=False)
    J_ref = min(J_pre, J_long)
    assert J_plain < 0.6 * J_start  # plain L-BFGS does make progress: the comparison is not against a stalled run
    assert J_pre - J_ref < 0.1 * (J_plain - J_ref), (J_pre, J_plain, J_long)


def test_fixed_directions_stay_in_the_basis():
    K, B, C, rng = _system(seed=4)
    n = K.shape[0]
    f = h2.modal_form(np.eye(n), K, B, C)
    fixed = np.linalg.qr(la.solve(K, B[:, :2]))[0]  # e.g. steady-state directions
    Z0 = np.linalg.qr(rng.standard_normal((n, 5)))[0]
    Z, J = h2.optimal_subspace([f], Z0, maxiter=200, fixed=fixed)
    assert Z.shape == (n, 7)
    np.testing.assert_allclose(Z.T @ Z, np.eye(7), atol=1e-10)
    np.testing.assert_allclose(fixed - Z @ (Z.T @ fixed), 0.0, atol=1e-10)
    assert J == pytest.approx(_rel_sum([f], Z), rel=1e-8)


def test_reduce_cli_passes_h2_maxiter_and_rejects_a_negative_one(tmp_path, monkeypatch, capsys):
    from hybridcomp.cli import main
    from hybridcomp.rom import machine as rom_machine

    seen = {}

    class Stop(Exception):
        pass

    def fake_reduce_model(model, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(rom_machine, "reduce_model", fake_reduce_model)
    out = tmp_path / "rom.npz"
    # the command line turns an unexpected exception into one line and exit code 1, never a traceback
    assert main(["reduce", "--element-size-mm", "300", "--order", "30", "--basis", "h2", "--h2-maxiter", "7",
                 "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "error: internal error Stop" in err and "Traceback" not in err
    assert seen["basis"] == "h2" and seen["h2_maxiter"] == 7
    assert main(["reduce", "--basis", "h2", "--h2-maxiter", "-1", "--out", str(out)]) == 2
    assert "--h2-maxiter must be a non-negative integer, got -1" in capsys.readouterr().err
    assert not out.exists()
