"""Ctrl-C and the signals that end a command the way it does: SIGTERM (``kill``, a service
manager's stop) and SIGHUP (the terminal or the SSH session closed).

Python's default for the last two ends the process at once: an arm in the middle of a press is
left wherever the signal found it and the session file is left unclosed. ``bubble`` handles them
like Ctrl-C instead: the arm is stopped and retracted, the files are closed, and the command exits
with ``128 + signal number`` (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP). Any of them
arriving again while that runs is ignored (a second Ctrl-C says ``still stopping``), so that the
safe stop and the closing of the files finish: a second Ctrl-C 20 ms after the first used to cut
the closing short and leave the session file unclosed.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

#: The signals handled like Ctrl-C.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
#: Ctrl-C and ``STOP_SIGNALS``.
INTERRUPTS = (signal.SIGINT, *STOP_SIGNALS)
#: What a Ctrl-C during the stop says (written to the stderr descriptor: a signal handler must not
#: enter a Python stream that the interrupted code may be writing).
STILL_STOPPING = b"bubble: still stopping (arm retracting, files closing) ...\n"


def exit_code(signum: int) -> int:
    """``128 + signum``, what a shell reports for a process ended by the signal (130 for Ctrl-C)."""
    return 128 + signum


class Terminated(KeyboardInterrupt):
    """Raised in the main thread for one of ``STOP_SIGNALS`` (``signum``): every ``except
    KeyboardInterrupt`` of a run (safe stop, files closed) handles it as it handles Ctrl-C."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(self.name)

    @property
    def name(self) -> str:
        """The signal's name, e.g. ``SIGTERM``."""
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return exit_code(self.signum)


@contextmanager
def stop_signals_handled(on_signal: Callable[[int], None], signals: tuple = STOP_SIGNALS) -> Iterator[None]:
    """Call ``on_signal(signum)`` for the first of ``signals`` that arrives during the with-block;
    later ones are ignored (a Ctrl-C prints ``STILL_STOPPING``). The previous handlers are restored
    afterwards. After SIGHUP stdout and stderr go to /dev/null first: the terminal is gone, and a
    write to it would fail in the middle of the safe stop. Outside the main thread (where no handler
    can be set) the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def still_stopping(signum, frame) -> None:
        if signum == signal.SIGINT:
            try:
                os.write(2, STILL_STOPPING)
            except OSError:  # no terminal any more
                pass

    def handler(signum, frame) -> None:
        for sig in signals:
            signal.signal(sig, still_stopping)
        if signum == signal.SIGHUP:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)
            os.close(null)
        on_signal(signum)

    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def raise_interrupt(signum: int) -> None:
    """``on_signal`` of a command that stops on ``KeyboardInterrupt``: raise it (``Terminated`` for
    ``STOP_SIGNALS``)."""
    raise KeyboardInterrupt if signum == signal.SIGINT else Terminated(signum)
