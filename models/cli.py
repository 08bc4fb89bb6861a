"""Command-line pieces every subcommand that loads a machine shares: ``--machine``, options given or refused.

The ``hybridcomp machine`` subcommand itself meshes, so it lives in :mod:`hybridcomp.fem.cli_machine`.
"""

from __future__ import annotations

import argparse


def add_machine_argument(p: argparse.ArgumentParser) -> None:
    """The ``--machine NAME_OR_PATH`` option every subcommand that loads a machine shares."""
    p.add_argument("--machine", default="vmc800", help="bundled machine name or path to a machine TOML (default: vmc800)")


def given(args: argparse.Namespace, dest: str) -> bool:
    """Whether the option with destination ``dest`` was typed on the command line (not a default)."""
    return dest in getattr(args, "_given", ())


def refuse_unused(args: argparse.Namespace, rules) -> str | None:
    """The message for the first option given on a path where it has no effect, or None.

    ``rules`` are ``(dest, unused, why)``: the option with destination ``dest`` has no effect when
    ``unused`` is true, and ``why`` says so, e.g. ``("basis", args.matrices is not None, "applies to
    a machine's FE model only, not to --matrices")``.  Options are named as typed (``--basis``).
    """
    for dest, unused, why in rules:
        if unused and given(args, dest):
            return f"--{dest.replace('_', '-')} {why}"
    return None
