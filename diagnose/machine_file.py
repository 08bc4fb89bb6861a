"""The extended machine file: the named causes written back into the machine's TOML.

What a machine file can express (``models/README.md``): a source's ``power_W`` and ``exponent``,
a zone's ``h_W_m2K``, a new fixed heat source with a driver (at an existing patch, or at the place a search over
the surface found), a body's material (so a body-specific
expansion coefficient is a new material).  What it cannot express is listed by
:func:`not_expressible`: air temperatures (ambient lag, workspace offset) are loads, sensor lag
and offset are properties of the measurement, and a zone has one coefficient, not one for motion
and one for standstill.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from hybridcomp.models.toml import dumps_toml, read_toml
from hybridcomp.safeio import write_text_atomic

NOT_EXPRESSIBLE = {
    "ambient_lag": "air temperatures are loads, not machine data: feed the lagged workshop air to the ambient zones' "
                   "`<zone>_degC` columns of the loads CSV",
    "workspace_offset": "air temperatures are loads, not machine data: add the offset to the workspace zones' "
                        "`<zone>_degC` columns of the loads CSV (or measure the enclosure air)",
    "htc_motion": "a zone has one heat-transfer coefficient in the machine file; the two fitted values need a "
                  "motion-dependent coefficient the model does not have (the file keeps the nominal value)",
    "sensor_lag": "a property of the measurement, not of the structure: correct the sensor reading or its mounting",
    "sensor_offset": "a property of the measurement, not of the structure: recalibrate the channel",
}


def _clean_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)


def not_expressible(causes) -> list[tuple[str, str]]:
    """(label, reason) of the causes the machine file cannot hold."""
    return [(f.candidate.label, NOT_EXPRESSIBLE[f.candidate.kind]) for f in causes if f.candidate.kind in NOT_EXPRESSIBLE]


def extended_machine(machine, causes, drives=()) -> dict:
    """The machine file's dictionary with every expressible cause applied.

    ``drives``: the drive effects named from probes at several poses (:class:`hybridcomp.diagnose.drives.DriveFit`):
    a nut's heat into its screw scaled, a screw's material with the fitted α, a scale's α, a seized floating bearing
    as ``mounting = "pre-stretched"`` (held at both ends).
    """
    src = Path(machine.source)
    data, _ = read_toml(src)
    mesh = data.get("mesh", {})
    if "file" in mesh and not Path(mesh["file"]).is_absolute():
        mesh["file"] = str((src.parent / mesh["file"]).resolve())
    m = data.setdefault("machine", {})
    m["name"] = _clean_name(f"{m.get('name', machine.name)}_extended")
    applied = []
    sources = data.get("heat_sources", [])
    zones = data.get("zones", [])
    bodies = data.get("bodies", [])
    for f in causes:
        c, p = f.candidate, [float(v) for v in f.params]
        if c.kind == "power_scale":
            s = next(s for s in sources if s["name"] == c.target)
            s["power_W"] = round(float(s["power_W"]) * p[0], 6)
            applied.append(f"heat_sources '{c.target}': power_W × {p[0]:.4g} = {s['power_W']:.4g} W")
        elif c.kind == "exponent":
            s = next(s for s in sources if s["name"] == c.target)
            s["exponent"] = round(p[0], 6)
            applied.append(f"heat_sources '{c.target}': exponent = {p[0]:.4g}")
        elif c.kind == "htc":
            z = next(z for z in zones if z["name"] == c.target)
            z["h_W_m2K"] = round(p[0], 6)
            applied.append(f"zones '{c.target}': h_W_m2K = {p[0]:.4g} W/(m2 K)")
        elif c.kind == "missing_source":
            loc, driver = c.target.split("|")
            s0 = next(s for s in sources if s["name"] == loc)
            name = _clean_name(f"{loc}_by_{driver}")
            new = {"name": name, "kind": "fixed", "body": s0["body"], "position_mm": list(s0["position_mm"]),
                   "size_mm": list(s0.get("size_mm", [20.0, 20.0, 20.0])), "power_W": round(p[0], 6), "driver": driver,
                   "exponent": 1.0}
            sources.append(new)
            applied.append(f"heat_sources: new '{name}' at {loc} ({s0['body']}), driven by {driver}, {p[0]:.4g} W at full load")
        elif c.kind == "located_source":
            new = located_source_entry(c, p, {b["name"]: b for b in bodies})
            sources.append(new)
            where = ", ".join(f"{v:g}" for v in new["position_mm"])
            if c.info.get("face") is not None:  # placed continuously on its face (opt-in): 1σ from the fit
                from hybridcomp.diagnose.locate import location_uncertainty_mm

                spread = f"± {location_uncertainty_mm(c, f.uncertainty):.0f} mm, 1σ from the fit"
            else:
                spread = f"± {c.info['location_spread_mm']:.0f} mm"
            applied.append(f"heat_sources: new '{new['name']}' on {new['body']} at ({where}) mm "
                           f"({spread}), {p[0]:.4g} W, {c.info['form']}"
                           + (f" with {c.info['driver']}" if c.info.get("driver") else ""))
        elif c.kind == "expansion":
            b = next(b for b in bodies if b["name"] == c.target)
            mats = data["materials"]
            new_mat = _clean_name(f"{b['material']}_{c.target}")
            mats[new_mat] = dict(mats[b["material"]])
            mats[new_mat]["expansion_1_K"] = float(f"{p[0] * 1e-6:.6g}")
            b["material"] = new_mat
            applied.append(f"bodies '{c.target}': material '{new_mat}' with expansion_1_K = {p[0]:.4g}e-6 1/K")
    data["heat_sources"] = sources
    applied += _apply_drives(data, drives)
    data["_applied"] = applied
    return data


def _apply_drives(data: dict, drives) -> list[str]:
    """Apply the named drive effects to the machine file's ``[[drives]]`` tables; returns what was applied."""
    applied = []
    tables = {d["axis"]: d for d in data.get("drives", [])}
    for f in drives:
        c, v = f.candidate, float(f.value)
        d = tables[c.axis]
        if c.kind == "nut_heat":
            d["nut_screw_W"] = round(float(d.get("nut_screw_W", 0.0)) * v, 6)
            applied.append(f"drives '{c.axis}': nut_screw_W × {v:.4g} = {d['nut_screw_W']:.4g} W")
        elif c.kind == "screw_expansion":
            mats = data["materials"]
            new_mat = _clean_name(f"{d['screw_material']}_{c.axis}_screw")
            mats[new_mat] = dict(mats[d["screw_material"]])
            mats[new_mat]["expansion_1_K"] = float(f"{v * 1e-6:.6g}")
            d["screw_material"] = new_mat
            applied.append(f"drives '{c.axis}': screw material '{new_mat}' with expansion_1_K = {v:.4g}e-6 1/K")
        elif c.kind == "scale_expansion":
            d["scale_expansion_1_K"] = float(f"{v * 1e-6:.6g}")
            applied.append(f"drives '{c.axis}': scale_expansion_1_K = {v:.4g}e-6 1/K")
        elif c.kind == "bearing_held":
            d["mounting"] = "pre-stretched"
            applied.append(f"drives '{c.axis}': mounting = 'pre-stretched' (the seized floating bearing holds the "
                           f"screw; fitted share {v:.3g} of its elongation held, the file holds all of it)")
    return applied


def located_source_entry(c, p, bodies: dict) -> dict:
    """A located source as a ``[[heat_sources]]`` table.

    Its patch sits at the fitted place; its drive shape becomes a power law
    (proportional: exponent 1; power law: the fitted exponent), a power table that switches on at 2 % load (on/off),
    or no driver (constant).
    """
    from hybridcomp.diagnose.locate import ON_THRESHOLD, located_at

    info = c.info
    box = bodies[info["body"]].get("box_mm")
    pos = located_at(c, p)[0] if "offset_mm" in info else np.asarray(info["location_mm"], float)
    if box is not None:
        pos = np.clip(pos, np.asarray(box[0], float), np.asarray(box[1], float))
    name = _clean_name(f"found_{info['body']}_{info['form']}_{info.get('driver') or 'always'}")
    new = {"name": name, "kind": "fixed", "body": info["body"], "position_mm": [round(float(v), 1) for v in pos],
           "size_mm": [float(info["patch_mm"])] * 3, "power_W": round(float(p[0]), 6)}
    if info.get("driver"):
        new["driver"] = info["driver"]
        if info["form"] == "on/off":
            new["power_table"] = [[0.0, 0.0], [ON_THRESHOLD, 1.0], [1.0, 1.0]]
        else:
            new["exponent"] = round(float(p[1]), 6) if info["form"] == "power law" else 1.0
    return new


def write_extended_machine(machine, causes, path: str | Path, drives=()) -> tuple[Path, list[str], list[tuple[str, str]]]:
    """Write ``machine_extended.toml``; returns the path, the applied changes and the causes it cannot hold.

    ``drives``: the named drive effects (:func:`extended_machine`).
    """
    data = extended_machine(machine, causes, drives)
    applied = data.pop("_applied")
    missing = not_expressible(causes)
    head = [f"# {machine.name} extended by hybridcomp diagnose from {Path(machine.source).name}",
            "# changes applied:"] + [f"#   {a}" for a in applied or ["(none)"]]
    if missing:
        head.append("# causes found that a machine file cannot express:")
        head += [f"#   {label}: {why}" for label, why in missing]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, "\n".join(head) + "\n\n" + dumps_toml(data))
    return path, applied, missing
