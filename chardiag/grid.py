"""CD sets per support point: the support-point table of a monitor without a pose-aware structure model.

The volumetric table (:mod:`hybridcomp.rom.volumetric`) gives the drift, TCP minus table, at the support points of
a workspace grid; with a pose-aware reduced model the daemon builds it from the model every cycle.  A monitor that
runs a one-pose model (or none) builds it from CDs instead: one CD set per support point, each trained on the drift
at that fixed pose, evaluated every cycle on the sensors, the table interpolated at the commanded position.

* :func:`grid_training_data`: per support point of a :class:`~hybridcomp.rom.volumetric.SupportGrid` (default
  3 × 3 × 3 over the travel), the drift time series at that fixed pose from the pose-aware model
  (:func:`hybridcomp.rom.poses.drift_along`: the support poses interpolated and each drive's added error, the
  machine standing at the point all along) on the load cases' inputs, with the sensor temperatures: one CD
  training table per point.
* :func:`fit_grid`: one CD set per point (:func:`hybridcomp.chardiag.fit.fit_cd_set`), each under its point's
  pose (its :func:`~hybridcomp.chardiag.cd.pose_key`).
* :class:`CDGrid`: the grid and its sets; :meth:`CDGrid.table` is the table at the current sensor temperatures.
  The database stores a grid as its sets plus a grid record (:meth:`hybridcomp.chardiag.db.CDDatabase.add_grid`).

The table's drives part is empty: each point's CDs hold the drives' errors at that point in their drift, so
between the points the table interpolates them linearly (the pose-aware table keeps them per axis at 17 points).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from hybridcomp.chardiag.cd import DIRECTIONS, TARGETS, CDError, CDSet, pose_key
from hybridcomp.chardiag.training import LoadCase, TrainingData
from hybridcomp.histogram.trace import position_column
from hybridcomp.models.layout import DRIFT_COLUMNS, temperature_column
from hybridcomp.rom.volumetric import SupportGrid, VolumetricTable


def point_pose(grid: SupportGrid, i: int) -> dict[str, float]:
    """The pose (axis → position [mm]) of grid point ``i`` (C order, the last axis fastest)."""
    return dict(zip(grid.axes, (float(v) for v in grid.points_mm()[i])))


def point_keys(grid: SupportGrid) -> tuple[str, ...]:
    """The pose keys of the grid's points, in C order."""
    return tuple(pose_key(dict(zip(grid.axes, p.tolist()))) for p in grid.points_mm())


@dataclass(frozen=True, eq=False)
class GridTrainingData:
    """The CD training tables of a support grid's points.

    Attributes
    ----------
    grid : the support grid
    tables : per point (C order) its :class:`~hybridcomp.chardiag.training.TrainingData` (``time_s``, ``T*_degC``,
        ``<axis>_mm`` at the point, ``dx_um`` …)
    """

    grid: SupportGrid
    tables: tuple[TrainingData, ...]


def grid_training_data(prom, cases: Mapping[str, LoadCase], grid: SupportGrid | None = None,
                       points: int | Sequence[int] = 3, feedback: bool = True) -> GridTrainingData:
    """The drift at every support point over the load cases, with the sensors: one CD training table per point.

    Each load case runs on the pose-aware reduced model from the steady state of its first row (inputs linear
    between the rows, as ``simulate``); the drift at a point is :func:`hybridcomp.rom.poses.drift_along` at that
    fixed position (feedback included), the sensors are the model's (the model pose's block: the same at every
    point).

    Parameters
    ----------
    prom : a pose-aware reduced model (:func:`hybridcomp.rom.poses.reduce_at_poses`)
    cases : load cases by name (:mod:`hybridcomp.chardiag.training`)
    grid : the support grid (default :func:`hybridcomp.rom.volumetric.default_grid` with ``points``)
    points : points per axis of the default grid
    feedback : include the drives' positioning errors (False: the structure's drift alone, for a control that
        compensates the drives by other means)
    """
    from hybridcomp.rom.poses import drift_along, grid_of
    from hybridcomp.rom.volumetric import VolumetricError, default_grid

    pg = grid_of(prom)
    grid = default_grid(prom, points) if grid is None else grid
    if tuple(grid.axes) != tuple(pg.axes):
        raise VolumetricError(f"support grid axes {list(grid.axes)} are not the model's {list(pg.axes)}")
    for a, p, (lo, hi) in zip(grid.axes, grid.positions_mm, pg.travel_mm):
        if p[0] < lo - 1e-9 or p[-1] > hi + 1e-9:
            raise VolumetricError(f"support grid: axis {a} spans [{p[0]:g}, {p[-1]:g}] mm, outside the travel "
                                  f"[{lo:g}, {hi:g}] mm")
    if not cases:
        raise ValueError("grid training data: no load cases")
    layout, outputs = prom.layout(), prom.output_layout()
    P = grid.points_mm()
    runs = []  # per case: (name, times, sensors [°C], outputs)
    for name, case in cases.items():
        U = layout.inputs(case.loads)
        t = np.asarray(case.loads.time_s, float)
        Y, _ = prom.integrate(t, U)
        runs.append((name, t, outputs.take(Y, "sensors") + layout.reference_temperature_degC, Y))
    sigs = {n: c.signature for n, c in cases.items() if c.signature is not None}
    tables = []
    for p in P:
        rows, cols = [], {}
        for name, t, T, Y in runs:
            block = {"time_s": t.copy()}
            for j, s in enumerate(outputs.sensors):
                block[temperature_column(s)] = T[:, j]
            for a, x in zip(grid.axes, p):
                block[position_column(a)] = np.full(t.size, float(x))
            D = drift_along(prom, Y, p[None], feedback=feedback)
            for j, c in enumerate(DRIFT_COLUMNS):
                block[c] = D[:, j]
            rows += [name] * t.size
            for k, v in block.items():
                cols.setdefault(k, []).append(v)
        tables.append(TrainingData(np.array(rows, dtype=object), {k: np.concatenate(v) for k, v in cols.items()},
                                   dict(sigs)))
    return GridTrainingData(grid, tuple(tables))


@dataclass(frozen=True, eq=False)
class CDGrid:
    """A support grid and one CD set per point: the CD form of the support-point table.

    Attributes
    ----------
    grid : the support grid
    sets : per point (C order) its CD set (pose = the point)
    grid_id : its id in the database (None when not stored)
    load_case : the training load case(s)
    """

    grid: SupportGrid
    sets: tuple[CDSet, ...]
    grid_id: int | None = None
    load_case: str = ""

    def __post_init__(self):
        if len(self.sets) != self.grid.n_points:
            raise CDError(f"CD grid: {len(self.sets)} sets for {self.grid.n_points} support points {self.grid.shape}")
        machines = {s.machine for s in self.sets}
        if len(machines) != 1:
            raise CDError(f"CD grid: the sets are for different machines {sorted(machines)}")
        for i, (s, key) in enumerate(zip(self.sets, point_keys(self.grid))):
            if s.pose_key != key:
                raise CDError(f"CD grid: the set of support point {i} is for pose {s.pose_key}, the point is {key}")

    @property
    def machine(self) -> str:
        return self.sets[0].machine

    def ids(self) -> tuple[dict[str, int], ...]:
        """The sets' CD ids per point (empty dicts when not stored)."""
        return tuple(dict(s.ids) for s in self.sets)

    def delta_T_K(self, temperatures_degC: Mapping[str, float]) -> float:
        """The largest |T_reference − T| over the points' sets and the common sensors [K] (inf: none common)."""
        out = -np.inf
        for s in self.sets:
            for cd in s.cds.values():
                ref = cd.t_reference()
                common = [k for k in temperatures_degC if k in ref]
                if not common:
                    return float("inf")
                out = max(out, max(abs(ref[k] - float(temperatures_degC[k])) for k in common))
        return float(out)

    def table(self, temperatures_degC: Mapping[str, float], time_s: float) -> tuple[VolumetricTable, bool]:
        """The support-point table at the sensor temperatures and whether a CD was outside its trained range.

        Each point's set is evaluated at the temperatures with the point's axis positions (a CD with position
        inputs reads them); no drives' part (the sets hold the drives' errors at their points).

        Raises
        ------
        KeyError
            a temperature an active CD input needs is missing
        hybridcomp.rom.volumetric.VolumetricError
            a non-finite value
        """
        g = self.grid
        values = dict(temperatures_degC)
        S = np.empty((g.n_points, 3))
        outside = False
        for i, (s, p) in enumerate(zip(self.sets, g.points_mm())):
            values.update(zip(g.axes, p.tolist()))
            v, o = s.evaluate_point(values)
            S[i] = [v[c] for c in DRIFT_COLUMNS]
            outside |= o
        return VolumetricTable(g, time_s, S.reshape(g.shape + (3,))), outside

    def predict(self, table: Mapping[str, np.ndarray], i: int) -> np.ndarray:
        """Point ``i``'s set on a table's columns (n × 3: dx, dy, dz) [µm] (its position columns set to the point)."""
        cols = dict(table)
        n = len(next(iter(table.values())))
        for a, x in point_pose(self.grid, i).items():
            cols[position_column(a)] = np.full(n, x)
        return np.column_stack([self.sets[i].cds[d].evaluate_table(cols)[0] for d in DIRECTIONS])


def fit_grid(data: GridTrainingData, *, machine: str, machine_sha256: str = "", options=None,
             candidates=None, source: str = "grid training data", load_case: str | None = None,
             t_reference_degC: Mapping[str, float] | None = None, weights: np.ndarray | None = None,
             constant_when_unexplained: bool = False) -> CDGrid:
    """One CD set per support point (:func:`hybridcomp.chardiag.fit.fit_cd_set`), each under its point's pose.

    ``options``: :class:`~hybridcomp.chardiag.fit.FitOptions` (default its defaults); ``candidates``: as
    :func:`~hybridcomp.chardiag.fit.fit_cd` (default every temperature column: a point's positions are constant);
    ``load_case``: the sets' load case (default the training cases' names); ``t_reference_degC``: the sets' reference
    temperatures (default the mean of each point's table); ``weights``: weight per row, the same rows at every
    point (default equal); ``constant_when_unexplained``: a direction of a point that no sensor explains gets a
    constant CD (its weighted mean drift) instead of the :class:`~hybridcomp.chardiag.fit.CDFitError`.
    """
    import dataclasses

    from hybridcomp.chardiag.fit import CDFitError, FitOptions, fit_cd

    options = FitOptions() if options is None else options
    constant = dataclasses.replace(options, min_target_range_um=1e12)  # any range: a constant CD
    sets = []
    for i, td in enumerate(data.tables):
        pose = point_pose(data.grid, i)
        kw = dict(machine=machine, machine_sha256=machine_sha256, pose_mm=pose, candidates=candidates,
                  load_case=",".join(td.cases) if load_case is None else load_case, signature=td.signature(),
                  t_reference_degC=t_reference_degC, weights=weights, source=f"{source}, support point {pose_key(pose)}")
        cds = {}
        for d in DIRECTIONS:
            try:
                cds[d] = fit_cd(td.columns, d, options=options, **kw)
            except CDFitError:
                if not constant_when_unexplained:
                    raise
                cds[d] = fit_cd(td.columns, d, options=constant, **kw)
        sets.append(CDSet(cds))
    return CDGrid(data.grid, tuple(sets), load_case=",".join(data.tables[0].cases) if load_case is None else load_case)


def grid_residuals(grid: CDGrid, data: GridTrainingData) -> np.ndarray:
    """RMS residual (points × 3) [µm] of each point's set on its own training table."""
    out = np.empty((grid.grid.n_points, 3))
    for i, td in enumerate(data.tables):
        pred = grid.predict(td.columns, i)
        y = np.column_stack([td.columns[TARGETS[d]] for d in DIRECTIONS])
        out[i] = np.sqrt(np.mean((y - pred) ** 2, axis=0))
    return out


__all__ = ["CDGrid", "GridTrainingData", "fit_grid", "grid_residuals", "grid_training_data", "point_keys",
           "point_pose"]
