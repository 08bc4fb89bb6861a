"""The report tables as a person reads them: no raw Python (dicts, ``None``) and no ``nan`` in any cell."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from hybridcomp.demo import event_details
from hybridcomp.metrics import drift_metrics, metrics_table
from hybridcomp.scenario import _event_brief

# events as the daemon stores them (payload shapes of monitor/daemon.py), through the scenario's brief
EVENTS = [
    ("decision", {"action": "switch", "reason": "interval error above 5 µm", "candidates": 2,
                  "error_um": {"interval_um": 5.47036379782565, "forecast_um": math.nan}, "delta_T_K": 0.6234}),
    ("decision", {"action": "generate", "reason": "no stored set fits", "error_um": None, "delta_T_K": None}),
    ("generation", {"status": "started", "request": {"load_case": "day"}}),
    ("generation", {"status": "finished", "ids": {"X": 4, "Y": 5, "Z": 6}, "load_case": "day", "wall_s": 312.4,
                    "notes": {"X": {"inputs": ["T1"], "rms_residual_um": 0.52, "bumpless": True}}}),
    ("activation", {"ids": {"X": 4, "Y": 5, "Z": 6}, "reason": "generated"}),
    ("sensor", {"status": "stuck", "sensor": "T1", "onset_s": 28800.0, "T_degC": [20.13, math.nan]}),
    ("observer", {"status": "flagged", "reason": None}),
]


def test_decision_table_cells_hold_no_raw_python():
    for kind, payload in EVENTS:
        brief = _event_brief(SimpleNamespace(kind=kind, payload=payload))
        cell = event_details({"kind": kind, "machine_time_s": 3600.0, **brief})
        assert not any(raw in cell for raw in ("{", "}", "None", "nan", "'", "|")), (kind, cell)
    cell = event_details({"kind": "decision", **_event_brief(SimpleNamespace(kind="decision", payload=EVENTS[0][1]))})
    assert cell == "action: switch; reason: interval error above 5 µm; error: interval 5.47 µm, forecast –; delta T: " \
                   "0.623 K"
    assert event_details({"kind": "generation", "status": "started", "ids": None, "error": None}) == "status: started"
    cell = event_details({"kind": "generation", **_event_brief(SimpleNamespace(kind="generation", payload=EVENTS[3][1]))})
    assert cell == "status: finished; ids: X 4, Y 5, Z 6; wall: 312 s; notes: X (inputs T1, rms residual 0.52 µm, " \
                   "bumpless yes)"


def test_metrics_table_prints_a_dash_where_there_is_no_value():
    t = np.arange(0.0, 2 * 3600.0 + 1, 60.0)  # 2 h: the 4 h and longer windows have no value
    res = np.column_stack([np.sin(t / 3000.0), np.cos(t / 2000.0), 0.1 * t / 3600.0])
    table = metrics_table({"no compensation": drift_metrics(t, res)})
    assert "nan" not in table.lower()
    assert "–" in table
    rows = [r for r in table.splitlines()[2:]]
    assert len(rows) == 4 and all(r.count("|") == table.splitlines()[0].count("|") for r in rows)


def test_xcorr_plot_draws_proportional_signals_as_one_curve_with_one_legend_entry():
    from hybridcomp.diagnose.metrics import cross_correlation
    from hybridcomp.diagnose.report import xcorr_curves

    t = np.linspace(0.0, 8.0, 200)
    residual = np.sin(t) + 0.1 * t
    spindle = np.clip(np.sin(3 * t), 0, None)
    signals = {f"{s}_W": f * spindle for s, f in (("bearing_front", 40.0), ("bearing_rear", 25.0), ("motor", 300.0),
                                                   ("nut", 2.0), ("housing", 7.0))}
    signals["ambient_degC"] = 20.0 + np.cos(t / 2)
    curves = []
    for name, v in signals.items():
        lags, rho = cross_correlation(residual, v, 20)
        curves.append(("dz_um", name, lags / 60.0, rho))
    drawn = xcorr_curves(curves)
    assert len(drawn) == 2  # six correlations, five of them the same curve
    label = drawn[0][0].replace("\n", " ")
    assert all(s in label for s in list(signals)[:5]) and "ambient" not in label
    assert drawn[1][0] == "dz_um vs ambient_degC"
