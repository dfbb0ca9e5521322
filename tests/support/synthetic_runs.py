"""Synthetic run files with known answers, written with the real RunWriter: a temperature sweep whose SF,
CLSF estimate and temperatures follow stated equations (used by the analysis and report tests, and by a
subprocess that is killed while writing one)."""

from __future__ import annotations

import math
import os
import signal
import textwrap
from pathlib import Path

import numpy as np

from qmg_lab.campaign.pipeline import new_run_file
from qmg_lab.campaign.plan import checked_plan
from qmg_lab.config.schema import parse_config
from qmg_lab.storage.writer import RunWriter

FS = 1400.0
F_D = 7.0
SF0 = 0.06  # V per deg/s
DITHER_LEAK_V = 0.08  # square wave at 7 Hz leaking into the rate output (removed by whole-period means)


def _config(
    kind: str,
    dwell: float,
    settle: float,
    mode: str = "observe",
    rate_hz: float = FS,
    dither_hz: float = F_D,
    extra: str = "",
) -> str:
    return textwrap.dedent(f"""
        [campaign]
        kind = "{kind}"
        [clsf]
        mode = "{mode}"
        [dither]
        frequency_hz = {dither_hz}
        [lockin]
        demod_rate_hz = {rate_hz}
        [plan]
        dwell_s = {dwell}
        settle_s = {settle}
        {extra}
    """)


def _writer(path: Path, config: str, planned_kinds: list[str], truth: bool) -> RunWriter:
    """A new run file made as every run file is made (qmg_lab.campaign.pipeline.new_run_file): on the twins (with
    /truth) or on the bench, with the plan `planned_kinds` written here."""
    cfg = parse_config(config)
    cfg = cfg.with_all_sim() if truth else cfg
    w = new_run_file(path, cfg, config, checked_plan(cfg), t0_unix=1.7e9, software_version="test")
    w.set_plan(len(planned_kinds), planned_kinds)
    return w


def square(t: np.ndarray, f_hz: float = F_D, fs: float = FS) -> np.ndarray:
    """+-1 square wave of frequency f_hz sampled at sample index k = t fs (exact integer arithmetic at the edges)."""
    k = np.round(np.asarray(t) * fs)
    return np.where(np.floor(k * 2 * f_hz / fs) % 2 == 0, 1.0, -1.0)


def _lockin(w: RunWriter, t: np.ndarray, rate_output: np.ndarray, dither_hz: float = F_D) -> None:
    # the same sample rate the callers' leak terms use (a rate from np.diff carries rounding that moves an edge
    # that falls exactly on a sample to the next one, so the recorded dither and the leak would disagree)
    fs = round(1.0 / float(np.median(np.diff(t))), 6) if t.shape[0] > 1 else FS
    sq = square(t, dither_hz, fs)
    z = np.zeros_like(t)
    w.append(
        "lockin",
        time=t,
        x_sense=z,
        y_sense=z,
        rate_output=rate_output,
        drive_amplitude=z + 0.5,
        drive_frequency=z + 2200.0,
        dither=0.6 * sq,
        table_encoder=z,
        pll_locked=z + 1,
    )


# ---- the temperature sweep --------------------------------------------------------------------------------------

DWELL, SETTLE, N_PAIRS, RATE = 20.0, 2.0, 8, 5.0
ALPHA = -1000e-6  # true SF tempco, 1/degC
BETA = 50e-6  # what the (synthetic) CLSF gets wrong, 1/degC: its estimate follows (ALPHA + BETA)
SIGMA_O = 1e-4  # V per sample
T_PRE = 4.0  # lock + dither steps before the pairs


def temperature(t: np.ndarray | float) -> np.ndarray | float:
    """Chamber ramp 25 -> 35 degC over the pairs."""
    return 25.0 + 10.0 * np.clip((np.asarray(t) - T_PRE) / (2 * N_PAIRS * DWELL), 0.0, 1.0)


def write_sweep(path: Path, pairs_written: int = N_PAIRS, truth: bool = True, kill: bool = False) -> None:
    rng = np.random.default_rng(7)
    kinds = ["lock", "dither"] + ["rate"] * (2 * N_PAIRS) + ["return"]
    w = _writer(path, _config("temperature_sweep", DWELL, SETTLE), kinds, truth)
    steps = [(0, "lock", 0.0, 2.0, 0.0), (1, "dither", 2.0, 4.0, 0.0)]
    for k in range(2 * pairs_written):
        steps.append((2 + k, "rate", T_PRE + k * DWELL, T_PRE + (k + 1) * DWELL, RATE if k % 2 == 0 else -RATE))
    prev_rate = 0.0
    for index, kind, a, b, rate in steps:
        t = np.arange(round(a * FS), round(b * FS)) / FS
        temp = temperature(t)
        sf = SF0 * (1 + ALPHA * (temp - 25.0))
        omega = rate + (prev_rate - rate) * np.exp(-(t - a) / 0.08)  # the rate loop's first-order response
        out = sf * omega + 2e-3 + DITHER_LEAK_V * square(t) + SIGMA_O * rng.standard_normal(t.shape[0])
        _lockin(w, t, out)
        tc = np.arange(math.ceil(a * F_D), math.floor(b * F_D)) / F_D + 1 / F_D
        tc = tc[tc <= b]
        s = (ALPHA + BETA) * (temperature(tc) - 25.0) + 20e-6 * rng.standard_normal(tc.shape[0])
        w.append(
            "clsf",
            time=tc,
            eta=1 / (1 + s) - 1,
            sf_change_estimate=s,
            gain_correction=np.ones_like(tc),
            rate_output_mean=SF0 * rate + 0 * tc,
        )
        tt = np.arange(a + 0.5, b + 1e-9, 0.5)
        w.append("table", time=tt, rate_command=rate + 0 * tt, rate_measured=rate + 0 * tt, position=0 * tt)
        w.append("chamber", time=tt, setpoint=35.0 + 0 * tt, temperature=temperature(tt))
        if truth:
            w.append("truth", time=t, scale_factor=sf, temperature=temp, rate=omega)
        w.append_step(
            index=index, kind=kind, t_start=a, t_end=b, table_rate=rate, chamber_setpoint=35.0, status="completed"
        )
        prev_rate = rate
    if kill:
        w.flush()
        os.kill(os.getpid(), signal.SIGKILL)
    w.set_status("completed")
    w.close()


# ---- a linearity characterization ---------------------------------------------------------------------------

LIN_RATES = [float(r) for r in range(-5, 6)]
LIN_DWELL, LIN_SETTLE = 4.0, 1.0


def write_linearity(path: Path, k: float) -> None:
    """Level steps at LIN_RATES (deg/s), LIN_DWELL s each, output O = SF0 r + 1e-3 V + k r^2 (no noise)."""
    w = _writer(
        path,
        _config("linearity", LIN_DWELL, LIN_SETTLE, extra=f"linearity_rates_dps = {LIN_RATES}"),
        ["level"] * len(LIN_RATES),
        truth=False,
    )
    for i, r in enumerate(LIN_RATES):
        t = np.arange(round(i * LIN_DWELL * FS), round((i + 1) * LIN_DWELL * FS)) / FS
        _lockin(w, t, SF0 * r + 1e-3 + k * r * r + DITHER_LEAK_V * square(t))
        w.append(
            "table", time=t[::700], rate_command=r + 0 * t[::700], rate_measured=r + 0 * t[::700], position=0 * t[::700]
        )
        w.append_step(
            index=i,
            kind="level",
            t_start=i * LIN_DWELL,
            t_end=(i + 1) * LIN_DWELL,
            table_rate=r,
            chamber_setpoint=25.0,
            status="completed",
        )
    w.close()
