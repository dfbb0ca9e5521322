"""analyze() on synthetic run files with known answers (equations in each test), written with RunWriter."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from qmg_lab.analysis.compute import analyze
from qmg_lab.analysis.render import render_table
from tests.support.synthetic_runs import (
    ALPHA,
    BETA,
    DITHER_LEAK_V,
    DWELL,
    F_D,
    FS,
    N_PAIRS,
    RATE,
    SETTLE,
    SF0,
    SIGMA_O,
    T_PRE,
    _config,
    _lockin,
    _writer,
    square,
    temperature,
    write_linearity,
    write_sweep,
)


def expected_pairs() -> tuple[np.ndarray, np.ndarray]:
    """Pair-mean temperatures and the true relative SF change vs pair 0 (SF linear in T, T linear in t)."""
    temps = []
    for k in range(N_PAIRS):
        a = T_PRE + 2 * k * DWELL
        wp = (a + SETTLE, a + DWELL)
        wm = (a + DWELL + SETTLE, a + 2 * DWELL)
        temps.append(0.5 * (temperature(sum(wp) / 2) + temperature(sum(wm) / 2)))
    temps = np.array(temps)
    sf = 1 + ALPHA * (temps - 25)
    return temps, (sf / sf[0] - 1) * 1e6


def test_sweep_recovers_sf_changes_tempco_and_clsf_accuracy(tmp_path: Path) -> None:
    p = tmp_path / "sweep.h5"
    write_sweep(p)
    r = analyze(p)
    temps, e = expected_pairs()
    assert r.n_step_pairs == N_PAIRS and r.status == "completed"
    assert r.missing_steps == [{"index": 2 + 2 * N_PAIRS, "kind": "return"}]  # the writer skips the return step
    # noise: mean of 25200 samples of 1e-4 V -> 6.3e-7 V; SF difference / 10 deg/s / 0.06 -> 1.5 ppm per pair
    tol_ppm = 6 * math.sqrt(2) * SIGMA_O / math.sqrt((DWELL - SETTLE) * FS) / (2 * RATE) / SF0 * 1e6
    got = np.array([q.true_change_ppm for q in r.pairs])
    np.testing.assert_allclose(got, e, atol=tol_ppm)
    assert r.sf_true_change_ppm == pytest.approx(np.ptp(e), abs=2 * tol_ppm)
    assert r.sf_measured_v_per_dps == pytest.approx(SF0 * (1 + ALPHA * (temps[0] - 25)), rel=tol_ppm * 1e-6)
    assert r.sf_tempco_ppm_per_c == pytest.approx(ALPHA * 1e6 / (1 + ALPHA * (temps[0] - 25)), abs=1.0)
    # CLSF estimate (ALPHA + BETA) dT re-referenced to pair 0; its error vs the true change:
    s = (ALPHA + BETA) * (temps - 25)
    c = ((1 + s) / (1 + s[0]) - 1) * 1e6
    d = (c - e)[1:]
    assert r.clsf_accuracy_rms_ppm == pytest.approx(np.sqrt(np.mean(d**2)), abs=tol_ppm + 1.0)
    assert r.clsf_accuracy_rms_ppm_mean_removed == pytest.approx(
        np.sqrt(np.mean((d - d.mean()) ** 2)), abs=tol_ppm + 1.0
    )
    assert r.truth_check_rms_ppm is not None and r.truth_check_rms_ppm < tol_ppm
    js = r.to_json()
    json.dumps(js)  # valid JSON (no NaN)
    for key in (
        "sf_nominal_v_per_dps",
        "n_step_pairs",
        "sf_true_change_ppm",
        "clsf_accuracy_rms_ppm",
        "clsf_accuracy_rms_ppm_mean_removed",
        "adev",
        "truth_check_rms_ppm",
    ):
        assert key in js
    assert js["sf_nominal_v_per_dps"] == 0.06
    assert {"tau_s", "ppm", "ppm_low", "ppm_high"} <= set(js["adev"][0])
    render_table(r)


def test_hardware_file_without_truth(tmp_path: Path) -> None:
    p = tmp_path / "hw.h5"
    write_sweep(p, pairs_written=3, truth=False)
    r = analyze(p)
    assert r.mode == "hardware" and r.truth_check_rms_ppm is None and r.n_step_pairs == 3
    assert r.to_json()["truth_check_rms_ppm"] is None


def test_killed_file_is_analysed_and_names_missing_steps(tmp_path: Path) -> None:
    p = tmp_path / "killed.h5"
    code = (
        f"import sys; sys.path[:0] = [{str(Path(__file__).parents[2])!r}]\n"
        f"from pathlib import Path\nfrom tests.support.synthetic_runs import write_sweep\n"
        f"write_sweep(Path({str(p)!r}), pairs_written=3, kill=True)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], timeout=60)
    assert proc.returncode == -signal.SIGKILL
    r = analyze(p)
    assert r.status == "running" and r.steps_planned == 2 + 2 * N_PAIRS + 1
    assert r.steps_completed == 2 + 6 and r.n_step_pairs == 3
    assert [m["index"] for m in r.missing_steps] == list(range(8, 2 + 2 * N_PAIRS + 1))
    assert r.missing_steps[-1]["kind"] == "return" and r.missing_steps[0]["kind"] == "rate"
    assert any("not closed" in n for n in r.notes)


# ---- Allan deviation and gyro noise -----------------------------------------------------------------------------


def test_adev_of_white_clsf_and_rate_noise(tmp_path: Path) -> None:
    """White noise of per-sample sigma at rate fs: sigma(tau) = sigma / sqrt(tau fs)."""
    rng = np.random.default_rng(3)
    fs_l, fd, dur = 200.0, 5.0, 1600.0
    sig_c = 300e-6  # CLSF per-period sigma (dimensionless)
    sig_r = 0.01  # per-period rate-output sigma, deg/s
    p = tmp_path / "allan.h5"
    w = _writer(p, _config("allan", 60.0, 1.0, "correct", fs_l, fd), ["hold"], truth=False)
    t = np.arange(int(dur * fs_l)) / fs_l
    _lockin(w, t, SF0 * 0.01 * rng.standard_normal(t.shape[0]), fd)
    tc = np.arange(1, int(dur * fd) + 1) / fd
    s = sig_c * rng.standard_normal(tc.shape[0])
    g = np.exp(1e-4 * np.cumsum(rng.standard_normal(tc.shape[0])) * 0 + 0.01 * tc / dur)
    w.append(
        "clsf",
        time=tc,
        eta=1 / (1 + s) - 1,
        sf_change_estimate=s,
        gain_correction=g,
        rate_output_mean=SF0 * sig_r * rng.standard_normal(tc.shape[0]),
    )
    w.append_step(
        index=0, kind="hold", t_start=0.0, t_end=dur, table_rate=0.0, chamber_setpoint=25.0, status="completed"
    )
    w.set_status("completed")
    w.close()
    r = analyze(p)
    taus = np.array([a["tau_s"] for a in r.adev])
    dev = np.array([a["value"] for a in r.adev])
    expect = sig_c * 1e6 / np.sqrt(taus * fd)
    half_width = np.array([(a["high"] - a["low"]) / 2 for a in r.adev])  # 68 % interval: ~1 sigma
    assert np.all(np.abs(dev - expect) <= 3 * half_width)
    assert np.all(half_width[1:] >= half_width[:-1] * dev[1:] / dev[:-1] * 0.99)  # fewer clusters, wider
    np.testing.assert_allclose(dev[:6], expect[:6], rtol=0.1)
    assert r.adev_at_60s_ppm == pytest.approx(sig_c * 1e6 / math.sqrt(60 * fd), rel=0.35)  # edf ~ 27
    assert r.adev_gain_correction  # correct mode: drift removed by g_c analysed too
    # ARW: sigma(1 s) = sig_r / sqrt(fd) deg/s -> x 3600 deg/h -> / 60 deg/sqrt(h)
    assert r.arw_deg_per_rt_h == pytest.approx(sig_r / math.sqrt(fd) * 3600 / 60, rel=0.1)
    # white rate noise alone has no flat part: its Allan deviation still falls at the longest tau, so the
    # bias-instability floor is not resolved (IEEE 952 reads B on the flat part, min / 0.664)
    gy = r.gyro_adev_deg_per_h
    assert np.argmin([x["value"] for x in gy]) == len(gy) - 1
    assert math.isnan(r.bias_instability_deg_per_h)


def test_bias_instability_is_read_at_the_floor_when_the_curve_turns_up() -> None:
    """White rate noise sigma_w plus a rate random walk K: sigma(tau)^2 = sigma_w^2/tau + K^2 tau/3, a minimum
    at tau* = sqrt(3) sigma_w / K inside the record; B = sigma_min / 0.664 is read there."""
    from qmg_lab.analysis.adev import bias_instability_deg_per_h, overlapping_adev

    rng = np.random.default_rng(11)
    fs, n = 10.0, 200_000  # 20000 s at 10 Hz
    sigma_w, k = 1.0, 0.01  # deg/h/sqrt(Hz), deg/h/sqrt(s)
    y = sigma_w * math.sqrt(fs) * rng.standard_normal(n) + k * np.cumsum(rng.standard_normal(n)) / math.sqrt(fs)
    res = overlapping_adev(y, fs)
    b = bias_instability_deg_per_h(res)
    floor = math.sqrt(2 * sigma_w * k / math.sqrt(3))  # sigma at tau*: sigma_w^2/tau* + K^2 tau*/3
    assert b == pytest.approx(floor / 0.664, rel=0.25)
    assert b == pytest.approx(float(np.min(res.dev)) / 0.664)


# ---- FTR characterization ---------------------------------------------------------------------------------------

FB = 2.0  # first-order FTR bandwidth, Hz


@pytest.mark.parametrize("truth", [True, False])
def test_bandwidth_phase_and_settling_of_a_first_order_loop(tmp_path: Path, truth: bool) -> None:
    rng = np.random.default_rng(5)
    freqs = [0.5, 1.0, 1.5, 2.0, 3.0, 5.0]
    amp, settle, dwell = 5.0, 1.0, 6.0
    kinds = ["rate", "return"] + [f"sine:{f:.3f}Hz" for f in freqs]
    extra = f"bandwidth_frequencies_hz = {freqs}\nbandwidth_amplitude_dps = {amp}"
    p = tmp_path / "bw.h5"
    w = _writer(p, _config("bandwidth", dwell, settle, extra=extra), kinds, truth)
    tau = 1 / (2 * math.pi * FB)
    t_now, idx = 0.0, 0
    # a quiet second, then the rate step 0 -> 5 deg/s and the return to rest
    t = np.arange(0, round(FS)) / FS
    _lockin(w, t, 0 * t)
    t_now = 1.0
    for rate_from, rate_to in ((0.0, amp), (amp, 0.0)):
        t = np.arange(round(t_now * FS), round((t_now + dwell) * FS)) / FS
        y = rate_to + (rate_from - rate_to) * np.exp(-(t - t_now) / tau)
        _lockin(w, t, SF0 * y + DITHER_LEAK_V * square(t))
        if truth:
            w.append("truth", time=t, scale_factor=SF0 + 0 * t, temperature=25 + 0 * t, rate=rate_to + 0 * t)
        w.append_step(
            index=idx,
            kind=kinds[idx],
            t_start=t_now,
            t_end=t_now + dwell,
            table_rate=rate_to,
            chamber_setpoint=25.0,
            status="completed",
        )
        idx, t_now = idx + 1, t_now + dwell
    for f in freqs:
        dur = 10 / f + max(settle, 2 / f) + 2 / f
        t = np.arange(round(t_now * FS), round((t_now + dur) * FS)) / FS
        h = 1 / (1 + 1j * f / FB)
        omega = amp * np.sin(2 * np.pi * f * (t - t_now))
        y = amp * abs(h) * np.sin(2 * np.pi * f * (t - t_now) + np.angle(h))
        _lockin(w, t, SF0 * y + DITHER_LEAK_V * square(t) + 1e-4 * rng.standard_normal(t.shape[0]))
        if truth:
            w.append("truth", time=t, scale_factor=SF0 + 0 * t, temperature=25 + 0 * t, rate=omega)
        w.append_step(
            index=idx,
            kind=kinds[idx],
            t_start=t_now,
            t_end=t_now + dur,
            table_rate=amp,
            chamber_setpoint=25.0,
            status="completed",
        )
        idx, t_now = idx + 1, t_now + dur
    w.set_status("completed")
    w.close()
    r = analyze(p)
    assert len(r.bode) == len(freqs)
    for b in r.bode:
        h = 1 / (1 + 1j * b.frequency_hz / FB)
        assert b.amplitude_ratio == pytest.approx(abs(h), rel=0.01)
        assert b.phase_deg == pytest.approx(math.degrees(np.angle(h)), abs=1.0)
    # -3.01 dB of a first-order loop is FB; linear interpolation in (log f, dB) between 1.5 and 2 Hz
    assert r.bandwidth_hz == pytest.approx(FB, rel=0.02)
    # 2 % settling of exp(-t/tau) seen through a centred one-dither-period boxcar (width W):
    # the boxcar scales the tail by sinh(x)/x, x = W/(2 tau) -> t_s = tau ln(50 sinh(x)/x)
    x = (1 / F_D) / (2 * tau)
    assert r.settling_time_s == pytest.approx(tau * math.log(50 * math.sinh(x) / x), abs=2 / FS)


def test_linearity_of_a_quadratic_response(tmp_path: Path) -> None:
    """O = SF r + B + k r^2 on r = -5..5 deg/s: residual max 15 k (at +-5, mean r^2 = 10), asymmetry 10 k / SF."""
    k = 2e-5  # V/(deg/s)^2
    p = tmp_path / "lin.h5"
    write_linearity(p, k)
    lin = analyze(p).linearity
    assert lin["sf_v_per_dps"] == pytest.approx(SF0, rel=1e-9)
    assert lin["bias_v"] == pytest.approx(1e-3 + 10 * k, rel=1e-6)
    assert lin["nonlinearity_max_pct_fs"] == pytest.approx(100 * 15 * k / (SF0 * 5), rel=1e-6)
    assert lin["asymmetry_ppm"] == pytest.approx(10 * k / SF0 * 1e6, rel=1e-6)
