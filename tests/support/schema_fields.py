"""Every leaf field of the configuration schema, for tests that sweep it (bad input, finite floats, times)."""

from __future__ import annotations

from collections.abc import Iterator

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from qmg_lab.config.schema import Config


def schema_fields(model: type[BaseModel] = Config, prefix: str = "") -> Iterator[tuple[str, str, FieldInfo]]:
    """(TOML section, key, FieldInfo) of every field that is not a section ([sim.faults] as "sim.faults")."""
    for key, info in model.model_fields.items():
        ann = info.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            yield from schema_fields(ann, f"{prefix}.{key}" if prefix else key)
        else:
            yield prefix, key, info
