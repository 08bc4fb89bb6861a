"""A throw-away PostgreSQL server for the test run.

Fixtures (use them from a test module with ``pytest_plugins = ["pg_server"]``, which registers them once
for the whole run, so every module shares one server):

* ``postgres_url`` (session): starts a real PostgreSQL server — ``initdb`` + ``pg_ctl`` in a temporary
  directory, on a free loopback port, with its unix socket in that directory, run as the ``postgres`` OS
  user when the tests run as root — and yields a SQLAlchemy URL ``postgresql+psycopg://...`` of an empty
  database; the server is stopped and its directory removed at the end of the run.
* ``fresh_postgres_url`` (function): a new empty database on that server per test, dropped afterwards.

They skip with the reason stated when psycopg or SQLAlchemy is missing or no server binaries are found
(``/usr/lib/postgresql/*/bin``, ``$PATH``, or the directory in ``HYBRIDCOMP_PG_BIN``).  Debian:
``apt-get install postgresql`` (``.ci/run`` does it when it can).
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import re
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

import pytest

SERVER_USER = "postgres"  # the OS user that runs the server when the tests run as root (initdb refuses root)


def find_server_binaries() -> Path | None:
    """The directory holding ``initdb`` and ``pg_ctl``: $HYBRIDCOMP_PG_BIN, the newest /usr/lib/postgresql/N/bin, or $PATH."""
    candidates = []
    if os.environ.get("HYBRIDCOMP_PG_BIN"):
        candidates.append(Path(os.environ["HYBRIDCOMP_PG_BIN"]))

    def version(p: str) -> float:
        m = re.search(r"postgresql/(\d+(?:\.\d+)?)/bin", p)
        return float(m.group(1)) if m else 0.0

    candidates += [Path(p) for p in sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=version, reverse=True)]
    which = shutil.which("pg_ctl")
    if which:
        candidates.append(Path(which).parent)
    for d in candidates:
        if (d / "initdb").is_file() and (d / "pg_ctl").is_file():
            return d
    return None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _skip_reason() -> str | None:
    try:
        import psycopg  # noqa: F401
        import sqlalchemy  # noqa: F401
    except ImportError as exc:
        return f"PostgreSQL tests need psycopg and SQLAlchemy (pip install 'hybridcomp[postgres]'): {exc}"
    if find_server_binaries() is None:
        return ("no PostgreSQL server binaries (initdb, pg_ctl) in /usr/lib/postgresql/*/bin, on PATH or in "
                "HYBRIDCOMP_PG_BIN; install them (Debian: apt-get install postgresql) to run the PostgreSQL tests")
    if os.geteuid() == 0:
        try:
            pwd.getpwnam(SERVER_USER)
        except KeyError:
            return f"the tests run as root and there is no {SERVER_USER!r} OS user to run the PostgreSQL server"
        base = Path(tempfile.gettempdir()).resolve()
        for d in (base, *base.parents):
            if not os.stat(d).st_mode & 0o001:
                return (f"the temporary directory {base} is not reachable for the {SERVER_USER!r} OS user "
                        f"({d} is not world-searchable); set TMPDIR to a directory that is")
    return None


class PostgresServer:
    """A PostgreSQL server in a temporary directory (``start()``, ``stop()``)."""

    def __init__(self, bin_dir: Path):
        self.bin = bin_dir
        self.dir = Path(tempfile.mkdtemp(prefix="hybridcomp-pg-"))
        self.data = self.dir / "data"
        self.log = self.dir / "server.log"
        self.port = 0
        self.run_as: dict = {}
        if os.geteuid() == 0:
            pw = pwd.getpwnam(SERVER_USER)
            os.chown(self.dir, pw.pw_uid, pw.pw_gid)
            self.run_as = {"user": pw.pw_uid, "group": pw.pw_gid, "extra_groups": []}
        os.chmod(self.dir, 0o700)

    def _run(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        env = {**os.environ, "LC_ALL": "C", "LANG": "C", "HOME": str(self.dir), "PGTZ": "UTC"}
        return subprocess.run([str(self.bin / args[0]), *args[1:]], cwd=self.dir, env=env, capture_output=True,
                              text=True, timeout=timeout, check=False, **self.run_as)

    def start(self) -> None:
        r = self._run("initdb", "-D", str(self.data), "-U", "postgres", "-A", "trust", "-E", "UTF8", "--no-locale",
                      "--no-sync")
        if r.returncode != 0:
            raise RuntimeError(f"initdb failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
        for _attempt in range(3):  # the free port may be taken between the probe and the bind
            self.port = _free_port()
            opts = (f"-p {self.port} -c listen_addresses=127.0.0.1 -c unix_socket_directories='{self.dir}' "
                    "-c fsync=off -c synchronous_commit=off -c full_page_writes=off -c max_connections=60")
            r = self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "-o", opts, "start")
            if r.returncode == 0:
                return
        log = self.log.read_text()[-2000:] if self.log.exists() else ""
        raise RuntimeError(f"pg_ctl start failed ({r.returncode}): {r.stderr.strip()[-1000:]} {log}")

    def stop(self) -> None:
        with contextlib.suppress(Exception):
            if (self.data / "postmaster.pid").exists():
                self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")
        shutil.rmtree(self.dir, ignore_errors=True)

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{database}"

    def admin(self, sql: str) -> None:
        """Run one statement outside a transaction (CREATE / DROP DATABASE)."""
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user="postgres", dbname="postgres",
                             autocommit=True) as conn:
            conn.execute(sql)


@pytest.fixture(scope="session")
def postgres_server():
    """The running :class:`PostgresServer` of this test run (skips with the reason when there can be none)."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    server = PostgresServer(find_server_binaries())
    try:
        server.start()
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        server.stop()
        pytest.fail(f"PostgreSQL server binaries are installed in {server.bin} but the server did not start: {exc}")
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="session")
def postgres_url(postgres_server) -> str:
    """SQLAlchemy URL (``postgresql+psycopg://``) of an empty database on the test run's PostgreSQL server."""
    postgres_server.admin("CREATE DATABASE hybridcomp_test")
    return postgres_server.url("hybridcomp_test")


@pytest.fixture
def fresh_postgres_url(postgres_server):
    """SQLAlchemy URL of a new empty database for one test (dropped afterwards)."""
    name = f"t_{uuid.uuid4().hex[:12]}"
    postgres_server.admin(f"CREATE DATABASE {name}")
    try:
        yield postgres_server.url(name)
    finally:
        postgres_server.admin(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
