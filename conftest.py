"""Make every test run import this checkout's code, installed or not.

``hybridcomp/<package>`` are relative symlinks to the top-level folders, so this checkout's root on ``sys.path``
is all ``import hybridcomp`` needs.  It goes first, ahead of any installed (editable or not) copy, and into
``PYTHONPATH`` for the processes the tests start (daemons, Dask workers, spawned pools).
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
os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
