"""A missing heat source anywhere on the machine's surface: sites, drive shapes and the search over both.

The library's ``missing_source`` only tries existing sources' patches.  A pump, a fan, a brake or a cabinet sits
anywhere.  Here every body's surface (its faces in the air and its joints with other bodies) is cut into *sites* one
search spacing apart (default: the element size), each a box patch of that size centred on the surface, clipped to its
body like a machine-file heat source.  The reduced model's basis carries a site's heat input: ``B_site = Vᵀ b``.
The basis holds output-side Krylov directions (the sensors' and the drifts' adjoints), so the Galerkin
projection reproduces the outputs' response to heat anywhere at the expansion points, not only to the modelled
sources' heat.

In the reduced model's modes (``M Φ = K Φ Λ⁻¹``, ``Φᵀ M Φ = I``) the response of every channel to a unit power
``f(t)`` at a site is ``Σ_j (C Φ)_j (Φᵀ B_site)_j g_j(t)`` with ``g_j`` the first-order lag of ``f`` with time
constant ``1/λ_j`` and gain ``1/λ_j``: one set of lags per drive shape serves every site.  The power of a site
and shape is then a non-negative least-squares fit of the weighted training residual, in closed form for all
sites at once.

Drive shapes (``shapes``): on/off with the spindle or any axis (on above 2 % load), proportional to its activity,
a power law of it (exponent fitted once the site is found), constant (on before the record began: the machine in
its steady state with it), and switched on at the record's first sample (the machine at rest before: a cabinet or
a hydraulic unit that comes on with the machine).

Placement (``candidates(..., place=)``): ``"patch"`` (default) keeps a source at its best search site (refined on
finer sites), its place known to the search's confidence region; ``"continuous"`` (opt-in, costly: a bounded fit of
power and place per refined site, patches sampled ``PATCH_SAMPLING`` times more finely) fits the place on the site's
face with the power, its uncertainty in mm from the fit.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from hybridcomp.diagnose.problem import Problem, first_order_lag

log = logging.getLogger(__name__)

#: load factor above which a driver counts as on (on/off shapes)
ON_THRESHOLD = 0.02
#: lattice points per element size (each side of the start, one element far) on which a placed source's input is
#: made once and interpolated
LATTICE_PER_ELEMENT = 6
#: most residual evaluations of a face's fit of power and place (half of them for another patch size from there)
FACE_NFEV = 40
#: continuous placement: a patch's heat is sampled this many times more finely than a machine-file source's (smooth
#: in its place)
PATCH_SAMPLING = 4.0
#: how located sources are placed: at the best search site, or fitted continuously on its face (opt-in)
PLACES = ("patch", "continuous")
#: sites kept per drive shape (distinct places, at least two spacings apart) as candidates of the selection
TOP_SITES = 2
#: (shape, site) pairs refined on finer sites, the best by their coarse fit (the others stay candidates as they are)
REFINED = 4
#: the location's confidence region: sites whose training misfit is within this Δχ² (3 location parameters, 95 %)
#: of the best, the misfit inflated for the residual's correlation in time
CHI2_3_95 = 7.81


@dataclass(frozen=True)
class Sites:
    """Places on the bodies' surfaces where a missing heat source is tried.

    Attributes
    ----------
    position_mm : site centres at the model's pose (n × 3) [mm]
    reference_mm : the same in machine-file coordinates (the reference pose, all axes at 0) (n × 3) [mm]
    body : body name per site
    Br : reduced heat input of 1 W at each site (r × n) [-]
    patch_mm : edge length of a site's box patch [mm]
    mesh : the machine's mesh at the model's pose (for a finer search near a site)
    """

    position_mm: np.ndarray
    reference_mm: np.ndarray
    body: tuple[str, ...]
    Br: np.ndarray
    patch_mm: float
    mesh: object = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def n(self) -> int:
        return len(self.body)


@dataclass(frozen=True)
class Shape:
    """A drive shape: the unit power over time of a missing source.

    Attributes
    ----------
    name : ``"spindle on/off"``, ``"X proportional"``, ``"constant"`` …
    driver : the spindle or an axis name, None for constant
    form : ``"on/off"``, ``"proportional"``, ``"constant"`` (on before the record began: the machine in its steady
        state with it) or ``"switched on"`` (at the record's first sample, the machine at rest before)
    f : unit power per sample, 0..1 [-]
    also : other drivers with the same shape in these data
    """

    name: str
    driver: str | None
    form: str
    f: np.ndarray
    also: tuple[str, ...] = ()


def shapes(problem: Problem) -> list[Shape]:
    """Every drive shape the dataset's activity signals allow, the spindle's first.

    Drivers whose shapes are the same in these data (an axis that runs exactly while the spindle does) give one
    shape, named by the first of them, with the others in ``also``: the data cannot tell them apart.
    """
    out: list[Shape] = []

    def add(shape: Shape) -> None:
        for k, other in enumerate(out):
            if other.form == shape.form and np.allclose(other.f, shape.f, rtol=0, atol=1e-9):
                out[k] = dataclasses.replace(other, also=other.also + (shape.driver,))
                return
        out.append(shape)

    for driver in sorted(problem.activity, key=lambda d: d != "spindle"):
        act = np.asarray(problem.activity[driver], float)
        if np.ptp(act) == 0:
            continue
        on = (act > ON_THRESHOLD).astype(float)
        add(Shape(f"{driver} on/off", driver, "on/off", on))
        if not np.array_equal(on, act):
            add(Shape(f"{driver} proportional", driver, "proportional", act))
    n = problem.time_s.size
    out.append(Shape("constant", None, "constant", np.ones(n)))
    if n > 1:
        out.append(Shape("on from the start", None, "switched on", np.r_[0.0, np.ones(n - 1)]))
    return out


def surface_sites(machine, rom, mesh=None, spacing_mm: float | None = None, patch_mm: float | None = None,
                  near: tuple[np.ndarray, float, str] | None = None, sampling: float | None = None) -> Sites:
    """The search sites of a machine for a reduced model with its basis V.

    Parameters
    ----------
    machine : the machine the reduced model was made of
    rom : reduced model with ``V``; its ``meta`` gives the pose and element size of the mesh
    mesh : the :class:`~hybridcomp.fem.mesh.MachineMesh` (made here from the reduced model's pose if None)
    spacing_mm : distance between sites [mm] (default: the element size)
    patch_mm : edge of a site's box patch [mm] (default: the spacing)
    near : (centre at the pose [mm], radius [mm], body): only the surface of that body within the radius
    sampling : a patch's heat sampled this many times more finely than a machine-file source's (:func:`patch_inputs`;
        default: as a machine-file source's)
    """
    from hybridcomp.fem.mesh import mesh_machine
    from hybridcomp.fem.model import MM

    if rom.V is None:
        raise ValueError("the reduced model has no basis V: a missing source cannot be searched over the surface")
    h = float(rom.meta.get("element_size_mm") or machine.mesh.element_size_mm)
    if mesh is None:
        m = dataclasses.replace(machine, mesh=dataclasses.replace(machine.mesh, element_size_mm=h))
        mesh = mesh_machine(m, rom.meta.get("pose_mm"))
    if mesh.n_nodes != rom.V.shape[0]:
        raise ValueError(f"the reduced model has {rom.V.shape[0]} nodes, the mesh {mesh.n_nodes}: use the same element size")
    spacing = float(spacing_mm or h)
    patch = float(patch_mm or spacing)
    sk = mesh.mesh
    # the bodies' surfaces: facets on the boundary (air) and between two bodies (a joint), the latter once per side
    left = mesh.body_of_element[sk.f2t[0]]
    right = np.where(sk.f2t[1] >= 0, mesh.body_of_element[np.maximum(sk.f2t[1], 0)], -1)
    outer = np.flatnonzero(right < 0)
    joint = np.flatnonzero((right >= 0) & (right != left))
    facets = np.concatenate([outer, joint, joint])
    body_idx = np.concatenate([left[outer], left[joint], right[joint]])
    corners_mm = sk.p[:, sk.facets[:, facets]].transpose(2, 1, 0) / MM  # facet × node × xyz
    if near is not None:
        lo, hi = corners_mm.min(axis=1), corners_mm.max(axis=1)
        gap = np.linalg.norm(np.clip(np.asarray(near[0], float), lo, hi) - np.asarray(near[0], float), axis=1)
        keep = (gap <= near[1]) & (body_idx == mesh.body_names.index(near[2]))
        corners_mm, body_idx = corners_mm[keep], body_idx[keep]
    cent_mm, body_idx = _facet_points(corners_mm, body_idx, spacing)
    if near is not None:
        keep = np.linalg.norm(cent_mm - np.asarray(near[0], float), axis=1) <= near[1]
        cent_mm, body_idx = cent_mm[keep], body_idx[keep]
    if cent_mm.shape[0] == 0:  # nothing of that body within the radius
        return Sites(np.zeros((0, 3)), np.zeros((0, 3)), (), np.zeros((rom.order, 0)), patch, mesh)
    keys = np.column_stack([body_idx, np.floor(cent_mm / spacing).astype(int)])
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = group.ravel()
    n = int(group.max()) + 1
    pos = np.zeros((n, 3))
    np.add.at(pos, group, cent_mm)
    pos /= np.bincount(group, minlength=n)[:, None]
    bodies = [mesh.body_names[int(b)] for b in np.bincount(group, weights=body_idx, minlength=n)
              // np.bincount(group, minlength=n)]
    ref = np.array([p - machine.body_offset_mm(b, mesh.pose_mm) for p, b in zip(pos, bodies)])
    return Sites(pos, ref, tuple(bodies), patch_inputs(machine, rom, mesh, bodies, ref, patch, sampling), patch, mesh)


def patch_inputs(machine, rom, mesh, bodies, reference_mm: np.ndarray, patch_mm: float,
                 sampling: float | None = None) -> np.ndarray:
    """Reduced heat inputs (r × n) of 1 W on a box patch of edge ``patch_mm`` centred at each point.

    ``reference_mm``: the points in machine-file coordinates (n × 3) [mm], on the ``bodies``; the patch is clipped to
    its body as a machine-file heat source is.  ``sampling``: the patch's heat sampled this many times more finely
    than a machine-file source's (the input then varies smoothly with the point, which a fit of the place needs);
    None: as a machine-file source's.
    """
    return np.asarray(patch_rows(machine, rom, mesh, bodies, reference_mm, patch_mm, sampling) @ rom.V).T


def patch_rows(machine, rom, mesh, bodies, reference_mm: np.ndarray, patch_mm: float, sampling: float | None = None):
    """The FE heat input rows (sparse, n_points × n nodes) of 1 W on :func:`patch_inputs`'s patches."""
    from hybridcomp.fem.assembly import cell_basis
    from hybridcomp.fem.model import heat_input_rows

    template = machine.heat_sources[0] if machine.heat_sources else None
    if template is None:
        from hybridcomp.models.machine import HeatSource

        template = HeatSource("site", "fixed", bodies[0], None, None, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1.0, 1.0, None)
    srcs = tuple(dataclasses.replace(template, name=f"site{i}", kind="fixed", body=b, axis=None, driver=None,
                                     position_mm=tuple(map(float, r)), size_mm=(float(patch_mm),) * 3, power_W=1.0,
                                     exponent=1.0, power_table=None)
                 for i, (r, b) in enumerate(zip(reference_mm, bodies)))
    m = dataclasses.replace(machine, heat_sources=srcs)
    if sampling is None:
        return heat_input_rows(m, mesh, cell_basis(mesh.mesh))[0]
    key = ("cell_basis", id(mesh))  # a fit of the place makes inputs hundreds of times: the basis once per mesh
    if key not in rom._cache:
        rom._cache[key] = (mesh, cell_basis(mesh.mesh))  # the mesh kept with it: its id stays its own
    h = float(rom.meta.get("element_size_mm") or machine.mesh.element_size_mm) / float(sampling)
    m = dataclasses.replace(m, mesh=dataclasses.replace(machine.mesh, element_size_mm=h))
    return heat_input_rows(m, mesh, rom._cache[key][1])[0]


def _facet_points(corners_mm: np.ndarray, body_idx: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the facets at most ``spacing`` apart.

    The centroid of a facet smaller than the spacing, else a lattice of combinations of its corners (bilinear on a
    quadrilateral, barycentric on a triangle).
    """
    size = np.max(np.linalg.norm(corners_mm - corners_mm.mean(axis=1, keepdims=True), axis=2), axis=1) * 2.0
    pts, bodies = [corners_mm.mean(axis=1)], [body_idx]
    big = np.flatnonzero(size > spacing)
    per_edge = np.ceil(size[big] / spacing).astype(int)
    for k in np.unique(per_edge):
        sel = big[per_edge == k]
        u = (np.arange(k) + 0.5) / k
        c = corners_mm[sel]
        U, W = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
        if c.shape[1] == 4:  # quadrilateral, corners in cyclic order
            wts = np.column_stack([(1 - U) * (1 - W), U * (1 - W), U * W, (1 - U) * W])
        else:  # triangle: the lattice points inside
            inside = U + W < 1
            U, W = U[inside], W[inside]
            wts = np.column_stack([1 - U - W, U, W])
        pts.append(np.einsum("pn,fnd->fpd", wts, c[:, : wts.shape[1]]).reshape(-1, 3))
        bodies.append(np.repeat(body_idx[sel], wts.shape[0]))
    return np.vstack(pts), np.concatenate(bodies)


def _sampling(place: str) -> float | None:
    if place not in PLACES:
        raise ValueError(f"place of located sources: {place!r}, expected one of {', '.join(PLACES)}")
    return PATCH_SAMPLING if place == "continuous" else None


def sites_for(problem: Problem, machine=None, place: str = "patch") -> Sites | None:
    """The problem's search sites, made once per reduced model and placement (kept in its cache); None without a basis.

    ``place``: ``"continuous"`` samples the patches' heat ``PATCH_SAMPLING`` times more finely.
    """
    rom = problem.rom
    if rom.V is None:
        return None
    sampling = _sampling(place)
    key = "surface_sites" if sampling is None else ("surface_sites", sampling)
    if key not in rom._cache:
        t0 = time.perf_counter()
        rom._cache[key] = surface_sites(machine or problem.machine, rom, sampling=sampling)
        log.info("%d surface sites for a missing source in %.1f s", rom._cache[key].n, time.perf_counter() - t0)
    return rom._cache[key]


def _channel_scale(problem: Problem) -> np.ndarray:
    """Raw output unit → channel unit (K → K, m → µm)."""
    return np.array([1.0 if problem.is_temperature(k) else 1e6 for k in range(len(problem.channels))])


def mode_lags(problem: Problem, f: np.ndarray) -> np.ndarray:
    """Per reduced mode j, the response g_j (nt × r) of ġ = −λ_j g + f from its steady state at f[0]."""
    lam = problem.rom._modes()[0]
    t = problem.time_s
    G = np.empty((t.size, lam.size))
    for j, rate in enumerate(lam):
        G[:, j] = first_order_lag(t, f, 1.0 / rate) / rate
    return G


def site_responses(problem: Problem, G: np.ndarray, Bm: np.ndarray) -> np.ndarray:
    """Raw channel outputs (nt × nch × ns) of 1 W at each site with the mode responses ``G``; ``Bm = Φᵀ B_site``."""
    Phi = problem.rom._modes()[1]
    Cz = problem.rom.C[list(problem.out_index)] @ Phi
    return np.stack([(G * Cz[k]) @ Bm for k in range(Cz.shape[0])], axis=1)


@dataclass(frozen=True)
class Found:
    """The best sites of one shape for a residual.

    Attributes
    ----------
    shape : the drive shape
    sites : site indices, best first (distinct places)
    power_W : fitted power per site [W]
    gain : drop of the weighted training misfit per site [-]
    spread_mm : per site, the largest distance to a site of its confidence region [mm]
    """

    shape: Shape
    sites: tuple[int, ...]
    power_W: tuple[float, ...]
    gain: tuple[float, ...]
    spread_mm: tuple[float, ...]


def search(problem: Problem, sites: Sites, residual: np.ndarray, shape: Shape, top: int = TOP_SITES,
           max_power_W: float = 2000.0, G: np.ndarray | None = None) -> Found:
    """Fit a missing source of ``shape`` at every site to the weighted training ``residual`` (measured − model).

    The location is chosen on the training rows only.  With the weighted response ``Y_s = Σ_j G_j (w ∘ Cz_j) Bm_js``
    the fit needs ``⟨R, Y_s⟩ = (Σ_c w_c Cz_c ∘ (Rᵀ G)_c) Bm_s`` and ``‖Y_s‖² = Bm_sᵀ Q Bm_s`` with
    ``Q = Σ_c w_c² (Cz_c Cz_cᵀ) ∘ (Gᵀ G)``: O(nt r²) once, then O(r²) a site, whatever the record's length.
    The confidence region of a site: the sites whose misfit is within ``CHI2_3_95`` × the inflation of the
    residual's correlation in time of its own.  ``G``: the shape's :func:`mode_lags` over all rows, if the caller
    has them.
    """
    from hybridcomp.diagnose.metrics import lag1_autocorrelation

    tr = problem.split.train
    w = problem.weights * _channel_scale(problem)
    R = residual[tr] * problem.weights[None, :]
    Phi = problem.rom._modes()[1]
    Bm = Phi.T @ sites.Br
    Cz = problem.rom.C[list(problem.out_index)] @ Phi * w[:, None]
    G = (mode_lags(problem, shape.f) if G is None else G)[tr]
    num = np.einsum("cj,cj->j", Cz, R.T @ G) @ Bm
    Q = (Cz.T @ Cz) * (G.T @ G)
    den = np.maximum(np.einsum("js,jk,ks->s", Bm, Q, Bm), 1e-300)
    P = np.clip(num / den, 0.0, max_power_W)
    drop = 2 * P * num - P**2 * den  # misfit drop of power P
    base = float(np.sum(R**2))
    rho = np.clip(np.mean([lag1_autocorrelation(r) for r in R.T]), 0.0, 0.99)
    s2 = base / max(R.size - 1, 1)
    threshold = CHI2_3_95 * s2 * (1 + rho) / (1 - rho)
    order = np.argsort(-drop)
    picked: list[int] = []
    for i in order:
        if len(picked) >= top or drop[i] <= 0:
            break
        if all(np.linalg.norm(sites.position_mm[i] - sites.position_mm[j]) >= 2 * sites.patch_mm for j in picked):
            picked.append(int(i))
    spread = []
    for i in picked:
        near = drop >= drop[i] - threshold
        spread.append(float(np.max(np.linalg.norm(sites.position_mm[near] - sites.position_mm[i], axis=1))))
    return Found(shape, tuple(picked), tuple(float(P[i]) for i in picked), tuple(float(drop[i] / base) for i in picked),
                 tuple(spread))


def refine(problem: Problem, sites: Sites, i: int, residual: np.ndarray, shape: Shape,
           G: np.ndarray | None = None, sampling: float | None = None) -> tuple[Sites, int, float]:
    """Finer searches around site ``i`` on its body.

    First a third of the spacing within 1.2 spacings, then a ninth within half a spacing with patches of one, two
    and three thirds of the spacing.  ``sampling``: as :func:`surface_sites`'.

    Returns the sites searched last, the best one's index among them, and the confidence region's extent [mm].
    """
    h = sites.patch_mm
    at, best, spread = sites, i, 0.5 * h
    for step, radius, patches in ((h / 3.0, 1.2 * h, (h,)), (h / 9.0, 0.5 * h, (h / 3.0, 2.0 * h / 3.0, h))):
        trials = []
        for patch in patches:
            fine = surface_sites(problem.machine, problem.rom, sites.mesh, step, patch,
                                 (at.position_mm[best], radius, at.body[best]), sampling)
            found = search(problem, fine, residual, shape, top=1, G=G)
            if found.sites:
                trials.append((found.gain[0], fine, found.sites[0], found.spread_mm[0]))
        if not trials:
            break
        _, at, best, spread = max(trials, key=lambda x: x[0])
    return at, best, spread


def _adds(rows: list[int], response: np.ndarray):
    """A raw-output operation that adds ``response`` (nt × len(rows)) to the output ``rows``, in place."""

    def op(Y: np.ndarray) -> None:
        Y[:, rows] += response

    return op


def _label(sites: Sites, i: int, shape: Shape, exponent: float | None = None) -> str:
    """A located source's name in reports: its body, its place in machine-file coordinates, its drive."""
    ref = np.round(sites.reference_mm[i]).astype(int)
    return (f"missing heat source on {sites.body[i]} at ({ref[0]}, {ref[1]}, {ref[2]}) mm, "
            f"{_describe_shape(shape, exponent)}")


def _describe_shape(shape: Shape, exponent: float | None = None) -> str:
    if shape.form == "constant":
        return "constant (on before the record began)"
    if shape.form == "switched on":
        return "switched on at the record's start"
    who = " or ".join("the spindle" if d == "spindle" else f"axis {d}" for d in (shape.driver, *shape.also))
    if exponent is not None:
        text = f"following {who}'s activity to a power"
    else:
        text = f"on while {who} runs" if shape.form == "on/off" else f"proportional to {who}'s activity"
    return text + (" (the same in these data)" if shape.also else "")


def candidates(problem: Problem, residual: np.ndarray, top: int = TOP_SITES, place: str = "patch") -> list:
    """``located_source`` candidates: per drive shape, the ``top`` best distinct sites for ``residual``.

    The ``REFINED`` best of them are placed more finely (:func:`refine`).  Each is linear in its power; a
    proportional shape's best site is also tried with a power law of its activity (power and exponent fitted).
    The location counts as three parameters more in the selection's BIC (``Candidate.extra_dof``); the
    confidence region's extent is reported with it.

    ``place="continuous"`` (opt-in, several times slower): a refined site's source is placed on its face by a fit of
    power and place (:func:`_continuous`), its uncertainty in mm from the fit; ``"patch"``: at the site found.
    """
    from hybridcomp.diagnose.effects import Candidate

    sampling = _sampling(place)
    continuous = sampling is not None
    sites = sites_for(problem, place=place)
    if sites is None:
        log.info("the reduced model has no basis V: no search for a missing source over the surface")
        return []
    rows = list(problem.out_index)
    out = []
    lags = [(shape, mode_lags(problem, shape.f)) for shape in shapes(problem)]  # once per shape, for every search
    founds = [(search(problem, sites, residual, shape, top, G=G), G) for shape, G in lags]
    gains = sorted((g for f, _ in founds for g in f.gain), reverse=True)
    refine_from = gains[min(REFINED, len(gains)) - 1] if gains else np.inf
    for found, G in founds:
        shape = found.shape
        for i0, g0, s0 in zip(found.sites, found.gain, found.spread_mm):
            if g0 >= refine_from:
                at, i, spread = refine(problem, sites, i0, residual, shape, G, sampling)
            else:
                at, i, spread = sites, i0, max(s0, 0.5 * sites.patch_mm)
            resp = site_responses(problem, G, problem.rom._modes()[1].T @ at.Br[:, [i]])[:, :, 0]
            ref = np.round(at.reference_mm[i]).astype(int)
            where = f"{at.body[i]}@{ref[0]},{ref[1]},{ref[2]}"
            info = {"location_mm": [float(v) for v in at.reference_mm[i]], "body": at.body[i],
                    "location_at_pose_mm": [float(v) for v in at.position_mm[i]],
                    "location_spread_mm": max(spread, sites.patch_mm / 6.0), "patch_mm": at.patch_mm,
                    "driver": shape.driver, "form": shape.form, "same_as": list(shape.also)}

            def apply(s, p, resp=resp):
                s.raw_ops.append(_adds(rows, p[0] * resp))

            label = _label(at, i, shape)
            if not continuous:
                out.append(Candidate("located_source", f"{where}|{shape.name}", label, ("power [W]",), (0.0,),
                                     (2000.0,), (0.0,), (0.0,), True, "raw", apply, physical=((True, False),),
                                     extra_dof=3, info=info))
                if shape.form == "proportional" and i0 == found.sites[0]:
                    out.append(_power_law(problem, at, i, shape, where, info))
                continue
            info = {**info, "offset_mm": [float(v) for v in at.position_mm[i] - at.reference_mm[i]]}
            refined = g0 >= refine_from
            cont = _continuous(problem, at, i, shape, where, info, G, _power_at(problem, resp, residual), residual) \
                if refined else None
            if cont is not None:  # placed continuously on its face, with its power, in every fit
                out.append(cont)
            else:
                out.append(Candidate("located_source", f"{where}|{shape.name}", label, ("power [W]",), (0.0,),
                                     (2000.0,), (0.0,), (0.0,), True, "raw", apply, physical=((True, False),),
                                     extra_dof=3, info=info))
            if shape.form == "proportional" and i0 == found.sites[0]:
                cont = _continuous(problem, at, i, shape, where, info, G, _power_at(problem, resp, residual), residual,
                                   True) if refined else None
                out.append(cont if cont is not None else _power_law(problem, at, i, shape, where, info))
    return out


def faces_near(machine, body: str, reference_mm: np.ndarray, distance_mm: float) -> list[dict]:
    """The faces of a box body whose plane lies within ``distance_mm`` of a surface point, the nearest first.

    Near an edge the heat may sit on either face.  Each face as ``{"axis": a, "value_mm": v, "free": (i, j),
    "lower_mm": (lo_i, lo_j), "upper_mm": (hi_i, hi_j)}`` in machine-file coordinates; none for a body that is not a
    box (an imported mesh's group).
    """
    box = machine.body(body).box_mm
    if box is None:
        return []
    lo, hi = np.asarray(box[0], float), np.asarray(box[1], float)
    p = np.asarray(reference_mm, float)
    gaps = np.concatenate([np.abs(p - lo), np.abs(p - hi)])
    out = []
    for k in np.argsort(gaps, kind="stable"):
        if gaps[k] > distance_mm and out:
            break
        a = int(k % 3)
        free = tuple(d for d in range(3) if d != a)
        out.append({"axis": a, "value_mm": float((lo if k < 3 else hi)[a]), "free": free,
                    "lower_mm": tuple(float(lo[d]) for d in free), "upper_mm": tuple(float(hi[d]) for d in free)})
    return out


def _face_point(face: dict, reference_mm: np.ndarray, uv=None) -> np.ndarray:
    """The point of ``face`` at in-plane coordinates ``uv`` (default: the projection of ``reference_mm``, in the face)."""
    ref = np.asarray(reference_mm, float).copy()
    if uv is None:
        uv = np.clip(ref[list(face["free"])], face["lower_mm"], face["upper_mm"])
    ref[list(face["free"])] = uv
    ref[face["axis"]] = face["value_mm"]
    return ref


def _chi2_threshold(problem: Problem, residual: np.ndarray, best_cost: float) -> float:
    """``CHI2_3_95`` as a change of ``least_squares``' cost (half the weighted training misfit).

    Scaled by the variance the best fit leaves (``best_cost``) and inflated for the residual's correlation in time.
    """
    from hybridcomp.diagnose.metrics import lag1_autocorrelation

    R = residual[problem.split.train] * problem.weights[None, :]
    rho = np.clip(np.mean([lag1_autocorrelation(r) for r in R.T]), 0.0, 0.99)
    s2 = 2.0 * best_cost / max(R.size - 3, 1)
    return 0.5 * CHI2_3_95 * s2 * (1 + rho) / (1 - rho)


#: exponents tried at a power law's start place before its face fit (the fit refines the best)
EXPONENT_GRID = (0.6, 1.0, 1.5, 2.0, 2.5, 3.0)


def _face_fit(problem: Problem, at: Sites, i: int, G: np.ndarray, residual: np.ndarray, face: dict,
              power_W: float, patch_mm: float, start_mm: np.ndarray | None = None,
              max_nfev: int | None = None, power_law: np.ndarray | None = None,
              exponent: float | None = None) -> tuple[float, np.ndarray]:
    """Power and place of a ``patch_mm`` patch on one face fitted to the weighted training ``residual``.

    From the site ``i`` projected on the face, or from ``start_mm``.  ``power_law``: the drive's activity ``f`` of a
    power law: its exponent ``n`` is fitted with the power and place (the response of ``f**n``), from ``exponent``
    or, without one, from the best of ``EXPONENT_GRID`` at the start place; ``G`` is then unused.  Returns (misfit as
    ``least_squares``' cost, (power, u, v)) or, for a power law, (power, n, u, v).
    """
    from scipy.optimize import least_squares

    tr = problem.split.train
    w = problem.weights * _channel_scale(problem)
    R = (residual[tr] * problem.weights[None, :]).ravel()
    Phi = problem.rom._modes()[1]
    ref0 = _face_point(face, at.reference_mm[i] if start_mm is None else start_mm)
    lags: dict = {}

    def G_of(n: float) -> np.ndarray:
        key = round(float(n), 6)
        if key not in lags:
            lags[key] = mode_lags(problem, power_law**key)[tr]
        return lags[key]

    def unit(uv, Gn) -> np.ndarray:
        Br = patch_inputs(problem.machine, problem.rom, at.mesh, [at.body[i]], _face_point(face, ref0, uv)[None, :],
                          patch_mm, PATCH_SAMPLING)
        return (site_responses(problem, Gn, Phi.T @ Br)[:, :, 0] * w[None, :]).ravel()

    uv0 = ref0[list(face["free"])]
    lo_uv, hi_uv = np.asarray(face["lower_mm"], float), np.asarray(face["upper_mm"], float)
    if power_law is None:
        def resid(x):
            return R - x[0] * unit(x[1:], G[tr])

        lo, hi = np.r_[0.0, lo_uv], np.r_[2000.0, hi_uv]
        x0 = np.clip(np.r_[max(power_W, 1.0), uv0], lo, hi)
        scale = np.r_[max(power_W, 1.0), at.patch_mm, at.patch_mm]
    else:
        def resid(x):
            return R - x[0] * unit(x[2:], G_of(x[1]))

        lo, hi = np.r_[0.0, 0.2, lo_uv], np.r_[2000.0, 4.0, hi_uv]
        trials = EXPONENT_GRID if exponent is None else (exponent,)
        best = None
        for n in trials:  # the power in closed form at the start place for each exponent tried
            Y = unit(np.clip(uv0, lo_uv, hi_uv), G_of(n))
            P = float(np.clip(Y @ R / max(Y @ Y, 1e-300), 0.0, 2000.0))
            cost = float(np.sum((R - P * Y) ** 2))
            if best is None or cost < best[0]:
                best = (cost, P, n)
        x0 = np.clip(np.r_[max(best[1], 1.0), best[2], uv0], lo, hi)
        scale = np.r_[max(best[1], 1.0), 0.2, at.patch_mm, at.patch_mm]
    res = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, max_nfev=max_nfev or FACE_NFEV, method="trf")
    return float(res.cost), res.x


def located_at(candidate, params) -> tuple[np.ndarray, np.ndarray]:
    """A located source's place at fitted ``params``: (machine-file coordinates, at the model's pose) [mm].

    A source placed continuously on a face (``info["face"]``) has its two in-plane coordinates among its parameters
    (from ``info["uv_index"]``); one found at a search site has the site's place.
    """
    info = candidate.info
    ref = np.asarray(info["location_mm"], float).copy()
    if "offset_mm" not in info:  # placed at a search site (``place="patch"``)
        return ref, np.asarray(info["location_at_pose_mm"], float)
    face = info.get("face")
    if face is not None:
        k = info["uv_index"]
        ref[list(face["free"])] = np.asarray(params, float)[k:k + 2]
        ref[face["axis"]] = face["value_mm"]
    return ref, ref + np.asarray(info["offset_mm"], float)


def location_uncertainty_mm(candidate, uncertainty) -> float:
    """1σ radius of a located source's place in the face's plane [mm].

    For a source placed continuously: its in-plane coordinates' 1σ from the fit's Jacobian (scaled by the residual,
    inflated for its correlation in time), in quadrature, or, if larger, the distance to the fit on another face near
    an edge that fits the training rows as well (``info["face_spread_mm"]``); for one placed at a site the search's
    confidence-region extent.  The shift the model's discretisation error could make of the place is reported beside it
    (``info["discretisation_shift_mm"]``, :func:`hybridcomp.diagnose.discretisation.parameter_shift`).
    """
    if candidate.info.get("face") is None:
        return float(candidate.info["location_spread_mm"])
    k = candidate.info["uv_index"]
    u = np.asarray(uncertainty, float)[k:k + 2]
    return float(max(np.sqrt(np.sum(u**2)), candidate.info.get("face_spread_mm", 0.0)))


#: coordinates closer than this share one reduced input (a cache key; far below the fit's finite-difference step) [mm]
_POSITION_ROUND_MM = 1e-6


def _continuous(problem: Problem, at: Sites, i: int, shape: Shape, where: str, info: dict, G: np.ndarray,
                power_W: float, residual: np.ndarray, power_law: bool = False):
    """A located source whose place on its body's face is fitted with its power (and exponent).

    Bounded least squares over the face's two in-plane coordinates, from the search's best site.
    The reduced input of a patch at any point (:func:`patch_inputs`) is continuous in the point, so the fit moves the
    patch between the search's sites; its uncertainty in mm comes from the fit's Jacobian like every parameter's.
    Returns None for a site on a body that is not a box.
    """
    from hybridcomp.diagnose.effects import Candidate

    faces = faces_near(problem.machine, at.body[i], at.reference_mm[i], at.patch_mm)
    if not faces:
        return None
    # the face by the evidence: near an edge, the power and place fitted on each face, the best kept as the start
    # with the search's patch; then on the best face the patch's size among three (a third, two thirds and the whole
    # search spacing), from the place found.  A power law's faces are compared with its exponent fitted too: the
    # proportional shape's best face need not be the power law's
    h = float(sites_for(problem, place="continuous").patch_mm)
    law = shape.f if power_law else None
    k_uv = 2 if power_law else 1  # where the place starts among a face fit's parameters
    fits = [(*_face_fit(problem, at, i, G, residual, f, power_W, at.patch_mm, power_law=law), f, at.patch_mm)
            for f in faces]
    _, x_best, face, _ = min(fits, key=lambda x: x[0])
    start = _face_point(face, at.reference_mm[i], x_best[k_uv:])
    n_best = float(x_best[1]) if power_law else None
    fits += [(*_face_fit(problem, at, i, G, residual, face, float(x_best[0]), size, start, FACE_NFEV // 2, law, n_best),
              face, size) for size in (h / 3.0, 2.0 * h / 3.0, h) if abs(size - at.patch_mm) > 1e-6 * h]
    _, x_best, face, patch = min(fits, key=lambda x: x[0])
    threshold = _chi2_threshold(problem, residual, min(f[0] for f in fits))
    power_W = float(x_best[0])
    exponent = float(x_best[1]) if power_law else 1.0
    rows = list(problem.out_index)
    Phi = problem.rom._modes()[1]
    ref0 = _face_point(face, at.reference_mm[i], x_best[k_uv:])
    body = at.body[i]
    Bms: dict = {}
    lags: dict = {}
    axes = "xyz"

    # the patch's modal input on a lattice around the start, made in one go and interpolated bilinearly (a fit
    # evaluates it hundreds of times); made directly outside the lattice
    step = float(sites_for(problem, place="continuous").patch_mm) / LATTICE_PER_ELEMENT
    axes_uv = [np.clip(ref0[d] + step * np.arange(-LATTICE_PER_ELEMENT, LATTICE_PER_ELEMENT + 1), lo_d, hi_d)
               for d, lo_d, hi_d in zip(face["free"], face["lower_mm"], face["upper_mm"])]
    grid_u, grid_v = (np.unique(a) for a in axes_uv)
    U_, V_ = np.meshgrid(grid_u, grid_v, indexing="ij")
    pts = np.array([_face_point(face, ref0, (u, v)) for u, v in zip(U_.ravel(), V_.ravel())])
    lattice = (Phi.T @ patch_inputs(problem.machine, problem.rom, at.mesh, [body] * len(pts), pts, patch,
                                          PATCH_SAMPLING)).reshape(
        Phi.shape[1], grid_u.size, grid_v.size)

    def Bm(uv) -> np.ndarray:  # the two in-plane coordinates [mm]
        u, v = (float(x) for x in uv)
        if grid_u.size > 1 and grid_v.size > 1 and grid_u[0] <= u <= grid_u[-1] and grid_v[0] <= v <= grid_v[-1]:
            i0 = min(int(np.searchsorted(grid_u, u, side="right")) - 1, grid_u.size - 2)
            j0 = min(int(np.searchsorted(grid_v, v, side="right")) - 1, grid_v.size - 2)
            a = (u - grid_u[i0]) / (grid_u[i0 + 1] - grid_u[i0])
            b = (v - grid_v[j0]) / (grid_v[j0 + 1] - grid_v[j0])
            L = lattice
            return ((1 - a) * (1 - b) * L[:, i0, j0] + a * (1 - b) * L[:, i0 + 1, j0] + (1 - a) * b * L[:, i0, j0 + 1]
                    + a * b * L[:, i0 + 1, j0 + 1])[:, None]
        key = tuple(np.round(np.asarray(uv, float) / _POSITION_ROUND_MM).astype(int))
        if key not in Bms:
            if len(Bms) > 256:
                Bms.clear()
            ref = _face_point(face, ref0, np.asarray(key, float) * _POSITION_ROUND_MM)
            Bms[key] = Phi.T @ patch_inputs(problem.machine, problem.rom, at.mesh, [body], ref[None, :], patch,
                                             PATCH_SAMPLING)
        return Bms[key]

    def lag(n: float) -> np.ndarray:
        key = round(float(n), 6)
        if key not in lags:
            if len(lags) > 32:
                lags.clear()
            lags[key] = mode_lags(problem, shape.f ** key)
        return lags[key]

    if power_law:
        def apply(s, p):
            s.raw_ops.append(_adds(rows, p[0] * site_responses(problem, lag(p[1]), Bm(p[2:4]))[:, :, 0]))
    else:
        def apply(s, p):
            s.raw_ops.append(_adds(rows, p[0] * site_responses(problem, G, Bm(p[1:3]))[:, :, 0]))

    uv0 = tuple(float(ref0[d]) for d in face["free"])
    names = tuple(f"{axes[d]} [mm]" for d in face["free"])
    lower, upper = face["lower_mm"], face["upper_mm"]
    sign = f"{axes[face['axis']]} = {face['value_mm']:g} mm"
    label = (f"missing heat source on {body}'s face {sign}, placed on it by the fit, "
             f"{_describe_shape(shape, 1.0 if power_law else None)}")
    # faces and patch sizes that fit the training residual as well (within the Δχ² of three parameters, inflated for its
    # correlation in time): the place is known to the distance between their fits
    best = min(f[0] for f in fits)
    alike = [_face_point(f[2], at.reference_mm[i], f[1][k_uv:]) for f in fits if f[0] - best <= threshold]
    spread = max(float(np.linalg.norm(a - ref0)) for a in alike)
    info = {**info, "face": face, "patch_mm": patch, "offset_mm": [float(v) for v in at.position_mm[i] - at.reference_mm[i]],
            "uv_index": k_uv, "face_spread_mm": spread}
    edge = ((True, True), (True, True))  # a source at a face's edge is a result, not the wrong shape
    p0 = float(np.clip(power_W, 1.0, 2000.0))
    if power_law:
        return Candidate("located_source", f"{where}|{shape.driver} power law", label,
                         ("power [W]", "exponent [-]") + names, (0.0, 0.2) + lower,
                         (2000.0, 4.0) + upper, (0.0, 1.0) + uv0, (p0, exponent) + uv0, False, "raw", apply,
                         grid=(0.5 * p0, p0, 2.0 * p0), physical=((True, False), (False, False)) + edge, extra_dof=1,
                         info={**info, "form": "power law"})
    return Candidate("located_source", f"{where}|{shape.name}", label, ("power [W]",) + names,
                     (0.0,) + lower, (2000.0,) + upper, (0.0,) + uv0, (p0,) + uv0, False, "raw",
                     apply, grid=(0.7 * p0, p0, 1.4 * p0), physical=((True, False),) + edge, extra_dof=1, info=info)


def _power_at(problem: Problem, resp: np.ndarray, residual: np.ndarray) -> float:
    """The non-negative power [W] of a unit response fitted to a residual.

    ``resp``: raw outputs of 1 W (nt × nch); ``residual``: measured − model in channel units, weighted, training rows.
    """
    tr = problem.split.train
    w = problem.weights * _channel_scale(problem)
    Y = resp[tr] * w[None, :]
    R = residual[tr] * problem.weights[None, :]
    return float(max(np.sum(Y * R) / max(np.sum(Y * Y), 1e-300), 0.0))


def _power_law(problem: Problem, sites: Sites, i: int, shape: Shape, where: str, info: dict):
    from hybridcomp.diagnose.effects import Candidate

    Bm = problem.rom._modes()[1].T @ sites.Br[:, [i]]
    rows = list(problem.out_index)
    cache: dict = {}

    def response(n: float) -> np.ndarray:
        key = round(float(n), 6)
        if key not in cache:
            if len(cache) > 64:
                cache.clear()
            G = mode_lags(problem, shape.f ** key)
            cache[key] = site_responses(problem, G, Bm)[:, :, 0]
        return cache[key]

    def apply(s, p):
        s.raw_ops.append(_adds(rows, p[0] * response(p[1])))

    label = _label(sites, i, shape, exponent=1.0)
    return Candidate("located_source", f"{where}|{shape.driver} power law", label, ("power [W]", "exponent [-]"),
                     (0.0, 0.2), (2000.0, 4.0), (0.0, 1.0), (100.0, 1.0), False, "raw", apply, grid=(20.0, 100.0, 500.0),
                     physical=((True, False), (False, False)), extra_dof=3, info={**info, "form": "power law"})
