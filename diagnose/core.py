"""The diagnosis entry points: prepare the reduced model, diagnose a dataset."""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from hybridcomp.diagnose.data import Dataset, DatasetError, Split, parse_split
from hybridcomp.diagnose.effects import library
from hybridcomp.diagnose.problem import body_drift_rows, build_problem, with_body_rows
from hybridcomp.diagnose.selection import Diagnosis, select
from hybridcomp.fem.blas import single_blas_thread

log = logging.getLogger(__name__)

DEFAULT_SPLIT = "0:60%"


def prepare_model(machine, *, rom=None, model=None, element_size_mm: float | None = None, pose_mm: dict | None = None,
                  order: int | None = None, tol_K: float = 0.02, tol_um: float = 0.1, check_loads=None,
                  body_rows: bool = True):
    """The reduced model a diagnosis runs on, with per-body drift rows appended for the expansion effects.

    Parameters
    ----------
    machine : loaded machine
    rom : an existing reduced model of this machine (reduced with its basis V); None: reduce now
    model : the assembled FE model (built here if needed)
    element_size_mm : FE element size [mm] (default: the machine file's)
    pose_mm : pose of the model [mm] (default: mid travel)
    order, tol_K, tol_um, check_loads : passed to :func:`hybridcomp.rom.machine.reduce_model`
    body_rows : compute per-body drift rows (one elastic adjoint set per body) for the expansion effects
    """
    from hybridcomp.fem.model import build_model
    from hybridcomp.rom.machine import reduce_model

    t0 = time.perf_counter()
    if rom is not None and rom.meta.get("poses"):
        raise ValueError("a pose-aware reduced model (reduce --poses) cannot be diagnosed: give the diagnosis the "
                         "model pose's reduced model (reduce without --poses)")
    if rom is not None and rom.output_layout().bodies:
        body_rows = False  # already has per-body drift rows
    if model is None and (rom is None or (body_rows and rom.V is not None)):
        model = build_model(machine, pose_mm, element_size_mm)
    if rom is None:
        rom = reduce_model(model, tol_K=tol_K, tol_um=tol_um, order=order, check_loads=check_loads)
    if body_rows and rom.V is not None and model is not None:
        if model.n != rom.V.shape[0]:
            raise ValueError(f"the reduced model has {rom.V.shape[0]} nodes, the FE model {model.n}: use the same element size")
        bodies, rows = body_drift_rows(model)
        rom = with_body_rows(rom, bodies, rows)
    log.info("model for the diagnosis ready in %.1f s (order %d)", time.perf_counter() - t0, rom.order)
    return rom


def diagnose(machine, dataset: Dataset, split: str | Split = DEFAULT_SPLIT, rom=None, kinds=None,
             max_effects: int = 4, tolerance: tuple[float, float] = (0.02, 0.1), progress: bool = False,
             discretisation: bool = False, place: str = "patch") -> Diagnosis:
    """Diagnose what the reduced model of ``machine`` gets wrong on ``dataset``.

    Parameters
    ----------
    machine : loaded machine (:func:`hybridcomp.models.load_machine`)
    dataset : measured data (:func:`hybridcomp.diagnose.read_dataset`): heat inputs ``*_W``, zone or
        measured air ``*_degC``, measured sensors ``<sensor>_degC`` and drift ``dx_um`` ...
    split : training range (``"0:60%"``, ``"0:24h"``) or a :class:`Split`; validation is the rest
    rom : the model (:func:`prepare_model`); None: reduce the machine's FE model now
    kinds : effect kinds to consider (default: the whole library)
    max_effects : most effects named
    tolerance : (K, µm) residual the model itself may leave (its reduction error): a channel whose validation
        RMS is below this or below 1.5 × its noise level counts as explained
    discretisation : know the model's own discretisation error (``diagnose.discretisation``): the machine reduced on
        second, coarser meshes; the models' difference on the dataset's inputs is a per-channel floor, a residual
        within it counts as explained and an effect the mesh alone could make is not named.  Off by default: the
        second meshes' reductions and the refits on them cost minutes per diagnosis
    place : how a heat source found anywhere on the surface is placed: ``"patch"`` (default) at the best search site,
        known to the search's confidence region; ``"continuous"`` its place fitted on the site's face with its power,
        with an uncertainty in mm from the fit (opt-in: several times the search's cost)
    """
    t0 = time.perf_counter()
    from hybridcomp.diagnose.locate import PLACES

    if place not in PLACES:
        raise ValueError(f"diagnose: place={place!r}, expected one of {', '.join(PLACES)}")
    if not isinstance(split, Split):
        split = parse_split(split, dataset.time_s)
    if rom is None:
        rom = prepare_model(machine)
    problem = build_problem(machine, rom, dataset, split, None, tolerance)
    if discretisation:
        from hybridcomp.diagnose.discretisation import with_floor

        with single_blas_thread():
            problem = with_floor(problem, machine)
    cands = library(problem, kinds)
    log.info("%d candidate effects", len(cands))
    with single_blas_thread():
        memo: dict = {}
        wanted = kinds is None or "located_source" in kinds
        d, cands = _select_above_floor(problem, cands, max_effects, progress, memo)
        if d.verdict == "unexplained" and wanted and rom.V is not None:
            # the machine's own elements leave a structured residual: then, and only then, a heat source the machine
            # file lacks, searched anywhere on the surface (the most flexible hypothesis comes last), on the residual
            # of the model as it is and on the one the partial candidates leave
            from hybridcomp.diagnose.effects import predicted_channels
            from hybridcomp.diagnose.locate import candidates as located

            t1 = time.perf_counter()
            more = located(problem, problem.Y - predicted_channels(problem, []), place=place)
            if d.partial:
                seen = {c.key for c in more}
                more += [c for c in located(problem, problem.Y - d.Y_after, place=place) if c.key not in seen]
            log.info("%d located-source candidates in %.1f s", len(more), time.perf_counter() - t1)
            timings = d.timings_s
            # a new selection with the located sources beside the machine's own effects (the screening fits and
            # joint refits it repeats are remembered)
            d, cands = _select_above_floor(problem, cands + more, max_effects, progress, memo)
            for _ in range(RESEARCHES):
                # still unexplained with a located source beside a sensor's effect (its lag or offset): the search
                # ran on a residual that effect distorted (on the sensor nearest the source, often).  Searched again
                # on the residual the sensor effects leave, and a selection from them (refitted with every effect
                # accepted after, dropped if those make them unnecessary); kept only if it explains the data
                found = list(d.causes) + list(d.partial)
                sensor = [(f.candidate, f.params) for f in found if f.candidate.stage == "out"]
                if d.verdict != "unexplained" or not sensor or all(f.candidate.kind != "located_source" for f in found):
                    break
                seen = {c.key for c in cands}
                new = [c for c in located(problem, problem.Y - predicted_channels(problem, sensor), place=place)
                       if c.key not in seen]
                log.info("%d located-source candidates more on the residual of %s", len(new),
                         "; ".join(c.label for c, _ in sensor))
                if not new:
                    break
                d2, cands2 = _select_above_floor(problem, cands + new, max_effects, progress, memo, seed=tuple(sensor))
                if d2.verdict != "explained":
                    break
                d, cands = d2, cands2
            d.timings_s["without located sources"] = timings["selection"]
        elif d.verdict == "unexplained" and wanted:
            why = ("the search for a heat source anywhere on the surface did not run: the reduced model carries no "
                   "basis (V) to place one (reduce it from the machine file, or load it with its basis)")
            log.warning(why)
            d = dataclasses.replace(d, message=f"{d.message}; {why}")
    if problem.floor is not None:
        from hybridcomp.diagnose.discretisation import parameter_shift

        with single_blas_thread():
            for i, f in enumerate(d.causes):
                if f.candidate.kind == "located_source" and f.candidate.info.get("face") is not None:
                    # how far the model's own discretisation error could move the place: part of its uncertainty
                    k = f.candidate.info["uv_index"]
                    shift = parameter_shift(problem, d.causes, i)[k:k + 2]
                    f.candidate.info["discretisation_shift_mm"] = [float(v) for v in shift]
    d.timings_s["total"] = time.perf_counter() - t0
    d.timings_s["candidates"] = len(cands)
    return d


#: searches for a located source repeated, at most, on the residual the other effects of an unexplained result leave
RESEARCHES = 1
#: selections repeated, at most, with the effects found within the discretisation floor left out
FLOOR_ROUNDS = 3


def _select_above_floor(problem, cands: list, max_effects: int, progress: bool, memo: dict, seed: tuple = ()):
    """:func:`select`, repeated without the effects whose contribution stays within the model's discretisation floor.

    Such an effect (named or partial) is what the mesh alone can make of the data: it is left out of the library and
    the selection runs again (at most ``FLOOR_ROUNDS`` times, then any still within it is dropped from the result).
    Returns the diagnosis and the candidates it chose from.  Without a floor (the default): :func:`select` once.
    ``seed``: as :func:`select`'s (those the floor leaves out dropped from it).
    """
    if problem.floor is None:
        return select(problem, cands, max_effects=max_effects, progress=progress, memo=memo, seed=seed), cands
    from hybridcomp.diagnose.discretisation import within_floor

    dropped: list = []
    for attempt in range(FLOOR_ROUNDS + 1):
        d = select(problem, cands, max_effects=max_effects, progress=progress, memo=memo,
                   seed=tuple((c, p) for c, p in seed if c.key in {k.key for k in cands}))
        low = within_floor(problem, list(d.causes)) + within_floor(problem, list(d.partial))
        if not low:
            break
        dropped += [f.candidate.describe(f.params) for f in low]
        keys = {f.candidate.key for f in low}
        log.info("within the discretisation floor, not named: %s", "; ".join(f.candidate.label for f in low))
        if attempt == FLOOR_ROUNDS:
            d = dataclasses.replace(d, causes=tuple(f for f in d.causes if f.candidate.key not in keys),
                                    partial=tuple(f for f in d.partial if f.candidate.key not in keys))
            break
        cands = [c for c in cands if c.key not in keys]
    if problem.floor is not None:
        f = problem.floor
        note = (f"the model's discretisation error ({f.describe()}) is a floor per channel: up to "
                + ", ".join(f"{c} {v:.3g}" for c, v in zip(problem.channels, f.rms)))
        if dropped:
            note += "; within it, not named: " + "; ".join(dict.fromkeys(dropped))
        d = dataclasses.replace(d, message=f"{d.message}; {note}")
    return d, cands


def dataset_from_trace(path, machine, increment_s: float = 60.0, raw: Dataset | None = None) -> Dataset:
    """A measured trace turned into a diagnosis dataset.

    The trace: ``time_s``, axis positions ``x_mm`` …, ``spindle_rpm``, measured ``Tamb_degC``, sensors
    ``T1_degC`` …, drift ``dx_um`` ….

    The histogram generator makes the heat inputs and zone air per increment (its loads-CSV contract: values at
    the trace start and at every increment end); the measured channels are interpolated to those times.

    Parameters
    ----------
    path : trace CSV
    machine : the machine (axes, sources)
    increment_s : histogram increment [s]
    raw : the trace file already read as a dataset (its own column names), if the caller has it
    """
    from hybridcomp.diagnose.data import read_dataset
    from hybridcomp.histogram import boundary_conditions, increments_from_trace

    inc = increments_from_trace(path, machine, increment_s)
    loads = boundary_conditions(machine, inc)
    if raw is None:
        raw = read_dataset(path)
    t = loads.time_s
    cols = {n: loads.values[:, j] for j, n in enumerate(loads.names)}
    for n in raw.names:
        if n not in cols and (n.endswith("_um") or n.endswith("_degC")):
            cols[n] = np.interp(t, raw.time_s, raw[n])
    return Dataset(t, cols, f"{path} (trace in {increment_s:g} s increments)")


def read_measured(path, machine, column_map=None, increment_s: float = 60.0) -> Dataset:
    """Read a measured dataset for the model mode.

    A loads-form CSV (heat inputs ``*_W``) as it is, a trace (axis positions, no heat inputs) through the histogram
    generator (:func:`dataset_from_trace`).
    """
    from hybridcomp.diagnose.data import read_dataset
    from hybridcomp.histogram.trace import position_column

    ds = read_dataset(path, column_map)
    has_power = any(n.endswith("_W") for n in ds.names)
    positions = [position_column(a.name) for a in machine.axes]
    if not has_power and positions and all(p in ds.names for p in positions):
        if column_map is not None:
            raise DatasetError(f"{path}: a trace is read by its own column names; a column map is only for loads-form datasets")
        return dataset_from_trace(path, machine, increment_s, raw=ds)  # read without a map: the trace as it is
    return ds


def channel_residuals(d: Diagnosis) -> dict[str, np.ndarray]:
    """The residual per channel (measured minus the extended model), over all rows."""
    p = d.problem
    return {c: p.Y[:, k] - d.Y_after[:, k] for k, c in enumerate(p.channels)}
