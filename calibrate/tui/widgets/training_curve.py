"""Live fine-tuning curve (training loss and validation a1) drawn with block characters."""

from __future__ import annotations

import numpy as np
from rich.text import Text
from textual.containers import Vertical
from textual.widget import Widget
from textual.widgets import Static

from calibrate.commission_events import TrainingProgress
from calibrate.tui.widgets.formatting import duration

_LEVELS = " ▁▂▃▄▅▆▇█"
#: Width of the y-axis labels, cells.
_AXIS = 9


def column_values(values: list[float], width: int) -> np.ndarray:
    """One value per chart column, ``(min(len(values), width),) float64``: the points themselves
    while they fit, else means of ``width`` equal buckets over the whole history (the curve is
    compressed, never cropped)."""
    data = np.asarray(values, dtype=np.float64)
    if len(data) <= width:
        return data
    edges = np.linspace(0, len(data), width + 1).astype(np.int64)
    return np.array([data[a:b].mean() for a, b in zip(edges[:-1], edges[1:])])


def bar_chart(values: list[float], width: int, height: int) -> tuple[list[str], float, float]:
    """Rows (top first) of a ``width`` x ``height`` cell bar chart of the finite ``values``, with
    the value range (lo, hi) it spans; each cell holds eighths of a bar."""
    finite = [v for v in values if np.isfinite(v)]
    if width <= 0 or height <= 0 or not finite:
        return [" " * max(width, 0)] * max(height, 0), 0.0, 0.0
    cols = column_values(finite, width)
    lo, hi = float(cols.min()), float(cols.max())
    if hi > lo:
        eighths = np.round((cols - lo) / (hi - lo) * (height * 8 - 1)).astype(np.int64) + 1
    else:  # a flat series: half-height bars
        eighths = np.full(len(cols), height * 4, dtype=np.int64)
    rows = []
    for r in range(height):
        level = np.clip(eighths - (height - 1 - r) * 8, 0, 8)
        rows.append("".join(_LEVELS[k] for k in level).ljust(width))
    return rows, lo, hi


class CurvePlot(Widget):
    """A titled bar chart of one series with its latest value and y-range labels."""

    DEFAULT_CSS = """
    CurvePlot { height: 1fr; min-height: 3; }
    """

    def __init__(self, title: str, fmt: str, style: str, **kwargs) -> None:
        super().__init__(**kwargs)
        self.title = title
        self.fmt = fmt
        self.chart_style = style
        self.values: list[float] = []

    def set_values(self, values: list[float]) -> None:
        """Show ``values``, the series in order (in the unit that ``fmt`` prints; NaN and inf left out of the bars)."""
        self.values = list(values)
        self.refresh()

    def render(self) -> Text:
        width, height = self.size.width, self.size.height
        text = Text(no_wrap=True, overflow="crop")
        text.append(f"{self.title}", style="bold")
        finite = [v for v in self.values if np.isfinite(v)]
        if finite:
            latest = self.fmt.format(self.values[-1]) if np.isfinite(self.values[-1]) else "-"
            text.append(f"  {latest}", style=self.chart_style)
        else:
            text.append("  (no data yet)", style="dim")
        chart_h = max(height - 1, 0)
        rows, lo, hi = bar_chart(finite, max(width - _AXIS, 0), chart_h)
        for r, row in enumerate(rows):
            label = ""
            if finite and r == 0:
                label = self.fmt.format(hi)
            elif finite and r == chart_h - 1:
                label = self.fmt.format(lo)
            text.append("\n")
            text.append(f"{label:>{_AXIS - 1}} ", style="dim")
            text.append(row, style=self.chart_style)
        return text


class TrainingCurve(Vertical):
    """Loss and a1 charts plus step / elapsed / ETA, from ``TrainingProgress`` events. ``loss``: the
    training loss of every point in mm (the masked L1 depth error, as the CLI and the report give it)."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.border_title = "Fine-tuning"
        self.loss: list[float] = []
        self.a1: list[float] = []
        self.last: TrainingProgress | None = None
        self.line = Static("waiting for fine-tuning", id="training-line")
        self.loss_plot = CurvePlot("loss (mm)", "{:.3f}", "bold yellow", id="loss-plot")  # was: m, unlike the rest
        self.a1_plot = CurvePlot("val δ<1.05", "{:.3f}", "bold green", id="a1-plot")

    def compose(self):
        yield self.line
        yield self.loss_plot
        yield self.a1_plot

    def reset(self) -> None:
        """Back to "waiting for fine-tuning" (no redraw when no point came yet)."""
        if self.last is None:
            return
        self.loss, self.a1, self.last = [], [], None
        self.line.update("waiting for fine-tuning", layout=False)
        self.loss_plot.set_values([])
        self.a1_plot.set_values([])

    def apply(self, points: list[TrainingProgress]) -> None:
        """Append a batch of training points and redraw once."""
        if not points:
            return
        for point in points:
            self.loss.append(float(point.loss) * 1000.0)  # m -> mm
            if point.a1 is not None:
                self.a1.append(float(point.a1))
        self.last = points[-1]
        self.line.update(
            f"step {self.last.step}  elapsed {duration(self.last.elapsed_s)}  ETA {duration(self.last.eta_s)}",
            layout=False,
        )
        self.loss_plot.set_values(self.loss)
        self.a1_plot.set_values(self.a1)
