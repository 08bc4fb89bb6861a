"""hybridcomp: hybrid thermal error compensation for machine tools.

The core flow in one namespace::

    import hybridcomp as hc

    machine = hc.load_machine("vmc800")
    loads = hc.example_loads(machine)                      # or hc.boundary_conditions(machine, increments)
    model = hc.build_model(machine, element_size_mm=150)   # the FE model at mid travel
    fe = hc.simulate(model, loads)                         # SimulationResult: sensors_degC, drift_um
    rom = hc.reduce_model(model)                           # the structure model
    fast = hc.simulate(rom, loads)                         # the same SimulationResult, in milliseconds

Names are imported from their packages on first use, so ``import hybridcomp`` stays light; each
package (``hybridcomp.models``, ``.histogram``, ``.fem``, ``.rom``, ``.chardiag``, ``.monitor``,
``.diagnose``) exports its own public names too.  Every error hybridcomp raises is a
:class:`HybridcompError` and the built-in exception it is.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from hybridcomp.errors import HybridcompError

if TYPE_CHECKING:
    import numpy as np

    from hybridcomp.models.layout import Loads
    from hybridcomp.models.simulation import SimulationResult

__version__ = "0.1.0"

# public name -> the module that defines it
_EXPORTS = {
    # models: machine files and the input/output vocabulary
    "load_machine": "models.machine", "Machine": "models.machine", "MachineFileError": "models.machine",
    "InputLayout": "models.layout", "Loads": "models.layout", "input_layout": "models.layout",
    "in_model_order": "models.layout", "DIRECTIONS": "models.layout", "DRIFT_COLUMNS": "models.layout",
    "SimulationResult": "models.simulation",
    # histogram: traces and G-code to boundary conditions
    "increments_from_trace": "histogram.increments", "boundary_conditions": "histogram.bcs",
    "Increments": "histogram.increments",
    # fem: the FE model and its files
    "build_model": "fem.model", "ThermoElasticModel": "fem.model", "read_loads": "fem.loads",
    "write_loads": "fem.loads", "write_outputs": "fem.loads", "example_loads": "fem.loads",
    # rom: the structure model
    "reduce_model": "rom.machine", "ReducedModel": "rom.reduced", "save_rom": "rom.reduced", "load_rom": "rom.reduced",
    # chardiag: characteristic diagrams and their database
    "fit_cd_set": "chardiag.fit", "CharDiagram": "chardiag.cd", "CDSet": "chardiag.cd", "read_cd": "chardiag.xmlio",
    "write_cd": "chardiag.xmlio", "simulate_load_cases": "chardiag.training",
    "standard_load_cases": "chardiag.training", "CDDatabase": "chardiag.db",
    # monitor: the daemon
    "load_config": "monitor.config", "Monitor": "monitor.daemon", "run_monitor": "monitor.daemon",
    # diagnose: what the model misses in measured data (the diagnosis itself is hybridcomp.diagnose.diagnose:
    # the name hybridcomp.diagnose is the package)
    "prepare_model": "diagnose.core", "read_measured": "diagnose.core", "write_report": "diagnose.report",
}

__all__ = ["HybridcompError", "__version__", "simulate", *sorted(_EXPORTS)]


def simulate(model, loads: Loads, initial: str | np.ndarray = "steady", **options) -> SimulationResult:
    """Run an FE model or a reduced structure model on a loads time series.

    Parameters
    ----------
    model : a :class:`ThermoElasticModel` (``build_model``) or a machine :class:`ReducedModel` (``reduce_model``)
    loads : heat powers [W] and air temperatures [°C] by loads column (``read_loads``, ``boundary_conditions``)
    initial : ``"steady"`` (steady state of the first loads row), ``"reference"`` (zero rise) or a state
        (``SimulationResult.final_state`` of an earlier run of the same model)
    options : the model's own: ``theta``, ``store_steps``, ``progress`` (FE); ``hold`` (reduced model)

    Returns
    -------
    SimulationResult with sensor temperatures [°C] and TCP drift [µm] at the loads' times
    """
    return model.simulate(loads, initial, **options)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'hybridcomp' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"hybridcomp.{module}"), name)
    globals()[name] = value  # once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
