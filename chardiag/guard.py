"""The last check before a compensation offset leaves the program: finite and within a clamp.

Every path that writes offsets for a control (the CNC export here, the monitoring daemon's
sinks, ``cd eval``) calls :func:`guard_offsets` on what it is about to write, so a value that is
not finite or implausibly large is refused with a clear error instead of being written (an
``$SA_TEMP_COMP_ABS_VALUE[Z1]=nan`` would be read by the control, or rejected mid-program).

The guard refuses; it never clamps silently: an offset beyond the clamp means the model or its
inputs are broken, and writing the clamp instead would hide that.  (The daemon's rate and
magnitude limiting of plausible offsets is a separate, deliberate decision.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from hybridcomp.errors import HybridcompError

#: the default clamp of a compensation offset [µm]: 1 mm of thermal drift is far beyond a working machine tool
DEFAULT_CLAMP_UM = 1000.0


class OffsetGuardError(HybridcompError, ValueError):
    """An offset about to be written is not finite or beyond its clamp; the message names the source, axis and value."""


def guard_offsets(offsets_um: Mapping[str, float], *, clamp_um: float = DEFAULT_CLAMP_UM,
                  source: str = "offsets") -> dict[str, float]:
    """The offsets as floats, after checking each is finite and within ±``clamp_um``.

    Parameters
    ----------
    offsets_um : offset per axis or drift column (``{"X": -12.3}``, ``{"dz_um": 4.5}``) [µm]
    clamp_um : the largest magnitude allowed [µm] (default :data:`DEFAULT_CLAMP_UM`)
    source : what is being written, first in the message (``"cd eval --cnc 840d"``, a sink's name)

    Returns
    -------
    dict
        the same keys, values as ``float`` [µm], unchanged.

    Raises
    ------
    OffsetGuardError
        naming ``source``, the first bad key and its value, when a value is not finite or
        ``|value| > clamp_um``; nothing is to be written then.
    ValueError
        when ``clamp_um`` itself is not a finite positive number.
    """
    if not (isinstance(clamp_um, (int, float)) and math.isfinite(clamp_um) and clamp_um > 0):
        raise ValueError(f"guard_offsets: clamp_um must be a finite positive number [µm], got {clamp_um!r}")
    out = guard_finite(offsets_um, source=source, unit="µm", what="offset ")
    for key, v in out.items():
        if abs(v) > clamp_um:
            raise OffsetGuardError(f"{source}: offset {key} = {v:.6g} µm is beyond the clamp of ±{clamp_um:g} µm; "
                                   "nothing written")
    return out


def guard_finite(values: Mapping[str, float], *, source: str = "values", unit: str = "",
                 what: str = "") -> dict[str, float]:
    """The values as floats, after checking each is finite (slopes, reference positions of a CNC export).

    ``what`` is put before each key in a message (``"offset "``), ``unit`` after its value.

    Raises
    ------
    OffsetGuardError
        naming ``source``, the first non-finite key and its value.
    """
    out: dict[str, float] = {}
    for key, value in values.items():
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise OffsetGuardError(f"{source}: {what}{key} = {value!r} is not a number; nothing written") from None
        if not math.isfinite(v):
            raise OffsetGuardError(f"{source}: {what}{key} = {v}{' ' + unit if unit else ''} is not finite; "
                                   "nothing written")
        out[key] = v
    return out


__all__ = ["DEFAULT_CLAMP_UM", "OffsetGuardError", "guard_finite", "guard_offsets"]
