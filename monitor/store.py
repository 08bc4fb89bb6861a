"""The monitor's persistence: its events and its state, in the database of its CDs.

The monitor keeps its record beside the CDs it switches: one database (SQLite
file or any SQLAlchemy URL), one schema, the ``events`` and ``state`` tables of
``hybridcomp.chardiag.db`` (which creates and migrates the schema and writes the
``activation`` events in the transaction that changes the active set).
:class:`MonitorStore` reads and writes them through that database's engine, so
its writes serialise with every other writer of the database.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from hybridcomp.chardiag.db import EVENTS_LOCK, CDDatabase, lease_free, utc_now
from hybridcomp.errors import HybridcompError
from hybridcomp.models import jsonio

log = logging.getLogger(__name__)


class LeaseHeld(HybridcompError, RuntimeError):
    """Another daemon holds the machine's pose (one writer per pose)."""


@dataclass(frozen=True)
class Event:
    """A logged event: ``payload`` holds its numbers."""

    id: int
    kind: str
    machine_time_s: float | None
    created: str
    payload: dict
    key: str | None = None


class MonitorStore:
    """Events and state of a monitor, in the tables of its CD database.

    Parameters
    ----------
    db : the CD database the monitor works with (its engine is shared, nothing is opened twice)
    """

    def __init__(self, db: CDDatabase):
        self.db = db

    def log_event(self, kind: str, machine_time_s: float | None, payload: Mapping, key: str | None = None) -> int | None:
        """Append an event (payload as strict JSON: non-finite numbers as null).

        With a ``key`` that is already logged nothing is written and None is returned.
        """
        db, sa = self.db, self.db.sa
        ev = db.t["events"]
        text = jsonio.dumps(dict(payload))

        def run(conn):
            db.lock(conn, EVENTS_LOCK)
            if key is not None and conn.execute(sa.select(ev.c.id).where(ev.c.key == key)).first():
                return None
            return conn.execute(ev.insert().values(kind=kind, machine_time_s=machine_time_s, created=utc_now(),
                                                   payload=text, key=key)).inserted_primary_key[0]

        try:
            return db.write(run, f"logging a {kind} event")
        except sa.exc.IntegrityError:  # the same key from another writer in the same instant
            return None

    def events(self, kind: str | None = None, since_id: int = 0, limit: int | None = None) -> list[Event]:
        """Events after ``since_id``, oldest first (the activations of ``CDDatabase.activate`` among them)."""
        db, sa = self.db, self.db.sa
        ev = db.t["events"]
        q = sa.select(ev).where(ev.c.id > since_id).order_by(ev.c.id)
        if kind is not None:
            q = q.where(ev.c.kind == kind)
        if limit is not None:
            q = q.limit(limit)
        with db.engine.connect() as conn:
            return [Event(r.id, r.kind, r.machine_time_s, r.created, json.loads(r.payload), r.key)
                    for r in conn.execute(q)]

    def put_state(self, key: str, value: str) -> None:
        """Set a state value (JSON text)."""
        db, sa = self.db, self.db.sa
        st = db.t["state"]

        def run(conn):
            n = conn.execute(st.update().where(st.c.key == key).values(value=value, updated=utc_now())).rowcount
            if n == 0:
                conn.execute(st.insert().values(key=key, value=value, updated=utc_now()))

        try:
            db.write(run, f"saving state {key!r}")
        except sa.exc.IntegrityError:  # another writer inserted the key first: now it is an update
            db.write(run, f"saving state {key!r}")

    def get_state(self, key: str) -> str | None:
        """A state value (JSON text), or None."""
        db, sa = self.db, self.db.sa
        st = db.t["state"]
        with db.engine.connect() as conn:
            return conn.execute(sa.select(st.c.value).where(st.c.key == key)).scalar()

    def call(self, fn: Callable[[], object], what: str) -> None:
        """Run a database write now (:class:`QueuedStore` queues it)."""
        fn()

    # ------------------------------------------------------------------ the lease: one writer per pose
    def acquire_lease(self, name: str, owner: Mapping, ttl_s: float, now_unix: float) -> dict | None:
        """Take or renew the lease ``name`` for ``owner`` until ``now_unix + ttl_s``; returns None when held.

        Returns the holder's record when another owner holds it: a lease is free when it has expired, or when its
        holder was a process on this host that no longer runs (a daemon killed with -9 leaves its lease behind).
        The check and the write are one serialised transaction (SQLite's write lock; an advisory lock on
        PostgreSQL), so of two daemons starting at once exactly one gets it.
        """
        db, sa = self.db, self.db.sa
        st = db.t["state"]
        key = f"lease:{name}"
        mine = {**owner, "expires_unix": now_unix + ttl_s, "renewed_unix": now_unix}

        def run(conn):
            db.lock(conn, key)
            text = conn.execute(sa.select(st.c.value).where(st.c.key == key)).scalar()
            if text:
                cur = json.loads(text)
                if cur.get("owner") != owner["owner"] and not lease_free(cur, now_unix):
                    return cur
                conn.execute(st.update().where(st.c.key == key).values(value=jsonio.dumps(mine), updated=utc_now()))
            else:
                conn.execute(st.insert().values(key=key, value=jsonio.dumps(mine), updated=utc_now()))
            return None

        try:
            return db.write(run, f"taking the lease {name!r}")
        except sa.exc.IntegrityError:  # another daemon inserted it in the same instant: read again
            return db.write(run, f"taking the lease {name!r}")

    def release_lease(self, name: str, owner: str) -> None:
        """Give the lease up (only the owner's)."""
        db, sa = self.db, self.db.sa
        st = db.t["state"]
        key = f"lease:{name}"

        def run(conn):
            db.lock(conn, key)
            text = conn.execute(sa.select(st.c.value).where(st.c.key == key)).scalar()
            if text and json.loads(text).get("owner") == owner:
                conn.execute(st.delete().where(st.c.key == key))

        db.write(run, f"releasing the lease {name!r}")


def lease_owner() -> dict:
    """The lease owner record of the running process: a unique token, the host and the process id."""
    return {"owner": f"{socket.gethostname()}:{os.getpid()}:{os.urandom(6).hex()}", "host": socket.gethostname(),
            "pid": os.getpid()}


_lease_free = lease_free  # (the database's rule: its writers check the lease too)


class QueuedStore:
    """A :class:`MonitorStore` whose writes run on a background thread, in order.

    The compensation loop never waits for the database (another process holding SQLite's write lock, a
    PostgreSQL server restarting): events, states and activations go to a bounded queue and a writer thread
    retries them until they are stored. A write that waited long, or a queue that backs up, is logged as a
    ``store`` event once the database takes writes again; when the queue is full, the heartbeat and state
    records are skipped first (the next one replaces them), never an event. Reads (WAL snapshots on SQLite)
    stay direct.

    Parameters
    ----------
    store : the synchronous store
    maxsize : queue bound [items]
    slow_s : a write waiting longer than this is reported [s]
    """

    def __init__(self, store: MonitorStore, maxsize: int = 20_000, slow_s: float = 2.0):
        self.store = store
        self.db = store.db
        self.slow_s = slow_s
        self._q: queue.Queue = queue.Queue(maxsize)
        self._closing = threading.Event()
        self.stats = {"queued_max": 0, "skipped_states": 0, "failed": 0, "slow": 0}
        self.error: str | None = None
        self._thread = threading.Thread(target=self._work, name="monitor-store", daemon=True)
        self._thread.start()

    # writes: queued
    def log_event(self, kind: str, machine_time_s: float | None, payload: Mapping, key: str | None = None) -> None:
        self._put(("event", (kind, machine_time_s, json.loads(jsonio.dumps(dict(payload))), key)), essential=True)

    def put_state(self, key: str, value: str) -> None:
        self._put(("state", (key, value)), essential=not key.endswith(":heartbeat"))

    def call(self, fn: Callable[[], object], what: str) -> None:
        self._put(("call", (fn, what)), essential=True)

    # reads: direct
    def events(self, *a, **kw):
        return self.store.events(*a, **kw)

    def get_state(self, key: str) -> str | None:
        return self.store.get_state(key)

    def acquire_lease(self, *a, **kw):
        return self.store.acquire_lease(*a, **kw)

    def release_lease(self, *a, **kw):
        return self.store.release_lease(*a, **kw)

    def backlog(self) -> int:
        """Writes waiting [items]."""
        return self._q.qsize()

    def _put(self, item, essential: bool) -> None:
        try:
            self._q.put_nowait(item)
        except queue.Full:
            if not essential:
                self.stats["skipped_states"] += 1
                return
            log.error("the database has not taken writes for a while: %d writes queued; waiting for room",
                      self._q.qsize())
            self._q.put(item)  # an event is never dropped: better late than lost
        self.stats["queued_max"] = max(self.stats["queued_max"], self._q.qsize())

    def flush(self, timeout_s: float | None = None) -> bool:
        """Wait until every queued write is stored (or ``timeout_s`` passed); True when the queue is empty."""
        t_end = None if timeout_s is None else time.monotonic() + timeout_s
        while self._q.unfinished_tasks:
            if t_end is not None and time.monotonic() > t_end:
                return False
            time.sleep(0.01)
        return True

    def close(self, timeout_s: float = 60.0) -> None:
        """Store what is queued (for at most ``timeout_s``), then stop the writer."""
        done = self.flush(timeout_s)
        if not done:
            log.error("%d writes could not be stored in %.0f s and are lost: %s", self._q.qsize(), timeout_s, self.error)
        self._closing.set()
        self._thread.join(timeout=5.0)

    def _work(self) -> None:
        while not self._closing.is_set():
            try:
                kind, args = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            t0 = time.monotonic()
            delay = 0.1
            while True:
                try:
                    if kind == "event":
                        self.store.log_event(*args)
                    elif kind == "state":
                        self.store.put_state(*args)
                    else:
                        args[0]()
                    break
                except Exception as exc:  # noqa: BLE001 - the writer retries whatever the database says
                    self.error = f"{type(exc).__name__}: {exc}"
                    if kind == "call" and not _transient(exc):
                        self.stats["failed"] += 1
                        log.error("%s failed: %s", args[1], exc)
                        break
                    if self._closing.is_set():
                        break
                    log.warning("database write (%s) failed, retrying in %.1f s: %s", kind, delay, exc)
                    time.sleep(delay)
                    delay = min(2 * delay, 5.0)
            waited = time.monotonic() - t0
            self._q.task_done()
            if waited > self.slow_s:
                self.stats["slow"] += 1
                try:
                    self.store.log_event("store", None, {"status": "slow", "waited_s": round(waited, 3),
                                                         "queued": self._q.qsize(), "last_error": self.error,
                                                         "message": f"the database took {waited:.1f} s for one write; "
                                                         "compensation went on, the writes were queued"})
                except Exception:
                    log.exception("cannot log the slow write")


def _transient(exc: BaseException) -> bool:
    """A lock timeout or a lost connection: worth retrying."""
    text = str(exc).lower()
    return any(w in text for w in ("locked", "busy", "timeout", "connection", "server closed", "could not connect"))


__all__ = ["Event", "LeaseHeld", "MonitorStore", "QueuedStore", "lease_owner"]
