"""Sparse symmetric positive definite solves, chosen deliberately.

Measured on the 2-core reference machine for a 50,653-node hexahedral heat
matrix (see README): scipy's ``splu`` with its default COLAMD ordering factors
in about 30 s, but the same SuperLU on the matrix reordered by nested
dissection factors in 2.2 s and back-solves in 32 ms.  CHOLMOD (scikit-sparse,
an extra that needs the SuiteSparse system library) factors in 1.0 s and
back-solves in 15 ms.  So:

* scalar (heat) systems: CHOLMOD when importable, else SuperLU on a geometric
  nested-dissection ordering computed here from the node coordinates;
* vector (elastic) systems, solved only for three adjoint right-hand sides:
  CHOLMOD, else smoothed-aggregation AMG + CG with the rigid-body modes
  (pyamg, extra ``fast``), else SuperLU with nested dissection (slow above
  ~50k nodes; a warning names the extra).
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

log = logging.getLogger(__name__)

# HYBRIDCOMP_SOLVER limits the backends for benchmarks: "amg" (no CHOLMOD), "superlu" (scipy only)
_FORCE = os.environ.get("HYBRIDCOMP_SOLVER", "")


def have_cholmod() -> bool:
    if _FORCE in ("amg", "superlu"):
        return False
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


def have_pyamg() -> bool:
    if _FORCE == "superlu":
        return False
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


def nested_dissection(A: sp.spmatrix, coords: np.ndarray, leaf_size: int = 128) -> np.ndarray:
    """Fill-reducing ordering by geometric nested dissection.

    Recursively splits the node set at the median of its longest extent; the
    nodes of one half that touch the other half form the separator, numbered
    after both halves.  Optimal in order for grid-like 3D meshes.

    Parameters
    ----------
    A : sparse matrix whose pattern is the node graph
    coords : (n, d) node coordinates
    """
    A = sp.csr_matrix(A)
    n = A.shape[0]
    coords = np.asarray(coords, float)
    if coords.shape[0] != n:
        raise ValueError(f"coords has {coords.shape[0]} rows for a matrix of size {n}")
    out: list[np.ndarray] = []
    stack: list[tuple[np.ndarray, bool]] = [(np.arange(n), False)]
    # iterative post-order: (set, expanded?)
    pending: list[np.ndarray] = []
    while stack:
        S, done = stack.pop()
        if done:
            out.append(pending.pop())
            continue
        if len(S) <= leaf_size:
            out.append(S)
            continue
        x = coords[S]
        ax = int(np.argmax(x.max(0) - x.min(0)))
        order = np.argsort(x[:, ax], kind="stable")
        left = np.zeros(len(S), bool)
        left[order[: len(S) // 2]] = True
        sub = A[S][:, S]
        cross = sub[left][:, ~left]
        li = np.flatnonzero(left)
        sep = np.zeros(len(S), bool)
        sep[li[np.diff(cross.indptr) > 0]] = True
        pending.append(S[sep])
        stack.append((S, True))
        stack.append((S[~left], False))
        stack.append((S[left & ~sep], False))
    perm = np.concatenate(out)
    assert perm.size == n
    return perm


@dataclass(frozen=True)
class Factor:
    """A factorised SPD matrix: ``factor(b)`` solves ``A x = b`` (b: vector or columns)."""

    solve: Callable[[np.ndarray], np.ndarray]
    backend: str
    nnz_factor: int

    def __call__(self, b: np.ndarray) -> np.ndarray:
        return self.solve(b)


def factorize_spd(A: sp.spmatrix, coords: np.ndarray | None = None, block: int = 1) -> Factor:
    """Factorise a sparse SPD matrix with the fastest available backend.

    Parameters
    ----------
    A : sparse symmetric positive definite matrix
    coords : (n / block, 3) coordinates of the nodes, for the nested-dissection ordering
    block : DOFs per node (3 for node-interleaved displacement)
    """
    A = sp.csc_matrix(A)
    if have_cholmod():
        from sksparse.cholmod import cholesky

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # CHOLMOD warns about CSC conversions only
            f = cholesky(A)
        return Factor(lambda b: f(b), "cholmod", int(f.L().nnz))
    if coords is None:
        lu = sla.splu(A)  # plain COLAMD: slow in 3D, used only without coordinates
        return Factor(lu.solve, "superlu-colamd", int(lu.L.nnz + lu.U.nnz))
    node_graph = A if block == 1 else sp.csr_matrix(A)[::block][:, ::block]
    pn = nested_dissection(node_graph, coords)
    perm = (block * pn[:, None] + np.arange(block)).ravel()
    Ap = sp.csc_matrix(A[perm][:, perm])
    lu = sla.splu(Ap, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def solve(b: np.ndarray) -> np.ndarray:
        b = np.asarray(b)
        x = np.empty_like(b, dtype=float)
        x[perm] = lu.solve(np.ascontiguousarray(b[perm]))
        return x

    return Factor(solve, "superlu-nd", int(lu.L.nnz + lu.U.nnz))


def solve_spd_few(
    A: sp.spmatrix, rhs: np.ndarray, coords: np.ndarray, block: int = 1, near_null: np.ndarray | None = None, rtol: float = 1e-12
) -> tuple[np.ndarray, str]:
    """Solve ``A X = rhs`` for a few columns (adjoint solves): direct or AMG-CG.

    ``near_null`` (n × k) are the rigid-body modes for AMG on elasticity.  ``rtol``
    is the AMG-CG relative residual.  The drift rows multiply whole temperature
    fields, so they are solved as tightly as a direct solver: 1e-8 left errors
    of 2e-8 relative (enough to break the exact free-expansion check), 1e-11 gave
    2.5e-12 at about 20 % more iterations than 1e-8.
    """
    rhs = np.asarray(rhs, float)
    cols = rhs.reshape(rhs.shape[0], -1)
    if have_cholmod():
        return factorize_spd(A, coords, block)(cols).reshape(rhs.shape), "cholmod"
    if have_pyamg():
        import pyamg

        A = sp.csr_matrix(A)
        ml = pyamg.smoothed_aggregation_solver(A, B=near_null, symmetry="symmetric")
        out = np.empty_like(cols)
        for j in range(cols.shape[1]):
            res: list[float] = []
            x = ml.solve(cols[:, j], tol=rtol, accel="cg", maxiter=500, residuals=res)
            if res and res[-1] > 1e3 * rtol * max(res[0], 1e-300):
                raise RuntimeError(f"AMG-CG did not converge: residual {res[-1]:.3e} after {len(res)} iterations")
            out[:, j] = x
        return out.reshape(rhs.shape), "pyamg-cg"
    if A.shape[0] > 60_000:
        log.warning("elastic solve of %d DOFs without CHOLMOD or pyamg is slow: pip install 'hybridcomp[fast]'", A.shape[0])
    return factorize_spd(A, coords, block)(cols).reshape(rhs.shape), "superlu-nd"
