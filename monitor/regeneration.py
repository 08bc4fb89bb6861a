"""The regeneration job: recent load history → BCs → FE → CD fit → database.

The daemon runs a job in a worker process (``daemon.Regenerator``) with a
timeout and activates the set the job returns, so a job that fails, hangs or
dies never touches the active set. A job is any importable function
``job(request: dict) -> {"ids": {"X": id, "Y": id, "Z": id}, "load_case": str}``
named ``"module:function"`` in the configuration; the request is the JSON form
of :class:`RegenerationRequest` (plain data: it crosses a process boundary and
is stored in the database so that a restart can resubmit it).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import asdict, dataclass, fields

import numpy as np

log = logging.getLogger(__name__)

N_SUPPORT = 4  # support points per input of a generated CD: a few hours of history fill a 4 × 4 × 4 grid
MAX_INPUTS = 3  # at most this many sensors (chosen by BIC): sensors move together, more inputs extrapolate wildly
# The recent load history is run on FE as it was measured and with the air around the machine shifted, so that
# the CD learns how the drift follows the sensors when the air differs from what the histogram knows (a warmer
# enclosure, a draught): (zones: "workspace" | "all", offset [K]).
AIR_VARIANTS_K = (("all", 0.0), ("workspace", 2.0), ("workspace", -2.0), ("all", 1.5), ("all", -1.5))
_MODELS: dict = {}  # FE models built in this worker process, by (machine file hash, pose, element size)


@dataclass(frozen=True)
class RegenerationRequest:
    """What a generation job needs.

    Attributes
    ----------
    machine : machine name or file
    pose_key, pose_mm : the pose of the CDs (database key, axis positions [mm])
    database : CD database path or URL
    machine_time_s : machine time of the decision [s]
    t_reference_degC : the structure model's sensor temperatures at the decision [°C]; the new set's T_reference
    signature : load-case signature of the last monitoring interval (or None)
    loads_names : model input names (``*_W`` powers, ``*_degC`` zone air)
    loads_time_s : end times of the recent increments [s]
    loads_inputs : model inputs over each of them (powers [W], air rises over the reference [K])
    reference_temperature_degC : the model's reference temperature [°C]
    element_size_mm : FE element size for the job [mm]
    initial_x : reduced state at the start of the history (reserved; the FE starts from steady state)
    """

    machine: str
    pose_key: str
    pose_mm: dict
    database: str
    machine_time_s: float
    t_reference_degC: dict
    signature: list | None
    loads_names: list
    loads_time_s: list
    loads_inputs: list
    reference_temperature_degC: float
    element_size_mm: float
    initial_x: list | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> RegenerationRequest:
        names = {f.name for f in fields(RegenerationRequest)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"regeneration request: unknown field(s) {sorted(unknown)}")
        return RegenerationRequest(**d)


def request_loads(req: RegenerationRequest, dt_s: float = 60.0):
    """The request's load history as a ``fem.loads.Loads`` on a ``dt_s`` grid (°C air).

    Each history row holds the mean inputs over the increment that ends at its
    time; the grid repeats them over that increment (piecewise constant), the
    first grid row is the start of the first increment with its inputs (a
    steady start).
    """
    from hybridcomp.fem.loads import Loads

    t = np.asarray(req.loads_time_s, float)
    U = np.asarray(req.loads_inputs, float)
    if t.size < 1 or U.shape != (t.size, len(req.loads_names)):
        raise ValueError(f"regeneration request at {req.machine_time_s} s has no usable load history "
                         f"({t.size} times, inputs of shape {U.shape})")
    start = t[0] - (t[1] - t[0] if t.size > 1 else 300.0)
    V = U.copy()
    for j, n in enumerate(req.loads_names):
        if n.endswith("_degC"):
            V[:, j] += req.reference_temperature_degC
    grid = np.arange(start, t[-1], dt_s)
    grid = np.append(grid, t[-1]) if t[-1] - grid[-1] > 1e-9 else grid
    k = np.clip(np.searchsorted(t, grid, side="left"), 0, t.size - 1)  # the increment (t[k-1], t[k]] holding τ
    return Loads(grid, V[k], tuple(req.loads_names))


def default_job(request: dict) -> dict:
    """BCs of the recent history → FE training run → three CDs → database (the daemon activates them).

    Uses ``hybridcomp.chardiag.training`` and ``hybridcomp.chardiag.fit`` (``N_SUPPORT`` support points per
    input). The history is run as measured and with the air shifted (``AIR_VARIANTS_K``), one table. The
    new CDs' T_reference is the structure model's temperatures at the decision. A direction whose drift no
    sensor explains in the history keeps the active set's CD (relabelled; noted in the result). The FE
    model is built once per worker process.
    """
    from hybridcomp.chardiag.cd import DIRECTIONS
    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.chardiag.fit import CDFitError, FitOptions, fit_cd
    from hybridcomp.chardiag.training import LoadCase, simulate_load_cases
    from hybridcomp.models import load_machine

    t0 = time.monotonic()
    req = RegenerationRequest.from_dict(request)
    machine = load_machine(req.machine)
    loads = request_loads(req)
    name = f"generated@{req.machine_time_s:.0f}s"
    sig = None if req.signature is None else np.asarray(req.signature, float)
    pose = machine.check_pose(dict(req.pose_mm or {}))
    key = (machine.sha256, tuple(sorted(pose.items())), req.element_size_mm)
    if key not in _MODELS:  # the worker process lives on: build the FE model once
        from hybridcomp.fem.model import build_model

        _MODELS.clear()
        _MODELS[key] = build_model(machine, pose, req.element_size_mm)
    cases = {}
    for zones, dK in AIR_VARIANTS_K:
        V = loads.values.copy()
        for z in machine.zones:
            col = f"{z.name}_degC"
            if dK and (zones == "all" or z.air == zones):
                if col in loads.names:
                    V[:, loads.names.index(col)] += dK
        variant = f"{name}{'' if not dK else f' {zones} {dK:+g} K'}"
        cases[variant] = LoadCase(variant, type(loads)(loads.time_s, V, loads.names), None, sig)
    data = simulate_load_cases(machine, cases, pose_mm=pose, element_size_mm=req.element_size_mm, model=_MODELS[key])
    kw = dict(machine=machine.name, machine_sha256=machine.sha256, pose_mm=pose, load_case=name, signature=sig,
              t_reference_degC=req.t_reference_degC, source=name)
    db = CDDatabase(req.database)
    try:
        cds, notes = {}, {}
        for d in DIRECTIONS:
            try:
                cds[d] = fit_cd(data.columns, d, options=FitOptions(n_support=N_SUPPORT, select="bic",
                                                                   max_inputs=MAX_INPUTS), **kw)
            except CDFitError as exc:
                # no sensor explains this direction's drift in the history (e.g. a direction that hardly
                # moves): keep the active set's CD for it, labelled with the new load case
                active = db.active_set(machine.name, req.pose_key)
                if active is None:
                    raise
                notes[d] = f"kept the active CD ({exc})"
                cds[d] = dataclasses.replace(active.cds[d], load_case=name, signature=np.asarray(
                    sig if sig is not None else active.cds[d].signature, float),
                    t_reference_degC=tuple((k, float(v)) for k, v in req.t_reference_degC.items()))
        ids = {d: int(db.add(cds[d], load_case=name)) for d in DIRECTIONS}
    finally:
        db.close()
    return {"ids": ids, "load_case": name, "wall_s": time.monotonic() - t0, "notes": notes}
