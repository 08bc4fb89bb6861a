"""Boundary conditions from increments: heat power per source and rail segment, zone air temperatures.

The result is a :class:`hybridcomp.models.layout.Loads` with every column of the machine's
input layout, in model order: the loads-CSV contract that ``hybridcomp simulate`` reads.

Powers per increment (``P(f)`` is ``machine.source_power_W``: the power law
``power_W f**exponent`` or the machine file's ``power_table``):

* fixed source driven by an axis: ``P(f_axis)``; by the spindle: ``P(f_spindle)``;
  without a driver (not tied to a drive): ``power_W`` all the time;
* moving source (nut, carriages) of axis a, column ``<source>[k]_W``:
  ``P(f_a) * (time in rail segment k) / (increment length)``, so the
  segments add up to ``P(f_a)``.

That is ``power="factor"``. ``power="mean"``, the default, instead takes the
time average of ``P(f(t))`` with the instantaneous factor (constant between
two samples or breakpoints), and puts a moving source's heat into the segment
where the axis was while dissipating it. The two agree for constant speeds.
They differ when the speed varies within an increment: for the convex spindle
law (exponent 1.67) ``P(mean f) < mean P(f)``, and an axis that stands in one
segment and moves in another heats the segment it moves in. On the bundled
job-shop day (vmc800) ``"factor"`` puts in 14.7 % (5 min increments), 16.0 %
(15 min) and 19.6 % (60 min) less heat than ``"mean"``, whose heat does not
depend on the increment length: that is why ``"mean"`` is the default.

Time stamps: row 0 is the start of the trace with the machine at standstill
(``P(0)``: zero for the power law) and the air temperatures measured at the
first sample; row k+1 is the end of increment k and holds that increment's
mean values. ``hybridcomp simulate`` with its default backward Euler steps on
the CSV's own times applies row k+1 over exactly increment k, so the heat
put in per increment is exact, and ``--initial steady`` starts from a machine
that has stood still.

Zones: a zone's ``<zone>_degC`` column follows the air the trace measured for it
(``InputLayout.air_sources``); a zone whose air was not measured stays at the
reference temperature.
"""

from __future__ import annotations

import numpy as np

from hybridcomp.histogram.increments import Increments
from hybridcomp.models.layout import Loads
from hybridcomp.models.loads import write_loads
from hybridcomp.models.machine import SPINDLE, Machine


def source_factors(machine: Machine, inc: Increments) -> dict[str, np.ndarray]:
    """Load factor of every heat source per increment [-] (NaN for a source without a driver)."""
    out = {}
    for s in machine.heat_sources:
        if s.driver is None:
            out[s.name] = np.full(len(inc), np.nan)
        elif s.driver == SPINDLE:
            out[s.name] = inc.spindle_factor
        else:
            out[s.name] = inc.axis_factor[:, inc.axis_names.index(s.driver)]
    return out


def heat_powers(machine: Machine, inc: Increments, power: str = "mean") -> tuple[tuple[str, ...], np.ndarray]:
    """Heat power per heat input and increment [W].

    Parameters
    ----------
    machine : the machine the increments were made for
    inc : increments
    power : ``"factor"``: ``P(mean factor)``, and a moving source's power split over the
        segments by the time fractions (the module docstring); ``"mean"``: the time average of
        ``P(f(t))`` over the increment with the instantaneous factor ``f(t)``, and a moving source's
        heat put into the segment where it was dissipated. The two agree for constant speeds; for a
        convex power law (spindle bearings, exponent 1.67) ``"factor"`` gives less heat the longer
        the increment, ``"mean"`` keeps the heat of every increment exact.

    Returns
    -------
    column names ``<source>_W`` / ``<source>[k]_W`` in model order, and the powers (nk × n_inputs)
    """
    if inc.axis_names != tuple(a.name for a in machine.axes):
        raise ValueError(f"increments are for axes {inc.axis_names}, "
                         f"machine {machine.name!r} has {[a.name for a in machine.axes]}")
    if power not in ("factor", "mean"):
        raise ValueError(f"power must be 'factor' or 'mean', got {power!r}")
    layout = machine.layout()
    names = layout.heat_columns
    P = np.zeros((len(inc), len(names)))
    factors = source_factors(machine, inc)
    for s in machine.heat_sources:
        f = factors[s.name]
        p = np.full(len(inc), s.power_W) if s.driver is None else machine.source_power_W(s, f)
        cols = layout.source_columns(s.name)
        if s.kind == "fixed":
            P[:, cols[0]] = p
        else:
            P[:, list(cols)] = p[:, None] * inc.segment_fraction(s.axis)
    if power == "mean":
        for j, n in enumerate(inc.mean_power_inputs):
            P[:, names.index(n)] = inc.mean_power_W[:, j]
    return names, P


def standstill_powers(machine: Machine) -> np.ndarray:
    """Heat power per heat input at standstill [W] (model order): ``P(0)``, spread evenly over rail segments."""
    layout = machine.layout()
    vals = np.zeros(len(layout.heat_inputs))
    for s in machine.heat_sources:
        p = float(s.power_W) if s.driver is None else float(machine.source_power_W(s, 0.0))
        cols = list(layout.source_columns(s.name))
        vals[cols] = p / len(cols)
    return vals


def boundary_conditions(machine: Machine, inc: Increments, power: str = "mean") -> Loads:
    """The BC time series of increments, in the loads-CSV contract of ``hybridcomp simulate``.

    Parameters
    ----------
    machine : the machine the increments were made for
    inc : load factors and histograms per increment
    power : ``"factor"`` or ``"mean"``, see :func:`heat_powers`

    Returns
    -------
    Loads in model order with ``time_s`` = [start of the trace, end of each increment] [s], heat
    powers [W] for every heat input and air temperatures [°C] for every zone (the reference
    temperature where its air was not measured).
    """
    names, P = heat_powers(machine, inc, power)
    layout = machine.layout()
    zones = layout.air_sources(inc.air_names)  # zone -> measured air column; the others stay at the reference
    Z = np.column_stack([inc.air_degC[:, inc.air_names.index(zones[z])] if z in zones else
                         np.full(len(inc), layout.reference_temperature_degC) for z in layout.zones]) \
        if layout.zones else np.zeros((len(inc), 0))
    Z0 = np.array([inc.initial_air_degC[inc.air_names.index(zones[z])] if z in zones else
                   layout.reference_temperature_degC for z in layout.zones])
    first = np.concatenate([standstill_powers(machine), Z0])[None, :]
    values = np.vstack([first, np.hstack([P, Z])])
    time_s = np.concatenate([[inc.start_s[0]], inc.end_s])
    return Loads(time_s, values, layout.columns)


def write_bcs(path, loads: Loads) -> None:
    """Write a BC time series as a loads CSV (``models.loads.write_loads``)."""
    write_loads(path, loads)
