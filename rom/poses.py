"""A reduced structure model that gives the drift at every pose: one reduced model per support pose.

The drift at a pose depends on where the moving bodies sit twice: in the elastic problem (lever arms, supports)
and in the heat paths (the headstock heats the column where it touches it).  Carrying one thermal model's field
with the bodies (:func:`hybridcomp.fem.poses.pose_drift`) gets the first and misses the second: on vmc800 its
z error reaches 2.7 µm at off-grid poses (``benchmarks/pose_drift.py``).  Here every support pose of a
:class:`~hybridcomp.fem.poses.PoseGrid` gets its own FE model (thermal and elastic, built at that pose) and its own
reduced model, cheaply: the basis is the model-pose reduced model's basis carried with the bodies onto that pose's
mesh (:func:`~hybridcomp.fem.poses.carry_field`), extended by ``enrich`` rational Krylov directions of that pose's
own system (its steady state exact), and the pose's operators are projected on it (one-sided Galerkin: symmetric
and stable like every reduced model here).  No FE check runs per pose: the benchmark checks the result.

The feed drives (``[[drives]]``) come along with the error they add beyond the structure
(:class:`hybridcomp.fem.drives.DriveError`): a screw's 1D thermal model is a block of its own (full order, a
hundred-odd nodes; its convection enters as part of its zone's, scaled to the screw's coefficient, so a changed
zone coefficient scales both alike), and the carrier's share (minus its expansion along the screw; a linear
scale's ``α_scale − α_carrier`` on it) reads the model pose's block, the carrier's field at the model's pose: a
screw's output row spans its own block and the first one.  Their outputs are the positioning errors
``e<AXIS>@<x>`` [m] at ``FEEDBACK_POINTS`` positions over each axis' travel.

The result is one :class:`~hybridcomp.rom.reduced.ReducedModel`, block diagonal but for the screws' output rows:
the model pose's reduced model first, unchanged (its sensors and drift are the first outputs, so everything that
reads a reduced model reads this one), then per further support pose its drift ``dx@k``, ``dy@k``, ``dz@k``, then
the screws.  ``meta["poses"]``
holds the grid, ``meta["feedback"]`` the drives; :func:`drift_along` gives the drift, TCP minus table, at the axis
positions of every time: the support poses interpolated plus every drive's added error at its axis' position.

The pose history: each block runs as if the machine stood at its support pose all along.  Where the machine was
decides the field, so the model keeps a state transfer between the blocks (:func:`pose_transfer`, built with them
from their bases carried with the bodies) and, at a move, every block takes the field the blocks gave where the
machine had been (:func:`blend_history`); :func:`integrate_along` runs a path so (the monitor's model step does the
same, :func:`hybridcomp.monitor.volumetric.advance`).  ``benchmarks/pose_path.py`` checks it against FE carried
along paths with moves.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la

from hybridcomp.fem.drives import drive_error
from hybridcomp.fem.iso230 import axis_sign
from hybridcomp.fem.operators import ThermalOperators
from hybridcomp.fem.poses import PoseGrid, carry_field, default_levels, pose_grid
from hybridcomp.models.layout import feedback_output_names, output_layout, pose_output_names
from hybridcomp.rom.krylov import Reductor, orthonormal_extension, project
from hybridcomp.rom.reduced import ReducedModel, RomInputError

#: Krylov directions of a support pose's own system added to the carried basis
DEFAULT_ENRICH = 20
#: positions over each axis' travel at which a drive's positioning error is an output (linear between them)
FEEDBACK_POINTS = 17


def reduce_at_poses(model, rom: ReducedModel, scheme: str = "star", enrich: int = DEFAULT_ENRICH,
                    input_scale: np.ndarray | None = None, drives: bool = True, workers: int = 1,
                    scheduler: str = "process", progress: bool = False,
                    levels: dict[str, int] | None = None) -> ReducedModel:
    """The pose-aware reduced model of an FE model and its reduced model (module docstring).

    Parameters
    ----------
    model : the FE model ``rom`` was reduced from (:class:`~hybridcomp.fem.model.ThermoElasticModel`)
    rom : its reduced model, with its basis ``V``
    scheme : the support poses, ``"star"`` (each axis' levels with the others at the model's pose) or ``"grid"``
        (the product of the levels)
    enrich : Krylov directions of each support pose's own system added to the carried basis
    input_scale : typical magnitude per input (W, K) for choosing those directions (default: 16 h example day)
    drives : include the machine's feed drives (their positioning errors)
    workers, scheduler : where the support poses' FE models are built and reduced, as an FE batch
        (:mod:`hybridcomp.fem.batch`): one worker and ``"process"``: here, one after another; more workers: a
        local process pool (one BLAS thread each); ``"local"`` or a Dask scheduler address: a Dask cluster
    progress : a progress bar over the support poses (stderr)
    levels : per axis name its number of levels (odd, ≥ 3; :func:`hybridcomp.fem.poses.pose_grid`), 3 for the rest;
        None: :func:`hybridcomp.fem.poses.default_levels` (a star: vmc800 7 along Y and Z; a grid: three along
        every axis); ``{}``: three along every axis
    """
    if rom.V is None:
        raise RomInputError("the pose-aware model carries the reduced model's basis: reduce with the basis kept")
    if rom.V.shape[0] != model.n:
        raise RomInputError(f"the reduced model's basis has {rom.V.shape[0]} rows, the FE model {model.n} nodes")
    if rom.meta.get("poses"):
        raise RomInputError("this reduced model is pose-aware already")
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    t0 = time.perf_counter()
    machine = model.machine
    grid = pose_grid(model, scheme, default_levels(machine, scheme) if levels is None else levels)
    if input_scale is None:
        from hybridcomp.fem.loads import example_loads

        U = machine.layout().inputs(example_loads(machine, 16.0, 60.0))
        input_scale = np.abs(U).max(axis=0)
    scale = np.where(np.asarray(input_scale) > 0, input_scale, 1.0)
    ns = len(model.sensor_names)
    tol = np.r_[np.full(ns, rom.meta.get("tol_K", 0.05)), np.full(3, rom.meta.get("tol_um", 0.2) * 1e-6)]
    blocks, names, orders = [], [], [rom.order]
    mid_C, mid_names, feedback, spans = rom.C, (), {}, []
    h_range = tuple(rom.meta.get("h_range", (0.5, 2.0)))
    jobs = [(model, rom.V, grid.pose_mm(k), enrich, tol, scale, h_range) for k in range(1, len(grid.poses))]
    M0V = model.M @ rom.V  # the model pose's own basis: the mass-weighted projection onto it
    to_block, from_block = [np.linalg.solve(rom.M, M0V.T)], [rom.V]
    for k, block in enumerate(_run_jobs(jobs, workers, scheduler, progress), start=1):
        blocks.append(block[:6])
        to_block.append(block[6])
        from_block.append(block[7])
        names += pose_output_names(k)
        orders.append(block[0].shape[0])
    transfer = pose_transfer(to_block, from_block)
    del to_block, from_block
    for drive in machine.drives if drives else ():
        positions = np.linspace(*machine.axis(drive.axis).travel_mm, FEEDBACK_POINTS)
        out = feedback_output_names(drive.axis, positions)
        feedback[drive.axis] = {"feedback": drive.feedback, "positions_mm": positions.tolist(), "outputs": list(out),
                                "direction": machine.axis(drive.axis).direction,
                                "sign": axis_sign(machine, drive.axis)}
        err = drive_error(model, drive)  # the error the drive adds beyond the structure (fem.drives)
        carrier = err.fe_rows(positions) @ rom.V * 1e-6  # the carrier's field at the model's pose: the first block
        if err.screw is None:  # a linear scale: rows of the first block only
            mid_C = np.vstack([mid_C, carrier])
            mid_names += out
            continue
        screw = err.screw
        z = machine.layout().zones.index(drive.screw_zone)
        h_zone = float(rom.h_W_m2K[z])
        Hs = np.zeros((len(rom.h_W_m2K),) + screw.M.shape)
        # so that h_zone * Hs[z] is the screw's own convection and its bearings' conductance (both to the zone's
        # air; a changed zone coefficient scales the bearings' conductance too)
        Hs[z] = (screw.H + screw.G).toarray() / h_zone
        m = len(machine.layout().heat_inputs)
        blocks.append((screw.M.toarray(), screw.K.toarray(), Hs, screw.Bu[:, :m], Hs.sum(axis=2).T,
                       err.screw_rows(positions) * 1e-6))
        names += out
        orders.append(screw.s_mm.size)
        spans.append((out, carrier))  # these outputs' rows span the screw's block and the first one
    M = la.block_diag(rom.M, *(b[0] for b in blocks))
    K = la.block_diag(rom.K, *(b[1] for b in blocks))
    H = np.array([la.block_diag(rom.H[i], *(b[2][i] for b in blocks)) for i in range(len(rom.h_W_m2K))])
    H = H.reshape(len(rom.h_W_m2K), M.shape[0], M.shape[0])
    B = np.vstack([rom.B] + [b[3] for b in blocks])
    Hb = np.vstack([rom.Hb] + [b[4] for b in blocks])
    C = la.block_diag(mid_C, *(b[5] for b in blocks))
    all_names = tuple(rom.output_names) + mid_names + tuple(names)
    for out, carrier in spans:
        C[[all_names.index(n) for n in out], :rom.order] += carrier
    meta = {**rom.meta, "poses": grid.as_dict() | {"orders": orders, "enrich": enrich,
                                                   "build_s": time.perf_counter() - t0},
            "feedback": feedback}
    D = None if rom.D is None else np.vstack([rom.D, np.zeros((M.shape[0] - rom.order, rom.D.shape[1]))])
    return ReducedModel(ThermalOperators(M=M, K=K, H=H, h_W_m2K=np.asarray(rom.h_W_m2K, float), B=B, Hb=Hb, C=C,
                                         input_names=rom.input_names,
                                         output_names=all_names),
                        D=D, disturbance_names=tuple(rom.disturbance_names) if rom.D is not None else (),
                        pose_transfer=transfer, meta=meta)


def pose_transfer(to_block: list[np.ndarray], from_block: list[np.ndarray]) -> np.ndarray:
    """The support poses' state transfer (R × R): block (k, j) = ``to_block[k] @ from_block[j]``.

    ``from_block[j]`` (n × r_j) gives the field block j's state stands for on the model's mesh (its basis carried
    with the bodies), ``to_block[k]`` (r_k × n) projects a field on the model's mesh onto block k (carried to its
    pose's mesh, then the Galerkin projection weighted with the capacity matrix).  A diagonal block is that
    block's own round trip: :func:`blend_history` moves a block by the difference its round trip sees, so what
    the trip loses (interpolation between the meshes, the part outside the other bases) is kept, not lost.
    """
    o = np.cumsum([0] + [T.shape[0] for T in to_block])
    T = np.empty((o[-1], o[-1]))
    for k, to in enumerate(to_block):
        for j, frm in enumerate(from_block):
            T[o[k]:o[k + 1], o[j]:o[j + 1]] = to @ frm
    return T


def model_pose_block(prom: ReducedModel) -> ReducedModel:
    """The model pose's reduced model inside a pose-aware one: its first block, as :func:`reduce_at_poses` got it.

    Its operators, sensors, drift and disturbance shapes are those of the reduced model the pose-aware one was
    built from (a model written before the shapes were kept has none).
    """
    grid_of(prom)
    r = int(prom.meta["poses"]["orders"][0])
    layout = prom.output_layout()
    rows = list(layout.indices("sensors")) + list(layout.indices("drift"))
    meta = {k: v for k, v in prom.meta.items() if k not in ("poses", "feedback")}
    ops = ThermalOperators(M=prom.M[:r, :r], K=prom.K[:r, :r], H=prom.H[:, :r, :r], h_W_m2K=prom.h_W_m2K,
                           B=prom.B[:r], Hb=prom.Hb[:r], C=prom.C[rows, :r], input_names=prom.input_names,
                           output_names=tuple(prom.output_names[i] for i in rows))
    D = None if prom.D is None else prom.D[:r]
    return ReducedModel(ops, D=D, disturbance_names=tuple(prom.disturbance_names) if D is not None else (), meta=meta)


def pose_block(model, V_mid: np.ndarray, pose_mm: dict, enrich: int, tol: np.ndarray, scale: np.ndarray,
               h_range: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """The reduced operators (M, K, H, B, Hb, drift rows C) of one support pose (a job of :func:`reduce_at_poses`).

    Builds the FE model at ``pose_mm``, carries the model pose's basis ``V_mid`` onto its mesh, extends it by
    ``enrich`` Krylov directions of that pose's system and projects.  Also its two halves of the pose transfer
    (:func:`pose_transfer`): the projection of a field on the model's mesh onto this block (r × n) and this
    block's field carried to the model's mesh (n × r).
    """
    from hybridcomp.fem.model import build_model
    from hybridcomp.rom.machine import h_samples, system_from_model

    machine = model.machine
    fe = build_model(machine, pose_mm, machine.mesh.element_size_mm)
    system = system_from_model(fe)
    V = la.qr(carry_field(model, fe.mesh) @ V_mid, mode="economic")[0]
    if enrich > 0:
        own = Reductor(system, tol, scale, h_samples(fe.h_W_m2K, h_range))
        V = np.hstack([V, orthonormal_extension(V, own.reduce(order=enrich).V)])
    P = project(system, V)
    drift = list(output_layout(system.output_names, model="the support pose's FE model").drift_indices)
    MV = fe.M @ V  # the capacity-weighted projection of a field carried here from the model's mesh
    to_block = np.linalg.solve(P["M"], (carry_field(model, fe.mesh).T @ MV).T)
    from_block = carry_field(fe, model.mesh) @ V
    return P["M"], P["K"], P["H"], P["B"], P["Hb"], P["C"][drift], to_block, from_block


def _run_jobs(jobs: list[tuple], workers: int, scheduler: str, progress: bool):
    """:func:`pose_block` of every job, in order: here (one worker), on a process pool or on a Dask cluster."""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), unit="pose", desc="support poses", leave=False)
    try:
        if workers <= 1 and scheduler == "process":
            for job in jobs:
                yield pose_block(*job)
                if bar is not None:
                    bar.update()
            return
        from hybridcomp.fem.batch import dask_client, process_pool

        if scheduler == "process":
            with process_pool(workers) as ex:
                futures = [ex.submit(pose_block, *job) for job in jobs]
                for f in futures:
                    yield f.result()
                    if bar is not None:
                        bar.update()
            return
        with dask_client(scheduler, workers) as client:
            futures = [client.submit(pose_block, *job, pure=False) for job in jobs]
            for f in futures:
                yield f.result()
                if bar is not None:
                    bar.update()
    finally:
        if bar is not None:
            bar.close()


def grid_of(rom: ReducedModel) -> PoseGrid:
    """The support poses of a pose-aware reduced model."""
    d = rom.meta.get("poses")
    if not d:
        raise RomInputError("this reduced model knows one pose only (reduce with --poses)")
    return PoseGrid.from_dict(d)


def drift_along(rom: ReducedModel, Y: np.ndarray, positions_mm: np.ndarray, feedback: bool = True) -> np.ndarray:
    """The drift [µm] (nt × 3), TCP minus table, at the axis positions of every row, from a pose-aware model.

    The structure's drift interpolated between the support poses, plus (``feedback``) the positioning error every
    drive adds to it at its axis' position (linear between its output positions; the feedback's length less the
    carrier's, :class:`hybridcomp.fem.drives.DriveError`), with the sign of the side the axis moves.

    Parameters
    ----------
    rom : a pose-aware reduced model (:func:`reduce_at_poses`)
    Y : its outputs (nt × q), from :meth:`~hybridcomp.rom.reduced.ReducedModel.integrate`
    positions_mm : axis positions per row (nt × axes, machine order), or one row for every time [mm]
    feedback : add the drives' added positioning errors
    """
    grid = grid_of(rom)
    outputs = rom.output_layout()
    D = np.stack([Y[:, list(outputs.pose_indices(k))] for k in range(len(grid.poses))], axis=1) * 1e6  # nt × poses × 3
    W = grid.weights_along(positions_mm)
    if W.shape[0] == 1:
        W = np.repeat(W, Y.shape[0], axis=0)
    if W.shape[0] != Y.shape[0]:
        raise ValueError(f"{W.shape[0]} rows of positions for {Y.shape[0]} rows of outputs")
    drift = np.einsum("tk,tkd->td", W, D)
    if feedback:
        P = np.atleast_2d(np.asarray(positions_mm, float))
        P = np.repeat(P, Y.shape[0], axis=0) if P.shape[0] == 1 else P
        for fb in outputs.feedback:
            x = P[:, grid.axes.index(fb.axis)]
            E = Y[:, list(fb.indices)] * 1e6
            e = np.array([np.interp(x[t], fb.positions_mm, E[t]) for t in range(Y.shape[0])])
            drift[:, fb.direction] += fb.sign * e
    return drift


#: how :func:`integrate_along` follows the poses the machine visits (:func:`blend_history`)
HISTORIES = ("moves", "steps", "none")
#: a move, for the pose history: interpolation weights that differ by more than this (any support pose's) [-];
#: 0.1 is a tenth of an axis' half travel
MOVE_WEIGHT_TOL = 0.1
#: the pose history's clock [s]: the blocks are blended at most at these ticks, with the time-weighted weights of
#: where the machine was since the last tick; the same ticks whatever the model's step (60 s, 5 min), so the
#: history does not depend on it, and at most 96 blends a day
HISTORY_TICK_S = 900.0


@dataclass(frozen=True)
class StepPoses:
    """Where the machine was over model steps: its samples' support-pose interpolation weights.

    Arrays of shape (poses,) for one step or (steps × poses) for a path's rows.  The pose history decides from the
    samples, not from the step's mean, so that the same samples give the same blends on 1 min and on 5 min steps.

    Attributes
    ----------
    weights : the time-weighted mean over the step (each sample for the time until the next)
    low, high : the smallest and largest weight of each support pose over the step's samples
    first : the weights of the step's first sample
    """

    weights: np.ndarray
    low: np.ndarray
    high: np.ndarray
    first: np.ndarray

    @staticmethod
    def held(weights: np.ndarray) -> StepPoses:
        """Steps in which the machine held its pose: every sample at ``weights``."""
        w = np.asarray(weights, float)
        return StepPoses(w, w, w, w)

    @staticmethod
    def of(sample_weights: np.ndarray, dt_s: np.ndarray | None = None) -> StepPoses:
        """One step of samples' weights (m × poses), each standing for ``dt_s`` (default: equal)."""
        W = np.atleast_2d(np.asarray(sample_weights, float))
        dt = np.ones(W.shape[0]) if dt_s is None else np.asarray(dt_s, float)
        if dt.sum() <= 0:
            dt = np.ones(W.shape[0])
        return StepPoses(dt @ W / dt.sum(), W.min(axis=0), W.max(axis=0), W[0])

    def row(self, k: int) -> StepPoses:
        """Row ``k`` of a path's steps."""
        return StepPoses(self.weights[k], self.low[k], self.high[k], self.first[k])

    @property
    def spread(self) -> np.ndarray | float:
        """How far the samples' weights went from the step's mean (largest over the support poses)."""
        d = np.maximum(self.high - self.weights, self.weights - self.low)
        return d.max(axis=-1)


@dataclass(frozen=True)
class HistoryWindow:
    """Where the machine was since the pose history's last tick (:func:`history_step`).

    Attributes
    ----------
    since_s : time since the tick [s]
    weights : the time-weighted interpolation weights over it (None before the first step)
    low, high : the smallest and largest weight of each support pose over its samples
    moved : the machine moved in it (a window saved before ``low`` and ``high`` were kept)
    """

    since_s: float = 0.0
    weights: np.ndarray | None = None
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    moved: bool = False

    def as_dict(self) -> dict:
        def lst(v):
            return None if v is None else [float(x) for x in v]

        return {"since_s": self.since_s, "moved": self.moved, "weights": lst(self.weights), "low": lst(self.low),
                "high": lst(self.high)}

    @staticmethod
    def from_dict(d: dict) -> HistoryWindow:
        def arr(v):
            return None if v is None else np.asarray(v, float)

        w = arr(d["weights"])
        if "low" not in d:  # saved before the samples' range was kept: its first step and whether it moved
            first = arr(d.get("first"))
            lo = hi = first if first is not None else w
            return HistoryWindow(float(d["since_s"]), w, lo, hi, bool(d["moved"]))
        return HistoryWindow(float(d["since_s"]), w, arr(d["low"]), arr(d["high"]), bool(d.get("moved", False)))


def history_step(window: HistoryWindow, step: StepPoses | np.ndarray, step_s: float, tol: float = MOVE_WEIGHT_TOL,
                 tick_s: float = HISTORY_TICK_S) -> tuple[np.ndarray | None, HistoryWindow]:
    """Before a step of ``step_s`` seconds at ``step`` (its samples' weights): blend or not, and the window after it.

    At a tick (``tick_s`` since the last one) the blocks are blended with the window's time-weighted weights when
    the machine moved in it or moves on now: when any support pose's weight over the window's samples and the new
    step's first sample ranges over more than ``tol``.  A machine that held its pose all along is left alone, so
    each block keeps its own heat paths there.  The decision reads the samples, not the steps' means, so the same
    samples give the same blends on 1 min and on 5 min steps (``benchmarks/pose_history_step.py``).  ``step``: a
    :class:`StepPoses` row, or weights for a step in which the machine held its pose.  Returns the weights to
    blend with (None: no blend) and the window with this step in it.
    """
    s = step if isinstance(step, StepPoses) else StepPoses.held(step)
    blend = None
    if window.weights is not None and window.since_s >= tick_s - 1e-9:
        lo, hi = np.minimum(window.low, s.first), np.maximum(window.high, s.first)
        if window.moved or (hi - lo).max() > tol:
            blend = window.weights
        window = HistoryWindow()
    w = np.asarray(s.weights, float)
    if window.weights is None:
        return blend, HistoryWindow(step_s, w, np.asarray(s.low, float), np.asarray(s.high, float))
    total = window.since_s + step_s
    avg = w if total <= 0 else (window.weights * window.since_s + w * step_s) / total
    return blend, HistoryWindow(total, avg, np.minimum(window.low, s.low), np.maximum(window.high, s.high),
                                window.moved)


def blend_history(prom: ReducedModel, x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The state after the machine was where the interpolation weights ``weights`` say: the pose history.

    Every support pose's block runs as if the machine stood at that pose (its heat paths).  The field the machine
    has is the one the blocks give where it was: their fields ``F_j`` (carried to the model's mesh) blended with the
    weights ``w_j`` of where it was (time-weighted since the history's last tick, :func:`history_step`).  Every
    block ``k`` takes the difference between that field and its own, carried onto its pose:
    ``x_k ← x_k + P_k (Σ_j w_j F_j − F_k)``, with ``T_kj = P_k F_j`` (:attr:`ReducedModel.pose_transfer`).  At a
    support pose (one weight 1) its block is unchanged and every other takes its field; blocks that agree are left
    as they are (a uniform rise, any weights); what a block holds beyond the trip between the meshes is kept.  The
    screws' blocks (after the support poses') are not touched.

    Parameters
    ----------
    prom : a pose-aware reduced model with its pose transfer (:func:`reduce_at_poses`)
    x : its state (order,)
    weights : the support poses' interpolation weights (:meth:`~hybridcomp.fem.poses.PoseGrid.weights`), sum 1
    """
    T = prom.pose_transfer
    if T is None:
        raise RomInputError("this pose-aware reduced model has no pose transfer (reduced before the pose history "
                            "was modelled): reduce it again with --poses")
    grid = grid_of(prom)
    w = np.asarray(weights, float)
    if w.shape != (len(grid.poses),):
        raise ValueError(f"{w.shape} weights for {len(grid.poses)} support poses")
    if not (np.all(np.isfinite(w)) and abs(w.sum() - 1.0) <= 1e-9):
        raise ValueError(f"the support poses' weights must be finite and sum to 1, got sum {float(w.sum())!r}")
    orders = prom.meta["poses"]["orders"][:len(grid.poses)]
    o = np.cumsum([0] + list(orders))
    xs = np.asarray(x[:o[-1]], float)
    y = np.array(x, float, copy=True)
    y[:o[-1]] += T @ (np.repeat(w, orders) * xs)
    for k in range(len(orders)):
        b = slice(o[k], o[k + 1])
        y[b] -= T[b, b] @ xs[b]
    return y


def history_cuts(time_s: np.ndarray, weights: np.ndarray | StepPoses, tol: float = MOVE_WEIGHT_TOL,
                 tick_s: float = HISTORY_TICK_S) -> list[tuple[int, np.ndarray]]:
    """Where a path's pose history blends its blocks, and with which weights: (row, weights) in time order.

    ``weights`` (nt × poses): row k's weights hold over the step from ``time_s[k]`` to the next row; or a
    :class:`StepPoses` of the rows (where each row's samples were).  The blends are those of :func:`history_step`
    before each step.
    """
    t = np.asarray(time_s, float)
    steps = weights if isinstance(weights, StepPoses) else StepPoses.held(np.asarray(weights, float))
    cuts, window = [], HistoryWindow()
    for k in range(t.size - 1):
        blend, window = history_step(window, steps.row(k), t[k + 1] - t[k], tol, tick_s)
        if blend is not None:
            cuts.append((k, blend))
    return cuts


def integrate_along(prom: ReducedModel, time_s: np.ndarray, inputs: np.ndarray, positions_mm: np.ndarray,
                    initial: str | np.ndarray = "steady", history: str = "moves", hold: str = "linear",
                    weights: np.ndarray | StepPoses | None = None, tol: float = MOVE_WEIGHT_TOL,
                    tick_s: float = HISTORY_TICK_S) -> tuple[np.ndarray, np.ndarray]:
    """A pose-aware model's outputs along a path, following the poses the machine visits (:func:`blend_history`).

    Parameters
    ----------
    prom : a pose-aware reduced model (:func:`reduce_at_poses`)
    time_s, inputs, initial, hold : as :meth:`~hybridcomp.rom.reduced.ReducedModel.integrate`
    positions_mm : axis positions per row (nt × axes, machine order) [mm]; row k's pose holds from ``time_s[k]``
        to the next row (the step into row k ran at row k − 1's pose)
    history : ``"moves"``: the blocks blended at the history's ticks where the machine moved (:func:`history_cuts`)
        with the time-weighted weights since the last tick; ``"steps"``: at every step with that step's weights
        (a comparison: it replaces each block's own heat paths by the blend every step); ``"none"``: every block
        as if the machine stood at its pose all along
    weights : the support poses' weights per row (nt × poses) instead of those of ``positions_mm``, or where each
        row's samples were (:class:`StepPoses`, e.g. of a trace's samples: the time-weighted weights over a step in
        which the machine moved, and the samples' range, which decides the blends)
    tol, tick_s : what counts as a move and the history's clock (:func:`history_cuts`)

    Returns
    -------
    outputs (nt × q) and the final state, as :meth:`~hybridcomp.rom.reduced.ReducedModel.integrate`
    """
    if history not in HISTORIES:
        raise ValueError(f"history must be one of {HISTORIES}, got {history!r}")
    t = np.asarray(time_s, float)
    if history == "none":
        return prom.integrate(t, inputs, initial, hold=hold)
    steps = StepPoses.held(grid_of(prom).weights_along(positions_mm)) if weights is None else (
        weights if isinstance(weights, StepPoses) else StepPoses.held(np.asarray(weights, float)))
    W = steps.weights
    if W.shape[0] != t.size:
        raise ValueError(f"{W.shape[0]} rows of positions or weights for {t.size} times")
    U = np.asarray(inputs, float)
    Y = np.empty((t.size, prom.C.shape[0]))
    if history == "steps":
        Y[:1], x = prom.integrate(t[:1], U[:1], initial, hold=hold)
        for k in range(1, t.size):
            x = prom.step(x, U[k] if hold == "step" else U[k - 1], U[k], t[k] - t[k - 1])
            x = blend_history(prom, x, W[k - 1])
            Y[k] = prom.outputs(x)
        return Y, x
    x, i0 = initial, 0
    for k, w in history_cuts(t, steps, tol, tick_s):
        Y[i0:k + 1], x = prom.integrate(t[i0:k + 1], U[i0:k + 1], x, hold=hold)
        x = blend_history(prom, x, w)
        Y[k], i0 = prom.outputs(x), k
    if i0 < t.size - 1 or t.size == 1:
        Y[i0:], x = prom.integrate(t[i0:], U[i0:], x, hold=hold)
    return Y, x
