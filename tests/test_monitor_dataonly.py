"""The monitor's strategy ``dataonly``: the data-only model, stepped on every sample and updated by the probes.

A hand-made data-only model (two channels, a spindle transfer function and temperature lags) on 40 min of the
job-shop day at 0.1 Hz: the offsets a replay writes are the pure step function's, row by row, computed here from the
readings alone; the rate limit acts on them as on any strategy's; a probe moves the coefficients (the offsets up to
it unchanged, after it changed); a restarted daemon continues the model's state exactly; the configuration refuses
a missing, unreadable or unusable model file.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hybridcomp.monitor import dataonly_strategy as D
from hybridcomp.monitor import decisions
from hybridcomp.monitor import transitions as T
from hybridcomp.monitor.config import ConfigError, parse_config, read_dataonly_model
from hybridcomp.monitor.sources import Reading
from hybridcomp.monitor.state import MonitorState
from hybridcomp.rom.coefficient_filter import CoefficientSettings
from hybridcomp.rom.dataonly_model import ChannelModel, DataOnlyModel, model_to_json

PKEY = "X=0,Y=0,Z=0"
NOW_UNIX = 1.7e9
SENSORS = ("T1", "T3", "Tamb")
PROBES = (60, 150)


def _channel(name: str, family: str, ncols: int, seed: int) -> ChannelModel:
    rng = np.random.default_rng(seed)
    p = ncols + 1
    B = rng.normal(size=(p, p))
    settings = CoefficientSettings(every_h=0.25, probe_sd_um=0.3, prior_scale=1.0, walk=0.05, range_walk=0.1)
    return ChannelModel(name, family, "spindle_rpm" if family.startswith("S") else None, 1.5 if family.startswith("S")
                        else 1.0, rng.normal(20.0, 1.0, ncols), rng.uniform(0.5, 2.0, ncols), rng.normal(0.0, 3.0, p),
                        B @ B.T + p * np.eye(p), 0.25, np.full(ncols, -2.0), np.full(ncols, 2.0), settings)


def _model() -> DataOnlyModel:
    nT = len(SENSORS)
    return DataOnlyModel(SENSORS, {"spindle_rpm": 12000.0}, (
        _channel("dx_um", "T+lagT", 2 * nT, 1),
        _channel("dz_um", "S1.5(spindle_rpm)+T+lagT", 2 + 2 * nT, 2),
    ), (1.0,), (0.25, 2.0))


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("dataonly") / "dataonly_model.json"
    path.write_text(model_to_json(_model()))
    return path


@pytest.fixture(scope="module")
def readings(machine):
    """40 min of the job-shop day at 0.1 Hz, the sensors as the structure model knows no better (smooth), probes."""
    from hybridcomp.monitor.example import jobshop_samples

    s = jobshop_samples(machine, hours=40 / 60, rate_hz=0.1)
    names = [n.name for n in machine.sensors]
    out = []
    for i in range(len(s)):
        t = float(s.time_s[i])
        sensors = {n: 20.0 + 0.3 * j + 2.0 * (1 - math.exp(-t / (1800.0 + 300 * j))) for j, n in enumerate(names)}
        probe = (1.0 + 0.1 * i, math.nan, -2.0 - 0.05 * i) if i in PROBES else None
        out.append(Reading(t, tuple(map(float, s.position_mm[i])), float(s.spindle_rpm[i]), sensors,
                           {s.air_names[0]: float(s.air_degC[i, 0])}, probe))
    return out


def _cfg(tmp_path, model_file, **comp):
    data = {"monitor": {"machine": "vmc800", "database": "unused.db", "rom": "unused.rom.npz", "increment_s": 60.0},
            "compensation": {"strategy": "dataonly", "dataonly_model": str(model_file), "sensor_filter_s": 0.0,
                             "max_offset_um": 1e4, "max_step_um": 1e4, **comp},
            "source": {"kind": "replay", "path": "unused.csv", "speed": 0}, "sink": {"kind": "none"},
            "regeneration": {"enabled": False}}
    return parse_config(data, "test.toml", tmp_path)


def _replay(ctx, readings, state=None):
    state = T.initial(ctx) if state is None else state
    offsets, states = [], []
    for r in readings:
        step = T.on_reading(ctx, state, r, T.no_stored_sets, NOW_UNIX)
        state = step.state
        offsets += step.offsets
        states.append(state)
    return offsets, states


def _expected(readings, probes=True):
    """The pure step function on the readings (sensors unfiltered: sensor_filter_s = 0), row by row."""
    model = _model()
    rows = []
    st = None
    for r in readings:
        sensors = {**r.sensors_degC, **{k.removesuffix("_degC"): v for k, v in r.air_degC.items()}}
        sensors = {n: sensors[n] for n in SENSORS}
        spindle = {"spindle_rpm": r.spindle_rpm}
        if st is None:
            st = D.start(model, r.time_s, sensors, spindle)
            off, _ = D.predict(model, st)
        else:
            st, off, _ = D.step(model, st, r.time_s, sensors, spindle, r.probe_um if probes else None)
        rows.append((off["dx_um"], 0.0, off["dz_um"]))
    return rows


def test_a_replay_writes_the_pure_step_functions_offsets_and_rate_limits_them(tmp_path, model_file, machine,
                                                                              small_rom, readings):
    cfg = _cfg(tmp_path, model_file)
    ctx = T.context(cfg, machine, small_rom, PKEY, read_dataonly_model(cfg.dataonly_model))
    offsets, states = _replay(ctx, readings)
    want = _expected(readings)
    assert len(offsets) == len(readings)  # every sample (10 s) completes a compensation cycle (5 s)
    assert [(o.dx_um, o.dy_um, o.dz_um) for o in offsets] == want
    assert {o.by for o in offsets} == {"dataonly"}
    assert max(abs(w[2]) for w in want) > 1.0  # (the model gives offsets worth limiting)
    # the rate limit as for every strategy: the first offsets clamped only, then max_step_um per cycle
    cfg = _cfg(tmp_path, model_file, max_step_um=0.2, max_offset_um=5.0)
    ctx = T.context(cfg, machine, small_rom, PKEY, read_dataonly_model(cfg.dataonly_model))
    limited, _ = _replay(ctx, readings)
    last, step = {"dx_um": 0.0, "dy_um": 0.0, "dz_um": 0.0}, math.inf
    for o, w in zip(limited, want):
        last, _, _ = decisions.limit_offsets(dict(zip(("dx_um", "dy_um", "dz_um"), w)), last, 5.0, step)
        step = 0.2
        assert (o.dx_um, o.dy_um, o.dz_um) == (last["dx_um"], last["dy_um"], last["dz_um"])
    assert any(o.limited for o in limited) and any(o.clamped for o in limited)


def test_a_probe_updates_the_coefficients(tmp_path, model_file, machine, small_rom, readings):
    cfg = _cfg(tmp_path, model_file)
    ctx = T.context(cfg, machine, small_rom, PKEY, read_dataonly_model(cfg.dataonly_model))
    probed, states = _replay(ctx, readings)
    plain, _ = _replay(ctx, [dataclasses.replace(r, probe_um=None) for r in readings])
    k = PROBES[0]
    before, after = states[k - 1].saved.dataonly, states[k].saved.dataonly
    model = _model()
    for c, f0, f1 in zip(model.channels, before.filters, after.filters):
        np.testing.assert_array_equal(f0.theta, c.coef)  # the training fit until the first probe
        assert f1.t_probe_s == readings[k].time_s and not np.array_equal(f1.theta, c.coef)
    # the probed sample's offsets come from the probes before it; those after it from the updated coefficients
    assert [(o.dx_um, o.dz_um) for o in probed[:k + 1]] == [(o.dx_um, o.dz_um) for o in plain[:k + 1]]
    assert all(o.dx_um != p.dx_um and o.dz_um != p.dz_um for o, p in zip(probed[k + 1:], plain[k + 1:]))
    assert _expected(readings, probes=False) == [(o.dx_um, o.dy_um, o.dz_um) for o in plain]


def test_a_restarted_daemon_continues_the_models_state(tmp_path, model_file, machine, small_rom, readings):
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.daemon import Monitor

    cfg = _cfg(tmp_path, model_file, max_step_um=0.5)
    stop_at = readings[0].time_s + 1500.0  # after the first probe, the boundary at 900 s persisted
    runs = {}
    for name in ("straight", "restarted"):
        db = CDDatabase(tmp_path / f"{name}.db")
        try:
            mon = Monitor(cfg, machine, small_rom, db, PKEY)
            if name == "straight":
                offsets = [o for r in readings for o in mon.process(r)]
            else:
                offsets = [o for r in readings if r.time_s <= stop_at for o in mon.process(r)]
                mon = Monitor(cfg, machine, small_rom, db, PKEY)  # the daemon restarted
                after = mon.resume_after_s()
                saved = mon.state.saved.dataonly
                assert after is not None and after < stop_at and saved is not None and saved.t_s == after
                assert saved.filters[0].t_probe_s == readings[PROBES[0]].time_s  # the probe's update persisted
                again = [o for r in readings if r.time_s > after for o in mon.process(r)]
                offsets = [o for o in offsets if o.time_s <= after] + again
            runs[name] = offsets
        finally:
            db.close()
    a, b = runs["straight"], runs["restarted"]
    assert len(a) == len(b) == len(readings) and all(x == y for x, y in zip(a, b))
    # the persisted form is exact
    s = mon.state.saved
    back = MonitorState.from_json(s.to_json()).dataonly
    assert back.t_s == s.dataonly.t_s and np.array_equal(back.lags, s.dataonly.lags)
    assert all(np.array_equal(x.P, y.P) and np.array_equal(x.theta, y.theta)
               for x, y in zip(back.filters, s.dataonly.filters))


def test_the_configuration_refuses_a_missing_unreadable_or_unusable_model(tmp_path, model_file, machine, small_rom):
    with pytest.raises(ConfigError, match=r"test\.toml: compensation\.dataonly_model is missing"):
        parse_config(
            {"monitor": {"machine": "vmc800", "database": "d.db", "rom": "r.npz"}, "source": {"path": "t.csv"},
             "sink": {"kind": "none"}, "compensation": {"strategy": "dataonly"}}, "test.toml", tmp_path)
    with pytest.raises(ConfigError, match=r"compensation\.dataonly_model = '.*nope\.json': cannot be read"):
        _cfg(tmp_path, tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"sensors": ["T1"]}')
    with pytest.raises(ConfigError, match=r"dataonly_model = '.*bad\.json': not a data-only model \(KeyError"):
        _cfg(tmp_path, bad)
    other = tmp_path / "other.json"
    m = _model()
    other.write_text(model_to_json(dataclasses.replace(m, channels=(dataclasses.replace(m.channels[0],
                                                                                         channel="dq_um"),))))
    with pytest.raises(ConfigError, match=r"channel 'dq_um' is not an offset"):
        _cfg(tmp_path, other)
    with pytest.raises(ConfigError, match=r"dataonly_model = '.*' applies to strategy 'dataonly' only, not 'hybrid'"):
        _cfg(tmp_path, model_file, strategy="hybrid")
    cfg = _cfg(tmp_path, model_file)  # relative to the configuration's folder
    rel = parse_config({"monitor": {"machine": "vmc800", "database": "d.db", "rom": "r.npz"}, "source": {"path": "t"},
                        "sink": {"kind": "none"}, "compensation": {"strategy": "dataonly",
                                                                   "dataonly_model": model_file.name}},
                       "test.toml", model_file.parent)
    assert rel.dataonly_model == model_file and cfg.dataonly_model == model_file
    with pytest.raises(ValueError, match="strategy 'dataonly' needs the data-only model"):
        T.context(cfg, machine, small_rom, PKEY)
    odd = dataclasses.replace(m, sensors=("T1", "T3", "Tcoolant"))
    with pytest.raises(ValueError, match="reads Tcoolant, which machine vmc800 has neither as a sensor nor as an air"):
        T.context(cfg, machine, small_rom, PKEY, odd)
