"""The monitoring daemon: a thin stateful shell around the pure decisions and the structure model's observer.

:class:`Monitor` keeps one :class:`~hybridcomp.monitor.state.MonitorState` and turns each
:class:`Reading` into compensation offsets. Three clocks of machine time drive it:

* every ``compensation_interval_s`` (5 s): offsets — the active CD set on the low-passed sensors (strategy
  ``hybrid``) or the corrected structure model's drift (strategy ``observer``, the CDs standing in while the
  observer is flagged), clamped and rate limited;
* every ``increment_s`` (20 s, a model step): the histogram of the step's samples gives the loads; the
  observer (:mod:`hybridcomp.rom.observer`) steps the structure model and corrects it with the sensors and,
  when there is one, a probed drift;
* every ``monitoring_interval_s`` (15 min, and at the first sample): the active set's predicted compensation
  error — the CDs on the measured sensors against the corrected model's drift over the interval, and on the
  forecast sensors against the forecast drift — decides keep, switch or generate
  (:func:`hybridcomp.monitor.decisions.decide`); the seeds' ΔT test is reported beside it.

Everything it decides is decided by :mod:`hybridcomp.monitor.decisions`. :func:`run_monitor` is the asyncio
loop around it: data source with reconnect, sink, background generation in a worker process, clean stop.
A replay at 1000× makes the same decisions as the machine in real time.

Persistence and restarts: at every monitoring boundary the whole state is written as one JSON value
(``MonitorStore.put_state``), and every event carries a key made of its kind, the pose and its machine time,
so a daemon killed at any moment and restarted re-processes the samples after the last boundary, makes the
same decisions again and writes no event twice.
"""

from __future__ import annotations

import asyncio
import concurrent.futures as cf
import dataclasses
import hashlib
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

from hybridcomp.chardiag.cd import CDSet
from hybridcomp.histogram.bcs import boundary_conditions
from hybridcomp.histogram.increments import increments_from_samples
from hybridcomp.histogram.signature import SignatureLayout, signatures
from hybridcomp.histogram.trace import Samples, TraceFileError, position_column
from hybridcomp.models import jsonio
from hybridcomp.models.layout import DIRECTIONS, DRIFT_COLUMNS, temperature_column
from hybridcomp.monitor import decisions, volumetric
from hybridcomp.monitor.config import MonitorConfig
from hybridcomp.monitor.decisions import Candidate, Decision, SensorState, SetError
from hybridcomp.monitor.regeneration import FORECAST_STEP_S, RegenerationRequest
from hybridcomp.monitor.sinks import Offset
from hybridcomp.monitor.sources import Reading, SourceDisconnected, WallClock
from hybridcomp.monitor.state import NO_DROPS, STATE_VERSION, MonitorState
from hybridcomp.monitor.store import LeaseHeld, MonitorStore, QueuedStore, lease_owner
from hybridcomp.rom.observer import build_observer

log = logging.getLogger(__name__)

HISTORY_STEP_S = 300.0  # one history row (sensors, estimated drift, mean loads) per this much machine time
SNAPSHOT_STEPS = 6  # the rewind log keeps the observer's estimate before every this many model steps


@dataclass(frozen=True)
class StepRecord:
    """What one model step fed the observer, for re-filtering it when a sensor turns out to have been faulty.

    Attributes
    ----------
    end_s : end of the step [s]
    dt_s : its length [s]
    u : its model inputs (powers [W], air rises [K])
    y_degC : the sensors at its end, from a line through its readings [°C] (NaN: not measured)
    probe_um : a probed drift at its end [µm], or None
    before : the observer's estimate before the step (every ``SNAPSHOT_STEPS`` steps), or None
    """

    end_s: float
    dt_s: float
    u: np.ndarray
    y_degC: np.ndarray
    probe_um: tuple | None
    before: object | None


def state_key(machine: str, pose_key: str) -> str:
    """Key of the monitor's state in the database."""
    return f"monitor:{machine}:{pose_key}"


def _t(x: float) -> str:
    return f"{x:.3f}"


def _finite(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def digest(text: str) -> str:
    """A short stable digest (the same in every process, unlike ``hash()``)."""
    return hashlib.sha256(text.encode()).hexdigest()[:12]


@dataclass
class Counters:
    """What the daemon counts (status, metrics)."""

    readings: int = 0
    compensations: int = 0
    model_steps: int = 0
    monitorings: int = 0
    dropped_repeated: int = 0
    dropped_backwards: int = 0
    dropped_invalid: int = 0
    dropped_jump: int = 0
    gaps: int = 0
    resyncs: int = 0
    switches: int = 0
    generations: int = 0
    reconnects: int = 0
    probes: int = 0
    max_decision_s: float = 0.0
    last_decision_s: float = 0.0


def set_predictions(cds, T_rows: np.ndarray, sensor_names, pose_mm: Mapping[str, float]) -> np.ndarray:
    """A CD set's offsets (n × 3: dx, dy, dz) [µm] on sensor rows [°C] at the pose's axis positions."""
    cols = {temperature_column(s): T_rows[:, j] for j, s in enumerate(sensor_names)}
    cols |= {position_column(a): np.full(len(T_rows), float(v)) for a, v in pose_mm.items()}
    return np.column_stack([cds[d].evaluate_table(cols)[0] for d in DIRECTIONS])


class Monitor:
    """The daemon's state and its reaction to one reading (no I/O but the database).

    Parameters
    ----------
    cfg : configuration
    machine : the machine (axes, sensors, zones, heat sources)
    rom : reduced structure model of the machine at the CDs' pose; a pose-aware one (its first block that model)
        makes the monitor write a support-point table every cycle and the offsets at the commanded position
        (:mod:`hybridcomp.monitor.volumetric`)
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
        self.pose_mm = dict(rom.meta.get("pose_mm") or machine.default_pose_mm())
        # a pose-aware model: the observer keeps its model-pose block on the machine, the whole runs beside it
        self.pose = volumetric.pose_model(rom, cfg.table_points) if rom.meta.get("poses") else None
        self.counters = Counters()
        self.sig_layout = SignatureLayout.of(machine)
        self.layout = machine.layout()
        self.t_ref = self.layout.reference_temperature_degC
        self.observer = build_observer(self.pose.block if self.pose is not None else rom, machine, cfg.observer)
        self.s = self._fresh()
        # --- not persisted
        self.buffer: list[Reading] = []  # samples of the current model step
        self.temps: dict[str, float] = {}  # the sensors of the last sample as the CDs read them (stand-ins included)
        self.measured: dict[str, float] = {}  # ... as the observer reads them (NaN for a degraded sensor)
        self.step_readings: list[tuple[float, np.ndarray]] = []  # the measured sensors over the current step
        self.active = None
        self.regeneration_running = False
        # machine seconds per wall second of the source: None (no clock to ask, a replay), a number, or "observed"
        # (a live control: its stamps against the wall clock over the last samples)
        self.time_scale: float | str | None = None
        self._pace: deque[tuple[float, float]] = deque(maxlen=64)  # (machine time, wall time) of accepted samples
        self._outbox: list[dict] = []
        self._eval_failed_logged = False
        self._nonfinite_logged = False
        self._invalid_after: float | None = -math.inf  # last_time_s of the last invalid-stamp event
        self._snap: dict | None = None
        self.rewind: deque[StepRecord] = deque()  # the recent model steps (not persisted: a restart cannot rewind)
        # the pose-aware model, the table written last and the drives' gains (into s at each boundary: persisted)
        self.track: volumetric.PoseTrack | None = None
        self.table = None
        self.raw_table = None  # the table before the drives' gains and the rate limit
        self.gain_settings = volumetric.GainSettings(probe_sigma_um=cfg.observer.probe_sigma_um)
        self.gains = (volumetric.initial_gains(tuple(rom.meta.get("feedback", {})), self.gain_settings)
                      if self.pose is not None else None)
        self.restore()
        self.reload_active()

    def _fresh(self) -> MonitorState:
        return MonitorState(machine=self.machine.name, pose_key=self.pose_key, rom_id=self.rom.rom_id,
                            sensors={s: SensorState() for s in self.sensor_names},
                            pos_hold=[a.mid_mm for a in self.machine.axes])

    # ------------------------------------------------------------------ persistence
    def persist(self) -> None:
        """Write the state of the last monitoring boundary (with the current generation bookkeeping).

        Only boundary states are written: a restart re-processes the samples after the boundary, so the
        histogram of the interval is complete. Before the first boundary, a fresh state is written (a
        restart starts from the beginning; events are keyed, nothing doubles).
        """
        snap = self._snap if self._snap is not None else self._fresh().to_dict()
        snap = {**snap, "pending": self.s.pending, "regen_blocked_until_s": _finite(self.s.regen_blocked_until_s),
                "activated_s": _finite(self.s.activated_s), "active_ids": self.s.active_ids}
        self.store.put_state(self.key, jsonio.dumps({**snap, "updated_unix": self.clock.unix()}))

    def restore(self) -> None:
        text = self.store.get_state(self.key)
        if not text:
            return
        d = json.loads(text)
        d.pop("updated_unix", None)
        if d.get("version") != STATE_VERSION:
            log.warning("state %s has version %r, this daemon writes %d: starting fresh", self.key, d.get("version"),
                        STATE_VERSION)
            return
        try:
            s = MonitorState.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("state %s is unreadable (%s): starting fresh", self.key, exc)
            return
        if s.rom_id != self.rom.rom_id:
            log.warning("state %s belongs to reduced model %s, not %s: starting fresh", self.key, s.rom_id,
                        self.rom.rom_id)
            return
        self.s = s
        self._snap = s.to_dict()
        if self.pose is not None:
            from hybridcomp.rom.volumetric import table_from_dict

            self.track = volumetric.state_in(self.pose, s.pose_track, s.step_inputs, self.cfg.increment_s)
            self.table = table_from_dict(s.table) if s.table is not None else None
            if s.gains is not None:
                self.gains = volumetric.DriveGains.from_dict(s.gains)
        if s.carry is not None:
            self.buffer = [s.carry]
        if s.pending is not None:
            self._outbox.append(s.pending)  # resubmit a generation the last run did not finish
        log.info("resumed %s at machine time %s s", self.key, s.last_time_s)

    def reload_active(self) -> None:
        self.active = self.db.active_set(self.machine.name, self.pose_key)
        self.s.active_ids = {k: int(v) for k, v in self.active.ids.items()} if self.active is not None else None
        self._eval_failed_logged = False

    def event(self, kind: str, t: float | None, payload: dict, key: str) -> None:
        self.store.log_event(kind, t, payload, key=f"{kind}@{self.pose_key}@{key}")

    # ------------------------------------------------------------------ one reading
    def process(self, r: Reading) -> list[Offset]:
        """Handle one reading; returns the offsets of the compensation cycles it completes (0 or 1)."""
        s = self.s
        r = self._check_time(r)
        if r is None:
            return []
        self.counters.readings += 1
        r = self._clean(r)
        first = s.origin_s is None
        if first:
            self._start(r)
        else:
            # model steps ending before this sample close first (samples up to a boundary belong to its step)
            gap_end = s.origin_s + (math.ceil((r.time_s - s.origin_s) / self.cfg.increment_s) - 1) * self.cfg.increment_s
            if gap_end - s.next_step_s > self.cfg.monitoring_interval_s:
                # a long gap in the data: the step of the samples before it, then one standstill step across it
                # (bounded work however long the gap), and one monitoring decision at its end
                self._close_step(s.next_step_s)
                self._close_step(gap_end, standstill=True)
            while r.time_s > s.next_step_s:
                self._close_step(s.next_step_s)
            self.buffer.append(r)
        s.last_time_s = r.time_s
        self._check_sensors(r)
        self._filter(r.time_s)
        if r.probe_um is not None:
            probe = [float(v) for v in r.probe_um]
            at_pose = True
            if self.pose is not None and self.raw_table is not None:
                self.gains = volumetric.update_gains(self.gains, self.raw_table, r.position_mm, probe, r.time_s,
                                                     self.gain_settings)
                # the observer owns the model's pose: a probe elsewhere teaches the drives' gains only (taken to
                # the pose through the table, the table's errors there would reach the one-pose estimate); one at
                # the pose less the drives' errors there, which the one-pose model does not hold
                at_pose = volumetric.at_model_pose(self.raw_table, r.position_mm)
                if at_pose:
                    probe = volumetric.without_drives_um(volumetric.with_gains(self.raw_table, self.gains),
                                                         r.position_mm, probe)
            if at_pose:
                s.probe_um, s.probe_n = _mean_probe(s.probe_um, s.probe_n, probe)
        if first:
            self._first_estimate(r.time_s)
        out = []
        if r.time_s >= s.next_comp_s:
            out.append(self._compensate(r))
            k = math.floor((r.time_s - s.origin_s) / self.cfg.compensation_interval_s) + 1
            s.next_comp_s = s.origin_s + k * self.cfg.compensation_interval_s
        if r.time_s == s.next_step_s:  # r is the last sample of the step
            self._close_step(r.time_s)
        return out

    def _check_time(self, r: Reading) -> Reading | None:
        """The reading in the monitor's time line, or None when its time stamp is dropped (counted, reported).

        A suspect stamp (far ahead of the time line, or behind it) is an event at once; a confirmed gap or a new
        time line of the control's clock is an event too (:func:`hybridcomp.monitor.decisions.check_time`).
        """
        s = self.s
        now = self.clock.unix()
        wall = None if s.last_wall_unix is None else now - s.last_wall_unix
        chk = decisions.check_time(s.last_time_s, r.time_s, s.time_offset_s, s.time_candidates, self.cfg.time, wall,
                                   self._time_scale())
        first_suspect = chk.verdict in ("jump", "backwards") and len(chk.candidates) == 1 and not s.time_candidates
        s.time_candidates = list(chk.candidates)
        if not chk.accepted:
            s.interval_drops[chk.verdict] += 1
            name = f"dropped_{chk.verdict}"
            setattr(self.counters, name, getattr(self.counters, name) + 1)
            if chk.verdict == "jump" and first_suspect:
                self.event("time", s.last_time_s, {
                    "status": "implausible time stamp", "source_time_s": _finite(r.time_s), "last_time_s": s.last_time_s,
                    "max_step_s": self.cfg.time.max_step_s,
                    "message": f"time stamp {r.time_s!r} s is {r.time_s + s.time_offset_s - s.last_time_s:.6g} s ahead of "
                               f"the last sample (plausible: {self.cfg.time.max_step_s:g} s): dropped until "
                               f"{self.cfg.time.confirm_samples} samples confirm it",
                }, f"jump@{_t(s.last_time_s)}")
                log.warning("implausible time stamp %r s after %.3f s: dropped", r.time_s, s.last_time_s)
            elif chk.verdict == "invalid" and self._invalid_after != s.last_time_s:
                self._invalid_after = s.last_time_s  # one event per run of invalid stamps
                self.event("time", s.last_time_s, {
                    "status": "invalid time stamp", "source_time_s": _finite(r.time_s), "last_time_s": s.last_time_s,
                    "message": f"time stamp {r.time_s!r} s is not a time (not finite, or beyond ±1e10 s): dropped"},
                    f"invalid@{_t(s.last_time_s) if s.last_time_s is not None else 'start'}")
                log.warning("invalid time stamp %r s: dropped", r.time_s)
            return None
        if chk.verdict in ("gap", "resync"):
            msg = (f"the data resumed {chk.time_s - s.last_time_s:.6g} s after the last sample (a gap: the machine time "
                   "is kept)" if chk.verdict == "gap" else
                   f"the control's clock was set: its time stamps moved by {r.time_s - (s.last_source_time_s or 0.0):.6g} s; "
                   f"the monitor's time continues from {s.last_time_s:.3f} s")
            self.event("time", chk.time_s, {"status": chk.verdict, "source_time_s": r.time_s, "last_time_s": s.last_time_s,
                                            "offset_s": chk.offset_s, "message": msg}, f"{chk.verdict}@{_t(chk.time_s)}")
            log.warning("%s", msg)
            self.counters.resyncs += chk.verdict == "resync"
            self.counters.gaps += chk.verdict == "gap"
        if chk.verdict != "ok":
            self._pace.clear()
        self._pace.append((chk.time_s, now))
        s.time_offset_s = chk.offset_s
        s.last_source_time_s = r.time_s
        s.last_wall_unix = now
        return r if chk.time_s == r.time_s else dataclasses.replace(r, time_s=chk.time_s)

    def _time_scale(self) -> float | None:
        """Machine seconds per wall second of the source: given, observed over the recent samples, or None."""
        if self.time_scale != "observed":
            return self.time_scale
        if len(self._pace) < 2:
            return None
        (t0, w0), (t1, w1) = self._pace[0], self._pace[-1]
        return (t1 - t0) / (w1 - w0) if w1 - w0 >= 1.0 else None

    def resume_after_s(self) -> float | None:
        """The source time stamp to resume after (a reconnect or restart)."""
        return self.s.last_source_time_s if self.s.last_source_time_s is not None else self.s.last_time_s

    def _start(self, r: Reading) -> None:
        s = self.s
        s.origin_s = r.time_s
        s.next_comp_s = r.time_s
        s.next_step_s = r.time_s + self.cfg.increment_s
        s.next_mon_s = r.time_s  # the first decision at once
        s.carry = r  # the first step's histogram starts here, after a restart from the first decision too
        self.buffer = [r]

    def _clean(self, r: Reading) -> Reading:
        """Hold positions, spindle speed and air at their last finite values (NaN from a glitching bus)."""
        s = self.s
        pos = list(r.position_mm)
        for j, v in enumerate(pos):
            if math.isfinite(v):
                s.pos_hold[j] = v
            else:
                pos[j] = s.pos_hold[j]
        sp = r.spindle_rpm
        if math.isfinite(sp):
            s.spindle_hold = sp
        else:
            sp = s.spindle_hold
        air = dict(r.air_degC)
        for k, v in air.items():
            if v is not None and math.isfinite(v):
                s.air_hold[k] = v
            else:
                air[k] = s.air_hold.get(k, self.t_ref)
        return Reading(r.time_s, tuple(pos), sp, r.sensors_degC, air, r.probe_um)

    def _estimate_degC(self) -> dict[str, float]:
        if self.s.observer is None:
            return {}
        return dict(zip(self.sensor_names, map(float, self.observer.sensors_degC(self.s.observer))))

    def _check_sensors(self, r: Reading) -> None:
        s = self.s
        est = self._estimate_degC()
        temps, measured = {}, {}
        for name in self.sensor_names:
            raw = r.sensors_degC.get(name)
            if raw is None:
                raw = math.nan
            st = s.sensors[name]
            ref = decisions.substitute(est.get(name, math.nan), s.bias_K.get(name, math.nan))
            v = decisions.check_sensor(st, r.time_s, float(raw), self.cfg.sensors, ref)
            s.sensors[name] = v.state
            if v.event is not None:
                self.event("sensor", r.time_s, {
                    "sensor": name, "status": v.event, "reason": v.state.reason, "raw_degC": _finite(raw),
                    "held_degC": _finite(v.state.value_degC), "substitute_degC": _finite(ref),
                    "message": _sensor_message(name, v.event, v.state.reason, self.cfg.sensors),
                }, f"{name}@{v.event}@{_t(r.time_s)}")
                (log.warning if v.event == "degraded" else log.info)(
                    "sensor %s %s at %.0f s (%s)", name, v.event, r.time_s, v.state.reason)
                if v.event == "degraded":
                    st = v.state
                    onset = st.raw_since_s if st.reason == "frozen" else st.bad_since_s
                    self._refilter(name, onset, r.time_s)
            measured[name] = v.value_degC if v.state.status != "degraded" else math.nan
            temps[name] = v.value_degC if math.isfinite(v.value_degC) else ref
        self.temps, self.measured = temps, measured
        self.step_readings.append((r.time_s, np.array([measured[n] for n in self.sensor_names])))

    def _filter(self, t: float) -> None:
        """Low-pass the sensors the CDs read (first order, ``sensor_filter_s``)."""
        s = self.s
        tau = self.cfg.sensor_filter_s
        a = 1.0 if tau <= 0 or s.filter_time_s is None else -math.expm1(-(t - s.filter_time_s) / tau)
        for name, v in self.temps.items():
            old = s.filtered_degC.get(name, math.nan)
            s.filtered_degC[name] = v if not math.isfinite(old) or not math.isfinite(v) else old + a * (v - old)
        s.filter_time_s = t

    # ------------------------------------------------------------------ the structure model and its observer
    def _first_estimate(self, t: float) -> None:
        """The observer's prior at the first sample, corrected by its sensors; then the first monitoring decision.

        The prior is the steady state in the first sample's air, with no load.
        """
        s = self.s
        u = self._standstill_inputs(self.buffer[-1])
        s.observer = self.observer.initial(u, t)
        s.observer, _ = self.observer.update_sensors(s.observer, [self.measured[n] for n in self.sensor_names])
        self.step_readings = []
        self._after_update(t, u)
        self._record(t)
        self._close_interval(t)

    def _standstill_inputs(self, r: Reading) -> np.ndarray:
        u = np.zeros(self.layout.n_inputs)
        air = self.layout.inputs(list(r.air_degC), np.array([list(r.air_degC.values())], float), "monitor",
                                 self.layout.air_sources(list(r.air_degC)))[0]
        nh = len(self.layout.heat_inputs)
        u[nh:] = air[nh:]
        return u

    def _step_inputs(self, end_s: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Mean model inputs over the closing step from its samples' histogram, and its signature row."""
        s = self.s
        b = self.buffer
        if len(b) >= 2:
            air_names = tuple(sorted(b[-1].air_degC))
            smp = Samples(np.fromiter((x.time_s for x in b), float, len(b)), np.array([x.position_mm for x in b], float),
                          None, np.fromiter((x.spindle_rpm for x in b), float, len(b)), air_names,
                          np.array([[x.air_degC.get(k, self.t_ref) for k in air_names] for x in b], float)
                          .reshape(len(b), len(air_names)), np.arange(len(b)) + 2)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    span = max(smp.time_s[-1] - smp.time_s[0], 1e-6)
                    inc = increments_from_samples(self.machine, smp, min(self.cfg.increment_s, span),
                                                  max_gap_s=self.cfg.max_gap_s, source=f"model step ending {end_s:g} s")
                    loads = boundary_conditions(self.machine, inc)
                    U = self.layout.inputs(loads.names, loads.values, "monitor")
                    _, _, sig_rows = signatures(inc)
                    w = inc.duration_s
                    return (U[1:] * w[:, None]).sum(axis=0) / w.sum(), (sig_rows * w[:, None]).sum(axis=0) / w.sum()
                except (TraceFileError, ValueError) as exc:
                    self.event("warning", end_s, {"message": f"histogram of the step failed: {exc}; last loads held"},
                               f"histogram-error@{_t(end_s)}")
                finally:
                    for wn in caught:
                        self.event("warning", end_s, {"message": str(wn.message)},
                                   f"histogram@{_t(end_s)}@{digest(str(wn.message))}")
        if s.step_inputs is None:
            return self._standstill_inputs(b[-1] if b else s.carry), None
        return np.asarray(s.step_inputs, float), None  # no samples, or an implausible histogram: hold the loads

    def _close_step(self, end_s: float, standstill: bool = False) -> None:
        """One model step: loads of the step's samples → observer predict → correct with sensors and probe.

        ``standstill``: a step across a gap in the data, with no heat and the last air.
        """
        s = self.s
        u, sig = (self._standstill_inputs(s.carry), None) if standstill else self._step_inputs(end_s)
        dt = end_s - s.observer.time_s
        before = s.observer
        if dt > 0:
            s.observer = self.observer.predict(s.observer, u, dt)
            # how far the model moves each sensor in this step: a reading that stands still meanwhile is stuck
            moved = self.observer.sensors_degC(s.observer) - self.observer.sensors_degC(before)
            for name, d in zip(self.sensor_names, moved):
                s.sensors[name] = decisions.model_moved(s.sensors[name], before.time_s, float(d))
        # the sensors at the step's end from a line through their readings over it (their noise averages out)
        y = (decisions.step_end_values([t for t, _ in self.step_readings], [m for _, m in self.step_readings])
             if self.step_readings else np.full(len(self.sensor_names), math.nan))
        self.step_readings = []
        self._log_step(end_s, dt, u, y, s.probe_um, before)
        s.observer, inn = self.observer.update_sensors(s.observer, y)
        for name in inn.rejected:
            s.rejected[name] = s.rejected.get(name, 0) + 1
        if s.probe_um is not None:
            s.observer = self.observer.update_probe(s.observer, s.probe_um)
            self.counters.probes += 1
            payload = {"measured_um": dict(zip(DRIFT_COLUMNS, s.probe_um)), "probes": s.probe_n,
                       "estimate_um": dict(zip(DRIFT_COLUMNS, map(float, self.observer.drift_um(s.observer))))}
            if self.gains is not None and len(self.gains.axes):  # what the probes at several positions taught
                payload["drive_gains"] = {a: float(g) for a, g in zip(self.gains.axes, self.gains.g)}
                payload["message"] = "drives' errors over the model's: " + ", ".join(
                    f"{a} {1 + g:.2f} x" for a, g in zip(self.gains.axes, self.gains.g))
            self.event("probe", end_s, payload, _t(end_s))
            s.probe_um, s.probe_n = None, 0
        self._after_update(end_s, u)
        if sig is not None:
            d = self.cfg.increment_s
            s.signature_sum = list(np.asarray(s.signature_sum if s.signature_sum is not None else np.zeros_like(sig)) + d * sig)
            s.signature_s += d
        s.step_rows.append([end_s, *map(float, u)])
        self._record(end_s)
        self.counters.model_steps += 1
        # next step: the last sample carries over (continuity of the histogram)
        s.carry = self.buffer[-1] if self.buffer else s.carry
        self.buffer = [s.carry] if s.carry is not None else []
        s.next_step_s = end_s + self.cfg.increment_s
        if end_s >= s.next_mon_s:
            self._close_interval(end_s)

    def _log_step(self, end_s: float, dt: float, u: np.ndarray, y: np.ndarray, probe, before) -> None:
        """Keep the step for a rewind: as far back as a faulty sensor can go unnoticed (frozen, then held)."""
        snap = before if len(self.rewind) % SNAPSHOT_STEPS == 0 else None
        self.rewind.append(StepRecord(end_s, dt, np.array(u, float), np.array(y, float),
                                      None if probe is None else tuple(probe), snap))
        keep = self.cfg.sensors.frozen_s + self.cfg.sensors.hold_s + (SNAPSHOT_STEPS + 2) * self.cfg.increment_s
        while len(self.rewind) > SNAPSHOT_STEPS and self.rewind[SNAPSHOT_STEPS].end_s < end_s - keep:
            for _ in range(SNAPSHOT_STEPS):  # drop whole snapshot groups: the first record keeps its snapshot
                self.rewind.popleft()

    def _refilter(self, sensor: str, onset_s: float, t: float) -> None:
        """A sensor found faulty now has been wrong since ``onset_s``: filter the steps since then again without it.

        A frozen sensor is recognised only ``frozen_s`` after it froze; meanwhile the observer took its stuck
        value for the machine's and moved its disturbance estimates (a heat source's scale, the air) to explain
        it, and those would stay wrong. The observer goes back to its estimate before the onset and runs the
        logged steps again with the sensor masked.
        """
        s = self.s
        j = self.sensor_names.index(sensor)
        recs = list(self.rewind)
        starts = [k for k, rec in enumerate(recs) if rec.before is not None and rec.end_s - rec.dt_s <= onset_s]
        if not math.isfinite(onset_s) or not starts or s.observer is None:
            self.event("observer", t, {"status": "not rewound", "sensor": sensor, "onset_s": _finite(onset_s),
                                       "reason": "the steps since the onset are not in the rewind log"},
                       f"rewind@{sensor}@{_t(t)}")
            return
        k0 = starts[-1]
        state = recs[k0].before
        masked = 0
        for rec in recs[k0:]:
            if rec.dt_s > 0:
                state = self.observer.predict(state, rec.u, rec.dt_s)
            y = rec.y_degC.copy()
            if rec.end_s > onset_s:
                y[j] = math.nan
                masked += 1
            state, _ = self.observer.update_sensors(state, y)
            if rec.probe_um is not None:
                state = self.observer.update_probe(state, rec.probe_um)
        was = self.observer.drift_um(s.observer)
        s.observer = state
        for _, m in self.step_readings:
            m[j] = math.nan
        if s.step_inputs is not None:
            self._after_update(s.step_time_s, np.asarray(s.step_inputs, float))
        self.event("observer", t, {
            "status": "rewound", "sensor": sensor, "onset_s": onset_s, "steps_masked": masked,
            "drift_change_um": dict(zip(DRIFT_COLUMNS, map(float, self.observer.drift_um(state) - was))),
        }, f"rewind@{sensor}@{_t(t)}")
        log.warning("observer rewound to %.0f s and %d steps filtered again without %s", recs[k0].end_s - recs[k0].dt_s,
                    masked, sensor)

    def _after_update(self, t: float, u: np.ndarray) -> None:
        """Estimates after an observer update: drift now and one step ahead, stand-in biases."""
        s = self.s
        s.step_time_s = t
        s.step_inputs = [float(v) for v in u]
        s.drift_um = [float(v) for v in self.observer.drift_um(s.observer)]
        s.drift_next_um = [float(v) for v in self.observer.forecast(s.observer, u[None, :], self.cfg.increment_s)[1][0]]
        if self.pose is not None:  # the pose-aware model on the inputs as corrected (a rewind's earlier steps leave it)
            uc = self.observer.corrected_inputs(s.observer, u)
            if self.track is None:
                self.track = volumetric.start(self.pose, uc, t, self.cfg.increment_s)
            elif t > self.track.time_s:
                self.track = volumetric.advance(self.pose, self.track, uc, t, self.cfg.increment_s)
        est = self._estimate_degC()
        for n, v in self.measured.items():
            if math.isfinite(v) and s.sensors[n].status == "ok":
                s.bias_K[n] = v - est[n]

    def _record(self, t: float) -> None:
        """The interval row of this step, and a history row every ``HISTORY_STEP_S``."""
        s = self.s
        row = [t, *(s.filtered_degC.get(n, math.nan) for n in self.sensor_names), *s.drift_um]
        s.interval.append(row)
        last = s.history[-1][0] if s.history else -math.inf
        if t - last >= HISTORY_STEP_S - 1e-9 or not s.history:
            s.history.append(row)
            if s.step_rows:
                s.loads.append([t, *np.mean(np.asarray(s.step_rows, float)[:, 1:], axis=0)])
            elif s.step_inputs is not None:
                s.loads.append([t, *s.step_inputs])
            s.step_rows = []
            keep = t - self.cfg.regeneration.history_s
            s.history = [h for h in s.history if h[0] >= keep]
            s.loads = [h for h in s.loads if h[0] >= keep]

    # ------------------------------------------------------------------ compensation
    def _model_drift_now(self, t: float) -> dict[str, float] | None:
        """The corrected structure model's drift at ``t`` [µm]; None before its first estimate and while it is flagged.

        Linear between the end of the last model step and its forecast one step ahead.
        """
        s = self.s
        if s.observer_flag or s.drift_um is None:
            return None
        f = min(max((t - s.step_time_s) / self.cfg.increment_s, 0.0), 1.0)
        return {c: a + f * (b - a) for c, a, b in zip(DRIFT_COLUMNS, s.drift_um, s.drift_next_um)}

    def _compensate(self, r: Reading) -> Offset:
        s = self.s
        self.counters.compensations += 1
        degraded = ",".join(n for n in self.sensor_names if s.sensors[n].status == "degraded")
        target, outside, by = None, False, "cd"
        model = self._model_drift_now(r.time_s)
        if self.cfg.strategy == "observer" and model is not None:
            target, by = dict(model), "observer"
        elif self.active is not None:
            values = dict(s.filtered_degC)
            values.update(zip(self.axis_names, r.position_mm))
            try:
                target, outside = self.active.evaluate_point(values)
                if not all(math.isfinite(v) for v in target.values()):
                    raise ValueError(f"non-finite offsets {target}")
                self._eval_failed_logged = False
            except (KeyError, ValueError) as exc:
                target = None
                if not self._eval_failed_logged:
                    self._eval_failed_logged = True
                    self.event("warning", r.time_s, {"message": f"the active CDs cannot be evaluated ({exc}); offsets held",
                                                     "values": {k: _finite(v) for k, v in values.items()}},
                               f"evaluate@{_t(r.time_s)}")
        if target is not None and not all(math.isfinite(float(v)) for v in target.values()):
            if not self._nonfinite_logged:
                self._nonfinite_logged = True
                self.event("warning", r.time_s, {"message": f"non-finite offsets from the {by} ({target}); offsets "
                                                 "held"}, f"nonfinite@{by}@{_t(r.time_s)}")
            target = None
        elif target is not None:
            self._nonfinite_logged = False
        if target is None:
            target = dict(s.offsets_um)  # hold (zero before the first CD)
        else:
            target = {k: float(v) for k, v in target.items()}
            if by == "cd":
                if s.blend_pending:  # after a set change: continue from the offsets written last
                    s.blend_um = {k: s.offsets_um.get(k, 0.0) - v for k, v in target.items()}
                    s.blend_time_s = r.time_s
                    s.blend_pending = False
                dt = 0.0 if s.blend_time_s is None else r.time_s - s.blend_time_s
                target, s.blend_um = decisions.blend_offsets(target, s.blend_um, dt, self.cfg.blend_s)
                s.blend_time_s = r.time_s
                if self.cfg.model_transient_s > 0 and model is not None:
                    # the corrected structure model's fast part on top of the CDs' slow part (the model is not flagged)
                    dtc = 0.0 if s.complement_time_s is None else max(r.time_s - s.complement_time_s, 0.0)
                    # a fresh start trusts the corrected model (the CDs earn their part over the crossover time);
                    # an activation does not restart the filter: the new set's difference enters it as slowly
                    # as any other (restarting from the new set's prediction passed each set's fit error on at
                    # once: hybrid 0.57 against 0.33 µm RMS on the demo day at 150 mm)
                    low = s.complement_um if s.complement_um is not None else (
                        dict.fromkeys(DRIFT_COLUMNS, 0.0) if s.complement_time_s is None else None)
                    target, s.complement_um = decisions.complementary_offsets(target, model, low, dtc,
                                                                              self.cfg.model_transient_s)
                    s.complement_time_s = r.time_s
                    by = "cd+model"
                else:
                    s.complement_um = None  # the CDs alone: a later start of the filter begins from its own values
        # the first offsets of a fresh state have nothing to continue: only clamped (a restart continues its own)
        step = self.cfg.max_step_um if s.written else math.inf
        applied, clamped, limited = decisions.limit_offsets(target, s.offsets_um, self.cfg.max_offset_um, step)
        s.offsets_um, s.written = applied, True
        ids = s.active_ids or {}
        active = ",".join(f"{k}={ids[k]}" for k in sorted(ids))
        at_pose = tuple(applied[c] for c in DRIFT_COLUMNS)
        if self.pose is not None and self.track is not None:
            return self._compensate_at_position(r, at_pose, active, clamped, limited, bool(outside), degraded, by)
        return Offset(r.time_s, *at_pose, active, clamped, limited, bool(outside), degraded, by)

    def _compensate_at_position(self, r: Reading, at_pose: tuple, active: str, clamped: bool, limited: bool,
                                outside: bool, degraded: str, by: str) -> Offset:
        """The support-point table of this cycle and the offsets it gives at the reading's commanded position.

        The one-pose offsets carried to every pose, each entry rate limited against the last table.
        """
        from hybridcomp.rom.volumetric import VolumetricError, interpolate_one

        try:
            self.raw_table = volumetric.table_now(self.pose, self.track, r.time_s, self.cfg.increment_s, at_pose)
            table = volumetric.with_gains(self.raw_table, self.gains)
            table, moved = volumetric.table_step(table, self.table, self.cfg.max_step_um)
        except VolumetricError as exc:  # a model gone non-finite: the one-pose offsets, the last table held
            if not self._nonfinite_logged:
                self._nonfinite_logged = True
                self.event("warning", r.time_s, {"message": f"the support-point table cannot be built ({exc}); the "
                                                 "offsets at the model's pose are written"}, f"table@{_t(r.time_s)}")
            return Offset(r.time_s, *at_pose, active, clamped, limited, outside, degraded, by)
        self.table = table
        dx, dy, dz = interpolate_one(table, r.position_mm)
        return Offset(r.time_s, dx, dy, dz, active, clamped, limited or moved, outside, degraded, by,
                      position_mm=tuple(float(v) for v in r.position_mm), pose_um=at_pose, table=table)

    # ------------------------------------------------------------------ monitoring
    def _close_interval(self, boundary: float) -> None:
        """The monitoring cycle at a boundary, then persist and start the next interval."""
        t0 = time.perf_counter()
        s = self.s
        try:
            self._monitor(boundary)
        finally:
            if any(s.interval_drops.values()):
                self.event("time", boundary, {"message": "samples dropped for repeated, backward, implausible or "
                                              "invalid time stamps", **s.interval_drops}, _t(boundary))
                s.interval_drops = dict(NO_DROPS)
            s.interval = s.interval[-1:]  # the boundary row opens the next interval
            s.signature_sum, s.signature_s, s.rejected = None, 0.0, {}
            s.next_mon_s = boundary + self.cfg.monitoring_interval_s
            self.counters.monitorings += 1
            dt = time.perf_counter() - t0
            self.counters.last_decision_s = dt
            self.counters.max_decision_s = max(self.counters.max_decision_s, dt)
            self._sync_pose_state()
            self._snap = s.to_dict()
            self.persist()

    def _sync_pose_state(self) -> None:
        """The pose-aware model's state, the last table and the drives' gains into the state a boundary persists."""
        if self.pose is None:
            return
        from hybridcomp.rom.volumetric import table_to_dict

        s = self.s
        s.pose_track = volumetric.state_out(self.track)
        s.table = table_to_dict(self.table) if self.table is not None else None
        s.gains = self.gains.as_dict()

    def _forecasts(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Sensors and drift over the forecast horizon: the last hour's load continued, and a cool-down."""
        s = self.s
        rows = [r[1:] for r in s.loads if r[0] > s.step_time_s - 3600.0] + [r[1:] for r in s.step_rows]
        u = np.mean(np.asarray(rows, float), axis=0) if rows else np.asarray(s.step_inputs, float)
        nh = len(self.layout.heat_inputs)
        cool = np.concatenate([np.zeros(nh), np.asarray(s.step_inputs, float)[nh:]])
        n = max(1, int(round(self.cfg.validity.forecast_h * 3600.0 / FORECAST_STEP_S)))
        return [self.observer.forecast(s.observer, np.tile(v, (n, 1)), FORECAST_STEP_S) for v in (u, cool)]

    def _set_error(self, cds, rows: np.ndarray, forecasts) -> SetError:
        ns = len(self.sensor_names)
        error = decisions.compensation_error_um
        interval = error(set_predictions(cds, rows[:, 1:1 + ns], self.sensor_names, self.pose_mm), rows[:, 1 + ns:])
        fc = max(error(set_predictions(cds, T, self.sensor_names, self.pose_mm), d) for T, d in forecasts)
        return SetError(interval, fc)

    def _monitor(self, boundary: float) -> None:
        s = self.s
        rows = np.asarray(s.interval, float)
        est = self._estimate_degC()
        measured = {n: v for n, v in self.measured.items() if math.isfinite(v) and s.sensors[n].status == "ok"}
        drifted, drift_K, drift_sensor = decisions.model_drift(est, measured, self.cfg.model_drift_K)
        s.max_residual_K = _finite(drift_K)
        self._flag(boundary, drifted, drift_K, drift_sensor)
        if drifted or s.rejected:
            self.event("model_drift", boundary, {
                "max_abs_K": _finite(drift_K), "sensor": drift_sensor, "threshold_K": self.cfg.model_drift_K,
                "rejected": dict(s.rejected), "estimate_degC": est, "measured_degC": measured,
                "disturbances": self.observer.disturbances(s.observer),
            }, _t(boundary))
        forecasts = self._forecasts()
        error = None
        if self.active is not None:
            try:
                error = self._set_error(self.active.cds, rows, forecasts)
            except (KeyError, ValueError) as exc:
                log.warning("the active set cannot be assessed: %s", exc)
        t_ref = self.active.t_reference_degC if self.active is not None else {}
        dT, dT_sensor = decisions.temperature_deviation(est, t_ref) if self.active is not None else (math.inf, None)
        v = self.cfg.validity
        enabled = self.cfg.regeneration.enabled and boundary >= s.regen_blocked_until_s
        why = ("regeneration is disabled" if not self.cfg.regeneration.enabled else
               f"no generation before {s.regen_blocked_until_s:.0f} s after a failed one")
        running = self.regeneration_running or s.pending is not None
        since = boundary - s.activated_s
        d = decisions.decide(s.active_ids, error, since, v, [], enabled, running, why)
        candidates: list[Candidate] = []
        if d.action != "keep" and v.max_candidates:
            candidates = self._candidates(rows, forecasts, est)
            d = decisions.decide(s.active_ids, error, since, v, candidates, enabled, running, why)
        sig = None if s.signature_sum is None else [float(x) / s.signature_s for x in s.signature_sum]
        payload = {
            "action": d.action, "reason": d.reason, "error_um": None if error is None else error.as_dict(),
            "active": s.active_ids, "candidates": len(candidates),
            "target": None if d.target is None else {"ids": dict(d.target.ids), "load_case": d.target.load_case,
                                                     "error_um": d.target.error.as_dict(), "jump_um": d.target.jump_um},
            "delta_T_K": _finite(dT), "sensor": dT_sensor, "threshold_K": self.cfg.threshold_K,
            "T_actual_degC": est, "T_reference_degC": t_ref, "drift_um": dict(zip(DRIFT_COLUMNS, s.drift_um)),
            "model_drift_K": _finite(drift_K), "signature": None if sig is None else [round(x, 6) for x in sig],
        }
        self.event("decision", boundary, payload, _t(boundary))
        s.last_decision = {"time_s": boundary, "action": d.action, "reason": d.reason}
        s.last_error = None if error is None else error.as_dict()
        s.last_delta_T_K = _finite(dT)
        log.info("t = %.0f s: %s (%s)", boundary, d.action, d.reason)
        self._act(d, boundary, est, sig)

    def _flag(self, t: float, drifted: bool, drift_K: float, sensor: str | None) -> None:
        """The observer is flagged while it departs from the sensors or half of them are degraded."""
        s = self.s
        degraded = [n for n in self.sensor_names if s.sensors[n].status == "degraded"]
        reason = ""
        if drifted:
            reason = f"|estimate − measured| {drift_K:.2f} K at {sensor} above {self.cfg.model_drift_K:g} K"
        elif 2 * len(degraded) >= len(self.sensor_names):
            reason = f"{len(degraded)} of {len(self.sensor_names)} sensors degraded"
        if reason != s.observer_flag:
            self.event("observer", t, {"status": "flagged" if reason else "ok", "reason": reason}, _t(t))
            s.observer_flag = reason

    def _candidates(self, rows: np.ndarray, forecasts, est: Mapping[str, float]) -> list[Candidate]:
        """Stored sets (best by signature, then ΔT) with their predicted errors and their jumps now."""
        s = self.s
        sig = None if s.signature_sum is None else np.asarray(s.signature_sum, float) / s.signature_s
        out = []
        now = np.array([[s.filtered_degC.get(n, math.nan) for n in self.sensor_names]])
        for m in self.db.search(self.machine.name, self.pose_key, sig, est, math.inf, layout=self.sig_layout):
            ids = {k: int(v) for k, v in m.ids.items()}
            if ids == s.active_ids:
                continue
            try:
                cds = {d: self.db.get(ids[d]) for d in DIRECTIONS}
                err = self._set_error(cds, rows, forecasts)
                jump = float(np.max(np.abs(set_predictions(cds, now, self.sensor_names, self.pose_mm)[0]
                                           - np.array([s.offsets_um[c] for c in DRIFT_COLUMNS]))))
            except (KeyError, ValueError) as exc:
                log.info("stored set %s cannot be assessed: %s", ids, exc)
                continue
            out.append(Candidate(ids, m.load_case, err, jump, float(m.delta_T_K)))
            if len(out) >= self.cfg.validity.max_candidates:
                break
        return out

    def _act(self, d: Decision, t: float, est: Mapping[str, float], sig) -> None:
        if d.action == "switch":
            self.activate(d.target.ids, f"switch: {d.reason}", t)
        elif d.action == "regenerate":
            self.s.pending = self._request(t, est, sig)
            self._outbox.append(self.s.pending)
            self.event("generation", t, {"status": "started", "request": _brief(self.s.pending)}, f"{_t(t)}@started")
        elif d.action == "warn":
            self.event("warning", t, {"message": d.reason}, f"decision@{_t(t)}")

    def activate(self, ids: Mapping[str, int], reason: str, t: float) -> None:
        """Make a set active (idempotent: nothing happens when it already is)."""
        ids = {k: int(v) for k, v in ids.items()}
        if self.s.active_ids == ids:
            return
        new = CDSet({d: self.db.get(ids[d]) for d in DIRECTIONS}, ids)  # (reads never wait; a missing id raises)
        if (new.machine, new.pose_key) != (self.machine.name, self.pose_key):
            raise ValueError(f"CD set {ids} is for {new.machine} {new.pose_key}, not {self.machine.name} {self.pose_key}")
        key = f"activation@{self.pose_key}@{_t(t)}@{ids['X']},{ids['Y']},{ids['Z']}"
        name, pose = self.machine.name, self.pose_key
        # the database's record of the switch is written in order with the events, off the compensation path
        self.store.call(lambda: self.db.activate(name, pose, ids, reason=reason, machine_time_s=t, event_key=key),
                        f"activating {ids}")
        self.counters.switches += 1
        had_set = self.active is not None
        self.active = new
        self.s.active_ids = dict(ids)
        self._eval_failed_logged = False
        self.s.activated_s = t
        self.s.blend_pending = had_set and self.cfg.blend_s > 0

    def _request(self, t: float, est: Mapping[str, float], sig) -> dict:
        s = self.s
        ns = len(self.sensor_names)
        H = np.asarray(s.history, float).reshape(-1, 1 + ns + 3)
        L = np.asarray(s.loads, float).reshape(-1, 1 + self.layout.n_inputs)
        return RegenerationRequest(
            machine=self.cfg.machine, pose_key=self.pose_key, pose_mm=dict(self.pose_mm), database=self.cfg.database,
            machine_time_s=t, t_reference_degC=dict(est), signature=sig, rom=str(self.cfg.rom),
            observer=dataclasses.asdict(self.cfg.observer), observer_x=[float(v) for v in s.observer.x],
            history_time_s=H[:, 0].tolist(), history_degC=H[:, 1:1 + ns].tolist(), history_drift_um=H[:, 1 + ns:].tolist(),
            loads_names=list(self.layout.columns), loads_time_s=L[:, 0].tolist(), loads_inputs=L[:, 1:].tolist(),
            anchor_degC={n: float(s.filtered_degC[n]) for n in self.sensor_names},
            anchor_um=dict(s.offsets_um), forecast_h=self.cfg.validity.forecast_h, bump_um=self.cfg.validity.bump_um,
            reference_temperature_degC=self.t_ref, element_size_mm=self.cfg.regeneration.element_size_mm,
        ).to_dict()

    # ------------------------------------------------------------------ generation results
    def take_requests(self) -> list[dict]:
        out, self._outbox = self._outbox, []
        return out

    def regeneration_finished(self, request: dict, result: Mapping | None, error: str | None, status: str) -> None:
        """Record the outcome of a generation job; activate its set when it succeeded."""
        s = self.s
        t = float(request["machine_time_s"])
        if status == "finished" and result is not None:
            ids = {k: int(v) for k, v in result["ids"].items()}
            self.event("generation", t, {"status": "finished", "ids": ids, "load_case": result.get("load_case", ""),
                                         "wall_s": result.get("wall_s"), "notes": result.get("notes") or {}},
                       f"{_t(t)}@finished")
            self.counters.generations += 1
            try:
                self.activate(ids, f"generated for the load case at {t:.0f} s", s.last_time_s)
            except Exception as exc:  # noqa: BLE001 - a broken result must not stop the daemon
                self.event("generation", t, {"status": "activation_failed", "ids": ids, "error": f"{type(exc).__name__}: {exc}"},
                           f"{_t(t)}@activation_failed")
                log.error("generated set %s for %.0f s cannot be activated: %s", ids, t, exc)
        else:
            self.event("generation", t, {"status": status, "error": error}, f"{_t(t)}@{status}")
            # do not start another job for a while
            s.regen_blocked_until_s = (s.last_time_s or t) + self.cfg.regeneration.retry_after_s
            log.warning("generation job for %.0f s %s: %s", t, status, error)
        s.pending = None
        self.persist()

    def status(self) -> dict:
        """Numbers for the status command and the metrics endpoint."""
        s = self.s
        return {
            "machine": self.machine.name, "pose_key": self.pose_key, "active": s.active_ids, "strategy": self.cfg.strategy,
            "last_time_s": s.last_time_s, "last_delta_T_K": s.last_delta_T_K, "last_decision": s.last_decision,
            "last_error_um": s.last_error, "observer_flag": s.observer_flag, "max_residual_K": s.max_residual_K,
            "offsets_um": s.offsets_um, "degraded": [n for n in self.sensor_names if s.sensors[n].status == "degraded"],
            "regeneration_running": self.regeneration_running, **self.counters.__dict__,
        }


def _mean_probe(mean: list | None, n: int, probe: list[float]) -> tuple[list[float], int]:
    """The running mean of the probes of one model step, per direction (NaN: a direction not probed)."""
    if mean is None or n <= 0:
        return list(probe), 1
    out = []
    for m, p in zip(mean, probe):
        out.append(p if not math.isfinite(m) else m if not math.isfinite(p) else m + (p - m) / (n + 1))
    return out, n + 1


def _brief(req: Mapping) -> dict:
    return {k: req[k] for k in ("machine", "pose_key", "machine_time_s") if k in req} | {
        "history_rows": len(req.get("history_time_s", []))}


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
    standby: bool = False,
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
    standby : when another daemon holds the pose, wait until its lease ends (then resume from its last state)
        instead of refusing to start (:class:`~hybridcomp.monitor.store.LeaseHeld`)

    The database is written by a background thread (:class:`~hybridcomp.monitor.store.QueuedStore`): a locked or
    restarting database delays the record, never an offset. Every offset passes :func:`check_offset` before a
    sink sees it.
    """
    clock = clock or WallClock()
    stop = stop or asyncio.Event()
    lease = monitor.key
    owner = lease_owner()
    await _take_lease(monitor, lease, owner, cfg.lease_s, clock, stop, standby)
    if stop.is_set():
        return RunResult(monitor.status(), "signal")
    sync_store = monitor.store
    monitor.store = QueuedStore(sync_store)
    monitor.time_scale = getattr(source, "time_scale", None)
    regen = regenerator or Regenerator(cfg.regeneration.job, cfg.regeneration.timeout_s)
    rng = random.Random(seed)
    jobs: set[asyncio.Task] = set()
    attempt = 0
    last_beat = -math.inf
    applied_unix: float | None = None
    reported: set[str] = set()  # source nodes whose non-numeric values have an event
    lost: list[str] = []

    def renew() -> None:
        """Renew the lease (on the writer thread, in order with the writes); a lost lease stops the daemon."""
        def run():
            holder = sync_store.acquire_lease(lease, owner, cfg.lease_s, clock.unix())
            if holder is not None:
                lost.append(f"the lease on {lease} was taken by {holder.get('owner')} (this daemon could not renew it "
                            f"within {cfg.lease_s:g} s)")
        monitor.store.call(run, "renewing the lease")

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

    def beat(force: bool = False, running: bool = True) -> None:
        nonlocal last_beat
        now = clock.monotonic()
        if force or now - last_beat >= heartbeat_s:
            last_beat = now
            monitor.store.put_state(monitor.key + ":heartbeat", jsonio.dumps(
                {"unix": clock.unix(), "applied_unix": applied_unix, "running": running,
                 "last_time_s": monitor.s.last_time_s, "offsets_um": monitor.s.offsets_um,
                 "active": monitor.s.active_ids, "degraded": monitor.status()["degraded"],
                 "regeneration_running": monitor.regeneration_running, "store_backlog": monitor.store.backlog(),
                 "stale_after_s": cfg.stale_after_s}))

    def source_faults(r: Reading) -> None:
        """Values the source could not read as numbers (a String node where a number belongs): an event per node."""
        for node, n in (getattr(source, "bad_values", None) or {}).items():
            if node not in reported:
                reported.add(node)
                monitor.event("source", r.time_s, {"status": "not a number", "node": node, "count": n,
                                                   "message": f"{node}: a value that is not a number was read as "
                                                   "missing (a sensor fault for a temperature)"},
                              f"nan-value@{node}@{_t(r.time_s) if math.isfinite(r.time_s) else 'nan'}")
                log.warning("source value %s is not a number: read as missing", node)

    async def consume() -> str:
        nonlocal attempt, applied_unix
        while True:
            connected = False
            try:
                async for r in source.readings(start_after_s=monitor.resume_after_s()):
                    if not connected:
                        connected = True
                        if attempt:
                            monitor.counters.reconnects += 1
                            monitor.store.log_event("source", r.time_s, {"status": "reconnected", "attempts": attempt})
                        attempt = 0
                    source_faults(r)
                    for off in monitor.process(r):
                        problem = check_offset(off, cfg.max_offset_um)
                        if problem:
                            monitor.event("warning", off.time_s, {"message": f"offset not written: {problem}"},
                                          f"guard@{_t(off.time_s)}")
                            continue
                        await sink.write(off)
                        applied_unix = clock.unix()
                    if lost:
                        raise LeaseHeld(lost[0])
                    start_jobs()
                    if await_regeneration:
                        while jobs:
                            await asyncio.wait(set(jobs))
                    beat()
                if getattr(source, "finished", True):
                    return "end of data"
            except SourceDisconnected as exc:
                delay = decisions.backoff_delay(attempt, cfg.reconnect, rng.random())
                log.warning("data source: %s; reconnecting in %.2f s (attempt %d)", exc, delay, attempt + 1)
                if attempt == 0:
                    monitor.store.log_event("source", monitor.s.last_time_s, {"status": "disconnected", "error": str(exc)})
                attempt += 1
                await clock.sleep(delay)

    async def keep_lease() -> None:
        """Renew the lease every third of its length, whether data come or not."""
        while True:
            await clock.sleep(cfg.lease_s / 3.0)
            renew()

    start_jobs()
    consumer = asyncio.create_task(consume())
    stopper = asyncio.create_task(stop.wait())
    leaser = asyncio.create_task(keep_lease())
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
        leaser.cancel()
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
        if monitor.s.last_time_s is not None:
            beat(force=True, running=False)
        if not lost:
            monitor.store.call(lambda: sync_store.release_lease(lease, owner["owner"]), "releasing the lease")
        monitor.store.close()
        monitor.store = sync_store
    return RunResult(monitor.status(), stopped_by)


def check_offset(off: Offset, max_abs_um: float) -> str:
    """Why an offset must not reach the control ("" when it may): not finite, or beyond the clamp [µm].

    The project's one output guard (:func:`hybridcomp.chardiag.guard.guard_offsets`), as the CNC exports use it.
    """
    from hybridcomp.chardiag.guard import OffsetGuardError, guard_offsets

    if not math.isfinite(off.time_s):
        return f"time_s = {off.time_s!r} is not finite"
    try:
        guard_offsets({c: getattr(off, c) for c in DRIFT_COLUMNS}, clamp_um=max_abs_um * (1 + 1e-12),
                      source=f"offset at {off.time_s:.3f} s")
    except OffsetGuardError as exc:
        return str(exc)
    return ""  # a support-point table is finite by construction (rom.volumetric.VolumetricTable refuses NaN)


async def _take_lease(monitor: Monitor, lease: str, owner: dict, ttl_s: float, clock, stop: asyncio.Event,
                      standby: bool) -> None:
    """Hold the pose: refuse to start while another daemon holds it, or wait for it (``standby``)."""
    waited = False
    while True:
        holder = monitor.store.acquire_lease(lease, owner, ttl_s, clock.unix())
        if holder is None:
            break
        msg = (f"{lease} is held by another daemon ({holder.get('owner')}, pid {holder.get('pid')} on "
               f"{holder.get('host')}) until its lease ends or it stops")
        if not standby:
            raise LeaseHeld(f"{msg}: refusing to start a second writer (--standby waits for it)")
        if not waited:
            log.warning("%s: standing by", msg)
            waited = True
        try:
            await asyncio.wait_for(stop.wait(), max(0.2, ttl_s / 3.0))
            return
        except TimeoutError:
            pass
    if waited:  # the other daemon went on meanwhile: continue from where it stopped
        monitor.s = monitor._fresh()
        monitor.restore()
        monitor.reload_active()
        monitor.store.log_event("lease", monitor.s.last_time_s, {"status": "taken over", "owner": owner["owner"]})


def install_signal_handlers(stop: asyncio.Event) -> None:
    """SIGTERM and SIGINT set ``stop`` (the loop finishes the current reading, persists and exits)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
