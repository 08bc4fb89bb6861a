"""Training data for CDs from the FE model: load cases → FE → sensor temperatures, axis positions, drift.

A :class:`LoadCase` is a BC time series (``fem.loads.Loads``) plus, when it
came from motion (G-code or a trace), the mean axis positions per increment
and the load-case signature. :func:`simulate_load_cases` runs them on the FE
model at one pose and returns one :class:`TrainingData` table with the
columns

    load_case, time_s, T1_degC .. T8_degC, x_mm, y_mm, z_mm, dx_um, dy_um, dz_um

Bundled load cases (:func:`standard_load_cases`):

* ``basic_<axis>`` / ``basic_spindle``: each axis alone at its maximum feed
  over its full travel (the spindle alone at its maximum speed) for
  ``heat_h`` hours, then ``cool_h`` hours of standstill;
* ``simultaneous``: X and Y together, then Y and Z together with the spindle,
  at part feed, then standstill — a load case none of the basic ones is;
* ``jobshop``: the bundled 16 h job-shop day with its workshop air.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.loads import Loads, in_model_order, read_loads
from hybridcomp.histogram.bcs import boundary_conditions
from hybridcomp.histogram.gcode import increments_from_motion, parse_gcode
from hybridcomp.histogram.increments import DEFAULT_INCREMENT_S, Increments, increments_from_trace
from hybridcomp.histogram.scenarios import basic_programs, jobshop_ambient, jobshop_program
from hybridcomp.histogram.signature import signatures
from hybridcomp.histogram.trace import AMBIENT, position_column
from hybridcomp.models.layout import DRIFT_COLUMNS, temperature_column
from hybridcomp.models.machine import Machine
from hybridcomp.models.toml import open_text, read_text

log = logging.getLogger(__name__)

STANDARD_CASES = ("basic", "simultaneous", "jobshop")


class TrainingDataError(HybridcompError, ValueError):
    """A training-data file or load case is invalid; the message names the file, column and value."""


@dataclass(frozen=True)
class LoadCase:
    """One load case for CD training.

    Attributes
    ----------
    name : load-case name (``basic_X``, ``jobshop``, a file stem)
    loads : BC time series
    positions_mm : mean axis positions per loads row (nt × n_axes) [mm], or None when unknown (a loads CSV)
    signature : time-weighted mean load-case signature over the case, or None when unknown
    """

    name: str
    loads: Loads
    positions_mm: np.ndarray | None = None
    signature: np.ndarray | None = None


def _mean_positions(inc: Increments) -> np.ndarray:
    """Mean position per increment and axis [mm] (nk × n_axes) from the position histograms."""
    cols = []
    for edges, t in zip(inc.bin_edges_mm, inc.bin_time_s):
        centers = 0.5 * (edges[1:] + edges[:-1])
        tot = t.sum(axis=1)
        cols.append(np.where(tot > 0, (t @ centers) / np.where(tot > 0, tot, 1.0), centers.mean()))
    return np.column_stack(cols)


def load_case_from_increments(machine: Machine, name: str, inc: Increments, power: str = "mean") -> LoadCase:
    """A load case from increments: BCs, mean positions at the loads rows, mean signature."""
    loads = boundary_conditions(machine, inc, power)
    pos = _mean_positions(inc)
    pos = np.vstack([pos[:1], pos])  # the loads rows are [start, end of each increment]
    _, _, sig = signatures(inc)
    w = inc.duration_s
    mean_sig = (sig * w[:, None]).sum(axis=0) / w.sum()
    return LoadCase(name=name, loads=loads, positions_mm=pos, signature=mean_sig)


def load_case_from_gcode(machine: Machine, name: str, gcode: str, increment_s: float = DEFAULT_INCREMENT_S,
                         air_degC: dict | None = None, source: str = "<gcode>") -> LoadCase:
    """A load case from a G-code programme (its exact motion, see ``histogram.increments_from_motion``)."""
    motion = parse_gcode(gcode, machine, source=source)
    inc = increments_from_motion(machine, motion, increment_s, air_degC=air_degC)
    return load_case_from_increments(machine, name, inc)


def with_cooling(gcode: str, cool_h: float) -> str:
    """The programme followed by ``cool_h`` hours of standstill (spindle off)."""
    if cool_h <= 0:
        return gcode
    lines = [ln for ln in gcode.rstrip("\n").split("\n") if ln.strip() not in ("M30", "%")]
    return "\n".join(lines + ["M5", f"G4 P{cool_h * 3600.0:.3f} (cooling)", "M30"]) + "\n"


def _num(v: float) -> str:
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def simultaneous_program(machine: Machine, heat_h: float = 8.0) -> str:
    """G-code of the simultaneous-motion load case: X+Y diagonals, then Y+Z with the spindle, each ``heat_h / 2``.

    Needs axes X, Y, Z. Each phase moves two axes together between 20 % and 80 % of their travel at 70 % of
    the slower axis' maximum feed (per axis), spindle at 40 % then 80 % of its maximum speed.
    """
    ax = {a.name: a for a in machine.axes}
    for n in ("X", "Y", "Z"):
        if n not in ax:
            raise TrainingDataError(f"machine {machine.name!r} has no axis {n!r}: the simultaneous load case needs X, Y, Z")

    def frac(a, f):
        lo, hi = ax[a].travel_mm
        return lo + f * (hi - lo)

    lines = ["(simultaneous-motion load case: X+Y, then Y+Z with the spindle, then cooling)", "G21 G90 G94",
             f"G0 X{_num(frac('X', 0.2))} Y{_num(frac('Y', 0.2))} Z{_num(frac('Z', 0.5))}"]
    rpm = machine.spindle_max_speed_rpm
    for (a, b), f_sp in ((("X", "Y"), 0.4), (("Y", "Z"), 0.8)):
        lo = {a: frac(a, 0.2), b: frac(b, 0.2)}
        hi = {a: frac(a, 0.8), b: frac(b, 0.8)}
        # path feed such that each axis runs at 70 % of the slower axis' maximum
        v_axis = 0.7 * min(ax[a].max_feed_mm_min, ax[b].max_feed_mm_min)
        da, db = hi[a] - lo[a], hi[b] - lo[b]
        feed = v_axis * math.hypot(da, db) / max(da, db)
        stroke_s = math.hypot(da, db) / feed * 60.0
        n = max(2, math.ceil(heat_h / 2 * 3600.0 / stroke_s))
        if rpm > 0:
            lines.append(f"S{_num(f_sp * rpm)} M3")
        lines.append(f"G1 {a}{_num(lo[a])} {b}{_num(lo[b])} F{_num(feed)}")
        for k in range(n):
            p = hi if k % 2 == 0 else lo
            lines.append(f"{a}{_num(p[a])} {b}{_num(p[b])}")
    lines += ["M5", "M30"]
    return "\n".join(lines) + "\n"


def standard_load_cases(machine: Machine, which: Sequence[str] = STANDARD_CASES, heat_h: float = 8.0,
                        cool_h: float = 8.0, increment_s: float = DEFAULT_INCREMENT_S) -> dict[str, LoadCase]:
    """The bundled load cases by group name: ``basic`` (one per axis and the spindle), ``simultaneous``, ``jobshop``."""
    out: dict[str, LoadCase] = {}
    for w in which:
        if w == "basic":
            for k, g in basic_programs(machine, heat_h).items():
                name = f"basic_{k}"
                out[name] = load_case_from_gcode(machine, name, with_cooling(g, cool_h), increment_s, source=name)
        elif w == "simultaneous":
            g = with_cooling(simultaneous_program(machine, heat_h), cool_h)
            out[w] = load_case_from_gcode(machine, w, g, increment_s, source=w)
        elif w == "jobshop":
            out[w] = load_case_from_gcode(machine, w, jobshop_program(machine), increment_s,
                                          air_degC={AMBIENT: jobshop_ambient(machine)}, source=w)
        else:
            raise TrainingDataError(f"unknown load case {w!r} (bundled: {', '.join(STANDARD_CASES)}; or a file)")
    return out


def load_case_from_file(machine: Machine, path: str | Path, increment_s: float = DEFAULT_INCREMENT_S) -> LoadCase:
    """A load case from a file.

    G-code (``.nc``, ``.gcode``, ``.ngc``, ``.mpf``), a trace CSV (has ``x_mm`` ...) or a loads CSV (``*_W`` / zone
    ``*_degC`` columns; positions and signature then unknown).
    """
    p = Path(path)
    if not p.exists():
        raise TrainingDataError(f"{p}: no such file")
    if p.suffix.lower() in (".nc", ".gcode", ".ngc", ".mpf", ".tap"):
        return load_case_from_gcode(machine, p.stem, _read_text(p, "G-code"), increment_s, source=str(p))
    with open_text(p, TrainingDataError, "load case", newline="") as fh:
        try:
            header = next(csv.reader(fh), [])
        except csv.Error as exc:
            raise TrainingDataError(f"{p}: line 1: not a readable CSV header: {exc}") from None
        except OSError as exc:
            raise TrainingDataError(f"{p}: cannot read load case: {exc.strerror or exc}") from None
    if any(h.endswith("_W") for h in header):
        return LoadCase(name=p.stem, loads=read_loads(p, machine))
    inc = increments_from_trace(p, machine, increment_s)
    return load_case_from_increments(machine, p.stem, inc)


def _read_text(path: Path, what: str) -> str:
    """The text of a regular UTF-8 file with universal newlines (a leading byte-order mark is dropped).

    Errors name the file.
    """
    return read_text(path, TrainingDataError, what).replace("\r\n", "\n").replace("\r", "\n")


# --------------------------------------------------------------------------- the table


@dataclass(frozen=True)
class TrainingData:
    """Training table: rows of all load cases; ``columns`` by name, ``load_case`` per row.

    Attributes
    ----------
    load_case : load-case name per row (n,)
    columns : ``time_s`` [s], ``T*_degC`` [°C], ``<axis>_mm`` [mm], ``dx_um`` ... [µm], each (n,)
    signatures : load-case name → mean signature (cases from motion only)
    """

    load_case: np.ndarray
    columns: Mapping[str, np.ndarray]
    signatures: Mapping[str, np.ndarray]

    @property
    def cases(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(self.load_case.tolist()))

    def __len__(self) -> int:
        return len(self.load_case)

    def subset(self, cases: Sequence[str]) -> TrainingData:
        """The rows of some load cases."""
        unknown = [c for c in cases if c not in self.cases]
        if unknown:
            raise TrainingDataError(f"load case(s) {unknown} not in the training data (have: {', '.join(self.cases)})")
        m = np.isin(self.load_case, list(cases))
        return TrainingData(self.load_case[m], {k: v[m] for k, v in self.columns.items()},
                            {k: v for k, v in self.signatures.items() if k in cases})

    def signature(self) -> np.ndarray | None:
        """Row-weighted mean signature of its cases (None if a case has none)."""
        sigs, w = [], []
        for c in self.cases:
            if c not in self.signatures:
                return None
            sigs.append(self.signatures[c])
            w.append(np.count_nonzero(self.load_case == c))
        return np.average(np.array(sigs), axis=0, weights=w)


def simulate_load_cases(
    machine: Machine,
    cases: Mapping[str, LoadCase],
    pose_mm: Mapping[str, float] | None = None,
    element_size_mm: float | None = None,
    dt_s: float | None = 60.0,
    theta: float | None = None,
    model=None,
    progress: bool = False,
    executor: str | object | None = None,
    workers: int | None = None,
    scheme: str = "theta",
) -> TrainingData:
    """Run load cases on the FE model and collect the training table.

    Parameters
    ----------
    machine : the machine
    cases : load cases by name
    pose_mm : pose of the FE model (default mid travel); the positions of loads-only cases
    element_size_mm : FE element size [mm] (default: the machine file's)
    dt_s : FE time step [s] (the loads resampled with :meth:`~hybridcomp.models.layout.Loads.resample`, the
        outputs interpolated linearly at the loads rows); None: the loads rows themselves
    theta : θ-method (0.5 Crank–Nicolson, 1 backward Euler)
    model : an already built ``ThermoElasticModel`` of the same machine and pose (reused; serial run)
    progress : show a progress bar
    executor : None: serial in this process; else run the cases as a batch with ``fem.batch.run_batch``:
        ``"process"`` (local process pool), ``"local"`` (Dask LocalCluster), a Dask scheduler address
        ``"tcp://HOST:8786"``, or an executor object
    workers : worker processes for ``"process"`` / ``"local"``
    scheme : ``"theta"`` (default here: the θ-method at ``dt_s``) or ``"trbdf2"`` (TR-BDF2 to the default
        tolerance of :meth:`ThermoElasticModel.simulate`; give ``dt_s=None`` and no ``theta``)
    """
    if scheme == "theta" and theta is None:
        theta = 0.5
    pose = machine.check_pose(dict(pose_mm or {}))
    full = {name: in_model_order(case.loads, machine) for name, case in cases.items()}
    outputs = {}  # name -> (sensor names, sensors at the loads rows, drift at the loads rows)
    if executor is None:
        from hybridcomp.fem.model import build_model

        if model is None:
            model = build_model(machine, pose, element_size_mm)
        for name, L in full.items():
            t = L.time_s
            R = L.resample(dt_s, keep_rows=True) if dt_s is not None else L
            tt = R.time_s
            log.info("load case %s: %d loads intervals", name, len(tt) - 1)
            res = model.simulate(R, "steady", scheme=scheme, theta=theta, progress=progress)
            pick = np.searchsorted(tt, t)
            outputs[name] = (model.sensor_names, res.sensors_degC[pick], res.drift_um[pick])
    else:
        from hybridcomp.fem.batch import run_batch

        results = run_batch(machine, full, pose_mm=pose, element_size_mm=element_size_mm, scheme=scheme, theta=theta,
                            dt_s=dt_s, executor=executor, workers=workers, progress=progress)
        for name, r in results.items():
            t = full[name].time_s
            sens = np.column_stack([np.interp(t, r.time_s, r.sensors_degC[:, j]) for j in range(len(r.sensor_names))])
            drift = np.column_stack([np.interp(t, r.time_s, r.drift_um[:, j]) for j in range(3)])
            outputs[name] = (r.sensor_names, sens, drift)
    axes = [a.name for a in machine.axes]
    rows_case, cols = [], {}
    sigs = {}
    for name, case in cases.items():
        t = full[name].time_s
        sensor_names, sensors, drift = outputs[name]
        rows_case += [name] * len(t)
        block = {"time_s": t.copy()}
        for j, s in enumerate(sensor_names):
            block[temperature_column(s)] = sensors[:, j]
        pos = case.positions_mm if case.positions_mm is not None else np.tile([pose[a] for a in axes], (len(t), 1))
        for j, a in enumerate(axes):
            block[position_column(a)] = pos[:, j]
        for j, d in enumerate(DRIFT_COLUMNS):
            block[d] = drift[:, j]
        for k, v in block.items():
            cols.setdefault(k, []).append(v)
        if case.signature is not None:
            sigs[name] = case.signature
    return TrainingData(np.array(rows_case, dtype=object), {k: np.concatenate(v) for k, v in cols.items()}, sigs)


SIGNATURE_PREFIX = "# signature "


def write_training_csv(path: str | Path, data: TrainingData) -> Path:
    """Write a training table as CSV (``load_case`` first).

    Signatures go in ``# signature NAME v1 v2 ...`` lines at the top so the file stays one self-contained table.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(data.columns)
    with path.open("w", newline="") as fh:
        for c, s in data.signatures.items():
            fh.write(SIGNATURE_PREFIX + c + " " + " ".join(repr(float(v)) for v in s) + "\n")
        w = csv.writer(fh)
        w.writerow(["load_case", *names])
        cols = [data.columns[k] for k in names]
        for i in range(len(data)):
            w.writerow([data.load_case[i], *(repr(float(c[i])) for c in cols)])
    return path


def read_training_csv(path: str | Path) -> TrainingData:
    """Read a training table.

    As written by :func:`write_training_csv`, or any CSV with the unit-suffixed columns (``load_case`` is optional).
    """
    path = Path(path)
    if not path.exists():
        raise TrainingDataError(f"{path}: no such file")
    sigs: dict[str, np.ndarray] = {}
    lines = _read_text(path, "training table").splitlines()
    body = []
    for ln in lines:
        if ln.startswith(SIGNATURE_PREFIX):
            parts = ln[len(SIGNATURE_PREFIX):].split()
            try:
                sigs[parts[0]] = np.array([float(v) for v in parts[1:]])
            except (ValueError, IndexError):
                raise TrainingDataError(f"{path}: malformed signature line {ln[:80]!r}") from None
        elif ln.strip() and not ln.startswith("#"):
            body.append(ln)
    if not body:
        raise TrainingDataError(f"{path}: no header row")
    reader = csv.reader(body)
    try:
        header = [h.strip() for h in next(reader)]
        if len(set(header)) != len(header):
            raise TrainingDataError(f"{path}: duplicate column names in the header {header}")
        case_col = header.index("load_case") if "load_case" in header else None
        num = [j for j in range(len(header)) if j != case_col]
        data = {header[j]: [] for j in num}
        cases = []
        for i, row in enumerate(reader, start=2):
            if len(row) != len(header):
                raise TrainingDataError(f"{path}: row {i} has {len(row)} fields, the header has {len(header)}")
            for j in num:
                v = row[j].strip()
                try:
                    data[header[j]].append(float(v) if v else math.nan)
                except ValueError:
                    raise TrainingDataError(f"{path}: row {i}, column {header[j]!r}: {v!r} is not a number") from None
            cases.append(row[case_col] if case_col is not None else path.stem)
    except csv.Error as exc:
        raise TrainingDataError(f"{path}: row {reader.line_num}: not a readable CSV line: {exc}") from None
    if not cases:
        raise TrainingDataError(f"{path}: no data rows")
    return TrainingData(np.array(cases, dtype=object), {k: np.asarray(v, float) for k, v in data.items()}, sigs)
