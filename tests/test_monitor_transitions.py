"""The monitor's pure transitions (:mod:`hybridcomp.monitor.transitions`) driven directly, with no database.

A 1.5 h stretch of the job-shop day at 0.1 Hz on the shared coarse reduced model, with a sensor gap and probes: each
call leaves its input state as it was (frozen, arrays not changed in place), the same inputs give the same outputs,
the offsets and events are what the :class:`~hybridcomp.monitor.daemon.Monitor` shell writes on the same readings,
and a monitoring decision whose active set is wrong switches to a stored set that fits: an activate command, the
stored sets asked for once, no database.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math

import numpy as np
import pytest

from hybridcomp.models import jsonio
from hybridcomp.monitor import transitions as T
from hybridcomp.monitor.config import parse_config
from hybridcomp.monitor.sources import Reading

PKEY = "X=0,Y=0,Z=0"
POSE = {"X": 0.0, "Y": 0.0, "Z": 0.0}
NOW_UNIX = 1.7e9


class FixedClock:
    def unix(self) -> float:
        return NOW_UNIX

    def monotonic(self) -> float:
        return 0.0


@pytest.fixture(scope="module")
def day(machine, small_rom):
    """Readings (a T2 dropout long enough to degrade it, probes at the model's pose) and the model's drift [µm]."""
    from hybridcomp.monitor.example import jobshop_samples, rom_outputs

    s = jobshop_samples(machine, hours=1.5, rate_hz=0.1)
    T_degC, drift = rom_outputs(machine, small_rom, s, 60.0)
    names = [n.name for n in machine.sensors]
    out = []
    for i in range(len(s)):
        sensors = dict(zip(names, map(float, T_degC[i])))
        if 100 <= i < 130:
            sensors["T2"] = math.nan
        probe = tuple(float(v) + 0.3 for v in drift[i]) if i in (200, 203, 400) else None
        out.append(Reading(float(s.time_s[i]), tuple(map(float, s.position_mm[i])), float(s.spindle_rpm[i]), sensors,
                           {s.air_names[0]: float(s.air_degC[i, 0])}, probe))
    return out, T_degC, drift


@pytest.fixture(scope="module")
def cfg(tmp_path_factory):
    data = {"monitor": {"machine": "vmc800", "database": "unused.db", "rom": "unused.rom.npz", "pose_mm": POSE,
                        "increment_s": 60.0},
            "compensation": {"max_offset_um": 100.0, "max_step_um": 2.0},
            "sensors": {"hold_s": 60.0, "frozen_s": 1800.0, "spike_K": 2.0},
            "validity": {"bump_um": 100.0},
            "source": {"kind": "replay", "path": "unused.csv", "speed": 0}, "sink": {"kind": "none"},
            "regeneration": {"enabled": False}}
    return parse_config(data, "test.toml", tmp_path_factory.mktemp("cfg"))


@pytest.fixture(scope="module")
def ctx(cfg, machine, small_rom):
    return T.context(cfg, machine, small_rom, PKEY)


def fit_set(machine, T_degC, drift, name):
    """A CD set fitted to ``drift`` [µm] over the trace's sensors, referenced at the first sample."""
    from hybridcomp.chardiag.fit import FitOptions, fit_cd_set

    table = {f"{sn.name}_degC": T_degC[:, j] for j, sn in enumerate(machine.sensors)}
    table |= {"dx_um": drift[:, 0], "dy_um": drift[:, 1], "dz_um": drift[:, 2]}
    opts = FitOptions(n_support=6, select="bic", max_inputs=4, max_full_dims=1, min_target_range_um=0.5)
    names = [sn.name for sn in machine.sensors]
    return fit_cd_set(table, machine=machine.name, machine_sha256=machine.sha256, pose_mm=POSE, load_case=name,
                      t_reference_degC=dict(zip(names, map(float, T_degC[0]))), options=opts)


@pytest.fixture(scope="module")
def sets(machine, day, tmp_path_factory):
    """A database with a set of the wrong sign (active) and the right one; their CDs as the database gives them."""
    from hybridcomp.chardiag.cd import CDSet
    from hybridcomp.chardiag.db import CDDatabase

    _, T_degC, drift = day
    path = tmp_path_factory.mktemp("db") / "cd.db"
    db = CDDatabase(path)
    try:
        ids = {"wrong": db.add_set(fit_set(machine, T_degC, -drift, "wrong"), "wrong"),
               "right": db.add_set(fit_set(machine, T_degC, drift, "right"), "right")}
        db.activate(machine.name, PKEY, ids["wrong"], "initial")
        loaded = {k: CDSet({d: db.get(i) for d, i in v.items()}, v) for k, v in ids.items()}
    finally:
        db.close()
    return path, ids, loaded


def stored(sets, asked=None):
    """The stored sets of the database as a list (no database): the right one; ``asked`` collects the queries."""
    _, ids, loaded = sets

    def query(q: T.SetQuery):
        if asked is not None:
            asked.append(q)
        return [T.StoredSet(ids["right"], "right", 0.0, dict(loaded["right"].cds))]
    return query


def replay(ctx, state, readings, stored_sets=T.no_stored_sets, check=None):
    """Every reading through :func:`on_reading`; the steps (``check(before, step)`` after each call)."""
    steps = []
    for r in readings:
        step = T.on_reading(ctx, state, r, stored_sets, NOW_UNIX)
        if check is not None:
            check(state, step)
        steps.append(step)
        state = step.state
    return steps


def same(a, b) -> bool:
    """Deep equality: dataclasses field by field, arrays bit for bit (NaN equal to NaN), floats with NaN == NaN."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.dtype == b.dtype and a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if hasattr(a, "__dict__") and type(a) is type(b) and not isinstance(a, (int, float, str, bool)):
        return same(vars(a), vars(b))
    return a == b


def test_same_can_fail():
    assert not same({"a": np.array([1.0, np.nan])}, {"a": np.array([1.0, 2.0])})
    assert not same(T.Counters(readings=1), T.Counters(readings=2))
    assert same((1.0, math.nan, [np.zeros(2)]), (1.0, math.nan, [np.zeros(2)]))


def test_a_transition_leaves_its_input_state_as_it_was(ctx, day, sets):
    readings, _, _ = day
    state = T.with_active(ctx, T.initial(ctx), sets[2]["wrong"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.saved = None
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.saved.offsets_um = {}
    checked = []

    def check(before, step):
        if len(checked) % 3 == 0 or step.events:  # every third reading and every one with an event, deep
            snapshot = copy.deepcopy(before)
            again = T.on_reading(ctx, before, readings[len(checked)], stored(sets), NOW_UNIX)
            assert same(before, snapshot), f"reading {len(checked)} changed its input state"
            assert same(again, step)  # (and the same inputs give the same step)
        checked.append(step)

    steps = replay(ctx, state, readings, stored(sets), check)
    # the run went through every clock: model steps, monitoring boundaries, a degraded sensor and a probe
    events = [e for s in steps for e in s.events]
    kinds = {e.kind for e in events}
    assert {"decision", "sensor", "probe"} <= kinds
    assert sum(isinstance(c, T.Persist) for s in steps for c in s.commands) == len(
        [e for e in events if e.kind == "decision"]) >= 6
    assert steps[-1].state.counters.model_steps == int((readings[-1].time_s - readings[0].time_s) // 60.0)


def test_the_same_readings_give_the_same_steps(ctx, day, sets):
    readings, _, _ = day
    state = T.with_active(ctx, T.initial(ctx), sets[2]["wrong"])
    a = replay(ctx, state, readings, stored(sets))
    b = replay(ctx, state, readings, stored(sets))
    assert len(a) == len(b) == len(readings)
    assert all(same(x.offsets, y.offsets) and same(x.effects, y.effects) for x, y in zip(a, b))
    assert same(a[-1].state, b[-1].state)


def test_a_wrong_active_set_switches_to_a_stored_set_that_fits_with_no_database(ctx, day, sets):
    readings, _, _ = day
    _, ids, loaded = sets
    asked = []
    state = T.with_active(ctx, T.initial(ctx), loaded["wrong"])
    steps = replay(ctx, state, readings, stored(sets, asked))
    k = next(i for i, s in enumerate(steps) if any(isinstance(c, T.Activate) for c in s.commands))
    step = steps[k]
    act = [c for c in step.commands if isinstance(c, T.Activate)]
    assert len(act) == 1 and act[0].ids == ids["right"] and act[0].reason.startswith("switch")
    decision = next(e for e in step.events if e.kind == "decision")
    assert decision.payload["action"] == "switch" and decision.payload["target"]["ids"] == ids["right"]
    assert act[0].t == decision.t
    # the switch is in the state at once (the compensation after it evaluates the new set) and in the boundary's
    # state the daemon persists (the Persist after the Activate)
    assert step.state.active.cds["X"] is loaded["right"].cds["X"]  # the stored set's CDs, not read again
    assert step.state.saved.active_ids == ids["right"] and step.state.saved.activated_s == decision.t
    assert dict(step.state.active.ids) == ids["right"]
    kinds = [type(c).__name__ for c in step.commands]
    assert kinds.index("Activate") < kinds.index("Persist")
    persisted = next(c for c in step.commands if isinstance(c, T.Persist)).state
    assert persisted.saved.active_ids == ids["right"]
    # the stored sets were asked for at the decisions that needed candidates only, with the active set to skip
    assert asked and all(q.skip_ids == ids["wrong"] for q in asked[:1])
    assert all(q.temperatures_degC.keys() == set(ctx.sensor_names) for q in asked)
    # before the switch every decision kept or asked; after it the right set is written
    after = [o for s in steps[k + 1:] for o in s.offsets]
    assert after and all(o.active == ",".join(f"{d}={ids['right'][d]}" for d in sorted(ids["right"])) for o in after)


def test_the_interval_clock_switches_to_a_stored_set_that_fits_with_no_database(ctx, day, sets):
    """:func:`on_interval` on a state mid-interval whose active set is wrong (no stored set offered so far: kept with
    a warning) and a stored set that fits: one decision, a switch, an activate command before the persist, the stored
    sets asked for once, the interval reset."""
    readings, _, _ = day
    _, ids, loaded = sets
    state = T.with_active(ctx, T.initial(ctx), loaded["wrong"])
    before = replay(ctx, state, readings[:300])
    assert {e.payload["action"] for s in before for e in s.events if e.kind == "decision"} == {"warn"}
    st = before[-1].state
    assert st.saved.active_ids == ids["wrong"] and len(st.saved.interval) > 1
    boundary = st.saved.step_time_s
    asked = []
    step = T.on_interval(ctx, st, boundary, stored(sets, asked))
    (decision,) = [e for e in step.events if e.kind == "decision"]
    assert decision.t == boundary and decision.payload["action"] == "switch"
    assert decision.payload["error_um"]["interval_um"] > 1.5 > decision.payload["target"]["error_um"]["interval_um"]
    assert [type(c).__name__ for c in step.commands if not isinstance(c, T.Log)] == ["Activate", "Persist"]
    (act,) = [c for c in step.commands if isinstance(c, T.Activate)]
    assert act.ids == ids["right"] and act.t == boundary
    assert len(asked) == 1 and asked[0].skip_ids == ids["wrong"]
    new = step.state.saved
    assert new.active_ids == ids["right"] and new.activated_s == boundary
    assert new.blend_pending == (ctx.cfg.blend_s > 0)  # a set was active: the offsets blend over
    assert new.next_mon_s == boundary + ctx.cfg.monitoring_interval_s
    assert new.interval == st.saved.interval[-1:] and new.signature_sum is None and new.rejected == {}
    assert step.commands[-1].state is step.state
    assert st.saved.active_ids == ids["wrong"] and st.active is loaded["wrong"]  # the input state as it was


def test_the_shell_writes_what_the_transitions_return(ctx, cfg, machine, small_rom, day, sets, tmp_path):
    """The :class:`Monitor` on a copy of the database and the transitions on the same readings: the same offsets
    bit for bit, the same events in the same order (and the database's activation record for each Activate)."""
    import shutil

    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.daemon import Monitor
    from hybridcomp.monitor.store import MonitorStore

    readings, _, _ = day
    path, ids, loaded = sets
    shutil.copy(path, tmp_path / "cd.db")
    db = CDDatabase(tmp_path / "cd.db")
    try:
        n0 = len(MonitorStore(db).events())
        mon = Monitor(cfg, machine, small_rom, db, PKEY, FixedClock())
        shell = [o for r in readings for o in mon.process(r)]
        logged = [(e.kind, e.machine_time_s, e.payload, e.key) for e in MonitorStore(db).events()[n0:]]
        saved = json.loads(MonitorStore(db).get_state(mon.key))
    finally:
        db.close()
    original = CDDatabase(path)  # the stored sets as the shell's database offers them (both, the active one skipped)
    try:
        def offered(q: T.SetQuery):
            for m in original.search(machine.name, PKEY, q.signature, q.temperatures_degC, math.inf,
                                     layout=ctx.sig_layout):
                if dict(m.ids) != q.skip_ids:
                    yield T.StoredSet(dict(m.ids), m.load_case, m.delta_T_K, {d: original.get(i) for d, i in m.ids.items()})
        steps = replay(ctx, T.with_active(ctx, T.initial(ctx), loaded["wrong"]), readings, offered)
    finally:
        original.close()
    pure = [o for s in steps for o in s.offsets]
    assert len(pure) == len(shell) == len(readings)
    assert all(a == b for a, b in zip(pure, shell))
    want = []
    for s in steps:
        for e in s.effects:
            if isinstance(e, T.Event):
                want.append((e.kind, e.t, json.loads(jsonio.dumps(e.payload)), f"{e.kind}@{PKEY}@{e.key}"))
            elif isinstance(e, T.Activate):
                want.append(("activation", e.t, {"ids": e.ids}, None))
    assert len(logged) == len(want)
    for (kind, t, payload, key), (wk, wt, wp, wkey) in zip(logged, want):
        assert (kind, t) == (wk, wt)
        if kind == "activation":
            assert payload["ids"] == wp["ids"] and key.startswith(f"activation@{PKEY}@")
        else:
            assert (payload, key) == (wp, wkey)
    assert sum(k == "activation" for k, *_ in logged) == 1
    # the state the shell persisted is the last boundary's of the transitions
    last = next(c.state for s in reversed(steps) for c in reversed(s.commands) if isinstance(c, T.Persist))
    saved.pop("updated_unix")
    assert saved == json.loads(jsonio.dumps(last.saved.to_dict()))



# --------------------------------------------------------------------------- fail safe on a known-wrong set
@pytest.fixture(scope="module")
def absurd(machine, day, tmp_path_factory):
    """The only stored set, active: the drift plus 5,000 µm (inside the CDs' plausibility bound of 1e4 µm)."""
    from hybridcomp.chardiag.cd import CDSet
    from hybridcomp.chardiag.db import CDDatabase

    _, T_degC, drift = day
    db = CDDatabase(tmp_path_factory.mktemp("absurd") / "cd.db")
    try:
        ids = db.add_set(fit_set(machine, T_degC, drift + 5000.0, "absurd"), "absurd")
        return CDSet({d: db.get(i) for d, i in ids.items()}, ids)
    finally:
        db.close()


def _at(offsets, times, drift):
    """The drift [µm] at the offsets' times (the day's drift is sampled with the readings)."""
    idx = np.searchsorted(times, [o.time_s for o in offsets])
    return drift[idx]


def test_a_set_the_decision_calls_wrong_is_never_applied(ctx, day, absurd):
    """The issue's attack: the only stored set is 5,000 µm off, regeneration is off. Every offset comes from the
    corrected structure model (it never sits at the ±100 µm clamp), with one ``failsafe`` event at the first
    decision, naming the error and the limit."""
    readings, _, drift = day
    steps = replay(ctx, T.with_active(ctx, T.initial(ctx), absurd), readings)
    offsets = [o for s in steps for o in s.offsets]
    events = [e for s in steps for e in s.events]
    fs = [e for e in events if e.kind == "failsafe"]
    first = next(e for e in events if e.kind == "decision")
    assert first.payload["error_um"]["interval_um"] > 4000 and first.payload["action"] == "warn"
    assert len(fs) == 1 and fs[0].payload["status"] == "entered" and fs[0].t == first.t
    assert "beyond reject_um = 50 µm" in fs[0].payload["message"] and "not applied" in fs[0].payload["message"]
    assert fs[0].payload["reject_um"] == ctx.cfg.validity.reject_um == 50.0
    assert {o.by for o in offsets} == {"observer"} and not any(o.clamped for o in offsets)
    got = np.array([[o.dx_um, o.dy_um, o.dz_um] for o in offsets])
    times = np.array([r.time_s for r in readings])
    assert np.max(np.abs(got)) <= np.max(np.abs(drift)) + 1.0  # never beyond the true drift (was: the 100 µm clamp)
    assert np.max(np.abs(got - _at(offsets, times, drift))) < 1.0
    assert steps[-1].state.saved.failsafe and steps[-1].state.saved.active_ids == absurd.ids


def test_the_fail_safe_holds_the_offsets_and_ramps_to_the_observer(ctx, day, absurd):
    """A run that applied the wrong set (a limit above its error: the offsets at the clamp) and then meets the
    limit: from the decision on the offsets move at most ``max_step_um`` per cycle from where they were, toward the
    corrected model's drift, and reach it."""
    readings, _, drift = day
    lax = dataclasses.replace(ctx, cfg=dataclasses.replace(
        ctx.cfg, validity=dataclasses.replace(ctx.cfg.validity, reject_um=1e9)))
    n = 200
    before = replay(lax, T.with_active(ctx, T.initial(ctx), absurd), readings[:n])
    written = [o for s in before for o in s.offsets]
    assert all(o.clamped and o.by == "cd+model" for o in written[-10:])  # what happened without the fail-safe
    assert not any(e.kind == "failsafe" for s in before for e in s.events)
    after = replay(ctx, before[-1].state, readings[n:])
    k = next(i for i, s in enumerate(after) if any(e.kind == "failsafe" for e in s.events))
    # (the reading that closes the interval may have written its offsets before the decision)
    offsets = [o for s in after[k + 1:] for o in s.offsets]
    last = ([o for s in after[:k + 1] for o in s.offsets] or written)[-1]
    prev = np.array([last.dx_um, last.dy_um, last.dz_um])
    got = np.array([[o.dx_um, o.dy_um, o.dz_um] for o in offsets])
    steps_um = np.abs(np.diff(np.vstack([prev, got]), axis=0))
    assert np.max(steps_um) <= ctx.cfg.max_step_um + 1e-9  # held, then ramped at the rate limit
    assert abs(got[0] - prev).max() <= ctx.cfg.max_step_um + 1e-9 and np.max(np.abs(prev)) >= 99.0
    times = np.array([r.time_s for r in readings])
    assert np.max(np.abs(got[-20:] - _at(offsets[-20:], times, drift))) < 1.0  # arrived at the drift
    assert {o.by for o in offsets} == {"observer"}


# --------------------------------------------------------------------------- a restart continues, nothing twice
def test_a_restart_resumes_with_the_sample_that_closed_the_boundary(ctx, cfg, machine, small_rom, day, sets, tmp_path):
    """Samples that never fall on a step's end (each 3 s after it) and a 70 s gap in the step after a monitoring
    boundary (a histogram warning): a daemon stopped after that step and restarted from the boundary's state writes
    the warning once, under one key, and the offsets of an uninterrupted run (the sample that closed the boundary's
    step is not skipped)."""
    import shutil

    from hybridcomp.chardiag.db import CDDatabase
    from hybridcomp.monitor.daemon import Monitor
    from hybridcomp.monitor.store import MonitorStore

    readings, T_degC, _ = day
    t0 = readings[0].time_s
    # (T2 read throughout: a sensor degraded across a restart is rewound from another point, the log not persisted)
    whole = [dataclasses.replace(r, sensors_degC={**r.sensors_degC, "T2": float(T_degC[i, 1])})
             for i, r in enumerate(readings)]
    shifted = [whole[0]] + [dataclasses.replace(r, time_s=r.time_s + 3.0) for r in whole[1:]]
    boundary = t0 + ctx.cfg.monitoring_interval_s
    k0 = next(i for i, r in enumerate(shifted) if r.time_s > boundary + 60.0)
    trace = shifted[:k0] + shifted[k0 + 7:]  # a 80 s gap in the second step after the boundary
    stop_at = boundary + 400.0
    path, _, _ = sets

    def events_of(db):
        return [(e.kind, e.machine_time_s, e.key, e.payload) for e in MonitorStore(db).events() if e.kind != "activation"]

    runs = {}
    for name in ("straight", "restarted"):
        shutil.copy(path, tmp_path / f"{name}.db")
        db = CDDatabase(tmp_path / f"{name}.db")
        try:
            mon = Monitor(cfg, machine, small_rom, db, PKEY, FixedClock())
            if name == "straight":
                offsets = [o for r in trace for o in mon.process(r)]
            else:
                offsets = [o for r in trace if r.time_s <= stop_at for o in mon.process(r)]
                mon = Monitor(cfg, machine, small_rom, db, PKEY, FixedClock())  # the daemon restarted
                after = mon.resume_after_s()
                assert after is not None and after < stop_at
                again = [o for r in trace if r.time_s > after for o in mon.process(r)]
                offsets = [o for o in offsets if o.time_s <= after] + again
            runs[name] = (offsets, events_of(db))
        finally:
            db.close()
    (a, ev_a), (b, ev_b) = runs["straight"], runs["restarted"]
    hist = [e for e in ev_b if e[0] == "warning" and "@histogram@" in e[2]]
    assert hist and len({e[1] for e in hist}) == len(hist), hist  # one histogram warning per step
    assert [e[:3] for e in ev_a] == [e[:3] for e in ev_b]
    assert len(a) == len(b) and all(x == y for x, y in zip(a, b))


def test_a_histogram_warning_of_a_step_has_one_key_whatever_its_counts():
    """After a restart on a live source the step's samples differ: the same warning with other counts and lines is
    the same event (it was a second one under a second key)."""
    a = "model step ending 960 s: 1 gap(s) longer than 10 s (total 20 s, first ending at line 3) counted as standstill"
    b = "model step ending 960 s: 2 gap(s) longer than 10 s (total 33.5 s, first ending at line 4) counted as standstill"
    other = "model step ending 960 s: dropped 3 of 9 rows with NaN or empty fields (first at line 2)"
    assert T.histogram_warning_key(960.0, a) == T.histogram_warning_key(960.0, b)
    assert T.histogram_warning_key(960.0, a) != T.histogram_warning_key(960.0, other)
    assert T.histogram_warning_key(960.0, a) != T.histogram_warning_key(980.0, a)


def test_the_context_bounds_the_gains_of_the_drives_read_at_the_screw(ctx, machine):
    """The machine file's drives with a rotary encoder (X, Y on the demonstrator; Z reads a linear scale)."""
    want = tuple(d.axis for d in machine.drives if d.feedback == "rotary_encoder")
    assert want == ("X", "Y") and ctx.gain_settings.bounded_axes == want
