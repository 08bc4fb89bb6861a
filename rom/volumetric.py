"""Compensation where the tool is: the drift over a grid of support points and its interpolation in the NC cycle.

The pose-aware reduced model (:mod:`hybridcomp.rom.poses`) gives the drift, TCP minus table, at any pose through
:func:`~hybridcomp.rom.poses.drift_along`.  The control cannot run that at its 2–4 ms cycle, so the drift is
tabulated: every model step (5 s) the outputs ``y`` of the model become a :class:`VolumetricTable` over a
:class:`SupportGrid` of the workspace (:func:`table_of`, one matrix–vector product), and the control cycle
interpolates the table at the commanded position (:func:`interpolate`, :func:`interpolate_one`).

The table has two parts, the way the drift has them:

* the structure's drift (the FE model's support poses) at every grid point, multilinear between them;
* per feed drive its positioning error (``rom.meta["feedback"]``: a screw's or scale's error at ``FEEDBACK_POINTS``
  positions over its travel), linear in its own axis' position between its points, entering the drift only in
  the axis' direction with the sign of the side the axis moves (+1 tool side, −1 table side).

Both are linear in ``y``: :func:`table_operator` builds the map once by probing ``drift_along`` with unit outputs,
so the table stays what ``drift_along`` defines (and refuses to build when the drives' part of ``drift_along``
no longer matches the per-axis form the table keeps).  At the grid points the table equals ``drift_along`` to
round-off; between them the table interpolates linearly what the model interpolates quadratically between its
support poses (a finer :func:`default_grid` narrows the difference).

Positions outside the grid's box are clamped to it, axis by axis (the structure's part to the grid, each drive's
error to its own points): the reduced model itself refuses positions outside the travel, and a control that
commands a position outside the travel has other problems than the drift.
"""

from __future__ import annotations

import itertools
import math
from bisect import bisect_right
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.models.jsonio import check_versioned

#: the identifier of the dict (JSON) form of a table
TABLE_FORMAT = "hybridcomp.volumetric_table"
TABLE_VERSION = 1


class VolumetricError(HybridcompError, ValueError):
    """A support grid, table or position that cannot be used; the message names the axis or field and the value."""


def _finite_vector(values, n: int, what: str, names: Sequence[str] | None = None) -> np.ndarray:
    v = np.asarray(values, float)
    if v.shape != (n,):
        raise VolumetricError(f"{what} must have {n} entries, got shape {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        j = int(bad[0])
        raise VolumetricError(f"{what}: {names[j] if names else f'entry {j}'} = {v[j]} is not finite")
    return v


@dataclass(frozen=True)
class SupportGrid:
    """A tensor grid of support points over the workspace.

    Attributes
    ----------
    axes : axis names, in machine order
    positions_mm : per axis its support positions, strictly ascending, at least two [mm]
    pose_mm : the model's pose per axis, where the other axes stand for the per-axis CNC forms [mm]; None: the
        middle of each axis' range
    """

    axes: tuple[str, ...]
    positions_mm: tuple[tuple[float, ...], ...]
    pose_mm: tuple[float, ...] | None = None

    def __post_init__(self):
        object.__setattr__(self, "axes", tuple(str(a) for a in self.axes))
        if len(set(self.axes)) != len(self.axes) or not self.axes:
            raise VolumetricError(f"support grid: the axes must be distinct and at least one, got {list(self.axes)}")
        if len(self.positions_mm) != len(self.axes):
            raise VolumetricError(f"support grid: {len(self.positions_mm)} position lists for axes {list(self.axes)}")
        pos = []
        for a, p in zip(self.axes, self.positions_mm):
            p = tuple(float(x) for x in p)
            if len(p) < 2:
                raise VolumetricError(f"support grid: axis {a} needs at least 2 positions, got {list(p)}")
            if not all(math.isfinite(x) for x in p):
                raise VolumetricError(f"support grid: axis {a} has a position that is not finite: {list(p)}")
            if any(b <= c for c, b in zip(p, p[1:])):
                raise VolumetricError(f"support grid: the positions of axis {a} must rise strictly, got {list(p)}")
            pos.append(p)
        object.__setattr__(self, "positions_mm", tuple(pos))
        if self.pose_mm is not None:
            pose = tuple(float(x) for x in self.pose_mm)
            if len(pose) != len(self.axes):
                raise VolumetricError(f"support grid: pose_mm has {len(pose)} entries for axes {list(self.axes)}")
            for a, x, p in zip(self.axes, pose, pos):
                if not (math.isfinite(x) and p[0] <= x <= p[-1]):
                    raise VolumetricError(f"support grid: pose {a} = {x} mm is not inside [{p[0]:g}, {p[-1]:g}] mm")
            object.__setattr__(self, "pose_mm", pose)

    @property
    def shape(self) -> tuple[int, ...]:
        """Points per axis."""
        return tuple(len(p) for p in self.positions_mm)

    @property
    def n_points(self) -> int:
        return math.prod(self.shape)

    def points_mm(self) -> np.ndarray:
        """Every grid point (n_points × axes) [mm], C order (the last axis fastest)."""
        return np.array(list(itertools.product(*self.positions_mm)), float).reshape(self.n_points, len(self.axes))

    def reference_mm(self) -> tuple[float, ...]:
        """The model's pose, or the middle of each axis' range when the grid does not know it [mm]."""
        if self.pose_mm is not None:
            return self.pose_mm
        return tuple(0.5 * (p[0] + p[-1]) for p in self.positions_mm)

    def as_dict(self) -> dict:
        return {"axes": list(self.axes), "positions_mm": [list(p) for p in self.positions_mm],
                "pose_mm": None if self.pose_mm is None else list(self.pose_mm)}

    @staticmethod
    def from_dict(d: Mapping) -> SupportGrid:
        try:
            return SupportGrid(tuple(d["axes"]), tuple(tuple(p) for p in d["positions_mm"]), d.get("pose_mm"))
        except (KeyError, TypeError) as exc:
            raise VolumetricError(f"support grid: field {exc} missing or malformed") from None


def _axis_levels(lo: float, mid: float, hi: float, n: int, axis: str) -> tuple[float, ...]:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise VolumetricError(f"support grid: axis {axis} needs an integer number of points ≥ 2, got {n!r}")
    if n == 2:
        return (lo, hi)
    if n % 2:  # the model's pose a support point, evenly on either side: as the support poses' levels
        from hybridcomp.fem.poses import axis_levels

        return axis_levels(lo, mid, hi, n)
    return tuple(np.linspace(lo, hi, n).tolist())


def default_grid(rom, points: int | Sequence[int] = 3) -> SupportGrid:
    """The support grid over each axis' travel of a pose-aware reduced model.

    Parameters
    ----------
    rom : a pose-aware reduced model (:func:`hybridcomp.rom.poses.reduce_at_poses`)
    points : points per axis (one number for all, or one per axis in machine order): 2 the travel's ends; odd
        the ends and the model's pose with the points evenly spaced on either side of it (3: travel min, model
        pose, travel max, the support poses' levels); even ≥ 4 evenly spaced over the travel
    """
    from hybridcomp.rom.poses import grid_of

    pg = grid_of(rom)
    k = len(pg.axes)
    n = [points] * k if isinstance(points, (int, np.integer)) and not isinstance(points, bool) else list(points)
    if len(n) != k:
        raise VolumetricError(f"support grid: {len(n)} point counts for axes {list(pg.axes)}")
    levels = [_axis_levels(lo, mid, hi, m, a) for a, (lo, hi), mid, m in zip(pg.axes, pg.travel_mm, pg.model_pose_mm, n)]
    return SupportGrid(pg.axes, tuple(levels), pg.model_pose_mm)


class FeedbackRows(NamedTuple):
    """One drive's part of a :class:`TableOperator`: its error at ``positions_mm`` is ``rows @ y`` [µm]."""

    axis: str
    positions_mm: np.ndarray
    rows: np.ndarray
    direction: int
    sign: float


class FeedbackTable(NamedTuple):
    """One drive's part of a :class:`VolumetricTable`.

    Its positioning error ``error_um`` at ``positions_mm``, linear between them, is added to the drift in
    ``direction`` (0, 1, 2 for x, y, z) times ``sign``.
    """

    axis: str
    positions_mm: np.ndarray
    error_um: np.ndarray
    direction: int
    sign: float


@dataclass(frozen=True, eq=False)
class TableOperator:
    """The linear map from a pose-aware reduced model's outputs ``y`` (q,) [K, m] to a :class:`VolumetricTable`.

    Attributes
    ----------
    grid : the support grid
    structure : (n_points · 3, q) the structure's drift [µm] per unit output, grid points in C order, each dx, dy, dz
    feedback : per drive its :class:`FeedbackRows` (rows (m, q) [µm] per unit output)
    output_names : the reduced model's output names (q,)
    rom_id : the reduced model's identifier
    """

    grid: SupportGrid
    structure: np.ndarray
    feedback: tuple[FeedbackRows, ...]
    output_names: tuple[str, ...] = ()
    rom_id: str = ""

    @property
    def n_outputs(self) -> int:
        return self.structure.shape[1]


def _drives_part(feedback: Sequence, axes: Sequence[str], P: np.ndarray, q: int) -> np.ndarray:
    """The drives' drift (n × 3 × q) at points ``P`` per unit output, from the per-axis rows."""
    out = np.zeros((P.shape[0], 3, q))
    for fb in feedback:
        x = P[:, list(axes).index(fb.axis)]
        R = np.array([np.interp(x, fb.positions_mm, fb.rows[:, j]) for j in range(q)]).T  # n × q
        out[:, fb.direction] += fb.sign * R
    return out


def table_operator(rom, grid: SupportGrid | None = None) -> TableOperator:
    """The map from a pose-aware reduced model's outputs to its table over ``grid`` (default :func:`default_grid`).

    Built through :func:`hybridcomp.rom.poses.drift_along`, probed with unit outputs (``drift_along`` is linear
    in its outputs): the structure's part with ``feedback=False``; the drives' part is kept per axis from
    ``rom.meta["feedback"]`` and checked against what ``drift_along`` adds at every grid point.

    Raises
    ------
    VolumetricError
        the grid's axes are not the model's, or a grid position is outside an axis' travel, or the drives' part of
        ``drift_along`` is not the per-axis form of the table
    RomInputError
        not a pose-aware reduced model
    """
    from hybridcomp.rom.poses import drift_along, grid_of

    pg = grid_of(rom)
    grid = default_grid(rom) if grid is None else grid
    if tuple(grid.axes) != tuple(pg.axes):
        raise VolumetricError(f"support grid axes {list(grid.axes)} are not the model's {list(pg.axes)}")
    for a, p, (lo, hi) in zip(grid.axes, grid.positions_mm, pg.travel_mm):
        for x in p:
            if not lo - 1e-9 <= x <= hi + 1e-9:
                raise VolumetricError(f"support grid: axis {a} = {x:g} mm is outside the travel [{lo:g}, {hi:g}] mm")
    names = tuple(rom.output_names)
    q = len(names)
    E = np.eye(q)
    P = grid.points_mm()
    S = np.empty((P.shape[0], 3, q))
    full = np.empty_like(S)
    for i, p in enumerate(P):
        S[i] = drift_along(rom, E, p[None], feedback=False).T
        full[i] = drift_along(rom, E, p[None], feedback=True).T
    feedback = []
    for axis, fb in rom.meta.get("feedback", {}).items():
        if axis not in grid.axes:
            raise VolumetricError(f"drive of axis {axis} is not on the support grid's axes {list(grid.axes)}")
        pos = np.asarray(fb["positions_mm"], float)
        rows = np.zeros((pos.size, q))
        rows[np.arange(pos.size), [names.index(n) for n in fb["outputs"]]] = 1e6  # outputs [m] → [µm]
        direction, sign = int(fb["direction"]), float(fb["sign"])
        if direction not in (0, 1, 2) or sign not in (-1.0, 1.0):
            raise VolumetricError(f"drive of axis {axis}: direction {direction} / sign {sign} is not 0..2 / ±1")
        for arr in (pos, rows):
            arr.setflags(write=False)
        feedback.append(FeedbackRows(axis, pos, rows, direction, sign))
    mine = S + _drives_part(feedback, grid.axes, P, q)
    scale = max(float(np.abs(full).max()), 1.0)
    if not np.allclose(mine, full, rtol=0.0, atol=1e-9 * scale):
        i, d, j = np.unravel_index(int(np.abs(mine - full).argmax()), full.shape)
        raise VolumetricError(f"the drives' part of drift_along at {dict(zip(grid.axes, P[i].tolist()))} "
                              f"({'xyz'[d]}, output {names[j]}) is {full[i, d, j] - S[i, d, j]:.9g} µm per unit, "
                              f"the table's per-axis form gives {mine[i, d, j] - S[i, d, j]:.9g}: the table no "
                              "longer models what drift_along adds")
    structure = np.ascontiguousarray(S.reshape(P.shape[0] * 3, q))
    structure.setflags(write=False)
    return TableOperator(grid, structure, tuple(feedback), names, str(getattr(rom, "rom_id", "")))


class _Fast(NamedTuple):
    """Plain-Python copies of a table for :func:`interpolate_one`."""

    pos: tuple[list[float], ...]
    strides: tuple[int, ...]
    corners: tuple[tuple[int, tuple[bool, ...]], ...]
    offsets: tuple[int, ...]
    values: tuple[list[float], list[float], list[float]]
    drives: tuple[tuple[int, list[float], list[float], int, float], ...]


@dataclass(frozen=True, eq=False)
class VolumetricTable:
    """The drift, TCP minus table, over a support grid at one time.

    Attributes
    ----------
    grid : the support grid
    time_s : the time of the model state it comes from [s]
    structure_um : (n_1, …, n_k, 3) the structure's drift dx, dy, dz at the grid points [µm]
    feedback_um : per drive its :class:`FeedbackTable` [µm]
    """

    grid: SupportGrid
    time_s: float
    structure_um: np.ndarray
    feedback_um: tuple[FeedbackTable, ...] = ()
    _fast: _Fast | None = field(init=False, repr=False, default=None)

    def __post_init__(self):
        g = self.grid
        t = float(self.time_s)
        if not math.isfinite(t):
            raise VolumetricError(f"table time_s = {self.time_s!r} is not finite")
        object.__setattr__(self, "time_s", t)
        try:
            S = np.array(self.structure_um, float)
        except (TypeError, ValueError) as exc:
            raise VolumetricError(f"table structure_um is not an array of numbers: {exc}") from None
        if S.shape != g.shape + (3,):
            raise VolumetricError(f"table structure_um has shape {S.shape}, the grid {list(g.axes)} needs "
                                  f"{g.shape + (3,)}")
        bad = np.argwhere(~np.isfinite(S))
        if bad.size:
            at = {a: g.positions_mm[i][j] for i, (a, j) in enumerate(zip(g.axes, bad[0][:-1]))}
            raise VolumetricError(f"table structure_um at {at} ({'xyz'[bad[0][-1]]}) = {S[tuple(bad[0])]} is not "
                                  "finite")
        S.setflags(write=False)
        object.__setattr__(self, "structure_um", S)
        fbs = []
        for fb in self.feedback_um:
            axis, pos, err, d, sign = fb
            if axis not in g.axes:
                raise VolumetricError(f"table feedback axis {axis!r} is not a grid axis {list(g.axes)}")
            try:
                pos, err = np.array(pos, float), np.array(err, float)
            except (TypeError, ValueError) as exc:
                raise VolumetricError(f"table feedback of axis {axis}: not arrays of numbers: {exc}") from None
            if pos.ndim != 1 or pos.size < 2 or err.shape != pos.shape:
                raise VolumetricError(f"table feedback of axis {axis}: {pos.shape} positions and {err.shape} errors "
                                      "(need the same number, at least 2)")
            if not np.all(np.isfinite(pos)) or np.any(np.diff(pos) <= 0):
                raise VolumetricError(f"table feedback of axis {axis}: positions must be finite and rise strictly, "
                                      f"got {pos.tolist()}")
            if not np.all(np.isfinite(err)):
                j = int(np.flatnonzero(~np.isfinite(err))[0])
                raise VolumetricError(f"table feedback of axis {axis} at {pos[j]:g} mm = {err[j]} µm is not finite")
            if int(d) not in (0, 1, 2) or float(sign) not in (-1.0, 1.0):
                raise VolumetricError(f"table feedback of axis {axis}: direction {d!r} / sign {sign!r} is not "
                                      "0..2 / ±1")
            pos.setflags(write=False)
            err.setflags(write=False)
            fbs.append(FeedbackTable(str(axis), pos, err, int(d), float(sign)))
        object.__setattr__(self, "feedback_um", tuple(fbs))
        k = len(g.axes)
        strides = tuple(math.prod(g.shape[i + 1:]) for i in range(k))
        corners = tuple((sum(s for s, b in zip(strides, bits) if b), bits)
                        for bits in itertools.product((False, True), repeat=k))
        drives = tuple((g.axes.index(f.axis), f.positions_mm.tolist(), f.error_um.tolist(), f.direction, f.sign)
                       for f in fbs)
        flat = S.reshape(-1, 3).T
        object.__setattr__(self, "_fast", _Fast(tuple(list(p) for p in g.positions_mm), strides, corners,
                                                tuple(c[0] for c in corners),
                                                (flat[0].tolist(), flat[1].tolist(), flat[2].tolist()), drives))


def table_of(op: TableOperator, y: np.ndarray, time_s: float) -> VolumetricTable:
    """The table of the model outputs ``y`` (q,) [K, m] at ``time_s`` [s]: one matrix–vector product."""
    y = _finite_vector(y, op.n_outputs, "table_of: the model outputs y", op.output_names or None)
    S = (op.structure @ y).reshape(op.grid.shape + (3,))
    fb = tuple(FeedbackTable(f.axis, f.positions_mm, f.rows @ y, f.direction, f.sign) for f in op.feedback)
    return VolumetricTable(op.grid, time_s, S, fb)


def shifted(table: VolumetricTable, offset_um) -> VolumetricTable:
    """The table with a uniform ``offset_um`` (dx, dy, dz) [µm] added to its structure part (a probe's correction)."""
    off = _finite_vector(offset_um, 3, "shifted: offset_um", ("dx", "dy", "dz"))
    return VolumetricTable(table.grid, table.time_s, table.structure_um + off, table.feedback_um)


def _check_positions(table: VolumetricTable, positions_mm) -> np.ndarray:
    axes = table.grid.axes
    P = np.asarray(positions_mm, float)
    if P.ndim != 2 or P.shape[1] != len(axes):
        raise VolumetricError(f"positions need one column per axis {list(axes)} (N × {len(axes)}), got shape "
                              f"{P.shape}")
    bad = ~np.isfinite(P)
    if bad.any():
        i, a = (int(v) for v in np.argwhere(bad)[0])
        raise VolumetricError(f"position {axes[a]} = {P[i, a]} mm (row {i}) is not finite")
    return P


def _segments(pos: np.ndarray, x: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Index of the segment of ascending ``pos`` that holds each ``x`` (clamped to the first and last), into ``out``."""
    m = pos.size
    h = (pos[-1] - pos[0]) / (m - 1)
    if np.allclose(np.diff(pos), h, rtol=1e-12, atol=0.0):  # evenly spaced: arithmetic, no search
        t = (x - pos[0]) * (1.0 / h)
        np.floor(t, out=t)
        np.clip(t, 0, m - 2, out=t)
        out[:] = t
        # round-off at a point: the search's answer (x on a point belongs to the segment it starts)
        np.subtract(out, x < pos[out], out=out, casting="unsafe")
        np.add(out, x >= pos[np.minimum(out + 1, m - 1)], out=out, casting="unsafe")
        np.clip(out, 0, m - 2, out=out)
        return out
    out[:] = np.searchsorted(pos, x, side="right")
    out -= 1
    np.clip(out, 0, m - 2, out=out)
    return out


def interpolate(table: VolumetricTable, positions_mm: np.ndarray) -> np.ndarray:
    """The drift (N × 3) [µm] at axis positions (N × axes, machine order) [mm].

    Multilinear in the structure's grid plus each drive's error linear in its own axis' position, in its
    direction with its sign.  Positions outside the grid are clamped to its box (module docstring).  Written
    with preallocated buffers: 100,000 positions in a few ms.
    """
    P = _check_positions(table, positions_mm)
    g = table.grid
    f = table._fast
    n, k = P.shape
    base = np.zeros(n, np.intp)
    i = np.empty(n, np.intp)
    x = np.empty(n)
    t = np.empty(n)
    W = np.empty((2 ** k, n))  # the corner weights, first axis slowest (the order of f.corners)
    W[0] = 1.0
    m = 1
    for a, pos in enumerate(g.positions_mm):
        p = np.asarray(pos)
        np.clip(P[:, a], p[0], p[-1], out=x)
        _segments(p, x, i)
        np.subtract(x, np.take(p, i), out=t)
        np.multiply(t, np.take(1.0 / np.diff(p), i), out=t)
        i *= f.strides[a]
        base += i
        for j in range(m - 1, -1, -1):  # w → (w (1 − t), w t), in place from the top
            np.multiply(W[j], t, out=W[2 * j + 1])
            np.subtract(W[j], W[2 * j + 1], out=W[2 * j])
        m *= 2
    S = np.ascontiguousarray(table.structure_um.reshape(-1, 3).T)  # 3 × n_points
    out = np.zeros((3, n))
    buf = np.empty((3, n))
    for w, off in zip(W, f.offsets):
        np.add(base, off, out=i)
        np.take(S, i, axis=1, out=buf)
        buf *= w
        out += buf
    for fb in table.feedback_um:
        p = fb.positions_mm
        np.clip(P[:, g.axes.index(fb.axis)], p[0], p[-1], out=x)
        _segments(p, x, i)
        x -= np.take(p, i)
        x *= np.take(np.diff(fb.error_um) / np.diff(p), i)
        x += np.take(fb.error_um, i)
        if fb.sign < 0:
            out[fb.direction] -= x
        else:
            out[fb.direction] += x
    return out.T


def interpolate_one(table: VolumetricTable, position_mm) -> tuple[float, float, float]:
    """The drift (dx, dy, dz) [µm] at one position (axes, machine order) [mm].

    :func:`interpolate` in plain Python (no array is made; a few µs, for the control's cycle), clamped to the
    grid's box the same way.
    """
    f = table._fast
    if len(position_mm) != len(f.pos):
        raise VolumetricError(f"position needs one value per axis {list(table.grid.axes)}, got {len(position_mm)}")
    base = 0
    ws = [1.0]
    for a, pos in enumerate(f.pos):
        x = float(position_mm[a])
        if not math.isfinite(x):
            raise VolumetricError(f"position {table.grid.axes[a]} = {x} mm is not finite")
        if x <= pos[0]:
            i, t = 0, 0.0
        elif x >= pos[-1]:
            i, t = len(pos) - 2, 1.0
        else:
            i = bisect_right(pos, x) - 1
            t = (x - pos[i]) / (pos[i + 1] - pos[i])
        base += i * f.strides[a]
        u = 1.0 - t
        ws = [w * s for w in ws for s in (u, t)]
    vx, vy, vz = f.values
    dx = dy = dz = 0.0
    for w, off in zip(ws, f.offsets):
        j = base + off
        dx += w * vx[j]
        dy += w * vy[j]
        dz += w * vz[j]
    if not f.drives:
        return dx, dy, dz
    d = [dx, dy, dz]
    for a, pos, err, direction, sign in f.drives:
        x = float(position_mm[a])
        if x <= pos[0]:
            e = err[0]
        elif x >= pos[-1]:
            e = err[-1]
        else:
            i = bisect_right(pos, x) - 1
            e = err[i] + (x - pos[i]) / (pos[i + 1] - pos[i]) * (err[i + 1] - err[i])
        d[direction] += sign * e
    return d[0], d[1], d[2]


def _same_layout(new: VolumetricTable, old: VolumetricTable) -> None:
    if new.grid != old.grid:
        raise VolumetricError(f"tables on different grids: {new.grid.as_dict()} against {old.grid.as_dict()}")
    a = [(f.axis, f.positions_mm.tolist(), f.direction, f.sign) for f in new.feedback_um]
    b = [(f.axis, f.positions_mm.tolist(), f.direction, f.sign) for f in old.feedback_um]
    if a != b:
        raise VolumetricError(f"tables with different drives: {[x[0] for x in a]} against {[x[0] for x in b]} "
                              "(or their positions, directions, signs differ)")


def limit_table(new: VolumetricTable, old: VolumetricTable, max_step_um: float) -> tuple[VolumetricTable, bool]:
    """``new`` with every entry moved at most ``max_step_um`` [µm] from ``old``, and whether the limit acted.

    The daemon's rate limit, per support point and direction and per drive entry.

    Raises
    ------
    VolumetricError
        tables on different grids or with different drives, or ``max_step_um`` not finite and ≥ 0
    """
    step = float(max_step_um)
    if not (math.isfinite(step) and step >= 0):
        raise VolumetricError(f"limit_table: max_step_um = {max_step_um!r} must be finite and ≥ 0")
    _same_layout(new, old)
    dS = new.structure_um - old.structure_um
    acted = bool(np.any(np.abs(dS) > step))
    S = old.structure_um + np.clip(dS, -step, step)
    fbs = []
    for n, o in zip(new.feedback_um, old.feedback_um):
        de = n.error_um - o.error_um
        acted |= bool(np.any(np.abs(de) > step))
        fbs.append(n._replace(error_um=o.error_um + np.clip(de, -step, step)))
    return VolumetricTable(new.grid, new.time_s, S, tuple(fbs)), acted


def table_to_dict(table: VolumetricTable) -> dict:
    """The table as plain JSON types (floats round-trip exactly through JSON)."""
    return {"format": TABLE_FORMAT, "version": TABLE_VERSION, "grid": table.grid.as_dict(), "time_s": table.time_s,
            "structure_um": table.structure_um.tolist(),
            "feedback_um": [{"axis": f.axis, "positions_mm": f.positions_mm.tolist(), "error_um": f.error_um.tolist(),
                             "direction": f.direction, "sign": f.sign} for f in table.feedback_um]}


def table_from_dict(d: Mapping) -> VolumetricTable:
    """The table of :func:`table_to_dict`'s form; a clear error on a wrong format or a missing field."""
    check_versioned(d, TABLE_FORMAT, TABLE_VERSION, "volumetric table", VolumetricError)
    try:
        fbs = tuple(FeedbackTable(f["axis"], f["positions_mm"], f["error_um"], f["direction"], f["sign"])
                    for f in d["feedback_um"])
        return VolumetricTable(SupportGrid.from_dict(d["grid"]), d["time_s"], d["structure_um"], fbs)
    except (KeyError, TypeError) as exc:
        raise VolumetricError(f"volumetric table: field {exc} missing or malformed") from None
    except ValueError as exc:
        if isinstance(exc, VolumetricError):
            raise
        raise VolumetricError(f"volumetric table: {exc}") from None


__all__ = ["FeedbackTable", "FeedbackRows", "SupportGrid", "TABLE_FORMAT", "TableOperator", "VolumetricError",
           "VolumetricTable", "default_grid", "interpolate", "interpolate_one", "limit_table", "shifted",
           "table_from_dict", "table_of", "table_operator", "table_to_dict"]
