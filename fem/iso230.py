"""ISO 230-3 thermal tests, simulated on the FE model and the feed drives' screw models.

* :func:`moving_axis_test`: thermal distortion caused by a moving linear axis.  The axis moves back and forth
  over its whole travel at a stated feed, every other drive at rest and the spindle off, from the machine's
  standstill steady state; the error along the axis is recorded at five or more target positions over time.
* :func:`etve_test`: the environmental temperature variation error.  The machine at rest while the air of every
  zone swings sinusoidally; the drift in x, y and z and the feedback errors over a day or more.

The error at a target is the TCP-minus-table drift along the axis (the project's drift convention, what an
interferometer between spindle and table reads): the structure's drift at the target's pose (the model's field
carried with the bodies onto the support poses of :mod:`hybridcomp.fem.poses` and interpolated there, so lever
arms and the carrier's expansion up to the moving body change with the target) plus the error the drive adds to
it at the target (:class:`hybridcomp.fem.drives.DriveError`: the feedback's length less the carrier's, which
the structure holds already), with the sign of the side the axis moves (an axis that moves the table side
displaces the table, so its error enters TCP minus table negatively).

The summary values are this module's, named after what they measure (the standard's own evaluation, for a
measurement, reads the same curves): the largest error change at each target, the spread of the error over the
targets (its largest range across the travel at one time), the slope of the error along the travel at the end
(µm per m), and when the test reached steady state (every target within 5 % of its final change from then on).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hybridcomp.fem.drives import drive_error
from hybridcomp.fem.poses import drift_rows_at
from hybridcomp.histogram.bcs import standstill_powers
from hybridcomp.models.layout import Loads
from hybridcomp.models.machine import Machine, MachineFileError

#: share of its final change within which every target must stay for the test to be at steady state
STEADY_SHARE = 0.05


def axis_sign(machine: Machine, axis: str) -> float:
    """+1 when the axis moves the tool side (the TCP's body is on it), −1 when it moves the table side."""
    moves = machine.axis(axis).moves
    for sign, point in ((1.0, machine.tcp), (-1.0, machine.table_reference)):
        name = point.body
        while name is not None:
            if name == moves:
                return sign
            name = machine.body(name).mounted_on
    raise MachineFileError(f"{machine.source}: axis {axis} moves {moves!r}, which carries neither the TCP nor the "
                           "table reference")


def _require_drive(machine: Machine, axis: str):
    names = [a.name for a in machine.axes]
    if axis not in names:
        raise MachineFileError(f"{machine.source}: machine {machine.name!r} has no axis {axis!r} (axes: {names})")
    drive = machine.drive(axis)
    if drive is None:
        raise MachineFileError(f"{machine.source}: axis {axis} has no [[drives]] entry: give its ball screw and "
                               "position feedback to simulate its positioning error")
    return drive


def default_targets_mm(machine: Machine, axis: str, n: int = 5) -> np.ndarray:
    """``n`` equally spaced targets over the travel, 5 % of it in from each end [mm]."""
    lo, hi = machine.axis(axis).travel_mm
    margin = 0.05 * (hi - lo)
    return np.linspace(lo + margin, hi - margin, n)


def axis_cycle_loads(machine: Machine, axis: str, feed_mm_min: float, hours: float, step_s: float) -> Loads:
    """Loads of the moving-axis test.

    Row 0 the machine at rest, then ``axis`` moving back and forth over its travel at ``feed_mm_min`` (its sources
    at load factor feed / max feed, a moving source's heat over the rail segments by the time spent in each: their
    lengths), every other source at standstill, air at the reference.
    """
    a = machine.axis(axis)
    if not 0 < feed_mm_min <= a.max_feed_mm_min:
        raise ValueError(f"feed {feed_mm_min:g} mm/min of axis {axis} must be in (0, {a.max_feed_mm_min:g}] mm/min")
    if not hours > 0 or not step_s > 0 or step_s > hours * 3600:
        raise ValueError(f"hours ({hours:g}) and step_s ({step_s:g}) must be positive, the step within the test")
    layout = machine.layout()
    t = np.arange(0.0, hours * 3600 + 0.5 * step_s, step_s)
    rest = np.concatenate([standstill_powers(machine), np.zeros(len(layout.zones))])
    run = rest.copy()
    factor = feed_mm_min / a.max_feed_mm_min
    lengths = np.diff(a.segment_bounds_mm) / (a.travel_mm[1] - a.travel_mm[0])
    for s in machine.heat_sources:
        on_rail = s.kind == "moving" and s.axis == axis
        if s.driver == axis or on_rail:
            cols = list(layout.source_columns(s.name))
            p1 = float(machine.source_power_W(s, factor))
            run[cols] = p1 * lengths if on_rail else p1 / len(cols)
    U = np.vstack([rest, np.repeat(run[None, :], t.size - 1, axis=0)])
    return Loads(t, layout.loads_values(U), layout.columns)


def etve_loads(machine: Machine, hours: float, amplitude_K: float, period_h: float, step_s: float) -> Loads:
    """Loads of the ETVE test: every source at standstill, the air of every zone ``T_ref + A sin(2π t / period)``."""
    if not hours > 0 or not period_h > 0 or not step_s > 0 or not np.isfinite(amplitude_K) or step_s > hours * 3600:
        raise ValueError(f"hours ({hours:g}), period_h ({period_h:g}) and step_s ({step_s:g}) must be positive and "
                         f"the amplitude ({amplitude_K:g} K) finite")
    layout = machine.layout()
    t = np.arange(0.0, hours * 3600 + 0.5 * step_s, step_s)
    U = np.zeros((t.size, layout.n_inputs))
    U[:, :len(layout.heat_inputs)] = standstill_powers(machine)
    U[:, len(layout.heat_inputs):] = amplitude_K * np.sin(2 * np.pi * t / (period_h * 3600))[:, None]
    return Loads(t, layout.loads_values(U), layout.columns)


def feedback_errors_um(model, axis: str, loads: Loads, positions_mm, fields: dict[int, np.ndarray],
                       initial: str = "steady") -> tuple[np.ndarray, np.ndarray | None]:
    """The positioning error an axis' drive adds to the structure [µm] (nt × positions) on a loads time series.

    Also the pre-stretch left [µm] (nt,) for a pre-stretched screw (else None).  The carrier's share (and a linear
    scale's whole error) reads the FE fields ``fields`` (loads row → state, every row) of ``model``; a rotary
    encoder's screw share comes from the screw model started from ``initial`` (:class:`~hybridcomp.fem.drives.DriveError`).
    """
    drive = _require_drive(model.machine, axis)
    if fields is None or len(fields) != loads.time_s.size:
        raise ValueError("a drive's error needs the FE field at every loads row (its carrier's temperature)")
    err = drive_error(model, drive)
    X = np.array([fields[i] for i in range(loads.time_s.size)])
    if err.screw is None:
        return err.error_um(positions_mm, X), None
    T = err.screw.temperature_rise_of_loads(loads, initial)
    left = err.prestretch_left_um(X, T) if drive.mounting == "pre-stretched" else None
    return err.error_um(positions_mm, X, T), left


def structure_along_um(model, axis: str, positions_mm, fields: dict[int, np.ndarray]) -> np.ndarray:
    """The structure's drift along an axis [µm] (nt × positions), TCP minus table, at the axis' positions.

    The other axes at the model's pose; the model's field at every row (``fields``) carried onto the support poses
    and the drift interpolated between them (:func:`hybridcomp.fem.poses.drift_rows_at`).  The table side's point is
    the table reference at every position, as the standard measures (a reflector fixed on the table), also when
    the machine file takes the drift under the tool for the compensation.
    """
    d = model.machine.axis(axis).direction
    R = drift_rows_at(model, [{axis: float(p)} for p in np.atleast_1d(positions_mm)], fixed_target=True)[:, d, :]
    X = np.array([fields[i] for i in range(len(fields))])
    return X @ R.T * 1e6


@dataclass(frozen=True)
class AxisTestResult:
    """A simulated moving-axis test.

    Attributes
    ----------
    axis, feedback : the axis and its feedback kind
    feed_mm_min : the test feed
    targets_mm : target positions [mm]
    time_s : times [s]
    error_um : TCP-minus-table drift along the axis at each target (nt × targets) [µm]
    feedback_um : the error the drive adds to the structure at each target (nt × targets) [µm] (as the drive sees
        it: the feedback's length less the carrier's)
    structure_um : the structure's drift along the axis at each target's pose (nt × targets) [µm]
    prestretch_left_um : pre-stretch left of a pre-stretched screw (nt,) [µm], else None
    """

    axis: str
    feedback: str
    feed_mm_min: float
    targets_mm: np.ndarray
    time_s: np.ndarray
    error_um: np.ndarray
    feedback_um: np.ndarray
    structure_um: np.ndarray
    prestretch_left_um: np.ndarray | None = None

    def summary(self) -> dict:
        """The test's values (module docstring), JSON-ready."""
        return axis_summary(self.time_s, self.targets_mm, self.error_um) | {
            "axis": self.axis, "feedback": self.feedback, "feed_mm_min": self.feed_mm_min,
            "feedback_spread_um": float(np.max(np.ptp(self.feedback_um, axis=1))),
            "structure_change_um": float(np.max(np.abs(self.structure_um - self.structure_um[0]))),
            "prestretch_left_min_um": None if self.prestretch_left_um is None else float(self.prestretch_left_um.min()),
        }


def axis_summary(time_s: np.ndarray, targets_mm: np.ndarray, error_um: np.ndarray) -> dict:
    """Largest change per target, spread over the travel, final slope [µm/m] and the time of steady state [h]."""
    change = error_um - error_um[0]
    final = change[-1]
    inside = np.all(np.abs(change - final) <= STEADY_SHARE * np.maximum(np.abs(final), 1e-9), axis=1)
    # steady from the first time after which every later sample is inside the band
    later_all = np.flip(np.cumprod(np.flip(inside)).astype(bool))
    steady = float(time_s[np.argmax(later_all)] / 3600) if later_all.any() else None
    slope = np.polyfit(np.asarray(targets_mm) * 1e-3, change[-1], 1)[0] if len(targets_mm) > 1 else 0.0
    return {
        "targets_mm": [float(x) for x in targets_mm],
        "max_change_um": [float(x) for x in np.max(np.abs(change), axis=0)],
        "final_change_um": [float(x) for x in final],
        "spread_um": float(np.max(np.ptp(change, axis=1))),
        "final_slope_um_per_m": float(slope),
        "steady_state_h": steady,
        "duration_h": float(time_s[-1] / 3600),
    }


def moving_axis_test(model, axis: str, feed_mm_min: float, targets_mm=None, hours: float = 12.0,
                     step_s: float = 300.0, progress: bool = False) -> AxisTestResult:
    """Simulate the ISO 230-3 moving-axis test of ``axis`` on an FE model (module docstring)."""
    machine = model.machine
    _require_drive(machine, axis)  # before the default targets: names a missing drive
    targets = default_targets_mm(machine, axis) if targets_mm is None else np.asarray(targets_mm, float)
    lo, hi = machine.axis(axis).travel_mm
    if targets.size < 2 or np.any(targets < lo) or np.any(targets > hi):
        raise ValueError(f"targets {targets.tolist()} mm must be two or more positions within the travel of "
                         f"{axis} [{lo:g}, {hi:g}] mm")
    loads = axis_cycle_loads(machine, axis, feed_mm_min, hours, step_s)
    return axis_test_of_loads(model, axis, loads, targets, feed_mm_min, progress)


def axis_test_of_loads(model, axis: str, loads: Loads, targets_mm, feed_mm_min: float = 0.0,
                       progress: bool = False) -> AxisTestResult:
    """:func:`moving_axis_test`'s evaluation on any loads (from the steady state of row 0): the error at each target."""
    machine = model.machine
    drive = _require_drive(machine, axis)
    targets = np.asarray(targets_mm, float)
    res = model.simulate(loads, initial="steady", store_steps=tuple(range(loads.time_s.size)), progress=progress)
    fb, left = feedback_errors_um(model, axis, loads, targets, res.fields_K)
    structure = structure_along_um(model, axis, targets, res.fields_K)
    error = structure + axis_sign(machine, axis) * fb
    return AxisTestResult(axis, drive.feedback, float(feed_mm_min), targets, loads.time_s, error, fb, structure, left)


@dataclass(frozen=True)
class EtveResult:
    """A simulated ETVE test: drift at the model's pose and each drive's axis at its travel ends.

    ``feedback_um`` maps axis → (nt × 2) errors the drive adds at the travel's ends [µm]; ``error_um`` axis →
    (nt × 2) the error along the axis at the travel's ends, TCP minus table (the structure at that pose plus the
    signed added error); ``air_rise_K`` is the air's rise (nt,).
    """

    time_s: np.ndarray
    air_rise_K: np.ndarray
    drift_um: np.ndarray
    feedback_um: dict[str, np.ndarray]
    error_um: dict[str, np.ndarray]

    def summary(self) -> dict:
        """Range of the drift per direction, of each added feedback error and each axis' error at the travel ends."""
        return {
            "duration_h": float(self.time_s[-1] / 3600),
            "air_range_K": float(np.ptp(self.air_rise_K)),
            "drift_range_um": {c: float(np.ptp(self.drift_um[:, j])) for j, c in enumerate("xyz")},
            "feedback_range_um": {a: [float(x) for x in np.ptp(e, axis=0)] for a, e in self.feedback_um.items()},
            "error_range_um": {a: [float(x) for x in np.ptp(e, axis=0)] for a, e in self.error_um.items()},
        }


def etve_test(model, hours: float = 48.0, amplitude_K: float = 2.0, period_h: float = 24.0, step_s: float = 600.0,
              progress: bool = False) -> EtveResult:
    """Simulate the ETVE test on an FE model: at rest, the air swinging, from the steady state at the mean."""
    machine = model.machine
    loads = etve_loads(machine, hours, amplitude_K, period_h, step_s)
    return etve_of_loads(model, loads, progress=progress)


def etve_of_loads(model, loads: Loads, progress: bool = False) -> EtveResult:
    """:func:`etve_test`'s evaluation on any loads with the machine at rest (from the steady state of row 0)."""
    machine = model.machine
    res = model.simulate(loads, initial="steady", store_steps=tuple(range(loads.time_s.size)), progress=progress)
    fb, err = {}, {}
    for d in machine.drives:
        ends = machine.axis(d.axis).travel_mm
        fb[d.axis] = feedback_errors_um(model, d.axis, loads, ends, res.fields_K)[0]
        err[d.axis] = structure_along_um(model, d.axis, ends, res.fields_K) + axis_sign(machine, d.axis) * fb[d.axis]
    air = loads.values[:, len(machine.layout().heat_inputs)] - machine.reference_temperature_degC \
        if machine.zones else np.zeros(loads.time_s.size)
    return EtveResult(loads.time_s, air, res.drift_um, fb, err)


__all__ = ["axis_sign", "axis_cycle_loads", "etve_loads", "moving_axis_test", "etve_test",
           "AxisTestResult", "EtveResult", "feedback_errors_um", "structure_along_um", "default_targets_mm",
           "axis_summary", "etve_of_loads", "axis_test_of_loads"]
