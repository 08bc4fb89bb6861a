"""CD training on the FE model (coarse mesh, short load cases) and the ``hybridcomp cd`` command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridcomp.chardiag.fit import fit_cd_set
from hybridcomp.chardiag.training import (
    TrainingDataError,
    read_training_csv,
    simulate_load_cases,
    standard_load_cases,
    write_training_csv,
)
from hybridcomp.cli import main
from hybridcomp.histogram.signature import SignatureLayout

# FE runs of whole load-case groups: the module's training table, the command line, a process pool
pytestmark = pytest.mark.slow

ELEMENT_MM = 150.0  # 4,081 nodes


def total_ratio(cds, data) -> float:
    """RMS of the 3D residual over the RMS of the 3D uncompensated drift [-]."""
    R, Y = [], []
    for cd in cds.values():
        pred, _ = cd.evaluate_table(data.columns)
        y = data.columns[cd.target]
        R.append(y - pred)
        Y.append(y)
    return float(np.sqrt(np.mean(np.square(R))) / np.sqrt(np.mean(np.square(Y))))


@pytest.fixture(scope="module")
def training(machine, model_150mm):
    cases = standard_load_cases(machine, ["basic", "simultaneous", "jobshop"], heat_h=4.0, cool_h=4.0)
    model = model_150mm  # at mid travel, as {} gives
    assert model.machine.mesh.element_size_mm == ELEMENT_MM
    return simulate_load_cases(machine, cases, model=model, dt_s=300.0)


def test_training_table_has_every_case_and_column(training, machine):
    assert training.cases == ("basic_X", "basic_Y", "basic_Z", "basic_spindle", "simultaneous", "jobshop")
    cols = set(training.columns)
    assert {f"{s.name}_degC" for s in machine.sensors} <= cols
    assert {"time_s", "x_mm", "y_mm", "z_mm", "dx_um", "dy_um", "dz_um"} <= cols
    size = SignatureLayout.of(machine).size
    assert all(training.signatures[c].shape == (size,) for c in training.cases)
    # the X case moves X alone at full feed over its full travel: factor 1 while it runs, 0 for the others
    sig = training.signatures["basic_X"]
    assert sig[0] == pytest.approx(0.5, abs=0.01) and sig[1] == 0 and sig[2] == 0  # 4 h of 8 h at factor 1
    # heating then cooling: the spindle case warms the head and cools back towards the reference
    sp = training.subset(["basic_spindle"]).columns
    dz = sp["dz_um"]
    assert np.argmax(np.abs(dz)) == pytest.approx(len(dz) / 2, abs=3) and abs(dz[-1]) < 0.6 * np.max(np.abs(dz))


def test_basic_cds_predict_the_unseen_simultaneous_case(training):
    basic = training.subset(["basic_X", "basic_Y", "basic_Z", "basic_spindle"])
    cds = fit_cd_set(basic.columns, machine="vmc800", signature=basic.signature())
    assert total_ratio(cds, training.subset(["simultaneous"])) <= 0.15


def test_cds_trained_on_the_jobshop_day_fit_it(training):
    js = training.subset(["jobshop"])
    cds = fit_cd_set(js.columns, machine="vmc800")
    assert total_ratio(cds, js) <= 0.05


def test_training_csv_round_trip_is_exact(training, tmp_path):
    p = write_training_csv(tmp_path / "train.csv", training)
    back = read_training_csv(p)
    assert back.cases == training.cases and list(back.columns) == list(training.columns)
    assert all(np.array_equal(back.columns[k], training.columns[k]) for k in training.columns)
    assert all(np.array_equal(back.signatures[k], training.signatures[k]) for k in training.signatures)
    with pytest.raises(TrainingDataError, match=r"load case\(s\) \['nope'\] not in the training data"):
        back.subset(["nope"])
    bad = tmp_path / "bad.csv"
    bad.write_text("load_case,T1_degC,dz_um\nx,20.0,1.0\nx,abc,2.0\n")
    with pytest.raises(TrainingDataError, match=r"bad\.csv: row 3, column 'T1_degC': 'abc' is not a number"):
        read_training_csv(bad)


def test_cd_command_line_fit_eval_cnc_and_database(training, tmp_path, capsys):
    data = write_training_csv(tmp_path / "train.csv", training)
    db = tmp_path / "cds.sqlite"
    out = tmp_path / "cds"
    assert main(["cd", "fit", str(data), "--cases", "basic_X,basic_Y,basic_Z,basic_spindle", "--out", str(out),
                 "--db", str(db), "--activate", "--no-plot"]) == 0
    info = json.loads((out / "fit.json").read_text())
    assert info["db_ids"] == {"X": 1, "Y": 2, "Z": 3} and info["rows"] > 100
    assert main(["cd", "eval", str(out), "--data", str(data), "--cases", "simultaneous",
                 "--out", str(tmp_path / "pred.csv")]) == 0
    assert "dz_um: rms residual" in capsys.readouterr().err
    assert main(["cd", "eval", str(out), "--point", "T1=21,T2=20.5,T3=20.2,T4=20,T5=20.3,T6=20.2,T7=20.1,T8=20",
                 "--cnc", "840d"]) == 0
    text = capsys.readouterr().out
    assert "$SA_TEMP_COMP_ABS_VALUE[X1]=" in text and "$SA_TEMP_COMP_REF_POSITION[Z1]=0.0000" in text
    assert main(["cd", "db", "list", "--db", str(db)]) == 0
    assert capsys.readouterr().out.count("ACTIVE") == 3
    assert main(["cd", "db", "export", "1", "2", "3", "--db", str(db), "--out", str(tmp_path / "exp")]) == 0
    capsys.readouterr()
    # the exported XML is the stored record: importing it again stores nothing new
    assert main(["cd", "db", "import", *map(str, sorted((tmp_path / "exp").glob("*.xml"))), "--db", str(db),
                 "--machine", "vmc800"]) == 0
    assert [ln.split(": ", 1)[1] for ln in capsys.readouterr().out.splitlines()] == [
        f"already stored as id {i}" for i in (1, 2, 3)]
    assert main(["cd", "db", "activate", "X=1,Y=2,Z=3", "--db", str(db)]) == 0
    capsys.readouterr()
    assert main(["cd", "db", "show", "1", "--db", str(db)]) == 0
    assert "T_reference" in capsys.readouterr().out
    # bad input: clear errors, exit code 2
    assert main(["cd", "eval", str(out), "--point", "T1=abc"]) == 2
    assert "--point: value 'abc' of 'T1' is not a number" in capsys.readouterr().err
    assert main(["cd", "fit", str(tmp_path / "missing.csv"), "--out", str(out)]) == 2
    assert "missing.csv: no such file" in capsys.readouterr().err
    (tmp_path / "foreign.csv").write_text("T1_degC,T99_degC,dx_um,dy_um,dz_um\n20,20,1,1,1\n21,22,2,2,2\n")
    assert main(["cd", "fit", str(tmp_path / "foreign.csv"), "--out", str(out)]) == 2
    assert "T99_degC is not a sensor of machine 'vmc800'" in capsys.readouterr().err


def test_train_data_command(tmp_path, capsys):
    out = tmp_path / "data.csv"
    assert main(["cd", "train-data", "--cases", "basic", "--heat-hours", "0.5", "--cool-hours", "0.5", "--element-size-mm", "200",
                 "--dt", "300", "--no-progress", "--out", str(out)]) == 0
    data = read_training_csv(out)
    assert data.cases == ("basic_X", "basic_Y", "basic_Z", "basic_spindle")
    T = np.column_stack([data.columns[f"T{i}_degC"] for i in range(1, 9)])
    assert T.max() > 21.0  # heat sources warm the machine ...
    assert T.min() > 20.0 - 0.02  # ... and never cool it (beyond the small undershoot of a consistent-mass FE model)
    assert main(["cd", "train-data", "--cases", "basic,nonsense", "--out", str(tmp_path / "other.csv")]) == 2
    assert "nonsense: no such file" in capsys.readouterr().err


def test_training_on_a_process_pool_equals_the_serial_run(machine):
    cases = standard_load_cases(machine, ["basic"], heat_h=0.5, cool_h=0.5)
    serial = simulate_load_cases(machine, cases, element_size_mm=200.0, dt_s=300.0)
    pooled = simulate_load_cases(machine, cases, element_size_mm=200.0, dt_s=300.0, executor="process", workers=2)
    assert pooled.cases == serial.cases
    for k in serial.columns:
        np.testing.assert_allclose(pooled.columns[k], serial.columns[k], rtol=0, atol=1e-9)
