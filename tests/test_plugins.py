"""Law plugins: the example package installed from examples/, entry points,
module:Class names, and what is refused (with its key, never a traceback)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mrctl.config import ConfigError, load_experiment
from mrctl.laws import registry

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "mrctl-law-example"
FIG5 = (ROOT / "config" / "experiments" / "fig5.yaml").read_text()


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The example package installed (pip, from a copy of examples/) into a
    directory of its own: the test venv is left as it was, so the test is
    idempotent. pip builds it offline: setuptools comes from this machine's
    package index (build isolation), or from the venv if it can build wheels."""
    tmp = tmp_path_factory.mktemp("plugin")
    src, target = tmp / "src", tmp / "site"
    shutil.copytree(EXAMPLE, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    base = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check",
            "--target", str(target)]
    tries = [base + [str(src)], base + ["--no-build-isolation", "--no-index", str(src)]]
    errors = []
    for cmd in tries:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if r.returncode == 0:
            break
        errors.append(r.stderr[-2000:])
    else:
        pytest.fail("could not install examples/mrctl-law-example:\n" + "\n".join(errors))
    assert (target / "mrctl_law_example").is_dir()
    assert list(target.glob("mrctl_law_example-*.dist-info/entry_points.txt"))
    return target


def _env(site: Path) -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]))


def _mrctl(site: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=ROOT, env=_env(site),
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def on_path(site, monkeypatch):
    """The installed example visible in this process too (entry points scan sys.path)."""
    monkeypatch.syspath_prepend(str(site))
    registry.REGISTRY.clear()
    yield site
    registry.REGISTRY.clear()


def test_check_shows_the_plugin_its_source_and_keys(site):
    r = _mrctl(site, "check", str(EXAMPLE / "example.yaml"))
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "inverse.law: force_pi (entry point mrctl-law-example (mrctl.inverse_laws" in out
    assert "kp_A_per_N = 0.004" in out and "ki_A_per_Ns = 0.5" in out
    assert "demand.type: sine_force (entry point mrctl-law-example" in out
    assert "  force_pi [entry point mrctl-law-example" in out and "(keys: kp_A_per_N, ki_A_per_Ns, ff_A_per_N)" in out
    assert "  smooth [built-in]" in out
    r = _mrctl(site, "check", "--laws")
    assert r.returncode == 0 and "| `inverse.kp_A_per_N` | number (>= 0, <= 1) | `0.004` | proportional gain (A/N) |" in r.stdout


def test_simulate_runs_the_plugin(site, tmp_path):
    out = tmp_path / "sim.csv"
    r = _mrctl(site, "simulate", str(EXAMPLE / "example.yaml"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "law force_pi" in r.stdout
    nrmse = float(r.stdout.split("force NRMSE")[1].split(":")[1].split("%")[0])
    assert nrmse < 3.0  # the PI on the load cell tracks its demand
    data = np.genfromtxt(out, delimiter=",", names=True)  # a plain CSV: the header first
    assert len(data) == 4001 and np.nanmax(np.abs(data["F_des"])) == pytest.approx(30.0, rel=1e-3)


def test_run_runs_the_plugin_on_the_sim_bench(site, tmp_path):
    out = tmp_path / "run.csv"
    cfg = tmp_path / "example.yaml"  # timing not judged: a shared machine
    cfg.write_text((EXAMPLE / "example.yaml").read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    r = _mrctl(site, "run", str(cfg), "--duration", "1.5", "--quiet", "--out", str(out),
               "--status-socket", str(tmp_path / "st.sock"))
    assert r.returncode == 0, r.stderr
    assert "law force_pi" in r.stdout and "safety: OK" in r.stdout
    from mrctl.daemon.recorder import read_run

    cols = read_run(out)
    assert len(cols["t"]) > 500 and np.max(cols["I"]) > 0.05


@pytest.mark.parametrize("edit,expect", [
    (("kp_A_per_N: 0.004", "kp: 0.004"), "inverse.kp: unknown key (allowed here: law, kp_A_per_N, ki_A_per_Ns, ff_A_per_N)"),
    (("kp_A_per_N: 0.004", "kp_A_per_N: -1"), "inverse.kp_A_per_N: -1 out of range"),
    (("amplitude_N: 30.0", "amplitude: 30.0"), "demand.amplitude: unknown key"),
    (("law: force_pi", "law: force_pj"), "inverse.law: 'force_pj' not allowed"),
])
def test_a_wrong_key_in_the_plugin_section_exits_2_naming_it(site, tmp_path, edit, expect):
    text = (EXAMPLE / "example.yaml").read_text()
    assert edit[0] in text
    p = tmp_path / "bad.yaml"
    p.write_text(text.replace(edit[0], edit[1]))
    for cmd in ("check", "simulate", "run"):
        r = _mrctl(site, cmd, str(p))
        assert r.returncode == 2, (cmd, r.stdout, r.stderr)
        assert expect in r.stderr and "Traceback" not in r.stderr


def test_the_unknown_name_lists_plugins(site, tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text((EXAMPLE / "example.yaml").read_text().replace("law: force_pi", "law: force_pj"))
    r = _mrctl(site, "check", str(p))
    assert "plugins: force_pi" in r.stderr


def test_sighup_swaps_in_a_plugin_law(on_path, tmp_path):
    from mrctl.daemon.recorder import read_run
    from mrctl.daemon.service import RunOptions, Service

    cfg = tmp_path / "exp.yaml"
    open_timing = "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n"  # the reload is judged, not the clock
    cfg.write_text(FIG5 + open_timing)
    out = tmp_path / "run.csv"
    svc = Service(RunOptions(str(cfg), out=str(out), duration_s=2.5, live=False,
                             status_socket=str(tmp_path / "st.sock")))
    marks = {}

    def later():
        while svc.ctl is None or svc.ctl.ticks < 500:
            time.sleep(0.005)
        cfg.write_text(FIG5.replace("law: smooth", "law: force_pi").replace("  eps_N_per_A: 3.0", "  kp_A_per_N: 0.004")
                       .replace("  max_slew_A_per_s: 50.0", "  ki_A_per_Ns: 0.5") + open_timing)
        os.kill(os.getpid(), signal.SIGHUP)
        while svc.reloads_ok + svc.reloads_rejected < 1:
            time.sleep(0.005)
        marks["at"] = svc.ctl.ticks
        while svc.ctl.ticks < marks["at"] + 5:
            time.sleep(0.005)
        marks["law"] = svc.ctl.law.name

    threading.Thread(target=later, daemon=True).start()
    assert svc.run() == 0
    assert svc.reloads_ok == 1, svc.last_reload_error
    assert marks["law"] == "force_pi" and type(svc.ctl.law).__module__ == "mrctl_law_example.laws"
    cols = read_run(out)
    assert np.all(np.isfinite(cols["I"])) and svc.ctl.law_fault is None


def _fake_dist(root: Path, name: str, entry_points: str) -> None:
    d = root / f"{name}-1.0.dist-info"
    d.mkdir(parents=True)
    (d / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (d / "entry_points.txt").write_text(entry_points)


@pytest.fixture
def fake_plugins(tmp_path, monkeypatch):
    """Installed-looking plugins (dist-info on sys.path): a clash with a
    built-in, one that fails to import, one that is not a law, a good one."""
    site = tmp_path / "site"
    _fake_dist(site, "clashing", "[mrctl.inverse_laws]\nsmooth = bad_laws:Raises\n")
    _fake_dist(site, "broken", "[mrctl.current_laws]\nbroken = no_such_module_xyz:Law\nnotlaw = bad_laws:NotALaw\n")
    _fake_dist(site, "good", "[mrctl.current_laws]\nraiser = bad_laws:Raises\n")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.syspath_prepend(str(Path(__file__).parent / "plugins"))
    registry.REGISTRY.clear()
    yield site
    registry.REGISTRY.clear()


def _load(tmp_path: Path, inverse: str) -> object:
    p = tmp_path / "exp.yaml"
    p.write_text(FIG5.replace("law: smooth", inverse).replace("  eps_N_per_A: 3.0        # hold the current where dF/dI is below ~3 N/A\n", "")
                 .replace("  max_slew_A_per_s: 50.0  # current-driver slew bound: 0.05 A per 1 ms tick\n", ""))
    return load_experiment(p)


def test_entry_points_are_found_and_refused_with_reasons(fake_plugins, tmp_path):
    infos: dict = {}
    for i in registry.all_laws("current"):
        infos.setdefault(i.name, i)
    assert infos["smooth"].source == "built-in" and infos["smooth"].cls is not None  # the built-in wins
    assert infos["raiser"].cls is not None and infos["raiser"].source.startswith("entry point good (mrctl.current_laws")
    assert "No module named 'no_such_module_xyz'" in infos["broken"].error
    assert "not a law class" in infos["notlaw"].error
    with pytest.raises(ConfigError) as e:
        _load(tmp_path, "law: broken")
    assert "inverse.law: 'broken' (entry point broken (mrctl.current_laws: broken = no_such_module_xyz:Law))" in str(e.value)
    assert _load(tmp_path, "law: raiser").inverse.law == "raiser"
    clash = [i for i in registry.REGISTRY.entry_points("current").values() if "clashes" in (i.error or "")]
    assert clash and "clashes with the built-in law 'smooth': rename the entry point" in clash[0].error


@pytest.mark.parametrize("name,expect", [
    ("'no_such_module_xyz:Law'", "inverse.law: cannot load 'no_such_module_xyz:Law': ModuleNotFoundError"),
    ("'bad_laws:Missing'", "inverse.law: cannot load 'bad_laws:Missing': AttributeError"),
    ("'bad_laws:NotALaw'", "is not a law class"),
    ("'bad_laws:DemandRaises'", "bad_laws.DemandRaises is a DemandLaw; inverse.law needs a subclass of mrctl.laws.base.CurrentLaw"),
    ("'bad_laws:BadParams'", "BadParams.params['gain'] is not a schema field"),
    ("'mrctl.laws.base:InverseLaw'", "mrctl.laws.base.InverseLaw is abstract (implement current)"),
    ("bad_laws", "'bad_laws' not allowed"),
])
def test_module_class_names_are_checked(fake_plugins, tmp_path, name, expect):
    with pytest.raises(ConfigError) as e:
        _load(tmp_path, f"law: {name}")
    assert expect in str(e.value)


def test_module_class_params_are_validated_with_key_paths(fake_plugins, tmp_path):
    with pytest.raises(ConfigError) as e:
        _load(tmp_path, "law: 'bad_laws:Raises'\n  after_ticks: -3\n  colour: red")
    msg = str(e.value)
    assert "inverse.after_ticks: -3 out of range" in msg and "inverse.colour: unknown key" in msg


def test_a_constructor_that_raises_is_a_config_error(fake_plugins, tmp_path):
    from mrctl.experiment import build

    with pytest.raises(ConfigError) as e:
        build(_load(tmp_path, "law: 'bad_laws:RaisesOnBuild'"))
    assert "inverse.law: 'bad_laws:RaisesOnBuild' cannot be built: RuntimeError: cannot build me" in str(e.value)


def test_a_law_needing_a_channel_the_link_lacks_is_refused(fake_plugins, tmp_path):
    from mrctl.cli import main

    with pytest.raises(ConfigError) as e:
        _load(tmp_path, "law: 'bad_laws:NeedsChannel'")
    assert "needs channel(s) v_sprung, which the sim bench (plant.bench: shaker) does not provide" in str(e.value)
    p = tmp_path / "qc.yaml"
    p.write_text((tmp_path / "exp.yaml").read_text().replace("plant: {driver_tau_s: 0.0}", "plant: {bench: quarter_car}"))
    assert load_experiment(p).inverse.law == "bad_laws:NeedsChannel"
    # at start-up, against what an opened link provides
    from mrctl.experiment import build, check_channels

    exp = build(load_experiment(p))
    with pytest.raises(ConfigError) as e:
        check_channels((exp.demand, exp.law), {"x_road": 0.0}, "serial: /dev/ttyX")
    assert "needs channel(s) v_sprung; serial: /dev/ttyX provides x_road" in str(e.value)
    assert e.value.exit_code == 2
    assert main(["check", str(p)]) == 0
