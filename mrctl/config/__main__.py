"""``python -m mrctl.config``: regenerate docs/config.md's generated block."""

import sys
from pathlib import Path

from mrctl.config import schema_markdown
from mrctl.util.gendoc import replace_block

_doc = Path(__file__).resolve().parents[2] / "docs" / "config.md"
_b, _e = "<!-- BEGIN GENERATED: mrctl.config.schema_markdown -->", "<!-- END GENERATED -->"
replace_block(_doc, _b, _e, schema_markdown())
print(f"updated {_doc}", file=sys.stderr)
