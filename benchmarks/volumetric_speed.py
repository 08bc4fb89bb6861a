"""Benchmark: the volumetric table in real time, from the model step to the position in the control's cycle.

    python benchmarks/volumetric_speed.py [--element-size 80] [--rom POSE_ROM.npz] [--points 3] [--repeats 15]
                                          [--all-blas-threads]

On the demonstrator's pose-aware reduced model (:mod:`hybridcomp.rom.poses`, star scheme, with its drives; built
at ``--element-size`` mm and cached in the temporary folder, or read from ``--rom``) it times, as medians of
``--repeats`` runs:

* the model step at every support pose: one exact step of the whole pose-aware model, 60 s and 5 s
  (:meth:`~hybridcomp.rom.reduced.ReducedModel.step`, its first-order-hold discretisation cached per step size as
  in the daemon; the one-time discretisation is reported apart), plus the outputs ``C x``; beside it the same
  step through :meth:`~hybridcomp.rom.reduced.ReducedModel.integrate` (held inputs, what a batch run does) and the
  daemon's observer predict on the model pose's block (:meth:`~hybridcomp.rom.observer.Observer.predict`: state
  and covariance; the pose-aware rest runs beside it without one), and the daemon's step of the pose-aware part
  (:func:`hybridcomp.monitor.volumetric.advance` on its 5 min step: the model, its run on the nuts' heat alone for
  the drives' nuts' part, the pose history's clock and the outputs one step ahead);
* the table update: :func:`~hybridcomp.rom.volumetric.table_of` for the grid's support points (27 with
  ``--points 3``);
* the interpolation of 100,000 positions (:func:`~hybridcomp.rom.volumetric.interpolate`) and of one position
  (:func:`~hybridcomp.rom.volumetric.interpolate_one`, median over 10,000 calls).

Everything runs with one BLAS thread, as the daemon steps its observer (a small dense product on a second thread
only waits, and on a shared machine the waits swing from 0.1 ms to 8 ms); ``--all-blas-threads`` leaves the library's
default.  Criteria: model step (60 s and 5 s, and the daemon's) ≤ 50 ms, table update ≤ 5 ms, 100,000 positions
≤ 50 ms, one position ≤ 20 µs.  Prints a table and a final JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from hybridcomp.fem.blas import single_blas_thread
from hybridcomp.fem.loads import example_loads
from hybridcomp.models import jsonio, load_machine
from hybridcomp.rom.reduced import load_rom, save_rom
from hybridcomp.rom.volumetric import default_grid, interpolate, interpolate_one, table_of, table_operator

from _table import table

LIMITS = {"model step 60 s": 50e-3, "model step 5 s": 50e-3, "table update": 5e-3, "interpolate 100,000": 50e-3,
          "interpolate one": 20e-6, "daemon's model step 300 s": 50e-3}


def pose_rom(machine, element_size_mm: float, path: str | None):
    """The pose-aware reduced model from ``path``, or built and cached in the temporary folder."""
    if path:
        return load_rom(path, machine), 0.0
    from hybridcomp.fem.poses import default_levels

    levels = "".join(f"{a}{n}" for a, n in sorted(default_levels(machine).items())) or "3"  # not a model of others
    cache = Path(tempfile.gettempdir()) / f"hybridcomp-volumetric-{machine.name}-{element_size_mm:g}mm-{levels}.npz"
    if cache.exists():
        return load_rom(cache, machine), 0.0
    from hybridcomp.fem.model import build_model
    from hybridcomp.rom.machine import reduce_model
    from hybridcomp.rom.poses import reduce_at_poses

    t0 = time.perf_counter()
    model = build_model(machine, None, element_size_mm)
    rom = reduce_at_poses(model, reduce_model(model), "star")
    save_rom(cache, rom)
    return rom, time.perf_counter() - t0


def median_s(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size", type=float, default=80.0, help="FE element size of the model [mm]")
    p.add_argument("--rom", help="a pose-aware reduced model (.npz) instead of building one")
    p.add_argument("--points", type=int, default=3, help="support points per axis")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--positions", type=int, default=100_000)
    p.add_argument("--all-blas-threads", action="store_true", help="time with the BLAS library's threads, not one")
    a = p.parse_args(argv)
    with contextlib.nullcontext() if a.all_blas_threads else single_blas_thread():
        return measure(a)


def measure(a: argparse.Namespace) -> int:
    m = load_machine("vmc800")
    rom, build_s = pose_rom(m, a.element_size, a.rom)
    loads = example_loads(m, 4.0, 60.0)
    U = rom.layout().inputs(loads.names, loads.values)
    u0, u1 = U[100], U[101]
    x = rom.steady_state(U[0])
    times, extra = {}, {}
    for dt in (60.0, 5.0):
        t0 = time.perf_counter()
        rom.discretize(dt)
        extra[f"discretize_{dt:g}s_s"] = time.perf_counter() - t0
        times[f"model step {dt:g} s"] = median_s(lambda dt=dt: rom.outputs(rom.step(x, u0, u1, dt)), a.repeats)
        times[f"integrate one {dt:g} s step"] = median_s(
            lambda dt=dt: rom.integrate(np.array([0.0, dt]), np.vstack([u1, u1]), initial=x, hold="step"), a.repeats)
    # the daemon's step of the pose-aware part: the model and its run on the nuts' heat alone (the drives' nuts'
    # part, monitor.volumetric), with the pose history's clock, on the 5 min model step
    from hybridcomp.monitor import volumetric

    pm = volumetric.pose_model(rom, a.points, m)
    extra["nuts_part"] = pm.nut_inputs is not None
    track = volumetric.start(pm, U[0], 0.0, 300.0)
    volumetric.advance(pm, track, u1, 300.0, 300.0)
    times["daemon's model step 300 s"] = median_s(lambda: volumetric.advance(pm, track, u1, 300.0, 300.0), a.repeats)
    try:
        from hybridcomp.rom.observer import build_observer
        from hybridcomp.rom.poses import model_pose_block

        obs = build_observer(model_pose_block(rom), m)  # the daemon's observer: the model pose's block only
        s0 = obs.initial(U[0])
        obs.predict(s0, u1, 5.0)
        times["observer predict 5 s"] = median_s(lambda: obs.predict(s0, u1, 5.0), max(3, a.repeats // 3))
    except (ValueError, np.linalg.LinAlgError) as exc:  # the observer is beside the point: say why it is missing
        extra["observer"] = f"{type(exc).__name__}: {exc}"
    t0 = time.perf_counter()
    op = table_operator(rom, default_grid(rom, a.points))
    extra["table_operator_s"] = time.perf_counter() - t0
    y = rom.outputs(rom.step(x, u0, u1, 60.0))
    times["table update"] = median_s(lambda: table_of(op, y, 60.0), a.repeats)
    tab = table_of(op, y, 60.0)
    rng = np.random.default_rng(0)
    box = np.array([(pos[0], pos[-1]) for pos in op.grid.positions_mm])
    Q = rng.uniform(box[:, 0], box[:, 1], (a.positions, box.shape[0]))
    interpolate(tab, Q)
    times[f"interpolate {a.positions:,}"] = median_s(lambda: interpolate(tab, Q), a.repeats)
    one = Q[:10_000].tolist()
    ts = []
    for q in one:
        t0 = time.perf_counter()
        interpolate_one(tab, q)
        ts.append(time.perf_counter() - t0)
    times["interpolate one"] = statistics.median(ts)
    rows, ok = [], True
    for name, t in times.items():
        lim = LIMITS.get(name)
        passed = None if lim is None else t <= lim
        ok &= passed is not False
        rows.append({"step": name, "median": f"{t * 1e3:.4f} ms" if t >= 1e-4 else f"{t * 1e6:.2f} us",
                     "limit": "-" if lim is None else (f"{lim * 1e3:g} ms" if lim >= 1e-3 else f"{lim * 1e6:g} us"),
                     "ok": "-" if passed is None else ("yes" if passed else "no")})
    print(f"volumetric table on {m.name}: pose-aware model of order {rom.order} ({len(rom.output_names)} outputs, "
          f"{len(rom.meta['poses']['poses'])} support poses), {op.grid.n_points} support points, medians of "
          f"{a.repeats} runs")
    print(table(rows, ["step", "median", "limit", "ok"]))
    print(jsonio.dumps({"benchmark": "volumetric_speed", "element_size_mm": a.element_size, "order": rom.order,
                        "outputs": len(rom.output_names), "support_points": op.grid.n_points,
                        "blas": "all threads" if a.all_blas_threads else "one thread",
                        "build_s": build_s, "within_limits": ok, "median_s": times, **extra}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
