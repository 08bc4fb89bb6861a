"""Poses and named values as typed on a command line: ``"X=100,Y=-50"``.

The text form every subcommand and configuration takes for a pose (axis positions [mm]) or for
other named numbers (a CD's inputs, ``T1=21.3,T2=20.8``); :meth:`Machine.check_pose
<hybridcomp.models.machine.Machine.check_pose>` then completes and checks a pose against the
machine.
"""

from __future__ import annotations


def parse_pairs(text: str | None, what: str) -> dict[str, float]:
    """``"X=100,Y=-50"`` → {"X": 100.0, "Y": -50.0}; errors name the option ``what`` and the bad part.

    Parameters
    ----------
    text : comma-separated ``NAME=VALUE`` pairs; None or empty gives no pairs
    what : the option or field the text comes from, for the message (``--pose``)

    Raises
    ------
    ValueError
        naming ``what`` and the part that is not ``NAME=VALUE`` or whose value is not a number.
    """
    if not text:
        return {}
    out = {}
    for part in text.split(","):
        if "=" not in part:
            raise ValueError(f"{what}: {part!r} is not NAME=VALUE")
        k, v = part.split("=", 1)
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise ValueError(f"{what}: value {v!r} of {k.strip()!r} is not a number") from None
    return out


def parse_pose(text: str | None) -> dict[str, float]:
    """``"X=100,Y=-50"`` → {"X": 100.0, "Y": -50.0}: axis positions [mm] as the ``--pose`` option takes them."""
    return parse_pairs(text, "--pose")
