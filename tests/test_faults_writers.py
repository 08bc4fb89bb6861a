"""Every writer of a pose respects the monitoring daemon's lease, a pose has one key however it is spelled, and
``monitor status`` tells a dead daemon at once and a daemon behind a locked database as healthy (issue 31, item 2).

The CD database commands run in-process (``hybridcomp cd db ...``) on tiny sets; the lease is taken as the daemon
takes it (:meth:`~hybridcomp.monitor.store.MonitorStore.acquire_lease` under
:func:`~hybridcomp.monitor.daemon.state_key`).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest
from test_faults_files import cd_set, ok, refused
from test_monitor_daemon import rom, rom_file  # noqa: F401 - fixtures (the shared small model, saved)

from hybridcomp.chardiag.cd import pose_key
from hybridcomp.models import jsonio

PKEY = "X=0,Y=0,Z=0"


@pytest.fixture()
def db_two_sets(tmp_path):
    pytest.importorskip("sqlalchemy", reason="the CD database needs SQLAlchemy (pip install 'hybridcomp[db]')")
    from hybridcomp.chardiag.db import CDDatabase

    path = tmp_path / "cd.db"
    with CDDatabase(path) as db:
        one, two = db.add_set(cd_set(1), "one"), db.add_set(cd_set(2), "two")
        db.activate("vmc800", PKEY, one, "initial")
    return path, one, two


def _ids(ids) -> str:
    return ",".join(f"{k}={v}" for k, v in sorted(ids.items()))


def _hold(path, owner=None, ttl_s=30.0):
    """Take the pose's lease as a daemon does; returns the owner record."""
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.daemon import state_key
    from hybridcomp.monitor.store import MonitorStore, lease_owner

    owner = owner or lease_owner()
    with CDDatabase(path) as db:
        assert MonitorStore(db).acquire_lease(state_key("vmc800", PKEY), owner, ttl_s, time.time()) is None
    return owner


def test_the_lease_the_database_checks_is_the_daemons():
    from hybridcomp.chardiag.db import monitor_lease_key
    from hybridcomp.monitor.daemon import state_key

    assert monitor_lease_key("vmc800", PKEY) == "lease:" + state_key("vmc800", PKEY)


def test_cd_db_activate_is_refused_while_a_daemon_holds_the_pose(tmp_path, capsys, db_two_sets):
    from hybridcomp.chardiag.db import CDDatabase, CDDatabaseError

    path, one, two = db_two_sets
    owner = _hold(path)
    err = refused(capsys, ["cd", "db", "activate", _ids(two), "--db", path], "held by a monitoring daemon",
                  f"pid {os.getpid()}", "vmc800 X=0,Y=0,Z=0")
    assert "stop it first" in err
    with CDDatabase(path) as db:
        assert db.active_ids("vmc800", PKEY) == one  # the daemon's set stays
        # every writer through the database (cd fit --db --activate, the API), not only the command
        with pytest.raises(CDDatabaseError, match="held by a monitoring daemon"):
            db.activate("vmc800", PKEY, two, "by hand")
        # the daemon itself (its owner token) may
        db.activate("vmc800", PKEY, two, "the daemon's switch", lease_owner=owner["owner"])
        assert db.active_ids("vmc800", PKEY) == two
        from hybridcomp.monitor.daemon import state_key
        from hybridcomp.monitor.store import MonitorStore

        MonitorStore(db).release_lease(state_key("vmc800", PKEY), owner["owner"])
    ok(capsys, ["cd", "db", "activate", _ids(one), "--db", path])  # released: the operator may again
    with CDDatabase(path) as db:
        assert db.active_ids("vmc800", PKEY) == one


def test_a_lease_of_a_killed_daemon_or_an_expired_one_binds_no_one(tmp_path, capsys, db_two_sets):
    import socket

    path, one, two = db_two_sets
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    _hold(path, {"owner": "dead", "host": socket.gethostname(), "pid": proc.pid})
    ok(capsys, ["cd", "db", "activate", _ids(two), "--db", path])
    _hold(path, {"owner": "gone", "host": "elsewhere", "pid": 1}, ttl_s=-1.0)
    ok(capsys, ["cd", "db", "activate", _ids(one), "--db", path])


def test_cd_fit_activate_is_refused_while_a_daemon_holds_the_pose(tmp_path, capsys, db_two_sets):
    """``cd fit --db --activate`` stores the set but does not make it active while the daemon holds the pose."""
    import numpy as np

    from hybridcomp.chardiag.db import CDDatabase

    path, one, _ = db_two_sets
    rng = np.random.default_rng(3)
    n = 120
    T = 22.0 + rng.uniform(-2, 2, (n, 3))
    data = tmp_path / "train.csv"
    lines = ["load_case,time_s,T1_degC,T2_degC,T3_degC,X_mm,Y_mm,Z_mm,dx_um,dy_um,dz_um"]
    for i in range(n):
        d = (T[i] - 22) @ np.array([1.0, -0.5, 0.2])
        lines.append(f"c,{60.0 * i},{T[i, 0]},{T[i, 1]},{T[i, 2]},0,0,0,{d},{0.5 * d},{-d}")
    data.write_text("\n".join(lines) + "\n")
    _hold(path)
    refused(capsys, ["cd", "fit", data, "--machine", "vmc800", "--pose", "X=0,Y=0,Z=0", "--out", tmp_path / "cds",
                     "--db", path, "--activate"], "held by a monitoring daemon")
    with CDDatabase(path) as db:
        assert db.active_ids("vmc800", PKEY) == one


@pytest.mark.parametrize("pose,key", [({"X": 1e-12, "Y": 0, "Z": 0}, PKEY), ({"X": -0.0, "Y": 0, "Z": 0}, PKEY),
                                      ({"X": 0.1 + 0.2, "Y": -50.00000001, "Z": 0}, "X=0.3,Y=-50,Z=0"),
                                      ({"X": 12.3456, "Y": 0, "Z": 0}, "X=12.346,Y=0,Z=0")])
def test_a_pose_is_one_key_however_it_is_spelled(pose, key):
    assert pose_key(pose) == key


def test_a_monitor_on_a_pose_spelled_otherwise_meets_the_same_lease(tmp_path):
    """``pose_mm = {X = 1e-12, ...}`` is the pose ``X=0,Y=0,Z=0``: the same state and lease key, not a second lease."""
    from hybridcomp.monitor.config import parse_config

    data = {"monitor": {"machine": "vmc800", "database": str(tmp_path / "cd.db"), "rom": "unused.rom.npz",
                        "pose_mm": {"X": 1e-12, "Y": 0.0, "Z": -0.0}},
            "source": {"kind": "replay", "path": "unused.csv"}, "sink": {"kind": "none"}}
    cfg = parse_config(data, "m.toml", tmp_path)
    from hybridcomp.models import load_machine

    machine = load_machine(cfg.machine)
    assert pose_key(machine.check_pose(dict(cfg.pose_mm))) == PKEY


# --------------------------------------------------------------------------- monitor status
def _status(path, stale_after_s=20.0):
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.cli import status_dict

    with CDDatabase(path) as db:
        return status_dict(SimpleNamespace(stale_after_s=stale_after_s), db, "vmc800", PKEY)


def test_status_tells_a_killed_daemon_within_one_heartbeat(tmp_path, db_two_sets):
    """A daemon killed with -9 leaves a heartbeat that says running, its last offset fresh: unhealthy at once (it
    said healthy until ``stale_after_s`` had passed)."""
    import socket

    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.daemon import state_key
    from hybridcomp.monitor.store import MonitorStore

    path, _, _ = db_two_sets
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        now = time.time()
        beat = {"unix": now, "applied_unix": now, "running": True, "last_time_s": 100.0, "store_backlog": 0,
                "heartbeat_s": 5.0, "pid": proc.pid, "host": socket.gethostname()}
        with CDDatabase(path) as db:
            MonitorStore(db).put_state(state_key("vmc800", PKEY) + ":heartbeat", jsonio.dumps(beat))
        st = _status(path)
        assert st["health"] == "healthy", st["health_reason"]
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        st = _status(path)
        assert st["health"] == "unhealthy" and f"pid {proc.pid}" in st["health_reason"]
        assert "not running" in st["health_reason"] and time.time() - now < 5.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- the monitor refuses a day of nothing
@pytest.fixture()
def monitor_toml(tmp_path, request):
    """A monitor configuration file on the shared small model; ``database`` and ``path`` of the trace by argument."""
    rom_path = request.getfixturevalue("rom_file")

    def write(trace, database):
        p = tmp_path / "monitor.toml"
        p.write_text(f"""[monitor]
machine = "vmc800"
database = "{database}"
rom = "{rom_path}"
pose_mm = {{ X = 0, Y = 0, Z = 0 }}
increment_s = 60
[source]
kind = "replay"
path = "{trace}"
speed = 0
[sink]
kind = "none"
[regeneration]
enabled = false
""")
        return p
    return write


def _trace(path, sensors: bool):
    head = "time_s,x_mm,y_mm,z_mm,spindle_rpm," + ("T1_degC," if sensors else "") + "Tamb_degC"
    rows = [f"{10 * i},0,0,0,6000," + ("22.0," if sensors else "") + "21.0" for i in range(30)]
    path.write_text("\n".join([head, *rows]) + "\n")
    return path


def test_a_replay_with_no_sensor_column_is_refused_at_start(tmp_path, capsys, monitor_toml):
    trace = _trace(tmp_path / "nosensors.csv", sensors=False)
    cfg = monitor_toml(trace, tmp_path / "cd.db")
    err = refused(capsys, ["monitor", "run", "--config", cfg], str(trace), "no sensor column", "T1_degC")
    assert "the trace has time_s, x_mm" in err
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.store import MonitorStore

    with CDDatabase(tmp_path / "cd.db", readonly=True) as db:  # (the database was opened, nothing ran)
        assert not [e for e in MonitorStore(db).events() if e.kind == "decision"]


def test_a_database_in_a_folder_that_does_not_exist_is_refused_not_created(tmp_path, capsys, monitor_toml):
    trace = _trace(tmp_path / "t.csv", sensors=True)
    missing = tmp_path / "no" / "such" / "folder"
    cfg = monitor_toml(trace, missing / "cd.db")
    refused(capsys, ["monitor", "run", "--config", cfg], "monitor.database", str(missing), "does not exist")
    assert not (tmp_path / "no").exists()


def test_a_cd_grid_activation_is_refused_while_a_daemon_holds_one_of_its_poses(tmp_path, capsys, db_two_sets):
    """A grid is activated point by point: a point at the pose a daemon holds refuses anyone but that daemon (the
    command and the API), and nothing of the grid becomes active."""
    import numpy as np

    from hybridcomp.chardiag.cd import CDSet
    from hybridcomp.chardiag.db import CDDatabase, CDDatabaseError
    from hybridcomp.chardiag.fit import fit_cd_set
    from hybridcomp.chardiag.grid import CDGrid, point_pose
    from hybridcomp.rom.volumetric import SupportGrid

    path, one, _ = db_two_sets
    grid = SupportGrid(("X", "Y", "Z"), ((0.0, 100.0), (0.0, 50.0), (0.0, 40.0)))  # point 0: the held pose
    rng = np.random.default_rng(1)
    T1 = 20.0 + rng.uniform(-2.0, 2.0, 40)
    sets = tuple(CDSet(fit_cd_set({"T1_degC": T1, "dx_um": (i + 1) * (T1 - 20.0), "dy_um": -(T1 - 20.0),
                                   "dz_um": 0.5 * (T1 - 20.0)}, machine="vmc800", pose_mm=point_pose(grid, i),
                                  load_case="grid")) for i in range(grid.n_points))
    with CDDatabase(path) as db:
        gid = db.add_grid(CDGrid(grid, sets, load_case="grid"))
    owner = _hold(path)
    refused(capsys, ["cd", "db", "grid-activate", str(gid), "--db", path], "held by a monitoring daemon",
            "vmc800 X=0,Y=0,Z=0")
    with CDDatabase(path) as db:
        with pytest.raises(CDDatabaseError, match="held by a monitoring daemon"):
            db.activate_grid(gid, "by hand")
        assert db.active_ids("vmc800", PKEY) == one and db.active_grid_id("vmc800") is None
        db.activate_grid(gid, "the daemon's switch", lease_owner=owner["owner"])  # the daemon itself may
        assert db.active_grid_id("vmc800") == gid
