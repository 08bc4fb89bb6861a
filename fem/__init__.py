"""Thermo-elastic finite element model of a machine tool.

* :mod:`hybridcomp.fem.mesh` — the conforming hexahedral mesh of a machine at a pose, or an imported one
* :mod:`hybridcomp.fem.model` — :class:`ThermoElasticModel` (M, K, H_i, B, C and the adjoint drift rows G)
* :mod:`hybridcomp.fem.transient` — θ-method stepping and steady states
* :mod:`hybridcomp.fem.loads` — the loads and outputs CSV files
* :mod:`hybridcomp.fem.export` — VTU/XDMF fields and an off-screen picture
* :mod:`hybridcomp.fem.batch` — load-case batches on a process pool or a Dask cluster
"""

from hybridcomp.fem.loads import LoadsFileError, example_loads, full_power_inputs, read_loads, write_loads, write_outputs
from hybridcomp.fem.mesh import MachineMesh, mesh_machine
from hybridcomp.fem.model import ThermoElasticModel, build_model
from hybridcomp.fem.transient import integrate, simulate, steady_state

__all__ = [
    "LoadsFileError", "MachineMesh", "ThermoElasticModel", "build_model", "example_loads", "full_power_inputs",
    "integrate", "mesh_machine", "read_loads", "simulate", "steady_state", "write_loads", "write_outputs",
]
