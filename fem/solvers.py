"""Sparse symmetric positive definite solves, chosen deliberately.

Measured on the 2-core reference machine for the 64,945-node demonstrator heat
matrix (see README): scipy's ``splu`` with its default COLAMD ordering needs
about 30 s per factorisation; the same SuperLU on the matrix reordered by
nested dissection (computed here from the node coordinates) factors in about
4 s and back-solves in about 40 ms; CHOLMOD (supernodal Cholesky) on the same
ordering factors in 0.5 s and back-solves in about 30 ms.  CHOLMOD comes two
ways: scikit-sparse (extra ``cholmod``, needs the SuiteSparse system library)
or the cvxopt wheel, which bundles CHOLMOD and a single-threaded OpenBLAS and
installs with pip alone (extra ``fast``).  So, in this order:

* scalar (heat) systems, factorised once and back-solved every step:
  scikit-sparse CHOLMOD, else cvxopt's CHOLMOD, else SuperLU; cvxopt and
  SuperLU get the nested-dissection ordering (cvxopt's CHOLMOD has no METIS:
  its AMD ordering gave 1.7 times the factor nonzeros here);
* vector (elastic) systems, solved only for three adjoint right-hand sides:
  scikit-sparse CHOLMOD, else cvxopt's CHOLMOD up to
  :data:`DIRECT_ELASTIC_MAX_DOF` unknowns, else smoothed-aggregation AMG + CG
  with the rigid-body modes (pyamg, extra ``fast``), else cvxopt at any size,
  else SuperLU with nested dissection (slow above ~50k nodes).

Without a fast backend a warning names the extra to install.  The environment
variable ``HYBRIDCOMP_SOLVER`` (``auto``, ``cholmod``, ``cvxopt``, ``pyamg``,
``superlu``; ``amg`` is an alias of ``pyamg``) starts the list at that backend,
skipping the faster ones; the benchmarks measure the fallbacks with it.  A
named backend that is not installed is an error, not a silent fallback.

Threads: cvxopt's bundled OpenBLAS is built single-threaded and its CHOLMOD
uses no OpenMP, so its factorisations and solves run on the calling thread,
give bit-identical results from run to run and cannot oversubscribe the cores.
"""

from __future__ import annotations

import importlib
import logging
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from hybridcomp.errors import HybridcompError

log = logging.getLogger(__name__)

#: the backends, fastest first; ``HYBRIDCOMP_SOLVER`` names where the list starts
BACKENDS = ("cholmod", "cvxopt", "pyamg", "superlu")
_ALIASES = {"": "auto", "auto": "auto", "amg": "pyamg", **{b: b for b in BACKENDS}}
#: the module whose import proves a backend is installed, and the extra that installs it
_MODULES = {"cholmod": "sksparse.cholmod", "cvxopt": "cvxopt.cholmod", "pyamg": "pyamg"}
_EXTRAS = {"cholmod": "cholmod", "cvxopt": "fast", "pyamg": "fast"}

# HYBRIDCOMP_SOLVER: start the backend list here (benchmarks of the fallbacks)
_FORCE = os.environ.get("HYBRIDCOMP_SOLVER", "")

#: above this many unknowns the elastic adjoint solves prefer pyamg-CG to cvxopt's CHOLMOD.  Measured on
#: the demonstrator (assembly + 3 solves): 194,835 unknowns 20 s and 3.0 GB against pyamg's 44 s and 2.5 GB;
#: 267,996 unknowns 34 s and 4.4 GB against 54 s and 3.4 GB.  The factor's memory grows faster than the
#: AMG hierarchy's, so larger models take the AMG path.
DIRECT_ELASTIC_MAX_DOF = 300_000

#: a SuperLU fallback at or above this size logs a warning naming the extra
_SLOW_FALLBACK_DOF = 20_000
_warned: list[bool] = []


class MatrixNotSPDError(HybridcompError, np.linalg.LinAlgError):
    """A matrix handed to a symmetric positive definite solver is not symmetric positive definite."""


def _first_backend() -> str:
    """The backend ``HYBRIDCOMP_SOLVER`` starts the list at (``"auto"``: the fastest installed)."""
    name = _ALIASES.get(_FORCE.strip().lower())
    if name is None:
        raise ValueError(f"HYBRIDCOMP_SOLVER={_FORCE!r} is not a solver; use one of auto, {', '.join(BACKENDS)} (or amg)")
    return name


def _importable(module: str) -> bool:
    """True when ``module`` imports (the import is what a backend needs anyway, done once)."""
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def _allowed(backend: str) -> bool:
    """True when ``HYBRIDCOMP_SOLVER`` does not skip ``backend``; a skipped-to backend must be installed."""
    first = _first_backend()
    if first == "auto":
        return True
    if BACKENDS.index(backend) < BACKENDS.index(first):
        return False
    if backend == first and first in _MODULES and not _importable(_MODULES[first]):
        raise ImportError(f"HYBRIDCOMP_SOLVER={_FORCE!r} names a solver that is not installed: "
                          f"pip install 'hybridcomp[{_EXTRAS[first]}]'")
    return True


def have_cholmod() -> bool:
    """True when scikit-sparse's CHOLMOD is installed and not skipped."""
    return _allowed("cholmod") and _importable(_MODULES["cholmod"])


def have_cvxopt() -> bool:
    """True when cvxopt (bundling CHOLMOD) is installed and not skipped."""
    return _allowed("cvxopt") and _importable(_MODULES["cvxopt"])


def have_pyamg() -> bool:
    """True when pyamg is installed and not skipped."""
    return _allowed("pyamg") and _importable(_MODULES["pyamg"])


def factor_backend() -> str:
    """The backend :func:`factorize_spd` uses now: ``"cholmod"``, ``"cvxopt"`` or ``"superlu"``."""
    if have_cholmod():
        return "cholmod"
    if have_cvxopt():
        return "cvxopt"
    return "superlu"


def few_backend(n_dof: int) -> str:
    """The backend :func:`solve_spd_few` uses for ``n_dof`` unknowns.

    ``"cholmod"``, ``"cvxopt"`` (up to :data:`DIRECT_ELASTIC_MAX_DOF` unknowns, or at any
    size without pyamg), ``"pyamg"`` or ``"superlu"``.
    """
    if have_cholmod():
        return "cholmod"
    cvx = have_cvxopt()
    if cvx and (n_dof <= DIRECT_ELASTIC_MAX_DOF or _first_backend() == "cvxopt"):
        return "cvxopt"
    if have_pyamg():
        return "pyamg"
    return "cvxopt" if cvx else "superlu"


def _warn_slow(what: str, n: int) -> None:
    """Log once per process that a slow fallback runs for want of the ``fast`` extra."""
    if _first_backend() != "auto" or n < _SLOW_FALLBACK_DOF or _warned:
        return
    _warned.append(True)
    log.warning("%s of %d unknowns without CHOLMOD falls back to SuperLU (several times slower): "
                "pip install 'hybridcomp[fast]' for cvxopt's CHOLMOD and pyamg", what, n)


def check_spd_input(A: sp.spmatrix) -> sp.csc_matrix:
    """``A`` as CSC after checking it is square, finite and symmetric to round-off.

    The Cholesky backends read only one triangle, so a non-symmetric matrix
    would be solved as a different one without a word.

    Raises
    ------
    MatrixNotSPDError
        naming what is wrong with the matrix
    """
    A = sp.csc_matrix(A, dtype=float)
    n, m = A.shape
    if n != m:
        raise MatrixNotSPDError(f"an SPD solve needs a square matrix, got {n} × {m}")
    if not np.all(np.isfinite(A.data)):
        raise MatrixNotSPDError(f"the {n} × {n} matrix has {int(np.sum(~np.isfinite(A.data)))} non-finite entries")
    scale = float(np.abs(A.data).max(initial=0.0))
    asym = float(np.abs((A - A.T).data).max(initial=0.0))
    if asym > 1e-10 * scale:
        raise MatrixNotSPDError(f"the {n} × {n} matrix is not symmetric: max |A - Aᵀ| = {asym:.3e} "
                                f"against max |A| = {scale:.3e}")
    return A


def _best_split(sub: sp.coo_matrix, x: np.ndarray, min_part: float) -> tuple[float, np.ndarray, np.ndarray]:
    """The cheapest plane cut of a node set: cost, left nodes, separator nodes (masks).

    For each axis the nodes are ranked by coordinate; a cut at rank k puts the
    nodes ranked below k on the left, and the left nodes with a neighbour at
    rank k or above form the separator.  Its size for every k follows from each
    node's highest neighbour rank in one pass.  The cost is the separator size
    divided by the balance ``4 n_left n_right / m²`` (1 for halves); cuts that
    leave less than ``min_part`` of the nodes on a side are not considered.
    """
    m = x.shape[0]
    k = np.arange(m + 1)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for ax in range(x.shape[1]):
        rank = np.empty(m, np.int64)
        rank[np.argsort(x[:, ax], kind="stable")] = np.arange(m)
        top = rank.copy()
        np.maximum.at(top, sub.row, rank[sub.col])  # highest rank among each node's neighbours
        inside = top > rank  # node i separates the cuts rank_i < k <= top_i
        d = np.zeros(m + 2, np.int64)
        np.add.at(d, rank[inside] + 1, 1)
        np.add.at(d, top[inside] + 1, -1)
        sep = np.cumsum(d)[: m + 1]
        n_left, n_right = k - sep, m - k
        ok = (k >= min_part * m) & (n_right >= min_part * m) & (n_left > 0)
        cost = np.full(m + 1, np.inf)
        cost[ok] = sep[ok] * float(m) ** 2 / (4.0 * n_left[ok] * n_right[ok])
        kb = int(np.argmin(cost))
        if np.isfinite(cost[kb]) and (best is None or cost[kb] < best[0]):
            left = rank < kb
            best = (float(cost[kb]), left, left & (top >= kb))
    if best is None:
        return np.inf, np.zeros(m, bool), np.zeros(m, bool)
    return best


def nested_dissection(A: sp.spmatrix, coords: np.ndarray, leaf_size: int = 128) -> np.ndarray:
    """Fill-reducing ordering by geometric nested dissection.

    Recursively cuts the node set by the plane (normal to x, y or z, anywhere
    between 30 % and 70 % of its nodes) with the smallest separator for its
    balance; the nodes of one side that touch the other form the separator,
    numbered after both sides.  Optimal in order for grid-like 3D meshes; on
    the demonstrator (64,945 nodes) the cheapest plane instead of the median of
    the longest extent cut CHOLMOD's factor from 30.3 to 20.3 million nonzeros
    (back-solves 27 % faster).

    Parameters
    ----------
    A : sparse matrix whose pattern is the node graph
    coords : (n, d) node coordinates
    leaf_size : node sets this small are not cut further
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
        cost, left, sep = _best_split(sp.coo_matrix(A[S][:, S]), coords[S], 0.3)
        if not np.isfinite(cost):  # no cut leaves nodes on both sides: keep the set whole
            out.append(S)
            continue
        pending.append(S[sep])
        stack.append((S, True))
        stack.append((S[~left], False))
        stack.append((S[left & ~sep], False))
    perm = np.concatenate(out)
    assert perm.size == n
    return perm


@dataclass(frozen=True)
class Factor:
    """A factorised SPD matrix: ``factor(b)`` solves ``A x = b`` (b: vector or columns).

    ``nnz_factor`` is the number of stored nonzeros of the factor(s), −1 where the
    backend does not expose it (cvxopt's supernodal factor).
    """

    solve: Callable[[np.ndarray], np.ndarray]
    backend: str
    nnz_factor: int

    def __call__(self, b: np.ndarray) -> np.ndarray:
        return self.solve(b)


def _ordering(A: sp.csc_matrix, coords: np.ndarray, block: int) -> np.ndarray:
    """Nested-dissection permutation of the unknowns (``block`` per node, node-interleaved)."""
    node_graph = A if block == 1 else sp.csr_matrix(A)[::block][:, ::block]
    pn = nested_dissection(node_graph, coords)
    return (block * pn[:, None] + np.arange(block)).ravel()


def _not_pd(A: sp.spmatrix, backend: str, detail: str) -> MatrixNotSPDError:
    n = A.shape[0]
    return MatrixNotSPDError(f"the {n} × {n} matrix is not positive definite ({backend} found a non-positive pivot"
                             f"{detail}): check the supports, the material data and the time step")


def cvxopt_factor(A: sp.spmatrix, perm: np.ndarray | None = None) -> Factor:
    """Factorise an SPD matrix with the CHOLMOD bundled in the cvxopt wheel (supernodal ``L Lᵀ``).

    Parameters
    ----------
    A : sparse symmetric positive definite matrix (n × n); only its lower triangle is handed over
    perm : fill-reducing permutation of the n unknowns; default CHOLMOD's AMD ordering

    Returns
    -------
    the factor; it solves any number of right-hand sides at once (columns of ``b``)

    Raises
    ------
    MatrixNotSPDError
        when CHOLMOD meets a non-positive pivot
    """
    import cvxopt
    import cvxopt.cholmod

    A = sp.csc_matrix(A, dtype=float)
    n = A.shape[0]
    itype = np.asarray(cvxopt.matrix(0, (1, 1), "i")).dtype  # cvxopt's index type (int64 on 64-bit Linux)
    low = sp.tril(A, format="csc")
    low.sum_duplicates()
    low.sort_indices()
    cols = np.repeat(np.arange(n, dtype=itype), np.diff(low.indptr))
    S = cvxopt.spmatrix(cvxopt.matrix(low.data), cvxopt.matrix(low.indices.astype(itype)), cvxopt.matrix(cols), (n, n))
    opts = cvxopt.cholmod.options
    saved = dict(opts)
    opts.clear()
    opts["supernodal"] = 2  # always L Lᵀ: a non-positive pivot stops it instead of an indefinite L D Lᵀ
    try:
        F = cvxopt.cholmod.symbolic(S) if perm is None else \
            cvxopt.cholmod.symbolic(S, p=cvxopt.matrix(np.asarray(perm).astype(itype)))
        try:
            cvxopt.cholmod.numeric(S, F)
        except ArithmeticError as exc:
            col = f" at column {exc.args[0]} of the ordered matrix" if exc.args else ""
            raise _not_pd(A, "cvxopt-cholmod", col) from None
    finally:
        opts.clear()
        opts.update(saved)

    def solve(b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=float)
        if b.shape[0] != n:
            raise ValueError(f"right-hand side has {b.shape[0]} rows for a matrix of size {n}")
        X = cvxopt.matrix(b.reshape(n, -1))  # a copy in cvxopt's column-major dense type
        cvxopt.cholmod.solve(F, X)  # overwrites X with the solution
        return np.array(X).reshape(b.shape)

    return Factor(solve, "cvxopt-cholmod", -1)


def factorize_spd(A: sp.spmatrix, coords: np.ndarray | None = None, block: int = 1) -> Factor:
    """Factorise a sparse SPD matrix with the fastest available backend.

    Parameters
    ----------
    A : sparse symmetric positive definite matrix
    coords : (n / block, 3) coordinates of the nodes, for the nested-dissection ordering
    block : DOFs per node (3 for node-interleaved displacement)

    Returns
    -------
    the factor; ``Factor.backend`` names the backend (``cholmod``, ``cvxopt-cholmod``,
    ``superlu-nd`` or ``superlu-colamd``)

    Raises
    ------
    MatrixNotSPDError
        when the matrix is not square, finite and symmetric, or a Cholesky backend finds it not positive definite
    """
    A = check_spd_input(A)
    backend = factor_backend()
    if backend == "cholmod":
        from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # CHOLMOD warns about CSC conversions only
            try:
                f = cholesky(A)
            except CholmodNotPositiveDefiniteError as exc:
                raise _not_pd(A, "cholmod", f": {exc}") from None
        return Factor(lambda b: f(b), "cholmod", int(f.L().nnz))
    if backend == "cvxopt":
        return cvxopt_factor(A, None if coords is None else _ordering(A, coords, block))
    _warn_slow("a sparse factorisation", A.shape[0])
    if coords is None:
        lu = sla.splu(A)  # plain COLAMD: slow in 3D, used only without coordinates
        return Factor(lu.solve, "superlu-colamd", int(lu.L.nnz + lu.U.nnz))
    perm = _ordering(A, coords, block)
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

    Returns
    -------
    the solution (shaped like ``rhs``) and the backend's name (``cholmod``,
    ``cvxopt-cholmod``, ``pyamg-cg`` or ``superlu-nd``)
    """
    rhs = np.asarray(rhs, float)
    cols = rhs.reshape(rhs.shape[0], -1)
    backend = few_backend(A.shape[0])
    if backend in ("cholmod", "cvxopt"):
        f = factorize_spd(A, coords, block)
        return f(cols).reshape(rhs.shape), f.backend
    if backend == "pyamg":
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
    _warn_slow("an elastic solve", A.shape[0])
    return factorize_spd(A, coords, block)(cols).reshape(rhs.shape), "superlu-nd"
