"""Docs that are generated must match what generates them."""

from pathlib import Path

from mrctl.config import schema_markdown

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_config_reference_is_current():
    text = (DOCS / "config.md").read_text()
    block = text.split("<!-- BEGIN GENERATED: mrctl.config.schema_markdown -->\n", 1)[1].split("\n<!-- END GENERATED -->")[0]
    assert block == schema_markdown(), "docs/config.md is stale: run python -m mrctl.config"


def test_every_schema_key_is_documented():
    md = schema_markdown()
    for line in md.splitlines():
        if line.startswith("| `"):
            assert line.rstrip().split("|")[-2].strip(), f"undocumented key: {line}"


def test_a_pipe_in_a_doc_does_not_split_its_table_cell():
    """A plugin's doc may say |F_des| (mrctl check --laws prints it in a table)."""
    import re

    from mrctl.util.schema import Num, schema_markdown as table

    md = table({"ff": Num(default=0.01, doc="current per newton of |F_des| (A/N)")})
    row = [ln for ln in md.splitlines() if ln.startswith("| `ff`")][0]
    assert len(re.split(r"(?<!\\)\|", row)) == 6, row  # 4 cells


def test_docs_cli_lists_the_exit_codes_every_help_ends_with():
    from mrctl.cli import EXIT_CODES

    cli = (DOCS / "cli.md").read_text()
    for line in EXIT_CODES.splitlines()[1:]:
        code = line.split()[0]
        assert f"| {code} |" in cli, code


def test_sweep_reference_is_current():
    from mrctl.sweep.spec import sweep_markdown

    text = (DOCS / "sweeps.md").read_text()
    block = text.split("<!-- BEGIN GENERATED: mrctl.sweep.sweep_markdown -->\n", 1)[1].split("\n<!-- END GENERATED -->")[0]
    assert block == sweep_markdown(), "docs/sweeps.md is stale: run python -m mrctl.sweep"


def test_the_exit_code_table_of_every_command_is_current():
    from mrctl.runlog.format import command_exits_markdown

    text = (DOCS / "cli.md").read_text()
    block = text.split("<!-- BEGIN GENERATED: mrctl.runlog.format.command_exits_markdown -->\n", 1)[1]
    assert block.split("\n<!-- END GENERATED -->")[0] == command_exits_markdown()
