"""Writing a diagnosis: ``report.md`` with plots, ``summary.json`` and ``machine_extended.toml``."""

from __future__ import annotations

import logging
import textwrap
from pathlib import Path

import numpy as np

from hybridcomp.diagnose.metrics import cross_correlation, ep95_curve, lag_grid, strongest_correlations
from hybridcomp.diagnose.selection import Diagnosis
from hybridcomp.models import jsonio
from hybridcomp.safeio import write_text_atomic

log = logging.getLogger(__name__)

EP95_WINDOWS_H = (1 / 60, 0.25, 1.0, 4.0, 8.0, 24.0)


def _fmt(v, nd=3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f"{v:.{nd}g}" if abs(v) < 1e4 else f"{v:.0f}"


def before_correlations(d: Diagnosis, top: int = 10) -> list:
    """Strongest correlations of the model-as-is residual (validation rows) with the available signals."""
    p = d.problem
    va = p.split.validation
    res = {c: p.Y[va, k] - d.Y_before[va, k] for k, c in enumerate(p.channels)}
    return strongest_correlations(p.time_s[va], res, {n: v[va] for n, v in p.signals.items()}, top=top)


def ep95_table(d: Diagnosis) -> dict:
    """E_P95(range) of every channel's validation residual before and after: {channel: {windows_s, before, after}}."""
    p = d.problem
    va = p.split.validation
    out = {}
    for k, c in enumerate(p.channels):
        w, b = ep95_curve(p.time_s[va], p.Y[va, k] - d.Y_before[va, k])
        _, a = ep95_curve(p.time_s[va], p.Y[va, k] - d.Y_after[va, k])
        out[c] = {"window_s": w.tolist(), "before": b.tolist(), "after": a.tolist()}
    return out


#: cross-correlation curves closer than this at every lag are drawn as one [-] (invisible at the plot's scale)
XCORR_SAME = 1e-3


def xcorr_curves(curves: list[tuple[str, str, np.ndarray, np.ndarray]]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """One legend entry per distinct cross-correlation curve: (label, lag [h], ρ [-]) in the order given.

    Signals proportional to one another (the spindle's heat sources all follow its speed; air zones that follow the
    workshop air) give the same normalised curve against a channel, to the rounding of the record: curves within
    ``XCORR_SAME`` of each other at every lag share one line, its label naming every signal, instead of lines drawn
    on top of each other with a legend entry each.

    Parameters
    ----------
    curves : (channel, signal, lag [h], ρ [-]) per correlation
    """
    groups: list[list] = []  # [channel, [signals], lag_h, rho]
    for channel, signal, lag_h, rho in curves:
        for g in groups:
            if g[0] == channel and g[2].shape == lag_h.shape and np.allclose(g[3], rho, rtol=0.0, atol=XCORR_SAME):
                g[1].append(signal)
                break
        else:
            groups.append([channel, [signal], lag_h, rho])
    return [(textwrap.fill(f"{ch} vs {', '.join(sig)}" + (" (one curve: the same within 0.001)" if len(sig) > 1 else ""),
                           70), lag_h, rho) for ch, sig, lag_h, rho in groups]


def ep95_plot(path: Path, ep: dict, channels) -> Path:
    """Write :func:`ep95_figure` to ``path`` (PNG)."""
    import matplotlib.pyplot as plt

    fig = ep95_figure(ep, channels)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def ep95_figure(ep: dict, channels):
    """E_P95(range) of the validation residuals against the window length: temperatures left, drift right.

    Solid: the model as is, dashed: the extended one, on the axes of the demo's E_P95 plot
    (:func:`hybridcomp.plotaxes.window_axes`: log y, the window ticks as a person says them, 15 min, 1 h, 4 h, 15 h);
    a range of zero leaves a gap on the log axis.

    Parameters
    ----------
    ep : :func:`ep95_table`'s {channel: {window_s, before, after}}
    channels : the channels in the order drawn (``*_degC`` on the left, the drift on the right)
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hybridcomp.plotaxes import positive, window_axes

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    windows_h = [[], []]
    for c in channels:
        e = ep[c]
        k = 0 if c.endswith("_degC") else 1
        w = [float(x) / 3600.0 for x in e["window_s"]]
        windows_h[k] += w
        line, = axes[k].plot(w, positive(e["before"]), lw=1, label=c)
        axes[k].plot(w, positive(e["after"]), lw=1, ls="--", color=line.get_color())
    axes[0].set_title("E_P95(range), temperatures (solid: model, dashed: extended)", fontsize=9)
    axes[1].set_title("E_P95(range), drift (solid: model, dashed: extended)", fontsize=9)
    axes[0].set_ylabel("E_P95(range) of the residual [K]")
    axes[1].set_ylabel("E_P95(range) of the residual [µm]")
    for ax, w in zip(axes, windows_h):
        if ax.lines:
            window_axes(ax, w)
            ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def _plots(d: Diagnosis, out: Path, ep: dict, corr: list) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("matplotlib is not installed: no plots (pip install 'hybridcomp[plot]')")
        return []
    p = d.problem
    th = (p.time_s - p.time_s[0]) / 3600
    va = p.split.validation
    t_val = th[va][0]
    files = []
    n = len(p.channels)
    fig, axes = plt.subplots(n, 2, figsize=(12, 1.9 * n + 0.6), sharex=True, squeeze=False)
    for k, c in enumerate(p.channels):
        ax = axes[k, 0]
        ax.plot(th, p.Y[:, k], color="k", lw=0.8, label="measured")
        ax.plot(th, d.Y_before[:, k], color="tab:red", lw=0.8, label="model")
        ax.plot(th, d.Y_after[:, k], color="tab:blue", lw=0.8, ls="--", label="extended")
        ax.axvspan(t_val, th[-1], color="0.92", zorder=0)
        ax.set_ylabel(c, fontsize=8)
        ax = axes[k, 1]
        ax.plot(th, p.Y[:, k] - d.Y_before[:, k], color="tab:red", lw=0.8, label="residual, model")
        ax.plot(th, p.Y[:, k] - d.Y_after[:, k], color="tab:blue", lw=0.8, label="residual, extended")
        ax.axvspan(t_val, th[-1], color="0.92", zorder=0)
        ax.axhline(0, color="k", lw=0.5)
    axes[0, 0].legend(fontsize=7, loc="best")
    axes[0, 1].legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("time [h] (grey: validation)")
    axes[-1, 1].set_xlabel("time [h] (grey: validation)")
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=90)
    plt.close(fig)
    files.append("residuals.png")
    ep95_plot(out / "ep95.png", ep, p.channels)
    files.append("ep95.png")
    if corr:
        dt, max_lag = lag_grid(p.time_s[va])  # the lags strongest_correlations looked at
        curves = []
        for c in corr[:6]:
            k = p.channels.index(c.channel)
            lags, rho = cross_correlation(p.Y[va, k] - d.Y_before[va, k], p.signals[c.signal][va], max_lag)
            curves.append((c.channel, c.signal, lags * dt / 3600, rho))
        fig, ax = plt.subplots(figsize=(8, 4))
        for label, lag_h, rho in xcorr_curves(curves):
            ax.plot(lag_h, rho, lw=1, label=label)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("lag [h] (> 0: the residual follows the signal)")
        ax.set_ylabel("normalised cross-correlation")
        ax.set_title("residual of the model as is (validation part)", fontsize=9)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "xcorr.png", dpi=90)
        plt.close(fig)
        files.append("xcorr.png")
    return files


def write_report(d: Diagnosis, out_dir: str | Path, dataset_name: str = "", plots: bool = True, drives=None) -> dict:
    """Write ``report.md`` (with plots), ``summary.json`` and ``machine_extended.toml`` into ``out_dir``.

    ``drives``: the feed drives' diagnosis from probes at several poses
    (:class:`hybridcomp.diagnose.drives.DriveDiagnosis`), a section of its own; its named effects go into the
    extended machine file too.  Returns the summary dictionary.
    """
    from hybridcomp.diagnose.machine_file import write_extended_machine

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = d.problem
    ep = ep95_table(d)
    corr_before = before_correlations(d)
    summary = d.summary()
    for f, entry in zip(d.causes, summary["causes"]):
        if f.candidate.kind == "located_source" and "offset_mm" in f.candidate.info:  # placed continuously (opt-in)
            from hybridcomp.diagnose.locate import located_at, location_uncertainty_mm

            ref, at_pose = located_at(f.candidate, f.params)
            entry["place"] = {"body": f.candidate.info["body"], "position_mm": [float(v) for v in ref],
                              "position_at_pose_mm": [float(v) for v in at_pose],
                              "uncertainty_mm": location_uncertainty_mm(f.candidate, f.uncertainty),
                              "patch_mm": float(f.candidate.info["patch_mm"])}
            if "discretisation_shift_mm" in f.candidate.info:  # with the discretisation floor (opt-in)
                entry["place"]["discretisation_shift_mm"] = float(np.hypot(*f.candidate.info["discretisation_shift_mm"]))
    summary["machine"] = p.machine.name
    summary["dataset"] = dataset_name
    summary["model"] = {"order": int(p.rom.order), "nodes": p.rom.meta.get("nodes"),
                        "element_size_mm": p.rom.meta.get("element_size_mm")}
    summary["ep95_range"] = ep
    if p.floor is not None:
        summary["discretisation_floor"] = p.floor.as_dict(p.channels)
    summary["residual_correlations_before"] = [c.as_dict() for c in corr_before]
    if drives is not None:
        summary["drives"] = drives.as_dict()
    mpath, applied, missing = write_extended_machine(p.machine, d.causes, out / "machine_extended.toml",
                                                     drives.named if drives is not None else ())
    summary["machine_extended"] = {"file": mpath.name, "applied": applied,
                                   "not_expressible": [{"cause": a, "reason": b} for a, b in missing]}
    write_text_atomic(out / "summary.json", jsonio.dumps(summary, indent=2, default=float))
    files = _plots(d, out, ep, corr_before) if plots else []

    L = [f"# Diagnosis of {p.machine.name}" + (f" on {dataset_name}" if dataset_name else ""), ""]
    sp = summary["split"]
    L += [f"**Verdict: {d.verdict}.** {d.message}.", "",
          f"Training rows {sp['train_rows']} ({sp['train_h'][0]:.3g}–{sp['train_h'][1]:.3g} h), validation rows "
          f"{sp['validation_rows']} ({sp['validation_h'][0]:.3g}–{sp['validation_h'][1]:.3g} h); reduced model of order "
          f"{p.rom.order}; {d.timings_s.get('candidates', '?')} candidate effects; "
          f"{d.timings_s.get('total', d.timings_s.get('selection', 0)):.1f} s.", ""]
    L += ["## Causes", ""]
    if d.causes:
        L += ["| # | cause | parameters (± 1σ) | nominal | BIC drop (training) | validation gain |", "|---|---|---|---|---|---|"]
        for i, f in enumerate(d.causes, 1):
            c = f.candidate
            pars = "; ".join(f"{n} = {_fmt(v, 4)} ± {_fmt(u, 2)}" for n, v, u in zip(c.param_names, f.params, f.uncertainty))
            nom = "; ".join(_fmt(v, 4) for v in c.nominal)
            L.append(f"| {i} | {c.label} | {pars} | {nom} | {f.bic_drop:.1f} | {100 * f.validation_gain:.1f} % |")
        L += ["", "Validation gain: reduction of the noise-weighted residual energy on the validation rows when the "
              "effect was added."]
        for f in d.causes:
            w = f.candidate.info
            if f.candidate.kind == "located_source":
                if w.get("face") is not None:  # placed continuously on its face (opt-in)
                    from hybridcomp.diagnose.locate import located_at, location_uncertainty_mm

                    xyz = ", ".join(f"{v:.0f}" for v in located_at(f.candidate, f.params)[0])
                    unc = location_uncertainty_mm(f.candidate, f.uncertainty)
                    how = (f"its place fitted continuously on the face with its power (± {unc:.0f} mm, 1σ from the "
                           "fit's Jacobian, scaled by the residual")
                    if "discretisation_shift_mm" in w:
                        how += (f"; the model's discretisation error could move it by up to "
                                f"{np.hypot(*w['discretisation_shift_mm']):.0f} mm")
                    how += ")"
                else:
                    xyz = ", ".join(f"{v:.0f}" for v in w["location_mm"])
                    how = (f"sites within {w['location_spread_mm']:.0f} mm of it fit the training data as well within "
                           "the noise (the place is known to that extent)")
                L += ["", f"The missing source was searched over every body's surface (sites {w['patch_mm']:.0f} mm "
                      f"patches, on the training rows only): it sits on {w['body']} at ({xyz}) mm in machine-file "
                      f"coordinates; {how}."
                      + (f" Its drive cannot be told apart from {', '.join(w['same_as'])}'s in these data."
                         if w.get("same_as") else "")]
    else:
        L.append("No effect named.")
    if d.partial:
        L += ["", "Best combination of library effects found, **not confirmed** (a structured residual remains, so these "
              "names are not claimed as the cause):", "", "| candidate | parameters | validation gain |", "|---|---|---|"]
        for f in d.partial:
            c = f.candidate
            pars = "; ".join(f"{n} = {_fmt(v, 4)}" for n, v in zip(c.param_names, f.params))
            L.append(f"| {c.label} | {pars} | {100 * f.validation_gain:.1f} % |")
        worse = [c for c in p.channels if d.after[c]["fit_percent"] < d.before[c]["fit_percent"]]
        if worse:
            L += ["", f"Together they make the validation fit worse on {', '.join(worse)} (table below): no improvement "
                  "there."]
    if drives is not None:
        from hybridcomp.diagnose.drives import drive_section

        L += [""] + drive_section(drives)
    L += ["", "## Before and after (validation part)", "",
          "| channel | noise σ | RMS before | RMS after | P2P before | P2P after | fit % before | fit % after |",
          "|---|---|---|---|---|---|---|---|"]
    for k, c in enumerate(p.channels):
        b, a = d.before[c], d.after[c]
        L.append(f"| {c} | {_fmt(p.sigma[k], 2)} | {_fmt(b['rms'])} | {_fmt(a['rms'])} | {_fmt(b['p2p'])} | {_fmt(a['p2p'])} | "
                 f"{b['fit_percent']:.1f} | {a['fit_percent']:.1f} |")
    L += ["", "Units: °C channels in K, µm channels in µm. fit % = 100 (1 − ‖y − ŷ‖/‖y − ȳ‖).", ""]
    if p.floor is not None:
        fl = p.floor
        L += [f"The model's own discretisation error ({fl.describe()}: the meshes' difference on these inputs, "
              "extrapolated to the model's error; the largest RMS over the validation rows) is a floor: a residual within "
              "it counts as explained, and an effect that changes the channels no more than the same effect fitted to "
              "the discretisation error alone is not named.", "", "| channel | discretisation floor |", "|---|---|"]
        L += [f"| {c} | {_fmt(float(v), 2)} |" for c, v in zip(p.channels, fl.rms)] + [""]
    L += ["## E_P95(range)", "", "95th percentile of the residual's range over sliding windows (validation part), "
          "model as is → extended:", ""]
    hdr = [f"{w * 60:.0f} min" if w < 1 else f"{w:g} h" for w in EP95_WINDOWS_H]
    L += ["| channel | " + " | ".join(hdr) + " |", "|---|" + "---|" * len(hdr)]
    for c, e in ep.items():
        w = np.array(e["window_s"]) / 3600
        cells = []
        for wh in EP95_WINDOWS_H:
            if wh > w[-1] * 1.0001:
                cells.append("–")
                continue
            i = int(np.argmin(np.abs(np.log(w / wh))))
            cells.append(f"{_fmt(e['before'][i], 2)} → {_fmt(e['after'][i], 2)}")
        L.append(f"| {c} | " + " | ".join(cells) + " |")
    L += ["", "## What the simulation gets wrong: residual correlations", "",
          "Strongest normalised cross-correlations of the model-as-is residual (validation part) with the available "
          "signals; lag > 0: the residual follows the signal.", "", "| channel | signal | lag [h] | ρ |", "|---|---|---|---|"]
    for c in corr_before:
        L.append(f"| {c.channel} | {c.signal} | {c.lag_s / 3600:.2f} | {c.r:.3f} |")
    if d.correlations:
        L += ["", "### Unexplained remainder", "", "Strongest correlations of the residual left after the named effects:", "",
              "| channel | signal | lag [h] | ρ |", "|---|---|---|---|"]
        for c in d.correlations:
            L.append(f"| {c.channel} | {c.signal} | {c.lag_s / 3600:.2f} | {c.r:.3f} |")
    if d.rounds:
        L += ["", "## Model selection", ""]
        for i, r in enumerate(d.rounds, 1):
            L += [f"Round {i}: {'accepted ' + r.accepted if r.accepted else 'no candidate passed both tests'}", "",
                  "| candidate | BIC drop | validation gain |", "|---|---|---|"]
            for s in r.scores[:8]:
                L.append(f"| {s['label']} | {s['bic_drop']:.1f} | {100 * s['validation_gain']:.1f} % |")
            L.append("")
    L += ["## Extended machine file", "", f"`{mpath.name}` loads with `hybridcomp.models.load_machine` and runs with "
          "`hybridcomp simulate` and `hybridcomp reduce` as it is."]
    L += [f"* {a}" for a in applied] or ["* no change (no cause the machine file can express)"]
    if missing:
        L += ["", "Causes the machine file cannot express:", ""] + [f"* {a}: {b}" for a, b in missing]
    if files:
        L += ["", "## Plots", ""] + [f"![{f}]({f})" for f in files]
    write_text_atomic(out / "report.md", "\n".join(L) + "\n")
    return summary
