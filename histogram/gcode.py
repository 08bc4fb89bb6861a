"""G-code programmes turned into machine motion (a trace at the programme's own breakpoints).

Supported words (RS274/NGC style, one block per line, case-insensitive):

==========================  ================================================================
``G0``                      rapid: straight line, every axis at most at its ``max_feed_mm_min``
                            (the slowest axis sets the time, as a linear-interpolated rapid)
``G1`` ``F``                straight line at the programmed path feed ``F`` [mm/min or in/min]
``G2`` / ``G3``             arc clockwise / counter-clockwise in the active plane, centre by
                            ``I J K`` (incremental from the start) or radius ``R`` (negative:
                            the arc over 180°); a move along the plane normal makes a helix
``G4 P``                    dwell ``P`` seconds (axes stand, the spindle keeps turning)
``G17`` ``G18`` ``G19``     arc plane XY, ZX, YZ
``G20`` ``G21``             inch / millimetre input
``G90`` ``G91``             absolute / incremental positions
``G94``                     feed per minute (the only feed mode)
``S`` ``M3`` ``M4`` ``M5``  spindle speed [1/min], on clockwise / counter-clockwise, off
``M6`` ``T``, ``M8`` ``M9`` tool change, coolant on/off: accepted, no time and no heat
``M2`` ``M30``              end of programme (the rest is not read)
``N``                       block number (ignored)
comments                    ``( ... )`` and from ``;`` to the end of the line; ``%`` lines
==========================  ================================================================

Positions are the machine's axis positions [mm] (the machine file's axis
coordinates, no work offsets); the axis letters are the machine's one-letter
axis names. The programme starts at ``start_mm`` (default: every axis at 0 mm)
with the spindle off. Axes move at constant speed with instantaneous
acceleration; arcs are split into chords no more than 1 µm from the arc.
Any other word, a feed above an axis' ``max_feed_mm_min``, a spindle speed
above ``[spindle] max_speed_rpm``, a target outside the travel, ``G1`` without
a feed or an arc whose end is not on its circle is a :class:`GcodeError`
naming the file, the line and the word.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridcomp.histogram.increments import (
    DEFAULT_BINS_PER_SEGMENT,
    DEFAULT_INCREMENT_S,
    Increments,
    _Integrator,
)
from hybridcomp.histogram.trace import Samples, TraceFileError
from hybridcomp.models.machine import Machine
from hybridcomp.models.toml import read_text

CHORD_TOLERANCE_MM = 1e-3
ARC_RADIUS_TOLERANCE_MM = 2e-3
GCODE_SUFFIXES = (".nc", ".ngc", ".gcode", ".gc", ".tap", ".cnc", ".mpf", ".g")

_WORD = re.compile(r"([A-Z])\s*([+-]?(?:\d+\.?\d*|\.\d+))")
_G_SUPPORTED = {0, 1, 2, 3, 4, 17, 18, 19, 20, 21, 90, 91, 94}
_M_SUPPORTED = {2, 3, 4, 5, 6, 8, 9, 30}
_PLANES = {17: ("X", "Y", "Z", "I", "J"), 18: ("Z", "X", "Y", "K", "I"), 19: ("Y", "Z", "X", "J", "K")}


class GcodeError(TraceFileError):
    """A G-code programme is invalid or cannot run on the machine; the message names the file, line and word."""


@dataclass(frozen=True)
class Motion:
    """Piecewise-linear machine motion: breakpoints and what holds between them.

    Attributes
    ----------
    time_s : breakpoint times [s] (n+1,), strictly increasing
    position_mm : axis positions at the breakpoints [mm] (n+1 × n_axes)
    spindle_rpm : spindle speed during each interval [1/min] (n,)
    line : programme line of each interval (n,)
    axis_names : machine axis names (column order)
    """

    time_s: np.ndarray
    position_mm: np.ndarray
    spindle_rpm: np.ndarray
    line: np.ndarray
    axis_names: tuple[str, ...]

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0])


def _fmt(v: float) -> str:
    return f"{v:g}"


@dataclass(frozen=True)
class _Programme:
    """What every block of a programme is read against: the machine's axes and the file's name."""

    source: str
    machine_name: str
    axes: tuple
    letters: dict[str, int]
    allowed: frozenset[str]
    lo: np.ndarray
    hi: np.ndarray
    vmax: np.ndarray
    nmax: float

    def err(self, ln: int, msg: str) -> GcodeError:
        return GcodeError(f"{self.source}: line {ln}: {msg}")


@dataclass(frozen=True)
class _Block:
    """One block (line) of a programme: its number, text, value words and G and M words in the order written."""

    ln: int
    raw: str
    words: dict[str, float]
    gs: tuple[int, ...]
    ms: tuple[int, ...]


@dataclass(frozen=True)
class _State:
    """The interpreter's modal state after a block: position [mm], time [s], units, feed, plane and spindle."""

    pos: np.ndarray
    t: float = 0.0
    feed: float | None = None  # mm/min
    scale: float = 1.0  # mm per input unit
    absolute: bool = True
    plane: int = 17
    motion_mode: int | None = None
    s_word: float = 0.0
    spindle_on: bool = False
    rpm: float = 0.0


def parse_gcode(text: str, machine: Machine, source: str = "<gcode>", start_mm: dict[str, float] | None = None) -> Motion:
    """Run a G-code programme on ``machine`` and return its motion.

    Parameters
    ----------
    text : the programme
    machine : axes (letters, travel, max feed) and spindle max speed
    source : file name used in messages
    start_mm : axis positions at the start [mm] (default 0 mm, the reference pose)

    Raises
    ------
    GcodeError
        naming the line and the word (see the module docstring).
    """
    prog = _programme(machine, source)
    state = _State(pos=_start_position(machine, prog, start_mm))
    T: list[float] = [0.0]
    Pts: list[list[float]] = [state.pos.tolist()]
    R: list[float] = []
    Ln: list[int] = []
    for ln, raw in enumerate(text.splitlines(), start=1):
        block = _read_block(prog, ln, raw)
        if block is None:
            continue
        state = _modal(prog, state, block)
        state, times, points = _execute(prog, state, block)
        T.extend(times.tolist())
        Pts.extend(points.tolist())
        R.extend([state.rpm] * times.size)
        Ln.extend([ln] * times.size)
        if 2 in block.ms or 30 in block.ms:
            break
    if len(T) < 2:
        raise GcodeError(f"{source}: the programme never moves nor dwells (no time passes)")
    return Motion(np.asarray(T), np.asarray(Pts), np.asarray(R), np.asarray(Ln, np.int64),
                  tuple(a.name for a in machine.axes))


def _programme(machine: Machine, source: str) -> _Programme:
    """The machine's axes as the interpreter reads them: letters, travel [mm], max feed [mm/min], max speed [rpm]."""
    axes = machine.axes
    letters = {a.name.upper(): i for i, a in enumerate(axes) if len(a.name) == 1}
    return _Programme(
        source=source,
        machine_name=machine.name,
        axes=axes,
        letters=letters,
        allowed=frozenset("GMFSPNTIJKR") | frozenset(letters),
        lo=np.array([a.travel_mm[0] for a in axes]),
        hi=np.array([a.travel_mm[1] for a in axes]),
        vmax=np.array([a.max_feed_mm_min for a in axes]),
        nmax=machine.spindle_max_speed_rpm,
    )


def _start_position(machine: Machine, prog: _Programme, start_mm: dict[str, float] | None) -> np.ndarray:
    """The axis positions at the start [mm]: ``start_mm``, 0 mm for every axis it does not name."""
    names = [a.name for a in machine.axes]
    pos = np.zeros(len(names))
    for k, v in (start_mm or {}).items():
        if k not in names:
            raise ValueError(f"start_mm names axis {k!r}, which machine {machine.name!r} has not")
        pos[names.index(k)] = float(v)
    if np.any(pos < prog.lo) or np.any(pos > prog.hi):
        raise ValueError(f"start_mm {dict(zip(names, pos.tolist()))} is outside the travel")
    return pos


def _read_block(prog: _Programme, ln: int, raw: str) -> _Block | None:
    """The words of one line, comments removed; None for a line without words."""
    s = raw.upper()
    if "(" in s or ")" in s:
        if s.count("(") != s.count(")") or re.search(r"\([^)]*\(", s):
            raise prog.err(ln, f"unbalanced comment parentheses in {raw.strip()!r}")
        s = re.sub(r"\([^)]*\)", " ", s)
    s = s.split(";", 1)[0].strip()
    if not s or s == "%":
        return None
    words: dict[str, float] = {}
    gs: list[int] = []
    ms: list[int] = []
    end = 0
    for mt in _WORD.finditer(s):
        gap = s[end : mt.start()].strip()
        if gap:
            raise prog.err(ln, f"cannot read {gap!r} in {raw.strip()!r}")
        end = mt.end()
        letter, val = mt.group(1), float(mt.group(2))
        word = f"{letter}{mt.group(2)}"
        if letter not in prog.allowed:
            what = "an axis the machine has not" if letter in "XYZABCUVW" else "an unknown word"
            raise prog.err(ln, f"{word!r} is {what} (machine {prog.machine_name!r}, supported: G M F S P N T I J K R "
                           f"{' '.join(sorted(prog.letters))})")
        if letter == "G":
            if val != int(val) or int(val) not in _G_SUPPORTED:
                raise prog.err(ln, f"{word!r} is an unknown G-code word (supported: {sorted(_G_SUPPORTED)})")
            gs.append(int(val))
        elif letter == "M":
            if val != int(val) or int(val) not in _M_SUPPORTED:
                raise prog.err(ln, f"{word!r} is an unknown M-code word (supported: {sorted(_M_SUPPORTED)})")
            ms.append(int(val))
        else:
            if letter in words:
                raise prog.err(ln, f"word {letter} appears twice")
            words[letter] = val
    rest = s[end:].strip()
    if rest:
        raise prog.err(ln, f"cannot read {rest!r} in {raw.strip()!r}")
    return _Block(ln, raw, words, tuple(gs), tuple(ms))


def _modal(prog: _Programme, state: _State, block: _Block) -> _State:
    """The modal settings of a block, before its motion: units, positioning, plane, feed, spindle speed and M words."""
    ln, words = block.ln, block.words
    scale, absolute, plane = state.scale, state.absolute, state.plane
    feed, s_word, spindle_on, rpm = state.feed, state.s_word, state.spindle_on, state.rpm
    for g in block.gs:
        if g in (20, 21):
            scale = 25.4 if g == 20 else 1.0
        elif g in (90, 91):
            absolute = g == 90
        elif g in (17, 18, 19):
            plane = g
    if "F" in words:
        if not words["F"] > 0:
            raise prog.err(ln, f"feed F{_fmt(words['F'])} must be positive")
        feed = words["F"] * scale
    if "S" in words:
        if words["S"] < 0:
            raise prog.err(ln, f"spindle speed S{_fmt(words['S'])} must not be negative")
        if prog.nmax > 0 and words["S"] > prog.nmax * (1 + 1e-9):
            raise prog.err(ln, f"spindle speed S{_fmt(words['S'])} is above [spindle] max_speed_rpm {_fmt(prog.nmax)}")
        s_word = words["S"]
        if spindle_on:
            rpm = s_word
    for mc in block.ms:
        if mc in (3, 4):
            spindle_on, rpm = True, s_word
        elif mc == 5:
            spindle_on, rpm = False, 0.0
    if prog.nmax <= 0:
        rpm = 0.0
    return dataclasses.replace(state, scale=scale, absolute=absolute, plane=plane, feed=feed, s_word=s_word,
                               spindle_on=spindle_on, rpm=rpm)


_NONE = (np.zeros(0), np.zeros((0, 0)))


def _execute(prog: _Programme, state: _State, block: _Block) -> tuple[_State, np.ndarray, np.ndarray]:
    """A block's dwell or motion: the new state and the breakpoints it adds (times [s], positions [mm])."""
    ln, words, gs = block.ln, block.words, block.gs
    motions = [g for g in gs if g in (0, 1, 2, 3)]
    if len(motions) > 1 or (motions and 4 in gs):
        raise prog.err(ln, f"more than one motion word (G{', G'.join(map(str, motions + ([4] if 4 in gs else [])))})")
    axis_words = {k: v for k, v in words.items() if k in prog.letters}
    if 4 in gs:
        if axis_words:
            raise prog.err(ln, "G4 (dwell) cannot move axes on the same line")
        if "P" not in words or words["P"] < 0:
            raise prog.err(ln, "G4 needs a dwell time P >= 0 [s]")
        if words["P"] > 0:
            t = state.t + words["P"]
            return dataclasses.replace(state, t=t), np.array([t]), state.pos[None, :]
        return state, *_NONE
    if "P" in words:
        raise prog.err(ln, f"word P{_fmt(words['P'])} is only used with G4")
    if motions:
        state = dataclasses.replace(state, motion_mode=motions[0])
    motion_mode = state.motion_mode
    arc_words = {k for k in "IJKR" if k in words}
    if arc_words and motion_mode not in (2, 3):
        raise prog.err(ln, f"words {sorted(arc_words)} need G2 or G3")
    if not (axis_words or (motion_mode in (2, 3) and arc_words)):
        return state, *_NONE
    if motion_mode is None:
        raise prog.err(ln, "axis words without a motion mode (G0, G1, G2, G3)")
    return _move(prog, state, block, axis_words)


def _move(prog: _Programme, state: _State, block: _Block, axis_words: dict[str, float]):
    """A G0, G1, G2 or G3 move to the block's target: the new state and its breakpoints (see :func:`_execute`)."""
    ln, pos, t, feed, scale = block.ln, state.pos, state.t, state.feed, state.scale
    target = pos.copy()
    for k, v in axis_words.items():
        i = prog.letters[k]
        target[i] = v * scale if state.absolute else pos[i] + v * scale
    _check_target(prog, ln, target)
    times, pts = _NONE
    if state.motion_mode == 0:
        d = np.abs(target - pos)
        if d.max() > 0:
            t += float(np.max(d / prog.vmax)) * 60.0
            times, pts = np.array([t]), target[None, :]
    elif state.motion_mode == 1:
        if feed is None:
            raise prog.err(ln, "G1 without a feed F")
        d = target - pos
        L = float(np.sqrt(np.sum(d * d)))
        if L > 0:
            dt = L / feed * 60.0
            v = np.abs(d) / dt * 60.0
            _check_speed(prog.err, ln, prog.axes, v, prog.vmax, feed)
            t += dt
            times, pts = np.array([t]), target[None, :]
    else:
        if feed is None:
            raise prog.err(ln, f"G{state.motion_mode} without a feed F")
        times, pts = _arc(prog.err, ln, state.motion_mode, state.plane, prog.letters, pos, target, block.words, scale,
                          feed, prog.axes, prog.vmax)
        times += t
        for p in pts:
            _check_target(prog, ln, p)
        t = float(times[-1])
    return dataclasses.replace(state, pos=target, t=t), times, pts


def _check_target(prog: _Programme, ln: int, target: np.ndarray) -> None:
    bad = np.flatnonzero((target < prog.lo - 1e-6) | (target > prog.hi + 1e-6))
    if bad.size:
        a = prog.axes[bad[0]]
        raise prog.err(ln, f"{a.name} = {_fmt(target[bad[0]])} mm is outside the travel {list(a.travel_mm)} mm of axis "
                       f"{a.name}")


def _check_speed(err, ln, axes, v, vmax, feed):
    over = np.flatnonzero(v > vmax * (1 + 1e-9))
    if over.size:
        a = axes[over[0]]
        raise err(ln, f"feed F{_fmt(feed)} mm/min moves axis {a.name} at {v[over[0]]:.0f} mm/min, above its "
                  f"max_feed_mm_min {_fmt(a.max_feed_mm_min)}")


def _arc(err, ln, mode, plane, letters, pos, target, words, scale, feed, axes, vmax):
    """Chord points and their times (from 0) of a G2/G3 arc or helix."""
    a_l, b_l, n_l, i_l, j_l = _PLANES[plane]
    for L in (a_l, b_l):
        if L not in letters:
            raise err(ln, f"G{mode} in plane G{plane} needs axis {L}, which the machine has not")
    ia, ib = letters[a_l], letters[b_l]
    i_n = letters.get(n_l)
    a0, b0, a1, b1 = pos[ia], pos[ib], target[ia], target[ib]
    cw = mode == 2
    if "R" in words:
        if i_l in words or j_l in words:
            raise err(ln, "an arc takes either R or the centre offsets, not both")
        r_w = words["R"] * scale
        dx, dy = a1 - a0, b1 - b0
        d = math.hypot(dx, dy)
        if d == 0 or r_w == 0:
            raise err(ln, f"an R arc needs distinct start and end points and R != 0, got R{_fmt(words['R'])}")
        if d > 2 * abs(r_w) + ARC_RADIUS_TOLERANCE_MM:
            raise err(ln, f"R{_fmt(words['R'])} is too small for a chord of {d:.4g} mm")
        h = math.sqrt(max(r_w * r_w - d * d / 4, 0.0))
        side = (1.0 if not cw else -1.0) * (1.0 if r_w > 0 else -1.0)
        ca = 0.5 * (a0 + a1) - side * h * dy / d
        cb = 0.5 * (b0 + b1) + side * h * dx / d
    else:
        ca = a0 + words.get(i_l, 0.0) * scale
        cb = b0 + words.get(j_l, 0.0) * scale
    r0 = math.hypot(a0 - ca, b0 - cb)
    r1 = math.hypot(a1 - ca, b1 - cb)
    if r0 == 0 or abs(r0 - r1) > max(ARC_RADIUS_TOLERANCE_MM, 1e-6 * r0):
        raise err(ln, f"arc end is not on its circle: radius {r0:.4f} mm at the start, {r1:.4f} mm at the end")
    th0 = math.atan2(b0 - cb, a0 - ca)
    th1 = math.atan2(b1 - cb, a1 - ca)
    full = math.hypot(a1 - a0, b1 - b0) < 1e-9
    if cw:
        dth = -((th0 - th1) % (2 * math.pi))
        if full or dth == 0:
            dth = -2 * math.pi
    else:
        dth = (th1 - th0) % (2 * math.pi)
        if full or dth == 0:
            dth = 2 * math.pi
    dn = (target[i_n] - pos[i_n]) if i_n is not None else 0.0
    length = math.hypot(r0 * dth, dn)
    duration = length / feed * 60.0
    step = 2 * math.acos(max(1 - CHORD_TOLERANCE_MM / r0, -1.0)) if r0 > CHORD_TOLERANCE_MM else math.pi / 2
    n = int(min(max(1, math.ceil(abs(dth) / step)), 100_000))
    f = np.arange(1, n + 1) / n
    pts = np.repeat(pos[None, :], n, axis=0)
    pts[:, ia] = ca + r0 * np.cos(th0 + dth * f)
    pts[:, ib] = cb + r0 * np.sin(th0 + dth * f)
    if i_n is not None:
        pts[:, i_n] = pos[i_n] + dn * f
    pts[-1] = target
    times = duration * f
    # peak axis speed on the arc: the path feed times the share of that axis' direction
    peak = np.zeros(len(axes))
    peak[ia] = peak[ib] = feed * r0 * abs(dth) / length
    if i_n is not None:
        peak[i_n] = feed * abs(dn) / length
    _check_speed(err, ln, axes, peak, vmax, feed)
    return times, pts


def read_gcode(path: str | Path, machine: Machine, start_mm: dict[str, float] | None = None) -> Motion:
    """Read and run a G-code file (see :func:`parse_gcode`)."""
    path = Path(path)
    text = read_text(path, GcodeError, "G-code")
    return parse_gcode(text, machine, source=str(path), start_mm=start_mm)


def increments_from_motion(
    machine: Machine,
    motion: Motion,
    increment_s: float = DEFAULT_INCREMENT_S,
    bins_per_segment: int = DEFAULT_BINS_PER_SEGMENT,
    air_degC: dict | None = None,
) -> Increments:
    """Increments of a programme's motion, integrated exactly between its breakpoints (no sampling).

    Parameters
    ----------
    machine : the machine the motion ran on
    motion : from :func:`parse_gcode`
    increment_s : increment length [s]
    bins_per_segment : histogram bins per rail segment
    air_degC : optional air temperatures to pass through, trace column (``Tamb_degC`` ...) → function of
        time [s] → [°C]; taken at the breakpoints and linear between them
    """
    if motion.axis_names != tuple(a.name for a in machine.axes):
        raise ValueError(f"motion is for axes {motion.axis_names}, machine {machine.name!r} has other axes")
    names = tuple(air_degC or {})
    integ = _Integrator(machine, increment_s, bins_per_segment, names)
    P = motion.position_mm
    n = motion.spindle_rpm.size
    r = np.abs(motion.spindle_rpm)
    if names:
        A = np.column_stack([np.asarray(f(motion.time_s), float) for f in air_degC.values()])
    else:
        A = np.zeros((n + 1, 0))
    integ.add(motion.time_s, P[:-1], P[1:], np.zeros(n, bool), r, r, A[:-1], A[1:])
    return integ.result(rows=n + 1)


def sample_motion(motion: Motion, rate_hz: float = 10.0, air_degC: dict | None = None) -> Samples:
    """A sampled trace of a motion at ``rate_hz``, as a controller's data logger would record it.

    Positions are interpolated linearly between breakpoints, the spindle speed
    is the one in force at the sample time. ``air_degC`` maps air columns
    (``Tamb_degC`` ...) to functions of time [s] → [°C].
    """
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
    t0, t1 = motion.time_s[0], motion.time_s[-1]
    n = int(math.floor((t1 - t0) * rate_hz + 1e-9)) + 1
    t = t0 + np.arange(n) / rate_hz
    if t1 - t[-1] > 1e-9:  # the last breakpoint is recorded too, so the trace covers the whole programme
        t = np.append(t, t1)
        n += 1
    P = np.column_stack([np.interp(t, motion.time_s, motion.position_mm[:, a]) for a in range(motion.position_mm.shape[1])])
    k = np.clip(np.searchsorted(motion.time_s, t, side="right") - 1, 0, motion.spindle_rpm.size - 1)
    r = motion.spindle_rpm[k]
    names = tuple(air_degC or {})
    A = np.column_stack([np.asarray(f(t), float) for f in air_degC.values()]) if names else np.zeros((n, 0))
    return Samples(t, P, None, r, names, A, np.arange(n) + 2)
