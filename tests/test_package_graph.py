"""The package graph is a tree in data-flow order, and no library module imports a command-line module.

DESIGN's data flow is models → histogram → fem → rom → chardiag → monitor, with diagnose beside: a
package may import the packages before it, never one after it; diagnose (measured data and a model)
may import models, histogram, fem and rom, and no package imports diagnose.  The top-level modules of
``hybridcomp`` are of two kinds: the base every package may use (errors, lazy exports, safe output,
the version, the frozen states' replace) and the composers that use every package (the dispatcher and
its command-line modules, the demo, the scenario harness and its metrics), which no package imports.

Every import counts, wherever it stands: at the top of a module, inside a function (a lazy import is
still a dependency, only a later one) and under ``if TYPE_CHECKING:`` (a type from a later package in a
signature couples the module to that package as much as a call does; only the interpreter skips it).
``import_module("hybridcomp....")`` with a literal name counts too.

A command-line module is one whose name starts with ``cli`` (``cli.py``, ``cli_simulate.py``) and the
``__main__`` module; library modules (every other one) must not import one: what a library needs from a
command-line module belongs in a library module.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ORDER = ("models", "histogram", "fem", "rom", "chardiag", "monitor")
#: a package beside the line and the packages it may import
BESIDE = {"diagnose": ("models", "histogram", "fem", "rom")}
#: top-level modules of hybridcomp every package may import (they import none)
BASE = ("errors", "_lazy", "_version", "_packages", "safeio", "plotaxes", "frozen")
#: top-level modules that compose every package (and the command-line modules, ``cli*``): no package imports them
COMPOSERS = ("__init__", "__main__", "demo", "scenario", "metrics", "verify")
PACKAGES = ORDER + tuple(BESIDE)


def may_import(src: str, dst: str) -> bool:
    """Whether package (or top-level group) ``src`` may import ``dst``."""
    if src == dst or dst == "base":
        return True
    if src == "top":
        return True
    if src == "base" or dst == "top":
        return False
    if src in BESIDE:
        return dst in BESIDE[src]
    if dst in BESIDE:
        return False
    return ORDER.index(dst) < ORDER.index(src)


def modules() -> dict[str, Path]:
    """Every module of the project by dotted name (``hybridcomp.fem.batch``) → its file."""
    out = {}
    files = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))]
    for path in files + sorted((ROOT / "hybridcomp").glob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        parts = parts[1:] if parts[0] == "hybridcomp" else parts
        out[".".join(("hybridcomp", *parts)).removesuffix(".__init__")] = path  # a package is its __init__
    return out


def group(module: str) -> str:
    """The package of a dotted module name, or ``"base"`` / ``"top"`` for the top-level modules."""
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in PACKAGES:
        return parts[1]
    if len(parts) == 1 or parts[1] in COMPOSERS or parts[1].startswith("cli"):
        return "top"  # ``hybridcomp`` itself is its __init__, a composer
    if parts[1] in BASE:
        return "base"
    raise AssertionError(f"top-level module hybridcomp.{parts[1]} is neither base nor a composer: classify it here")


def is_cli(module: str) -> bool:
    return module.rsplit(".", 1)[-1].startswith("cli") or module.endswith("__main__")


def imports(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, imported module) of every import of hybridcomp in a file: top level, in functions, under TYPE_CHECKING."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]  # what ``from .`` means
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            # ``from hybridcomp.fem import batch`` imports the submodule batch when there is one
            found += [(node.lineno, f"{name}.{a.name}") for a in node.names] + [(node.lineno, name)]
        elif (isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append((node.lineno, node.args[0].value))
    return [(line, name) for line, name in found if name == "hybridcomp" or name.startswith("hybridcomp.")]


def violations() -> list[str]:
    mods = modules()
    out = []
    for module, path in mods.items():
        src = group(module)
        where = path.relative_to(ROOT)
        for line, name in imports(module, path):
            parts = name.split(".")
            # the longest module the name starts with: ``hybridcomp.fem.loads.Loads`` → ``hybridcomp.fem.loads``
            target = next(".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in mods)
            dst = group(target)
            if not may_import(src, dst):
                why = "a top-level composer, which no package imports" if dst == "top" else \
                    f"{dst} comes later in the data flow"
                out.append(f"{where}:{line}: {src} imports {target} ({why})")
            elif is_cli(target) and not is_cli(module):
                out.append(f"{where}:{line}: library module {module} imports the command-line module {target}")
    return sorted(set(out))


def test_nothing_imports_upward_and_no_library_module_imports_a_command_line_module():
    bad = violations()
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(("src", "dst", "allowed"), [
    ("fem", "histogram", True), ("histogram", "fem", False), ("rom", "fem", True), ("fem", "rom", False),
    ("monitor", "chardiag", True), ("diagnose", "rom", True), ("diagnose", "chardiag", False),
    ("monitor", "diagnose", False), ("monitor", "top", False), ("models", "base", True), ("top", "monitor", True),
    ("base", "models", False),
])
def test_the_rule(src, dst, allowed):
    assert may_import(src, dst) is allowed


def test_the_parser_sees_imports_in_functions_type_checking_blocks_and_import_module(tmp_path):
    path = tmp_path / "m.py"
    path.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from hybridcomp.rom import load_rom\n"
                    "def f():\n    import hybridcomp.monitor.daemon\n    from . import cli_simulate\n"
                    "    return import_module('hybridcomp.scenario')\n", encoding="utf-8")
    names = {name for _, name in imports("hybridcomp.fem.m", path)}
    assert {"hybridcomp.rom.load_rom", "hybridcomp.monitor.daemon", "hybridcomp.fem.cli_simulate",
            "hybridcomp.scenario"} <= names
