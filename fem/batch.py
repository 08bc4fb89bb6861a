"""Batches of FE load cases: serially, on a local process pool, or on a Dask cluster.

One machine at one pose, many load cases (CD training data, CD regeneration,
the diagnosis' FE confirmation).  The expensive part is the model: meshing,
assembly, the elastic adjoint solves for the drift rows and the factorisation
of the stepping matrix.  Each worker process builds it once and keeps it in a
per-process cache keyed by the machine (its file's SHA-256 and a digest of the
object), the pose and the element size; tasks carry only their loads and the
machine definition (a few kB), never matrices, and the factorisations cached on
the model are reused by every later case with the same time step.

The executor is a seam, not a framework:

* ``"serial"``: in this process, one case after another;
* ``"process"`` (default): a :class:`concurrent.futures.ProcessPoolExecutor`
  whose workers are forked from a clean fork server started with one BLAS /
  OpenMP thread per worker; a worker that dies breaks the pool, so the
  unfinished cases are resubmitted on a fresh pool (up to ``max_restarts``);
* ``"local"``: a Dask ``LocalCluster`` with ``workers`` single-threaded
  worker processes;
* ``"tcp://HOST:PORT"`` (any Dask scheduler address): an existing Dask
  distributed cluster (``dask scheduler`` + ``dask worker``); the scheduler
  reschedules the cases of a worker that dies;
* or an object: a ``concurrent.futures.Executor`` or a ``distributed.Client``.

Results are returned to the caller, which writes one outputs CSV per case
(``OUT/<case>.csv``, the ``outputs.csv`` columns) through a temporary file and
an atomic rename, so a case is written exactly once and a crash never leaves a
half-written file; the workers need no shared file system.  ``OUT/batch.json``
holds the settings from the start and the cases at the end, so an interrupted
batch can be resumed (``resume=True``): the cases already written are kept,
only the missing ones run.

Reproducibility: the FE arithmetic is deterministic for a given number of BLAS
threads, so every executor gives bitwise identical results when its processes
run the same number of BLAS threads (the pool and ``"local"`` use one; Dask's
nanny sets one by default).  A run in a process with more BLAS threads differs
by round-off only (CHOLMOD's supernodal kernels sum in another order; about
1e-12 µm measured on the demonstrator).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import hashlib
import json
import logging
import multiprocessing
import os
import pickle
import re
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.loads import Loads, LoadsFileError, in_model_order, input_columns, read_loads, write_outputs
from hybridcomp.fem.stepping import DEFAULT_THETA, check_scheme
from hybridcomp.models.layout import DRIFT_COLUMNS, LoadsColumnError, temperature_column
from hybridcomp.models.machine import Machine
from hybridcomp.models.toml import open_text
from hybridcomp.safeio import write_text_atomic

log = logging.getLogger(__name__)

#: environment of every pool worker: one BLAS / OpenMP thread (2 workers on 2 cores must not oversubscribe)
WORKER_ENVIRONMENT = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: Dask settings for clusters started here: one BLAS thread per worker, and glibc's dynamic mmap threshold
#: left alone (Dask's default MALLOC_TRIM_THRESHOLD_=65536 made scipy work 2.4x slower in workers in one
#: measurement; on FE batches with CHOLMOD no difference was measured, so this is a precaution)
DASK_CONFIG = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    **{f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in WORKER_ENVIRONMENT.items()},
}

MAX_CACHED_MODELS = 4
_FORK_SERVER_THREADS: int | None = None
_MALLOC_WARNED = False
_CASE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class BatchError(HybridcompError, RuntimeError):
    """A batch could not be completed; the message names the case and the cause."""


@dataclass(frozen=True)
class ModelSpec:
    """What identifies the assembled operators: machine, pose and element size.

    Attributes
    ----------
    machine : the validated machine definition
    pose_mm : axis positions, complete and sorted by axis name [mm]
    element_size_mm : largest element edge [mm]; None means the machine file's
    machine_digest : SHA-256 of the pickled machine object; a machine derived in memory from a file
        (changed coefficients, same file hash) must not reuse the file's cached model
    """

    machine: Machine
    pose_mm: tuple[tuple[str, float], ...]
    element_size_mm: float | None
    machine_digest: str = ""

    @property
    def key(self) -> tuple:
        return (self.machine.sha256, self.machine_digest, self.pose_mm, self.element_size_mm)


@dataclass(frozen=True)
class SimulationOptions:
    """Options of :meth:`ThermoElasticModel.simulate` shared by all cases.

    Attributes
    ----------
    scheme : ``"theta"`` (the θ-method on each case's times) or ``"trbdf2"`` (TR-BDF2 to the default tolerance)
    theta : θ of the θ-method, in [0.5, 1]; None for TR-BDF2
    initial : ``"steady"`` (steady state of the first loads row) or ``"reference"``
    dt_s : resample every case to this uniform step [s]; None keeps each case's own times
    """

    scheme: str = "theta"
    theta: float | None = DEFAULT_THETA
    initial: str = "steady"
    dt_s: float | None = None


@dataclass(frozen=True)
class CaseResult:
    """Outputs of one load case.

    Attributes
    ----------
    name : case name
    time_s : output times [s]
    sensor_names : sensor names in column order
    sensors_degC : sensor temperatures (nt × s) [°C]
    drift_um : TCP-minus-table drift dx, dy, dz (nt × 3) [µm]
    worker : ``host:pid`` of the process that computed it
    built_model : whether this task had to build the operators (False: reused from the worker's cache)
    compute_s : wall time of the task inside the worker, model build included [s]
    cpu_s : CPU time of the worker process during the task [s] (below ``compute_s`` when the cores are shared)
    path : the outputs CSV written for it, if any
    """

    name: str
    time_s: np.ndarray
    sensor_names: tuple[str, ...]
    sensors_degC: np.ndarray
    drift_um: np.ndarray
    worker: str
    built_model: bool
    compute_s: float
    cpu_s: float = float("nan")
    path: Path | None = None

    def columns(self) -> dict[str, np.ndarray]:
        """The outputs-CSV columns: ``time_s``, ``<sensor>_degC`` ..., ``dx_um``, ``dy_um``, ``dz_um``."""
        cols = {"time_s": self.time_s}
        cols |= {temperature_column(s): self.sensors_degC[:, j] for j, s in enumerate(self.sensor_names)}
        cols |= {c: self.drift_um[:, j] for j, c in enumerate(DRIFT_COLUMNS)}
        return cols


# --------------------------------------------------------------------------- the worker side

_MODELS: dict[tuple, object] = {}
_MODELS_LOCK = threading.Lock()
_SIMULATE_LOCKS: dict[tuple, threading.Lock] = {}


def cached_model(spec: ModelSpec):
    """The assembled model for ``spec`` from this process's cache, built on first use.

    Returns
    -------
    (ThermoElasticModel, built, lock): ``built`` says whether this call built it; hold ``lock`` while
    simulating (the model's factorisation cache is not shared between threads)
    """
    from hybridcomp.fem.model import build_model

    with _MODELS_LOCK:
        model = _MODELS.pop(spec.key, None)
        built = model is None
        if built:
            t0 = time.perf_counter()
            model = build_model(spec.machine, dict(spec.pose_mm), spec.element_size_mm)
            log.info("process %d built %s (%d nodes) in %.2f s", os.getpid(), spec.machine.name, model.n,
                     time.perf_counter() - t0)
            _SIMULATE_LOCKS.setdefault(spec.key, threading.Lock())
        _MODELS[spec.key] = model  # most recently used last
        while len(_MODELS) > MAX_CACHED_MODELS:
            old = next(iter(_MODELS))
            del _MODELS[old]
            _SIMULATE_LOCKS.pop(old, None)
        lock = _SIMULATE_LOCKS[spec.key]
    return model, built, lock


def clear_model_cache() -> None:
    """Forget this process's cached models (tests and benchmarks)."""
    with _MODELS_LOCK:
        _MODELS.clear()
        _SIMULATE_LOCKS.clear()


def run_case(spec: ModelSpec, options: SimulationOptions, name: str, loads: Loads) -> CaseResult:
    """Simulate one load case on the cached model of ``spec`` (the task every executor runs)."""
    global _MALLOC_WARNED
    t0, c0 = time.perf_counter(), time.process_time()
    if os.environ.get("MALLOC_TRIM_THRESHOLD_") and not _MALLOC_WARNED:
        _MALLOC_WARNED = True
        log.warning("this worker runs with MALLOC_TRIM_THRESHOLD_=%s (Dask's default), which can slow scipy work "
                    "in workers (2.4x measured); start Dask workers with the setting removed (see fem.batch.DASK_CONFIG)",
                    os.environ["MALLOC_TRIM_THRESHOLD_"])
    model, built, lock = cached_model(spec)
    if options.dt_s is not None:
        loads = loads.resample(options.dt_s)
    with lock:  # the model's factorisation cache is not shared between threads of one worker
        res = model.simulate(loads, options.initial, scheme=options.scheme, theta=options.theta)
    return CaseResult(
        name=name,
        time_s=res.time_s,
        sensor_names=model.sensor_names,
        sensors_degC=res.sensors_degC,
        drift_um=res.drift_um,
        worker=f"{socket.gethostname()}:{os.getpid()}",
        built_model=built,
        compute_s=time.perf_counter() - t0,
        cpu_s=time.process_time() - c0,
    )


def warm_up(spec: ModelSpec) -> str:
    """Build the model of ``spec`` in this process (run on every worker before a batch); returns ``host:pid``."""
    cached_model(spec)
    return f"{socket.gethostname()}:{os.getpid()}"


# --------------------------------------------------------------------------- inputs and outputs


def read_loads_dir(directory: str | Path, machine: Machine) -> dict[str, Loads]:
    """Every ``*.csv`` in ``directory`` as a load case named by the file stem, sorted by name."""
    directory = Path(directory)
    if not directory.is_dir():
        raise LoadsFileError(f"{directory}: loads directory not found")
    files = sorted(directory.glob("*.csv"))
    if not files:
        raise LoadsFileError(f"{directory}: no loads CSV (*.csv) in the directory")
    return {p.stem: read_loads(p, machine) for p in files}


def prepare_cases(cases: Mapping[str, Loads], machine: Machine) -> dict[str, Loads]:
    """The cases checked and in the machine's input order.

    Names usable as file names, known columns only (a missing heat input is zero power, a missing zone the reference
    temperature), at least two rows each.
    """
    expected = input_columns(machine)
    if not cases:
        raise ValueError("the batch has no load cases")
    out = {}
    for name, loads in cases.items():
        if not isinstance(name, str) or not _CASE_NAME.match(name):
            raise ValueError(f"load case name {name!r}: use letters, digits and _ . + - (it names the output file)")
        if not isinstance(loads, Loads):
            raise TypeError(f"load case {name!r}: expected fem.loads.Loads, got {type(loads).__name__}")
        if tuple(loads.names) != expected:
            try:
                loads = in_model_order(loads, machine)
            except LoadsColumnError as exc:
                raise LoadsFileError(f"load case {name!r}: {exc}") from None
        if loads.values.shape != (len(loads.time_s), len(expected)) or len(loads.time_s) < 2:
            raise LoadsFileError(f"load case {name!r}: needs at least two rows of {len(expected)} inputs, "
                                 f"got values of shape {loads.values.shape}")
        if np.any(np.diff(loads.time_s) <= 0):
            raise LoadsFileError(f"load case {name!r}: time_s does not increase strictly")
        out[name] = loads
    return out


def write_case_atomically(out_dir: Path, result: CaseResult) -> Path:
    """Write ``out_dir/<case>.csv`` through a unique temporary file and an atomic rename."""
    from hybridcomp.models.loads import check_outputs

    check_outputs(result.time_s, result.sensor_names, result.sensors_degC, result.drift_um,
                  f"batch case {result.name!r}")
    path = out_dir / f"{result.name}.csv"
    tmp = out_dir / f".{result.name}.csv.{os.getpid()}.{uuid.uuid4().hex}.tmp"
    try:
        write_outputs(tmp, result.time_s, result.sensor_names, result.sensors_degC, result.drift_um)
        with tmp.open("rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_case(path: Path, name: str, sensor_names: tuple[str, ...]) -> CaseResult:
    """An outputs CSV written by :func:`write_case_atomically` back as a result (values as written, 6 decimals)."""
    expected = ["time_s", *(temperature_column(s) for s in sensor_names), *DRIFT_COLUMNS]
    with open_text(path, ValueError, "outputs") as fh:
        header = fh.readline().strip().split(",")
        if header != expected:
            raise ValueError(f"{path}: header {header} is not the outputs of this machine ({expected})")
        data = np.loadtxt(fh, delimiter=",", ndmin=2)
    ns = len(sensor_names)
    return CaseResult(name=name, time_s=data[:, 0], sensor_names=tuple(sensor_names), sensors_degC=data[:, 1:1 + ns],
                      drift_um=data[:, 1 + ns:], worker="file", built_model=False, compute_s=0.0, cpu_s=0.0, path=path)


def _write_json_atomically(path: Path, info: dict) -> None:
    write_text_atomic(path, json.dumps(info, indent=2))


def _resumable(out: Path, settings: dict, cases, sensor_names) -> dict[str, CaseResult]:
    """The results an interrupted run of the same batch left in ``out`` (checked against its batch.json)."""
    info_path = out / "batch.json"
    files = {n: out / f"{n}.csv" for n in cases if (out / f"{n}.csv").exists()}
    if not info_path.exists():
        if files:
            raise ValueError(f"{out}: has outputs ({min(files)}.csv ...) but no batch.json saying how they "
                             "were computed; cannot resume, use another output directory")
        return {}
    try:
        old = json.loads(info_path.read_text())["settings"]
    except (ValueError, KeyError) as exc:
        raise ValueError(f"{info_path}: not a batch.json of 'hybridcomp batch run' ({exc})") from None
    for key, value in settings.items():
        if old.get(key) != value:
            raise ValueError(f"{info_path}: the outputs in {out} were computed with {key} = {old.get(key)!r}, this "
                             f"batch has {value!r}; cannot resume, use another output directory")
    return {n: read_case(p, n, sensor_names) for n, p in files.items()}


# --------------------------------------------------------------------------- executors


def _fork_server_context(threads: int) -> multiprocessing.context.BaseContext:
    """A fork-server context whose server (and so every worker) starts with ``threads`` BLAS threads.

    Workers fork from a small clean server process instead of this (possibly multi-threaded) one,
    and the thread variables take effect because the server reads them before any BLAS is loaded.
    """
    ctx = multiprocessing.get_context("forkserver")
    from multiprocessing import forkserver

    global _FORK_SERVER_THREADS
    running = getattr(forkserver._forkserver, "_forkserver_pid", None) is not None
    if running:
        if _FORK_SERVER_THREADS not in (None, threads):
            log.warning("the fork server runs with %s BLAS threads per worker; %d asked for is ignored in this process",
                        _FORK_SERVER_THREADS, threads)
        return ctx
    _FORK_SERVER_THREADS = threads
    saved = {k: os.environ.get(k) for k in WORKER_ENVIRONMENT}
    os.environ.update({k: str(threads) for k in WORKER_ENVIRONMENT})
    try:
        forkserver.ensure_running()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return ctx


def process_pool(workers: int, threads_per_worker: int = 1) -> cf.ProcessPoolExecutor:
    """A process pool whose workers fork from a clean fork server with ``threads_per_worker`` BLAS threads each."""
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=_fork_server_context(threads_per_worker))


def _run_futures(executor: cf.Executor, spec, options, cases, done: Callable[[CaseResult], None]) -> None:
    futures = {executor.submit(run_case, spec, options, name, loads): name for name, loads in cases.items()}
    try:
        for f in cf.as_completed(futures):
            if isinstance(f.exception(), cf.process.BrokenProcessPool):
                raise f.exception()
            if f.exception() is not None:
                raise BatchError(f"load case {futures[f]!r} failed: {f.exception()}") from f.exception()
            done(f.result())
    except cf.process.BrokenProcessPool:
        # harvest what finished before the pool broke, the rest is resubmitted
        for f in futures:
            if f.done() and not f.cancelled() and f.exception() is None:
                done(f.result())
        raise
    finally:
        for f in futures:
            f.cancel()


def _run_process_pool(workers, threads, max_restarts, spec, options, cases, done) -> None:
    pending = dict(cases)

    def record(r: CaseResult) -> None:
        if r.name in pending:
            del pending[r.name]
            done(r)

    for attempt in range(max_restarts + 1):
        pool = process_pool(workers, threads)
        try:
            _run_futures(pool, spec, options, dict(pending), record)
            return
        except cf.process.BrokenProcessPool as exc:
            if attempt < max_restarts:
                log.warning("a worker process died (%s); resubmitting %d unfinished load cases on a new pool",
                            exc, len(pending))
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    raise BatchError(f"a worker process died {max_restarts + 1} time(s) (max_restarts={max_restarts}); "
                     f"{len(pending)} load cases unfinished: {sorted(pending)[:5]}")


def _import_distributed():
    try:
        import dask
        import distributed
    except ImportError:
        raise ImportError("Dask executors need dask.distributed: pip install 'hybridcomp[dask]'") from None
    return dask, distributed


@contextlib.contextmanager
def dask_client(address: str, workers: int | None = None, threads: int = 1) -> Iterator:
    """A Dask client: ``"local"`` starts a LocalCluster of ``workers`` processes, else connect to ``address``."""
    dask, distributed = _import_distributed()
    if address == "local":
        n = workers or os.cpu_count() or 1
        config = {**DASK_CONFIG, **{f"distributed.nanny.pre-spawn-environ.{k}": str(threads) for k in WORKER_ENVIRONMENT}}
        with dask.config.set(config):
            # ":0": Dask starts its HTTP server even without a dashboard, on 8787 unless told a free port
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                               dashboard_address=":0", host="127.0.0.1")
        try:
            with distributed.Client(cluster) as client:
                yield client
        finally:
            cluster.close()
    else:
        with distributed.Client(address, timeout="30s") as client:
            yield client


def _run_dask(client, spec, options, cases, done, warm: bool) -> None:
    _, distributed = _import_distributed()
    if warm:
        client.run(warm_up, spec)  # build the operators on every worker at once, not on the first case of each
    # the spec (the machine definition, a few kB) travels with each task rather than scattered once: scattered
    # data dies with the workers that hold it, a task's own arguments are resubmitted with it
    token = uuid.uuid4().hex[:8]
    futures = {client.submit(run_case, spec, options, name, loads, key=f"hybridcomp-case-{name}-{token}", pure=False): name
               for name, loads in cases.items()}
    seen: set[str] = set()
    try:
        pending = distributed.as_completed(list(futures))
        for f in pending:
            name = futures[f]
            if f.status == "cancelled":
                raise BatchError(f"load case {name!r} was cancelled on the Dask cluster (scheduler lost or restarted?)")
            if f.status in ("lost", "pending"):  # computed, then its worker died before the result was fetched:
                pending.add(f)  # the scheduler computes it again (was "failed: NoneType: None", all workers killed)
                continue
            if f.status != "finished":
                exc = f.exception()
                raise BatchError(f"load case {name!r} failed on the Dask cluster: {type(exc).__name__}: {exc}")
            r = f.result()
            if name not in seen:
                seen.add(name)
                done(r)
    finally:
        unfinished = [f for f in futures if not f.done()]
        if unfinished:
            client.cancel(unfinished)


# --------------------------------------------------------------------------- the batch


def run_batch(
    machine: Machine,
    loads: Mapping[str, Loads] | str | Path,
    *,
    pose_mm: Mapping[str, float] | None = None,
    element_size_mm: float | None = None,
    scheme: str = "theta",
    theta: float | None = None,
    initial: str = "steady",
    dt_s: float | None = None,
    executor: str | object = "process",
    workers: int | None = None,
    threads_per_worker: int = 1,
    out_dir: str | Path | None = None,
    resume: bool = False,
    progress: bool = False,
    warm: bool = True,
    max_restarts: int = 3,
    on_result: Callable[[CaseResult], None] | None = None,
) -> dict[str, CaseResult]:
    """Simulate many load cases of one machine at one pose.

    Parameters
    ----------
    machine : the machine (``models.load_machine``)
    loads : case name → :class:`~hybridcomp.fem.loads.Loads`, or a directory of loads CSVs (case = file stem)
    pose_mm : axis positions [mm]; missing axes at mid travel
    element_size_mm : largest element edge [mm]; default from the machine file
    scheme, theta : as :meth:`ThermoElasticModel.simulate`, but the θ-method by default here (θ = 1, backward Euler,
        on each case's own times or on ``dt_s``): a batch's cases are many and its callers chose their step
    initial : as :meth:`ThermoElasticModel.simulate`
    dt_s : resample every case to this uniform time step [s] (default: each case's own times)
    executor : ``"serial"``, ``"process"`` (default), ``"local"`` (Dask LocalCluster), a Dask scheduler address
        (``"tcp://HOST:8786"``), a ``concurrent.futures.Executor`` or a ``distributed.Client``
    workers : worker processes for ``"process"`` and ``"local"`` (default: the number of cores)
    threads_per_worker : BLAS / OpenMP threads of each worker process started here
    out_dir : if given, write ``out_dir/<case>.csv`` (outputs-CSV columns) atomically per case and ``batch.json``
        (the settings, at the start; the cases, at the end)
    resume : keep the outputs an interrupted run of the same batch (same settings in ``batch.json``) left in
        ``out_dir`` and compute only the missing cases; kept cases come back as read from their file
        (``worker="file"``, values rounded as written)
    progress : a progress bar over load cases (tqdm)
    warm : on Dask, build the operators on every worker before submitting the cases
    max_restarts : times a broken local process pool is replaced before giving up
    on_result : called in this process with each result as it arrives

    Returns
    -------
    case name → :class:`CaseResult`, in the order of ``loads``
    """
    theta = check_scheme(scheme, theta)
    if initial not in ("steady", "reference"):
        raise ValueError(f"initial must be 'steady' or 'reference', got {initial!r}")
    if dt_s is not None and not dt_s > 0:
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    if element_size_mm is not None and not element_size_mm > 0:
        raise ValueError(f"element_size_mm must be positive, got {element_size_mm}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if threads_per_worker < 1:
        raise ValueError(f"threads_per_worker must be at least 1, got {threads_per_worker}")
    if isinstance(executor, str):
        if executor not in ("serial", "process", "local") and "://" not in executor:
            raise ValueError(f"executor {executor!r}: use 'serial', 'process', 'local' or a Dask scheduler "
                             "address such as tcp://HOST:8786")
    elif not (isinstance(executor, cf.Executor) or type(executor).__module__.startswith("distributed")):
        raise TypeError(f"executor: expected a name, a concurrent.futures.Executor or a distributed.Client, "
                        f"got {type(executor).__name__}")
    cases = prepare_cases(read_loads_dir(loads, machine) if isinstance(loads, (str, Path)) else loads, machine)
    pose = machine.check_pose(dict(pose_mm or {}))
    spec = ModelSpec(machine, tuple(sorted((k, float(v)) for k, v in pose.items())),
                     None if element_size_mm is None else float(element_size_mm),
                     hashlib.sha256(pickle.dumps(machine)).hexdigest())
    options = SimulationOptions(scheme=scheme, theta=theta, initial=initial, dt_s=dt_s)
    if resume and out_dir is None:
        raise ValueError("resume needs out_dir (the outputs of the interrupted run)")
    settings = json.loads(json.dumps({
        "machine": machine.name, "machine_sha256": machine.sha256, "machine_digest": spec.machine_digest,
        "pose_mm": pose, "element_size_mm": spec.element_size_mm, "scheme": scheme, "theta": theta, "initial": initial,
        "dt_s": dt_s}))
    out = None
    results: dict[str, CaseResult] = {}
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        if resume:
            results = _resumable(out, settings, cases, tuple(s.name for s in machine.sensors))
            log.info("resuming: %d of %d load cases already in %s", len(results), len(cases), out)
        else:  # a fresh run replaces these outputs: none of an older batch may pass for this one's if interrupted
            for name in cases:
                (out / f"{name}.csv").unlink(missing_ok=True)
        _write_json_atomically(out / "batch.json", {"settings": settings, "complete": False})
    todo = {n: c for n, c in cases.items() if n not in results}

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(cases), initial=len(results), unit="case", desc="load cases")

    def done(r: CaseResult) -> None:
        if r.name in results:  # a case reported twice (a retried task whose first attempt also finished)
            log.debug("load case %s reported again by %s; kept the first result", r.name, r.worker)
            return
        if out is not None:
            r = dataclasses.replace(r, path=write_case_atomically(out, r))
        results[r.name] = r
        if bar is not None:
            bar.update()
        if on_result is not None:
            on_result(r)

    t0 = time.perf_counter()
    kind = executor if isinstance(executor, str) else type(executor).__name__
    n = min(workers or os.cpu_count() or 1, len(todo))  # process or Dask workers: none without a case to build a model for
    try:
        if not todo:
            pass
        elif executor == "serial":
            for name, case in todo.items():
                try:
                    r = run_case(spec, options, name, case)
                except Exception as exc:  # named like the pool's and Dask's failures
                    raise BatchError(f"load case {name!r} failed: {exc}") from exc
                done(r)
        elif executor == "process":
            _run_process_pool(n, threads_per_worker, max_restarts, spec, options, todo, done)
        elif isinstance(executor, str):
            with dask_client(executor, n, threads_per_worker) as client:
                _run_dask(client, spec, options, todo, done, warm)
        elif isinstance(executor, cf.Executor):
            _run_futures(executor, spec, options, todo, done)
        else:
            _run_dask(executor, spec, options, todo, done, warm)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    missing = [n for n in cases if n not in results]
    if missing:
        raise BatchError(f"{len(missing)} load cases returned no result: {missing[:5]}")
    log.info("%d load cases on %s in %.2f s", len(cases), kind, wall)
    if out is not None:
        _write_json_atomically(out / "batch.json", {
            "settings": settings,
            "complete": True,
            "machine_file": Path(machine.source).name,
            "executor": kind,
            "wall_s": wall,
            "cases": {n: {"file": f"{n}.csv", "worker": results[n].worker, "compute_s": results[n].compute_s}
                      for n in cases},
        })
    return {n: results[n] for n in cases}
