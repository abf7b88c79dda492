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


def test_sweep_reference_is_current():
    from mrctl.sweep.spec import sweep_markdown

    text = (DOCS / "sweeps.md").read_text()
    block = text.split("<!-- BEGIN GENERATED: mrctl.sweep.sweep_markdown -->\n", 1)[1].split("\n<!-- END GENERATED -->")[0]
    assert block == sweep_markdown(), "docs/sweeps.md is stale: run python -m mrctl.sweep"
