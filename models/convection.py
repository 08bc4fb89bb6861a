"""Heat-transfer coefficients of a ball screw in still air: turning (forced) and at rest (natural convection).

* Turning: a cylinder rotating in quiescent air, ``Nu = 0.133 Re^(2/3) Pr^(1/3)`` with ``Re = ω D² / ν``
  (Becker 1963, the correlation of Anderson & Saunders' and Becker's measurements; Re up to 4.3e5, 0.7 < Pr < 670;
  Incropera & DeWitt, Fundamentals of Heat and Mass Transfer, ch. 7, rotating cylinder).
* At rest: natural convection from a long horizontal cylinder, Churchill & Chu (1975),
  ``Nu = {0.60 + 0.387 Ra^(1/6) / [1 + (0.559/Pr)^(9/16)]^(8/27)}²`` with ``Ra = g β ΔT D³ / (ν a)``, taken at a
  screw ``NATURAL_DT_K`` over its air (the model is linear: one coefficient).
* Both: combined as ``h = (h_forced³ + h_natural³)^(1/3)`` (Churchill 1977, mixed convection; the larger wins,
  the smaller fills in near rest).

Air at 20 °C and 1 bar (VDI Heat Atlas): conductivity 0.0257 W/(m K), kinematic viscosity 1.516e-5 m²/s,
Prandtl number 0.713, β = 1/T.  Radiation is not included (a bright ground screw radiates little; a blackened
one about 5 W/(m² K) more at room temperature).
"""

from __future__ import annotations

import math

AIR_K_W_MK = 0.0257
AIR_NU_M2_S = 1.516e-5
AIR_PR = 0.713
AIR_T_K = 293.15
G_M_S2 = 9.81
#: the screw's rise over its air at which the natural-convection coefficient is taken [K]
NATURAL_DT_K = 5.0


def rotating_cylinder_h_W_m2K(diameter_mm: float, rpm: float) -> float:
    """Forced convection of a cylinder turning at ``rpm`` in still air (Becker 1963) [W/(m² K)]; 0 at rest."""
    d = diameter_mm * 1e-3
    re = rpm * 2 * math.pi / 60 * d * d / AIR_NU_M2_S
    return 0.133 * re ** (2 / 3) * AIR_PR ** (1 / 3) * AIR_K_W_MK / d


def horizontal_cylinder_natural_h_W_m2K(diameter_mm: float, dT_K: float = NATURAL_DT_K) -> float:
    """Natural convection of a long horizontal cylinder ``dT_K`` over its air (Churchill & Chu 1975) [W/(m² K)]."""
    d = diameter_mm * 1e-3
    ra = G_M_S2 * dT_K / AIR_T_K * d**3 / (AIR_NU_M2_S * AIR_NU_M2_S / AIR_PR)
    nu = (0.60 + 0.387 * ra ** (1 / 6) / (1 + (0.559 / AIR_PR) ** (9 / 16)) ** (8 / 27)) ** 2
    return nu * AIR_K_W_MK / d


def screw_h_W_m2K(diameter_mm: float, mean_rpm: float) -> float:
    """A screw's heat-transfer coefficient at its mean speed: forced and natural combined (module docstring)."""
    if not diameter_mm > 0 or not mean_rpm >= 0:
        raise ValueError(f"diameter {diameter_mm!r} mm must be positive and the speed {mean_rpm!r} rpm not negative")
    forced, natural = rotating_cylinder_h_W_m2K(diameter_mm, mean_rpm), horizontal_cylinder_natural_h_W_m2K(diameter_mm)
    return (forced**3 + natural**3) ** (1 / 3)
