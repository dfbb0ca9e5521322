"""The HF2LI driver on a real instrument: skipped unless QMG_HF2_HOST and QMG_HF2_DEVICE name one.

Read-only apart from safe_state (which switches the outputs off): run it with the gyroscope disconnected or
at rest. Example: QMG_HF2_HOST=192.168.1.10 QMG_HF2_DEVICE=dev1234 pytest -m hardware tests/drivers
"""

from __future__ import annotations

import os

import pytest

from drivers.hf2li import HF2LI
from qmg_lab.config.schema import LockInSection

HOST = os.environ.get("QMG_HF2_HOST")
DEVICE = os.environ.get("QMG_HF2_DEVICE")

pytestmark = [
    pytest.mark.hardware,
    pytest.mark.skipif(not (HOST and DEVICE), reason="set QMG_HF2_HOST and QMG_HF2_DEVICE"),
]


def test_identify_state_and_safe_state_on_the_instrument() -> None:
    li = HF2LI(
        str(HOST), str(DEVICE), LockInSection(device=str(DEVICE)), port=int(os.environ.get("QMG_HF2_PORT", "8005"))
    )
    assert "HF2" in li.identify()
    st = li.state()
    assert st["clockbase_hz"] == 210e6  # the HF2's timestamp clock as third-party HF2 code has it
    # which oscillator each PLL drives is read, never assumed: the forcer's PLL (none with MF) drives its oscillator
    assert st["pll"]["oscselect"] == st["carriers"]["reference_oscillator"]
    for n, pll in st["tracking_plls"].items():
        assert pll["oscselect"] == st["carriers"]["forcer_oscillator"], n
    offset = st["demod_timestamp_offset_ticks"]  # None while the demodulators are off
    assert offset is None or abs(offset) < st["clockbase_hz"] / max(st["demod_rate_hz"]) / 2
    li.safe_state()
    assert all(li.state()["pids"][n]["enable"] == 0 for n in ("agc", "rate", "quadrature"))
    li.close()
