"""``hybridcomp data fetch``: the public spindle test, converted to the project's CSV and checked.

The machine running the tests may have no internet: the download is injected, and the conversion is checked on a
workbook written here and on the published CSV when the shared data folder sits next to the repository (skipped,
with the reason, when it does not).
"""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from hybridcomp.cli import main
from hybridcomp.diagnose.datasets import (
    CAIVIAC_SPINDLE,
    DataFetchError,
    dataset_csv,
    fetch_dataset,
    sha256,
    xlsx_to_csv,
)

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "caiviac-spindle"
SHARED_CSV = SHARED / "measured.csv"
needs_shared = pytest.mark.skipif(not SHARED_CSV.is_file(), reason=f"the published spindle test's CSV is not in "
                                  f"{SHARED.relative_to(ROOT.parent)} next to the repository (nothing to compare with)")
HEADER = [old for old, _ in CAIVIAC_SPINDLE.columns]


def workbook(rows, header=HEADER) -> bytes:
    openpyxl = pytest.importorskip("openpyxl", reason="reading xlsx needs openpyxl (extra 'data')")
    wb = openpyxl.Workbook()
    ws = wb.active
    ws.append(header)
    for r in rows:
        ws.append(r)
    buf = io.BytesIO()
    wb.save(buf)
    return buf.getvalue()


def test_xlsx_columns_are_renamed_and_values_kept():
    row1 = [0, 0, 0.377452788, 0.404387633, 0.106198061, 0.207412066, 0.14420852, *[26.1908623380691] * 16]
    row2 = [15.0, 1250, -1.5, 2.0, 3.25, 4.0, 5.0, *[20.0 + i / 7 for i in range(16)]]
    text = xlsx_to_csv(workbook([row1, row2]), CAIVIAC_SPINDLE, "t.xlsx")
    lines = text.splitlines()
    assert lines[0] == ",".join(["time_s", "spindle_rpm", *(f"ch{i}_um" for i in range(1, 6)),
                                 *(f"t{i}_degC" for i in range(1, 17))])
    assert lines[1].startswith("0,0,0.377453,0.404388,0.106198,0.207412,0.144209,26.190862,")
    assert lines[2].split(",")[:7] == ["15", "1250", "-1.500000", "2", "3.250000", "4", "5"]
    assert float(lines[2].split(",")[8]) == pytest.approx(20.0 + 1 / 7, abs=5e-7) and len(lines) == 3


def test_another_workbook_is_refused_naming_the_column():
    data = workbook([[0] * 23], header=["time", *HEADER[1:]])
    with pytest.raises(DataFetchError, match=r"t\.xlsx: not the caiviac-spindle data set: column 1 is 'time', "
                                             r"expected '時間\(s\)'"):
        xlsx_to_csv(data, CAIVIAC_SPINDLE, "t.xlsx")
    bad = workbook([[0, "n/a", *[0] * 21]])
    with pytest.raises(DataFetchError, match=r"t\.xlsx: row 2, column 'spindle\(RPM\)': expected a number, got 'n/a'"):
        xlsx_to_csv(bad, CAIVIAC_SPINDLE, "t.xlsx")


def test_without_openpyxl_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "openpyxl", None)
    with pytest.raises(DataFetchError, match=r"needs openpyxl: pip install 'hybridcomp\[data\]'"):
        xlsx_to_csv(b"PK\x03\x04", CAIVIAC_SPINDLE, "t.xlsx")


def test_a_download_with_another_checksum_is_refused(tmp_path):
    urls = []

    def fake(url):
        urls.append(url)
        return workbook([[0] * 23])

    with pytest.raises(DataFetchError, match=r"SHA-256 [0-9a-f]{64} is not the one of caiviac-spindle's published"):
        fetch_dataset("caiviac-spindle", tmp_path, fetch=fake)
    assert urls == [CAIVIAC_SPINDLE.url] and CAIVIAC_SPINDLE.url.startswith("https://raw.githubusercontent.com/")
    assert not list(tmp_path.iterdir())  # nothing written
    with pytest.raises(DataFetchError, match="unknown data set 'spindle' \\(known: caiviac-spindle\\)"):
        fetch_dataset("spindle", tmp_path, fetch=fake)


def test_no_network_is_one_error_that_suggests_from(tmp_path, capsys, monkeypatch):
    import hybridcomp.diagnose.datasets as m

    def offline(url, timeout=None):
        raise m.urllib.error.URLError("Name or service not known")

    monkeypatch.setattr(m.urllib.request, "urlopen", offline)
    assert main(["data", "fetch", "caiviac-spindle", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "cannot download https://raw.githubusercontent.com/CAIVIAC/FL_THERMAL/" in err and "--from PATH" in err


@needs_shared
def test_the_published_csv_is_fetched_from_a_local_copy(tmp_path, capsys):
    assert sha256(SHARED_CSV.read_bytes()) == CAIVIAC_SPINDLE.csv_sha256
    assert main(["data", "fetch", "caiviac-spindle", "--from", str(SHARED_CSV), "--out", str(tmp_path)]) == 0
    out = tmp_path / "caiviac-spindle.csv"
    assert out.read_bytes() == SHARED_CSV.read_bytes() and "checksum verified" in capsys.readouterr().out
    # the download path gives the same bytes; a file there with the right checksum is kept without a download
    assert dataset_csv(CAIVIAC_SPINDLE, fetch=lambda url: SHARED_CSV.read_bytes()) == SHARED_CSV.read_bytes()
    assert fetch_dataset("caiviac-spindle", tmp_path, fetch=lambda url: pytest.fail("downloaded again")) == out
    out.write_text("time_s\n0\n")
    assert main(["data", "fetch", "caiviac-spindle", "--from", str(SHARED_CSV), "--out", str(tmp_path)]) == 2
    assert "--force" in capsys.readouterr().err and out.read_text() == "time_s\n0\n"
    assert main(["data", "fetch", "caiviac-spindle", "--from", str(SHARED_CSV), "--out", str(tmp_path), "--force"]) == 0
    assert out.read_bytes() == SHARED_CSV.read_bytes()


@pytest.mark.skipif(not (SHARED / "data.xlsx").is_file(),
                    reason="the published workbook (data.xlsx) is not in the shared data folder next to the repository")
def test_the_published_workbook_converts_to_the_published_csv(tmp_path):
    pytest.importorskip("openpyxl", reason="reading xlsx needs openpyxl (extra 'data')")
    out = fetch_dataset("caiviac-spindle", tmp_path, from_path=SHARED / "data.xlsx")
    assert sha256(out.read_bytes()) == CAIVIAC_SPINDLE.csv_sha256
