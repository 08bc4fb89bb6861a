"""The public API: the core flow from ``hybridcomp``, one error base, one vocabulary, one simulate for FE and ROM."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import types

import numpy as np
import pytest

import hybridcomp as hc
from hybridcomp.models.layout import LoadsColumnError, heat_input_name


def test_every_public_name_resolves_to_an_object():
    for name in hc.__all__:
        value = getattr(hc, name)
        assert not isinstance(value, types.ModuleType), f"hybridcomp.{name} is a module, not the function or type"
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        hc.nonsense  # noqa: B018


def _modules():
    for info in pkgutil.walk_packages(hc.__path__, "hybridcomp."):
        if info.name.endswith("__main__"):
            continue
        yield importlib.import_module(info.name)


def test_every_error_is_a_hybridcomp_error_and_a_builtin():
    errors = {obj for m in _modules() for _, obj in inspect.getmembers(m, inspect.isclass)
              if issubclass(obj, Exception) and not issubclass(obj, Warning) and obj.__module__.startswith("hybridcomp.")}
    assert len(errors) >= 15
    for e in errors:
        if e is hc.HybridcompError or issubclass(e, ConnectionError):  # a lost OPC UA link is the built-in's
            continue
        assert issubclass(e, hc.HybridcompError), e
        assert any(issubclass(e, b) for b in (ValueError, RuntimeError, OSError)), e


def test_layout_names_maps_and_refuses(machine):
    layout = machine.layout()
    assert heat_input_name("x_nut", 2) == "x_nut[2]" and heat_input_name("x_motor") == "x_motor"
    assert layout.columns[:4] == ("x_motor_W", "x_bearing_fixed_W", "x_bearing_floating_W", "x_nut[1]_W")
    assert layout.output_columns[-3:] == hc.DRIFT_COLUMNS
    U = layout.inputs(["x_motor_W", "Tamb_degC"], np.array([[5.0, 21.5]]), "f.csv", layout.air_sources(["Tamb_degC"]))
    assert U[0, 0] == 5.0 and U[0, 1:len(layout.heat_inputs)].sum() == 0.0
    zones = np.array(layout.zone_air)
    air = U[0, len(layout.heat_inputs):]
    # no workspace column measured: workspace zones follow the workshop air too (1.5 K above the reference)
    assert np.allclose(air, 21.5 - machine.reference_temperature_degC) and set(zones) == {"ambient", "workspace"}
    with pytest.raises(LoadsColumnError, match=r"f.csv: column 'x_motr_W' is not an input of machine 'vmc800'"):
        layout.inputs(["x_motr_W"], np.zeros((1, 1)), "f.csv")
    with pytest.raises(LoadsColumnError):
        hc.in_model_order(hc.Loads(np.zeros(1), np.zeros((1, 1)), ("nonsense_W",)), layout)


@pytest.mark.slow
def test_one_simulate_for_fe_and_reduced_models(machine, model_200mm):
    model = model_200mm  # at mid travel, 200 mm elements (shared)
    # reduced to its default tolerance (0.05 K / 0.2 µm) on another load case than the one compared below
    rom = hc.reduce_model(model, keep_basis=False, check_loads=hc.example_loads(machine, 2.0, 600.0, seed=1))
    loads = hc.example_loads(machine, duration_h=4.0, dt_s=300.0)
    # a loads subset: missing columns are zero power / the reference temperature, for both
    sub = hc.Loads(loads.time_s, loads.values[:, :12], loads.names[:12])
    fe = hc.simulate(model, sub)
    red = hc.simulate(rom, sub)
    assert isinstance(fe, hc.SimulationResult) and isinstance(red, hc.SimulationResult)
    assert fe.sensor_names == red.sensor_names == tuple(s.name for s in machine.sensors)
    assert fe.time_error["met"]
    # the ROM reproduces the FE run (to its reduction tolerance) and continues from its final state exactly
    assert np.abs(fe.sensors_degC - red.sensors_degC).max() < 0.05
    assert np.abs(fe.drift_um - red.drift_um).max() < 0.2
    k = 20
    first = hc.Loads(sub.time_s[:k + 1], sub.values[:k + 1], sub.names)
    rest = hc.Loads(sub.time_s[k:], sub.values[k:], sub.names)
    cont = rom.simulate(rest, initial=rom.simulate(first).final_state)
    np.testing.assert_allclose(cont.drift_um, red.drift_um[k:], rtol=1e-9, atol=1e-9)


def test_step_hold_holds_each_row_over_its_interval(machine, small_rom):
    rom = small_rom  # any reduced model of the machine: the shared one (200 mm, order 40)
    loads = hc.example_loads(machine, duration_h=2.0, dt_s=600.0)
    U = rom.layout().inputs(loads.names, loads.values)
    x = rom.steady_state(U[0])
    for k in range(1, len(loads.time_s)):
        x = rom.step(x, U[k], U[k], loads.time_s[k] - loads.time_s[k - 1])
    held = rom.simulate(loads, hold="step")
    np.testing.assert_allclose(held.final_state, x, rtol=1e-9, atol=1e-12)
    # and it differs from the linear reading where the loads change
    assert np.abs(rom.simulate(loads).final_state - x).max() > 1e-6
