"""A compensation strategy for machines without an FE model: the data-only regularised model, updated by probes.

The data-only diagnosis (``diagnose --data-only``) fits per drift channel a ridge regression over the temperatures,
their first-order lags and the spindle's transfer functions (:mod:`hybridcomp.diagnose.regularised`). This module
runs that model online, one sample at a time, with its coefficients updated at every probe cycle by the coefficient
filter of :mod:`hybridcomp.rom.coefficient_filter` (prior: the training fit; random walks; more uncertainty while an
input is outside its training range, so the next probe counts more):

* :func:`model_from_diagnosis` takes the fitted model and the filter settings out of a diagnosis;
  :func:`model_to_json` / :func:`model_from_json` write and read it (one JSON document per machine);
* :func:`start` gives the state before the first sample; :func:`step` is pure: the state and one sample in, the
  new state, the offsets [µm] and their spread [µm] out. A probe in the sample updates the coefficients after the
  offsets of that sample are computed (each sample predicted from earlier probes only).

The regressors are rebuilt from the sample stream with the same first-order hold as
:func:`hybridcomp.diagnose.problem.first_order_lag` (exact for inputs linear between samples), so the online
prediction equals the diagnosis's on the same rows (tested). Only ``*_rpm`` activities are supported online.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hybridcomp.rom.coefficient_filter import CoefficientSettings, FilterState, filter_start, filter_step

PROBE_INDEX = {"dx_um": 0, "dy_um": 1, "dz_um": 2}  # a channel's place in a probe (dx, dy, dz)


@dataclass(frozen=True)
class ChannelModel:
    """One drift channel's regularised model: its family, standardisation, coefficients, prior and filter settings."""

    channel: str
    family: str
    signal: str | None  # the activity column (``spindle_rpm``) of an ``S<n>`` family, None for ``T+lagT``
    exponent: float
    mu: np.ndarray
    sd: np.ndarray
    coef: np.ndarray
    A: np.ndarray
    s2_um2: float
    z_lo: np.ndarray
    z_hi: np.ndarray
    settings: CoefficientSettings


@dataclass(frozen=True)
class DataOnlyModel:
    """The models of every channel and what the regressors are made of.

    The sensors in order (names as the monitor reads them, without the ``_degC`` suffix) and each activity's full
    scale.
    """

    sensors: tuple[str, ...]
    activity_max: dict
    channels: tuple[ChannelModel, ...]
    temp_lags_h: tuple[float, ...]  # the temperatures' lag time constants, in the families' column order
    source_lags_h: tuple[float, ...]  # the activities' lag time constants


@dataclass(frozen=True)
class StrategyState:
    """Between samples: the last sample's time and inputs, the lag states and every channel's filter."""

    t_s: float
    inputs: np.ndarray  # the sensors, then the activities' normalised powers a^n (one per exponent in use)
    lags: np.ndarray  # inputs × lag time constants: the lag of every input at every time constant
    filters: tuple[FilterState, ...]


def _family_parts(family: str) -> tuple[str | None, float]:
    """The activity and exponent of a family name (``S1.5(spindle_rpm)+T+lagT`` → (spindle_rpm, 1.5))."""
    if family == "T+lagT":
        return None, 1.0
    head = family.split("+", 1)[0]
    if not (head.startswith("S") and "(" in head and head.endswith(")")):
        raise ValueError(f"unknown family {family!r}: expected 'T+lagT' or 'S<n>(<signal>)+T+lagT'")
    n, sig = head[1:].split("(", 1)
    return sig[:-1], float(n)


def model_from_diagnosis(d, settings: Mapping[str, CoefficientSettings] | None = None) -> DataOnlyModel:
    """The online model of a data-only diagnosis's regularised families (``diagnose_data_only(regularised=True)``).

    ``settings``: the coefficient filter per channel (default: those the diagnosis chose with ``probe_every_h``;
    without them, an error names the missing option).
    """
    if not d.regularised:
        raise ValueError("the diagnosis has no regularised model: run it with regularised=True")
    if settings is None:
        if not d.coefficient_updating:
            raise ValueError("the diagnosis chose no coefficient filter: run it with probe_every_h (the probe cycle's "
                             "interval) or give the settings")
        settings = {c: u["settings"] for c, u in d.coefficient_updating.items()}
    spec = next(iter(d.regularised.values()))["inputs"]
    chans = []
    for c, r in d.regularised.items():
        sig, n = _family_parts(r["family"])
        if sig is not None and sig not in spec["activity_max"]:
            raise ValueError(f"{c}: the family {r['family']} is driven by {sig}, which the online strategy cannot "
                             "rebuild (only *_rpm activities)")
        m = r["model"]
        chans.append(ChannelModel(c, r["family"], sig, n, m.mu, m.sd, m.coef, m.A, m.s2_um2, m.z_lo, m.z_hi,
                                  settings[c]))
    sensors = tuple(s.removesuffix("_degC") for s in spec["temperatures"])
    return DataOnlyModel(sensors, dict(spec["activity_max"]), tuple(chans), tuple(spec["temp_lags_h"]),
                         tuple(spec["source_lags_h"]))


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


def model_to_json(model: DataOnlyModel) -> str:
    """The model as one JSON document (arrays as lists)."""
    def arr(x):
        return np.asarray(x, float).tolist()

    return json.dumps({"sensors": list(model.sensors), "activity_max": model.activity_max,
                       "temp_lags_h": list(model.temp_lags_h), "source_lags_h": list(model.source_lags_h), "channels": [
        {"channel": c.channel, "family": c.family, "mu": arr(c.mu), "sd": arr(c.sd), "coef": arr(c.coef),
         "A": arr(c.A), "s2_um2": c.s2_um2, "z_lo": arr(c.z_lo), "z_hi": arr(c.z_hi),
         "settings": {"every_h": c.settings.every_h, "probe_sd_um": c.settings.probe_sd_um,
                      "prior_scale": c.settings.prior_scale, "walk": c.settings.walk,
                      "range_walk": c.settings.range_walk, "offset_walk": c.settings.offset_walk,
                      "gain_walk_per_sqrt_h": c.settings.gain_walk_per_sqrt_h, "gain_sd": c.settings.gain_sd}}
        for c in model.channels]})


def model_from_json(text: str) -> DataOnlyModel:
    """The model written by :func:`model_to_json`."""
    d = json.loads(text)
    chans = []
    for c in d["channels"]:
        sig, n = _family_parts(c["family"])
        chans.append(ChannelModel(c["channel"], c["family"], sig, n, *(np.array(c[k]) for k in ("mu", "sd", "coef", "A")),
                                  float(c["s2_um2"]), np.array(c["z_lo"]), np.array(c["z_hi"]),
                                  CoefficientSettings(**c["settings"])))
    return DataOnlyModel(tuple(d["sensors"]), dict(d["activity_max"]), tuple(chans), tuple(d["temp_lags_h"]),
                         tuple(d["source_lags_h"]))
