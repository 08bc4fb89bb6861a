"""The observer's admissible disturbance ranges: the constrained Kalman filter's estimate projection against its
closed form, a probe pushing an estimate beyond a bound, the unconstrained filter untouched when no bound acts,
and the settings' validation."""

from __future__ import annotations

import numpy as np
import pytest

from hybridcomp.fem.loads import example_loads
from hybridcomp.monitor.config import ConfigError, parse_config
from hybridcomp.rom.observer import ObserverError, ObserverSettings, build_observer, project_bounds

#: ranges so wide that nothing in these tests reaches them (a power scale cannot go below −1)
WIDE = dict(air_min_K=-1e9, air_max_K=1e9, scale_min=-1.0, scale_max=1e9, heat_min_W=-1e9, heat_max_W=1e9)


def test_projection_of_two_correlated_states_is_the_conditional_mean():
    # x0 ≤ 1 violated, x1 free: x̃0 = 1, x̃1 = x1 − p01 / p00 (x0 − 1) (the mean of x1 given x0 = 1)
    P = np.array([[4.0, 1.2], [1.2, 1.0]])
    x = np.array([3.0, 0.5])
    out = project_bounds(x, P, np.array([0]), np.array([-1.0]), np.array([1.0]))
    np.testing.assert_allclose(out, [1.0, 0.5 - 1.2 / 4.0 * 2.0], rtol=0, atol=1e-14)
    # a lower bound the same way: x0 ≥ 4 pulls x1 up by p01 / p00 × 1
    out = project_bounds(x, P, np.array([0]), np.array([4.0]), np.array([9.0]))
    np.testing.assert_allclose(out, [4.0, 0.5 + 1.2 / 4.0], rtol=0, atol=1e-14)
    # an admissible estimate is returned as it is
    assert project_bounds(x, P, np.array([0]), np.array([0.0]), np.array([5.0])) is x


def test_projection_takes_the_active_set_not_every_violated_bound():
    # both states above 1, strongly correlated: bringing x0 to its bound brings x1 inside (1.5 − 0.9 = 0.6), so
    # only x0's bound is active; clipping both would give (1, 1), farther from x in the P⁻¹ metric
    P = np.array([[1.0, 0.9], [0.9, 1.0]])
    x = np.array([2.0, 1.5])
    lo, hi = np.array([-5.0, -5.0]), np.array([1.0, 1.0])
    out = project_bounds(x, P, np.array([0, 1]), lo, hi)
    np.testing.assert_allclose(out, [1.0, 0.6], rtol=0, atol=1e-12)
    Pi = np.linalg.inv(P)
    d = out - x
    c = np.array([1.0, 1.0]) - x
    assert d @ Pi @ d < c @ Pi @ c
    # weakly correlated: both bounds active, and a third, free state moves by P_fA P_AA⁻¹ (d − x_A)
    P3 = np.array([[1.0, 0.2, 0.5], [0.2, 1.0, -0.3], [0.5, -0.3, 2.0]])
    x3 = np.array([2.0, 2.0, 0.0])
    out3 = project_bounds(x3, P3, np.array([0, 1]), lo, hi)
    # by hand: P_AA⁻¹ = [[1, −0.2], [−0.2, 1]] / 0.96, x_A − d = (1, 1) → (0.8, 0.8) / 0.96 = (5/6, 5/6)
    np.testing.assert_allclose(out3, [1.0, 1.0, 0.0 - (0.5 - 0.3) * 5.0 / 6.0], rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def day(machine, small_rom):
    """Two hours of the example day on the 200 mm model reduced to order 40 (inputs and sensors, per 60 s)."""
    loads = example_loads(machine, 2.0, 60.0)
    U = machine.layout().inputs(loads.names, loads.values)
    Y, _ = small_rom.integrate(loads.time_s, U, hold="step")
    return U, Y[:, :8] + 20.0


def run(obs, U, T, steps):
    s = obs.initial(U[0])
    s, _ = obs.update_sensors(s, T[0])
    for k in range(1, steps):
        s = obs.predict(s, U[k], 60.0)
        s, _ = obs.update_sensors(s, T[k])
    return s


def test_a_probe_pushing_an_estimate_beyond_a_bound_is_projected_back_with_its_correlated_states(
        machine, small_rom, day):
    U, T = day
    # no widening: the probe's 10 µm offset in y goes into the thermal state and, through P, the disturbances:
    # a zone's air 1.5 K up, beyond the ±1 K allowed here
    wide = build_observer(small_rom, machine, ObserverSettings(probe_widen_sigma=0.0, **WIDE))
    bounded = build_observer(small_rom, machine, ObserverSettings(probe_widen_sigma=0.0, air_min_K=-1.0,
                                                                  air_max_K=1.0))
    s = run(wide, U, T, 30)
    probe = wide.drift_um(s) + np.array([0.0, -10.0, 0.0])
    free = wide.update_probe(s, probe)
    held = bounded.update_probe(s, probe)
    idx, lo, hi = bounded._bounds()
    xf, xh = free.x[idx], held.x[idx]
    wlo, whi = wide._bounds()[1:]
    assert np.all((xf > wlo) & (xf < whi))  # the wide filter's bounds did not act
    assert np.any((xf < lo) | (xf > hi))
    assert np.all((xh >= lo) & (xh <= hi))
    active = idx[(xh == lo) | (xh == hi)]
    assert active.size > 0
    np.testing.assert_array_equal(held.P, free.P)  # the covariance is the unconstrained filter's
    # the change is P's columns of the active states times (P_AA⁻¹ (bound − x_A)): solved here by least squares
    delta = held.x - free.x
    c, *_ = np.linalg.lstsq(free.P[:, active], delta, rcond=None)
    np.testing.assert_allclose(free.P[:, active] @ c, delta, rtol=0, atol=1e-9 * np.abs(delta).max())
    z = bounded.slices()["z"]
    assert np.abs(delta[z]).max() > 1e-3  # the thermal state moves with the disturbances
    # optimality (KKT): the multipliers c push each active state back inside (negative at an upper bound)
    at_upper = held.x[active] == hi[np.searchsorted(idx, active)]
    assert np.all(np.where(at_upper, c <= 0, c >= 0))


def test_no_active_bound_leaves_the_filter_unchanged(machine, small_rom, day):
    U, T = day
    a = run(build_observer(small_rom, machine), U, T, 120)
    b = run(build_observer(small_rom, machine, ObserverSettings(**WIDE)), U, T, 120)
    idx, lo, hi = build_observer(small_rom, machine)._bounds()
    assert np.all((a.x[idx] > lo) & (a.x[idx] < hi))
    assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


@pytest.mark.parametrize("low,high", [("scale_min", "scale_max"), ("air_min_K", "air_max_K"),
                                      ("heat_min_W", "heat_max_W")])
def test_a_lower_bound_above_the_upper_one_is_refused_naming_it(low, high):
    with pytest.raises(ObserverError, match=rf"'{low}' \(0\.5\) is above '{high}' \(0\.2\)"):
        ObserverSettings(**{low: 0.5, high: 0.2})


def test_bounds_that_exclude_the_prior_or_a_negative_power_are_refused():
    with pytest.raises(ObserverError, match=r"'scale_min' must be ≥ −1 \(a power is never negative\), got -1.5"):
        ObserverSettings(scale_min=-1.5)
    with pytest.raises(ObserverError, match=r"'air_min_K' must be ≤ 0 .* got 0.5"):
        ObserverSettings(air_min_K=0.5)
    with pytest.raises(ObserverError, match=r"'heat_max_W' must be a finite number ≥ 0, got -1"):
        ObserverSettings(heat_min_W=-2.0, heat_max_W=-1.0)
    assert ObserverSettings().bounds("scale") == (-0.9, 3.0)


def test_config_takes_negative_lower_bounds_and_names_a_bad_one():
    base = {"monitor": {"machine": "vmc800", "database": "cd.db", "rom": "r.npz"}, "source": {"path": "t.csv"},
            "sink": {"path": "o.jsonl"}}
    c = parse_config({**base, "observer": {"scale_min": -0.5, "air_min_K": -2.0}}, "m.toml")
    assert c.observer.bounds("scale") == (-0.5, 3.0) and c.observer.bounds("air") == (-2.0, 3.0)
    with pytest.raises(ConfigError, match=r"m\.toml: \[observer\] observer setting 'scale_min' \(0\.5\) is above"):
        parse_config({**base, "observer": {"scale_min": 0.5, "scale_max": 0.2}}, "m.toml")
