"""``hybridcomp simulate``: the FE model, or with ``--rom ROM.npz`` a reduced model under the same outputs.csv contract.

The subcommand's options and the FE path are :mod:`hybridcomp.fem.cli_simulate`'s; this module, one level up
the data flow, adds the reduced-model path (fem imports nothing of rom).  A reduced model's outputs beyond the sensors
and the drift at its pose go to one table per group (:data:`GROUP_FILES`), each headed by its own columns.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hybridcomp.fem import cli_simulate as fe_cli

if TYPE_CHECKING:
    from hybridcomp.models.layout import Loads
    from hybridcomp.models.machine import Machine


#: the table of each output group beyond outputs.csv (sensors and the drift at the model's pose), when the model has it
GROUP_FILES = {"poses": "poses.csv", "feedback": "feedback.csv", "bodies": "bodies.csv"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``hybridcomp simulate`` options (the FE path's, ``--rom`` among them)."""
    fe_cli.add_arguments(p)


def run(args: argparse.Namespace) -> int:
    """Run ``hybridcomp simulate``: the FE path, or :func:`run_rom` with ``--rom``; returns the exit code."""
    return fe_cli.run(args, reduced=run_rom)


def run_rom(args: argparse.Namespace, machine: Machine, pose: dict[str, float], loads: Loads) -> int:
    """Check the ROM against the machine file and the options, simulate, write outputs.csv, the group tables, run.json."""
    from hybridcomp.fem.loads import write_outputs
    from hybridcomp.models import jsonio
    from hybridcomp.models.cli import given
    from hybridcomp.models.layout import check_result
    from hybridcomp.models.loads import check_outputs, write_columns
    from hybridcomp.rom.machine import inputs_from_columns, split_outputs
    from hybridcomp.rom.reduced import RomFileError, RomInputError, load_rom
    from hybridcomp.safeio import OutputPathError, atomic_path, check_output_dir, write_text_atomic

    t0 = time.perf_counter()
    try:
        unsupported = [(flag, bad) for flag, bad in (
            ("--element-size-mm", args.element_size_mm is not None),
            ("--fields", args.fields > 0),
            ("--png", args.png),
            ("--theta", given(args, "theta")),
            ("--time-tol-K", given(args, "time_tol_K")),
            ("--time-tol-um", given(args, "time_tol_um")),
        ) if bad]
        if unsupported:
            raise RomInputError(f"{unsupported[0][0]} applies to the FE path only, not with --rom "
                                "(the ROM's mesh is fixed and its stepping is exact)")
        rom = load_rom(args.rom, machine)
        rom_pose = rom.meta.get("pose_mm", {})
        if set(rom_pose) != set(pose) or any(not abs(pose[k] - float(rom_pose[k])) <= 1e-9 for k in pose):
            raise RomInputError(f"{args.rom}: field 'pose_mm' is {rom_pose}, but the requested pose is {pose}")
        if rom.meta.get("reference_temperature_degC") is None:
            raise RomInputError(f"{args.rom}: reduced from exported matrices, not from a machine; use hybridcomp.rom from Python")
        outputs = rom.output_layout()
        groups = {g: f for g, f in GROUP_FILES.items() if outputs.indices(g)}
        # outputs.csv and run.json were checked by the caller (fem.cli_simulate.run); the group tables are the model's
        check_output_dir(args.out, list(groups.values()), inputs=(args.loads, machine.source, args.rom), force=args.force)
        U = inputs_from_columns(rom, loads.names, loads.values, str(args.loads))
    except (RomFileError, RomInputError, OutputPathError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    ts = time.perf_counter()
    Y, _ = rom.integrate(loads.time_s, U, initial=args.initial)
    t_sim = time.perf_counter() - ts
    sensors_degC, drift_um = split_outputs(rom, Y)
    what = f"simulate --rom {args.rom}"
    check_outputs(loads.time_s, outputs.sensors, sensors_degC, drift_um, what)
    for group in groups:  # drifts and errors [m] -> [µm]
        check_result(loads.time_s, outputs.columns(group), outputs.take(Y, group) * 1e6, what)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "outputs.csv") as tmp:  # --out was checked by the caller (fem.cli_simulate.run)
        write_outputs(tmp, loads.time_s, outputs.sensors, sensors_degC, drift_um)
    for group, name in groups.items():  # drifts and errors [m] -> [µm]
        with atomic_path(out / name) as tmp:
            write_columns(tmp, loads.time_s, outputs.columns(group), outputs.take(Y, group) * 1e6)
    info = {
        "machine": machine.name,
        "machine_file": Path(machine.source).name,
        "machine_sha256": machine.sha256,
        "pose_mm": rom.meta.get("pose_mm"),
        "rom": str(args.rom),
        "rom_order": rom.order,
        "rom_id": rom.rom_id,
        "nodes": rom.meta.get("nodes"),
        "steps": len(loads.time_s) - 1,
        "timings_s": {"stepping": t_sim, "total": time.perf_counter() - t0},
        "files": ["outputs.csv", *groups.values()],
    }
    if "poses" in groups:  # what pose<k> of poses.csv is
        from hybridcomp.rom.poses import grid_of

        grid = grid_of(rom)
        info["support_poses_mm"] = {f"pose{k}": grid.pose_mm(k) for k in range(1, len(grid.poses))}
    write_text_atomic(out / "run.json", jsonio.dumps(info, indent=2))
    print(f"wrote {out / 'outputs.csv'} ({len(loads.time_s)} rows, ROM order {rom.order}, {t_sim * 1e3:.1f} ms stepping)",
          file=sys.stderr)
    return 0
