"""The simulated test stand's shared physical state and its virtual clock.

One `World` is shared by every twin: the DS345 twin writes the dither, the table twin the rate command, the
chamber twin the setpoint; the HF2 twin advances the clock block by block (`advance`), receiving the inputs the
gyro physics needs at every step. Nothing here sleeps: a 3-hour campaign takes as long as its arithmetic.

Dynamics (all exact for inputs held over a step; a block is one compiled call, sims/world_kernel.block_inputs):

* Table, rate mode: rate moves toward the command at the acceleration limit a,
  r(t) = r0 + sign(r1 - r0) * min(a t, |r1 - r0|); sinusoid mode: r(t) = A sin(2 pi f (t - t_s)).
  The delivered rate is the profile times (1 + e) (1 + r sin(theta + phi_r)): e the table's rate scale error
  (1291BR: 100 ppm class), r a once-per-revolution rate ripple at the table angle theta (bearing runout and
  encoder eccentricity: the servo holds the *encoder's* rate, the table turns at that rate times the ripple; a
  specification "averaged over 360 deg" says nothing of it, so its size is assumed, docs/accuracy-budget.md).
  theta in the ripple is the angle of the ripple-free profile (the ripple's own angle error is second order,
  r^2). Position is the integral of the delivered rate.
* Chamber: the controller setpoint s(t) ramps to the target at the ramp rate (deg C/min); the air follows s with
  a first-order lag tau_air; the gyro follows the air with a first-order lag tau_gyro. Exact ZOH recursion
  y[k+1] = a y[k] + (1 - a) u[k], a = exp(-dt/tau), evaluated in closed form (`first_order_lag`).
* Dither (DS345 output): v(t) = offset + (Vpp/2) w(u(t)), w the unit waveform of the phase u in cycles
  (square: +1 on the first half cycle, -1 on the second; sine: sin 2 pi u; triangle; ramp), with
  u(t) = f (tau(t) - tau(t_origin)) + phase/360. tau is the DS345's own timebase, which is not the HF2's clock
  (the World's time t): tau(t) = t (1 + e0) + e_w P/(2 pi) (1 - cos(2 pi t / P)), i.e. a rate error
  e(t) = e0 + e_w sin(2 pi t / P) of e0 = `ds345_timebase_offset_ppm` plus a slow wander. A command takes
  effect `ds345_command_latency_s` after it arrives (t_origin = t_command + latency), so the dither's phase is
  not tied to the lock-in's sample grid either. The dither's edges therefore fall anywhere between samples.
* Exact dither integrals: every dither value the World hands out is the mean of v over an interval,
  (W(u1) - W(u0)) / (u1 - u0) with W the antiderivative of w (square: W = frac(u) for frac < 1/2, else
  1 - frac(u)), so a step or a sampling window that contains an edge gets the exact fraction of each level.
  (The local frequency is taken as constant within one interval: the wander changes it by e_w 2 pi dt/P, a
  1e-12 effect over a 1 ms step.)

Every input returned for step k is its mean over [t_k, t_k + dt) (for the dither, the exact mean above), the
ZOH convention of the gyro kernel.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sims import world_kernel as wk

DITHER_SINE, DITHER_SQUARE, DITHER_TRIANGLE, DITHER_RAMP = (
    wk.DITHER_SINE,
    wk.DITHER_SQUARE,
    wk.DITHER_TRIANGLE,
    wk.DITHER_RAMP,
)


_DEG = math.pi / 180.0  # rad per degree (numpy's deg2rad multiplies by this)


@dataclass
class WorldParams:
    """Physical constants of the stand outside the gyro itself.

    Every field is required: the configuration's [sim] section exposes each one, and the schema
    (qmg_lab/config/schema.py SimSection) is the one place of their defaults, bounds, descriptions and origins
    (the DS345 timebase values are assumed: a crystal timebase of a few ppm is typical of such generators; see
    docs/simulation.md). qmg_lab/station.py `world_params` maps a configuration to this class.
    """

    chamber_time_constant_s: float  # chamber air -> its setpoint, first-order lag, s
    thermal_lag_s: float  # chamber air -> gyro, first-order lag, s
    initial_temperature_c: float
    table_rate_scale_error_ppm: float
    table_rate_ripple_ppm: float  # once-per-revolution rate ripple r, ppm of the rate
    table_ripple_phase_deg: float  # phi_r: where on the revolution the ripple peaks
    # the DS345's own timebase against the HF2's clock
    ds345_timebase_offset_ppm: float
    ds345_timebase_wander_ppm: float
    ds345_timebase_wander_period_s: float
    ds345_command_latency_s: float


@dataclass
class DitherState:
    function: int = DITHER_SINE
    frequency_hz: float = 1000.0
    amplitude_vpp: float = 0.0
    offset_v: float = 0.0
    phase_deg: float = 0.0
    origin_s: float = 0.0


@dataclass
class TableState:
    mode: str = "rate"  # "rate" | "sine"
    rate_command_dps: float = 0.0
    accel_dps2: float = 300.0
    rate_dps: float = 0.0  # profile rate (before the scale error) at the current time
    angle_deg: float = 0.0
    sine_amplitude_dps: float = 0.0
    sine_frequency_hz: float = 0.0
    sine_start_s: float = 0.0
    interlock: bool = False


@dataclass
class ChamberState:
    target_c: float = 25.0
    ramp_c_per_min: float = 1.0
    controller_setpoint_c: float = 25.0
    air_c: float = 25.0
    gyro_c: float = 25.0
    heater_on: bool = True
    disturbance_c: float = 0.0  # added to the air temperature (fault injection: overshoot)


@dataclass
class BlockInputs:
    """Per-step inputs for one block of n steps: t[k] is the start of step k."""

    t: np.ndarray
    table_rate_dps: np.ndarray  # delivered rate, mean over the step
    table_angle_deg: np.ndarray  # at the start of the step
    chamber_c: np.ndarray  # air temperature
    gyro_c: np.ndarray  # gyro temperature
    dither_v: np.ndarray  # DS345 output, mean over the step (mid-step value)


@dataclass
class TruthRecord:
    time: np.ndarray
    scale_factor: np.ndarray
    temperature: np.ndarray
    rate: np.ndarray


def first_order_lag(u: np.ndarray, y0: float, a: float) -> np.ndarray:
    """y[0] = y0, y[k+1] = a y[k] + (1 - a) u[k] for k < n - 1: the one-pole recursion (for 0 < a, the compiled
    loop sims.world_kernel.first_order_lag, scipy.signal.lfilter's b = [0, 1 - a], a = [1, -a] with the initial
    state y0 step by step)."""
    n = u.shape[0]
    y = np.empty(n)
    if a <= 0.0:
        y[0] = y0
        y[1:] = u[:-1]
        return y
    wk.first_order_lag(np.ascontiguousarray(u, dtype=np.float64), float(y0), float(a), y)
    return y


class World:
    """The virtual clock and the shared physical state. Thread-safe: twins on pty threads read it too."""

    def __init__(self, params: WorldParams, clock: str = "virtual") -> None:
        if clock not in ("virtual", "wall"):
            raise ValueError("clock must be 'virtual' or 'wall'")
        self.params = params
        self.clock = clock
        self.lock = threading.RLock()
        self.t = 0.0
        if clock == "wall":
            # A wall-clock world answers the instruments' commands in real time (a serial twin's reply within the
            # driver's timeout), and its first advance would compile the block kernel (seconds on a fresh install,
            # against a 1291BR timeout of 2 s): compile it, or load it from numba's cache, on a throwaway world now.
            World(self.params).advance(1, 0.01)
        self._wall0 = time.monotonic()
        self.dither = DitherState()
        self.table = TableState()
        t0 = self.params.initial_temperature_c
        self.chamber = ChamberState(target_c=t0, controller_setpoint_c=t0, air_c=t0, gyro_c=t0)
        self._truth: deque[TruthRecord] = deque()
        self.forcer_gain = 1.0  # forcer-path gain set through the lock-in (CLSF correct mode)
        self._last_grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # last advance's dither phases
        self._offsets_key: tuple[int, float] | None = None  # (n, dt) of the cached `_step_offsets`
        self._offsets = (np.zeros(0), np.zeros(0), np.zeros(1))
        self._tau_origin_key: tuple[float, float, float, float] | None = None  # what `_tau_origin_s` was formed from
        self._tau_origin_s = 0.0
        # called as fn(t_start_s, t_end_s) at the start of every advance, under the lock (fault injection)
        self.on_advance: list[Callable[[float, float], None]] = []

    # ------------------------------------------------------------------ clock
    def now(self) -> float:
        """Current time, s. On a wall clock the slow dynamics are first brought up to date."""
        if self.clock == "wall":
            self.sync_wall()
        return self.t

    def sync_wall(self, dt: float = 0.01) -> None:
        """Wall-clock mode (no HF2 twin advancing the world): integrate up to the real elapsed time."""
        with self.lock:
            target = time.monotonic() - self._wall0
            n = int((target - self.t) / dt)
            if n > 0:
                self.advance(n, dt)

    # ------------------------------------------------------------------ commands from the twins
    def set_dither(
        self,
        *,
        function: int | None = None,
        frequency_hz: float | None = None,
        amplitude_vpp: float | None = None,
        offset_v: float | None = None,
        phase_deg: float | None = None,
    ) -> None:
        """Change the generator's settings. A new frequency restarts the phase origin at the current time."""
        with self.lock:
            d = self.dither
            if function is not None:
                d.function = int(function)
            if frequency_hz is not None and frequency_hz != d.frequency_hz:
                d.frequency_hz = float(frequency_hz)
                d.origin_s = self.t + self.params.ds345_command_latency_s
            if amplitude_vpp is not None:
                d.amplitude_vpp = float(amplitude_vpp)
            if offset_v is not None:
                d.offset_v = float(offset_v)
            if phase_deg is not None:
                d.phase_deg = float(phase_deg)

    def set_table_rate(self, rate_dps: float, accel_dps2: float) -> None:
        with self.lock:
            self._freeze_table_profile()
            self.table.mode = "rate"
            self.table.rate_command_dps = float(rate_dps)
            self.table.accel_dps2 = float(accel_dps2)

    def set_table_sine(self, amplitude_dps: float, frequency_hz: float) -> None:
        with self.lock:
            self._freeze_table_profile()
            self.table.mode = "sine"
            self.table.sine_amplitude_dps = float(amplitude_dps)
            self.table.sine_frequency_hz = float(frequency_hz)
            self.table.sine_start_s = self.t

    def stop_table(self, accel_dps2: float | None = None) -> None:
        with self.lock:
            self.set_table_rate(0.0, accel_dps2 if accel_dps2 is not None else self.table.accel_dps2)

    def trip_interlock(self) -> None:
        """Hardware protection: the table brakes to rest and ignores rate commands until reset."""
        with self.lock:
            self.set_table_rate(0.0, max(self.table.accel_dps2, 300.0))
            self.table.interlock = True

    def reset_interlock(self) -> None:
        with self.lock:
            self.table.interlock = False

    def set_chamber(self, target_c: float, ramp_c_per_min: float | None = None) -> None:
        with self.lock:
            self.chamber.target_c = float(target_c)
            if ramp_c_per_min is not None:
                self.chamber.ramp_c_per_min = float(ramp_c_per_min)

    def restore(
        self,
        time_s: float | None = None,
        chamber_setpoint_c: float | None = None,
        chamber_air_c: float | None = None,
        gyro_c: float | None = None,
        table_angle_deg: float | None = None,
    ) -> None:
        """Put the world back where a resumed run's file says it was: the physical bench did not stop when the
        host process died. The time is restored only on the virtual clock (a wall clock runs on by itself); the
        chamber controller's setpoint and target, its air, the gyro temperature and the table's angle (deg: the
        once-per-revolution rate ripple and the encoder depend on it) as given (None: unchanged)."""
        with self.lock:
            if time_s is not None and self.clock == "virtual":
                self.t = float(time_s)
            if table_angle_deg is not None:
                self.table.angle_deg = float(table_angle_deg)
            if chamber_setpoint_c is not None:
                self.chamber.controller_setpoint_c = float(chamber_setpoint_c)
                self.chamber.target_c = float(chamber_setpoint_c)
            if chamber_air_c is not None:
                self.chamber.air_c = float(chamber_air_c)
            if gyro_c is not None:
                self.chamber.gyro_c = float(gyro_c)

    def set_forcer_gain(self, gain: float) -> None:
        with self.lock:
            self.forcer_gain = float(gain)

    # ------------------------------------------------------------------ read-backs
    def table_rate_dps(self) -> float:
        """Delivered table rate now, deg/s (scale error and ripple at the current angle)."""
        with self.lock:
            p = self.params  # the ripple factor 1 + r sin(theta + phi_r) at the current angle
            ripple = 1.0
            if p.table_rate_ripple_ppm != 0.0:
                ripple += (
                    p.table_rate_ripple_ppm * 1e-6 * math.sin((self.table.angle_deg + p.table_ripple_phase_deg) * _DEG)
                )
            return self.table.rate_dps * (1.0 + p.table_rate_scale_error_ppm * 1e-6) * ripple

    def table_angle_deg(self) -> float:
        with self.lock:
            return self.table.angle_deg

    def chamber_air_c(self) -> float:
        with self.lock:
            return self.chamber.air_c + self.chamber.disturbance_c

    # ------------------------------------------------------------------ truth
    def record_truth(self, rec: TruthRecord) -> None:
        self._truth.append(rec)

    def drain_truth(self) -> TruthRecord | None:
        recs = []
        while self._truth:
            recs.append(self._truth.popleft())
        if not recs:
            return None
        if len(recs) == 1:  # the usual drain, once per poll: the record itself (its arrays are the twin's own copies)
            return recs[0]
        return TruthRecord(
            *(np.concatenate([getattr(r, f) for r in recs]) for f in ("time", "scale_factor", "temperature", "rate"))
        )

    # ------------------------------------------------------------------ dynamics
    def _freeze_table_profile(self) -> None:
        """A new command starts from the rate the table has now."""
        if self.table.mode == "sine":
            tab = self.table
            tab.rate_dps = tab.sine_amplitude_dps * math.sin(
                2 * math.pi * tab.sine_frequency_hz * (self.t - tab.sine_start_s)
            )
            tab.rate_command_dps = tab.rate_dps

    def _table_profile(self, tau: np.ndarray) -> np.ndarray:
        """Profile rate (before scale error) at times tau (s from now)."""
        tab = self.table
        if tab.mode == "sine":
            return tab.sine_amplitude_dps * np.sin(
                2 * np.pi * tab.sine_frequency_hz * (self.t + tau - tab.sine_start_s)
            )
        r0, r1, a = tab.rate_dps, tab.rate_command_dps, tab.accel_dps2
        if r0 == r1:
            return np.full_like(tau, r0)
        return r0 + math.copysign(1.0, r1 - r0) * np.minimum(a * tau, abs(r1 - r0))

    def ds345_time(self, t: np.ndarray | float) -> np.ndarray:
        """tau(t): the DS345 timebase's reading at World (HF2) time t, s (module docstring)."""
        p = self.params
        e0, ew, per = (
            p.ds345_timebase_offset_ppm * 1e-6,
            p.ds345_timebase_wander_ppm * 1e-6,
            p.ds345_timebase_wander_period_s,
        )
        tt = np.asarray(t, dtype=np.float64)
        return tt * (1.0 + e0) + (ew * per / (2 * np.pi)) * (1.0 - np.cos(2 * np.pi * tt / per))

    def _tau_origin(self) -> float:
        """tau(t_origin), the DS345 timebase's reading at the dither's phase origin: `ds345_time`, kept while the
        origin and the timebase parameters stay as they were (it changes only with a new frequency)."""
        p = self.params
        key = (
            self.dither.origin_s,
            p.ds345_timebase_offset_ppm,
            p.ds345_timebase_wander_ppm,
            p.ds345_timebase_wander_period_s,
        )
        if key != self._tau_origin_key:
            self._tau_origin_key, self._tau_origin_s = key, float(self.ds345_time(self.dither.origin_s))
        return self._tau_origin_s

    def _dither_phase(self, t: np.ndarray) -> np.ndarray:
        """u(t): the generator's phase in cycles at World times t."""
        d = self.dither
        return d.frequency_hz * (self.ds345_time(t) - self.ds345_time(d.origin_s)) + d.phase_deg / 360.0

    def _dither_wave(self, t: np.ndarray) -> np.ndarray:
        """The generator's output at the instants t, V."""
        d = self.dither
        if d.amplitude_vpp == 0.0:
            return np.full(np.shape(t), d.offset_v)
        u = self._dither_phase(np.asarray(t, dtype=np.float64))
        frac = u - np.floor(u)
        if d.function == DITHER_SQUARE:
            w = np.where(frac < 0.5, 1.0, -1.0)
        elif d.function == DITHER_TRIANGLE:
            w = 1.0 - 4.0 * np.abs(frac - 0.5)
        elif d.function == DITHER_RAMP:
            w = 2.0 * frac - 1.0
        else:
            w = np.sin(2 * np.pi * u)
        return d.offset_v + 0.5 * d.amplitude_vpp * w

    def window_means_at_step_ends(self, window_s: float) -> np.ndarray:
        """For each step of the last advance, the exact mean of the output over [t_end - window_s, t_end] (an
        AuxIn reading), window_s <= the step. The phase at t_end - w is u(t_end) - w du/dt, du/dt taken over
        the step (the timebase's wander changes it by 1e-12 within a step; the loop:
        sims.world_kernel.dither_window_means)."""
        grid = self._last_grid
        d = self.dither
        if grid is None:
            raise RuntimeError("window_means_at_step_ends needs a dither and an advance first")
        tb, u, wint = grid
        if window_s <= 0.0:
            return self._dither_wave(tb[1:])
        means = np.empty(tb.shape[0] - 1)
        wk.dither_window_means(tb, u, wint, float(window_s), d.function, d.offset_v, 0.5 * d.amplitude_vpp, means)
        return means

    def _step_offsets(self, n: int, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(k dt for k < n, k dt + dt/2 for k < n, k dt for k <= n): the step starts, mid-steps and boundaries of
        a block of n steps from its start, s. Read-only arrays, kept while blocks keep their n and dt."""
        if self._offsets_key != (n, dt):
            k = np.arange(n + 1, dtype=np.float64)
            bounds = k * dt
            start = bounds[:n]
            mid = start + 0.5 * dt
            for a in (bounds, mid):
                a.flags.writeable = False
            self._offsets, self._offsets_key = (start, mid, bounds), (n, dt)
        return self._offsets

    def advance(self, n: int, dt: float) -> BlockInputs:
        """Advance the clock by n steps of dt and return the inputs of each step (one compiled pass:
        sims.world_kernel.block_inputs)."""
        if n <= 0:
            raise ValueError("advance needs n >= 1")
        with self.lock:
            for fn in self.on_advance:
                fn(self.t, self.t + n * dt)
            p, tab, c, d = self.params, self.table, self.chamber, self.dither
            rate_mode = tab.mode != "sine"
            profile_mid = np.empty(n) if rate_mode else self._table_profile(self._step_offsets(n, dt)[1])
            r0, r1, s0, s1 = tab.rate_dps, tab.rate_command_dps, c.controller_setpoint_c, c.target_c
            a_air = math.exp(-dt / p.chamber_time_constant_s)
            a_gyro = math.exp(-dt / p.thermal_lag_s)
            table = np.array(
                [
                    self.t,
                    dt,
                    r0,
                    math.copysign(1.0, r1 - r0),
                    tab.accel_dps2,
                    abs(r1 - r0),
                    1.0 + p.table_rate_scale_error_ppm * 1e-6,
                    tab.angle_deg,
                    p.table_rate_ripple_ppm * 1e-6,
                    p.table_ripple_phase_deg,
                ]
            )
            chamber = np.array(
                [
                    s0,
                    math.copysign(1.0, s1 - s0),
                    c.ramp_c_per_min / 60.0,
                    abs(s1 - s0),
                    a_air,
                    c.air_c,
                    c.disturbance_c,
                    a_gyro,
                    c.gyro_c,
                ]
            )
            dither_on = d.amplitude_vpp != 0.0
            per = p.ds345_timebase_wander_period_s
            dither = np.array(
                [
                    p.ds345_timebase_offset_ppm * 1e-6,
                    p.ds345_timebase_wander_ppm * 1e-6 * per / (2 * np.pi),
                    per,
                    self._tau_origin() if dither_on else 0.0,
                    d.frequency_hz,
                    d.phase_deg / 360.0,
                    d.offset_v,
                    0.5 * d.amplitude_vpp,
                ]
            )
            t, tb = np.empty(n), np.empty(n + 1)
            rate, angle, sp, air, air_meas, gyro = (np.empty(n) for _ in range(6))
            u, wint = np.empty(n + 1), np.empty(n + 1)
            means = np.empty(n) if dither_on else np.full(n, d.offset_v)
            wk.block_inputs(
                table, chamber, dither, rate_mode, dither_on, d.function,
                t, tb, profile_mid, rate, angle, sp, air, air_meas, gyro, u, wint, means,
            )  # fmt: skip
            self._last_grid = (tb, u, wint) if dither_on else None
            # state at the end of the block
            end = float(n * dt)
            if rate_mode:  # _table_profile at `end`, in scalar arithmetic
                tab.rate_dps = (
                    r0 if r0 == r1 else r0 + math.copysign(1.0, r1 - r0) * min(tab.accel_dps2 * end, abs(r1 - r0))
                )
            else:
                tab.rate_dps = float(self._table_profile(np.array([end]))[0])
            tab.angle_deg = float(angle[-1] + rate[-1] * dt)
            c.air_c = float(a_air * air[-1] + (1.0 - a_air) * sp[-1])
            c.gyro_c = float(a_gyro * gyro[-1] + (1.0 - a_gyro) * air_meas[-1])
            c.controller_setpoint_c = (
                s0 if s0 == s1 else s0 + math.copysign(1.0, s1 - s0) * min(c.ramp_c_per_min / 60.0 * end, abs(s1 - s0))
            )
            self.t = self.t + end
            return BlockInputs(
                t=t, table_rate_dps=rate, table_angle_deg=angle, chamber_c=air_meas, gyro_c=gyro, dither_v=means
            )
