"""The drift at any pose from one thermal model: drift rows at support poses and their interpolation.

The thermal model is built at one pose (mid travel by default).  Its temperature field moves with the bodies: a
body's field at another pose is the same field, carried along with the body.  At a support pose ``P`` the
machine is meshed again and its elastic drift rows ``G_P`` (TCP minus table, three adjoint solves) are computed;
the field of the thermal model is carried onto that mesh body by body (``Π_P``: each node of body b at ``P``
takes the temperature of the same body point at the model's pose), so that ``R_P = G_P Π_P`` gives the drift at
``P`` for the model's state.  Between support poses the rows are interpolated per axis with quadratic Lagrange
polynomials through the travel's ends and the model's pose (three levels per axis), or with more levels along an
axis (an odd number: the model's pose and evenly spaced levels on either side of it, down to the travel's ends),
piecewise quadratic over consecutive triples of them (a drift whose dependence on that axis a single quadratic does
not follow, e.g. where the tool leaves the table: ``benchmarks/pose_reference.py --sweep``):

* ``"star"`` (default, ``2 n + 1`` poses for ``n`` axes with three levels each): each axis at its levels with the
  others at the model's pose (:func:`auto_levels` says which axes get seven by default); the pose dependence is
  taken as a sum over axes (no products of two axes' positions);
* ``"grid"`` (``3^n`` poses): the full tensor grid, products included.

What moves with the pose and what does not: the elastic problem (where each body sits, and so the lever arms of
every tilt and the supports' reactions) is solved at each support pose; the temperature field is the model's,
carried with the bodies, so the change of the heat paths between a moving body and its carrier with the pose is
left out.  ``benchmarks/pose_drift.py`` measures both against FE models built at off-grid poses.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from hybridcomp.models.machine import Machine, MachineFileError

SCHEMES = ("star", "grid")


def _lagrange3(x: float, nodes: tuple[float, float, float]) -> np.ndarray:
    """Quadratic Lagrange weights at ``x`` for three distinct nodes."""
    a, b, c = nodes
    return np.array([(x - b) * (x - c) / ((a - b) * (a - c)), (x - a) * (x - c) / ((b - a) * (b - c)),
                     (x - a) * (x - b) / ((c - a) * (c - b))])


def piecewise_weights(x: float, levels: tuple[float, ...]) -> np.ndarray:
    """Weights at ``x`` of the piecewise quadratic through increasing ``levels`` (odd count): one triple a segment.

    Segments are the triples (0, 1, 2), (2, 3, 4), …; ``x`` in the first segment that holds it.  Three levels: the
    quadratic through them (:func:`_lagrange3`).
    """
    w = np.zeros(len(levels))
    for i in range(0, len(levels) - 2, 2):
        if x <= levels[i + 2] + 1e-9 or i + 3 >= len(levels):
            w[i:i + 3] = _lagrange3(x, levels[i:i + 3])
            return w
    raise AssertionError("unreachable")  # pragma: no cover - the last segment takes every x


@dataclass(frozen=True)
class PoseGrid:
    """Support poses over the workspace and the interpolation between them.

    Attributes
    ----------
    axes : the axis names, in machine order
    levels_mm : per axis its levels, increasing from travel min to travel max and holding the model's pose (three:
        travel min, the model's pose, travel max; or any odd number, :func:`axis_levels`) [mm]
    scheme : ``"star"`` or ``"grid"`` (module docstring)
    poses : the support poses, as level indices per axis; the model's pose first
    """

    axes: tuple[str, ...]
    levels_mm: tuple[tuple[float, ...], ...]
    scheme: str
    poses: tuple[tuple[int, ...], ...]

    @property
    def travel_mm(self) -> tuple[tuple[float, float], ...]:
        """Per axis its travel (min, max) [mm]: the outer levels."""
        return tuple((lv[0], lv[-1]) for lv in self.levels_mm)

    @property
    def model_pose_mm(self) -> tuple[float, ...]:
        """Per axis the model's pose [mm] (support pose 0)."""
        return tuple(lv[j] for lv, j in zip(self.levels_mm, self.poses[0]))

    def pose_mm(self, k: int) -> dict[str, float]:
        """Support pose ``k`` in mm."""
        return {a: self.levels_mm[i][j] for i, (a, j) in enumerate(zip(self.axes, self.poses[k]))}

    def weights(self, pose_mm: dict[str, float]) -> np.ndarray:
        """Interpolation weight of each support pose at ``pose_mm`` (axes left out: the model's pose); sum 1."""
        unknown = set(pose_mm) - set(self.axes)
        if unknown:
            raise ValueError(f"pose names axes {sorted(unknown)} the machine has not (axes: {list(self.axes)})")
        L = []
        for a, lv, mid in zip(self.axes, self.levels_mm, self.model_pose_mm):
            x = float(pose_mm.get(a, mid))
            if not lv[0] - 1e-9 <= x <= lv[-1] + 1e-9:
                raise ValueError(f"pose {a} = {x:g} mm is outside the travel [{lv[0]:g}, {lv[-1]:g}] mm")
            L.append(piecewise_weights(x, lv))
        base = self.poses[0]
        w = np.zeros(len(self.poses))
        for k, levels in enumerate(self.poses):
            if self.scheme == "grid":
                w[k] = np.prod([L[i][j] for i, j in enumerate(levels)])
            else:
                moved = [i for i, j in enumerate(levels) if j != base[i]]
                w[k] = L[moved[0]][levels[moved[0]]] if moved else 0.0
        if self.scheme == "star":
            w[0] = 1.0 - w.sum()
        return w

    def weights_along(self, positions_mm: np.ndarray) -> np.ndarray:
        """Weights (nt × poses) for axis positions per row (nt × axes, machine order) [mm]."""
        P = np.atleast_2d(np.asarray(positions_mm, float))
        if P.shape[1] != len(self.axes):
            raise ValueError(f"positions need one column per axis {list(self.axes)}, got shape {P.shape}")
        return np.array([self.weights(dict(zip(self.axes, row))) for row in P])

    def as_dict(self) -> dict:
        return {"axes": list(self.axes), "levels_mm": [list(v) for v in self.levels_mm], "scheme": self.scheme,
                "poses": [list(p) for p in self.poses]}

    @staticmethod
    def from_dict(d: dict) -> PoseGrid:
        return PoseGrid(tuple(d["axes"]), tuple(tuple(float(x) for x in v) for v in d["levels_mm"]), d["scheme"],
                        tuple(tuple(int(j) for j in p) for p in d["poses"]))


def axis_levels(lo: float, mid: float, hi: float, count: int = 3) -> tuple[float, ...]:
    """An axis' ``count`` levels [mm] (odd, ≥ 3), increasing.

    The model's pose ``mid`` and ``(count − 1) / 2`` evenly spaced levels on either side of it, the outer ones the
    travel's ends ``lo``, ``hi``.
    """
    if not (isinstance(count, (int, np.integer)) and count >= 3 and count % 2 == 1):
        raise ValueError(f"an axis needs an odd number of levels, at least 3, got {count!r}")
    m = (count - 1) // 2
    return (tuple(float(lo + (mid - lo) * i / m) for i in range(m)) + (float(mid),)
            + tuple(float(mid + (hi - mid) * i / m) for i in range(1, m + 1)))


#: levels along an axis that :func:`auto_levels` refines (:func:`edge_levels`, :func:`tool_axes`)
EDGE_LEVELS = 7


def edge_levels(machine: Machine) -> dict[str, int]:
    """:data:`EDGE_LEVELS` levels along every axis on which the tool leaves the table within its travel.

    With the drift taken at the table point under the tool (``[table_reference] under_tool``), the drift along such
    an axis kinks where the tool crosses the table's edge, and one quadratic through the travel's ends and the
    model's pose does not follow it (``benchmarks/pose_reference.py --sweep``; vmc800's Y: 0.32 µm in y, seven
    levels 0.12).  Each axis is moved to its travel's ends with the others at mid travel.
    """
    from hybridcomp.models.geometry import table_point_weights

    if not machine.table_under_tool:
        return {}
    return {a.name: EDGE_LEVELS for a in machine.axes
            if any(len(table_point_weights(machine, {a.name: float(x)})) > 1 for x in a.travel_mm)}


def tool_axes(machine: Machine) -> tuple[str, ...]:
    """The axes that carry the tool: they move the TCP's body or a body it is mounted on (vmc800: Z)."""
    return tuple(a.name for a in machine.axes
                 if np.any(machine.body_offset_mm(machine.tcp.body, {a.name: 1.0}) != 0.0))


def auto_levels(machine: Machine) -> dict[str, int]:
    """The support levels a star of support poses gets by default (``reduce --poses star``).

    :data:`EDGE_LEVELS` along every axis on which the tool leaves the table (:func:`edge_levels`) or that carries the
    tool (:func:`tool_axes`), three along the rest.  An axis that carries the tool slides the tool's body along a
    carrier (vmc800: the headstock on the column) whose heat pattern stays where the body stood: after a move the
    tool's drift follows the carrier's deformation at the new position, which one quadratic along the axis does not
    (``benchmarks/pose_path.py``, 80 mm: after a move across the workspace, three levels 0.74 µm in y, seven along Y
    0.52, along Z 0.46, along both 0.23 against a limit of 0.40; seven along X alone: 0.75).  vmc800: Y and Z, 15
    support poses against 7.
    """
    refined = set(edge_levels(machine)) | set(tool_axes(machine))
    return {a.name: EDGE_LEVELS for a in machine.axes if a.name in refined}


def default_levels(machine: Machine, scheme: str = "star") -> dict[str, int]:
    """The levels a pose-aware model gets when none are asked for (``reduce_at_poses``, ``reduce --poses``).

    :func:`auto_levels` for a star, three along every axis for a grid (its support poses are the product of the
    levels).
    """
    return auto_levels(machine) if scheme == "star" else {}


def parse_levels(text: str | None, axes: tuple[str, ...] | list[str], machine: Machine | None = None) -> dict[str, int]:
    """Levels per axis (:func:`pose_grid`) from ``"Y=7"`` or ``"X=5,Y=7"``.

    ``"auto"``: :func:`auto_levels` of ``machine``; ``"N"``: N along every axis (``"3"``: the plain star); None or
    empty: {} (three along every axis).

    Raises
    ------
    ValueError
        naming the option's text and what is wrong in it (not AXIS=N, an axis the machine has not, N not odd ≥ 3)
    """
    whole = (text or "").strip()
    if whole == "auto":
        if machine is None:
            raise ValueError("--pose-levels auto needs the machine")
        return auto_levels(machine)
    parts = [f"{a}={whole}" for a in axes] if whole.isdigit() else whole.split(",")
    out: dict[str, int] = {}
    for part in filter(None, (t.strip() for t in parts)):
        name, eq, count = part.partition("=")
        name = name.strip()
        if not eq or not count.strip().isdigit():
            raise ValueError(f"--pose-levels {text!r}: {part!r} is not AXIS=N (e.g. Y=7)")
        if name not in axes:
            raise ValueError(f"--pose-levels {text!r}: the machine has no axis {name!r} (axes: {', '.join(axes)})")
        n = int(count)
        if n < 3 or n % 2 == 0:
            raise ValueError(f"--pose-levels {text!r}: {name} = {n}, a number of levels must be odd and at least 3")
        out[name] = n
    return out


def pose_grid(model, scheme: str = "star", levels: dict[str, int] | None = None) -> PoseGrid:
    """The support poses of an FE model's machine around the model's pose.

    ``levels``: per axis name its number of levels (odd, ≥ 3; :func:`axis_levels`), 3 for the axes left out.

    Raises
    ------
    MachineFileError
        an imported mesh (it is drawn at one pose), or a model whose pose puts an axis at a travel end
    ValueError
        ``levels`` names an axis the machine has not, or a count that is not odd and ≥ 3
    """
    machine: Machine = model.machine
    if machine.mesh.file is not None:
        raise MachineFileError(f"{machine.source}: the drift at other poses needs box bodies; an imported mesh is "
                               "drawn at one pose")
    counts = dict(levels or {})
    names = [a.name for a in machine.axes]
    unknown = sorted(set(counts) - set(names))
    if unknown:
        raise ValueError(f"levels name axes {unknown} the machine has not (axes: {names})")
    out = []
    for a in machine.axes:
        lo, hi = a.travel_mm
        mid = float(model.mesh.pose_mm[a.name])
        if not lo < mid < hi:
            raise MachineFileError(f"{machine.source}: the model is built at {a.name} = {mid:g} mm, a travel end: the "
                                   f"support poses need it inside ({lo:g}, {hi:g}) mm")
        out.append(axis_levels(float(lo), mid, float(hi), counts.get(a.name, 3)))
    return PoseGrid(tuple(names), tuple(out), scheme,
                    support_poses_of(tuple(len(lv) for lv in out), scheme))


@dataclass(frozen=True)
class PoseDrift:
    """Drift rows of one thermal model's state at the support poses of a grid (the carried field).

    ``rows`` (poses × 3 × n) [m/K]: the drift at support pose k is ``rows[k] @ x`` for the model's state ``x``.
    """

    grid: PoseGrid
    rows: np.ndarray

    def drift_rows(self, pose_mm: dict[str, float]) -> np.ndarray:
        """Drift rows at a pose (3 × n) [m/K]: ``drift = rows @ x`` for the model's state ``x``."""
        return np.tensordot(self.grid.weights(pose_mm), self.rows, axes=1)


def support_poses(n_axes: int, scheme: str) -> tuple[tuple[int, ...], ...]:
    """Level indices of the support poses with three levels per axis: the model's pose first."""
    return support_poses_of((3,) * n_axes, scheme)


def support_poses_of(counts: tuple[int, ...], scheme: str) -> tuple[tuple[int, ...], ...]:
    """Level indices of the support poses, ``counts[i]`` levels on axis i with the model's pose in the middle.

    The model's pose first; star: then each axis at each of its other levels, in order (three levels: its two
    ends), the others at the model's pose; grid: then every other combination.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {scheme!r}")
    base = tuple((c - 1) // 2 for c in counts)
    if scheme == "grid":
        return (base,) + tuple(p for p in itertools.product(*(range(c) for c in counts)) if p != base)
    out = [base]
    for i, c in enumerate(counts):
        for j in range(c):
            if j != base[i]:
                out.append(tuple(j if k == i else base[k] for k in range(len(counts))))
    return tuple(out)


def carry_field(model, mm_pose) -> sp.csr_matrix:
    """``Π`` (n_pose × n): the model's temperature field carried body by body onto a mesh at another pose."""
    from hybridcomp.fem import assembly

    machine: Machine = model.machine
    src = model.mesh
    rows, cols, vals = [], [], []
    done = np.zeros(mm_pose.n_nodes, bool)
    basis = assembly.cell_basis(src.mesh)
    for bi, body in enumerate(mm_pose.body_names):
        nodes = np.unique(mm_pose.mesh.t[:, mm_pose.body_of_element == bi])
        nodes = nodes[~done[nodes]]
        if nodes.size == 0:
            continue
        shift = (machine.body_offset_mm(body, src.pose_mm) - machine.body_offset_mm(body, mm_pose.pose_mm)) * 1e-3
        pts = mm_pose.mesh.p[:, nodes] + shift[:, None]
        cells = src.find_elements(pts, body=body)
        if (cells < 0).any():
            bad = pts[:, cells < 0][:, 0] * 1e3
            raise MachineFileError(f"{machine.source}: body {body!r} at pose {mm_pose.pose_mm} has a node that is not "
                                   f"in its mesh at pose {src.pose_mm} ({bad.round(3).tolist()} mm)")
        P = assembly.probe_matrix(basis, pts, cells).tocoo()
        rows.append(nodes[P.row])
        cols.append(P.col)
        vals.append(P.data)
        done[nodes] = True
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(mm_pose.n_nodes, model.n))


def pose_drift(model, scheme: str = "star", progress: bool = False) -> PoseDrift:
    """The drift rows of an FE model's thermal state at the support poses of ``scheme``.

    The model's field is carried with the bodies (module docstring).
    """
    grid = pose_grid(model, scheme)
    rows = np.empty((len(grid.poses), 3, model.n))
    rows[0] = model.G
    for k in _progress(range(1, len(grid.poses)), progress):
        rows[k] = support_rows(model, grid, k)
    return PoseDrift(grid, rows)


def support_rows(model, grid: PoseGrid, k: int, fixed_target: bool = False) -> np.ndarray:
    """The drift rows (3 × n) [m/K] at support pose ``k`` of ``grid`` for the model's state (the carried field).

    ``fixed_target``: TCP minus the table reference at every pose, a target that stays where it is on the table (an
    interferometer's reflector, as ISO 230-3 measures), even when the machine file takes the drift under the tool.
    """
    import dataclasses

    from hybridcomp.fem import assembly
    from hybridcomp.fem.mesh import mesh_machine
    from hybridcomp.fem.model import _material_arrays, drift_rows

    machine: Machine = model.machine
    fixed = fixed_target and machine.table_under_tool
    if fixed:
        machine = dataclasses.replace(machine, table_under_tool=False)
    if k == 0:
        if not fixed:
            return np.asarray(model.G)
        mm = model.mesh
        G, _ = drift_rows(machine, mm, assembly.cell_basis(mm.mesh), _material_arrays(machine, mm))
        return np.asarray(G)
    mm = mesh_machine(machine, grid.pose_mm(k), machine.mesh.element_size_mm)
    G, _ = drift_rows(machine, mm, assembly.cell_basis(mm.mesh), _material_arrays(machine, mm))
    return np.asarray((carry_field(model, mm).T @ G.T).T)


def drift_rows_at(model, poses_mm: list[dict[str, float]], scheme: str = "star",
                  fixed_target: bool = False) -> np.ndarray:
    """The drift rows (poses × 3 × n) [m/K] at each pose for the model's state, as :class:`PoseDrift` gives them.

    Only the support poses with a weight at one of the poses are meshed (an axis moved alone: two).
    ``fixed_target``: at the table reference at every pose (:func:`support_rows`).
    """
    grid = pose_grid(model, scheme)
    W = np.array([grid.weights(p) for p in poses_mm])
    rows = {k: support_rows(model, grid, k, fixed_target) for k in range(len(grid.poses))
            if np.any(np.abs(W[:, k]) > 1e-14)}
    return np.array([sum(w[k] * r for k, r in rows.items()) for w in W])


def _progress(it, show: bool):
    if not show:
        return it
    from tqdm import tqdm

    return tqdm(it, unit="pose", desc="support poses", leave=False)
