"""Hardening II (issue 23), the file side: what a hostile or careless user can
make identify, report, simulate and the readers of sidecars and replies do.

D6 outputs never destroy files; D8 one sidecar per run; D18 simulate's
sidecar survives a full disk; D9 degenerate datasets are exit 2; D11 reads
are capped and refuse devices; D16 data paths stay under the description's
directory and errors do not echo what a file holds; D10 deep nesting is a
clean error; D17 the messages that were wrong. Each test failed on the tree
before the fix.
"""

from __future__ import annotations

import errno
import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from identify_synth import broadband_record, write_csv
from mrctl.cli import main
from mrctl.errors import BadInput

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "config" / "experiments" / "fig5.yaml"

DS = """version: 1
protocol: broadband
input: voltage
columns: {time: time_s, displacement: {name: D_cm, scale: 0.01}, force: F_N, input: Y_V}
sample_rate_hz: 3000
resample_hz: 1000
motion_band_hz: 15
files: [{path: bb.csv, name: bb}]
fit: {starts: 1, max_nfev: 25}
"""


@pytest.fixture(scope="module")
def bb(tmp_path_factory):
    """A small broadband dataset that identifies (a few seconds) and the
    description of it; each test copies what it changes."""
    d = tmp_path_factory.mktemp("bb")
    rec = broadband_record(seconds=3.0)
    write_csv(d / "bb.csv", rec, {"t": "time_s", "x": "D_cm", "F": "F_N", "u": "Y_V"}, {"x": 0.01})
    (d / "ds.yaml").write_text(DS)
    return d


def _ident(ds: Path, out: Path, *extra: str) -> int:
    return main(["identify", str(ds), "--out", str(out), "--no-progress", *extra])


# -- D6: identify and report never destroy files ---------------------------------
def test_identify_refuses_a_symlink_an_existing_file_and_the_json_name(bb, capsys):
    precious = bb / "precious.txt"
    precious.write_text("keep me\n")
    link = bb / "link.yaml"
    link.symlink_to(precious)
    assert _ident(bb / "ds.yaml", link) == 2
    assert "symlink" in capsys.readouterr().err and precious.read_text() == "keep me\n" and link.is_symlink()
    existing = bb / "old.yaml"
    existing.write_text("old\n")
    assert _ident(bb / "ds.yaml", existing) == 2
    assert "--force" in capsys.readouterr().err and existing.read_text() == "old\n"
    assert _ident(bb / "ds.yaml", bb / "x.json") == 2  # the summary's own name: refused, nothing written
    assert "YAML" in capsys.readouterr().err and not (bb / "x.json").exists()


def test_identify_never_writes_over_an_input_even_with_force(bb, capsys):
    before = (bb / "ds.yaml").read_text()
    assert _ident(bb / "ds.yaml", bb / "ds.yaml", "--force") == 2
    assert "an input" in capsys.readouterr().err and (bb / "ds.yaml").read_text() == before
    data = (bb / "bb.csv").read_bytes()
    assert _ident(bb / "ds.yaml", bb / "bb.csv", "--force") == 2  # the data file
    assert (bb / "bb.csv").read_bytes() == data
    capsys.readouterr()
    assert _ident(bb / "ds.yaml", bb / "p.png", "--report", str(bb / "p.png")) == 2  # two outputs, one name
    assert "same file" in capsys.readouterr().err and not (bb / "p.png").exists()


def test_identify_with_force_replaces_a_symlink_itself_not_its_target(bb, capsys):
    target = bb / "target.txt"
    target.write_text("target\n")
    link = bb / "forced.yaml"
    link.symlink_to(target)
    assert _ident(bb / "ds.yaml", link, "--force") == 0, capsys.readouterr().err
    assert target.read_text() == "target\n" and not link.is_symlink() and "F_offset" in link.read_text()
    assert (bb / "forced.json").is_file()


def test_report_refuses_an_existing_figure_a_symlink_and_an_input(tmp_path, capsys):
    run = tmp_path / "run.csv"
    assert main(["simulate", str(FIG5), "--duration", "0.3", "--out", str(run)]) == 0
    capsys.readouterr()
    fig = tmp_path / "fig.png"
    fig.write_bytes(b"old figure")
    assert main(["report", str(run), "--out", str(fig)]) == 2
    assert "--force" in capsys.readouterr().err and fig.read_bytes() == b"old figure"
    precious = tmp_path / "precious.txt"
    precious.write_text("keep\n")
    (tmp_path / "link.svg").symlink_to(precious)
    assert main(["report", str(run), "--out", str(tmp_path / "link.svg")]) == 2
    assert precious.read_text() == "keep\n"
    side = run.with_suffix(".json").read_bytes()
    (tmp_path / "side.svg").symlink_to(run.with_suffix(".json"))  # an input reached through a symlink
    assert main(["report", str(run), "--out", str(tmp_path / "side.svg"), "--force"]) == 2
    assert "an input" in capsys.readouterr().err and run.with_suffix(".json").read_bytes() == side


def test_outputs_are_written_all_or_nothing(tmp_path):
    from mrctl.runlog.files import write_outputs

    (tmp_path / "b.json").write_text("taken")
    with pytest.raises(BadInput, match="appeared"):
        write_outputs([(tmp_path / "a.yaml", b"a"), (tmp_path / "b.json", b"b")])
    assert not (tmp_path / "a.yaml").exists() and (tmp_path / "b.json").read_text() == "taken"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.json"]  # no temp file left


# -- D8, D18: one sidecar per run, reserved ----------------------------------------------
def test_two_logs_with_one_stem_cannot_share_a_sidecar(tmp_path):
    from mrctl.runlog.files import create_log

    fh = create_log(tmp_path / "run.csv")
    try:
        with pytest.raises(BadInput, match="sidecar"):
            create_log(tmp_path / "run.tsv")  # started at the same moment: both passed the check
        assert not (tmp_path / "run.tsv").exists()
    finally:
        fh.close()


class _FullDisk:
    """A log file that takes the header's write, then fails with ENOSPC."""

    def __init__(self, path: Path) -> None:
        self.fh = open(path, "wb", buffering=0)

    def write(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    def fileno(self):
        return self.fh.fileno()

    def close(self):
        self.fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def test_simulate_on_a_full_disk_leaves_a_sidecar_that_says_so(tmp_path, monkeypatch, capsys):
    import mrctl.runlog.files as files

    real = files.create_log

    def create(path, force=False, mkdir=False):
        real(path, force, mkdir).close()
        return _FullDisk(Path(path))

    monkeypatch.setattr(files, "create_log", create)
    out = tmp_path / "run.csv"
    assert main(["simulate", str(FIG5), "--duration", "0.2", "--out", str(out)]) == 4
    assert "Traceback" not in capsys.readouterr().err
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["complete"] is False and side["exit_code"] == 4 and "No space left" in side["error"]


def test_simulate_refuses_an_empty_out_and_run_an_empty_out_or_stream(tmp_path, capsys):
    assert main(["simulate", str(FIG5), "--duration", "0.1", "--out", ""]) == 2
    assert main(["run", str(FIG5), "--duration", "0.1", "--out", ""]) == 2
    assert main(["run", str(FIG5), "--duration", "0.1", "--stream", ""]) == 2
    err = capsys.readouterr().err
    assert err.count("empty") == 3 and "Traceback" not in err


# -- D9: degenerate datasets are exit 2, nothing written ---------------------------------
@pytest.mark.parametrize("change, expect", [
    ({"sample_rate_hz: 3000": "sample_rate_hz: 1e300"}, "sample_rate_hz"),
    ({"force: F_N": "force: {name: F_N, scale: 1e308}"}, "columns.force.scale"),
    ({"fit: {": "format: {delimiter: ''}\nfit: {"}, "format.delimiter"),
    ({"bb.csv": "flat.csv"}, "columns.force) is constant"),
    ({"bb.csv": "empty.mat"}, "empty.mat: empty file"),
    ({"bb.csv": "text.mat"}, "text.mat: not a readable MATLAB .mat file"),
], ids=["rate-1e300", "scale-overflow", "delimiter-empty", "zero-variance-force", "empty-mat", "text-mat"])
def test_degenerate_datasets_are_exit_2_naming_the_key_or_file(bb, tmp_path, capsys, change, expect):
    for f in ("bb.csv",):
        (tmp_path / f).write_bytes((bb / f).read_bytes())
    lines = (bb / "bb.csv").read_text().splitlines()
    head = lines[0].split(",")
    j = head.index("F_N")
    flat = [lines[0]] + [",".join("7" if k == j else c for k, c in enumerate(ln.split(","))) for ln in lines[1:]]
    (tmp_path / "flat.csv").write_text("\n".join(flat) + "\n")
    (tmp_path / "empty.mat").write_bytes(b"")
    (tmp_path / "text.mat").write_text("time,force\n1,2\n")
    text = DS
    for a, b in change.items():
        text = text.replace(a, b)
    (tmp_path / "ds.yaml").write_text(text)
    out = tmp_path / "P.yaml"
    assert _ident(tmp_path / "ds.yaml", out) == 2
    err = capsys.readouterr().err
    assert expect in err and "internal error" not in err, err
    assert not out.exists() and not out.with_suffix(".json").exists()


# -- D11, D17: capped reads, devices and FIFOs named as such ------------------------------
def test_a_sidecar_that_is_dev_zero_is_not_read(tmp_path):
    """Old: read whole (MemoryError). Run in a child with 1 GiB of address space."""
    (tmp_path / "run.csv").write_text("t,I\n0,0\n")
    (tmp_path / "run.json").symlink_to("/dev/zero")
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30));"
            "from mrctl.runlog.read import try_sidecar; import sys; print(try_sidecar(sys.argv[1]))")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "run.csv")], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "{}", r.stderr[-500:]


def test_dataset_files_are_capped_and_fifos_named(bb, tmp_path, monkeypatch, capsys):
    import mrctl.offline.identify.records as records

    (tmp_path / "bb.csv").write_bytes((bb / "bb.csv").read_bytes())
    (tmp_path / "ds.yaml").write_text(DS)
    monkeypatch.setattr(records, "MAX_DATA_BYTES", 1000)
    assert _ident(tmp_path / "ds.yaml", tmp_path / "P.yaml") == 2
    assert "too large" in capsys.readouterr().err
    os.mkfifo(tmp_path / "fifo.csv")
    (tmp_path / "fifo.yaml").write_text(DS.replace("bb.csv", "fifo.csv"))
    assert _ident(tmp_path / "fifo.yaml", tmp_path / "P.yaml") == 2
    err = capsys.readouterr().err
    assert "a FIFO" in err and "no such file" not in err


def test_manifest_levels_must_be_finite(tmp_path, capsys):
    from mrctl.offline.identify import IdentificationError
    from mrctl.config.dataset import load_dataset
    from mrctl.offline.identify.records import read_records

    (tmp_path / "r.csv").write_text("t,x,F\n0,0,0\n0.01,1,1\n0.02,0,2\n0.03,1,0\n")
    for bad in ("nan", "inf"):
        (tmp_path / "m.csv").write_text(f"file,level\nr.csv,{bad}\n")
        (tmp_path / "ds.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, "
                                          "force: F}\nmodel: {stiffness: false}\n"
                                          "manifest: {path: m.csv, file: file, level: level}\n")
        with pytest.raises(IdentificationError, match="not a finite number"):
            read_records(load_dataset(tmp_path / "ds.yaml"))


# -- D16: data paths contained, contents never echoed -------------------------------------
def test_data_paths_stay_under_the_description_and_errors_do_not_echo_contents(bb, tmp_path, capsys):
    secret = tmp_path / "outside" / "secret.txt"
    secret.parent.mkdir()
    secret.write_text("root:$6$SECRETHASH:19000:0:99999:7:::\nline two\n")
    d = tmp_path / "ds"
    d.mkdir()
    (d / "ds.yaml").write_text(DS.replace("bb.csv", str(secret)))
    assert _ident(d / "ds.yaml", d / "P.yaml") == 2
    err = capsys.readouterr().err
    assert "outside" in err and "--allow-outside-paths" in err and "SECRETHASH" not in err
    assert _ident(d / "ds.yaml", d / "P.yaml", "--data-dir", str(secret.parent)) == 2  # now inside: read, not echoed
    err = capsys.readouterr().err
    assert "no column" in err and "SECRETHASH" not in err and "root" not in err.replace(str(tmp_path), "")
    assert _ident(d / "ds.yaml", d / "P.yaml", "--allow-outside-paths") == 2
    assert "SECRETHASH" not in capsys.readouterr().err
    # a manifest row leaving the directory
    (d / "r.csv").write_text("t,x,F\n0,0,0\n")
    (d / "m.csv").write_text(f"file,level\n{secret},0.5\n")
    (d / "man.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, "
                                "force: F}\nmodel: {stiffness: false}\n"
                                "manifest: {path: m.csv, file: file, level: level}\n")
    assert _ident(d / "man.yaml", d / "P.yaml") == 2
    err = capsys.readouterr().err
    assert "outside" in err and "SECRETHASH" not in err


# -- D10: deep nesting ---------------------------------------------------------------------
def test_deeply_nested_yaml_is_a_config_error(tmp_path, capsys):
    (tmp_path / "deep.yaml").write_text("[" * 60_000 + "\n")  # under the 64 KiB cap: the parser sees it
    assert main(["check", str(tmp_path / "deep.yaml")]) == 2
    assert main(["identify", str(tmp_path / "deep.yaml"), "--out", str(tmp_path / "P.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.count("nested too deeply") == 2 and "internal error" not in err
    (tmp_path / "deeper.yaml").write_text("[" * 200_000 + "\n")  # over the cap: refused before parsing
    assert main(["check", str(tmp_path / "deeper.yaml")]) == 2
    assert "too large" in capsys.readouterr().err


def test_deeply_nested_sidecar_is_no_sidecar(tmp_path):
    from mrctl.runlog.read import try_sidecar

    (tmp_path / "run.json").write_text("[" * 200_000)
    assert try_sidecar(tmp_path / "run.csv") == {}


def _serve_once(path: Path, reply: bytes) -> threading.Thread:
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(1)

    def run() -> None:
        c, _ = srv.accept()
        try:
            c.settimeout(5)
            c.recv(65536)  # the client's request (or its shutdown): closing over unread bytes would reset it
            c.sendall(reply)
        except OSError:
            pass
        c.close()
        srv.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_deeply_nested_status_and_tap_replies_are_not_replies(tmp_path):
    from mrctl.daemon.status import StatusError, query_status
    from mrctl.daemon.tap import tap

    _serve_once(tmp_path / "s.sock", b"[" * 200_000)
    with pytest.raises(StatusError, match="not a status reply"):
        query_status(str(tmp_path / "s.sock"))
    _serve_once(tmp_path / "t.sock", b"[" * 60_000 + b"\n")
    with pytest.raises(StatusError, match="not a tap reply"):
        tap(str(tmp_path / "t.sock"), open(os.devnull, "wb"), 1)


def test_a_deeply_nested_request_does_not_kill_the_status_server(tmp_path):
    from mrctl.daemon.status import StatusServer

    srv = StatusServer(str(tmp_path / "s.sock"), lambda: {"state": "RUN"}, lambda conn, req: False)
    srv.start()
    try:
        for _ in range(2):  # the second still answered: the server thread lived through the first
            c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            c.settimeout(5)
            c.connect(str(tmp_path / "s.sock"))
            c.sendall(b"[" * 4000 + b"\n")
            data = b""
            while True:
                b = c.recv(65536)
                if not b:
                    break
                data += b
            c.close()
            assert json.loads(data)["state"] == "RUN"
    finally:
        srv.close()


# -- D17: messages -----------------------------------------------------------------------
def test_a_regular_file_where_the_status_directory_should_be_is_called_so(tmp_path, monkeypatch):
    from mrctl.util.files import check_private_dir

    f = tmp_path / "mrctl-dir"
    f.write_text("")
    with pytest.raises(OSError, match="is a regular file, not a directory"):
        check_private_dir(f)


def test_status_into_a_closed_pipe_is_quiet_and_exit_0(tmp_path):
    sock = tmp_path / "s.sock"
    _serve_once(sock, json.dumps({"state": "RUN", "pad": "x" * 300_000}).encode())
    p = subprocess.Popen([sys.executable, "-m", "mrctl", "status", "--socket", str(sock), "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # `| true`: the reader is gone before the first byte
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 0 and "Broken pipe" not in err and "Traceback" not in err, err


def test_the_exporter_prints_an_ipv6_url_with_brackets(monkeypatch, capsys):
    import prometheus_client  # noqa: F401 - a test dependency: missing, the test fails
    import mrctl.daemon.exporter as exporter

    class _Server:
        server_address = ("::1", 19878, 0, 0)

        def shutdown(self):
            pass

    class _Thread:
        def is_alive(self):
            return False

    monkeypatch.setattr(exporter, "start", lambda listen, path, inst: (_Server(), _Thread()))
    assert main(["exporter", "--listen", "[::1]:19878", "--socket", "/nonexistent.sock"]) == 0
    assert "http://[::1]:19878/metrics" in capsys.readouterr().out


def test_identify_names_dev_zero_as_a_device(tmp_path, capsys):
    (tmp_path / "ds.yaml").write_text(DS.replace("bb.csv", "/dev/zero"))
    assert _ident(tmp_path / "ds.yaml", tmp_path / "P.yaml", "--allow-outside-paths") == 2
    err = capsys.readouterr().err
    assert "a character device" in err and "no such file" not in err
    np.testing.assert_equal(list(tmp_path.iterdir()), [tmp_path / "ds.yaml"])


def test_a_demand_file_that_is_not_a_csv_is_not_echoed(tmp_path, capsys):
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$SECRETHASH:19000:0:99999:7:::\n")
    text = FIG5.read_text().replace("demand: {type: viscous, c_des: 500.0}", f"demand: {{type: file, path: {secret}}}")
    (tmp_path / "x.yaml").write_text(text)
    assert main(["check", str(tmp_path / "x.yaml")]) == 2
    err = capsys.readouterr().err
    assert "missing required column(s) t, F_des" in err and "SECRETHASH" not in err


def test_outputs_without_hard_links_are_still_created_exclusively(tmp_path, monkeypatch):
    """A filesystem without hard links (vfat): the name is created with O_EXCL instead."""
    from mrctl.runlog.files import write_outputs

    def no_link(*a, **k):
        raise OSError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", no_link)
    write_outputs([(tmp_path / "a.yaml", b"a")])
    assert (tmp_path / "a.yaml").read_bytes() == b"a"
    with pytest.raises(BadInput, match="appeared"):
        write_outputs([(tmp_path / "a.yaml", b"b")])
    assert (tmp_path / "a.yaml").read_bytes() == b"a" and sorted(p.name for p in tmp_path.iterdir()) == ["a.yaml"]


def test_demand_and_excitation_files_stay_under_the_config_unless_allowed(tmp_path, capsys):
    series = tmp_path / "elsewhere" / "f.csv"
    series.parent.mkdir()
    series.write_text("t,F_des\n0,0\n1,10\n")
    cfg_dir = tmp_path / "cfg"
    cfg_dir.mkdir()
    text = FIG5.read_text().replace("demand: {type: viscous, c_des: 500.0}", f"demand: {{type: file, path: {series}}}")
    (cfg_dir / "x.yaml").write_text(text)
    assert main(["check", str(cfg_dir / "x.yaml")]) == 2
    err = capsys.readouterr().err
    assert "demand.path" in err and "outside" in err and "--allow-outside-paths" in err
    assert main(["check", str(cfg_dir / "x.yaml"), "--allow-outside-paths"]) == 0
    (cfg_dir / "y.yaml").write_text(FIG5.read_text().replace(
        "excitation: {type: sine, amplitude_m: 0.010, frequency_hz: 1.0}", "excitation: {type: file, path: ../e.csv}"))
    assert main(["simulate", str(cfg_dir / "y.yaml"), "--duration", "0.1"]) == 2
    assert "excitation.path" in capsys.readouterr().err


def test_a_file_a_manifest_lists_is_an_input_never_an_output(tmp_path, capsys):
    (tmp_path / "r.csv").write_text("t,x,F\n0,0,0\n0.01,1,1\n0.02,0,2\n0.03,1,0\n")
    (tmp_path / "m.csv").write_text("file,level\nr.csv,0.5\n")
    (tmp_path / "ds.yaml").write_text("version: 1\nprotocol: constant_input\ncolumns: {time: t, displacement: x, "
                                      "force: F}\nmodel: {stiffness: false}\n"
                                      "manifest: {path: m.csv, file: file, level: level}\n")
    before = (tmp_path / "r.csv").read_bytes()
    assert main(["identify", "--dataset", str(tmp_path / "ds.yaml"), "--out", str(tmp_path / "r.csv"),
                 "--force"]) == 2
    assert "Traceback" not in capsys.readouterr().err
    assert (tmp_path / "r.csv").read_bytes() == before
