"""Run logs are never overwritten by surprise, and never through a symlink."""

from __future__ import annotations

from pathlib import Path

import pytest

from mrctl.cli import main

ROOT = Path(__file__).resolve().parents[1]
FIG5 = str(ROOT / "config" / "experiments" / "fig5.yaml")


def _run(out: Path, *extra: str) -> int:
    # timing is not judged: these runs are about the log's path, on a shared machine
    cfg = out.parent / "fig5.yaml"
    if not cfg.exists():
        cfg.write_text(Path(FIG5).read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    return main(["run", str(cfg), "--out", str(out), "--duration", "0.2", "--quiet",
                 "--status-socket", str(out.parent / "s.sock"), *extra])


def test_run_refuses_an_existing_log_unless_forced(tmp_path, capsys):
    out = tmp_path / "run.csv"
    assert _run(out) == 0
    first = out.read_bytes()
    side = out.with_suffix(".json").read_bytes()
    capsys.readouterr()
    assert _run(out) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--force" in err and "Traceback" not in err
    assert out.read_bytes() == first and out.with_suffix(".json").read_bytes() == side
    # only the sidecar left over from an earlier run: refused as well
    out.unlink()
    assert _run(out) == 2 and not out.exists()
    assert _run(out, "--force") == 0
    assert out.read_bytes() != first


def test_run_never_follows_a_symlink_at_the_log_path(tmp_path):
    from hil_sim.testing.daemon_faults import log_path_symlink

    r = log_path_symlink(tmp_path)
    assert r["exit"] == 2 and r["target_untouched"], r
    assert any("symlink" in m or "exists" in m for m in r["messages"]), r["messages"]
    assert r["force_exit"] == 0 and r["force_target_untouched"] and r["force_link_replaced_by_log"], r
    assert r["existing_exit"] == 2 and r["existing_untouched"], r


def test_a_symlinked_sidecar_is_not_followed_either(tmp_path):
    precious = tmp_path / "precious.json"
    precious.write_text('{"keep": true}\n')
    (tmp_path / "run.json").symlink_to(precious.name)
    out = tmp_path / "run.csv"
    assert _run(out) == 2
    assert _run(out, "--force") == 0
    assert precious.read_text() == '{"keep": true}\n'
    assert not (tmp_path / "run.json").is_symlink()


def test_simulate_out_json_would_be_its_own_sidecar_and_is_refused(tmp_path, capsys):
    out = tmp_path / "x.json"
    assert main(["simulate", FIG5, "--out", str(out), "--duration", "0.2"]) == 2
    assert "sidecar" in capsys.readouterr().err
    assert not out.exists()


def test_simulate_refuses_an_existing_log_and_does_not_follow_symlinks(tmp_path, capsys):
    precious = tmp_path / "precious.txt"
    precious.write_text("keep\n")
    link = tmp_path / "sim.csv"
    link.symlink_to(precious.name)
    assert main(["simulate", FIG5, "--out", str(link), "--duration", "0.2"]) == 2
    assert "--force" in capsys.readouterr().err
    assert precious.read_text() == "keep\n"
    assert main(["simulate", FIG5, "--out", str(link), "--duration", "0.2", "--force"]) == 0
    assert precious.read_text() == "keep\n" and not link.is_symlink()
    assert link.read_text().startswith("t,x,v,F_des,F,I,")


@pytest.mark.parametrize("cmd", ["run", "simulate"])
def test_out_directory_is_refused_before_anything_runs(tmp_path, capsys, cmd):
    d = tmp_path / "adir"
    d.mkdir()
    args = [cmd, FIG5, "--out", str(d), "--duration", "0.2"]
    if cmd == "run":
        args += ["--quiet", "--status-socket", str(tmp_path / "s.sock")]
    assert main(args) == 2
    err = capsys.readouterr()
    assert "directory" in err.err and "Traceback" not in err.err
    assert "ticks" not in err.out  # nothing ran


@pytest.mark.parametrize("cmd", ["run", "simulate", "report", "identify"])
def test_a_missing_out_directory_is_exit_2_naming_it_and_nothing_is_created(tmp_path, capsys, cmd, monkeypatch):
    """A typo in --out must not grow a tree (as root it could be anywhere):
    exit 2 naming the missing directory, before anything runs; --mkdir
    creates it; runs/ in the current directory is created as README expects."""
    monkeypatch.chdir(tmp_path)
    fig5 = tmp_path / "fig5.yaml"  # timing is not judged: the run is about its log's path, on a shared machine
    fig5.write_text(Path(FIG5).read_text() + "acceptance: {max_skipped_share: 1.0, max_gap_s: 3600.0}\n")
    fig5 = str(fig5)
    out = tmp_path / "no" / "such" / "x.csv"
    inp = {"run": [fig5], "simulate": [fig5], "report": [str(tmp_path / "r.csv")],
           "identify": [str(tmp_path / "r.csv")]}[cmd]
    args = [cmd, *inp, "--out", str(out)]
    if cmd in ("run", "simulate"):
        args += ["--duration", "0.2"]
    if cmd == "run":
        args += ["--quiet", "--socket", str(tmp_path / "s.sock")]
    assert main(args) == 2
    err = capsys.readouterr()
    assert str(tmp_path / "no" / "such") in err.err and "--mkdir" in err.err and "Traceback" not in err.err
    assert "ticks" not in err.out  # nothing ran
    assert not (tmp_path / "no").exists()
    if cmd in ("run", "simulate"):
        assert main([*args, "--mkdir"]) == 0 and out.is_file()
        assert main([cmd, fig5, "--duration", "0.2", "--out", "runs/a.csv", *args[len(inp) + 5:]]) == 0
        assert (tmp_path / "runs" / "a.csv").is_file()
        assert main([cmd, fig5, "--duration", "0.2", "--out", "runs/deeper/a.csv", *args[len(inp) + 5:]]) == 2
        assert not (tmp_path / "runs" / "deeper").exists()
