"""Reducing exported systems (``reduce --matrices``): balanced truncation, the H2-optimal basis, the exact error
figure, scale invariance, the order delivered, D, refusals.

Systems: a heat-conduction plate of its own making (a 20 × 20 grid with convection at its edges, five heated
patches, four measured points: many inputs and outputs, symmetric, 400 states), and small 1-D chains (heat with
an FE mass matrix as E; convection-diffusion, non-symmetric, with a feedthrough D) and diagonal systems whose
Hankel singular values and errors are known by hand. Every reference is computed densely with scipy.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.io

from hybridcomp.cli import main
from hybridcomp.rom.external import MatrixFileError, load_external, plate_system, reduce_matrices
from tests.test_rom_balanced import lyapunov_error


@pytest.fixture(scope="module")
def mat(tmp_path_factory):
    m = plate_system(20)
    path = tmp_path_factory.mktemp("plate") / "plate.mat"
    scipy.io.savemat(path, m)
    return path, m


@pytest.mark.slow  # 400 L-BFGS iterations and dense Lyapunov references: seconds
def test_the_h2_basis_changes_the_basis_lowers_the_error_and_the_error_is_exact(mat):
    from hybridcomp.rom import h2

    path, m = mat
    r = 10
    kr = reduce_matrices(path, order=r, basis="krylov")
    opt = reduce_matrices(path, order=r, basis="h2", h2_maxiter=400)
    assert kr.meta["basis"] == "krylov" and opt.meta["basis"] == "h2" and opt.order == kr.order == r
    # the stored figure is the exact relative H2 error (checked against scipy's Lyapunov solver)
    for rom in (kr, opt):
        ref = lyapunov_error(m, rom)
        assert rom.meta["h2_error_relative"] == pytest.approx(ref, rel=1e-6)
    e_kr, e_opt = kr.meta["h2_error_relative"], opt.meta["h2_error_relative"]
    assert e_opt < 0.8 * e_kr, (e_opt, e_kr)
    # against balanced truncation at the same order (dense, two-sided): within a factor 2
    form = h2.modal_form(m["E"].toarray(), -m["A"].toarray(), m["B"], m["C"])
    Ar, Br, Cr, _, _ = h2.balanced_truncation(form, r)
    e_bt = h2.general_h2_error(form, Ar, Br, Cr)
    assert e_opt <= 2.0 * e_bt, (e_opt, e_bt)
    assert np.all(opt.poles().real < 0) and opt.meta["stable"]


def test_reduce_cli_with_matrices_bt_default_and_basis_h2(mat, tmp_path, capsys):
    path, m = mat
    out = tmp_path / "m.npz"
    assert main(["reduce", "--matrices", str(path), "--order", "8", "--basis", "h2", "--h2-maxiter", "20",
                 "--out", str(out)]) == 0
    cap = capsys.readouterr()
    summary = json.loads(cap.out.strip().splitlines()[-1])
    assert summary["basis"] == "h2" and summary["order"] == 8 and 0 < summary["h2_error_relative"] < 1
    assert "surrogate" not in cap.out and "relative H2 error" in cap.err
    # exported systems default to balanced truncation; the saved model reads back, its figure exact
    assert main(["reduce", "--matrices", str(path), "--order", "8", "--out", str(tmp_path / "d.npz")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["basis"] in ("bt", "irka") and summary["order"] == 8 and summary["stable"]
    rom = load_external(tmp_path / "d.npz")
    assert rom.meta["matrices"]["file"] == "plate.mat" and rom.order == 8
    assert summary["h2_error_relative"] == pytest.approx(lyapunov_error(m, rom), rel=1e-6)
    from hybridcomp.rom.reduced import RomFileError, load_rom

    with pytest.raises(RomFileError, match="load_external"):
        load_rom(tmp_path / "d.npz")
    assert main(["reduce", "--matrices", str(path), "--basis", "h2", "--out", str(tmp_path / "x.npz")]) == 2
    assert "needs --order or --h2-tol" in capsys.readouterr().err
    assert main(["reduce", "--h2-tol", "0.1", "--out", str(tmp_path / "x.npz")]) == 2
    assert "--h2-tol applies with --matrices only" in capsys.readouterr().err
    assert main(["reduce", "--matrices", str(path), "--order", "8", "--h2-tol", "0.1",
                 "--out", str(tmp_path / "x.npz")]) == 2
    assert main(["reduce", "--matrices", str(path), "--order", "8", "--fastest-time-s", "1",
                 "--out", str(tmp_path / "x.npz")]) == 2
    assert "--fastest-time-s applies with --basis krylov or h2 only" in capsys.readouterr().err
    assert main(["reduce", "--basis", "bt", "--out", str(tmp_path / "x.npz")]) == 2
    assert "bt applies with --matrices only" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_corrupted_or_wrongly_shaped_files_are_named(mat, tmp_path, capsys):
    path, m = mat
    bad = tmp_path / "garbage.mat"
    bad.write_bytes(b"MATLAB 5.0 MAT-file" + bytes(range(256)) * 4)
    with pytest.raises(MatrixFileError, match=r"garbage\.mat"):
        reduce_matrices(bad, order=5)
    scipy.io.savemat(tmp_path / "shape.mat", {**m, "B": m["B"][:-3]})
    with pytest.raises(MatrixFileError, match=r"shape\.mat: variable 'B' has shape 397, expected 400 rows"):
        reduce_matrices(tmp_path / "shape.mat", order=5)
    with pytest.raises(ValueError, match="--order must be between 1 and 399"):
        reduce_matrices(path, order=400)
    assert main(["reduce", "--matrices", str(bad), "--order", "5", "--out", str(tmp_path / "o.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "garbage.mat" in err and "Traceback" not in err


def _write_mat73(path, mats: dict) -> None:
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 behind a 512-byte user block, dense arrays transposed,
    sparse matrices as groups of data, ir, jc with the row count in the MATLAB_sparse attribute."""
    import h5py
    import scipy.sparse as sp

    with h5py.File(path, "w", userblock_size=512) as f:
        for name, a in mats.items():
            if sp.issparse(a):
                c = sp.csc_matrix(a)
                g = f.create_group(name)
                g.attrs["MATLAB_class"] = np.bytes_("double")
                g.attrs["MATLAB_sparse"] = np.uint64(c.shape[0])
                g["data"], g["ir"], g["jc"] = c.data, c.indices.astype(np.uint64), c.indptr.astype(np.uint64)
            else:
                d = f.create_dataset(name, data=np.asarray(a, float).T)
                d.attrs["MATLAB_class"] = np.bytes_("double")
    with open(path, "r+b") as fh:  # the user block opens with MATLAB's text header, which makes scipy refuse v7.3
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Wed Nov 25 2026 HDF5 schema 1.00 .".ljust(116))
        fh.seek(124)
        fh.write(b"\x00\x02IM")


def test_a_matlab_v73_file_reads_like_v5(mat, tmp_path):
    from hybridcomp.rom.external import read_matrices

    path, m = mat
    v73 = tmp_path / "plate73.mat"
    _write_mat73(v73, {"E": m["E"], "A": m["A"], "B": np.asarray(m["B"]), "C": np.asarray(m["C"])})
    with pytest.raises(NotImplementedError):  # scipy's own reader stops at v7.3: the HDF5 path is the one tested
        scipy.io.loadmat(v73)
    got, _ = read_matrices(v73)
    want, _ = read_matrices(path)
    for v in ("E", "A", "B", "C"):
        a, b = got[v], want[v]
        a = a.toarray() if hasattr(a, "toarray") else a
        b = b.toarray() if hasattr(b, "toarray") else b
        np.testing.assert_array_equal(a, b, err_msg=v)
    assert reduce_matrices(v73, order=6).meta["h2_error_relative"] == reduce_matrices(path, order=6).meta["h2_error_relative"]
