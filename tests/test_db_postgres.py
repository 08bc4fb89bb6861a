"""The CD database on a real PostgreSQL server started by the test setup (tests/pg_server.py).

Skipped with the reason stated when no server can be run here.  Concurrency is tested with separate
processes, as on a shop floor: two monitors writing events at once, two writers activating sets of one
pose at once while a reader watches, two monitors creating the schema of a new database at once.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.monitor.store import MonitorStore

pytest_plugins = ["pg_server"]

POSE = {"X": 0.0, "Y": 0.0, "Z": 0.0}


def test_the_server_is_a_real_postgresql(postgres_url):
    sa = pytest.importorskip("sqlalchemy")
    assert postgres_url.startswith("postgresql+psycopg://postgres@127.0.0.1:")
    engine = sa.create_engine(postgres_url)
    try:
        with engine.connect() as conn:
            assert conn.execute(sa.text("SELECT version()")).scalar().startswith("PostgreSQL ")
            assert conn.execute(sa.text("SELECT current_database()")).scalar() == "hybridcomp_test"
    finally:
        engine.dispose()


# --------------------------------------------------------------------------- CDs to store


@pytest.fixture(scope="module")
def chardiag():
    db = pytest.importorskip("hybridcomp.chardiag.db", reason="hybridcomp.chardiag.db is not there yet")
    fit = pytest.importorskip("hybridcomp.chardiag.fit")
    return db, fit


def training_table(offset_K: float, n: int = 240, seed: int = 0) -> dict[str, np.ndarray]:
    """Planted linear drifts in T1 and T2 (2 and -1 µm/K in x, ...) over a warm-up ``offset_K`` above 20 °C."""
    rng = np.random.default_rng(seed)
    t1 = 20 + offset_K + 4 * rng.random(n)
    t2 = 20 + offset_K + 3 * rng.random(n)
    t3 = 20 + offset_K + 0.1 * rng.random(n)  # range below 0.5 K: an inactive input
    return {
        "time_s": np.arange(n) * 60.0,
        "T1_degC": t1, "T2_degC": t2, "T3_degC": t3,
        "dx_um": 2.0 * (t1 - 20) - 1.0 * (t2 - 20),
        "dy_um": 0.5 * (t1 - 20),
        "dz_um": -3.0 * (t2 - 20) + 0.7 * (t1 - 20),
    }


def cd_set(fit, load_case: str, offset_K: float, seed: int = 0):
    table = training_table(offset_K, seed=seed)
    t_ref = {k[:-5]: float(np.mean(v)) for k, v in table.items() if k.endswith("_degC")}
    return fit.fit_cd_set(table, machine="vmc800", machine_sha256="0" * 64, pose_mm=POSE, load_case=load_case,
                          signature=np.array([offset_K, 1.0, 0.0]), t_reference_degC=t_ref)


@pytest.fixture(scope="module")
def sets(chardiag):
    _, fit = chardiag
    return {"warm": cd_set(fit, "warm", 2.0, seed=1), "cold": cd_set(fit, "cold", 0.0, seed=2)}


def test_add_get_round_trip_on_postgresql(chardiag, sets, fresh_postgres_url):
    db, _ = chardiag
    with db.CDDatabase(fresh_postgres_url) as store:
        assert store.dialect == "postgresql"
        assert store.schema_version() == db.SCHEMA_VERSION
        ids = {d: store.add(cd) for d, cd in sets["warm"].items()}
        assert len(set(ids.values())) == 3
        for d, cd_id in ids.items():
            back = store.get(cd_id)
            assert back == sets["warm"][d]  # bit-exact, arrays included
            X = np.array([[21.0, 22.5, 20.0], [23.0, 21.0, 20.0]])
            np.testing.assert_array_equal(back.evaluate(X)[0], sets["warm"][d].evaluate(X)[0])
    # a second connection (another monitor) sees the same rows and the same schema version
    with db.CDDatabase(fresh_postgres_url) as other:
        assert other.get(ids["Z"]) == sets["warm"]["Z"]
    with pytest.raises(db.CDDatabaseError, match="no id 999999"), db.CDDatabase(fresh_postgres_url) as store:
        store.get(999999)


def test_search_finds_the_fitting_complete_set(chardiag, sets, fresh_postgres_url):
    db, _ = chardiag
    with db.CDDatabase(fresh_postgres_url) as store:
        warm = store.add_set(sets["warm"])
        cold = store.add_set(sets["cold"])
        # a load case with only two directions is never offered
        lone = cd_set(chardiag[1], "incomplete", 2.05, seed=3)
        store.add(lone["X"])
        store.add(lone["Y"])
        pose = db.pose_key(POSE)
        t_warm = dict(sets["warm"]["X"].t_reference_degC)
        hits = store.search("vmc800", pose, None, t_warm, threshold_K=0.5)
        assert [h.load_case for h in hits] == ["warm"]
        assert hits[0].ids == warm and hits[0].delta_T_K == pytest.approx(0.0, abs=1e-12)
        # both within a wide threshold: the closer signature first
        t_mid = {k: v - 1.0 for k, v in t_warm.items()}
        hits = store.search("vmc800", pose, np.array([0.1, 1.0, 0.0]), t_mid, threshold_K=5.0)
        assert [h.load_case for h in hits] == ["cold", "warm"]
        assert hits[0].ids == cold
        assert store.search("vmc800", pose, None, {k: v + 3.0 for k, v in t_warm.items()}, threshold_K=0.5) == []
        assert store.search("other", pose, None, t_warm) == []


# --------------------------------------------------------------------------- processes at once

HEADER = textwrap.dedent("""
    import json, sys, time
    from pathlib import Path
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.store import MonitorStore
    url, go, who = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
    store = CDDatabase(url)
    (go.parent / f"ready-{who}").touch()
    while not go.exists():
        time.sleep(0.005)
""")


def _run_at_once(tmp_path: Path, url: str, body: str, n: int = 2, timeout: float = 120.0) -> list[str]:
    """Start ``n`` processes running ``HEADER + body``, release them together, return their stdout."""
    go = tmp_path / "go"
    script = tmp_path / "worker.py"
    script.write_text(HEADER + textwrap.dedent(body))
    procs = [subprocess.Popen([sys.executable, str(script), url, str(go), f"p{k}"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for k in range(n)]
    try:
        deadline = time.monotonic() + timeout
        while not all((tmp_path / f"ready-p{k}").exists() for k in range(n)):
            if time.monotonic() > deadline or any(p.poll() not in (None, 0) for p in procs):
                break
            time.sleep(0.01)
        go.touch()
        outs = []
        for p in procs:
            out, err = p.communicate(timeout=timeout)
            assert p.returncode == 0, err[-3000:]
            outs.append(out)
        return outs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


@pytest.mark.slow  # separate Python processes, as on a shop floor: seconds of start-up and imports
def test_two_monitors_write_events_at_once_none_lost_none_duplicated(chardiag, fresh_postgres_url, tmp_path):
    db, _ = chardiag
    db.CDDatabase(fresh_postgres_url).close()  # schema exists; its concurrent creation is tested below
    n = 150
    body = f"""
        ids = []
        for i in range({n}):
            # its own decision events, each written twice as a restarted daemon would: the key keeps one
            ids.append(MonitorStore(store).log_event("decision", float(i), {{"who": who, "i": i}}, key=f"{{who}}-{{i}}"))
            assert MonitorStore(store).log_event("decision", float(i), {{"who": who, "i": i}}, key=f"{{who}}-{{i}}") is None
            # warnings without a key: every one is kept
            MonitorStore(store).log_event("warning", float(i), {{"who": who, "i": i}})
            # events both monitors report (one shop-floor event seen twice): exactly one is kept
            MonitorStore(store).log_event("switch", float(i), {{"who": who, "i": i}}, key=f"shared-{{i}}")
        print(json.dumps(ids))
    """
    outs = _run_at_once(tmp_path, fresh_postgres_url, body)
    with db.CDDatabase(fresh_postgres_url) as store:
        events = MonitorStore(store).events()
    returned = [json.loads(o) for o in outs]
    for who, ids in zip(("p0", "p1"), returned):
        assert None not in ids and ids == sorted(ids)  # each monitor's own events in its order
        mine = {e.id: e for e in events if e.kind == "decision" and e.payload["who"] == who}
        assert sorted(mine) == ids
        assert [mine[i].payload["i"] for i in ids] == list(range(n))
        assert [mine[i].key for i in ids] == [f"{who}-{i}" for i in range(n)]
    ids = [e.id for e in events]
    assert len(ids) == len(set(ids))
    assert sum(e.kind == "decision" for e in events) == 2 * n
    warnings = sorted((e.payload["who"], e.payload["i"]) for e in events if e.kind == "warning")
    assert warnings == sorted((w, i) for w in ("p0", "p1") for i in range(n))
    shared = sorted(e.key for e in events if e.kind == "switch")
    assert shared == sorted(f"shared-{i}" for i in range(n))
    assert len(events) == 5 * n  # 2n decisions, 2n warnings, n shared switches
    # both monitors really interleaved: their decision ids overlap in range
    assert min(returned[0]) < max(returned[1]) and min(returned[1]) < max(returned[0])


@pytest.mark.slow  # separate Python processes, as on a shop floor: seconds of start-up and imports
def test_activation_is_atomic_under_concurrent_writers(chardiag, sets, fresh_postgres_url, tmp_path):
    db, _ = chardiag
    pose = db.pose_key(POSE)
    with db.CDDatabase(fresh_postgres_url) as store:
        warm = store.add_set(sets["warm"])
        cold = store.add_set(sets["cold"])
    rounds = 40
    body = f"""
        ids = json.loads({json.dumps(json.dumps({"p0": warm, "p1": cold}))})[who]
        for i in range({rounds}):
            store.activate("vmc800", {pose!r}, ids, reason=f"{{who}} round {{i}}", machine_time_s=float(i))
        print("done")
    """
    seen = []
    go = tmp_path / "go"
    import threading

    stop = threading.Event()

    def watch():
        with db.CDDatabase(fresh_postgres_url) as reader:
            while not stop.is_set():
                if go.exists():
                    seen.append(reader.active_ids("vmc800", pose))

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        _run_at_once(tmp_path, fresh_postgres_url, body)
    finally:
        stop.set()
        watcher.join()
    observed = [s for s in seen if s]
    assert observed, "the reader saw no active set"
    for s in observed:  # never a mixture of the two sets
        assert s in (warm, cold), s
    with db.CDDatabase(fresh_postgres_url) as store:
        final = store.active_ids("vmc800", pose)
        assert final in (warm, cold)
        active = store.active_set("vmc800", pose)
        assert active is not None and dict(active.ids) == final
        acts = MonitorStore(store).events("activation")
    assert len(acts) == 2 * rounds
    assert len({e.id for e in acts}) == 2 * rounds
    # the log is a consistent history: each activation's "previous" is what the one before it activated
    for before, after in itertools.pairwise(acts):
        assert {d: int(v) for d, v in after.payload["previous"].items()} == before.payload["ids"]
    assert acts[-1].payload["ids"] == final


@pytest.mark.slow  # separate Python processes, as on a shop floor: seconds of start-up and imports
def test_two_monitors_open_a_new_database_at_once(chardiag, fresh_postgres_url, tmp_path):
    db, _ = chardiag
    go = tmp_path / "go"
    script = tmp_path / "opener.py"
    script.write_text(textwrap.dedent("""
        import sys, time
        from pathlib import Path
        go = Path(sys.argv[2])
        from hybridcomp.chardiag.db import CDDatabase
        from hybridcomp.monitor.store import MonitorStore
        (go.parent / f"ready-{sys.argv[3]}").touch()
        while not go.exists():
            time.sleep(0.002)
        store = CDDatabase(sys.argv[1])
        print(store.schema_version())
        MonitorStore(store).log_event("sensor", 0.0, {"who": sys.argv[3]})
    """))
    procs = [subprocess.Popen([sys.executable, str(script), fresh_postgres_url, str(go), f"p{k}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for k in range(2)]
    deadline = time.monotonic() + 120
    while not all((tmp_path / f"ready-p{k}").exists() for k in range(2)):  # both imported and waiting
        if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
            break
        time.sleep(0.01)
    go.touch()
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
        assert out.strip() == str(db.SCHEMA_VERSION)
    with db.CDDatabase(fresh_postgres_url) as store:
        assert sorted(e.payload["who"] for e in MonitorStore(store).events("sensor")) == ["p0", "p1"]


def test_a_reader_creates_nothing_and_an_import_is_idempotent_and_all_or_nothing_on_postgresql(
        chardiag, sets, fresh_postgres_url):
    db, _ = chardiag
    sa = pytest.importorskip("sqlalchemy")
    with pytest.raises(db.CDDatabaseError, match="is not a hybridcomp CD database"):
        db.CDDatabase(fresh_postgres_url, readonly=True)
    engine = sa.create_engine(fresh_postgres_url)
    try:
        assert sa.inspect(engine).get_table_names() == []  # the reader created no schema
    finally:
        engine.dispose()
    warm = list(sets["warm"].values())
    with db.CDDatabase(fresh_postgres_url) as store:
        first = store.add_many(warm)
        assert [stored for _, stored in first] == [True, True, True]
        again = store.add_many([*warm, warm[0]])
        assert again == [(i, False) for i, _ in first] + [(first[0][0], False)]
        real = store._insert

        def failing(conn, cd, xml, load_case):
            if cd.direction == "Z":
                raise db.CDDatabaseError("planted failure")
            return real(conn, cd, xml, load_case)

        store._insert = failing
        with pytest.raises(db.CDDatabaseError, match="planted failure"):
            store.add_many(list(sets["cold"].values()))
    with db.CDDatabase(fresh_postgres_url, readonly=True) as reader:
        assert [r["id"] for r in reader.list()] == [i for i, _ in first]  # nothing of the failed import


def test_sqlite_stays_the_default(chardiag, tmp_path):
    db, _ = chardiag
    with db.CDDatabase(tmp_path / "cd.sqlite") as store:
        assert store.dialect == "sqlite"
        assert store.url == f"sqlite:///{tmp_path / 'cd.sqlite'}"
    assert (tmp_path / "cd.sqlite").is_file()


def _tail_while_an_earlier_writer_is_still_committing(db, url: str) -> tuple[list[int], list[int]]:
    """Writer A has its event inserted but not committed, writer B logs one after it, a reader tails with
    ``since_id`` meanwhile.  Returns (ids the reader saw, all ids)."""
    import threading

    sa = pytest.importorskip("sqlalchemy")
    a, b, reader = db.CDDatabase(url), db.CDDatabase(url), db.CDDatabase(url)
    at_commit, go = threading.Event(), threading.Event()

    @sa.event.listens_for(a.engine, "commit")
    def hold(conn):  # A's INSERT has run (its id is taken); its commit waits
        at_commit.set()
        go.wait(3)  # on SQLite writer B waits for this commit (writes run BEGIN IMMEDIATE; reads do not wait)

    try:
        ta = threading.Thread(target=MonitorStore(a).log_event, args=("sensor", 1.0, {"who": "a"}))
        ta.start()
        assert at_commit.wait(10)
        tb = threading.Thread(target=MonitorStore(b).log_event, args=("sensor", 2.0, {"who": "b"}))
        tb.start()
        tb.join(0.5)  # B commits now, unless writers are serialised (then it waits for A)
        seen = [e.id for e in MonitorStore(reader).events()]
        go.set()
        ta.join(10)
        tb.join(10)
        seen += [e.id for e in MonitorStore(reader).events(since_id=max(seen, default=0))]
        return seen, [e.id for e in MonitorStore(reader).events()]
    finally:
        go.set()
        for store in (a, b, reader):
            store.close()


def test_a_reader_tailing_events_misses_none_on_sqlite(chardiag, tmp_path):
    db, _ = chardiag
    seen, everything = _tail_while_an_earlier_writer_is_still_committing(db, str(tmp_path / "cd.sqlite"))
    assert len(everything) == 2 and sorted(seen) == everything


def test_a_reader_tailing_events_misses_none_on_postgresql(chardiag, fresh_postgres_url):
    db, _ = chardiag
    seen, everything = _tail_while_an_earlier_writer_is_still_committing(db, fresh_postgres_url)
    assert len(everything) == 2 and sorted(seen) == everything


def _two_monitors_upgrade_at_once(db, url: str, monkeypatch) -> list:
    """A version-1 database opened at once by two monitors of a hypothetical version 2 (adds a column).
    Returns what each opening raised (None: it succeeded)."""
    import threading

    sa = pytest.importorskip("sqlalchemy")
    with db.CDDatabase(url) as store:
        MonitorStore(store).log_event("sensor", 0.0, {"before": "upgrade"})
    both_read_version_1 = threading.Barrier(2)

    def add_column(conn):
        try:  # let both openers get here if nothing serialises them, as it happens on a shop floor
            both_read_version_1.wait(2)
        except threading.BrokenBarrierError:
            pass
        conn.execute(sa.text("ALTER TABLE events ADD COLUMN note TEXT"))

    monkeypatch.setattr(db, "SCHEMA_VERSION", db.SCHEMA_VERSION + 1)
    monkeypatch.setitem(db.MIGRATIONS, db.SCHEMA_VERSION - 1, add_column)
    errors = [None, None]

    def open_it(k):
        try:
            db.CDDatabase(url).close()
        except Exception as exc:  # noqa: BLE001 - reported to the test
            errors[k] = exc

    threads = [threading.Thread(target=open_it, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    if errors == [None, None]:
        with db.CDDatabase(url) as store:
            assert store.schema_version() == db.SCHEMA_VERSION
            assert [e.payload for e in MonitorStore(store).events()] == [{"before": "upgrade"}]
    return errors


def test_two_monitors_upgrading_the_schema_at_once_on_postgresql(chardiag, fresh_postgres_url, monkeypatch):
    db, _ = chardiag
    assert _two_monitors_upgrade_at_once(db, fresh_postgres_url, monkeypatch) == [None, None]
