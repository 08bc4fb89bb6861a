"""The monitoring daemon: a thin shell around the pure transitions of :mod:`hybridcomp.monitor.transitions`.

:class:`Monitor` holds the run's context and the current frozen state, hands each :class:`Reading` to
:func:`~hybridcomp.monitor.transitions.on_reading` and carries out what the transition returns: the offsets go to
the sink, the events into the event log, the commands to the database (activate a set), the generation worker
(a request) or the state store (a boundary's state). Three clocks of machine time drive the transitions:

* every ``compensation_interval_s`` (5 s): offsets — the active CD set on the low-passed sensors (strategy
  ``hybrid``), the corrected structure model's drift (strategy ``observer``, the CDs standing in while the
  observer is flagged) or the data-only model updated by the probes (strategy ``dataonly``, stepped every sample),
  clamped and rate limited;
* every ``increment_s`` (20 s, a model step): the histogram of the step's samples gives the loads; the
  observer (:mod:`hybridcomp.rom.observer`) steps the structure model and corrects it with the sensors and,
  when there is one, a probed drift;
* every ``monitoring_interval_s`` (15 min, and at the first sample): the active set's predicted compensation
  error — the CDs on the measured sensors against the corrected model's drift over the interval, and on the
  forecast sensors against the forecast drift — decides keep, switch or generate
  (:func:`hybridcomp.monitor.decisions.decide`); the seeds' ΔT test is reported beside it.

Everything it decides is decided by :mod:`hybridcomp.monitor.decisions` inside the transitions.
:func:`run_monitor` is the asyncio loop around it: data source with reconnect, sink, background generation in a
worker process, clean stop. A replay at 1000× makes the same decisions as the machine in real time.

Persistence and restarts: at every monitoring boundary the whole state is written as one JSON value
(``MonitorStore.put_state``), and every event carries a key made of its kind, the pose and its machine time,
so a daemon killed at any moment and restarted re-processes the samples after the last boundary, makes the
same decisions again and writes no event twice.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import importlib
import json
import logging
import math
import multiprocessing
import os
import random
import signal
import socket
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

from hybridcomp.chardiag.cd import CDSet
from hybridcomp.models import jsonio
from hybridcomp.models.layout import DIRECTIONS, DRIFT_COLUMNS
from hybridcomp.monitor import decisions
from hybridcomp.monitor import transitions as T
from hybridcomp.monitor.config import MonitorConfig, read_dataonly_model
from hybridcomp.monitor.sinks import Offset, SinkWriteError
from hybridcomp.monitor.sources import Reading, SourceDisconnected, WallClock
from hybridcomp.monitor.state import STATE_VERSION, MonitorState
from hybridcomp.monitor.store import LeaseHeld, MonitorStore, QueuedStore, lease_owner
from hybridcomp.monitor.transitions import Counters

log = logging.getLogger(__name__)


def state_key(machine: str, pose_key: str) -> str:
    """Key of the monitor's state in the database."""
    return f"monitor:{machine}:{pose_key}"


def heartbeat_file(db_url: str, key: str) -> Path:
    """The file holding this host's copy of a daemon's heartbeat: ``monitor status`` here reads it when the database lags.

    The daemon writes its heartbeat to the database and to this file (beside an SQLite database, as its journal is;
    for a database server in the system's temporary folder; named by a digest of the key); a locked database delays
    the one, not the other.
    """
    from hybridcomp.chardiag.db import sqlite_file

    file = sqlite_file(db_url)
    name = f"{T.digest(key)}.heartbeat.json"
    if file is not None:
        return file.with_name(f"{file.name}.{name}")
    return Path(tempfile.gettempdir()) / f"hybridcomp-monitor-{T.digest(str(db_url))}.{name}"


def read_heartbeat_file(db_url: str, key: str) -> dict | None:
    """The heartbeat this host's copy holds for ``key``, or None."""
    try:
        d = json.loads(heartbeat_file(db_url, key).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) and d.get("key") == key else None


def _write_heartbeat_file(db_url: str, key: str, record: dict) -> None:
    path = heartbeat_file(db_url, key)
    try:
        with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=path.name, suffix=".tmp", delete=False,
                                         encoding="utf-8") as fh:
            fh.write(jsonio.dumps({**record, "key": key}))
        os.replace(fh.name, path)
    except OSError as exc:  # (the database's copy is the record; this one only bridges a lock)
        log.debug("heartbeat file %s: %s", path, exc)


def _t(x: float) -> str:
    return f"{x:.3f}"


class Monitor:
    """The daemon's shell: the current state, the transitions' effects carried out (no I/O but the database).

    Parameters
    ----------
    cfg : configuration
    machine : the machine (axes, sensors, zones, heat sources)
    rom : reduced structure model of the machine at the CDs' pose; a pose-aware one (its first block that model)
        makes the monitor write a support-point table every cycle and the offsets at the commanded position
        (:mod:`hybridcomp.monitor.volumetric`)
    db : CD database (``hybridcomp.chardiag.db.CDDatabase`` or anything with its methods)
    pose_key : the pose's database key
    clock : gives Unix time for freshness (default :class:`WallClock`)
    """

    def __init__(self, cfg: MonitorConfig, machine, rom, db, pose_key: str, clock=None):
        self.cfg = cfg
        self.machine = machine
        self.rom = rom
        self.db = db
        self.store = MonitorStore(db)
        self.pose_key = pose_key
        self.clock = clock or WallClock()
        self.key = state_key(machine.name, pose_key)
        dataonly = read_dataonly_model(cfg.dataonly_model, cfg.source_file) if cfg.strategy == "dataonly" else None
        self.ctx = T.context(cfg, machine, rom, pose_key, dataonly)
        self.state = T.initial(self.ctx)
        self.regeneration_running = False
        self.lease_owner: str | None = None  # the owner token of the pose's lease while run_monitor holds it
        # machine seconds per wall second of the source: None (no clock to ask, a replay), a number, or "observed"
        # (a live control: its stamps against the wall clock over the last samples)
        self.time_scale: float | str | None = None
        self._boundary: T.State | None = None  # the state of the last monitoring boundary (persisted)
        self._outbox: list[dict] = []
        self.restore()
        self.reload_active()

    # ------------------------------------------------------------------ views of the state
    @property
    def s(self) -> MonitorState:
        """The persisted part of the current state."""
        return self.state.saved

    @property
    def counters(self) -> Counters:
        return self.state.counters

    def count(self, **inc) -> None:
        """Add to counters the shell keeps (reconnects)."""
        self.state = T.counted(self.state, **inc)

    @property
    def observer(self):
        return self.ctx.observer

    @property
    def pose(self):
        return self.ctx.pose

    @property
    def pose_mm(self) -> dict:
        return dict(self.ctx.pose_mm)

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return self.ctx.sensor_names

    @property
    def active(self) -> CDSet | None:
        return self.state.active

    @property
    def track(self):
        return self.state.track

    @property
    def table(self):
        return self.state.written_table

    @property
    def gains(self):
        return self.state.drive_gains

    # ------------------------------------------------------------------ persistence
    def persist(self) -> None:
        """Write the state of the last monitoring boundary (with the current generation bookkeeping).

        Only boundary states are written: a restart re-processes the samples after the boundary, so the
        histogram of the interval is complete. Before the first boundary, a fresh state is written (a
        restart starts from the beginning; events are keyed, nothing doubles).
        """
        saved = T.boundary_saved(self.ctx, self._boundary, self.state)
        self.store.put_state(self.key, jsonio.dumps({**saved.to_dict(), "updated_unix": self.clock.unix()}))

    def restore(self) -> None:
        """The state of the last boundary the database holds (a fresh one when it holds none that fits)."""
        self.state, self._boundary = T.initial(self.ctx), None
        text = self.store.get_state(self.key)
        if not text:
            return
        d = json.loads(text)
        d.pop("updated_unix", None)
        if d.get("version") != STATE_VERSION:
            log.warning("state %s has version %r, this daemon writes %d: starting fresh", self.key, d.get("version"),
                        STATE_VERSION)
            return
        try:
            s = MonitorState.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("state %s is unreadable (%s): starting fresh", self.key, exc)
            return
        if s.rom_id != self.rom.rom_id:
            log.warning("state %s belongs to reduced model %s, not %s: starting fresh", self.key, s.rom_id,
                        self.rom.rom_id)
            return
        self.state = self._boundary = T.restored(self.ctx, s)
        for pending in (s.pending, s.grid_pending):  # resubmit a generation the last run did not finish
            if pending is not None:
                self._outbox.append(pending)
        log.info("resumed %s at machine time %s s", self.key, s.last_time_s)

    def reload_active(self) -> None:
        self.state = T.with_active(self.ctx, self.state, self.db.active_set(self.machine.name, self.pose_key))
        self.reload_grid()

    def reload_grid(self) -> None:
        """Without a pose-aware model: the machine's active CD grid (its sets give the support-point table)."""
        if self.ctx.pose is None and hasattr(self.db, "active_grid"):
            self.state = T.with_active_grid(self.ctx, self.state, self.db.active_grid(self.machine.name))

    def event(self, kind: str, t: float | None, payload: dict, key: str) -> None:
        self.store.log_event(kind, t, payload, key=f"{kind}@{self.pose_key}@{key}")

    # ------------------------------------------------------------------ carrying out a transition
    def _apply(self, step: T.Step, t0: float | None = None) -> list[Offset]:
        """Take the step's state and carry out its effects in order; returns its offsets."""
        self.state = step.state
        boundary = None
        for e in step.effects:
            if isinstance(e, T.Event):
                self.event(e.kind, e.t, dict(e.payload), e.key)
            elif isinstance(e, T.Log):
                getattr(log, e.level)("%s", e.message)
            elif isinstance(e, T.Activate):
                self._record_activation(e)
            elif isinstance(e, T.ActivateGrid):
                self._record_grid_activation(e)
            elif isinstance(e, T.Request):
                self._outbox.append(dict(e.request))
            elif isinstance(e, T.Persist):
                if e.state is not None:
                    self._boundary = boundary = e.state
                    if t0 is not None:  # how long the reading that closed the interval took, its decision included
                        dt = time.perf_counter() - t0
                        c = self.state.counters
                        self.state = replace(self.state, counters=replace(
                            c, last_decision_s=dt, max_decision_s=max(c.max_decision_s, dt)))
                self.persist()
        if boundary is not None and T.decides_grids(self.ctx, self.state):
            self._decide_grid(boundary)
        return list(step.offsets)

    def _decide_grid(self, boundary: T.State) -> None:
        """The CD grid decision at a monitoring boundary (:func:`transitions.on_grid_decision`).

        The stored grids are read lazily from the database, as the decision asks for them.
        """
        temps = T.grid_temperatures(self.ctx, boundary)
        t = boundary.saved.last_time_s

        def candidates():
            for m in self.db.search_grids(self.machine.name, None, temps, self.cfg.threshold_K):
                try:
                    yield self.db.grid(m.grid_id)
                except (KeyError, ValueError) as exc:  # an unreadable grid is no candidate
                    log.warning("CD grid %s cannot be read: %s", m.grid_id, exc)

        self._apply(T.on_grid_decision(self.ctx, self.state, t, temps, candidates()))

    def _record_grid_activation(self, a: T.ActivateGrid) -> None:
        """The database's record of a grid switch, written in order with the events."""
        gid, t, reason, owner = int(a.grid_id), a.t, a.reason, self.lease_owner
        key = f"grid activation@{self.machine.name}@{_t(t)}@{gid}"
        self.store.call(lambda: self.db.activate_grid(gid, reason=reason, machine_time_s=t, event_key=key,
                                                      lease_owner=owner), f"activating CD grid {gid}")

    def _record_activation(self, a: T.Activate) -> None:
        """The database's record of a switch, written in order with the events, off the compensation path."""
        ids = {k: int(v) for k, v in a.ids.items()}
        t = a.t
        key = f"activation@{self.pose_key}@{_t(t)}@{ids['X']},{ids['Y']},{ids['Z']}"
        name, pose, reason, owner = self.machine.name, self.pose_key, a.reason, self.lease_owner
        self.store.call(lambda: self.db.activate(name, pose, ids, reason=reason, machine_time_s=t, event_key=key,
                                                 lease_owner=owner), f"activating {ids}")

    def _stored_sets(self, q: T.SetQuery):
        """The stored sets of a monitoring decision's query, read from the database as the decision asks for them."""
        for m in self.db.search(self.machine.name, self.pose_key, q.signature, q.temperatures_degC, math.inf,
                                layout=self.ctx.sig_layout):
            ids = {k: int(v) for k, v in m.ids.items()}
            if ids == q.skip_ids:
                continue
            try:
                cds = {d: self.db.get(ids[d]) for d in DIRECTIONS}
            except (KeyError, ValueError) as exc:
                yield T.StoredSet(ids, m.load_case, float(m.delta_T_K), None, str(exc))
                continue
            yield T.StoredSet(ids, m.load_case, float(m.delta_T_K), cds)

    # ------------------------------------------------------------------ the clocks
    def process(self, r: Reading) -> list[Offset]:
        """Handle one reading; returns the offsets of the compensation cycles it completes (0 or 1)."""
        t0 = time.perf_counter()
        return self._apply(T.on_reading(self.ctx, self.state, r, self._stored_sets, self.clock.unix(),
                                        self.time_scale), t0)

    def resume_after_s(self) -> float | None:
        """The source time stamp to resume after (a reconnect or restart)."""
        s = self.state.saved
        return s.last_source_time_s if s.last_source_time_s is not None else s.last_time_s

    def activate(self, ids: Mapping[str, int], reason: str, t: float) -> None:
        """Make a set active (idempotent: nothing happens when it already is)."""
        ids = {k: int(v) for k, v in ids.items()}
        if self.state.saved.active_ids == ids:
            return
        new = CDSet({d: self.db.get(ids[d]) for d in DIRECTIONS}, ids)  # (reads never wait; a missing id raises)
        self._apply(T.on_activate(self.ctx, self.state, new, reason, t))

    # ------------------------------------------------------------------ generation results
    def take_requests(self) -> list[dict]:
        out, self._outbox = self._outbox, []
        return out

    def regeneration_finished(self, request: dict, result: Mapping | None, error: str | None, status: str) -> None:
        """Record the outcome of a generation job; activate its set (its CD grid) when it succeeded."""
        if "grid" in request:
            self._grid_generation_finished(request, result, error, status)
            return
        new, load_error = None, None
        if status == "finished" and result is not None:
            ids = {k: int(v) for k, v in result["ids"].items()}
            if ids != self.state.saved.active_ids:
                try:
                    new = CDSet({d: self.db.get(ids[d]) for d in DIRECTIONS}, ids)
                except Exception as exc:  # noqa: BLE001 - a broken result must not stop the daemon
                    load_error = f"{type(exc).__name__}: {exc}"
        self._apply(T.on_regeneration_finished(self.ctx, self.state, request, result, error, status, new, load_error))

    def _grid_generation_finished(self, request: dict, result: Mapping | None, error: str | None, status: str) -> None:
        grid, load_error = None, None
        if status == "finished" and result is not None:
            try:
                grid = self.db.grid(int(result["grid_id"]))
            except Exception as exc:  # noqa: BLE001 - a broken result must not stop the daemon
                load_error = f"{type(exc).__name__}: {exc}"
        self._apply(T.on_grid_generation_finished(self.ctx, self.state, request, result, error, status, grid,
                                                  load_error))

    def status(self) -> dict:
        """Numbers for the status command and the metrics endpoint."""
        s = self.state.saved
        return {
            "machine": self.machine.name, "pose_key": self.pose_key, "active": s.active_ids, "strategy": self.cfg.strategy,
            "last_time_s": s.last_time_s, "last_delta_T_K": s.last_delta_T_K, "last_decision": s.last_decision,
            "last_error_um": s.last_error, "observer_flag": s.observer_flag, "max_residual_K": s.max_residual_K,
            "offsets_um": s.offsets_um, "degraded": [n for n in self.sensor_names if s.sensors[n].status == "degraded"],
            "regeneration_running": self.regeneration_running, **self.counters.__dict__,
        }


# ====================================================================== the asyncio shell


def resolve_job(spec: str) -> Callable:
    """``"module:function"`` → the function."""
    mod, _, fn = spec.partition(":")
    return getattr(importlib.import_module(mod), fn)


def generation_key(request: Mapping) -> str:
    """The database key of a generation request's result: its kind (a set, a CD grid), machine, pose and machine time."""
    kind = "grid generation" if "grid" in request else "generation"
    return f"{kind}@{request.get('machine')}@{request.get('pose_key')}@{_t(float(request['machine_time_s']))}"


def _job_store(request: Mapping):
    """The request's database (a :class:`MonitorStore`), or None when the request names none."""
    if not request.get("database"):
        return None
    from hybridcomp.chardiag.db import CDDatabase

    return MonitorStore(CDDatabase(request["database"]))


def _call_job(spec: str, request: dict) -> dict:
    """Worker-process entry: the stored result of the same request, else resolve the job, run it, store its result.

    A request is pending in the daemon's persisted state from the decision that made it; a daemon restarted before
    it heard the result submits it again. The result is stored under the request's key (:func:`generation_key`)
    the moment the job returns, so the second submission adopts it (``notes.adopted``) instead of generating a
    second set for one request. A CD grid's request (its ``grid`` entry) runs the job it names there
    (:func:`hybridcomp.monitor.regeneration.grid_job`), under the same timeout.
    """
    store = _job_store(request)
    key = generation_key(request)
    try:
        if store is not None:
            text = store.get_state(key)
            if text:
                done = json.loads(text)
                return {**done, "notes": {**(done.get("notes") or {}),
                                          "adopted": f"the stored result of request {key} (a restart)"}}
        if "grid" in request:  # a CD grid's generation names its own job
            spec = request["grid"].get("job") or spec
        result = dict(resolve_job(spec)(request))
        if store is not None:
            store.put_state(key, jsonio.dumps(result))
        return result
    finally:
        if store is not None:
            store.db.close()


def _worker_init(parent_pid: int) -> None:
    """In a generation worker: end it when the daemon that started it is gone (killed with -9, crashed).

    A watch thread compares the worker's parent with the daemon's pid once a second; when the worker has been
    handed to another parent (the daemon died), it exits at once, its job with it.
    """
    import threading

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(70)
            time.sleep(PARENT_CHECK_S)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


PARENT_CHECK_S = 0.5  # how often a generation worker checks that its daemon still runs [s]


class Regenerator:
    """Runs generation jobs in a worker process with a wall-clock timeout; a hanging job is killed.

    Compensation never waits for it: the shell only looks at finished futures.
    """

    def __init__(self, job: str, timeout_s: float):
        self.job = job
        self.timeout_s = timeout_s
        self._pool: cf.ProcessPoolExecutor | None = None

    def _executor(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            # (a worker ends with the daemon: _worker_init watches its parent)
            self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                initializer=_worker_init, initargs=(os.getpid(),))
        return self._pool

    async def run(self, request: dict) -> tuple[dict | None, str | None, str]:
        """Returns (result, error, status) with status ``finished``, ``failed`` or ``timeout``."""
        loop = asyncio.get_running_loop()
        t0 = time.monotonic()
        try:
            fut = loop.run_in_executor(self._executor(), _call_job, self.job, request)
            result = await asyncio.wait_for(fut, self.timeout_s)
            result = dict(result)
            result.setdefault("wall_s", time.monotonic() - t0)
            return result, None, "finished"
        except TimeoutError:
            self.kill()
            return None, f"no result after {self.timeout_s:g} s: job killed", "timeout"
        except asyncio.CancelledError:
            self.kill()
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of the job is reported, never raised
            if isinstance(exc, cf.process.BrokenProcessPool):
                self.kill()
            return None, f"{type(exc).__name__}: {exc}", "failed"

    def kill(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        procs = list(getattr(pool, "_processes", {}).values())  # no public API to stop a running job
        for p in procs:
            if p.is_alive():
                p.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            p.join(timeout=5)

    def close(self) -> None:
        self.kill()


@dataclass
class RunResult:
    """Summary of one run of the daemon."""

    status: dict
    stopped_by: str


async def run_monitor(
    cfg: MonitorConfig,
    monitor: Monitor,
    source,
    sink,
    *,
    clock=None,
    stop: asyncio.Event | None = None,
    regenerator: Regenerator | None = None,
    await_regeneration: bool = False,
    seed: int | None = None,
    heartbeat_s: float = 5.0,
    standby: bool = False,
) -> RunResult:
    """The daemon's loop: readings → monitor → sink, with reconnect, background jobs and a clean stop.

    Parameters
    ----------
    cfg : configuration (reconnect schedule, regeneration)
    monitor : the state holder
    source : data source (``readings(start_after_s)``)
    sink : offsets sink
    clock : clock for backoff sleeps and freshness
    stop : set it to stop (SIGTERM/SIGINT handlers do)
    regenerator : runs generation jobs (default: from ``cfg.regeneration``)
    await_regeneration : hold the data stream while a job runs (scenario replays, where machine time is
        virtual; never for a live machine)
    seed : seed of the reconnect jitter
    heartbeat_s : write the freshness record this often [s of wall time]
    standby : when another daemon holds the pose, wait until its lease ends (then resume from its last state)
        instead of refusing to start (:class:`~hybridcomp.monitor.store.LeaseHeld`)

    The database is written by a background thread (:class:`~hybridcomp.monitor.store.QueuedStore`): a locked or
    restarting database delays the record, never an offset. Every offset passes :func:`check_offset` before a
    sink sees it.
    """
    clock = clock or WallClock()
    stop = stop or asyncio.Event()
    lease = monitor.key
    owner = lease_owner()
    await _take_lease(monitor, lease, owner, cfg.lease_s, clock, stop, standby)
    if stop.is_set():
        return RunResult(monitor.status(), "signal")
    monitor.lease_owner = owner["owner"]  # its own activations pass the lease (no other writer's do)
    sync_store = monitor.store
    monitor.store = QueuedStore(sync_store)
    monitor.time_scale = getattr(source, "time_scale", None)
    regen = regenerator or Regenerator(cfg.regeneration.job, cfg.regeneration.timeout_s)
    rng = random.Random(seed)
    jobs: set[asyncio.Task] = set()
    attempt = 0
    last_beat = -math.inf
    applied_unix: float | None = None
    reported: set = set()  # source nodes whose non-numeric values (or absence) have an event
    db_url = getattr(monitor.db, "url", None)
    lost: list[str] = []

    def renew() -> None:
        """Renew the lease (on the writer thread, in order with the writes); a lost lease stops the daemon."""
        def run():
            holder = sync_store.acquire_lease(lease, owner, cfg.lease_s, clock.unix())
            if holder is not None:
                lost.append(f"the lease on {lease} was taken by {holder.get('owner')} (this daemon could not renew it "
                            f"within {cfg.lease_s:g} s)")
        monitor.store.call(run, "renewing the lease")

    async def job(request: dict) -> None:
        monitor.regeneration_running = True
        try:
            result, error, status = await regen.run(request)
            monitor.regeneration_finished(request, result, error, status)
        finally:
            monitor.regeneration_running = False

    def start_jobs() -> None:
        for req in monitor.take_requests():
            t = asyncio.create_task(job(req))
            jobs.add(t)
            t.add_done_callback(jobs.discard)

    def beat(force: bool = False, running: bool = True) -> None:
        nonlocal last_beat
        now = clock.monotonic()
        if force or now - last_beat >= heartbeat_s:
            last_beat = now
            record = {"unix": clock.unix(), "applied_unix": applied_unix, "running": running,
                      "last_time_s": monitor.s.last_time_s, "offsets_um": monitor.s.offsets_um,
                      "active": monitor.s.active_ids, "degraded": monitor.status()["degraded"],
                      "regeneration_running": monitor.regeneration_running, "store_backlog": monitor.store.backlog(),
                      "stale_after_s": cfg.stale_after_s, "heartbeat_s": heartbeat_s, "pid": os.getpid(),
                      "host": socket.gethostname(), "live": live_record(monitor)}
            monitor.store.put_state(monitor.key + ":heartbeat", jsonio.dumps(record))
            if db_url is not None:
                _write_heartbeat_file(db_url, monitor.key, record)

    def source_faults(r: Reading) -> None:
        """Values the source could not read as numbers, and nodes the server does not have: an event per node.

        (A String node where a number belongs; a well-formed id of a node that does not exist.)
        """
        for col, (node, why) in (getattr(source, "missing_nodes", None) or {}).items():
            if ("missing", col) not in reported:
                reported.add(("missing", col))
                monitor.event("source", r.time_s, {
                    "status": "node not found", "node": node, "column": col, "error": why,
                    "message": f"source.nodes.{col} = {node!r}: the server has no such node ({why}); {col} is read "
                               "as missing (a sensor: held, then degraded)"}, f"missing@{col}")
                log.error("source node %s (%s) does not exist on the server: %s", node, col, why)
        for node, n in (getattr(source, "bad_values", None) or {}).items():
            if node not in reported:
                reported.add(node)
                monitor.event("source", r.time_s, {"status": "not a number", "node": node, "count": n,
                                                   "message": f"{node}: a value that is not a number was read as "
                                                   "missing (a sensor fault for a temperature)"},
                              f"nan-value@{node}@{_t(r.time_s) if math.isfinite(r.time_s) else 'nan'}")
                log.warning("source value %s is not a number: read as missing", node)

    async def consume() -> str:
        nonlocal attempt, applied_unix
        while True:
            connected = False
            try:
                async for r in source.readings(start_after_s=monitor.resume_after_s()):
                    if not connected:
                        connected = True
                        if attempt:
                            monitor.count(reconnects=1)
                            monitor.store.log_event("source", r.time_s, {"status": "reconnected", "attempts": attempt})
                        attempt = 0
                    source_faults(r)
                    for off in monitor.process(r):
                        problem = check_offset(off, cfg.max_offset_um)
                        if problem:
                            monitor.event("warning", off.time_s, {"message": f"offset not written: {problem}"},
                                          f"guard@{_t(off.time_s)}")
                            continue
                        try:
                            await sink.write(off)
                        except SinkWriteError as exc:  # a full disk: stop, the file named, its lines whole
                            monitor.event("sink", off.time_s, {"status": "write failed", "file": str(exc.path),
                                                               "error": getattr(exc.cause, "strerror", None)
                                                               or str(exc.cause)}, f"write-failed@{_t(off.time_s)}")
                            raise
                        applied_unix = clock.unix()
                    if lost:
                        raise LeaseHeld(lost[0])
                    start_jobs()
                    if await_regeneration:
                        while jobs:
                            await asyncio.wait(set(jobs))
                    beat()
                if getattr(source, "finished", True):
                    return "end of data"
            except SourceDisconnected as exc:
                delay = decisions.backoff_delay(attempt, cfg.reconnect, rng.random())
                log.warning("data source: %s; reconnecting in %.2f s (attempt %d)", exc, delay, attempt + 1)
                if attempt == 0:
                    monitor.store.log_event("source", monitor.s.last_time_s, {"status": "disconnected", "error": str(exc)})
                attempt += 1
                await clock.sleep(delay)

    async def keep_lease() -> None:
        """Renew the lease every third of its length, whether data come or not."""
        while True:
            await clock.sleep(cfg.lease_s / 3.0)
            renew()

    start_jobs()
    consumer = asyncio.create_task(consume())
    stopper = asyncio.create_task(stop.wait())
    leaser = asyncio.create_task(keep_lease())
    try:
        await asyncio.wait({consumer, stopper}, return_when=asyncio.FIRST_COMPLETED)
        if consumer.done():
            stopped_by = consumer.result()  # (raises what the loop raised)
            if await_regeneration and jobs:
                await asyncio.wait(set(jobs))
        else:
            # a stop request: the reading being processed is complete (processing has no await inside), the
            # state of the last monitoring boundary is in the database; wait for nothing else
            stopped_by = "signal"
            consumer.cancel()
            try:
                await consumer
            except asyncio.CancelledError:
                pass
    finally:
        stopper.cancel()
        leaser.cancel()
        if not consumer.done():
            consumer.cancel()
            try:
                await consumer
            except (asyncio.CancelledError, Exception):  # noqa: BLE001 - shutting down
                pass
        for t in list(jobs):
            t.cancel()
        if jobs:
            await asyncio.gather(*jobs, return_exceptions=True)
        regen.close()
        await sink.close()
        if monitor.s.last_time_s is not None:
            beat(force=True, running=False)
        if not lost:
            monitor.store.call(lambda: sync_store.release_lease(lease, owner["owner"]), "releasing the lease")
        monitor.store.close()
        monitor.store = sync_store
    return RunResult(monitor.status(), stopped_by)


def live_record(monitor: Monitor) -> dict:
    """What the live view (``hybridcomp monitor serve``) reads from the heartbeat beyond its freshness.

    The sensors as the observer reads them (NaN: degraded) and as it estimates them at its last model step [°C], its
    drift estimate [µm], the last predicted error [µm] with the limits it is judged by, the strategy, why the observer
    or the active set is not trusted, and the support-point table written last (None without one).
    """
    from hybridcomp.rom.volumetric import table_to_dict

    cfg, st = monitor.cfg, monitor.state
    v = cfg.validity
    try:
        estimate = T._estimate_degC(monitor.ctx, st)
        table = None if st.written_table is None else table_to_dict(st.written_table)
    except Exception as exc:  # noqa: BLE001 - a view never stops compensation
        log.debug("live record: %s", exc)
        estimate, table = {}, None
    return {
        "strategy": cfg.strategy, "measured_degC": dict(st.measured), "estimate_degC": estimate,
        "drift_um": st.saved.drift_um, "error_um": st.saved.last_error, "observer_flag": st.saved.observer_flag,
        "failsafe": st.saved.failsafe, "limits_um": {"keep": v.keep_um, "forecast": v.forecast_um, "hard": v.hard_um,
                                                     "reject": v.reject_um},
        "threshold_K": cfg.threshold_K, "model_drift_K": cfg.model_drift_K,
        "table": table,
    }


def check_offset(off: Offset, max_abs_um: float) -> str:
    """Why an offset must not reach the control ("" when it may): not finite, or beyond the clamp [µm].

    The project's one output guard (:func:`hybridcomp.chardiag.guard.guard_offsets`), as the CNC exports use it.
    """
    from hybridcomp.chardiag.guard import OffsetGuardError, guard_offsets

    if not math.isfinite(off.time_s):
        return f"time_s = {off.time_s!r} is not finite"
    try:
        guard_offsets({c: getattr(off, c) for c in DRIFT_COLUMNS}, clamp_um=max_abs_um * (1 + 1e-12),
                      source=f"offset at {off.time_s:.3f} s")
    except OffsetGuardError as exc:
        return str(exc)
    return ""  # a support-point table is finite by construction (rom.volumetric.VolumetricTable refuses NaN)


async def _take_lease(monitor: Monitor, lease: str, owner: dict, ttl_s: float, clock, stop: asyncio.Event,
                      standby: bool) -> None:
    """Hold the pose: refuse to start while another daemon holds it, or wait for it (``standby``)."""
    waited = False
    while True:
        holder = monitor.store.acquire_lease(lease, owner, ttl_s, clock.unix())
        if holder is None:
            break
        msg = (f"{lease} is held by another daemon ({holder.get('owner')}, pid {holder.get('pid')} on "
               f"{holder.get('host')}) until its lease ends or it stops")
        if not standby:
            raise LeaseHeld(f"{msg}: refusing to start a second writer (--standby waits for it)")
        if not waited:
            log.warning("%s: standing by", msg)
            waited = True
        try:
            await asyncio.wait_for(stop.wait(), max(0.2, ttl_s / 3.0))
            return
        except TimeoutError:
            pass
    if waited:  # the other daemon went on meanwhile: continue from where it stopped
        monitor.restore()
        monitor.reload_active()
        monitor.store.log_event("lease", monitor.s.last_time_s, {"status": "taken over", "owner": owner["owner"]})


def install_signal_handlers(stop: asyncio.Event) -> None:
    """SIGTERM and SIGINT set ``stop`` (the loop finishes the current reading, persists and exits)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
