"""The solver backends agree with each other and with a dense reference."""

from __future__ import annotations

import importlib.util
import logging

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import skfem

from hybridcomp.errors import HybridcompError
from hybridcomp.fem import assembly, solvers

# HYBRIDCOMP_SOLVER value -> (module it needs, the name a factorisation reports)
DIRECT = {"cholmod": ("sksparse", "cholmod"), "cvxopt": ("cvxopt", "cvxopt-cholmod"), "superlu": (None, "superlu-nd")}


def installed(module):
    return module is None or importlib.util.find_spec(module) is not None


def force(monkeypatch, backend):
    """Start the backend list at ``backend``; skip the test when it is not installed."""
    module = {**{k: v[0] for k, v in DIRECT.items()}, "pyamg": "pyamg", "auto": None}[backend]
    if not installed(module):
        pytest.skip(f"{module} is not installed")
    monkeypatch.setattr(solvers, "_FORCE", backend)


def heat_system(n=12):
    m = skfem.MeshHex.init_tensor(np.linspace(0, 1, n + 1), np.linspace(0, 0.7, n), np.linspace(0, 1.3, n + 2))
    b = assembly.cell_basis(m)
    A = assembly.capacity_matrix(b, 3.6e6) / 60.0 + assembly.conductivity_matrix(b, 46.0)
    return A.tocsr(), m.p.T


def test_nested_dissection_is_a_permutation_that_reduces_fill():
    A, x = heat_system()
    perm = solvers.nested_dissection(A, x, leaf_size=32)
    assert np.array_equal(np.sort(perm), np.arange(A.shape[0]))
    import scipy.sparse.linalg as sla

    opts = dict(diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    natural = sla.splu(sp.csc_matrix(A), permc_spec="NATURAL", **opts)
    nd = sla.splu(sp.csc_matrix(A[perm][:, perm]), permc_spec="NATURAL", **opts)
    assert nd.L.nnz < 0.7 * natural.L.nnz


def test_superlu_nd_matches_dense(monkeypatch):
    monkeypatch.setattr(solvers, "_FORCE", "superlu")
    A, x = heat_system(8)
    f = solvers.factorize_spd(A, x)
    assert f.backend == "superlu-nd"
    rhs = np.random.default_rng(1).random((A.shape[0], 2))
    np.testing.assert_allclose(f(rhs), np.linalg.solve(A.toarray(), rhs), rtol=1e-10)


def elastic_system():
    """A supported elasticity matrix (node-interleaved, 6 DOFs held by identity rows), its mesh."""
    m = skfem.MeshHex.init_tensor(np.linspace(0, 1, 7), np.linspace(0, 0.5, 5), np.linspace(0, 0.5, 5))
    b = assembly.cell_basis(m)
    K = assembly.elasticity_matrix(b, 2.1e11, 0.3)
    fixed = np.r_[0, 1, 2, 3 * 6 + 1, 3 * 6 + 2, 3 * 40 + 2]  # any 6 independent DOFs suffice for the algebra
    keep = np.ones(K.shape[0])
    keep[fixed] = 0
    Kc = (sp.diags(keep) @ K @ sp.diags(keep) + sp.diags(1 - keep)).tocsr()
    return Kc, fixed, m


@pytest.mark.parametrize("backend", ["auto", "cholmod", "cvxopt", "amg", "superlu"])
def test_elastic_backends_agree(monkeypatch, backend):
    force(monkeypatch, "pyamg" if backend == "amg" else backend)
    monkeypatch.setattr(solvers, "_FORCE", backend)  # "amg" is kept as the old spelling of "pyamg"
    Kc, fixed, m = elastic_system()
    rhs = np.random.default_rng(2).random((Kc.shape[0], 3))
    rhs[fixed] = 0
    x, used = solvers.solve_spd_few(Kc, rhs, m.p.T, block=3, near_null=assembly.rigid_body_modes(m.p))
    expected = {"cholmod": "cholmod", "cvxopt": "cvxopt-cholmod", "amg": "pyamg-cg", "superlu": "superlu-nd"}.get(backend)
    if backend == "auto":  # a small system: the fastest direct solver installed
        expected = "cholmod" if installed("sksparse") else "cvxopt-cholmod" if installed("cvxopt") else used
    assert used == expected
    np.testing.assert_allclose(Kc @ x, rhs, atol=1e-8 * np.abs(rhs).max() * np.abs(Kc).max())
    np.testing.assert_allclose(x, np.linalg.solve(Kc.toarray(), rhs), rtol=1e-6, atol=1e-6 * np.abs(x).max())


def tet_heat_system(n=7):
    """A P1 tetrahedral heat matrix M/Δt + K [W/K] with convection on the boundary, its node coordinates."""
    m = skfem.MeshTet.init_tensor(np.linspace(0, 0.4, n + 1), np.linspace(0, 0.3, n), np.linspace(0, 0.5, n + 2))
    b = assembly.cell_basis(m)
    A = assembly.capacity_matrix(b, 3.6e6) / 60.0 + assembly.conductivity_matrix(b, 46.0)
    A = A + 10.0 * assembly.convection_matrix(m, m.boundary_facets())
    return A.tocsr(), m.p.T


@pytest.mark.parametrize("backend", list(DIRECT))
@pytest.mark.parametrize("system", ["hex", "tet"])
def test_direct_backends_solve_heat_matrices_to_round_off(monkeypatch, backend, system):
    force(monkeypatch, backend)
    A, x = heat_system(9) if system == "hex" else tet_heat_system()
    rhs = np.random.default_rng(3).standard_normal((A.shape[0], 4))
    f = solvers.factorize_spd(A, x)
    assert f.backend == DIRECT[backend][1]
    reference = sla.splu(sp.csc_matrix(A)).solve(rhs)  # scipy's LU with its own ordering
    X = f(rhs)
    assert X.shape == rhs.shape
    np.testing.assert_allclose(X, reference, rtol=0, atol=1e-11 * np.abs(reference).max())
    np.testing.assert_allclose(f(rhs[:, 2]), reference[:, 2], rtol=0, atol=1e-11 * np.abs(reference).max())
    np.testing.assert_allclose(A @ X, rhs, rtol=0, atol=1e-12 * np.abs(A).max() * np.abs(X).max() * 30)


@pytest.mark.parametrize("backend", list(DIRECT))
def test_direct_backends_solve_an_elastic_matrix_against_dense(monkeypatch, backend):
    force(monkeypatch, backend)
    Kc, fixed, m = elastic_system()
    rhs = np.random.default_rng(4).standard_normal((Kc.shape[0], 5))
    for coords, block in ((m.p.T, 3), (None, 1)):  # nested dissection by nodes, and the backend's own ordering
        f = solvers.factorize_spd(Kc, coords, block)
        assert f.backend == (DIRECT[backend][1] if coords is not None or backend != "superlu" else "superlu-colamd")
        reference = np.linalg.solve(Kc.toarray(), rhs)
        np.testing.assert_allclose(f(rhs), reference, rtol=0, atol=1e-9 * np.abs(reference).max())


def test_cvxopt_solves_are_bit_identical_from_run_to_run(monkeypatch):
    force(monkeypatch, "cvxopt")
    A, x = heat_system(10)
    rhs = np.random.default_rng(5).random((A.shape[0], 3))
    first = solvers.factorize_spd(A, x)(rhs)
    for _ in range(3):
        np.testing.assert_array_equal(solvers.factorize_spd(A, x)(rhs), first)


def fake_installed(monkeypatch, *modules):
    """Pretend only ``modules`` (of sksparse.cholmod, cvxopt.cholmod, pyamg) are installed."""
    monkeypatch.setattr(solvers, "_importable", lambda name: name in modules)


def test_selection_order_prefers_scikit_sparse_then_cvxopt_then_pyamg_then_superlu(monkeypatch):
    monkeypatch.setattr(solvers, "_FORCE", "")
    big = solvers.DIRECT_ELASTIC_MAX_DOF + 1
    fake_installed(monkeypatch, "sksparse.cholmod", "cvxopt.cholmod", "pyamg")
    assert (solvers.factor_backend(), solvers.few_backend(1000), solvers.few_backend(big)) == ("cholmod",) * 3
    fake_installed(monkeypatch, "cvxopt.cholmod", "pyamg")
    assert (solvers.factor_backend(), solvers.few_backend(1000), solvers.few_backend(big)) == ("cvxopt", "cvxopt", "pyamg")
    fake_installed(monkeypatch, "cvxopt.cholmod")
    assert (solvers.factor_backend(), solvers.few_backend(big)) == ("cvxopt", "cvxopt")
    fake_installed(monkeypatch, "pyamg")
    assert (solvers.factor_backend(), solvers.few_backend(1000)) == ("superlu", "pyamg")
    fake_installed(monkeypatch)
    assert (solvers.factor_backend(), solvers.few_backend(1000)) == ("superlu", "superlu")
    # HYBRIDCOMP_SOLVER starts the list at the named backend
    fake_installed(monkeypatch, "sksparse.cholmod", "cvxopt.cholmod", "pyamg")
    for start, expected in [("cvxopt", ("cvxopt", "cvxopt", "cvxopt")), ("pyamg", ("superlu", "pyamg", "pyamg")),
                            ("amg", ("superlu", "pyamg", "pyamg")), ("superlu", ("superlu",) * 3)]:
        monkeypatch.setattr(solvers, "_FORCE", start)
        assert (solvers.factor_backend(), solvers.few_backend(1000), solvers.few_backend(big)) == expected, start


def test_cvxopt_is_used_when_scikit_sparse_is_absent(monkeypatch):
    pytest.importorskip("cvxopt")
    monkeypatch.setattr(solvers, "_FORCE", "")
    fake_installed(monkeypatch, "cvxopt.cholmod", "pyamg")
    A, x = heat_system(6)
    assert solvers.factorize_spd(A, x).backend == "cvxopt-cholmod"
    Kc, fixed, m = elastic_system()
    _, used = solvers.solve_spd_few(Kc, np.ones((Kc.shape[0], 2)), m.p.T, block=3)
    assert used == "cvxopt-cholmod"


def test_a_bad_or_missing_forced_solver_is_named(monkeypatch):
    monkeypatch.setattr(solvers, "_FORCE", "umfpack")
    with pytest.raises(ValueError, match=r"HYBRIDCOMP_SOLVER='umfpack' is not a solver; use one of auto, cholmod"):
        solvers.factor_backend()
    monkeypatch.setattr(solvers, "_FORCE", "cvxopt")
    fake_installed(monkeypatch, "pyamg")
    with pytest.raises(ImportError, match=r"HYBRIDCOMP_SOLVER='cvxopt' .* not installed: pip install 'hybridcomp\[fast\]'"):
        solvers.factor_backend()


def test_no_fast_solver_logs_the_extra_to_install(monkeypatch, caplog):
    monkeypatch.setattr(solvers, "_FORCE", "")
    monkeypatch.setattr(solvers, "_SLOW_FALLBACK_DOF", 100)
    monkeypatch.setattr(solvers, "_warned", [])
    fake_installed(monkeypatch)
    A, x = heat_system(6)
    with caplog.at_level(logging.WARNING, logger=solvers.__name__):
        assert solvers.factorize_spd(A, x).backend == "superlu-nd"
        solvers.factorize_spd(A, x)
    assert len(caplog.records) == 1  # once per process
    assert "pip install 'hybridcomp[fast]'" in caplog.records[0].getMessage()


@pytest.mark.parametrize("backend", list(DIRECT))
def test_a_matrix_that_is_not_spd_is_refused_by_name(monkeypatch, backend):
    force(monkeypatch, backend)
    A, x = heat_system(5)
    rhs = np.ones(A.shape[0])
    unsym = A.tolil()
    unsym[3, 4] += 0.01 * abs(A).max()
    with pytest.raises(solvers.MatrixNotSPDError, match=r"is not symmetric: max \|A - Aᵀ\| = "):
        solvers.factorize_spd(unsym.tocsr(), x)
    bad = A.tolil()
    bad[7, 7] = np.nan
    with pytest.raises(solvers.MatrixNotSPDError, match="has 1 non-finite entries"):
        solvers.factorize_spd(bad.tocsr(), x)
    if backend == "superlu":
        return  # an LU solves symmetric indefinite systems; only the Cholesky backends need definiteness
    lam_min = sla.eigsh(A, k=1, sigma=0, which="LM", return_eigenvectors=False)[0]
    indefinite = A - 2.0 * lam_min * sp.eye(A.shape[0])  # symmetric, one negative eigenvalue at least
    pivot = r"matrix is not positive definite \(\S+ found a non-positive pivot"
    with pytest.raises(solvers.MatrixNotSPDError, match=pivot) as err:
        solvers.factorize_spd(indefinite, x)(rhs)
    assert isinstance(err.value, HybridcompError) and isinstance(err.value, np.linalg.LinAlgError)
