"""``hybridcomp data``: fetch the public measured data sets the README's examples and benchmarks read."""

from __future__ import annotations

import argparse
from pathlib import Path

from hybridcomp.safeio import FORCE_HELP


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp data`` actions and their options."""
    from hybridcomp.diagnose.datasets import DATASETS

    names = ", ".join(f"{d.name} ({d.description})" for d in DATASETS.values())
    sub = p.add_subparsers(dest="data_command", metavar="ACTION", required=True)
    f = sub.add_parser("fetch", help="download a public data set, check it and convert it to this project's CSV",
                       description="Download a public measured data set from its published place, check its "
                       "SHA-256, convert it to this project's CSV (columns renamed to the unit-suffixed "
                       f"convention, values unchanged) and check that too. Data sets: {names}. Writes "
                       "OUT/<name>.csv; a file there with the right checksum is kept. Reading the xlsx needs "
                       "openpyxl (pip install 'hybridcomp[data]').")
    f.add_argument("name", choices=sorted(DATASETS), metavar="NAME", help="data set: " + ", ".join(sorted(DATASETS)))
    f.add_argument("--out", type=Path, default=Path("data"), help="folder to write the CSV into (default data/)")
    f.add_argument("--from", dest="from_path", type=Path, default=None, metavar="PATH",
                   help="a local copy instead of the download: the original xlsx or the converted CSV "
                   "(checked the same way)")
    f.add_argument("--force", action="store_true", help=FORCE_HELP)


def run(args: argparse.Namespace) -> int:
    """Run a ``hybridcomp data`` action; returns the exit code (errors raise, the dispatcher reports them)."""
    from hybridcomp.diagnose.datasets import DATASETS, fetch_dataset

    ds = DATASETS[args.name]
    out = fetch_dataset(args.name, args.out, args.from_path, force=args.force)
    print(f"{out}: {ds.description}; checksum verified; licence {ds.licence}")
    return 0
