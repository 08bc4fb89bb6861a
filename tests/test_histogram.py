"""Histogram generator: load factors, segment fractions and BCs against exact, hand-computed values.

Motions are built so that the right answer is known in closed form (constant
speeds, whole strokes per increment), and every quantity is compared with
that answer, not with an earlier run of the code.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridcomp.fem.loads import input_columns, read_loads, write_loads
from hybridcomp.histogram import (
    SignatureLayout,
    TraceFileError,
    TraceWarning,
    boundary_conditions,
    heat_powers,
    increments_from_samples,
    increments_from_trace,
    samples,
    signature_distance,
    signatures,
    write_bcs,
    write_trace,
)


def triangle(t, lo, hi, speed_mm_min, start=None):
    """Back and forth between lo and hi at constant speed [mm/min], starting at lo (or ``start`` going up)."""
    v = speed_mm_min / 60.0
    L = hi - lo
    period = 2 * L / v
    s0 = 0.0 if start is None else (start - lo) / v
    ph = ((np.asarray(t) + s0) % period) / period
    return np.where(ph < 0.5, lo + 2 * ph * L, hi - 2 * (ph - 0.5) * L)


# --------------------------------------------------------------------------- exact factors and fractions


def test_half_feed_over_full_travel_gives_factor_half_and_equal_segments(machine):
    # X at 20,000 mm/min (half of 40,000) over -400..400: one stroke takes 2.4 s, 300 s hold 125 whole strokes
    t = np.arange(0, 1800 + 1e-9, 0.1)
    s = samples(machine, t, {"X": triangle(t, -400, 400, 20000)}, spindle_rpm=np.full(t.size, 3000.0))
    inc = increments_from_samples(machine, s, 300)
    assert len(inc) == 6
    np.testing.assert_allclose(inc.start_s, np.arange(6) * 300.0)
    np.testing.assert_allclose(inc.axis_factor[:, 0], 0.5, rtol=1e-12)
    np.testing.assert_array_equal(inc.axis_factor[:, 1:], 0.0)
    np.testing.assert_allclose(inc.segment_fraction("X"), 0.25, rtol=1e-9)
    np.testing.assert_allclose(inc.spindle_factor, 3000 / 12000, rtol=1e-12)
    # Y and Z stand at 0 mm, a segment bound: a point on an inner bound counts in the segment above it
    np.testing.assert_array_equal(inc.segment_fraction("Y"), np.tile([0, 0, 1.0, 0], (6, 1)))
    # the fine histogram refines the segments: 5 bins of 40 mm each hold a fifth of a segment's time
    np.testing.assert_allclose(inc.histogram("X"), 0.05, rtol=1e-9)


def test_standstill_and_spindle_dwell_give_zero_axis_factors(machine):
    t = np.arange(0, 600 + 1e-9, 1.0)
    s = samples(machine, t, {"X": 150.0, "Y": -300.0, "Z": 10.0}, spindle_rpm=np.full(t.size, 6000.0))
    inc = increments_from_samples(machine, s, 300)
    np.testing.assert_array_equal(inc.axis_factor, 0.0)
    np.testing.assert_array_equal(inc.segment_fraction("X"), [[0, 0, 1.0, 0]] * 2)  # 150 mm: segment 3 (0..200 mm)
    np.testing.assert_array_equal(inc.segment_fraction("Y"), [[1.0, 0, 0, 0]] * 2)  # -300 mm: segment 1 (-325..-162.5 mm)
    np.testing.assert_allclose(inc.spindle_factor, 0.5)


def test_increment_boundaries_split_an_interval_exactly(machine):
    # one move from -400 to 400 mm over 1000 s (48 mm/min), sampled only at its ends; increments of 300 s
    s = samples(machine, [0.0, 1000.0], {"X": np.array([-400.0, 400.0])})
    inc = increments_from_samples(machine, s, 300, max_gap_s=1000.0)
    np.testing.assert_allclose(inc.end_s, [300, 600, 900, 1000])
    np.testing.assert_allclose(inc.axis_factor[:, 0], 48.0 / 40000.0, rtol=1e-12)
    # 0.8 mm/s: segment k (200 mm) takes 250 s; increment 1 (0..300 s) holds 250 s of segment 1 and 50 s of segment 2
    np.testing.assert_allclose(inc.segment_time_s("X"), [[250, 50, 0, 0], [0, 200, 100, 0], [0, 0, 150, 150], [0, 0, 0, 100]],
                               atol=1e-9)


def test_irregular_sampling_and_chunking_do_not_change_the_result(machine):
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.05, 0.3, 20000))
    x = triangle(t, -400, 400, 20000)
    y = triangle(t, -325, 325, 8000, start=0.0)
    s = samples(machine, t, {"X": x, "Y": y}, spindle_rpm=np.full(t.size, 1200.0))
    whole = increments_from_samples(machine, s, 200)
    parts = increments_from_samples(machine, (s.take(slice(a, a + 777)) for a in range(0, len(s), 777)), 200)
    for a in ("X", "Y", "Z"):
        np.testing.assert_allclose(parts.segment_time_s(a), whole.segment_time_s(a), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(parts.axis_factor, whole.axis_factor, rtol=1e-12)
    # the segment times add up to the covered time, whatever the sampling
    np.testing.assert_allclose(whole.segment_time_s("X").sum(), t[-1] - t[0], rtol=1e-12)


def test_velocity_columns_integrate_abs_v_exactly_through_a_sign_change(machine):
    # v goes linearly from +30,000 to -10,000 mm/min in 1 s: ∫|v| = (30000² + 10000²) / (2 · 40000) / 60 mm
    s = samples(machine, [0.0, 1.0], {"X": np.array([0.0, 166.6666667])}, velocity_mm_min={"X": np.array([30000.0, -10000.0])})
    # (positions: the mean velocity 10,000 mm/min over 1 s)
    inc = increments_from_samples(machine, s, 300)
    path = (30000.0**2 + 10000.0**2) / (2 * 40000.0) / 60.0
    np.testing.assert_allclose(inc.axis_factor[0, 0], path / (40000 / 60 * 1.0), rtol=1e-12)


def test_gap_counts_as_standstill_with_a_warning(machine):
    t = np.concatenate([np.arange(0, 100.0, 0.5), np.arange(160.0, 300.0 + 1e-9, 0.5)])  # 60.5 s without samples
    x = np.where(t < 120, -100.0, 100.0)
    s = samples(machine, t, {"X": x}, spindle_rpm=np.full(t.size, 12000.0))
    with pytest.warns(TraceWarning, match=r"1 gap\(s\) longer than 10 s \(total 60\.5 s, first ending at line 202\)"):
        inc = increments_from_samples(machine, s, 300)
    np.testing.assert_allclose(inc.gap_s, [60.5])
    np.testing.assert_allclose(inc.spindle_factor, (300 - 60.5) / 300)
    assert inc.axis_factor[0, 0] == 0.0  # the jump across the gap is no motion
    # the gap is spent at the position before it (-100 mm, segment 2)
    np.testing.assert_allclose(inc.segment_time_s("X")[0], [0, 99.5 + 60.5, 140, 0])


# --------------------------------------------------------------------------- boundary conditions


def test_bcs_power_law_moving_sources_and_contract(machine, tmp_path):
    t = np.arange(0, 600 + 1e-9, 0.1)
    air = 20.0 + t / 600.0  # 20 .. 21 °C
    s = samples(machine, t, {"X": triangle(t, -400, 400, 20000)}, spindle_rpm=np.full(t.size, 6000.0),
                air_degC={"Tamb_degC": air})
    inc = increments_from_samples(machine, s, 300)
    loads = boundary_conditions(machine, inc)
    col = {n: loads.values[:, j] for j, n in enumerate(loads.names)}
    np.testing.assert_allclose(loads.time_s, [0, 300, 600])
    # row 0: standstill at the first measured air temperature; rows 1, 2: means of the increments
    np.testing.assert_allclose(col["x_motor_W"], [0, 45, 45])  # 90 W · 0.5
    for k in range(1, 5):
        np.testing.assert_allclose(col[f"x_nut[{k}]_W"], [0, 3.75, 3.75])  # 30 W · 0.5 / 4
    np.testing.assert_allclose(col["y_motor_W"], 0.0)
    np.testing.assert_allclose(col["spindle_bearing_front_W"], [0, 110 * 0.5**1.67, 110 * 0.5**1.67], rtol=1e-12)
    np.testing.assert_allclose(col["spindle_motor_W"], [0, 220 * 0.5**1.2, 220 * 0.5**1.2], rtol=1e-12)
    # ambient zones and workspace zones (no workspace column measured) follow Tamb: mean over each increment
    for z in ("ambient", "floor", "ws_table", "ws_spindle"):
        np.testing.assert_allclose(col[f"{z}_degC"], [20.0, 20.25, 20.75], rtol=1e-12)
    # exactly the loads-CSV contract: round trip through hybridcomp simulate's reader
    write_loads(tmp_path / "l.csv", loads)
    back = read_loads(tmp_path / "l.csv", machine)
    assert back.names == input_columns(machine)
    np.testing.assert_allclose(back.values[:, back.names.index("x_nut[3]_W")], [0, 3.75, 3.75], rtol=1e-6)


def test_workspace_column_and_no_air_columns(machine):
    t = np.arange(0, 300 + 1e-9, 1.0)
    s = samples(machine, t, {}, air_degC={"Tamb_degC": np.full(t.size, 19.0), "Tws_degC": np.full(t.size, 23.0),
                                          "floor_degC": np.full(t.size, 18.0)})
    loads = boundary_conditions(machine, increments_from_samples(machine, s, 300))
    col = {n: loads.values[-1, j] for j, n in enumerate(loads.names)}
    assert (col["ambient_degC"], col["floor_degC"], col["ws_table_degC"], col["ws_spindle_degC"]) == (19.0, 18.0, 23.0, 23.0)
    bare = boundary_conditions(machine, increments_from_samples(machine, samples(machine, t, {}), 300))
    # unmeasured air: the reference temperature, and the loads are always in model order
    assert bare.names == machine.layout().columns
    air = [j for j, n in enumerate(bare.names) if n.endswith("_degC")]
    assert np.all(bare.values[:, air] == machine.reference_temperature_degC)


def test_power_table_is_interpolated(machine):
    src = [s for s in machine.heat_sources if s.name == "x_motor"][0]
    tabled = dataclasses.replace(src, power_table=((0.0, 0.1), (0.25, 0.2), (1.0, 1.0)))
    m = dataclasses.replace(machine, heat_sources=tuple(tabled if s is src else s for s in machine.heat_sources))
    t = np.arange(0, 300 + 1e-9, 0.1)
    inc = increments_from_samples(m, samples(m, t, {"X": triangle(t, -400, 400, 20000)}), 300)
    names, P = heat_powers(m, inc)
    # f = 0.5: 0.2 + (0.5 - 0.25) / 0.75 · 0.8 = 0.4667 of 90 W
    np.testing.assert_allclose(P[0, names.index("x_motor_W")], 90 * (0.2 + 0.25 / 0.75 * 0.8), rtol=1e-12)
    loads = boundary_conditions(m, inc)
    assert loads.values[0, loads.names.index("x_motor_W")] == pytest.approx(9.0)  # standstill row: P(0) = 0.1 · 90 W


def test_increment_length_is_a_parameter(machine):
    # X runs at full feed for the first 5 min of every 15 min, stands otherwise
    t = np.arange(0, 3600 + 1e-9, 0.1)
    run = (t % 900) < 300
    x = np.where(run, triangle(t % 900, -400, 400, 40000), -400.0)
    s = samples(machine, t, {"X": x})
    f5 = increments_from_samples(machine, s, 300).axis_factor[:, 0]
    f15 = increments_from_samples(machine, s, 900).axis_factor[:, 0]
    f60 = increments_from_samples(machine, s, 3600).axis_factor[:, 0]
    np.testing.assert_allclose(f5, np.tile([1.0, 0, 0], 4), atol=1e-9)
    np.testing.assert_allclose(f15, 1 / 3, rtol=1e-9)
    np.testing.assert_allclose(f60, 1 / 3, rtol=1e-9)


# --------------------------------------------------------------------------- the trace CSV


def test_trace_csv_round_trip_streamed_in_small_chunks(machine, tmp_path):
    t = np.arange(0, 900 + 1e-9, 0.1)
    s = samples(machine, t, {"X": triangle(t, -400, 400, 20000), "Z": triangle(t, -275, 275, 10000)},
                spindle_rpm=np.full(t.size, 9000.0), air_degC={"Tamb_degC": np.full(t.size, 21.5)})
    write_trace(tmp_path / "trace.csv", machine, s)
    inc = increments_from_trace(tmp_path / "trace.csv", machine, 300, chunk_rows=1000)
    ref = increments_from_samples(machine, s, 300)
    np.testing.assert_allclose(inc.axis_factor, ref.axis_factor, atol=1e-7)
    np.testing.assert_allclose(inc.axis_factor[:, 0], 0.5, rtol=1e-6)
    np.testing.assert_allclose(inc.segment_fraction("X"), 0.25, rtol=1e-6)
    np.testing.assert_allclose(inc.air_degC, 21.5)
    assert inc.rows == t.size and inc.dropped_rows == 0


HEADER = ["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm"]


@pytest.mark.parametrize(
    "header,rows,match",
    [
        (HEADER, [[0, 0, 0, 0, 0], [1, 0, 0, 0, 0], [0.5, 0, 0, 0, 0]],
         r"t\.csv: line 4: time_s 0\.5 does not increase after 1 \(line 3\)"),
        (HEADER, [[0, 0, 0, 0, 0], [1, 0, 0, 0, 0], [1, 0, 0, 0, 0]], r"t\.csv: line 4: time_s 1 does not increase after 1"),
        (HEADER, [[0, 0, 0, 0, 0], [1, 412.5, 0, 0, 0]],
         r"t\.csv: line 3: x_mm = 412\.5 mm is outside the travel \[-400\.0, 400\.0\] mm of axis X"),
        (HEADER, [[0, 0, 0, 0, 0], [0.1, 0, 80, 0, 0]],
         r"t\.csv: line 3: axis Y moves 80 mm in 0\.1 s since line 2, 48000 mm/min, above its max_feed_mm_min 40000"),
        (HEADER, [[0, 0, 0, 0, 0], [1, 0, 0, 0, 13000]],
         r"t\.csv: line 3: spindle_rpm = 13000 is above \[spindle\] max_speed_rpm 12000"),
        ([*HEADER, "vx_mm_min"], [[0, 0, 0, 0, 0, 41000]],
         r"t\.csv: line 2: vx_mm_min = 41000 mm/min is above the max_feed_mm_min 40000"),
        (HEADER, [[0, 0, 0, 0, 0], [1, 0, "abc", 0, 0]], r"t\.csv: line 3, column 'y_mm': value 'abc' is not a number"),
        (HEADER, [[0, 0, 0, 0, 0], [1, 0, 0, 0]], r"t\.csv: line 3 has 4 fields, the header has 5"),
        (["time_s", "x_mm", "y_mm", "z_mm"], [[0, 0, 0, 0]], r"t\.csv: column 'spindle_rpm' is missing"),
        (["time_s", "x_mm", "y_mm", "spindle_rpm"], [[0, 0, 0, 0]], r"t\.csv: column 'z_mm' is missing"),
        ([*HEADER, "x_mmm"], [[0, 0, 0, 0, 0, 0]], r"t\.csv: column 'x_mmm' is not a trace column .* \(did you mean 'x_mm'\?\)"),
        (HEADER, [[0, 0, 0, 0, 0]], r"t\.csv: needs at least two valid samples"),
    ],
)
def test_bad_traces_are_named(machine, tmp_path, header, rows, match, write_csv):
    p = write_csv(tmp_path / "t.csv", header, rows)
    with pytest.raises(TraceFileError, match=match):
        increments_from_trace(p, machine)


def test_a_few_nan_rows_are_dropped_with_a_counted_warning(machine, tmp_path, write_csv):
    rows = [[0.1 * i, 0, 0, 0, 6000] for i in range(3001)]
    rows[1000][1] = "nan"
    rows[2000][2] = ""
    p = write_csv(tmp_path / "t.csv", HEADER, rows)
    with pytest.warns(TraceWarning, match=r"t\.csv: dropped 2 of 3001 rows with NaN or empty fields \(first at line 1002\)"):
        inc = increments_from_trace(p, machine)
    assert inc.dropped_rows == 2
    np.testing.assert_allclose(inc.spindle_factor, 0.5)  # the neighbours bridge the dropped rows
    rows[5][3] = "nan"
    rows[6][3] = "nan"
    p = write_csv(tmp_path / "t.csv", HEADER, rows[:100])
    with pytest.raises(TraceFileError,
                       match=r"t\.csv: 2 of 100 rows have NaN or empty fields \(first at line 7\), more than 1 %"):
        increments_from_trace(p, machine)


# --------------------------------------------------------------------------- signatures


def test_signature_layout_and_distance(machine):
    lay = SignatureLayout.of(machine)
    assert lay.size == 3 + 12 + 1
    assert lay.names[:4] == ("f_X", "f_Y", "f_Z", "h_X[1]") and lay.names[-1] == "f_spindle"
    t = np.arange(0, 900 + 1e-9, 0.1)
    inc = increments_from_samples(machine, samples(machine, t, {"X": triangle(t, -400, 400, 20000)}), 300)
    start, end, V = signatures(inc)
    assert V.shape == (3, 16)
    np.testing.assert_allclose(V[0, :4], [0.5, 0, 0, 0.25])
    _, _, P = signatures(inc, period_s=900)
    np.testing.assert_allclose(P, V[:1], rtol=1e-12)
    a = V[0]
    b = a.copy()
    b[0] = 0.4  # axis factor off by 0.1
    assert signature_distance(a, b, lay) == pytest.approx(0.1)
    c = a.copy()
    c[3:7] = [1, 0, 0, 0]  # same factor, X works only in segment 1: TV = 0.75, weight 0.5
    assert signature_distance(a, c, lay) == pytest.approx(0.5 * 0.75)
    d = a.copy()
    d[7:11] = [0, 0, 0, 1]  # a standing axis' position does not count
    assert signature_distance(a, d, lay) == 0.0
    assert signature_distance(a, a, lay) == 0.0
    with pytest.raises(ValueError, match="whole multiple"):
        signatures(inc, period_s=450)


def test_epoch_time_stamps_and_partial_last_increment_survive_the_loads_csv(machine, tmp_path):
    t0 = 1.7e9  # Unix time stamps: 6 significant digits would merge every row
    t = t0 + np.arange(0, 700.5 + 1e-9, 0.5)
    s = samples(machine, t, {"X": 100.0}, spindle_rpm=np.full(t.size, 6000.0))
    loads = boundary_conditions(machine, increments_from_samples(machine, s, 300))
    write_bcs(tmp_path / "l.csv", loads)
    back = read_loads(tmp_path / "l.csv", machine)
    np.testing.assert_array_equal(back.time_s, t0 + np.array([0, 300, 600, 700.5]))
    np.testing.assert_allclose(back.values[1:, back.names.index("spindle_motor_W")], 220 * 0.5**1.2, rtol=1e-6)


def test_positions_within_the_travel_tolerance_are_clipped(machine):
    t = np.arange(0, 10.0 + 1e-9, 1.0)
    inc = increments_from_samples(machine, samples(machine, t, {"X": np.full(t.size, 400.005)}), 300)
    np.testing.assert_array_equal(inc.segment_fraction("X"), [[0, 0, 0, 1.0]])
    with pytest.raises(TraceFileError, match=r"line 2: x_mm = 400\.02 mm is outside the travel"):
        increments_from_samples(machine, samples(machine, t, {"X": np.full(t.size, 400.02)}), 300)


def test_crlf_bom_blank_lines_and_empty_unused_fields_are_read(machine, tmp_path):
    body = "time_s,x_mm,y_mm,z_mm,spindle_rpm,T1_degC\r\n0,0,0,0,0,20\r\n1,10,0,0,6000,20\r\n\r\n2,20,0,0,6000,\r\n"
    p = tmp_path / "t.csv"
    p.write_bytes(b"\xef\xbb\xbf" + body.encode())
    inc = increments_from_trace(p, machine, 10)
    assert inc.rows == 3 and inc.dropped_rows == 0  # an empty sensor field is not read, so the row stays
    np.testing.assert_allclose(inc.axis_factor[0], [20 / (40000 / 60) / 2, 0, 0], rtol=1e-12)
    np.testing.assert_allclose(inc.spindle_factor, (3000 + 6000) / 2 / 12000, rtol=1e-12)  # trapezoid 0→6000→6000
