"""CD sets per support point (chardiag.grid): training data at the points from the pose-aware model, the fitted grid
against the drift at and between the points, the database's grids (store, list, activate, search, migrate), and a
daemon with a one-pose structure model writing the active grid's table and the offsets at the commanded position."""

from __future__ import annotations

import asyncio
import csv
import dataclasses
import json
import sqlite3

import numpy as np
import pytest

from hybridcomp.chardiag.cd import CDSet, pose_key
from hybridcomp.chardiag.db import CDDatabase, CDDatabaseError
from hybridcomp.chardiag.fit import fit_cd_set
from hybridcomp.chardiag.grid import CDGrid, point_keys, point_pose
from hybridcomp.rom.volumetric import SupportGrid, VolumetricTable, interpolate

AXES = ("X", "Y", "Z")


# ------------------------------------------------------------------------------------------- synthetic grids (fast)
def _synthetic_grid(gain: float = 1.0, level_degC: float = 20.0, machine: str = "m1") -> CDGrid:
    """A 2 x 2 x 2 grid whose point i has dx = gain (i + 1) (T1 − 20), dy = −dx, dz = 0.5 (T2 − 20): fitted exactly.

    The training temperatures sweep T1 and T2 around ``level_degC`` (the sets' reference temperatures).
    """
    grid = SupportGrid(AXES, ((-100.0, 100.0), (-50.0, 50.0), (0.0, 40.0)))
    rng = np.random.default_rng(0)
    T1 = level_degC + rng.uniform(-2.0, 2.0, 60)
    T2 = level_degC + rng.uniform(-2.0, 2.0, 60)
    sets = []
    for i in range(grid.n_points):
        dx = gain * (i + 1) * (T1 - 20.0)
        table = {"T1_degC": T1, "T2_degC": T2, "dx_um": dx, "dy_um": -dx, "dz_um": 0.5 * (T2 - 20.0)}
        sets.append(CDSet(fit_cd_set(table, machine=machine, pose_mm=point_pose(grid, i), load_case=f"lc{level_degC:g}",
                                     signature=np.array([level_degC, 1.0]))))
    return CDGrid(grid, tuple(sets), load_case=f"lc{level_degC:g}")


def test_a_cd_grid_table_is_each_points_set_at_the_temperatures_and_multilinear_between():
    g = _synthetic_grid()
    table, outside = g.table({"T1": 21.0, "T2": 21.5}, 5.0)
    assert not outside and table.grid == g.grid and table.time_s == 5.0
    S = table.structure_um.reshape(-1, 3)
    # hand values: dx = (i + 1) · 1 K, dy = −dx, dz = 0.5 · 1.5 K
    assert S[:, 0] == pytest.approx(np.arange(1, 9), abs=1e-9)
    assert S[:, 1] == pytest.approx(-np.arange(1, 9), abs=1e-9)
    assert S[:, 2] == pytest.approx(np.full(8, 0.75), abs=1e-9)
    # the centre of the box: the mean of the eight corners
    assert interpolate(table, np.array([[0.0, 0.0, 20.0]]))[0] == pytest.approx([4.5, -4.5, 0.75], abs=1e-9)
    # outside a CD's trained range: clamped and flagged
    assert g.table({"T1": 40.0, "T2": 21.5}, 0.0)[1]


def test_a_cd_grid_refuses_sets_of_other_poses():
    g = _synthetic_grid()
    sets = list(g.sets)
    sets[0], sets[1] = sets[1], sets[0]
    with pytest.raises(ValueError, match="support point 0 is for pose"):
        CDGrid(g.grid, tuple(sets))
    with pytest.raises(ValueError, match="7 sets for 8 support points"):
        CDGrid(g.grid, g.sets[:7])


def test_the_database_stores_lists_activates_searches_and_exports_a_grid(tmp_path):
    near, far = _synthetic_grid(1.0, 21.0), _synthetic_grid(2.0, 25.0)
    with CDDatabase(tmp_path / "cd.db") as db:
        a, b = db.add_grid(near), db.add_grid(far)
        rows = db.grids("m1")
        assert [r["id"] for r in rows] == [a, b] and rows[0]["shape"] == [2, 2, 2] and not rows[0]["active"]
        assert rows[0]["max_rms_residual_um"] < 1e-6
        assert db.active_grid("m1") is None
        ev = db.activate_grid(b, reason="test")
        assert ev is not None and db.active_grid_id("m1") == b
        back = db.grid(b)
        # every point's set is the active set of its pose, and the grid read back is the grid stored
        for key, s, s0 in zip(point_keys(back.grid), back.sets, far.sets):
            assert db.active_ids("m1", key) == s.ids
            assert all(s.cds[d] == s0.cds[d] for d in AXES)
        t = {"T1": 24.0, "T2": 26.0}
        assert np.array_equal(back.table(t, 0.0)[0].structure_um, far.table(t, 0.0)[0].structure_um)
        db.activate_grid(a)
        assert db.active_grid_id("m1") == a and [r["active"] for r in db.grids()] == [True, False]
        assert db.active_ids("m1", point_keys(near.grid)[3]) == db.grid(a).sets[3].ids
        # search: the grid trained nearest the temperatures first; the threshold leaves the other out
        temps = {"T1": 21.2, "T2": 21.1}
        found = db.search_grids("m1", None, temps, threshold_K=10.0)
        assert [m.grid_id for m in found] == [a, b]
        assert found[0].delta_T_K == pytest.approx(max(abs(np.mean(near.sets[0].cds["X"].t_reference()[s] - temps[s]))
                                                       for s in ("T1", "T2")), abs=1e-9)
        assert [m.grid_id for m in db.search_grids("m1", None, temps, threshold_K=1.0)] == [a]
        assert [m.grid_id for m in db.search_grids("m1", np.array([25.0, 1.0]), temps, threshold_K=10.0)] == [b, a]
        assert db.search_grids("m2", None, temps, 10.0) == []
        events = [json.loads(r[0]) for r in db.engine.connect().exec_driver_sql(
            "SELECT payload FROM events WHERE kind = 'grid activation' ORDER BY id")]
        assert [(e["grid_id"], e["previous"]) for e in events] == [(b, None), (a, b)]
        with pytest.raises(CDDatabaseError, match="table grids has no id 99"):
            db.activate_grid(99)


def test_cd_db_list_shows_grids_and_grid_export_writes_them(tmp_path, capsys):
    from hybridcomp.cli import main

    with CDDatabase(tmp_path / "cd.db") as db:
        gid = db.add_grid(_synthetic_grid())
    db_path = str(tmp_path / "cd.db")
    assert main(["cd", "db", "grid-activate", str(gid), "--db", db_path]) == 0
    assert main(["cd", "db", "list", "--db", db_path]) == 0
    out = capsys.readouterr().out
    assert f"grid {gid:>4}  m1" in out and "2x2x2" in out and out.rstrip().endswith("ACTIVE")
    assert main(["cd", "db", "grid-export", str(gid), "--out", str(tmp_path / "ex"), "--db", db_path]) == 0
    info = json.loads((tmp_path / "ex" / "grid.json").read_text())
    assert info["grid_id"] == gid and len(info["points"]) == 8 and (tmp_path / "ex" / "p07" / "cd_Z.xml").is_file()
    assert main(["cd", "db", "grid-export", str(gid), "--out", str(tmp_path / "ex"), "--db", db_path]) == 2
    assert "pass --force" in capsys.readouterr().err
    assert main(["cd", "db", "grid-search", "--machine-name", "m1", "--temperatures", "T1=20,T2=20", "--db", db_path,
                 "--threshold-K", "0.001"]) == 1


def test_an_old_database_is_migrated_and_keeps_its_cds(tmp_path):
    path = tmp_path / "old.db"
    with CDDatabase(path) as db:
        ids = db.add_set(_synthetic_grid().sets[0].cds)
    con = sqlite3.connect(path)  # back to schema 1: no grid tables
    for t in ("active_grid", "grid_cds", "grids"):
        con.execute(f"DROP TABLE {t}")
    con.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    con.commit()
    con.close()
    with pytest.raises(CDDatabaseError, match="schema_version is 1, older"):
        CDDatabase(path, readonly=True)
    with CDDatabase(path) as db:  # a writer migrates
        assert db.schema_version() == 2
        assert db.get(ids["X"]).direction == "X" and db.grids() == []
        gid = db.add_grid(_synthetic_grid())
        db.activate_grid(gid)
    with CDDatabase(path, readonly=True) as db:
        assert db.active_grid("m1").grid_id == gid


def test_the_fit_grid_command_refuses_a_one_pose_model(tmp_path, small_rom, capsys):
    from hybridcomp.cli import main
    from hybridcomp.rom import save_rom

    p = save_rom(tmp_path / "one.rom.npz", small_rom)
    assert main(["cd", "fit-grid", "--pose-rom", str(p), "--out", str(tmp_path / "g")]) == 2
    assert "knows one pose only" in capsys.readouterr().err
    assert main(["cd", "fit-grid", "--pose-rom", str(p), "--out", str(tmp_path / "g"), "--activate"]) == 2
    assert "--activate" in capsys.readouterr().err


# ------------------------------------------------------------------------------------ on the 200 mm pose-aware model
def _cases(machine):
    from hybridcomp.chardiag.training import LoadCase
    from hybridcomp.models.loads import example_loads

    return {f"day{s}": LoadCase(f"day{s}", example_loads(machine, 8.0, 120.0, seed=s)) for s in (0, 1)}


@pytest.fixture(scope="module")
def grid_fit(machine, pose_roms_200mm):
    """(training data, fitted grid) on the pose-aware 200 mm model, two 8 h example days."""
    from hybridcomp.chardiag.grid import fit_grid, grid_training_data

    data = grid_training_data(pose_roms_200mm[1], _cases(machine))
    return data, fit_grid(data, machine=machine.name)


def _outputs(prom, machine):
    out = []
    for c in _cases(machine).values():
        Y, _ = prom.integrate(c.loads.time_s, prom.layout().inputs(c.loads))
        out.append(Y)
    return np.vstack(out)


@pytest.mark.slow
def test_training_data_at_a_support_pose_is_its_blocks_drift_plus_the_drives_errors(machine, pose_roms_200mm, grid_fit):
    """Independent of drift_along's weights: at a point that is a support pose, that pose's drift outputs plus every
    drive's error interpolated by hand at the axis position; the sensors from ``simulate``."""
    from hybridcomp.rom.poses import grid_of

    prom = pose_roms_200mm[1]
    data, _ = grid_fit
    pg = grid_of(prom)
    Y = _outputs(prom, machine)
    lay = prom.output_layout()
    checked = 0
    for k in range(len(pg.poses)):
        pose = pg.pose_mm(k)
        key = pose_key(pose)
        if key not in point_keys(data.grid):
            continue
        i = point_keys(data.grid).index(key)
        td = data.tables[i]
        rows = list(lay.pose_indices(k)) if k else list(lay.indices("drift"))
        want = Y[:, rows] * 1e6
        for fb in lay.feedback:
            e = Y[:, list(fb.indices)] * 1e6
            want[:, fb.direction] += fb.sign * np.array([np.interp(pose[fb.axis], fb.positions_mm, r) for r in e])
        got = np.column_stack([td.columns[c] for c in ("dx_um", "dy_um", "dz_um")])
        assert got == pytest.approx(want, abs=1e-9 * max(1.0, np.abs(want).max()))
        for a in AXES:
            assert np.all(td.columns[f"{a.lower()}_mm"] == pose[a])
        checked += 1
    assert checked == 7  # the model's pose and each axis' travel ends are points of the 3 x 3 x 3 grid (not the
    # inner levels along Y and Z of the default star)
    sim = [prom.simulate(c.loads).sensors_degC for c in _cases(machine).values()]
    T = np.vstack(sim)
    for j, s in enumerate(lay.sensors):
        assert data.tables[0].columns[f"{s}_degC"] == pytest.approx(T[:, j], abs=1e-9)
        assert np.array_equal(data.tables[0].columns[f"{s}_degC"], data.tables[26].columns[f"{s}_degC"])


@pytest.mark.slow
def test_a_fitted_grid_gives_the_drift_at_its_points_within_the_fit_residual_and_interpolates_between(
        machine, pose_roms_200mm, grid_fit):
    from hybridcomp.rom.poses import drift_along

    prom = pose_roms_200mm[1]
    data, g = grid_fit
    Y = _outputs(prom, machine)
    lay = prom.output_layout()
    T = lay.take(Y, "sensors") + prom.layout().reference_temperature_degC
    P = g.grid.points_mm()
    exact = np.stack([drift_along(prom, Y, p[None]) for p in P], axis=1)  # rows × points × 3
    tables = [g.table(dict(zip(lay.sensors, T[k])), float(k))[0] for k in range(len(Y))]
    cd = np.stack([t.structure_um.reshape(-1, 3) for t in tables])
    rms = np.sqrt(np.mean((cd - exact) ** 2, axis=0))  # points × 3
    fit = np.array([[s.cds[d].fit_stats()["rms_residual_um"] for d in AXES] for s in g.sets])
    assert rms == pytest.approx(fit, rel=1e-9, abs=1e-12)  # the table at a point is that point's fitted set
    # between the points: the CD table differs from the exact drift's table by a convex combination of the
    # corners' residuals, never by more than the largest of them
    rng = np.random.default_rng(3)
    lo, hi = P.min(axis=0), P.max(axis=0)
    Q = lo + rng.random((40, 3)) * (hi - lo)
    worst, gap = 0.0, []
    for k in range(0, len(Y), 7):
        ex = VolumetricTable(g.grid, float(k), exact[k].reshape(g.grid.shape + (3,)))
        d = np.abs(interpolate(tables[k], Q) - interpolate(ex, Q))
        worst = max(worst, float((d - np.abs(cd[k] - exact[k]).max(axis=0)).max()))
        gap.append(interpolate(tables[k], Q) - np.array([drift_along(prom, Y[k:k + 1], q[None])[0] for q in Q]))
    assert worst <= 1e-9
    gap = np.array(gap)
    print("fit residual at the points (RMS, µm) mean", fit.mean(axis=0), "max", fit.max(axis=0),
          "| CD table against drift_along between the points (RMS, µm)", np.sqrt(np.mean(gap ** 2, axis=(0, 1))))


# ----------------------------------------------------------------------------------------------- the daemon
def _replay(machine, rom, db_path, trace, tmp_path, max_step_um=1000.0):
    from hybridcomp.monitor.config import parse_config
    from hybridcomp.monitor.daemon import Monitor, run_monitor
    from hybridcomp.monitor.sinks import MemorySink
    from hybridcomp.monitor.sources import ReplaySource
    from hybridcomp.rom import save_rom

    path = save_rom(tmp_path / "one.rom.npz", rom)
    data = {"monitor": {"machine": "vmc800", "database": str(db_path), "rom": str(path), "increment_s": 60.0},
            "compensation": {"strategy": "hybrid", "max_step_um": max_step_um, "sensor_filter_s": 0.0},
            "source": {"kind": "replay", "path": str(trace), "speed": 0},
            "sink": {"kind": "none"}, "regeneration": {"enabled": False}}
    cfg = parse_config(data, "test.toml", tmp_path)
    db = CDDatabase(db_path)
    try:
        mon = Monitor(cfg, machine, rom, db, "X=0,Y=0,Z=0")
        sink = MemorySink()
        asyncio.run(run_monitor(cfg, mon, ReplaySource(trace, machine, speed=0), sink))
        again = Monitor(cfg, machine, rom, db, "X=0,Y=0,Z=0")  # a restart continues the last boundary's table
        return sink.rows, again
    finally:
        db.close()


def _trace_temps(trace, sensors):
    with open(trace, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {float(r["time_s"]): {s: float(r[f"{s}_degC"]) for s in sensors} for r in rows}


def _swapped(g: CDGrid, i: int, j: int) -> CDGrid:
    """``g`` with point i's set replaced by point j's CDs (posed at point i): a planted error."""
    pose = tuple(sorted(point_pose(g.grid, i).items()))
    cds = {d: dataclasses.replace(cd, pose_mm=pose) for d, cd in g.sets[j].cds.items()}
    sets = list(g.sets)
    sets[i] = CDSet(cds)
    return CDGrid(g.grid, tuple(sets))


@pytest.mark.slow
def test_a_daemon_with_a_one_pose_model_writes_the_active_grids_table_and_offsets_at_the_commanded_position(
        machine, pose_roms_200mm, grid_fit, tmp_path):
    from hybridcomp.monitor.example import write_example_trace

    rom = pose_roms_200mm[0]
    _, g = grid_fit
    trace = write_example_trace(tmp_path / "trace.csv", machine, rom, hours=1.0, rate_hz=0.2)
    temps = _trace_temps(trace, [s.name for s in machine.sensors])
    runs = {}
    for name, grid in (("good", g), ("bad", _swapped(g, 0, 26))):  # bad: corner X−Y−Z− has the X+Y+Z+ corner's CDs
        (tmp_path / name).mkdir()
        with CDDatabase(tmp_path / name / "cd.db") as db:
            db.activate_grid(db.add_grid(grid))
        runs[name] = _replay(machine, rom, tmp_path / name / "cd.db", trace, tmp_path / name)
    rows, again = runs["good"]
    tabled = [r for r in rows if r.table is not None]
    assert len(tabled) == len(rows) > 100 and all(r.by == "cd-grid" for r in tabled)
    for r in tabled[::10]:
        assert r.table.grid == g.grid
        # the table is the grid's sets at the sensors (no filter, no rate limit acting) ...
        want, _ = g.table(temps[r.time_s], r.time_s)
        assert r.table.structure_um == pytest.approx(want.structure_um, abs=1e-9)
        # ... and the offsets written are the table at the commanded position
        assert (r.dx_um, r.dy_um, r.dz_um) == pytest.approx(interpolate(r.table, np.array([r.position_mm]))[0],
                                                            abs=1e-9)
    assert again.table is not None and again.table.grid == g.grid and again.state.grid.grid_id == 1
    # the planted error changes the table at its point only, and the offsets by that change times the point's
    # interpolation weight at the commanded position (by hand: the product over the axes of the distance to the
    # cell's far side over the cell's width, in the first cell of every axis, else 0)
    bad = {r.time_s: r for r in runs["bad"][0]}
    lo = [p[0] for p in g.grid.positions_mm]
    mid = [p[1] for p in g.grid.positions_mm]
    near = 0
    for r in tabled:
        b = bad[r.time_s]
        d = b.table.structure_um.reshape(-1, 3) - r.table.structure_um.reshape(-1, 3)
        assert np.abs(d[1:]).max() == 0.0
        w = np.prod([min(max((m - x) / (m - a), 0.0), 1.0) for x, a, m in zip(r.position_mm, lo, mid)])
        got = np.array([b.dx_um - r.dx_um, b.dy_um - r.dy_um, b.dz_um - r.dz_um])
        assert got == pytest.approx(w * d[0], abs=1e-9)
        near += w > 0.05 and np.abs(w * d[0]).max() > 0.5
    assert near > 10  # the trace's tool visits the corner's cell, where the swapped set moves the offsets
    # with the rate limit: every table entry moves at most max_step_um a cycle, the offsets still the table's
    (tmp_path / "limited").mkdir()
    with CDDatabase(tmp_path / "limited" / "cd.db") as db:
        db.activate_grid(db.add_grid(g))
    slow, _ = _replay(machine, rom, tmp_path / "limited" / "cd.db", trace, tmp_path / "limited", max_step_um=0.05)
    steps = [np.abs(b.table.structure_um - a.table.structure_um).max() for a, b in zip(slow, slow[1:])]
    assert max(steps) <= 0.05 + 1e-12 and any(r.limited for r in slow)
    for r in slow[::20]:
        assert (r.dx_um, r.dy_um, r.dz_um) == pytest.approx(interpolate(r.table, np.array([r.position_mm]))[0],
                                                            abs=1e-9)


def test_a_changed_grid_continues_from_the_last_table_carried_onto_its_points():
    from hybridcomp.monitor.volumetric import on_grid, table_step

    a = _synthetic_grid().grid
    b = SupportGrid(AXES, ((-100.0, 0.0, 100.0), (-50.0, 50.0), (0.0, 40.0)))
    S = np.arange(24, dtype=float).reshape(2, 2, 2, 3)
    old = VolumetricTable(a, 0.0, S)
    moved = on_grid(old, b)
    assert moved.grid == b and on_grid(old, a) is old and on_grid(None, b) is None
    # a new point halfway along X: the mean of its neighbours (hand value), the others as they were
    assert moved.structure_um[1] == pytest.approx(0.5 * (S[0] + S[1]), abs=1e-12)
    assert np.array_equal(moved.structure_um[[0, 2]], S)
    new = VolumetricTable(b, 5.0, np.full(b.shape + (3,), 100.0))
    limited, acted = table_step(new, moved, 0.2)
    assert acted and np.abs(limited.structure_um - moved.structure_um).max() == pytest.approx(0.2)


def test_a_table_file_needs_a_pose_aware_model_or_an_active_grid(tmp_path, small_rom):
    from hybridcomp.monitor.cli import open_everything
    from hybridcomp.monitor.config import ConfigError, parse_config
    from hybridcomp.rom import save_rom

    rom = save_rom(tmp_path / "one.rom.npz", small_rom)
    data = {"monitor": {"machine": "vmc800", "database": "cd.db", "rom": str(rom)},
            "source": {"kind": "replay", "path": "trace.csv"},
            "sink": {"kind": "none", "table_path": "tables.jsonl"}, "regeneration": {"enabled": False}}
    cfg = parse_config(data, "test.toml", tmp_path)
    with pytest.raises(ConfigError, match="or an active CD grid of vmc800"):
        open_everything(cfg)
    assert not (tmp_path / "cd.db").exists()  # the refusal creates no database
    g = _synthetic_grid(machine="vmc800")
    with CDDatabase(tmp_path / "cd.db") as db:
        db.add_grid(g)
        with pytest.raises(ConfigError, match="or an active CD grid"):
            open_everything(cfg)
        db.activate_grid(1)
    *_, db = open_everything(cfg)
    db.close()


# ----------------------------------------------------------------------------------------------- grid decisions
def _vmc_grid(machine, level_degC: float, gain: float) -> CDGrid:
    """A 2 x 2 x 2 grid of vmc800 over its travel: dx = gain (T1 − 20) at every point, reference ``level_degC``."""
    grid = SupportGrid(AXES, tuple((a.travel_mm[0], a.travel_mm[1]) for a in machine.axes))
    rng = np.random.default_rng(0)
    T1 = 20.0 + rng.uniform(-3.0, 3.0, 40)
    T2 = 20.0 + rng.uniform(-3.0, 3.0, 40)
    tref = {s.name: level_degC for s in machine.sensors}
    sets = []
    for i in range(grid.n_points):
        table = {"T1_degC": T1, "T2_degC": T2, "dx_um": gain * (T1 - 20.0), "dy_um": -(T2 - 20.0),
                 "dz_um": 0.1 * (T2 - 20.0)}
        sets.append(CDSet(fit_cd_set(table, machine=machine.name, pose_mm=point_pose(grid, i), t_reference_degC=tref,
                                     load_case=f"ref{level_degC:g}")))
    return CDGrid(grid, tuple(sets), load_case=f"ref{level_degC:g}")


def test_the_grid_decision_keeps_a_fitting_grid_and_switches_to_the_first_stored_one_that_fits(machine, small_rom):
    from hybridcomp.monitor import transitions as T
    from hybridcomp.monitor.config import MonitorConfig

    cfg = MonitorConfig(machine="vmc800", database="cd.db", rom="r.npz", threshold_K=1.0)
    ctx = T.context(cfg, machine, small_rom, "X=0,Y=0,Z=0")
    far, near, other = (dataclasses.replace(_vmc_grid(machine, lv, 1.0), grid_id=i)
                        for i, lv in ((1, 30.0), (2, 20.5), (3, 20.2)))
    st = T.with_active_grid(ctx, T.initial(ctx), far)
    temps = {s.name: 20.0 for s in machine.sensors}
    step = T.on_grid_decision(ctx, st, 900.0, temps, iter([far, near, other]))
    assert step.state.grid is near  # the first other grid within 1 K (the database's order), not the nearest
    assert [type(c).__name__ for c in step.commands] == ["ActivateGrid"] and step.commands[0].grid_id == 2
    assert [e.kind for e in step.events] == ["grid switch"] and step.events[0].payload["delta_T_K"] == 10.0
    kept = T.on_grid_decision(ctx, step.state, 1800.0, temps, iter([other]))
    assert kept.state.grid is near and kept.effects == ()  # within 0.5 K: kept, nothing read
    none = T.on_grid_decision(ctx, st, 900.0, temps, iter([far]))
    assert none.state.grid is far and [e.kind for e in none.events] == ["grid decision"] and not none.commands
    assert T.on_grid_decision(ctx, T.initial(ctx), 900.0, temps, iter([near])).effects == ()  # no active grid


@pytest.fixture(scope="module")
def small_rom_trace(machine, small_rom, tmp_path_factory):
    """The first hour of the job-shop day at 0.2 Hz with ``small_rom``'s sensors (shared: it takes seconds)."""
    from hybridcomp.monitor.example import write_example_trace

    return write_example_trace(tmp_path_factory.mktemp("trace") / "trace.csv", machine, small_rom, hours=1.0,
                               rate_hz=0.2)


@pytest.mark.slow
def test_a_daemon_switches_to_the_stored_grid_that_fits_at_its_monitoring_boundary(machine, small_rom, small_rom_trace,
                                                                                  tmp_path):
    trace = small_rom_trace
    T0 = np.mean(list(_trace_temps(trace, ["T1"]).values())[0]["T1"])
    far, fits = _vmc_grid(machine, 40.0, 1.0), _vmc_grid(machine, float(T0), 3.0)
    with CDDatabase(tmp_path / "cd.db") as db:
        a, b = db.add_grid(far), db.add_grid(fits)
        db.activate_grid(a)
    rows, again = _replay(machine, small_rom, tmp_path / "cd.db", trace, tmp_path)
    with CDDatabase(tmp_path / "cd.db") as db:
        assert db.active_grid_id("vmc800") == b
        kinds = [r[0] for r in db.engine.connect().exec_driver_sql("SELECT kind FROM events ORDER BY id")]
        assert kinds.count("grid switch") == 1 and kinds.count("grid activation") == 2
    assert again.state.grid.grid_id == b
    # before the switch the offsets come from the first grid (dx = T1 − 20), after it from the second (3 x)
    temps = _trace_temps(trace, [s.name for s in machine.sensors])
    ratio = [r.dx_um / (temps[r.time_s]["T1"] - 20.0) for r in rows if abs(temps[r.time_s]["T1"] - 20.0) > 0.2]
    assert ratio[0] == pytest.approx(1.0, abs=1e-6) and ratio[-1] == pytest.approx(3.0, abs=1e-6)


# ----------------------------------------------------------------------------------------------- grid generation
def _boundary_state(T, ctx, machine):
    """A state as at a monitoring boundary: an observer estimate, one history row and one load row."""
    u0 = np.zeros(ctx.layout.n_inputs)
    ns = len(ctx.sensor_names)
    return T._set(T.initial(ctx), observer=ctx.observer.initial(u0, 0.0), loads=[[600.0, *u0]],
                  history=[[600.0, *[20.0] * ns, 0.0, 0.0, 0.0]], filtered_degC={n: 20.0 for n in ctx.sensor_names},
                  last_time_s=900.0)


def test_a_boundary_with_no_fitting_grid_asks_for_a_grid_generation(machine, small_rom, tmp_path):
    from pathlib import Path

    from hybridcomp.monitor import transitions as T
    from hybridcomp.monitor.config import MonitorConfig
    from hybridcomp.monitor.regeneration import GRID_JOB, RegenerationRequest

    cfg = MonitorConfig(machine="vmc800", database="cd.db", rom="r.npz", threshold_K=1.0,
                        grid_rom=Path("poses.npz"), table_points=2)
    ctx = T.context(cfg, machine, small_rom, "X=0,Y=0,Z=0")
    far = dataclasses.replace(_vmc_grid(machine, 30.0, 1.0), grid_id=1)
    temps = {s.name: 20.0 for s in machine.sensors}
    st = _boundary_state(T, ctx, machine)
    assert T.decides_grids(ctx, st)  # no grid active, but grids may be generated
    for active in (None, far):  # without an active grid, and with one 10 K off: the stored one does not fit either
        step = T.on_grid_decision(ctx, T.with_active_grid(ctx, st, active), 900.0, temps, iter([far]))
        assert [type(c).__name__ for c in step.commands] == ["Request", "Persist"]
        req = step.commands[0].request
        assert req["grid"] == {"rom": "poses.npz", "points": 2, "job": GRID_JOB}
        base = RegenerationRequest.from_dict({k: v for k, v in req.items() if k != "grid"})  # a set's request beside
        assert base.machine_time_s == 900.0 and base.t_reference_degC == temps and base.loads_time_s == [600.0]
        assert step.state.saved.grid_pending == req and step.state.grid is active  # the active grid untouched
        assert [(e.kind, e.payload["status"], e.key) for e in step.events] == [("grid generation", "started",
                                                                               "900.000@started")]
    pending = step.state
    # persisted with the boundary (a restart submits it again), under its own result key beside a set's
    from hybridcomp.monitor.daemon import generation_key

    assert T.boundary_saved(ctx, None, pending).grid_pending == req
    assert generation_key(req) == "grid generation@vmc800@X=0,Y=0,Z=0@900.000" != generation_key(base.to_dict())
    # while it runs, the next boundary waits; its outcome activates the grid, or blocks a retry
    again = T.on_grid_decision(ctx, pending, 1800.0, temps, iter([]))
    assert not again.commands and "a grid generation is running" in again.events[0].payload["message"]
    new = dataclasses.replace(_vmc_grid(machine, 20.0, 2.0), grid_id=7)
    done = T.on_grid_generation_finished(ctx, pending, req, {"grid_id": 7}, None, "finished", new)
    assert done.state.grid is new and done.state.saved.grid_pending is None
    assert [(type(c).__name__, getattr(c, "grid_id", None)) for c in done.commands] == [("ActivateGrid", 7),
                                                                                        ("Persist", None)]
    failed = T.on_grid_generation_finished(ctx, pending, req, None, "boom", "failed")
    assert failed.state.grid is far and failed.state.saved.grid_pending is None
    assert failed.state.saved.grid_blocked_until_s == 900.0 + cfg.regeneration.retry_after_s
    blocked = T.on_grid_decision(ctx, failed.state, 1800.0, temps, iter([]))
    assert not blocked.commands and "after a failed one" in blocked.events[0].payload["message"]
    # a set generation running holds the grid's back (one job at a time)
    busy = T.on_grid_decision(ctx, T._set(st, pending={"machine_time_s": 0.0}), 900.0, temps, iter([]))
    assert not busy.commands and "a set generation is running" in busy.events[0].payload["message"]
    # without compensation.grid_rom: no generation, the decision says why; no active grid: nothing at all
    ctx0 = T.context(dataclasses.replace(cfg, grid_rom=None), machine, small_rom, "X=0,Y=0,Z=0")
    kept = T.on_grid_decision(ctx0, T.with_active_grid(ctx0, st, far), 900.0, temps, iter([far]))
    assert not kept.commands and "grid_rom is not set" in kept.events[0].payload["message"]
    assert not T.decides_grids(ctx0, st) and T.on_grid_decision(ctx0, st, 900.0, temps, iter([])).effects == ()


def test_the_grid_rom_key_is_checked_when_the_configuration_is_read(machine, small_rom, tmp_path):
    from pathlib import Path

    from hybridcomp.monitor.config import ConfigError, parse_config
    from hybridcomp.rom import save_rom

    one = save_rom(tmp_path / "one.rom.npz", small_rom)

    def cfg(grid_rom, machine_name="vmc800", **comp):
        return parse_config({"monitor": {"machine": machine_name, "database": "cd.db", "rom": str(one)},
                             "compensation": {"grid_rom": grid_rom, **comp},
                             "source": {"kind": "replay", "path": "trace.csv"}, "sink": {"kind": "none"}},
                            "test.toml", tmp_path)

    with pytest.raises(ConfigError, match=r"test\.toml: compensation\.grid_rom = '.*one\.rom\.npz': a reduced model "
                                          r"of one pose; a CD grid needs the drift at every support point"):
        cfg("one.rom.npz")
    with pytest.raises(ConfigError, match=r"compensation\.grid_rom = '.*nope\.npz': .*nope\.npz"):
        cfg("nope.npz")
    other = tmp_path / "other.toml"  # the same machine's file with one more line: another machine file
    other.write_text(Path(machine.source).read_text() + "\n# changed\n")
    with pytest.raises(ConfigError, match=r"compensation\.grid_rom = '.*one\.rom\.npz': .*machine\.sha256"):
        cfg("one.rom.npz", str(other))
    with pytest.raises(ConfigError, match=r"compensation\.grid_rom = .* strategy 'dataonly' does not apply"):
        cfg("one.rom.npz", strategy="dataonly", dataonly_model="m.json")


@pytest.mark.slow
def test_a_daemon_with_no_fitting_grid_generates_one_in_its_worker_activates_it_and_applies_its_table(
        machine, small_rom, pose_rom_200mm, small_rom_trace, tmp_path):
    from hybridcomp.chardiag.fit import FitOptions
    from hybridcomp.monitor.config import parse_config
    from hybridcomp.monitor.daemon import Monitor, run_monitor
    from hybridcomp.monitor.sinks import MemorySink
    from hybridcomp.monitor.sources import ReplaySource
    from hybridcomp.monitor.store import MonitorStore
    from hybridcomp.rom import save_rom

    trace = small_rom_trace
    save_rom(tmp_path / "one.rom.npz", small_rom)
    save_rom(tmp_path / "poses.npz", pose_rom_200mm)
    pose = {"X": 0.0, "Y": 0.0, "Z": 0.0}
    zero = {"T1_degC": np.linspace(18.0, 30.0, 20), **{c: np.zeros(20) for c in ("dx_um", "dy_um", "dz_um")}}
    with CDDatabase(tmp_path / "cd.db") as db:  # an active set the decisions keep: no set generation competes
        db.activate("vmc800", pose_key(pose), db.add_set(fit_cd_set(zero, machine="vmc800", pose_mm=pose,
                                                                    options=FitOptions(min_target_range_um=1.0)),
                                                         "zero"))
    data = {"monitor": {"machine": "vmc800", "database": "cd.db", "rom": "one.rom.npz", "pose_mm": pose,
                        "increment_s": 60.0, "threshold_K": 5.0},
            "compensation": {"strategy": "hybrid", "max_step_um": 1000.0, "sensor_filter_s": 0.0,
                             "grid_rom": "poses.npz", "table_points": 2},
            "validity": {"keep_um": 1000.0, "forecast_um": 1000.0, "hard_um": 1000.0, "reject_um": 1000.0},
            "source": {"kind": "replay", "path": str(trace), "speed": 0}, "sink": {"kind": "none"},
            "regeneration": {"enabled": True, "timeout_s": 300.0}}
    cfg = parse_config(data, "test.toml", tmp_path)
    db = CDDatabase(tmp_path / "cd.db")
    try:
        mon = Monitor(cfg, machine, small_rom, db, pose_key(pose))
        sink = MemorySink()
        asyncio.run(run_monitor(cfg, mon, ReplaySource(trace, machine, speed=0), sink, await_regeneration=True))
        again = Monitor(cfg, machine, small_rom, db, pose_key(pose))  # a restart: the generated grid is active
        ev = {k: [(e.machine_time_s, e.payload) for e in MonitorStore(db).events(k)]
              for k in ("grid generation", "grid activation", "grid decision")}
        gid = db.active_grid_id("vmc800")
        g = db.grid(gid)
    finally:
        db.close()
    # the first boundary (the first sample) generates the grid, on the forecasts from its state; the grid fits after
    assert ev["grid decision"] == []
    assert [(t, p["status"]) for t, p in ev["grid generation"]] == [(0.0, "started"), (0.0, "finished")]
    done = ev["grid generation"][1][1]
    assert done["grid"] == gid and len(ev["grid activation"]) == 1 and g.grid.shape == (2, 2, 2)
    print("grid generation:", done["wall_s"], "s,", done["notes"])
    assert again.state.grid.grid_id == gid and again.s.grid_pending is None
    # its sets' reference: the corrected model's sensors at the decision (the trace's are the model's own)
    temps = _trace_temps(trace, [s.name for s in machine.sensors])
    print("grid's reference against the first sample:", g.delta_T_K(temps[0.0]), "K")
    assert g.delta_T_K(temps[0.0]) < 0.1
    # before the activation the one-pose offsets, after it the grid's table at the sensors, at the position
    after = [r for r in sink.rows if r.by == "cd-grid"]
    assert len(after) == len(sink.rows) - 1 and sink.rows[0].by != "cd-grid"
    for r in after[::10]:
        want, _ = g.table(temps[r.time_s], r.time_s)
        assert r.table.structure_um == pytest.approx(want.structure_um, abs=1e-9)
        assert (r.dx_um, r.dy_um, r.dz_um) == pytest.approx(interpolate(r.table, np.array([r.position_mm]))[0],
                                                            abs=1e-9)


def test_a_grids_load_cases_are_the_history_and_the_forecasts_after_it_as_the_observer_corrects_them(machine,
                                                                                                    small_rom):
    from hybridcomp.monitor import transitions as T
    from hybridcomp.monitor.config import MonitorConfig
    from hybridcomp.monitor.regeneration import FORECAST_STEP_S, RegenerationRequest, forecast_scenarios, grid_cases

    cfg = MonitorConfig(machine="vmc800", database="cd.db", rom="r.npz")
    ctx = T.context(cfg, machine, small_rom, "X=0,Y=0,Z=0")
    obs, lay = ctx.observer, ctx.layout
    U = np.zeros((3, lay.n_inputs))
    U[:, 0] = [100.0, 200.0, 50.0]  # the first heat input [W]; the air as the reference
    st = T._set(_boundary_state(T, ctx, machine), loads=[[300.0 * (k + 1), *U[k]] for k in range(3)])
    req = RegenerationRequest.from_dict(T._request(ctx, st, 900.0, {}, None))
    x = np.array(st.saved.observer.x, float)
    x[obs.slices()["air"]] = 0.5  # the estimate: every zone's air 0.5 K warmer
    cases, t_end = grid_cases(obs, x, req, machine)
    air = np.array([c.endswith("_degC") for c in lay.columns])
    ref = req.reference_temperature_degC
    h = cases["history"].loads
    assert t_end == 900.0 and h.time_s[0] == 0.0 and h.time_s[-1] == 900.0
    # by hand: each 300 s row's inputs over the increment ending at it, the air 0.5 K over the reference
    want = np.array([U[min(int(np.ceil(t / 300.0)) - 1, 2) if t > 0 else 0] for t in h.time_s]) + (ref + 0.5) * air
    assert h.values == pytest.approx(want, abs=1e-12)
    scen = forecast_scenarios(machine, req.loads_names, req.loads_inputs, req.forecast_h)
    assert set(cases) == {"history", *scen}
    for name, F in scen.items():
        c = cases[name].loads
        assert np.array_equal(c.values[:len(h.time_s)], h.values)  # the history is the run-in
        assert c.time_s[len(h.time_s):] == pytest.approx(900.0 + FORECAST_STEP_S * np.arange(1, len(F) + 1))
        assert c.values[len(h.time_s):] == pytest.approx(F + (ref + 0.5) * air, abs=1e-12)
