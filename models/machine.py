"""Typed machine definitions and their loader.

A machine file is TOML, documented field by field in ``models/README.md``.
Geometry is given in millimetres at the reference pose (every axis at 0 mm);
the loader converts nothing: SI conversion happens in ``fem``.  Every table is
checked for unknown keys so that a typo is an error, not a silent default.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import logging
import math
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.models.layout import COORDINATES, MAX_HEAT_POWER_W, TEMPERATURE_RANGE_DEGC, InputLayout, input_layout
from hybridcomp.models.toml import StrictTable, read_toml

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]
FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
AIR_KINDS = ("ambient", "workspace")
#: position feedback of a feed drive: semi-closed loop (motor encoder) or closed loop (linear scale)
FEEDBACKS = ("rotary_encoder", "linear_scale")
#: ball-screw mountings: one axially fixed bearing, or both fixed with the screw pre-stretched
MOUNTINGS = ("fixed-floating", "pre-stretched")
SPINDLE = "spindle"
GEOMETRY_TOLERANCE_MM = 1e-6

# bounds that keep the work of loading and meshing a machine file bounded on any input (models/README.md)
#: the largest magnitude of a coordinate, size or travel [mm] (100 m)
MAX_COORDINATE_MM = 1e5
#: the most axes a machine may have: the geometry is checked at 3 positions per axis, 3^n poses (6,561 for 8)
MAX_AXES = 8
#: the most box bodies a machine may have: every pair is checked at every pose
MAX_BOX_BODIES = 100
#: the most rail segments of one axis (each is a heat input and a loads column)
MAX_SEGMENTS = 1000
#: default limit of the number of elements of a box-body mesh (its tensor grid, before empty cells are dropped)
DEFAULT_MAX_ELEMENTS = 2_000_000
#: environment variable that sets the element limit when the machine file has no ``[mesh] max_elements``
MAX_ELEMENTS_ENV = "HYBRIDCOMP_MAX_ELEMENTS"
#: memory meshing takes per grid cell [bytes] (measured: ~490 on vmc800 at 30 and 49 mm); assembly takes more
MESH_BYTES_PER_ELEMENT = 500


class MachineFileError(HybridcompError, ValueError):
    """A machine file is invalid; the message names the file, field and value."""


@dataclass(frozen=True)
class Material:
    """Isotropic material.

    Attributes
    ----------
    conductivity_W_mK : thermal conductivity [W/(m K)]
    density_kg_m3 : density [kg/m^3]
    specific_heat_J_kgK : specific heat capacity [J/(kg K)]
    youngs_modulus_Pa : Young's modulus [Pa]
    poisson_ratio : Poisson's ratio [-]
    expansion_1_K : linear thermal expansion coefficient [1/K]
    """

    name: str
    conductivity_W_mK: float
    density_kg_m3: float
    specific_heat_J_kgK: float
    youngs_modulus_Pa: float
    poisson_ratio: float
    expansion_1_K: float


@dataclass(frozen=True)
class Body:
    """A rigid part of the structure: an axis-aligned box or a group of an imported mesh.

    ``box_mm`` holds the lower and upper corner [mm] at the reference pose.
    ``mounted_on`` names the body that carries it (``None``: the ground, i.e.
    the body stands on the supports).  A body moves with every axis that moves
    it or any body below it in the chain.
    """

    name: str
    material: str
    box_mm: tuple[Vec3, Vec3] | None
    group: str | None
    mounted_on: str | None


@dataclass(frozen=True)
class Axis:
    """A linear feed axis.

    Attributes
    ----------
    direction : index 0, 1, 2 for x, y, z
    moves : the body the axis drives (it carries everything mounted on it)
    travel_mm : (min, max) axis position [mm]; the geometry is given at 0 mm
    max_feed_mm_min : feed at load factor 1 [mm/min]
    segment_bounds_mm : rail segment boundaries [mm], ascending, from min to max travel
    """

    name: str
    direction: int
    moves: str
    travel_mm: tuple[float, float]
    max_feed_mm_min: float
    segment_bounds_mm: tuple[float, ...]

    @property
    def n_segments(self) -> int:
        return len(self.segment_bounds_mm) - 1

    @property
    def mid_mm(self) -> float:
        return 0.5 * (self.travel_mm[0] + self.travel_mm[1])


@dataclass(frozen=True)
class HeatSource:
    """A heat source.

    ``kind`` is ``"fixed"`` (a patch on ``body`` that moves with it) or ``"moving"``
    (a nut or guide carriage travelling with ``axis``: its heat enters the
    carrier body along the rail, split over the axis' rail segments).
    ``power_W`` is the power at load factor 1; the power at factor f is
    ``power_W * f**exponent`` unless ``power_table`` gives (factor, fraction) pairs.
    """

    name: str
    kind: str
    body: str
    axis: str | None
    driver: str | None
    position_mm: Vec3
    size_mm: Vec3
    power_W: float
    exponent: float
    power_table: tuple[tuple[float, float], ...] | None


@dataclass(frozen=True)
class Drive:
    """A ball-screw feed drive of an axis and its position feedback (``[[drives]]``, ``models/README.md``).

    The screw runs along the axis between the positions of two heat sources, its fixed bearing and its other
    bearing (floating, or the second fixed one of a pre-stretched screw); the nut moves with the axis.  The
    heat that enters the screw is given per source at load factor 1 (``*_screw_W``), in addition to the
    source's own ``power_W``, which enters the structure: it follows that source's loads column in proportion.

    Axial coordinates (``*_at_mm``) are global coordinates along the axis direction at the reference pose.
    A linear scale lies on the carrier body along the line ``scale_from_mm`` → ``scale_to_mm``, fixed at
    ``scale_fixed_at_mm``; its reading head, on the moving body, is at ``scale_head_at_mm`` at the reference pose.
    """

    axis: str
    feedback: str
    screw_diameter_mm: float
    screw_lead_mm: float
    screw_material: str
    mounting: str
    prestretch_um: float | None
    fixed_bearing: str
    floating_bearing: str
    nut: str
    fixed_bearing_screw_W: float
    floating_bearing_screw_W: float
    nut_screw_W: float
    screw_h_W_m2K: float
    screw_zone: str
    scale_body: str | None = None
    scale_from_mm: Vec3 | None = None
    scale_to_mm: Vec3 | None = None
    scale_fixed_at_mm: float | None = None
    scale_head_at_mm: float | None = None
    scale_expansion_1_K: float | None = None


@dataclass(frozen=True)
class Surface:
    """Part of a convection zone: faces of a box body (optionally clipped) or a mesh group."""

    body: str | None
    faces: tuple[str, ...]
    region_mm: tuple[Vec3, Vec3] | None
    group: str | None


@dataclass(frozen=True)
class Zone:
    """A convection zone: exposed surfaces that exchange heat with one air temperature.

    ``h_W_m2K`` is the heat-transfer coefficient [W/(m^2 K)]; ``air`` says whether
    the air is the workshop ambient or a workspace zone behind the enclosure.
    ``rest`` zones take every exposed surface no other zone claims.
    """

    name: str
    h_W_m2K: float
    air: str
    surfaces: tuple[Surface, ...]
    rest: bool


@dataclass(frozen=True)
class Point:
    """A named point attached to a body (sensor, TCP, table reference) [mm at reference pose]."""

    name: str
    body: str
    position_mm: Vec3


@dataclass(frozen=True)
class Support:
    """A point support of the ground body fixing displacement in the listed directions."""

    name: str
    body: str
    position_mm: Vec3
    directions: tuple[int, ...]


@dataclass(frozen=True)
class MeshSettings:
    """How the FE mesh is made: box bodies are meshed with ``element_size_mm``; ``file`` imports a mesh.

    ``max_elements`` is the file's limit of the element count (None: :func:`max_elements` decides).
    """

    element_size_mm: float
    file: Path | None
    max_elements: int | None = None


@dataclass(frozen=True)
class Machine:
    """A validated machine definition (see ``models/README.md``)."""

    name: str
    description: str
    source: str
    sha256: str
    reference_temperature_degC: float
    spindle_max_speed_rpm: float
    materials: dict[str, Material]
    bodies: tuple[Body, ...]
    axes: tuple[Axis, ...]
    heat_sources: tuple[HeatSource, ...]
    zones: tuple[Zone, ...]
    sensors: tuple[Point, ...]
    tcp: Point
    table_reference: Point
    supports: tuple[Support, ...]
    mesh: MeshSettings
    drives: tuple[Drive, ...] = ()

    def body(self, name: str) -> Body:
        for b in self.bodies:
            if b.name == name:
                return b
        raise KeyError(name)

    def axis(self, name: str) -> Axis:
        for a in self.axes:
            if a.name == name:
                return a
        raise KeyError(name)

    def drive(self, axis: str) -> Drive | None:
        """The feed drive of an axis, None when the file gives none."""
        return next((d for d in self.drives if d.axis == axis), None)

    def heat_source(self, name: str) -> HeatSource:
        for s in self.heat_sources:
            if s.name == name:
                return s
        raise KeyError(name)

    def default_pose_mm(self) -> dict[str, float]:
        """Mid travel of every axis [mm]; the reference pose (all 0 mm) for an imported mesh, which is drawn there."""
        if self.mesh.file is not None:
            return {a.name: 0.0 for a in self.axes}
        return {a.name: a.mid_mm for a in self.axes}

    def check_pose(self, pose_mm: dict[str, float]) -> dict[str, float]:
        """Complete a pose with mid-travel defaults and check it lies within travel."""
        names = {a.name for a in self.axes}
        for k in pose_mm:
            if k not in names:
                raise MachineFileError(f"{self.source}: pose names axis {k!r}, which the machine has not (axes: {sorted(names)})")
        full = self.default_pose_mm() | dict(pose_mm)
        for a in self.axes:
            lo, hi = a.travel_mm
            if not lo - 1e-9 <= full[a.name] <= hi + 1e-9:
                raise MachineFileError(
                    f"{self.source}: pose {a.name} = {full[a.name]} mm is outside the travel [{lo}, {hi}] mm"
                )
        return full

    def body_offset_mm(self, body: str, pose_mm: dict[str, float]) -> np.ndarray:
        """Translation [mm] of a body at a pose against the reference pose (all axes at 0)."""
        off = np.zeros(3)
        moved_by = {a.moves: a for a in self.axes}
        name: str | None = body
        seen = set()
        while name is not None:
            if name in seen:  # guarded by validation; keeps a bad object from looping
                raise MachineFileError(f"{self.source}: bodies form a mounting cycle through {name!r}")
            seen.add(name)
            if name in moved_by:
                a = moved_by[name]
                off[a.direction] += pose_mm.get(a.name, 0.0)
            name = self.body(name).mounted_on
        return off

    def layout(self) -> InputLayout:
        """The model's inputs and outputs: names, kinds, order and units (:mod:`hybridcomp.models.layout`)."""
        return input_layout(self)

    def heat_inputs(self) -> tuple[str, ...]:
        """Names of the heat inputs in the loads CSV, without the ``_W`` suffix."""
        return self.layout().heat_inputs

    def source_power_W(self, source: HeatSource, factor: float | np.ndarray) -> np.ndarray:
        """Power of a source at load factor ``factor`` (0 standstill .. 1 max speed) [W]."""
        f = np.clip(np.asarray(factor, dtype=float), 0.0, 1.0)
        if source.power_table is not None:
            xs, ys = zip(*source.power_table)
            return source.power_W * np.interp(f, xs, ys)
        return source.power_W * f**source.exponent


# --------------------------------------------------------------------------- loading


def bundled_machines() -> list[str]:
    """Names of the machine files shipped with the package."""
    root = resources.files("hybridcomp.models") / "machines"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def resolve_machine_path(name_or_path: str | Path) -> Path:
    """A bundled machine name or a path to a TOML file."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise MachineFileError(f"{p}: machine file not found")
        if not p.is_file():
            raise MachineFileError(f"{p}: not a regular file (a directory, named pipe or device); a machine file "
                                   "is a TOML file")
        return p
    root = resources.files("hybridcomp.models") / "machines"
    cand = root / f"{name_or_path}.toml"
    if not cand.is_file():
        raise MachineFileError(
            f"machine {str(name_or_path)!r} is neither a file nor a bundled machine (bundled: {bundled_machines()})"
        )
    return Path(str(cand))


def load_machine(name_or_path: str | Path) -> Machine:
    """Load and validate a machine file (bundled name or path).

    Raises
    ------
    MachineFileError
        naming the file, the field and the offending value.
    """
    path = resolve_machine_path(name_or_path)
    data, raw = read_toml(path, MachineFileError)
    return parse_machine(data, source=str(path), sha256=hashlib.sha256(raw).hexdigest(), base_dir=path.parent)


KEYS = {
    "top": ("machine", "spindle", "mesh", "materials", "bodies", "axes", "heat_sources", "zones", "sensors", "tcp",
            "table_reference", "supports", "drives"),
    "machine": ("name", "description", "reference_temperature_degC"),
    "spindle": ("max_speed_rpm",),
    "mesh": ("element_size_mm", "file", "max_elements"),
    "material": ("conductivity_W_mK", "density_kg_m3", "specific_heat_J_kgK", "youngs_modulus_GPa", "poisson_ratio",
                 "expansion_1_K"),
    "body": ("name", "material", "box_mm", "group", "mounted_on"),
    "axis": ("name", "direction", "moves", "travel_mm", "max_feed_mm_min", "segments", "segment_bounds_mm"),
    "heat_source": ("name", "kind", "body", "axis", "driver", "position_mm", "size_mm", "power_W", "exponent",
                    "power_table"),
    "zone": ("name", "h_W_m2K", "air", "rest", "surfaces"),
    "surface": ("body", "faces", "region_mm", "group"),
    "point": ("name", "body", "position_mm"),
    "anchor": ("body", "position_mm"),
    "support": ("name", "body", "position_mm", "directions"),
    "box": ("lo", "hi"),
    "drive": ("axis", "feedback", "screw_diameter_mm", "screw_lead_mm", "screw_material", "mounting", "prestretch_um",
              "fixed_bearing", "floating_bearing", "nut", "fixed_bearing_screw_W", "floating_bearing_screw_W",
              "nut_screw_W", "screw_h_W_m2K", "screw_zone", "scale_body", "scale_from_mm", "scale_to_mm",
              "scale_fixed_at_mm", "scale_head_at_mm", "scale_expansion_1_K"),
}


class _Reader(StrictTable):
    """Reads one machine-file table of a known kind (:data:`KEYS`); an unknown key is an error before anything else."""

    def __init__(self, src: str, where: str, table: Any, kind: str):
        super().__init__(src, where, table, KEYS[kind], MachineFileError)

    def _name(self, key: str) -> str:
        return self.name(key)

    def vec3(self, key: str, default: Any = ..., positive: bool = False) -> Vec3:
        v = self.get(key, default, (list, tuple))
        if v is None:
            return v
        if len(v) != 3 or not all(_is_number(x) for x in v):
            raise self.err(key, f"must be three numbers [mm], got {v!r}")
        if not all(_plausible_mm(x) for x in v):
            raise self.err(key, f"must be finite and within ±{MAX_COORDINATE_MM:g} mm, got {v!r}")
        if positive and min(v) <= 0:
            raise self.err(key, f"must be positive in every direction, got {v!r}")
        return (float(v[0]), float(v[1]), float(v[2]))

    def box(self, key: str, default: Any = ..., flat_ok: bool = False) -> tuple[Vec3, Vec3] | None:
        v = self.get(key, default, (list, tuple))
        if v is None:
            return None
        if len(v) != 2:
            raise self.err(key, f"must be [[x0, y0, z0], [x1, y1, z1]] in mm, got {v!r}")
        sub = _Reader(self.src, self._name(key), {"lo": v[0], "hi": v[1]}, "box")
        lo, hi = sub.vec3("lo"), sub.vec3("hi")
        if any(b < a or (b == a and not flat_ok) for a, b in zip(lo, hi)):
            raise self.err(key, f"must have its second corner above the first in x, y and z, got {v!r}")
        return lo, hi


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _plausible_mm(x: float) -> bool:
    """A finite length or coordinate within ±:data:`MAX_COORDINATE_MM`."""
    return math.isfinite(x) and abs(x) <= MAX_COORDINATE_MM


def _name_of(rd: _Reader) -> str:
    name = rd.get("name", kind=str)
    if not name or not all(c.isalnum() or c in "_-" for c in name):
        raise rd.err("name", f"must be letters, digits, '_' or '-', got {name!r}")
    return name


def parse_machine(data: dict, source: str = "<machine>", sha256: str = "", base_dir: Path | None = None) -> Machine:
    """Build a validated :class:`Machine` from parsed TOML."""
    top = _Reader(source, "", data, "top")

    m = _Reader(source, "machine", top.get("machine", kind=dict), "machine")
    name = _name_of(m)
    description = m.get("description", "", str)
    t_ref = m.number("reference_temperature_degC", 20.0)
    if not TEMPERATURE_RANGE_DEGC[0] <= t_ref <= TEMPERATURE_RANGE_DEGC[1]:
        raise m.err("reference_temperature_degC", f"must be within {list(TEMPERATURE_RANGE_DEGC)} °C, got {t_ref!r}")

    sp = _Reader(source, "spindle", top.get("spindle", {}, dict), "spindle")
    spindle_rpm = sp.number("max_speed_rpm", 0.0, nonneg=True)

    materials: dict[str, Material] = {}
    mats = top.get("materials", kind=dict)
    for mname, mt in mats.items():
        r = _Reader(source, f"materials.{mname}", mt, "material")
        nu = r.number("poisson_ratio")
        if not 0.0 <= nu < 0.5:
            raise r.err("poisson_ratio", f"must be in [0, 0.5), got {nu!r}")
        materials[mname] = Material(
            name=mname,
            conductivity_W_mK=r.number("conductivity_W_mK", positive=True),
            density_kg_m3=r.number("density_kg_m3", positive=True),
            specific_heat_J_kgK=r.number("specific_heat_J_kgK", positive=True),
            youngs_modulus_Pa=r.number("youngs_modulus_GPa", positive=True) * 1e9,
            poisson_ratio=nu,
            expansion_1_K=r.number("expansion_1_K", nonneg=True),
        )
    if not materials:
        raise top.err("materials", "must define at least one material")

    msh = _Reader(source, "mesh", top.get("mesh", {}, dict), "mesh")
    h_mm = msh.number("element_size_mm", 50.0, positive=True)
    max_el = msh.number("max_elements", None, integer=True)
    if max_el is not None and max_el < 1:
        raise msh.err("max_elements", f"must be at least 1, got {max_el!r}")
    mfile = msh.get("file", None, str)
    mesh_path = None
    if mfile is not None:
        mesh_path = Path(mfile) if Path(mfile).is_absolute() else (base_dir or Path(".")) / mfile
        if not mesh_path.exists():
            raise msh.err("file", f"names a mesh that does not exist: {mfile!r} (looked at {mesh_path})")
        if not mesh_path.is_file():
            raise msh.err("file", f"names {mfile!r}, which is not a regular file (looked at {mesh_path})")

    bodies: list[Body] = []
    for where, t in top.tables("bodies"):
        r = _Reader(source, where, t, "body")
        bname = _name_of(r)
        mat = r.get("material", kind=str)
        if mat not in materials:
            raise r.err("material", f"names an unknown material {mat!r} (defined: {sorted(materials)})")
        box = r.box("box_mm", None)
        group = r.get("group", None, str)
        if mesh_path is None and box is None:
            raise r.err("box_mm", "is required when the machine has no [mesh] file")
        if mesh_path is None and group is not None:
            raise r.err("group", f"= {group!r} needs an imported [mesh] file; box bodies have no groups")
        if mesh_path is not None and box is not None:
            raise r.err("box_mm", "cannot be combined with an imported [mesh] file; name the mesh group with 'group'")
        if mesh_path is not None and group is None:
            group = bname
        bodies.append(Body(bname, mat, box, group, r.get("mounted_on", None, str)))
    if not bodies:
        raise top.err("bodies", "must define at least one body")
    if mesh_path is None and len(bodies) > MAX_BOX_BODIES:
        raise top.err("bodies", f"has {len(bodies)} box bodies, more than the limit of {MAX_BOX_BODIES} (every pair of "
                                "bodies is checked at every pose)")
    _unique(source, "bodies", [b.name for b in bodies])
    body_names = {b.name for b in bodies}
    for i, b in enumerate(bodies):
        if b.mounted_on is not None and b.mounted_on not in body_names:
            raise MachineFileError(f"{source}: field 'bodies[{i}].mounted_on' names an unknown body {b.mounted_on!r}")
    _check_mount_tree(source, bodies)

    axes: list[Axis] = []
    for where, t in top.tables("axes", required=False):
        r = _Reader(source, where, t, "axis")
        aname = _name_of(r)
        if aname == SPINDLE:
            raise r.err("name", f"must not be {SPINDLE!r}, which names the spindle drive")
        d = r.get("direction", kind=str)
        if d not in COORDINATES:
            raise r.err("direction", f"must be one of {COORDINATES}, got {d!r}")
        moves = r.get("moves", kind=str)
        if moves not in body_names:
            raise r.err("moves", f"names an unknown body {moves!r}")
        tr = r.get("travel_mm", kind=list)
        if len(tr) == 2 and all(_is_number(x) for x in tr) and not all(_plausible_mm(x) for x in tr):
            raise r.err("travel_mm", f"must be finite and within ±{MAX_COORDINATE_MM:g} mm, got {tr!r}")
        if len(tr) != 2 or not all(_is_number(x) for x in tr) or tr[1] <= tr[0]:
            raise r.err("travel_mm", f"must be [min, max] with max > min, got {tr!r}")
        if not tr[0] <= 0 <= tr[1]:
            raise r.err("travel_mm", f"must contain 0 mm, the reference pose the geometry is given at, got {tr!r}")
        feed = r.number("max_feed_mm_min", positive=True)
        nseg = r.get("segments", None, int)
        bounds = r.get("segment_bounds_mm", None, list)
        if (nseg is None) == (bounds is None):
            raise r.err("segments", "or 'segment_bounds_mm' must be given (exactly one of them)")
        if nseg is not None:
            if not 1 <= nseg <= MAX_SEGMENTS:
                raise r.err("segments", f"must be from 1 to {MAX_SEGMENTS}, got {nseg!r}")
            bounds = list(np.linspace(tr[0], tr[1], nseg + 1))
        else:
            if (
                not all(_is_number(b) and _plausible_mm(b) for b in bounds)
                or not 2 <= len(bounds) <= MAX_SEGMENTS + 1
                or abs(bounds[0] - tr[0]) > 1e-9
                or abs(bounds[-1] - tr[1]) > 1e-9
                or any(b <= a for a, b in zip(bounds, bounds[1:]))
            ):
                raise r.err("segment_bounds_mm", f"must ascend from the travel min to max {tr!r} in at most "
                                                 f"{MAX_SEGMENTS} segments, got {bounds!r}")
        axes.append(Axis(aname, COORDINATES.index(d), moves, (float(tr[0]), float(tr[1])), feed, tuple(float(b) for b in bounds)))
    if len(axes) > MAX_AXES:
        raise top.err("axes", f"has {len(axes)} axes, more than the limit of {MAX_AXES} (the geometry is checked at "
                              f"3^n poses: 3^{len(axes)} = {3 ** len(axes):,})")
    _unique(source, "axes", [a.name for a in axes])
    _unique(source, "axes[].moves", [a.moves for a in axes])
    axis_names = {a.name for a in axes}
    for i, a in enumerate(axes):
        if bodies_by(bodies)[a.moves].mounted_on is None:
            raise MachineFileError(f"{source}: field 'axes[{i}].moves' names {a.moves!r}, a body on the ground, "
                                   "which cannot move")

    sources: list[HeatSource] = []
    for where, t in top.tables("heat_sources", required=False):
        r = _Reader(source, where, t, "heat_source")
        sname = _name_of(r)
        kind = r.get("kind", "fixed", str)
        if kind not in ("fixed", "moving"):
            raise r.err("kind", f"must be 'fixed' or 'moving', got {kind!r}")
        driver = r.get("driver", None, str)
        if kind == "fixed" and "axis" in t:
            raise r.err("axis", f"= {t['axis']!r} is only for moving sources; a fixed source names its 'driver'")
        axis = r.get("axis", None, str) if kind == "moving" else None
        if kind == "moving":
            if axis is None:
                raise r.err("axis", "is required for a moving source")
            if axis not in axis_names:
                raise r.err("axis", f"names an unknown axis {axis!r} (axes: {sorted(axis_names)})")
            driver = driver or axis
            carrier = bodies_by(bodies)[[a for a in axes if a.name == axis][0].moves].mounted_on
            body = r.get("body", carrier, str)
            if body != carrier:
                raise r.err("body", f"of a moving source must be the body carrying the rail of axis {axis} "
                                    f"({carrier!r}), got {body!r}")
        else:
            body = r.get("body", kind=str)
        if body not in body_names:
            raise r.err("body", f"names an unknown body {body!r}")
        if driver is not None and driver not in axis_names | {SPINDLE}:
            raise r.err("driver", f"must be an axis name or {SPINDLE!r}, got {driver!r}")
        if driver == SPINDLE and spindle_rpm <= 0:
            raise r.err("driver", "is 'spindle' but [spindle] max_speed_rpm is not set")
        table = r.get("power_table", None, list)
        if table is not None:
            ok = all(isinstance(p, list) and len(p) == 2 and all(_is_number(x) and math.isfinite(x) for x in p)
                     for p in table)
            xs = [p[0] for p in table] if ok else []
            if (not ok or len(table) < 2 or xs[0] != 0 or xs[-1] != 1 or any(b <= a for a, b in zip(xs, xs[1:]))
                    or any(p[1] < 0 for p in table)):
                raise r.err("power_table", "must be [[0, p0], ..., [1, p1]] with ascending factors and fractions >= 0, "
                                           f"got {table!r}")
            table = tuple((float(a), float(b)) for a, b in table)
        sources.append(
            HeatSource(
                name=sname,
                kind=kind,
                body=body,
                axis=axis,
                driver=driver,
                position_mm=r.vec3("position_mm"),
                size_mm=r.vec3("size_mm", (20.0, 20.0, 20.0), positive=True),
                power_W=_power(r),
                exponent=r.number("exponent", 1.0, positive=True),
                power_table=table,
            )
        )
    _unique(source, "heat_sources", [s.name for s in sources])

    zones: list[Zone] = []
    for where, t in top.tables("zones", required=False):
        r = _Reader(source, where, t, "zone")
        zname = _name_of(r)
        h = r.number("h_W_m2K")
        if h <= 0:
            raise r.err("h_W_m2K", f"must be positive, got {h!r}")
        air = r.get("air", "ambient", str)
        if air not in AIR_KINDS:
            raise r.err("air", f"must be one of {AIR_KINDS}, got {air!r}")
        rest = r.get("rest", False, bool)
        if rest and "surfaces" in t:
            raise r.err("surfaces", "cannot be combined with rest = true (a rest zone takes every unclaimed surface)")
        surfs = []
        for swhere, st in r.tables("surfaces", required=not rest):
            sr = _Reader(source, swhere, st, "surface")
            group = sr.get("group", None, str)
            body = sr.get("body", None, str)
            faces = tuple(sr.get("faces", list(FACES) if body else [], list))
            if body is not None and not faces:
                raise sr.err("faces", "must list at least one face (omit it for all six)")
            if group is None and body is None:
                raise sr.err("body", "or 'group' is required")
            if body is not None and body not in body_names:
                raise sr.err("body", f"names an unknown body {body!r}")
            if group is not None and mesh_path is None:
                raise sr.err("group", "needs an imported [mesh] file")
            for f in faces:
                if f not in FACES:
                    raise sr.err("faces", f"must list faces of {FACES}, got {f!r}")
            surfs.append(Surface(body, faces, sr.box("region_mm", None, flat_ok=True), group))
        zones.append(Zone(zname, h, air, tuple(surfs), rest))
    _unique(source, "zones", [z.name for z in zones])
    if sum(z.rest for z in zones) > 1:
        raise top.err("zones", "may have only one zone with rest = true")

    def point(where: str, t: dict, named: bool = True) -> Point:
        r = _Reader(source, where, t, "point" if named else "anchor")
        pname = _name_of(r) if named else where
        body = r.get("body", None, str)
        if body is not None and body not in body_names:
            raise r.err("body", f"names an unknown body {body!r}")
        pos = r.vec3("position_mm")
        return Point(pname, body or "", pos)

    sensors = tuple(point(w, t) for w, t in top.tables("sensors", required=False))
    _unique(source, "sensors", [s.name for s in sensors])
    tcp = point("tcp", top.get("tcp", kind=dict), named=False)
    table_ref = point("table_reference", top.get("table_reference", kind=dict), named=False)

    supports: list[Support] = []
    for where, t in top.tables("supports"):
        r = _Reader(source, where, t, "support")
        dirs = r.get("directions", kind=list)
        if not dirs or any(d not in COORDINATES for d in dirs) or len(set(dirs)) != len(dirs):
            raise r.err("directions", f"must list distinct directions of {COORDINATES}, got {dirs!r}")
        body = r.get("body", None, str)
        if body is not None and body not in body_names:
            raise r.err("body", f"names an unknown body {body!r}")
        supports.append(Support(_name_of(r), body or "", r.vec3("position_mm"), tuple(COORDINATES.index(d) for d in dirs)))
    _unique(source, "supports", [s.name for s in supports])

    machine = Machine(
        name=name,
        description=description,
        source=source,
        sha256=sha256,
        reference_temperature_degC=t_ref,
        spindle_max_speed_rpm=spindle_rpm,
        materials=materials,
        bodies=tuple(bodies),
        axes=tuple(axes),
        heat_sources=tuple(sources),
        zones=tuple(zones),
        sensors=sensors,
        tcp=tcp,
        table_reference=table_ref,
        supports=tuple(supports),
        mesh=MeshSettings(h_mm, mesh_path, max_el),
    )
    machine = _validate_geometry(machine)  # the drives build on checked sources and bodies
    drives = tuple(_drive(machine, where, t) for where, t in top.tables("drives", required=False))
    _unique(source, "drives[].axis", [d.axis for d in drives])
    return dataclasses.replace(machine, drives=drives)


def _power(r: _Reader) -> float:
    p = r.number("power_W", nonneg=True)
    if p > MAX_HEAT_POWER_W:
        raise r.err("power_W", f"must be at most {MAX_HEAT_POWER_W:g} W (a plausible heat source), got {p!r}")
    return p


#: default heat-transfer coefficient of a turning ball screw to the air around it [W/(m^2 K)] (forced convection
#: at a few hundred rpm; Xu et al. 2007 report 20-50)
SCREW_H_W_M2K = 20.0


def _drive(machine: Machine, where: str, t: dict) -> Drive:
    """One ``[[drives]]`` table, checked against the machine's axes, sources, zones and bodies."""
    r = _Reader(machine.source, where, t, "drive")
    axis_name = r.string("axis")
    try:
        axis = machine.axis(axis_name)
    except KeyError:
        raise r.err("axis", f"names an unknown axis {axis_name!r} (axes: {[a.name for a in machine.axes]})") from None
    d = axis.direction
    carrier = machine.body(axis.moves).mounted_on
    feedback = r.string("feedback", choices=FEEDBACKS)
    mounting = r.string("mounting", "fixed-floating", choices=MOUNTINGS)
    prestretch = r.number("prestretch_um", None, nonneg=True)
    if prestretch is not None and mounting != "pre-stretched":
        raise r.err("prestretch_um", f"= {prestretch!r} is only for mounting = 'pre-stretched', not {mounting!r}")
    material = r.string("screw_material")
    if material not in machine.materials:
        raise r.err("screw_material", f"names an unknown material {material!r} (defined: {sorted(machine.materials)})")

    def source(key: str, kind: str) -> HeatSource:
        name = r.string(key)
        try:
            s = machine.heat_source(name)
        except KeyError:
            raise r.err(key, f"names an unknown heat source {name!r}") from None
        if kind == "fixed" and (s.kind != "fixed" or s.body != carrier):
            raise r.err(key, f"= {name!r} must be a fixed heat source on {carrier!r}, the body carrying axis "
                             f"{axis.name}'s rail (it is a {s.kind} source on {s.body!r})")
        if kind == "moving" and (s.kind != "moving" or s.axis != axis.name):
            raise r.err(key, f"= {name!r} must be a moving heat source of axis {axis.name} (the nut)")
        return s

    fixed, floating, nut = source("fixed_bearing", "fixed"), source("floating_bearing", "fixed"), source("nut", "moving")
    s_fixed, s_float = fixed.position_mm[d], floating.position_mm[d]
    if abs(s_float - s_fixed) < 1.0:
        raise r.err("floating_bearing", f"= {floating.name!r} lies {abs(s_float - s_fixed):g} mm from the fixed bearing "
                                        f"along {COORDINATES[d]}: the screw between them must be at least 1 mm long")
    lo, hi = sorted((s_fixed, s_float))
    nut_lo, nut_hi = nut.position_mm[d] + axis.travel_mm[0], nut.position_mm[d] + axis.travel_mm[1]
    if nut_lo < lo - GEOMETRY_TOLERANCE_MM or nut_hi > hi + GEOMETRY_TOLERANCE_MM:
        raise r.err("nut", f"= {nut.name!r} travels over {COORDINATES[d]} = [{nut_lo:g}, {nut_hi:g}] mm, beyond the "
                           f"screw between its bearings [{lo:g}, {hi:g}] mm")
    heat = {}
    for key, s in (("fixed_bearing_screw_W", fixed), ("floating_bearing_screw_W", floating), ("nut_screw_W", nut)):
        heat[key] = r.number(key, 0.0, nonneg=True)
        if heat[key] > MAX_HEAT_POWER_W:
            raise r.err(key, f"must be at most {MAX_HEAT_POWER_W:g} W, got {heat[key]!r}")
        if heat[key] > 0 and s.power_W <= 0:
            raise r.err(key, f"= {heat[key]!r} W follows source {s.name!r}, whose power_W is 0: give that source a power")
    rest = [z.name for z in machine.zones if z.rest]
    zone = r.string("screw_zone", rest[0] if rest else None)
    if zone is None:
        raise r.err("screw_zone", "is required: the machine has no rest zone to default to")
    if zone not in [z.name for z in machine.zones]:
        raise r.err("screw_zone", f"names an unknown zone {zone!r} (zones: {[z.name for z in machine.zones]})")
    drive = Drive(
        axis=axis.name, feedback=feedback,
        screw_diameter_mm=r.number("screw_diameter_mm", positive=True),
        screw_lead_mm=r.number("screw_lead_mm", positive=True),
        screw_material=material, mounting=mounting, prestretch_um=prestretch,
        fixed_bearing=fixed.name, floating_bearing=floating.name, nut=nut.name, **heat,
        screw_h_W_m2K=r.number("screw_h_W_m2K", SCREW_H_W_M2K, positive=True), screw_zone=zone,
    )
    scale_keys = [k for k in KEYS["drive"] if k.startswith("scale_") and k in t]
    if feedback == "rotary_encoder":
        if scale_keys:
            raise r.err(scale_keys[0], "is only for feedback = 'linear_scale' (this drive reads a rotary encoder)")
        return drive
    return dataclasses.replace(drive, **_scale(r, machine, axis, carrier, nut))


def _scale(r: _Reader, machine: Machine, axis: Axis, carrier: str, nut: HeatSource) -> dict:
    """The linear-scale fields of a drive: a line along the axis on the carrier body, its fixed point and head."""
    d = axis.direction
    body = r.string("scale_body", carrier)
    if body != carrier:
        raise r.err("scale_body", f"must be {carrier!r}, the body carrying axis {axis.name} (its reading head rides "
                                  f"on {axis.moves!r}), got {body!r}")
    a, b = r.vec3("scale_from_mm"), r.vec3("scale_to_mm")
    off = [i for i in range(3) if i != d and abs(a[i] - b[i]) > GEOMETRY_TOLERANCE_MM]
    if off or b[d] <= a[d]:
        raise r.err("scale_to_mm", f"must lie along {COORDINATES[d]} from scale_from_mm {list(a)} (equal in the other "
                                   f"coordinates, larger in {COORDINATES[d]}), got {list(b)}")
    box = machine.body(body).box_mm
    for key, p in (("scale_from_mm", a), ("scale_to_mm", b)):
        if box is not None and not _inside(box, p):
            raise r.err(key, f"= {list(p)} mm is outside the scale's body {body!r}")
    fixed = r.number("scale_fixed_at_mm", a[d])
    head = r.number("scale_head_at_mm", nut.position_mm[d])
    if not a[d] - GEOMETRY_TOLERANCE_MM <= fixed <= b[d] + GEOMETRY_TOLERANCE_MM:
        raise r.err("scale_fixed_at_mm", f"= {fixed!r} mm is off the scale [{a[d]:g}, {b[d]:g}] mm")
    if head + axis.travel_mm[0] < a[d] - GEOMETRY_TOLERANCE_MM or head + axis.travel_mm[1] > b[d] + GEOMETRY_TOLERANCE_MM:
        raise r.err("scale_head_at_mm", f"= {head!r} mm: the reading head travels over [{head + axis.travel_mm[0]:g}, "
                                        f"{head + axis.travel_mm[1]:g}] mm, beyond the scale [{a[d]:g}, {b[d]:g}] mm")
    return dict(scale_body=body, scale_from_mm=a, scale_to_mm=b, scale_fixed_at_mm=fixed, scale_head_at_mm=head,
                scale_expansion_1_K=r.number("scale_expansion_1_K", nonneg=True))


def bodies_by(bodies) -> dict[str, Body]:
    """Bodies by name."""
    return {b.name: b for b in bodies}


def _unique(source: str, field: str, names: list[str]) -> None:
    seen = set()
    for n in names:
        if n in seen:
            raise MachineFileError(f"{source}: field {field!r} has the name {n!r} twice")
        seen.add(n)


def _check_mount_tree(source: str, bodies: list[Body]) -> None:
    by = bodies_by(bodies)
    for b in bodies:
        seen = [b.name]
        cur = b.mounted_on
        while cur is not None:
            if cur in seen:
                raise MachineFileError(f"{source}: field 'bodies.mounted_on' forms a cycle {' -> '.join(seen + [cur])}")
            seen.append(cur)
            cur = by[cur].mounted_on


# --------------------------------------------------------------------------- geometry checks


def _inside(box: tuple[Vec3, Vec3], p, tol: float = GEOMETRY_TOLERANCE_MM) -> bool:
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


def _validate_geometry(machine: Machine) -> Machine:
    src = machine.source
    if machine.mesh.file is None:
        box_ok = lambda b, p: _inside(b.box_mm, p)  # noqa: E731
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
        if not _inside(b.box_mm, s.position_mm):
            raise MachineFileError(f"{machine.source}: field {where!r} = {list(s.position_mm)} mm is outside its body {s.body!r}")
        return
    a = machine.axis(s.axis)
    for end in a.travel_mm:
        p = np.asarray(s.position_mm, float)
        p[a.direction] += end
        # the rail patch lies in the carrier body, which does not move with this axis
        if not _inside(b.box_mm, p):
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
