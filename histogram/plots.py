"""Pictures of histograms and load factors (matplotlib, PNG; extra ``plot``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hybridcomp.histogram.increments import Increments


def _pyplot():
    try:
        import matplotlib
    except ImportError:  # pragma: no cover - depends on the installation
        raise RuntimeError("pictures need matplotlib: pip install 'hybridcomp[plot]'") from None
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_increment(inc: Increments, k: int, path: str | Path) -> Path:
    """Per-axis histogram of increment ``k``: bars per rail segment, the fine histogram and the load factor.

    Parameters
    ----------
    inc : increments
    k : increment index (negative counts from the end)
    path : PNG to write

    Returns
    -------
    the PNG path
    """
    plt = _pyplot()
    n = len(inc)
    if not -n <= k < n:
        raise IndexError(f"increment {k} does not exist ({n} increments)")
    k = k % n
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    na = len(inc.axis_names)
    fig, axs = plt.subplots(na, 2, figsize=(7.5, 2.2 * na + 0.6), squeeze=False, gridspec_kw={"width_ratios": [14, 1]})
    for j, name in enumerate(inc.axis_names):
        ax = axs[j, 0]
        seg = inc.segment_edges_mm(name)
        frac = inc.segment_fraction(name)[k]
        ax.bar(seg[:-1], frac, width=np.diff(seg), align="edge", color="#9ecae1", edgecolor="#3182bd",
               label="time fraction in the rail segment")
        e = inc.bin_edges_mm[j]
        # a density, so that bars and bins share one scale: time fraction per rail-segment length (a bin is
        # 1/bins_per_segment of a segment, so a bin's value is its time fraction × bins_per_segment and can exceed 1)
        fine = inc.histogram(name)[k] * inc.bins_per_segment
        ax.stairs(fine, e, color="#08519c",
                  label=f"positions: time fraction in the bin × {inc.bins_per_segment} bins per segment")
        ax.set_xlim(e[0], e[-1])
        ax.set_ylim(0, max(1.0, float(fine.max()) * 1.05))
        ax.set_ylabel("time fraction\nper segment length [-]", fontsize=9)
        f = inc.axis_factor[k, j]
        ax.set_title(f"axis {name}", fontsize=10, loc="left")
        if j == 0:
            ax.legend(fontsize=7, loc="upper center")
        fx = axs[j, 1]
        fx.bar([0], [f], color="#e6550d", width=0.8)
        fx.set_xlim(-0.5, 0.5)
        fx.set_ylim(0, 1)
        fx.set_xticks([])
        fx.yaxis.tick_right()
        fx.set_title(f"f = {f:.3f}", fontsize=9)
    axs[-1, 0].set_xlabel("axis position [mm]")
    fig.suptitle(
        f"increment {k}: {inc.start_s[k] / 3600:.3f} h to {inc.end_s[k] / 3600:.3f} h, "
        f"spindle factor {inc.spindle_factor[k]:.3f}",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_factors(inc: Increments, path: str | Path) -> Path:
    """Load factors of every axis and the spindle over the whole trace, one step per increment."""
    plt = _pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(9.0, 3.6))
    edges = np.append(inc.start_s, inc.end_s[-1]) / 3600.0
    for j, name in enumerate(inc.axis_names):
        ax.stairs(inc.axis_factor[:, j], edges, label=f"axis {name}")
    ax.stairs(inc.spindle_factor, edges, label="spindle", color="k", linewidth=1.5)
    gaps = np.flatnonzero(inc.gap_s > 0)
    for g in gaps:
        ax.axvspan(edges[g], edges[g + 1], color="0.9", zorder=0)
    ax.set_xlim(edges[0], edges[-1])
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("time [h]")
    ax.set_ylabel("load factor [-]")
    ax.set_title(f"load factors per {inc.increment_s:g} s increment" + (" (grey: recording gaps)" if gaps.size else ""),
                 fontsize=10)
    ax.legend(fontsize=8, ncol=len(inc.axis_names) + 1, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
