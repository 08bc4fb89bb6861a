"""Public measured data sets, fetched by ``hybridcomp data fetch`` (never shipped in the repository).

``caiviac-spindle``: a 46.3 h thermal test of a CNC machine tool (spindle speed steps, five displacement channels,
sixteen temperatures, every 15 s), published with an MIT licence in the public repository CAIVIAC/FL_THERMAL as
``data/data.xlsx``. It is downloaded from GitHub at a fixed commit, its SHA-256 checked, and converted to this
project's CSV: the columns renamed to the unit-suffixed convention (``time_s``, ``spindle_rpm``, ``ch1_um`` …
``ch5_um``, ``t1_degC`` … ``t16_degC``), the values unchanged (whole numbers as integers, the others to six
decimals), and the SHA-256 of the CSV checked too. A local copy (the xlsx or the converted CSV) can stand in for
the download. Reading the xlsx needs openpyxl (extra ``data``).
"""

from __future__ import annotations

import hashlib
import io
import logging
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hybridcomp.errors import HybridcompError
from hybridcomp.safeio import check_output_path, write_bytes_atomic

log = logging.getLogger(__name__)

DOWNLOAD_TIMEOUT_S = 120.0


class DataFetchError(HybridcompError, ValueError):
    """A data set cannot be fetched or converted; the message names the data set, the file or URL and the value."""


@dataclass(frozen=True)
class PublicDataset:
    """A public data set and how it becomes this project's CSV.

    Attributes
    ----------
    name : name on the command line (``hybridcomp data fetch NAME``)
    url : where the original file is downloaded from (pinned to a commit)
    source_sha256 : SHA-256 of the original file
    csv_sha256 : SHA-256 of the converted CSV
    columns : original column name -> this project's column name, in the file's order
    file_name : the CSV written into the output folder
    licence : the licence and where it is stated
    description : one line on what it is
    """

    name: str
    url: str
    source_sha256: str
    csv_sha256: str
    columns: tuple[tuple[str, str], ...]
    file_name: str
    licence: str
    description: str


CAIVIAC_COMMIT = "9fa40bd4c3d8a67b802c19719ff9b20bbba085d7"
CAIVIAC_SPINDLE = PublicDataset(
    name="caiviac-spindle",
    url=f"https://raw.githubusercontent.com/CAIVIAC/FL_THERMAL/{CAIVIAC_COMMIT}/data/data.xlsx",
    source_sha256="663328610bb57ce3597f9880619f57f13d0b9007713c21d9e4e272799bfbbb28",
    csv_sha256="a152205c967542df2d6c63d8066cd776300b19d8f087ca1764cf4b8e7a3af593",
    columns=(("時間(s)", "time_s"), ("spindle(RPM)", "spindle_rpm"),
             *((f"ch{i}(um)", f"ch{i}_um") for i in range(1, 6)),
             *((f"t{i}(°C)", f"t{i}_degC") for i in range(1, 17))),
    file_name="caiviac-spindle.csv",
    licence=f"MIT, Copyright (c) 2024 CAIVIAC: https://github.com/CAIVIAC/FL_THERMAL/blob/{CAIVIAC_COMMIT}/LICENSE",
    description="measured spindle thermal test of a CNC machine tool, 46.3 h every 15 s (CAIVIAC/FL_THERMAL)",
)
DATASETS = {d.name: d for d in (CAIVIAC_SPINDLE,)}


def sha256(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def _number(v, where: str) -> str:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise DataFetchError(f"{where}: expected a number, got {v!r}")
    if isinstance(v, int) or v.is_integer():
        return str(int(v))
    return f"{v:.6f}"


def xlsx_to_csv(data: bytes, dataset: PublicDataset, source: str = "<xlsx>") -> str:
    """Convert the first sheet of an xlsx file to this project's CSV text.

    Parameters
    ----------
    data : the xlsx file's bytes
    dataset : gives the expected columns and their new names
    source : the file's name for messages

    Raises
    ------
    DataFetchError
        openpyxl missing (names the extra), another header, or a cell that is not a number
    """
    try:
        import openpyxl
    except ImportError:
        raise DataFetchError(f"{source}: reading an xlsx file needs openpyxl: pip install 'hybridcomp[data]' "
                             "(or pass the converted CSV with --from)") from None
    try:
        wb = openpyxl.load_workbook(io.BytesIO(data), read_only=True, data_only=True)
    except Exception as exc:  # noqa: BLE001 - openpyxl raises many types for a broken file; reported as one error
        raise DataFetchError(f"{source}: not a readable xlsx file: {type(exc).__name__}: {exc}") from None
    try:
        rows = wb.worksheets[0].iter_rows(values_only=True)
        header = [str(h).strip() if h is not None else "" for h in next(rows, ())]
        want = [old for old, _ in dataset.columns]
        if header != want:
            bad = next((f"column {i + 1} is {h!r}, expected {w!r}" for i, (h, w) in enumerate(zip(header, want))
                        if h != w), f"{len(header)} columns, expected {len(want)}")
            raise DataFetchError(f"{source}: not the {dataset.name} data set: {bad}")
        lines = [",".join(new for _, new in dataset.columns)]
        for k, row in enumerate(rows, start=2):
            if all(v is None for v in row):
                continue
            if len(row) != len(want):
                raise DataFetchError(f"{source}: row {k} has {len(row)} cells, expected {len(want)}")
            lines.append(",".join(_number(v, f"{source}: row {k}, column {want[j]!r}") for j, v in enumerate(row)))
    finally:
        wb.close()
    return "\n".join(lines) + "\n"


def download(url: str, timeout_s: float = DOWNLOAD_TIMEOUT_S) -> bytes:
    """The bytes at ``url`` (HTTPS GET).

    Raises
    ------
    DataFetchError
        no connection, an HTTP error or a timeout; the message names the URL and suggests ``--from``
    """
    log.info("downloading %s", url)
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as r:
            return r.read()
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise DataFetchError(f"cannot download {url}: {reason}; download it by another way and pass the file "
                             "with --from PATH") from None


def dataset_csv(dataset: PublicDataset, from_path: str | Path | None = None,
                fetch: Callable[[str], bytes] = download) -> bytes:
    """The data set as this project's CSV (bytes), checked against its SHA-256.

    Parameters
    ----------
    dataset : the data set
    from_path : a local copy instead of the download: the original xlsx or the converted CSV
    fetch : how the original file is downloaded (``url -> bytes``; injected by the tests)

    Raises
    ------
    DataFetchError
        a file whose SHA-256 differs from the published one, or a failed download or conversion
    OSError
        ``from_path`` cannot be read
    """
    if from_path is None:
        source, data = dataset.url, fetch(dataset.url)
    else:
        source, data = str(from_path), Path(from_path).read_bytes()
    if data[:4] == b"PK\x03\x04":  # a zip container: the xlsx
        got = sha256(data)
        if got != dataset.source_sha256:
            raise DataFetchError(f"{source}: SHA-256 {got} is not the one of {dataset.name}'s published file "
                                 f"({dataset.source_sha256}); a different version of the file")
        data = xlsx_to_csv(data, dataset, source).encode("utf-8")
    got = sha256(data)
    if got != dataset.csv_sha256:
        raise DataFetchError(f"{source}: the CSV's SHA-256 is {got}, expected {dataset.csv_sha256} for {dataset.name} "
                             "(give the original xlsx or the CSV this command writes)")
    return data


def fetch_dataset(name: str, out_dir: str | Path, from_path: str | Path | None = None, force: bool = False,
                  fetch: Callable[[str], bytes] = download) -> Path:
    """Fetch a public data set into ``out_dir`` as this project's CSV; returns the CSV's path.

    A CSV already there with the right SHA-256 is kept as it is (nothing downloaded); any other file there is
    replaced only with ``force``.

    Raises
    ------
    DataFetchError
        unknown name, a download, checksum or conversion failure
    OSError
        an existing output without ``force``, or an unreadable ``from_path``
    """
    if name not in DATASETS:
        raise DataFetchError(f"unknown data set {name!r} (known: {', '.join(DATASETS)})")
    ds = DATASETS[name]
    out = Path(out_dir) / ds.file_name
    if out.is_file() and not out.is_symlink() and sha256(out.read_bytes()) == ds.csv_sha256:
        log.info("%s is there already, checksum verified", out)
        return out
    out = check_output_path(out, inputs=[from_path], force=force)
    return write_bytes_atomic(out, dataset_csv(ds, from_path, fetch))
