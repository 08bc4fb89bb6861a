"""The regeneration job's forecast scenarios heat a drive with the machine's own power law."""

from __future__ import annotations

import numpy as np
import pytest

from hybridcomp.models import load_machine
from hybridcomp.models.loader import resolve_machine_path
from hybridcomp.monitor.regeneration import BASIC_FACTOR, forecast_scenarios

VMC800 = resolve_machine_path("vmc800").read_text(encoding="utf-8")
X_MOTOR = 'name = "x_motor"\nbody = "saddle"\nposition_mm = [-470.0, -150.0, 100.0]\nsize_mm = [60.0, 120.0, 120.0]\n' \
    'power_W = 90.0\ndriver = "X"\nexponent = 1.0\n'
# far from the power law at the basic factor 0.6: the law gives 0.6, the table 0.9
TABLE = "power_table = [[0.0, 0.2], [0.6, 0.9], [1.0, 1.0]]\n"


@pytest.fixture(scope="module")
def tabled(tmp_path_factory):
    assert VMC800.count(X_MOTOR) == 1
    path = tmp_path_factory.mktemp("table") / "tabled.toml"
    path.write_text(VMC800.replace(X_MOTOR, X_MOTOR + TABLE), encoding="utf-8")
    return load_machine(path)


def _x_alone(machine):
    layout = machine.layout()
    U = np.column_stack([np.zeros((4, len(layout.heat_inputs))),
                         np.full((4, len(layout.zones)), machine.reference_temperature_degC)])
    return forecast_scenarios(machine, layout.columns, U, 1.0)["X alone"][0], layout


def test_a_drive_alone_takes_the_power_table_of_its_sources(tabled):
    u, layout = _x_alone(tabled)
    src = {s.name: s for s in tabled.heat_sources}["x_motor"]
    (j,) = layout.source_columns("x_motor")
    assert u[j] == pytest.approx(0.9 * src.power_W)  # the table at 0.6, not 0.6 ** exponent
    assert u[j] == pytest.approx(float(tabled.source_power_W(src, BASIC_FACTOR)))


def test_a_drive_alone_without_a_table_follows_the_power_law():
    machine = load_machine("vmc800")
    u, layout = _x_alone(machine)
    for s in machine.heat_sources:
        if (s.driver or s.axis) == "X":
            cols = list(layout.source_columns(s.name))
            np.testing.assert_allclose(u[cols], s.power_W * BASIC_FACTOR ** s.exponent / len(cols), rtol=1e-12)
