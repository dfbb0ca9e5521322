"""A configuration is a regular, readable file of bounded size, checked before it is opened: a FIFO would make
`open` wait for a writer (a hung `check`), a device such as /dev/zero never ends. Each is refused with words
(ConfigError), at once."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from qmg_lab.config.schema import CONFIG_MAX_BYTES, ConfigError, load_config


@pytest.mark.skipif(sys.platform == "win32", reason="FIFOs and /dev/zero are POSIX")
def test_a_fifo_and_a_device_are_refused_without_opening_them(tmp_path: Path) -> None:
    fifo = tmp_path / "campaign.toml"
    os.mkfifo(fifo)  # nothing ever writes it: an open for reading would wait for ever
    with pytest.raises(ConfigError, match="is not a regular file"):
        load_config(fifo)
    with pytest.raises(ConfigError, match="is not a regular file"):
        load_config("/dev/zero")


def test_a_directory_and_an_oversized_file_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * (CONFIG_MAX_BYTES + 1))
    with pytest.raises(ConfigError, match=f"at most {CONFIG_MAX_BYTES} bytes"):
        load_config(big)
    ok = tmp_path / "ok.toml"
    ok.write_text('[campaign]\nname = "ok"\n')
    assert load_config(ok)[0].campaign.name == "ok"
