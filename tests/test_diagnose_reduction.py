"""The reduced model's own error for heat anywhere on the surface (``diagnose.reduction``), against direct runs."""

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import hybridcomp as hc
from hybridcomp.diagnose.locate import patch_rows, surface_sites
from hybridcomp.diagnose.reduction import surface_error, surface_order


@pytest.fixture(scope="module")
def rom_with_basis(machine, model_200mm):
    return hc.reduce_model(model_200mm, order=30, check_loads=hc.example_loads(machine, duration_h=1.0, dt_s=600.0))


def _few_sites(machine, rom, model, idx):
    s = surface_sites(machine, rom, model.mesh)
    return dataclasses.replace(s, position_mm=s.position_mm[idx], reference_mm=s.reference_mm[idx],
                               body=tuple(s.body[i] for i in idx), Br=s.Br[:, idx])


def test_surface_error_is_the_direct_step_responses_difference(machine, model_200mm, rom_with_basis):
    """The FE step responses of every site from one run per sensor (symmetry) equal direct runs with the site's heat,
    and the reduced model's equal its own backward-Euler steps: the error and peak per site, by hand."""
    model, rom = model_200mm, rom_with_basis
    sites = _few_sites(machine, rom, model, [0, 7, 40])
    dt, n_steps = 600.0, 12
    got = surface_error(machine, model, rom, sites, duration_s=dt * n_steps, step_s=dt)
    rows = sp.csr_matrix(patch_rows(machine, rom, sites.mesh, list(sites.body), sites.reference_mm, sites.patch_mm))
    q = len(model.sensor_names)
    C = model.C.toarray()[:q] if sp.issparse(model.C) else np.asarray(model.C)[:q]
    K = sp.csr_matrix(model.K) + sum(h * sp.csr_matrix(H) for h, H in zip(model.h_W_m2K, model.H))
    M = sp.csr_matrix(model.M)
    solve = spla.factorized(sp.csc_matrix(M + dt * K))
    Mr, Kr, Cr = np.asarray(rom.M), rom.stiffness(), np.asarray(rom.C)[:q]
    for j in range(sites.n):
        b = rows[j].toarray().ravel()
        x, xr = np.zeros(model.n), np.zeros(rom.order)
        err = peak = 0.0
        for _ in range(n_steps):
            x = solve(M @ x + dt * b)
            xr = np.linalg.solve(Mr + dt * Kr, Mr @ xr + dt * (rom.V.T @ b))
            err = max(err, float(np.abs(Cr @ xr - C @ x).max()))
            peak = max(peak, float(np.abs(C @ x).max()))
        assert got.peak_K[j] == pytest.approx(peak, rel=1e-8)
        assert got.error_K[j] == pytest.approx(err, rel=1e-6, abs=1e-12 * peak)
    assert got.worst == pytest.approx(np.max(got.error_K / got.peak_K), rel=1e-12)


def test_surface_order_stops_at_the_first_order_within(machine, model_200mm, rom_with_basis):
    """The ladder stops at the first order within the tolerance, runs to its end otherwise."""
    calls = []

    def prepare(order):
        calls.append(order)
        return rom_with_basis

    steps = {"duration_s": 3600.0, "step_s": 600.0}
    _, tried = surface_order(machine, model_200mm, 1e-12, orders=(30, 60), prepare=prepare, **steps)
    assert calls == [30, 60] and len(tried) == 2
    calls.clear()
    got, again = surface_order(machine, model_200mm, tried[0].worst, orders=(30, 60), prepare=prepare, **steps)
    assert calls == [30] and len(again) == 1 and again[0].worst == tried[0].worst and got is rom_with_basis
    with pytest.raises(ValueError, match="relative tolerance"):
        surface_order(machine, model_200mm, 0.0, prepare=prepare)
