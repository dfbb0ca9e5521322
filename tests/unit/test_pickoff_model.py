"""The whole-SF calibration's pickoff-ratio model (qmg_lab/clsf/pickoff_model.py): the lag is the exact solution of
its differential equation, the fit recovers a known ratio law exactly when the data follow it, the file round-trips
and refuses what is not a model; the retired [sim] key names its successors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from qmg_lab.clsf.pickoff_model import (
    PickoffRatioModel,
    first_order_lag,
    fit_pickoff_model,
    window_means,
)
from qmg_lab.config.schema import ConfigError, parse_config

ROOT = Path(__file__).resolve().parents[2]


def test_lag_of_a_ramp_is_the_closed_form() -> None:
    # y' = (x - y)/tau, x = r t, y(0) = 0: y = r (t - tau (1 - e^(-t/tau))); the first-order hold is exact for it
    tau, r = 300.0, -2e-4
    t = np.sort(np.concatenate([np.arange(0.0, 3000.0, 1.0), [0.37, 12.9, 1500.5]]))  # uneven steps too
    y = first_order_lag(t, r * t, tau)
    # rounding only: a few ulps of |y| <= 0.6 per step, over 3003 steps: < 3003 * 4 * 2.2e-16 * 0.6 = 1.6e-12
    assert np.max(np.abs(y - r * (t - tau * (1.0 - np.exp(-t / tau))))) < 1.6e-12


def _path() -> tuple[np.ndarray, np.ndarray, list[list[tuple[float, float]]]]:
    """A drive-frequency path: hold, ramp down 0.8 Hz over 5000 s, hold; pairs of 120 s windows every 360 s."""
    t = np.arange(0.0, 8000.0, 1.0)
    x = -0.8 * np.clip((t - 300.0) / 5000.0, 0.0, 1.0)
    windows = [[(a + 60.0, a + 180.0), (a + 240.0, a + 360.0)] for a in np.arange(0.0, 7600.0, 360.0)]
    return t, 2200.0 + x, windows


@pytest.mark.parametrize("tau_true", [0.0, 300.0, 1200.0])
def test_fit_recovers_a_known_ratio_law(tau_true: float) -> None:
    a1, a2, b = -3e-4, 4e-5, -6e-4  # ln r per Hz, per Hz^2, per Hz of the lagged frequency
    t, f, windows = _path()
    x = f - f[0]
    m = a1 * x + a2 * x * x + (b * first_order_lag(t, x, tau_true) if tau_true > 0 else b * x)
    y = window_means(t, m[np.newaxis, :], windows)[:, 0] + 1.234e-3  # any constant: references drop it
    model = fit_pickoff_model(t, f, windows, y).model
    assert model.residual_rms_ppm < 1e-3
    got = model.log_ratio(t, f)
    # the law itself, not only the pairs: m(t) - m(0) everywhere on the path, to 0.01 ppm
    assert np.max(np.abs((got - got[0]) - (m - m[0]))) < 1e-8
    if tau_true > 0:
        assert model.lag_tau_s == pytest.approx(tau_true, rel=1e-3)
        assert model.lagged_per_hz == pytest.approx(b, rel=1e-3)
        assert model.linear_per_hz == pytest.approx(a1, rel=1e-3)
    assert model.quadratic_per_hz2 == pytest.approx(a2, rel=1e-3)


def test_too_few_pairs_is_refused() -> None:
    t, f, windows = _path()
    with pytest.raises(ValueError, match="too few"):
        fit_pickoff_model(t, f, windows[:4], np.zeros(4))


def test_model_file_round_trips_and_refuses_other_files(tmp_path: Path) -> None:
    model = PickoffRatioModel(2200.0, -1e-3, 2e-5, 3e-4, 250.0, 12.0, 20, (-0.8, 0.0), {"seed": 2})
    path = tmp_path / "m.json"
    model.save(path)
    assert PickoffRatioModel.load(path) == model
    path.write_text(json.dumps({"format": "something else"}), encoding="utf-8")
    with pytest.raises(ValueError, match="not a pickoff-model file"):
        PickoffRatioModel.load(path)
    path.write_text("{", encoding="utf-8")
    with pytest.raises(ValueError, match="not a readable"):
        PickoffRatioModel.load(path)


def test_retired_pickoff_key_names_its_successors() -> None:
    text = (ROOT / "configs" / "paper_campaign.toml").read_text(encoding="utf-8")
    text = text.replace("[sim]", "[sim]\npickoff_ratio_tempco_ppm_per_c = 60.0", 1)
    with pytest.raises(ConfigError) as exc:
        parse_config(text)
    for key in ("pickoff_electronics_tempco_ppm_per_c", "pickoff_transducer_tempco_ppm_per_c"):
        assert key in str(exc.value)


def test_budget_front_end_lag_follows_its_equation() -> None:
    """The budget's board temperature: the die temperature through one more first-order lag (exact for a ramp)."""
    from qmg_lab.budget.sweep import frontend_temperature_c, gyro_temperature_c

    cfg = parse_config((ROOT / "configs" / "paper_campaign.toml").read_text(encoding="utf-8"))
    t = np.arange(0.0, 3000.0, 1.0)
    die = gyro_temperature_c(cfg, t, 300.0)
    board = frontend_temperature_c(cfg, t, 300.0)
    tau = cfg.sim.frontend_thermal_tau_s
    ref = first_order_lag(t, die, tau)
    assert np.max(np.abs(board - ref)) < 1e-9
    assert math.isclose(board[0], die[0])


def test_characterize_sf_model_refuses_a_missing_run(tmp_path: Path) -> None:
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "qmg_lab", "characterize", "sf-model", str(tmp_path / "none.h5"), "-o", "m.json"],
        check=False,
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "no such run file" in " ".join(proc.stderr.split())  # rich wraps long lines
    assert "Traceback" not in proc.stderr
