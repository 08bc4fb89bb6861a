"""Plot axes a person reads at a glance, shared by the reports: E_P95(range) against the window length.

The demo's ``ep95.png`` (:func:`hybridcomp.demo._ep95_plot`) and the diagnosis report's
(:func:`hybridcomp.diagnose.report.ep95_plot`) draw their curves on the same axes (:func:`window_axes`): the window
length on a log x axis whose ticks are windows as a person says them (15 min, 1 h, 4 h, 15 h; not 3×10⁻¹ h) and a
log y axis (compensated or extended models lie one to two decades below the others) with its ticks at 1, 2, 5 of
each decade (more when the curves span less than two decades) written as plain numbers. Only matplotlib's axes are
touched: the caller makes the figure.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

#: window lengths [h] a tick may stand at, when the caller does not name its own: 10 s, 1 min, 5 min, 15 min, 1 h,
#: 4 h, 15 h, 48 h, 168 h
READABLE_WINDOWS_H = (10.0 / 3600.0, 1.0 / 60.0, 5.0 / 60.0, 0.25, 1.0, 4.0, 15.0, 48.0, 168.0)


def window_label(hours: float) -> str:
    """A window length as a person says it: ``10 s``, ``15 min``, ``1 h``, ``1.5 h``, ``15 h``."""
    minutes = hours * 60.0
    if minutes < 1.0 - 1e-9:
        return f"{minutes * 60.0:.0f} s"
    if minutes < 60.0 - 1e-9:
        return f"{minutes:.0f} min"
    return f"{hours:g} h"


def readable_ticks(windows_h: Iterable[float], candidates_h: Sequence[float] = READABLE_WINDOWS_H) -> list[float]:
    """The candidates within the range of ``windows_h`` [h] (1 % slack at either end), in increasing order."""
    w = [float(x) for x in windows_h if x is not None and math.isfinite(float(x)) and float(x) > 0]
    if not w:
        return []
    lo, hi = min(w) / 1.01, max(w) * 1.01
    return [c for c in sorted(candidates_h) if lo <= c <= hi]


def positive(values: Iterable) -> list[float]:
    """``values`` as floats for a log axis: None, zero, negative and non-finite values become NaN (a gap)."""
    out = []
    for x in values:
        v = math.nan if x is None else float(x)
        out.append(v if math.isfinite(v) and v > 0 else math.nan)
    return out


def y_subs(lo: float, hi: float) -> tuple[float, ...]:
    """The mantissas labelled on a log axis from ``lo`` to ``hi``: 1, 2, 5 over two decades or more, more below.

    A curve within one decade would otherwise carry one or two labels (0.1 and 0.2).
    """
    decades = math.log10(hi / lo) if 0 < lo < hi and math.isfinite(hi / lo) else math.inf
    if decades >= 2.0:
        return (1.0, 2.0, 5.0)
    if decades >= 1.0:
        return (1.0, 2.0, 3.0, 5.0)
    return (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0)


def window_axes(ax, windows_h: Iterable[float], ticks_h: Sequence[float] | None = None,
                xlabel: str = "window length") -> list[float]:
    """Log x (the window length) with readable window ticks, log y with ticks as plain numbers (1, 2, 5, ...), a grid.

    Call it after the curves are drawn: the y ticks are chosen for their range (:func:`y_subs`).

    Parameters
    ----------
    ax : a matplotlib ``Axes`` with the curves drawn (x in hours)
    windows_h : the windows the curves are drawn at [h]
    ticks_h : the windows to tick [h]; None: :func:`readable_ticks` of ``windows_h``
    xlabel : the x axis label

    Returns
    -------
    the windows ticked [h]
    """
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter, NullLocator

    ticks = sorted(ticks_h) if ticks_h is not None else readable_ticks(windows_h)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_locator(NullLocator())
    ax.set_xticks(ticks, [window_label(h) for h in ticks])
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=y_subs(*ax.get_ylim())))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:g}"))
    ax.set_xlabel(xlabel)
    ax.grid(alpha=0.3, which="both")
    return ticks


__all__ = ["READABLE_WINDOWS_H", "positive", "readable_ticks", "window_axes", "window_label", "y_subs"]
