"""What a feed drive adds to the FE structure: the feedback's length less the carrier's (``fem.drives.DriveError``).

The structure bonds the moving body to its carrier, so it holds the carrier's expansion between the fixed bearing
and the nut already; the drive adds only what its feedback (screw or scale) expands beyond that.  On a uniform rise
the error along every axis therefore grows with the feedback's α alone: a rotary encoder's screw (X, Y: steel,
11.5 µm/m per K, on the table side: negative) and a linear scale's glass (Z: 8 µm/m per K, on the tool side).
Counting the carrier twice (the structure plus the screw's whole elongation) adds the carrier's cast iron
(10.5 µm/m per K) and fails every slope here by that much.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridcomp.fem.drives import build_screw, carrier_line, drive_error, integral_weights
from hybridcomp.fem.iso230 import axis_sign, axis_test_of_loads, etve_of_loads
from hybridcomp.fem.model import build_model
from hybridcomp.models import load_machine
from hybridcomp.models.convection import horizontal_cylinder_natural_h_W_m2K, rotating_cylinder_h_W_m2K, screw_h_W_m2K
from hybridcomp.models.layout import Loads
from tests.test_machine_file import assert_names, edit, load_error

H_MM = 200.0
ALPHA_STEEL = 11.5e-6
ALPHA_CAST_IRON = 10.5e-6
ALPHA_GLASS = 8.0e-6
#: the feedback's α per axis, and the side the axis moves (X, Y the table's, Z the tool's)
FEEDBACK_ALPHA = {"X": ALPHA_STEEL, "Y": ALPHA_STEEL, "Z": ALPHA_GLASS}
SIGN = {"X": -1.0, "Y": -1.0, "Z": 1.0}
#: the FE structure's own slope under a uniform rise is the cast iron's within this [µm/m per K] (the steel
#: spindle in the cast iron headstock strains the structure a little: 0.006 µm/m measured on 200 mm elements)
STRUCTURE_TOL_UM_PER_M = 0.02


@pytest.fixture(scope="module")
def model(model_200mm):
    assert model_200mm.machine.mesh.element_size_mm == H_MM
    return model_200mm


def uniform_air_loads(machine, rise_K: float = 1.0) -> Loads:
    """Every zone's air ``rise_K`` over the reference, no heat, for an hour: steady, so a uniform rise."""
    layout = machine.layout()
    U = np.zeros((2, layout.n_inputs))
    U[:, len(layout.heat_inputs):] = rise_K
    return Loads(np.array([0.0, 3600.0]), layout.loads_values(U), layout.columns)


def slope_um_per_m(positions_mm, values_um) -> float:
    return float(np.polyfit(np.asarray(positions_mm) * 1e-3, values_um, 1)[0])


def test_the_materials_are_the_ones_the_hand_numbers_take(vmc):
    assert vmc.materials["steel"].expansion_1_K == ALPHA_STEEL
    assert vmc.materials["cast_iron"].expansion_1_K == ALPHA_CAST_IRON
    assert vmc.drive("Z").scale_expansion_1_K == ALPHA_GLASS
    assert {a: axis_sign(vmc, a) for a in "XYZ"} == SIGN
    for axis, body in (("X", "saddle"), ("Y", "bed")):
        assert vmc.heat_source(vmc.drive(axis).fixed_bearing).body == body
    assert vmc.body("saddle").material == vmc.body("bed").material == vmc.body("column").material == "cast_iron"


# --------------------------------------------------------------------------- the definition, closed forms

@pytest.mark.parametrize("axis", ["X", "Y", "Z"])
def test_uniform_rise_adds_the_feedbacks_alpha_less_the_carriers(vmc, model, axis):
    err = drive_error(model, vmc.drive(axis))
    dT = 2.7
    p = np.linspace(*vmc.axis(axis).travel_mm, 7)
    x_screw = None if err.screw is None else np.full(err.screw.s_mm.size, dT)
    got = err.error_um(p, np.full(model.n, dT), x_screw)
    drive = vmc.drive(axis)
    d = vmc.axis(axis).direction
    if axis == "Z":
        distance = drive.scale_head_at_mm + p - drive.scale_fixed_at_mm
    else:
        distance = vmc.heat_source(drive.nut).position_mm[d] + p - vmc.heat_source(drive.fixed_bearing).position_mm[d]
    want = (FEEDBACK_ALPHA[axis] - ALPHA_CAST_IRON) * dT * distance * 1e3
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=0)


@pytest.mark.parametrize("axis", ["X", "Y"])
def test_carrier_term_vanishes_on_a_uniform_field_when_the_carrier_has_the_screws_alpha(vmc, model, axis):
    err = drive_error(model, vmc.drive(axis))
    same = dataclasses.replace(err, carrier=dataclasses.replace(err.carrier, alpha_1_K=err.screw.alpha_1_K))
    p = np.linspace(*vmc.axis(axis).travel_mm, 5)
    x, xs = np.full(model.n, 4.0), np.full(err.screw.s_mm.size, 4.0)
    np.testing.assert_allclose(same.error_um(p, x, xs), 0.0, atol=1e-9)
    # the carrier's own term is the carrier's expansion: minus α ΔT times the nut's distance from the fixed bearing
    np.testing.assert_allclose(err.fe_rows(p) @ x, -ALPHA_CAST_IRON * 4.0 * (err.moving_mm(p) - err.s_fixed_mm) * 1e3,
                               rtol=1e-9)


def test_carrier_line_integrates_a_linear_field_exactly(vmc, model):
    """A field linear along x at the model's pose: ``∫ c s ds`` along the X screw's line on the saddle."""
    c = 3e-3  # K/mm
    x = c * model.mesh.mesh.p[0] * 1e3  # the saddle does not move with X: its x at the model's pose is the reference's
    line = carrier_line(model, vmc.drive("X"))
    assert line.body == "saddle" and line.alpha_1_K == ALPHA_CAST_IRON
    ends = np.array([-400.0, -123.4, 0.0, 271.7, 400.0])
    sf = -430.0
    np.testing.assert_allclose(line.integral_rows(sf, ends) @ x, c * (ends**2 - sf**2) / 2, rtol=1e-9)


@pytest.fixture(scope="module")
def prestretched(tmp_path_factory):
    path = tmp_path_factory.mktemp("pre") / "m.toml"
    path.write_text(edit('fixed_bearing = "x_bearing_fixed"', 'fixed_bearing = "x_bearing_fixed"\nmounting = '
                         '"pre-stretched"\nprestretch_um = 40.0'), encoding="utf-8")
    m = load_machine(path)
    return m, build_model(m, None, H_MM)


def test_pre_stretched_screw_follows_its_carrier_and_the_mean_difference_is_strain(prestretched):
    m, fe = prestretched
    err = drive_error(fe, m.drive("X"))
    sc = err.screw
    p = np.array([-400.0, -250.0, 17.0, 333.0, 400.0])
    s, sf, so = sc.nut_mm(p), sc.s_fixed_mm, sc.s_other_mm
    # uniform, whatever the two α: the bearings on the carrier hold the screw, no error; the pre-stretch left is
    # the pre-stretch less the screw's expansion beyond the carrier's over the whole length
    x, xs = np.full(fe.n, 5.0), np.full(sc.s_mm.size, 5.0)
    np.testing.assert_allclose(err.error_um(p, x, xs), 0.0, atol=1e-9)
    np.testing.assert_allclose(err.prestretch_left_um(x, xs),
                               40.0 - (ALPHA_STEEL - ALPHA_CAST_IRON) * 5.0 * (so - sf) * 1e3, rtol=1e-9)
    # gradients b s (screw) and c s (carrier): E(s) = (α_s b − α_c c) (s² − sf²) / 2, its mean share taken off
    b, c = 6e-3, 2e-3
    E = lambda z: (ALPHA_STEEL * b - ALPHA_CAST_IRON * c) * (z**2 - sf**2) / 2 * 1e3  # noqa: E731
    want = E(s) - (s - sf) / (so - sf) * E(so)
    got = err.error_um(p, c * fe.mesh.mesh.p[0] * 1e3, b * sc.s_mm)
    np.testing.assert_allclose(got, want, rtol=1e-6)


# --------------------------------------------------------------------------- a uniform air rise, the FE paths

@pytest.fixture(scope="module")
def uniform(vmc, model):
    loads = uniform_air_loads(vmc)
    return loads, {a: axis_test_of_loads(model, a, loads, np.linspace(*vmc.axis(a).travel_mm, 5)) for a in "XYZ"}


@pytest.mark.parametrize("axis", ["X", "Y", "Z"])
def test_uniform_air_rise_moving_axis_error_grows_with_the_feedbacks_alpha_alone(uniform, axis):
    _, res = uniform
    r = res[axis]
    got = slope_um_per_m(r.targets_mm, r.error_um[-1])
    assert got == pytest.approx(SIGN[axis] * FEEDBACK_ALPHA[axis] * 1e6, abs=STRUCTURE_TOL_UM_PER_M)
    # its parts: the structure at the target's pose expands with the carrier's cast iron, the drive adds the rest
    assert slope_um_per_m(r.targets_mm, r.structure_um[-1]) == pytest.approx(SIGN[axis] * ALPHA_CAST_IRON * 1e6,
                                                                            abs=STRUCTURE_TOL_UM_PER_M)
    assert slope_um_per_m(r.targets_mm, r.feedback_um[-1]) == pytest.approx(
        (FEEDBACK_ALPHA[axis] - ALPHA_CAST_IRON) * 1e6, rel=1e-9)


def test_uniform_air_rise_etve_error_at_the_travel_ends_has_the_feedbacks_alpha(vmc, model, uniform):
    loads, res = uniform
    etve = etve_of_loads(model, loads)
    for axis in "XYZ":
        lo, hi = vmc.axis(axis).travel_mm
        e = etve.error_um[axis][-1]
        assert (e[1] - e[0]) / (hi - lo) * 1e3 == pytest.approx(SIGN[axis] * FEEDBACK_ALPHA[axis] * 1e6,
                                                                abs=STRUCTURE_TOL_UM_PER_M)
        r = res[axis]  # the same error as the moving-axis machinery's at the ends
        np.testing.assert_allclose(e, r.error_um[-1][[0, -1]], rtol=1e-12)


# --------------------------------------------------------------------------- the screw's heat paths

def test_turning_screw_convection_is_the_rotating_cylinder_correlation():
    # by hand, 40 mm at 1000 rpm: ω = 104.72 1/s, Re = ω D² / ν = 104.72 · 0.0016 / 1.516e-5 = 11,052,
    # Nu = 0.133 · 11,052^(2/3) · 0.713^(1/3) = 0.133 · 496.2 · 0.8934 = 58.96, h = Nu k / D = 58.96 · 0.0257 / 0.04
    assert rotating_cylinder_h_W_m2K(40.0, 1000.0) == pytest.approx(37.88, rel=1e-3)
    # at rest, 5 K over the air: Ra = 9.81 · (5 / 293.15) · 0.04³ / (1.516e-5 · 2.126e-5) = 33,220,
    # Nu = (0.60 + 0.387 · 33,220^(1/6) / 1.2042)² = (0.60 + 0.387 · 5.670 / 1.2042)² = 5.866, h = Nu k / D
    assert horizontal_cylinder_natural_h_W_m2K(40.0) == pytest.approx(3.769, rel=1e-3)
    assert screw_h_W_m2K(40.0, 0.0) == pytest.approx(3.769, rel=1e-3)  # at rest: natural convection alone
    assert screw_h_W_m2K(40.0, 1000.0) == pytest.approx((37.88**3 + 3.769**3) ** (1 / 3), rel=1e-3)
    # the forced part grows as (ω D²)^(2/3) / D = ω^(2/3) D^(1/3)
    assert rotating_cylinder_h_W_m2K(80.0, 250.0) / rotating_cylinder_h_W_m2K(40.0, 1000.0) == pytest.approx(
        0.25 ** (2 / 3) * 2 ** (1 / 3), rel=1e-12)


def _drive_text(extra: str) -> str:
    return edit('fixed_bearing = "x_bearing_fixed"', 'fixed_bearing = "x_bearing_fixed"\n' + extra)


@pytest.mark.parametrize("extra, want", [
    ("screw_mean_rpm = 1000.0", 37.89),  # the correlation
    ("screw_mean_rpm = 1000.0\nscrew_h_W_m2K = 12.5", 12.5),  # given: it wins
    ("", 20.0),  # neither: the default
])
def test_screw_coefficient_from_the_mean_speed_unless_given(tmp_path, extra, want):
    path = tmp_path / "m.toml"
    path.write_text(_drive_text(extra), encoding="utf-8")
    assert load_machine(path).drive("X").screw_h_W_m2K == pytest.approx(want, rel=1e-3)


def test_screw_speed_beyond_the_correlation_is_refused(tmp_path):
    assert_names(load_error(tmp_path, _drive_text("screw_mean_rpm = 50000.0")), "drives[0].screw_mean_rpm", "50000")


@pytest.fixture(scope="module")
def conducting(tmp_path_factory):
    """vmc800 with 0.8 W/K at each X bearing."""
    path = tmp_path_factory.mktemp("g") / "m.toml"
    path.write_text(_drive_text("bearing_conductance_W_K = 0.8"), encoding="utf-8")
    return load_machine(path)


def test_bearing_conductance_leaves_a_uniform_air_rise_uniform_and_balances_the_heat(conducting):
    m = conducting
    drive = m.drive("X")
    assert drive.bearing_conductance_W_K == 0.8
    screw = build_screw(m, drive)
    assert screw.G.sum() == pytest.approx(2 * 0.8, rel=1e-12)  # two bearings
    layout = m.layout()
    u = np.zeros(layout.n_inputs)
    u[len(layout.heat_inputs) + layout.zones.index(drive.screw_zone)] = 1.0
    np.testing.assert_allclose(screw.steady(u), 1.0, rtol=1e-12)
    u[:] = 0.0
    u[layout.source_columns(drive.fixed_bearing)[0]] = 20.0
    x = screw.steady(u)
    q_in = drive.fixed_bearing_screw_W / m.heat_source(drive.fixed_bearing).power_W * 20.0
    area = np.pi * drive.screw_diameter_mm * 1e-3 * 1e-3  # m² per mm of screw
    q_conv = drive.screw_h_W_m2K * area * (integral_weights(screw.s_mm, screw.s_mm[0], screw.s_mm[-1]) @ x)
    assert q_conv + screw.G @ x @ np.ones(x.size) == pytest.approx(q_in, rel=1e-9)
    assert screw.G @ x @ np.ones(x.size) > 0.05 * q_in  # the bearings take a share


def test_bearing_conductance_of_a_well_conducting_screw_gives_the_lumped_temperature(conducting):
    """A screw conducting a million times better is isothermal: T = Q / (h π D L + 2 G) by hand."""
    m = conducting
    steel = m.materials["steel"]
    m = dataclasses.replace(m, materials={**m.materials, "steel": dataclasses.replace(
        steel, conductivity_W_mK=1e6 * steel.conductivity_W_mK)})
    drive = m.drive("X")
    screw = build_screw(m, drive)
    layout = m.layout()
    u = np.zeros(layout.n_inputs)
    u[layout.source_columns(drive.fixed_bearing)[0]] = 20.0
    q = drive.fixed_bearing_screw_W / m.heat_source(drive.fixed_bearing).power_W * 20.0
    length_m = (screw.s_mm[-1] - screw.s_mm[0]) * 1e-3
    want = q / (drive.screw_h_W_m2K * np.pi * drive.screw_diameter_mm * 1e-3 * length_m + 2 * 0.8)
    x = screw.steady(u)
    assert np.ptp(x) < 2e-3 * want
    assert x.mean() == pytest.approx(want, rel=2e-3)
