"""The drift at the table point under the tool (``[table_reference] under_tool``), against hand formulas.

vmc800: the table (X moves it, Y its saddle) spans x -600 .. 600, y -400 .. 100 mm at the reference pose, its top at
z = 350 mm; the table reference is its top centre (0, -150, 350); the TCP (0, 0, 700) hangs on the Z headstock.  At
pose (X, Y) the table point under the tool is table point (-X, -Y, 350), clipped to y ≤ 100 (Y < -100: the tool is
behind the table).
"""

from __future__ import annotations

import dataclasses
import logging
import re

import numpy as np
import pytest

from hybridcomp.fem import assembly
from hybridcomp.fem.mesh import mesh_machine
from hybridcomp.fem.model import _material_arrays, drift_rows
from hybridcomp.models import MachineFileError, load_machine, parse_machine
from hybridcomp.models.geometry import table_point
from hybridcomp.models.loader import resolve_machine_path
from hybridcomp.models.toml import read_toml

H_MM = 200.0
MM = 1e-3


def _rows(machine, pose_mm):
    """Drift rows (3 × n) [m/K] of ``machine`` at a pose on the H_MM mesh."""
    mm = mesh_machine(machine, pose_mm, H_MM)
    G, _ = drift_rows(machine, mm, assembly.cell_basis(mm.mesh), _material_arrays(machine, mm))
    return G


def _one_alpha(machine):
    """Every body of cast iron: a uniform rise is a stress-free linear displacement field (exact on any mesh)."""
    ci = machine.materials["cast_iron"]
    return dataclasses.replace(machine, materials={k: dataclasses.replace(ci, name=k) for k in machine.materials})


# --------------------------------------------------------------------------- the machine file


def test_vmc800_sets_under_tool_and_other_files_default_to_the_reference(vmc):
    assert vmc.table_under_tool
    data, _ = read_toml(resolve_machine_path("vmc800"), MachineFileError)
    del data["table_reference"]["under_tool"]
    plain = parse_machine(data, source="plain.toml")
    assert not plain.table_under_tool
    assert table_point(plain, {"X": 300.0}) == plain.table_reference


def test_under_tool_must_be_a_boolean(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(resolve_machine_path("vmc800").read_text().replace("under_tool = true", "under_tool = 1"))
    with pytest.raises(MachineFileError, match=re.escape(f"{path}: field 'table_reference.under_tool' has the wrong "
                                                         "type: 1")):
        load_machine(path)


def test_under_tool_needs_box_bodies(tmp_path):
    (tmp_path / "x.msh").write_text("")
    text = resolve_machine_path("vmc800").read_text().replace("element_size_mm = 80.0", 'file = "x.msh"', 1)
    path = tmp_path / "m.toml"
    path.write_text(re.sub(r"box_mm = .*\n", "", text))
    with pytest.raises(MachineFileError, match=re.escape(f"{path}: field 'table_reference.under_tool' needs box "
                                                         "bodies")):
        load_machine(path)


# --------------------------------------------------------------------------- the point


@pytest.mark.parametrize("pose, local", [
    ({}, (0.0, 0.0, 350.0)),
    ({"X": 0.0, "Y": 150.0}, (0.0, -150.0, 350.0)),  # the tool over the table-top centre
    ({"X": 250.0, "Y": -80.0, "Z": 200.0}, (-250.0, 80.0, 350.0)),  # Z moves the tool vertically only
    ({"X": -400.0, "Y": 325.0}, (400.0, -325.0, 350.0)),
])
def test_table_point_is_under_the_tool(vmc, pose, local, caplog):
    with caplog.at_level(logging.INFO, logger="hybridcomp.models.geometry"):
        p = table_point(vmc, pose)
    assert (p.body, p.position_mm) == ("table", local)
    full = vmc.check_pose(pose)
    tcp = np.asarray(vmc.tcp.position_mm) + vmc.body_offset_mm("spindle", full)
    glob = np.asarray(p.position_mm) + vmc.body_offset_mm("table", full)
    np.testing.assert_allclose(glob[:2], tcp[:2], rtol=0, atol=1e-12)
    assert "beyond the table" not in caplog.text


def test_beyond_the_table_the_point_is_continued_past_its_edge(vmc):
    """The clipped edge point and the tool's point mirrored into the table, weights that extrapolate linearly."""
    from hybridcomp.models.geometry import table_point_weights

    (q, wq), (m, wm) = table_point_weights(vmc, {"X": 100.0, "Y": -325.0})
    assert q.position_mm == (-100.0, 100.0, 350.0) and m.position_mm == (-100.0, -125.0, 350.0)
    assert (wq, wm) == pytest.approx((1.0 + 225.0 / 225.0, -225.0 / 225.0))
    # a linear function of the point is continued exactly to the tool's own y (325 in table coordinates)
    assert wq * q.position_mm[1] + wm * m.position_mm[1] == pytest.approx(325.0)
    assert table_point_weights(vmc, {"X": 100.0, "Y": 0.0}) == ((table_point(vmc, {"X": 100.0, "Y": 0.0}), 1.0),)


def test_tool_beyond_the_table_is_clipped_to_its_edge_and_logged(vmc, caplog):
    with caplog.at_level(logging.INFO, logger="hybridcomp.models.geometry"):
        p = table_point(vmc, {"X": 100.0, "Y": -325.0})
    assert p.position_mm == (-100.0, 100.0, 350.0)  # table y = 325 clipped to its rear edge 100
    assert "the tool (x, y) = (0, 0) mm is beyond the table body 'table'" in caplog.text
    assert "nearest point of its top face, (0, -225) mm" in caplog.text


# --------------------------------------------------------------------------- the drift rows


def test_tool_over_the_table_centre_gives_the_old_rows(vmc):
    """Y = 150 puts the table-top centre under the tool: the rows are the table reference's; at mid travel not."""
    old = dataclasses.replace(vmc, table_under_tool=False)
    centre = {"X": 0.0, "Y": 150.0, "Z": 100.0}
    np.testing.assert_allclose(_rows(vmc, centre), _rows(old, centre), rtol=0, atol=1e-15)
    mid_new, mid_old = _rows(vmc, {}), _rows(old, {})
    assert np.abs(mid_new - mid_old).max() > 1e-3 * np.abs(mid_old).max()


@pytest.mark.parametrize("pose", [{"X": 300.0, "Y": 60.0}, {"X": -200.0, "Y": -250.0}])
def test_uniform_rise_table_points_differ_by_free_expansion(vmc, pose):
    """Uniform ΔT, one α: u(reference) − u(point under the tool) = α ΔT (reference − point) on the table top.

    The second pose has the tool behind the table: the table's displacement is continued past its edge, which is
    exact for this linear expansion, so the hand formula holds at the tool's own x, y there too.  So the drift under
    the tool minus the drift at the reference is that formula, and under a uniform rise the drift under the tool
    has no x or y at all, whereas the reference's drift changes by α ΔT ΔX between two X positions.
    """
    dT = 2.0
    new = _one_alpha(vmc)
    old = dataclasses.replace(new, table_under_tool=False)
    alpha = new.materials["cast_iron"].expansion_1_K
    G_new, G_old = _rows(new, pose), _rows(old, pose)
    d_new, d_old = G_new @ np.full(G_new.shape[1], dT), G_old @ np.full(G_old.shape[1], dT)
    ref = np.asarray(vmc.table_reference.position_mm)
    full = vmc.check_pose(pose)
    tcp = np.asarray(vmc.tcp.position_mm) + vmc.body_offset_mm("spindle", full)
    pt = np.r_[(tcp - vmc.body_offset_mm("table", full))[:2], ref[2]]  # under the tool, on or beyond the table
    expected = alpha * dT * (ref - pt) * MM
    assert abs(expected[0]) > 4e-6  # 200 mm or more off the centre: micrometres
    np.testing.assert_allclose(d_new - d_old, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d_new[:2], 0.0, rtol=0, atol=1e-12)  # no x, y under a uniform rise, anywhere


def test_uniform_rise_reference_drift_moves_with_x_but_not_under_the_tool(vmc):
    """Two poses that differ only in X (the tool over another table point): the old drift differs by α ΔT ΔX in x."""
    dT = 1.5
    new = _one_alpha(vmc)
    old = dataclasses.replace(new, table_under_tool=False)
    alpha = new.materials["cast_iron"].expansion_1_K
    a, b = {"X": -250.0, "Y": 50.0}, {"X": 350.0, "Y": 50.0}

    def drift(m, pose):
        G = _rows(m, pose)
        return G @ np.full(G.shape[1], dT)

    np.testing.assert_allclose(drift(old, b)[0] - drift(old, a)[0], -alpha * dT * 600.0 * MM, rtol=1e-9)
    np.testing.assert_allclose(drift(new, b), drift(new, a), rtol=0, atol=1e-12)


def test_displacement_rows_give_the_drift_rows_and_a_uniform_rise_by_hand(vmc):
    """``displacement_rows`` of the TCP less those of the table points, weighted as the drift takes them, are the drift
    rows ``G`` (to round-off), at a pose whose tool is behind the table (two table points). Under a uniform rise with
    one α, two table points' displacements differ by α ΔT times their distance (free expansion, exact on any mesh)."""
    from hybridcomp.fem.model import build_model, displacement_rows
    from hybridcomp.models.geometry import table_point_weights
    from hybridcomp.models.machine import Point

    pose = {"X": 280.0, "Y": -220.0, "Z": 120.0}
    model = build_model(vmc, pose, H_MM)
    pts = table_point_weights(vmc, pose)
    assert len(pts) == 2  # the tool 120 mm behind the table: the edge and the mirrored point
    R = displacement_rows(model, [vmc.tcp] + [p for p, _ in pts])
    G = R[0] - sum(w * R[1 + i] for i, (_, w) in enumerate(pts))
    np.testing.assert_allclose(G, model.G, rtol=0, atol=1e-9 * np.abs(model.G).max())

    one = _one_alpha(vmc)
    m1 = build_model(one, pose, H_MM)
    a, b = (Point("a", "table", (-300.0, -100.0, 350.0)), Point("b", "table", (250.0, 80.0, 350.0)))
    u = displacement_rows(m1, [a, b]) @ np.full(m1.n, 2.0)
    alpha = one.materials["cast_iron"].expansion_1_K
    want = alpha * 2.0 * (np.asarray(b.position_mm) - np.asarray(a.position_mm)) * MM
    np.testing.assert_allclose(u[1] - u[0], want, rtol=1e-6, atol=1e-12)
