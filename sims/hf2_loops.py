"""Which gyroscope loops the HF2 node settings close, as the physics would see them.

The twin does not trust the driver's intent: it reads the node values and decides, loop by loop, whether the
cabling of the bench (``HF2Wiring``) and the settings together close the loop. A loop that is not closed runs
open in the physics (its output sits at the value the output node holds by itself), so a wrong setting shows up
as a wrong bandwidth or no lock, as on the bench.

Rules (HF2 node semantics from the nodedoc and docs/wiring.md; the twin's reading of them):

* Reference oscillator. PLL 0 is closed if ``plls/0/enable`` = 1, ``plls/0/adcselect`` = drive_sigin and
  ``plls/0/harmonic`` = 1; it then owns oscillator ``plls/0/oscselect`` and its frequency follows the PLL
  (p Hz/deg, i Hz^2/deg, setpoint deg, freqcenter, freqrange). Otherwise the reference is the oscillator of the
  drive demodulator at ``oscs/n/freq`` (PLL open, frequency fixed).
* A *drive demod* has adcselect = drive_sigin; a *sense demod* adcselect = sense_sigin; both must use the
  reference oscillator, harmonic 1 and phaseshift 0 to feed a loop (any rotation would change the loop gain).
* AGC closed: an enabled PID with input 2 (R), inputchannel = a drive demod, setpointselect 0 (manual), output
  = drive_sigout (0 = SigOut1 amplitude, 1 = SigOut2 amplitude), outputchannel = a mixer channel m that is
  enabled on that output, whose demod m uses the reference oscillator, with the output on. Open: the drive
  voltage is the sum over such channels of amplitudes/m * range (V), times sigouts/<drive>/on.
* Mixer channels 6 and 7 have no demodulator of their own (6 demods); on an HF2 without MF they are the outputs'
  only channels (output 1 -> 6, output 2 -> 7, zhinst-utils default_output_mixer_channel). Their oscillators are
  fixed (``FIXED_CHANNEL_OSCILLATORS``): channel 7 ("Demodulator 8") runs on oscillator 2 (index 1), as the HF2
  user manual's External Reference tutorial generates Output 2's signal with "Demodulator 8 Amplitude 2 ...
  Oscillator 2 frequency"; channel 6 ("Demodulator 7") on oscillator 1 (index 0) by the same construction
  (*inferred*: the tutorial shows Output 2 only). No node selects them.
* Coherence of an output channel with the drive (``oscillator_coherence``): its oscillator is the reference, or
  it is the oscillator of another PLL n (``plls/n/oscselect``, read-only: "Index of the oscillator used",
  nodedoc_hf2.json) that is enabled on the drive input with harmonic 1 (the HF2 has two independent PLLs with the
  PLL option, HF2 user manual, PLL tab). Such a PLL locks its oscillator to the same pickoff signal, so its phase
  is the reference's plus the setpoint difference d = plls/n/setpoint - plls/0/setpoint; the carrier's in-phase
  part is cos(d) of its amplitude. It tracks while the drive frequency (the reference oscillator's) lies within
  freqcenter +- freqrange, checked at the start of every poll; out of range it does not lock, its oscillator is
  not coherent and the channel drives nothing coherent. The demodulator it uses (``plls/n/demodselect``; the
  manual: "Demodulators that are used by an active PLL are set to read-only values") demodulates the drive input
  on its oscillator, so it cannot be the sense demodulator. Any other oscillator runs at its fixed ``oscs/n/freq``:
  a carrier there is not coherent with the mode and averages out (gain 0).
* A branch the instrument does not list (no PLL or PID option) counts as open.
* Rate loop closed: an enabled PID with input 0 (X), inputchannel = a sense demod, setpointselect 0, output 3
  (AuxOut offset), outputchannel = rate_auxout, and that AuxOut in manual mode (outputselect = -1). Quadrature:
  the same with input 1 (Y) and quadrature_auxout. Open: the AuxOut's own offset in manual mode, else 0 V
  (the twin does not model an AuxOut showing a demod quantity).
* Forcer-path gain = sigouts/<forcer_sigout>/amplitudes/m / forcer_carrier_amplitude * on * enables/m * cos(d),
  with m = wiring.forcer_mixer_channel and d the phase offset of m's oscillator (above); 0 if that oscillator is
  not coherent with the drive.
* The demod filter the physics applies (time constant, order) is that of the sense demod used by the rate PID
  (else the first sense demod, else demod 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

from sims.gyro import LoopSettings, PidSettings, PllSettings

N_DEMODS, N_PIDS, N_MIXER_CHANNELS = 6, 4, 8
PID_INPUT_X, PID_INPUT_Y, PID_INPUT_R = 0, 1, 2
PID_OUTPUT_AUXOUT = 3


class NodeReader(Protocol):
    def peek(self, rel_or_abs: str) -> Any: ...
    def has(self, rel_or_abs: str) -> bool: ...


FIXED_CHANNEL_OSCILLATORS = {6: 0, 7: 1}  # mixer channel -> oscillator index (module doc: HF2 user manual)
N_PLLS = 2


def channel_oscillator(nodes: NodeReader, m: int) -> int:
    """The oscillator output mixer channel m runs on: that of demod m, or the fixed one of channels 6 and 7."""
    return FIXED_CHANNEL_OSCILLATORS[m] if m >= N_DEMODS else int(nodes.peek(f"demods/{m}/oscselect"))


@dataclass(frozen=True)
class TrackingPll:
    """A PLL other than the reference's, locked on the drive input: its oscillator follows the drive."""

    index: int
    osc: int
    demod: int  # plls/n/demodselect: the demodulator the PLL takes over (its input and oscillator)
    center_hz: float
    range_hz: float
    offset_deg: float  # its setpoint minus the reference PLL's

    def tracks(self, drive_hz: float) -> bool:
        """Whether the drive frequency lies within the PLL's output range (it can lock)."""
        return abs(drive_hz - self.center_hz) <= self.range_hz


def tracking_plls(nodes: NodeReader, wiring: HF2Wiring, ref_osc: int, pll_closed: bool) -> dict[int, TrackingPll]:
    """The PLLs besides PLL 1 enabled on the drive input with harmonic 1, by the oscillator they drive (none if
    PLL 1 is not closed: there is no drive-locked reference to be coherent with)."""
    out: dict[int, TrackingPll] = {}
    for n in range(1, N_PLLS):
        b = f"plls/{n}/"
        if not pll_closed or not nodes.has(b + "enable") or not int(nodes.peek(b + "enable")):
            continue
        if int(nodes.peek(b + "adcselect")) != wiring.drive_sigin or int(nodes.peek(b + "harmonic")) != 1:
            continue
        osc = int(nodes.peek(b + "oscselect"))
        if osc == ref_osc:
            continue
        out[osc] = TrackingPll(
            index=n,
            osc=osc,
            demod=int(nodes.peek(b + "demodselect")),
            center_hz=float(nodes.peek(b + "freqcenter")),
            range_hz=float(nodes.peek(b + "freqrange")),
            offset_deg=float(nodes.peek(b + "setpoint")) - float(nodes.peek("plls/0/setpoint")),
        )
    return out


def oscillator_coherence(osc: int, ref_osc: int, trackers: dict[int, TrackingPll]) -> float | None:
    """The phase offset (deg) of oscillator `osc` from the reference when it is coherent with the drive (0 for
    the reference itself), None when it runs at a fixed frequency (module doc)."""
    if osc == ref_osc:
        return 0.0
    tracker = trackers.get(osc)
    return None if tracker is None else tracker.offset_deg


@dataclass
class HF2Wiring:
    """The cables of the bench (docs/wiring.md): the [lockin] wiring fields of qmg_lab/config/schema.py
    LockInSection, which declares their defaults and bounds once; the station passes them validated, and nothing
    here checks them again.

    forcer_mixer_channel: the mixer channel of forcer_sigout that carries the forcer carrier (twin addition).
    """

    drive_sigin: int
    sense_sigin: int
    drive_sigout: int
    forcer_sigout: int
    forcer_carrier_amplitude: float  # nominal carrier amplitude (fraction of range) = forcer-path gain 1.0
    rate_auxout: int
    quadrature_auxout: int
    rate_auxin: int
    dither_auxin: int
    forcer_mixer_channel: int


@dataclass
class LoopPlan:
    """The loops as the node settings close them."""

    settings: LoopSettings
    ref_osc: int
    pll_closed: bool
    pid_of: dict[str, int | None]  # "agc"/"rate"/"quadrature" -> the PID index closing it (None = open)
    open_reasons: dict[str, str] = field(default_factory=dict)
    sense_demod: int = 1
    drive_demod: int = 0
    trackers: dict[int, TrackingPll] = field(default_factory=dict)  # PLLs besides PLL 1 on the drive, by osc
    forcer_tracker: TrackingPll | None = None  # the PLL the forcer carrier's coherence depends on (if not PLL 1)


def _demod_ok(nodes: NodeReader, d: int, sigin: int, ref_osc: int) -> bool:
    return (
        0 <= d < N_DEMODS
        and int(nodes.peek(f"demods/{d}/adcselect")) == sigin
        and int(nodes.peek(f"demods/{d}/oscselect")) == ref_osc
        and int(nodes.peek(f"demods/{d}/harmonic")) == 1
        and abs(float(nodes.peek(f"demods/{d}/phaseshift"))) < 1e-9
    )


def _pid(nodes: NodeReader, n: int, *, enabled: bool | None = None, center: float | None = None) -> PidSettings:
    def g(leaf: str) -> float:
        return float(nodes.peek(f"pids/{n}/{leaf}"))

    return PidSettings(
        enabled=bool(int(nodes.peek(f"pids/{n}/enable"))) if enabled is None else enabled,
        p=g("p"),
        i=g("i"),
        d=g("d"),
        setpoint=g("setpoint"),
        center=g("center") if center is None else center,
        range=g("range"),
    )


def _find_pid(nodes: NodeReader, want: dict[str, int], check_in: Any, check_out: Any) -> int | None:
    for n in range(N_PIDS):
        if not nodes.has(f"pids/{n}/enable"):
            continue
        if not int(nodes.peek(f"pids/{n}/enable")) or int(nodes.peek(f"pids/{n}/setpointselect")) != 0:
            continue
        if int(nodes.peek(f"pids/{n}/input")) != want["input"]:
            continue
        if not check_in(int(nodes.peek(f"pids/{n}/inputchannel"))):
            continue
        if int(nodes.peek(f"pids/{n}/output")) != want["output"]:
            continue
        if check_out(int(nodes.peek(f"pids/{n}/outputchannel"))):
            return n
    return None


def identify_loops(nodes: NodeReader, wiring: HF2Wiring) -> LoopPlan:
    """Read the node values and return the LoopSettings the physics runs under (rules in the module doc)."""
    reasons: dict[str, str] = {}
    pll_on = nodes.has("plls/0/enable") and bool(int(nodes.peek("plls/0/enable")))
    pll_closed = (
        pll_on and int(nodes.peek("plls/0/adcselect")) == wiring.drive_sigin and int(nodes.peek("plls/0/harmonic")) == 1
    )
    drive_candidates = [d for d in range(N_DEMODS) if int(nodes.peek(f"demods/{d}/adcselect")) == wiring.drive_sigin]
    if pll_closed:
        ref_osc = int(nodes.peek("plls/0/oscselect"))
        pll = PllSettings(
            enabled=True,
            p=float(nodes.peek("plls/0/p")),
            i=float(nodes.peek("plls/0/i")),
            setpoint_deg=float(nodes.peek("plls/0/setpoint")),
            center_hz=float(nodes.peek("plls/0/freqcenter")),
            range_hz=float(nodes.peek("plls/0/freqrange")),
        )
    else:
        reasons["pll"] = "plls/0 disabled or not on the drive input with harmonic 1"
        d0 = drive_candidates[0] if drive_candidates else 0
        ref_osc = int(nodes.peek(f"demods/{d0}/oscselect"))
        pll = PllSettings(
            enabled=False,
            center_hz=float(nodes.peek(f"oscs/{ref_osc}/freq")),
            range_hz=float(nodes.peek("plls/0/freqrange")) if pll_on else PllSettings().range_hz,
        )

    def drive_ok(d: int) -> bool:
        return _demod_ok(nodes, d, wiring.drive_sigin, ref_osc)

    dso = wiring.drive_sigout
    trackers = tracking_plls(nodes, wiring, ref_osc, pll_closed)
    pll_demods = {t.demod for t in trackers.values()}

    def sense_ok(d: int) -> bool:  # a demodulator a tracking PLL uses demodulates the drive input on its osc
        return d not in pll_demods and _demod_ok(nodes, d, wiring.sense_sigin, ref_osc)

    def drive_channel_ok(m: int) -> bool:
        return (
            nodes.has(f"sigouts/{dso}/enables/{m}")
            and int(nodes.peek(f"sigouts/{dso}/on")) == 1
            and int(nodes.peek(f"sigouts/{dso}/enables/{m}")) in (1, 3)
            and oscillator_coherence(channel_oscillator(nodes, m), ref_osc, trackers) == 0.0
        )

    # AGC
    agc_n = _find_pid(nodes, {"input": PID_INPUT_R, "output": dso}, drive_ok, drive_channel_ok)
    if agc_n is not None:
        agc = _pid(nodes, agc_n)
    else:
        reasons["agc"] = "no enabled PID on R of a drive demod writing an enabled drive mixer channel"
        on = int(nodes.peek(f"sigouts/{dso}/on"))
        rng = float(nodes.peek(f"sigouts/{dso}/range"))
        v = (
            sum(
                float(nodes.peek(f"sigouts/{dso}/amplitudes/{m}")) * rng
                for m in range(N_MIXER_CHANNELS)
                if drive_channel_ok(m)
            )
            if on
            else 0.0
        )
        agc = PidSettings(enabled=False, center=v)

    def aux_manual(ch: int) -> bool:
        return int(nodes.peek(f"auxouts/{ch}/outputselect")) == -1

    def aux_open_value(ch: int) -> float:
        return float(nodes.peek(f"auxouts/{ch}/offset")) if aux_manual(ch) else 0.0

    loops: dict[str, PidSettings] = {}
    pid_of: dict[str, int | None] = {"agc": agc_n}
    for name, inp, ch in (
        ("rate", PID_INPUT_X, wiring.rate_auxout),
        ("quadrature", PID_INPUT_Y, wiring.quadrature_auxout),
    ):
        n = _find_pid(
            nodes, {"input": inp, "output": PID_OUTPUT_AUXOUT}, sense_ok, lambda c, ch=ch: c == ch and aux_manual(ch)
        )
        pid_of[name] = n
        if n is not None:
            loops[name] = _pid(nodes, n)
        else:
            reasons[name] = f"no enabled PID on {'XY'[inp]} of a sense demod writing AuxOut {ch} in manual mode"
            loops[name] = PidSettings(enabled=False, center=aux_open_value(ch))

    # demod filter: that of the sense demod the rate PID reads
    if pid_of["rate"] is not None:
        sense_demod = int(nodes.peek(f"pids/{pid_of['rate']}/inputchannel"))
    else:
        cands = [d for d in range(N_DEMODS) if int(nodes.peek(f"demods/{d}/adcselect")) == wiring.sense_sigin]
        sense_demod = cands[0] if cands else 1
    drive_demod = (
        int(nodes.peek(f"pids/{agc_n}/inputchannel"))
        if agc_n is not None
        else (drive_candidates[0] if drive_candidates else 0)
    )

    fso, m = wiring.forcer_sigout, wiring.forcer_mixer_channel
    listed = nodes.has(f"sigouts/{fso}/enables/{m}")
    forcer_osc = channel_oscillator(nodes, m) if listed else -1
    offset_deg = oscillator_coherence(forcer_osc, ref_osc, trackers) if listed else None
    if not listed:
        reasons["forcer"] = f"the forcer output lists no mixer channel {m}"
    elif offset_deg is None:
        reasons["forcer"] = (
            f"mixer channel {m} of the forcer output runs on oscillator {forcer_osc}, which no PLL locks to the drive"
        )
    gain = (
        0.0
        if offset_deg is None
        else (
            float(nodes.peek(f"sigouts/{fso}/amplitudes/{m}"))
            / wiring.forcer_carrier_amplitude
            * int(nodes.peek(f"sigouts/{fso}/on"))
            * (int(nodes.peek(f"sigouts/{fso}/enables/{m}")) in (1, 3))
            * math.cos(math.radians(offset_deg))
        )
    )

    settings = LoopSettings(
        pll=pll,
        agc=agc,
        rate=loops["rate"],
        quadrature=loops["quadrature"],
        forcer_gain=float(gain),
        demod_timeconstant_s=float(nodes.peek(f"demods/{sense_demod}/timeconstant")),
        demod_order=int(nodes.peek(f"demods/{sense_demod}/order")),
    )
    return LoopPlan(
        settings=settings,
        ref_osc=ref_osc,
        pll_closed=pll_closed,
        pid_of=pid_of,
        open_reasons=reasons,
        sense_demod=sense_demod,
        drive_demod=drive_demod,
        trackers=trackers,
        forcer_tracker=trackers.get(forcer_osc) if offset_deg is not None else None,
    )
