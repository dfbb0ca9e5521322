"""DS345 number formatting, as a property: the text is the value rounded to the wire resolution."""

from __future__ import annotations

import re

from hypothesis import given
from hypothesis import strategies as st

from drivers.ds345 import format_number

PLAIN = re.compile(r"^-?\d+(\.\d*[1-9])?$")  # no exponent, no trailing zero, no trailing '.'


@given(st.floats(min_value=-1e8, max_value=1e8, allow_nan=False), st.sampled_from([3, 4, 6]))
def test_text_is_the_rounded_value(value: float, decimals: int) -> None:
    text = format_number(value, decimals)
    assert PLAIN.match(text), text
    assert text != "-0"
    assert abs(float(text) - round(value, decimals)) <= 10.0 ** -(decimals + 3) * max(1.0, abs(value))
