"""What the daemon remembers between samples, as one dataclass with a derived JSON form.

:class:`MonitorState` is everything a restart needs; :meth:`MonitorState.to_json` and
:meth:`MonitorState.from_json` are derived from its fields (a field's type says how it is written), so a new
field is persisted by being declared. Floats that are ±inf or NaN are written as null and read back as the
field's default kind of missing (``-inf`` for the "next time" fields, NaN otherwise); arrays of the observer
are written bit-exactly (base64), so a restarted daemon makes the same decisions to the last bit.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

from hybridcomp.models import jsonio
from hybridcomp.monitor.dataonly_strategy import StrategyState, state_from_dict, state_to_dict
from hybridcomp.monitor.decisions import SensorState
from hybridcomp.monitor.sources import Reading
from hybridcomp.rom.observer import ObserverState

STATE_VERSION = 8
ZERO_OFFSETS = {"dx_um": 0.0, "dy_um": 0.0, "dz_um": 0.0}
NO_DROPS = {"repeated": 0, "backwards": 0, "jump": 0, "invalid": 0}


def _reading_out(r: Reading | None):
    if r is None:
        return None
    return [r.time_s, list(r.position_mm), r.spindle_rpm, dict(r.sensors_degC), dict(r.air_degC),
            None if r.probe_um is None else list(r.probe_um)]


def _reading_in(v) -> Reading | None:
    if v is None:
        return None
    t, p, rpm, sn, air, probe = v
    nan = lambda d: {k: (math.nan if x is None else x) for k, x in d.items()}  # noqa: E731
    return Reading(t, tuple(p), rpm, nan(sn), nan(air),
                   None if probe is None else tuple(math.nan if x is None else x for x in probe))


def _floats_in(d: dict | None) -> dict | None:
    return None if d is None else {k: (math.nan if v is None else v) for k, v in d.items()}


_FLOATS = (lambda d: d, _floats_in)

# field name -> (write, read) for the fields that are not plain JSON
_CODECS: dict[str, tuple[Any, Any]] = {
    **dict.fromkeys(("filtered_degC", "bias_K", "offsets_um", "blend_um", "air_hold", "complement_um"), _FLOATS),
    "observer": (lambda o: None if o is None else o.to_dict(), lambda v: None if v is None else ObserverState.from_dict(v)),
    "sensors": (lambda d: {k: s.to_dict() for k, s in d.items()}, lambda d: {k: SensorState.from_dict(s) for k, s in d.items()}),
    "carry": (_reading_out, _reading_in),
    "dataonly": (lambda s: None if s is None else state_to_dict(s), lambda v: None if v is None else state_from_dict(v)),
}


@dataclass(frozen=True)
class MonitorState:
    """The daemon's persisted state (machine times in seconds, temperatures in °C, offsets in µm).

    Frozen: the monitor's transitions (:mod:`hybridcomp.monitor.transitions`) replace it, and its containers, never
    change them in place.

    Attributes
    ----------
    version : :data:`STATE_VERSION` of the layout
    machine, pose_key, rom_id : what the state belongs to
    origin_s : machine time of the first sample; the cycles are counted from it
    last_time_s : machine time of the last accepted sample (in the monitor's time line: source time + ``time_offset_s``)
    last_source_time_s : the source's time stamp of that sample (a reconnect resumes after it)
    last_wall_unix : wall time when it was accepted [Unix s] (a jump ahead of the stamps is a gap if the wall
        clock moved as far)
    time_offset_s : monitor time − source time; changes when the control's clock is set (a confirmed new time line)
    time_candidates : source times of suspect samples (far ahead of or behind the time line) not yet confirmed
    next_comp_s, next_step_s, next_mon_s : the next compensation cycle, model step and monitoring boundary
    observer : the observer's estimate (None before the first sample)
    step_time_s : end of the last model step
    step_inputs : model inputs of the last step (powers [W], air rises [K])
    drift_um, drift_next_um : the estimated drift at the last step's end and one step ahead (observer strategy)
    sensors : plausibility state per sensor
    filtered_degC : the low-passed sensors the CDs read
    filter_time_s : time of the last filter update
    bias_K : measured − estimate per sensor when last good (stand-in of a degraded sensor)
    offsets_um : offsets written last
    written : whether any offset was written (the first one is not rate limited: there is none to continue)
    blend_um, blend_time_s, blend_pending : what remains of a jump at a set change, and since when
    complement_um, complement_time_s : the low-passed difference CD − structure model of the hybrid's complementary
        filter, and when it was updated
    carry : the last sample of the previous model step (continuity of the histogram)
    air_hold, pos_hold, spindle_hold : last finite air, positions, spindle speed
    probe_um : a probed drift waiting for the next model step (dx, dy, dz), or None (the mean of several probes
        within the step; with a pose-aware model each taken to the model's pose)
    probe_n : how many probes that mean holds
    history : rows ``[time_s, *sensors, dx, dy, dz]`` every history step: the sensors the CDs read and the
        estimated drift (the generation job trains on them)
    loads : rows ``[time_s, *inputs]``: mean model inputs over each history step
    step_rows : the current history step's model steps ``[time_s, *inputs]``
    interval : rows ``[time_s, *sensors, dx, dy, dz]`` of the current monitoring interval, per model step
    signature_sum, signature_s : time-weighted load-case signature of the current interval, and its weight
    pending : a generation request not yet finished
    regen_blocked_until_s : no new generation before this machine time
    grid_pending : a CD grid generation request not yet finished (without a pose-aware model, ``compensation.grid_rom``)
    grid_blocked_until_s : no new grid generation before this machine time (after a failed one)
    activated_s : machine time of the last activation
    last_decision, last_error, last_delta_T_K : the last monitoring decision, its predicted error, the seeds' ΔT
    observer_flag : why the observer is not trusted now ("" when it is)
    max_residual_K : the largest |measured − estimate| of the last interval
    rejected : sensors the observer's gate rejected in the current interval, with counts
    interval_drops : samples dropped in the current interval, by reason
    active_ids : the active set's ids (the database has the last word)
    pose_track : a pose-aware structure model's state at ``step_time_s`` (:func:`hybridcomp.monitor.volumetric.state_out`)
    table : the support-point table written last (:func:`hybridcomp.rom.volumetric.table_to_dict`)
    gains : the drives' gains learnt from probes at several positions (:class:`hybridcomp.monitor.volumetric.DriveGains`)
    failsafe : why the active set is not applied ("" when it is): its predicted error exceeded ``reject_um`` and no
        stored set fitted (:func:`hybridcomp.monitor.transitions.fail_safe`)
    dataonly : strategy ``dataonly``: the data-only model's state after the last sample (lags, coefficient filters:
        :class:`hybridcomp.monitor.dataonly_strategy.StrategyState`), None before the first sample and for the others
    """

    version: int = STATE_VERSION
    machine: str = ""
    pose_key: str = ""
    rom_id: str = ""
    origin_s: float | None = None
    last_time_s: float | None = None
    last_source_time_s: float | None = None
    last_wall_unix: float | None = None
    time_offset_s: float = 0.0
    time_candidates: list = field(default_factory=list)
    next_comp_s: float = -math.inf
    next_step_s: float = -math.inf
    next_mon_s: float = -math.inf
    observer: ObserverState | None = None
    step_time_s: float | None = None
    step_inputs: list | None = None
    drift_um: list | None = None
    drift_next_um: list | None = None
    sensors: dict = field(default_factory=dict)
    filtered_degC: dict = field(default_factory=dict)
    filter_time_s: float | None = None
    bias_K: dict = field(default_factory=dict)
    offsets_um: dict = field(default_factory=lambda: dict(ZERO_OFFSETS))
    written: bool = False
    blend_um: dict = field(default_factory=lambda: dict(ZERO_OFFSETS))
    blend_time_s: float | None = None
    blend_pending: bool = False
    complement_um: dict | None = None
    complement_time_s: float | None = None
    carry: Reading | None = None
    air_hold: dict = field(default_factory=dict)
    pos_hold: list = field(default_factory=list)
    spindle_hold: float = 0.0
    probe_um: list | None = None
    probe_n: int = 0
    history: list = field(default_factory=list)
    loads: list = field(default_factory=list)
    step_rows: list = field(default_factory=list)
    interval: list = field(default_factory=list)
    signature_sum: list | None = None
    signature_s: float = 0.0
    pending: dict | None = None
    regen_blocked_until_s: float = -math.inf
    grid_pending: dict | None = None
    grid_blocked_until_s: float = -math.inf
    activated_s: float = -math.inf
    last_decision: dict | None = None
    last_error: dict | None = None
    last_delta_T_K: float | None = None
    observer_flag: str = ""
    max_residual_K: float | None = None
    rejected: dict = field(default_factory=dict)
    interval_drops: dict = field(default_factory=lambda: dict(NO_DROPS))
    active_ids: dict | None = None
    pose_track: dict | None = None
    table: dict | None = None
    gains: dict | None = None
    failsafe: str = ""
    dataonly: StrategyState | None = None

    def to_dict(self) -> dict:
        """JSON-able (non-finite floats become null)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = _CODECS[f.name][0](v) if f.name in _CODECS else v
        return out

    def to_json(self) -> str:
        return jsonio.dumps(self.to_dict())

    @staticmethod
    def from_dict(d: dict) -> MonitorState:
        """The state of :meth:`to_dict`'s output; an unknown or missing field is an error."""
        names = {f.name: f for f in dataclasses.fields(MonitorState)}
        if set(d) != set(names):
            raise ValueError(f"monitor state: unknown {sorted(set(d) - set(names))}, missing {sorted(set(names) - set(d))}")
        kw = {}
        for name, f in names.items():
            v = d[name]
            if name in _CODECS:
                v = _CODECS[name][1](v)
            elif v is None and f.default is not dataclasses.MISSING and isinstance(f.default, float):
                v = f.default  # a non-finite float written as null
            kw[name] = v
        return MonitorState(**kw)

    @staticmethod
    def from_json(text: str) -> MonitorState:
        return MonitorState.from_dict(json.loads(text))
