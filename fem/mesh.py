"""FE meshes of a machine at a pose.

Box bodies are meshed together on one conforming tensor grid of trilinear
hexahedra: every box face at the pose is a grid plane, so touching bodies share
nodes (perfect thermal contact, bonded joints) and each element belongs to
exactly one body.  An imported mesh (anything meshio reads, e.g. gmsh ``.msh``
with physical groups) is used as it is, with bodies and convection surfaces
taken from its named cell sets.  Coordinates inside are metres.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import skfem

from hybridcomp.models.geometry import box_at_pose, check_element_budget, check_pose_geometry, max_elements
from hybridcomp.models.machine import FACES, Machine, MachineFileError
from hybridcomp.models.toml import open_regular_file

log = logging.getLogger(__name__)

MM = 1e-3


@dataclass(frozen=True)
class MachineMesh:
    """A meshed machine at one pose.

    Attributes
    ----------
    mesh : skfem mesh (``MeshHex`` or ``MeshTet``), coordinates [m]
    body_of_element : index into ``body_names`` per element
    body_names : names of the bodies, in machine-file order
    zone_facets : boundary facet indices per convection-zone name
    pose_mm : axis positions the mesh was made at [mm]
    grid_m : grid lines per direction [m] for a tensor mesh, else ``None``
    cell_of_grid : element index per tensor-grid cell (``-1``: no body), else ``None``
    """

    mesh: skfem.Mesh
    body_of_element: np.ndarray
    body_names: tuple[str, ...]
    zone_facets: dict[str, np.ndarray]
    pose_mm: dict[str, float]
    grid_m: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    cell_of_grid: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_nodes(self) -> int:
        return self.mesh.p.shape[1]

    def find_elements(self, points_m: np.ndarray, body: str | None = None) -> np.ndarray:
        """Element index containing each point (3 × n) [m]; -1 outside (or outside ``body``)."""
        pts = np.atleast_2d(points_m)
        if self.grid_m is not None:
            idx = []
            for d in range(3):
                g = self.grid_m[d]
                i = np.searchsorted(g, pts[d], side="right") - 1
                # points on the last grid plane belong to the last cell; tolerate round-off
                i = np.where(np.isclose(pts[d], g[-1], rtol=0, atol=1e-9), len(g) - 2, i)
                idx.append(i)
            ix, iy, iz = idx
            nx, ny, nz = (len(g) - 1 for g in self.grid_m)
            ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (iz >= 0) & (iz < nz)
            cells = np.full(pts.shape[1], -1)
            flat = (ix + nx * (iy + ny * iz))[ok]
            cells[ok] = self.cell_of_grid[flat]
            if body is not None:
                # a point on a face between two bodies: search the neighbouring cells of its own body
                want = self.body_names.index(body)
                bad = np.flatnonzero((cells < 0) | (self.body_of_element[np.maximum(cells, 0)] != want))
                for j in bad:
                    cells[j] = self._neighbour_in_body(pts[:, j], want)
        elif isinstance(self.mesh, skfem.MeshTet):
            # imported tetrahedra: an exact containment test among the elements of the body
            # (of every body without ``body``), so that a point on the face between two bodies
            # gets an element of its own body, never a neighbour's element it would extrapolate
            want = None if body is None else self.body_names.index(body)
            cells = self._nearest_in_body(pts, want)
        else:
            finder = self.mesh.element_finder()
            cells = np.full(pts.shape[1], -1)
            for j in range(pts.shape[1]):
                try:
                    cells[j] = finder(*pts[:, j : j + 1])[0]
                except (ValueError, IndexError):
                    cells[j] = -1
            if body is not None:
                want = self.body_names.index(body)
                bad = np.flatnonzero((cells < 0) | (self.body_of_element[np.maximum(cells, 0)] != want))
                for j in bad:
                    cells[j] = self._nearest_in_body(pts[:, j], want)
        return cells

    def _neighbour_in_body(self, p: np.ndarray, want: int) -> int:
        nx, ny, nz = (len(g) - 1 for g in self.grid_m)
        base = []
        for d in range(3):
            g = self.grid_m[d]
            i = int(np.clip(np.searchsorted(g, p[d], side="right") - 1, 0, len(g) - 2))
            base.append(i)
        for dx in (0, -1, 1):
            for dy in (0, -1, 1):
                for dz in (0, -1, 1):
                    i, j, k = base[0] + dx, base[1] + dy, base[2] + dz
                    if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
                        c = self.cell_of_grid[i + nx * (j + ny * k)]
                        if c >= 0 and self.body_of_element[c] == want:
                            lo = np.array([self.grid_m[0][i], self.grid_m[1][j], self.grid_m[2][k]])
                            hi = np.array([self.grid_m[0][i + 1], self.grid_m[1][j + 1], self.grid_m[2][k + 1]])
                            if np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9):
                                return int(c)
        return -1

    def _nearest_in_body(self, p: np.ndarray, want: int | None, tol_m: float = 1e-6):
        """Element of body ``want`` (``None``: any body) containing the point ``p`` [m]; -1: none.

        ``p`` is one point (3,) (returns an int) or many (3 × n) (returns an array).
        A point up to ``tol_m`` outside an element (round-off on its faces) still
        counts as inside; of several such elements the one the point lies deepest
        in wins.  Tetrahedra are tested exactly, by the signed distances to their
        four face planes: a k-d tree of the body's element centroids proposes the
        16 nearest, and a point none of them holds is tested against every element
        whose centroid is close enough to possibly hold it.  Other element types
        (a non-tensor hexahedral mesh) keep the bounding-box test of the element
        with the nearest centroid, for a single point.
        """
        if isinstance(self.mesh, skfem.MeshTet):
            from scipy.spatial import cKDTree

            mesh = self.mesh
            pts = np.asarray(p, dtype=float)
            P = pts.reshape(3, -1)
            found = np.full(P.shape[1], -1)
            # per body: its elements, a k-d tree of their centroids and the largest centroid-vertex
            # distance; kept on the (frozen) instance, which find_elements calls for every patch
            cache = self.__dict__.setdefault("_tet_search", {})
            if want not in cache:
                els = np.arange(mesh.t.shape[1]) if want is None else np.flatnonzero(self.body_of_element == want)
                V = mesh.p[:, mesh.t[:, els]]
                cent = V.mean(axis=1)
                reach = float(np.sqrt(np.sum((V - cent[:, None]) ** 2, axis=0)).max()) if len(els) else 0.0
                cache[want] = (els, cKDTree(cent.T) if len(els) else None, reach)
            els, tree, reach = cache[want]
            if tree is None or P.shape[1] == 0:
                return int(found[0]) if pts.ndim == 1 else found

            def depth(q: np.ndarray, e: np.ndarray) -> np.ndarray:
                """Signed distance [m] of point q[:, i] into tetrahedron e[i] (negative: outside)."""
                V = mesh.p[:, mesh.t[:, e]]  # 3 × 4 × len(e)
                d = np.full((4, len(e)), -np.inf)
                for i in range(4):
                    a, b, c = (V[:, j] for j in range(4) if j != i)
                    n = np.cross(b - a, c - a, axis=0)
                    side = np.sum(n * (V[:, i] - a), axis=0)  # > 0: n points into the element
                    size = np.linalg.norm(n, axis=0) * np.sign(side)
                    ok = side != 0  # a flat element holds nothing
                    d[i, ok] = np.sum(n[:, ok] * (q[:, ok] - a[:, ok]), axis=0) / size[ok]
                return d.min(axis=0)

            def best(pt: np.ndarray, e: np.ndarray) -> None:
                """Keep, per point index, the candidate element the point lies deepest in."""
                chunks = np.array_split(np.arange(len(pt)), max(1, len(pt) // 200_000))  # bounded memory
                dep = np.concatenate([depth(P[:, pt[c]], e[c]) for c in chunks])
                good = dep >= -tol_m
                pt, e, dep = pt[good], e[good], dep[good]
                order = np.lexsort((-dep, pt))
                first = np.unique(pt[order], return_index=True)[1]
                found[pt[order][first]] = e[order][first]

            k = min(16, len(els))
            nn = tree.query(P.T, k)[1].reshape(P.shape[1], k)
            best(np.repeat(np.arange(P.shape[1]), k), els[nn].ravel())
            rest = np.flatnonzero(found < 0)
            if rest.size:
                # a containing element's centroid lies within ``reach`` of the point
                near = tree.query_ball_point(P[:, rest].T, reach + tol_m)
                counts = np.array([len(c) for c in near], dtype=int)
                if counts.sum():
                    best(np.repeat(rest, counts), els[np.concatenate([np.asarray(c, dtype=int) for c in near])])
            return int(found[0]) if pts.ndim == 1 else found
        els = np.flatnonzero(self.body_of_element == want)
        cent = self.mesh.p[:, self.mesh.t[:, els]].mean(axis=1)
        j = els[np.argmin(np.sum((cent - p[:, None]) ** 2, axis=0))]
        # accept only when the point lies on (or within round-off of) that element's bounding box
        lo = self.mesh.p[:, self.mesh.t[:, j]].min(axis=1) - tol_m
        hi = self.mesh.p[:, self.mesh.t[:, j]].max(axis=1) + tol_m
        return int(j) if np.all(p >= lo) and np.all(p <= hi) else -1


def _grid_lines(breaks_mm: np.ndarray, h_mm: float) -> np.ndarray:
    """Grid lines [mm]: every break, with each interval split into equal cells of at most ``h_mm``."""
    lines = [breaks_mm[:1]]
    for a, b in zip(breaks_mm[:-1], breaks_mm[1:]):
        n = max(1, int(np.ceil((b - a) / h_mm - 1e-9)))
        lines.append(np.linspace(a, b, n + 1)[1:])
    return np.concatenate(lines)


def mesh_machine(machine: Machine, pose_mm: dict[str, float] | None = None, element_size_mm: float | None = None) -> MachineMesh:
    """Mesh the machine at a pose (default: mid travel of every axis).

    Parameters
    ----------
    machine : a loaded machine
    pose_mm : axis positions [mm]; missing axes at mid travel
    element_size_mm : largest element edge [mm]; default from the machine file

    Raises
    ------
    MachineFileError
        for a bad pose or geometry, and before any meshing when the element count (estimated from the
        box faces and the element size) is over the limit (:func:`hybridcomp.models.geometry.max_elements`).
    """
    pose = machine.check_pose(pose_mm or {})
    if machine.mesh.file is not None:
        return _import_mesh(machine, pose)
    check_pose_geometry(machine, pose)
    h = float(machine.mesh.element_size_mm if element_size_mm is None else element_size_mm)
    check_element_budget(machine, pose, h)
    boxes = [box_at_pose(machine, b, pose) for b in machine.bodies]
    lines_mm = []
    for d in range(3):
        br = np.unique(np.round(np.concatenate([[lo[d], hi[d]] for lo, hi in boxes]), 9))
        lines_mm.append(_grid_lines(br, h))
    grid = tuple(g * MM for g in lines_mm)
    nx, ny, nz = (len(g) - 1 for g in grid)
    cx, cy, cz = (0.5 * (g[1:] + g[:-1]) for g in lines_mm)
    CX, CY, CZ = np.meshgrid(cx, cy, cz, indexing="ij")
    body_of_cell = np.full((nx, ny, nz), -1)
    for i, (lo, hi) in enumerate(boxes):
        inside = (CX > lo[0]) & (CX < hi[0]) & (CY > lo[1]) & (CY < hi[1]) & (CZ > lo[2]) & (CZ < hi[2])
        body_of_cell[inside] = i
    full = skfem.MeshHex.init_tensor(*grid)
    # locate each tensor element in the grid by its centroid (independent of skfem's numbering)
    cent = full.p[:, full.t].mean(axis=1)
    ijk = [np.searchsorted(grid[d], cent[d]) - 1 for d in range(3)]
    body_full = body_of_cell[ijk[0], ijk[1], ijk[2]]
    keep = np.flatnonzero(body_full >= 0)
    mesh = full.restrict(keep)
    cell_of_grid = np.full(nx * ny * nz, -1)
    flat = ijk[0][keep] + nx * (ijk[1][keep] + ny * ijk[2][keep])
    cell_of_grid[flat] = np.arange(len(keep))
    body_of_element = body_full[keep]
    names = tuple(b.name for b in machine.bodies)
    mm = MachineMesh(mesh, body_of_element, names, {}, pose, grid, cell_of_grid)
    zones = _box_zone_facets(machine, mm)
    log.info("meshed %s at %s: %d nodes, %d hexahedra", machine.name, pose, mesh.p.shape[1], mesh.t.shape[1])
    return dataclasses.replace(mm, zone_facets=zones)


def _facet_normals(mesh: skfem.Mesh, facets: np.ndarray) -> np.ndarray:
    """Outward unit normals of boundary facets (3 × n)."""
    fc = mesh.p[:, mesh.facets[:, facets]].mean(axis=1)
    tc = mesh.p[:, mesh.t[:, mesh.f2t[0, facets]]].mean(axis=1)
    a = mesh.p[:, mesh.facets[0, facets]]
    b = mesh.p[:, mesh.facets[1, facets]]
    c = mesh.p[:, mesh.facets[2, facets]]
    n = np.cross((b - a).T, (c - a).T).T
    n /= np.linalg.norm(n, axis=0)
    flip = np.sum(n * (fc - tc), axis=0) < 0
    n[:, flip] *= -1
    return n


def _box_zone_facets(machine: Machine, mm: MachineMesh) -> dict[str, np.ndarray]:
    mesh = mm.mesh
    bf = mesh.boundary_facets()
    normals = _facet_normals(mesh, bf)
    body = mm.body_of_element[mesh.f2t[0, bf]]
    fc_mm = mesh.p[:, mesh.facets[:, bf]].mean(axis=1) / MM
    face_of = np.full(len(bf), "", dtype=object)
    for d, ax in enumerate("xyz"):
        face_of[normals[d] > 0.5] = "+" + ax
        face_of[normals[d] < -0.5] = "-" + ax
    claimed = np.full(len(bf), -1)
    out: dict[str, np.ndarray] = {}
    for zi, z in enumerate(machine.zones):
        if z.rest:
            continue
        sel = np.zeros(len(bf), bool)
        for s in z.surfaces:
            bi = mm.body_names.index(s.body)
            m = (body == bi) & np.isin(face_of, list(s.faces or FACES))
            if s.region_mm is not None:
                off = machine.body_offset_mm(s.body, mm.pose_mm)
                lo, hi = np.asarray(s.region_mm[0]) + off, np.asarray(s.region_mm[1]) + off
                m &= np.all((fc_mm >= lo[:, None] - 1e-9) & (fc_mm <= hi[:, None] + 1e-9), axis=0)
            sel |= m
        clash = sel & (claimed >= 0)
        if clash.any():
            other = machine.zones[claimed[np.flatnonzero(clash)[0]]].name
            raise MachineFileError(
                f"{machine.source}: field 'zones' gives surfaces to both {other!r} and {z.name!r} "
                f"(e.g. the facet at {np.round(fc_mm[:, np.flatnonzero(clash)[0]], 1).tolist()} mm)"
            )
        claimed[sel] = zi
        out[z.name] = bf[sel]
    for zi, z in enumerate(machine.zones):
        if z.rest:
            out[z.name] = bf[claimed < 0]
            claimed[claimed < 0] = zi
    for z in machine.zones:
        if len(out[z.name]) == 0:
            raise MachineFileError(f"{machine.source}: field 'zones' zone {z.name!r} has no exposed surface at pose {mm.pose_mm}")
    return out


#: mesh formats meshio reads that hold surfaces only (no tetrahedra)
SURFACE_FORMATS = (".stl", ".ply", ".off", ".obj")


def _import_mesh(machine: Machine, pose: dict[str, float]) -> MachineMesh:
    """Bodies and zones from the named cell sets of an imported mesh (units: mm in the file)."""
    import meshio

    path: Path = machine.mesh.file
    try:  # a named pipe or a device would hang meshio or feed it forever
        open_regular_file(path, MachineFileError, "mesh file").close()
    except MachineFileError as exc:
        raise MachineFileError(f"{machine.source}: field 'mesh.file': {exc}") from None
    if path.suffix.lower() in SURFACE_FORMATS:  # no volume in them, and meshio's PLY reader loops on a cut header
        raise MachineFileError(f"{machine.source}: field 'mesh.file' {str(path)!r} is a surface mesh format "
                               f"({path.suffix}): a machine's mesh needs tetrahedra in named cell sets (gmsh .msh, "
                               ".vtu, .med, Abaqus .inp)")
    said = io.StringIO()  # meshio prints why it fails, and some of its readers then exit the process
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - meshio raises many kinds, and SystemExit
        why = "" if isinstance(exc, SystemExit) else str(exc)
        why = why or " ".join(said.getvalue().split()) or type(exc).__name__
        raise MachineFileError(f"{machine.source}: field 'mesh.file' {str(path)!r} could not be read: {why}") from None
    if said.getvalue().strip():
        log.info("meshio on %s: %s", path, " ".join(said.getvalue().split()))
    moved = {k: v for k, v in pose.items() if abs(v) > 1e-12}
    if moved:
        raise MachineFileError(
            f"{machine.source}: field 'mesh.file' {path.name!r} is drawn at the reference pose (every axis at 0 mm) and cannot "
            f"be meshed at {moved}; supply one mesh file per pose"
        )
    tets = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not tets:
        raise MachineFileError(f"{machine.source}: field 'mesh.file' {str(path)!r} has no tetrahedra")
    n_tets = sum(len(m.cells[i].data) for i in tets)
    if n_tets > max_elements(machine):
        raise MachineFileError(f"{machine.source}: field 'mesh.file' {str(path)!r} has {n_tets:,} tetrahedra, more than "
                               f"the limit of {max_elements(machine):,} elements (set [mesh] max_elements)")
    offsets = np.cumsum([0] + [len(c.data) for c in m.cells])
    tet_global = np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i in tets])
    t = np.concatenate([m.cells[i].data for i in tets]).T
    used = np.unique(t)
    remap = np.full(m.points.shape[0], -1)
    remap[used] = np.arange(len(used))
    # C-contiguous arrays: skfem would otherwise copy them and log about it
    mesh = skfem.MeshTet(np.ascontiguousarray(m.points[used, :3].T * MM), np.ascontiguousarray(remap[t]))
    sets = _cell_sets(m)
    body_of_element = np.full(mesh.t.shape[1], -1)
    g2l = np.full(offsets[-1], -1)  # global cell index -> tetrahedron index (-1: not a tetrahedron)
    g2l[tet_global] = np.arange(len(tet_global))
    for bi, b in enumerate(machine.bodies):
        where = f"{machine.source}: field 'bodies[{bi}].group' {b.group!r}"
        if b.group not in sets:
            raise MachineFileError(f"{where} is not a group of {path.name} (groups: {sorted(sets)})")
        idx = g2l[sets[b.group]]
        idx = idx[idx >= 0]
        if idx.size == 0:
            raise MachineFileError(f"{where} holds no tetrahedra in {path.name}: a body must be a volume group")
        taken = body_of_element[idx]
        if (taken >= 0).any():
            other = machine.bodies[int(taken[taken >= 0][0])].name
            raise MachineFileError(f"{where} shares {(taken >= 0).sum()} tetrahedra with the group of body {other!r} "
                                   f"in {path.name}")
        body_of_element[idx] = bi
    if (body_of_element < 0).any():
        raise MachineFileError(f"{machine.source}: field 'mesh.file' has {(body_of_element < 0).sum()} tetrahedra "
                               "in no body group")
    # boundary facets per surface group: match triangles by their sorted node triples
    bf = mesh.boundary_facets()
    key = {tuple(sorted(mesh.facets[:, f])): f for f in bf}
    tri_blocks = [i for i, c in enumerate(m.cells) if c.type == "triangle"]
    tri_local = np.full(offsets[-1], -1)  # global cell index -> row of ``tri`` (-1: not a triangle)
    if tri_blocks:
        tri = np.concatenate([m.cells[i].data for i in tri_blocks])
        tri_local[np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i in tri_blocks])] = np.arange(len(tri))
    zones = {}
    claimed = set()
    for zi, z in enumerate(machine.zones):
        if z.rest:
            continue
        fs = []
        for s in z.surfaces:
            if s.group is None:
                raise MachineFileError(f"{machine.source}: field 'zones' zone {z.name!r} needs 'group' surfaces "
                                       "with an imported mesh")
            if s.group not in sets:
                raise MachineFileError(f"{machine.source}: field 'zones' group {s.group!r} is not in {path.name} "
                                       f"(groups: {sorted(sets)})")
            rows = tri_local[sets[s.group]]
            rows = rows[rows >= 0]
            if rows.size == 0:
                raise MachineFileError(
                    f"{machine.source}: field 'zones[{zi}].surfaces' group {s.group!r} holds no triangles in {path.name}: "
                    "a zone surface must be a surface group"
                )
            nodes = remap[tri[rows]]
            for r in nodes[(nodes >= 0).all(axis=1)]:
                f = key.get(tuple(sorted(r)))
                if f is not None:
                    fs.append(f)
        fs = np.unique(np.asarray(fs, dtype=int))
        if fs.size == 0:
            raise MachineFileError(
                f"{machine.source}: field 'zones' zone {z.name!r} has no exposed surface: "
                f"none of its triangles is a boundary facet of {path.name}"
            )
        if claimed & set(fs.tolist()):
            raise MachineFileError(f"{machine.source}: field 'zones' zone {z.name!r} shares surfaces with another zone")
        claimed |= set(fs.tolist())
        zones[z.name] = fs
    for z in machine.zones:
        if z.rest:
            zones[z.name] = np.asarray([f for f in bf if f not in claimed], dtype=int)
            if zones[z.name].size == 0:
                raise MachineFileError(
                    f"{machine.source}: field 'zones' zone {z.name!r} has no exposed surface: "
                    "other zones claim every boundary facet"
                )
    names = tuple(b.name for b in machine.bodies)
    return MachineMesh(mesh, body_of_element, names, zones, pose)


def _cell_sets(m) -> dict[str, np.ndarray]:
    """Named cell sets as global cell indices (meshio's per-block lists concatenated)."""
    out: dict[str, np.ndarray] = {}
    offsets = np.cumsum([0] + [len(c.data) for c in m.cells])
    for name, blocks in (m.cell_sets or {}).items():
        if name.startswith("gmsh:"):
            continue
        idx = [offsets[i] + np.asarray(b, dtype=int) for i, b in enumerate(blocks) if b is not None and len(b)]
        out[name] = np.concatenate(idx) if idx else np.zeros(0, int)
    # gmsh physical groups without cell sets: meshio's MSH 2.2 reader gives the names only in
    # field_data ({name: [tag, dim]}) and the tags in cell_data["gmsh:physical"], one array
    # per block.  Tags are unique per dimension only, so the block's dimension must match.
    phys = (m.cell_data or {}).get("gmsh:physical")
    if phys is not None and len(phys) == len(m.cells):
        for name, tag_dim in (m.field_data or {}).items():
            if len(out.get(name, ())) or name.startswith("gmsh:") or np.size(tag_dim) != 2:
                continue
            tag, dim = (int(v) for v in np.ravel(tag_dim))
            idx = [offsets[i] + np.flatnonzero(np.asarray(phys[i]) == tag) for i, c in enumerate(m.cells) if c.dim == dim]
            out[name] = np.concatenate(idx).astype(int) if idx else np.zeros(0, int)
    return out
