"""``python -m mrctl.config``: regenerate docs/config.md's generated block."""

import sys
from pathlib import Path

from mrctl.config import schema_markdown

_doc = Path(__file__).resolve().parents[2] / "docs" / "config.md"
_b, _e = "<!-- BEGIN GENERATED: mrctl.config.schema_markdown -->", "<!-- END GENERATED -->"
_src = _doc.read_text()
_doc.write_text(_src[: _src.index(_b) + len(_b)] + "\n" + schema_markdown() + "\n" + _src[_src.index(_e):])
print(f"updated {_doc}", file=sys.stderr)
