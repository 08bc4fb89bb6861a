"""Files handled like a careful tool: no command overwrites an input, writes through a symbolic link, overwrites an
existing output without ``--force``, or creates anything when it only reads; ``cd db import`` is all or nothing and
idempotent.

Every case is a real ``hybridcomp`` call in-process on tiny files: a refusal is exit code 2 and one line on stderr
that names the path, and the file tree is byte-for-byte what it was.
"""

from __future__ import annotations

import csv
import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.cli import main
from hybridcomp.safeio import OutputPathError, atomic_path, check_output_dir, check_output_path, write_text_atomic

POSE = {"X": 0.0, "Y": 0.0, "Z": 0.0}


# --------------------------------------------------------------------------- helpers


def tree(root: Path) -> dict[str, object]:
    """Every entry under ``root``: a file's bytes, a link's target, a folder's marker."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = ("link", os.readlink(p))
            elif p.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = p.read_bytes()
    return out


def refused(capsys, argv, *names) -> str:
    """Run ``argv``; assert exit code 2 and one line on stderr naming each of ``names``; return that line."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "\n" not in err, err
    for n in names:
        assert str(n) in err, err
    return err


def ok(capsys, argv) -> str:
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return cap.out


@pytest.fixture()
def trace(tmp_path):
    """A 12 s trace at 10 Hz: the spindle at full speed, the axes standing."""
    p = tmp_path / "t.csv"
    with p.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", "Tamb_degC"])
        w.writerows([[f"{0.1 * i:.1f}", "0", "0", "0", "12000", "21"] for i in range(121)])
    return p


@pytest.fixture()
def loads_csv(tmp_path):
    p = tmp_path / "l.csv"
    p.write_text("time_s,x_motor_W\n0,1\n60,1\n")
    return p


def cd_set(seed: int = 1):
    """Three small CDs of vmc800 (sensors T1..T3)."""
    from hybridcomp.chardiag.fit import FitOptions, fit_cd_set

    rng = np.random.default_rng(seed)
    T = 22.0 + rng.uniform(-2, 2, (200, 3))
    tab = {f"T{i + 1}_degC": T[:, i] for i in range(3)}
    for k, d in enumerate(("dx_um", "dy_um", "dz_um")):
        tab[d] = (T - 22) @ rng.normal(size=3) + k
    return fit_cd_set(tab, machine="vmc800", pose_mm=POSE, signature=np.zeros(3), load_case=f"case{seed}",
                      options=FitOptions(n_support=3))


@pytest.fixture(scope="module")
def cds():
    pytest.importorskip("sqlalchemy", reason="the CD database needs SQLAlchemy (pip install 'hybridcomp[db]')")
    return {seed: cd_set(seed) for seed in (1, 2)}


@pytest.fixture()
def cd_dir(tmp_path, cds):
    from hybridcomp.chardiag.xmlio import write_cd

    d = tmp_path / "cds"
    for k, cd in cds[1].items():
        write_cd(d / f"cd_{k}.xml", cd)
    return d


def n_rows(db: Path) -> int:
    con = sqlite3.connect(f"{db.absolute().as_uri()}?mode=ro", uri=True)
    try:
        return con.execute("SELECT count(*) FROM cds").fetchone()[0]
    finally:
        con.close()


# --------------------------------------------------------------------------- histogram


def test_histogram_never_overwrites_its_input_even_with_force(tmp_path, capsys, trace):
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        refused(capsys, ["histogram", trace, "--increment", "6", "--out", trace, *extra], trace, "--out", "input")
        assert tree(tmp_path) == before
    # the same file by another name (a hard link) is the input too
    os.link(trace, tmp_path / "alias.csv")
    before = tree(tmp_path)
    refused(capsys, ["histogram", trace, "--increment", "6", "--out", tmp_path / "alias.csv", "--force"], "alias.csv")
    refused(capsys, ["histogram", trace, "--increment", "6", "--out", tmp_path / "l.csv",
                     "--signature", trace, "--force"], "--signature", trace)
    assert tree(tmp_path) == before


def test_histogram_overwrites_an_existing_output_only_with_force(tmp_path, capsys, trace):
    out, sig = tmp_path / "l.csv", tmp_path / "sig.csv"
    out.write_text("keep me\n")
    before = tree(tmp_path)
    err = refused(capsys, ["histogram", trace, "--increment", "6", "--out", out], out)
    assert "exists; pass --force to overwrite" in err
    assert tree(tmp_path) == before
    ok(capsys, ["histogram", trace, "--increment", "6", "--out", out, "--signature", sig, "--force"])
    assert out.read_text().startswith("time_s,")
    assert set(tree(tmp_path)) == set(before) | {"sig.csv"}  # no temporary file left behind
    refused(capsys, ["histogram", trace, "--increment", "6", "--out", tmp_path / "new.csv", "--signature", sig],
            "--signature", sig)
    assert not (tmp_path / "new.csv").exists()  # every output is checked before the first is written
    refused(capsys, ["histogram", trace, "--increment", "6", "--out", sig, "--signature", sig, "--force"],
            "--out", "--signature", "same file")


def test_histogram_never_writes_through_a_symbolic_link(tmp_path, capsys, trace):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    victim = outside / "victim.csv"
    victim.write_text("not yours\n")
    work = tmp_path / "work"
    work.mkdir()
    (work / "l.csv").symlink_to(victim)
    plots = work / "plots"
    plots.mkdir()
    (plots / "factors.png").symlink_to(outside / "picture.png")
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        err = refused(capsys, ["histogram", trace, "--increment", "6", "--out", work / "l.csv", *extra], work / "l.csv")
        assert "symbolic link" in err
        refused(capsys, ["histogram", trace, "--increment", "6", "--out", work / "ok.csv", "--plot", plots, *extra],
                "--plot", plots / "factors.png")
    assert tree(tmp_path) == before


# --------------------------------------------------------------------------- simulate (refused before any FE work)


def test_simulate_never_overwrites_its_loads_even_with_force(tmp_path, capsys):
    s = tmp_path / "s"
    s.mkdir()
    (s / "outputs.csv").write_text("time_s,x_motor_W\n0,1\n60,1\n")
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        err = refused(capsys, ["simulate", "--loads", s / "outputs.csv", "--out", s, "--element-size-mm", "400",
                               "--no-progress", *extra], s / "outputs.csv")
        assert "input" in err
    assert tree(tmp_path) == before


def test_simulate_refuses_a_link_in_its_output_folder_and_an_earlier_run_without_force(tmp_path, capsys, loads_csv):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "victim.csv").write_text("not yours\n")
    s = tmp_path / "s"
    s.mkdir()
    (s / "outputs.csv").symlink_to(outside / "victim.csv")
    t = tmp_path / "t"
    t.mkdir()
    (t / "fields").symlink_to(outside)
    u = tmp_path / "u"
    u.mkdir()
    (u / "run.json").write_text("{}\n")
    (u / "notes.txt").write_text("mine\n")
    before = tree(tmp_path)
    common = ["simulate", "--loads", loads_csv, "--element-size-mm", "400", "--no-progress"]
    for extra in ([], ["--force"]):
        assert "symbolic link" in refused(capsys, [*common, "--out", s, *extra], s / "outputs.csv")
        assert "symbolic link" in refused(capsys, [*common, "--out", t, "--fields", "2", *extra], t / "fields")
    err = refused(capsys, [*common, "--out", u], u, "run.json")
    assert "pass --force" in err and "notes.txt" not in err  # only the files this run would write count
    refused(capsys, [*common, "--out", loads_csv], loads_csv, "not a directory")
    assert tree(tmp_path) == before


# --------------------------------------------------------------------------- small writers


def test_example_loads_and_monitor_example_config_keep_an_existing_file(tmp_path, capsys):
    loads, cfg = tmp_path / "l.csv", tmp_path / "monitor.toml"
    loads.write_text("mine\n")
    cfg.write_text("# my configuration\n")
    before = tree(tmp_path)
    refused(capsys, ["example-loads", "--hours", "0.5", "--out", loads], loads, "--force")
    refused(capsys, ["monitor", "example-config", "--out", cfg], cfg, "--force")
    assert tree(tmp_path) == before
    ok(capsys, ["example-loads", "--hours", "0.5", "--out", loads, "--force"])
    ok(capsys, ["monitor", "example-config", "--out", cfg, "--force"])
    assert loads.read_text().startswith("time_s,") and "[monitor]" in cfg.read_text()
    assert sorted(tree(tmp_path)) == ["l.csv", "monitor.toml"]
    link = tmp_path / "link.toml"
    link.symlink_to(loads)
    before = tree(tmp_path)
    assert "symbolic link" in refused(capsys, ["monitor", "example-config", "--out", link, "--force"], link)
    assert "symbolic link" in refused(capsys, ["example-loads", "--hours", "0.5", "--out", link, "--force"], link)
    assert tree(tmp_path) == before


def test_scenario_refuses_a_folder_holding_its_files_without_force(tmp_path, capsys):
    out = tmp_path / "sc"
    out.mkdir()
    (out / "basic_Y_loads.csv").write_text("mine\n")
    (out / "other.txt").write_text("untouched\n")
    before = tree(tmp_path)
    args = ["scenario", "basic", "--out", out, "--hours", "0.01", "--rate-hz", "2", "--increment", "30"]
    refused(capsys, args, out, "basic_Y_loads.csv", "--force")
    assert tree(tmp_path) == before
    ok(capsys, [*args, "--force"])
    after = tree(tmp_path)
    assert after["sc/other.txt"] == b"untouched\n" and after["sc/basic_Y_loads.csv"].startswith(b"time_s,")
    assert sorted(after) == sorted({"sc", "sc/other.txt"} | {f"sc/basic_{c}{s}" for c in ("X", "Y", "Z", "spindle")
                                                             for s in (".nc", "_trace.csv", "_loads.csv")})


# --------------------------------------------------------------------------- cd eval, fit, export


def test_cd_eval_never_overwrites_a_cd_and_keeps_an_existing_output(tmp_path, capsys, cd_dir):
    point = "T1=22,T2=22.5,T3=21"
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        assert "input" in refused(capsys, ["cd", "eval", cd_dir, "--point", point, "--out", cd_dir / "cd_Y.xml", *extra],
                                  cd_dir / "cd_Y.xml")
    link = tmp_path / "pred.txt"
    link.symlink_to(cd_dir / "cd_X.xml")
    assert "symbolic link" not in refused(capsys, ["cd", "eval", cd_dir, "--point", point, "--out", link, "--force"],
                                          link)  # a link to an input is refused as the input
    link.unlink()
    (tmp_path / "elsewhere.txt").write_text("not yours\n")
    link.symlink_to(tmp_path / "elsewhere.txt")
    before = tree(tmp_path)
    assert "symbolic link" in refused(capsys, ["cd", "eval", cd_dir, "--point", point, "--out", link, "--force"], link)
    assert tree(tmp_path) == before
    link.unlink()
    ok(capsys, ["cd", "eval", cd_dir, "--point", point, "--out", tmp_path / "pred.txt"])
    refused(capsys, ["cd", "eval", cd_dir, "--point", point, "--out", tmp_path / "pred.txt"], "pred.txt", "--force")
    ok(capsys, ["cd", "eval", cd_dir, "--point", point, "--out", tmp_path / "pred.txt", "--force"])
    assert (tmp_path / "pred.txt").read_text().startswith("dx_um = ")
    refused(capsys, ["cd", "eval", cd_dir, "--point", point, "--force"], "--force applies with --out only")


def test_cd_fit_and_export_keep_existing_files(tmp_path, capsys, cds, cd_dir):
    from hybridcomp.chardiag.db import CDDatabase

    rng = np.random.default_rng(0)
    data = tmp_path / "data.csv"
    T = 22.0 + rng.uniform(-2, 2, (60, 2))
    with data.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["T1_degC", "T2_degC", "dx_um", "dy_um", "dz_um"])
        w.writerows([[a, b, a - 22, 2 * (b - 22), a - b] for a, b in T])
    before = tree(tmp_path)
    refused(capsys, ["cd", "fit", data, "--out", cd_dir, "--no-plot"], cd_dir, "cd_X.xml", "--force")
    assert tree(tmp_path) == before
    db = tmp_path / "cds.sqlite"
    with CDDatabase(db) as store:
        store.add_set(cds[1])
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "cd_2_Y.xml").write_text("mine\n")
    before = tree(tmp_path)
    refused(capsys, ["cd", "db", "export", "1", "2", "--db", db, "--out", exp], exp, "cd_2_Y.xml", "--force")
    assert tree(tmp_path) == before
    ok(capsys, ["cd", "db", "export", "1", "2", "--db", db, "--out", exp, "--force"])
    assert sorted(p.name for p in exp.iterdir()) == ["cd_1_X.xml", "cd_2_Y.xml"]


# --------------------------------------------------------------------------- the database: read-only creates nothing


@pytest.mark.parametrize("action", [["list"], ["show", "1"], ["export", "1", "--out", "{tmp}/exp"],
                                    ["search", "--machine-name", "vmc800", "--pose-key", "X=0,Y=0,Z=0",
                                     "--temperatures", "T1=22"]], ids=lambda a: a[0])
def test_a_read_only_database_command_creates_nothing(tmp_path, capsys, cds, action):
    argv = ["cd", "db", *(a.format(tmp=tmp_path) for a in action)]
    missing = tmp_path / "new" / "dir" / "x.sqlite"
    text = tmp_path / "notes.txt"
    text.write_text("a text file\n")
    empty = tmp_path / "empty.sqlite"
    empty.touch()
    before = tree(tmp_path)
    assert "does not exist" in refused(capsys, [*argv, "--db", missing], missing)
    assert "is not an SQLite database" in refused(capsys, [*argv, "--db", text], text)
    assert "is not an SQLite database" in refused(capsys, [*argv, "--db", empty], empty)
    assert "is not an SQLite database" in refused(capsys, [*argv, "--db", f"sqlite:///{text}"], text)
    assert tree(tmp_path) == before


def test_reading_a_database_leaves_its_folder_as_it_was(tmp_path, capsys, cds):
    from hybridcomp.chardiag.db import CDDatabase, CDDatabaseError

    db = tmp_path / "cds.sqlite"
    with CDDatabase(db) as store:
        store.add_set(cds[1])
    before = tree(tmp_path)
    assert ok(capsys, ["cd", "db", "list", "--db", db]).count("vmc800") == 3
    assert "T_reference" in ok(capsys, ["cd", "db", "show", "2", "--db", db])
    assert tree(tmp_path) == before  # not even SQLite's -wal and -shm files are left
    with CDDatabase(db, readonly=True) as store, pytest.raises(CDDatabaseError, match="opened read-only"):
        store.add(cds[2]["X"])
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE t (x)")
    con.close()
    before = tree(tmp_path)
    refused(capsys, ["cd", "db", "list", "--db", other], other, "not a hybridcomp CD database")
    assert tree(tmp_path) == before


def test_a_writing_database_command_refuses_a_file_that_is_not_a_database(tmp_path, capsys, cd_dir):
    text = tmp_path / "notes.txt"
    text.write_text("a text file\n")
    before = tree(tmp_path)
    refused(capsys, ["cd", "db", "import", cd_dir / "cd_X.xml", "--db", text], text, "is not an SQLite database")
    refused(capsys, ["cd", "db", "activate", "X=1,Y=2,Z=3", "--db", text], text)
    assert tree(tmp_path) == before
    # a writer creates a missing database and its folder, as before
    new = tmp_path / "new" / "cds.sqlite"
    ok(capsys, ["cd", "db", "import", cd_dir / "cd_X.xml", "--db", new])
    assert n_rows(new) == 1


# --------------------------------------------------------------------------- the database: import


def test_import_is_all_or_nothing(tmp_path, capsys, cds, cd_dir):
    from hybridcomp.chardiag.xmlio import write_cd

    db = tmp_path / "cds.sqlite"
    ok(capsys, ["cd", "db", "import", cd_dir / "cd_X.xml", "--db", db])
    assert n_rows(db) == 1
    new = [write_cd(tmp_path / f"new_{k}.xml", cd) for k, cd in cds[2].items()]
    bad = tmp_path / "bad.xml"
    bad.write_bytes(new[1].read_bytes().replace(b"<", b"[", 3))
    before = tree(tmp_path)
    refused(capsys, ["cd", "db", "import", new[0], bad, new[2], "--db", db], bad)
    assert n_rows(db) == 1 and tree(tmp_path) == before
    refused(capsys, ["cd", "db", "import", new[0], tmp_path / "missing.xml", "--db", db], "missing.xml")
    assert n_rows(db) == 1
    other = tmp_path / "other.toml"
    from hybridcomp.models.loader import resolve_machine_path

    other.write_text(resolve_machine_path("vmc800").read_text().replace('name = "vmc800"', 'name = "other"', 1))
    refused(capsys, ["cd", "db", "import", *new, "--db", db, "--machine", other], new[0], "'other'")
    assert n_rows(db) == 1
    # a failure inside the transaction (here: the third insert) leaves nothing of the first two
    from hybridcomp.chardiag.db import CDDatabase, CDDatabaseError

    with CDDatabase(db) as store:
        real = store._insert
        calls = []

        def failing(conn, cd, xml, load_case):
            calls.append(cd.direction)
            if len(calls) == 3:
                raise CDDatabaseError("planted failure")
            return real(conn, cd, xml, load_case)

        store._insert = failing
        with pytest.raises(CDDatabaseError, match="planted failure"):
            store.add_many(list(cds[2].values()))
    assert calls == ["X", "Y", "Z"] and n_rows(db) == 1


def test_import_is_idempotent(tmp_path, capsys, cds, cd_dir):
    from hybridcomp.chardiag.xmlio import write_cd

    db = tmp_path / "cds.sqlite"
    files = [cd_dir / f"cd_{k}.xml" for k in ("X", "Y", "Z")]
    out = ok(capsys, ["cd", "db", "import", *files, "--db", db, "--machine", "vmc800"])
    assert out.splitlines() == [f"{f}: stored as id {i}" for i, f in enumerate(files, 1)]
    assert n_rows(db) == 3
    copy = write_cd(tmp_path / "copy_of_Y.xml", cds[1]["Y"])
    new = write_cd(tmp_path / "new_X.xml", cds[2]["X"])
    out = ok(capsys, ["cd", "db", "import", *files, copy, new, new, "--db", db])
    assert out.splitlines() == [*(f"{f}: already stored as id {i}" for i, f in enumerate(files, 1)),
                                f"{copy}: already stored as id 2", f"{new}: stored as id 4",
                                f"{new}: already stored as id 4"]
    assert n_rows(db) == 4
    ok(capsys, ["cd", "db", "import", *files, "--db", db])
    assert n_rows(db) == 4


# --------------------------------------------------------------------------- the building blocks


def test_atomic_path_keeps_the_old_file_on_failure_and_replaces_a_link_not_its_target(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old\n")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert target.read_text() == "old\n" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    victim = tmp_path / "victim.txt"
    victim.write_text("not yours\n")
    link = tmp_path / "link.txt"
    link.symlink_to(victim)
    write_text_atomic(link, "new\n")
    assert victim.read_text() == "not yours\n" and not link.is_symlink() and link.read_text() == "new\n"


def test_the_checks_name_option_and_path(tmp_path):
    inp = tmp_path / "in.csv"
    inp.write_text("x\n")
    with pytest.raises(OutputPathError, match=r"--signature .*in\.csv is the input"):
        check_output_path(tmp_path / "sub" / ".." / "in.csv", inputs=[inp], force=True, what="--signature")
    with pytest.raises(OutputPathError, match=r"is a directory"):
        check_output_path(tmp_path, force=True)
    assert check_output_path(tmp_path / "new.csv", inputs=[inp, None]) == tmp_path / "new.csv"
    assert isinstance(OutputPathError("x"), ValueError)
    d = tmp_path / "d"
    assert check_output_dir(d, ["a.csv", "sub/b.vtu"]) == d and not d.exists()
    with pytest.raises(ValueError, match="not relative"):
        check_output_dir(d, ["../escape.csv"])
    d.mkdir()
    (d / "sub").symlink_to(tmp_path)
    with pytest.raises(OutputPathError, match=r"sub is a symbolic link"):
        check_output_dir(d, ["sub/b.vtu"], force=True)
