"""``hybridcomp machine``: check a machine file and show what it defines (and, with ``--mesh``, its mesh size)."""

from __future__ import annotations

import argparse
import sys

from hybridcomp.models.cli import refuse_unused
from hybridcomp.models.layout import temperature_column
from hybridcomp.models.loader import bundled_machines, load_machine
from hybridcomp.models.machine import MachineFileError


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp machine`` options."""
    p.add_argument("machine", nargs="?", help="bundled machine name or path to a machine TOML; none: list bundled machines")
    p.add_argument("--mesh", action="store_true", help="also mesh it at mid travel and report nodes and elements")
    p.add_argument("--element-size-mm", type=float, help="element size for --mesh [mm]")


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp machine``; returns the exit code (2: bad input, named on stderr)."""
    bad = refuse_unused(args, [("element_size_mm", not args.mesh, "applies with --mesh only")])
    if bad:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    if not args.machine:
        print("\n".join(bundled_machines()))
        return 0
    try:
        m = load_machine(args.machine)
    except MachineFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{m.name}: {m.description}")
    print(f"  file {m.source} (sha256 {m.sha256[:12]})")
    print(f"  bodies: {', '.join(b.name for b in m.bodies)}")
    for a in m.axes:
        print(f"  axis {a.name}: {'xyz'[a.direction]}, travel {a.travel_mm} mm, {a.n_segments} segments, moves {a.moves}")
    print(f"  heat inputs ({len(m.heat_inputs())}): {', '.join(m.layout().heat_columns)}")
    print(f"  zones: {', '.join(f'{temperature_column(z.name)} (h = {z.h_W_m2K} W/m2K, {z.air})' for z in m.zones)}")
    print(f"  sensors: {', '.join(s.name + '@' + s.body for s in m.sensors)}")
    for d in m.drives:
        where = f"scale on {d.scale_body}, {d.scale_expansion_1_K:g} 1/K" if d.feedback == "linear_scale" else \
            f"screw {d.screw_diameter_mm:g} x {d.screw_lead_mm:g} mm, {d.mounting}"
        print(f"  drive {d.axis}: {d.feedback.replace('_', ' ')} ({where}; bearings {d.fixed_bearing}, "
              f"{d.floating_bearing}; nut {d.nut})")
    if args.mesh:
        from hybridcomp.fem.mesh import mesh_machine

        try:
            mm = mesh_machine(m, None, args.element_size_mm)
        except MachineFileError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(f"  mesh at {mm.pose_mm}: {mm.n_nodes} nodes, {mm.mesh.t.shape[1]} elements")
    return 0
