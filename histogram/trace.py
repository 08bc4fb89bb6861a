"""Machine traces: the trace CSV contract, a streaming reader and a writer.

A trace CSV (DESIGN.md) has the columns

* ``time_s`` – sample time [s], strictly increasing, any (also irregular) rate;
* ``<axis>_mm`` – axis position [mm] per machine axis, the axis name in lower
  case (``x_mm`` for axis ``X``), in the machine file's axis coordinates
  (travel e.g. [-400, 400] mm);
* ``v<axis>_mm_min`` – optional axis velocity [mm/min] (signed); when present
  for an axis, its time integral of ``|v|`` gives the path instead of the
  position differences;
* ``spindle_rpm`` – spindle speed [1/min] (the sign, M3/M4, is ignored);
  required when the machine has spindle-driven heat sources;
* ``Tamb_degC`` – optional measured workshop air [°C]; ``Tws_degC`` – optional
  measured workspace air [°C]; ``<zone>_degC`` – optional air temperature of
  one convection zone of the machine [°C];
* any other ``*_degC`` column (sensors ``T1_degC`` ...) and the measured drift
  ``dx_um``, ``dy_um``, ``dz_um`` are allowed and not read here.

Any other column is an error (a misspelt column is never silently ignored).
The reader streams the file in chunks of rows, so a week of 10 Hz data never
sits in memory at once. Rows with a NaN or empty field in a column that is read
are dropped and counted (the caller warns); a field that is not a number, an
infinite value, an air temperature outside [-50, 200] °C, a row with the wrong
number of fields and a missing column are errors naming the file, line and
column. The file must be a regular file of UTF-8 text (a byte-order mark is
allowed) whose name has no control character (it names the load case).
"""

from __future__ import annotations

import csv
import difflib
import io
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.models.layout import (
    AMBIENT_COLUMN,
    DRIFT_COLUMNS,
    PROBE_COLUMNS,
    TEMPERATURE_RANGE_DEGC,
    WORKSPACE_COLUMN,
    control_character,
    value_problem,
)
from hybridcomp.models.machine import SPINDLE, Machine
from hybridcomp.models.toml import open_regular_file

log = logging.getLogger(__name__)

TIME = "time_s"
SPINDLE_RPM = "spindle_rpm"
AMBIENT = AMBIENT_COLUMN
WORKSPACE = WORKSPACE_COLUMN
DRIFT = DRIFT_COLUMNS
DEFAULT_CHUNK_ROWS = 65_536


class TraceFileError(HybridcompError, ValueError):
    """A trace (CSV or G-code) is invalid; the message names the file, line, column and value."""


class TraceWarning(UserWarning):
    """Rows were dropped or time counted as standstill; the message says how many and where."""


def position_column(axis_name: str) -> str:
    """Trace column of an axis position: ``x_mm`` for axis ``X``."""
    return f"{axis_name.lower()}_mm"


def velocity_column(axis_name: str) -> str:
    """Trace column of an axis velocity: ``vx_mm_min`` for axis ``X``."""
    return f"v{axis_name.lower()}_mm_min"


def air_columns(machine: Machine) -> tuple[str, ...]:
    """Trace columns that can carry a measured air temperature for a zone of ``machine``."""
    return (AMBIENT, WORKSPACE, *machine.layout().zone_columns)


def zone_air_sources(machine: Machine, measured: tuple[str, ...]) -> dict[str, str]:
    """Which measured trace column gives the air temperature of each zone (:meth:`InputLayout.air_sources`).

    A zone's own column ``<zone>_degC`` wins; otherwise a workspace zone takes
    ``Tws_degC``, then ``Tamb_degC``; an ambient zone takes ``Tamb_degC``. Zones
    without a measured column are left out (they stay at the reference temperature).
    """
    return machine.layout().air_sources(measured)


@dataclass(frozen=True)
class Samples:
    """Trace samples (one chunk of a file, or a whole in-memory trace).

    Attributes
    ----------
    time_s : sample times [s] (n,)
    position_mm : axis positions [mm] (n × n_axes), machine axis order
    velocity_mm_min : axis velocities [mm/min] (n × n_axes), NaN for axes without a velocity column; or None
    spindle_rpm : spindle speed [1/min] (n,)
    air_names : trace columns of the measured air temperatures (e.g. ``("Tamb_degC",)``)
    air_degC : measured air temperatures [°C] (n × len(air_names))
    line : file line of each sample (header = line 1); for in-memory traces the row index + 2
    """

    time_s: np.ndarray
    position_mm: np.ndarray
    velocity_mm_min: np.ndarray | None
    spindle_rpm: np.ndarray
    air_names: tuple[str, ...]
    air_degC: np.ndarray
    line: np.ndarray

    def __post_init__(self):
        n = self.time_s.shape[0]
        for name in ("position_mm", "spindle_rpm", "air_degC", "line"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(f"Samples.{name} has {getattr(self, name).shape[0]} rows, time_s has {n}")
        if self.velocity_mm_min is not None and self.velocity_mm_min.shape != self.position_mm.shape:
            raise ValueError("Samples.velocity_mm_min must have the shape of position_mm")
        if self.air_degC.shape[1:] != (len(self.air_names),):
            raise ValueError(f"Samples.air_degC must have {len(self.air_names)} columns, got {self.air_degC.shape}")

    def __len__(self) -> int:
        return int(self.time_s.shape[0])

    def take(self, index) -> Samples:
        """The samples at ``index`` (a slice, mask or index array)."""
        return Samples(
            self.time_s[index],
            self.position_mm[index],
            None if self.velocity_mm_min is None else self.velocity_mm_min[index],
            self.spindle_rpm[index],
            self.air_names,
            self.air_degC[index],
            self.line[index],
        )


def samples(
    machine: Machine,
    time_s,
    position_mm: dict[str, np.ndarray] | np.ndarray,
    spindle_rpm=None,
    velocity_mm_min: dict[str, np.ndarray] | None = None,
    air_degC: dict[str, np.ndarray] | None = None,
) -> Samples:
    """Build in-memory :class:`Samples` for ``machine``.

    Parameters
    ----------
    time_s : sample times [s]
    position_mm : per axis name its positions [mm] (a missing axis stands at 0 mm), or an (n × n_axes) array
    spindle_rpm : spindle speed [1/min] per sample (default 0)
    velocity_mm_min : optional per axis name the velocities [mm/min]
    air_degC : optional measured air temperatures [°C] keyed by trace column (``Tamb_degC`` ...)
    """
    t = np.asarray(time_s, float)
    n = t.size
    names = [a.name for a in machine.axes]
    if isinstance(position_mm, dict):
        for k in position_mm:
            if k not in names:
                raise ValueError(f"position_mm names axis {k!r}, which machine {machine.name!r} has not (axes: {names})")
        P = np.column_stack([np.broadcast_to(np.asarray(position_mm.get(a, 0.0), float), (n,)) for a in names])
    else:
        P = np.asarray(position_mm, float).reshape(n, len(names))
    V = None
    if velocity_mm_min:
        V = np.column_stack([np.broadcast_to(np.asarray(velocity_mm_min.get(a, np.nan), float), (n,)) for a in names])
    r = np.zeros(n) if spindle_rpm is None else np.broadcast_to(np.asarray(spindle_rpm, float), (n,)).copy()
    air = dict(air_degC or {})
    allowed = air_columns(machine)
    for k in air:
        if k not in allowed:
            raise ValueError(f"air_degC names {k!r}, which is not an air column of machine {machine.name!r} ({allowed})")
    A = np.column_stack([np.asarray(v, float) for v in air.values()]) if air else np.zeros((n, 0))
    return Samples(t, P, V, r, tuple(air), A, np.arange(n) + 2)


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class _Layout:
    """Where the columns a machine needs are in a trace file's header."""

    header: tuple[str, ...]
    time: int
    positions: tuple[int, ...]
    velocities: tuple[int | None, ...]
    spindle: int | None
    air_names: tuple[str, ...]
    air: tuple[int, ...]

    @property
    def used(self) -> list[int]:
        cols = [self.time, *self.positions, *(v for v in self.velocities if v is not None), *self.air]
        if self.spindle is not None:
            cols.append(self.spindle)
        return cols


def _layout(path: Path, header: list[str], machine: Machine) -> _Layout:
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise TraceFileError(f"{path}: column {dup!r} appears twice")
    pos = {position_column(a.name): a for a in machine.axes}
    vel = {velocity_column(a.name): a for a in machine.axes}
    air = air_columns(machine)
    known = [TIME, SPINDLE_RPM, *pos, *vel, *air, *DRIFT, *PROBE_COLUMNS]
    for h in header:
        if h in known or h.endswith("_degC"):
            continue
        hint = difflib.get_close_matches(h, known, n=1)
        more = f" (did you mean {hint[0]!r}?)" if hint else ""
        raise TraceFileError(
            f"{path}: column {h!r} is not a trace column for machine {machine.name!r}{more}; "
            f"known: {', '.join(known)} and sensor columns '<name>_degC'"
        )
    for need in (TIME, *pos):
        if need not in header:
            raise TraceFileError(f"{path}: column {need!r} is missing (header: {header})")
    needs_spindle = any(s.driver == SPINDLE for s in machine.heat_sources)
    if needs_spindle and SPINDLE_RPM not in header:
        raise TraceFileError(
            f"{path}: column {SPINDLE_RPM!r} is missing, and machine {machine.name!r} has spindle-driven heat sources "
            "(write a column of zeros if the spindle stood still)"
        )
    air_present = tuple(h for h in header if h in air)
    return _Layout(
        header=tuple(header),
        time=header.index(TIME),
        positions=tuple(header.index(c) for c in pos),
        velocities=tuple(header.index(c) if c in header else None for c in vel),
        spindle=header.index(SPINDLE_RPM) if SPINDLE_RPM in header else None,
        air_names=air_present,
        air=tuple(header.index(c) for c in air_present),
    )


def _parse_slow(path: Path, lines: list[str], first_line: int, layout: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """Parse line by line (blank lines skipped, empty fields NaN); errors name the line and column."""
    ncol = len(layout.header)
    used = layout.used
    rows, line_no = [], []
    for i, text in enumerate(lines):
        s = text.strip()
        if not s:
            continue
        ln = first_line + i
        try:
            f = next(csv.reader([s]))
        except csv.Error as exc:
            raise TraceFileError(f"{path}: line {ln}: not a readable CSV line: {exc}") from None
        if len(f) != ncol:
            raise TraceFileError(f"{path}: line {ln} has {len(f)} fields, the header has {ncol}")
        vals = []
        for j in used:
            c = f[j].strip()
            if not c:
                vals.append(math.nan)
                continue
            try:
                vals.append(float(c))
            except ValueError:
                raise TraceFileError(f"{path}: line {ln}, column {layout.header[j]!r}: value {c!r} is not a number") from None
        rows.append(vals)
        line_no.append(ln)
    return np.asarray(rows, float).reshape(len(rows), len(used)), np.asarray(line_no, np.int64)


def _parse_block(path: Path, lines: list[str], first_line: int, layout: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """Fast path: numpy's C reader on the block; anything unusual falls back to the line-by-line parser."""
    used = layout.used
    ncol = len(layout.header)
    every = sorted(used) == list(range(ncol))
    try:
        if every:  # numpy checks that every row has the header's number of fields
            data = np.loadtxt(lines, delimiter=",", dtype=float, ndmin=2, comments=None)
            if data.shape == (len(lines), ncol):
                return data[:, used], first_line + np.arange(len(lines), dtype=np.int64)
        else:  # numpy reads only the used columns: count the separators of the whole block instead
            data = np.loadtxt(lines, delimiter=",", dtype=float, usecols=used, ndmin=2, comments=None)
            if data.shape[0] == len(lines) and "".join(lines).count(",") == len(lines) * (ncol - 1):
                return data, first_line + np.arange(len(lines), dtype=np.int64)
    except ValueError:
        pass
    return _parse_slow(path, lines, first_line, layout)


def _to_samples(data: np.ndarray, line: np.ndarray, layout: _Layout) -> tuple[Samples, int, int]:
    """Columns of a parsed block → Samples; rows with NaN are dropped. Returns (samples, dropped, first dropped line)."""
    na = len(layout.positions)
    t = data[:, 0]
    P = data[:, 1 : 1 + na]
    k = 1 + na
    V = None
    nv = sum(v is not None for v in layout.velocities)
    if nv:
        V = np.full((data.shape[0], na), np.nan)
        for a, v in enumerate(layout.velocities):
            if v is not None:
                V[:, a] = data[:, k]
                k += 1
    nair = len(layout.air)
    A = data[:, k : k + nair]
    k += nair
    r = data[:, k] if layout.spindle is not None else np.zeros(data.shape[0])
    bad = np.isnan(data).any(axis=1)  # only the columns read (NaN in V marks axes without a velocity column)
    s = Samples(t, P, V, r, layout.air_names, A, line)
    if bad.any():
        first = int(line[np.argmax(bad)])
        return s.take(~bad), int(bad.sum()), first
    return s, 0, -1


@dataclass
class ReadStats:
    """What the reader saw: rows read, rows dropped for NaN, the first dropped line (-1: none)."""

    rows: int = 0
    dropped: int = 0
    first_dropped_line: int = -1


def read_trace_chunks(
    path: str | Path, machine: Machine, chunk_rows: int = DEFAULT_CHUNK_ROWS, stats: ReadStats | None = None
) -> Iterator[Samples]:
    """Stream a trace CSV as :class:`Samples` chunks of at most ``chunk_rows`` rows.

    Parameters
    ----------
    path : trace CSV
    machine : the machine whose axes and zones the columns are matched to
    chunk_rows : rows per chunk (memory is about 100 bytes per row and column)
    stats : filled in while reading (rows, NaN rows dropped)

    Raises
    ------
    TraceFileError
        naming the file, line and column, for a missing or unknown column, a
        field that is not a number or a row with the wrong number of fields.
    """
    path = Path(path)
    stats = stats if stats is not None else ReadStats()
    bad_name = control_character(path.name)
    if bad_name:
        raise TraceFileError(f"{str(path)!r}: the file name has a control character {bad_name!r}; it names the load case")
    # universal newlines: CRLF files read like LF ones
    with open_regular_file(path, TraceFileError, "trace") as raw, io.TextIOWrapper(raw, encoding="utf-8-sig") as fh:
        line = 1
        first = _read_text(path, fh.readline, line)
        if not first.strip():
            raise TraceFileError(f"{path}: empty file, expected a header with {TIME!r}")
        try:
            header = [h.strip() for h in next(csv.reader([first]))]
        except csv.Error as exc:
            raise TraceFileError(f"{path}: line 1: not a readable CSV header: {exc}") from None
        layout = _layout(path, header, machine)
        line = 2
        hint = max(1, chunk_rows) * max(16, len(first))  # bytes per chunk, from the header length as a row-size guess
        while True:
            lines = _read_text(path, lambda: fh.readlines(hint), line)
            if not lines:
                break
            if len(lines) > chunk_rows:  # keep the chunk size promise whatever the row length
                for i in range(0, len(lines), chunk_rows):
                    yield from _emit(path, lines[i : i + chunk_rows], line + i, layout, stats)
            else:
                yield from _emit(path, lines, line, layout, stats)
            line += len(lines)


def _read_text(path: Path, read, line: int):
    """``read()`` on the text file, with an undecodable byte or a read error named with the file and line."""
    try:
        return read()
    except UnicodeDecodeError as exc:
        raise TraceFileError(f"{path}: not a UTF-8 text CSV: undecodable byte {exc.object[exc.start:exc.start + 1]!r} "
                             f"at or after line {line}") from None
    except OSError as exc:
        raise TraceFileError(f"{path}: cannot read trace: {exc.strerror or exc}") from None


def _check_values(path: Path, data: np.ndarray, line_no: np.ndarray, layout: _Layout) -> None:
    """No infinite value in a column that is read; air temperatures plausible (NaN rows are dropped later)."""
    lo, hi = TEMPERATURE_RANGE_DEGC
    used = layout.used
    air = set(layout.air)
    bad = np.isinf(data)
    for k, j in enumerate(used):
        if j in air:
            bad[:, k] |= (data[:, k] < lo) | (data[:, k] > hi)  # NaN compares False: dropped, not refused
    if bad.any():
        r, k = (int(x) for x in np.argwhere(bad)[0])
        name = layout.header[used[k]]
        why = value_problem(name, float(data[r, k])) or f"value {data[r, k]} is not finite"
        raise TraceFileError(f"{path}: line {int(line_no[r])}, column {name!r}: {why}")


def _emit(path, lines, first_line, layout, stats: ReadStats) -> Iterator[Samples]:
    data, line_no = _parse_block(path, lines, first_line, layout)
    _check_values(path, data, line_no, layout)
    s, dropped, first_bad = _to_samples(data, line_no, layout)
    stats.rows += len(line_no)
    if dropped:
        if stats.dropped == 0:
            stats.first_dropped_line = first_bad
        stats.dropped += dropped
    if len(s):
        yield s


# --------------------------------------------------------------------------- writing


def write_trace(path: str | Path, machine: Machine, s: Samples, chunk_rows: int = 100_000) -> None:
    """Write samples as a trace CSV (positions to 0.1 µm, times to 1 µs).

    Parameters
    ----------
    path : CSV to write
    machine : gives the axis column names
    s : the samples; velocity columns are written for axes with finite velocities
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [TIME, *(position_column(a.name) for a in machine.axes)]
    cols = [s.time_s[:, None], s.position_mm]
    fmts = ["%.6f"] + ["%.4f"] * len(machine.axes)
    if s.velocity_mm_min is not None:
        keep = [a for a in range(len(machine.axes)) if np.isfinite(s.velocity_mm_min[:, a]).all()]
        names += [velocity_column(machine.axes[a].name) for a in keep]
        cols.append(s.velocity_mm_min[:, keep])
        fmts += ["%.3f"] * len(keep)
    names.append(SPINDLE_RPM)
    cols.append(s.spindle_rpm[:, None])
    fmts.append("%.2f")
    names += list(s.air_names)
    cols.append(s.air_degC)
    fmts += ["%.4f"] * len(s.air_names)
    fmt = ",".join(fmts)
    with path.open("w", newline="") as fh:
        fh.write(",".join(names) + "\n")
        n = len(s)
        for i in range(0, n, chunk_rows):
            block = np.hstack([c[i : i + chunk_rows] for c in cols])
            np.savetxt(fh, block, fmt=fmt, delimiter=",")
