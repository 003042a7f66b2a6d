"""Acceptance checks with pass/fail, the overall verdict and the report path (``Verdict``)."""

from __future__ import annotations

from rich.text import Text
from textual.containers import Vertical
from textual.widgets import DataTable, Static

from calibrate.tui.widgets.formatting import number


class AcceptanceTable(Vertical):
    """Table of checks ``{name, value, threshold, passed, reason}`` under a verdict line."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.border_title = "Acceptance"
        self.verdict_line = Static("no verdict yet", id="verdict-line")
        self.table = DataTable(id="checks", zebra_stripes=True, cursor_type="none", show_cursor=False)
        self.report_line = Static("", id="report-line")

    def compose(self):
        yield self.verdict_line
        yield self.table
        yield self.report_line

    def on_mount(self) -> None:
        self.table.add_columns("check", "value", "threshold", "result", "reason")

    def reset(self) -> None:
        self.verdict_line.update("no verdict yet")
        self.report_line.update("")
        self.table.clear()

    def show(self, accepted: bool | None, checks: list[dict], report_path: str, note: str = "") -> None:
        """Show the checks; ``accepted`` None means the run ended without a verdict (``note`` says why)."""
        if accepted is None:
            line = Text(f" NO VERDICT  {note}", style="bold black on yellow")
        elif accepted:
            line = Text(" ACCEPTED ", style="bold black on green")
        else:
            line = Text(" REJECTED ", style="bold white on red")
        if accepted is not None:
            failed = sum(1 for check in checks if not check.get("passed"))
            line.append(f"  {len(checks) - failed}/{len(checks)} checks passed")
        self.verdict_line.update(line)
        table = self.table
        table.clear()
        for check in checks:
            passed = bool(check.get("passed"))
            table.add_row(
                str(check.get("name", "?")),
                number(check.get("value")),
                number(check.get("threshold")),
                Text("PASS", style="bold green") if passed else Text("FAIL", style="bold red"),
                str(check.get("reason", "") or ""),
            )
        self.report_line.update(f"report: {report_path}" if report_path else "")
