"""The measured CAIVIAC spindle test, as the benchmarks that read it take it: its default place and options."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

#: data/ of this checkout, written by 'hybridcomp data fetch caiviac-spindle --out data/'
DATA = Path(__file__).resolve().parents[1] / "data" / "caiviac-spindle.csv"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``--data`` (the spindle test CSV) and ``--train`` (the training part)."""
    p.add_argument("--data", type=Path, default=DATA, help="the spindle test CSV (default: data/caiviac-spindle.csv of this "
                   "checkout, written by 'hybridcomp data fetch caiviac-spindle --out data/')")
    p.add_argument("--train", default="0:50%", help="training part (default 0:50%%, as README)")


def missing(path: Path) -> bool:
    """Whether the spindle test at ``path`` is missing (then an error saying how to fetch it is printed)."""
    if path.is_file():
        return False
    print(f"error: the measured spindle test {path} is missing: fetch it with 'hybridcomp data fetch "
          "caiviac-spindle --out data/' (or give its path with --data)", file=sys.stderr)
    return True
