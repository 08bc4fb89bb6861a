"""Krylov reduced-order structure model: reduction, the reduced LTI model, exact stepping, save/load.

* :mod:`hybridcomp.rom.krylov` — the parametric system and the greedy block rational Krylov reductor
* :mod:`hybridcomp.rom.reduced` — :class:`ReducedModel` (immutable; exact stepping, steady state, states, files)
* :mod:`hybridcomp.rom.machine` — reduce an FE machine model to a tolerance, checked against FE
* :mod:`hybridcomp.rom.external` — systems exported from other FE codes (.mat, Matrix Market)
"""

from hybridcomp.rom.krylov import (
    ExpansionPoint,
    Reduction,
    ReductionError,
    Reductor,
    ThermalSystem,
)
from hybridcomp.rom.reduced import (
    ReducedModel,
    RomFileError,
    RomInputError,
    RomState,
    load_rom,
    load_state,
    save_rom,
    save_state,
)
from hybridcomp.rom.machine import CheckResult, inputs_from_columns, reduce_model, split_outputs

__all__ = [
    "CheckResult",
    "ExpansionPoint",
    "ReducedModel",
    "Reduction",
    "ReductionError",
    "Reductor",
    "RomFileError",
    "RomInputError",
    "RomState",
    "ThermalSystem",
    "inputs_from_columns",
    "load_rom",
    "load_state",
    "reduce_model",
    "save_rom",
    "save_state",
    "split_outputs",
]
