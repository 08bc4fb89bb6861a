"""Residual measures: RMS, peak-to-peak, fit %, the E_P95(range) curve, cross-correlation at lags, noise level."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d


def rms(r: np.ndarray) -> float:
    """Root mean square of a residual [its unit]."""
    r = np.asarray(r, float)
    return float(np.sqrt(np.mean(r**2)))


def p2p(r: np.ndarray) -> float:
    """Peak-to-peak (max − min) of a residual [its unit]."""
    r = np.asarray(r, float)
    return float(r.max() - r.min())


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Fit % = 100 (1 − ‖y − ŷ‖ / ‖y − ȳ‖): 100 perfect, 0 no better than the mean, negative worse [%]."""
    y = np.asarray(y, float)
    den = np.linalg.norm(y - y.mean())
    if den == 0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(y - np.asarray(y_hat, float)) / den))


def channel_metrics(y: np.ndarray, y_hat: np.ndarray) -> dict:
    """RMS and P2P of the residual and the fit % of one channel."""
    r = np.asarray(y, float) - np.asarray(y_hat, float)
    return {"rms": rms(r), "p2p": p2p(r), "fit_percent": fit_percent(y, y_hat)}


def ep95_curve(time_s: np.ndarray, r: np.ndarray, n_windows: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """E_P95(range): the 95th percentile of the residual's range (max − min) in sliding windows.

    Window lengths run log-spaced from one sample step to the whole record.

    Returns
    -------
    window durations [s] and the 95th-percentile ranges [unit of ``r``]
    """
    r = np.asarray(r, float)
    t = np.asarray(time_s, float)
    n = r.size
    dt = float(np.median(np.diff(t))) if n > 1 else 1.0
    steps = np.unique(np.round(np.geomspace(1, max(n - 1, 1), n_windows)).astype(int))
    out = np.empty(steps.size)
    for i, k in enumerate(steps):
        w = k + 1  # k steps span k + 1 samples
        if w >= n:
            out[i] = np.ptp(r)
            continue
        hi = _sliding(r, w, np.maximum)
        lo = _sliding(r, w, np.minimum)
        out[i] = np.percentile(hi - lo, 95)
    return steps * dt, out


def _sliding(r: np.ndarray, w: int, op) -> np.ndarray:
    """Sliding max or min over windows of ``w`` samples, one value per full window (n − w + 1)."""
    f = maximum_filter1d if op is np.maximum else minimum_filter1d
    full = f(r, size=w, mode="nearest")  # centred: index i covers [i - w//2, i - w//2 + w)
    return full[w // 2: r.size - w + w // 2 + 1]


@dataclass(frozen=True)
class Correlation:
    """Normalised cross-correlation of a channel's residual with a signal at a lag.

    ``lag_s`` > 0: the residual follows the signal by that time [s].
    """

    channel: str
    signal: str
    lag_s: float
    r: float

    def as_dict(self) -> dict:
        return {"channel": self.channel, "signal": self.signal, "lag_s": self.lag_s, "r": self.r}


def cross_correlation(res: np.ndarray, sig: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised cross-correlation ρ(k) = corr(res[t], sig[t − k]) for k = −max_lag..max_lag."""
    a = np.asarray(res, float) - np.mean(res)
    b = np.asarray(sig, float) - np.mean(sig)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    lags = np.arange(-max_lag, max_lag + 1)
    if na == 0 or nb == 0:
        return lags, np.zeros(lags.size)
    n = a.size
    m = 1 << int(np.ceil(np.log2(2 * n)))
    cc = np.fft.irfft(np.fft.rfft(a, m) * np.conj(np.fft.rfft(b, m)), m)
    vals = np.array([cc[k % m] for k in lags]) / (na * nb)
    return lags, vals


def lag_grid(time_s, max_lag_s: float = 4 * 3600.0) -> tuple[float, int]:
    """Sample interval [s] of a series and the largest lag [samples] its cross-correlations look at.

    The largest lag is ``max_lag_s``, at most a third of the series.
    """
    t = np.asarray(time_s, float)
    dt = float(np.median(np.diff(t)))
    return dt, max(1, min(int(max_lag_s / dt), t.size // 3))


def strongest_correlations(time_s, residuals: dict, signals: dict, max_lag_s: float = 4 * 3600.0, top: int = 8,
                           n_lags: int = 49) -> list[Correlation]:
    """The strongest |ρ| of every residual channel against every signal, over lags up to ``max_lag_s`` [s].

    Signals and residuals are compared as changes (first differences of a smoothed series would
    favour noise; the series themselves are used, mean removed), one best lag per pair.
    """
    dt, max_lag = lag_grid(time_s, max_lag_s)
    out = []
    for c, r in residuals.items():
        for s, v in signals.items():
            if np.ptp(v) == 0:
                continue
            lags, rho = cross_correlation(r, v, max_lag)
            k = int(np.argmax(np.abs(rho)))
            out.append(Correlation(c, s, float(lags[k] * dt), float(rho[k])))
    out.sort(key=lambda c: -abs(c.r))
    return out[:top]


def noise_level(y: np.ndarray) -> float:
    """Robust white-noise level of a measured series from its second differences [its unit].

    σ = 1.4826 · MAD(Δ²y) / √6: second differences cancel slow (thermal) variation, and for white
    noise Var(Δ²e) = 6σ².
    """
    d2 = np.diff(np.asarray(y, float), 2)
    if d2.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def lag1_autocorrelation(r: np.ndarray) -> float:
    """Lag-1 autocorrelation of a series about its mean (0 for a constant series)."""
    a = np.asarray(r, float) - np.mean(r)
    den = float(a @ a)
    return float(a[1:] @ a[:-1] / den) if den > 0 else 0.0
