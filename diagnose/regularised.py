"""Regularised model families of the data-only diagnosis, and a choice of them that does not swing with the folds.

Beside the beam search over named extensions (:mod:`hybridcomp.diagnose.dataonly`), each drift channel gets a ridge
regression (Tikhonov; inputs standardised on the fit rows, the intercept not penalised) of one of a few **families**:

| family | columns |
|---|---|
| ``T+lagT`` | every temperature and its first-order lags at ``TEMP_LAGS_H`` (a distributed lag) |
| ``S<n>(<signal>)+T+lagT`` | beside them the activity's power law ``a^n`` through lags of ``SOURCE_LAGS_H`` |

(the second: the heat source's first-order transfer functions with their gains fitted over a fixed bank of time
constants)

No column is selected: the weight λ decides how far the coefficients are shrunk. The family and λ are chosen on the
training rows only, by a **repeated blocked cross-validation** (``folds`` contiguous blocks of time; each repetition
shifts the blocks' boundaries by a phase drawn from ``seed``, the first repetition unshifted) and two rules:

* **stability across folds**: the folds of every repetition are pooled, so no single set of block boundaries decides;
* the **one-standard-error rule**: every (family, λ) whose mean fold error lies within one standard error (over the
  folds of one repetition) of the smallest is as good as the best, and the simplest of them is chosen: the fewest
  effective degrees of freedom ``Σ w/(w + λ)``, i.e. the most shrinkage. In how many repetitions on their own the
  choice was as good as the best is reported (its votes).

A choice made so moves little when the fold count or the phases change; :func:`fold_spread` measures by how much
(the held-out fit of the choice made with 3, 5 and 10 folds and three seeds). :func:`choose_pooled` goes one step
further: the cross-validation curves of 3, 5 and 10 folds are averaged before the rule is applied, so the choice no
longer depends on the fold count at all (the data-only diagnosis's default); only the phases (``seed``) are left to
move it. :func:`every_row_fits` gives what the family could reach if it had seen every row (NOT held out: how far
the held-out fit is from what the data allow).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hybridcomp.diagnose.data import DatasetError
from hybridcomp.diagnose.metrics import fit_percent
from hybridcomp.diagnose.problem import first_order_lag

TEMP_LAGS_H = (0.25, 1.0, 4.0)
SOURCE_LAGS_H = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
EXPONENTS = (1.0, 1.5, 2.0)
LAMBDAS = tuple(10.0 ** np.arange(-2.0, 4.01, 0.5))
REPEATS = 3  # cross-validation repetitions (phases of the blocks)
SPREAD_FOLDS = (3, 5, 10)
SPREAD_SEEDS = (0, 1, 2)


@dataclass(frozen=True)
class Family:
    """A regressor family: its name, column names and values (rows × columns)."""

    name: str
    columns: tuple[str, ...]
    X: np.ndarray = field(repr=False, compare=False)


@dataclass(frozen=True)
class RidgeModel:
    """A ridge regression fitted on some rows: standardisation, coefficients (intercept first) and the training range.

    ``A`` is ``ZᵀZ + λR`` of the fit rows (R the identity without the intercept): with the residual variance
    ``s2_um2`` it gives the coefficients' covariance ``s2 A⁻¹``, the prior of the coefficient filter
    (:mod:`hybridcomp.diagnose.updating`). ``z_lo`` / ``z_hi`` are the standardised inputs' range on the fit rows.
    """

    family: str
    lam: float
    mu: np.ndarray
    sd: np.ndarray
    coef: np.ndarray
    A: np.ndarray = field(repr=False)
    s2_um2: float
    z_lo: np.ndarray = field(repr=False)
    z_hi: np.ndarray = field(repr=False)

    def design(self, X: np.ndarray) -> np.ndarray:
        """``[1, (X − μ)/σ]``: the standardised regressors with the intercept column."""
        return np.column_stack([np.ones(len(X)), (X - self.mu) / self.sd])

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.design(X) @ self.coef


def _lag(time_s: np.ndarray, x: np.ndarray, tau_s: float, starts: np.ndarray) -> np.ndarray:
    """First-order lag restarting at every run start."""
    ends = np.r_[starts[1:], x.size]
    return np.concatenate([first_order_lag(time_s[a:b], x[a:b], tau_s) for a, b in zip(starts, ends)])


def families(time_s: np.ndarray, temps: dict[str, np.ndarray], activity: dict[str, np.ndarray],
             starts: np.ndarray | None = None) -> list[Family]:
    """The families of a dataset, fewest columns first (the order ties are broken in).

    Parameters
    ----------
    temps : temperature columns (name → values)
    activity : normalised activity signals 0..1 (name → values), e.g. the spindle speed over its maximum
    starts : first row of each run of a campaign (no lag crosses a run boundary)
    """
    if not temps:
        raise DatasetError("the regularised families need at least one temperature column '*_degC'")
    st = np.array([0]) if starts is None else np.asarray(starts)
    names = list(temps)
    T = np.column_stack([temps[n] for n in names])
    lagged = [np.column_stack([_lag(time_s, T[:, j], h * 3600.0, st) for j in range(T.shape[1])]) for h in TEMP_LAGS_H]
    cols_T = tuple(names) + tuple(f"lag({n}, {h:g} h)" for h in TEMP_LAGS_H for n in names)
    X_T = np.column_stack([T, *lagged])
    out = [Family("T+lagT", cols_T, X_T)]
    for sig, a in activity.items():
        for n in EXPONENTS:
            s = np.asarray(a, float) ** n
            S = np.column_stack([_lag(time_s, s, h * 3600.0, st) for h in SOURCE_LAGS_H])
            cols = tuple(f"lag({sig}^{n:g}, {h:g} h)" for h in SOURCE_LAGS_H)
            out.append(Family(f"S{n:g}({sig})+T+lagT", cols + cols_T, np.column_stack([S, X_T])))
    return out


def _moments(X: np.ndarray, Y: np.ndarray, rows: np.ndarray) -> tuple:
    """Row count and sums of a set of rows: n, Σx, Σxxᵀ, Σy, Σxyᵀ (X and Y centred beforehand by the caller)."""
    Xr, Yr = X[rows], Y[rows]
    return len(Xr), Xr.sum(0), Xr.T @ Xr, Yr.sum(0), Xr.T @ Yr


def _path_from_moments(m: tuple, X_out: np.ndarray, lams=LAMBDAS) -> np.ndarray:
    """Ridge predictions at ``X_out`` from the fit rows' moments ``m`` (standardised on them), one per λ."""
    n, sx, sxx, sy, sxy = m
    mu, ym = sx / n, sy / n
    C = sxx / n - np.outer(mu, mu)
    sd = np.sqrt(np.clip(np.diag(C), 0.0, None))
    sd = np.where(sd > 1e-12 * (1.0 + np.abs(mu)), sd, 1.0)
    G = n * C / np.outer(sd, sd)  # ZᵀZ of the standardised, centred fit rows
    b = (sxy - np.outer(sx, ym)) / sd[:, None]  # Zᵀ(Y − ȳ)
    w, V = np.linalg.eigh(G)
    w = np.clip(w, 0.0, None)
    Vb = V.T @ b
    Zo = (X_out - mu) / sd @ V
    return np.stack([ym + Zo @ (Vb / (w + lam)[:, None]) for lam in lams])


def zero_runs(X: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Every column of ``X`` relative to its value at the first row of each run (a campaign's own zeros)."""
    ends = np.r_[starts[1:], len(X)]
    return X - np.repeat(X[starts], ends - starts, axis=0)


def ridge_path(X: np.ndarray, Y: np.ndarray, fit_rows: np.ndarray, lams=LAMBDAS, out_rows=None) -> np.ndarray:
    """Predictions of the ridge fits on ``fit_rows``, one per λ, at ``out_rows`` (default every row).

    The inputs are standardised on ``fit_rows``, the intercept is not penalised; shape ``len(lams) × rows × channels``.
    """
    c = X[fit_rows].mean(0)
    Xc = X - c
    out = slice(None) if out_rows is None else out_rows
    return _path_from_moments(_moments(Xc, Y, fit_rows), Xc[out], lams)


def fit_ridge(family: Family, y: np.ndarray, fit_rows: np.ndarray, lam: float, s2_um2: float | None = None) -> RidgeModel:
    """The ridge regression of ``y`` on a family's columns, fitted on ``fit_rows`` with weight ``lam``.

    ``s2_um2``: the residual variance the coefficient covariance is scaled with (default: the fit's own).
    """
    X = family.X
    mu, sd = X[fit_rows].mean(0), X[fit_rows].std(0)
    sd = np.where(sd > 0, sd, 1.0)
    Z = np.column_stack([np.ones(len(X)), (X - mu) / sd])
    Zf = Z[fit_rows]
    R = np.eye(Z.shape[1])
    R[0, 0] = 0.0
    A = Zf.T @ Zf + lam * R
    coef = np.linalg.solve(A, Zf.T @ y[fit_rows])
    r = y[fit_rows] - Zf @ coef
    s2 = float(r @ r / max(r.size, 1)) if s2_um2 is None else float(s2_um2)
    return RidgeModel(family.name, float(lam), mu, sd, coef, A, s2, Zf[:, 1:].min(0), Zf[:, 1:].max(0))


def cv_blocks(train: np.ndarray, folds: int, phase: float = 0.0, runs: np.ndarray | None = None) -> list[np.ndarray]:
    """The scored rows of each fold.

    ``folds`` contiguous blocks of the training rows, their boundaries shifted by ``phase`` (a fraction of a block; a
    shifted block may wrap from the last rows to the first), or, for a campaign with two or more training runs, the runs.
    """
    rows = np.flatnonzero(train)
    if runs is not None and np.unique(runs[rows]).size >= 2:
        return [rows[runs[rows] == r] for r in np.unique(runs[rows])]
    if folds < 2 or rows.size < 4 * folds:
        raise DatasetError(f"{rows.size} training rows cannot be cut into {folds} blocks for the cross-validation "
                           "(at least 2 blocks of 4 rows)")
    shift = int(round(phase * rows.size / folds))
    return np.array_split(np.roll(rows, -shift), folds)


def fold_errors(fams: list[Family], Y: np.ndarray, train: np.ndarray, blocks: list[np.ndarray],
                cache: dict | None = None) -> np.ndarray:
    """Mean squared error of every block predicted from the other training rows: ``blocks × families × λ × channels``.

    Each fold's fit is the training rows' moments less the block's (the same fit as on those rows, exactly).
    ``cache`` keeps the training rows' moments per family between calls on the same rows.
    """
    out = np.empty((len(blocks), len(fams), len(LAMBDAS), Y.shape[1]))
    cache = {} if cache is None else cache
    for f, fam in enumerate(fams):
        if f not in cache:
            Xc = fam.X - fam.X[train].mean(0)
            cache[f] = (Xc, _moments(Xc, Y, train))
        Xc, m_all = cache[f]
        for b, rows in enumerate(blocks):
            m_b = _moments(Xc, Y, rows)
            m = tuple(a - c for a, c in zip(m_all, m_b))
            P = _path_from_moments(m, Xc[rows])
            out[b, f] = np.mean((Y[rows][None] - P) ** 2, axis=1)
    return out


@dataclass(frozen=True)
class Choice:
    """The (family, λ) chosen for a channel and the evidence: in how many repetitions it was as good as the best."""

    family: int
    lam_index: int
    votes: int
    repeats: int
    cv_mse: float  # its mean fold error over the repetitions [unit²]


def effective_dof(fams: list[Family], train: np.ndarray) -> np.ndarray:
    """Effective degrees of freedom ``Σ w/(w + λ)`` of every (family, λ): ``families × λ``.

    ``w`` are the eigenvalues of ZᵀZ on the training rows. The simpler of two fits is the one with fewer.
    """
    out = np.empty((len(fams), len(LAMBDAS)))
    for f, fam in enumerate(fams):
        Z = fam.X[train] - fam.X[train].mean(0)
        sd = Z.std(0)
        Z = Z / np.where(sd > 0, sd, 1.0)
        w = np.clip(np.linalg.eigvalsh(Z.T @ Z), 0.0, None)
        out[f] = [float(np.sum(w / (w + lam))) for lam in LAMBDAS]
    return out


def choose(errors: list[np.ndarray], dof: np.ndarray) -> list[Choice]:
    """The one-standard-error rule on the pooled repetitions, per channel.

    ``errors``: per repetition (phase of the blocks), :func:`fold_errors`' array; ``dof``: :func:`effective_dof`.
    The folds of every repetition are pooled: the mean fold error of each (family, λ), and its standard error over the
    folds of one repetition (the repetitions reuse the same rows, so they do not shrink it). Every (family, λ) within
    one standard error of the smallest mean is as good as the best; of those, the one with the fewest effective
    degrees of freedom (the most shrinkage) is chosen. ``votes`` says in how many repetitions on their own the choice
    was within one standard error of that repetition's best (its stability).
    """
    return choose_pooled([errors], dof)


def choose_pooled(errors_by_count: list[list[np.ndarray]], dof: np.ndarray) -> list[Choice]:
    """:func:`choose` on the cross-validation curves of several fold counts averaged before choosing.

    ``errors_by_count``: per fold count (e.g. 3, 5 and 10 blocks), :func:`repeated_errors`' list. Per fold count, the
    mean fold error of each (family, λ) over its pooled repetitions and its standard error over the folds of one
    repetition, as in :func:`choose`; the curves and standard errors are then averaged over the fold counts (each
    count weighs the same, however many folds it has) and the one-standard-error rule applied once. The choice no
    longer depends on the fold count; what is left is the phases' (``seed``'s). ``votes`` counts the repetitions of
    every fold count in which the choice was within one standard error of that repetition's best.
    """
    means, ses = [], []
    for errors in errors_by_count:
        E = np.concatenate(errors, axis=0)
        means.append(E.mean(0))
        ses.append(E.std(0, ddof=1) / np.sqrt(errors[0].shape[0]))
    m, se = np.mean(means, axis=0), np.mean(ses, axis=0)
    nch = m.shape[-1]
    votes = np.zeros(m.shape, int)
    reps = [Er for errors in errors_by_count for Er in errors]
    for Er in reps:
        mr = Er.mean(0)
        ser = Er.std(0, ddof=1) / np.sqrt(Er.shape[0]) if Er.shape[0] > 1 else np.zeros_like(mr)
        fl = mr.reshape(-1, nch)
        best = fl.argmin(0)
        thr = fl[best, np.arange(nch)] + ser.reshape(-1, nch)[best, np.arange(nch)]
        votes += (mr <= thr).astype(int)
    out = []
    for c in range(nch):
        mc = m[..., c]
        b = np.unravel_index(int(mc.argmin()), mc.shape)
        cand = np.argwhere(mc <= mc[b] + se[..., c][b])
        f, li = min(cand, key=lambda fl: dof[fl[0], fl[1]])
        out.append(Choice(int(f), int(li), int(votes[f, li, c]), len(reps), float(mc[f, li])))
    return out


def _phases(seed: int, repeats: int) -> list[float]:
    """The phases of the blocks of ``repeats`` cross-validation repetitions: 0, then drawn from ``seed``."""
    return [0.0] + list(np.random.default_rng(seed).uniform(0.1, 0.9, repeats - 1))


def repeated_errors(fams: list[Family], Y: np.ndarray, train: np.ndarray, folds: int, seed: int = 0,
                    repeats: int = REPEATS, runs: np.ndarray | None = None, cache: dict | None = None
                    ) -> list[np.ndarray]:
    """:func:`fold_errors` for ``repeats`` phases of the blocks: 0, then drawn from ``seed``."""
    phases = _phases(seed, repeats)
    out = []
    cache = {} if cache is None else cache
    for ph in phases:
        blocks = cv_blocks(train, folds, ph, runs)
        out.append(fold_errors(fams, Y, train, blocks, cache))
        if runs is not None and np.unique(runs[train]).size >= 2:
            break  # the runs are the folds: no phases
    return out


# ---------------------------------------------------------------------------------------------------- PLS
PLS_COMPONENTS = 20  # partial least squares: 1 … this many components are the candidates


def pls_coefficients(Z: np.ndarray, y: np.ndarray, components: int = PLS_COMPONENTS) -> np.ndarray:
    """PLS1 (NIPALS) of a centred ``y`` on centred regressors ``Z``: the coefficients of 1 … ``components``.

    ``components × columns``; where the data hold fewer components, the last is repeated. Each component takes the
    direction of ``Zᵀy`` left after the earlier ones; the coefficients of ``k`` are ``W (PᵀW)⁻¹ q`` of the first
    ``k`` weights ``W``, loadings ``P`` and inner coefficients ``q``.
    """
    Z, y = np.array(Z, float), np.array(y, float)
    p = Z.shape[1]
    W, P, q = np.zeros((p, components)), np.zeros((p, components)), np.zeros(components)
    out = np.zeros((components, p))
    k = 0
    scale = max(float(np.linalg.norm(Z)), 1e-300)
    for a in range(components):
        w = Z.T @ y
        nw = float(np.linalg.norm(w))
        if nw <= 1e-12 * scale * max(float(np.linalg.norm(y)), 1e-300):
            break
        w /= nw
        t = Z @ w
        tt = float(t @ t)
        if tt <= 1e-24 * scale**2:
            break
        W[:, a], P[:, a], q[a] = w, Z.T @ t / tt, float(y @ t) / tt
        Z -= np.outer(t, P[:, a])
        y = y - q[a] * t
        k = a + 1
        out[a] = W[:, :k] @ np.linalg.solve(P[:, :k].T @ W[:, :k], q[:k])
    out[k:] = out[k - 1] if k else 0.0
    return out


def pls_path(X: np.ndarray, Y: np.ndarray, fit_rows: np.ndarray, out_rows=None,
             components: int = PLS_COMPONENTS) -> np.ndarray:
    """Predictions of the PLS1 fits on ``fit_rows``, one per number of components 1 … ``components``.

    Each channel on its own, the inputs standardised on the fit rows; at ``out_rows`` (default every row):
    ``components × rows × channels``.
    """
    Xf = X[fit_rows]
    mu, sd = Xf.mean(0), Xf.std(0)
    sd = np.where(sd > 1e-12 * (1.0 + np.abs(mu)), sd, 1.0)
    Zf = (Xf - mu) / sd
    Zo = (X[slice(None) if out_rows is None else out_rows] - mu) / sd
    out = np.empty((components, Zo.shape[0], Y.shape[1]))
    for c in range(Y.shape[1]):
        ym = Y[fit_rows, c].mean()
        out[:, :, c] = ym + (Zo @ pls_coefficients(Zf, Y[fit_rows, c] - ym, components).T).T
    return out


def pls_repeated_errors(fams: list[Family], Y: np.ndarray, train: np.ndarray, folds: int, seed: int = 0,
                        repeats: int = REPEATS, components: int = PLS_COMPONENTS) -> list[np.ndarray]:
    """:func:`repeated_errors` for PLS: per phase, ``blocks × families × components × channels``.

    The number of components stands in place of λ; the blocks and phases are :func:`repeated_errors`' for the same
    ``seed``.
    """
    out = []
    for ph in _phases(seed, repeats):
        blocks = cv_blocks(train, folds, ph)
        E = np.empty((len(blocks), len(fams), components, Y.shape[1]))
        for f, fam in enumerate(fams):
            for b, rows in enumerate(blocks):
                fit = train.copy()
                fit[rows] = False
                E[b, f] = np.mean((Y[rows][None] - pls_path(fam.X, Y, fit, rows, components)) ** 2, axis=1)
        out.append(E)
    return out


def pls_choice_fits(fams: list[Family], Y: np.ndarray, train: np.ndarray, validation: np.ndarray,
                    seed: int = 0, fold_counts=SPREAD_FOLDS, components: int = PLS_COMPONENTS
                    ) -> tuple[list[Choice], np.ndarray]:
    """PLS chosen as the ridge is, and its fit % on the validation rows per channel.

    :func:`choose_pooled` on the curves of ``fold_counts`` folds, the simplest being the fewest components;
    ``Choice.lam_index`` is the number of components less one.
    """
    errors = [pls_repeated_errors(fams, Y, train, k, seed, components=components) for k in fold_counts]
    dof = np.tile(np.arange(1.0, components + 1.0), (len(fams), 1))
    made = choose_pooled(errors, dof)
    fits = np.empty(Y.shape[1])
    for j, c in enumerate(made):
        P = pls_path(fams[c.family].X, Y[:, [j]], train, validation, components)[c.lam_index, :, 0]
        fits[j] = fit_percent(Y[validation, j], P)
    return made, fits


def held_out_fits(fams: list[Family], Y: np.ndarray, train: np.ndarray, validation: np.ndarray) -> np.ndarray:
    """Fit % on the validation rows of every (family, λ) fitted on the training rows: ``families × λ × channels``."""
    out = np.empty((len(fams), len(LAMBDAS), Y.shape[1]))
    yv = Y[validation]
    den = np.linalg.norm(yv - yv.mean(0), axis=0)
    for f, fam in enumerate(fams):
        P = ridge_path(fam.X, Y, train, out_rows=validation)
        out[f] = 100.0 * (1.0 - np.linalg.norm(yv[None] - P, axis=1) / den)
    return out


def fold_spread(fams: list[Family], Y: np.ndarray, train: np.ndarray, validation: np.ndarray,
                held: np.ndarray | None = None, fold_counts=SPREAD_FOLDS, seeds=SPREAD_SEEDS,
                runs: np.ndarray | None = None, pooled: bool = False) -> dict:
    """The held-out fit of the choice made with each fold count and seed, per channel.

    Returns ``{"fits": {(folds, seed): [fit per channel]}, "choices": {(folds, seed): [(family, λ) per channel]},
    "made": {(folds, seed): [Choice per channel]}, "min", "max", "spread"}`` (per channel; spread = max − min). The
    validation rows only score the choices.
    ``pooled``: the choice of :func:`choose_pooled` over all ``fold_counts`` for each seed (keys
    ``(fold_counts, seed)``): the spread is then the seeds' (the phases of the blocks) alone.
    """
    held = held_out_fits(fams, Y, train, validation) if held is None else held
    dof = effective_dof(fams, train)
    fits, picks, made = {}, {}, {}
    cache: dict = {}
    by_runs = runs is not None and np.unique(runs[train]).size >= 2  # the runs are the folds: one choice
    once = None
    if pooled:
        for s in seeds:
            if once is None or not by_runs:
                once = choose_pooled([repeated_errors(fams, Y, train, k, s, runs=runs, cache=cache)
                                      for k in fold_counts], dof)
            fits[(tuple(fold_counts), s)] = [float(held[c.family, c.lam_index, j]) for j, c in enumerate(once)]
            picks[(tuple(fold_counts), s)] = [(fams[c.family].name, LAMBDAS[c.lam_index]) for c in once]
            made[(tuple(fold_counts), s)] = once
    for k in () if pooled else fold_counts:
        for s in seeds:
            if once is None or not by_runs:
                once = choose(repeated_errors(fams, Y, train, k, s, runs=runs, cache=cache), dof)
            ch = once
            fits[(k, s)] = [float(held[c.family, c.lam_index, j]) for j, c in enumerate(ch)]
            picks[(k, s)] = [(fams[c.family].name, LAMBDAS[c.lam_index]) for c in ch]
            made[(k, s)] = ch
    F = np.array(list(fits.values()))
    return {"fits": fits, "choices": picks, "made": made, "min": F.min(0), "max": F.max(0),
            "spread": F.max(0) - F.min(0)}


def every_row_fits(fams: list[Family], Y: np.ndarray, validation: np.ndarray) -> np.ndarray:
    """Fit % on the validation rows of every family fitted on EVERY row, best λ per channel: ``families × channels``.

    NOT held out (the validation rows are fitted too): what the family can represent when it has seen the rows.
    """
    every = np.ones(len(Y), bool)
    yv = Y[validation]
    den = np.linalg.norm(yv - yv.mean(0), axis=0)
    out = np.empty((len(fams), Y.shape[1]))
    for f, fam in enumerate(fams):
        P = ridge_path(fam.X, Y, every, out_rows=validation)
        out[f] = (100.0 * (1.0 - np.linalg.norm(yv[None] - P, axis=1) / den)).max(0)
    return out
