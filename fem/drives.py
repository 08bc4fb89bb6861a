"""Feed drives: the ball screw's temperature and the positioning error of the axis' position feedback.

A drive (``[[drives]]`` of the machine file, :class:`hybridcomp.models.machine.Drive`) is a ball screw between
two bearings on the body carrying the axis' rail, a nut moving with the axis, and a position feedback:

* **rotary encoder** (semi-closed loop): the control turns the motor by the commanded angle, so the nut lands
  where the screw's thermal elongation between the fixed bearing and the nut puts it.  The positioning error
  at axis position ``p`` [mm] is ``e(p) = α ∫_{s_fixed}^{s_nut(p)} ΔT(s) ds`` along the screw (signed: a nut
  below the fixed bearing moves down).  A pre-stretched screw is held at both ends: while its bearings hold,
  its length stays and ``e(p) = α ∫_{s_fixed}^{s_nut(p)} (ΔT(s) − mean ΔT) ds``; the pre-stretch it has left
  is reported.
* **linear scale** (closed loop): the control positions the reading head on the scale, so the error is the
  scale's own expansion between its fixed point and the head, at the temperature of the carrier it lies on:
  ``e(p) = α_scale ∫_{s_fixed}^{s_head(p)} ΔT_carrier(s) ds``, the carrier's temperature taken from the FE
  field along the scale's line.

The screw's temperature comes from a 1D transient model (:class:`ScrewModel`): a rod of the screw's diameter
with conduction along it, convection to the air of a zone all along its surface, and heat entering over the
bearings' lengths and, from the nut, over the stretch of screw each rail segment covers (the nut's heat
input per segment ``<nut>[k]`` of the loads).  The heat into the screw is given per source in the machine file
(``*_screw_W`` at load factor 1) and follows that source's loads column in proportion; it is heat in addition
to what the source puts into the structure.  The bearings' ends are taken as adiabatic: what the screw takes
leaves it through its surface.

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
    (heat inputs [W], zone air rises [K]); ``A = K + H``: conduction along the screw and convection from its
    surface at ``screw_h_W_m2K``.
    """

    drive: Drive
    s_mm: np.ndarray
    M: sp.csr_matrix
    Bu: np.ndarray
    K: sp.csr_matrix
    H: sp.csr_matrix
    alpha_1_K: float
    s_fixed_mm: float
    s_other_mm: float
    nut_at_mm: float
    layout: InputLayout

    @property
    def A(self) -> sp.csr_matrix:
        """K + H [W/K]."""
        return (self.K + self.H).tocsr()

    @property
    def length_mm(self) -> float:
        return abs(self.s_other_mm - self.s_fixed_mm)

    def nut_mm(self, position_mm: float) -> float:
        """Axial coordinate of the nut at axis position ``position_mm``."""
        return self.nut_at_mm + position_mm

    def error_rows(self, positions_mm) -> np.ndarray:
        """Rows ``R`` with ``R @ x`` the positioning error [µm] at the axis positions for a screw temperature ``x``."""
        R = np.array([integral_weights(self.s_mm, self.s_fixed_mm, self.nut_mm(p)) for p in np.atleast_1d(positions_mm)])
        if self.drive.mounting == "pre-stretched":  # held at both ends: the mean expansion is taken up as strain
            whole = integral_weights(self.s_mm, self.s_fixed_mm, self.s_other_mm)
            dist = np.array([self.nut_mm(p) - self.s_fixed_mm for p in np.atleast_1d(positions_mm)])
            R = R - np.outer(dist / (self.s_other_mm - self.s_fixed_mm), whole)
        return self.alpha_1_K * R * 1e3  # mm -> µm

    def prestretch_left_um(self, x: np.ndarray) -> np.ndarray:
        """Pre-stretch left [µm] at screw temperatures ``x`` (nt × n).

        The pre-stretch less the thermal elongation of the whole screw; negative once the bearings take compression.
        """
        whole = np.abs(integral_weights(self.s_mm, self.s_fixed_mm, self.s_other_mm))
        return (self.drive.prestretch_um or 0.0) - self.alpha_1_K * 1e3 * (np.atleast_2d(x) @ whole)

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
    zone = layout.zones.index(drive.screw_zone)
    Bu[:, len(layout.heat_inputs) + zone] = H @ np.ones(s.size)
    return ScrewModel(drive=drive, s_mm=s, M=M, Bu=Bu, K=K, H=H, alpha_1_K=mat.expansion_1_K,
                      s_fixed_mm=s_fixed, s_other_mm=s_other, nut_at_mm=nut_at, layout=layout)


def build_screws(machine: Machine) -> dict[str, ScrewModel]:
    """The screw model of every drive of the machine, by axis."""
    return {dr.axis: build_screw(machine, dr) for dr in machine.drives}


@dataclass(frozen=True)
class ScaleLine:
    """A linear scale's line in an FE model: temperature rows at nodes along it and its integral weights.

    ``P @ x`` is the carrier's temperature rise [K] at the nodes ``s_mm`` (axial coordinates at the reference pose)
    for an FE state ``x``.
    """

    drive: Drive
    s_mm: np.ndarray
    P: sp.csr_matrix

    def error_rows(self, positions_mm) -> np.ndarray:
        """Rows ``R`` (positions × FE nodes) with ``R @ x`` the positioning error [µm] at the axis positions."""
        dr = self.drive
        W = np.array([integral_weights(self.s_mm, dr.scale_fixed_at_mm, dr.scale_head_at_mm + p)
                      for p in np.atleast_1d(positions_mm)])
        return dr.scale_expansion_1_K * 1e3 * (sp.csr_matrix(W) @ self.P).toarray()


def scale_line(model, drive: Drive, spacing_mm: float | None = None) -> ScaleLine:
    """The scale of a linear-scale drive in an FE model (:class:`hybridcomp.fem.model.ThermoElasticModel`).

    Sampled at ``spacing_mm`` (default a quarter of the element size, at most 10 mm).
    """
    from hybridcomp.fem import assembly

    if drive.feedback != "linear_scale":
        raise ValueError(f"drive of axis {drive.axis} reads a {drive.feedback}, not a linear scale")
    machine, mm = model.machine, model.mesh
    d = machine.axis(drive.axis).direction
    spacing = spacing_mm or min(SCREW_ELEMENT_MM, 0.25 * machine.mesh.element_size_mm)
    a, b = drive.scale_from_mm[d], drive.scale_to_mm[d]
    s = _nodes([drive.scale_fixed_at_mm], a, b, spacing)
    pts = np.repeat(np.asarray(drive.scale_from_mm, float)[:, None], s.size, axis=1)
    pts[d] = s
    pts = (pts + machine.body_offset_mm(drive.scale_body, mm.pose_mm)[:, None]) * MM
    cells = mm.find_elements(pts, body=drive.scale_body)
    if (cells < 0).any():
        bad = pts[:, cells < 0][:, 0] / MM
        raise MachineFileError(f"{machine.source}: the linear scale of axis {drive.axis} leaves the mesh of body "
                               f"{drive.scale_body!r} at {bad.round(3).tolist()} mm")
    return ScaleLine(drive, s, assembly.probe_matrix(assembly.cell_basis(mm.mesh), pts, cells))
