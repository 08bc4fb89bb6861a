"""Systems exported from other FE codes (ANSYS, Abaqus): ``E x' = A x + B u, y = C x``.

Accepted files:

* a MATLAB ``.mat`` file with variables ``E``, ``A``, ``B``, ``C`` (sparse or dense), versions 5 to 7.2
  (scipy) and 7.3 (HDF5, through h5py);
* Matrix Market files: a directory holding ``E.mtx``, ``A.mtx``, ``B.mtx``,
  ``C.mtx`` (or the path of any one of them).

The reductor keeps the reduced system symmetric and stable by a one-sided
Galerkin projection, which needs ``E`` symmetric positive definite and ``A``
symmetric negative definite (a thermal capacity and minus a conductivity with
some convection or fixed temperature); anything else is refused with the name
of the variable.
"""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.operators import ThermalOperators
from hybridcomp.models.toml import read_bytes
from hybridcomp.rom.krylov import ReductionError, ThermalSystem

NAMES = ("E", "A", "B", "C")


class MatrixFileError(HybridcompError, ValueError):
    """An exported system is unreadable or not symmetric/definite; the message names the file and variable."""


def _files(path: Path) -> dict[str, Path]:
    if path.is_dir():
        folder = path
    elif path.suffix.lower() == ".mtx":
        folder = path.parent
    else:
        raise MatrixFileError(f"{path}: expected a .mat file, a .mtx file or a directory of E.mtx, A.mtx, B.mtx, C.mtx")
    out = {}
    for v in NAMES:
        p = folder / f"{v}.mtx"
        if not p.is_file():
            raise MatrixFileError(f"{folder}: Matrix Market file {p.name!r} for variable {v!r} is missing")
        out[v] = p
    return out


def _read_mat73(path: Path, raw: bytes) -> dict[str, object]:
    """The variables E, A, B, C of a MATLAB v7.3 file (HDF5).

    Dense arrays are stored transposed (MATLAB is column-major); a sparse matrix is a group of ``data``, ``ir``
    and ``jc`` (compressed columns) with the row count in its ``MATLAB_sparse`` attribute.
    """
    try:
        import h5py
    except ImportError:
        raise MatrixFileError(f"{path}: a MATLAB v7.3 file (HDF5) needs h5py: pip install h5py") from None
    out = {}
    try:
        with h5py.File(io.BytesIO(raw), "r") as f:
            for v in NAMES:
                if v not in f:
                    continue
                node = f[v]
                if isinstance(node, h5py.Group):
                    if "MATLAB_sparse" not in node.attrs or not {"ir", "jc"} <= set(node):
                        raise MatrixFileError(f"{path}: variable {v!r} is a group but not a MATLAB sparse matrix")
                    jc = np.asarray(node["jc"], np.int64)
                    data = np.asarray(node["data"], float) if "data" in node else np.zeros(jc[-1])
                    out[v] = sp.csc_matrix((data, np.asarray(node["ir"], np.int64), jc),
                                           shape=(int(node.attrs["MATLAB_sparse"]), jc.size - 1))
                else:
                    out[v] = np.asarray(node, float).T
    except MatrixFileError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MatrixFileError(f"{path}: cannot read MATLAB v7.3 (HDF5) file: {exc}") from None
    return out


def read_matrices(path: str | Path) -> tuple[dict[str, object], str]:
    """Read E, A, B, C from a .mat file or Matrix Market files; returns them and the SHA-256 of the file(s)."""
    path = Path(path)
    if not path.exists():
        raise MatrixFileError(f"{path}: no such file or directory")
    hsh = hashlib.sha256()
    if path.suffix.lower() == ".mat":
        import scipy.io

        raw = read_bytes(path, MatrixFileError, "MATLAB file")
        hsh.update(raw)
        try:
            data = scipy.io.loadmat(io.BytesIO(raw))
        except NotImplementedError:  # scipy reads up to v7.2; v7.3 is HDF5
            data = _read_mat73(path, raw)
        except (ValueError, OSError) as exc:
            raise MatrixFileError(f"{path}: cannot read MATLAB file: {exc}") from None
        missing = [v for v in NAMES if v not in data]
        if missing:
            found = sorted(k for k in data if not k.startswith("__"))
            raise MatrixFileError(f"{path}: variable {missing[0]!r} is missing (found: {found})")
        mats = {v: data[v] for v in NAMES}
    else:
        import scipy.io

        mats = {}
        for v, p in _files(path).items():
            raw = read_bytes(p, MatrixFileError, "Matrix Market file")
            hsh.update(raw)
            try:
                mats[v] = scipy.io.mmread(io.BytesIO(raw))
            except (ValueError, OSError) as exc:
                raise MatrixFileError(f"{p}: cannot read Matrix Market file for {v!r}: {exc}") from None
    return mats, hsh.hexdigest()


def system_from_matrices(mats: dict[str, object], source: str = "<matrices>") -> ThermalSystem:
    """A :class:`ThermalSystem` (M = E, K = −A, no zones) from exported matrices, after checking them."""
    E = sp.csr_matrix(mats["E"], dtype=float)
    A = sp.csr_matrix(mats["A"], dtype=float)
    B = mats["B"].toarray() if sp.issparse(mats["B"]) else np.asarray(mats["B"], float)
    C = mats["C"].toarray() if sp.issparse(mats["C"]) else np.asarray(mats["C"], float)
    n = E.shape[0]
    B = B.reshape(n, -1) if B.ndim == 1 else B
    C = C.reshape(1, -1) if C.ndim == 1 else C
    for v, got, want in (("E", E.shape, (n, n)), ("A", A.shape, (n, n)), ("B", B.shape[0], n), ("C", C.shape[1], n)):
        if got != want:
            raise MatrixFileError(f"{source}: variable {v!r} has shape {got}, expected {want} (E is {n} × {n})")
    for v, X in (("E", E), ("A", A)):
        asym = abs(X - X.T).max() if X.nnz else 0.0
        if asym > 1e-10 * max(abs(X).max(), 1e-300):
            raise MatrixFileError(f"{source}: variable {v!r} is not symmetric (max |{v} - {v}^T| = {asym:.3g}); "
                                  "the reductor needs symmetric E and A")
    if not (np.all(np.isfinite(E.data)) and np.all(np.isfinite(A.data)) and np.all(np.isfinite(B)) and np.all(np.isfinite(C))):
        raise MatrixFileError(f"{source}: the matrices contain NaN or infinite values")
    if np.any(E.diagonal() <= 0):
        raise MatrixFileError(f"{source}: variable 'E' must be positive definite, but its diagonal has entries ≤ 0")
    if np.any(A.diagonal() >= 0):
        raise MatrixFileError(f"{source}: variable 'A' must be negative definite, but its diagonal has entries ≥ 0")
    try:
        return ThermalSystem(ThermalOperators(
            M=E, K=sp.csr_matrix(-A), H=(), h_W_m2K=np.zeros(0), B=B, Hb=np.zeros((n, 0)), C=C,
            input_names=tuple(f"u{j + 1}" for j in range(B.shape[1])),
            output_names=tuple(f"y{i + 1}" for i in range(C.shape[0])),
        ))
    except ReductionError as exc:
        raise MatrixFileError(f"{source}: {exc}") from None


EXACT_ERROR_MAX_STATES = 4000  # up to this size the relative H2 error is computed exactly (dense modal form)


def exact_h2_error(system: ThermalSystem, V: np.ndarray) -> float:
    """Relative H2 error ``‖G − G_r‖₂ / ‖G‖₂`` of the Galerkin projection on ``V``, exactly (dense; unit weights)."""
    from hybridcomp.rom.h2 import general_h2_error, modal_form
    from hybridcomp.rom.krylov import project

    form = modal_form(system.M.toarray(), system.stiffness(system.h).toarray(), system.input_matrix(system.h), system.C)
    P = project(system, V)
    return general_h2_error(form, -P["K"], P["B"], P["C"], P["M"])


#: order of the reference model the relative H2 error is estimated against above EXACT_ERROR_MAX_STATES
ESTIMATE_REFERENCE_ORDER = 400


def estimated_h2_error(system: ThermalSystem, V: np.ndarray) -> float:
    """Relative H2 error of the Galerkin projection on ``V`` against a large rational Krylov reference model.

    The reference: every direction a greedy block rational Krylov reductor with 12 expansion points per
    candidate decade (fastest time scale 5 s) finds, up to :data:`ESTIMATE_REFERENCE_ORDER`.  An estimate, not a
    bound: it misses what the reference misses, so it reads low where the error is smallest (on rail_1357, where
    the exact error is known: 0.6277 for 0.6277 at order 10, 0.0277 for 0.0280 at 20, 0.00457 for 0.00570 at 40).
    """
    from hybridcomp.rom.h2 import general_h2_error, modal_form
    from hybridcomp.rom.krylov import Reductor, project

    q, m = system.C.shape[0], system.B.shape[1]
    ref = Reductor(system, np.ones(q), np.ones(m), np.zeros((1, 0)), n_s=12, fastest_time_s=5.0)
    R = project(system, ref.reduce(order=min(system.n - 1, ESTIMATE_REFERENCE_ORDER)).V)
    P = project(system, V)
    return general_h2_error(modal_form(R["M"], R["K"], R["B"], R["C"]), -P["K"], P["B"], P["C"], P["M"])


def reduce_matrices(
    path: str | Path,
    *,
    tol: float | None = None,
    order: int | None = None,
    fastest_time_s: float = 60.0,
    keep_basis: bool = False,
    basis: str = "krylov",
    h2_maxiter: int = 1500,
    h2_tol: float | None = None,
    h2_step: int = 5,
    progress: bool = False,
):
    """Reduce an exported system to an order or to a tolerance.

    Parameters
    ----------
    path : ``.mat`` file or Matrix Market file/directory
    tol : largest transfer-function error per unit input over the candidate
        frequencies, in the output's units (the same for every output)
    order : reduce to exactly this order instead
    fastest_time_s : shortest time scale to resolve [s]
    keep_basis : keep V (n × r) for reconstructing full states
    basis : ``"krylov"`` (greedy rational Krylov) or ``"h2"``: the one-sided basis with the smallest H2 error
        (:func:`hybridcomp.rom.h2.h2_optimal_basis` inside a large Krylov surrogate; needs ``order``). Without
        zones to cover, every direction goes to the H2 error: the ``s = 0`` block is not held, so steady states
        are matched only as well as the H2 optimum matches them
    h2_maxiter : L-BFGS iterations of the ``h2`` basis
    h2_tol : with ``basis="h2"`` instead of ``order``: the relative H2 error to reach, exactly computed; the
        order grows by ``h2_step`` (5, 10, 15 …) until the H2-optimal basis of that order reaches it (systems up
        to :data:`EXACT_ERROR_MAX_STATES` states, where the error is exact)
    h2_step : order step of ``h2_tol``
    progress : a progress bar over the L-BFGS iterations (``h2``)

    Returns
    -------
    :class:`~hybridcomp.rom.reduced.ReducedModel` whose ``meta['matrices']``
    holds the file name and its SHA-256, and ``meta['h2_error_relative']`` the relative H2 error: computed
    exactly for systems up to :data:`EXACT_ERROR_MAX_STATES` states, estimated above
    (:func:`estimated_h2_error`, ``meta['h2_error_exact']`` says which).
    """
    from hybridcomp.rom.krylov import Reductor, project
    from hybridcomp.rom.reduced import ReducedModel

    if basis not in ("krylov", "h2"):
        raise ValueError(f"basis must be 'krylov' or 'h2', got {basis!r}")
    if basis == "h2":
        if (order is None) == (h2_tol is None):
            raise ValueError("--basis h2 with --matrices needs --order or --h2-tol (exactly one): the H2-optimal "
                             "basis is built for one order, or grown until its exact relative H2 error is reached")
        if h2_tol is not None and not 0 < h2_tol < 1:
            raise ValueError(f"--h2-tol must be a relative H2 error in (0, 1), got {h2_tol}")
        if h2_step < 1:
            raise ValueError(f"h2_step must be at least 1, got {h2_step}")
        if tol is not None:
            raise ValueError("tol is the krylov basis's tolerance; with basis 'h2' give h2_tol (a relative H2 error)")
    else:
        if h2_tol is not None:
            raise ValueError("--h2-tol applies with --basis h2 only")
        if (tol is None) == (order is None):
            raise ValueError("give exactly one of tol and order")
    if tol is not None and not tol > 0:
        raise ValueError(f"tol must be positive, got {tol}")
    path = Path(path)
    mats, sha = read_matrices(path)
    system = system_from_matrices(mats, str(path))
    q = system.C.shape[0]
    if order is not None and not 1 <= order < system.n:
        raise ValueError(f"--order must be between 1 and {system.n - 1} (the system has {system.n} states), got {order}")
    if h2_tol is not None and system.n > EXACT_ERROR_MAX_STATES:
        raise ValueError(f"--h2-tol needs the exact H2 error, computed up to {EXACT_ERROR_MAX_STATES} states; "
                         f"{path.name} has {system.n}: give --order")
    reductor = Reductor(system, np.full(q, tol if tol is not None else 1.0), np.ones(system.B.shape[1]),
                        np.zeros((1, 0)), fastest_time_s=fastest_time_s)
    tried = []
    if basis == "h2":
        from hybridcomp.rom.machine import _reduce_h2

        def h2_basis(r):
            return _reduce_h2(system, reductor, np.zeros((1, 0)), np.ones(system.B.shape[1]), np.ones(q), r, r, 1,
                              lambda V: True, fastest_time_s, h2_maxiter, progress=progress, hold_steady=False)

        if order is not None:
            red, method = h2_basis(order)
        else:
            for r in range(h2_step, system.n, h2_step):
                red, method = h2_basis(r)
                tried.append((red.V.shape[1], exact_h2_error(system, red.V)))
                if tried[-1][1] <= h2_tol:
                    break
            method += f"; order grown by {h2_step} to relative H2 error {h2_tol:g}"
    else:
        red, method = reductor.reduce(target=1.0, order=order), "greedy rational Krylov"
    P = project(system, red.V)
    exact = system.n <= EXACT_ERROR_MAX_STATES
    if tried:
        err = tried[-1][1]
    else:
        err = exact_h2_error(system, red.V) if exact else estimated_h2_error(system, red.V)
    meta = {
        "matrices": {"file": path.name, "sha256": sha},
        "nodes": system.n,
        "order": red.V.shape[1],
        "basis": basis,
        "method": method,
        "tol": tol,
        "estimate": (red.estimate if tol is None else red.estimate * tol) if np.isfinite(red.estimate) else None,
        "h2_error_relative": err,
        "h2_error_exact": exact,
        "h2_error_note": ("exact (dense modal form of the full system)" if exact else
                          f"estimated: more than {EXACT_ERROR_MAX_STATES} states, so against a rational Krylov "
                          f"reference model of order up to {ESTIMATE_REFERENCE_ORDER} (not a bound: it reads low where "
                          "the error is smallest)"),
        "expansion_points": [{"s_1_s": p.s, "moments": p.moments, "complete": p.complete} for p in red.points],
    }
    if h2_tol is not None:
        meta |= {"h2_tol": h2_tol, "h2_orders_tried": [[r, e] for r, e in tried], "h2_tol_met": err <= h2_tol}
    return ReducedModel(ThermalOperators(M=P["M"], K=P["K"], H=P["H"], h_W_m2K=np.zeros(0), B=P["B"], Hb=P["Hb"],
                                         C=P["C"], input_names=system.input_names, output_names=system.output_names),
                        V=red.V if keep_basis else None, meta=meta)


def plate_system(n_side: int = 20, seed: int = 0) -> dict[str, object]:
    """A many-input, many-output heat-conduction system to try the reductors on (``E``, ``A``, ``B``, ``C``).

    A square plate on an ``n_side × n_side`` grid: random conductances between neighbours (0.5–2), convection
    (0.3) to a zero ambient at the edges, capacities 0.8–1.2; five heated 2 × 2 patches as inputs, four
    measured points as outputs. Symmetric ``E`` > 0 and ``A`` < 0, ``n_side²`` states. Write it with
    ``scipy.io.savemat`` to reduce it with ``hybridcomp reduce --matrices``.
    """
    if n_side < 20:
        raise ValueError(f"n_side must be at least 20 (the patches and points are placed on a 20 x 20 layout), got {n_side}")
    rng = np.random.default_rng(seed)
    n = n_side * n_side
    idx = np.arange(n).reshape(n_side, n_side)
    ia = np.r_[idx[:, :-1].ravel(), idx[:-1, :].ravel()]  # the two ends of every edge between neighbours
    ib = np.r_[idx[:, 1:].ravel(), idx[1:, :].ravel()]
    k = rng.uniform(0.5, 2.0, ia.size)
    G = sp.coo_matrix((np.r_[k, k], (np.r_[ia, ib], np.r_[ib, ia])), shape=(n, n)).tocsr()
    edge = np.zeros((n_side, n_side))
    edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = 0.3
    K = sp.diags(np.asarray(G.sum(axis=1)).ravel() + edge.ravel()) - G
    E = sp.diags(rng.uniform(800.0, 1200.0, n))  # time constants from about 2 min to hours, as in a machine part
    s = n_side / 20.0  # the layout scales with the plate
    B = np.zeros((n, 5))
    for j, (i0, j0) in enumerate([(3, 3), (3, 15), (10, 10), (16, 4), (15, 15)]):
        i0, j0 = int(i0 * s), int(j0 * s)
        B[idx[i0:i0 + 2, j0:j0 + 2].ravel(), j] = 1.0
    C = np.zeros((4, n))
    for i, (i0, j0) in enumerate([(5, 5), (5, 14), (12, 8), (18, 18)]):
        C[i, idx[int(i0 * s), int(j0 * s)]] = 1.0
    return {"E": E.tocsr(), "A": (-K).tocsr(), "B": B, "C": C}
