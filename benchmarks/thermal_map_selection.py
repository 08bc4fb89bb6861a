"""Benchmark: how the thermal volumetric model chooses its inputs, against the alternatives, on planted problems.

    python benchmarks/thermal_map_selection.py [--seeds 40] [--states 10] [--noise-um 0.5]

Each seed draws the planted problem of ``tests/test_thermal_map.py`` (a cubic kinematic model of the demonstrator
whose coefficients are c0 + G ΔT with G nonzero for 2 of 8 sensors, the other six following the same two heat
sources; calibrations on a 5 × 5 × 5 plan with ``--noise-um`` of noise at ``--states`` training states, 5 held-out
states) and fits it in several ways:

* ``shared/exhaustive/bicc``: :func:`~hybridcomp.chardiag.thermal_map.fit_thermal_map` as it is;
* ``shared/greedy/bicc``: the same with the greedy forward search;
* ``per-component/...``: one BICc selection per drift component instead of one shared set;
* ``shared/exhaustive/bic``: the uncorrected criterion;
* ``per-coefficient``: every state identified, one BICc selection per kinematic coefficient;
* ``OLS all 8`` / ``oracle``: least squares of the per-state coefficients on every sensor / on the planted two;
* ``max_inputs=1`` / ``max_inputs=0``: one input where two are needed / none.

Scores: the held-out states' TCP error rms over a 3 × 3 × 3 grid against the truth (median and max over the seeds)
and in how many seeds the selected sensors are not exactly the planted ones. No choice is made on the held-out
states. Prints the table and a final JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_thermal_map import NAMES, PLANTED, _grid, _planted

from hybridcomp.chardiag import thermal_map as tm
from hybridcomp.chardiag.kinematic import ErrorModel, chain_of, identify, tcp_error_um
from hybridcomp.models import load_machine

from _table import table


def _per_component(chain, cals, limit):
    """One BICc selection per drift component (the alternative to one shared set)."""
    d = tm._drift(chain, cals, 3)
    gains_w, used = np.zeros((d.directions.shape[1], len(NAMES))), set()
    for k in range(d.scores.shape[1]):
        sub, g = tm._select(d.dT, d.scores[:, k], range(len(NAMES)), "bicc", 3, limit=limit)
        gains_w += np.outer(d.directions[k], g[:, 0])
        used |= set(sub)
    coef0, gains = tm._coefficients(chain, 3, d, gains_w)
    return lambda T: ErrorModel(chain, 3, coef0 + gains @ (T - d.reference_degC)), used


def _per_coefficient(chain, cals, cols=None):
    """Every state identified; per coefficient a BICc selection (``cols`` None) or least squares on ``cols``."""
    C = np.array([identify(chain, c.poses_mm, c.error_um, 3).coef.ravel() for c in cals])
    T = np.array([c.sensors_degC for c in cals])
    ref = T.mean(axis=0)
    dT, c0 = T - ref, C.mean(axis=0)
    G, used = np.zeros((C.shape[1], len(NAMES))), set()
    if cols is None:
        for j in range(C.shape[1]):
            sub, g = tm._select(dT, C[:, j] - c0[j], range(len(NAMES)), "bicc", 3)
            G[j], used = g[:, 0], used | set(sub)
    else:
        G[:, cols] = np.linalg.lstsq(dT[:, cols], C - c0, rcond=None)[0].T
        used = set(cols)
    return lambda Tn: ErrorModel(chain, 3, (c0 + G @ (Tn - ref)).reshape(3, 6, 4)), used


def _fitted(chain, cals, **kw):
    m = tm.fit_thermal_map(chain, cals, NAMES, **kw)
    return m.model_at, set(m.selected)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--states", type=int, default=10)
    ap.add_argument("--noise-um", type=float, default=0.5)
    args = ap.parse_args(argv)
    chain = chain_of(load_machine("vmc800"))
    ev = _grid(chain, 3)
    planted = set(PLANTED)
    res: dict[str, list] = {}
    for seed in range(args.seeds):
        cals, T_test, truth = _planted(chain, seed, n_train=args.states, noise=args.noise_um)
        out = {"shared/exhaustive/bicc": _fitted(chain, cals)}
        limit, tm.EXHAUSTIVE_LIMIT = tm.EXHAUSTIVE_LIMIT, 0
        try:
            out["shared/greedy/bicc"] = _fitted(chain, cals)
        finally:
            tm.EXHAUSTIVE_LIMIT = limit
        out["per-component/exhaustive/bicc"] = _per_component(chain, cals, 10**6)
        out["per-component/greedy/bicc"] = _per_component(chain, cals, 0)
        out["shared/exhaustive/bic"] = _fitted(chain, cals, criterion="bic")
        out["per-coefficient/exhaustive/bicc"] = _per_coefficient(chain, cals)
        out["OLS all 8"] = _per_coefficient(chain, cals, list(range(8)))
        out["oracle (OLS planted 2)"] = _per_coefficient(chain, cals, list(PLANTED))
        out["max_inputs=1"] = _fitted(chain, cals, max_inputs=1)
        out["max_inputs=0"] = _fitted(chain, cals, max_inputs=0)
        for name, (model_at, used) in out.items():
            err = [tcp_error_um(model_at(T), ev) - tcp_error_um(truth(T), ev) for T in T_test]
            res.setdefault(name, []).append((float(np.sqrt(np.mean(np.square(err)))), used != planted))
    rows = []
    for name, v in res.items():
        h = np.array([x[0] for x in v])
        wrong = sum(x[1] for x in v)
        rows.append({"variant": name, "held-out median [um]": f"{np.median(h):.3f}",
                     "held-out max [um]": f"{h.max():.3f}", "wrong input set": f"{wrong}/{len(v)}"})
    print(table(rows, list(rows[0])))
    print(json.dumps({"seeds": args.seeds, "states": args.states, "noise_um": args.noise_um, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
