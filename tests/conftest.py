"""Fixtures shared by the test modules.

The demonstrator's coarse FE models and the small reduced model are built once per session and shared by every
module that needs them (they are immutable): a module asks for ``model_150mm``, ``model_200mm`` or ``small_rom``
instead of building its own copy.
"""

from __future__ import annotations

import csv

import pytest
from scripts import load_script

import hybridcomp as hc
from hybridcomp.models import load_machine


@pytest.fixture(scope="session")
def machine():
    """The bundled demonstrator (immutable, so one load serves every test)."""
    return load_machine("vmc800")


@pytest.fixture(scope="session")
def vmc(machine):
    """:func:`machine` under the name the machine-file, drive and pose tests give it."""
    return machine


@pytest.fixture(scope="session")
def model_150mm(machine):
    """The demonstrator's FE model at mid travel on 150 mm elements (about 4,100 nodes)."""
    return hc.build_model(machine, None, 150.0)


@pytest.fixture(scope="session")
def model_200mm(machine):
    """The demonstrator's FE model at mid travel on 200 mm elements (about 1,600 nodes)."""
    return hc.build_model(machine, None, 200.0)


@pytest.fixture(scope="session")
def small_rom(machine, model_200mm):
    """``model_200mm`` reduced to order 40 without its basis, checked on a 1 h example day: the cheap reduced model
    of the tests that need one of the demonstrator but not the reduction tolerance."""
    return hc.reduce_model(model_200mm, order=40, keep_basis=False,
                           check_loads=hc.example_loads(machine, duration_h=1.0, dt_s=600.0))


@pytest.fixture(scope="session")
def pose_roms_200mm(machine, model_200mm):
    """``model_200mm`` reduced to the default tolerance (checked on a 4 h example day) and its pose-aware model over
    the star of support poses, with the drives: an FE model built and reduced at each of six poses (about 10 s), so
    every test that takes it is marked slow; three levels along every axis, seven support poses (the mechanics its
    tests check do not depend on the levels; the default levels, 15 support poses, cost the suite a minute:
    ``tests/test_poses.py`` and ``tests/test_pose_path.py`` build them). (reduced model, pose-aware model)"""
    import numpy as np

    from hybridcomp.rom.poses import reduce_at_poses

    loads = hc.example_loads(machine, 4.0, 300.0)
    rom = hc.reduce_model(model_200mm, check_loads=loads)
    return rom, reduce_at_poses(model_200mm, rom, "star", levels={},
                                input_scale=np.abs(model_200mm.layout().inputs(loads)).max(axis=0))


@pytest.fixture(scope="session")
def pose_rom_200mm(pose_roms_200mm):
    """The pose-aware model of :func:`pose_roms_200mm`."""
    return pose_roms_200mm[1]


@pytest.fixture
def write_csv():
    """Write ``rows`` under ``header`` to ``path`` and return the path."""

    def write(path, header, rows):
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            w.writerows(rows)
        return path

    return write


@pytest.fixture(scope="session")
def benchmark_script():
    """Load a script of ``benchmarks/`` by its name as a module (its functions tested without a subprocess)."""
    return lambda name: load_script(f"benchmarks/{name}.py", f"benchmark_{name}")
