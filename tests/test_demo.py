"""The main job end to end, shortened (coarse mesh, 6 h of the day, 3 h basic load cases): the report's claims."""

from __future__ import annotations

import json
import logging

import pytest

pytest.importorskip("sqlalchemy", reason="the demo's CD database needs SQLAlchemy (pip install 'hybridcomp[db]')")

from hybridcomp.cli import main

pytestmark = pytest.mark.slow  # FE, reduced models and daemon runs: the full suite, not the fast loop


def _refuse(word):
    raise ValueError(f"summary.json is not strict JSON: {word}")


def test_short_demo_names_the_planted_cause_and_hybrid_beats_static(tmp_path, monkeypatch, caplog):
    # a relative --out, as README types it: the generation worker must write into the same database
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "demo"
    assert main(["demo", "--out", "demo", "--element-size-mm", "150", "--day-hours", "6", "--basic-hours", "3",
                 "--no-pictures", "--no-progress"]) == 0
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], "the demo logged errors"
    assert not (out / "hybrid_nominal" / "demo").exists(), "a relative path was joined twice"
    s = json.loads((out / "summary.json").read_text(), parse_constant=_refuse)  # strict JSON: NaN is written as null
    generated = [e["ids"] for e in s["events"] if e["kind"] == "generation" and e["status"] == "finished"]
    activated = [e["ids"] for e in s["events"] if e["kind"] == "activation"]
    assert generated, "the short demo should generate at least one CD set"
    assert all(ids in activated for ids in generated), "a generated CD set was not activated"
    r = s["residual_3d"]
    # the diagnosis names the planted effect (front spindle bearing at 1.6 x its power) and recovers its factor
    assert s["diagnosis"]["verdict"] == "explained" and s["diagnosis"]["planted_cause_named"]
    (cause,) = [c for c in s["diagnosis"]["causes"] if c["target"] == "spindle_bearing_front"]
    assert cause["parameters"]["factor [-]"] == pytest.approx(1.6, rel=0.05)
    # the hybrid monitor beats the static default CDs and no compensation
    assert r["hybrid monitor"]["rms_um"] < r["static default CDs"]["rms_um"] < r["no compensation"]["rms_um"]
    # the extended machine file fixes the structure model
    assert r["ROM direct after diagnosis"]["rms_um"] < 0.2 * r["ROM direct"]["rms_um"]
    report = (out / "report.md").read_text()
    assert "| hybrid after diagnosis |" in report and "spindle_bearing_front" in report
    assert (out / "diagnosis" / "machine_extended.toml").is_file()
    # along the path the screws' elongation is ten-odd µm a one-pose compensation cannot see; the pose-aware
    # structure model, with the drives, can, and the daemons compensating where the tool is do as well as at the pose
    p = s["along_path"]
    assert p["position_dependent_um"]["dx_um"] > 5 and p["position_dependent_um"]["dy_um"] > 5
    a = p["residual_3d"]
    assert a["ROM direct"]["rms_um"] > 1.5 * a["ROM direct along the path"]["rms_um"]  # one pose: blind to the screws
    assert a["ROM direct along the path"]["rms_um"] < r["ROM direct"]["rms_um"] + 1.0  # as good as at its own pose
    for name in ("hybrid monitor", "observer"):
        assert a[f"{name} at one pose"]["rms_um"] > 5.0  # the same runs' one-pose offsets leave the screws
        assert a[name]["rms_um"] <= 0.05 * a["no compensation"]["rms_um"]
        # and within 1.5 x + 0.2 µm of what the part sees at the model's pose (its tables there against the real
        # structure and drives there), the benchmark's yardstick. (Not of the structure alone at the pose, 0.24 µm:
        # since the observer's air walk follows an unmeasured swing within minutes, it takes the bearing's excess
        # heat for warm air in the first hour, the screws follow, 1.4 µm in y from 25 to 70 min, 0.66 µm along the
        # path, README "Compensating where the tool is")
        assert a[name]["rms_um"] <= 1.5 * a[f"{name} at the model's pose, drives included"]["rms_um"] + 0.2
        assert p["largest_table_step_um"][name] <= 0.2 + 1e-9
    assert "## Along the path" in report
    assert main(["demo", "--out", str(out), "--day-hours", "17"]) == 2
