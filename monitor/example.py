"""The example trace of the monitor walk-through (``hybridcomp monitor example-trace``).

A replay source needs a trace with the sensor columns a control would send. The project makes one: the bundled
job-shop day (``hybridcomp scenario jobshop``), sampled at ``rate_hz``, with the workshop air ``Tamb_degC`` and,
for every sensor of the structure model, the temperature the structure model computes for the day's own loads.
Its sensors are those of a machine exactly like its model: the daemon has nothing to correct, but every part of it
runs. A real machine's record comes from its control (``[source] kind = "opcua"``); a record of a simulated real
machine that differs from the model is what ``hybridcomp monitor scenario`` replays.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from hybridcomp.histogram.bcs import boundary_conditions
from hybridcomp.histogram.gcode import parse_gcode, sample_motion
from hybridcomp.histogram.increments import DEFAULT_INCREMENT_S, increments_from_samples
from hybridcomp.histogram.scenarios import JOBSHOP_HOURS, jobshop_ambient, jobshop_program
from hybridcomp.histogram.trace import AMBIENT, Samples, write_trace
from hybridcomp.safeio import atomic_path

log = logging.getLogger(__name__)


def jobshop_samples(machine, hours: float = JOBSHOP_HOURS, rate_hz: float = 1.0) -> Samples:
    """The first ``hours`` [h] of the bundled job-shop day, sampled at ``rate_hz`` [Hz], with the workshop air.

    Raises
    ------
    ValueError
        ``hours`` not in (0, 16] or ``rate_hz`` not positive
    """
    if not 0.0 < hours <= JOBSHOP_HOURS:
        raise ValueError(f"hours: the job-shop day is {JOBSHOP_HOURS:g} h long, got {hours!r}")
    motion = parse_gcode(jobshop_program(machine), machine, source="jobshop.nc")
    s = sample_motion(motion, rate_hz, {AMBIENT: jobshop_ambient(machine)})
    return s.take(s.time_s <= hours * 3600.0 + 1e-9)


def rom_outputs(machine, rom, samples: Samples, increment_s: float = DEFAULT_INCREMENT_S,
                loads_edit=None) -> tuple[np.ndarray, np.ndarray]:
    """Sensor temperatures [°C] and drift [µm] at the sample times of a trace: the structure model on its own BCs.

    The BCs are the histogram generator's, per ``increment_s`` [s] (``loads_edit(loads)`` may change them);
    the ROM steps each increment with its loads row held constant (row k+1 over increment k, the reading of a
    mean power per increment) and the outputs are interpolated linearly to the sample times.
    """
    loads = boundary_conditions(machine, increments_from_samples(machine, samples, increment_s))
    if loads_edit is not None:
        loads = loads_edit(loads)
    res = rom.simulate(loads, hold="step")
    at = lambda Y: np.column_stack([np.interp(samples.time_s, loads.time_s, Y[:, j]) for j in range(Y.shape[1])])  # noqa: E731
    return at(res.sensors_degC), at(res.drift_um)


def model_sensors_degC(machine, rom, s: Samples, increment_s: float = DEFAULT_INCREMENT_S) -> np.ndarray:
    """Sensor temperatures [°C] at the sample times (samples × sensors of the model): :func:`rom_outputs`."""
    return rom_outputs(machine, rom, s, increment_s)[0]


def write_example_trace(path: str | Path, machine, rom, hours: float = JOBSHOP_HOURS,
                        rate_hz: float = 1.0) -> Path:
    """Write the walk-through's replay trace: :func:`jobshop_samples` plus :func:`model_sensors_degC`.

    Parameters
    ----------
    path : trace CSV to write (atomically)
    machine : the machine the structure model was reduced from
    rom : the structure model (:class:`hybridcomp.rom.ReducedModel` of ``machine``)
    hours : length of the trace, from the start of the day [h]
    rate_hz : sampling rate [Hz]

    Returns
    -------
    the path written; columns ``time_s``, the axis positions, ``spindle_rpm``, ``Tamb_degC`` and one
    ``<sensor>_degC`` per sensor of the model
    """
    path = Path(path)
    s = jobshop_samples(machine, hours, rate_hz)
    T = model_sensors_degC(machine, rom, s)
    names = rom.layout().sensor_columns
    with atomic_path(path) as tmp:
        write_trace(tmp, machine, s)
        lines = tmp.read_text().splitlines()
        with tmp.open("w", newline="") as fh:
            fh.write(",".join([lines[0], *names]) + "\n")
            for line, row in zip(lines[1:], T):
                fh.write(line + "," + ",".join(f"{v:.4f}" for v in row) + "\n")
    log.info("wrote %s: %d samples, %.1f h, sensors %s", path, len(s), hours, ", ".join(names))
    return path
