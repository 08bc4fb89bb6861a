"""A state observer on the reduced structure model: a Kalman filter with disturbance states.

The structure model knows the machine as its machine file describes it; the real machine differs (a loss
estimate off by half, the enclosure air warmer than the workshop's, a pump nobody modelled). The observer
keeps the model on the real machine with what the controller measures: the temperature sensors every step,
and, when there is one, a measured drift (a probe cycle in a pause, as in post-process updating).

Augmented state, in the reduced model's modal coordinates ``z`` (``x_r = Φ z``, ``Φᵀ M_r Φ = I``)::

    z       the thermal state (r)
    air     an offset of each zone's air against what the loads say [K]                  (random walk)
    scale   a relative error of each heat source's power, power × (1 + scale) [-]         (random walk)
    heat    heat the model does not know, per body spread uniformly (ROM shape ``D``) [W]  (random walk)
    bias    a drift offset dx, dy, dz [µm] that only a probe sees                         (random walk)

One step of ``dt`` with the inputs held over it (the daemon's histogram rows are mean powers over the step)::

    z' = e^{-Λ dt} z + g0 Wᵀ(u + [0, air] + [power ⊙ S scale, 0]) + g0 W_Dᵀ heat,   g0 = (1 − e^{-λ dt}) / λ
    sensors = C_s Φ z + T_ref,     drift = C_d Φ z + bias

The filter is the textbook linear Kalman filter on this time-varying system (the scale columns depend on the
known powers); measurements whose innovation is beyond ``gate_sigma`` standard deviations are rejected one by
one and reported (a faulty sensor must not pull the state). The prior at the start is the steady state of the
first inputs with the disturbances at their prior spread (a machine that stood long enough in its air), plus
an uncertain load history (``initial_load``).

The disturbances have admissible ranges (a power is never negative, the air a few K off; ``ObserverSettings``):
after each update an estimate beyond one is projected back onto them in the metric of its covariance
(:func:`project_bounds`, the constrained Kalman filter of Simon & Chia 2002), its correlated states moving with
it. The covariance stays the unconstrained filter's. The truth lies in the admissible set, which is convex, and
a projection onto a convex set in the ``P⁻¹`` metric moves no estimate farther from any point of it, so ``P``
still bounds the error (conservatively). Collapsing it along the active bound, as an equality constraint
would, tells the filter the state is exactly at the bound: the next measurements could no longer move it off,
and the process noise alone would let it go again.

Everything here is pure: :class:`Observer` holds the fixed matrices of one model, :class:`ObserverState`
the estimate; every method returns a new state.
"""

from __future__ import annotations

import base64
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.blas import single_blas_thread
from hybridcomp.models.layout import DRIFT_OUTPUTS
from hybridcomp.models.toml import nonnegative_number

#: drift directions dx, dy, dz: the probed values and the bias states
N_DRIFT = len(DRIFT_OUTPUTS)


class ObserverError(HybridcompError, ValueError):
    """The observer cannot be built or fed: the message names the setting, input or value."""


#: the bounded disturbance kinds and the settings of their lower bounds (the upper: ``_min`` → ``_max``)
BOUND_SETTINGS = {"air": "air_min_K", "scale": "scale_min", "heat": "heat_min_W"}


def _is_finite_number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True)
class ObserverSettings:
    """Noise levels of the observer: priors (standard deviations at the start) and rates (per √h).

    Attributes
    ----------
    sensor_sigma_K : measurement noise of a temperature sensor, model error included [K] (the model's own
        error at a sensor near a source, from loads known only as step means, is larger than a sensor's noise)
    probe_sigma_um : noise of a probed drift [µm]
    air_sigma_K, air_rate_K : prior and random-walk rate of a zone's air offset [K, K/√h]
    air_common : the share of the zones' air random walks they have in common [-] (0: each zone on its own; 1: one
        offset for all). Where the air column the trace measures does not stand for the air around the machine (a
        sensor by the door, a workshop that swings), the enclosures' and the floor's air still move together, and
        a sensor on any body then tells about the air at every other.

        The defaults (3 K/√h, 0.8) are set by the screws: a screw follows its air within half an hour, so an air
        estimate behind an unmeasured swing leaves the drives the swing's change over the lag (15 min behind a
        ±1.5 K, 6 h swing: 2.6 µm of the Y screw's ±10 µm). The sensors on the structure see the air late and
        weakly, and a slow walk follows them late: with 1 K/√h and a walk per zone (the former defaults) the
        estimate was 15 to 65 min behind that swing, the floor zone's at half its amplitude; the common part
        gives every zone the evidence of every body's sensors and the faster walk takes it sooner (10 to 15 min
        behind at 0.8 and 1 K/√h; 7 to 10 min at 3 K/√h, ``tests/test_observer.py``). The compensation
        benchmark (150 mm, 16 h, 2026-12-02), along the path / at the model's pose [µm], former → these
        defaults: ambient swing 5.55 / 1.64 → 1.77 / 0.20 (0.8 at 1 K/√h: 4.40 / 1.42), workspace air 1.28 /
        0.21 → 0.81 / 0.17, unmodelled source 2.25 / 1.20 → 2.20 / 1.21, mis-scaled source, nut heat, scale
        and seized bearing within 0.03 µm. Days they were not chosen on (``benchmarks/observer_air.py``,
        another noise seed): an unmeasured ±1 K, 3 h swing with the spindle motor at 1.3 × 4.60 / 1.21 →
        1.86 / 0.47, ±2 K over 10 h 3.74 / 0.29 → 1.56 / 0.27, rear bearing 0.7 × and workspace +1 K 0.76 /
        0.42 → 0.62 / 0.41, X motor 1.47 × 0.57 / 0.40 → 0.56 / 0.37. The price is what the observer takes
        for air on a day whose air is as measured: the demo day's front bearing, 1.6 × its power, is taken
        for warm air at first, and the screws follow it before the bearing's scale catches up (0.60 / 0.28 →
        0.67 / 0.28; on the 6 h demo of the tests 0.47 → 0.66 µm along the path, 1.4 µm in y from 25 to 70
        min); a stuck sensor is taken for cold or warm air until it is excluded (the sensor fault 0.68 →
        0.83 along the path, 0.75 since a rewind takes the pose-aware model back too; ``frozen_model_K`` asks
        the model run open-loop, ``monitor.transitions``).
    scale_sigma, scale_rate : prior and rate of a heat source's relative power error [-, 1/√h]
    heat_sigma_W, heat_rate_W : prior and rate of unknown heat per disturbance shape [W, W/√h]
    bias_sigma_um, bias_rate_um : prior and rate of the drift offset only probes see [µm, µm/√h]
    input_sigma : model error as a random input per step, a fraction of each input's rated value [-]
    initial_load : spread of the load history before the start, a fraction of the rated powers [-]
    gate_sigma : a measurement whose innovation exceeds this many standard deviations is rejected [-]
    probe_widen_sigma : a probed direction whose innovation exceeds this many standard deviations widens the
        bias's variance by the excess before the update, so that an offset the small prior thought unlikely (a
        fixture that sagged) is taken at once (0: off) [-]
    air_min_K, air_max_K : the admissible range of a zone's air offset [K]
    scale_min, scale_max : the admissible range of a source's relative power error [-]
    heat_min_W, heat_max_W : the admissible range of the unknown heat per disturbance shape [W]

    The ranges hold after every update: an estimate beyond one is projected back (:func:`project_bounds`), its
    correlated states moving with it. Without them a heat the model has no place for (an unmodelled pump) was
    explained by physically impossible values that the pose-aware model then ran on: the Z motor's scale at −3.88
    (a negative power), the floor air 2.9 K off. The defaults: a power is never below 0 (scale ≥ −1); −0.9 keeps a
    tenth of it, since a source the machine file lists and the load model drives runs (one found at a tenth of its
    power is a machine file to correct, by a diagnosis), and +3 (four times the nominal power) is beyond every loss
    estimate's error the package has met (the demo day's front bearing: +0.5). The air the enclosures hold differs
    from the workshop's by a few K (the scenarios: a workspace 2 K warmer, an ambient swing of ±1.5 K): ±3 K. The
    unknown heat per body may be either sign (a coolant flow takes heat away, a pump adds it); ±100 W keeps it
    within the size of the machine's own sources (the demonstrator's: 8 to 220 W; the benchmark's pump: 60 W).

    Admissible is not right: in the compensation benchmark (150 mm) the unmodelled pump's day ends with the Z
    motor at its bound (−0.9), the neighbouring fixed bearing taking up the rest (−0.50 → −0.67), the floor air
    still −2.7 K; the hybrid compensation moved by 0.02 µm (2.40 → 2.38 µm RMS along the path, 2.92 → 2.90 at
    the model's pose); the demo day, workspace air, nut heat and seized bearing did not move (0.515 / 0.28, 1.47 /
    0.20, 2.05 / 0.45, 4.03 / 12.63 µm). Neither did a pose-aware model given only the scales whose posterior σ
    is below the prior (2.39 / 2.91), nor heat bounded at 0 (2.41 / 2.88). What hurt there is the air: without
    the air offsets the pose-aware model reached 1.50 / 1.22 µm, but the workspace air's day (whose air offsets
    are right, with the same posterior σ) went from 1.47 / 0.20 to 9.61 / 14.70 µm, so they stay.

    The priors are small: the model as its machine file describes it is taken as right until the sensors or a
    probe show otherwise. Larger priors let the first measurements' noise into the estimate and keep it there
    (random walks with small rates forget it slowly): with a bias prior of 2 µm the first probe's noise
    (0.3 µm per direction) set the drift offset for hours. The compensation benchmark's cases (150 mm, offline
    on their recorded sensors and probes) measured the drift estimate's RMS against the old priors (air 1 K,
    scale 0.5, heat 30 W, bias 2 µm): 0.44 → 0.23 µm on the demo day, 0.43 → 0.22 after its diagnosis,
    0.50 → 0.23 ambient swing, 0.41 → 0.24 mis-scaled source, 0.46 → 0.16 workspace air, 1.15 → 1.22 µm
    with the unmodelled pump (heat at one place on a body, which no disturbance here represents: the column sensor
    sees it, 0.1 K above the model in 4 h, but the drift it makes is caught only at the probes, as an offset).
    """

    sensor_sigma_K: float = 0.15
    probe_sigma_um: float = 0.5
    air_sigma_K: float = 0.3
    air_rate_K: float = 3.0
    air_common: float = 0.8
    scale_sigma: float = 0.15
    scale_rate: float = 0.1
    heat_sigma_W: float = 3.0
    heat_rate_W: float = 0.5
    bias_sigma_um: float = 0.1
    bias_rate_um: float = 0.1
    input_sigma: float = 0.02
    initial_load: float = 0.3
    gate_sigma: float = 6.0
    probe_widen_sigma: float = 3.0
    air_min_K: float = -3.0
    air_max_K: float = 3.0
    scale_min: float = -0.9
    scale_max: float = 3.0
    heat_min_W: float = -100.0
    heat_max_W: float = 100.0

    def __post_init__(self):
        lower = set(BOUND_SETTINGS.values())
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not _is_finite_number(v):
                raise ObserverError(f"observer setting {f.name!r} must be a finite number, got {v!r}")
        for lo in BOUND_SETTINGS.values():
            hi = lo.replace("_min", "_max")
            if getattr(self, lo) > getattr(self, hi):
                raise ObserverError(f"observer setting {lo!r} ({getattr(self, lo)!r}) is above {hi!r} "
                                    f"({getattr(self, hi)!r}): a lower bound must not exceed its upper one")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in lower:
                if v > 0:
                    raise ObserverError(f"observer setting {f.name!r} must be ≤ 0 (the prior estimate 0 must be "
                                        f"admissible), got {v!r}")
            elif not nonnegative_number(v):
                raise ObserverError(f"observer setting {f.name!r} must be a finite number ≥ 0, got {v!r}")
        for name in ("sensor_sigma_K", "probe_sigma_um", "gate_sigma"):
            if not getattr(self, name) > 0:
                raise ObserverError(f"observer setting {name!r} must be positive, got {getattr(self, name)!r}")
        if self.air_common > 1.0:
            raise ObserverError(f"observer setting 'air_common' is a share of the air's random walk, 0 to 1, "
                                f"got {self.air_common!r}")
        if self.scale_min < -1.0:
            raise ObserverError(f"observer setting 'scale_min' must be ≥ −1 (a power is never negative), "
                                f"got {self.scale_min!r}")

    def bounds(self, kind: str) -> tuple[float, float]:
        """The admissible range (lower, upper) of the disturbance states of ``kind`` (air, scale, heat)."""
        lo = BOUND_SETTINGS[kind]
        return getattr(self, lo), getattr(self, lo.replace("_min", "_max"))


def _output_variance(H: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The variance of each output row of ``H`` under the state covariance ``P``: diag(H P Hᵀ)."""
    return np.einsum("ij,jk,ik->i", H, P, H)


def project_bounds(x: np.ndarray, P: np.ndarray, index: np.ndarray, lower: np.ndarray,
                   upper: np.ndarray) -> np.ndarray:
    """The estimate ``x`` projected onto ``lower ≤ x[index] ≤ upper`` in the metric of its covariance ``P``.

    The constrained Kalman filter's estimate projection (Simon & Chia 2002): the admissible ``x̃`` nearest to ``x``
    in ``(x̃ − x)ᵀ P⁻¹ (x̃ − x)``; with the active constraints ``D x̃ = d`` (a row ±e_i per bound reached)

        x̃ = x − P Dᵀ (D P Dᵀ)⁻¹ (D x − d)

    so that every state correlated with a bounded one moves with it as the covariance says (the conditional mean
    given the bounded states at their bounds), where clipping one coordinate would leave the others explaining
    the measurements with the old value. Which bounds are active is found exactly: on the bounded coordinates
    ``B`` the problem is the box-constrained least squares ``min ‖L⁻¹ (y − x_B)‖``, ``L Lᵀ = P_BB``, solved by
    bounded-variable least squares (an active-set method; the free coordinates then follow ``x̃`` above). A
    coordinate of zero variance cannot be moved by any measurement, nor by this projection, and is left out.

    Parameters
    ----------
    x, P : the estimate and its covariance (n, n × n)
    index : the bounded coordinates (m,); lower, upper : their bounds (m,), lower ≤ upper

    Returns ``x`` itself (not a copy) when it is admissible.
    """
    index = np.asarray(index, int)
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    xb = x[index]
    if np.all((xb >= lower) & (xb <= upper)):
        return x
    keep = np.diag(P)[index] > 0.0
    index, lower, upper, xb = index[keep], lower[keep], upper[keep], xb[keep]
    if not np.any((xb < lower) | (xb > upper)):
        return x
    from scipy.optimize import lsq_linear

    Pbb = P[np.ix_(index, index)]
    try:
        L = la.cholesky(Pbb, lower=True)
    except la.LinAlgError:  # positive semidefinite to round-off: the least regularisation that factors it
        L = la.cholesky(Pbb + np.eye(index.size) * 1e-12 * np.trace(Pbb), lower=True)
    A = la.solve_triangular(L, np.eye(index.size), lower=True)
    sol = lsq_linear(A, A @ xb, bounds=(lower, upper), method="bvls", tol=1e-12)
    act = sol.active_mask != 0
    if not act.any():
        return x
    ia = index[act]
    d = np.where(sol.active_mask[act] < 0, lower[act], upper[act])
    out = x - P[:, ia] @ la.solve(P[np.ix_(ia, ia)], x[ia] - d, assume_a="pos")
    out[ia] = d  # at the bounds exactly, not to round-off
    return out


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f8").tobytes()).decode("ascii")


def _unb64(text: str, shape: tuple[int, ...]) -> np.ndarray:
    a = np.frombuffer(base64.b64decode(text.encode("ascii")), dtype="<f8")
    if a.size != int(np.prod(shape)):
        raise ObserverError(f"observer state: {a.size} numbers where {shape} were expected")
    return a.reshape(shape).copy()


@dataclass(frozen=True)
class ObserverState:
    """The estimate: augmented mean ``x`` and covariance ``P`` at ``time_s`` [s] (see the module docstring)."""

    time_s: float
    x: np.ndarray
    P: np.ndarray

    def to_dict(self) -> dict:
        """JSON-able and bit-exact (base64 of little-endian float64)."""
        return {"time_s": self.time_s, "n": int(self.x.size), "x": _b64(self.x), "P": _b64(self.P)}

    @staticmethod
    def from_dict(d: dict) -> ObserverState:
        n = int(d["n"])
        return ObserverState(float(d["time_s"]), _unb64(d["x"], (n,)), _unb64(d["P"], (n, n)))


@dataclass(frozen=True)
class Innovation:
    """What one sensor update saw.

    Attributes
    ----------
    residual_K : measured minus predicted per sensor, before the update [K] (NaN: not measured)
    normalized : residual over its predicted standard deviation [-]
    rejected : names of the sensors rejected by the gate
    """

    residual_K: np.ndarray
    normalized: np.ndarray
    rejected: tuple[str, ...]


@dataclass(frozen=True)
class Observer:
    """The fixed parts of the filter for one reduced model, machine layout and settings.

    Build it with :func:`build_observer`. Attributes are the modal matrices (``lam`` decay rates [1/s],
    ``W`` modal input columns, ``WD`` modal disturbance columns, ``Cs`` sensor rows [K], ``Cd`` drift rows
    [µm]), the grouping of heat inputs into sources (``S``), the rated input values, and names.
    """

    settings: ObserverSettings
    rom_id: str
    reference_temperature_degC: float
    sensor_names: tuple[str, ...]
    zone_names: tuple[str, ...]
    source_names: tuple[str, ...]
    disturbance_names: tuple[str, ...]
    lam: np.ndarray
    Phi: np.ndarray
    PhiTM: np.ndarray
    W: np.ndarray
    WD: np.ndarray
    Cs: np.ndarray
    Cd: np.ndarray
    S: np.ndarray
    rated: np.ndarray
    n_heat: int

    # -- sizes and slices -------------------------------------------------------------------------------
    @property
    def r(self) -> int:
        return self.lam.size

    @property
    def sizes(self) -> dict[str, int]:
        return {"z": self.r, "air": len(self.zone_names), "scale": len(self.source_names),
                "heat": len(self.disturbance_names), "bias": N_DRIFT}

    def slices(self) -> dict[str, slice]:
        out, k = {}, 0
        for name, n in self.sizes.items():
            out[name] = slice(k, k + n)
            k += n
        return out

    @property
    def n(self) -> int:
        return sum(self.sizes.values())

    def _check_u(self, u) -> np.ndarray:
        u = np.asarray(u, float)
        if u.shape != (self.W.shape[1],) or not np.all(np.isfinite(u)):
            raise ObserverError(f"observer inputs must be {self.W.shape[1]} finite values, got shape {u.shape}")
        return u

    # -- the model of one step ----------------------------------------------------------------------------
    def _step_coefficients(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Per mode, the decay ``a`` over a step of ``dt_s`` and the gain ``g0`` of an input held over it (r,)."""
        x = self.lam * dt_s
        a = np.where(x > 50.0, 0.0, np.exp(-np.minimum(x, 50.0)))
        g0 = np.where(x < 1e-8, dt_s, -np.expm1(-x) / np.where(x < 1e-8, 1.0, self.lam))
        return a, g0

    def _transition(self, u: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """F (n × n) and the known drive (r,) of one step of ``dt_s`` with inputs ``u`` held."""
        sl = self.slices()
        a, g0 = self._step_coefficients(dt_s)
        F = np.eye(self.n)
        F[sl["z"], sl["z"]] = np.diag(a)
        F[sl["z"], sl["air"]] = g0[:, None] * self.W[:, self.n_heat:]
        F[sl["z"], sl["scale"]] = g0[:, None] * (self.W[:, :self.n_heat] @ (u[:self.n_heat, None] * self.S))
        F[sl["z"], sl["heat"]] = g0[:, None] * self.WD
        return F, g0 * (self.W @ u)

    def _process_noise(self, dt_s: float) -> np.ndarray:
        s, sl = self.settings, self.slices()
        h = dt_s / 3600.0
        x = self.lam * dt_s
        g0 = np.where(x < 1e-8, dt_s, -np.expm1(-x) / np.where(x < 1e-8, 1.0, self.lam))
        G = g0[:, None] * self.W * (s.input_sigma * self.rated)
        Q = np.zeros((self.n, self.n))
        Q[sl["z"], sl["z"]] = G @ G.T
        k, m, c = sl["air"], len(self.zone_names), s.air_common  # the zones' walks share a common part
        Q[k, k] = (c * np.ones((m, m)) + (1.0 - c) * np.eye(m)) * s.air_rate_K**2 * h
        for name, rate in (("scale", s.scale_rate), ("heat", s.heat_rate_W), ("bias", s.bias_rate_um)):
            k = sl[name]
            Q[k, k] = np.eye(k.stop - k.start) * rate**2 * h
        return Q

    # -- the filter ---------------------------------------------------------------------------------------
    def initial(self, u0, time_s: float = 0.0) -> ObserverState:
        """The prior: steady state of inputs ``u0``, the disturbances at their prior spread.

        The steady states the disturbances cause are in the covariance, plus an uncertain load history
        (``settings.initial_load``).
        """
        s, sl = self.settings, self.slices()
        u0 = self._check_u(u0)
        x = np.zeros(self.n)
        x[sl["z"]] = (self.W @ u0) / self.lam
        D = np.zeros((self.n, self.n))
        for name, sigma in (("air", s.air_sigma_K), ("scale", s.scale_sigma), ("heat", s.heat_sigma_W),
                            ("bias", s.bias_sigma_um)):
            k = sl[name]
            D[k, k] = np.eye(k.stop - k.start) * sigma**2
        T = np.eye(self.n)  # disturbance states -> the steady state they cause
        T[sl["z"], sl["z"]] = 0.0
        T[sl["z"], sl["air"]] = self.W[:, self.n_heat:] / self.lam[:, None]
        T[sl["z"], sl["scale"]] = (self.W[:, :self.n_heat] @ (u0[:self.n_heat, None] * self.S)) / self.lam[:, None]
        T[sl["z"], sl["heat"]] = self.WD / self.lam[:, None]
        L = (self.W[:, :self.n_heat] * (s.initial_load * self.rated[:self.n_heat])) / self.lam[:, None]
        P = T @ D @ T.T
        P[sl["z"], sl["z"]] += L @ L.T
        return ObserverState(float(time_s), x, 0.5 * (P + P.T))

    def predict(self, state: ObserverState, u, dt_s: float) -> ObserverState:
        """Advance by ``dt_s`` [s] with inputs ``u`` (powers [W], air rises [K], in the ROM's order) held."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ObserverError(f"observer step must be positive, got {dt_s!r} s")
        u = self._check_u(u)
        F, drive = self._transition(u, dt_s)
        x = F @ state.x
        x[self.slices()["z"]] += drive
        with single_blas_thread():  # small dense products: a second BLAS thread only waits (36x slower measured)
            P = F @ state.P @ F.T + self._process_noise(dt_s)
        return ObserverState(state.time_s + dt_s, x, 0.5 * (P + P.T))

    def _update(self, state: ObserverState, H: np.ndarray, y: np.ndarray, R: np.ndarray) -> ObserverState:
        with single_blas_thread():
            S = H @ state.P @ H.T + R
            K = la.solve(S, H @ state.P, assume_a="pos").T
            x = state.x + K @ (y - H @ state.x)
            IKH = np.eye(self.n) - K @ H
            P = IKH @ state.P @ IKH.T + K @ R @ K.T  # Joseph form: stays symmetric positive semidefinite
            P = 0.5 * (P + P.T)
            x = project_bounds(x, P, *self._bounds())
        return ObserverState(state.time_s, x, P)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bounded coordinates of the state and their lower and upper bounds (``ObserverSettings``)."""
        sl = self.slices()
        idx, lo, hi = [], [], []
        for kind in BOUND_SETTINGS:
            k = sl[kind]
            a, b = self.settings.bounds(kind)
            idx.append(np.arange(k.start, k.stop))
            lo.append(np.full(k.stop - k.start, a))
            hi.append(np.full(k.stop - k.start, b))
        return np.concatenate(idx), np.concatenate(lo), np.concatenate(hi)

    def update_sensors(self, state: ObserverState, measured_degC: Sequence[float]) -> tuple[ObserverState, Innovation]:
        """Correct the estimate with the sensors (NaN: not measured this step) [°C]."""
        y = np.asarray(measured_degC, float)
        if y.shape != (len(self.sensor_names),):
            raise ObserverError(f"observer expects {len(self.sensor_names)} sensor values "
                                f"({', '.join(self.sensor_names)}), got shape {y.shape}")
        sl = self.slices()
        H = np.zeros((y.size, self.n))
        H[:, sl["z"]] = self.Cs
        pred = H @ state.x + self.reference_temperature_degC
        var = _output_variance(H, state.P) + self.settings.sensor_sigma_K**2
        res = y - pred
        norm = res / np.sqrt(var)
        use = np.isfinite(y)
        rejected = use & (np.abs(norm) > self.settings.gate_sigma)
        # the gate rejects outliers, not a common shift: when most sensors disagree, the model is what moved
        if rejected.sum() > use.sum() // 2:
            rejected[:] = False
        use &= ~rejected
        names = tuple(n for n, r in zip(self.sensor_names, rejected) if r)
        if not use.any():
            return state, Innovation(res, norm, names)
        R = np.eye(int(use.sum())) * self.settings.sensor_sigma_K**2
        new = self._update(state, H[use], y[use] - self.reference_temperature_degC, R)
        return new, Innovation(res, norm, names)

    def update_probe(self, state: ObserverState, drift_um: Sequence[float], sigma_um: float | None = None) -> ObserverState:
        """Correct the estimate with a measured drift dx, dy, dz [µm] (NaN: a direction not probed)."""
        d = np.asarray(drift_um, float)
        if d.shape != (N_DRIFT,):
            raise ObserverError(f"a probed drift has {N_DRIFT} values (dx, dy, dz), got shape {d.shape}")
        use = np.isfinite(d)
        if not use.any():
            return state
        sl = self.slices()
        H = self._drift_rows()
        sigma = self.settings.probe_sigma_um if sigma_um is None else float(sigma_um)
        k = self.settings.probe_widen_sigma
        if k > 0:
            # an offset the prior thought unlikely, shown by a probe, is taken: a direction whose innovation lies
            # beyond k standard deviations widens its bias variance by the excess (covariance matching)
            var = _output_variance(H, state.P) + sigma**2
            r2 = (d - H @ state.x) ** 2
            grow = np.where(use & (r2 > k**2 * var), r2 - var, 0.0)
            if np.any(grow > 0):
                P = state.P.copy()
                b = np.arange(sl["bias"].start, sl["bias"].stop)
                P[b, b] += grow
                state = ObserverState(state.time_s, state.x, P)
        return self._update(state, H[use], d[use], np.eye(int(use.sum())) * sigma**2)

    # -- reading the estimate -----------------------------------------------------------------------------
    def sensors_degC(self, state: ObserverState | np.ndarray) -> np.ndarray:
        """The sensors' temperatures of an estimate (or of a state vector, :meth:`predict_mean`) [°C]."""
        x = state.x if isinstance(state, ObserverState) else np.asarray(state, float)
        return self.Cs @ x[self.slices()["z"]] + self.reference_temperature_degC

    def predict_mean(self, x: np.ndarray, u, dt_s: float) -> np.ndarray:
        """The state vector ``x`` advanced by ``dt_s`` [s] with inputs ``u`` held, its disturbances as they stand.

        The mean of :meth:`predict` without the covariance: the model run open-loop.
        """
        u = self._check_u(u)
        x = np.asarray(x, float)
        sl = self.slices()
        a, g0 = self._step_coefficients(dt_s)  # _transition's rows of F, without building the n × n matrix
        h = self.n_heat
        heat = u[:h] * (1.0 + self.S @ x[sl["scale"]])
        out = x.copy()
        out[sl["z"]] = a * x[sl["z"]] + g0 * (self.W[:, :h] @ heat + self.W[:, h:] @ (u[h:] + x[sl["air"]])
                                              + self.WD @ x[sl["heat"]])
        return out

    def drift_um(self, state: ObserverState) -> np.ndarray:
        sl = self.slices()
        return self.Cd @ state.x[sl["z"]] + state.x[sl["bias"]]

    def drift_sigma_um(self, state: ObserverState) -> np.ndarray:
        """Standard deviation of the drift estimate [µm]."""
        return np.sqrt(_output_variance(self._drift_rows(), state.P))

    def _drift_rows(self) -> np.ndarray:
        """The drift dx, dy, dz as rows on the state: the model's drift outputs plus the bias only probes see."""
        sl = self.slices()
        H = np.zeros((N_DRIFT, self.n))
        H[:, sl["z"]] = self.Cd
        H[:, sl["bias"]] = np.eye(N_DRIFT)
        return H

    def reduced_state(self, state: ObserverState) -> np.ndarray:
        """The reduced model's coordinates ``x_r = Φ z`` [K]."""
        return self.Phi @ state.x[self.slices()["z"]]

    def corrected_inputs(self, state: ObserverState, u) -> np.ndarray:
        """The inputs as the estimate has them: each source's powers scaled by ``1 + scale``, each zone's air offset.

        What a model on the same inputs (the pose-aware model beside the daemon's observer) needs to follow the
        air and power corrections; the unknown heat per body is a state of this model's own shapes and stays here.
        """
        u = self._check_u(u)
        sl = self.slices()
        out = u.copy()
        out[:self.n_heat] += u[:self.n_heat] * (self.S @ state.x[sl["scale"]])
        out[self.n_heat:] += state.x[sl["air"]]
        return out

    def disturbances(self, state: ObserverState) -> dict[str, dict[str, float]]:
        """The estimated disturbances by kind and name (air [K], scale [-], heat [W], bias [µm])."""
        sl = self.slices()
        out = {"air_K": dict(zip(self.zone_names, state.x[sl["air"]])),
               "scale": dict(zip(self.source_names, state.x[sl["scale"]])),
               "heat_W": dict(zip(self.disturbance_names, state.x[sl["heat"]])),
               "bias_um": dict(zip(("dx", "dy", "dz"), state.x[sl["bias"]]))}
        return {k: {n: float(v) for n, v in d.items()} for k, d in out.items()}

    def forecast(self, state: ObserverState, U: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The mean run on: inputs ``U`` (steps × inputs), each held over one step of ``dt_s`` [s].

        The disturbances are held at their estimate. Returns sensors [°C] and drift [µm] at the end of each step.
        """
        U = np.asarray(U, float)
        if U.ndim != 2 or U.shape[1] != self.W.shape[1] or not np.all(np.isfinite(U)):
            raise ObserverError(f"forecast inputs must be finite, of shape (steps, {self.W.shape[1]}), got {U.shape}")
        sl = self.slices()
        a, g0 = self._step_coefficients(dt_s)
        air, scale = state.x[sl["air"]], state.x[sl["scale"]]
        const = g0 * (self.W[:, self.n_heat:] @ air + self.WD @ state.x[sl["heat"]])
        Wh = self.W[:, :self.n_heat] * (1.0 + self.S @ scale)[None, :]
        z = state.x[sl["z"]].copy()
        T = np.empty((len(U), len(self.sensor_names)))
        D = np.empty((len(U), N_DRIFT))
        bias = state.x[sl["bias"]]
        for k, u in enumerate(U):
            z = a * z + g0 * (Wh @ u[:self.n_heat] + self.W[:, self.n_heat:] @ u[self.n_heat:]) + const
            T[k] = self.Cs @ z
            D[k] = self.Cd @ z + bias
        return T + self.reference_temperature_degC, D


def build_observer(rom, machine, settings: ObserverSettings = ObserverSettings()) -> Observer:
    """The observer of a machine's reduced model (:func:`hybridcomp.rom.machine.reduce_model`).

    Parameters
    ----------
    rom : the reduced model; its uniform disturbance shapes (``rom.D``, one per body) become the unknown-heat
        states (none for a model reduced without them). The shapes that vary linearly over a body are not used:
        with one sensor or a few per body they let the filter explain one sensor's departure as heat (a column
        sensor drifting 2 K was absorbed as −274 W of gradient heat instead of being rejected), and the
        compensation benchmark's disturbances were tracked as well or better without them
    machine : the machine it was reduced from (heat sources for the scale states, rated powers)
    settings : noise levels
    """
    from hybridcomp.fem.loads import full_power_inputs

    layout = machine.layout()
    if tuple(rom.input_names) != layout.columns:
        raise ObserverError(f"the reduced model's inputs ({len(rom.input_names)}) are not machine "
                            f"{machine.name!r}'s ({len(layout.columns)}): reduce its model again")
    lam, Phi = rom._modes()
    try:
        outputs = rom.output_layout()
    except HybridcompError as exc:
        raise ObserverError(f"the observer needs the reduced model's sensors and drift: {exc}") from None
    if outputs.sensors != layout.sensors:
        raise ObserverError(f"the reduced model's sensors ({', '.join(outputs.sensors)}) are not machine "
                            f"{machine.name!r}'s ({', '.join(layout.sensors)}): reduce its model again")
    Cz = rom.C @ Phi
    W = Phi.T @ rom.input_matrix()
    keep = [j for j, n in enumerate(rom.disturbance_names) if ":" not in n]  # "<body>" uniform, "<body>:x" linear
    WD = Phi.T @ rom.D[:, keep] if rom.D is not None else np.zeros((rom.order, 0))
    n_heat = len(layout.heat_inputs)
    sources = tuple(name for name, _ in layout.source_inputs)
    S = np.zeros((n_heat, len(sources)))
    for j, (_, cols) in enumerate(layout.source_inputs):
        S[list(cols), j] = 1.0
    rated = np.abs(full_power_inputs(machine))
    rated[n_heat:] = 1.0  # 1 K of air
    return Observer(
        settings=settings, rom_id=rom.rom_id, reference_temperature_degC=float(layout.reference_temperature_degC),
        sensor_names=tuple(layout.sensors), zone_names=tuple(layout.zones), source_names=sources,
        disturbance_names=tuple(rom.disturbance_names[j] for j in keep), lam=lam, Phi=Phi, PhiTM=Phi.T @ rom.M,
        W=W, WD=WD,
        Cs=Cz[list(outputs.sensor_indices)], Cd=Cz[list(outputs.drift_indices)] * 1e6, S=S, rated=rated, n_heat=n_heat,
    )
