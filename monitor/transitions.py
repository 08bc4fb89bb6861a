"""The monitor as pure transitions: one frozen state, one function per clock, each returning a :class:`Step`.

:class:`Context` is what does not change during a run (configuration, machine, the structure model's observer, the
pose-aware model, sensor names, limits); :class:`State` is everything that does (the persisted
:class:`~hybridcomp.monitor.state.MonitorState` and what a run keeps beside it).  Both are frozen; the containers
and numpy arrays inside a state are never changed in place: every transition builds new ones, so a state once
returned stays what it was (a boundary's state is persisted by keeping a reference to it).

The clocks of machine time, each a function ``(ctx, state, ...) -> Step``:

* :func:`on_reading` — one sample: time stamp and sensor checks, the held inputs, the low-pass filter, the data-only
  model's step (strategy ``dataonly``), a probe;
  the model steps and monitoring boundaries the sample completes (:func:`on_model_step`, :func:`on_interval`);
  every ``compensation_interval_s`` (5 s) the offsets;
* :func:`on_model_step` — every ``increment_s`` (a model step): the histogram's loads, the observer's predict and
  correction with the sensors and a probe; at a monitoring boundary :func:`on_interval` too;
* :func:`on_interval` — every ``monitoring_interval_s`` (15 min): the active set's predicted error decides keep,
  switch or generate (:func:`hybridcomp.monitor.decisions.decide`);
* :func:`on_activate`, :func:`on_regeneration_finished` — a set made active, a generation job's outcome;
* :func:`on_grid_decision`, :func:`on_grid_generation_finished` — without a pose-aware model, at a boundary: keep,
  switch or generate the CD grid, and a grid generation's outcome.

A :class:`Step` is the new state, the offsets to write, and what the daemon must do, in order: the
event-log entries (:class:`Event`) and the commands (:class:`Activate` a set in the database, submit a generation
:class:`Request`, :class:`Persist` a boundary's state, :class:`Log` a line).  The database reads a decision needs
come in as arguments: the active set is part of the state (the daemon loads it, :func:`with_active`), the stored
sets a monitoring decision may switch to come from ``stored_sets`` (:class:`SetQuery` → :class:`StoredSet`), which
the daemon reads lazily from the database and a test gives as a list.  Nothing here touches the database, files,
the clock or the network.
"""

from __future__ import annotations

import dataclasses
import math
import re
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from hybridcomp.chardiag.cd import CDSet
from hybridcomp.frozen import evolve
from hybridcomp.histogram.bcs import boundary_conditions
from hybridcomp.histogram.increments import increments_from_samples
from hybridcomp.histogram.signature import SignatureLayout, signatures
from hybridcomp.histogram.trace import Samples, TraceFileError, air_columns, position_column
from hybridcomp.models.layout import DIRECTIONS, DRIFT_COLUMNS, temperature_column
from hybridcomp.monitor import dataonly_strategy, decisions, volumetric
from hybridcomp.monitor.config import MonitorConfig
from hybridcomp.monitor.decisions import Candidate, Decision, SensorState, SetError
from hybridcomp.monitor.regeneration import FORECAST_STEP_S, RegenerationRequest
from hybridcomp.monitor.sinks import Offset
from hybridcomp.monitor.sources import Reading
from hybridcomp.monitor.state import NO_DROPS, MonitorState
from hybridcomp.rom.observer import build_observer

HISTORY_STEP_S = 300.0  # one history row (sensors, estimated drift, mean loads) per this much machine time
SNAPSHOT_STEPS = 6  # the rewind log keeps the observer's estimate before every this many model steps
PACE_SAMPLES = 64  # (machine time, wall time) pairs kept to observe a live source's pace


# ============================================================================================ context, state, steps
@dataclass(frozen=True)
class Context:
    """What does not change during a run.

    Attributes
    ----------
    cfg : configuration
    machine : the machine (axes, sensors, zones, heat sources)
    pose_key : the pose's database key
    rom_id : the reduced structure model's id (a persisted state belongs to it)
    observer : the structure model's observer (:mod:`hybridcomp.rom.observer`) on the model pose's reduced model
    pose : the pose-aware model (:class:`hybridcomp.monitor.volumetric.PoseModel`), or None for a one-pose model
    sensor_names, axis_names : the machine's sensors and axes, in its order
    pose_mm : the CDs' pose [mm]
    layout, sig_layout : the model inputs' layout and the load-case signature's
    t_ref : reference temperature [°C] (the air before the first finite reading)
    gain_settings : priors of the drives' gains
    feedback_axes : the pose-aware model's drives
    dataonly : strategy ``dataonly``: the data-only model (:class:`hybridcomp.monitor.dataonly_strategy.DataOnlyModel`)
        that gives the offsets; None for the other strategies
    """

    cfg: MonitorConfig
    machine: object
    pose_key: str
    rom_id: str
    observer: object
    pose: volumetric.PoseModel | None
    sensor_names: tuple[str, ...]
    axis_names: tuple[str, ...]
    pose_mm: Mapping[str, float]
    layout: object
    sig_layout: object
    t_ref: float
    gain_settings: volumetric.GainSettings
    feedback_axes: tuple[str, ...]
    dataonly: dataonly_strategy.DataOnlyModel | None = None


def context(cfg: MonitorConfig, machine, rom, pose_key: str,
            dataonly: dataonly_strategy.DataOnlyModel | None = None) -> Context:
    """The context of a run on ``rom`` (a pose-aware model: its model pose's block is the observer's).

    ``dataonly``: the data-only model, required with strategy ``dataonly`` (its sensors must be the machine's
    sensors or air columns), ignored otherwise.
    """
    pose = volumetric.pose_model(rom, cfg.table_points, machine) if rom.meta.get("poses") else None
    layout = machine.layout()
    if cfg.strategy != "dataonly":
        dataonly = None
    elif dataonly is None:
        raise ValueError(f"{cfg.source_file}: strategy 'dataonly' needs the data-only model (compensation.dataonly_model)")
    else:
        known = {s.name for s in machine.sensors} | {c.removesuffix("_degC") for c in air_columns(machine)}
        unknown = [n for n in dataonly.sensors if n not in known]
        if unknown:
            raise ValueError(f"{cfg.source_file}: compensation.dataonly_model = {str(cfg.dataonly_model)!r} reads "
                             f"{', '.join(unknown)}, which machine {machine.name} has neither as a sensor nor as an "
                             f"air column (sensors: {', '.join(sorted(known))})")
    return Context(
        cfg=cfg, machine=machine, pose_key=pose_key, rom_id=rom.rom_id,
        observer=build_observer(pose.block if pose is not None else rom, machine, cfg.observer), pose=pose,
        sensor_names=tuple(s.name for s in machine.sensors), axis_names=tuple(a.name for a in machine.axes),
        pose_mm=dict(rom.meta.get("pose_mm") or machine.default_pose_mm()), layout=layout,
        sig_layout=SignatureLayout.of(machine), t_ref=layout.reference_temperature_degC,
        gain_settings=volumetric.GainSettings(
            probe_sigma_um=cfg.observer.probe_sigma_um,
            bounded_axes=tuple(d.axis for d in machine.drives if d.feedback == "rotary_encoder")),
        feedback_axes=tuple(rom.meta.get("feedback", {})), dataonly=dataonly)


@dataclass(frozen=True)
class Counters:
    """What the daemon counts (status, metrics).

    ``reconnects`` and the decision times are the shell's: ``last_decision_s`` and ``max_decision_s`` are the wall
    time of the reading that closed a monitoring interval (its decision, the model steps and compensation of the
    reading included) [s].
    """

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


@dataclass(frozen=True)
class GainProbe:
    """A drift probed away from the model's pose as the drives' gains took it, for learning it again in a rewind.

    Attributes
    ----------
    time_s : when it was probed [s]
    position_mm : the axis positions it was probed at [mm]
    probe_um : the probed drift (dx, dy, dz) [µm]
    gains_before : the drives' gains before it
    table_time_s : the time of the table it was taken against (the last compensation cycle's) [s]
    offsets_um : the one-pose offsets that table carried to every pose [µm]
    drift_um : the observer's drift estimate then (its last step's) [µm], or None
    """

    time_s: float
    position_mm: tuple[float, ...]
    probe_um: tuple[float, ...]
    gains_before: object
    table_time_s: float
    offsets_um: tuple[float, float, float]
    drift_um: tuple[float, float, float] | None


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
    track_before : with ``before``, the pose-aware model's state then (None: it had not started)
    weights : where the machine was over the step, as the pose-aware model was advanced with it
        (:func:`_step_weights`), or None
    gain_probes : the probes over the step that taught the drives' gains (:class:`GainProbe`)
    """

    end_s: float
    dt_s: float
    u: np.ndarray
    y_degC: np.ndarray
    probe_um: tuple | None
    before: object | None
    track_before: object | None = None
    weights: object | None = None
    gain_probes: tuple[GainProbe, ...] = ()


@dataclass(frozen=True)
class State:
    """The monitor's state: the persisted part and what a run keeps beside it (a restart starts it afresh).

    Attributes
    ----------
    saved : what a restart needs (:class:`~hybridcomp.monitor.state.MonitorState`; its ``pose_track``, ``table``
        and ``gains`` are brought up to date at each monitoring boundary from the fields below)
    active : the active CD set (loaded by the daemon; None without one)
    buffer : samples of the current model step
    temps : the sensors of the last sample as the CDs read them (stand-ins included) [°C]
    measured : ... as the observer reads them (NaN for a degraded sensor) [°C]
    step_readings : (time, measured sensors) over the current step
    rewind : the recent model steps (:class:`StepRecord`), for a rewind when a sensor turns out faulty
    track : the pose-aware model's state (:class:`hybridcomp.monitor.volumetric.PoseTrack`), or None
    written_table : the support-point table written last, or None
    raw_table : the last table before the drives' gains and the rate limit, or None
    raw_nut_table : the nuts' part of it (:func:`hybridcomp.monitor.volumetric.nut_table_now`), or None
    raw_table_of : the time and the one-pose offsets ``raw_table`` was built at, or None
    step_gain_probes : the probes of the current step that taught the drives' gains, for the rewind log
    drive_gains : the drives' gains (:class:`hybridcomp.monitor.volumetric.DriveGains`), or None
    grid : without a pose-aware model, the active CD grid (:class:`hybridcomp.chardiag.grid.CDGrid`, loaded by the
        daemon: :func:`with_active_grid`), whose sets give the support-point table; None: none
    pace : (machine time, wall time) of the last accepted samples (a live source's pace)
    eval_failed_logged, nonfinite_logged : a warning of a failing evaluation / non-finite offsets is out (once
        per run of them)
    invalid_after_s : ``last_time_s`` at the last invalid-stamp event (one event per run of them)
    dataonly_um, dataonly_sd_um : strategy ``dataonly``: the data-only model's offsets and their spread at the last
        sample [µm] (None: none, the offsets are held)
    counters : what the monitor counts
    """

    saved: MonitorState
    active: CDSet | None = None
    buffer: tuple[Reading, ...] = ()
    temps: Mapping[str, float] = field(default_factory=dict)
    measured: Mapping[str, float] = field(default_factory=dict)
    step_readings: tuple[tuple[float, np.ndarray], ...] = ()
    rewind: tuple[StepRecord, ...] = ()
    track: volumetric.PoseTrack | None = None
    written_table: object | None = None
    raw_table: object | None = None
    raw_nut_table: object | None = None
    raw_table_of: tuple[float, tuple[float, float, float]] | None = None
    step_gain_probes: tuple[GainProbe, ...] = ()
    drive_gains: volumetric.DriveGains | None = None
    grid: object | None = None
    pace: tuple[tuple[float, float], ...] = ()
    eval_failed_logged: bool = False
    nonfinite_logged: bool = False
    invalid_after_s: float | None = -math.inf
    dataonly_um: Mapping[str, float] | None = None
    dataonly_sd_um: Mapping[str, float] | None = None
    counters: Counters = Counters()


@dataclass(frozen=True)
class Event:
    """An entry of the event log: its kind, machine time, payload and key (unique within the kind and pose)."""

    kind: str
    t: float | None
    payload: Mapping
    key: str


@dataclass(frozen=True)
class Activate:
    """Record in the database that the set ``ids`` became active at machine time ``t`` (the state already has it)."""

    ids: Mapping[str, int]
    reason: str
    t: float | None


@dataclass(frozen=True)
class Request:
    """Submit a generation job (:class:`hybridcomp.monitor.regeneration.RegenerationRequest` as a dict)."""

    request: Mapping


@dataclass(frozen=True)
class Persist:
    """Persist ``state`` as the last monitoring boundary's.

    None: the last boundary's again, with the current generation bookkeeping.
    """

    state: State | None


@dataclass(frozen=True)
class Log:
    """A line for the daemon's log (``level``: a :mod:`logging` method name)."""

    level: str
    message: str


@dataclass(frozen=True)
class Step:
    """A transition's result: the new state, the offsets to write, and the effects (events and commands) in order."""

    state: State
    offsets: tuple[Offset, ...] = ()
    effects: tuple[Event | Activate | ActivateGrid | Request | Persist | Log, ...] = ()

    @property
    def events(self) -> tuple[Event, ...]:
        return tuple(e for e in self.effects if isinstance(e, Event))

    @property
    def commands(self) -> tuple:
        return tuple(e for e in self.effects if not isinstance(e, Event))


@dataclass(frozen=True)
class SetQuery:
    """What a monitoring decision asks the database for: stored sets of this load case, best first.

    Attributes
    ----------
    signature : the interval's load-case signature, or None
    temperatures_degC : the structure model's sensor temperatures now [°C]
    skip_ids : the active set's ids (not a candidate), or None
    """

    signature: np.ndarray | None
    temperatures_degC: Mapping[str, float]
    skip_ids: Mapping[str, int] | None


@dataclass(frozen=True)
class StoredSet:
    """A stored CD set the database offers (``cds`` None when it could not be read: ``error`` says why)."""

    ids: Mapping[str, int]
    load_case: str
    delta_T_K: float
    cds: Mapping[str, object] | None
    error: str = ""


StoredSets = Callable[[SetQuery], Iterable[StoredSet]]


def no_stored_sets(query: SetQuery) -> tuple[StoredSet, ...]:
    """No stored sets (a database without any beside the active one)."""
    return ()


class _Out:
    """The effects of one transition call, in order (local to the call: the transitions stay pure)."""

    def __init__(self):
        self.offsets: list[Offset] = []
        self.effects: list = []

    def event(self, kind: str, t: float | None, payload: dict, key: str) -> None:
        self.effects.append(Event(kind, t, payload, key))

    def command(self, c) -> None:
        self.effects.append(c)

    def log(self, level: str, message: str) -> None:
        self.effects.append(Log(level, message))

    def step(self, st: State) -> Step:
        return Step(st, tuple(self.offsets), tuple(self.effects))


_SAVED = frozenset(f.name for f in dataclasses.fields(MonitorState))


def _set(st: State, **kw) -> State:
    """``st`` with fields replaced: those of :class:`MonitorState` in ``saved``, the others in the state."""
    saved = {k: kw.pop(k) for k in list(kw) if k in _SAVED}
    if saved:
        kw["saved"] = evolve(st.saved, **saved)
    return evolve(st, **kw) if kw else st


def counted(st: State, **inc) -> State:
    """``st`` with its counters increased by ``inc`` (name → increment)."""
    c = st.counters
    return evolve(st, counters=evolve(c, **{k: getattr(c, k) + v for k, v in inc.items()}))


def _t(x: float) -> str:
    return f"{x:.3f}"


def _finite(x) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


# ============================================================================================ starting points
def initial(ctx: Context) -> State:
    """A fresh state (no sample yet, no active set)."""
    saved = MonitorState(machine=ctx.machine.name, pose_key=ctx.pose_key, rom_id=ctx.rom_id,
                         sensors={s: SensorState() for s in ctx.sensor_names},
                         pos_hold=[a.mid_mm for a in ctx.machine.axes])
    gains = None if ctx.pose is None else volumetric.initial_gains(ctx.feedback_axes, ctx.gain_settings,
                                                                   nuts=ctx.pose.nut_inputs is not None)
    return State(saved, drive_gains=gains)


def restored(ctx: Context, saved: MonitorState) -> State:
    """The state of a persisted boundary: the pose-aware model's state, the last table and the gains read back."""
    if saved.dataonly is not None and (ctx.dataonly is None
                                       or not dataonly_strategy.compatible(ctx.dataonly, saved.dataonly)):
        saved = evolve(saved, dataonly=None)  # another strategy's or model's: the data-only model starts afresh
    st = evolve(initial(ctx), saved=saved)
    if ctx.pose is not None:
        from hybridcomp.rom.volumetric import table_from_dict

        st = evolve(st, track=volumetric.state_in(ctx.pose, saved.pose_track, saved.step_inputs, ctx.cfg.increment_s),
                    written_table=table_from_dict(saved.table) if saved.table is not None else None)
        if saved.gains is not None:
            st = evolve(st, drive_gains=volumetric.DriveGains.from_dict(saved.gains))
    elif saved.table is not None:  # a CD grid's table (a one-pose model): the rate limit continues from it
        from hybridcomp.rom.volumetric import table_from_dict

        st = evolve(st, written_table=table_from_dict(saved.table))
    if saved.carry is not None:
        st = evolve(st, buffer=(saved.carry,))
    return st


def with_active(ctx: Context, st: State, active: CDSet | None) -> State:
    """The state with ``active`` the active set as the database has it (the database has the last word)."""
    ids = {k: int(v) for k, v in active.ids.items()} if active is not None else None
    return evolve(_set(st, active_ids=ids), active=active, eval_failed_logged=False)


def with_active_grid(ctx: Context, st: State, grid) -> State:
    """The state with ``grid`` the active CD grid as the database has it (None: none).

    A pose-aware model and strategy ``dataonly`` ignore it.

    The next compensation cycles build the support-point table from its sets (:func:`_compensate_from_grid`); the
    table written last stays the rate limit's start (carried onto the new grid's points when they differ).
    """
    return evolve(st, grid=grid if ctx.pose is None and ctx.dataonly is None else None)


def boundary_saved(ctx: Context, boundary: State | None, st: State) -> MonitorState:
    """What to persist: the last boundary's state with ``st``'s generation bookkeeping.

    The boundary's state is a fresh one before the first boundary; the bookkeeping is the pending request, the
    block after a failed job, the activation.
    """
    snap = boundary.saved if boundary is not None else initial(ctx).saved
    s = st.saved
    return evolve(snap, pending=s.pending, regen_blocked_until_s=s.regen_blocked_until_s,
                  grid_pending=s.grid_pending, grid_blocked_until_s=s.grid_blocked_until_s,
                  activated_s=s.activated_s, active_ids=s.active_ids)


# ============================================================================================ one reading
def on_reading(ctx: Context, st: State, r: Reading, stored_sets: StoredSets = no_stored_sets,
               now_unix: float | None = None, time_scale: float | str | None = None) -> Step:
    """One sample: the offsets of the compensation cycle it completes (0 or 1) and what it decided.

    Parameters
    ----------
    ctx, st : context and state
    r : the sample (source time stamps)
    stored_sets : the stored sets a monitoring decision within this sample may switch to
    now_unix : wall time when it arrived [Unix s] (None: no wall clock, a jump ahead is never a gap)
    time_scale : machine seconds per wall second of the source: None (unknown), a number, or ``"observed"``
        (from the recent samples' stamps and wall times)
    """
    out = _Out()
    prev = st.saved
    st, r = _check_time(ctx, st, r, now_unix, time_scale, out)
    if r is None:
        return out.step(st)
    st = counted(st, readings=1)
    st, r = _clean(ctx, st, r)
    first = st.saved.origin_s is None
    if first:
        st = _start(ctx, st, r)
    else:
        # model steps ending before this sample close first (samples up to a boundary belong to its step); a boundary
        # among them is persisted as of the sample before this one, which is not in it: a restart resumes with this
        # sample (not after it: that lost it, and its step's histogram differed from the uninterrupted run's)
        mine = {"last_source_time_s": st.saved.last_source_time_s, "last_wall_unix": st.saved.last_wall_unix}
        st = _set(st, last_source_time_s=prev.last_source_time_s, last_wall_unix=prev.last_wall_unix)
        s = st.saved
        inc = ctx.cfg.increment_s
        gap_end = s.origin_s + (math.ceil((r.time_s - s.origin_s) / inc) - 1) * inc
        if gap_end - s.next_step_s > ctx.cfg.monitoring_interval_s:
            # a long gap in the data: the step of the samples before it, then one standstill step across it
            # (bounded work however long the gap), and one monitoring decision at its end
            st = _close_step(ctx, st, s.next_step_s, stored_sets, out)
            st = _close_step(ctx, st, gap_end, stored_sets, out, standstill=True)
        while r.time_s > st.saved.next_step_s:
            st = _close_step(ctx, st, st.saved.next_step_s, stored_sets, out)
        st = evolve(_set(st, **mine), buffer=(*st.buffer, r))
    st = _set(st, last_time_s=r.time_s)
    st = _check_sensors(ctx, st, r, out)
    st = _filter(ctx, st, r.time_s)
    if ctx.dataonly is not None:
        st = _dataonly_step(ctx, st, r)
    if r.probe_um is not None:
        st = _probe(ctx, st, r)
    if first:
        st = _first_estimate(ctx, st, r.time_s, stored_sets, out)
    if r.time_s >= st.saved.next_comp_s:
        st, off = _compensate(ctx, st, r, out)
        out.offsets.append(off)
        s = st.saved
        k = math.floor((r.time_s - s.origin_s) / ctx.cfg.compensation_interval_s) + 1
        st = _set(st, next_comp_s=s.origin_s + k * ctx.cfg.compensation_interval_s)
    if r.time_s == st.saved.next_step_s:  # r is the last sample of the step
        st = _close_step(ctx, st, r.time_s, stored_sets, out)
    return out.step(st)


def _check_time(ctx: Context, st: State, r: Reading, now: float | None, time_scale, out: _Out
                ) -> tuple[State, Reading | None]:
    """The reading in the monitor's time line, or None when its time stamp is dropped (counted, reported).

    A suspect stamp (far ahead of the time line, or behind it) is an event at once; a confirmed gap or a new
    time line of the control's clock is an event too (:func:`hybridcomp.monitor.decisions.check_time`).
    """
    s = st.saved
    cfg = ctx.cfg
    wall = None if s.last_wall_unix is None or now is None else now - s.last_wall_unix
    chk = decisions.check_time(s.last_time_s, r.time_s, s.time_offset_s, s.time_candidates, cfg.time, wall,
                               _time_scale(st.pace, time_scale))
    first_suspect = chk.verdict in ("jump", "backwards") and len(chk.candidates) == 1 and not s.time_candidates
    st = _set(st, time_candidates=list(chk.candidates))
    if not chk.accepted:
        st = _set(st, interval_drops={**s.interval_drops, chk.verdict: s.interval_drops[chk.verdict] + 1})
        st = counted(st, **{f"dropped_{chk.verdict}": 1})
        if chk.verdict == "jump" and first_suspect:
            out.event("time", s.last_time_s, {
                "status": "implausible time stamp", "source_time_s": _finite(r.time_s), "last_time_s": s.last_time_s,
                "max_step_s": cfg.time.max_step_s,
                "message": f"time stamp {r.time_s!r} s is {r.time_s + s.time_offset_s - s.last_time_s:.6g} s ahead of "
                           f"the last sample (plausible: {cfg.time.max_step_s:g} s): dropped until "
                           f"{cfg.time.confirm_samples} samples confirm it",
            }, f"jump@{_t(s.last_time_s)}")
            out.log("warning", f"implausible time stamp {r.time_s!r} s after {s.last_time_s:.3f} s: dropped")
        elif chk.verdict == "invalid" and st.invalid_after_s != s.last_time_s:
            st = evolve(st, invalid_after_s=s.last_time_s)  # one event per run of invalid stamps
            out.event("time", s.last_time_s, {
                "status": "invalid time stamp", "source_time_s": _finite(r.time_s), "last_time_s": s.last_time_s,
                "message": f"time stamp {r.time_s!r} s is not a time (not finite, or beyond ±1e10 s): dropped"},
                f"invalid@{_t(s.last_time_s) if s.last_time_s is not None else 'start'}")
            out.log("warning", f"invalid time stamp {r.time_s!r} s: dropped")
        return st, None
    if chk.verdict in ("gap", "resync"):
        msg = (f"the data resumed {chk.time_s - s.last_time_s:.6g} s after the last sample (a gap: the machine time "
               "is kept)" if chk.verdict == "gap" else
               f"the control's clock was set: its time stamps moved by {r.time_s - (s.last_source_time_s or 0.0):.6g} s; "
               f"the monitor's time continues from {s.last_time_s:.3f} s")
        out.event("time", chk.time_s, {"status": chk.verdict, "source_time_s": r.time_s, "last_time_s": s.last_time_s,
                                       "offset_s": chk.offset_s, "message": msg}, f"{chk.verdict}@{_t(chk.time_s)}")
        out.log("warning", msg)
        st = counted(st, resyncs=int(chk.verdict == "resync"), gaps=int(chk.verdict == "gap"))
    pace = st.pace if chk.verdict == "ok" else ()
    st = evolve(_set(st, time_offset_s=chk.offset_s, last_source_time_s=r.time_s, last_wall_unix=now),
                pace=(*pace, (chk.time_s, now))[-PACE_SAMPLES:])
    return st, (r if chk.time_s == r.time_s else evolve(r, time_s=chk.time_s))


def _time_scale(pace, setting) -> float | None:
    """Machine seconds per wall second of the source: given, observed over the recent samples, or None."""
    if setting != "observed":
        return setting
    if len(pace) < 2 or pace[0][1] is None or pace[-1][1] is None:
        return None
    (t0, w0), (t1, w1) = pace[0], pace[-1]
    return (t1 - t0) / (w1 - w0) if w1 - w0 >= 1.0 else None


def _start(ctx: Context, st: State, r: Reading) -> State:
    st = _set(st, origin_s=r.time_s, next_comp_s=r.time_s, next_step_s=r.time_s + ctx.cfg.increment_s,
              next_mon_s=r.time_s,  # the first decision at once
              carry=r)  # the first step's histogram starts here, after a restart from the first decision too
    return evolve(st, buffer=(r,))


def _clean(ctx: Context, st: State, r: Reading) -> tuple[State, Reading]:
    """Hold positions, spindle speed and air at their last finite values (NaN from a glitching bus)."""
    s = st.saved
    pos = list(r.position_mm)
    hold = list(s.pos_hold)
    for j, v in enumerate(pos):
        if math.isfinite(v):
            hold[j] = v
        else:
            pos[j] = hold[j]
    sp = r.spindle_rpm
    spindle = s.spindle_hold
    if math.isfinite(sp):
        spindle = sp
    else:
        sp = spindle
    air = dict(r.air_degC)
    air_hold = dict(s.air_hold)
    for k, v in air.items():
        if v is not None and math.isfinite(v):
            air_hold[k] = v
        else:
            air[k] = air_hold.get(k, ctx.t_ref)
    st = _set(st, pos_hold=hold, spindle_hold=spindle, air_hold=air_hold)
    return st, Reading(r.time_s, tuple(pos), sp, r.sensors_degC, air, r.probe_um)


def _estimate_degC(ctx: Context, st: State) -> dict[str, float]:
    if st.saved.observer is None:
        return {}
    return dict(zip(ctx.sensor_names, map(float, ctx.observer.sensors_degC(st.saved.observer))))


def _check_sensors(ctx: Context, st: State, r: Reading, out: _Out) -> State:
    est = _estimate_degC(ctx, st)
    temps, measured = {}, {}
    sensors = dict(st.saved.sensors)
    for name in ctx.sensor_names:
        raw = r.sensors_degC.get(name)
        if raw is None:
            raw = math.nan
        ref = decisions.substitute(est.get(name, math.nan), st.saved.bias_K.get(name, math.nan))
        v = decisions.check_sensor(sensors[name], r.time_s, float(raw), ctx.cfg.sensors, ref)
        sensors[name] = v.state
        if v.event is not None:
            out.event("sensor", r.time_s, {
                "sensor": name, "status": v.event, "reason": v.state.reason, "raw_degC": _finite(raw),
                "held_degC": _finite(v.state.value_degC), "substitute_degC": _finite(ref),
                "message": _sensor_message(name, v.event, v.state.reason, ctx.cfg.sensors),
            }, f"{name}@{v.event}@{_t(r.time_s)}")
            out.log("warning" if v.event == "degraded" else "info",
                    f"sensor {name} {v.event} at {r.time_s:.0f} s ({v.state.reason})")
            if v.event == "degraded":
                vs = v.state
                onset = vs.raw_since_s if vs.reason == "frozen" else vs.bad_since_s
                # (the rewind's stand-in biases see the sensors checked so far)
                st = _refilter(ctx, _set(st, sensors=dict(sensors)), name, onset, r.time_s, out)
        measured[name] = v.value_degC if v.state.status != "degraded" else math.nan
        temps[name] = v.value_degC if math.isfinite(v.value_degC) else ref
    row = (r.time_s, np.array([measured[n] for n in ctx.sensor_names]))
    return evolve(_set(st, sensors=sensors), temps=temps, measured=measured,
                  step_readings=(*st.step_readings, row))


def _filter(ctx: Context, st: State, t: float) -> State:
    """Low-pass the sensors the CDs read (first order, ``sensor_filter_s``)."""
    s = st.saved
    tau = ctx.cfg.sensor_filter_s
    a = 1.0 if tau <= 0 or s.filter_time_s is None else -math.expm1(-(t - s.filter_time_s) / tau)
    filtered = dict(s.filtered_degC)
    for name, v in st.temps.items():
        old = filtered.get(name, math.nan)
        filtered[name] = v if not math.isfinite(old) or not math.isfinite(v) else old + a * (v - old)
    return _set(st, filtered_degC=filtered, filter_time_s=t)


def _dataonly_step(ctx: Context, st: State, r: Reading) -> State:
    """Strategy ``dataonly``: the data-only model one sample on (every sample: its lags are exact) with its probe.

    Its inputs: the low-passed sensors, the air as read (held: :func:`_clean`; an air column never read is at the
    reference temperature) and the spindle speed. The first sample starts it (the offsets at its steady state); a
    sample with a non-finite input leaves it as it was and the offsets are held.
    """
    s = st.saved
    model = ctx.dataonly
    air = {k.removesuffix("_degC"): v for k, v in {**s.air_hold, **r.air_degC}.items()}
    values = {**air, **s.filtered_degC}
    sensors = {n: float(values.get(n, ctx.t_ref)) for n in model.sensors}
    spindle = {"spindle_rpm": float(r.spindle_rpm)}
    if not all(map(math.isfinite, [*sensors.values(), *spindle.values()])):
        return evolve(st, dataonly_um=None, dataonly_sd_um=None)
    if s.dataonly is None:
        ds = dataonly_strategy.start(model, r.time_s, sensors, spindle)
        off, sd = dataonly_strategy.predict(model, ds)
    else:
        ds, off, sd = dataonly_strategy.step(model, s.dataonly, r.time_s, sensors, spindle, r.probe_um)
    return evolve(_set(st, dataonly=ds), dataonly_um=off, dataonly_sd_um=sd)


def _probe(ctx: Context, st: State, r: Reading) -> State:
    """A probed drift: into the mean of the step's probes (at the model's pose) and the drives' gains."""
    probe = [float(v) for v in r.probe_um]
    at_pose = True
    if ctx.pose is not None and st.raw_table is not None:
        gains = volumetric.update_gains(st.drive_gains, st.raw_table, r.position_mm, probe, r.time_s,
                                        ctx.gain_settings, st.raw_nut_table)
        learnt = st.step_gain_probes
        if st.raw_table_of is not None and not volumetric.at_model_pose(st.raw_table, r.position_mm):
            learnt = (*learnt, GainProbe(r.time_s, tuple(float(v) for v in r.position_mm), tuple(probe),
                                         st.drive_gains, st.raw_table_of[0], st.raw_table_of[1],
                                         None if st.saved.drift_um is None
                                         else tuple(float(v) for v in st.saved.drift_um)))
        st = evolve(st, drive_gains=gains, step_gain_probes=learnt)
        # the observer owns the model's pose: a probe elsewhere teaches the drives' gains only (taken to the pose
        # through the table, the table's errors there would reach the one-pose estimate); one at the pose less the
        # drives' errors there, which the one-pose model does not hold
        at_pose = volumetric.at_model_pose(st.raw_table, r.position_mm)
        if at_pose:  # the gains' share at the pose is taken out at the step's end (:func:`_probe_at_pose`)
            probe = volumetric.without_drives_um(st.raw_table, r.position_mm, probe)
    if not at_pose:
        return st
    mean, n = _mean_probe(st.saved.probe_um, st.saved.probe_n, probe)
    return _set(st, probe_um=mean, probe_n=n)


# ============================================================================================ the model step
def on_model_step(ctx: Context, st: State, end_s: float, stored_sets: StoredSets = no_stored_sets,
                  standstill: bool = False) -> Step:
    """One model step to ``end_s`` (and the monitoring decision when it reaches a boundary).

    The loads of the step's samples → observer predict → correct with the sensors and a probe. ``standstill``: a
    step across a gap in the data, with no heat and the last air.
    """
    out = _Out()
    return out.step(_close_step(ctx, st, end_s, stored_sets, out, standstill))


def _first_estimate(ctx: Context, st: State, t: float, stored_sets: StoredSets, out: _Out) -> State:
    """The observer's prior at the first sample, corrected by its sensors; then the first monitoring decision.

    The prior is the steady state in the first sample's air, with no load.
    """
    u = _standstill_inputs(ctx, st.buffer[-1])
    obs = ctx.observer.initial(u, t)
    obs, _ = ctx.observer.update_sensors(obs, [st.measured[n] for n in ctx.sensor_names])
    st = evolve(_set(st, observer=obs), step_readings=())
    st = _after_update(ctx, st, t, u)
    st = _record(ctx, st, t)
    return _close_interval(ctx, st, t, stored_sets, out)


def _standstill_inputs(ctx: Context, r: Reading) -> np.ndarray:
    layout = ctx.layout
    u = np.zeros(layout.n_inputs)
    air = layout.inputs(list(r.air_degC), np.array([list(r.air_degC.values())], float), "monitor",
                        layout.air_sources(list(r.air_degC)))[0]
    nh = len(layout.heat_inputs)
    u[nh:] = air[nh:]
    return u


def _step_inputs(ctx: Context, st: State, end_s: float, out: _Out) -> tuple[np.ndarray, np.ndarray | None]:
    """Mean model inputs over the closing step from its samples' histogram, and its signature row."""
    s = st.saved
    b = st.buffer
    machine = ctx.machine
    if len(b) >= 2:
        air_names = tuple(sorted(b[-1].air_degC))
        smp = Samples(np.fromiter((x.time_s for x in b), float, len(b)), np.array([x.position_mm for x in b], float),
                      None, np.fromiter((x.spindle_rpm for x in b), float, len(b)), air_names,
                      np.array([[x.air_degC.get(k, ctx.t_ref) for k in air_names] for x in b], float)
                      .reshape(len(b), len(air_names)), np.arange(len(b)) + 2)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                span = max(smp.time_s[-1] - smp.time_s[0], 1e-6)
                inc = increments_from_samples(machine, smp, min(ctx.cfg.increment_s, span),
                                              max_gap_s=ctx.cfg.max_gap_s, source=f"model step ending {end_s:g} s")
                loads = boundary_conditions(machine, inc)
                U = ctx.layout.inputs(loads.names, loads.values, "monitor")
                _, _, sig_rows = signatures(inc)
                w = inc.duration_s
                return (U[1:] * w[:, None]).sum(axis=0) / w.sum(), (sig_rows * w[:, None]).sum(axis=0) / w.sum()
            except (TraceFileError, ValueError) as exc:
                out.event("warning", end_s, {"message": f"histogram of the step failed: {exc}; last loads held"},
                          f"histogram-error@{_t(end_s)}")
            finally:
                for wn in caught:
                    out.event("warning", end_s, {"message": str(wn.message)}, histogram_warning_key(end_s, str(wn.message)))
    if s.step_inputs is None:
        return _standstill_inputs(ctx, b[-1] if b else s.carry), None
    return np.asarray(s.step_inputs, float), None  # no samples, or an implausible histogram: hold the loads


def _close_step(ctx: Context, st: State, end_s: float, stored_sets: StoredSets, out: _Out,
                standstill: bool = False) -> State:
    obs = ctx.observer
    s = st.saved
    u, sig = (_standstill_inputs(ctx, s.carry), None) if standstill else _step_inputs(ctx, st, end_s, out)
    before = s.observer
    dt = end_s - before.time_s
    state = before
    sensors = s.sensors
    if dt > 0:
        state = obs.predict(before, u, dt)
        # how far the model moves each sensor: a reading that stands still meanwhile is stuck. Open-loop from the
        # rewind log where it reaches back; else the corrected model's move in each step, summed
        opened = _open_loop_moved(ctx, st, sensors, before.time_s, u, dt)
        moved = obs.sensors_degC(state) - obs.sensors_degC(before)
        sensors = {**sensors, **{
            name: (decisions.model_moved_since(sensors[name], before.time_s, opened[name]) if name in opened
                   else decisions.model_moved(sensors[name], before.time_s, float(d)))
            for name, d in zip(ctx.sensor_names, moved)}}
    # the sensors at the step's end from a line through their readings over it (their noise averages out)
    y = (decisions.step_end_values([t for t, _ in st.step_readings], [m for _, m in st.step_readings])
         if st.step_readings else np.full(len(ctx.sensor_names), math.nan))
    probe = _probe_at_pose(st, s.probe_um)
    weights = _step_weights(ctx, st, end_s) if ctx.pose is not None else None
    st = _log_step(ctx, evolve(st, step_readings=()), end_s, dt, u, y, probe, before, weights)
    state, inn = obs.update_sensors(state, y)
    rejected = dict(s.rejected)
    for name in inn.rejected:
        rejected[name] = rejected.get(name, 0) + 1
    st = _set(st, observer=state, sensors=sensors, rejected=rejected)
    if probe is not None:
        state = obs.update_probe(state, probe)
        st = counted(_set(st, observer=state, probe_um=None, probe_n=0), probes=1)
        payload = {"measured_um": dict(zip(DRIFT_COLUMNS, probe)), "probes": s.probe_n,
                   "estimate_um": dict(zip(DRIFT_COLUMNS, map(float, obs.drift_um(state))))}
        g = st.drive_gains
        if g is not None and len(g.axes):  # what the probes at several positions taught
            payload["drive_gains"] = {a: float(v) for a, v in zip(g.axes, g.g)}
            payload["message"] = "drives' errors over the model's: " + ", ".join(
                f"{a} {1 + v:.2f} x" for a, v in zip(g.axes, g.g))
            if g.h is not None:
                payload["nut_gains"] = {a: float(v) for a, v in zip(g.axes, g.h)}
                payload["message"] += "; nuts' part added: " + ", ".join(
                    f"{a} {v:+.2f} x" for a, v in zip(g.axes, g.h))
        out.event("probe", end_s, payload, _t(end_s))
    st = _after_update(ctx, st, end_s, u, weights)
    s = st.saved
    if sig is not None:
        d = ctx.cfg.increment_s
        st = _set(st, signature_sum=list(np.asarray(s.signature_sum if s.signature_sum is not None
                                                    else np.zeros_like(sig)) + d * sig),
                  signature_s=s.signature_s + d)
    st = _set(st, step_rows=[*st.saved.step_rows, [end_s, *map(float, u)]])
    st = counted(_record(ctx, st, end_s), model_steps=1)
    # next step: the last sample carries over (continuity of the histogram)
    carry = st.buffer[-1] if st.buffer else st.saved.carry
    st = evolve(_set(st, carry=carry, next_step_s=end_s + ctx.cfg.increment_s),
                buffer=(carry,) if carry is not None else ())
    if end_s >= st.saved.next_mon_s:
        st = _close_interval(ctx, st, end_s, stored_sets, out)
    return st


def _open_loop_moved(ctx: Context, st: State, sensors: Mapping[str, decisions.SensorState], step_start_s: float,
                     u: np.ndarray, dt: float) -> dict[str, float]:
    """How far the loads alone move each sensor whose raw reading has stood still since before this step [K].

    The corrected model is no judge of a stuck sensor: the observer takes the stuck value for the machine's and
    explains it, by the air above all (every zone's with the common walk, ``ObserverSettings``), after which the
    model moves the sensor no more than its reading moves (a sensor stuck while the spindle heated it was found
    after 31 min instead of 16). The model run open-loop from the rewind log's oldest estimate, its disturbances
    held as they stood then, is: the move from the start of the first step after the reading last changed to
    this step's end. Sensors standing still since before the log's start are left out (the caller sums the
    corrected model's moves for them).

    Cost: one open-loop step per logged step, run again at every model step while any reading stands still
    (quantised readings often do). With the defaults (20 s steps, ``frozen_s`` 1800 s) the log holds about 107
    steps: 8 ms on the 80 mm demonstrator's observer (order 122, one BLAS thread, the 2-core machine with another
    job beside it), 0.04 % of the 20 s step; keeping the open-loop state between steps would save it.
    """
    standing = {n: s.raw_since_s for n, s in sensors.items() if decisions.stood_still(s, step_start_s)}
    recs = st.rewind
    if not standing or not recs or recs[0].before is None:
        return {}
    first = recs[0].end_s - recs[0].dt_s
    standing = {n: t for n, t in standing.items() if t >= first}
    if not standing:
        return {}
    obs = ctx.observer
    x = recs[0].before.x
    starts, T = [], []
    for t0, uk, dtk in [*((r.end_s - r.dt_s, r.u, r.dt_s) for r in recs), (step_start_s, u, dt)]:
        starts.append(t0)
        T.append(obs.sensors_degC(x))
        if dtk > 0:
            x = obs.predict_mean(x, uk, dtk)
    now = obs.sensors_degC(x)
    out = {}
    for n, since in standing.items():
        k = next(i for i, t0 in enumerate(starts) if t0 >= since)  # the current step's start qualifies
        j = ctx.sensor_names.index(n)
        out[n] = float(now[j] - T[k][j])
    return out


def _log_step(ctx: Context, st: State, end_s: float, dt: float, u, y, probe, before, weights=None) -> State:
    """Keep the step for a rewind: as far back as a faulty sensor can go unnoticed (frozen, then held).

    ``weights``: where the machine was over the step (the pose-aware model's, :func:`_step_weights`).
    """
    snap = before if len(st.rewind) % SNAPSHOT_STEPS == 0 else None
    rw = (*st.rewind, StepRecord(end_s, dt, np.array(u, float), np.array(y, float),
                                 None if probe is None else tuple(probe), snap,
                                 st.track if snap is not None else None, weights, st.step_gain_probes))
    rules = ctx.cfg.sensors
    keep = rules.frozen_s + rules.hold_s + (SNAPSHOT_STEPS + 2) * ctx.cfg.increment_s
    while len(rw) > SNAPSHOT_STEPS and rw[SNAPSHOT_STEPS].end_s < end_s - keep:
        rw = rw[SNAPSHOT_STEPS:]  # drop whole snapshot groups: the first record keeps its snapshot
    return evolve(st, rewind=rw, step_gain_probes=())


def _refilter(ctx: Context, st: State, sensor: str, onset_s: float, t: float, out: _Out) -> State:
    """A sensor found faulty now has been wrong since ``onset_s``: filter the steps since then again without it.

    A frozen sensor is recognised only ``frozen_s`` after it froze; meanwhile the observer took its stuck value for
    the machine's and moved its disturbance estimates (a heat source's scale, the air) to explain it, and those
    would stay wrong. The observer goes back to its estimate before the onset and runs the logged steps again with
    the sensor masked. The pose-aware model, run on the inputs as the observer corrected them (its air above all),
    goes back with it and runs the same steps again on the inputs as the rewound observer corrects them: its screws
    follow their air within half an hour, and would otherwise keep the stuck value's air that long.
    """
    obs = ctx.observer
    s = st.saved
    j = ctx.sensor_names.index(sensor)
    recs = st.rewind
    starts = [k for k, rec in enumerate(recs) if rec.before is not None and rec.end_s - rec.dt_s <= onset_s]
    if not math.isfinite(onset_s) or not starts or s.observer is None:
        out.event("observer", t, {"status": "not rewound", "sensor": sensor, "onset_s": _finite(onset_s),
                                  "reason": "the steps since the onset are not in the rewind log"},
                  f"rewind@{sensor}@{_t(t)}")
        return st
    k0 = starts[-1]
    state = recs[k0].before
    track = recs[k0].track_before if ctx.pose is not None else None
    masked = 0
    learnt = [gp for rec in recs[k0:] for gp in rec.gain_probes] + list(st.step_gain_probes)
    gains = learnt[0].gains_before if learnt else None
    for rec in recs[k0:]:
        for gp in rec.gain_probes:  # taken while the pose-aware model stood where the rewound one now stands
            gains = _relearnt(ctx, gains, gp, state, track)
        if rec.dt_s > 0:
            state = obs.predict(state, rec.u, rec.dt_s)
        y = rec.y_degC.copy()
        if rec.end_s > onset_s:
            y[j] = math.nan
            masked += 1
        state, _ = obs.update_sensors(state, y)
        if rec.probe_um is not None:
            state = obs.update_probe(state, rec.probe_um)
        if ctx.pose is not None:  # as _after_update advanced it, on the inputs as now corrected
            track = _advanced(ctx, track, obs.corrected_inputs(state, rec.u), rec.end_s, rec.weights)
    was = obs.drift_um(s.observer)

    def without(m: np.ndarray) -> np.ndarray:
        m = m.copy()
        m[j] = math.nan
        return m

    st = evolve(_set(st, observer=state), step_readings=tuple((tm, without(m)) for tm, m in st.step_readings))
    if ctx.pose is not None and track is not None:
        st = evolve(st, track=track)
    for gp in st.step_gain_probes:  # this step's, against the model as it stands at the step's start
        gains = _relearnt(ctx, gains, gp, state, track)
    payload = {"status": "rewound", "sensor": sensor, "onset_s": onset_s, "steps_masked": masked,
               "drift_change_um": dict(zip(DRIFT_COLUMNS, map(float, obs.drift_um(state) - was)))}
    if gains is not None:
        payload["gain_probes_relearnt"] = len(learnt)
        payload["drive_gains"] = {a: float(v) for a, v in zip(gains.axes, gains.g)}
        st = evolve(st, drive_gains=gains)
    if s.step_inputs is not None:
        st = _after_update(ctx, st, s.step_time_s, np.asarray(s.step_inputs, float))
    out.event("observer", t, payload, f"rewind@{sensor}@{_t(t)}")
    out.log("warning", f"observer rewound to {recs[k0].end_s - recs[k0].dt_s:.0f} s and {masked} steps filtered "
                       f"again without {sensor}")
    return st


def _relearnt(ctx: Context, gains, gp: GainProbe, state, track):
    """The drives' gains after probe ``gp`` taken again against the rewound models (:func:`_refilter`).

    The table it is taken against is the pose-aware model's as rewound (``track``, at the compensation cycle the
    probe was taken against), carrying the one-pose offsets of then moved by as much as the rewound observer's drift
    estimate (``state``) moved: the offsets a run without the faulty sensor would have carried, as near as the
    observer tells them.  Without a track (the model had not started) the gains stay as they are.
    """
    if gains is None or track is None:
        return gains
    offsets = np.asarray(gp.offsets_um, float)
    if gp.drift_um is not None:
        offsets = offsets + ctx.observer.drift_um(state) - np.asarray(gp.drift_um, float)
    raw = volumetric.table_now(ctx.pose, track, gp.table_time_s, ctx.cfg.increment_s, offsets)
    nut = volumetric.nut_table_now(ctx.pose, track, gp.table_time_s, ctx.cfg.increment_s)
    return volumetric.update_gains(gains, raw, gp.position_mm, gp.probe_um, gp.time_s, ctx.gain_settings, nut)


def _step_weights(ctx: Context, st: State, end_s: float):
    """Where the machine was over the step ending at ``end_s``, for the pose history (None without samples).

    The support poses' weights of the step's samples, each for the time until the next (the last until ``end_s``)
    (:func:`hybridcomp.monitor.volumetric.step_weights`, :func:`~hybridcomp.monitor.volumetric.advance`).
    """
    b = st.buffer
    if not b:
        return None
    ts = np.fromiter((x.time_s for x in b), float, len(b))
    dt = np.clip(np.diff(ts, append=max(end_s, ts[-1])), 0.0, None)
    if dt.sum() <= 0:
        dt = np.ones(len(b))
    return volumetric.step_weights(ctx.pose, np.array([x.position_mm for x in b], float), dt)


def _advanced(ctx: Context, track: volumetric.PoseTrack | None, uc: np.ndarray, t: float, weights
              ) -> volumetric.PoseTrack:
    """The pose-aware model advanced to ``t`` on the corrected inputs ``uc`` (started there if it had not)."""
    if track is None:
        return volumetric.start(ctx.pose, uc, t, ctx.cfg.increment_s)
    if t > track.time_s:
        return volumetric.advance(ctx.pose, track, uc, t, ctx.cfg.increment_s, weights)
    return track


def _after_update(ctx: Context, st: State, t: float, u: np.ndarray, weights=None) -> State:
    """Estimates after an observer update: drift now and one step ahead, stand-in biases.

    ``weights``: where the machine was over the step ending at ``t`` (:func:`_step_weights`; None: from the buffer).
    """
    obs = ctx.observer
    state = st.saved.observer
    track = st.track
    if ctx.pose is not None:  # the pose-aware model on the inputs as corrected (a rewind re-runs it: _refilter)
        if track is not None and t > track.time_s and weights is None:
            weights = _step_weights(ctx, st, t)
        track = _advanced(ctx, track, obs.corrected_inputs(state, u), t, weights)
    st = evolve(_set(st, step_time_s=t, step_inputs=[float(v) for v in u],
                      drift_um=[float(v) for v in obs.drift_um(state)],
                      drift_next_um=[float(v) for v in obs.forecast(state, u[None, :], ctx.cfg.increment_s)[1][0]]),
                track=track)
    est = _estimate_degC(ctx, st)
    bias = dict(st.saved.bias_K)
    for n, v in st.measured.items():
        if math.isfinite(v) and st.saved.sensors[n].status == "ok":
            bias[n] = v - est[n]
    return _set(st, bias_K=bias)


def _record(ctx: Context, st: State, t: float) -> State:
    """The interval row of this step, and a history row every ``HISTORY_STEP_S``."""
    s = st.saved
    row = [t, *(s.filtered_degC.get(n, math.nan) for n in ctx.sensor_names), *s.drift_um]
    history, loads, step_rows = s.history, s.loads, s.step_rows
    last = history[-1][0] if history else -math.inf
    if t - last >= HISTORY_STEP_S - 1e-9 or not history:
        history = [*history, row]
        if step_rows:
            loads = [*loads, [t, *np.mean(np.asarray(step_rows, float)[:, 1:], axis=0)]]
        elif s.step_inputs is not None:
            loads = [*loads, [t, *s.step_inputs]]
        step_rows = []
        keep = t - ctx.cfg.regeneration.history_s
        history = [h for h in history if h[0] >= keep]
        loads = [h for h in loads if h[0] >= keep]
    return _set(st, interval=[*s.interval, row], history=history, loads=loads, step_rows=step_rows)


# ============================================================================================ compensation
def _model_drift_now(ctx: Context, st: State, t: float) -> dict[str, float] | None:
    """The corrected structure model's drift at ``t`` [µm]; None before its first estimate and while it is flagged.

    Linear between the end of the last model step and its forecast one step ahead.
    """
    s = st.saved
    if s.observer_flag or s.drift_um is None:
        return None
    f = min(max((t - s.step_time_s) / ctx.cfg.increment_s, 0.0), 1.0)
    return {c: a + f * (b - a) for c, a, b in zip(DRIFT_COLUMNS, s.drift_um, s.drift_next_um)}


def _compensate(ctx: Context, st: State, r: Reading, out: _Out) -> tuple[State, Offset]:
    """One compensation cycle: the offsets (and with a pose-aware model the support-point table)."""
    cfg = ctx.cfg
    s = st.saved
    st = counted(st, compensations=1)
    degraded = ",".join(n for n in ctx.sensor_names if s.sensors[n].status == "degraded")
    target, outside, by = None, False, "cd"
    eval_failed, nonfinite = st.eval_failed_logged, st.nonfinite_logged
    upd: dict = {}
    model = _model_drift_now(ctx, st, r.time_s)
    if cfg.strategy == "dataonly":  # the data-only model's offsets (a channel it has no model of: 0); no CDs
        by = "dataonly"
        if st.dataonly_um is not None:
            target = {c: st.dataonly_um.get(c, 0.0) for c in DRIFT_COLUMNS}
    elif s.failsafe:  # the active set is known to be wrong (:func:`fail_safe`): never evaluated
        target, by = (dict(model), "observer") if model is not None else (dict.fromkeys(DRIFT_COLUMNS, 0.0), "zero")
    elif cfg.strategy == "observer" and model is not None:
        target, by = dict(model), "observer"
    elif st.active is not None:
        values = dict(s.filtered_degC)
        values.update(zip(ctx.axis_names, r.position_mm))
        try:
            target, outside = st.active.evaluate_point(values)
            if not all(math.isfinite(v) for v in target.values()):
                raise ValueError(f"non-finite offsets {target}")
            eval_failed = False
        except (KeyError, ValueError) as exc:
            target = None
            if not eval_failed:
                eval_failed = True
                out.event("warning", r.time_s, {"message": f"the active CDs cannot be evaluated ({exc}); offsets held",
                                                "values": {k: _finite(v) for k, v in values.items()}},
                          f"evaluate@{_t(r.time_s)}")
    if target is not None and not all(math.isfinite(float(v)) for v in target.values()):
        if not nonfinite:
            nonfinite = True
            out.event("warning", r.time_s, {"message": f"non-finite offsets from the {by} ({target}); offsets held"},
                      f"nonfinite@{by}@{_t(r.time_s)}")
        target = None
    elif target is not None:
        nonfinite = False
    if target is None:
        target = dict(s.offsets_um)  # hold (zero before the first CD)
    else:
        target = {k: float(v) for k, v in target.items()}
        if by == "cd":
            blend_um, blend_time_s = s.blend_um, s.blend_time_s
            if s.blend_pending:  # after a set change: continue from the offsets written last
                blend_um = {k: s.offsets_um.get(k, 0.0) - v for k, v in target.items()}
                blend_time_s = r.time_s
                upd["blend_pending"] = False
            dt = 0.0 if blend_time_s is None else r.time_s - blend_time_s
            target, upd["blend_um"] = decisions.blend_offsets(target, blend_um, dt, cfg.blend_s)
            upd["blend_time_s"] = r.time_s
            if cfg.model_transient_s > 0 and model is not None:
                # the corrected structure model's fast part on top of the CDs' slow part (the model is not flagged)
                dtc = 0.0 if s.complement_time_s is None else max(r.time_s - s.complement_time_s, 0.0)
                # a fresh start trusts the corrected model (the CDs earn their part over the crossover time); an
                # activation does not restart the filter: the new set's difference enters it as slowly as any
                # other (restarting from the new set's prediction passed each set's fit error on at once: hybrid
                # 0.57 against 0.33 µm RMS on the demo day at 150 mm)
                low = s.complement_um if s.complement_um is not None else (
                    dict.fromkeys(DRIFT_COLUMNS, 0.0) if s.complement_time_s is None else None)
                target, upd["complement_um"] = decisions.complementary_offsets(target, model, low, dtc,
                                                                               cfg.model_transient_s)
                upd["complement_time_s"] = r.time_s
                by = "cd+model"
            else:
                upd["complement_um"] = None  # the CDs alone: a later start of the filter begins from its own values
    # the first offsets of a fresh state have nothing to continue: only clamped (a restart continues its own)
    step = cfg.max_step_um if s.written else math.inf
    applied, clamped, limited = decisions.limit_offsets(target, s.offsets_um, cfg.max_offset_um, step)
    st = evolve(_set(st, offsets_um=applied, written=True, **upd), eval_failed_logged=eval_failed,
                nonfinite_logged=nonfinite)
    ids = s.active_ids or {}
    active = ",".join(f"{k}={ids[k]}" for k in sorted(ids))
    at_pose = tuple(applied[c] for c in DRIFT_COLUMNS)
    if ctx.pose is not None and st.track is not None:
        return _compensate_at_position(ctx, st, r, at_pose, active, clamped, limited, bool(outside), degraded, by,
                                       out)
    if ctx.pose is None and st.grid is not None:
        return _compensate_from_grid(ctx, st, r, at_pose, active, clamped, limited, bool(outside), degraded, by, out)
    return st, Offset(r.time_s, *at_pose, active, clamped, limited, bool(outside), degraded, by)


def _compensate_at_position(ctx: Context, st: State, r: Reading, at_pose: tuple, active: str, clamped: bool,
                            limited: bool, outside: bool, degraded: str, by: str, out: _Out) -> tuple[State, Offset]:
    """The support-point table of this cycle and the offsets it gives at the reading's commanded position.

    The one-pose offsets carried to every pose, each entry rate limited against the last table.
    """
    from hybridcomp.rom.volumetric import VolumetricError, interpolate_one

    try:
        raw = volumetric.table_now(ctx.pose, st.track, r.time_s, ctx.cfg.increment_s, at_pose)
        nut = volumetric.nut_table_now(ctx.pose, st.track, r.time_s, ctx.cfg.increment_s)
        st = evolve(st, raw_table=raw, raw_nut_table=nut,
                    raw_table_of=(float(r.time_s), tuple(float(v) for v in at_pose)))
        table = volumetric.with_gains(raw, st.drive_gains, nut)
        table, moved = volumetric.table_step(table, st.written_table, ctx.cfg.max_step_um)
    except VolumetricError as exc:  # a model gone non-finite: the one-pose offsets, the last table held
        if not st.nonfinite_logged:
            st = evolve(st, nonfinite_logged=True)
            out.event("warning", r.time_s, {"message": f"the support-point table cannot be built ({exc}); the "
                                            "offsets at the model's pose are written"}, f"table@{_t(r.time_s)}")
        return st, Offset(r.time_s, *at_pose, active, clamped, limited, outside, degraded, by)
    dx, dy, dz = interpolate_one(table, r.position_mm)
    return evolve(st, written_table=table), Offset(
        r.time_s, dx, dy, dz, active, clamped, limited or moved, outside, degraded, by,
        position_mm=tuple(float(v) for v in r.position_mm), pose_um=at_pose, table=table)


def _compensate_from_grid(ctx: Context, st: State, r: Reading, at_pose: tuple, active: str, clamped: bool,
                          limited: bool, outside: bool, degraded: str, by: str, out: _Out) -> tuple[State, Offset]:
    """The support-point table of the active CD grid at the sensors and the offsets it gives at the commanded position.

    Without a pose-aware model: every point's CD set on the low-passed sensors (:meth:`CDGrid.table
    <hybridcomp.chardiag.grid.CDGrid.table>`), each entry rate limited against the last table (carried onto this
    grid's points when the grid changed), interpolated at the reading's position.  A grid that cannot be evaluated
    (a missing sensor, a non-finite value): the offsets at the model's pose, the last table held, one warning.
    """
    from hybridcomp.rom.volumetric import interpolate_one

    grid = st.grid
    try:
        table, grid_outside = grid.table(st.saved.filtered_degC, r.time_s)
        old = volumetric.on_grid(st.written_table, table.grid)
        table, moved = volumetric.table_step(table, old, ctx.cfg.max_step_um)
    except (KeyError, ValueError) as exc:  # VolumetricError and CDError are ValueErrors
        if not st.nonfinite_logged:
            st = evolve(st, nonfinite_logged=True)
            out.event("warning", r.time_s, {"message": f"the CD grid {grid.grid_id} cannot give a support-point table "
                                            f"({type(exc).__name__}: {exc}); the offsets at the model's pose are "
                                            "written"}, f"grid@{_t(r.time_s)}")
        return st, Offset(r.time_s, *at_pose, active, clamped, limited, outside, degraded, by)
    dx, dy, dz = interpolate_one(table, r.position_mm)
    return evolve(st, written_table=table), Offset(
        r.time_s, dx, dy, dz, active, clamped, limited or moved, outside or grid_outside, degraded,
        "cd-grid", position_mm=tuple(float(v) for v in r.position_mm), pose_um=at_pose, table=table)


# ============================================================================================ monitoring
def on_interval(ctx: Context, st: State, boundary_s: float, stored_sets: StoredSets = no_stored_sets) -> Step:
    """The monitoring decision at a boundary, then the next interval; the boundary's state is to be persisted.

    ``stored_sets``: the stored sets the decision may switch to (read only when the active set does not fit).
    """
    out = _Out()
    return out.step(_close_interval(ctx, st, boundary_s, stored_sets, out))


def _close_interval(ctx: Context, st: State, boundary: float, stored_sets: StoredSets, out: _Out) -> State:
    st = _monitor(ctx, st, boundary, stored_sets, out)
    s = st.saved
    if any(s.interval_drops.values()):
        out.event("time", boundary, {"message": "samples dropped for repeated, backward, implausible or invalid time "
                                     "stamps", **s.interval_drops}, _t(boundary))
        st = _set(st, interval_drops=dict(NO_DROPS))
    st = _set(st, interval=st.saved.interval[-1:],  # the boundary row opens the next interval
              signature_sum=None, signature_s=0.0, rejected={},
              next_mon_s=boundary + ctx.cfg.monitoring_interval_s)
    st = counted(st, monitorings=1)
    if ctx.pose is not None:  # the pose-aware model's state, the last table and the drives' gains: persisted
        from hybridcomp.rom.volumetric import table_to_dict

        st = _set(st, pose_track=volumetric.state_out(st.track),
                  table=table_to_dict(st.written_table) if st.written_table is not None else None,
                  gains=st.drive_gains.as_dict())
    elif st.written_table is not None:  # a CD grid's table: a restart continues its rate limit
        from hybridcomp.rom.volumetric import table_to_dict

        st = _set(st, table=table_to_dict(st.written_table))
    out.command(Persist(st))
    return st


def set_predictions(cds, T_rows: np.ndarray, sensor_names, pose_mm: Mapping[str, float]) -> np.ndarray:
    """A CD set's offsets (n × 3: dx, dy, dz) [µm] on sensor rows [°C] at the pose's axis positions."""
    cols = {temperature_column(s): T_rows[:, j] for j, s in enumerate(sensor_names)}
    cols |= {position_column(a): np.full(len(T_rows), float(v)) for a, v in pose_mm.items()}
    return np.column_stack([cds[d].evaluate_table(cols)[0] for d in DIRECTIONS])


def _forecasts(ctx: Context, st: State) -> list[tuple[np.ndarray, np.ndarray]]:
    """Sensors and drift over the forecast horizon: the last hour's load continued, and a cool-down."""
    s = st.saved
    rows = [r[1:] for r in s.loads if r[0] > s.step_time_s - 3600.0] + [r[1:] for r in s.step_rows]
    u = np.mean(np.asarray(rows, float), axis=0) if rows else np.asarray(s.step_inputs, float)
    nh = len(ctx.layout.heat_inputs)
    cool = np.concatenate([np.zeros(nh), np.asarray(s.step_inputs, float)[nh:]])
    n = max(1, int(round(ctx.cfg.validity.forecast_h * 3600.0 / FORECAST_STEP_S)))
    return [ctx.observer.forecast(s.observer, np.tile(v, (n, 1)), FORECAST_STEP_S) for v in (u, cool)]


def _set_error(ctx: Context, cds, rows: np.ndarray, forecasts) -> SetError:
    ns = len(ctx.sensor_names)
    error = decisions.compensation_error_um
    interval = error(set_predictions(cds, rows[:, 1:1 + ns], ctx.sensor_names, ctx.pose_mm), rows[:, 1 + ns:])
    fc = max(error(set_predictions(cds, T, ctx.sensor_names, ctx.pose_mm), d) for T, d in forecasts)
    return SetError(interval, fc)


def _monitor(ctx: Context, st: State, boundary: float, stored_sets: StoredSets, out: _Out) -> State:
    cfg = ctx.cfg
    s = st.saved
    rows = np.asarray(s.interval, float)
    est = _estimate_degC(ctx, st)
    measured = {n: v for n, v in st.measured.items() if math.isfinite(v) and s.sensors[n].status == "ok"}
    drifted, drift_K, drift_sensor = decisions.model_drift(est, measured, cfg.model_drift_K)
    st = _set(st, max_residual_K=_finite(drift_K))
    st = _flag(ctx, st, boundary, drifted, drift_K, drift_sensor, out)
    if drifted or s.rejected:
        out.event("model_drift", boundary, {
            "max_abs_K": _finite(drift_K), "sensor": drift_sensor, "threshold_K": cfg.model_drift_K,
            "rejected": dict(s.rejected), "estimate_degC": est, "measured_degC": measured,
            "disturbances": ctx.observer.disturbances(s.observer),
        }, _t(boundary))
    forecasts = _forecasts(ctx, st)
    error = None
    if st.active is not None:
        try:
            error = _set_error(ctx, st.active.cds, rows, forecasts)
        except (KeyError, ValueError) as exc:
            out.log("warning", f"the active set cannot be assessed: {exc}")
    t_ref = st.active.t_reference_degC if st.active is not None else {}
    dT, dT_sensor = decisions.temperature_deviation(est, t_ref) if st.active is not None else (math.inf, None)
    v = cfg.validity
    enabled = cfg.regeneration.enabled and boundary >= s.regen_blocked_until_s and ctx.dataonly is None
    why = ("strategy 'dataonly' compensates without CDs: none is generated" if ctx.dataonly is not None else
           "regeneration is disabled" if not cfg.regeneration.enabled else
           f"no generation before {s.regen_blocked_until_s:.0f} s after a failed one")
    # a generation job runs exactly while its request is pending (submitted with it, finished with it cleared); one
    # job at a time: a CD grid's generation holds a set's back
    running = s.pending is not None or s.grid_pending is not None
    since = boundary - s.activated_s
    d = decisions.decide(s.active_ids, error, since, v, [], enabled, running, why)
    candidates: list[Candidate] = []
    sets: dict = {}
    sig = None if s.signature_sum is None else [float(x) / s.signature_s for x in s.signature_sum]
    if d.action != "keep" and v.max_candidates:
        candidates, sets = _candidates(ctx, st, rows, forecasts, est, stored_sets, out)
        d = decisions.decide(s.active_ids, error, since, v, candidates, enabled, running, why)
    payload = {
        "action": d.action, "reason": d.reason, "error_um": None if error is None else error.as_dict(),
        "active": s.active_ids, "candidates": len(candidates),
        "target": None if d.target is None else {"ids": dict(d.target.ids), "load_case": d.target.load_case,
                                                 "error_um": d.target.error.as_dict(), "jump_um": d.target.jump_um},
        "delta_T_K": _finite(dT), "sensor": dT_sensor, "threshold_K": cfg.threshold_K,
        "T_actual_degC": est, "T_reference_degC": t_ref, "drift_um": dict(zip(DRIFT_COLUMNS, s.drift_um)),
        "model_drift_K": _finite(drift_K), "signature": None if sig is None else [round(x, 6) for x in sig],
    }
    out.event("decision", boundary, payload, _t(boundary))
    st = _set(st, last_decision={"time_s": boundary, "action": d.action, "reason": d.reason},
              last_error=None if error is None else error.as_dict(), last_delta_T_K=_finite(dT))
    out.log("info", f"t = {boundary:.0f} s: {d.action} ({d.reason})")
    st = fail_safe(ctx, st, d, boundary, out)
    return _act(ctx, st, d, boundary, est, sig, sets, out)


def fail_safe(ctx: Context, st: State, d: Decision, t: float, out: _Out) -> State:
    """Enter or leave the fail-safe: a set the decision calls wrong is never applied.

    The active set is known to be wrong when its predicted error over the last interval exceeds
    ``[validity] reject_um`` and the decision does not switch to a stored set that fits. Then, until another set is
    activated (a stored one, a generated one, or one the operator activates) or a decision finds the active set within
    ``reject_um`` again, :func:`_compensate` does not evaluate the set: the offsets written last are held and move at
    most ``max_step_um`` per cycle (the rate limit) toward the corrected structure model's drift, or toward zero while
    that model is flagged or has no estimate. A ``failsafe`` event says when it starts and ends.

    Why the observer's drift and not zero: it is the yardstick the decision judged the set by (the set is wrong
    *because* it departs from it), it is corrected by the sensors every model step, and on the demonstrator's day it
    follows the drift to 0.20 µm RMS where no compensation leaves 34 µm peak to peak; zero is the target only when
    the model itself is not trusted (flagged: it departs from the sensors), when nothing better is known. Why a ramp
    and not a jump: the offsets written last are what the machine is cutting with; the rate limit keeps the path
    continuous (0.2 µm per 5 s cycle by default) whichever target is right.
    """
    s = st.saved
    v = ctx.cfg.validity
    error = d.error
    bad = s.active_ids is not None and error is not None and d.action != "switch" and error.interval_um > v.reject_um
    if bad and not s.failsafe:
        toward = "zero (the structure model is flagged)" if s.observer_flag else "the corrected structure model's drift"
        ids = ",".join(f"{k}={s.active_ids[k]}" for k in sorted(s.active_ids))
        msg = (f"the active set {ids} is predicted {error.interval_um:.2f} µm off, beyond reject_um = {v.reject_um:g} µm, "
               f"and no stored set fits: it is not applied; the offsets are held and move at most "
               f"{ctx.cfg.max_step_um:g} µm per cycle toward {toward}")
        out.event("failsafe", t, {"status": "entered", "active": dict(s.active_ids), "error_um": error.as_dict(),
                                  "reject_um": v.reject_um, "action": d.action, "message": msg}, f"{_t(t)}@entered")
        out.log("error", msg)
        return _set(st, failsafe=msg)
    if s.failsafe and not bad and d.action != "switch" and error is not None:
        return _leave_fail_safe(st, t, f"the active set is predicted {error.interval_um:.2f} µm off, within "
                                f"reject_um = {v.reject_um:g} µm: applied again", out)
    return st


def _leave_fail_safe(st: State, t: float | None, why: str, out: _Out) -> State:
    out.event("failsafe", t, {"status": "left", "message": why}, f"{_t(t) if t is not None else 'start'}@left")
    out.log("warning", why)
    return _set(st, failsafe="")


def _flag(ctx: Context, st: State, t: float, drifted: bool, drift_K: float, sensor: str | None, out: _Out) -> State:
    """The observer is flagged while it departs from the sensors or half of them are degraded."""
    s = st.saved
    degraded = [n for n in ctx.sensor_names if s.sensors[n].status == "degraded"]
    reason = ""
    if drifted:
        reason = f"|estimate − measured| {drift_K:.2f} K at {sensor} above {ctx.cfg.model_drift_K:g} K"
    elif 2 * len(degraded) >= len(ctx.sensor_names):
        reason = f"{len(degraded)} of {len(ctx.sensor_names)} sensors degraded"
    if reason == s.observer_flag:
        return st
    out.event("observer", t, {"status": "flagged" if reason else "ok", "reason": reason}, _t(t))
    return _set(st, observer_flag=reason)


def _candidates(ctx: Context, st: State, rows: np.ndarray, forecasts, est: Mapping[str, float],
                stored_sets: StoredSets, out: _Out) -> tuple[list[Candidate], dict]:
    """Stored sets (best by signature, then ΔT) with their predicted errors and their jumps now.

    Returns the candidates and their CDs by :func:`_ids_key`.
    """
    s = st.saved
    sig = None if s.signature_sum is None else np.asarray(s.signature_sum, float) / s.signature_s
    found, sets = [], {}
    now = np.array([[s.filtered_degC.get(n, math.nan) for n in ctx.sensor_names]])
    for m in stored_sets(SetQuery(sig, est, s.active_ids)):
        ids = {k: int(v) for k, v in m.ids.items()}
        if ids == s.active_ids:
            continue
        try:
            if m.cds is None:
                raise ValueError(m.error)
            cds = {d: m.cds[d] for d in DIRECTIONS}
            err = _set_error(ctx, cds, rows, forecasts)
            jump = float(np.max(np.abs(set_predictions(cds, now, ctx.sensor_names, ctx.pose_mm)[0]
                                       - np.array([s.offsets_um[c] for c in DRIFT_COLUMNS]))))
        except (KeyError, ValueError) as exc:
            out.log("info", f"stored set {ids} cannot be assessed: {exc}")
            continue
        found.append(Candidate(ids, m.load_case, err, jump, float(m.delta_T_K)))
        sets[_ids_key(ids)] = cds
        if len(found) >= ctx.cfg.validity.max_candidates:
            break
    return found, sets


def _ids_key(ids: Mapping[str, int]) -> tuple:
    return tuple(sorted((k, int(v)) for k, v in ids.items()))


def _act(ctx: Context, st: State, d: Decision, t: float, est: Mapping[str, float], sig, sets: dict,
         out: _Out) -> State:
    if d.action == "switch":
        ids = {k: int(v) for k, v in d.target.ids.items()}
        return _activate(ctx, st, CDSet(sets[_ids_key(ids)], ids), f"switch: {d.reason}", t, out)
    if d.action == "regenerate":
        req = _request(ctx, st, t, est, sig)
        out.command(Request(req))
        out.event("generation", t, {"status": "started", "request": _brief(req)}, f"{_t(t)}@started")
        return _set(st, pending=req)
    if d.action == "warn":
        out.event("warning", t, {"message": d.reason}, f"decision@{_t(t)}")
    return st


def _request(ctx: Context, st: State, t: float, est: Mapping[str, float], sig) -> dict:
    """The generation request of a decision at ``t`` (:class:`~hybridcomp.monitor.regeneration.RegenerationRequest`)."""
    cfg = ctx.cfg
    s = st.saved
    ns = len(ctx.sensor_names)
    H = np.asarray(s.history, float).reshape(-1, 1 + ns + 3)
    L = np.asarray(s.loads, float).reshape(-1, 1 + ctx.layout.n_inputs)
    return RegenerationRequest(
        machine=cfg.machine, pose_key=ctx.pose_key, pose_mm=dict(ctx.pose_mm), database=cfg.database,
        machine_time_s=t, t_reference_degC=dict(est), signature=sig, rom=str(cfg.rom),
        observer=dataclasses.asdict(cfg.observer), observer_x=[float(v) for v in s.observer.x],
        history_time_s=H[:, 0].tolist(), history_degC=H[:, 1:1 + ns].tolist(), history_drift_um=H[:, 1 + ns:].tolist(),
        loads_names=list(ctx.layout.columns), loads_time_s=L[:, 0].tolist(), loads_inputs=L[:, 1:].tolist(),
        anchor_degC={n: float(s.filtered_degC[n]) for n in ctx.sensor_names},
        anchor_um=dict(s.offsets_um), forecast_h=cfg.validity.forecast_h, bump_um=cfg.validity.bump_um,
        reference_temperature_degC=ctx.t_ref, element_size_mm=cfg.regeneration.element_size_mm,
    ).to_dict()


# ============================================================================================ activation, generation
def on_activate(ctx: Context, st: State, new: CDSet, reason: str, t: float | None) -> Step:
    """Make ``new`` the active set at machine time ``t`` (nothing happens when it already is).

    Raises ValueError when the set is for another machine or pose.
    """
    out = _Out()
    return out.step(_activate(ctx, st, new, reason, t, out))


def _activate(ctx: Context, st: State, new: CDSet | None, reason: str, t: float | None, out: _Out) -> State:
    ids = {k: int(v) for k, v in new.ids.items()} if new is not None else None
    if new is None or st.saved.active_ids == ids:
        return st
    if (new.machine, new.pose_key) != (ctx.machine.name, ctx.pose_key):
        raise ValueError(f"CD set {ids} is for {new.machine} {new.pose_key}, not {ctx.machine.name} {ctx.pose_key}")
    out.command(Activate(ids, reason, t))
    if st.saved.failsafe:
        st = _leave_fail_safe(st, t, f"set {ids} activated ({reason}): the fail-safe ends", out)
    had_set = st.active is not None
    st = _set(st, active_ids=dict(ids), activated_s=t, blend_pending=had_set and ctx.cfg.blend_s > 0)
    return counted(evolve(st, active=new, eval_failed_logged=False), switches=1)


def on_regeneration_finished(ctx: Context, st: State, request: Mapping, result: Mapping | None, error: str | None,
                             status: str, new: CDSet | None = None, load_error: str | None = None) -> Step:
    """The outcome of a generation job; its set becomes active when it succeeded.

    Parameters
    ----------
    request : the job's request
    result, error, status : its result (the new set's ``ids``), error, and ``finished``, ``failed`` or ``timeout``
    new : the result's set as the daemon loaded it (None when it is the active one already, or could not be loaded)
    load_error : why it could not be loaded, or None
    """
    out = _Out()
    s = st.saved
    t = float(request["machine_time_s"])
    if status == "finished" and result is not None:
        ids = {k: int(v) for k, v in result["ids"].items()}
        out.event("generation", t, {"status": "finished", "ids": ids, "load_case": result.get("load_case", ""),
                                    "wall_s": result.get("wall_s"), "notes": result.get("notes") or {}},
                  f"{_t(t)}@finished")
        st = counted(st, generations=1)
        if load_error is None:
            try:
                st = _activate(ctx, st, new, f"generated for the load case at {t:.0f} s", s.last_time_s, out)
            except ValueError as exc:
                load_error = f"{type(exc).__name__}: {exc}"
        if load_error is not None:
            out.event("generation", t, {"status": "activation_failed", "ids": ids, "error": load_error},
                      f"{_t(t)}@activation_failed")
            out.log("error", f"generated set {ids} for {t:.0f} s cannot be activated: {load_error}")
    else:
        st = _job_failed(ctx, st, out, t, "generation", status, error, "regen_blocked_until_s", "generation job")
    st = _set(st, pending=None)
    out.command(Persist(None))
    return out.step(st)


def _job_failed(ctx: Context, st: State, out, t: float, kind: str, status: str, error, blocked: str,
                what: str) -> State:
    """A generation job that did not finish: its event, a warning, and no other job of its kind for a while.

    ``blocked``: the state's field that holds when the next may start.
    """
    out.event(kind, t, {"status": status, "error": error}, f"{_t(t)}@{status}")
    out.log("warning", f"{what} for {t:.0f} s {status}: {error}")
    return _set(st, **{blocked: (st.saved.last_time_s or t) + ctx.cfg.regeneration.retry_after_s})


# ============================================================================================ CD grids
@dataclass(frozen=True)
class ActivateGrid:
    """Record in the database that CD grid ``grid_id`` became the machine's active grid at ``t``.

    The state already has it; ``t`` is machine time [s].
    """

    grid_id: int
    reason: str
    t: float | None


def grid_temperatures(ctx: Context, st: State) -> dict[str, float]:
    """What a grid decision compares the grids' reference temperatures with: the structure model's sensors now [°C]."""
    return _estimate_degC(ctx, st)


def decides_grids(ctx: Context, st: State) -> bool:
    """Whether a monitoring boundary has a CD grid decision.

    A one-pose model (not strategy ``dataonly``) with an active grid, or one that may generate grids
    (``compensation.grid_rom``).
    """
    return ctx.pose is None and ctx.dataonly is None and (st.grid is not None or ctx.cfg.grid_rom is not None)


def on_grid_decision(ctx: Context, st: State, t: float, temperatures_degC: Mapping[str, float],
                     candidates: Iterable) -> Step:
    """At a monitoring boundary, without a pose-aware model: keep the active CD grid, switch to a stored one, generate.

    The active grid is kept while its sets' reference temperatures are within ``threshold_K`` of
    ``temperatures_degC`` (the structure model's sensors, :func:`grid_temperatures`; max over the sets and the
    common sensors).  Otherwise the first of ``candidates`` (stored CD grids,
    best first: the database's :meth:`~hybridcomp.chardiag.db.CDDatabase.search_grids`, read lazily by the shell)
    that is another grid and fits within ``threshold_K`` becomes active: a ``grid switch`` event and an
    :class:`ActivateGrid` command; the table's rate limit carries the change over.  None fitting: with
    ``compensation.grid_rom`` a grid generation (a :class:`Request` whose request carries ``grid``, a ``grid
    generation`` event, the request pending in ``grid_pending``) when generation is enabled, not blocked after a
    failed one and no job runs; else one ``grid decision`` event saying why, the active grid kept.  Without an active
    grid the same order applies when grids may be generated (a stored grid, else a generation); otherwise, and with a
    pose-aware model, nothing.
    """
    out = _Out()
    active = st.grid
    if not decides_grids(ctx, st) or not temperatures_degC:
        return out.step(st)
    limit = ctx.cfg.threshold_K
    dT = active.delta_T_K(temperatures_degC) if active is not None else math.inf
    if dT <= limit:
        return out.step(st)
    why_active = (f"grid {active.grid_id}'s reference temperatures are {dT:.2f} K off (> {limit:g} K)"
                  if active is not None else "no CD grid is active")
    for g in candidates:
        if active is not None and g.grid_id == active.grid_id:
            continue
        d = g.delta_T_K(temperatures_degC)
        if d <= limit:
            out.event("grid switch", t, {"from": None if active is None else active.grid_id, "to": g.grid_id,
                                         "delta_T_K": _finite(dT), "new_delta_T_K": _finite(d),
                                         "load_case": g.load_case, "reason": why_active}, f"{_t(t)}@{g.grid_id}")
            out.command(ActivateGrid(int(g.grid_id), why_active, t))
            return out.step(evolve(st, grid=g))
    s = st.saved
    cfg = ctx.cfg
    why = ("compensation.grid_rom is not set: the daemon does not generate grids" if cfg.grid_rom is None else
           "regeneration is disabled" if not cfg.regeneration.enabled else
           f"no grid generation before {s.grid_blocked_until_s:.0f} s after a failed one"
           if t < s.grid_blocked_until_s else
           "a grid generation is running" if s.grid_pending is not None else
           "a set generation is running: the grid waits for the next boundary" if s.pending is not None else
           "no load history yet: the grid waits for the next boundary" if not s.loads else "")
    if not why:
        req = grid_request(ctx, st, t, temperatures_degC)
        out.command(Request(req))
        out.event("grid generation", t, {"status": "started", "reason": f"{why_active} and no stored grid fits",
                                         "request": _brief(req) | {"points": req["grid"]["points"]}},
                  f"{_t(t)}@started")
        out.command(Persist(None))
        return out.step(_set(st, grid_pending=req))
    kept = "kept" if active is not None else "none active"
    out.event("grid decision", t, {"grid": None if active is None else active.grid_id, "delta_T_K": _finite(dT),
                                   "message": f"{why_active} and no stored grid fits better: {kept} ({why})"}, _t(t))
    return out.step(st)


def grid_request(ctx: Context, st: State, t: float, temperatures_degC: Mapping[str, float]) -> dict:
    """The request of a CD grid generation at ``t``.

    The set generation's request (the corrected structure model's history and state) with ``grid`` = the pose-aware
    model that trains it (``compensation.grid_rom``), the support points per axis (``compensation.table_points``) and
    the job (:func:`hybridcomp.monitor.regeneration.grid_job`).
    """
    from hybridcomp.monitor.regeneration import GRID_JOB

    req = _request(ctx, st, t, temperatures_degC, None)
    return req | {"grid": {"rom": str(ctx.cfg.grid_rom), "points": int(ctx.cfg.table_points), "job": GRID_JOB}}


def on_grid_generation_finished(ctx: Context, st: State, request: Mapping, result: Mapping | None,
                                error: str | None, status: str, grid=None, load_error: str | None = None) -> Step:
    """The outcome of a CD grid generation; its grid becomes the active grid when it succeeded.

    Parameters
    ----------
    request : the job's request
    result, error, status : its result (the new grid's ``grid_id``), error, and ``finished``, ``failed`` or
        ``timeout``
    grid : the result's grid as the daemon loaded it (:class:`hybridcomp.chardiag.grid.CDGrid`; None when it could
        not be loaded)
    load_error : why it could not be loaded, or None

    A failure never touches the active grid; no grid generation starts for ``regeneration.retry_after_s`` after it.
    """
    out = _Out()
    s = st.saved
    t = float(request["machine_time_s"])
    if status == "finished" and result is not None:
        gid = int(result["grid_id"])
        out.event("grid generation", t, {"status": "finished", "grid": gid, "load_case": result.get("load_case", ""),
                                         "wall_s": result.get("wall_s"), "notes": result.get("notes") or {}},
                  f"{_t(t)}@finished")
        st = counted(st, generations=1)
        if load_error is None and (grid is None or grid.machine != ctx.machine.name):
            load_error = f"grid {gid} is for {None if grid is None else grid.machine}, not {ctx.machine.name}"
        if load_error is None:
            if st.grid is None or st.grid.grid_id != gid:
                reason = f"generated for the state at {t:.0f} s"
                out.command(ActivateGrid(gid, reason, s.last_time_s))
                st = with_active_grid(ctx, st, grid)
        else:
            out.event("grid generation", t, {"status": "activation_failed", "grid": gid, "error": load_error},
                      f"{_t(t)}@activation_failed")
            out.log("error", f"generated CD grid {gid} for {t:.0f} s cannot be activated: {load_error}")
    else:
        st = _job_failed(ctx, st, out, t, "grid generation", status, error, "grid_blocked_until_s",
                         "CD grid generation")
    st = _set(st, grid_pending=None)
    out.command(Persist(None))
    return out.step(st)


# ============================================================================================ small helpers
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def histogram_warning_key(end_s: float, message: str) -> str:
    """The event key of a histogram warning of the model step ending at ``end_s``: one per step and kind of warning.

    The kind is the message with its numbers taken out: the step's samples after a restart (a live source does not
    send the ones before it again) may give the same warning with other counts and lines, and it is one warning.
    """
    return f"histogram@{_t(end_s)}@{digest(_NUMBER.sub('#', message))}"


def digest(text: str) -> str:
    """A short stable digest (the same in every process, unlike ``hash()``)."""
    import hashlib

    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _probe_at_pose(st: State, probe_um: list | None) -> list | None:
    """The step's probes at the model's pose as the observer takes them: less the drives' gains' share there.

    The probes were taken less the drives' errors of the table without gains (:func:`_probe`); their gains' share
    at the model's pose goes with the gains as they are at the step's end, after the whole probing cycle: a cycle
    that starts at the model's pose and then teaches the gains elsewhere would otherwise leave the observer with the
    gains before it until the next cycle, while the table has the new ones.
    """
    if probe_um is None or st.raw_table is None or st.drive_gains is None:
        return probe_um
    share = volumetric.gain_share_at_pose(st.raw_table, st.drive_gains, st.raw_nut_table)
    return [float(v) - float(d) for v, d in zip(probe_um, share)]


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
