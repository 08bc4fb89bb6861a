"""One name per package: ``hybridcomp.fem``, never ``fem``.

The packages live in top-level folders (``fem/``, ``rom/``, ...) that ``hybridcomp/<package>`` links to, so from
the repository root ``import fem.model`` would find them too and load a second copy of every module beside
``hybridcomp.fem.model``: two classes of the same name, two module states, ``isinstance`` failing across them.
Each package's ``__init__`` calls :func:`refuse_top_level_import` with its ``__name__`` first.
"""

from __future__ import annotations

PREFIX = "hybridcomp."


def refuse_top_level_import(name: str) -> None:
    """Raise unless the package is imported as ``hybridcomp.<package>``.

    Parameters
    ----------
    name : the package's ``__name__`` (``"hybridcomp.fem"``; ``"fem"`` is refused)

    Raises
    ------
    ImportError
        When ``name`` is not under ``hybridcomp.``; the message says what to import instead.  The built-in itself:
        a failed import, not bad input (no :class:`~hybridcomp.errors.HybridcompError`).
    """
    if not name.startswith(PREFIX):
        raise ImportError(
            f"import hybridcomp.{name}, not {name}: the folder {name}/ is the package hybridcomp.{name}, and "
            f"importing it as {name!r} would load a second copy of its modules beside hybridcomp.{name}"
        )
