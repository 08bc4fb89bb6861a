"""Diagnosis on a dataset alone (``--data-only``): no FE model, the model under test is a compensation model.

The model under test is a multiple linear regression of each measured drift channel (``*_um``) on the
temperature sensors (``*_degC``), inputs selected greedily by BIC on the training part.  The candidate
extensions are data-side, each a named, parametrised regressor or model structure:

| kind | parameters | regressor |
|---|---|---|
| ``activity_lag`` | signal, exponent n, τ [h] | first-order lag of an activity signal (``*_rpm`` speed, ``*_mm`` axis speed), normalised, to the power n |
| ``heating_cooling`` | signal, τ heating, τ cooling [h] | a lag whose time constant differs while the signal rises (heating) and falls (cooling) |
| ``sensor_lag`` | sensor, τ [h] | ``T − lag_τ(T)``: the sensor lags the structure it stands for (a lead term) |
| ``ambient_tf`` | air column, τ [h] | ``lag_τ(T_air)``: the structure follows the air through a first-order lag (the ambient model) |
| ``autoregressive`` | τ [h] | output-error AR(1): ``ŷ_k = a ŷ_{k−1} + (1 − a) x_kᵀβ``, i.e. every regressor through one lag |
| ``add_input`` / ``drop_input`` | sensor | a temperature input the BIC selection left out / took in |

The search: starting from the BIC-selected regression, a step adds one extension term, drops one sensor input
or puts every regressor through the AR lag; a step is allowed when the training BIC drops by ``MIN_BIC_DROP``
and the fit that chooses rises by ``MIN_FIT_GAIN`` points. That fit is, by default (``selection="held-out"``),
a blocked cross-validation on the training rows (contiguous blocks of time, each predicted by the model fitted
on the others): no choice sees the validation rows, which score the chosen model once — a held-out fit. With
``selection="assisted"`` it is the validation fit itself (the method as first published).  A beam search keeps the ``BEAM_WIDTH`` best models of
each step (width 1 is greedy forward selection; on the real spindle test widths 1, 4, 8, 16 and 32 reach a
validation fit of 73–93 %, 78–96 %, 85–95 %, 87–95 % and 88–96 % over the five channels).  Every candidate
extension of a model is scored at once in closed form (its column's part orthogonal to the model's columns gives
its coefficient and the drop of the residual sum of squares), so a search of a few thousand models takes seconds.

When assisted, the validation part takes part in the selection, so its fit is an optimistic estimate of a
fresh dataset's. The *selection check* says by how much: it repeats the whole selection on the first half of
the validation part only and scores the result on the second half, which took no part in it.
"""  # noqa: E501 - the rows of the table above do not wrap

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hybridcomp.diagnose import regularised as reg
from hybridcomp.diagnose.data import Dataset, DatasetError, Split, check_channels
from hybridcomp.diagnose.metrics import channel_metrics
from hybridcomp.diagnose.problem import first_order_lag
from hybridcomp.diagnose.updating import (
    choose_coefficient_settings,
    choose_settings,
    coefficient_updating,
    probe_rows,
    updated_prediction,
)
from hybridcomp.models import jsonio
from hybridcomp.safeio import write_text_atomic

log = logging.getLogger(__name__)

LAGS_H = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
EXPONENTS = (1.0, 1.5, 2.0)
MAX_INPUTS = 16
SPLIT_LAGS_H = (0.25, 0.5, 1.0, 2.0, 4.0)
SENSOR_LAGS_H = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
AR_H = (0.05, 0.1, 0.25, 0.5, 1.0)
MIN_FIT_GAIN = 0.5  # validation fit points an extension must add
MIN_BIC_DROP = 10.0
BEAM_WIDTH = 16  # models kept per search step
MAX_ROWS = 50_000  # longer datasets are thinned to every k-th row (the library's time constants are 6 min and longer)


@dataclass(frozen=True)
class Term:
    """A regressor: its name, the extension kind that made it, its parameters and values."""

    name: str
    kind: str
    params: dict
    values: np.ndarray = field(repr=False, compare=False)


@dataclass(frozen=True)
class ChannelModel:
    """The regression of one channel: terms, optional AR lag, coefficients and predictions."""

    channel: str
    terms: tuple[Term, ...]
    ar_tau_h: float | None
    coef: np.ndarray
    y_hat: np.ndarray


@dataclass(frozen=True)
class DataOnlyDiagnosis:
    """Per channel: the reference, the model under test and the extended model.

    The static regression of all temperatures is the reference, the BIC-selected regression the model under test;
    the extended model comes with its named extensions and gains.
    """

    time_s: np.ndarray
    Y: dict
    split: Split
    reference: dict
    base: dict
    extended: dict
    extensions: dict  # channel -> list of dicts (name, kind, parameters, gain)
    timings_s: dict
    selection_check: dict | None = None  # the selection repeated on half the validation part, scored on the other
    selection: str = "held-out"  # "held-out": every choice on the training rows (blocked CV); "assisted": not
    folds: int = 3
    runs: np.ndarray | None = None  # a campaign's run number per row (Y and the predictions relative to each run's start)
    criterion: str = "bic"  # the information criterion of the input selection and the search: "bic" or "bicc"
    # post-process gain updating on the validation rows (None without probes): per channel the settings chosen on the
    # training rows, the probe rows, the updated prediction and (gain, offset) per validation row
    updating: dict | None = None
    # the regularised families beside the search (None when switched off): per channel the chosen family and λ,
    # its prediction at every row, the held-out fits of the choice made with other fold counts and seeds, and the
    # family fitted on every row (NOT held out); see :mod:`hybridcomp.diagnose.regularised`
    regularised: dict | None = None
    # coefficient updating of the regularised model on the validation rows (None without probes or without it)
    coefficient_updating: dict | None = None

    @property
    def criterion_name(self) -> str:
        return {"bic": "BIC", "bicc": "BICc"}[self.criterion]


def per_run(fn, starts: np.ndarray, time_s: np.ndarray, x: np.ndarray, *args) -> np.ndarray:
    """``fn(time_s, x, *args)`` on each run separately: no lag or filter state crosses a run boundary."""
    if len(starts) <= 1:
        return fn(time_s, x, *args)
    return np.concatenate([fn(time_s[a:b], x[a:b], *args) for a, b in zip(starts, np.r_[starts[1:], len(x)])])


def zero_runs(x: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Each run relative to its first row.

    Each run has its own zero: a dial gauge zeroed at the start, a cold machine at that day's air.
    """
    ends = np.r_[starts[1:], len(x)]
    return x - np.repeat(x[starts], ends - starts)


def _activity_signals(ds: Dataset) -> dict[str, np.ndarray]:
    """Normalised activity 0..1: |speed| / max for ``*_rpm``; axis speed |Δx/Δt| / max for ``*_mm``."""
    out = {}
    t = ds.time_s
    starts = ds.run_starts()
    for n in ds.names:
        v = ds[n]
        if n.endswith("_rpm"):
            a = np.abs(v)
        elif n.endswith("_mm"):
            a = np.r_[0.0, np.abs(np.diff(v)) / np.diff(t)]
            a[starts] = 0.0  # no axis speed across a run boundary
        else:
            continue
        if a.max() > 0:
            out[n] = a / a.max()
    return out


def heating_cooling_lag(time_s: np.ndarray, s: np.ndarray, tau_heat_s: float, tau_cool_s: float) -> np.ndarray:
    """A first-order lag with time constant ``tau_heat_s`` while the input is above the state, else ``tau_cool_s`` [s]."""
    t = np.asarray(time_s, float)
    dts = np.diff(t)
    ah = np.exp(-dts / tau_heat_s)
    ac = np.exp(-dts / tau_cool_s)
    x = np.empty_like(s)
    x[0] = s[0]
    xk = float(s[0])
    sl = s.tolist()
    for k in range(1, len(sl)):
        a = ah[k - 1] if sl[k] > xk else ac[k - 1]
        xk = a * xk + (1 - a) * sl[k]
        x[k] = xk
    return x


def candidate_terms(ds: Dataset, temps: list[str]) -> list[Term]:
    """Every data-side extension regressor of a dataset (lags restart at every run of a campaign)."""
    t = ds.time_s
    st = ds.run_starts()
    out = []
    for name, s in _activity_signals(ds).items():
        for n in EXPONENTS:
            for tau in LAGS_H:
                out.append(Term(f"lag({name}^{n}, {tau:g} h)", "activity_lag", {"signal": name, "exponent": n, "tau_h": tau},
                                per_run(first_order_lag, st, t, s**n, tau * 3600)))
        for th in SPLIT_LAGS_H:
            for tc in SPLIT_LAGS_H:
                if th == tc:
                    continue
                out.append(Term(f"heat/cool({name}, {th:g} h / {tc:g} h)", "heating_cooling",
                                {"signal": name, "tau_heating_h": th, "tau_cooling_h": tc},
                                per_run(heating_cooling_lag, st, t, s, th * 3600, tc * 3600)))
    for T in temps:
        v = ds[T]
        if is_air(T):
            # the ambient model: the structure follows the air through a first-order lag. (An air sensor leads no
            # structure: it gets no lead terms, which would span the same with the air itself under another name.)
            for tau in LAGS_H:
                out.append(Term(f"air TF({T}, {tau:g} h)", "ambient_tf", {"air": T, "tau_h": tau},
                                per_run(first_order_lag, st, t, v, tau * 3600)))
            continue
        for tau in SENSOR_LAGS_H:
            out.append(Term(f"lead({T}, {tau:g} h)", "sensor_lag", {"sensor": T, "tau_h": tau},
                            v - per_run(first_order_lag, st, t, v, tau * 3600)))
    return out


def is_air(name: str) -> bool:
    """A temperature column of the air (``Tamb_degC``, ``ambient_degC``, ``hall_air_degC`` ...), not of the structure."""
    n = name.lower()
    return n.endswith("_degc") and ("amb" in n or "air" in n)


CRITERIA = ("bic", "bicc")


def _bic_rss(rss, n: int, k: int, criterion: str = "bic"):
    """Information criterion of a least-squares fit on ``n`` rows with ``k`` parameters: BIC or BICc.

    ``bic`` (Schwarz): ``n ln(RSS/n) + k ln n``. ``bicc``, the small-sample correction of McQuarrie (1999):
    ``n ln(RSS/n) + n k ln n / (n − k − 2)``, which penalises a parameter more the fewer rows there are per
    parameter (the two agree for many rows; a model with ``k ≥ n − 2`` gets ``inf``).
    (Dividing ``n`` by the residual's decorrelation length, tried on the spindle test, selected fewer inputs and
    predicted the validation part worse.)
    """
    fit = n * np.log(np.maximum(rss, 1e-300) / n)
    if criterion == "bicc":
        return fit + (n * k * np.log(n) / (n - k - 2) if n - k - 2 > 0 else np.inf)
    return fit + k * np.log(n)


class _Library:
    """The regressor columns a search draws from, and their autoregressive versions.

    Sensors first, then the extension terms; the autoregressive versions (every column through one first-order lag)
    are made once per lag and kept.
    """

    def __init__(self, time_s: np.ndarray, terms: list[Term], starts: np.ndarray | None = None):
        self.time_s = time_s
        self.terms = terms
        self.starts = np.array([0]) if starts is None else np.asarray(starts)
        self.index = {tm.name: i for i, tm in enumerate(terms)}
        self._cols = {None: np.column_stack([tm.values for tm in terms])}

    def columns(self, ar_tau_h: float | None) -> np.ndarray:
        if ar_tau_h not in self._cols:
            C = self._cols[None]
            self._cols[ar_tau_h] = np.column_stack([per_run(first_order_lag, self.starts, self.time_s, C[:, j],
                                                            ar_tau_h * 3600) for j in range(C.shape[1])])
        return self._cols[ar_tau_h]

    def design(self, idx: tuple[int, ...], ar_tau_h: float | None) -> np.ndarray:
        return np.column_stack([np.ones(self.time_s.size), self.columns(ar_tau_h)[:, list(idx)]])


@dataclass(frozen=True)
class _State:
    """A model in the search: library columns, optional AR lag, training BIC, validation fit, and the steps that made it."""

    idx: tuple[int, ...]
    ar_tau_h: float | None
    bic: float
    fit: float
    path: tuple = ()

    @property
    def key(self):
        return frozenset(self.idx), self.ar_tau_h


class _Scorer:
    """Training BIC and validation fit of models on one channel.

    :meth:`additions` scores every one-column extension of a model at once (the new column's part orthogonal to the
    model's columns on the training rows gives its least-squares coefficient and the drop of the residual sum of
    squares in closed form).
    """

    def __init__(self, lib: _Library, y: np.ndarray, train: np.ndarray, validation: np.ndarray, channel: str = "channel",
                 what: str = "validation rows", criterion: str = "bic"):
        self.lib, self.y, self.tr, self.va = lib, y, train, validation
        self.criterion = criterion
        self.n = int(train.sum())
        yv = y[validation]
        self.yv = yv
        self.den = float(np.linalg.norm(yv - yv.mean()))
        if self.den == 0:
            raise DatasetError(f"{channel}: the {what} are constant ({yv[0]:g}): no fit can be scored")

    def score(self, idx, ar_tau_h) -> tuple[float, float]:
        X = self.lib.design(idx, ar_tau_h)
        coef, *_ = np.linalg.lstsq(X[self.tr], self.y[self.tr], rcond=None)
        r = self.y[self.tr] - X[self.tr] @ coef
        k = X.shape[1] + (ar_tau_h is not None)
        fit = 100.0 * (1.0 - np.linalg.norm(self.yv - X[self.va] @ coef) / self.den)
        return float(_bic_rss(r @ r, self.n, k, self.criterion)), float(fit)

    def predict(self, idx, ar_tau_h) -> tuple[np.ndarray, np.ndarray]:
        X = self.lib.design(idx, ar_tau_h)
        coef, *_ = np.linalg.lstsq(X[self.tr], self.y[self.tr], rcond=None)
        return coef, X @ coef

    def _extensions(self, idx, ar_tau_h, scored: bool = True):
        """The model plus each library column, in closed form: which columns are new, the training BICs.

        With ``scored``, also the scored rows' sums of squared errors (None without).
        """
        X = self.lib.design(idx, ar_tau_h)
        C = self.lib.columns(ar_tau_h)
        Xt, Ct = X[self.tr], C[self.tr]
        Q, R = np.linalg.qr(Xt)
        coef, *_ = np.linalg.lstsq(Xt, self.y[self.tr], rcond=None)
        r = self.y[self.tr] - Xt @ coef
        P = Q.T @ Ct
        Cp = Ct - Q @ P  # each column's part orthogonal to the model
        norm2 = np.einsum("ij,ij->j", Cp, Cp)
        new = norm2 > 1e-10 * np.einsum("ij,ij->j", Ct, Ct)
        new[list(idx)] = False
        norm2 = np.where(new, norm2, 1.0)
        rc = r @ Cp
        gain = rc / norm2  # coefficient of the new column
        rss = r @ r - rc**2 / norm2
        bic = _bic_rss(rss, self.n, X.shape[1] + 1 + (ar_tau_h is not None), self.criterion)
        if not scored:
            return new, bic, None
        proj = np.linalg.lstsq(R, P, rcond=None)[0]  # the new column's projection on the model, as model coefficients
        E = (self.yv - X[self.va] @ coef)[:, None] - (C[self.va] - X[self.va] @ proj) * gain[None, :]
        return new, bic, np.einsum("ij,ij->j", E, E)

    def additions(self, idx, ar_tau_h) -> tuple[np.ndarray, np.ndarray]:
        """Training BIC and validation fit of the model plus each library column (inf / -inf where not a new column)."""
        new, bic, sse = self._extensions(idx, ar_tau_h)
        fit = 100.0 * (1.0 - np.sqrt(sse) / self.den)
        return np.where(new, bic, np.inf), np.where(new, fit, -np.inf)

    def addition_bics(self, idx, ar_tau_h) -> np.ndarray:
        """Training BIC of the model plus each library column (inf where not a new column); no scoring."""
        new, bic, _ = self._extensions(idx, ar_tau_h, scored=False)
        return np.where(new, bic, np.inf)

    def addition_sses(self, idx, ar_tau_h) -> np.ndarray:
        """Scored rows' sum of squared errors of the model plus each library column (inf where not a new column)."""
        new, _, sse = self._extensions(idx, ar_tau_h)
        return np.where(new, sse, np.inf)

    def sse(self, idx, ar_tau_h) -> float:
        """Sum of squared errors on the scored rows of the model fitted on the training rows."""
        X = self.lib.design(idx, ar_tau_h)
        coef, *_ = np.linalg.lstsq(X[self.tr], self.y[self.tr], rcond=None)
        e = self.yv - X[self.va] @ coef
        return float(e @ e)


class _BlockedCV:
    """Training BIC and blocked cross-validation fit on the training rows only: the validation rows stay unseen.

    The training rows are cut into ``folds`` contiguous blocks of time; each block is predicted by the model fitted
    on the other training rows, and the fit is pooled over the blocks:
    ``100 (1 − √(Σ_k ‖y_k − ŷ_k‖²) / √(Σ_k ‖y_k − ȳ_k‖²))``. The BIC is the one of the fit on every training row.
    Same interface as :class:`_Scorer`, so the searches take either.
    """

    def __init__(self, lib: _Library, y: np.ndarray, train: np.ndarray, folds: int, channel: str = "channel",
                 runs: np.ndarray | None = None, criterion: str = "bic"):
        rows = np.flatnonzero(train)
        if folds < 2 or rows.size < 4 * folds:
            raise DatasetError(f"{channel}: {rows.size} training rows cannot be cut into {folds} blocks for the "
                               "cross-validation (at least 2 blocks of 4 rows)")
        self.lib, self.y, self.tr = lib, y, train
        self.full = _Scorer(lib, y, train, train, channel, "training rows", criterion)
        self.n = self.full.n
        self.parts = []
        train_runs = np.unique(runs[rows]) if runs is not None else np.zeros(0)
        if train_runs.size >= 2:  # a campaign: the training runs held out in turn
            blocks = [rows[runs[rows] == r] for r in train_runs]
        else:
            blocks = np.array_split(rows, folds)
        for k, block in enumerate(blocks):
            va = np.zeros_like(train)
            va[block] = True
            self.parts.append(_Scorer(lib, y, train & ~va, va, channel, f"training rows of block {k + 1}"))
        self.den = float(np.sqrt(sum(p.den**2 for p in self.parts)))

    def _fit(self, sse):
        return 100.0 * (1.0 - np.sqrt(sse) / self.den)

    def score(self, idx, ar_tau_h) -> tuple[float, float]:
        bic = self.full.score(idx, ar_tau_h)[0]
        return bic, float(self._fit(sum(p.sse(idx, ar_tau_h) for p in self.parts)))

    def predict(self, idx, ar_tau_h) -> tuple[np.ndarray, np.ndarray]:
        return self.full.predict(idx, ar_tau_h)

    def additions(self, idx, ar_tau_h) -> tuple[np.ndarray, np.ndarray]:
        """Training BIC and pooled cross-validation fit of each one-column extension (closed form per block)."""
        bic = self.full.addition_bics(idx, ar_tau_h)
        fit = self._fit(sum(p.addition_sses(idx, ar_tau_h) for p in self.parts))
        return bic, np.where(np.isfinite(bic) & np.isfinite(fit), fit, -np.inf)


def forward_sensors(scorer: _Scorer, n_sensors: int) -> tuple[int, ...]:
    """Forward selection of the sensor inputs by training BIC: the model under test.

    The sensor inputs are the first ``n_sensors`` library columns. Each added input must lower the BIC by
    ``MIN_BIC_DROP``; at most ``MAX_INPUTS``.
    """
    idx: tuple[int, ...] = ()
    best = scorer.score(idx, None)[0]
    while len(idx) < MAX_INPUTS:
        bics = scorer.additions(idx, None)[0][:n_sensors]
        j = int(np.argmin(bics))
        if not bics[j] <= best - MIN_BIC_DROP:
            break
        idx += (j,)
        best = float(bics[j])
    return idx


def beam_search(scorer: _Scorer, start: tuple[int, ...], droppable: set[int], beam_width: int = BEAM_WIDTH,
                max_steps: int = 16, min_fit_gain: float = MIN_FIT_GAIN, min_bic_drop: float = MIN_BIC_DROP) -> _State:
    """Extend the model ``start`` one step at a time, by a beam search.

    A step adds a library column, drops a ``droppable`` one, or puts every regressor through an AR lag; it is allowed
    when the training BIC drops by ``min_bic_drop`` and the validation fit rises by ``min_fit_gain`` points.  The
    ``beam_width`` best models (by validation fit) of each step are extended further; the best model seen is returned.
    ``beam_width = 1`` is greedy forward selection.
    """
    b0, f0 = scorer.score(start, None)
    best = root = _State(tuple(start), None, b0, f0)
    frontier = [root]
    names = [tm.name for tm in scorer.lib.terms]
    for _ in range(max_steps):
        nxt: dict = {}

        def offer(st: _State, idx, ar, bic, fit, step, nxt=nxt):
            if st.bic - bic >= min_bic_drop and fit - st.fit >= min_fit_gain:
                new = _State(tuple(idx), ar, float(bic), float(fit), st.path + ((*step, fit - st.fit, st.bic - bic),))
                if new.key not in nxt or nxt[new.key].fit < new.fit:
                    nxt[new.key] = new

        for st in frontier:
            bics, fits = scorer.additions(st.idx, st.ar_tau_h)
            for j in np.flatnonzero((st.bic - bics >= min_bic_drop) & (fits - st.fit >= min_fit_gain)):
                offer(st, st.idx + (int(j),), st.ar_tau_h, bics[j], fits[j], ("add", names[j]))
            for j in st.idx:
                if j in droppable:
                    idx = tuple(i for i in st.idx if i != j)
                    offer(st, idx, st.ar_tau_h, *scorer.score(idx, st.ar_tau_h), ("drop", names[j]))
            if st.ar_tau_h is None:
                for tau in AR_H:
                    offer(st, st.idx, tau, *scorer.score(st.idx, tau), ("ar", tau))
        if not nxt:
            break
        frontier = sorted(nxt.values(), key=lambda s: (-s.fit, s.bic))[:beam_width]
        if frontier[0].fit > best.fit:
            best = frontier[0]
    return best


def _extension_records(lib: _Library, path, gain_key: str = "validation_fit_points") -> list[dict]:
    out = []
    for kind, what, gain, drop in path:
        g = {gain_key: float(gain), "bic_drop_train": float(drop)}
        if kind == "add" and lib.terms[lib.index[what]].kind == "sensor":
            out.append({"name": "add_input", "term": f"with {what}", "parameters": {"sensor": what}, "gain": g})
        elif kind == "add":
            tm = lib.terms[lib.index[what]]
            out.append({"name": tm.kind, "term": tm.name, "parameters": tm.params, "gain": g})
        elif kind == "drop":
            out.append({"name": "drop_input", "term": f"without {what}", "parameters": {"sensor": what}, "gain": g})
        else:
            out.append({"name": "autoregressive", "term": f"AR(1) output lag {what:g} h", "parameters": {"tau_h": what},
                        "gain": g})
    return out


def diagnose_data_only(ds: Dataset, split: Split, max_terms: int = 16, min_fit_gain: float = MIN_FIT_GAIN,
                       beam_width: int = BEAM_WIDTH, selection_check: bool = True, selection: str = "held-out",
                       folds: int = 3, criterion: str = "bic", probe_every_h: float | None = None,
                       probe_sd_um: float = 0.5, regularised: bool = True, spread: bool = True,
                       seed: int = 0, pool_folds: bool = True) -> DataOnlyDiagnosis:
    """Diagnose a regression compensation model on a dataset alone (see the module docstring).

    Parameters
    ----------
    max_terms : most search steps (extension terms added or inputs dropped) per channel
    min_fit_gain : fit points a step must add (cross-validation fit, or validation fit when assisted)
    beam_width : models kept per search step (1: greedy forward selection)
    selection_check : with ``selection="assisted"``: also run the whole selection on the first half of the
        validation part and score it on the second half, which took no part in it
    selection : ``"held-out"`` (default): every choice — inputs, extensions, lags, exponents, the AR lag — is made
        on the training rows, by blocked cross-validation over ``folds`` contiguous blocks of them, and the
        validation rows score the result once: a held-out fit. ``"assisted"``: the validation rows take part in
        the choice (the search keeps what raises their fit), so their fit flatters
    folds : blocks of the training rows for the cross-validation (``selection="held-out"``)
    criterion : ``"bic"`` (default) or ``"bicc"``, BIC with McQuarrie's small-sample correction: the training
        criterion that selects the sensor inputs and that every search step must lower by ``MIN_BIC_DROP``
    probe_every_h : post-process gain updating (:mod:`hybridcomp.diagnose.updating`): on the validation rows the
        drift is measured every ``probe_every_h`` hours and the extended model's gain and offset are updated from
        those measurements; the filter's settings are chosen on the training rows. ``None``: no updating
    probe_sd_um : the probe measurement's repeatability [µm]
    regularised : also fit the regularised families (:mod:`hybridcomp.diagnose.regularised`) beside the search: ridge
        regressions over the temperatures, their lags and the activities' transfer functions, family and λ chosen
        on the training rows by a repeated blocked cross-validation (``folds`` blocks, phases drawn from ``seed``)
        with the one-standard-error rule and selection by stability; with ``probe_every_h`` their coefficients are
        updated from the probes (:func:`hybridcomp.diagnose.updating.coefficient_updating`)
    spread : with ``regularised``: the held-out fit of the choice made with 3, 5 and 10 folds and seeds 0, 1, 2
        (with ``pool_folds``: of the pooled choice with seeds 0, 1, 2)
    pool_folds : with ``regularised``: choose family and λ on the cross-validation curves of 3, 5 and 10 folds
        averaged (:func:`hybridcomp.diagnose.regularised.choose_pooled`), so the choice does not depend on the fold
        count; False: on ``folds`` blocks alone

    Raises
    ------
    DatasetError
        no ``*_um`` channel or no ``*_degC`` sensor, a constant channel.
    """
    from hybridcomp.fem.blas import single_blas_thread

    if beam_width < 1:
        raise DatasetError(f"beam width must be at least 1, got {beam_width}")
    if selection not in ("held-out", "assisted"):
        raise DatasetError(f"selection must be 'held-out' or 'assisted', got {selection!r}")
    if not (isinstance(folds, int) and 2 <= folds <= 20):
        raise DatasetError(f"folds must be an integer in 2..20, got {folds!r}")
    if criterion not in CRITERIA:
        raise DatasetError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    if probe_every_h is not None and not (np.isfinite(probe_every_h) and probe_every_h > 0):
        raise DatasetError(f"the probe interval must be a positive number of hours, got {probe_every_h!r}")
    if not (np.isfinite(probe_sd_um) and probe_sd_um > 0):
        raise DatasetError(f"the probe repeatability must be a positive number of µm, got {probe_sd_um!r}")
    with single_blas_thread():
        d = _diagnose_data_only(ds, split, max_terms, min_fit_gain, beam_width,
                                selection_check and selection == "assisted", selection, folds, criterion,
                                probe_every_h, probe_sd_um)
        if not regularised:
            return d
        t0 = time.perf_counter()
        r, cu = _regularised(ds, d, folds, seed, spread, probe_every_h, probe_sd_um, pool_folds)
        timings = {**d.timings_s, "regularised": time.perf_counter() - t0}
        timings["total"] = d.timings_s["total"] + timings["regularised"]
        return replace(d, regularised=r, coefficient_updating=cu, timings_s=timings)


def _diagnose_data_only(ds: Dataset, split: Split, max_terms: int, min_fit_gain: float, beam_width: int,
                        selection_check: bool, selection: str = "held-out", folds: int = 3,
                        criterion: str = "bic", probe_every_h: float | None = None,
                        probe_sd_um: float = 0.5) -> DataOnlyDiagnosis:
    t0 = time.perf_counter()
    targets = [n for n in ds.names if n.endswith("_um")]
    temps = [n for n in ds.names if n.endswith("_degC")]
    if not targets:
        raise DatasetError(f"{ds.source}: --data-only needs measured drift columns '*_um'; columns: {', '.join(ds.names)}")
    if not temps:
        raise DatasetError(f"{ds.source}: --data-only needs temperature columns '*_degC'; columns: {', '.join(ds.names)}")
    check_channels(ds, targets, split)
    stride = -(-ds.time_s.size // MAX_ROWS)
    if stride > 1:
        rows = np.arange(0, ds.time_s.size, stride)
        log.warning("%s: %d rows; the diagnosis uses every %d. row (%d rows, median step %.0f s)", ds.source,
                    ds.time_s.size, stride, rows.size, float(np.median(np.diff(ds.time_s[rows]))))
        ds = ds.subset(rows)
        split = Split(split.train[rows], split.validation[rows], split.text)
    t = ds.time_s
    tr, va = split.train, split.validation
    temp_vals = {n: ds[n] for n in temps if np.ptp(ds[n][tr]) > 0}
    cands = candidate_terms(ds, list(temp_vals))
    starts = ds.run_starts()
    if ds.runs is not None:
        # a campaign: every run relative to its first row (its own zero and its own initial state, a cold machine
        # at that day's air), regressors and channels alike
        temp_vals = {n: zero_runs(v, starts) for n, v in temp_vals.items()}
        cands = [Term(c.name, c.kind, c.params, zero_runs(c.values, starts)) for c in cands]
    lib = _Library(t, [Term(n, "sensor", {"sensor": n}, v) for n, v in temp_vals.items()] + cands, starts)
    log.info("%d candidate extension terms, beam width %d", len(cands), beam_width)
    # selection check: select on the first half of the validation rows, score on the second half
    va_rows = np.flatnonzero(va)
    va1 = np.zeros_like(va)
    va1[va_rows[: va_rows.size // 2]] = True
    va2 = va & ~va1
    reference, base, extended, extensions, Y, check, updating = {}, {}, {}, {}, {}, {}, {}
    for ch in targets:
        y = ds[ch] if ds.runs is None else zero_runs(ds[ch], starts)
        Y[ch] = y
        every = tuple(range(len(temp_vals)))
        droppable = set(every)
        sc = _Scorer(lib, y, tr, va, ch, criterion=criterion)
        # what chooses: the validation rows themselves (assisted), or a cross-validation on the training rows only
        chooser = sc if selection == "assisted" else _BlockedCV(lib, y, tr, folds, ch, ds.runs, criterion)
        _, yh = sc.predict(every, None)
        reference[ch] = {**channel_metrics(y[va], yh[va]), "terms": len(every)}
        start = forward_sensors(chooser, len(temp_vals))
        _, yh = sc.predict(start, None)
        base[ch] = {**channel_metrics(y[va], yh[va]), "inputs": [lib.terms[i].name for i in start]}
        best = beam_search(chooser, start, droppable, beam_width, max_terms, min_fit_gain)
        coef, yh = sc.predict(best.idx, best.ar_tau_h)  # fitted on the training rows, scored once on the validation
        extended[ch] = ChannelModel(ch, tuple(lib.terms[i] for i in best.idx), best.ar_tau_h, coef, yh)
        if probe_every_h is not None:
            cv = chooser if isinstance(chooser, _BlockedCV) else _BlockedCV(lib, y, tr, folds, ch, ds.runs, criterion)
            updating[ch] = _post_process_updating(cv, best, t, y, yh, va, starts, probe_every_h, probe_sd_um)
        extensions[ch] = _extension_records(lib, best.path,
                                            "validation_fit_points" if selection == "assisted" else "cv_fit_points")
        log.info("%s: reference fit %.1f %%, base %.1f %%, extended %.1f %% (%s)", ch, reference[ch]["fit_percent"],
                 base[ch]["fit_percent"], channel_metrics(y[va], yh[va])["fit_percent"], selection)
        if selection_check and va1.sum() >= 2 and va2.sum() >= 2 and np.ptp(y[va1]) > 0 and np.ptp(y[va2]) > 0:
            best2 = beam_search(_Scorer(lib, y, tr, va1, ch, criterion=criterion), start, droppable, beam_width,
                                max_terms, min_fit_gain)
            sc2 = _Scorer(lib, y, tr, va2, ch, criterion=criterion)
            check[ch] = {
                "static_all_temperatures": sc2.score(every, None)[1],
                "base": sc2.score(start, None)[1],
                "extended": sc2.score(best2.idx, best2.ar_tau_h)[1],
                "terms": [tm["term"] for tm in _extension_records(lib, best2.path)],
            }
    split_check = None
    if check:
        split_check = {"selected_on_h": [float(t[va1][0] / 3600), float(t[va1][-1] / 3600)],
                       "scored_on_h": [float(t[va2][0] / 3600), float(t[va2][-1] / 3600)], "channels": check}
    return DataOnlyDiagnosis(t, Y, split, reference, base, extended, extensions,
                             {"total": time.perf_counter() - t0, "candidates": len(cands), "beam_width": beam_width,
                              "row_stride": stride},
                             split_check, selection, folds, ds.runs, criterion, updating or None)


def regularised_families(ds: Dataset, d: DataOnlyDiagnosis) -> tuple[Dataset, dict, dict, list]:
    """The regularised families of a diagnosed dataset: the same rows, thinning and zeros as the search.

    Returns the dataset on the diagnosis' rows, its temperatures and activity signals (name → values) and the
    families (:func:`hybridcomp.diagnose.regularised.families`, each run from its own zero in a campaign).
    """
    t = d.time_s
    if t.size != ds.time_s.size:  # the search thinned the record: the same rows
        ds = ds.subset(np.flatnonzero(np.isin(ds.time_s, t)))
    tr = d.split.train
    starts = ds.run_starts()
    temps = {n: ds[n] for n in ds.names if n.endswith("_degC") and np.ptp(ds[n][tr]) > 0}
    act = _activity_signals(ds)
    fams = reg.families(t, temps, act, starts)
    if ds.runs is not None:
        fams = [reg.Family(f.name, f.columns, reg.zero_runs(f.X, starts)) for f in fams]
    return ds, temps, act, fams


def _regularised(ds: Dataset, d: DataOnlyDiagnosis, folds: int, seed: int, spread: bool,
                 probe_every_h: float | None, probe_sd_um: float, pool_folds: bool = True) -> tuple[dict, dict | None]:
    """The regularised families of a diagnosed dataset (the same rows, thinning and zeros as the search)."""
    t = d.time_s
    tr, va = d.split.train, d.split.validation
    ds, temps, act, fams = regularised_families(ds, d)
    # what an online evaluation needs to rebuild the regressors: the sensors in order and each activity's scale
    spec = {"temperatures": list(temps), "activity_max": {n: float(np.abs(ds[n]).max()) for n in act
                                                          if n.endswith("_rpm")},
            "temp_lags_h": list(reg.TEMP_LAGS_H), "source_lags_h": list(reg.SOURCE_LAGS_H)}
    chans = list(d.extended)
    Y = np.column_stack([d.Y[c] for c in chans])
    dof = reg.effective_dof(fams, tr)
    held = reg.held_out_fits(fams, Y, tr, va)
    sp = reg.fold_spread(fams, Y, tr, va, held, runs=ds.runs, pooled=pool_folds) if spread else None
    # the spread makes this very choice among its own (the same rows, folds and seed): taken from it, not made twice
    choice = (sp or {}).get("made", {}).get((tuple(reg.SPREAD_FOLDS), seed) if pool_folds else (folds, seed))
    if choice is None and pool_folds:
        cache: dict = {}
        choice = reg.choose_pooled([reg.repeated_errors(fams, Y, tr, k, seed, runs=ds.runs, cache=cache)
                                    for k in reg.SPREAD_FOLDS], dof)
    elif choice is None:
        choice = reg.choose(reg.repeated_errors(fams, Y, tr, folds, seed, runs=ds.runs), dof)
    every = reg.every_row_fits(fams, Y, va)
    out, upd = {}, {}
    for j, (c, ch) in enumerate(zip(chans, choice)):
        fam = fams[ch.family]
        lam = reg.LAMBDAS[ch.lam_index]
        m = reg.fit_ridge(fam, d.Y[c], tr, lam, s2_um2=ch.cv_mse)
        yh = m.predict(fam.X)
        f_best = int(np.argmax(every[:, j]))
        out[c] = {"family": fam.name, "lam": float(lam), "votes": ch.votes, "repeats": ch.repeats,
                  "pool_folds": pool_folds,
                  "cv_rms": float(np.sqrt(ch.cv_mse)), "effective_dof": float(dof[ch.family, ch.lam_index]),
                  "columns": len(fam.columns), "y_hat": yh, "model": m, "inputs": spec,
                  "held_out": channel_metrics(d.Y[c][va], yh[va]),
                  "every_row": {"family": fam.name, "fit_percent": float(every[ch.family, j])},
                  "every_row_best": {"family": fams[f_best].name, "fit_percent": float(every[f_best, j])},
                  "spread": None if sp is None else {
                      "pooled_folds": pool_folds,
                      "fits": {f"{_folds_label(k)} folds, seed {s}": v[j] for (k, s), v in sp["fits"].items()},
                      "choices": {f"{_folds_label(k)} folds, seed {s}": f"{v[j][0]} λ={v[j][1]:.3g}" for (k, s), v in
                                  sp["choices"].items()},
                      "min": float(sp["min"][j]), "max": float(sp["max"][j]), "spread": float(sp["spread"][j])}}
        if probe_every_h is not None:
            upd[c] = _coefficient_updating(fam, d.Y[c], t, tr, va, lam, m, ds.runs, folds, probe_every_h, probe_sd_um)
    return out, (upd or None)


def _folds_label(k) -> str:
    """A fold count (``3``) or the fold counts whose curves were pooled (``3/5/10 pooled``)."""
    return str(k) if isinstance(k, int) else "/".join(str(i) for i in k) + " pooled"


def _coefficient_updating(fam, y: np.ndarray, t: np.ndarray, tr: np.ndarray, va: np.ndarray, lam: float, m,
                          runs: np.ndarray | None, folds: int, every_h: float, probe_sd_um: float) -> dict:
    """The regularised model with its coefficients updated at the probes of the validation rows.

    The filter's settings are chosen on the training rows (each block probed, the model fitted on the other blocks).
    """
    blocks = []
    for rows in reg.cv_blocks(tr, folds, 0.0, runs):
        fit_rows = tr.copy()
        fit_rows[rows] = False
        mb = reg.fit_ridge(fam, y, fit_rows, lam, s2_um2=m.s2_um2)
        blocks.append({"time_s": t[rows], "y": y[rows], "Z": mb.design(fam.X[rows]), "coef": mb.coef, "A": mb.A,
                       "s2_um2": mb.s2_um2, "z_lo": mb.z_lo, "z_hi": mb.z_hi})
    settings, cv_rms = choose_coefficient_settings(blocks, every_h, probe_sd_um)
    rows = np.flatnonzero(va)
    probes = probe_rows(t[rows], np.ones(rows.size, bool), every_h)
    u, sd, theta = coefficient_updating(m.design(fam.X[rows]), y[rows], t[rows], probes, m.coef, m.A, m.s2_um2,
                                        m.z_lo, m.z_hi, settings)
    return {"settings": settings, "cv_rms_updated_um": cv_rms, "probe_rows": rows[probes], "y_hat": u,
            "scored": scored_mask(rows.size, probes),
            "spread_um": sd, "coef_change": float(np.linalg.norm(theta[-1] - m.coef) / np.linalg.norm(m.coef))}


def _post_process_updating(cv: _BlockedCV, best: _State, t: np.ndarray, y: np.ndarray, yh: np.ndarray,
                           va: np.ndarray, starts: np.ndarray, every_h: float, probe_sd_um: float) -> dict:
    """The chosen model with gain updating on the validation rows; the filter settings chosen on the training blocks."""
    blocks = [(np.flatnonzero(p.va), p.predict(best.idx, best.ar_tau_h)[1][p.va]) for p in cv.parts]
    settings, cv_rms = choose_settings(t, y, blocks, every_h, probe_sd_um)
    rows = np.flatnonzero(va)
    probes = probe_rows(t[rows], np.ones(rows.size, bool), every_h)
    restarts = np.flatnonzero(np.isin(rows, starts))
    u, theta = updated_prediction(yh[rows], y[rows], t[rows], probes, settings, restarts)
    return {"settings": settings, "cv_rms_updated_um": cv_rms, "probe_rows": rows[probes], "y_hat": u,
            "scored": scored_mask(rows.size, probes), "gain": theta[:, 0], "offset_um": theta[:, 1]}


def scored_mask(n: int, probes: np.ndarray) -> np.ndarray:
    """Of ``n`` validation rows, those that score an updated prediction: every row but the probes."""
    m = np.ones(n, bool)
    m[np.asarray(probes, int)] = False
    return m


def _structure_name(tm: Term) -> str:
    """A term in the words of the thermal-error literature."""
    p = tm.params
    if tm.kind == "sensor":
        return f"static regression on {tm.name} (MLR)"
    if tm.kind == "activity_lag":
        return (f"first-order transfer function of the heat from {p['signal']} (speed^{p['exponent']:g}), "
                f"time constant {p['tau_h']:g} h")
    if tm.kind == "heating_cooling":
        return (f"transfer function of {p['signal']} with separate heating and cooling time constants "
                f"({p['tau_heating_h']:g} h heating, {p['tau_cooling_h']:g} h cooling)")
    if tm.kind == "ambient_tf":
        return f"first-order transfer function of the air {p['air']} (the ambient model), time constant {p['tau_h']:g} h"
    if tm.kind == "sensor_lag":
        return f"sensor lead of {p['sensor']}: the structure leads the sensor by a first-order lag of {p['tau_h']:g} h"
    return tm.name


def model_structure(m: ChannelModel) -> dict:
    """The extended model of a channel as model structures with their fitted gains.

    A gain is in the channel's unit per unit of its term (µm/K for a sensor, µm per unit of a normalised activity).
    """
    terms = [{"term": tm.name, "structure": _structure_name(tm), "gain": float(g)} for tm, g in zip(m.terms, m.coef[1:])]
    return {"offset": float(m.coef[0]), "terms": terms,
            "output_lag": None if m.ar_tau_h is None else
            f"output-error AR(1): every term through a first-order lag of {m.ar_tau_h:g} h"}


def summary(d: DataOnlyDiagnosis) -> dict:
    """The JSON-ready summary of a data-only diagnosis (validation metrics per channel and the extensions)."""
    va = d.split.validation
    ch = {}
    for c, m in d.extended.items():
        after = channel_metrics(d.Y[c][va], m.y_hat[va])
        ch[c] = {"reference_all_temperatures": d.reference[c], "before": d.base[c], "after": after,
                 "extensions": d.extensions[c], "model": model_structure(m)}
    causes = [{"channel": c, **e} for c in d.extended for e in d.extensions[c]]
    held_out = {c: _headline(ch[c]["after"]) for c in d.extended}
    return {
        "mode": "data-only",
        "criterion": d.criterion_name,
        "selection": (f"held-out: every choice by blocked {d.folds}-fold cross-validation on the training rows; the "
                      "validation rows scored the result once" if d.selection == "held-out" else
                      "assisted: the validation rows took part in choosing the extensions (their fit flatters)"),
        # the headline: fits on rows that no choice saw (None when the validation rows took part in the choice)
        "held_out": held_out if d.selection == "held-out" else None,
        # reported, not chosen on: does the extended model predict the validation rows better than the model under test
        "generalises": {c: bool(ch[c]["after"]["fit_percent"] > d.base[c]["fit_percent"]) for c in d.extended},
        "verdict": "extended" if causes else "no significant discrepancy",
        "causes": causes,
        "before": {c: {k: v for k, v in d.base[c].items() if k != "inputs"} for c in d.extended},
        "after": {c: ch[c]["after"] for c in d.extended},
        "channels": ch,
        "split": d.split.describe(d.time_s),
        "runs": None if d.runs is None else _per_run_metrics(d),
        "selection_check": d.selection_check,
        "post_process_updating": _updating_summary(d),
        "regularised": _regularised_summary(d),
        "coefficient_updating": _coefficient_summary(d),
        "timings_s": d.timings_s,
    }


def _headline(metrics: dict) -> dict:
    """The figures a fit is reported by: fit %, RMS and peak-to-peak."""
    return {k: metrics[k] for k in ("fit_percent", "rms", "p2p")}


def _updating_summary(d: DataOnlyDiagnosis) -> dict | None:
    """Fits with post-process gain updating on the validation rows (None without probes)."""
    if not d.updating:
        return None
    va = d.split.validation
    out = {}
    for c, u in d.updating.items():
        st = u["settings"]
        sc = u["scored"]  # the validation rows without the probes
        out[c] = {"fit": _headline(channel_metrics(d.Y[c][va][sc], u["y_hat"][sc])),
                  "without_updating": _headline(channel_metrics(d.Y[c][va][sc], d.extended[c].y_hat[va][sc])),
                  "probes": int(u["probe_rows"].size), "final_gain": float(u["gain"][-1]),
                  "final_offset_um": float(u["offset_um"][-1]), "settings": {
                      "gain_walk_per_sqrt_h": st.gain_walk_per_sqrt_h,
                      "offset_walk_um_per_sqrt_h": st.offset_walk_um_per_sqrt_h, "offset_sd_um": st.offset_sd_um},
                  "training_cv_rms_updated_um": u["cv_rms_updated_um"]}
    st = next(iter(d.updating.values()))["settings"]
    return {"every_h": st.every_h, "probe_sd_um": st.probe_sd_um,
            "how": "the extended model's gain and offset updated by a Kalman filter at each probe of the validation "
                   "rows; each row uses earlier probes only; the filter's random walks chosen on the training rows; "
                   "scored on the validation rows without the probe rows",
            "channels": out}


def _regularised_summary(d: DataOnlyDiagnosis) -> dict | None:
    """The regularised families per channel: choice, held-out fit, its spread over fold counts and seeds.

    Also the family fitted on every row (NOT held out), with the gap between the two.
    """
    if not d.regularised:
        return None
    out = {}
    pooled = bool(next(iter(d.regularised.values())).get("pool_folds"))
    cv = ("blocked cross-validation with 3, 5 and 10 folds (three phases of the blocks each; the curves of the fold "
          "counts averaged before choosing, so the choice does not depend on the fold count)" if pooled else
          f"blocked {d.folds}-fold cross-validation (three phases of the blocks, pooled)")
    for c, r in d.regularised.items():
        ho = r["held_out"]["fit_percent"]
        out[c] = {"family": r["family"], "lambda": r["lam"], "effective_dof": r["effective_dof"], "votes": r["votes"],
                  "repeats": r["repeats"], "cv_rms": r["cv_rms"], "held_out": _headline(r["held_out"]),
                  "spread_over_folds_and_seeds": r["spread"],
                  "every_row_NOT_held_out": r["every_row"], "every_row_best_family_NOT_held_out": r["every_row_best"],
                  "gap_to_every_row_points": float(r["every_row"]["fit_percent"] - ho)}
    return {"how": "ridge regressions over the temperatures, their first-order lags and the activities' transfer "
                   "functions (families T+lagT and S<n>(signal)+T+lagT), no column selected; family and λ chosen on "
                   f"the training rows by a repeated {cv} with the one-standard-error rule (the fewest effective "
                   "degrees of freedom within one standard error of the best); held out: the validation rows scored "
                   "the result once",
            "channels": out}


def _coefficient_summary(d: DataOnlyDiagnosis) -> dict | None:
    """Fits of the regularised model with coefficient updating (scored on the validation rows without the probes)."""
    if not d.coefficient_updating:
        return None
    va = d.split.validation
    out = {}
    for c, u in d.coefficient_updating.items():
        sc = u["scored"]
        y = d.Y[c][va][sc]
        st = u["settings"]
        out[c] = {"fit": _headline(channel_metrics(y, u["y_hat"][sc])),
                  "without_updating": _headline(channel_metrics(y, d.regularised[c]["y_hat"][va][sc])),
                  "probes": int(u["probe_rows"].size), "coefficient_change": u["coef_change"],
                  "spread_um_median": float(np.median(u["spread_um"])),
                  "settings": {"prior_scale": st.prior_scale, "walk": st.walk, "range_walk": st.range_walk,
                               "offset_walk": st.offset_walk},
                  "training_cv_rms_updated_um": u["cv_rms_updated_um"]}
    st = next(iter(d.coefficient_updating.values()))["settings"]
    return {"every_h": st.every_h, "probe_sd_um": st.probe_sd_um,
            "how": "the regularised model's coefficients updated by a Kalman filter at each probe (prior: the training "
                   "fit; random walks and the inflation outside the training range chosen on the training rows); "
                   "each row uses earlier probes only; scored on the validation rows without the probe rows",
            "channels": out}


def _per_run_metrics(d: DataOnlyDiagnosis) -> dict:
    """Per run of a campaign: training or validation, and each channel's metrics of the extended model on it."""
    out = {}
    for r in np.unique(d.runs):
        rows = d.runs == r
        out[str(int(r))] = {"part": "training" if d.split.train[rows].all() else "validation" if d.split.validation[
            rows].all() else "both", "hours": float((d.time_s[rows][-1] - d.time_s[rows][0]) / 3600),
            **{c: channel_metrics(d.Y[c][rows], m.y_hat[rows]) for c, m in d.extended.items()}}
    return out


def _regularised_report(s: dict) -> list[str]:
    """The report's section on the regularised families and their coefficient updating."""
    rg = s.get("regularised")
    if not rg:
        return []
    L = ["## Regularised families beside the search", "",
         f"Each channel is also fitted as one of the {rg['how']}. The votes say in how many of the repetitions on "
         "their own the choice was as good as their best. The spread is the held-out fit of the choice made with "
         "3, 5 and 10 folds (each alone, or their curves pooled) and seeds 0, 1, 2 (the phases of the blocks); the "
         "last columns are the chosen family fitted "
         "on every row, the validation rows too: NOT held out, what the data allow that family, and how far the "
         "held-out fit is from it.", "",
         "| channel | static, all temperatures | search, held out | regularised, held out (RMS) | over folds 3/5/10 × "
         "seeds: min–max (spread) | family, λ (votes) | fitted on every row, NOT held out | gap |",
         "|---|---|---|---|---|---|---|---|"]
    for c, v in rg["channels"].items():
        ch = s["channels"][c]
        sp = v["spread_over_folds_and_seeds"]
        spt = "–" if sp is None else f"{sp['min']:.1f}–{sp['max']:.1f} ({sp['spread']:.1f})"
        L.append(f"| {c} | {ch['reference_all_temperatures']['fit_percent']:.1f} | {ch['after']['fit_percent']:.1f} | "
                 f"**{v['held_out']['fit_percent']:.1f}** ({v['held_out']['rms']:.3g}) | {spt} | {v['family']}, "
                 f"λ = {v['lambda']:.3g} ({v['votes']}/{v['repeats']}) | *{v['every_row_NOT_held_out']['fit_percent']:.1f}* "
                 f"| {v['gap_to_every_row_points']:.1f} |")
    L.append("")
    cu = s.get("coefficient_updating")
    if cu:
        L += [f"### Coefficient updating: a probe every {cu['every_h']:g} h", "",
              f"{cu['how']}.", "",
              "| channel | regularised, no probes | coefficients updated | probes | coefficients changed by | "
              "median spread [µm] |", "|---|---|---|---|---|---|"]
        for c, v in cu["channels"].items():
            L.append(f"| {c} | {v['without_updating']['fit_percent']:.1f} | **{v['fit']['fit_percent']:.1f}** | "
                     f"{v['probes']} | {100 * v['coefficient_change']:.0f} % | {v['spread_um_median']:.3g} |")
        L.append("")
    return L


def _plot_runs(d: DataOnlyDiagnosis, path: Path, plt) -> None:
    """One panel per channel, every run over its own time axis: measured (solid) and the extended model (dashed)."""
    n = len(d.extended)
    fig, axes = plt.subplots(n, 1, figsize=(11, 2.2 * n + 0.5), sharex=True, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (c, m) in zip(axes[:, 0], d.extended.items()):
        for k, r in enumerate(np.unique(d.runs)):
            rows = d.runs == r
            th = (d.time_s[rows] - d.time_s[rows][0]) / 3600
            val = bool(d.split.validation[rows].all())
            col = colors[k % len(colors)]
            ax.plot(th, d.Y[c][rows], color=col, lw=1.6 if val else 0.7, label=f"run {int(r)}{' (validation)' if val else ''}")
            ax.plot(th, m.y_hat[rows], color=col, lw=1.6 if val else 0.7, ls="--")
        ax.set_ylabel(c, fontsize=8)
    axes[0, 0].legend(fontsize=6, ncol=4)
    axes[-1, 0].set_xlabel("time since the run's start [h]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_data_only_report(d: DataOnlyDiagnosis, out_dir, dataset_name: str = "", plots: bool = True) -> dict:
    """``report.md`` (with a plot), ``summary.json`` of a data-only diagnosis."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = summary(d)
    s["dataset"] = dataset_name
    write_text_atomic(out / "summary.json", jsonio.dumps(s, indent=2, default=float))
    stride = d.timings_s["row_stride"]
    thinned = "" if stride == 1 else f" (every {stride}. row of the dataset)"
    if d.selection == "held-out":
        how = (f"while the training {d.criterion_name} drops and the fit in a blocked {d.folds}-fold cross-validation "
               "on the training rows improves. Every choice is made on the training rows: the validation fits below "
               "are held out (no choice saw those rows).")
        gain_key, gain_name = "cv_fit_points", "cross-validation fit points"
    else:
        how = (f"while the training {d.criterion_name} drops and the validation fit improves (selection-assisted: "
               "the validation part takes part in this selection; the selection check below says how much that "
               "flatters).")
        gain_key, gain_name = "validation_fit_points", "fit points"
    L = [f"# Data-only diagnosis{' of ' + dataset_name if dataset_name else ''}", "",
         "Model under test: a multiple linear regression of each drift channel on the temperature sensors, inputs "
         f"selected greedily by {d.criterion_name} on the training part. Extensions: lag terms of activity signals, "
         "heating/cooling split, sensor lags (lead terms), an autoregressive output lag; added (or sensor inputs "
         "dropped) by a beam search "
         f"(width {d.timings_s['beam_width']}) {how}", "",
         f"Training rows {s['split']['train_rows']}, validation rows {s['split']['validation_rows']}"
         f"{thinned}; "
         f"{d.timings_s['candidates']} candidate terms; {d.timings_s['total']:.1f} s.", "",
         f"| channel | static, all temperatures: fit % | {d.criterion_name}-selected regression: fit % (RMS, P2P) | "
         "extended: fit % (RMS, P2P)"
         f"{' — held out' if d.selection == 'held-out' else ' — selection-assisted'} |",
         "|---|---|---|---|"]
    for c, v in s["channels"].items():
        b, a = v["before"], v["after"]
        L.append(f"| {c} | {v['reference_all_temperatures']['fit_percent']:.1f} | {b['fit_percent']:.1f} "
                 f"({b['rms']:.3g}, {b['p2p']:.3g}) | {a['fit_percent']:.1f} ({a['rms']:.3g}, {a['p2p']:.3g}) |")
    worse = [c for c, g in s["generalises"].items() if not g and s["channels"][c]["extensions"]]
    if worse and d.selection == "held-out":
        L += ["", f"On the held-out rows the extended model predicts {', '.join(worse)} no better than the model under "
              "test: the extensions found on the training rows do not carry over there (too little variety in the "
              "training rows, or a regime the training rows do not contain)."]
    if s["runs"]:
        L += ["", f"## Runs ({len(s['runs'])}: each from its own first row, no lag across a run boundary)", "",
              "| run | part | hours | " + " | ".join(f"{c} fit %" for c in d.extended) + " |",
              "|---|---|---|" + "---|" * len(d.extended)]
        for r, v in s["runs"].items():
            L.append(f"| {r} | {v['part']} | {v['hours']:.1f} | " + " | ".join(f"{v[c]['fit_percent']:.1f}"
                                                                           for c in d.extended) + " |")
    L += ["", "## Extensions found", ""]
    for c, v in s["channels"].items():
        L.append(f"**{c}** (inputs {', '.join(v['before']['inputs'])}):")
        L.append("")
        for e in v["extensions"]:
            L.append(f"* {e['term']} — +{e['gain'][gain_key]:.1f} {gain_name}, {d.criterion_name} drop "
                     f"{e['gain']['bic_drop_train']:.0f}")
        if not v["extensions"]:
            L.append("* none")
        L.append("")
        ms = v["model"]
        L.append("Model structure and fitted gains:")
        L.append("")
        for t in ms["terms"]:
            L.append(f"* {t['structure']}: gain {t['gain']:.4g}")
        if ms["output_lag"]:
            L.append(f"* {ms['output_lag']}")
        L.append("")
    if d.selection_check:
        sc = d.selection_check
        a, b = sc["selected_on_h"], sc["scored_on_h"]
        L += ["## Selection check", "",
              f"The same selection run on validation rows {a[0]:.1f}–{a[1]:.1f} h only, scored on {b[0]:.1f}–{b[1]:.1f} h, "
              "which took no part in it (fit % on that part; a short part with little variance gives low fits):", "",
              f"| channel | static, all temperatures | {d.criterion_name}-selected regression | extended |",
              "|---|---|---|---|"]
        for c, v in sc["channels"].items():
            L.append(f"| {c} | {v['static_all_temperatures']:.1f} | {v['base']:.1f} | {v['extended']:.1f} |")
        L.append("")
    if s["post_process_updating"]:
        pu = s["post_process_updating"]
        L += [f"## Post-process gain updating: a probe every {pu['every_h']:g} h", "",
              "The extended model as a transfer-function model with post-process gain updating: on the validation "
              f"rows the drift is measured every {pu['every_h']:g} h (repeatability {pu['probe_sd_um']:g} µm), and a "
              "Kalman filter updates the model's gain and offset at each measurement; every row is predicted from "
              "the measurements before it. How fast gain and offset may wander was chosen on the training rows "
              "(the updating replayed on the cross-validation's predictions of them).", "",
              "| channel | held out, no updating: fit % (RMS) | with updating: fit % (RMS, P2P) | probes | gain at the end "
              "| offset at the end [µm] |", "|---|---|---|---|---|---|"]
        for c, v in pu["channels"].items():
            a, b = v["without_updating"], v["fit"]
            L.append(f"| {c} | {a['fit_percent']:.1f} ({a['rms']:.3g}) | {b['fit_percent']:.1f} ({b['rms']:.3g}, "
                     f"{b['p2p']:.3g}) | {v['probes']} | {v['final_gain']:.3f} | {v['final_offset_um']:.3g} |")
        L += ["", "The filter per channel, as chosen on the training rows:", ""]
        L += [f"* {c}: {u['settings'].describe()}" for c, u in d.updating.items()]
        L.append("")
    L += _regularised_report(s)
    if plots:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            n = len(d.extended)
            fig, axes = plt.subplots(n, 1, figsize=(11, 2.2 * n + 0.5), sharex=True, squeeze=False)
            th = (d.time_s - d.time_s[0]) / 3600
            t_val = th[d.split.validation][0]
            for ax, (c, m) in zip(axes[:, 0], d.extended.items()):
                ax.plot(th, d.Y[c], "k", lw=0.8, label="measured")
                ax.plot(th, m.y_hat, "tab:blue", lw=0.8, label="extended")
                if d.updating:
                    u = d.updating[c]
                    ax.plot(th[d.split.validation], u["y_hat"], "tab:orange", lw=0.8, label="updated by probes")
                    ax.plot(th[u["probe_rows"]], d.Y[c][u["probe_rows"]], "o", ms=2.5, color="tab:red", label="probes")
                ax.axvspan(t_val, th[-1], color="0.92", zorder=0)
                ax.set_ylabel(c, fontsize=8)
            axes[0, 0].legend(fontsize=7)
            axes[-1, 0].set_xlabel("time [h] (grey: validation)")
            fig.tight_layout()
            fig.savefig(out / "channels.png", dpi=90)
            plt.close(fig)
            L += ["![channels](channels.png)", ""]
            if d.runs is not None:
                _plot_runs(d, out / "runs.png", plt)
                L += ["Per run (time since its start; each run from its own zero; dashed: the extended model; "
                      "thick: validation runs):", "", "![runs](runs.png)", ""]
        except ImportError:
            log.warning("matplotlib is not installed: no plots (pip install 'hybridcomp[plot]')")
    write_text_atomic(out / "report.md", "\n".join(L) + "\n")
    return s
