"""The feed drives' diagnosis: which drive effect the nominal model lacks, named from drift probed at several poses.

A drive's error (:class:`hybridcomp.fem.drives.DriveError`) depends on the axis position, so the drift at the
model's pose hardly shows what a drive gets wrong; probing cycles that touch a star of poses over the workspace do.
Given probes (time, axis positions, measured dx, dy, dz) and the nominal pose-aware model (``hybridcomp reduce
--poses``) on the loads of the same record, every candidate drive effect gets a **sensitivity** from the nominal
physics: the drift change in its drive's direction at every probe per unit change of its parameter.

| kind | parameter | sensitivity (per unit parameter, sign and direction of the axis applied) |
|---|---|---|
| ``nut_heat`` | factor on the nut's heat into the screw [-] | the screw's error from the nut's heat alone |
| ``screw_expansion`` | the screw's α [µm/(m K)] | ``∫_{s_fixed}^{s_nut(p)} ΔT_screw ds`` |
| ``scale_expansion`` | the scale's α [µm/(m K)] | ``∫_{s_fixed}^{s_head(p)} ΔT_carrier ds`` |
| ``bearing_held`` | share of the screw's elongation its bearings hold [-] | ``−(s_nut − s_fixed)/L · E(s_other)`` |
| ``workspace_offset`` | the workspace air's offset [K] | the drift's change for 1 K warmer workspace air (not a drive's) |

``bearing_held`` is a fixed-floating screw whose floating bearing has seized: held at both ends like a
pre-stretched screw (``E`` the screw's elongation beyond the carrier's, :mod:`hybridcomp.fem.drives`, ``L`` the
screw's length between its bearings).  ``workspace_offset`` is the competitor that is not a drive effect: warmer
workspace air warms the screws too and changes their error along the axes; when it explains a direction best, no
drive effect is named there.

The screw's temperatures come from its 1D model (:func:`hybridcomp.fem.drives.build_screw`) on the loads, the nut's
share from the nut's inputs alone (the screw is linear in them); the carrier's integral from the pose-aware model's
drive outputs (a scale's output is ``(α_scale − α_carrier)`` times it; a screw's carrier share is ``−α_carrier``
times it, extrapolated linearly from the two outputs nearest to the floating bearing over the stretch the nut never
reaches).  Nothing is taken from the planted truth: the sensitivities are the nominal model's.

Every probe cycle has its own uniform offset (3 values, the nuisance the observer at the model's pose takes care of):
residuals and sensitivities are taken less their cycle's mean per direction, so a cycle tells only what differs
between its poses.  Each candidate is fitted by least squares and judged by leave-one-cycle-out: its fit on the
other cycles predicts each held-out cycle; the **validation gain** is ``1 − RMS(held-out residual after) /
RMS(residual before)`` in the drive's direction.  Per direction the best candidate is named when its gain reaches
``min_gain``, its parameter lies within the physical range (within 3 σ) and the direction's residual is above the
probes' noise; then the next candidate on what it leaves (up to ``max_per_direction``).  Candidates within 10 % of the
named one's held-out RMS are reported as alternatives these probes do not tell apart.  The uncertainty is the
jackknife over cycles (the cycles' residuals are not white noise: the least-squares σ would flatter).

```python
from hybridcomp.diagnose.drives import diagnose_drives, drive_candidates, read_probes
probes = read_probes("probes.csv", machine)          # or a monitor trace with probe_dx_um ... columns
cands, predicted = drive_candidates(machine, pose_rom, loads, probes)   # pose_rom: hybridcomp reduce --poses
d = diagnose_drives(probes, cands, predicted)
print(d.summary())
```
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hybridcomp.diagnose.data import DatasetError
from hybridcomp.models.layout import DRIFT_COLUMNS as DIRS

#: probes further apart in time than this belong to different probing cycles [s]
CYCLE_GAP_S = 600.0
#: a candidate whose held-out RMS is within this factor of the named one's is an alternative not told apart
ALTERNATIVE_RATIO = 1.1
KINDS = ("nut_heat", "screw_expansion", "scale_expansion", "bearing_held", "workspace_offset")


@dataclass(frozen=True)
class Probes:
    """Drift probed at several poses (``n`` probes).

    Attributes
    ----------
    time_s : probe times [s] (n)
    positions_mm : axis positions of each probe, machine axis order (n × axes) [mm]
    axes : axis names of the columns of ``positions_mm``
    measured_um : probed dx, dy, dz [µm] (n × 3), NaN where a direction was not measured
    cycle : probing cycle of each probe (n), integers
    predicted_um : the nominal model's drift at the probes [µm] (n × 3), or None (then computed by
        :func:`drive_candidates`)
    """

    time_s: np.ndarray
    positions_mm: np.ndarray
    axes: tuple[str, ...]
    measured_um: np.ndarray
    cycle: np.ndarray
    predicted_um: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.time_s.size

    def subset(self, rows: np.ndarray) -> Probes:
        """The probes of the rows ``rows`` (a mask or indices)."""
        return Probes(self.time_s[rows], self.positions_mm[rows], self.axes, self.measured_um[rows], self.cycle[rows],
                      None if self.predicted_um is None else self.predicted_um[rows])


def probe_cycles(time_s: np.ndarray, gap_s: float = CYCLE_GAP_S) -> np.ndarray:
    """Cycle number of each probe: a new cycle wherever two probes lie more than ``gap_s`` apart (times ascending)."""
    t = np.asarray(time_s, float)
    return np.concatenate([[0], np.cumsum(np.diff(t) > gap_s)]).astype(int)


def make_probes(time_s, positions_mm, axes, measured_um, predicted_um=None, cycle=None,
                gap_s: float = CYCLE_GAP_S) -> Probes:
    """:class:`Probes` from arrays, sorted by time, cycles from the time gaps unless given."""
    t = np.asarray(time_s, float)
    order = np.argsort(t, kind="stable")
    P = np.atleast_2d(np.asarray(positions_mm, float))[order]
    M = np.atleast_2d(np.asarray(measured_um, float))[order]
    if P.shape != (t.size, len(axes)) or M.shape != (t.size, 3):
        raise ValueError(f"probes: {t.size} times, positions {P.shape} (want {t.size} × {len(axes)}), measured "
                         f"{M.shape} (want {t.size} × 3)")
    pred = None if predicted_um is None else np.atleast_2d(np.asarray(predicted_um, float))[order]
    cyc = probe_cycles(t[order], gap_s) if cycle is None else np.asarray(cycle, int)[order]
    return Probes(t[order], P, tuple(axes), M, cyc, pred)


def read_probes(path, machine, gap_s: float = CYCLE_GAP_S) -> Probes:
    """Read a probes CSV: ``time_s``, the axis positions (``x_mm`` …), ``dx_um``, ``dy_um``, ``dz_um``.

    A monitor trace (``probe_dx_um`` … columns, :data:`hybridcomp.models.layout.PROBE_COLUMNS`) is read too: its rows
    with a probe.

    Optional: ``cycle`` (the probing cycle of each row; default from the time gaps, :func:`probe_cycles`) and the
    nominal model's drift ``pred_dx_um`` … (default: computed from the pose-aware model).  Empty cells of a drift
    column are directions not measured; rows without any drift are skipped.

    Raises
    ------
    DatasetError
        a missing column or a value that is not a number (names the file, row and column)
    """
    from hybridcomp.histogram.trace import position_column
    from hybridcomp.models.layout import PROBE_COLUMNS

    path = Path(path)
    axes = tuple(a.name for a in machine.axes)
    pos_cols = [position_column(a) for a in axes]
    pred_cols = [f"pred_{d}" for d in DIRS]
    drift_cols = list(DIRS)
    try:
        fh = path.open(newline="")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the probes ({exc.strerror or exc})") from exc
    with fh:
        reader = csv.DictReader(fh)
        header = reader.fieldnames or []
        if all(c in header for c in PROBE_COLUMNS):  # a monitor trace: its probed drift
            drift_cols = list(PROBE_COLUMNS)
        missing = [c for c in ["time_s", *pos_cols, *drift_cols] if c not in header]
        if missing:
            raise DatasetError(f"{path}: the probes lack the column {missing[0]!r} (need time_s, "
                               f"{', '.join(pos_cols)}, {', '.join(DIRS)} or {', '.join(PROBE_COLUMNS)}; have "
                               f"{', '.join(header) or 'none'})")
        has_pred = all(c in header for c in pred_cols)
        rows = []
        for i, r in enumerate(reader, start=2):
            def num(c, empty_nan=False, r=r, i=i):
                v = (r.get(c) or "").strip()
                if v == "" and empty_nan:
                    return math.nan
                try:
                    x = float(v)
                except ValueError:
                    raise DatasetError(f"{path}, line {i}: column {c!r} = {v!r} is not a number") from None
                if not math.isfinite(x) and not empty_nan:
                    raise DatasetError(f"{path}, line {i}: column {c!r} = {v!r} is not finite")
                return x
            d = [num(c, True) for c in drift_cols]
            if all(math.isnan(v) for v in d):
                continue
            rows.append((num("time_s"), [num(c) for c in pos_cols], d,
                         [num(c, True) for c in pred_cols] if has_pred else None,
                         int(num("cycle")) if "cycle" in header else None))
    if not rows:
        raise DatasetError(f"{path}: no probe with a measured drift")
    cycle = [r[4] for r in rows] if "cycle" in header else None
    return make_probes([r[0] for r in rows], [r[1] for r in rows], axes, [r[2] for r in rows],
                       [r[3] for r in rows] if has_pred else None, cycle, gap_s)


@dataclass(frozen=True)
class DriveCandidate:
    """One candidate drive effect and its sensitivity at the probes.

    Attributes
    ----------
    kind : see ``KINDS``
    axis : the drive's axis
    label : what it means, in words
    param_name : the parameter with its unit
    nominal : the parameter's value in the nominal model
    lower, upper : its physical range
    direction : the drift direction the drive acts in (0, 1, 2)
    sensitivity_um : drift change in ``direction`` at each probe per unit change of the parameter [µm/unit] (n)
    drive : a drive effect; False for a competitor that is not one (the workspace air's offset, which warms the
        screws too): when it explains a direction best, no drive effect is named there
    """

    kind: str
    axis: str
    label: str
    param_name: str
    nominal: float
    lower: float
    upper: float
    direction: int
    sensitivity_um: np.ndarray = field(repr=False)
    drive: bool = True

    @property
    def key(self) -> tuple[str, str]:
        return (self.kind, self.axis)


def _at_times(t_grid: np.ndarray, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows of ``X`` (at ``t_grid``) linearly interpolated at the times ``t``."""
    k = np.clip(np.searchsorted(t_grid, t, side="right") - 1, 0, t_grid.size - 2)
    w = ((t - t_grid[k]) / (t_grid[k + 1] - t_grid[k]))[:, None]
    return (1 - w) * X[k] + w * X[k + 1]


def _first_block(prom, rows: list[int]):
    """The pose-aware model's first block (the model pose's reduced model) with the output rows ``rows`` on it.

    A screw's carrier share reads the first block only (:func:`hybridcomp.rom.poses.reduce_at_poses`), which is
    decoupled from the others: integrating it alone gives that share exactly.
    """
    from hybridcomp.fem.operators import ThermalOperators
    from hybridcomp.rom.reduced import ReducedModel

    r = int(prom.meta["poses"]["orders"][0])
    ops = ThermalOperators(M=prom.M[:r, :r], K=prom.K[:r, :r], H=prom.H[:, :r, :r], h_W_m2K=prom.h_W_m2K,
                           B=prom.B[:r], Hb=prom.Hb[:r], C=prom.C[rows, :r], input_names=prom.input_names,
                           output_names=tuple(prom.output_names[i] for i in rows))
    return ReducedModel(ops)


def dataset_inputs(machine, dataset) -> tuple[np.ndarray, np.ndarray]:
    """(times [s], model inputs (nt × inputs): powers [W], air rises [K]) of a diagnosis dataset.

    The rules of the diagnosis on the machine's model (:func:`hybridcomp.diagnose.problem.build_problem`): heat inputs
    from ``<input>_W`` (missing: zero), zone air from ``<zone>_degC`` or the measured air by the zone's kind.
    """
    layout = machine.layout()
    present = [n for n in layout.heat_columns if n in dataset]
    if layout.heat_columns and not present:
        raise DatasetError(f"{dataset.source}: no heat-input column of machine {machine.name!r} "
                           f"({', '.join(layout.heat_columns[:4])}, ...): the drives' diagnosis needs the record's loads")
    air = layout.air_sources(dataset.names)
    used = [*present, *dict.fromkeys(air.values())]
    return dataset.time_s, layout.inputs(used, np.column_stack([dataset[c] for c in used]), dataset.source, air)


def drive_candidates(machine, prom, loads, probes: Probes, kinds=None) -> tuple[list[DriveCandidate], np.ndarray]:
    """Every candidate drive effect of the machine with its sensitivity at the probes, and the nominal prediction.

    Parameters
    ----------
    machine : the nominal machine (its ``[[drives]]``)
    prom : its pose-aware reduced model (:func:`hybridcomp.rom.poses.reduce_at_poses`, with the drives)
    loads : the record's loads covering the probes' times: a :class:`hybridcomp.models.layout.Loads` (heat inputs
        [W], air [°C]) or (times [s], model inputs (nt × inputs): powers [W], air rises [K], :func:`dataset_inputs`)
    probes : the probes (:class:`Probes`)
    kinds : the kinds to consider (default all, ``KINDS``)

    Returns
    -------
    (candidates, predicted): the candidates (:class:`DriveCandidate`) and the nominal model's drift at the probes
    [µm] (n × 3): the probes' own prediction when they carry one, else the pose-aware model's (drives included).
    """
    from hybridcomp.fem.drives import build_screw, integral_weights
    from hybridcomp.rom.poses import drift_along, grid_of

    kinds = KINDS if kinds is None else tuple(kinds)
    bad = [k for k in kinds if k not in KINDS]
    if bad:
        raise ValueError(f"unknown drive effect {bad[0]!r} (kinds: {', '.join(KINDS)})")
    grid = grid_of(prom)
    if tuple(grid.axes) != tuple(probes.axes):
        raise ValueError(f"the probes' axes {probes.axes} are not the pose-aware model's {tuple(grid.axes)}")
    layout_in = prom.layout()
    if isinstance(loads, tuple):
        t, U = (np.asarray(v, float) for v in loads)
    else:
        t, U = np.asarray(loads.time_s, float), layout_in.inputs(loads)
    tp = probes.time_s
    if tp.size == 0:
        raise ValueError("no probe to diagnose the drives on")
    if tp.min() < t[0] - 1e-6 or tp.max() > t[-1] + 1e-6:
        raise ValueError(f"the probes span {tp.min():g} … {tp.max():g} s, the loads {t[0]:g} … {t[-1]:g} s")
    tp = np.clip(tp, t[0], t[-1])
    Yp = _at_times(t, prom.integrate(t, U)[0], tp)
    predicted = probes.predicted_um if probes.predicted_um is not None else drift_along(prom, Yp, probes.positions_mm)
    layout = prom.output_layout()
    out = []
    for fb in layout.feedback:
        drive = next(d for d in machine.drives if d.axis == fb.axis)
        p = probes.positions_mm[:, grid.axes.index(fb.axis)]
        pos = np.asarray(fb.positions_mm, float)
        rows = list(fb.indices)
        if fb.feedback == "linear_scale":
            if "scale_expansion" not in kinds:
                continue
            a_c = machine.materials[machine.body(drive.scale_body).material].expansion_1_K
            da = drive.scale_expansion_1_K - a_c
            if abs(da) < 1e-12:  # the outputs are zero: no integral to read (the caller needs the FE model)
                continue
            e = np.array([np.interp(p[i], pos, Yp[i, rows] * 1e6) for i in range(p.size)])
            out.append(DriveCandidate("scale_expansion", fb.axis, f"wrong expansion coefficient of the {fb.axis} scale",
                                      "alpha [um/(m K)]", drive.scale_expansion_1_K * 1e6, 0.0, 30.0, fb.direction,
                                      fb.sign * e / da * 1e-6))
            continue
        screw = build_screw(machine, drive)
        x_all = _at_times(t, screw.temperature_rise(t, U), tp)
        rows_p = screw.elongation_rows(p)  # (n × screw nodes) [µm/K]
        if "nut_heat" in kinds and drive.nut_screw_W > 0:
            U_nut = np.zeros_like(U)
            cols = list(screw.layout.source_columns(drive.nut))
            U_nut[:, cols] = U[:, cols]
            x_nut = _at_times(t, screw.temperature_rise(t, U_nut), tp)
            out.append(DriveCandidate("nut_heat", fb.axis, f"the {fb.axis} nut's heat into its screw mis-scaled",
                                      "factor [-]", 1.0, 0.0, 10.0, fb.direction,
                                      fb.sign * np.einsum("ij,ij->i", rows_p, x_nut)))
        if "screw_expansion" in kinds:
            out.append(DriveCandidate("screw_expansion", fb.axis, f"wrong expansion coefficient of the {fb.axis} screw",
                                      "alpha [um/(m K)]", screw.alpha_1_K * 1e6, 0.0, 30.0, fb.direction,
                                      fb.sign * np.einsum("ij,ij->i", rows_p, x_all) / screw.alpha_1_K * 1e-6))
        if "bearing_held" in kinds and drive.mounting == "fixed-floating":
            # the carrier's share at the outputs: -alpha_c ∫_{fixed}^{nut(p)} ΔT_carrier [µm], on the first block
            carrier = _at_times(t, _first_block(prom, rows).integrate(t, U)[0], tp) * 1e6
            p_other = screw.s_other_mm - screw.nut_at_mm
            j = [0, 1] if abs(p_other - pos[0]) < abs(p_other - pos[-1]) else [-2, -1]
            slope = (carrier[:, j[1]] - carrier[:, j[0]]) / (pos[j[1]] - pos[j[0]])
            carrier_other = carrier[:, j[1]] + slope * (p_other - pos[j[1]])
            screw_other = screw.alpha_1_K * 1e3 * x_all @ integral_weights(screw.s_mm, screw.s_fixed_mm,
                                                                            screw.s_other_mm)
            E_other = screw_other + carrier_other
            share = (screw.nut_mm(p) - screw.s_fixed_mm) / (screw.s_other_mm - screw.s_fixed_mm)
            out.append(DriveCandidate("bearing_held", fb.axis, f"the {fb.axis} screw's floating bearing seized "
                                      "(the screw held at both ends)", "held share [-]", 0.0, 0.0, 1.0, fb.direction,
                                      -fb.sign * share * E_other))
    if "workspace_offset" in kinds:
        cols = [len(layout_in.heat_inputs) + layout_in.zones.index(z.name) for z in machine.zones
                if z.air == "workspace"]
        if cols:
            U_air = U.copy()
            U_air[:, cols] += 1.0
            dY = _at_times(t, prom.integrate(t, U_air)[0], tp) - Yp
            dD = drift_along(prom, dY, probes.positions_mm)  # linear in the outputs
            for d in range(3):
                out.append(DriveCandidate("workspace_offset", "", f"workspace air offset ({DIRS[d]}; not a drive "
                                          "effect: it warms the screws, the carriers and the structure)", "dT [K]", 0.0,
                                          -15.0, 15.0, d, dD[:, d], drive=False))
    return out, np.asarray(predicted, float)


# ------------------------------------------------------------------------------------------------ the fit
@dataclass(frozen=True)
class DriveFit:
    """A candidate fitted on the probes.

    Attributes
    ----------
    candidate : the candidate
    value : the fitted parameter (nominal + change)
    sigma : its uncertainty (jackknife over the probing cycles; least squares with fewer than 3 cycles)
    validation_gain : ``1 − held-out RMS after / RMS before`` in its direction (before: with the effects named
        earlier in that direction)
    rms_before_um, rms_after_um : residual RMS in its direction, less the cycles' offsets, before and held out after
    alternatives : labels of candidates these probes do not tell apart from it
    """

    candidate: DriveCandidate
    value: float
    sigma: float
    validation_gain: float
    rms_before_um: float
    rms_after_um: float
    alternatives: tuple[str, ...] = ()

    def describe(self) -> str:
        c = self.candidate
        name, _, unit = c.param_name.partition(" [")
        unit = unit.rstrip("]")
        unit = "" if unit in ("", "-") else f" {unit}"
        return f"{c.label} ({name} = {self.value:.3g} ± {self.sigma:.2g}{unit}, nominal {c.nominal:.3g}{unit})"


@dataclass(frozen=True)
class DriveDiagnosis:
    """What :func:`diagnose_drives` found.

    Attributes
    ----------
    named : the drive effects named, per direction in the order chosen
    fits : every candidate's first fit (on the residual of the nominal model)
    rms_um : per direction (dx_um, …) the residual RMS less the cycles' offsets: before, and after the named effects
        (in sample)
    noise_um : the probes' noise taken as the floor
    n_probes, n_cycles : what the probes held
    message : one sentence
    others : per direction a competitor that is not a drive effect, where it explained the probes best (then no
        drive effect is named in that direction)
    """

    named: tuple[DriveFit, ...]
    fits: tuple[DriveFit, ...]
    rms_um: dict
    noise_um: float
    n_probes: int
    n_cycles: int
    message: str
    others: tuple[DriveFit, ...] = ()

    def summary(self) -> str:
        lines = [self.message]
        lines += [f"  {f.describe()}; validation gain {100 * f.validation_gain:.0f} %" for f in self.named]
        return "\n".join(lines)

    def as_dict(self) -> dict:
        def fit(f: DriveFit) -> dict:
            c = f.candidate
            return {"kind": c.kind, "axis": c.axis, "label": c.label, "parameter": c.param_name, "nominal": c.nominal,
                    "value": f.value, "sigma": f.sigma, "validation_gain": f.validation_gain,
                    "rms_before_um": f.rms_before_um, "rms_after_um": f.rms_after_um,
                    "alternatives": list(f.alternatives)}

        return {"message": self.message, "named": [fit(f) for f in self.named], "not_drives": [fit(f) for f in self.others],
                "fits": [fit(f) for f in self.fits],
                "rms_um": self.rms_um, "noise_um": self.noise_um, "probes": self.n_probes, "cycles": self.n_cycles}


def _less_cycle_means(v: np.ndarray, cycle: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``v`` less its mean over each cycle's rows where ``ok``; 0 elsewhere and in cycles of one row."""
    out = np.zeros_like(v, dtype=float)
    for c in np.unique(cycle):
        m = (cycle == c) & ok
        if m.sum() >= 2:
            out[m] = v[m] - v[m].mean()
    return out


def _solve(S: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.linalg.lstsq(S, r, rcond=None)[0]


def _held_out(S: np.ndarray, r: np.ndarray, cycle: np.ndarray) -> tuple[float, np.ndarray]:
    """Leave-one-cycle-out: the held-out sum of squares and the fit without each cycle (cycles × params)."""
    sse, thetas = 0.0, []
    for c in np.unique(cycle):
        out = cycle == c
        th = _solve(S[~out], r[~out])
        thetas.append(th)
        sse += float(np.sum((r[out] - S[out] @ th) ** 2))
    return sse, np.array(thetas)


def _uncertainty(S: np.ndarray, r: np.ndarray, theta: np.ndarray, thetas: np.ndarray) -> np.ndarray:
    """Jackknife σ over the cycles (least squares with fewer than 3 cycles)."""
    k = thetas.shape[0]
    if k >= 3:
        return np.sqrt((k - 1) / k * np.sum((thetas - thetas.mean(axis=0)) ** 2, axis=0))
    dof = max(S.shape[0] - S.shape[1], 1)
    s2 = float(np.sum((r - S @ theta) ** 2)) / dof
    return np.sqrt(np.diag(s2 * np.linalg.pinv(S.T @ S)))


def diagnose_drives(probes: Probes, candidates: list[DriveCandidate], predicted_um: np.ndarray | None = None,
                    min_gain: float = 0.3, noise_um: float = 0.3, max_per_direction: int = 1) -> DriveDiagnosis:
    """Name the drive effects the probes show (module docstring).

    Parameters
    ----------
    probes : the probes (:class:`Probes`)
    candidates : from :func:`drive_candidates` (their sensitivities at these probes)
    predicted_um : the nominal model's drift at the probes (n × 3) (default: the probes' own)
    min_gain : least validation gain (held out, leave one cycle out) of a named effect [-]
    noise_um : the probes' noise [µm]: a direction whose residual (less the cycles' offsets) is below 1.5 × this
        has nothing to explain
    max_per_direction : most effects named per drift direction
    """
    pred = probes.predicted_um if predicted_um is None else np.asarray(predicted_um, float)
    if pred is None:
        raise ValueError("diagnose_drives needs the nominal model's drift at the probes (drive_candidates gives it)")
    for c in candidates:
        if np.shape(c.sensitivity_um) != (probes.n,):
            raise ValueError(f"candidate {c.label!r}: sensitivity of shape {np.shape(c.sensitivity_um)} for "
                             f"{probes.n} probes")
    resid = probes.measured_um - pred
    named, fits, rms, others, unexplained = [], [], {}, [], []
    n_cycles = int(np.unique(probes.cycle).size)
    for d, dname in enumerate(DIRS):
        ok = np.isfinite(resid[:, d])
        r_all = _less_cycle_means(np.where(ok, resid[:, d], 0.0), probes.cycle, ok)
        multi = [c for c in np.unique(probes.cycle) if ((probes.cycle == c) & ok).sum() >= 2]
        use = ok & np.isin(probes.cycle, multi)  # a cycle of one probe tells nothing beyond its offset
        r, cyc = r_all[use], probes.cycle[use]
        rms_before = float(np.sqrt(np.mean(r ** 2))) if r.size else 0.0
        rms[dname] = {"before": rms_before, "after": rms_before}
        cands = [c for c in candidates if c.direction == d]
        if not cands or r.size == 0 or np.unique(cyc).size < 2:
            continue
        S_of = {c.key: _less_cycle_means(c.sensitivity_um, probes.cycle, ok)[use] for c in cands}
        chosen: list[DriveCandidate] = []
        sse_now = float(np.sum(r ** 2))
        first = True
        while len(chosen) < max_per_direction:
            trial = []
            for c in cands:
                if c in chosen or not np.any(S_of[c.key]):
                    continue
                S = np.column_stack([S_of[k.key] for k in chosen] + [S_of[c.key]])
                sse, thetas = _held_out(S, r, cyc)
                theta = _solve(S, r)
                sig = _uncertainty(S, r, theta, thetas)
                gain = 1.0 - math.sqrt(sse / sse_now) if sse_now > 0 else 0.0
                f = DriveFit(c, c.nominal + float(theta[-1]), float(sig[-1]), gain, math.sqrt(sse_now / r.size),
                             math.sqrt(sse / r.size))
                trial.append((sse, f, theta))
                if first:
                    fits.append(f)
            first = False
            if not trial or math.sqrt(sse_now / r.size) < 1.5 * noise_um:
                break
            trial.sort(key=lambda x: x[0])
            sse, best, theta = trial[0]
            c = best.candidate
            inside = c.lower - 3 * best.sigma <= best.value <= c.upper + 3 * best.sigma
            if best.validation_gain < min_gain or not inside:
                if not inside and best.validation_gain >= min_gain:  # the best shape, at an impossible value
                    unexplained.append(f"{dname}: its best fit is out of the physical range, {best.describe()}")
                break
            alts = tuple(f.candidate.label for s, f, _ in trial[1:] if s <= ALTERNATIVE_RATIO ** 2 * sse
                         and f.validation_gain >= min_gain
                         and f.candidate.lower - 3 * f.sigma <= f.value <= f.candidate.upper + 3 * f.sigma)
            if not c.drive:  # the drift between poses is not a drive's: name none here
                others.append(replace(best, alternatives=alts))
                break
            named.append(replace(best, alternatives=alts))
            chosen.append(c)
            sse_now = sse
            S = np.column_stack([S_of[k.key] for k in chosen])
            rms[dname]["after"] = float(np.sqrt(np.mean((r - S @ _solve(S, r)) ** 2)))
    if named:
        message = "drive effects named: " + "; ".join(f.describe() for f in named)
    elif not others and not unexplained:
        message = "no drive effect named: the probes' drift between poses is within what the nominal drives explain"
    else:
        message = "no drive effect named"
    if unexplained:
        message += "; not explained by the drive candidates: " + "; ".join(unexplained)
    if others:
        message += ("; the drift between poses in " + ", ".join(DIRS[f.candidate.direction] for f in others)
                    + " fits an effect that is not a drive's better (" + "; ".join(f.describe() for f in others) + ")")
    return DriveDiagnosis(tuple(named), tuple(fits), rms, noise_um, probes.n, n_cycles, message, tuple(others))


def drive_section(d: DriveDiagnosis) -> list[str]:
    """The report's section on the feed drives (Markdown lines)."""
    L = ["## Feed drives (probes at several poses)", "",
         f"{d.n_probes} probes in {d.n_cycles} probing cycles; each cycle's uniform offset taken off (the observer's at "
         "the model's pose); every candidate judged leaving one cycle out. " + d.message[0].upper() + d.message[1:]
         + ".", ""]
    if d.named:
        L += ["| drive | effect | parameter (± 1σ, jackknife over cycles) | nominal | validation gain | alternatives |",
              "|---|---|---|---|---|---|"]
        for f in d.named:
            c = f.candidate
            L.append(f"| {c.axis} | {c.label} | {c.param_name} = {f.value:.4g} ± {f.sigma:.2g} | {c.nominal:.4g} | "
                     f"{100 * f.validation_gain:.0f} % | {', '.join(f.alternatives) or '–'} |")
        L.append("")
    L += ["| direction | residual between poses before [µm] | after [µm] |", "|---|---|---|"]
    L += [f"| {k} | {v['before']:.3g} | {v['after']:.3g} |" for k, v in d.rms_um.items()]
    L += ["", "Every candidate on the nominal model's residual:", "",
          "| drive | effect | parameter | validation gain |", "|---|---|---|---|"]
    L += [f"| {f.candidate.axis or '–'} | {f.candidate.label} | {f.candidate.param_name} = {f.value:.4g} ± "
          f"{f.sigma:.2g} | {100 * f.validation_gain:.0f} % |" for f in d.fits]
    return L
