"""Commissioning steps, each with a status mark, progress bar, ETA / duration and summary.

One widget draws every step as a line of fixed-width columns (no child widgets, no ``rich`` table
to measure): the panel is updated many times a second during a run and redrawn on every switch to
its tab, so it must stay cheap to lay out and render.
"""

from __future__ import annotations

from dataclasses import dataclass

from rich.text import Text
from textual.widgets import Static

from calibrate.commission_events import STEPS, Step, StepFinished, StepProgress, StepStarted
from calibrate.tui.widgets.formatting import duration, text_bar

STEP_TITLES = {
    Step.CONNECT: "Connect",
    Step.LEAK_TEST: "Leak test",
    Step.CAMERA_HEALTH: "Camera health",
    Step.REFERENCE: "Reference",
    Step.COLLECT: "Collect",
    Step.FINETUNE: "Fine-tune",
    Step.VALIDATE: "Validate",
    Step.POSE_CHECK: "Pose check",
    Step.VERDICT: "Verdict",
}

#: status -> (mark, title style, bar style)
_LOOK = {
    "pending": ("·", "dim", "grey35"),
    "running": ("▶", "bold yellow", "dodger_blue1"),
    "ok": ("✔", "green", "green"),
    "failed": ("✘", "bold red", "red"),
    "stopped": ("■", "yellow", "yellow"),
    "resumed": ("↺", "green", "green"),
    "skipped": ("–", "dim", "grey35"),
}

#: Below this progress since the step's first report the ETA comes from the step's announced duration, not
#: from its rate of progress.
_MIN_FRACTION_FOR_RATE = 0.05
#: Bar width range, cells: the bar gives way to the summary column in narrow terminals.
BAR_WIDTH = (10, 24)
#: Cells of the fixed columns other than the bar: title, percent, time.
_TITLE_CELLS, _PERCENT_CELLS, _TIME_CELLS = 15, 4, 9
#: Cells of the title, percent and time columns with the 4 one-cell gaps between the columns.
_FIXED_CELLS = _TITLE_CELLS + _PERCENT_CELLS + _TIME_CELLS + 4
#: Summary cells kept before the bar shrinks.
_MIN_SUMMARY = 24


@dataclass
class StepState:
    """What the panel knows of one step; times in s of the app's clock."""

    step: Step
    status: str = "pending"  # a key of _LOOK
    started_at: float | None = None
    finished_at: float | None = None
    eta_s: float | None = None
    fraction: float = 0.0
    summary: str = ""
    #: The step's first progress report: its fraction (the share an earlier, interrupted run had done,
    #: for a resumed step) and when it came (s of the app's clock).
    first_fraction: float = 0.0
    first_report_at: float | None = None

    def time_text(self, now: float) -> str:
        """ETA while running, duration when done, blank otherwise.

        The ETA is the time left at the rate of the progress made since the step's first report, or
        before enough progress the announced duration, scaled to the share left at that report (was:
        the fraction done over this run's time, so that a resumed collection counted the poses of the
        earlier run as done in seconds: ETA 0:01 for two poses of ~9 s each)."""
        if self.status == "running" and self.started_at is not None:
            gained = self.fraction - self.first_fraction
            if gained >= _MIN_FRACTION_FOR_RATE:
                remaining = (now - self.first_report_at) * (1.0 - self.fraction) / gained
            elif self.eta_s is not None:
                remaining = max(self.eta_s * (1.0 - self.first_fraction) - (now - self.started_at), 0.0)
            else:
                remaining = None
            return f"ETA {duration(remaining)}"
        if self.status in ("skipped", "resumed") or self.started_at is None or self.finished_at is None:
            return ""
        return f"took {duration(self.finished_at - self.started_at)}"


class StepsPanel(Static):
    """All commissioning steps in order; consumes ``StepStarted/StepProgress/StepFinished``."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.border_title = "Commissioning steps"
        self.rows = {step: StepState(step) for step in STEPS}
        self._now = 0.0

    def on_mount(self) -> None:
        self._redraw()

    def row(self, step: Step) -> StepState:
        return self.rows[Step(step)]

    def apply(self, event: object, now: float) -> bool:
        """Apply one step event to the rows; returns False for other events. Does not redraw: the
        caller calls ``tick`` once per batch."""
        if isinstance(event, StepStarted):
            self.rows[Step(event.step)] = StepState(event.step, "running", started_at=now, eta_s=event.eta_s)
        elif isinstance(event, StepProgress):
            row = self.row(event.step)
            row.fraction = max(row.fraction, min(max(float(event.fraction), 0.0), 1.0))  # never backwards
            if row.first_report_at is None:
                row.first_fraction, row.first_report_at = row.fraction, now
            if event.message:
                row.summary = event.message
        elif isinstance(event, StepFinished):
            row = self.row(event.step)
            row.finished_at = now
            if event.skipped:
                row.status = "skipped"
                row.summary = event.summary or "skipped"
            else:
                row.status = "resumed" if event.resumed and event.ok else ("ok" if event.ok else "failed")
                row.summary = ("resumed: " if event.resumed else "") + event.summary
                if event.ok:
                    row.fraction = 1.0
        else:
            return False
        return True

    def reset(self) -> None:
        """Every step pending (no redraw when they all are)."""
        pending = {step: StepState(step) for step in STEPS}
        if pending != self.rows:
            self.rows = pending
            self._redraw()

    def interrupt(self, now: float, status: str = "stopped") -> None:
        """The run ended early: a running step is marked ``status`` (``stopped`` by the operator,
        ``failed`` by a fault or an error)."""
        for row in self.rows.values():
            if row.status == "running":
                row.status, row.finished_at = status, now
        self.tick(now)

    def tick(self, now: float) -> None:
        """Redraw with ETAs and durations at ``now``."""
        self._now = now
        self._redraw()

    def on_resize(self) -> None:
        self._redraw()

    def _redraw(self) -> None:
        width = self.content_region.width if self.is_mounted else 0
        lo, hi = BAR_WIDTH
        bar_width = max(lo, min(hi, width - _FIXED_CELLS - _MIN_SUMMARY))
        summary_width = max(width - _FIXED_CELLS - bar_width, 0)
        lines = [self._line(row, bar_width, summary_width) for row in self.rows.values()]
        self.update(Text("\n", no_wrap=True, end="").join(lines), layout=False)

    def _line(self, row: StepState, bar_width: int, summary_width: int) -> Text:
        """One step: mark and title, bar, percent, ETA / duration, summary; one space between."""
        mark, title_style, bar_style = _LOOK[row.status]
        return Text(" ", end="").join([
            _cell(f"{mark} {STEP_TITLES[row.step]}", _TITLE_CELLS, title_style),
            text_bar(row.fraction, bar_width, bar_style),
            _cell(f"{row.fraction * 100:.0f}%", _PERCENT_CELLS, right=True),
            _cell(row.time_text(self._now), _TIME_CELLS, "dim"),
            _cell(row.summary, summary_width, "dim"),
        ])


def _cell(content: str, width: int, style: str = "", right: bool = False) -> Text:
    """``content`` in ``style`` cut to ``width`` cells (an ellipsis marks the cut) and padded to
    exactly ``width`` (on the left when ``right``) with spaces in the same style."""
    text = Text(content if width > 0 else "", style=style, end="", overflow="ellipsis")
    text.align("right" if right else "left", width)
    return text
