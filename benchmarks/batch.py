"""Benchmark: FE load-case batches on 1 and 2 workers, and the overhead per task.

Throughput: ``--cases`` load cases of ``--hours`` at ``--dt`` on the demonstrator at ``--element-size-mm``
(FE-bound: the back-solves of 15k nodes at 80 mm), run by ``run_batch`` on

* the local process pool with 1 and 2 workers,
* a Dask LocalCluster with 1 and 2 workers (this package's worker environment),
* a Dask LocalCluster with 2 workers and Dask's default worker environment (MALLOC_TRIM_THRESHOLD_=65536),

each timed from the call to the last result, pool or cluster start and one model build per worker included.
Per-task overhead: ``--tiny`` two-row load cases on an already warm single worker (model built, pool or
cluster running): (wall − Σ task compute) / tasks.

Prints tables and a final JSON line::

    python benchmarks/batch.py [--element-size-mm 80] [--cases 8] [--hours 4] [--dt 60] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import time


def table(rows: list[dict], cols: list[str]) -> str:
    w = [max(len(c), *(len(f"{r[c]}") for r in rows)) for c in cols]
    line = " | ".join(c.ljust(k) for c, k in zip(cols, w))
    out = [line, "-+-".join("-" * k for k in w)]
    out += [" | ".join(f"{r[c]}".ljust(k) for c, k in zip(cols, w)) for r in rows]
    return "\n".join(out)


def throughput(machine, cases, element_size_mm: float, config: str, workers: int) -> dict:
    from hybridcomp.fem.batch import run_batch

    t0 = time.perf_counter()
    if config == "dask-default-env":  # a LocalCluster as Dask starts it: MALLOC_TRIM_THRESHOLD_=65536 in workers
        import distributed

        with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=":0",
                                      host="127.0.0.1") as cluster, distributed.Client(cluster) as client:
            res = run_batch(machine, cases, element_size_mm=element_size_mm, executor=client)
    else:
        res = run_batch(machine, cases, element_size_mm=element_size_mm,
                        executor="process" if config == "process" else "local", workers=workers)
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "compute_s": sum(r.compute_s for r in res.values()),
            "workers_used": len({r.worker for r in res.values()})}


def overhead(machine, tiny, element_size_mm: float, config: str) -> dict:
    """Per-task overhead on one warm worker."""
    from hybridcomp.fem.batch import dask_client, process_pool, run_batch

    def measure(executor):
        run_batch(machine, dict(list(tiny.items())[:2]), element_size_mm=element_size_mm, executor=executor)  # warm
        t0 = time.perf_counter()
        res = run_batch(machine, tiny, element_size_mm=element_size_mm, executor=executor)
        wall = time.perf_counter() - t0
        compute = sum(r.compute_s for r in res.values())
        return {"per_task_ms": 1e3 * wall / len(tiny), "overhead_ms": 1e3 * (wall - compute) / len(tiny),
                "compute_ms": 1e3 * compute / len(tiny)}

    if config == "serial":
        return measure("serial")
    if config == "process":
        with process_pool(1) as pool:
            return measure(pool)
    with dask_client("local", workers=1) as client:
        return measure(client)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--element-size-mm", type=float, default=80.0)
    p.add_argument("--cases", type=int, default=8)
    p.add_argument("--hours", type=float, default=4.0)
    p.add_argument("--dt", type=float, default=60.0)
    p.add_argument("--tiny", type=int, default=200, help="two-row load cases for the per-task overhead")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--skip-default-env", action="store_true", help="leave out the run with Dask's default environment")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("distributed").setLevel(logging.WARNING)

    from hybridcomp.fem.loads import Loads, example_loads
    from hybridcomp.models import load_machine

    machine = load_machine("vmc800")
    cases = {f"c{i:03d}": example_loads(machine, duration_h=a.hours, dt_s=a.dt, seed=i) for i in range(a.cases)}
    day = example_loads(machine, duration_h=1.0, dt_s=a.dt, seed=0)
    tiny = {f"t{i:04d}": Loads(day.time_s[:2], day.values[:2], day.names) for i in range(a.tiny)}

    configs = [("process", 1), ("process", 2), ("local", 1), ("local", 2)]
    if not a.skip_default_env:
        configs.append(("dask-default-env", 2))
    rows, results = [], []
    base = {}
    for config, workers in configs:
        runs = [throughput(machine, cases, a.element_size_mm, config, workers) for _ in range(a.repeats)]
        wall = statistics.median(r["wall_s"] for r in runs)
        compute = statistics.median(r["compute_s"] for r in runs)
        if workers == 1:
            base[config] = wall
        ref = base.get(config if config != "dask-default-env" else "local")
        speedup = ref / wall if ref else float("nan")
        results.append({"executor": config, "workers": workers, "wall_s": wall, "task_compute_s": compute,
                        "cases_per_min": 60 * a.cases / wall, "speedup_vs_1_worker": speedup,
                        "walls_s": [r["wall_s"] for r in runs]})
        rows.append({"executor": "dask LocalCluster" if config == "local" else
                     "dask LocalCluster, Dask default env" if config == "dask-default-env" else "process pool",
                     "workers": workers, "wall [s]": f"{wall:.2f}", "cases/min": f"{60 * a.cases / wall:.1f}",
                     "speed-up": f"{speedup:.2f}", "Σ task compute [s]": f"{compute:.1f}"})
    print(f"{a.cases} load cases of {a.hours} h at dt = {a.dt} s, vmc800 at {a.element_size_mm} mm; "
          f"median of {a.repeats}; {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(table(rows, list(rows[0])))

    over_rows, over = [], []
    for config in ("serial", "process", "local"):
        runs = [overhead(machine, tiny, a.element_size_mm, config) for _ in range(a.repeats)]
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        over.append({"executor": config, **med})
        over_rows.append({"executor": {"serial": "serial (this process)", "process": "process pool",
                                       "local": "dask LocalCluster"}[config],
                          "per task [ms]": f"{med['per_task_ms']:.2f}", "overhead [ms]": f"{med['overhead_ms']:.2f}",
                          "task compute [ms]": f"{med['compute_ms']:.2f}"})
    print(f"\nper-task overhead: {a.tiny} two-row load cases on one warm worker; median of {a.repeats}")
    print(table(over_rows, list(over_rows[0])))
    print(json.dumps({"benchmark": "batch", "machine": "vmc800", "element_size_mm": a.element_size_mm,
                      "cases": a.cases, "hours": a.hours, "dt_s": a.dt, "cores": os.cpu_count(),
                      "load_average": os.getloadavg()[0], "throughput": results, "overhead": over}))


if __name__ == "__main__":
    main()
