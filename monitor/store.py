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
from collections.abc import Mapping
from dataclasses import dataclass

from hybridcomp.chardiag.db import EVENTS_LOCK, CDDatabase, utc_now
from hybridcomp.models import jsonio


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


__all__ = ["Event", "MonitorStore"]
