"""Confirmation dialog shown before anything moves."""

from __future__ import annotations

from rich.text import Text
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Static


class ConfirmStart(ModalScreen[bool]):
    """Asks before the arm moves; dismisses with True (start) or False (cancel)."""

    BINDINGS = [
        Binding("y,Y", "answer(True)", "Start", key_display="y"),
        Binding("n,N", "answer(False)", "Cancel", key_display="n"),
        Binding("escape", "answer(False)", "Cancel", show=False),
        Binding("q,Q", "answer(False)", "Cancel", show=False),  # the app's quit key: back out first
    ]

    def __init__(self, details: str) -> None:
        super().__init__()
        self.details = details

    def compose(self):
        with Vertical(id="confirm-box"):
            yield Static("[b]Start commissioning?[/b]", id="confirm-title")
            yield Static("The arm will move. Clear the bench and keep the stop key [b]s[/b] at hand.")
            yield Static(Text(self.details), id="confirm-details")  # paths are no markup
            with Horizontal(id="confirm-buttons"):
                yield Button("Start (y)", variant="warning", id="confirm-yes")
                yield Button("Cancel (n)", variant="primary", id="confirm-no")

    def on_mount(self) -> None:
        self.query_one("#confirm-no", Button).focus()

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "confirm-yes")

    def action_answer(self, start: bool) -> None:
        self.dismiss(start)
