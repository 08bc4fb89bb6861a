"""The volumetric error model of a machine's linear axes (ISO 230-1): error functions composed to the TCP.

Each linear axis' carriage moves on its carrier with six small errors that depend on the axis position ``q``: three
translations and three rotations, named as ISO 230-1 names them (for the X axis: ``EXX`` its positioning error,
``EYX`` and ``EZX`` its straightness in y and z, ``EAX``, ``EBX``, ``ECX`` its rotations about x, y and z: roll,
pitch and yaw).  The squareness errors are in the linear terms of the straightness functions (two axes' straightness
slopes against each other).  The error of the tool tip against the workpiece point
under it is their first-order composition through the kinematic chain of the machine file: a carriage's error
moves every point it carries by ``δ + θ × (P − O)``, ``O`` a reference point on the carriage (its body's box
centre), so the rotations act with the lever arm from the carriage to the tool tip, which changes with every
other axis' position (the Abbe offsets)::

    E(p) = Σ_tool-side axes [δ_a(q_a) + θ_a(q_a) × (P(p) − O_a(p))] − Σ_table-side axes [same]

with ``P(p)`` the tool tip at pose ``p`` (the workpiece point under it coincides nominally) and ``O_a(p)`` the
carriage's reference point moved with its axis and every axis below it in the chain
(:meth:`~hybridcomp.models.machine.Machine.body_offset_mm`).  ``E`` is the drift convention of the project: TCP
minus table.  Second-order terms (a rotation times a translation error, products of rotations) are left out: with
rotations of 50 µrad and lever arms of 1 m they are below 0.003 µm.

Every error function is a Legendre series in the axis position normalised over its travel (``degree``: 3 by
default, a cubic), so the model is linear in its coefficients: :func:`design_matrix` gives the TCP errors at a set of
poses as a matrix times the coefficients, :func:`identify` fits them to measured TCP errors (least squares; the
combinations that no TCP measurement can see, such as one constant offset shared by all axes, are left at zero and
reported as the rank deficit) and :func:`tcp_error_um` evaluates a model anywhere.  Units: translations in µm,
rotations in µrad, positions in mm.

This is the geometric half of a thermal volumetric model: its coefficients at each thermal state are what a
volumetric calibration identifies; how they follow the temperatures is the other half.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre

#: the six error components of a carriage: translations along x, y, z [µm] and rotations about x, y, z [µrad]
COMPONENTS = ("X", "Y", "Z", "A", "B", "C")
#: the default degree of every error function's Legendre series
DEFAULT_DEGREE = 3


@dataclass(frozen=True)
class Chain:
    """The kinematic chain of a machine's linear axes, as the volumetric error model needs it.

    Attributes
    ----------
    axes : axis names, machine order
    directions : each axis' direction (0, 1, 2: x, y, z)
    sides : +1 for an axis that moves the tool side, −1 for one that moves the table side
    travel_mm : each axis' travel (min, max) [mm]
    tip_mm : the tool tip at the reference pose (every axis at 0) [mm]
    tip_moves : (axes,) 1 where the axis moves the tool tip (its body or one below it in the chain)
    ref_mm : (axes × 3) each carriage's reference point at the reference pose [mm]
    ref_moves : (axes × axes) row a: 1 where axis b moves carriage a's reference point
    """

    axes: tuple[str, ...]
    directions: tuple[int, ...]
    sides: tuple[float, ...]
    travel_mm: tuple[tuple[float, float], ...]
    tip_mm: np.ndarray
    tip_moves: np.ndarray
    ref_mm: np.ndarray
    ref_moves: np.ndarray

    def names(self, degree: int) -> list[str]:
        """The coefficients' names in :func:`design_matrix`'s column order: ``EBX[2]`` the X pitch's P2 term."""
        return [f"E{c}{a}[{j}]" for a in self.axes for c in COMPONENTS for j in range(degree + 1)]

    def poses(self, poses_mm) -> np.ndarray:
        """Poses as an array (m × axes) [mm], checked against the travel."""
        P = np.atleast_2d(np.asarray(poses_mm, float))
        if P.ndim != 2 or P.shape[1] != len(self.axes):
            raise ValueError(f"poses must have one column per axis ({', '.join(self.axes)}), got shape {P.shape}")
        if not np.all(np.isfinite(P)):
            raise ValueError("poses must be finite")
        for i, (a, (lo, hi)) in enumerate(zip(self.axes, self.travel_mm)):
            out = (P[:, i] < lo - 1e-9) | (P[:, i] > hi + 1e-9)
            if out.any():
                raise ValueError(f"axis {a} at {P[out, i][0]:g} mm is outside its travel [{lo:g}, {hi:g}] mm")
        return P

    def tip_at(self, P: np.ndarray) -> np.ndarray:
        """The tool tip at poses ``P`` (m × 3) [mm]."""
        return self.tip_mm + (P * self.tip_moves) @ self._unit()

    def refs_at(self, P: np.ndarray) -> np.ndarray:
        """Each carriage's reference point at poses ``P`` (m × axes × 3) [mm]."""
        return self.ref_mm[None] + np.einsum("ab,mb,bd->mad", self.ref_moves, P, self._unit())

    def _unit(self) -> np.ndarray:
        return np.eye(3)[list(self.directions)]


def chain_of(machine) -> Chain:
    """The kinematic chain of a machine file's linear axes (its bodies' mounting, its TCP and table reference)."""
    from hybridcomp.fem.iso230 import axis_sign

    axes = tuple(a.name for a in machine.axes)

    def moved_by(body: str) -> np.ndarray:
        unit = np.eye(len(axes))
        return np.array([machine.body_offset_mm(body, dict(zip(axes, unit[b])))[machine.axes[b].direction]
                         for b in range(len(axes))])

    refs = []
    for a in machine.axes:
        box = machine.body(a.moves).box_mm
        refs.append(np.mean(np.asarray(box, float), axis=0) if box is not None else np.zeros(3))
    return Chain(axes=axes, directions=tuple(a.direction for a in machine.axes),
                 sides=tuple(axis_sign(machine, n) for n in axes),
                 travel_mm=tuple(tuple(float(v) for v in a.travel_mm) for a in machine.axes),
                 tip_mm=np.asarray(machine.tcp.position_mm, float), tip_moves=moved_by(machine.tcp.body),
                 ref_mm=np.array(refs), ref_moves=np.array([moved_by(a.moves) for a in machine.axes]))


def _basis(chain: Chain, P: np.ndarray, degree: int) -> np.ndarray:
    """Legendre polynomials of each axis' normalised position (m × axes × degree + 1)."""
    lo = np.array([t[0] for t in chain.travel_mm])
    hi = np.array([t[1] for t in chain.travel_mm])
    xi = (2.0 * P - (lo + hi)) / np.where(hi > lo, hi - lo, 1.0)
    return np.stack([legendre.legvander(xi[:, i], degree) for i in range(len(chain.axes))], axis=1)


def design_matrix(chain: Chain, poses_mm, degree: int = DEFAULT_DEGREE) -> np.ndarray:
    """The TCP errors at ``poses_mm`` as a linear map of the coefficients: (3 m × coefficients).

    Rows: dx, dy, dz of the first pose, then of the next; columns: :meth:`Chain.names`.
    """
    if int(degree) != degree or degree < 0:
        raise ValueError(f"degree must be a whole number ≥ 0, got {degree!r}")
    P = chain.poses(poses_mm)
    m, n = P.shape[0], len(chain.axes)
    L = _basis(chain, P, degree)  # m × axes × k
    lever = chain.tip_at(P)[:, None, :] - chain.refs_at(P)  # m × axes × 3 [mm]
    k = degree + 1
    D = np.zeros((m, 3, n, len(COMPONENTS), k))
    for a in range(n):
        s = chain.sides[a]
        for d in range(3):  # translations: δ_d
            D[:, d, a, d, :] = s * L[:, a, :]
        for r in range(3):  # rotations: (e_r × lever) per µrad, lever in mm: 1e-3 µm
            cross = np.cross(np.eye(3)[r], lever[:, a, :]) * 1e-3  # m × 3
            D[:, :, a, 3 + r, :] = s * cross[:, :, None] * L[:, a, None, :]
    return D.reshape(3 * m, n * len(COMPONENTS) * k)


@dataclass(frozen=True)
class ErrorModel:
    """A volumetric error model: the chain, the degree of its error functions and their coefficients.

    ``coef`` (axes × 6 × degree + 1): Legendre coefficients of each axis' components (:data:`COMPONENTS`) [µm, µrad];
    ``rank_deficit``: how many coefficient combinations the data it was identified from could not see (0 for a
    model given by hand).
    """

    chain: Chain
    degree: int
    coef: np.ndarray
    rank_deficit: int = 0

    def function(self, axis: str, component: str, positions_mm) -> np.ndarray:
        """One error function of one axis at its positions (``component`` one of :data:`COMPONENTS`) [µm, µrad]."""
        a, c = self.chain.axes.index(axis), COMPONENTS.index(component)
        P = np.zeros((np.size(positions_mm), len(self.chain.axes)))
        P[:, a] = np.ravel(positions_mm)
        return _basis(self.chain, P, self.degree)[:, a, :] @ self.coef[a, c]


def tcp_error_um(model: ErrorModel, poses_mm) -> np.ndarray:
    """The TCP-minus-table error of the model at ``poses_mm`` (m × 3) [µm]."""
    D = design_matrix(model.chain, poses_mm, model.degree)
    return (D @ model.coef.ravel()).reshape(-1, 3)


def identify(chain: Chain, poses_mm, error_um, degree: int = DEFAULT_DEGREE) -> ErrorModel:
    """The error model whose TCP errors fit ``error_um`` (m × 3 [µm], NaN: a direction not measured) at the poses.

    Least squares with the minimum-norm solution over the coefficients scaled to their columns' norms: the
    combinations that no TCP error at these poses can see (a constant offset shared by every axis, a rotation whose
    lever arm never changes) are left at zero in those scaled coordinates and counted in ``rank_deficit``.  They
    change no prediction anywhere when the poses form a grid with ``degree + 1`` levels of every axis whose lever
    arm to the tool tip stays the same as it moves (a tool-side axis) and ``degree + 2`` levels of every axis whose
    lever arm changes with its own position (a table-side axis: its rotation, a polynomial of ``degree``, acts
    with a lever arm linear in the same position, so the TCP error is of ``degree + 1`` in it).  With fewer
    levels the unseen combinations are zero at the poses and not between them.
    """
    D = design_matrix(chain, poses_mm, degree)
    y = np.asarray(error_um, float).ravel()
    if y.shape != (D.shape[0],):
        raise ValueError(f"{y.size} error values for {D.shape[0] // 3} poses: give dx, dy, dz per pose")
    ok = np.isfinite(y)
    if ok.sum() == 0:
        raise ValueError("no finite error value to identify from")
    scale = np.linalg.norm(D[ok], axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    sol, _, rank, _ = np.linalg.lstsq(D[ok] / scale, y[ok], rcond=1e-10)
    coef = (sol / scale).reshape(len(chain.axes), len(COMPONENTS), degree + 1)
    return ErrorModel(chain, degree, coef, rank_deficit=D.shape[1] - int(rank))

