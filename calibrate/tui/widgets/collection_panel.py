"""Live per-pose progress during data collection, from ``CollectionProgress`` events."""

from __future__ import annotations

from rich.text import Text
from textual.containers import Vertical
from textual.widgets import Label, ProgressBar

from calibrate.commission_events import CollectionProgress

_PHASE_STYLES = {"press": "bold red", "hold": "bold magenta", "approach": "yellow", "retract": "cyan", "free": "dim"}


class CollectionPanel(Vertical):
    """Object, pose k/K, contact phase, frames recorded, force and pressure, and a bar over all
    contact poses of the run (``objects`` in plan order, ``poses_per_object`` each)."""

    def __init__(self, objects: tuple[str, ...], poses_per_object: int, **kwargs) -> None:
        super().__init__(**kwargs)
        self.objects = list(objects)
        self.poses_per_object = poses_per_object
        self.border_title = "Collection"
        self.last: CollectionProgress | None = None  # the latest event shown
        self.line = Label("waiting for collection", id="collection-line")
        self.bar = ProgressBar(total=max(1, len(self.objects) * poses_per_object), show_eta=False, id="collection-bar")

    def compose(self):
        yield self.line
        yield self.bar

    def reset(self) -> None:
        self.last = None
        self.line.update("waiting for collection")
        self.bar.update(progress=0)

    def complete(self) -> None:
        """Collection is over: the bar shows every pose done."""
        self.bar.update(progress=self.bar.total)

    def apply(self, event: CollectionProgress) -> None:
        self.last = event
        name = event.object_name
        line = Text()
        if not name:  # between objects or after the last one: the arm is free
            line.append("no object", style="dim")
        else:
            if name not in self.objects:
                self.objects.append(name)
            self.poses_per_object = event.poses_per_object
            total = max(1, len(self.objects) * event.poses_per_object)
            done = self.objects.index(name) * event.poses_per_object + max(event.pose_index, 0)
            self.bar.update(total=total, progress=min(done, total))
            line.append(name, style="bold")
            if event.pose_index < 0:
                line.append("  reference frames")
            else:
                line.append(f"  pose {event.pose_index + 1}/{event.poses_per_object}")
        line.append("  ")
        line.append(f"{event.phase:<8}", style=_PHASE_STYLES.get(event.phase, ""))
        line.append(f"  frames {event.frames:5d}  |F| {event.force_n:5.2f} N  {event.pressure_hpa:7.1f} hPa")
        self.line.update(line)
