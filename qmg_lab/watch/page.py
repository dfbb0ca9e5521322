"""The watch page's Bokeh document: a header and eight plots against run time, fed by a RunFollower.

Plots (x: run time in s since the file's t0_unix, shared by all but the events' categories):
Traces from the lock-in stream (drive amplitude, PLL frequency, gyro temperature) are read in sampled chunks
(follow.py) and drawn as points, so that no line is drawn across a stretch that was not read.

    sf        CLSF SF-change estimate per dither period (ppm, faint) with its trailing 60 s moving mean, and the
              true SF change from each completed +-rate step pair (follow.py), placed on the CLSF mean at the
              first pair so both read as changes from there
    gain      CLSF gain correction g_c - 1 (ppm; 0 unless the run is in correct mode)
    temp      chamber air temperature, its setpoint, and (twins) the gyro temperature from /truth
    table     table rate commanded and measured (deg/s)
    drive     drive amplitude R (V)
    pll       PLL oscillator frequency (Hz): steady while the loop is locked
    steps     the plan as a timeline: completed steps by kind, the current step marked red, the remaining
              planned steps grey at their planned durations
    events    every /events row by kind (hover: instrument and message)

Each trace is a `Trace`: new rows are reduced by min/max decimation (qmg_lab/data/decimate.py) and streamed
to the browser (ColumnDataSource.stream); once a trace holds more than 2 x MAX_POINTS points it is decimated
again to MAX_POINTS and sent whole. The browser thus never holds more than about 2 x MAX_POINTS points per
trace, whatever the run's length.
"""

from __future__ import annotations

import html
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from bokeh.document import Document
from bokeh.layouts import column
from bokeh.models import ColumnDataSource, DataRange1d, FactorRange, HoverTool
from bokeh.models.annotations import Legend
from bokeh.models.widgets import Div
from bokeh.plotting import figure

from qmg_lab.data.decimate import minmax
from qmg_lab.storage.layout import RUN_CONTEXT_ATTRS
from qmg_lab.storage.records import EVENT_KINDS
from qmg_lab.watch.follow import PPM, RunFollower, Update, planned_kinds

MAX_POINTS = 1000  # about a plot's width in pixels
CHUNK_BINS = MAX_POINTS // 5
#: the page reads the file and redraws every 1.5 s: a block is on the page within 1.5 s of the writer's flush plus
#: the draw (under 2 s), and a software-drawn browser on the campaign's own two cores costs it under 10 % (once a
#: second cost about 14 %: docs/performance.md)
POLL_MS = 1500
STEP_FAMILIES = ("lock", "dither", "soak", "rate", "hold", "sine", "level", "return")
PLOTS = ("sf", "gain", "temp", "table", "drive", "pll", "steps", "events")  # model names: plot_<name>


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


def _clock(s: float) -> str:
    if not math.isfinite(s):
        return "-"
    h, rem = divmod(int(round(max(s, 0.0))), 3600)
    return f"{h}:{rem // 60:02d}:{rem % 60:02d}"


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
        self.last_t = math.nan
        self.file_steps: dict[str, np.ndarray] = {}  # /steps as last read
        self.doc: Document | None = None
        self.traces = {
            n: Trace(n)
            for n in (
                "sf_period",
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
        self.pairs = ColumnDataSource({"t": [], "y": []}, name="sf_pairs")
        self.steps = ColumnDataSource(
            {"left": [], "right": [], "family": [], "label": [], "color": []}, name="steps_timeline"
        )
        self.events = ColumnDataSource({"t": [], "kind": [], "instrument": [], "message": []}, name="events")
        # a fixed height: a new header text then needs no new layout of the plots below it
        self.header = Div(
            text=f"<b>{html.escape(path.name)}</b>: opening ...", name="header", height=44, sizing_mode="stretch_width"
        )
        self.polls = ColumnDataSource({"n": [0]}, name="polls")  # how many times the page has read the file
        self.layout = self._layout()

    # ---- layout ------------------------------------------------------------------------------------------

    def _figure(self, name: str, title: str, ylabel: str, x_range: DataRange1d | None, **kw: Any) -> Any:
        fig = figure(
            name=f"plot_{name}",
            title=title,
            height=kw.pop("height", 190),
            sizing_mode="stretch_width",
            x_range=x_range if x_range is not None else DataRange1d(),
            tools="pan,xwheel_zoom,box_zoom,reset,save",
            active_scroll="xwheel_zoom",
            **kw,
        )
        fig.yaxis.axis_label = ylabel
        fig.xaxis.axis_label = "run time [s]"
        fig.add_layout(Legend(location="top_left", click_policy="hide"), "right")
        return fig

    def _line(self, fig: Any, trace: str, label: str, color: str, **kw: Any) -> None:
        fig.line("t", "y", source=self.traces[trace].source, legend_label=label, color=color, **kw)

    def _dots(self, fig: Any, trace: str, label: str, color: str) -> None:
        """A lock-in-rate trace: read in sampled chunks (follow.py), so drawn as points: no line across a gap."""
        fig.scatter("t", "y", source=self.traces[trace].source, legend_label=label, color=color, size=2)

    def _layout(self) -> Any:
        sf = self._figure("sf", "scale factor", "SF change [ppm]", None)
        x = self.x_range = sf.x_range
        self._line(sf, "sf_period", "CLSF, each period", "#bbbbbb", line_width=1)
        self._line(sf, "sf_mean", "CLSF, 60 s mean", "#1f77b4", line_width=2)
        sf.scatter("t", "y", source=self.pairs, size=8, color="#d62728", legend_label="true SF, step pairs")
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
        steps = self._figure("steps", "plan", "", x, y_range=FactorRange(factors=list(STEP_FAMILIES)), height=220)
        steps.hbar(
            y="family",
            left="left",
            right="right",
            height=0.7,
            color="color",
            source=self.steps,
            legend_field="label",
        )
        steps.add_tools(HoverTool(tooltips=[("step", "@label"), ("from", "@left{0.0} s"), ("to", "@right{0.0} s")]))
        events = self._figure("events", "events", "", x, y_range=FactorRange(factors=list(EVENT_KINDS)), height=240)
        events.scatter("t", "kind", source=self.events, size=9, color="#d62728", legend_label="event")
        events.add_tools(HoverTool(tooltips=[("t", "@t{0.0} s"), ("", "@instrument: @message")]))
        return column(self.header, sf, gain, temp, table, drive, pll, steps, events, sizing_mode="stretch_width")

    # ---- updates -----------------------------------------------------------------------------------------

    def attach(self, doc: Document) -> None:
        doc.title = f"qmg-lab watch: {self.path.name}"
        doc.add_root(self.layout)
        doc.add_root(self.polls)
        self.doc = doc
        self.update()
        doc.add_periodic_callback(self.update, POLL_MS)

    def update(self) -> None:
        """One poll of the file; every change to the page's models goes to the browser as one message (held
        and combined), so the browser draws the page once per poll, not once per trace."""
        if self.doc is None:
            self._update()
            return
        self.doc.hold("combine")
        try:
            self._update()
        finally:
            self.doc.unhold()

    def _update(self) -> None:
        up = self.follower.poll()
        self.polls.data = {"n": [self.polls.data["n"][0] + 1]}
        if not up.ready:
            self.header.text = f"<b>{html.escape(self.path.name)}</b>: {html.escape(up.problem)}"
            return
        if up.reset:  # a resume cut the file back: show it again from its start
            for tr in self.traces.values():
                tr.clear()
            self.last_t = math.nan
        if self.durations is None:
            self.identity, self.durations, self.settle_s = _identity(str(up.attrs.get("config_toml", "")))
            self.identity += _run_context(up.attrs)
        self.file_steps = up.steps
        self._feed(up)
        self._time_axis()
        self._steps(up)
        self._events(up)
        text = self._header(up)
        if text != self.header.text:
            self.header.text = text

    def _feed(self, up: Update) -> None:
        g = up.groups
        tr = self.traces
        if "clsf" in g:
            c = g["clsf"]
            tr["sf_period"].add(c["time"], c["sf_change_estimate"] * PPM)
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
            tr["drive_amplitude"].add(g["lockin"]["time"], g["lockin"]["drive_amplitude"])
            tr["pll_frequency"].add(g["lockin"]["time"], g["lockin"]["drive_frequency"])
        ends = [t.t[-1] for t in tr.values() if t.t.shape[0]]
        if ends:
            self.last_t = max(ends)
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
            running = first and up.attrs.get("status") == "running"
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
        from qmg_lab.storage.h5clear import writer_flags_set
        from qmg_lab.storage.layout import StorageError
        from qmg_lab.storage.reader import RunData
        from qmg_lab.storage.resume import status_detail

        a = up.attrs
        try:
            status = status_detail(RunData(self.path, a, {}, {}, writer_open=writer_flags_set(self.path)))
        except StorageError:
            status = str(a.get("status", "?"))
        if a.get("status") == "running" and int(a.get("writer_pid", -1)) == os.getpid():
            status = "running (written by this process)"  # status_detail cannot tell its own process's writer
        planned = int(a.get("planned_steps", -1))
        done = int(a.get("completed_steps", 0))
        total = sum(self.durations) if self.durations else math.nan
        remaining = max(total - self.last_t, 0.0) if a.get("status") == "running" else 0.0
        current = ""
        kinds = planned_kinds(a)
        if a.get("status") == "running" and done < len(kinds):
            current = f", now step {done} ({html.escape(kinds[done])})"
        resumed = f", resumed {a.get('resume_count')}x" if int(a.get("resume_count", 0)) else ""
        return (
            f"<b>{html.escape(self.path.name)}</b> &middot; configuration {self.identity}"
            f" &middot; {html.escape(str(a.get('mode', '')))}"
            f"<br>status <b>{html.escape(status)}</b>{resumed} &middot; steps {done} / {planned}{current}"
            f" &middot; elapsed <b><span class='elapsed'>{_clock(self.last_t)}</span></b> run time"
            f" (data to t = <span class='last-t'>{self.last_t:.1f}</span> s)"
            f" &middot; remaining {_clock(remaining) if math.isfinite(remaining) else '?'}"
            f" &middot; started {html.escape(str(a.get('created', '')))}"
        )
