"""The driver's AMPL/OFFS ordering keeps |AC peak| + |DC| <= 5 V at every step, which the twin enforces.

From any legal state (A_old/2 + |o_old| <= 5 V) to any legal state, the driver must never trip the twin's
execution-error bit; the World must end at exactly the requested levels.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.ds345 import DS345
from sims.ds345_twin import DS345Twin
from tests.support.twin_params import paper_world


@st.composite
def legal_levels(draw: st.DrawFn) -> tuple[float, float]:
    """(Vpp, offset) on the 1 mV grid with Vpp/2 + |offset| <= 5 V and Vpp = 0 or >= 10 mVpp."""
    vpp_mv = draw(st.one_of(st.just(0), st.integers(10, 10000)))
    room_mv = 5000 - vpp_mv // 2 if vpp_mv % 2 == 0 else 5000 - (vpp_mv + 1) // 2
    offset_mv = draw(st.integers(-room_mv, room_mv))
    return vpp_mv / 1000.0, offset_mv / 1000.0


@settings(max_examples=60, deadline=None)
@given(st.lists(legal_levels(), min_size=2, max_size=5))
def test_every_transition_is_accepted(path: list[tuple[float, float]]) -> None:
    world = paper_world()
    gen = DS345(DS345Twin(world).resource())
    for vpp, offset in path:
        gen.set_square(7.0, vpp, offset)  # raises InstrumentError if any intermediate state was refused
        assert (world.dither.amplitude_vpp, world.dither.offset_v) == (vpp, offset)
