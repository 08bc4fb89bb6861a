"""The model's own discretisation error: a floor below which no effect is named.

A real machine differs from any mesh.  The reduced model the diagnosis fits stands for an FE model of one element
size; the same machine on a coarser mesh answers the same inputs a little differently, and that difference is what
the discretisation alone can make of the channels.  An effect whose contribution to every channel lies within it
(e.g. a source's power scaled by 1.24 to absorb the mesh difference between 80 and 150 mm elements) is not a cause:
the data cannot tell it from the mesh.

* :func:`coarse_models`: the machine reduced on second meshes, ``COARSER`` × the element size (1.5 and 2) or coarser
  until each has at most half the nodes (element sizes snap to the bodies' dimensions; made once per reduced model,
  kept in its cache);
* :func:`mesh_difference`: both models on the dataset's inputs, channel by channel (nt × nch); extrapolated to the
  model's own error at first order in the element size (:func:`extrapolation_factor`, 2.8 from 80 to 120 mm): the
  floor, whose per-channel RMS over the validation rows is the model's uncertainty (the diagnosis counts a channel's
  residual within it as explained, ``Problem.tolerance``);
* :func:`within_floor`: the named effects that a second mesh moves by as much as they deviate from the model (the
  named effects fitted again on each second mesh, the parameter change extrapolated to the model's error).
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

log = logging.getLogger(__name__)

#: the second meshes' element sizes as multiples of the model's (element sizes snap to the bodies' dimensions, so the
#: error between two meshes is erratic: the floor is the largest of what these make of the data)
COARSER = (1.5, 2.0)
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
    differences : per second mesh, the model's estimated error on the dataset's inputs, per sample and channel
        (nt × nch): the two meshes' difference × its ``factors`` entry [°C or µm]
    rms : per channel, the largest RMS over the validation rows of the ``differences`` [°C or µm]
    factors : per second mesh, the first-order extrapolation of its difference to the model's own error, 1 / (k − 1)
        with k the ratio of the meshes' effective element sizes, (n_model / n_second)^(1/3) [-]
    element_size_mm : the model's element size, then the second meshes' [mm]
    nodes : the model's node count, then the second meshes'
    models : the second meshes' reduced models
    """

    differences: tuple
    rms: np.ndarray
    factors: tuple[float, ...]
    element_size_mm: tuple[float, ...]
    nodes: tuple[int, ...]
    models: tuple = dataclasses.field(default=(), compare=False, repr=False)

    @property
    def difference(self) -> np.ndarray:
        """The largest of the ``differences`` (Frobenius norm over the validation rows' weights aside)."""
        return max(self.differences, key=lambda d: float(np.sum(d**2)))

    def as_dict(self, channels) -> dict:
        return {"element_size_mm": list(self.element_size_mm), "nodes": list(self.nodes),
                "factors": [float(f) for f in self.factors], "rms": {c: float(v) for c, v in zip(channels, self.rms)}}

    def describe(self) -> str:
        others = ", ".join(f"{h:g} mm ({n} nodes, × {f:.2g})" for h, n, f in zip(self.element_size_mm[1:],
                                                                              self.nodes[1:], self.factors))
        return f"its {self.element_size_mm[0]:g} mm mesh ({self.nodes[0]} nodes) against {others}"


def coarse_models(machine, rom, factors=COARSER) -> list:
    """The machine reduced on coarser meshes, one per factor of ``factors``.

    Each at ``factor`` × the model's element size, or larger if that meshes nearly the same (at most
    ``MAX_NODE_RATIO`` of the model's nodes, and no mesh twice).

    Returns [(reduced model, element size [mm], node count)], empty when the reduced model does not say its element
    size and node count (then no floor is known).  Kept in ``rom._cache``.
    """
    from hybridcomp.fem.loads import example_loads
    from hybridcomp.fem.model import build_model
    from hybridcomp.rom.machine import reduce_model

    key = ("coarse_models", tuple(float(f) for f in factors))
    if key in rom._cache:
        return rom._cache[key]
    h = rom.meta.get("element_size_mm")
    n0 = rom.meta.get("nodes") or (rom.V.shape[0] if rom.V is not None else None)
    out: list = []
    if not h or n0 is None:
        log.info("the reduced model does not record its element size and node count: no discretisation floor")
        rom._cache[key] = out
        return out
    t0 = time.perf_counter()
    for factor in factors:
        for f in (factor, 4.0 * factor / 3.0, 5.0 * factor / 3.0, 2.0 * factor):
            try:
                model = build_model(machine, rom.meta.get("pose_mm"), float(h) * f)
            except ValueError as exc:  # too coarse for the machine's bodies
                log.info("no mesh at %g mm: %s", float(h) * f, exc)
                break
            if model.n <= MAX_NODE_RATIO * n0 and all(model.n != o[2] for o in out):
                coarse = reduce_model(model, order=min(COARSE_ORDER, rom.order), keep_basis=False,
                                      check_loads=example_loads(machine, duration_h=1.0, dt_s=600.0))
                out.append((coarse, float(h) * f, int(model.n)))
                break
    log.info("second meshes for the discretisation floor: %s in %.1f s",
             ", ".join(f"{o[1]:g} mm ({o[2]} nodes)" for o in out) or "none", time.perf_counter() - t0)
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
    got = coarse_models(machine or problem.machine, problem.rom)
    if not got:
        return problem
    n1 = int(problem.rom.meta["nodes"])
    factors = tuple(extrapolation_factor(n1, n2) for _, _, n2 in got)
    diffs = tuple(f * mesh_difference(problem, coarse) for f, (coarse, _, _) in zip(factors, got))
    va = problem.split.validation
    rms = np.max([np.sqrt(np.mean(d[va] ** 2, axis=0)) for d in diffs], axis=0)
    floor = Floor(diffs, rms, factors, (float(problem.rom.meta["element_size_mm"]), *(h for _, h, _ in got)),
                  (n1, *(n for _, _, n in got)), tuple(c for c, _, _ in got))
    # the residual the mesh may leave: the nearest second mesh's difference as it is (not extrapolated)
    near = np.sqrt(np.mean((diffs[0][va] / factors[0]) ** 2, axis=0))
    tol = near if problem.tolerance is None else np.maximum(problem.tolerance, near)
    return dataclasses.replace(problem, tolerance=tol, floor=floor)


def on_mesh(problem, coarse):
    """The problem on a second mesh's reduced model (same data, inputs and noise; no per-body drift rows)."""
    names = [problem.rom.output_names[i] for i in problem.out_index]
    rows = tuple(list(coarse.output_names).index(n) for n in names)
    return dataclasses.replace(problem, rom=coarse, out_index=rows, body_names=(), floor=None, _cache={})


#: effects a second mesh's reduced model can carry (it has no basis for a located source, no per-body drift rows)
PORTABLE = ("ambient_lag", "missing_source", "power_scale", "exponent", "htc", "htc_motion", "sensor_lag",
            "sensor_offset", "workspace_offset")


def within_floor(problem, fitted) -> list:
    """The fitted effects (``Fitted``) within the model's discretisation error.

    The named effects are fitted again, jointly, on each second mesh's reduced model (same data, from the parameters
    found).  An effect is within the discretisation error when the mesh moves it by as much as it deviates from the
    model: ``factor × ‖Δ_mesh‖ ≥ ‖Δ_nominal‖``, both the noise-weighted change of the channels (every row) that the
    parameter difference makes, the effect alone on the model, ``factor`` the second mesh's extrapolation to the
    model's own error.  A name the mesh can move that far is the mesh's, not the machine's.  Effects a second mesh
    cannot carry (a located source, an expansion coefficient) are kept.
    """
    from hybridcomp.diagnose.selection import fit

    floor = getattr(problem, "floor", None)
    if floor is None or not fitted:
        return []
    port = [f for f in fitted if f.candidate.kind in PORTABLE]
    if not port:
        return []
    from hybridcomp.diagnose.effects import predicted_channels

    moved = np.zeros(len(port))
    # the effects a second mesh cannot carry are held as the model makes them: their change of the channels taken off
    # the data
    rest = [(f.candidate, f.params) for f in fitted if f.candidate.kind not in PORTABLE]
    held = predicted_channels(problem, rest) - predicted_channels(problem, []) if rest else 0.0
    for factor, coarse in zip(floor.factors, floor.models):
        other = dataclasses.replace(on_mesh(problem, coarse), Y=problem.Y - held)
        try:
            params, _, _ = fit(other, [], [f.candidate for f in port], start=[f.params for f in port])
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.info("the named effects could not be fitted on the %s-node mesh: %s", coarse.meta.get("nodes"), exc)
            continue
        for k, (f, pc) in enumerate(zip(port, params)):
            c = f.candidate
            moved[k] = max(moved[k], factor * _change(problem, c, f.params, pc))
    return [f for k, f in enumerate(port) if moved[k] >= _change(problem, f.candidate, f.params, f.candidate.nominal)]


def _change(problem, candidate, p, q) -> float:
    """Noise-weighted norm over every row of the channels' change between parameters ``p`` and ``q`` of one effect."""
    from hybridcomp.diagnose.effects import predicted_channels

    a = predicted_channels(problem, [(candidate, np.asarray(p, float))])
    b = predicted_channels(problem, [(candidate, np.asarray(q, float))])
    return float(np.linalg.norm((a - b) * problem.weights[None, :]))


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
