"""The schema engine: strict YAML, declarative fields, errors with key paths.

Why our own small engine instead of a library: what we need is narrow and
exact: unknown keys rejected, numbers range-checked, unions chosen by a
``type`` or ``law`` key, defaults filled, *all* errors collected with their
key paths so ``mrctl check`` lists every one at once, and the schema itself
generating its reference tables (``docs/config.md``). Experiment, bench,
dataset and law-parameter schemas are all written in these terms
(:mod:`mrctl.config`, ``hil_sim.config``, law classes' ``params``).

Strict YAML loading, and what an error may quote of a file, are
:mod:`mrctl.util.yamlfile`'s (re-exported here: one import for a schema).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

from mrctl.util.files import Fence
from mrctl.util.yamlfile import (
    MAX_YAML_ALIASES,
    MAX_YAML_BYTES,
    MAX_YAML_NODES,
    ConfigError,
    key_repr,
    load_yaml,
    load_yaml_lines,
    quoting,
    read_named_yaml,
    short_repr,
)

_REQUIRED = object()

__all__ = [
    "ConfigError", "load_yaml", "Num", "Str", "Bool", "Section", "Union", "Custom", "Node", "REQUIRED",
    "FilePath", "bind_paths", "auto_or", "check_num", "validate_fields", "validate_union", "file_check", "range_check",
    "optional_bool",
    "schema_markdown", "short_repr", "key_repr", "quoting", "load_yaml_lines", "read_named_yaml",
    "MAX_YAML_BYTES", "MAX_YAML_ALIASES", "MAX_YAML_NODES",
]

# --------------------------------------------------------------------------
# Schema
@dataclass(frozen=True)
class Num:
    """A number field (int or float in YAML; bools rejected)."""

    default: Any = _REQUIRED
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False
    integer: bool = False
    optional: bool = False  # None allowed
    doc: str = ""


@dataclass(frozen=True)
class Str:
    default: Any = _REQUIRED
    choices: tuple[str, ...] | None = None
    optional: bool = False
    doc: str = ""


@dataclass(frozen=True)
class Bool:
    default: Any = _REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class Section:
    fields: Mapping[str, Any]
    doc: str = ""
    optional: bool = True  # absent section → all defaults


@dataclass(frozen=True)
class Union:
    """A section whose allowed keys depend on its discriminator key."""

    key: str
    variants: Mapping[str, Mapping[str, Any]]
    default: str | None = None
    doc: str = ""
    #: absent section → None (no error); only with ``default`` None
    optional: bool = False
    #: names beyond ``variants`` (plugins): name → (fields, None) or (None, why not)
    resolve: Callable[[str], tuple[Mapping[str, Any] | None, str | None]] | None = None


@dataclass(frozen=True)
class Custom:
    """A field validated by a function: value, key path → (result, errors)."""

    check: Callable[[Any, str], tuple[Any, list[str]]]
    default: Any = _REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class FilePath:
    """A path to an existing file, relative to the file that names it.

    Law and profile classes declare their fields without knowing where the
    config lives; :func:`bind_paths` turns each into a check against the
    config file's directory when the schema is assembled."""

    default: Any = _REQUIRED
    doc: str = ""


def bind_paths(fields_: Mapping[str, Any], base_dir: Path, fence: Fence | None = None) -> dict[str, Any]:
    """``fields_`` with every :class:`FilePath` resolved against ``base_dir``
    (and admitted by ``fence``: :func:`file_check`)."""
    return {k: (Custom(file_check(base_dir, fence), default=v.default, doc=v.doc) if isinstance(v, FilePath) else v)
            for k, v in fields_.items()}


class Node:
    """Validated config section: attribute access, read-only, printable."""

    def __init__(self, values: dict[str, Any]) -> None:
        object.__setattr__(self, "_values", values)

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("config is read-only")

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def get(self, name: str, default: Any = None) -> Any:
        return self._values.get(name, default)

    def to_dict(self) -> dict[str, Any]:
        return {k: (v.to_dict() if isinstance(v, Node) else v) for k, v in self._values.items()}

    def replace(self, **changes: Any) -> "Node":
        """A copy with top-level keys changed (the config stays read-only)."""
        unknown = set(changes) - set(self._values)
        if unknown:
            raise KeyError(f"not in this section: {', '.join(sorted(unknown))}")
        return Node({**self._values, **changes})

    def __repr__(self) -> str:
        return f"Node({self.to_dict()!r})"

    def __reduce__(self) -> tuple[Any, ...]:
        # pickled whole (the reload's validating child hands its result back);
        # without this, unpickling recurses through __getattr__
        return (Node, (self._values,))


def _path(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def check_num(spec: Num, value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None and spec.optional:
        return None, []
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None, [f"{path}: must be a number, got {short_repr(value)}"]
    if spec.integer and not (isinstance(value, int) or float(value).is_integer()):
        return None, [f"{path}: must be a whole number, got {short_repr(value)}"]
    if not math.isfinite(float(value)):
        return None, [f"{path}: must be finite, got {short_repr(value)}"]
    v = int(value) if spec.integer else float(value)
    lo, hi = spec.min, spec.max
    if lo is not None and (v <= lo if spec.min_exclusive else v < lo):
        rel = ">" if spec.min_exclusive else ">="
        return None, [f"{path}: {short_repr(value)} out of range (must be {rel} {lo:g}{f' and <= {hi:g}' if hi is not None else ''})"]
    if hi is not None and v > hi:
        return None, [f"{path}: {short_repr(value)} out of range (must be <= {hi:g})"]
    return v, []


def validate_fields(fields_: Mapping[str, Any], data: Any, path: str) -> tuple[Node, list[str]]:
    errors: list[str] = []
    if data is None:
        data = {}
    if not isinstance(data, dict):
        return Node({}), [f"{path or 'config'}: must be a mapping, got {type(data).__name__}"]
    for key in data:
        if key not in fields_:
            allowed = ", ".join(fields_)
            errors.append(f"{_path(path, key_repr(key))}: unknown key (allowed here: {allowed})")
    out: dict[str, Any] = {}
    for key, spec in fields_.items():
        kpath = _path(path, key)
        present = key in data
        value = data.get(key)
        if isinstance(spec, Section):
            if not present and not spec.optional:
                errors.append(f"{kpath}: missing required section")
                continue
            node, errs = validate_fields(spec.fields, value if present else {}, kpath)
            out[key] = node
            errors += errs
            continue
        if isinstance(spec, Union):
            node, errs = validate_union(spec, value if present else None, kpath, present)
            out[key] = node
            errors += errs
            continue
        if not present:
            if spec.default is _REQUIRED:
                errors.append(f"{kpath}: missing required key")
            elif isinstance(spec, Custom):  # defaults of custom fields are inputs too
                out[key], errs = spec.check(spec.default, kpath)
                errors += errs
            else:
                out[key] = spec.default
            continue
        if isinstance(spec, Num):
            v, errs = check_num(spec, value, kpath)
        elif isinstance(spec, Str):
            if value is None and spec.optional:
                v, errs = None, []
            elif not isinstance(value, str):
                v, errs = None, [f"{kpath}: must be a string, got {short_repr(value)}"]
            elif spec.choices is not None and value not in spec.choices:
                v, errs = None, [f"{kpath}: {short_repr(value)} not allowed (allowed: {', '.join(spec.choices)})"]
            else:
                v, errs = value, []
        elif isinstance(spec, Bool):
            v, errs = (value, []) if isinstance(value, bool) else (None, [f"{kpath}: must be true or false, got {short_repr(value)}"])
        elif isinstance(spec, Custom):
            v, errs = spec.check(value, kpath)
        else:  # pragma: no cover - schema bug
            raise TypeError(f"bad schema entry at {kpath}")
        out[key] = v
        errors += errs
    return Node(out), errors


def validate_union(spec: Union, data: Any, path: str, present: bool) -> tuple[Node, list[str]]:
    if not present or data is None:
        if spec.default is None:
            if spec.optional:
                return None, []  # type: ignore[return-value]
            return Node({}), [f"{path}: missing required section (with {spec.key}: one of {', '.join(spec.variants)})"]
        data = {spec.key: spec.default}
    if not isinstance(data, dict):
        return Node({}), [f"{path}: must be a mapping, got {type(data).__name__}"]
    kind = data.get(spec.key, spec.default)
    if kind is None:
        return Node({}), [f"{_path(path, spec.key)}: missing (one of {', '.join(spec.variants)})"]
    if isinstance(kind, str) and kind not in spec.variants and spec.resolve is not None:
        fields_, why = spec.resolve(kind)
        if fields_ is None:
            return Node({}), [f"{_path(path, spec.key)}: {why}"]
        return validate_fields({spec.key: Str(default=kind), **fields_}, data, path)
    if not isinstance(kind, str) or kind not in spec.variants:
        return Node({}), [f"{_path(path, spec.key)}: {short_repr(kind)} not allowed (allowed: {', '.join(spec.variants)})"]
    variant = {spec.key: Str(default=kind), **spec.variants[kind]}
    return validate_fields(variant, data, path)


REQUIRED = _REQUIRED


# --------------------------------------------------------------------------
# Custom checks many schemas share
def file_check(base_dir: Path, fence: Fence | None = None) -> Callable[[Any, str], tuple[Any, list[str]]]:
    """A data file's path (a demand or excitation series): relative to
    ``base_dir``, a regular file, admitted by ``fence`` (default: under
    ``base_dir``'s folder, :meth:`Fence.admit`)."""
    fence = fence if fence is not None else Fence.around(base_dir)

    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        full, err = fence.admit(value, base_dir, path)
        return (str(full), []) if full is not None else (None, [str(err)])

    return check


def auto_or(spec: Num) -> Callable[[Any, str], tuple[Any, list[str]]]:
    """A :class:`Custom` check: the word ``auto``, or a number as ``spec`` takes it."""
    def check(value: Any, path: str) -> tuple[Any, list[str]]:
        if value == "auto":
            return "auto", []
        return check_num(spec, value, path)

    return check


def range_check(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None:
        return None, []
    if not isinstance(value, list) or len(value) != 2:
        return None, [f"{path}: must be [lo, hi] or null, got {short_repr(value)}"]
    lo, e1 = check_num(Num(), value[0], f"{path}[0]")
    hi, e2 = check_num(Num(), value[1], f"{path}[1]")
    if e1 or e2:
        return None, e1 + e2
    if not lo <= hi:
        return None, [f"{path}: need lo <= hi, got {short_repr(value)}"]
    return (lo, hi), []


def optional_bool(value: Any, path: str) -> tuple[Any, list[str]]:
    if value is None or isinstance(value, bool):
        return value, []
    return None, [f"{path}: must be true, false or null (probe), got {short_repr(value)}"]


# --------------------------------------------------------------------------
# Reference documentation, generated from the schema (docs/config.md)
def _kind(spec: Any) -> str:
    if isinstance(spec, Num):
        kind = "integer" if spec.integer else "number"
        lo = "" if spec.min is None else (f"> {spec.min:g}" if spec.min_exclusive else f">= {spec.min:g}")
        hi = "" if spec.max is None else f"<= {spec.max:g}"
        rng = ", ".join(x for x in (lo, hi) if x)
        return kind + (f" ({rng})" if rng else "") + (" or null" if spec.optional else "")
    if isinstance(spec, Str):
        return ("one of " + ", ".join(f"`{c}`" for c in spec.choices)) if spec.choices else "string"
    if isinstance(spec, Bool):
        return "true/false"
    return "see description"


def _default(spec: Any) -> str:
    d = getattr(spec, "default", _REQUIRED)
    if d is _REQUIRED:
        return "**required**"
    return "null" if d is None else f"`{d}`"


def schema_markdown(schema: Mapping[str, Any]) -> str:
    """A schema as markdown tables: the generated part of a reference page."""
    lines: list[str] = []

    def table(fields_: Mapping[str, Any], prefix: str) -> None:
        rows = [(k, v) for k, v in fields_.items() if not isinstance(v, (Section, Union))]
        if rows:
            lines.append("| key | type | default | meaning |")
            lines.append("|---|---|---|---|")
            for k, spec in rows:
                cells = (_kind(spec), _default(spec), getattr(spec, "doc", "") or "")
                kind, default, doc = (c.replace("|", "\\|") for c in cells)  # |F_des| must not split a cell
                lines.append(f"| `{_path(prefix, k)}` | {kind} | {default} | {doc} |")
            lines.append("")
        for k, spec in fields_.items():
            path = _path(prefix, k)
            if isinstance(spec, Section):
                lines.append(f"### `{path}`" + (f": {spec.doc}" if spec.doc else ""))
                lines.append("")
                table(spec.fields, path)
            elif isinstance(spec, Union):
                lines.append(f"### `{path}`: {spec.doc}")
                lines.append("")
                lines.append(f"Chosen by `{path}.{spec.key}`" + (f" (default `{spec.default}`)" if spec.default else "")
                             + ("; the section is optional" if spec.optional else "") + ".")
                lines.append("")
                for name, vfields in spec.variants.items():
                    lines.append(f"#### `{path}.{spec.key}: {name}`")
                    lines.append("")
                    if vfields:
                        table(vfields, path)
                    else:
                        lines.append("(no further keys)")
                        lines.append("")

    table(schema, "")
    return "\n".join(lines)
