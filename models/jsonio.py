"""Strict JSON for every file, line and database payload the project writes.

JSON has no NaN or infinity; Python's ``json`` writes them as the bare words
``NaN`` and ``Infinity`` that strict parsers (browsers, ``jq``, PostgreSQL's
``json``) reject.  :func:`jsonable` turns every non-finite number into
``null`` (and NumPy scalars and arrays into plain numbers and lists), and
:func:`dumps` writes with ``allow_nan=False``, so a non-finite number that got
past it is an error, never a file no one else can read.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np


def jsonable(obj: Any) -> Any:
    """``obj`` with every non-finite float as None, recursively.

    NumPy scalars and arrays become Python numbers and lists, tuples lists; anything else is unchanged.
    """
    if isinstance(obj, bool) or obj is None or isinstance(obj, (str, int)):
        return obj
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, Mapping):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    return obj


def dumps(obj: Any, **kwargs) -> str:
    """Strict JSON text of ``obj`` (non-finite numbers as null).

    ``kwargs`` as for :func:`json.dumps` (``default`` handles types JSON does not know, e.g. ``default=str`` for
    paths).
    """
    return json.dumps(jsonable(obj), allow_nan=False, **kwargs)


def write_json(path: str | Path, obj: Any, **kwargs) -> Path:
    """Write ``obj`` as strict JSON to ``path``; returns the path."""
    path = Path(path)
    path.write_text(dumps(obj, **kwargs) + "\n")
    return path




def check_versioned(d: Any, fmt: str, version: int, what: str, error: type[Exception]) -> Mapping:
    """``d`` as a mapping of the dict form ``fmt`` at ``version``; else ``error`` saying what it is instead.

    ``what`` names the form in the message (``"volumetric table"``): ``not a volumetric table: format 'x',
    expected '...'`` or ``volumetric table version 2, this program reads 1``.
    """
    if not isinstance(d, Mapping) or d.get("format") != fmt:
        got = d.get("format") if isinstance(d, Mapping) else type(d).__name__
        raise error(f"not a {what}: format {got!r}, expected {fmt!r}")
    if d.get("version") != version:
        raise error(f"{what} version {d.get('version')!r}, this program reads {version}")
    return d


__all__ = ["check_versioned", "dumps", "jsonable", "write_json"]
