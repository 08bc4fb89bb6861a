"""CNC forms of a volumetric table (:mod:`hybridcomp.rom.volumetric`): a generic CSV and JSON, and Siemens 840D sl.

Sign convention as in :mod:`hybridcomp.chardiag.export`: the table holds the *drift* of the TCP against the table
[µm]; the *compensation* written for the control is its negative, in the same (relative, tool-against-workpiece)
axis directions.  Every value passes :mod:`hybridcomp.chardiag.guard` first: a compensation that is not finite
or beyond the clamp (default ±1000 µm), or a slope, step or position that is not finite, raises
:class:`~hybridcomp.chardiag.guard.OffsetGuardError` and nothing is written.

Generic forms
-------------
* :func:`table_csv`: one row per grid point (C order, the last axis fastest): the axis positions ``<axis>_mm``
  and the compensation ``comp_dx_um, comp_dy_um, comp_dz_um`` there (structure and drives, the table's full
  drift, negated); :func:`read_table_csv` reads it back.
* :func:`table_json`: the table's dict form (:func:`~hybridcomp.rom.volumetric.table_to_dict`, the *drift*) as
  strict JSON, after the same guard on the compensation it implies.

Siemens 840D sl
---------------
(i) Temperature compensation (function K3), per axis the error line ``ΔK = K0 + tan β · (P − P0)`` in the setting
data SD43900 ``$SA_TEMP_COMP_ABS_VALUE`` (K0 [mm]), SD43910 ``$SA_TEMP_COMP_SLOPE`` (tan β [-]) and SD43920
``$SA_TEMP_COMP_REF_POSITION`` (P0 [mm]), active through MD32750 ``$MA_TEMP_COMP_TYPE`` (bit 0 the
position-independent K0, bit 1 the position-dependent line; MD32760 ``$MA_COMP_ADD_VELO_FACTOR`` limits the
compensation per interpolation cycle and tan β).  :func:`k3_offsets` fits the line, least squares, to the
compensation along each axis, in the axis' own direction, over the axis' support points and its drive's error
points, the other axes at the model's pose; P0 is the axis' position at the model's pose.  Setting data can be
rewritten while the machine runs: this is the form for the 5 s update.

(ii) Interpolatory compensation tables (the "sag" / cross-error compensation, CEC): per input axis A and output
direction B a table ``t`` of the compensation in B along A::

    $AN_CEC[t,i]             compensation at point i [mm]
    $AN_CEC_INPUT_AXIS[t]    base axis A (its setpoint is the table's input)
    $AN_CEC_OUTPUT_AXIS[t]   compensation axis (the axis of direction B)
    $AN_CEC_STEP[t]          distance between the points [mm]
    $AN_CEC_MIN[t]           position of point 0 [mm]
    $AN_CEC_MAX[t]           position of the last point [mm]
    $AN_CEC_DIRECTION[t]     0: both directions of travel
    $AN_CEC_MULT_BY_TABLE[t] 0: no table multiplication (not used here)
    $AN_CEC_IS_MODULO[t]     0: no modulo

The control adds the tables of an output axis, so the tables are the star decomposition of the table: the first
input axis' tables carry the compensation at the model's pose, every other axis' tables the change along that axis
from the model's pose (zero there).  That is exact along the lines through the model's pose; what two axes do
together (the grid's products) is not in per-axis tables, and the program's header states how far the sum of the
tables is from the table at its grid points.  The points must be evenly spaced: :func:`cec_tables` takes the
fewest evenly spaced points (at most ``max_points``) that hit every support point of the axis and its drive's
error points, else the support points alone, else ``max_points`` (the header states the largest difference
between the table and its piecewise-linear form along each axis).

Machine data the tables need (commissioning; the tables sit in static memory and are loaded only while the
compensation is off):

* MD18342 ``$MN_MM_CEC_MAX_POINTS[t]`` ≥ the points of table t (memory, formatted at the next run-up);
* MD32710 ``$MA_CEC_ENABLE[<axis>]`` = 1 per compensation axis (must be 0 while a table is loaded);
* SD41300 ``$SN_CEC_TABLE_ENABLE[t]`` = 1 per table;
* MD32720 ``$MA_CEC_MAX_SUM[<axis>]`` the largest total compensation and MD32730 ``$MA_CEC_MAX_VELO[<axis>]``
  its largest rate of change (names from the function manual's list, not checked against a manual here);
* ``$AN_CEC_MULT_BY_TABLE`` is not used (0).

Checked against the SINUMERIK 840D sl function manual K3 (extended functions): the K3 setting and machine data
above, the ``$AN_CEC*`` variables with their meanings, MD18342, MD32710 and SD41300; the program form (header
``%_N_NC_CEC_INI``, ``CHANDATA(1)``, ``$AN_CEC[t,i]`` in mm, the axes as ``$AN_CEC_INPUT_AXIS[t]=(AX2)``, the
table parameters after the values, one table after the other) against the sag-compensation table example of the
K3 function manual (SINUMERIK 802D sl, 11/2012, section 11.3 "Interpolatory compensation"; the 840D sl manual
describes the same variables).  Not checked: MD32720/MD32730 and the closing ``M17`` of a ``_N_NC_CEC_INI``
program (the manual's excerpt ends in its table values; its encoder example closes with ``M17``): compare with
the control's own documentation before loading.  The tables are a commissioning form, for a compensation that is
updated rarely; the running compensation goes through K3 or the generic table.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hybridcomp.chardiag.export import AxisOffset, siemens_840d
from hybridcomp.chardiag.guard import DEFAULT_CLAMP_UM, guard_finite, guard_offsets
from hybridcomp.models import jsonio
from hybridcomp.models.layout import control_character
from hybridcomp.rom.volumetric import VolumetricTable, interpolate, table_to_dict

#: the compensation columns of the generic CSV
COMP_COLUMNS = ("comp_dx_um", "comp_dy_um", "comp_dz_um")
#: the most points of one CEC table :func:`cec_tables` chooses
DEFAULT_CEC_POINTS = 257
_XYZ = "xyz"


def _guard_grid(table: VolumetricTable, clamp_um: float, source: str) -> np.ndarray:
    """The compensation (n_points × 3) [µm] at the grid points, guarded, and every stored entry's too."""
    P = table.grid.points_mm()
    comp = -interpolate(table, P)
    guard_offsets({f"{_XYZ[d]} at {_at(table, p)}": comp[i, d] for i, p in enumerate(P) for d in range(3)},
                  clamp_um=clamp_um, source=source)
    guard_offsets({f"{fb.axis} drive at {x:g} mm": -e for fb in table.feedback_um
                   for x, e in zip(fb.positions_mm, fb.error_um)}, clamp_um=clamp_um, source=source)
    return comp


def _at(table: VolumetricTable, p) -> str:
    return " ".join(f"{a}={x:g}" for a, x in zip(table.grid.axes, p))


def table_csv(table: VolumetricTable, clamp_um: float = DEFAULT_CLAMP_UM) -> str:
    """CSV: one row per grid point, ``<axis>_mm`` … then ``comp_dx_um, comp_dy_um, comp_dz_um`` (−drift) [µm].

    Raises :class:`~hybridcomp.chardiag.guard.OffsetGuardError` (nothing written) when a compensation is not
    finite or beyond ±``clamp_um``.
    """
    comp = _guard_grid(table, clamp_um, "CNC export (volumetric table, CSV)")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([f"{a.lower()}_mm" for a in table.grid.axes] + list(COMP_COLUMNS))
    for p, c in zip(table.grid.points_mm(), comp):
        w.writerow([repr(float(x)) for x in p] + [repr(float(v)) for v in c])
    return buf.getvalue()


def read_table_csv(text: str) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """Axis names, positions (n × axes) [mm] and compensation (n × 3) [µm] of :func:`table_csv`'s text."""
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(rows[0][-3:]) != COMP_COLUMNS or not all(c.endswith("_mm") for c in rows[0][:-3]):
        raise ValueError(f"not a volumetric table CSV: header {rows[0] if rows else None}")
    axes = tuple(c[:-3].upper() for c in rows[0][:-3])
    body = np.array([[float(v) for v in r] for r in rows[1:]], float).reshape(len(rows) - 1, len(rows[0]))
    return axes, body[:, :-3], body[:, -3:]


def table_json(table: VolumetricTable, clamp_um: float = DEFAULT_CLAMP_UM) -> str:
    """The table's dict form (the drift) as strict JSON, after the guard on the compensation it implies."""
    _guard_grid(table, clamp_um, "CNC export (volumetric table, JSON)")
    return jsonio.dumps(table_to_dict(table), indent=1) + "\n"


def axis_directions(table: VolumetricTable, directions: Mapping[str, int] | None = None) -> dict[str, int]:
    """The direction (0, 1, 2) each grid axis moves in: ``directions``, else its drive's, else its name's (X, Y, Z).

    Raises ValueError for an axis none of them names.
    """
    out = {fb.axis: fb.direction for fb in table.feedback_um}
    out.update(directions or {})
    for a in table.grid.axes:
        if a not in out:
            if a.upper() not in ("X", "Y", "Z"):
                raise ValueError(f"CNC export: the direction of axis {a!r} is unknown (no drive, not X/Y/Z): "
                                 "give it in directions")
            out[a] = "XYZ".index(a.upper())
    return {a: int(out[a]) for a in table.grid.axes}


def _line(table: VolumetricTable, axis: str, x: np.ndarray) -> np.ndarray:
    """The compensation (n × 3) [µm] at positions ``x`` of ``axis``, the others at the model's pose."""
    i = table.grid.axes.index(axis)
    P = np.tile(np.asarray(table.grid.reference_mm(), float), (x.size, 1))
    P[:, i] = x
    return -interpolate(table, P)


def _axis_points(table: VolumetricTable, axis: str) -> np.ndarray:
    pts = list(table.grid.positions_mm[table.grid.axes.index(axis)])
    for fb in table.feedback_um:
        if fb.axis == axis:
            pts += fb.positions_mm.tolist()
    return np.unique(np.round(np.asarray(pts, float), 9))


def k3_offsets(table: VolumetricTable, directions: Mapping[str, int] | None = None,
               clamp_um: float = DEFAULT_CLAMP_UM) -> tuple[AxisOffset, ...]:
    """The K3 error line of every grid axis, fitted to the compensation along it (module docstring).

    Returns :class:`~hybridcomp.chardiag.export.AxisOffset` per axis: ``compensation_um`` K0 at ``reference_mm`` P0
    (the model's pose), ``slope`` tan β of the compensation [-], ``drift_um`` = −K0.

    Raises :class:`~hybridcomp.chardiag.guard.OffsetGuardError` when a compensation of the table (at a grid point,
    a drive's point or along an axis) is not finite or beyond ±``clamp_um``.
    """
    _guard_grid(table, clamp_um, "CNC export (K3 of a volumetric table)")  # the whole table, not only the lines
    dirs = axis_directions(table, directions)
    ref = table.grid.reference_mm()
    out = []
    for i, a in enumerate(table.grid.axes):
        x = _axis_points(table, a)
        c = _line(table, a, x)[:, dirs[a]]
        guard_offsets({f"{a} at {v:g} mm": cv for v, cv in zip(x, c)}, clamp_um=clamp_um,
                      source="CNC export (K3 of a volumetric table)")
        slope_um_mm, k0 = np.polyfit(x - ref[i], c, 1)
        out.append(AxisOffset(axis=a, drift_um=float(-k0), compensation_um=float(k0), slope=float(slope_um_mm) * 1e-3,
                              reference_mm=float(ref[i]), outside=False))
    return tuple(out)


def siemens_k3(table: VolumetricTable, axis_names: Mapping[str, str] | None = None, header: str = "",
               directions: Mapping[str, int] | None = None, clamp_um: float = DEFAULT_CLAMP_UM) -> str:
    """The K3 setting data SD43900/SD43910/SD43920 per axis of :func:`k3_offsets` as a part-program fragment.

    Written by :func:`hybridcomp.chardiag.export.siemens_840d`: ``axis_names`` axis → the control's identifier
    (default ``X1``), ``header`` a comment line.
    """
    names = {a: f"{a}1" for a in table.grid.axes}
    names.update(axis_names or {})
    return siemens_840d(k3_offsets(table, directions, clamp_um), names, header, clamp_um)


@dataclass(frozen=True)
class CecTable:
    """One interpolatory compensation table: the compensation in ``output`` along ``input``.

    Attributes
    ----------
    index : table index t
    input : the grid axis whose position is the input
    output : the grid axis that moves in the compensated direction
    min_mm, step_mm : position of point 0 and the distance between points [mm]
    values_um : compensation at the points [µm]
    """

    index: int
    input: str
    output: str
    min_mm: float
    step_mm: float
    values_um: tuple[float, ...]

    @property
    def max_mm(self) -> float:
        return self.min_mm + self.step_mm * (len(self.values_um) - 1)

    def positions_mm(self) -> np.ndarray:
        return self.min_mm + self.step_mm * np.arange(len(self.values_um))


def _even_points(lo: float, hi: float, must: list[np.ndarray], max_points: int) -> int:
    """The fewest evenly spaced points over [lo, hi] that hit every position of a list of ``must``.

    The first list that can be hit within ``max_points`` wins; if none, ``max_points``.
    """
    for need in must:
        for n in range(2, max_points + 1):
            step = (hi - lo) / (n - 1)
            s = (need - lo) / step
            if np.all(np.abs(s - np.round(s)) * step < 1e-6):  # within 1 nm
                return n
    return max_points


def cec_tables(table: VolumetricTable, directions: Mapping[str, int] | None = None,
               max_points: int = DEFAULT_CEC_POINTS) -> tuple[CecTable, ...]:
    """The star decomposition of the table into per-axis CEC tables (module docstring), input axis first."""
    if not (isinstance(max_points, int) and max_points >= 2):
        raise ValueError(f"CNC export (CEC): max_points must be an integer ≥ 2, got {max_points!r}")
    dirs = axis_directions(table, directions)
    by_dir = {}
    for a, d in dirs.items():
        by_dir.setdefault(d, a)
    g = table.grid
    pose = -interpolate(table, np.asarray([g.reference_mm()], float))[0]
    out = []
    for i, a in enumerate(g.axes):
        pos = g.positions_mm[i]
        lo, hi = pos[0], pos[-1]
        drive = _axis_points(table, a)
        n = _even_points(lo, hi, [drive, np.asarray(pos)], max_points)
        x = np.linspace(lo, hi, n)
        c = _line(table, a, x)
        if i > 0:
            c = c - pose
        for d in range(3):
            if d not in by_dir:
                continue
            out.append(CecTable(len(out), a, by_dir[d], float(lo), float((hi - lo) / (n - 1)),
                                tuple(float(v) for v in c[:, d])))
    return tuple(out)


def cec_sum(tables: tuple[CecTable, ...], directions: Mapping[str, int], axes: tuple[str, ...],
            positions_mm: np.ndarray) -> np.ndarray:
    """What the control adds from ``tables`` at positions (n × axes) [mm]: compensation (n × 3) [µm]."""
    P = np.atleast_2d(np.asarray(positions_mm, float))
    out = np.zeros((P.shape[0], 3))
    for t in tables:
        out[:, directions[t.output]] += np.interp(P[:, axes.index(t.input)], t.positions_mm(), t.values_um)
    return out


def siemens_cec(table: VolumetricTable, axis_names: Mapping[str, str] | None = None, header: str = "",
                directions: Mapping[str, int] | None = None, clamp_um: float = DEFAULT_CLAMP_UM,
                max_points: int = DEFAULT_CEC_POINTS) -> str:
    """The CEC tables of :func:`cec_tables` as an init program (values in mm).

    The module docstring lists the machine data.  ``axis_names``: grid axis → the control's machine axis
    identifier (default ``X1``, ``Y1``, ``Z1``).

    Raises
    ------
    OffsetGuardError
        a compensation not finite or beyond ±``clamp_um``, or a position or step not finite; nothing written
    ValueError
        a header or axis identifier with a control character (it would forge a program line)
    """
    source = "CNC export (Siemens 840D sl CEC tables)"
    _guard_grid(table, clamp_um, source)
    dirs = axis_directions(table, directions)
    tables = cec_tables(table, dirs, max_points)
    names = {a: f"{a}1" for a in table.grid.axes}
    names.update(axis_names or {})
    for text in (header, *names.values()):
        c = control_character(text)
        if c is not None:
            raise ValueError(f"{source}: {text!r} has a control character {c!r}")
    for t in tables:
        guard_offsets({f"table {t.index} ({t.input}→{t.output}) point {j}": v for j, v in enumerate(t.values_um)},
                      clamp_um=clamp_um, source=source)
        guard_finite({f"table {t.index} min": t.min_mm, f"table {t.index} step": t.step_mm}, source=source, unit="mm")
    P = table.grid.points_mm()
    gap = float(np.abs(cec_sum(tables, dirs, table.grid.axes, P) + interpolate(table, P)).max())
    lines = ["%_N_NC_CEC_INI", "CHANDATA(1)"]
    if header:
        lines.append(f"; {header}")
    lines += ["; hybridcomp volumetric table as interpolatory compensation tables (compensation = -drift) [mm]",
              f"; sum of the tables against the table at its {P.shape[0]} grid points: max |difference| = "
              f"{gap:.4f} um",
              "; needs MD18342 $MN_MM_CEC_MAX_POINTS[t] >= points, MD32710 $MA_CEC_ENABLE[axis] = 1 (0 while "
              "loading), SD41300 $SN_CEC_TABLE_ENABLE[t] = 1"]
    for t in tables:
        lines.append(f"; table {t.index}: {t.output} compensation along {t.input}, {len(t.values_um)} points")
        lines += [f"$AN_CEC[{t.index},{j}]={v * 1e-3:.7f}" for j, v in enumerate(t.values_um)]
        lines += [f"$AN_CEC_INPUT_AXIS[{t.index}]=({names[t.input]})",
                  f"$AN_CEC_OUTPUT_AXIS[{t.index}]=({names[t.output]})",
                  f"$AN_CEC_STEP[{t.index}]={t.step_mm:.6f}",
                  f"$AN_CEC_MIN[{t.index}]={t.min_mm:.6f}",
                  f"$AN_CEC_MAX[{t.index}]={t.max_mm:.6f}",
                  f"$AN_CEC_DIRECTION[{t.index}]=0",
                  f"$AN_CEC_MULT_BY_TABLE[{t.index}]=0",
                  f"$AN_CEC_IS_MODULO[{t.index}]=0"]
    lines.append("M17")
    return "\n".join(lines) + "\n"


_CEC_LINE = re.compile(r"^\$(AN_CEC\w*)\[(\d+)(?:,(\d+))?\]=(.*)$")


def read_cec(text: str) -> dict[int, dict]:
    """The tables of :func:`siemens_cec`'s text (a reader for checks, not for any program).

    Per index: ``values_mm`` (list), ``input``, ``output``, ``step``, ``min``, ``max``, ``direction``,
    ``mult_by_table``, ``is_modulo``.
    """
    out: dict[int, dict] = {}
    for line in text.splitlines():
        m = _CEC_LINE.match(line.strip())
        if not m:
            continue
        name, t, j, value = m.group(1), int(m.group(2)), m.group(3), m.group(4)
        d = out.setdefault(t, {"values_mm": {}})
        if name == "AN_CEC":
            d["values_mm"][int(j)] = float(value)
        elif name in ("AN_CEC_INPUT_AXIS", "AN_CEC_OUTPUT_AXIS"):
            d[name.removeprefix("AN_CEC_").removesuffix("_AXIS").lower()] = value.strip("()")
        else:
            d[name.removeprefix("AN_CEC_").lower()] = float(value)
    for d in out.values():
        v = d["values_mm"]
        if sorted(v) != list(range(len(v))):
            raise ValueError(f"CEC table: points {sorted(v)} are not 0..{len(v) - 1}")
        d["values_mm"] = [v[j] for j in range(len(v))]
    return out


def read_k3(text: str) -> dict[str, dict[str, float]]:
    """The K3 setting data of :func:`siemens_k3`'s text: per control axis ``abs`` [mm], ``slope`` [-], ``ref`` [mm]."""
    keys = {"$SA_TEMP_COMP_ABS_VALUE": "abs", "$SA_TEMP_COMP_SLOPE": "slope", "$SA_TEMP_COMP_REF_POSITION": "ref"}
    out: dict[str, dict[str, float]] = {}
    for line in text.splitlines():
        m = re.match(r"^(\$SA_TEMP_COMP_\w+)\[(\w+)\]=(.*)$", line.strip())
        if m and m.group(1) in keys:
            v = float(m.group(3))
            if not math.isfinite(v):
                raise ValueError(f"K3 program: {line!r} is not finite")
            out.setdefault(m.group(2), {})[keys[m.group(1)]] = v
    return out


__all__ = ["COMP_COLUMNS", "CecTable", "DEFAULT_CEC_POINTS", "axis_directions", "cec_sum", "cec_tables",
           "k3_offsets", "read_cec", "read_k3", "read_table_csv", "siemens_cec", "siemens_k3", "table_csv",
           "table_json"]
