r"""Benchmark: ``hybridcomp reduce --matrices`` on systems it was not tuned on, in two time units, against pyMOR.

Systems, built here from their published definitions (no download):

* ``penzl``: Penzl's FOM (1,006 states, SISO, non-symmetric, E = I; as pyMOR's ``penzl_example``);
* ``penzl_mimo``: its MIMO variant (2,000 states, 2 inputs × 3 outputs; as pyMOR's ``penzl_mimo_example``);
* ``msd``: the mass-spring-damper chain of Gugercin, Polyuga, Beattie, van der Schaft 2012 (1,000 states,
  2 × 2, non-symmetric, lightly damped; pyMOR's ``msd_example(as_lti=True)``); ``msd100``: the same chain with
  50 masses (100 states);
* ``heat1d``: 1-D heat conduction, linear finite elements, E = FE mass (1,000 states, SISO, symmetric);
* ``heat2d``: 2-D heat conduction on the unit square, bilinear finite elements, E = FE mass, 2 heated patches ×
  3 measured points (900 states; with ``--large`` also a 141 × 141 grid, 19,881 states, SISO, low-rank path);
* ``convdiff``: 2-D convection–diffusion, upwind finite differences (900 states, SISO, non-symmetric, E = I,
  feedthrough D = 0.5);
* ``plate``: the project's own heat plate (:func:`hybridcomp.rom.external.plate_system`, 1,024 states, 5 × 4,
  E diagonal);
* any ``.mat`` / Matrix Market systems given with ``--matrices``.

Each system in two time units 10^6 apart (``E`` and ``10^6 E``), at each order: the relative H2 error
``‖G − G_r‖₂ / ‖G − D‖₂`` of ours (the default basis: balanced truncation, or IRKA from three starts when
better), of pyMOR's balanced truncation and IRKA (``pip install pymor``, the ``bench`` extra; the columns say
``skipped: pymor not installed`` without it); whether the model is stable and has the order asked for; our
printed figure against an independent frequency quadrature on a twice finer grid, panelled at the full system's
sharp resonances (:func:`sharp_poles`) and the reduced poles (:func:`hybridcomp.rom.balanced.quadrature_h2_error`);
pyMOR's errors by the route our printed figure takes (Lyapunov equations of
:func:`hybridcomp.rom.balanced.h2_error`, frequency quadrature below 1e-4 where the Lyapunov terms cancel, on
the same panels; every quadrature below 1e-11 with its transfer functions refined in long double, as ours); the
seconds per call (ours: reading, checks, Gramians, reduction and both error figures;
pyMOR's: the reduction alone; everything with one BLAS thread, as ``reduce_matrices`` runs).
Prints a table and a final JSON line::

    python benchmarks/external_reduction.py [--orders 10,20,40] [--systems penzl,heat2d] [--large] [--no-pymor]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.io
import scipy.sparse as sp

from _table import table  # benchmarks/_table.py, beside this script


# -- systems from their published definitions -----------------------------------------------------------------
def penzl(n: int = 1006) -> dict:
    """Penzl's FOM: three lightly damped 2 × 2 blocks and −diag(1 … n−6); B = C^T = [10 × 6, 1 …]."""
    blocks = [np.array([[-1.0, w], [-w, -1.0]]) for w in (100.0, 200.0, 400.0)]
    A = sp.block_diag([*blocks, sp.diags(-np.arange(1.0, n - 5))]).tocsr()
    B = np.ones((n, 1))
    B[:6] = 10.0
    return {"A": A, "B": B, "C": B.T.copy()}


def penzl_mimo(n: int = 2000, m: int = 2, p: int = 3) -> dict:
    """pyMOR's MIMO variant of Penzl's FOM: the same A, ``B = arange(m n)``, ``C = arange(p n)`` reshaped."""
    blocks = [np.array([[-1.0, w], [-w, -1.0]]) for w in (100.0, 200.0, 400.0)]
    A = sp.block_diag([*blocks, sp.diags(-np.arange(1.0, n - 5))]).tocsr()
    return {"A": A, "B": np.arange(m * n, dtype=float).reshape(n, m), "C": np.arange(p * n, dtype=float).reshape(p, n)}


def msd(n: int = 1000, m_i: float = 4.0, k_i: float = 4.0, c_i: float = 1.0) -> dict:
    """Mass-spring-damper chain (GPBV12; pyMOR's ``msd_example(n, m=2, as_lti=True)``): states (q_j, p_j),
    ``q_j' = p_j / m``, ``p_j' = k (q_{j−1} − 2 q_j + q_{j+1}) − c p_j / m`` (the first mass: ``−k q_1 + k q_2``),
    forces on the first two masses, their velocities measured."""
    N = n // 2
    rows, cols, vals = [], [], []

    def put(i, j, v):
        rows.append(i)
        cols.append(j)
        vals.append(v)

    for j in range(N):
        q, p = 2 * j, 2 * j + 1
        put(q, p, 1.0 / m_i)
        put(p, p, -c_i / m_i)
        put(p, q, -k_i if j == 0 else -2 * k_i)
        if j > 0:
            put(p, q - 2, k_i)
        if j < N - 1:
            put(p, q + 2, k_i)
    A = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    B = np.zeros((n, 2))
    B[1, 0] = B[3, 1] = 1.0
    return {"A": A, "B": B, "C": B.T / m_i}


def heat1d(n: int = 1000) -> dict:
    """1-D heat conduction on (0, 1), linear elements, both ends at zero; heated at x = 0.2, measured at 0.7."""
    h = 1.0 / (n + 1)
    E = sp.diags([np.full(n - 1, h / 6), np.full(n, 4 * h / 6), np.full(n - 1, h / 6)], [-1, 0, 1])
    K = sp.diags([np.full(n - 1, -1 / h), np.full(n, 2 / h), np.full(n - 1, -1 / h)], [-1, 0, 1])
    B = np.zeros((n, 1))
    B[int(0.2 * n), 0] = 1.0
    C = np.zeros((1, n))
    C[0, int(0.7 * n)] = 1.0
    return {"E": E.tocsr(), "A": (-K).tocsr(), "B": B, "C": C}


def heat2d(k: int = 30, mimo: bool = True) -> dict:
    """2-D heat conduction on the unit square (k × k interior nodes, zero boundary), bilinear elements: E = mass,
    A = −stiffness (Kronecker products of the 1-D matrices); MIMO: 2 heated patches × 3 points, else 1 × 1."""
    h = 1.0 / (k + 1)
    M1 = sp.diags([np.full(k - 1, h / 6), np.full(k, 4 * h / 6), np.full(k - 1, h / 6)], [-1, 0, 1])
    K1 = sp.diags([np.full(k - 1, -1 / h), np.full(k, 2 / h), np.full(k - 1, -1 / h)], [-1, 0, 1])
    E = sp.kron(M1, M1).tocsr()
    K = (sp.kron(K1, M1) + sp.kron(M1, K1)).tocsr()
    idx = np.arange(k * k).reshape(k, k)
    patches = [(0.2, 0.2), (0.6, 0.7)] if mimo else [(0.3, 0.3)]
    points = [(0.5, 0.5), (0.8, 0.2), (0.3, 0.8)] if mimo else [(0.7, 0.6)]
    B = np.zeros((k * k, len(patches)))
    for j, (x, y) in enumerate(patches):
        i0, j0, w = int(x * k), int(y * k), max(1, k // 10)
        B[idx[i0:i0 + w, j0:j0 + w].ravel(), j] = h * h
    C = np.zeros((len(points), k * k))
    for i, (x, y) in enumerate(points):
        C[i, idx[int(x * k), int(y * k)]] = 1.0
    return {"E": E, "A": (-K).tocsr(), "B": B, "C": C}


def convdiff(k: int = 30, peclet: float = 20.0) -> dict:
    """2-D convection–diffusion on the unit square, upwind differences (flow along x), E = I, SISO, D = 0.5."""
    h = 1.0 / (k + 1)
    T = sp.diags([np.full(k - 1, 1 / h**2), np.full(k, -2 / h**2), np.full(k - 1, 1 / h**2)], [-1, 0, 1])
    U = sp.diags([np.full(k - 1, peclet / h), np.full(k, -peclet / h)], [-1, 0])
    I1 = sp.identity(k)
    A = (sp.kron(I1, T) + sp.kron(T, I1) + sp.kron(I1, U)).tocsr()
    idx = np.arange(k * k).reshape(k, k)
    B = np.zeros((k * k, 1))
    B[idx[:, : k // 5].ravel(), 0] = 1.0
    C = np.zeros((1, k * k))
    C[0, idx[:, -k // 5:].ravel()] = 1.0 / (k * (k // 5))
    return {"A": A, "B": B, "C": C, "D": np.array([[0.5]])}


def builtin_systems(large: bool) -> dict[str, dict]:
    from hybridcomp.rom.external import plate_system

    out = {"penzl": penzl(), "penzl_mimo": penzl_mimo(), "msd": msd(), "msd100": msd(100),
           "heat1d": heat1d(), "heat2d": heat2d(),
           "convdiff": convdiff(), "plate": plate_system(32)}
    if large:
        out["heat2d_large"] = heat2d(141, mimo=False)
    return out


# -- the comparison -------------------------------------------------------------------------------------------
def _pymor_models(mats: dict, r: int, irka_maxit: int) -> dict:
    """pyMOR's BT and IRKA at order r: (E_r, A_r, B_r, C_r) and seconds, or the reason they are missing."""
    try:
        from pymor.models.iosys import LTIModel
        from pymor.reductors.bt import BTReductor
        from pymor.reductors.h2 import IRKAReductor
    except ImportError:
        return {"skip": "pymor not installed (pip install pymor, the bench extra)"}
    n = mats["A"].shape[0]
    fom = LTIModel.from_matrices(sp.csc_matrix(mats["A"]), np.asarray(mats["B"]), np.asarray(mats["C"]),
                                 E=sp.csc_matrix(mats["E"]) if "E" in mats else None)
    out = {}
    for name, red, kw in (("BT", BTReductor, {}), ("IRKA", IRKAReductor, {"maxit": irka_maxit})):
        t0 = time.perf_counter()
        try:
            rom = red(fom).reduce(r, **kw)
        except Exception as exc:  # noqa: BLE001  (a reference that fails is a row's finding, not the benchmark's end)
            out[name] = {"error": f"{type(exc).__name__}: {exc}"[:80]}
            continue
        A, B, C, _, E = rom.to_matrices()
        A, B, C = (X.toarray() if sp.issparse(X) else np.asarray(X) for X in (A, B, C))
        E = np.eye(A.shape[0]) if E is None else (E.toarray() if sp.issparse(E) else np.asarray(E))
        out[name] = {"model": (E, A, B, C), "s": time.perf_counter() - t0}
    del n
    return out


def sharp_poles(system, ratio: float = 20.0, most: int = 20) -> np.ndarray:
    """The full system's sharpest resonances (``|Im λ| > ratio |Re λ|``, at most ``most``), for the quadratures'
    panels: a reduced model may miss a resonance (Penzl's at 100, 200, 400 rad/s at order 10), and a quadrature
    panelled on its poles alone then steps over the full model's peak (2.3e-5 instead of 5.1e-5). Dense
    eigenvalues up to 2,000 states of a non-symmetric system; a symmetric one has real poles only."""
    import scipy.linalg as la

    if system.symmetric or system.n > 2000:
        return np.zeros(0, complex)
    lam = la.eigvals(system.A.toarray(), system.E.toarray())
    lam = lam[np.abs(lam.imag) > ratio * np.abs(lam.real)]
    return lam[np.argsort(-np.abs(lam.imag / lam.real))][:most]


def error_of(system, Zp, spec, mdl, peaks, per_decade: int = 12) -> float:
    """The route of our printed figure for any model: Lyapunov, frequency quadrature below 1e-4 (terms cancel)."""
    from hybridcomp.rom import balanced as bl

    E, A, B, C = system.E, system.A, system.B, system.C
    e = bl.h2_error(E, A, B, C, Zp, *mdl, system.symmetric)
    if e < 1e-4:
        e = quadrature(system, spec, mdl, np.r_[peaks, np.linalg.eigvals(np.linalg.solve(mdl[0], mdl[1]))],
                       per_decade)
    return e


def quadrature(system, spec, mdl, peaks, per_decade: int) -> float:
    """Frequency quadrature of the relative H2 error, refined in long double below ``REFINE_BELOW`` (as ours)."""
    from hybridcomp.rom import balanced as bl
    from hybridcomp.rom.external import REFINE_BELOW

    full = (system.E, system.A, system.B, system.C, system.D)
    e = bl.quadrature_h2_error(full, (*mdl[:4], system.D), spec.slow, spec.fast, per_decade, system.symmetric, peaks)
    if e < REFINE_BELOW:
        e = bl.quadrature_h2_error(full, (*mdl[:4], system.D), spec.slow, spec.fast, per_decade, system.symmetric,
                                   peaks, refined=True)
    return e


def main(argv=None) -> dict:
    from hybridcomp.fem.blas import single_blas_thread

    with single_blas_thread():  # small dense work throughout (see hybridcomp.rom.external._one_blas_thread)
        return _main(argv)


def _main(argv=None) -> dict:
    from hybridcomp.rom import balanced as bl
    from hybridcomp.rom.external import check_system, read_matrices, reduce_matrices

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--orders", default="10,20,40", help="reduced orders (default 10,20,40)")
    p.add_argument("--systems", help="comma-separated names of the built-in systems (default: all)")
    p.add_argument("--matrices", nargs="*", type=Path, default=[], help="more systems: .mat files or Matrix Market dirs")
    p.add_argument("--large", action="store_true", help="also the 19,881-state 2-D heat system (low-rank path)")
    p.add_argument("--units", default="1,1e6", help="factors on E, i.e. time units (default 1,1e6)")
    p.add_argument("--no-pymor", action="store_true", help="skip pyMOR's BT and IRKA even when installed")
    p.add_argument("--irka-maxit", type=int, default=50, help="IRKA iterations (default 50)")
    p.add_argument("--no-quadrature", action="store_true", help="skip the independent frequency quadrature")
    args = p.parse_args(argv)
    orders = [int(v) for v in args.orders.split(",")]
    units = [float(v) for v in args.units.split(",")]
    work = Path(tempfile.mkdtemp(prefix="external-reduction-"))
    systems = builtin_systems(args.large)
    if args.systems:
        systems = {k: systems[k] for k in args.systems.split(",")}
    for path in args.matrices:
        systems[path.stem] = read_matrices(path)[0]
    rows = []
    for name, mats in systems.items():
        for unit in units:
            m = dict(mats)
            if unit != 1.0:
                m["E"] = (sp.identity(m["A"].shape[0]) if m.get("E") is None else sp.csr_matrix(m["E"])) * unit
            path = work / f"{name}_E{unit:g}.mat"
            scipy.io.savemat(path, {k: v for k, v in m.items() if v is not None})
            system = check_system(m, str(path))
            E, A, B, C = system.E, system.A, system.B, system.C
            Zp, _, gram = bl.gramian_factors(E, A, B, C, system.symmetric)
            spec = bl.spectrum_bounds(E, A, system.symmetric)
            sharp = sharp_poles(system)
            for r in orders:
                if r >= system.n:
                    continue
                row = {"system": name, "n": system.n, "m x q": f"{B.shape[1]}x{C.shape[0]}",
                       "sym": "y" if system.symmetric else "n", "E": "I" if "E" not in mats else "M",
                       "E x": f"{unit:g}", "r": r}
                t0 = time.perf_counter()
                try:
                    ours = reduce_matrices(path, order=r)
                except ValueError as exc:  # a refusal (e.g. an order above the minimal realisation) is reported
                    row |= {"ours": f"refused: {exc}"[:60], "_": {}}
                    rows.append(row)
                    continue
                t_ours = time.perf_counter() - t0
                e_ours = ours.meta["h2_error_relative"]
                model = (ours.E, ours.A, ours.B, ours.C)
                e_check = bl.h2_error(E, A, B, C, Zp, *model, system.symmetric)
                peaks = np.r_[ours.poles(), sharp]

                # independent of the printed figure: quadrature on a twice finer grid
                q = None if args.no_quadrature else quadrature(system, spec, model, peaks, 24)
                ref = {} if args.no_pymor else _pymor_models(m, r, args.irka_maxit)
                errs = {}
                for k in ("BT", "IRKA"):
                    got = ref.get(k, {})
                    if "model" in got:
                        e = error_of(system, Zp, spec, got["model"], peaks)
                        if np.isfinite(e):  # an unstable reference (error inf) is no reference
                            errs[k] = e
                        row[f"pymor {k}"] = f"{e:.3g}" if np.isfinite(e) else "unstable"
                        row[f"{k} s"] = f"{got['s']:.2f}"
                    else:
                        row[f"pymor {k}"] = ref.get("skip") or got.get("error", "skipped (--no-pymor)")
                        row[f"{k} s"] = "-"
                best = min(errs.values()) if errs else None
                row |= {"ours": f"{e_ours:.3g}", "ratio": f"{e_ours / best:.2f}" if best else "-",
                        "stable": "y" if ours.meta["stable"] else "NO", "order": ours.order,
                        "quadrature": "-" if q is None else f"{q:.3g}",
                        "printed/indep": "-" if q is None else f"{e_ours / q:.4f}",
                        "ours s": f"{t_ours:.2f}",
                        "_": {"h2_ours": e_ours, "h2_ours_recomputed": e_check, "h2_quadrature": q,
                              "h2_pymor_bt": errs.get("BT"), "h2_pymor_irka": errs.get("IRKA"), "gramians": gram,
                              "hinf_relative": ours.meta["hinf_error_relative"], "seconds_ours": t_ours,
                              "seconds_pymor_bt": ref.get("BT", {}).get("s"),
                              "seconds_pymor_irka": ref.get("IRKA", {}).get("s"),
                              "within_2x": None if best is None else bool(e_ours <= 2 * best)}}
                rows.append(row)
                print(f"{name} E×{unit:g} r={r}: ours {e_ours:.3g} (quadrature {q}), pyMOR BT "
                      f"{errs.get('BT')}, IRKA {errs.get('IRKA')} [{t_ours:.1f} s]", file=sys.stderr, flush=True)
    cols = ["system", "n", "m x q", "sym", "E", "E x", "r", "ours", "pymor BT", "pymor IRKA", "ratio", "stable",
            "order", "quadrature", "printed/indep", "ours s", "BT s", "IRKA s"]
    for row in rows:
        for c in cols:
            row.setdefault(c, "-")
    print(table(rows, cols))
    judged = [r["_"]["within_2x"] for r in rows if r["_"].get("within_2x") is not None]
    out = {"benchmark": "external_reduction", "machine": platform.machine(), "cpus": os.cpu_count(),
           "rows_within_2x_of_best_reference": sum(judged), "rows_judged": len(judged),
           "rows_refused": sum(str(r["ours"]).startswith("refused") for r in rows),
           "all_stable": all(r["stable"] == "y" for r in rows if r["stable"] != "-"),
           "orders_delivered": all(r["order"] == r["r"] for r in rows if r["order"] != "-"),
           "printed_within_10pct_of_independent": all(abs(r["_"]["h2_ours"] / r["_"]["h2_quadrature"] - 1) <= 0.1
                                                       for r in rows if r["_"].get("h2_quadrature")),
           "rows": [{k: v for k, v in r.items() if k != "_"} | r["_"] for r in rows]}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
