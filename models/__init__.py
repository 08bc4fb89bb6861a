"""Machine definitions and the one vocabulary of a machine model's inputs, outputs and results.

The typed machine definitions (:mod:`hybridcomp.models.machine`), the TOML machine-file loader
(:mod:`hybridcomp.models.loader`) and its geometry checks (:mod:`hybridcomp.models.geometry`), the inputs and
outputs (:mod:`hybridcomp.models.layout`) and the results (:mod:`hybridcomp.models.simulation`).
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "layout": (
        "COORDINATES", "DIRECTIONS", "DRIFT_COLUMNS", "DRIFT_OUTPUTS", "InputLayout", "Loads", "LoadsColumnError",
        "OutputLayout", "OutputLayoutError", "heat_input_name", "in_model_order", "input_layout", "output_layout",
    ),
    "machine": ("Axis", "Body", "HeatSource", "Machine", "MachineFileError", "Material", "Point", "Support", "Zone"),
    "loader": ("bundled_machines", "load_machine", "parse_machine"),
    "simulation": ("SimulationResult", "initial_state"),
})
