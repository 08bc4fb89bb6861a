"""A campaign of test runs: why the data-only diagnosis must treat runs as units.

Six test days are made with the FE model of the demonstrator. Each day starts from a cold machine at that
day's workshop air (17–24 °C), runs the example programme from another hour and at another intensity, and
the dial gauges are zeroed at an arbitrary reading. The same regression search is run twice, trained on
days 1–4 and scored on days 5 and 6, which no choice saw:

* as one long series (the days one after the other: lags run across the nights, the different air
  levels and gauge zeros look like thermal error);
* as a campaign (``runs``): each day from its own first row, no lag crossing a day boundary, the
  training days held out in turn by the cross-validation.

Both are scored the way a compensation is used: the change of each channel since the day's first row.

    python examples/campaign.py --out campaign/
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

import hybridcomp as hc
from hybridcomp.diagnose.data import Dataset, Split, parse_split, read_campaign
from hybridcomp.diagnose.dataonly import diagnose_data_only
from hybridcomp.fem.model import build_model

CHANNELS = ("dx_um", "dy_um", "dz_um")


def make_runs(out_dir: Path, element_size_mm: float = 150.0, runs: int = 6, hours: float = 10.0,
              dt_s: float = 120.0, seed: int = 3) -> list[Path]:
    """One CSV per test day (``run1.csv`` ...): time from 0, spindle speed, the eight sensors, zeroed gauges."""
    machine = hc.load_machine("vmc800")
    model = build_model(machine, None, element_size_mm)
    base = hc.example_loads(machine, duration_h=hours, dt_s=dt_s)
    names = list(base.names)
    heat = [j for j, n in enumerate(names) if n.endswith("_W")]
    air = [j for j, n in enumerate(names) if n.endswith("_degC")]
    spindle = names.index("spindle_motor_W")
    rng = np.random.default_rng(seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(runs):
        air_degC = rng.uniform(17.0, 24.0)  # that day's workshop air
        work = rng.uniform(0.6, 1.4)  # that day's intensity
        shift = int(rng.integers(0, base.time_s.size))  # the programme from another hour
        V = base.values.copy()
        V[:, heat] = np.roll(base.values[:, heat], shift, axis=0) * work
        V[:3, heat] = 0.0  # a cold machine: nothing runs before the first samples
        V[:, air] = air_degC + (base.values[:, air] - base.values[0, air])  # the day's air, with the example's swing
        res = model.simulate(hc.Loads(base.time_s, V, tuple(names)), initial="steady", scheme="theta", theta=0.5)
        zero = rng.normal(0.0, 20.0, 3)  # the gauges' reading when they were zeroed
        drift = res.drift_um - res.drift_um[0] + zero + rng.normal(0.0, 0.3, res.drift_um.shape)
        sensors = res.sensors_degC + rng.normal(0.0, 0.02, res.sensors_degC.shape)
        cols = {"time_s": base.time_s - base.time_s[0],
                "spindle_rpm": V[:, spindle] / max(V[:, spindle].max(), 1e-9) * machine.spindle_max_speed_rpm,
                **{f"{s.name}_degC": sensors[:, j] for j, s in enumerate(machine.sensors)},
                **dict(zip(CHANNELS, drift.T))}
        path = out_dir / f"run{k + 1}.csv"
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(cols)
            w.writerows(zip(*(np.char.mod("%.6g", v) for v in cols.values())))
        paths.append(path)
    return paths


def zeroed_fit(y: np.ndarray, y_hat: np.ndarray, rows: np.ndarray, runs: np.ndarray) -> float:
    """Fit % of the change since each run's first row, over ``rows`` [%]."""
    e, d = [], []
    for r in np.unique(runs[rows]):
        ix = np.flatnonzero(rows & (runs == r))
        dy = y[ix] - y[ix[0]]
        e.append(dy - (y_hat[ix] - y_hat[ix[0]]))
        d.append(dy)
    e, d = np.concatenate(e), np.concatenate(d)
    return float(100.0 * (1.0 - np.linalg.norm(e) / np.linalg.norm(d - d.mean())))


def compare(paths: list[Path], train: str = "runs:1-4") -> dict:
    """Held-out fits of the campaign diagnosis and of the one-series diagnosis on the same rows."""
    camp = read_campaign(paths)
    split = parse_split(train, camp.time_s, camp.runs)
    aware = diagnose_data_only(camp, split)
    one = diagnose_data_only(Dataset(camp.time_s, camp.columns, "one series"), Split(split.train, split.validation,
                                                                                     "the same rows"))
    out = {}
    for c in CHANNELS:
        out[c] = {"one_series": zeroed_fit(camp[c], one.extended[c].y_hat, split.validation, camp.runs),
                  "campaign": zeroed_fit(camp[c], aware.extended[c].y_hat, split.validation, camp.runs),
                  "extensions": [e["term"] for e in aware.extensions[c]]}
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("campaign"), help="folder for the run CSVs")
    p.add_argument("--element-size-mm", type=float, default=150.0, help="FE element size [mm] (default 150)")
    args = p.parse_args(argv)
    paths = make_runs(args.out, args.element_size_mm)
    res = compare(paths)
    print("held-out fit % on days 5 and 6 (change since each day's first row):")
    print(f"{'channel':8} {'one series':>11} {'campaign':>9}")
    for c, v in res.items():
        print(f"{c:8} {v['one_series']:11.1f} {v['campaign']:9.1f}")
    print(f"(hybridcomp diagnose --data-only --data {' '.join(str(q) for q in paths)} --train runs:1-4 --out DIR)")
    return res


if __name__ == "__main__":
    main()
