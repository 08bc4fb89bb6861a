"""The CD database: SQLite file by default, any SQLAlchemy URL (PostgreSQL for a fleet).

Tables (schema version :data:`SCHEMA_VERSION`, kept in ``meta``):

* ``load_cases``: one row per machine, pose and training load case — its signature and the structure model's
  reference temperatures;
* ``cds``: every CD ever stored, its XML (the exchange format is the record) and searchable metadata;
* ``active``: the active CD per machine, pose and direction (three rows per pose, replaced atomically);
* ``events``: activations (written here, in the transaction that changes ``active``) and the monitor's
  switches, generations, decisions and warnings, with their numbers as JSON; an event may carry a unique
  ``key`` so a daemon that is killed and restarted never writes one twice;
* ``state``: a small key–value store (JSON text) for a daemon's state;
* ``grids``, ``grid_cds``, ``active_grid`` (schema 2): CD sets per support point of a workspace grid
  (:mod:`hybridcomp.chardiag.grid`): the grid record (axes, positions, the model's pose), its points' CD ids, and the
  active grid per machine (activating a grid activates every point's set in ``active`` too).

This module stores CDs, load cases and active sets; the monitor's events and state are read and written by
``hybridcomp.monitor.store`` through the same engine (one database, one schema, created and migrated here).

Read-only uses (:class:`CDDatabase` with ``readonly=True``: listing, showing, searching, exporting, a monitor's
status) never create anything: a missing SQLite file, a file that is not an SQLite database and a database without
the hybridcomp schema are errors, and no folder is made. Writers create the database and its folder.

Writers serialise per database: SQLite opens every write transaction with ``BEGIN IMMEDIATE`` (WAL mode, so
readers never wait); PostgreSQL takes transaction-scoped advisory locks: one per machine and pose for an
activation, one for every transaction that writes events (so ids become visible in order), one for schema
creation and migration. Two processes activating sets for one pose at once therefore leave one complete set active,
never a mixture.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import time
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from hybridcomp.chardiag.cd import DIRECTIONS, CDSet, CharDiagram, pose_key
from hybridcomp.chardiag.xmlio import cd_from_bytes, cd_to_bytes
from hybridcomp.errors import HybridcompError
from hybridcomp.models import jsonio

log = logging.getLogger(__name__)

SCHEMA_VERSION = 2
# event writers serialise on this lock, so event ids become visible in commit order (a reader tailing with
# ``since_id`` never skips an event that commits after a later id)
EVENTS_LOCK = "hybridcomp events"


class CDDatabaseError(HybridcompError, RuntimeError):
    """The CD database cannot be opened or used; the message names the URL, table and value."""


def _sqlalchemy():
    try:
        import sqlalchemy
    except ImportError:  # pragma: no cover - depends on the installation
        raise CDDatabaseError("the CD database needs SQLAlchemy: pip install 'hybridcomp[db]' "
                              "(and 'hybridcomp[postgres]' for PostgreSQL)") from None
    return sqlalchemy


def monitor_lease_key(machine: str, pose: str) -> str:
    """The ``state`` row of the lease a monitoring daemon holds on a machine's pose (``monitor.store``)."""
    return f"lease:monitor:{machine}:{pose}"


def lease_free(cur: Mapping, now_unix: float) -> bool:
    """Whether a lease record binds no one: it has expired, or its holder was a process on this host that is gone.

    (A daemon killed with -9 leaves its lease behind; on its own host that is seen at once.)
    """
    if not float(cur.get("expires_unix", 0.0)) > now_unix:
        return True
    if cur.get("host") == socket.gethostname() and isinstance(cur.get("pid"), int):
        try:
            os.kill(cur["pid"], 0)
        except ProcessLookupError:
            return True  # its process is gone
        except PermissionError:
            return False  # it runs (as another user)
    return False


def utc_now() -> str:
    """The current UTC time as ISO 8601 text with microseconds (the `created` columns)."""
    return datetime.now(UTC).isoformat(timespec="microseconds")


SQLITE_HEADER = b"SQLite format 3\x00"


def _url(url_or_path: str | Path, create: bool = True) -> str:
    """The SQLAlchemy URL of a URL or a file path (SQLite); ``create``: make the file's folder."""
    s = str(url_or_path)
    if "://" in s:
        return s
    p = Path(s)
    if create:
        p.parent.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{p}"


def sqlite_file(url_or_path: str | Path | None) -> Path | None:
    """The file of an SQLite database given as a path or an ``sqlite://`` URL; None for other databases and memory."""
    if url_or_path is None:
        return None
    s = str(url_or_path)
    if "://" not in s:
        return Path(s)
    if not s.startswith("sqlite"):
        return None
    url = _sqlalchemy().engine.make_url(s)
    if not url.database or url.database == ":memory:" or url.query.get("uri") or url.database.startswith("file:"):
        return None
    return Path(url.database)


def _check_sqlite_file(path: Path, must_exist: bool) -> None:
    """Refuse a path that is not an SQLite database file (and, when ``must_exist``, a missing one), in one line."""
    if not path.exists():
        if must_exist:
            raise CDDatabaseError(f"CD database {path} does not exist (read-only: nothing is created; 'hybridcomp cd "
                                  "db import' or 'cd fit --db' create a database)")
        return
    if not path.is_file():
        raise CDDatabaseError(f"CD database {path} is not a file")
    try:
        with path.open("rb") as fh:
            head = fh.read(len(SQLITE_HEADER))
    except OSError as exc:
        raise CDDatabaseError(f"cannot open CD database {path}: {exc.strerror}") from None
    if head == b"" and not must_exist:  # an empty file is an empty SQLite database to a writer (``touch db.sqlite``)
        return
    if head != SQLITE_HEADER:
        raise CDDatabaseError(f"CD database {path} is not an SQLite database"
                              + (" (the file is empty)" if head == b"" else ""))


def _reason(exc: BaseException) -> str:
    """The first line of a database error's own message (without SQLAlchemy's statement and background link)."""
    text = str(getattr(exc, "orig", None) or exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _redact(url: str) -> str:
    """The URL without its password, for messages."""
    if "@" in url and "://" in url:
        scheme, rest = url.split("://", 1)
        cred, host = rest.rsplit("@", 1)
        return f"{scheme}://{cred.split(':', 1)[0]}:***@{host}"
    return url


@dataclass(frozen=True)
class Match:
    """A stored CD set that fits a load case.

    Attributes
    ----------
    ids : CD id per direction
    load_case : its training load case
    load_case_id : its row in ``load_cases``
    delta_T_K : max |T_reference − T| over the common sensors [K]
    distance : load-case signature distance (NaN when no signature was given or stored)
    """

    ids: dict[str, int]
    load_case: str
    load_case_id: int
    delta_T_K: float
    distance: float


@dataclass(frozen=True)
class GridMatch:
    """A stored CD grid that fits a load case (:meth:`CDDatabase.search_grids`).

    Attributes
    ----------
    grid_id : its id
    load_case : its training load case(s)
    delta_T_K : max |T_reference − T| over its points' sets and the common sensors [K]
    distance : the largest load-case signature distance over its points' sets (NaN when none was given or stored)
    """

    grid_id: int
    load_case: str
    delta_T_K: float
    distance: float


def _tables(sa):
    md = sa.MetaData()
    sa.Table("meta", md, sa.Column("key", sa.String(64), primary_key=True), sa.Column("value", sa.Text, nullable=False))
    sa.Table(
        "load_cases", md,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("machine", sa.String(200), nullable=False),
        sa.Column("pose_key", sa.String(400), nullable=False),
        sa.Column("name", sa.String(400), nullable=False),
        sa.Column("signature", sa.Text, nullable=False),
        sa.Column("t_reference", sa.Text, nullable=False),
        sa.Column("created", sa.String(40), nullable=False),
        sa.UniqueConstraint("machine", "pose_key", "name", "t_reference", name="uq_load_case"),
    )
    sa.Table(
        "cds", md,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("machine", sa.String(200), nullable=False, index=True),
        sa.Column("machine_sha256", sa.String(64), nullable=False),
        sa.Column("pose_key", sa.String(400), nullable=False),
        sa.Column("direction", sa.String(1), nullable=False),
        sa.Column("load_case_id", sa.Integer, sa.ForeignKey("load_cases.id"), nullable=False, index=True),
        sa.Column("n_active_inputs", sa.Integer, nullable=False),
        sa.Column("rms_residual_um", sa.Float, nullable=True),
        sa.Column("created", sa.String(40), nullable=False),
        sa.Column("software_version", sa.String(40), nullable=False),
        sa.Column("xml", sa.LargeBinary, nullable=False),
    )
    sa.Table(
        "active", md,
        sa.Column("machine", sa.String(200), primary_key=True),
        sa.Column("pose_key", sa.String(400), primary_key=True),
        sa.Column("direction", sa.String(1), primary_key=True),
        sa.Column("cd_id", sa.Integer, sa.ForeignKey("cds.id"), nullable=False),
        sa.Column("activated", sa.String(40), nullable=False),
    )
    sa.Table(
        "events", md,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("kind", sa.String(40), nullable=False, index=True),
        sa.Column("machine_time_s", sa.Float, nullable=True),
        sa.Column("created", sa.String(40), nullable=False),
        sa.Column("payload", sa.Text, nullable=False),
        sa.Column("key", sa.String(400), nullable=True, unique=True),
    )
    sa.Table(
        "grids", md,
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("machine", sa.String(200), nullable=False, index=True),
        sa.Column("grid", sa.Text, nullable=False),  # SupportGrid.as_dict() as JSON
        sa.Column("load_case", sa.String(400), nullable=False),
        sa.Column("created", sa.String(40), nullable=False),
    )
    sa.Table(
        "grid_cds", md,
        sa.Column("grid_id", sa.Integer, sa.ForeignKey("grids.id"), primary_key=True),
        sa.Column("point", sa.Integer, primary_key=True),
        sa.Column("direction", sa.String(1), primary_key=True),
        sa.Column("pose_key", sa.String(400), nullable=False),
        sa.Column("cd_id", sa.Integer, sa.ForeignKey("cds.id"), nullable=False),
    )
    sa.Table(
        "active_grid", md,
        sa.Column("machine", sa.String(200), primary_key=True),
        sa.Column("grid_id", sa.Integer, sa.ForeignKey("grids.id"), nullable=False),
        sa.Column("activated", sa.String(40), nullable=False),
    )
    sa.Table(
        "state", md,
        sa.Column("key", sa.String(200), primary_key=True),
        sa.Column("value", sa.Text, nullable=False),
        sa.Column("updated", sa.String(40), nullable=False),
    )
    return md


def _readonly_connector(path: Path):
    """A DB-API connect function that opens an existing SQLite file without creating it.

    Opened read-write when the file and its folder are writable (the connection is ``query_only``), so SQLite's
    -wal and -shm files go again when it closes; read-only (``mode=ro``) otherwise.
    """
    import sqlite3

    folder = path.absolute().parent
    mode = "rw" if os.access(path, os.W_OK) and os.access(folder, os.W_OK) else "ro"
    uri = f"{path.absolute().as_uri()}?mode={mode}"

    def connect():
        return sqlite3.connect(uri, uri=True, timeout=60.0, check_same_thread=False)

    return connect


def _migrate_1(conn) -> None:
    """Version 1 → 2: the CD grids' tables.

    ``grids``, ``grid_cds`` and ``active_grid`` are new tables, created from the table definitions before the
    migration runs; no existing table changes.
    """


# schema migrations: version N → N+1, each a function of a connection
MIGRATIONS: dict[int, object] = {1: _migrate_1}


class CDDatabase:
    """The CD database behind a SQLAlchemy engine.

    Parameters
    ----------
    url_or_path : a SQLAlchemy URL (``postgresql+psycopg://user:pw@host/db``) or a file path (SQLite)
    readonly : only read: create, migrate and write nothing. A missing SQLite file, a file that is not an SQLite
        database and a database without the hybridcomp schema raise :class:`CDDatabaseError`; no folder is made.
        Otherwise the database (and an SQLite file's folder) is created when missing.
    """

    def __init__(self, url_or_path: str | Path, *, readonly: bool = False):
        sa = _sqlalchemy()
        self.sa = self._sa = sa
        self.readonly = bool(readonly)
        self.url = _url(url_or_path, create=not self.readonly)
        kwargs = {}
        self.dialect = self.url.split(":", 1)[0].split("+", 1)[0]
        file = sqlite_file(url_or_path) if self.dialect == "sqlite" else None
        if file is not None:
            _check_sqlite_file(file, must_exist=self.readonly)
        if self.dialect == "sqlite":
            kwargs["connect_args"] = {"timeout": 60.0, "check_same_thread": False}
            if self.readonly and file is not None:
                kwargs["creator"] = _readonly_connector(file)
        else:  # a monitor runs for weeks: survive a database server restart
            kwargs["pool_pre_ping"] = True
        try:
            self.engine = sa.create_engine(self.url, **kwargs)
        except Exception as exc:  # noqa: BLE001 - any driver or URL problem
            raise CDDatabaseError(f"cannot open CD database {_redact(self.url)}: {_reason(exc)}") from None
        if self.dialect == "sqlite":
            readonly = self.readonly

            @sa.event.listens_for(self.engine, "connect")
            def _connect(dbapi_conn, _rec):
                dbapi_conn.isolation_level = None  # we issue BEGIN ourselves
                cur = dbapi_conn.cursor()
                if readonly:  # a reader changes nothing, not even the journal mode
                    cur.execute("PRAGMA query_only=ON")
                else:
                    cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA foreign_keys=ON")
                cur.execute("PRAGMA busy_timeout=60000")
                cur.close()

            @sa.event.listens_for(self.engine, "begin")
            def _begin(conn):  # writers take the write lock up front; readers get a snapshot and never wait
                conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("write") else "BEGIN")

        self.md = _tables(sa)
        self.t = self.md.tables
        try:
            if self.readonly:
                self._check_schema()
            else:
                self._init_schema()
        except BaseException:
            self.engine.dispose()  # no connection outlives a refused opening
            raise

    # ------------------------------------------------------------------ plumbing

    def write(self, fn, what: str):
        """Run ``fn(conn)`` in a write transaction, retrying a few times on lock or serialisation conflicts.

        Every writer of this database goes through here, the monitor's store too.
        """
        sa = self._sa
        if self.readonly:
            raise CDDatabaseError(f"{_redact(self.url)}: {what}: the database was opened read-only")
        delay = 0.05
        for attempt in range(8):
            try:
                with self.engine.connect().execution_options(write=True) as conn, conn.begin():
                    return fn(conn)
            except sa.exc.OperationalError as exc:
                if attempt == 7:
                    raise CDDatabaseError(f"{_redact(self.url)}: {what} failed: {exc.orig}") from None
                log.debug("%s: retry after %s", what, exc.orig)
                time.sleep(delay)
                delay *= 2

    def lock(self, conn, name: str) -> None:
        """On PostgreSQL, a transaction-scoped advisory lock (SQLite's BEGIN IMMEDIATE already serialises writers)."""
        if self.dialect == "postgresql":
            key = zlib.crc32(name.encode()) - 2**31
            conn.execute(self._sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": key})

    def _init_schema(self) -> None:
        """Create the tables, or bring an older schema up to :data:`SCHEMA_VERSION`, in one serialised transaction.

        Two processes opening an old database at once run each migration step once. Migration steps alter existing
        tables; new tables come from the table definitions.
        """
        sa = self._sa
        meta = self.t["meta"]

        def init(conn):
            self.lock(conn, "hybridcomp schema")
            self.md.create_all(conn, checkfirst=True)
            row = conn.execute(sa.select(meta.c.value).where(meta.c.key == "schema_version")).first()
            if row is None:
                conn.execute(meta.insert().values(key="schema_version", value=str(SCHEMA_VERSION)))
                return SCHEMA_VERSION
            version = int(row[0])
            while version < SCHEMA_VERSION:
                log.info("%s: migrating the schema from version %d", _redact(self.url), version)
                MIGRATIONS[version](conn)
                version += 1
                conn.execute(meta.update().where(meta.c.key == "schema_version").values(value=str(version)))
            return version

        try:
            version = self.write(init, "creating or migrating the schema")
        except sa.exc.IntegrityError:  # another process created it at the same moment
            version = self.schema_version()
        except sa.exc.SQLAlchemyError as exc:
            raise CDDatabaseError(f"cannot open CD database {_redact(self.url)}: {_reason(exc)}") from None
        if version > SCHEMA_VERSION:
            raise CDDatabaseError(f"{_redact(self.url)}: meta.schema_version is {version}, newer than this "
                                  f"hybridcomp's {SCHEMA_VERSION}: upgrade hybridcomp")

    def _check_schema(self) -> None:
        """A read-only opening: the hybridcomp schema must be there, at this hybridcomp's version."""
        sa = self._sa
        meta = self.t["meta"]
        name = _redact(self.url)
        try:
            with self.engine.connect() as conn:
                if not sa.inspect(conn).has_table("meta"):
                    raise CDDatabaseError(f"{name} is not a hybridcomp CD database (it has no table 'meta')")
                row = conn.execute(sa.select(meta.c.value).where(meta.c.key == "schema_version")).first()
        except sa.exc.SQLAlchemyError as exc:
            raise CDDatabaseError(f"cannot open CD database {name}: {_reason(exc)}") from None
        if row is None:
            raise CDDatabaseError(f"{name} is not a hybridcomp CD database (meta has no schema_version)")
        version = int(row[0])
        if version > SCHEMA_VERSION:
            raise CDDatabaseError(f"{name}: meta.schema_version is {version}, newer than this hybridcomp's "
                                  f"{SCHEMA_VERSION}: upgrade hybridcomp")
        if version < SCHEMA_VERSION:
            raise CDDatabaseError(f"{name}: meta.schema_version is {version}, older than this hybridcomp's "
                                  f"{SCHEMA_VERSION}: a command that writes (hybridcomp cd db import, activate) migrates it")

    def schema_version(self) -> int:
        sa = self._sa
        meta = self.t["meta"]
        with self.engine.connect() as conn:
            return int(conn.execute(sa.select(meta.c.value).where(meta.c.key == "schema_version")).scalar_one())

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ CDs and load cases

    def _insert(self, conn, cd: CharDiagram, xml: bytes, load_case: str | None) -> int:
        """Insert a CD (and its load case, once) in an open write transaction; returns its id."""
        sa = self._sa
        lc, cds = self.t["load_cases"], self.t["cds"]
        name = load_case if load_case is not None else cd.load_case
        tref = jsonio.dumps(dict(cd.t_reference_degC), sort_keys=True)
        q = sa.select(lc.c.id).where(lc.c.machine == cd.machine, lc.c.pose_key == cd.pose_key, lc.c.name == name,
                                     lc.c.t_reference == tref)
        lc_id = conn.execute(q).scalar()
        if lc_id is None:
            lc_id = conn.execute(lc.insert().values(
                machine=cd.machine, pose_key=cd.pose_key, name=name, t_reference=tref,
                signature=jsonio.dumps([float(v) for v in cd.signature]), created=utc_now())).inserted_primary_key[0]
        return int(conn.execute(cds.insert().values(
            machine=cd.machine, machine_sha256=cd.machine_sha256, pose_key=cd.pose_key, direction=cd.direction,
            load_case_id=lc_id, n_active_inputs=len(cd.active_inputs),
            rms_residual_um=cd.fit_stats().get("rms_residual_um"), created=cd.created or utc_now(),
            software_version=cd.software_version, xml=xml)).inserted_primary_key[0])

    def add(self, cd: CharDiagram, load_case: str | None = None) -> int:
        """Store a CD (and its load case, once); returns its id."""
        xml = cd_to_bytes(cd)
        return int(self.write(lambda conn: self._insert(conn, cd, xml, load_case), "storing a CD"))

    def add_many(self, cds: Sequence[CharDiagram]) -> list[tuple[int, bool]]:
        """Store CDs in one transaction, each unless a CD with the same XML is already stored (an import).

        All or nothing: when one cannot be stored, none is. Importers serialise, so two importing the same file at
        once store it once.

        Returns
        -------
        per CD, in order: ``(id, True)`` when it was stored, ``(id of the stored one, False)`` when its XML (the
        record) was already there, from before or earlier in ``cds``
        """
        sa = self._sa
        table = self.t["cds"]
        items = [(cd, cd_to_bytes(cd)) for cd in cds]

        def add(conn):
            self.lock(conn, "hybridcomp cds import")
            out = []
            for cd, xml in items:
                found = conn.execute(sa.select(table.c.id).where(
                    table.c.machine == cd.machine, table.c.pose_key == cd.pose_key, table.c.direction == cd.direction,
                    table.c.xml == xml).order_by(table.c.id).limit(1)).scalar()
                out.append((int(found), False) if found is not None else (self._insert(conn, cd, xml, None), True))
            return out

        return self.write(add, f"storing {len(items)} CD(s)")

    def add_set(self, cds: Mapping[str, CharDiagram], load_case: str | None = None) -> dict[str, int]:
        """Store the three CDs of one pose; returns their ids by direction."""
        return {d: self.add(cds[d], load_case) for d in DIRECTIONS}

    def xml(self, cd_id: int) -> bytes:
        """The stored XML of a CD."""
        sa = self._sa
        cds = self.t["cds"]
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(cds.c.xml).where(cds.c.id == int(cd_id))).first()
        if row is None:
            raise CDDatabaseError(f"{_redact(self.url)}: table cds has no id {cd_id}")
        return bytes(row[0])

    def get(self, cd_id: int) -> CharDiagram:
        """A stored CD."""
        return cd_from_bytes(self.xml(cd_id), source=f"cds id {cd_id}")

    def list(self, machine: str | None = None) -> list[dict]:
        """Summary rows of the stored CDs (newest last), with whether each is active."""
        sa = self._sa
        cds, lc, act = self.t["cds"], self.t["load_cases"], self.t["active"]
        q = (sa.select(cds.c.id, cds.c.machine, cds.c.pose_key, cds.c.direction, lc.c.name.label("load_case"),
                       cds.c.n_active_inputs, cds.c.rms_residual_um, cds.c.created, act.c.cd_id.label("active"))
             .join(lc, lc.c.id == cds.c.load_case_id)
             .outerjoin(act, act.c.cd_id == cds.c.id).order_by(cds.c.id))
        if machine is not None:
            q = q.where(cds.c.machine == machine)
        with self.engine.connect() as conn:
            return [{**r._asdict(), "active": r.active is not None} for r in conn.execute(q)]

    def load_cases(self, machine: str, pose: str) -> list[dict]:
        """Stored load cases of a machine and pose with their signature and reference temperatures."""
        sa = self._sa
        lc = self.t["load_cases"]
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(lc).where(lc.c.machine == machine, lc.c.pose_key == pose).order_by(lc.c.id))
            return [{"id": r.id, "name": r.name, "signature": np.array(json.loads(r.signature), float),
                     "t_reference_degC": json.loads(r.t_reference), "created": r.created} for r in rows]

    def _complete_sets(self, conn, machine: str, pose: str) -> dict[int, dict[str, int]]:
        """Load-case id → the newest CD id per direction, for load cases with all three directions."""
        sa = self._sa
        cds = self.t["cds"]
        q = (sa.select(cds.c.load_case_id, cds.c.direction, sa.func.max(cds.c.id))
             .where(cds.c.machine == machine, cds.c.pose_key == pose)
             .group_by(cds.c.load_case_id, cds.c.direction))
        sets: dict[int, dict[str, int]] = {}
        for lc_id, d, cd_id in conn.execute(q):
            sets.setdefault(lc_id, {})[d] = int(cd_id)
        return {k: v for k, v in sets.items() if set(v) == set(DIRECTIONS)}

    def search(self, machine: str, pose: str, signature, t_reference_degC: Mapping[str, float],
               threshold_K: float = 0.5, layout=None) -> list[Match]:
        """Stored CD sets for a load case, best first.

        Parameters
        ----------
        machine, pose : machine name and :func:`pose_key`
        signature : the current load-case signature, or None
        t_reference_degC : the structure model's current sensor temperatures [°C]
        threshold_K : a set fits when max |T_reference − T| over the common sensors is at most this [K]
        layout : ``histogram.SignatureLayout`` for :func:`histogram.signature_distance`; None: Euclidean

        Returns
        -------
        the fitting complete (X, Y, Z) sets, by signature distance (when a signature is given) then ΔT
        """
        if not threshold_K >= 0:
            raise ValueError(f"threshold_K must be ≥ 0, got {threshold_K!r}")
        sig = None if signature is None else np.asarray(signature, float)
        with self.engine.connect() as conn:
            sets = self._complete_sets(conn, machine, pose)
        out = []
        for row in self.load_cases(machine, pose):
            if row["id"] not in sets:
                continue
            common = [s for s in t_reference_degC if s in row["t_reference_degC"]]
            if not common:
                continue
            dT = max(abs(float(row["t_reference_degC"][s]) - float(t_reference_degC[s])) for s in common)
            if not dT <= threshold_K:
                continue
            dist = math.nan
            if sig is not None and row["signature"].shape == sig.shape and sig.size:
                if layout is not None:
                    from hybridcomp.histogram.signature import signature_distance

                    dist = float(signature_distance(sig, row["signature"], layout))
                else:
                    dist = float(np.linalg.norm(sig - row["signature"]))
            out.append(Match(ids=sets[row["id"]], load_case=row["name"], load_case_id=row["id"], delta_T_K=dT,
                             distance=dist))
        out.sort(key=lambda m: (math.inf if math.isnan(m.distance) else m.distance, m.delta_T_K, -m.load_case_id))
        return out

    # ------------------------------------------------------------------ activation

    def activate(self, machine: str, pose: str, ids: Mapping[str, int], reason: str = "",
                 machine_time_s: float | None = None, event_key: str | None = None,
                 lease_owner: str | None = None) -> int | None:
        """Make three stored CDs (X, Y, Z) the active set of a pose, atomically.

        An ``activation`` event is logged in the same transaction. Returns the event id (None when ``event_key`` was
        already logged: then nothing changes). While a monitoring daemon holds the pose's lease, only that daemon
        (``lease_owner``: its owner token) may change the pose's active set: anyone else is refused
        (:class:`CDDatabaseError` naming the daemon), in the same transaction as the check.
        """
        sa = self._sa
        cds, act, ev = self.t["cds"], self.t["active"], self.t["events"]
        if set(ids) != set(DIRECTIONS):
            raise ValueError(f"activate: needs one CD id per direction {DIRECTIONS}, got {sorted(ids)}")

        def run(conn):
            self.lock(conn, f"active {machine}\0{pose}")
            self._refuse_held(conn, machine, pose, lease_owner)
            self.lock(conn, EVENTS_LOCK)
            if event_key is not None and conn.execute(sa.select(ev.c.id).where(ev.c.key == event_key)).first():
                return None
            for d, cd_id in ids.items():
                row = conn.execute(sa.select(cds.c.machine, cds.c.pose_key, cds.c.direction)
                                   .where(cds.c.id == int(cd_id))).first()
                if row is None:
                    raise CDDatabaseError(f"{_redact(self.url)}: activate: table cds has no id {cd_id}")
                if (row.machine, row.pose_key, row.direction) != (machine, pose, d):
                    raise CDDatabaseError(f"activate: CD {cd_id} is for {row.machine} {row.pose_key} direction "
                                          f"{row.direction}, not for {machine} {pose} direction {d}")
            previous = {r.direction: r.cd_id for r in conn.execute(
                sa.select(act.c.direction, act.c.cd_id).where(act.c.machine == machine, act.c.pose_key == pose))}
            conn.execute(act.delete().where(act.c.machine == machine, act.c.pose_key == pose))
            now = utc_now()
            conn.execute(act.insert(), [{"machine": machine, "pose_key": pose, "direction": d, "cd_id": int(ids[d]),
                                         "activated": now} for d in DIRECTIONS])
            payload = {"machine": machine, "pose": pose, "ids": {d: int(ids[d]) for d in DIRECTIONS},
                       "previous": previous, "reason": reason}
            return conn.execute(ev.insert().values(kind="activation", machine_time_s=machine_time_s, created=now,
                                                   payload=jsonio.dumps(payload), key=event_key)).inserted_primary_key[0]

        return self.write(run, "activating a CD set")

    def pose_holder(self, machine: str, pose: str, now_unix: float | None = None) -> dict | None:
        """The lease record of the monitoring daemon that holds the pose now, or None."""
        with self.engine.connect() as conn:
            return self._holder(conn, machine, pose, None, time.time() if now_unix is None else now_unix)

    def check_pose_free(self, machine: str, pose: str, lease_owner: str | None = None) -> None:
        """Raise :class:`CDDatabaseError` when a monitoring daemon other than ``lease_owner`` holds the pose."""
        with self.engine.connect() as conn:
            self._refuse_held(conn, machine, pose, lease_owner, lock=False)

    def _holder(self, conn, machine: str, pose: str, owner: str | None, now_unix: float) -> dict | None:
        sa = self._sa
        st = self.t["state"]
        text = conn.execute(sa.select(st.c.value).where(st.c.key == monitor_lease_key(machine, pose))).scalar()
        if not text:
            return None
        cur = json.loads(text)
        return None if cur.get("owner") == owner or lease_free(cur, now_unix) else cur

    def _refuse_held(self, conn, machine: str, pose: str, owner: str | None, lock: bool = True) -> None:
        if lock:  # (in a write transaction: serialised with the daemon's lease)
            self.lock(conn, monitor_lease_key(machine, pose))
        cur = self._holder(conn, machine, pose, owner, time.time())
        if cur is not None:
            raise CDDatabaseError(
                f"{_redact(self.url)}: {machine} {pose} is held by a monitoring daemon (pid {cur.get('pid')} on "
                f"{cur.get('host')}, lease until {datetime.fromtimestamp(float(cur['expires_unix']), UTC):%H:%M:%S} "
                "UTC): it chooses the pose's active set; stop it first ('hybridcomp monitor status' shows it)")

    def active_ids(self, machine: str, pose: str) -> dict[str, int]:
        sa = self._sa
        act = self.t["active"]
        with self.engine.connect() as conn:
            return {r.direction: int(r.cd_id) for r in conn.execute(
                sa.select(act.c.direction, act.c.cd_id).where(act.c.machine == machine, act.c.pose_key == pose))}

    def active_set(self, machine: str, pose: str) -> CDSet | None:
        """The active CD set of a pose, or None."""
        ids = self.active_ids(machine, pose)
        if not ids:
            return None
        return CDSet({d: self.get(i) for d, i in ids.items()}, ids)

    # ------------------------------------------------------------------ CD grids (CD sets per support point)

    def add_grid(self, grid, load_case: str | None = None) -> int:
        """Store a :class:`~hybridcomp.chardiag.grid.CDGrid`; returns the grid's id.

        Every point's CDs and the grid record, in one transaction (all or nothing).
        """
        from hybridcomp.chardiag.grid import point_keys

        grids, gc = self.t["grids"], self.t["grid_cds"]
        keys = point_keys(grid.grid)
        items = [[(s.cds[d], cd_to_bytes(s.cds[d])) for d in DIRECTIONS] for s in grid.sets]
        name = load_case if load_case is not None else grid.load_case

        def add(conn):
            gid = int(conn.execute(grids.insert().values(
                machine=grid.machine, grid=jsonio.dumps(grid.grid.as_dict()), load_case=name,
                created=utc_now())).inserted_primary_key[0])
            rows = []
            for i, (key, cds) in enumerate(zip(keys, items)):
                for cd, xml in cds:
                    rows.append({"grid_id": gid, "point": i, "direction": cd.direction, "pose_key": key,
                                 "cd_id": self._insert(conn, cd, xml, load_case)})
            conn.execute(gc.insert(), rows)
            return gid

        return int(self.write(add, f"storing a CD grid of {len(items)} support points"))

    def grids(self, machine: str | None = None) -> list[dict]:
        """Summary rows of the stored CD grids (oldest first).

        Each: id, machine, axes, shape, load case, created, the largest RMS fit residual of its CDs [µm], whether
        it is the machine's active grid.
        """
        sa = self._sa
        grids, gc, cds, ag = self.t["grids"], self.t["grid_cds"], self.t["cds"], self.t["active_grid"]
        worst = (sa.select(gc.c.grid_id, sa.func.max(cds.c.rms_residual_um).label("rms"))
                 .join(cds, cds.c.id == gc.c.cd_id).group_by(gc.c.grid_id).subquery())
        q = (sa.select(grids.c.id, grids.c.machine, grids.c.grid, grids.c.load_case, grids.c.created,
                       worst.c.rms, ag.c.grid_id.label("active"))
             .outerjoin(worst, worst.c.grid_id == grids.c.id)
             .outerjoin(ag, sa.and_(ag.c.grid_id == grids.c.id, ag.c.machine == grids.c.machine))
             .order_by(grids.c.id))
        if machine is not None:
            q = q.where(grids.c.machine == machine)
        out = []
        with self.engine.connect() as conn:
            for r in conn.execute(q):
                g = json.loads(r.grid)
                out.append({"id": int(r.id), "machine": r.machine, "axes": g["axes"],
                            "shape": [len(p) for p in g["positions_mm"]], "load_case": r.load_case,
                            "created": r.created, "max_rms_residual_um": r.rms, "active": r.active is not None})
        return out

    def grid_ids(self, grid_id: int) -> tuple[dict, list[dict[str, int]]]:
        """A stored grid's record (machine, grid dict, load case) and its points' CD ids by direction."""
        sa = self._sa
        grids, gc = self.t["grids"], self.t["grid_cds"]
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(grids).where(grids.c.id == int(grid_id))).first()
            if row is None:
                raise CDDatabaseError(f"{_redact(self.url)}: table grids has no id {grid_id}")
            pts = conn.execute(sa.select(gc.c.point, gc.c.direction, gc.c.cd_id)
                               .where(gc.c.grid_id == int(grid_id)).order_by(gc.c.point)).all()
        rec = {"machine": row.machine, "grid": json.loads(row.grid), "load_case": row.load_case, "created": row.created}
        n = 1
        for p in rec["grid"]["positions_mm"]:
            n *= len(p)
        ids: list[dict[str, int]] = [{} for _ in range(n)]
        for p, d, cd_id in pts:
            if not 0 <= p < n:
                raise CDDatabaseError(f"{_redact(self.url)}: grid {grid_id}: point {p} is not one of its {n} points")
            ids[p][d] = int(cd_id)
        bad = [i for i, x in enumerate(ids) if set(x) != set(DIRECTIONS)]
        if bad:
            raise CDDatabaseError(f"{_redact(self.url)}: grid {grid_id}: support point {bad[0]} has CDs for "
                                  f"{sorted(ids[bad[0]])}, not one per direction {DIRECTIONS}")
        return rec, ids

    def grid(self, grid_id: int):
        """A stored :class:`~hybridcomp.chardiag.grid.CDGrid` (its sets read and checked)."""
        from hybridcomp.chardiag.grid import CDGrid
        from hybridcomp.rom.volumetric import SupportGrid

        rec, ids = self.grid_ids(grid_id)
        sets = tuple(CDSet({d: self.get(i[d]) for d in DIRECTIONS}, i) for i in ids)
        return CDGrid(SupportGrid.from_dict(rec["grid"]), sets, int(grid_id), rec["load_case"])

    def activate_grid(self, grid_id: int, reason: str = "", machine_time_s: float | None = None,
                      event_key: str | None = None, lease_owner: str | None = None) -> int | None:
        """Make a stored grid its machine's active grid and every point's set the active set of its pose, atomically.

        A ``grid activation`` event is logged in the same transaction.  Returns the event id (None when
        ``event_key`` was already logged: then nothing changes).  A point whose pose a monitoring daemon holds
        refuses it for anyone but that daemon (``lease_owner``, as :meth:`activate`).

        Raises
        ------
        CDDatabaseError
            a daemon other than ``lease_owner`` holds one of the grid's poses
        """
        sa = self._sa
        act, ag, ev = self.t["active"], self.t["active_grid"], self.t["events"]
        rec, ids = self.grid_ids(grid_id)
        machine = rec["machine"]
        from hybridcomp.chardiag.grid import point_keys
        from hybridcomp.rom.volumetric import SupportGrid

        keys = point_keys(SupportGrid.from_dict(rec["grid"]))

        def run(conn):
            self.lock(conn, f"active grid {machine}")
            for key in keys:
                self._refuse_held(conn, machine, key, lease_owner)
                self.lock(conn, f"active {machine}\0{key}")
            self.lock(conn, EVENTS_LOCK)
            if event_key is not None and conn.execute(sa.select(ev.c.id).where(ev.c.key == event_key)).first():
                return None
            previous = conn.execute(sa.select(ag.c.grid_id).where(ag.c.machine == machine)).scalar()
            now = utc_now()
            for key, i in zip(keys, ids):
                conn.execute(act.delete().where(act.c.machine == machine, act.c.pose_key == key))
                conn.execute(act.insert(), [{"machine": machine, "pose_key": key, "direction": d, "cd_id": i[d],
                                             "activated": now} for d in DIRECTIONS])
            conn.execute(ag.delete().where(ag.c.machine == machine))
            conn.execute(ag.insert().values(machine=machine, grid_id=int(grid_id), activated=now))
            payload = {"machine": machine, "grid_id": int(grid_id), "points": len(ids), "previous": previous,
                       "reason": reason}
            return conn.execute(ev.insert().values(kind="grid activation", machine_time_s=machine_time_s, created=now,
                                                   payload=jsonio.dumps(payload), key=event_key)).inserted_primary_key[0]

        return self.write(run, f"activating CD grid {grid_id}")

    def active_grid_id(self, machine: str) -> int | None:
        """The id of the machine's active CD grid, or None."""
        sa = self._sa
        ag = self.t["active_grid"]
        with self.engine.connect() as conn:
            v = conn.execute(sa.select(ag.c.grid_id).where(ag.c.machine == machine)).scalar()
        return None if v is None else int(v)

    def active_grid(self, machine: str):
        """The machine's active :class:`~hybridcomp.chardiag.grid.CDGrid`, or None."""
        gid = self.active_grid_id(machine)
        return None if gid is None else self.grid(gid)

    def search_grids(self, machine: str, signature, t_reference_degC: Mapping[str, float], threshold_K: float = 0.5,
                     layout=None) -> list[GridMatch]:
        """Stored CD grids of a machine for a load case, best first (as :meth:`search` per pose).

        A grid fits when the reference temperatures of every point's set are within ``threshold_K`` of
        ``t_reference_degC`` (max over the common sensors); ordered by its largest signature distance (when a
        signature is given), then ΔT.
        """
        if not threshold_K >= 0:
            raise ValueError(f"threshold_K must be ≥ 0, got {threshold_K!r}")
        sa = self._sa
        grids, gc, cds, lc = self.t["grids"], self.t["grid_cds"], self.t["cds"], self.t["load_cases"]
        sig = None if signature is None else np.asarray(signature, float)
        q = (sa.select(grids.c.id, grids.c.load_case, lc.c.signature, lc.c.t_reference)
             .join(gc, gc.c.grid_id == grids.c.id).join(cds, cds.c.id == gc.c.cd_id)
             .join(lc, lc.c.id == cds.c.load_case_id).where(grids.c.machine == machine).distinct())
        per: dict[int, list] = {}
        with self.engine.connect() as conn:
            for r in conn.execute(q):
                per.setdefault(int(r.id), []).append(r)
        out = []
        for gid, rows in per.items():
            dT, dist, ok = 0.0, math.nan, True
            for r in rows:
                tref = json.loads(r.t_reference)
                common = [s for s in t_reference_degC if s in tref]
                if not common:
                    ok = False
                    break
                dT = max(dT, max(abs(float(tref[s]) - float(t_reference_degC[s])) for s in common))
                stored = np.array(json.loads(r.signature), float)
                if sig is not None and sig.size and stored.shape == sig.shape:
                    if layout is not None:
                        from hybridcomp.histogram.signature import signature_distance

                        d = float(signature_distance(sig, stored, layout))
                    else:
                        d = float(np.linalg.norm(sig - stored))
                    dist = d if math.isnan(dist) else max(dist, d)
            if ok and dT <= threshold_K:
                out.append(GridMatch(gid, rows[0].load_case, dT, dist))
        out.sort(key=lambda m: (math.inf if math.isnan(m.distance) else m.distance, m.delta_T_K, -m.grid_id))
        return out


__all__ = ["CDDatabase", "CDDatabaseError", "GridMatch", "Match", "SCHEMA_VERSION", "pose_key", "sqlite_file"]
