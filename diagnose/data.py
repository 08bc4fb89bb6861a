"""Measured datasets: reading, column mapping, training/validation split.

A measured dataset is a CSV whose columns carry their unit (``time_s``,
``T3_degC``, ``dz_um``, ``spindle_rpm``, ``x_mm``, heat inputs ``*_W``); any
other CSV is read through a column map (TOML)::

    [columns]              # project name = column in the CSV
    time_s = "Time"
    T1_degC = "spindle housing"
    dz_um = "Z displacement"

    [scale]                # optional: multiply a mapped column (e.g. hours to seconds, mm to µm)
    time_s = 3600.0

With a map only the mapped columns are read (and every mapped column must be
in the CSV); without one, every column is read under its own name.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.models.toml import open_text, read_toml

log = logging.getLogger(__name__)

MIN_VALIDATION_SAMPLES = 30
MIN_VALIDATION_FRACTION = 0.05
MIN_TRAINING_SAMPLES = 30


class DatasetError(HybridcompError, ValueError):
    """A measured dataset, column map or split is invalid; the message names the file, column and value."""


@dataclass(frozen=True)
class Dataset:
    """A measured dataset with project column names.

    Attributes
    ----------
    time_s : sample times, strictly increasing [s]
    columns : column name (unit-suffixed project name) → values (unit in the name)
    source : file or description the data came from
    runs : for a campaign, the run number of each row (1, 2, ...; each run a contiguous block of rows with its own
        initial state and its own zero), or None for one series
    """

    time_s: np.ndarray
    columns: dict
    source: str = "dataset"
    runs: np.ndarray | None = None

    def __post_init__(self):
        t = np.asarray(self.time_s, float)
        if t.ndim != 1 or t.size < 2:
            raise DatasetError(f"{self.source}: need at least two samples, got {t.size}")
        bad = np.flatnonzero(~(np.diff(t) > 0))
        if bad.size:
            i = int(bad[0])
            raise DatasetError(f"{self.source}: column 'time_s' does not increase at row {i + 1}: {t[i]} then {t[i + 1]}")
        for name, v in self.columns.items():
            v = np.asarray(v, float)
            if v.shape != t.shape:
                raise DatasetError(f"{self.source}: column {name!r} has {v.size} values, 'time_s' has {t.size}")
            if not np.all(np.isfinite(v)):
                k = int(np.flatnonzero(~np.isfinite(v))[0])
                raise DatasetError(f"{self.source}: column {name!r}, row {k + 1}: value {v[k]} is not finite")
        if self.runs is not None:
            r = np.asarray(self.runs)
            if r.shape != t.shape or not np.all(np.diff(r) >= 0) or r[0] < 1:
                raise DatasetError(f"{self.source}: the run numbers must be 1, 2, ... in contiguous blocks of rows")

    def run_starts(self) -> np.ndarray:
        """First row of each run (``[0]`` for one series)."""
        if self.runs is None:
            return np.array([0])
        r = np.asarray(self.runs)
        return np.r_[0, np.flatnonzero(np.diff(r)) + 1]

    @property
    def n_runs(self) -> int:
        return 1 if self.runs is None else int(np.unique(self.runs).size)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.columns)

    def __getitem__(self, name: str) -> np.ndarray:
        return np.asarray(self.columns[name], float)

    def __contains__(self, name: str) -> bool:
        return name in self.columns

    def subset(self, rows: np.ndarray) -> Dataset:
        """The rows selected by an index or boolean array."""
        return Dataset(self.time_s[rows], {k: np.asarray(v)[rows] for k, v in self.columns.items()}, self.source,
                       None if self.runs is None else np.asarray(self.runs)[rows])


def read_column_map(path: str | Path) -> tuple[dict[str, str], dict[str, float]]:
    """Read a column map TOML: ``[columns] project_name = "csv column"`` and optional ``[scale]``."""
    path = Path(path)
    data, _ = read_toml(path, DatasetError)
    unknown = [k for k in data if k not in ("columns", "scale")]
    if unknown:
        raise DatasetError(f"{path}: field {unknown[0]!r} is not a known field (known: columns, scale)")
    cols = data.get("columns")
    if not isinstance(cols, dict) or not cols:
        raise DatasetError(f"{path}: field 'columns' is required: a table project_name = \"csv column\"")
    for k, v in cols.items():
        if not isinstance(v, str):
            raise DatasetError(f"{path}: field 'columns.{k}' must be a column name (string), got {v!r}")
        check_column_name(k, f"{path}: field 'columns.{k}'")
    if "time_s" not in cols:
        raise DatasetError(f"{path}: field 'columns.time_s' is required (the time column)")
    scale = data.get("scale", {})
    if not isinstance(scale, dict):
        raise DatasetError(f"{path}: field 'scale' must be a table")
    for k, v in scale.items():
        if k not in cols:
            raise DatasetError(f"{path}: field 'scale.{k}' scales a column the map does not define")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise DatasetError(f"{path}: field 'scale.{k}' must be a finite number, got {v!r}")
    return dict(cols), {k: float(v) for k, v in scale.items()}


UNIT_SUFFIXES = ("_s", "_degC", "_um", "_rpm", "_mm", "_W", "_mm_min")


def check_column_name(name: str, where: str) -> None:
    """A project column name must end in a known unit suffix (or be the campaign's ``run`` number)."""
    if name != RUN_COLUMN and not any(name.endswith(s) for s in UNIT_SUFFIXES):
        raise DatasetError(f"{where}: column name {name!r} has no known unit suffix ({', '.join(UNIT_SUFFIXES)})")


def read_dataset(path: str | Path, column_map: str | Path | dict | None = None) -> Dataset:
    """Read a measured dataset CSV, optionally through a column map (file or ``{project: csv}`` dict).

    Raises
    ------
    DatasetError
        missing file or column, a column named by the map that is not in the CSV, non-numeric or
        non-finite values, time not increasing.
    """
    path = Path(path)
    scale: dict[str, float] = {}
    if isinstance(column_map, (str, Path)):
        mapping, scale = read_column_map(column_map)
        map_src = str(column_map)
    elif isinstance(column_map, dict):
        mapping, map_src = dict(column_map), "column map"
    else:
        mapping, map_src = None, ""
    try:
        with open_text(path, DatasetError, "dataset") as fh:
            header = [h.strip() for h in fh.readline().strip().split(",")]
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read dataset: {exc}") from None
    if not header or header == [""]:
        raise DatasetError(f"{path}: empty file, expected a header line")
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise DatasetError(f"{path}: column {dup!r} appears twice")
    if mapping is not None:
        missing = [(k, v) for k, v in mapping.items() if v not in header]
        if missing:
            k, v = missing[0]
            raise DatasetError(
                f"{path}: column {v!r} named by {map_src} field 'columns.{k}' is not in the dataset "
                f"(columns: {', '.join(header)})"
            )
        wanted = {k: header.index(v) for k, v in mapping.items()}
    else:
        if "time_s" not in header:
            raise DatasetError(f"{path}: column 'time_s' is missing (columns: {', '.join(header)}); "
                               "name the columns by the unit-suffix convention or give a column map")
        wanted = {}
        for j, h in enumerate(header):
            if any(h.endswith(s) for s in UNIT_SUFFIXES) or h == RUN_COLUMN:
                wanted[h] = j
            else:
                log.warning("%s: column %r has no unit suffix and is not read (give a column map to use it)", path, h)
    try:
        with open_text(path, DatasetError, "dataset") as fh:
            data = np.loadtxt(fh, delimiter=",", skiprows=1, usecols=sorted(set(wanted.values())), ndmin=2)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read dataset: {exc}") from None
    except DatasetError:
        raise
    except ValueError as exc:
        raise DatasetError(f"{path}: not a numeric CSV: {exc}") from None
    if data.shape[0] == 0:
        raise DatasetError(f"{path}: no data rows")
    pos = {j: i for i, j in enumerate(sorted(set(wanted.values())))}
    cols = {k: data[:, pos[j]] * scale.get(k, 1.0) for k, j in wanted.items()}
    t = cols.pop("time_s")
    run_col = cols.pop(RUN_COLUMN, None)
    if run_col is None:
        return Dataset(t, cols, str(path))
    # a campaign in one file: a 'run' column numbers the runs (contiguous blocks); time may restart in each run
    if not np.all(run_col == np.round(run_col)):
        raise DatasetError(f"{path}: column {RUN_COLUMN!r} must hold whole run numbers")
    starts = np.r_[0, np.flatnonzero(np.diff(run_col)) + 1]
    if np.unique(run_col[starts]).size != starts.size:
        k = next(i for n, i in enumerate(starts) if run_col[i] in run_col[starts[:n]])
        raise DatasetError(f"{path}: run {run_col[k]:g} appears again at row {k + 2}: each run must be one block of rows")
    parts = np.split(np.arange(t.size), starts[1:])
    return campaign([Dataset(t[ix], {k: v[ix] for k, v in cols.items()}, f"{path} run {run_col[ix[0]]:g}")
                     for ix in parts], str(path))


RUN_COLUMN = "run"
RUN_GAP_S = 3600.0  # runs whose times restart are laid one after the other with this gap [s]


def campaign(runs: list[Dataset], source: str = "campaign") -> Dataset:
    """Several runs (test days) as one dataset: each its own initial state and zero, numbered 1, 2, ... in order.

    The runs need the same columns. A run whose time does not come after the previous run's end (each file from 0,
    say) is shifted to start ``RUN_GAP_S`` after it; the time inside a run is kept.
    """
    if not runs:
        raise DatasetError(f"{source}: a campaign needs at least one run")
    names = runs[0].names
    for r in runs[1:]:
        if set(r.names) != set(names):
            raise DatasetError(f"{r.source}: columns {sorted(r.names)} differ from those of {runs[0].source} "
                               f"({sorted(names)}): every run of a campaign needs the same columns")
    times, end = [], -math.inf
    for r in runs:
        t = np.asarray(r.time_s, float)
        if t[0] <= end:
            t = t - t[0] + end + RUN_GAP_S
        times.append(t)
        end = t[-1]
    return Dataset(np.concatenate(times), {n: np.concatenate([r[n] for r in runs]) for n in names}, source,
                   np.concatenate([np.full(r.time_s.size, k + 1) for k, r in enumerate(runs)]))


def read_campaign(paths, column_map: str | Path | dict | None = None) -> Dataset:
    """Several dataset files, one run each, as one campaign (:func:`campaign`); one file is read as it is."""
    paths = [Path(p) for p in paths]
    if len(paths) == 1:
        return read_dataset(paths[0], column_map)
    sets = [read_dataset(p, column_map) for p in paths]
    if any(d.runs is not None for d in sets):
        raise DatasetError(f"{next(d.source for d in sets if d.runs is not None)}: a file with a '{RUN_COLUMN}' column "
                           "is a campaign of its own: give it alone")
    return campaign(sets, f"{len(paths)} runs: {', '.join(p.name for p in paths)}")


# ---------------------------------------------------------------------------------------------- split


@dataclass(frozen=True)
class Split:
    """Training and validation rows of a dataset (boolean masks; validation = the rest)."""

    train: np.ndarray
    validation: np.ndarray
    text: str

    def describe(self, time_s: np.ndarray) -> dict:
        t = np.asarray(time_s)
        return {
            "spec": self.text,
            "train_rows": int(self.train.sum()),
            "validation_rows": int(self.validation.sum()),
            "train_h": [float(t[self.train][0] / 3600), float(t[self.train][-1] / 3600)],
            "validation_h": [float(t[self.validation][0] / 3600), float(t[self.validation][-1] / 3600)],
        }


_BOUND = re.compile(r"^\s*([0-9.eE+-]*)\s*(%|s|h)?\s*$")


def _bound(text: str, t: np.ndarray, default: float, spec: str) -> float:
    m = _BOUND.match(text)
    if not m:
        raise DatasetError(f"split {spec!r}: bound {text!r} is not a number with %, s or h")
    num, unit = m.groups()
    if num == "":
        if unit:
            raise DatasetError(f"split {spec!r}: bound {text!r} has a unit but no number")
        return default
    try:
        v = float(num)
    except ValueError:
        raise DatasetError(f"split {spec!r}: bound {text!r} is not a number") from None
    if unit == "%":
        if not 0 <= v <= 100:
            raise DatasetError(f"split {spec!r}: percentage {v} is outside 0..100")
        return t[0] + v / 100 * (t[-1] - t[0])
    if unit == "h":
        return t[0] + v * 3600
    return t[0] + v


def parse_runs_split(spec: str, runs: np.ndarray | None) -> Split:
    """Training runs ``runs:1-12`` or ``runs:1,3,5-7`` of a campaign; validation is the other runs."""
    if runs is None:
        raise DatasetError(f"split {spec!r}: a split by runs needs a campaign (several files, or a '{RUN_COLUMN}' column)")
    text = spec.split(":", 1)[1]
    chosen: set[int] = set()
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m:
            raise DatasetError(f"split {spec!r}: {part!r} is not a run number or a range like 1-12")
        a, b = int(m.group(1)), int(m.group(2) or m.group(1))
        if b < a:
            raise DatasetError(f"split {spec!r}: range {part!r} runs backwards")
        chosen.update(range(a, b + 1))
    known = set(int(v) for v in np.unique(runs))
    if not chosen <= known:
        raise DatasetError(f"split {spec!r}: run {min(chosen - known)} does not exist (runs 1-{max(known)})")
    train = np.isin(runs, sorted(chosen))
    if train.all():
        raise DatasetError(f"split {spec!r}: every run is a training run: none is left to validate on")
    return Split(train, ~train, spec)


def parse_split(spec: str, time_s: np.ndarray, runs: np.ndarray | None = None) -> Split:
    """Training range ``START:END`` in %, s or h of the record (e.g. ``0:60%``, ``0:24h``); validation is the rest.

    For a campaign (``runs``), ``runs:1-12`` (or ``runs:1,3,5-7``) names the training runs; the other runs validate.

    Raises
    ------
    DatasetError
        unparsable range, an empty training part, or a validation part shorter than
        ``MIN_VALIDATION_SAMPLES`` samples or ``MIN_VALIDATION_FRACTION`` of the record.
    """
    t = np.asarray(time_s, float)
    if spec.strip().startswith("runs:"):
        return parse_runs_split(spec, runs)
    if ":" not in spec:
        raise DatasetError(f"split {spec!r}: expected START:END of the training part, e.g. 0:60% or 0:24h")
    a, b = spec.split(":", 1)
    lo = _bound(a, t, t[0], spec)
    hi = _bound(b, t, t[-1], spec)
    if not hi > lo:
        raise DatasetError(f"split {spec!r}: the training part must end after it starts ({lo} s .. {hi} s)")
    train = (t >= lo) & (t < hi) if hi < t[-1] else (t >= lo)
    val = ~train
    if train.sum() < MIN_TRAINING_SAMPLES:
        raise DatasetError(f"split {spec!r}: training part has {int(train.sum())} samples, "
                           f"at least {MIN_TRAINING_SAMPLES} needed")
    need = max(MIN_VALIDATION_SAMPLES, int(math.ceil(MIN_VALIDATION_FRACTION * t.size)))
    if val.sum() < need:
        raise DatasetError(
            f"split {spec!r}: validation part has {int(val.sum())} samples "
            f"({(t[val][-1] - t[val][0]) / 3600 if val.sum() > 1 else 0:.3g} h); "
            f"at least {need} samples ({MIN_VALIDATION_SAMPLES} and {MIN_VALIDATION_FRACTION:.0%} of the record) are needed "
            "to measure the gain on data the fit has not seen"
        )
    return Split(train, val, spec)


def check_channels(ds: Dataset, channels, split: Split) -> None:
    """Every measured channel must vary in the training and in the validation part."""
    for c in channels:
        y = ds[c]
        for part, mask in (("training", split.train), ("validation", split.validation)):
            v = y[mask]
            if np.ptp(v) <= 1e-9 * max(1.0, np.abs(v).max()):
                raise DatasetError(
                    f"{ds.source}: channel {c!r} is constant ({v[0]:g}) in the {part} part: a residual fit % is undefined; "
                    "remove the channel (column map) or check the sensor"
                )
