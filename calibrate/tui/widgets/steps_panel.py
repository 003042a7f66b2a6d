"""Commissioning steps, each with a status mark, progress bar, ETA / duration and summary."""

from __future__ import annotations

from textual.containers import Horizontal, Vertical
from textual.widgets import Label, ProgressBar

from calibrate.commission_events import STEPS, Step, StepFinished, StepProgress, StepStarted
from calibrate.tui.widgets.formatting import duration

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

#: status -> (mark, CSS class)
_MARKS = {
    "pending": ("·", "-pending"),
    "running": ("▶", "-running"),
    "ok": ("✔", "-ok"),
    "failed": ("✘", "-failed"),
    "stopped": ("■", "-stopped"),
    "resumed": ("↺", "-ok"),
    "skipped": ("–", "-pending"),
}

#: Below this fraction the ETA comes from the step's announced duration, not from its progress.
_MIN_FRACTION_FOR_RATE = 0.05


class StepRow(Horizontal):
    """One step: ``mark title  [bar] pct  ETA m:ss  summary``."""

    def __init__(self, step: Step) -> None:
        super().__init__(id=f"step-{step.value}", classes="step-row -pending")
        self.step = step
        self.status = "pending"
        self.started_at: float | None = None
        self.finished_at: float | None = None
        self.eta_s: float | None = None
        self.fraction = 0.0
        self.title_label = Label(f"· {STEP_TITLES[step]}", classes="step-title")
        self.bar = ProgressBar(total=1.0, show_eta=False, classes="step-bar")
        self.time_label = Label("", classes="step-time")
        self.summary_label = Label("", classes="step-summary")

    def compose(self):
        yield self.title_label
        yield self.bar
        yield self.time_label
        yield self.summary_label

    def _set_status(self, status: str) -> None:
        old_class = _MARKS[self.status][1]
        self.status = status
        mark, new_class = _MARKS[status]
        self.remove_class(old_class)
        self.add_class(new_class)
        self.title_label.update(f"{mark} {STEP_TITLES[self.step]}")

    def reset(self) -> None:
        """Back to pending, for a new run."""
        self.started_at = self.finished_at = self.eta_s = None
        self.fraction = 0.0
        self._set_status("pending")
        self.bar.update(progress=0.0)
        self.time_label.update("")
        self.summary_label.update("")

    def start(self, now: float, eta_s: float | None) -> None:
        self.started_at, self.finished_at, self.eta_s, self.fraction = now, None, eta_s, 0.0
        self._set_status("running")
        self.bar.update(progress=0.0)
        self.summary_label.update("")

    def progress(self, fraction: float, message: str) -> None:
        self.fraction = min(max(float(fraction), 0.0), 1.0)
        self.bar.update(progress=self.fraction)
        if message:
            self.summary_label.update(message)

    def finish(self, now: float, ok: bool, summary: str, resumed: bool, skipped: bool = False) -> None:
        self.finished_at = now
        if skipped:
            self._set_status("skipped")
            self.summary_label.update(("skipped: " + summary) if summary else "skipped")
            return
        self._set_status("resumed" if resumed and ok else ("ok" if ok else "failed"))
        if ok:
            self.fraction = 1.0
            self.bar.update(progress=1.0)
        self.summary_label.update(("resumed: " if resumed else "") + summary)

    def interrupt(self, now: float) -> None:
        """The run ended (stop or fault) while this step was running."""
        if self.status == "running":
            self.finished_at = now
            self._set_status("stopped")

    def tick(self, now: float) -> None:
        """Refresh the time column: ETA while running, duration when done."""
        label = self.time_label
        if self.status == "running" and self.started_at is not None:
            elapsed = now - self.started_at
            if self.fraction >= _MIN_FRACTION_FOR_RATE:
                remaining = elapsed * (1.0 - self.fraction) / self.fraction
            elif self.eta_s is not None:
                remaining = max(self.eta_s - elapsed, 0.0)
            else:
                remaining = None
            label.update(f"ETA {duration(remaining)}")
        elif self.status == "skipped":
            label.update("")
        elif self.started_at is not None and self.finished_at is not None:
            label.update(f"took {duration(self.finished_at - self.started_at)}")
        elif self.status == "resumed":
            label.update("")


class StepsPanel(Vertical):
    """All commissioning steps in order; consumes ``StepStarted/StepProgress/StepFinished``."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.border_title = "Commissioning steps"
        self.rows = {step: StepRow(step) for step in STEPS}

    def compose(self):
        yield from self.rows.values()

    def row(self, step: Step) -> StepRow:
        return self.rows[Step(step)]

    def apply(self, event: object, now: float) -> None:
        """Apply one step event (others are ignored)."""
        if isinstance(event, StepStarted):
            self.row(event.step).start(now, event.eta_s)
        elif isinstance(event, StepProgress):
            self.row(event.step).progress(event.fraction, event.message)
        elif isinstance(event, StepFinished):
            self.row(event.step).finish(now, event.ok, event.summary, event.resumed, event.skipped)
        else:
            return
        self.tick(now)

    def reset(self) -> None:
        for row in self.rows.values():
            row.reset()

    def interrupt(self, now: float) -> None:
        for row in self.rows.values():
            row.interrupt(now)
        self.tick(now)

    def tick(self, now: float) -> None:
        for row in self.rows.values():
            row.tick(now)
