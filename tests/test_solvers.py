"""The solver backends agree with each other and with a dense reference."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import skfem

from hybridcomp.fem import assembly, solvers


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


@pytest.mark.parametrize("force", ["", "amg", "superlu"])
def test_elastic_backends_agree(monkeypatch, force):
    monkeypatch.setattr(solvers, "_FORCE", force)
    m = skfem.MeshHex.init_tensor(np.linspace(0, 1, 7), np.linspace(0, 0.5, 5), np.linspace(0, 0.5, 5))
    b = assembly.cell_basis(m)
    K = assembly.elasticity_matrix(b, 2.1e11, 0.3)
    fixed = np.r_[0, 1, 2, 3 * 6 + 1, 3 * 6 + 2, 3 * 40 + 2]  # any 6 independent DOFs suffice for the algebra
    keep = np.ones(K.shape[0])
    keep[fixed] = 0
    Kc = (sp.diags(keep) @ K @ sp.diags(keep) + sp.diags(1 - keep)).tocsr()
    rhs = np.random.default_rng(2).random((K.shape[0], 3))
    rhs[fixed] = 0
    x, backend = solvers.solve_spd_few(Kc, rhs, m.p.T, block=3, near_null=assembly.rigid_body_modes(m.p))
    expected = {"amg": "pyamg-cg", "superlu": "superlu-nd"}.get(force)
    if expected:
        assert backend == expected
    np.testing.assert_allclose(Kc @ x, rhs, atol=1e-8 * np.abs(rhs).max() * np.abs(Kc).max())
    np.testing.assert_allclose(x, np.linalg.solve(Kc.toarray(), rhs), rtol=1e-6, atol=1e-6 * np.abs(x).max())
