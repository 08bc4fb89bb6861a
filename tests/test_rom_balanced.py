"""Balanced truncation of exported systems (rom/balanced.py through ``reduce_matrices``) on small systems.

* a 1-D heat chain, linear finite elements (E = the FE mass matrix, symmetric A), 2 inputs, 3 outputs;
* a 1-D convection-diffusion chain (non-symmetric A, E = I absent from the file) with a feedthrough D;
* diagonal systems of decoupled channels, whose Hankel singular values and errors are known by hand.

References: scipy's dense Lyapunov solver on the error system (independent of the module's Sylvester-by-poles
route and of its closed forms), and hand formulas. Every system has at most 120 states: the file runs in seconds.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io
import scipy.linalg as la
import scipy.sparse as sp

from hybridcomp.rom import balanced as bl
from hybridcomp.rom.external import MatrixFileError, reduce_matrices


def heat_chain(n=120):
    """Linear FE heat conduction on (0, 1), both ends at zero, E = mass, A = −stiffness; 2 heated nodes, 3 points."""
    h = 1.0 / (n + 1)
    E = sp.diags([np.full(n - 1, h / 6), np.full(n, 4 * h / 6), np.full(n - 1, h / 6)], [-1, 0, 1])
    K = sp.diags([np.full(n - 1, -1 / h), np.full(n, 2 / h), np.full(n - 1, -1 / h)], [-1, 0, 1])
    B = np.zeros((n, 2))
    B[n // 5, 0] = B[2 * n // 3, 1] = 1.0
    C = np.zeros((3, n))
    C[0, n // 4] = C[1, n // 2] = C[2, 5 * n // 6] = 1.0
    return {"E": E.tocsr(), "A": (-K).tocsr(), "B": B, "C": C}


def convection_diffusion(n=100, peclet=8.0):
    """Upwind convection-diffusion on (0, 1) (non-symmetric A), E = I (not in the file), SISO with D = 0.5."""
    h = 1.0 / (n + 1)
    A = sp.diags([np.full(n - 1, 1 / h**2 + peclet / h), np.full(n, -2 / h**2 - peclet / h), np.full(n - 1, 1 / h**2)],
                 [-1, 0, 1])
    B = np.zeros((n, 1))
    B[:5, 0] = 1.0
    C = np.zeros((1, n))
    C[0, -10:] = 0.1
    return {"A": A.tocsr(), "B": B, "C": C, "D": np.array([[0.5]])}


def _dense(X):
    return X.toarray() if sp.issparse(X) else np.asarray(X, float)


def lyapunov_error(m: dict, rom) -> float:
    """‖G − G_r‖₂ / ‖G − D‖₂ by scipy's Bartels–Stewart on the (standard-form) error system."""
    def std(E, A, B, C):
        Li = la.inv(la.cholesky(E, lower=True))
        return Li @ A @ Li.T, Li @ B, C @ Li.T

    n = m["A"].shape[0]
    A1, B1, C1 = std(_dense(m.get("E", sp.identity(n))), _dense(m["A"]), m["B"], m["C"])
    Ai = la.inv(rom.E)
    A2, B2, C2 = Ai @ rom.A, Ai @ rom.B, rom.C
    P1 = la.solve_continuous_lyapunov(A1, -B1 @ B1.T)
    A = la.block_diag(A1, A2)
    B = np.vstack([B1, B2])
    C = np.hstack([C1, -C2])
    P = la.solve_continuous_lyapunov(A, -B @ B.T)
    return float(np.sqrt(max(np.trace(C @ P @ C.T), 0.0) / np.trace(C1 @ P1 @ C1.T)))


def _save(tmp_path, name, m):
    path = tmp_path / name
    scipy.io.savemat(path, m)
    return path


@pytest.mark.parametrize("adi", [False, True], ids=["dense", "low-rank ADI"])
def test_relative_error_is_unchanged_when_E_is_scaled_by_1e6_either_way(tmp_path, monkeypatch, adi):
    if adi:
        monkeypatch.setattr(bl, "DENSE_MAX_STATES", 50)  # the 120-state chain goes through LR-ADI
    m = heat_chain()
    errs = []
    for scale in (1.0, 1e-6, 1e6):
        rom = reduce_matrices(_save(tmp_path, f"h{scale:g}.mat", {**m, "E": m["E"] * scale}), order=6)
        assert rom.order == 6 and rom.meta["stable"]
        errs.append((rom.meta["h2_error_relative"], rom.meta["hinf_error_relative"]))
        # the poles scale with 1/E: the model is the same in another time unit
        if scale == 1.0:
            p0 = np.sort(np.abs(rom.poles()))
        else:
            np.testing.assert_allclose(np.sort(np.abs(rom.poles())) * scale, p0, rtol=1e-7)
    assert 1e-4 < errs[0][0] < 0.5
    for e in errs[1:]:
        np.testing.assert_allclose(e, errs[0], rtol=1e-7)


@pytest.mark.parametrize("adi", [False, True], ids=["dense", "low-rank ADI"])
def test_printed_error_equals_an_independent_lyapunov_computation(tmp_path, monkeypatch, adi):
    if adi:
        monkeypatch.setattr(bl, "DENSE_MAX_STATES", 50)
    for name, m, r in (("heat", heat_chain(), 5), ("cd", convection_diffusion(), 4)):
        rom = reduce_matrices(_save(tmp_path, f"{name}.mat", m), order=r)
        ref = lyapunov_error(m, rom)
        assert rom.meta["h2_error_relative"] == pytest.approx(ref, rel=1e-6), name
        assert rom.meta["symmetric"] == (name == "heat")
        assert 1e-6 < ref < 0.5


def test_the_order_asked_is_delivered_beyond_the_minimal_realisation_with_the_same_transfer_function(tmp_path):
    path = _save(tmp_path, "heat.mat", heat_chain())
    for r in (1, 7, 13):
        assert reduce_matrices(path, order=r).order == r
    # three decoupled channels driven, seven not: the minimal realisation has 3 states, G = Σ 1/(s + i), i = 1..3
    n = 10
    B = np.zeros((n, 1))
    B[:3, 0] = 1.0
    m = {"A": sp.diags(-np.arange(1.0, n + 1)).tocsr(), "B": B, "C": np.ones((1, n))}
    mpath = _save(tmp_path, "min.mat", m)
    for basis in ("bt", "auto"):
        rom = reduce_matrices(mpath, order=5, basis=basis)
        assert rom.order == 5 and rom.meta["minimal_order"] == 3 and rom.meta["stable"]
        assert rom.meta["h2_error_relative"] < 1e-6
        for s in (0.0, 0.7, 3.0j, 10.0 + 2.0j):  # the transfer function by hand
            g = rom.C @ np.linalg.solve(s * rom.E - rom.A, rom.B) + rom.D
            assert g[0, 0] == pytest.approx(sum(1.0 / (s + i) for i in (1, 2, 3)), rel=1e-9)
    assert reduce_matrices(mpath, order=5, basis="bt").meta["decoupled_states"] == 2
    assert reduce_matrices(mpath, order=3, basis="bt").meta["decoupled_states"] == 0


def test_h2_tol_gives_the_smallest_order_reaching_it(tmp_path):
    path = _save(tmp_path, "heat.mat", heat_chain())
    rom = reduce_matrices(path, h2_tol=1e-3)
    r = rom.order
    assert rom.meta["h2_tol_met"] and rom.meta["h2_error_relative"] <= 1e-3
    assert reduce_matrices(path, order=r - 1, basis="bt").meta["h2_error_relative"] > 1e-3  # bisected on BT
    assert len(rom.meta["h2_orders_tried"]) <= 8  # bisection, not a walk over the orders


def test_balanced_truncation_of_decoupled_channels_matches_hand_formulas(tmp_path):
    """``G = diag(c_i b_i / (e_i s + a_i))``: Gramians diagonal, σ_i = |b_i c_i| / (2 a_i) whatever e_i; truncation
    drops the smallest σ; ‖channel‖₂² = (b c)² / (2 a e); the H∞ error is the largest dropped ``|b c| / a``."""
    a = np.array([1.0, 3.0, 10.0, 0.5, 40.0, 7.0])
    e = np.array([2.0, 0.1, 5.0, 1.0, 0.02, 3.0])
    b = np.array([1.0, 2.0, 4.0, 0.2, 30.0, 1.0])
    c = np.array([1.0, 1.5, 0.5, 1.0, 0.7, 0.3])
    m = {"E": sp.diags(e).tocsr(), "A": sp.diags(-a).tocsr(), "B": np.diag(b), "C": np.diag(c)}
    r = 3
    rom = reduce_matrices(_save(tmp_path, "diag.mat", m), order=r)
    sigma = np.abs(b * c) / (2 * a)
    np.testing.assert_allclose(rom.meta["hankel_singular_values"], np.sort(sigma)[::-1], rtol=1e-10)
    drop = np.argsort(sigma)[:-r]
    n2 = (b * c) ** 2 / (2 * a * e)
    assert rom.meta["h2_error_relative"] == pytest.approx(np.sqrt(n2[drop].sum() / n2.sum()), rel=1e-8)
    gain = np.abs(b * c) / a  # each channel's peak, at ω = 0
    assert rom.meta["hinf_error_relative"] == pytest.approx(gain[drop].max() / gain.max(), rel=1e-6)
    assert rom.meta["hinf_bound_bt"] == pytest.approx(2 * sigma[drop].sum(), rel=1e-10)
    np.testing.assert_allclose(np.sort(-rom.poles().real), np.sort((a / e)[np.argsort(sigma)[-r:]]), rtol=1e-10)


def test_D_is_kept_in_the_model_and_in_the_error(tmp_path):
    """Two channels driven out of five, D ≠ 0: order 2 is exact, at every frequency (with D), error 0."""
    lam = np.array([1.0, 4.0, 9.0, 16.0, 25.0])
    B = np.array([[1.0, 0.0], [0.0, 2.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    C = np.array([[1.0, 1.0, 1.0, 1.0, 1.0], [0.0, 3.0, 0.0, 1.0, 0.0]])
    D = np.array([[0.25, -1.0], [2.0, 0.0]])
    m = {"A": sp.diags(-lam).tocsr(), "B": B, "C": C, "D": D}
    rom = reduce_matrices(_save(tmp_path, "d.mat", m), order=2)
    for s in (0.0, 1.0, 3j, 1e9j):
        G = np.array([[1 / (s + 1), 2 / (s + 4)], [0.0, 6 / (s + 4)]]) + D  # by hand
        np.testing.assert_allclose(rom.transfer(s), G, atol=1e-12)
    assert rom.meta["h2_error_relative"] < 1e-7 and rom.meta["hinf_error_relative"] < 1e-12
    assert rom.meta["matrices"]["D"] and not rom.meta["matrices"]["E"]


def test_the_non_symmetric_system_with_D_reduces_stably_and_quadrature_agrees(tmp_path):
    m = convection_diffusion()
    rom = reduce_matrices(_save(tmp_path, "cd.mat", m), order=6)
    assert rom.meta["stable"] and np.all(rom.poles().real < 0)
    np.testing.assert_array_equal(rom.D, m["D"])
    n = m["A"].shape[0]
    full = (sp.identity(n, format="csr"), m["A"], m["B"], m["C"], m["D"])
    spec = rom.meta["spectrum"]
    q = bl.quadrature_h2_error(full, (rom.E, rom.A, rom.B, rom.C, rom.D), spec["slowest_rate"], spec["fastest_rate"])
    assert rom.meta["h2_error_relative"] == pytest.approx(q, rel=1e-4)


def _expect(tmp_path, name, m, match, **kw):
    with pytest.raises(MatrixFileError, match=match):
        reduce_matrices(_save(tmp_path, name, m), **kw)


def test_refusals_name_the_file_the_variable_and_the_property_before_any_long_computation(tmp_path, monkeypatch):
    def never(*a, **k):
        raise AssertionError("the Gramians were computed before the refusal")

    monkeypatch.setattr(bl, "gramian_factors", never)
    m = heat_chain(60)
    _expect(tmp_path, "cplx.mat", {**m, "B": m["B"] * (1 + 1j)}, r"cplx\.mat: variable 'B' is complex", order=3)
    E = sp.lil_matrix(m["E"])
    E[0, 1] += 0.01
    _expect(tmp_path, "asym.mat", {**m, "E": E.tocsr()}, r"asym\.mat: variable 'E' is not symmetric", order=3)
    E = m["E"].tolil()
    E[5, 5] = -1.0
    _expect(tmp_path, "indef.mat", {**m, "E": E.tocsr()}, r"indef\.mat: variable 'E' is not positive definite",
            order=3)
    _expect(tmp_path, "unst.mat", {**m, "A": -m["A"]}, r"unst\.mat: variable 'A' is symmetric but not negative "
            r"definite: the system is not asymptotically stable", order=3)
    cd = convection_diffusion(60)
    _expect(tmp_path, "unst2.mat", {**cd, "A": cd["A"] + 1e5 * sp.identity(60)},
            r"unst2\.mat: variable 'A' makes the system unstable", order=3)
    _expect(tmp_path, "dshape.mat", {**m, "D": np.zeros((2, 2))}, r"dshape\.mat: variable 'D' has shape \(2, 2\), "
            r"expected \(3, 2\)", order=3)
    _expect(tmp_path, "nsym.mat", cd, r"nsym\.mat: variable 'A' is not symmetric; the h2 basis", order=3, basis="h2")


def test_an_error_far_below_the_gramians_round_off_is_still_right(tmp_path):
    """Five channels, one of them 1e-7 as strong: dropping it leaves a relative H2 error of about 1e-7, which the
    Lyapunov terms (each the size of ‖G‖²) cannot resolve; the printed figure is the quadrature's, by hand."""
    a = np.array([1.0, 2.0, 5.0, 11.0, 3.0])
    e = np.array([1.0, 0.5, 2.0, 1.0, 0.3])
    bc = np.array([1.0, 0.8, 1.3, 0.6, 1e-7])
    m = {"E": sp.diags(e).tocsr(), "A": sp.diags(-a).tocsr(), "B": np.diag(bc), "C": np.eye(5)}
    rom = reduce_matrices(_save(tmp_path, "tiny.mat", m), order=4)
    n2 = bc**2 / (2 * a * e)
    assert rom.meta["h2_error_method"] == "quadrature" and "quadrature" in rom.meta["h2_error_note"]
    assert rom.meta["h2_error_relative"] == pytest.approx(np.sqrt(n2[4] / n2.sum()), rel=1e-3)


def test_irka_from_balanced_truncation_and_the_default_keeps_the_better(tmp_path):
    m = convection_diffusion()
    path = _save(tmp_path, "cd.mat", m)
    irka = reduce_matrices(path, order=4, basis="irka")
    assert irka.order == 4 and irka.meta["stable"] and irka.meta["basis"] == "irka"
    assert irka.meta["h2_error_relative"] == pytest.approx(lyapunov_error(m, irka), rel=1e-6)
    auto = reduce_matrices(path, order=4)
    cand = auto.meta["candidates_h2_error_relative"]
    assert set(cand) == {"bt", "irka"} and auto.meta["h2_error_relative"] == pytest.approx(min(cand.values()))
    assert auto.meta["basis"] == min(cand, key=cand.get)


def mass_spring_damper(n=60, m_i=4.0, k_i=4.0, c_i=1.0):
    """The chain of Gugercin, Polyuga, Beattie, van der Schaft (2012): states (q_j, p_j), forces on the first two
    masses, their velocities measured (2 × 2, non-symmetric, lightly damped)."""
    N = n // 2
    A = np.zeros((n, n))
    for j in range(N):
        q, p = 2 * j, 2 * j + 1
        A[q, p] = 1.0 / m_i
        A[p, p] = -c_i / m_i
        A[p, q] = -k_i if j == 0 else -2 * k_i
        if j > 0:
            A[p, q - 2] = k_i
        if j < N - 1:
            A[p, q + 2] = k_i
    B = np.zeros((n, 2))
    B[1, 0] = B[3, 1] = 1.0
    return {"A": sp.csr_matrix(A), "B": B, "C": B.T / m_i}


def penzl_mimo(n=200):
    """Penzl's system (three lightly damped 2 × 2 blocks at 100, 200, 400 rad/s and −1 … −(n − 6)), 2 × 3 as in
    pyMOR's ``penzl_mimo_example``."""
    blocks = [np.array([[-1.0, w], [-w, -1.0]]) for w in (100.0, 200.0, 400.0)]
    A = sp.block_diag([*blocks, sp.diags(-np.arange(1.0, n - 5))]).tocsr()
    return {"A": A, "B": np.arange(2 * n, dtype=float).reshape(n, 2), "C": np.arange(3 * n, dtype=float).reshape(3, n)}


def test_irka_from_several_starts_beats_the_start_from_balanced_truncation(tmp_path):
    """On the mass-spring-damper chain at order 6, IRKA from balanced truncation's model stops in a local optimum
    twice as bad as the one reached from shifts around the fastest rate; the default keeps the best, in either
    time unit, and its printed error is scipy's Lyapunov figure."""
    m = mass_spring_damper()
    n = m["A"].shape[0]
    E, A = sp.identity(n, format="csr"), m["A"]
    Zp, Zq = bl.dense_gramian_factors(E, A, m["B"], m["C"], symmetric=False)
    bt = bl.truncate(E, A, m["B"], m["C"], bl.balance(E, Zp, Zq), 6)[:4]
    single, _, _ = bl.irka(E, A, m["B"], m["C"], bt)
    e_single = bl.h2_error(E, A, m["B"], m["C"], Zp, *single[:4])
    errs = []
    for scale in (1.0, 1e6):
        rom = reduce_matrices(_save(tmp_path, f"msd{scale:g}.mat", {**m, "E": scale * sp.identity(n)}), order=6)
        assert rom.order == 6 and rom.meta["stable"] and rom.meta["basis"] == "irka"
        errs.append(rom.meta["h2_error_relative"])
    assert errs[0] == pytest.approx(lyapunov_error(m, reduce_matrices(_save(tmp_path, "m.mat", m), order=6)), rel=1e-6)
    assert errs[0] < 0.5 * e_single
    assert errs[1] == pytest.approx(errs[0], rel=1e-6)


def test_penzl_mimo_reduces_to_the_same_error_in_either_time_unit(tmp_path):
    """Every shift, start and tolerance comes from the system: E × 1e6 gives the same model in another unit."""
    m = penzl_mimo()
    got, roms = [], []
    for scale in (1.0, 1e6):
        rom = reduce_matrices(_save(tmp_path, f"p{scale:g}.mat", {**m, "E": scale * sp.identity(200)}), order=10)
        assert rom.order == 10 and rom.meta["stable"]
        roms.append(rom)
        got.append((rom.meta["h2_error_relative"], rom.meta["method"].split(" (")[0], np.sort(np.abs(rom.poles())) * scale))
    assert got[1][0] == pytest.approx(got[0][0], rel=1e-6) and got[1][1] == got[0][1]
    # IRKA stops once its shifts move by less than IRKA_TOL: the poles of two runs whose round-off differs (another
    # unit, another CPU) agree to that, not to round-off (8e-6 measured on one CPU, 1e-7 on another)
    np.testing.assert_allclose(got[1][2], got[0][2], rtol=bl.IRKA_TOL)
    assert got[0][0] == pytest.approx(lyapunov_error(m, roms[0]), rel=1e-3)


def test_gramian_factors_resolve_hankel_singular_values_down_to_1e_12():
    """Decoupled channels in an unbalanced realisation (inputs from 1 down to 1e-11, outputs 1), seen through a
    non-orthogonal change of state: σ_i = |b_i c_i| / (2 a_i) by hand, from 0.5 down to 1e-13. A factor taken as
    the square root of an assembled Gramian loses every σ below about 1e-8 σ_1 (the Gramian's eigenvalues b_i² /
    (2 a_i) fall below its round-off); Hammarling's and the Cauchy factors, computed as factors, keep them."""
    rng = np.random.default_rng(3)
    n = 14
    a = np.geomspace(1.0, 50.0, n)
    b, c = np.geomspace(1.0, 1e-11, n), np.ones(n)
    sigma = np.sort(b * c / (2 * a))[::-1]
    Q = la.qr(rng.normal(size=(n, n)))[0]
    S = Q @ (np.eye(n) + 0.3 * rng.normal(size=(n, n)) / np.sqrt(n))  # well conditioned, not orthogonal
    Si = la.inv(S)
    E = sp.identity(n, format="csr")
    for sym, (A, B, C) in (("nonsymmetric", (S @ np.diag(-a) @ Si, S @ np.diag(b), np.diag(c) @ Si)),
                           ("symmetric", (Q @ np.diag(-a) @ Q.T, Q @ np.diag(b), np.diag(c) @ Q.T))):
        Zp, Zq = bl.dense_gramian_factors(E, sp.csr_matrix(A), B, C, symmetric=sym == "symmetric")
        hsv = bl.balance(E, Zp, Zq).hsv
        keep = sigma > 1e-12 * sigma[0]
        np.testing.assert_allclose(hsv[: keep.sum()], sigma[keep], rtol=1e-3, err_msg=sym)


def test_the_refined_transfer_function_agrees_with_50_digit_arithmetic():
    """``transfer_refined`` against mpmath at 50 digits on the same (double) matrices: to 1e-17 relative, where
    the plain double solve is off by about 1e-16 to 1e-14 (a non-normal 12-state system)."""
    mpmath = pytest.importorskip("mpmath")
    rng = np.random.default_rng(3)
    n = 12
    A = -np.diag(np.geomspace(0.1, 100.0, n)) + np.triu(rng.normal(0, 5, (n, n)), 1)
    E = np.eye(n) + 0.1 * rng.normal(size=(n, n)) @ rng.normal(size=(n, n)).T / n
    B, C = rng.normal(size=(n, 2)), rng.normal(size=(3, n))
    mpmath.mp.dps = 50
    for s in (0.3j, 2.0 + 5.0j, 70.0j):
        K = mpmath.matrix([[mpmath.mpc(complex(s)) * mpmath.mpf(E[i, j]) - mpmath.mpf(A[i, j]) for j in range(n)]
                           for i in range(n)])
        ref = np.zeros((3, 2), complex)
        for j in range(2):
            x = mpmath.lu_solve(K, mpmath.matrix(B[:, j].tolist()))
            for i in range(3):
                ref[i, j] = complex(sum(mpmath.mpf(C[i, k]) * x[k] for k in range(n)))
        got = bl.transfer_refined(E, A, B, C, s)
        scale = np.abs(ref).max()
        assert np.abs(got.astype(complex) - ref).max() <= 1e-17 * scale
        assert got.dtype == np.clongdouble


def test_an_error_at_double_round_off_is_resolved_by_the_refined_quadrature():
    """A non-normal 30-state system S (cond 4e4) beside a decoupled weak channel ``w / (s + 2)``; the reduced model
    is S itself. The error is the weak channel's, by hand (S's norm from scipy's Lyapunov solver): 2.3e-16, 2.3e-18
    relative. Refined, the quadrature gives it to about one long-double unit of |G| relative to the error (measured
    0.01 % and 0.6–1.5 % on two grids on one CPU, 2.8 % at 2.3e-18 on another; the limit there is eps/error = 4.8 %);
    in double it read 2.4–3.6× and 230–340× too high (each G(iω) carries about 1e-15 of round-off)."""
    eps = float(np.finfo(np.longdouble).eps)
    if eps > 1e-17:
        pytest.skip(f"this platform's long double is no wider than double (eps {eps:.1e}): nothing to refine in")
    rng = np.random.default_rng(5)
    n = 30
    S = -np.diag(np.geomspace(0.5, 50.0, n)) + np.triu(rng.normal(0, 3, (n, n)), 1)
    Bs, Cs = rng.normal(size=(n, 1)), rng.normal(size=(1, n))
    gs2 = (Cs @ la.solve_continuous_lyapunov(S, -Bs @ Bs.T) @ Cs.T).item()
    red = (np.eye(n), S, Bs, Cs, np.zeros((1, 1)))
    for w in (1e-13, 1e-15):
        A = sp.block_diag([sp.csr_matrix(S), sp.csr_matrix([[-2.0]])]).tocsr()
        full = (sp.identity(n + 1, format="csr"), A, np.vstack([Bs, [[w]]]), np.hstack([Cs, [[1.0]]]), np.zeros((1, 1)))
        hand = np.sqrt(w**2 / 4.0 / (gs2 + w**2 / 4.0))
        rel = eps / hand  # one long-double unit of |G| against the error: 4.8e-4 at w = 1e-13, 4.8 % at 1e-15
        for per_decade in (8, 16):
            got = bl.quadrature_h2_error(full, red, 0.5, 50.0, per_decade, refined=True)
            assert got == pytest.approx(hand, rel=rel, abs=0.0)


def test_balancing_free_bases_are_orthonormal_and_span_the_square_root_ones():
    m = heat_chain(60)
    E, A, B, C = m["E"], m["A"], m["B"], m["C"]
    bal = bl.balance(E, *bl.gramian_factors(E, A, B, C, True)[:2])
    for r in (3, 8):
        V, W = bal.bases(r)
        Vf, Wf = bal.bases_balancing_free(r)
        assert np.allclose(Vf.T @ Vf, np.eye(r), atol=1e-12) and np.allclose(Wf.T @ Wf, np.eye(r), atol=1e-12)
        # the same spaces: projecting the square-root bases onto them leaves nothing
        assert np.linalg.norm(V - Vf @ (Vf.T @ V)) <= 1e-9 * np.linalg.norm(V)
        assert np.linalg.norm(W - Wf @ (Wf.T @ W)) <= 1e-9 * np.linalg.norm(W)
