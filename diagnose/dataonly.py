"""Diagnosis on a dataset alone (``--data-only``): no FE model, the model under test is a compensation model.

The model under test is a multiple linear regression of each measured drift channel (``*_um``) on the
temperature sensors (``*_degC``), inputs selected greedily by BIC on the training part.  The candidate
extensions are data-side, each a named, parametrised regressor or model structure:

| kind | parameters | regressor |
|---|---|---|
| ``activity_lag`` | signal, exponent n, τ [h] | first-order lag of an activity signal (``*_rpm`` speed, ``*_mm`` axis speed), normalised, to the power n |
| ``heating_cooling`` | signal, τ heating, τ cooling [h] | a lag whose time constant differs while the signal rises (heating) and falls (cooling) |
| ``sensor_lag`` | sensor, τ [h] | ``T − lag_τ(T)``: the sensor lags the structure it stands for (a lead term) |
| ``autoregressive`` | τ [h] | output-error AR(1): ``ŷ_k = a ŷ_{k−1} + (1 − a) x_kᵀβ``, i.e. every regressor through one lag |

Extensions are added greedily while the training BIC drops and the validation fit improves.  The
validation part is used for this selection, so its fit is an optimistic estimate of a fresh dataset's.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hybridcomp.diagnose.data import Dataset, DatasetError, Split, check_channels
from hybridcomp.diagnose.metrics import channel_metrics, fit_percent
from hybridcomp.diagnose.problem import first_order_lag

log = logging.getLogger(__name__)

LAGS_H = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
EXPONENTS = (1.0, 2.0)
MAX_INPUTS = 16
SPLIT_LAGS_H = (0.25, 0.5, 1.0, 2.0, 4.0)
SENSOR_LAGS_H = (0.1, 0.25, 0.5, 1.0, 2.0)
AR_H = (0.05, 0.1, 0.25, 0.5, 1.0)
MIN_FIT_GAIN = 0.5  # validation fit points an extension must add
MIN_BIC_DROP = 10.0


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
    """Per channel: the static regression of all temperatures (reference), the BIC-selected regression (the
    model under test), and the extended model with its named extensions and gains."""

    time_s: np.ndarray
    Y: dict
    split: Split
    reference: dict
    base: dict
    extended: dict
    extensions: dict  # channel -> list of dicts (name, kind, parameters, gain)
    timings_s: dict


def _activity_signals(ds: Dataset) -> dict[str, np.ndarray]:
    """Normalised activity 0..1: |speed| / max for ``*_rpm``; axis speed |Δx/Δt| / max for ``*_mm``."""
    out = {}
    t = ds.time_s
    for n in ds.names:
        v = ds[n]
        if n.endswith("_rpm"):
            a = np.abs(v)
        elif n.endswith("_mm"):
            a = np.r_[0.0, np.abs(np.diff(v)) / np.diff(t)]
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
    """Every data-side extension regressor of a dataset."""
    t = ds.time_s
    out = []
    for name, s in _activity_signals(ds).items():
        for n in EXPONENTS:
            for tau in LAGS_H:
                out.append(Term(f"lag({name}^{n}, {tau:g} h)", "activity_lag", {"signal": name, "exponent": n, "tau_h": tau},
                                first_order_lag(t, s**n, tau * 3600)))
        for th in SPLIT_LAGS_H:
            for tc in SPLIT_LAGS_H:
                if th == tc:
                    continue
                out.append(Term(f"heat/cool({name}, {th:g} h / {tc:g} h)", "heating_cooling",
                                {"signal": name, "tau_heating_h": th, "tau_cooling_h": tc},
                                heating_cooling_lag(t, s, th * 3600, tc * 3600)))
    for T in temps:
        v = ds[T]
        for tau in SENSOR_LAGS_H:
            out.append(Term(f"lead({T}, {tau:g} h)", "sensor_lag", {"sensor": T, "tau_h": tau},
                            v - first_order_lag(t, v, tau * 3600)))
    return out


def _fit(time_s, terms: list[Term], y: np.ndarray, train: np.ndarray, ar_tau_h: float | None):
    X = np.column_stack([np.ones(y.size)] + [tm.values for tm in terms])
    if ar_tau_h:
        X = np.column_stack([first_order_lag(time_s, X[:, j], ar_tau_h * 3600) for j in range(X.shape[1])])
    coef, *_ = np.linalg.lstsq(X[train], y[train], rcond=None)
    return coef, X @ coef


def decorrelation_samples(r: np.ndarray) -> int:
    """Lag [samples] at which a residual's autocorrelation falls below 1/e (at least 1)."""
    a = np.asarray(r, float) - np.mean(r)
    m = 1 << int(np.ceil(np.log2(2 * a.size)))
    f = np.fft.rfft(a, m)
    ac = np.fft.irfft(f * np.conj(f), m)[: a.size]
    if ac[0] <= 0:
        return 1
    below = np.flatnonzero(ac / ac[0] < np.exp(-1))
    return int(max(1, below[0] if below.size else a.size))


def _bic(y, y_hat, mask, k) -> float:
    """BIC on the training rows.  (Dividing N by the residual's decorrelation length, tried on the spindle
    test, selected fewer inputs and predicted the validation part worse.)"""
    r = y[mask] - y_hat[mask]
    n = r.size
    return float(n * np.log(max(r @ r, 1e-300) / n) + k * np.log(n))


def _greedy_temps(t, temps: dict[str, np.ndarray], y, train) -> list[Term]:
    """Forward selection of temperature inputs by BIC on the training part."""
    chosen: list[Term] = []
    pool = [Term(n, "sensor", {"sensor": n}, v) for n, v in temps.items()]
    _, yh = _fit(t, chosen, y, train, None)
    best_bic = _bic(y, yh, train, 1)
    while pool and len(chosen) < MAX_INPUTS:
        trials = []
        for tm in pool:
            _, yh = _fit(t, chosen + [tm], y, train, None)
            trials.append((_bic(y, yh, train, len(chosen) + 2), tm))
        b, tm = min(trials, key=lambda x: x[0])
        if b > best_bic - MIN_BIC_DROP:
            break
        chosen.append(tm)
        pool.remove(tm)
        best_bic = b
    return chosen


def diagnose_data_only(ds: Dataset, split: Split, max_terms: int = 12, min_fit_gain: float = MIN_FIT_GAIN) -> DataOnlyDiagnosis:
    """Diagnose a regression compensation model on a dataset alone (see the module docstring).

    Raises
    ------
    DatasetError
        no ``*_um`` channel or no ``*_degC`` sensor, a constant channel.
    """
    from hybridcomp.fem.blas import single_blas_thread

    with single_blas_thread():
        return _diagnose_data_only(ds, split, max_terms, min_fit_gain)


def _diagnose_data_only(ds: Dataset, split: Split, max_terms: int, min_fit_gain: float) -> DataOnlyDiagnosis:
    t0 = time.perf_counter()
    targets = [n for n in ds.names if n.endswith("_um")]
    temps = [n for n in ds.names if n.endswith("_degC")]
    if not targets:
        raise DatasetError(f"{ds.source}: --data-only needs measured drift columns '*_um'; columns: {', '.join(ds.names)}")
    if not temps:
        raise DatasetError(f"{ds.source}: --data-only needs temperature columns '*_degC'; columns: {', '.join(ds.names)}")
    check_channels(ds, targets, split)
    t = ds.time_s
    tr, va = split.train, split.validation
    temp_vals = {n: ds[n] for n in temps if np.ptp(ds[n][tr]) > 0}
    cands = candidate_terms(ds, list(temp_vals))
    log.info("%d candidate extension terms", len(cands))
    reference, base, extended, extensions, Y = {}, {}, {}, {}, {}
    for ch in targets:
        y = ds[ch]
        Y[ch] = y
        allT = [Term(n, "sensor", {}, v) for n, v in temp_vals.items()]
        _, yh = _fit(t, allT, y, tr, None)
        reference[ch] = {**channel_metrics(y[va], yh[va]), "terms": len(allT)}
        terms = _greedy_temps(t, temp_vals, y, tr)
        ar = None
        _, yh = _fit(t, terms, y, tr, ar)
        base[ch] = {**channel_metrics(y[va], yh[va]), "inputs": [tm.name for tm in terms]}
        cur_bic = _bic(y, yh, tr, len(terms) + 1)
        cur_fit = fit_percent(y[va], yh[va])
        ext: list[dict] = []
        for _ in range(max_terms):
            trials = []
            used = {tm.name for tm in terms}
            for tm in cands:
                if tm.name in used:
                    continue
                _, yh2 = _fit(t, terms + [tm], y, tr, ar)
                trials.append((cur_bic - _bic(y, yh2, tr, len(terms) + 2 + (ar is not None)),
                               fit_percent(y[va], yh2[va]) - cur_fit, tm, None))
            for tm in [tm for tm in terms if tm.kind == "sensor"]:
                rest = [x for x in terms if x is not tm]
                _, yh2 = _fit(t, rest, y, tr, ar)
                trials.append((cur_bic - _bic(y, yh2, tr, len(rest) + 1 + (ar is not None)),
                               fit_percent(y[va], yh2[va]) - cur_fit, ("drop", tm), None))
            if ar is None:
                for tau in AR_H:
                    _, yh2 = _fit(t, terms, y, tr, tau)
                    trials.append((cur_bic - _bic(y, yh2, tr, len(terms) + 2), fit_percent(y[va], yh2[va]) - cur_fit,
                                   None, tau))
            trials.sort(key=lambda x: -x[0])
            ok = [x for x in trials if x[0] >= MIN_BIC_DROP and x[1] >= min_fit_gain]
            if not ok:
                break
            drop, gain, tm, tau = ok[0]
            if isinstance(tm, tuple):
                terms.remove(tm[1])
                ext.append({"name": "drop_input", "term": f"without {tm[1].name}", "parameters": {"sensor": tm[1].name},
                            "gain": {"validation_fit_points": float(gain), "bic_drop_train": float(drop)}})
            elif tm is not None:
                terms.append(tm)
                ext.append({"name": tm.kind, "term": tm.name, "parameters": tm.params, "gain": {
                    "validation_fit_points": float(gain), "bic_drop_train": float(drop)}})
            else:
                ar = tau
                ext.append({"name": "autoregressive", "term": f"AR(1) output lag {tau:g} h", "parameters": {"tau_h": tau},
                            "gain": {"validation_fit_points": float(gain), "bic_drop_train": float(drop)}})
            coef, yh = _fit(t, terms, y, tr, ar)
            cur_bic = _bic(y, yh, tr, len(terms) + 1 + (ar is not None))
            cur_fit = fit_percent(y[va], yh[va])
        coef, yh = _fit(t, terms, y, tr, ar)
        extended[ch] = ChannelModel(ch, tuple(terms), ar, coef, yh)
        extensions[ch] = ext
        log.info("%s: reference fit %.1f %%, base %.1f %%, extended %.1f %%", ch, reference[ch]["fit_percent"],
                 base[ch]["fit_percent"], cur_fit)
    return DataOnlyDiagnosis(t, Y, split, reference, base, extended, extensions, {"total": time.perf_counter() - t0,
                                                                                   "candidates": len(cands)})


def summary(d: DataOnlyDiagnosis) -> dict:
    va = d.split.validation
    ch = {}
    for c, m in d.extended.items():
        after = channel_metrics(d.Y[c][va], m.y_hat[va])
        ch[c] = {"reference_all_temperatures": d.reference[c], "before": d.base[c], "after": after,
                 "extensions": d.extensions[c]}
    causes = [{"channel": c, **e} for c in d.extended for e in d.extensions[c]]
    return {
        "mode": "data-only",
        "verdict": "extended" if causes else "no significant discrepancy",
        "causes": causes,
        "before": {c: {k: v for k, v in d.base[c].items() if k != "inputs"} for c in d.extended},
        "after": {c: ch[c]["after"] for c in d.extended},
        "channels": ch,
        "split": d.split.describe(d.time_s),
        "timings_s": d.timings_s,
    }


def write_data_only_report(d: DataOnlyDiagnosis, out_dir, dataset_name: str = "", plots: bool = True) -> dict:
    """``report.md`` (with a plot), ``summary.json`` of a data-only diagnosis."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = summary(d)
    s["dataset"] = dataset_name
    (out / "summary.json").write_text(json.dumps(s, indent=2, default=float))
    L = [f"# Data-only diagnosis{' of ' + dataset_name if dataset_name else ''}", "",
         "Model under test: a multiple linear regression of each drift channel on the temperature sensors, inputs "
         "selected greedily by BIC on the training part. Extensions: lag terms of activity signals, heating/cooling "
         "split, sensor lags (lead terms), an autoregressive output lag; added while the training BIC drops and the "
         "validation fit improves (the validation part takes part in this selection).", "",
         f"Training rows {s['split']['train_rows']}, validation rows {s['split']['validation_rows']}; "
         f"{d.timings_s['candidates']} candidate terms; {d.timings_s['total']:.1f} s.", "",
         "| channel | static, all temperatures: fit % | BIC-selected regression: fit % (RMS, P2P) | extended: fit % (RMS, P2P) |",
         "|---|---|---|---|"]
    for c, v in s["channels"].items():
        b, a = v["before"], v["after"]
        L.append(f"| {c} | {v['reference_all_temperatures']['fit_percent']:.1f} | {b['fit_percent']:.1f} "
                 f"({b['rms']:.3g}, {b['p2p']:.3g}) | {a['fit_percent']:.1f} ({a['rms']:.3g}, {a['p2p']:.3g}) |")
    L += ["", "## Extensions found", ""]
    for c, v in s["channels"].items():
        L.append(f"**{c}** (inputs {', '.join(v['before']['inputs'])}):")
        L.append("")
        for e in v["extensions"]:
            L.append(f"* {e['term']} — +{e['gain']['validation_fit_points']:.1f} fit points, BIC drop "
                     f"{e['gain']['bic_drop_train']:.0f}")
        if not v["extensions"]:
            L.append("* none")
        L.append("")
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
                ax.axvspan(t_val, th[-1], color="0.92", zorder=0)
                ax.set_ylabel(c, fontsize=8)
            axes[0, 0].legend(fontsize=7)
            axes[-1, 0].set_xlabel("time [h] (grey: validation)")
            fig.tight_layout()
            fig.savefig(out / "channels.png", dpi=90)
            plt.close(fig)
            L += ["![channels](channels.png)", ""]
        except ImportError:
            log.warning("matplotlib is not installed: no plots (pip install 'hybridcomp[plot]')")
    (out / "report.md").write_text("\n".join(L) + "\n")
    return s
