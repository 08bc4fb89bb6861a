"""Machine definitions: the TOML machine-file format and its validating loader, and the one vocabulary of a
machine model's inputs and outputs (:mod:`hybridcomp.models.layout`) and results (:mod:`hybridcomp.models.simulation`)."""

from hybridcomp.models.layout import (
    COORDINATES,
    DIRECTIONS,
    DRIFT_COLUMNS,
    DRIFT_OUTPUTS,
    InputLayout,
    Loads,
    LoadsColumnError,
    heat_input_name,
    in_model_order,
    input_layout,
)
from hybridcomp.models.machine import (
    Axis,
    Body,
    HeatSource,
    Machine,
    MachineFileError,
    Material,
    Point,
    Support,
    Zone,
    bundled_machines,
    load_machine,
    parse_machine,
)
from hybridcomp.models.simulation import SimulationResult, initial_state

__all__ = [
    "COORDINATES", "DIRECTIONS", "DRIFT_COLUMNS", "DRIFT_OUTPUTS", "InputLayout", "Loads", "LoadsColumnError",
    "SimulationResult", "heat_input_name", "in_model_order", "initial_state", "input_layout",
    "Axis", "Body", "HeatSource", "Machine", "MachineFileError", "Material", "Point", "Support", "Zone",
    "bundled_machines", "load_machine", "parse_machine",
]
