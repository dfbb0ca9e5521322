"""Whole simulated campaigns through the real CLI, checked against the physics and the file contract.

Each campaign runs once per module in a subprocess (`python -m qmg_lab run ... --sim`), exactly as a user runs it.
Expected numbers are computed here, independently of qmg_lab.analysis.compute, from the raw datasets of the contract:
true SF from each +-5 deg/s pair, SF = (mean O+ - mean O-)/(Omega+ - Omega-) (IEEE 1431), and the twin's /truth.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import allantools
import h5py
import numpy as np
import pytest
from scipy.integrate import trapezoid
from scipy.optimize import brentq

from qmg_lab.budget.sweep import DETERMINISTIC_OFF, sim_lines

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "configs" / "paper_campaign.toml"
ADEV = ROOT / "configs" / "clsf_adev.toml"


def qmg(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", *args], capture_output=True, text=True, cwd=ROOT, timeout=600
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"qmg-lab {' '.join(args)} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc


IDEAL_SIM_LINES = sim_lines(DETERMINISTIC_OFF)


def config_with(tmp: Path, base: Path, sim_lines: str, name: str) -> Path:
    lines = base.read_text(encoding="utf-8").splitlines()
    at = [i for i, line in enumerate(lines) if line.split("#")[0].strip() == "[sim]"]
    assert len(at) == 1, "the configuration must have one [sim] section"
    lines.insert(at[0] + 1, sim_lines)
    text = "\n".join(lines) + "\n"
    path = tmp / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def zero_residual_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper campaign on the twins with every deterministic accuracy source off (the ideal electronics:
    no pickoff-ratio drift, no mode split, no Q or damping drift, no forcer cubic, no feedthrough, no table
    ripple); only the noise remains."""
    tmp = tmp_path_factory.mktemp("paper0")
    cfg = config_with(tmp, PAPER, IDEAL_SIM_LINES, "paper0.toml")
    out = tmp / "run.h5"
    qmg("run", str(cfg), "--sim", "-o", str(out), "-q")
    return out


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper campaign as shipped (the twin's documented default non-idealities)."""
    out = tmp_path_factory.mktemp("paper") / "run.h5"
    qmg("run", str(PAPER), "--sim", "-o", str(out), "-q")
    return out


def _mean(t: np.ndarray, y: np.ndarray, a: float, b: float) -> float:
    m = (t >= a) & (t < b)
    assert m.any(), f"no samples in [{a}, {b})"
    return float(y[m].mean())


def _mean_over_dither_periods(t: np.ndarray, y: np.ndarray, d: np.ndarray, a: float, b: float) -> float:
    """Mean of y over whole dither periods inside [a, b]: from the first to the last rising mid-level crossing of
    the recorded dither d (linearly interpolated, at least one sample inside), y integrated with the trapezoid
    rule between them. A period is a non-integer number of samples, so whole periods are cut in time."""
    mid = 0.5 * (d.max() + d.min())
    k = np.flatnonzero((d[1:] >= mid) & (d[:-1] < mid))
    edges = t[k] + (mid - d[k]) / (d[k + 1] - d[k]) * (t[k + 1] - t[k])
    dt = float(np.median(np.diff(t)))
    e = edges[(edges >= a + dt) & (edges <= b - dt)]
    assert e.size >= 2, f"no whole dither period in [{a}, {b}]"
    grid = np.concatenate(([e[0]], t[(t > e[0]) & (t < e[-1])], [e[-1]]))
    return float(trapezoid(np.interp(grid, t, y), grid) / (e[-1] - e[0]))


def step_pairs(path: Path, settle_s: float = 5.0) -> dict[str, np.ndarray]:
    """Per +-rate pair: table SF, mean CLSF estimate, mean true SF and mean gyro temperature."""
    with h5py.File(path, "r") as f:
        st = f["steps"]
        kinds = [k.decode() for k in st["kind"][:]]
        ts, te, rate = st["t_start"][:], st["t_end"][:], st["table_rate"][:]
        lt, ro, dith = f["lockin/time"][:], f["lockin/rate_output"][:], f["lockin/dither"][:]
        ct, cs = f["clsf/time"][:], f["clsf/sf_change_estimate"][:]
        tt, tsf, ttemp = f["truth/time"][:], f["truth/scale_factor"][:], f["truth/temperature"][:]
        tab_t, tab_cmd = f["table/time"][:], f["table/rate_command"][:]
    rows = [i for i, k in enumerate(kinds) if k == "rate"]
    out: dict[str, list[float]] = {k: [] for k in ("sf", "clsf", "truth", "temp")}
    for a, b in zip(rows[0::2], rows[1::2], strict=False):
        # commanded rates as the file's /table records them during each dwell
        w_a = _mean(tab_t, tab_cmd, ts[a] + settle_s, te[a])
        w_b = _mean(tab_t, tab_cmd, ts[b] + settle_s, te[b])
        assert (w_a, w_b) == (rate[a], rate[b])
        o_a = _mean_over_dither_periods(lt, ro, dith, ts[a] + settle_s, te[a])
        o_b = _mean_over_dither_periods(lt, ro, dith, ts[b] + settle_s, te[b])
        out["sf"].append((o_a - o_b) / (w_a - w_b))
        out["clsf"].append(_mean(ct, cs, ts[a] + settle_s, te[b]))
        out["truth"].append(_mean(tt, tsf, ts[a] + settle_s, te[b]))
        out["temp"].append(_mean(tt, ttemp, ts[a] + settle_s, te[b]))
    return {k: np.asarray(v) for k, v in out.items()}


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# ------------------------------------------------------------------------------------------------ contract


ROOT_ATTRS = (
    "format",
    "created",
    "t0_unix",
    "software_version",
    "mode",
    "config_toml",
    "config_sha256",
    "status",
    "abort_reason",
)
CONTRACT = {
    "lockin": ("time", "x_sense", "y_sense", "rate_output", "drive_amplitude", "drive_frequency", "dither"),
    "clsf": ("time", "eta", "sf_change_estimate", "gain_correction"),
    "table": ("time", "rate_command", "rate_measured", "position"),
    "chamber": ("time", "setpoint", "temperature"),
    "steps": ("index", "kind", "t_start", "t_end", "table_rate", "chamber_setpoint", "status"),
    "truth": ("time", "scale_factor", "temperature", "rate"),
}


def test_paper_run_writes_every_contract_item(zero_residual_run: Path) -> None:
    with h5py.File(zero_residual_run, "r") as f:
        for a in ROOT_ATTRS:
            assert a in f.attrs, a
        assert f.attrs["format"] == "qmg-lab/2" and f.attrs["mode"] == "sim" and f.attrs["status"] == "completed"
        for group, cols in CONTRACT.items():
            for c in cols:
                ds = f[group][c]
                assert ds.ndim == 1 and ds.chunks is not None and ds.maxshape == (None,), f"{group}/{c}"
                assert "units" in ds.attrs, f"{group}/{c} has no units"
            if "time" in cols:
                t = f[group]["time"][:]
                assert np.all(np.diff(t) >= 0), f"{group}/time not monotonic"
        # /lockin at the configured 1800 Sa/s as the HF2 twin streams it (whole 210 MHz ticks), gap-free
        dt = np.diff(f["lockin/time"][:])
        assert np.allclose(dt, round(210e6 / 1800) / 210e6, rtol=1e-9)
        # every planned step present once, completed
        idx = f["steps/index"][:]
        assert sorted(idx) == list(range(int(f.attrs["planned_steps"])))
        assert set(f["steps/status"][:]) == {b"completed"}


# ------------------------------------------------------------------------------------------------ tracking


def clsf_pair_noise() -> float:
    """The CLSF estimate's noise over one pair's two windows, from the noise budget (observe mode, white level q
    summed over the sources, docs/noise-budget.md): q / sqrt(T), T = 2 (dwell - settle); relative to the first
    pair, whose own error enters every difference, sqrt(2) times that."""
    from qmg_lab.budget.noise import noise_budget
    from qmg_lab.config.schema import load_config

    cfg, _ = load_config(PAPER)
    q = math.sqrt(sum(src.white_ppm_rt_s**2 for src in noise_budget(cfg, sim_blocks=True).sources)) * 1e-6
    return math.sqrt(2.0) * q / math.sqrt(2.0 * (cfg.plan.dwell_s - cfg.plan.settle_s))


def test_clsf_tracks_true_sf_change_without_residual_drift(zero_residual_run: Path) -> None:
    p = step_pairs(zero_residual_run)
    true_rel = p["truth"] / p["truth"][0] - 1
    clsf_rel = (1 + p["clsf"]) / (1 + p["clsf"][0]) - 1
    # the sweep really moved the SF: forcer tempco -1000 ppm/degC over ~9 degC of gyro temperature
    assert np.ptp(true_rel) > 7000e-6
    # within the estimate's own noise (the budget's, ~35 ppm here); a 1 % sensitivity error would add 87 ppm
    assert rms(clsf_rel - true_rel) <= 1.5 * clsf_pair_noise()


def test_table_step_sf_agrees_with_truth_within_50_ppm(zero_residual_run: Path) -> None:
    p = step_pairs(zero_residual_run)
    sf_rel = p["sf"] / p["sf"][0] - 1
    true_rel = p["truth"] / p["truth"][0] - 1
    assert rms(sf_rel - true_rel) <= 50e-6
    # absolute: the table's +60 ppm rate scale error is inside what the table steps measure
    assert p["sf"][0] / p["truth"][0] - 1 == pytest.approx(0.0, abs=150e-6)


def test_paper_campaign_accuracy_is_the_budgets(paper_run: Path) -> None:
    """The shipped campaign's CLSF accuracy, computed here from the raw datasets (CLSF change minus the table-step
    SF change, pair by pair), is what qmg_lab.budget.sweep predicts from the configuration: within 15 % of the
    prediction plus 10 ppm (the budget's model error, tests/integration/test_sweep_budget.py, plus the per-pair
    noise of the CLSF and of two 55 s table windows, about 10 ppm). The prediction itself is of the paper's 350 ppm
    order."""
    from qmg_lab.budget.sweep import sweep_accuracy
    from qmg_lab.config.schema import load_config

    budget = sweep_accuracy(load_config(PAPER)[0])
    p = step_pairs(paper_run)
    sf_rel = p["sf"] / p["sf"][0] - 1
    clsf_rel = (1 + p["clsf"]) / (1 + p["clsf"][0]) - 1
    err = (clsf_rel - sf_rel)[1:] * 1e6
    assert len(p["sf"]) == len(budget.pair_errors_ppm)
    assert rms(err) == pytest.approx(budget.total_ppm, rel=0.15, abs=10.0)
    assert rms(err - np.array(budget.pair_errors_ppm[1:])) <= 0.15 * budget.total_ppm + 10.0
    assert 350 / 1.5 <= budget.total_ppm <= 350 * 1.5


# ------------------------------------------------------------------------------------------------ analysis


def test_analysis_agrees_with_independent_computation(zero_residual_run: Path, tmp_path: Path) -> None:
    proc = qmg("analyze", str(zero_residual_run), "--json", "--figures", str(tmp_path / "figs"))
    res = json.loads(proc.stdout)
    p = step_pairs(zero_residual_run)
    sf_rel = p["sf"] / p["sf"][0] - 1
    clsf_rel = (1 + p["clsf"]) / (1 + p["clsf"][0]) - 1
    assert res["n_step_pairs"] == len(p["sf"])
    # accuracy: CLSF vs table-step SF over the pairs after the reference pair
    mine = rms((clsf_rel - sf_rel)[1:])
    assert res["clsf_accuracy_rms_ppm"] == pytest.approx(mine * 1e6, rel=0.05, abs=2.0)
    assert res["truth_check_rms_ppm"] <= 50.0
    assert res["sf_true_change_ppm"] == pytest.approx(np.ptp(sf_rel) * 1e6, rel=0.02)
    assert res["sf_nominal_v_per_dps"] == pytest.approx(0.06)
    for row in res["adev"]:
        assert row["ppm_low"] <= row["ppm"] <= row["ppm_high"]
    pngs = sorted((tmp_path / "figs").glob("*.png"))
    assert len(pngs) >= 6
    assert all(p.stat().st_size > 10_000 for p in pngs)


# ------------------------------------------------------------------------------------------------ characterization


def test_characterize_bandwidth_is_two_hertz() -> None:
    res = json.loads(qmg("characterize", "bandwidth", str(PAPER), "--sim", "--json").stdout)
    assert res["bandwidth_hz"] == pytest.approx(2.0, abs=0.1)
    # the critically damped sense PIs (qmg_lab/campaign/loops.py): step response 1 - e^{-pt} (1 - p t) with
    # p = 2 pi 2 Hz / sqrt(3 + sqrt 10), within 2 % after p t = x, e^{-x} (x - 1) = 0.02: 1.07 s (paper: 0.5 s)
    x = brentq(lambda v: math.exp(-v) * (v - 1) - 0.02, 3.0, 20.0)
    p = 2 * math.pi * 2.0 / math.sqrt(3 + math.sqrt(10))
    assert res["settling_time_s"] == pytest.approx(x / p, abs=0.05)


def test_characterize_linearity_measures_the_scale_factor() -> None:
    """The level sweep's fitted SF is the twin's true SF times the table's +60 ppm scale error (the rates are the
    commands); the nonlinearity against the budget: tests/integration/test_sweep_budget.py."""
    res = json.loads(qmg("characterize", "linearity", str(PAPER), "--sim", "--json").stdout)
    assert res["sf_v_per_dps"] == pytest.approx(0.06 * (1 + 60e-6), rel=100e-6)


# ------------------------------------------------------------------------------------------------ Allan deviation


@pytest.mark.slow
def test_clsf_correct_mode_allan_deviation_is_the_budgets(tmp_path: Path) -> None:
    """Fig. 7 on the twins: CLSF correcting for 3 h. The Allan deviation of the CLSF estimate and of the twin's
    self-calibrated SF (1 s means of /truth) at 60 s and 2000 s against what `qmg-lab budget --sim` predicts from
    the same configuration (docs/noise-budget.md). Tolerances: at 60 s +-25 % (edf ~ 260 from 3 h: 3 sigma is
    13 %); at 2000 s the chi-squared 0.5 %/99.5 % band of its few degrees of freedom (edf ~ 6)."""
    from scipy.stats import chi2

    budget = json.loads(qmg("budget", str(ADEV), "--json", "--sim").stdout)
    out = tmp_path / "adev.h5"
    qmg("run", str(ADEV), "--sim", "-o", str(out), "-q")
    with h5py.File(out, "r") as f:
        t0 = float(f["steps/t_end"][list(f["steps/kind"][:]).index(b"soak")])
        tt, sf = f["truth/time"][:], f["truth/scale_factor"][:]
        ct, ce = f["clsf/time"][:], f["clsf/sf_change_estimate"][:]
    keep = tt >= t0
    sec = np.floor(tt[keep] - tt[keep][0]).astype(np.int64)  # whole seconds, at whatever rate the HF2 streams
    counts = np.bincount(sec)
    per_s = (np.bincount(sec, weights=sf[keep]) / np.maximum(counts, 1))[counts >= 0.9 * np.median(counts)]
    taus = np.array([60.0, 2000.0])
    truth = allantools.oadev(per_s / per_s.mean() - 1, rate=1.0, data_type="freq", taus=taus)[1]
    k = ct >= t0
    est = allantools.oadev(ce[k], rate=1.0 / float(np.median(np.diff(ct[k]))), data_type="freq", taus=taus)[1]
    n = int(np.count_nonzero(k))
    edf = allantools.edf_greenhall(alpha=0, d=2, m=2000 * 7, N=n, overlapping=True, modified=False)
    low, high = math.sqrt(chi2.ppf(0.005, edf) / edf), math.sqrt(chi2.ppf(0.995, edf) / edf)
    for name, measured, predicted in (
        ("estimate", est, budget["adev_ppm"]),
        ("self-calibrated SF", truth, budget["adev_self_calibrated_sf_ppm"]),
    ):
        assert measured[0] * 1e6 == pytest.approx(predicted["60"], rel=0.25), (name, measured, predicted)
        assert low <= measured[1] * 1e6 / predicted["2000"] <= high, (name, measured, predicted, low, high)
