"""Configuration errors in words: what pydantic reports, rewritten to name the field and what it accepts.

`describe_error(error, root)` turns one pydantic error into a line such as
"plan.dwell_s: Input should be greater than 0 (got -1); allowed: a number > 0 and <= 86400". The bounds are
read from the field's own constraints (`bound_texts`), the same words docs/configuration.md uses.
"""

from __future__ import annotations

import re
import tomllib
from typing import Any, Literal

from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails

_BOUND_SYMBOLS = (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"))


def _constraints(info: FieldInfo) -> list[Any]:
    """The field's constraint objects; for a list, those of its items (list[Annotated[float, Field(ge=0)]])."""
    found = list(info.metadata)
    if getattr(info.annotation, "__origin__", None) is list:
        for item in getattr(info.annotation, "__args__", ()):
            for meta in getattr(item, "__metadata__", ()):
                found.extend(getattr(meta, "metadata", ()))
    return found


def bound_texts(info: FieldInfo) -> list[str]:
    """The field's numeric bounds as text, e.g. ["> 0", "<= 86400"] (numbers in %g); a list's are its items'."""
    out = []
    for m in _constraints(info):
        for attr, sym in _BOUND_SYMBOLS:
            v = getattr(m, attr, None)
            if v is not None:
                out.append(f"{sym} {v:g}" if isinstance(v, (int, float)) else f"{sym} {v}")
    extra = info.json_schema_extra
    keys = extra.get("limited_by") if isinstance(extra, dict) else None
    if isinstance(keys, list):  # bounds that are other keys of the configuration (instrument limits)
        out.append(f"within [{keys[0]}, {keys[1]}]" if len(keys) == 2 else f"magnitude <= {keys[0]}")
    return out


def field_at(root: type[BaseModel], loc: tuple[Any, ...]) -> tuple[type[BaseModel] | None, FieldInfo | None]:
    """The model owning the field at `loc` (list indices skipped) and the field's FieldInfo (None if unknown)."""
    model: Any = root
    owner: type[BaseModel] | None = None
    info: FieldInfo | None = None
    for part in loc:
        if isinstance(part, int):
            break
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            return owner, None
        owner, info = model, model.model_fields.get(str(part))
        if info is None:
            return owner, None
        model = info.annotation
    return owner, info


def allowed_text(info: FieldInfo) -> str:
    """What a field accepts, in words: its type and bounds (e.g. "a number > 0 and <= 86400")."""
    ann = info.annotation
    args = [a for a in getattr(ann, "__args__", ()) if a is not type(None)]
    if getattr(ann, "__origin__", None) is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    base = ann if isinstance(ann, type) else (args[0] if len(args) == 1 else None)
    words: dict[object, str] = {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}
    kind = words.get(base, "")
    if getattr(ann, "__origin__", None) is list:
        kind = "a list of finite numbers"
    bounds = bound_texts(info)
    for m in info.metadata:
        if getattr(m, "pattern", None):
            bounds.append(f"matching {m.pattern}")
        if getattr(m, "min_length", None):
            bounds.append("not empty")
    text = " and ".join(bounds)
    if type(None) in getattr(ann, "__args__", ()):
        kind = kind + " (or absent)" if kind else kind
    return f"{kind} {text}".strip() if kind or text else ""


def describe_error(error: ErrorDetails, root: type[BaseModel]) -> str:
    """One pydantic validation error of a `root` model, as a line naming the key and what it accepts."""
    loc_parts = tuple(error.get("loc", ()))
    loc = ".".join(str(p) for p in loc_parts) or "(top level)"
    kind = error.get("type", "")
    ctx = error.get("ctx") or {}
    msg = error.get("msg", "invalid")
    owner, info = field_at(root, loc_parts)
    if kind == "extra_forbidden":
        known = f"; known keys: {', '.join(owner.model_fields)}" if owner is not None and info is None else ""
        return f"{loc}: unknown key (check the spelling; see docs/configuration.md{known})"
    if ctx.get("error") is not None and kind == "value_error":
        named = not loc_parts or str(ctx["error"]).startswith(loc.split(".")[0])  # the message names its keys
        return f"{ctx['error']}" if named else f"{loc}: {ctx['error']}"
    allowed = allowed_text(info) if info is not None else ""
    if info is not None and isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel):
        allowed = f"a [{loc}] section (a TOML table)"
    suffix = f"; allowed: {allowed}" if allowed else ""
    return f"{loc}: {msg} (got {error.get('input')!r}){suffix}"


_AT = re.compile(r"\s*\(at line (\d+), column (\d+)\)|\s*\(at end of document\)")
_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]*?)\s*\]")
_SYNTAX_HINTS = (
    ("Invalid value", "a value is a number, true or false, a quoted string ('text') or a list [1.0, 2.0]"),
    ("Expected ']'", "a section is [name] or [name.sub], in ASCII letters, digits, _ and -"),
    ("Invalid statement", "each line is key = value, a [section] or a # comment"),
    ("Expected '=' after a key", "each line is key = value; a key is ASCII letters, digits, _ and -"),
    ("Expected newline", "one key = value per line; a comment starts with #"),
)


def toml_syntax_message(text: str, error: tomllib.TOMLDecodeError) -> str:
    """A TOML syntax error in words: the line, the key or section, what is wrong and what to do.

    tomllib reports "Cannot overwrite a value (at line 3, column 13)"; this names the key set twice and where it
    was first set, a UTF-8 byte-order mark, a key with non-ASCII characters, and shows the line."""
    raw = str(error)
    what = _AT.sub("", raw).strip()
    if text.startswith("\ufeff"):
        return (
            "the file starts with a UTF-8 byte-order mark (BOM), which TOML does not allow: save it as UTF-8 "
            'without BOM (editors offer "UTF-8" beside "UTF-8 with BOM")'
        )
    where = re.search(r"\(at line (\d+), column (\d+)\)", raw)
    if where is None:
        return f"at the end of the file: {what}: a quoted string, a list [...] or a {{...}} table is not closed"
    lines = text.splitlines()
    number, column = int(where.group(1)), int(where.group(2))
    line = lines[number - 1] if 0 < number <= len(lines) else ""
    shown = f"\n    line {number}: {line.strip()[:120]}"
    header = _HEADER.match(line)
    name = header.group(1) if header else line.split("=", 1)[0].strip()
    odd = sorted({c for c in name if ord(c) > 127 or c in "\ufeff"})
    if odd:
        chars = ", ".join(repr(c) for c in odd)
        return (
            f"line {number}: {'section' if header else 'key'} {name!r} contains {chars}: configuration keys and "
            f"sections are ASCII letters, digits, _ and - (docs/configuration.md lists them){shown}"
        )
    section, first = _first_definition(lines[: number - 1], name, header is not None)
    if what.startswith("Cannot declare"):
        again = f" (first on line {first})" if first else ""
        return f"line {number}: the section [{name}] appears twice{again}: merge the two into one section{shown}"
    if what.startswith("Cannot overwrite"):
        key = f"{section}.{name}" if section and not header else name
        again = f" (first on line {first})" if first else ""
        return f"line {number}: {key} is set twice{again}: keep one of the two{shown}"
    hint = next((h for start, h in _SYNTAX_HINTS if what.startswith(start)), "docs/configuration.md shows the syntax")
    return f"line {number}, column {column}: {what[:1].lower()}{what[1:]}: {hint}{shown}"


def _first_definition(before: list[str], name: str, is_section: bool) -> tuple[str, int]:
    """The section the next line belongs to, and the 1-based line (0 if none) where `name` was first defined: as
    a [section] header if `is_section`, else as a key of that same section."""
    section, first = "", 0
    for i, line in enumerate(before, start=1):
        header = _HEADER.match(line)
        if header:
            section = header.group(1)
            if is_section and section == name and not first:
                first = i
            elif not is_section:
                first = 0  # only a definition inside the current section counts
        elif not is_section and "=" in line and line.split("=", 1)[0].strip() == name:
            first = i
    return section, first
