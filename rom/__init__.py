"""Krylov reduced-order structure model: reduction, the reduced LTI model, exact stepping, save/load.

* :mod:`hybridcomp.rom.krylov` — the parametric system and the greedy block rational Krylov reductor
* :mod:`hybridcomp.rom.reduced` — :class:`ReducedModel` (immutable; exact stepping, steady state, states, files)
* :mod:`hybridcomp.rom.machine` — reduce an FE machine model to a tolerance, checked against FE
* :mod:`hybridcomp.rom.external` — systems exported from other FE codes (.mat, Matrix Market)
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "krylov": ("ExpansionPoint", "Reduction", "ReductionError", "Reductor", "ThermalSystem"),
    "reduced": (
        "ReducedModel", "RomFileError", "RomInputError", "RomState", "load_rom", "load_state", "save_rom",
        "save_state",
    ),
    "machine": ("CheckResult", "inputs_from_columns", "reduce_model", "split_outputs"),
})
