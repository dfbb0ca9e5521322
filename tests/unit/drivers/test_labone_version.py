"""The LabOne version advice of drivers/hf2li.py: the pin it suggests and the refusal texts it recognises.

Facts from outside the code:
* zhinst-core's releases, as PyPI lists them (``pip index versions zhinst-core``, 2026-11-27): among them
  26.7.2.5, 26.4.1.6, 25.1.0.834, 24.10.65175, 23.6.46756 (three- and four-part versions). ``pip download --no-deps
  "zhinst-core==25.1.*"`` (and ``==24.10.*``, ``==26.4.*``) found 25.1.0.834, 24.10.65175 and 26.4.1.6, while
  ``==25.1.0`` found nothing. ``packaging``'s SpecifierSet is the PEP 440 matching pip's resolver uses.
* The refusal texts: zhinst-core's ZIAPIVersionMismatchException as zhinst-toolkit issue #294 quotes it; the
  others are strings of zhinst-core 26.7's _core.so ("Incompatible server version. Please ensure the client and
  server run on the same LabOne version.", "The server version is too old. The server runs on version '...' but
  the client runs on version '...'. Please update the LabOne Software.").
"""

from __future__ import annotations

import pytest
import zhinst.core
from packaging.specifiers import SpecifierSet
from packaging.version import Version

import drivers.hf2li as hf2li_module
from drivers.hf2li import open_hf2_session, version_mismatch_message, zhinst_core_pin
from qmg_lab.instruments import InstrumentError

# (LabOne version as a data server reports it, a real zhinst-core release of that LabOne version on PyPI)
REAL = [
    ("25.1", "25.1.0.834"),
    ("24.10.1", "24.10.65175"),
    ("26.04", "26.4.1.6"),
    ("26.07", "26.7.2.5"),
    ("23.06.2", "23.6.46756"),
]
OTHERS = ["25.4.0.628", "24.1.55273", "26.1.3.9", "22.8.36541"]  # real releases of other LabOne versions


@pytest.mark.parametrize(("labone", "release"), REAL)
def test_the_pin_matches_the_real_release_of_that_labone_version_and_no_other(labone: str, release: str) -> None:
    pin = zhinst_core_pin(labone)
    assert pin is not None and pin.startswith("zhinst-core==") and pin.endswith(".*")
    spec = SpecifierSet(pin.removeprefix("zhinst-core"))
    assert Version(release) in spec
    assert not any(Version(v) in spec for v in OTHERS + [r for _, r in REAL if r != release])


def test_an_exact_three_part_pin_matches_no_four_part_release() -> None:
    assert Version("25.1.0.834") not in SpecifierSet("==25.1.0")  # why the advice is ==X.Y.*
    assert zhinst_core_pin("not a version") is None


def test_the_26x_refusal_without_versions_is_recognised_and_the_server_is_asked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text = "Incompatible server version. Please ensure the client and server run on the same LabOne version."

    def refuse(host: str, port: int, allow: bool) -> None:
        raise RuntimeError(text)

    asked: list[tuple[str, int]] = []

    def server_version(host: str, port: int) -> str:
        asked.append((host, port))
        return "25.1"

    monkeypatch.setattr(hf2li_module, "data_server_session", refuse)
    monkeypatch.setattr(hf2li_module, "server_labone_version", server_version)
    with pytest.raises(InstrumentError, match=r'runs LabOne 25\.1,.*pip install "zhinst-core==25\.1\.\*"') as err:
        open_hf2_session("bench-pc", 8005)
    assert asked == [("bench-pc", 8005)] and "allow_version_mismatch = true" in str(err.value)


@pytest.mark.parametrize(
    ("text", "pin"),
    [
        (
            "ZIAPIVersionMismatchException with status code: 32780 - Connection invalid. Extended information: "
            "Version mismatch detected. The server is at LabOne version '24.10.1' but the client is at LabOne "
            "version '26.07.2'. Please update the LabOne data-server to the newer version.",
            "zhinst-core==24.10.*",
        ),
        (
            "The server version is too old. The server runs on version '25.1' but the client runs on version "
            "'26.07'. Please update the LabOne Software.",
            "zhinst-core==25.1.*",
        ),
        (
            "Incompatible server version. Please ensure the client and server run on the same LabOne version.",
            None,
        ),
    ],
)
def test_every_refusal_text_is_explained(text: str, pin: str | None) -> None:
    msg = version_mismatch_message("bench-pc", 8005, text)
    assert msg is not None and f"zhinst-core is {zhinst.core.__version__}" in msg
    assert (f'pip install "{pin}"' in msg) if pin else "<X.Y of the server's LabOne>.*" in msg
    assert version_mismatch_message("bench-pc", 8005, "Unable to connect socket") is None
