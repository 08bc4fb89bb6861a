"""The operators of a thermal system with convection affine in ``h``, full or reduced (SI units).

In temperature rise ``x`` [K]::

    M x' + (K + Σ_i h_i H_i) x = [B, h_1 H_1 1, ..., h_z H_z 1] u,    y = C x

with inputs ``u = [q_1 .. q_m [W], ΔT_air,1 .. ΔT_air,z [K]]``.  The FE model
(:class:`hybridcomp.fem.model.ThermoElasticModel`), the system a reduction starts from
(:class:`hybridcomp.rom.krylov.ThermalSystem`) and the reduced model
(:class:`hybridcomp.rom.reduced.ReducedModel`) each hold one :class:`ThermalOperators` and read its fields
through :class:`HasOperators`; each keeps its own arithmetic on them (sparse or dense), so moving the fields
here changed no result by a bit.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ThermalOperators:
    """The matrices and names of ``M x' + (K + Σ h_i H_i) x = [B, h_i H_i 1] u``, ``y = C x``.

    Attributes
    ----------
    M : capacity (n × n) [J/K]
    K : conduction (n × n) [W/K]
    H : unit convection per zone, a tuple of (n × n) matrices or a (z × n × n) array [m^2]
    h_W_m2K : heat-transfer coefficient per zone (z,) [W/(m^2 K)]
    B : heat input columns (n × m) [-]
    Hb : ``H_i 1`` per zone (n × z) [m^2]; input ``m + i`` is the air temperature rise of zone i [K]
    C : output rows (q × n), in output units per kelvin
    input_names : loads column per input (``*_W`` powers, then ``*_degC`` zone air), or raw names
    output_names : name per row of ``C``
    """

    M: object
    K: object
    H: object
    h_W_m2K: np.ndarray
    B: np.ndarray
    Hb: np.ndarray
    C: object
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]

    @property
    def n(self) -> int:
        return self.M.shape[0]

    def shape_problems(self) -> list[tuple[str, object, object]]:
        """Every field whose shape does not fit the others: (field, shape, expected shape)."""
        n, z = self.n, len(self.h_W_m2K)
        checks = [
            ("M", self.M.shape, (n, n)),
            ("K", self.K.shape, (n, n)),
            ("H", len(self.H), z),
            ("B", self.B.shape[0], n),
            ("Hb", self.Hb.shape, (n, z)),
            ("C", self.C.shape[1], n),
            ("input_names", len(self.input_names), self.B.shape[1] + z),
            ("output_names", len(self.output_names), self.C.shape[0]),
        ]
        checks += [(f"H[{i}]", Hi.shape, (n, n)) for i, Hi in enumerate(self.H)]
        return [(name, got, want) for name, got, want in checks if got != want]


class HasOperators:
    """Read access to the :class:`ThermalOperators` a model holds in its field ``operators``."""

    operators: ThermalOperators

    M = property(lambda self: self.operators.M, doc="capacity [J/K]")
    K = property(lambda self: self.operators.K, doc="conduction [W/K]")
    H = property(lambda self: self.operators.H, doc="unit convection per zone [m^2]")
    h_W_m2K = property(lambda self: self.operators.h_W_m2K, doc="heat-transfer coefficient per zone [W/(m^2 K)]")
    B = property(lambda self: self.operators.B, doc="heat input columns [-]")
    Hb = property(lambda self: self.operators.Hb, doc="H_i 1 per zone [m^2]")
    C = property(lambda self: self.operators.C, doc="output rows")
    input_names = property(lambda self: self.operators.input_names, doc="name per input, in input order")
    output_names = property(lambda self: self.operators.output_names, doc="name per output")

    @property
    def zone_names(self) -> tuple[str, ...]:
        """The zones, named as the air columns in ``input_names`` without ``_degC``."""
        z = len(self.h_W_m2K)
        names = self.input_names
        return tuple(n.removesuffix("_degC") for n in names[len(names) - z:]) if z else ()

    def with_operators(self, **changes):
        """A copy with changed operator fields (``B=..., input_names=...``); cached products are dropped."""
        extra = {"_cache": {}} if any(f.name == "_cache" for f in dataclasses.fields(self)) else {}
        return dataclasses.replace(self, operators=dataclasses.replace(self.operators, **changes), **extra)

    @property
    def heat_names(self) -> tuple[str, ...]:
        """The heat inputs, named as the power columns in ``input_names`` without ``_W``."""
        return tuple(n.removesuffix("_W") for n in self.input_names[:self.B.shape[1]])

    def with_htc(self, **h_W_m2K: float):
        """A copy with changed zone heat-transfer coefficients [W/(m^2 K)]: no re-assembly, no new reduction.

        Zones are named as in :attr:`zone_names`.  For a reduced model outside the range its basis was enriched
        for (``meta['h_range']``) the model stays stable but its error is not controlled.

        Raises
        ------
        KeyError
            an unknown zone
        ValueError
            a coefficient that is not positive
        """
        zones = self.zone_names
        h = np.array(self.h_W_m2K, float)
        for name, value in h_W_m2K.items():
            if name not in zones:
                raise KeyError(f"unknown zone {name!r} (zones: {zones})")
            if not value > 0:
                raise ValueError(f"h of zone {name!r} must be positive, got {value}")
            h[zones.index(name)] = value
        return self.with_operators(h_W_m2K=h)
