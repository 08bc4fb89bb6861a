"""Thermo-elastic finite element model of a machine tool.

* :mod:`hybridcomp.fem.mesh` — the conforming hexahedral mesh of a machine at a pose, or an imported one
* :mod:`hybridcomp.fem.model` — :class:`ThermoElasticModel` (M, K, H_i, B, C and the adjoint drift rows G)
* :mod:`hybridcomp.fem.stepping` — the time schemes behind ``model.simulate(loads, scheme=...)`` (TR-BDF2 to a
  tolerance, the θ-method) and steady states
* :mod:`hybridcomp.fem.loads` — the loads and outputs CSV files
* :mod:`hybridcomp.fem.export` — VTU/XDMF fields and an off-screen picture
* :mod:`hybridcomp.fem.batch` — load-case batches on a process pool or a Dask cluster
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "loads": ("LoadsFileError", "example_loads", "full_power_inputs", "read_loads", "write_loads", "write_outputs"),
    "mesh": ("MachineMesh", "mesh_machine"),
    "model": ("ThermoElasticModel", "build_model"),
    "stepping": (
        "DEFAULT_SCHEME", "DEFAULT_TOLERANCE", "SCHEMES", "TimeTolerance", "integrate_inputs", "integrate_theta",
        "integrate_trbdf2", "steady_state",
    ),
})
