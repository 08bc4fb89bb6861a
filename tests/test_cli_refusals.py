"""Options given on a path where they have no effect are refused, never silently ignored.

Every case runs ``hybridcomp`` in-process: exit code 2, one line on stderr that names the option, nothing
written. The refusals come before any file is read, so the inputs need not exist.
"""

from __future__ import annotations

import pytest

from hybridcomp.cli import main
from hybridcomp.models.loader import load_machine

MONITOR_OPCUA = """\
[monitor]
machine = "vmc800"
database = "cd.db"
rom = "rom.npz"

[source]
kind = "opcua"
url = "opc.tcp://127.0.0.1:4840"
nodes = { time_s = "ns=2;s=time" }

[sink]
kind = "none"
"""

CASES = {
    "reduce --matrices --basis h2": (["reduce", "--matrices", "{d}/sys.mat", "--basis", "h2", "--out", "{out}"], "--basis"),
    "reduce --matrices --machine": (["reduce", "--matrices", "{d}/sys.mat", "--machine", "vmc800", "--out", "{out}"],
                                    "--machine"),
    "reduce --matrices --pose": (["reduce", "--matrices", "{d}/sys.mat", "--pose", "X=0", "--out", "{out}"], "--pose"),
    "reduce --matrices --element-size-mm": (["reduce", "--matrices", "{d}/sys.mat", "--element-size-mm", "100",
                                             "--out", "{out}"], "--element-size-mm"),
    "reduce --matrices --tol-um": (["reduce", "--matrices", "{d}/sys.mat", "--tol-um", "0.1", "--out", "{out}"],
                                   "--tol-um"),
    "reduce --matrices --h-range": (["reduce", "--matrices", "{d}/sys.mat", "--h-range", "0.5,2", "--out", "{out}"],
                                    "--h-range"),
    "reduce --matrices --check-loads": (["reduce", "--matrices", "{d}/sys.mat", "--check-loads", "{d}/l.csv",
                                         "--out", "{out}"], "--check-loads"),
    "reduce --matrices --order --tol-K": (["reduce", "--matrices", "{d}/sys.mat", "--order", "10", "--tol-K", "0.1",
                                           "--out", "{out}"], "--tol-K"),
    "reduce --h2-maxiter without h2": (["reduce", "--h2-maxiter", "5", "--out", "{out}"], "--h2-maxiter"),
    "simulate --field-format without --fields": (["simulate", "--loads", "{d}/l.csv", "--field-format", "xdmf",
                                                  "--out", "{out}"], "--field-format"),
    "batch serial --workers": (["batch", "run", "{d}", "--scheduler", "serial", "--workers", "2", "--out", "{out}"], "--workers"),
    "batch on a Dask scheduler --workers": (["batch", "run", "{d}", "--scheduler", "tcp://127.0.0.1:1", "--workers",
                                             "2", "--out", "{out}"], "--workers"),
    "machine --element-size-mm without --mesh": (["machine", "vmc800", "--element-size-mm", "200"],
                                                 "--element-size-mm"),
    "histogram G-code --max-gap": (["histogram", "{d}/p.nc", "--max-gap", "10", "--out", "{out}"], "--max-gap"),
    "histogram G-code --feed-tolerance": (["histogram", "{d}/p.nc", "--feed-tolerance", "0.1", "--out", "{out}"],
                                          "--feed-tolerance"),
    "histogram --signature-period without --signature": (["histogram", "{d}/t.csv", "--signature-period", "600",
                                                          "--out", "{out}"], "--signature-period"),
    "histogram --plot-increment without --plot": (["histogram", "{d}/t.csv", "--plot-increment", "3",
                                                   "--out", "{out}"], "--plot-increment"),
    "scenario jobshop --hours": (["scenario", "jobshop", "--hours", "2", "--out", "{out}"], "--hours"),
    "cd train-data --workers without a pool": (["cd", "train-data", "--workers", "2", "--out", "{out}"], "--workers"),
    "cd train-data --heat-hours for the job-shop day": (["cd", "train-data", "--cases", "jobshop", "--heat-hours", "2",
                                                         "--out", "{out}"], "--heat-hours"),
    "cd train-data --cool-hours for a file case": (["cd", "train-data", "--cases", "{d}/t.csv", "--cool-hours", "2",
                                                    "--out", "{out}"], "--cool-hours"),
    "cd fit --activate without --db": (["cd", "fit", "{d}/data.csv", "--activate", "--out", "{out}"], "--activate"),
    "cd eval --point --cases": (["cd", "eval", "{d}", "--point", "T1=20", "--cases", "a", "--out", "{out}"],
                                "--cases"),
    "cd eval --cnc without --point": (["cd", "eval", "{d}", "--data", "{d}/data.csv", "--cnc", "generic",
                                       "--out", "{out}"], "--cnc"),
    "cd eval --axis-names without 840d": (["cd", "eval", "{d}", "--point", "T1=20", "--cnc", "generic",
                                           "--axis-names", "X=X1", "--out", "{out}"], "--axis-names"),
    "diagnose --data-only --rom": (["diagnose", "--data-only", "--data", "{d}/m.csv", "--rom", "{d}/r.npz",
                                    "--out", "{out}"], "--rom"),
    "diagnose --data-only --machine": (["diagnose", "--data-only", "--data", "{d}/m.csv", "--machine", "vmc800",
                                        "--out", "{out}"], "--machine"),
    "diagnose --data-only --effects": (["diagnose", "--data-only", "--data", "{d}/m.csv", "--effects", "htc",
                                        "--out", "{out}"], "--effects"),
    "diagnose model --beam": (["diagnose", "--data", "{d}/m.csv", "--beam", "4", "--out", "{out}"], "--beam"),
    "diagnose --data-only --place-sources": (["diagnose", "--data-only", "--data", "{d}/m.csv", "--place-sources",
                                              "continuous", "--out", "{out}"], "--place-sources"),
    "diagnose --data-only --surface-tolerance": (["diagnose", "--data-only", "--data", "{d}/m.csv",
                                                  "--surface-tolerance", "0.02", "--out", "{out}"], "--surface-tolerance"),
    "diagnose --surface-tolerance with --rom": (["diagnose", "--data", "{d}/m.csv", "--rom", "{d}/r.npz",
                                                 "--surface-tolerance", "0.02", "--out", "{out}"], "--surface-tolerance"),
    "monitor run --speed on OPC UA": (["monitor", "run", "--config", "{d}/monitor.toml", "--speed", "0"], "--speed"),
}


@pytest.mark.parametrize("argv,option", CASES.values(), ids=CASES.keys())
def test_an_option_without_effect_is_refused_in_one_line(tmp_path, capsys, argv, option):
    (tmp_path / "monitor.toml").write_text(MONITOR_OPCUA)
    out = tmp_path / "out"
    rc = main([a.format(d=tmp_path, out=out) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "\n" not in err and option in err, err
    assert not out.exists()


def test_an_option_typed_with_its_default_value_on_its_own_path_is_not_refused(tmp_path, capsys):
    # --basis krylov with --matrices is exactly what runs: no refusal; the missing file is the error
    rc = main(["reduce", "--matrices", str(tmp_path / "sys.mat"), "--basis", "krylov", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--basis" not in err and "sys.mat" in err, err


@pytest.mark.parametrize("argv,option", [
    (["--plant-source", "spindle_fan"], "--plant-source"),
    (["--plant-factor", "0"], "--plant-factor"),
    (["--day-hours", "17"], "--day-hours"),
], ids=["unknown source", "factor not positive", "longer than the day"])
def test_demo_refuses_a_planted_effect_it_cannot_plant_before_any_work(tmp_path, capsys, argv, option):
    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--no-pictures", "--no-progress", *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and option in err, err
    assert not out.exists()


@pytest.mark.parametrize("argv,option", [
    (["--disturbance", "sensor fault", "--day-hours", "6"], "--day-hours 6"),
    (["--disturbance", "sensor fault", "--day-hours", "8"], "--day-hours 8"),
    (["--day-hours", "17"], "--day-hours"),
    (["--basic-hours", "0"], "--basic-hours"),
    (["--element-size-mm", "-1"], "--element-size-mm"),
], ids=["sensor fault after a 6 h day", "sensor fault at the end of the day", "longer than the day",
        "no basic load cases", "negative element size"])
def test_monitor_scenario_refuses_what_it_cannot_run_before_any_work(tmp_path, capsys, argv, option):
    # the sensor fault is planted at 8 h: a 6 h day used to crash with an IndexError in a half-written folder
    out = tmp_path / "scenario"
    rc = main(["monitor", "scenario", "--out", str(out), "--element-size-mm", "150", "--basic-hours", "3", *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and err.startswith("error: ") and option in err, err
    assert not out.exists()


def test_a_scenario_with_a_sensor_fault_after_the_day_is_refused_when_it_is_made():
    from hybridcomp.scenario import DISTURBANCES, Scenario

    with pytest.raises(ValueError, match="day_hours 6: .*sensor T1"):
        Scenario(disturbance=DISTURBANCES["sensor fault"], day_hours=6.0)


@pytest.mark.parametrize("option", [["--theta", "1"], ["--time-tol-K", "0.01"], ["--time-tol-um", "0.05"]])
def test_simulate_with_a_rom_refuses_an_fe_stepping_option_even_at_its_default_value(tmp_path, capsys, option):
    from hybridcomp.models.loads import example_loads, write_loads

    machine = load_machine("vmc800")
    write_loads(tmp_path / "loads.csv", example_loads(machine, duration_h=1.0, dt_s=600.0))
    rc = main(["simulate", "--loads", str(tmp_path / "loads.csv"), "--rom", str(tmp_path / "any.rom.npz"),
               *option, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc == 2 and f"{option[0]} applies to the FE path only" in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("command", [["batch", "run", "{d}"], ["cd", "train-data"], ["simulate", "--loads", "{d}/l.csv"]])
@pytest.mark.parametrize("option, message", [(["--theta", "3"], "--theta must be in [0.5, 1], got 3.0"),
                                             (["--dt", "-60"], "--dt must be positive, got -60.0")])
def test_every_fe_command_refuses_a_bad_dt_or_theta_by_its_option_before_any_work(tmp_path, capsys, command,
                                                                                   option, message):
    from hybridcomp.models.loads import example_loads, write_loads

    write_loads(tmp_path / "l.csv", example_loads(load_machine("vmc800"), duration_h=1.0, dt_s=600.0))
    out = tmp_path / "out"
    rc = main([c.replace("{d}", str(tmp_path)) for c in command] + [*option, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and message in err, err
    assert not out.exists()
