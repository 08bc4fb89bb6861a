"""Residual-drift metrics as a part sees them.

One module for the scenario, the demo, the benchmarks and the diagnosis:

* RMS and peak-to-peak of the residual (true drift − compensation);
* E_P95(w): the 95th percentile, over all windows of length ``w``, of the residual's range (max − min) within
  the window — what a part machined in ``w`` sees;
* the largest change of the offsets from one compensation cycle to the next (a step marks the surface).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from hybridcomp.models.layout import DRIFT_COLUMNS

WINDOWS_S = (900.0, 1800.0, 3600.0, 2 * 3600.0, 4 * 3600.0, 8 * 3600.0, 15 * 3600.0)
DIRS = DRIFT_COLUMNS


def window_ranges(x: np.ndarray, n: int) -> np.ndarray:
    """Range (max − min) of ``x`` in every window of ``n`` consecutive samples (x.size − n + 1 values)."""
    from numpy.lib.stride_tricks import sliding_window_view

    v = sliding_window_view(np.asarray(x, float), n)
    return v.max(axis=1) - v.min(axis=1)


def p95_range(x: np.ndarray, n: int) -> float:
    """E_P95 of ``x`` for windows of ``n`` samples (NaN when the record is shorter)."""
    x = np.asarray(x, float)
    return float(np.percentile(window_ranges(x, n), 95.0)) if 1 <= n <= x.size else math.nan


def drift_metrics(time_s: np.ndarray, residual_um: np.ndarray, windows_s: Sequence[float] = WINDOWS_S) -> dict:
    """RMS, peak-to-peak and windowed 95th-percentile ranges of a residual drift.

    Parameters
    ----------
    time_s : uniformly spaced times [s] (n,)
    residual_um : residual drift per direction [µm] (n × 3: dx, dy, dz)
    windows_s : sliding-window lengths [s]

    Returns
    -------
    ``{"dx_um": {...}, "dy_um": {...}, "dz_um": {...}, "3d": {...}}`` with ``rms_um``, ``p2p_um`` and
    ``p95_range_um`` (window length [s] → value); for ``"3d"`` the RMS of the vector length and, per
    window, the largest of the three directions' values.
    """
    t = np.asarray(time_s, float)
    R = np.asarray(residual_um, float)
    dt = np.diff(t)
    if not np.allclose(dt, dt[0], rtol=1e-6, atol=1e-9):
        raise ValueError("drift_metrics needs uniformly spaced samples")
    out = {}
    for j, d in enumerate(DIRS):
        x = R[:, j]
        p95 = {float(w): p95_range(x, int(round(w / dt[0])) + 1) for w in windows_s}
        out[d] = {"rms_um": float(np.sqrt(np.mean(x**2))), "p2p_um": float(x.max() - x.min()), "p95_range_um": p95}
    out["3d"] = {
        "rms_um": float(np.sqrt(np.mean(np.sum(R**2, axis=1)))),
        "p2p_um": max(out[d]["p2p_um"] for d in DIRS),
        "p95_range_um": {float(w): max(out[d]["p95_range_um"][float(w)] for d in DIRS) for w in windows_s},
    }
    return out


def largest_step_um(offsets_um: np.ndarray) -> float:
    """The largest change of any offset from one compensation cycle to the next [µm] (rows: cycles)."""
    o = np.asarray(offsets_um, float)
    return float(np.abs(np.diff(o, axis=0)).max()) if len(o) > 1 else 0.0


def _hms(w: float) -> str:
    return f"{w / 3600:g} h" if w >= 3600 else f"{w / 60:g} min"


def cell_um(value: float) -> str:
    """A table cell of a length [µm] to 0.01 µm; ``–`` where there is no value (NaN: e.g. a window longer than the day)."""
    return f"{value:.2f}" if math.isfinite(value) else "–"


def metrics_table(metrics: Mapping[str, dict], windows_s: Sequence[float] = WINDOWS_S) -> str:
    """A Markdown table: one row per strategy and direction (and the 3-D residual); ``–`` where there is no value."""
    head = ["strategy", "direction", "RMS [µm]", "P2P [µm]", *(f"p95 range {_hms(w)} [µm]" for w in windows_s)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, m in metrics.items():
        for d in (*DIRS, "3d"):
            r = m[d]
            lines.append("| " + " | ".join([name, d.replace("_um", ""), cell_um(r["rms_um"]), cell_um(r["p2p_um"]),
                                            *(cell_um(r["p95_range_um"][float(w)]) for w in windows_s)]) + " |")
    return "\n".join(lines)
