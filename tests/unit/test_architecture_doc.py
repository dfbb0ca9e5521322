"""docs/architecture.md names only what exists: every file of its module map is in the repository, every other file
it cites exists, and every dotted name it cites imports (a module, or an attribute of one), resolves as a
configuration key (`section.key` of the schema), or is a method of a class defined in qmg_lab, drivers or sims.
Names of the standard library (`gc.freeze`) are the platform's, not checked here."""

from __future__ import annotations

import ast
import importlib
import re
import sys
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from qmg_lab.config.schema import Config

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"
PACKAGES = ("qmg_lab", "drivers", "sims")
FILE_SUFFIXES = (".py", ".md", ".toml", ".yaml")  # files of the repository (results.csv is an output)
OUTPUT_SUFFIXES = (".csv", ".h5", ".png", ".json")  # what the commands write: named, not in the repository
DOTTED = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)+$")


def _cited() -> list[str]:
    return sorted(set(re.findall(r"`([^`\n]+)`", DOC.read_text(encoding="utf-8"))))


def _module_map_paths() -> list[str]:
    """The files of the module-map tables: `| package | module | job |` rows under "### `qmg_lab/`", and
    `| module | job |` rows under "### `drivers/`" and "### `sims/`" (a blank package cell: the row above's)."""
    paths: list[str] = []
    root, package = "", ""
    for line in DOC.read_text(encoding="utf-8").splitlines():
        head = re.match(r"^### `([a-z_]+)/`", line)
        if head:
            root, package = head.group(1), ""
            continue
        if line.startswith("## "):
            root = ""
        if not root or not line.startswith("|") or set(line) <= set("|- "):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if root == "qmg_lab" and len(cells) == 3:
            if cells[0] and cells[0] != "package":
                package = "" if cells[0] == "(top)" else cells[0].strip("`")
            modules = cells[1]
        elif root != "qmg_lab" and len(cells) == 2:
            package, modules = "", cells[0]
        else:
            continue
        for name in re.findall(r"`([^`]+)`", modules):
            if name != "module":
                paths.append("/".join(p.strip("/") for p in (root, package, name) if p))
    return paths


@cache
def _classes() -> dict[str, str]:
    """Top-level class name -> module (dotted) over qmg_lab, drivers and sims."""
    found: dict[str, str] = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            mod = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            for node in ast.parse(path.read_text(encoding="utf-8")).body:
                if isinstance(node, ast.ClassDef):
                    found.setdefault(node.name, mod)
    return found


def _resolve(dotted: str) -> Any:
    """The object a dotted name means, importing the longest module prefix; LookupError if nothing matches."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:n]))
        except ImportError:
            continue
        for attr in parts[n:]:
            obj = getattr(obj, attr)
        return obj
    raise LookupError(dotted)


def _config_key(dotted: str) -> bool:
    section, _, key = dotted.partition(".")
    field = Config.model_fields.get(section)
    model = field.annotation if field is not None else None
    return key in getattr(model, "model_fields", {})


def _problem(name: str) -> str | None:
    """None if `name` (a dotted name or a file name cited by the page) exists, else what is wrong."""
    if name.endswith(FILE_SUFFIXES) and "/" not in name and " " not in name:
        return None if any(ROOT.glob(f"**/{name}")) else f"no file named {name}"
    if not DOTTED.match(name) or name.endswith(OUTPUT_SUFFIXES):
        return None
    first = name.split(".", maxsplit=1)[0]
    if first in sys.stdlib_module_names or _config_key(name):
        return None
    candidates = [name] if first in PACKAGES else [name, f"qmg_lab.{name}"]
    if first in _classes():
        candidates.append(f"{_classes()[first]}.{name}")
    for c in candidates:
        try:
            _resolve(c)
            return None
        except (LookupError, AttributeError):
            continue
    return f"{name} does not import (tried {', '.join(candidates)})"


def test_every_file_of_the_module_map_exists() -> None:
    paths = _module_map_paths()
    assert len(paths) > 80  # the map lists every module: the parse found its rows
    missing = [p for p in paths if not (ROOT / p).is_file()]
    assert missing == []


def test_every_cited_path_exists() -> None:
    # HDF5 groups (/lockin) and option words are not paths of the repository
    paths = [c for c in _cited() if "/" in c and " " not in c and not c.startswith(("http", "-", "/"))]
    assert len(paths) > 5
    missing = [p for p in paths if not (ROOT / p.rstrip("/")).exists() and not (ROOT / "qmg_lab" / p).exists()]
    assert missing == []


@pytest.mark.parametrize("name", [c for c in _cited() if DOTTED.match(c) or c.endswith(FILE_SUFFIXES)])
def test_every_cited_name_imports(name: str) -> None:
    assert _problem(name) is None, _problem(name)
