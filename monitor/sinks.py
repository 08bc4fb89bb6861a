"""Where the compensation offsets go: JSON lines, CSV, OPC UA, memory.

Every sink has ``async write(offset)`` and ``async close()``. An offset row
is the TCP drift the active CDs predict, after clamping and rate limiting
(``dx_um``, ``dy_um``, ``dz_um``; the control subtracts it from the
position), with the machine time, the ids of the active set and flags.
A sink that cannot write (an OPC UA server away) logs, retries on the next
cycle and never stops compensation.
"""

from __future__ import annotations

import asyncio
import csv
import json
import logging
import math
from dataclasses import dataclass, field, fields
from pathlib import Path

from hybridcomp.models.layout import DRIFT_COLUMNS
from hybridcomp.monitor.decisions import Backoff, backoff_delay

log = logging.getLogger(__name__)

DIRECTIONS = DRIFT_COLUMNS


@dataclass(frozen=True)
class Offset:
    """One compensation cycle's output.

    Attributes
    ----------
    time_s : machine time [s]
    dx_um, dy_um, dz_um : offsets written (predicted TCP drift, clamped and rate limited) [µm]
    active : ids of the active CD set, ``"X=1,Y=2,Z=3"``, empty without one
    clamped, limited : whether the clamp or the rate limit acted
    outside : whether an input was outside the CDs' trained range
    degraded : sensors standing in by the structure model's estimate
    by : what computed the offsets: ``"cd"`` (the active CD set), ``"cd+model"`` (the CDs' slow part and the corrected
        structure model's fast part) or ``"observer"`` (the corrected structure model)
    position_mm : with a pose-aware structure model: the commanded axis positions the offsets are for [mm]
    pose_um : ... the offsets at the model's pose (what a one-pose compensation writes) [µm]
    table : ... the support-point table of the cycle (:class:`hybridcomp.rom.volumetric.VolumetricTable`); the
        offsets are this table interpolated at ``position_mm``
    """

    time_s: float
    dx_um: float
    dy_um: float
    dz_um: float
    active: str = ""
    clamped: bool = False
    limited: bool = False
    outside: bool = False
    degraded: str = ""
    by: str = "cd"
    position_mm: tuple[float, ...] | None = None
    pose_um: tuple[float, float, float] | None = None
    table: object = field(default=None, compare=False, repr=False)

    def record(self) -> dict:
        """The offsets' JSON-ready fields (the table goes to its own file: :class:`TableSink`)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "table"}

    def values(self) -> dict[str, float]:
        return {"dx_um": self.dx_um, "dy_um": self.dy_um, "dz_um": self.dz_um}


class MemorySink:
    """Keeps the offsets in a list (tests, the scenario runner)."""

    def __init__(self):
        self.rows: list[Offset] = []

    async def write(self, offset: Offset) -> None:
        self.rows.append(offset)

    async def close(self) -> None:
        pass


class _FileSink:
    """What the file sinks share: a flush every ``flush_every`` rows, and close."""

    _fh = None
    _n = 0
    flush_every = 1

    def _open(self, path: str | Path, flush_every: int) -> None:
        """Open ``path`` to append lines (its folder made)."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("a")
        self._n = 0
        self.flush_every = flush_every

    def _wrote(self) -> None:
        self._n += 1
        if self._n % self.flush_every == 0:
            self._fh.flush()

    async def close(self) -> None:
        self._fh.close()


class JsonlSink(_FileSink):
    """Appends one JSON object per cycle to a file.

    Flushed every ``flush_every`` rows (default: each, as a control reading the file expects) and on close.
    """

    def __init__(self, path: str | Path, flush_every: int = 1):
        self._open(path, flush_every)

    async def write(self, offset: Offset) -> None:
        self._fh.write(json.dumps(offset.record(), allow_nan=False) + "\n")
        self._wrote()


class CsvSink(_FileSink):
    """Appends one CSV row per cycle (header written when the file is new)."""

    FIELDS = ("time_s", *DIRECTIONS, "active", "clamped", "limited", "outside", "degraded", "by")

    def __init__(self, path: str | Path, flush_every: int = 1):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._fh = self.path.open("a", newline="")
        self._w = csv.writer(self._fh)
        if new:
            self._w.writerow(self.FIELDS)
        self._n = 0
        self.flush_every = flush_every

    async def write(self, offset: Offset) -> None:
        d = offset.record()
        self._w.writerow([f"{d[k]:.6f}" if isinstance(d[k], float) else int(d[k]) if isinstance(d[k], bool) else d[k]
                          for k in self.FIELDS])
        self._wrote()


class TableSink(_FileSink):
    """Appends the support-point table of every cycle that has one, one JSON object a line.

    (:func:`hybridcomp.rom.volumetric.table_to_dict`: the grid, the structure's drift at its points and each
    drive's error over its axis [µm]; a control that interpolates the table itself reads it.)
    """

    def __init__(self, path: str | Path, flush_every: int = 1):
        self._open(path, flush_every)

    async def write(self, offset: Offset) -> None:
        if offset.table is None:
            return
        from hybridcomp.rom.volumetric import table_to_dict

        self._fh.write(json.dumps(table_to_dict(offset.table), allow_nan=False) + "\n")
        self._wrote()


class TeeSink:
    """Writes every offset to each of its sinks, in order."""

    def __init__(self, *sinks):
        self.sinks = sinks

    async def write(self, offset: Offset) -> None:
        for sk in self.sinks:
            await sk.write(offset)

    async def close(self) -> None:
        for sk in self.sinks:
            await sk.close()


class OpcUaSink:
    """Writes the offsets to OPC UA nodes of the control (``dx_um`` ... -> node id), as doubles.

    The connection is made lazily and re-made with the backoff after a failure;
    while it is down, offsets are dropped (the next cycle writes fresh ones) and
    counted in :attr:`failed`.
    """

    def __init__(self, url: str, nodes: dict[str, str], backoff: Backoff | None = None, clock=None, timeout_s: float = 2.0):
        from hybridcomp.monitor.sources import WallClock, _asyncua

        self._ua = _asyncua()
        self.url = url
        self.nodes = dict(nodes)
        self.backoff = backoff or Backoff()
        self.clock = clock or WallClock()
        self.timeout_s = timeout_s
        self._client = None
        self._attempt = 0
        self._retry_at = -math.inf
        self.failed = 0
        self.written = 0

    async def _connect(self):
        c = self._ua.Client(self.url, timeout=self.timeout_s)
        await c.connect()
        self._nodes = {k: c.get_node(v) for k, v in self.nodes.items()}
        self._client = c

    async def write(self, offset: Offset) -> None:
        if self._client is None:
            if self.clock.monotonic() < self._retry_at:
                self.failed += 1
                return
            try:
                await self._connect()
                self._attempt = 0
            except Exception as exc:  # noqa: BLE001 - any failure: retry later
                self._retry_at = self.clock.monotonic() + backoff_delay(self._attempt, self.backoff)
                self._attempt += 1
                self.failed += 1
                log.warning("OPC UA sink %s: cannot connect (%r); next try in %.1f s", self.url, exc,
                            self._retry_at - self.clock.monotonic())
                return
        ua = self._ua.ua
        vals = offset.values()
        try:
            for k, node in self._nodes.items():
                await asyncio.wait_for(node.write_value(ua.DataValue(ua.Variant(float(vals[k]), ua.VariantType.Double))),
                                       self.timeout_s)
            self.written += 1
        except Exception as exc:  # noqa: BLE001
            self.failed += 1
            log.warning("OPC UA sink %s: write failed (%r); reconnecting", self.url, exc)
            await self.close()

    async def close(self) -> None:
        c, self._client = self._client, None
        if c is not None:
            try:
                await asyncio.wait_for(c.disconnect(), 1.0)
            except Exception:  # noqa: BLE001
                pass


def make_sink(cfg, backoff: Backoff | None = None, clock=None):
    """The sink of a :class:`~hybridcomp.monitor.config.SinkConfig` (with its table file, when it has one)."""
    main = _make_offsets_sink(cfg, backoff, clock)
    if getattr(cfg, "table_path", None) is None:
        return main
    return TeeSink(main, TableSink(cfg.table_path))


def _make_offsets_sink(cfg, backoff: Backoff | None = None, clock=None):
    if cfg.kind == "jsonl":
        return JsonlSink(cfg.path)
    if cfg.kind == "csv":
        return CsvSink(cfg.path)
    if cfg.kind == "opcua":
        return OpcUaSink(cfg.url, dict(cfg.nodes), backoff or Backoff(), clock)
    if cfg.kind == "none":
        return _NullSink()
    raise ValueError(f"unknown sink kind {cfg.kind!r}")


class _NullSink:
    async def write(self, offset: Offset) -> None:
        pass

    async def close(self) -> None:
        pass
