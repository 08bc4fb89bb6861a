"""hybridcomp.frozen.evolve: the same instances as dataclasses.replace, and what it must not shortcut."""

from __future__ import annotations

import dataclasses
import functools

import pytest

from hybridcomp.frozen import evolve
from hybridcomp.monitor.decisions import SensorState
from hybridcomp.monitor.state import MonitorState


def test_evolve_gives_what_replace_gives_on_the_monitors_states():
    s = MonitorState()
    changes = {"offsets_um": {"dx_um": 1.5, "dy_um": -2.0, "dz_um": 0.25}, "last_time_s": 12.0, "written": True}
    new = evolve(s, **changes)
    assert new == dataclasses.replace(s, **changes)
    assert type(new) is MonitorState and new is not s
    assert s == MonitorState()  # the original is untouched
    with pytest.raises(dataclasses.FrozenInstanceError):
        new.last_time_s = 1.0  # still frozen
    sensor = SensorState()
    assert evolve(sensor, status="degraded", reason="stuck") == dataclasses.replace(sensor, status="degraded",
                                                                                    reason="stuck")
    assert evolve(sensor) == sensor


def test_an_unknown_field_is_refused_naming_it():
    with pytest.raises(TypeError, match="no field offset_um"):
        evolve(MonitorState(), offset_um={})
    with pytest.raises(TypeError):
        evolve(object(), a=1)  # not a dataclass: as dataclasses.replace


@dataclasses.dataclass(frozen=True)
class _Checked:
    a: float
    b: float = 0.0

    def __post_init__(self):
        if self.a < 0:
            raise ValueError("a < 0")


@dataclasses.dataclass(frozen=True)
class _Cached:
    a: float

    @functools.cached_property
    def twice(self):
        return 2 * self.a


@dataclasses.dataclass(frozen=True)
class _Derived:
    a: float
    b: float = dataclasses.field(init=False, default=0.0)


@dataclasses.dataclass(frozen=True, slots=True)
class _Slotted:
    a: float


def test_classes_whose_init_does_more_go_through_replace():
    with pytest.raises(ValueError, match="a < 0"):  # __post_init__ runs
        evolve(_Checked(1.0), a=-1.0)
    c = _Cached(1.0)
    assert c.twice == 2.0
    assert evolve(c, a=3.0).twice == 6.0  # no stale cached value carried over
    with pytest.raises(ValueError):  # an init=False field cannot be given, as with replace
        evolve(_Derived(1.0), b=2.0)
    assert evolve(_Slotted(1.0), a=2.0) == _Slotted(2.0)
