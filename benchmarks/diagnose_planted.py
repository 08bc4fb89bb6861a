"""Benchmark: the diagnosis on randomly planted cases of the job-shop day.

    python benchmarks/diagnose_planted.py [--cases 20] [--seed 2026] [--element-size-mm 150] [--case N ...]

Each case plants what a drawn generator makes (seeded) into FE runs of the bundled 16 h job-shop day at 150 mm
(sensor noise 0.02 K, drift noise 0.3 µm), and ``diagnose`` runs on the first 60 % with the whole library:

* one library effect at a random target and magnitude: a source's power scaled (any source the day drives), a
  zone's heat-transfer coefficient, a sensor's offset or lag (any sensor), the workspace air warmer, the workshop
  air reaching the surfaces with a lag, a body's expansion coefficient, the spindle bearings' speed exponent;
* two or three of them at once (different targets);
* nothing (null);
* a heat source the machine file lacks at a random point of a random body's surface (in the air or at a joint),
  with a random drive shape: on/off with the spindle or an axis, proportional to or a power law of its activity,
  constant, or switched on at the record's start;
* an effect outside the library: such a source on its own thermostat cycle, which no signal of the dataset
  switches.

Criteria (the issue's): an in-library effect is named, with every parameter within 20 % of its deviation from
the nominal model (a missing source: its shape and body, its power and exponent within 20 %, its place within one
element size); null gives "no significant discrepancy"; out of the library, no confident wrong name (an
"explained" verdict must name a missing heat source).  A planted change that stays below the noise (its largest
RMS over the validation rows under 3 noise standard deviations on every channel, column ``sigma``: a 15 min lag
of a sensor on the slow bed) cannot be asked to be named: there only a wrong name fails.  Prints one row per case
and a final JSON line.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from hybridcomp.diagnose import Dataset, diagnose, prepare_model
from hybridcomp.diagnose.data import parse_split
from hybridcomp.diagnose.problem import build_problem, first_order_lag
from hybridcomp.fem.model import build_model
from hybridcomp.fem.stepping import integrate_inputs
from hybridcomp.histogram.scenarios import jobshop_loads
from hybridcomp.models import jsonio, load_machine

from _table import table

SIGMA_K, SIGMA_UM = 0.02, 0.3
#: a planted change whose largest validation RMS is below this many noise standard deviations cannot be asked for
DETECTABLE = 3.0
SINGLE = ("power_scale", "htc", "sensor_offset", "sensor_lag", "workspace_offset", "ambient_lag", "expansion",
          "exponent")
KINDS = SINGLE + ("two", "three", "null", "located", "outside")
WEIGHTS = np.array([3, 2, 2, 2, 1, 1, 2, 1, 3, 1, 1, 3, 1], float)


@dataclasses.dataclass
class Case:
    kind: str
    description: str
    expected: list  # [(key, truth, nominal)] for in-library effects (a missing source: + place [mm], body)
    sensors: np.ndarray
    drift: np.ndarray
    columns: dict
    drop: tuple


def _fe(model, loads, U):
    r = integrate_inputs(model, loads.time_s, U, scheme="theta", theta=0.5)
    return r.sensors_degC, r.drift_um


def _col(loads, name):
    return loads.names.index(name)


def _driven_sources(machine, U, loads):
    """Fixed sources whose power varies over the day (a scale of theirs shows)."""
    out = []
    for s in machine.heat_sources:
        if s.kind == "fixed" and s.driver is not None and np.ptp(U[:, _col(loads, f"{s.name}_W")]) > 0.2 * s.power_W:
            out.append(s.name)
    return out


def plant_inputs(kind, machine, loads, U, rng, used):
    """Edit the inputs ``U`` for one library effect acting on the machine; returns (edit of outputs, expected,
    model edit, dataset columns, dropped columns, description)."""
    t_ref = machine.reference_temperature_degC
    if kind == "power_scale":
        src = rng.choice([s for s in _driven_sources(machine, U, loads) if s not in used])
        f = float(rng.choice([rng.uniform(0.55, 0.75), rng.uniform(1.3, 1.6)]))
        U[:, _col(loads, f"{src}_W")] *= f
        return None, [(("power_scale", src), f, 1.0)], None, {}, (), f"{src} power x {f:.2f}", src
    if kind == "htc":
        z = rng.choice([z for z in machine.zones if z.name not in used and z.name != "floor"])
        h = float(z.h_W_m2K * rng.uniform(1.4, 1.7))
        return None, [(("htc", z.name), h, z.h_W_m2K)], ("htc", z.name, h), {}, (), f"h of {z.name} = {h:.1f}", z.name
    if kind == "workspace_offset":
        dT = float(rng.uniform(1.0, 2.0))
        for z in machine.zones:
            if z.air == "workspace":
                U[:, _col(loads, f"{z.name}_degC")] += dT
        return None, [(("workspace_offset", ""), dT, 0.0)], None, {}, (), f"workspace air +{dT:.2f} K", "ws"
    if kind == "ambient_lag":
        tau_h = float(rng.uniform(1.5, 3.0))
        amb = next(z for z in machine.zones if z.air == "ambient")
        tamb = loads.values[:, _col(loads, f"{amb.name}_degC")]
        for z in machine.zones:
            if z.air == "ambient":
                U[:, _col(loads, f"{z.name}_degC")] = first_order_lag(loads.time_s, tamb - t_ref, tau_h * 3600)
        drop = tuple(f"{z.name}_degC" for z in machine.zones if z.air == "ambient")
        return (None, [(("ambient_lag", ""), (1.0, tau_h), (0.0, None))], None, {"Tamb_degC": tamb}, drop,
                f"ambient air lag {tau_h:.2f} h", "amb")
    if kind == "expansion":
        b = rng.choice([b.name for b in machine.bodies if b.name not in used and b.name not in ("table", "saddle")])
        body = machine.body(b)
        a0 = machine.materials[body.material].expansion_1_K * 1e6
        a = float(a0 * rng.uniform(1.15, 1.3))
        return None, [(("expansion", b), a, a0)], ("expansion", b, a), {}, (), f"alpha of {b} = {a:.2f}e-6", b
    if kind == "exponent":
        src = machine.heat_source("spindle_bearing_front")
        n = float(rng.uniform(2.2, 2.8))
        j = _col(loads, f"{src.name}_W")
        f = (U[:, j] / src.power_W) ** (1 / src.exponent)
        U[:, j] = src.power_W * f**n
        return (None, [(("exponent", src.name), n, src.exponent)], None, {}, (), f"{src.name} exponent {n:.2f}",
                src.name)
    if kind == "sensor_offset":
        k = int(rng.integers(len(machine.sensors)))
        name = machine.sensors[k].name
        off = float(rng.choice([-1, 1]) * rng.uniform(0.3, 0.6))

        def edit(s, d):
            s[:, k] += off
        return edit, [(("sensor_offset", f"{name}_degC"), (off, 0.0), (0.0, 0.0))], None, {}, (), \
            f"{name} reads {off:+.2f} K", name
    if kind == "sensor_lag":
        k = int(rng.integers(len(machine.sensors)))
        name = machine.sensors[k].name
        tau_min = float(rng.uniform(15.0, 30.0))

        def edit(s, d):
            s[:, k] = first_order_lag(loads.time_s, s[:, k], tau_min * 60)
        return edit, [(("sensor_lag", f"{name}_degC"), tau_min, 0.0)], None, {}, (), f"{name} lags {tau_min:.0f} min", name
    raise AssertionError(kind)


def _model_with(machine, fe, edits, h_mm):
    model = fe
    for e in edits:
        if e[0] == "htc":
            model = model.with_htc(**{e[1]: e[2]})
        elif e[0] == "expansion":
            body = machine.body(e[1])
            mats = dict(machine.materials)
            mats["planted"] = dataclasses.replace(machine.materials[body.material], name="planted",
                                                  expansion_1_K=e[2] * 1e-6)
            bodies = tuple(dataclasses.replace(b, material="planted") if b.name == e[1] else b for b in machine.bodies)
            model = build_model(dataclasses.replace(machine, materials=mats, bodies=bodies), None, h_mm)
            if any(x[0] == "htc" for x in edits):
                model = model.with_htc(**{x[1]: x[2] for x in edits if x[0] == "htc"})
    return model


def _surface_point(machine, rng):
    """A random point on a random face of a random body [mm] (faces in the air and joints alike)."""
    body = machine.bodies[int(rng.integers(len(machine.bodies)))]
    lo, hi = np.asarray(body.box_mm[0]), np.asarray(body.box_mm[1])
    face = int(rng.integers(6))
    p = rng.uniform(lo, hi)
    p[face // 2] = (lo if face % 2 == 0 else hi)[face // 2]
    return body, p, np.minimum(100.0, hi - lo)


def _with_source(machine, fe, loads, U, body, p, size, P):
    """FE channels with a heat source the machine file lacks: ``P`` [W] per sample on a patch at ``p``."""
    src = dataclasses.replace(machine.heat_sources[0], name="planted", kind="fixed", body=body.name, axis=None,
                              driver=None, position_mm=tuple(p), size_mm=tuple(size), power_W=1.0, power_table=None)
    model = fe.with_heat_input(src)
    m = len(fe.heat_names)
    return _fe(model, loads, np.hstack([U[:, :m], P[:, None], U[:, m:]]))


#: drive shapes of a planted missing source (the library's, ``diagnose.locate.shapes``)
FORMS = ("on/off", "on/off", "proportional", "power law", "constant", "switched on")


def make_case(kind, machine, fe, loads, rng, h_mm, activity=None) -> Case:
    U = machine.layout().inputs(loads)
    if kind == "null":
        s, d = _fe(fe, loads, U)
        return Case(kind, "nothing planted", [], s, d, {}, ())
    if kind == "outside":  # a cabinet heater on its own thermostat: no driver of the dataset switches it
        body, p, size = _surface_point(machine, rng)
        power = float(rng.uniform(40.0, 80.0))
        period_s, duty = float(rng.uniform(1800, 3600)), float(rng.uniform(0.3, 0.6))
        on = (((loads.time_s - loads.time_s[0]) % period_s) < duty * period_s).astype(float)
        s, d = _with_source(machine, fe, loads, U, body, p, size, power * on)
        return Case(kind, f"{power:.0f} W on {body.name} at {np.round(p).tolist()} mm, on a {period_s / 60:.0f} min "
                    f"thermostat cycle ({duty:.0%} on)", [], s, d, {}, ())
    if kind == "located":  # a missing source anywhere, with one of the library's drive shapes
        body, p, size = _surface_point(machine, rng)
        form = str(rng.choice(FORMS))
        driver = None if form in ("constant", "switched on") else str(rng.choice(list(activity)))
        act = np.ones(loads.time_s.size) if driver is None else activity[driver]
        if form == "switched on":
            act = np.r_[0.0, act[1:]]
        power = float(rng.uniform(40.0, 80.0))
        n = float(rng.uniform(1.6, 2.4)) if form == "power law" else None
        f = {"on/off": (act > 0.02).astype(float), "proportional": act, "constant": act, "switched on": act}.get(form)
        f = act**n if form == "power law" else f
        if form in ("proportional", "power law"):
            power = float(rng.uniform(150.0, 300.0))  # at full activity, which the day seldom reaches
        s, d = _with_source(machine, fe, loads, U, body, p, size, power * f)
        shape = {"constant": "constant", "switched on": "on from the start", "power law": f"{driver} power law"}.get(
            form, f"{driver} {form}")
        truth = (power,) if n is None else (power, n)
        what = f", exponent {n:.2f}" if n is not None else ""
        at_pose = p + machine.body_offset_mm(body.name, fe.mesh.pose_mm)
        return Case(kind, f"{power:.0f} W on {body.name} at {np.round(p).tolist()} mm, {shape}{what}",
                    [(("located_source", shape), truth, tuple([None] * len(truth)), tuple(at_pose), body.name)],
                    s, d, {}, ())
    n_effects = {"two": 2, "three": 3}.get(kind, 1)
    kinds = [kind] if n_effects == 1 else list(rng.choice([k for k in SINGLE if k not in ("ambient_lag", "exponent")],
                                                          n_effects, replace=False))
    used, expected, edits, outs, columns, drop, desc = set(), [], [], [], {}, (), []
    for k in kinds:
        edit, exp, model_edit, cols, dr, text, target = plant_inputs(k, machine, loads, U, rng, used)
        used.add(target)
        expected += exp
        if model_edit is not None:
            edits.append(model_edit)
        if edit is not None:
            outs.append(edit)
        columns |= cols
        drop += dr
        desc.append(text)
    s, d = _fe(_model_with(machine, fe, edits, h_mm), loads, U)
    for edit in outs:
        edit(s, d)
    return Case(kind, "; ".join(desc), expected, s, d, columns, drop)


def dataset(machine, loads, case: Case, seed: int) -> Dataset:
    rng = np.random.default_rng(seed)
    cols = {n: loads.values[:, j] for j, n in enumerate(loads.names) if n not in case.drop}
    cols.update(case.columns)
    for k, s in enumerate(machine.sensors):
        cols[f"{s.name}_degC"] = case.sensors[:, k] + rng.normal(0, SIGMA_K, case.sensors.shape[0])
    for k, d in enumerate(("dx", "dy", "dz")):
        cols[f"{d}_um"] = case.drift[:, k] + rng.normal(0, SIGMA_UM, case.drift.shape[0])
    return Dataset(loads.time_s, cols, "planted")


def within(params, truth, nominal) -> bool:
    """Every parameter within 20 % of the effect's deviation from nominal (of its value, without a nominal)."""
    truth, nominal = np.atleast_1d(truth), np.atleast_1d(np.array(nominal, dtype=object))
    scale = max((abs(v - n) for v, n in zip(truth, nominal) if n is not None), default=0.0)
    for p, v, n in zip(params, truth, nominal):
        limit = 0.2 * abs(v) if n is None else 0.2 * scale
        if abs(p - v) > limit:
            return False
    return True


def detectability(case: Case, nominal: Case, start: int) -> float:
    """The planted change's largest RMS over the validation rows, in noise units (channels: sensors, drift)."""
    ds = np.abs(case.sensors[start:] - nominal.sensors[start:])
    dd = np.abs(case.drift[start:] - nominal.drift[start:])
    return float(max(np.sqrt(np.mean(ds**2, axis=0)).max() / SIGMA_K, np.sqrt(np.mean(dd**2, axis=0)).max() / SIGMA_UM))


def judge(case: Case, d, snr: float, h_mm: float) -> tuple[bool, str]:
    named = {f.candidate.key: f.params for f in d.causes}
    if case.expected and snr < DETECTABLE:  # below the noise: no name is right, a wrong name is not
        keys = {e[0] for e in case.expected}
        said = {(k[0], k[1].split("|")[-1]) if k[0] == "located_source" else k for k in named}
        ok = d.verdict == "no significant discrepancy" or (said <= keys and bool(named))
        return ok, f"below noise ({snr:.1f} sigma): {d.verdict} " + ", ".join(f"{k[0]} {k[1]}" for k in named)
    if case.kind == "null":
        return d.verdict == "no significant discrepancy", d.verdict
    if case.kind == "outside":
        ok = d.verdict != "explained" or all(k[0] in ("missing_source", "located_source") for k in named)
        return ok, f"{d.verdict}: " + ", ".join(f"{k[0]} {k[1]}" for k in named)
    if case.kind == "located":
        (_, shape), truth, nominal, where, _body = case.expected[0]
        found = [f for f in d.causes if f.candidate.kind == "located_source"]
        if d.verdict != "explained" or len(d.causes) != 1 or len(found) != 1:
            return False, f"{d.verdict}: " + ", ".join(f"{k[0]} {k[1]}" for k in named)
        ok, said = _judge_located(found[0], case.expected[0], h_mm)
        return ok, said
    if case.kind == "hidden":
        return judge_hidden(case, d, h_mm)
    keys = [e[0] for e in case.expected]
    if d.verdict != "explained" or set(named) != set(keys):
        return False, f"{d.verdict}: " + ", ".join(f"{k[0]} {k[1]}" for k in named)
    ok = all(within(named[k], truth, nominal) for k, truth, nominal in case.expected)
    return ok, "named; " + ("parameters within 20 %" if ok else "parameters off: " + ", ".join(
        f"{k[0]} {np.round(named[k], 3).tolist()} vs {np.round(np.atleast_1d(t).astype(float), 3).tolist()}"
        for k, t, _ in case.expected))


def _judge_located(f, expected, h_mm: float) -> tuple[bool, str]:
    """A located source against the planted one: its shape, its power (and exponent) within 20 %, its place within
    one element size (at the model's pose: at a joint the heat may be placed on either body)."""
    from hybridcomp.diagnose.locate import located_at, location_uncertainty_mm

    (_, shape), truth, nominal, where, _body = expected
    miss_mm = float(np.linalg.norm(located_at(f.candidate, f.params)[1] - np.asarray(where)))
    ok_shape = f.candidate.target.endswith("|" + shape)
    ok = ok_shape and miss_mm <= h_mm and within(f.params[:len(truth)], truth, nominal)
    return ok, (f"located {miss_mm:.0f} mm off (± {location_uncertainty_mm(f.candidate, f.uncertainty):.0f}), "
                f"{f.candidate.target.split('|')[1]}, {np.round(f.params[:len(truth)], 2).tolist()} vs "
                f"{np.round(truth, 2).tolist()}")


def judge_hidden(case: Case, d, h_mm: float) -> tuple[bool, str]:
    """A hidden-style case: the located source as :func:`_judge_located`, the second effect named within 20 %."""
    named = {f.candidate.key: f for f in d.causes}
    found = [f for f in d.causes if f.candidate.kind == "located_source"]
    others = case.expected[1:]
    text = f"{d.verdict}: " + ", ".join(f"{k[0]} {k[1]}" for k in named)
    if d.verdict != "explained" or len(found) != 1 or len(d.causes) != 1 + len(others):
        return False, text
    ok, said = _judge_located(found[0], case.expected[0], h_mm)
    for key, truth, nominal in others:
        got = named.get(key)
        good = got is not None and within(got.params, truth, nominal)
        ok = ok and good
        said += f"; {key[0]} {key[1]} " + (f"{np.round(got.params, 2).tolist()} vs {np.round(np.atleast_1d(truth), 2).tolist()}"
                                           if got is not None else "not named")
    return ok, said


#: the hidden-style cases' reduced order: the smallest of 150, 200, 250, 300, 400 whose response to every source
#: they plant is within a third of the sensor noise (RMS over the day against FE, at 150 mm, seed 11;
#: ``benchmarks/rom_surface_error.py``): at 150 a source near the bed's lower edge was off by 0.014 K RMS at its one
#: sensor and put on the wrong face.  A model for a diagnosis can be chosen so: ``diagnose.reduction.surface_order``
HIDDEN_ORDER = 400
#: the hidden-style cases' drive shapes: (form, driver)
HIDDEN_FORMS = (("on/off", "spindle"), ("constant", None), ("power law", "spindle"))


def hidden_cases(machine, fe, loads, rng, h_mm, activity, sites=None, sources=None) -> list[Case]:
    """Sources between the search's sites and the machine's own patches, one per drive shape of ``HIDDEN_FORMS``,
    alone and with a sensor effect (a lag or an offset of the sensor that varies most), at a random point of a random
    body's surface at least a quarter element from every search site and one element from every existing source.
    ``sources``: a list that gets each case's planted source, (body, point [mm], patch size [mm], power per sample [W])."""
    out = []
    existing = [np.asarray(s.position_mm, float) + machine.body_offset_mm(s.body, fe.mesh.pose_mm)
                for s in machine.heat_sources if s.kind == "fixed"]
    for with_sensor in (False, True):
        for form, driver in HIDDEN_FORMS:
            for _ in range(200):
                body, p, size = _surface_point(machine, rng)
                at_pose = p + machine.body_offset_mm(body.name, fe.mesh.pose_mm)
                off_site = sites is None or np.linalg.norm(sites - at_pose, axis=1).min() >= 0.25 * h_mm
                if off_site and min(np.linalg.norm(at_pose - e) for e in existing) >= h_mm:
                    break
            act = np.ones(loads.time_s.size) if driver is None else activity[driver]
            if form == "on/off":
                f, power, n = (act > 0.02).astype(float), float(rng.uniform(30.0, 60.0)), None
            elif form == "constant":
                f, power, n = act, float(rng.uniform(30.0, 60.0)), None
            else:
                n = float(rng.uniform(1.6, 2.4))
                f, power = act**n, float(rng.uniform(150.0, 300.0))
            U = machine.layout().inputs(loads)
            s, d = _with_source(machine, fe, loads, U, body, p, size, power * f)
            if sources is not None:
                sources.append((body, p, size, power * f))
            shape = {"constant": "constant", "power law": f"{driver} power law"}.get(form, f"{driver} {form}")
            truth = (power,) if n is None else (power, n)
            expected = [(("located_source", shape), truth, tuple([None] * len(truth)), tuple(at_pose), body.name)]
            desc = f"{power:.0f} W on {body.name} at {np.round(p).tolist()} mm, {shape}" + (
                f", exponent {n:.2f}" if n is not None else "")
            if with_sensor:
                k = int(np.argmax(np.ptp(s, axis=0)))  # the sensor that varies most: its lag shows
                name = machine.sensors[k].name
                if rng.uniform() < 0.5:
                    tau_min = float(rng.uniform(20.0, 40.0))
                    s[:, k] = first_order_lag(loads.time_s, s[:, k], tau_min * 60)
                    expected.append((("sensor_lag", f"{name}_degC"), tau_min, 0.0))
                    desc += f"; {name} lags {tau_min:.0f} min"
                else:
                    off = float(rng.choice([-1, 1]) * rng.uniform(0.3, 0.6))
                    s[:, k] += off
                    expected.append((("sensor_offset", f"{name}_degC"), (off, 0.0), (0.0, 0.0)))
                    desc += f"; {name} reads {off:+.2f} K"
            out.append(Case("hidden", desc, expected, s, d, {}, ()))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", type=int, default=20)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--element-size-mm", type=float, default=150.0)
    p.add_argument("--dt", type=float, default=120.0, help="sampling of the day [s]")
    p.add_argument("--order", type=int, default=None,
                   help="the reduced model's order (default: 400 with --hidden, 150 otherwise; "
                        "benchmarks/rom_surface_error.py measures the choice)")
    p.add_argument("--hidden", action="store_true",
                   help="the hidden-style cases instead of random ones: a source between the search's sites and the "
                        "machine's patches, on/off, constant and power law, alone and with a sensor effect (6 cases; "
                        "--cases N: the first N), diagnosed with the discretisation floor and continuous placement")
    p.add_argument("--case", type=int, action="append", default=None,
                   help="run only this case (1-based; repeatable), the others drawn all the same (the same planted cases)")
    a = p.parse_args(argv)
    machine = load_machine("vmc800")
    loads = jobshop_loads(machine).resample(a.dt)
    fe = build_model(machine, None, a.element_size_mm)
    t0 = time.perf_counter()
    rom = prepare_model(machine, model=fe, order=a.order or (HIDDEN_ORDER if a.hidden else 150))
    prep_s = time.perf_counter() - t0
    nominal = make_case("null", machine, fe, loads, np.random.default_rng(0), a.element_size_mm)
    ds0 = dataset(machine, loads, nominal, seed=0)
    activity = build_problem(machine, rom, ds0, parse_split("0:60%", ds0.time_s)).activity
    start = int(0.6 * loads.time_s.size)
    rng = np.random.default_rng(a.seed)
    rows, records = [], []
    if a.hidden:
        from hybridcomp.diagnose.locate import sites_for

        pb = build_problem(machine, rom, ds0, parse_split("0:60%", ds0.time_s))
        hidden = hidden_cases(machine, fe, loads, rng, a.element_size_mm, activity,
                              sites_for(pb, place="continuous").position_mm)
    for i in range(min(len(hidden), a.cases) if a.hidden else a.cases):
        if a.hidden:
            case, kind = hidden[i], "hidden"
        else:
            kind = str(rng.choice(KINDS, p=WEIGHTS / WEIGHTS.sum()))
            case = make_case(kind, machine, fe, loads, rng, a.element_size_mm, activity)
        if a.case and i + 1 not in a.case:
            continue
        t0 = time.perf_counter()
        # the hidden cases with the opt-in discretisation floor and continuous placement; the random ones as the
        # diagnosis runs by default
        opts = {"discretisation": True, "place": "continuous"} if a.hidden else {"discretisation": False, "place": "patch"}
        d = diagnose(machine, dataset(machine, loads, case, seed=a.seed + i), "0:60%", rom=rom, **opts)
        snr = detectability(case, nominal, start)
        ok, said = judge(case, d, snr, a.element_size_mm)
        rows.append({"case": i + 1, "kind": kind, "planted": case.description, "sigma": f"{snr:.0f}", "result": said,
                     "ok": "yes" if ok else "NO", "s": f"{time.perf_counter() - t0:.0f}"})
        records.append({"kind": kind, "planted": case.description, "verdict": d.verdict, "ok": ok, "snr": snr,
                        "named": [[*f.candidate.key, [float(x) for x in np.atleast_1d(f.params)]] for f in d.causes]})
        print(f"{i + 1:2d} {kind:>16} {'ok' if ok else 'NO':>3}  {case.description} -> {said}", file=sys.stderr)
    if rows:
        print(table(rows, list(rows[0])))
    passed = sum(r["ok"] for r in records)
    print(f"{passed} of {len(records)} cases pass (model preparation {prep_s:.0f} s)")
    print(jsonio.dumps({"benchmark": "diagnose_planted" + ("_hidden" if a.hidden else ""), "cases": len(records),
                        "passed": passed,
                        "element_size_mm": a.element_size_mm, "seed": a.seed, "records": records}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
