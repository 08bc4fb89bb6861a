"""The loads-CSV contract and ``hybridcomp simulate`` end to end (in-process, coarse mesh)."""

from __future__ import annotations

import csv
import json

import meshio
import numpy as np
import pytest

from hybridcomp.cli import main
from hybridcomp.fem.loads import LoadsFileError, example_loads, read_loads, write_loads
from hybridcomp.models import load_machine
from hybridcomp.models.loader import resolve_machine_path

COARSE = ["--element-size-mm", "150", "--no-progress"]


def test_missing_columns_mean_zero_power_and_reference_temperature(machine, tmp_path, write_csv):
    p = write_csv(tmp_path / "l.csv", ["time_s", "y_nut[2]_W", "ambient_degC"], [[0, 5, 21], [60, 6, 22]])
    loads = read_loads(p, machine)
    j = loads.names.index("y_nut[2]_W")
    np.testing.assert_array_equal(loads.values[:, j], [5, 6])
    others = [k for k, n in enumerate(loads.names) if n.endswith("_W") and k != j]
    assert not loads.values[:, others].any()
    np.testing.assert_array_equal(loads.values[:, loads.names.index("ambient_degC")], [21, 22])
    np.testing.assert_array_equal(loads.values[:, loads.names.index("floor_degC")], [20, 20])
    U = machine.layout().inputs(loads)
    np.testing.assert_array_equal(U[:, loads.names.index("ambient_degC")], [1, 2])


@pytest.mark.parametrize(
    "header,rows,match",
    [
        (["time_s", "x_nutt[1]_W"], [[0, 1]], r"l\.csv: column 'x_nutt\[1\]_W' is not an input of machine 'vmc800'"),
        (["time_s", "x_motor_W"], [[0, 1], [60, 1], [30, 1]], r"l\.csv: line 4: time_s 30\.0 does not increase after 60\.0"),
        (["time_s", "x_motor_W"], [[0, 1], [60, "nan"]], r"l\.csv: line 3, column 'x_motor_W': value nan is not finite"),
        (["time_s", "x_motor_W"], [[0, -1]], r"l\.csv: line 2, column 'x_motor_W': a heat power cannot be negative, got -1"),
        (["time_s", "x_motor_W"], [[0, "abc"]], r"l\.csv: line 2, column 'x_motor_W': value 'abc' is not a number"),
        (["x_motor_W"], [[1]], r"l\.csv: column 'time_s' is missing"),
        (["time_s", "x_motor_W", "x_motor_W"], [[0, 1, 1]], r"l\.csv: column 'x_motor_W' appears twice"),
    ],
)
def test_bad_loads_are_named(machine, tmp_path, header, rows, match, write_csv):
    p = write_csv(tmp_path / "l.csv", header, rows)
    with pytest.raises(LoadsFileError, match=match):
        read_loads(p, machine)


@pytest.mark.slow
def test_simulate_cli_writes_the_output_contract(machine, tmp_path):
    loads = example_loads(machine, duration_h=2.0, dt_s=300.0)
    write_loads(tmp_path / "loads.csv", loads)
    out = tmp_path / "run"
    rc = main(["simulate", "--machine", "vmc800", "--loads", str(tmp_path / "loads.csv"), "--out", str(out),
               "--fields", "2", *COARSE])
    assert rc == 0
    with (out / "outputs.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["time_s", *(f"T{i}_degC" for i in range(1, 9)), "dx_um", "dy_um", "dz_um"]
    assert len(rows) - 1 == len(loads.time_s)
    data = np.array(rows[1:], dtype=float)
    np.testing.assert_allclose(data[:, 0], loads.time_s)
    assert np.all(np.isfinite(data))
    assert data[-1, 1] > data[0, 1]  # the spindle sensor warms up during the first two hours
    # the VTU fields read back with the temperatures of the outputs at the sensor points' neighbourhood
    vtus = sorted((out / "fields").glob("*.vtu"))
    assert len(vtus) == 2
    m = meshio.read(vtus[-1])
    T = m.point_data["temperature_degC"]
    assert T.min() <= data[-1, 1:9].min() + 1e-6 and T.max() >= data[-1, 1:9].max() - 1e-6
    assert m.point_data["displacement_um"].shape == (len(T), 3)
    assert np.ptp(m.points, axis=0).max() > 1000  # written in mm


@pytest.mark.slow
def test_simulate_cli_resamples_with_dt(machine, tmp_path, write_csv):
    write_csv(tmp_path / "l.csv", ["time_s", "spindle_motor_W"], [[0, 0], [3600, 100]])
    out = tmp_path / "o"
    assert main(["simulate", "--loads", str(tmp_path / "l.csv"), "--out", str(out), "--dt", "600", *COARSE]) == 0
    t = np.loadtxt(out / "outputs.csv", delimiter=",", skiprows=1)[:, 0]
    np.testing.assert_allclose(t, np.arange(0, 3601, 600))
    info = json.loads((out / "run.json").read_text())["time"]  # a chosen --dt: backward Euler, no error estimate
    assert info["scheme"] == "theta-method" and info["theta"] == 1.0 and info["step_sizes_s"] == [600.0]
    assert info["estimate_sensor_K"] is None and info["estimate"].startswith("none")
    # run.json names the solvers that ran: the fastest installed (cvxopt's CHOLMOD with the fast extra)
    from hybridcomp.fem import solvers

    run = json.loads((out / "run.json").read_text())
    names = {"cholmod": "cholmod", "cvxopt": "cvxopt-cholmod", "pyamg": "pyamg-cg", "superlu": "superlu-nd"}
    assert run["solvers"] == {"heat": names[solvers.factor_backend()],
                              "elastic": names[solvers.few_backend(3 * run["nodes"])]}


@pytest.mark.parametrize(
    "args,match",
    [
        (["--loads", "{bad}"], "is not an input of machine"),
        (["--loads", "{good}", "--pose", "X=900"], "pose X = 900.0 mm is outside the travel"),
        (["--loads", "{good}", "--pose", "Q=1"], "pose names axis 'Q'"),
        (["--loads", "{good}", "--dt", "-5"], "--dt must be positive"),
        (["--loads", "{good}", "--time-tol-um", "0"], "--time-tol-um must be positive, got 0.0"),
        (["--loads", "{good}", "--theta", "0.5", "--time-tol-K", "0.1"],
         "--time-tol-K applies to the default error-controlled scheme, not with --theta"),
        (["--loads", "{good}", "--machine", "{typo}"], "'machine.nmae' is not a known field"),
        (["--loads", "{good}", "--machine", "nosuchmachine"], "neither a file nor a bundled machine"),
    ],
)
def test_simulate_cli_bad_input_writes_nothing(tmp_path, capsys, args, match, write_csv):
    good = write_csv(tmp_path / "good.csv", ["time_s", "x_motor_W"], [[0, 1], [60, 1]])
    bad = write_csv(tmp_path / "bad.csv", ["time_s", "x_motor_typo_W"], [[0, 1], [60, 1]])
    typo = tmp_path / "typo.toml"
    typo.write_text(resolve_machine_path("vmc800").read_text().replace('name = "vmc800"', 'nmae = "vmc800"', 1))
    args = [a.format(good=good, bad=bad, typo=typo) for a in args]
    out = tmp_path / "out"
    rc = main(["simulate", "--out", str(out), *COARSE, *args])
    assert rc == 2
    assert match in capsys.readouterr().err
    assert not out.exists()


def test_help_explains_the_contract(capsys):
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "<source>[<segment>]_W" in text and "unknown column is an error" in text
    assert "TR-BDF2" in text and "--time-tol-K" in text and "no time-error estimate" in text


def test_machine_and_example_loads_commands(tmp_path, capsys):
    assert main(["machine"]) == 0
    assert "vmc800" in capsys.readouterr().out
    assert main(["machine", "vmc800", "--mesh", "--element-size-mm", "200"]) == 0
    assert "nodes" in capsys.readouterr().out
    assert main(["example-loads", "--hours", "1", "--out", str(tmp_path / "l.csv")]) == 0
    loads = read_loads(tmp_path / "l.csv", load_machine("vmc800"))
    assert loads.time_s[-1] == 3600


def test_xdmf_time_series_round_trip(machine, tmp_path):
    pytest.importorskip("h5py", reason="XDMF export needs h5py (extra 'xdmf')")
    from hybridcomp.fem.export import write_fields
    from hybridcomp.fem.model import build_model

    model = build_model(machine, None, 200.0)
    loads = example_loads(machine, duration_h=1.0, dt_s=600.0)
    res = model.simulate(loads, scheme="theta", store_steps=(0, 3, 6))
    (path,) = write_fields(model, tmp_path, res.fields_K, res.time_s, fmt="xdmf", with_displacement=False)
    with meshio.xdmf.TimeSeriesReader(path) as r:
        points, cells = r.read_points_cells()
        times = []
        for k in range(r.num_steps):
            t, pdata, _ = r.read_data(k)
            times.append(t)
            step = [0, 3, 6][k]
            np.testing.assert_allclose(pdata["temperature_degC"], res.fields_K[step] + 20.0, rtol=1e-12)
    np.testing.assert_allclose(times, res.time_s[[0, 3, 6]])
    assert len(points) == model.n


@pytest.mark.slow
def test_simulate_rom_writes_every_output_group_of_a_pose_aware_model_under_its_own_header(machine, tmp_path, capsys):
    """``reduce --poses star`` on the coarse model, then ``simulate --rom``: each table's header matches its rows,
    and its values are the model's outputs in µm (a support pose's drift is what drift_along gives there)."""
    from hybridcomp.rom.poses import drift_along, grid_of
    from hybridcomp.rom.reduced import load_rom

    loads = example_loads(machine, duration_h=2.0, dt_s=300.0)
    write_loads(tmp_path / "loads.csv", loads)
    assert main(["reduce", "--machine", "vmc800", "--element-size-mm", "200", "--order", "20", "--poses", "star",
                 "--pose-enrich", "5", "--out", str(tmp_path / "pose.npz")]) == 0
    out = tmp_path / "run"
    out.mkdir()
    (out / "poses.csv").write_text("an earlier run's\n")
    args = ["simulate", "--machine", "vmc800", "--loads", str(tmp_path / "loads.csv"), "--rom", str(tmp_path / "pose.npz"),
            "--out", str(out)]
    capsys.readouterr()
    assert main(args) == 2  # a group table of an earlier run is kept without --force, and nothing is written
    assert "poses.csv" in capsys.readouterr().err and not (out / "outputs.csv").exists()
    assert main([*args, "--force"]) == 0

    rom = load_rom(tmp_path / "pose.npz")
    grid = grid_of(rom)
    loads = read_loads(tmp_path / "loads.csv", machine)  # as the command read them
    Y, _ = rom.integrate(loads.time_s, rom.layout().inputs(loads))
    info = json.loads((out / "run.json").read_text())
    assert info["files"] == ["outputs.csv", "poses.csv", "feedback.csv"]
    tables = {}
    for name in info["files"]:
        with (out / name).open(newline="") as fh:
            rows = list(csv.reader(fh))
        assert all(len(row) == len(rows[0]) for row in rows), name  # every row has a field per header name
        assert len(rows) - 1 == loads.time_s.size and rows[0][0] == "time_s"
        tables[name] = (rows[0][1:], np.array(rows[1:], float)[:, 1:])

    header, data = tables["outputs.csv"]
    assert header == [*(f"T{i}_degC" for i in range(1, 9)), "dx_um", "dy_um", "dz_um"]
    at = lambda k: np.array([[grid.pose_mm(k)[a] for a in grid.axes]])  # noqa: E731
    np.testing.assert_allclose(data[:, 8:], drift_along(rom, Y, at(0), feedback=False), rtol=0, atol=6e-7)
    np.testing.assert_allclose(data[:, :8], rom.simulate(loads).sensors_degC, rtol=0, atol=6e-7)

    header, data = tables["poses.csv"]
    assert header == [f"pose{k}_{d}_um" for k in range(1, len(grid.poses)) for d in ("dx", "dy", "dz")]
    assert info["support_poses_mm"] == {f"pose{k}": grid.pose_mm(k) for k in range(1, len(grid.poses))}
    for k in range(1, len(grid.poses)):
        np.testing.assert_allclose(data[:, 3 * (k - 1):3 * k], drift_along(rom, Y, at(k), feedback=False),
                                   rtol=0, atol=6e-7)

    header, data = tables["feedback.csv"]
    fb = rom.meta["feedback"]
    assert len(header) == sum(len(f["positions_mm"]) for f in fb.values())
    for axis, f in fb.items():  # at a feedback position the drive adds its error there, signed by the side it moves
        p = f["positions_mm"][3]
        j = header.index(f"{axis}_feedback_um@{p:g}")
        pos = at(0)
        pos[0, grid.axes.index(axis)] = p
        added = drift_along(rom, Y, pos) - drift_along(rom, Y, pos, feedback=False)
        np.testing.assert_allclose(f["sign"] * data[:, j], added[:, f["direction"]], rtol=0, atol=6e-7)
        assert np.abs(data[:, j]).max() > 1e-3  # the drive's error is not zero
