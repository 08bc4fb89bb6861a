"""The reduced model's own error for heat anywhere on the surface, and an order chosen by it.

The reduction is checked against FE on the machine's own heat inputs (``reduce_model``'s check load case).  A heat
source the machine file lacks (``diagnose.locate``) enters the reduced model through its basis alone (``Vᵀ b``),
which reproduces the outputs' response to heat anywhere only as well as the outputs' adjoint Krylov directions in
it do: between the expansion points the error at a sensor near such a source can be a few per cent of its response
(seen: 4.6 % at order 150 on the 150 mm mesh, 0.014 K RMS of a 0.3 K response, above a third of the 0.02 K sensor
noise, and enough to put the source on the wrong face).

* :func:`surface_error`: for every surface site (a patch one element size wide, as the search's), the largest
  error at the sensors of the reduced model's response to a 1 W step of heat there, against FE.  FE's step
  responses of every site at once by symmetry: the system is symmetric (``M``, ``K + Σ h H``), so the response of
  output ``i`` to a step of heat ``b`` is ``bᵀ w_i(t)`` with ``w_i`` the FE response to a step of heat ``c_iᵀ`` (the
  output row as a heat input): one FE run per sensor, not one per site.  Both models are stepped by backward Euler
  on the same steps, so the difference is the reduction's alone.
* :func:`surface_order`: the smallest order of ``orders`` whose error is within a tolerance relative to each site's
  own response.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

log = logging.getLogger(__name__)

#: the step responses' duration and step [s]: the job-shop day's 16 h at the benchmark's 120 s sampling
DURATION_S = 16 * 3600.0
STEP_S = 120.0
#: sites whose step response at the sensors peaks below this share of the strongest site's are not judged (a source
#: there that showed above the noise would be hundreds of times stronger than one near a sensor)
WEAK_SITE = 0.01


@dataclasses.dataclass(frozen=True)
class SurfaceError:
    """The reduced model's error for 1 W of heat stepped on at each surface site.

    Attributes
    ----------
    order : the reduced model's order
    error_K : per site, the largest error over the steps and the sensors [K per W]
    peak_K : per site, the largest response over the steps and the sensors (FE) [K per W]
    position_mm : the sites at the model's pose (n × 3) [mm]
    bodies : the body per site
    """

    order: int
    error_K: np.ndarray
    peak_K: np.ndarray
    position_mm: np.ndarray
    bodies: tuple[str, ...]

    @property
    def judged(self) -> np.ndarray:
        """The sites judged: those whose response peaks at least ``WEAK_SITE`` × the strongest site's."""
        return self.peak_K >= WEAK_SITE * self.peak_K.max()

    @property
    def relative(self) -> np.ndarray:
        """Per site, the error relative to the site's own peak response [-] (NaN for a site not judged)."""
        return np.where(self.judged, self.error_K / np.maximum(self.peak_K, 1e-300), np.nan)

    @property
    def worst(self) -> float:
        """The largest relative error over the judged sites [-]."""
        return float(np.nanmax(self.relative))

    def describe(self) -> str:
        rel = self.relative[self.judged]
        k = int(np.nanargmax(self.relative))
        return (f"order {self.order}: the step response of heat anywhere on the surface within {100 * self.worst:.2g} % "
                f"of its peak at the sensors (median {100 * np.median(rel):.2g} % over {rel.size} sites; worst on "
                f"{self.bodies[k]} at {np.round(self.position_mm[k]).tolist()} mm)")


def _fe_steps(M, K, dt_s: float, n_steps: int, rhs: np.ndarray):
    """Backward-Euler states of ``M x' = −K x + rhs`` from zero, one per step (a generator of n × k arrays)."""
    solve = spla.factorized(sp.csc_matrix(M + dt_s * K))
    x = np.zeros_like(rhs)
    for _ in range(n_steps):
        x = np.column_stack([solve(M @ x[:, j] + dt_s * rhs[:, j]) for j in range(rhs.shape[1])])
        yield x


def _rom_steps(rom, dt_s: float, n_steps: int, Br: np.ndarray, q: int):
    """The reduced model's outputs ``0..q-1`` for a unit step of each column of ``Br``, from zero (backward Euler).

    One (q × k) array per step; in its modes (``K_h Φ = M Φ Λ``) each decays by ``1/(1 + Δt λ)`` a step.
    """
    lam, Phi = rom._modes()
    CP = np.asarray(rom.C)[:q] @ Phi
    F = Phi.T @ Br
    a = 1.0 / (1.0 + dt_s * lam)
    z = np.zeros_like(F)
    for _ in range(n_steps):
        z = a[:, None] * (z + dt_s * F)
        yield CP @ z


def surface_error(machine, model, rom, sites=None, duration_s: float = DURATION_S,
                  step_s: float = STEP_S) -> SurfaceError:
    """The reduced model's error at the sensors for a 1 W step of heat at every surface site, against FE.

    Parameters
    ----------
    machine : the machine as the diagnosis gets it (its mesh settings sample the patches' heat, as the search's)
    model : the FE model the reduced model was made of (:class:`~hybridcomp.fem.model.ThermoElasticModel`)
    rom : its reduced model, with its basis V
    sites : :class:`~hybridcomp.diagnose.locate.Sites` (default: the search's, one element size apart)
    duration_s, step_s : the step responses' duration and backward-Euler step [s]
    """
    from hybridcomp.diagnose.locate import patch_rows, surface_sites

    if rom.V is None or rom.V.shape[0] != model.n:
        raise ValueError(f"surface_error: the reduced model needs its basis V on the FE model's {model.n} nodes")
    t0 = time.perf_counter()
    if sites is None:
        sites = surface_sites(machine, rom, model.mesh)
    rows = sp.csr_matrix(patch_rows(machine, rom, sites.mesh, list(sites.body), sites.reference_mm, sites.patch_mm))
    q = len(model.sensor_names)
    C = model.C.toarray() if sp.issparse(model.C) else np.asarray(model.C)
    C = C[:q]
    K = sp.csr_matrix(model.K) + sum(h * sp.csr_matrix(H) for h, H in zip(model.h_W_m2K, model.H))
    M = sp.csr_matrix(model.M)
    n_steps = max(1, int(round(duration_s / step_s)))
    Br = np.asarray(rows @ rom.V).T  # r × sites
    err = np.zeros(sites.n)
    peak = np.zeros(sites.n)
    fe_steps = _fe_steps(M, K, step_s, n_steps, C.T)  # w_i: the FE response to heat c_iᵀ (n × q)
    for W, Y in zip(fe_steps, _rom_steps(rom, step_s, n_steps, Br, q)):
        y_fe = np.asarray(rows @ W)  # sites × q, [K per W]
        y_rom = Y.T
        err = np.maximum(err, np.abs(y_rom - y_fe).max(axis=1))
        peak = np.maximum(peak, np.abs(y_fe).max(axis=1))
    out = SurfaceError(rom.order, err, peak, np.asarray(sites.position_mm), tuple(sites.body))
    log.info("%s (%d sites, %.1f s)", out.describe(), sites.n, time.perf_counter() - t0)
    return out


def surface_order(machine, model, relative: float, orders=(150, 200, 250, 300, 400), prepare=None, **steps):
    """The reduced model of the smallest order of ``orders`` whose :func:`surface_error` is within ``relative``.

    ``relative``: the error allowed at the sensors, a share of each judged site's own peak response (for a source
    whose response at the sensors reaches A above sensor noise σ, σ / (3 A) keeps the model's error below a third of
    the noise).  ``prepare(order) -> reduced model`` (default :func:`hybridcomp.diagnose.prepare_model` on ``model``);
    ``steps``: :func:`surface_error`'s ``duration_s`` and ``step_s``.
    Returns (reduced model, [SurfaceError per order tried]); the largest order's when none is within.
    """
    from hybridcomp.diagnose.core import prepare_model

    if not relative > 0:
        raise ValueError(f"surface_order: the relative tolerance must be positive, got {relative}")
    prepare = prepare or (lambda order: prepare_model(machine, model=model, order=int(order)))
    tried = []
    rom = None
    for order in orders:
        rom = prepare(order)
        tried.append(surface_error(machine, model, rom, **steps))
        if tried[-1].worst <= relative:
            break
    else:
        log.warning("no order of %s keeps the surface error within %.3g: %s", tuple(orders), relative,
                    tried[-1].describe())
    return rom, tried
