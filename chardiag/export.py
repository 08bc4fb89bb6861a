"""Compensation offsets for the CNC: a generic per-axis table and the Siemens 840D sl form.

Sign convention: a CD predicts the *drift* of the TCP against the table
[µm]; the *compensation* the control adds to the axis is its negative.

Siemens 840D sl temperature compensation (function K3) adds per axis the
error line

    ΔK = K0 + tan β · (P − P0)

with three setting data per axis:

* SD43900 ``$SA_TEMP_COMP_ABS_VALUE`` — K0, the position-independent offset [mm]
* SD43910 ``$SA_TEMP_COMP_SLOPE`` — tan β, the slope of the error line along the axis' own position [-]
* SD43920 ``$SA_TEMP_COMP_REF_POSITION`` — P0, the reference position of the error line [mm]

(active when MD32750 ``$MA_TEMP_COMP_TYPE`` enables them). K0 is the
compensation at P0 = the axis position of the CD's pose; tan β is the
derivative of the compensation along the same axis where the CD has that
axis' position as an active input (central difference over 1 % of its
trained range), else 0 (a CD of one pose says nothing about the slope).

Every export passes its values through :mod:`hybridcomp.chardiag.guard` first: an offset that is
not finite or beyond the clamp (default ±1000 µm), or a slope or reference position that is not
finite, raises :class:`~hybridcomp.chardiag.guard.OffsetGuardError` and nothing is written.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from dataclasses import dataclass

from hybridcomp.chardiag.cd import DIRECTIONS, TARGETS, CDSet
from hybridcomp.chardiag.guard import DEFAULT_CLAMP_UM, guard_finite, guard_offsets
from hybridcomp.models.layout import control_character

SIEMENS_SD = {"abs": ("SD43900", "$SA_TEMP_COMP_ABS_VALUE"), "slope": ("SD43910", "$SA_TEMP_COMP_SLOPE"),
              "ref": ("SD43920", "$SA_TEMP_COMP_REF_POSITION")}


@dataclass(frozen=True)
class AxisOffset:
    """The compensation of one axis.

    Attributes
    ----------
    axis : axis name (``"X"``)
    drift_um : predicted TCP drift along the axis [µm]
    compensation_um : offset to add to the axis, −drift [µm]
    slope : d(compensation)/d(axis position) [-] (tan β)
    reference_mm : position the offset refers to [mm] (P0)
    outside : an input was outside the CD's trained range (clamped)
    """

    axis: str
    drift_um: float
    compensation_um: float
    slope: float
    reference_mm: float
    outside: bool


def axis_offsets(cds: CDSet, values: Mapping[str, float]) -> tuple[AxisOffset, ...]:
    """Compensation per axis (X, Y, Z) from the active CD set at the current inputs (``"T1"`` [°C], ``"X"`` [mm])."""
    out = []
    for d in DIRECTIONS:
        cd = cds.cds[d]
        pose = dict(cd.pose_mm)
        drift, outside = cd.evaluate_point(values)
        slope = 0.0
        pos_in = next((i for i in cd.inputs if i.active and i.unit == "mm" and i.name == d), None)
        ref = float(values[d]) if pos_in is not None else float(pose.get(d, 0.0))
        if pos_in is not None:
            h = 0.01 * (pos_in.max - pos_in.min)
            lo = min(max(ref - h, pos_in.min), pos_in.max - 2 * h)
            up, _ = cd.evaluate_point({**values, d: lo + 2 * h})
            dn, _ = cd.evaluate_point({**values, d: lo})
            slope = -(up - dn) / (2 * h) * 1e-3  # µm/mm → mm/mm, of the compensation (−drift)
        out.append(AxisOffset(axis=d, drift_um=drift, compensation_um=-drift, slope=slope, reference_mm=ref,
                              outside=outside))
    return tuple(out)


def check_offsets(offsets: tuple[AxisOffset, ...], clamp_um: float = DEFAULT_CLAMP_UM,
                  source: str = "CNC export") -> None:
    """Raise :class:`~hybridcomp.chardiag.guard.OffsetGuardError` unless every offset can be written.

    Drift and compensation finite and within ±``clamp_um`` [µm]; slope and reference position finite.
    """
    guard_offsets({f"{o.axis} compensation": o.compensation_um for o in offsets}, clamp_um=clamp_um, source=source)
    guard_offsets({f"{o.axis} drift": o.drift_um for o in offsets}, clamp_um=clamp_um, source=source)
    guard_finite({f"{o.axis} slope": o.slope for o in offsets}, source=source)
    guard_finite({f"{o.axis} reference position": o.reference_mm for o in offsets}, source=source, unit="mm")


def generic_table(offsets: tuple[AxisOffset, ...], clamp_um: float = DEFAULT_CLAMP_UM) -> str:
    """CSV: ``axis, drift_um, compensation_um, slope, reference_mm, outside``.

    Raises :class:`~hybridcomp.chardiag.guard.OffsetGuardError` (nothing written) when an offset is not
    finite or beyond ±``clamp_um`` [µm] (:func:`check_offsets`).
    """
    check_offsets(offsets, clamp_um, "CNC export (generic table)")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["axis", "drift_um", "compensation_um", "slope", "reference_mm", "outside"])
    for o in offsets:
        w.writerow([o.axis, f"{o.drift_um:.4f}", f"{o.compensation_um:.4f}", f"{o.slope:.9f}", f"{o.reference_mm:.4f}",
                    int(o.outside)])
    return buf.getvalue()


def siemens_840d(offsets: tuple[AxisOffset, ...], axis_names: Mapping[str, str] | None = None,
                 header: str = "", clamp_um: float = DEFAULT_CLAMP_UM) -> str:
    """A part-program fragment that writes SD43900/SD43910/SD43920 per axis.

    Parameters
    ----------
    offsets : from :func:`axis_offsets`
    axis_names : CD direction → the control's axis identifier (default ``X1``, ``Y1``, ``Z1``)
    header : a comment line (machine, pose, time)
    clamp_um : the largest compensation magnitude written [µm]; beyond it nothing is written

    Raises
    ------
    OffsetGuardError
        when an offset is not finite or beyond ±``clamp_um`` (:func:`check_offsets`).
    ValueError
        when the header or an axis identifier has a control character (it would forge a program line).
    """
    check_offsets(offsets, clamp_um, "CNC export (Siemens 840D sl)")
    names = {d: f"{d}1" for d in DIRECTIONS}
    names.update(axis_names or {})
    lines = []
    if header:
        lines.append(f"; {header}")
    lines += ["; hybridcomp temperature compensation: dK = K0 + tanB * (P - P0)",
              f"; {SIEMENS_SD['abs'][0]} {SIEMENS_SD['abs'][1]} = K0 [mm], {SIEMENS_SD['slope'][0]} "
              f"{SIEMENS_SD['slope'][1]} = tanB [-], {SIEMENS_SD['ref'][0]} {SIEMENS_SD['ref'][1]} = P0 [mm]"]
    for text in (header, *names.values()):
        c = control_character(text)
        if c is not None:
            raise ValueError(f"CNC export (Siemens 840D sl): {text!r} has a control character {c!r}")
    for o in offsets:
        ax = names[o.axis]
        if o.outside:
            lines.append(f"; {ax}: inputs outside the trained range of the CD (clamped)")
        lines += [f"{SIEMENS_SD['abs'][1]}[{ax}]={o.compensation_um * 1e-3:.6f}",
                  f"{SIEMENS_SD['slope'][1]}[{ax}]={o.slope:.9f}",
                  f"{SIEMENS_SD['ref'][1]}[{ax}]={o.reference_mm:.4f}"]
    lines.append("M17")
    return "\n".join(lines) + "\n"


__all__ = ["AxisOffset", "SIEMENS_SD", "TARGETS", "axis_offsets", "check_offsets", "generic_table", "siemens_840d"]
