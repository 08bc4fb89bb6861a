"""The library of named, physically parametrised model extensions.

Each :class:`Candidate` is one effect at one target (a source, zone, sensor, body, or the whole
machine) with bounded parameters, the parameter value that means "no effect" (``nominal``), and
an ``apply`` function that changes a :class:`~hybridcomp.diagnose.problem.Setup`.

| kind | parameters | what it changes |
|---|---|---|
| ``ambient_lag`` | gain [-], τ [h] | ambient-air zones follow the measured workshop air through a first-order lag |
| ``missing_source`` | power at full activity [W] | a heat input at an existing source's patch driven by another activity signal |
| ``located_source`` | power [W] (exponent [-]) | a heat input anywhere on a body's surface, with a drive shape (``locate``) |
| ``power_scale`` | factor [-] | the power of a modelled source |
| ``exponent`` | exponent [-] | the speed-to-heat exponent of a modelled source |
| ``htc`` | h [W/(m² K)] | a zone's heat-transfer coefficient |
| ``htc_motion`` | h moving, h standstill [W/(m² K)] | a zone's coefficient switching with machine activity (heating vs cooling) |
| ``sensor_lag`` | τ [min] | a temperature sensor reads its point through a first-order lag |
| ``sensor_offset`` | offset [unit], drift [unit/h] | a channel reads with an offset and a linear drift |
| ``workspace_offset`` | ΔT [K] (τ [h]) | every workspace (enclosure) zone's air is off by a constant, all along or |
|  |  | rising from the record's start through a first-order lag τ (target ``rising``: an enclosure that warms) |
| ``expansion`` | α [µm/(m K)] | a body's thermal expansion coefficient (drift channels) |
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hybridcomp.diagnose.problem import Problem, Setup, activity_mask, first_order_lag

KINDS = ("ambient_lag", "missing_source", "located_source", "power_scale", "exponent", "htc", "htc_motion", "sensor_lag",
         "sensor_offset", "workspace_offset", "expansion")


@dataclass(frozen=True)
class Candidate:
    """One named effect at one target.

    Attributes
    ----------
    kind : library key (see ``KINDS``)
    target : source, zone, sensor channel or body name ('' for machine-wide effects)
    label : human-readable name
    param_names : parameter names with their unit in brackets
    lower, upper : bounds of the parameters
    nominal : parameter values meaning "no effect" (the model as it is)
    start : starting values of a nonlinear fit
    linear : outputs are affine in the parameters (fitted in closed form)
    stage : ``"sim"`` (inputs or h: a new simulation), ``"raw"`` (raw outputs) or ``"out"`` (measured channels)
    apply : changes a setup for given parameters
    grid : trial values of the first parameter for a nonlinear fit's start
    physical : per parameter, whether its (lower, upper) bound is a physically meaningful value (a time constant
        of 0: the air reaches the surfaces at once; a power factor of 0: the source gives no heat) rather than the
        edge of the search range; a fit at a meaningful bound is a result, at an artefact bound the wrong shape
    extra_dof : parameters chosen outside the fit that count in the BIC (a located source's three coordinates)
    info : what a report needs beyond the parameters (a located source's place, its confidence region, its driver)
    """

    kind: str
    target: str
    label: str
    param_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    nominal: tuple[float, ...]
    start: tuple[float, ...]
    linear: bool
    stage: str
    apply: Callable = field(compare=False, repr=False)
    grid: tuple[float, ...] | None = None
    physical: tuple[tuple[bool, bool], ...] = ()
    extra_dof: int = 0
    info: dict = field(default_factory=dict, compare=False)

    @property
    def key(self) -> tuple[str, str]:
        return (self.kind, self.target)

    def describe(self, p) -> str:
        vals = ", ".join(f"{n} = {v:.4g}" for n, v in zip(self.param_names, p))
        return f"{self.label} ({vals})"


def _varies(f: np.ndarray | None) -> bool:
    """A load factor with enough intermediate levels to tell exponents apart."""
    if f is None:
        return False
    mid = (f > 0.05) & (f < 0.95)
    return mid.mean() > 0.05 and np.unique(np.round(f[mid], 2)).size >= 3


def library(problem: Problem, kinds=None) -> list[Candidate]:
    """Every candidate effect the problem's machine and data allow (``kinds`` restricts the library).

    ``located_source`` candidates depend on a residual: :func:`hybridcomp.diagnose.core.diagnose` makes them with
    :func:`hybridcomp.diagnose.locate.candidates` when the others leave the data unexplained.
    """
    kinds = KINDS if kinds is None else tuple(kinds)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise ValueError(f"unknown effect kind {unknown[0]!r} (library: {', '.join(KINDS)})")
    m = problem.machine
    out: list[Candidate] = []
    zone_h = dict(zip(problem.rom.zone_names, problem.rom.h_W_m2K))
    t0 = problem.time_s[0]

    if "ambient_lag" in kinds and "Tamb_degC" in problem.signals and problem.zone_columns("ambient"):
        cols = problem.zone_columns("ambient")
        tamb = problem.signals["Tamb_degC"] - problem.t_ref

        def apply(s: Setup, p, cols=cols, tamb=tamb):
            lagged = first_order_lag(problem.time_s, tamb, p[1] * 3600.0)
            for j in cols:
                s.U[:, j] += p[0] * (lagged - s.U[:, j])

        out.append(Candidate("ambient_lag", "", "unmodelled ambient variation: ambient zones follow the workshop air "
                             "through a first-order lag", ("gain [-]", "tau [h]"), (0.0, 0.0), (1.5, 24.0), (0.0, 1.0),
                             (1.0, 1.0), False, "sim", apply, grid=None, physical=((False, False), (True, False))))

    fixed = [s for s in problem.sources if s.kind == "fixed"]
    if "missing_source" in kinds:
        for loc in fixed:
            for driver, f in problem.activity.items():
                if driver == loc.driver or np.ptp(f) == 0:
                    continue
                j = loc.columns[0]

                def apply(s: Setup, p, j=j, f=f):
                    s.U[:, j] += p[0] * f

                out.append(Candidate("missing_source", f"{loc.name}|{driver}",
                                     f"missing heat source at {loc.name} ({loc.body}) driven by {driver}",
                                     ("power at full load [W]",), (0.0,), (2000.0,), (0.0,), (0.0,), True, "sim", apply))

    for si in problem.sources:
        P = problem.U[:, list(si.columns)].sum(axis=1)
        if np.ptp(P) == 0 and P.max() == 0:
            continue
        if "power_scale" in kinds:

            def apply(s: Setup, p, cols=list(si.columns)):  # noqa: B006 - binds this source's columns, never mutated
                s.U[:, cols] *= p[0]

            out.append(Candidate("power_scale", si.name, f"mis-scaled power of {si.name}", ("factor [-]",), (0.0,), (5.0,),
                                 (1.0,), (1.0,), True, "sim", apply, physical=((True, False),)))
        if "exponent" in kinds and si.exponent is not None and _varies(si.factor):
            n0 = si.exponent

            def apply(s: Setup, p, cols=list(si.columns), f=si.factor, n0=n0):  # noqa: B006 - binds, never mutated
                old = f**n0
                ratio = np.where(old > 1e-12, f ** p[0] / np.where(old > 1e-12, old, 1.0), 0.0)
                s.U[:, cols] *= ratio[:, None]

            out.append(Candidate("exponent", si.name, f"wrong speed-to-heat exponent of {si.name}", ("exponent [-]",),
                                 (0.3,), (4.0,), (n0,), (n0,), False, "sim", apply, grid=(0.6, 1.0, 1.5, 2.2, 3.0)))

    zones = [z.name for z in m.zones]
    if "htc" in kinds:
        for z in zones:
            h0 = float(zone_h[z])

            def apply(s: Setup, p, z=z):
                s.h[z] = p[0]

            out.append(Candidate("htc", z, f"wrong convection coefficient of zone {z}", ("h [W/(m2 K)]",), (0.25 * h0,),
                                 (4.0 * h0,), (h0,), (h0,), False, "sim", apply,
                                 grid=tuple(h0 * np.array([0.4, 0.6, 0.85, 1.2, 1.7, 2.5]))))
    if "htc_motion" in kinds and activity_mask(problem).any() and not activity_mask(problem).all():
        for z in zones:
            h0 = float(zone_h[z])

            def apply(s: Setup, p, z=z):
                s.switch.append((z, p[0], p[1]))

            out.append(Candidate("htc_motion", z, f"convection of zone {z} differs between motion and standstill",
                                 ("h moving [W/(m2 K)]", "h standstill [W/(m2 K)]"), (0.25 * h0, 0.25 * h0),
                                 (4.0 * h0, 4.0 * h0), (h0, h0), (h0, h0), False, "sim", apply))

    for k, c in enumerate(problem.channels):
        if "sensor_lag" in kinds and problem.is_temperature(k):

            def apply(s: Setup, p, k=k):
                s.out_ops.append(lambda Yc, k=k, tau=p[0]: Yc.__setitem__(
                    (slice(None), k), first_order_lag(problem.time_s, Yc[:, k], tau * 60.0)))

            out.append(Candidate("sensor_lag", c, f"sensor lag of {c.removesuffix('_degC')}", ("tau [min]",), (0.0,), (240.0,),
                                 (0.0,), (5.0,), False, "out", apply, grid=(2.0, 6.0, 15.0, 40.0, 100.0)))
        if "sensor_offset" in kinds:
            unit = "K" if problem.is_temperature(k) else "um"
            big = 20.0 if unit == "K" else 500.0

            def apply(s: Setup, p, k=k):
                s.out_ops.append(lambda Yc, k=k, a=p[0], b=p[1]: Yc.__setitem__(
                    (slice(None), k), Yc[:, k] + a + b * (problem.time_s - t0) / 3600.0))

            out.append(Candidate("sensor_offset", c, f"offset and drift of channel {c}",
                                 (f"offset [{unit}]", f"drift [{unit}/h]"),
                                 (-big, -big / 10), (big, big / 10), (0.0, 0.0), (0.0, 0.0), True, "out", apply))

    if "workspace_offset" in kinds and problem.zone_columns("workspace"):

        def apply(s: Setup, p, cols=problem.zone_columns("workspace")):  # noqa: B008 - binds the columns once
            s.U[:, cols] += p[0]

        out.append(Candidate("workspace_offset", "", "workspace (enclosure) air temperature offset", ("dT [K]",), (-15.0,),
                             (15.0,), (0.0,), (0.0,), True, "sim", apply))

        def apply_rising(s: Setup, p, cols=problem.zone_columns("workspace"), age_s=problem.time_s - t0):  # noqa: B008
            # from the machine's state at the record's start (no offset in the first row), the air's offset builds
            # up through a first-order lag; τ at its lower bound is a step at the start
            rise = -np.expm1(-age_s / max(p[1] * 3600.0, 1.0))
            s.U[:, cols] += p[0] * rise[:, None]

        out.append(Candidate("workspace_offset", "rising", "workspace (enclosure) air temperature offset, rising from "
                             "the record's start", ("dT [K]", "tau [h]"), (-15.0, 0.0), (15.0, 12.0), (0.0, 1.0),
                             (1.0, 1.0), False, "sim", apply_rising, grid=(-4.0, -1.0, 1.0, 4.0),
                             physical=((False, False), (True, False))))

    if "expansion" in kinds and problem.body_names and any(c.endswith("_um") for c in problem.channels):
        drift_rows = list(problem.rom.output_layout().drift_indices)
        for b in problem.body_names:
            mat = m.materials[m.body(b).material]
            a0 = mat.expansion_1_K * 1e6
            if a0 <= 0:
                continue
            rows = problem.body_rows(b)

            def apply(s: Setup, p, rows=rows, a0=a0):
                s.raw_ops.append(lambda Y, rows=rows, k=p[0] / a0: Y.__setitem__(
                    (slice(None), drift_rows), Y[:, drift_rows] + (k - 1.0) * Y[:, rows]))

            out.append(Candidate("expansion", b, f"wrong expansion coefficient of body {b}", ("alpha [um/(m K)]",),
                                 (0.0,), (4.0 * a0,), (a0,), (a0,), True, "raw", apply, physical=((True, False),)))
    return out


def params_key(p) -> tuple:
    """Parameter values as a cache key (rounded, so that round-off does not tell equal fits apart)."""
    return tuple(np.round(np.asarray(p, float), 12))


def predicted_channels(problem: Problem, effects) -> np.ndarray:
    """Channels (nt × nch) in measured units for the model with ``effects`` [(Candidate, params)]."""
    from hybridcomp.diagnose.problem import channel_outputs, new_setup, raw_outputs

    s = new_setup(problem)
    key = []
    for cand, p in effects:
        cand.apply(s, np.asarray(p, float))
        if cand.stage == "sim":
            key.append((cand.kind, cand.target, params_key(p)))
    Y = raw_outputs(problem, s, tuple(key))
    if s.raw_ops:
        Y = Y.copy()
        for op in s.raw_ops:
            op(Y)
    Yc = channel_outputs(problem, Y)
    for op in s.out_ops:
        op(Yc)
    return Yc
