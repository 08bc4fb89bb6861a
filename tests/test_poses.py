"""The drift at any pose: support-pose interpolation, the field carried with the bodies, the pose-aware reduced
model against FE models built at the pose, and the ``reduce --poses`` command."""

from __future__ import annotations

import numpy as np
import pytest

from hybridcomp.cli import main
from hybridcomp.fem.drives import drive_error
from hybridcomp.fem.loads import example_loads
from hybridcomp.fem.mesh import mesh_machine
from hybridcomp.fem.model import build_model
from hybridcomp.fem.poses import PoseGrid, carry_field, pose_drift, support_poses
from hybridcomp.rom.machine import reduce_model
from hybridcomp.rom.poses import FEEDBACK_POINTS, drift_along, grid_of, reduce_at_poses
from hybridcomp.rom.reduced import load_rom, save_rom

H_MM = 200.0
LEVELS = ((-400.0, 0.0, 400.0), (-325.0, 50.0, 325.0), (-275.0, 0.0, 275.0))


@pytest.fixture(scope="module")
def model(model_200mm):
    """The FE model at mid travel (shared with the other modules)."""
    assert model_200mm.machine.mesh.element_size_mm == H_MM
    return model_200mm


@pytest.fixture(scope="module")
def loads(vmc):
    return example_loads(vmc, 4.0, 300.0)


@pytest.fixture(scope="module")
def pose_rom(model, loads):
    """The reduced model to the default tolerance and its pose-aware model over the star with the default levels:
    an FE model built and reduced at each of 14 support poses, so every test that takes it is marked slow."""
    rom = reduce_model(model, check_loads=loads)
    return rom, reduce_at_poses(model, rom, "star", input_scale=np.abs(model.layout().inputs(loads)).max(axis=0))


# --------------------------------------------------------------------------- interpolation

@pytest.mark.parametrize("scheme", ["star", "grid"])
def test_weights_reproduce_what_the_scheme_can_represent(scheme):
    grid = PoseGrid(("X", "Y", "Z"), LEVELS, scheme, support_poses(3, scheme))
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 3))
    c = rng.normal()

    def f(p):  # a sum of quadratics per axis, and with the grid a product of all three
        v = sum(a[i, 0] + a[i, 1] * p[i] + a[i, 2] * p[i] ** 2 for i in range(3)) * 1e-4
        return v + (c * p[0] * p[1] * p[2] * 1e-7 if scheme == "grid" else 0.0)

    values = np.array([f([grid.pose_mm(k)[n] for n in "XYZ"]) for k in range(len(grid.poses))])
    for _ in range(5):
        p = [rng.uniform(lo, hi) for lo, _, hi in LEVELS]
        w = grid.weights(dict(zip("XYZ", p)))
        assert w.sum() == pytest.approx(1.0, abs=1e-12)
        assert w @ values == pytest.approx(f(p), rel=1e-9, abs=1e-12)
    for k in range(len(grid.poses)):  # at a support pose: that pose alone
        np.testing.assert_allclose(grid.weights(grid.pose_mm(k)), np.eye(len(grid.poses))[k], atol=1e-12)
    with pytest.raises(ValueError, match="outside the travel"):
        grid.weights({"X": 401.0})
    assert len(grid.poses) == (7 if scheme == "star" else 27)


def test_star_misses_a_product_of_two_axes():
    grid = PoseGrid(("X", "Y", "Z"), LEVELS, "star", support_poses(3, "star"))
    values = np.array([grid.pose_mm(k)["X"] * grid.pose_mm(k)["Y"] for k in range(len(grid.poses))])
    assert grid.weights({"X": 200.0, "Y": 200.0}) @ values != pytest.approx(200.0 * 200.0, rel=0.5)


@pytest.mark.parametrize("scheme", ["star", "grid"])
def test_more_levels_along_an_axis_follow_a_kink_at_a_level(scheme):
    """Seven levels along Y (``axis_levels``: the model's pose at 50 mm and three evenly spaced on either side):
    piecewise quadratic over the triples (0, 1, 2), (2, 3, 4), (4, 5, 6). A drift that kinks at level 2 (as where
    the tool leaves the table) and is quadratic on either side is reproduced exactly; three levels miss it."""
    from hybridcomp.fem.poses import axis_levels, support_poses_of

    y7 = axis_levels(-325.0, 50.0, 325.0, 7)
    assert y7[0] == -325.0 and y7[3] == 50.0 and y7[-1] == 325.0 and np.allclose(np.diff(y7[:4]), 125.0)
    levels = (LEVELS[0], y7, LEVELS[2])
    grid = PoseGrid(("X", "Y", "Z"), levels, scheme, support_poses_of((3, 7, 3), scheme))
    three = PoseGrid(("X", "Y", "Z"), LEVELS, scheme, support_poses(3, scheme))
    assert len(grid.poses) == (11 if scheme == "star" else 63) and grid.poses[0] == (1, 3, 1)
    assert grid.model_pose_mm == (0.0, 50.0, 0.0) and grid.travel_mm[1] == (-325.0, 325.0)
    kink = y7[2]

    def f(p):  # quadratic in X, a kink in Y at level 2, linear in Z
        return 1e-4 * p[0] ** 2 + 2e-3 * p[0] + 3e-5 * (p[1] - kink) ** 2 * (p[1] < kink) + 1e-3 * p[1] + 4e-3 * p[2]

    def interp(g, p):
        values = np.array([f([g.pose_mm(k)[n] for n in "XYZ"]) for k in range(len(g.poses))])
        return g.weights(dict(zip("XYZ", p))) @ values

    rng = np.random.default_rng(5)
    for _ in range(8):
        p = [rng.uniform(lo, hi) for lo, hi in grid.travel_mm]
        assert grid.weights(dict(zip("XYZ", p))).sum() == pytest.approx(1.0, abs=1e-12)
        assert interp(grid, p) == pytest.approx(f(p), rel=1e-9, abs=1e-12)
    p = [0.0, -250.0, 0.0]
    assert abs(interp(three, p) - f(p)) > 0.1  # the planted miss: one quadratic through -325, 50, 325
    for k in range(len(grid.poses)):
        np.testing.assert_allclose(grid.weights(grid.pose_mm(k)), np.eye(len(grid.poses))[k], atol=1e-12)
    assert PoseGrid.from_dict(grid.as_dict()) == grid


def test_three_levels_are_the_former_grid_and_bad_counts_are_refused(vmc):
    from hybridcomp.fem.poses import axis_levels, parse_levels, support_poses_of

    assert axis_levels(-400.0, 0.0, 400.0) == (-400.0, 0.0, 400.0)
    for scheme in ("star", "grid"):
        assert support_poses_of((3, 3, 3), scheme) == support_poses(3, scheme)
    assert parse_levels("Y=7", ("X", "Y", "Z")) == {"Y": 7} and parse_levels(None, ("X",)) == {}
    assert parse_levels(" X=5 , Z=3 ", ("X", "Y", "Z")) == {"X": 5, "Z": 3}
    for text, msg in (("Y=4", "must be odd"), ("Y=1", "must be odd"), ("Q=5", "no axis 'Q'"), ("Y", "not AXIS=N"),
                      ("Y=x", "not AXIS=N")):
        with pytest.raises(ValueError, match=msg):
            parse_levels(text, ("X", "Y", "Z"))
    with pytest.raises(ValueError, match="odd number of levels"):
        axis_levels(-1.0, 0.0, 1.0, 4)


def test_auto_levels_are_seven_along_the_axes_that_leave_the_table_or_carry_the_tool(vmc):
    """vmc800 takes the drift under the tool, and only its Y moves the table from under the tool (at Y -325 the tool
    is 225 mm behind the table's rear edge); its Z carries the tool (the headstock, on which the spindle is mounted).
    With the drift at the table reference only Z gets more levels; with the spindle mounted on the column, none."""
    import dataclasses

    from hybridcomp.fem.poses import EDGE_LEVELS, auto_levels, default_levels, edge_levels, parse_levels, tool_axes

    axes = [a.name for a in vmc.axes]
    assert EDGE_LEVELS == 7 and edge_levels(vmc) == {"Y": 7} and tool_axes(vmc) == ("Z",)
    assert auto_levels(vmc) == {"Y": 7, "Z": 7} == parse_levels("auto", axes, vmc) == default_levels(vmc, "star")
    assert default_levels(vmc, "grid") == {}  # a grid's support poses are the product of the levels
    at_reference = dataclasses.replace(vmc, table_under_tool=False)
    assert edge_levels(at_reference) == {} and auto_levels(at_reference) == {"Z": 7}
    spindle = vmc.body(vmc.tcp.body)
    on_column = dataclasses.replace(vmc, bodies=tuple(dataclasses.replace(b, mounted_on="column") if b is spindle
                                                      else b for b in vmc.bodies))
    assert tool_axes(on_column) == () and auto_levels(dataclasses.replace(on_column, table_under_tool=False)) == {}
    with pytest.raises(ValueError, match="needs the machine"):
        parse_levels("auto", axes)
    assert parse_levels("3", axes) == {"X": 3, "Y": 3, "Z": 3} and parse_levels("5", axes) == {"X": 5, "Y": 5, "Z": 5}
    with pytest.raises(ValueError, match="--pose-levels '4': X = 4, a number of levels must be odd"):
        parse_levels("4", axes)


# --------------------------------------------------------------------------- the field carried with the bodies

def test_carried_field_moves_with_each_body(vmc, model):
    pose = {"X": 300.0, "Y": -200.0, "Z": 150.0}
    mm = mesh_machine(vmc, pose, H_MM)
    Pi = carry_field(model, mm)
    np.testing.assert_allclose(Pi @ np.ones(model.n), 1.0, atol=1e-12)
    # a field linear in x, y, z at the model's pose reads, at each node, the point of its body at that pose
    g = np.array([1.0, -2.0, 0.5])
    got = Pi @ (g @ model.mesh.mesh.p)
    for bi, body in enumerate(mm.body_names):
        nodes = np.unique(mm.mesh.t[:, mm.body_of_element == bi])
        shift = (vmc.body_offset_mm(body, model.mesh.pose_mm) - vmc.body_offset_mm(body, pose)) * 1e-3
        inside = [n for n in nodes if np.sum(mm.body_of_element[np.any(mm.mesh.t == n, axis=0)] != bi) == 0]
        np.testing.assert_allclose(got[inside], g @ (mm.mesh.p[:, inside] + shift[:, None]), atol=1e-12)


def test_uniform_rise_drift_at_a_support_pose_equals_the_fe_model_built_there(vmc, model):
    pd = pose_drift(model, "star")
    k = 5  # Z at its lower end
    fe = build_model(vmc, pd.grid.pose_mm(k), H_MM)
    np.testing.assert_allclose(pd.rows[k] @ np.ones(model.n), fe.G @ np.ones(fe.n), rtol=1e-9, atol=1e-15)


# --------------------------------------------------------------------------- the pose-aware reduced model

@pytest.mark.slow
def test_pose_aware_rom_keeps_the_model_pose_outputs(pose_rom, loads):
    rom, pr = pose_rom
    a, b = rom.simulate(loads), pr.simulate(loads)
    np.testing.assert_allclose(b.drift_um, a.drift_um, atol=1e-9)
    np.testing.assert_allclose(b.sensors_degC, a.sensors_degC, atol=1e-12)
    assert pr.order == sum(pr.meta["poses"]["orders"])
    support = len(pr.meta["poses"]["poses"]) - 1  # after the model's pose: 6 with three levels, 14 by default
    assert len(pr.output_names) == rom.C.shape[0] + 3 * support + 3 * FEEDBACK_POINTS  # their drift, 3 drives' errors


@pytest.mark.slow
def test_pose_aware_rom_carries_the_drives_exactly(vmc, model, pose_rom, loads):
    rom, pr = pose_rom
    u = pr.layout().inputs(loads.names, loads.values)[25]
    y = pr.outputs(pr.steady_state(u))
    x_mid = pr.steady_state(u)[:rom.order]
    for axis in "XYZ":
        fb = pr.meta["feedback"][axis]
        got = y[[pr.output_names.index(n) for n in fb["outputs"]]] * 1e6
        err = drive_error(model, vmc.drive(axis))  # the carrier (and a scale) on the model pose's field
        if fb["feedback"] == "rotary_encoder":  # the screw's own block: its steady state is the screw model's
            want = err.error_um(fb["positions_mm"], rom.V @ x_mid, err.screw.steady(u))
        else:
            want = err.error_um(fb["positions_mm"], rom.V @ x_mid)
        np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-9)
    # along a path the drift is the structure's plus each drive's error, signed by the side the axis moves
    Y = y[None, :]
    at = np.array([[123.0, -40.0, 77.0]])
    with_fb, without = drift_along(pr, Y, at), drift_along(pr, Y, at, feedback=False)
    fb = pr.meta["feedback"]["X"]
    e_x = np.interp(123.0, fb["positions_mm"], y[[pr.output_names.index(n) for n in fb["outputs"]]] * 1e6)
    fb_z = pr.meta["feedback"]["Z"]
    e_z = np.interp(77.0, fb_z["positions_mm"], y[[pr.output_names.index(n) for n in fb_z["outputs"]]] * 1e6)
    assert with_fb[0, 0] - without[0, 0] == pytest.approx(-e_x, rel=1e-12)  # X moves the table
    assert with_fb[0, 2] - without[0, 2] == pytest.approx(e_z, rel=1e-12)  # Z moves the tool


@pytest.mark.slow
def test_pose_aware_rom_uniform_air_rise_gives_the_feedbacks_alpha_along_each_axis(vmc, pose_rom):
    """All zones' air +1 K, no heat, steady: a uniform rise.

    At a table target fixed on the table (the ISO 230-3 convention, tests/test_drive_physics.py) the drift along
    each axis grows with the feedback's α alone.  vmc800 takes the drift at the table point under the tool: along
    X and Y (the table side) that point moves with the table's own free expansion, so the structure adds nothing
    along the axis and what remains is the drive's difference to the carrier's cast iron, sign (α_screw − α_cast
    iron); along Z (the tool side, the point under the tool stays) the scale's α alone, as at a fixed target.
    """
    from tests.test_drive_physics import ALPHA_CAST_IRON, FEEDBACK_ALPHA, SIGN, STRUCTURE_TOL_UM_PER_M, slope_um_per_m

    _, pr = pose_rom
    layout = pr.layout()
    u = np.zeros(layout.n_inputs)
    u[len(layout.heat_inputs):] = 1.0
    Y = pr.outputs(pr.steady_state(u))[None, :]
    for i, axis in enumerate(a.name for a in vmc.axes):
        p = np.linspace(*vmc.axis(axis).travel_mm, 5)
        at = np.zeros((p.size, 3))
        at[:, i] = p
        d = np.array([drift_along(pr, Y, row[None])[0, i] for row in at])
        table_side = SIGN[axis] < 0
        want = SIGN[axis] * (FEEDBACK_ALPHA[axis] - (ALPHA_CAST_IRON if table_side else 0.0)) * 1e6
        assert slope_um_per_m(p, d) == pytest.approx(want, abs=STRUCTURE_TOL_UM_PER_M), axis


@pytest.mark.slow
def test_pose_aware_rom_matches_fe_at_a_support_pose_and_beats_the_model_pose_off_grid(vmc, pose_rom, loads):
    _, pr = pose_rom
    U = pr.layout().inputs(loads.names, loads.values)
    Y, _ = pr.integrate(loads.time_s, U)
    grid = grid_of(pr)
    k = 2  # X at its upper end
    at = grid.pose_mm(k)
    fe = build_model(vmc, at, H_MM).simulate(loads, scheme="theta", theta=0.5).drift_um
    got = drift_along(pr, Y, np.array([[at[a] for a in grid.axes]]), feedback=False)  # FE knows the structure only
    assert np.abs(got - fe).max() < pr.meta["tol_um"]
    # the tool over the table: at Y = -180 (behind it) this mesh's z interpolation error (1.9 µm, the same at the
    # table reference) exceeds what the mid pose misses now that the drift is taken under the tool (its dx error
    # there fell from 5.1 to 0.25 µm: the table's own expansion no longer enters it)
    off = {"X": 250.0, "Y": 180.0, "Z": 160.0}
    fe = build_model(vmc, off, H_MM).simulate(loads, scheme="theta", theta=0.5).drift_um
    got = drift_along(pr, Y, np.array([[off[a] for a in grid.axes]]), feedback=False)
    mid_only = pr.simulate(loads).drift_um
    # on this coarse mesh the grid itself changes with the pose (the FE models at support poses, interpolated,
    # miss by as much): the accuracy criterion is benchmarks/pose_drift.py's, on finer meshes
    assert np.abs(got - fe).max() < 0.4 * np.abs(mid_only - fe).max()
    # what the reduced models approximate: FE models at the support poses, interpolated the same way; against that
    # the pose-aware model is held to the reduction tolerance at the off-grid pose too
    runs = np.array([build_model(vmc, grid.pose_mm(j), H_MM).simulate(loads, scheme="theta", theta=0.5).drift_um
                     for j in range(len(grid.poses))])
    assert np.abs(got - np.tensordot(grid.weights(off), runs, axes=1)).max() < pr.meta["tol_um"]
    # along a path: the positions of every row
    path = np.column_stack([np.linspace(-400, 400, loads.time_s.size), np.zeros(loads.time_s.size),
                            np.zeros(loads.time_s.size)])
    d = drift_along(pr, Y, path)
    np.testing.assert_allclose(d[loads.time_s.size // 2], drift_along(pr, Y[loads.time_s.size // 2:][:1],
                                                                      path[loads.time_s.size // 2][None])[0])


@pytest.mark.slow
def test_pose_aware_rom_round_trips_through_its_file(pose_rom, tmp_path):
    _, pr = pose_rom
    back = load_rom(save_rom(tmp_path / "p.npz", pr))
    assert grid_of(back) == grid_of(pr) and back.rom_id == pr.rom_id


@pytest.mark.slow
def test_pose_aware_reduction_refuses_a_model_without_basis_or_at_a_travel_end(vmc, model, pose_rom):
    import dataclasses

    from hybridcomp.errors import HybridcompError

    rom, pr = pose_rom
    with pytest.raises(HybridcompError, match="basis"):
        reduce_at_poses(model, dataclasses.replace(rom, V=None, _cache={}))
    with pytest.raises(HybridcompError, match="pose-aware already"):
        reduce_at_poses(model, dataclasses.replace(rom, meta=pr.meta, _cache={}))
    with pytest.raises(HybridcompError, match="one pose only"):
        grid_of(rom)


def test_reduce_cli_refuses_pose_options_that_would_be_ignored(capsys, tmp_path):
    assert main(["reduce", "--pose-enrich", "5", "--out", str(tmp_path / "r.npz")]) == 2
    assert "--pose-enrich applies with --poses only" in capsys.readouterr().err
    assert main(["reduce", "--poses", "star", "--pose", "Z=275", "--out", str(tmp_path / "r.npz")]) == 2
    assert "travel end" in capsys.readouterr().err
    assert main(["reduce", "--poses", "star", "--no-basis", "--out", str(tmp_path / "r.npz")]) == 2
    assert main(["reduce", "--workers", "2", "--out", str(tmp_path / "r.npz")]) == 2
    assert "--workers applies with --poses only" in capsys.readouterr().err
    assert main(["reduce", "--poses", "star", "--scheduler", "udp://x", "--out", str(tmp_path / "r.npz")]) == 2
    capsys.readouterr()
    assert main(["reduce", "--pose-levels", "Y=7", "--out", str(tmp_path / "r.npz")]) == 2
    assert "--pose-levels applies with --poses only" in capsys.readouterr().err
    assert main(["reduce", "--poses", "star", "--pose-levels", "Y=6", "--out", str(tmp_path / "r.npz")]) == 2
    assert "--pose-levels 'Y=6': Y = 6, a number of levels must be odd" in capsys.readouterr().err
    assert not (tmp_path / "r.npz").exists()


@pytest.mark.slow
def test_support_poses_run_as_a_batch_on_a_process_pool(model, pose_rom, loads):
    rom, serial = pose_rom
    pooled = reduce_at_poses(model, rom, "star", input_scale=np.abs(model.layout().inputs(loads)).max(axis=0), workers=2)
    # the same arithmetic in worker processes with one BLAS thread each: round-off apart
    assert pooled.meta["poses"]["orders"] == serial.meta["poses"]["orders"]
    for name in ("M", "K", "B", "C"):
        a, b = getattr(pooled, name), getattr(serial, name)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8 * np.abs(b).max(), err_msg=name)


@pytest.mark.slow
def test_a_pose_aware_model_is_refused_where_one_pose_is_meant(vmc, pose_rom):
    from hybridcomp.diagnose import prepare_model

    with pytest.raises(ValueError, match="pose-aware reduced model"):
        prepare_model(vmc, rom=pose_rom[1])
