"""Replace a generated block of a doc: the one way the package's
``python -m`` doc generators and the bench scripts write their tables.

    from mrctl.util.gendoc import replace_block
    replace_block(ROOT / "docs" / "x.md", BEGIN, END, text)

The block between the two markers becomes ``begin``, a newline, ``text``, a
newline, ``end`` (what tests/test_docs.py reads back); the rest of the file
is kept byte for byte. A doc
without both markers, in order, is an error (exit with a message), never
a doc cut short. ``text`` is written as it is: no regex escapes.
"""

from __future__ import annotations

from pathlib import Path


def replace_block(doc: Path, begin: str, end: str, text: str) -> None:
    """Write ``text`` between ``begin`` and ``end`` in ``doc`` (the rest kept)."""
    src = doc.read_text()
    i = src.find(begin)
    j = src.find(end, i + len(begin)) if i >= 0 else -1
    if i < 0 or j < 0:
        raise SystemExit(f"{doc}: no block between {begin!r} and {end!r}")
    doc.write_text(src[: i + len(begin)] + "\n" + text + "\n" + src[j:])


def regenerate(doc: Path, begin: str, end: str, text: str) -> None:
    """``python -m`` generators: in a source tree, rewrite the block of ``doc``
    (see :func:`replace_block`); installed, where the package's docs are a
    copy (``mrctl docs --path``), print ``text`` on stdout instead of a
    traceback, so the reference of the installed code is still one command away."""
    import sys

    root = doc.resolve().parents[1]
    if doc.is_file() and (root / "pyproject.toml").is_file():
        replace_block(doc, begin, end, text)
        print(f"updated {doc}", file=sys.stderr)
        return
    print(text)
    print(f"{doc.name}: not in a source tree; printed the generated reference (also: mrctl docs "
          f"{doc.stem} --generate)", file=sys.stderr)
