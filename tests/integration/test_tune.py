"""Device characterisation and tuning (issue 12): `qmg-lab tune CONFIG --sim -o tuned.toml` recovers the twin's
own constants when [sim] sets them away from the defaults, and the tuned configuration runs the paper campaign.

Targets (issue 12): f0 within 0.01 Hz, Q within 2 %, nominal SF within 100 ppm, for several parameter sets.
The expected values are the [sim] values the twin was given (its true f0, Q and SF at the reference
temperature), never earlier output; the [device] section starts at the defaults (2200 Hz, 1.2e6, 0.06 V/(deg/s)).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import h5py
import pytest

from qmg_lab.campaign.tuning import tune, tuned_config_text
from qmg_lab.config.schema import parse_config
from qmg_lab.station import build_station

ROOT = Path(__file__).resolve().parents[2]
TWINS = "[lockin]\nsim = true\n[generator]\nsim = true\n[table]\nsim = true\n[chamber]\nsim = true\n"


def qmg(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


@pytest.mark.parametrize(
    ("f0", "q", "drive_v", "sf", "seed"),
    [
        (2207.3, 9.0e5, 0.07, 0.055, 1),
        (2192.8, 1.5e6, 0.04, 0.065, 2),
        (2213.05, 6.0e5, 0.09, 0.048, 3),
    ],
)
def test_tune_recovers_the_twins_constants(f0: float, q: float, drive_v: float, sf: float, seed: int) -> None:
    cfg = parse_config(
        TWINS + f"[sim]\nseed = {seed}\nf0_hz = {f0}\nq_factor = {q}\ndrive_voltage_v = {drive_v}\n"
        f"sf_true_v_per_dps = {sf}\n"
    )
    station = build_station(cfg)
    try:
        result = tune(cfg, station)
    finally:
        station.close()
    dev = result.device_values()
    assert abs(dev["f0_hz"] - f0) <= 0.01
    assert dev["q_factor"] == pytest.approx(q, rel=0.02)
    assert abs(dev["sf_nominal_v_per_dps"] / sf - 1.0) <= 100e-6
    assert dev["drive_voltage_v"] == pytest.approx(drive_v, rel=0.02)


def test_tuned_config_text_keeps_the_rest_and_is_valid() -> None:
    text = "# my bench\n[device]\nf0_hz = 2200.0   # from the datasheet\nangular_gain = 0.8\n\n[plan]\ndwell_s = 30.0\n"
    tuned = tuned_config_text(text, {"f0_hz": 2207.3, "q_factor": 9.0e5}, ["measured"])
    data = tomllib.loads(tuned)
    assert data["device"] == {"f0_hz": 2207.3, "angular_gain": 0.8, "q_factor": 9.0e5}
    assert data["plan"] == {"dwell_s": 30.0}
    assert tuned.startswith("# my bench\n# measured\n[device]\n")
    assert "f0_hz = 2207.3  # tuned; was 2200.0 (from the datasheet)" in tuned
    parse_config(tuned)
    # no [device] section: one is appended
    assert tomllib.loads(tuned_config_text("[plan]\ndwell_s = 30.0\n", {"f0_hz": 2201.0}, None))["device"] == {
        "f0_hz": 2201.0
    }


def test_tune_cli_writes_a_configuration_that_runs_the_paper_campaign(tmp_path: Path) -> None:
    lines = (ROOT / "configs" / "paper_campaign.toml").read_text(encoding="utf-8").splitlines()
    at = [i for i, line in enumerate(lines) if line.split("#")[0].strip() == "[sim]"]
    lines.insert(at[0] + 1, "f0_hz = 2195.5\nq_factor = 1.0e6\ndrive_voltage_v = 0.06\nsf_true_v_per_dps = 0.058")
    cfg = tmp_path / "bench.toml"
    cfg.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tuned = tmp_path / "tuned.toml"
    proc = qmg("tune", str(cfg), "--sim", "-o", str(tuned), "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    device = tomllib.loads(tuned.read_text(encoding="utf-8"))["device"]
    assert device == report["device"] | {"angular_gain": 0.8, "max_forcer_v": 10.0}
    assert abs(device["f0_hz"] - 2195.5) <= 0.01
    assert device["q_factor"] == pytest.approx(1.0e6, rel=0.02)
    assert abs(device["sf_nominal_v_per_dps"] / 0.058 - 1) <= 100e-6
    # the same file again: refused without --overwrite
    again = qmg("tune", str(cfg), "--sim", "-o", str(tuned))
    assert again.returncode == 2 and "exists" in again.stderr
    run = tmp_path / "run.h5"
    proc = qmg("run", str(tuned), "--sim", "-o", str(run), "-q")
    assert proc.returncode == 0, proc.stderr
    with h5py.File(run, "r") as f:
        assert f.attrs["status"] == "completed"
        assert int(f.attrs["completed_steps"]) == int(f.attrs["planned_steps"])


def test_characterize_ringdown_and_noise_json(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    # one mode: a split (the twin's default 0.02 Hz at 20 deg) beats in the free decay, which the fit of
    # ln R = c - t/tau does not model (qmg_lab/campaign/tuning.py)
    cfg.write_text(
        "[device]\nq_factor = 9.0e5\n[sim]\nq_factor = 9.0e5\narw_deg_per_rt_h = 0.05\nfreq_mismatch_hz = 0.0\n",
        encoding="utf-8",
    )
    proc = qmg("characterize", "ringdown", str(cfg), "--sim", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["q_factor"] == pytest.approx(9.0e5, rel=0.02)
    proc = qmg("characterize", "noise", str(cfg), "--sim", "--json", "--record", "600")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["arw_deg_per_rt_h"] == pytest.approx(0.05, rel=0.25)
    bad = qmg("characterize", "noise", str(cfg), "--sim", "--record", "5")
    assert bad.returncode == 2 and "--record 5 s" in bad.stderr


def test_tune_without_lock_is_an_instrument_fault_in_the_safe_state(tmp_path: Path) -> None:
    """[device] f0 60 Hz away from the resonance: outside the PLL's range, the tune stops with exit 3."""
    cfg = tmp_path / "far.toml"
    cfg.write_text("[device]\nf0_hz = 2260.0\n[loops]\nlock_timeout_s = 20.0\n", encoding="utf-8")
    proc = qmg("tune", str(cfg), "--sim", "-o", str(tmp_path / "t.toml"))
    assert proc.returncode == 3, (proc.stdout, proc.stderr)
    text = " ".join(proc.stderr.split())
    assert "did not lock" in text and "safe state" in text and "Traceback" not in text
    assert not (tmp_path / "t.toml").exists()
