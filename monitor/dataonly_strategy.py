"""A compensation strategy for machines without an FE model: the data-only regularised model, updated by probes.

The data-only diagnosis (``diagnose --data-only``) fits per drift channel a ridge regression over the temperatures,
their first-order lags and the spindle's transfer functions (:mod:`hybridcomp.diagnose.regularised`). This module
runs that model online, one sample at a time, with its coefficients updated at every probe cycle by the coefficient
filter of :mod:`hybridcomp.rom.coefficient_filter` (prior: the training fit; random walks; more uncertainty while an
input is outside its training range, so the next probe counts more):

* :func:`model_from_diagnosis` takes the fitted model and the filter settings out of a diagnosis;
  :func:`model_to_json` / :func:`model_from_json` write and read it (one JSON document per machine; they live in
  :mod:`hybridcomp.rom.dataonly_model`, which the diagnosis writes with, and are re-exported here);
* :func:`start` gives the state before the first sample; :func:`step` is pure: the state and one sample in, the
  new state, the offsets [µm] and their spread [µm] out. A probe in the sample updates the coefficients after the
  offsets of that sample are computed (each sample predicted from earlier probes only); :func:`predict` gives the
  offsets at the state's own sample (the first one's);
* :func:`state_to_dict` / :func:`state_from_dict`: the state bit-exact in JSON (the monitor persists it).

The regressors are rebuilt from the sample stream with the same first-order hold as
:func:`hybridcomp.diagnose.problem.first_order_lag` (exact for inputs linear between samples), so the online
prediction equals the diagnosis's on the same rows (tested). Only ``*_rpm`` activities are supported online.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hybridcomp.rom.coefficient_filter import FilterState, filter_start, filter_step
from hybridcomp.rom.dataonly_model import (  # noqa: F401 (the model's functions, re-exported)
    ChannelModel,
    DataOnlyModel,
    model_from_diagnosis,
    model_from_json,
    model_to_json,
)

PROBE_INDEX = {"dx_um": 0, "dy_um": 1, "dz_um": 2}  # a channel's place in a probe (dx, dy, dz)


@dataclass(frozen=True)
class StrategyState:
    """Between samples: the last sample's time and inputs, the lag states and every channel's filter."""

    t_s: float
    inputs: np.ndarray  # the sensors, then the activities' normalised powers a^n (one per exponent in use)
    lags: np.ndarray  # inputs × lag time constants: the lag of every input at every time constant
    filters: tuple[FilterState, ...]


def _taus_s(model: DataOnlyModel) -> np.ndarray:
    return np.array(sorted(set(model.temp_lags_h) | set(model.source_lags_h))) * 3600.0


def _inputs(model: DataOnlyModel, sensors_degC: Mapping[str, float], spindle: Mapping[str, float]) -> np.ndarray:
    """The current inputs: every sensor, then every (activity, exponent) in use."""
    try:
        T = [float(sensors_degC[n]) for n in model.sensors]
    except KeyError as exc:
        raise ValueError(f"the sample lacks the sensor {exc.args[0]!r} the data-only model needs") from None
    acts = []
    for sig, n in _activities(model):
        acts.append((abs(float(spindle[sig])) / model.activity_max[sig]) ** n)
    return np.array(T + acts)


def _activities(model: DataOnlyModel) -> list[tuple[str, float]]:
    return sorted({(c.signal, c.exponent) for c in model.channels if c.signal is not None})


def start(model: DataOnlyModel, t_s: float, sensors_degC: Mapping[str, float],
          spindle: Mapping[str, float]) -> StrategyState:
    """The state at the first sample: every lag steady at its input, every filter at its training fit."""
    u = _inputs(model, sensors_degC, spindle)
    lags = np.repeat(u[:, None], _taus_s(model).size, axis=1)
    filters = tuple(filter_start(c.coef, c.A, c.s2_um2, c.settings, t_s) for c in model.channels)
    return StrategyState(float(t_s), u, lags, filters)


def _regressors(model: DataOnlyModel, c: ChannelModel, u: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """The standardised regressors of a channel with the intercept, in the family's column order."""
    taus = list(_taus_s(model))
    nT = len(model.sensors)
    T = u[:nT]
    cols = []
    if c.signal is not None:
        j = nT + _activities(model).index((c.signal, c.exponent))
        cols += [lags[j, taus.index(h * 3600.0)] for h in model.source_lags_h]
    cols += list(T)
    for h in model.temp_lags_h:
        cols += list(lags[:nT, taus.index(h * 3600.0)])
    x = np.array(cols)
    return np.r_[1.0, (x - c.mu) / c.sd]


def step(model: DataOnlyModel, st: StrategyState, t_s: float, sensors_degC: Mapping[str, float],
         spindle: Mapping[str, float], probe_um: tuple | None = None) -> tuple[StrategyState, dict, dict]:
    """One sample: the new state, the offsets per channel [µm] and their spread [µm] (pure).

    ``spindle``: the activity columns by name (``{"spindle_rpm": 3000.0}``); ``probe_um``: a drift probed at this
    sample (dx, dy, dz; NaN for a direction not probed) or None. A channel's probe value is taken from its place
    in ``probe_um`` (:data:`PROBE_INDEX`; a channel not named dx_um/dy_um/dz_um takes the probe's entries in the
    order of the model's channels).
    """
    if not t_s > st.t_s:
        raise ValueError(f"sample time {t_s!r} s is not after the last one ({st.t_s!r} s)")
    u = _inputs(model, sensors_degC, spindle)
    dt = t_s - st.t_s
    taus = _taus_s(model)
    a = np.exp(-dt / taus)
    q = taus * (1.0 - a) / dt
    lags = a * st.lags + (q - a) * st.inputs[:, None] + (1.0 - q) * u[:, None]
    offsets, spreads, filters = {}, {}, []
    for i, (c, fs) in enumerate(zip(model.channels, st.filters)):
        z = _regressors(model, c, u, lags)
        y = None
        if probe_um is not None:
            k = PROBE_INDEX.get(c.channel, i)
            if k < len(probe_um) and math.isfinite(float(probe_um[k])):
                y = float(probe_um[k])
        fs, pred, sd = filter_step(fs, z, t_s, c.settings, c.s2_um2, c.z_lo, c.z_hi, y)
        filters.append(fs)
        offsets[c.channel], spreads[c.channel] = pred, sd
    return StrategyState(float(t_s), u, lags, tuple(filters)), offsets, spreads


def predict(model: DataOnlyModel, st: StrategyState) -> tuple[dict, dict]:
    """The offsets [µm] and their spread [µm] at the state's own sample, the state unchanged (the first sample's)."""
    offsets, spreads = {}, {}
    for c, fs in zip(model.channels, st.filters):
        _, offsets[c.channel], spreads[c.channel] = filter_step(fs, _regressors(model, c, st.inputs, st.lags), st.t_s,
                                                                c.settings, c.s2_um2, c.z_lo, c.z_hi)
    return offsets, spreads


def compatible(model: DataOnlyModel, st: StrategyState) -> bool:
    """Whether ``st`` is a state of ``model``'s shape (a persisted state of another model file is not)."""
    return (st.inputs.shape == (len(model.sensors) + len(_activities(model)),)
            and st.lags.shape == (st.inputs.size, _taus_s(model).size) and len(st.filters) == len(model.channels)
            and all(f.theta.shape == c.coef.shape for f, c in zip(st.filters, model.channels)))


def _b64(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a, dtype="<f8")
    return {"shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode("ascii")}


def _unb64(d: Mapping) -> np.ndarray:
    return np.frombuffer(base64.b64decode(d["data"]), dtype="<f8").reshape(d["shape"]).copy()


def state_to_dict(st: StrategyState) -> dict:
    """The state as JSON-able values, bit-exact (arrays as base64 of little-endian float64, times as repr floats)."""
    return {"t_s": st.t_s, "inputs": _b64(st.inputs), "lags": _b64(st.lags), "filters": [
        {"theta": _b64(f.theta), "P": _b64(f.P), "t_probe_s": f.t_probe_s, "t_last_s": f.t_last_s,
         "excess": _b64(f.excess), "theta0": _b64(f.theta0)} for f in st.filters]}


def state_from_dict(d: Mapping) -> StrategyState:
    """The state written by :func:`state_to_dict`."""
    filters = tuple(FilterState(_unb64(f["theta"]), _unb64(f["P"]), float(f["t_probe_s"]), float(f["t_last_s"]),
                                _unb64(f["excess"]), _unb64(f["theta0"])) for f in d["filters"])
    return StrategyState(float(d["t_s"]), _unb64(d["inputs"]), _unb64(d["lags"]), filters)
