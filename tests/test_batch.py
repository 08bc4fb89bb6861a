"""FE load-case batches: every executor gives the serial results; killed workers lose and duplicate nothing.

The reference is a serial run in a fresh process with one BLAS thread, the setting every worker process
runs with.  The results are compared to round-off, not bitwise: with the same thread count on both sides
the drift rows still differed by 2.5e-12 relative between processes on one host (an AMD EPYC; OpenBLAS
picks kernels by CPU and memory alignment, and the AMG-CG adjoint solve sums in the order its products
give).  What must be exact stays exact: which cases came back, once each, the time axes, and one file per
case with nothing left over.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.cli import main
from hybridcomp.fem.batch import WORKER_ENVIRONMENT, BatchError, run_batch
from hybridcomp.fem.loads import Loads, example_loads, write_loads, write_outputs

ELEMENT_SIZE_MM = 150.0
N_CASES = 8
CASE_ARGS = {"duration_h": 4.0, "dt_s": 60.0}  # 241 steps, about 0.15 s per case on the coarse mesh


def make_cases(machine) -> dict[str, Loads]:
    return {f"case{i:02d}": example_loads(machine, seed=i, **CASE_ARGS) for i in range(N_CASES)}


@pytest.fixture(scope="module")
def cases(machine):
    return make_cases(machine)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """Serial run of the batch in a fresh process with one BLAS thread: name -> (sensors_degC, drift_um, time_s)."""
    out = tmp_path_factory.mktemp("reference") / "reference.npz"
    code = textwrap.dedent(f"""
        import numpy as np
        from hybridcomp.models import load_machine
        from hybridcomp.fem.batch import run_batch
        from test_batch import make_cases
        m = load_machine("vmc800")
        res = run_batch(m, make_cases(m), element_size_mm={ELEMENT_SIZE_MM}, executor="serial")
        arrays = {{}}
        for name, r in res.items():
            arrays[name + "/sensors"] = r.sensors_degC
            arrays[name + "/drift"] = r.drift_um
            arrays[name + "/time"] = r.time_s
        np.savez({str(out)!r}, **arrays)
    """)
    # this test folder (make_cases) and what the root conftest put first: this checkout, installed or not
    env = {**os.environ, **WORKER_ENVIRONMENT,
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=Path(__file__).parent, timeout=120)
    data = np.load(out)
    return {n: (data[n + "/sensors"], data[n + "/drift"], data[n + "/time"]) for n in make_cases_names()}


def make_cases_names() -> list[str]:
    return [f"case{i:02d}" for i in range(N_CASES)]


# round-off of a solve in another process: 2.5e-12 relative measured; a wrong case or step differs by >1e-3
ROUND_OFF = {"rtol": 1e-9, "atol": 1e-9}


def assert_identical(results, reference):
    """Every case once, in order, with the reference's time axis exactly and its values to round-off."""
    assert list(results) == make_cases_names()
    for name, (sensors, drift, t) in reference.items():
        r = results[name]
        assert r.name == name
        np.testing.assert_array_equal(r.time_s, t)
        np.testing.assert_allclose(r.sensors_degC, sensors, **ROUND_OFF)
        np.testing.assert_allclose(r.drift_um, drift, **ROUND_OFF)


def assert_files_once(out: Path, reference, sensor_names, tmp_path: Path):
    """Exactly one outputs CSV per case (no temporaries left), each as the reference would be written.

    Header, row count and time column are compared exactly; the values (written to 6 decimals) to one unit of
    the last written digit, since a round-off difference can flip the rounding of a value.
    """
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"{n}.csv" for n in reference] + ["batch.json"])
    for name, (sensors, drift, t) in reference.items():
        expected = tmp_path / f"expected_{name}.csv"
        write_outputs(expected, t, sensor_names, sensors, drift)
        got_lines = (out / f"{name}.csv").read_text().splitlines()
        want_lines = expected.read_text().splitlines()
        assert got_lines[0] == want_lines[0] and len(got_lines) == len(want_lines), name
        got = np.array([[float(v) for v in line.split(",")] for line in got_lines[1:]])
        want = np.array([[float(v) for v in line.split(",")] for line in want_lines[1:]])
        np.testing.assert_array_equal(got[:, 0], want[:, 0])
        np.testing.assert_allclose(got[:, 1:], want[:, 1:], rtol=0, atol=1.0001e-6)
    info = json.loads((out / "batch.json").read_text())
    assert sorted(info["cases"]) == sorted(reference) and info["complete"] is True


@pytest.mark.slow
def test_process_pool_matches_serial_builds_once_per_worker(machine, cases, reference, tmp_path):
    out = tmp_path / "out"
    res = run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor="process", workers=2, out_dir=out)
    assert_identical(res, reference)
    assert_files_once(out, reference, res["case00"].sensor_names, tmp_path)
    workers = {r.worker for r in res.values()}
    builders = [r.worker for r in res.values() if r.built_model]
    assert len(workers) == 2  # both workers took cases
    assert sorted(builders) == sorted(workers)  # each built the operators exactly once and reused them


@pytest.mark.slow
def test_serial_in_this_process_agrees_to_round_off(machine, cases, reference):
    res = run_batch(machine, dict(list(cases.items())[:2]), element_size_mm=ELEMENT_SIZE_MM, executor="serial")
    for name, r in res.items():
        sensors, drift, _ = reference[name]
        # this process may run more BLAS threads than the reference: summation order, nothing else
        np.testing.assert_allclose(r.drift_um, drift, rtol=0, atol=1e-9)
        np.testing.assert_allclose(r.sensors_degC, sensors, rtol=0, atol=1e-9)
    assert [r.built_model for r in res.values()].count(True) <= 1


@pytest.mark.slow
def test_process_pool_worker_killed_mid_batch_loses_and_duplicates_nothing(machine, cases, reference, tmp_path, caplog):
    killed = []

    def kill_busy_worker(r):
        if not killed:  # the worker that delivered the first case is already simulating its next one
            pid = int(r.worker.rsplit(":", 1)[1])
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    out = tmp_path / "out"
    res = run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor="process", workers=2, out_dir=out,
                    on_result=kill_busy_worker)
    assert killed
    assert "a worker process died" in caplog.text  # the pool broke and the unfinished cases were resubmitted
    assert_identical(res, reference)
    assert_files_once(out, reference, res["case00"].sensor_names, tmp_path)
    # the killed worker delivered the case that triggered the kill (and at most the one it was finishing)
    assert 1 <= sum(int(r.worker.rsplit(":", 1)[1]) in killed for r in res.values()) <= 2


@pytest.mark.slow
def test_process_pool_without_restarts_reports_the_unfinished_cases(machine, cases):
    killed = []

    def kill_busy_worker(r):
        if not killed:
            killed.append(int(r.worker.rsplit(":", 1)[1]))
            os.kill(killed[0], signal.SIGKILL)

    with pytest.raises(BatchError, match=r"died 1 time\(s\) \(max_restarts=0\); \d+ load cases unfinished"):
        run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor="process", workers=2, max_restarts=0,
                  on_result=kill_busy_worker)


@pytest.mark.slow
def test_dask_local_cluster_matches_serial(machine, cases, reference, tmp_path):
    pytest.importorskip("distributed", reason="needs dask.distributed (extra 'dask')")
    out = tmp_path / "out"
    res = run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor="local", workers=2, out_dir=out)
    assert_identical(res, reference)
    assert_files_once(out, reference, res["case00"].sensor_names, tmp_path)
    assert len({r.worker for r in res.values()}) == 2
    # warm-up built the operators on each worker before the cases: no case had to build them
    assert not any(r.built_model for r in res.values())


@pytest.mark.slow
def test_local_cluster_workers_run_one_blas_thread_without_malloc_trim(monkeypatch):
    pytest.importorskip("distributed", reason="needs dask.distributed (extra 'dask')")
    from hybridcomp.fem.batch import dask_client

    for name in WORKER_ENVIRONMENT:  # the workers get them from the cluster's configuration, not from the test run's
        monkeypatch.delenv(name, raising=False)

    with dask_client("local", workers=1) as client:
        for name, value in {"MALLOC_TRIM_THRESHOLD_": None, **WORKER_ENVIRONMENT}.items():
            assert set(client.run(os.getenv, name).values()) == {value}, name


# --------------------------------------------------------------------------- a real dask scheduler + 2 workers


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
    else:  # the session leader is gone; make sure its children are too
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.fixture(scope="module")
def dask_cli_cluster(tmp_path_factory):
    """``dask scheduler`` + two ``dask worker`` processes on 127.0.0.1 (free ports); yields the scheduler address."""
    pytest.importorskip("distributed", reason="needs dask.distributed (extra 'dask')")
    tmp = tmp_path_factory.mktemp("dask")
    sched_file = tmp / "scheduler.json"
    # the documented way to start workers: glibc's dynamic mmap threshold left alone (no MALLOC_TRIM_THRESHOLD_)
    # and no thread counts of the test run's own (the root conftest's one BLAS thread): the workers' come from Dask
    env = {**{k: v for k, v in os.environ.items() if k not in WORKER_ENVIRONMENT},
           "DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON": '{"MALLOC_TRIM_THRESHOLD_": None}'}
    dask = [sys.executable, "-m"]
    procs = []
    logs = []

    def start(args, name):
        log = (tmp / f"{name}.log").open("w")
        logs.append(log)
        procs.append(subprocess.Popen(dask + args, env=env, cwd=tmp, stdout=log, stderr=subprocess.STDOUT,
                                      start_new_session=True))

    try:
        start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address", ":0",
               "--scheduler-file", str(sched_file)], "scheduler")
        deadline = time.monotonic() + 60
        while not sched_file.exists() or not sched_file.read_text().strip():
            if time.monotonic() > deadline or procs[0].poll() is not None:
                pytest.fail(f"dask scheduler did not start: {(tmp / 'scheduler.log').read_text()[-2000:]}")
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        for k in range(2):
            start(["distributed.cli.dask_worker", address, "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard",
                   "--name", f"w{k}", "--local-directory", str(tmp / f"w{k}")], f"worker{k}")
        from distributed import Client

        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            _stop(p)
        for log in logs:
            log.close()


@pytest.mark.slow
def test_dask_scheduler_and_two_workers_match_serial_bitwise(machine, cases, reference, dask_cli_cluster, tmp_path):
    from distributed import Client

    assert dask_cli_cluster.startswith("tcp://127.0.0.1:")
    with Client(dask_cli_cluster, timeout="30s") as client:
        for name, value in {"MALLOC_TRIM_THRESHOLD_": None, **WORKER_ENVIRONMENT}.items():
            assert set(client.run(os.getenv, name).values()) == {value}, name
    out = tmp_path / "out"
    res = run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor=dask_cli_cluster, out_dir=out)
    assert_identical(res, reference)
    assert_files_once(out, reference, res["case00"].sensor_names, tmp_path)
    assert len({r.worker for r in res.values()}) == 2


@pytest.mark.slow
def test_cli_batch_run_on_a_dask_scheduler_address_and_on_the_pool(machine, cases, dask_cli_cluster, tmp_path, capsys):
    loads_dir = tmp_path / "loads"
    for name, loads in list(cases.items())[:3]:
        write_loads(loads_dir / f"{name}.csv", loads)
    common = ["batch", "run", str(loads_dir), "--machine", "vmc800", "--element-size-mm", str(ELEMENT_SIZE_MM),
              "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "dask"), "--scheduler", dask_cli_cluster]) == 0, capsys.readouterr().err
    assert main([*common, "--out", str(tmp_path / "pool")]) == 0, capsys.readouterr().err  # the default: a pool
    for name in ("case00", "case01", "case02"):
        assert (tmp_path / "dask" / f"{name}.csv").read_bytes() == (tmp_path / "pool" / f"{name}.csv").read_bytes()
    info = json.loads((tmp_path / "dask" / "batch.json").read_text())
    assert info["executor"] == dask_cli_cluster and sorted(info["cases"]) == ["case00", "case01", "case02"]


@pytest.mark.slow
def test_dask_worker_killed_mid_batch_is_retried_without_duplicates(machine, cases, reference, dask_cli_cluster,
                                                                    tmp_path):
    from distributed import Client

    killed = {}

    with Client(dask_cli_cluster, timeout="30s") as client:

        def kill_busy_worker(r):
            if killed:
                return
            processing = client.processing()
            for address, keys in processing.items():
                if keys:
                    pid = client.run(os.getpid, workers=[address])[address]
                    os.kill(pid, signal.SIGKILL)  # the worker process; its nanny starts a new one
                    killed["pid"] = pid
                    killed["cases"] = {str(k).split("-")[2] for k in keys}
                    return

        out = tmp_path / "out"
        res = run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor=client, out_dir=out,
                        on_result=kill_busy_worker)
        client.wait_for_workers(2, timeout=60)  # leave the cluster whole for other tests
    assert killed and killed["cases"]
    assert_identical(res, reference)
    assert_files_once(out, reference, res["case00"].sensor_names, tmp_path)
    for name in killed["cases"]:  # what the dead worker was running was computed again elsewhere
        assert int(res[name].worker.rsplit(":", 1)[1]) != killed["pid"], name


@pytest.mark.slow
def test_dask_batch_survives_all_workers_killed_and_restarted(machine, cases, reference, dask_cli_cluster, tmp_path):
    from distributed import Client

    killed = []
    with Client(dask_cli_cluster, timeout="30s") as client:

        def kill_all_workers(r):
            if not killed:
                for pid in client.run(os.getpid).values():
                    os.kill(pid, signal.SIGKILL)  # both worker processes; their nannies start new ones
                    killed.append(pid)

        out = tmp_path / "out"
        res = run_batch(machine, cases, element_size_mm=ELEMENT_SIZE_MM, executor=client, out_dir=out,
                        on_result=kill_all_workers)
        client.wait_for_workers(2, timeout=60)
    assert len(killed) == 2
    assert_identical(res, reference)
    assert_files_once(out, reference, res["case00"].sensor_names, tmp_path)
    after = [r for r in res.values() if int(r.worker.rsplit(":", 1)[1]) not in killed]
    assert any(r.built_model for r in after)  # a new worker built the operators again


# --------------------------------------------------------------------------- CLI and bad input


def test_cli_batch_errors_name_the_problem(tmp_path, capsys):
    assert main(["batch", "run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "loads directory not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["batch", "run", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "no loads CSV" in capsys.readouterr().err
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "c1.csv").write_text("time_s,nonsense_W\n0,1\n60,1\n")
    assert main(["batch", "run", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "c1.csv" in err and "nonsense_W" in err
    assert main(["batch", "run", str(bad), "--out", str(tmp_path / "o"), "--scheduler", "nowhere"]) == 2
    assert "--scheduler 'nowhere'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_run_batch_rejects_bad_input(machine, cases):
    one = {"a": cases["case00"]}
    with pytest.raises(ValueError, match="executor 'bogus'"):
        run_batch(machine, one, executor="bogus")
    with pytest.raises(ValueError, match="load case name '../x'"):
        run_batch(machine, {"../x": cases["case00"]}, executor="serial")
    short = Loads(cases["case00"].time_s[:1], cases["case00"].values[:1], cases["case00"].names)
    with pytest.raises(ValueError, match="load case 'a': needs at least two rows"):
        run_batch(machine, {"a": short}, executor="serial")
    unknown = Loads(cases["case00"].time_s, cases["case00"].values, ("nonsense_W", *cases["case00"].names[1:]))
    with pytest.raises(ValueError, match="load case 'a': loads: column 'nonsense_W' is not an input of machine 'vmc800'"):
        run_batch(machine, {"a": unknown}, executor="serial")
    with pytest.raises(ValueError, match="theta"):
        run_batch(machine, one, theta=0.2)
    with pytest.raises(TypeError, match="executor"):
        run_batch(machine, one, executor=42)
    with pytest.raises(ValueError, match="outside the travel"):
        run_batch(machine, one, pose_mm={"X": 1e6}, executor="serial")


class BrokenLoads(Loads):
    """Loads that pass the up-front checks but fail inside the worker."""

    def resample(self, dt_s):
        raise ValueError("planted failure")


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["serial", "process"])
def test_a_failing_case_names_itself(machine, cases, executor):
    c = cases["case00"]
    bad = BrokenLoads(c.time_s, c.values, c.names)
    with pytest.raises(BatchError, match="load case 'b' failed: planted failure"):
        run_batch(machine, {"a": cases["case01"], "b": bad}, element_size_mm=ELEMENT_SIZE_MM, executor=executor,
                  workers=1, dt_s=600.0)


@pytest.mark.slow
def test_loads_in_another_column_order_or_with_columns_missing_give_the_same_results(machine, cases):
    c = cases["case00"]
    values = c.values.copy()
    values[:, :3] = 0.0  # three heat inputs off
    values[:, -1] = machine.reference_temperature_degC  # the last zone at the reference temperature
    c = Loads(c.time_s, values, c.names)
    reversed_order = Loads(c.time_s, c.values[:, ::-1], tuple(reversed(c.names)))
    keep = list(range(3, len(c.names) - 1))
    zeros_dropped = Loads(c.time_s, c.values[:, keep], tuple(c.names[j] for j in keep))
    res = run_batch(machine, {"a": c, "b": reversed_order, "c": zeros_dropped}, element_size_mm=ELEMENT_SIZE_MM,
                    executor="serial")
    for name in ("b", "c"):
        np.testing.assert_array_equal(res[name].drift_um, res["a"].drift_um)
        np.testing.assert_array_equal(res[name].sensors_degC, res["a"].sensors_degC)


@pytest.mark.slow
def test_a_machine_changed_in_memory_does_not_reuse_the_cached_model(machine, cases):
    import dataclasses

    one = {"case00": cases["case00"]}
    first = run_batch(machine, one, element_size_mm=ELEMENT_SIZE_MM, executor="serial")["case00"]
    again = run_batch(machine, one, element_size_mm=ELEMENT_SIZE_MM, executor="serial")["case00"]
    assert not again.built_model  # the same machine, pose and mesh: the cached operators
    np.testing.assert_array_equal(again.drift_um, first.drift_um)
    z0 = machine.zones[0]
    cooler = dataclasses.replace(machine, zones=(dataclasses.replace(z0, h_W_m2K=2 * z0.h_W_m2K), *machine.zones[1:]))
    assert cooler.sha256 == machine.sha256  # same file hash, different physics
    changed = run_batch(cooler, one, element_size_mm=ELEMENT_SIZE_MM, executor="serial")["case00"]
    assert changed.built_model
    assert np.abs(changed.sensors_degC - first.sensors_degC).max() > 1e-3


@pytest.mark.slow
def test_resume_computes_only_the_missing_cases_and_refuses_other_settings(machine, cases, tmp_path):
    three = dict(list(cases.items())[:3])
    out = tmp_path / "out"
    first = run_batch(machine, three, element_size_mm=ELEMENT_SIZE_MM, executor="serial", out_dir=out)
    before = {n: (out / f"{n}.csv").read_bytes() for n in three}
    # an interrupted run: one case not written yet, batch.json not marked complete
    (out / "case01.csv").unlink()
    info = json.loads((out / "batch.json").read_text())
    (out / "batch.json").write_text(json.dumps({"settings": info["settings"], "complete": False}))
    again = run_batch(machine, three, element_size_mm=ELEMENT_SIZE_MM, executor="serial", out_dir=out, resume=True)
    assert [r.worker for r in again.values()] == ["file", first["case01"].worker, "file"]
    assert {n: (out / f"{n}.csv").read_bytes() for n in three} == before
    for name in ("case00", "case02"):  # read back: the written 6 decimals
        np.testing.assert_allclose(again[name].drift_um, first[name].drift_um, rtol=0, atol=5e-7)
        np.testing.assert_array_equal(again[name].time_s, first[name].time_s)
    assert json.loads((out / "batch.json").read_text())["complete"] is True
    with pytest.raises(ValueError, match="computed with theta = 1.0, this batch has 0.5"):
        run_batch(machine, three, element_size_mm=ELEMENT_SIZE_MM, theta=0.5, executor="serial", out_dir=out,
                  resume=True)
    with pytest.raises(ValueError, match="computed with element_size_mm = 150.0, this batch has 120.0"):
        run_batch(machine, three, element_size_mm=120.0, executor="serial", out_dir=out, resume=True)

    # a fresh run with other settings, interrupted after its first case: the older outputs cannot pass for its own
    def interrupt(r):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(machine, three, element_size_mm=ELEMENT_SIZE_MM, theta=0.5, executor="serial", out_dir=out,
                  on_result=interrupt)
    assert sorted(p.name for p in out.iterdir()) == ["batch.json", "case00.csv"]
    resumed = run_batch(machine, three, element_size_mm=ELEMENT_SIZE_MM, theta=0.5, executor="serial", out_dir=out,
                        resume=True)
    assert [r.worker == "file" for r in resumed.values()] == [True, False, False]
