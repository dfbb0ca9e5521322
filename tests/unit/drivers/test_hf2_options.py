"""The HF2LI as it is: with and without the MF option, without PLL or PID, a safe state that survives a refused
node, LabOne version refusals and reconnects. Through the real zhinst-toolkit Session over the HF2 twin.

Where the expected instrument facts come from (independent of the driver and the twin's tables):
* node names, types, read/write properties and enumerated options: zhinst-toolkit's bundled
  resources/nodedoc_hf2.json (read here directly);
* which instances exist (EXPECTED_INDICES): zhinst-toolkit's recorded HF2 node list
  (tests/data/list_nodes_hf2_dev.txt of its repository: 6 demods, 6 oscillators and mixer channels 0..7 with MF,
  2 PLLs, 4 AuxOuts, 2 inputs and outputs) and, without MF, 2 oscillators and mixer channels 6 and 7 only (the
  public qudi-iqo-modules HF2 driver's recorded dev1492; zhinst-utils default_output_mixer_channel); 4 PIDs of the
  HF2-PID option (HF2 user manual);
* the version refusal text: zhinst-core's ZIAPIVersionMismatchException as quoted in zhinst-toolkit issue #294.
"""

from __future__ import annotations

import fnmatch
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zhinst.core
from zhinst.toolkit import Session

import drivers.hf2li as hf2li_module
from drivers.hf2_nodes import MissingOptionError
from drivers.hf2li import HF2LI, version_mismatch_message
from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config
from qmg_lab.instruments import InstrumentError
from qmg_lab.station import hf2_wiring
from sims.hf2_loops import identify_loops
from sims.hf2_nodetree import NodeError, nodedoc_path
from sims.hf2_server import HF2DataServerTwin
from tests.support.twin_params import hf2_twin_settings, paper_gyro_params, paper_world

MF = ("MF", "PLL", "PID")
NON_MF = ("PLL", "PID")
EXPECTED_INDICES: dict[tuple[str, ...], dict[str, tuple[int, ...]]] = {
    MF: {
        "demods": tuple(range(6)),
        "oscs": tuple(range(6)),
        "plls": (0, 1),
        "pids": tuple(range(4)),
        "sigins": (0, 1),
        "sigouts": (0, 1),
        "mixer": tuple(range(8)),
        "auxouts": tuple(range(4)),
        "auxins": (0,),
        "values": (0, 1),
    },
}
EXPECTED_INDICES[NON_MF] = {**EXPECTED_INDICES[MF], "oscs": (0, 1), "mixer": (6, 7)}
MIXER_LEAVES = ("enables", "amplitudes", "waveforms")
# zhinst-core's refusal, as zhinst-toolkit issue #294 quotes it (the versions here are ours)
REFUSAL = (
    "ZIAPIVersionMismatchException with status code: 32780 - Connection invalid. Extended information: Version "
    "mismatch detected. The server is at LabOne version '24.10.1' but the client is at LabOne version '{client}'. "
    "Please update the LabOne data-server to the newer version."
)


class RecordingTwin(HF2DataServerTwin):
    """The twin, recording every device node path the driver sets (with the value) or reads."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sets: list[tuple[str, Any]] = []
        self.reads: list[str] = []
        self.refuse: set[str] = set()  # paths whose set the "instrument" refuses (a failing node)

    def set(self, path: Any, value: Any = None, **kwargs: Any) -> None:
        pairs = [(path, value)] if value is not None else list(path)
        for p, _ in pairs:
            if p.lower() in self.refuse:
                raise NodeError(f"ZIAPIWriteException: node {p} refused the write")
        self.sets.extend((p.lower(), v) for p, v in pairs)
        super().set(path, value, **kwargs)

    def getInt(self, path: str) -> int:
        self.reads.append(path.lower())
        return super().getInt(path)

    def getDouble(self, path: str) -> float:
        self.reads.append(path.lower())
        return super().getDouble(path)

    def getString(self, path: str) -> str:
        self.reads.append(path.lower())
        return super().getString(path)

    def get(self, paths: str, *args: Any, **kwargs: Any) -> dict:
        self.reads.append(paths.lower())
        return super().get(paths, *args, **kwargs)


def bare_twin(options: tuple[str, ...], cfg: Config | None = None) -> HF2DataServerTwin:
    """The HF2 twin with `options`, wired as `cfg` (default: the default configuration) says."""
    wiring = hf2_wiring(cfg or Config())
    return HF2DataServerTwin(
        paper_world(), paper_gyro_params(), seed=3, wiring=wiring, **hf2_twin_settings(options=options)
    )


def make_twin(options: tuple[str, ...], cfg: Config | None = None) -> tuple[Config, RecordingTwin]:
    cfg = (cfg or Config()).model_copy(update={"sim": Config().sim.model_copy(update={"hf2_options": list(options)})})
    return cfg, RecordingTwin(
        paper_world(), paper_gyro_params(), seed=3, wiring=hf2_wiring(cfg), **hf2_twin_settings(options=options)
    )


def driver_on(twin: HF2DataServerTwin, cfg: Config) -> HF2LI:
    return HF2LI(Session("localhost", hf2=True, connection=twin), "dev1234", cfg.lockin)


def nodedoc() -> dict[str, dict[str, Any]]:
    return {k.lower(): v for k, v in json.loads(nodedoc_path().read_text(encoding="utf-8")).items()}


def generic(path: str) -> tuple[str, dict[str, list[int]]]:
    """/dev1234/sigouts/1/enables/6 -> (/devxxxx/sigouts/n/enables/n, {"sigouts": [1], "mixer": [6]})."""
    parts = path.lower().split("/")[2:]
    indices: dict[str, list[int]] = {}
    out = ["", "devxxxx"]
    for i, part in enumerate(parts):
        if part.isdigit() or part == "*":
            branch = "mixer" if parts[i - 1] in MIXER_LEAVES else parts[i - 1]
            if part != "*":
                indices.setdefault(branch, []).append(int(part))
            out.append("n")
        else:
            out.append(part)
    return "/".join(out), indices


def exercise(li: HF2LI, cfg: Config) -> None:
    """Everything the driver does on a campaign: identify, configure, stream, poll, read state, safe state."""
    li.identify()
    li.configure(lockin_setup(cfg))
    li.set_forcer_gain(1.5)
    li.start_stream()
    li.poll(0.05)
    li.stream_timing()
    li.pll_locked()
    li.state()
    li.snapshot()
    li.safe_state()
    li.reconnect()


@pytest.mark.parametrize("options", [MF, NON_MF], ids=["MF", "no-MF"])
def test_every_node_the_driver_touches_exists_with_the_nodedoc_type_and_options(options: tuple[str, ...]) -> None:
    cfg, twin = make_twin(options)
    exercise(driver_on(twin, cfg), cfg)
    doc, expected = nodedoc(), EXPECTED_INDICES[options]
    touched = {p for p, _ in twin.sets} | set(twin.reads)
    device_paths = sorted(p for p in touched if p.startswith("/dev1234/"))
    assert len(device_paths) > 80  # the whole configuration went through the recorder
    for path in device_paths:
        key, indices = generic(path)
        assert key in doc, f"{path}: no {key} in zhinst-toolkit's nodedoc_hf2.json"
        for branch, found in indices.items():
            assert set(found) <= set(expected[branch]), f"{path}: {branch} {found} not on an HF2LI with {options}"
    for path, value in twin.sets:
        entry = doc[generic(path)[0]]
        assert "Write" in entry["Properties"], f"{path} is read-only in the nodedoc"
        kind, opts = entry["Type"], entry.get("Options")
        if kind.startswith("Integer"):
            assert float(value) == int(value), f"{path} = {value!r}: the nodedoc says Integer"
            if opts and entry.get("Unit") != "bit-coded":
                assert float(value) in {float(o) for o in opts}, f"{path} = {value!r} not in {sorted(opts)}"
        else:
            assert kind == "Double" and isinstance(value, float | int), f"{path} = {value!r} ({kind})"
    for path in twin.reads:
        if path.startswith("/dev1234/"):
            assert "Read" in doc[generic(path)[0]]["Properties"], f"{path} is not readable in the nodedoc"


def test_without_mf_the_drive_and_forcer_use_mixer_channels_6_and_7() -> None:
    cfg, twin = make_twin(NON_MF)
    li = driver_on(twin, cfg)
    li.configure(lockin_setup(cfg))
    g, d = twin.getInt, "/dev1234"
    assert (li.layout.drive, li.layout.forcer) == (6, 7)
    assert g(f"{d}/sigouts/0/enables/6") == 1 and g(f"{d}/sigouts/1/enables/7") == 1
    assert g(f"{d}/sigouts/0/enables/7") == 0 and g(f"{d}/sigouts/1/enables/6") == 0
    assert g(f"{d}/pids/0/outputchannel") == 6  # the AGC writes the drive channel's amplitude
    assert twin.getDouble(f"{d}/sigouts/1/amplitudes/7") == 0.5  # nominal carrier, gain 1
    state = li.state()
    assert state["options"] == ["PLL", "PID"] and state["mixer_channels"] == {"drive": 6, "forcer": 7}
    assert state["devtype"] == "HF2LI"
    plan = identify_loops(twin.nodes, twin.wiring)
    assert plan.open_reasons == {} and plan.settings.forcer_gain == 1.0


def test_a_configured_mixer_channel_overrides_the_derived_one_and_an_absent_one_is_refused() -> None:
    cfg = Config().model_copy(update={"lockin": Config().lockin.model_copy(update={"forcer_mixer_channel": 3})})
    cfg, twin = make_twin(MF, cfg)
    li = driver_on(twin, cfg)
    li.configure(lockin_setup(cfg))
    assert li.layout.forcer == 3 and twin.getInt("/dev1234/sigouts/1/enables/3") == 1
    assert twin.getInt("/dev1234/demods/3/oscselect") == twin.getInt("/dev1234/plls/0/oscselect")
    _, bare = make_twin(NON_MF)  # the MF channel 3 does not exist without MF: refused at connect, named
    with pytest.raises(InstrumentError, match=r"forcer_mixer_channel = 3 is not a mixer channel.*6, 7"):
        driver_on(bare, cfg)


@pytest.mark.parametrize(
    ("options", "missing"),
    [(("MF", "PID"), "the HF2LI lacks the PLL option"), (("MF", "PLL"), "lacks the PID option"), ((), "PLL and PID")],
)
def test_a_lockin_without_pll_or_pid_is_refused_naming_the_option(options: tuple[str, ...], missing: str) -> None:
    cfg = Config()
    twin = bare_twin(options, cfg)
    with pytest.raises(MissingOptionError, match=missing):
        driver_on(twin, cfg)


def test_cli_instruments_exits_3_naming_the_missing_option(tmp_path: Path) -> None:
    path = tmp_path / "no_pid.toml"
    path.write_text('[sim]\nhf2_options = ["MF", "PLL"]\n', encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "instruments", str(path), "--sim"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 3, (proc.stdout, proc.stderr)
    said = " ".join(proc.stderr.split())  # the console wraps long lines
    assert "lacks the PID option" in said and "Traceback" not in said


def test_safe_state_applies_every_other_node_when_one_is_refused_and_names_it() -> None:
    cfg, twin = make_twin(MF)
    li = driver_on(twin, cfg)
    li.configure(lockin_setup(cfg))
    li.start_stream()
    twin.refuse = {"/dev1234/auxouts/0/offset"}
    with pytest.raises(InstrumentError, match=r"auxouts/0/offset = 0\.0.*refused") as err:
        li.safe_state()
    assert "the other nodes were set" in str(err.value)
    g = twin.getInt
    assert [g(f"/dev1234/pids/{n}/enable") for n in range(4)] == [0, 0, 0, 0]
    assert g("/dev1234/sigouts/0/on") == 0 and g("/dev1234/sigouts/1/on") == 0
    assert twin.getDouble("/dev1234/sigouts/1/amplitudes/1") == 0.0
    assert twin.getDouble("/dev1234/auxouts/1/offset") == 0.0 and g("/dev1234/auxouts/1/outputselect") == -1
    assert not twin.subscribed  # the stream was stopped first
    twin.refuse = set()
    li.safe_state()  # nothing refused: one transaction, no error


def test_version_refusal_names_both_versions_and_both_ways_out() -> None:
    client = zhinst.core.__version__
    msg = version_mismatch_message("bench-pc", 8005, REFUSAL.format(client=client))
    assert msg is not None
    assert "LabOne 24.10.1" in msg and f"zhinst-core is {client}" in msg
    assert 'pip install "zhinst-core==24.10.*"' in msg and "allow_version_mismatch = true" in msg
    assert version_mismatch_message("bench-pc", 8005, "Unable to connect socket") is None


class FakeServerSessions:
    """Stands in for drivers.hf2li.data_server_session, i.e. Session(host, port, hf2=True,
    allow_version_mismatch=...) on a bench: each call is one new data-server connection, here a real Session over
    the twin. Records the calls; refuses like zhinst-core when told the server runs another LabOne version."""

    def __init__(self, twin: HF2DataServerTwin, server_version: str | None = None) -> None:
        self.twin, self.server_version = twin, server_version
        self.calls: list[dict[str, Any]] = []

    def __call__(self, host: str, port: int, allow_version_mismatch: bool) -> Session:
        self.calls.append({"host": host, "port": port, "allow": allow_version_mismatch})
        if self.server_version is not None and not allow_version_mismatch:
            raise RuntimeError(REFUSAL.format(client=zhinst.core.__version__).replace("24.10.1", self.server_version))
        return Session(host, port, hf2=True, connection=self.twin)


def test_a_refused_connection_is_an_instrument_error_with_the_message(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg, twin = make_twin(MF)
    sessions = FakeServerSessions(twin, server_version="23.06.1")
    monkeypatch.setattr(hf2li_module, "data_server_session", sessions)
    with pytest.raises(InstrumentError, match=r'runs LabOne 23\.06\.1.*pip install "zhinst-core==23\.6\.\*"'):
        HF2LI("bench-pc", "dev1234", cfg.lockin, port=8005)
    li = HF2LI("bench-pc", "dev1234", cfg.lockin, port=8005, allow_version_mismatch=True)
    assert sessions.calls[-1] == {"host": "bench-pc", "port": 8005, "allow": True}
    assert li.state()["devtype"] == "HF2LI"


def test_reconnect_on_hardware_opens_a_new_data_server_session(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg, twin = make_twin(NON_MF)
    sessions = FakeServerSessions(twin)
    monkeypatch.setattr(hf2li_module, "data_server_session", sessions)
    li = HF2LI("bench-pc", "dev1234", cfg.lockin, port=8005)
    li.configure(lockin_setup(cfg))
    first = li._session
    twin.set("/dev1234/sigouts/0/on", 0)  # what a power cycle of the outputs would leave
    li.reconnect()
    assert len(sessions.calls) == 2 and li._session is not first
    assert twin.getInt("/dev1234/sigouts/0/on") == 1  # the configuration was re-applied on the new session


def test_twin_lists_exactly_the_option_dependent_branches() -> None:
    for options, expected in EXPECTED_INDICES.items():
        twin = bare_twin(options)
        twin.connectDevice("dev1234")
        nodes = [n.lower() for n in twin.listNodes("/dev1234", recursive=True, leavesonly=True)]
        for leaf in MIXER_LEAVES:
            got = {int(m.rsplit("/", 1)[1]) for m in fnmatch.filter(nodes, f"/dev1234/sigouts/0/{leaf}/*")}
            assert got == set(expected["mixer"]), (options, leaf)
        oscs = {int(re.match(r"/dev1234/oscs/(\d+)/", p).group(1)) for p in nodes if p.startswith("/dev1234/oscs/")}
        assert oscs == set(expected["oscs"])
    no_pid = bare_twin(("MF", "PLL"))
    no_pid.connectDevice("dev1234")
    listed = no_pid.listNodes("/dev1234", recursive=True, leavesonly=True)
    assert not [p for p in listed if "/PIDS/" in p.upper()] and [p for p in listed if "/PLLS/" in p.upper()]
    assert no_pid.getString("/dev1234/features/options") == "MF\nPLL"
