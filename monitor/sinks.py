"""Where the compensation offsets go: JSON lines, CSV, OPC UA, memory.

Every sink has ``async write(offset)`` and ``async close()``. An offset row
is the TCP drift the active CDs predict, after clamping and rate limiting
(``dx_um``, ``dy_um``, ``dz_um``; the control subtracts it from the
position), with the machine time, the ids of the active set and flags.
A sink that cannot write (an OPC UA server away) logs, retries on the next
cycle and never stops compensation. A file sink is checked at startup
(:func:`check_sink_paths`: never one of the monitor's inputs, never a
symbolic link) and writes whole, fsync'd lines; a write that fails (a full
disk) raises :class:`SinkWriteError`, naming the file, with the partial line
cut off.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import logging
import math
from dataclasses import dataclass, field, fields
from pathlib import Path

from hybridcomp.errors import HybridcompError
from hybridcomp.models.layout import DRIFT_COLUMNS
from hybridcomp.monitor.decisions import Backoff, backoff_delay
from hybridcomp.safeio import AppendOnlyFile, OutputPathError, same_file

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
        structure model's fast part), ``"observer"`` (the corrected structure model), ``"zero"`` (the fail-safe on
        a known-wrong set while the structure model is flagged: ramping to zero), ``"cd-grid"`` (the
        support-point table of the active CD grid, :mod:`hybridcomp.chardiag.grid`) or ``"dataonly"`` (the data-only
        model of strategy ``dataonly``)
    position_mm : with a pose-aware structure model or an active CD grid: the commanded axis positions the offsets
        are for [mm]
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


class SinkWriteError(HybridcompError, OSError):
    """A file sink could not write its line (a full disk, an I/O error): the file is named, its lines stay whole.

    Attributes
    ----------
    path : the sink's file
    cause : the ``OSError`` of the write
    """

    def __init__(self, path: str | Path, cause: OSError):
        self.path = Path(path)
        self.cause = cause
        why = cause.strerror or str(cause) or type(cause).__name__
        super().__init__(f"sink {self.path}: cannot write the offsets ({why}); the file holds only whole lines, "
                         "the last one the last offsets written")

    def __str__(self) -> str:
        return self.args[0]

    def __reduce__(self):
        return (type(self), (self.path, self.cause))


class _FileSink:
    """What the file sinks share: an :class:`~hybridcomp.safeio.AppendOnlyFile`, a whole line per write, close.

    Every line is flushed and fsync'd before :meth:`write` returns (a control reading the file sees whole lines
    only; ``fsync=False``, for a benchmark of the daemon rather than the disk, only flushes); a failed write
    raises :class:`SinkWriteError` with the file cut back to its last whole line.
    """

    _file = None

    def _open(self, path: str | Path, fsync: bool) -> None:
        """Open ``path`` to append lines (its folder made; never through a link)."""
        self.path = Path(path)
        self._file = AppendOnlyFile(self.path, fsync)

    def _append(self, line: str) -> None:
        try:
            self._file.append(line)
        except OSError as exc:
            raise SinkWriteError(self.path, exc) from exc

    async def close(self) -> None:
        if self._file is not None:
            self._file.close()


class JsonlSink(_FileSink):
    """Appends one JSON object per cycle to a file, one whole, fsync'd line each."""

    def __init__(self, path: str | Path, fsync: bool = True):
        self._open(path, fsync)

    async def write(self, offset: Offset) -> None:
        self._append(json.dumps(offset.record(), allow_nan=False) + "\n")


def _csv_line(row) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(row)
    return buf.getvalue()


class CsvSink(_FileSink):
    """Appends one CSV row per cycle (header written when the file is new; an existing file must have it)."""

    FIELDS = ("time_s", *DIRECTIONS, "active", "clamped", "limited", "outside", "degraded", "by")

    def __init__(self, path: str | Path, fsync: bool = True):
        self._open(path, fsync)
        header = _csv_line(self.FIELDS)
        if self._file.size == 0:
            self._append(header)
            return
        with open(self.path, encoding="utf-8", errors="replace", newline="") as fh:
            first = fh.readline()
        if first.replace("\r\n", "\n") != header:
            self._file.close()
            raise OutputPathError(f"sink {self.path}: an existing file whose first line is not the offsets' header "
                                  f"{header.strip()!r} (got {first.strip()[:80]!r}): not appending to another file")

    async def write(self, offset: Offset) -> None:
        d = offset.record()
        self._append(_csv_line([f"{d[k]:.6f}" if isinstance(d[k], float) else int(d[k]) if isinstance(d[k], bool)
                                else d[k] for k in self.FIELDS]))


class TableSink(_FileSink):
    """Appends the support-point table of every cycle that has one, one JSON object a line.

    (:func:`hybridcomp.rom.volumetric.table_to_dict`: the grid, the structure's drift at its points and each
    drive's error over its axis [µm]; a control that interpolates the table itself reads it.)
    """

    def __init__(self, path: str | Path, fsync: bool = True):
        self._open(path, fsync)

    async def write(self, offset: Offset) -> None:
        if offset.table is None:
            return
        from hybridcomp.rom.volumetric import table_to_dict

        self._append(json.dumps(table_to_dict(offset.table), allow_nan=False) + "\n")


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


#: every sink kind of a configuration: whether it writes a file (checked by :func:`check_sink_paths`)
SINK_FILE_KINDS = {"jsonl": True, "csv": True, "opcua": False, "none": False}


def sink_files(sink_cfg) -> dict[str, Path]:
    """The files a sink configuration appends to, by their key (``sink.path``, ``sink.table_path``)."""
    files = {}
    if SINK_FILE_KINDS[sink_cfg.kind] and sink_cfg.path is not None:
        files["sink.path"] = Path(sink_cfg.path)
    if getattr(sink_cfg, "table_path", None) is not None:
        files["sink.table_path"] = Path(sink_cfg.table_path)
    return files


def monitor_inputs(cfg) -> dict[str, Path]:
    """The files a monitor configuration reads or owns, by what they are: a sink may be none of them."""
    from hybridcomp.chardiag.db import sqlite_file

    inputs = {"the configuration": Path(cfg.source_file)}
    if cfg.source.kind == "replay" and cfg.source.path is not None:
        inputs["the replay trace source.path"] = Path(cfg.source.path)
    inputs["the structure model monitor.rom"] = Path(cfg.rom)
    if cfg.dataonly_model is not None:
        inputs["the data-only model compensation.dataonly_model"] = Path(cfg.dataonly_model)
    if str(cfg.machine).endswith(".toml") or Path(cfg.machine).exists():
        inputs["the machine file monitor.machine"] = Path(cfg.machine)
    db = sqlite_file(cfg.database)
    if db is not None:
        inputs["the database monitor.database"] = Path(db)
        for suffix in ("-wal", "-shm", "-journal"):
            inputs[f"the database's {suffix[1:]} file"] = Path(f"{db}{suffix}")
    return inputs


def check_sink_paths(cfg) -> None:
    """Refuse a file sink that is one of the monitor's inputs (by resolved path and inode) or a symbolic link.

    Parameters
    ----------
    cfg : the :class:`~hybridcomp.monitor.config.MonitorConfig`

    Raises
    ------
    OutputPathError
        naming the configuration, the sink key, its path and what else that file is.
    """
    files = sink_files(cfg.sink)
    inputs = monitor_inputs(cfg)
    for key, path in files.items():
        if path.is_symlink():
            raise OutputPathError(f"{cfg.source_file}: {key} {path} is a symbolic link: a sink never writes through one")
        for what, inp in inputs.items():
            if same_file(path, inp):
                raise OutputPathError(f"{cfg.source_file}: {key} {path} is {what}: the offsets are never appended to "
                                      "an input of the monitor")
        if path.exists() and not path.is_file():
            raise OutputPathError(f"{cfg.source_file}: {key} {path} is not a regular file")
    if len(files) == 2 and same_file(*files.values()):
        raise OutputPathError(f"{cfg.source_file}: sink.path and sink.table_path are the same file {files['sink.path']}")


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
