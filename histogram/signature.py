"""Load-case signatures: a fixed-length vector per increment or period, and its distance.

The signature of a load case over a time span is the vector

    [f_1 .. f_n,  h_1[1] .. h_1[m_1],  ...,  h_n[1] .. h_n[m_n],  f_spindle]

with ``f_a`` the time-averaged load factor of axis a, ``h_a[k]`` the fraction
of the span axis a spent in its rail segment k (sums to 1 per axis) and
``f_spindle`` the spindle factor (all in [0, 1]). Its length is fixed by the
machine: ``n + Σ m_a + 1`` (vmc800: 3 + 12 + 1 = 16).

The distance between two signatures a and b is

    d(a, b)² = Σ_axes (f_a − f_b)²  +  Σ_axes f̄² · TV(h_a, h_b)²  +  (f_spindle,a − f_spindle,b)²

with ``f̄ = (f_a + f_b) / 2`` the mean factor of that axis and ``TV = ½ Σ_k |h_a[k] − h_b[k]|``
the total-variation distance of the two position distributions (0: same
distribution, 1: no segment in common). Where an axis stands still its
position distribution carries no heat and does not count; where it runs at
full speed a complete change of working region counts like a factor change
of 1. ``d`` is symmetric, zero for equal signatures (up to the segment
fractions of axes that stand still in both), and at most ``sqrt(2 n + 1)``.
A distance of 0.05 is, for example, one axis factor differing by 0.05.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.histogram.increments import Increments
from hybridcomp.models.machine import Machine


@dataclass(frozen=True)
class SignatureLayout:
    """Which entries of a signature vector are what: axis names and their segment counts."""

    axis_names: tuple[str, ...]
    n_segments: tuple[int, ...]

    @classmethod
    def of(cls, machine: Machine) -> SignatureLayout:
        return cls(tuple(a.name for a in machine.axes), tuple(a.n_segments for a in machine.axes))

    @property
    def size(self) -> int:
        return len(self.axis_names) + sum(self.n_segments) + 1

    @property
    def names(self) -> tuple[str, ...]:
        """Column names: ``f_X`` ..., ``h_X[1]`` ..., ``f_spindle``."""
        f = [f"f_{a}" for a in self.axis_names]
        h = [f"h_{a}[{k + 1}]" for a, m in zip(self.axis_names, self.n_segments) for k in range(m)]
        return (*f, *h, "f_spindle")


def signatures(inc: Increments, period_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signature vectors per increment, or per period of whole increments.

    Parameters
    ----------
    inc : increments
    period_s : length of a period [s], a whole multiple of the increment
        length (e.g. 900 for the 15 min monitoring interval with 5 min
        increments); None: one signature per increment. Values are
        time-weighted means over the increments of a period.

    Returns
    -------
    start_s, end_s [s] (np,), and the signatures (np × layout.size)
    """
    segs = [inc.segment_fraction(a) for a in inc.axis_names]
    D = inc.duration_s
    V = np.hstack([inc.axis_factor, *segs, inc.spindle_factor[:, None]])
    if period_s is None:
        return inc.start_s.copy(), inc.end_s.copy(), V
    ratio = period_s / inc.increment_s
    n = int(round(ratio))
    if n < 1 or abs(ratio - n) > 1e-9:
        raise ValueError(f"period_s {period_s!r} must be a whole multiple of the increment {inc.increment_s!r} s")
    group = np.arange(len(inc)) // n
    ng = int(group[-1]) + 1
    W = np.bincount(group, D, ng)
    out = np.column_stack([np.bincount(group, V[:, j] * D, ng) for j in range(V.shape[1])]) / W[:, None]
    first = np.searchsorted(group, np.arange(ng))
    last = np.searchsorted(group, np.arange(ng), side="right") - 1
    return inc.start_s[first], inc.end_s[last], out


def signature_distance(a, b, layout: SignatureLayout) -> np.ndarray:
    """Distance between signatures (see the module docstring); broadcasts over leading dimensions."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if a.shape[-1] != layout.size or b.shape[-1] != layout.size:
        raise ValueError(f"signatures must have {layout.size} entries, got {a.shape[-1]} and {b.shape[-1]}")
    na = len(layout.axis_names)
    fa, fb = a[..., :na], b[..., :na]
    d2 = np.sum((fa - fb) ** 2, axis=-1)
    off = na
    for j, m in enumerate(layout.n_segments):
        tv = 0.5 * np.sum(np.abs(a[..., off : off + m] - b[..., off : off + m]), axis=-1)
        d2 = d2 + (0.5 * (fa[..., j] + fb[..., j])) ** 2 * tv**2
        off += m
    d2 = d2 + (a[..., -1] - b[..., -1]) ** 2
    return np.sqrt(d2)


def write_signatures(path, inc: Increments, layout: SignatureLayout, period_s: float | None = None) -> None:
    """Write signatures as CSV: ``start_s, end_s`` and the layout's names (see :func:`signatures`)."""
    start, end, V = signatures(inc, period_s)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["start_s", "end_s", *layout.names])
        for s, e, row in zip(start, end, V):
            w.writerow([f"{s:g}", f"{e:g}", *(f"{v:.6g}" for v in row)])
