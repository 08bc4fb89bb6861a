"""Volumetric compensation in the daemon: the drift where the tool is, as a support-point table every cycle.

The observer keeps the model pose's reduced model on the machine with the sensors and the probes; the CDs and
the complementary filter give the offsets at the model's pose (:mod:`hybridcomp.monitor.daemon`).  Beside
them the pose-aware structure model (``hybridcomp reduce --poses``, :mod:`hybridcomp.rom.poses`: a reduced
model per support pose and the feed drives' screws) runs on the inputs as the observer corrects them, and every
compensation cycle the daemon writes the table of the drift at the support points of a workspace grid
(:mod:`hybridcomp.rom.volumetric`)::

    table(p) = offsets at the model's pose + [pose-aware model at p − pose-aware model at the model's pose]

What the monitor knows at the model's pose (CDs fitted on the machine's history, the observer's corrections,
the probes) carries over to every pose unchanged; what the pose adds (lever arms, heat paths per pose, the
screws' elongation and the scales' expansion at the axis positions) comes from the pose-aware model, run on
the inputs as the observer corrects them (its air offsets and power scales).  Its first block is the model
pose's reduced model itself, so the bracket is zero at the model's pose: at that pose the table gives the
one-pose offsets plus the drives' error at the model's axis positions.

Probes: one at the model's pose goes to the observer less the drives' errors there, the gains' share as the
gains stand at the model step's end (the one-pose model holds none); one elsewhere teaches the drives' gains
(:class:`DriveGains`: each drive's whole error and its nuts' part, the model run on the nuts' heat alone) and
nothing else.

Each entry of the table moves at most ``max_step_um`` per cycle (the rate limit of the one-pose offsets,
per support point); the offsets at the commanded position are the table interpolated there, as the control
interpolates it every 2–4 ms.

Everything here is pure: :class:`PoseTrack` is the pose-aware model's state, each function returns a new one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PoseModel:
    """The fixed part: the pose-aware reduced model, its model-pose block, its table operator, its TCP outputs.

    ``nut_inputs``: which inputs are the drives' nuts' heat (a mask over the inputs), or None: the model runs a second
    time on those alone, whose drives' errors are the nuts' part of the drives' errors (:class:`DriveGains`).
    """

    rom: object
    block: object
    op: object
    tcp: tuple[int, int, int]
    nut_inputs: np.ndarray | None = None


@dataclass(frozen=True)
class PoseTrack:
    """The pose-aware model's state at the end of the last model step, its outputs then and one step ahead.

    ``history``: where the machine was since the pose history's last tick
    (:class:`hybridcomp.rom.poses.HistoryWindow`, :func:`advance`).
    """

    time_s: float
    x: np.ndarray
    y_now: np.ndarray
    y_next: np.ndarray
    history: object = None
    x_nut: np.ndarray | None = None
    y_nut_now: np.ndarray | None = None
    y_nut_next: np.ndarray | None = None


def pose_model(prom, points: int = 3, machine=None) -> PoseModel:
    """The pose-aware reduced model ``prom`` (:func:`hybridcomp.rom.poses.reduce_at_poses`) ready for the daemon.

    ``block`` is the model pose's reduced model inside it (the observer's), ``op`` the table over a grid of
    ``points`` support points per axis over the travel.  With ``machine`` (the model's machine file), the inputs of
    its drives' nuts that heat their screws are ``nut_inputs`` (:class:`PoseModel`).
    """
    from hybridcomp.rom.poses import model_pose_block
    from hybridcomp.rom.volumetric import default_grid, table_operator

    tcp = tuple(prom.output_layout().indices("drift"))
    return PoseModel(prom, model_pose_block(prom), table_operator(prom, default_grid(prom, points)), tcp,
                     None if machine is None else nut_inputs(prom, machine))


def nut_inputs(prom, machine) -> np.ndarray | None:
    """The mask of ``prom``'s inputs that are the heat of a drive's nut into its screw (None: no such drive)."""
    layout = machine.layout()  # the model's inputs are in its machine's layout (as the observer reads them)
    if len(layout.heat_inputs) + len(layout.zones) != prom.n_inputs:
        return None
    mask = np.zeros(prom.n_inputs, bool)
    for axis in prom.output_layout().feedback_axes:
        d = machine.drive(axis)
        if d is not None and d.nut_screw_W > 0:
            mask[list(layout.source_columns(d.nut))] = True
    return mask if mask.any() else None


def _nut(pm: PoseModel, u: np.ndarray) -> np.ndarray:
    return np.where(pm.nut_inputs, u, 0.0)


def _outputs(pm: PoseModel, x: np.ndarray) -> np.ndarray:
    return np.asarray(pm.rom.outputs(x), float)


def start(pm: PoseModel, u: np.ndarray, time_s: float, horizon_s: float) -> PoseTrack:
    """The pose-aware model at rest in the first inputs (the observer's prior), and one step ahead."""
    x = np.asarray(pm.rom.steady_state(u), float)
    x_nut = None if pm.nut_inputs is None else np.asarray(pm.rom.steady_state(_nut(pm, u)), float)
    return _track(pm, time_s, x, u, horizon_s, x_nut=x_nut)


def advance(pm: PoseModel, track: PoseTrack, u: np.ndarray, end_s: float, horizon_s: float,
            weights=None) -> PoseTrack:
    """One model step to ``end_s`` with the inputs ``u`` held over it (as the observer steps), and the forecast.

    ``weights``: where the machine was over this step, the support poses' interpolation weights of its readings
    (:func:`step_weights`, a :class:`~hybridcomp.rom.poses.StepPoses`; plain weights: it held that pose).  The pose
    history's clock
    (:func:`hybridcomp.rom.poses.history_step`) decides whether the support poses' blocks are first blended with
    where the machine was since its last tick
    (:func:`hybridcomp.rom.poses.blend_history`), as :func:`~hybridcomp.rom.poses.integrate_along` does.  A model
    without a pose transfer, or no weights, runs every block as if the machine stood at its pose.
    """
    from hybridcomp.rom.poses import blend_history, history_step

    dt = end_s - track.time_s
    x, window, x_nut = track.x, track.history, track.x_nut
    if pm.nut_inputs is not None and x_nut is None:  # a state saved without the nuts' part: it starts at rest
        x_nut = np.asarray(pm.rom.steady_state(_nut(pm, u)), float)
    if weights is not None and pm.rom.pose_transfer is not None:
        blend, window = history_step(window, weights, max(dt, 0.0))
        if blend is not None:
            x = blend_history(pm.rom, x, blend)
            x_nut = None if x_nut is None else blend_history(pm.rom, x_nut, blend)
    if dt > 0:
        x = np.asarray(pm.rom.step(x, u, u, dt), float)
        if x_nut is not None:
            x_nut = np.asarray(pm.rom.step(x_nut, _nut(pm, u), _nut(pm, u), dt), float)
    return _track(pm, end_s, x, u, horizon_s, window, x_nut)


def step_weights(pm: PoseModel, positions_mm: np.ndarray, dt_s: np.ndarray | None = None):
    """Where the machine was over a model step: its readings' support-pose weights (:class:`~hybridcomp.rom.poses.StepPoses`).

    The time-weighted mean, the readings' range and the first reading's.  ``positions_mm``: the readings' axis
    positions (m × axes, machine order) [mm]; ``dt_s``: the time each reading stands for (default: equal).
    """
    from hybridcomp.rom.poses import StepPoses, grid_of

    return StepPoses.of(grid_of(pm.rom).weights_along(positions_mm), dt_s)


def _track(pm: PoseModel, time_s: float, x: np.ndarray, u: np.ndarray, horizon_s: float,
           history=None, x_nut: np.ndarray | None = None) -> PoseTrack:
    from hybridcomp.rom.poses import HistoryWindow

    x_next = np.asarray(pm.rom.step(x, u, u, horizon_s), float)
    y_nut = y_nut_next = None
    if x_nut is not None and pm.nut_inputs is not None:
        y_nut = _outputs(pm, x_nut)
        y_nut_next = _outputs(pm, np.asarray(pm.rom.step(x_nut, _nut(pm, u), _nut(pm, u), horizon_s), float))
    else:
        x_nut = None
    return PoseTrack(float(time_s), x, _outputs(pm, x), _outputs(pm, x_next),
                     HistoryWindow() if history is None else history, x_nut, y_nut, y_nut_next)


def outputs_at(track: PoseTrack, t: float, horizon_s: float) -> np.ndarray:
    """The outputs at ``t``: linear between the last step's end and its forecast (as the one-pose drift)."""
    f = min(max((t - track.time_s) / horizon_s, 0.0), 1.0)
    return track.y_now + f * (track.y_next - track.y_now)


def table_now(pm: PoseModel, track: PoseTrack, t: float, horizon_s: float, offsets_um) -> object:
    """The support-point table at ``t`` (module docstring): the offsets at the model's pose carried to every pose.

    ``offsets_um``: the one-pose offsets (dx, dy, dz) written this cycle [µm].
    """
    from hybridcomp.rom.volumetric import shifted, table_of

    y = outputs_at(track, t, horizon_s)
    at_pose = y[list(pm.tcp)] * 1e6
    return shifted(table_of(pm.op, y, t), np.asarray(offsets_um, float) - at_pose)


def nut_table_now(pm: PoseModel, track: PoseTrack, t: float, horizon_s: float):
    """The table of the nuts' heat alone at ``t`` (its drives' errors: the nuts' part of the drives'), or None."""
    from hybridcomp.rom.volumetric import table_of

    if track.y_nut_now is None:
        return None
    f = min(max((t - track.time_s) / horizon_s, 0.0), 1.0)
    return table_of(pm.op, track.y_nut_now + f * (track.y_nut_next - track.y_nut_now), t)


def table_step(new, old, max_step_um: float):
    """The table rate-limited against the last one written (each entry by at most ``max_step_um``).

    Returns the table and whether the limit acted; the first table is not limited (nothing to continue).
    """
    from hybridcomp.rom.volumetric import limit_table

    if old is None:
        return new, False
    return limit_table(new, old, max_step_um)


def on_grid(table, grid):
    """``table`` carried onto ``grid``'s points (its value interpolated there, drives included).

    ``table`` itself when it is on ``grid`` already; None for None or for a grid of other axes.  The rate limit's
    start when the support grid changes (another CD grid made active): the offsets move from what the last table
    gave at each new point, by at most the rate limit per cycle.
    """
    from hybridcomp.rom.volumetric import VolumetricTable, interpolate

    if table is None or table.grid == grid:
        return table
    if tuple(table.grid.axes) != tuple(grid.axes):
        return None  # another machine's axes: nothing to continue
    S = interpolate(table, grid.points_mm()).reshape(grid.shape + (3,))
    return VolumetricTable(grid, table.time_s, S)


#: a probe within this of the model's pose on every axis is a probe at the model's pose [mm]
AT_POSE_MM = 1.0


def at_model_pose(table, position_mm) -> bool:
    """Whether ``position_mm`` is the model's pose of the table's grid (within :data:`AT_POSE_MM` on every axis)."""
    return all(abs(float(p) - r) <= AT_POSE_MM for p, r in zip(position_mm, table.grid.reference_mm()))


def _drive_at(table, f, position_mm) -> float:
    """Drive ``f``'s error [µm] at its axis' position in ``position_mm`` (grid order), as the table has it."""
    return float(np.interp(float(position_mm[table.grid.axes.index(f.axis)]), f.positions_mm, f.error_um))


def without_drives_um(table, position_mm, probe_um) -> list[float]:
    """A drift probed at ``position_mm`` less the drives' errors the table has there (sign and direction applied)."""
    out = [float(v) for v in probe_um]
    for f in table.feedback_um:
        out[f.direction] -= f.sign * _drive_at(table, f, position_mm)
    return out


def state_out(track: PoseTrack | None) -> dict | None:
    """JSON-ready (the daemon's persisted state)."""
    if track is None:
        return None
    out = {"time_s": track.time_s, "x": [float(v) for v in track.x]}
    if track.history is not None:
        out["history"] = track.history.as_dict()
    if track.x_nut is not None:
        out["x_nut"] = [float(v) for v in track.x_nut]
    return out


def state_in(pm: PoseModel, d: dict | None, u, horizon_s: float) -> PoseTrack | None:
    """The track of :func:`state_out`, its outputs recomputed with the last step's inputs ``u``."""
    if d is None or u is None:
        return None
    x = np.asarray(d["x"], float)
    if x.shape != (pm.rom.order,):
        raise ValueError(f"pose-aware state of {x.size} values for a model of order {pm.rom.order}")
    from hybridcomp.rom.poses import HistoryWindow

    h = d.get("history")
    x_nut = d.get("x_nut")
    if pm.nut_inputs is not None:  # a state saved without the nuts' part: it starts at rest in the last inputs
        x_nut = (np.asarray(x_nut, float) if x_nut is not None and len(x_nut) == pm.rom.order
                 else np.asarray(pm.rom.steady_state(_nut(pm, np.asarray(u, float))), float))
    return _track(pm, float(d["time_s"]), x, np.asarray(u, float), horizon_s,
                  None if h is None else HistoryWindow.from_dict(h), None if pm.nut_inputs is None else x_nut)


# ---------------------------------------------------------------------------------------------- the drives' gains
@dataclass(frozen=True)
class GainSettings:
    """Priors and rates of the drives' gains (:class:`DriveGains`).

    Attributes
    ----------
    gain_sigma : prior spread of each drive's relative error [-] (a machine file's drives known to 30 %; a fault,
        a seized bearing or a scale of another material, is 3–5 spreads off and is learnt once the drives are warm)
    gain_rate : its random walk per √h [-]
    offset_sigma_um, offset_rate_um : the uniform offset's prior spread [µm] and random walk per √h [µm]; None:
        by the mode (:meth:`offset_prior`). With ``whole_error`` 0.5 µm and 0.1 µm/√h: the one-pose observer owns
        a uniform offset (it takes the probe at the model's pose, which the gains leave alone), so the offset here
        holds only what a cycle's probes away from the pose share beyond the drives. Wide (5 µm, 1 µm/√h), it
        shares a drive's error whose mean over the probed positions is not zero, and takes it from the gain: a
        seized floating bearing's error grows from its fixed end, and the first warm cycle put about 2 µm of it in
        the offset and left the multiplier ``1 + g`` at 0.51 for about 0.05 (narrow: 0.01;
        ``benchmarks/compensation.py``: 1.94 µm along the path, 1.16 with the narrow offset; the unmodelled source
        2.20 against 1.55). Relative to the pose (``whole_error`` False) the
        offset also holds the drives' share at the model's pose: 5 µm and 1 µm/√h
    probe_sigma_um : noise of a probed drift [µm]
    model_sigma_um : what the probe less the table holds besides the drives' gains and the offset, at each position:
        the pose-aware structure model's own error away from the model's pose [µm] (up to 0.7 µm against FE
        carried along a path, ``benchmarks/pose_path.py``); without it a cycle on a cold machine, whose drives'
        errors are a few µm, takes that error for a gain and the table carries it to the warm machine's tens of µm
    whole_error : the gains scale each drive's whole error, its share at the model's pose included
        (:class:`DriveGains`); False: only its change from the model's pose
    nut_sigma : prior spread of the nuts' gains [-] (1: the nuts' part of the error twice the machine file's)
    bounded_axes : the drives read at the screw (rotary encoder), whose multipliers ``1 + g`` and ``1 + g + h``
        cannot turn negative (:func:`update_gains`); the daemon takes them from the machine file
    """

    gain_sigma: float = 0.3
    gain_rate: float = 0.05
    offset_sigma_um: float | None = None
    offset_rate_um: float | None = None
    probe_sigma_um: float = 0.5
    model_sigma_um: float = 0.7
    whole_error: bool = True
    nut_sigma: float = 1.0
    bounded_axes: tuple[str, ...] = ()

    def offset_prior(self, whole_error: bool) -> tuple[float, float]:
        """The uniform offset's prior spread [µm] and random walk per √h [µm] for gains of that mode."""
        sigma, rate = (0.5, 0.1) if whole_error else (5.0, 1.0)
        return (sigma if self.offset_sigma_um is None else self.offset_sigma_um,
                rate if self.offset_rate_um is None else self.offset_rate_um)


@dataclass(frozen=True)
class DriveGains:
    """Relative errors of each drive's positioning error, learnt from drift probed at several positions.

    The pose-aware model's drives (a screw's elongation, a scale's expansion) are known only as well as their
    heat inputs and coefficients: a seized floating bearing, or a scale of another material, scales the error
    along the axis; a nut that runs warmer than its machine file says changes its shape and timing too (its heat
    enters over the nut's travel, with the feed).  A probing cycle that touches several positions along the axes
    sees it: the probe less the table without gains is ``b + Σ_a sign_a (g_a e_a(p_a) + h_a n_a(p_a))`` in the
    drive's direction (``e_a`` the drive's error, ``n_a`` its nuts' part: the model run on the nuts' heat alone,
    :func:`nut_table_now`; ``b`` a uniform offset that the observer at the model's pose takes care of, here a
    nuisance), and a Kalman filter on ``(g, h, b)`` (random walks) estimates the gains.  The table's drive
    entries become ``e + g e + h n``.  ``whole_error`` False: every error less its value at the model's pose
    (``e − e(p0)``), so the table there is left to the one-pose observer.  Probes at the model's pose alone leave
    the gains alone either way: there a gain cannot be told from the observer's structure, which owns it.
    ``h`` is None without the nuts' part (a model without nuts' heat into screws, or a state saved before it).
    """

    axes: tuple[str, ...]
    g: np.ndarray
    b: np.ndarray
    P: np.ndarray
    time_s: float | None = None
    whole_error: bool = False
    h: np.ndarray | None = None

    def as_dict(self) -> dict:
        return {"axes": list(self.axes), "g": [float(v) for v in self.g], "b": [float(v) for v in self.b],
                "P": [[float(v) for v in row] for row in self.P], "time_s": self.time_s,
                "whole_error": self.whole_error, "h": None if self.h is None else [float(v) for v in self.h]}

    @staticmethod
    def from_dict(d: dict) -> DriveGains:
        h = d.get("h")
        return DriveGains(tuple(d["axes"]), np.asarray(d["g"], float), np.asarray(d["b"], float),
                          np.asarray(d["P"], float), d.get("time_s"), bool(d.get("whole_error", False)),
                          None if h is None else np.asarray(h, float))

    def _with(self, x: np.ndarray, P: np.ndarray, time_s: float | None) -> DriveGains:
        n = len(self.axes)
        h = None if self.h is None else x[n:2 * n]
        return DriveGains(self.axes, x[:n], x[-3:], P, time_s, self.whole_error, h)

    @property
    def x(self) -> np.ndarray:
        return np.r_[self.g, [] if self.h is None else self.h, self.b]


def initial_gains(axes, settings: GainSettings = GainSettings(), nuts: bool = False) -> DriveGains:
    """No error known yet: every gain 0 and the offset 0 at their prior spreads (``nuts``: with the nuts' gains)."""
    n = len(axes)
    sig = [settings.gain_sigma ** 2] * n + ([settings.nut_sigma ** 2] * n if nuts else [])
    P = np.diag(np.r_[sig, np.full(3, settings.offset_prior(settings.whole_error)[0] ** 2)])
    return DriveGains(tuple(axes), np.zeros(n), np.zeros(3), P, whole_error=settings.whole_error,
                      h=np.zeros(n) if nuts else None)


def _drive_rows(table, position_mm, axes, whole_error: bool) -> np.ndarray:
    """(3 × n): each drive's error at ``position_mm`` (sign applied) in its direction [µm], less at the model's pose.

    Its whole error (nothing less) with ``whole_error``.
    """
    H = np.zeros((3, len(axes)))
    ref = table.grid.reference_mm()
    for f in table.feedback_um:
        if f.axis in axes:
            e0 = 0.0 if whole_error else _drive_at(table, f, ref)
            H[f.direction, list(axes).index(f.axis)] = f.sign * (_drive_at(table, f, position_mm) - e0)
    return H


def _rows(gains: DriveGains, raw_table, nut_table, position_mm) -> np.ndarray:
    """The measurement rows (3 × states) of a probe at ``position_mm``: the gains, the nuts' gains, the offset."""
    H = [_drive_rows(raw_table, position_mm, gains.axes, gains.whole_error)]
    if gains.h is not None:
        H.append(np.zeros((3, len(gains.axes))) if nut_table is None
                 else _drive_rows(nut_table, position_mm, gains.axes, gains.whole_error))
    return np.hstack(H + [np.eye(3)])


def update_gains(gains: DriveGains, raw_table, position_mm, probe_um, time_s: float,
                 settings: GainSettings = GainSettings(), nut_table=None) -> DriveGains:
    """The gains after a probe at ``position_mm``.

    ``raw_table``: the table at that time without gains; ``nut_table``: the nuts' part then (:func:`nut_table_now`).
    """
    from hybridcomp.rom.volumetric import interpolate_one

    m = len(gains.x) - 3
    P = gains.P
    if gains.time_s is not None and time_s > gains.time_s:
        h = (time_s - gains.time_s) / 3600.0
        rate = settings.offset_prior(gains.whole_error)[1]
        P = P + np.diag(np.r_[np.full(m, settings.gain_rate ** 2 * h), np.full(3, rate ** 2 * h)])
    y = np.asarray(probe_um, float) - np.asarray(interpolate_one(raw_table, position_mm), float)
    ok = np.isfinite(y)
    if not ok.any() or at_model_pose(raw_table, position_mm):
        # at the model's pose a gain's share and the observer's structure cannot be told apart: the observer owns it
        # (it gets the probe less the drives as corrected, :func:`gain_share_at_pose`), the gains learn elsewhere
        return gains._with(gains.x, P, time_s)
    H, y = _rows(gains, raw_table, nut_table, position_mm)[ok], y[ok]
    x = gains.x
    r2 = settings.probe_sigma_um ** 2 + settings.model_sigma_um ** 2
    S = H @ P @ H.T + r2 * np.eye(H.shape[0])
    K = np.linalg.solve(S, H @ P).T
    x = x + K @ (y - H @ x)
    IKH = np.eye(P.shape[0]) - K @ H
    P = IKH @ P @ IKH.T + r2 * K @ K.T  # Joseph form: stays symmetric and positive
    P = 0.5 * (P + P.T)
    return gains._with(_within_bounds(x, P, gains, settings.bounded_axes), P, time_s)


def _within_bounds(x: np.ndarray, P: np.ndarray, gains: DriveGains, bounded_axes) -> np.ndarray:
    """The estimate projected (in the metric of ``P``) onto the physical bounds of the screw drives' multipliers.

    A drive whose position is read at the screw (rotary encoder): ``1 + g`` scales its error (heat from motor,
    bearings and nuts: none of it is negative; a seized floating bearing blocks the screw's expansion, it does not
    reverse it) and, with the nuts' gain, ``1 + g + h`` its nuts' part; neither can turn negative.  A linear scale's
    error is the scale's expansion less the carrier's, whose difference may change sign with the material: it is
    not bounded.  Active-set projection: the smallest ``Δxᵀ P⁻¹ Δx`` that puts every violated bound on its edge.
    """
    n, E = len(gains.axes), np.eye(len(x))
    rows = []
    for a, axis in enumerate(gains.axes):
        if axis in bounded_axes:
            rows.append(E[a])  # 1 + g >= 0
            if gains.h is not None:
                rows.append(E[a] + E[n + a])  # 1 + g + h >= 0
    active: list[int] = []
    for _ in rows:
        viol = [i for i, row in enumerate(rows) if i not in active and 1.0 + row @ x < -1e-12]
        if not viol:
            break
        active.append(viol[0])
        A = np.array([rows[i] for i in active])
        # onto the edges of every active bound (projections onto nested affine sets compose)
        x = x - P @ A.T @ np.linalg.solve(A @ P @ A.T, 1.0 + A @ x)
    return x


def with_gains(table, gains: DriveGains | None, nut_table=None):
    """The table with each drive's entries ``e + g e + h n`` (:class:`DriveGains`).

    Relative to the model's pose unless ``whole_error``; ``nut_table``: the nuts' part (:func:`nut_table_now`).
    """
    if gains is None or not len(gains.axes):
        return table
    import dataclasses

    g = dict(zip(gains.axes, gains.g))
    h = dict(zip(gains.axes, gains.h)) if gains.h is not None and nut_table is not None else {}
    nuts = {f.axis: f for f in nut_table.feedback_um} if h else {}
    ref = table.grid.reference_mm()

    def rel(t, f) -> np.ndarray:
        return f.error_um - (0.0 if gains.whole_error else _drive_at(t, f, ref))

    fb = []
    for f in table.feedback_um:
        e = f.error_um + g.get(f.axis, 0.0) * rel(table, f)
        if f.axis in nuts:
            nf = nuts[f.axis]
            e = e + h[f.axis] * np.interp(f.positions_mm, nf.positions_mm, rel(nut_table, nf))
        fb.append(f._replace(error_um=e))
    return dataclasses.replace(table, feedback_um=tuple(fb))


def gain_share_at_pose(table, gains: DriveGains | None, nut_table=None) -> np.ndarray:
    """What the gains add to the drives' errors at the model's pose [µm] (dx, dy, dz); zero relative to the pose."""
    ref = table.grid.reference_mm()
    raw = np.asarray(without_drives_um(table, ref, np.zeros(3)), float)
    return raw - np.asarray(without_drives_um(with_gains(table, gains, nut_table), ref, np.zeros(3)), float)
