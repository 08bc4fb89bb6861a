"""Fixtures shared by the test modules."""

from __future__ import annotations

import csv

import pytest

from hybridcomp.models import load_machine


@pytest.fixture(scope="session")
def machine():
    """The bundled demonstrator (immutable, so one load serves every test)."""
    return load_machine("vmc800")


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
