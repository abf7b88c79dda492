"""One CLI vocabulary (docs/cli.md), checked on every subparser, including
subcommands added later: this walks the parser, it lists no commands."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from mrctl.cli import EXIT_CODES, build_parser, main

ROOT = Path(__file__).resolve().parents[1]
CLI_MD = (ROOT / "docs" / "cli.md").read_text()


def _subparsers(ap: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return {name: sp for a in ap._actions if isinstance(a, argparse._SubParsersAction)
            for name, sp in a.choices.items()}


SUBS = _subparsers(build_parser())


def _options(sp: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """Every option string -> its action (help and version left out)."""
    return {s: a for a in sp._actions if not isinstance(a, (argparse._HelpAction, argparse._VersionAction))
            for s in a.option_strings}


def test_there_are_subcommands_to_walk():
    assert {"run", "status", "ls", "simulate", "report", "identify", "docs", "tap", "exporter"} <= set(SUBS)


@pytest.mark.parametrize("name", sorted(SUBS))
def test_every_help_ends_with_the_exit_codes(name, capsys):
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    from mrctl.runlog.format import exit_codes_text

    assert EXIT_CODES.rstrip() in out  # the general table, then this command's codes
    assert out.rstrip().endswith(exit_codes_text(name).rstrip()), out[-400:]
    for code in range(6):
        assert re.search(rf"^\s+{code}\s+\S", out, flags=re.M), (name, code)


@pytest.mark.parametrize("name", sorted(SUBS))
def test_every_argument_has_help_and_argparse_forms(name):
    sp = SUBS[name]
    for a in sp._actions:
        if isinstance(a, (argparse._HelpAction, argparse._VersionAction)):
            continue
        what = a.option_strings or [a.dest]
        assert a.help, f"mrctl {name} {what}: no help"
        if a.help == argparse.SUPPRESS:
            continue  # a hidden alias (--status-socket) of an option that has help
        longs = [s for s in a.option_strings if s.startswith("--")]
        shorts = [s for s in a.option_strings if not s.startswith("--")]
        if a.option_strings:
            assert longs, f"mrctl {name} {what}: a short option needs a long form"
        for s in longs:
            assert re.fullmatch(r"--[a-z0-9]+(-[a-z0-9]+)*", s), f"mrctl {name} {s}: not --kebab-case"
        for s in shorts:
            assert re.fullmatch(r"-[a-zA-Z]", s), f"mrctl {name} {s}: a short option is one letter"


@pytest.mark.parametrize("name", sorted(SUBS))
def test_shared_concepts_have_one_spelling(name):
    """--socket with --instance (and the old --status-socket as a hidden
    alias of --socket); --quiet always with -q; --out always with -o,
    strftime and --mkdir; no second spelling of these anywhere."""
    opts = _options(SUBS[name])
    if "--socket" in opts or "--instance" in opts:
        assert "--socket" in opts and "--instance" in opts, name
        assert opts["--status-socket"].dest == opts["--socket"].dest, name
        assert opts["--status-socket"].help == argparse.SUPPRESS, name
    if "--quiet" in opts:
        assert opts["--quiet"].option_strings == ["-q", "--quiet"], name
    if "--out" in opts:
        assert opts["--out"].option_strings == ["-o", "--out"], name
        assert "strftime" in opts["--out"].help, name
        assert "--mkdir" in opts, name
        assert not opts["--out"].required, f"mrctl {name} --out: a default beside the input, not required"
    for other in ("--status", "--sock", "--name", "--silent", "--output", "--progress", "--no-quiet", "--create"):
        assert other not in opts, f"mrctl {name} {other}: the vocabulary's word is another (docs/cli.md)"


def test_every_shared_option_is_in_docs_cli_md():
    """An option that several subcommands have is part of the vocabulary:
    docs/cli.md names it (and every subcommand)."""
    seen: dict[str, set[str]] = {}
    for name, sp in SUBS.items():
        assert f"`mrctl {name}" in CLI_MD, f"docs/cli.md does not mention mrctl {name}"
        for opt, a in _options(sp).items():
            if opt.startswith("--") and a.help != argparse.SUPPRESS:
                seen.setdefault(opt, set()).add(name)
    for opt, names in seen.items():
        if len(names) > 1:
            assert f"`{opt}" in CLI_MD, f"{opt} ({', '.join(sorted(names))}) is not in docs/cli.md"


def test_out_expands_strftime_everywhere(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fig5 = str(ROOT / "config" / "experiments" / "fig5.yaml")
    assert main(["simulate", fig5, "--duration", "0.2", "--out", "sim-%Y.csv"]) == 0
    made = [p.name for p in tmp_path.glob("sim-*.csv")]
    assert len(made) == 1 and "%" not in made[0] and re.fullmatch(r"sim-\d{4}\.csv", made[0]), made


def test_a_missing_optional_dependency_is_exit_2_naming_the_extra(monkeypatch, capsys):
    """Whichever command meets it: the extra to install, exit 2."""
    import builtins

    real = builtins.__import__

    def no_prometheus(name, *a, **k):
        if name.startswith("prometheus_client"):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_prometheus)
    assert main(["exporter", "--socket", "/nonexistent/s.sock", "--listen", "127.0.0.1:0"]) == 2
    assert "mrctl[metrics]" in capsys.readouterr().err


def test_default_outputs_go_beside_the_input(tmp_path, capsys, monkeypatch):
    """report run.csv -> run.png; identify --dataset d.yaml -> d.params.yaml."""
    import matplotlib  # noqa: F401 - a test dependency: missing, the test fails
    run = tmp_path / "data" / "run.csv"
    run.parent.mkdir()
    fig5 = str(ROOT / "config" / "experiments" / "fig5.yaml")
    assert main(["simulate", fig5, "--duration", "0.5", "--out", str(run), "-q"]) == 0
    capsys.readouterr()
    assert main(["report", str(run), "-q"]) == 0
    assert (tmp_path / "data" / "run.png").read_bytes()[:4] == b"\x89PNG"
    assert capsys.readouterr().out == ""  # -q: no 'wrote' line

    import mrctl.offline.identify as ident
    import mrctl.offline.identify_command as command

    seen = {}

    def fake(out, report, inputs, **kw):  # the outputs are checked before the fit: stop there
        seen["out"] = out
        raise ident.IdentificationError("stop here")

    monkeypatch.setattr(command, "check_outputs", fake)
    (tmp_path / "data" / "a.csv").write_text("t,x,F\n0,0,0\n0.001,0,0\n")
    d = tmp_path / "data" / "d.yaml"
    d.write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, force: F}\n"
                 "files: [{path: a.csv, level: 0.1}]\n")
    assert main(["identify", "--dataset", str(d)]) == 2
    assert seen["out"] == str(tmp_path / "data" / "d.params.yaml")
    assert main(["identify", str(d), "-o", str(tmp_path / "p-%Y.yaml")]) == 2
    assert "%" not in seen["out"] and re.fullmatch(r"p-\d{4}\.yaml", Path(seen["out"]).name)
