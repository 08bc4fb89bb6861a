"""One stepping module: ``model.simulate(loads, scheme=...)`` over :mod:`hybridcomp.fem.stepping`, no import circle."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hybridcomp.fem import stepping
from hybridcomp.fem.loads import example_loads

FEM = Path(stepping.__file__).resolve().parent
ROOT = FEM.parent


def _fem_imports(path: Path) -> tuple[set[str], set[str]]:
    """(modules of hybridcomp.fem imported when the module runs, those imported inside a function) of a source file."""
    tree = ast.parse(path.read_text(), str(path))
    at_run, in_function = set(), set()

    def visit(node, inside_function: bool):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and getattr(child.test, "id", None) == "TYPE_CHECKING":
                continue  # annotations only
            if isinstance(child, ast.ImportFrom) and (child.module or "").startswith("hybridcomp.fem."):
                (in_function if inside_function else at_run).add(child.module)
            visit(child, inside_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    visit(tree, False)
    return at_run, in_function


def test_model_and_stepping_import_each_other_in_one_direction_only():
    model_run, model_late = _fem_imports(FEM / "model.py")
    step_run, step_late = _fem_imports(FEM / "stepping.py")
    assert "hybridcomp.fem.stepping" in model_run  # at the top of the model module
    assert "hybridcomp.fem.model" not in step_run | step_late  # the model type under TYPE_CHECKING only
    # no circle broken by an import inside a function, in either module
    assert not {m for m in model_late | step_late if m in ("hybridcomp.fem.model", "hybridcomp.fem.stepping")}
    assert not (FEM / "transient.py").exists() and not (FEM / "timestep.py").exists()


def test_stepping_imports_without_the_model_module_in_a_fresh_interpreter():
    code = ("import sys, hybridcomp.fem.stepping as s; assert 'hybridcomp.fem.model' not in sys.modules, 'model'; "
            "import hybridcomp.fem.model as m; assert m.integrate_inputs is s.integrate_inputs; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


@pytest.fixture(scope="module")
def small_model(machine):
    from hybridcomp.fem.model import build_model

    return build_model(machine, None, 300.0)


@pytest.mark.parametrize("theta", [1.0, 0.5])
def test_simulate_theta_is_bit_identical_to_the_array_level_theta_method(small_model, machine, theta):
    """``model.simulate(loads, scheme="theta")`` adds nothing to the θ-method on the model's operators."""
    loads = example_loads(machine, duration_h=2.0, dt_s=600.0)
    res = small_model.simulate(loads, scheme="theta", theta=theta, store_steps=(3,))
    # the same run spelled out on the operators: inputs in model order, steady start, one θ-method pass
    assert loads.names == small_model.input_names
    U = loads.values.copy()
    nh = len(small_model.heat_names)
    U[:, nh:] -= small_model.reference_temperature_degC
    x0 = stepping.steady_state(small_model, U[0])
    (sens, drift), fields, _ = stepping.integrate_theta(
        small_model.M, small_model.A(), small_model.input_matrix(), (small_model.C, small_model.G), loads.time_s, U,
        theta=theta, x0=x0, coords=small_model.coords_m, cache={})
    assert fields == {}
    np.testing.assert_array_equal(res.sensors_degC, sens + small_model.reference_temperature_degC)
    np.testing.assert_array_equal(res.drift_um, drift * 1e6)
    assert set(res.fields_K) == {3}
    np.testing.assert_array_equal(res.fields_K[3], stepping.integrate_theta(
        small_model.M, small_model.A(), small_model.input_matrix(), (), loads.time_s, U, theta=theta, x0=x0,
        coords=small_model.coords_m, cache={}, store_steps=(3,))[1][3])
    assert res.time_error is None
    array_level = stepping.integrate_inputs(small_model, loads.time_s, U, scheme="theta", theta=theta)
    np.testing.assert_array_equal(res.drift_um, array_level.drift_um)


def test_default_scheme_is_trbdf2_and_options_must_fit_the_scheme(small_model, machine):
    loads = example_loads(machine, duration_h=1.0, dt_s=600.0)
    res = small_model.simulate(loads)
    assert stepping.DEFAULT_SCHEME == "trbdf2" and res.time_error["scheme"] == "TR-BDF2"
    with pytest.raises(ValueError, match="theta=0.5 applies to scheme='theta'"):
        small_model.simulate(loads, theta=0.5)
    with pytest.raises(ValueError, match="tolerance applies to scheme='trbdf2'"):
        small_model.simulate(loads, scheme="theta", tolerance=stepping.DEFAULT_TOLERANCE)
    with pytest.raises(ValueError, match="unknown time scheme 'euler'"):
        small_model.simulate(loads, scheme="euler")
    with pytest.raises(ValueError, match=r"theta must be in \[0.5, 1\]"):
        small_model.simulate(loads, scheme="theta", theta=0.3)


# -- one default time scheme across the commands -----------------------------------------------------------------
@pytest.mark.parametrize("command", [["simulate"], ["batch", "run"], ["cd", "train-data"]])
def test_every_fe_command_says_its_default_scheme_is_trbdf2(command, capsys):
    from hybridcomp.cli import main

    with pytest.raises(SystemExit):
        main([*command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "Default: TR-BDF2" in text or "Default time scheme: TR-BDF2" in text


@pytest.mark.parametrize(("options", "scheme", "theta"), [
    ([], "trbdf2", None),
    (["--theta", "0.5"], "theta", 0.5),
    (["--dt", "600"], "theta", 1.0),
])
def test_batch_and_train_data_pass_the_one_default_scheme(options, scheme, theta, monkeypatch, tmp_path, machine):
    """``batch run`` and ``cd train-data`` run TR-BDF2 unless --dt or --theta ask for the θ-method (θ = 1 with --dt)."""
    from hybridcomp.chardiag import training
    from hybridcomp.cli import main
    from hybridcomp.fem import batch
    from hybridcomp.fem.loads import write_loads

    seen = []

    def fake_batch(machine, cases, **kw):
        seen.append((kw["scheme"], kw["theta"], kw["dt_s"]))
        return {}

    def fake_training(machine, cases, pose, element_size_mm, dt_s, theta, **kw):
        seen.append((kw["scheme"], theta, dt_s))
        raise SystemExit(0)  # the table is not the point

    monkeypatch.setattr(batch, "run_batch", fake_batch)
    monkeypatch.setattr(training, "simulate_load_cases", fake_training)
    write_loads(tmp_path / "loads" / "a.csv", example_loads(machine, duration_h=1.0, dt_s=600.0))
    assert main(["batch", "run", str(tmp_path / "loads"), "--out", str(tmp_path / "b"), "--no-progress",
                 *options]) == 0
    with pytest.raises(SystemExit):
        main(["cd", "train-data", "--cases", "basic", "--heat-hours", "0.1", "--cool-hours", "0.1",
              "--out", str(tmp_path / "t.csv"), "--no-progress", *options])
    dt = 600.0 if "--dt" in options else None
    assert seen == [(scheme, theta, dt), (scheme, theta, dt)]


def test_a_model_pickles_without_its_factorisations(model_200mm):
    """A model that has stepped carries factorisations (solver state, not picklable with every backend); a copy
    sent to a worker process leaves them behind and rebuilds them, with the same result."""
    import pickle

    model = model_200mm
    loads = example_loads(model.machine, duration_h=1.0, dt_s=600.0)
    first = model.simulate(loads, scheme="theta", theta=1.0)
    assert model._cache
    copy = pickle.loads(pickle.dumps(model))
    assert copy._cache == {} and model._cache
    np.testing.assert_allclose(copy.simulate(loads, scheme="theta", theta=1.0).drift_um, first.drift_um, rtol=1e-10)
