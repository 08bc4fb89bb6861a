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
the directory are never touched. A command whose files are not known before it runs (``demo``, ``monitor
scenario``: databases, traces and plots of every stage) checks its folder as a whole
(:func:`check_output_folder`): a folder that holds anything is refused without ``--force``, and a symbolic
link anywhere in it is refused always.

An append-only file (the monitor's offsets sink) is opened by :class:`AppendOnlyFile`: never through a
symbolic link, never anything but a regular file, and every append is whole lines, written, flushed and
fsync'd; a write that fails (a full disk) is cut back to the last whole line before the error is raised.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
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


def check_output_folder(out_dir: str | os.PathLike, *, inputs: Iterable = (), force: bool = False,
                        what: str = "--out") -> Path:
    """Check an output folder whose files are not known before the command runs; returns it.

    Parameters
    ----------
    out_dir : the output folder (it need not exist)
    inputs : the files the command reads (None entries are skipped)
    force : whether a folder that already holds files may be written into (``--force``)
    what : the option that names the folder, for the message

    Raises
    ------
    OutputPathError
        when ``out_dir`` is not a directory or is a symbolic link, when it holds a symbolic link anywhere (even
        with ``force``), when it holds an input (even with ``force``), and when it holds anything and ``force`` is
        False; the message names the option and the path.
    """
    out_dir = Path(out_dir)
    _refuse_link(out_dir, f"{what} {out_dir}")
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputPathError(f"{what} {out_dir} is not a directory")
    if not out_dir.exists():
        return out_dir
    ins = _inputs(inputs)
    held = []
    for dirpath, dirnames, filenames in os.walk(out_dir):
        for name in sorted(dirnames + filenames):
            p = Path(dirpath) / name
            _refuse_link(p, f"{what} {out_dir}: {p}")
            _refuse_input(p, ins, f"{what} {out_dir}: {p}")
            held.append(p)
    if held and not force:
        shown = ", ".join(str(p.relative_to(out_dir)) for p in sorted(held)[:3])
        raise OutputPathError(f"{what} {out_dir} already holds {shown}{' ...' if len(held) > 3 else ''}: "
                              "pass --force to write into it (files of an earlier run are replaced)")
    return out_dir


def start_folder(out_dir: str | os.PathLike, *, inputs: Iterable = (), force: bool = False,
                 finals: Iterable[str] = (), what: str = "--out") -> Path:
    """:func:`check_output_folder`, then remove the files that mark a finished run (``finals``) from an earlier one.

    A run that is interrupted after this then leaves no summary of the earlier run beside its own new files:
    the folder holds a finished run only when its final files are there, written last.
    """
    out_dir = check_output_folder(out_dir, inputs=inputs, force=force, what=what)
    for name in finals:
        (out_dir / name).unlink(missing_ok=True)
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


class AppendOnlyFile:
    """A file that only grows by whole lines, each written, flushed and fsync'd before :meth:`append` returns.

    Opened without following a symbolic link (``O_NOFOLLOW``) and refused unless it is a regular file; a last
    line left unfinished by an earlier crash is cut off at opening. A write or fsync that fails (``ENOSPC`` on a
    full disk, ``EIO``) truncates the file back to the size it had before the append and re-raises the
    ``OSError``, so the file holds only whole lines.

    Parameters
    ----------
    path : the file (created with its folder when missing)
    fsync : whether each append is fsync'd (default; about 1.3 ms a line on an ext4 disk); False only flushes to the
        operating system (a replay benchmark that measures the daemon, not the disk): the lines stay whole
    """

    def __init__(self, path: str | os.PathLike, fsync: bool = True):
        self.path = Path(path)
        self.fsync = fsync
        _refuse_link(self.path, str(self.path))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # O_NONBLOCK: a named pipe without a reader is refused at once instead of blocking the open
        flags = (os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
                 | getattr(os, "O_NONBLOCK", 0))
        try:
            fd = os.open(self.path, flags, 0o644)
        except OSError as exc:
            raise OutputPathError(f"{self.path}: cannot open to append: {exc.strerror} (a symbolic link, a folder "
                                  "or a named pipe without a reader is never written to)") from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            raise OutputPathError(f"{self.path} is not a regular file (a named pipe, device or folder)")
        os.set_blocking(fd, True)
        self._fh = os.fdopen(fd, "ab", buffering=0)
        try:
            self._cut_unfinished_line(st.st_size)
        except BaseException:
            self._fh.close()
            raise

    def _cut_unfinished_line(self, size: int) -> None:
        if size == 0:
            return
        with open(self.path, "rb") as fh:
            fh.seek(max(0, size - 65536))
            tail = fh.read()
        if tail.endswith(b"\n"):
            return
        k = tail.rfind(b"\n")
        keep = size - len(tail) + k + 1 if k >= 0 else (0 if size <= 65536 else None)
        if keep is None:
            raise OutputPathError(f"{self.path}: the last line is unfinished and longer than 64 KiB: not a file "
                                  "of whole lines")
        os.ftruncate(self._fh.fileno(), keep)

    @property
    def size(self) -> int:
        """The file's size in bytes."""
        return os.fstat(self._fh.fileno()).st_size

    def append(self, text: str) -> None:
        """Append ``text`` (whole lines: it ends in a newline), flushed and fsync'd.

        Raises
        ------
        OSError
            when the write or the fsync fails; the file is cut back to its size before the call.
        """
        if not text.endswith("\n"):
            raise ValueError(f"{self.path}: an append must be whole lines, got {text[-40:]!r}")
        data = text.encode("utf-8")
        before = self.size
        try:
            view = memoryview(data)
            while view:
                n = self._fh.write(view)
                if n is None or n <= 0:
                    raise OSError(28, os.strerror(28), str(self.path))
                view = view[n:]
            self._fh.flush()
            if self.fsync:
                os.fsync(self._fh.fileno())
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fh.fileno(), before)
            raise

    def close(self) -> None:
        """Close the file (again: nothing)."""
        if not self._fh.closed:
            self._fh.close()


__all__ = [
    "FORCE_HELP",
    "AppendOnlyFile",
    "OutputPathError",
    "atomic_path",
    "check_distinct",
    "check_output_folder",
    "check_output_dir",
    "check_output_path",
    "start_folder",
    "same_file",
    "write_bytes_atomic",
    "write_text_atomic",
]
