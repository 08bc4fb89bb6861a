"""The machine-file loader: the bundled vmc800, the README example, and bad files.

Bad files are the text of vmc800.toml with one edit, written to ``tmp_path``.
Every bad-file test checks that ``MachineFileError`` names the file path, the
field and the offending value.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import pytest

from hybridcomp.models import MachineFileError, bundled_machines, load_machine, parse_machine
from hybridcomp.models.loader import resolve_machine_path

VMC800_PATH = resolve_machine_path("vmc800")
VMC800 = VMC800_PATH.read_text(encoding="utf-8")
README = Path(__file__).resolve().parents[1] / "models" / "README.md"


def edit(old: str, new: str, text: str = VMC800) -> str:
    """Replace ``old`` (which must occur exactly once, so an edit can never silently miss) by ``new``."""
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times in the machine file"
    return text.replace(old, new)


def append(extra: str, text: str = VMC800) -> str:
    return text.rstrip("\n") + "\n\n" + extra.strip("\n") + "\n"


def load_error(tmp_path: Path, text: str) -> str:
    """Write ``text`` to a file, load it, and return the error message (which must name the file)."""
    path = tmp_path / "bad_machine.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(MachineFileError) as info:
        load_machine(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    return msg


def assert_names(msg: str, *parts: str) -> None:
    for p in parts:
        assert p in msg, f"{p!r} not in message: {msg}"


def readme_example() -> str:
    """The TOML block after the minimal-example marker in models/README.md."""
    text = README.read_text(encoding="utf-8")
    m = re.search(r"<!-- minimal-example.*?-->\s*```toml\n(.*?)```", text, flags=re.S)
    assert m, "models/README.md has no minimal-example toml block"
    return m.group(1)


# --------------------------------------------------------------------------- the bundled machine


def test_vmc800_is_bundled():
    assert "vmc800" in bundled_machines()
    assert VMC800_PATH.name == "vmc800.toml"


def test_vmc800_machine_and_sensors(vmc):
    assert vmc.name == "vmc800"
    assert vmc.reference_temperature_degC == 20.0
    assert vmc.spindle_max_speed_rpm == 12000.0
    assert [s.name for s in vmc.sensors] == [f"T{i}" for i in range(1, 9)]
    assert {s.name: s.body for s in vmc.sensors} == {
        "T1": "spindle", "T2": "headstock", "T3": "column", "T4": "column",
        "T5": "column", "T6": "bed", "T7": "table", "T8": "bed",
    }
    assert (vmc.tcp.body, vmc.table_reference.body) == ("spindle", "table")
    # supports without 'body' are located in the ground body
    assert [(s.name, s.body, len(s.directions)) for s in vmc.supports] == [("A", "bed", 3), ("B", "bed", 2), ("C", "bed", 1)]
    assert vmc.source == str(VMC800_PATH) and len(vmc.sha256) == 64


def test_vmc800_axes_and_segments(vmc):
    assert [(a.name, a.direction, a.moves) for a in vmc.axes] == [("X", 0, "table"), ("Y", 1, "saddle"), ("Z", 2, "headstock")]
    assert [a.n_segments for a in vmc.axes] == [4, 4, 4]
    assert vmc.axis("X").segment_bounds_mm == (-400.0, -200.0, 0.0, 200.0, 400.0)
    assert vmc.axis("Z").travel_mm == (-275.0, 275.0)
    assert vmc.default_pose_mm() == {"X": 0.0, "Y": 0.0, "Z": 0.0}
    # the table moves with X and, through the saddle it is mounted on, with Y
    assert vmc.body_offset_mm("table", {"X": 100.0, "Y": -50.0, "Z": 30.0}).tolist() == [100.0, -50.0, 0.0]
    assert vmc.body_offset_mm("spindle", {"X": 100.0, "Y": -50.0, "Z": 30.0}).tolist() == [0.0, 0.0, 30.0]
    assert vmc.body_offset_mm("column", {"X": 100.0, "Y": -50.0, "Z": 30.0}).tolist() == [0.0, 0.0, 0.0]


def test_vmc800_heat_inputs(vmc):
    names = vmc.heat_inputs()
    fixed = [s.name for s in vmc.heat_sources if s.kind == "fixed"]
    moving = [s.name for s in vmc.heat_sources if s.kind == "moving"]
    assert len(fixed) == 12 and moving == ["x_nut", "x_carriages", "y_nut", "y_carriages", "z_nut", "z_carriages"]
    assert len(names) == 12 + 6 * 4 == 36
    assert len(set(names)) == len(names)
    assert names[:4] == ("x_motor", "x_bearing_fixed", "x_bearing_floating", "x_nut[1]")
    assert [n for n in names if n.startswith("x_nut")] == ["x_nut[1]", "x_nut[2]", "x_nut[3]", "x_nut[4]"]
    assert "x_nut" not in names and "spindle_motor" in names
    # moving sources heat the carrier of their axis and are driven by it
    by = {s.name: s for s in vmc.heat_sources}
    assert [(by[n].body, by[n].driver) for n in ("x_nut", "y_nut", "z_nut")] == [("saddle", "X"), ("bed", "Y"), ("column", "Z")]
    assert by["x_motor"].axis is None and by["x_motor"].driver == "X"
    assert by["spindle_motor"].size_mm == (200.0, 200.0, 250.0)


def test_vmc800_power_law(vmc):
    by = {s.name: s for s in vmc.heat_sources}
    front = by["spindle_bearing_front"]
    assert front.driver == "spindle" and front.exponent == 1.67
    assert front.power_W > 0 and front.power_table is None
    assert float(vmc.source_power_W(front, 1.0)) == pytest.approx(front.power_W)
    assert float(vmc.source_power_W(front, 0.5)) == pytest.approx(front.power_W * 0.5**1.67)
    assert float(vmc.source_power_W(front, 2.0)) == pytest.approx(front.power_W)  # the factor is clipped to [0, 1]
    assert float(vmc.source_power_W(front, 0.0)) == 0.0
    nut = by["x_nut"]
    assert float(vmc.source_power_W(nut, 0.25)) == pytest.approx(0.25 * nut.power_W)


def test_vmc800_zones(vmc):
    assert [(z.name, z.h_W_m2K, z.air, z.rest) for z in vmc.zones] == [
        ("ws_table", 10.0, "workspace", False),
        ("ws_spindle", 18.0, "workspace", False),
        ("floor", 3.0, "ambient", False),
        ("ambient", 6.0, "ambient", True),
    ]
    ws = vmc.zones[0]
    assert [s.body for s in ws.surfaces] == ["table", "saddle", "bed"]
    assert ws.surfaces[0].faces == ("+x", "-x", "+y", "-y", "+z", "-z")  # default: all six faces
    assert ws.surfaces[2].faces == ("+z",)
    assert ws.surfaces[2].region_mm == ((-900.0, -1000.0, 0.0), (900.0, 500.0, 0.0))
    assert vmc.zones[1].surfaces[1].faces == ("-z", "-y")
    assert vmc.zones[3].surfaces == ()


# --------------------------------------------------------------------------- the README example


def test_readme_minimal_example_loads():
    m = parse_machine(tomllib.loads(readme_example()), source="example.toml")
    assert m.name == "slide1"
    assert [b.name for b in m.bodies] == ["bed", "slide"] and [a.name for a in m.axes] == ["X"]
    assert m.heat_inputs() == ("x_motor", "x_nut[1]", "x_nut[2]", "x_nut[3]")
    assert [z.name for z in m.zones] == ["ambient"]
    assert m.heat_sources[1].body == "bed"  # the carrier of X
    assert m.mesh.element_size_mm == 50.0 and m.mesh.file is None


def test_readme_example_error_quoted_in_readme():
    text = edit("position_mm = [0.0, 0.0, -30.0]", "position_mm = [300.0, 0.0, -30.0]", readme_example())
    with pytest.raises(MachineFileError) as info:
        parse_machine(tomllib.loads(text), source="example.toml")
    quoted = (
        "field 'heat_sources[1].position_mm' = [300.0, 0.0, -30.0] mm leaves its carrier body 'bed' at X = 300.0 mm"
    )
    assert str(info.value).startswith("example.toml: " + quoted)
    assert " ".join(quoted.split()) in " ".join(README.read_text(encoding="utf-8").split())


# --------------------------------------------------------------------------- bad files

GUARD_FLOATING = """
[[bodies]]
name = "guard"
material = "steel"
box_mm = [[2000.0, 2000.0, 2000.0], [2100.0, 2100.0, 2100.0]]
mounted_on = "bed"
"""

# touches the bed only along its vertical edge at x = 900, y = 1100: no face contact
GUARD_EDGE = """
[[bodies]]
name = "guard"
material = "steel"
box_mm = [[900.0, 1100.0, -400.0], [1000.0, 1200.0, -300.0]]
mounted_on = "bed"
"""

# on the bed top, inside the saddle's path only at Y = 0 (saddle y = -450..150 shifted by -325..325)
BLOCK_IN_SADDLE_PATH = """
[[bodies]]
name = "block"
material = "steel"
box_mm = [[-100.0, -170.0, 0.0], [100.0, -130.0, 100.0]]
mounted_on = "bed"
"""

BAD_CASES = {
    # unknown keys, with did-you-mean
    "typo_required_body_key": (
        edit('name = "spindle"\nmaterial = "steel"', 'name = "spindle"\nmatrial = "steel"'),
        ["field 'bodies[5].matrial'", "is not a known field", "did you mean 'material'?"],
    ),
    "typo_optional_body_key": (
        edit('mounted_on = "headstock"', 'mounted_onn = "headstock"'),
        ["field 'bodies[5].mounted_onn'", "is not a known field", "did you mean 'mounted_on'?"],
    ),
    "typo_heat_source_key": (
        edit("exponent = 1.2", "exponnent = 1.2"),
        ["field 'heat_sources[17].exponnent'", "is not a known field", "did you mean 'exponent'?"],
    ),
    "typo_top_level_table": (
        edit("[[sensors]]\nname = \"T8\"", "[[sensor]]\nname = \"T8\""),
        ["field 'sensor'", "is not a known field", "did you mean 'sensors'?"],
    ),
    "unknown_key_in_surface": (
        edit('surfaces = [{ body = "bed", faces = ["-z"] }]', 'surfaces = [{ body = "bed", face = ["-z"] }]'),
        ["field 'zones[2].surfaces[0].face'", "is not a known field", "did you mean 'faces'?"],
    ),
    "unknown_key_in_surface_region": (
        edit('faces = ["+z"], region_mm =', 'faces = ["+z"], region ='),
        ["field 'zones[0].surfaces[2].region'", "is not a known field", "did you mean 'region_mm'?"],
    ),
    "key_not_allowed_for_fixed_source": (
        edit('name = "spindle_motor"\n', 'name = "spindle_motor"\naxis = "Z"\n'),
        ["field 'heat_sources[17].axis'", "= 'Z' is only for moving sources"],
    ),
    # references
    "unknown_material": (
        edit('name = "spindle"\nmaterial = "steel"', 'name = "spindle"\nmaterial = "stainless"'),
        ["field 'bodies[5].material'", "unknown material 'stainless'", "['cast_iron', 'steel']"],
    ),
    "unknown_mounted_on": (
        edit('mounted_on = "headstock"', 'mounted_on = "headstok"'),
        ["field 'bodies[5].mounted_on'", "unknown body 'headstok'"],
    ),
    "mounting_cycle": (
        edit(
            "box_mm = [[-900.0, -1000.0, -800.0], [900.0, 1100.0, 0.0]]",
            'box_mm = [[-900.0, -1000.0, -800.0], [900.0, 1100.0, 0.0]]\nmounted_on = "table"',
        ),
        ["field 'bodies.mounted_on'", "cycle bed -> table -> saddle -> bed"],
    ),
    "mounted_on_itself": (
        edit('mounted_on = "headstock"', 'mounted_on = "spindle"'),
        ["field 'bodies.mounted_on'", "cycle spindle -> spindle"],
    ),
    "duplicate_sensor_name": (
        edit('name = "T2"', 'name = "T1"'),
        ["field 'sensors'", "name 'T1' twice"],
    ),
    "bad_axis_direction": (
        edit('direction = "z"', 'direction = "Z"'),
        ["field 'axes[2].direction'", "got 'Z'", "('x', 'y', 'z')"],
    ),
    "bad_axis_direction_word": (
        edit('direction = "x"', 'direction = "horizontal"'),
        ["field 'axes[0].direction'", "got 'horizontal'"],
    ),
    "bad_support_direction": (
        edit('directions = ["z"]', 'directions = ["q"]'),
        ["field 'supports[2].directions'", "got ['q']"],
    ),
    "repeated_support_direction": (
        edit('directions = ["y", "z"]', 'directions = ["z", "z"]'),
        ["field 'supports[1].directions'", "got ['z', 'z']", "distinct"],
    ),
    # convection
    "h_zero": (
        edit("h_W_m2K = 3.0", "h_W_m2K = 0"),
        ["field 'zones[2].h_W_m2K'", "must be positive", "got 0.0"],
    ),
    "h_negative": (
        edit("h_W_m2K = 3.0", "h_W_m2K = -3.0"),
        ["field 'zones[2].h_W_m2K'", "must be positive", "got -3.0"],
    ),
    "bad_face": (
        edit('faces = ["-z", "-y"]', 'faces = ["-z", "front"]'),
        ["field 'zones[1].surfaces[1].faces'", "got 'front'"],
    ),
    "two_rest_zones": (
        append('[[zones]]\nname = "second_rest"\nh_W_m2K = 5.0\nrest = true'),
        ["field 'zones'", "only one zone with rest = true"],
    ),
    "surfaces_on_rest_zone": (
        edit("h_W_m2K = 6.0\nair = \"ambient\"\nrest = true",
             "h_W_m2K = 6.0\nair = \"ambient\"\nrest = true\nsurfaces = [{ body = \"bed\" }]"),
        ["field 'zones[3].surfaces'", "cannot be combined with rest = true"],
    ),
    # points outside bodies
    "sensor_outside_every_body": (
        append('[[sensors]]\nname = "T9"\nposition_mm = [0.0, 0.0, 3000.0]'),
        ["field 'sensors[8].position_mm'", "[0.0, 0.0, 3000.0] mm", "outside every body"],
    ),
    "sensor_outside_its_body": (
        edit('body = "table"\nposition_mm = [600.0, -150.0, 280.0]', 'body = "saddle"\nposition_mm = [600.0, -150.0, 280.0]'),
        ["field 'sensors[6].position_mm'", "[600.0, -150.0, 280.0] mm", "outside its body 'saddle'"],
    ),
    "tcp_outside_its_body": (
        edit('body = "spindle"\nposition_mm = [0.0, 0.0, 700.0]', 'body = "spindle"\nposition_mm = [0.0, 0.0, 690.0]'),
        ["field 'tcp.position_mm'", "[0.0, 0.0, 690.0] mm", "outside its body 'spindle'"],
    ),
    "fixed_source_outside_its_body": (
        edit("position_mm = [-470.0, -150.0, 100.0]", "position_mm = [-470.0, -150.0, 300.0]"),
        ["field 'heat_sources[0].position_mm'", "[-470.0, -150.0, 300.0] mm", "outside its body 'saddle'"],
    ),
    "moving_source_rail_leaves_carrier": (
        edit("position_mm = [0.0, -150.0, 175.0]", "position_mm = [200.0, -150.0, 175.0]"),
        [
            "field 'heat_sources[3].position_mm'",
            "[200.0, -150.0, 175.0] mm",
            "leaves its carrier body 'saddle'",
            "at X = 400.0 mm",
            "[600.0, -150.0, 175.0]",
        ],
    ),
    "moving_source_on_wrong_body": (
        edit('name = "x_nut"\nkind = "moving"', 'name = "x_nut"\nbody = "table"\nkind = "moving"'),
        ["field 'heat_sources[3].body'", "('saddle')", "got 'table'"],
    ),
    # overlaps and loose bodies
    "overlap_at_every_pose": (
        edit("[[-600.0, -400.0, 200.0], [600.0, 100.0, 350.0]]", "[[-600.0, -400.0, 150.0], [600.0, 100.0, 350.0]]"),
        ["field 'bodies'", "overlapping bodies 'saddle' and 'table'", "overlap [", ", 50.0] mm"],
    ),
    "overlap_only_at_reference_pose": (
        append(BLOCK_IN_SADDLE_PATH),
        ["field 'bodies'", "overlapping bodies 'saddle' and 'block'", "'Y': 0.0", "overlap [200.0, 40.0, 100.0] mm"],
    ),
    "overlap_only_at_travel_end": (
        # Z min -400: the spindle nose (z = 700 - 400 = 300) runs into the table top (z = 350)
        edit("travel_mm = [-275.0, 275.0]", "travel_mm = [-400.0, 275.0]"),
        ["field 'bodies'", "overlapping bodies 'table' and 'spindle'", "'Z': -400.0", "overlap [180.0, 180.0, 50.0] mm"],
    ),
    "loose_body": (
        append(GUARD_FLOATING),
        ["field 'bodies'", "leaves ['guard'] without face contact to 'bed'"],
    ),
    "edge_contact_only": (
        append(GUARD_EDGE),
        ["field 'bodies'", "leaves ['guard'] without face contact to 'bed'"],
    ),
    "body_slides_off_at_travel_end": (
        # X travel +-1100: the table (x = -600..600) leaves the saddle (x = -500..500)
        edit("travel_mm = [-400.0, 400.0]", "travel_mm = [-1100.0, 1100.0]"),
        ["field 'bodies'", "leaves ['table'] without face contact", "'X': -1100.0"],
    ),
    # supports
    "supports_5_mechanism": (
        edit('directions = ["y", "z"]', 'directions = ["z"]'),
        ["field 'supports'", "5 constraints of rank 5", "mechanism"],
    ),
    "supports_7_overconstrained": (
        edit('directions = ["y", "z"]', 'directions = ["x", "y", "z"]'),
        ["field 'supports'", "7 constraints of rank 6", "over-constrained"],
    ),
    "supports_6_collinear_rank_5": (
        # C on the line through A and B (y = -900, z = -800): the bed can rotate about it
        edit("position_mm = [0.0, 1000.0, -800.0]", "position_mm = [0.0, -900.0, -800.0]"),
        ["field 'supports'", "6 constraints of rank 5", "mechanism"],
    ),
    "support_outside_every_body": (
        edit("position_mm = [0.0, 1000.0, -800.0]", "position_mm = [0.0, 1000.0, -900.0]"),
        ["field 'supports[2].position_mm'", "[0.0, 1000.0, -900.0] mm", "outside every body"],
    ),
    "support_on_moving_body": (
        edit("position_mm = [0.0, 1000.0, -800.0]", 'body = "column"\nposition_mm = [0.0, 1000.0, 0.0]'),
        ["field 'supports[2].body'", "'column'", "mounted on another body"],
    ),
    # axes
    "travel_without_zero": (
        edit("travel_mm = [-325.0, 325.0]", "travel_mm = [10.0, 325.0]"),
        ["field 'axes[1].travel_mm'", "[10.0, 325.0]", "must contain 0"],
    ),
    "axis_moves_ground_body": (
        edit('moves = "saddle"', 'moves = "bed"'),
        ["field 'axes[1].moves'", "'bed'", "cannot move"],
    ),
    "both_segment_keys": (
        edit("segments = 4\n\n[[axes]]\nname = \"Y\"",
             "segments = 4\nsegment_bounds_mm = [-400.0, 400.0]\n\n[[axes]]\nname = \"Y\""),
        ["field 'axes[0].segments'", "exactly one"],
    ),
    "segment_bounds_not_spanning_travel": (
        edit("segments = 4\n\n[[axes]]\nname = \"Y\"", "segment_bounds_mm = [-400.0, 0.0, 300.0]\n\n[[axes]]\nname = \"Y\""),
        ["field 'axes[0].segment_bounds_mm'", "[-400.0, 0.0, 300.0]"],
    ),
    # materials and heat sources
    "poisson_ratio_too_large": (
        edit("poisson_ratio = 0.29", "poisson_ratio = 0.5"),
        ["field 'materials.steel.poisson_ratio'", "0.5"],
    ),
    "power_table_not_ending_at_1": (
        edit("exponent = 1.2", "power_table = [[0.0, 0.1], [0.8, 1.0]]"),
        ["field 'heat_sources[17].power_table'", "[[0.0, 0.1], [0.8, 1.0]]"],
    ),
    "spindle_driver_without_spindle": (
        edit("max_speed_rpm = 12000", "max_speed_rpm = 0"),
        ["field 'heat_sources[15].driver'", "'spindle'", "max_speed_rpm"],
    ),
    "unknown_driver": (
        edit('driver = "X"\nexponent = 1.0\n\n[[heat_sources]]\nname = "x_bearing_fixed"',
             'driver = "W"\nexponent = 1.0\n\n[[heat_sources]]\nname = "x_bearing_fixed"'),
        ["field 'heat_sources[0].driver'", "got 'W'"],
    ),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_machine_file(tmp_path, case):
    text, expected = BAD_CASES[case]
    assert text != VMC800
    msg = load_error(tmp_path, text)
    assert_names(msg, *expected)


def test_unedited_vmc800_file_loads_from_its_path():
    """The unedited text loads, so each bad case fails because of its one edit."""
    load_machine(VMC800_PATH)


def _toml_line_of(text: str, needle: str) -> int:
    return text[: text.index(needle)].count("\n") + 1


@pytest.mark.parametrize(
    "bad, needle, what",
    [
        (append('[[bodies]\nname = "x"'), "[[bodies]\nname = \"x\"", "Expected ']]'"),
        (edit('name = "T8"', 'name = "T8'), 'name = "T8', "Illegal character"),
        (edit('name = "T8"', 'name = "T8"\nname = "T9"'), 'name = "T9"', "Cannot overwrite a value"),
    ],
    ids=["unclosed_table_header", "unterminated_string", "duplicate_key"],
)
def test_invalid_toml(tmp_path, bad, needle, what):
    msg = load_error(tmp_path, bad)
    assert_names(msg, "not valid TOML", what, f"(at line {_toml_line_of(bad, needle)},")


def test_missing_file_and_unknown_name(tmp_path):
    with pytest.raises(MachineFileError, match=re.escape(str(tmp_path / "none.toml")) + ".*not found"):
        load_machine(tmp_path / "none.toml")
    with pytest.raises(MachineFileError, match=r"'vmc9000' is neither a file nor a bundled machine.*vmc800"):
        load_machine("vmc9000")


def test_check_pose_rejects_out_of_travel(vmc):
    assert vmc.check_pose({"X": 400.0}) == {"X": 400.0, "Y": 0.0, "Z": 0.0}
    with pytest.raises(MachineFileError, match=r"pose X = 401.0 mm is outside the travel \[-400.0, 400.0\] mm"):
        vmc.check_pose({"X": 401.0})
    with pytest.raises(MachineFileError, match=r"pose names axis 'W'"):
        vmc.check_pose({"W": 0.0})


# --------------------------------------------------------------------------- regressions of loader bugs found in review


def test_empty_bodies_is_a_machine_file_error():
    data = tomllib.loads(readme_example())
    data["bodies"], data["axes"], data["heat_sources"], data["sensors"] = [], [], [], []
    for p in (data["tcp"], data["table_reference"], *data["supports"]):
        p.pop("body", None)
    with pytest.raises(MachineFileError, match="bodies"):
        parse_machine(data, source="example.toml")


def test_missing_required_key_does_not_call_a_valid_key_unknown(tmp_path):
    text = edit('name = "spindle_motor"\n', 'name = "spindle_motor"\npower_table = [[0, 0.1], [1, 1.0]]\n')
    text = re.sub(r'(name = "spindle_motor"\n(?:.*\n)*?)power_W = [0-9.]+\n', r"\1", text, count=1)
    msg = load_error(tmp_path, text)
    assert_names(msg, "field 'heat_sources[17].power_W' is required")
    assert "power_table' is not a known field" not in msg, msg


def test_boolean_segments_rejected(tmp_path):
    msg = load_error(tmp_path, edit("segments = 4\n\n[[axes]]\nname = \"Y\"", "segments = true\n\n[[axes]]\nname = \"Y\""))
    assert_names(msg, "field 'axes[0].segments'", "wrong type: True")


def test_power_table_replaces_power_law(tmp_path):
    path = tmp_path / "table.toml"
    path.write_text(edit("exponent = 1.2", "power_table = [[0, 0.1], [0.5, 0.4], [1, 1.0]]"), encoding="utf-8")
    m = load_machine(path)
    src = {s.name: s for s in m.heat_sources}["spindle_motor"]
    assert src.power_table == ((0.0, 0.1), (0.5, 0.4), (1.0, 1.0))
    assert float(m.source_power_W(src, 0.0)) == pytest.approx(0.1 * src.power_W)
    assert float(m.source_power_W(src, 0.75)) == pytest.approx(0.7 * src.power_W)
    assert math.isclose(float(m.source_power_W(src, 1.0)), src.power_W)


# --------------------------------------------------------------------------- the TOML writer and the strict reader


def test_toml_writer_round_trips_the_bundled_machine_and_refuses_non_finite_numbers():
    from hybridcomp.models.toml import dumps_toml

    data = tomllib.loads(VMC800)
    assert tomllib.loads(dumps_toml(data)) == data
    with pytest.raises(ValueError, match="non-finite number nan"):
        dumps_toml({"machine": {"reference_temperature_degC": math.nan}})


def test_one_strict_reader_for_machine_files_and_monitor_configurations(tmp_path):
    from hybridcomp.models.toml import StrictTable
    from hybridcomp.monitor.config import ConfigError, parse_config

    t = StrictTable("f.toml", "zone", {"h_W_m2K": 0, "air": "ambient"}, ("h_W_m2K", "air"), ArithmeticError)
    with pytest.raises(ArithmeticError, match="f.toml: field 'zone.h_W_m2K' must be positive, got 0.0"):
        t.number("h_W_m2K", positive=True)
    machine_msg = load_error(tmp_path, edit("[machine]\n", "[machine]\nnmae = 'x'\n"))
    with pytest.raises(ConfigError) as info:
        parse_config({"monitor": {"machine": "vmc800", "database": "d", "rom": "r", "databse": 1}}, "m.toml")
    assert machine_msg.endswith("field 'machine.nmae' is not a known field (did you mean 'name'?)"), machine_msg
    assert str(info.value) == "m.toml: field 'monitor.databse' is not a known field (did you mean 'database'?)"
