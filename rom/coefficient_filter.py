"""A Kalman filter over a linear model's coefficients: recursive least squares with forgetting, from sparse probes.

A regression compensation model predicts ``ŷ = zᵀθ`` with ``z`` its standardised regressors and an intercept. The
coefficients are the filter's states: the prior is the training fit, ``θ₀`` with covariance
``prior_scale · s² A⁻¹ + gain_sd² θ₀θ₀ᵀ`` (``A = ZᵀZ + λR`` of the training rows, ``s²`` the model's mean squared
error; the second term a common gain on every coefficient); between probes every coefficient follows a random walk
of ``walk · s² / p`` per hour (forgetting: old probes count less), the intercept one of ``offset_walk · s²`` more and
the common gain one of ``gain_walk²`` per hour along ``θ₀``; and every hour a regressor spends outside its training
range adds ``range_walk · s² / p · e²`` to its coefficient's variance (``e`` the excursion beyond the range in
standard deviations): a speed the training never ran makes the model's weights there uncertain, so the next probe
counts more. At a probe the states are updated by the Kalman gain; the predicted spread ``√(zᵀPz)`` comes with every
row.

It lives here, below both, so that the data-only diagnosis (:mod:`hybridcomp.diagnose.updating`, which chooses the
settings on the training rows) and the monitor's data-only strategy (:mod:`hybridcomp.monitor.dataonly_strategy`)
run the same filter. :func:`filter_step` is pure (one row); :func:`coefficient_updating` is the same over many rows,
vectorised between probes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAIN_SD = 0.25  # prior spread of a common gain: the model's own gain may be 25 % off on new data


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
