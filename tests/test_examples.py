"""The scripts in examples/ run as users run them, and show what they claim (as scikit-fem tests its examples)."""

from __future__ import annotations

import numpy as np
import pytest
from scripts import ROOT, load_script

EXAMPLES = ROOT / "examples"


def load(name: str):
    return load_script(f"examples/{name}.py", f"example_{name}")


def test_every_example_is_tested():
    tested = {"trace_to_fe", "reduce_and_replay", "diagnose_csv", "campaign"}
    assert {p.stem for p in EXAMPLES.glob("*.py")} == tested


@pytest.mark.slow
def test_trace_to_fe(tmp_path, capsys):
    res = load("trace_to_fe").main(["--out", str(tmp_path / "out")])
    assert (tmp_path / "out" / "outputs.csv").is_file() and (tmp_path / "out" / "loads.csv").is_file()
    # the default FE run meets its stated time tolerance
    assert res.time_error["met"] and res.time_error["estimate_drift_um"] <= res.time_error["tolerance_drift_um"]
    # X and the spindle work for the first two hours, then the machine stands: the drift peaks when the work stops
    t_peak_h = res.time_s[np.argmax(np.abs(res.drift_um[:, 2]))] / 3600.0
    assert 1.75 <= t_peak_h <= 2.25 and np.abs(res.drift_um[:, 2]).max() > 5.0
    assert "largest |dz|" in capsys.readouterr().out


@pytest.mark.slow
def test_reduce_and_replay(tmp_path):
    pytest.importorskip("sqlalchemy", reason="the CD database needs SQLAlchemy (pip install 'hybridcomp[db]')")
    r = load("reduce_and_replay").main(["--out", str(tmp_path / "out")])
    # an offset for every replayed sample, all finite, and compensation halves the drift at least
    assert len(r["time_s"]) == 721 and np.isfinite(r["offsets_um"]).all()
    drift_rms = float(np.sqrt(np.mean(np.sum(r["drift_um"] ** 2, axis=1))))
    assert r["residual_rms_um"] < 0.5 * drift_rms


@pytest.mark.slow
def test_diagnose_csv(tmp_path):
    summary = load("diagnose_csv").main(["--out", str(tmp_path / "out")])
    # the planted cause (front spindle bearing at 1.5 x its power) is named with its factor
    assert summary["verdict"] == "explained"
    (cause,) = [c for c in summary["causes"] if c["target"] == "spindle_bearing_front"]
    assert cause["name"] == "power_scale" and cause["parameters"]["factor [-]"] == pytest.approx(1.5, rel=0.05)


@pytest.mark.slow
def test_campaign(tmp_path, capsys):
    """Six FE test days with their own air and gauge zeros: treated as runs, the held-out days are predicted far
    better than by the same search on the days as one long series."""
    res = load("campaign").main(["--out", str(tmp_path / "runs"), "--element-size-mm", "200"])
    for c, v in res.items():
        assert v["campaign"] > v["one_series"] + 10.0, (c, v)
    assert res["dz_um"]["campaign"] > 75.0 and res["dy_um"]["campaign"] > 75.0
    assert "--train runs:1-4" in capsys.readouterr().out
