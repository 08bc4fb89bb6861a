"""Systems exported from other FE codes or benchmark collections: ``E x' = A x + B u``, ``y = C x + D u``.

Accepted files:

* a MATLAB ``.mat`` file with variables ``A``, ``B``, ``C`` and, optionally, ``E`` (the identity when absent)
  and ``D`` (zero when absent), sparse or dense, versions 5 to 7.2 (scipy) and 7.3 (HDF5, through h5py);
* Matrix Market files: a directory holding ``A.mtx``, ``B.mtx``, ``C.mtx`` and optionally ``E.mtx``,
  ``D.mtx`` (or the path of any one of them).

Every property the reduction needs is checked first (:func:`check_system`), each refusal naming the file,
the variable and the property: real data, shapes, finite values, ``E`` symmetric positive definite, the
system stable. ``A`` may be non-symmetric. The default reduction is square-root balanced truncation
(:mod:`hybridcomp.rom.balanced`), which knows no time unit; the one-sided symmetric bases (``h2``,
``krylov``), stable by construction, apply to symmetric ``A``. The reduced model keeps ``D``.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.blas import single_blas_thread
from hybridcomp.fem.operators import ThermalOperators
from hybridcomp.models.toml import read_bytes
from hybridcomp.rom.krylov import ReductionError, ThermalSystem

NAMES = ("E", "A", "B", "C", "D")
REQUIRED = ("A", "B", "C")


class MatrixFileError(HybridcompError, ValueError):
    """An exported system is unreadable or lacks a property the reduction needs.

    The message names the file, the variable and the property.
    """


def _files(path: Path) -> dict[str, Path]:
    if path.is_dir():
        folder = path
    elif path.suffix.lower() == ".mtx":
        folder = path.parent
    else:
        raise MatrixFileError(f"{path}: expected a .mat file, a .mtx file or a directory of A.mtx, B.mtx, C.mtx "
                              "(E.mtx, D.mtx optional)")
    out = {}
    for v in NAMES:
        p = folder / f"{v}.mtx"
        if not p.is_file():
            if v in REQUIRED:
                raise MatrixFileError(f"{folder}: Matrix Market file {p.name!r} for variable {v!r} is missing")
            continue
        out[v] = p
    return out


def _real(path: Path, v: str, node) -> np.ndarray:
    """A dataset as float; MATLAB stores complex data as a compound of ``real`` and ``imag``: refused by name."""
    a = np.asarray(node)
    if a.dtype.names and "imag" in a.dtype.names or np.iscomplexobj(a):
        raise MatrixFileError(f"{path}: variable {v!r} is complex; the reductor takes real systems only "
                              "(a complex part would be cut off)")
    return np.asarray(a, float)


def _read_mat73(path: Path, raw: bytes) -> dict[str, object]:
    """The variables E, A, B, C, D of a MATLAB v7.3 file (HDF5).

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
                    data = _real(path, v, node["data"]) if "data" in node else np.zeros(jc[-1])
                    out[v] = sp.csc_matrix((data, np.asarray(node["ir"], np.int64), jc),
                                           shape=(int(node.attrs["MATLAB_sparse"]), jc.size - 1))
                else:
                    out[v] = _real(path, v, node).T
    except MatrixFileError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MatrixFileError(f"{path}: cannot read MATLAB v7.3 (HDF5) file: {exc}") from None
    return out


def _is_complex(a) -> bool:
    return np.iscomplexobj(a.data if sp.issparse(a) else np.asarray(a))


def read_matrices(path: str | Path) -> tuple[dict[str, object], str]:
    """Read ``A``, ``B``, ``C`` and, when present, ``E`` and ``D`` from a .mat file or Matrix Market files.

    Returns them (``E``/``D`` absent: not in the dict) and the SHA-256 of the file(s). Complex data is refused
    naming the variable (it would be cut to its real part).
    """
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
        missing = [v for v in REQUIRED if v not in data]
        if missing:
            found = sorted(k for k in data if not k.startswith("__"))
            raise MatrixFileError(f"{path}: variable {missing[0]!r} is missing (found: {found})")
        mats = {v: data[v] for v in NAMES if v in data}
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
    for v, a in mats.items():
        if _is_complex(a):
            raise MatrixFileError(f"{path}: variable {v!r} is complex; the reductor takes real systems only "
                                  "(a complex part would be cut off)")
        if not (sp.issparse(a) or np.issubdtype(np.asarray(a).dtype, np.number)):
            raise MatrixFileError(f"{path}: variable {v!r} is not a numeric matrix (MATLAB class "
                                  f"{np.asarray(a).dtype})")
    return mats, hsh.hexdigest()


@dataclass(frozen=True)
class ExternalSystem:
    """A checked system ``E x' = A x + B u``, ``y = C x + D u``: E symmetric positive definite, A stable.

    Attributes
    ----------
    E, A : sparse (n × n), CSR
    B : (n × m), C : (q × n), D : (q × m), dense
    symmetric : A symmetric (then every pole is real and the one-sided symmetric bases apply)
    source : the file, for messages
    """

    E: sp.csr_matrix
    A: sp.csr_matrix
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    symmetric: bool
    source: str

    @property
    def n(self) -> int:
        return self.A.shape[0]


def _dense(a) -> np.ndarray:
    return a.toarray() if sp.issparse(a) else np.asarray(a, float)


def _definite(X: sp.csr_matrix) -> bool:
    """Whether the symmetric ``X`` is positive definite.

    Cholesky up to 2,000 states, else the signs of the pivots of a symmetrically permuted LU (the inertia of
    ``X``, Sylvester).
    """
    n = X.shape[0]
    if n <= 2000:
        try:
            la.cholesky(X.toarray())
            return True
        except la.LinAlgError:
            return False
    import scipy.sparse.linalg as sla

    try:
        lu = sla.splu(sp.csc_matrix(X), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
    except RuntimeError:  # exactly singular
        return False
    if np.array_equal(lu.perm_r, lu.perm_c):
        return bool(np.all(lu.U.diagonal() > 0))
    lam = sla.eigsh(sp.csc_matrix(X), k=1, sigma=0.0, which="LM", return_eigenvectors=False)
    return bool(lam[0] > 0)  # the eigenvalue nearest 0 of a matrix with a positive diagonal


def check_system(mats: dict[str, object], source: str = "<matrices>") -> ExternalSystem:
    """Every property the reduction needs, checked before any long computation.

    A refusal names the file, the variable and the property.

    ``E`` absent: the identity. ``D`` absent: zero. ``E`` must be symmetric positive definite; ``A`` stable (a
    symmetric ``A`` negative definite; a non-symmetric one: no eigenvalue of ``(A, E)`` in the closed right half
    plane among all of them up to 400 states, among the six nearest 0 above).
    """
    from hybridcomp.rom.balanced import rightmost_eigenvalues

    A = sp.csr_matrix(mats["A"], dtype=float)
    if A.shape[0] != A.shape[1]:
        raise MatrixFileError(f"{source}: variable 'A' has shape {A.shape}, expected a square matrix")
    n = A.shape[0]
    E = sp.identity(n, format="csr") if mats.get("E") is None else sp.csr_matrix(mats["E"], dtype=float)
    B = _dense(mats["B"])
    C = _dense(mats["C"])
    B = B.reshape(n, -1) if B.ndim == 1 and B.size % max(n, 1) == 0 else B
    C = C.reshape(-1, n) if C.ndim == 1 and C.size % max(n, 1) == 0 else C
    if B.ndim != 2 or B.shape[0] != n:
        raise MatrixFileError(f"{source}: variable 'B' has shape {B.shape[0] if B.ndim == 2 else B.shape}, expected {n} "
                              f"rows (A is {n} × {n})")
    if C.ndim != 2 or C.shape[1] != n:
        raise MatrixFileError(f"{source}: variable 'C' has shape {C.shape}, expected {n} columns (A is {n} × {n})")
    q, m = C.shape[0], B.shape[1]
    D = np.zeros((q, m)) if mats.get("D") is None else _dense(mats["D"])
    if D.size == q * m and D.shape != (q, m) and min(q, m) == 1:
        D = D.reshape(q, m)
    for v, got, want in (("E", E.shape, (n, n)), ("D", D.shape, (q, m))):
        if got != want:
            raise MatrixFileError(f"{source}: variable {v!r} has shape {got}, expected {want} (A is {n} × {n}, "
                                  f"B has {m} columns, C {q} rows)")
    for v, X in (("E", E.data), ("A", A.data), ("B", B), ("C", C), ("D", D)):
        if not np.all(np.isfinite(X)):
            raise MatrixFileError(f"{source}: variable {v!r} contains NaN or infinite values")
    scale = lambda X: max(abs(X).max(), 1e-300) if X.nnz else 1.0  # noqa: E731
    asym = abs(E - E.T).max() if E.nnz else 0.0
    if asym > 1e-10 * scale(E):
        raise MatrixFileError(f"{source}: variable 'E' is not symmetric (max |E - E^T| = {asym:.3g}); the reductor "
                              "needs a symmetric positive definite E (a descriptor system with singular or "
                              "non-symmetric E is not supported)")
    E = sp.csr_matrix(0.5 * (E + E.T))
    if not _definite(E):
        raise MatrixFileError(f"{source}: variable 'E' is not positive definite (it is symmetric but indefinite or "
                              "singular); the reductor needs a symmetric positive definite E")
    symmetric = (abs(A - A.T).max() if A.nnz else 0.0) <= 1e-10 * scale(A)
    if symmetric:
        A = sp.csr_matrix(0.5 * (A + A.T))
        if not _definite(sp.csr_matrix(-A)):
            raise MatrixFileError(f"{source}: variable 'A' is symmetric but not negative definite: the system is not "
                                  "asymptotically stable (an eigenvalue of (A, E) is ≥ 0)")
    else:
        lam = rightmost_eigenvalues(E, A, symmetric=False)
        if np.max(lam.real) >= 0:
            raise MatrixFileError(f"{source}: variable 'A' makes the system unstable: (A, E) has the eigenvalue "
                                  f"{complex(lam[np.argmax(lam.real)]):.4g} with a real part ≥ 0")
    return ExternalSystem(E, A, B, C, D, bool(symmetric), source)


def system_from_matrices(mats: dict[str, object], source: str = "<matrices>") -> ThermalSystem:
    """A :class:`ThermalSystem` (M = E, K = −A, no zones) from exported matrices, after checking them.

    Needs a symmetric A; ``D`` is not part of a ThermalSystem.
    """
    return _thermal(check_system(mats, source), "krylov")


def _thermal(s: ExternalSystem, basis: str) -> ThermalSystem:
    if not s.symmetric:
        raise MatrixFileError(f"{s.source}: variable 'A' is not symmetric; the {basis} basis is a one-sided symmetric "
                              "projection and needs symmetric A (the default --basis bt takes any stable A)")
    n = s.n
    try:
        return ThermalSystem(ThermalOperators(
            M=s.E, K=sp.csr_matrix(-s.A), H=(), h_W_m2K=np.zeros(0), B=s.B, Hb=np.zeros((n, 0)), C=s.C,
            input_names=tuple(f"u{j + 1}" for j in range(s.B.shape[1])),
            output_names=tuple(f"y{i + 1}" for i in range(s.C.shape[0])),
        ))
    except ReductionError as exc:
        raise MatrixFileError(f"{s.source}: {exc}") from None


# -- the reduced model ----------------------------------------------------------------------------------------
EXTERNAL_FORMAT = "hybridcomp-external-lti"
EXTERNAL_FORMAT_VERSION = 1


@dataclass(frozen=True)
class ExternalModel:
    """A reduced exported system ``E_r x' = A_r x + B_r u``, ``y = C_r x + D u`` (any real stable model).

    Attributes
    ----------
    E, A : (r × r); B : (r × m); C : (q × r); D : (q × m), the full system's feedthrough
    V : right basis (n × r, full state ``≈ V x``), or None
    input_names, output_names : ``u1`` …, ``y1`` …
    meta : provenance (file, hash, basis, order, errors, stability)
    """

    E: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    V: np.ndarray | None = None
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict, compare=False)

    @property
    def order(self) -> int:
        return self.A.shape[0]

    def poles(self) -> np.ndarray:
        """Eigenvalues of ``(A_r, E_r)`` (complex; real parts < 0 for a stable model)."""
        return la.eigvals(self.A, self.E)

    def transfer(self, s: complex) -> np.ndarray:
        """``C_r (s E_r − A_r)^{-1} B_r + D`` (real for real ``s``)."""
        G = self.C @ la.solve(s * self.E - self.A, self.B.astype(complex)) + self.D
        return G.real if np.isreal(s) else G


def save_external(path: str | Path, model: ExternalModel) -> Path:
    """Write a reduced exported system as ``.npz`` with its JSON metadata inside (no pickles), atomically."""
    from hybridcomp.models import jsonio
    from hybridcomp.safeio import atomic_path

    path = Path(path)
    meta = {**model.meta, "format": EXTERNAL_FORMAT, "format_version": EXTERNAL_FORMAT_VERSION,
            "input_names": list(model.input_names), "output_names": list(model.output_names), "order": model.order}
    arrays = {"E": model.E, "A": model.A, "B": model.B, "C": model.C, "D": model.D,
              "meta_json": np.array(jsonio.dumps(meta))}
    if model.V is not None:
        arrays["V"] = model.V
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path


def load_external(path: str | Path) -> ExternalModel:
    """Read a model written by :func:`save_external`."""
    import json

    from hybridcomp.rom.reduced import read_npz

    path = Path(path)
    data = read_npz(path, MatrixFileError)
    meta = json.loads(str(data.get("meta_json", "{}")))
    if meta.get("format") != EXTERNAL_FORMAT or meta.get("format_version") != EXTERNAL_FORMAT_VERSION:
        raise MatrixFileError(f"{path}: field 'format' is {meta.get('format')!r} version {meta.get('format_version')!r}; "
                              f"expected {EXTERNAL_FORMAT!r} version {EXTERNAL_FORMAT_VERSION}")
    missing = [k for k in ("E", "A", "B", "C", "D") if k not in data]
    if missing:
        raise MatrixFileError(f"{path}: array {missing[0]!r} is missing")
    return ExternalModel(data["E"], data["A"], data["B"], data["C"], data["D"], data.get("V"),
                         tuple(meta["input_names"]), tuple(meta["output_names"]), meta)


# -- reduction ------------------------------------------------------------------------------------------------
BASES = ("auto", "bt", "irka", "h2", "krylov")
#: with the default basis, IRKA (from balanced truncation's model) is tried beside it up to this many states
IRKA_AUTO_MAX_STATES = 5000
#: frequency points of the H∞ error (log-spaced over the system's own band)
HINF_POINTS = 60
#: below this relative H2 error the Lyapunov figure (a difference of three terms of the size of ‖G‖²) is replaced
#: by frequency quadrature of the error itself: on a 1-D heat chain BT's 6e-8 reads 9e-6 by the Gramians
QUADRATURE_BELOW = 1e-4
#: below this relative H2 error the quadrature's transfer functions are refined in long double
#: (:func:`~hybridcomp.rom.balanced.transfer_refined`): double precision leaves about 1e-15 relative noise in each
#: ``G(iω)``, which scattered a 3e-15 error by ±15 % between quadrature grids (beyond the minimal order the
#: quadrature is refined from the start)
REFINE_BELOW = 1e-11
#: ADI tolerance of the factors whose truncations are the candidates beyond the minimal order: with 1e-13 every
#: truncation of convection–diffusion at r = 40 stopped at 1.2e-15 (pyMOR's balanced truncation: 4.5e-16), with
#: 1e-15 at 6.4e-16
BEYOND_ADI_TOL = 1e-15


def _one_sided(system: ExternalSystem, V: np.ndarray):
    """Galerkin projection ``V^T (.) V``: ``E_r, A_r, B_r, C_r`` (symmetric E_r > 0, A_r < 0 for symmetric A)."""
    return V.T @ (system.E @ V), V.T @ (system.A @ V), V.T @ system.B, system.C @ V


def _with_decoupled_states(model, order: int, slowest_rate: float, fastest_rate: float):
    """A model of the minimal realisation's order, padded with decoupled states up to ``order``.

    ``model`` is ``(E_r, A_r, B_r, C_r, V, method)``. The added states are reached by neither input nor output
    (``B = 0``, ``C = 0``), at rates log-spaced over the system's own band (so they scale with its time unit):
    the same transfer function, hence the same error, in the number of states asked for (a controller's fixed
    slot). ``V`` gets zero columns: the added states stay at zero.
    """
    Er, Ar, Br, Cr, V, method = model
    r, k = Ar.shape[0], order - Ar.shape[0]
    rates = np.geomspace(slowest_rate, fastest_rate, k) if k > 1 else np.array([slowest_rate])

    def block(X, Y):
        out = np.zeros((order, order))
        out[:r, :r], out[r:, r:] = X, Y
        return out

    return (block(Er, np.eye(k)), block(Ar, -np.diag(rates)), np.vstack([Br, np.zeros((k, Br.shape[1]))]),
            np.hstack([Cr, np.zeros((Cr.shape[0], k))]), np.hstack([V, np.zeros((V.shape[0], k))]),
            f"{method}, of the minimal realisation's order {r}, with {k} decoupled states (B = 0, C = 0) up to the "
            f"order asked for")


@single_blas_thread()  # small dense work (r × r models, n × r bases): a second BLAS thread only waits (a 10 × 10 solve
# took 4 ms with two OpenBLAS threads on the shared 2-core machine, 0.2 ms with one)
def reduce_matrices(
    path: str | Path,
    *,
    tol: float | None = None,
    order: int | None = None,
    fastest_time_s: float | None = None,
    keep_basis: bool = False,
    basis: str | None = None,
    h2_maxiter: int = 1500,
    h2_tol: float | None = None,
    h2_step: int | None = None,
    progress: bool = False,
) -> ExternalModel:
    """Reduce an exported system to an order, to a relative H2 error or to an H∞ tolerance.

    Parameters
    ----------
    path : ``.mat`` file or Matrix Market file/directory (variables A, B, C; E and D optional)
    tol : with ``bt``: the smallest order whose balanced-truncation bound ``2 Σ_{k>r} σ_k`` on the H∞ error
        (largest transfer-function error per unit input, output units) is at most ``tol``; with ``krylov``:
        its greedy estimate of that error
    order : reduce to exactly this order (or be refused saying why)
    fastest_time_s : shortest time scale to resolve, in the system's time unit (``krylov`` and ``h2`` only);
        default: from the system (its balanced model's fastest pole)
    keep_basis : keep V (n × r) for reconstructing full states
    basis : ``"auto"`` (default): balanced truncation, and at a stated order up to :data:`IRKA_AUTO_MAX_STATES`
        states also two-sided IRKA from three starts (BT's model, real shifts log-spaced over the spectrum and
        around its fastest rate), the stable model with the smallest exact error kept (by frequency quadrature
        when the errors are below :data:`QUADRATURE_BELOW`); ``"bt"``: square-root balanced truncation (any
        stable system); ``"irka"``: the best of the three IRKA runs; ``"h2"``: the one-sided
        symmetric basis with the smallest H2 error (symmetric A only; stable by construction); ``"krylov"``:
        the greedy rational Krylov basis (symmetric A only)
    h2_maxiter : L-BFGS iterations of the ``h2`` basis
    h2_tol : instead of ``order``: the relative H2 error to reach; the smallest order reaching it is found by
        bisection on the exact error (of balanced truncation, the basis asked for otherwise)
    h2_step : ignored (kept for callers of the former order grid)
    progress : a progress bar over the L-BFGS iterations (``h2``; it shows the surrogate's error and says so)

    Returns
    -------
    :class:`ExternalModel` whose ``meta`` holds the file and its SHA-256, ``h2_error_relative``
    (``‖G − G_r‖₂ / ‖G − D‖₂``, from Lyapunov equations: dense, or low-rank ADI Gramians above
    :data:`~hybridcomp.rom.balanced.DENSE_MAX_STATES` states), ``hinf_error`` / ``hinf_error_relative`` on a
    frequency grid over the system's band, ``stable`` and the poles' largest real part.
    """
    import time

    from hybridcomp.rom import balanced as bl

    basis = basis or "auto"
    if basis not in BASES:
        raise ValueError(f"basis must be one of {', '.join(BASES)}, got {basis!r}")
    if sum(v is not None for v in (order, tol, h2_tol)) != 1:
        raise ValueError("give exactly one of order, tol (an H∞ tolerance) and h2_tol (a relative H2 error)")
    if h2_tol is not None and not 0 < h2_tol < 1:
        raise ValueError(f"--h2-tol must be a relative H2 error in (0, 1), got {h2_tol}")
    if tol is not None and not tol > 0:
        raise ValueError(f"tol must be positive, got {tol}")
    if tol is not None and basis == "h2":
        raise ValueError("tol is an H∞ tolerance of the bt and krylov bases; with basis 'h2' give order or h2_tol")
    if fastest_time_s is not None and not fastest_time_s > 0:
        raise ValueError(f"--fastest-time-s must be positive, got {fastest_time_s}")
    if order is not None and order < 1:
        raise ValueError(f"--order must be a positive integer, got {order}")
    t0 = time.perf_counter()
    path = Path(path)
    mats, sha = read_matrices(path)
    system = check_system(mats, str(path))
    if basis in ("h2", "krylov"):
        _thermal(system, basis)  # refuses a non-symmetric A by name, before any long computation
    n, E, A, B, C, D = system.n, system.E, system.A, system.B, system.C, system.D
    if order is not None and order >= n:
        raise ValueError(f"--order must be between 1 and {n - 1} (the system has {n} states), got {order}")
    spec = bl.spectrum_bounds(E, A, system.symmetric)
    Zp, Zq, gram = bl.gramian_factors(E, A, B, C, system.symmetric)
    bal = bl.balance(E, Zp, Zq)
    r_max = min(n - 1, bal.max_order)
    # beyond the minimal realisation (Hankel singular values above round-off) no projection has much more to carry:
    # balanced truncations from r_max up to r (padded with decoupled states) and IRKA at r (where it runs) are
    # candidates, the exact error decides
    beyond = order is not None and order > r_max and basis in ("bt", "auto", "irka")

    def band_fast(r: int) -> float:
        """The fastest rate the balanced model of order ~2r resolves (scale-free frequency band)."""
        k = min(r_max, max(2 * r, r + 10))
        Er, Ar, _, _, _ = bl.truncate(E, A, B, C, bal, k)
        return float(np.max(np.abs(bl.reduced_poles(Er, Ar))))

    thermal = _thermal(system, basis) if basis in ("h2", "krylov") else None

    def build(r: int | None, want_tol: float | None = None):
        """(E_r, A_r, B_r, C_r, V, method) of order r."""
        if basis in ("bt", "auto", "irka"):
            Er, Ar, Br, Cr, V = bl.truncate(E, A, B, C, bal, r)
            return Er, Ar, Br, Cr, V, f"square-root balanced truncation ({gram})"
        from hybridcomp.rom.krylov import Reductor

        ft = fastest_time_s if fastest_time_s is not None else 1.0 / band_fast(r or 20)
        q, m = C.shape[0], B.shape[1]
        reductor = Reductor(thermal, np.full(q, want_tol or 1.0), np.ones(m), np.zeros((1, 0)), fastest_time_s=ft)
        if basis == "krylov":
            red = reductor.reduce(target=1.0, order=r)
            method = f"greedy rational Krylov (fastest time scale {ft:.3g})"
        else:
            from hybridcomp.rom.machine import _reduce_h2

            red, method = _reduce_h2(thermal, reductor, np.zeros((1, 0)), np.ones(m), np.ones(q), r, r, 1,
                                     lambda V: True, ft, h2_maxiter, progress=progress, hold_steady=False,
                                     surrogate_fastest_time_s=ft / 12)
        V = red.V
        return (*_one_sided(system, V), V, method)

    def err_of(model) -> float:
        Er, Ar, Br, Cr = model[:4]
        return bl.h2_error(E, A, B, C, Zp, Er, Ar, Br, Cr, system.symmetric)

    tried: list[tuple[int, float]] = []
    beyond_bt: dict[str, tuple] = {}  # beyond the minimal order: truncations of other orders, padded
    if order is not None and beyond:
        # σ_k at round-off: which truncation is best is not known from them; each candidate's exact error (by
        # quadrature) decides. Low-rank factors again to 1e-15 (their last directions are what these candidates
        # are made of); every order from the minimal one to r (or the factors' rank), square root and balancing-free
        model = _with_decoupled_states(build(r_max), order, spec.slow, spec.fast)
        bal_fine = bal
        if n > bl.dense_limit(system.symmetric):
            bal_fine = bl.balance(E, *bl.lr_adi(E, A, B, C, system.symmetric, tol=BEYOND_ADI_TOL))
        for k in range(r_max + 1, min(order, bal_fine.hsv.size) + 1):
            for label, free in (("square-root", False), ("balancing-free", True)):
                Er, Ar, Br, Cr, V = bl.truncate(E, A, B, C, bal_fine, k, balancing_free=free)
                poles = bl.reduced_poles(Er, Ar)
                if np.all(np.isfinite(poles)) and np.max(poles.real) < 0:
                    beyond_bt[f"bt{k}-{label}"] = _with_decoupled_states(
                        (Er, Ar, Br, Cr, V, f"{label} balanced truncation ({gram}; factors again to "
                                            f"{BEYOND_ADI_TOL:g} beyond the minimal order) at order {k}"),
                        order, spec.slow, spec.fast)
    elif order is not None:
        model = build(order)
    elif tol is not None and basis != "krylov":
        r = next((k for k in range(1, r_max + 1) if bal.hinf_bound(k) <= tol), r_max)
        model = build(r)
    elif tol is not None:
        model = build(None, tol)
    else:  # h2_tol: bisection on the exact error between 1 and r_max
        lo, hi, best = 0, r_max, None  # error(lo) > tol (lo = 0: the zero model), error(hi) checked below
        cache = {}

        def at(r):
            if r not in cache:
                mdl = build(r)
                cache[r] = (mdl, err_of(mdl))
                tried.append((r, cache[r][1]))
            return cache[r]

        if at(hi)[1] > h2_tol:
            best = hi
        else:
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if at(mid)[1] <= h2_tol:
                    hi = mid
                else:
                    lo = mid
            best = hi
        model = at(best)[0]
    # each candidate: (model, relative H2 error by Lyapunov equations)
    found = {"bt": (model, err_of(model) if np.max(bl.reduced_poles(model[0], model[1]).real) < 0 else np.inf)}
    # beyond the minimal order every error is far below QUADRATURE_BELOW: the candidates go to the quadrature
    # directly (0: no Lyapunov figure; it could not resolve them, and it costs a sparse solve per reduced pole)
    found |= {key: (mdl, 0.0) for key, mdl in beyond_bt.items()}
    irka_starts: dict[str, float | None] = {}
    if basis == "irka" or (basis == "auto" and n <= IRKA_AUTO_MAX_STATES and order is not None):
        # IRKA from several starts (each may end in another local optimum): BT's model, and real shifts
        # log-spaced over the system's band and over the band around its fastest rate (pyMOR's default start
        # [0.1, 10] in units of that rate / 2); the stable one with the smallest exact error is kept
        r, m_in, q_out = model[1].shape[0], B.shape[1], C.shape[0]
        starts = {} if beyond else {"balanced truncation's model": model[:4]}  # decoupled states: no directions
        starts |= {
            "shifts log-spaced over the spectrum": bl.logspaced_interpolation(spec.slow, spec.fast, r, m_in, q_out),
            "shifts log-spaced around the fastest rate": bl.logspaced_interpolation(
                spec.fast / 20, 5 * spec.fast, r, m_in, q_out)}
        best = None
        for label, s0 in starts.items():
            out, its, change = bl.irka(E, A, B, C, s0, system.symmetric, rank_tol=0.0 if beyond else 1e-13)
            if out is None or np.max(bl.reduced_poles(out[0], out[1]).real) >= 0:
                irka_starts[label] = None
                continue
            e = err_of(out)
            irka_starts[label] = e
            if best is None or e < best[1]:
                best = ((*out, f"two-sided IRKA from {label} ({its} iterations, last shift change {change:.1e}; "
                               f"BT's relative H2 error {found['bt'][1]:.3g} by {gram})"), e)
        if best is not None:
            found["irka"] = best
        elif basis == "irka":
            raise ValueError(f"IRKA at order {model[1].shape[0]} gave an unstable or collapsed model from every start; "
                             "use --basis bt")
    how = "lyapunov"
    lyapunov = {k: e for k, (_, e) in found.items()}
    if min(lyapunov.values()) < QUADRATURE_BELOW:
        # the Gramian terms cancel to round-off: integrate the errors themselves (one pass for every candidate)
        k = min(r_max, max(2 * model[1].shape[0], model[1].shape[0] + 10))
        Eb, Ab, _, _, _ = bl.truncate(E, A, B, C, bal, k)
        keys = [key for key, e in lyapunov.items() if np.isfinite(e)]
        peaks = np.concatenate([bl.reduced_poles(Eb, Ab)] + [bl.reduced_poles(found[key][0][0], found[key][0][1])
                                                            for key in keys])

        def quadrature(refined: bool) -> list[float]:
            return bl.quadrature_h2_errors((E, A, B, C, D), [(*found[key][0][:4], D) for key in keys], spec.slow,
                                           spec.fast, symmetric=system.symmetric, peaks=peaks, refined=refined)

        # beyond the minimal order the errors are at round-off: refined at once (the plain pass would be thrown away)
        refined = beyond
        q = quadrature(refined)
        if not refined and min(q) < REFINE_BELOW:  # near round-off: every transfer function again, refined
            refined = True
            q = quadrature(refined)
        if refined:
            how = "quadrature (refined)"
        found = {key: (found[key][0], q[i]) for i, key in enumerate(keys)}
        how = "quadrature" if how == "lyapunov" else how
    candidates = {key: e for key, (_, e) in found.items()} if len(found) > 1 else {}
    # another candidate replaces balanced truncation (its bound, its ordering) only when clearly better, not on a tie
    best_key = min(found, key=lambda key: found[key][1])
    pick = "irka" if basis == "irka" else best_key if found[best_key][1] < (1 - 1e-6) * found["bt"][1] else "bt"
    model, err = found[pick]
    err_lyap = lyapunov[pick]
    Er, Ar, Br, Cr, V, method = model
    poles = bl.reduced_poles(Er, Ar)
    stable = bool(np.max(poles.real) < 0)
    fast_r = float(np.max(np.abs(poles))) if poles.size else spec.fast
    omega = bl.frequency_grid(spec.slow, min(spec.fast, 100 * fast_r), HINF_POINTS)
    if n > 2000:  # a sparse complex factorisation per point: fewer points
        omega = np.r_[0.0, omega[1::3]]
    hinf, gnorm = bl.hinf_error((E, A, B, C, D), (Er, Ar, Br, Cr, D), omega, system.symmetric)
    low_rank = n > bl.dense_limit(system.symmetric)
    meta = {
        "matrices": {"file": path.name, "sha256": sha, "E": "E" in mats and mats["E"] is not None, "D": "D" in mats},
        "nodes": n,
        "order": int(Ar.shape[0]),
        "order_asked": order,
        "minimal_order": int(r_max),
        "decoupled_states": int(np.sum(~np.any(Br, axis=1) & ~np.any(Cr, axis=0))) if beyond else 0,
        "basis": basis if basis != "auto" else ("irka" if method.startswith("two-sided IRKA") else "bt"),
        "basis_asked": basis,
        "candidates_h2_error_relative": candidates,
        "irka_starts_h2_error_lyapunov": irka_starts,
        "method": method,
        "symmetric": system.symmetric,
        "spectrum": {"slowest_rate": spec.slow, "fastest_rate": spec.fast},
        "gramians": gram,
        "hankel_singular_values": [float(v) for v in bal.hsv[:min(bal.hsv.size, 200)]],
        "tol": tol,
        "hinf_bound_bt": bal.hinf_bound(int(Ar.shape[0])) if method.startswith("square-root") else None,
        "h2_error_relative": err,
        "h2_error_exact": not low_rank,
        "h2_error_note": ("relative to the H2 norm of G − D, "
                          + ("from Lyapunov equations of the error system: "
                             + ("dense Gramians" if not low_rank else
                                f"the full Gramian from low-rank ADI (relative residual ≤ {bl.ADI_TOL:g})")
                             if how == "lyapunov" else
                             "by frequency quadrature of the error ("
                             + (f"the Lyapunov figure, {err_lyap:.3g}, is below " if pick not in beyond_bt else
                                "beyond the minimal order every error is below ")
                             + f"{QUADRATURE_BELOW:g}, where the Lyapunov terms cancel to round-off"
                             + (f"; below {REFINE_BELOW:g}, each transfer function refined in long double)"
                                if how == "quadrature (refined)" else ")"))),
        "h2_error_method": how,
        "h2_error_lyapunov": err_lyap if pick not in beyond_bt else None,
        "hinf_error": hinf,
        "hinf_error_relative": hinf / gnorm if gnorm > 0 else None,
        "hinf_grid_rad_per_time_unit": [float(omega[1]), float(omega[-1]), int(omega.size)],  # and ω = 0
        "stable": stable,
        "max_pole_real_part": float(np.max(poles.real)),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    if h2_tol is not None:
        meta |= {"h2_tol": h2_tol, "h2_orders_tried": [[r, e] for r, e in sorted(tried)],
                 "h2_tol_met": err <= h2_tol}
    return ExternalModel(Er, Ar, Br, Cr, D.copy(), V if keep_basis else None,
                         tuple(f"u{j + 1}" for j in range(B.shape[1])),
                         tuple(f"y{i + 1}" for i in range(C.shape[0])), meta)


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
