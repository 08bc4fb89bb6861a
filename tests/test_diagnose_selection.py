"""Bound rules of the effect fits: a parameter at a physically meaningful bound is a result, at the edge of the
search range the wrong shape."""

from __future__ import annotations

import numpy as np

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

