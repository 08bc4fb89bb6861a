"""The ```python blocks of the READMEs run as written, each in a fresh namespace in a temporary folder.

A block the test cannot run says so in an HTML comment on the line before its fence (invisible on the
rendered page), with the reason:

    <!-- snippet: skip (needs a running OPC UA server) -->   not run; reported as skipped with the reason
    <!-- snippet: slow -->                                  run with the ``slow`` tests only (more than a few seconds)
"""

from __future__ import annotations

import re
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


@dataclass(frozen=True)
class Snippet:
    """One ```python block: where it is, its code and the directive before it."""

    readme: str
    line: int  # line of the opening fence (1-based)
    code: str
    what: str = ""  # "", "skip" or "slow"
    reason: str = ""

    @property
    def where(self) -> str:
        return f"{self.readme}:{self.line}"


def parse(readme: str) -> list[Snippet]:
    """The python blocks of one README; a malformed or misplaced ``snippet:`` comment is an error."""
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
            if lang in PYTHON:
                indent = len(fence["indent"])
                code = "\n".join(text[indent:] for text in lines[i + 1:end]) + "\n"
                what, reason = directive or ("", "")
                snippets.append(Snippet(readme, i + 1, code, what, reason))
            elif directive:
                raise ValueError(f"{readme}:{i}: a snippet comment before a {lang or 'plain'} block, not a python one")
            directive, i = None, end + 1
            continue
        if directive:
            raise ValueError(f"{readme}:{i}: a snippet comment must be the line just before a ```python fence")
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
        raise ValueError(f"{readme}: the last snippet comment is not followed by a ```python fence")
    return snippets


def params():
    for readme in READMES:
        for s in parse(readme):
            marks = ()
            if s.what == "skip":
                marks = pytest.mark.skip(reason=f"{s.where}: {s.reason}")
            elif s.what == "slow":
                marks = pytest.mark.slow
            yield pytest.param(s, id=s.where, marks=marks)


def test_every_readme_with_python_is_listed():
    found = {p.relative_to(ROOT).as_posix() for p in [ROOT / "README.md", *ROOT.glob("*/README.md")]}
    with_python = {r for r in found if parse(r)}
    assert with_python <= set(READMES), f"add to READMES: {sorted(with_python - set(READMES))}"
    assert set(READMES) <= found, f"listed but missing: {sorted(set(READMES) - found)}"


@pytest.mark.parametrize("snippet", list(params()))
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
