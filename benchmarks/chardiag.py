"""Benchmark: characteristic diagrams — speed targets and accuracy on the demonstrator.

Speed (medians of ``--repeats`` runs):

* single-point evaluation (the compensation loop's path) of a 4-input full-grid CD and of the
  demonstrator's additive CD (target ≤ 20 µs);
* 100,000 points vectorised (target ≤ 50 ms);
* fit of 20,000 samples with 4 active inputs (target ≤ 2 s).

Accuracy (FE at ``--element-size-mm``, one run): CDs trained on the basic load cases (each axis
alone at max feed, the spindle alone, ``--heat-hours`` h then ``--cool-hours`` h cooling) predict the unseen
simultaneous-motion case (target: RMS residual ≤ 15 % of the uncompensated RMS drift); CDs trained on
the job-shop day's own BCs (target ≤ 5 %). Ratios per direction and for the 3D drift vector.

    python benchmarks/chardiag.py [--repeats 5] [--element-size-mm 80] [--no-accuracy]

Prints tables and a final JSON line.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

from hybridcomp.models import jsonio

from _table import table  # benchmarks/_table.py, beside this script


def synthetic(n: int, d: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    T = rng.uniform(20, 30, (n, d))
    y = T @ np.linspace(1, 2, d) + 0.1 * (T[:, 0] - 25) * (T[:, 1] - 25) + rng.normal(0, 0.05, n)
    tab = {f"T{i + 1}_degC": T[:, i] for i in range(d)}
    tab["dz_um"] = y
    return tab


def point_times_us(cd, Q: np.ndarray, repeats: int) -> list[float]:
    """Mean time of one ``evaluate_point`` over the rows of Q, per repeat [µs]."""
    pts = [dict(zip(cd.input_names, q)) for q in Q]
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for p in pts:
            cd.evaluate_point(p)
        out.append((time.perf_counter() - t0) / len(pts) * 1e6)
    return out


def speed(repeats: int) -> dict:
    from hybridcomp.chardiag.fit import FitOptions, fit_cd

    opts = FitOptions(n_support=6, max_full_dims=4)
    tab = synthetic(20000, 4)
    fit_s = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cd = fit_cd(tab, "Z", machine="bench", options=opts)
        fit_s.append(time.perf_counter() - t0)
    assert len(cd.active_inputs) == 4 and len(cd.terms) == 1
    rng = np.random.default_rng(1)
    Q = rng.uniform(20, 30, (100000, 4))
    vec_s = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cd.evaluate(Q)
        vec_s.append(time.perf_counter() - t0)
    point_us = point_times_us(cd, Q[:2000], repeats)
    # an additive CD of 8 temperatures (the demonstrator's shape)
    cd8 = fit_cd(synthetic(20000, 8), "Z", machine="bench", options=FitOptions(n_support=6))
    point8_us = point_times_us(cd8, rng.uniform(20, 30, (2000, 8)), repeats)
    return {
        "fit_20000x4_s": statistics.median(fit_s),
        "eval_100000_ms": 1e3 * statistics.median(vec_s),
        "point_4d_full_us": statistics.median(point_us),
        "point_8d_additive_us": statistics.median(point8_us),
        "memory_4d_full_bytes": cd.memory_bytes,
        "memory_8d_additive_bytes": cd8.memory_bytes,
    }


def accuracy(element_size_mm: float, heat_h: float, cool_h: float) -> tuple[dict, list[dict]]:
    from hybridcomp.chardiag.fit import fit_cd_set
    from hybridcomp.chardiag.training import simulate_load_cases, standard_load_cases
    from hybridcomp.fem.model import build_model
    from hybridcomp.models import load_machine

    machine = load_machine("vmc800")
    t0 = time.perf_counter()
    cases = standard_load_cases(machine, ["basic", "simultaneous", "jobshop"], heat_h=heat_h, cool_h=cool_h)
    model = build_model(machine, {}, element_size_mm)
    data = simulate_load_cases(machine, cases, model=model, dt_s=60.0, theta=0.5, progress=False)
    t_fe = time.perf_counter() - t0
    basic = data.subset([c for c in data.cases if c.startswith("basic")])
    sim, js = data.subset(["simultaneous"]), data.subset(["jobshop"])
    rows = []
    out = {"nodes": model.n, "fe_training_s": t_fe}
    for label, train, test in (("basic → simultaneous", basic, sim), ("job-shop → job-shop", js, js)):
        cds = fit_cd_set(train.columns, machine=machine.name, signature=train.signature())
        R, Y = [], []
        for d, cd in cds.items():
            pred, outside = cd.evaluate_table(test.columns)
            y = test.columns[cd.target]
            R.append(y - pred)
            Y.append(y)
            rows.append({"case": label, "direction": d, "active inputs": len(cd.active_inputs),
                         "rms drift µm": f"{np.sqrt(np.mean(y**2)):.3f}",
                         "rms residual µm": f"{np.sqrt(np.mean((y - pred) ** 2)):.3f}",
                         "ratio %": f"{100 * np.sqrt(np.mean((y - pred) ** 2)) / np.sqrt(np.mean(y**2)):.1f}",
                         "outside %": f"{100 * outside.mean():.0f}"})
        ratio = float(np.sqrt(np.mean(np.square(R))) / np.sqrt(np.mean(np.square(Y))))
        rows.append({"case": label, "direction": "3D", "active inputs": "", "rms drift µm":
                     f"{np.sqrt(np.mean(np.square(Y))):.3f}", "rms residual µm": f"{np.sqrt(np.mean(np.square(R))):.3f}",
                     "ratio %": f"{100 * ratio:.1f}", "outside %": ""})
        out["simultaneous_ratio" if label.startswith("basic") else "jobshop_ratio"] = ratio
    return out, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--element-size-mm", type=float, default=80.0)
    ap.add_argument("--heat-hours", type=float, default=8.0)
    ap.add_argument("--cool-hours", type=float, default=8.0)
    ap.add_argument("--no-accuracy", action="store_true", help="speed only (no FE runs)")
    args = ap.parse_args()
    sp = speed(args.repeats)
    print(table([
        {"measure": "single point, 4-input full grid", "value": f"{sp['point_4d_full_us']:.1f} µs", "target": "≤ 20 µs"},
        {"measure": "single point, 8-input additive", "value": f"{sp['point_8d_additive_us']:.1f} µs", "target": "≤ 20 µs"},
        {"measure": "100,000 points (4-input full grid)", "value": f"{sp['eval_100000_ms']:.1f} ms", "target": "≤ 50 ms"},
        {"measure": "fit 20,000 samples, 4 inputs × 6 points", "value": f"{sp['fit_20000x4_s']:.3f} s", "target": "≤ 2 s"},
        {"measure": "memory per CD (4-input full / 8-input additive)",
         "value": f"{sp['memory_4d_full_bytes']} / {sp['memory_8d_additive_bytes']} bytes", "target": ""},
    ], ["measure", "value", "target"]))
    result = {"machine": platform.node(), "cpus": os.cpu_count(), "repeats": args.repeats, **sp}
    if not args.no_accuracy:
        acc, rows = accuracy(args.element_size_mm, args.heat_hours, args.cool_hours)
        print()
        print(f"accuracy on vmc800 at {args.element_size_mm:g} mm ({acc['nodes']} nodes), "
              f"FE training data in {acc['fe_training_s']:.1f} s")
        print(table(rows, ["case", "direction", "active inputs", "rms drift µm", "rms residual µm", "ratio %",
                           "outside %"]))
        result.update(acc)
    print(jsonio.dumps(result))


if __name__ == "__main__":
    main()
