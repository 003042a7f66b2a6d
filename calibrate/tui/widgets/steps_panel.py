"""Commissioning steps, each with a status mark, progress bar, ETA / duration and summary.

One widget draws every step as a row of a table (no child widgets): the panel is updated many
times a second during a run and must stay cheap to lay out and render.
"""

from __future__ import annotations

from dataclasses import dataclass

from rich.table import Table
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

#: Below this fraction the ETA comes from the step's announced duration, not from its progress.
_MIN_FRACTION_FOR_RATE = 0.05
#: Bar width range, cells: the bar gives way to the summary column in narrow terminals.
BAR_WIDTH = (10, 24)
#: Cells of the other fixed columns with their gaps (title 15, percent 4, time 9, 4 gaps of 1).
_FIXED_CELLS = 32
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

    def time_text(self, now: float) -> str:
        """ETA while running, duration when done, blank otherwise."""
        if self.status == "running" and self.started_at is not None:
            elapsed = now - self.started_at
            if self.fraction >= _MIN_FRACTION_FOR_RATE:
                remaining = elapsed * (1.0 - self.fraction) / self.fraction
            elif self.eta_s is not None:
                remaining = max(self.eta_s - elapsed, 0.0)
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

    def apply(self, event: object, now: float) -> None:
        """Apply one step event (others are ignored); redraws."""
        if isinstance(event, StepStarted):
            self.rows[Step(event.step)] = StepState(event.step, "running", started_at=now, eta_s=event.eta_s)
        elif isinstance(event, StepProgress):
            row = self.row(event.step)
            row.fraction = max(row.fraction, min(max(float(event.fraction), 0.0), 1.0))  # never backwards
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
            return
        self.tick(now)

    def reset(self) -> None:
        self.rows = {step: StepState(step) for step in STEPS}
        self._redraw()

    def interrupt(self, now: float) -> None:
        """The run ended (stop or fault): a running step is marked stopped."""
        for row in self.rows.values():
            if row.status == "running":
                row.status, row.finished_at = "stopped", now
        self.tick(now)

    def tick(self, now: float) -> None:
        """Redraw with ETAs and durations at ``now``."""
        self._now = now
        self._redraw()

    def on_resize(self) -> None:
        self._redraw()

    def _bar_width(self) -> int:
        width = self.content_region.width if self.is_mounted else 0
        lo, hi = BAR_WIDTH
        return max(lo, min(hi, width - _FIXED_CELLS - _MIN_SUMMARY))

    def _redraw(self) -> None:
        bar_width = self._bar_width()
        grid = Table.grid(padding=(0, 1), expand=True)
        grid.add_column(width=15, no_wrap=True)
        grid.add_column(width=bar_width, no_wrap=True)
        grid.add_column(width=4, justify="right", no_wrap=True)
        grid.add_column(width=9, no_wrap=True)
        grid.add_column(ratio=1, no_wrap=True, overflow="ellipsis")
        for row in self.rows.values():
            mark, title_style, bar_style = _LOOK[row.status]
            grid.add_row(
                Text(f"{mark} {STEP_TITLES[row.step]}", style=title_style),
                text_bar(row.fraction, bar_width, bar_style),
                f"{row.fraction * 100:.0f}%",
                Text(row.time_text(self._now), style="dim"),
                Text(row.summary, style="dim"),
            )
        self.update(grid, layout=False)
