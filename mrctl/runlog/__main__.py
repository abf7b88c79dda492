"""``python -m mrctl.runlog``: regenerate docs/runlog.md's generated block."""

import sys
from pathlib import Path

from mrctl.runlog.format import columns_markdown

_doc = Path(__file__).resolve().parents[2] / "docs" / "runlog.md"
_b, _e = "<!-- BEGIN GENERATED: mrctl.runlog.format.columns_markdown -->", "<!-- END GENERATED -->"
_src = _doc.read_text()
_doc.write_text(_src[: _src.index(_b) + len(_b)] + "\n" + columns_markdown() + "\n" + _src[_src.index(_e):])
print(f"updated {_doc}", file=sys.stderr)
