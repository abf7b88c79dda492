"""``mrctl docs [TOPIC]``: the reference docs that travel with the package.

The docs (``docs/*.md`` of the source tree) are package data
(``mrctl/data/docs``, a symlink to ``docs/`` in the source tree, copied into
the wheel), so an installed mrctl can show them without its source tree:
:func:`topics` lists them, :func:`read_topic` returns one, :func:`docs_dir`
says where they are installed (for a browser or ``less``).

What is generated from code (the config keys, the run-log columns, the
laws, the dataset keys) stays generated: :func:`generated` returns it from
the installed code, the same text the docs' generated blocks hold.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Callable

from mrctl.errors import BadInput

__all__ = ["docs_dir", "topics", "topic_path", "read_topic", "generated", "GENERATED"]


def docs_dir() -> Path:
    """Where the docs are: the installed package's copy, or the source tree's
    ``docs/`` (through the ``mrctl/data/docs`` symlink)."""
    return Path(str(importlib.resources.files("mrctl") / "data" / "docs"))


def _title(path: Path) -> str:
    with path.open(encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("# "):
                return line[2:].strip()
    return ""


def topics() -> list[tuple[str, str]]:
    """Every doc as (topic, title): the topic is the file name without ``.md``."""
    d = docs_dir()
    return [(p.stem, _title(p)) for p in sorted(d.glob("*.md")) if p.is_file()]


def topic_path(name: str) -> Path:
    """The file of topic ``name`` (``config``, ``config.md``, or an unambiguous
    prefix such as ``reli``); ``BadInput`` naming the topics otherwise."""
    names = [t for t, _ in topics()]
    if not names:
        raise BadInput(f"no docs found in {docs_dir()}: is mrctl installed completely?")
    key = name[:-3] if name.lower().endswith(".md") else name
    key = key.lower()
    hits = [n for n in names if n.lower() == key] or [n for n in names if n.lower().startswith(key)]
    if len(hits) != 1:
        why = "ambiguous" if hits else "no such topic"
        raise BadInput(f"docs {name!r}: {why}; topics: {', '.join(hits or names)}")
    return docs_dir() / f"{hits[0]}.md"


def read_topic(name: str) -> str:
    """The text of one doc (see :func:`topic_path`)."""
    return topic_path(name).read_text(encoding="utf-8")


def _config() -> str:
    from mrctl.config import schema_markdown

    return schema_markdown()


def _runlog() -> str:
    from mrctl.runlog.format import columns_markdown

    return columns_markdown()


def _laws() -> str:
    from mrctl.config.laws import laws_markdown

    return laws_markdown()


def _dataset() -> str:
    from mrctl.config.dataset import dataset_markdown

    return dataset_markdown()


#: topic -> the code that generates its reference part
GENERATED: dict[str, Callable[[], str]] = {"config": _config, "runlog": _runlog, "laws": _laws,
                                           "identification": _dataset}


def generated(name: str) -> str:
    """The reference that topic ``name``'s generated block holds, made by the
    installed code (plugins' laws included); ``BadInput`` for a topic with none."""
    key = name.lower()[:-3] if name.lower().endswith(".md") else name.lower()
    topic = key if key in GENERATED else topic_path(name).stem
    if topic not in GENERATED:
        raise BadInput(f"docs {name}: nothing generated from code; --generate works for: {', '.join(GENERATED)}")
    return GENERATED[topic]()
