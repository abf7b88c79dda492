"""The compiled tick and its source run interpreted compute the same, bit for bit.

mypyc compiles the modules in mrctl/build.py at install; ``MRCTL_PURE_PYTHON=1``
runs the same sources interpreted. These tests run the interpreted build in a
subprocess beside the build this suite runs (compiled where a C compiler was
there at install) and compare: every log row of replayed ticks (every
built-in law, the observer, faults, gaps, NaN samples, a reload, a law
fault), ``mrctl simulate``'s CSV, and the law, model and controller tests.
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mrctl.build import C_EXTENSIONS, COMPILED, COMPILED_MODULES, PURE, PURE_ENV, module_build, pure_requested, tick_build
from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]
PURE_ENVIRON = {**os.environ, PURE_ENV: "1"}


def _pure(*args: str, cwd: Path = ROOT, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], cwd=cwd, env=PURE_ENVIRON, capture_output=True, text=True,
                          timeout=timeout)


def test_the_suite_runs_the_compiled_build_where_a_compiler_was_there():
    if pure_requested():
        pytest.skip(f"{PURE_ENV} is set: this run is the interpreted build")
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler: the install fell back to the pure-Python build")
    assert tick_build() == COMPILED
    pure = [m for m in COMPILED_MODULES if module_build(importlib.import_module(m)) != COMPILED]
    assert not pure, f"installed without their compiled extension: {pure}"
    for name in C_EXTENSIONS:  # built with them (the run log's row formatter)
        assert module_build(importlib.import_module(name)) == COMPILED


def test_the_switch_loads_every_compiled_module_from_its_source():
    code = ("import importlib, json; from mrctl.build import COMPILED_MODULES, module_build, tick_build; "
            "from mrctl.runlog.rowtext import compiled_available; "
            "print(json.dumps([tick_build(), [module_build(importlib.import_module(m)) for m in COMPILED_MODULES], "
            "compiled_available()]))")
    res = _pure("-c", code)
    assert res.returncode == 0, res.stderr
    build, builds, c_formatter = json.loads(res.stdout)
    assert build == PURE and set(builds) == {PURE}
    assert not c_formatter  # the C extensions are refused: their Python twins run
    res = _pure("-m", "mrctl.cli", "--version")
    assert res.returncode == 0 and "(pure Python)" in res.stdout


def test_replayed_ticks_are_bit_identical_in_both_builds():
    script = str(ROOT / "tests" / "builds_replay.py")
    res = _pure(script)
    assert res.returncode == 0, res.stderr[-2000:]
    pure = json.loads(res.stdout)
    res = subprocess.run([sys.executable, script], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    this = json.loads(res.stdout)
    assert pure["build"] == PURE
    assert pure["cases"].keys() == this["cases"].keys()
    for name, case in this["cases"].items():
        other = pure["cases"][name]
        assert len(case["rows"]) == len(other["rows"]) > (250 if name == "law_fault" else 900), name
        for k, (a, b) in enumerate(zip(case["rows"], other["rows"])):
            assert a == b, f"{name}: tick {k} differs between the builds"
        assert case["fault"] == other["fault"], name
    # the replay reached what it is there for: faults, and a law fault that ended one run
    fault_ticks = sum(1 for row in this["cases"]["closed"]["rows"] if float.fromhex(row[13]))
    assert fault_ticks >= 10
    assert "non-finite" in this["cases"]["law_fault"]["fault"]


@pytest.mark.parametrize("config", ["fig5_robust.yaml", "quarter_car.yaml"])
def test_simulate_writes_the_same_csv_in_both_builds(tmp_path, config, capsys):
    exp = ROOT / "config" / "experiments" / config
    res = _pure("-m", "mrctl.cli", "simulate", str(exp), "--out", str(tmp_path / "pure.csv"), "--duration", "2")
    assert res.returncode == 0, res.stderr
    assert main(["simulate", str(exp), "--out", str(tmp_path / "this.csv"), "--duration", "2"]) == 0
    assert (tmp_path / "pure.csv").read_bytes() == (tmp_path / "this.csv").read_bytes()
    side = json.loads((tmp_path / "this.json").read_text())
    assert side["build"] == tick_build()
    assert json.loads((tmp_path / "pure.json").read_text())["build"] == PURE


@pytest.mark.parametrize("law", ["smooth", "closed", "paper"])
def test_simulate_with_the_optional_model_terms_writes_the_same_csv_in_both_builds(tmp_path, law):
    """A set with every optional term (σ1(v), rise and fall lags, the hysteretic
    stiffness) in the plant and the law: fig5_robust's motion, both builds."""
    import yaml

    from builds_replay import EXTRA_PARAMS

    data = yaml.safe_load((ROOT / "config" / "experiments" / "fig5_robust.yaml").read_text())
    data["parameters"] = dict(EXTRA_PARAMS)
    data["inverse"] = {"law": law}
    data.pop("plant", None)  # the plant's input lags are the set's (fig5_robust imposes none)
    exp = tmp_path / "extras.yaml"
    exp.write_text(yaml.safe_dump(data))
    res = _pure("-m", "mrctl.cli", "simulate", str(exp), "--out", str(tmp_path / "pure.csv"), "--duration", "2")
    assert res.returncode == 0, res.stderr
    assert main(["simulate", str(exp), "--out", str(tmp_path / "this.csv"), "--duration", "2"]) == 0
    assert (tmp_path / "pure.csv").read_bytes() == (tmp_path / "this.csv").read_bytes()
    side = json.loads((tmp_path / "this.json").read_text())
    assert side["parameters"]["k_hys_neg"] == EXTRA_PARAMS["k_hys_neg"]  # the terms reached the run


def test_the_law_model_and_controller_tests_pass_interpreted():
    """CI runs the compiled build; these tests again on the interpreted one."""
    files = ["test_lugre.py", "test_inverse.py", "test_closed.py", "test_observer.py", "test_safety.py",
             "test_controller.py", "test_law_guard.py", "test_params.py", "test_quarter_car.py"]
    res = _pure("-m", "pytest", "-q", "-p", "no:cacheprovider", *[str(ROOT / "tests" / f) for f in files],
                timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert " passed" in res.stdout and " failed" not in res.stdout


def test_without_a_compiler_the_install_is_the_pure_build_and_says_so(tmp_path):
    """setup.py with a C compiler that fails: no extension is left behind (a
    module's without the shared library would not import), and mrctl runs
    interpreted with one line on stderr."""
    import mypyc  # noqa: F401 - a test dependency: missing, the test fails
    for name in ("mrctl", "config"):
        shutil.copytree(ROOT / name, tmp_path / name, symlinks=True,
                        ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    for name in ("setup.py", "pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, tmp_path / name)
    env = {k: v for k, v in os.environ.items() if k != PURE_ENV}
    env["CC"] = "false"
    res = subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--inplace"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "installing the pure-Python build" in res.stderr
    assert not list(tmp_path.rglob("*.so"))
    env["PYTHONPATH"] = str(tmp_path)
    run = subprocess.run([sys.executable, "-m", "mrctl.cli", "simulate", "config/experiments/fig5.yaml",
                          "--duration", "0.2"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stderr.count("running the pure-Python build") == 1
