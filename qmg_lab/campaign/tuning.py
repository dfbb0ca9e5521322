"""Device characterisation and tuning: measure the [device] constants instead of typing them in.

Measurements on a connected station (real or twins), through the instrument interfaces only:

* resonance (`measure_resonance`): close the loops with the configured constants, wait until the PLL is locked
  and the drive amplitude R has settled on the AGC setpoint, then record `record_s`: f0 is the mean PLL
  oscillator frequency (the PLL holds the drive at resonance, 90 deg phase), the drive voltage that sustains
  the setpoint amplitude is the AGC's output (centre + shift, read back from the lock-in's state).
  This needs the configured f0 within the PLL's range of the true one; there is no open-loop frequency sweep
  (no Lorentzian fit, no mode split): see docs/bench-bringup.md.
* ring-down (`measure_ringdown`): the drive is switched off (the lock-in's safe state: PIDs and outputs off,
  the PLL left tracking, docs/wiring.md) and the free decay of the drive pickoff amplitude R(t) is recorded;
  a least-squares fit of ln R = c - t/tau gives the amplitude decay time tau = 2Q/omega, so Q = pi f0 tau.
* scale factor (`measure_scale_factor`): with the loops closed on the tuned constants and the table at +r, -r,
  +r, ... (`pairs` +- pairs, `dwell_s` each, the first `settle_s` discarded), SF = (mean O+ - mean O-) /
  (mean Omega+ - mean Omega-), Omega the rate the table reports (PVE: the delivered rate), O the rate output.
  Each neighbouring pair gives one estimate; the result is their mean (IEEE 1431 step method).
* noise (`measure_noise`): a static record, the rate output averaged to 10 Hz, divided by the SF, Allan
  deviation in deg/h: ARW = sigma(1 s)/60 deg/sqrt(h), bias instability = min sigma / 0.664 (IEEE 952), NaN when
  the record is too short to show the floor.

`tune(cfg, station)` runs resonance and ring-down with the configured constants, re-closes the loops with the
measured f0, Q and drive voltage (the loop design depends on them: a wrong f0/Q biases the measured SF by about
100 ppm on the twin), then measures the scale factor, and ends in the safe state. `tuned_config_text` writes
the results into the [device] section of the configuration text, commented with what was measured.
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from qmg_lab.analysis.adev import arw_deg_per_rt_h, bias_instability_deg_per_h, overlapping_adev
from qmg_lab.campaign.loops import lockin_setup
from qmg_lab.config.schema import Config
from qmg_lab.instruments import InstrumentError, LockInBlock, Station

log = logging.getLogger(__name__)

AMPLITUDE_SETTLED_REL = 1e-4  # |R - setpoint| / setpoint below this counts as settled
NOISE_RATE_HZ = 10.0


class TuningError(InstrumentError):
    """A characterisation could not be completed (no lock, no decay, an implausible fit)."""


@dataclass(frozen=True)
class Resonance:
    f0_hz: float
    f0_std_hz: float
    drive_amplitude_vrms: float
    drive_voltage_v: float
    record_s: float


@dataclass(frozen=True)
class Ringdown:
    tau_s: float
    q_factor: float
    start_amplitude_vrms: float
    end_amplitude_vrms: float
    record_s: float


@dataclass(frozen=True)
class ScaleFactor:
    sf_v_per_dps: float
    estimates_v_per_dps: list[float]
    spread_ppm: float
    rate_dps: float


@dataclass(frozen=True)
class Noise:
    arw_deg_per_rt_h: float
    bias_instability_deg_per_h: float
    record_s: float
    adev: list[dict[str, float]]


@dataclass(frozen=True)
class Tuning:
    resonance: Resonance
    ringdown: Ringdown
    scale_factor: ScaleFactor

    def device_values(self) -> dict[str, float]:
        """The [device] keys tune writes, rounded to what the measurements resolve."""
        return {
            "f0_hz": round(self.resonance.f0_hz, 4),
            "q_factor": float(f"{self.ringdown.q_factor:.5g}"),
            "drive_voltage_v": float(f"{self.resonance.drive_voltage_v:.6g}"),
            "drive_amplitude_vrms": float(f"{self.resonance.drive_amplitude_vrms:.6g}"),
            "sf_nominal_v_per_dps": float(f"{self.scale_factor.sf_v_per_dps:.7g}"),
        }

    def as_dict(self) -> dict[str, Any]:
        return {
            "resonance": asdict(self.resonance),
            "ringdown": asdict(self.ringdown),
            "scale_factor": asdict(self.scale_factor),
            "device": self.device_values(),
        }


# ------------------------------------------------------------------------------------------------ recording
def _record(station: Station, seconds: float, fields: tuple[str, ...] = LockInBlock.FIELDS) -> dict[str, np.ndarray]:
    """Poll the lock-in for `seconds` of samples; the fields concatenated. Raises TuningError on sample loss."""
    blocks: list[LockInBlock] = []
    got, rate = 0.0, 0.0
    while got < seconds:
        block = station.lockin.poll(min(station.poll_interval_s, max(seconds - got, 0.05)))
        if len(block) == 0:
            continue
        blocks.append(block)
        if len(block.time) > 1:
            rate = (len(block.time) - 1) / float(block.time[-1] - block.time[0])
        got += len(block) / rate if rate > 0 else station.poll_interval_s
    return {f: np.concatenate([getattr(b, f) for b in blocks]) for f in fields} | {
        "locked": np.array([all(b.pll_locked for b in blocks)])
    }


def _close_loops_and_settle(cfg: Config, station: Station) -> None:
    """Configure the loops from cfg, start the stream, and wait until the PLL is locked and R has been within
    AMPLITUDE_SETTLED_REL of the AGC setpoint for loops.lock_settle_s (at most loops.lock_timeout_s + that)."""
    lp, setpoint = cfg.loops, cfg.device.drive_amplitude_vrms
    station.lockin.configure(lockin_setup(cfg))
    station.lockin.start_stream()
    waited, settled = 0.0, 0.0
    while settled < max(lp.lock_settle_s, 1.0):
        d = _record(station, station.poll_interval_s, ("time", "drive_amplitude"))
        span = float(d["time"][-1] - d["time"][0]) if len(d["time"]) > 1 else station.poll_interval_s
        waited += span
        ok = bool(d["locked"][0]) and np.all(np.abs(d["drive_amplitude"] / setpoint - 1) < AMPLITUDE_SETTLED_REL)
        settled = settled + span if ok else 0.0
        if waited > lp.lock_timeout_s + lp.lock_settle_s:
            raise TuningError(
                f"the PLL did not lock and settle within loops.lock_timeout_s = {lp.lock_timeout_s:g} s "
                f"with device.f0_hz = {cfg.device.f0_hz:g} Hz: is the resonance within the PLL's range?"
            )


def _prepare(cfg: Config, station: Station) -> None:
    """The bench quiet: dither muted, table at rest, chamber at the plan's start temperature."""
    station.generator.mute()
    station.table.stop()
    station.chamber.set_setpoint(cfg.plan.chamber_start_c, cfg.plan.chamber_ramp_c_per_min)


# ------------------------------------------------------------------------------------------------ measurements
def measure_resonance(cfg: Config, station: Station, record_s: float = 20.0) -> Resonance:
    """f0 from the locked PLL, the AGC's drive voltage at the setpoint amplitude (see the module docstring)."""
    _close_loops_and_settle(cfg, station)
    d = _record(station, record_s, ("drive_frequency", "drive_amplitude"))
    agc = station.lockin.state()["pids"]["agc"]
    result = Resonance(
        f0_hz=float(np.mean(d["drive_frequency"])),
        f0_std_hz=float(np.std(d["drive_frequency"])),
        drive_amplitude_vrms=float(np.mean(d["drive_amplitude"])),
        drive_voltage_v=float(agc["center"] + agc["shift"]),
        record_s=record_s,
    )
    log.info("resonance: %s", result)
    return result


def measure_ringdown(cfg: Config, station: Station, f0_hz: float, record_s: float | None = None) -> Ringdown:
    """Drive off, fit the free decay of R (see the module docstring). record_s: default the configured tau
    (about one decay time: R falls to 1/e), at least 20 s."""
    tau_guess = cfg.device.tau_s
    record = record_s if record_s is not None else max(20.0, min(tau_guess, 3600.0))
    station.lockin.safe_state()  # PIDs and outputs off: the drive is off; the PLL keeps tracking
    station.lockin.start_stream()
    d = _record(station, record, ("time", "drive_amplitude"))
    t, r = d["time"] - d["time"][0], d["drive_amplitude"]
    if r.size < 10 or not np.all(r > 0) or r[-1] >= r[0]:
        raise TuningError(f"no ring-down: the drive pickoff amplitude went from {r[0]:.4g} to {r[-1]:.4g} Vrms")
    slope = float(np.polyfit(t, np.log(r), 1)[0])
    if not slope < 0:
        raise TuningError(f"no ring-down: ln R grows at {slope:.3g} per s")
    tau = -1.0 / slope
    result = Ringdown(
        tau_s=tau,
        q_factor=math.pi * f0_hz * tau,
        start_amplitude_vrms=float(r[0]),
        end_amplitude_vrms=float(r[-1]),
        record_s=record,
    )
    log.info("ring-down: %s", result)
    return result


def measure_scale_factor(
    cfg: Config,
    station: Station,
    *,
    rate_dps: float | None = None,
    pairs: int = 2,
    dwell_s: float = 30.0,
    settle_s: float = 10.0,
) -> ScaleFactor:
    """Table steps +r, -r, ... (2 pairs + 1 step): SF from each neighbouring pair (see the module docstring)."""
    r = rate_dps if rate_dps is not None else cfg.plan.table_rate_dps
    if not r > 0:
        raise TuningError("the scale factor needs a non-zero table rate (plan.table_rate_dps)")
    means: list[tuple[float, float]] = []
    for k in range(2 * pairs + 1):
        station.table.set_rate(r if k % 2 == 0 else -r, cfg.plan.table_accel_dps2)
        d = _record(station, dwell_s, ("time", "rate_output"))
        keep = d["time"] >= d["time"][0] + settle_s
        means.append((station.table.read().rate_dps, float(np.mean(d["rate_output"][keep]))))
    station.table.stop()
    est = [(means[i][1] - means[i + 1][1]) / (means[i][0] - means[i + 1][0]) for i in range(len(means) - 1)]
    sf = float(np.mean(est))
    result = ScaleFactor(
        sf_v_per_dps=sf,
        estimates_v_per_dps=[float(e) for e in est],
        spread_ppm=float((max(est) - min(est)) / sf * 1e6),
        rate_dps=r,
    )
    log.info("scale factor: %s", result)
    return result


def measure_noise(cfg: Config, station: Station, record_s: float = 1800.0) -> Noise:
    """Static record with the loops closed: ARW and bias instability (see the module docstring)."""
    _close_loops_and_settle(cfg, station)
    d = _record(station, record_s, ("time", "rate_output"))
    fs = (len(d["time"]) - 1) / float(d["time"][-1] - d["time"][0])
    per = max(1, int(round(fs / NOISE_RATE_HZ)))
    n = (d["rate_output"].shape[0] // per) * per
    y = d["rate_output"][:n].reshape(-1, per).mean(axis=1) / cfg.device.sf_nominal_v_per_dps * 3600.0
    adev = overlapping_adev(y, fs / per)
    return Noise(
        arw_deg_per_rt_h=arw_deg_per_rt_h(adev),
        bias_instability_deg_per_h=bias_instability_deg_per_h(adev),
        record_s=record_s,
        adev=adev.rows(),
    )


def tune(
    cfg: Config,
    station: Station,
    *,
    resonance_s: float = 20.0,
    ringdown_s: float | None = None,
    dwell_s: float = 30.0,
    settle_s: float = 10.0,
    pairs: int = 2,
) -> Tuning:
    """Resonance and ring-down with the configured constants, then the scale factor with the measured ones;
    the station is left in its safe state."""
    try:
        _prepare(cfg, station)
        res = measure_resonance(cfg, station, resonance_s)
        ring = measure_ringdown(cfg, station, res.f0_hz, ringdown_s)
        dev = cfg.device.model_copy(
            update={"f0_hz": res.f0_hz, "q_factor": ring.q_factor, "drive_voltage_v": res.drive_voltage_v}
        )
        tuned = cfg.model_copy(update={"device": dev})
        _close_loops_and_settle(tuned, station)
        sf = measure_scale_factor(tuned, station, pairs=pairs, dwell_s=dwell_s, settle_s=settle_s)
        return Tuning(resonance=res, ringdown=ring, scale_factor=sf)
    finally:
        failures = station.safe_state()
        with contextlib.suppress(InstrumentError):
            station.lockin.stop_stream()
        if failures:
            log.error("safe state not confirmed after tuning: %s", failures)


def tuned_config_text(text: str, values: dict[str, float], header: list[str] | None) -> str:
    """The configuration text with `values` set in its [device] section (existing keys replaced in place,
    missing ones appended to the section, the section created if absent); `header` comment lines go above the
    section. Everything else of the text is kept as written."""
    lines = text.splitlines()
    out: list[str] = []
    section = ""
    written: set[str] = set()
    in_device = False

    def flush_missing() -> None:
        for k, v in values.items():
            if k not in written:
                out.append(f"{k} = {v!r}")
                written.add(k)

    for line in lines:
        stripped = line.strip()
        if stripped.startswith("[") and not stripped.startswith("[["):
            if in_device:
                flush_missing()
            section = stripped.split("#")[0].strip().strip("[]").strip()
            in_device = section == "device"
            if in_device and header:
                out.extend(f"# {h}" for h in header)
            out.append(line)
            continue
        if in_device:
            key = stripped.split("=")[0].strip() if "=" in stripped and not stripped.startswith("#") else ""
            if key in values:
                old, _, note = stripped.split("=", 1)[1].partition("#")
                out.append(
                    f"{key} = {values[key]!r}  # tuned; was {old.strip()}"
                    + (f" ({note.strip()})" if note.strip() else "")
                )
                written.add(key)
                continue
        out.append(line)
    if in_device:
        flush_missing()
    if len(written) < len(values):
        out.append("")
        if header:
            out.extend(f"# {h}" for h in header)
        out.append("[device]")
        flush_missing()
    return "\n".join(out) + "\n"


def header_lines(t: Tuning, source: str) -> list[str]:
    """The comment written above the tuned [device] section: what was measured, when, how well."""
    r, g, s = t.resonance, t.ringdown, t.scale_factor
    return [
        f"[device] tuned by qmg-lab tune from {source} on {datetime.now(UTC).isoformat(timespec='seconds')}",
        f"f0: locked PLL frequency, mean of {r.record_s:g} s, std {r.f0_std_hz:.3g} Hz",
        f"q_factor: ring-down tau = {g.tau_s:.4g} s over {g.record_s:g} s (R {g.start_amplitude_vrms:.4g} -> "
        f"{g.end_amplitude_vrms:.4g} Vrms), Q = pi f0 tau",
        f"drive_voltage_v: AGC output at R = {r.drive_amplitude_vrms:.6g} Vrms",
        f"sf_nominal_v_per_dps: +-{s.rate_dps:g} deg/s steps, {len(s.estimates_v_per_dps)} pairs, spread "
        f"{s.spread_ppm:.1f} ppm",
    ]
