"""The CD database on SQLite: storage round trip, search, atomic activation across processes, events, state."""

from __future__ import annotations

import multiprocessing as mp
import sqlite3

import numpy as np
import pytest

pytest.importorskip("sqlalchemy", reason="the CD database needs SQLAlchemy (pip install 'hybridcomp[db]')")

from hybridcomp.chardiag.cd import CDSet
from hybridcomp.chardiag.db import SCHEMA_VERSION, CDDatabase, CDDatabaseError
from hybridcomp.chardiag.fit import FitOptions, fit_cd_set
from hybridcomp.histogram.signature import SignatureLayout
from hybridcomp.monitor.store import MonitorStore

POSE = {"X": 0.0, "Y": 0.0, "Z": 0.0}
LAYOUT = SignatureLayout(("X", "Y", "Z"), (1, 1, 1))  # 3 factors + 3 single-segment fractions + spindle


def cd_set(seed: int, t_offset: float, signature):
    """Three CDs of a load case whose sensors sit around 22 + t_offset °C."""
    rng = np.random.default_rng(seed)
    T = 22.0 + t_offset + rng.uniform(-2, 2, (300, 3))
    tab = {f"T{i + 1}_degC": T[:, i] for i in range(3)}
    for k, d in enumerate(("dx_um", "dy_um", "dz_um")):
        tab[d] = (T - 22) @ rng.normal(size=3) + k
    return fit_cd_set(tab, machine="vmc800", pose_mm=POSE, signature=np.asarray(signature, float),
                      load_case=f"case{seed}", options=FitOptions(n_support=3))


@pytest.fixture()
def db(tmp_path):
    with CDDatabase(tmp_path / "cds.sqlite") as d:
        yield d


def test_store_and_get_round_trip(db):
    cds = cd_set(1, 0.0, [0.5, 0, 0, 1, 1, 1, 0])
    ids = db.add_set(cds)
    assert sorted(ids) == ["X", "Y", "Z"]
    for d, i in ids.items():
        assert db.get(i) == cds[d]
    rows = db.list("vmc800")
    assert [r["direction"] for r in rows] == ["X", "Y", "Z"] and not any(r["active"] for r in rows)
    assert len(db.load_cases("vmc800", "X=0,Y=0,Z=0")) == 1  # one load case for the three CDs
    with pytest.raises(CDDatabaseError, match="table cds has no id 99"):
        db.get(99)


def test_search_returns_the_nearest_load_case_within_the_threshold(db):
    sigs = {0: [0.9, 0.0, 0.0, 1, 1, 1, 0.0], 1: [0.0, 0.9, 0.0, 1, 1, 1, 0.0], 2: [0.0, 0.0, 0.0, 1, 1, 1, 0.9],
            3: [0.5, 0.5, 0.0, 1, 1, 1, 0.2]}
    ids = {k: db.add_set(cd_set(k, 0.1 * k, s)) for k, s in sigs.items()}
    far = db.add_set(cd_set(9, 3.0, [0.5, 0.5, 0.0, 1, 1, 1, 0.2]))  # same load case, but 3 K warmer
    tref = cd_set(3, 0.3, sigs[3])["X"].t_reference()
    found = db.search("vmc800", "X=0,Y=0,Z=0", [0.45, 0.5, 0.0, 1, 1, 1, 0.25], tref, threshold_K=0.5, layout=LAYOUT)
    assert found[0].ids == ids[3]
    assert far not in [m.ids for m in found]
    assert [m.distance for m in found] == sorted(m.distance for m in found)
    assert all(m.delta_T_K <= 0.5 for m in found)
    # the nearest by signature among those within the threshold: case 0 (X only) for an X-heavy load
    found = db.search("vmc800", "X=0,Y=0,Z=0", [0.8, 0.05, 0.0, 1, 1, 1, 0.0], tref, threshold_K=1.0, layout=LAYOUT)
    assert found[0].ids == ids[0]
    assert db.search("vmc800", "X=0,Y=0,Z=0", None, {"T1": 40.0}, threshold_K=0.5) == []
    # an incomplete set (two directions only) is never offered
    lone = cd_set(5, 0.0, sigs[0])
    db.add(lone["X"])
    db.add(lone["Y"])
    assert all(m.load_case != "case5" for m in db.search("vmc800", "X=0,Y=0,Z=0", None, tref, 10.0))


def test_activation_is_atomic_and_logged(db):
    a = db.add_set(cd_set(1, 0.0, [0] * 7))
    b = db.add_set(cd_set(2, 0.0, [0] * 7))
    assert db.active_set("vmc800", "X=0,Y=0,Z=0") is None
    db.activate("vmc800", "X=0,Y=0,Z=0", a, reason="default CDs", machine_time_s=0.0)
    db.activate("vmc800", "X=0,Y=0,Z=0", b, reason="switch", machine_time_s=900.0)
    s = db.active_set("vmc800", "X=0,Y=0,Z=0")
    assert isinstance(s, CDSet) and dict(s.ids) == b
    ev = MonitorStore(db).events("activation")
    assert [e.payload["ids"] for e in ev] == [a, b]
    assert ev[1].payload["previous"] == a and ev[1].machine_time_s == 900.0
    with pytest.raises(CDDatabaseError, match="direction X, not for .* direction Y"):
        db.activate("vmc800", "X=0,Y=0,Z=0", {"X": a["X"], "Y": a["X"], "Z": a["Z"]})
    assert dict(db.active_set("vmc800", "X=0,Y=0,Z=0").ids) == b  # the failed activation changed nothing


def test_events_with_a_key_are_written_once_and_state_persists(db, tmp_path):
    assert MonitorStore(db).log_event("decision", 900.0, {"dT_K": 0.31, "action": "keep"}, key="decision@900") is not None
    assert MonitorStore(db).log_event("decision", 900.0, {"dT_K": 0.31, "action": "keep"}, key="decision@900") is None
    MonitorStore(db).log_event("warning", None, {"text": "no CD set within 0.5 K", "dT": np.float64(0.7), "rms": np.nan})
    ev = MonitorStore(db).events()
    assert [e.kind for e in ev] == ["decision", "warning"] and ev[1].payload["dT"] == 0.7
    assert ev[1].payload["rms"] is None  # strict JSON: NaN is stored as null
    MonitorStore(db).put_state("monitor", '{"time_s": 1}')
    MonitorStore(db).put_state("monitor", '{"time_s": 2}')
    assert MonitorStore(db).get_state("monitor") == '{"time_s": 2}' and MonitorStore(db).get_state("nothing") is None
    assert MonitorStore(CDDatabase(tmp_path / "cds.sqlite")).get_state("monitor") == '{"time_s": 2}'  # another connection


def test_a_newer_schema_is_refused(tmp_path):
    path = tmp_path / "cds.sqlite"
    CDDatabase(path).close()
    with sqlite3.connect(path) as con:
        con.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION + 1),))
    with pytest.raises(CDDatabaseError, match=f"schema_version is {SCHEMA_VERSION + 1}, newer"):
        CDDatabase(path)


def _activate_many(url, sets, n, tag, barrier):
    db = CDDatabase(url)
    barrier.wait()
    for k in range(n):
        db.activate("vmc800", "X=0,Y=0,Z=0", sets[k % len(sets)], reason=f"{tag}{k}")
        MonitorStore(db).log_event("decision", float(k), {"by": tag, "k": k}, key=f"{tag}-{k}")
    db.close()


@pytest.mark.slow  # separate Python processes, as on a shop floor: seconds of start-up and imports
def test_two_processes_activating_at_once_leave_a_consistent_set(tmp_path):
    path = tmp_path / "cds.sqlite"
    db = CDDatabase(path)
    sets = [db.add_set(cd_set(k, 0.0, [0] * 7)) for k in range(4)]
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(2)
    n = 40
    procs = [ctx.Process(target=_activate_many, args=(str(path), sets[2 * i:2 * i + 2], n, f"p{i}", barrier))
             for i in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]
    active = db.active_ids("vmc800", "X=0,Y=0,Z=0")
    assert active in sets  # one complete set, never a mixture
    acts = MonitorStore(db).events("activation")
    assert len(acts) == 2 * n
    assert all(e.payload["ids"] in sets and (not e.payload["previous"] or e.payload["previous"] in sets) for e in acts)
    # every activation saw the set the one before it left: the history is a chain
    for prev, cur in zip(acts, acts[1:]):
        assert cur.payload["previous"] == prev.payload["ids"]
    assert acts[-1].payload["ids"] == active
    assert len(MonitorStore(db).events("decision")) == 2 * n
    db.close()


def test_readers_do_not_wait_for_a_writer(db):
    import threading
    import time

    MonitorStore(db).log_event("decision", 0.0, {"action": "keep"})
    started = threading.Event()

    def slow_write(conn):
        started.set()
        time.sleep(1.5)

    writer = threading.Thread(target=lambda: db.write(slow_write, "a long write"))
    writer.start()
    started.wait(5)
    t0 = time.perf_counter()
    assert len(MonitorStore(db).events()) == 1 and MonitorStore(db).get_state("x") is None
    assert time.perf_counter() - t0 < 0.5  # WAL snapshot read, not queued behind BEGIN IMMEDIATE
    writer.join()
