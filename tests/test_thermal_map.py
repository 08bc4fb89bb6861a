"""The thermal volumetric error model: a planted temperature dependence of the kinematic coefficients recovered from
calibrations at a few thermal states (its inputs among correlated distractors, held-out states predicted to the
noise), BICc against BIC on few states, the dict form and the refusals."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from hybridcomp.chardiag.kinematic import ErrorModel, chain_of, design_matrix, tcp_error_um
from hybridcomp.chardiag.thermal_map import (
    Calibration,
    ThermalErrorModel,
    ThermalMapError,
    _ic,
    _select,
    fit_thermal_map,
    from_dict,
    predict_um,
    to_dict,
)

NAMES = tuple(f"T{i + 1}" for i in range(8))
PLANTED = (1, 4)  # T2 and T5 drive the coefficients; the other six only follow the same heat sources
#: each sensor's response to the two heat sources (a spindle-like one, 0 … 6 K, and the workshop air, −2 … 2 K)
MIX = np.array([[0.8, 0.3], [1.0, 0.1], [0.5, 0.5], [0.3, 0.9], [0.1, 1.0], [0.9, 0.0], [0.0, 0.8], [0.6, 0.7]])
NOISE_UM = 0.5


@pytest.fixture(scope="module")
def chain(machine):
    return chain_of(machine)


def _grid(chain, levels):
    return np.array(list(itertools.product(*[np.linspace(lo, hi, levels) for lo, hi in chain.travel_mm])))


def _planted(chain, seed, n_train=10, n_test=5, noise=NOISE_UM, degree=3, own_K=0.5):
    """A cubic model whose coefficients are c0 + G ΔT, G nonzero for the planted sensors only (1 µm/K, 4 µrad/K
    per coefficient), measured on a 5 × 5 × 5 plan with ``noise`` [µm] at ``n_train`` states; the sensors follow two
    heat sources in different mixtures plus ``own_K`` of their own.  (training calibrations, held-out temperatures
    (n_test × 8), the true model at temperatures)"""
    rng = np.random.default_rng(seed)
    shape = (3, 6, degree + 1)
    c0 = np.zeros(shape)
    c0[:, :3] = rng.normal(0, 5, (3, 3, degree + 1))
    c0[:, 3:] = rng.normal(0, 20, (3, 3, degree + 1))
    G = np.zeros((*shape, 8))
    for j in PLANTED:
        G[:, :3, :, j] = rng.normal(0, 1.0, (3, 3, degree + 1))
        G[:, 3:, :, j] = rng.normal(0, 4.0, (3, 3, degree + 1))
    ref = 20.0 + rng.normal(0, 0.3, 8)

    def temps(n):
        d = np.column_stack([rng.uniform(0, 6, n), rng.uniform(-2, 2, n)])
        return ref + d @ MIX.T + rng.normal(0, own_K, (n, 8))

    T_train, T_test = temps(n_train), temps(n_test)
    plan = _grid(chain, 5)

    def truth(T):
        return ErrorModel(chain, degree, c0 + G @ (T - ref))

    cals = [Calibration(plan, tcp_error_um(truth(T), plan) + rng.normal(0, noise, (len(plan), 3)), T,
                        time_s=3600.0 * i, label=f"state {i}") for i, T in enumerate(T_train)]
    return cals, T_test, truth


def _held_out_rms(model, T_test, truth, poses):
    err = [predict_um(model, T, poses) - tcp_error_um(truth(T), poses) for T in T_test]
    return float(np.sqrt(np.mean(np.square(err))))


def _noise_rms(chain, cals, T_test, poses, inputs):
    """The rms error at ``poses`` that the noise alone gives a least-squares fit with the right inputs: each state
    identified (its noise mapped by the plan's pseudo-inverse), then c0 + G ΔT fitted over the states; at held-out
    temperatures T the states' noise enters with the weights h_s(T) = 1/S + ΔT(T)ᵀ (XᵀX)⁻¹ ΔT_s."""
    D = design_matrix(chain, cals[0].poses_mm, 3)
    gain = np.linalg.norm(design_matrix(chain, poses, 3) @ np.linalg.pinv(D, rcond=1e-10)) / math.sqrt(3 * len(poses))
    T = np.array([c.sensors_degC for c in cals])[:, inputs]
    X = T - T.mean(axis=0)
    h = 1.0 / len(cals) + (T_test[:, inputs] - T.mean(axis=0)) @ np.linalg.solve(X.T @ X, X.T)
    return NOISE_UM * gain * math.sqrt(np.mean(np.sum(h**2, axis=1)))


def test_the_planted_inputs_are_found_among_distractors_and_held_out_states_predicted(chain):
    """2 of 8 sensors drive the coefficients; the other six follow the same heat sources (correlated with a planted
    one by 0.68 to 0.97); 10 calibrations to train, 5 other thermal states held out. The fit takes exactly the
    planted sensors and predicts the held-out states over a 3 × 3 × 3 grid within twice the error the noise alone
    gives the right model (BIC takes a distractor as well); without one planted input the held-out error is many
    times that."""
    cals, T_test, truth = _planted(chain, seed=3)
    T = np.array([c.sensors_degC for c in cals])
    corr = np.corrcoef(T.T)
    assert all(max(abs(corr[j, p]) for p in PLANTED) > 0.65 for j in range(8) if j not in PLANTED)
    model = fit_thermal_map(chain, cals, NAMES)
    assert model.inputs == ("T2", "T5") and model.selected == PLANTED
    assert model.components == 2  # two heat-driven patterns above the noise, not one per coefficient
    assert model.noise_um == pytest.approx(NOISE_UM, rel=0.1)
    assert model.criterion == "bicc" and model.n_states == 10 and model.rank_deficit > 0
    assert not np.any(model.gains[..., [j for j in range(8) if j not in PLANTED]])
    # BIC, uncorrected for 10 states, takes a distractor too
    bic = fit_thermal_map(chain, cals, NAMES, criterion="bic")
    assert set(bic.inputs) > {"T2", "T5"}
    poses = _grid(chain, 3)
    tol = 2.0 * _noise_rms(chain, cals, T_test, poses, list(PLANTED))
    assert 0.02 < tol < NOISE_UM  # a calibration of 375 points averages the noise
    held_out = _held_out_rms(model, T_test, truth, poses)
    assert held_out < tol, (held_out, tol)
    # the coefficients move by tens of µm over the states: the constant model misses by far
    still = fit_thermal_map(chain, cals, NAMES, max_inputs=0)
    assert still.inputs == () and not np.any(still.gains)
    assert _held_out_rms(still, T_test, truth, poses) > 20 * tol
    # one input where two are needed: the held-out error grows many times over
    one = fit_thermal_map(chain, cals, NAMES, max_inputs=1)
    assert len(one.inputs) == 1
    assert _held_out_rms(one, T_test, truth, poses) > 10 * tol
    # the temperatures as a mapping of the used sensors; a used sensor outside its training range is reported
    T0 = T_test[0]
    np.testing.assert_array_equal(model.model_at({"T2": T0[1], "T5": T0[4]}).coef,
                                  model.model_at(np.where(np.isin(np.arange(8), PLANTED), T0, model.reference_degC)).coef)
    hot = model.reference_degC.copy()
    hot[4] = model.range_degC[4, 1] + 1.0
    assert model.outside(hot) == ("T5",)


def test_a_sensor_that_hardly_varies_is_no_candidate(chain):
    """T2 read through a gauge that shrinks its swing 100-fold (0.03 K over the training states, below min_range_K
    = 0.1 K): a perfect predictor in training, whose gain of 100 times the true one would turn any later offset of
    a few hundredths of a kelvin into microns. It is no candidate, and its gain stays zero; with min_range_K = 0 it
    is taken."""
    cals, _, _ = _planted(chain, seed=3, noise=0.0)
    ref = np.mean([c.sensors_degC[1] for c in cals])
    flat = []
    for c in cals:
        T = c.sensors_degC.copy()
        T[1] = ref + 0.01 * (T[1] - ref)
        flat.append(Calibration(c.poses_mm, c.error_um, T, c.time_s, c.label))
    assert 0.01 < np.ptp([c.sensors_degC[1] for c in flat]) < 0.1
    model = fit_thermal_map(chain, flat, NAMES)
    assert "T2" not in model.inputs and not np.any(model.gains[..., 1])
    assert "T2" in fit_thermal_map(chain, flat, NAMES, min_range_K=0.0).inputs


def test_calibrations_on_different_plans(chain):
    """Every other state measured without dz at every other pose, one on a denser grid: the states are brought to
    the space every plan sees, and without noise the held-out states are predicted exactly; a state on a plan too
    coarse for a cubic (4 levels: a table-side rotation's lever grows with its own axis) leaves more combinations
    unseen, which the model reports."""
    cals, T_test, truth = _planted(chain, seed=5, noise=0.0)
    mixed = []
    for i, c in enumerate(cals):
        if i % 2:
            e = c.error_um.copy()
            e[::2, 2] = np.nan
            mixed.append(Calibration(c.poses_mm, e, c.sensors_degC, c.time_s))
        elif i == 4:
            plan = _grid(chain, 6)
            mixed.append(Calibration(plan, tcp_error_um(truth(c.sensors_degC), plan), c.sensors_degC, c.time_s))
        else:
            mixed.append(c)
    same = fit_thermal_map(chain, cals, NAMES)
    model = fit_thermal_map(chain, mixed, NAMES)
    assert model.inputs == ("T2", "T5") and model.rank_deficit == same.rank_deficit
    poses = _grid(chain, 3)
    assert _held_out_rms(model, T_test, truth, poses) < 1e-6
    coarse = _grid(chain, 4)
    mixed[0] = Calibration(coarse, tcp_error_um(truth(cals[0].sensors_degC), coarse), cals[0].sensors_degC)
    assert fit_thermal_map(chain, mixed, NAMES).rank_deficit > same.rank_deficit


def test_bicc_is_above_bic_on_few_states_and_selects_no_more_inputs():
    """BICc (McQuarrie 1999) = n ln(RSS/n) + n k ln n / (n − k − 2): above BIC on few rows, equal in the limit,
    infinite without two spare rows; on 10 states with one true input among 8 it never takes more inputs than BIC,
    and over the seeds it takes fewer spurious ones."""
    n, k, rss = 10, 3, 4.0
    assert _ic(rss, n, k, "bicc") == pytest.approx(n * math.log(rss / n) + n * k * math.log(n) / (n - k - 2))
    assert _ic(rss, n, k, "bic") == pytest.approx(n * math.log(rss / n) + k * math.log(n))
    assert _ic(rss, n, k, "bicc") > _ic(rss, n, k, "bic") + 5.0
    assert _ic(rss, n, n - 2, "bicc") == _ic(rss, n, n + 1, "bicc") == math.inf
    assert _ic(rss, n, n - 1, "bic") < math.inf == _ic(0.0, n, n, "bic")  # an exact fit through every row: no score
    assert _ic(rss, 10**7, k, "bicc") == pytest.approx(_ic(rss, 10**7, k, "bic"), rel=1e-6)
    spurious = {"bic": 0, "bicc": 0}
    for seed in range(40):
        rng = np.random.default_rng(seed)
        X = rng.normal(size=(10, 8))
        X -= X.mean(axis=0)
        Y = np.column_stack([3.0 * X[:, 0], -2.0 * X[:, 0]]) + rng.normal(size=(10, 2))
        Y -= Y.mean(axis=0)
        for limit in (10**6, 0):  # exhaustive, greedy forward
            got = {c: _select(X, Y, range(8), c, 3, limit=limit)[0] for c in spurious}
            assert len(got["bicc"]) <= len(got["bic"]), (seed, limit, got)
            if limit:
                spurious["bic"] += len(set(got["bic"]) - {0})
                spurious["bicc"] += len(set(got["bicc"]) - {0})
    assert spurious["bicc"] < spurious["bic"], spurious


def test_the_dict_form_round_trips_through_json(chain):
    cals, T_test, _ = _planted(chain, seed=3)
    model = fit_thermal_map(chain, cals, NAMES)
    d = json.loads(json.dumps(to_dict(model)))
    back = from_dict(d)
    assert isinstance(back, ThermalErrorModel)
    for f in ("sensor_names", "selected", "criterion", "n_states", "noise_um", "rank_deficit", "components", "degree"):
        assert getattr(back, f) == getattr(model, f), f
    for f in ("reference_degC", "coef0", "gains", "range_degC"):
        np.testing.assert_array_equal(getattr(back, f), getattr(model, f))
    for f in ("axes", "directions", "sides", "travel_mm"):
        assert getattr(back.chain, f) == getattr(chain, f)
    poses = _grid(chain, 3)
    np.testing.assert_array_equal(predict_um(back, T_test[0], poses), predict_um(model, T_test[0], poses))
    with pytest.raises(ThermalMapError, match="not a thermal error map: format 'x'"):
        from_dict({**d, "format": "x"})
    with pytest.raises(ThermalMapError, match="thermal error map version 2, this program reads 1"):
        from_dict({**d, "version": 2})
    with pytest.raises(ThermalMapError, match="field 'gains' missing"):
        from_dict({k: v for k, v in d.items() if k != "gains"})
    with pytest.raises(ThermalMapError, match=r"coef0 has shape \(3, 6, 3\), expected \(3, 6, 4\)"):
        from_dict({**d, "coef0": np.zeros((3, 6, 3)).tolist()})
    with pytest.raises(ThermalMapError, match="gains of a sensor not in selected are not zero"):
        from_dict({**d, "selected": [1]})
    with pytest.raises(ThermalMapError, match=r"chain.ref_mm has shape \(2, 3\), expected \(3, 3\)"):
        from_dict({**d, "chain": {**d["chain"], "ref_mm": d["chain"]["ref_mm"][:2]}})


def test_bad_input_is_refused_naming_the_field(chain):
    cals, _, _ = _planted(chain, seed=3, n_train=6)
    c = cals[0]

    def fit(**kw):
        return fit_thermal_map(chain, **(dict(calibrations=cals, sensor_names=NAMES) | kw))

    cases = [
        (dict(calibrations=cals[:1]), "calibrations: 1 thermal state"),
        (dict(sensor_names=NAMES[:7]), r"calibration 0 \('state 0'\): sensors_degC has 8 values for 7 sensors"),
        (dict(sensor_names=NAMES[:7] + ("T1",)), "sensor_names: 'T1' is given twice"),
        (dict(criterion="aic"), "criterion: 'aic', expected one of bicc, bic"),
        (dict(max_inputs=-1), "max_inputs: -1 must be a whole number"),
        (dict(calibrations=[c, Calibration(c.poses_mm + 1e4, c.error_um, c.sensors_degC, label="far")]),
         r"calibration 1 \('far'\): axis X at .* mm is outside its travel"),
        (dict(calibrations=[c, Calibration(c.poses_mm[:, :2], c.error_um, c.sensors_degC)]),
         "calibration 1: poses_mm has 2 columns for the axes X, Y, Z"),
    ]
    for kw, msg in cases:
        with pytest.raises(ThermalMapError, match=msg):
            fit(**kw)
    T = c.sensors_degC.copy()
    T[2] = np.nan
    with pytest.raises(ThermalMapError, match=r"calibration 'bad': sensors_degC\[2\] = nan is not finite"):
        Calibration(c.poses_mm, c.error_um, T, label="bad")
    with pytest.raises(ThermalMapError, match="calibration: error_um has no finite value"):
        Calibration(c.poses_mm, np.full_like(c.error_um, np.nan), c.sensors_degC)
    with pytest.raises(ThermalMapError, match=r"error_um must be \(125 poses × 3\)"):
        Calibration(c.poses_mm, c.error_um[:-1], c.sensors_degC)
    with pytest.raises(ValueError):  # a ValueError too: callers that catch ValueError keep working
        Calibration(c.poses_mm, c.error_um, c.sensors_degC, time_s=math.inf)
    model = fit()
    with pytest.raises(ThermalMapError, match=r"sensors_degC: 7 values \(shape \(7,\)\) for 8 sensors"):
        model.model_at(c.sensors_degC[:7])
    with pytest.raises(ThermalMapError, match="sensors_degC: T3 = inf is not finite"):
        model.model_at(np.where(np.arange(8) == 2, np.inf, c.sensors_degC))
    with pytest.raises(ThermalMapError, match="sensors_degC: sensor 'T9' is not one of"):
        model.model_at({"T9": 20.0, **{n: 20.0 for n in model.inputs}})
    assert model.inputs == ("T2", "T5")
    with pytest.raises(ThermalMapError, match="no value for sensor 'T2', which the model uses"):
        model.model_at({"T5": 20.0})
