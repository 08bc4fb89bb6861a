"""Every decision the monitoring daemon makes, as pure functions.

The daemon (:mod:`hybridcomp.monitor.daemon`) is a thin shell that feeds
these functions and acts on what they return; each is tested on its own
(``tests/test_monitor_decisions.py``).

* :func:`limit_offsets` — clamp the compensation offsets and limit their change per cycle;
* :func:`blend_offsets` — bumpless transfer when the active CD set changes;
* :func:`check_time` — drop samples whose time stamp is repeated, goes backwards or leaps implausibly; accept a
  confirmed gap, resynchronise to a confirmed new time line of the control's clock;
* :func:`check_sensor` — NaN, frozen and spiking sensors: hold the last good value for a
  bounded time, then degrade (the structure model's estimate stands in), recover when the
  readings are plausible again;
* :func:`temperature_deviation` — the largest |T_actual − T_reference| over common sensors (the seeds' test,
  reported beside the decision);
* :func:`compensation_error_um` and :func:`decide` — keep, switch to a stored CD set, regenerate, or warn, on
  the predicted compensation error in µm (:class:`Validity`);
* :func:`model_drift` — does the structure model still follow the measured sensors;
* :func:`backoff_delay` — the reconnect schedule for a dropped data source.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from hybridcomp.frozen import evolve
from hybridcomp.models.toml import nonnegative_number

# --------------------------------------------------------------------------- compensation offsets


def limit_offsets(
    target_um: Mapping[str, float],
    previous_um: Mapping[str, float],
    max_abs_um: float,
    max_step_um: float,
) -> tuple[dict[str, float], bool, bool]:
    """Clamp offsets to ``±max_abs_um`` and move at most ``max_step_um`` from the previous ones.

    Parameters
    ----------
    target_um : offsets the active CDs ask for, per direction (``dx_um`` ...) [µm]
    previous_um : offsets written in the previous cycle [µm] (a missing direction counts as 0)
    max_abs_um : largest offset magnitude allowed [µm]
    max_step_um : largest change per compensation cycle [µm]

    Returns
    -------
    the offsets to write [µm], whether any was clamped, whether any was rate limited
    """
    if not (max_abs_um >= 0 and max_step_um >= 0):
        raise ValueError(f"max_abs_um and max_step_um must not be negative, got {max_abs_um}, {max_step_um}")
    out: dict[str, float] = {}
    clamped = limited = False
    for k, v in target_um.items():
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"offset {k} is not finite: {v}")
        c = min(max(v, -max_abs_um), max_abs_um)
        clamped |= c != v
        p = float(previous_um.get(k, 0.0))
        s = min(max(c, p - max_step_um), p + max_step_um)
        limited |= s != c
        out[k] = s
    return out, clamped, limited


def complementary_offsets(
    cd_um: Mapping[str, float], model_um: Mapping[str, float], low_um: Mapping[str, float] | None, dt_s: float,
    tau_s: float,
) -> tuple[dict[str, float], dict[str, float]]:
    """The CD tables' prediction for the slow part, the structure model's for the fast part (a complementary filter).

    ``offsets = model + LP_τ(CD − model)`` = ``LP_τ(CD) + HP_τ(model)``: what changes within ``tau_s`` (a spindle
    start, a machining cycle; heat the sensors see late or not at all) comes from the structure model, which is
    driven by the loads themselves; what is slower comes from the CDs on the measured sensors, which carry the real
    machine's state and none of the model's bias.  The residual is the model's error high-passed plus the CDs'
    error low-passed.

    Parameters
    ----------
    cd_um : the active set's prediction now [µm]
    model_um : the corrected structure model's drift now [µm]
    low_um : the low-passed difference CD − model of the previous cycle (None: start from this cycle's, so that
        the offsets are the CDs'; zeros: start from the model) [µm]
    dt_s : machine time since the previous cycle [s]
    tau_s : the crossover time constant [s] (0: the CDs alone)

    Returns
    -------
    the offsets [µm] and the low-passed difference [µm]
    """
    if not (dt_s >= 0 and tau_s >= 0):
        raise ValueError(f"dt_s and tau_s must not be negative, got {dt_s}, {tau_s}")
    if tau_s == 0:
        return {k: float(v) for k, v in cd_um.items()}, {k: float(v) - float(model_um[k]) for k, v in cd_um.items()}
    a = math.exp(-dt_s / tau_s)
    low = {}
    for k, v in cd_um.items():
        x = float(v) - float(model_um[k])
        low[k] = x if low_um is None or k not in low_um or not math.isfinite(low_um[k]) else a * low_um[k] + (1 - a) * x
    return {k: float(model_um[k]) + low[k] for k in cd_um}, low


def blend_offsets(
    target_um: Mapping[str, float], blend_um: Mapping[str, float], dt_s: float, tau_s: float
) -> tuple[dict[str, float], dict[str, float]]:
    """Bumpless transfer after a change of the active CD set.

    At the change the caller sets ``blend_um`` = offsets written before − the new set's prediction, so the
    offsets continue where they were; the difference then decays as ``exp(−Δt / tau_s)``.

    Parameters
    ----------
    target_um : the active set's prediction now [µm]
    blend_um : the remaining difference from the previous cycle [µm]
    dt_s : machine time since the previous cycle [s]
    tau_s : decay time [s] (0: no blending)

    Returns
    -------
    the blended target [µm] and the decayed difference [µm]
    """
    if not (dt_s >= 0 and tau_s >= 0):
        raise ValueError(f"dt_s and tau_s must not be negative, got {dt_s}, {tau_s}")
    f = 0.0 if tau_s == 0 else math.exp(-dt_s / tau_s)
    left = {k: float(blend_um.get(k, 0.0)) * f for k in target_um}
    return {k: float(v) + left[k] for k, v in target_um.items()}, left


# --------------------------------------------------------------------------- time stamps


WALL_JITTER_S = 2.0  # wall time a sample may arrive late or early in a burst [s]
MAX_ABS_TIME_S = 1e10  # a time stamp beyond ±317 years is invalid (Unix time in seconds is 1.8e9), even the first


@dataclass(frozen=True)
class TimeRules:
    """Plausibility of the machine's time stamps.

    Attributes
    ----------
    max_step_s : a sample farther ahead of the last one than this is suspect (a corrupt stamp, or the control's
        clock was set) until ``confirm_samples`` samples continue from it [s]
    confirm_samples : consecutive samples, each within ``max_step_s`` of the one before, that confirm a new time
        line (forward or backward) [-]
    """

    max_step_s: float = 600.0
    confirm_samples: int = 5

    def __post_init__(self):
        if not (math.isfinite(self.max_step_s) and self.max_step_s > 0):
            raise ValueError(f"max_step_s must be a positive number of seconds, got {self.max_step_s!r}")
        if not (isinstance(self.confirm_samples, int) and 2 <= self.confirm_samples <= 1000):
            raise ValueError(f"confirm_samples must be an integer in 2..1000, got {self.confirm_samples!r}")


@dataclass(frozen=True)
class TimeCheck:
    """What :func:`check_time` made of a time stamp.

    Attributes
    ----------
    verdict : ``"ok"``; ``"gap"`` (a confirmed jump ahead that the wall clock, or a source without one, backs:
        the data stopped, the machine time is kept); ``"resync"`` (a confirmed new time line the wall clock
        contradicts, or one that went backwards: the control's clock was set; machine time continues from the
        last sample and ``offset_s`` changes); or the sample is dropped: ``"repeated"``, ``"backwards"``,
        ``"jump"`` (suspect, not yet confirmed), ``"invalid"`` (NaN/inf)
    time_s : the sample's machine time in the monitor's time line (``source time + offset_s``) [s], NaN if dropped
    offset_s : monitor time − source time from now on [s]
    candidates : source times of the suspect samples so far [s]
    """

    verdict: str
    time_s: float
    offset_s: float
    candidates: tuple[float, ...] = ()

    @property
    def accepted(self) -> bool:
        return self.verdict in ("ok", "gap", "resync")


def check_time(
    last_time_s: float | None,
    source_time_s: float,
    offset_s: float,
    candidates: Sequence[float],
    rules: TimeRules,
    wall_elapsed_s: float | None = None,
    time_scale: float | None = None,
) -> TimeCheck:
    """Check a time stamp against the last accepted one, a plausible step and the source's clock.

    A single corrupt stamp (far in the future, or 1e308) is dropped, and the samples after it are accepted as
    before; compensation never stops because one stamp was wrong. A stamp that leaves the time line is suspect:
    when ``rules.confirm_samples`` consecutive samples continue from it (each within ``max_step_s`` of the one
    before), the new time line is real. Ahead of the last sample it is a gap in the data (the machine time is
    kept) if the wall clock has moved as far — ``(wall_elapsed_s + WALL_JITTER_S) × time_scale`` at least half the
    jump — or if the source has no clock to ask (``time_scale`` None: a replay as fast as possible); otherwise, and
    always when it
    goes backwards, the control's clock was set, and the monitor's time continues from the last sample with the
    new line's step (``offset_s`` changes).

    Parameters
    ----------
    last_time_s : machine time of the last accepted sample in the monitor's time line [s] (None: first sample)
    source_time_s : the sample's time stamp as the source gives it [s]
    offset_s : monitor time − source time so far [s]
    candidates : source times of the suspect samples before this one [s]
    rules : plausible step and confirmation
    wall_elapsed_s : wall time since the last accepted sample [s] (None: unknown)
    time_scale : machine seconds per wall second of the source (1 for a live machine; None: no clock)
    """
    if not (math.isfinite(source_time_s) and abs(source_time_s) <= MAX_ABS_TIME_S):
        return TimeCheck("invalid", math.nan, offset_s, tuple(candidates))
    t = source_time_s + offset_s
    if last_time_s is None:
        return TimeCheck("ok", t, offset_s)
    dt = t - last_time_s
    if 0 < dt <= rules.max_step_s:
        return TimeCheck("ok", t, offset_s)
    if dt == 0:
        return TimeCheck("repeated", math.nan, offset_s, tuple(candidates))
    # the wall clock backs a jump ahead if it moved at least half as far; WALL_JITTER_S absorbs samples that arrive in
    # a burst after a pause of the reading loop (on a live machine it is a few seconds against a jump of minutes)
    if (dt > 0 and time_scale is not None and wall_elapsed_s is not None
            and (wall_elapsed_s + WALL_JITTER_S) * time_scale >= 0.5 * dt):
        return TimeCheck("gap", t, offset_s)  # the wall clock has moved as far: the data stopped for a while
    step = source_time_s - candidates[-1] if candidates else math.nan
    cand = (*candidates, source_time_s) if 0 < step <= rules.max_step_s else (source_time_s,)
    if len(cand) < rules.confirm_samples:
        return TimeCheck("jump" if dt > 0 else "backwards", math.nan, offset_s, cand)
    if dt > 0 and time_scale is None:
        return TimeCheck("gap", t, offset_s)  # no clock to ask: a confirmed jump ahead is a gap in the data
    new_step = min(max(cand[-1] - cand[-2], 1e-3), rules.max_step_s)
    new_offset = last_time_s + new_step - source_time_s
    return TimeCheck("resync", source_time_s + new_offset, new_offset)


# --------------------------------------------------------------------------- sensors


@dataclass(frozen=True)
class SensorRules:
    """Plausibility rules for one temperature sensor.

    Attributes
    ----------
    hold_s : how long a bad reading is replaced by the last good value before the sensor degrades [s]
    frozen_s : a reading that has not changed at all for this long is frozen [s]
    frozen_model_K : ... and so is one that has not changed at all while the structure model predicts the sensor's
        temperature to move by this much (a stuck sensor while the machine heats or cools; 0: off) [K]
    spike_K : a jump larger than this against the last good value is a spike [K] ...
    spike_rate_K_s : ... plus this rate times the time since the last good value [K/s]
    min_degC, max_degC : readings outside this range are implausible (open or shorted sensor) [°C]
    """

    hold_s: float = 60.0
    frozen_s: float = 1800.0
    frozen_model_K: float = 0.5
    spike_K: float = 2.0
    spike_rate_K_s: float = 0.01
    min_degC: float = -10.0
    max_degC: float = 80.0

    def __post_init__(self):
        for name in ("hold_s", "frozen_s", "frozen_model_K", "spike_K", "spike_rate_K_s"):
            v = getattr(self, name)
            if not nonnegative_number(v):
                raise ValueError(f"sensor rule {name} must be a non-negative number, got {v!r}")
        if not self.min_degC < self.max_degC:
            raise ValueError(f"sensor rule min_degC {self.min_degC!r} must be below max_degC {self.max_degC!r}")


@dataclass(frozen=True)
class SensorState:
    """What the daemon remembers about one sensor between samples.

    Attributes
    ----------
    status : ``"ok"``, ``"holding"`` (a bad reading replaced by the last good value) or ``"degraded"``
    value_degC : the value in use [°C] (the last good one while holding), NaN before the first
    good_time_s : time of the last good reading [s]
    bad_since_s : start of the current run of bad readings [s], NaN when none
    reason : why the last reading was bad (``"nan"``, ``"spike"``, ``"frozen"``), empty when good
    raw_degC : the last raw reading [°C] (for the frozen check)
    raw_since_s : since when the raw reading has not changed [s]
    model_moved_K : how far the structure model's prediction of this sensor has moved while the raw reading stood
        still (the sum of its prediction steps since ``raw_since_s``) [K]
    """

    status: str = "ok"
    value_degC: float = math.nan
    good_time_s: float = math.nan
    bad_since_s: float = math.nan
    reason: str = ""
    raw_degC: float = math.nan
    raw_since_s: float = math.nan
    model_moved_K: float = 0.0

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in self.__dict__.items()}

    @staticmethod
    def from_dict(d: Mapping) -> SensorState:
        return SensorState(**{k: (math.nan if v is None else v) for k, v in d.items()})


@dataclass(frozen=True)
class SensorVerdict:
    """Result of one sensor check.

    Attributes
    ----------
    state : the sensor's new state
    value_degC : the value to use now [°C] (NaN while degraded: use the structure model's estimate)
    event : ``None`` or the transition to report (``"holding"``, ``"degraded"``, ``"recovered"``)
    """

    state: SensorState
    value_degC: float
    event: str | None = None


def check_sensor(
    state: SensorState, time_s: float, raw_degC: float, rules: SensorRules, reference_degC: float = math.nan
) -> SensorVerdict:
    """Check one reading of a temperature sensor and decide which value to use.

    A reading is bad when it is NaN, outside ``[min_degC, max_degC]``, jumps
    against the last good value by more than ``spike_K + spike_rate_K_s · (time
    since it)`` (a spike), or has not changed at all for ``frozen_s`` or while the
    structure model moved it by ``frozen_model_K`` (a frozen sensor or a dead bus;
    the caller accumulates ``state.model_moved_K``, see :func:`model_moved`). A
    bad reading is replaced by the last good value for up to ``hold_s``; after
    that the sensor is ``"degraded"`` and the value is NaN (the caller
    substitutes the structure model's estimate, see :func:`substitute`). A good
    reading ends holding at once. A degraded sensor recovers with the first
    reading that is plausible: in range, not frozen (a frozen one: moving again),
    and within ``spike_K`` of ``reference_degC`` (the stand-in value) when the
    caller has one.

    Parameters
    ----------
    state : the sensor's state after the previous reading
    time_s : time of this reading [s]
    raw_degC : the reading [°C] (NaN for a missing value)
    rules : thresholds
    reference_degC : the value the caller uses for a degraded sensor [°C] (NaN: none)
    """
    # frozen bookkeeping (exactly repeated raw values)
    if math.isfinite(raw_degC) and raw_degC == state.raw_degC:
        raw_since = state.raw_since_s
    else:
        raw_since = time_s
    st = evolve(state, raw_degC=raw_degC if math.isfinite(raw_degC) else math.nan, raw_since_s=raw_since,
                model_moved_K=state.model_moved_K if raw_since == state.raw_since_s else 0.0)

    reason = ""
    if not math.isfinite(raw_degC):
        reason = "nan"
    elif not rules.min_degC <= raw_degC <= rules.max_degC:
        reason = "range"
    elif st.status == "degraded":
        if state.reason == "frozen" and raw_since == state.raw_since_s:
            reason = "frozen"  # a frozen sensor recovers only when its reading moves again
        elif math.isfinite(reference_degC) and abs(raw_degC - reference_degC) > rules.spike_K:
            reason = "spike"
    elif math.isfinite(st.value_degC):
        allowed = rules.spike_K + rules.spike_rate_K_s * max(0.0, time_s - st.good_time_s)
        if abs(raw_degC - st.value_degC) > allowed:
            reason = "spike"
    if not reason and math.isfinite(raw_since) and (time_s - raw_since >= rules.frozen_s > 0
                                                    or abs(st.model_moved_K) >= rules.frozen_model_K > 0):
        reason = "frozen"

    if not reason:
        event = "recovered" if state.status == "degraded" else None
        new = evolve(st, status="ok", value_degC=float(raw_degC), good_time_s=time_s, bad_since_s=math.nan, reason="")
        return SensorVerdict(new, float(raw_degC), event)

    if st.status == "degraded":
        return SensorVerdict(evolve(st, reason=reason), math.nan, None)
    bad_since = st.bad_since_s if math.isfinite(st.bad_since_s) else time_s
    if reason == "frozen":  # the value has been stuck since raw_since: count the hold from there
        bad_since = min(bad_since, raw_since + rules.frozen_s)
    if not math.isfinite(st.value_degC) or time_s - bad_since > rules.hold_s:
        new = evolve(st, status="degraded", bad_since_s=bad_since, reason=reason)
        return SensorVerdict(new, math.nan, "degraded")
    event = "holding" if st.status == "ok" else None
    new = evolve(st, status="holding", bad_since_s=bad_since, reason=reason)
    return SensorVerdict(new, st.value_degC, event)


def model_moved(state: SensorState, step_start_s: float, predicted_step_K: float) -> SensorState:
    """Accumulate how far the structure model moves a sensor while its raw reading stands still.

    Adds one step's predicted change (the prediction minus the corrected state before it) while the raw reading
    has not changed since before the step began; otherwise starts again from 0.
    """
    if stood_still(state, step_start_s) and math.isfinite(predicted_step_K):
        return evolve(state, model_moved_K=state.model_moved_K + predicted_step_K)
    return evolve(state, model_moved_K=0.0)


def model_moved_since(state: SensorState, step_start_s: float, moved_K: float) -> SensorState:
    """Set how far the structure model, run open-loop, has moved a sensor since its raw reading last changed.

    ``moved_K``: the move from the start of the first step that began after the reading last changed to the end
    of this one; it counts while the raw reading has not changed since before this step began, otherwise 0.
    """
    if stood_still(state, step_start_s) and math.isfinite(moved_K):
        return evolve(state, model_moved_K=float(moved_K))
    return evolve(state, model_moved_K=0.0)


def stood_still(state: SensorState, step_start_s: float) -> bool:
    """The sensor's raw reading has not changed since before the step that begins at ``step_start_s``."""
    return math.isfinite(state.raw_since_s) and state.raw_since_s <= step_start_s


def step_end_values(time_s: np.ndarray, values_degC: np.ndarray) -> np.ndarray:
    """The sensors at the end of a model step from their readings over it [°C] (NaN: no reading).

    Per sensor, a straight line through its finite readings, evaluated at its last reading; the mean where there
    are fewer than three or they do not spread in time. The observer compares the model's sensors at the step's
    end: the plain mean lags them by half a step, and near a source that heats within minutes that lag is read
    as a disturbance (drift estimate on the demo day after a diagnosis: 0.34 µm RMS with the mean, 0.21 µm with
    the line). The line keeps the mean's noise reduction (its end value has 4/n of one reading's variance).

    Parameters
    ----------
    time_s : reading times (n,) [s]
    values_degC : readings (n × sensors), NaN where a sensor was not measured [°C]
    """
    t = np.asarray(time_s, float)
    Y = np.asarray(values_degC, float).reshape(t.size, -1)
    out = np.full(Y.shape[1], math.nan)
    for j in range(Y.shape[1]):
        ok = np.isfinite(Y[:, j])
        if not ok.any():
            continue
        tj, yj = t[ok], Y[ok, j]
        out[j] = yj.mean()
        if tj.size >= 3:
            dt = tj - tj.mean()
            sxx = float(dt @ dt)
            if sxx > 0.0:
                out[j] += float(dt @ (yj - out[j])) / sxx * dt[-1]
    return out


def substitute(model_degC: float, bias_K: float) -> float:
    """Stand-in value of a degraded sensor: the structure model's estimate plus the last known bias [°C].

    ``bias_K`` is measured minus model at the last time the sensor was good [K]
    (0 when unknown); the model's estimate is NaN when there is none.
    """
    return model_degC + (bias_K if math.isfinite(bias_K) else 0.0)


# --------------------------------------------------------------------------- monitoring decisions


def temperature_deviation(actual_degC: Mapping[str, float], reference_degC: Mapping[str, float]) -> tuple[float, str | None]:
    """Largest |T_actual − T_reference| over the sensors both name [K], and which sensor.

    NaN entries are skipped; no common finite sensor gives ``(inf, None)`` (no
    evidence that the set fits).
    """
    best, name = -1.0, None
    for k, r in reference_degC.items():
        a = actual_degC.get(k)
        if a is None or not (math.isfinite(a) and math.isfinite(r)):
            continue
        d = abs(a - r)
        if d > best:
            best, name = d, k
    return (best, name) if name is not None else (math.inf, None)


@dataclass(frozen=True)
class Validity:
    """When the active CD set is kept, replaced or regenerated: its predicted compensation error [µm].

    Attributes
    ----------
    keep_um : keep while the set's error against the structure model's drift over the last interval stays
        at most this [µm]
    forecast_um : ... and over the forecasts (the current load continued, a cool-down) at most this [µm]
    hard_um : above this over the last interval, act even within the dwell time [µm]
    dwell_s : after an activation, keep a set at least this long unless ``hard_um`` is exceeded [s]
    forecast_h : forecast horizon [h]
    bump_um : a generated set whose own fit differs from the offsets being written by at most this is made
        to continue them exactly; a stored set may be switched to only within this of them [µm]
    max_candidates : stored sets evaluated per decision (best by signature, then ΔT)
    reject_um : a set whose predicted error over the last interval exceeds this is known to be wrong: while it is
        active and no stored set fits, the monitor fails safe (it never applies it: the offsets are held and ramp at
        the rate limit to the corrected structure model's drift, or to zero while that model is flagged) [µm]; at
        least ``hard_um``
    """

    keep_um: float = 1.5
    forecast_um: float = 3.0
    hard_um: float = 3.0
    dwell_s: float = 3600.0
    forecast_h: float = 3.0
    bump_um: float = 1.0
    max_candidates: int = 8
    reject_um: float = 50.0

    def __post_init__(self):
        for name in ("keep_um", "forecast_um", "hard_um", "forecast_h", "reject_um"):
            v = getattr(self, name)
            if not nonnegative_number(v, strict=True):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        for name in ("dwell_s", "bump_um"):
            v = getattr(self, name)
            if not nonnegative_number(v):
                raise ValueError(f"{name} must be a number ≥ 0, got {v!r}")
        if int(self.max_candidates) != self.max_candidates or self.max_candidates < 0:
            raise ValueError(f"max_candidates must be a whole number ≥ 0, got {self.max_candidates!r}")
        object.__setattr__(self, "max_candidates", int(self.max_candidates))
        if self.reject_um < self.hard_um:
            raise ValueError(f"reject_um must be at least hard_um ({self.hard_um:g}), got {self.reject_um!r}")


@dataclass(frozen=True)
class SetError:
    """A CD set's predicted compensation error: max over directions and samples of |CD(T) − drift| [µm].

    Attributes
    ----------
    interval_um : over the last monitoring interval (the CDs on the measured sensors against the corrected
        structure model's drift)
    forecast_um : over the forecasts (the CDs on the forecast sensors against the forecast drift)
    """

    interval_um: float
    forecast_um: float

    def as_dict(self) -> dict:
        return {"interval_um": self.interval_um, "forecast_um": self.forecast_um}


def compensation_error_um(predicted_um, reference_um) -> float:
    """Max |predicted − reference| over all finite entries [µm] (inf when there is none: no evidence)."""
    d = np.abs(np.asarray(predicted_um, float) - np.asarray(reference_um, float))
    d = d[np.isfinite(d)]
    return float(d.max()) if d.size else math.inf


@dataclass(frozen=True)
class Candidate:
    """A stored CD set the database offers, with its predicted error and its jump.

    Attributes
    ----------
    ids : CD id per direction
    load_case : its training load case
    error : its predicted error (:class:`SetError`)
    jump_um : largest |its prediction − the offsets being written| now [µm]
    delta_T_K : the seeds' test, |T_reference − T_actual| [K]
    """

    ids: Mapping[str, int]
    load_case: str
    error: SetError
    jump_um: float
    delta_T_K: float = math.nan


@dataclass(frozen=True)
class Decision:
    """What the monitoring loop does after one interval.

    Attributes
    ----------
    action : ``"keep"``, ``"switch"``, ``"regenerate"`` or ``"warn"``
    reason : one sentence with the numbers
    error : the active set's predicted error (None without an active set)
    target : the set to switch to (``"switch"``), else None
    """

    action: str
    reason: str
    error: SetError | None
    target: Candidate | None = None


def _fits(e: SetError, v: Validity) -> bool:
    return e.interval_um <= v.keep_um and e.forecast_um <= v.forecast_um


def decide(
    active_ids: Mapping[str, int] | None,
    error: SetError | None,
    since_activation_s: float,
    validity: Validity,
    candidates: Sequence[Candidate],
    regeneration_enabled: bool,
    regeneration_running: bool,
    not_enabled_because: str = "regeneration is disabled",
) -> Decision:
    """Keep the active CD set, switch to a stored one, regenerate, or warn, on the predicted error in µm.

    Parameters
    ----------
    active_ids : ids of the active set per direction, None without one
    error : the active set's predicted error (None without an active set)
    since_activation_s : machine time since the active set was activated [s] (inf: unknown)
    validity : thresholds, dwell time, jump limit
    candidates : stored sets with their errors and jumps (any order)
    regeneration_enabled : whether the monitor may generate a new set
    regeneration_running : whether a generation job is already under way
    not_enabled_because : why the monitor may not generate (for the reason of a warning)
    """
    active = dict(active_ids) if active_ids else None
    if active is not None and error is not None:
        said = (f"predicted error {error.interval_um:.2f} µm over the interval, {error.forecast_um:.2f} µm over the "
                f"forecasts")
        if _fits(error, validity):
            return Decision("keep", f"{said}: within {validity.keep_um:g} / {validity.forecast_um:g} µm", error)
        if since_activation_s < validity.dwell_s and error.interval_um <= validity.hard_um:
            return Decision("keep", f"{said}, above {validity.keep_um:g} / {validity.forecast_um:g} µm, but the set "
                            f"was activated {since_activation_s / 60:.0f} min ago (dwell {validity.dwell_s / 60:g} min) "
                            f"and stays within {validity.hard_um:g} µm", error)
        what = f"{said}: above {validity.keep_um:g} / {validity.forecast_um:g} µm"
    else:
        what = "no active CD set"
    fitting = [c for c in candidates if dict(c.ids) != active and _fits(c.error, validity)
               and c.jump_um <= validity.bump_um]
    if fitting:
        c = min(fitting, key=lambda c: (max(c.error.interval_um / validity.keep_um,
                                            c.error.forecast_um / validity.forecast_um), c.jump_um))
        return Decision("switch", f"{what}; stored set {c.load_case!r} fits ({c.error.interval_um:.2f} / "
                        f"{c.error.forecast_um:.2f} µm, jump {c.jump_um:.2f} µm)", error, c)
    if regeneration_running:
        return Decision("warn", f"{what}; no stored set fits, a generation job is already running", error)
    if regeneration_enabled:
        return Decision("regenerate", f"{what}; no stored set fits: generating one", error)
    return Decision("warn", f"{what}; no stored set fits and {not_enabled_because}", error)


def model_drift(model_degC: Mapping[str, float], measured_degC: Mapping[str, float],
                threshold_K: float) -> tuple[bool, float, str | None]:
    """Whether the structure model has drifted from the measured sensors.

    Returns
    -------
    drifted (largest |model − measured| above ``threshold_K``), that largest difference [K], the sensor
    """
    d, s = temperature_deviation(model_degC, measured_degC)
    if s is None:
        return False, math.nan, None
    return d > threshold_K, d, s


# --------------------------------------------------------------------------- reconnecting


@dataclass(frozen=True)
class Backoff:
    """Reconnect schedule: ``initial_s · factor^attempt`` capped at ``max_s``, with ± ``jitter`` (fraction)."""

    initial_s: float = 0.5
    factor: float = 2.0
    max_s: float = 30.0
    jitter: float = 0.1

    def __post_init__(self):
        if not (self.initial_s > 0 and self.factor >= 1 and self.max_s >= self.initial_s and 0 <= self.jitter < 1):
            raise ValueError(
                f"backoff needs initial_s > 0, factor >= 1, max_s >= initial_s, 0 <= jitter < 1; got {self}"
            )


def backoff_delay(attempt: int, backoff: Backoff, u: float = 0.5) -> float:
    """Delay before reconnect attempt ``attempt`` (0 for the first retry) [s].

    ``u`` in [0, 1] is the random draw for the jitter (0.5: none), injected so
    that the schedule is reproducible.
    """
    if attempt < 0:
        raise ValueError(f"attempt must be >= 0, got {attempt}")
    base = min(backoff.max_s, backoff.initial_s * backoff.factor ** min(attempt, 1000))
    return base * (1.0 + backoff.jitter * (2.0 * u - 1.0))
