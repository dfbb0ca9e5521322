"""The pickoff-ratio model of the whole-SF calibration: the drive resonance as a thermometer of what CLSF cannot see.

CLSF tracks the forcer path; the scale factor also moves with the pickoff-gain ratio r = G_py/G_px, which the
dither cannot see (docs/physics.md section 6: (1 + s) = (SF/SF0)(r0/r)). The drive-mode resonance the PLL holds,
/lockin/drive_frequency, is an in-situ thermometer of the die (Prikhodko, Trusov, Shkel, Sensors and Actuators A,
2013). With x = f_drive - f_anchor (Hz) the model is

    ln r(t) = a1 x(t) + a2 x(t)^2 + b L_tau[x](t) + const

* a1 x: the parts of r at the die temperature (the electrodes and gaps; also the front end when its board follows
  the die), a2 x^2 a quadratic part;
* b L_tau[x]: a front end whose board lags the die by a first-order lag of time constant tau; L_tau is that lag
  applied to x, starting in equilibrium with the first sample (a run that begins after a soak).

The constant never matters: every estimate is a change against a reference. The calibrated SF change is

    1 + s_cal(t) = (1 + s(t)) exp(m(t) - m_ref),     m = a1 x + a2 x^2 + b L_tau[x]

with s the CLSF estimate (/clsf/sf_change_estimate) and m_ref the mean of m over CLSF's reference periods.

The coefficients come from a separate characterisation run (`qmg-lab characterize sf-model RUN -o model.json`):
its table step pairs give y_i = ln(1 + e_i) - ln(1 + c_i), e_i the table's SF change and c_i the CLSF's, and
y_i = k + a1 X1_i + a2 X2_i + b XL_i (X the means of x, x^2 and L_tau[x] over pair i's windows) is solved by
least squares for each tau of a grid (0 = no lag term), keeping the tau of the smallest residual variance per
degree of freedom. The evaluated run's table steps never enter: they only judge (qmg_lab/analysis/calibrated_sf.py).

Assumptions the model names (and `analyze` warns about when a run breaks them): the drive frequency depends on
the die temperature alone (no drift of f0 by ageing, charging or a changed drive amplitude between the runs); r
depends on the die and one lagging board only; the run's temperatures stay within the characterised range.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

MODEL_FORMAT = "qmg-lab/pickoff-model/1"
TAU_GRID_S: tuple[float, ...] = (0.0, *(float(v) for v in np.geomspace(20.0, 4000.0, 31)))
"""The front-end lags tried by the fit, s (0: no lag term); 4000 s covers the issue's 0-1200 s with margin."""
BIN_S = 1.0
"""The drive frequency is averaged over bins of this length before the lag filter (its noise averages down)."""


@dataclass(frozen=True)
class PickoffRatioModel:
    """ln(G_py/G_px) as a function of the drive frequency (module docstring); JSON on disk (`save`, `load`)."""

    anchor_hz: float  # x = f_drive - anchor_hz
    linear_per_hz: float  # a1
    quadratic_per_hz2: float  # a2
    lagged_per_hz: float  # b
    lag_tau_s: float  # tau (0: no lag term)
    residual_rms_ppm: float  # the characterisation fit's residual over its pairs
    n_pairs: int
    x_range_hz: tuple[float, float]  # the characterisation run's range of x (pair means)
    source: dict[str, Any] = field(default_factory=dict)  # run file, seed, campaign, temperatures: traceability

    def log_ratio(self, t_s: np.ndarray, f_hz: np.ndarray) -> np.ndarray:
        """m(t) = a1 x + a2 x^2 + b L_tau[x] at the samples (t_s increasing, s; f_hz the drive frequency)."""
        x = np.asarray(f_hz, dtype=np.float64) - self.anchor_hz
        m = self.linear_per_hz * x + self.quadratic_per_hz2 * x * x
        if self.lag_tau_s > 0.0 and self.lagged_per_hz != 0.0:
            m = m + self.lagged_per_hz * first_order_lag(np.asarray(t_s, dtype=np.float64), x, self.lag_tau_s)
        return m

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["x_range_hz"] = list(self.x_range_hz)
        return {"format": MODEL_FORMAT, **d}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n", encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> PickoffRatioModel:
        """Read a model file; ValueError naming what is wrong if it is not one."""
        try:
            d = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: not a readable pickoff-model file ({exc})") from exc
        if not isinstance(d, dict) or d.get("format") != MODEL_FORMAT:
            raise ValueError(f"{path}: not a pickoff-model file (format {MODEL_FORMAT!r} expected)")
        try:
            lo, hi = d["x_range_hz"]
            model = cls(
                anchor_hz=float(d["anchor_hz"]),
                linear_per_hz=float(d["linear_per_hz"]),
                quadratic_per_hz2=float(d["quadratic_per_hz2"]),
                lagged_per_hz=float(d["lagged_per_hz"]),
                lag_tau_s=float(d["lag_tau_s"]),
                residual_rms_ppm=float(d["residual_rms_ppm"]),
                n_pairs=int(d["n_pairs"]),
                x_range_hz=(float(lo), float(hi)),
                source=dict(d.get("source", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: pickoff-model file incomplete ({exc})") from exc
        values = (model.anchor_hz, model.linear_per_hz, model.quadratic_per_hz2, model.lagged_per_hz, model.lag_tau_s)
        if not all(math.isfinite(v) for v in values) or model.lag_tau_s < 0.0:
            raise ValueError(f"{path}: pickoff-model coefficients must be finite (and lag_tau_s >= 0)")
        return model


def first_order_lag(t_s: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """y' = (x - y)/tau from y(t_0) = x(t_0), stepped exactly for x linear between the samples (first-order hold):
    y_k = a y_(k-1) + (1 - a) x_(k-1) + (1 - tau (1 - a)/h)(x_k - x_(k-1)), a = e^(-h/tau), h = t_k - t_(k-1)."""
    y = np.empty_like(x)
    if x.size == 0:
        return y
    y[0] = x[0]
    if tau_s <= 0.0:
        return x.copy()
    h = np.diff(t_s)
    a = np.exp(-h / tau_s)
    ramp = 1.0 - tau_s * (1.0 - a) / np.where(h > 0.0, h, 1.0)
    ramp = np.where(h > 0.0, ramp, 0.0)
    # the recursion is a first-order IIR with varying coefficients: a plain loop over the (binned, ~1e4) samples
    yy = float(x[0])
    for k in range(1, x.shape[0]):
        yy = a[k - 1] * yy + (1.0 - a[k - 1]) * x[k - 1] + ramp[k - 1] * (x[k] - x[k - 1])
        y[k] = yy
    return y


def binned(t_s: np.ndarray, values: np.ndarray, bin_s: float = BIN_S) -> tuple[np.ndarray, np.ndarray]:
    """Means of `values` over consecutive bins of bin_s (empty bins dropped): (bin mean time, bin mean value)."""
    if t_s.size == 0:
        return t_s, values
    k = np.floor((t_s - t_s[0]) / bin_s).astype(np.int64)
    n = np.bincount(k)
    ok = n > 0
    tm = np.bincount(k, weights=t_s)[ok] / n[ok]
    vm = np.bincount(k, weights=values)[ok] / n[ok]
    return tm, vm


def window_means(t_s: np.ndarray, columns: np.ndarray, windows: list[list[tuple[float, float]]]) -> np.ndarray:
    """Mean of each column (rows: features, columns: samples at t_s) over each pair's windows: (pairs, features)."""
    out = np.full((len(windows), columns.shape[0]), np.nan)
    for i, wins in enumerate(windows):
        mask = np.zeros(t_s.shape[0], dtype=bool)
        for a, b in wins:
            mask |= (t_s >= a) & (t_s <= b)
        if mask.any():
            out[i] = columns[:, mask].mean(axis=1)
    return out


def features(t_s: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """The model's regressors at the samples: rows x, x^2 and L_tau[x] (only x, x^2 for tau = 0)."""
    rows = [x, x * x]
    if tau_s > 0.0:
        rows.append(first_order_lag(t_s, x, tau_s))
    return np.array(rows)


@dataclass(frozen=True)
class FitResult:
    model: PickoffRatioModel
    residuals_ppm: np.ndarray
    tau_scores: dict[float, float]  # tau -> residual variance per degree of freedom, ppm^2


def fit_pickoff_model(
    t_s: np.ndarray,
    f_hz: np.ndarray,
    windows: list[list[tuple[float, float]]],
    y: np.ndarray,
    *,
    source: dict[str, Any] | None = None,
    tau_grid_s: tuple[float, ...] = TAU_GRID_S,
) -> FitResult:
    """Least-squares fit of y_i = k + a1 X1_i + a2 X2_i + b XL_i (module docstring) over the pairs.

    t_s, f_hz: the (binned) drive frequency; windows[i]: pair i's analysis windows (s); y[i] = ln(1 + e_i) -
    ln(1 + c_i). ValueError if fewer pairs than parameters + 2."""
    y = np.asarray(y, dtype=np.float64)
    anchor = float(f_hz[0])
    x = np.asarray(f_hz, dtype=np.float64) - anchor
    scores: dict[float, float] = {}

    def solve(tau: float) -> tuple[float, np.ndarray, np.ndarray] | None:
        feats = window_means(t_s, features(t_s, x, tau), windows)
        ok = np.all(np.isfinite(feats), axis=1) & np.isfinite(y)
        a = np.column_stack([np.ones(int(ok.sum())), feats[ok]])
        if a.shape[0] < a.shape[1] + 2:
            return None
        # columns scaled to unit norm: x and L_tau[x] are nearly collinear for a small tau
        norms = np.linalg.norm(a, axis=0)
        norms[norms == 0.0] = 1.0
        coef, *_ = np.linalg.lstsq(a / norms, y[ok], rcond=None)
        coef = coef / norms
        res = y[ok] - a @ coef
        score = float(np.sum(res**2) / (a.shape[0] - a.shape[1])) * 1e12
        scores[tau] = score
        return score, coef, res

    grid = [(tau, r) for tau in tau_grid_s if (r := solve(tau)) is not None]
    if not grid:
        raise ValueError(f"{len(y)} step pairs: too few to fit the pickoff-ratio model (at least 6 needed)")
    k = min(range(len(grid)), key=lambda j: grid[j][1][0])
    tau, (score, coef, res) = grid[k]
    if tau > 0.0 and 0 < k < len(grid) - 1 and grid[k - 1][0] > 0.0:
        from scipy.optimize import minimize_scalar  # only the characterisation needs it

        lo, hi = math.log(grid[k - 1][0]), math.log(grid[k + 1][0])
        opt = minimize_scalar(lambda u: solve(math.exp(u))[0], bounds=(lo, hi), method="bounded")  # type: ignore[index]
        refined = solve(math.exp(float(opt.x)))
        if refined is not None and refined[0] < score:
            tau, (score, coef, res) = math.exp(float(opt.x)), refined
    pair_x = window_means(t_s, x[np.newaxis, :], windows)[:, 0]
    pair_x = pair_x[np.isfinite(pair_x)]
    model = PickoffRatioModel(
        anchor_hz=anchor,
        linear_per_hz=float(coef[1]),
        quadratic_per_hz2=float(coef[2]),
        lagged_per_hz=float(coef[3]) if tau > 0.0 else 0.0,
        lag_tau_s=float(tau),
        residual_rms_ppm=float(np.sqrt(np.mean(res**2)) * 1e6),
        n_pairs=int(res.shape[0]),
        x_range_hz=(float(pair_x.min()), float(pair_x.max())),
        source=dict(source or {}),
    )
    return FitResult(model, res * 1e6, scores)
