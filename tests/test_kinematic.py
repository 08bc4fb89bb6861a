"""The volumetric error model (ISO 230-1): its first-order composition against rigid-body transforms composed
exactly along the machine's chain, the Abbe error of a pitch by hand, and identification from TCP errors."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hybridcomp.chardiag.kinematic import COMPONENTS, ErrorModel, chain_of, design_matrix, identify, tcp_error_um


@pytest.fixture(scope="module")
def chain(machine):
    return chain_of(machine)


def _random_model(chain, degree, rng, um=5.0, urad=20.0):
    coef = np.zeros((len(chain.axes), 6, degree + 1))
    coef[:, :3] = rng.normal(0.0, um, (len(chain.axes), 3, degree + 1))
    coef[:, 3:] = rng.normal(0.0, urad, (len(chain.axes), 3, degree + 1))
    return ErrorModel(chain, degree, coef)


def _poses(chain, rng, m):
    lo = np.array([t[0] for t in chain.travel_mm])
    hi = np.array([t[1] for t in chain.travel_mm])
    return lo + (hi - lo) * rng.random((m, len(chain.axes)))


def _rotation(theta):
    """The exact rotation matrix of a rotation vector (Rodrigues)."""
    a = np.linalg.norm(theta)
    if a == 0:
        return np.eye(3)
    k = theta / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _exact_error_um(machine, model, pose):
    """The tool tip against the workpiece point under it with every carriage's error applied as a rigid motion,
    innermost carriage first, along the mounting chain of the machine file (independent of the model's sums)."""
    chain = model.chain
    p = dict(zip(chain.axes, pose))
    tip = np.asarray(machine.tcp.position_mm, float) + machine.body_offset_mm(machine.tcp.body, p)

    def carried(point_body):  # the axes whose carriage carries the body, innermost first
        moved_by = {a.moves: i for i, a in enumerate(machine.axes)}
        out, name = [], point_body
        while name is not None:
            if name in moved_by:
                out.append(moved_by[name])
            name = machine.body(name).mounted_on
        return out

    def displaced(x, body):
        for a in carried(body):
            f = {c: model.function(chain.axes[a], c, [pose[a]])[0] for c in COMPONENTS}
            delta = np.array([f["X"], f["Y"], f["Z"]]) * 1e-3  # mm
            theta = np.array([f["A"], f["B"], f["C"]]) * 1e-6  # rad
            box = machine.body(machine.axes[a].moves).box_mm
            o = np.mean(np.asarray(box, float), axis=0) + machine.body_offset_mm(machine.axes[a].moves, p)
            x = o + _rotation(theta) @ (x - o) + delta
        return x

    tool = displaced(tip, machine.tcp.body) - tip
    work = displaced(tip, machine.table_reference.body) - tip
    return (tool - work) * 1e3


def test_the_chain_of_the_demonstrator(chain):
    # X moves the table and Y the saddle under it (the table side), Z the headstock with the spindle (the tool side)
    assert chain.axes == ("X", "Y", "Z") and chain.sides == (-1.0, -1.0, 1.0)
    np.testing.assert_array_equal(chain.tip_moves, [0, 0, 1])
    np.testing.assert_array_equal(chain.ref_moves, [[1, 1, 0], [0, 1, 0], [0, 0, 1]])  # the table rides on Y


def test_first_order_composition_matches_rigid_motions_composed_exactly(machine, chain):
    """Errors of a few µm and tens of µrad on every axis: the model's sum agrees with the exact composition to the
    second order (rotations of ~50 µrad over lever arms of ~1 m: a few nm)."""
    rng = np.random.default_rng(4)
    model = _random_model(chain, 3, rng)
    poses = _poses(chain, rng, 20)
    got = tcp_error_um(model, poses)
    want = np.array([_exact_error_um(machine, model, p) for p in poses])
    assert np.abs(want).max() > 20.0  # errors of tens of µm, the rotations' lever arms among them
    np.testing.assert_allclose(got, want, atol=0.01)
    # the planted behaviour: a table-side axis counted as a tool-side one misses by the whole of its error
    flipped = ErrorModel(type(chain)(**{**chain.__dict__, "sides": (1.0, -1.0, 1.0)}), 3, model.coef)
    assert np.abs(tcp_error_um(flipped, poses) - want).max() > 5.0


def test_a_constant_pitch_of_the_table_gives_the_abbe_error_by_hand(chain):
    """X pitch (EBX, about y) of 10 µrad, nothing else: the workpiece point under the tool moves by θ e_y × l, l its
    lever arm from the table carriage's reference point, i.e. θ (h, 0, −l_x) with h the tool tip's height above that
    point; the TCP-minus-table error is the opposite. h changes with the Z axis' position and l_x with X's (Abbe
    offsets): the same pitch gives another error at every pose."""
    coef = np.zeros((3, 6, 4))
    coef[0, COMPONENTS.index("B"), 0] = 10.0  # µrad, constant (P0)
    model = ErrorModel(chain, 3, coef)
    seen = set()
    for x, z in itertools.product((-300.0, 100.0), (-250.0, 0.0, 250.0)):
        pose = np.array([[x, -50.0, z]])
        lx, _, h = chain.tip_at(pose)[0] - chain.refs_at(pose)[0, 0]  # mm
        e = tcp_error_um(model, pose)[0]
        assert e == pytest.approx([-10e-6 * h * 1e3, 0.0, 10e-6 * lx * 1e3], abs=1e-9)
        seen.add(tuple(np.round(e, 6)))
    assert len(seen) == 6


def test_identified_from_a_grid_the_model_predicts_anywhere(chain):
    """TCP errors at a 5 × 5 × 5 grid of a cubic model (no noise): the identified model predicts the errors at
    random poses to round-off, although some coefficient combinations are invisible (left at zero and counted)."""
    rng = np.random.default_rng(7)
    truth = _random_model(chain, 3, rng)
    levels = [np.linspace(lo, hi, 5) for lo, hi in chain.travel_mm]
    grid = np.array(list(itertools.product(*levels)))
    fitted = identify(chain, grid, tcp_error_um(truth, grid), degree=3)
    assert fitted.rank_deficit > 0  # e.g. one offset shared by all axes, the roll of Z about its own lever
    assert not np.allclose(fitted.coef, truth.coef)
    anywhere = _poses(chain, rng, 200)
    np.testing.assert_allclose(tcp_error_um(fitted, anywhere), tcp_error_um(truth, anywhere), atol=1e-7)
    # three levels per axis cannot hold a cubic: the prediction between them misses
    few = np.array(list(itertools.product(*[np.linspace(lo, hi, 3) for lo, hi in chain.travel_mm])))
    coarse = identify(chain, few, tcp_error_um(truth, few), degree=3)
    assert np.abs(tcp_error_um(coarse, anywhere) - tcp_error_um(truth, anywhere)).max() > 1.0
    # the table-side axes (X, Y) turn their carriage about a lever linear in their own position: a cubic rotation
    # gives a quartic TCP error, which 4 levels do not hold; 5 of X and Y and 4 of the tool-side Z do
    def fit(levels):
        g = np.array(list(itertools.product(*[np.linspace(lo, hi, n) for (lo, hi), n in zip(chain.travel_mm, levels)])))
        return np.abs(tcp_error_um(identify(chain, g, tcp_error_um(truth, g), degree=3), anywhere)
                      - tcp_error_um(truth, anywhere)).max()
    assert fit((4, 4, 4)) > 0.05 and fit((5, 4, 4)) > 0.05
    assert fit((5, 5, 4)) < 1e-7


def test_directions_not_measured_and_bad_input(chain):
    rng = np.random.default_rng(1)
    truth = _random_model(chain, 1, rng)
    grid = np.array(list(itertools.product(*[np.linspace(lo, hi, 3) for lo, hi in chain.travel_mm])))
    e = tcp_error_um(truth, grid)
    e[::2, 2] = np.nan  # a probe that misses dz at every other pose
    fitted = identify(chain, grid, e, degree=1)
    ok = np.isfinite(e)
    np.testing.assert_allclose(tcp_error_um(fitted, grid)[ok], e[ok], atol=1e-8)
    with pytest.raises(ValueError, match="axis X at 900 mm is outside its travel"):
        design_matrix(chain, [[900.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="one column per axis"):
        design_matrix(chain, [[0.0, 0.0]])
    with pytest.raises(ValueError, match="dx, dy, dz per pose"):
        identify(chain, grid, e[:-1], degree=1)
    with pytest.raises(ValueError, match="degree must be a whole number"):
        design_matrix(chain, grid, degree=-1)
