"""One output policy for every command and every sink, checked on the parser so a new output cannot skip it.

Every option of the ``hybridcomp`` parser that names a file or folder is registered here, either as an input or
as an output (:data:`OUTPUTS`); a new path option that is in neither table fails
:func:`test_every_path_option_is_registered_as_input_or_output`.  Every output is then attacked the same way,
in-process and before any work (the expensive work is replaced by a function that fails the test): an existing
output without ``--force`` is refused, a symbolic link is refused even with ``--force``, and the tree is
byte-for-byte what it was.  The monitor's file sinks (:data:`hybridcomp.monitor.sinks.SINK_FILE_KINDS`) are never
one of its inputs, never a link, and on a full disk raise an error naming the file with only whole lines left.
"""

from __future__ import annotations

import csv
import errno
import json
import os
from pathlib import Path

import numpy as np
import pytest
from test_cli_conventions import walk  # every option of the parser
from test_faults_files import cd_set, refused, tree  # the same CDs and checks of a refusal and of the disk

from hybridcomp.cli import build_parser, main
from hybridcomp.safeio import AppendOnlyFile, OutputPathError

# --------------------------------------------------------------------------- the registry


def _name(action) -> str:
    return action.option_strings[-1] if action.option_strings else action.dest


#: every path option that a command reads
INPUTS = {
    ("simulate", "--loads"), ("simulate", "--rom"), ("histogram", "input"), ("cd fit", "data"), ("cd eval", "cds"),
    ("cd eval", "--data"), ("cd db import", "files"), ("table", "--rom"), ("table", "--loads"),
    ("reduce", "--matrices"), ("reduce", "--check-loads"), ("diagnose", "--data"), ("diagnose", "--map"),
    ("diagnose", "--rom"), ("diagnose", "--probes"), ("diagnose", "--pose-rom"), ("cd fit-grid", "--pose-rom"),
    ("data fetch", "--from"), ("batch run", "loads_dir"), ("monitor run", "--config"),
    ("monitor status", "--config"), ("monitor example-trace", "--rom"), ("monitor serve", "--config"),
    ("monitor serve", "--offsets"),
}

#: every output option: (argv with {out} and the inputs of the ``inputs`` fixture, "file" or the name of a file the
#: command writes into the folder)
OUTPUTS = {
    ("demo", "--out"): (["demo", "--out", "{out}", "--no-pictures", "--no-progress"], "report.md"),
    ("simulate", "--out"): (["simulate", "--loads", "{loads}", "--out", "{out}", "--no-progress"], "outputs.csv"),
    ("example-loads", "--out"): (["example-loads", "--hours", "0.5", "--out", "{out}"], "file"),
    ("histogram", "--out"): (["histogram", "{trace}", "--increment", "6", "--out", "{out}"], "file"),
    ("histogram", "--signature"): (["histogram", "{trace}", "--increment", "6", "--out", "{tmp}/h1.csv",
                                    "--signature", "{out}"], "file"),
    ("histogram", "--plot"): (["histogram", "{trace}", "--increment", "6", "--out", "{tmp}/h2.csv", "--plot", "{out}"],
                              "factors.png"),
    ("scenario", "--out"): (["scenario", "basic", "--out", "{out}", "--hours", "0.01", "--rate-hz", "2",
                             "--increment", "30"], "basic_Y_loads.csv"),
    ("cd train-data", "--out"): (["cd", "train-data", "--cases", "basic", "--out", "{out}"], "file"),
    ("cd fit", "--out"): (["cd", "fit", "{table}", "--out", "{out}", "--no-plot"], "cd_X.xml"),
    ("cd eval", "--out"): (["cd", "eval", "{cds}", "--point", "T1=22,T2=22.5,T3=21", "--out", "{out}"], "file"),
    ("cd db export", "--out"): (["cd", "db", "export", "1", "--db", "{db}", "--out", "{out}"], "cd_1_X.xml"),
    ("cd fit-grid", "--out"): (["cd", "fit-grid", "--pose-rom", "{rom}", "--out", "{out}"], "grid.json"),
    ("cd db grid-export", "--out"): (["cd", "db", "grid-export", "1", "--db", "{db}", "--out", "{out}"], "grid.json"),
    ("table", "--out"): (["table", "--rom", "{rom}", "--loads", "{loads}", "--at-hours", "0", "--form", "csv", "--out", "{out}"],
                         "file"),
    ("reduce", "--out"): (["reduce", "--machine", "vmc800", "--out", "{out}"], "file"),
    ("diagnose", "--out"): (["diagnose", "--data", "{measured}", "--out", "{out}"], "report.md"),
    ("data fetch", "--out"): (["data", "fetch", "caiviac-spindle", "--from", "{measured}", "--out", "{out}"],
                              "caiviac-spindle.csv"),
    ("batch run", "--out"): (["batch", "run", "{loads_dir}", "--out", "{out}", "--no-progress"], "day.csv"),
    ("iso230 moving-axis", "--out"): (["iso230", "moving-axis", "--axis", "X", "--out", "{out}", "--no-progress"],
                                      "moving_axis_X.json"),
    ("iso230 etve", "--out"): (["iso230", "etve", "--out", "{out}", "--no-progress"], "etve.csv"),
    ("monitor example-config", "--out"): (["monitor", "example-config", "--out", "{out}"], "file"),
    ("monitor example-trace", "--out"): (["monitor", "example-trace", "--rom", "{rom}", "--out", "{out}"], "file"),
    ("monitor scenario", "--out"): (["monitor", "scenario", "--out", "{out}", "--basic-hours", "1"], "summary.json"),
    ("verify", "--out"): (["verify", "--out", "{out}"], "report.md"),
}

PATH_OPTIONS = sorted({(" ".join(p), _name(a)) for p, a in walk(build_parser()) if a.type is Path})


def test_every_path_option_is_registered_as_input_or_output():
    assert set(PATH_OPTIONS) == INPUTS | set(OUTPUTS), "register the new path option in INPUTS or OUTPUTS"
    assert not INPUTS & set(OUTPUTS)


@pytest.mark.parametrize("command", sorted({c for c, _ in OUTPUTS}))
def test_every_command_with_an_output_has_force(command):
    options = {o for p, a in walk(build_parser()) if " ".join(p) == command for o in a.option_strings}
    assert "--force" in options, f"{command}: an output command overwrites an existing file only with --force"


# --------------------------------------------------------------------------- fixtures


def reached_work(capsys, argv) -> None:
    """Run ``argv``; assert that it passed the output checks and reached the (replaced) work."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 1 and "WorkStarted" in err, err


class WorkStarted(Exception):
    """Raised by the expensive work: the output was not refused before it."""


@pytest.fixture()
def no_work(monkeypatch):
    """Replace every expensive stage by one that fails the test: a refusal must come before the work."""

    def fail(*a, **k):
        raise WorkStarted("the work started before the output was refused")

    for target in ("hybridcomp.fem.model.build_model", "hybridcomp.demo.run_demo", "hybridcomp.scenario.run_scenario",
                   "hybridcomp.fem.batch.run_batch", "hybridcomp.diagnose.core.prepare_model",
                   "hybridcomp.diagnose.core.read_measured", "hybridcomp.rom.reduced.load_rom",
                   "hybridcomp.rom.load_rom", "hybridcomp.chardiag.training.simulate_load_cases"):
        monkeypatch.setattr(target, fail)


@pytest.fixture(scope="module")
def cds():
    return cd_set(1)


@pytest.fixture()
def inputs(tmp_path, cds):
    """The inputs the argv templates name, in tmp_path/in."""
    from hybridcomp.chardiag.xmlio import write_cd

    d = tmp_path / "in"
    d.mkdir()
    files = {"tmp": tmp_path}
    files["loads"] = d / "l.csv"
    files["loads"].write_text("time_s,x_motor_W\n0,1\n60,1\n")
    files["loads_dir"] = d / "cases"
    files["loads_dir"].mkdir()
    (files["loads_dir"] / "day.csv").write_text("time_s,x_motor_W\n0,1\n60,1\n")
    files["trace"] = d / "t.csv"
    with files["trace"].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", "x_mm", "y_mm", "z_mm", "spindle_rpm", "Tamb_degC"])
        w.writerows([[f"{0.1 * i:.1f}", "0", "0", "0", "12000", "21"] for i in range(121)])
    files["table"] = d / "data.csv"
    files["table"].write_text("T1_degC,T2_degC,dx_um,dy_um,dz_um\n" +
                              "".join(f"{22 + i / 10},{21 + i / 7},{i / 10},{i / 5},{i / 20}\n" for i in range(40)))
    files["cds"] = d / "cds"
    for k, cd in cds.items():
        write_cd(files["cds"] / f"cd_{k}.xml", cd)
    files["rom"] = d / "r.npz"
    files["rom"].write_bytes(b"not read: the output is refused first")
    files["measured"] = d / "measured.csv"
    files["measured"].write_text("time_s,dx_um\n0,0\n1,0\n")
    files["db"] = d / "cds.sqlite"
    return files


def _argv(template, files, out):
    return [a.format(out=out, **files) for a in template]


@pytest.mark.parametrize("key", sorted(OUTPUTS), ids=[" ".join(k) for k in sorted(OUTPUTS)])
def test_every_output_refuses_an_existing_file_without_force_and_a_link_always(tmp_path, capsys, no_work, inputs,
                                                                             key):
    template, held = OUTPUTS[key]
    if "{db}" in " ".join(template):
        pytest.importorskip("sqlalchemy", reason="the CD database needs SQLAlchemy")
        from hybridcomp.chardiag.db import CDDatabase

        with CDDatabase(inputs["db"]) as store:
            store.add_set(inputs_cds := cd_set(1))
        assert inputs_cds
    out = tmp_path / "o"
    if held == "file":
        out.write_text("mine\n")
        existing = out
    else:
        out.mkdir()
        existing = out / held
        existing.write_text("mine\n")
    argv = _argv(template, inputs, out)
    before = tree(tmp_path)
    assert "--force" in refused(capsys, argv, out)
    assert tree(tmp_path) == before
    victim = tmp_path / "victim.txt"
    victim.write_text("not yours\n")
    existing.unlink()
    existing.symlink_to(victim)
    before = tree(tmp_path)
    assert "symbolic link" in refused(capsys, [*argv, "--force"], existing.name)
    assert tree(tmp_path) == before


# --------------------------------------------------------------------------- the attacks of the issue


def test_reduce_never_overwrites_its_machine_file_even_with_force(tmp_path, capsys, no_work):
    from hybridcomp.models.loader import resolve_machine_path

    m = tmp_path / "m.toml"
    m.write_bytes(resolve_machine_path("vmc800").read_bytes())
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        assert "is the input" in refused(capsys, ["reduce", "--machine", m, "--out", m, *extra], m)
    assert tree(tmp_path) == before


def test_reduce_keeps_an_existing_model_without_force_and_never_writes_through_a_link(tmp_path, capsys, no_work):
    used = tmp_path / "vmc800.rom.npz"  # the model a monitor configuration reads
    used.write_bytes(b"the order-91 model")
    victim = tmp_path / "elsewhere.npz"
    victim.write_bytes(b"not yours")
    link = tmp_path / "link.npz"
    link.symlink_to(victim)
    before = tree(tmp_path)
    assert "pass --force" in refused(capsys, ["reduce", "--order", "10", "--out", used], used)
    assert "symbolic link" in refused(capsys, ["reduce", "--order", "10", "--out", link, "--force"], link)
    assert tree(tmp_path) == before


def test_batch_run_never_replaces_its_input_loads(tmp_path, capsys, no_work):
    cases = tmp_path / "cases"
    cases.mkdir()
    for k in (1, 2):
        (cases / f"day{k}.csv").write_text("time_s,x_motor_W\n0,1\n60,1\n")
    before = tree(tmp_path)
    for extra in ([], ["--force"], ["--resume"]):
        assert "is the input" in refused(capsys, ["batch", "run", cases, "--out", cases, "--no-progress", *extra],
                                         cases / "day1.csv")
    assert tree(tmp_path) == before


def test_batch_run_keeps_an_earlier_batch_without_force(tmp_path, capsys, no_work):
    cases = tmp_path / "cases"
    cases.mkdir()
    (cases / "day1.csv").write_text("time_s,x_motor_W\n0,1\n60,1\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "batch.json").write_text("{}\n")
    before = tree(tmp_path)
    assert "pass --force" in refused(capsys, ["batch", "run", cases, "--out", out, "--no-progress"], "batch.json")
    assert tree(tmp_path) == before
    reached_work(capsys, ["batch", "run", cases, "--out", out, "--no-progress", "--resume"])  # accepted
    reached_work(capsys, ["batch", "run", cases, "--out", out, "--no-progress", "--force"])


def test_diagnose_never_writes_through_a_link_nor_over_its_machine_file(tmp_path, capsys, no_work):
    from hybridcomp.models.loader import resolve_machine_path

    data = tmp_path / "measured.csv"
    data.write_text("time_s,dx_um\n0,0\n1,0\n")
    out = tmp_path / "diag"
    out.mkdir()
    victim = tmp_path / "victim.md"
    victim.write_text("not yours\n")
    (out / "report.md").symlink_to(victim)
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        assert "symbolic link" in refused(capsys, ["diagnose", "--data", data, "--out", out, *extra], "report.md")
    assert tree(tmp_path) == before
    (out / "report.md").unlink()
    extended = out / "machine_extended.toml"  # the previous run's extended machine, diagnosed again
    extended.write_bytes(resolve_machine_path("vmc800").read_bytes())
    before = tree(tmp_path)
    for extra in ([], ["--force"]):
        assert "is the input" in refused(capsys, ["diagnose", "--machine", extended, "--data", data, "--out", out,
                                                  *extra], extended)
    assert tree(tmp_path) == before


@pytest.mark.parametrize("argv", [["demo", "--no-pictures", "--no-progress"], ["monitor", "scenario"]],
                         ids=["demo", "monitor scenario"])
def test_demo_and_scenario_keep_an_earlier_folder_without_force(tmp_path, capsys, no_work, argv):
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text('{"disturbance": "the earlier run"}\n')
    (out / "real_machine.toml").write_text("# the earlier run's machine\n")
    before = tree(tmp_path)
    assert "pass --force" in refused(capsys, [*argv, "--out", out], out)
    assert tree(tmp_path) == before
    victim = tmp_path / "victim"
    victim.mkdir()
    (out / "hybrid_nominal").symlink_to(victim)
    before = tree(tmp_path)
    assert "symbolic link" in refused(capsys, [*argv, "--out", out, "--force"], "hybrid_nominal")
    assert tree(tmp_path) == before
    (out / "hybrid_nominal").unlink()
    reached_work(capsys, [*argv, "--out", out, "--force"])  # with --force it runs, the earlier summary gone first
    assert not (out / "summary.json").exists() and (out / "real_machine.toml").exists()


# --------------------------------------------------------------------------- the monitor's sinks


CONFIG = """\
[monitor]
machine = "{machine}"
database = "cds.sqlite"
rom = "r.npz"
[source]
kind = "replay"
path = "trace.csv"
[sink]
kind = "{kind}"
{sink}
"""


def test_the_sink_kinds_are_the_configurations():
    from hybridcomp.monitor.config import SINK_KINDS
    from hybridcomp.monitor.sinks import SINK_FILE_KINDS

    assert set(SINK_FILE_KINDS) == set(SINK_KINDS), "register the new sink kind in SINK_FILE_KINDS"


FILE_SINKS = [(kind, key) for kind in ("jsonl", "csv", "opcua", "none") for key in ("path", "table_path")
              if key == "table_path" or kind in ("jsonl", "csv")]
VICTIMS = ["trace.csv", "monitor.toml", "r.npz", "cds.sqlite", "m.toml"]


@pytest.mark.parametrize("kind,key", FILE_SINKS, ids=[f"{k}.{p}" for k, p in FILE_SINKS])
@pytest.mark.parametrize("victim", VICTIMS)
def test_a_sink_is_never_an_input_of_the_monitor(tmp_path, capsys, kind, key, victim):
    from hybridcomp.models.loader import resolve_machine_path

    (tmp_path / "m.toml").write_bytes(resolve_machine_path("vmc800").read_bytes())
    (tmp_path / "trace.csv").write_text("time_s,x_mm,y_mm,z_mm,spindle_rpm,Tamb_degC\n0,0,0,0,0,20\n")
    (tmp_path / "r.npz").write_bytes(b"a model")
    (tmp_path / "cds.sqlite").write_bytes(b"a database")
    other = {"path": 'path = "offsets.out"'} if kind in ("jsonl", "csv") and key == "table_path" else {}
    extra = "\n".join([*other.values(), 'url = "opc.tcp://127.0.0.1:1"\nnodes = {dx_um = "ns=2;s=dx"}'
                       if kind == "opcua" else "", f'{key} = "{victim}"'])
    cfg = tmp_path / "monitor.toml"
    cfg.write_text(CONFIG.format(machine="m.toml", kind=kind, sink=extra))
    before = tree(tmp_path)
    err = refused(capsys, ["monitor", "run", "--config", cfg], f"sink.{key}", victim)
    assert "input of the monitor" in err
    assert tree(tmp_path) == before
    # the same file by another name: a hard link is refused by its inode
    os.link(tmp_path / victim, tmp_path / "alias")
    cfg.write_text(CONFIG.format(machine="m.toml", kind=kind, sink=extra.replace(f'"{victim}"', '"alias"')))
    before = tree(tmp_path)
    refused(capsys, ["monitor", "run", "--config", cfg], "alias")
    assert tree(tmp_path) == before


def test_a_sink_is_never_a_link(tmp_path, capsys):
    victim = tmp_path / "victim.jsonl"
    victim.write_text("not yours\n")
    (tmp_path / "offsets.jsonl").symlink_to(victim)
    cfg = tmp_path / "monitor.toml"
    cfg.write_text(CONFIG.format(machine="vmc800", kind="jsonl", sink='path = "offsets.jsonl"'))
    before = tree(tmp_path)
    assert "symbolic link" in refused(capsys, ["monitor", "run", "--config", cfg], "offsets.jsonl")
    assert tree(tmp_path) == before
    from hybridcomp.monitor.sinks import JsonlSink

    with pytest.raises(OutputPathError, match="symbolic link"):  # and the sink itself never opens one
        JsonlSink(tmp_path / "offsets.jsonl")
    assert victim.read_text() == "not yours\n"


class FullDisk:
    """A raw file whose write puts part of the data on disk, then fails as a full disk does."""

    def __init__(self, fh, error=errno.ENOSPC, after: int = 7):
        self.fh, self.error, self.after = fh, error, after

    def write(self, data):
        self.fh.write(bytes(data)[:self.after])
        raise OSError(self.error, os.strerror(self.error))

    def __getattr__(self, name):
        return getattr(self.fh, name)


def _offset(t: float, table=None):
    from hybridcomp.monitor.sinks import Offset

    return Offset(time_s=t, dx_um=1.5 * t, dy_um=-0.25, dz_um=2.0, active="X=1,Y=2,Z=3", table=table)


SINK_KINDS = ["jsonl", "csv", "table"]


def _make(kind: str, path: Path, monkeypatch):
    from hybridcomp.monitor.config import SinkConfig
    from hybridcomp.monitor.sinks import make_sink

    if kind == "table":
        monkeypatch.setattr("hybridcomp.rom.volumetric.table_to_dict", lambda table: {"table": table})
        sink = make_sink(SinkConfig(kind="none", table_path=path))
        return sink, sink.sinks[1]
    sink = make_sink(SinkConfig(kind=kind, path=path))
    return sink, sink


def _lines(kind: str, path: Path) -> list:
    text = path.read_text()
    assert text.endswith("\n")
    if kind == "csv":
        return list(csv.reader(text.splitlines()))
    return [json.loads(line) for line in text.splitlines()]


@pytest.mark.parametrize("error", [errno.ENOSPC, errno.EIO], ids=["ENOSPC", "EIO"])
@pytest.mark.parametrize("kind", SINK_KINDS)
def test_a_full_disk_raises_an_error_naming_the_sink_and_leaves_whole_lines(tmp_path, monkeypatch, kind, error):
    import asyncio

    from hybridcomp.errors import HybridcompError
    from hybridcomp.monitor.sinks import SinkWriteError

    path = tmp_path / f"offsets.{kind}"
    sink, file_sink = _make(kind, path, monkeypatch)

    async def go():
        for t in (0.0, 5.0):
            await sink.write(_offset(t, table=[t]))
        good = path.read_bytes()
        real = file_sink._file._fh
        file_sink._file._fh = FullDisk(real, error)
        with pytest.raises(SinkWriteError) as info:
            await sink.write(_offset(10.0, table=[10.0]))
        assert path.read_bytes() == good, "the partial line was left behind"
        file_sink._file._fh = real  # space again: the next line is whole and follows the last whole one
        await sink.write(_offset(15.0, table=[15.0]))
        await sink.close()
        return info.value

    exc = asyncio.run(go())
    assert isinstance(exc, HybridcompError) and exc.path == path and str(path) in str(exc)
    assert os.strerror(error) in str(exc)
    rows = _lines(kind, path)
    if kind == "csv":
        assert rows[0][0] == "time_s" and [r[0] for r in rows[1:]] == ["0.000000", "5.000000", "15.000000"]
    elif kind == "jsonl":
        assert [r["time_s"] for r in rows] == [0.0, 5.0, 15.0]
    else:
        assert [r["table"] for r in rows] == [[0.0], [5.0], [15.0]]


def test_a_failed_fsync_is_cut_back_too(tmp_path, monkeypatch):
    f = AppendOnlyFile(tmp_path / "a.jsonl")
    f.append('{"a": 1}\n')

    def no_fsync(fd):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, "fsync", no_fsync)
    with pytest.raises(OSError):
        f.append('{"a": 2}\n')
    assert (tmp_path / "a.jsonl").read_text() == '{"a": 1}\n'
    with pytest.raises(ValueError, match="whole lines"):
        f.append('{"a": 3}')
    f.close()


def test_an_unfinished_last_line_is_cut_at_opening_and_a_foreign_csv_is_refused(tmp_path):
    from hybridcomp.monitor.sinks import CsvSink, JsonlSink

    p = tmp_path / "offsets.jsonl"
    p.write_text('{"time_s": 0}\n{"time_s": 5, "dx_u')  # a crash in the middle of a line
    JsonlSink(p)._file.close()
    assert p.read_text() == '{"time_s": 0}\n'
    trace = tmp_path / "trace.csv"
    trace.write_text("time_s,x_mm\n0,1\n")
    with pytest.raises(OutputPathError, match="not the offsets' header"):
        CsvSink(trace)
    assert trace.read_text() == "time_s,x_mm\n0,1\n"
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for not_a_file in (fifo, tmp_path):  # refused at once: a named pipe without a reader does not block the open
        with pytest.raises(OutputPathError, match="cannot open to append|not a regular file"):
            JsonlSink(not_a_file)


# --------------------------------------------------------------------------- physical plausibility (item 5)


def _machine_with(tmp_path: Path, old: str, new: str) -> Path:
    from hybridcomp.models.loader import resolve_machine_path

    text = resolve_machine_path("vmc800").read_text()
    assert old in text
    p = tmp_path / "m.toml"
    p.write_text(text.replace(old, new, 1))
    return p


ABSURD = [
    ("conductivity_W_mK = 46.0", "conductivity_W_mK = 1e-300", "conductivity_W_mK", "1e-300"),
    ("expansion_1_K = 11.5e-6", "expansion_1_K = 1e300", "expansion_1_K", "1e+300"),
    ("h_W_m2K = 10.0", "h_W_m2K = 1e300", "h_W_m2K", "1e+300"),
    ("density_kg_m3 = 7200.0", "density_kg_m3 = 1e-200", "density_kg_m3", "1e-200"),
    ("specific_heat_J_kgK = 460.0", "specific_heat_J_kgK = 1e250", "specific_heat_J_kgK", "1e+250"),
    ("youngs_modulus_GPa = 210.0", "youngs_modulus_GPa = 1e-250", "youngs_modulus_GPa", "1e-250"),
]


@pytest.mark.parametrize("old,new,field,value", ABSURD, ids=[a[2] for a in ABSURD])
def test_an_absurd_material_or_boundary_value_is_refused_naming_file_field_value(tmp_path, capsys, old, new, field,
                                                                                 value):
    m = _machine_with(tmp_path, old, new)
    out = tmp_path / "run"
    err = refused(capsys, ["simulate", "--machine", m, "--loads", _loads(tmp_path), "--out", out,
                           "--element-size-mm", "400", "--no-progress"], m, field, value, "plausible range")
    assert not out.exists()
    refused(capsys, ["machine", m], field)
    assert err


def test_the_bundled_machine_and_its_handbook_values_pass():
    from hybridcomp.models.loader import PHYSICAL_RANGES, load_machine

    m = load_machine("vmc800")
    for mat in m.materials.values():
        for field, v in (("conductivity_W_mK", mat.conductivity_W_mK), ("density_kg_m3", mat.density_kg_m3),
                         ("specific_heat_J_kgK", mat.specific_heat_J_kgK), ("expansion_1_K", mat.expansion_1_K),
                         ("youngs_modulus_GPa", mat.youngs_modulus_Pa / 1e9)):
            lo, hi, _ = PHYSICAL_RANGES[field]
            assert lo <= v <= hi, (mat.name, field, v)
    # the extremes of the handbooks are inside: air (0.026 W/(m K), 1.2 kg/m³, 1005 J/(kg K)), diamond
    # (2,300 W/(m K), 1,050 GPa), Invar (1.2e-6 1/K), condensing steam (h = 1e4 W/(m² K))
    for field, v in (("conductivity_W_mK", 0.026), ("conductivity_W_mK", 2300), ("density_kg_m3", 1.2),
                     ("specific_heat_J_kgK", 1005), ("youngs_modulus_GPa", 1050), ("expansion_1_K", 1.2e-6),
                     ("h_W_m2K", 1e4)):
        lo, hi, _ = PHYSICAL_RANGES[field]
        assert lo <= v <= hi, (field, v)


def _loads(tmp_path: Path) -> Path:
    p = tmp_path / "l.csv"
    if not p.exists():
        p.write_text("time_s,x_motor_W,spindle_bearing_front_W\n0,50,100\n600,50,100\n1200,50,100\n")
    return p


# A conductivity of 1e-300 leaves the steady start's matrix singular inside the bodies (convection reaches the
# surface only): what comes out is round-off, below absolute zero or far above melting depending on the sparse
# ordering; either is an impossible result the check must refuse
IMPOSSIBLE_T = ("below absolute zero", "where every solid has melted", "not finite")


@pytest.mark.parametrize("old,new,column,why", [
    ("conductivity_W_mK = 46.0", "conductivity_W_mK = 1e-300", "_degC", IMPOSSIBLE_T),
    ("expansion_1_K = 11.5e-6", "expansion_1_K = 1e300", "_um", ("not finite",)),
], ids=["conductivity 1e-300", "expansion 1e300"])
@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the overflow of 1e300 in the assembly, before the check
def test_simulate_never_writes_a_non_finite_or_impossible_result(tmp_path, capsys, monkeypatch, old, new, column, why):
    # the loader's ranges off (as before them): the final check of simulate's outputs still refuses
    from hybridcomp.models import loader

    monkeypatch.setattr(loader, "PHYSICAL_RANGES", {k: (0.0, np.inf, u) for k, (_, _, u) in loader.PHYSICAL_RANGES.items()})
    m = _machine_with(tmp_path, old, new)
    out = tmp_path / "run"
    rc = main([str(a) for a in ["simulate", "--machine", m, "--loads", _loads(tmp_path), "--out", out,
                                "--element-size-mm", "400", "--no-progress"]])
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the time-error warning, the one error line
    assert rc == 2 and err.startswith(f"error: simulate {m}: column") and column in err, err
    assert any(w in err for w in why), err
    assert "nothing is written" in err
    assert not (out / "outputs.csv").exists() and not (out / "run.json").exists()


def test_the_result_check_names_column_time_and_value():
    from hybridcomp.models.layout import ResultError, check_result

    t = np.array([0.0, 60.0])
    check_result(t, ["T1_degC", "dx_um"], np.array([[20.0, 1.0], [3999.0, -9e5]]))
    with pytest.raises(ResultError, match=r"'T1_degC' is 1e\+281 at t = 60 s, above 4000 °C"):
        check_result(t, ["T1_degC", "dx_um"], np.array([[20.0, 1.0], [1e281, 1.0]]), "simulate")
    with pytest.raises(ResultError, match=r"'dx_um' is nan at t = 0 s, not finite"):
        check_result(t, ["T1_degC", "dx_um"], np.array([[20.0, np.nan], [20.0, 1.0]]))
    with pytest.raises(ResultError, match=r"'dy_um' is 1e\+15 at t = 60 s, beyond"):
        check_result(t, ["dy_um"], np.array([[0.0], [1e15]]))
    with pytest.raises(ResultError, match="below absolute zero"):
        check_result(t, ["T1_degC"], np.array([[20.0], [-300.0]]))


# --------------------------------------------------------------------------- a model that fails its check


def test_reduce_warns_loudly_when_the_model_fails_its_fe_check(tmp_path, capsys, monkeypatch):
    # a written model that reports passed = false (reduce --order 10) is a warning on stderr naming the file, the
    # errors and the tolerances, beside "passed": false in the summary; exit 0 because the order was asked for
    from hybridcomp.fem.operators import ThermalOperators
    from hybridcomp.rom.reduced import ReducedModel, load_rom

    r = 3
    rom = ReducedModel(ThermalOperators(
        M=np.eye(r), K=2 * np.eye(r), H=np.eye(r)[None], h_W_m2K=np.array([8.0]), B=np.ones((r, 1)),
        Hb=np.ones((r, 1)), C=np.ones((1, r)), input_names=("spindle_W", "air_degC"), output_names=("T1",)),
        meta={"check": {"max_sensor_error_K": [0.4, 1.25], "max_drift_error_um": [3.5], "passed": False}})

    class Model:
        n = 10

    monkeypatch.setattr("hybridcomp.fem.model.build_model", lambda *a, **k: Model())
    monkeypatch.setattr("hybridcomp.rom.machine.reduce_model", lambda *a, **k: rom)
    out = tmp_path / "r.npz"
    assert main(["reduce", "--order", "10", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert f"warning: {out} does NOT meet the tolerances on the FE check: sensors off by up to 1.25 K (--tol-K 0.05), " \
           "drift by up to 3.5 µm (--tol-um 0.2) at --order 10" in cap.err
    assert json.loads(cap.out)["passed"] is False
    assert load_rom(out).meta["check"]["passed"] is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]  # written atomically: no temporary file left
