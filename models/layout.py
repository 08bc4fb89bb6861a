"""The input layout of a machine: the one vocabulary every package speaks.

A machine model (FE or reduced) has inputs, in this order:

* one heat input per fixed source, ``<source>``, and per rail segment ``k = 1 … n`` of a
  moving source, ``<source>[k]`` — loads column ``<input>_W``, power [W];
* one air temperature per convection zone — loads column ``<zone>_degC`` [°C]; the model
  itself takes the rise over the reference temperature [K];

and outputs (:class:`OutputLayout`), in typed groups: one temperature per sensor (column ``<sensor>_degC``
[°C]), the TCP-minus-table drift in three directions at the model's pose, and in a pose-aware reduced model the drift
at every further support pose and every drive's positioning error, in a diagnosis' model each body's share of the
drift.  Directions have one spelling per layer:

=======================  ======================  ==================================================
layer                    spelling                where
=======================  ======================  ==================================================
machine file             ``x``, ``y``, ``z``      :data:`COORDINATES`: an axis's or support's direction
CDs and axes             ``X``, ``Y``, ``Z``      :data:`DIRECTIONS`: CD XML, CD sets, axis names
model outputs (SI)       ``dx``, ``dy``, ``dz``   :data:`DRIFT_OUTPUTS`: FE/ROM output names [m]
files, tables, sinks     ``dx_um`` …              :data:`DRIFT_COLUMNS`: CSV columns, offsets [µm]
=======================  ======================  ==================================================

This module builds every heat-input name (:func:`heat_input_name`) and every output name beyond the sensors and
the drift (:func:`pose_output_names`, :func:`feedback_output_names`, :func:`body_output_names`), maps named columns to
model inputs (:meth:`InputLayout.inputs`) and finds a model's outputs by group (:func:`output_layout`); no other
module does any of these.
"""

from __future__ import annotations

import math
import unicodedata
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hybridcomp.errors import HybridcompError

if TYPE_CHECKING:  # the layout is built from a machine, but needs nothing else of it
    from hybridcomp.models.machine import Machine

COORDINATES = ("x", "y", "z")
DIRECTIONS = ("X", "Y", "Z")
DRIFT_OUTPUTS = ("dx", "dy", "dz")
DRIFT_COLUMNS = ("dx_um", "dy_um", "dz_um")
#: a drift measured now and then (a probe cycle in a pause) in a trace: NaN where nothing was probed [µm]
PROBE_COLUMNS = tuple(f"probe_{c}" for c in DRIFT_COLUMNS)
POWER_SUFFIX = "_W"
TEMPERATURE_SUFFIX = "_degC"
# measured air columns of a trace or dataset, by the kind of air a zone has
AMBIENT_COLUMN = "Tamb_degC"
WORKSPACE_COLUMN = "Tws_degC"


# physical bounds of the inputs a file may give (loads CSV, trace CSV, CDs): beyond them a value is a
# mistake in the file, never an operating condition, and is refused with the file, column and line
ABSOLUTE_ZERO_DEGC = -273.15
#: plausible air (zone) and structure temperatures [°C]: a workshop, a cold store, a hot enclosure
TEMPERATURE_RANGE_DEGC = (-50.0, 200.0)
#: the largest power one heat input (loads column) may carry [W]; the largest spindle motors have ~100 kW
MAX_HEAT_POWER_W = 1e6
#: a computed structure temperature above this [°C] is no machine: every solid has melted (hafnium carbide, the
#: highest known melting point, at about 3,900 °C; CRC Handbook); below absolute zero is impossible
MAX_RESULT_TEMPERATURE_DEGC = 4000.0
#: a computed drift or positioning error beyond this [µm] (1 m) is no machine tool's thermal error
MAX_RESULT_DRIFT_UM = 1e6
#: a negative power down to this is round-off of a written number and is read as 0 [W]
POWER_ROUND_OFF_W = 1e-6
#: a resampled grid time this close to the end time (relative, at least as many seconds) is the end time
END_TIME_TOLERANCE = 1e-9
#: the largest magnitude of a time in a loads CSV [s] (Unix times in seconds fit) ...
MAX_TIME_S = 1e10
#: ... and of the time a loads CSV spans [s] (about 3.2 years)
MAX_SPAN_S = 1e8


class LoadsColumnError(HybridcompError, ValueError):
    """A named column is not an input of the model; the message names the source, the column and the inputs."""


def heat_input_name(source: str, segment: int | None = None) -> str:
    """Name of a heat input: ``<source>`` (fixed source) or ``<source>[k]`` (rail segment ``k``, from 1)."""
    return source if segment is None else f"{source}[{segment}]"


def power_column(heat_input: str) -> str:
    """Loads column of a heat input: ``<input>_W`` [W]."""
    return heat_input + POWER_SUFFIX


def temperature_column(name: str) -> str:
    """Column of a temperature (sensor or zone air): ``<name>_degC`` [°C]."""
    return name + TEMPERATURE_SUFFIX


@dataclass(frozen=True)
class InputLayout:
    """Names, kinds, order and units of a machine model's inputs and outputs.

    Attributes
    ----------
    heat_inputs : heat-input names in model order (``<source>``, ``<source>[k]``)
    zones : convection zone names in model order
    zone_air : kind of air per zone, ``"ambient"`` or ``"workspace"``
    sensors : sensor names in output order
    reference_temperature_degC : the state of zero rise, and the air temperature of a zone with no column [°C]
    source_inputs : per heat source, its name and the indices of its heat inputs
    model : what the layout belongs to, for messages (``machine 'vmc800'``)
    """

    heat_inputs: tuple[str, ...]
    zones: tuple[str, ...]
    zone_air: tuple[str, ...]
    sensors: tuple[str, ...]
    reference_temperature_degC: float
    source_inputs: tuple[tuple[str, tuple[int, ...]], ...] = ()
    model: str = "the model"

    def __post_init__(self):
        if len(self.zone_air) != len(self.zones):
            raise ValueError(f"zone_air has {len(self.zone_air)} entries for {len(self.zones)} zones")
        if not np.isfinite(self.reference_temperature_degC):
            raise ValueError(f"reference_temperature_degC must be finite, got {self.reference_temperature_degC}")

    # -- names ------------------------------------------------------------------------------------
    @property
    def heat_columns(self) -> tuple[str, ...]:
        return tuple(power_column(q) for q in self.heat_inputs)

    @property
    def zone_columns(self) -> tuple[str, ...]:
        return tuple(temperature_column(z) for z in self.zones)

    @property
    def columns(self) -> tuple[str, ...]:
        """Loads columns in model input order: ``<input>_W`` …, ``<zone>_degC`` …."""
        return self.heat_columns + self.zone_columns

    @property
    def n_inputs(self) -> int:
        return len(self.heat_inputs) + len(self.zones)

    @property
    def output_names(self) -> tuple[str, ...]:
        """Model output names: sensors, then ``dx``, ``dy``, ``dz``."""
        return self.sensors + DRIFT_OUTPUTS

    @property
    def sensor_columns(self) -> tuple[str, ...]:
        return tuple(temperature_column(s) for s in self.sensors)

    @property
    def output_columns(self) -> tuple[str, ...]:
        """Outputs-CSV columns after ``time_s``: ``<sensor>_degC`` …, ``dx_um``, ``dy_um``, ``dz_um``."""
        return self.sensor_columns + DRIFT_COLUMNS

    def source_columns(self, source: str) -> tuple[int, ...]:
        """Input indices of a heat source's inputs (one for a fixed source, one per segment for a moving one)."""
        for name, cols in self.source_inputs:
            if name == source:
                return cols
        raise KeyError(f"unknown heat source {source!r} (sources: {', '.join(n for n, _ in self.source_inputs)})")

    # -- columns -> inputs --------------------------------------------------------------------------
    def air_sources(self, measured: Sequence[str]) -> dict[str, str]:
        """Which measured column gives the air temperature of each zone.

        A zone's own column ``<zone>_degC`` wins; otherwise a workspace zone takes ``Tws_degC``,
        then ``Tamb_degC``; an ambient zone takes ``Tamb_degC``.  Zones without a measured
        column are left out (they stay at the reference temperature).
        """
        present = set(measured)
        out = {}
        for z, air in zip(self.zones, self.zone_air):
            order = [temperature_column(z), WORKSPACE_COLUMN, AMBIENT_COLUMN] if air == "workspace" else \
                [temperature_column(z), AMBIENT_COLUMN]
            for c in order:
                if c in present:
                    out[z] = c
                    break
        return out

    def complete(self, names: Sequence[str], values: np.ndarray, source: str = "loads",
                 air: Mapping[str, str] | None = None) -> np.ndarray:
        """Every loads column in model order, in loads units (powers [W], air [°C]) (nt × nu).

        Parameters
        ----------
        names : column names of ``values``
        values : the columns (nt × len(names))
        source : what the columns come from, for the error message (a file name)
        air : zone → column to read its air temperature from when it is not ``<zone>_degC``
            (see :meth:`air_sources`); columns it names are not inputs and not unknown

        A missing heat input is zero power, a missing zone the reference temperature; a column
        that is not an input is an error naming it.
        """
        names = list(names)
        values = np.asarray(values, float)
        if values.ndim != 2 or values.shape[1] != len(names):
            raise LoadsColumnError(f"{source}: {len(names)} column names for values of shape {values.shape}")
        expected = self.columns
        aliases = set((air or {}).values())
        unknown = [n for n in names if n not in expected and n not in aliases]
        if unknown:
            raise LoadsColumnError(f"{source}: column {unknown[0]!r} is not an input of {self.model} "
                                   f"(inputs: {', '.join(expected)})")
        index = {n: j for j, n in enumerate(names)}
        U = np.zeros((values.shape[0], len(expected)))
        nh = len(self.heat_inputs)
        for j, col in enumerate(expected):
            if col in index:
                U[:, j] = values[:, index[col]]
            elif j >= nh:
                alias = (air or {}).get(self.zones[j - nh])
                U[:, j] = values[:, index[alias]] if alias in index else self.reference_temperature_degC
        return U

    def inputs(self, names: Sequence[str] | Loads, values: np.ndarray | None = None, source: str = "loads",
               air: Mapping[str, str] | None = None) -> np.ndarray:
        """Model inputs (nt × nu) from named columns: powers [W], air temperature rises [K].

        As :meth:`complete`, with the reference temperature taken off the zone columns.  ``names`` may be
        a :class:`Loads` (then without ``values``): its columns in this layout's order, whatever theirs.
        """
        if isinstance(names, Loads):
            if values is not None:
                raise TypeError("inputs(loads) takes no values: they are the loads' own")
            names, values = names.names, names.values
        elif values is None:
            raise TypeError("inputs(names, values): values missing")
        U = self.complete(names, values, source, air)
        U[:, len(self.heat_inputs):] -= self.reference_temperature_degC
        return U

    def loads_values(self, inputs: np.ndarray) -> np.ndarray:
        """Loads columns (powers [W], air [°C]) from model inputs (powers [W], air rises [K]): the inverse of :meth:`inputs`."""
        V = np.array(inputs, float, copy=True)
        V[..., len(self.heat_inputs):] += self.reference_temperature_degC
        return V


@dataclass(frozen=True)
class Loads:
    """A boundary-condition time series, its columns in model input order.

    Attributes
    ----------
    time_s : times [s]
    values : heat powers [W] and air temperatures [°C] (nt × nu), columns as ``names``
    names : column names (``*_W``, ``*_degC``); :func:`in_model_order` makes them a layout's ``columns``
    """

    time_s: np.ndarray
    values: np.ndarray
    names: tuple[str, ...]

    def resample(self, dt_s: float, keep_rows: bool = False) -> Loads:
        """The loads at a uniform step ``dt_s`` [s], every column interpolated linearly.

        The times are ``t0 + k·dt_s`` (``k = 0, 1, …``, as :func:`numpy.arange` makes them) before the end
        time, then the end time itself: the first and the last time are kept exactly and every step is
        ``dt_s`` but the last, which is at most ``dt_s`` (plus the tolerance).  A grid time within :data:`END_TIME_TOLERANCE`
        (relative, at least that many seconds) of the end time is the end time: it is dropped, so no step
        is a sliver of round-off and no time lies beyond the end.

        Parameters
        ----------
        dt_s : the step [s], positive and finite
        keep_rows : also keep every row's own time (the union of the grid and the rows): a kink of the loads
            stays on a step boundary and outputs at the rows need no interpolation (the CD training's grid)
        """
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive and finite, got {dt_s}")
        time_s = np.asarray(self.time_s, float)
        t0, t1 = time_s[0], time_s[-1]
        t = np.arange(t0, t1, dt_s)
        t = np.append(t[t < t1 - END_TIME_TOLERANCE * max(1.0, abs(t1))], t1)
        if keep_rows:
            t = np.union1d(t, time_s)
        V = np.asarray(self.values, float)
        values = np.empty((t.size, V.shape[1]))
        for j in range(V.shape[1]):
            values[:, j] = np.interp(t, time_s, V[:, j])
        return Loads(t, values, self.names)


def control_character(text: str) -> str | None:
    """The first control character in ``text`` (a newline, a tab, an escape, a line separator), or None.

    Names that reach a listing, a log line or a CNC file (load cases, CD metadata, file names) must
    have none: a newline in a name would forge a line.
    """
    for c in text:
        if unicodedata.category(c) in ("Cc", "Zl", "Zp"):
            return c
    return None


def value_problem(column: str, value: float) -> str | None:
    """Why ``value`` cannot be in a loads (or trace air) column, or None when it is plausible.

    A ``*_W`` column holds a heat power: finite, not negative beyond :data:`POWER_ROUND_OFF_W`, at
    most :data:`MAX_HEAT_POWER_W`.  A ``*_degC`` column holds an air temperature: finite, within
    :data:`TEMPERATURE_RANGE_DEGC` (and never below absolute zero).  Other columns: finite.

    Parameters
    ----------
    column : the column name (its unit suffix decides the check)
    value : the value [W or °C]
    """
    if not math.isfinite(value):
        return f"value {value} is not finite"
    if column.endswith(POWER_SUFFIX):
        if value < -POWER_ROUND_OFF_W:
            return f"a heat power cannot be negative, got {value} W"
        if value > MAX_HEAT_POWER_W:
            return f"heat power {value:g} W is beyond the plausible maximum of {MAX_HEAT_POWER_W:g} W per input"
    elif column.endswith(TEMPERATURE_SUFFIX):
        if value < ABSOLUTE_ZERO_DEGC:
            return f"temperature {value:g} °C is below absolute zero ({ABSOLUTE_ZERO_DEGC} °C)"
        lo, hi = TEMPERATURE_RANGE_DEGC
        if not lo <= value <= hi:
            return f"temperature {value:g} °C is outside the plausible range [{lo:g}, {hi:g}] °C"
    return None


def check_loads(loads: Loads, source: str = "loads") -> Loads:
    """``loads`` with every value checked by :func:`value_problem` and its times by the loads-CSV rules.

    Times must be finite, within ±:data:`MAX_TIME_S`, strictly increasing and span at most
    :data:`MAX_SPAN_S`; a power negative only by round-off is set to 0.  For loads made in memory
    (rows counted from 1); :func:`hybridcomp.models.loads.read_loads` makes the same checks naming
    the file's lines.

    Raises
    ------
    LoadsColumnError
        naming ``source``, the row, the column and the value.
    """
    t = np.asarray(loads.time_s, float)
    V = np.asarray(loads.values, float)
    for j, name in enumerate(loads.names):
        col = V[:, j]
        lo, hi = TEMPERATURE_RANGE_DEGC
        ok = np.isfinite(col)
        if name.endswith(POWER_SUFFIX):
            ok &= (col >= -POWER_ROUND_OFF_W) & (col <= MAX_HEAT_POWER_W)
        elif name.endswith(TEMPERATURE_SUFFIX):
            ok &= (col >= lo) & (col <= hi)
        if not ok.all():
            i = int(np.argmin(ok))
            raise LoadsColumnError(f"{source}: row {i + 1}, column {name!r}: {value_problem(name, float(col[i]))}")
    problem = time_problem(t)
    if problem is not None:
        i, why = problem
        raise LoadsColumnError(f"{source}: row {i + 1}: {why}")
    powers = [j for j, n in enumerate(loads.names) if n.endswith(POWER_SUFFIX)]
    if powers and (V[:, powers] < 0).any():
        V = V.copy()
        V[:, powers] = np.maximum(V[:, powers], 0.0)
        return Loads(t, V, loads.names)
    return loads


class ResultError(HybridcompError, ValueError):
    """A computed result that is not finite or not physically possible: never written as a result."""


def check_result(time_s: np.ndarray, columns: Sequence[str], values: np.ndarray, what: str = "the result") -> None:
    """Refuse a computed table with a non-finite or implausible value, naming the column, the time and the value.

    ``*_degC`` columns are temperatures (within [-273.15, :data:`MAX_RESULT_TEMPERATURE_DEGC`] °C), every other
    column a drift or error in µm (within ±:data:`MAX_RESULT_DRIFT_UM`).

    Parameters
    ----------
    time_s : (nt,) times [s]
    columns : the column names, one per column of ``values``
    values : (nt, len(columns)) the computed values
    what : what computed them, for the message

    Raises
    ------
    ResultError
        at the first bad value: ``<what>: column 'T1_degC' is 1e+281 at t = 60 s, ...; nothing is written``.
    """
    values = np.asarray(values, dtype=float).reshape(len(time_s), len(columns))
    temp = np.array([c.endswith("_degC") for c in columns], dtype=bool)
    lo = np.where(temp, ABSOLUTE_ZERO_DEGC, -MAX_RESULT_DRIFT_UM)
    hi = np.where(temp, MAX_RESULT_TEMPERATURE_DEGC, MAX_RESULT_DRIFT_UM)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (values < lo) | (values > hi)
    if not bad.any():
        return
    i, j = (int(k[0]) for k in np.nonzero(bad))
    v = values[i, j]
    if not np.isfinite(v):
        why = "not finite"
    elif temp[j]:
        why = (f"below absolute zero ({ABSOLUTE_ZERO_DEGC:g} °C)" if v < lo[j] else
               f"above {MAX_RESULT_TEMPERATURE_DEGC:g} °C, where every solid has melted")
    else:
        why = f"beyond ±{MAX_RESULT_DRIFT_UM:g} µm (1 m)"
    raise ResultError(f"{what}: column {columns[j]!r} is {v:g} at t = {float(time_s[i]):g} s, {why}: not a machine's "
                      "result (check the machine file's materials, zones and the loads); nothing is written")


def time_problem(time_s: np.ndarray) -> tuple[int, str] | None:
    """(index, why) of the first time that breaks the loads-CSV rules (see :func:`check_loads`), or None."""
    t = np.asarray(time_s, float)
    bad = ~np.isfinite(t) | (np.abs(t) > MAX_TIME_S)
    if bad.any():
        i = int(np.argmax(bad))
        return i, f"time_s {t[i]:g} is not finite or beyond ±{MAX_TIME_S:g} s"
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        return i, f"time_s {t[i]} does not increase after {t[i - 1]}"
    if t.size and t[-1] - t[0] > MAX_SPAN_S:
        return t.size - 1, (f"time_s {t[-1]:g} is {t[-1] - t[0]:g} s after the first time {t[0]:g} s: loads may span at "
                            f"most {MAX_SPAN_S:g} s ({MAX_SPAN_S / 86400 / 365.25:.1f} years)")
    return None


def in_model_order(loads: Loads, layout: InputLayout | Machine, source: str = "loads") -> Loads:
    """The same loads with every input column of ``layout`` (or of a machine's layout), in its order.

    A missing heat input is zero power, a missing zone the reference temperature; an unknown column is an error.
    """
    if not isinstance(layout, InputLayout):
        layout = layout.layout()
    return Loads(loads.time_s, layout.complete(loads.names, loads.values, source), layout.columns)


def input_layout(machine: Machine) -> InputLayout:
    """The input layout of a machine (its heat sources, zones and sensors in file order)."""
    heat: list[str] = []
    per_source = []
    for s in machine.heat_sources:
        if s.kind == "fixed":
            names = [heat_input_name(s.name)]
        else:
            names = [heat_input_name(s.name, k + 1) for k in range(machine.axis(s.axis).n_segments)]
        per_source.append((s.name, tuple(range(len(heat), len(heat) + len(names)))))
        heat.extend(names)
    return InputLayout(
        heat_inputs=tuple(heat),
        zones=tuple(z.name for z in machine.zones),
        zone_air=tuple(z.air for z in machine.zones),
        sensors=tuple(s.name for s in machine.sensors),
        reference_temperature_degC=float(machine.reference_temperature_degC),
        source_inputs=tuple(per_source),
        model=f"machine {machine.name!r}",
    )


def layout_from_names(input_names: Sequence[str], output_names: Sequence[str],
                      reference_temperature_degC: float, model: str = "the model") -> InputLayout:
    """The layout of a model known by its input and output names (a saved reduced model).

    ``input_names`` are loads columns (``*_W`` then ``*_degC``), ``output_names`` sensors then
    ``dx``, ``dy``, ``dz`` (then any further rows, such as a diagnosis' per-body drift).  Zone air kinds
    are unknown there and taken as ambient.
    """
    heat = [n.removesuffix(POWER_SUFFIX) for n in input_names if n.endswith(POWER_SUFFIX)]
    zones = [n.removesuffix(TEMPERATURE_SUFFIX) for n in input_names if n.endswith(TEMPERATURE_SUFFIX)]
    if len(heat) + len(zones) != len(input_names) or list(input_names) != [power_column(q) for q in heat] + \
            [temperature_column(z) for z in zones]:
        raise LoadsColumnError(f"input names {list(input_names)} are not heat inputs (*_W) followed by zones (*_degC)")
    outputs = tuple(output_names)
    ns = _drift_start(outputs)
    if ns < 0:
        raise LoadsColumnError(f"output names {list(outputs)} have no {', '.join(DRIFT_OUTPUTS)} after the sensors")
    return InputLayout(tuple(heat), tuple(zones), ("ambient",) * len(zones), outputs[:ns],
                       float(reference_temperature_degC), model=model)


# -- outputs ---------------------------------------------------------------------------------------
#: the output groups of a model, in model order (:meth:`OutputLayout.indices`)
OUTPUT_GROUPS = ("sensors", "drift", "poses", "feedback", "bodies")


class OutputLayoutError(HybridcompError, ValueError):
    """A model's output names and metadata do not form the typed groups; the message names the output or field."""


def pose_output_names(k: int) -> tuple[str, ...]:
    """Output names of the drift at support pose ``k`` (k ≥ 1) of a pose-aware model: ``dx@k``, ``dy@k``, ``dz@k`` [m]."""
    return tuple(f"{d}@{k}" for d in DRIFT_OUTPUTS)


def feedback_output_names(axis: str, positions_mm: Sequence[float]) -> tuple[str, ...]:
    """Output names of a drive's positioning error at positions over its axis' travel: ``e<axis>@<x>`` [m]."""
    return tuple(f"e{axis}@{p:g}" for p in positions_mm)


def body_output_names(body: str) -> tuple[str, ...]:
    """Output names of one body's share of the drift (a diagnosis' expansion rows): ``dx@<body>`` … [m]."""
    return tuple(f"{d}@{body}" for d in DRIFT_OUTPUTS)


@dataclass(frozen=True)
class FeedbackOutputs:
    """One drive's positioning-error outputs [m], at positions over its axis' travel (linear between them).

    Attributes
    ----------
    axis : the axis (``X``)
    feedback : the drive's feedback kind (``rotary_encoder``, ``linear_scale``)
    positions_mm : axis positions of the outputs [mm]
    names : output names, one per position
    indices : output indices, one per position
    direction : the drift direction the error adds to (0, 1, 2: dx, dy, dz)
    sign : +1 when the axis moves the tool, -1 when it moves the table
    """

    axis: str
    feedback: str
    positions_mm: tuple[float, ...]
    names: tuple[str, ...]
    indices: tuple[int, ...]
    direction: int
    sign: float


@dataclass(frozen=True)
class OutputLayout:
    """A model's outputs in typed groups, each found by name (:func:`output_layout`); no output is found by position.

    Groups (:data:`OUTPUT_GROUPS`): ``sensors`` (temperature rises [K]), ``drift`` (dx, dy, dz at the model's pose
    [m]), ``poses`` (dx, dy, dz at support pose k = 1 … of a pose-aware model [m]), ``feedback`` (each drive's
    positioning error over its travel [m]) and ``bodies`` (each body's share of the drift, a diagnosis' rows [m]).

    Attributes
    ----------
    names : every output name in model order
    sensors : sensor names, in output order
    sensor_indices : output index per sensor
    drift_indices : output indices of dx, dy, dz at the model's pose
    pose_rows : per support pose k = 1, 2, … the output indices of its dx, dy, dz
    feedback : per drive its :class:`FeedbackOutputs`, in the model's order
    body_rows : per body its name and the output indices of its dx, dy, dz
    """

    names: tuple[str, ...]
    sensors: tuple[str, ...]
    sensor_indices: tuple[int, ...]
    drift_indices: tuple[int, int, int]
    pose_rows: tuple[tuple[int, int, int], ...] = ()
    feedback: tuple[FeedbackOutputs, ...] = ()
    body_rows: tuple[tuple[str, tuple[int, int, int]], ...] = ()

    @property
    def n_poses(self) -> int:
        """Poses whose drift is an output: the model's own (k = 0) and every support pose."""
        return 1 + len(self.pose_rows)

    @property
    def bodies(self) -> tuple[str, ...]:
        return tuple(b for b, _ in self.body_rows)

    @property
    def feedback_axes(self) -> tuple[str, ...]:
        return tuple(f.axis for f in self.feedback)

    def pose_indices(self, k: int) -> tuple[int, int, int]:
        """Output indices of dx, dy, dz at pose ``k``: 0 the model's pose, 1 … the support poses."""
        if not 0 <= k < self.n_poses:
            raise OutputLayoutError(f"pose {k} has no drift outputs: the model has poses 0 … {self.n_poses - 1}")
        return self.drift_indices if k == 0 else self.pose_rows[k - 1]

    def feedback_of(self, axis: str) -> FeedbackOutputs:
        """The positioning-error outputs of the drive of ``axis``."""
        for f in self.feedback:
            if f.axis == axis:
                return f
        raise OutputLayoutError(f"axis {axis!r} has no positioning-error outputs "
                                f"(axes with outputs: {', '.join(self.feedback_axes) or 'none'})")

    def body_indices(self, body: str) -> tuple[int, int, int]:
        """Output indices of dx, dy, dz of one body's share of the drift."""
        for b, rows in self.body_rows:
            if b == body:
                return rows
        raise OutputLayoutError(f"body {body!r} has no drift outputs (bodies with outputs: {', '.join(self.bodies) or 'none'})")

    def indices(self, group: str, key: str | int | None = None) -> tuple[int, ...]:
        """Output indices of a group (:data:`OUTPUT_GROUPS`) or of one member of it.

        ``key``: a sensor name, a support pose k ≥ 1, an axis, a body.  A whole group's indices are in the order of
        :meth:`columns`.
        """
        if group == "sensors":
            return self.sensor_indices if key is None else (self.sensor_indices[self._member(self.sensors, key, group)],)
        if group == "drift":
            if key is not None:
                raise OutputLayoutError("the drift group has no members: indices('drift') gives dx, dy, dz")
            return self.drift_indices
        if group == "poses":
            if key is None:
                return tuple(i for rows in self.pose_rows for i in rows)
            if not (isinstance(key, int) and key >= 1):
                raise OutputLayoutError(f"a support pose is a number k ≥ 1, got {key!r} (pose 0 is the 'drift' group)")
            return self.pose_indices(key)
        if group == "feedback":
            return tuple(i for f in self.feedback for i in f.indices) if key is None else self.feedback_of(key).indices
        if group == "bodies":
            return tuple(i for _, rows in self.body_rows for i in rows) if key is None else self.body_indices(key)
        raise OutputLayoutError(f"unknown output group {group!r} (groups: {', '.join(OUTPUT_GROUPS)})")

    def columns(self, group: str) -> tuple[str, ...]:
        """Table columns of a whole group, in the order of :meth:`indices`, in file units.

        ``<sensor>_degC`` [°C]; ``dx_um`` …; ``pose<k>_dx_um`` …; ``<axis>_feedback_um@<x>`` (``x`` the axis
        position [mm]); ``<body>_dx_um`` … (drifts and errors [µm]).
        """
        if group == "sensors":
            return tuple(temperature_column(s) for s in self.sensors)
        if group == "drift":
            return DRIFT_COLUMNS
        if group == "poses":
            return tuple(f"pose{k}_{c}" for k in range(1, self.n_poses) for c in DRIFT_COLUMNS)
        if group == "feedback":
            return tuple(f"{f.axis}_feedback_um@{p:g}" for f in self.feedback for p in f.positions_mm)
        if group == "bodies":
            return tuple(f"{b}_{c}" for b in self.bodies for c in DRIFT_COLUMNS)
        raise OutputLayoutError(f"unknown output group {group!r} (groups: {', '.join(OUTPUT_GROUPS)})")

    def take(self, Y: np.ndarray, group: str, key: str | int | None = None) -> np.ndarray:
        """The columns of outputs ``Y`` (… × outputs, model units) that :meth:`indices` names."""
        return np.asarray(Y)[..., list(self.indices(group, key))]

    @staticmethod
    def _member(members: tuple[str, ...], key, group: str) -> int:
        if key not in members:
            raise OutputLayoutError(f"{key!r} is not in output group {group!r} ({', '.join(members)})")
        return members.index(key)


def _drift_start(outputs: tuple[str, ...]) -> int:
    """Index of ``dx`` in output names where ``dx``, ``dy``, ``dz`` follow one another, or -1."""
    ns = outputs.index(DRIFT_OUTPUTS[0]) if DRIFT_OUTPUTS[0] in outputs else -1
    return ns if ns >= 0 and outputs[ns:ns + 3] == DRIFT_OUTPUTS else -1


def output_layout(output_names: Sequence[str], meta: Mapping | None = None, model: str = "the model") -> OutputLayout:
    """The typed outputs of a model from its output names and the metadata a reduced model records.

    The names are the sensors, then ``dx``, ``dy``, ``dz`` (the model's pose), then in any order: per support pose
    k = 1 … n - 1 of ``meta["poses"]["poses"]`` (n poses) :func:`pose_output_names`; per axis of
    ``meta["feedback"]`` the names its ``"outputs"`` list at its ``"positions_mm"``; per body
    :func:`body_output_names`.  ``meta["n_sensors"]``, where given, must agree.  Files written before the layout
    existed carry exactly these names and fields, so they load as they are.

    Raises
    ------
    OutputLayoutError
        no drift after the sensors, a missing or repeated output of a group, or an output no group holds; the message
        names it and ``model``.
    """
    outputs = tuple(output_names)
    meta = meta or {}
    ns = _drift_start(outputs)
    if ns < 0:
        raise OutputLayoutError(f"{model}: output names {list(outputs)} have no {', '.join(DRIFT_OUTPUTS)} after the sensors")
    if "n_sensors" in meta and int(meta["n_sensors"]) != ns:
        raise OutputLayoutError(f"{model}: field 'n_sensors' is {meta['n_sensors']}, but {ns} outputs precede "
                                f"{', '.join(DRIFT_OUTPUTS)}")
    index = {n: i for i, n in enumerate(outputs)}
    if len(index) != len(outputs):
        twice = next(n for n in outputs if outputs.count(n) > 1)
        raise OutputLayoutError(f"{model}: output {twice!r} appears more than once")
    claimed = set(range(ns + 3))

    def find(names: Sequence[str], what: str) -> tuple[int, ...]:
        missing = [n for n in names if n not in index]
        if missing:
            raise OutputLayoutError(f"{model}: output {missing[0]!r} of {what} is missing")
        rows = tuple(index[n] for n in names)
        if claimed.intersection(rows):
            raise OutputLayoutError(f"{model}: output {outputs[min(claimed.intersection(rows))]!r} of {what} "
                                    "belongs to another group as well")
        claimed.update(rows)
        return rows

    poses = meta.get("poses") or {}
    n_poses = len(poses.get("poses", ()))
    pose_rows = tuple(find(pose_output_names(k), f"support pose {k}") for k in range(1, n_poses))
    feedback = []
    for axis, fb in (meta.get("feedback") or {}).items():
        names, positions = tuple(fb["outputs"]), tuple(float(p) for p in fb["positions_mm"])
        if len(names) != len(positions):
            raise OutputLayoutError(f"{model}: field 'feedback.{axis}' has {len(names)} outputs at "
                                    f"{len(positions)} positions")
        feedback.append(FeedbackOutputs(str(axis), str(fb.get("feedback", "")), positions, names,
                                        find(names, f"axis {axis}'s positioning error"), int(fb["direction"]),
                                        float(fb["sign"])))
    bodies = []
    for i, name in enumerate(outputs):
        if i in claimed:
            continue
        body = name.partition("@")[2]
        if not body or name != body_output_names(body)[0]:
            raise OutputLayoutError(f"{model}: output {name!r} belongs to no group (sensors, {', '.join(DRIFT_OUTPUTS)}, "
                                    "support poses, feedback, bodies)")
        bodies.append((body, find(body_output_names(body), f"body {body!r}")))
    return OutputLayout(outputs, outputs[:ns], tuple(range(ns)), (ns, ns + 1, ns + 2), pose_rows, tuple(feedback),
                        tuple(bodies))
