"""The ``hybridcomp`` command: a thin dispatcher to the subcommands beside each package."""

from __future__ import annotations

import argparse
import logging
import sys
import traceback
from importlib import import_module

from hybridcomp import __version__
from hybridcomp.errors import HybridcompError

# subcommand -> module with add_arguments(parser) and run(args) -> int
SUBCOMMANDS = {
    "demo": ("hybridcomp.demo", "the whole hybrid cycle on the bundled demonstrator: CDs, monitor, diagnosis, report"),
    "simulate": ("hybridcomp.rom.cli_simulate", "simulate a load case on the FE model and write outputs.csv"),
    "example-loads": ("hybridcomp.fem.cli_example_loads", "write a reproducible example loads CSV for a machine"),
    "machine": ("hybridcomp.fem.cli_machine", "check a machine file and print its inputs, sensors and mesh size"),
    "histogram": ("hybridcomp.histogram.cli", "turn a trace CSV or G-code into load factors, histograms and a loads CSV"),
    "scenario": ("hybridcomp.histogram.cli_scenario",
                 "write a bundled scenario (basic load cases, job-shop day): G-code, trace, loads"),
    "cd": ("hybridcomp.chardiag.cli", "characteristic diagrams: training data, fit, evaluation, CNC export, database"),
    "table": ("hybridcomp.chardiag.cli_table",
              "the volumetric table of a pose-aware reduced model at one time: CSV, JSON, Siemens 840D K3 or CEC"),
    "reduce": ("hybridcomp.rom.cli_reduce", "reduce a machine's FE model (or exported matrices) to a real-time ROM.npz"),
    "diagnose": ("hybridcomp.diagnose.cli",
                 "diagnose measured data: residuals, named physical causes, extended machine file, gain"),
    "data": ("hybridcomp.diagnose.cli_data", "fetch a public measured data set (the README's real spindle test)"),
    "batch": ("hybridcomp.fem.cli_batch", "run a directory of load cases on the FE model: local process pool or Dask cluster"),
    "iso230": ("hybridcomp.fem.cli_iso230",
               "ISO 230-3 thermal tests, simulated: moving linear axis (feed drives) and ETVE"),
    "verify": ("hybridcomp.cli_verify",
               "the compensation verified as a builder signs it off: calibrations, the ambient, a machined part"),
    "monitor": ("hybridcomp.monitor.cli",
                "the monitoring daemon: run, status, example-config, example-trace, and the hybrid scenario"),
}
# subcommand -> action -> module with add_parser(actions) and run(args) -> int: actions of a package's subcommand
# that compose every package, so they live at the top, not in the package (which imports nothing above itself)
COMPOSED_ACTIONS = {
    "monitor": {"scenario": "hybridcomp.cli_monitor_scenario"},
}


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors carry the one prefix of every hybridcomp error, ``error:``."""

    def error(self, message: str):
        """Print the usage and ``error: <command>: <message>`` to stderr and exit with code 2."""
        self.print_usage(sys.stderr)
        self.exit(2, f"error: {self.prog}: {one_line(message)}\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``hybridcomp`` parser with every subcommand's options (sub-subcommands inherit its :class:`Parser`)."""
    p = Parser(
        prog="hybridcomp",
        description="Hybrid thermal error compensation for machine tools: FE model, reduced structure model, "
        "characteristic diagrams, monitoring and diagnosis.",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                   help="print the version of hybridcomp and exit")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        actions = import_module(module).add_arguments(sp)
        sp.set_defaults(_module=module)
        for action, composed in COMPOSED_ACTIONS.get(name, {}).items():
            import_module(composed).add_parser(actions).set_defaults(_module=composed)
            assert action in actions.choices, (name, action)
    return p


def _given_options(argv: list[str] | None) -> set[str]:
    """The destinations of the options typed on the command line (not filled in from a default).

    The command line is parsed a second time by a parser whose defaults are all suppressed, so only
    what was given lands in the namespace; a subcommand refuses an option that has no effect on its
    path with it (:func:`hybridcomp.models.cli.refuse_unused`).
    """
    parser = build_parser()
    stack = [parser]
    while stack:
        p = stack.pop()
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                stack.extend(action.choices.values())
            elif action.option_strings:
                action.default = argparse.SUPPRESS
    return set(vars(parser.parse_args(argv)))


def one_line(text: str) -> str:
    """``text`` on one line: control characters (a newline in a file name or a value) written as escapes."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def error_message(exc: BaseException) -> str:
    """The message of an expected error, naming the file for an ``OSError`` (``x.csv: No such file or directory``)."""
    if isinstance(exc, OSError) and exc.strerror:
        where = exc.filename if exc.filename is not None else ""
        return f"{where}: {exc.strerror}" if where != "" else exc.strerror
    return str(exc) or type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    """Run the ``hybridcomp`` command line (``argv`` without the program name); returns the exit code.

    A subcommand's error never ends in a traceback: bad input (:class:`~hybridcomp.errors.HybridcompError`,
    ``OSError``, ``ValueError`` including ``UnicodeDecodeError``) prints one line ``error: <message>`` to
    stderr and returns 2; anything else prints ``error: internal error <Type>: <message> (run with -vv for
    the traceback)`` and returns 1.  With ``-vv`` the traceback is printed before that line.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    args._given = _given_options(argv)
    if not args.command:
        parser.print_help()
        return 2
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return import_module(args._module).run(args)
    except (HybridcompError, OSError, ValueError) as exc:
        if args.verbose >= 2:
            traceback.print_exc()
        print(f"error: {one_line(error_message(exc))}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - the one place that turns any failure into a line and an exit code
        if args.verbose >= 2:
            traceback.print_exc()
        hint = "" if args.verbose >= 2 else " (run with -vv for the traceback)"
        print(f"error: internal error {type(exc).__name__}: {one_line(str(exc))}{hint}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
