"""Post-process gain updating: a compensation model corrected by occasional measurements of the drift.

On a machine, a probe cycle in a pause (or a measured part) now and then gives the true drift at that moment.
Post-process updating uses those few measurements to correct the model between them: the model's prediction
``ŷ`` becomes ``g ŷ + o``, with a gain ``g`` (1 at first) and an offset ``o`` [µm] (0 at first) that a Kalman
filter re-estimates at every measurement. Both follow a random walk between measurements, so the correction
keeps learning when the machine's behaviour changes (a new fixture, a season, a speed the training never saw).

Every prediction uses only the measurements taken before it.  The filter's settings (how far gain and offset may
wander per hour) are chosen on the training rows, by replaying the updating on the blocked cross-validation's
predictions of them (each block predicted by the model fitted on the others, probed as the validation rows
will be); the validation rows only supply the probes, so the updated fit stays a held-out fit between probes.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from hybridcomp.rom.coefficient_filter import (
    GAIN_SD,
    CoefficientSettings,
    FilterState,
    coefficient_updating,
    excursion,
    filter_start,
    filter_step,
)

__all__ = ["GAIN_SD", "CoefficientSettings", "FilterState", "coefficient_updating", "excursion", "filter_start",
           "filter_step", "UpdateSettings", "probe_rows", "updated_prediction", "choose_settings",
           "choose_coefficient_settings"]
GAIN_WALK_PER_SQRT_H = (0.0, 0.01, 0.03, 0.1)  # candidate gain random walks [1/√h]
OFFSET_WALK_FACTORS = (0.3, 1.0, 3.0)  # candidate offset random walks, × the model's cross-validation RMS per √h


@dataclass(frozen=True)
class UpdateSettings:
    """A post-process updating scheme: a probe every ``every_h`` hours and the filter's spreads."""

    every_h: float
    probe_sd_um: float  # the measurement's repeatability
    offset_sd_um: float  # prior spread of the offset
    gain_walk_per_sqrt_h: float
    offset_walk_um_per_sqrt_h: float

    def describe(self) -> str:
        return (f"probe every {self.every_h:g} h (repeatability {self.probe_sd_um:g} µm); gain 1 ± {GAIN_SD:g}, "
                f"walk {self.gain_walk_per_sqrt_h:g}/√h; offset 0 ± {self.offset_sd_um:.2g} µm, "
                f"walk {self.offset_walk_um_per_sqrt_h:.2g} µm/√h")


def probe_rows(time_s: np.ndarray, rows: np.ndarray, every_h: float) -> np.ndarray:
    """Rows (indices into ``time_s``) at which a probe is taken.

    The first of ``rows`` at or after each multiple of ``every_h`` past the first of them (the first row itself is
    not probed: the model starts unaided).
    """
    if not every_h > 0:
        raise ValueError(f"the probe interval must be positive, got {every_h!r} h")
    idx = np.flatnonzero(rows)
    if idx.size == 0:
        return idx
    t = time_s[idx]
    marks = t[0] + every_h * 3600.0 * np.arange(1, int((t[-1] - t[0]) // (every_h * 3600.0)) + 1)
    k = np.searchsorted(t, marks - 1e-9)
    return np.unique(idx[k[k < idx.size]])


def updated_prediction(y_hat: np.ndarray, y: np.ndarray, time_s: np.ndarray, probes: np.ndarray,
                       s: UpdateSettings, restarts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``g ŷ + o`` with gain and offset updated at each probe row by a Kalman filter; each row uses earlier probes only.

    Parameters
    ----------
    y_hat : the model's prediction [µm] at every row
    y : the measured drift [µm]; only the values at ``probes`` are read
    probes : sorted row indices of the measurements
    restarts : rows at which the offset starts afresh (a run of a campaign, with its own zero); the gain carries on

    Returns
    -------
    the updated prediction at every row, and (gain, offset) per row
    """
    n = y_hat.size
    out = np.empty(n)
    theta = np.empty((n, 2))
    th = np.array([1.0, 0.0])
    P = np.diag([GAIN_SD**2, s.offset_sd_um**2])
    q = np.array([s.gain_walk_per_sqrt_h**2, s.offset_walk_um_per_sqrt_h**2])
    r2 = s.probe_sd_um**2
    restart = set() if restarts is None else set(int(k) for k in restarts)
    is_probe = np.zeros(n, bool)
    is_probe[probes] = True
    t_last = time_s[0]
    for k in range(n):
        if k in restart:
            th[1] = 0.0
            P[1, :] = P[:, 1] = 0.0
            P[1, 1] = s.offset_sd_um**2
        out[k] = th[0] * y_hat[k] + th[1]
        theta[k] = th
        if is_probe[k]:
            P += np.diag(q * (time_s[k] - t_last) / 3600.0)
            t_last = time_s[k]
            h = np.array([y_hat[k], 1.0])
            Ph = P @ h
            gain = Ph / (h @ Ph + r2)
            th = th + gain * (y[k] - h @ th)
            P = P - np.outer(gain, Ph)
    return out, theta


def choose_settings(time_s: np.ndarray, y: np.ndarray, cv_blocks: list[tuple[np.ndarray, np.ndarray]],
                    every_h: float, probe_sd_um: float) -> tuple[UpdateSettings, float]:
    """The filter spreads that predict the training blocks best when they are probed every ``every_h`` hours.

    ``cv_blocks``: per block of the training rows, its row indices (contiguous in time) and the prediction of them
    by the model fitted on the other blocks. Returns the settings and their pooled RMS error [µm] on the blocks.
    """
    e2 = sum(float(np.sum((y[rows] - p) ** 2)) for rows, p in cv_blocks)
    n = sum(rows.size for rows, _ in cv_blocks)
    cv_rms = float(np.sqrt(e2 / max(n, 1)))
    probes = [probe_rows(time_s[rows], np.ones(rows.size, bool), every_h) for rows, _ in cv_blocks]
    best, best_sse = None, np.inf
    for gw, of in itertools.product(GAIN_WALK_PER_SQRT_H, OFFSET_WALK_FACTORS):
        s = UpdateSettings(every_h, probe_sd_um, max(cv_rms, probe_sd_um), gw, of * cv_rms)
        sse = 0.0
        for (rows, p), pr in zip(cv_blocks, probes):
            u, _ = updated_prediction(p, y[rows], time_s[rows], pr, s)
            sse += float(np.sum((y[rows] - u) ** 2))
        if sse < best_sse:
            best, best_sse = s, sse
    return best, float(np.sqrt(best_sse / max(n, 1)))


# coefficient updating (the filter: hybridcomp.rom.coefficient_filter): the settings tried on the training rows
COEF_PRIOR_SCALES = (1.0, 100.0)
COEF_WALKS = (0.0, 0.1, 1.0)  # × s²/p per hour
COEF_RANGE_WALKS = (0.0, 10.0)  # × s²/p per hour and (standard deviations beyond the training range)²
COEF_OFFSET_WALKS = (0.0, 1.0)  # the intercept's own random walk, × s² per hour
COEF_GAIN_WALKS = (0.0, 0.03, 0.1)  # the gain's random walk [1/√h]: all coefficients in proportion (as g ŷ)


def choose_coefficient_settings(blocks: list[dict], every_h: float, probe_sd_um: float
                                ) -> tuple[CoefficientSettings, float]:
    """The coefficient filter that predicts the training blocks best when they are probed every ``every_h`` hours.

    ``blocks``: per block of the training rows (contiguous in time), a dict with ``time_s``, ``y``, ``Z`` and the
    model fitted on the other blocks (``coef``, ``A``, ``s2_um2``, ``z_lo``, ``z_hi``). Returns the settings and
    their pooled RMS error [µm] on the blocks.
    """
    probes = [probe_rows(b["time_s"], np.ones(b["time_s"].size, bool), every_h) for b in blocks]
    n = sum(b["time_s"].size for b in blocks)
    best, best_sse = None, np.inf
    for ps, w, rw, ow, gw in itertools.product(COEF_PRIOR_SCALES, COEF_WALKS, COEF_RANGE_WALKS, COEF_OFFSET_WALKS,
                                               COEF_GAIN_WALKS):
        s = CoefficientSettings(every_h, probe_sd_um, ps, w, rw, ow, gw)
        sse = 0.0
        for b, pr in zip(blocks, probes):
            u, _, _ = coefficient_updating(b["Z"], b["y"], b["time_s"], pr, b["coef"], b["A"], b["s2_um2"],
                                           b["z_lo"], b["z_hi"], s, spread=False)
            sse += float(np.sum((b["y"] - u) ** 2))
        if sse < best_sse:
            best, best_sse = s, sse
    return best, float(np.sqrt(best_sse / max(n, 1)))
