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

GAIN_SD = 0.25  # prior spread of the gain: the model's own gain may be 25 % off on new data
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


# ------------------------------------------------------------------------------------------ coefficient updating
# Coefficient updating (recursive least squares with forgetting, as a Kalman filter over the model's coefficients).
#
# The regularised model (:mod:`hybridcomp.diagnose.regularised`) predicts ``ŷ = zᵀθ`` with ``z`` the standardised
# regressors and an intercept. Its coefficients are the filter's states: the prior is the training fit, ``θ₀`` with
# covariance ``prior_scale · s² A⁻¹`` (``A = ZᵀZ + λR`` of the training rows, ``s²`` the cross-validation's mean
# squared error); between probes every coefficient follows a random walk of ``walk · s² / p`` per hour (forgetting:
# old probes count less), and every hour a regressor spends outside its training range adds
# ``range_walk · s² / p · e²`` to its coefficient's variance (``e`` the excursion beyond the range in standard
# deviations): a speed the training never ran makes the model's weights there uncertain, so the next probe counts more.
# At a probe the states are updated by the Kalman gain. The predicted spread ``√(zᵀPz)`` of every row is returned too.
COEF_PRIOR_SCALES = (1.0, 100.0)
COEF_WALKS = (0.0, 0.1, 1.0)  # × s²/p per hour
COEF_RANGE_WALKS = (0.0, 10.0)  # × s²/p per hour and (standard deviations beyond the training range)²
COEF_OFFSET_WALKS = (0.0, 1.0)  # the intercept's own random walk, × s² per hour
COEF_GAIN_WALKS = (0.0, 0.03, 0.1)  # the gain's random walk [1/√h]: all coefficients in proportion (as g ŷ)


@dataclass(frozen=True)
class CoefficientSettings:
    """A coefficient filter: a probe every ``every_h`` hours, the prior's scale and the random walks."""

    every_h: float
    probe_sd_um: float
    prior_scale: float
    walk: float
    range_walk: float
    offset_walk: float = 0.0
    gain_walk_per_sqrt_h: float = 0.0
    gain_sd: float = GAIN_SD  # prior spread of a common gain on every coefficient

    def describe(self) -> str:
        return (f"probe every {self.every_h:g} h (repeatability {self.probe_sd_um:g} µm); coefficients from the "
                f"training fit, covariance {self.prior_scale:g} × the fit's; random walk {self.walk:g} s²/p per h "
                f"(the offset {self.offset_walk:g} s² per h more), a common gain 1 ± {self.gain_sd:g} walking "
                f"{self.gain_walk_per_sqrt_h:g}/√h, {self.range_walk:g} s²/p per h and (σ beyond the training range)²")

    def walk_diag(self, s2_um2: float, p: int) -> np.ndarray:
        """The coefficients' random-walk variance per hour [µm² per unit of each regressor, per h]."""
        q = np.full(p, self.walk * s2_um2 / p)
        q[0] += self.offset_walk * s2_um2
        return q


@dataclass(frozen=True)
class FilterState:
    """The coefficient filter between rows.

    Coefficients, their covariance at the last probe, the time of the last probe and of the last row [s], and the
    accumulated (excursion² · h) per coefficient since the last probe.
    """

    theta: np.ndarray
    P: np.ndarray
    t_probe_s: float
    t_last_s: float
    excess: np.ndarray
    theta0: np.ndarray  # the training fit's coefficients: the direction of a common gain


def filter_start(coef: np.ndarray, A: np.ndarray, s2_um2: float, s: CoefficientSettings, t_s: float) -> FilterState:
    """The filter's state before the first row: the training fit's coefficients and covariance.

    The covariance is ``prior_scale · s² A⁻¹`` plus the spread of a common gain on every coefficient
    (``gain_sd² θ₀θ₀ᵀ``).
    """
    c = np.asarray(coef, float).copy()
    P = s.prior_scale * s2_um2 * np.linalg.inv(A) + s.gain_sd**2 * np.outer(c, c)
    return FilterState(c, 0.5 * (P + P.T), float(t_s), float(t_s), np.zeros(len(c)), c)


def excursion(z: np.ndarray, z_lo: np.ndarray, z_hi: np.ndarray) -> np.ndarray:
    """How far standardised regressors lie outside their training range [standard deviations] (0 inside).

    The intercept column (first) never does. Works on one row or a rows × columns array.
    """
    zr = z[..., 1:]
    e = np.maximum(0.0, np.maximum(zr - z_hi, z_lo - zr))
    return np.concatenate([np.zeros(e.shape[:-1] + (1,)), e], axis=-1)


def _effective_P(st: FilterState, t_s: float, q_walk: np.ndarray, q_range: float, gain_walk: float) -> np.ndarray:
    """The covariance at ``t_s``: the last probe's, the random walks since it and the range excursions."""
    h = (t_s - st.t_probe_s) / 3600.0
    return st.P + np.diag(q_walk * h + q_range * st.excess) + gain_walk**2 * h * np.outer(st.theta0, st.theta0)


def filter_step(st: FilterState, z: np.ndarray, t_s: float, s: CoefficientSettings, s2_um2: float,
                z_lo: np.ndarray, z_hi: np.ndarray, y_um: float | None = None) -> tuple[FilterState, float, float]:
    """One row of the coefficient filter (a pure function): the new state, the prediction [µm] and its spread [µm].

    The prediction ``zᵀθ`` and its spread come from the state before the row; then, if ``y_um`` was probed at this
    row, the update.

    ``z``: the row's standardised regressors with the intercept (:meth:`RidgeModel.design`); ``s2_um2`` the model's
    mean squared error that scales the walks; ``z_lo`` / ``z_hi`` the training range of ``z[1:]``.
    """
    p = len(st.theta)
    q_walk, q_range = s.walk_diag(s2_um2, p), s.range_walk * s2_um2 / p
    e = excursion(z, z_lo, z_hi)
    excess = st.excess + e**2 * max(t_s - st.t_last_s, 0.0) / 3600.0
    st = FilterState(st.theta, st.P, st.t_probe_s, float(t_s), excess, st.theta0)
    P = _effective_P(st, t_s, q_walk, q_range, s.gain_walk_per_sqrt_h)
    pred = float(z @ st.theta)
    spread = float(np.sqrt(max(z @ P @ z, 0.0)))
    if y_um is None:
        return st, pred, spread
    Pz = P @ z
    k = Pz / (z @ Pz + s.probe_sd_um**2)
    theta = st.theta + k * (y_um - pred)
    P = P - np.outer(k, Pz)
    return FilterState(theta, 0.5 * (P + P.T), float(t_s), float(t_s), np.zeros(p), st.theta0), pred, spread


def coefficient_updating(Z: np.ndarray, y: np.ndarray, time_s: np.ndarray, probes: np.ndarray, coef: np.ndarray,
                         A: np.ndarray, s2_um2: float, z_lo: np.ndarray, z_hi: np.ndarray,
                         s: CoefficientSettings, spread: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The coefficient filter over rows (vectorised between probes; the same as :func:`filter_step` row by row).

    Parameters
    ----------
    Z : standardised regressors with the intercept, rows × (1 + columns)
    y : measured drift [µm]; only the values at ``probes`` are read
    probes : sorted row indices of the measurements
    spread : compute the spread (else NaN: faster, for choosing the settings)

    Returns
    -------
    the prediction at every row (from the probes before it), its spread [µm], and the coefficients per row
    """
    n, p = Z.shape
    q_walk, q_range = s.walk_diag(s2_um2, p), s.range_walk * s2_um2 / p
    st = filter_start(coef, A, s2_um2, s, time_s[0])
    gw2 = s.gain_walk_per_sqrt_h**2
    out, sd, thetas = np.empty(n), np.full(n, np.nan), np.empty((n, p))
    e2 = excursion(Z, z_lo, z_hi) ** 2
    dt_h = np.r_[0.0, np.diff(time_s)] / 3600.0
    probe_set = set(np.asarray(probes, int).tolist())
    cuts = np.unique(np.r_[0, np.asarray(probes, int) + 1, n])
    excess = np.zeros(p)
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b <= a:
            continue
        seg = slice(a, b)
        acc = excess + np.cumsum(e2[seg] * dt_h[seg, None], axis=0)  # accumulated up to and including each row
        Zs = Z[seg]
        out[seg] = Zs @ st.theta
        thetas[seg] = st.theta
        if spread:
            h = (time_s[seg] - st.t_probe_s) / 3600.0
            var = np.einsum("ij,jk,ik->i", Zs, st.P, Zs) + h * ((Zs * Zs) @ q_walk) \
                + q_range * np.einsum("ij,ij->i", Zs * Zs, acc) + gw2 * h * (Zs @ st.theta0) ** 2
            sd[seg] = np.sqrt(np.clip(var, 0.0, None))
        k = b - 1
        if k in probe_set:
            z = Z[k]
            P = _effective_P(FilterState(st.theta, st.P, st.t_probe_s, float(time_s[k]), acc[-1], st.theta0),
                             float(time_s[k]), q_walk, q_range, s.gain_walk_per_sqrt_h)
            Pz = P @ z
            g = Pz / (z @ Pz + s.probe_sd_um**2)
            theta = st.theta + g * (y[k] - z @ st.theta)
            P = P - np.outer(g, Pz)
            st = FilterState(theta, 0.5 * (P + P.T), float(time_s[k]), float(time_s[k]), np.zeros(p), st.theta0)
            excess = np.zeros(p)
        else:
            excess = acc[-1]
    return out, sd, thetas


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
