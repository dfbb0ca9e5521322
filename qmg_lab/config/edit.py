"""Edit a configuration's TOML text by key, keeping the user's comments, order and layout (tomlkit).

Used where qmg-lab derives a configuration from one the user wrote, and stores the derived text in the run file
(`characterize` sets [campaign] kind): `with_values(text, {"campaign.kind": "linearity"})`. A dotted key names
section.key; a missing section is created. The result is validated like any configuration before it is used.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import tomlkit
from tomlkit.items import Table


def with_values(text: str, values: Mapping[str, Any]) -> str:
    """`text` with each dotted key of `values` set (replacing what the text had there)."""
    doc = tomlkit.parse(text)
    for dotted, value in values.items():
        *sections, key = dotted.split(".")
        table: Any = doc
        for name in sections:
            if name not in table:
                table[name] = tomlkit.table()
            table = table[name]
            if not isinstance(table, Table):
                raise ValueError(f"{dotted}: {name} is not a TOML table in this configuration")
        table[key] = value
    return tomlkit.dumps(doc)
