"""The shared thermal operators: one set of fields for the FE model, the full system and the reduced model."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from hybridcomp.fem.operators import HasOperators, ThermalOperators
from hybridcomp.rom.krylov import ReductionError, ThermalSystem
from hybridcomp.rom.reduced import ReducedModel, RomInputError, load_rom, save_rom


def small_operators(r: int = 3, zones: int = 2, heats: int = 2, seed: int = 0) -> ThermalOperators:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(r, r))
    H = np.array([np.diag(rng.uniform(0.5, 1.0, r)) for _ in range(zones)])
    return ThermalOperators(
        M=np.eye(r) * 1e4 + 0.0, K=X @ X.T + r * np.eye(r), H=H, h_W_m2K=np.linspace(5.0, 8.0, zones),
        B=rng.normal(size=(r, heats)), Hb=H.sum(axis=2).T, C=rng.normal(size=(4, r)),
        input_names=tuple(f"q{j}_W" for j in range(heats)) + tuple(f"zone{i}_degC" for i in range(zones)),
        output_names=("T1", "dx", "dy", "dz"),
    )


def test_every_model_reads_its_operators_through_one_set_of_attributes():
    ops = small_operators()
    rom = ReducedModel(ops)
    system = ThermalSystem(ops)
    for model in (rom, system):
        assert isinstance(model, HasOperators) and model.operators is ops
        for name in ("M", "K", "H", "h_W_m2K", "B", "Hb", "C", "input_names", "output_names"):
            assert getattr(model, name) is getattr(ops, name)
        assert model.zone_names == ("zone0", "zone1") and model.heat_names == ("q0", "q1")
    assert system.h is ops.h_W_m2K


def test_with_htc_changes_one_zone_and_leaves_the_original():
    rom = ReducedModel(small_operators())
    rom._modes()  # cached products must not follow the copy
    hotter = rom.with_htc(zone1=20.0)
    np.testing.assert_array_equal(hotter.h_W_m2K, [5.0, 20.0])
    np.testing.assert_array_equal(rom.h_W_m2K, [5.0, 8.0])
    assert "modes" not in hotter._cache and hotter.K is rom.K
    with pytest.raises(KeyError, match="unknown zone 'zone9'"):
        rom.with_htc(zone9=1.0)
    with pytest.raises(ValueError, match="h of zone 'zone0' must be positive, got 0"):
        rom.with_htc(zone0=0)


def test_shapes_that_do_not_fit_are_errors_of_the_owner_naming_the_field():
    ops = small_operators()
    with pytest.raises(RomInputError, match="reduced model field 'Hb' has shape"):
        ReducedModel(dataclasses.replace(ops, Hb=ops.Hb[:, :1]))
    with pytest.raises(ReductionError, match="system field 'output_names' has shape 3, expected 4"):
        ThermalSystem(dataclasses.replace(ops, output_names=("a", "b", "c")))


def test_a_rom_file_in_the_format_written_before_the_operators_moved_still_loads(tmp_path):
    """Format 1, written field by field as ``save_rom`` always wrote it: arrays by operator name and a JSON meta."""
    ops = small_operators()
    arrays = {k: getattr(ops, k) for k in ("M", "K", "H", "h_W_m2K", "B", "Hb", "C")}
    digest = hashlib.sha256()
    for k in ("M", "K", "H", "B", "Hb", "C"):
        digest.update(np.ascontiguousarray(arrays[k], dtype=float).tobytes())
    meta = {"format": "hybridcomp-rom", "format_version": 1, "input_names": list(ops.input_names),
            "output_names": list(ops.output_names), "order": 3, "rom_id": digest.hexdigest()[:16],
            "reference_temperature_degC": 20.0}
    path = tmp_path / "old.rom.npz"
    with path.open("wb") as fh:
        np.savez_compressed(fh, **arrays, meta_json=np.array(json.dumps(meta)))
    rom = load_rom(path)
    for k, v in arrays.items():
        np.testing.assert_array_equal(getattr(rom, k), v)
    assert rom.input_names == ops.input_names and rom.output_names == ops.output_names
    assert rom.rom_id == meta["rom_id"]
    again = load_rom(save_rom(tmp_path / "again.rom.npz", rom))
    with np.load(tmp_path / "again.rom.npz") as z:
        assert sorted(z.files) == sorted([*arrays, "meta_json"])  # the same entries as before
    for k in arrays:
        np.testing.assert_array_equal(getattr(again, k), arrays[k])
