"""The monitoring daemon: a thin stateful shell around the pure decisions.

:class:`Monitor` holds what has to be remembered between samples (the
structure model's state, sensor states, the histogram buffer of the current
monitoring interval, the last offsets) and turns each :class:`Reading` into
compensation offsets and, at each monitoring boundary, one decision.
Everything it decides is decided by :mod:`hybridcomp.monitor.decisions`.
:func:`run_monitor` is the asyncio loop around it: data source with reconnect,
sink, background regeneration in a worker process, clean stop.

Machine time drives both loops (compensation every ``compensation_interval_s``,
monitoring every ``monitoring_interval_s`` of machine time), so a replay at
1000× makes the same decisions as the machine in real time.

Persistence and restarts: at every monitoring boundary the whole state is
written as one JSON value (``MonitorStore.put_state``), and every event carries a
key made of its kind, the pose and its machine time, so a daemon killed at
any moment and restarted re-processes the samples after the last boundary,
makes the same decisions again and writes no event twice.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import importlib
import json
import logging
import math
import multiprocessing
import random
import signal
import time
import warnings
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from hybridcomp.histogram.bcs import boundary_conditions
from hybridcomp.histogram.increments import increments_from_samples
from hybridcomp.histogram.signature import SignatureLayout, signatures
from hybridcomp.histogram.trace import Samples, TraceFileError
from hybridcomp.models import jsonio
from hybridcomp.monitor.config import MonitorConfig
from hybridcomp.monitor.decisions import (
    Candidate,
    Decision,
    SensorState,
    accept_time,
    backoff_delay,
    blend_offsets,
    check_sensor,
    decide,
    limit_offsets,
    model_drift,
    substitute,
    temperature_deviation,
)
from hybridcomp.monitor.regeneration import RegenerationRequest
from hybridcomp.monitor.sinks import Offset
from hybridcomp.models.layout import DIRECTIONS
from hybridcomp.rom.machine import inputs_from_columns
from hybridcomp.monitor.sources import Reading, SourceDisconnected, WallClock
from hybridcomp.monitor.store import MonitorStore

log = logging.getLogger(__name__)

STATE_VERSION = 1
AXIS_INPUTS = DIRECTIONS  # CD inputs that are axis positions


def state_key(machine: str, pose_key: str) -> str:
    """Key of the monitor's state in the database."""
    return f"monitor:{machine}:{pose_key}"


def _t(x: float) -> str:
    return f"{x:.3f}"


def _finite(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


@dataclass
class Counters:
    """What the daemon counts (status, metrics)."""

    readings: int = 0
    compensations: int = 0
    monitorings: int = 0
    dropped_repeated: int = 0
    dropped_backwards: int = 0
    dropped_invalid: int = 0
    switches: int = 0
    generations: int = 0
    reconnects: int = 0
    max_decision_s: float = 0.0
    last_decision_s: float = 0.0


class Monitor:
    """The daemon's state and its reaction to one reading (no I/O but the database).

    Parameters
    ----------
    cfg : configuration
    machine : the machine (axes, sensors, zones)
    rom : reduced structure model of the machine at the CDs' pose
    db : CD database (``hybridcomp.chardiag.db.CDDatabase`` or anything with its methods)
    pose_key : the pose's database key
    clock : gives Unix time for freshness (default :class:`WallClock`)
    """

    def __init__(self, cfg: MonitorConfig, machine, rom, db, pose_key: str, clock=None):
        self.cfg = cfg
        self.machine = machine
        self.rom = rom
        self.db = db
        self.store = MonitorStore(db)
        self.pose_key = pose_key
        self.clock = clock or WallClock()
        self.key = state_key(machine.name, pose_key)
        self.sensor_names = tuple(s.name for s in machine.sensors)
        self.axis_names = tuple(a.name for a in machine.axes)
        self.counters = Counters()
        self.layout = SignatureLayout.of(machine)
        self.t_ref = rom.layout().reference_temperature_degC
        n_inc = int(round(cfg.monitoring_interval_s / cfg.increment_s))
        self.history_rows = max(1, int(math.ceil(cfg.regeneration.history_s / cfg.increment_s)))
        self._n_inc = n_inc
        # --- the state (everything below is persisted at each monitoring boundary)
        self.origin_s: float | None = None
        self.last_time_s: float | None = None
        self.next_comp_s = -math.inf
        self.next_mon_s = -math.inf
        self.x: np.ndarray | None = None  # reduced state at rom_time_s
        self.rom_time_s: float | None = None
        self.rom_sensors_degC: dict[str, float] = {}
        self.bias_K: dict[str, float] = {}
        self.sensors: dict[str, SensorState] = {s: SensorState() for s in self.sensor_names}
        self.offsets_um = {"dx_um": 0.0, "dy_um": 0.0, "dz_um": 0.0}
        self.blend_um = {"dx_um": 0.0, "dy_um": 0.0, "dz_um": 0.0}
        self.blend_time_s: float | None = None
        self.blend_pending = False  # the active set changed: the next cycle starts a bumpless transfer
        self.carry: Reading | None = None  # last sample of the previous interval
        self.air_hold: dict[str, float] = {}
        self.pos_hold: list[float] = [a.mid_mm for a in machine.axes]
        self.spindle_hold = 0.0
        self.history: deque = deque(maxlen=self.history_rows)  # (time_s, loads row) of past increments
        self.loads_names: tuple[str, ...] | None = None
        self.pending: dict | None = None  # a regeneration request not yet finished
        self.regen_blocked_until_s = -math.inf
        self.last_decision: dict | None = None
        self.last_delta_T_K: float | None = None
        self.interval_drops = {"repeated": 0, "backwards": 0, "invalid": 0}
        # --- not persisted
        self.buffer: list[Reading] = []
        self.active = None
        self.active_ids: dict[str, int] | None = None
        self.regeneration_running = False
        self._outbox: list[dict] = []  # regeneration requests for the shell
        self._eval_failed_logged = False
        self._snap: dict | None = None
        self.restore()
        self.reload_active()

    # ------------------------------------------------------------------ persistence
    def snapshot(self) -> dict:
        """The persisted state (JSON-able)."""
        c = self.carry
        return {
            "version": STATE_VERSION,
            "machine": self.machine.name,
            "pose_key": self.pose_key,
            "rom_id": self.rom.rom_id,
            "origin_s": self.origin_s,
            "last_time_s": self.last_time_s,
            "next_comp_s": _finite(self.next_comp_s),
            "next_mon_s": _finite(self.next_mon_s),
            "x": None if self.x is None else self.x.tolist(),
            "rom_time_s": self.rom_time_s,
            "rom_sensors_degC": self.rom_sensors_degC,
            "bias_K": self.bias_K,
            "sensors": {k: v.to_dict() for k, v in self.sensors.items()},
            "offsets_um": self.offsets_um,
            "blend_um": self.blend_um,
            "blend_time_s": self.blend_time_s,
            "blend_pending": self.blend_pending,
            "carry": None if c is None else [c.time_s, list(c.position_mm), c.spindle_rpm, dict(c.sensors_degC), dict(c.air_degC)],
            "air_hold": self.air_hold,
            "pos_hold": self.pos_hold,
            "spindle_hold": self.spindle_hold,
            "history": [[t, list(u)] for t, u in self.history],
            "loads_names": None if self.loads_names is None else list(self.loads_names),
            "pending": self.pending,
            "regen_blocked_until_s": _finite(self.regen_blocked_until_s),
            "last_decision": self.last_decision,
            "last_delta_T_K": self.last_delta_T_K,
            "active_ids": self.active_ids,
            "updated_unix": self.clock.unix(),
        }

    def persist(self) -> None:
        """Write the state of the last monitoring boundary (with the current regeneration bookkeeping).

        Only boundary states are written: a restart re-processes the samples
        after the boundary, so the histogram of the interval is complete.
        """
        if self._snap is not None:
            snap = self._snap
        else:  # before the first boundary: a restart starts from the beginning (events are keyed, nothing doubles)
            snap = {**self.snapshot(), "origin_s": None, "last_time_s": None, "next_comp_s": None, "next_mon_s": None,
                    "x": None, "rom_time_s": None, "carry": None, "history": [],
                    "sensors": {k: SensorState().to_dict() for k in self.sensor_names},
                    "offsets_um": {"dx_um": 0.0, "dy_um": 0.0, "dz_um": 0.0}}
        snap = {**snap, "pending": self.pending, "regen_blocked_until_s": _finite(self.regen_blocked_until_s),
                "updated_unix": self.clock.unix()}
        self.store.put_state(self.key, jsonio.dumps(snap))

    def restore(self) -> None:
        text = self.store.get_state(self.key)
        if not text:
            return
        s = json.loads(text)
        if s.get("version") != STATE_VERSION:
            log.warning("state %s has version %r; starting fresh", self.key, s.get("version"))
            return
        self.origin_s = s["origin_s"]
        self.last_time_s = s["last_time_s"]
        self.next_comp_s = s["next_comp_s"] if s["next_comp_s"] is not None else -math.inf
        self.next_mon_s = s["next_mon_s"] if s["next_mon_s"] is not None else -math.inf
        if s.get("x") is not None and s.get("rom_id") == self.rom.rom_id:
            self.x = np.asarray(s["x"], float)
            self.rom_time_s = s["rom_time_s"]
        elif s.get("x") is not None:
            log.warning("state %s belongs to reduced model %s, not %s: the structure model restarts from steady state",
                        self.key, s.get("rom_id"), self.rom.rom_id)
        self.rom_sensors_degC = {k: (math.nan if v is None else v) for k, v in s["rom_sensors_degC"].items()}
        self.bias_K = {k: (math.nan if v is None else v) for k, v in s["bias_K"].items()}
        self.sensors = {k: SensorState.from_dict(v) for k, v in s["sensors"].items()}
        self.offsets_um = s["offsets_um"]
        self.blend_um = s.get("blend_um") or dict.fromkeys(self.offsets_um, 0.0)
        self.blend_time_s = s.get("blend_time_s")
        self.blend_pending = bool(s.get("blend_pending"))
        if s["carry"] is not None:
            t, p, r, sn, air = s["carry"]
            self.carry = Reading(t, tuple(p), r, {k: (math.nan if v is None else v) for k, v in sn.items()}, air)
        self.air_hold = s["air_hold"]
        self.pos_hold = s["pos_hold"]
        self.spindle_hold = s["spindle_hold"]
        self.history = deque([(t, np.asarray(u, float)) for t, u in s["history"]], maxlen=self.history_rows)
        self.loads_names = tuple(s["loads_names"]) if s["loads_names"] else None
        self.pending = s["pending"]
        self.regen_blocked_until_s = s["regen_blocked_until_s"] if s["regen_blocked_until_s"] is not None else -math.inf
        self.last_decision = s["last_decision"]
        self.last_delta_T_K = s["last_delta_T_K"]
        self._snap = s
        if self.carry is not None:
            self.buffer = [self.carry]
        if self.pending is not None:
            self._outbox.append(self.pending)  # resubmit a generation the last run did not finish
        log.info("resumed %s at machine time %s s", self.key, self.last_time_s)

    def reload_active(self) -> None:
        self.active = self.db.active_set(self.machine.name, self.pose_key)
        self.active_ids = {k: int(v) for k, v in self.active.ids.items()} if self.active is not None else None
        self._eval_failed_logged = False

    def event(self, kind: str, t: float | None, payload: dict, key: str) -> None:
        self.store.log_event(kind, t, payload, key=f"{kind}@{self.pose_key}@{key}")

    # ------------------------------------------------------------------ one reading
    def process(self, r: Reading) -> list[Offset]:
        """Handle one reading; returns the offsets of the compensation cycles it completes (0 or 1)."""
        verdict = accept_time(self.last_time_s, r.time_s)
        if verdict != "ok":
            self.interval_drops[verdict] += 1
            setattr(self.counters, f"dropped_{verdict}", getattr(self.counters, f"dropped_{verdict}") + 1)
            return []
        self.counters.readings += 1
        r = self._clean(r)
        if self.origin_s is None:
            self.origin_s = r.time_s
            self.next_comp_s = r.time_s
            self.next_mon_s = r.time_s + self.cfg.monitoring_interval_s
            self.buffer = []
        # monitoring boundary: samples up to the boundary belong to the closing interval
        if r.time_s > self.next_mon_s:
            self._close_interval(r.time_s)
        self.buffer.append(r)
        self.last_time_s = r.time_s
        temps = self._check_sensors(r)
        out = []
        if r.time_s >= self.next_comp_s:
            out.append(self._compensate(r, temps))
            k = math.floor((r.time_s - self.origin_s) / self.cfg.compensation_interval_s) + 1
            self.next_comp_s = self.origin_s + k * self.cfg.compensation_interval_s
        if r.time_s == self.next_mon_s:  # r is the last sample of the interval
            self._close_interval(r.time_s)
        return out

    def _clean(self, r: Reading) -> Reading:
        """Hold positions, spindle speed and air at their last finite values (NaN from a glitching bus)."""
        pos = list(r.position_mm)
        for j, v in enumerate(pos):
            if math.isfinite(v):
                self.pos_hold[j] = v
            else:
                pos[j] = self.pos_hold[j]
        sp = r.spindle_rpm
        if math.isfinite(sp):
            self.spindle_hold = sp
        else:
            sp = self.spindle_hold
        air = dict(r.air_degC)
        for k, v in air.items():
            if v is not None and math.isfinite(v):
                self.air_hold[k] = v
            else:
                air[k] = self.air_hold.get(k, self.t_ref)
        return Reading(r.time_s, tuple(pos), sp, r.sensors_degC, air)

    def _check_sensors(self, r: Reading) -> dict[str, float]:
        temps = {}
        for name in self.sensor_names:
            raw = r.sensors_degC.get(name)
            if raw is None:
                continue
            st = self.sensors[name]
            ref = substitute(self.rom_sensors_degC.get(name, math.nan), self.bias_K.get(name, math.nan))
            v = check_sensor(st, r.time_s, float(raw), self.cfg.sensors, ref)
            self.sensors[name] = v.state
            if v.event is not None:
                self.event("sensor", r.time_s, {
                    "sensor": name, "status": v.event, "reason": v.state.reason, "raw_degC": _finite(raw),
                    "held_degC": _finite(v.state.value_degC), "substitute_degC": _finite(ref),
                    "message": _sensor_message(name, v.event, v.state.reason, self.cfg.sensors),
                }, f"{name}@{v.event}@{_t(r.time_s)}")
                (log.warning if v.event == "degraded" else log.info)(
                    "sensor %s %s at %.0f s (%s)", name, v.event, r.time_s, v.state.reason)
            temps[name] = v.value_degC if math.isfinite(v.value_degC) else ref
        return temps

    # ------------------------------------------------------------------ compensation
    def _compensate(self, r: Reading, temps: Mapping[str, float]) -> Offset:
        self.counters.compensations += 1
        degraded = ",".join(n for n in self.sensor_names if self.sensors[n].status == "degraded")
        values = dict(temps)
        for name, p in zip(self.axis_names, r.position_mm):
            values[name] = p
        target = None
        outside = False
        if self.active is not None:
            try:
                target, outside = self.active.evaluate_point(values)
                if not all(math.isfinite(v) for v in target.values()):
                    raise ValueError(f"non-finite offsets {target}")
            except (KeyError, ValueError) as exc:
                target = None
                if not self._eval_failed_logged:
                    self._eval_failed_logged = True
                    self.event("warning", r.time_s, {"message": f"the active CDs cannot be evaluated ({exc}); offsets held",
                                                     "values": {k: _finite(v) for k, v in values.items()}},
                               f"evaluate@{_t(r.time_s)}")
        if target is None:
            target = dict(self.offsets_um)  # hold (zero before the first CD)
        else:
            self._eval_failed_logged = False
            target = {k: float(v) for k, v in target.items()}
            if self.blend_pending:  # bumpless transfer: continue from the offsets written last
                self.blend_um = {k: self.offsets_um.get(k, 0.0) - v for k, v in target.items()}
                self.blend_time_s = r.time_s
                self.blend_pending = False
            dt = 0.0 if self.blend_time_s is None else r.time_s - self.blend_time_s
            target, self.blend_um = blend_offsets(target, self.blend_um, dt, self.cfg.blend_s)
            self.blend_time_s = r.time_s
        applied, clamped, limited = limit_offsets(target, self.offsets_um, self.cfg.max_offset_um, self.cfg.max_step_um)
        self.offsets_um = applied
        ids = self.active_ids or {}
        return Offset(r.time_s, applied["dx_um"], applied["dy_um"], applied["dz_um"],
                      ",".join(f"{k}={ids[k]}" for k in sorted(ids)), clamped, limited, bool(outside), degraded)

    # ------------------------------------------------------------------ monitoring
    def _samples(self) -> Samples | None:
        b = self.buffer
        if len(b) < 2:
            return None
        air_names = tuple(sorted(b[-1].air_degC))
        t = np.fromiter((x.time_s for x in b), float, len(b))
        P = np.array([x.position_mm for x in b], float)
        S = np.fromiter((x.spindle_rpm for x in b), float, len(b))
        A = np.array([[x.air_degC.get(k, self.t_ref) for k in air_names] for x in b], float).reshape(len(b), len(air_names))
        return Samples(t, P, None, S, air_names, A, np.arange(len(b)) + 2)

    def _close_interval(self, now_s: float) -> None:
        """Monitoring cycle over the buffered interval, then persist and start the next interval."""
        t0 = time.perf_counter()
        boundary = self.next_mon_s
        s = self._samples()
        if s is not None:
            self._monitor(s, boundary)
        else:
            self.event("warning", boundary, {"message": "no samples in the monitoring interval: structure model not advanced"},
                       f"empty@{_t(boundary)}")
        if any(self.interval_drops.values()):
            self.event("time", boundary, {"message": "samples dropped for repeated, backward or invalid time stamps",
                                          **self.interval_drops}, _t(boundary))
            self.interval_drops = {"repeated": 0, "backwards": 0, "invalid": 0}
        # next interval: the last sample carries over (continuity of the histogram)
        self.carry = self.buffer[-1] if self.buffer else self.carry
        self.buffer = [self.carry] if self.carry is not None else []
        k = math.floor((now_s - self.origin_s) / self.cfg.monitoring_interval_s) + 1
        if self.origin_s + k * self.cfg.monitoring_interval_s <= now_s:
            k += 1
        if now_s == self.next_mon_s:
            k = round((now_s - self.origin_s) / self.cfg.monitoring_interval_s) + 1
        self.next_mon_s = self.origin_s + k * self.cfg.monitoring_interval_s
        self.counters.monitorings += 1
        dt = time.perf_counter() - t0
        self.counters.last_decision_s = dt
        self.counters.max_decision_s = max(self.counters.max_decision_s, dt)
        self._snap = self.snapshot()
        self.persist()

    def _monitor(self, s: Samples, boundary: float) -> None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                inc = increments_from_samples(self.machine, s, min(self.cfg.increment_s, max(s.time_s[-1] - s.time_s[0], 1e-6)),
                                              max_gap_s=self.cfg.max_gap_s, source=f"monitor interval ending {boundary:g} s")
                loads = boundary_conditions(self.machine, inc)
                error = None
            except (TraceFileError, ValueError) as exc:
                inc, loads, error = None, None, exc
        for w in caught:
            self.event("warning", boundary, {"message": str(w.message)}, f"histogram@{_t(boundary)}@{hash(str(w.message)) & 0xffff}")
        if error is not None:
            # an implausible interval (a glitch faster than the axes can move): hold the last loads
            self.event("warning", boundary, {"message": f"histogram of the interval failed: {error}; last loads held"},
                       f"histogram-error@{_t(boundary)}")
            if self.x is None or not self.history:
                return
            u = self.history[-1][1]
            U = np.tile(u, (2, 1))
            dts = [s.time_s[-1] - (self.rom_time_s or s.time_s[0])]
            times = [s.time_s[-1]]
            sig = None
        else:
            U_all = inputs_from_columns(self.rom, loads.names, loads.values, "monitor")
            self.loads_names = self.rom.input_names
            if self.x is None:
                self.x = self.rom.steady_state(U_all[0])  # a machine that stood still in the first sample's air
                self.rom_time_s = float(loads.time_s[0])
            U = U_all
            times = list(loads.time_s[1:])
            dts = list(np.diff(loads.time_s))
            _, _, sig_rows = signatures(inc)
            w = inc.duration_s
            sig = (sig_rows * w[:, None]).sum(axis=0) / w.sum()
        # each increment's loads row held over it (mean power); empty increments are skipped
        grid = np.concatenate([[times[0] - dts[0]], times])
        keep = np.concatenate([[True], np.asarray(dts) > 0])
        if keep[1:].any():
            _, self.x = self.rom.integrate(grid[keep], U[:grid.size][keep], initial=self.x, hold="step")
        self.history.extend((float(tk), U[k + 1].copy()) for k, tk in enumerate(times))
        self.rom_time_s = float(times[-1])
        y = self.rom.outputs(self.x)
        n_s = len(self.rom.output_names) - 3
        actual = {name: float(y[j]) + self.t_ref for j, name in enumerate(self.rom.output_names[:n_s])}
        self.rom_sensors_degC = actual

        # the structure model against the measured sensors (the input for the diagnosis)
        measured = {n: self.sensors[n].value_degC for n in self.sensor_names if self.sensors[n].status == "ok"}
        drifted, drift_K, drift_sensor = model_drift(actual, measured, self.cfg.model_drift_K)
        for n, v in measured.items():
            if n in actual and math.isfinite(v):
                self.bias_K[n] = v - actual[n]
        if drifted:
            self.event("model_drift", boundary, {
                "max_abs_K": drift_K, "sensor": drift_sensor, "threshold_K": self.cfg.model_drift_K,
                "model_degC": actual, "measured_degC": measured,
            }, _t(boundary))

        # does the active CD set still fit?
        t_ref = self.active.t_reference_degC if self.active is not None else {}
        dT, sensor = temperature_deviation(actual, t_ref) if self.active is not None else (math.inf, None)
        candidates = []
        if self.active is None or dT > self.cfg.threshold_K:
            for m in self.db.search(self.machine.name, self.pose_key, None if sig is None else np.asarray(sig), actual,
                                    self.cfg.threshold_K, layout=self.layout):
                candidates.append(Candidate({k: int(v) for k, v in m.ids.items()}, m.load_case, float(m.delta_T_K),
                                            float(m.distance) if m.distance is not None else math.nan))
        enabled = self.cfg.regeneration.enabled and boundary >= self.regen_blocked_until_s
        d = decide(dT, sensor, self.cfg.threshold_K, self.active_ids, candidates, enabled,
                   self.regeneration_running or self.pending is not None)
        payload = {
            "action": d.action, "reason": d.reason, "delta_T_K": _finite(d.delta_T_K), "sensor": d.sensor,
            "threshold_K": self.cfg.threshold_K, "active": self.active_ids,
            "target": None if d.target is None else {"ids": dict(d.target.ids), "load_case": d.target.load_case,
                                                     "delta_T_K": d.target.delta_T_K},
            "candidates": len(candidates), "T_actual_degC": actual, "T_reference_degC": t_ref,
            "model_drift_K": _finite(drift_K), "signature": None if sig is None else [round(float(v), 6) for v in sig],
        }
        self.event("decision", boundary, payload, _t(boundary))
        self.last_decision = {"time_s": boundary, "action": d.action, "reason": d.reason}
        self.last_delta_T_K = _finite(d.delta_T_K)
        log.info("t = %.0f s: %s (%s)", boundary, d.action, d.reason)
        self._act(d, boundary, actual, sig)

    def _act(self, d: Decision, t: float, actual: Mapping[str, float], sig) -> None:
        if d.action == "switch":
            self.activate(d.target.ids, f"switch: {d.reason}", t)
        elif d.action == "regenerate":
            self.pending = self._request(t, actual, sig)
            self._outbox.append(self.pending)
            self.event("generation", t, {"status": "started", "request": _brief(self.pending)}, f"{_t(t)}@started")
        elif d.action == "warn":
            self.event("warning", t, {"message": d.reason, "delta_T_K": _finite(d.delta_T_K)}, f"decision@{_t(t)}")

    def activate(self, ids: Mapping[str, int], reason: str, t: float) -> None:
        """Make a set active (idempotent: nothing happens when it already is)."""
        ids = {k: int(v) for k, v in ids.items()}
        if self.active_ids == ids:
            return
        self.db.activate(self.machine.name, self.pose_key, ids, reason=reason, machine_time_s=t,
                         event_key=f"activation@{self.pose_key}@{_t(t)}@{ids['X']},{ids['Y']},{ids['Z']}")
        self.counters.switches += 1
        had_set = self.active is not None
        self.reload_active()
        self.blend_pending = had_set and self.cfg.blend_s > 0

    def _request(self, t: float, actual: Mapping[str, float], sig) -> dict:
        return RegenerationRequest(
            machine=self.cfg.machine, pose_key=self.pose_key, pose_mm=dict(self.rom.meta.get("pose_mm") or {}),
            database=self.cfg.database, machine_time_s=t, t_reference_degC=dict(actual),
            signature=None if sig is None else [float(v) for v in sig],
            loads_names=list(self.loads_names or self.rom.input_names),
            loads_time_s=[h[0] for h in self.history], loads_inputs=[list(map(float, h[1])) for h in self.history],
            reference_temperature_degC=self.t_ref, element_size_mm=self.cfg.regeneration.element_size_mm,
            initial_x=None,
        ).to_dict()

    # ------------------------------------------------------------------ regeneration results
    def take_requests(self) -> list[dict]:
        out, self._outbox = self._outbox, []
        return out

    def regeneration_finished(self, request: dict, result: Mapping | None, error: str | None, status: str) -> None:
        """Record the outcome of a generation job; activate its set when it succeeded."""
        t = float(request["machine_time_s"])
        if status == "finished" and result is not None:
            ids = {k: int(v) for k, v in result["ids"].items()}
            self.event("generation", t, {"status": "finished", "ids": ids, "load_case": result.get("load_case", ""),
                                         "wall_s": result.get("wall_s"), "notes": result.get("notes") or {}},
                       f"{_t(t)}@finished")
            self.counters.generations += 1
            try:
                self.activate(ids, f"generated for the load case at {t:.0f} s", self.last_time_s)
            except Exception as exc:  # noqa: BLE001 - a broken result must not stop the daemon
                self.event("generation", t, {"status": "activation_failed", "ids": ids, "error": f"{type(exc).__name__}: {exc}"},
                           f"{_t(t)}@activation_failed")
                log.error("generated set %s for %.0f s cannot be activated: %s", ids, t, exc)
        else:
            self.event("generation", t, {"status": status, "error": error}, f"{_t(t)}@{status}")
            # do not start another job for a while
            self.regen_blocked_until_s = (self.last_time_s or t) + self.cfg.regeneration.retry_after_s
            log.warning("generation job for %.0f s %s: %s", t, status, error)
        self.pending = None
        self.persist()

    def status(self) -> dict:
        """Numbers for the status command and the metrics endpoint."""
        return {
            "machine": self.machine.name, "pose_key": self.pose_key, "active": self.active_ids,
            "last_time_s": self.last_time_s, "last_delta_T_K": self.last_delta_T_K, "last_decision": self.last_decision,
            "offsets_um": self.offsets_um, "degraded": [n for n in self.sensor_names if self.sensors[n].status == "degraded"],
            "regeneration_running": self.regeneration_running, **self.counters.__dict__,
        }


def _brief(req: Mapping) -> dict:
    return {k: req[k] for k in ("machine", "pose_key", "machine_time_s", "element_size_mm") if k in req} | {
        "history_rows": len(req.get("loads_time_s", []))}


def _sensor_message(name: str, event: str, reason: str, rules) -> str:
    if event == "holding":
        return f"sensor {name}: {reason} reading, holding the last good value for at most {rules.hold_s:g} s"
    if event == "degraded":
        return (f"sensor {name}: {reason} for longer than {rules.hold_s:g} s: degraded, the structure model's "
                "estimate (plus the last known bias) stands in")
    return f"sensor {name}: plausible readings again, back in use"


# ====================================================================== the asyncio shell


def resolve_job(spec: str) -> Callable:
    """``"module:function"`` → the function."""
    mod, _, fn = spec.partition(":")
    return getattr(importlib.import_module(mod), fn)


def _call_job(spec: str, request: dict) -> dict:
    """Worker-process entry: resolve the job and run it."""
    return resolve_job(spec)(request)


class Regenerator:
    """Runs generation jobs in a worker process with a wall-clock timeout; a hanging job is killed.

    Compensation never waits for it: the shell only looks at finished futures.
    """

    def __init__(self, job: str, timeout_s: float):
        self.job = job
        self.timeout_s = timeout_s
        self._pool: cf.ProcessPoolExecutor | None = None

    def _executor(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool

    async def run(self, request: dict) -> tuple[dict | None, str | None, str]:
        """Returns (result, error, status) with status ``finished``, ``failed`` or ``timeout``."""
        loop = asyncio.get_running_loop()
        t0 = time.monotonic()
        try:
            fut = loop.run_in_executor(self._executor(), _call_job, self.job, request)
            result = await asyncio.wait_for(fut, self.timeout_s)
            result = dict(result)
            result.setdefault("wall_s", time.monotonic() - t0)
            return result, None, "finished"
        except TimeoutError:
            self.kill()
            return None, f"no result after {self.timeout_s:g} s: job killed", "timeout"
        except asyncio.CancelledError:
            self.kill()
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of the job is reported, never raised
            if isinstance(exc, cf.process.BrokenProcessPool):
                self.kill()
            return None, f"{type(exc).__name__}: {exc}", "failed"

    def kill(self) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        procs = list(getattr(pool, "_processes", {}).values())  # no public API to stop a running job
        for p in procs:
            if p.is_alive():
                p.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            p.join(timeout=5)

    def close(self) -> None:
        self.kill()


@dataclass
class RunResult:
    """Summary of one run of the daemon."""

    status: dict
    stopped_by: str


async def run_monitor(
    cfg: MonitorConfig,
    monitor: Monitor,
    source,
    sink,
    *,
    clock=None,
    stop: asyncio.Event | None = None,
    regenerator: Regenerator | None = None,
    await_regeneration: bool = False,
    seed: int | None = None,
    heartbeat_s: float = 5.0,
) -> RunResult:
    """The daemon's loop: readings → monitor → sink, with reconnect, background jobs and a clean stop.

    Parameters
    ----------
    cfg : configuration (reconnect schedule, regeneration)
    monitor : the state holder
    source : data source (``readings(start_after_s)``)
    sink : offsets sink
    clock : clock for backoff sleeps and freshness
    stop : set it to stop (SIGTERM/SIGINT handlers do)
    regenerator : runs generation jobs (default: from ``cfg.regeneration``)
    await_regeneration : hold the data stream while a job runs (scenario replays, where machine time is
        virtual; never for a live machine)
    seed : seed of the reconnect jitter
    heartbeat_s : write the freshness record this often [s of wall time]
    """
    clock = clock or WallClock()
    stop = stop or asyncio.Event()
    regen = regenerator or Regenerator(cfg.regeneration.job, cfg.regeneration.timeout_s)
    rng = random.Random(seed)
    jobs: set[asyncio.Task] = set()
    attempt = 0
    last_beat = -math.inf

    async def job(request: dict) -> None:
        monitor.regeneration_running = True
        try:
            result, error, status = await regen.run(request)
            monitor.regeneration_finished(request, result, error, status)
        finally:
            monitor.regeneration_running = False

    def start_jobs() -> None:
        for req in monitor.take_requests():
            t = asyncio.create_task(job(req))
            jobs.add(t)
            t.add_done_callback(jobs.discard)

    def beat(force: bool = False) -> None:
        nonlocal last_beat
        now = clock.monotonic()
        if force or now - last_beat >= heartbeat_s:
            last_beat = now
            monitor.store.put_state(monitor.key + ":heartbeat", jsonio.dumps(
                {"unix": clock.unix(), "last_time_s": monitor.last_time_s, "offsets_um": monitor.offsets_um,
                 "active": monitor.active_ids, "degraded": monitor.status()["degraded"],
                 "regeneration_running": monitor.regeneration_running}))

    async def consume() -> str:
        nonlocal attempt
        while True:
            connected = False
            try:
                async for r in source.readings(start_after_s=monitor.last_time_s):
                    if not connected:
                        connected = True
                        if attempt:
                            monitor.counters.reconnects += 1
                            monitor.store.log_event("source", r.time_s, {"status": "reconnected", "attempts": attempt})
                        attempt = 0
                    for off in monitor.process(r):
                        await sink.write(off)
                    start_jobs()
                    if await_regeneration:
                        while jobs:
                            await asyncio.wait(set(jobs))
                    beat()
                if getattr(source, "finished", True):
                    return "end of data"
            except SourceDisconnected as exc:
                delay = backoff_delay(attempt, cfg.reconnect, rng.random())
                log.warning("data source: %s; reconnecting in %.2f s (attempt %d)", exc, delay, attempt + 1)
                if attempt == 0:
                    monitor.store.log_event("source", monitor.last_time_s, {"status": "disconnected", "error": str(exc)})
                attempt += 1
                await clock.sleep(delay)

    start_jobs()
    consumer = asyncio.create_task(consume())
    stopper = asyncio.create_task(stop.wait())
    try:
        await asyncio.wait({consumer, stopper}, return_when=asyncio.FIRST_COMPLETED)
        if consumer.done():
            stopped_by = consumer.result()  # (raises what the loop raised)
            if await_regeneration and jobs:
                await asyncio.wait(set(jobs))
        else:
            # a stop request: the reading being processed is complete (processing has no await inside), the
            # state of the last monitoring boundary is in the database; wait for nothing else
            stopped_by = "signal"
            consumer.cancel()
            try:
                await consumer
            except asyncio.CancelledError:
                pass
    finally:
        stopper.cancel()
        if not consumer.done():
            consumer.cancel()
            try:
                await consumer
            except (asyncio.CancelledError, Exception):  # noqa: BLE001 - shutting down
                pass
        for t in list(jobs):
            t.cancel()
        if jobs:
            await asyncio.gather(*jobs, return_exceptions=True)
        regen.close()
        await sink.close()
        if monitor.last_time_s is not None:
            beat(force=True)
    return RunResult(monitor.status(), stopped_by)


def install_signal_handlers(stop: asyncio.Event) -> None:
    """SIGTERM and SIGINT set ``stop`` (the loop finishes the current reading, persists and exits)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
