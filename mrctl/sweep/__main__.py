"""``python -m mrctl.sweep``: regenerate docs/sweeps.md's reference block from the sweep schema."""

import sys
from pathlib import Path

from mrctl.sweep.spec import sweep_markdown
from mrctl.util.gendoc import replace_block

_doc = Path(__file__).resolve().parents[2] / "docs" / "sweeps.md"
replace_block(_doc, "<!-- BEGIN GENERATED: mrctl.sweep.sweep_markdown -->", "<!-- END GENERATED -->", sweep_markdown())
print(f"updated {_doc}", file=sys.stderr)
