"""Strict JSON: every JSON the project writes parses with a strict parser; NaN and infinity become null."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hybridcomp.models import jsonio


def strict_loads(text: str):
    """``json.loads`` that rejects the non-standard words NaN, Infinity and -Infinity."""
    def refuse(word):
        raise ValueError(f"not JSON: {word}")

    return json.loads(text, parse_constant=refuse)


def test_a_nan_metric_becomes_null_and_the_file_parses_strictly(tmp_path):
    summary = {"rms_um": math.nan, "p95_range_um": {"3600": np.float64(np.inf), "7200": 1.5},
               "series": np.array([1.0, -np.inf, 2.0]), "count": np.int64(3), "ok": np.bool_(True),
               "pair": (math.nan, 0.25)}
    with pytest.raises(ValueError, match="not JSON: NaN"):
        strict_loads(json.dumps(summary, default=lambda o: o.tolist() if hasattr(o, "tolist") else o))
    path = jsonio.write_json(tmp_path / "summary.json", summary, indent=1)
    back = strict_loads(path.read_text())
    assert back == {"rms_um": None, "p95_range_um": {"3600": None, "7200": 1.5}, "series": [1.0, None, 2.0],
                    "count": 3, "ok": True, "pair": [None, 0.25]}


def test_a_non_finite_number_that_slips_past_is_an_error_not_a_file():
    with pytest.raises(ValueError, match="Out of range float values are not JSON compliant"):
        jsonio.dumps({"x": object()}, default=lambda o: math.nan)
