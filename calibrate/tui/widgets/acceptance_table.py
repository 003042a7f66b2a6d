"""Acceptance checks with pass/fail, the overall verdict and the report path (``Verdict``)."""

from __future__ import annotations

from rich import box
from rich.console import Group
from rich.table import Table
from rich.text import Text
from textual.containers import Vertical, VerticalScroll
from textual.widgets import Static

from calibrate.acceptance import NOT_RUN, check_value_text, limit_text, unit_suffix
from collect.numbers import is_number


def _with_unit(text: str, unit: str | None) -> str:
    return text + unit_suffix(unit) if text != "-" else text  # was: "ratio" written


def _limit(value: object) -> str:
    """A limit as its thresholds file writes it (``acceptance.limit_text``); other values as text."""
    return limit_text(value) if is_number(value) else str(value)


def threshold_text(check: dict) -> str:
    """``<= 1.5 mm``, ``in [1030, 1110] hPa``, or the bare threshold when the check has no ``op``."""
    threshold, op, unit = check.get("threshold"), check.get("op"), check.get("unit")
    if isinstance(threshold, (list, tuple)):
        bounds = "[" + ", ".join(_limit(v) for v in threshold) + "]"
        return _with_unit(f"{op or 'in'} {bounds}", unit)
    return _with_unit(f"{op} {_limit(threshold)}" if op else _limit(threshold), unit)


def value_text(check: dict) -> str:
    """The measured value with its unit, ``-`` when it was not measured: 4 significant digits, more where
    those would round it onto its limit (``acceptance.check_value_text``, as the report; was: a failed a1
    of 0.94996 shown as ``0.95`` beside ``>= 0.95``)."""
    return _with_unit(check_value_text(check), check.get("unit"))


class AcceptanceTable(Vertical):
    """Checks ``{name, value, threshold, op, unit, passed, reason}`` under a verdict line, the
    reasons of the failed ones below; scrolls when taller than the panel. In a narrow panel the check
    names are cut and the thresholds wrap first, so that the values and PASS/FAIL stay whole."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.border_title = "Acceptance"
        self.checks: list[dict] = []  # the checks shown
        self.showing = False  # a verdict (or a run's end) is shown
        self.verdict_line = Static("no verdict yet", id="verdict-line")
        self.table = Static("", id="checks")
        self.report_line = Static("", id="report-line")

    def compose(self):
        yield self.verdict_line
        with VerticalScroll(id="checks-scroll"):
            yield self.table
        yield self.report_line

    def reset(self) -> None:
        """Back to "no verdict yet" (nothing to redraw when nothing was shown: the start of a run
        redraws no more than it changes)."""
        if not self.showing:
            return
        self.showing = False
        self.checks = []
        self.verdict_line.update("no verdict yet")
        self.report_line.update("")
        self.table.update("")

    def show(self, accepted: bool | None, checks: list[dict], report_path: str, note: str = "") -> None:
        """Show the checks; ``accepted`` None means the run ended without a verdict. ``note`` says why
        the run ended early (a stop, a hardware fault), after the verdict."""
        self.showing = True
        if accepted is None:
            line = Text(f" NO VERDICT  {note}", style="bold black on yellow")
        elif accepted:
            line = Text(" ACCEPTED ", style="bold black on green")
        else:
            line = Text(" REJECTED ", style="bold white on red")
        if accepted is not None:
            made = [check for check in checks if check.get("verdict") != NOT_RUN]
            passed = sum(1 for check in made if check.get("passed"))
            line.append(f"  {passed}/{len(made)} checks passed")
            if len(made) < len(checks):  # a gate failed: the checks after it, as acceptance.json lists them
                line.append(f", {len(checks) - len(made)} not run")
            if note:
                line.append(f"  ({note})", style="bold red")
        self.verdict_line.update(line)
        self.checks = list(checks)
        table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, row_styles=["", "on grey11"])
        # Too wide for the panel, rich narrows the wrappable columns first (names cut, thresholds
        # wrapped); with every column no_wrap it cut all four evenly: "PA…" in a 100-column terminal.
        table.add_column("check", style="bold")
        table.add_column("value", no_wrap=True, justify="right")
        table.add_column("threshold")
        table.add_column("result", no_wrap=True)
        why = []  # reasons of the failed checks, below the table
        for check in checks:
            passed, ran = bool(check.get("passed")), check.get("verdict") != NOT_RUN
            table.add_row(
                str(check.get("name", "?")),
                value_text(check),
                threshold_text(check),
                Text("PASS", style="bold green") if passed else Text("FAIL", style="bold red") if ran
                else Text("not run", style="dim"),
            )
            if ran and not passed and check.get("reason"):
                why.append(Text.assemble((f"{check.get('name', '?')}: ", "bold red"), str(check["reason"])))
        self.table.update(Group(table, *([Text("")] + why if why else [])) if checks else "")
        self.report_line.update(Text(f"report: {report_path}") if report_path else "")
