"""Block rational Krylov reduction of a parametric thermal system (one-sided Galerkin).

The full system, in temperature rise ``x`` [K]::

    M x' = -(K + Σ_i h_i H_i) x + [B, h_1 H_1 1, ..., h_z H_z 1] u,    y = C x

with ``M`` (capacity) and ``K`` (conduction) symmetric, ``M`` positive definite
and ``K + Σ h_i H_i`` positive definite for every ``h > 0``.  The basis ``V``
(orthonormal, re-orthogonalised) spans, at each chosen expansion point
``(s_j, h_j)``, the block Krylov spaces of the inputs *and* of the outputs::

    (s_j M + K_hj)^-1 [B, H_i 1],   (s_j M + K_hj)^-1 M (...),  ...
    (s_j M + K_hj)^-1 C^T,          ...

Because the system is symmetric, the one-sided projection ``V^T (.) V`` with
both spaces in ``V`` interpolates the transfer function *and its first
derivative* at every point (Hermite interpolation, as a two-sided projection
would) while ``M_r`` and ``K_r + Σ h_i H_i,r`` stay symmetric positive
definite: every reduced pole is negative for every ``h > 0``, and ``h`` stays
an affine parameter of the reduced model.

Expansion points are chosen greedily from candidates ``s ∈ {0} ∪ logspace``
times sampled ``h``: at every candidate the full transfer function is computed
once (one factorisation), and the candidate with the largest weighted error of
the current reduced model gets the next block (its next moment if chosen
again), until the error estimate is below the target or the order is reached.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.operators import HasOperators, ThermalOperators
from hybridcomp.fem.solvers import Factor, factor_backend, factorize_spd

log = logging.getLogger(__name__)


class ReductionError(HybridcompError, ValueError):
    """The system cannot be reduced as given (shapes, symmetry, definiteness)."""


@dataclass(frozen=True)
class ThermalSystem(HasOperators):
    """A full-order parametric thermal system (SI units).

    Attributes
    ----------
    operators : the system, read through the attributes of :class:`~hybridcomp.fem.operators.HasOperators`:
        ``M`` capacity, symmetric positive definite (n × n, sparse) [J/K], ``K`` conduction, symmetric (n × n,
        sparse) [W/K], ``H`` unit convection per zone (sparse, n × n each) [m^2], ``h_W_m2K`` nominal
        heat-transfer coefficient per zone (z,) [W/(m^2 K)] (also ``h``), ``B`` heat input columns (n × m) [-],
        ``Hb`` ``H_i 1`` per zone (n × z) [m^2], ``C`` output rows (q × n, dense) in output units per kelvin,
        ``input_names`` and ``output_names``
    coords : (n, 3) node coordinates for the fill-reducing ordering, or None
    """

    operators: ThermalOperators
    coords: np.ndarray | None = None

    def __post_init__(self):
        for name, got, want in self.operators.shape_problems():
            raise ReductionError(f"system field {name!r} has shape {got}, expected {want}")

    @property
    def n(self) -> int:
        return self.M.shape[0]

    @property
    def h(self) -> np.ndarray:
        """Nominal heat-transfer coefficient per zone (z,) [W/(m^2 K)]."""
        return self.h_W_m2K

    def stiffness(self, h: np.ndarray) -> sp.csr_matrix:
        """K + Σ h_i H_i [W/K]."""
        A = self.K.copy()
        for hi, Hi in zip(h, self.H):
            A = A + hi * Hi
        return sp.csr_matrix(A)

    def input_matrix(self, h: np.ndarray) -> np.ndarray:
        """[B, h_i H_i 1] (n × (m + z))."""
        return np.hstack([self.B, self.Hb * np.asarray(h, float)[None, :]])

    def transfer(self, s: float, h: np.ndarray | None = None) -> np.ndarray:
        """C (s M + K_h)^-1 [B, h_i H_i 1] (q × (m + z)) at a real ``s`` [1/s] (one factorisation)."""
        h = self.h if h is None else np.asarray(h, float)
        f = factor_spd(s * self.M + self.stiffness(h), self.coords)
        # einsum, not BLAS: OpenBLAS threads left spinning after a dense product starve the sparse factorisation
        return np.einsum("ij,jk->ik", self.C, f(self.input_matrix(h)))


def factor_spd(A: sp.spmatrix, coords: np.ndarray | None) -> Factor:
    """Factorise a sparse SPD matrix: the project's solvers with coordinates or CHOLMOD, else SuperLU (MMD)."""
    if coords is not None or factor_backend() != "superlu":
        return factorize_spd(A, coords)
    lu = sla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return Factor(lu.solve, "superlu-mmd", int(lu.L.nnz + lu.U.nnz))


def orthonormal_extension(V: np.ndarray, W: np.ndarray, deflation_tol: float = 1e-10) -> np.ndarray:
    """Orthonormal columns spanning ``W`` outside ``span(V)``, most significant first.

    Columns of ``W`` are scaled to unit norm, projected out of ``V`` twice
    (classical Gram–Schmidt with re-orthogonalisation), and the remainder is
    compressed by an SVD: directions whose singular value is below
    ``deflation_tol`` (relative to the unit columns) are dropped as already
    contained in ``V`` or in the rest of the block.
    """
    W = np.array(W, dtype=float, copy=True)
    norms = np.linalg.norm(W, axis=0)
    W = W[:, norms > 0] / norms[norms > 0]
    if W.shape[1] == 0:
        return np.zeros((W.shape[0], 0))
    for _ in range(2):
        if V.shape[1]:
            W -= V @ (V.T @ W)
    Q, R = np.linalg.qr(W)
    U, S, _ = np.linalg.svd(R)
    keep = S > deflation_tol
    Qn = Q @ U[:, keep]
    # one more pass against V and a QR keep the basis orthonormal to round-off
    if V.shape[1]:
        Qn -= V @ (V.T @ Qn)
    Qn, _ = np.linalg.qr(Qn)
    return Qn


@dataclass(frozen=True)
class ExpansionPoint:
    """A point where the reduced transfer function interpolates the full one.

    Attributes
    ----------
    s : Laplace variable [1/s] (real, ≥ 0)
    h : heat-transfer coefficients per zone [W/(m^2 K)]
    moments : number of input and output moments matched (value and derivatives up to 2·moments − 1)
    complete : False when the last block was truncated to meet a requested order
    """

    s: float
    h: tuple[float, ...]
    moments: int
    complete: bool = True


@dataclass(frozen=True)
class Reduction:
    """The result of :meth:`Reductor.reduce`.

    Attributes
    ----------
    V : orthonormal basis (n × r)
    points : expansion points in the order they were added
    estimate : weighted error estimate after the last block (1 = tolerance) [-]
    history : (order, estimate) after each block
    """

    V: np.ndarray
    points: tuple[ExpansionPoint, ...]
    estimate: float
    history: tuple[tuple[int, float], ...]


def project(system: ThermalSystem, V: np.ndarray) -> dict[str, np.ndarray]:
    """Galerkin projection ``V^T (.) V`` of every operator; symmetric parts kept exactly symmetric."""

    def sym(A):
        P = V.T @ (A @ V)
        return 0.5 * (P + P.T)

    return {
        "M": sym(system.M),
        "K": sym(system.K),
        "H": np.array([sym(Hi) for Hi in system.H]).reshape(len(system.H), V.shape[1], V.shape[1]),
        "B": V.T @ system.B,
        "Hb": V.T @ system.Hb,
        "C": np.asarray(system.C @ V),
    }


def _reduced_transfer(P: dict, s: float, h: np.ndarray) -> np.ndarray:
    A = s * P["M"] + P["K"] + np.einsum("i,ijk->jk", h, P["H"])
    Bu = np.hstack([P["B"], P["Hb"] * h[None, :]])
    return P["C"] @ la.solve(A, Bu, assume_a="pos")


@dataclass
class Reductor:
    """Greedy block rational Krylov reductor of a :class:`ThermalSystem`.

    Parameters
    ----------
    system : the full-order system
    output_tol : tolerance per output, in output units (q,)
    input_scale : typical magnitude of each input (m + z,), in input units ([W], [K])
    h_samples : heat-transfer coefficient samples (k × z), the nominal first [W/(m^2 K)]
    n_s : number of non-zero expansion-point candidates per h sample
    fastest_time_s : shortest time scale the model must resolve [s]; sets the largest candidate s
    deflation_tol : relative singular value below which a Krylov direction is dropped

    The full transfer functions at the candidates are computed on first use and
    kept, so repeated :meth:`reduce` calls (tighter targets, other orders) only
    pay for the blocks they add.
    """

    system: ThermalSystem
    output_tol: np.ndarray
    input_scale: np.ndarray
    h_samples: np.ndarray
    n_s: int = 8
    fastest_time_s: float = 60.0
    deflation_tol: float = 1e-10
    _candidates: list = field(default_factory=list, repr=False)
    _full: list = field(default_factory=list, repr=False)

    def __post_init__(self):
        sysm = self.system
        self.output_tol = np.asarray(self.output_tol, float).reshape(-1)
        self.input_scale = np.asarray(self.input_scale, float).reshape(-1)
        z = len(sysm.H)
        hs = np.asarray(self.h_samples, float)
        self.h_samples = hs.reshape(-1, z) if z else np.zeros((1, 0))
        if self.output_tol.shape != (sysm.C.shape[0],) or not np.all(self.output_tol > 0):
            raise ReductionError(f"output_tol must be {sysm.C.shape[0]} positive values, got {self.output_tol}")
        if self.input_scale.shape != (len(sysm.input_names),) or not np.all(self.input_scale >= 0):
            raise ReductionError(f"input_scale must be {len(sysm.input_names)} values ≥ 0, got shape {self.input_scale.shape}")
        if self.h_samples.shape[0] == 0:
            self.h_samples = sysm.h[None, :]
        if len(sysm.H) and not np.all(self.h_samples > 0):
            raise ReductionError("every sampled heat-transfer coefficient must be positive")
        if not self.fastest_time_s > 0:
            raise ReductionError(f"fastest_time_s must be positive, got {self.fastest_time_s}")

    # -- Krylov blocks -------------------------------------------------------------------------
    def _blocks(self, s: float, h: np.ndarray, moments: int) -> np.ndarray:
        """Input and output moments 1..``moments`` at (s, h), raw (columns unnormalised)."""
        sysm = self.system
        f = factor_spd(s * sysm.M + sysm.stiffness(h), sysm.coords)
        X = f(np.hstack([sysm.B, sysm.Hb, np.asarray(sysm.C.T)]))
        out = [X]
        for _ in range(moments - 1):
            X = f(sysm.M @ X)
            X /= np.maximum(np.linalg.norm(X, axis=0), 1e-300)
            out.append(X)
        return out[-1]

    def _setup_candidates(self, V0: np.ndarray) -> None:
        """Candidates: s = 0 and log-spaced s from the slowest reduced mode to 1/fastest_time_s, per h sample."""
        sysm = self.system
        P = project(sysm, V0)
        lam = la.eigvalsh(P["K"] + np.einsum("i,ijk->jk", sysm.h, P["H"]), P["M"])
        s_lo = max(float(lam[0]), 1e-12)
        s_hi = max(1.0 / self.fastest_time_s, 10 * s_lo)
        s_values = [0.0, *np.geomspace(s_lo, s_hi, self.n_s)] if self.n_s > 0 else [0.0]
        self._candidates = [(float(s), tuple(float(v) for v in h)) for h in self.h_samples for s in s_values]
        t0 = time.perf_counter()
        self._full = [sysm.transfer(s, np.array(h)) for s, h in self._candidates]
        log.info("full transfer functions at %d candidates in %.1f s (s from %.3g to %.3g 1/s)",
                 len(self._candidates), time.perf_counter() - t0, s_values[0], s_values[-1])

    def _errors(self, V: np.ndarray) -> np.ndarray:
        """Weighted error per candidate: max over outputs of Σ_j |ΔH_ij| input_scale_j / tol_i."""
        P = project(self.system, V)
        out = np.empty(len(self._candidates))
        for c, ((s, h), Hf) in enumerate(zip(self._candidates, self._full)):
            D = np.abs(Hf - _reduced_transfer(P, s, np.array(h)))
            out[c] = np.max((D @ self.input_scale) / self.output_tol)
        return out

    def _next(self, err: np.ndarray, exhausted: set) -> tuple | None:
        """The candidate with the largest error that can still add a direction, or None."""
        for c in np.argsort(-err):
            if self._candidates[int(c)] not in exhausted:
                return self._candidates[int(c)]
        return None

    # -- the greedy loop -----------------------------------------------------------------------
    def reduce(self, target: float = 0.5, order: int | None = None, max_order: int = 400, accept=None,
               chunk: int | None = None) -> Reduction:
        """Add blocks until the weighted error estimate at every candidate is ≤ ``target`` (1 = tolerance).

        The estimate ``max_i Σ_j |ΔH_ij(s)| input_scale_j / tol_i`` bounds the
        error for all inputs at full scale with the worst signs, so it is
        pessimistic; ``accept(V) -> bool`` (for example a check against FE
        on a load case) may stop the loop earlier.  With ``order`` the loop
        instead stops at exactly that order (the last block truncated to its
        most significant directions) or earlier if the estimate falls below 1e-12.
        With ``chunk`` (tolerance mode), every block after the first is added
        ``chunk`` directions at a time, most significant first, and ``accept``
        is asked after each: a finer order for the same tolerance.
        """
        sysm = self.system
        if order is not None and not (isinstance(order, (int, np.integer)) and order >= 1):
            raise ReductionError(f"order must be a positive integer, got {order!r}")
        limit = max_order if order is None else int(order)
        h0 = tuple(float(v) for v in sysm.h)
        V = np.zeros((sysm.n, 0))
        points: list[ExpansionPoint] = []
        moments: dict[tuple, int] = {}
        history: list[tuple[int, float]] = []
        est = np.inf
        err = np.zeros(0)
        exhausted: set[tuple] = set()
        choice = (0.0, h0)
        while True:
            k = moments.get(choice, 0) + 1
            Wn = orthonormal_extension(V, self._blocks(choice[0], np.array(choice[1]), k), self.deflation_tol)
            complete = True
            if V.shape[1] + Wn.shape[1] > limit:
                Wn = Wn[:, : limit - V.shape[1]]
                complete = False
            if Wn.shape[1] == 0 and complete:
                # nothing new here (deflated): try the next-worst candidate, stop when none is left
                exhausted.add(choice)
                log.info("block at s=%g h=%s adds nothing new", choice[0], choice[1])
                choice = self._next(err, exhausted)
                if choice is None:
                    break
                continue
            if order is None and chunk and accept is not None and V.shape[1] > 0:
                for j in range(chunk, Wn.shape[1], chunk):
                    if accept(np.hstack([V, Wn[:, :j]])):
                        Wn, complete = Wn[:, :j], False
                        break
            V = np.hstack([V, Wn])
            moments[choice] = k
            points.append(ExpansionPoint(choice[0], choice[1], k, complete))
            if V.shape[1] >= limit and order is not None:
                history.append((V.shape[1], float("nan")))
                est = float("nan")
                break
            if not self._candidates:
                self._setup_candidates(V)
            err = self._errors(V)
            est = float(err.max())
            history.append((V.shape[1], est))
            log.info("order %d: estimate %.3g (block at s=%.3g, h=%s, moment %d)", V.shape[1], est, choice[0], choice[1], k)
            if V.shape[1] >= limit or est <= 1e-12:
                break
            if order is None and (est <= target or not complete or (accept is not None and accept(V))):
                break
            choice = self._next(err, exhausted)
            if choice is None:
                break
        return Reduction(V=V, points=tuple(points), estimate=est, history=tuple(history))
