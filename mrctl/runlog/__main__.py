"""``python -m mrctl.runlog``: regenerate docs/runlog.md's generated block (installed: print it)."""

from pathlib import Path

from mrctl.runlog.format import columns_markdown
from mrctl.util.gendoc import regenerate

_doc = Path(__file__).resolve().parents[2] / "docs" / "runlog.md"
_b, _e = "<!-- BEGIN GENERATED: mrctl.runlog.format.columns_markdown -->", "<!-- END GENERATED -->"
regenerate(_doc, _b, _e, columns_markdown())
