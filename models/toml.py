"""TOML for every file the project reads or writes: one strict reader, one writer.

Reading is strict: :class:`StrictTable` checks a table's keys against the
known ones before anything is read, so a misspelt key is an error with a
did-you-mean hint, never a silent default, and its typed getters name the
file, the field and the value in every message.  :func:`read_toml` reads a
file and turns a syntax error into the caller's error class.

Writing: :func:`dumps_toml` writes the plain data TOML can hold (tables,
arrays of tables, inline tables in lists); it refuses a non-finite number.

Reading any input file: :func:`open_regular_file` opens a file only when it is
a regular file (never blocking on a named pipe, never reading a device or a
directory), for the project's TOML and CSV readers; :func:`read_bytes`,
:func:`read_text` and :func:`open_text` build on it and name the file in every
error.
"""

from __future__ import annotations

import contextlib
import difflib
import io
import json
import math
import os
import re
import stat
import tomllib
from collections.abc import Collection, Iterator, Mapping
from pathlib import Path
from typing import Any, BinaryIO

#: the largest TOML file read [bytes]: a machine file or a configuration is a few kB
MAX_TOML_BYTES = 16 * 1024 * 1024
#: the deepest nesting of tables and arrays a TOML file may have (a machine file needs 7: zones[].surfaces[].region_mm)
MAX_TOML_DEPTH = 32

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def open_regular_file(path: str | Path, error: type[Exception] = ValueError, what: str = "file") -> BinaryIO:
    """Open ``path`` for binary reading if it is a regular file; raises ``error`` naming it otherwise.

    The file is opened without blocking and checked on the open descriptor, so a named pipe
    without a writer, a character device or a directory is refused at once instead of
    hanging or reading forever, and nothing can be swapped in between the check and the read.

    Parameters
    ----------
    path : the file
    error : exception class of the message (``<path>: cannot open <what>: ...``)
    what : what the file is, for the message (``"loads file"``)
    """
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except OSError as exc:
        raise error(f"{path}: cannot open {what}: {exc.strerror or exc}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = next((k for test, k in _KINDS if test(mode)), "not a regular file")
            raise error(f"{path}: cannot open {what}: it is {kind}, not a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | Path, error: type[Exception] = ValueError, what: str = "file",
               limit: int | None = None) -> bytes:
    """The bytes of a regular file; a read error is ``error`` naming the file.

    With ``limit``, at most ``limit`` + 1 bytes are read: enough to tell an oversize file without reading it all.
    """
    with open_regular_file(path, error, what) as fh:
        try:
            return fh.read() if limit is None else fh.read(limit + 1)
        except OSError as exc:
            raise error(f"{path}: cannot read {what}: {exc.strerror or exc}") from None


def read_text(path: str | Path, error: type[Exception] = ValueError, what: str = "file") -> str:
    """The UTF-8 text of a regular file (a leading byte-order mark dropped); anything else is ``error`` naming it."""
    raw = read_bytes(path, error, what)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text ({exc.reason})") from None


@contextlib.contextmanager
def open_text(path: str | Path, error: type[Exception] = ValueError, what: str = "file",
              newline: str | None = None) -> Iterator[io.TextIOWrapper]:
    """A regular file as UTF-8 text to read line by line (a leading byte-order mark dropped).

    Bytes that are not UTF-8 are ``error`` naming the file.
    """
    with open_regular_file(path, error, what) as raw, io.TextIOWrapper(raw, encoding="utf-8-sig", newline=newline) as fh:
        try:
            yield fh
        except UnicodeDecodeError as exc:
            raise error(f"{path}: not UTF-8 text ({exc.reason})") from None


def _depth(data: Any) -> int:
    """Nesting depth of parsed TOML: 0 for a scalar, 1 for a flat table or array (iterative, any depth)."""
    deepest, todo = 0, [(data, 1)]
    while todo:
        v, d = todo.pop()
        items = v.values() if isinstance(v, Mapping) else v if isinstance(v, list) else None
        if items is None:
            continue
        deepest = max(deepest, d)
        todo.extend((x, d + 1) for x in items if isinstance(x, (Mapping, list)))
    return deepest


def read_toml(path: str | Path, error: type[Exception] = ValueError) -> tuple[dict, bytes]:
    """Parse a TOML file; returns the data and the file's bytes (for a checksum).

    Raises ``error`` naming the file when it cannot be read, is not a regular file, is larger than
    :data:`MAX_TOML_BYTES`, is not valid UTF-8 TOML (a leading byte-order mark is allowed) or nests
    tables and arrays deeper than :data:`MAX_TOML_DEPTH`.
    """
    path = Path(path)
    raw = read_bytes(path, error, "the file", limit=MAX_TOML_BYTES)
    if len(raw) > MAX_TOML_BYTES:
        raise error(f"{path}: the file is larger than the limit of {MAX_TOML_BYTES} bytes for a TOML file")
    too_deep = f"{path}: not valid TOML: tables and arrays nested more than {MAX_TOML_DEPTH} levels deep"
    try:
        data = tomllib.loads(raw.decode("utf-8-sig"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and inline tables recursively
        raise error(too_deep) from None
    if _depth(data) > MAX_TOML_DEPTH:
        raise error(too_deep)
    return data, raw


def did_you_mean(key: str, known: Collection[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest known key, else `` (known: a, b, c)``."""
    close = difflib.get_close_matches(key, list(known), n=1)
    return f" (did you mean {close[0]!r}?)" if close else f" (known: {', '.join(known)})"


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def nonnegative_number(x: Any, strict: bool = False) -> bool:
    """Whether ``x`` is a finite int or float (a bool is not) that is ≥ 0 (> 0 with ``strict``)."""
    return _is_number(x) and math.isfinite(x) and (x > 0 if strict else x >= 0)


class StrictTable:
    """One TOML table of a known shape; an unknown key is an error before anything else.

    Parameters
    ----------
    source : the file the table comes from (first in every message)
    where : dotted name of the table in the file (``"bodies[2]"``, ``"monitor"``; ``""`` for the top level)
    table : the parsed table
    known : the keys the table may have
    error : exception class of every message (a subclass of a built-in exception)
    """

    def __init__(self, source: str, where: str, table: Any, known: Collection[str],
                 error: type[Exception] = ValueError):
        self.src, self.where, self.known, self.error = source, where, tuple(known), error
        if not isinstance(table, Mapping):
            raise error(f"{source}: field {where!r} must be a table, got {table!r}")
        self.t = dict(table)
        for k in self.t:
            if k not in self.known:
                raise error(f"{source}: field {self.name(k)!r} is not a known field{did_you_mean(k, self.known)}")

    def name(self, key: str) -> str:
        """The dotted name of ``key`` in the file."""
        return f"{self.where}.{key}" if self.where else key

    def err(self, key: str, msg: str) -> Exception:
        """The error for field ``key``: ``<file>: field '<table>.<key>' <msg>``."""
        return self.error(f"{self.src}: field {self.name(key)!r} {msg}")

    def __contains__(self, key: str) -> bool:
        return key in self.t

    def _lookup(self, key: str, default: Any) -> tuple[bool, Any]:
        """(True, the value) when ``key`` is in the table, else (False, ``default``); ``...`` means required."""
        assert key in self.known, key
        if key not in self.t:
            if default is ...:
                raise self.err(key, "is required")
            return False, default
        return True, self.t[key]

    def get(self, key: str, default: Any = ..., kind: type | tuple = object) -> Any:
        """The raw value of ``key`` checked against ``kind``; ``default`` when absent (``...``: required)."""
        present, v = self._lookup(key, default)
        if not present:
            return v
        wants_bool = kind is bool or (isinstance(kind, tuple) and bool in kind)
        if (kind is not object and not isinstance(v, kind)) or (isinstance(v, bool) and not wants_bool):
            raise self.err(key, f"has the wrong type: {v!r}")
        return v

    def number(self, key: str, default: Any = ..., *, positive: bool = False, nonneg: bool = False,
               integer: bool = False) -> Any:
        """A finite number (float, or int with ``integer``); the default is returned unchecked."""
        present, v = self._lookup(key, default)
        if not present:
            return v
        if not _is_number(v):
            raise self.err(key, f"must be a number, got {v!r}")
        if not math.isfinite(v):
            raise self.err(key, f"must be finite, got {v!r}")
        if integer and int(v) != v:
            raise self.err(key, f"must be a whole number, got {v!r}")
        v = int(v) if integer else float(v)
        if positive and not v > 0:
            raise self.err(key, f"must be positive, got {v!r}")
        if nonneg and not v >= 0:
            raise self.err(key, f"must not be negative, got {v!r}")
        return v

    def string(self, key: str, default: Any = ..., choices: Collection[str] | None = None) -> Any:
        """A non-empty string, one of ``choices`` if given."""
        v = self.get(key, default, str)
        if v is default and key not in self.t:
            return v
        if not v:
            raise self.err(key, f"must be a non-empty string, got {v!r}")
        if choices and v not in choices:
            raise self.err(key, f"is {v!r}, must be one of {', '.join(choices)}")
        return v

    def boolean(self, key: str, default: Any = ...) -> Any:
        """``true`` or ``false``."""
        if key in self.t and not isinstance(self.t[key], bool):
            raise self.err(key, f"must be true or false, got {self.t[key]!r}")
        return self.get(key, default, bool)

    def mapping(self, key: str, value_kind: type = str) -> dict:
        """A table of strings (``value_kind=str``) or of numbers (``float``); empty when absent."""
        v = self.get(key, {}, Mapping)
        for k, x in v.items():
            ok = isinstance(x, str) if value_kind is str else _is_number(x)
            if not ok:
                raise self.err(f"{key}.{k}", f"must be a {'string' if value_kind is str else 'number'}, got {x!r}")
        return {k: (x if value_kind is str else float(x)) for k, x in v.items()}

    def tables(self, key: str, required: bool = True) -> list[tuple[str, dict]]:
        """An array of tables as (dotted name, table) pairs."""
        v = self.get(key, ... if required else [], list)
        return [(f"{self.name(key)}[{i}]", t) for i, t in enumerate(v)]


# --------------------------------------------------------------------------- writing

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write a non-finite number {v} to a TOML file")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_aot(v) -> bool:
    return isinstance(v, list) and len(v) > 0 and all(isinstance(x, dict) for x in v)


def dumps_toml(data: dict) -> str:
    """TOML text of a dictionary (tables, arrays of tables, inline tables in lists)."""
    lines: list[str] = []

    def table(d: dict, path: list[str]):
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and not _is_aot(v)}
        subs = {k: v for k, v in d.items() if isinstance(v, dict)}
        aots = {k: v for k, v in d.items() if _is_aot(v)}
        for k, v in scalars.items():
            lines.append(f"{_key(k)} = {_value(v)}")
        for k, v in subs.items():
            lines.append("")
            lines.append(f"[{'.'.join(_key(p) for p in path + [k])}]")
            table(v, path + [k])
        for k, items in aots.items():
            for item in items:
                lines.append("")
                lines.append(f"[[{'.'.join(_key(p) for p in path + [k])}]]")
                table(item, path + [k])

    table(data, [])
    return "\n".join(lines).lstrip("\n") + "\n"


__all__ = ["MAX_TOML_BYTES", "MAX_TOML_DEPTH", "StrictTable", "did_you_mean", "dumps_toml", "open_regular_file",
           "open_text", "read_bytes", "read_text", "read_toml"]
