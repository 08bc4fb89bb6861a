"""``Loads.resample``: one end-time rule; ``InputLayout.inputs(loads)``: the layout's column order."""

from __future__ import annotations

import numpy as np
import pytest

from hybridcomp.models.layout import END_TIME_TOLERANCE, InputLayout, Loads, LoadsColumnError


def ramp(time_s):
    t = np.asarray(time_s, float)
    return Loads(t, np.column_stack([2.0 * t, 20.0 + 0.0 * t]), ("q_W", "air_degC"))


def test_a_step_dividing_the_span_gives_the_uniform_grid_with_both_ends():
    r = ramp([0.0, 300.0, 600.0]).resample(60.0)
    np.testing.assert_array_equal(r.time_s, np.arange(0.0, 601.0, 60.0))
    np.testing.assert_array_equal(r.values[:, 0], 2.0 * r.time_s)  # linear interpolation, exact at these times
    assert r.names == ("q_W", "air_degC")


def test_an_end_off_the_grid_is_kept_and_only_the_last_step_is_shorter():
    r = ramp([10.0, 100.0, 250.0]).resample(60.0)
    np.testing.assert_array_equal(r.time_s, [10.0, 70.0, 130.0, 190.0, 250.0])
    np.testing.assert_array_equal(r.values[:, 0], 2.0 * r.time_s)


def test_a_grid_time_within_round_off_of_the_end_is_the_end():
    # a G-code day ends 9e-10 s after the last whole step: no sliver step, the end time exactly
    end = 57600.00000000093
    r = ramp([0.0, 300.0, end]).resample(60.0)
    assert r.time_s.size == 961 and r.time_s[-1] == end
    assert np.diff(r.time_s).min() == pytest.approx(60.0)
    # arange(0, 0.3, 0.1) has a fourth point 0.30000000000000004, past the end: it is the end
    r = ramp([0.0, 0.3]).resample(0.1)
    assert r.time_s.size == 4 and r.time_s[-1] == 0.3 and (r.time_s <= 0.3).all()
    # just outside the tolerance a grid time stays, and the end follows it
    tol = END_TIME_TOLERANCE * 1000.0
    r = ramp([0.0, 1000.0 + 3 * tol]).resample(100.0)
    assert r.time_s[-2] == 1000.0 and r.time_s[-1] == 1000.0 + 3 * tol


def test_a_step_longer_than_the_span_keeps_the_two_ends_and_one_row_stays_one_row():
    np.testing.assert_array_equal(ramp([0.0, 30.0]).resample(60.0).time_s, [0.0, 30.0])
    one = ramp([5.0]).resample(60.0)
    np.testing.assert_array_equal(one.time_s, [5.0])
    np.testing.assert_array_equal(one.values, [[10.0, 20.0]])


@pytest.mark.parametrize("dt_s", [0.0, -60.0, np.nan, np.inf])
def test_a_step_that_is_not_positive_and_finite_is_refused(dt_s):
    with pytest.raises(ValueError, match="dt_s must be positive and finite"):
        ramp([0.0, 60.0]).resample(dt_s)


LAYOUT = InputLayout(heat_inputs=("a", "b"), zones=("air",), zone_air=("ambient",), sensors=("T1",),
                     reference_temperature_degC=20.0)


def test_inputs_of_loads_follow_the_layout_order_not_the_loads_order():
    loads = Loads(np.array([0.0, 60.0]), np.array([[21.0, 5.0, 7.0], [22.0, 6.0, 8.0]]), ("air_degC", "b_W", "a_W"))
    U = LAYOUT.inputs(loads)
    np.testing.assert_array_equal(U, [[7.0, 5.0, 1.0], [8.0, 6.0, 2.0]])
    np.testing.assert_array_equal(U, LAYOUT.inputs(loads.names, loads.values))


def test_inputs_of_loads_fill_missing_columns_and_refuse_unknown_ones():
    np.testing.assert_array_equal(LAYOUT.inputs(Loads(np.array([0.0]), np.array([[3.0]]), ("b_W",))), [[0.0, 3.0, 0.0]])
    with pytest.raises(LoadsColumnError, match="'c_W' is not an input"):
        LAYOUT.inputs(Loads(np.array([0.0]), np.array([[3.0]]), ("c_W",)))
    with pytest.raises(TypeError, match="takes no values"):
        LAYOUT.inputs(Loads(np.array([0.0]), np.array([[3.0]]), ("b_W",)), np.zeros((1, 1)))


def test_keep_rows_adds_every_row_to_the_grid_so_a_kink_stays_on_a_step():
    # a triangle with its peak at 130 s, off the 60 s grid: resampled alone the peak is cut, with the rows kept
    # it stays, and the grid is the union of the uniform times and the rows
    t = np.array([0.0, 130.0, 300.0])
    loads = Loads(t, np.column_stack([[0.0, 13.0, 0.0], [1.0, 1.0, 1.0]]), ("a_W", "air_degC"))
    plain = loads.resample(60.0)
    kept = loads.resample(60.0, keep_rows=True)
    np.testing.assert_array_equal(plain.time_s, [0.0, 60.0, 120.0, 180.0, 240.0, 300.0])
    np.testing.assert_array_equal(kept.time_s, [0.0, 60.0, 120.0, 130.0, 180.0, 240.0, 300.0])
    assert plain.values[:, 0].max() < 13.0 and kept.values[:, 0].max() == 13.0
    np.testing.assert_array_equal(kept.values[np.searchsorted(kept.time_s, t)], loads.values)
