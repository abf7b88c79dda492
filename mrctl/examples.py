"""``mrctl examples [DIR]``: the files a pip install ships besides the code.

The example experiments (``config/experiments/*.yaml``), hil_sim's bench
configs (``config/hil_*.yaml``), the systemd units and the tmpfiles.d entry
for the device-lock directory (``systemd/``) and the reference docs
(``docs/``, the targets of README's links) live in the package
(``mrctl/data/``, whose ``config``, ``systemd`` and ``docs`` are symlinks to
the source tree's top-level directories, copied into the wheel when it is built),
so they exist wherever mrctl is installed. This copies them out, with the
same layout as the source tree, so README's commands (``mrctl run
config/experiments/fig5.yaml``) work in DIR; and README.md itself, from the
package's metadata (the units' ``Documentation=`` names it, docs/install.md).
"""

from __future__ import annotations

import importlib.metadata
import importlib.resources
from pathlib import Path

from mrctl.errors import BadInput

__all__ = ["example_files", "copy_examples"]

_PATTERNS = ("config/**/*.yaml", "systemd/*.service", "systemd/*.conf", "docs/*.md", "docs/*.xml", "docs/img/*.png")

#: what the copied README says first: its links to docs/ work in DIR, what is not shipped is named
_README_NOTE = ("> Copied by `mrctl examples` from the installed mrctl {version}: the links to `docs/` open the\n"
                "> reference installed with it (also `mrctl docs TOPIC`); `bench/` and `examples/`, named below,\n"
                "> are in the source repository, not in the package.\n\n")


def _data() -> Path:
    return Path(str(importlib.resources.files("mrctl") / "data"))


def example_files() -> list[str]:
    """Every shipped example, as a path relative to the data directory."""
    root = _data()
    return sorted({str(p.relative_to(root)) for pat in _PATTERNS for p in root.glob(pat) if p.is_file()})


def _readme() -> str | None:
    src = Path(__file__).resolve().parents[1] / "README.md"  # a source checkout
    if src.is_file():
        return src.read_text(encoding="utf-8")
    try:
        meta = importlib.metadata.metadata("mrctl")
    except importlib.metadata.PackageNotFoundError:
        return None
    body = meta.get_payload() if hasattr(meta, "get_payload") else None  # the long description
    return body or meta.get("Description") or None


def copy_examples(dest: Path, force: bool = False) -> list[str]:
    """Copy every example (and README.md) under ``dest``; returns the paths
    written, relative to it. Refuses (``BadInput``, nothing written) if any
    would overwrite a file, unless ``force``."""
    root = _data()
    items: list[tuple[str, bytes]] = [(rel, (root / rel).read_bytes()) for rel in example_files()]
    if not items:
        raise BadInput(f"no example files found in {root}: is mrctl installed completely?")
    readme = _readme()
    if readme:
        from mrctl import __version__

        items.append(("README.md", (_README_NOTE.format(version=__version__) + readme).encode("utf-8")))
    if not force:
        clash = [rel for rel, _ in items if (dest / rel).exists() or (dest / rel).is_symlink()]
        if clash:
            raise BadInput(f"{dest}: {len(clash)} file(s) exist, e.g. {dest / clash[0]}; "
                           f"nothing written (pass --force to overwrite them)")
    if dest.exists() and not dest.is_dir():
        raise BadInput(f"{dest}: exists and is not a directory")
    for rel, data in items:
        target = dest / rel
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.is_symlink():
                target.unlink()  # replace a link, never write through it
            target.write_bytes(data)
        except OSError as exc:
            raise BadInput(f"{target}: cannot write: {exc.strerror or exc}") from None
    return [rel for rel, _ in items]
