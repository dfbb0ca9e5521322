"""The serial drivers against their twins under every framing the configuration can set (issue 12).

The twins reply with CR, LF or CR LF line ends (the 1291BR's prompt with or without its terminator) and accept
commands ending CR, LF or CR LF; the configuration's [table]/[chamber] framing keys set both sides. The driver
reads replies tolerantly ("auto") and, where configured, with the exact terminator. Expected values come from
the documented protocol: STA at rest = 8 (servo on) | 2 (at rate) = 10; after JOG r the commanded rate is r;
the chamber twin starts at [sim] initial_temperature_c = 25.00 degC and SET= is echoed by SET? once on.
"""

from __future__ import annotations

import itertools

import pytest

from qmg_lab.config.schema import parse_config
from qmg_lab.station import connect_instrument
from tests.support.twin_params import paper_world_params, table_twin_settings

TERMS = ("CR", "LF", "CRLF")


@pytest.mark.parametrize(
    ("command", "reply", "prompt", "transport"),
    [
        *[(c, r, p, "inprocess") for c, r, p in itertools.product(TERMS, TERMS, ("CR", "none"))],
        *[("CRLF", r, p, "socket") for r, p in itertools.product(TERMS, ("CRLF", "none"))],
    ],
)
def test_table_under_every_framing(command: str, reply: str, prompt: str, transport: str) -> None:
    cfg = parse_config(
        f'[table]\nsim = true\nsim_transport = "{transport}"\ncommand_terminator = "{command}"\n'
        f'sim_reply_terminator = "{reply}"\nsim_prompt_terminator = "{prompt}"\n'
    )
    conn = connect_instrument(cfg, "table")
    table = conn.instrument
    try:
        assert table.identify().endswith("STA=10)")
        table.set_rate(5.0, 300.0)
        assert table.read().status & 8  # servo on
        table.stop()
        assert table.state()["rate_command_dps"] == 0.0
    finally:
        conn.close()


@pytest.mark.parametrize("reply", TERMS)
def test_table_with_the_exact_reply_terminator(reply: str) -> None:
    cfg = parse_config(
        f'[table]\nsim = true\nreply_terminator = "{reply}"\nsim_reply_terminator = "{reply}"\n'
        f'sim_prompt_terminator = "{reply}"\n'
    )
    conn = connect_instrument(cfg, "table")
    try:
        assert conn.instrument.identify().endswith("STA=10)")
        assert conn.instrument.read().rate_dps == 0.0
    finally:
        conn.close()


@pytest.mark.parametrize(
    ("command", "reply", "transport"),
    [
        *[(c, r, "inprocess") for c, r in itertools.product(TERMS, TERMS)],
        *[("CRLF", r, "socket") for r in TERMS],
    ],
)
def test_chamber_under_every_framing(command: str, reply: str, transport: str) -> None:
    cfg = parse_config(
        f'[chamber]\nsim = true\nsim_transport = "{transport}"\ncommand_terminator = "{command}"\n'
        f'sim_reply_terminator = "{reply}"\n'
    )
    conn = connect_instrument(cfg, "chamber")
    chamber = conn.instrument
    try:
        assert chamber.read().temperature_c == 25.0
        chamber.set_setpoint(25.0, 2.0)
        reading = chamber.read()
        assert reading.setpoint_c == 25.0 and reading.ramping is False
        assert chamber.ramp_rate() == 2.0
    finally:
        conn.close()


def test_a_wrong_command_terminator_is_named_by_the_twin() -> None:
    """Driver sends LF only, the instrument wants CR LF: the 1291BR twin answers E05 FRAMING; the error says so."""
    from qmg_lab.instruments import InstrumentError
    from qmg_lab.station import table_driver
    from sims.serial_twin import InProcessSerial
    from sims.table_twin import RateTableTwin
    from sims.world import World

    cfg = parse_config('[table]\ncommand_terminator = "LF"\n')
    twin = RateTableTwin(World(paper_world_params(), clock="wall"), **table_twin_settings())  # expects CR LF
    with pytest.raises(InstrumentError, match=r"'STA' refused: E05 FRAMING"):
        table_driver(cfg, lambda: InProcessSerial(twin)).identify()
