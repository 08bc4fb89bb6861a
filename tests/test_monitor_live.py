"""``hybridcomp monitor serve``: the live view's JSON, /metrics, the page in a headless browser, its refusals.

One short replay (an hour at 0.1 Hz, axis X and the spindle busy for 40 min, on the shared coarse reduced model, a CD
set that predicts 0.8 × the drift, two probes, a JSON-lines sink) is the daemon's record. The server runs on loopback
(port 0) in this process; what it shows is checked against what the daemon wrote (the sink's last line, the
database's events) and against the daemon's own state after the run, not against the server's own reading.
"""

from __future__ import annotations

import asyncio
import collections
import importlib.util
import json
import math
import os
import re
import shutil
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from hybridcomp.models.layout import DRIFT_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
POSE = {"X": 0.0, "Y": 0.0, "Z": 0.0}
PKEY = "X=0,Y=0,Z=0"
TOKEN = "a-test-token-of-32-characters-xx"
OK = {"": 200, "api/live": 200, "metrics": 200 if importlib.util.find_spec("prometheus_client") else 503}
FIGURE = ROOT / "benchmarks" / "figures" / "live_view.png"  # the README's picture (HYBRIDCOMP_UPDATE_FIGURES=1)


def get(url: str, headers: dict | None = None, method: str = "GET") -> tuple[int, bytes, dict]:
    req = urllib.request.Request(url, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read(), dict(r.headers)
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(), dict(exc.headers)


# --------------------------------------------------------------------------- pure parts (no replay)
def test_scrub_removes_paths_and_urls_and_keeps_units():
    from hybridcomp.monitor.live import scrub

    text = ("sink /srv/plant/offsets.jsonl: cannot write; database postgresql+psycopg://op:secret@db.plant/cds; "
            r"C:\monitor\cds.sqlite; 0.4 µm/K at X=0,Y=0,Z=0, 1/√h")
    out = scrub({"msg": text, "n": [1.5, math.nan]})
    assert "/srv" not in out["msg"] and "secret" not in out["msg"] and "monitor\\cds" not in out["msg"]
    assert "0.4 µm/K at X=0,Y=0,Z=0, 1/√h" in out["msg"] and out["n"] == [1.5, None]


def test_the_support_point_table_is_shown_point_by_point():
    import numpy as np

    from hybridcomp.monitor.live import _table
    from hybridcomp.rom.volumetric import FeedbackTable, SupportGrid, VolumetricTable, table_to_dict

    grid = SupportGrid(("X", "Y", "Z"), ((-400.0, 0.0, 400.0), (-250.0, 250.0), (-300.0, 0.0, 300.0)))
    S = np.arange(3 * 2 * 3 * 3, dtype=float).reshape(3, 2, 3, 3) / 10.0
    fb = (FeedbackTable("X", np.linspace(-400.0, 400.0, 17), np.linspace(0.0, -3.0, 17), 0, 1.0),)
    t = _table(table_to_dict(VolumetricTable(grid, 7200.0, S, fb)))
    assert t["axes"] == ["X", "Y", "Z"] and t["time_h"] == 2.0 and len(t["points"]) == 18
    i, j, k = 2, 1, 0  # X = 400, Y = 250, Z = -300: row (i * 2 + j) * 3 + k in the order of the axes
    assert t["points"][(i * 2 + j) * 3 + k] == [400.0, 250.0, -300.0, *S[i, j, k]]
    assert t["drives"] == [{"axis": "X", "direction": 0, "max_abs_um": 3.0}]


def test_binding_refusals():
    from hybridcomp.monitor.serve import ServeError, check_binding, is_loopback

    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.20") and not is_loopback("plant-pc")
    check_binding("127.0.0.1", None)
    check_binding("0.0.0.0", TOKEN)
    with pytest.raises(ServeError, match="--token"):
        check_binding("0.0.0.0", None)
    with pytest.raises(ServeError, match="at least 16"):
        check_binding("127.0.0.1", "short")


def test_the_command_refuses_another_address_without_a_token(capsys, monkeypatch, tmp_path):
    from hybridcomp.cli import main

    monkeypatch.delenv("HYBRIDCOMP_MONITOR_TOKEN", raising=False)
    assert main(["monitor", "serve", "--database", str(tmp_path / "none.db"), "--host", "0.0.0.0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --host 0.0.0.0") and "--token" in err
    assert not (tmp_path / "none.db").exists()  # refused before anything is opened


def test_ep95_window_labels_read_as_a_person_says_them():
    from hybridcomp.metrics import WINDOWS_S
    from hybridcomp.plotaxes import window_label

    assert [window_label(w / 3600.0) for w in WINDOWS_S] == ["15 min", "30 min", "1 h", "2 h", "4 h", "8 h", "15 h"]


# --------------------------------------------------------------------------- the replay
def busy_hour(machine):
    """1 h at 0.1 Hz: axis X and the spindle busy for 40 min, then standstill; the air 20 → 20.3 °C."""
    import numpy as np

    from hybridcomp.histogram.trace import samples

    t = np.arange(0.0, 3600.0 + 5.0, 10.0)
    busy = t < 2400.0
    x = np.where(busy, 300.0 * np.sin(2 * np.pi * t / 97.0), 0.0)
    spindle = np.where(busy, 0.6 * machine.spindle_max_speed_rpm, 0.0)
    return samples(machine, t, {"X": x, "Y": np.full_like(t, -100.0), "Z": np.zeros_like(t)}, spindle,
                   air_degC={"Tamb_degC": 20.0 + 0.3 * t / t[-1]})


@pytest.fixture(scope="module")
def replay(machine, small_rom, tmp_path_factory):
    """The daemon's record of a 1 h replay: database, heartbeat file, JSON-lines sink; and the daemon itself."""
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import FitOptions, fit_cd_set
    from hybridcomp.monitor.config import parse_config
    from hybridcomp.monitor.daemon import Monitor, run_monitor
    from hybridcomp.monitor.example import rom_outputs
    from hybridcomp.monitor.sinks import make_sink
    from hybridcomp.monitor.sources import ReplaySource
    from hybridcomp.rom import save_rom

    out = tmp_path_factory.mktemp("live-replay")
    rom_file = save_rom(out / "vmc800.rom.npz", small_rom)
    s = busy_hour(machine)
    T, drift = rom_outputs(machine, small_rom, s, 60.0)
    names = [n.name for n in machine.sensors]
    probes = {150: 0.4, 300: -0.3}  # rows probed, with an offset the sensors cannot see [µm]
    with open(out / "trace.csv", "w") as fh:
        fh.write(",".join(["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", *(f"{n}_degC" for n in names),
                           "Tamb_degC", "probe_dx_um", "probe_dy_um", "probe_dz_um"]) + "\n")
        for i in range(len(s)):
            p = [f"{v + probes[i]:.6f}" for v in drift[i]] if i in probes else ["", "", ""]
            fh.write(",".join([*(f"{v:.12g}" for v in (s.time_s[i], *s.position_mm[i], s.spindle_rpm[i], *T[i],
                                                         s.air_degC[i, 0])), *p]) + "\n")
    table = {f"{n}_degC": T[:, j] for j, n in enumerate(names)}
    table |= {c: 0.8 * drift[:, j] for j, c in enumerate(DRIFT_COLUMNS)}
    cds = fit_cd_set(table, machine=machine.name, machine_sha256=machine.sha256, pose_mm=POSE, load_case="0.8 day",
                     t_reference_degC=dict(zip(names, map(float, T[0]))),
                     options=FitOptions(n_support=4, select="bic", max_inputs=2, max_full_dims=1))
    db = CDDatabase(out / "cd.sqlite")
    db.activate(machine.name, PKEY, db.add_set(cds, "0.8 day"), "initial")
    cfg = parse_config({"monitor": {"machine": "vmc800", "database": str(out / "cd.sqlite"), "rom": str(rom_file),
                                    "pose_mm": POSE, "increment_s": 60.0},
                        "compensation": {"max_offset_um": 100.0, "max_step_um": 2.0},
                        "source": {"kind": "replay", "path": str(out / "trace.csv"), "speed": 0},
                        "sink": {"kind": "jsonl", "path": str(out / "offsets.jsonl")},
                        "regeneration": {"enabled": False}}, "live.toml", out)
    mon = Monitor(cfg, machine, small_rom, db, PKEY)
    asyncio.run(run_monitor(cfg, mon, ReplaySource(out / "trace.csv", machine, 0), make_sink(cfg.sink, cfg.reconnect,
                                                                                              None)))
    db.close()
    rows = [json.loads(line) for line in (out / "offsets.jsonl").read_text().splitlines()]
    assert len(rows) == len(s)
    return {"dir": out, "cfg": cfg, "monitor": mon, "rows": rows}


def reader_of(replay, **kw):
    from hybridcomp.monitor.live import LiveReader, source_from_config

    return LiveReader(source_from_config(replay["cfg"]), **kw)


@pytest.fixture
def server(replay):
    """The live view of the replay on loopback, port 0 (a fresh reader: nothing cached between tests)."""
    from hybridcomp.monitor.serve import LiveServer, serve_in_thread

    started = []

    def start(reader=None, token=None, interval_s=0.5):
        srv = LiveServer(reader or reader_of(replay, refresh_s=0.2), "127.0.0.1", 0, token, interval_s)
        serve_in_thread(srv)
        started.append(srv)
        return srv

    yield start
    for srv in started:
        srv.shutdown()
        srv.server_close()
        srv.reader.close()


def db_events(replay):
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.store import MonitorStore

    with CDDatabase(replay["cfg"].database, readonly=True) as db:
        return MonitorStore(db).events()


@pytest.mark.slow
def test_the_json_shows_what_the_daemon_wrote(replay, server):
    from hybridcomp.monitor import transitions as T
    from hybridcomp.monitor.live import MAX_POINTS

    srv = server()
    code, body, headers = get(srv.url + "api/live")
    assert code == 200 and headers["Content-Type"] == "application/json"
    d = json.loads(body)
    last = replay["rows"][-1]
    assert d["latest"]["offsets_um"] == {c: last[c] for c in DRIFT_COLUMNS}
    assert d["latest"]["t_h"] == pytest.approx(last["time_s"] / 3600.0, abs=1e-6) == pytest.approx(1.0, abs=1e-6)
    off = d["series"]["offsets"]
    assert len(off["t_h"]) <= MAX_POINTS and off["dz_um"][-1] == last["dz_um"] and off["t_h"][0] == 0.0
    # the decisions' predicted errors, in order, and the last one's as the latest
    decisions = [e for e in db_events(replay) if e.kind == "decision"]
    assert d["series"]["error"]["t_h"] == [e.machine_time_s / 3600.0 for e in decisions]
    assert d["series"]["error"]["interval_um"][-1] == decisions[-1].payload["error_um"]["interval_um"]
    assert d["latest"]["error_um"]["forecast_um"] == decisions[-1].payload["error_um"]["forecast_um"]
    assert d["limits"] == {"keep_um": 1.5, "forecast_um": 3.0, "hard_um": 3.0, "reject_um": 50.0, "threshold_K": 0.5,
                           "model_drift_K": 1.0}
    # the sensors against the observer's estimate: the daemon's own state at its end
    mon = replay["monitor"]
    est = T._estimate_degC(mon.ctx, mon.state)
    for s in d["sensors_now"]:
        assert s["estimate_degC"] == est[s["name"]] and s["measured_degC"] == mon.state.measured[s["name"]]
        assert s["residual_K"] == pytest.approx(mon.state.measured[s["name"]] - est[s["name"]], abs=1e-12)
    # probes at the rows probed, the active set, the events of the shift (no kept decisions among them)
    assert [p["t_h"] for p in d["series"]["probes"]] == pytest.approx([1500 / 3600, 3000 / 3600], abs=60 / 3600)
    assert d["active"]["load_case"] == "0.8 day" and d["strategy"] == "hybrid"
    counts = collections.Counter(e.kind for e in db_events(replay))
    assert d["event_counts"] == dict(counts) and counts["probe"] == 2
    assert all(not (e["kind"] == "decision" and e["summary"].startswith("keep")) for e in d["events"])
    assert d["health"]["status"] == "unhealthy" and d["health"]["running"] is False  # the replay has ended


@pytest.mark.slow
def test_metrics_parse_and_carry_the_figures(replay, server):
    pytest.importorskip("prometheus_client", reason="/metrics needs prometheus_client (extra live, in the test extra)")
    from prometheus_client.parser import text_string_to_metric_families

    srv = server()
    t0 = time.time()
    code, body, headers = get(srv.url + "metrics")
    t1 = time.time()
    assert code == 200 and headers["Content-Type"].startswith("text/plain")
    samples = {}
    for fam in text_string_to_metric_families(body.decode()):
        for s in fam.samples:
            samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    last = replay["rows"][-1]
    for c in DRIFT_COLUMNS:
        assert samples[("hybridcomp_monitor_offset_micrometers", (("axis", c[:2]),))] == last[c]
    events = db_events(replay)
    err = [e for e in events if e.kind == "decision"][-1].payload["error_um"]
    assert samples[("hybridcomp_monitor_predicted_error_micrometers", (("horizon", "interval"),))] == err["interval_um"]
    assert samples[("hybridcomp_monitor_predicted_error_micrometers", (("horizon", "forecast"),))] == err["forecast_um"]
    assert samples[("hybridcomp_monitor_error_limit_micrometers", (("limit", "keep"),))] == 1.5
    for kind, n in collections.Counter(e.kind for e in events).items():
        assert samples[("hybridcomp_monitor_events_total", (("kind", kind),))] == n
    mon = replay["monitor"]
    from hybridcomp.monitor import transitions as T

    est = T._estimate_degC(mon.ctx, mon.state)
    for n, v in est.items():
        assert samples[("hybridcomp_monitor_sensor_residual_kelvin", (("sensor", n),))] == pytest.approx(
            mon.state.measured[n] - v, abs=1e-12)
    beat = json.loads(next(replay["dir"].glob("cd.sqlite.*.heartbeat.json")).read_text())
    assert samples[("hybridcomp_monitor_store_queue_length", ())] == beat["store_backlog"]
    since = samples[("hybridcomp_monitor_seconds_since_applied_offset", ())]
    assert t0 - beat["applied_unix"] <= since <= t1 - beat["applied_unix"]
    assert samples[("hybridcomp_monitor_healthy", ())] == 0.0  # the replay has ended
    # every metric the Grafana dashboard shows exists
    dashboard = (ROOT / "monitor" / "grafana_dashboard.json").read_text()
    used = set(re.findall(r"hybridcomp_monitor_[a-z_]+", dashboard))
    assert len(used) >= 10 and used <= {name for name, _ in samples}, used - {name for name, _ in samples}


@pytest.mark.slow
def test_the_view_follows_new_offsets_within_two_intervals(replay, server, tmp_path):
    from hybridcomp.monitor.live import LiveReader, LiveSource

    sink = tmp_path / "offsets.jsonl"
    shutil.copyfile(replay["dir"] / "offsets.jsonl", sink)
    interval_s = 0.3
    srv = server(LiveReader(LiveSource(str(replay["cfg"].database), "vmc800", PKEY, sink, "jsonl"),
                            refresh_s=interval_s / 2), interval_s=interval_s)
    assert json.loads(get(srv.url + "api/live")[1])["latest"]["offsets_um"]["dx_um"] == replay["rows"][-1]["dx_um"]
    new = {**replay["rows"][-1], "time_s": replay["rows"][-1]["time_s"] + 10.0, "dx_um": 1.234567}
    line = json.dumps(new) + "\n"
    with open(sink, "a") as fh:  # half a line first: never read
        fh.write(line[:20])
    time.sleep(2 * interval_s)
    assert json.loads(get(srv.url + "api/live")[1])["latest"]["offsets_um"]["dx_um"] == replay["rows"][-1]["dx_um"]
    with open(sink, "a") as fh:
        fh.write(line[20:])
    time.sleep(2 * interval_s)
    d = json.loads(get(srv.url + "api/live")[1])
    assert d["latest"]["offsets_um"]["dx_um"] == 1.234567 and d["series"]["offsets"]["dx_um"][-1] == 1.234567
    assert d["latest"]["offsets_t_h"] == pytest.approx(new["time_s"] / 3600.0, abs=1e-6)


@pytest.mark.slow
def test_read_only_token_and_no_paths(replay, server):
    db_file = Path(replay["cfg"].database)
    before = db_file.read_bytes()
    srv = server(token=TOKEN)
    for path in ("", "api/live", "metrics"):
        assert get(srv.url + path)[0] == 401
        assert get(srv.url + path, {"Authorization": "Bearer " + TOKEN[:-1] + "y"})[0] == 401
        assert get(srv.url + path, {"Authorization": "Bearer " + TOKEN})[0] == OK[path]
    assert get(srv.url + "api/live?token=" + TOKEN)[0] == 200
    for method in ("POST", "PUT", "DELETE", "PATCH"):
        code, _, headers = get(srv.url + "api/live", {"Authorization": "Bearer " + TOKEN}, method)
        assert code == 405 and headers["Allow"] == "GET, HEAD"
    # no path of this machine, no file name of the record, no token in anything the server sends
    secret = [str(replay["dir"]), replay["dir"].name, "cd.sqlite", "offsets.jsonl", "trace.csv", "rom.npz", TOKEN]
    for path in ("", "api/live", "metrics"):
        code, body, headers = get(srv.url + path, {"Authorization": "Bearer " + TOKEN})
        text = body.decode()
        assert code == OK[path] and not [s for s in secret if s in text], path
        assert "default-src 'none'" in headers["Content-Security-Policy"]
    assert db_file.read_bytes() == before  # nothing was written


def render(url: str, tmp_path: Path, interval_s: float, shot: Path | None = None) -> str:
    """The page's DOM after two intervals of its time in headless Chromium, checked for console lines and errors."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed (Debian: apt-get install chromium; .ci/run installs it as root)")
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
           f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0", "--dump-dom",
           *([f"--screenshot={shot}"] if shot else []), "--window-size=1400,1250",
           f"--virtual-time-budget={int(2 * interval_s * 1000)}", url]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr[-2000:]
    console = [line for line in res.stderr.splitlines() if ":CONSOLE" in line]
    assert not console, console  # the page writes nothing to the console: any line is an error or a failed load
    dom = res.stdout
    errors = re.search(r'<pre id="page-errors">(.*?)</pre>', dom, re.S)
    assert errors is not None and errors.group(1).strip() == ""
    assert int(re.search(r'data-updates="(\d+)"', dom).group(1)) >= 1
    return dom


@pytest.mark.slow
def test_the_page_in_a_headless_browser(replay, server, tmp_path):
    interval_s = 0.5
    srv = server(interval_s=interval_s)
    shot = tmp_path / "live_view.png"
    dom = render(srv.url, tmp_path, interval_s, shot)
    last = replay["rows"][-1]
    for c in DRIFT_COLUMNS:  # the offsets plot's legend: the replay's last offsets
        m = re.search(rf'id="latest-offsets-{c}" data-value="([^"]+)" data-t="([^"]+)">([^<]*)<', dom)
        assert m is not None and float(m.group(1)) == last[c], c
        assert float(m.group(2)) == pytest.approx(last["time_s"] / 3600.0, abs=1e-6)
        assert m.group(3) == f"{last[c]:.2f} µm".replace("-0.00", "0.00")
    m = re.search(r'id="latest-error-interval" data-value="([^"]+)"', dom)
    err = [e for e in db_events(replay) if e.kind == "decision"][-1].payload["error_um"]
    assert float(m.group(1)) == err["interval_um"]
    assert dom.count("<path d=") >= 6 and "machine time [h]" in dom and "offset [µm]" in dom
    assert shot.stat().st_size > 20_000
    if os.environ.get("HYBRIDCOMP_UPDATE_FIGURES") == "1":
        shutil.copyfile(shot, FIGURE)


def js_fixed(v: float, digits: int) -> str:
    """The page's ``fmt``: ``toFixed`` without the sign of a negative zero."""
    s = f"{v:.{digits}f}"
    return s[1:] if re.fullmatch(r"-0\.?0*", s) else s


@pytest.mark.slow
def test_the_browser_shows_the_support_point_table_point_by_point(tmp_path):
    """A heartbeat that carries a support-point table (written by hand, no replay): every point's row in the page."""
    import numpy as np

    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.daemon import state_key
    from hybridcomp.monitor.live import LiveReader, LiveSource
    from hybridcomp.monitor.serve import LiveServer, serve_in_thread
    from hybridcomp.monitor.store import MonitorStore
    from hybridcomp.rom.volumetric import FeedbackTable, SupportGrid, VolumetricTable, table_to_dict

    positions = ((-400.0, 0.0, 400.0), (-250.0, 250.0), (-300.0, 0.0, 300.0))
    grid = SupportGrid(("X", "Y", "Z"), positions)
    S = (np.arange(3 * 2 * 3 * 3, dtype=float).reshape(3, 2, 3, 3) - 20.0) / 7.0  # [µm], negatives and fractions
    fb = (FeedbackTable("X", np.linspace(-400.0, 400.0, 17), np.linspace(0.0, -3.0, 17), 0, 1.0),)
    key = state_key("vmc800", PKEY)
    with CDDatabase(tmp_path / "cd.sqlite") as db:
        MonitorStore(db).put_state(key + ":heartbeat", json.dumps({
            "key": key, "unix": time.time(), "running": False, "last_time_s": 7200.0,
            "offsets_um": {c: 0.5 for c in DRIFT_COLUMNS},
            "live": {"table": table_to_dict(VolumetricTable(grid, 7200.0, S, fb))}}))
    interval_s = 0.5
    srv = LiveServer(LiveReader(LiveSource(str(tmp_path / "cd.sqlite"), "vmc800", PKEY), refresh_s=0.2), "127.0.0.1",
                     0, None, interval_s)
    serve_in_thread(srv)
    try:
        dom = render(srv.url, tmp_path, interval_s)
    finally:
        srv.shutdown()
        srv.server_close()
        srv.reader.close()
    box = re.search(r'<div id="support-table"[^>]*>(.*?)</div>', dom, re.S).group(1)
    rows = [re.findall(r"<t[hd]>([^<]*)</t[hd]>", r) for r in re.findall(r"<tr>(.*?)</tr>", box, re.S)]
    assert rows[0] == ["X [mm]", "Y [mm]", "Z [mm]", "dx [µm]", "dy [µm]", "dz [µm]"]
    want = [[js_fixed(x, 0), js_fixed(y, 0), js_fixed(z, 0), *(js_fixed(v, 2) for v in S[i, j, k])]
            for i, x in enumerate(positions[0]) for j, y in enumerate(positions[1]) for k, z in enumerate(positions[2])]
    assert rows[1:] == want  # 18 points, the last axis fastest, as the grid's positions are ordered
    assert "feed drives, largest error over the axis: X 3.00 µm" in box
    assert re.search(r'id="table-note"[^>]*>\(at 2\.000 h\)<', dom)


@pytest.mark.slow
def test_a_replay_folder_is_read_from_its_database(replay, tmp_path):
    from hybridcomp.monitor.live import LiveError, LiveReader, source_from_database

    db_file = Path(replay["cfg"].database)
    for name in ("cd_hybrid.db", "cd_observer.db"):  # what 'monitor scenario --out' leaves, one per strategy
        shutil.copyfile(db_file, tmp_path / name)
    src = source_from_database(tmp_path)
    assert (src.machine, src.pose_key, Path(src.database).name, src.sink_path) == ("vmc800", PKEY, "cd_hybrid.db", None)
    reader = LiveReader(src)
    try:
        d = reader.snapshot()
    finally:
        reader.close()
    # no offsets file: the heartbeat's offsets, the daemon's last ones
    assert d["latest"]["offsets_um"] == {c: replay["rows"][-1][c] for c in DRIFT_COLUMNS}
    assert len(d["series"]["drift"]["t_h"]) >= 12 and d["series"]["error"]["t_h"][-1] == 1.0
    (tmp_path / "cd_hybrid.db").unlink()
    (tmp_path / "other.sqlite").write_bytes(b"")
    with pytest.raises(LiveError, match="2 CD databases"):
        source_from_database(tmp_path)


@pytest.mark.slow
def test_the_command_serves_until_sigterm(replay):
    import signal
    import sys

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("HYBRIDCOMP_MONITOR_TOKEN", None)
    proc = subprocess.Popen([sys.executable, "-m", "hybridcomp", "monitor", "serve", "--database",
                             str(replay["cfg"].database), "--offsets", str(replay["dir"] / "offsets.jsonl"),
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        url = re.search(r"on (http://127\.0\.0\.1:\d+/)", line).group(1)
        d = json.loads(get(url + "api/live")[1])
        assert d["latest"]["offsets_um"]["dy_um"] == replay["rows"][-1]["dy_um"]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
