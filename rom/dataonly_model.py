"""The data-only regularised model of a machine without an FE model, as one JSON document.

The data-only diagnosis (``hybridcomp diagnose --data-only --probe-every-hours H``) fits per drift channel a ridge
regression over the temperatures, their first-order lags and the spindle's transfer functions, with the settings of
the coefficient filter (:mod:`hybridcomp.rom.coefficient_filter`) that updates it from probes. This module holds
that model (:class:`DataOnlyModel`), takes it out of a diagnosis (:func:`model_from_diagnosis`) and writes and reads
it (:func:`model_to_json`, :func:`model_from_json`); the monitor runs it online
(:mod:`hybridcomp.monitor.dataonly_strategy`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hybridcomp.rom.coefficient_filter import CoefficientSettings


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
