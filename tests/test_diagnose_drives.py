"""The feed drives' diagnosis (:mod:`hybridcomp.diagnose.drives`): planted drive effects named from probes.

The planted truth is computed independently of the diagnosis' sensitivities: the real machine's drive (its
``[[drives]]`` table edited as the scenario's disturbances edit it) through :class:`hybridcomp.fem.drives.DriveError`
on the FE field of the nominal model's first block (the basis times its state) and the edited screw's own 1D model;
the structure's drift from the nominal pose-aware model (the edits change no FE structure).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import hybridcomp as hc
from hybridcomp.diagnose.data import DatasetError
from hybridcomp.diagnose.drives import (
    DriveCandidate,
    diagnose_drives,
    drive_candidates,
    make_probes,
    probe_cycles,
    read_probes,
)

NOISE_UM = 0.3


# ------------------------------------------------------------------------------------------ without an FE model
def _synthetic(theta: float, seed: int = 0):
    """Probes of 8 cycles × 7 poses whose dx residual is ``theta`` × a known sensitivity + offsets + noise."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([k * 7200.0 + 10.0 * np.arange(7) for k in range(8)])
    x = np.tile(np.linspace(-300, 300, 7), 8)
    P = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    amp = np.repeat(np.linspace(1.0, 3.0, 8), 7)  # the drive warms over the day
    s_true = amp * x / 100.0  # µm per unit at each probe
    s_other = amp * (x / 300.0) ** 2 * 3.0  # another shape on the same drive
    offsets = np.repeat(rng.normal(0, 5, (8, 3)), 7, axis=0)  # each cycle's uniform offset
    measured = offsets + rng.normal(0, NOISE_UM, (t.size, 3))
    measured[:, 0] += theta * s_true
    probes = make_probes(t, P, ("X", "Y", "Z"), measured, np.zeros((t.size, 3)))
    cands = [DriveCandidate("nut_heat", "X", "X nut heat", "factor [-]", 1.0, 0.0, 10.0, 0, s_true),
             DriveCandidate("bearing_held", "X", "X bearing held", "held share [-]", 0.0, 0.0, 1.0, 0, s_other)]
    return probes, cands


def test_synthetic_effect_named_with_its_parameter():
    probes, cands = _synthetic(1.5)
    d = diagnose_drives(probes, cands)
    assert [(f.candidate.kind, f.candidate.axis) for f in d.named] == [("nut_heat", "X")]
    f = d.named[0]
    assert f.value == pytest.approx(2.5, abs=3 * f.sigma + 0.02)  # nominal 1 + the planted 1.5
    assert 0 < f.sigma < 0.05 and f.validation_gain > 0.8
    assert d.rms_um["dx_um"]["after"] < 1.5 * NOISE_UM < d.rms_um["dx_um"]["before"]
    assert d.n_cycles == 8 and d.n_probes == 56


def test_synthetic_no_effect_names_none():
    probes, cands = _synthetic(0.0)
    d = diagnose_drives(probes, cands)
    assert d.named == () and "no drive effect named" in d.message
    # the offsets alone (5 µm per cycle) are the observer's, not a drive's: nothing left above the noise
    assert d.rms_um["dx_um"]["before"] < 1.5 * NOISE_UM


def test_synthetic_parameter_outside_the_physical_range_is_not_named():
    probes, cands = _synthetic(-3.0)  # a factor of -2 on the nut's heat: no physical nut does that
    d = diagnose_drives(probes, cands)
    assert all(f.candidate.kind != "nut_heat" for f in d.named)


def test_probe_cycles_split_at_gaps():
    assert probe_cycles(np.array([0.0, 5.0, 10.0, 4000.0, 4005.0, 9000.0])).tolist() == [0, 0, 0, 1, 1, 2]


def test_read_probes_table_and_monitor_trace(vmc, tmp_path, write_csv):
    p = write_csv(tmp_path / "probes.csv", ["time_s", "x_mm", "y_mm", "z_mm", "dx_um", "dy_um", "dz_um"],
                  [[0, 1, 2, 3, 0.5, "", 1.5], [10, -1, 2, 3, 0.25, 0.5, ""], [20, 0, 0, 0, "", "", ""]])
    pr = read_probes(p, vmc)
    assert pr.n == 2 and pr.axes == ("X", "Y", "Z") and pr.cycle.tolist() == [0, 0]
    assert np.isnan(pr.measured_um[0, 1]) and pr.measured_um[1, 0] == 0.25 and pr.predicted_um is None
    trace = write_csv(tmp_path / "trace.csv", ["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", "probe_dx_um",
                                               "probe_dy_um", "probe_dz_um"],
                      [[0, 0, 0, 0, 0, "", "", ""], [1, 380, 0, 0, 0, 1.0, 2.0, 3.0], [2, 0, 0, 0, 0, "", "", ""]])
    pt = read_probes(trace, vmc)
    assert pt.n == 1 and pt.positions_mm[0].tolist() == [380, 0, 0] and pt.measured_um[0].tolist() == [1, 2, 3]
    bad = write_csv(tmp_path / "bad.csv", ["time_s", "x_mm", "y_mm", "z_mm", "dx_um", "dy_um", "dz_um"],
                    [[0, "a", 2, 3, 0.5, 1, 1.5]])
    with pytest.raises(DatasetError, match=r"bad\.csv, line 2: column 'x_mm' = 'a'"):
        read_probes(bad, vmc)
    with pytest.raises(DatasetError, match="lack the column 'dz_um'"):
        read_probes(write_csv(tmp_path / "few.csv", ["time_s", "x_mm", "y_mm", "z_mm", "dx_um", "dy_um"], [[0] * 6]),
                    vmc)


def test_scenario_plants_a_seized_bearing(vmc, tmp_path):
    from hybridcomp.scenario import DISTURBANCES, POSITION_DEPENDENT, real_machine_file

    assert {"nut heat", "scale expansion", "bearing seized"} <= set(POSITION_DEPENDENT)
    real = hc.load_machine(real_machine_file(vmc, DISTURBANCES["bearing seized"], tmp_path / "real.toml"))
    mounting = {d.axis: d.mounting for d in real.drives}
    assert mounting == {"X": "fixed-floating", "Y": "pre-stretched", "Z": "fixed-floating"}
    assert {d.axis: d.mounting for d in vmc.drives}["Y"] == "fixed-floating"


# ---------------------------------------------------------------------------- on the coarse pose-aware model
@pytest.fixture(scope="module")
def day(vmc, model_200mm, pose_roms_200mm):
    """The nominal models on a 16 h example day, probing cycles every 2 h over the star of poses, and a truth maker."""
    from hybridcomp.fem.drives import DriveError, build_screw, carrier_line
    from hybridcomp.fem.iso230 import axis_sign
    from hybridcomp.fem.operators import ThermalOperators
    from hybridcomp.rom.poses import drift_along
    from hybridcomp.rom.reduced import ReducedModel
    from hybridcomp.scenario import probe_poses

    rom, prom = pose_roms_200mm
    loads = hc.example_loads(vmc, 16.0, 300.0)
    t = loads.time_s
    poses = probe_poses(vmc, vmc.default_pose_mm())
    times = np.concatenate([t0 + 6.0 * np.arange(len(poses)) for t0 in np.arange(1800.0, t[-1] - 600.0, 7200.0)])
    P = np.tile(poses, (times.size // len(poses), 1))

    def at(A):
        return np.column_stack([np.interp(times, t, A[:, i]) for i in range(A.shape[1])])

    r = rom.order
    states = ReducedModel(ThermalOperators(M=prom.M[:r, :r], K=prom.K[:r, :r], H=prom.H[:, :r, :r],
                                           h_W_m2K=prom.h_W_m2K, B=prom.B[:r], Hb=prom.Hb[:r], C=np.eye(r),
                                           input_names=prom.input_names,
                                           output_names=tuple(f"z{i}" for i in range(r))))

    def truth(edits: dict, loads_real=loads, seed: int = 0) -> np.ndarray:
        """The real machine's drift at the probes [µm]: drives edited (``{axis: {field: value}}``), given loads."""
        U = prom.layout().inputs(loads_real)
        Y, _ = prom.integrate(t, U)
        D = drift_along(prom, at(Y), P, feedback=False)
        x_fe = at(states.integrate(t, U)[0]) @ rom.V.T  # the FE field at the model's pose
        for dr in vmc.drives:
            real = dataclasses.replace(dr, **edits.get(dr.axis, {}))
            screw = None if real.feedback == "linear_scale" else build_screw(vmc, real)
            err = DriveError(real, screw, carrier_line(model_200mm, real))
            p = P[:, [a.name for a in vmc.axes].index(dr.axis)]
            e = np.einsum("ij,ij->i", x_fe, err.fe_rows(p))
            if screw is not None:
                e += np.einsum("ij,ij->i", at(screw.temperature_rise(t, U)), err.screw_rows(p))
            D[:, vmc.axis(dr.axis).direction] += axis_sign(vmc, dr.axis) * e
        return D + np.random.default_rng(seed).normal(0.0, NOISE_UM, D.shape)

    def probes(measured):
        return make_probes(times, P, [a.name for a in vmc.axes], measured)

    return {"prom": prom, "loads": loads, "truth": truth, "probes": probes, "at": at, "positions": P}


def _diagnose(vmc, day, edits=None, loads_real=None, swap=None):
    measured = day["truth"](edits or {}, day["loads"] if loads_real is None else loads_real)
    pr = day["probes"](measured)
    cands, pred = drive_candidates(vmc, day["prom"], day["loads"], pr)
    if swap is not None:
        cands = swap(cands)
    return diagnose_drives(pr, cands, pred, noise_um=NOISE_UM)


def _named(d) -> dict:
    return {(f.candidate.kind, f.candidate.axis): f for f in d.named}


@pytest.mark.slow
def test_truth_of_the_nominal_machine_is_the_pose_aware_model(vmc, day):
    from hybridcomp.rom.poses import drift_along

    prom = day["prom"]
    Y, _ = prom.integrate(day["loads"].time_s, prom.layout().inputs(day["loads"]))
    model = drift_along(prom, day["at"](Y), day["positions"])
    truth = day["truth"]({}) - np.random.default_rng(0).normal(0.0, NOISE_UM, model.shape)
    assert np.abs(truth - model).max() < 0.1  # the drives' outputs are linear between 17 points; the truth exact


@pytest.mark.slow
def test_nominal_and_non_drive_disturbances_name_no_drive_effect(vmc, day):
    from hybridcomp.models.layout import Loads
    from hybridcomp.scenario import DISTURBANCES, planted_air

    assert _diagnose(vmc, day).named == ()
    swing = _diagnose(vmc, day, loads_real=planted_air(vmc, day["loads"], DISTURBANCES["ambient swing"]))
    assert swing.named == () and swing.rms_um["dx_um"]["before"] > 1.0  # the swing does show between the poses
    loads = day["loads"]
    V = loads.values.copy()
    for c in vmc.layout().source_columns("spindle_motor"):
        V[:, c] *= 0.6
    assert _diagnose(vmc, day, loads_real=Loads(loads.time_s, V, loads.names)).named == ()
    # warmer workspace air warms the screws: the competitor that is not a drive effect explains it
    ws = _diagnose(vmc, day, loads_real=planted_air(vmc, day["loads"], DISTURBANCES["workspace air"]))
    assert ws.named == () and {f.candidate.kind for f in ws.others} == {"workspace_offset"}


@pytest.mark.slow
def test_nut_heat_named_on_both_screws(vmc, day):
    d = _diagnose(vmc, day, {"X": {"nut_screw_W": 37.5}, "Y": {"nut_screw_W": 37.5}})
    named = _named(d)
    assert set(named) == {("nut_heat", "X"), ("nut_heat", "Y")}
    for f in named.values():  # 37.5 W for the nominal 15 W
        assert f.value == pytest.approx(2.5, rel=0.2) and f.validation_gain > 0.5


@pytest.mark.slow
def test_scale_expansion_named(vmc, day):
    d = _diagnose(vmc, day, {"Z": {"scale_expansion_1_K": 11.5e-6}})
    named = _named(d)
    assert set(named) == {("scale_expansion", "Z")}
    f = named["scale_expansion", "Z"]
    assert f.value == pytest.approx(11.5, rel=0.2) and f.candidate.nominal == pytest.approx(8.0)


@pytest.mark.slow
def test_seized_bearing_named(vmc, day):
    d = _diagnose(vmc, day, {"Y": {"mounting": "pre-stretched"}})
    named = _named(d)
    assert set(named) == {("bearing_held", "Y")}
    assert named["bearing_held", "Y"].value == pytest.approx(1.0, rel=0.2)


@pytest.mark.slow
def test_planted_effect_missed_with_a_wrong_sensitivity(vmc, day):
    """The X nut's sensitivity taken at the mirrored X positions (the screw's line the wrong way round): missed."""
    mirrored = day["probes"](np.zeros((day["positions"].shape[0], 3)))
    mirrored = dataclasses.replace(mirrored, positions_mm=mirrored.positions_mm * np.array([-1.0, 1.0, 1.0]))
    wrong = {c.key: c for c in drive_candidates(vmc, day["prom"], day["loads"], mirrored)[0]}

    def swap(cands):
        return [wrong[c.key] if c.key == ("nut_heat", "X") else c for c in cands]

    edits = {"X": {"nut_screw_W": 37.5}}
    right = _named(_diagnose(vmc, day, edits))
    assert right["nut_heat", "X"].value == pytest.approx(2.5, rel=0.2)
    d = _diagnose(vmc, day, edits, swap=swap)
    assert ("nut_heat", "X") not in _named(d)
    # the mirrored shape fits best at a negative factor: no nut does that, and the report says what is left
    assert "dx_um: its best fit is out of the physical range" in d.message


@pytest.mark.slow
def test_cli_names_the_drive_effect_in_the_report_and_the_extended_machine(vmc, day, pose_roms_200mm, tmp_path,
                                                                           write_csv):
    """``hybridcomp diagnose --probes --pose-rom``: the drives' section, summary and machine file."""
    from hybridcomp.cli import main
    from hybridcomp.rom import save_rom

    rom, prom = pose_roms_200mm
    loads = day["loads"]
    sim = rom.simulate(loads)  # the record at the model's pose: the nominal model's, no discrepancy there
    sensors = [s.name for s in vmc.sensors]
    header = ["time_s", *loads.names, *(f"{s}_degC" for s in sensors), "dx_um", "dy_um", "dz_um"]
    data = write_csv(tmp_path / "measured.csv", header,
                     np.column_stack([loads.time_s, loads.values, sim.sensors_degC, sim.drift_um]).tolist())
    measured = day["truth"]({"X": {"nut_screw_W": 37.5}})
    P = day["positions"]
    t = day["probes"](measured).time_s
    probes = write_csv(tmp_path / "probes.csv", ["time_s", "x_mm", "y_mm", "z_mm", "dx_um", "dy_um", "dz_um"],
                       np.column_stack([t, P, measured]).tolist())
    rom_path, prom_path = save_rom(tmp_path / "rom.npz", rom), save_rom(tmp_path / "poses.npz", prom)
    args = ["diagnose", "--machine", "vmc800", "--data", str(data), "--rom", str(rom_path), "--element-size-mm", "200",
            "--no-plots", "--effects", "workspace_offset"]
    assert main(args + ["--out", str(tmp_path / "x"), "--pose-rom", str(prom_path)]) == 2  # no --probes
    assert main(args + ["--out", str(tmp_path / "x"), "--probes", str(probes)]) == 2  # no --pose-rom
    assert main(args + ["--out", str(tmp_path / "x"), "--probes", str(probes), "--pose-rom", str(rom_path)]) == 2
    out = tmp_path / "out"
    assert main(args + ["--out", str(out), "--probes", str(probes), "--pose-rom", str(prom_path)]) == 0
    import json

    named = json.loads((out / "summary.json").read_text())["drives"]["named"]
    assert [(n["kind"], n["axis"]) for n in named] == [("nut_heat", "X")]
    assert named[0]["value"] == pytest.approx(2.5, rel=0.2)
    assert "## Feed drives (probes at several poses)" in (out / "report.md").read_text()
    ext = hc.load_machine(out / "machine_extended.toml")
    nut = {d.axis: d.nut_screw_W for d in ext.drives}
    assert nut["X"] == pytest.approx(15.0 * named[0]["value"], rel=1e-4) and nut["Y"] == 15.0


def test_synthetic_candidates_not_told_apart_are_alternatives():
    probes, cands = _synthetic(1.5)
    twin = DriveCandidate("screw_expansion", "X", "X screw alpha", "alpha [um/(m K)]", 11.5, 0.0, 30.0, 0,
                          cands[0].sensitivity_um * 0.1 + 0.002 * np.sin(np.arange(probes.n)))
    d = diagnose_drives(probes, cands + [twin])
    (f,) = d.named
    assert f.alternatives == ((twin.label,) if f.candidate is cands[0] else (cands[0].label,))
    # the twin's shape is the planted one to 0.2 %: its fit is 15 µm/(m K) off its nominal, ten times the factor's
    fits = {c.candidate.kind: c for c in d.fits}
    assert fits["screw_expansion"].value == pytest.approx(11.5 + 15.0, abs=0.5)
