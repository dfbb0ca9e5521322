"""The watch page's Bokeh document: a "now" panel, a header line, and eight plots against run time (one shared
toolbar), fed by a RunFollower.

The now panel (top, above the plots) is what a person at the bench reads at a glance, each value at the common
data horizon h of the page (follow.py; the header's "data to t = h"):

    status      running | completed | aborted: <abort_reason> | process died: check the instruments (a "running"
                file whose writer is gone: the instruments were not put in their safe state by the run)
    SF          the CLSF SF-change estimate, its trailing 60 s mean at h, in ppm: SF/SF_0 - 1 with SF_0 the scale
                factor when the CLSF reference was formed (the start), so it is the change since the start; and
                the true SF change of the last completed +-rate step pair against the first (follow.py)
    chamber     the setpoint and the air temperature of the last /chamber row; the gyro temperature of the last
                /truth row read (twins; the bench file has no gyro temperature)
    PLL         /lockin/pll_locked of the last row read: locked, or NOT LOCKED (a file without the column: not
                recorded)
    step        the current step (the first planned step not completed), its kind and its time left:
                t_start + d - h, t_start the end of the last completed step, d its planned duration
    end         while running: now + R / v, R the plan's remaining run time (the current step's time left plus the
                planned durations of the steps after it) and v the run time the page saw pass per wall second over
                the last minute (1 on the bench in real time, hundreds on the twins); once ended: the file's last
                modification time, and the steps not run
    banner      faults, reconnects, suspensions (and whether one is still on), the abort, and the safe-state
                outcome, from /events; data loss (follow.missing_samples); after a dead writer: the instruments
                may not be in a safe state

Plots (x: run time in s since the file's t0_unix, shared by all but the events' categories):

    sf        CLSF SF-change estimate per dither period (ppm) as a min/max envelope (a shaded band: its lower
              and upper edges are each bin's minimum and maximum, so a long run's scatter does not alias into a
              zig-zag), its trailing 60 s moving mean, and the true SF change from each completed +-rate step
              pair (follow.py), placed on the CLSF mean at the first pair so both read as changes from there
    gain      CLSF gain correction g_c - 1 (ppm; 0 unless the run is in correct mode)
    temp      chamber air temperature, its setpoint, and (twins) the gyro temperature from /truth
    table     table rate commanded and measured (deg/s)
    drive     drive amplitude R (V)
    pll       PLL oscillator frequency (Hz): steady while the loop is locked; unlocked samples in red
    steps     the plan as a timeline: completed steps by kind, the current step marked red, the remaining
              planned steps grey at their planned durations
    events    every /events row by kind (hover: instrument and message)

Traces from the lock-in stream (drive amplitude, PLL frequency, gyro temperature) are read in sampled chunks
(follow.py) and drawn as points, so that no line is drawn across a stretch that was not read.

Each trace is a `Trace` (a `Band` for the envelope): new rows are reduced by min/max decimation
(qmg_lab/data/decimate.py) and streamed to the browser (ColumnDataSource.stream); once a trace holds more than
2 x MAX_POINTS points it is decimated again to MAX_POINTS and sent whole. The browser thus never holds more than
about 2 x MAX_POINTS points per trace, whatever the run's length.

What the browser redraws: BokehJS draws the page on canvases, in software on many lab PCs and on the twins' own
cores, so an update costs what it makes the browser do, not what it sends. Three things kept every update
from costing a whole new layout of the page: the now panel and the header are a document root of their own
(`_layout`: their new text every update lays out the text, not the plots); each numeric plot's y range is a
`StableRange`, which moves only when the data leave it (new tick labels make BokehJS measure and align every
axis again); and the legends are drawn from stand-in glyphs on a source that never changes (`_keyed`: BokehJS
3.9 rebuilds a legend's entries whenever anything under its renderers changes). Only the top and the bottom plot
label the shared time axis. docs/performance.md has the browser's CPU per update before and after.

Timing: the page checks the file's status every CHECK_MS and reads its new rows every POLL_MS; a change of status
(the run ended, was stopped, or its process died) is sent to the browser at once, alone (the now panel's text),
and the file is read and redrawn on the next tick: the final status is on the page within CHECK_MS plus the
check and one small message.
"""

from __future__ import annotations

import html
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from bokeh.document import Document
from bokeh.layouts import column, gridplot
from bokeh.models import ColumnDataSource, DataRange1d, FactorRange, HoverTool, Range1d
from bokeh.models.annotations import Legend
from bokeh.models.widgets import Div
from bokeh.plotting import figure

from qmg_lab.clsf.moving_mean import SF_MEAN_WINDOW_S as MOVING_MEAN_S
from qmg_lab.data.decimate import minmax
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS
from qmg_lab.storage.records import EVENT_KINDS
from qmg_lab.watch.follow import PPM, RunFollower, Update, planned_kinds

MAX_POINTS = 1000  # about a plot's width in pixels
CHUNK_BINS = MAX_POINTS // 5
#: the page reads the file and redraws every 3 s: a block is on the page within 3 s of the writer's flush plus the
#: draw. Beside a twin campaign the browser's drawing is the page's main cost, paid once per update
#: (docs/performance.md has it per update, and the campaign's slowdown). A run's end is shown within CHECK_MS.
POLL_MS = 3000
#: ... and checks the file's status (its root attributes and its writer's liveness: no data) every 0.5 s
CHECK_MS = 500
#: the run-time speed v (run s per wall s) of the expected end is taken over the last SPEED_WINDOW_S wall seconds
SPEED_WINDOW_S = 60.0
STEP_FAMILIES = ("lock", "dither", "soak", "rate", "hold", "sine", "level", "return")
PLOTS = ("sf", "gain", "temp", "table", "drive", "pll", "steps", "events")  # model names: plot_<name>
TIME_LABELLED = ("sf", "events")  # the plots that label the shared time axis: the top one and the bottom one
DIED = "process died: check the instruments"


class Trace:
    """One line of a plot, kept bounded (module docstring)."""

    def __init__(self, name: str) -> None:
        self.source = ColumnDataSource({"t": [], "y": []}, name=name)
        self.t = np.zeros(0)
        self.y = np.zeros(0)

    def add(self, t: np.ndarray, y: np.ndarray) -> None:
        if t.shape[0] == 0:
            return
        t, y = minmax(t, y, CHUNK_BINS)
        self.t, self.y = np.concatenate((self.t, t)), np.concatenate((self.y, y))
        if self.t.shape[0] > 2 * MAX_POINTS:
            self.t, self.y = minmax(self.t, self.y, MAX_POINTS // 2)
            self.source.data = {"t": self.t, "y": self.y}
        else:
            self.source.stream({"t": t, "y": y})

    def clear(self) -> None:
        self.t, self.y = np.zeros(0), np.zeros(0)
        self.source.data = {"t": [], "y": []}


def _envelope(t: np.ndarray, lo: np.ndarray, hi: np.ndarray, bins: int) -> tuple[np.ndarray, ...]:
    """(t, lo, hi) merged into at most `bins` bins of equal time span: each bin's last time, the minimum of its
    lows and the maximum of its highs."""
    if t.shape[0] <= bins:
        return t, lo, hi
    edges = np.linspace(t[0], t[-1], bins + 1)[1:-1]
    starts = np.unique(np.concatenate(([0], np.searchsorted(t, edges, side="right"))))
    starts = starts[starts < t.shape[0]]
    ends = np.concatenate((starts[1:], [t.shape[0]])) - 1
    return t[ends], np.minimum.reduceat(lo, starts), np.maximum.reduceat(hi, starts)


class Band:
    """A min/max envelope of one trace (`lo` <= y <= `hi` in each bin of time), kept bounded like `Trace`."""

    def __init__(self, name: str) -> None:
        self.source = ColumnDataSource({"t": [], "lo": [], "hi": []}, name=name)
        self.t, self.lo, self.hi = np.zeros(0), np.zeros(0), np.zeros(0)

    def add(self, t: np.ndarray, y: np.ndarray) -> None:
        if t.shape[0] == 0:
            return
        t, lo, hi = _envelope(t, y, y, CHUNK_BINS)
        self.t, self.lo, self.hi = (np.concatenate(p) for p in ((self.t, t), (self.lo, lo), (self.hi, hi)))
        if self.t.shape[0] > 2 * MAX_POINTS:
            self.t, self.lo, self.hi = _envelope(self.t, self.lo, self.hi, MAX_POINTS)
            self.source.data = {"t": self.t, "lo": self.lo, "hi": self.hi}
        else:
            self.source.stream({"t": t, "lo": lo, "hi": hi})

    def clear(self) -> None:
        self.t, self.lo, self.hi = np.zeros(0), np.zeros(0), np.zeros(0)
        self.source.data = {"t": [], "lo": [], "hi": []}


def _nice_step(span: float) -> float:
    """The smallest 1, 2 or 5 x 10^k that is >= span (span > 0)."""
    k = 10.0 ** math.floor(math.log10(span))
    return next(m * k for m in (1.0, 2.0, 5.0, 10.0) if m * k >= span * (1 - 1e-12))


class StableRange:
    """A plot's y range that moves only when its data leave it.

    Bokeh's DataRange1d follows the data at every update, and every new range gives the axis new tick labels:
    the browser then lays out the whole page again (BokehJS measures every axis's labels to align the stacked
    plots), which on a software-drawn page cost as much as drawing it. A trace keeps its whole run (min/max
    decimation keeps every extreme), so the data's extent [lo, hi] only grows, until a resume starts the page
    again (`clear`). The first range is [lo - PAD w, hi + PAD w], w = hi - lo (flat data: w = |hi| 1e-6, or 1
    at zero); when the data leave [a, b], each side they left by moves out by b - a beyond them, so the span at
    least doubles and a steady drift changes the range a logarithmic number of times, not at every update.
    Both ends are rounded outwards to the 1-2-5 step >= span / 5. Reset (the toolbar) returns to [a, b].
    """

    PAD = 0.1

    def __init__(self) -> None:
        self.range = Range1d(start=0.0, end=1.0)
        self.bounds: tuple[float, float] | None = None

    def cover(self, lo: float, hi: float) -> None:
        """Make [a, b] hold [lo, hi], the minimum and maximum of all the plot's data."""
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return
        if self.bounds is None:
            w = hi - lo if hi > lo else (abs(hi) * 1e-6 or 1.0)
            a, b = lo - self.PAD * w, hi + self.PAD * w
        else:
            a, b = self.bounds
            if a <= lo and hi <= b:
                return
            span = b - a
            a, b = (lo - span if lo < a else a), (hi + span if hi > b else b)
        step = _nice_step((b - a) / 5.0)
        self.bounds = (math.floor(a / step) * step, math.ceil(b / step) * step)
        a, b = self.bounds
        self.range.update(start=a, end=b, reset_start=a, reset_end=b)

    def clear(self) -> None:
        self.bounds = None


def _extent(*arrays: Any) -> tuple[float, float]:
    """(min, max) over the finite values of all arrays; (nan, nan) if none."""
    values = [np.asarray(a, dtype=float) for a in arrays]
    values = [v[np.isfinite(v)] for v in values if v.shape[0]]
    values = [v for v in values if v.shape[0]]
    if not values:
        return math.nan, math.nan
    return min(float(v.min()) for v in values), max(float(v.max()) for v in values)


def _clock(s: float) -> str:
    if not math.isfinite(s):
        return "-"
    h, rem = divmod(int(round(max(s, 0.0))), 3600)
    return f"{h}:{rem // 60:02d}:{rem % 60:02d}"


def _wall(unix_s: float) -> str:
    """A wall-clock time on this machine's clock: HH:MM:SS, with the date when it is not today."""
    t = time.localtime(unix_s)
    today = time.localtime()
    return time.strftime("%H:%M:%S" if t[:3] == today[:3] else "%Y-%m-%d %H:%M:%S", t)


def _family(kind: str) -> str:
    return kind.split(":", 1)[0]


def _identity(config_toml: str) -> tuple[str, list[float], float]:
    """("name (kind, CLSF mode)", each planned step's duration in s, the plan's settle_s) from the stored
    configuration, with the schema's defaults; ("?", [], 0) if it cannot be read."""
    from qmg_lab.campaign.plan import build_plan
    from qmg_lab.config.schema import ConfigError, parse_config

    try:
        cfg = parse_config(config_toml)
        steps = build_plan(cfg)
    except (ConfigError, ValueError):
        return "? (stored configuration not readable)", [], 0.0
    name = f"<b>{html.escape(cfg.campaign.name)}</b> ({cfg.campaign.kind}, CLSF {cfg.clsf.mode})"
    return name, [s.duration_s for s in steps], float(cfg.plan.settle_s)


def _degc(v: float | None) -> str:
    return f"{v:.2f}" if v is not None else "-"


def _value(name: str, text: str) -> str:
    """A value of the now panel, findable by its class (the browser test reads them)."""
    return f"<span class='now-{name}'>{html.escape(text)}</span>"


def _run_context(attrs: dict[str, Any]) -> str:
    """Who ran it, on which device, why (storage.layout.RUN_CONTEXT_ATTRS), as HTML; "" when none is given."""
    given = [(k.replace("_", " "), str(attrs.get(k, ""))) for k in RUN_CONTEXT_ATTRS]
    return "".join(f"; {html.escape(k)}: {html.escape(v)}" for k, v in given if v)


class WatchPage:
    """The page of one browser session: its Bokeh models and the follower that feeds them."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.follower = RunFollower(path)
        self.settle_s = 0.0
        self.durations: list[float] | None = None
        self.identity = ""
        self.last_t = math.nan  # the page's data horizon (s of run time)
        self.file_steps: dict[str, np.ndarray] = {}  # /steps as last read
        self.status = ""  # the status as the page shows it (_status)
        self.unlocked_at = math.nan  # run time of the last unlocked /lockin row read
        self.lost = 0  # /lockin samples seen missing in the stretches read (follow.missing_samples)
        self.seen: list[tuple[float, float]] = []  # (wall s, horizon s) of each poll while running
        self.last_poll = -math.inf
        self.last_up: Update | None = None  # the last poll's findings (check shows a new status with them)
        self.doc: Document | None = None
        self.traces = {
            n: Trace(n)
            for n in (
                "sf_mean",
                "gain",
                "chamber_air",
                "chamber_setpoint",
                "gyro_temperature",
                "table_command",
                "table_measured",
                "drive_amplitude",
                "pll_frequency",
            )
        }
        self.sf_band = Band("sf_period")
        self.unlocked = ColumnDataSource({"t": [], "y": []}, name="pll_unlocked")
        self.pairs = ColumnDataSource({"t": [], "y": []}, name="sf_pairs")
        self.steps = ColumnDataSource(
            {"left": [], "right": [], "family": [], "label": [], "color": []}, name="steps_timeline"
        )
        self.events = ColumnDataSource({"t": [], "kind": [], "instrument": [], "message": []}, name="events")
        # fixed heights: a new text then needs no new layout of the plots below it
        self.now = Div(text=f"<b>{html.escape(path.name)}</b>: loading ...", name="now", sizing_mode="stretch_width")
        self.now.height = 150
        self.header = Div(
            text=f"<b>{html.escape(path.name)}</b>: opening ...", name="header", height=44, sizing_mode="stretch_width"
        )
        self.polls = ColumnDataSource({"n": [0]}, name="polls")  # how many times the page has read the file
        # the legends' stand-in glyphs draw from this source, which never changes (_keyed): one row whose
        # coordinates are NaN, so it draws nothing on the plots and gives each legend swatch a row to draw
        nan = np.full(1, np.nan)
        key = {c: nan for c in ("t", "y", "lo", "hi", "left", "right")}
        self.key_source = ColumnDataSource(
            {**key, "family": [STEP_FAMILIES[0]], "kind": [EVENT_KINDS[0]]}, name="legend_key"
        )
        self.y_ranges: dict[str, StableRange] = {}
        self.text, self.plots = self._layout()

    # ---- layout ------------------------------------------------------------------------------------------

    def _figure(self, name: str, title: str, ylabel: str, x_range: DataRange1d | None, **kw: Any) -> Any:
        """A plot of the stack. Its legend (on the right) is drawn from stand-ins (`_keyed`); only the top and
        the bottom plot label the shared time axis (the plots between keep its grid lines)."""
        if "y_range" not in kw:
            kw["y_range"] = self.y_ranges.setdefault(name, StableRange()).range
        fig = figure(
            name=f"plot_{name}",
            title=title,
            height=kw.pop("height", 170),
            sizing_mode="stretch_width",
            x_range=x_range if x_range is not None else DataRange1d(),
            tools="pan,xwheel_zoom,box_zoom,reset,save",
            active_scroll="xwheel_zoom",
            **kw,
        )
        fig.yaxis.axis_label = ylabel
        if name in TIME_LABELLED:
            fig.xaxis.axis_label = "run time [s]"
        else:
            fig.xaxis.visible = False
        fig.add_layout(Legend(location="top_left"), "right")
        return fig

    def _keyed(self, fig: Any, glyph: str, label: str, source: ColumnDataSource, **kw: Any) -> None:
        """Draw `glyph` from `source`, and its legend entry from the same glyph on `key_source`, which never
        changes: BokehJS 3.9's legend builds its entries again (new DOM elements, a canvas each) whenever
        anything under its renderers changes, which for a renderer of a streamed source was every update. (An
        empty source would not do: the legend draws a swatch from a row of its renderer's data.)"""
        getattr(fig, glyph)(source=source, **kw)
        getattr(fig, glyph)(source=self.key_source, legend_label=label, **kw)

    def _line(self, fig: Any, trace: str, label: str, color: str, **kw: Any) -> None:
        self._keyed(fig, "line", label, self.traces[trace].source, x="t", y="y", color=color, **kw)

    def _dots(self, fig: Any, trace: str, label: str, color: str) -> None:
        """A lock-in-rate trace: read in sampled chunks (follow.py), so drawn as points: no line across a gap."""
        self._keyed(fig, "scatter", label, self.traces[trace].source, x="t", y="y", color=color, size=2)

    def _layout(self) -> tuple[Any, Any]:
        """(the text: now panel and header; the plots): two roots of the document, so that a new text (every
        update) lays out the text alone, not the plots below it."""
        sf = self._figure("sf", "scale factor", "SF change [ppm]", None)
        x = self.x_range = sf.x_range
        band = dict(x="t", y1="lo", y2="hi", color="#cccccc", alpha=0.7)
        self._keyed(sf, "varea", "CLSF, each period (min-max)", self.sf_band.source, **band)
        self._line(sf, "sf_mean", "CLSF, 60 s mean", "#1f77b4", line_width=2)
        self._keyed(sf, "scatter", "true SF, step pairs", self.pairs, x="t", y="y", size=8, color="#d62728")
        gain = self._figure("gain", "CLSF gain correction", "g_c - 1 [ppm]", x)
        self._line(gain, "gain", "g_c - 1", "#ff7f0e")
        temp = self._figure("temp", "temperatures", "degC", x)
        self._line(temp, "chamber_air", "chamber air", "#2ca02c", line_width=2)
        self._line(temp, "chamber_setpoint", "setpoint", "#000000", line_dash="dashed")
        self._dots(temp, "gyro_temperature", "gyro (twin)", "#9467bd")
        table = self._figure("table", "table rate", "deg/s", x)
        self._line(table, "table_command", "commanded", "#000000", line_dash="dashed")
        self._line(table, "table_measured", "measured", "#1f77b4")
        drive = self._figure("drive", "drive amplitude", "R [V]", x)
        self._dots(drive, "drive_amplitude", "drive R", "#8c564b")
        pll = self._figure("pll", "PLL frequency (steady while locked)", "Hz", x)
        self._dots(pll, "pll_frequency", "PLL oscillator", "#17becf")
        self._keyed(pll, "scatter", "PLL not locked", self.unlocked, x="t", y="y", size=5, color="#d62728")
        steps = self._figure("steps", "plan", "", x, y_range=FactorRange(factors=list(STEP_FAMILIES)), height=200)
        bars = dict(y="family", left="left", right="right", height=0.7)
        steps.hbar(color="color", source=self.steps, **bars)
        for label, color in (("completed", "#1f77b4"), ("current", "#d62728"), ("planned", "#cccccc")):
            steps.hbar(color=color, source=self.key_source, legend_label=label, **bars)
        steps.add_tools(HoverTool(tooltips=[("step", "@label"), ("from", "@left{0.0} s"), ("to", "@right{0.0} s")]))
        events = self._figure("events", "events", "", x, y_range=FactorRange(factors=list(EVENT_KINDS)), height=220)
        self._keyed(events, "scatter", "event", self.events, x="t", y="kind", size=9, color="#d62728")
        events.add_tools(HoverTool(tooltips=[("t", "@t{0.0} s"), ("", "@instrument: @message")]))
        # one toolbar for all the plots (their tools merged): pan or zoom one and all follow the shared time axis
        plots = gridplot(
            [[f] for f in (sf, gain, temp, table, drive, pll, steps, events)],
            merge_tools=True,
            toolbar_location="right",
            sizing_mode="stretch_width",
        )
        return column(self.now, self.header, sizing_mode="stretch_width"), plots

    def _cover_ranges(self) -> None:
        """Each numeric plot's y range over all its data (StableRange)."""
        tr = self.traces
        data = {
            "sf": (self.sf_band.lo, self.sf_band.hi, tr["sf_mean"].y, self.pairs.data["y"]),
            "gain": (tr["gain"].y,),
            "temp": (tr["chamber_air"].y, tr["chamber_setpoint"].y, tr["gyro_temperature"].y),
            "table": (tr["table_command"].y, tr["table_measured"].y),
            "drive": (tr["drive_amplitude"].y,),
            "pll": (tr["pll_frequency"].y, self.unlocked.data["y"]),
        }
        for name, arrays in data.items():
            self.y_ranges[name].cover(*_extent(*arrays))

    # ---- updates -----------------------------------------------------------------------------------------

    def attach(self, doc: Document) -> None:
        """Add the page to a document. Served (a browser session), the first read of the file follows on the next
        tick, so the page is up at once and says it is loading until the file is drawn; a bare document (tests,
        benchmarks) is fed at once."""
        doc.title = f"qmg-lab watch: {self.path.name}"
        doc.add_root(self.text)
        doc.add_root(self.plots)
        doc.add_root(self.polls)
        self.doc = doc
        if doc.session_context is None:
            self.update()
        else:
            doc.add_next_tick_callback(self.update)
        doc.add_periodic_callback(self.check, CHECK_MS)

    def check(self) -> None:
        """Every CHECK_MS: read and redraw if POLL_MS has passed, or at once if the file's status changed."""
        if time.monotonic() - self.last_poll >= POLL_MS / 1000.0 - 0.05:
            self.update()
            return
        attrs = self.follower.attrs()
        if attrs is None or self.last_up is None:
            return
        status = self._status(attrs)
        if status != self.status:
            # the new status first, alone (a small message the browser shows at once: text, no plot to draw),
            # then the whole read and redraw on the next tick
            self.status = status
            up = self.last_up
            up.attrs = attrs
            self.now.text = self._now(up)
            if self.doc is not None and self.doc.session_context is not None:
                self.doc.add_next_tick_callback(self.update)
            else:
                self.update()

    def update(self) -> None:
        """One poll of the file; every change to the page's models goes to the browser as one message (held
        and combined), so the browser draws the page once per poll, not once per trace."""
        self.last_poll = time.monotonic()
        if self.doc is None:
            self._update()
            return
        self.doc.hold("combine")
        try:
            self._update()
        finally:
            self.doc.unhold()

    def _update(self) -> None:
        attrs = self.follower.attrs()
        status = self._status(attrs) if attrs is not None else ""
        up = self.follower.poll(writer_gone=status == DIED)
        self.polls.data = {"n": [self.polls.data["n"][0] + 1]}
        if not up.ready:
            self.header.text = f"<b>{html.escape(self.path.name)}</b>: {html.escape(up.problem)}"
            self.now.text = self.header.text
            return
        if up.reset:  # a resume cut the file back: show it again from its start
            for tr in self.traces.values():
                tr.clear()
            self.sf_band.clear()
            self.unlocked.data = {"t": [], "y": []}
            for r in self.y_ranges.values():
                r.clear()
            self.last_t = self.unlocked_at = math.nan
            self.seen = []
            self.lost = 0
        if self.durations is None:
            self.identity, self.durations, self.settle_s = _identity(str(up.attrs.get("config_toml", "")))
            self.identity += _run_context(up.attrs)
        self.status = self._status(up.attrs)
        self.file_steps = up.steps
        self.lost += up.lost_samples
        self._feed(up)
        self._cover_ranges()
        if math.isfinite(up.horizon):
            self.last_t = up.horizon
        if self.status.startswith("running") and math.isfinite(self.last_t):
            wall = time.time()
            self.seen = [(w, h) for w, h in self.seen if w >= wall - SPEED_WINDOW_S] + [(wall, self.last_t)]
        self._time_axis()
        self._steps(up)
        self._events(up)
        self.last_up = up
        for div, text in ((self.header, self._header(up)), (self.now, self._now(up))):
            if text != div.text:
                div.text = text

    def _status(self, a: dict[str, Any]) -> str:
        """The status as the page shows it (module docstring)."""
        from qmg_lab.storage.h5clear import writer_flags_set
        from qmg_lab.storage.layout import StorageError
        from qmg_lab.storage.reader import RunData
        from qmg_lab.storage.resume import status_detail

        s = str(a.get("status", "?"))
        if s == "aborted":
            reason = str(a.get("abort_reason", "")).strip()
            return f"aborted: {reason}" if reason else "aborted"
        if s != "running":
            return s
        if int(a.get("writer_pid", -1)) == os.getpid():
            return "running (written by this process)"  # status_detail cannot tell its own process's writer
        try:
            detail = status_detail(RunData(self.path, a, {}, {}, writer_open=writer_flags_set(self.path)))
        except (StorageError, OSError):
            return "running"
        return DIED if detail.startswith("interrupted") else detail

    def _feed(self, up: Update) -> None:
        g = up.groups
        tr = self.traces
        if "clsf" in g:
            c = g["clsf"]
            self.sf_band.add(c["time"], c["sf_change_estimate"] * PPM)
            mean = self.follower.moving_mean_of_new(c["time"].shape[0])
            tr["sf_mean"].add(c["time"], mean * PPM)
            tr["gain"].add(c["time"], (c["gain_correction"] - 1.0) * PPM)
        if "chamber" in g:
            tr["chamber_air"].add(g["chamber"]["time"], g["chamber"]["temperature"])
            tr["chamber_setpoint"].add(g["chamber"]["time"], g["chamber"]["setpoint"])
        if "truth" in g:
            tr["gyro_temperature"].add(g["truth"]["time"], g["truth"]["temperature"])
        if "table" in g:
            tr["table_command"].add(g["table"]["time"], g["table"]["rate_command"])
            tr["table_measured"].add(g["table"]["time"], g["table"]["rate_measured"])
        if "lockin" in g:
            lk = g["lockin"]
            tr["drive_amplitude"].add(lk["time"], lk["drive_amplitude"])
            tr["pll_frequency"].add(lk["time"], lk["drive_frequency"])
            if "pll_locked" in lk:
                off = lk["pll_locked"] == 0
                if off.any():
                    t, y = minmax(lk["time"][off], lk["drive_frequency"][off], CHUNK_BINS)
                    self.unlocked.stream({"t": t, "y": y}, rollover=2 * MAX_POINTS)
                    self.unlocked_at = float(lk["time"][off][-1])
        mids, change = self.follower.pair_changes(up.steps, self.settle_s)
        if mids.shape[0] != len(self.pairs.data["t"]):
            t = self.follower.clsf_t
            offset = 0.0
            if mids.shape[0] and t.shape[0]:
                at = int(np.clip(np.searchsorted(t, mids[0]), 0, t.shape[0] - 1))
                offset = float(self.follower.moving_mean_of_new(t.shape[0])[at]) * PPM
            self.pairs.data = {"t": mids, "y": change + offset}

    def _time_axis(self) -> None:
        """The shared time axis spans the whole plan (0 to its planned duration, or past the data if a run runs
        longer): it does not move with every new block, so the browser redraws the traces, not the axes."""
        total = sum(self.durations) if self.durations else math.nan
        end = max(total, 1.02 * self.last_t) if math.isfinite(self.last_t) else total
        if math.isfinite(end) and end > 0 and (self.x_range.end is None or end > self.x_range.end):
            self.x_range.start, self.x_range.end = -0.01 * end, end

    def _plan_position(self, s: dict[str, np.ndarray], planned: int) -> tuple[int, float, float, int]:
        """(current step index or -1, its time left in s, the plan's remaining run time in s, steps not run) at
        the horizon (module docstring: step, end)."""
        done = s["status"] == "completed" if s else np.zeros(0, dtype=bool)
        done_idx = {int(i) for i in s["index"][done]} if s else set()
        left_steps = [i for i in range(planned) if i not in done_idx]
        if not left_steps:
            return -1, 0.0, 0.0, 0
        durations = self.durations or []
        current = left_steps[0]
        start = max((float(x) for x in s["t_end"][done]), default=0.0) if s else 0.0
        d = durations[current] if current < len(durations) else math.nan
        h = self.last_t if math.isfinite(self.last_t) else start
        step_left = max(start + d - h, 0.0)
        later = sum(durations[i] if i < len(durations) else math.nan for i in left_steps[1:])
        return current, step_left, step_left + later, len(left_steps)

    def _steps(self, up: Update) -> None:
        s = up.steps
        done = s["status"] == "completed" if s else np.zeros(0, dtype=bool)
        left = [float(x) for x in s["t_start"][done]] if s else []
        right = [float(x) for x in s["t_end"][done]] if s else []
        kinds = [str(k) for k in s["kind"][done]] if s else []
        colors = ["#1f77b4" if k % 2 else "#6baed6" for k in range(len(kinds))]  # neighbours told apart
        labels = ["completed"] * len(kinds)
        planned = planned_kinds(up.attrs)
        done_idx = {int(i) for i in s["index"][done]} if s else set()
        start = max(right, default=0.0)
        durations = self.durations or []
        first = True
        for i, kind in enumerate(planned):
            if i in done_idx:
                continue
            d = durations[i] if i < len(durations) else math.nan
            if not math.isfinite(d):
                break
            running = first and self.status.startswith("running")
            left.append(start)
            right.append(start + d)
            kinds.append(kind)
            colors.append("#d62728" if running else "#cccccc")
            labels.append("current" if running else "planned")
            start += d
            first = False
        data = {"left": left, "right": right, "family": [_family(k) for k in kinds], "label": labels, "color": colors}
        if data != dict(self.steps.data):  # an unchanged timeline is not sent (nor drawn) again
            self.steps.data = data

    def _events(self, up: Update) -> None:
        e = up.events
        if not e or len(self.events.data["t"]) == e["time"].shape[0]:
            return
        self.events.data = {
            "t": e["time"],
            "kind": list(e["kind"]),
            "instrument": list(e["instrument"]),
            "message": list(e["message"]),
        }

    def _header(self, up: Update) -> str:
        a = up.attrs
        planned = int(a.get("planned_steps", -1))
        done = int(a.get("completed_steps", 0))
        resumed = f", resumed {a.get('resume_count')}x" if int(a.get("resume_count", 0)) else ""
        return (
            f"<b>{html.escape(self.path.name)}</b> &middot; configuration {self.identity}"
            f" &middot; {html.escape(str(a.get('mode', '')))}"
            f"<br>status <b>{html.escape(self.status)}</b>{resumed} &middot; steps {done} / {planned}"
            f" &middot; elapsed <b><span class='elapsed'>{_clock(self.last_t)}</span></b> run time"
            f" (data to t = {self.last_t:.1f} s<span class='last-t' style='display:none'>{self.last_t!r}</span>)"
            f" &middot; started {html.escape(str(a.get('created', '')))}"
        )

    def _now(self, up: Update) -> str:
        a = up.attrs
        latest = self.follower.latest
        running = self.status.startswith("running")
        color = "#2ca02c" if running else "#1f77b4" if self.status == "completed" else "#d62728"
        cells: list[str] = []
        t, s = self.follower.clsf_t, self.follower.clsf_s
        if t.shape[0]:
            inside = t > t[-1] - MOVING_MEAN_S
            sf = f"{float(np.mean(s[inside])) * PPM:+.1f}"
            sf_line = f"SF change since start {_value('sf', sf)} ppm <small>(CLSF, 60 s mean)</small>"
            if len(self.pairs.data["t"]) > 1:
                _, change = self.follower.pair_changes(up.steps, self.settle_s)
                sf_line += f" &middot; step pairs {_value('pair', f'{float(change[-1]):+.1f}')} ppm since the first"
        else:
            sf_line = f"SF change since start {_value('sf', '-')} <small>(no CLSF period yet)</small>"
        cells.append(sf_line)
        ch, tru = latest.get("chamber", {}), latest.get("truth", {})
        gyro = _value("gyro", _degc(tru.get("temperature"))) + " degC" if "truth" in latest else "not recorded"
        cells.append(
            f"chamber setpoint {_value('setpoint', _degc(ch.get('setpoint')))} degC &middot; air "
            f"{_value('air', _degc(ch.get('temperature')))} degC &middot; gyro {gyro}"
        )
        lk = latest.get("lockin", {})
        if "pll_locked" in lk:
            locked = lk["pll_locked"] != 0
            pll = _value("pll", "locked" if locked else "NOT LOCKED")
            pll = f"<b style='color:{'#2ca02c' if locked else '#d62728'}'>{pll}</b>"
            if locked and math.isfinite(self.unlocked_at):
                pll += f" <small>(lost lock last at t = {self.unlocked_at:.0f} s)</small>"
        else:
            pll = _value("pll", "not recorded") + " <small>(file without /lockin/pll_locked)</small>"
        planned = int(a.get("planned_steps", -1))
        current, step_left, remaining, not_run = self._plan_position(up.steps, max(planned, 0))
        kinds = planned_kinds(a)
        if running and current >= 0:
            kind = kinds[current] if current < len(kinds) else "?"
            step = (
                f"step {_value('step', str(current))} / {planned} {_value('kind', kind)} &middot; "
                f"left {_value('left', _clock(step_left))}"
            )
        elif not_run:
            step = f"stopped with {_value('not-run', str(not_run))} of {planned} steps not run"
        else:
            step = f"all {planned} steps done"
        cells.append(f"PLL {pll} &middot; {step}")
        cells.append(self._end(running, remaining))
        status = f"<b style='font-size:130%;color:{color}'>{_value('status', self.status)}</b>"
        banner = self._banner(up)
        return (
            f"<div style='font-size:110%;line-height:1.45'>{status} &middot; <b>{html.escape(self.path.name)}</b>"
            f"<br>{'<br>'.join(cells)}{banner}</div>"
        )

    def _end(self, running: bool, remaining: float) -> str:
        if not running:
            try:
                ended = _wall(self.path.stat().st_mtime)
            except OSError:
                ended = "?"
            return f"ended {_value('end', ended)} <small>(the file's last write)</small>"
        if not math.isfinite(remaining):
            return f"expected end {_value('end', '?')} <small>(plan durations not readable)</small>"
        speed = math.nan
        if len(self.seen) >= 2 and self.seen[-1][0] - self.seen[0][0] >= 3.0:
            (w0, h0), (w1, h1) = self.seen[0], self.seen[-1]
            speed = (h1 - h0) / (w1 - w0)
        if not speed > 0:
            return (
                f"expected end {_value('end', 'estimating')} &middot; remaining "
                f"{_value('remaining', _clock(remaining))} run time"
            )
        return (
            f"expected end {_value('end', _wall(time.time() + remaining / speed))} &middot; remaining "
            f"{_value('remaining', _clock(remaining))} run time <small>({speed:.3g} s of run time per s)</small>"
        )

    def _banner(self, up: Update) -> str:
        """Faults, reconnects, suspensions, data loss, the abort and the safe state (module docstring)."""
        e = up.events
        notes: list[str] = []
        ok = False  # the safe state confirmed: its note is not an alarm
        if self.status == DIED:
            notes.append(
                "the run's process died: the instruments may NOT be in their safe state (table stopped, chamber "
                f"idle, drive off): check them; continue with qmg-lab run --resume {html.escape(self.path.name)}"
            )
        if self.lost:
            notes.append(f"data loss: {_value('lost', str(self.lost))} lock-in samples missing in the stretches read")
        if e and e["time"].shape[0]:
            kinds = [str(k) for k in e["kind"]]
            count = {k: kinds.count(k) for k in ("fault", "reconnect", "suspended")}
            said = [f"{n} {k}{'s' if n > 1 else ''}" for k, n in count.items() if n]
            if said:
                last = max(i for i, k in enumerate(kinds) if k in count)
                said.append(f"last at t = {float(e['time'][last]):.0f} s: {html.escape(str(e['message'][last]))}")
                notes.append(", ".join(said))
            susp = [i for i, k in enumerate(kinds) if k == "suspended"]
            back = [i for i, k in enumerate(kinds) if k in ("resumed", "recovered")]
            if susp and (not back or back[-1] < susp[-1]) and self.status.startswith("running"):
                notes.append(f"SUSPENDED since t = {float(e['time'][susp[-1]]):.0f} s")
            for i, k in enumerate(kinds):
                if k in ("abort", "interrupted"):
                    notes.append(f"{k}: {html.escape(str(e['message'][i]))}")
            safe = [i for i, k in enumerate(kinds) if k == "safe_state"]
            if safe:
                said_safe = str(e["message"][safe[-1]])
                ok = said_safe == "confirmed"
                notes.append(f"safe state {_value('safe', said_safe)}")
        alarm = "background:#fde0dc;border-left:4px solid #d62728;padding:2px 6px;margin-top:3px"
        calm = "background:#e5f5e0;border-left:4px solid #2ca02c;padding:2px 6px;margin-top:3px"
        return "".join(f"<div style='{calm if ok and n.startswith('safe state') else alarm}'>{n}</div>" for n in notes)
