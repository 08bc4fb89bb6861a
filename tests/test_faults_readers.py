"""File readers refuse what is not a regular UTF-8 text file, naming it, and read a UTF-8 BOM like no BOM.

A named pipe without a writer must be refused at once (reading it would block forever), binary garbage must
give the reader's own error with the file name instead of a bare codec error, and a file saved with a
byte-order mark must read exactly like the same file without one.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.chardiag.training import TrainingDataError, read_training_csv
from hybridcomp.diagnose.data import DatasetError, read_dataset
from hybridcomp.histogram.gcode import GcodeError, read_gcode
from hybridcomp.rom.external import MatrixFileError, read_matrices

BOM = b"\xef\xbb\xbf"
GARBAGE = b"\xff\xfe\x00\x81\xc3\x28binary\x00\xa0\xa1"

TRAINING = b"load_case,time_s,spindle_rpm,dx_um\ncase1,0,0,0.5\ncase1,60,6000,1.5\n"
DATASET = b"time_s,a_degC,dx_um\n0,20,0.1\n60,21,0.2\n120,22,0.4\n"
GCODE = b"G21 G90\nG0 X0 Y0\nG1 X100 F6000\nS6000 M3\nG4 P60\nM5\n"


def _in_time(fn, timeout_s: float = 3.0):
    """``fn()``'s result or exception, failing (not hanging) the test if it takes longer than ``timeout_s``."""
    box: dict[str, object] = {}

    def run():
        try:
            box["value"] = fn()
        except Exception as exc:  # noqa: BLE001 - handed to the test thread
            box["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        pytest.fail(f"the reader did not return within {timeout_s} s (blocked on the file?)")
    if "error" in box:
        raise box["error"]
    return box["value"]


def _fifo(path: Path) -> Path:
    if not hasattr(os, "mkfifo"):
        pytest.skip("no named pipes on this platform")
    os.mkfifo(path)
    return path


READERS = [
    pytest.param(lambda p, m: read_training_csv(p), TrainingDataError, "t.csv", id="read_training_csv"),
    pytest.param(lambda p, m: read_dataset(p), DatasetError, "d.csv", id="read_dataset"),
    pytest.param(lambda p, m: read_gcode(p, m), GcodeError, "p.nc", id="read_gcode"),
]


@pytest.mark.parametrize(("read", "error", "name"), READERS)
def test_fifo_is_refused_at_once_naming_it(tmp_path, machine, read, error, name):
    fifo = _fifo(tmp_path / name)
    with pytest.raises(error, match="named pipe") as info:
        _in_time(lambda: read(fifo, machine))
    assert str(fifo) in str(info.value)


def test_fifo_matrix_market_file_is_refused_at_once(tmp_path):
    path = tmp_path / "m.mat"
    _fifo(path)
    with pytest.raises(MatrixFileError, match="named pipe") as info:
        _in_time(lambda: read_matrices(path))
    assert str(path) in str(info.value)


@pytest.mark.parametrize(("read", "error", "name"), READERS)
def test_binary_garbage_names_the_file(tmp_path, machine, read, error, name):
    path = tmp_path / name
    path.write_bytes(GARBAGE)
    with pytest.raises(error, match="not UTF-8 text") as info:
        _in_time(lambda: read(path, machine))
    assert str(path) in str(info.value)


def test_bom_training_table_reads_like_without(tmp_path):
    plain, bom = tmp_path / "plain.csv", tmp_path / "bom.csv"
    plain.write_bytes(TRAINING)
    bom.write_bytes(BOM + TRAINING.replace(b"\n", b"\r\n"))
    a, b = read_training_csv(plain), read_training_csv(bom)
    assert list(a.columns) == list(b.columns) == ["time_s", "spindle_rpm", "dx_um"]
    for k in a.columns:
        np.testing.assert_array_equal(a.columns[k], b.columns[k])
    assert list(a.load_case) == list(b.load_case) == ["case1", "case1"]


def test_bom_dataset_reads_like_without(tmp_path):
    plain, bom = tmp_path / "plain.csv", tmp_path / "bom.csv"
    plain.write_bytes(DATASET)
    bom.write_bytes(BOM + DATASET)
    a, b = read_dataset(plain), read_dataset(bom)
    assert sorted(a.columns) == sorted(b.columns) == ["a_degC", "dx_um"]
    np.testing.assert_array_equal(a.time_s, b.time_s)
    for k in a.columns:
        np.testing.assert_array_equal(a.columns[k], b.columns[k])


def test_bom_gcode_reads_like_without(tmp_path, machine):
    plain, bom = tmp_path / "plain.nc", tmp_path / "bom.nc"
    plain.write_bytes(GCODE)
    bom.write_bytes(BOM + GCODE)
    a, b = read_gcode(plain, machine), read_gcode(bom, machine)
    np.testing.assert_array_equal(a.time_s, b.time_s)
