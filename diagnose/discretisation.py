"""The model's own discretisation error: a floor below which no effect is named.

A real machine differs from any mesh.  The reduced model the diagnosis fits stands for an FE model of one element
size; the same machine on a coarser mesh answers the same inputs a little differently, and that difference is what
the discretisation alone can make of the channels.  An effect whose contribution to every channel lies within it
(e.g. a source's power scaled by 1.24 to absorb the mesh difference between 80 and 150 mm elements) is not a cause:
the data cannot tell it from the mesh.

* :func:`coarse_model`: the machine reduced on a second mesh, ``COARSER`` × the element size or coarser until it has
  at most half the nodes (element sizes snap to the bodies' dimensions; made once per reduced model, kept in its
  cache);
* :func:`mesh_difference`: both models on the dataset's inputs, channel by channel (nt × nch); extrapolated to the
  model's own error at first order in the element size (:func:`extrapolation_factor`, 2.8 from 80 to 120 mm): the
  floor, whose per-channel RMS over the validation rows is the model's uncertainty (the diagnosis counts a channel's
  residual within it as explained, ``Problem.tolerance``);
* :func:`within_floor`: the named effects whose change of the channels is no larger than what the same effect
  fitted to the floor alone changes (:func:`mimicked`).
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

log = logging.getLogger(__name__)

#: the second mesh's element size as a multiple of the model's
COARSER = 1.5
#: the second mesh has at most this share of the model's nodes (a larger element size is tried until it has)
MAX_NODE_RATIO = 0.5
#: finite-difference step of :func:`parameter_shift`, a share of each parameter's range
FD_STEP = 1e-3
#: order of the second mesh's reduced model (its reduction error adds to the floor: kept well below it)
COARSE_ORDER = 80


@dataclasses.dataclass(frozen=True)
class Floor:
    """The model's discretisation error per channel.

    Attributes
    ----------
    difference : the model's estimated error on the dataset's inputs, per sample and channel (nt × nch): the two
        meshes' difference × ``factor`` [°C or µm]
    rms : per channel, its RMS over the validation rows [°C or µm]
    factor : first-order extrapolation of the two meshes' difference to the model's own error, 1 / (k − 1) with k the
        ratio of the meshes' effective element sizes, (n_model / n_second)^(1/3) [-]
    element_size_mm : (the model's element size, the second mesh's) [mm]
    nodes : (the model's node count, the second mesh's)
    """

    difference: np.ndarray
    rms: np.ndarray
    factor: float
    element_size_mm: tuple[float, float]
    nodes: tuple[int, int]

    def as_dict(self, channels) -> dict:
        return {"element_size_mm": list(self.element_size_mm), "nodes": list(self.nodes), "factor": float(self.factor),
                "rms": {c: float(v) for c, v in zip(channels, self.rms)}}


def coarse_model(machine, rom, factor: float = COARSER):
    """The machine reduced on a coarser mesh (``factor`` × the model's element size, larger if that meshes the same).

    Returns (reduced model, element size [mm], node count), or None when the reduced model does not say its element
    size or pose (then no floor is known).  Kept in ``rom._cache``.
    """
    from hybridcomp.fem.loads import example_loads
    from hybridcomp.fem.model import build_model
    from hybridcomp.rom.machine import reduce_model

    key = ("coarse_model", float(factor))
    if key in rom._cache:
        return rom._cache[key]
    h = rom.meta.get("element_size_mm")
    n0 = rom.meta.get("nodes") or (rom.V.shape[0] if rom.V is not None else None)
    if not h or n0 is None:
        log.info("the reduced model does not record its element size and node count: no discretisation floor")
        rom._cache[key] = None
        return None
    t0 = time.perf_counter()
    out = None
    for f in (factor, 4.0 * factor / 3.0, 5.0 * factor / 3.0, 2.0 * factor):
        model = build_model(machine, rom.meta.get("pose_mm"), float(h) * f)
        if model.n <= MAX_NODE_RATIO * n0:  # element sizes that snap to nearly the same mesh tell little
            coarse = reduce_model(model, order=min(COARSE_ORDER, rom.order), keep_basis=False,
                                  check_loads=example_loads(machine, duration_h=1.0, dt_s=600.0))
            out = (coarse, float(h) * f, int(model.n))
            break
    log.info("second mesh for the discretisation floor: %s in %.1f s",
             f"{out[1]:g} mm, {out[2]} nodes" if out else "none", time.perf_counter() - t0)
    rom._cache[key] = out
    return out


def mesh_difference(problem, coarse) -> np.ndarray:
    """Channels of the model minus those of the coarse model on the problem's inputs (nt × nch) [°C or µm]."""
    names = [problem.rom.output_names[i] for i in problem.out_index]
    rows = [list(coarse.output_names).index(n) for n in names]
    fine = problem.rom.integrate(problem.time_s, problem.U)[0][:, list(problem.out_index)]
    other = coarse.integrate(problem.time_s, problem.U)[0][:, rows]
    scale = np.array([1.0 if problem.is_temperature(k) else 1e6 for k in range(len(problem.channels))])
    return (fine - other) * scale


def extrapolation_factor(nodes: int, nodes_second: int) -> float:
    """1 / (k − 1): the model's own error from its difference to a second, coarser mesh.

    First order in the element size; k = (n / n_second)^(1/3), the ratio of the meshes' effective element sizes.
    """
    k = (float(nodes) / float(nodes_second)) ** (1.0 / 3.0)
    return 1.0 / max(k - 1.0, 1e-6)


def with_floor(problem, machine=None):
    """The problem with its discretisation floor (``Problem.floor``) and the floor in its tolerance.

    Without a second mesh (a reduced model that does not record its element size) the problem as it is.
    """
    got = coarse_model(machine or problem.machine, problem.rom)
    if got is None:
        return problem
    coarse, h2, n2 = got
    n1 = int(problem.rom.meta["nodes"])
    factor = extrapolation_factor(n1, n2)
    diff = factor * mesh_difference(problem, coarse)
    va = problem.split.validation
    rms = np.sqrt(np.mean(diff[va] ** 2, axis=0))
    floor = Floor(diff, rms, factor, (float(problem.rom.meta["element_size_mm"]), h2), (n1, n2))
    tol = rms if problem.tolerance is None else np.maximum(problem.tolerance, rms)
    return dataclasses.replace(problem, tolerance=tol, floor=floor)


def _contribution(problem, effect) -> float:
    """Noise-weighted norm over every row of what one effect (Candidate, params) changes in the model's channels."""
    from hybridcomp.diagnose.effects import predicted_channels

    base = predicted_channels(problem, [])
    return float(np.linalg.norm((predicted_channels(problem, [effect]) - base) * problem.weights[None, :]))


def mimicked(problem, candidate) -> np.ndarray:
    """The parameters of ``candidate`` fitted to the discretisation error alone.

    The data: the model's channels plus ``Floor.difference`` (what the effect can make of the mesh).
    """
    from hybridcomp.diagnose.effects import predicted_channels
    from hybridcomp.diagnose.selection import fit

    fake = dataclasses.replace(problem, Y=predicted_channels(problem, []) + problem.floor.difference)
    (p,), _, _ = fit(fake, [], [candidate])
    return p


def within_floor(problem, fitted) -> list:
    """The fitted effects (``Fitted``) within the model's discretisation error.

    An effect is within it when what it changes in the channels at its fitted parameters is no larger (noise-weighted
    norm over every row) than what it changes at the parameters the discretisation error alone gives it
    (:func:`mimicked`): its parameter change is no more than the mesh can make.
    """
    if getattr(problem, "floor", None) is None or not fitted:
        return []
    out = []
    for f in fitted:
        c = f.candidate
        if _contribution(problem, (c, f.params)) <= _contribution(problem, (c, mimicked(problem, c))):
            out.append(f)
    return out


def parameter_shift(problem, fitted, i: int) -> np.ndarray:
    """How far the discretisation error could move effect ``i``'s parameters: |Δp| (one per parameter).

    The linearised least-squares shift of the parameters, the other effects held, when the training rows carry
    ``Floor.difference`` on top of the data: ``Δp = (JᵀJ)⁻¹ Jᵀ (w ∘ D)``, ``J`` the noise-weighted channels' derivative
    in the parameters at the fit (central differences over ``FD_STEP`` of each parameter's range).
    """
    from hybridcomp.diagnose.effects import predicted_channels

    if getattr(problem, "floor", None) is None:
        return np.zeros(len(fitted[i].params))
    tr = problem.split.train
    effects = [(f.candidate, np.asarray(f.params, float)) for f in fitted]
    c, p = effects[i]
    cols = []
    for j in range(p.size):
        step = FD_STEP * (c.upper[j] - c.lower[j])
        lo, hi = p.copy(), p.copy()
        lo[j], hi[j] = max(p[j] - step, c.lower[j]), min(p[j] + step, c.upper[j])
        Yp = predicted_channels(problem, effects[:i] + [(c, hi)] + effects[i + 1:])
        Ym = predicted_channels(problem, effects[:i] + [(c, lo)] + effects[i + 1:])
        cols.append(((Yp - Ym)[tr] * problem.weights[None, :]).ravel() / max(hi[j] - lo[j], 1e-300))
    J = np.column_stack(cols)
    D = (problem.floor.difference[tr] * problem.weights[None, :]).ravel()
    return np.abs(np.linalg.lstsq(J, D, rcond=None)[0])
