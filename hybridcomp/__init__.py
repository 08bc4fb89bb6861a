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

from typing import TYPE_CHECKING

from hybridcomp._lazy import lazy_exports
from hybridcomp._version import __version__
from hybridcomp.errors import HybridcompError

if TYPE_CHECKING:
    import numpy as np

    from hybridcomp.models.layout import Loads
    from hybridcomp.models.simulation import SimulationResult


# module -> the public names it defines (imported on first use)
_names, __getattr__, __dir__ = lazy_exports(__name__, {
    # models: machine files and the input/output vocabulary
    "models.machine": ("Machine", "MachineFileError"),
    "models.loader": ("load_machine",),
    "models.layout": ("InputLayout", "Loads", "input_layout", "in_model_order", "DIRECTIONS", "DRIFT_COLUMNS"),
    "models.simulation": ("SimulationResult",),
    # histogram: traces and G-code to boundary conditions
    "histogram.increments": ("increments_from_trace", "Increments"),
    "histogram.bcs": ("boundary_conditions",),
    # fem: the FE model and its files
    "fem.model": ("build_model", "ThermoElasticModel"),
    "fem.loads": ("read_loads", "write_loads", "write_outputs", "example_loads"),
    "fem.drives": ("build_screw",),
    "fem.iso230": ("moving_axis_test", "etve_test"),
    # rom: the structure model
    "rom.machine": ("reduce_model",),
    "rom.reduced": ("ReducedModel", "save_rom", "load_rom"),
    # chardiag: characteristic diagrams and their database
    "chardiag.fit": ("fit_cd_set",),
    "chardiag.cd": ("CharDiagram", "CDSet"),
    "chardiag.xmlio": ("read_cd", "write_cd"),
    "chardiag.training": ("simulate_load_cases", "standard_load_cases"),
    "chardiag.db": ("CDDatabase",),
    # monitor: the daemon
    "monitor.config": ("load_config",),
    "monitor.daemon": ("Monitor", "run_monitor"),
    # diagnose: what the model misses in measured data (the diagnosis itself is hybridcomp.diagnose.diagnose:
    # the name hybridcomp.diagnose is the package)
    "diagnose.core": ("prepare_model", "read_measured"),
    "diagnose.report": ("write_report",),
})

__all__ = ["HybridcompError", "__version__", "simulate", *_names]


def simulate(model, loads: Loads, initial: str | np.ndarray = "steady", **options) -> SimulationResult:
    """Run an FE model or a reduced structure model on a loads time series.

    Parameters
    ----------
    model : a :class:`ThermoElasticModel` (``build_model``) or a machine :class:`ReducedModel` (``reduce_model``)
    loads : heat powers [W] and air temperatures [°C] by loads column (``read_loads``, ``boundary_conditions``)
    initial : ``"steady"`` (steady state of the first loads row), ``"reference"`` (zero rise) or a state
        (``SimulationResult.final_state`` of an earlier run of the same model)
    options : the model's own: ``scheme`` (FE: ``"trbdf2"`` to a tolerance, the default, or ``"theta"``; reduced
        model: ``"exact"``), ``theta``, ``tolerance``, ``store_steps``, ``progress`` (FE); ``hold`` (reduced model)

    Returns
    -------
    SimulationResult with sensor temperatures [°C] and TCP drift [µm] at the loads' times
    """
    return model.simulate(loads, initial, **options)
