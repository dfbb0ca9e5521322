"""The compiled loops of the HF2 twin's poll (sims/hf2_kernel.py) against the equations of its module docstring
written as numpy array expressions (a sequential cumulative sum, numpy's floor-modulo, the AuxIn window mean, noise
drawn as one (2, n) array, rounding to the ADC step and clipping), with the AuxIn noise drawn as the twin draws it.

These are compared exactly, and need no library to agree with another: every step is an elementwise IEEE
operation (correctly rounded: the same operation on the same operands gives the same number anywhere), a
cumulative sum (an accumulate, one order by definition), a floating-point remainder (exact), floor and clip, or
the same generator's draws."""

from __future__ import annotations

import numpy as np
import pytest

from sims import hf2_kernel as hk

CLOCKBASE_HZ = 210e6
TICKS_PER_SAMPLE = 116667  # the 1800 Sa/s rung on a 210 MHz clockbase
DT = TICKS_PER_SAMPLE / CLOCKBASE_HZ
N = 3600


@pytest.mark.parametrize("harmonic", [1, 2, 3])
def test_oscillator_phases_are_the_cumulative_sum_and_floor_modulo(harmonic: int) -> None:
    rng = np.random.default_rng(4)
    f = 2200.0 + np.cumsum(rng.normal(0.0, 1e-3, N))  # a PLL oscillator wandering around 2.2 kHz
    phase0 = 5.9
    ref = phase0 + 2 * np.pi * np.cumsum(f) * DT
    ref_wrapped = np.mod(ref * harmonic if harmonic != 1 else ref, 2 * np.pi)
    ph, wrapped = np.empty(N), np.empty(N)
    hk.oscillator_phases(f, phase0, DT, float(harmonic), ph, wrapped)
    np.testing.assert_array_equal(ph, ref)
    np.testing.assert_array_equal(wrapped, ref_wrapped)
    assert np.all((wrapped >= 0.0) & (wrapped < 2 * np.pi))
    # f = 2200 Hz for 2 s: the phase has turned 4400 cycles, less the wander's share
    assert ph[-1] - phase0 == pytest.approx(2 * np.pi * np.sum(f) * DT, rel=1e-14)


def test_sample_times_are_whole_ticks_and_their_seconds() -> None:
    ticks0 = 7 * 10**11 + 12345  # about an hour into a campaign at 210 MHz
    ts, t = np.empty(N, dtype=np.uint64), np.empty(N)
    hk.sample_times(ticks0, TICKS_PER_SAMPLE, CLOCKBASE_HZ, ts, t)
    ref = (ticks0 + TICKS_PER_SAMPLE * np.arange(1, N + 1, dtype=np.int64)).astype(np.uint64)
    np.testing.assert_array_equal(ts, ref)
    np.testing.assert_array_equal(t, ref.astype(float) / CLOCKBASE_HZ)
    assert np.all(np.diff(ts.astype(np.int64)) == TICKS_PER_SAMPLE)


def _auxin_reference(
    v: np.ndarray,
    previous: float,
    factor: float,
    dither: np.ndarray,
    rng: np.random.Generator,
    sigma: float,
    lsb: float,
    r: float,
) -> np.ndarray:
    both = np.empty((2, v.shape[0]))
    rate = both[0]
    rate[1:] = v[1:] - v[:-1]
    rate[0] = v[0] - previous
    rate *= factor
    both[0] = v - rate
    both[1] = dither
    if sigma > 0.0:
        noise = rng.standard_normal(both.shape)
        noise *= sigma
        both += noise
    if lsb > 0.0:
        both /= lsb
        both += 0.5
        np.floor(both, out=both)
        both *= lsb
        np.clip(both, -r, r, out=both)
    return both


@pytest.mark.parametrize(("sigma", "bits"), [(1e-4, 16), (0.0, 16), (1e-4, 0), (0.01, 8)])
def test_auxin_readings_are_the_window_mean_noise_adc_and_clip(sigma: float, bits: int) -> None:
    signal = np.random.default_rng(5)
    v = np.cumsum(signal.normal(0.0, 0.05, N))  # an AuxOut wandering past the +-R = 1 V range (clipped)
    dither = np.where(np.arange(N) % 257 < 128, 0.3, -0.3)
    r = 1.0
    lsb = 2.0 * r / 2.0**bits if bits else 0.0
    factor = (2.5e-6) / (2.0 * DT)  # one 400 kSa/s AuxIn ADC sample in a 1800 Sa/s step
    seed = np.random.SeedSequence(1, spawn_key=(7,))
    ref_rng, rng = (np.random.Generator(np.random.PCG64(seed)) for _ in range(2))
    ref = _auxin_reference(v, 0.123, factor, dither, ref_rng, sigma, lsb, r)
    normals = np.full((2, N), np.nan)  # as the twin draws them: into its reused buffer, only with noise on
    if sigma > 0.0:
        rng.standard_normal(out=normals)
    out = np.empty((2, N))
    hk.auxin_readings(v, 0.123, factor, dither, normals, sigma, lsb, r, out)
    np.testing.assert_array_equal(out, ref)
    # both drew the same 2 n numbers (or none): the next block continues the same stream
    assert rng.standard_normal() == ref_rng.standard_normal()
    if bits:
        assert np.max(np.abs(out)) == r  # the wandering AuxOut was clipped at the range
        np.testing.assert_array_equal(np.round(out / lsb), out / lsb)  # every reading is a whole ADC step


def test_auxin_window_mean_of_a_ramp_is_its_value_half_a_window_back() -> None:
    """Ideal ADC, no noise: the mean of a linear AuxOut over [t - W, t] is V(t - W/2)."""
    slope_v_per_s = 3.0
    v = slope_v_per_s * DT * np.arange(1, N + 1)
    w = 2.5e-6
    out = np.empty((2, N))
    hk.auxin_readings(v, 0.0, w / (2.0 * DT), np.zeros(N), np.zeros((2, N)), 0.0, 0.0, 10.0, out)
    np.testing.assert_allclose(out[0], v - slope_v_per_s * w / 2.0, rtol=0.0, atol=1e-15)
    np.testing.assert_array_equal(out[1], 0.0)
