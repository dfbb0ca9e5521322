"""The space a run asks for (qmg_lab/storage/space.py): the formula, and a figure that is enough when freed exactly
as written (rounded up; what is free rounded down)."""

from __future__ import annotations

import re
from pathlib import Path

from qmg_lab.storage.space import MARGIN, RESERVE_BYTES, WORDS_PATTERN, SpaceNeed, raw_bytes_per_s, space_need


def test_the_raw_rate_is_the_stored_bytes_of_every_column() -> None:
    # /lockin: 8 float64 columns and the uint8 pll_locked, /truth 4 float64: 1800 Sa/s each; /clsf 5 at 7 rows/s
    lockin_row = 8 * 8 + 1
    assert raw_bytes_per_s({"lockin": 1800.0, "truth": 1800.0, "clsf": 7.0}) == 1800 * lockin_row + 8 * (
        1800 * 4 + 7 * 5
    )


def test_the_need_is_the_margin_times_the_rate_times_the_time_left_plus_the_reserve(tmp_path: Path) -> None:
    need = space_need(tmp_path / "run.h5", bytes_per_s=1000.0, left_s=100.0, measured=True)
    assert need.needed == int(MARGIN * 1000.0 * 100.0) + RESERVE_BYTES
    assert need.free is not None and need.free > 0


def test_freeing_the_figure_asked_is_always_enough() -> None:
    for needed in (4_194_304, 4_250_001, 10_000_000, 123_456_789):
        said = SpaceNeed(needed, 0, 100.0, 10.0, True).words()
        found = re.search(r"needs about ([0-9.]+) MB more", said)
        assert found is not None, said
        asked = float(found.group(1)) * 1e6
        assert asked >= needed, said
        assert SpaceNeed(needed, round(asked), 100.0, 10.0, True).enough


def test_the_words_pattern_finds_every_figure_asked() -> None:
    """A figure asked before a write failed is replaced by the one computed after it (campaign.pipeline), found
    by WORDS_PATTERN: it must match the whole of every `words()`, known free space or not."""
    for free in (0, None, 123_456_789):
        said = SpaceNeed(4_250_001, free, 100.0, 10.0, True).words()
        found = WORDS_PATTERN.search(f"stopped: {said}. Free the space")
        assert found is not None and found.group(0) == said
