"""Rules of the selection: a parameter at a physically meaningful bound is a result, at the edge of the search range
the wrong shape; an effect accepted early is replaced when, with the later ones, the evidence prefers another."""

from __future__ import annotations

import numpy as np
import pytest

from hybridcomp.diagnose.effects import Candidate
from hybridcomp.diagnose.selection import at_bound


def _cand(lower, upper, nominal, physical=()):
    return Candidate("k", "", "test", tuple(f"p{i}" for i in range(len(lower))), lower, upper, nominal, nominal, False,
                     "sim", lambda s, p: None, physical=physical)


def test_a_physical_bound_is_a_result_an_artefact_bound_the_wrong_shape():
    # ambient lag: gain in 0..1.5 (nominal 0), tau in 0..24 h, where tau = 0 (air at the surfaces at once) is physical
    lag = _cand((0.0, 0.0), (1.5, 24.0), (0.0, 1.0), physical=((False, False), (True, False)))
    assert not at_bound(lag, np.array([1.0, 0.0]))  # a perfect fit with tau at 0: accepted
    assert not at_bound(lag, np.array([1.0, 2.0]))
    assert at_bound(lag, np.array([1.0, 24.0]))  # at the end of the search range: the wrong shape
    assert at_bound(lag, np.array([1.5, 2.0]))
    # the same candidate without the physical mark pins at tau = 0 (the rule before)
    assert at_bound(_cand((0.0, 0.0), (1.5, 24.0), (0.0, 1.0)), np.array([1.0, 0.0]))
    # a bound that is the nominal value never pins
    assert not at_bound(_cand((0.0,), (240.0,), (0.0,)), np.array([0.0]))
    # a power factor of 0 (the source gives no heat) is physical; an h at a quarter of nominal is the range's edge
    assert not at_bound(_cand((0.0,), (5.0,), (1.0,), physical=((True, False),)), np.array([0.0]))
    assert at_bound(_cand((2.5,), (40.0,), (10.0,)), np.array([2.5]))



def test_an_effect_chosen_before_a_sensor_effect_is_replaced_when_the_evidence_prefers_it(monkeypatch):
    """A source seen through a sensor offset: round one takes the wrong source A (it mimics the source B plus the
    offset S on channel a), round two the offset; with S there, B in A's place fits to the noise, so the replacement
    step swaps them and the diagnosis is "explained" by B and S at their planted values (without it: "unexplained",
    A and S partial).  The effects' responses are fixed arrays (no model), the selection's rules the real ones."""
    from types import SimpleNamespace

    from hybridcomp.diagnose import selection

    n, sig = 300, 0.02
    k = np.arange(n)
    u = np.sin(k / 17.0) + 0.3 * np.sin(k / 5.3)
    w = np.cos(k / 23.0)
    zero = np.zeros(n)
    resp = {"A": np.column_stack([u + 0.5 * w, 0.8 * u, 0.8 * u]), "B": np.column_stack([u, u, u]),
            "S": np.column_stack([w, zero, zero])}
    Y = resp["B"] + resp["S"] + np.random.default_rng(1).normal(0, sig, (n, 3))
    split = SimpleNamespace(train=k < 0.6 * n, validation=k >= 0.6 * n)
    problem = SimpleNamespace(Y=Y, weights=np.full(3, 1 / sig), split=split, sigma=np.full(3, sig),
                              tolerance=np.zeros(3), channels=("a", "b", "c"), signals={}, time_s=120.0 * k)

    def predicted(problem, effects):
        return sum((p[0] * c.info["resp"] for c, p in effects), np.zeros_like(problem.Y))

    monkeypatch.setattr(selection, "predicted_channels", predicted)
    cands = [Candidate(kind, name, name, ("p",), (-10.0,), (10.0,), (0.0,), (0.0,), True, stage, lambda s, p: None,
                       info={"resp": resp[name]})
             for kind, name, stage in (("located_source", "A", "raw"), ("located_source", "B", "raw"),
                                       ("sensor_offset", "S", "out"))]
    d = selection.select(problem, cands)
    assert [r.accepted.split(" ")[0] for r in d.rounds[:2]] == ["A", "S"]  # the greedy order: A first
    assert d.verdict == "explained", [f.candidate.target for f in d.partial]
    named = {f.candidate.target: float(f.params[0]) for f in d.causes}
    assert set(named) == {"B", "S"}
    assert named["B"] == pytest.approx(1.0, abs=0.01) and named["S"] == pytest.approx(1.0, abs=0.01)
