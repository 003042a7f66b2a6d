"""Signals that end a command the way Ctrl-C does: SIGTERM (``kill``, a service manager's stop)
and SIGHUP (the terminal or the SSH session closed).

Python's default for them ends the process at once: an arm in the middle of a press is left
wherever the signal found it and the session file is left unclosed. ``bubble`` handles them like
Ctrl-C instead: the arm is stopped and retracted, the files are closed, and the command exits with
``128 + signal number`` (143 for SIGTERM, 129 for SIGHUP). A repeat of either signal while that
runs is ignored, so that the safe stop finishes.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

#: The signals handled like Ctrl-C.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread for one of ``STOP_SIGNALS`` (``signum``): every ``except
    KeyboardInterrupt`` of a run (safe stop, files closed) handles it as it handles Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def name(self) -> str:
        """The signal's name, e.g. ``SIGTERM``."""
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        """``128 + signum``, what a shell reports for a process ended by the signal."""
        return 128 + self.signum


@contextmanager
def stop_signals_handled(on_signal: Callable[[int], None]) -> Iterator[None]:
    """Call ``on_signal(signum)`` for the first of ``STOP_SIGNALS`` that arrives during the with-block
    (later ones are ignored); the previous handlers are restored afterwards. After SIGHUP stdout and
    stderr go to /dev/null first: the terminal is gone, and a write to it would fail in the middle of
    the safe stop. Outside the main thread (where no handler can be set) the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame) -> None:
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)
        if signum == signal.SIGHUP:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)
            os.close(null)
        on_signal(signum)

    previous = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def raise_terminated(signum: int) -> None:
    """``on_signal`` of a command that stops on ``KeyboardInterrupt``: raise ``Terminated``."""
    raise Terminated(signum)
