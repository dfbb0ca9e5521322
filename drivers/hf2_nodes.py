"""HF2LI node settings for the gyroscope loops: pure functions from a LockInSetup and the bench wiring to the
list of (relative node path, value) pairs the driver sends in one transaction, and the limit checks that run
before anything is sent. Node semantics: docs/wiring.md; the cabling: docs/wiring.md.

Channel assignment (fixed here, documented in docs/wiring.md):
* demod 0 = drive (input drive_sigin), demod 1 = sense (input sense_sigin), both on the PLL 0 oscillator,
  harmonic 1, phaseshift 0, same rate and filter;
* PLL 0 on drive_sigin: frequency = freqcenter + p e + i int(e) (e = phase - setpoint, deg), range freqrange;
* PID 0 = AGC: input R (2) of demod 0 -> output drive_sigout amplitude (0/1), outputchannel = the drive mixer
  channel (pids/n/outputchannel: "the channel of the selected OUTPUT", nodedoc_hf2.json);
* PID 1 = rate: input X (0) of demod 1 -> AuxOut offset (3), channel rate_auxout (manual mode, outputselect -1);
* PID 2 = quadrature: input Y (1) of demod 1 -> AuxOut offset (3), channel quadrature_auxout; PID 3 off;
* forcer carrier: forcer_sigout, the forcer mixer channel, amplitude = forcer_carrier_amplitude * forcer_gain
  (fraction of the output range).

Mixer channels (``mixer_layout``), from the instrument's ``features/options``:
* with the MF option every output lists mixer channels 0..7 (zhinst-toolkit's recorded HF2 node list
  tests/data/list_nodes_hf2_dev.txt: sigouts/n/{enables,amplitudes,waveforms}/0..7); mixer channel m runs on the
  oscillator of demod m. Drive = channel 0 (demod 0's oscillator = the PLL's), forcer = channel 1 (demod 1's).
* without MF each output is driven by one mixer channel: output 1 by channel 6, output 2 by channel 7
  (zhinst-utils ``default_output_mixer_channel``; zhinst-toolkit's HF2 PID-advisor example uses
  ``OUT_MIXER_CHANNEL = 6``); the outputs list only channels 6 and 7 (a recorded non-MF HF2, dev1492, in the
  public qudi-iqo-modules HF2 driver: ``{'/dev1492/sigouts/0/enables/6': 0, '/dev1492/sigouts/0/enables/7': 0}``).
* channels 6 and 7 have no demodulator whose oscillator could be chosen: their oscillators are fixed
  (``carrier_plan``). Channel 7 runs on oscillator 2 (index 1): the HF2 user manual's External Reference tutorial
  generates Output 2's signal with "Demodulator 8 Amplitude 2 ... Oscillator 2 frequency" (channel 7 is
  "Demodulator 8" counted from 1); channel 6 on oscillator 1 (index 0) by the same construction (*inferred*: the
  tutorial shows Output 2 only). ``[lockin] fixed_channel_oscillators`` holds the two indices, to be changed if the
  scope at bring-up shows otherwise (docs/wiring.md).

Carrier coherence (``carrier_plan``): the drive and the forcer carrier must run at the drive frequency in phase
with the PLL. PLL 1 (``plls/0``) locks oscillator ``plls/0/oscselect`` to the drive pickoff; every demodulator the
loops use runs on it. A carrier channel on another oscillator is made coherent by the second PLL (the HF2-PLL
option has two independent PLLs, HF2 user manual, PLL tab): PLL n, the one whose ``plls/n/oscselect`` (read-only,
"Index of the oscillator used", nodedoc_hf2.json, read at connect) is that oscillator, is set up exactly like
PLL 1 on the drive input (same centre, range, gains and phase setpoint), so both oscillators lock to the same
signal with the same phase. Without MF that is the forcer carrier on channel 7: oscillator 2, PLL 2. A PLL uses a
demodulator of its own (``plls/n/demodselect``, read-only, "Source demodulator"; the manual: "Demodulators that
are used by an active PLL are set to read-only values"): the sense demodulator is the first one no such PLL uses.
*Unconfirmed on an instrument*: that PLL 2 drives oscillator 2 (the driver reads it and refuses a layout where
no PLL drives the carrier's oscillator) and the phase of the two PLLs' oscillators at equal setpoints (check on a
scope: docs/wiring.md).
* ``[lockin] drive_mixer_channel`` / ``forcer_mixer_channel`` override the derived channel for a bench wired
  otherwise (it must be one the instrument lists).
* PLL and PID are required options (the PLL closes the drive loop, the PIDs the AGC, rate and quadrature loops):
  a lock-in without one is refused (MissingOptionError, an InstrumentError: exit 3).

The wiring (`LockInWiring`) is the validated [lockin] section: qmg_lab/config/schema.py LockInSection declares
its defaults, its bounds and the pairs that must differ, once; nothing here checks them again. What is checked here
is what the instrument reports: its options (`check_options`), the mixer channels its outputs list
(`mixer_layout`), the PLLs that drive the carriers' oscillators (`carrier_plan`), and the limits of a setup
(`check_setup`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from qmg_lab.instruments import InstrumentError, LimitError, LockInSetup, PidGains, check_limit

DRIVE_DEMOD, SENSE_DEMOD = 0, 1  # SENSE_DEMOD: unless a tracking PLL uses it (carrier_plan)
DRIVE_PLL = 0
AGC_PID, RATE_PID, QUAD_PID, SPARE_PID = 0, 1, 2, 3
# AuxIn ADC sample rate, Sa/s. *Assumed*: the HF2 documentation says the AuxIns average 2^n (1..32768) ADC
# samples and align the result by timestamp with the demodulator sample, but the ADC rate was not found. With the
# default averaging 0 the window is a single ADC sample and this value hardly matters (docs/wiring.md).
AUXIN_ADC_RATE_HZ = 400e3
DRIVE_MIXER_CHANNEL = 0  # with MF: uses demod 0's oscillator = the PLL oscillator
DEFAULT_FORCER_MIXER_CHANNEL = 1  # with MF: uses demod 1's oscillator = the PLL oscillator
NON_MF_OUTPUT_MIXER_CHANNELS = (6, 7)  # without MF: output 1 -> channel 6, output 2 -> channel 7 (module doc)
REQUIRED_OPTIONS = ("PLL", "PID")
N_DEMODS = 6  # demodulators of an HF2LI (recorded node list: demods/0..5), with or without MF
SIGOUT_RANGES_V = (0.01, 0.1, 1.0, 10.0)
FORCER_OUTPUT_RANGE_V = 1.0  # carrier into the external modulator: amplitude = fraction * 1 V
SIGIN_RANGE_V = 1.0  # pickoff inputs: drive pickoff ~0.7 V peak at 0.5 Vrms
AUXOUT_LIMIT_V = 10.0
FORCER_GAIN_LIMITS = (0.5, 2.0)
N_MIXER_CHANNELS = 8


class LockInWiring(Protocol):
    """The cabling fields of qmg_lab.config.schema.LockInSection, read-only: that section, validated (module
    doc), is what the station passes. drive_mixer_channel / forcer_mixer_channel: None = derived from the options
    (`mixer_layout`); fixed_channel_oscillators: the oscillators of mixer channels 6 and 7."""

    @property
    def drive_sigin(self) -> int: ...
    @property
    def sense_sigin(self) -> int: ...
    @property
    def drive_sigout(self) -> int: ...
    @property
    def forcer_sigout(self) -> int: ...
    @property
    def forcer_carrier_amplitude(self) -> float: ...
    @property
    def rate_auxout(self) -> int: ...
    @property
    def quadrature_auxout(self) -> int: ...
    @property
    def rate_auxin(self) -> int: ...
    @property
    def dither_auxin(self) -> int: ...
    @property
    def drive_mixer_channel(self) -> int | None: ...
    @property
    def forcer_mixer_channel(self) -> int | None: ...
    @property
    def fixed_channel_oscillators(self) -> Sequence[int]: ...


class MissingOptionError(InstrumentError):
    """The lock-in lacks an option the loops need (PLL or PID)."""


def parse_options(text: str) -> tuple[str, ...]:
    """``features/options`` ("a newline-separated list of all installed options", nodedoc_hf2.json) as upper-case
    option names; commas and blanks are taken as separators too."""
    return tuple(o.upper() for o in re.split(r"[\s,]+", str(text)) if o)


def check_options(devtype: str, options: tuple[str, ...]) -> None:
    """MissingOptionError naming each required option (REQUIRED_OPTIONS) the instrument lacks."""
    missing = [o for o in REQUIRED_OPTIONS if o not in options]
    if missing:
        names = " and ".join(missing)
        raise MissingOptionError(
            f"the {devtype} lacks the {names} option{'s' if len(missing) > 1 else ''} (installed options: "
            f"{', '.join(options) or 'none'}): qmg-lab closes the drive loop with the PLL and the AGC, rate and "
            "quadrature loops with the PIDs, and cannot run without them"
        )


@dataclass(frozen=True)
class MixerLayout:
    """Which output mixer channels the instrument has and which ones carry the drive and the forcer carrier."""

    channels: tuple[int, ...]  # mixer channels every signal output lists (sigouts/n/enables/<m>)
    drive: int  # mixer channel of drive_sigout carrying the drive
    forcer: int  # mixer channel of forcer_sigout carrying the forcer carrier


def mixer_layout(options: tuple[str, ...], wiring: LockInWiring) -> MixerLayout:
    """The mixer channels from the options (module doc) and the wiring, with the [lockin] drive_mixer_channel /
    forcer_mixer_channel overrides (None = derived). ValueError names an impossible choice."""
    w = wiring
    if "MF" in options:
        channels: tuple[int, ...] = tuple(range(N_MIXER_CHANNELS))
        drive, forcer = DRIVE_MIXER_CHANNEL, DEFAULT_FORCER_MIXER_CHANNEL
    else:
        channels = NON_MF_OUTPUT_MIXER_CHANNELS
        drive, forcer = channels[w.drive_sigout], channels[w.forcer_sigout]
    drive = drive if w.drive_mixer_channel is None else int(w.drive_mixer_channel)
    forcer = forcer if w.forcer_mixer_channel is None else int(w.forcer_mixer_channel)
    for name, m in (("drive_mixer_channel", drive), ("forcer_mixer_channel", forcer)):
        if m not in channels:
            kind = "with" if "MF" in options else "without"
            raise ValueError(
                f"lock-in wiring: {name} = {m} is not a mixer channel of this HF2 ({kind} the MF option it has "
                f"channels {', '.join(map(str, channels))})"
            )
    if drive == forcer and w.drive_sigout == w.forcer_sigout:
        raise ValueError(
            f"lock-in wiring: the drive and the forcer carrier both use mixer channel {drive} of output "
            f"{w.drive_sigout}: they need two channels (or two outputs)"
        )
    return MixerLayout(channels=channels, drive=drive, forcer=forcer)


@dataclass(frozen=True)
class CarrierPlan:
    """Which oscillator each carrier runs on, which PLLs lock them to the drive, and the demodulators the loops
    use (module doc: carrier coherence)."""

    ref_osc: int  # PLL 1's oscillator: the demodulators' reference
    drive_osc: int  # oscillator of the drive mixer channel
    forcer_osc: int  # oscillator of the forcer mixer channel
    tracking_plls: tuple[int, ...]  # PLLs besides PLL 1 set up on the drive input (each locks one carrier's osc)
    drive_demod: int
    sense_demod: int


def fixed_channel_oscillators(wiring: LockInWiring) -> dict[int, int]:
    """{6: oscillator of channel 6, 7: oscillator of channel 7} from [lockin] fixed_channel_oscillators."""
    pair = wiring.fixed_channel_oscillators
    return {NON_MF_OUTPUT_MIXER_CHANNELS[0]: int(pair[0]), NON_MF_OUTPUT_MIXER_CHANNELS[1]: int(pair[1])}


def carrier_plan(
    layout: MixerLayout, wiring: LockInWiring, pll_oscs: tuple[int, ...], pll_demods: tuple[int, ...]
) -> CarrierPlan:
    """The carriers' oscillators and the PLLs that lock them (module doc) from the instrument's read-only
    ``plls/n/oscselect`` (`pll_oscs`) and ``plls/n/demodselect`` (`pll_demods`); ValueError when a carrier's
    oscillator is driven by no PLL or no demodulator is left for the sense pickoff."""
    ref = pll_oscs[DRIVE_PLL]
    fixed = fixed_channel_oscillators(wiring)

    def osc_of(m: int) -> int:  # a channel with a demodulator runs on it, which setup_nodes puts on PLL 1's osc
        return fixed[m] if m >= N_DEMODS else ref

    drive_osc, forcer_osc = osc_of(layout.drive), osc_of(layout.forcer)
    tracking: list[int] = []
    for name, osc in (("drive", drive_osc), ("forcer", forcer_osc)):
        if osc == ref:
            continue
        owners = [n for n, o in enumerate(pll_oscs) if o == osc and n != DRIVE_PLL]
        if not owners:
            raise ValueError(
                f"the {name} carrier's mixer channel runs on oscillator {osc + 1} (index {osc}, [lockin] "
                f"fixed_channel_oscillators), but no PLL drives that oscillator (plls/n/oscselect = "
                f"{list(pll_oscs)}): the carrier cannot be locked to the drive"
            )
        if owners[0] not in tracking:
            tracking.append(owners[0])
    busy = {pll_demods[n] for n in tracking}
    drive_demod = DRIVE_DEMOD
    free = [d for d in range(N_DEMODS) if d != drive_demod and d not in busy]
    if drive_demod in busy or not free:
        raise ValueError(
            f"the PLLs {[n + 1 for n in tracking]} use demodulators {sorted(busy)} (plls/n/demodselect): no "
            "demodulator is left for the drive or the sense pickoff"
        )
    sense_demod = SENSE_DEMOD if SENSE_DEMOD in free else free[0]
    return CarrierPlan(ref, drive_osc, forcer_osc, tuple(tracking), drive_demod, sense_demod)


def forcer_amplitude(wiring: LockInWiring, gain: float) -> float:
    """Forcer carrier amplitude (fraction of range) for a forcer-path gain; LimitError outside the limits."""
    check_limit("forcer_gain", gain, *FORCER_GAIN_LIMITS, "")
    amplitude = float(wiring.forcer_carrier_amplitude) * gain
    if amplitude > 1.0:
        raise LimitError(
            f"forcer carrier amplitude = {amplitude:g} (nominal {wiring.forcer_carrier_amplitude:g} "
            f"x gain {gain:g}) is above the limit 1.0 of the output range"
        )
    return amplitude


def drive_output_range(agc: PidGains) -> float:
    """Smallest HF2 output range (V) that holds the AGC output centre +- range."""
    need = max(abs(agc.center + agc.range), abs(agc.center - agc.range))
    for r in SIGOUT_RANGES_V:
        if need <= r:
            return r
    raise LimitError(f"AGC output centre +- range reaches {need:g} V, above the HF2 output limit 10 V")


def _check_pid(name: str, g: PidGains, limit_v: float | None) -> None:
    for field in ("p", "i", "d", "setpoint", "center", "range"):
        v = getattr(g, field)
        if not math.isfinite(v):
            raise LimitError(f"{name}.{field} = {v!r} is not a finite number")
    if g.range <= 0:
        raise LimitError(f"{name}.range = {g.range:g} must be positive")
    if limit_v is not None and abs(g.center) + g.range > limit_v:
        raise LimitError(
            f"{name} output centre {g.center:g} V +- range {g.range:g} V exceeds the limit +-{limit_v:g} V"
        )


def check_setup(setup: LockInSetup, wiring: LockInWiring) -> None:
    """Every limit of a LockInSetup, checked before anything is sent (LimitError names the limit)."""
    check_limit("f0_hz", setup.f0_hz, 1.0, 100e6, "Hz")
    check_limit("pll_range_hz", setup.pll_range_hz, 1e-3, min(setup.f0_hz, 100e6), "Hz")
    check_limit("demod_rate_hz", setup.demod_rate_hz, 1.0, 460e3, "Sa/s")
    check_limit("demod_timeconstant_s", setup.demod_timeconstant_s, 780e-9, 500.0, "s")
    check_limit("demod_order", setup.demod_order, 1, 8, "")
    if int(setup.demod_order) != setup.demod_order:
        raise LimitError(f"demod_order = {setup.demod_order!r} must be an integer 1..8")
    if int(setup.auxin_averaging) != setup.auxin_averaging or not 0 <= setup.auxin_averaging <= 15:
        raise LimitError(
            f"auxin_averaging = {setup.auxin_averaging!r} must be an integer 0..15 "
            "(the AuxIns average 2^n = 1..32768 ADC samples)"
        )
    _check_pid("pll", setup.pll, None)
    _check_pid("agc", setup.agc, None)
    drive_output_range(setup.agc)
    _check_pid("rate", setup.rate, AUXOUT_LIMIT_V)
    _check_pid("quadrature", setup.quadrature, AUXOUT_LIMIT_V)
    forcer_amplitude(wiring, setup.forcer_gain)


def _pid_nodes(n: int, g: PidGains, inp: int, inch: int, out: int, outch: int) -> list[tuple[str, Any]]:
    b = f"pids/{n}/"
    return [
        (b + "enable", 0),
        (b + "input", inp),
        (b + "inputchannel", inch),
        (b + "output", out),
        (b + "outputchannel", outch),
        (b + "setpointselect", 0),
        (b + "setpoint", g.setpoint),
        (b + "p", g.p),
        (b + "i", g.i),
        (b + "d", g.d),
        (b + "center", g.center),
        (b + "range", g.range),
        (b + "outputdefaultenable", 0),
    ]


def _pll_nodes(n: int, setup: LockInSetup, wiring: LockInWiring) -> list[tuple[str, Any]]:
    """PLL n on the drive input: centre f0, range, gains, phase setpoint and filter of the configuration."""
    b = f"plls/{n}/"
    return [
        (b + "adcselect", wiring.drive_sigin),
        (b + "harmonic", 1),
        (b + "freqcenter", setup.f0_hz),
        (b + "freqrange", setup.pll_range_hz),
        (b + "setpoint", setup.pll.setpoint),
        (b + "p", setup.pll.p),
        (b + "i", setup.pll.i),
        (b + "d", setup.pll.d),
        (b + "autocenter", 0),
        (b + "autopid", 1),
        (b + "autotimeconstant", 1),
        (b + "timeconstant", setup.demod_timeconstant_s),
        (b + "order", int(setup.demod_order)),
    ]


def setup_nodes(
    setup: LockInSetup, wiring: LockInWiring, carriers: CarrierPlan, layout: MixerLayout
) -> list[tuple[str, Any]]:
    """The (relative path, value) pairs of a full configuration, loops enabled last. Call check_setup first.
    Only nodes the instrument of ``layout`` lists are named (its mixer channels); the PLLs and demodulators are
    those of ``carriers`` (carrier_plan)."""
    w = wiring
    dm, fm = layout.drive, layout.forcer
    pll_osc, drive_demod, sense_demod = carriers.ref_osc, carriers.drive_demod, carriers.sense_demod
    drange = drive_output_range(setup.agc)
    plls = (DRIVE_PLL, *carriers.tracking_plls)
    s: list[tuple[str, Any]] = [("pids/*/enable", 0)]
    s += [(f"plls/{n}/enable", 0) for n in plls]
    s += [
        (f"sigins/{w.drive_sigin}/range", SIGIN_RANGE_V),
        (f"sigins/{w.sense_sigin}/range", SIGIN_RANGE_V),
    ]
    s += [(f"oscs/{o}/freq", setup.f0_hz) for o in sorted({pll_osc, carriers.drive_osc, carriers.forcer_osc})]
    for d, sigin in ((drive_demod, w.drive_sigin), (sense_demod, w.sense_sigin)):
        b = f"demods/{d}/"
        s += [
            (b + "adcselect", sigin),
            (b + "oscselect", pll_osc),
            (b + "harmonic", 1),
            (b + "phaseshift", 0.0),
            (b + "order", int(setup.demod_order)),
            (b + "timeconstant", setup.demod_timeconstant_s),
            (b + "sinc", 0),
            (b + "trigger", 0),
            (b + "rate", setup.demod_rate_hz),
            (b + "enable", 1),
        ]
    for m in sorted({dm, fm} - {drive_demod, sense_demod}):  # an output channel's oscillator must be the PLL's
        if m < N_DEMODS:  # channels 6 and 7 have no demodulator whose oscillator could be chosen (module doc)
            s += [(f"demods/{m}/oscselect", pll_osc), (f"demods/{m}/harmonic", 1), (f"demods/{m}/phaseshift", 0.0)]
    s += [("auxins/0/averaging", int(setup.auxin_averaging))]
    for n in plls:
        s += _pll_nodes(n, setup, w)
    # outputs: drive channel and forcer carrier; every other mixer channel of the used outputs off
    used = {(w.drive_sigout, dm), (w.forcer_sigout, fm)}
    for out in sorted({w.drive_sigout, w.forcer_sigout}):
        for m in layout.channels:
            if (out, m) not in used:
                s.append((f"sigouts/{out}/enables/{m}", 0))
    s += [
        (f"sigouts/{w.drive_sigout}/range", drange),
        (f"sigouts/{w.drive_sigout}/add", 0),
        (f"sigouts/{w.drive_sigout}/offset", 0.0),
        (f"sigouts/{w.drive_sigout}/waveforms/{dm}", 0),
        (f"sigouts/{w.drive_sigout}/amplitudes/{dm}", setup.agc.center / drange),
        (f"sigouts/{w.drive_sigout}/enables/{dm}", 1),
    ]
    if w.forcer_sigout != w.drive_sigout:
        s += [
            (f"sigouts/{w.forcer_sigout}/range", FORCER_OUTPUT_RANGE_V),
            (f"sigouts/{w.forcer_sigout}/add", 0),
            (f"sigouts/{w.forcer_sigout}/offset", 0.0),
        ]
    s += [
        (f"sigouts/{w.forcer_sigout}/waveforms/{fm}", 0),
        (f"sigouts/{w.forcer_sigout}/amplitudes/{fm}", forcer_amplitude(w, setup.forcer_gain)),
        (f"sigouts/{w.forcer_sigout}/enables/{fm}", 1),
    ]
    for ch, g in ((w.rate_auxout, setup.rate), (w.quadrature_auxout, setup.quadrature)):
        s += [(f"auxouts/{ch}/outputselect", -1), (f"auxouts/{ch}/scale", 1.0), (f"auxouts/{ch}/offset", g.center)]
    s += _pid_nodes(AGC_PID, setup.agc, 2, drive_demod, w.drive_sigout, dm)
    s += _pid_nodes(RATE_PID, setup.rate, 0, sense_demod, 3, w.rate_auxout)
    s += _pid_nodes(QUAD_PID, setup.quadrature, 1, sense_demod, 3, w.quadrature_auxout)
    # switch on: outputs, PLLs, then the loops
    s += [
        (f"sigouts/{w.drive_sigout}/on", 1),
        (f"sigouts/{w.forcer_sigout}/on", 1),
        *[(f"plls/{n}/enable", 1) for n in plls],
        (f"pids/{AGC_PID}/enable", 1),
        (f"pids/{RATE_PID}/enable", 1),
        (f"pids/{QUAD_PID}/enable", 1),
    ]
    return s


def safe_nodes(wiring: LockInWiring, output_safe_v: float, layout: MixerLayout) -> list[tuple[str, Any]]:
    """Safe state: every PID off, the loop AuxOuts in manual mode at output_safe_v, forcer carrier amplitude 0,
    both signal outputs off (the resonator then rings down freely, tau = 2Q/omega). The PLL is left running: it
    drives nothing but its oscillator."""
    check_limit("output_safe_v", output_safe_v, -AUXOUT_LIMIT_V, AUXOUT_LIMIT_V, "V")
    w = wiring
    fm = layout.forcer
    s: list[tuple[str, Any]] = [("pids/*/enable", 0)]
    for ch in (w.rate_auxout, w.quadrature_auxout):
        s += [(f"auxouts/{ch}/outputselect", -1), (f"auxouts/{ch}/offset", float(output_safe_v))]
    s += [
        (f"sigouts/{w.forcer_sigout}/amplitudes/{fm}", 0.0),
        (f"sigouts/{w.forcer_sigout}/on", 0),
        (f"sigouts/{w.drive_sigout}/on", 0),
    ]
    return s
