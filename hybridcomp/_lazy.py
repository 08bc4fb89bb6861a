"""Public names of a package, imported from their modules on first use.

``import hybridcomp.monitor`` must not import scipy.signal, scikit-fem and SQLAlchemy before the daemon has read
its configuration: a package's ``__init__`` declares which module defines each public name, and the module is
imported when the name is first looked up (PEP 562).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping


def lazy_exports(package: str, table: Mapping[str, tuple[str, ...]]) -> tuple[list[str], Callable, Callable]:
    """``__all__``, ``__getattr__`` and ``__dir__`` for a package.

    Parameters
    ----------
    package : the package's ``__name__``
    table : module, relative to the package (``"layout"``, ``"fem.model"``) -> the public names it defines
    """
    where = {name: module for module, names in table.items() for name in names}
    if len(where) != sum(len(n) for n in table.values()):
        raise ValueError(f"{package}: a public name is exported from two modules")

    def __getattr__(name: str):
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # once
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return sorted(where), __getattr__, __dir__
