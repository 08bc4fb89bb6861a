"""Diagnosis: what the simulation gets wrong on measured data, the named physical cause, the extended model, the gain.

* :mod:`hybridcomp.diagnose.data` — measured datasets, column maps, training/validation split
* :mod:`hybridcomp.diagnose.metrics` — RMS, P2P, fit %, E_P95(range), cross-correlation, noise level
* :mod:`hybridcomp.diagnose.problem` — the reduced model and the dataset; simulating variants
* :mod:`hybridcomp.diagnose.effects` — the library of named, parametrised model extensions
* :mod:`hybridcomp.diagnose.drives` — the feed drives' effects named from drift probed at several poses
* :mod:`hybridcomp.diagnose.reduction` — the reduced model's error for heat anywhere on the surface; an order by it
* :mod:`hybridcomp.diagnose.selection` — bounded least squares and greedy selection (BIC + validation gain)
* :mod:`hybridcomp.diagnose.report` — report.md, plots, summary.json, machine_extended.toml
* :mod:`hybridcomp.diagnose.dataonly` — the same on a dataset alone (a regression compensation model)
* :mod:`hybridcomp.diagnose.regularised` — its regularised families (ridge), chosen stably on the training rows
* :mod:`hybridcomp.diagnose.updating` — post-process updating from sparse probes (gain/offset, coefficients)
* :mod:`hybridcomp.diagnose.datasets` — public measured data sets, fetched and checked (``hybridcomp data fetch``)

```python
from hybridcomp.models import load_machine
from hybridcomp.diagnose import diagnose, prepare_model, read_measured, write_report
machine = load_machine("vmc800")
d = diagnose(machine, read_measured("measured.csv", machine), "0:60%", rom=prepare_model(machine))
write_report(d, "out/")
```
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "core": ("DEFAULT_SPLIT", "dataset_from_trace", "diagnose", "prepare_model", "read_measured"),
    "data": ("Dataset", "DatasetError", "Split", "parse_split", "read_column_map", "read_dataset"),
    "effects": ("KINDS", "Candidate", "library", "predicted_channels"),
    "drives": ("diagnose_drives", "drive_candidates", "read_probes"),
    "reduction": ("SurfaceError", "surface_error", "surface_order"),
    "selection": ("Diagnosis", "Fitted"),
    "report": ("write_report",),
})
