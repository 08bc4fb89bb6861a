"""The boundary-condition time series (loads CSV) and the outputs CSV.

The loads CSV is the exchange format between histogram, which writes it, and fem, which reads it;
both stand above models in the data flow, so the format lives here (and :mod:`hybridcomp.fem.loads`
re-exports it for fem's callers).

Loads CSV (DESIGN.md): ``time_s``, one column ``<source>[<segment>]_W`` (or
``<source>_W`` for a fixed source) per heat input [W], one ``<zone>_degC`` per
convection zone [°C].  A missing column means zero power or the reference
temperature; an unknown column is an error.  Outputs CSV: ``time_s``,
``<sensor>_degC`` ..., ``dx_um``, ``dy_um``, ``dz_um``.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from hybridcomp.models.layout import (  # Loads and in_model_order re-exported for the loads' callers
    DRIFT_COLUMNS,
    Loads,
    LoadsColumnError,
    check_result,
    control_character,
    in_model_order,
    temperature_column,
    time_problem,
    value_problem,
)
from hybridcomp.models.machine import Machine
from hybridcomp.models.toml import open_regular_file


class LoadsFileError(LoadsColumnError):
    """A loads CSV is invalid; the message names the file, row or column and value."""


def input_columns(machine: Machine) -> tuple[str, ...]:
    """Loads columns of a machine in model input order (its layout's ``columns``)."""
    return machine.layout().columns


def full_power_inputs(machine: Machine) -> np.ndarray:
    """Model inputs with every source at its full power [W] and every air temperature at the reference.

    A moving source is spread evenly over its rail segments; the air rises are 0 K; in ``input_columns`` order.
    """
    layout = machine.layout()
    u = np.zeros(layout.n_inputs)
    for s in machine.heat_sources:
        cols = list(layout.source_columns(s.name))
        u[cols] = s.power_W / len(cols)
    return u


def read_loads(path: str | Path, machine: Machine) -> Loads:
    """Read and check a loads CSV against a machine.

    The file must be a regular file of UTF-8 text (a byte-order mark is allowed) whose name has no
    control character (it names the load case); every value must be physically plausible
    (:func:`hybridcomp.models.layout.value_problem`): heat powers finite, not negative beyond
    round-off (read as 0) and at most 1e6 W per input; air temperatures within [-50, 200] °C;
    ``time_s`` finite, strictly increasing and spanning at most 1e8 s.

    Raises
    ------
    LoadsFileError
        naming the file, the line, the column and the value.
    """
    path = Path(path)
    expected = input_columns(machine)
    bad_name = control_character(path.name)
    if bad_name:
        raise LoadsFileError(f"{str(path)!r}: the file name has a control character {bad_name!r}; it names the load case")
    with open_regular_file(path, LoadsFileError, "loads file") as raw, \
            io.TextIOWrapper(raw, encoding="utf-8-sig", newline="") as fh:
        rd = csv.reader(fh)
        try:
            header, rows, lines = _read_rows(path, rd, expected, machine)
        except UnicodeDecodeError as exc:
            raise LoadsFileError(f"{path}: not a UTF-8 text CSV: undecodable byte {exc.object[exc.start:exc.start + 1]!r} "
                                 f"after line {rd.line_num}") from None
        except csv.Error as exc:
            raise LoadsFileError(f"{path}: line {rd.line_num}: not a readable CSV line: {exc}") from None
        except OSError as exc:
            raise LoadsFileError(f"{path}: cannot read loads file: {exc.strerror or exc}") from None
    if not rows:
        raise LoadsFileError(f"{path}: no data rows")
    data = np.array(rows)
    t = data[:, header.index("time_s")]
    problem = time_problem(t)
    if problem is not None:
        i, why = problem
        raise LoadsFileError(f"{path}: line {lines[i]}: {why}")
    cols = [j for j, h in enumerate(header) if h != "time_s"]
    values = data[:, cols]
    powers = [k for k, j in enumerate(cols) if header[j].endswith("_W")]
    values[:, powers] = np.maximum(values[:, powers], 0.0)  # round-off below 0 (larger negatives are refused)
    try:
        return in_model_order(Loads(t, values, tuple(header[j] for j in cols)), machine.layout(), str(path))
    except LoadsColumnError as exc:
        raise LoadsFileError(str(exc)) from None


def _read_rows(path: Path, rd, expected: tuple[str, ...], machine: Machine) -> tuple[list[str], list, list[int]]:
    """The header, the checked data rows and their line numbers of a loads CSV."""
    try:
        header = [h.strip() for h in next(rd)]
    except StopIteration:
        raise LoadsFileError(f"{path}: empty file, expected a header with 'time_s'") from None
    if "time_s" not in header:
        raise LoadsFileError(f"{path}: column 'time_s' is missing (header: {header})")
    if len(set(header)) != len(header):
        dup = [h for h in header if header.count(h) > 1][0]
        raise LoadsFileError(f"{path}: column {dup!r} appears twice")
    unknown = [h for h in header if h != "time_s" and h not in expected]
    if unknown:
        raise LoadsFileError(
            f"{path}: column {unknown[0]!r} is not an input of machine {machine.name!r} (inputs: {', '.join(expected)})"
        )
    rows, lines = [], []
    for row in rd:
        i = rd.line_num
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise LoadsFileError(f"{path}: line {i} has {len(row)} fields, the header has {len(header)}")
        try:
            vals = [float(c) for c in row]
        except ValueError:
            j = next(j for j, c in enumerate(row) if not _is_float(c))
            raise LoadsFileError(f"{path}: line {i}, column {header[j]!r}: value {row[j]!r} is not a number") from None
        for h, v in zip(header, vals):
            why = value_problem(h, v) if h != "time_s" else None
            if why:
                raise LoadsFileError(f"{path}: line {i}, column {h!r}: {why}")
        rows.append(vals)
        lines.append(i)
    return header, rows, lines


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def write_loads(path: str | Path, loads: Loads) -> None:
    """Write loads as a loads CSV (the contract of ``hybridcomp simulate --loads``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", *loads.names])
        for t, row in zip(loads.time_s, loads.values):
            w.writerow([f"{t:.12g}", *(f"{v:.6g}" for v in row)])


def check_outputs(time_s, sensor_names, sensors_degC, drift_um, what: str) -> None:
    """The final check before outputs.csv is written: every temperature and drift finite and physically possible.

    Raises :class:`~hybridcomp.models.layout.ResultError` (exit code 2, nothing written) otherwise.
    """
    columns = [temperature_column(s) for s in sensor_names] + list(DRIFT_COLUMNS)
    check_result(np.asarray(time_s), columns, np.hstack([np.asarray(sensors_degC).reshape(len(time_s), -1),
                                                         np.asarray(drift_um).reshape(len(time_s), -1)]), what)


def write_outputs(path: str | Path, time_s: np.ndarray, sensor_names, sensors_degC: np.ndarray, drift_um: np.ndarray) -> None:
    """Write the outputs CSV contract: time_s, <sensor>_degC..., dx_um, dy_um, dz_um."""
    nt, ns = len(time_s), len(sensor_names)
    sensors_degC, drift_um = np.asarray(sensors_degC, float), np.asarray(drift_um, float)
    if sensors_degC.shape != (nt, ns) or drift_um.shape != (nt, len(DRIFT_COLUMNS)):
        raise ValueError(f"{path}: {ns} sensors and {nt} times for sensor values of shape {sensors_degC.shape} and "
                         f"drift of shape {drift_um.shape}")
    write_columns(path, time_s, [*(temperature_column(s) for s in sensor_names), *DRIFT_COLUMNS],
                  np.hstack([sensors_degC, drift_um]))


def write_columns(path: str | Path, time_s: np.ndarray, columns, values: np.ndarray) -> None:
    """Write a time series CSV: ``time_s`` then ``columns`` (their units in their names), one row per time.

    Times with 12 significant digits, values with 6 decimals (the outputs CSV's format).

    Raises
    ------
    ValueError
        ``values`` is not (times × columns): a header that does not match its rows is never written
    """
    columns = list(columns)
    values = np.asarray(values, float)
    if values.shape != (len(time_s), len(columns)):
        raise ValueError(f"{path}: {len(columns)} columns and {len(time_s)} times for values of shape {values.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", *columns])
        for k in range(len(time_s)):
            w.writerow([f"{time_s[k]:.12g}", *(f"{v:.6f}" for v in values[k])])


def example_loads(machine: Machine, duration_h: float = 16.0, dt_s: float = 60.0, seed: int = 0) -> Loads:
    """A reproducible working-day load case for a machine (until the histogram generator supplies real ones).

    Blocks of one hour alternate between axis-heavy roughing, spindle-heavy
    finishing and pauses; the workshop air follows a daily swing of ±1.5 K and
    the workspace air lags it by one hour, 1 K warmer while the spindle runs.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_h * 3600 + 0.5 * dt_s, dt_s)
    layout = machine.layout()
    names = layout.columns
    U = np.zeros((t.size, len(names)))
    n_blocks = int(np.ceil(duration_h))
    axis_f = {a.name: rng.uniform(0.1, 0.6, n_blocks) for a in machine.axes}
    spindle_f = rng.uniform(0.2, 0.9, n_blocks)
    pause = rng.random(n_blocks) < 0.25
    block = np.minimum((t // 3600).astype(int), n_blocks - 1)
    active = ~pause[block]
    for s in machine.heat_sources:
        if s.driver is None:
            f = np.where(active, 0.5, 0.0)
        elif s.driver == "spindle":
            f = np.where(active, spindle_f[block], 0.0)
        else:
            f = np.where(active, axis_f[s.driver][block], 0.0)
        p = machine.source_power_W(s, f)
        cols = layout.source_columns(s.name)
        n = len(cols)
        # a moving source's share over rail segments: the job works mostly in the middle of the travel
        w = np.exp(-0.5 * ((np.arange(n) - (n - 1) / 2) / max(n / 3, 1)) ** 2)
        w /= w.sum()
        for k, j in enumerate(cols):
            U[:, j] = p * w[k]
    t_ref = machine.reference_temperature_degC
    ambient = t_ref + 1.5 * np.sin(2 * np.pi * (t / 3600 - 9) / 24)
    lagged = t_ref + 1.5 * np.sin(2 * np.pi * (t / 3600 - 10) / 24)
    for z in machine.zones:
        j = names.index(temperature_column(z.name))
        U[:, j] = ambient if z.air == "ambient" else lagged + 1.0 * active
    return Loads(t, U, names)
