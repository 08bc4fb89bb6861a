"""The monitor's TOML configuration: typed, validated, every key checked.

A misspelt key is an error with a did-you-mean hint, never silently ignored.
Relative paths are relative to the configuration file. See ``monitor/README.md``
for an annotated example; :func:`example_config` writes one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from dataclasses import fields as dataclass_fields
from pathlib import Path

from hybridcomp.errors import HybridcompError
from hybridcomp.histogram.increments import DEFAULT_MAX_GAP_S
from hybridcomp.models.layout import DRIFT_COLUMNS
from hybridcomp.models.toml import StrictTable, did_you_mean, read_toml
from hybridcomp.monitor.decisions import Backoff, SensorRules, TimeRules, Validity
from hybridcomp.rom.observer import BOUND_SETTINGS, ObserverError, ObserverSettings


class ConfigError(HybridcompError, ValueError):
    """The monitor configuration is invalid; the message names the file, the key and the value."""


@dataclass(frozen=True)
class SourceConfig:
    """Where the machine data comes from.

    Attributes
    ----------
    kind : ``"replay"`` (a trace CSV) or ``"opcua"`` (an OPC UA server of the machine control)
    path : trace CSV to replay
    speed : replay time acceleration [-] (machine seconds per wall second; 0: as fast as possible)
    start_s : skip samples before this machine time [s]
    url : OPC UA endpoint, e.g. ``opc.tcp://127.0.0.1:4840``
    nodes : trace column -> OPC UA node id (``time_s``, ``x_mm`` ..., ``spindle_rpm``, ``T1_degC`` ..., ``Tamb_degC``)
    publishing_interval_ms : OPC UA subscription publishing interval [ms]
    stale_s : no sample for this long (wall time) means the connection is checked [s]
    """

    kind: str = "replay"
    path: Path | None = None
    speed: float = 1.0
    start_s: float = -math.inf
    url: str = ""
    nodes: Mapping[str, str] = field(default_factory=dict)
    publishing_interval_ms: float = 100.0
    stale_s: float = 5.0


@dataclass(frozen=True)
class SinkConfig:
    """Where the compensation offsets go.

    Attributes
    ----------
    kind : ``"jsonl"``, ``"csv"``, ``"opcua"`` or ``"none"``
    path : output file (jsonl, csv)
    url : OPC UA endpoint (opcua)
    nodes : ``dx_um``/``dy_um``/``dz_um`` -> node id to write (opcua)
    table_path : with a pose-aware structure model: the support-point table of every cycle, one JSON object a
        line (:func:`hybridcomp.rom.volumetric.table_to_dict`), for a control that interpolates it itself
    """

    kind: str = "jsonl"
    path: Path | None = None
    url: str = ""
    nodes: Mapping[str, str] = field(default_factory=dict)
    table_path: Path | None = None


@dataclass(frozen=True)
class RegenerationConfig:
    """The background generation of a new CD set.

    Attributes
    ----------
    enabled : whether the monitor may generate CD sets
    job : ``"module:function"`` called in a worker process with a :class:`~hybridcomp.monitor.regeneration.RegenerationRequest`
        (default: CDs trained on the corrected structure model; ``...:fe_job`` trains them on FE runs instead)
    timeout_s : wall-clock limit of one job [s]; a job over it is killed
    element_size_mm : FE element size for the FE job [mm]
    history_s : how much of the history (estimated states and loads) the job gets [s]
    retry_after_s : after a failed or timed-out job, no new one for this long [s of machine time]
    """

    enabled: bool = True
    job: str = "hybridcomp.monitor.regeneration:default_job"
    timeout_s: float = 3600.0
    element_size_mm: float = 80.0
    history_s: float = 16 * 3600.0
    retry_after_s: float = 3600.0


@dataclass(frozen=True)
class MonitorConfig:
    """The whole configuration (see the module docstring and ``monitor/README.md``).

    Attributes
    ----------
    machine : machine name or machine file
    pose_mm : pose of the CDs [mm] (default: the machine's default pose)
    database : CD database (path of an SQLite file or an SQLAlchemy URL)
    rom : reduced structure model file (``hybridcomp reduce``); a pose-aware one (``hybridcomp reduce --poses``)
        makes the daemon compensate where the tool is, writing a support-point table every cycle
        (:mod:`hybridcomp.monitor.volumetric`); one reduced at one pose compensates at the CDs' pose
    table_points : support points per axis of that table (over the travel; 3: ends and the model's pose)
    compensation_interval_s : compensation cycle in machine time [s]
    monitoring_interval_s : monitoring cycle in machine time [s]
    increment_s : histogram increment and step of the structure model and its observer [s] (the monitoring
        interval is a whole multiple of it)
    max_gap_s : samples farther apart than this are a recording gap, counted as standstill [s] (raise it for a
        source that delivers samples more sparsely, e.g. OPC UA with a long publishing interval)
    threshold_K : the seeds' test, reported with every decision: |T_actual − T_reference| of the active set [K]
    model_drift_K : |observer − measured| at a sensor above which a model-drift event is raised [K]
    strategy : ``"hybrid"`` (the active CD set on the measured sensors; the corrected structure model chooses
        and generates sets) or ``"observer"`` (the corrected structure model's drift itself, the CDs standing in
        while it is flagged) or ``"dataonly"`` (the data-only regularised model of ``dataonly_model``, its
        coefficients updated by the probes: :mod:`hybridcomp.monitor.dataonly_strategy`)
    dataonly_model : strategy ``dataonly``: the model file (``hybridcomp diagnose --data-only --probe-every-hours H
        --out DIR`` writes ``DIR/dataonly_model.json``); required for that strategy, refused for the others
    grid_rom : a pose-aware reduced model of the same machine (``hybridcomp reduce --poses``) used only to train the
        CD grids the daemon generates when its ``rom`` knows one pose and no stored grid fits (None: no grid is
        generated); checked when the configuration is read (:func:`read_grid_rom`)
    sensor_filter_s : time constant of the low-pass on the sensors the CDs read [s] (0: none)
    max_offset_um : largest compensation offset magnitude [µm]
    max_step_um : largest change of an offset per compensation cycle [µm]
    blend_s : after a change of the active set, what remains between the offsets written and the new set's
        prediction (a generated set continues them by construction) decays with this time constant [s]
    model_transient_s : hybrid strategy: crossover time constant of the complementary filter that takes what
        changes faster than this from the corrected structure model and the rest from the CDs (0: the CDs alone;
        while the model is flagged the CDs alone) [s]
    validity : when the active set is kept, replaced or regenerated (predicted compensation error in µm)
    observer : noise levels of the structure model's state observer
    sensors : plausibility rules for the temperature sensors
    time : plausibility of the machine's time stamps (largest plausible step, samples that confirm a new time line)
    lease_s : the daemon holds the machine's pose for this long and renews it every third of it; a second daemon
        on the same pose refuses to start (or waits with ``--standby``) while the lease is held [s of wall time]
    stale_after_s : ``monitor status`` reports unhealthy when no offset was applied for this long [s of wall time]
    source, sink, regeneration : see their classes
    reconnect : backoff schedule for a dropped data source or sink
    prometheus_port : serve Prometheus metrics on 127.0.0.1 at this port (0: off; needs prometheus_client, extra ``live``)
    source_file : the file the configuration was read from
    """

    machine: str
    database: str
    rom: Path
    pose_mm: Mapping[str, float] | None = None
    table_points: int = 3
    compensation_interval_s: float = 5.0
    monitoring_interval_s: float = 900.0
    increment_s: float = 20.0
    max_gap_s: float = DEFAULT_MAX_GAP_S
    threshold_K: float = 0.5
    model_drift_K: float = 1.0
    strategy: str = "hybrid"
    dataonly_model: Path | None = None
    grid_rom: Path | None = None
    sensor_filter_s: float = 20.0
    max_offset_um: float = 200.0
    max_step_um: float = 0.2
    blend_s: float = 0.0
    model_transient_s: float = 57600.0
    validity: Validity = field(default_factory=Validity)
    observer: ObserverSettings = field(default_factory=ObserverSettings)
    sensors: SensorRules = field(default_factory=SensorRules)
    time: TimeRules = field(default_factory=TimeRules)
    lease_s: float = 30.0
    stale_after_s: float = 20.0
    source: SourceConfig = field(default_factory=SourceConfig)
    sink: SinkConfig = field(default_factory=SinkConfig)
    regeneration: RegenerationConfig = field(default_factory=RegenerationConfig)
    reconnect: Backoff = field(default_factory=Backoff)
    prometheus_port: int = 0
    source_file: str = "<config>"


_MONITOR_KEYS = {
    "machine", "pose_mm", "database", "rom", "compensation_interval_s", "monitoring_interval_s", "increment_s",
    "threshold_K", "model_drift_K", "prometheus_port", "max_gap_s", "lease_s", "stale_after_s",
}
_SECTIONS = {
    "monitor": _MONITOR_KEYS,
    "compensation": {"strategy", "dataonly_model", "sensor_filter_s", "max_offset_um", "max_step_um", "blend_s",
                     "model_transient_s", "table_points", "grid_rom"},
    "validity": {f.name for f in dataclass_fields(Validity)},
    "observer": {f.name for f in dataclass_fields(ObserverSettings)},
    "sensors": {"hold_s", "frozen_s", "frozen_model_K", "spike_K", "spike_rate_K_s", "min_degC", "max_degC"},
    "time": {"max_step_s", "confirm_samples"},
    "source": {"kind", "path", "speed", "start_s", "url", "nodes", "publishing_interval_ms", "stale_s"},
    "sink": {"kind", "path", "url", "nodes", "table_path"},
    "regeneration": {"enabled", "job", "timeout_s", "element_size_mm", "history_s", "retry_after_s"},
    "reconnect": {"initial_s", "factor", "max_s", "jitter"},
}
SOURCE_KINDS = ("replay", "opcua")
STRATEGIES = ("hybrid", "observer", "dataonly")
SINK_KINDS = ("jsonl", "csv", "opcua", "none")


class _Reader(StrictTable):
    """One section of the configuration (its keys in :data:`_SECTIONS`)."""

    def __init__(self, src: str, section: str, table: Mapping):
        super().__init__(src, section, table, sorted(_SECTIONS[section]), ConfigError)

    def path(self, key, base: Path, default=None):
        """A path; a relative one is taken relative to ``base`` (the configuration file's folder)."""
        v = self.string(key, None)
        if v is None:
            return default
        p = Path(v)
        return p if p.is_absolute() else base / p


def _database_url(text: str, base: Path) -> str:
    if "://" in text:
        return text
    p = Path(text)
    return str(p if p.is_absolute() else base / p)


def parse_config(data: Mapping, source: str = "<config>", base_dir: Path | None = None) -> MonitorConfig:
    """Build a :class:`MonitorConfig` from parsed TOML, checking every key and value."""
    # resolved once, here: every path of the configuration leaves this function absolute, so no process that
    # receives it (a generation worker with another working directory) can join it to a folder a second time
    base = (Path(base_dir) if base_dir is not None else Path.cwd()).resolve()
    for sec in data:
        if sec not in _SECTIONS:
            raise ConfigError(f"{source}: unknown section [{sec}]{did_you_mean(sec, sorted(_SECTIONS))}")
    if "monitor" not in data:
        raise ConfigError(f"{source}: section [monitor] is missing (it needs machine, database and rom)")
    m = _Reader(source, "monitor", data["monitor"])
    for req in ("machine", "database", "rom"):
        if req not in m.t:
            raise ConfigError(f"{source}: monitor.{req} is missing")
    machine = m.string("machine", None)
    mp = base / machine
    if machine.endswith(".toml") and not Path(machine).is_absolute():
        machine = str(mp)
    comp = m.number("compensation_interval_s", 5.0, positive=True)
    mon = m.number("monitoring_interval_s", 900.0, positive=True)
    inc = m.number("increment_s", MonitorConfig.increment_s, positive=True)
    ratio = mon / inc
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ConfigError(f"{source}: monitor.monitoring_interval_s {mon:g} must be a whole multiple of "
                          f"monitor.increment_s {inc:g}")
    if comp > mon:
        raise ConfigError(f"{source}: monitor.compensation_interval_s {comp:g} is longer than "
                          f"monitor.monitoring_interval_s {mon:g}")
    pose = m.mapping("pose_mm", float) or None

    c = _Reader(source, "compensation", data.get("compensation", {}))
    v = _Reader(source, "validity", data.get("validity", {}))
    values = {f.name: v.number(f.name, f.default, nonneg=True) for f in dataclass_fields(Validity)}
    try:
        validity = Validity(**values)
    except ValueError as exc:
        raise ConfigError(f"{source}: [validity] {exc}") from None
    o = _Reader(source, "observer", data.get("observer", {}))
    try:
        # a lower bound of a disturbance (air_min_K, scale_min, heat_min_W) is ≤ 0; ObserverSettings checks it
        observer = ObserverSettings(**{f.name: o.number(f.name, f.default,
                                                        nonneg=f.name not in BOUND_SETTINGS.values())
                                       for f in dataclass_fields(ObserverSettings)})
    except ObserverError as exc:
        raise ConfigError(f"{source}: [observer] {exc}") from None
    s = _Reader(source, "sensors", data.get("sensors", {}))
    d = SensorRules()
    try:
        rules = SensorRules(
            hold_s=s.number("hold_s", d.hold_s, nonneg=True),
            frozen_s=s.number("frozen_s", d.frozen_s, nonneg=True),
            frozen_model_K=s.number("frozen_model_K", d.frozen_model_K, nonneg=True),
            spike_K=s.number("spike_K", d.spike_K, positive=True),
            spike_rate_K_s=s.number("spike_rate_K_s", d.spike_rate_K_s, nonneg=True),
            min_degC=s.number("min_degC", d.min_degC),
            max_degC=s.number("max_degC", d.max_degC),
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: [sensors] {exc}") from None

    tm = _Reader(source, "time", data.get("time", {}))
    try:
        time_rules = TimeRules(tm.number("max_step_s", TimeRules.max_step_s, positive=True),
                               tm.number("confirm_samples", TimeRules.confirm_samples, positive=True, integer=True))
    except ValueError as exc:
        raise ConfigError(f"{source}: [time] {exc}") from None

    so = _Reader(source, "source", data.get("source", {}))
    kind = so.string("kind", "replay", SOURCE_KINDS)
    src = SourceConfig(
        kind=kind,
        path=so.path("path", base),
        speed=so.number("speed", 1.0, nonneg=True),
        start_s=so.number("start_s", -math.inf),
        url=so.string("url", ""),
        nodes=so.mapping("nodes"),
        publishing_interval_ms=so.number("publishing_interval_ms", 100.0, positive=True),
        stale_s=so.number("stale_s", 5.0, positive=True),
    )
    if kind == "replay" and src.path is None:
        raise ConfigError(f"{source}: source.path is missing (the trace CSV to replay)")
    if kind == "opcua":
        if not src.url:
            raise ConfigError(f"{source}: source.url is missing (the OPC UA endpoint)")
        if "time_s" not in src.nodes:
            raise ConfigError(f"{source}: source.nodes.time_s is missing (the node with the machine time)")

    si = _Reader(source, "sink", data.get("sink", {}))
    sink = SinkConfig(kind=si.string("kind", "jsonl", SINK_KINDS), path=si.path("path", base), url=si.string("url", ""),
                      nodes=si.mapping("nodes"), table_path=si.path("table_path", base))
    if sink.kind in ("jsonl", "csv") and sink.path is None:
        raise ConfigError(f"{source}: sink.path is missing (the {sink.kind} file for the offsets)")
    if sink.kind == "opcua" and not (sink.url and sink.nodes):
        raise ConfigError(f"{source}: sink.url and sink.nodes are needed for an OPC UA sink")
    bad = [k for k in sink.nodes if k not in DRIFT_COLUMNS]
    if bad:
        raise ConfigError(f"{source}: sink.nodes.{bad[0]} is not an offset ({', '.join(DRIFT_COLUMNS)})")

    r = _Reader(source, "regeneration", data.get("regeneration", {}))
    regen = RegenerationConfig(
        enabled=r.boolean("enabled", True),
        job=r.string("job", RegenerationConfig.job),
        timeout_s=r.number("timeout_s", RegenerationConfig.timeout_s, positive=True),
        element_size_mm=r.number("element_size_mm", RegenerationConfig.element_size_mm, positive=True),
        history_s=r.number("history_s", RegenerationConfig.history_s, positive=True),
        retry_after_s=r.number("retry_after_s", RegenerationConfig.retry_after_s, nonneg=True),
    )
    points = c.number("table_points", MonitorConfig.table_points, positive=True, integer=True)
    if points < 2:
        raise ConfigError(f"{source}: compensation.table_points = {points} must be at least 2 (the travel's ends)")
    if ":" not in regen.job:
        raise ConfigError(f"{source}: regeneration.job {regen.job!r} must be 'module:function'")

    b = _Reader(source, "reconnect", data.get("reconnect", {}))
    db = Backoff()
    try:
        backoff = Backoff(
            b.number("initial_s", db.initial_s, positive=True), b.number("factor", db.factor, positive=True),
            b.number("max_s", db.max_s, positive=True), b.number("jitter", db.jitter, nonneg=True),
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: [reconnect] {exc}") from None

    port = m.number("prometheus_port", 0, nonneg=True, integer=True)
    strategy = c.string("strategy", MonitorConfig.strategy, STRATEGIES)
    dataonly = c.path("dataonly_model", base)
    grid_rom = c.path("grid_rom", base)
    if grid_rom is not None and strategy == "dataonly":
        raise ConfigError(f"{source}: compensation.grid_rom = {str(grid_rom)!r} trains CD grids, which strategy "
                          "'dataonly' does not apply")
    if strategy == "dataonly":
        if dataonly is None:
            raise ConfigError(f"{source}: compensation.dataonly_model is missing (strategy 'dataonly' needs the model "
                              "file: hybridcomp diagnose --data-only --probe-every-hours H --out DIR writes "
                              "DIR/dataonly_model.json)")
        read_dataonly_model(dataonly, source)
    elif dataonly is not None:
        raise ConfigError(f"{source}: compensation.dataonly_model = {str(dataonly)!r} applies to strategy 'dataonly' "
                          f"only, not {strategy!r}")
    if grid_rom is not None:
        read_grid_rom(grid_rom, machine, source)
    return MonitorConfig(
        machine=machine,
        database=_database_url(m.string("database", None), base),
        rom=m.path("rom", base),
        pose_mm=pose,
        table_points=points,
        compensation_interval_s=comp,
        monitoring_interval_s=mon,
        increment_s=inc,
        max_gap_s=m.number("max_gap_s", DEFAULT_MAX_GAP_S, positive=True),
        threshold_K=m.number("threshold_K", 0.5, positive=True),
        model_drift_K=m.number("model_drift_K", 1.0, positive=True),
        strategy=strategy,
        dataonly_model=dataonly,
        grid_rom=grid_rom,
        sensor_filter_s=c.number("sensor_filter_s", MonitorConfig.sensor_filter_s, nonneg=True),
        max_offset_um=c.number("max_offset_um", 200.0, positive=True),
        max_step_um=c.number("max_step_um", MonitorConfig.max_step_um, positive=True),
        blend_s=c.number("blend_s", MonitorConfig.blend_s, nonneg=True),
        model_transient_s=c.number("model_transient_s", MonitorConfig.model_transient_s, nonneg=True),
        validity=validity,
        observer=observer,
        sensors=rules,
        time=time_rules,
        lease_s=m.number("lease_s", MonitorConfig.lease_s, positive=True),
        stale_after_s=m.number("stale_after_s", MonitorConfig.stale_after_s, positive=True),
        source=src,
        sink=sink,
        regeneration=regen,
        reconnect=backoff,
        prometheus_port=port,
        source_file=source,
    )


def read_dataonly_model(path: Path, source: str = "<config>"):
    """The data-only model of ``compensation.dataonly_model`` (:func:`~hybridcomp.rom.dataonly_model.model_from_json`).

    Raises
    ------
    ConfigError
        the file cannot be read or is no data-only model, a channel is no offset (``dx_um``, ``dy_um``, ``dz_um``),
        or a channel is driven by an activity other than ``spindle_rpm`` (the only one a sample carries); the
        message names the configuration, the key and the file.
    """
    from hybridcomp.rom.dataonly_model import model_from_json

    where = f"{source}: compensation.dataonly_model = {str(path)!r}"
    try:
        model = model_from_json(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{where}: cannot be read ({exc.strerror or exc})") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ConfigError(f"{where}: not a data-only model ({type(exc).__name__}: {exc})") from None
    for ch in model.channels:
        if ch.channel not in DRIFT_COLUMNS:
            raise ConfigError(f"{where}: channel {ch.channel!r} is not an offset ({', '.join(DRIFT_COLUMNS)})")
        if ch.signal not in (None, "spindle_rpm"):
            raise ConfigError(f"{where}: channel {ch.channel} is driven by {ch.signal!r}; the monitor's samples carry "
                              "spindle_rpm only")
    if not model.channels:
        raise ConfigError(f"{where}: the model has no channel")
    return model


def read_grid_rom(path: Path, machine: str, source: str = "<config>"):
    """The pose-aware reduced model of ``compensation.grid_rom``, checked against the configuration's machine.

    Raises
    ------
    ConfigError
        the file cannot be read or is no reduced model, it was reduced from another machine file, or it knows one
        pose only (no ``meta["poses"]``: it cannot give the drift at the grid's support points); the message names
        the configuration, the key and the file.
    """
    from hybridcomp.models import load_machine
    from hybridcomp.rom import load_rom
    from hybridcomp.rom.reduced import RomFileError

    where = f"{source}: compensation.grid_rom = {str(path)!r}"
    try:
        m = load_machine(machine)
    except Exception as exc:  # noqa: BLE001 - the machine's own error, named with the key that needs it
        raise ConfigError(f"{where}: machine {machine!r} (monitor.machine) cannot be loaded to check it: {exc}") from None
    try:
        rom = load_rom(path, m)
    except RomFileError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if not rom.meta.get("poses"):
        raise ConfigError(f"{where}: a reduced model of one pose; a CD grid needs the drift at every support point, "
                          "which a pose-aware model gives (hybridcomp reduce --poses star)")
    return rom


def load_config(path: str | Path) -> MonitorConfig:
    """Read and check a monitor TOML file."""
    path = Path(path)
    data, _ = read_toml(path, ConfigError)
    return parse_config(data, str(path), path.parent)


EXAMPLE = """\
# hybridcomp monitor configuration (hybridcomp monitor run --config monitor.toml)
[monitor]
machine = "vmc800"                 # bundled machine name or a machine file
database = "cds.sqlite"            # SQLite file or any SQLAlchemy URL (postgresql+psycopg://user:pw@host/db)
rom = "vmc800.rom.npz"             # hybridcomp reduce --machine vmc800 --out vmc800.rom.npz; reduced with
                                   # --poses star the daemon compensates where the tool is (a table every cycle)
compensation_interval_s = 5        # machine time between compensation cycles [s]
monitoring_interval_s = 900        # machine time between monitoring cycles [s]
increment_s = 20                   # histogram increment = step of the structure model and its observer [s]
max_gap_s = 10                     # samples farther apart are a recording gap (standstill) [s]
threshold_K = 0.5                  # the seeds' test, reported: |T_actual - T_reference| of the active set [K]
model_drift_K = 1.0                # |observer - measured| at a sensor that raises a model-drift event [K]
prometheus_port = 0                # 0: off; else Prometheus metrics on 127.0.0.1:port/metrics (extra live)
lease_s = 30                       # one daemon per machine and pose: it holds the pose this long, renewed [s]
stale_after_s = 20                 # 'monitor status' is unhealthy when no offset was applied this long [s]

[compensation]
strategy = "hybrid"                # "hybrid": CD tables on the sensors, chosen and generated by the corrected
                                   # structure model; "observer": that model's drift itself (CDs while it is flagged);
                                   # "dataonly": the data-only model of dataonly_model, updated by the probes
# dataonly_model = "dataonly_model.json"  # hybridcomp diagnose --data-only --probe-every-hours 4 --out DIR
sensor_filter_s = 20               # low-pass on the sensors the CDs read [s]
max_offset_um = 200                # offsets are clamped to this magnitude [um]
max_step_um = 0.2                  # and change by at most this much per compensation cycle [um]
blend_s = 0                        # after a change of CD set, what is left of a jump decays with this time constant [s]
                                   # (0: it is taken out at max_step_um per cycle)
model_transient_s = 57600          # hybrid: what changes faster than this comes from the corrected structure model,
                                   # the rest from the CDs (a complementary filter; 0: the CDs alone) [s]
table_points = 3                   # with a pose-aware rom: support points per axis of the table over the travel
# grid_rom = "vmc800.poses.npz"    # with a one-pose rom: a pose-aware model (reduce --poses star) of the same machine
                                   # that trains a CD grid when no stored grid fits (none: grids are not generated)

[validity]                         # the active set's predicted compensation error decides
keep_um = 1.5                      # keep while |CD(T) - drift| over the last interval stays below this [um]
forecast_um = 3.0                  # ... and below this over the forecasts (load continued, cool-down) [um]
hard_um = 3.0                      # above this over the last interval, act even within the dwell time [um]
dwell_s = 3600                     # after an activation, keep a set at least this long [s of machine time]
forecast_h = 3                     # forecast horizon [h]
bump_um = 1.0                      # a set that continues the offsets within this is made to continue them [um]
max_candidates = 8                 # stored sets evaluated per decision
reject_um = 50                     # a set predicted this far off is never applied: while no stored set fits, the
                                   # offsets are held and ramp (max_step_um) to the corrected model's drift [um]

[observer]                         # the Kalman filter that keeps the structure model on the machine
sensor_sigma_K = 0.15              # sensor noise including model error [K]
probe_sigma_um = 0.5               # noise of a probed drift (probe_dx_um ... columns of the trace) [um]
# air_sigma_K, air_rate_K, air_common, scale_sigma, scale_rate, heat_sigma_W, heat_rate_W, bias_sigma_um, bias_rate_um,
# input_sigma, initial_load, gate_sigma, probe_widen_sigma: see monitor/README.md
# admissible ranges of the estimates, held after each update: air_min_K, air_max_K (-3, 3) [K],
# scale_min, scale_max (-0.9, 3) [-], heat_min_W, heat_max_W (-100, 100) [W]

[sensors]
hold_s = 60                        # a bad reading is replaced by the last good value this long [s]
frozen_s = 1800                    # a reading unchanged this long is frozen [s] ...
frozen_model_K = 0.5               # ... or unchanged while the structure model moves it this much (0: off) [K]
spike_K = 2.0                      # a jump larger than this (plus spike_rate_K_s per second) is a spike [K]
spike_rate_K_s = 0.01
min_degC = -10                     # plausible range [degC]
max_degC = 80

[time]                             # plausibility of the machine's time stamps
max_step_s = 600                   # a sample farther ahead than this is suspect (dropped, with an event) ...
confirm_samples = 5                # ... until this many samples continue from it: a gap (the wall clock moved
                                   # as far) or the control's clock was set (the monitor's time continues)

[source]
kind = "replay"                    # or "opcua"
path = "jobshop_trace.csv"         # trace CSV (time_s, x_mm, y_mm, z_mm, spindle_rpm, T1_degC ..., Tamb_degC);
                                   # hybridcomp monitor example-trace --rom vmc800.rom.npz --out jobshop_trace.csv
speed = 0                          # machine seconds per wall second: 0 as fast as possible, 1 real time
                                   # (as a control sends it; 'monitor run --speed 1' overrides this)
# kind = "opcua"
# url = "opc.tcp://127.0.0.1:4840"
# nodes = { time_s = "ns=2;s=time_s", x_mm = "ns=2;s=x_mm", y_mm = "ns=2;s=y_mm", z_mm = "ns=2;s=z_mm",
#           spindle_rpm = "ns=2;s=spindle_rpm", T1_degC = "ns=2;s=T1_degC", Tamb_degC = "ns=2;s=Tamb_degC" }

[sink]
kind = "jsonl"                     # "jsonl", "csv", "opcua" or "none"
path = "offsets.jsonl"
# table_path = "tables.jsonl"      # with a pose-aware rom: the support-point table of every cycle

[regeneration]
enabled = true
job = "hybridcomp.monitor.regeneration:default_job"
timeout_s = 3600                   # wall-clock limit of one generation job [s]
element_size_mm = 80               # FE mesh of the FE job (job = "hybridcomp.monitor.regeneration:fe_job") [mm]
history_s = 57600                  # history (estimated states, loads) the job trains on [s]
retry_after_s = 3600               # after a failed or timed-out job, none for this long [s of machine time]

[reconnect]
initial_s = 0.5                    # first retry after [s], then x factor up to max_s
factor = 2.0
max_s = 30
jitter = 0.1
"""


def example_config(rom: str = "vmc800.rom.npz") -> str:
    """An annotated example configuration (TOML text) reading the structure model ``rom``."""
    if any(c in rom for c in '"\\\n'):
        raise ValueError(f"--rom {rom!r}: a file name without quotes, backslashes or line breaks, please")
    return EXAMPLE.replace('rom = "vmc800.rom.npz" ', f'rom = "{rom}" '.ljust(len('rom = "vmc800.rom.npz" ')), 1)
