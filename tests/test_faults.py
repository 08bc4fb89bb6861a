"""Faults a daemon meets in weeks beside a machine, replayed one by one: each must be named in an event, the
compensation cycles must go on (no gap over two cycles except where the data itself stops, and then an
unhealthy status), and nothing non-finite may reach a sink or the control.

The structure model, the trace and the CD sets are those of ``test_monitor_daemon.py`` (a small ROM of the
demonstrator; sensor temperatures from that very ROM).
"""

from __future__ import annotations

import asyncio
import json
import math
import sqlite3
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from test_monitor_daemon import (  # noqa: F401 - fixtures among them
    PKEY,
    TimedSink,
    config,
    events,
    make_db,
    rom,
    rom_file,
    run,
    trace,
)

from hybridcomp.monitor.daemon import Monitor, check_offset, run_monitor
from hybridcomp.monitor.decisions import TimeRules, check_time
from hybridcomp.monitor.sinks import MemorySink, Offset
from hybridcomp.monitor.sources import ListSource, read_replay
from hybridcomp.monitor.store import LeaseHeld, MonitorStore

pytest_plugins = ["pg_server"]

DT = 10.0  # the trace's sample interval [s]


# --------------------------------------------------------------------------- time stamps (pure)


def test_a_single_corrupt_stamp_is_dropped_and_the_time_line_goes_on():
    rules = TimeRules(max_step_s=600.0, confirm_samples=3)
    assert check_time(100.0, 1e6, 0.0, (), rules).verdict == "jump"
    assert check_time(100.0, 1e308, 0.0, (), rules).verdict == "invalid"  # no time at all (beyond ±1e10 s)
    c = check_time(100.0, 1e6, 0.0, (), rules)
    after = check_time(100.0, 110.0, 0.0, c.candidates, rules)
    assert (after.verdict, after.time_s, after.candidates) == ("ok", 110.0, ())
    assert check_time(100.0, math.nan, 0.0, (), rules).verdict == "invalid"
    assert check_time(100.0, math.inf, 0.0, (), rules).verdict == "invalid"
    # a corrupt first stamp cannot become the origin of the time line (everything after it would be "backwards")
    assert check_time(None, 1e308, 0.0, (), rules).verdict == "invalid"
    assert check_time(None, 1.8e9, 0.0, (), rules).verdict == "ok"  # Unix time in seconds is a time line


def test_a_confirmed_new_time_line_is_a_gap_when_the_wall_clock_backs_it_else_a_resync():
    rules = TimeRules(max_step_s=600.0, confirm_samples=3)
    # the data stopped for two hours and the wall clock says so: a gap at once, machine time kept
    g = check_time(100.0, 7300.0, 0.0, (), rules, wall_elapsed_s=7200.0, time_scale=1.0)
    assert (g.verdict, g.time_s, g.offset_s) == ("gap", 7300.0, 0.0)
    # the control's clock was set 1e5 s ahead, 10 s after the last sample: confirmed by three samples, then the
    # monitor's time continues from the last sample with the new line's step
    cand = ()
    for k, t in enumerate((1e5, 1e5 + 10, 1e5 + 20)):
        c = check_time(100.0, t, 0.0, cand, rules, wall_elapsed_s=10.0 * (k + 1), time_scale=1.0)
        cand = c.candidates
    assert c.verdict == "resync" and c.time_s == pytest.approx(110.0) and c.offset_s == pytest.approx(110.0 - 1e5 - 20)
    # the same jump from a replay, which has no clock to ask: a gap
    cand = ()
    for t in (1e5, 1e5 + 10, 1e5 + 20):
        c = check_time(100.0, t, 0.0, cand, rules)
        cand = c.candidates
    assert (c.verdict, c.time_s) == ("gap", 1e5 + 20)
    # a clock set back: three samples on the new line, then a resync (never a machine time going backwards)
    cand = ()
    for t in (50.0, 60.0, 70.0):
        c = check_time(100.0, t, 0.0, cand, rules)
        cand = c.candidates
    assert c.verdict == "resync" and c.time_s == pytest.approx(110.0)
    # suspect samples that do not continue each other never confirm anything
    cand = ()
    for t in (1e6, 5e5, 2e6, 3e5):
        c = check_time(100.0, t, 0.0, cand, rules)
        cand = c.candidates
        assert c.verdict == "jump"


# --------------------------------------------------------------------------- the daemon on faulty data


def _rows(sink):
    return np.array([[o.time_s, o.dx_um, o.dy_um, o.dz_um] for o in sink.rows])


def _gaps_ok(rows, readings, cycle_s=5.0):
    """No gap between offsets longer than two cycles, except where the samples themselves are farther apart."""
    t = rows[:, 0]
    sample_t = np.array([r.time_s for r in readings])
    worst_data_gap = np.max(np.diff(sample_t[np.isfinite(sample_t)]))
    return np.max(np.diff(t)) <= max(2 * cycle_s, worst_data_gap) + 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("bad", [1e6, 1e308])
def test_a_corrupt_future_time_stamp_is_named_and_compensation_goes_on(machine, rom, rom_file, trace, tmp_path, bad):
    path, s, T = trace
    clean = list(read_replay(path, machine))
    k = len(clean) // 2  # a few hours in
    messy = clean[:k] + [replace(clean[k], time_s=bad)] + clean[k + 1:]
    db_a, _ = make_db(tmp_path / "a.db", machine, T)
    db_b, _ = make_db(tmp_path / "b.db", machine, T)
    # the CDs' offsets alone: the structure model's fast part (model_transient_s) would pass the one model step's
    # loads with a sample fewer straight into the offsets (0.08 µm seen); this test is about the time line
    cfg = config(rom_file, path, tmp_path, compensation={"model_transient_s": 0})
    _, sink_a, _ = run(cfg, machine, rom, db_a, ListSource(clean))
    mon, sink_b, _ = run(cfg, machine, rom, db_b, ListSource(messy))
    a, b = _rows(sink_a), _rows(sink_b)
    assert len(b) == len(a) - 1  # one sample lost, the rest compensated
    assert b[-1, 0] == clean[-1].time_s  # to the end of the data
    assert np.all(np.isfinite(b[:, 1:]))
    assert _gaps_ok(b, [r for r in messy if r.time_s != bad])
    # 1e6 s is a time, far ahead: implausible until confirmed; 1e308 s is no time at all
    status = "implausible time stamp" if bad < 1e10 else "invalid time stamp"
    (ev,) = [e[2] for e in events(db_b, "time") if e[2].get("status") == status]
    assert ev["source_time_s"] == bad and ev["last_time_s"] == clean[k - 1].time_s
    assert (mon.counters.dropped_jump, mon.counters.dropped_invalid) == ((1, 0) if bad < 1e10 else (0, 1))
    # the compensation after the corrupt sample is the clean run's (one sample less in one model step's histogram)
    assert np.max(np.abs(b[k:, 1:] - a[k + 1:, 1:])) < 0.05


@pytest.mark.slow
def test_a_clock_set_back_resynchronises_and_compensation_goes_on(machine, rom, rom_file, trace, tmp_path):
    path, s, T = trace
    clean = list(read_replay(path, machine))
    k = len(clean) // 2
    back = 7200.0  # the control's clock set back by two hours
    messy = clean[:k] + [replace(r, time_s=r.time_s - back) for r in clean[k:]]
    db, _ = make_db(tmp_path / "a.db", machine, T)
    cfg = config(rom_file, path, tmp_path)
    mon, sink, _ = run(cfg, machine, rom, db, ListSource(messy))
    rows = _rows(sink)
    n_confirm = cfg.time.confirm_samples
    assert len(rows) == len(clean) - (n_confirm - 1)  # the samples that confirmed the new line, then all
    assert np.all(np.diff(rows[:, 0]) > 0)  # the monitor's time never goes back
    (ev,) = [e[2] for e in events(db, "time") if e[2].get("status") == "resync"]
    assert ev["offset_s"] == pytest.approx(back - (n_confirm - 1) * DT)
    assert mon.counters.resyncs == 1
    assert _gaps_ok(rows, clean, 5.0) or np.max(np.diff(rows[:, 0])) <= n_confirm * DT


@pytest.mark.slow
def test_a_long_gap_in_replayed_data_is_bounded_work(machine, rom, rom_file, trace, tmp_path):
    path, s, T = trace
    clean = list(read_replay(path, machine))
    k = len(clean) // 2
    messy = clean[:k] + [replace(r, time_s=r.time_s + 30 * 86400.0) for r in clean[k:]]  # a month off
    db, _ = make_db(tmp_path / "a.db", machine, T)
    cfg = config(rom_file, path, tmp_path)
    t0 = time.perf_counter()
    mon, sink, _ = run(cfg, machine, rom, db, ListSource(messy))
    wall = time.perf_counter() - t0
    (ev,) = [e[2] for e in events(db, "time") if e[2].get("status") == "gap"]
    assert ev["last_time_s"] == clean[k - 1].time_s
    assert mon.s.last_time_s == messy[-1].time_s
    # not a step per 60 s across the month (43,200 of them): one step across it, one decision at its end
    assert mon.counters.model_steps < 2 * len(clean) * DT / cfg.increment_s
    assert wall < 120.0
    assert np.all(np.isfinite(_rows(sink)[:, 1:]))


class _NodeSource:
    """Readings as an OPC UA source makes them from node values (some of them strings), with its count of bad
    values."""

    time_scale = None

    def __init__(self, machine, readings, bad_at):
        from hybridcomp.monitor.sources import as_number

        self.bad_values: dict[str, int] = {}
        self.finished = False
        self._out = []
        for i, r in enumerate(readings):
            sensors = dict(r.sensors_degC)
            if i in bad_at:
                sensors["T3"] = as_number("n/a", "T3_degC", self.bad_values)  # a String node: read as missing
            self._out.append((replace(r, sensors_degC=sensors), dict(self.bad_values)))

    async def readings(self, start_after_s=None):
        for r, bad in self._out:
            if start_after_s is not None and r.time_s <= start_after_s:
                continue
            self.bad_values.clear()
            self.bad_values.update(bad)
            await asyncio.sleep(0)
            yield r
        self.finished = True


@pytest.mark.slow
def test_a_string_where_a_number_belongs_is_a_sensor_fault_not_an_exit(machine, rom, rom_file, trace, tmp_path):
    path, s, T = trace
    clean = list(read_replay(path, machine))
    bad_at = set(range(600, 660))  # ten minutes of "n/a": longer than hold_s = 60 s, so T3 degrades
    db, _ = make_db(tmp_path / "a.db", machine, T)
    cfg = config(rom_file, path, tmp_path)
    mon, sink, res = run(cfg, machine, rom, db, _NodeSource(machine, clean, bad_at))
    assert res.stopped_by == "end of data"
    assert len(sink.rows) == len(clean)
    (src,) = [e[2] for e in events(db, "source")]
    assert src["status"] == "not a number" and src["node"] == "T3_degC"
    statuses = [(e[2]["sensor"], e[2]["status"]) for e in events(db, "sensor")]
    assert ("T3", "degraded") in statuses and ("T3", "recovered") in statuses or ("T3", "ok") in statuses


def test_malformed_node_ids_are_a_configuration_error_not_a_retry_loop(machine):
    pytest.importorskip("asyncua")
    from hybridcomp.monitor.sources import OpcUaSource, SourceFileError

    with pytest.raises(SourceFileError, match=r"source.nodes.x_mm = 'ns=2;q=\?\?' is not an OPC UA node id"):
        OpcUaSource("opc.tcp://127.0.0.1:4840", {"time_s": "ns=2;s=time_s", "x_mm": "ns=2;q=??", "y_mm": "ns=2;s=y",
                                                  "z_mm": "ns=2;s=z"}, machine)


@pytest.mark.slow
def test_a_well_formed_node_id_that_does_not_exist_is_an_event_naming_the_node(machine, rom, rom_file, trace,
                                                                                tmp_path):
    """The OPC UA server (the simulator playing the trace) has no node ``ns=2;s=T1_nowhere``: a ``source`` event names
    the node and its column, T1 degrades, compensation goes on; a missing time node is one configuration error."""
    pytest.importorskip("asyncua")
    from test_monitor_daemon import free_port, start_server, stop_server

    from hybridcomp.monitor.simulator import node_ids
    from hybridcomp.monitor.sources import OpcUaSource, SourceFileError

    path, s, T = trace
    db, _ = make_db(tmp_path / "cd.db", machine, T)
    cfg = config(rom_file, path, tmp_path, monitor={"max_gap_s": 500.0, "increment_s": 300.0})
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}/"
    header = path.read_text().split("\n", 1)[0].split(",")
    nodes = node_ids(header) | {"T1_degC": "ns=2;s=T1_nowhere"}
    server = start_server(path, port, float(s.time_s[-1]) / 6.0)
    mon = Monitor(cfg, machine, rom, db, PKEY)
    sink = MemorySink()

    async def main():
        stop = asyncio.Event()
        src = OpcUaSource(url, nodes, machine, publishing_interval_ms=50, stale_s=0.5, timeout_s=1.0)
        task = asyncio.create_task(run_monitor(cfg, mon, src, sink, stop=stop, seed=1))
        t0 = time.monotonic()
        while (mon.s.last_time_s or 0.0) < 3600.0:
            assert time.monotonic() - t0 < 20 and not task.done(), "no data from the OPC UA server"
            await asyncio.sleep(0.05)
        stop.set()
        await task
        async def read_all(src):
            async for _ in src.readings():
                pass

        with pytest.raises(SourceFileError, match=r"source.nodes.time_s = 'ns=2;s=clock': the server has no such "
                                                  r"node \(BadNodeIdUnknown\)"):  # (it waited for ever)
            await asyncio.wait_for(read_all(OpcUaSource(url, node_ids(header) | {"time_s": "ns=2;s=clock"}, machine,
                                                        publishing_interval_ms=50, stale_s=0.5, timeout_s=1.0)), 10.0)

    try:
        asyncio.run(main())
    finally:
        stop_server(server)
    missing = [e[2] for e in events(db, "source") if e[2]["status"] == "node not found"]
    assert len(missing) == 1 and missing[0]["node"] == "ns=2;s=T1_nowhere" and missing[0]["column"] == "T1_degC"
    assert "BadNodeIdUnknown" in missing[0]["message"] and "ns=2;s=T1_nowhere" in missing[0]["message"]
    assert ("T1", "degraded") in [(e[2]["sensor"], e[2]["status"]) for e in events(db, "sensor")]
    assert sink.rows and all(math.isfinite(o.dx_um) for o in sink.rows)


# --------------------------------------------------------------------------- the database may stall, offsets may not


class _PacedSource(ListSource):
    """The trace at ``per_s`` readings per wall second; then, with ``release``, silence (the machine's data stop)
    until it is set."""

    time_scale = None

    def __init__(self, readings, per_s, release=None):
        super().__init__(readings)
        self.per_s = per_s
        self.release = release

    async def readings(self, start_after_s=None):
        t0 = time.monotonic()
        for i, r in enumerate(self._readings):
            if start_after_s is not None and r.time_s <= start_after_s:
                continue
            await asyncio.sleep(max(0.0, t0 + i / self.per_s - time.monotonic()))
            yield r
        while self.release is not None and not self.release.is_set():
            await asyncio.sleep(0.02)
        self.finished = True


@pytest.mark.slow
def test_a_database_locked_by_another_process_does_not_stall_compensation(machine, rom, rom_file, trace, tmp_path):
    path, s, T = trace
    readings = list(read_replay(path, machine))[:900]  # 2.5 h of machine time in 9 s of wall time
    db, _ = make_db(tmp_path / "cd.db", machine, T)
    cfg = config(rom_file, path, tmp_path)
    hold_s = 4.0
    locked = threading.Event()

    def hold_the_write_lock():
        time.sleep(2.0)
        con = sqlite3.connect(tmp_path / "cd.db", timeout=30.0, isolation_level=None)
        con.execute("BEGIN IMMEDIATE")  # what another writer does while it works
        locked.set()
        time.sleep(hold_s)
        con.execute("ROLLBACK")
        con.close()

    th = threading.Thread(target=hold_the_write_lock)
    th.start()
    sink = TimedSink()
    mon, sink, res = run(cfg, machine, rom, db, _PacedSource(readings, 100.0), sink)
    th.join()
    assert locked.is_set()
    assert len(sink.rows) == len(readings)
    # the readings come every 10 ms of wall time; with the lock held for 4 s, no offset waited for the database
    assert np.max(np.diff(sink.wall)) < 1.0
    # and everything that waited was stored afterwards, in order, the delay reported
    dec = events(db, "decision")
    assert len(dec) == int((readings[-1].time_s - readings[0].time_s) // 900) + 1
    slow = [e[2] for e in events(db, "store")]
    assert slow and slow[0]["status"] == "slow" and slow[0]["waited_s"] > 1.0


@pytest.mark.slow
def test_status_is_healthy_while_offsets_are_applied_behind_a_database_lock(machine, rom, rom_file, trace, tmp_path):
    """Another process holds the database's write lock for 3 s: the daemon's heartbeat in the database waits, its
    offsets do not; ``monitor status`` on this host reads the heartbeat's local copy and says healthy (it said
    unhealthy once the database's copy was older than ``stale_after_s``)."""
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.cli import status_dict

    path, s, T = trace
    readings = list(read_replay(path, machine))[:900]
    db, _ = make_db(tmp_path / "cd.db", machine, T)
    cfg = config(rom_file, path, tmp_path, monitor={"stale_after_s": 1.0})
    seen = {}

    def hold_the_write_lock():
        time.sleep(2.0)
        con = sqlite3.connect(tmp_path / "cd.db", timeout=30.0, isolation_level=None)
        con.execute("BEGIN IMMEDIATE")
        time.sleep(3.0)
        with CDDatabase(tmp_path / "cd.db", readonly=True) as reader:  # status reads (and never waits)
            seen["status"] = status_dict(cfg, reader, machine.name, PKEY)
        con.execute("ROLLBACK")
        con.close()

    th = threading.Thread(target=hold_the_write_lock)
    th.start()
    sink = TimedSink()
    run(cfg, machine, rom, db, _PacedSource(readings, 100.0), sink, heartbeat_s=0.2)
    th.join()
    st = seen["status"]
    assert len(sink.rows) == len(readings) and np.max(np.diff(sink.wall)) < 1.0  # offsets went on
    assert st["health"] == "healthy", st["health_reason"]
    assert st["running"] is True and st["daemon_alive"] is True and st["seconds_since_offset"] < 1.0


# --------------------------------------------------------------------------- nothing absurd reaches the control


def test_the_output_guard_refuses_non_finite_and_beyond_clamp_offsets():
    ok = Offset(10.0, 1.0, -2.0, 3.0, "X=1,Y=2,Z=3", False, False, False, "", "cd")
    assert check_offset(ok, 100.0) == ""
    assert "offset dz_um = nan µm is not finite" in check_offset(replace(ok, dz_um=math.nan), 100.0)
    assert "offset dx_um = inf µm is not finite" in check_offset(replace(ok, dx_um=math.inf), 100.0)
    assert "beyond the clamp" in check_offset(replace(ok, dy_um=-1e300), 100.0)
    assert "time_s" in check_offset(replace(ok, time_s=math.nan), 100.0)


@pytest.mark.slow
def test_non_finite_offsets_are_held_and_never_reach_the_sink(machine, rom, rom_file, trace, tmp_path, monkeypatch):
    path, s, T = trace
    readings = list(read_replay(path, machine))[:400]
    db, _ = make_db(tmp_path / "cd.db", machine, T)
    cfg = config(rom_file, path, tmp_path, compensation={"strategy": "observer"})
    mon = Monitor(cfg, machine, rom, db, PKEY)
    poisoned = {"n": 0}
    real = type(mon.observer).drift_um

    def drift_um(self, state):  # the structure model goes NaN for a while (a numerical fault)
        poisoned["n"] += 1
        return real(self, state) * (math.nan if 20 <= poisoned["n"] < 40 else 1.0)

    monkeypatch.setattr(type(mon.observer), "drift_um", drift_um)
    sink = MemorySink()
    asyncio.run(run_monitor(cfg, mon, ListSource(readings), sink))
    rows = _rows(sink)
    assert len(rows) == len(readings)
    assert np.all(np.isfinite(rows[:, 1:])) and np.all(np.abs(rows[:, 1:]) <= cfg.max_offset_um)
    assert any("non-finite offsets" in e[2]["message"] for e in events(db, "warning"))


# --------------------------------------------------------------------------- one writer per pose


def _lease_db(url_or_path):
    from hybridcomp.chardiag.db import CDDatabase

    return CDDatabase(url_or_path)


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return str(tmp_path / "lease.db")
    return request.getfixturevalue("fresh_postgres_url")


def test_one_lease_per_pose_on_sqlite_and_postgresql(db_url):
    a, b = _lease_db(db_url), _lease_db(db_url)
    try:
        sa_, sb = MonitorStore(a), MonitorStore(b)
        one = {"owner": "host-a:1:x", "host": "elsewhere", "pid": 1}
        two = {"owner": "host-b:2:y", "host": "elsewhere", "pid": 2}
        assert sa_.acquire_lease("m:pose", one, 30.0, 1000.0) is None
        assert sa_.acquire_lease("m:pose", one, 30.0, 1010.0) is None  # renewal
        held = sb.acquire_lease("m:pose", two, 30.0, 1020.0)
        assert held["owner"] == one["owner"]
        assert sb.acquire_lease("m:pose", two, 30.0, 1041.0) is None  # expired: taken over
        assert sa_.acquire_lease("m:pose", one, 30.0, 1042.0)["owner"] == two["owner"]  # the old owner has lost it
        sb.release_lease("m:pose", two["owner"])
        assert sa_.acquire_lease("m:pose", one, 30.0, 1043.0) is None
        # of many daemons starting at the same instant, exactly one gets the lease
        winners = []
        barrier = threading.Barrier(6)

        def contend(k):
            store = MonitorStore(_lease_db(db_url))
            barrier.wait()
            got = store.acquire_lease("m:race", {"owner": f"o{k}", "host": "elsewhere", "pid": k}, 30.0, 2000.0)
            if got is None:
                winners.append(k)
            store.db.close()

        ths = [threading.Thread(target=contend, args=(k,)) for k in range(6)]
        for t in ths:
            t.start()
        for t in ths:
            t.join()
        assert len(winners) == 1
    finally:
        a.close()
        b.close()


def test_a_lease_left_by_a_killed_process_on_this_host_is_free():
    import socket
    import subprocess
    import sys

    from hybridcomp.monitor.store import _lease_free

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    dead = {"owner": "x", "host": socket.gethostname(), "pid": proc.pid, "expires_unix": time.time() + 60}
    alive = {**dead, "pid": subprocess.os.getpid()}
    assert _lease_free(dead, time.time())
    assert not _lease_free(alive, time.time())


@pytest.mark.slow
def test_a_second_daemon_on_the_same_pose_refuses_or_stands_by(machine, rom, rom_file, trace, tmp_path, db_url):
    path, s, T = trace
    readings = list(read_replay(path, machine))[:600]
    if db_url.endswith(".db"):
        db_url = str(tmp_path / "cd.db")
    db, _ = make_db(db_url, machine, T)
    cfg = config(rom_file, path, tmp_path)

    async def both(standby):
        first = Monitor(cfg, machine, rom, db, PKEY)
        second = Monitor(cfg, machine, rom, db, PKEY)
        sink1, sink2 = MemorySink(), MemorySink()
        t1 = asyncio.create_task(run_monitor(cfg, first, _PacedSource(readings, 400.0), sink1))
        while first.s.last_time_s is None:
            await asyncio.sleep(0.01)
        r2 = await asyncio.gather(run_monitor(cfg, second, ListSource(readings), sink2, standby=standby),
                                  return_exceptions=True)
        r1 = await t1
        return r1, r2[0], sink1, sink2, second

    r1, r2, sink1, sink2, second = asyncio.run(both(False))
    assert isinstance(r2, LeaseHeld) and "refusing to start a second writer" in str(r2)
    assert len(sink2.rows) == 0 and len(sink1.rows) == len(readings)
    decisions = [e[3] for e in events(db, "decision")]
    assert len(decisions) == len(set(decisions)) == int((readings[-1].time_s - readings[0].time_s) // 900) + 1

    # a standby waits for the lease, then takes over from the first daemon's last state: no decision twice
    last_boundary = max(e[1] for e in events(db, "decision"))
    db.close()
    if not db_url.endswith(".db"):
        return  # (the standby is the same code on either database)
    db, _ = make_db(tmp_path / "cd2.db", machine, T)
    r1, r2, sink1, sink2, second = asyncio.run(both(True))
    assert not isinstance(r2, Exception)
    assert [e[2]["status"] for e in events(db, "lease")] == ["taken over"]
    # it resumed where a restart of the first would: after the first's last monitoring boundary
    assert sink2.rows and sink2.rows[0].time_s > last_boundary and second.s.last_time_s == readings[-1].time_s
    decisions = [e[3] for e in events(db, "decision")]
    assert len(decisions) == len(set(decisions)) == int((readings[-1].time_s - readings[0].time_s) // 900) + 1
    db.close()


# --------------------------------------------------------------------------- status when compensation stops


def test_status_is_unhealthy_when_no_offset_is_applied():
    from hybridcomp.monitor.cli import health

    now = {"running": True, "seconds_since_offset": 3.0, "store_backlog": 0}
    assert health(now, 20.0)[0] == "healthy"
    assert health({**now, "seconds_since_offset": 45.0}, 20.0) == ("unhealthy", "no offset applied for 45 s (limit 20 s)")
    assert health({**now, "running": False}, 20.0)[0] == "unhealthy"
    assert health({**now, "running": None}, 20.0)[0] == "unhealthy"
    # writes waiting for the database delay no offset: healthy, and said (issue 31: not unhealthy during a lock)
    assert health({**now, "store_backlog": 5000}, 20.0) == (
        "healthy", "last offset applied 3.0 s ago; 5000 database writes queued (the database does not take writes)")


@pytest.mark.slow
def test_status_after_the_data_stops_says_unhealthy(machine, rom, rom_file, trace, tmp_path):
    from hybridcomp.monitor.cli import status_dict

    path, s, T = trace
    readings = list(read_replay(path, machine))[:100]
    db, _ = make_db(tmp_path / "cd.db", machine, T)
    cfg = config(rom_file, path, tmp_path, monitor={"stale_after_s": 20.0})
    run(cfg, machine, rom, db, ListSource(readings))
    st = status_dict(cfg, db, machine.name, PKEY)
    assert st["health"] == "unhealthy" and "stopped" in st["health_reason"]
    beat = json.loads(MonitorStore(db).get_state(f"monitor:{machine.name}:{PKEY}:heartbeat"))
    assert beat["applied_unix"] is not None and beat["running"] is False


# --------------------------------------------------------------------------- replay files


def test_replay_traces_with_a_bom_binary_garbage_or_a_fifo(machine, tmp_path):
    import os

    from hybridcomp.monitor.sources import SourceFileError

    f = tmp_path / "t.csv"
    f.write_bytes("\ufefftime_s,x_mm,y_mm,z_mm\n0,1,2,3\n1,1,2,3\r\n".encode())
    assert [r.time_s for r in read_replay(f, machine)] == [0.0, 1.0]  # a BOM is no part of time_s
    f.write_bytes(b"time_s,x_mm,y_mm,z_mm\n0,1,2,3\n\xff\xfe,1,2,3\n")
    with pytest.raises(SourceFileError, match=r"t\.csv: line 3: not UTF-8 text"):
        list(read_replay(f, machine))
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(SourceFileError, match=r"fifo: cannot open replay trace: it is a named pipe"):
        list(read_replay(tmp_path / "fifo", machine))


@pytest.mark.slow
def test_the_lease_is_renewed_while_the_data_are_silent(machine, rom, rom_file, trace, tmp_path):
    from hybridcomp.monitor.store import lease_owner

    path, s, T = trace
    readings = list(read_replay(path, machine))[:20]
    db, _ = make_db(tmp_path / "cd.db", machine, T)
    cfg = config(rom_file, path, tmp_path, monitor={"lease_s": 0.6})
    other = MonitorStore(db)
    refused = []

    async def go():
        release = asyncio.Event()
        mon = Monitor(cfg, machine, rom, db, PKEY)
        task = asyncio.create_task(run_monitor(cfg, mon, _PacedSource(readings, 1000.0, release), MemorySink()))
        while mon.s.last_time_s != readings[-1].time_s:
            await asyncio.sleep(0.01)
        for _ in range(10):  # 2 s of silence: more than three lease lengths
            await asyncio.sleep(0.2)
            refused.append(other.acquire_lease(mon.key, lease_owner() | {"host": "elsewhere"}, 0.6, time.time()))
        release.set()
        await task

    asyncio.run(go())
    assert all(h is not None for h in refused)  # held all along: renewed without data
