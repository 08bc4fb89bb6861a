"""A model's outputs as typed groups (models.layout.OutputLayout): found by name and metadata, never by position.

The pose-aware file here is written the way ``reduce --poses`` wrote it before the layout existed (its arrays and its
JSON metadata, no field the layout added), so a file of that time is read as it is.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridcomp.fem.operators import ThermalOperators
from hybridcomp.fem.poses import PoseGrid, support_poses
from hybridcomp.models.layout import (
    OutputLayoutError,
    body_output_names,
    feedback_output_names,
    output_layout,
    pose_output_names,
)
from hybridcomp.rom.poses import drift_along, grid_of
from hybridcomp.rom.reduced import FORMAT, FORMAT_VERSION, ReducedModel, RomInputError, load_rom

SENSORS = ("T1", "T2")
LEVELS = ((-400.0, 0.0, 400.0), (-325.0, 0.0, 325.0), (-275.0, 0.0, 275.0))
GRID = PoseGrid(("X", "Y", "Z"), LEVELS, "star", support_poses(3, "star"))
POS_X = np.linspace(-400.0, 400.0, 5)
POS_Z = np.linspace(-275.0, 275.0, 3)
# in the order reduce_at_poses wrote them: the model pose's block (sensors, drift, then the Z scale's errors on its
# field), then the six further support poses' drift, then the X screw's errors
NAMES = (SENSORS + ("dx", "dy", "dz") + tuple(f"eZ@{p:g}" for p in POS_Z)
         + tuple(f"{d}@{k}" for k in range(1, 7) for d in ("dx", "dy", "dz")) + tuple(f"eX@{p:g}" for p in POS_X))
DRIFT_AT = {0: (2, 3, 4), **{k: (8 + 3 * (k - 1), 9 + 3 * (k - 1), 10 + 3 * (k - 1)) for k in range(1, 7)}}
EZ_AT, EX_AT = (5, 6, 7), tuple(range(26, 31))


def old_meta() -> dict:
    """The metadata of a pose-aware model as reduce_at_poses and save_rom wrote it (field by field)."""
    return {
        "machine": {"name": "vmc800", "file": "vmc800.toml", "sha256": "0" * 64},
        "pose_mm": {"X": 0.0, "Y": 0.0, "Z": 0.0}, "nodes": 10, "element_size_mm": 200.0,
        "reference_temperature_degC": 20.0, "n_sensors": 2, "h_range": [0.5, 2.0], "h_nominal_W_m2K": [8.0],
        "tol_K": 0.05, "tol_um": 0.2,
        "poses": {"axes": ["X", "Y", "Z"], "levels_mm": [list(v) for v in LEVELS], "scheme": "star",
                  "poses": [list(p) for p in GRID.poses], "orders": [3, 3], "enrich": 20, "build_s": 1.0},
        "feedback": {
            "X": {"feedback": "rotary_encoder", "positions_mm": POS_X.tolist(),
                  "outputs": [f"eX@{p:g}" for p in POS_X], "direction": 0, "sign": -1.0},
            "Z": {"feedback": "linear_scale", "positions_mm": POS_Z.tolist(),
                  "outputs": [f"eZ@{p:g}" for p in POS_Z], "direction": 2, "sign": 1.0},
        },
    }


def old_pose_aware_file(path) -> ReducedModel:
    """A small pose-aware model written as a file of the format before the layout; returns the model itself."""
    rng = np.random.default_rng(7)
    r = 6
    A = rng.normal(size=(r, r))
    rom = ReducedModel(ThermalOperators(
        M=np.eye(r), K=A @ A.T + r * np.eye(r), H=np.eye(r)[None], h_W_m2K=np.array([8.0]),
        B=rng.normal(size=(r, 1)), Hb=rng.normal(size=(r, 1)), C=rng.normal(size=(len(NAMES), r)) * 1e-6,
        input_names=("spindle_W", "air_degC"), output_names=NAMES), meta=old_meta())
    meta = {**old_meta(), "format": FORMAT, "format_version": FORMAT_VERSION, "input_names": list(rom.input_names),
            "output_names": list(NAMES), "order": r, "rom_id": rom.rom_id}
    with path.open("wb") as fh:
        np.savez_compressed(fh, M=rom.M, K=rom.K, H=rom.H, h_W_m2K=rom.h_W_m2K, B=rom.B, Hb=rom.Hb, C=rom.C,
                            meta_json=np.array(json.dumps(meta)))
    return rom


def test_a_pose_aware_file_of_the_old_format_loads_with_every_group(tmp_path):
    old_pose_aware_file(tmp_path / "old.npz")
    rom = load_rom(tmp_path / "old.npz")
    out = rom.output_layout()
    assert out.sensors == SENSORS and out.indices("sensors") == (0, 1) and out.indices("sensors", "T2") == (1,)
    assert out.indices("drift") == DRIFT_AT[0] and out.n_poses == 7
    for k in range(7):
        assert out.pose_indices(k) == DRIFT_AT[k]
        assert [NAMES[i] for i in out.pose_indices(k)] == (["dx", "dy", "dz"] if k == 0 else list(pose_output_names(k)))
    assert out.indices("poses") == sum((DRIFT_AT[k] for k in range(1, 7)), ())
    assert out.feedback_axes == ("X", "Z")  # the metadata's order, not the outputs'
    fx, fz = out.feedback_of("X"), out.feedback_of("Z")
    assert fx.indices == EX_AT and fz.indices == EZ_AT and out.indices("feedback") == EX_AT + EZ_AT
    assert fx.positions_mm == tuple(POS_X) and (fx.direction, fx.sign, fz.direction, fz.sign) == (0, -1.0, 2, 1.0)
    assert fx.names == feedback_output_names("X", POS_X) and out.bodies == ()
    # every table's columns match its indices one for one
    for group in ("sensors", "drift", "poses", "feedback", "bodies"):
        assert len(out.columns(group)) == len(out.indices(group))
    assert out.columns("poses")[:4] == ("pose1_dx_um", "pose1_dy_um", "pose1_dz_um", "pose2_dx_um")
    assert out.columns("feedback")[0] == "X_feedback_um@-400" and out.columns("feedback")[-1] == "Z_feedback_um@275"
    assert out.columns("sensors") == ("T1_degC", "T2_degC") and out.columns("drift") == ("dx_um", "dy_um", "dz_um")


def test_drift_along_an_old_file_is_the_hand_sum_of_its_outputs(tmp_path):
    old_pose_aware_file(tmp_path / "old.npz")
    rom = load_rom(tmp_path / "old.npz")
    rng = np.random.default_rng(1)
    nt = 4
    Y = rng.normal(size=(nt, len(NAMES))) * 1e-6
    P = np.column_stack([rng.uniform(-400, 400, nt), rng.uniform(-325, 325, nt), rng.uniform(-275, 275, nt)])
    W = grid_of(rom).weights_along(P)
    want = np.einsum("tk,tkd->td", W, np.stack([Y[:, list(DRIFT_AT[k])] for k in range(7)], axis=1)) * 1e6
    np.testing.assert_allclose(drift_along(rom, Y, P, feedback=False), want, rtol=1e-12)
    for t in range(nt):  # X moves the table (sign -1, into dx), the Z scale's error adds to dz
        want[t, 0] -= np.interp(P[t, 0], POS_X, Y[t, list(EX_AT)] * 1e6)
        want[t, 2] += np.interp(P[t, 2], POS_Z, Y[t, list(EZ_AT)] * 1e6)
    np.testing.assert_allclose(drift_along(rom, Y, P), want, rtol=1e-12)


def test_body_rows_are_a_group_of_their_own():
    names = SENSORS + ("dx", "dy", "dz") + body_output_names("bed") + body_output_names("column")
    out = output_layout(names, {"n_sensors": 2})
    assert out.bodies == ("bed", "column")
    # the diagnosis' rows as it found them by position: the last 3 per body, in order
    assert out.body_indices("bed") == (5, 6, 7) and out.body_indices("column") == (8, 9, 10)
    assert out.columns("bodies") == ("bed_dx_um", "bed_dy_um", "bed_dz_um", "column_dx_um", "column_dy_um", "column_dz_um")
    assert out.indices("poses") == () and out.indices("feedback") == () and out.n_poses == 1
    Y = np.arange(2 * len(names), dtype=float).reshape(2, -1)
    np.testing.assert_array_equal(out.take(Y, "bodies", "column"), Y[:, 8:11])


def test_a_plain_model_has_sensors_and_drift_only():
    out = output_layout(("T1", "dx", "dy", "dz"))
    assert (out.sensors, out.indices("sensors"), out.drift_indices) == (("T1",), (0,), (1, 2, 3))
    assert out.pose_indices(0) == (1, 2, 3)
    with pytest.raises(OutputLayoutError, match="pose 1 has no drift outputs"):
        out.pose_indices(1)
    with pytest.raises(OutputLayoutError, match="axis 'X' has no positioning-error outputs"):
        out.feedback_of("X")
    with pytest.raises(OutputLayoutError, match="unknown output group 'drifts'"):
        out.indices("drifts")


@pytest.mark.parametrize("names, meta, match", [
    (("T1", "dy", "dx", "dz"), {}, "no dx, dy, dz after the sensors"),
    (("T1", "dx", "dy", "dz"), {"n_sensors": 2}, "field 'n_sensors' is 2, but 1 outputs precede"),
    (("T1", "dx", "dy", "dz", "dx@1", "dy@1"), {"poses": {"poses": [[1], [0]]}}, "output 'dz@1' of support pose 1 is missing"),
    (("T1", "dx", "dy", "dz", "y7"), {}, "output 'y7' belongs to no group"),
    (("T1", "dx", "dy", "dz", "dx@bed", "dy@bed"), {}, "output 'dz@bed' of body 'bed' is missing"),
    (("T1", "dx", "dy", "dz", "T1"), {}, "output 'T1' appears more than once"),
    (("T1", "dx", "dy", "dz", "eX@0"), {"feedback": {"X": {"outputs": ["eX@0"], "positions_mm": [0.0, 1.0],
                                                           "direction": 0, "sign": 1}}}, "1 outputs at 2 positions"),
])
def test_outputs_that_form_no_groups_are_named(names, meta, match):
    with pytest.raises(OutputLayoutError, match=match):
        output_layout(names, meta, "model.npz")


def test_an_external_systems_outputs_have_no_groups():
    rom = ReducedModel(ThermalOperators(M=np.eye(1), K=np.eye(1), H=np.zeros((0, 1, 1)), h_W_m2K=np.zeros(0),
                                        B=np.ones((1, 1)), Hb=np.zeros((1, 0)), C=np.ones((2, 1)),
                                        input_names=("u1",), output_names=("y1", "y2")))
    with pytest.raises(RomInputError, match="no dx, dy, dz after the sensors"):
        rom.output_layout()
