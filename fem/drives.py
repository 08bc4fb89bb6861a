"""Feed drives: the ball screw's temperature and the positioning error a drive adds to the FE structure.

A drive (``[[drives]]`` of the machine file, :class:`hybridcomp.models.machine.Drive`) is a ball screw between
two bearings on the body carrying the axis' rail (the **carrier**: the body of the fixed bearing's heat source), a
nut moving with the axis, and a position feedback.  The FE structure bonds the moving body to its carrier at each
pose, so it already moves the moving body with the carrier's own expansion between the fixed bearing and the nut.
What a drive adds is the difference between the feedback's length and that carrier length (:class:`DriveError`,
the one definition every user calls, :func:`drive_error`):

* **rotary encoder** (semi-closed loop): the control turns the motor by the commanded angle, so the nut lands
  where the screw's thermal elongation between the fixed bearing and the nut puts it; the structure put it where
  the carrier's expansion over the same stretch did.  At axis position ``p`` [mm]::

      e(p) = α_screw ∫_{s_fixed}^{s_nut(p)} ΔT_screw ds − α_carrier ∫_{s_fixed}^{s_nut(p)} ΔT_carrier ds

  signed (a nut below the fixed bearing moves down), ``ΔT_carrier`` the FE field sampled along the screw's line
  on the carrier (:class:`CarrierLine`).  A **pre-stretched** screw is held at both ends by bearings on the
  carrier: its length between them is the carrier's, and the difference of the two elongations over the whole
  screw is taken up as a uniform axial strain (one force along a uniform rod), shared by the stretch to the nut in
  proportion to its length.  With ``E(s)`` the bracket above up to ``s``::

      e(p) = E(s_nut) − (s_nut − s_fixed) / (s_other − s_fixed) · E(s_other)

  the same "mean taken up as strain" rule as before, now applied to what the screw adds: on a uniform field of
  any α the error is zero, as it must be for a screw that follows its carrier's bearings.  The pre-stretch left is
  the pre-stretch less ``E(s_other)`` (counted along the screw, from the fixed bearing): the carrier's expansion
  stretches the screw, the screw's own relieves it.
* **linear scale** (closed loop): the control positions the reading head on the scale, a scale fixed at one point
  of its carrier and free to expand along it with its own α at the carrier's temperature (``scale_body``,
  ``ΔT_carrier`` along the scale's line), against the carrier's own expansion over the same stretch::

      e(p) = (α_scale − α_carrier) ∫_{s_fixed}^{s_head(p)} ΔT_carrier ds

``α_carrier`` is the carrier body's material expansion coefficient.  On a uniform rise the slope of the error along
an axis is the feedback's α alone: the structure's slope (the carrier's α) plus the drive's (the difference).

Why subtract the carrier and not release the moving body axially in the FE structure: the structure's drift
comes from one bonded elastic problem per support pose, reduced once and interpolated; releasing the moving body
along the axis would need a contact (or a spring of the screw's stiffness) in every one of those problems and an
axial position fixed by the screw's temperature, a second field coupled into the elastic one.  The bonded
structure holds everything but the axial stretch between the fixed bearing and the nut, and along that stretch
the carrier is a slender line (the screw or scale runs close along it), so its expansion there is
``α_carrier ∫ ΔT_carrier ds`` to first order: subtracting it exchanges the carrier's length for the feedback's and
leaves every other deformation (tilts, bending, the moving body's own expansion) to the FE structure.  What is
neglected: the carrier's shear and bending strain along the line (second order against the thermal strain for
the slender carriers here) and, for the scale, the carrier's strain between the scale's line and the rail.

The screw's temperature comes from a 1D transient model (:class:`ScrewModel`): a rod of the screw's diameter
with conduction along it, convection to the air of a zone all along its surface, and heat entering over the
bearings' lengths and, from the nut, over the stretch of screw each rail segment covers (the nut's heat
input per segment ``<nut>[k]`` of the loads).  The heat into the screw is given per source in the machine file
(``*_screw_W`` at load factor 1) and follows that source's loads column in proportion; it is heat in addition
to what the source puts into the structure.  The screw's convection coefficient is the drive's
``screw_h_W_m2K``: given, or from its mean speed ``screw_mean_rpm`` (a rotating cylinder and natural convection,
:mod:`hybridcomp.models.convection`).  The bearings conduct heat to their housings on the carrier:
``bearing_conductance_W_K`` per bearing (default 0), spread over the bearing's stretch of screw, to a sink at the
screw zone's air temperature, not the carrier's (the carrier's temperature is not coupled back: the screw model
stays a model of its own, run before or beside the FE model).  The screw's ends are otherwise adiabatic: what the
screw takes leaves it through its surface and its bearings.

Units: axial coordinates in mm (global, along the axis, at the reference pose), temperatures as rises over
the reference [K], errors in µm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hybridcomp.models.layout import InputLayout, Loads
from hybridcomp.models.machine import Drive, Machine, MachineFileError
from hybridcomp.models.simulation import initial_state

MM = 1e-3
#: the longest element of a screw's 1D mesh [mm]
SCREW_ELEMENT_MM = 10.0


def integral_weights(s_mm: np.ndarray, a_mm: float, b_mm: float) -> np.ndarray:
    """Weights ``w`` with ``w @ f = ∫_a^b f_h(s) ds`` [mm · unit of f].

    ``f_h`` is the piecewise-linear function through the nodal values ``f`` at ascending nodes ``s_mm``; the
    integral is signed (negative for ``b < a``) and exact for ``f_h``.

    Raises
    ------
    ValueError
        a bound off the nodes' span (names it)
    """
    return _primitive(s_mm, b_mm) - _primitive(s_mm, a_mm)


def _primitive(s: np.ndarray, x: float) -> np.ndarray:
    """Weights of ``∫_{s_0}^x f_h``."""
    if not s[0] - 1e-9 <= x <= s[-1] + 1e-9:
        raise ValueError(f"{x:g} mm is off the line [{s[0]:g}, {s[-1]:g}] mm")
    x = min(max(x, s[0]), s[-1])
    w = np.zeros(s.size)
    i = int(np.clip(np.searchsorted(s, x, side="right") - 1, 0, s.size - 2))
    h = np.diff(s[: i + 1])
    w[:i] += 0.5 * h
    w[1: i + 1] += 0.5 * h
    hi = s[i + 1] - s[i]
    t = (x - s[i]) / hi
    w[i] += hi * (t - 0.5 * t * t)
    w[i + 1] += hi * 0.5 * t * t
    return w


def _nodes(breaks_mm: list[float], lo: float, hi: float, h_mm: float) -> np.ndarray:
    """Ascending nodes from ``lo`` to ``hi`` through every break inside, no element longer than ``h_mm``."""
    pts = np.unique(np.clip(np.asarray(breaks_mm + [lo, hi], float), lo, hi))
    out = [pts[:1]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(np.ceil((b - a) / h_mm - 1e-9)))
        out.append(np.linspace(a, b, n + 1)[1:])
    s = np.concatenate(out)
    return s[np.concatenate([[True], np.diff(s) > 1e-9])]


def _interval_column(s: np.ndarray, a: float, b: float) -> np.ndarray:
    """Nodal loads of 1 W spread uniformly over ``[a, b]`` (clipped to the line): P1 shares, summing to 1."""
    a, b = max(min(a, b), s[0]), min(max(a, b), s[-1])
    if b - a < 1e-9:  # a point: the hat functions at it
        return _point_column(s, a)
    return integral_weights(s, a, b) / (b - a)


def _point_column(s: np.ndarray, x: float) -> np.ndarray:
    i = int(np.clip(np.searchsorted(s, x, side="right") - 1, 0, s.size - 2))
    t = (x - s[i]) / (s[i + 1] - s[i])
    w = np.zeros(s.size)
    w[i], w[i + 1] = 1 - t, t
    return w


@dataclass(frozen=True)
class ScrewModel:
    """The 1D thermal model of one ball screw (SI operators on the nodes ``s_mm``).

    ``M x' + A x = Bu u`` with ``x`` the temperature rise [K] and ``u`` the machine's inputs in layout order
    (heat inputs [W], zone air rises [K]); ``A = K + H + G``: conduction along the screw, convection from its
    surface at ``screw_h_W_m2K`` and the bearings' conductance ``bearing_conductance_W_K`` each, spread over its
    bearing's stretch (lumped), to a sink at the screw zone's air.
    """

    drive: Drive
    s_mm: np.ndarray
    M: sp.csr_matrix
    Bu: np.ndarray
    K: sp.csr_matrix
    H: sp.csr_matrix
    G: sp.csr_matrix
    alpha_1_K: float
    s_fixed_mm: float
    s_other_mm: float
    nut_at_mm: float
    layout: InputLayout

    @property
    def A(self) -> sp.csr_matrix:
        """K + H + G [W/K]."""
        return (self.K + self.H + self.G).tocsr()

    @property
    def length_mm(self) -> float:
        return abs(self.s_other_mm - self.s_fixed_mm)

    def nut_mm(self, position_mm: float) -> float:
        """Axial coordinate of the nut at axis position ``position_mm``."""
        return self.nut_at_mm + position_mm

    def elongation_rows(self, positions_mm) -> np.ndarray:
        """Rows ``R`` [µm/K] with ``R @ x`` the screw's share of the positioning error at the axis positions.

        ``α_screw ∫_{s_fixed}^{s_nut(p)} ΔT_screw ds`` for a screw temperature ``x``, less for a pre-stretched screw
        the share of the whole screw's elongation (module docstring); the carrier's share and the two together are
        :class:`DriveError`'s.
        """
        nut = [self.nut_mm(p) for p in np.atleast_1d(positions_mm)]
        held = self.s_other_mm if self.drive.mounting == "pre-stretched" else None
        return self.alpha_1_K * 1e3 * axial_weights(self.s_mm, self.s_fixed_mm, nut, held)

    def steady(self, u: np.ndarray) -> np.ndarray:
        """Steady temperature rise [K] under constant inputs."""
        return spla.spsolve(self.A.tocsc(), self.Bu @ u)

    def temperature_rise(self, time_s: np.ndarray, U: np.ndarray, initial: str | np.ndarray = "steady") -> np.ndarray:
        """Temperature rise [K] at the times (nt × n) under the inputs ``U`` (nt × inputs, layout order).

        The inputs are linear between the samples, as for the FE model: the trapezoidal rule (Crank–Nicolson),
        started from ``initial`` (``"steady"`` of row 0, ``"reference"`` or a state).
        """
        t = np.asarray(time_s, float)
        U = np.asarray(U, float)
        x = initial_state(initial, self.s_mm.size, lambda: self.steady(U[0]))
        out = np.empty((t.size, x.size))
        out[0] = x
        lus: dict[float, tuple] = {}
        for i in range(1, t.size):
            dt = float(t[i] - t[i - 1])
            key = round(dt, 9)
            if key not in lus:
                A = self.A
                lus[key] = (spla.splu((self.M / dt + 0.5 * A).tocsc()), (self.M / dt - 0.5 * A).tocsr())
            lu, rhs = lus[key]
            x = lu.solve(rhs @ x + self.Bu @ (0.5 * (U[i - 1] + U[i])))
            out[i] = x
        return out

    def temperature_rise_of_loads(self, loads: Loads, initial: str | np.ndarray = "steady") -> np.ndarray:
        """:meth:`temperature_rise` on a loads time series (the FE model's columns: powers [W], air [°C])."""
        return self.temperature_rise(loads.time_s, self.layout.inputs(loads.names, loads.values, "loads"), initial)


def _line_matrix(diag_e: np.ndarray, off_e: np.ndarray) -> sp.csr_matrix:
    """A P1 matrix on a line of elements, from each element's diagonal and off-diagonal entry."""
    main = np.zeros(diag_e.size + 1)
    main[:-1] += diag_e
    main[1:] += diag_e
    return sp.diags([off_e, main, off_e], [-1, 0, 1], format="csr")


def build_screw(machine: Machine, drive: Drive, element_mm: float = SCREW_ELEMENT_MM) -> ScrewModel:
    """The 1D thermal model of a drive's screw (see the module docstring)."""
    axis = machine.axis(drive.axis)
    d = axis.direction
    fixed, other, nut = (machine.heat_source(n) for n in (drive.fixed_bearing, drive.floating_bearing, drive.nut))
    s_fixed, s_other = fixed.position_mm[d], other.position_mm[d]
    lo, hi = min(s_fixed, s_other), max(s_fixed, s_other)
    nut_at = nut.position_mm[d]
    half = {n: 0.5 * machine.heat_source(n).size_mm[d] for n in (fixed.name, other.name)}
    breaks = [s_fixed - half[fixed.name], s_fixed + half[fixed.name], s_other - half[other.name],
              s_other + half[other.name]] + [nut_at + b for b in axis.segment_bounds_mm]
    s = _nodes(breaks, lo, hi, element_mm)
    h = np.diff(s) * MM
    mat = machine.materials[drive.screw_material]
    area = np.pi / 4 * (drive.screw_diameter_mm * MM) ** 2
    perimeter = np.pi * drive.screw_diameter_mm * MM
    rc = mat.density_kg_m3 * mat.specific_heat_J_kgK * area
    kA = mat.conductivity_W_mK * area
    hP = drive.screw_h_W_m2K * perimeter
    M = _line_matrix(rc * h / 3, rc * h / 6)
    K = _line_matrix(kA / h, -kA / h)
    H = _line_matrix(hP * h / 3, hP * h / 6)
    layout = machine.layout()
    Bu = np.zeros((s.size, layout.n_inputs))
    for src, watts in ((fixed, drive.fixed_bearing_screw_W), (other, drive.floating_bearing_screw_W)):
        if watts > 0:
            c = src.position_mm[d]
            Bu[:, layout.source_columns(src.name)[0]] += watts / src.power_W * _interval_column(s, c - half[src.name],
                                                                                                 c + half[src.name])
    if drive.nut_screw_W > 0:
        cols = layout.source_columns(nut.name)
        for k, (a, b) in enumerate(zip(axis.segment_bounds_mm[:-1], axis.segment_bounds_mm[1:])):
            Bu[:, cols[k]] += drive.nut_screw_W / nut.power_W * _interval_column(s, nut_at + a, nut_at + b)
    g = np.zeros(s.size)
    for src in (fixed, other):  # the bearing's conductance over its stretch, to the zone's air
        c = src.position_mm[d]
        g += drive.bearing_conductance_W_K * _interval_column(s, c - half[src.name], c + half[src.name])
    G = sp.diags(g, format="csr")
    zone = layout.zones.index(drive.screw_zone)
    Bu[:, len(layout.heat_inputs) + zone] = H @ np.ones(s.size) + g
    return ScrewModel(drive=drive, s_mm=s, M=M, Bu=Bu, K=K, H=H, G=G, alpha_1_K=mat.expansion_1_K,
                      s_fixed_mm=s_fixed, s_other_mm=s_other, nut_at_mm=nut_at, layout=layout)


def build_screws(machine: Machine) -> dict[str, ScrewModel]:
    """The screw model of every drive of the machine, by axis."""
    return {dr.axis: build_screw(machine, dr) for dr in machine.drives}


def axial_weights(s_mm: np.ndarray, s_fixed_mm: float, ends_mm, held_at_mm: float | None = None) -> np.ndarray:
    """Weights (ends × nodes) [mm] of ``∫_{s_fixed}^{end} f ds`` for a line held (or not) at its far end.

    With ``held_at_mm`` (a pre-stretched screw's other bearing) the share ``(end − s_fixed) / (held − s_fixed)`` of
    the integral over the whole line is taken off: what the bearings take up as a uniform strain.
    """
    ends = np.atleast_1d(np.asarray(ends_mm, float))
    W = np.array([integral_weights(s_mm, s_fixed_mm, e) for e in ends])
    if held_at_mm is not None:
        W = W - np.outer((ends - s_fixed_mm) / (held_at_mm - s_fixed_mm), integral_weights(s_mm, s_fixed_mm,
                                                                                           held_at_mm))
    return W


@dataclass(frozen=True)
class CarrierLine:
    """A drive's line on its carrier in an FE model: temperature rows at nodes along it.

    ``P @ x`` is the carrier's temperature rise [K] at the nodes ``s_mm`` (axial coordinates at the reference pose)
    for an FE state ``x``: along the screw's line (a rotary encoder's drive, from bearing to bearing) or along the
    scale (a linear scale's).  ``alpha_1_K`` is the carrier body's expansion coefficient.
    """

    drive: Drive
    body: str
    s_mm: np.ndarray
    P: sp.csr_matrix
    alpha_1_K: float

    def integral_rows(self, s_fixed_mm: float, ends_mm, held_at_mm: float | None = None) -> np.ndarray:
        """Rows (ends × FE nodes) [mm]: ``∫_{s_fixed}^{end} ΔT_carrier ds`` per K of the state.

        ``held_at_mm`` as in :func:`axial_weights`.
        """
        return (sp.csr_matrix(axial_weights(self.s_mm, s_fixed_mm, ends_mm, held_at_mm)) @ self.P).toarray()


def carrier_line(model, drive: Drive, spacing_mm: float | None = None) -> CarrierLine:
    """A drive's line on its carrier in an FE model (:class:`hybridcomp.fem.model.ThermoElasticModel`).

    A rotary encoder's drive: the screw's line from bearing to bearing at the fixed bearing's cross position, on the
    fixed bearing's body; a linear scale's: the scale's line on ``scale_body``.  Sampled at ``spacing_mm`` (default
    a quarter of the element size, at most 10 mm), at the model's pose.

    Raises
    ------
    MachineFileError
        the line leaves its body's mesh (names the drive and the point)
    """
    from hybridcomp.fem import assembly

    machine, mm = model.machine, model.mesh
    d = machine.axis(drive.axis).direction
    spacing = spacing_mm or min(SCREW_ELEMENT_MM, 0.25 * machine.mesh.element_size_mm)
    if drive.feedback == "linear_scale":
        body, start, a, b = drive.scale_body, drive.scale_from_mm, drive.scale_from_mm[d], drive.scale_to_mm[d]
        breaks, what = [drive.scale_fixed_at_mm], "linear scale"
    else:
        fixed, other = machine.heat_source(drive.fixed_bearing), machine.heat_source(drive.floating_bearing)
        body, start, a, b = fixed.body, fixed.position_mm, fixed.position_mm[d], other.position_mm[d]
        breaks, what = [], "screw's line"
    s = _nodes(breaks, min(a, b), max(a, b), spacing)
    pts = np.repeat(np.asarray(start, float)[:, None], s.size, axis=1)
    pts[d] = s
    pts = (pts + machine.body_offset_mm(body, mm.pose_mm)[:, None]) * MM
    cells = mm.find_elements(pts, body=body)
    if (cells < 0).any():
        bad = pts[:, cells < 0][:, 0] / MM
        raise MachineFileError(f"{machine.source}: the {what} of axis {drive.axis} leaves the mesh of body "
                               f"{body!r} at {bad.round(3).tolist()} mm")
    alpha = machine.materials[machine.body(body).material].expansion_1_K
    return CarrierLine(drive, body, s, assembly.probe_matrix(assembly.cell_basis(mm.mesh), pts, cells), alpha)


@dataclass(frozen=True)
class DriveError:
    """The positioning error a drive adds beyond the FE structure (module docstring): the one definition.

    ``e = screw_rows(p) @ x_screw + fe_rows(p) @ x`` [µm] at axis positions ``p`` for the screw's temperature
    ``x_screw`` (rotary encoder; ``screw`` is None for a linear scale) and the FE state ``x``.
    """

    drive: Drive
    screw: ScrewModel | None
    carrier: CarrierLine

    @property
    def s_fixed_mm(self) -> float:
        """The axial coordinate the error is counted from: the fixed bearing or the scale's fixed point."""
        return self.screw.s_fixed_mm if self.screw is not None else self.drive.scale_fixed_at_mm

    def moving_mm(self, positions_mm) -> np.ndarray:
        """Axial coordinates of the nut (or the scale's reading head) at the axis positions."""
        p = np.atleast_1d(np.asarray(positions_mm, float))
        return self.screw.nut_mm(p) if self.screw is not None else self.drive.scale_head_at_mm + p

    def screw_rows(self, positions_mm) -> np.ndarray | None:
        """Rows (positions × screw nodes) [µm/K] on the screw's temperature, None for a linear scale."""
        return None if self.screw is None else self.screw.elongation_rows(positions_mm)

    def fe_rows(self, positions_mm) -> np.ndarray:
        """Rows (positions × FE nodes) [µm/K] on the FE state.

        Minus the carrier's elongation (a screw's drive), ``(α_scale − α_carrier) ∫ ΔT_carrier`` (a linear scale).
        """
        c = self.carrier
        ends = self.moving_mm(positions_mm)
        if self.screw is None:
            return (self.drive.scale_expansion_1_K - c.alpha_1_K) * 1e3 * c.integral_rows(self.s_fixed_mm, ends)
        held = self.screw.s_other_mm if self.drive.mounting == "pre-stretched" else None
        return -c.alpha_1_K * 1e3 * c.integral_rows(self.s_fixed_mm, ends, held)

    def error_um(self, positions_mm, x, x_screw=None) -> np.ndarray:
        """The error [µm] at the positions for FE states ``x`` (n or nt × n) and screw temperatures (rotary)."""
        e = np.atleast_2d(x) @ self.fe_rows(positions_mm).T
        if self.screw is not None:
            if x_screw is None:
                raise ValueError(f"the error of axis {self.drive.axis}'s rotary encoder needs the screw's temperature")
            e = e + np.atleast_2d(x_screw) @ self.screw_rows(positions_mm).T
        return e if np.ndim(x) > 1 else e[0]

    def prestretch_left_um(self, x, x_screw) -> np.ndarray:
        """Pre-stretch left [µm] of a pre-stretched screw for FE states and screw temperatures (nt × ·).

        The pre-stretch less the screw's elongation over its whole length beyond the carrier's between the bearings;
        negative once the bearings take compression.
        """
        sc, c = self.screw, self.carrier
        screw = sc.alpha_1_K * 1e3 * np.atleast_2d(x_screw) @ integral_weights(sc.s_mm, sc.s_fixed_mm, sc.s_other_mm)
        carrier = c.alpha_1_K * 1e3 * np.atleast_2d(x) @ c.integral_rows(sc.s_fixed_mm, [sc.s_other_mm])[0]
        return (self.drive.prestretch_um or 0.0) - np.sign(sc.s_other_mm - sc.s_fixed_mm) * (screw - carrier)


def drive_error(model, drive: Drive) -> DriveError:
    """The added positioning error of a drive in an FE model: its screw model (rotary) and carrier line."""
    screw = None if drive.feedback == "linear_scale" else build_screw(model.machine, drive)
    return DriveError(drive, screw, carrier_line(model, drive))
