"""Data sources of the monitor behind one interface, and the injected clock.

A source is an object with ``async readings(start_after_s)``, an async
iterator of :class:`Reading` in machine-time order (the daemon still checks
the order), that raises :class:`SourceDisconnected` when the connection to the
machine is lost; the daemon then reconnects with a backoff and calls
``readings`` again.

* :class:`ReplaySource` — a trace CSV replayed with a time acceleration (the default;
  demos, tests, the soak benchmark);
* :class:`OpcUaSource` — an OPC UA client (``asyncua``, extra ``opcua``) subscribed to
  the configured nodes of the machine control;
* :class:`ListSource` — readings from memory (tests).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import AsyncIterator, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from hybridcomp.errors import HybridcompError
from hybridcomp.histogram.trace import (
    DRIFT,
    SPINDLE_RPM,
    TIME,
    air_columns,
    position_column,
    velocity_column,
)
from hybridcomp.models.layout import PROBE_COLUMNS, temperature_column
from hybridcomp.models.machine import Machine
from hybridcomp.models.toml import open_regular_file

log = logging.getLogger(__name__)


class SourceDisconnected(ConnectionError):
    """The data source lost (or could not make) its connection; the daemon reconnects with a backoff."""


class SourceFileError(HybridcompError, ValueError):
    """A replay trace is unusable; the message names the file, line and column."""


@dataclass(frozen=True, slots=True)
class Reading:
    """One sample of the machine.

    Attributes
    ----------
    time_s : machine time [s]
    position_mm : axis positions in machine axis order [mm]
    spindle_rpm : spindle speed [1/min]
    sensors_degC : temperature sensors by name (``T1`` ...) [°C], NaN for a missing value
    air_degC : measured air by trace column (``Tamb_degC`` ...) [°C]
    probe_um : a drift measured at this time (dx, dy, dz; NaN for a direction not probed) [µm], or None
    """

    time_s: float
    position_mm: tuple[float, ...]
    spindle_rpm: float
    sensors_degC: Mapping[str, float]
    air_degC: Mapping[str, float]
    probe_um: tuple[float, float, float] | None = None


class WallClock:
    """The real clock: monotonic seconds, Unix time and asyncio sleep (tests inject their own)."""

    def monotonic(self) -> float:
        return time.monotonic()

    def unix(self) -> float:
        return time.time()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


@dataclass(frozen=True)
class TraceColumns:
    """Where the monitor's quantities are in a trace header."""

    time: int
    positions: tuple[int, ...]
    spindle: int | None
    sensors: tuple[tuple[str, int], ...]
    air: tuple[tuple[str, int], ...]
    probe: tuple[int, int, int] | None = None


def trace_columns(header: Sequence[str], machine: Machine, source: str = "<trace>") -> TraceColumns:
    """Map a trace header to the monitor's quantities; an unknown column is an error naming it."""
    idx = {h: i for i, h in enumerate(header)}
    if TIME not in idx:
        raise SourceFileError(f"{source}: line 1: column {TIME!r} is missing")
    pos = []
    for a in machine.axes:
        c = position_column(a.name)
        if c not in idx:
            raise SourceFileError(f"{source}: line 1: column {c!r} (axis {a.name}) is missing")
        pos.append(idx[c])
    sensors = tuple((s.name, idx[temperature_column(s.name)]) for s in machine.sensors if temperature_column(s.name) in idx)
    airs = tuple((c, idx[c]) for c in air_columns(machine) if c in idx)
    known = {TIME, SPINDLE_RPM, *DRIFT, *(position_column(a.name) for a in machine.axes),
             *(velocity_column(a.name) for a in machine.axes), *(temperature_column(s.name) for s in machine.sensors),
             *air_columns(machine), *PROBE_COLUMNS}
    for h in header:
        if h not in known:
            raise SourceFileError(f"{source}: line 1: unknown column {h!r} (machine {machine.name} sensors: "
                                  f"{', '.join(temperature_column(s.name) for s in machine.sensors)})")
    probe = None
    if any(c in idx for c in PROBE_COLUMNS):
        if not all(c in idx for c in PROBE_COLUMNS):
            raise SourceFileError(f"{source}: line 1: probe columns come as all of {', '.join(PROBE_COLUMNS)}")
        probe = tuple(idx[c] for c in PROBE_COLUMNS)
    return TraceColumns(idx[TIME], tuple(pos), idx.get(SPINDLE_RPM), sensors, airs, probe)


def _float(text: str) -> float:
    return float(text) if text.strip() else math.nan


def check_replay(path: str | Path, machine: Machine) -> TraceColumns:
    """The columns of a trace the monitor is to replay.

    Refused (:class:`SourceFileError`) when it has no column of the machine's sensors: a day of nothing (every sensor
    degraded, no CD to evaluate, no set to generate) with exit 0.
    """
    path = Path(path)
    with open_regular_file(path, SourceFileError, "replay trace") as fh:
        header = _decode(fh.readline(), path, 1, "utf-8-sig").strip().split(",")
    cols = trace_columns(header, machine, str(path))
    if not cols.sensors:
        raise SourceFileError(f"{path}: line 1: no sensor column: the monitor reads the temperatures of machine "
                              f"{machine.name}'s sensors ({', '.join(temperature_column(s.name) for s in machine.sensors)}"
                              f"), the trace has {', '.join(header)}")
    return cols


def read_replay(path: str | Path, machine: Machine) -> Iterable[Reading]:
    """Stream the readings of a trace CSV (line by line; memory does not grow with the file).

    NaN and empty fields are passed on as NaN (the daemon's sensor checks deal
    with them); a field that is not a number is an error naming line and column.
    """
    path = Path(path)
    with open_regular_file(path, SourceFileError, "replay trace") as fh:
        header = _decode(fh.readline(), path, 1, "utf-8-sig").strip().split(",")
        cols = trace_columns(header, machine, str(path))
        n = len(header)
        for lineno, raw in enumerate(fh, start=2):
            line = _decode(raw, path, lineno)
            f = line.rstrip("\r\n").split(",")
            if len(f) != n:
                if not line.strip():
                    continue
                raise SourceFileError(f"{path}: line {lineno}: {len(f)} fields, the header has {n}")
            try:
                yield Reading(
                    _float(f[cols.time]),
                    tuple(_float(f[i]) for i in cols.positions),
                    _float(f[cols.spindle]) if cols.spindle is not None else 0.0,
                    {name: _float(f[i]) for name, i in cols.sensors},
                    {name: _float(f[i]) for name, i in cols.air},
                    _probe(tuple(_float(f[i]) for i in cols.probe)) if cols.probe else None,
                )
            except ValueError:
                bad = next(h for h, x in zip(header, f) if not _is_number(x))
                raise SourceFileError(f"{path}: line {lineno}: column {bad!r} is not a number: "
                                      f"{f[header.index(bad)]!r}") from None


def as_number(x: object, name: str = "", bad: dict[str, int] | None = None) -> float:
    """A node's value as a float; a missing value, or one that is no number (``"n/a"``, a bool), is NaN.

    The daemon treats NaN as a sensor fault (held, then degraded, with events) or, for the time, as an invalid
    stamp; ``bad`` counts the values that were no numbers, per name.
    """
    if x is None:
        return math.nan
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return float(x)
    try:
        if isinstance(x, bool):
            raise TypeError
        return float(x)  # numpy scalars, Decimal, numeric text
    except (TypeError, ValueError, OverflowError):
        if bad is not None:
            bad[name] = bad.get(name, 0) + 1
        return math.nan


def _decode(raw: bytes, path: Path, lineno: int, encoding: str = "utf-8") -> str:
    """One line of the trace as text; bytes that are no UTF-8 are an error naming the file and line."""
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        raise SourceFileError(f"{path}: line {lineno}: not UTF-8 text ({exc.reason} at column {exc.start + 1})") from None


def _probe(values: tuple[float, ...]) -> tuple[float, ...] | None:
    """A probed drift, or None when nothing was probed at this sample (all NaN)."""
    return values if any(math.isfinite(v) for v in values) else None


def _is_number(x: str) -> bool:
    try:
        _float(x)
        return True
    except ValueError:
        return False


PACE_STEP_S = 3600.0  # a replay waits for at most this much machine time between two samples


class ReplaySource:
    """Replay a trace CSV in machine time accelerated by ``speed`` (0: as fast as possible).

    A replay has no clock of its own to check time stamps against (``time_scale`` None): the daemon takes a
    confirmed jump ahead in its stamps for a gap in the data. Two stamps more than :data:`PACE_STEP_S` apart (or
    going backwards) are not waited for.

    Parameters
    ----------
    path : trace CSV (``time_s``, axis positions, ``spindle_rpm``, ``T1_degC`` ..., ``Tamb_degC`` ...)
    machine : the machine (column names)
    speed : machine seconds per wall second [-]
    clock : the clock to pace with (default :class:`WallClock`)
    start_s : readings before this machine time are skipped [s]
    """

    def __init__(self, path: str | Path, machine: Machine, speed: float = 1.0, clock=None, start_s: float = -math.inf):
        if not speed >= 0:
            raise ValueError(f"replay speed must not be negative, got {speed}")
        check_replay(path, machine)
        self.path = Path(path)
        self.machine = machine
        self.speed = float(speed)
        self.clock = clock or WallClock()
        self.start_s = start_s
        self.finished = False
        self.time_scale = None

    async def readings(self, start_after_s: float | None = None) -> AsyncIterator[Reading]:
        after = self.start_s if start_after_s is None else max(self.start_s, start_after_s)
        t0 = w0 = None
        last = None
        n = 0
        for r in read_replay(self.path, self.machine):
            if r.time_s <= after:  # (NaN times are passed on: the daemon reports them)
                continue
            n += 1
            if self.speed > 0 and math.isfinite(r.time_s):
                if t0 is None or not 0 <= r.time_s - last <= PACE_STEP_S:
                    # pace from here: a stamp far ahead (or behind) must not make the replay sleep for ever
                    t0, w0 = r.time_s, self.clock.monotonic()
                last = r.time_s
                wait = w0 + (r.time_s - t0) / self.speed - self.clock.monotonic()
                if wait > 1e-3:
                    await self.clock.sleep(wait)
                elif n % 256 == 0:
                    await asyncio.sleep(0)
            elif n % 256 == 0:
                await asyncio.sleep(0)  # let the other tasks (signals, regeneration, metrics) run
            yield r
        self.finished = True


class ListSource:
    """Readings from a list (tests); ``fail_after`` raises :class:`SourceDisconnected` after that many readings once."""

    def __init__(self, readings: Sequence[Reading], fail_after: int | None = None):
        self._readings = list(readings)
        self.fail_after = fail_after
        self.finished = False
        self.connects = 0

    async def readings(self, start_after_s: float | None = None) -> AsyncIterator[Reading]:
        self.connects += 1
        for i, r in enumerate(self._readings):
            if start_after_s is not None and r.time_s <= start_after_s:
                continue
            if self.fail_after is not None and i >= self.fail_after:
                self.fail_after = None
                raise SourceDisconnected("planted connection loss")
            await asyncio.sleep(0)
            yield r
        self.finished = True


def _asyncua():
    try:
        import asyncua
    except ImportError:  # pragma: no cover - depends on the installation
        raise ImportError("the OPC UA source and sink need asyncua: pip install 'hybridcomp[opcua]'") from None
    return asyncua


class OpcUaSource:
    """OPC UA client subscribed to the machine control's nodes.

    One :class:`Reading` is emitted per publish batch in which the time node
    changed, holding the latest value of every node (a batch is delivered at
    once, so positions, speeds and temperatures written before the time stamp
    arrive with it). No data for ``stale_s`` wall seconds makes the source read
    the server state; a failed read (or connect) raises :class:`SourceDisconnected`.

    Parameters
    ----------
    url : endpoint, e.g. ``opc.tcp://127.0.0.1:4840``
    nodes : trace column -> node id; ``time_s`` is required, ``x_mm`` ... per axis, ``spindle_rpm``,
        ``<sensor>_degC``, air columns, and optionally the probed drift ``probe_dx_um``, ``probe_dy_um``,
        ``probe_dz_um`` (all three): a probe is read when any of them changes in a publish batch (the control
        writes a probing cycle's result there, NaN or an unchanged value between probes meaning none)
    machine : the machine (axes, sensors)
    publishing_interval_ms : subscription publishing interval [ms]
    stale_s : silence after which the connection is checked [s]
    """

    def __init__(self, url: str, nodes: Mapping[str, str], machine: Machine, publishing_interval_ms: float = 100.0,
                 stale_s: float = 5.0, timeout_s: float = 4.0):
        cols = trace_columns(list(nodes), machine, f"{url} nodes") if nodes else None
        if cols is None:
            raise ValueError("OPC UA source needs nodes (at least time_s and the axis positions)")
        self.url = url
        self.nodes = dict(nodes)
        self.machine = machine
        self.publishing_interval_ms = float(publishing_interval_ms)
        self.stale_s = float(stale_s)
        self.timeout_s = float(timeout_s)
        self.finished = False
        self.time_scale = "observed"  # the daemon compares the stamps with the wall clock (1 for a live machine)
        self.bad_values: dict[str, int] = {}  # node → values that were not numbers (read as NaN: a sensor fault)
        # column → (node id, the server's status) of a well-formed node id the server does not have (read as NaN)
        self.missing_nodes: dict[str, tuple[str, str]] = {}
        self._check_node_ids()
        self._axes = [position_column(a.name) for a in machine.axes]
        self._sensors = [s.name for s in machine.sensors if temperature_column(s.name) in nodes]
        self._air = [c for c in air_columns(machine) if c in nodes]
        self._probe = cols.probe is not None

    def _reading(self, v: Mapping[str, object], changed: frozenset = frozenset()) -> Reading:
        """The reading of the latest node values ``v``; ``changed``: the columns of this publish batch."""
        def g(k: str) -> float:
            return as_number(v.get(k), k, self.bad_values)

        probe = None
        if self._probe and changed & set(PROBE_COLUMNS):
            probe = _probe(tuple(g(c) for c in PROBE_COLUMNS))
        return Reading(
            g(TIME), tuple(g(c) for c in self._axes), g(SPINDLE_RPM) if SPINDLE_RPM in self.nodes else 0.0,
            {s: g(temperature_column(s)) for s in self._sensors}, {c: g(c) for c in self._air}, probe,
        )

    def _check_node_ids(self) -> None:
        """A malformed node id is a configuration error now, not a connection that is retried for ever."""
        ua = _asyncua()
        for col, nid in self.nodes.items():
            try:
                ua.ua.NodeId.from_string(str(nid))
            except Exception as exc:  # noqa: BLE001 - asyncua raises several types for a malformed id
                raise SourceFileError(f"{self.url} nodes: source.nodes.{col} = {nid!r} is not an OPC UA node id "
                                      f"(e.g. 'ns=2;s=time_s'): {exc}") from None

    def _check_subscribed(self, handles, ua) -> None:
        """Nodes the server refused to subscribe (a well-formed id it does not have).

        The time and the axes are a configuration error (no reading can be made); a sensor, the spindle or the air is
        read as missing and named (``missing_nodes``: the daemon writes a ``source`` event per node).
        """
        for (col, nid), h in zip(self.nodes.items(), handles if isinstance(handles, list) else [handles]):
            if not isinstance(h, ua.ua.StatusCode):
                continue
            why = getattr(h, "name", None) or str(h)
            if col == TIME or col in self._axes:
                raise SourceFileError(f"{self.url}: source.nodes.{col} = {nid!r}: the server has no such node ({why}); "
                                      "without it the monitor reads nothing")
            self.missing_nodes[col] = (str(nid), why)

    async def readings(self, start_after_s: float | None = None) -> AsyncIterator[Reading]:
        ua = _asyncua()
        client = ua.Client(self.url, timeout=self.timeout_s)
        try:
            await client.connect()
        except (TimeoutError, OSError, ua.ua.UaError) as exc:
            raise SourceDisconnected(f"{self.url}: cannot connect: {exc!r}") from None
        try:
            by_id = {}
            nodes = []
            for col, nid in self.nodes.items():
                node = client.get_node(nid)
                nodes.append(node)
                by_id[node.nodeid] = col
            sub = await client.create_subscription(self.publishing_interval_ms, None, queue_maxsize=100_000)
            handles = await sub.subscribe_data_change(nodes)
            self._check_subscribed(handles, ua)
            values: dict[str, float] = {}
            changed: set[str] = set()  # columns published since the last reading (a probe belongs to one reading)
            last_time = None
            while True:
                ev = await sub.next_event(timeout=self.stale_s)
                if ev is None:
                    try:
                        await asyncio.wait_for(client.nodes.server_state.read_value(), self.timeout_s)
                    except Exception as exc:  # noqa: BLE001 - any failure of the probe means the link is gone
                        raise SourceDisconnected(f"{self.url}: no data for {self.stale_s:g} s and the server does not "
                                                 f"answer: {exc!r}") from None
                    continue
                batch = [ev]
                while True:  # the rest of the same publish batch is already queued
                    try:
                        batch.append(sub._event_queue.get_nowait())
                    except (asyncio.QueueEmpty, AttributeError):
                        break
                for e in batch:
                    node = getattr(e, "node", None)
                    if node is not None and node.nodeid in by_id:
                        values[by_id[node.nodeid]] = e.value
                        changed.add(by_id[node.nodeid])
                t = values.get(TIME)
                if t is None or t == last_time:
                    continue
                # the first values are the subscription's snapshot of the nodes, not a probe taken now
                r = self._reading(values, frozenset(changed) if last_time is not None else frozenset())
                last_time = t
                changed.clear()
                if start_after_s is not None and r.time_s <= start_after_s:
                    continue
                yield r
        except (TimeoutError, OSError, ConnectionError, ua.ua.UaError) as exc:
            if isinstance(exc, SourceDisconnected):
                raise
            raise SourceDisconnected(f"{self.url}: connection lost: {exc!r}") from None
        finally:
            try:
                await asyncio.wait_for(client.disconnect(), 1.0)
            except Exception:  # noqa: BLE001 - the connection may already be gone
                pass
