r"""Benchmark: the Krylov reduced model against FE on the demonstrator.

Measures, on one machine in one run:

* reduction: order reached for the tolerances, time, errors against FE reported by ``reduce_model``;
* accuracy on the 16 h example day at Δt = 60 s: exact ROM against FE Crank–Nicolson at 60 s and at a
  finer step (whose difference is the FE time error), and against FE backward Euler;
* error against order (ROM by the FE's own θ-method, so the difference is the reduction error alone);
* speed: the same 16 h at Δt = 60 s, FE stepping (backward Euler, the FE default) against the ROM; one
  ROM step; a week at Δt = 1 s.

Prints tables and a final JSON line::

    python benchmarks/rom.py [--element-size-mm 80] [--orders 51,60,...] [--pymor]

``--pymor`` adds the cross-check against pyMOR's balanced truncation and IRKA (a benchmark-only
dependency: ``pip install pymor``) on the demonstrator's matrices at ``--pymor-element-size-mm``;
``--pymor-only`` runs only that: relative H2 errors of the greedy Krylov basis, of the H2-optimal
one-sided basis (:mod:`hybridcomp.rom.h2`), of pyMOR's balanced truncation and IRKA, each also computed
exactly from the full modal decomposition (``*_exact``).  Inputs are scaled by their largest magnitude on
the example day (``--pymor-input-scaling range``) or not at all (``unit``); outputs by 1/tolerance.
``--figure F.png`` plots the errors against order (``--plot-from`` replots an earlier run's output)::

    python benchmarks/rom.py --pymor-only --pymor-orders 20,40,60,80 --irka-maxit 0 \
        --figure benchmarks/figures/rom_h2_vs_order.png
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hybridcomp.models import jsonio

from _table import table  # benchmarks/_table.py, beside this script


def max_err(a, b) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).max())


def pymor_check(model, orders: list[int], irka_maxit: int = 50, input_scaling: str = "range", h2_maxiter: int = 3000,
                bt_max_order: int = 1000) -> list[dict]:
    """H2 errors of our ROMs, pyMOR's balanced truncation and IRKA at equal orders (same matrices, same weights).

    The system is the demonstrator's at nominal h; inputs are scaled by their largest magnitude on the 16 h
    example day (``range``: W for heat inputs, K for zone air) or not at all (``unit``), outputs by
    1/tolerance (sensors 1/0.05 K, drift 1/0.2 µm).  Besides pyMOR's ``(fom - rom).h2_norm()``, every error
    is also computed exactly from the full modal decomposition (dense, closed-form Gramians), which checks
    pyMOR's low-rank computation and ours against each other.
    """
    try:
        from pymor.models.iosys import LTIModel
        from pymor.reductors.bt import BTReductor
        from pymor.reductors.h2 import IRKAReductor
    except ImportError:
        raise SystemExit("the pyMOR cross-check needs pyMOR, a benchmark-only dependency: pip install pymor") from None

    from hybridcomp.fem.loads import example_loads
    from hybridcomp.rom import h2
    from hybridcomp.rom.krylov import Reductor
    from hybridcomp.rom.machine import system_from_model

    system = system_from_model(model)
    h = system.h
    w = np.r_[np.full(len(model.sensor_names), 1 / 0.05), np.full(3, 1e6 / 0.2)]
    if input_scaling == "range":
        U = model.machine.layout().inputs(example_loads(model.machine, 16.0, 60.0))
        scale = np.abs(U).max(axis=0)
        scale[scale == 0] = 1.0
    else:
        scale = np.ones(len(system.input_names))
    E = system.M.tocsc()
    A = (-system.stiffness(h)).tocsc()
    B = system.input_matrix(h) * scale[None, :]
    C = w[:, None] * system.C
    truth = h2.modal_form(E.toarray(), -A.toarray(), B, C) if system.n <= 6000 else None
    fom = LTIModel.from_matrices(A, B, C, E=E)
    t0 = time.perf_counter()
    fom_h2 = fom.h2_norm()
    t_fom = time.perf_counter() - t0
    bt = BTReductor(fom)
    irka = IRKAReductor(fom)
    greedy = Reductor(system, 1 / w, scale, h[None, :])
    surrogate = Reductor(system, 1 / w, scale, h[None, :], n_s=12, fastest_time_s=5.0).reduce(order=max(500, 4 * max(orders))).V

    def exact(rom_mats):
        return h2.general_h2_error(truth, *rom_mats) if truth is not None else float("nan")

    def galerkin(V):
        mats = (V.T @ (A @ V), V.T @ B, C @ V, V.T @ (E @ V))
        lti = LTIModel.from_matrices(*mats[:3], E=mats[3])
        return (fom - lti).h2_norm() / fom_h2, exact(mats)

    rows = []
    for r in orders:
        row = {"order": r}
        row["greedy_rel_H2"], row["greedy_exact"] = galerkin(greedy.reduce(order=r).V)
        t0 = time.perf_counter()
        V = h2.h2_optimal_basis(system, surrogate, r, [h], scale, w, maxiter=h2_maxiter)
        row["h2opt_s"] = time.perf_counter() - t0
        row["h2opt_maxiter"] = h2_maxiter
        row["h2opt_rel_H2"], row["h2opt_exact"] = galerkin(V)
        if r <= bt_max_order:
            t0 = time.perf_counter()
            rom_bt = bt.reduce(r)
            row["bt_s"] = time.perf_counter() - t0
            row["bt_rel_H2"] = (fom - rom_bt).h2_norm() / fom_h2
        else:
            row["bt_s"], row["bt_rel_H2"] = float("nan"), float("nan")
        row["bt_exact"] = exact(h2.balanced_truncation(truth, r)[:3]) if truth is not None else float("nan")
        row["irka_rel_H2"], row["irka_s"] = "not run", float("nan")
        if irka_maxit > 0:
            try:
                t0 = time.perf_counter()
                rom_irka = irka.reduce(r, tol=1e-4, maxit=irka_maxit)
                row["irka_s"] = time.perf_counter() - t0
                row["irka_rel_H2"] = (fom - rom_irka).h2_norm() / fom_h2
            except Exception as exc:  # noqa: BLE001 (IRKA may fail to converge in many ways; the table reports it)
                row["irka_rel_H2"] = f"failed: {exc}"
        ref = row["bt_exact"] if np.isfinite(row["bt_exact"]) else row["bt_rel_H2"]
        row["h2opt_over_bt"] = row["h2opt_exact"] / ref if np.isfinite(row["h2opt_exact"]) else row["h2opt_rel_H2"] / ref
        row["fom_h2_s"] = t_fom
        rows.append(row)
        print(jsonio.dumps(rows[-1], default=str), flush=True)
    return rows


def plot_h2(run: dict, path: Path) -> Path:
    """Relative H2 error against order of a :func:`run_pymor` result: greedy Krylov, H2-optimal one-sided,
    balanced truncation, IRKA."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def col(key):
        return [float(r[key]) if isinstance(r[key], (int, float)) else float("nan") for r in rows]

    rows = sorted(run["rows"], key=lambda row: row["order"])
    title = f"vmc800, {run['nodes']} nodes, nominal h; inputs scaled: {run['input_scaling']}, outputs 1/tol"
    r = [row["order"] for row in rows]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy(r, col("greedy_exact"), "s-", label="ours: greedy rational Krylov (one-sided)")
    ax.semilogy(r, col("h2opt_exact"), "o-", label="ours: H2-optimal one-sided basis")
    ax.semilogy(r, col("bt_exact"), "k^--", label="balanced truncation (two-sided)")
    ax.semilogy(r, [2 * v for v in col("bt_exact")], "k:", lw=0.8, label="2 × balanced truncation")
    if any(np.isfinite(col("irka_rel_H2"))):
        ax.semilogy(r, col("irka_rel_H2"), "v", color="tab:red", label="pyMOR IRKA (50 iterations)")
    ax.set_xlabel("reduced order")
    ax.set_ylabel("relative H2 error")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_pymor(args) -> dict:
    """The pyMOR cross-check of the command line (``--pymor`` or ``--pymor-only``): prints its table, plots it
    (``--figure``) and returns ``{"nodes", "input_scaling", "rows"}`` for the JSON line."""
    from hybridcomp.fem.model import build_model
    from hybridcomp.models import load_machine

    model = build_model(load_machine("vmc800"), None, args.pymor_element_size_mm)
    rows = pymor_check(model, [int(v) for v in args.pymor_orders.split(",")], args.irka_maxit,
                       args.pymor_input_scaling, args.h2_maxiter)
    run = {"nodes": model.n, "input_scaling": args.pymor_input_scaling, "rows": rows}
    print(f"pyMOR cross-check at {model.n} nodes (relative H2 errors; inputs scaled: {args.pymor_input_scaling}, "
          "outputs weighted by 1/tolerance)")
    print(table([{k: (f"{v:.3g}" if isinstance(v, float) else v) for k, v in r.items()} for r in rows], list(rows[0])))
    if args.figure:
        plot_h2(run, args.figure)
    return run


def speed_child(path: str, hours: float, repeats: int) -> dict:
    """ROM timings in a fresh process: the 16 h day at 60 s, single steps, a week at 1 s (medians)."""
    from hybridcomp.fem.loads import example_loads
    from hybridcomp.models import load_machine
    from hybridcomp.rom.reduced import load_rom

    machine = load_machine("vmc800")
    rom = load_rom(path, machine)
    loads = example_loads(machine, hours, 60.0)
    t, U = loads.time_s, machine.layout().inputs(loads)
    rom.integrate(t, U)  # discretisation cached, as in the monitor's steady operation
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        rom.integrate(t, U)
        runs.append(time.perf_counter() - t0)
    x = rom.steady_state(U[0])
    n_steps = 20000
    t0 = time.perf_counter()
    for k in range(n_steps):
        x = rom.step(x, U[k % len(t)], U[(k + 1) % len(t)], 60.0)
    one_step_us = (time.perf_counter() - t0) / n_steps * 1e6
    week = example_loads(machine, 168.0, 1.0)
    Uw = machine.layout().inputs(week)
    week_runs = []
    for _ in range(max(1, repeats // 2)):
        t0 = time.perf_counter()
        rom.integrate(week.time_s, Uw)
        week_runs.append(time.perf_counter() - t0)
    return {"rom_16h_s": statistics.median(runs), "one_step_us": one_step_us, "week_1s_s": statistics.median(week_runs)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=80.0)
    p.add_argument("--hours", type=float, default=16.0)
    p.add_argument("--orders", default="20,30,40,51,60,70,80,90,100,120,150")
    p.add_argument("--fine-dt", type=float, default=15.0, help="FE Crank–Nicolson step for the time-converged reference [s]")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--pymor", action="store_true", help="add the pyMOR cross-check (needs: pip install pymor)")
    p.add_argument("--pymor-element-size-mm", type=float, default=150.0)
    p.add_argument("--pymor-orders", default="20,40,60")
    p.add_argument("--irka-maxit", type=int, default=50, help="IRKA iterations (0: skip IRKA)")
    p.add_argument("--pymor-only", action="store_true", help="only the pyMOR cross-check")
    p.add_argument("--pymor-input-scaling", choices=("range", "unit"), default="range",
                   help="inputs scaled by their largest magnitude on the example day (range) or not (unit)")
    p.add_argument("--h2-maxiter", type=int, default=45000, help="L-BFGS iterations of the H2-optimal basis "
                   "(the published pyMOR table: 45,000)")
    p.add_argument("--figure", type=Path, help="with --pymor or --pymor-only: plot the H2 errors against order to this PNG")
    p.add_argument("--plot-from", type=Path, help="only plot (--figure) from the JSON line of an earlier --pymor-only run")
    p.add_argument("--speed-child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.speed_child:
        print(jsonio.dumps(speed_child(args.speed_child, args.hours, args.repeats)))
        return 0
    if args.plot_from:
        print(plot_h2(json.loads(args.plot_from.read_text().strip().splitlines()[-1])["pymor"], args.figure))
        return 0
    if args.pymor_only:
        print(jsonio.dumps({"pymor": run_pymor(args)}, default=str))
        return 0

    from hybridcomp.fem.loads import example_loads
    from hybridcomp.fem.model import build_model
    from hybridcomp.fem.stepping import integrate_inputs
    from hybridcomp.models import load_machine
    from hybridcomp.rom.krylov import Reduction, Reductor, orthonormal_extension
    from hybridcomp.rom.machine import (
        gramian_directions,
        h_samples,
        reduce_model,
        split_outputs,
        system_from_model,
        theta_outputs,
        to_reduced,
    )
    from hybridcomp.rom.reduced import save_rom

    result: dict = {"machine": platform.machine(), "python": platform.python_version(), "date": time.strftime("%Y-%m-%d")}
    machine = load_machine("vmc800")
    t0 = time.perf_counter()
    model = build_model(machine, None, args.element_size_mm)
    result.update(nodes=model.n, element_size_mm=args.element_size_mm, build_s=time.perf_counter() - t0)
    loads = example_loads(machine, args.hours, 60.0)
    U = machine.layout().inputs(loads)
    t = loads.time_s

    # -- reduction to the tolerances -----------------------------------------------------------------
    t0 = time.perf_counter()
    rom = reduce_model(model, tol_K=0.05, tol_um=0.2, check_loads=loads)
    result["reduce_s"] = time.perf_counter() - t0
    result["order"] = rom.order
    result["check"] = rom.meta["check"]
    print(f"{model.n} nodes: reduced to order {rom.order} in {result['reduce_s']:.1f} s; check {jsonio.dumps(rom.meta['check'])}")

    # -- FE references -------------------------------------------------------------------------------
    t0 = time.perf_counter()
    fe_be = integrate_inputs(model, t, U, scheme="theta", theta=1.0)  # backward Euler: the speed reference
    fe_be_wall = time.perf_counter() - t0
    fe_cn = integrate_inputs(model, t, U, scheme="theta", theta=0.5)
    t_fine = np.arange(t[0], t[-1] + 0.5 * args.fine_dt, args.fine_dt)
    U_fine = np.column_stack([np.interp(t_fine, t, U[:, j]) for j in range(U.shape[1])])
    fe_fine = integrate_inputs(model, t_fine, U_fine, scheme="theta", theta=0.5)
    step = round(60.0 / args.fine_dt)
    fine_s, fine_d = fe_fine.sensors_degC[::step], fe_fine.drift_um[::step]

    Y, _ = rom.integrate(t, U)
    s_rom, d_rom = split_outputs(rom, Y)
    acc = [
        {"comparison": "FE CN 60 s vs FE CN fine (FE time error)",
         "sensor_K": max_err(fe_cn.sensors_degC, fine_s), "drift_um": max_err(fe_cn.drift_um, fine_d)},
        {"comparison": "FE BE 60 s vs FE CN fine (FE time error)",
         "sensor_K": max_err(fe_be.sensors_degC, fine_s), "drift_um": max_err(fe_be.drift_um, fine_d)},
        {"comparison": "ROM (CN 60 s) vs FE CN 60 s (reduction error)",
         **dict(zip(("sensor_K", "drift_um"),
                    (max_err(a, b) for a, b in zip(split_outputs(rom, theta_outputs(rom, t, U, 0.5)),
                                                   (fe_cn.sensors_degC, fe_cn.drift_um)))))},
        {"comparison": "ROM exact vs FE CN 60 s",
         "sensor_K": max_err(s_rom, fe_cn.sensors_degC), "drift_um": max_err(d_rom, fe_cn.drift_um)},
        {"comparison": f"ROM exact vs FE CN {args.fine_dt:g} s",
         "sensor_K": max_err(s_rom, fine_s), "drift_um": max_err(d_rom, fine_d)},
        {"comparison": "ROM exact vs FE BE 60 s",
         "sensor_K": max_err(s_rom, fe_be.sensors_degC), "drift_um": max_err(d_rom, fe_be.drift_um)},
    ]
    for r in acc:
        r["sensor_K"] = round(r["sensor_K"], 5)
        r["drift_um"] = round(r["drift_um"], 5)
    print()
    print(table(acc, ["comparison", "sensor_K", "drift_um"]))
    result["accuracy"] = acc

    # -- error against order -------------------------------------------------------------------------
    system = system_from_model(model)
    scale = np.abs(U).max(axis=0)
    scale[scale == 0] = 1.0
    tol = np.r_[np.full(len(model.sensor_names), 0.05), np.full(3, 0.2e-6)]
    reductor = Reductor(system, tol, scale, h_samples(model.h_W_m2K, (0.5, 2.0)))
    big = reductor.reduce(order=250)
    n_first = big.history[0][0]
    first = big.V[:, :n_first]
    D = gramian_directions(system, big.V, h_samples(model.h_W_m2K, (0.5, 2.0))[:3], scale, tol)
    meta0 = {"reference_temperature_degC": machine.reference_temperature_degC}

    def errors(V):
        ro = to_reduced(system, Reduction(V, (), 0.0, ()), meta0, keep_basis=False)
        s_r, d_r = split_outputs(ro, theta_outputs(ro, t, U, 0.5))
        return round(max_err(s_r, fe_cn.sensors_degC), 5), round(max_err(d_r, fe_cn.drift_um), 5)

    curve = []
    for r in [int(v) for v in args.orders.split(",")]:
        row = {"order": r}
        row["greedy_sensor_K"], row["greedy_drift_um"] = errors(reductor.reduce(order=r).V)
        row["compressed_sensor_K"], row["compressed_drift_um"] = "-", "-"
        if r > n_first:
            V = np.hstack([first, orthonormal_extension(first, D[:, : r - n_first])])
            if V.shape[1] == r:
                row["compressed_sensor_K"], row["compressed_drift_um"] = errors(V)
        curve.append(row)
    print()
    print(f"error against order (reduction error alone; compressed = first block + Gramian directions of order {big.V.shape[1]})")
    print(table(curve, list(curve[0])))
    result["error_vs_order"] = curve

    # -- speed (the ROM in a fresh process: BLAS threads left spinning by the FE runs would slow it) ----------
    fe_step_s = fe_be.timings_s["stepping_total"]
    with tempfile.TemporaryDirectory() as tmp:
        path = save_rom(Path(tmp) / "rom.npz", rom)
        # one BLAS thread: the ROM's matrices are far too small for threads, which only add wake-up latency
        # (and, on a loaded 2-core machine, measured 30x slower runs)
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        out = subprocess.run([sys.executable, __file__, "--speed-child", str(path), "--hours", str(args.hours),
                              "--repeats", str(args.repeats)], check=True, capture_output=True, text=True, env=env).stdout
    sp = json.loads(out.strip().splitlines()[-1])
    rom_16h, one_step_us, week_s = sp["rom_16h_s"], sp["one_step_us"], sp["week_1s_s"]
    speed = [
        {"what": f"16 h at 60 s ({len(t) - 1} steps), FE backward Euler stepping", "seconds": round(fe_step_s, 3)},
        {"what": "  FE whole simulate call (incl. factorisation)", "seconds": round(fe_be_wall, 3)},
        {"what": "  ROM simulate (median)", "seconds": round(rom_16h, 5)},
        {"what": "  speed-up FE stepping / ROM", "seconds": round(fe_step_s / rom_16h, 1)},
        {"what": "one ROM step [µs]", "seconds": round(one_step_us, 2)},
        {"what": "a week at 1 s (604,800 steps), ROM (median)", "seconds": round(week_s, 3)},
    ]
    print()
    print(table(speed, ["what", "seconds"]))
    result.update(fe_stepping_s=fe_step_s, fe_simulate_s=fe_be_wall, rom_16h_s=rom_16h, speedup=fe_step_s / rom_16h,
                  one_step_us=one_step_us, week_1s_s=week_s,
                  targets={"speedup>=1000": fe_step_s / rom_16h >= 1000, "one_step<=50us": one_step_us <= 50,
                           "week<=2s": week_s <= 2.0})

    if args.pymor:
        print()
        result["pymor"] = run_pymor(args)
    print()
    print(jsonio.dumps(result, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
