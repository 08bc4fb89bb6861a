"""CNC forms of a volumetric table: the generic CSV and JSON, the Siemens 840D sl K3 lines and CEC tables; read back,
compared with the table (compensation = −drift) and refused through the guard."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridcomp.chardiag import table_export as tx
from hybridcomp.chardiag.guard import OffsetGuardError
from hybridcomp.rom.volumetric import FeedbackTable, SupportGrid, VolumetricTable, interpolate, table_from_dict

AXES = ("X", "Y", "Z")
POS = ((-400.0, -100.0, 0.0, 400.0), (-325.0, 50.0, 325.0), (-275.0, 0.0, 275.0))
POSE = (0.0, 50.0, 0.0)
DRIVES = (("X", 0, -1.0), ("Y", 1, -1.0), ("Z", 2, 1.0))


def make_table(rng, scale: float = 10.0, separable: bool = False) -> VolumetricTable:
    grid = SupportGrid(AXES, POS, POSE)
    if separable:  # a sum of one function per axis: what per-axis tables represent exactly
        parts = [rng.normal(size=(len(p), 3)) * scale for p in POS]
        S = parts[0][:, None, None] + parts[1][None, :, None] + parts[2][None, None, :]
    else:
        S = rng.normal(size=grid.shape + (3,)) * scale
    fb = tuple(FeedbackTable(a, np.linspace(p[0], p[-1], 9), rng.normal(size=9) * 2, d, s)
               for (a, d, s), p in zip(DRIVES, POS))
    return VolumetricTable(grid, 3600.0, S, fb)


def test_csv_has_the_compensation_at_every_grid_point_and_reads_back():
    rng = np.random.default_rng(1)
    table = make_table(rng)
    text = tx.table_csv(table)
    assert text.splitlines()[0] == "x_mm,y_mm,z_mm,comp_dx_um,comp_dy_um,comp_dz_um"
    axes, P, comp = tx.read_table_csv(text)
    assert axes == AXES and comp.shape == (table.grid.n_points, 3)
    np.testing.assert_array_equal(P, table.grid.points_mm())
    np.testing.assert_array_equal(comp, -interpolate(table, P))  # the full drift there, negated, exactly


def test_json_is_the_dict_form():
    rng = np.random.default_rng(2)
    table = make_table(rng)
    back = table_from_dict(json.loads(tx.table_json(table)))
    np.testing.assert_array_equal(back.structure_um, table.structure_um)
    np.testing.assert_array_equal(back.feedback_um[2].error_um, table.feedback_um[2].error_um)


def test_k3_line_is_the_least_squares_line_of_the_compensation_along_each_axis():
    rng = np.random.default_rng(3)
    table = make_table(rng)
    offsets = tx.k3_offsets(table)
    for o, (a, d, _), p, p0 in zip(offsets, DRIVES, POS, POSE):
        # the axis' support points and its drive's points, the others at the model's pose
        x = np.unique(np.r_[p, np.linspace(p[0], p[-1], 9)])
        P = np.tile(POSE, (x.size, 1))
        P[:, AXES.index(a)] = x
        c = -interpolate(table, P)[:, d]
        xm, cm = x.mean(), c.mean()
        slope = np.sum((x - xm) * (c - cm)) / np.sum((x - xm) ** 2)  # µm/mm, by hand
        assert o.axis == a and o.reference_mm == p0
        assert o.slope == pytest.approx(slope * 1e-3, rel=1e-10)
        assert o.compensation_um == pytest.approx(cm + slope * (p0 - xm), rel=1e-10, abs=1e-12)
        assert o.drift_um == -o.compensation_um
    text = tx.siemens_k3(table, axis_names={"X": "X1", "Y": "Y1", "Z": "Z2"}, header="vmc800 table")
    back = tx.read_k3(text)
    assert set(back) == {"X1", "Y1", "Z2"}
    for o, name in zip(offsets, ("X1", "Y1", "Z2")):
        assert back[name]["abs"] == pytest.approx(o.compensation_um * 1e-3, abs=5e-7)
        assert back[name]["slope"] == pytest.approx(o.slope, abs=5e-10)
        assert back[name]["ref"] == pytest.approx(o.reference_mm, abs=5e-5)


def test_k3_of_a_table_linear_along_its_axes_is_exact():
    grid = SupportGrid(AXES, POS, POSE)
    P = grid.points_mm()
    drift = np.stack([3.0 + 0.01 * P[:, 0], -2.0 - 0.02 * P[:, 1], 1.0 + 0.005 * P[:, 2]], axis=1)
    table = VolumetricTable(grid, 0.0, drift.reshape(grid.shape + (3,)))
    offsets = tx.k3_offsets(table)
    assert [o.compensation_um for o in offsets] == pytest.approx([-3.0, 2.0 + 0.02 * 50.0, -1.0], abs=1e-12)
    assert [o.slope for o in offsets] == pytest.approx([-1e-5, 2e-5, -5e-6], rel=1e-10)


def test_cec_tables_are_the_star_decomposition_and_read_back():
    rng = np.random.default_rng(4)
    table = make_table(rng, separable=True)
    tables = tx.cec_tables(table)
    assert len(tables) == 9 and [t.index for t in tables] == list(range(9))
    dirs = tx.axis_directions(table)
    for t in tables:
        # evenly spaced, through every support point of the axis and its drive's points (linspace 9 → 25 points)
        x = t.positions_mm()
        i = AXES.index(t.input)
        assert x[0] == POS[i][0] and x[-1] == pytest.approx(POS[i][-1], abs=1e-9)
        for p in np.r_[POS[i], np.linspace(POS[i][0], POS[i][-1], 9)]:
            assert np.abs(x - p).min() < 1e-9
    P = table.grid.points_mm()
    # a separable table: the control's sum of the tables is the table's compensation at every grid point
    np.testing.assert_allclose(tx.cec_sum(tables, dirs, AXES, P), -interpolate(table, P), rtol=0, atol=1e-9)
    text = tx.siemens_cec(table, header="vmc800 at 1 h")
    assert text.startswith("%_N_NC_CEC_INI\nCHANDATA(1)\n; vmc800 at 1 h\n") and text.endswith("M17\n")
    back = tx.read_cec(text)
    assert sorted(back) == list(range(9))
    for t in tables:
        b = back[t.index]
        assert (b["input"], b["output"]) == (f"{t.input}1", f"{t.output}1")
        assert b["step"] == pytest.approx(t.step_mm, abs=1e-6) and b["min"] == pytest.approx(t.min_mm, abs=1e-6)
        assert b["max"] == pytest.approx(t.max_mm, abs=1e-6)
        assert (b["direction"], b["mult_by_table"], b["is_modulo"]) == (0, 0, 0)
        np.testing.assert_allclose(np.array(b["values_mm"]) * 1e3, t.values_um, rtol=0, atol=1e-4)
    # the first axis' tables carry the compensation at the model's pose, the others only the change from it
    at_pose = -interpolate(table, np.array([POSE]))[0]
    for t in tables:
        x0 = POSE[AXES.index(t.input)]
        v = np.interp(x0, t.positions_mm(), t.values_um)
        assert v == pytest.approx(at_pose[dirs[t.output]] if t.input == "X" else 0.0, abs=1e-9)


def test_cec_of_a_table_with_products_states_its_gap():
    rng = np.random.default_rng(5)
    table = make_table(rng)
    tables = tx.cec_tables(table)
    P = table.grid.points_mm()
    gap = np.abs(tx.cec_sum(tables, tx.axis_directions(table), AXES, P) + interpolate(table, P)).max()
    assert gap > 1.0  # random values at the grid points: per-axis tables cannot hold them
    assert f"max |difference| = {gap:.4f} um" in tx.siemens_cec(table)
    # along the lines through the model's pose they are exact
    for i in range(3):
        x = np.linspace(POS[i][0], POS[i][-1], 31)
        L = np.tile(POSE, (31, 1))
        L[:, i] = x
        np.testing.assert_allclose(tx.cec_sum(tables, tx.axis_directions(table), AXES, L), -interpolate(table, L),
                                   rtol=0, atol=1e-9)


def test_every_form_refuses_a_compensation_beyond_the_clamp_or_not_finite(monkeypatch):
    rng = np.random.default_rng(6)
    table = make_table(rng)
    S = np.array(table.structure_um)
    S[1, 2, 0, 2] = 1500.0
    big = VolumetricTable(table.grid, 0.0, S, table.feedback_um)
    forms = (tx.table_csv, tx.table_json, tx.siemens_k3, tx.siemens_cec)
    for form in forms:
        with pytest.raises(OffsetGuardError, match="beyond the clamp"):
            form(big)
        assert form(big, clamp_um=2000.0)
    fb = list(table.feedback_um)
    fb[0] = fb[0]._replace(error_um=fb[0].error_um + 1200.0)
    with pytest.raises(OffsetGuardError, match="X drive at -400 mm|beyond the clamp"):
        tx.table_csv(VolumetricTable(table.grid, 0.0, table.structure_um, tuple(fb)))
    # a table cannot hold a value that is not finite; should the interpolation make one, the guard refuses it
    monkeypatch.setattr(tx, "interpolate", lambda t, P: np.full((np.shape(P)[0], 3), np.nan))
    for form in forms:
        with pytest.raises(OffsetGuardError, match="not finite"):
            form(table)


def test_a_control_character_in_a_name_is_refused():
    table = make_table(np.random.default_rng(7))
    with pytest.raises(ValueError, match="control character"):
        tx.siemens_cec(table, header="a\nM30")
    with pytest.raises(ValueError, match="control character"):
        tx.siemens_k3(table, axis_names={"X": "X1\n"})


@pytest.mark.slow
def test_table_command_writes_each_form_of_the_models_table_and_refuses_to_overwrite(pose_rom_200mm, tmp_path, capsys):
    from hybridcomp.cli import main
    from hybridcomp.fem.loads import example_loads
    from hybridcomp.models import load_machine
    from hybridcomp.models.loads import read_loads, write_loads
    from hybridcomp.rom.reduced import save_rom
    from hybridcomp.rom.volumetric import table_of, table_operator

    rom = pose_rom_200mm
    loads = example_loads(load_machine("vmc800"), 4.0, 300.0)
    rom_file = save_rom(tmp_path / "pose.npz", rom)
    loads_file = tmp_path / "loads.csv"
    write_loads(loads_file, loads)
    loads = read_loads(loads_file, load_machine("vmc800"))  # what the command reads (the CSV rounds)
    base = ["table", "--rom", str(rom_file), "--loads", str(loads_file)]
    assert main([*base, "--at-hours", "2", "--form", "csv", "--out", str(tmp_path / "t.csv")]) == 0
    # independently: the model run over the loads, its outputs at 2 h (a row of the loads) through the table's map
    Y, _ = rom.integrate(loads.time_s, rom.layout().inputs(loads.names, loads.values))
    k = int(np.flatnonzero(loads.time_s == 7200.0)[0])
    table = table_of(table_operator(rom), Y[k], 7200.0)
    axes, P, comp = tx.read_table_csv((tmp_path / "t.csv").read_text())
    np.testing.assert_allclose(comp, -interpolate(table, P), rtol=1e-9, atol=1e-9)
    assert main([*base, "--at-hours", "2", "--form", "csv", "--out", str(tmp_path / "t.csv")]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    for form in ("json", "840d", "840d-cec"):
        names = [] if form == "json" else ["--axis-names", "X=X1"]
        assert main([*base, "--at-hours", "2.05", "--form", form, *names, "--out", str(tmp_path / f"t.{form}")]) == 0
    assert set(tx.read_k3((tmp_path / "t.840d").read_text())) == {"X1", "Y1", "Z1"}
    assert len(tx.read_cec((tmp_path / "t.840d-cec").read_text())) == 9
    assert table_from_dict(json.loads((tmp_path / "t.json").read_text())).time_s == 2.05 * 3600
    assert main([*base, "--at-hours", "5", "--form", "csv", "--out", str(tmp_path / "u.csv")]) == 2
    assert "outside the loads' time span" in capsys.readouterr().err
    assert main([*base, "--at-hours", "1", "--form", "csv", "--axis-names", "X=X1", "--out", str(tmp_path / "u.csv")]) == 2
    assert not (tmp_path / "u.csv").exists()
