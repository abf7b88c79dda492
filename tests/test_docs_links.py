"""The installed user's docs have no dead ends: every link in the docs that
ship in the package (``mrctl docs``, copied by ``mrctl examples`` with
README.md) opens a file of that copy, and what is only in the source tree
(``bench/`` scripts, ``tests/``, ``firmware/``, ``examples/``) is said to be."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mrctl.examples import copy_examples
from mrctl.docs import docs_dir

LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")
SOURCE_ONLY = re.compile(r"(?<![\w/.-])(bench|tests|firmware|examples)/")
NOTE = "> Source tree: `python bench/...` commands and the files under `bench/`, `tests/`, `firmware/` and"


@pytest.fixture(scope="module")
def copied(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("ex") / "mrctl-examples"
    copy_examples(d)
    return d


def _links(doc: Path) -> list[str]:
    return [m.group(1) for m in LINK.finditer(doc.read_text()) if not re.match(r"[a-z][a-z0-9+.-]*:", m.group(1))]


def test_every_link_of_the_packaged_docs_opens_a_shipped_file(copied):
    docs = sorted((copied / "docs").glob("*.md"))
    assert len(docs) >= 15  # the reference docs, all of them
    dead = [f"{doc.name}: {target}" for doc in docs for target in _links(doc)
            if not (doc.parent / target).resolve().is_relative_to(copied.resolve())
            or not (doc.parent / target).exists()]
    assert not dead, dead


def test_readme_links_open_a_shipped_file_or_are_the_source_trees_it_names(copied):
    readme = copied / "README.md"
    text = readme.read_text()
    assert "are in the source repository (the source tree), not in the package" in text.split("\n\n")[0]
    for target in _links(readme):
        if (copied / target).exists():
            continue
        assert SOURCE_ONLY.match(target), f"README.md: {target} is neither shipped nor marked as the source tree's"


def test_a_doc_that_names_the_source_trees_files_says_they_are_not_installed():
    for doc in sorted(Path(docs_dir()).glob("*.md")):
        text = doc.read_text()
        if SOURCE_ONLY.search(text):
            assert NOTE in text.split("\n\n", 2)[1], f"{doc.name} names bench/, tests/, ... without the note"


def test_the_installed_docs_dir_is_the_shipped_copy():
    """``mrctl docs --path`` (what an installed user opens) holds the same files the copy does."""
    assert {p.name for p in Path(docs_dir()).glob("*.md")} >= {"cli.md", "config.md", "hardware.md", "runlog.md"}
