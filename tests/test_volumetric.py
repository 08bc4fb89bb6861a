"""The volumetric table: support grid, the linear map from the model's outputs, interpolation in the NC cycle, the
rate limit and the dict form; against drift_along of a stand-in pose-aware model and of the real one."""

from __future__ import annotations

import itertools
import json
from types import SimpleNamespace

import numpy as np
import pytest

from hybridcomp.fem.poses import PoseGrid, support_poses
from hybridcomp.models.layout import output_layout
from hybridcomp.rom import volumetric as vol
from hybridcomp.rom.poses import drift_along, pose_output_names
from hybridcomp.rom.volumetric import (
    FeedbackTable,
    SupportGrid,
    VolumetricError,
    VolumetricTable,
    default_grid,
    interpolate,
    interpolate_one,
    limit_table,
    shifted,
    table_from_dict,
    table_of,
    table_operator,
    table_to_dict,
)

LEVELS = ((-400.0, 0.0, 400.0), (-325.0, 50.0, 325.0), (-275.0, 0.0, 275.0))
DRIVES = {"X": (0, -1.0), "Y": (1, -1.0), "Z": (2, 1.0)}  # direction, sign (X and Y move the table)


def stand_in_rom(scheme: str = "star", points: int = 5) -> SimpleNamespace:
    """What drift_along reads of a pose-aware reduced model: output names and the metadata (poses, drives)."""
    grid = PoseGrid(("X", "Y", "Z"), LEVELS, scheme, support_poses(3, scheme))
    names = ["T1", "T2", "dx", "dy", "dz"]
    for k in range(1, len(grid.poses)):
        names += pose_output_names(k)
    feedback = {}
    for (axis, (d, s)), (lo, _, hi) in zip(DRIVES.items(), LEVELS):
        pos = np.linspace(lo, hi, points)
        out = [f"e{axis}@{p:g}" for p in pos]
        names += out
        feedback[axis] = {"feedback": "rotary_encoder", "positions_mm": pos.tolist(), "outputs": out,
                          "direction": d, "sign": s}
    meta = {"poses": grid.as_dict(), "n_sensors": 2, "feedback": feedback}
    return SimpleNamespace(output_names=tuple(names), rom_id="stand-in", meta=meta,
                           output_layout=lambda: output_layout(tuple(names), meta))


def random_table(rng, feedback: bool = True, grid: SupportGrid | None = None) -> VolumetricTable:
    grid = grid or SupportGrid(("X", "Y", "Z"), ((-400.0, -100.0, 0.0, 400.0), (-325.0, 50.0, 325.0),
                                                 (-275.0, 0.0, 275.0)), (0.0, 50.0, 0.0))
    fb = ()
    if feedback:
        fb = tuple(FeedbackTable(a, np.linspace(lo, hi, 7), rng.normal(size=7) * 3, d, s)
                   for (a, (d, s)), (lo, _, hi) in zip(DRIVES.items(), LEVELS))
    return VolumetricTable(grid, 60.0, rng.normal(size=grid.shape + (3,)) * 10, fb)


def inside(rng, n: int) -> np.ndarray:
    return rng.uniform([lv[0] for lv in LEVELS], [lv[2] for lv in LEVELS], (n, 3))


# --------------------------------------------------------------------------- the grid

def test_default_grid_spans_the_travel_through_the_model_pose():
    rom = stand_in_rom()
    g = default_grid(rom)
    assert g.positions_mm == LEVELS and g.pose_mm == (0.0, 50.0, 0.0) and g.n_points == 27
    g5 = default_grid(rom, 5)
    assert g5.positions_mm[1] == (-325.0, -137.5, 50.0, 187.5, 325.0)
    g4 = default_grid(rom, (2, 4, 3))
    assert g4.positions_mm[0] == (-400.0, 400.0) and g4.positions_mm[1] == (-325.0, -108.33333333333334,
                                                                             108.33333333333331, 325.0)
    assert g4.points_mm()[:3].tolist() == [[-400.0, -325.0, -275.0], [-400.0, -325.0, 0.0], [-400.0, -325.0, 275.0]]
    for bad in (1, (3, 3), (3, 3, 1)):
        with pytest.raises(VolumetricError, match="points|point counts"):
            default_grid(rom, bad)
    with pytest.raises(VolumetricError, match="axis Y .* rise strictly"):
        SupportGrid(("X", "Y"), ((0.0, 1.0), (2.0, 2.0)))
    with pytest.raises(VolumetricError, match="axis X needs at least 2"):
        SupportGrid(("X",), ((0.0,),))
    with pytest.raises(VolumetricError, match="outside the travel"):
        table_operator(rom, SupportGrid(("X", "Y", "Z"), ((-400.0, 401.0), LEVELS[1], LEVELS[2])))


# --------------------------------------------------------------------------- the map from the outputs

@pytest.mark.parametrize("scheme", ["star", "grid"])
def test_table_at_the_grid_points_is_drift_along(scheme):
    rom = stand_in_rom(scheme)
    rng = np.random.default_rng(4)
    for points in (3, 5):
        op = table_operator(rom, default_grid(rom, points))
        y = rng.normal(size=len(rom.output_names)) * 1e-5
        table = table_of(op, y, 300.0)
        P = op.grid.points_mm()
        want = drift_along(rom, np.repeat(y[None], P.shape[0], axis=0), P)
        np.testing.assert_allclose(interpolate(table, P), want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
        bare = drift_along(rom, np.repeat(y[None], P.shape[0], axis=0), P, feedback=False)
        np.testing.assert_allclose(table.structure_um.reshape(-1, 3), bare, rtol=1e-12, atol=1e-12 * np.abs(want).max())
        assert table.time_s == 300.0


def test_table_operator_refuses_when_drift_along_adds_the_drives_otherwise(monkeypatch):
    rom = stand_in_rom()
    real = drift_along

    def doubled(rom, Y, P, feedback=True):
        return 2 * real(rom, Y, P, feedback) - real(rom, Y, P, False) if feedback else real(rom, Y, P, False)

    monkeypatch.setattr("hybridcomp.rom.poses.drift_along", doubled)
    with pytest.raises(VolumetricError, match="no longer models what drift_along adds"):
        table_operator(rom)


def test_table_of_names_a_bad_output():
    rom = stand_in_rom()
    op = table_operator(rom)
    y = np.zeros(len(rom.output_names))
    with pytest.raises(VolumetricError, match=f"must have {y.size} entries"):
        table_of(op, y[:-1], 0.0)
    y[3] = np.nan
    with pytest.raises(VolumetricError, match="dy = nan is not finite"):
        table_of(op, y, 0.0)


# --------------------------------------------------------------------------- interpolation

def test_interpolation_is_exact_for_multilinear_fields_and_at_the_grid_points():
    rng = np.random.default_rng(7)
    grid = SupportGrid(("X", "Y", "Z"), ((-400.0, -100.0, 0.0, 400.0), (-325.0, 50.0, 325.0), (-275.0, 275.0)))
    c = rng.normal(size=(8, 3))

    def f(P):  # per direction a + b x + c y + d z + e xy + f xz + g yz + h xyz, positions in m
        x, y, z = (P / 1000.0).T
        mono = np.stack([np.ones_like(x), x, y, z, x * y, x * z, y * z, x * y * z], axis=1)
        return mono @ c

    P = grid.points_mm()
    table = VolumetricTable(grid, 0.0, f(P).reshape(grid.shape + (3,)))
    np.testing.assert_array_equal(interpolate(table, P), f(P))  # at the grid points: the values, exactly
    Q = inside(rng, 500)
    np.testing.assert_allclose(interpolate(table, Q), f(Q), rtol=1e-12, atol=1e-12)
    # outside the box: the value at the clamped position
    out = np.array([[-500.0, 0.0, 0.0], [0.0, 400.0, -300.0], [1e6, -1e6, 1e6]])
    clamped = np.clip(out, [-400, -325, -275], [400, 325, 275])
    np.testing.assert_allclose(interpolate(table, out), f(clamped), rtol=1e-12, atol=1e-12)


def test_interpolate_one_is_interpolate():
    rng = np.random.default_rng(8)
    table = random_table(rng)
    grid = table.grid
    nodes = np.array(list(itertools.product(*[sorted(set(p) | set(np.linspace(lv[0], lv[2], 7)))
                                              for p, lv in zip(grid.positions_mm, LEVELS)])))
    Q = np.vstack([inside(rng, 300), nodes, [[-1e4, 1e4, 0.0], [450.0, -330.0, 280.0]]])
    got = np.array([interpolate_one(table, q) for q in Q])
    np.testing.assert_allclose(got, interpolate(table, Q), rtol=1e-13, atol=1e-12)
    assert interpolate_one(table, [1.0, 2.0, 3.0]) == interpolate_one(table, (1, 2, 3))
    with pytest.raises(VolumetricError, match="one value per axis"):
        interpolate_one(table, [1.0, 2.0])
    with pytest.raises(VolumetricError, match="position Y = nan"):
        interpolate_one(table, [1.0, np.nan, 3.0])
    with pytest.raises(VolumetricError, match=r"position Z = inf mm \(row 1\)"):
        interpolate(table, [[0.0, 0.0, 0.0], [0.0, 0.0, np.inf]])
    with pytest.raises(VolumetricError, match="one column per axis"):
        interpolate(table, [0.0, 0.0, 0.0])


def test_a_drives_error_enters_its_direction_only_with_its_sign():
    rng = np.random.default_rng(9)
    grid = SupportGrid(("X", "Y", "Z"), LEVELS)
    zero = np.zeros(grid.shape + (3,))
    pos = np.linspace(-400.0, 400.0, 9)
    err = rng.normal(size=9)
    Q = inside(rng, 50)
    for axis, d, s, col in (("X", 0, -1.0, 0), ("Z", 1, 1.0, 0), ("Y", 2, -1.0, 1)):
        p = pos if axis == "X" else np.linspace(LEVELS[col][0], LEVELS[col][2], 9)
        table = VolumetricTable(grid, 0.0, zero, (FeedbackTable(axis, p, err, d, s),))
        got = interpolate(table, Q)
        want = s * np.interp(Q[:, grid.axes.index(axis)], p, err)
        np.testing.assert_allclose(got[:, d], want, rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(np.delete(got, d, axis=1), 0.0)
        # at its own points its error, whatever the other axes do
        at = np.zeros((p.size, 3))
        at[:, grid.axes.index(axis)] = p
        np.testing.assert_allclose(interpolate(table, at)[:, d], s * err, rtol=1e-14)


def test_shifted_adds_to_the_structure_only():
    rng = np.random.default_rng(10)
    table = random_table(rng)
    moved = shifted(table, [1.0, -2.0, 0.5])
    Q = inside(rng, 20)
    np.testing.assert_allclose(interpolate(moved, Q) - interpolate(table, Q), np.tile([1.0, -2.0, 0.5], (20, 1)),
                               atol=1e-12)
    for a, b in zip(moved.feedback_um, table.feedback_um):
        np.testing.assert_array_equal(a.error_um, b.error_um)
    with pytest.raises(VolumetricError, match="dz = nan"):
        shifted(table, [0.0, 0.0, np.nan])


def test_a_table_refuses_non_finite_values_and_wrong_shapes():
    grid = SupportGrid(("X", "Y"), ((0.0, 1.0), (0.0, 2.0, 3.0)))
    S = np.zeros((2, 3, 3))
    S[1, 2, 1] = np.inf
    with pytest.raises(VolumetricError, match=r"at \{'X': 1.0, 'Y': 3.0\} \(y\) = inf"):
        VolumetricTable(grid, 0.0, S)
    with pytest.raises(VolumetricError, match=r"shape \(2, 2, 3\)"):
        VolumetricTable(grid, 0.0, np.zeros((2, 2, 3)))
    with pytest.raises(VolumetricError, match="feedback of axis Y at 1 mm = nan"):
        VolumetricTable(grid, 0.0, np.zeros((2, 3, 3)), (FeedbackTable("Y", [0.0, 1.0], [0.0, np.nan], 1, 1.0),))
    with pytest.raises(VolumetricError, match="not a grid axis"):
        VolumetricTable(grid, 0.0, np.zeros((2, 3, 3)), (FeedbackTable("Z", [0.0, 1.0], [0.0, 0.0], 2, 1.0),))
    with pytest.raises(VolumetricError, match="time_s"):
        VolumetricTable(grid, np.nan, np.zeros((2, 3, 3)))


# --------------------------------------------------------------------------- rate limit and dict form

def test_limit_table_moves_every_entry_at_most_the_step():
    rng = np.random.default_rng(11)
    old = random_table(rng)
    new = VolumetricTable(old.grid, 65.0, old.structure_um + rng.normal(size=old.structure_um.shape) * 2,
                          tuple(f._replace(error_um=f.error_um + rng.normal(size=f.error_um.size) * 2)
                                for f in old.feedback_um))
    lim, acted = limit_table(new, old, 0.5)
    assert acted and lim.time_s == 65.0
    d = new.structure_um - old.structure_um
    np.testing.assert_allclose(lim.structure_um, old.structure_um + np.clip(d, -0.5, 0.5), rtol=0, atol=1e-14)
    assert np.abs(lim.structure_um - old.structure_um).max() <= 0.5 + 1e-12
    small = np.abs(d) <= 0.5
    np.testing.assert_array_equal(lim.structure_um[small], new.structure_um[small])
    for a, o, n in zip(lim.feedback_um, old.feedback_um, new.feedback_um):
        np.testing.assert_allclose(a.error_um, o.error_um + np.clip(n.error_um - o.error_um, -0.5, 0.5), atol=1e-14)
    same, acted = limit_table(new, old, 100.0)
    assert not acted
    np.testing.assert_allclose(same.structure_um, new.structure_um, atol=1e-12)
    # a drive's entry alone trips the flag
    only_fb = VolumetricTable(old.grid, 70.0, old.structure_um,
                              (old.feedback_um[0]._replace(error_um=old.feedback_um[0].error_um + 1.0),)
                              + old.feedback_um[1:])
    assert limit_table(only_fb, old, 0.5)[1]
    with pytest.raises(VolumetricError, match="different grids"):
        limit_table(random_table(rng, grid=SupportGrid(("X", "Y", "Z"), LEVELS)), old, 1.0)
    with pytest.raises(VolumetricError, match="different drives"):
        limit_table(random_table(rng, feedback=False, grid=old.grid), old, 1.0)
    with pytest.raises(VolumetricError, match="max_step_um"):
        limit_table(new, old, -1.0)


def test_dict_form_round_trips_exactly_through_json():
    rng = np.random.default_rng(12)
    table = random_table(rng)
    back = table_from_dict(json.loads(json.dumps(table_to_dict(table))))
    assert back.grid == table.grid and back.time_s == table.time_s
    np.testing.assert_array_equal(back.structure_um, table.structure_um)
    for a, b in zip(back.feedback_um, table.feedback_um):
        assert (a.axis, a.direction, a.sign) == (b.axis, b.direction, b.sign)
        np.testing.assert_array_equal(a.positions_mm, b.positions_mm)
        np.testing.assert_array_equal(a.error_um, b.error_um)
    Q = inside(rng, 10)
    np.testing.assert_array_equal(interpolate(back, Q), interpolate(table, Q))
    d = table_to_dict(table)
    with pytest.raises(VolumetricError, match="not a volumetric table"):
        table_from_dict({**d, "format": "cd"})
    with pytest.raises(VolumetricError, match="'structure_um'"):
        table_from_dict({k: v for k, v in d.items() if k != "structure_um"})
    with pytest.raises(VolumetricError, match="structure_um"):
        table_from_dict({**d, "structure_um": [[1.0], [2.0, 3.0]]})


# --------------------------------------------------------------------------- the real pose-aware model

@pytest.mark.slow
def test_table_of_a_pose_aware_model_is_drift_along_at_the_grid_points(pose_rom_200mm):
    from hybridcomp.fem.loads import example_loads
    from hybridcomp.models import load_machine

    rom = pose_rom_200mm
    loads = example_loads(load_machine("vmc800"), 4.0, 300.0)
    Y, _ = rom.integrate(loads.time_s, rom.layout().inputs(loads.names, loads.values))
    for points in (3, 4):
        op = table_operator(rom, default_grid(rom, points))
        P = op.grid.points_mm()
        for k in (5, Y.shape[0] // 2, Y.shape[0] - 1):
            table = table_of(op, Y[k], loads.time_s[k])
            want = drift_along(rom, np.repeat(Y[k][None], P.shape[0], axis=0), P)
            assert np.abs(want).max() > 1.0  # a drift worth comparing
            np.testing.assert_allclose(interpolate(table, P), want, rtol=0, atol=1e-10 * np.abs(want).max())
            np.testing.assert_allclose([interpolate_one(table, p) for p in P], want, rtol=0,
                                       atol=1e-10 * np.abs(want).max())
    assert {f.axis for f in op.feedback} == set(rom.meta["feedback"])
    assert vol.TABLE_FORMAT in json.dumps(table_to_dict(table))
