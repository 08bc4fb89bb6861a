"""``hybridcomp histogram`` and ``hybridcomp scenario`` in-process, and the job-shop day end to end through simulate."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from hybridcomp.cli import main
from hybridcomp.fem.loads import input_columns, read_loads
from hybridcomp.histogram.scenarios import jobshop_program

PNG = b"\x89PNG\r\n\x1a\n"


def read_rows(path):
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def test_histogram_cli_gcode_to_loads_signature_and_pictures(machine, tmp_path, capsys):
    nc = tmp_path / "square.nc"
    nc.write_text("G0 X-400\nS6000 M3\nG1 X400 F20000\nX-400\nX400\nX-400\nG4 P4.8\nM30\n")  # 9.6 s at half feed, 4.8 s dwell
    out = tmp_path / "loads.csv"
    rc = main(["histogram", str(nc), "--machine", "vmc800", "--increment", "5", "--out", str(out),
               "--signature", str(tmp_path / "sig.csv"), "--plot", str(tmp_path / "plots"), "--plot-increment", "1"])
    assert rc == 0, capsys.readouterr().err
    loads = read_loads(out, machine)
    assert loads.names == input_columns(machine)
    # 0.6 s rapid + 9.6 s at 20,000 mm/min + 4.8 s dwell = 15 s: increments end at 5, 10, 15 s
    np.testing.assert_allclose(loads.time_s, [0, 5, 10, 15])
    rows = read_rows(tmp_path / "sig.csv")
    assert rows[0][:3] == ["start_s", "end_s", "f_X"] and len(rows) == 4
    assert (tmp_path / "plots" / "factors.png").read_bytes()[:8] == PNG
    assert (tmp_path / "plots" / "histogram_0001.png").read_bytes()[:8] == PNG


def test_histogram_cli_trace_with_nan_rows_warns_and_goes_on(machine, tmp_path, capsys):
    trace = tmp_path / "t.csv"
    rows = [[f"{0.1 * i:.1f}", "0", "0", "0", "12000", "21"] for i in range(1201)]
    rows[7][1] = "nan"
    with trace.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", "Tamb_degC"])
        w.writerows(rows)
    rc = main(["histogram", str(trace), "--increment", "60", "--out", str(tmp_path / "l.csv")])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "warning: " in err and "dropped 1 of 1201 rows with NaN or empty fields (first at line 9)" in err
    loads = read_loads(tmp_path / "l.csv", machine)
    np.testing.assert_allclose(loads.values[1:, loads.names.index("spindle_bearing_front_W")], 110.0)
    np.testing.assert_allclose(loads.values[:, loads.names.index("ws_table_degC")], 21.0)


def test_histogram_cli_errors_name_the_line_and_write_nothing(tmp_path, capsys):
    nc = tmp_path / "bad.nc"
    nc.write_text("G0 X10\nG1 X20 F100\nG1 X30 E5\n")
    out = tmp_path / "loads.csv"
    rc = main(["histogram", str(nc), "--out", str(out)])
    assert rc == 2
    assert "bad.nc: line 3: 'E5' is an unknown word" in capsys.readouterr().err
    assert not out.exists()
    rc = main(["histogram", str(tmp_path / "x.txt"), "--out", str(out)])
    assert rc == 2 and "give --format" in capsys.readouterr().err
    rc = main(["histogram", str(nc), "--increment", "0", "--out", str(out)])
    assert rc == 2 and "--increment must be positive" in capsys.readouterr().err


def test_scenario_basic_writes_gcode_trace_and_loads(machine, tmp_path, capsys):
    rc = main(["scenario", "basic", "--machine", "vmc800", "--out", str(tmp_path), "--hours", "0.05", "--rate-hz", "5",
               "--increment", "60"])
    assert rc == 0, capsys.readouterr().err
    for case in ("X", "Y", "Z", "spindle"):
        for suffix in (".nc", "_trace.csv", "_loads.csv"):
            assert (tmp_path / f"basic_{case}{suffix}").is_file()
    loads = read_loads(tmp_path / "basic_Y_loads.csv", machine)
    col = {n: loads.values[:, j] for j, n in enumerate(loads.names)}
    # Y alone at max feed: the Y motor at its full 100 W in every increment (loads from the exact programme motion)
    np.testing.assert_allclose(col["y_motor_W"][1:], 100.0, rtol=1e-9)
    np.testing.assert_allclose(loads.time_s[-1], 185 * 650 / 40000 * 60 + 325 / 40000 * 60)  # ceil(180 s / 0.975 s) strokes
    np.testing.assert_array_equal(col["x_motor_W"], 0.0)
    sp = read_loads(tmp_path / "basic_spindle_loads.csv", machine)
    np.testing.assert_allclose(sp.values[1:, sp.names.index("spindle_motor_W")], 220.0, rtol=1e-9)


@pytest.mark.slow
def test_jobshop_piece_gcode_histogram_simulate_end_to_end(machine, tmp_path, capsys):
    """The first 2 h block of the job-shop day: G-code → histogram → loads CSV → simulate (coarse mesh)."""
    lines = jobshop_program(machine).splitlines()
    cut = next(i for i, ln in enumerate(lines) if ln.startswith("(block 2"))
    nc = tmp_path / "block1.nc"
    nc.write_text("\n".join(lines[:cut] + ["M30"]) + "\n")
    loads_csv = tmp_path / "loads.csv"
    assert main(["histogram", str(nc), "--increment", "600", "--out", str(loads_csv)]) == 0
    out = tmp_path / "run"
    rc = main(["simulate", "--loads", str(loads_csv), "--out", str(out), "--element-size-mm", "150", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    rows = read_rows(out / "outputs.csv")
    data = np.array(rows[1:], dtype=float)
    loads = read_loads(loads_csv, machine)
    np.testing.assert_allclose(data[:, 0], loads.time_s)
    assert len(loads.time_s) == 13  # 2 h in 10 min increments, plus the standstill start
    assert np.all(np.isfinite(data))
    t1 = data[:, rows[0].index("T1_degC")]
    # set-up pause (20 min, spindle off) keeps the spindle at the reference; the flange work then heats it
    assert t1[2] == pytest.approx(20.0, abs=1e-3)
    assert t1[-1] > 20.5


def test_histogram_cli_power_mode_and_signature_period(machine, tmp_path, capsys):
    nc = tmp_path / "p.nc"
    nc.write_text("S12000 M3\nG4 P30\nM5\nG4 P30\n")  # spindle at full speed for half of each minute
    for mode, expected in (("factor", 110 * 0.5**1.67), ("mean", 110 * 0.5)):
        out = tmp_path / f"{mode}.csv"
        assert main(["histogram", str(nc), "--increment", "60", "--power", mode, "--out", str(out),
                     "--signature", str(tmp_path / "sig.csv"), "--signature-period", "60", "--force"]) == 0, \
            capsys.readouterr().err  # the second mode writes sig.csv again
        loads = read_loads(out, machine)
        np.testing.assert_allclose(loads.values[1, loads.names.index("spindle_bearing_front_W")], expected, rtol=1e-5)
    rc = main(["histogram", str(nc), "--increment", "60", "--out", str(tmp_path / "x.csv"),
               "--signature", str(tmp_path / "sig.csv"), "--signature-period", "90"])
    assert rc == 2 and "must be a whole multiple of the increment" in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()  # checked before anything is written
