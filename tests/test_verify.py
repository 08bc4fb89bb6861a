"""The verification studies on hand-made machines: plans, calibrations, the ambient and its correction, the part.

Every truth here is a formula written in the test (a drift linear in the pose and the time, an ambient response of
a uniform expansion plus a scale), never the code under test; each check plants an error that makes it fail.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
import pytest

from hybridcomp.chardiag.kinematic import chain_of
from hybridcomp.models import load_machine
from hybridcomp.verify import (
    AmbientOptions,
    CalibrationPlan,
    MachiningOptions,
    VerifyError,
    ambient_study,
    bores_of,
    calibrate,
    machining_study,
    part_point_mm,
    reading_offset_um,
    sensors_between,
    workspace_grid,
)


@pytest.fixture(scope="module")
def chain():
    return chain_of(load_machine("vmc800"))


@dataclass(frozen=True)
class LinearDay:
    """A drift linear in the pose and in time: ``a(t) + B (p − centre)`` with ``a`` growing 1 µm/h per direction."""

    B: np.ndarray  # 3 × axes [µm/mm]
    centre: np.ndarray
    t: np.ndarray

    def at(self, t_s, P):
        P = np.atleast_2d(P)
        return (t_s / 3600.0) * np.ones((P.shape[0], 3)) + (P - self.centre) @ self.B.T


def _day(chain, hours=15.0):
    centre = np.array([(lo + hi) / 2 for lo, hi in chain.travel_mm])
    B = np.array([[0.02, 0.0, 0.0], [0.0, -0.03, 0.0], [0.0, 0.0, 0.01]])
    return LinearDay(B, centre, np.arange(0.0, hours * 3600.0 + 1, 60.0))


def test_plan_is_a_serpentine_over_the_travel(chain):
    plan = CalibrationPlan((3, 2, 2), seconds_per_point=30.0, margin=0.1)
    P = plan.poses_mm(chain.travel_mm)
    assert P.shape == (12, 3) and plan.duration_s() == 360.0
    assert len({tuple(p) for p in P}) == 12  # every pose once
    steps = np.abs(np.diff(P, axis=0))
    assert np.all(np.count_nonzero(steps > 1e-9, axis=1) == 1)  # one axis moves from one pose to the next
    for i, (lo, hi) in enumerate(chain.travel_mm):
        assert P[:, i].min() == pytest.approx(lo + 0.1 * (hi - lo)) and P[:, i].max() == pytest.approx(hi - 0.1 * (hi - lo))
    with pytest.raises(VerifyError, match="at least 2 levels"):
        CalibrationPlan((3, 1, 2))
    with pytest.raises(VerifyError, match="noise_um"):
        CalibrationPlan(noise_um=-1.0)


def test_calibration_measures_each_pose_at_its_own_time(chain):
    day = _day(chain)
    plan = CalibrationPlan((2, 2, 2), seconds_per_point=360.0, noise_um=0.0)
    m = calibrate(day.at, plan, chain.travel_mm, 3600.0, np.random.default_rng(0))
    assert np.allclose(m.time_s, 3600.0 + 360.0 * np.arange(8))
    # the hand formula: 1 µm/h plus the pose's linear part; a calibration taken at one instant misses the 0.7 h
    expected = (m.time_s / 3600.0)[:, None] + (m.poses_mm - day.centre) @ day.B.T
    assert np.allclose(m.error_um, expected, atol=1e-12)
    assert not np.allclose(m.error_um, 1.0 + (m.poses_mm - day.centre) @ day.B.T, atol=0.5)
    noisy = calibrate(day.at, CalibrationPlan((4, 4, 4), noise_um=2.0), chain.travel_mm, 0.0, np.random.default_rng(1))
    clean = calibrate(day.at, CalibrationPlan((4, 4, 4), noise_um=0.0), chain.travel_mm, 0.0, np.random.default_rng(1))
    assert np.std(noisy.error_um - clean.error_um) == pytest.approx(2.0, rel=0.15)


def test_sensors_between_averages_the_calibration(chain):
    s = {"time_s": np.arange(0.0, 100.0, 10.0), "degC": np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])}
    assert np.allclose(sensors_between(s, 20.0, 40.0), [3.0, 6.0])
    assert np.allclose(sensors_between(s, 25.0, 26.0), [3.0, 6.0])  # no reading inside: the next one


def test_reading_offset_of_a_tracker_and_an_artefact_by_hand(chain):
    # vmc800: X and Y move the table (side −1), Z the spindle (+1): the tool at X = +200 mm stands 200 mm on the
    # −x side of the table's centre.  3 K warmer, the cast-iron table top (10.5e-6 1/K) carries the point under the
    # tool 200 mm · 10.5e-6 · 3 = 6.3 µm further out (−x), which a tracker on the table reads; a steel artefact
    # (11.5e-6) has grown 6.9 µm there itself, so it reads +0.6 µm.  In z the table does not grow (the height
    # above it is air); the artefact's feature 100 mm below its reference has moved 3.45 µm down: +3.45 µm read
    assert chain.sides == (-1.0, -1.0, 1.0)
    P = np.array([[200.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, -100.0]])
    assert np.allclose(part_point_mm(chain, P), [[-200, 0, 0], [0, -100, 0], [0, 0, -100]])
    tracker = reading_offset_um(P, chain, 10.5e-6, 0.0, 3.0)
    assert np.allclose(tracker, [[-6.3, 0, 0], [0, -3.15, 0], [0, 0, 0]], atol=1e-9)
    steel = reading_offset_um(P, chain, 10.5e-6, 11.5e-6, 3.0)
    assert np.allclose(steel, [[0.6, 0, 0], [0, 0.3, 0], [0, 0, 3.45]], atol=1e-9)


def _uniform(chain, alpha_per_K, z_scale_per_K=0.0):
    """A machine that grows uniformly (α per K about the workspace centre) and whose Z scale adds its own slope."""

    def response(P):
        r = alpha_per_K * part_point_mm(chain, P) * 1e3
        r[:, 2] += z_scale_per_K * (np.atleast_2d(P)[:, 2] - 0.0) * 1e3
        return r

    return response


def test_ambient_correction_restores_the_working_temperature_functions(chain):
    day = _day(chain)
    real = _uniform(chain, 1e-6, z_scale_per_K=-3.5e-6)
    opts = AmbientOptions(plan=CalibrationPlan((5, 5, 4)), state_h=2.0, ambient_K=3.0, sigmas_um=(0.0, 1.0),
                          air_noise_K=0.0, artefacts=(("laser tracker", 0.0), ("steel artefact", 11.5e-6)),
                          grid_levels=(3, 3, 3))
    r = ambient_study(day, real, real, chain, 10.5e-6, opts)
    rows = {(x["artefact"], x["sigma_um"]): x for x in r["rows"]}
    tracker = rows[("laser tracker", 0.0)]
    # uncorrected, the tracker's functions carry the soak: 3 K · (1 + 10.5) µm/m over up to 400 mm in x
    assert tracker["uncorrected"]["max_um"] > 3 * 11.5e-6 * 400.0 * 1e3
    assert tracker["at working temperature"]["max_um"] < 1e-9  # a linear drift is inside the cubic functions
    assert tracker["corrected_vs_reference_max_um"] < 1e-9
    # the steel artefact grows nearly as the table does: less to correct, and the correction still exact
    steel = rows[("steel artefact", 0.0)]
    assert steel["uncorrected"]["max_um"] < tracker["uncorrected"]["max_um"]
    assert steel["corrected_vs_reference_max_um"] < 1e-9
    # noise: the corrected functions differ from the reference's by the correction alone, whatever the noise
    assert rows[("laser tracker", 1.0)]["corrected_vs_reference_max_um"] < 1e-9
    assert rows[("laser tracker", 1.0)]["at working temperature"]["max_um"] > 0.3
    # a model that does not know the Z scale's own slope leaves it: 3 K · 3.5 µm/m · 275 mm ≈ 2.9 µm
    wrong = ambient_study(day, real, _uniform(chain, 1e-6), chain, 10.5e-6, opts)
    miss = {(x["artefact"], x["sigma_um"]): x for x in wrong["rows"]}[("laser tracker", 0.0)]
    assert miss["corrected_vs_reference_max_um"] == pytest.approx(3 * 3.5e-6 * 275.0 * 1e3, rel=1e-6)


def test_the_air_thermometer_noise_enters_the_correction(chain):
    day = _day(chain)
    real = _uniform(chain, 10e-6)
    opts = AmbientOptions(plan=CalibrationPlan((3, 3, 3)), ambient_K=3.0, sigmas_um=(0.0,), air_noise_K=0.2,
                          artefacts=(("laser tracker", 0.0),), degree=2, grid_levels=(3, 3, 3))
    row = ambient_study(day, real, real, chain, 10.5e-6, opts, seed=3)["rows"][0]
    # the residual is (measured − true air) times the response: at most a few times 0.2 K · 20.5 µm/m · 500 mm
    assert 1e-6 < row["corrected_vs_reference_max_um"] < 3 * 0.2 * 20.5e-6 * 520.0 * 1e3


def test_bores_are_cut_over_the_plate_in_time(chain):
    pose = {"X": 0.0, "Y": 0.0, "Z": 50.0}
    b = bores_of(MachiningOptions(columns=3, rows=2, span=0.5, first_h=1.0, every_h=2.0), chain, pose, 16 * 3600.0)
    assert np.allclose(b.time_s / 3600.0, [1, 3, 5, 7, 9, 11])
    assert b.place == ((0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (0, 1))
    assert np.allclose(b.positions_mm[:, 2], 50.0)
    assert np.allclose(sorted(set(b.positions_mm[:, 0])), [-200.0, 0.0, 200.0])
    with pytest.raises(VerifyError, match="after the day"):
        bores_of(MachiningOptions(columns=5, rows=4), chain, pose, 15 * 3600.0)


def test_machined_part_deviations_and_distances(chain):
    day = _day(chain)
    pose = {"X": 0.0, "Y": 0.0, "Z": 0.0}
    opts = MachiningOptions(columns=3, rows=2, span=0.5, first_h=0.5, every_h=1.0)
    comps = {
        "no compensation": lambda t, P: np.zeros((len(t), 3)),
        "at one pose": lambda t, P: day.at(0.0, np.zeros((1, 3))) + (np.asarray(t) / 3600.0)[:, None],
        "everywhere": lambda t, P: np.vstack([day.at(ti, P[i:i + 1]) for i, ti in enumerate(t)]),
    }
    r = machining_study(day, comps, chain, pose, opts)["results"]
    assert r["everywhere"]["largest_position_um"] < 1e-12
    # one pose leaves the position-dependent part: at X = ±200 mm, 0.02 µm/mm · 200 mm = 4 µm in x; at
    # Y = ±162.5 mm, 0.03 · 162.5 = 4.875 µm in y
    assert r["at one pose"]["largest_position_um"] == pytest.approx(np.hypot(4.0, 4.875), rel=1e-9)
    # the distance between neighbouring bores 200 mm apart in x: their x deviations differ by 0.02 · 200 = 4 µm
    # (the table side: a bore further +x on the part is cut at a lower X), plus the hour between the cuts
    x_pairs = r["at one pose"]["distance_um"][:4]
    assert np.allclose(np.abs(x_pairs), 4.0)
    assert r["no compensation"]["largest_distance_um"] > 4.0


@dataclass(frozen=True)
class WarmingDay:
    """A drift that follows one sensor: ``(T1 − 20 K) · (a + B (p − centre))``, T1 warming over 3 h."""

    centre: np.ndarray
    t: np.ndarray

    @staticmethod
    def T1(t_s):
        return 20.0 + 5.0 * (1.0 - np.exp(-np.asarray(t_s, float) / (3 * 3600.0)))

    def at(self, t_s, P):
        P = np.atleast_2d(P)
        field = np.array([1.0, -2.0, 3.0]) + (P - self.centre) @ np.diag([0.01, 0.004, -0.006]).T
        return (self.T1(t_s) - 20.0) * field

    @property
    def truth(self):  # at the model's pose (the centre) over the day
        return (self.T1(self.t) - 20.0)[:, None] * np.array([1.0, -2.0, 3.0])


def test_volumetric_study_fits_on_half_the_states_and_judges_on_the_rest(chain):
    from hybridcomp.verify import VolumetricOptions, volumetric_study

    centre = np.array([(lo + hi) / 2 for lo, hi in chain.travel_mm])
    day = WarmingDay(centre, np.arange(0.0, 15 * 3600.0 + 1, 60.0))
    t = np.arange(0.0, 15 * 3600.0 + 1, 30.0)
    rng = np.random.default_rng(5)
    # T2 an air sensor that knows nothing of the drift
    sensors = {"time_s": t, "degC": np.column_stack([day.T1(t), 20.0 + 0.5 * np.sin(t / 7000.0)
                                                     + 0.01 * rng.standard_normal(t.size)])}
    opts = VolumetricOptions(plan=CalibrationPlan((5, 5, 4), seconds_per_point=5.0, noise_um=0.2), every_h=1.0,
                             grid_levels=(3, 3, 3))
    late = lambda tt, P: np.vstack([day.at(ti - 1800.0, P[i:i + 1]) for i, ti in enumerate(tt)])  # noqa: E731
    study = volumetric_study(day, late, sensors, ["T1", "T2"], chain, opts, np.random.default_rng(0))
    r = study.summary
    assert study.model.inputs == ("T1",) and len(study.calibrations) == 15
    roles = [c["role"] for c in r["calibrations"]]
    assert len(roles) == 15 and roles[:4] == ["fit", "held out", "fit", "held out"]
    # the drift's length (3.74 µm/K) grows at 6.2 µm/h at first (5 K / 3 h), 0.06 µm/h at 14 h: warming, then hot
    phases = [c["phase"] for c in r["calibrations"]]
    assert phases[0] == "warming" and phases[-1] == "hot" and "cooling" not in phases
    assert r["model"]["inputs"] == ["T1"]
    assert r["grid_points"] == workspace_grid(chain.travel_mm, (3, 3, 3)).shape[0] == 27
    held = r["held_out"]
    # the map knows T1, so it follows the drift to the calibrations' noise; tables 30 min late miss the warming
    assert held["volumetric model"]["max_um"] < 0.5
    assert held["support-point tables"]["max_um"] > 1.0
    with pytest.raises(VerifyError, match="overlap"):
        volumetric_study(day, late, sensors, ["T1", "T2"], chain,
                         VolumetricOptions(plan=CalibrationPlan((5, 5, 4), seconds_per_point=60.0), every_h=1.0),
                         np.random.default_rng(0))


@pytest.mark.parametrize("argv, words", [
    (["--bores", "5", "4"], "20 bores every 1 h from 0.5 h end at 19.5 h, after the day's 15 h"),
    (["--bores", "1", "1"], "at least 2 × 1 bores"),
    (["--seconds-per-point", "60"], "would overlap"),
    (["--day-hours", "3"], "the day (3 h) holds 3 calibrations"),
    (["--day-hours", "17"], "--day-hours must be in (0, 16]"),
    (["--noise-um", "-1"], "noise_um must be a finite number ≥ 0"),
    (["--plan-levels", "5", "1", "4"], "at least 2 levels"),
    (["--plan-levels", "5", "5"], "2 levels [5, 5] for the axes X, Y, Z of vmc800: give one per axis"),
    (["--machine", "no_such_machine"], "no_such_machine"),
    (["--criterion", "aic"], "invalid choice"),
])
def test_verify_refuses_a_study_that_cannot_run_before_any_file(tmp_path, capsys, argv, words):
    from hybridcomp.cli import main

    out = tmp_path / "v"
    with pytest.raises(SystemExit) if "invalid choice" in words else contextlib.nullcontext():
        assert main(["verify", "--out", str(out), *argv]) == 2
    assert words in capsys.readouterr().err
    assert not out.exists()



@pytest.mark.slow
def test_verify_end_to_end_on_a_short_day(tmp_path, caplog):
    """The command as a user types it, on a short day (150 mm, 5 h): every study, the report, the plots.

    The criteria are the benchmark's (``benchmarks/verification.py``, the whole day): the ambient correction restores
    the working-temperature functions within 0.5 µm, the volumetric compensation keeps the bores at ≤ 0.3 × the
    one-pose compensation's largest deviation.
    """
    import json
    import logging

    pytest.importorskip("sqlalchemy", reason="the daemon's CD database needs SQLAlchemy (pip install 'hybridcomp[db]')")
    from hybridcomp.cli import main

    out = tmp_path / "v"
    assert main(["verify", "--out", str(out), "--element-size-mm", "150", "--day-hours", "5", "--seconds-per-point",
                 "5", "--bores", "3", "2", "--bore-every-hours", "0.75", "--sigmas-um", "0", "1"]) == 0
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], "verify logged errors"
    s = json.loads((out / "summary.json").read_text())
    assert [c["role"] for c in s["volumetric"]["calibrations"]] == ["fit", "held out"] * 2 + ["fit"]
    assert set(s["volumetric"]["held_out"]) == {"volumetric model", "support-point tables", "identified at the state"}
    rows = s["ambient"]["rows"]
    assert {(r["artefact"], r["sigma_um"]) for r in rows} == {(a, g) for a in ("laser tracker", "steel artefact")
                                                             for g in (0.0, 1.0)}
    for r in rows:
        assert r["uncorrected"]["max_um"] > 5.0  # 3 K of soak is seen
        if r["sigma_um"] == 0:
            assert r["corrected_vs_reference_max_um"] <= 0.5
    part = s["machining"]
    assert len(part["bores"]) == 6 and part["ratio_volumetric_to_one_pose"] <= 0.3
    assert part["largest"]["hybrid at one pose"]["largest_position_um"] > 2.0
    report = (out / "report.md").read_text()
    assert "| hybrid volumetric |" in report and "![the part](part.png)" in report
    assert len(part["distances"]) == 7 and "### Distances between neighbouring bores" in report  # 3 × 2 bores
    # nothing lost: the fitted model in its stored form and every calibration point as a campaign records it
    from hybridcomp.chardiag.thermal_map import from_dict

    assert from_dict(json.loads((out / "thermal_map.json").read_text())).n_states == 3
    rows = (out / "calibrations.csv").read_text().splitlines()
    assert rows[0].startswith("calibration,role,time_s,X_mm,Y_mm,Z_mm,dx_um,dy_um,dz_um,T1_degC")
    assert len(rows) == 1 + 5 * 100
    assert (out / "part.png").stat().st_size > 10_000 and (out / "volumetric.png").stat().st_size > 5_000
    assert (out / "ambient.png").stat().st_size > 5_000 and "![the ambient during verification](ambient.png)" in report


def test_lagged_sensors_are_offered_as_inputs(chain):
    """A drift that follows T1 an hour late: the map picks T1's 1 h lag when it is offered, and does far better."""
    from hybridcomp.verify import VolumetricOptions, volumetric_study, with_lags

    t = np.arange(0.0, 15 * 3600.0 + 1, 30.0)
    T1 = 20.0 + 4.0 * (np.sin(2 * np.pi * t / (6 * 3600.0)) > 0)  # the spindle on and off every 3 h
    s, names = with_lags({"time_s": t, "degC": T1[:, None]}, ["T1"], (1.0,))
    assert names == ["T1", "T1_lag1h"]
    lagged = s["degC"][:, 1]
    # the hand formula of a first-order lag: 1 − e^(−1) of a step after one time constant
    k = np.searchsorted(t, 3600.0)
    assert lagged[k] == pytest.approx(20.0 + 4.0 * (1 - np.exp(-1.0)), abs=0.01)

    @dataclass(frozen=True)
    class LagDay:
        t: np.ndarray

        @property
        def truth(self):
            return (np.interp(self.t, t, lagged) - 20.0)[:, None] * np.array([1.0, 0.0, 2.0])

        def at(self, t_s, P):
            return (np.interp(t_s, t, lagged) - 20.0) * np.tile([1.0, 0.0, 2.0], (np.atleast_2d(P).shape[0], 1))

    day = LagDay(t)
    opts = dict(plan=CalibrationPlan((5, 5, 4), seconds_per_point=3.0, noise_um=0.1), every_h=0.5,
                grid_levels=(2, 2, 2), max_inputs=1)
    sensors = {"time_s": t, "degC": T1[:, None]}
    table = lambda tt, P: np.zeros((len(tt), 3))  # noqa: E731
    static = volumetric_study(day, table, sensors, ["T1"], chain, VolumetricOptions(**opts), np.random.default_rng(0))
    arx = volumetric_study(day, table, sensors, ["T1"], chain, VolumetricOptions(lags_h=(1.0,), **opts),
                           np.random.default_rng(0))
    assert arx.model.inputs == ("T1_lag1h",)
    assert arx.summary["held_out"]["volumetric model"]["max_um"] < 0.3 * static.summary["held_out"]["volumetric model"]["max_um"]
