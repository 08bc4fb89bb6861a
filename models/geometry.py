"""Geometry checks of a machine and the element budget of its mesh.

Box bodies must not overlap and must form one connected structure at every pose the axes reach; points,
supports and heat sources must lie in their bodies; the supports must be statically determinate; and the
tensor grid a box-body mesh would take is counted (:func:`check_element_budget`) before anything is meshed.
The loader (:mod:`hybridcomp.models.loader`) runs these checks on every machine file it reads.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import os

import numpy as np

from hybridcomp.models.machine import Body, HeatSource, Machine, MachineFileError, Point, Support, Vec3

log = logging.getLogger(__name__)

GEOMETRY_TOLERANCE_MM = 1e-6
#: default limit of the number of elements of a box-body mesh (its tensor grid, before empty cells are dropped)
DEFAULT_MAX_ELEMENTS = 2_000_000
#: environment variable that sets the element limit when the machine file has no ``[mesh] max_elements``
MAX_ELEMENTS_ENV = "HYBRIDCOMP_MAX_ELEMENTS"
#: memory meshing takes per grid cell [bytes] (measured: ~490 on vmc800 at 30 and 49 mm); assembly takes more
MESH_BYTES_PER_ELEMENT = 500


def inside_box(box: tuple[Vec3, Vec3], p, tol: float = GEOMETRY_TOLERANCE_MM) -> bool:
    """Whether point ``p`` [mm] lies in the box (lower, upper corner [mm]), up to ``tol`` [mm]."""
    lo, hi = np.asarray(box[0]), np.asarray(box[1])
    p = np.asarray(p)
    return bool(np.all(p >= lo - tol) and np.all(p <= hi + tol))


def box_at_pose(machine: Machine, body: Body, pose_mm: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """A body's box corners [mm] at a pose."""
    off = machine.body_offset_mm(body.name, pose_mm)
    return np.asarray(body.box_mm[0]) + off, np.asarray(body.box_mm[1]) + off


def _pair_overlaps(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-direction overlap [mm] of every pair of boxes (n_pairs × 3, negative: a gap), pairs in combinations order."""
    a, b = np.triu_indices(lo.shape[0], 1)
    return a, b, np.minimum(hi[a], hi[b]) - np.maximum(lo[a], lo[b])


def _touching(ov: np.ndarray) -> np.ndarray:
    """Pairs that share a face of positive area: in contact in one direction, overlapping in the other two."""
    tol = GEOMETRY_TOLERANCE_MM
    return (np.sum(np.abs(ov) <= tol, axis=1) == 1) & (np.sum(ov > tol, axis=1) == 2)


def _boxes_at(machine: Machine, pose_mm: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners [mm] of every body at a pose (n_bodies × 3 each)."""
    boxes = [box_at_pose(machine, b, pose_mm) for b in machine.bodies]
    return np.array([lo for lo, _ in boxes]), np.array([hi for _, hi in boxes])


def contact_graph(machine: Machine, pose_mm: dict[str, float]) -> dict[str, set[str]]:
    """Which box bodies share a face of positive area at a pose."""
    names = [b.name for b in machine.bodies]
    a, b, ov = _pair_overlaps(*_boxes_at(machine, pose_mm))
    g: dict[str, set[str]] = {n: set() for n in names}
    for i, j in zip(a[_touching(ov)], b[_touching(ov)]):
        g[names[i]].add(names[j])
        g[names[j]].add(names[i])
    return g


def check_pose_geometry(machine: Machine, pose_mm: dict[str, float]) -> None:
    """Bodies must not overlap and must form one connected structure at ``pose_mm``."""
    if machine.mesh.file is not None:
        return
    _check_boxes(machine, *_boxes_at(machine, pose_mm), pose_mm)


def _check_boxes(machine: Machine, lo: np.ndarray, hi: np.ndarray, pose_mm: dict[str, float]) -> None:
    """:func:`check_pose_geometry` on the bodies' corners at the pose (all pairs at once)."""
    a, b, ov = _pair_overlaps(lo, hi)
    _check_overlap(machine, a, b, ov, pose_mm)
    _check_connected(machine, np.arange(len(machine.bodies)), a, b, _touching(ov), pose_mm)


def _check_overlap(machine: Machine, a: np.ndarray, b: np.ndarray, ov: np.ndarray, pose_mm: dict[str, float]) -> None:
    """Raise for the first pair (a[k], b[k]) whose boxes overlap (``ov``: per-direction overlaps [mm])."""
    clash = np.all(ov > GEOMETRY_TOLERANCE_MM, axis=1)
    if clash.any():
        k = int(np.argmax(clash))
        names = [x.name for x in machine.bodies]
        raise MachineFileError(
            f"{machine.source}: field 'bodies' has overlapping bodies {names[a[k]]!r} and {names[b[k]]!r} at pose {pose_mm} "
            f"(overlap {np.round(ov[k], 3).tolist()} mm)"
        )


def _check_connected(machine: Machine, part: np.ndarray, a: np.ndarray, b: np.ndarray, touch: np.ndarray,
                     pose_mm: dict[str, float]) -> None:
    """Raise unless every body is connected to the first through face contacts.

    ``part`` is the group of each body (bodies of a group are known to be connected); ``a``, ``b``
    index bodies, ``touch`` says which of those pairs share a face at the pose.
    """
    nbr: dict[int, set[int]] = {}
    for i, j in zip(part[a[touch]].tolist(), part[b[touch]].tolist()):
        nbr.setdefault(i, set()).add(j)
        nbr.setdefault(j, set()).add(i)
    start = int(part[0])
    seen, todo = {start}, [start]
    while todo:
        for n in nbr.get(todo.pop(), ()):
            if n not in seen:
                seen.add(n)
                todo.append(n)
    loose = [x.name for x, g in zip(machine.bodies, part.tolist()) if g not in seen]
    if loose:
        raise MachineFileError(
            f"{machine.source}: field 'bodies' leaves {loose} without face contact to {machine.bodies[0].name!r} at pose "
            f"{pose_mm}: a loose body is a mechanism, not a statically determinate structure"
        )


def _check_all_poses(machine: Machine) -> None:
    """Overlap and connectivity at the reference pose and at every combination of travel ends (3^n poses at most).

    Bodies that move together (with the same axes) keep their relative position: their pairs are
    checked once, and their face contacts join them into one group; at each pose only the pairs of
    bodies that move against each other are checked again.
    """
    axes = [a.name for a in machine.axes]
    ref = {a: 0.0 for a in axes}
    A = _offset_matrix(machine)
    lo0, hi0 = _boxes_at(machine, ref)
    a, b, ov0 = _pair_overlaps(lo0, hi0)
    moving = np.any(A[a] != A[b], axis=(1, 2)) if axes else np.zeros(len(a), bool)
    _check_overlap(machine, a, b, ov0, ref)  # every pair at the reference pose, in file order
    # groups: bodies joined by face contacts that no axis changes (union-find)
    part = np.arange(len(machine.bodies))

    def root(i: int) -> int:
        while part[i] != i:
            part[i] = part[part[i]]
            i = int(part[i])
        return i

    fixed_touch = _touching(ov0) & ~moving
    for i, j in zip(a[fixed_touch].tolist(), b[fixed_touch].tolist()):
        part[root(i)] = root(j)
    part = np.array([root(i) for i in range(len(part))])
    am, bm = a[moving], b[moving]
    choices = [sorted({ax.travel_mm[0], 0.0, ax.travel_mm[1]}) for ax in machine.axes]
    for combo in itertools.chain([tuple(ref.values())], itertools.product(*choices)):
        pose = dict(zip(axes, combo))
        off = np.einsum("j,bjd->bd", np.asarray(combo, float), A) if axes else np.zeros_like(lo0)
        lo, hi = lo0 + off, hi0 + off
        ov = np.minimum(hi[am], hi[bm]) - np.maximum(lo[am], lo[bm])
        _check_overlap(machine, am, bm, ov, pose)
        _check_connected(machine, part, am, bm, _touching(ov), pose)


def _offset_matrix(machine: Machine) -> np.ndarray:
    """How each body moves with each axis: offsets [mm] = pose @ A[body] (n_bodies × n_axes × 3)."""
    A = np.zeros((len(machine.bodies), len(machine.axes), 3))
    for k, body in enumerate(machine.bodies):
        for j, axis in enumerate(machine.axes):
            A[k, j] = machine.body_offset_mm(body.name, {axis.name: 1.0})
    return A


def max_elements(machine: Machine) -> int:
    """The element limit of a machine's mesh: ``[mesh] max_elements``, else ``$HYBRIDCOMP_MAX_ELEMENTS``, else 2,000,000.

    Raises
    ------
    MachineFileError
        when the environment variable is set but not a positive whole number.
    """
    if machine.mesh.max_elements is not None:
        return machine.mesh.max_elements
    text = os.environ.get(MAX_ELEMENTS_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_ELEMENTS
    try:
        n = int(float(text))
    except (ValueError, OverflowError):
        n = 0
    if n < 1:
        raise MachineFileError(f"environment variable {MAX_ELEMENTS_ENV} = {text!r} must be a positive whole number")
    return n


def grid_cells(machine: Machine, pose_mm: dict[str, float], element_size_mm: float) -> float:
    """Elements of the tensor grid that meshes the box bodies at a pose with ``element_size_mm`` [mm], estimated.

    Counted from the box faces alone, without building the grid: every box face is a grid plane and each
    interval between planes is split into cells of at most ``element_size_mm``.  A float (it may be huge).
    """
    lo, hi = _boxes_at(machine, pose_mm)
    n = 1.0
    for d in range(3):
        breaks = np.unique(np.round(np.concatenate([lo[:, d], hi[:, d]]), 9))
        with np.errstate(over="ignore"):
            n *= float(np.sum(np.maximum(1.0, np.ceil(np.diff(breaks) / element_size_mm - 1e-9))))
    return n


def format_bytes(n: float) -> str:
    """``1.1 PiB``, ``512 MiB``: a byte count in binary units."""
    units = ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB")
    k = 0
    while n >= 1024 and k < len(units) - 1:
        n /= 1024
        k += 1
    return f"{n:.3g} {units[k]}"


def check_element_budget(machine: Machine, pose_mm: dict[str, float], element_size_mm: float,
                         what: str | None = None) -> float:
    """The estimated element count of meshing at a pose; raises before any meshing when it is over :func:`max_elements`.

    Parameters
    ----------
    machine : a machine with box bodies
    pose_mm : the pose [mm]
    element_size_mm : the element size [mm]
    what : how the element size is named in the message (default ``element size <h> mm``)

    Raises
    ------
    MachineFileError
        naming the element size, the estimated count, the memory meshing would take and the limit.
    """
    h = float(element_size_mm)
    if not (math.isfinite(h) and h > 0):
        raise MachineFileError(f"{machine.source}: element size must be a positive number, got {h} mm")
    n = grid_cells(machine, pose_mm, h)
    limit = max_elements(machine)
    if not n <= limit:
        name = what or f"element size {h:g} mm"
        raise MachineFileError(
            f"{machine.source}: {name} would give ~{n:.2g} elements at pose {pose_mm} (meshing alone would need "
            f"~{format_bytes(n * MESH_BYTES_PER_ELEMENT)}); the limit is {limit:,} elements (set [mesh] max_elements in "
            f"the machine file or the environment variable {MAX_ELEMENTS_ENV}, or use a larger element size)"
        )
    return n


def _locate(machine: Machine, where: str, p: Point | Support | HeatSource, box_ok) -> str:
    """The body a point lies in (checking a named body); raises when outside every body."""
    pos = p.position_mm
    if p.body:
        if not box_ok(machine.body(p.body), pos):
            raise MachineFileError(f"{machine.source}: field {where + '.position_mm'!r} = {list(pos)} mm "
                                   f"is outside its body {p.body!r}")
        return p.body
    for b in machine.bodies:
        if box_ok(b, pos):
            return b.name
    raise MachineFileError(f"{machine.source}: field {where + '.position_mm'!r} = {list(pos)} mm is outside every body")


def table_point(machine: Machine, pose_mm: dict[str, float]) -> Point:
    """The table point the drift (TCP minus table) is taken at, at a pose.

    The table reference, or with ``[table_reference] under_tool = true`` the point of its body at its height whose
    global x and y at ``pose_mm`` are the TCP's: the table point under the tool.  When the tool is beyond the table
    the point is clipped into the body's box, onto the nearest edge of its top face, and a log message (INFO) says
    so; the drift rows continue the table's displacement past that edge (:func:`table_point_weights`).

    Parameters
    ----------
    machine : the machine (box bodies with ``under_tool``)
    pose_mm : axis positions [mm]; missing axes at mid travel

    Returns
    -------
    Point
        on the table reference's body, its position at the reference pose [mm]
    """
    ref = machine.table_reference
    if not machine.table_under_tool:
        return ref
    pose = machine.check_pose(pose_mm)
    tcp = np.asarray(machine.tcp.position_mm, float) + machine.body_offset_mm(machine.tcp.body, pose)
    off = machine.body_offset_mm(ref.body, pose)
    lo, hi = (np.asarray(c, float) for c in machine.body(ref.body).box_mm)
    xy = np.clip(tcp[:2] - off[:2], lo[:2], hi[:2])
    if not np.allclose(xy, tcp[:2] - off[:2], rtol=0.0, atol=GEOMETRY_TOLERANCE_MM):
        log.info("%s: at pose %s the tool (x, y) = (%g, %g) mm is beyond the table body %r; the drift is taken at the "
                 "nearest point of its top face, (%g, %g) mm", machine.source, pose, tcp[0], tcp[1], ref.body,
                 xy[0] + off[0], xy[1] + off[1])
    return Point("table point under the tool", ref.body, (float(xy[0]), float(xy[1]), float(ref.position_mm[2])))


def table_point_weights(machine: Machine, pose_mm: dict[str, float]) -> tuple[tuple[Point, float], ...]:
    """The table points and weights whose weighted sum is the drift's table point at a pose (weights sum to 1).

    Over the table, the point under the tool (:func:`table_point`) with weight 1.  With the tool beyond the table
    (``under_tool``), the table's displacement is continued linearly past its edge: ``(1 + s) u(q) − s u(q')`` with
    ``q`` the clipped point on the edge, ``q'`` the tool's point mirrored into the table at that edge (clipped
    into it) and ``s = |tool − q| / |q − q'|`` — exact for a table that expands linearly, and without the kink a
    clipped point puts into the drift between support poses (on vmc800 at 80 mm a clipped Y = −325 support pose
    left 0.47–0.71 µm of dy error at poses over the table, the continued one 0.10–0.16 µm).
    """
    q = table_point(machine, pose_mm)
    ref = machine.table_reference
    if not machine.table_under_tool:
        return ((q, 1.0),)
    pose = machine.check_pose(pose_mm)
    tcp = np.asarray(machine.tcp.position_mm, float) + machine.body_offset_mm(machine.tcp.body, pose)
    want = tcp[:2] - machine.body_offset_mm(ref.body, pose)[:2]
    at = np.asarray(q.position_mm[:2], float)
    d = want - at
    if np.linalg.norm(d) <= GEOMETRY_TOLERANCE_MM:
        return ((q, 1.0),)
    lo, hi = (np.asarray(c, float) for c in machine.body(ref.body).box_mm)
    inner = np.clip(at - d, lo[:2], hi[:2])
    span = np.linalg.norm(at - inner)
    if span <= GEOMETRY_TOLERANCE_MM:  # a table thinner than nothing: the edge it is
        return ((q, 1.0),)
    s = float(np.linalg.norm(d) / span)
    mirror = Point("table point mirrored into the table", ref.body, (float(inner[0]), float(inner[1]),
                                                                     float(ref.position_mm[2])))
    return ((q, 1.0 + s), (mirror, -s))


def validate_geometry(machine: Machine) -> Machine:
    """The machine with its points located in their bodies, after every geometry check.

    Overlap and contact at every pose, sensors, TCP, table reference, supports and heat sources inside their
    bodies, statically determinate supports and the element budget of the file's mesh.

    Raises
    ------
    MachineFileError
        naming the file, the field and the offending value.
    """
    src = machine.source
    if machine.mesh.file is None:
        box_ok = lambda b, p: inside_box(b.box_mm, p)  # noqa: E731
        _check_all_poses(machine)
        sensors = tuple(
            dataclasses.replace(s, body=_locate(machine, f"sensors[{i}]", s, box_ok)) for i, s in enumerate(machine.sensors)
        )
        tcp = dataclasses.replace(machine.tcp, body=_locate(machine, "tcp", machine.tcp, box_ok))
        tref = dataclasses.replace(machine.table_reference,
                                   body=_locate(machine, "table_reference", machine.table_reference, box_ok))
        supports = tuple(
            dataclasses.replace(s, body=_locate(machine, f"supports[{i}]", s, box_ok)) for i, s in enumerate(machine.supports)
        )
        for i, s in enumerate(machine.heat_sources):
            _check_source_inside(machine, i, s)
        machine = dataclasses.replace(machine, sensors=sensors, tcp=tcp, table_reference=tref, supports=supports)
    else:
        for what, pts in (("sensors", machine.sensors), ("supports", machine.supports)):
            for i, p in enumerate(pts):
                if not p.body:
                    raise MachineFileError(f"{src}: field '{what}[{i}].body' is required with an imported mesh")
        for what, p in (("tcp", machine.tcp), ("table_reference", machine.table_reference)):
            if not p.body:
                raise MachineFileError(f"{src}: field '{what}.body' is required with an imported mesh")
    for i, s in enumerate(machine.supports):
        if machine.body(s.body).mounted_on is not None:
            raise MachineFileError(
                f"{src}: field 'supports[{i}].body' is {s.body!r}, which is mounted on another body; supports hold a ground body"
            )
    check_statically_determinate(machine)
    if machine.mesh.file is None:  # the grid the file's element size gives, counted before anything is meshed
        check_element_budget(machine, machine.default_pose_mm(), machine.mesh.element_size_mm,
                             f"field 'mesh.element_size_mm' = {machine.mesh.element_size_mm:g} mm")
    return machine


def _check_source_inside(machine: Machine, i: int, s: HeatSource) -> None:
    """The source's centre must lie in its body, for a moving source over the whole travel."""
    b = machine.body(s.body)
    where = f"heat_sources[{i}].position_mm"
    if s.kind == "fixed":
        if not inside_box(b.box_mm, s.position_mm):
            raise MachineFileError(f"{machine.source}: field {where!r} = {list(s.position_mm)} mm is outside its body {s.body!r}")
        return
    a = machine.axis(s.axis)
    for end in a.travel_mm:
        p = np.asarray(s.position_mm, float)
        p[a.direction] += end
        # the rail patch lies in the carrier body, which does not move with this axis
        if not inside_box(b.box_mm, p):
            raise MachineFileError(
                f"{machine.source}: field {where!r} = {list(s.position_mm)} mm leaves its carrier body {s.body!r} "
                f"at {a.name} = {end} mm (rail point {p.round(3).tolist()} mm)"
            )


def check_statically_determinate(machine: Machine) -> None:
    """Supports must remove exactly the six rigid-body motions: six constraints of rank six."""
    rows = []
    for s in machine.supports:
        x = np.asarray(s.position_mm) * 1e-3
        for d in s.directions:
            e = np.zeros(3)
            e[d] = 1.0
            # displacement at x under translation t and rotation w: t + w × x; its component along e
            rows.append(np.concatenate([e, np.cross(x, e)]))
    n = len(rows)
    rank = np.linalg.matrix_rank(np.asarray(rows), tol=1e-9) if rows else 0
    if n != 6 or rank != 6:
        kind = "a mechanism (rigid-body motion left free)" if rank < 6 else "over-constrained (constraint stresses)"
        raise MachineFileError(
            f"{machine.source}: field 'supports' has {n} constraints of rank {rank}: {kind}; "
            "a statically determinate support needs six independent ones (e.g. 3-2-1)"
        )
