"""The scenario's settings: every field checked when a Scenario is built, with a message naming it."""

from __future__ import annotations

import dataclasses
import math

import pytest

from hybridcomp.scenario import DISTURBANCES, NOMINAL, STRATEGIES, Scenario, run_scenario


def test_defaults_are_the_documented_run():
    s = Scenario()
    assert (s.disturbance, s.real_machine, s.machine_name, s.element_size_mm, s.rom_order) == (
        NOMINAL, None, "vmc800", 80.0, None)
    assert (s.basic_hours, s.day_hours, s.dt_s, s.real_dt_s, s.trace_rate_hz) == (8.0, None, 60.0, 20.0, 1.0)
    assert (s.sensor_noise_K, s.probe_every_h, s.probe_noise_um, s.seed) == (0.02, 4.0, 0.3, 0)
    assert s.strategies == STRATEGIES and s.plot and not s.keep_basis and not s.along_path
    assert s.monitor_overrides is None


def test_frozen_and_derived_with_replace():
    s = Scenario(disturbance=DISTURBANCES["demo day"], day_hours=6.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.day_hours = 2.0
    t = dataclasses.replace(s, along_path=True)
    assert t.along_path and t.day_hours == 6.0 and not s.along_path


def test_strategies_become_a_tuple():
    assert Scenario(strategies=["observer"]).strategies == ("observer",)
    with pytest.raises(ValueError, match="sequence of strategy names"):
        Scenario(strategies="hybrid")


@pytest.mark.parametrize("field, value, words", [
    ("strategies", ("hybrid", "cds"), "unknown strategy 'cds'"),
    ("strategies", ("hybrid", "dataonly"), "strategy 'dataonly' needs its model"),
    ("day_hours", 0.0, "day_hours must be in (0, 16]"),
    ("day_hours", 17.0, "day_hours must be in (0, 16], got 17.0"),
    ("element_size_mm", 0.0, "element_size_mm must be a finite number > 0, got 0.0"),
    ("element_size_mm", math.nan, "element_size_mm must be a finite number > 0"),
    ("basic_hours", -1.0, "basic_hours must be a finite number > 0"),
    ("dt_s", math.inf, "dt_s must be a finite number > 0"),
    ("real_dt_s", "20", "real_dt_s must be a finite number > 0, got '20'"),
    ("trace_rate_hz", 0, "trace_rate_hz must be a finite number > 0"),
    ("sensor_noise_K", -0.1, "sensor_noise_K must be a finite number >= 0"),
    ("probe_noise_um", True, "probe_noise_um must be a finite number >= 0, got True"),
    ("probe_every_h", 0.0, "probe_every_h must be a finite number > 0 or None (no probing)"),
    ("rom_order", 0, "rom_order must be a whole number >= 1 or None"),
    ("rom_order", 2.5, "rom_order must be a whole number >= 1 or None"),
])
def test_a_bad_field_is_refused_naming_it(field, value, words):
    with pytest.raises(ValueError) as exc:
        Scenario(**{field: value})
    assert words in str(exc.value)


def test_zero_noise_and_no_probing_are_allowed():
    s = Scenario(sensor_noise_K=0.0, probe_noise_um=0.0, probe_every_h=None, rom_order=12)
    assert s.probe_every_h is None and s.rom_order == 12


def test_run_scenario_takes_a_scenario_and_a_folder_only():
    with pytest.raises(TypeError):
        run_scenario(Scenario(), "out", disturbance=NOMINAL)  # the settings live in the Scenario


def test_activations_per_day_count_the_half_open_day():
    """A set activated at the day's last sample belongs to the next day: two days in a row must not both count it."""
    from hybridcomp.scenario import activations_within

    ev = [{"kind": "activation", "machine_time_s": t} for t in (0.0, 9000.0, 57600.0)]
    ev += [{"kind": "decision", "machine_time_s": 30000.0}, {"kind": "generation", "machine_time_s": 9000.0}]
    assert activations_within(ev, 0.0, 57600.0) == 2
    assert activations_within(ev, 57600.0, 115200.0) == 1
    assert activations_within(ev, 0.0, 57600.0) + activations_within(ev, 57600.0, 115200.0) == 3
