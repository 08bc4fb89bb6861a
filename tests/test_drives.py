"""Feed drives: positioning errors of ball screws and linear scales against closed forms, the screw's thermal
model against analytic solutions, the ``[[drives]]`` checks, and the simulated ISO 230-3 tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.cli import main
from hybridcomp.fem.drives import build_screw, drive_error, integral_weights
from hybridcomp.fem.iso230 import axis_sign, etve_loads, moving_axis_test
from hybridcomp.fem.model import build_model
from hybridcomp.models import MachineFileError, load_machine
from tests.test_machine_file import VMC800, append, assert_names, edit, load_error

H_MM = 200.0  # coarse: the scale's rows and the tests' structure share only
RNG = np.random.default_rng(230)
ALPHA_STEEL = 11.5e-6


@pytest.fixture(scope="module")
def model(model_200mm):
    assert model_200mm.machine.mesh.element_size_mm == H_MM
    return model_200mm


def _positions(vmc, axis: str, n: int = 7) -> np.ndarray:
    lo, hi = vmc.axis(axis).travel_mm
    return np.concatenate([[lo, hi], RNG.uniform(lo, hi, n - 2)])


# --------------------------------------------------------------------------- closed forms (1e-6 relative)

@pytest.mark.parametrize("axis", ["X", "Z"])  # Z's fixed bearing is above the nut: the error is negative
def test_uniform_screw_rise_gives_alpha_dT_times_distance_from_fixed_bearing(vmc, axis):
    screw = build_screw(vmc, vmc.drive(axis))
    dT = 3.7
    p = _positions(vmc, axis)
    got = screw.elongation_rows(p) @ np.full(screw.s_mm.size, dT)
    x_nut = vmc.heat_source(vmc.drive(axis).nut).position_mm[vmc.axis(axis).direction] + p
    want = ALPHA_STEEL * dT * (x_nut - screw.s_fixed_mm) * 1e3
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)
    assert np.all(np.sign(want) == (1 if screw.s_fixed_mm < x_nut.min() else -1))


def test_linear_gradient_along_the_screw_gives_the_closed_form_integral(vmc):
    screw = build_screw(vmc, vmc.drive("Y"))
    a, b = 1.5, 4e-3  # ΔT(s) = a + b s [K], s in mm
    p = _positions(vmc, "Y")  # off the nodes
    s = screw.nut_mm(p)
    got = screw.elongation_rows(p) @ (a + b * screw.s_mm)
    sf = screw.s_fixed_mm
    want = ALPHA_STEEL * (a * (s - sf) + b * (s**2 - sf**2) / 2) * 1e3
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)


def test_linear_scale_on_a_uniformly_heated_carrier_adds_its_alpha_less_the_carriers(vmc, model):
    drive = vmc.drive("Z")
    dT = 2.3
    p = _positions(vmc, "Z")
    got = drive_error(model, drive).error_um(p, np.full(model.n, dT))
    alpha_column = vmc.materials[vmc.body(drive.scale_body).material].expansion_1_K
    want = (drive.scale_expansion_1_K - alpha_column) * dT * (drive.scale_head_at_mm + p - drive.scale_fixed_at_mm) * 1e3
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)


def test_a_pre_stretched_screw_keeps_its_length(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(edit('fixed_bearing = "x_bearing_fixed"', 'fixed_bearing = "x_bearing_fixed"\nmounting = '
                         '"pre-stretched"\nprestretch_um = 40.0'), encoding="utf-8")
    m = load_machine(path)
    screw = build_screw(m, m.drive("X"))
    p = _positions(m, "X")
    # uniform: the bearings hold the length, the screw's share is no error anywhere
    np.testing.assert_allclose(screw.elongation_rows(p) @ np.full(screw.s_mm.size, 5.0), 0.0, atol=1e-9)
    # linear gradient: the free elongation less the share of the mean the nut's distance takes
    b = 6e-3
    s, sf, so = screw.nut_mm(p), screw.s_fixed_mm, screw.s_other_mm
    free = b * (s**2 - sf**2) / 2
    whole = b * (so**2 - sf**2) / 2
    want = ALPHA_STEEL * (free - (s - sf) / (so - sf) * whole) * 1e3
    np.testing.assert_allclose(screw.elongation_rows(p) @ (b * screw.s_mm), want, rtol=1e-6)


def test_integral_weights_are_exact_and_signed():
    s = np.array([0.0, 1.0, 3.0, 4.5])
    f = s**1  # linear: exact
    assert integral_weights(s, 0.5, 4.0) @ f == pytest.approx((4.0**2 - 0.5**2) / 2, rel=1e-12)
    assert integral_weights(s, 4.0, 0.5) @ f == pytest.approx(-(4.0**2 - 0.5**2) / 2, rel=1e-12)
    with pytest.raises(ValueError, match="off the line"):
        integral_weights(s, 0.0, 5.0)


# --------------------------------------------------------------------------- the screw's thermal model

def test_screw_air_step_follows_the_lumped_time_constant(vmc):
    """At rest the screw has no heat; a step of its zone's air heats it uniformly with τ = ρ c d / (4 h)."""
    drive = vmc.drive("X")
    screw = build_screw(vmc, drive)
    mat = vmc.materials[drive.screw_material]
    tau = mat.density_kg_m3 * mat.specific_heat_J_kgK * drive.screw_diameter_mm * 1e-3 / (4 * drive.screw_h_W_m2K)
    layout = vmc.layout()
    t = np.arange(0, 4 * tau, 20.0)
    U = np.zeros((t.size, layout.n_inputs))
    U[1:, len(layout.heat_inputs) + layout.zones.index(drive.screw_zone)] = 1.0  # 1 K, ramped over the first 20 s
    T = screw.temperature_rise(t, U, initial="reference")
    # the ramp over the first step delays the step by half a step
    want = 1 - np.exp(-np.clip(t - 10.0, 0, None) / tau)
    np.testing.assert_allclose(T[1:].mean(axis=1), want[1:], atol=2e-4)
    assert np.ptp(T[-1]) < 1e-9  # uniform: no gradient without heat


def test_screw_steady_state_balances_heat_in_and_convection_out(vmc):
    drive = vmc.drive("Y")
    screw = build_screw(vmc, drive)
    layout = vmc.layout()
    u = np.zeros(layout.n_inputs)
    nut_cols = list(layout.source_columns(drive.nut))
    u[nut_cols] = RNG.uniform(0, 10, len(nut_cols))
    u[layout.source_columns(drive.fixed_bearing)[0]] = 15.0
    x = screw.steady(u)
    q_in = drive.nut_screw_W / vmc.heat_source(drive.nut).power_W * u[nut_cols].sum() + \
        drive.fixed_bearing_screw_W / vmc.heat_source(drive.fixed_bearing).power_W * 15.0
    perimeter = np.pi * drive.screw_diameter_mm * 1e-3
    q_out = drive.screw_h_W_m2K * perimeter * 1e-3 * (integral_weights(screw.s_mm, screw.s_mm[0], screw.s_mm[-1]) @ x)
    assert q_out == pytest.approx(q_in, rel=1e-9)
    assert x[np.argmin(np.abs(screw.s_mm - screw.s_fixed_mm))] > x.mean()  # the bearing end is warmest


def test_screw_error_converges_at_second_order_in_the_element_length(vmc):
    drive = vmc.drive("X")
    layout = vmc.layout()
    u = np.zeros(layout.n_inputs)
    u[layout.source_columns(drive.fixed_bearing)[0]] = 15.0
    u[list(layout.source_columns(drive.nut))] = [2.0, 8.0, 1.0, 4.0]
    p = [-333.3, 123.4]
    e = {h: build_screw(vmc, drive, h).elongation_rows(p) @ build_screw(vmc, drive, h).steady(u) for h in (20, 10, 5, 1.25)}
    e1, e2 = np.abs(e[20] - e[1.25]).max(), np.abs(e[10] - e[1.25]).max()
    e3 = np.abs(e[5] - e[1.25]).max()
    assert e1 / e2 > 3.0 and e2 / e3 > 3.0, (e1, e2, e3)


# --------------------------------------------------------------------------- the machine file

DRIVE_CASES = {
    "unknown axis": (('axis = "X"\nfeedback', 'axis = "Q"\nfeedback'), ["drives[0].axis", "'Q'"]),
    "bearing off the carrier": (('fixed_bearing = "x_bearing_fixed"', 'fixed_bearing = "y_bearing_fixed"'),
                                ["drives[0].fixed_bearing", "'y_bearing_fixed'", "'saddle'"]),
    "nut of another axis": (('nut = "x_nut"', 'nut = "y_nut"'), ["drives[0].nut", "'y_nut'"]),
    "unknown feedback": (('feedback = "rotary_encoder"\nscrew_diameter_mm = 40.0\nscrew_lead_mm = 20.0\n'
                          'screw_material = "steel"\nfixed_bearing = "x_bearing_fixed"',
                          'feedback = "glass"\nscrew_diameter_mm = 40.0\nscrew_lead_mm = 20.0\n'
                          'screw_material = "steel"\nfixed_bearing = "x_bearing_fixed"'),
                         ["drives[0].feedback", "'glass'"]),
    "pre-stretch without the mounting": (('nut = "x_nut"', 'nut = "x_nut"\nprestretch_um = 30.0'),
                                         ["drives[0].prestretch_um", "pre-stretched"]),
    "scale keys on an encoder": (('nut = "x_nut"', 'nut = "x_nut"\nscale_expansion_1_K = 8e-6'),
                                 ["drives[0].scale_expansion_1_K", "linear_scale"]),
    "scale not along the axis": (("scale_to_mm = [300.0, 520.0, 1650.0]", "scale_to_mm = [310.0, 520.0, 1650.0]"),
                                 ["drives[2].scale_to_mm", "[310.0, 520.0, 1650.0]"]),
    "head beyond the scale": (("scale_head_at_mm = 1300.0", "scale_head_at_mm = 1500.0"),
                              ["drives[2].scale_head_at_mm", "1500.0"]),
    "negative screw heat": (("nut_screw_W = 15.0\nscale_from_mm", "nut_screw_W = -1.0\nscale_from_mm"),
                            ["drives[2].nut_screw_W", "-1.0"]),
    "unknown zone": (('screw_zone = "ws_table"\n\n[[drives]]\naxis = "Y"', 'screw_zone = "attic"\n\n[[drives]]\naxis = "Y"'),
                     ["drives[0].screw_zone", "'attic'"]),
    "screw_material unknown": (('screw_material = "steel"\nfixed_bearing = "x_bearing_fixed"',
                                'screw_material = "brass"\nfixed_bearing = "x_bearing_fixed"'),
                               ["drives[0].screw_material", "'brass'"]),
}


@pytest.mark.parametrize("case", list(DRIVE_CASES))
def test_bad_drive(tmp_path, case):
    (old, new), parts = DRIVE_CASES[case]
    assert_names(load_error(tmp_path, edit(old, new)), *parts)


def test_two_drives_for_one_axis_are_refused(tmp_path):
    second = VMC800[VMC800.index("[[drives]]\naxis = \"X\""):VMC800.index("[[drives]]\naxis = \"Y\"")]
    assert_names(load_error(tmp_path, append(second)), "drives[].axis", "'X'")


def test_screw_heat_of_a_powerless_source_is_refused(tmp_path):
    text = edit('name = "x_bearing_floating"\nbody = "saddle"\nposition_mm = [430.0, -150.0, 170.0]\n'
                'size_mm = [40.0, 60.0, 60.0]\npower_W = 8.0',
                'name = "x_bearing_floating"\nbody = "saddle"\nposition_mm = [430.0, -150.0, 170.0]\n'
                'size_mm = [40.0, 60.0, 60.0]\npower_W = 0.0')
    assert_names(load_error(tmp_path, text), "drives[0].floating_bearing_screw_W", "power_W is 0")


# --------------------------------------------------------------------------- ISO 230-3, simulated

def test_moving_axis_test_error_grows_with_travel_for_encoders_not_for_the_scale(vmc, model):
    res = {a: moving_axis_test(model, a, 20000, hours=6, step_s=600) for a in "XYZ"}
    s = {a: r.summary() for a, r in res.items()}
    for a in "XY":  # the error grows steadily away from the fixed bearing, at about α ΔT_screw
        change = np.array(s[a]["final_change_um"])
        assert np.all(np.diff(change) * np.sign(change[-1]) > 0), change
        assert abs(s[a]["final_slope_um_per_m"]) > 25, s[a]
        assert s[a]["steady_state_h"] is not None
    assert abs(s["Z"]["final_slope_um_per_m"]) < 0.25 * min(abs(s[a]["final_slope_um_per_m"]) for a in "XY")
    assert axis_sign(vmc, "X") == -1 and axis_sign(vmc, "Z") == 1


def test_etve_screw_follows_the_air_with_its_first_order_lag(vmc):
    """The screw's share of the ETVE error: the free expansion through the screw's first-order lag."""
    drive = vmc.drive("X")
    mat = vmc.materials[drive.screw_material]
    tau = mat.density_kg_m3 * mat.specific_heat_J_kgK * drive.screw_diameter_mm * 1e-3 / (4 * drive.screw_h_W_m2K)
    omega = 2 * np.pi / (24 * 3600)
    loads = etve_loads(vmc, 48, 2.0, 24, 300)
    screw = build_screw(vmc, drive)
    e = screw.temperature_rise_of_loads(loads) @ screw.elongation_rows(vmc.axis("X").travel_mm).T
    length = screw.nut_mm(vmc.axis("X").travel_mm[1]) - screw.s_fixed_mm
    want = 2 * 2.0 * ALPHA_STEEL * length * 1e3 / np.hypot(1, omega * tau)
    got = np.ptp(e[loads.time_s > 24 * 3600, 1])  # the second day: the start has died out
    assert got == pytest.approx(want, rel=0.01)


def test_iso230_cli_writes_report_and_refuses_an_axis_without_drive(tmp_path, capsys):
    out = tmp_path / "iso"
    assert main(["iso230", "moving-axis", "--axis", "X", "--element-size-mm", str(H_MM), "--hours", "2",
                 "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "moving_axis_X.json").read_text())
    assert len(summary["targets_mm"]) == 5 and summary["feedback"] == "rotary_encoder"
    header = (out / "moving_axis_X.csv").read_text().splitlines()[0]
    assert header.startswith("time_h,error_um@-360") and "structure_um" in header
    assert (out / "moving_axis_X.png").stat().st_size > 0
    assert main(["iso230", "moving-axis", "--axis", "X", "--element-size-mm", str(H_MM), "--hours", "2",
                 "--out", str(out), "--no-progress"]) == 2  # no silent overwrite
    assert "--force" in capsys.readouterr().err
    text = VMC800[:VMC800.index("# ------------------------------------------------------------------ feed drives")] + \
        VMC800[VMC800.index("# ------------------------------------------------------------------ convection zones"):]
    path = tmp_path / "nodrives.toml"
    path.write_text(text, encoding="utf-8")
    assert main(["iso230", "moving-axis", "--axis", "X", "--machine", str(path), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "[[drives]]" in err and str(path) in err and not (tmp_path / "o2").exists()


def test_machine_file_without_drives_still_loads(tmp_path):
    text = VMC800[:VMC800.index("# ------------------------------------------------------------------ feed drives")] + \
        VMC800[VMC800.index("# ------------------------------------------------------------------ convection zones"):]
    path = Path(tmp_path / "m.toml")
    path.write_text(text, encoding="utf-8")
    assert load_machine(path).drives == ()
    with pytest.raises(MachineFileError, match="no \\[\\[drives\\]\\] entry"):
        moving_axis_test(build_model(load_machine(path), None, 300.0), "X", 1000.0, hours=1)
