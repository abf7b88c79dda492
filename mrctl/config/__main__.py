"""``python -m mrctl.config``: regenerate docs/config.md's generated block (installed: print it)."""

from pathlib import Path

from mrctl.config import schema_markdown
from mrctl.util.gendoc import regenerate

_doc = Path(__file__).resolve().parents[2] / "docs" / "config.md"
_b, _e = "<!-- BEGIN GENERATED: mrctl.config.schema_markdown -->", "<!-- END GENERATED -->"
regenerate(_doc, _b, _e, schema_markdown())
