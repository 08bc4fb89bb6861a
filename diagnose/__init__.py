"""Diagnosis: what the simulation gets wrong on measured data, the named physical cause, the extended model, the gain.

* :mod:`hybridcomp.diagnose.data` — measured datasets, column maps, training/validation split
* :mod:`hybridcomp.diagnose.metrics` — RMS, P2P, fit %, E_P95(range), cross-correlation, noise level
* :mod:`hybridcomp.diagnose.problem` — the reduced model and the dataset; simulating variants
* :mod:`hybridcomp.diagnose.effects` — the library of named, parametrised model extensions
* :mod:`hybridcomp.diagnose.selection` — bounded least squares and greedy selection (BIC + validation gain)
* :mod:`hybridcomp.diagnose.report` — report.md, plots, summary.json, machine_extended.toml
* :mod:`hybridcomp.diagnose.dataonly` — the same on a dataset alone (a regression compensation model)

```python
from hybridcomp.models import load_machine
from hybridcomp.diagnose import diagnose, prepare_model, read_measured, write_report
machine = load_machine("vmc800")
d = diagnose(machine, read_measured("measured.csv", machine), "0:60%", rom=prepare_model(machine))
write_report(d, "out/")
```
"""

from hybridcomp.diagnose.core import DEFAULT_SPLIT, dataset_from_trace, diagnose, prepare_model, read_measured
from hybridcomp.diagnose.data import Dataset, DatasetError, Split, parse_split, read_column_map, read_dataset
from hybridcomp.diagnose.effects import KINDS, Candidate, library, simulate
from hybridcomp.diagnose.selection import Diagnosis, Fitted

__all__ = [
    "DEFAULT_SPLIT",
    "KINDS",
    "Candidate",
    "Dataset",
    "DatasetError",
    "Diagnosis",
    "Fitted",
    "Split",
    "dataset_from_trace",
    "diagnose",
    "library",
    "parse_split",
    "prepare_model",
    "read_column_map",
    "read_dataset",
    "read_measured",
    "simulate",
    "write_report",
]


def write_report(diagnosis, out_dir, **kwargs):
    """Write ``report.md``, plots, ``summary.json`` and ``machine_extended.toml`` (see :mod:`.report`)."""
    from hybridcomp.diagnose.report import write_report as _write

    return _write(diagnosis, out_dir, **kwargs)
