"""docs/configuration.md, generated from the configuration schema (a test keeps the file equal to it).

python -m qmg_lab.config.docs > docs/configuration.md
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel

from qmg_lab.config.errors import bound_texts
from qmg_lab.config.schema import Config, SimFaultsSection


def reference_markdown() -> str:
    """docs/configuration.md, generated from the schema (a test keeps the file equal to this)."""
    lines = [
        "# Configuration reference",
        "",
        "Generated from `qmg_lab/config/schema.py` by `python -m qmg_lab.config.docs > docs/configuration.md`.",
        "Every section is strict: an unknown key is an error that names it. Units are in the names",
        "(`_s` seconds, `_hz` hertz, `_dps` deg/s, `_dps2` deg/s², `_c` °C, `_v` volts, `_vrms` volts rms).",
        "",
    ]

    def section(name: str, model: type[BaseModel]) -> None:
        lines.extend(
            [
                f"## [{name}]",
                "",
                (model.__doc__ or "").strip().split("\n\n")[0],
                "",
                "| key | default | allowed | meaning |",
                "|---|---|---|---|",
            ]
        )
        for key, f in model.model_fields.items():
            ann = f.annotation
            if isinstance(ann, type) and issubclass(ann, BaseModel):
                continue
            default = f.get_default(call_default_factory=True)
            bounds = bound_texts(f)
            for m in f.metadata:
                pattern = getattr(m, "pattern", None)
                if pattern:
                    bounds.append(f"pattern `{pattern}`")
            args = getattr(ann, "__args__", ())
            if getattr(ann, "__origin__", None) is Literal:
                bounds.append(" \\| ".join(repr(a) for a in args))
            extra = f.json_schema_extra if isinstance(f.json_schema_extra, dict) else {}
            per_os = extra.get("default_per_os")  # a default that depends on the OS: each, not this machine's
            shown = (
                ", ".join(f"`{v!r}` ({k})" for k, v in per_os.items()) if isinstance(per_os, dict) else f"`{default!r}`"
            )
            lines.append(f"| `{key}` | {shown} | {', '.join(bounds) or '—'} | {f.description or ''} |")
        lines.append("")

    for name, f in Config.model_fields.items():
        model = f.annotation
        assert isinstance(model, type)
        section(name, model)
        if name == "sim":
            section("sim.faults", SimFaultsSection)
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    print(reference_markdown(), end="")
