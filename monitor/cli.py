"""``hybridcomp monitor``: run the daemon, show its status, write an example configuration.

The ``monitor scenario`` action composes every package and lives at the top level
(:mod:`hybridcomp.cli_monitor_scenario`); the dispatcher adds it to these actions.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

from hybridcomp.models import jsonio
from hybridcomp.monitor.health import daemon_alive as _alive
from hybridcomp.monitor.health import event_summary as _summary
from hybridcomp.monitor.health import health
from hybridcomp.safeio import FORCE_HELP

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """The ``hybridcomp monitor`` actions and their options.

    Returns the actions, for the dispatcher to add ``scenario``, which composes every package
    (:mod:`hybridcomp.cli_monitor_scenario`).
    """
    p.description = (
        "The monitoring daemon: compensation offsets every few seconds from the active characteristic diagrams "
        "(strategy hybrid), the structure model kept on the machine by a Kalman filter on the sensors (strategy "
        "observer) or a data-only model updated by the probes (strategy dataonly, no FE model behind it); every "
        "monitoring interval the active set's predicted compensation error in µm decides: keep, "
        "switch to a stored set, or generate a new one."
    )
    sub = p.add_subparsers(dest="monitor_command", metavar="ACTION", required=True)
    r = sub.add_parser("run", help="run the daemon (stop with SIGTERM or Ctrl-C)",
                       description="Run the monitoring daemon configured by a TOML file. SIGTERM/SIGINT stop it "
                       "cleanly; after a crash or kill it resumes at the last monitoring boundary.")
    r.add_argument("--config", required=True, type=Path, help="monitor TOML file (see 'hybridcomp monitor example-config')")
    r.add_argument("--speed", type=float, default=None, help="override [source] speed of a replay (0: as fast as possible)")
    r.add_argument("--standby", action="store_true", help="when another daemon holds this machine and pose, wait for "
                   "its lease to end and take over from its last state (default: refuse to start)")
    s = sub.add_parser("status", help="print health, the active CDs, last ΔT, last decision, data freshness",
                       description="Print what the daemon of a configuration last did, from its database. Exit code "
                       "0: healthy (an offset was applied within [monitor] stale_after_s); 1: unhealthy (no daemon "
                       "running, or no offset applied for longer, or the database writes back up).")
    s.add_argument("--config", required=True, type=Path, help="monitor TOML file")
    s.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    s.add_argument("--events", type=int, default=5, help="show the last N decisions/switches/generations/warnings")
    e = sub.add_parser("example-config", help="write an annotated example configuration",
                       description="Write an annotated example configuration. It replays jobshop_trace.csv beside "
                       "it (write it with 'hybridcomp monitor example-trace') as fast as the daemon can ([source] "
                       "speed = 0; speed = 1 is real time), with the structure model vmc800.rom.npz and the CD "
                       "database cds.sqlite beside it.")
    e.add_argument("--rom", default="vmc800.rom.npz",
                   help="the structure model the configuration reads (default vmc800.rom.npz); a pose-aware one "
                   "(reduce --poses star) makes the daemon compensate where the tool is, writing a support-point "
                   "table every cycle ([sink] table_path writes them to a file)")
    e.add_argument("--out", type=Path, default=None, help="file to write (default: print)")
    e.add_argument("--force", action="store_true", help=FORCE_HELP)
    t = sub.add_parser("example-trace", help="write the example replay trace: the job-shop day with sensor columns",
                       description="Write a trace CSV for a replay source: the bundled 16 h job-shop day sampled at "
                       "--rate-hz (time_s, axis positions, spindle_rpm, the workshop air Tamb_degC) plus, for every "
                       "sensor, the temperature the structure model --rom computes for the day's own loads: the "
                       "sensors of a machine exactly like its model. The example configuration replays it "
                       "(path = \"jobshop_trace.csv\"). A real machine's data comes from its control (source kind "
                       "opcua); 'monitor scenario' replays a simulated machine that differs from the model.")
    t.add_argument("--rom", type=Path, required=True, metavar="ROM.npz",
                   help="structure model that computes the sensors ('hybridcomp reduce')")
    t.add_argument("--machine", default="vmc800",
                   help="bundled machine name or machine TOML the model was reduced from (default vmc800)")
    t.add_argument("--hours", type=float, default=16.0, help="length of the trace from the start of the day, "
                   "at most 16 [h] (default 16)")
    t.add_argument("--rate-hz", type=float, default=1.0, help="sampling rate of the trace [Hz] (default 1)")
    t.add_argument("--out", type=Path, required=True, help="trace CSV to write")
    t.add_argument("--force", action="store_true", help=FORCE_HELP)
    v = sub.add_parser("serve", help="serve a live web page of the daemon and Prometheus /metrics (read-only)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description=_wrap("Serve the monitor's live view: one web page (no network needed: its plots are drawn "
                       "by the page itself) with the offsets per axis, the active CD set's predicted error and its "
                       "limits, the sensors against the observer's estimate, the probes, the events of the last shift "
                       "and the health, updated every --interval-s; /api/live gives the same as JSON and /metrics the "
                       "figures for Prometheus (extra 'live': pip install 'hybridcomp[live]'; a Grafana dashboard is "
                       "monitor/grafana_dashboard.json). It reads the daemon's record (its CD database, opened "
                       "read-only, its heartbeat and its offsets file) and works for a running daemon, a stopped one "
                       "and a replay ('monitor scenario --out DIR': --database DIR)."),
                       epilog="safety:\n  read-only: GET only; nothing on the page changes the machine or the database\n"
                       "  bound to 127.0.0.1 by default; another --host needs --token (or HYBRIDCOMP_MONITOR_TOKEN),\n"
                       "  then the page is opened as http://HOST:PORT/?token=... and Prometheus sends\n"
                       "  'Authorization: Bearer ...'\n  no file path or database URL is shown\n\nexamples:\n"
                       "  hybridcomp monitor serve --config monitor.toml\n"
                       "  hybridcomp monitor serve --database scenario/ --port 8080\n"
                       "  hybridcomp monitor serve --config monitor.toml --host 0.0.0.0 --token \"$(cat token.txt)\"")
    src = v.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", type=Path, help="monitor TOML file of the daemon (its database, pose, offsets file)")
    src.add_argument("--database", help="CD database (SQLite file or URL) a daemon wrote, or a replay's output "
                     "folder ('monitor scenario --out': its cd_hybrid.db)")
    v.add_argument("--pose", default=None, help="with --database holding several monitors: the pose key "
                   "(e.g. X=0,Y=0,Z=0)")
    v.add_argument("--offsets", type=Path, default=None, help="with --database: the daemon's offsets file "
                   "(sink .jsonl or .csv) to plot every offset written")
    v.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine "
                   "only; any other needs --token)")
    v.add_argument("--port", type=int, default=8765, help="port (default 8765; 0: any free one, printed)")
    v.add_argument("--token", default=None, help="access token (at least 16 characters), required when --host is "
                   "not loopback (default: the environment variable HYBRIDCOMP_MONITOR_TOKEN)")
    v.add_argument("--interval-s", type=float, default=2.0, help="how often the page updates [s] (default 2)")
    v.add_argument("--shift-hours", type=float, default=8.0, help="the curves and events of the last this many "
                   "hours of machine time (default 8)")
    return sub


def _wrap(text: str, width: int = 100) -> str:
    """A paragraph wrapped for a raw-formatted help text."""
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


def run(args: argparse.Namespace) -> int:
    """Run a ``hybridcomp monitor`` action; returns the exit code (2: bad configuration or input, named)."""
    from hybridcomp.errors import HybridcompError
    from hybridcomp.monitor.config import ConfigError

    try:
        if args.monitor_command == "run":
            return _run(args)
        if args.monitor_command == "status":
            return _status(args)
        if args.monitor_command == "example-config":
            from hybridcomp.monitor.config import example_config
            from hybridcomp.safeio import check_output_path, write_text_atomic

            if args.out is None:
                if args.force:
                    raise ValueError("--force applies with --out only")
                print(example_config(args.rom), end="")
            else:
                write_text_atomic(check_output_path(args.out, force=args.force), example_config(args.rom))
            return 0
        if args.monitor_command == "example-trace":
            return _example_trace(args)
        if args.monitor_command == "serve":
            return _serve(args)
    except (ConfigError, ValueError, OSError, HybridcompError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 2


def _serve(args) -> int:
    """``monitor serve``: the live view until Ctrl-C / SIGTERM."""
    import signal
    import threading

    from hybridcomp.monitor.live import LiveReader, source_from_config, source_from_database
    from hybridcomp.monitor.serve import LiveServer, check_binding

    token = args.token or os.environ.get("HYBRIDCOMP_MONITOR_TOKEN") or None
    check_binding(args.host, token)  # before anything is read
    if not (math.isfinite(args.interval_s) and args.interval_s >= 0.2):
        raise ValueError(f"--interval-s {args.interval_s}: at least 0.2 s")
    if not (math.isfinite(args.shift_hours) and args.shift_hours > 0):
        raise ValueError(f"--shift-hours {args.shift_hours}: a positive number of hours")
    if args.config is not None:
        from hybridcomp.monitor.config import load_config

        if args.pose is not None or args.offsets is not None:
            raise ValueError("--pose and --offsets apply with --database (a configuration names both)")
        src = source_from_config(load_config(args.config))
    else:
        src = source_from_database(args.database, args.pose, args.offsets)
    reader = LiveReader(src, args.shift_hours, refresh_s=min(1.0, args.interval_s / 2))
    try:
        server = LiveServer(reader, args.host, args.port, token, args.interval_s)
    except OSError as exc:
        reader.close()
        raise ValueError(f"--host {args.host} --port {args.port}: cannot listen ({exc.strerror or exc})") from None
    signal.signal(signal.SIGTERM, lambda *_: threading.Thread(target=server.shutdown, daemon=True).start())
    print(f"live view of {src.machine} {src.pose_key} on {server.url}" + ("?token=..." if token else "")
          + f" (metrics {server.url}metrics; Ctrl-C stops)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        reader.close()
    return 0


def _example_trace(args) -> int:
    from hybridcomp.models import load_machine
    from hybridcomp.monitor.example import write_example_trace
    from hybridcomp.rom import load_rom
    from hybridcomp.safeio import check_output_path

    out = check_output_path(args.out, inputs=[args.rom], force=args.force)
    machine = load_machine(args.machine)
    rom = load_rom(args.rom, machine)
    if rom.meta.get("poses"):  # the sensors come from the model pose's block
        from hybridcomp.rom.poses import model_pose_block

        rom = model_pose_block(rom)
    write_example_trace(out, machine, rom, hours=args.hours, rate_hz=args.rate_hz)
    print(f"wrote {out}: {args.hours:g} h of the job-shop day at {args.rate_hz:g} Hz, sensors "
          f"{', '.join(rom.layout().sensors)} from {args.rom}")
    return 0


def open_everything(cfg):
    """Machine, structure model, pose key and database of a configuration.

    The sink's files are checked first (:func:`hybridcomp.monitor.sinks.check_sink_paths`): none of them may be
    the configuration, the replay trace, the structure model, the machine file or the database.
    """
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.chardiag.db import CDDatabase, sqlite_file
    from hybridcomp.models import load_machine
    from hybridcomp.monitor.config import ConfigError
    from hybridcomp.monitor.sinks import check_sink_paths
    from hybridcomp.rom import load_rom

    check_sink_paths(cfg)
    db_file = sqlite_file(cfg.database)
    if db_file is not None and not db_file.parent.is_dir():  # a mistyped folder would run a day without any CD
        raise ConfigError(f"{cfg.source_file}: monitor.database {db_file}: the folder {db_file.parent} does not exist "
                          "(the monitor creates no folders)")
    machine = load_machine(cfg.machine)
    rom = load_rom(cfg.rom, machine)  # a pose-aware one: the daemon compensates where the tool is
    if (cfg.sink.table_path is not None and not rom.meta.get("poses") and cfg.grid_rom is None
            and not _has_active_grid(cfg.database, machine.name)):
        raise ConfigError(f"{cfg.source_file}: sink.table_path {cfg.sink.table_path} needs a pose-aware monitor.rom "
                          f"(reduce --poses star) or an active CD grid of {machine.name} in the database (cd fit-grid "
                          f"--activate, or compensation.grid_rom to generate one); {cfg.rom} compensates at one pose "
                          "and writes no tables")
    rom_pose = {k: float(v) for k, v in (rom.meta.get("pose_mm") or {}).items()}
    pose = machine.check_pose(dict(cfg.pose_mm or rom_pose))
    if rom_pose and any(abs(pose[k] - rom_pose.get(k, math.nan)) > 1e-9 for k in pose):
        raise ConfigError(f"{cfg.source_file}: monitor.pose_mm {dict(cfg.pose_mm)} differs from the pose {rom_pose} "
                          f"the structure model {cfg.rom} was reduced at")
    return machine, rom, pose, pose_key(pose), CDDatabase(cfg.database)


def _has_active_grid(database: str, machine: str) -> bool:
    """Whether the database (read only: nothing is created) holds an active CD grid of the machine."""
    from hybridcomp.chardiag.db import CDDatabase, CDDatabaseError

    try:
        with CDDatabase(database, readonly=True) as db:
            return db.active_grid_id(machine) is not None
    except CDDatabaseError:
        return False


def _run(args) -> int:
    import dataclasses

    from hybridcomp.monitor.config import ConfigError, load_config
    from hybridcomp.monitor.daemon import Monitor, install_signal_handlers, run_monitor
    from hybridcomp.monitor.sinks import make_sink
    from hybridcomp.monitor.sources import OpcUaSource, ReplaySource, WallClock

    cfg = load_config(args.config)
    if cfg.prometheus_port:  # refused before anything is opened
        from hybridcomp.monitor.metrics import require_client

        require_client(f"{args.config}: [monitor] prometheus_port = {cfg.prometheus_port}")
    if args.speed is not None and cfg.source.kind != "replay":
        raise ConfigError(f"--speed applies to a replay source only; {args.config} reads source.kind = "
                          f"{cfg.source.kind!r}")
    if args.speed is not None:
        cfg = dataclasses.replace(cfg, source=dataclasses.replace(cfg.source, speed=args.speed))
    machine, rom, _pose, pkey, db = open_everything(cfg)
    clock = WallClock()
    if cfg.source.kind == "replay":
        source = ReplaySource(cfg.source.path, machine, cfg.source.speed, clock, cfg.source.start_s)
    else:
        source = OpcUaSource(cfg.source.url, cfg.source.nodes, machine, cfg.source.publishing_interval_ms,
                             cfg.source.stale_s)
    sink = make_sink(cfg.sink, cfg.reconnect, clock)
    monitor = Monitor(cfg, machine, rom, db, pkey, clock)

    async def main():
        stop = asyncio.Event()
        install_signal_handlers(stop)
        server = None
        if cfg.prometheus_port:
            from hybridcomp.monitor.metrics import serve_metrics

            server = await serve_metrics(monitor, cfg.prometheus_port)
        try:
            return await run_monitor(cfg, monitor, source, sink, clock=clock, stop=stop, standby=args.standby)
        finally:
            if server is not None:
                server.close()
                await server.wait_closed()

    t0 = time.monotonic()
    res = asyncio.run(main())
    st = res.status
    log.info("stopped (%s) after %.1f s", res.stopped_by, time.monotonic() - t0)
    print(f"monitor stopped ({res.stopped_by}): machine time {st['last_time_s']} s, {st['readings']} readings, "
          f"{st['compensations']} compensation cycles, {st['monitorings']} monitoring cycles, "
          f"{st['switches']} switches, {st['generations']} generations, slowest decision {st['max_decision_s'] * 1e3:.1f} ms")
    db.close()
    return 0


def status_dict(cfg, db, machine_name: str, pkey: str, n_events: int = 5) -> dict:
    """What ``monitor status`` shows, as a dict."""
    from hybridcomp.monitor.daemon import read_heartbeat_file, state_key
    from hybridcomp.monitor.store import MonitorStore

    store = MonitorStore(db)
    key = state_key(machine_name, pkey)
    state = json.loads(store.get_state(key) or "null")
    beat = json.loads(store.get_state(key + ":heartbeat") or "null")
    # this host's copy is newer while the database holds the daemon's writes back (a lock): take the newer
    local = read_heartbeat_file(getattr(db, "url", ""), key) if getattr(db, "url", None) else None
    if local is not None and (beat is None or float(local.get("unix", 0.0)) > float(beat.get("unix", 0.0))):
        beat = local
    active = db.active_set(machine_name, pkey)
    now = time.time()
    ev = [e for e in store.events() if e.kind in ("decision", "activation", "generation", "warning", "model_drift", "sensor",
                                                  "time", "source", "store", "lease")]
    out = {
        "machine": machine_name, "pose": pkey,
        "active": None if active is None else {"ids": dict(active.ids), "load_case": active.cds["X"].load_case,
                                                "t_reference_degC": active.t_reference_degC},
        "last_delta_T_K": None if state is None else state.get("last_delta_T_K"),
        "last_decision": None if state is None else state.get("last_decision"),
        "last_machine_time_s": max([x["last_time_s"] for x in (beat, state) if x and x.get("last_time_s") is not None],
                                   default=None),
        "seconds_since_data": None if beat is None else now - beat["unix"],
        "seconds_since_offset": None if beat is None or beat.get("applied_unix") is None else now - beat["applied_unix"],
        "running": None if beat is None else beat.get("running", True),
        "daemon_alive": None if beat is None else _alive(beat),
        "daemon_pid": None if beat is None else beat.get("pid"),
        "store_backlog": None if beat is None else beat.get("store_backlog"),
        "seconds_since_boundary": None if state is None else now - state["updated_unix"],
        "degraded_sensors": None if beat is None else beat.get("degraded"),
        "regeneration_running": None if beat is None else beat.get("regeneration_running"),
        "pending_generation": None if state is None or not state.get("pending") else state["pending"]["machine_time_s"],
        "recent_events": [{"kind": e.kind, "machine_time_s": e.machine_time_s, "created": e.created,
                           "summary": _summary(e.kind, e.payload)} for e in ev[-n_events:]],
    }
    out["health"], out["health_reason"] = health(out, cfg.stale_after_s)
    return out


def _status(args) -> int:
    from hybridcomp.chardiag.cd import pose_key
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.models import load_machine
    from hybridcomp.monitor.config import load_config
    from hybridcomp.rom import load_rom

    cfg = load_config(args.config)
    machine = load_machine(cfg.machine)
    if cfg.pose_mm:
        pose = machine.check_pose(dict(cfg.pose_mm))
    else:
        pose = machine.check_pose({k: float(v) for k, v in (load_rom(cfg.rom).meta.get("pose_mm") or {}).items()})
    db = CDDatabase(cfg.database, readonly=True)
    try:
        st = status_dict(cfg, db, machine.name, pose_key(pose), args.events)
    finally:
        db.close()
    rc = 0 if st["health"] == "healthy" else 1
    if args.json:
        print(jsonio.dumps(st))
        return rc
    a = st["active"]
    print(f"machine {st['machine']}, pose {st['pose']}")
    print(f"health: {st['health']} ({st['health_reason']})")
    print("active CDs: " + ("none" if a is None else f"{a['ids']} (load case {a['load_case']})"))
    print(f"last ΔT: {_fmt(st['last_delta_T_K'], 'K')}")
    d = st["last_decision"]
    print("last decision: " + ("none" if d is None else f"{d['action']} at {d['time_s']:.0f} s: {d['reason']}"))
    print(f"data: machine time {_fmt(st['last_machine_time_s'], 's')}, last sample {_fmt(st['seconds_since_data'], 's')} ago, "
          f"last monitoring boundary saved {_fmt(st['seconds_since_boundary'], 's')} ago")
    if st["degraded_sensors"]:
        print(f"degraded sensors: {', '.join(st['degraded_sensors'])}")
    if st["pending_generation"] is not None:
        print(f"generation pending for the decision at {st['pending_generation']:.0f} s")
    for e in st["recent_events"]:
        print(f"  {e['created']}  t={_fmt(e['machine_time_s'], 's')}  {e['kind']}: {e['summary']}")
    return rc


def _fmt(v, unit) -> str:
    return "unknown" if v is None else f"{v:.3f} {unit}" if unit == "K" else f"{v:.1f} {unit}"
