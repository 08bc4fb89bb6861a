"""Make every test run import this checkout's code, installed or not.

``hybridcomp/<package>`` are relative symlinks to the top-level folders, so this checkout's root on ``sys.path``
is all ``import hybridcomp`` needs.  It goes first, ahead of any installed (editable or not) copy, and into
``PYTHONPATH`` for the processes the tests start (daemons, Dask workers, spawned pools).

The tests run with one OpenBLAS thread (unless ``OPENBLAS_NUM_THREADS`` is set), in this process and the ones it
starts: their dense products are small, so a second thread only waits for a core, and on a 2-core machine shared
with other work it stalls both.  Set here, before numpy is imported.  Measured on such a machine beside other
jobs, the fast loop's H2, diagnosis and API tests took 16.7 s of CPU with one thread against 25.5 s with two.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent

if sys.path[:1] != [str(ROOT)]:
    sys.path.insert(0, str(ROOT))
_loaded = sys.modules.get("hybridcomp")
if _loaded is not None and Path(_loaded.__file__).resolve().parent != ROOT / "hybridcomp":
    raise ImportError(f"hybridcomp was imported from {_loaded.__file__} before this checkout's conftest ran ({ROOT})")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
