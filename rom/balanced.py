"""Balanced truncation and exact error figures for any stable system ``E x' = A x + B u``, ``y = C x + D u``.

``E`` symmetric positive definite, ``A`` any matrix with its generalized eigenvalues in the open left half plane
(symmetric or not). Nothing here knows a unit of time: every shift, frequency and tolerance is taken from the
system itself (its spectrum bounds, its Gramians), so scaling ``E`` by any factor scales every rate and leaves
every relative error unchanged.

* Gramians ``A P E^T + E P A^T + B B^T = 0`` and ``A^T Q E + E^T Q A + C^T C = 0`` as factors ``P = Z_p Z_p^T``:
  dense (through ``E = L L^T``; closed form from an eigendecomposition when ``A`` is symmetric, Bartels–Stewart
  otherwise) up to :data:`DENSE_MAX_STATES`, low-rank ADI with self-generated projection shifts above
  (:func:`lr_adi`: Benner, Kürschner and Saak 2014; one sparse factorisation per shift);
* square-root balanced truncation on those factors (:func:`balanced_truncation`);
* the relative H2 error of any stable reduced model, exactly, from the full Gramian factor and one sparse
  Sylvester solve per reduced pole (:func:`h2_error`), and the H∞ error on a frequency grid (:func:`hinf_error`).

The feedthrough ``D`` is kept by every reduced model: the error system is strictly proper, and the relative H2
error is ``‖G − G_r‖₂ / ‖G − D‖₂`` (the H2 norm of a system with ``D ≠ 0`` is infinite).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla

log = logging.getLogger(__name__)

#: up to this many states the Gramians are computed densely (symmetric A: one eigendecomposition)
DENSE_MAX_STATES = 2000
#: the same for a non-symmetric A (two Bartels–Stewart solves, several times dearer)
DENSE_MAX_STATES_NONSYMMETRIC = 1000
#: relative residual ‖W^T W‖ / ‖B^T B‖ at which low-rank ADI stops
ADI_TOL = 1e-11
#: ADI steps at most (each one sparse solve with the inputs' or outputs' columns)
ADI_MAXITER = 400


@dataclass(frozen=True)
class Spectrum:
    """Bounds of the rates ``|λ|`` of the pencil ``(A, E)`` [1/time unit of E]: the slowest and the fastest."""

    slow: float
    fast: float


def spectrum_bounds(E, A, symmetric: bool) -> Spectrum:
    """The smallest and largest ``|λ|`` of ``A v = λ E v``: shift-invert Lanczos/Arnoldi at 0, plain at the far end."""
    n = A.shape[0]
    if n <= 150:
        lam = la.eigvalsh(A.toarray(), E.toarray()) if symmetric else la.eigvals(A.toarray(), E.toarray())
        a = np.abs(lam)
        return Spectrum(float(a.min()), float(a.max()))
    A, E = sp.csc_matrix(A), sp.csc_matrix(E)
    if symmetric:
        slow = sla.eigsh(A, k=1, M=E, sigma=0.0, which="LM", return_eigenvectors=False, tol=1e-6)
        fast = sla.eigsh(A, k=1, M=E, which="LM", return_eigenvectors=False, tol=1e-3)
    else:
        slow = sla.eigs(A, k=1, M=E, sigma=0.0, which="LM", return_eigenvectors=False, tol=1e-6)
        fast = sla.eigs(A, k=1, M=E, which="LM", return_eigenvectors=False, tol=1e-3, maxiter=5000)
    return Spectrum(float(np.abs(slow).min()), float(np.abs(fast).max()))


def rightmost_eigenvalues(E, A, symmetric: bool, k: int = 6) -> np.ndarray:
    """Eigenvalues of ``(A, E)`` that decide stability.

    All of them up to 400 states (dense), else the ``k`` nearest 0 (shift-invert; for a symmetric pencil the
    rightmost, for a non-symmetric one those the slow dynamics live on).
    """
    n = A.shape[0]
    if n <= 400:
        return la.eigvalsh(A.toarray(), E.toarray()) if symmetric else la.eigvals(A.toarray(), E.toarray())
    k = min(k, n - 2)
    A, E = sp.csc_matrix(A), sp.csc_matrix(E)
    if symmetric:
        return sla.eigsh(A, k=k, M=E, sigma=0.0, which="LM", return_eigenvectors=False, tol=1e-8)
    return sla.eigs(A, k=k, M=E, sigma=0.0, which="LM", return_eigenvectors=False, tol=1e-8)


# -- Gramians --------------------------------------------------------------------------------------------------
def _factor_of(P: np.ndarray) -> np.ndarray:
    """A factor ``Z`` with ``Z Z^T ≈ P`` (P symmetric positive semi-definite), negligible directions dropped."""
    e, U = la.eigh(0.5 * (P + P.T))
    keep = e > max(e[-1], 0.0) * 1e-15
    return U[:, keep][:, ::-1] * np.sqrt(e[keep][::-1])


def dense_gramian_factors(E, A, B, C, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    """``Z_p``, ``Z_q`` densely, in the original coordinates.

    ``P = L^{-T} P̃ L^{-1}`` with ``E = L L^T`` and ``P̃`` the
    Gramian of the standard system ``(L^{-1} A L^{-T}, L^{-1} B, C L^{-T})``.
    """
    Ed = E.toarray() if sp.issparse(E) else np.asarray(E)
    Ad = A.toarray() if sp.issparse(A) else np.asarray(A)
    L = la.cholesky(0.5 * (Ed + Ed.T), lower=True)
    At = la.solve_triangular(L, la.solve_triangular(L, Ad.T, lower=True).T, lower=True)
    Bt = la.solve_triangular(L, B, lower=True)
    Ct = la.solve_triangular(L, C.T, lower=True).T
    if symmetric:
        lam, T = la.eigh(0.5 * (At + At.T))  # all negative
        b, c = T.T @ Bt, Ct @ T
        s = -(lam[:, None] + lam[None, :])
        P = T @ ((b @ b.T) / s) @ T.T
        Q = T @ ((c.T @ c) / s) @ T.T
    else:
        P = la.solve_continuous_lyapunov(At, -Bt @ Bt.T)
        Q = la.solve_continuous_lyapunov(At.T, -Ct.T @ Ct)
    back = lambda Z: la.solve_triangular(L, Z, lower=True, trans="T")  # noqa: E731  (L^{-T} Z)
    return back(_factor_of(P)), back(_factor_of(Q))


def _projection_shifts(E, A, Z: np.ndarray, symmetric: bool) -> np.ndarray:
    """Ritz values of ``(A, E)`` on ``span(Z)`` in the open left half plane (the next ADI shifts)."""
    Q = la.orth(np.hstack([Z.real, Z.imag]) if np.iscomplexobj(Z) else Z)
    if Q.shape[1] == 0:
        return np.zeros(0)
    Ar, Er = Q.T @ (A @ Q), Q.T @ (E @ Q)
    mu = la.eigvalsh(0.5 * (Ar + Ar.T), 0.5 * (Er + Er.T)) if symmetric else la.eigvals(Ar, Er)
    mu = mu[np.isfinite(mu) & (mu.real < 0)]
    if not symmetric:  # one of each conjugate pair; the pair is completed when used
        mu = mu[mu.imag >= 0]
    return np.real_if_close(mu)


def splu(K, symmetric: bool):
    """Sparse LU of ``K``.

    A symmetric pencil (symmetric ``A``, ``E``) gets a symmetric ordering and diagonal pivots (five times faster
    on 3-D FE matrices, complex ones included).
    """
    K = sp.csc_matrix(K)
    if symmetric:
        return sla.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return sla.splu(K)


def lr_adi(E, A, B: np.ndarray, C: np.ndarray, symmetric: bool, tol: float = ADI_TOL,
           maxiter: int = ADI_MAXITER) -> tuple[np.ndarray, np.ndarray]:
    """Low-rank factors ``Z_p``, ``Z_q`` of ``A P E^T + E P A^T + B B^T = 0`` and ``A^T Q E + E^T Q A + C^T C = 0``.

    Generalized LR-ADI in its residual form, both equations with the same shifts (one sparse factorisation of
    ``A + p E`` per shift serves both, the second through the transposed solve): ``V = (A + p E)^{-1} W``,
    ``W ← W − 2 Re(p) E V``, ``Z ← [Z, sqrt(−2 Re p) V]``. Shifts: the Ritz values of the pencil on the last
    blocks (projection shifts, scale-free); a complex shift is followed by its conjugate, after which the residual
    is real, and the factor is made real at the end (``Re(Z Z^H) = [Re Z, Im Z][Re Z, Im Z]^T``, exact once every
    pair is complete). An equation stops at a relative residual ``‖W^T W‖₂ / ‖B^T B‖₂ ≤ tol``.
    """
    A, E = sp.csc_matrix(A), sp.csc_matrix(E)
    Ws = [np.asarray(B, float).copy(), np.asarray(C, float).T.copy()]
    b0 = [np.linalg.norm(W.T @ W, 2) for W in Ws]
    blocks: list[list[np.ndarray]] = [[], []]
    done = [b == 0 for b in b0]
    lu0 = splu(A, symmetric)
    first = [lu0.solve(Ws[0]), lu0.solve(Ws[1], trans="T")]
    shifts = list(_projection_shifts(E, A, np.hstack(first), symmetric))
    if not shifts:
        raise np.linalg.LinAlgError("no stable Ritz value on the first Krylov block: is A stable?")
    used, res = shifts[:1], [1.0, 1.0]
    for _ in range(maxiter):
        if all(done):
            break
        if not shifts:
            last = [blk[-1] for k, blk in enumerate(blocks) if blk and not done[k]]
            shifts = list(_projection_shifts(E, A, np.hstack(last), symmetric)) or used
        p = shifts.pop(0)
        used = [p]
        pair = [p.real] if abs(np.imag(p)) <= 1e-12 * abs(p) else [p, np.conj(p)]
        for q in pair:
            lu = splu(A + q * E, symmetric)
            for k in (0, 1):
                if done[k]:
                    continue
                W = Ws[k].astype(complex) if np.iscomplexobj(q) else Ws[k]
                V = lu.solve(W) if k == 0 else lu.solve(W, trans="T")
                Ws[k] = W - 2 * np.real(q) * ((E if k == 0 else E.T) @ V)
                blocks[k].append(np.sqrt(-2 * np.real(q)) * V)
        for k in (0, 1):
            if not done[k]:
                Ws[k] = Ws[k].real if len(pair) == 2 else Ws[k]  # real after a complete conjugate pair
                res[k] = np.linalg.norm(Ws[k].T @ Ws[k], 2) / b0[k]
                done[k] = res[k] <= tol
    if not all(done):
        log.warning("LR-ADI stopped after %d steps at relative residuals %.2g, %.2g", maxiter, *res)
    out = []
    for blk in blocks:
        if not blk:
            out.append(np.zeros((A.shape[0], 0)))
            continue
        Z = np.hstack(blk)
        Z = np.hstack([Z.real, Z.imag]) if np.iscomplexobj(Z) else Z
        out.append(_compress(Z) if Z.shape[1] > Z.shape[0] else Z)  # below n columns Z costs less than its SVD
    return out[0], out[1]


def _compress(Z: np.ndarray, rtol: float = 1e-13) -> np.ndarray:
    """The same ``Z Z^T`` with fewer columns, ordered by decreasing weight (thin QR, then SVD of the triangle)."""
    Qz, R = la.qr(Z, mode="economic", overwrite_a=True, check_finite=False)
    U, s, _ = la.svd(R, full_matrices=False, overwrite_a=True, check_finite=False)
    keep = s > rtol * s[0]
    return Qz @ (U[:, keep] * s[keep])


def dense_limit(symmetric: bool) -> int:
    """The largest system whose Gramians are computed densely."""
    return DENSE_MAX_STATES if symmetric else min(DENSE_MAX_STATES, DENSE_MAX_STATES_NONSYMMETRIC)


def gramian_factors(E, A, B, C, symmetric: bool) -> tuple[np.ndarray, np.ndarray, str]:
    """``Z_p``, ``Z_q`` and how they were computed (dense up to :func:`dense_limit` states, LR-ADI above)."""
    if A.shape[0] <= dense_limit(symmetric):
        Zp, Zq = dense_gramian_factors(E, A, B, C, symmetric)
        return Zp, Zq, "dense Lyapunov" + (" (closed form, symmetric)" if symmetric else " (Bartels-Stewart)")
    Zp, Zq = lr_adi(E, A, B, C, symmetric)
    return Zp, Zq, f"low-rank ADI (projection shifts; ranks {Zp.shape[1]}, {Zq.shape[1]})"


# -- balanced truncation ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Balanced:
    """Square-root balancing of a system: the Hankel singular values and the bases of every order.

    ``V = Z_p Ṽ_r Σ_r^{-1/2}``, ``W = Z_q U_r Σ_r^{-1/2}`` from ``U Σ Ṽ^T = Z_q^T E Z_p``; ``W^T E V = I``.
    """

    hsv: np.ndarray
    Zp: np.ndarray
    Zq: np.ndarray
    U: np.ndarray
    Vt: np.ndarray

    @property
    def max_order(self) -> int:
        """Orders above this are not balanced (Hankel singular values at round-off)."""
        return int(np.sum(self.hsv > self.hsv[0] * 1e-14))

    def bases(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        s = self.hsv[:r] ** -0.5
        return self.Zp @ (self.Vt[:r].T * s), self.Zq @ (self.U[:, :r] * s)

    def hinf_bound(self, r: int) -> float:
        """``2 Σ_{k>r} σ_k``: a bound on ``‖G − G_r‖_∞`` (exact Gramians)."""
        return float(2 * self.hsv[r:].sum())


def balance(E, Zp: np.ndarray, Zq: np.ndarray) -> Balanced:
    """Square-root balancing of the Gramian factors."""
    U, s, Vt = la.svd(Zq.T @ (E @ Zp), full_matrices=False)
    return Balanced(s, Zp, Zq, U, Vt)


def truncate(E, A, B, C, bal: Balanced, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reduced ``E_r, A_r, B_r, C_r`` of order ``r`` (Petrov–Galerkin ``W^T (.) V``) and ``V``."""
    V, W = bal.bases(r)
    return W.T @ (E @ V), W.T @ (A @ V), W.T @ B, C @ V, V


# -- error figures ---------------------------------------------------------------------------------------------
def _standard(Er, Ar, Br):
    return la.solve(Er, Ar), la.solve(Er, Br)


def reduced_poles(Er: np.ndarray, Ar: np.ndarray) -> np.ndarray:
    """Eigenvalues of the reduced pencil ``(A_r, E_r)``."""
    return la.eigvals(Ar, Er)


def h2_norm_sq(C: np.ndarray, Zp: np.ndarray) -> float:
    """``‖G − D‖₂² = tr(C P C^T) = ‖C Z_p‖_F²``."""
    return float(np.sum((C @ Zp) ** 2))


def h2_error(E, A, B, C, Zp: np.ndarray, Er, Ar, Br, Cr, symmetric: bool = False) -> float:
    """Relative H2 error ``‖G − G_r‖₂ / ‖G − D‖₂`` of a stable reduced model with the full model's ``D``.

    ``‖G − G_r‖₂² = tr(C P C^T) − 2 tr(C X C_r^T) + tr(C_r P_r C_r^T)`` with ``P = Z_p Z_p^T``, the reduced
    Gramian ``P_r`` (dense) and the cross Gramian ``A X + E X A_r^T + B B_r^T = 0``, solved column by column
    in the reduced model's eigenvector basis (one sparse complex solve per reduced pole). ``inf`` if the reduced
    model is unstable. Round-off limits it to about 1e-7 relative (the three terms cancel).
    """
    As, Bs = _standard(np.asarray(Er), np.asarray(Ar), np.asarray(Br))
    mu, U = la.eig(As.T)  # As^T U = U diag(mu)
    if mu.size and np.max(mu.real) >= 0:
        return float("inf")
    n2 = h2_norm_sq(C, Zp)
    Pr = la.solve_continuous_lyapunov(As, -Bs @ Bs.T)
    nr2 = float(np.trace(Cr @ Pr @ Cr.T))
    Ab, Eb = sp.csc_matrix(A), sp.csc_matrix(E)
    R = -(B @ (Bs.T @ U))  # right-hand sides, n × r (complex)
    CY = np.zeros((C.shape[0], mu.size), complex)
    for j, m in enumerate(mu):
        if m.imag < 0 and j > 0 and mu[j - 1] == np.conj(m):  # LAPACK pairs conjugate eigenvectors
            CY[:, j] = np.conj(CY[:, j - 1])
            continue
        K = (Ab + (m if m.imag else m.real) * Eb).tocsc()
        lu = splu(K, symmetric)
        y = lu.solve(R[:, j]) if m.imag else lu.solve(np.ascontiguousarray(R[:, j].real)) + 1j * lu.solve(
            np.ascontiguousarray(R[:, j].imag))
        CY[:, j] = C @ y
    cross = float(np.real(np.trace(CY @ la.solve(U, Cr.T))))
    return float(np.sqrt(max(n2 - 2 * cross + nr2, 0.0) / n2))


def frequency_grid(slow: float, fast: float, n: int = 80) -> np.ndarray:
    """``ω = 0`` (steady state) and ``n − 1`` log-spaced angular frequencies from ``slow / 100`` to ``100 fast``."""
    return np.r_[0.0, np.logspace(np.log10(slow / 100), np.log10(100 * fast), n - 1)]


def transfer(E, A, B, C, D, s: complex, symmetric: bool = False) -> np.ndarray:
    """``C (s E − A)^{-1} B + D`` (sparse or dense)."""
    if sp.issparse(A):
        K = s * E - A if s.imag else s.real * E - A
        X = splu(K, symmetric).solve(B.astype(complex) if s.imag else np.asarray(B, float))
    else:
        X = la.solve(s * np.asarray(E) - np.asarray(A), B.astype(complex))
    X = X.reshape(A.shape[0], -1)
    return C @ X + D


def hinf_error(full, reduced, omega: np.ndarray, symmetric: bool = False) -> tuple[float, float]:
    """Largest ``σ_max(G(iω) − G_r(iω))`` over ``omega`` and ``max σ_max(G(iω))`` (both with ``D``).

    ``full`` and ``reduced`` are ``(E, A, B, C, D)``.
    """
    err, norm = 0.0, 0.0
    for w in omega:
        G = transfer(*full[:4], full[4], 1j * w, symmetric)
        Gr = transfer(*reduced[:4], reduced[4], 1j * w)
        err = max(err, la.norm(G - Gr, 2))
        norm = max(norm, la.norm(G, 2))
    return float(err), float(norm)


def quadrature_h2_error(full, reduced, slow: float, fast: float, per_decade: int = 12, symmetric: bool = False,
                        peaks: np.ndarray | None = None) -> float:
    """Relative H2 error ``‖G − G_r‖₂ / ‖G − D‖₂`` by frequency quadrature (no cancellation, unlike the Gramians).

    ``‖H‖₂² = (1/π) ∫_0^∞ ‖H(iω)‖_F² dω`` in ``t = ln ω``: Gauss–Legendre panels of a decade from ``slow/1e3``
    to ``1e3 fast``, each split at the resonances ``peaks`` (``|Im λ|`` of lightly damped poles, with panels of
    their width around them), with the tails (constant below, ``ω^{-2}`` above) added. ``full`` and ``reduced`` are
    ``(E, A, B, C, D)``.
    """
    lo, hi = np.log10(slow) - 3, np.log10(fast) + 3
    x, wts = np.polynomial.legendre.leggauss(per_decade)
    edges = list(np.arange(np.floor(lo), np.ceil(hi) + 1))
    for lam in np.asarray([] if peaks is None else peaks):
        w, d = abs(lam.imag), abs(lam.real)
        if w > 3 * d > 0:  # a resonance narrower than a third of its frequency: panels of its width around it
            at = w + d * np.array([-8, -3, -1, 0, 1, 3, 8])
            edges += list(np.log10(at[at > 0]))
    edges = np.unique(np.clip(edges, np.floor(lo), np.ceil(hi)))
    Dz = np.zeros_like(full[4])

    def f(w):
        G = transfer(*full[:4], Dz, 1j * w, symmetric)
        Gr = transfer(*reduced[:4], full[4] - reduced[4], 1j * w)
        return np.sum(np.abs(G - Gr) ** 2), np.sum(np.abs(G) ** 2)

    num = den = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        for ti, wi in zip(0.5 * (b - a) * x + 0.5 * (a + b), wts):
            w = 10.0 ** ti
            e, g = f(w)
            jac = 0.5 * (b - a) * wi * w * np.log(10)
            num += jac * e
            den += jac * g
    for w in (10.0 ** edges[0], 10.0 ** edges[-1]):  # tails: ∫ ≈ ω ‖H(iω)‖² (constant below, ω^-2 above)
        e, g = f(w)
        num += w * e
        den += w * g
    return float(np.sqrt(num / den))


# -- IRKA ------------------------------------------------------------------------------------------------------
def _real_basis(X: np.ndarray) -> np.ndarray:
    """An orthonormal real basis of the span of complex columns closed under conjugation."""
    return la.orth(np.hstack([X.real, X.imag]))


def irka(E, A, B, C, start: tuple, symmetric: bool = False, maxit: int = 30, tol: float = 1e-6):
    """Two-sided iterative rational Krylov (Gugercin, Antoulas, Beattie 2008), tangential for MIMO.

    Starts from the reduced model ``start = (E_r, A_r, B_r, C_r)`` (balanced truncation's: its mirrored poles are
    good first shifts, and scale-free). Each step: shifts ``σ_i = −λ_i`` of the reduced poles, tangential
    directions from its residues, ``V = [(σ_i E − A)^{-1} B b_i]``, ``W = [(σ_i E − A)^{-T} C^T c_i]`` (one
    sparse LU per shift pair), real bases, Petrov–Galerkin. Stops when the shifts move less than ``tol``
    (relative). Returns ``(E_r, A_r, B_r, C_r, V)``, the iterations and the last relative shift change; ``None``
    for the model if the order collapses (a real basis smaller than r).
    """
    Er, Ar, Br, Cr = (np.asarray(X) for X in start)
    r = Ar.shape[0]
    A, E = sp.csc_matrix(A), sp.csc_matrix(E)
    sigma_old, change, it = None, np.inf, 0
    V = None
    for it in range(1, maxit + 1):
        lam, Yl, Xr = la.eig(Ar, Er, left=True, right=True)
        sigma = -lam
        bt = (Yl.conj().T @ Br)  # rows: input directions
        ct = Cr @ Xr  # columns: output directions
        Vc = np.zeros((A.shape[0], r), complex)
        Wc = np.zeros((A.shape[0], r), complex)
        for i, s_ in enumerate(sigma):
            if s_.imag < 0 and i > 0 and np.isclose(sigma[i - 1], np.conj(s_)):
                Vc[:, i], Wc[:, i] = np.conj(Vc[:, i - 1]), np.conj(Wc[:, i - 1])
                continue
            K = s_ * E - A if s_.imag else s_.real * E - A
            lu = splu(K, symmetric)
            rb = B @ bt[i]
            rc = C.T @ ct[:, i]
            if s_.imag:
                Vc[:, i] = lu.solve(rb.astype(complex))
                Wc[:, i] = lu.solve(rc.astype(complex), trans="T")
            else:
                Vc[:, i] = lu.solve(np.ascontiguousarray(rb.real)) + 1j * lu.solve(np.ascontiguousarray(rb.imag))
                Wc[:, i] = (lu.solve(np.ascontiguousarray(rc.real), trans="T")
                            + 1j * lu.solve(np.ascontiguousarray(rc.imag), trans="T"))
        V, W = _real_basis(Vc), _real_basis(Wc)
        if V.shape[1] < r or W.shape[1] < r:
            return None, it, change
        V, W = V[:, :r], W[:, :r]
        Er, Ar, Br, Cr = W.T @ (E @ V), W.T @ (A @ V), W.T @ B, C @ V
        s_sorted = np.sort_complex(sigma)
        if sigma_old is not None:
            change = float(np.max(np.abs(s_sorted - sigma_old) / np.abs(s_sorted)))
            if change < tol:
                break
        sigma_old = s_sorted
    return (Er, Ar, Br, Cr, V), it, change
