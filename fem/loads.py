"""The loads CSV and the outputs CSV for fem's callers: :mod:`hybridcomp.models.loads`, re-exported.

The format lives in models because histogram writes it and fem reads it (see DESIGN's data flow).
"""

from hybridcomp.models.loads import (
    Loads,
    LoadsFileError,
    example_loads,
    full_power_inputs,
    in_model_order,
    input_columns,
    read_loads,
    write_loads,
    write_outputs,
)

__all__ = ["Loads", "LoadsFileError", "example_loads", "full_power_inputs", "in_model_order", "input_columns",
           "read_loads", "write_loads", "write_outputs"]
