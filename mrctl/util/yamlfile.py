"""Strict YAML files, and what an error may quote of them.

* :func:`load_yaml`: a regular UTF-8 file of at most :data:`MAX_YAML_BYTES`,
  duplicate keys an error (PyYAML silently keeps the last), ``1e-3`` a number
  (YAML 1.1 makes it a string), alias bombs and recursive aliases refused
  before anything is built, every error a :class:`ConfigError` with its line.
* :func:`read_named_yaml`: a YAML file another file names (a parameter set,
  a calibration, a sweep's base), admitted by the one containment check
  (:meth:`mrctl.util.files.Fence.admit`) and read without quoting it.
* What an error may quote: key names (a key that is not a name, such as a
  line of ``/etc/shadow`` read as a YAML key, is called by its line number:
  :func:`key_repr`) and a few dozen characters of a value
  (:func:`short_repr`); of a named file's values, only what they are.
"""

from __future__ import annotations

import re
import reprlib
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, TypeVar

import yaml

from mrctl.errors import BadInput
from mrctl.util.files import Fence, FileProblem, MiB, read_regular_file

__all__ = ["ConfigError", "load_yaml", "load_yaml_lines", "read_named_yaml", "short_repr", "key_repr", "quoting",
           "MAX_YAML_BYTES", "MAX_YAML_ALIASES", "MAX_YAML_NODES", "MAX_ERRORS", "MAX_ERROR_CHARS"]

#: an error message quotes at most this much of a value (a 2 MB list must not be echoed)
_SHORT = reprlib.Repr()
_SHORT.maxlevel, _SHORT.maxstring, _SHORT.maxother = 3, 60, 60
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = _SHORT.maxset = 6
#: errors listed by one ConfigError, and characters per error line
MAX_ERRORS, MAX_ERROR_CHARS = 50, 1000


@dataclass(frozen=True)
class _Echo:
    """What errors may quote of the file being checked: its values or only
    their kind, and the line of each key (for keys that are not names)."""

    values: bool = True
    lines: Mapping[Any, int] = field(default_factory=dict)


_ECHO: ContextVar[_Echo] = ContextVar("mrctl_echo", default=_Echo())
#: what a key name looks like; any other key (a line of a file that is not a config) is called by its line
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]{0,47}\Z")


@contextmanager
def quoting(values: bool = True, lines: Mapping[Any, int] | None = None) -> Iterator[None]:
    """Within: errors quote values (``values``) or only say what they are,
    and name a key that is not a name by its line in ``lines``."""
    token = _ECHO.set(_Echo(values, dict(lines or {})))
    try:
        yield
    finally:
        _ECHO.reset(token)


def _kind_of(value: Any) -> str:
    """What a value is, without any of it: what errors say of a named file's values."""
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return f"a string ({len(value)} characters)"
    if isinstance(value, (list, tuple)):
        return f"a list ({len(value)} items)"
    if isinstance(value, dict):
        return f"a mapping ({len(value)} keys)"
    return f"a {type(value).__name__}"


def short_repr(value: Any) -> str:
    """``repr`` of a value cut to a few dozen characters, in time independent
    of the value's size: what an error message may echo of user input (in a
    named file's check, what the value is, not the value: :func:`quoting`)."""
    if not _ECHO.get().values:
        return _kind_of(value)
    try:
        return _SHORT.repr(value)
    except Exception:  # noqa: BLE001 - a repr must never turn an error into a traceback
        return f"<{type(value).__name__}>"


def key_repr(key: Any) -> str:
    """A key as an error may name it: itself if it looks like a key name,
    else by its line (``<the key at line 3>``): a line of ``/etc/shadow``
    parsed as a YAML key is not echoed."""
    if isinstance(key, str) and _NAME.match(key):
        return key
    try:
        line = _ECHO.get().lines.get(key)
    except TypeError:  # unhashable
        line = None
    return f"<the key at line {line}>" if line is not None else "<a key that is not a name>"


def _bounded(errors: list[str]) -> list[str]:
    """At most :data:`MAX_ERRORS` lines of at most :data:`MAX_ERROR_CHARS` each."""
    out = [e if len(e) <= MAX_ERROR_CHARS else e[:MAX_ERROR_CHARS - 1] + "…" for e in errors[:MAX_ERRORS]]
    if len(errors) > MAX_ERRORS:
        out.append(f"… and {len(errors) - MAX_ERRORS} more errors")
    return out


class ConfigError(BadInput):
    """One or more problems in a config; ``errors`` holds one line per problem."""

    def __init__(self, errors: list[str], source: str | None = None) -> None:
        self.errors = _bounded([str(e) for e in errors])
        self.source = source
        head = f"{source}: " if source else ""
        super().__init__(head + ("; ".join(self.errors) if len(self.errors) == 1 else f"{len(self.errors)} errors:\n  " + "\n  ".join(self.errors)))


# --------------------------------------------------------------------------
# YAML loading
#: the largest YAML file read: experiments, parameter sets, bench configs and
#: dataset descriptions are 1-3 kB; 30 times that is no real experiment, and
#: parsing it costs well under a second (a 2.6 MB one took a minute)
MAX_YAML_BYTES = 64 * 1024
#: aliases (``*name``) one file may use, and the nodes it may stand for once
#: every alias is expanded: a few anchors are handy, a billion laughs is not
MAX_YAML_ALIASES = 64
MAX_YAML_NODES = 100_000


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys, reads 1e-3 as a float, and
    refuses alias bombs (more than :data:`MAX_YAML_ALIASES` aliases, or a
    document that expands to more than :data:`MAX_YAML_NODES` nodes) before
    anything is constructed."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self._aliases = getattr(self, "_aliases", 0) + 1
            if self._aliases > MAX_YAML_ALIASES:
                mark = self.peek_event().start_mark
                raise yaml.composer.ComposerError(None, None, f"more than {MAX_YAML_ALIASES} aliases (*name): "
                                                  f"refused (an alias bomb expands without end)", mark)
        return super().compose_node(parent, index)

    def compose_document(self) -> Any:
        node = super().compose_document()
        if getattr(self, "_aliases", 0) and _expanded_size(node) > MAX_YAML_NODES:
            raise yaml.composer.ComposerError(None, None, f"expands to more than {MAX_YAML_NODES} nodes through "
                                              f"its aliases: refused", node.start_mark)
        return node


def _expanded_size(root: yaml.Node) -> int:
    """Nodes in the document with every alias expanded, without expanding
    (each node's size is computed once); iterative (no recursion limit).
    A recursive alias (``&a [1, *a]``, infinite once expanded) is refused."""
    size: dict[int, int] = {}
    entered: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        if id(node) in size:
            continue
        if not done and id(node) in entered:  # entered, not finished: one of its own ancestors
            raise yaml.composer.ComposerError(None, None, "a recursive alias (a node that contains itself): "
                                              "refused", node.start_mark)
        entered.add(id(node))
        kids: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            kids = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            kids = [n for pair in node.value for n in pair]
        if done:
            size[id(node)] = min(1 + sum(size.get(id(k), 1) for k in kids), MAX_YAML_NODES + 1)
        else:
            stack.append((node, True))
            stack.extend((k, False) for k in kids if id(k) not in size)
    return size[id(root)]


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: dict[Any, yaml.Node] = {}
    lines = loader.__dict__.setdefault("key_lines", {})
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            name = repr(key) if isinstance(key, str) and _NAME.match(key) else "(not a name)"
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {name} (first at line {seen[key].start_mark.line + 1})", key_node.start_mark
            )
        seen[key] = key_node
        try:
            lines.setdefault(key, key_node.start_mark.line + 1)
        except TypeError:  # an unhashable key: construct_mapping refuses it below
            pass
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:\d[\d_]*)?(?:\.\d*)?[eE][-+]?\d+$"),
    list("-+0123456789."),
)


def load_yaml(path: str | Path) -> Any:
    """Parse a YAML file strictly; errors become ConfigError with line numbers.
    Only a regular UTF-8 text file of at most :data:`MAX_YAML_BYTES` is read
    (``/dev/zero`` would be read without end)."""
    return load_yaml_lines(path)[0]


def load_yaml_lines(path: str | Path) -> tuple[Any, dict[Any, int]]:
    """:func:`load_yaml`, and the line of each mapping key (the first, for
    a key in several mappings): for :func:`quoting`."""
    p = Path(path)
    try:
        text = read_regular_file(p, MAX_YAML_BYTES).decode("utf-8")
    except FileProblem as exc:
        raise ConfigError([f"cannot read: {exc}" if exc.missing else str(exc)], str(p)) from None
    except UnicodeDecodeError as exc:
        raise ConfigError([f"not a text (UTF-8) file: byte {exc.start} is {exc.object[exc.start]:#04x}"],
                          str(p)) from None
    loader: _StrictLoader | None = None
    try:
        loader = _StrictLoader(text)  # refuses unprintable characters already
        return loader.get_single_data(), loader.__dict__.get("key_lines", {})
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        if not _ECHO.get().values:  # a named file: PyYAML quotes tags, aliases and anchors it met; not those
            problem = re.sub(r"'[^'\s]{4,}'", "'…'", problem)
        raise ConfigError([f"{where}invalid YAML: {problem}"], str(p)) from None
    except RecursionError:  # 200 000 '[': PyYAML's composer recurses per level
        raise ConfigError(["invalid YAML: nested too deeply (lists or mappings inside each other hundreds of "
                           "levels down); no config is"], str(p)) from None
    finally:
        if loader is not None:
            loader.dispose()


_T = TypeVar("_T")


def read_named_yaml(value: Any, base_dir: Path, fence: Fence, key: str,
                    read: Callable[[Path, Any], _T]) -> tuple[_T | None, list[str]]:
    """A YAML file a config names (a parameter set, a calibration, a sweep's
    base): admitted by ``fence`` (:meth:`Fence.admit`: under the config's
    folder, a regular file), parsed, then ``read(path, data)``, whose
    :class:`ConfigError` becomes errors prefixed ``key (path):``. Nothing of
    the file is quoted: a key that is not a name is called by its line, a
    value by its kind (:func:`quoting`)."""
    full, err = fence.admit(value, base_dir, key)
    if full is None:
        return None, [str(err)]
    try:
        with quoting(values=False):
            data, lines = load_yaml_lines(full)
        with quoting(values=False, lines=lines):
            return read(full, data), []
    except ConfigError as exc:
        return None, [f"{key} ({full}): {e}" for e in exc.errors]
