"""Typed machine definitions: the frozen dataclasses a machine file becomes.

A machine file is TOML, documented field by field in ``models/README.md``; :mod:`hybridcomp.models.loader` reads
and validates it (:func:`~hybridcomp.models.loader.load_machine`), :mod:`hybridcomp.models.geometry` checks its
geometry and the element budget of its mesh.  Geometry is given in millimetres at the reference pose (every axis
at 0 mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.models.layout import InputLayout, input_layout

Vec3 = tuple[float, float, float]
FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
AIR_KINDS = ("ambient", "workspace")
#: position feedback of a feed drive: semi-closed loop (motor encoder) or closed loop (linear scale)
FEEDBACKS = ("rotary_encoder", "linear_scale")
#: ball-screw mountings: one axially fixed bearing, or both fixed with the screw pre-stretched
MOUNTINGS = ("fixed-floating", "pre-stretched")
SPINDLE = "spindle"


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
    ``screw_h_W_m2K`` is the screw's convection coefficient: given, or from ``screw_mean_rpm``
    (:mod:`hybridcomp.models.convection`); ``bearing_conductance_W_K`` the conductance from each bearing's stretch
    of screw to a sink at the screw zone's air.
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
    screw_mean_rpm: float | None = None
    bearing_conductance_W_K: float = 0.0


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

    ``max_elements`` is the file's limit of the element count (None:
    :func:`hybridcomp.models.geometry.max_elements` decides).
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
    #: ``[table_reference] under_tool``: the drift is taken at the table point under the tool, not at the table
    #: reference (:func:`hybridcomp.models.geometry.table_point`)
    table_under_tool: bool = False

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

