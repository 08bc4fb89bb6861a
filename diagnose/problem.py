"""The diagnosis problem: a reduced model, the dataset's inputs and measured channels, and how to simulate variants.

Everything the effect library changes is one of four things, applied in this order:

* model inputs ``U`` (heat powers [W], air temperature rises [K]),
* the zones' heat-transfer coefficients (``ReducedModel.with_htc``: affine in h, no new reduction),
  optionally switching between two values with the machine's activity,
* raw reduced-model outputs (per-body drift rows, for expansion coefficients),
* the channels as measured (sensor lag, offset, drift).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from hybridcomp.diagnose.data import Dataset, DatasetError, Split, check_channels
from hybridcomp.diagnose.metrics import noise_level
from hybridcomp.models.layout import DRIFT_COLUMNS, body_output_names

log = logging.getLogger(__name__)

# noise floors: below these a channel's noise estimate is not trusted (quantisation, smoothing)
NOISE_FLOOR = {"degC": 0.002, "um": 0.02}


@dataclass(frozen=True)
class SourceInfo:
    """A heat source of the machine as the dataset drives it.

    Attributes
    ----------
    name : source name
    columns : model input indices of its heat input(s)
    power_W : power at load factor 1 [W]
    exponent : speed-to-heat exponent [-] (None with a power table)
    driver : axis name, ``"spindle"`` or None
    factor : load factor per sample reconstructed from its power, 0..1 (None if not invertible) [-]
    """

    name: str
    kind: str
    body: str
    columns: tuple[int, ...]
    power_W: float
    exponent: float | None
    driver: str | None
    factor: np.ndarray | None


@dataclass(frozen=True)
class Problem:
    """A reduced model and a measured dataset, ready for simulation and fitting.

    Attributes
    ----------
    machine : the machine definition
    rom : reduced model; outputs sensors [K], dx, dy, dz [m], then per-body drift rows [m] if any
    time_s : sample times [s]
    U : model inputs (nt × nu): powers [W] and air temperature rises [K]
    Y : measured channels (nt × nch) [°C or µm]
    channels : channel names (``T1_degC``, ``dz_um``)
    out_index : ROM output per channel
    sigma : noise level per channel [°C or µm]
    split : training and validation rows
    sources : heat sources with reconstructed load factors
    activity : driver → load factor 0..1 per sample
    signals : every named series the residual is correlated with
    body_names : bodies whose drift rows follow the base outputs
    air_measured : zone → the dataset column its air temperature came from
    tolerance : per channel, the residual the model itself may leave (reduction and discretisation error) [°C or µm]
    floor : the model's discretisation error (:class:`~hybridcomp.diagnose.discretisation.Floor`), None if not known
    """

    machine: object
    rom: object
    time_s: np.ndarray
    U: np.ndarray
    Y: np.ndarray
    channels: tuple[str, ...]
    out_index: tuple[int, ...]
    sigma: np.ndarray
    split: Split
    sources: tuple[SourceInfo, ...]
    activity: dict
    signals: dict
    body_names: tuple[str, ...] = ()
    air_measured: dict = field(default_factory=dict)
    tolerance: np.ndarray | None = None
    floor: object = None
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def t_ref(self) -> float:
        return float(self.machine.reference_temperature_degC)

    @property
    def weights(self) -> np.ndarray:
        return 1.0 / self.sigma

    @property
    def zone_names(self) -> tuple[str, ...]:
        return tuple(z.name for z in self.machine.zones)

    def zone_columns(self, air: str) -> list[int]:
        """Model input indices of the zones with this kind of air (``ambient`` or ``workspace``)."""
        layout = self.machine.layout()
        return [len(layout.heat_inputs) + i for i, kind in enumerate(layout.zone_air) if kind == air]

    def channel_unit(self, c: int) -> str:
        return "degC" if self.channels[c].endswith("_degC") else "um"

    def is_temperature(self, c: int) -> bool:
        return self.channels[c].endswith("_degC")

    def body_rows(self, body: str) -> list[int]:
        """The reduced model's outputs of one body's share of the drift (dx, dy, dz)."""
        return list(self.rom.output_layout().body_indices(body))


def first_order_lag(time_s: np.ndarray, u: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag y' = (u − y)/τ, exact for u linear between samples, starting at y = u[0] (steady) [unit of u]."""
    u = np.asarray(u, float)
    if tau_s <= 0:
        return u.copy()
    t = np.asarray(time_s, float)
    dts = np.diff(t)
    if np.allclose(dts, dts[0], rtol=1e-9):
        dt = dts[0]
        a = np.exp(-dt / tau_s)
        q = tau_s * (1 - a) / dt
        b1, b0 = 1 - q, q - a
        y = np.empty_like(u)
        y[0] = u[0]
        y[1:], _ = lfilter([b1, b0], [1.0, -a], u[1:], zi=[a * u[0] + b0 * u[0]])
        return y
    y = np.empty_like(u)
    y[0] = u[0]
    for k in range(1, u.size):
        a = np.exp(-dts[k - 1] / tau_s)
        q = tau_s * (1 - a) / dts[k - 1]
        y[k] = a * y[k - 1] + (q - a) * u[k - 1] + (1 - q) * u[k]
    return y


# --------------------------------------------------------------------------- building a problem


def body_drift_rows(model) -> tuple[tuple[str, ...], np.ndarray]:
    """Drift rows dx, dy, dz per body [m/K] (bodies × 3 × n): the rows G with only that body expanding.

    The thermo-elastic map is linear in the expansion coefficients, so ``G = Σ_b G_b`` and a body
    whose coefficient is wrong by a factor k changes the drift by ``(k − 1) G_b x``.  One adjoint
    solve set per body (the elastic operator does not depend on α).
    """
    from hybridcomp.fem.assembly import cell_basis
    from hybridcomp.fem.model import drift_rows

    machine, mm = model.machine, model.mesh
    basis = cell_basis(mm.mesh)
    mats = [machine.materials[machine.body(b).material] for b in mm.body_names]
    E = np.array([m.youngs_modulus_Pa for m in mats])[mm.body_of_element]
    nu = np.array([m.poisson_ratio for m in mats])[mm.body_of_element]
    alpha = np.array([m.expansion_1_K for m in mats])[mm.body_of_element]
    rows = []
    for i, _ in enumerate(mm.body_names):
        a = np.where(mm.body_of_element == i, alpha, 0.0)
        G, _backend = drift_rows(machine, mm, basis, {"E": E, "nu": nu, "alpha": a})
        rows.append(G)
    return tuple(mm.body_names), np.array(rows)


def with_body_rows(rom, bodies: tuple[str, ...], rows: np.ndarray):
    """The reduced model with per-body drift outputs appended (needs the basis V)."""
    if rom.V is None:
        raise ValueError("the reduced model has no basis V: per-body drift rows cannot be projected")
    extra = np.vstack([rows[i] @ rom.V for i in range(len(bodies))])
    names = tuple(n for b in bodies for n in body_output_names(b))
    return rom.with_operators(C=np.vstack([rom.C, extra]), output_names=tuple(rom.output_names) + names)


def _factor(machine, s, P: np.ndarray) -> np.ndarray | None:
    if s.power_W <= 0 or s.power_table is not None or s.driver is None:
        return None
    return np.clip(P / s.power_W, 0.0, 1.0) ** (1.0 / s.exponent)


def build_problem(machine, rom, dataset: Dataset, split: Split, body_names: tuple[str, ...] | None = (),
                  tolerance: tuple[float, float] = (0.0, 0.0)) -> Problem:
    """Model inputs, measured channels, noise levels and activity signals of a dataset.

    Heat inputs are read from ``<input>_W`` columns (missing: zero power); zone air from
    ``<zone>_degC``, else from the measured workspace (``Tws_degC``) or workshop (``Tamb_degC``)
    air by the zone's kind, else the reference temperature.  Measured channels are the machine's
    sensors ``<sensor>_degC`` and ``dx_um``, ``dy_um``, ``dz_um`` present in the dataset.

    ``tolerance`` = (K, µm): the residual the model itself may leave (its reduction error); a channel
    whose residual is below it counts as explained.  ``body_names``: the bodies whose drift rows the
    expansion effects use (None: every body the reduced model has rows of).

    Raises
    ------
    DatasetError
        no heat-input column, no measured channel, a constant channel.
    """
    layout = machine.layout()
    names = list(rom.input_names)
    t_ref = layout.reference_temperature_degC
    heat_cols = layout.heat_columns
    present = [n for n in heat_cols if n in dataset]
    if heat_cols and not present:
        hint = " (it looks like a trace: read it with diagnose.core.read_measured, or `hybridcomp histogram` first)" if any(
            c.endswith("_mm") for c in dataset.names) else ""
        raise DatasetError(
            f"{dataset.source}: no heat-input column of machine {machine.name!r} ({', '.join(heat_cols[:4])}, ...){hint}; "
            "columns found: " + ", ".join(dataset.names)
        )
    channels = [c for c in layout.output_columns if c in dataset]
    if not channels:
        raise DatasetError(
            f"{dataset.source}: no measured channel: expected sensor columns "
            f"{', '.join(layout.sensor_columns)} and/or {', '.join(DRIFT_COLUMNS)}; columns found: {', '.join(dataset.names)}"
        )
    check_channels(dataset, channels, split)
    if tuple(names) != layout.columns:
        raise DatasetError(f"{dataset.source}: the reduced model's inputs are not those of machine {machine.name!r}")
    outputs = rom.output_layout()
    if outputs.sensors != layout.sensors:
        raise DatasetError(f"{dataset.source}: the reduced model's sensors are not those of machine {machine.name!r}")
    row = dict(zip(outputs.columns("sensors") + outputs.columns("drift"),
                   outputs.indices("sensors") + outputs.indices("drift")))
    idx = [row[c] for c in channels]
    if body_names is None:
        body_names = outputs.bodies
    for n in present:
        if np.any(dataset[n] < 0):
            raise DatasetError(f"{dataset.source}: column {n!r}: a heat power cannot be negative, got {dataset[n].min()}")
    air_measured = layout.air_sources(dataset.names)  # zone -> the column its air temperature comes from
    used = [*present, *dict.fromkeys(air_measured.values())]
    U = layout.inputs(used, np.column_stack([dataset[c] for c in used]) if used else np.zeros((dataset.time_s.size, 0)),
                      dataset.source, air_measured)
    Y = np.column_stack([dataset[c] for c in channels])
    sigma = np.array([max(noise_level(Y[:, k]), NOISE_FLOOR["degC" if c.endswith("_degC") else "um"])
                      for k, c in enumerate(channels)])
    sources = []
    for s in machine.heat_sources:
        cols = layout.source_columns(s.name)
        P = U[:, list(cols)].sum(axis=1)
        sources.append(SourceInfo(s.name, s.kind, s.body, cols, s.power_W, None if s.power_table else s.exponent, s.driver,
                                  _factor(machine, s, P)))
    activity = {}
    if "spindle_rpm" in dataset and machine.spindle_max_speed_rpm > 0:
        activity["spindle"] = np.clip(np.abs(dataset["spindle_rpm"]) / machine.spindle_max_speed_rpm, 0, 1)
    for si in sorted(sources, key=lambda s: s.kind != "fixed"):
        if si.driver and si.driver not in activity and si.factor is not None and np.ptp(si.factor) > 0:
            activity[si.driver] = si.factor
    signals = {n: U[:, j] + (t_ref if n.endswith("_degC") else 0.0) for j, n in enumerate(names) if np.ptp(U[:, j]) > 0}
    signals.update({f"activity {d}": f for d, f in activity.items()})
    for extra in ("Tamb_degC", "Tws_degC", "spindle_rpm"):
        if extra in dataset and extra not in signals:
            signals[extra] = dataset[extra]
    signals["time_s"] = dataset.time_s.astype(float)
    return Problem(machine, rom, np.asarray(dataset.time_s, float), U, Y, tuple(channels), tuple(idx), sigma, split,
                   tuple(sources), activity, signals, tuple(body_names), air_measured,
                   np.array([tolerance[0] if c.endswith("_degC") else tolerance[1] for c in channels], float))


# --------------------------------------------------------------------------- simulating variants


@dataclass
class Setup:
    """What the effects change, collected before one simulation."""

    U: np.ndarray
    h: dict
    switch: list = field(default_factory=list)  # (zone, h_run, h_stop)
    raw_ops: list = field(default_factory=list)  # f(Yraw) in place
    out_ops: list = field(default_factory=list)  # f(Yc) in place


def _rom_variant(problem: Problem, h: dict):
    key = ("rom", tuple(sorted((k, round(v, 12)) for k, v in h.items())))
    cache = problem._cache
    if key not in cache:
        if len([k for k in cache if k[0] == "rom"]) > 64:
            for k in [k for k in cache if k[0] == "rom"][:32]:
                del cache[k]
        cache[key] = problem.rom.with_htc(**h) if h else problem.rom
    return cache[key]


def activity_mask(problem: Problem, threshold: float = 0.02) -> np.ndarray:
    """Samples at which any drive or the spindle is active (load factor above ``threshold``)."""
    if not problem.activity:
        return np.zeros(problem.time_s.size, bool)
    return np.max(np.column_stack(list(problem.activity.values())), axis=1) > threshold


def raw_outputs(problem: Problem, setup: Setup, key=None) -> np.ndarray:
    """Reduced-model outputs (nt × q) for a setup; cached under ``key`` (the simulation-stage effects)."""
    cache = problem._cache
    if key is not None and ("sim", key) in cache:
        return cache[("sim", key)]
    t, U = problem.time_s, setup.U
    if not setup.switch:
        Y = _rom_variant(problem, setup.h).integrate(t, U)[0]
    else:
        active = activity_mask(problem)
        h_run, h_stop = dict(setup.h), dict(setup.h)
        for zone, hr, hs in setup.switch:
            h_run[zone], h_stop[zone] = hr, hs
        roms = {True: _rom_variant(problem, h_run), False: _rom_variant(problem, h_stop)}
        state = active[:-1]  # the state during interval k → k + 1
        edges = np.flatnonzero(np.diff(state.astype(int))) + 1
        starts = np.r_[0, edges]
        ends = np.r_[edges, t.size - 1]
        Y = np.empty((t.size, problem.rom.C.shape[0]))
        x = "steady"
        for k0, k1 in zip(starts, ends):
            Ys, x = roms[bool(state[k0])].integrate(t[k0:k1 + 1], U[k0:k1 + 1], initial=x)
            Y[k0:k1 + 1] = Ys
    if key is not None:
        if len([k for k in cache if k[0] == "sim"]) > 256:
            for k in [k for k in cache if k[0] == "sim"][:128]:
                del cache[k]
        cache[("sim", key)] = Y
    return Y


def channel_outputs(problem: Problem, Yraw: np.ndarray) -> np.ndarray:
    """Channels in measured units from raw outputs: sensors [°C], drift [µm]."""
    out = np.empty((Yraw.shape[0], len(problem.channels)))
    for k, (c, i) in enumerate(zip(problem.channels, problem.out_index)):
        out[:, k] = Yraw[:, i] + problem.t_ref if c.endswith("_degC") else Yraw[:, i] * 1e6
    return out


def new_setup(problem: Problem) -> Setup:
    """An empty :class:`Setup` on a copy of the problem's inputs."""
    return Setup(U=problem.U.copy(), h={})
