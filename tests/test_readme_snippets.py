"""Every example of the READMEs runs as written: the ```python blocks and the ```bash blocks.

Python blocks run each in a fresh namespace in a temporary folder. Shell blocks run each in a fresh copy of the
repository (the files git tracks, as a clone of this commit holds them, with the working tree's edits), from its
root, under ``bash`` with ``set -eo pipefail`` (any failing command fails the block), with ``hybridcomp`` and
``python`` on ``PATH`` running that copy's code. After a shell block, ``git status`` of the copy must be clean:
whatever a README command writes is ignored by ``.gitignore``.

A shell command must be typable as it stands, so a placeholder fails the test, in every shell block, skipped or
not (comments after ``#`` are not commands):

* ``...`` or ``…`` in a command;
* ``<NAME>``-style angle brackets where a value belongs;
* a value in capitals (``OUT``, ``LOADS_DIR``, ``HOST`` in ``tcp://HOST:8786``): a word of three or more capitals,
  digits and underscores standing as an argument or as a part of one between ``= : / , @``
  (``T1=21.3`` and ``--axis X`` are values; ``HYBRIDCOMP_SOLVER=auto`` names a variable and is fine);
* usage notation for optional arguments: an argument that starts with ``[-`` or ``[--`` (``[--force]``).

A block the test cannot run says so in an HTML comment on the line before its fence (invisible on the
rendered page), with the reason:

    <!-- snippet: skip (needs a running OPC UA server) -->   not run; reported as skipped with the reason
    <!-- snippet: slow -->                                  run with the ``slow`` tests only (more than a few seconds)
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
READMES = (
    "README.md",
    "models/README.md",
    "histogram/README.md",
    "fem/README.md",
    "rom/README.md",
    "chardiag/README.md",
    "monitor/README.md",
    "diagnose/README.md",
)
FENCE = re.compile(r"^(?P<indent>\s*)(?P<ticks>`{3,}|~{3,})\s*(?P<lang>[\w+-]*)")
DIRECTIVE = re.compile(r"^\s*<!--\s*snippet:\s*(?P<what>\S+)\s*(?:\((?P<reason>.*)\))?\s*-->\s*$")
MENTION = re.compile(r"^\s*<!--\s*snippet:")  # a comment line of its own (not one quoted in the text)
PYTHON = {"python", "py", "python3"}
SHELL = {"bash", "sh", "shell"}
SHELL_TIMEOUT_S = 1800.0  # the slowest shell block (a structure model and a day's replay) takes minutes


#: README.md opens with the two set-up commands and nothing before them; they install into the running
#: environment, so the test does not run them: .ci/run runs the second, tests/test_demo.py a shortened demo
SETUP_REASON = "the set-up commands install into the running environment (.ci/run runs the second line)"


@dataclass(frozen=True)
class Snippet:
    """One ```python or ```bash block: where it is, its code and the directive before it."""

    readme: str
    line: int  # line of the opening fence (1-based)
    code: str
    what: str = ""  # "", "skip" or "slow"
    reason: str = ""
    lang: str = "python"  # "python" or "bash"

    @property
    def where(self) -> str:
        return f"{self.readme}:{self.line}"


def parse(readme: str, langs: frozenset[str] | None = None) -> list[Snippet]:
    """The python and shell blocks of one README (``langs``: only these, "python" or "bash");
    a malformed or misplaced ``snippet:`` comment is an error."""
    lines = (ROOT / readme).read_text(encoding="utf-8").splitlines()
    snippets, directive, i = [], None, 0
    while i < len(lines):
        line = lines[i]
        fence = FENCE.match(line)
        if fence:
            ticks, lang = fence["ticks"], fence["lang"].lower()
            end = i + 1
            while end < len(lines) and not lines[end].strip().startswith(ticks):
                end += 1
            if end == len(lines):
                raise ValueError(f"{readme}:{i + 1}: code fence {ticks} is never closed")
            kind = "python" if lang in PYTHON else "bash" if lang in SHELL else None
            if kind:
                indent = len(fence["indent"])
                code = "\n".join(text[indent:] for text in lines[i + 1:end]) + "\n"
                what, reason = directive or (("skip", SETUP_REASON) if (readme, i) == ("README.md", 0) else ("", ""))
                snippets.append(Snippet(readme, i + 1, code, what, reason, kind))
            elif directive:
                raise ValueError(f"{readme}:{i}: a snippet comment before a {lang or 'plain'} block, "
                                 "not a python or bash one")
            directive, i = None, end + 1
            continue
        if directive:
            raise ValueError(f"{readme}:{i}: a snippet comment must be the line just before a ```python or "
                             "```bash fence")
        if MENTION.search(line):
            m = DIRECTIVE.match(line)
            if not m or m["what"] not in ("skip", "slow"):
                raise ValueError(f"{readme}:{i + 1}: expected <!-- snippet: skip (reason) --> or <!-- snippet: slow -->, "
                                 f"got {line.strip()!r}")
            if m["what"] == "skip" and not (m["reason"] or "").strip():
                raise ValueError(f"{readme}:{i + 1}: a skipped snippet says why: <!-- snippet: skip (reason) -->")
            directive = (m["what"], (m["reason"] or "").strip())
        i += 1
    if directive:
        raise ValueError(f"{readme}: the last snippet comment is not followed by a ```python or ```bash fence")
    return [s for s in snippets if langs is None or s.lang in langs]


def params(lang: str):
    """One test per block; a shell block that two READMEs show alike runs once, under its first place."""
    seen = set()
    for readme in READMES:
        for s in parse(readme, frozenset({lang})):
            if lang == "bash" and s.code in seen:
                continue
            seen.add(s.code)
            marks = ()
            if s.what == "skip":
                marks = pytest.mark.skip(reason=f"{s.where}: {s.reason}")
            elif s.what == "slow":
                marks = pytest.mark.slow
            yield pytest.param(s, id=s.where, marks=marks)


def test_every_readme_with_examples_is_listed():
    found = {p.relative_to(ROOT).as_posix() for p in [ROOT / "README.md", *ROOT.glob("*/README.md")]}
    with_examples = {r for r in found if parse(r)}
    assert with_examples <= set(READMES), f"add to READMES: {sorted(with_examples - set(READMES))}"
    assert set(READMES) <= found, f"listed but missing: {sorted(set(READMES) - found)}"


@pytest.mark.parametrize("snippet", list(params("python")))
def test_readme_snippet_runs(snippet: Snippet, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # whatever the snippet writes lands here
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # compiled as the README's own lines, so a traceback points into the README
    source = "\n" * snippet.line + snippet.code
    code = compile(source, str(ROOT / snippet.readme), "exec")
    namespace = {"__name__": "__readme__"}
    failure = None
    try:
        exec(code, namespace)
    except Exception as exc:  # noqa: BLE001 - whatever a snippet raises is its failure, reported below
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == str(ROOT / snippet.readme)]
        line = frames[-1].lineno if frames else snippet.line
        failure = (f"the python snippet at {snippet.where} failed at {snippet.readme} line {line}: "
                   f"{type(exc).__name__}: {exc}\n\n{traceback.format_exc()}")
    if failure:  # outside the except block: the report is this message alone, not a chain of exceptions
        pytest.fail(failure, pytrace=False)


# ------------------------------------------------------------------------------------------ shell blocks
CAPITALS = re.compile(r"^[A-Z][A-Z0-9_]{2,}$")
ANGLE = re.compile(r"<[A-Za-z_][\w.-]*>")


def commands(snippet: Snippet) -> list[tuple[int, str]]:
    """(README line, command) of a shell block: continuation lines joined, blank and comment lines left out."""
    out, pending, first = [], "", 0
    for k, text in enumerate(snippet.code.splitlines()):
        if not pending:
            first = snippet.line + 1 + k
        if text.rstrip().endswith("\\"):
            pending += text.rstrip()[:-1] + " "
            continue
        command, pending = (pending + text).strip(), ""
        if command and not command.startswith("#"):
            out.append((first, command))
    return out


def placeholders(command: str) -> list[str]:
    """What in a shell command is a placeholder rather than a value (the rules in the module docstring)."""
    try:
        words = shlex.split(command, comments=True)
    except ValueError as exc:
        return [f"not a shell command ({exc})"]
    found = []
    for w in words:
        if "..." in w or "…" in w:
            found.append(f"{w!r} (an ellipsis)")
        elif ANGLE.search(w):
            found.append(f"{w!r} (a <NAME> placeholder)")
        elif w.startswith(("[-", "[--")):
            found.append(f"{w!r} (usage notation for an optional argument)")
        elif any(CAPITALS.match(part) for part in re.split(r"[=:/,@]", w)) and not re.match(r"^[A-Z][A-Z0-9_]*=", w):
            found.append(f"{w!r} (a value in capitals)")
    return found


@pytest.mark.parametrize("snippet", [pytest.param(s, id=s.where) for r in READMES for s in parse(r, frozenset({"bash"}))])
def test_readme_shell_commands_have_no_placeholder(snippet: Snippet):
    bad = [f"{snippet.readme}:{line}: {p}" for line, command in commands(snippet) for p in placeholders(command)]
    assert not bad, "a README command must run as typed; placeholders:\n" + "\n".join(bad)


@pytest.mark.parametrize("command,bad", [
    ("hybridcomp cd eval cds --point T1=21.3,T2=20.8,...,T8=20.1 --cnc 840d", "ellipsis"),
    ("hybridcomp batch run LOADS_DIR --machine vmc800 --out OUT", "capitals"),
    ("hybridcomp batch run cases --scheduler tcp://HOST:8786", "capitals"),
    ("hybridcomp diagnose --data <measured.csv> --out diag/", "<NAME>"),
    ("hybridcomp monitor status --config monitor.toml [--json]", "usage notation"),
    ("hybridcomp iso230 moving-axis --axis X --out iso/   # ... a comment may say anything", None),
    ("HYBRIDCOMP_SOLVER=superlu hybridcomp simulate --pose X=100,Y=-50,Z=0 --out run", None),
])
def test_the_placeholder_rule(command, bad):
    found = placeholders(command)
    assert (bad in " ".join(found)) if bad else not found, found


def fresh_copy(dest: Path) -> Path:
    """The files git tracks, copied from the working tree into ``dest`` (a repository of its own, committed)."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True).stdout
    for name in filter(None, files.decode().split("\0")):
        src, dst = ROOT / name, dest / name
        if not os.path.lexists(src):  # deleted in the working tree, not yet committed
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            os.symlink(os.readlink(src), dst)
        else:
            shutil.copy2(src, dst)
    git = ["git", "-c", "user.name=readme test", "-c", "user.email=readme@test", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "init", "-q"], cwd=dest, check=True)
    subprocess.run([*git, "add", "-A"], cwd=dest, check=True)
    subprocess.run([*git, "commit", "-q", "--no-verify", "-m", "the working tree"], cwd=dest, check=True)
    return dest


def shell_env(clone: Path, bin_dir: Path) -> dict:
    """``hybridcomp`` and ``python`` on PATH, running the code of ``clone``."""
    bin_dir.mkdir()
    for name, cmd in (("hybridcomp", f'exec "{sys.executable}" -m hybridcomp "$@"'),
                      ("python", f'exec "{sys.executable}" "$@"')):
        (bin_dir / name).write_text(f"#!/bin/sh\n{cmd}\n")
        (bin_dir / name).chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}", PYTHONPATH=str(clone),
               MPLBACKEND="Agg")
    env.pop("PYTHONHOME", None)
    return env


def test_the_shell_runs_the_copy(tmp_path):
    clone = fresh_copy(tmp_path / "repo")
    env = shell_env(clone, tmp_path / "bin")
    out = subprocess.run(["bash", "-c", 'python -c "import hybridcomp; print(hybridcomp.__file__)"; '
                          'command -v hybridcomp'], cwd=clone, env=env, capture_output=True, text=True, check=True)
    module, script = out.stdout.split()
    assert Path(module).resolve().is_relative_to(clone.resolve()) and Path(script).parent == tmp_path / "bin"
    assert not left_over(clone)
    (clone / "demo").mkdir()
    (clone / "demo" / "report.md").write_text("ignored")
    (clone / "stray.csv").write_text("not ignored")
    assert left_over(clone) == ["?? stray.csv"]


def left_over(clone: Path) -> list[str]:
    """``git status`` of the copy: files no ``.gitignore`` rule covers, and changed tracked files."""
    return subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=clone, check=True,
                          capture_output=True, text=True).stdout.splitlines()


@pytest.mark.parametrize("snippet", list(params("bash")))
def test_readme_shell_block_runs(snippet: Snippet, tmp_path):
    clone = fresh_copy(tmp_path / "repo")
    env = shell_env(clone, tmp_path / "bin")
    script = "set -eo pipefail\n" + snippet.code
    try:
        res = subprocess.run(["bash", "-x", "-c", script], cwd=clone, env=env, capture_output=True, text=True,
                             timeout=SHELL_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the shell block at {snippet.where} took more than {SHELL_TIMEOUT_S:.0f} s", pytrace=False)
    if res.returncode != 0:
        ran = [line for line in res.stderr.splitlines() if line.startswith("+ ")]
        pytest.fail(f"the shell block at {snippet.where} failed with exit code {res.returncode} at\n"
                    f"  {ran[-1] if ran else '(before the first command)'}\n\nstdout (end):\n{res.stdout[-3000:]}\n"
                    f"stderr (end):\n{res.stderr[-3000:]}", pytrace=False)
    status = left_over(clone)
    assert not status, (f"the shell block at {snippet.where} leaves files that .gitignore does not cover, or changes "
                        "tracked files:\n" + "\n".join(status[:20]))


def test_readme_starts_with_the_two_set_up_commands():
    """The first thing README.md shows is one shell block of two commands: install + demo, install + tests."""
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert lines[0] == "```bash" and lines[3] == "```", lines[:4]
    assert lines[1] == 'pip install -e ".[fast,plot,db]" && hybridcomp demo --out demo'
    assert lines[2] == 'pip install -e ".[test]" && python -m pytest -q'
    first = parse("README.md", frozenset({"bash"}))[0]
    assert (first.line, first.what) == (1, "skip")
