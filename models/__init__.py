"""Machine definitions: the TOML machine-file format and its validating loader."""

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

__all__ = [
    "Axis", "Body", "HeatSource", "Machine", "MachineFileError", "Material", "Point", "Support", "Zone",
    "bundled_machines", "load_machine", "parse_machine",
]
