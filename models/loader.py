"""The machine-file loader: TOML to a validated :class:`~hybridcomp.models.machine.Machine`.

A machine file is TOML, documented field by field in ``models/README.md``.  :func:`parse_machine` reads it with
one small reader per table; every table is checked for unknown keys so that a typo is an error, not a silent
default.  Geometry is given in millimetres at the reference pose (every axis at 0 mm); the loader converts
nothing: SI conversion happens in ``fem``.  The geometry checks are :mod:`hybridcomp.models.geometry`'s.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from hybridcomp.models.convection import screw_h_W_m2K
from hybridcomp.models.geometry import GEOMETRY_TOLERANCE_MM, inside_box, validate_geometry
from hybridcomp.models.layout import COORDINATES, MAX_HEAT_POWER_W, TEMPERATURE_RANGE_DEGC
from hybridcomp.models.machine import (
    AIR_KINDS,
    FACES,
    FEEDBACKS,
    MOUNTINGS,
    SPINDLE,
    Axis,
    Body,
    Drive,
    HeatSource,
    Machine,
    MachineFileError,
    Material,
    MeshSettings,
    Point,
    Support,
    Surface,
    Vec3,
    Zone,
)
from hybridcomp.models.toml import StrictTable, read_toml

# bounds that keep the work of loading and meshing a machine file bounded on any input (models/README.md)
#: the largest magnitude of a coordinate, size or travel [mm] (100 m)
MAX_COORDINATE_MM = 1e5
#: the most axes a machine may have: the geometry is checked at 3 positions per axis, 3^n poses (6,561 for 8)
MAX_AXES = 8
#: the most box bodies a machine may have: every pair is checked at every pose
MAX_BOX_BODIES = 100
#: the most rail segments of one axis (each is a heat input and a loads column)
MAX_SEGMENTS = 1000

#: plausible material and boundary values, field -> (lowest, highest, unit): what engineering solids (and, for
#: the thermal properties, gases) span at room temperature; beyond them a value is a typing mistake (1e-300,
#: 1e300), never a machine, and would make simulate write 1e281 °C or NaN. Sources:
#: conductivity: Incropera & DeWitt, Fundamentals of Heat and Mass Transfer, Fig. 2.4 and Tables A.1-A.4
#:   (gases 0.007-0.2, insulation 0.02-0.1, metals 10-430, diamond about 2,300 W/(m K));
#: density: CRC Handbook of Chemistry and Physics (hydrogen 0.08 kg/m³ at 1 bar to osmium 22,590 kg/m³);
#: specific heat: CRC Handbook (lead, gold, tungsten about 130 J/(kg K) to hydrogen 14,300 J/(kg K));
#: Young's modulus and expansion: Ashby, Materials Selection in Mechanical Design, charts E-ρ and α-λ
#:   (foams and elastomers 1e-4 GPa to diamond 1,200 GPa; zero-expansion glass ceramics 0 to elastomers
#:   and polymers below 1e-3 1/K);
#: heat-transfer coefficient: Incropera Table 1.1 (free convection of gases 2-25, forced liquids up to 20,000,
#:   boiling and condensation up to 100,000 W/(m² K)), down to 0.1 for a surface that is all but insulated;
#: a bearing's conductance: up to that of a 1 m² steel plate 5 mm thick (1e4 W/K).
#: Poisson's ratio is checked against [0, 0.5) (isotropic solids, no auxetics). The machine file has no emissivity
#: (radiation is part of the coefficient h).
PHYSICAL_RANGES = {
    "conductivity_W_mK": (0.005, 2500.0, "W/(m K)"),
    "density_kg_m3": (0.08, 23000.0, "kg/m³"),
    "specific_heat_J_kgK": (100.0, 15000.0, "J/(kg K)"),
    "youngs_modulus_GPa": (1e-4, 1200.0, "GPa"),
    "expansion_1_K": (0.0, 1e-3, "1/K"),
    "scale_expansion_1_K": (0.0, 1e-3, "1/K"),
    "h_W_m2K": (0.1, 1e5, "W/(m² K)"),
    "screw_h_W_m2K": (0.1, 1e5, "W/(m² K)"),
    "bearing_conductance_W_K": (0.0, 1e4, "W/K"),
}


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
    "table_reference": ("body", "position_mm", "under_tool"),
    "support": ("name", "body", "position_mm", "directions"),
    "box": ("lo", "hi"),
    "drive": ("axis", "feedback", "screw_diameter_mm", "screw_lead_mm", "screw_material", "mounting", "prestretch_um",
              "fixed_bearing", "floating_bearing", "nut", "fixed_bearing_screw_W", "floating_bearing_screw_W",
              "nut_screw_W", "screw_h_W_m2K", "screw_zone", "scale_body", "scale_from_mm", "scale_to_mm",
              "scale_fixed_at_mm", "scale_head_at_mm", "scale_expansion_1_K", "screw_mean_rpm",
              "bearing_conductance_W_K"),
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


def _physical(r: _Reader, key: str, default: Any = ...) -> Any:
    """A material or boundary value within :data:`PHYSICAL_RANGES` (a default is returned unchecked)."""
    v = r.number(key, default)
    if key not in r.t:
        return v
    lo, hi, unit = PHYSICAL_RANGES[key]
    if lo > 0 and not v > 0:
        raise r.err(key, f"must be positive, got {v!r}")
    if not v >= 0:
        raise r.err(key, f"must not be negative, got {v!r}")
    if not lo <= v <= hi:
        raise r.err(key, f"= {v!r} {unit} is outside the plausible range [{lo:g}, {hi:g}] {unit} of engineering "
                         "materials (models/README.md, 'Plausible values')")
    return v


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
    """Build a validated :class:`Machine` from parsed TOML.

    One reader per table, in the order the tables build on each other; the geometry checks
    (:func:`hybridcomp.models.geometry.validate_geometry`) run before the drives, which build on checked sources
    and bodies.

    Parameters
    ----------
    data : the parsed TOML
    source : the file's name in messages and in :attr:`Machine.source`
    sha256 : the file's checksum
    base_dir : the folder a relative ``[mesh] file`` is found in (default: the working directory)

    Raises
    ------
    MachineFileError
        naming the file, the field and the offending value.
    """
    top = _Reader(source, "", data, "top")
    name, description, t_ref = _read_machine(_Reader(source, "machine", top.get("machine", kind=dict), "machine"))
    spindle_rpm = _read_spindle(_Reader(source, "spindle", top.get("spindle", {}, dict), "spindle"))
    materials = _read_materials(top)
    mesh = _read_mesh(_Reader(source, "mesh", top.get("mesh", {}, dict), "mesh"), base_dir)
    bodies = _read_bodies(top, materials, mesh.file)
    axes = _read_axes(top, bodies)
    sources = _read_heat_sources(top, bodies, axes, spindle_rpm)
    zones = _read_zones(top, bodies, mesh.file)
    sensors = tuple(_read_point(source, w, t, bodies) for w, t in top.tables("sensors", required=False))
    _unique(source, "sensors", [s.name for s in sensors])
    tcp = _read_point(source, "tcp", top.get("tcp", kind=dict), bodies, named=False)
    table_ref, under_tool = _read_table_reference(_Reader(source, "table_reference",
                                                          top.get("table_reference", kind=dict), "table_reference"),
                                                  bodies, mesh)
    supports = _read_supports(top, bodies)

    machine = Machine(
        name=name,
        description=description,
        source=source,
        sha256=sha256,
        reference_temperature_degC=t_ref,
        spindle_max_speed_rpm=spindle_rpm,
        materials=materials,
        bodies=bodies,
        axes=axes,
        heat_sources=sources,
        zones=zones,
        sensors=sensors,
        tcp=tcp,
        table_reference=table_ref,
        supports=supports,
        mesh=mesh,
        table_under_tool=under_tool,
    )
    machine = validate_geometry(machine)  # the drives build on checked sources and bodies
    return dataclasses.replace(machine, drives=_read_drives(top, machine))


def _read_machine(m: _Reader) -> tuple[str, str, float]:
    """``[machine]``: the name, the description and the reference temperature [°C]."""
    name = _name_of(m)
    description = m.get("description", "", str)
    t_ref = m.number("reference_temperature_degC", 20.0)
    if not TEMPERATURE_RANGE_DEGC[0] <= t_ref <= TEMPERATURE_RANGE_DEGC[1]:
        raise m.err("reference_temperature_degC", f"must be within {list(TEMPERATURE_RANGE_DEGC)} °C, got {t_ref!r}")
    return name, description, t_ref


def _read_spindle(sp: _Reader) -> float:
    """``[spindle]``: the spindle's maximum speed [rpm] (0: no spindle)."""
    return sp.number("max_speed_rpm", 0.0, nonneg=True)


def _read_materials(top: _Reader) -> dict[str, Material]:
    """``[materials.<name>]``: at least one."""
    materials: dict[str, Material] = {}
    for mname, mt in top.get("materials", kind=dict).items():
        materials[mname] = _read_material(top.src, mname, mt)
    if not materials:
        raise top.err("materials", "must define at least one material")
    return materials


def _read_material(source: str, mname: str, mt: Any) -> Material:
    """One ``[materials.<name>]`` table."""
    r = _Reader(source, f"materials.{mname}", mt, "material")
    nu = r.number("poisson_ratio")
    if not 0.0 <= nu < 0.5:
        raise r.err("poisson_ratio", f"must be in [0, 0.5), got {nu!r}")
    return Material(
        name=mname,
        conductivity_W_mK=_physical(r, "conductivity_W_mK"),
        density_kg_m3=_physical(r, "density_kg_m3"),
        specific_heat_J_kgK=_physical(r, "specific_heat_J_kgK"),
        youngs_modulus_Pa=_physical(r, "youngs_modulus_GPa") * 1e9,
        poisson_ratio=nu,
        expansion_1_K=_physical(r, "expansion_1_K"),
    )


def _read_mesh(msh: _Reader, base_dir: Path | None) -> MeshSettings:
    """``[mesh]``: element size [mm], element limit and an imported mesh file (relative to ``base_dir``)."""
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
    return MeshSettings(h_mm, mesh_path, max_el)


def _read_bodies(top: _Reader, materials: dict[str, Material], mesh_path: Path | None) -> tuple[Body, ...]:
    """``[[bodies]]``: at least one, unique names, a mounting tree of known bodies."""
    source = top.src
    bodies = [_read_body(source, where, t, materials, mesh_path) for where, t in top.tables("bodies")]
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
    return tuple(bodies)


def _read_body(source: str, where: str, t: Any, materials: dict[str, Material], mesh_path: Path | None) -> Body:
    """One ``[[bodies]]`` table: a box, or a group of the imported mesh."""
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
    return Body(bname, mat, box, group, r.get("mounted_on", None, str))


def _read_axes(top: _Reader, bodies: tuple[Body, ...]) -> tuple[Axis, ...]:
    """``[[axes]]``: at most :data:`MAX_AXES`, unique names, each moving its own body off the ground."""
    source = top.src
    axes = [_read_axis(source, where, t, bodies) for where, t in top.tables("axes", required=False)]
    if len(axes) > MAX_AXES:
        raise top.err("axes", f"has {len(axes)} axes, more than the limit of {MAX_AXES} (the geometry is checked at "
                              f"3^n poses: 3^{len(axes)} = {3 ** len(axes):,})")
    _unique(source, "axes", [a.name for a in axes])
    _unique(source, "axes[].moves", [a.moves for a in axes])
    for i, a in enumerate(axes):
        if bodies_by(bodies)[a.moves].mounted_on is None:
            raise MachineFileError(f"{source}: field 'axes[{i}].moves' names {a.moves!r}, a body on the ground, "
                                   "which cannot move")
    return tuple(axes)


def _read_axis(source: str, where: str, t: Any, bodies: tuple[Body, ...]) -> Axis:
    """One ``[[axes]]`` table: direction, moved body, travel [mm], feed [mm/min] and rail segments."""
    r = _Reader(source, where, t, "axis")
    aname = _name_of(r)
    if aname == SPINDLE:
        raise r.err("name", f"must not be {SPINDLE!r}, which names the spindle drive")
    d = r.get("direction", kind=str)
    if d not in COORDINATES:
        raise r.err("direction", f"must be one of {COORDINATES}, got {d!r}")
    moves = r.get("moves", kind=str)
    if moves not in {b.name for b in bodies}:
        raise r.err("moves", f"names an unknown body {moves!r}")
    tr = r.get("travel_mm", kind=list)
    if len(tr) == 2 and all(_is_number(x) for x in tr) and not all(_plausible_mm(x) for x in tr):
        raise r.err("travel_mm", f"must be finite and within ±{MAX_COORDINATE_MM:g} mm, got {tr!r}")
    if len(tr) != 2 or not all(_is_number(x) for x in tr) or tr[1] <= tr[0]:
        raise r.err("travel_mm", f"must be [min, max] with max > min, got {tr!r}")
    if not tr[0] <= 0 <= tr[1]:
        raise r.err("travel_mm", f"must contain 0 mm, the reference pose the geometry is given at, got {tr!r}")
    feed = r.number("max_feed_mm_min", positive=True)
    bounds = _segment_bounds(r, tr)
    return Axis(aname, COORDINATES.index(d), moves, (float(tr[0]), float(tr[1])), feed, tuple(float(b) for b in bounds))


def _segment_bounds(r: _Reader, tr: list) -> list:
    """An axis' rail segment bounds [mm] from ``segments`` (equal parts) or ``segment_bounds_mm``."""
    nseg = r.get("segments", None, int)
    bounds = r.get("segment_bounds_mm", None, list)
    if (nseg is None) == (bounds is None):
        raise r.err("segments", "or 'segment_bounds_mm' must be given (exactly one of them)")
    if nseg is not None:
        if not 1 <= nseg <= MAX_SEGMENTS:
            raise r.err("segments", f"must be from 1 to {MAX_SEGMENTS}, got {nseg!r}")
        return list(np.linspace(tr[0], tr[1], nseg + 1))
    if (
        not all(_is_number(b) and _plausible_mm(b) for b in bounds)
        or not 2 <= len(bounds) <= MAX_SEGMENTS + 1
        or abs(bounds[0] - tr[0]) > 1e-9
        or abs(bounds[-1] - tr[1]) > 1e-9
        or any(b <= a for a, b in zip(bounds, bounds[1:]))
    ):
        raise r.err("segment_bounds_mm", f"must ascend from the travel min to max {tr!r} in at most "
                                         f"{MAX_SEGMENTS} segments, got {bounds!r}")
    return bounds


def _read_heat_sources(top: _Reader, bodies: tuple[Body, ...], axes: tuple[Axis, ...],
                       spindle_rpm: float) -> tuple[HeatSource, ...]:
    """``[[heat_sources]]``: unique names."""
    sources = [_read_heat_source(top.src, where, t, bodies, axes, spindle_rpm)
               for where, t in top.tables("heat_sources", required=False)]
    _unique(top.src, "heat_sources", [s.name for s in sources])
    return tuple(sources)


def _read_heat_source(source: str, where: str, t: Any, bodies: tuple[Body, ...], axes: tuple[Axis, ...],
                      spindle_rpm: float) -> HeatSource:
    """One ``[[heat_sources]]`` table: a fixed patch on a body, or a moving one on the rail of an axis."""
    r = _Reader(source, where, t, "heat_source")
    body_names, axis_names = {b.name for b in bodies}, {a.name for a in axes}
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
    table = _power_table(r)
    return HeatSource(
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


def _power_table(r: _Reader) -> tuple[tuple[float, float], ...] | None:
    """A heat source's ``power_table``: (load factor, power fraction) pairs from factor 0 to 1, or None."""
    table = r.get("power_table", None, list)
    if table is None:
        return None
    ok = all(isinstance(p, list) and len(p) == 2 and all(_is_number(x) and math.isfinite(x) for x in p)
             for p in table)
    xs = [p[0] for p in table] if ok else []
    if (not ok or len(table) < 2 or xs[0] != 0 or xs[-1] != 1 or any(b <= a for a, b in zip(xs, xs[1:]))
            or any(p[1] < 0 for p in table)):
        raise r.err("power_table", "must be [[0, p0], ..., [1, p1]] with ascending factors and fractions >= 0, "
                                   f"got {table!r}")
    return tuple((float(a), float(b)) for a, b in table)


def _power(r: _Reader) -> float:
    """A heat source's ``power_W`` at load factor 1 [W]."""
    p = r.number("power_W", nonneg=True)
    if p > MAX_HEAT_POWER_W:
        raise r.err("power_W", f"must be at most {MAX_HEAT_POWER_W:g} W (a plausible heat source), got {p!r}")
    return p


def _read_zones(top: _Reader, bodies: tuple[Body, ...], mesh_path: Path | None) -> tuple[Zone, ...]:
    """``[[zones]]``: unique names, at most one rest zone."""
    zones = [_read_zone(top.src, where, t, bodies, mesh_path) for where, t in top.tables("zones", required=False)]
    _unique(top.src, "zones", [z.name for z in zones])
    if sum(z.rest for z in zones) > 1:
        raise top.err("zones", "may have only one zone with rest = true")
    return tuple(zones)


def _read_zone(source: str, where: str, t: Any, bodies: tuple[Body, ...], mesh_path: Path | None) -> Zone:
    """One ``[[zones]]`` table: coefficient [W/(m^2 K)], air and its surfaces (none for the rest zone)."""
    r = _Reader(source, where, t, "zone")
    zname = _name_of(r)
    h = _physical(r, "h_W_m2K")
    air = r.get("air", "ambient", str)
    if air not in AIR_KINDS:
        raise r.err("air", f"must be one of {AIR_KINDS}, got {air!r}")
    rest = r.get("rest", False, bool)
    if rest and "surfaces" in t:
        raise r.err("surfaces", "cannot be combined with rest = true (a rest zone takes every unclaimed surface)")
    surfs = tuple(_read_surface(source, swhere, st, bodies, mesh_path)
                  for swhere, st in r.tables("surfaces", required=not rest))
    return Zone(zname, h, air, surfs, rest)


def _read_surface(source: str, where: str, t: Any, bodies: tuple[Body, ...], mesh_path: Path | None) -> Surface:
    """One ``[[zones.surfaces]]`` table: faces of a box body (optionally clipped to a region) or a mesh group."""
    sr = _Reader(source, where, t, "surface")
    group = sr.get("group", None, str)
    body = sr.get("body", None, str)
    faces = tuple(sr.get("faces", list(FACES) if body else [], list))
    if body is not None and not faces:
        raise sr.err("faces", "must list at least one face (omit it for all six)")
    if group is None and body is None:
        raise sr.err("body", "or 'group' is required")
    if body is not None and body not in {b.name for b in bodies}:
        raise sr.err("body", f"names an unknown body {body!r}")
    if group is not None and mesh_path is None:
        raise sr.err("group", "needs an imported [mesh] file")
    for f in faces:
        if f not in FACES:
            raise sr.err("faces", f"must list faces of {FACES}, got {f!r}")
    return Surface(body, faces, sr.box("region_mm", None, flat_ok=True), group)


def _read_point(source: str, where: str, t: Any, bodies: tuple[Body, ...], named: bool = True) -> Point:
    """A ``[[sensors]]`` table (``named``), or ``[tcp]`` / ``[table_reference]``, named after their field."""
    r = _Reader(source, where, t, "point" if named else "anchor")
    pname = _name_of(r) if named else where
    body = r.get("body", None, str)
    if body is not None and body not in {b.name for b in bodies}:
        raise r.err("body", f"names an unknown body {body!r}")
    pos = r.vec3("position_mm")
    return Point(pname, body or "", pos)


def _read_table_reference(r: _Reader, bodies: tuple[Body, ...], mesh: MeshSettings) -> tuple[Point, bool]:
    """``[table_reference]``: the point and ``under_tool`` (the drift at the table point under the tool)."""
    under_tool = r.get("under_tool", False, bool)
    if under_tool and mesh.file is not None:
        raise r.err("under_tool", "needs box bodies: an imported [mesh] file is drawn at one pose, so the table "
                                  "point under the tool at other poses is not known; remove under_tool")
    t = {k: v for k, v in r.t.items() if k != "under_tool"}
    return _read_point(r.src, r.where, t, bodies, named=False), under_tool


def _read_supports(top: _Reader, bodies: tuple[Body, ...]) -> tuple[Support, ...]:
    """``[[supports]]``: unique names (statical determinacy is a geometry check)."""
    supports = [_read_support(top.src, where, t, bodies) for where, t in top.tables("supports")]
    _unique(top.src, "supports", [s.name for s in supports])
    return tuple(supports)


def _read_support(source: str, where: str, t: Any, bodies: tuple[Body, ...]) -> Support:
    """One ``[[supports]]`` table: the directions it fixes at a point of a ground body."""
    r = _Reader(source, where, t, "support")
    dirs = r.get("directions", kind=list)
    if not dirs or any(d not in COORDINATES for d in dirs) or len(set(dirs)) != len(dirs):
        raise r.err("directions", f"must list distinct directions of {COORDINATES}, got {dirs!r}")
    body = r.get("body", None, str)
    if body is not None and body not in {b.name for b in bodies}:
        raise r.err("body", f"names an unknown body {body!r}")
    return Support(_name_of(r), body or "", r.vec3("position_mm"), tuple(COORDINATES.index(d) for d in dirs))


def _read_drives(top: _Reader, machine: Machine) -> tuple[Drive, ...]:
    """``[[drives]]``, read against the checked machine: at most one per axis."""
    drives = tuple(_read_drive(machine, where, t) for where, t in top.tables("drives", required=False))
    _unique(machine.source, "drives[].axis", [d.axis for d in drives])
    return drives


#: default heat-transfer coefficient of a turning ball screw to the air around it [W/(m^2 K)] (forced convection
#: at a few hundred rpm; Xu et al. 2007 report 20-50), when neither it nor the screw's mean speed is given
SCREW_H_W_M2K = 20.0
#: default conductance from each bearing's stretch of screw to its housing [W/K]: 0, the bearings' ends adiabatic
BEARING_CONDUCTANCE_W_K = 0.0
#: the largest mean screw speed taken [rpm] (the rotating-cylinder correlation holds to Re 4.3e5: 40 mm, 38,000 rpm)
MAX_SCREW_RPM = 20000.0


def _read_drive(machine: Machine, where: str, t: dict) -> Drive:
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
        screw_h_W_m2K=_screw_h(r), screw_zone=zone, screw_mean_rpm=r.number("screw_mean_rpm", None, nonneg=True),
        bearing_conductance_W_K=_physical(r, "bearing_conductance_W_K", BEARING_CONDUCTANCE_W_K),
    )
    scale_keys = [k for k in KEYS["drive"] if k.startswith("scale_") and k in t]
    if feedback == "rotary_encoder":
        if scale_keys:
            raise r.err(scale_keys[0], "is only for feedback = 'linear_scale' (this drive reads a rotary encoder)")
        return drive
    return dataclasses.replace(drive, **_read_scale(r, machine, axis, carrier, nut))


def _screw_h(r: _Reader) -> float:
    """``screw_h_W_m2K`` when given, else from ``screw_mean_rpm`` when given, else :data:`SCREW_H_W_M2K`."""
    h = _physical(r, "screw_h_W_m2K", None)
    rpm = r.number("screw_mean_rpm", None, nonneg=True)
    if rpm is not None and rpm > MAX_SCREW_RPM:
        raise r.err("screw_mean_rpm", f"= {rpm!r} rpm is beyond {MAX_SCREW_RPM:g} rpm, where the convection correlation "
                                      "is not taken")
    if h is not None:
        return h
    if rpm is None:
        return SCREW_H_W_M2K
    return screw_h_W_m2K(r.number("screw_diameter_mm", positive=True), rpm)


def _read_scale(r: _Reader, machine: Machine, axis: Axis, carrier: str, nut: HeatSource) -> dict:
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
        if box is not None and not inside_box(box, p):
            raise r.err(key, f"= {list(p)} mm is outside the scale's body {body!r}")
    fixed = r.number("scale_fixed_at_mm", a[d])
    head = r.number("scale_head_at_mm", nut.position_mm[d])
    if not a[d] - GEOMETRY_TOLERANCE_MM <= fixed <= b[d] + GEOMETRY_TOLERANCE_MM:
        raise r.err("scale_fixed_at_mm", f"= {fixed!r} mm is off the scale [{a[d]:g}, {b[d]:g}] mm")
    if head + axis.travel_mm[0] < a[d] - GEOMETRY_TOLERANCE_MM or head + axis.travel_mm[1] > b[d] + GEOMETRY_TOLERANCE_MM:
        raise r.err("scale_head_at_mm", f"= {head!r} mm: the reading head travels over [{head + axis.travel_mm[0]:g}, "
                                        f"{head + axis.travel_mm[1]:g}] mm, beyond the scale [{a[d]:g}, {b[d]:g}] mm")
    return dict(scale_body=body, scale_from_mm=a, scale_to_mm=b, scale_fixed_at_mm=fixed, scale_head_at_mm=head,
                scale_expansion_1_K=_physical(r, "scale_expansion_1_K"))


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
