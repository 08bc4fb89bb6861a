"""Benchmark: FE load-case batches on 1 and 2 workers, and the overhead per task.

Throughput: ``--cases`` load cases of ``--hours`` at ``--dt`` on the demonstrator at ``--element-size-mm``
(FE-bound: the back-solves of 15k nodes at 80 mm), run by ``run_batch`` on

* the local process pool with 1 and 2 workers,
* a Dask LocalCluster with 1 and 2 workers (this package's worker environment),
* a Dask LocalCluster with 2 workers and Dask's default worker environment (MALLOC_TRIM_THRESHOLD_=65536),

each executor started once (its start and the model build on each worker reported apart), then the batch
timed on the warm executors, the configurations interleaved per repeat so that a busy moment of a shared
machine hits all alike.  "core share" is the workers' CPU time over (wall × workers): 1.0 when each
worker had a core to itself; below 1 the machine was busy with other work and the speed-up shows that.
Per-task overhead: ``--tiny`` two-row load cases on one warm worker:
(wall − Σ task compute) / tasks.

Prints tables and a final JSON line::

    python benchmarks/batch.py [--element-size-mm 80] [--cases 8] [--hours 4] [--dt 60] [--repeats 3]
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import statistics
import time

from hybridcomp.models import jsonio

from _table import table  # benchmarks/_table.py, beside this script


@contextlib.contextmanager
def executor(config: str, workers: int):
    """A running executor: the local process pool, a LocalCluster as run_batch starts it, or one with Dask's
    default worker environment (MALLOC_TRIM_THRESHOLD_=65536)."""
    from hybridcomp.fem.batch import dask_client, process_pool

    if config == "process":
        with process_pool(workers) as pool:
            yield pool
    elif config == "local":
        with dask_client("local", workers=workers) as client:
            yield client
    else:
        import distributed

        with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=":0",
                                      host="127.0.0.1") as cluster, distributed.Client(cluster) as client:
            yield client


def batch(machine, cases, element_size_mm: float, ex) -> dict:
    from hybridcomp.fem.batch import run_batch

    t0 = time.perf_counter()
    res = run_batch(machine, cases, element_size_mm=element_size_mm, executor=ex)
    wall = time.perf_counter() - t0
    compute = sum(r.compute_s for r in res.values())
    workers = len({r.worker for r in res.values()})
    cpu = sum(r.cpu_s for r in res.values())
    return {"wall_s": wall, "compute_s": compute, "cpu_s": cpu, "core_share": cpu / (wall * workers), "workers_used": workers,
            "per_task_ms": 1e3 * wall / len(cases), "overhead_ms": 1e3 * (wall - compute) / len(cases),
            "compute_ms": 1e3 * compute / len(cases)}


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
    with contextlib.suppress(ImportError):
        import distributed  # noqa: F401 - importing it sets its loggers to INFO; quiet them afterwards

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
    names = {"process": "process pool", "local": "dask LocalCluster", "dask-default-env": "dask, Dask default env"}
    runs: dict[tuple, list[dict]] = {c: [] for c in configs}
    tiny_runs: dict[str, list[dict]] = {"serial": [], "process": [], "local": []}
    start_s = {}
    with contextlib.ExitStack() as stack:
        executors = {}
        for c in configs:  # start every executor and build the operators on each of its workers once
            t0 = time.perf_counter()
            executors[c] = stack.enter_context(executor(*c))
            batch(machine, dict(list(tiny.items())[: 2 * c[1]]), a.element_size_mm, executors[c])
            start_s[c] = time.perf_counter() - t0
        for _ in range(a.repeats):  # interleaved, so a busy moment of a shared machine hits every executor alike
            for c in configs:
                runs[c].append(batch(machine, cases, a.element_size_mm, executors[c]))
            tiny_runs["serial"].append(batch(machine, tiny, a.element_size_mm, "serial"))
            tiny_runs["process"].append(batch(machine, tiny, a.element_size_mm, executors[("process", 1)]))
            tiny_runs["local"].append(batch(machine, tiny, a.element_size_mm, executors[("local", 1)]))

    rows, results = [], []
    for c in configs:
        config, workers = c
        wall = statistics.median(r["wall_s"] for r in runs[c])
        one = statistics.median(r["wall_s"] for r in runs[("local" if config != "process" else "process", 1)])
        results.append({"executor": config, "workers": workers, "start_and_build_s": start_s[c], "wall_s": wall,
                        "cases_per_min": 60 * a.cases / wall, "speedup_vs_1_worker": one / wall,
                        "task_compute_s": statistics.median(r["compute_s"] for r in runs[c]),
                        "task_cpu_s": statistics.median(r["cpu_s"] for r in runs[c]),
                        "core_share": statistics.median(r["core_share"] for r in runs[c]),
                        "walls_s": [r["wall_s"] for r in runs[c]]})
        rows.append({"executor": names[config], "workers": workers, "start + build [s]": f"{start_s[c]:.1f}",
                     "batch wall [s]": f"{wall:.2f}", "cases/min": f"{60 * a.cases / wall:.1f}",
                     "speed-up": f"{one / wall:.2f}",
                     "Σ task CPU [s]": f"{statistics.median(r['cpu_s'] for r in runs[c]):.1f}",
                     "core share": f"{statistics.median(r['core_share'] for r in runs[c]):.2f}"})
    print(f"{a.cases} load cases of {a.hours} h at dt = {a.dt} s, vmc800 at {a.element_size_mm} mm, on warm "
          f"executors; median of {a.repeats}; {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    print(table(rows, list(rows[0])))

    over_rows, over = [], []
    for config, rs in tiny_runs.items():
        med = {k: statistics.median(r[k] for r in rs) for k in ("per_task_ms", "overhead_ms", "compute_ms")}
        over.append({"executor": config, **med})
        over_rows.append({"executor": {"serial": "serial (this process)", "process": "process pool",
                                       "local": "dask LocalCluster"}[config],
                          "per task [ms]": f"{med['per_task_ms']:.2f}", "overhead [ms]": f"{med['overhead_ms']:.2f}",
                          "task compute [ms]": f"{med['compute_ms']:.2f}"})
    print(f"\nper-task overhead: {a.tiny} two-row load cases on one warm worker; median of {a.repeats}")
    print(table(over_rows, list(over_rows[0])))
    print(jsonio.dumps({"benchmark": "batch", "machine": "vmc800", "element_size_mm": a.element_size_mm,
                      "cases": a.cases, "hours": a.hours, "dt_s": a.dt, "cores": os.cpu_count(),
                      "load_average": os.getloadavg()[0], "throughput": results, "overhead": over}))


if __name__ == "__main__":
    main()
