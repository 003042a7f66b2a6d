"""Live per-pose progress during data collection, from ``CollectionProgress`` events."""

from __future__ import annotations

from rich.console import Group
from rich.text import Text
from textual.widgets import Static

from calibrate.commission_events import CollectionProgress
from calibrate.tui.widgets.formatting import text_bar

_PHASE_STYLES = {"press": "bold red", "hold": "bold magenta", "approach": "yellow", "retract": "cyan", "free": "dim",
                 "stopping": "bold yellow"}


class CollectionPanel(Static):
    """Object, pose k/K, contact phase, frames recorded, force and pressure, and a bar over all
    contact poses of the run (``objects`` in plan order, ``poses_per_object`` each)."""

    def __init__(self, objects: tuple[str, ...], poses_per_object: int, **kwargs) -> None:
        super().__init__(**kwargs)
        self.objects = list(objects)
        self.poses_per_object = poses_per_object
        self.border_title = "Collection"
        self.last: CollectionProgress | None = None  # the latest event shown
        self.line = Text("waiting for collection", style="dim")
        self.done = 0  # contact poses finished

    def on_mount(self) -> None:
        self._redraw()

    @property
    def total(self) -> int:
        """Contact poses planned."""
        return max(1, len(self.objects) * self.poses_per_object)

    def reset(self) -> None:
        """Back to "waiting for collection" (no redraw when nothing was recorded yet)."""
        if self.last is None and self.done == 0:
            return
        self.last = None
        self.done = 0
        self.line = Text("waiting for collection", style="dim")
        self._redraw()

    def complete(self) -> None:
        """Collection is over: the bar shows every pose done."""
        self.done = self.total
        self._redraw()

    def apply(self, event: CollectionProgress) -> None:
        self.last = event
        name = event.object_name
        line = Text(no_wrap=True, overflow="ellipsis")
        if not name:  # between objects or after the last one: the arm is free
            line.append("no object", style="dim")
        else:
            if name not in self.objects:
                self.objects.append(name)
            self.poses_per_object = event.poses_per_object
            self.done = min(self.objects.index(name) * event.poses_per_object + max(event.pose_index, 0), self.total)
            line.append(name, style="bold")
            if event.pose_index < 0:
                line.append("  reference frames")
            else:
                line.append(f"  pose {event.pose_index + 1}/{event.poses_per_object}")
        line.append("  ")
        line.append(f"{event.phase:<8}", style=_PHASE_STYLES.get(event.phase, ""))
        line.append(f"  frames {event.frames:5d}  |F| {event.force_n:5.2f} N  {event.pressure_hpa:7.1f} hPa")
        self.line = line
        self._redraw()

    def _redraw(self) -> None:
        width = max(self.content_region.width - 14, 10) if self.is_mounted else 40
        bar = text_bar(self.done / self.total, width, "dodger_blue1")
        bar.append(f" {self.done}/{self.total} poses")
        self.update(Group(self.line, bar), layout=False)

    def on_resize(self) -> None:
        self._redraw()
