"""Configuration errors in words: what pydantic reports, rewritten to name the field and what it accepts.

`describe_error(error, root)` turns one pydantic error into a line such as
"plan.dwell_s: Input should be greater than 0 (got -1); allowed: a number > 0 and <= 86400". The bounds are
read from the field's own constraints (`bound_texts`), the same words docs/configuration.md uses.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import ErrorDetails

_BOUND_SYMBOLS = (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"))


def bound_texts(info: FieldInfo) -> list[str]:
    """The field's numeric bounds as text, e.g. ["> 0", "<= 86400"] (numbers in %g)."""
    out = []
    for m in info.metadata:
        for attr, sym in _BOUND_SYMBOLS:
            v = getattr(m, attr, None)
            if v is not None:
                out.append(f"{sym} {v:g}" if isinstance(v, (int, float)) else f"{sym} {v}")
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
    words: dict[object, str] = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    kind = words.get(base, "")
    if getattr(ann, "__origin__", None) is list:
        kind = "a list of numbers"
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
        return f"{ctx['error']}" if str(ctx["error"]).startswith(loc.split(".")[0]) else f"{loc}: {ctx['error']}"
    allowed = allowed_text(info) if info is not None else ""
    if info is not None and isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel):
        allowed = f"a [{loc}] section (a TOML table)"
    suffix = f"; allowed: {allowed}" if allowed else ""
    return f"{loc}: {msg} (got {error.get('input')!r}){suffix}"
