"""Output files written like a careful tool: never over an input, never through a link, never half.

Every command that writes files checks its outputs before any work that would be lost to a refusal:

* an output that is the same file as an input is refused, even with ``--force``;
* an output that exists is refused unless ``--force`` is given;
* an output that is a symbolic link, or (inside an output directory) resolves outside it, is refused: writing
  through the link would change a file elsewhere;

and writes each file atomically (:func:`atomic_path`): a temporary file in the same folder, renamed over the
target on success (``os.replace`` replaces a link itself, never its target) and removed on failure, so an
interrupted run leaves the old file or the new one, never a mixture.

A directory output (``simulate --out DIR``) is refused only when it already holds a file the command would
write; running a command again into its own output directory therefore needs ``--force``, and other files in
the directory are never touched.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

from hybridcomp.errors import HybridcompError

FORCE_HELP = "overwrite existing output files"


class OutputPathError(HybridcompError, ValueError):
    """An output path that would overwrite an input or an existing file, or write through a symbolic link."""


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name the same file: :func:`os.path.samefile` when both exist, the resolved paths otherwise."""
    try:
        if os.path.exists(a) and os.path.exists(b):
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


def _inputs(inputs: Iterable) -> list[Path]:
    return [Path(p) for p in inputs if p is not None and str(p) != ""]


def _refuse_input(path: Path, inputs: list[Path], named: str) -> None:
    """``named``: how the message names the output (``"--out PATH"``, ``"--out DIR: DIR/FILE"``)."""
    for inp in inputs:
        if same_file(path, inp):
            raise OutputPathError(f"{named} is the input {inp}: an input is never overwritten (not even with --force)")


def _refuse_link(path: Path, named: str) -> None:
    if path.is_symlink():
        raise OutputPathError(f"{named} is a symbolic link (to {os.readlink(path)}): refusing to write through it; "
                              "remove the link or choose another path")


def check_output_path(path: str | os.PathLike, *, inputs: Iterable = (), force: bool = False,
                      what: str = "--out") -> Path:
    """Check an output file before anything is written; returns it as a :class:`~pathlib.Path`.

    Parameters
    ----------
    path : the file to write
    inputs : the files the command reads (None entries are skipped)
    force : whether an existing file may be overwritten (``--force``)
    what : the option that names the output, for the message

    Raises
    ------
    OutputPathError
        when the output is one of the inputs (even with ``force``), is a symbolic link, is a directory, or exists
        and ``force`` is False; the message names the option and the path.
    """
    path = Path(path)
    _refuse_input(path, _inputs(inputs), f"{what} {path}")
    _refuse_link(path, f"{what} {path}")
    if path.is_dir():
        raise OutputPathError(f"{what} {path} is a directory, not a file")
    if path.exists() and not force:
        raise OutputPathError(f"{what} {path} exists; pass --force to overwrite")
    return path


def check_output_dir(out_dir: str | os.PathLike, file_names: Iterable[str], *, inputs: Iterable = (),
                     force: bool = False, what: str = "--out") -> Path:
    """Check the files a command writes inside an output directory; returns the directory.

    Parameters
    ----------
    out_dir : the output directory (it need not exist; it may itself be a link to a directory)
    file_names : the files the command writes, relative to ``out_dir`` (``"outputs.csv"``, ``"fields/f.vtu"``)
    inputs : the files the command reads (None entries are skipped)
    force : whether existing files may be overwritten (``--force``)
    what : the option that names the directory, for the message

    Raises
    ------
    OutputPathError
        when ``out_dir`` is not a directory, when a file to write is an input (even with ``force``), is a
        symbolic link or lies under one, or resolves outside ``out_dir``, and when ``force`` is False and the
        directory already holds any of the files; the message names the option and the path.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputPathError(f"{what} {out_dir} is not a directory")
    if not out_dir.exists() and out_dir.is_symlink():
        raise OutputPathError(f"{what} {out_dir} is a broken symbolic link (to {os.readlink(out_dir)})")
    ins = _inputs(inputs)
    root = Path(os.path.realpath(out_dir))
    existing = []
    for name in file_names:
        rel = Path(name)
        if rel.is_absolute() or ".." in rel.parts:
            raise ValueError(f"output file name {name!r} is not relative to the output directory")
        path = out_dir / rel
        _refuse_input(path, ins, f"{what} {out_dir}: {path}")
        for k in range(1, len(rel.parts) + 1):  # the file and every folder between it and out_dir
            inside = out_dir.joinpath(*rel.parts[:k])
            _refuse_link(inside, f"{what} {out_dir}: {inside}")
        if not Path(os.path.realpath(path)).is_relative_to(root):
            raise OutputPathError(f"{what} {out_dir}: {path} resolves to {os.path.realpath(path)}, outside the folder")
        if path.is_dir():
            raise OutputPathError(f"{what} {out_dir}: {path} is a directory, not a file")
        if path.exists():
            existing.append(str(rel))
    if existing and not force:
        shown = ", ".join(existing[:5]) + (f" and {len(existing) - 5} more" if len(existing) > 5 else "")
        raise OutputPathError(f"{what} {out_dir} already holds {shown}; pass --force to overwrite")
    return out_dir


def check_distinct(outputs: Mapping[str, str | os.PathLike | None]) -> None:
    """Refuse two options that name the same output file (``{"--out": a, "--signature": b}``; None entries skipped)."""
    given = [(k, Path(v)) for k, v in outputs.items() if v is not None]
    for i, (ka, a) in enumerate(given):
        for kb, b in given[i + 1:]:
            if same_file(a, b):
                raise OutputPathError(f"{ka} {a} and {kb} {b} are the same file")


def _temporary(path: Path) -> Path:
    # the suffix is kept: some writers choose the format by it (matplotlib, meshio)
    return path.with_name(f".{path.stem}-{secrets.token_hex(4)}.tmp{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed over ``path`` on success, removed on failure.

    The folder is created. The rename (:func:`os.replace`) is atomic on one file system and replaces a symbolic
    link at ``path`` itself, never the file it points to.

    Examples
    --------
    >>> with atomic_path(out) as tmp:  # doctest: +SKIP
    ...     write_loads(tmp, loads)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`); returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def write_text_atomic(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_path`); returns the path."""
    return write_bytes_atomic(path, text.encode(encoding))


__all__ = [
    "FORCE_HELP",
    "OutputPathError",
    "atomic_path",
    "check_distinct",
    "check_output_dir",
    "check_output_path",
    "same_file",
    "write_bytes_atomic",
    "write_text_atomic",
]
