"""What ``pip install mrctl`` gives a user outside the source tree: the example
experiments and unit files (``mrctl examples``), the reference docs
(``mrctl docs``, and copied beside the examples so README's links work), a
LICENSE, a unit whose ``Documentation=`` exists once the install steps are followed."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ["config/experiments/fig5.yaml", "config/experiments/fig5_paper.yaml", "config/experiments/identify.yaml",
            "config/experiments/hil_serial.yaml", "config/experiments/hil_modbus_tcp.yaml",
            "config/experiments/hil_modbus_rtu.yaml", "config/hil_fig5_bench.yaml", "config/hil_bench.yaml",
            "systemd/mrctl.service", "systemd/mrctl@.service", "systemd/mrctl-tmpfiles.conf",
            "docs/config.md", "docs/runlog.md", "docs/install.md", "docs/laws.md", "docs/protocol.md"]
DOCS = sorted(p.name for p in (ROOT / "docs").glob("*.md"))


def _links(readme: str) -> list[str]:
    return sorted(set(re.findall(r"\]\((docs/[^)#]+)", readme)))


def test_examples_command_copies_experiments_units_and_readme(tmp_path, capsys):
    dest = tmp_path / "ex"
    assert main(["examples", str(dest)]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "config/, docs/, systemd/" in out  # one line, not one per file
    for rel in EXAMPLES:
        assert (dest / rel).read_bytes() == (ROOT / rel).read_bytes(), rel
    readme = (dest / "README.md").read_text()
    assert "# mrctl" in readme and "mrctl docs" in readme.split("# mrctl")[0]
    links = _links(readme)
    assert len(links) >= 10
    for link in links:  # every docs/ link of the copied README opens
        assert (dest / link).is_file(), link
    # never over a user's edits without --force
    (dest / "config/experiments/fig5.yaml").write_text("# mine\n")
    assert main(["examples", str(dest)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (dest / "config/experiments/fig5.yaml").read_text() == "# mine\n"
    assert main(["examples", str(dest), "--force"]) == 0
    assert (dest / "config/experiments/fig5.yaml").read_bytes() == (ROOT / "config/experiments/fig5.yaml").read_bytes()


def test_docs_command_lists_prints_locates_and_generates(capsys):
    assert main(["docs"]) == 0
    out = capsys.readouterr().out
    for doc in DOCS:
        assert doc[:-3] in out, doc
    assert main(["docs", "reli"]) == 0  # a prefix will do
    assert capsys.readouterr().out == (ROOT / "docs" / "reliability.md").read_text()
    assert main(["docs", "--path"]) == 0
    assert Path(capsys.readouterr().out.strip()).resolve() == (ROOT / "docs").resolve()
    assert main(["docs", "config", "--path"]) == 0
    assert Path(capsys.readouterr().out.strip()).resolve() == (ROOT / "docs" / "config.md").resolve()
    from mrctl.config import schema_markdown

    assert main(["docs", "config", "--generate"]) == 0
    assert capsys.readouterr().out == schema_markdown() + "\n"
    assert main(["docs", "nosuch"]) == 2
    assert "topics: " in capsys.readouterr().err
    assert main(["docs", "r"]) == 2  # registers, reliability, robust-tracking, runlog
    assert "ambiguous" in capsys.readouterr().err
    assert main(["docs", "protocol", "--generate"]) == 2


def test_every_doc_ships_in_the_wheel_by_pyproject():
    """package-data names every doc file (the symlink mrctl/data/docs is what it globs)."""
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["mrctl"]
    assert (ROOT / "mrctl" / "data" / "docs").resolve() == (ROOT / "docs").resolve()
    for f in (ROOT / "docs").rglob("*"):
        if f.is_file():
            rel = "data/docs/" + str(f.relative_to(ROOT / "docs"))
            assert any(Path(rel).match(pat) for pat in data), f"{rel} is not shipped"


def test_license_file_matches_pyproject():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert meta["license"] == {"text": "MIT"}
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "WITHOUT WARRANTY OF ANY KIND" in text


@pytest.mark.parametrize("unit", ["mrctl.service", "mrctl@.service"])
def test_unit_documentation_is_a_file_the_install_steps_put_there(unit):
    text = (ROOT / "systemd" / unit).read_text()
    docs = re.findall(r"^Documentation=(.*)$", text, flags=re.M)
    assert docs
    install = (ROOT / "docs" / "install.md").read_text()
    m = re.search(r"mrctl examples (/\S+)", install)
    assert m, "docs/install.md must copy the examples (and README) to a fixed place"
    shared = m.group(1).rstrip("/")
    for uri in docs[0].split():
        assert uri.startswith("file:"), uri
        path = uri[len("file:"):]
        assert path.startswith(shared + "/"), (path, shared)
        rel = path[len(shared) + 1:]
        assert rel == "README.md" or rel in EXAMPLES or (rel.startswith("docs/") and rel[5:] in DOCS), rel


@pytest.mark.slow
def test_installed_wheel_runs_the_example_outside_the_source_tree(tmp_path):
    """Build the wheel, install it into an empty directory, and from a directory
    with nothing in it: copy the examples out, run one, report the license."""
    wheels = tmp_path / "wheels"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                        "-w", str(wheels), str(ROOT)], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = wheels.glob("mrctl-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    assert any(n.endswith("/LICENSE") for n in names), [n for n in names if "dist-info" in n]
    for rel in EXAMPLES:
        assert f"mrctl/data/{rel}" in names, rel
    for doc in DOCS:
        assert f"mrctl/data/docs/{doc}" in names, doc
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(whl)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(site)

    def mrctl(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "mrctl", *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=120)

    where = subprocess.run([sys.executable, "-c", "import mrctl; print(mrctl.__file__)"], cwd=work, env=env,
                           capture_output=True, text=True)
    assert where.stdout.startswith(str(site)), where.stdout + where.stderr  # the installed copy, not the tree
    r = mrctl("examples", ".")
    assert r.returncode == 0, r.stderr
    fig5 = work / "config" / "experiments" / "fig5.yaml"  # timing not judged: a shared machine
    fig5.write_text(fig5.read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    r = mrctl("run", "config/experiments/fig5.yaml", "--duration", "0.3", "--out", "runs/fig5.csv", "--quiet",
              "--status-socket", str(tmp_path / "s.sock"))
    assert r.returncode == 0, r.stderr
    assert (work / "runs" / "fig5.csv").exists() and (work / "systemd" / "mrctl.service").exists()
    # the docs travel with the package: listed, printed, located, generated from the installed code
    r = mrctl("docs")
    assert r.returncode == 0 and all(d[:-3] in r.stdout for d in DOCS), r.stdout + r.stderr
    r = mrctl("docs", "--path")
    assert r.returncode == 0 and r.stdout.strip().startswith(str(site)), r.stdout
    assert (Path(r.stdout.strip()) / "config.md").read_text() == (ROOT / "docs" / "config.md").read_text()
    r = mrctl("docs", "runlog")
    assert r.returncode == 0 and r.stdout == (ROOT / "docs" / "runlog.md").read_text()
    r = mrctl("docs", "config", "--generate")
    assert r.returncode == 0 and "| `safety.I_max` |" in r.stdout
    r = subprocess.run([sys.executable, "-m", "mrctl.config"], cwd=work, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "| `safety.I_max` |" in r.stdout and "Traceback" not in r.stderr, r.stderr
    readme = (work / "README.md").read_text()
    for link in _links(readme):
        assert (work / link).is_file(), link
    # every subcommand's --help, installed, ends with the exit codes
    from mrctl.cli import build_parser
    from mrctl.runlog.format import exit_codes_text

    for name in _subcommands(build_parser()):
        r = mrctl(name, "--help")
        assert r.returncode == 0 and "5  run completed but degraded" in r.stdout, name
        assert r.stdout.rstrip().endswith(exit_codes_text(name).rstrip()), name  # then this command's codes
    r = mrctl("ls", "--json")  # its daemons (none running here)
    assert r.returncode == 0 and r.stdout.strip().startswith("["), r.stdout + r.stderr
    # a run log replays on the installed package: its motion, another law
    r = mrctl("simulate", "--replay", "runs/fig5.csv", "--law", "paper", "--out", "runs/replay.csv")
    assert r.returncode == 0, r.stderr
    assert (work / "runs" / "replay.csv").is_file()


def _subcommands(ap) -> list[str]:
    import argparse

    return [n for a in ap._actions if isinstance(a, argparse._SubParsersAction) for n in a.choices]
