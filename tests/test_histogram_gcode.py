"""G-code to motion: exact times per segment, modal words, units, arcs, bad programmes; trace vs G-code."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridcomp.histogram import (
    GcodeError,
    heat_powers,
    increments_from_motion,
    increments_from_samples,
    parse_gcode,
    sample_motion,
)
from hybridcomp.histogram.scenarios import (
    WORKPIECES,
    basic_programs,
    jobshop_program,
    part_program,
)


@pytest.fixture(scope="module")
def jobshop(machine):
    """The job-shop day's motion, and its 5 min increments from the exact motion and from the 10 Hz trace."""
    motion = parse_gcode(jobshop_program(machine), machine)
    return (motion, increments_from_motion(machine, motion, 300),
            increments_from_samples(machine, sample_motion(motion, 10.0), 300))


SQUARE = """%
(a square at F6000 = 100 mm/s: X -300..300 and Y -250..250)
G21 G90 G94 G17
G0 X-300 Y-250     ; rapid to the corner
G1 X300 F6000
Y250
X-300
Y-250
M30
"""


def test_gcode_square_gives_exact_time_per_segment(machine):
    motion = parse_gcode(SQUARE, machine)
    # rapid: 300 mm in X and 250 mm in Y at 40,000 mm/min: X sets the time, 0.45 s
    rapid = 300 / (40000 / 60)
    assert motion.duration_s == pytest.approx(rapid + 6 + 5 + 6 + 5, rel=1e-14)
    inc = increments_from_motion(machine, motion, 100.0)
    assert len(inc) == 1
    # X segments (-400..-200..0..200..400): the rapid from 0 to -300 spends 300 mm in segments 3..2..1 proportionally;
    # the two X legs spend 1 s (100 mm) in segment 1 and 2 s in each of 2 and 3 and 1 s in 4; the Y legs stand at ±300 mm
    r = rapid / 300  # s per mm in the rapid
    x_expected = [1 + 1 + 5 + 100 * r, 2 + 2 + 200 * r, 2 + 2, 1 + 1 + 5]
    np.testing.assert_allclose(inc.segment_time_s("X")[0], x_expected, rtol=1e-12)
    # Y bounds (-325, -162.5, 0, 162.5, 325): the rapid from 0 to -250 in the same 0.45 s; the Y legs cross all
    # four segments (87.5, 162.5, 162.5, 87.5 mm at 100 mm/s), the first X leg stands at -250, the second at +250
    ry = rapid / 250
    y_expected = [0.875 * 2 + 6 + 87.5 * ry, 1.625 * 2 + 162.5 * ry, 1.625 * 2, 0.875 * 2 + 6]
    np.testing.assert_allclose(inc.segment_time_s("Y")[0], y_expected, rtol=1e-12)
    # factor: path / (v_max · duration)
    np.testing.assert_allclose(inc.axis_factor[0, :2], [(300 + 1200) / (40000 / 60) / motion.duration_s,
                                                        (250 + 1000) / (40000 / 60) / motion.duration_s], rtol=1e-12)


def test_dwell_gives_zero_and_spindle_words(machine):
    prog = "G0 X100\nS6000 M3\nG4 P600\nM5\nG4 P600\nS12000\nM4\nG4 P300\n"
    motion = parse_gcode(prog, machine)
    inc = increments_from_motion(machine, motion, 600)
    rapid = 100 / (40000 / 60)
    assert motion.duration_s == pytest.approx(1500 + rapid)
    # increment 1 holds the rapid and 600 - rapid s of dwell at 6000 rpm; increment 2 the rest, spindle off, then 12,000 rpm
    np.testing.assert_allclose(inc.axis_factor[:, 0], [100 / (40000 / 60) / 600, 0, 0], rtol=1e-12)
    np.testing.assert_array_equal(inc.axis_factor[:, 1:], 0)
    np.testing.assert_allclose(inc.spindle_factor, [(600 - rapid) * 0.5 / 600, rapid * 0.5 / 600,
                                                    300 / (300 + rapid)], rtol=1e-12)


def test_units_incremental_mode_and_comments(machine):
    prog = "G20 G91 (inch, incremental)\nG1 X2 F100 ; 2 in at 100 in/min\nX2\nG21 G90\nG1 Y-10 F600\n"
    m = parse_gcode(prog, machine)
    np.testing.assert_allclose(m.position_mm[-1], [101.6, -10.0, 0.0])
    np.testing.assert_allclose(m.time_s[1:], [1.2, 2.4, 3.4])  # 50.8 mm at 2540 mm/min, twice; 10 mm at 600 mm/min


def test_arcs_full_circle_helix_and_radius_form(machine):
    # full circle of radius 50 at F 3000 (50 mm/s): 2π·50/50 = 2π s; the centre is at (0, 0)
    m = parse_gcode("G0 X50 Y0\nG3 X50 Y0 I-50 J0 F3000\n", machine)
    rapid = 50 / (40000 / 60)
    assert m.duration_s == pytest.approx(rapid + 2 * math.pi, rel=1e-12)
    r = np.hypot(m.position_mm[1:, 0], m.position_mm[1:, 1])
    np.testing.assert_allclose(r, 50, rtol=1e-12)
    # chords within 1 µm of the arc
    mid = 0.5 * (m.position_mm[2:, :2] + m.position_mm[1:-1, :2])
    assert 50 - np.hypot(mid[:, 0], mid[:, 1]).min() < 1e-3 + 1e-9
    inc = increments_from_motion(machine, m, 1000)
    # X path of a full circle: 4 r = 200 mm (chords: slightly less), plus the rapid
    np.testing.assert_allclose(inc.axis_factor[0, 0] * (40000 / 60) * m.duration_s, 200 + 50, rtol=1e-5)
    # helix: one turn of radius 20 while Z drops 10 mm: length sqrt((2π 20)² + 10²)
    h = parse_gcode("G0 X20\nG2 X20 Y0 Z-10 I-20 J0 F1200\n", machine)
    assert h.duration_s == pytest.approx(20 / (40000 / 60) + math.hypot(2 * math.pi * 20, 10) / 20, rel=1e-12)
    assert h.position_mm[-1].tolist() == [20, 0, -10]
    # R form: a quarter circle counter-clockwise from (100, 0) to (0, 100) around (0, 0); R<0 the 3/4 arc
    q = parse_gcode("G0 X100\nG3 X0 Y100 R100 F6000\n", machine)
    assert q.duration_s == pytest.approx(100 / (40000 / 60) + 0.5 * math.pi * 100 / 100, rel=1e-12)
    q3 = parse_gcode("G0 X100\nG3 X0 Y100 R-100 F6000\n", machine)
    assert q3.duration_s == pytest.approx(100 / (40000 / 60) + 1.5 * math.pi * 100 / 100, rel=1e-12)


@pytest.mark.parametrize(
    "prog,match",
    [
        ("G54\nG0 X10\n", r"p\.nc: line 1: 'G54' is an unknown G-code word"),
        ("G0 X10\nG1 X20 Q5 F100\n", r"p\.nc: line 2: 'Q5' is an unknown word"),
        ("G0 A10\n", r"p\.nc: line 1: 'A10' is an axis the machine has not"),
        ("M7\n", r"p\.nc: line 1: 'M7' is an unknown M-code word"),
        ("G0 X10\nG1 X20\n", r"p\.nc: line 2: G1 without a feed F"),
        ("G1 X20 F50000\n", r"p\.nc: line 1: feed F50000 mm/min moves axis X at 50000 mm/min, above its max_feed_mm_min 40000"),
        ("S13000 M3\n", r"p\.nc: line 1: spindle speed S13000 is above \[spindle\] max_speed_rpm 12000"),
        ("G0 X0\nG0 X450\n", r"p\.nc: line 2: X = 450 mm is outside the travel \[-400\.0, 400\.0\] mm of axis X"),
        ("G0 X10\nG2 X30 Y0 I5 J0 F100\n", r"p\.nc: line 2: arc end is not on its circle"),
        ("G0 X10 (open comment\n", r"p\.nc: line 1: unbalanced comment parentheses"),
        ("G0 X10 X20\n", r"p\.nc: line 1: word X appears twice"),
        ("G4\n", r"p\.nc: line 1: G4 needs a dwell time P"),
        ("X10\n", r"p\.nc: line 1: axis words without a motion mode"),
        ("G0 X1 G1 Y1 F10\n", r"p\.nc: line 1: more than one motion word"),
        ("G0 X1 #5\n", r"p\.nc: line 1: cannot read '#5'"),
        ("(nothing)\n", r"p\.nc: the programme never moves"),
    ],
)
def test_bad_gcode_is_named(machine, prog, match):
    with pytest.raises(GcodeError, match=match):
        parse_gcode(prog, machine, source="p.nc")


def test_basic_programs_give_factor_one_and_equal_segments(machine):
    progs = basic_programs(machine, hours=0.25)
    assert set(progs) == {"X", "Y", "Z", "spindle"}
    for a in machine.axes:
        inc = increments_from_motion(machine, parse_gcode(progs[a.name], machine), 300)
        j = inc.axis_names.index(a.name)
        np.testing.assert_allclose(inc.axis_factor[:, j], 1.0, rtol=1e-9)
        # the first increment holds the rapid from 0 mm to the travel min (also at max feed); later ones whole strokes
        stroke = (a.travel_mm[1] - a.travel_mm[0]) / a.max_feed_mm_min * 60
        full = inc.duration_s > 0.999 * 300
        later = inc.segment_fraction(a.name)[1:][full[1:]]
        np.testing.assert_allclose(later, 0.25, atol=2 * stroke / 300)  # up to one round trip not whole
    sp = increments_from_motion(machine, parse_gcode(progs["spindle"], machine), 300)
    np.testing.assert_allclose(sp.spindle_factor, 1.0)
    np.testing.assert_array_equal(sp.axis_factor, 0.0)


def test_jobshop_day_is_16_h_of_eight_blocks(machine, jobshop):
    prog = jobshop_program(machine)
    blocks = [ln for ln in prog.splitlines() if ln.startswith("(block")]
    assert len(blocks) == 8 and len(WORKPIECES) == 8
    m, inc, _ = jobshop
    assert m.duration_s == pytest.approx(16 * 3600, abs=1e-3)
    assert len(inc) == 192
    busy = inc.spindle_factor > 0
    assert 0.4 < busy.mean() < 0.95  # pauses: set-up, load/unload, lunch
    # every block works a different region of the table: the X/Y position histograms of the blocks differ
    per_block = np.array([np.concatenate([inc.segment_fraction(a)[b * 24 : (b + 1) * 24].mean(0) for a in "XY"])
                          for b in range(8)])
    d = np.abs(per_block[:, None, :] - per_block[None, :, :]).sum(axis=2)
    assert d[~np.eye(8, dtype=bool)].min() > 0.05


def worst_source_deviation(machine, names, P1, P2) -> float:
    """Largest |P2 − P1| per increment, of a source or any of its segments, relative to the source's peak power in P1."""
    source = [n.split("[")[0].removesuffix("_W") for n in names]
    worst = 0.0
    for s in machine.heat_sources:
        idx = [i for i, n in enumerate(source) if n == s.name]
        peak = P1[:, idx].sum(axis=1).max()
        assert peak > 0, s.name  # every source works
        worst = max(worst, np.abs(P1[:, idx].sum(1) - P2[:, idx].sum(1)).max() / peak,
                    np.abs(P1[:, idx] - P2[:, idx]).max() / peak)
    return worst


def test_trace_and_its_gcode_give_the_same_bcs_within_1_percent(machine, jobshop):
    """The job-shop day as G-code (exact breakpoints) and as its 10 Hz trace: every heat input within 1 %.

    Criterion: per heat source, per increment, |P_trace − P_gcode| for the source and for each of its
    rail segments is at most 1 % of the source's peak power over the day.
    """
    _, exact, traced = jobshop
    names, P1 = heat_powers(machine, exact)
    _, P2 = heat_powers(machine, traced)
    assert worst_source_deviation(machine, names, P1, P2) <= 0.01
    np.testing.assert_allclose(traced.end_s, exact.end_s)


def test_part_programs_run_from_the_tool_change_position(machine):
    tc = {"X": 400.0, "Y": 325.0, "Z": 275.0}
    for wp in WORKPIECES:
        m = parse_gcode(part_program(machine, wp), machine, start_mm=tc)
        np.testing.assert_allclose(m.position_mm[-1], [400, 325, 275])
        assert m.spindle_rpm.max() > 0


def test_mean_power_puts_heat_where_and_when_it_is_dissipated(machine):
    """X strokes 200 mm in segment 1 at full feed for 150 s, rapids to 400 mm, stands; spindle on half the time."""
    strokes = "\n".join(f"X{-200 if k % 2 == 0 else -400}" for k in range(500))  # 500 strokes of 0.3 s, back at -400
    prog = f"S6000 M3\nG1 F40000\n{strokes}\nM5\nG0 X400\nG4 P148.8\n"
    motion = parse_gcode(prog, machine, start_mm={"X": -400.0})
    assert motion.duration_s == pytest.approx(300.0, rel=1e-12)
    inc = increments_from_motion(machine, motion, 300)
    names, Pf = heat_powers(machine, inc, "factor")
    _, Pm = heat_powers(machine, inc, "mean")
    col = names.index
    f = (500 * 200 + 800) / (40000 / 60) / 300  # path over v_max · 300 s = 0.504
    np.testing.assert_allclose(inc.axis_factor[0, 0], f, rtol=1e-12)
    # factor: P(f) split by the time fractions (segment 4 holds the 148.8 s standstill)
    np.testing.assert_allclose(Pf[0, col("x_nut[4]_W")], 30 * f * (0.3 + 148.8) / 300, rtol=1e-12)
    # mean: 30 W while moving, in the segment passed: 150 s + 0.3 s of rapid in segment 1, 0.3 s in each other
    np.testing.assert_allclose(Pm[0, [col(f"x_nut[{k}]_W") for k in range(1, 5)]], 30 * np.array([150.3, 0.3, 0.3, 0.3]) / 300,
                               rtol=1e-12)
    # the spindle runs 150 s at half speed: factor 0.25 → 110 W · 0.25^1.67; mean: 110 W · 0.5^1.67 for half the time
    np.testing.assert_allclose(Pf[0, col("spindle_bearing_front_W")], 110 * 0.25**1.67, rtol=1e-12)
    np.testing.assert_allclose(Pm[0, col("spindle_bearing_front_W")], 110 * 0.5**1.67 / 2, rtol=1e-12)
    # linear fixed sources are the same in both
    np.testing.assert_allclose(Pm[0, col("x_motor_W")], Pf[0, col("x_motor_W")])


def test_mean_power_heat_does_not_depend_on_the_increment_length(machine, jobshop):
    motion = jobshop[0]
    heat = {}
    for inc_s in (60, 300, 900, 3600):
        inc = increments_from_motion(machine, motion, inc_s)
        for mode in ("factor", "mean"):
            names, P = heat_powers(machine, inc, mode)
            heat[inc_s, mode] = P.T @ inc.duration_s  # J per heat input over the day
    for inc_s in (300, 900, 3600):
        np.testing.assert_allclose(heat[inc_s, "mean"], heat[60, "mean"], rtol=1e-9, atol=1e-6)
    # the power of the mean factor loses heat on the convex spindle law, the more the longer the increment
    tot = {k: v.sum() for k, v in heat.items()}
    assert tot[60, "factor"] > tot[300, "factor"] > tot[900, "factor"] > tot[3600, "factor"]
    assert tot[300, "factor"] < 0.9 * tot[300, "mean"]


def test_trace_and_gcode_agree_in_mean_power_mode_too(machine, jobshop):
    _, exact, traced = jobshop
    names, P1 = heat_powers(machine, exact, "mean")
    _, P2 = heat_powers(machine, traced, "mean")
    assert worst_source_deviation(machine, names, P1, P2) <= 0.01
