"""Load factors and position histograms per time increment.

The motion between two samples (or two G-code breakpoints) is taken as
piecewise linear in time: positions, velocities, spindle speed and air
temperatures vary linearly from one sample to the next. Every quantity is
integrated exactly over that motion, and an interval that straddles an
increment boundary is split there, so the increments add up to the whole
trace whatever the sampling rate. Per increment ``k`` of duration ``D_k``:

* axis load factor ``f = ∫|v| dt / (v_max D_k)``: the time-averaged speed over
  the axis' ``max_feed_mm_min``; ``∫|v| dt`` is the path length (the sum of
  ``|Δposition|``, or the exact integral of ``|v|`` when the trace has velocity
  columns);
* time-weighted position histogram: the time the axis spent in each bin
  [s]; the bins refine the machine's rail segments (``bins_per_segment`` each),
  so the segment fractions (time in segment / ``D_k``) are exact sums of bins;
* spindle factor ``∫|n| dt / (n_max D_k)`` with ``n_max`` the machine's
  ``[spindle] max_speed_rpm``;
* the time-averaged measured air temperatures [°C].

A sample interval longer than ``max_gap_s`` is a gap in the recording: it is
counted as standstill (no path, spindle off, positions held at the sample
before the gap), and the caller is warned with the number and the first line.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.histogram.trace import (
    ReadStats,
    Samples,
    TraceFileError,
    TraceWarning,
    position_column,
    read_trace_chunks,
    velocity_column,
)
from hybridcomp.models.machine import Machine

log = logging.getLogger(__name__)

DEFAULT_INCREMENT_S = 300.0
DEFAULT_MAX_GAP_S = 10.0
DEFAULT_FEED_TOLERANCE = 0.02
DEFAULT_TRAVEL_TOLERANCE_MM = 0.01
DEFAULT_BINS_PER_SEGMENT = 5
DEFAULT_MAX_DROPPED_FRACTION = 0.01


@dataclass(frozen=True)
class Increments:
    """Load factors and position histograms per time increment.

    Attributes
    ----------
    start_s, end_s : start and end of each increment [s] (nk,); the last one may be shorter
    increment_s : nominal increment length [s]
    axis_names : machine axis names, the order of the axis columns
    axis_factor : time-averaged ``|v| / v_max`` per increment and axis [-] (nk × n_axes)
    bin_edges_mm : per axis the histogram bin edges [mm] (travel min .. max)
    bin_time_s : per axis the time spent in each bin [s] (nk × n_bins)
    bins_per_segment : histogram bins per rail segment
    spindle_factor : time-averaged ``|n| / n_max`` per increment [-] (nk,)
    air_names : trace columns of the measured air temperatures
    air_degC : their time averages per increment [°C] (nk × n_air)
    initial_air_degC : their values at the first sample [°C] (n_air,)
    gap_s : time per increment counted as standstill because of recording gaps [s] (nk,)
    rows, dropped_rows : samples read and samples dropped for NaN
    mean_power_inputs : heat inputs (``<source>_W``, ``<source>[k]_W``) whose time-averaged power is
        integrated over the motion: every moving source, and the fixed sources whose power is not
        proportional to their load factor (exponent != 1, a power table)
    mean_power_W : their time-averaged power per increment [W] (nk × len(mean_power_inputs)): the mean
        of ``P(f(t))`` with ``f(t)`` the instantaneous factor, and for a moving source the heat
        dissipated while the axis was in segment k (see ``bcs.heat_powers(..., power="mean")``)
    """

    start_s: np.ndarray
    end_s: np.ndarray
    increment_s: float
    axis_names: tuple[str, ...]
    axis_factor: np.ndarray
    bin_edges_mm: tuple[np.ndarray, ...]
    bin_time_s: tuple[np.ndarray, ...]
    bins_per_segment: int
    spindle_factor: np.ndarray
    air_names: tuple[str, ...]
    air_degC: np.ndarray
    initial_air_degC: np.ndarray
    gap_s: np.ndarray
    rows: int = 0
    dropped_rows: int = 0
    mean_power_inputs: tuple[str, ...] = ()
    mean_power_W: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.start_s.size)

    @property
    def duration_s(self) -> np.ndarray:
        """Length of each increment [s]."""
        return self.end_s - self.start_s

    def histogram(self, axis: str) -> np.ndarray:
        """Fraction of each increment the axis spent in each histogram bin [-] (nk × n_bins)."""
        a = self.axis_names.index(axis)
        return self.bin_time_s[a] / self.duration_s[:, None]

    def segment_time_s(self, axis: str) -> np.ndarray:
        """Time the axis spent in each rail segment [s] (nk × n_segments)."""
        a = self.axis_names.index(axis)
        b = self.bin_time_s[a]
        return b.reshape(b.shape[0], -1, self.bins_per_segment).sum(axis=2)

    def segment_fraction(self, axis: str) -> np.ndarray:
        """Fraction of each increment the axis spent in each rail segment [-] (nk × n_segments); rows sum to 1."""
        return self.segment_time_s(axis) / self.duration_s[:, None]

    def segment_edges_mm(self, axis: str) -> np.ndarray:
        """Rail segment bounds of an axis [mm]."""
        a = self.axis_names.index(axis)
        return self.bin_edges_mm[a][:: self.bins_per_segment]


def _abs_integral(v0: np.ndarray, v1: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """∫|v| dt for v linear from v0 to v1 over dt (exact, also through a sign change)."""
    a0, a1 = np.abs(v0), np.abs(v1)
    same = v0 * v1 >= 0
    den = np.where(same, 1.0, a0 + a1)
    return np.where(same, 0.5 * (a0 + a1) * dt, 0.5 * (v0 * v0 + v1 * v1) / den * dt)


def _time_in_bins(x0: np.ndarray, x1: np.ndarray, dt: np.ndarray, edges: np.ndarray):
    """Time [s] a point moving linearly from x0 to x1 in dt spends in each bin.

    Returns (interval index, bin index, time) triplets; a point standing exactly
    on an inner edge counts in the bin above it, one at the travel max in the last bin.
    """
    nb = edges.size - 1
    lo, hi = np.minimum(x0, x1), np.maximum(x0, x1)
    i0 = np.clip(np.searchsorted(edges, lo, side="right") - 1, 0, nb - 1)
    i1 = np.clip(np.searchsorted(edges, hi, side="right") - 1, 0, nb - 1)
    one = i0 == i1
    idx = [np.flatnonzero(one)]
    bins = [i0[one]]
    w = [dt[one]]
    multi = np.flatnonzero(~one)
    if multi.size:
        a, b, d = lo[multi, None], hi[multi, None], dt[multi, None]
        ov = np.clip(np.minimum(b, edges[None, 1:]) - np.maximum(a, edges[None, :-1]), 0.0, None)
        share = ov / (b - a) * d  # b > a here: the interval crosses an edge
        r, c = np.nonzero(share)
        idx.append(multi[r])
        bins.append(c)
        w.append(share[r, c])
    return np.concatenate(idx), np.concatenate(bins), np.concatenate(w)


class _Integrator:
    """Accumulates piecewise-linear motion into increments (the only stateful part; used by the functions below)."""

    def __init__(self, machine: Machine, increment_s: float, bins_per_segment: int, air_names: tuple[str, ...]):
        if not (math.isfinite(increment_s) and increment_s > 0):
            raise ValueError(f"increment_s must be positive, got {increment_s!r}")
        if int(bins_per_segment) != bins_per_segment or bins_per_segment < 1:
            raise ValueError(f"bins_per_segment must be a positive integer, got {bins_per_segment!r}")
        self.machine = machine
        self.T = float(increment_s)
        self.bps = int(bins_per_segment)
        self.axes = machine.axes
        self.edges = []
        for a in machine.axes:
            b = np.asarray(a.segment_bounds_mm)
            fine = [np.linspace(b[k], b[k + 1], self.bps + 1)[:-1] for k in range(b.size - 1)]
            self.edges.append(np.append(np.concatenate(fine), b[-1]))
        self.nbins = [e.size - 1 for e in self.edges]
        self.bin_off = np.concatenate([[0], np.cumsum(self.nbins)])
        self.air_names = air_names
        # moving sources and sources whose power is not proportional to the factor: mean power integrated too
        self.nl: list[tuple] = []  # (source, driver index (-1: spindle), column offset)
        self.nl_names: list[str] = []
        layout = machine.layout()
        for src in machine.heat_sources:
            linear = src.power_table is None and src.exponent == 1.0
            if src.driver is None or (src.kind == "fixed" and linear):
                continue
            d = -1 if src.driver == "spindle" else [a.name for a in machine.axes].index(src.driver)
            self.nl.append((src, d, len(self.nl_names)))
            self.nl_names.extend(layout.heat_columns[j] for j in layout.source_columns(src.name))
        self.origin: float | None = None
        self.t_last: float | None = None
        self.initial_air = np.full(len(air_names), np.nan)
        self.cap = 0
        self.nk = 0
        self._alloc(64)

    def _alloc(self, cap: int) -> None:
        na, nair, nb = len(self.axes), len(self.air_names), int(self.bin_off[-1])
        new = {
            "dur": np.zeros(cap),
            "path": np.zeros((cap, na)),
            "spin": np.zeros(cap),
            "air": np.zeros((cap, nair)),
            "gap": np.zeros(cap),
            "bins": np.zeros((cap, nb)),
            "energy": np.zeros((cap, len(self.nl_names))),
        }
        for k, v in new.items():
            if self.cap:
                v[: self.cap] = getattr(self, k)
            setattr(self, k, v)
        self.cap = cap

    def add(self, t, pa, pb, gap, ra, rb, aira, airb, va=None, vb=None) -> None:
        """Add m contiguous intervals: breakpoints ``t`` (m+1,), per interval start/end values.

        pa, pb : positions [mm] at the interval start and end (m × n_axes)
        gap : intervals counted as standstill (positions held at ``pa``)
        ra, rb : spindle speed [1/min] at start and end (>= 0)
        aira, airb : air temperatures [°C] at start and end (m × n_air)
        va, vb : optional velocities [mm/min] at start and end (m × n_axes, NaN: use positions)
        """
        m = t.size - 1
        if m < 1:
            return
        if self.origin is None:
            self.origin = float(t[0])
            self.initial_air = np.asarray(aira[0], float).copy()
        T, o = self.T, self.origin
        # increment boundaries strictly inside (t0, tm), not already breakpoints
        k_lo = math.floor((t[0] - o) / T) + 1
        k_hi = math.ceil((t[-1] - o) / T)
        B = o + np.arange(k_lo, k_hi + 1) * T
        B = B[(B > t[0]) & (B < t[-1])]
        if B.size:
            pos = np.searchsorted(t, B)
            B = B[t[np.minimum(pos, m)] != B]
            starts = np.insert(t[:-1], np.searchsorted(t[:-1], B), B)  # both sorted, no common values
        else:
            starts = t[:-1]
        ends = np.append(starts[1:], t[-1])
        if starts.size == m:
            p = np.arange(m)
            aa, ab = np.zeros(m), np.ones(m)
        else:
            p = np.clip(np.searchsorted(t, starts, side="right") - 1, 0, m - 1)
            dtp = t[p + 1] - t[p]
            aa = (starts - t[p]) / dtp
            ab = (ends - t[p]) / dtp
        dt = ends - starts
        g = gap[p]
        mv = ~g
        dP = pb - pa
        xa = pa[p] + np.where(mv, aa, 0.0)[:, None] * dP[p]
        xb = pa[p] + np.where(mv, ab, 0.0)[:, None] * dP[p]
        path = np.abs(xb - xa)
        if va is not None:
            dV = vb - va
            v0 = va[p] + aa[:, None] * dV[p]
            v1 = va[p] + ab[:, None] * dV[p]
            has_v = np.isfinite(v0[0]) if v0.shape[0] else np.zeros(0, bool)
            if has_v.any():
                pv = _abs_integral(v0[:, has_v], v1[:, has_v], dt[:, None]) / 60.0  # mm/min · s → mm
                path[:, has_v] = np.where(mv[:, None], pv, 0.0)
        dr = rb - ra
        r0 = ra[p] + aa * dr[p]
        r1 = ra[p] + ab * dr[p]
        spin = np.where(mv, 0.5 * (r0 + r1) * dt, 0.0)
        if aira.shape[1]:
            dA = airb - aira
            a0 = aira[p] + aa[:, None] * dA[p]
            a1 = aira[p] + ab[:, None] * dA[p]
            air = 0.5 * (a0 + a1) * dt[:, None]
        else:
            air = np.zeros((dt.size, 0))
        # increment of each sub-interval (robust against rounding at the boundaries)
        k = np.floor((starts - o) / T).astype(np.int64)
        k += starts >= o + (k + 1) * T
        k -= starts < o + k * T
        kmin, kmax = int(k[0]), int(k[-1])
        if kmax + 1 > self.cap:
            self._alloc(max(2 * self.cap, kmax + 1))
        L = kmax - kmin + 1
        kl = k - kmin
        sl = slice(kmin, kmax + 1)
        self.dur[sl] += np.bincount(kl, dt, L)
        self.gap[sl] += np.bincount(kl, np.where(g, dt, 0.0), L)
        self.spin[sl] += np.bincount(kl, spin, L)
        for j in range(path.shape[1]):
            self.path[sl, j] += np.bincount(kl, path[:, j], L)
        for j in range(air.shape[1]):
            self.air[sl, j] += np.bincount(kl, air[:, j], L)
        nb = int(self.bin_off[-1])
        for j, e in enumerate(self.edges):
            i, b, w = _time_in_bins(xa[:, j], xb[:, j], dt, e)
            flat = kl[i] * nb + self.bin_off[j] + b
            self.bins[sl] += np.bincount(flat, w, L * nb).reshape(L, nb)
        if self.nl:
            self._add_energy(kl, sl, L, g, mv, dt, path, r0, r1, xa, xb)
        self.nk = max(self.nk, kmax + 1)
        self.t_last = float(t[-1])

    def _add_energy(self, kl, sl, L, g, mv, dt, path, r0, r1, xa, xb) -> None:
        """∫ P(f(t)) dt of the nonlinear sources; f is constant on a sub-interval (linear spindle: trapezoid)."""
        m = self.machine
        vmax = np.array([a.max_feed_mm_min for a in self.axes]) / 60.0
        nmax = m.spindle_max_speed_rpm
        with np.errstate(invalid="ignore", divide="ignore"):
            f_axis = np.where((dt > 0)[:, None], path / (vmax[None, :] * dt[:, None]), 0.0)
        for src, d, off in self.nl:
            if d < 0:
                e = 0.5 * (m.source_power_W(src, r0 / nmax) + m.source_power_W(src, r1 / nmax)) * dt
                e = np.where(mv, e, m.source_power_W(src, 0.0) * dt)
                self.energy[sl, off] += np.bincount(kl, e, L)
                continue
            p = m.source_power_W(src, f_axis[:, d])
            if src.kind == "fixed":
                self.energy[sl, off] += np.bincount(kl, p * dt, L)
                continue
            a = [x.name for x in self.axes].index(src.axis)
            i, b, w = _time_in_bins(xa[:, a], xb[:, a], dt, self.edges[a])
            nseg = self.axes[a].n_segments
            flat = kl[i] * nseg + b // self.bps
            self.energy[sl, off : off + nseg] += np.bincount(flat, w * p[i], L * nseg).reshape(L, nseg)

    def result(self, rows: int = 0, dropped: int = 0) -> Increments:
        if self.origin is None or self.t_last is None:
            raise ValueError("no motion: a trace needs at least two samples")
        nk = self.nk
        if nk >= 2 and self.t_last - (self.origin + (nk - 1) * self.T) < 1e-6 * self.T:
            # a rounding crumb after the last boundary (a programme of exactly n increments): fold it into the one before
            for name in ("dur", "path", "spin", "air", "gap", "bins", "energy"):
                arr = getattr(self, name)
                arr[nk - 2] += arr[nk - 1]
                arr[nk - 1] = 0
            nk -= 1
        start = self.origin + np.arange(nk) * self.T
        end = np.minimum(start + self.T, self.t_last)
        end[-1] = self.t_last
        D = self.dur[:nk]
        vmax = np.array([a.max_feed_mm_min for a in self.axes]) / 60.0
        nmax = self.machine.spindle_max_speed_rpm
        bins = self.bins[:nk]
        return Increments(
            start_s=start,
            end_s=end,
            increment_s=self.T,
            axis_names=tuple(a.name for a in self.axes),
            axis_factor=self.path[:nk] / (vmax[None, :] * D[:, None]),
            bin_edges_mm=tuple(self.edges),
            bin_time_s=tuple(bins[:, self.bin_off[j] : self.bin_off[j + 1]].copy() for j in range(len(self.axes))),
            bins_per_segment=self.bps,
            spindle_factor=self.spin[:nk] / (nmax * D) if nmax > 0 else np.zeros(nk),
            air_names=self.air_names,
            air_degC=self.air[:nk] / D[:, None],
            initial_air_degC=self.initial_air,
            gap_s=self.gap[:nk].copy(),
            rows=rows,
            dropped_rows=dropped,
            mean_power_inputs=tuple(self.nl_names),
            mean_power_W=self.energy[:nk] / D[:, None],
        )


@dataclass
class _GapLog:
    count: int = 0
    total_s: float = 0.0
    first_line: int = -1


class _SampleFeeder:
    """Checks consecutive trace samples and feeds the intervals between them to an :class:`_Integrator`."""

    def __init__(self, machine, integ: _Integrator, source: str, max_gap_s, feed_tolerance, travel_tolerance_mm):
        self.m = machine
        self.integ = integ
        self.src = source
        self.max_gap_s = float(max_gap_s)
        self.ftol = float(feed_tolerance)
        self.ttol = float(travel_tolerance_mm)
        self.prev: Samples | None = None
        self.gaps = _GapLog()
        self.lo = np.array([a.travel_mm[0] for a in machine.axes])
        self.hi = np.array([a.travel_mm[1] for a in machine.axes])
        self.vmax = np.array([a.max_feed_mm_min for a in machine.axes])
        if not self.max_gap_s > 0:
            raise ValueError(f"max_gap_s must be positive, got {max_gap_s!r}")
        if not self.ftol >= 0 or not self.ttol >= 0:
            raise ValueError(f"tolerances must not be negative, got {feed_tolerance!r}, {travel_tolerance_mm!r}")

    def _err(self, line, msg) -> TraceFileError:
        return TraceFileError(f"{self.src}: line {int(line)}: {msg}")

    def _check_rows(self, s: Samples) -> Samples:
        P = s.position_mm
        out = (P < self.lo - self.ttol) | (P > self.hi + self.ttol)
        if out.any():
            i, a = np.argwhere(out)[0]
            ax = self.m.axes[a]
            raise self._err(
                s.line[i],
                f"{position_column(ax.name)} = {P[i, a]:g} mm is outside the travel {list(ax.travel_mm)} mm of axis {ax.name}",
            )
        P = np.clip(P, self.lo, self.hi)
        r = np.abs(s.spindle_rpm)
        nmax = self.m.spindle_max_speed_rpm
        if nmax > 0:
            over = r > nmax * (1 + self.ftol)
            if over.any():
                i = int(np.argmax(over))
                raise self._err(s.line[i], f"spindle_rpm = {s.spindle_rpm[i]:g} is above [spindle] max_speed_rpm {nmax:g}")
        else:
            r = np.zeros_like(r)
        V = s.velocity_mm_min
        if V is not None:
            over = np.abs(V) > self.vmax * (1 + self.ftol)  # NaN (no column) compares False
            if over.any():
                i, a = np.argwhere(over)[0]
                ax = self.m.axes[a]
                raise self._err(
                    s.line[i],
                    f"{velocity_column(ax.name)} = {V[i, a]:g} mm/min is above the max_feed_mm_min {ax.max_feed_mm_min:g} "
                    f"of axis {ax.name} (tolerance {100 * self.ftol:g} %)",
                )
        return Samples(s.time_s, P, V, r, s.air_names, s.air_degC, s.line)

    def feed(self, s: Samples) -> None:
        if not len(s):
            return
        s = self._check_rows(s)
        if self.prev is not None:
            s = _concat(self.prev, s)
        t = s.time_s
        dt = np.diff(t)
        back = np.flatnonzero(~(dt > 0))
        if back.size:
            i = int(back[0])
            raise self._err(s.line[i + 1], f"time_s {t[i + 1]:g} does not increase after {t[i]:g} (line {int(s.line[i])})")
        gap = dt > self.max_gap_s
        if gap.any():
            if self.gaps.count == 0:
                self.gaps.first_line = int(s.line[np.argmax(gap) + 1])
            self.gaps.count += int(gap.sum())
            self.gaps.total_s += float(dt[gap].sum())
        P = s.position_mm
        speed = np.abs(np.diff(P, axis=0)) / dt[:, None] * 60.0
        over = (speed > self.vmax * (1 + self.ftol)) & ~gap[:, None]
        if over.any():
            i, a = np.argwhere(over)[0]
            ax = self.m.axes[a]
            raise self._err(
                s.line[i + 1],
                f"axis {ax.name} moves {P[i + 1, a] - P[i, a]:g} mm in {dt[i]:g} s since line {int(s.line[i])}, "
                f"{speed[i, a]:.0f} mm/min, above its max_feed_mm_min {ax.max_feed_mm_min:g} (tolerance {100 * self.ftol:g} %)",
            )
        V = s.velocity_mm_min
        self.integ.add(
            t,
            P[:-1],
            P[1:],
            gap,
            s.spindle_rpm[:-1],
            s.spindle_rpm[1:],
            s.air_degC[:-1],
            s.air_degC[1:],
            None if V is None else V[:-1],
            None if V is None else V[1:],
        )
        self.prev = s.take(slice(-1, None))


def _concat(a: Samples, b: Samples) -> Samples:
    if a.air_names != b.air_names:
        raise ValueError("samples with different air columns cannot be joined")
    V = None
    if a.velocity_mm_min is not None or b.velocity_mm_min is not None:
        na = a.position_mm.shape[1]
        V = np.concatenate(
            [x.velocity_mm_min if x.velocity_mm_min is not None else np.full((len(x), na), np.nan) for x in (a, b)]
        )
    return Samples(
        np.concatenate([a.time_s, b.time_s]),
        np.concatenate([a.position_mm, b.position_mm]),
        V,
        np.concatenate([a.spindle_rpm, b.spindle_rpm]),
        a.air_names,
        np.concatenate([a.air_degC, b.air_degC]),
        np.concatenate([a.line, b.line]),
    )


def increments_from_samples(
    machine: Machine,
    chunks: Samples | Iterable[Samples],
    increment_s: float = DEFAULT_INCREMENT_S,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    feed_tolerance: float = DEFAULT_FEED_TOLERANCE,
    travel_tolerance_mm: float = DEFAULT_TRAVEL_TOLERANCE_MM,
    bins_per_segment: int = DEFAULT_BINS_PER_SEGMENT,
    source: str = "<trace>",
    stats: ReadStats | None = None,
) -> Increments:
    """Increments of a trace given as :class:`Samples` (one or a stream of chunks in time order).

    Parameters
    ----------
    machine : axes (travel, max feed, rail segments) and spindle max speed
    chunks : trace samples
    increment_s : increment length [s]
    max_gap_s : a sample interval longer than this is a recording gap, counted as standstill [s]
    feed_tolerance : relative excess over ``max_feed_mm_min`` / ``max_speed_rpm`` tolerated [-]
    travel_tolerance_mm : positions this far outside the travel are clipped, farther is an error [mm]
    bins_per_segment : histogram bins per rail segment
    source : file name used in messages

    Raises
    ------
    TraceFileError
        naming the line for time going backwards, positions outside the travel,
        feeds or spindle speeds above the machine's maximum.
    """
    if isinstance(chunks, Samples):
        chunks = [chunks]
    integ = None
    feeder = None
    for s in chunks:
        if integ is None:
            integ = _Integrator(machine, increment_s, bins_per_segment, s.air_names)
            feeder = _SampleFeeder(machine, integ, source, max_gap_s, feed_tolerance, travel_tolerance_mm)
        feeder.feed(s)
    if integ is None or integ.origin is None:
        raise TraceFileError(f"{source}: needs at least two valid samples")
    rows = stats.rows if stats is not None else 0
    dropped = stats.dropped if stats is not None else 0
    if feeder.gaps.count:
        msg = (
            f"{source}: {feeder.gaps.count} gap(s) longer than {max_gap_s:g} s (total {feeder.gaps.total_s:g} s, "
            f"first ending at line {feeder.gaps.first_line}) counted as standstill"
        )
        log.warning(msg)
        warnings.warn(msg, TraceWarning, stacklevel=2)
    return integ.result(rows, dropped)


def increments_from_trace(
    path: str | Path,
    machine: Machine,
    increment_s: float = DEFAULT_INCREMENT_S,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    feed_tolerance: float = DEFAULT_FEED_TOLERANCE,
    travel_tolerance_mm: float = DEFAULT_TRAVEL_TOLERANCE_MM,
    bins_per_segment: int = DEFAULT_BINS_PER_SEGMENT,
    max_dropped_fraction: float = DEFAULT_MAX_DROPPED_FRACTION,
    chunk_rows: int | None = None,
) -> Increments:
    """Increments of a trace CSV, streamed in chunks (see :func:`increments_from_samples`).

    Rows with NaN in a column that is read are dropped with one :class:`TraceWarning`
    giving their number and the first line; more than ``max_dropped_fraction``
    of the rows dropped is an error.
    """
    path = Path(path)
    stats = ReadStats()
    kw = {} if chunk_rows is None else {"chunk_rows": chunk_rows}
    inc = increments_from_samples(
        machine,
        read_trace_chunks(path, machine, stats=stats, **kw),
        increment_s,
        max_gap_s,
        feed_tolerance,
        travel_tolerance_mm,
        bins_per_segment,
        source=str(path),
        stats=stats,
    )
    if stats.dropped:
        if stats.dropped > max_dropped_fraction * stats.rows:
            raise TraceFileError(
                f"{path}: {stats.dropped} of {stats.rows} rows have NaN or empty fields (first at line "
                f"{stats.first_dropped_line}), more than {100 * max_dropped_fraction:g} %"
            )
        msg = (f"{path}: dropped {stats.dropped} of {stats.rows} rows with NaN or empty fields "
               f"(first at line {stats.first_dropped_line})")
        log.warning(msg)
        warnings.warn(msg, TraceWarning, stacklevel=2)
    return inc
