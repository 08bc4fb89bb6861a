"""One BLAS thread around small dense work: reduced-model fits, the H2 optimisation.

Their products are small (r × r, N × r), so BLAS threads only wait. Measured on the 2-core
development machine: a greedy diagnosis selection took 4.5 s with one OpenBLAS thread and 180 s
with the default two, and the H2 tests 10 s against 266 s (threads spinning after every small
product starve each other; the FE time loop avoids dense BLAS for the same reason). numpy and
scipy wheels bundle OpenBLAS under ``numpy.libs`` / ``scipy.libs``; their ``*_set_num_threads``
entry points are called through ctypes (what threadpoolctl does), and the previous count is
restored afterwards.  cvxopt's wheel bundles a third OpenBLAS under ``cvxopt.libs`` (used by its
CHOLMOD, the sparse solver of the ``fast`` extra); it is built single-threaded, so limiting it
changes nothing today, but it is included once cvxopt has been imported (never imported here).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import logging
import os
import sys

log = logging.getLogger(__name__)

_SET = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads64_",
        "openblas_set_num_threads")
_GET = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads", "openblas_get_num_threads64_",
        "openblas_get_num_threads")


@functools.cache
def _package_libraries(pkg: str) -> tuple:
    """The OpenBLAS libraries a wheel bundles under ``<pkg>.libs`` (loaded once per package)."""
    try:
        mod = __import__(pkg)
    except ImportError:  # pragma: no cover
        return ()
    libs = []
    root = os.path.join(os.path.dirname(mod.__file__), os.pardir, f"{pkg}.libs")
    for path in glob.glob(os.path.join(root, "*openblas*")):
        try:
            libs.append(ctypes.CDLL(path))
        except OSError:
            continue
    return tuple(libs)


def _libraries() -> tuple:
    """The OpenBLAS of numpy and scipy, and cvxopt's when cvxopt is already imported."""
    pkgs = ["numpy", "scipy"] + (["cvxopt"] if "cvxopt" in sys.modules else [])
    return tuple(lib for pkg in pkgs for lib in _package_libraries(pkg))


def _calls(lib):
    s = next((getattr(lib, n) for n in _SET if hasattr(lib, n)), None)
    g = next((getattr(lib, n) for n in _GET if hasattr(lib, n)), None)
    return s, g


@contextlib.contextmanager
def single_blas_thread():
    """Run the block with one OpenBLAS thread (no effect where the library is not found)."""
    restore = []
    for lib in _libraries():
        s, g = _calls(lib)
        if s is None or g is None:
            continue
        try:
            restore.append((s, int(g())))
            s(1)
        except Exception as exc:  # noqa: BLE001 - a foreign BLAS build may fail in any way; limiting threads is optional
            log.debug("could not limit BLAS threads: %s", exc)
    try:
        yield
    finally:
        for s, n in restore:
            s(n)
