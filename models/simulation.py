"""What every simulation returns, FE or reduced, and how it starts.

Both model types, the assembled FE model (:class:`hybridcomp.fem.model.ThermoElasticModel`) and the
reduced structure model (:class:`hybridcomp.rom.reduced.ReducedModel`), run
``model.simulate(loads, initial) -> SimulationResult`` (and :func:`hybridcomp.simulate` does the same
for either); their array-level integrators take the initial state through :func:`initial_state`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hybridcomp.models.layout import DRIFT_COLUMNS, temperature_column

INITIAL_STATES = ("steady", "reference")


@dataclass(frozen=True)
class SimulationResult:
    """Outputs of a transient run, in boundary units.

    Attributes
    ----------
    time_s : output times [s]
    sensors_degC : sensor temperatures (nt × s) [°C]
    drift_um : TCP-minus-table drift dx, dy, dz (nt × 3) [µm]
    fields_K : temperature rise over the reference at the stored steps {step: (n,)} [K] (FE only)
    timings_s : factorisation and stepping wall times [s]
    sensor_names : the sensors, in column order of ``sensors_degC``
    final_state : the model's state at the last time (FE: temperature rise per node [K]; reduced model:
        reduced coordinates), to continue from with ``initial=``; None where the model does not keep it
    time_error : the estimated time-discretisation error of an FE run and its tolerance, None if not estimated
    """

    time_s: np.ndarray
    sensors_degC: np.ndarray
    drift_um: np.ndarray
    fields_K: dict[int, np.ndarray] = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    sensor_names: tuple[str, ...] = ()
    final_state: np.ndarray | None = None
    time_error: dict | None = None

    def columns(self) -> dict[str, np.ndarray]:
        """The outputs-CSV columns: ``time_s``, ``<sensor>_degC`` …, ``dx_um``, ``dy_um``, ``dz_um``."""
        names = self.sensor_names or tuple(f"T{j + 1}" for j in range(self.sensors_degC.shape[1]))
        cols = {"time_s": self.time_s}
        cols |= {temperature_column(s): self.sensors_degC[:, j] for j, s in enumerate(names)}
        cols |= {d: self.drift_um[:, j] for j, d in enumerate(DRIFT_COLUMNS)}
        return cols


def initial_state(initial: str | np.ndarray, n: int, steady: Callable[[], np.ndarray]) -> np.ndarray:
    """The initial state of a run.

    ``"steady"`` (``steady()``, the steady state of the first inputs), ``"reference"`` (zero rise) or a state
    vector of ``n`` entries [K or reduced coordinates].

    Raises
    ------
    ValueError
        an unknown name or a state of the wrong size (names the value)
    """
    if isinstance(initial, str):
        if initial == "steady":
            return steady()
        if initial == "reference":
            return np.zeros(n)
        raise ValueError(f"initial must be one of {INITIAL_STATES} or a state vector, got {initial!r}")
    x = np.asarray(initial, float)
    if x.shape != (n,):
        raise ValueError(f"initial state must have {n} entries, got shape {x.shape}")
    return x
