"""Physics checks on the bundled demonstrator (coarse meshes).

Exact statements the discretisation must honour whatever the mesh: uniform air
warming gives a uniform temperature and free expansion; heat in equals heat
convected out at steady state; the adjoint drift rows equal the direct
displacement solve; the θ-method converges at its order.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridcomp.fem.export import displacement_fields
from hybridcomp.fem.loads import full_power_inputs, input_columns
from hybridcomp.fem.model import build_model
from hybridcomp.fem.stepping import integrate_inputs, steady_state
from hybridcomp.models.geometry import table_point

# every test builds the demonstrator's FE model (at two poses, or the module's own)
pytestmark = pytest.mark.slow

H_MM = 150.0  # coarse: ~2,000 nodes


@pytest.fixture(scope="module")
def model(model_150mm):
    assert model_150mm.machine.mesh.element_size_mm == H_MM
    return model_150mm


def one_alpha(machine):
    """The machine with every body of cast iron (one expansion coefficient)."""
    ci = machine.materials["cast_iron"]
    return dataclasses.replace(machine, materials={k: dataclasses.replace(ci, name=k) for k in machine.materials})


def air_rise(model, dT_K: float) -> np.ndarray:
    u = np.zeros(len(model.input_names))
    u[len(model.heat_names):] = dT_K
    return u


def full_power(model) -> np.ndarray:
    assert tuple(model.input_names) == input_columns(model.machine)
    return full_power_inputs(model.machine)


@pytest.mark.parametrize("pose", [{}, {"X": 300.0, "Y": -200.0, "Z": 250.0}])
def test_uniform_air_rise_gives_uniform_temperature_and_free_expansion(machine, pose):
    m = one_alpha(machine)
    mod = build_model(m, pose, H_MM)
    x = steady_state(mod, air_rise(mod, 1.0))
    np.testing.assert_allclose(mod.C @ x, 1.0, atol=1e-9)
    np.testing.assert_allclose(x, 1.0, atol=1e-9)
    full = m.check_pose(pose)
    tcp = (np.asarray(m.tcp.position_mm) + m.body_offset_mm(m.tcp.body, full)) * 1e-3
    pt = table_point(m, full)  # the table point under the tool (vmc800 sets under_tool) ...
    tab = (np.asarray(pt.position_mm) + m.body_offset_mm(pt.body, full)) * 1e-3
    tab[:2] = tcp[:2]  # ... continued past the table's edge when the tool is beyond it: exact for free expansion
    expected_um = m.materials["cast_iron"].expansion_1_K * 1.0 * (tcp - tab) * 1e6
    np.testing.assert_allclose(mod.G @ x * 1e6, expected_um, rtol=1e-9, atol=1e-9)
    assert np.abs(expected_um).max() > 1.0  # the check is not vacuous


def test_mixed_alpha_breaks_free_expansion(model):
    """With the steel spindle the uniform-rise drift differs from the cast-iron formula: bodies matter."""
    m = model.machine
    x = steady_state(model, air_rise(model, 1.0))
    tcp = np.asarray(m.tcp.position_mm) * 1e-3
    tab = np.asarray(table_point(m, model.mesh.pose_mm).position_mm) * 1e-3
    ci = m.materials["cast_iron"].expansion_1_K * (tcp - tab) * 1e6
    assert abs((model.G @ x * 1e6)[2] - ci[2]) > 0.05


def test_energy_balance_at_steady_state(model):
    u = full_power(model)
    x = steady_state(model, u)
    heat_in_W = u[: len(model.heat_names)].sum()
    convected_W = sum(h * (H @ x).sum() for h, H in zip(model.h_W_m2K, model.H))
    assert heat_in_W == pytest.approx(sum(s.power_W for s in model.machine.heat_sources))
    assert convected_W == pytest.approx(heat_in_W, rel=5e-3)
    assert x.max() > 1.0  # the machine really warms up


def test_heat_inputs_conserve_power_and_sit_on_their_segments(model):
    np.testing.assert_allclose(model.B.sum(axis=0), 1.0, rtol=1e-12)
    m = model.machine
    p = model.mesh.mesh.p * 1e3
    for s in m.heat_sources:
        if s.kind != "moving":
            continue
        a = m.axis(s.axis)
        d = a.direction
        off = m.body_offset_mm(s.body, model.mesh.pose_mm)[d]
        for k in range(a.n_segments):
            col = model.B[:, model.heat_names.index(f"{s.name}[{k + 1}]")]
            centre = (col @ p[d]) / col.sum()
            lo = s.position_mm[d] + a.segment_bounds_mm[k] + off - H_MM
            hi = s.position_mm[d] + a.segment_bounds_mm[k + 1] + off + H_MM
            assert lo <= centre <= hi, (s.name, k, centre, lo, hi)


def test_adjoint_drift_rows_equal_direct_displacement(model):
    """G x from the three adjoint solves equals TCP minus table of the directly solved displacement."""
    x = steady_state(model, full_power(model))
    u = displacement_fields(model, [x])[0]  # (n, 3) [m]
    from hybridcomp.fem import assembly
    from hybridcomp.fem.model import _point_rows

    basis = assembly.cell_basis(model.mesh.mesh)
    m = model.machine
    P = _point_rows(m, model.mesh, basis, [m.tcp, table_point(m, model.mesh.pose_mm)])
    direct = (P[0] - P[1]) @ u
    np.testing.assert_allclose(model.G @ x, np.asarray(direct).ravel(), rtol=1e-8, atol=1e-12)
    assert np.abs(direct).max() > 1e-6  # micrometres of drift, not round-off


def test_transient_reaches_steady_state(model):
    u = full_power(model)
    t = np.arange(0, 400 * 3600.0, 3600.0)
    res = integrate_inputs(model, t, np.tile(u, (t.size, 1)), scheme="theta", initial="reference")
    x_ss = steady_state(model, u)
    np.testing.assert_allclose(res.sensors_degC[-1], model.C @ x_ss + 20.0, atol=1e-3)
    np.testing.assert_allclose(res.drift_um[-1], model.G @ x_ss * 1e6, atol=1e-3)


@pytest.mark.parametrize("theta,order", [(1.0, 1.0), (0.5, 2.0)])
def test_theta_method_converges_at_its_order(model, theta, order):
    """Warm-up from the reference state under a smooth ramp of the spindle heat."""
    t_end = 2 * 3600.0
    j = model.heat_names.index("spindle_bearing_front")

    def run(dt):
        t = np.arange(0.0, t_end + dt / 2, dt)
        U = np.zeros((t.size, len(model.input_names)))
        U[:, j] = 100.0 * np.sin(0.5 * np.pi * t / t_end) ** 2
        return integrate_inputs(model, t, U, scheme="theta", theta=theta, initial="reference").sensors_degC[-1, 0]

    ref = run(7.5)
    e = [abs(run(dt) - ref) for dt in (240.0, 120.0, 60.0)]
    rates = np.log2(np.array(e[:-1]) / np.array(e[1:]))
    assert e[0] > 1e-4  # the error is measurable
    assert np.all(np.abs(rates - order) < 0.35), (e, rates)


def test_htc_variant_changes_steady_temperature(model):
    u = full_power(model)
    x0 = steady_state(model, u)
    hotter = model.with_htc(ambient=model.h_W_m2K[model.zone_names.index("ambient")] / 2)
    x1 = steady_state(hotter, u)
    assert (model.C @ x1 > model.C @ x0).all()
    with pytest.raises(KeyError, match="unknown zone"):
        model.with_htc(nozone=3.0)


def test_a_point_on_a_cell_face_outside_by_round_off_is_interpolated():
    """A point on a hexahedron's face, outside it by 3e-13 m (a body's offset at a pose added in another order put
    vmc800's table point under the tool at Y = -216.67 mm so): the inverse mapping's Newton steps pushed it out and
    were clipped back for ever ("Newton iteration didn't converge"). Now it is taken into its cell and a linear field
    is interpolated exactly there."""
    import skfem

    from hybridcomp.fem import assembly

    mesh = skfem.MeshHex.init_tensor(np.linspace(0.0, 0.06, 3), np.linspace(-0.15, -0.116666666666667, 2),
                                     np.linspace(0.275, 0.35, 2))
    basis = assembly.cell_basis(mesh)
    p = np.array([[0.03], [-0.116666666666667 + 3.3e-13], [0.35]])
    cells = np.array([0])
    assert mesh.p[1, mesh.t[:, 0]].max() < p[1, 0]  # outside its cell, by round-off
    P = assembly.probe_matrix(basis, p, cells)
    field = 2.0 * mesh.p[0] - 5.0 * mesh.p[1] + 7.0 * mesh.p[2]
    assert (P @ field)[0] == pytest.approx(2.0 * 0.03 + 5.0 * 0.116666666666667 + 7.0 * 0.35, abs=1e-11)


@pytest.mark.parametrize("distort", [0.0, 0.3])
def test_probe_rows_reproduce_a_linear_field_on_bricks_and_distorted_hexahedra(distort):
    """Trilinear hexahedra reproduce a linear field exactly at any point inside, bricks or not. On bricks one Newton
    step of the inverse mapping is exact; distorted cells (inner nodes moved by up to 30 % of a cell) need the
    iteration: a wrong reference point would show here as a wrong value."""
    import skfem

    from hybridcomp.fem import assembly

    mesh = skfem.MeshHex.init_tensor(*(np.linspace(0.0, 0.3, 4),) * 3)
    if distort:
        rng = np.random.default_rng(3)
        inner = np.all((mesh.p > 1e-9) & (mesh.p < 0.3 - 1e-9), axis=0)
        p = mesh.p.copy()
        p[:, inner] += distort * 0.1 * rng.uniform(-1.0, 1.0, (3, inner.sum()))
        mesh = skfem.MeshHex(p, mesh.t)
    basis = assembly.cell_basis(mesh)
    rng = np.random.default_rng(7)
    cells = rng.integers(0, mesh.t.shape[1], 200)
    X = rng.uniform(0.05, 0.95, (3, 200, 1))  # points inside their cells, through the cells' own mapping
    pts = basis.mapping.F(X, tind=cells)[:, :, 0]
    P = assembly.probe_matrix(basis, pts, cells)
    field = 2.0 * mesh.p[0] - 5.0 * mesh.p[1] + 7.0 * mesh.p[2] + 0.5
    np.testing.assert_allclose(P @ field, 2.0 * pts[0] - 5.0 * pts[1] + 7.0 * pts[2] + 0.5, atol=1e-12)
