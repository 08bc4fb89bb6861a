"""Benchmark: the CAIVIAC spindle test, train the first half: the data-only models held out, without and with probes.

    python benchmarks/caiviac_updating.py [--data PATH] [--train 0:50%] [--search]

Prints one table of fit % per channel on the validation half and a final JSON line:

* the static regression of all 16 temperatures (the published reference);
* the **regularised families** (``diagnose/regularised.py``: ridge over the temperatures, their first-order lags and
  the spindle's transfer functions; family and λ chosen on the training half by a repeated blocked cross-validation
  with the one-standard-error rule), chosen with 3, 5 and 10 folds each alone, and the smallest / largest held-out
  fit over fold counts 3, 5, 10 × seeds 0, 1, 2 with its spread; then the default choice, on the cross-validation
  curves of 3, 5 and 10 folds averaged (``choose_pooled``: it no longer depends on the fold count), and its smallest
  / largest over seeds 0, 1, 2 (goal: ≥ 70 % on every channel, spread ≤ 10 points);
* partial least squares (PLS1 per channel, ``regularised.pls_choice_fits``) over the same families, the number of
  components (1–20) chosen as λ is (the pooled curves, the one-standard-error rule, fewest components), with its
  smallest fit and spread over seeds 0, 1, 2: the other regularisation the issue names, measured beside the ridge;
* the regularised model with a probe every 2 h and every 1 h: gain and offset updated (``updated_prediction``) and
  its coefficients updated (``coefficient_updating``), each filter's settings chosen on the training half; scored on
  the validation rows without the probe rows (goals: ≥ 85 % every 2 h, ≥ 90 % every 1 h); the pooled choice
  (``--alone``: that of 3 folds alone); beside them the gain/offset filter's reach: the best fit of 60 settings
  (gain walk 0–1/√h, offset walk 0.1–10 µm/√h, offset prior 1 or 10 µm) chosen on the validation rows themselves
  (NOT held out): when even that stays below a goal, the model, not the filter's settings, is what misses it; and
  the model with the one offset per interval between probes that fits that interval best, known in hindsight (NOT
  held out): the most any correction by an offset held from one probe to the next can give;
* with ``--search`` also the beam search's held-out fit (the default model of ``diagnose --data-only``) for 3, 5
  and 10 folds (about 2 minutes each);
* the chosen family fitted on EVERY row, the validation half too (NOT held out): what the data allow the family.

Reads the data set that ``hybridcomp data fetch caiviac-spindle --out data/`` writes (``--data`` to read another copy,
e.g. the shared data folder's ``caiviac-spindle/measured.csv``); exits with status 2 and says how to fetch it when the
file is missing.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _caiviac import add_arguments, missing

from hybridcomp.diagnose import regularised as reg
from hybridcomp.diagnose.data import parse_split, read_dataset
from hybridcomp.diagnose.dataonly import diagnose_data_only, regularised_families
from hybridcomp.diagnose.metrics import fit_percent
from hybridcomp.diagnose.regularised import cv_blocks, fit_ridge
from hybridcomp.diagnose.updating import UpdateSettings, choose_settings, probe_rows, updated_prediction

from _table import table

FOLDS = (3, 5, 10)
EVERY_H = (2.0, 1.0)


def _gain_offset(d, ds, c: str, every_h: float, probe_sd_um: float) -> float:
    """The regularised model with gain and offset updated (settings chosen on the training blocks), fit % on the
    validation rows without the probes."""
    r = d.regularised[c]
    t, tr = d.time_s, d.split.train
    fam = next(f for f in regularised_families(ds, d)[3] if f.name == r["family"])
    y = d.Y[c]
    blocks = []
    for rows in cv_blocks(tr, d.folds):
        fit_rows = tr.copy()
        fit_rows[rows] = False
        blocks.append((rows, fit_ridge(fam, y, fit_rows, r["lam"]).predict(fam.X[rows])))
    settings, _ = choose_settings(t, y, blocks, every_h, probe_sd_um)
    tv, yv, y_hat, probes, keep = _validation_probes(d, c, every_h)
    u, _ = updated_prediction(y_hat, yv, tv, probes, settings)
    return fit_percent(yv[keep], u[keep])


def _validation_probes(d, c: str, every_h: float):
    """Channel ``c`` on the validation rows: times [s], drift and the regularised model's prediction [µm], the probe
    rows (indices into them) of a probe every ``every_h`` hours, and the rows scored (all but the probes)."""
    rows = np.flatnonzero(d.split.validation)
    t = d.time_s[rows]
    probes = probe_rows(t, np.ones(rows.size, bool), every_h)
    keep = np.ones(rows.size, bool)
    keep[probes] = False
    return t, d.Y[c][rows], d.regularised[c]["y_hat"][rows], probes, keep


# the filter's reach: its spreads tried on the validation rows themselves (NOT held out)
REACH_GAIN_WALKS = (0.0, 0.01, 0.03, 0.1, 0.3, 1.0)  # [1/√h]
REACH_OFFSET_WALKS = (0.1, 0.3, 1.0, 3.0, 10.0)  # [µm/√h]
REACH_OFFSET_PRIORS = (1.0, 10.0)  # the offset's prior spread [µm]
REACH_SETTINGS = len(REACH_GAIN_WALKS) * len(REACH_OFFSET_WALKS) * len(REACH_OFFSET_PRIORS)


def _gain_offset_reach(d, c: str, every_h: float, probe_sd_um: float) -> float:
    """The best fit % a gain/offset filter of the grid above reaches on the validation rows (probes not scored), its
    spreads chosen on those very rows: NOT held out; near the held-out figure, the filter's tuning is not what
    limits the updating, the model is."""
    t, y, y_hat, probes, keep = _validation_probes(d, c, every_h)
    best = -np.inf
    for gw, ow, o0 in itertools.product(REACH_GAIN_WALKS, REACH_OFFSET_WALKS, REACH_OFFSET_PRIORS):
        u, _ = updated_prediction(y_hat, y, t, probes, UpdateSettings(every_h, probe_sd_um, o0, gw, ow))
        best = max(best, fit_percent(y[keep], u[keep]))
    return best


def _offset_oracle(d, c: str, every_h: float) -> float:
    """Fit % on the validation rows (probes not scored) when each interval between probes gets the one offset that
    fits it best, known in hindsight (NOT held out): no scheme that corrects the model by an offset held from one
    probe to the next can do better."""
    _, y, y_hat, probes, keep = _validation_probes(d, c, every_h)
    interval = np.searchsorted(probes, np.arange(y.size), side="right")
    u = y_hat.copy()
    for k in np.unique(interval):
        m = interval == k
        if (m & keep).any():
            u[m] += np.mean((y - y_hat)[m & keep])
    return fit_percent(y[keep], u[keep])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    p.add_argument("--probe-sd-um", type=float, default=0.5, help="the probes' repeatability (default 0.5 µm)")
    p.add_argument("--alone", action="store_true", help="the probe rows with the choice of 3 folds alone (not the "
                   "curves of 3/5/10 folds pooled)")
    p.add_argument("--search", action="store_true", help="also the beam search's held-out fit for 3, 5 and 10 folds "
                   "(about 2 minutes each on 2 cores)")
    a = p.parse_args(argv)
    if missing(a.data):
        return 2
    t0 = time.perf_counter()
    ds = read_dataset(a.data)
    split = parse_split(a.train, ds.time_s)
    va = split.validation
    rows, record = [], {}

    def add(name: str, fits: dict, note: str = ""):
        record[name] = {c: round(float(v), 1) for c, v in fits.items()}
        rows.append({"model": name, **{c: f"{v:.1f}" for c, v in fits.items()}, "min": f"{min(fits.values()):.1f}",
                     "note": note})

    timings = {}
    base = {}
    for k in FOLDS:
        tk = time.perf_counter()
        beam, steps = (16, 16) if a.search else (1, 0)
        d = diagnose_data_only(ds, split, folds=k, beam_width=beam, max_terms=steps, spread=(k == FOLDS[0]),
                               pool_folds=False)
        timings[f"{k} folds"] = round(time.perf_counter() - tk, 1)
        base[k] = d
        chans = list(d.extended)
        if k == FOLDS[0]:
            add("static regression, all 16 temperatures", {c: d.reference[c]["fit_percent"] for c in chans})
        if a.search:
            add(f"beam search, {k} folds (default model)",
                {c: fit_percent(d.Y[c][va], d.extended[c].y_hat[va]) for c in chans})
        add(f"regularised, {k} folds alone", {c: d.regularised[c]["held_out"]["fit_percent"] for c in chans},
            "; ".join(f"{d.regularised[c]['family']} λ={d.regularised[c]['lam']:.3g}" for c in chans))
    d3 = base[FOLDS[0]]
    chans = list(d3.extended)
    sp = {c: d3.regularised[c]["spread"] for c in chans}
    add("each alone: smallest over folds 3/5/10 × seeds 0/1/2", {c: sp[c]["min"] for c in chans})
    add("each alone: largest over folds 3/5/10 × seeds 0/1/2", {c: sp[c]["max"] for c in chans})
    add("each alone: spread (points)", {c: sp[c]["spread"] for c in chans}, "goal ≤ 10")
    tk = time.perf_counter()
    dp = diagnose_data_only(ds, split, folds=FOLDS[0], beam_width=1, max_terms=0, spread=True, pool_folds=True)
    timings["pooled"] = round(time.perf_counter() - tk, 1)
    add("regularised, curves of 3/5/10 folds pooled (default)",
        {c: dp.regularised[c]["held_out"]["fit_percent"] for c in chans},
        "; ".join(f"{dp.regularised[c]['family']} λ={dp.regularised[c]['lam']:.3g}" for c in chans))
    spp = {c: dp.regularised[c]["spread"] for c in chans}
    add("pooled: smallest over seeds 0/1/2", {c: spp[c]["min"] for c in chans})
    add("pooled: largest over seeds 0/1/2", {c: spp[c]["max"] for c in chans})
    add("pooled: spread (points)", {c: spp[c]["spread"] for c in chans}, "goal ≤ 10 (fold count no longer matters)")
    tk = time.perf_counter()
    fams, Y = regularised_families(ds, dp)[3], np.column_stack([dp.Y[c] for c in chans])
    pls = {s: reg.pls_choice_fits(fams, Y, dp.split.train, va, seed=s) for s in reg.SPREAD_SEEDS}
    timings["PLS"] = round(time.perf_counter() - tk, 1)
    made0, fits0 = pls[reg.SPREAD_SEEDS[0]]
    add("PLS over the same families, chosen as the pooled ridge (fewest components)", dict(zip(chans, fits0)),
        "; ".join(f"{fams[m.family].name} {m.lam_index + 1} comp." for m in made0))
    F = np.array([f for _, f in pls.values()])
    add("PLS: smallest / spread over seeds 0/1/2", {c: F[:, j].min() for j, c in enumerate(chans)},
        "spread " + " / ".join(f"{v:.1f}" for v in np.ptp(F, axis=0)))
    for h in EVERY_H:
        tk = time.perf_counter()
        d = diagnose_data_only(ds, split, folds=FOLDS[0], beam_width=1, max_terms=0, spread=False, probe_every_h=h,
                               probe_sd_um=a.probe_sd_um, pool_folds=not a.alone)
        timings[f"probes every {h:g} h"] = round(time.perf_counter() - tk, 1)
        add(f"regularised, probe every {h:g} h: gain and offset updated",
            {c: _gain_offset(d, ds, c, h, a.probe_sd_um) for c in chans})
        add(f"regularised, probe every {h:g} h: gain and offset, the best of {REACH_SETTINGS} settings chosen on the "
            "validation rows (NOT held out)",
            {c: _gain_offset_reach(d, c, h, a.probe_sd_um) for c in chans}, "the updating's reach with this model")
        add(f"regularised, probe every {h:g} h: the best offset per interval, in hindsight (NOT held out)",
            {c: _offset_oracle(d, c, h) for c in chans}, "no offset held between probes does better")
        cu = d.coefficient_updating
        add(f"regularised, probe every {h:g} h: coefficients updated",
            {c: fit_percent(d.Y[c][va][cu[c]["scored"]], cu[c]["y_hat"][cu[c]["scored"]]) for c in chans},
            f"{cu[chans[0]]['probe_rows'].size} probes; goal ≥ {85 if h >= 2 else 90} %")
    add("chosen family fitted on every row (NOT held out)",
        {c: dp.regularised[c]["every_row"]["fit_percent"] for c in chans})
    add("best family fitted on every row (NOT held out)",
        {c: dp.regularised[c]["every_row_best"]["fit_percent"] for c in chans})
    print(f"{a.data.name}: train {a.train}, fit % per channel on the validation half (held out unless marked; "
          "probe rows never scored)")
    print(table(rows, ["model", *chans, "min", "note"]))
    no_probe_min = min(spp[c]["min"] for c in chans)
    spread_max = max(spp[c]["spread"] for c in chans)
    upd = {h: min(record[f"regularised, probe every {h:g} h: coefficients updated"].values()) for h in EVERY_H}
    print(json.dumps({"benchmark": "caiviac_updating", "train": a.train, "fit_percent": record,
                      "goals": {"no_probes_min_70": bool(no_probe_min >= 70.0), "spread_max_10": bool(spread_max <= 10.0),
                                "every_2h_min_85": bool(upd[2.0] >= 85.0), "every_1h_min_90": bool(upd[1.0] >= 90.0)},
                      "no_probes_min_fit_percent": round(no_probe_min, 1), "spread_max_points": round(spread_max, 1),
                      "spread_max_points_each_fold_count_alone": round(max(sp[c]["spread"] for c in chans), 1),
                      "timings_s": timings, "wall_s": round(time.perf_counter() - t0, 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
