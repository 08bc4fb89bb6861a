"""Fitting characteristic diagrams: input selection and sparse regularised least squares.

Unknowns are the grid-node values of every term. The normal equations are

    (AᵀA + λ·(N/N_D)·DᵀD + N·ZᵀZ + ε·I) v = Aᵀy

with A the multilinear interpolation weights of the N data rows (2^d
non-zeros per row and term), D the second differences of the values along
every input of every term (N_D rows), Z one row per additional term that
pins its mean to zero (an additive CD's terms are otherwise free to trade
constants), and ε a tiny ridge (``ridge`` × mean diagonal of AᵀA) that
keeps grid nodes without data and smoothing determined. λ is
dimensionless: λ = 1 weighs the summed squared second differences like the
summed squared residuals per row. A multilinear function has zero second
differences along each input, so it is reproduced exactly for any λ; and the
roughness ‖Dv‖² never grows with λ.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from hybridcomp._version import __version__
from hybridcomp.chardiag.cd import DIRECTIONS, TARGETS, CDError, CDInput, CharDiagram, Term, _term_weights
from hybridcomp.errors import HybridcompError
from hybridcomp.histogram.trace import position_column
from hybridcomp.models.layout import temperature_column

log = logging.getLogger(__name__)


class CDFitError(HybridcompError, ValueError):
    """Training data cannot give a CD; the message names the source, column and value."""


@dataclass(frozen=True)
class FitOptions:
    """How a CD is fitted.

    Attributes
    ----------
    n_support : support points per active input
    smoothing : second-difference smoothing weight λ [-] (0: none)
    ridge : relative Tikhonov weight ε [-]
    min_range_K : a temperature input whose training range is below this is inactive [K]
    min_range_mm : an axis input whose training range is below this is inactive [mm]
    alpha : a correlation with the target whose two-sided p-value exceeds this is insignificant [-]
    select : ``"threshold"`` (range and correlation only) or ``"bic"`` (then greedy forward selection by BIC
        of a linear model among the inputs that pass the thresholds)
    max_inputs : at most this many active inputs (the strongest by |correlation| or BIC order); None: no limit
    max_full_dims : up to this many active inputs one full tensor-grid term; above, an additive CD (one
        1-D term per input)
    min_target_range_um : a target whose range in the training data is below this gets a constant CD (its
        weighted mean, or the anchor's value): no sensor can explain a drift that hardly moves, and a fit
        would only amplify sensor noise [µm] (0: always fit)
    """

    n_support: int = 6
    smoothing: float = 1.0
    ridge: float = 1e-10
    min_range_K: float = 0.5
    min_range_mm: float = 1.0
    alpha: float = 0.01
    select: str = "threshold"
    max_inputs: int | None = None
    max_full_dims: int = 3
    min_target_range_um: float = 0.0

    def __post_init__(self):
        if int(self.n_support) != self.n_support or self.n_support < 2:
            raise CDFitError(f"n_support must be an integer ≥ 2, got {self.n_support!r}")
        for name in ("smoothing", "ridge", "min_range_K", "min_range_mm", "min_target_range_um"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise CDFitError(f"{name} must be finite and ≥ 0, got {v!r}")
        if not 0 < self.alpha < 1:
            raise CDFitError(f"alpha must be in (0, 1), got {self.alpha!r}")
        if self.select not in ("threshold", "bic"):
            raise CDFitError(f"select must be 'threshold' or 'bic', got {self.select!r}")
        if self.max_inputs is not None and self.max_inputs < 1:
            raise CDFitError(f"max_inputs must be ≥ 1 or None, got {self.max_inputs!r}")
        if self.max_full_dims < 1:
            raise CDFitError(f"max_full_dims must be ≥ 1, got {self.max_full_dims!r}")


def candidate_inputs(columns: Sequence[str], positions: bool = False) -> list[tuple[str, str]]:
    """Candidate inputs of a training table by the unit-suffix convention.

    ``T3_degC`` → ("T3", "degC"), and with ``positions`` also ``x_mm`` → ("X", "mm"); drift (``*_um``),
    ``time_s`` and anything else are not inputs. Positions are off by default: the FE training data are for one
    pose, where an axis position only says where the load was, which the temperatures already carry.
    """
    out = []
    for c in columns:
        if c.endswith("_degC"):
            out.append((c[: -len("_degC")], "degC"))
        elif positions and c.endswith("_mm"):
            out.append((c[: -len("_mm")].upper(), "mm"))
    return out


def _column(name: str, unit: str) -> str:
    return temperature_column(name) if unit == "degC" else position_column(name)


def check_table(table: Mapping[str, np.ndarray], columns: Sequence[str], source: str = "training data") -> int:
    """Number of rows; raises :class:`CDFitError` for a missing column, unequal lengths or NaN/inf values."""
    n = None
    for c in columns:
        if c not in table:
            raise CDFitError(f"{source}: column {c!r} is missing (have: {', '.join(sorted(table))})")
        v = np.asarray(table[c], float)
        if n is None:
            n = len(v)
        elif len(v) != n:
            raise CDFitError(f"{source}: column {c!r} has {len(v)} rows, expected {n}")
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise CDFitError(f"{source}: column {c!r} has {bad.size} NaN/inf value(s), first at data row {bad[0] + 1} "
                             f"(drop or fill those rows first)")
    return int(n or 0)


def select_inputs(table: Mapping[str, np.ndarray], candidates: Sequence[tuple[str, str]], target: str,
                  options: FitOptions = FitOptions(), source: str = "training data") -> tuple[CDInput, ...]:
    """Decide which candidates are active, and record why.

    A candidate is inactive when its range is below ``min_range_K`` / ``min_range_mm`` or its correlation with
    the target is insignificant (two-sided t-test at ``alpha``); with ``select="bic"`` the remaining ones enter
    greedily while the BIC of a linear model of the target falls; ``max_inputs`` keeps the strongest.
    """
    y = np.asarray(table[target], float)
    n = len(y)
    sy = float(np.std(y))
    if not sy > 0:
        raise CDFitError(f"{source}: target column {target!r} is constant ({y[0]!r}): nothing to fit")
    rows = []
    for name, unit in candidates:
        x = np.asarray(table[_column(name, unit)], float)
        lo, hi = float(x.min()), float(x.max())
        rng = hi - lo
        thr, u = (options.min_range_K, "K") if unit == "degC" else (options.min_range_mm, "mm")
        if rng < thr or rng == 0:
            rows.append([name, unit, False, lo, hi, f"range {rng:.3g} {u} < {thr:g} {u}", 0.0])
            continue
        r = float(np.corrcoef(x, y)[0, 1])
        if abs(r) >= 1.0:
            p = 0.0
        else:
            t = abs(r) * math.sqrt((n - 2) / (1.0 - r * r))
            from scipy import stats  # here: scipy.stats takes 0.5 s to import, the monitor's start-up

            p = float(2 * stats.t.sf(t, n - 2))
        if p > options.alpha:
            rows.append([name, unit, False, lo, hi, f"correlation r = {r:.3f} with {target} not significant "
                         f"(p = {p:.2g} > {options.alpha:g})", r])
            continue
        rows.append([name, unit, True, lo, hi, f"range {rng:.3g} {u}, r = {r:.3f} (p = {p:.2g})", r])
    passing = [k for k, row in enumerate(rows) if row[2]]
    if options.select == "bic" and passing:
        order, bics = _forward_bic(np.column_stack([np.asarray(table[_column(rows[k][0], rows[k][1])], float)
                                                    for k in passing]), y)
        chosen = {passing[i] for i in order}
        for rank, i in enumerate(order):
            rows[passing[i]][5] += f"; BIC forward selection: entered {rank + 1}. (BIC {bics[rank]:.1f})"
        for k in passing:
            if k not in chosen:
                rows[k][2] = False
                rows[k][5] += "; not selected: adding it does not lower the BIC"
        passing = [passing[i] for i in order]
    else:
        passing.sort(key=lambda k: -abs(rows[k][6]))
    if options.max_inputs is not None:
        for k in passing[options.max_inputs:]:
            rows[k][2] = False
            rows[k][5] += f"; dropped: max_inputs = {options.max_inputs}"
    out = tuple(CDInput(name=r[0], unit=r[1], active=bool(r[2]), min=r[3], max=r[4],
                        n_support=options.n_support if r[2] else 0, reason=r[5]) for r in rows)
    if not any(i.active for i in out):
        raise CDFitError(f"{source}: no active input for {target}: " + "; ".join(f"{i.name}: {i.reason}" for i in out))
    return out


def _forward_bic(X: np.ndarray, y: np.ndarray) -> tuple[list[int], list[float]]:
    """Greedy forward selection of columns of X for a linear model of y with intercept, by BIC."""
    n = len(y)

    def bic(cols):
        A = np.column_stack([np.ones(n), X[:, cols]]) if cols else np.ones((n, 1))
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        rss = float(np.sum((y - A @ coef) ** 2))
        return n * math.log(max(rss, 1e-300) / n) + A.shape[1] * math.log(n)

    chosen: list[int] = []
    bics: list[float] = []
    best = bic(chosen)
    while True:
        trials = [(bic(chosen + [j]), j) for j in range(X.shape[1]) if j not in chosen]
        if not trials:
            break
        b, j = min(trials)
        if b >= best:
            break
        chosen.append(j)
        bics.append(b)
        best = b
    return chosen, bics


def term_structure(inputs: Sequence[CDInput], max_full_dims: int) -> tuple[tuple[int, ...], ...]:
    """One full term over all active inputs if there are at most ``max_full_dims``, else one term per input."""
    active = tuple(k for k, i in enumerate(inputs) if i.active)
    if len(active) <= max_full_dims:
        return (active,)
    return tuple((k,) for k in active)


def _second_differences(shape: tuple[int, ...]) -> sp.csr_matrix:
    """Second differences of a C-ordered grid along every axis with at least 3 points."""
    blocks = []
    for k, m in enumerate(shape):
        if m < 3:
            continue
        d2 = sp.diags([np.ones(m - 2), -2 * np.ones(m - 2), np.ones(m - 2)], [0, 1, 2], shape=(m - 2, m))
        before = sp.identity(int(np.prod(shape[:k])), format="csr")
        after = sp.identity(int(np.prod(shape[k + 1:])), format="csr")
        blocks.append(sp.kron(sp.kron(before, d2), after, format="csr"))
    if not blocks:
        return sp.csr_matrix((0, int(np.prod(shape))))
    return sp.vstack(blocks, format="csr")


def design(inputs: Sequence[CDInput], terms: Sequence[tuple[int, ...]], X: np.ndarray) -> sp.csr_matrix:
    """Interpolation rows: (n × total grid values) with every term's multilinear weights."""
    n = X.shape[0]
    blocks = []
    for t in terms:
        idx, w, _ = _term_weights(inputs, t, X)
        size = int(np.prod([inputs[j].n_support for j in t]))
        rows = np.repeat(np.arange(n), idx.shape[1])
        blocks.append(sp.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(n, size)))
    return sp.hstack(blocks, format="csr")


def smoothing_operator(inputs: Sequence[CDInput], terms: Sequence[tuple[int, ...]]) -> sp.csr_matrix:
    """Block-diagonal second differences of all terms."""
    return sp.block_diag([_second_differences(tuple(inputs[j].n_support for j in t)) for t in terms], format="csr")


def roughness(cd: CharDiagram) -> float:
    """Sum of squared second differences of all its tables [µm²]."""
    D = smoothing_operator(cd.inputs, [t.inputs for t in cd.terms])
    v = np.concatenate([t.values.ravel() for t in cd.terms])
    return float(np.sum((D @ v) ** 2))


def solve_values(inputs: Sequence[CDInput], terms: Sequence[tuple[int, ...]], X: np.ndarray, y: np.ndarray,
                 smoothing: float, ridge: float, weights: np.ndarray | None = None,
                 anchor: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """Grid values of all terms, concatenated [µm] (see the module docstring).

    ``weights`` (n,) weigh the data rows (their sum takes the place of n); ``anchor`` = (a point (1 × inputs),
    a value [µm]) is met exactly: the normal equations are bordered by its interpolation row (a Lagrange
    multiplier), so the CD passes through it whatever the data say.
    """
    A = design(inputs, terms, X)
    n, P = A.shape
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    D = smoothing_operator(inputs, terms)
    N = (A.T @ sp.diags(w) @ A).tocsc()
    eps = ridge * max(float(N.diagonal().mean()), 1e-300)
    n = float(w.sum())
    if smoothing > 0 and D.shape[0]:
        N = N + (smoothing * n / D.shape[0]) * (D.T @ D)
    sizes = [int(np.prod([inputs[j].n_support for j in t])) for t in terms]
    if len(terms) > 1:
        starts = np.cumsum([0, *sizes])
        Z = sp.csr_matrix(
            (np.concatenate([np.full(s, 1.0 / s) for s in sizes[1:]]),
             (np.repeat(np.arange(len(sizes) - 1), sizes[1:]), np.arange(starts[1], P))),
            shape=(len(sizes) - 1, P))
        N = N + n * (Z.T @ Z)
    N = (N + eps * sp.identity(P)).tocsc()
    rhs = A.T @ (w * y)
    if anchor is None:
        return splu(N).solve(rhs)
    a = design(inputs, terms, np.atleast_2d(np.asarray(anchor[0], float)))
    K = sp.bmat([[N, a.T], [a, None]], format="csc")
    return splu(K).solve(np.append(rhs, float(anchor[1])))[:P]


def fit_cd(
    table: Mapping[str, np.ndarray],
    direction: str,
    *,
    machine: str,
    machine_sha256: str = "",
    pose_mm: Mapping[str, float] | None = None,
    candidates: Sequence[tuple[str, str]] | None = None,
    options: FitOptions = FitOptions(),
    load_case: str = "",
    signature: np.ndarray | None = None,
    t_reference_degC: Mapping[str, float] | None = None,
    source: str = "training data",
    weights: np.ndarray | None = None,
    anchor: tuple[Mapping[str, float], float] | None = None,
) -> CharDiagram:
    """Fit one CD to a training table.

    Parameters
    ----------
    table : columns by name: ``T1_degC`` ... [°C], ``x_mm`` ... [mm], and the target ``dx_um``/``dy_um``/``dz_um`` [µm]
    direction : ``"X"``, ``"Y"`` or ``"Z"``
    machine, machine_sha256, pose_mm : what the CD is for
    candidates : (name, unit) of candidate inputs; default every ``*_degC`` column (see :func:`candidate_inputs`)
    options : grid, smoothing and selection
    load_case, signature : the training load case and its signature
    t_reference_degC : structure-model sensor temperatures of the training load case [°C];
        default the mean of the table's temperature columns
    source : name of the data for error messages (a file name)
    weights : weight per table row (≥ 0, not all zero) [-]; default equal
    anchor : (input values by column name, drift [µm]): the CD passes exactly through this point (a generated
        set that continues the offsets being applied at the sensors' current values); the grid ranges are
        widened to contain it
    """
    if direction not in DIRECTIONS:
        raise CDFitError(f"direction {direction!r} is not one of {DIRECTIONS}")
    target = TARGETS[direction]
    if candidates is None:
        candidates = candidate_inputs(list(table))
    if not candidates:
        raise CDFitError(f"{source}: no candidate input columns (*_degC temperatures)")
    cols = [_column(n, u) for n, u in candidates]
    n = check_table(table, [*cols, target], source)
    X = np.column_stack([np.asarray(table[c], float) for c in cols])
    y = np.asarray(table[target], float)
    w = None
    if weights is not None:
        w = np.asarray(weights, float)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
            raise CDFitError(f"{source}: weights must be {n} finite values ≥ 0, not all zero")
    point = None
    if anchor is not None:
        values, at = anchor
        missing = [c for c in cols if c not in values]
        if missing or not math.isfinite(float(at)):
            raise CDFitError(f"{source}: anchor needs a finite value for {missing[0] if missing else target} "
                             f"(got {dict(values)}, {at!r})")
        point = np.array([float(values[c]) for c in cols])
        if not np.all(np.isfinite(point)):
            raise CDFitError(f"{source}: anchor point {dict(zip(cols, point))} is not finite")
    if float(np.ptp(y)) < options.min_target_range_um:
        # a drift that hardly moves: a constant CD over the input with the widest range
        level = float(anchor[1]) if anchor is not None else float(np.average(y, weights=w))
        k0 = int(np.argmax(np.ptp(X, axis=0)))
        lo, hi = float(X[:, k0].min()), float(X[:, k0].max())
        if point is not None:
            lo, hi = min(lo, point[k0]), max(hi, point[k0])
        if not hi > lo:
            lo, hi = lo - 0.5, hi + 0.5
        why = f"{target} spans {np.ptp(y):.3g} µm < {options.min_target_range_um:g} µm: constant CD"
        inputs = tuple(CDInput(name=nm, unit=u, active=k == k0, min=lo if k == k0 else float(X[:, k].min()),
                               max=hi if k == k0 else float(X[:, k].max()), n_support=2 if k == k0 else 0,
                               reason=why if k == k0 else "unused by a constant CD")
                       for k, (nm, u) in enumerate(candidates))
        terms = ((k0,),)
        v = np.full(2, level)
    else:
        inputs = select_inputs(table, candidates, target, options, source)
        if point is not None:
            inputs = tuple(replace(i, min=min(i.min, point[k]), max=max(i.max, point[k])) if i.active else i
                           for k, i in enumerate(inputs))
        terms = term_structure(inputs, options.max_full_dims)
        n_values = sum(int(np.prod([inputs[j].n_support for j in t])) for t in terms)
        if n < n_values:
            raise CDFitError(f"{source}: too few samples for the grid: {n} rows for {n_values} grid values of "
                             f"{target} ({sum(i.active for i in inputs)} active inputs × {options.n_support} support "
                             "points); add data or lower n_support")
        v = solve_values(inputs, terms, X, y, options.smoothing, options.ridge, w,
                         None if point is None else (point, float(anchor[1])))
    tabs = []
    off = 0
    for t in terms:
        shape = tuple(inputs[j].n_support for j in t)
        size = int(np.prod(shape))
        tabs.append(Term(inputs=t, values=v[off:off + size].reshape(shape).copy()))
        off += size
    if t_reference_degC is None:
        t_reference_degC = {name: float(np.mean(np.asarray(table[_column(name, unit)], float)))
                            for name, unit in candidates if unit == "degC"}
    cd = CharDiagram(
        machine=machine,
        machine_sha256=machine_sha256,
        pose_mm=tuple((k, float(x)) for k, x in sorted((pose_mm or {}).items())),
        direction=direction,
        inputs=inputs,
        terms=tuple(tabs),
        smoothing=float(options.smoothing),
        ridge=float(options.ridge),
        load_case=load_case,
        signature=np.asarray(signature if signature is not None else np.zeros(0), float).copy(),
        t_reference_degC=tuple((k, float(x)) for k, x in t_reference_degC.items()),
        created=datetime.now(UTC).isoformat(timespec="seconds"),
        software_version=__version__,
    )
    pred, _ = cd.evaluate(X)
    res = y - pred
    wn = np.ones(n) / n if w is None else w / w.sum()
    spread = float(np.sum(wn * (y - np.sum(wn * y)) ** 2))
    stats_ = {
        "samples": float(n),
        "rms_residual_um": float(np.sqrt(np.sum(wn * res**2))),
        "rms_target_um": float(np.sqrt(np.sum(wn * y**2))),
        "r2": float(1.0 - np.sum(wn * res**2) / spread) if spread > 0 else 0.0,
        "max_abs_residual_um": float(np.max(np.abs(res))),
        "memory_bytes": float(cd.memory_bytes),
    }
    log.info("%s: %d active inputs, %d values, rms residual %.3g µm of %.3g µm", target,
             sum(i.active for i in inputs), cd.n_values, stats_["rms_residual_um"], stats_["rms_target_um"])
    return replace(cd, fit=tuple(stats_.items()))


def fit_cd_set(table: Mapping[str, np.ndarray], **kwargs) -> dict[str, CharDiagram]:
    """The three CDs (X, Y, Z) of one pose from one training table (keyword arguments as :func:`fit_cd`)."""
    return {d: fit_cd(table, d, **kwargs) for d in DIRECTIONS}


__all__ = ["CDError", "CDFitError", "FitOptions", "candidate_inputs", "check_table", "fit_cd", "fit_cd_set",
           "roughness", "select_inputs", "solve_values", "term_structure"]
