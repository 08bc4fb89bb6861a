"""The pose history of the pose-aware model: the support poses' blocks blended where the machine was
(:func:`hybridcomp.rom.poses.blend_history`, :func:`~hybridcomp.rom.poses.integrate_along`)."""

from __future__ import annotations

import numpy as np
import pytest

from hybridcomp.rom.poses import StepPoses, blend_history, grid_of, history_cuts, integrate_along
from hybridcomp.rom.reduced import RomInputError, load_rom, save_rom


def test_the_history_blends_at_its_ticks_where_the_machine_moved():
    """Ticks every 300 s, steps of 60 s: a hold is left alone, a move at a tick blends with the pose left, a move
    within a window blends at the next tick with where the machine was in it; a wiggle below the tolerance is none."""
    a, b = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.5, 0.5])
    t = np.arange(21) * 60.0
    hold_then_move = np.array([a] * 10 + [b] * 11)  # the move at 600 s, a tick
    cuts = history_cuts(t, hold_then_move, tol=0.1, tick_s=300.0)
    assert [k for k, _ in cuts] == [10] and np.allclose(cuts[0][1], a)
    mid = np.array([a] * 7 + [b] * 14)  # the move at 420 s, within the window 300-600 s
    cuts = history_cuts(t, mid, tol=0.1, tick_s=300.0)
    assert [k for k, _ in cuts] == [10] and np.allclose(cuts[0][1], (2 * a + 3 * b) / 5)
    wiggle = np.array([a] * 21)
    wiggle[3] = a + np.array([0.05, -0.05, 0.0])
    assert history_cuts(t, wiggle, tol=0.1, tick_s=300.0) == []
    # the same path on 5 min steps: the same blends (the clock, not the step, decides)
    t5, mid5 = t[::5], mid[::5]
    assert [(t5[k], w.round(12).tolist()) for k, w in history_cuts(t5, np.array([a, b, b, b, b]), 0.1, 300.0)] == \
        [(300.0, a.tolist())]
    assert [t5[k] for k, _ in history_cuts(t5, mid5, 0.1, 300.0)] == [600.0]  # as on the 1 min steps


def _steps_of(samples_t, samples_w, t):
    """The StepPoses of the steps of ``t`` from samples (each for the time until the next), by hand."""
    rows = [StepPoses.of(samples_w[(samples_t >= a) & (samples_t < b)]) for a, b in zip(t[:-1], t[1:])]
    rows.append(rows[-1])
    return StepPoses(*(np.array([getattr(r, f) for r in rows]) for f in ("weights", "low", "high", "first")))


def test_the_same_samples_blend_alike_on_1_and_5_min_steps():
    """Samples every 10 s; the machine at ``a`` but for short excursions just beyond the tolerance (0.11) and
    one within it (0.09): the blends at the same ticks with the same weights whatever the step, as the samples
    decide.  (Deciding on a step's mean and its samples' distance from it, the 1 min steps saw no move where the
    5 min steps saw one: a 10 s excursion is 1/6 of a 1 min step's mean, 1/30 of a 5 min step's.)"""
    a = np.array([1.0, 0.0, 0.0])
    ts = np.arange(0.0, 3600.0, 10.0)
    W = np.repeat(a[None], ts.size, 0)
    for t0, d in ((1230.0, 0.11), (2500.0, 0.09)):
        W[ts == t0] = a + np.array([-d, d, 0.0])
    cuts = {}
    for dt in (60.0, 300.0):
        t = np.arange(0.0, 3600.0 + 1.0, dt)
        cuts[dt] = [(t[k], w.round(12).tolist()) for k, w in history_cuts(t, _steps_of(ts, W, t), 0.1, 900.0)]
    assert [c[0] for c in cuts[60.0]] == [1800.0]  # the window 900-1800 s held the excursion beyond the tolerance
    assert cuts[60.0] == cuts[300.0]
    assert np.allclose(cuts[60.0][0][1], a + np.array([-0.11, 0.11, 0.0]) / 90)  # 10 s of 900


def _blocks(prom):
    n = len(grid_of(prom).poses)
    o = np.cumsum([0] + list(prom.meta["poses"]["orders"][:n]))
    return [slice(o[k], o[k + 1]) for k in range(n)], o[-1]


# the tests below take the pose-aware model of the 200 mm mesh (about 10 s, shared): slow
@pytest.mark.slow
def test_transfer_shape_and_round_trip(pose_rom_200mm, tmp_path):
    prom = pose_rom_200mm
    blocks, R = _blocks(prom)
    T = prom.pose_transfer
    assert T.shape == (R, R) and R < prom.order  # the screws' blocks are not in it
    b0 = blocks[0]  # the model pose's own basis: carried nowhere, its round trip is the identity
    assert np.allclose(T[b0, b0], np.eye(b0.stop - b0.start), atol=1e-8)
    back = load_rom(save_rom(tmp_path / "p.npz", prom))
    assert np.array_equal(back.pose_transfer, T) and back.rom_id == prom.rom_id
    changed = type(prom)(prom.operators, V=prom.V, D=prom.D, disturbance_names=prom.disturbance_names,
                         pose_transfer=T * 1.001, meta=prom.meta)
    assert changed.rom_id != prom.rom_id


@pytest.mark.slow
def test_a_uniform_rise_is_the_same_field_in_every_block(pose_rom_200mm):
    """Every air temperature +1 K, steady: the field is 1 K everywhere at every pose, so carrying it from any blend of
    blocks to any other changes nothing (the outputs stay 1 K at every sensor and α·1 K·(TCP − table) drift)."""
    prom = pose_rom_200mm
    u = np.zeros(prom.n_inputs)
    u[[i for i, n in enumerate(prom.input_names) if n.endswith("_degC")]] = 1.0
    x = prom.steady_state(u)
    y = prom.outputs(x)
    grid = grid_of(prom)
    for pose in ({"X": -250.0, "Y": 150.0, "Z": -150.0}, {"X": 0.0, "Y": 0.0, "Z": 275.0}):
        z = blend_history(prom, x, grid.weights(pose))
        assert np.allclose(prom.outputs(z), y, rtol=0, atol=1e-6 * np.abs(y).max())


@pytest.mark.slow
def test_at_a_support_pose_its_block_is_kept_and_the_others_take_its_field(pose_rom_200mm):
    prom = pose_rom_200mm
    blocks, R = _blocks(prom)
    T = prom.pose_transfer
    rng = np.random.default_rng(3)
    x = rng.standard_normal(prom.order)
    w = np.zeros(len(blocks))
    w[4] = 1.0
    z = blend_history(prom, x, w)
    assert np.allclose(z[blocks[4]], x[blocks[4]], rtol=0, atol=1e-12)
    assert np.array_equal(z[R:], x[R:])  # the screws' blocks
    for b in blocks:  # each takes the difference between block 4's field and its own, as its round trip sees it
        assert np.allclose(z[b], x[b] + T[b, blocks[4]] @ x[blocks[4]] - T[b, b] @ x[b], rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=f"weights for {len(blocks)} support poses"):
        blend_history(prom, x, w[:3])
    with pytest.raises(ValueError, match="sum to 1, got sum 2"):
        blend_history(prom, x, 2 * w)


@pytest.mark.slow
def test_without_moves_the_path_is_the_plain_integration(pose_rom_200mm, machine):
    from hybridcomp.fem.loads import example_loads

    prom = pose_rom_200mm
    loads = example_loads(machine, 4.0, 300.0)
    U = prom.layout().inputs(loads.names, loads.values)
    P = np.tile([100.0, -50.0, 20.0], (loads.time_s.size, 1))
    Y0, x0 = prom.integrate(loads.time_s, U)
    for history in ("moves", "none"):
        Y, x = integrate_along(prom, loads.time_s, U, P, history=history)
        assert np.array_equal(Y, Y0) and np.array_equal(x, x0)
    with pytest.raises(ValueError, match="history must be one of"):
        integrate_along(prom, loads.time_s, U, P, history="sometimes")


@pytest.mark.slow
def test_a_model_without_transfer_is_refused(pose_rom_200mm):
    prom = pose_rom_200mm
    old = type(prom)(prom.operators, V=prom.V, D=prom.D, disturbance_names=prom.disturbance_names, meta=prom.meta)
    with pytest.raises(RomInputError, match="no pose transfer"):
        blend_history(old, np.zeros(prom.order), grid_of(prom).weights({}))


@pytest.mark.slow
def test_the_monitors_steps_follow_the_poses_as_the_path_integration_does(pose_rom_200mm):
    """The daemon's model steps (:func:`hybridcomp.monitor.volumetric.advance` with each step's weights) blend the
    blocks at the moves exactly as :func:`integrate_along` does over the same steps, and the state round-trips with
    its weights."""
    from hybridcomp.monitor import volumetric

    prom = pose_rom_200mm
    pm = volumetric.pose_model(prom, points=2)
    rng = np.random.default_rng(5)
    n, dt = 24, 300.0
    t = np.arange(n + 1) * dt
    U = np.abs(rng.standard_normal((n + 1, prom.n_inputs))) * np.where(
        [name.endswith("_W") for name in prom.input_names], 50.0, 0.5)
    stops = [[-250.0, 150.0, -150.0], [280.0, -220.0, 120.0], [0.0, 0.0, 275.0]]
    P = np.array([stops[(k // 5) % 3] for k in range(n + 1)])  # row k: the pose of the step from t[k] on
    Y, x = integrate_along(prom, t, U, P, initial=prom.steady_state(U[0]), history="moves", hold="step")
    track = volumetric.start(pm, U[0], 0.0, dt)
    for k in range(1, n + 1):  # the step ending at t[k] ran at row k − 1's pose, with the inputs of row k
        track = volumetric.advance(pm, track, U[k], t[k], dt, weights=volumetric.step_weights(pm, P[k - 1:k]))
    assert np.allclose(track.x, x, rtol=1e-9, atol=1e-12 * np.abs(x).max())
    ignored, _ = integrate_along(prom, t, U, P, initial=prom.steady_state(U[0]), history="none", hold="step")
    assert not np.allclose(ignored[-1], Y[-1], rtol=1e-3)  # the moves did change the state
    back = volumetric.state_in(pm, volumetric.state_out(track), U[-1], dt)
    assert back.history.as_dict() == track.history.as_dict() and np.array_equal(back.x, track.x)
    assert 0 < track.history.since_s < 900.0 + dt  # since the last tick
    s = volumetric.step_weights(pm, np.array(stops[:2]), dt_s=np.array([1.0, 3.0]))
    w0, w1 = (grid_of(prom).weights(dict(zip("XYZ", p))) for p in stops[:2])
    assert np.allclose(s.weights, 0.25 * w0 + 0.75 * w1)
    assert np.array_equal(s.first, w0) and np.array_equal(s.low, np.minimum(w0, w1))
    assert np.array_equal(s.high, np.maximum(w0, w1))
    assert s.spread == pytest.approx(0.75 * np.abs(w0 - w1).max())  # the first reading, 3/4 of the way off


@pytest.mark.slow
def test_weeks_of_continuous_motion_stay_bounded(pose_rom_200mm, machine):
    """A month of a machine that moves on every 5 min step (random poses over the whole workspace, the example
    day's loads over and over): the blends (at most one a quarter hour, with the occupancy) stay within the range
    of the model that ignores the history, and nothing builds up."""
    from hybridcomp.fem.loads import example_loads

    prom = pose_rom_200mm
    day = example_loads(machine, 16.0, 300.0)
    U_day = prom.layout().inputs(day.names, day.values)
    days = 30
    U = np.vstack([U_day[:-1]] * days + [U_day[-1:]])
    t = np.arange(U.shape[0]) * 300.0
    rng = np.random.default_rng(7)
    grid = grid_of(prom)
    lo = np.array([lv[0] for lv in grid.levels_mm])
    hi = np.array([lv[-1] for lv in grid.levels_mm])
    P = lo + (hi - lo) * rng.random((t.size, 3))
    Y, _ = integrate_along(prom, t, U, P)
    Y0, _ = integrate_along(prom, t, U, P, history="none")
    assert np.all(np.isfinite(Y))
    scale = np.abs(Y0).max(axis=0)
    assert np.all(np.abs(Y).max(axis=0) <= 1.5 * scale + 1e-12)
    early, late = slice(5 * 192, 10 * 192), slice(25 * 192, 30 * 192)  # (the loads repeat every 192 steps)
    growth = np.abs(Y[late]).max(axis=0) / np.abs(Y[early]).max(axis=0)  # nothing builds up over weeks
    assert growth.max() <= 1.1, growth.max()
