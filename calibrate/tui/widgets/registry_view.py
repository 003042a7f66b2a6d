"""Sensor registry view: every commissioned sensor with its status and latest metrics."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

from rich.text import Text
from textual.containers import Vertical
from textual.widgets import DataTable, Static

from calibrate.sensor_registry import SensorRegistry
from calibrate.tui.widgets.formatting import number
from collect.errors import InputError


#: Widest serial shown whole, in cells: a longer one (serials run to 64 characters) ends in an
#: ellipsis, and the other columns stay in view (was: pushed off behind a horizontal scroll bar).
SERIAL_WIDTH = 16


def _short_serial(serial: str) -> str:
    """``serial`` cut to ``SERIAL_WIDTH`` cells with an ellipsis."""
    return serial if len(serial) <= SERIAL_WIDTH else serial[:SERIAL_WIDTH - 1] + "…"


def _short_time(iso: str | None) -> str:
    """``YYYY-MM-DD HH:MM`` of an ISO-8601 time stamp in local time, as the run folders are named (was:
    the stored UTC time with its offset cut off, unmarked); ``-`` when missing, a text that is no time
    stamp cut to 16 characters."""
    if not iso:
        return "-"
    try:
        return datetime.fromisoformat(str(iso)).astimezone().strftime("%Y-%m-%d %H:%M")
    except ValueError:
        return str(iso)[:16]


class RegistryView(Vertical):
    """Table of the readable profiles of ``SensorRegistry.survey()``, its damaged entries named above
    it; ``reload`` re-reads the registry directory."""

    def __init__(self, registry_dir: Path | None, **kwargs) -> None:
        super().__init__(**kwargs)
        self.registry_dir = registry_dir
        self.border_title = "Sensor registry"
        self.line = Static("", id="registry-line")
        self.table = DataTable(id="registry-table", zebra_stripes=True, cursor_type="none", show_cursor=False)

    def compose(self):
        yield self.line
        yield self.table

    def on_mount(self) -> None:
        self.reload()

    def reload(self) -> None:
        table, line = self.table, self.line
        table.clear(columns=True)
        try:
            registry = SensorRegistry(self.registry_dir)
            listing = registry.survey()
        except InputError as err:
            line.update(Text(f"registry unreadable: {err}", style="bold red"))
            return
        profiles = listing.profiles
        serial_width = max([len("serial")] + [len(_short_serial(p.serial)) for p in profiles])
        table.add_column("serial", width=serial_width)
        table.add_columns("status", "last run", "mode", "runs", "model", "abs_rel", "a1")
        summary = Text(f"{registry.root}  ({len(profiles)} sensor{'s' if len(profiles) != 1 else ''})  r: reload")
        problem = listing.problem()
        if problem is not None:
            summary.append(f"\n{problem}", style="bold red")
        line.update(summary)
        for profile in profiles:
            data = profile.data
            metrics = profile.model_metrics  # the kept model's (a rejected run changes neither)
            status = profile.status
            table.add_row(
                _short_serial(profile.serial),
                Text(status, style="bold green" if status == "accepted" else "bold red"),
                _short_time(data.get("last_commissioned")),
                "sim" if data.get("simulated") else "real",
                str(len(profile.history)),
                Text(profile.model_state, style="bold red" if profile.missing() else ""),
                number(metrics.get("abs_rel")),
                number(metrics.get("a1")),
            )
