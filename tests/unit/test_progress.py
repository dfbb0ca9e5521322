"""The live progress view: the SF as a 60 s mean, and the compile notice before the first blocks."""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from qmg_lab.campaign.plan import Step, StepKind
from qmg_lab.campaign.runner import Progress
from qmg_lab.cli.progress import (
    COMPILE_BLOCKS,
    COMPILE_NOTICE_AFTER_S,
    SF_MEAN_WINDOW_S,
    MovingMean,
    ProgressView,
)

STEP = Step(index=0, kind=StepKind.HOLD, duration_s=600.0, chamber_target_c=25.0, chamber_ramp_c_per_min=0.25)


def _progress(t_s: float, sf_ppm: float) -> Progress:
    return Progress(
        step=STEP,
        n_steps=3,
        step_elapsed_s=t_s,
        run_time_s=t_s,
        planned_s=600.0,
        done_s=t_s,
        chamber_c=25.0,
        chamber_setpoint_c=25.0,
        table_rate_dps=0.0,
        sf_change_ppm=sf_ppm,
        gain_correction=1.0,
        suspended="",
        wall_s=1.0,
    )


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _view(clock: FakeClock) -> tuple[ProgressView, io.StringIO]:
    buffer = io.StringIO()
    console = Console(file=buffer, force_terminal=False, width=200)
    return ProgressView(console, clock=clock), buffer


def test_the_moving_mean_keeps_the_last_window():
    mean = MovingMean(60.0)
    for t in range(0, 122, 2):  # value = t: the window [60, 120] holds 60, 62, ..., 120, mean 90
        mean.add(float(t), float(t))
    assert mean.count == 31 and mean.mean == 90.0
    mean.add(122.0, float("nan"))  # a period without an estimate: skipped, the window still moves
    assert mean.count == 30 and mean.mean == 91.0
    mean.add(5.0, 7.0)  # run time went back: a new run
    assert mean.count == 1 and mean.mean == 7.0


def test_the_sf_shown_is_the_60_s_mean_not_one_period():
    """Block estimates scatter +-690 ppm about 100 ppm (alternating): the view shows the mean, 100 ppm, exactly
    (an even number of alternating samples in the window sums to 100 n, each term exact in binary)."""
    clock = FakeClock()
    view, _ = _view(clock)
    for k in range(100):
        clock.now += 1.0
        view.update(_progress(2.0 * k, 100.0 + (690.0 if k % 2 else -690.0)))
    assert view.sf_mean.count == int(SF_MEAN_WINDOW_S / 2.0) + 1  # blocks at t - 60 ... t, every 2 s
    n = view.sf_mean.count
    expected = (100.0 * n + 690.0 * (1 if n % 2 else 0)) / n  # an odd count leaves one +690 (the last k is odd)
    assert view.sf_mean.mean == pytest.approx(expected, rel=1e-12)
    assert f"{expected:+.1f} ppm (60 s mean of {n})" in view.sf_text()


def test_no_estimate_yet_is_said_in_words():
    view, _ = _view(FakeClock())
    view.update(_progress(2.0, float("nan")))
    assert view.sf_text() == "- (no CLSF estimate yet)"


def test_a_late_first_block_is_explained_as_compiling():
    clock = FakeClock()
    view, buffer = _view(clock)
    with view:
        assert view.waiting_text() == ""  # at once: nothing to explain
        clock.now += COMPILE_NOTICE_AFTER_S + 2.0
        notice = view.waiting_text()
        assert "waiting 5 s for the first block" in notice and "numba is compiling" in notice
        assert "40-90 s" in notice and "cache" in notice
        view._print_notice()  # what the line-mode timer prints
        assert "numba is compiling" in buffer.getvalue()
        view.update(_progress(2.0, float("nan")))
        assert view.waiting_text() == ""  # the block came
        clock.now += COMPILE_NOTICE_AFTER_S + 1.0
        assert "for the next block" in view.waiting_text()  # the CLSF kernels compile at its first periods


def test_a_late_block_later_in_the_run_is_not_called_compiling():
    clock = FakeClock()
    view, _ = _view(clock)
    for k in range(COMPILE_BLOCKS):
        view.update(_progress(2.0 * k, 0.0))
    clock.now += 60.0
    assert view.waiting_text() == ""
