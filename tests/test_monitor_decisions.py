"""The monitor's pure decisions: offsets, time stamps, sensors, keep/switch/regenerate, model drift, backoff."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridcomp.monitor.decisions import (
    Backoff,
    Candidate,
    SensorRules,
    SensorState,
    SetError,
    TimeRules,
    Validity,
    backoff_delay,
    blend_offsets,
    check_sensor,
    check_time,
    compensation_error_um,
    complementary_offsets,
    decide,
    limit_offsets,
    model_drift,
    model_moved,
    model_moved_since,
    step_end_values,
    substitute,
    temperature_deviation,
)

# --------------------------------------------------------------------------- offsets


def test_limit_offsets_clamps_then_rate_limits():
    out, clamped, limited = limit_offsets({"dx_um": 500.0, "dy_um": -3.0, "dz_um": 1.0}, {"dx_um": 95.0}, 100.0, 2.0)
    assert out == {"dx_um": 97.0, "dy_um": -2.0, "dz_um": 1.0}  # 500 → 100 (clamp) → 95 + 2 (rate)
    assert clamped and limited


def test_limit_offsets_reaches_a_step_target_in_exact_steps():
    prev = {"dz_um": 0.0}
    seen = []
    for _ in range(6):
        prev, clamped, limited = limit_offsets({"dz_um": -10.0}, prev, 100.0, 3.0)
        seen.append(prev["dz_um"])
    assert seen == [-3.0, -6.0, -9.0, -10.0, -10.0, -10.0]
    assert not clamped and not limited


def test_limit_offsets_untouched_within_limits():
    out, clamped, limited = limit_offsets({"dx_um": 1.5}, {"dx_um": 1.0}, 10.0, 1.0)
    assert out == {"dx_um": 1.5} and not clamped and not limited


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_limit_offsets_rejects_non_finite(bad):
    with pytest.raises(ValueError, match="dx_um"):
        limit_offsets({"dx_um": bad}, {}, 10.0, 1.0)


def test_blend_offsets_continues_then_decays_exponentially():
    new = {"dz_um": -10.0}
    blend = {"dz_um": 4.0}  # written last: -6 µm, the new set says -10 µm
    out, left = blend_offsets(new, blend, 0.0, 300.0)
    assert out == {"dz_um": -6.0}
    out, left = blend_offsets(new, left, 300.0, 300.0)
    assert out["dz_um"] == pytest.approx(-10.0 + 4.0 / math.e) and left["dz_um"] == pytest.approx(4.0 / math.e)
    assert blend_offsets(new, blend, 5.0, 0.0) == ({"dz_um": -10.0}, {"dz_um": 0.0})  # tau 0: at once


# --------------------------------------------------------------------------- time


def test_check_time_orders_the_stamps():
    rules = TimeRules()
    verdict = lambda last, t: check_time(last, t, 0.0, (), rules).verdict  # noqa: E731
    assert verdict(None, 0.0) == "ok"
    assert verdict(1.0, 2.0) == "ok"
    assert verdict(2.0, 2.0) == "repeated"
    assert verdict(2.0, 1.0) == "backwards"
    assert verdict(2.0, math.nan) == "invalid"


# --------------------------------------------------------------------------- sensors

RULES = SensorRules(hold_s=10.0, frozen_s=100.0, spike_K=1.0, spike_rate_K_s=0.0)


def run(values, rules=RULES, dt=1.0, reference=math.nan):
    st = SensorState()
    out = []
    for k, v in enumerate(values):
        verdict = check_sensor(st, k * dt, v, rules, reference)
        st = verdict.state
        out.append((verdict.value_degC, verdict.event, st.status))
    return out


def test_sensor_nan_is_held_for_hold_s_then_degraded_then_recovers():
    vals = [20.0, 20.1] + [math.nan] * 13 + [20.3]
    out = run(vals)
    assert out[2] == (20.1, "holding", "holding")
    # held at the last good value up to hold_s = 10 s after the first bad reading at t = 2 s
    assert all(v == 20.1 and s == "holding" for v, _, s in out[3:13])
    assert out[13][1] == "degraded" and math.isnan(out[13][0])  # t = 13 s: 11 s > hold_s
    assert out[14][1] is None and out[14][2] == "degraded"
    assert out[15] == (20.3, "recovered", "ok")


def test_sensor_spike_is_rejected_and_a_short_spike_never_degrades():
    out = run([20.0, 20.05, 35.0, 20.1])
    assert out[2] == (20.05, "holding", "holding")
    assert out[3] == (20.1, None, "ok")


def test_sensor_spike_threshold_exact():
    rules = SensorRules(hold_s=1000.0, frozen_s=0.0, spike_K=1.0, spike_rate_K_s=0.1)
    st = check_sensor(SensorState(), 0.0, 20.0, rules).state
    assert check_sensor(st, 1.0, 21.09, rules).event is None  # 1.09 K ≤ 1.1 K
    assert check_sensor(st, 1.0, 21.11, rules).event == "holding"  # 1.11 K > 1.1 K
    assert check_sensor(st, 10.0, 21.99, rules).event is None  # ≤ 1 + 0.1·10 = 2 K


def test_sensor_out_of_range_is_bad():
    out = run([20.0, 850.0])
    assert out[1] == (20.0, "holding", "holding")
    assert check_sensor(SensorState(), 0.0, -40.0, RULES).state.reason == "range"


def test_sensor_frozen_degrades_after_frozen_plus_hold():
    out = run([20.0] * 125)
    statuses = [s for _, _, s in out]
    # unchanged since t = 0: frozen from t = 100 s, held until 110 s, degraded after
    assert statuses[99] == "ok"
    assert out[100][1] == "holding" and statuses[110] == "holding"
    assert out[111][1] == "degraded"


def test_sensor_unchanged_while_the_model_moves_it_is_frozen_and_stays_so_until_it_moves():
    """Unchanged while the structure model's prediction moves by frozen_model_K: frozen long before frozen_s; it
    stays degraded while the reading stands still, even when the model comes back; a changed reading restarts."""
    rules = SensorRules(hold_s=2.0, frozen_s=1000.0, frozen_model_K=0.5, spike_K=1.0, spike_rate_K_s=0.0)
    st, events = SensorState(), []
    path = [0.1] * 6 + [-0.1] * 12 + [0.0] * 5  # the model's predicted change per step [K]: up 0.6 K, back 1.2 K
    for k, d in enumerate(path):
        v = check_sensor(st, 10.0 * k, 20.0, rules, reference_degC=20.0 + 0.1 * min(k, 6))
        st = model_moved(v.state, 10.0 * k, d)
        events.append(v.event)
    # moved 0.5 K after the 5th step (k = 5 reads it at t = 50 s), held 2 s, degraded at the next reading
    assert events.index("holding") == 5 and events.index("degraded") == 6
    assert st.status == "degraded" and "recovered" not in events  # the model's way back recovers nothing
    assert model_moved(st, 0.0, 0.3).model_moved_K == pytest.approx(st.model_moved_K + 0.3)
    v = check_sensor(st, 300.0, 20.05, rules, reference_degC=20.0)
    assert v.event == "recovered" and v.state.model_moved_K == 0.0
    assert model_moved(v.state, 290.0, 0.2).model_moved_K == 0.0  # changed within the step: starts again
    # a healthy sensor the model moves by less than frozen_model_K is never frozen
    st = SensorState()
    for k in range(50):
        v = check_sensor(st, 10.0 * k, 20.0, rules)
        assert v.event is None
        st = model_moved(v.state, 10.0 * k, 0.009)


def test_the_open_loop_move_is_set_not_summed_and_counts_only_while_the_reading_stands():
    """``model_moved_since`` takes the open-loop model's whole move since the reading stood still (the caller runs
    the model from the rewind log): set, not added; 0 when the reading changed within the step or is NaN."""
    rules = SensorRules(hold_s=2.0, frozen_s=1000.0, frozen_model_K=0.5, spike_K=1.0, spike_rate_K_s=0.0)
    v = check_sensor(SensorState(), 0.0, 20.0, rules)
    st = model_moved_since(v.state, 10.0, 0.3)
    assert st.model_moved_K == pytest.approx(0.3)
    assert model_moved_since(st, 20.0, 0.45).model_moved_K == pytest.approx(0.45)  # the whole move, not 0.75
    assert check_sensor(model_moved_since(st, 20.0, 0.5), 20.0, 20.0, rules).event == "holding"
    v = check_sensor(st, 30.0, 20.1, rules)  # the reading moved at 30 s
    assert model_moved_since(v.state, 20.0, 0.6).model_moved_K == 0.0  # changed within the step: starts again
    assert model_moved_since(v.state, 30.0, float("nan")).model_moved_K == 0.0


def test_sensor_stuck_at_implausible_value_does_not_recover_against_the_reference():
    rules = SensorRules(hold_s=2.0, frozen_s=1e9, spike_K=1.0, spike_rate_K_s=0.0)
    out = run([20.0] + [45.0] * 6, rules, reference=20.2)
    assert out[4][1] == "degraded"
    assert out[5][2] == "degraded" and out[6][2] == "degraded"  # 45 °C is 24.8 K off the stand-in: no recovery
    st = check_sensor(SensorState(status="degraded", value_degC=20.0), 10.0, 20.5, rules, 20.2)
    assert st.event == "recovered" and st.value_degC == 20.5


def test_sensor_state_round_trips_json_dict():
    s2 = check_sensor(check_sensor(SensorState(), 0.0, 20.0, RULES).state, 1.0, math.nan, RULES).state
    back = SensorState.from_dict(s2.to_dict())
    assert s2.status == "holding"
    assert (back.status, back.value_degC, back.bad_since_s, back.reason) == (s2.status, s2.value_degC, s2.bad_since_s, s2.reason)
    assert math.isnan(back.raw_degC)


def test_step_end_values_follow_a_ramp_to_the_last_reading_and_average_the_noise():
    rng = np.random.default_rng(3)
    t = np.arange(1.0, 21.0)  # one 20 s step at 1 Hz
    ramp = 20.0 + 0.01 * t  # a sensor near a source that starts heating: 0.6 K/min
    ends, means = [], []
    for _ in range(2000):
        y = ramp + rng.normal(0.0, 0.02, t.size)
        ends.append(step_end_values(t, y[:, None])[0])
        means.append(y.mean())
    ends, means = np.array(ends), np.array(means)
    assert abs(ends.mean() - ramp[-1]) < 0.002  # no lag
    assert abs(np.mean(means) - ramp[-1]) == pytest.approx(0.095, abs=0.002)  # the mean lags by half the step
    # the line's end value: variance σ²(1/n + (t_n − t̄)²/Σ(t − t̄)²), under half of one reading's noise
    var = 1 / t.size + (t[-1] - t.mean()) ** 2 / np.sum((t - t.mean()) ** 2)
    assert ends.std() == pytest.approx(0.02 * math.sqrt(var), rel=0.05)
    assert math.sqrt(var) < 0.45


def test_step_end_values_without_a_line():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    Y = np.array([[1.0, math.nan, 5.0, math.nan], [2.0, math.nan, 5.0, math.nan], [3.0, 7.0, 5.0, math.nan],
                  [4.0, 9.0, math.nan, math.nan]])
    out = step_end_values(t, Y)
    assert out[0] == pytest.approx(4.0)  # a line through four readings, at the last
    assert out[1] == pytest.approx(8.0)  # two readings: their mean
    assert out[2] == pytest.approx(5.0)  # constant
    assert math.isnan(out[3])  # not measured
    assert step_end_values(np.full(3, 5.0), np.array([[1.0], [2.0], [3.0]]))[0] == pytest.approx(2.0)  # no spread


def test_substitute():
    assert substitute(21.0, 0.4) == pytest.approx(21.4)
    assert substitute(21.0, math.nan) == 21.0
    assert math.isnan(substitute(math.nan, 0.4))


# --------------------------------------------------------------------------- decisions


def test_temperature_deviation_over_common_finite_sensors():
    d, s = temperature_deviation({"T1": 25.0, "T2": 21.0, "T3": math.nan}, {"T1": 24.2, "T2": 22.0, "T3": 0.0, "T9": 5.0})
    assert (d, s) == (pytest.approx(1.0), "T2")
    assert temperature_deviation({"T1": 1.0}, {"T2": 1.0}) == (math.inf, None)


A = {"X": 1, "Y": 2, "Z": 3}
V = Validity(keep_um=1.5, forecast_um=3.0, hard_um=3.0, dwell_s=3600.0, bump_um=1.0)
GOOD = SetError(0.4, 1.0)


def cand(ids=(4, 5, 6), interval=0.5, forecast=1.0, jump=0.2, name="stored"):
    return Candidate(dict(zip("XYZ", ids)), name, SetError(interval, forecast), jump)


def test_compensation_error_is_the_largest_finite_difference():
    assert compensation_error_um([[1.0, 2.0, 3.0], [0.0, math.nan, 0.0]], [[1.5, 2.0, 1.0], [0.0, 0.0, 0.0]]) == 2.0
    assert compensation_error_um([[math.nan]], [[0.0]]) == math.inf  # no evidence that the set fits


def test_decide_keeps_a_set_within_both_limits_even_exactly_at_them():
    d = decide(A, SetError(1.5, 3.0), 10.0, V, [], True, False)
    assert d.action == "keep" and "1.50 µm over the interval" in d.reason


def test_decide_keeps_within_the_dwell_time_unless_the_hard_limit_is_passed():
    assert decide(A, SetError(2.5, 5.0), 1800.0, V, [], True, False).action == "keep"
    assert "dwell" in decide(A, SetError(2.5, 5.0), 1800.0, V, [], True, False).reason
    assert decide(A, SetError(3.1, 5.0), 1800.0, V, [], True, False).action == "regenerate"
    assert decide(A, SetError(2.5, 5.0), 3600.0, V, [], True, False).action == "regenerate"
    # a good interval but a bad forecast is also a reason to act (after the dwell)
    assert decide(A, SetError(0.5, 3.5), 7200.0, V, [], True, False).action == "regenerate"


def test_decide_switches_to_the_best_fitting_stored_set_within_the_jump_limit():
    far = cand((7, 8, 9), 0.3, 0.5, jump=1.5, name="far")  # fits but would jump 1.5 µm
    ok = cand((4, 5, 6), 1.0, 2.0, name="ok")
    best = cand((10, 11, 12), 0.5, 1.0, name="best")
    bad = cand((13, 14, 15), 2.0, 1.0, name="bad")
    same = cand((1, 2, 3), 0.1, 0.1, name="active")  # the active set itself is never a target
    d = decide(A, SetError(2.0, 4.0), 7200.0, V, [far, ok, best, bad, same], True, False)
    assert d.action == "switch" and d.target == best
    assert "'best'" in d.reason and "jump 0.20 µm" in d.reason


def test_decide_regenerates_or_warns_when_no_stored_set_fits():
    e = SetError(2.0, 4.0)
    assert decide(A, e, 7200.0, V, [cand(jump=2.0)], True, False).action == "regenerate"
    assert decide(A, e, 7200.0, V, [], True, True).action == "warn"
    d = decide(A, e, 7200.0, V, [], False, False)
    assert d.action == "warn" and "disabled" in d.reason


def test_decide_without_active_set():
    assert decide(None, None, math.inf, V, [cand()], True, False).action == "switch"
    d = decide(None, None, math.inf, V, [], False, False)
    assert d.action == "warn" and "no active CD set" in d.reason


@pytest.mark.parametrize("kw", [{"keep_um": 0.0}, {"dwell_s": -1.0}, {"max_candidates": 1.5}, {"forecast_h": math.inf}])
def test_validity_rejects_bad_settings(kw):
    with pytest.raises(ValueError):
        Validity(**kw)


def test_model_drift():
    assert model_drift({"T1": 20.0, "T2": 22.0}, {"T1": 20.5, "T2": 20.9}, 1.0) == (True, pytest.approx(1.1), "T2")
    assert model_drift({"T1": 20.0}, {"T1": 20.5}, 1.0)[0] is False
    assert model_drift({"T1": 20.0}, {}, 1.0)[0] is False


# --------------------------------------------------------------------------- backoff


def test_backoff_schedule_doubles_and_caps():
    b = Backoff(initial_s=0.5, factor=2.0, max_s=4.0, jitter=0.0)
    assert [backoff_delay(k, b) for k in range(6)] == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]


def test_backoff_jitter_bounds():
    b = Backoff(initial_s=1.0, factor=2.0, max_s=8.0, jitter=0.25)
    assert backoff_delay(1, b, 0.0) == pytest.approx(1.5)
    assert backoff_delay(1, b, 1.0) == pytest.approx(2.5)
    assert backoff_delay(1, b, 0.5) == pytest.approx(2.0)


@pytest.mark.parametrize("kw", [{"initial_s": 0.0}, {"factor": 0.5}, {"max_s": 0.1}, {"jitter": 1.0}])
def test_backoff_rejects_bad_settings(kw):
    with pytest.raises(ValueError):
        Backoff(**kw)


def test_complementary_offsets_take_the_fast_part_from_the_model_and_the_slow_part_from_the_cds():
    cd, model = {"dz_um": -10.0}, {"dz_um": -7.0}
    out, low = complementary_offsets(cd, model, None, 5.0, 900.0)
    assert out == {"dz_um": -10.0} and low == {"dz_um": -3.0}  # the first cycle: the CDs, nothing to continue
    # the model jumps by 2 µm (a spindle start the sensors see late): the offsets follow at once
    out, low = complementary_offsets(cd, {"dz_um": -5.0}, low, 5.0, 900.0)
    assert out["dz_um"] == pytest.approx(-8.0, abs=0.02)
    # held for long against the same CDs, the offsets settle on the CDs (the model's bias is not kept)
    for _ in range(2000):
        out, low = complementary_offsets(cd, {"dz_um": -5.0}, low, 5.0, 900.0)
    assert out["dz_um"] == pytest.approx(-10.0, abs=1e-3)
    # settling is first order with the crossover time constant
    out1, _ = complementary_offsets(cd, {"dz_um": -5.0}, {"dz_um": -3.0}, 900.0, 900.0)
    assert out1["dz_um"] == pytest.approx(-5.0 + (-3.0 * math.exp(-1.0) + -5.0 * (1 - math.exp(-1.0))))
    assert complementary_offsets(cd, model, {"dz_um": 1.0}, 5.0, 0.0)[0] == cd  # 0: the CDs alone
    with pytest.raises(ValueError):
        complementary_offsets(cd, model, None, -1.0, 900.0)
