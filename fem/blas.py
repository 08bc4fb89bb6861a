"""One BLAS thread around small dense work: reduced-model fits, the H2 optimisation.

Their products are small (r × r, N × r), so BLAS threads only wait. Measured on the 2-core
development machine: a greedy diagnosis selection took 4.5 s with one OpenBLAS thread and 180 s
with the default two, and the H2 tests 10 s against 266 s (threads spinning after every small
product starve each other; the FE time loop avoids dense BLAS for the same reason). numpy and
scipy wheels bundle OpenBLAS under ``numpy.libs`` / ``scipy.libs``; their ``*_set_num_threads``
entry points are called through ctypes (what threadpoolctl does), and the previous count is
restored afterwards.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import logging
import os

log = logging.getLogger(__name__)

_SET = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads64_",
        "openblas_set_num_threads")
_GET = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads", "openblas_get_num_threads64_",
        "openblas_get_num_threads")


@functools.lru_cache(maxsize=1)
def _libraries() -> tuple:
    libs = []
    for pkg in ("numpy", "scipy"):
        try:
            mod = __import__(pkg)
        except ImportError:  # pragma: no cover
            continue
        root = os.path.join(os.path.dirname(mod.__file__), os.pardir, f"{pkg}.libs")
        for path in glob.glob(os.path.join(root, "*openblas*")):
            try:
                libs.append(ctypes.CDLL(path))
            except OSError:
                continue
    return tuple(libs)


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
        except Exception as exc:  # pragma: no cover - a foreign BLAS build
            log.debug("could not limit BLAS threads: %s", exc)
    try:
        yield
    finally:
        for s, n in restore:
            s(n)
