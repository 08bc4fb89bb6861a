"""Each checkout tests its own code: installed or not, ``hybridcomp`` resolves to the checkout that runs pytest."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import hybridcomp
import hybridcomp.fem

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("models", "fem", "histogram", "rom", "chardiag", "monitor", "diagnose")


def test_this_checkout_is_imported():
    assert Path(hybridcomp.__file__).resolve().parent == ROOT / "hybridcomp"
    # through the relative symlink hybridcomp/fem -> ../fem
    assert Path(hybridcomp.fem.__file__).resolve().parent == ROOT / "fem"


@pytest.mark.slow
def test_a_second_checkout_imports_its_own_code(tmp_path):
    """A copy of the checkout (packages, symlinks, root conftest) runs a test that asserts where its imports come
    from; whatever this checkout installed (an editable install points here) must not leak into it."""
    copy = tmp_path / "second checkout"
    copy.mkdir()
    for name in ("hybridcomp", *PACKAGES):
        shutil.copytree(ROOT / name, copy / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("conftest.py", "pyproject.toml"):
        shutil.copy2(ROOT / name, copy / name)
    assert (copy / "hybridcomp" / "fem").is_symlink()
    (copy / "tests").mkdir()
    (copy / "tests" / "test_where.py").write_text(
        "from pathlib import Path\n"
        "import hybridcomp, hybridcomp.fem.model, hybridcomp.models\n"
        "def test_where():\n"
        "    root = Path(__file__).resolve().parents[1]\n"
        "    assert Path(hybridcomp.__file__).resolve().parent == root / 'hybridcomp'\n"
        "    assert Path(hybridcomp.fem.model.__file__).resolve().parent == root / 'fem'\n"
        "    assert Path(hybridcomp.models.__file__).resolve().parent == root / 'models'\n"
    )
    # nothing of this run's own test processes (pytest-xdist's worker variables) either
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH" and not k.startswith("PYTEST_")}
    # run from the copy and, the harder case, from this checkout (its folder first on sys.path)
    for cwd in (copy, ROOT):
        r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider",
                            str(copy / "tests")],
                           cwd=cwd, env=env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, f"from {cwd}:\n{r.stdout}\n{r.stderr}"


@pytest.mark.parametrize("package", PACKAGES)
def test_a_package_imported_by_its_folder_name_is_refused_with_the_name_to_use(package):
    """From the checkout's root the folder ``fem/`` is importable as ``fem``: a second copy of every module beside
    ``hybridcomp.fem``. The import fails and names ``hybridcomp.fem``; ``hybridcomp.fem`` itself imports."""
    # nothing of this run's own test processes (pytest-xdist's worker variables) either
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH" and not k.startswith("PYTEST_")}
    code = (
        "import importlib, sys\n"
        f"good = importlib.import_module('hybridcomp.{package}')\n"
        "assert good.__name__ == 'hybridcomp.' + sys.argv[1]\n"
        "for name in (sys.argv[1], sys.argv[1] + '.anything'):\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except ImportError as e:\n"
        "        print(type(e).__name__, e)\n"
        "    else:\n"
        "        raise SystemExit(f'{name} imported')\n"
        "    assert name not in sys.modules, sorted(sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, package], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 2
    for line in lines:
        assert line.startswith("ImportError") and f"import hybridcomp.{package}, not {package}" in line
