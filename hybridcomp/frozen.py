"""``dataclasses.replace`` for the monitor's frozen states, at the cost of a dictionary copy.

The monitor's transitions (:mod:`hybridcomp.monitor.transitions`) replace a frozen state of some fifty fields
several times per reading; :func:`dataclasses.replace` reads every field and calls ``__init__``, which sets each
one through ``object.__setattr__``: about half of a replayed day's time went there (a 6 h demo day, two daemons,
86,400 readings: 3.7 million calls, 55 of 213 s under the profiler). :func:`evolve` copies the instance's
dictionary and sets the changed fields in the copy. It is the same as :func:`dataclasses.replace` for a class
whose ``__init__`` only stores its fields (no ``__post_init__``, no ``init=False`` field, no ``__slots__``) and
whose instances keep nothing else in their dictionary (no ``functools.cached_property``, whose value a copy would
carry to changed fields); any other class goes to :func:`dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
import functools

_FIELDS: dict[type, frozenset[str] | None] = {}


def _plain_fields(cls: type) -> frozenset[str] | None:
    """The field names of ``cls`` when its instances hold its fields alone, set by ``__init__`` as given, else None."""
    if not dataclasses.is_dataclass(cls) or hasattr(cls, "__slots__") or hasattr(cls, "__post_init__"):
        return None
    fields = dataclasses.fields(cls)
    cached = any(isinstance(v, functools.cached_property) for c in cls.__mro__ for v in vars(c).values())
    if cached or any(not f.init for f in fields):
        return None
    return frozenset(f.name for f in fields)


def evolve(obj, /, **changes):
    """``obj`` with ``changes`` (field name → new value), as :func:`dataclasses.replace` returns it.

    Raises
    ------
    TypeError
        ``obj`` is not a dataclass instance, or a name in ``changes`` is not one of its fields.
    """
    cls = type(obj)
    try:
        names = _FIELDS[cls]
    except KeyError:
        names = _FIELDS[cls] = _plain_fields(cls)
    if names is None:
        return dataclasses.replace(obj, **changes)
    unknown = changes.keys() - names
    if unknown:
        raise TypeError(f"{cls.__name__} has no field {', '.join(sorted(unknown))}")
    new = object.__new__(cls)
    d = new.__dict__
    d.update(obj.__dict__)
    d.update(changes)
    return new
