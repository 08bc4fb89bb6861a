"""Render the README picture: the demonstrator after the 16 h example load case.

    python benchmarks/render_demonstrator.py [--out benchmarks/figures/vmc800_16h.png]

Prints a table of the final sensor temperatures and drift and a final JSON line.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hybridcomp.fem.export import render_png
from hybridcomp.fem.loads import example_loads
from hybridcomp.fem.model import build_model
from hybridcomp.fem.transient import simulate
from hybridcomp.models import jsonio, load_machine


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "figures" / "vmc800_16h.png")
    p.add_argument("--element-size-mm", type=float, default=50.0)
    a = p.parse_args(argv)
    m = load_machine("vmc800")
    model = build_model(m, None, a.element_size_mm)
    loads = example_loads(m, 16.0, 60.0)
    res = simulate(model, loads.time_s, m.layout().inputs(loads), store_steps=(len(loads.time_s) - 1,),
                   progress=True)
    render_png(model, res.fields_K[len(loads.time_s) - 1], a.out,
               title=f"vmc800 after the 16 h example day ({model.n} nodes), mid travel")
    print("sensor | T_end_degC")
    for s, v in zip(model.sensor_names, res.sensors_degC[-1]):
        print(f"{s} | {v:.2f}")
    print("drift_um | " + " ".join(f"{v:.2f}" for v in res.drift_um[-1]))
    print(jsonio.dumps({"benchmark": "render_demonstrator", "nodes": model.n, "png": str(a.out),
                      "sensors_end_degC": dict(zip(model.sensor_names, res.sensors_degC[-1].round(3).tolist())),
                      "drift_end_um": res.drift_um[-1].round(3).tolist()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
