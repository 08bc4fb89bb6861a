"""The live view's data: what ``hybridcomp monitor serve`` shows, read from the daemon's record, never written.

The daemon leaves everything the page needs behind it (:mod:`hybridcomp.monitor.daemon`): in the CD database its
state at the last monitoring boundary (the history of the low-passed sensors and the observer's drift estimate,
every 5 min), its heartbeat every 5 s of wall time (offsets, freshness, the sensors as measured and as the observer
estimates them, the last predicted error and its limits, the support-point table: ``daemon.live_record``), its
events (decisions with their predicted error, activations, generations, sensor faults, model drift, probes, gaps),
and this host's copy of the heartbeat beside an SQLite file; a file sink holds every offset written. A
:class:`LiveReader` reads them incrementally (new events since the last one read, the sink file's new lines, the
state only when it was written again) and gives one JSON-able :meth:`LiveReader.snapshot`, the same for a running
daemon, a stopped one and the database of a replay (``monitor scenario``'s ``cd_hybrid.db``).

Nothing here shows a file path or a database URL: :func:`scrub` removes any from the text that leaves.
"""

from __future__ import annotations

import collections
import csv
import io
import json
import math
import re
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from hybridcomp.errors import HybridcompError
from hybridcomp.models.layout import DRIFT_COLUMNS

SHIFT_HOURS = 8.0  # the events and curves of the last shift of machine time
MAX_POINTS = 720  # a curve sent to the page has at most this many points (decimated)
TAIL_BYTES = 4 << 20  # a sink file is read from at most this far before its end at the start [bytes]
EVENT_KINDS_SHOWN = ("decision", "activation", "generation", "warning", "model_drift", "sensor", "time", "source",
                     "store", "lease", "observer", "probe", "failsafe", "grid switch", "grid decision", "sink")
WARN_KINDS = ("warning", "model_drift", "sensor", "time", "source", "store", "failsafe", "sink", "lease")
DEFAULT_LIMITS = {"keep": 1.5, "forecast": 3.0, "hard": 3.0, "reject": 50.0}


class LiveError(HybridcompError, ValueError):
    """The live view cannot find what to show (no monitor state, several without a choice); the message says which."""


@dataclass(frozen=True)
class LiveSource:
    """Where a daemon's record is: its database, machine and pose, and its sink files.

    Attributes
    ----------
    database : the CD database (SQLite file or SQLAlchemy URL; never shown)
    machine, pose_key : the monitor's machine and pose key (its state is ``monitor:<machine>:<pose_key>``)
    sink_path, sink_kind : the offsets file and its kind (``"jsonl"`` or ``"csv"``), or None
    limits_um : the predicted error's limits ``keep``, ``forecast``, ``hard``, ``reject`` [µm] of the configuration;
        None: the heartbeat's (a daemon that writes them), else the defaults
    threshold_K, model_drift_K : the ΔT test and the model drift limit [K]
    stale_after_s : no offset applied for longer is unhealthy [s]
    """

    database: str
    machine: str
    pose_key: str
    sink_path: Path | None = None
    sink_kind: str | None = None
    limits_um: Mapping[str, float] | None = None
    threshold_K: float | None = None
    model_drift_K: float | None = None
    stale_after_s: float = 20.0


def source_from_config(cfg) -> LiveSource:
    """The record of the daemon a configuration runs (its pose from ``pose_mm`` or the structure model's)."""
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.models import load_machine

    machine = load_machine(cfg.machine)
    if cfg.pose_mm:
        pose = machine.check_pose(dict(cfg.pose_mm))
    else:
        from hybridcomp.rom import load_rom

        pose = machine.check_pose({k: float(v) for k, v in (load_rom(cfg.rom).meta.get("pose_mm") or {}).items()})
    v = cfg.validity
    kind = cfg.sink.kind if cfg.sink.kind in ("jsonl", "csv") else None
    return LiveSource(str(cfg.database), machine.name, pose_key(pose), cfg.sink.path if kind else None, kind,
                      {"keep": v.keep_um, "forecast": v.forecast_um, "hard": v.hard_um, "reject": v.reject_um},
                      cfg.threshold_K, cfg.model_drift_K, cfg.stale_after_s)


def monitor_keys(db) -> list[tuple[str, str]]:
    """(machine, pose key) of every monitor state a database holds."""
    st = db.t["state"]
    with db.engine.connect() as conn:
        keys = [r[0] for r in conn.execute(db.sa.select(st.c.key).where(st.c.key.like("monitor:%")))]
    out = []
    for k in keys:
        rest = k[len("monitor:"):]
        if rest.endswith(":heartbeat") or ":" not in rest:
            continue
        machine, pose = rest.split(":", 1)
        out.append((machine, pose))
    return sorted(out)


def find_database(folder: Path) -> Path:
    """The database of a replay's output folder: ``cd_hybrid.db`` (``monitor scenario``), else its only database."""
    if (folder / "cd_hybrid.db").is_file():
        return folder / "cd_hybrid.db"
    found = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in (".db", ".sqlite", ".sqlite3"))
    if len(found) != 1:
        raise LiveError(f"{folder}: {'no' if not found else len(found)} CD databases (*.db, *.sqlite) in the folder"
                        + ("" if not found else f" ({', '.join(p.name for p in found)})") + "; name one with --database")
    return found[0]


def source_from_database(database: str | Path, pose: str | None = None, offsets: Path | None = None,
                         stale_after_s: float = 20.0) -> LiveSource:
    """The record of the monitor whose state a database holds (``pose``: its pose key, when it holds several).

    ``database`` may be a replay's output folder (:func:`find_database`); ``offsets``: a sink file to read
    (``.jsonl`` or ``.csv``).
    """
    from hybridcomp.chardiag.db import CDDatabase

    path = Path(database) if "://" not in str(database) else None
    if path is not None and path.is_dir():
        database = find_database(path)
    with CDDatabase(database, readonly=True) as db:
        keys = monitor_keys(db)
    if pose is not None:
        keys = [k for k in keys if k[1] == pose]
    if not keys:
        raise LiveError(f"{database}: no monitor state" + (f" of pose {pose}" if pose else "")
                        + " (a daemon that ran on this database writes one at its first monitoring boundary)")
    if len(keys) > 1:
        raise LiveError(f"{database}: monitor states of {len(keys)} poses ({'; '.join(f'{m} {p}' for m, p in keys)}): "
                        "choose one with --pose")
    kind = None
    if offsets is not None:
        kind = {".jsonl": "jsonl", ".csv": "csv"}.get(Path(offsets).suffix)
        if kind is None:
            raise LiveError(f"--offsets {offsets}: a sink file is .jsonl or .csv")
    return LiveSource(str(database), keys[0][0], keys[0][1], Path(offsets) if offsets else None, kind,
                      stale_after_s=stale_after_s)


# ============================================================================================ reading files
class SinkTail:
    """The offsets of a JSON-lines or CSV sink file, read incrementally (whole lines only, from the last read on).

    A file that shrank or was replaced is read again from its start (its last ``TAIL_BYTES`` at most).
    """

    def __init__(self, path: Path | None, kind: str | None, maxlen: int = 40_000):
        self.path, self.kind = path, kind
        self.rows: collections.deque = collections.deque(maxlen=maxlen)  # (time_s, dx, dy, dz, by)
        self._pos = 0
        self._ino = None
        self._header: list[str] | None = None

    def read(self) -> None:
        if self.path is None:
            return
        try:
            st = self.path.stat()
        except OSError:
            return
        if st.st_ino != self._ino or st.st_size < self._pos:
            self.rows.clear()
            self._ino, self._header = st.st_ino, None
            self._pos = 0 if self.kind == "csv" or st.st_size <= TAIL_BYTES else st.st_size - TAIL_BYTES
        if st.st_size == self._pos:
            return
        try:
            with open(self.path, "rb") as fh:
                if self.kind == "csv" and self._header is None:
                    self._header = next(csv.reader([fh.readline().decode("utf-8", "replace")]), [])
                    self._pos = max(self._pos, fh.tell())
                    if st.st_size > TAIL_BYTES + self._pos:
                        self._pos = st.st_size - TAIL_BYTES
                fh.seek(self._pos)
                data = fh.read(st.st_size - self._pos)
        except OSError:
            return
        start_mid_line = self._pos > 0 and self._header is None and self.kind == "jsonl" and not self.rows
        end = data.rfind(b"\n")
        if end < 0:
            return
        chunk = data[:end + 1].decode("utf-8", "replace")
        self._pos += end + 1
        lines = chunk.splitlines()
        if start_mid_line and lines:
            lines = lines[1:]  # (the tail of a large file starts inside a line)
        for line in lines:
            row = self._parse(line)
            if row is not None:
                self.rows.append(row)

    def _parse(self, line: str):
        try:
            if self.kind == "jsonl":
                d = json.loads(line)
            else:
                d = dict(zip(self._header or [], next(csv.reader(io.StringIO(line)))))
            return (float(d["time_s"]), *(float(d[c]) for c in DRIFT_COLUMNS), str(d.get("by", "")))
        except (ValueError, KeyError, TypeError, StopIteration):
            return None


# ============================================================================================ text that leaves
_PATH = re.compile(r"(?<![\w.])(?:[A-Za-z]:)?(?:[\\/][\w.~+-]+){2,}[\\/]?|(?<![\w.])[A-Za-z]:\\[^\s'\"]+")
_URL = re.compile(r"\b[a-z][a-z0-9+.-]*://[^\s'\"]+", re.IGNORECASE)


def scrub(obj):
    """``obj`` with every file path and URL in its strings replaced by ``<path>`` and ``<url>``.

    Nothing of the machine's file system or database credentials leaves the server; non-finite floats become None.
    """
    if isinstance(obj, str):
        return _PATH.sub("<path>", _URL.sub("<url>", obj))
    if isinstance(obj, Mapping):
        return {scrub(str(k)): scrub(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [scrub(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def decimate(rows: Sequence, n_max: int = MAX_POINTS) -> list:
    """At most ``n_max`` of ``rows``, evenly strided, the last one always kept."""
    rows = list(rows)
    if len(rows) <= n_max:
        return rows
    step = math.ceil(len(rows) / n_max)
    out = rows[::step]
    if out[-1] is not rows[-1]:
        out.append(rows[-1])
    return out


def _num(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _hours(t_s) -> float | None:
    v = _num(t_s)
    return None if v is None else round(v / 3600.0, 6)


def event_summary(kind: str, p: Mapping) -> str:
    """One line for an event (no file names: a sink event says what failed, not where)."""
    from hybridcomp.monitor.health import event_summary

    if kind == "activation":
        ids = p.get("ids") or {}
        return f"CD set {', '.join(f'{k} {v}' for k, v in sorted(ids.items()))} activated ({p.get('reason')})"
    if kind == "sink":
        return f"the offsets could not be written ({p.get('status')}: {p.get('error')})"
    if kind == "probe":
        m, e = p.get("measured_um") or {}, p.get("estimate_um") or {}
        return "probed drift " + ", ".join(f"{c[:2]} {_fmt(m.get(c))} (est. {_fmt(e.get(c))})" for c in DRIFT_COLUMNS) \
            + " µm" + (f"; {p['message']}" if p.get("message") else "")
    if kind == "observer":
        return str(p.get("message") or " ".join(str(p.get(k)) for k in ("status", "sensor", "reason") if p.get(k)))
    return event_summary(kind, p)


def _fmt(x) -> str:
    v = _num(x)
    return "–" if v is None else f"{v:.2f}"


# ============================================================================================ the reader
@dataclass
class _Cache:
    events: collections.deque = field(default_factory=lambda: collections.deque(maxlen=5000))
    counts: collections.Counter = field(default_factory=collections.Counter)
    last_event_id: int = 0
    state_updated: str | None = None
    state: dict | None = None
    beats: collections.deque = field(default_factory=lambda: collections.deque(maxlen=20_000))
    beat: dict | None = None


class LiveReader:
    """Reads a daemon's record incrementally and gives the live view's snapshot (thread safe).

    Parameters
    ----------
    source : where the record is
    shift_hours : the curves and events of the last this many hours of machine time [h]
    refresh_s : a snapshot is at most this old [s] (every request within it gets the same one)
    clock : Unix time (tests)
    """

    def __init__(self, source: LiveSource, shift_hours: float = SHIFT_HOURS, refresh_s: float = 1.0, clock=time.time):
        from hybridcomp.chardiag.db import CDDatabase
        from hybridcomp.monitor.daemon import state_key
        from hybridcomp.monitor.store import MonitorStore

        self.source = source
        self.shift_s = float(shift_hours) * 3600.0
        self.refresh_s = float(refresh_s)
        self.clock = clock
        self.db = CDDatabase(source.database, readonly=True)
        self.store = MonitorStore(self.db)
        self.key = state_key(source.machine, source.pose_key)
        self.sink = SinkTail(source.sink_path, source.sink_kind)
        self._c = _Cache()
        self._lock = threading.Lock()
        self._snap: dict | None = None
        self._snap_unix = -math.inf

    def close(self) -> None:
        self.db.close()

    # ------------------------------------------------------------------ reading
    def _read(self) -> None:
        from hybridcomp.monitor.daemon import read_heartbeat_file

        c = self._c
        for e in self.store.events(since_id=c.last_event_id):
            c.last_event_id = e.id
            c.counts[e.kind] += 1
            if e.kind in EVENT_KINDS_SHOWN:
                c.events.append(e)
        st = self.db.t["state"]
        with self.db.engine.connect() as conn:
            rows = {r.key: (r.value, r.updated) for r in conn.execute(
                self.db.sa.select(st.c.key, st.c.value, st.c.updated).where(
                    st.c.key.in_([self.key, self.key + ":heartbeat"])))}
        if self.key in rows and rows[self.key][1] != c.state_updated:
            c.state_updated = rows[self.key][1]
            c.state = json.loads(rows[self.key][0])
        beat = json.loads(rows[self.key + ":heartbeat"][0]) if self.key + ":heartbeat" in rows else None
        local = read_heartbeat_file(self.db.url, self.key)
        if local is not None and (beat is None or float(local.get("unix", 0.0)) > float(beat.get("unix", 0.0))):
            beat = local
        if beat is not None and (c.beat is None or beat.get("unix") != c.beat.get("unix")):
            c.beat = beat
            if beat.get("last_time_s") is not None:
                c.beats.append(beat)
        self.sink.read()

    def snapshot(self) -> dict:
        """The live view's data (JSON-able, scrubbed); read again when the last one is older than ``refresh_s``."""
        with self._lock:
            now = self.clock()
            if self._snap is None or now - self._snap_unix >= self.refresh_s:
                self._read()
                self._snap = scrub(self._build(now))
                self._snap_unix = now
            return self._snap

    def event_counts(self) -> dict[str, int]:
        """Events in the database by kind, since its start (counts of a :meth:`snapshot`'s reading)."""
        with self._lock:
            return dict(self._c.counts)

    # ------------------------------------------------------------------ building the snapshot
    def _build(self, now: float) -> dict:
        from hybridcomp.monitor.health import daemon_alive, health

        c, src = self._c, self.source
        state, beat = c.state or {}, c.beat or {}
        live = beat.get("live") or {}
        sensors = self._sensor_names(state, live)
        latest_t = max([x for x in (beat.get("last_time_s"), state.get("last_time_s"),
                                    self.sink.rows[-1][0] if self.sink.rows else None) if _num(x) is not None],
                       default=None)
        t0 = -math.inf if latest_t is None else latest_t - self.shift_s
        limits = dict(src.limits_um or live.get("limits_um") or DEFAULT_LIMITS)
        threshold_K = src.threshold_K or live.get("threshold_K") or 0.5
        model_drift_K = src.model_drift_K or live.get("model_drift_K") or 1.0

        # health, as `monitor status` judges it
        st = {"running": beat.get("running", True) if beat else None, "daemon_alive": daemon_alive(beat) if beat else None,
              "daemon_pid": beat.get("pid"), "store_backlog": beat.get("store_backlog"),
              "seconds_since_offset": None if beat.get("applied_unix") is None else now - beat["applied_unix"]}
        status, reason = health(st, src.stale_after_s)

        # offsets: the sink file's rows, else the heartbeats seen
        if self.sink.rows:
            off = [r for r in self.sink.rows if r[0] >= t0]
            last_by = self.sink.rows[-1][4]
        else:
            off = [(b["last_time_s"], *((b.get("offsets_um") or {}).get(k) for k in DRIFT_COLUMNS), "")
                   for b in c.beats if b["last_time_s"] >= t0]
            last_by = ""
        off = decimate(off)
        history = [h for h in (state.get("history") or []) if h and h[0] >= t0]
        ns = len(sensors)
        drift = [(h[0], *h[1 + ns:4 + ns]) for h in history if len(h) == 4 + ns]
        measured = [(h[0], *h[1:1 + ns]) for h in history if len(h) == 4 + ns]
        # after the last boundary's history: the heartbeats seen since (a running daemon)
        t_hist = history[-1][0] if history else -math.inf
        for b in c.beats:
            lv = b.get("live") or {}
            if b["last_time_s"] > t_hist and b["last_time_s"] >= t0:
                if lv.get("drift_um"):
                    drift.append((b["last_time_s"], *lv["drift_um"]))
                if lv.get("measured_degC"):
                    measured.append((b["last_time_s"], *(lv["measured_degC"].get(n) for n in sensors)))
        drift, measured = decimate(drift), decimate(measured)

        decisions = [e for e in c.events if e.kind == "decision" and _within(e.machine_time_s, t0)]
        err = [(e.machine_time_s, (e.payload.get("error_um") or {}).get("interval_um"),
                (e.payload.get("error_um") or {}).get("forecast_um")) for e in decisions]
        est = [(e.machine_time_s, *((e.payload.get("T_actual_degC") or {}).get(n) for n in sensors)) for e in decisions
               if e.payload.get("T_actual_degC")]
        est += [(b["last_time_s"], *((b.get("live") or {}).get("estimate_degC", {}).get(n) for n in sensors))
                for b in c.beats if b["last_time_s"] >= t0 and (b.get("live") or {}).get("estimate_degC")]
        est.sort(key=lambda r: r[0])
        residual = self._residuals(history, decisions, sensors, ns)
        residual += [(b["last_time_s"], *(_diff((b["live"].get("measured_degC") or {}).get(n),
                                                b["live"]["estimate_degC"].get(n)) for n in sensors))
                     for b in c.beats if b["last_time_s"] >= t0 and (b.get("live") or {}).get("estimate_degC")]
        residual.sort(key=lambda r: r[0])
        probes = [{"t_h": _hours(e.machine_time_s), "measured_um": e.payload.get("measured_um"),
                   "estimate_um": e.payload.get("estimate_um")}
                  for e in c.events if e.kind == "probe" and _within(e.machine_time_s, t0)]
        marks = [{"t_h": _hours(e.machine_time_s), "label": _mark(e)} for e in c.events
                 if e.kind in ("activation", "failsafe") and e.machine_time_s is not None and e.machine_time_s >= t0]

        said = {(e.machine_time_s, e.payload.get("reason")) for e in decisions}  # a warn decision's warning: once
        shown = [e for e in c.events if (e.machine_time_s is None or e.machine_time_s >= t0)
                 and not (e.kind == "decision" and e.payload.get("action") == "keep")
                 and not (e.kind == "warning" and (e.machine_time_s, e.payload.get("message")) in said)]
        events = [{"t_h": _hours(e.machine_time_s), "created": e.created, "kind": e.kind,
                   "severity": "warn" if e.kind in WARN_KINDS or (e.kind == "decision" and e.payload.get("action")
                                                                  == "warn") else "info",
                   "summary": event_summary(e.kind, e.payload)} for e in shown[-200:]]

        # the latest values (what the page writes beside its curves)
        last_off = beat.get("offsets_um") or state.get("offsets_um") or {}
        last_off_t = beat.get("last_time_s")
        if self.sink.rows and (last_off_t is None or self.sink.rows[-1][0] >= last_off_t):
            r = self.sink.rows[-1]
            last_off, last_off_t = dict(zip(DRIFT_COLUMNS, r[1:4])), r[0]
        last_err = live.get("error_um") or state.get("last_error") or {}
        now_sensors = []
        m_now, e_now = live.get("measured_degC") or {}, live.get("estimate_degC") or {}
        if not m_now and measured:
            m_now = dict(zip(sensors, measured[-1][1:]))
        if not e_now and est:
            e_now = dict(zip(sensors, est[-1][1:]))
        sstates = state.get("sensors") or {}
        degraded = set(beat.get("degraded") or [])
        for n in sensors:
            status_n = "degraded" if n in degraded else (sstates.get(n) or {}).get("status", "ok")
            now_sensors.append({"name": n, "measured_degC": _num(m_now.get(n)), "estimate_degC": _num(e_now.get(n)),
                                "residual_K": _diff(m_now.get(n), e_now.get(n)), "status": status_n})

        active = None
        ids = beat.get("active") or state.get("active_ids")
        if ids:
            lc = self._load_case(ids)
            active = {"ids": ids, "label": ", ".join(f"{k} {v}" for k, v in sorted(ids.items())), "load_case": lc}
        return {
            "version": 1, "now_unix": now, "machine": src.machine, "pose": src.pose_key, "sensors": sensors,
            "health": {"status": status, "reason": reason, "running": st["running"],
                       "seconds_since_offset": st["seconds_since_offset"],
                       "seconds_since_heartbeat": None if not beat else now - float(beat.get("unix", now)),
                       "store_backlog": beat.get("store_backlog"), "regeneration_running": beat.get("regeneration_running"),
                       "degraded": sorted(degraded)},
            "strategy": live.get("strategy"), "observer_flag": live.get("observer_flag", state.get("observer_flag", "")),
            "failsafe": live.get("failsafe", state.get("failsafe", "")), "active": active,
            "limits": {"keep_um": limits.get("keep"), "forecast_um": limits.get("forecast"), "hard_um": limits.get("hard"),
                       "reject_um": limits.get("reject"), "threshold_K": threshold_K, "model_drift_K": model_drift_K},
            "latest": {"t_h": _hours(latest_t), "offsets_t_h": _hours(last_off_t),
                       "offsets_um": {k: _num(last_off.get(k)) for k in DRIFT_COLUMNS}, "by": last_by,
                       "error_um": {"interval_um": _num(last_err.get("interval_um")),
                                    "forecast_um": _num(last_err.get("forecast_um"))},
                       "error_t_h": _hours((state.get("last_decision") or {}).get("time_s")),
                       "delta_T_K": _num(state.get("last_delta_T_K")),
                       "last_decision": state.get("last_decision")},
            "series": {
                "offsets": _columns(off, ["t_h", *DRIFT_COLUMNS]),
                "drift": _columns(drift, ["t_h", *DRIFT_COLUMNS]),
                "error": _columns(err, ["t_h", "interval_um", "forecast_um"]),
                "measured": _columns(measured, ["t_h", *sensors]),
                "estimate": _columns(decimate(est), ["t_h", *sensors]),
                "residual": _columns(decimate(residual), ["t_h", *sensors]),
                "probes": probes, "marks": marks,
            },
            "sensors_now": now_sensors,
            "table": _table(live.get("table") or state.get("table")),
            "events": events,
            "event_counts": dict(c.counts),
        }

    def _sensor_names(self, state: dict, live: dict) -> list[str]:
        names = list((live.get("estimate_degC") or {}) or (state.get("filtered_degC") or {}) or (state.get("sensors") or {}))
        return names

    def _residuals(self, history, decisions, sensors, ns) -> list:
        """Measured − estimate at each decision: the history row at its time (within half a history step)."""
        out = []
        rows = [h for h in history if len(h) == 4 + ns]
        times = [h[0] for h in rows]
        import bisect

        for e in decisions:
            est = e.payload.get("T_actual_degC") or {}
            if not est or not rows:
                continue
            k = bisect.bisect_left(times, e.machine_time_s)
            best = min((j for j in (k - 1, k) if 0 <= j < len(rows)), key=lambda j: abs(times[j] - e.machine_time_s))
            if abs(times[best] - e.machine_time_s) > 150.0:
                continue
            out.append((e.machine_time_s, *(_diff(rows[best][1 + i], est.get(n)) for i, n in enumerate(sensors))))
        return out

    def _load_case(self, ids: Mapping) -> str | None:
        try:
            return self.db.get(int(ids.get("X"))).load_case
        except Exception:  # noqa: BLE001 - a set the database no longer has: no name
            return None


def _within(t_s, t0_s: float) -> bool:
    """Whether a machine time (None: none) is at or after ``t0_s``."""
    return t_s is not None and t_s >= t0_s


def _diff(a, b) -> float | None:
    a, b = _num(a), _num(b)
    return None if a is None or b is None else a - b


def _mark(e) -> str:
    if e.kind == "activation":
        ids = e.payload.get("ids") or {}
        return "set " + ",".join(str(ids[k]) for k in sorted(ids))
    return f"fail-safe {e.payload.get('status', '')}".strip()


def _columns(rows: Sequence, names: Sequence[str]) -> dict:
    """Rows (time [s] first) as columns, the time in hours."""
    cols = {n: [] for n in names}
    for r in rows:
        cols[names[0]].append(_hours(r[0]))
        for n, v in zip(names[1:], r[1:]):
            cols[n].append(_num(v))
    return cols


def _table(d: Mapping | None) -> dict | None:
    """The support-point table for the page: the grid's points with the structure's drift, each drive's largest error."""
    if not d:
        return None
    try:
        import itertools

        import numpy as np

        grid = d["grid"]
        axes = list(grid["axes"])
        pos = [list(p) for p in grid["positions_mm"]]
        S = np.asarray(d["structure_um"], float).reshape(*[len(p) for p in pos], 3)
        points = [[*p, *map(float, S[idx])] for idx, p in zip(itertools.product(*[range(len(p)) for p in pos]),
                                                              itertools.product(*pos))]
        drives = [{"axis": f["axis"], "direction": f.get("direction"),
                   "max_abs_um": float(np.max(np.abs(np.asarray(f["error_um"], float)))) if f["error_um"] else None}
                  for f in d.get("feedback_um") or []]
        return {"axes": axes, "time_h": _hours(d.get("time_s")), "points": points, "drives": drives}
    except (KeyError, TypeError, ValueError):
        return None


__all__ = ["LiveError", "LiveReader", "LiveSource", "SinkTail", "decimate", "find_database", "monitor_keys", "scrub",
           "source_from_config", "source_from_database"]
