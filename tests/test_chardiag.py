"""Characteristic diagrams: exactness, smoothing, selection, XML, hardening, bad input, CNC export."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hybridcomp.chardiag.cd import CDError, CDSet
from hybridcomp.chardiag.export import axis_offsets, generic_table, siemens_840d
from hybridcomp.chardiag.fit import CDFitError, FitOptions, fit_cd, fit_cd_set, roughness
from hybridcomp.chardiag.xmlio import CDXmlError, cd_from_bytes, cd_to_bytes, check_machine, read_cd, schema, write_cd


def multilinear(T):
    """A multilinear function of three temperatures [µm] (linear along each input for the others fixed)."""
    a, b, c = T[:, 0] - 20, T[:, 1] - 22, T[:, 2] - 21
    return 1.5 + 2.0 * a - 3.0 * b + 2.5 * c + 0.5 * a * b - 0.2 * b * c + 0.05 * a * b * c


def table(T, y, target="dz_um"):
    tab = {f"T{i + 1}_degC": T[:, i] for i in range(T.shape[1])}
    tab[target] = y
    return tab


@pytest.fixture(scope="module")
def rng():
    return np.random.default_rng(7)


@pytest.fixture(scope="module")
def cd3(rng):
    T = rng.uniform([18, 20, 19], [28, 31, 27], (3000, 3))
    return fit_cd(table(T, multilinear(T)), "Z", machine="vmc800", pose_mm={"X": 0.0, "Y": -12.5, "Z": 0.0},
                  signature=rng.random(16), load_case="synthetic",
                  options=FitOptions(n_support=5, smoothing=1.0, max_full_dims=3))


@pytest.mark.parametrize("smoothing", [0.0, 1.0, 100.0])
def test_multilinear_function_is_reproduced_exactly(rng, smoothing):
    T = rng.uniform([18, 20, 19], [28, 31, 27], (2000, 3))
    cd = fit_cd(table(T, multilinear(T)), "Z", machine="m",
                options=FitOptions(n_support=4, smoothing=smoothing, max_full_dims=3))
    assert [len(t.inputs) for t in cd.terms] == [3]  # one full tensor grid
    lo = np.array([i.min for i in cd.inputs])
    hi = np.array([i.max for i in cd.inputs])
    Q = rng.uniform(lo, hi, (5000, 3))
    pred, outside = cd.evaluate(Q)
    assert not outside.any()
    scale = np.max(np.abs(multilinear(Q)))
    assert np.max(np.abs(pred - multilinear(Q))) < 1e-8 * scale  # exact up to the solver's round-off
    for q in Q[:50]:
        v, out = cd.evaluate_point({"T1": q[0], "T2": q[1], "T3": q[2]})
        assert not out
        assert v == pytest.approx(multilinear(q[None])[0], abs=1e-8 * scale)


def test_additive_cd_of_eight_temperatures_and_five_axes_reproduces_an_additive_function(rng):
    # 13 inputs without a tensor grid: one 1-D table per input (n^13 values would not fit in memory)
    n = 4000
    T = rng.uniform(20, 30, (n, 8))
    P = rng.uniform(-300, 300, (n, 5))
    w = np.array([1.0, -2.0, 1.5, 3.0, -1.0, 2.5, -3.0, 2.0])
    y = T @ w + 0.01 * P @ np.arange(1, 6) + 3.0
    tab = table(T, y, "dx_um")
    for j, a in enumerate("xyzab"):
        tab[f"{a}_mm"] = P[:, j]
    from hybridcomp.chardiag.fit import candidate_inputs

    cd = fit_cd(tab, "X", machine="m", candidates=candidate_inputs(list(tab), positions=True),
                options=FitOptions(n_support=5, smoothing=0.0))
    assert len(cd.active_inputs) == 13 and len(cd.terms) == 13
    assert cd.memory_bytes == 13 * 5 * 8
    pred, _ = cd.evaluate_table(tab)
    assert np.max(np.abs(pred - y)) < 1e-8 * np.max(np.abs(y))
    names = [i.column for i in cd.inputs]
    for k in range(0, n, 400):  # the single-point path of additive CDs
        v, out = cd.evaluate_point({i.name: tab[c][k] for i, c in zip(cd.inputs, names)})
        assert not out and v == pytest.approx(pred[k], abs=1e-9 * np.max(np.abs(y)))


def test_more_smoothing_never_increases_roughness(rng):
    T = rng.uniform(20, 30, (600, 2))
    y = np.sin(T[:, 0]) * 3 + np.cos(1.3 * T[:, 1]) + rng.normal(0, 0.5, 600)
    r = [roughness(fit_cd(table(T, y), "Z", machine="m", options=FitOptions(n_support=8, smoothing=lam)))
         for lam in (0.0, 1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0)]
    assert all(b <= a * (1 + 1e-9) for a, b in zip(r, r[1:])), r
    assert r[-1] < 0.01 * r[0]  # and it does smooth


def test_point_and_vectorised_evaluation_agree_including_clamping(cd3, rng):
    lo = np.array([i.min for i in cd3.inputs])
    hi = np.array([i.max for i in cd3.inputs])
    Q = rng.uniform(lo - 2, hi + 2, (400, 3))
    pred, outside = cd3.evaluate(Q)
    expect_out = np.any((Q < lo) | (Q > hi), axis=1)
    assert np.array_equal(outside, expect_out)
    for q, p, o in zip(Q, pred, outside):
        v, out = cd3.evaluate_point(dict(zip(cd3.input_names, q)))
        assert out == o
        assert v == pytest.approx(p, abs=1e-9)
    # clamped: outside the box the value is the one at the nearest box point
    q = np.array([[lo[0] - 5, hi[1] + 5, 0.5 * (lo[2] + hi[2])]])
    assert cd3.evaluate(q)[0][0] == pytest.approx(cd3.evaluate(np.clip(q, lo, hi))[0][0], abs=1e-12)


def test_input_selection_records_why(rng):
    n = 800
    T1 = rng.uniform(20, 30, n)
    tab = {"T1_degC": T1, "T2_degC": np.full(n, 21.0), "T3_degC": 20 + 0.2 * rng.random(n),
           "T4_degC": rng.uniform(20, 30, n), "dz_um": 2.0 * T1 + rng.normal(0, 0.01, n)}
    cd = fit_cd(tab, "Z", machine="m")
    by = {i.name: i for i in cd.inputs}
    assert by["T1"].active
    assert not by["T2"].active and "range 0 K < 0.5 K" in by["T2"].reason
    assert not by["T3"].active and "< 0.5 K" in by["T3"].reason
    assert not by["T4"].active and "not significant" in by["T4"].reason


def test_bic_forward_selection_finds_the_true_inputs(rng):
    n = 1500
    T = rng.uniform(20, 30, (n, 6))
    T[:, 3] = T[:, 0] + rng.normal(0, 0.3, n)  # correlated with a true input, but not needed
    y = 3 * T[:, 0] - 2 * T[:, 2] + rng.normal(0, 0.05, n)
    cd = fit_cd(table(T, y), "Z", machine="m", options=FitOptions(select="bic"))
    assert {i.name for i in cd.active_inputs} == {"T1", "T3"}
    assert "not selected" in {i.name: i for i in cd.inputs}["T4"].reason


def test_bad_training_data_gives_clear_errors(rng):
    T = rng.uniform(20, 30, (100, 3))
    y = T.sum(axis=1)
    bad = table(T.copy(), y)
    bad["T2_degC"][17] = np.nan
    with pytest.raises(CDFitError, match=r"T2_degC.*NaN.*row 18"):
        fit_cd(bad, "Z", machine="m", source="train.csv")
    with pytest.raises(CDFitError, match=r"dz_um.*constant"):
        fit_cd(table(T, np.full(100, 4.0)), "Z", machine="m")
    const = {f"T{i}_degC": np.full(100, 20.0 + i) for i in range(3)}
    const["dz_um"] = y
    with pytest.raises(CDFitError, match="no active input"):
        fit_cd(const, "Z", machine="m")
    with pytest.raises(CDFitError, match=r"too few samples.*40 rows for 216"):
        fit_cd(table(T[:40], T[:40] @ [3.0, 3.0, 3.0]), "Z", machine="m", options=FitOptions(n_support=6, max_full_dims=3))
    with pytest.raises(CDFitError, match="column 'dz_um' is missing"):
        fit_cd({"T1_degC": T[:, 0]}, "Z", machine="m")
    with pytest.raises(CDFitError, match="n_support"):
        FitOptions(n_support=1)


def test_xml_round_trip_is_bit_exact_and_schema_valid(cd3, tmp_path):
    from dataclasses import replace

    tricky = replace(cd3, signature=np.array([0.1 + 0.2, 1e-310, -0.0, 1e300, np.pi, 2.0**-52]))
    for cd in (cd3, tricky):
        data = cd_to_bytes(cd)
        from lxml import etree

        assert schema().validate(etree.fromstring(data))
        back = cd_from_bytes(data)
        assert back == cd
        assert cd_to_bytes(back) == data
        p = write_cd(tmp_path / "cd.xml", cd)
        assert read_cd(p) == cd
    assert np.signbit(cd_from_bytes(cd_to_bytes(tricky)).signature[2])


def test_schema_rejects_a_broken_document(cd3):
    data = cd_to_bytes(cd3).replace(b"<direction>Z</direction>", b"<direction>W</direction>")
    with pytest.raises(CDXmlError, match=r"cd\.xml: line \d+: not a valid CD file.*direction"):
        cd_from_bytes(data, source="cd.xml")
    data = cd_to_bytes(cd3).replace(b'supportPoints="5"', b'supportPoints="4"', 1)
    with pytest.raises(CDXmlError, match="values"):
        cd_from_bytes(data)


def test_malicious_xml_is_rejected_quickly_without_reading_outside_files(cd3, tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET-CONTENT")
    xxe = (b'<?xml version="1.0"?>\n<!DOCTYPE characteristicDiagram [<!ENTITY x SYSTEM "file://'
           + str(secret).encode() + b'">]>\n' + cd_to_bytes(cd3).split(b"\n", 1)[1].replace(
               b"<created>", b"<created>&x;"))
    laughs = b'<?xml version="1.0"?>\n<!DOCTYPE lolz [<!ENTITY lol "lol">' + b"".join(
        b'<!ENTITY lol%d "%s">' % (k, (b"&lol%d;" % (k - 1) if k > 1 else b"&lol;") * 10) for k in range(1, 10)
    ) + b']>\n<characteristicDiagram xmlns="urn:hybridcomp:characteristic-diagram:1">&lol9;</characteristicDiagram>'
    for name, data in (("xxe", xxe), ("billion laughs", laughs)):
        t0 = time.perf_counter()
        with pytest.raises(CDXmlError, match="not allowed") as exc:
            cd_from_bytes(data, source=name)
        assert time.perf_counter() - t0 < 0.5
        assert "TOP-SECRET" not in str(exc.value)
    big = tmp_path / "big.xml"
    with big.open("wb") as fh:  # a 100 MB file (sparse: made instantly)
        fh.truncate(100 * 1024 * 1024)
    t0 = time.perf_counter()
    with pytest.raises(CDXmlError, match=r"big\.xml: 104857600 bytes is over the limit"):
        read_cd(big)
    assert time.perf_counter() - t0 < 0.5
    with pytest.raises(CDXmlError, match="not well-formed"):
        cd_from_bytes(b"<characteristicDiagram")


def test_xml_from_another_machine_or_with_unknown_inputs_is_refused(cd3, machine):
    from dataclasses import replace

    with pytest.raises(CDXmlError, match="for 'vmc800', not for 'other'"):
        check_machine(cd3, replace(machine, name="other"))
    with pytest.raises(CDXmlError, match="another version of the machine file"):
        cd_from_bytes(cd_to_bytes(replace(cd3, machine_sha256="0" * 64)), machine=machine)
    renamed = cd_to_bytes(replace(cd3, machine_sha256=machine.sha256)).replace(b'name="T3"', b'name="T99"')
    renamed = renamed.replace(b'inputs="T1 T2 T3"', b'inputs="T1 T2 T99"')
    with pytest.raises(CDXmlError, match="input 'T99': machine 'vmc800' has no sensor"):
        cd_from_bytes(renamed, machine=machine)
    ok = cd_from_bytes(cd_to_bytes(replace(cd3, machine_sha256=machine.sha256)), machine=machine)
    assert ok.machine == "vmc800"


def test_cd_invariants_are_checked(cd3):
    from dataclasses import replace

    with pytest.raises(CDError, match="direction"):
        replace(cd3, direction="W")
    t = cd3.terms[0]
    with pytest.raises(CDError, match="shape"):
        replace(cd3, terms=(replace(t, values=t.values[:-1]),))
    with pytest.raises(CDError, match="evaluate: X must have 3 columns"):
        cd3.evaluate(np.zeros((4, 2)))
    with pytest.raises(KeyError):
        cd3.evaluate_point({"T1": 20.0})


def test_cnc_export_generic_and_siemens_840d(rng):
    # dx = 2 µm/K·(T1 − 20) + 0.004 µm/mm·X: a compensation line along X with slope −0.004 µm/mm = −4e-6 mm/mm
    n = 2000
    T1 = rng.uniform(20, 25, n)
    X = rng.uniform(-400, 400, n)
    tab = {"T1_degC": T1, "x_mm": X, "dx_um": 2 * (T1 - 20) + 0.004 * X, "dy_um": -1.0 * (T1 - 20),
           "dz_um": 3.0 * (T1 - 20)}
    cands = [("T1", "degC"), ("X", "mm")]
    cds = CDSet(fit_cd_set(tab, machine="m", pose_mm={"X": 0.0, "Y": 0.0, "Z": 0.0}, candidates=cands,
                           options=FitOptions(n_support=5, smoothing=0.0, min_range_mm=1.0)))
    offs = axis_offsets(cds, {"T1": 22.5, "X": 100.0})
    by = {o.axis: o for o in offs}
    assert by["X"].drift_um == pytest.approx(5.0 + 0.4, abs=1e-9)
    assert by["X"].compensation_um == pytest.approx(-5.4, abs=1e-9)
    assert by["X"].slope == pytest.approx(-4e-6, rel=1e-6)
    assert by["X"].reference_mm == 100.0
    assert by["Y"].slope == 0.0 and by["Y"].reference_mm == 0.0
    text = siemens_840d(offs, {"X": "X1", "Y": "Y1", "Z": "Z1"})
    assert "$SA_TEMP_COMP_ABS_VALUE[X1]=-0.005400" in text
    assert "$SA_TEMP_COMP_SLOPE[X1]=-0.000004000" in text
    assert "$SA_TEMP_COMP_REF_POSITION[X1]=100.0000" in text
    assert "$SA_TEMP_COMP_ABS_VALUE[Z1]=-0.007500" in text
    rows = generic_table(offs).splitlines()
    assert rows[0] == "axis,drift_um,compensation_um,slope,reference_mm,outside"
    assert rows[2].startswith("Y,-2.5000,2.5000,")
