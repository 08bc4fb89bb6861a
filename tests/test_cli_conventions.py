"""Conventions every ``hybridcomp`` option keeps, checked on the parser itself so a new option cannot break them.

One spelling per concept: hours end in ``-hours`` (``--day-hours``, ``--heat-hours``), never ``-h``; every option
says what it does; ``--scheduler`` means the same wherever it appears; an error is one line starting ``error:``;
``hybridcomp --version`` prints the package's version.
"""

from __future__ import annotations

import argparse
import re
import tomllib
from pathlib import Path

import pytest

import hybridcomp
from hybridcomp.cli import SUBCOMMANDS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, action) of every option and positional of ``parser`` and all its sub-subcommands."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, (*path, name))
        else:
            yield path, action


OPTIONS = [(" ".join(path), a) for path, a in walk(build_parser()) if a.option_strings]


def test_the_walk_reaches_every_subcommand_and_its_actions():
    commands = {path.split(" ")[0] for path, _ in OPTIONS if path}
    assert commands == set(SUBCOMMANDS)
    assert {"cd train-data", "cd db search", "batch run", "iso230 etve", "monitor scenario"} <= {p for p, _ in OPTIONS}


@pytest.mark.parametrize("path,action", OPTIONS, ids=[f"{p} {a.option_strings[-1]}" for p, a in OPTIONS])
def test_every_option_has_help_and_spells_hours_one_way(path, action):
    assert action.help and action.help != argparse.SUPPRESS, f"{path} {action.option_strings}: no help text"
    for opt in action.option_strings:
        if opt in ("-h", "--help"):
            continue
        assert not re.search(r"-(h|hr|hrs|hour)$", opt), f"{path} {opt}: hours are spelled -hours"
        if "[h]" in action.help:
            assert opt.startswith("-") and opt.endswith("hours"), f"{path} {opt} takes hours: name it ...-hours"


def test_scheduler_means_one_thing_wherever_it_appears():
    from hybridcomp.fem.cli_batch import SCHEDULER_HELP, WORKERS_HELP

    found = {path: a for path, a in OPTIONS if "--scheduler" in a.option_strings}
    assert set(found) == {"batch run", "cd train-data", "reduce"}
    for path, a in found.items():
        assert a.default == "serial" and a.help.endswith(SCHEDULER_HELP), path
    for path, a in OPTIONS:
        if "--workers" in a.option_strings:
            assert path in found and a.help.endswith(WORKERS_HELP), path


def test_version_prints_the_package_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"hybridcomp {hybridcomp.__version__}"
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["version"] == hybridcomp.__version__


def test_errors_carry_one_prefix():
    # a subcommand's own error lines start "error: " (as hybridcomp.cli.main prints them), never "hybridcomp <cmd>: "
    own = re.compile(r"""print\(f?["']hybridcomp[ a-z-]*:""")
    offenders = [f"{p.relative_to(ROOT)}:{n}" for p in ROOT.glob("*/*.py") if p.parent.name != "tests"
                 for n, line in enumerate(p.read_text().splitlines(), 1) if own.search(line)]
    assert not offenders, offenders


def test_an_error_of_a_subcommand_is_one_line_starting_error(tmp_path, capsys):
    out = tmp_path / "s"
    rc = main(["monitor", "scenario", "--out", str(out), "--disturbance", "no such thing"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: --disturbance") and err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("argv", [
    ["batch", "run", "{d}"],
    ["cd", "train-data", "--cases", "basic"],
    ["reduce", "--poses", "star"],
], ids=["batch run", "cd train-data", "reduce --poses"])
def test_a_scheduler_outside_its_meaning_is_refused_the_same_way_everywhere(tmp_path, capsys, argv):
    out = tmp_path / "out"
    rc = main([a.format(d=tmp_path) for a in argv] + ["--scheduler", "udp://x", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: --scheduler 'udp://x': use serial, process, local") and \
        err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("argv", [["histogram", "t.csv", "--plot"], ["cd", "db", "show"], ["no-such-command"],
                                  ["monitor", "scenario", "--day-hours", "six"]])
def test_a_usage_error_ends_in_one_line_starting_error(capsys, argv):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    last = capsys.readouterr().err.rstrip("\n").splitlines()[-1]
    assert last.startswith("error: hybridcomp"), last
