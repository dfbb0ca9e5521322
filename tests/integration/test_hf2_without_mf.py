"""A campaign on an HF2LI without the MF option: `qmg-lab run CONFIG --sim` with `[sim] hf2_options = ["PLL", "PID"]`
completes, the driver drives mixer channels 6 and 7, locks oscillator 2 (which channel 7 runs on in the twin, as
the HF2 manual has it) to the drive with PLL 2, and the results match the MF run within noise.

The two runs share the seed, so the twin's noise is the same realisation in both and only the instrument's option
set differs. The tolerance is nevertheless the noise the comparison would have with independent realisations, so
that the test states what "match" means: per +-rate pair, the CLSF estimate's mean over the pair's two windows has
the white noise q / sqrt(T) (q from the noise budget, docs/noise-budget.md; T = 2 (dwell - settle)); the difference
of two such means is within 4 sqrt(2) q / sqrt(T) (4 sigma). A wrong mixer channel is far outside: a forcer carrier
on a channel the output does not use opens the rate loop (no lock, or an SF off by 100 %), and a 1 % carrier
amplitude error shifts the estimate by 1e4 ppm.

The analysis's CLSF accuracy (RMS over the pairs of the estimate's error against the truth) of the two runs then
differs by at most the same bound: |rms(a) - rms(b)| <= rms(a - b) <= max |a_i - b_i| (triangle inequality), and
the truth is the same in both runs (same seed, same world), so a_i - b_i is the difference of the pair means.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "configs" / "paper_campaign.toml"
SHORT_PLAN = {  # the paper campaign cut to a few minutes of simulated time: 25 -> 26 degC, 20 s dwells
    "chamber_end_c": "26.0",
    "chamber_ramp_c_per_min": "0.5",
    "chamber_soak_s": "30.0",
    "chamber_end_hold_s": "60.0",
    "dwell_s": "20.0",
}


def short_config(tmp: Path, options: list[str] | None, lockin_line: str = "") -> Path:
    text = PAPER.read_text(encoding="utf-8")
    for key, value in SHORT_PLAN.items():
        text, n = re.subn(rf"(?m)^{key}\s*=\s*[^#\n]*", f"{key} = {value} ", text)
        assert n == 1, key
    if options is not None:
        text, n = re.subn(r"(?m)^(\[sim\][^\n]*)$", rf"\1\nhf2_options = {json.dumps(options)}", text)
        assert n == 1
    if lockin_line:
        text, n = re.subn(r"(?m)^(\[lockin\][^\n]*)$", rf"\1\n{lockin_line}", text)
        assert n == 1
    name = "short_" + ("_".join(options) if options else "mf") + ("_edited" if lockin_line else "") + ".toml"
    (tmp / name).write_text(text, encoding="utf-8")
    return tmp / name


def run(cfg: Path, out: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "run", str(cfg), "--sim", "-o", str(out), "-q"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert proc.returncode == 0, (proc.stdout, proc.stderr)


def pair_means(path: Path, settle_s: float) -> np.ndarray:
    """Mean CLSF SF-change estimate over each +-rate pair's two windows (after settle_s in each)."""
    with h5py.File(path, "r") as f:
        assert f.attrs["status"] == "completed"
        kinds = [k.decode() for k in f["steps/kind"][:]]
        ts, te = f["steps/t_start"][:], f["steps/t_end"][:]
        ct, cs = f["clsf/time"][:], f["clsf/sf_change_estimate"][:]
    rows = [i for i, k in enumerate(kinds) if k == "rate"]
    means = []
    for a, b in zip(rows[0::2], rows[1::2], strict=False):
        m = (ct >= ts[a] + settle_s) & (ct < te[b])
        assert m.any()
        means.append(float(cs[m].mean()))
    return np.asarray(means)


def lockin_snapshot(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        snaps = f["snapshots"]
        names = [n.decode() for n in snaps["instrument"][:]]
        raw = bytes(snaps["json"][:])
        at = names.index("lockin")
        start, length = int(snaps["offset"][at]), int(snaps["length"][at])
    return json.loads(raw[start : start + length].decode())


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("hf2_options")
    mf, no_mf = tmp / "mf.h5", tmp / "no_mf.h5"
    run(short_config(tmp, None), mf)
    run(short_config(tmp, ["PLL", "PID"]), no_mf)
    return mf, no_mf


def test_the_run_without_mf_used_mixer_channels_6_and_7(runs: tuple[Path, Path]) -> None:
    mf, no_mf = runs
    state = lockin_snapshot(no_mf)["state"]
    assert state["options"] == ["PLL", "PID"] and state["mixer_channels"] == {"drive": 6, "forcer": 7}
    assert lockin_snapshot(mf)["state"]["mixer_channels"] == {"drive": 0, "forcer": 1}


def test_the_forcer_without_mf_ran_on_oscillator_2_locked_by_pll_2(runs: tuple[Path, Path]) -> None:
    mf, no_mf = runs
    carriers = lockin_snapshot(no_mf)["state"]["carriers"]
    assert carriers["forcer_oscillator"] == 1 and carriers["tracking_plls"] == [1]
    pll2 = lockin_snapshot(no_mf)["state"]["tracking_plls"]["1"]
    assert pll2["enable"] == 1 and pll2["oscselect"] == 1
    assert lockin_snapshot(mf)["state"]["carriers"]["tracking_plls"] == []


def test_results_without_mf_match_the_mf_run_within_noise(runs: tuple[Path, Path]) -> None:
    from qmg_lab.budget.noise import noise_budget
    from qmg_lab.config.schema import load_config

    cfg, _ = load_config(PAPER)
    settle = cfg.plan.settle_s
    q = math.sqrt(sum(s.white_ppm_rt_s**2 for s in noise_budget(cfg, sim_blocks=True).sources)) * 1e-6
    tolerance = 4.0 * math.sqrt(2.0) * q / math.sqrt(2.0 * (float(SHORT_PLAN["dwell_s"]) - settle))
    mf, no_mf = (pair_means(p, settle) for p in runs)
    assert len(mf) == len(no_mf) >= 3
    assert np.max(np.abs(no_mf - mf)) <= tolerance, (no_mf - mf, tolerance)
    assert tolerance < 1e-3  # the bound is tight enough to see a 0.1 % carrier error


def test_a_driver_that_leaves_oscillator_2_alone_is_stopped_at_the_clsf_reference(tmp_path: Path) -> None:
    # the driver is told channel 7 runs on PLL 1's oscillator, so it neither sets nor locks oscillator 2: in the
    # twin (channel 7 on oscillator 2, as the manual has it) the forcer carrier exerts no force, so the dither
    # (which enters the forcer path) does not come through. The CLSF reference rho_0, the forcer path's gain, is
    # then far below the plant gain b = k R_d / SF the loops were designed on (qmg_lab.campaign.loops.
    # forcer_path_problem), and the campaign stops there in words (exit 3, safe state, the file kept) instead of
    # reading an SF change of -95 % for the whole run.
    from qmg_lab.campaign.loops import rate_plant
    from qmg_lab.config.schema import load_config

    wrong = tmp_path / "wrong.h5"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "qmg_lab",
            "run",
            str(short_config(tmp_path, ["PLL", "PID"], "fixed_channel_oscillators = [0, 0]")),
            "--sim",
            "-o",
            str(wrong),
            "-q",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    words = proc.stdout + proc.stderr
    assert proc.returncode == 3, words
    assert "the forcer does not act as configured" in words and "safe state" in words, words
    assert lockin_snapshot(wrong)["state"]["carriers"]["tracking_plls"] == []
    b = rate_plant(load_config(PAPER)[0].device).b
    with h5py.File(wrong, "r") as f:
        assert f.attrs["status"] == "aborted"
        assert f.attrs["clsf_reference"] / b < 0.5
        assert [k.decode() for k in f["steps/kind"][:]].count("rate") == 0  # stopped before the table moved


def test_the_analysis_accuracy_without_mf_matches_the_mf_run_within_the_same_bound(runs: tuple[Path, Path]) -> None:
    from qmg_lab.analysis.compute import analyze
    from qmg_lab.budget.noise import noise_budget
    from qmg_lab.config.schema import load_config

    cfg, _ = load_config(PAPER)
    q = math.sqrt(sum(s.white_ppm_rt_s**2 for s in noise_budget(cfg, sim_blocks=True).sources))  # ppm sqrt(s)
    tolerance_ppm = 4.0 * math.sqrt(2.0) * q / math.sqrt(2.0 * (float(SHORT_PLAN["dwell_s"]) - cfg.plan.settle_s))
    mf, no_mf = (analyze(p).to_json() for p in runs)
    assert mf["n_step_pairs"] == no_mf["n_step_pairs"] >= 3
    a, b = mf["clsf_accuracy_rms_ppm"], no_mf["clsf_accuracy_rms_ppm"]
    assert a is not None and b is not None
    assert abs(a - b) <= tolerance_ppm, (a, b, tolerance_ppm)
