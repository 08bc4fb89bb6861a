"""Bad input never crashes, hangs or writes nonsense: each failure a user measured, replayed.

Machine files (non-finite or huge geometry, a mesh finer than the element limit, a deeply nested
TOML array, a long chain of axes, an unreadable mesh), loads and trace CSVs (implausible powers and
temperatures, binary garbage, a byte-order mark, a control character in the name), CD files
(duplicate term inputs, extreme or NaN values, a newline in a name) and non-regular files (a named
pipe, a directory, a device) are refused with one line that names the file, the field and the
value, without a traceback and without attempting the work; the CNC export writes no value that
is not finite or beyond its clamp; and the command line turns any error into one line.
"""

from __future__ import annotations

import math
import os
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.chardiag.cd import CDError, CDInput, CharDiagram, Term
from hybridcomp.chardiag.guard import OffsetGuardError, guard_offsets
from hybridcomp.chardiag.xmlio import CDXmlError, cd_to_bytes, read_cd, write_cd
from hybridcomp.cli import main
from hybridcomp.errors import HybridcompError
from hybridcomp.fem.loads import LoadsFileError, read_loads
from hybridcomp.histogram.trace import TraceFileError, read_trace_chunks
from hybridcomp.models import MachineFileError, load_machine
from hybridcomp.models.geometry import MAX_ELEMENTS_ENV
from hybridcomp.models.layout import Loads, LoadsColumnError, check_loads
from hybridcomp.models.loader import MAX_AXES, resolve_machine_path
from hybridcomp.models.toml import MAX_TOML_DEPTH

VMC800 = resolve_machine_path("vmc800").read_text(encoding="utf-8")
FIRST_BOX = "box_mm = [[-900.0, -1000.0, -800.0], [900.0, 1100.0, 0.0]]"
POINT = "T1=21,T2=20.5,T3=20.2,T4=20,T5=20.3,T6=20.2,T7=20.1,T8=20"


def refused(capsys, argv, *names) -> str:
    """Run the command line: exit code 2, exactly one stderr line naming each of ``names``, no traceback."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for n in names:
        assert str(n) in lines[0], (n, err)
    return lines[0]


def bounded(fn, seconds: float = 5.0):
    """Run ``fn()`` in a thread and fail (instead of hanging the test run) unless it returns within ``seconds``."""
    box: dict = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc

    th = threading.Thread(target=target, daemon=True)
    th.start()
    th.join(seconds)
    assert not th.is_alive(), f"still running after {seconds} s: the input was not refused before the work"
    if "error" in box:
        raise box["error"]
    return box.get("value")


def fifo(path: Path) -> Path:
    if not hasattr(os, "mkfifo"):
        pytest.skip("no named pipes on this system")
    os.mkfifo(path)
    return path


def edit(old: str, new: str, text: str = VMC800) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- machine files


@pytest.mark.parametrize("corner", ["-inf", "1e300", "nan"])
def test_non_finite_or_huge_geometry_is_refused_by_the_loader(tmp_path, capsys, corner):
    path = write(tmp_path / "m.toml", edit(FIRST_BOX, f"box_mm = [[{corner}, -1000.0, -800.0], [900.0, 1100.0, 0.0]]"))
    line = refused(capsys, ["machine", path], path, "'bodies[0].box_mm.lo'", "within ±100000 mm")
    assert corner.replace("1e300", "1e+300") in line


def test_huge_travel_is_refused(tmp_path):
    path = write(tmp_path / "m.toml", edit("travel_mm = [-400.0, 400.0]", "travel_mm = [-inf, inf]"))
    with pytest.raises(MachineFileError, match=r"'axes\[0\]\.travel_mm' must be finite"):
        load_machine(path)


def test_a_fine_element_size_is_refused_before_any_meshing(tmp_path, capsys):
    path = write(tmp_path / "m.toml", edit("element_size_mm = 80.0", "element_size_mm = 0.01"))
    t0 = time.perf_counter()
    line = refused(capsys, ["machine", path], path, "'mesh.element_size_mm' = 0.01 mm", "elements", "EiB",
                   "the limit is 2,000,000 elements", MAX_ELEMENTS_ENV)
    assert re.search(r"~1e\+16 elements", line)
    # the bundled file at a fine size on the command line: refused by mesh_machine, before it allocates anything
    line = refused(capsys, ["machine", "vmc800", "--mesh", "--element-size-mm", "0.01"], "element size 0.01 mm",
                   "the limit is 2,000,000 elements")
    assert time.perf_counter() - t0 < 5.0


def test_simulate_refuses_a_fine_mesh_before_meshing(tmp_path, capsys, write_csv):
    loads = write_csv(tmp_path / "l.csv", ["time_s", "x_motor_W"], [[0, 1], [60, 1]])
    refused(capsys, ["simulate", "--loads", loads, "--out", tmp_path / "out", "--element-size-mm", "0.01",
                     "--no-progress"], "element size 0.01 mm", "limit")
    assert not (tmp_path / "out" / "outputs.csv").exists()


def test_the_element_limit_is_set_in_the_file_or_the_environment(tmp_path, capsys, monkeypatch):
    path = write(tmp_path / "m.toml", edit("element_size_mm = 80.0", "element_size_mm = 80.0\nmax_elements = 1000"))
    refused(capsys, ["machine", path], "'mesh.element_size_mm' = 80 mm", "~3e+04 elements", "the limit is 1,000")
    monkeypatch.setenv(MAX_ELEMENTS_ENV, "1000")
    refused(capsys, ["machine", "vmc800", "--mesh"], "the limit is 1,000 elements")
    monkeypatch.setenv(MAX_ELEMENTS_ENV, "many")
    refused(capsys, ["machine", "vmc800"], MAX_ELEMENTS_ENV, "'many'", "positive whole number")
    monkeypatch.setenv(MAX_ELEMENTS_ENV, "40000")  # vmc800 at 80 mm: a grid of 30,132 cells
    assert main(["machine", "vmc800"]) == 0


def test_a_deeply_nested_toml_array_is_one_error_naming_the_file(tmp_path, capsys):
    path = write(tmp_path / "deep.toml", "a = " + "[" * 5000 + "]" * 5000 + "\n")
    refused(capsys, ["machine", path], path, f"nested more than {MAX_TOML_DEPTH} levels deep")
    # nested deep enough for the limit but not for Python's recursion: the same message
    path = write(tmp_path / "deep40.toml", edit("[machine]", "x = " + "[" * 40 + "]" * 40 + "\n[machine]"))
    refused(capsys, ["machine", path], path, f"nested more than {MAX_TOML_DEPTH} levels deep")


def chain_machine(n_axes: int) -> str:
    """Bodies stacked in z, each moved by its own x axis against the one below: a chain of ``n_axes`` axes."""
    parts = ['[machine]\nname = "chain"\n\n[materials.steel]\nconductivity_W_mK = 46.0\ndensity_kg_m3 = 7800.0\n'
             'specific_heat_J_kgK = 460.0\nyoungs_modulus_GPa = 210.0\npoisson_ratio = 0.3\nexpansion_1_K = 11.5e-6\n']
    for k in range(n_axes + 1):
        parts.append(f'[[bodies]]\nname = "b{k}"\nmaterial = "steel"\n'
                     f'box_mm = [[-500.0, -500.0, {100.0 * k}], [500.0, 500.0, {100.0 * (k + 1)}]]\n'
                     + (f'mounted_on = "b{k - 1}"\n' if k else ""))
    for k in range(1, n_axes + 1):
        parts.append(f'[[axes]]\nname = "A{k}"\ndirection = "x"\nmoves = "b{k}"\ntravel_mm = [-10.0, 10.0]\n'
                     'max_feed_mm_min = 1000.0\nsegments = 1\n')
    parts.append(f'[[zones]]\nname = "air"\nh_W_m2K = 6.0\nrest = true\n\n[tcp]\nposition_mm = [0.0, 0.0, '
                 f'{100.0 * (n_axes + 1)}]\n\n[table_reference]\nposition_mm = [0.0, 0.0, 0.0]\n\n'
                 '[[supports]]\nname = "A"\nposition_mm = [-400.0, -400.0, 0.0]\ndirections = ["x", "y", "z"]\n\n'
                 '[[supports]]\nname = "B"\nposition_mm = [400.0, -400.0, 0.0]\ndirections = ["y", "z"]\n\n'
                 '[[supports]]\nname = "C"\nposition_mm = [0.0, 400.0, 0.0]\ndirections = ["z"]\n')
    return "\n".join(parts)


def test_a_long_chain_of_axes_is_refused_at_once_and_the_longest_allowed_loads_quickly(tmp_path, capsys):
    path = write(tmp_path / "chain10.toml", chain_machine(10))
    t0 = time.perf_counter()
    refused(capsys, ["machine", path], path, "'axes' has 10 axes", f"limit of {MAX_AXES}", "3^10 = 59,049")
    assert time.perf_counter() - t0 < 1.0
    t0 = time.perf_counter()
    m = load_machine(write(tmp_path / "chain8.toml", chain_machine(MAX_AXES)))  # 3^8 = 6,561 poses checked
    assert len(m.axes) == MAX_AXES
    assert time.perf_counter() - t0 < 5.0


def test_the_exhaustive_pose_check_still_finds_an_overlap_at_a_travel_end(tmp_path):
    # a ground wall touching the chain at x = 500 mm: at the reference pose every body only touches it; b3 (moved
    # by A1 + A2 + A3) first crosses x = 500 mm at A1 = -10, A2 = 10, A3 = 10 in the documented order of poses
    # (each axis at min, 0, max; the last axis fastest), by 10 mm
    text = chain_machine(3).replace('[[axes]]\nname = "A1"', '[[bodies]]\nname = "wall"\nmaterial = "steel"\n'
                                    'box_mm = [[500.0, -500.0, 0.0], [600.0, 500.0, 400.0]]\n\n[[axes]]\nname = "A1"')
    with pytest.raises(MachineFileError, match=re.escape("overlapping bodies 'b3' and 'wall' at pose "
                                                         "{'A1': -10.0, 'A2': 10.0, 'A3': 10.0} (overlap [10.0, 1000.0, "
                                                         "100.0] mm)")):
        load_machine(write(tmp_path / "wall.toml", text))


def test_machine_file_that_is_a_fifo_or_a_directory_is_refused_without_blocking(tmp_path, capsys):
    pipe = fifo(tmp_path / "m.toml")
    bounded(lambda: refused(capsys, ["machine", pipe], pipe, "not a regular file"))
    d = tmp_path / "d.toml"
    d.mkdir()
    refused(capsys, ["machine", d], d, "not a regular file")


IMPORTED = """
[machine]
name = "imported"

[mesh]
file = "m.msh"

[materials.steel]
conductivity_W_mK = 46.0
density_kg_m3 = 7800.0
specific_heat_J_kgK = 460.0
youngs_modulus_GPa = 210.0
poisson_ratio = 0.3
expansion_1_K = 11.5e-6

[[bodies]]
name = "bed"
material = "steel"

[[zones]]
name = "air"
h_W_m2K = 6.0
rest = true

[tcp]
body = "bed"
position_mm = [0.0, 0.0, 0.0]

[table_reference]
body = "bed"
position_mm = [0.0, 0.0, 0.0]

[[supports]]
name = "A"
body = "bed"
position_mm = [0.0, 0.0, 0.0]
directions = ["x", "y", "z"]

[[supports]]
name = "B"
body = "bed"
position_mm = [100.0, 0.0, 0.0]
directions = ["y", "z"]

[[supports]]
name = "C"
body = "bed"
position_mm = [0.0, 100.0, 0.0]
directions = ["z"]
"""


@pytest.mark.parametrize("name,data,said", [
    ("m.vtk", b"# vtk DataFile Version 4.2\ngarbage\n", "Couldn't read file"),  # meshio's reader exits the process
    ("m.vtu", b"<?xml version='1.0'?><VTKFile type='UnstructuredGrid'><broken", "Couldn't read file"),
    ("m.xyz", b"1 2 3\n", "Could not deduce file format"),
    ("m.ply", b"ply\nformat ascii 1.0\nelement vertex 2\n", "surface mesh format"),  # meshio loops on it
], ids=["vtk exits", "vtu", "unknown suffix", "ply loops"])
def test_a_mesh_file_meshio_cannot_read_names_the_field(tmp_path, capsys, name, data, said):
    path = write(tmp_path / "imported.toml", IMPORTED.replace('"m.msh"', f'"{name}"'))
    (tmp_path / name).write_bytes(data)
    bounded(lambda: refused(capsys, ["machine", path, "--mesh"], path, "'mesh.file'", name, said))


def test_machine_mesh_with_an_unreadable_mesh_file_is_one_line(tmp_path, capsys):
    path = write(tmp_path / "imported.toml", IMPORTED)
    (tmp_path / "m.msh").write_bytes(b"\x00\xffnot a mesh\n")
    assert main(["machine", str(path)]) == 0  # loading does not read the mesh
    capsys.readouterr()
    refused(capsys, ["machine", path, "--mesh"], path, "'mesh.file'", "could not be read")
    (tmp_path / "m.msh").unlink()
    fifo(tmp_path / "m.msh")
    bounded(lambda: refused(capsys, ["machine", path, "--mesh"], path, "'mesh.file'", "not a regular file"))


# --------------------------------------------------------------------------- loads CSV and simulate


@pytest.mark.parametrize(
    "column, value, says",
    [
        ("x_motor_W", "1e308", "heat power 1e+308 W is beyond the plausible maximum of 1e+06 W"),
        ("x_motor_W", "inf", "value inf is not finite"),
        ("x_motor_W", "-0.5", "a heat power cannot be negative, got -0.5 W"),
        ("ambient_degC", "-300", "temperature -300 °C is below absolute zero"),
        ("ambient_degC", "250", "temperature 250 °C is outside the plausible range [-50, 200] °C"),
        ("ambient_degC", "nan", "value nan is not finite"),
    ],
)
def test_simulate_refuses_implausible_loads_naming_file_line_and_column(tmp_path, capsys, write_csv, column, value,
                                                                        says):
    loads = write_csv(tmp_path / "l.csv", ["time_s", column], [[0, 1.0 if column.endswith("_W") else 20.0],
                                                               [60, value]])
    out = tmp_path / "out"
    refused(capsys, ["simulate", "--loads", loads, "--out", out, "--no-progress"], loads, "line 3",
            f"column {column!r}", says)
    assert not (out / "outputs.csv").exists()


@pytest.mark.parametrize(
    "times, says",
    [
        (["0", "inf"], "line 3: time_s inf is not finite"),
        (["0", "1e11"], "line 3: time_s 1e+11 is not finite or beyond ±1e+10 s"),
        (["60", "0"], "line 3: time_s 0.0 does not increase after 60.0"),
        (["0", "2e8"], "line 3: time_s 2e+08 is 2e+08 s after the first time 0 s"),
    ],
)
def test_loads_times_must_be_finite_increasing_and_bounded(machine, tmp_path, write_csv, times, says):
    path = write_csv(tmp_path / "l.csv", ["time_s", "x_motor_W"], [[t, 1.0] for t in times])
    with pytest.raises(LoadsFileError, match=re.escape(says)):
        read_loads(path, machine)


def test_power_round_off_below_zero_reads_as_zero(machine, tmp_path, write_csv):
    path = write_csv(tmp_path / "l.csv", ["time_s", "x_motor_W"], [[0, "-1e-12"], [60, 2.0]])
    loads = read_loads(path, machine)
    j = loads.names.index("x_motor_W")
    assert loads.values[0, j] == 0.0 and loads.values[1, j] == 2.0


def test_check_loads_applies_the_same_bounds_to_loads_made_in_memory():
    ok = Loads(np.array([0.0, 60.0]), np.array([[1.0, 20.0], [-1e-9, 21.0]]), ("q_W", "air_degC"))
    assert check_loads(ok).values[1, 0] == 0.0
    bad = Loads(np.array([0.0, 60.0]), np.array([[1.0, 20.0], [1.0, -300.0]]), ("q_W", "air_degC"))
    with pytest.raises(LoadsColumnError, match=r"day: row 2, column 'air_degC': temperature -300 °C is below"):
        check_loads(bad, "day")


def test_loads_csv_with_binary_garbage_names_the_file(machine, tmp_path):
    path = tmp_path / "garbage.csv"
    path.write_bytes(b"time_s,x_motor_W\n0,1\n\xff\xfe\x80\x81binary\n")
    with pytest.raises(LoadsFileError, match=r"garbage\.csv: not a UTF-8 text CSV: undecodable byte"):
        read_loads(path, machine)
    path.write_bytes(b"time_s,x_motor_W\n0,1\n60,\x001\n")
    with pytest.raises(LoadsFileError, match=r"garbage\.csv: line 3, column 'x_motor_W': value '\\x001' is not a num"):
        read_loads(path, machine)


def test_loads_csv_with_a_byte_order_mark_reads(machine, tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes("time_s,x_motor_W\r\n0,1\r\n60,2\r\n".encode("utf-8-sig"))
    loads = read_loads(path, machine)
    assert loads.time_s.tolist() == [0.0, 60.0]


def test_a_control_character_in_a_loads_file_name_is_refused(machine, tmp_path, write_csv, capsys):
    path = write_csv(tmp_path / "day\n1 fake line.csv", ["time_s", "x_motor_W"], [[0, 1], [60, 1]])
    with pytest.raises(LoadsFileError, match=r"control character '\\n'"):
        read_loads(path, machine)
    refused(capsys, ["simulate", "--loads", path, "--out", tmp_path / "out", "--no-progress"], "control character")


def test_loads_file_that_is_a_fifo_directory_or_device_is_refused_without_blocking(machine, tmp_path, capsys):
    pipe = fifo(tmp_path / "pipe.csv")
    with pytest.raises(LoadsFileError, match="a named pipe"):
        bounded(lambda: read_loads(pipe, machine))
    with pytest.raises(LoadsFileError, match="a directory"):
        read_loads(tmp_path, machine)
    with pytest.raises(LoadsFileError, match="a character device"):
        bounded(lambda: read_loads(os.devnull, machine))
    bounded(lambda: refused(capsys, ["simulate", "--loads", pipe, "--out", tmp_path / "out", "--no-progress"], pipe,
                            "not a regular file"))


# --------------------------------------------------------------------------- trace CSV


TRACE_HEADER = "time_s,x_mm,y_mm,z_mm,spindle_rpm,Tamb_degC\n"


def read_trace(path, machine):
    return [len(s) for s in read_trace_chunks(path, machine)]


@pytest.mark.parametrize(
    "row, says",
    [
        ("1,0,0,0,0,-300", "line 3, column 'Tamb_degC': temperature -300 °C is below absolute zero"),
        ("1,0,0,0,0,500", "line 3, column 'Tamb_degC': temperature 500 °C is outside the plausible range"),
        ("1,inf,0,0,0,20", "line 3, column 'x_mm': value inf is not finite"),
        ("inf,0,0,0,0,20", "line 3, column 'time_s': value inf is not finite"),
    ],
)
def test_trace_refuses_infinite_values_and_implausible_air(machine, tmp_path, row, says):
    path = write(tmp_path / "t.csv", TRACE_HEADER + "0,0,0,0,0,20\n" + row + "\n")
    with pytest.raises(TraceFileError, match=re.escape(says)):
        read_trace(path, machine)


def test_trace_with_binary_garbage_bom_and_control_characters(machine, tmp_path):
    path = tmp_path / "t.csv"
    path.write_bytes(TRACE_HEADER.encode() + b"0,0,0,0,0,20\n\xff\xfe\x80garbage\n")
    with pytest.raises(TraceFileError, match=r"t\.csv: not a UTF-8 text CSV: undecodable byte"):
        read_trace(path, machine)
    path.write_bytes(TRACE_HEADER.encode() + b"0,0,0,0,0,20\n1,0,\x000,0,0,20\n")
    with pytest.raises(TraceFileError, match=r"t\.csv: line 3, column 'y_mm': value '\\x000' is not a number"):
        read_trace(path, machine)
    path.write_bytes((TRACE_HEADER + "0,0,0,0,0,20\n1,0,0,0,0,20\n").encode("utf-8-sig"))
    assert read_trace(path, machine) == [2]
    named = write(tmp_path / "a\rb.csv", TRACE_HEADER + "0,0,0,0,0,20\n")
    with pytest.raises(TraceFileError, match=r"control character '\\r'"):
        read_trace(named, machine)
    with pytest.raises(TraceFileError, match="a named pipe"):
        bounded(lambda: read_trace(fifo(tmp_path / "pipe.csv"), machine))


# --------------------------------------------------------------------------- CD files and the CNC export


def small_cd(direction: str, values=(0.0, 10.0), load_case: str = "lc", **kw) -> CharDiagram:
    """A CD of vmc800 over T1 and T3 (one full term, 2 × 2 grid), linear in T1."""
    inputs = (CDInput("T1", "degC", True, 15.0, 30.0, 2), CDInput("T3", "degC", True, 15.0, 30.0, 2))
    v = np.array([[values[0], values[0]], [values[1], values[1]]], float)
    args = dict(machine="vmc800", machine_sha256="", pose_mm=(("X", 0.0), ("Y", 0.0), ("Z", 0.0)),
                direction=direction, inputs=inputs, terms=(Term((0, 1), v),), smoothing=1.0, ridge=1e-10,
                load_case=load_case, signature=np.zeros(0), t_reference_degC=(("T1", 20.0), ("T3", 20.0)))
    args.update(kw)
    return CharDiagram(**args)


def cd_dir(tmp_path: Path, z_values=(0.0, 10.0)) -> Path:
    d = tmp_path / "cds"
    for direction in "XY":
        write_cd(d / f"cd_{direction}.xml", small_cd(direction))
    write_cd(d / "cd_Z.xml", small_cd("Z", z_values))
    return d


def tamper(path: Path, old: str, new: str) -> Path:
    text = path.read_text(encoding="utf-8")
    assert old in text, old
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return path


def test_duplicate_term_inputs_are_refused(tmp_path, capsys):
    d = cd_dir(tmp_path)
    tamper(d / "cd_Z.xml", 'inputs="T1 T3"', 'inputs="T1 T1 T3"')
    with pytest.raises(CDXmlError, match=r"cd_Z\.xml: term 0: input 'T1' appears twice in its inputs 'T1 T1 T3'"):
        read_cd(d / "cd_Z.xml")
    refused(capsys, ["cd", "eval", d, "--point", POINT], "cd_Z.xml", "'T1' appears twice")
    cd = small_cd("Z")
    with pytest.raises(CDError, match="input 'T1' appears twice"):
        CharDiagram(**{**cd.__dict__, "terms": (Term((0, 0), cd.terms[0].values),)})


@pytest.mark.parametrize(
    "old, new, says",
    [
        ("<values>0.0 0.0 10.0 10.0</values>", "<values>1e308 -1e308 1e308 1e308</values>",
         "term 0: value 1e+308 µm is not finite or beyond the plausible ±10000 µm"),
        ('min="15.0"', 'min="-1e308"', "input 'T1': range [-1e+308, 30.0] degC is outside the plausible [-50, 200]"),
        ('T_degC="20.0"', 'T_degC="NaN"', "sensor 'T1' T_degC nan is not finite"),
        ('position_mm="0.0"', 'position_mm="INF"', "pose: axis 'X' position inf mm is not finite"),
    ],
)
def test_extreme_or_nan_cd_values_are_refused_on_reading(tmp_path, capsys, old, new, says):
    d = cd_dir(tmp_path)
    tamper(d / "cd_Z.xml", old, new)
    out = tmp_path / "offsets.mpf"
    line = refused(capsys, ["cd", "eval", d, "--point", POINT, "--cnc", "840d", "--out", out], "cd_Z.xml", says)
    assert "nan" not in capsys.readouterr().out and not out.exists()
    assert "Traceback" not in line
    # the database import refuses it the same way (it used to crash writing 'nan' against the schema)
    refused(capsys, ["cd", "db", "import", "--db", tmp_path / "cds.sqlite", d / "cd_Z.xml"], "cd_Z.xml", says)


def test_a_cd_whose_reference_temperatures_name_a_sensor_the_machine_lacks_is_refused(tmp_path, capsys):
    path = write_cd(tmp_path / "cd_Z.xml", small_cd("Z", t_reference_degC=(("T1", 20.0), ("T9", 20.0))))
    with pytest.raises(CDXmlError, match=r"cd_Z\.xml: referenceTemperatures sensor 'T9': machine 'vmc800' has no "
                                         r"sensor of that name \(has: T1, "):
        read_cd(path, load_machine("vmc800"))
    db = tmp_path / "cds.sqlite"
    refused(capsys, ["cd", "db", "import", "--db", db, "--machine", "vmc800", path], "cd_Z.xml", "'T9'")
    assert not db.exists()
    read_cd(path)  # without a machine there is nothing to compare with


def test_the_cnc_export_writes_no_offset_beyond_its_clamp(tmp_path, capsys):
    d = cd_dir(tmp_path, z_values=(4000.0, 9000.0))  # a plausible file, an implausible compensation of 6 mm at T1 = 21 °C
    out = tmp_path / "offsets.mpf"
    line = refused(capsys, ["cd", "eval", d, "--point", POINT, "--cnc", "840d", "--out", out],
                   "CNC export (Siemens 840D sl): offset Z compensation = -6000 µm", "clamp of ±1000 µm",
                   "nothing written")
    assert not out.exists() and "nan" not in line
    refused(capsys, ["cd", "eval", d, "--point", POINT, "--cnc", "generic"], "CNC export (generic table)")
    assert "$SA_TEMP" not in capsys.readouterr().out
    assert main(["cd", "eval", str(cd_dir(tmp_path / "ok")), "--point", POINT, "--cnc", "840d"]) == 0
    assert "$SA_TEMP_COMP_ABS_VALUE[Z1]=-0.004000" in capsys.readouterr().out


def test_guard_offsets():
    assert guard_offsets({"dz_um": 3, "dx_um": -4.5}, clamp_um=10.0, source="sink") == {"dz_um": 3.0, "dx_um": -4.5}
    for bad, says in ((math.nan, "dz_um = nan µm is not finite"), (math.inf, "dz_um = inf µm is not finite"),
                      (-12.0, "dz_um = -12 µm is beyond the clamp of ±10 µm")):
        with pytest.raises(OffsetGuardError, match=re.escape(f"sink: offset {says}")) as info:
            guard_offsets({"dx_um": 1.0, "dz_um": bad}, clamp_um=10.0, source="sink")
        assert isinstance(info.value, HybridcompError) and isinstance(info.value, ValueError)
    with pytest.raises(ValueError, match="clamp_um must be a finite positive number"):
        guard_offsets({}, clamp_um=math.nan, source="sink")


def test_a_control_character_in_cd_metadata_is_refused(tmp_path, capsys):
    with pytest.raises(CDError, match=r"loadCase name: 'day\\n    7  vmc800  forged' has a control character"):
        small_cd("Z", load_case="day\n    7  vmc800  forged")
    with pytest.raises(CDError, match="input 'T1' reason"):
        small_cd("Z", inputs=(CDInput("T1", "degC", True, 15.0, 30.0, 2, reason="a\x1b[2Jb"),
                              CDInput("T3", "degC", True, 15.0, 30.0, 2)))
    d = cd_dir(tmp_path)
    tamper(d / "cd_Z.xml", 'loadCase name="lc"', 'loadCase name="lc&#10;    99  forged line"')
    refused(capsys, ["cd", "db", "import", "--db", tmp_path / "cds.sqlite", d / "cd_Z.xml"], "cd_Z.xml",
            "loadCase name", "control character")


def test_cd_file_that_is_a_fifo_or_directory_is_refused_without_blocking(tmp_path, capsys):
    pipe = fifo(tmp_path / "cd_Z.xml")
    with pytest.raises(CDXmlError, match="a named pipe"):
        bounded(lambda: read_cd(pipe))
    bounded(lambda: refused(capsys, ["cd", "eval", pipe, "--point", POINT], pipe, "not a regular file"))
    with pytest.raises(CDXmlError, match="a directory"):
        read_cd(tmp_path)


def test_the_xml_writer_spells_non_finite_statistics_as_the_schema_does():
    cd = small_cd("Z", fit=(("r2", math.nan), ("max_abs_residual_um", math.inf)))
    xml = cd_to_bytes(cd).decode()
    assert 'value="NaN"' in xml and 'value="INF"' in xml


# --------------------------------------------------------------------------- the command line


def test_every_error_of_a_subcommand_is_one_line(monkeypatch, capsys):
    import hybridcomp.fem.cli_machine as machine_cli

    def raising(exc):
        def run(args):
            raise exc
        return run

    monkeypatch.setattr(machine_cli, "run", raising(FileNotFoundError(2, "No such file or directory", "x.csv")))
    refused(capsys, ["machine"], "error: x.csv: No such file or directory")
    monkeypatch.setattr(machine_cli, "run", raising(IsADirectoryError(21, "Is a directory", "d")))
    refused(capsys, ["machine"], "error: d: Is a directory")
    monkeypatch.setattr(machine_cli, "run", raising(ValueError("a.csv: value\nforged line")))
    refused(capsys, ["machine"], "error: a.csv: value\\nforged line")
    monkeypatch.setattr(machine_cli, "run", raising(UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte")))
    refused(capsys, ["machine"], "invalid start byte")
    monkeypatch.setattr(machine_cli, "run", raising(RuntimeError("boom")))
    assert main(["machine"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines() == ["error: internal error RuntimeError: boom (run with -vv for the traceback)"]
    assert main(["-vv", "machine"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and err.splitlines()[-1] == "error: internal error RuntimeError: boom"
