"""``benchmarks/pose_path.py`` can fail: planted errors (a support pose's block dropped, the pose history ignored)
fail where the prediction passes."""

from __future__ import annotations

import json

import pytest


def test_hold_rows_give_the_move_row_to_the_new_hold(benchmark_script):
    import numpy as np

    t = np.arange(0.0, 16 * 3600.0 + 1.0, 1800.0)
    assert benchmark_script("pose_path").hold_rows(t, ((8.0, {}), (8.0, {}))) == [(0, 16), (16, 32)]
    with pytest.raises(ValueError, match="the holds last 12 h, the loads 16 h"):
        benchmark_script("pose_path").hold_rows(t, ((4.0, {}), (8.0, {})))


@pytest.mark.slow
def test_planted_errors_fail_where_the_prediction_passes(capsys, benchmark_script):
    """200 mm, 5 min steps, no off-grid poses held all day: the second path's first hold sits at support pose 9 (the
    Z axis' lower end with the default levels, seven along Y and Z), where the pose-aware model is its own block;
    dropping that block must fail the criterion.
    After the move to the Z axis' upper end, the model that ignores the pose history must fail too."""
    assert benchmark_script("pose_path").main(["--fast", "--poses", "0", "--plant", "9"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["plant"] == 9 and out["element_size_mm"] == 200.0 and out["levels"] == {"Y": 7, "Z": 7}
    hold = next(c for c in out["cases"] if c["case"] == "8 h Z low, 8 h Z high" and c["hold"].startswith("1:"))
    assert hold["pose-aware ROM"]["ok"], hold
    assert not hold["planted: a support pose dropped"]["ok"], hold
    assert any(e > 2 * lim for e, lim in zip(hold["planted: a support pose dropped"]["max_error_um"], hold["limit_um"]))
    assert out["within_limit"]["paths_planted"] is False
    after = next(c for c in out["cases"] if c["case"] == "8 h Z low, 8 h Z high" and c["hold"].startswith("2:"))
    assert after["pose-aware ROM"]["ok"], after
    assert not after["history ignored"]["ok"], after
    assert max(after["history ignored"]["max_error_um"]) > 3 * max(after["pose-aware ROM"]["max_error_um"]), after
