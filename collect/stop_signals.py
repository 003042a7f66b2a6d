"""Ctrl-C and the signals that end a command the way it does: SIGTERM (``kill``, a service
manager's stop) and SIGHUP (the terminal or the SSH session closed).

Python's default for the last two ends the process at once: an arm in the middle of a press is
left wherever the signal found it and the session file is left unclosed. ``bubble`` handles them
like Ctrl-C instead: the arm is stopped and retracted, the files are closed, and the command exits
with ``128 + signal number`` (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP). Any of them
arriving again while that runs is ignored (a second Ctrl-C says ``still stopping``), so that the
safe stop and the closing of the files finish: a second Ctrl-C 20 ms after the first used to cut
the closing short and leave the session file unclosed. Once a stop has begun the process only
ends: a repeat that arrives after the stop, while the process exits, is ignored too (was: a
stop that took under 20 ms left the default handler back in place, and the second Ctrl-C killed
the exiting process, which then reported -2 to its parent instead of 130).
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


#: While a ``process_ends`` block runs: the stop signals handled so far, by it or by a block nested
#: in it (``None`` outside one). Signal dispositions are process-wide, and so is this record.
_stops_before_exit: list[int] | None = None


@contextmanager
def stop_signals_handled(on_signal: Callable[[int], None], signals: tuple = STOP_SIGNALS, *,
                         process_ends: bool = False, exits_after: bool = False) -> Iterator[None]:
    """Call ``on_signal(signum)`` for the first of ``signals`` that arrives during the with-block;
    later ones are ignored (a Ctrl-C prints ``STILL_STOPPING``). The previous handlers are restored
    afterwards. After SIGHUP stdout and stderr go to /dev/null first: the terminal is gone, and a
    write to it would fail in the middle of the safe stop. Outside the main thread (where no handler
    can be set) the block runs unchanged.

    ``process_ends``: the block is the command's outermost, and the process exits after it. Once a
    stop has begun in it (this block's signal or a nested block's), each of ``INTERRUPTS`` is only
    acknowledged, no block inside restores a handler that would act on it, and this one leaves
    them ignored (``SIG_IGN``: the interpreter puts Python handlers back to the default as it
    shuts down, and the default of each kills the process), so that a repeat can no longer change
    how the process ends. ``exits_after`` (with ``process_ends``): the process exits right after the
    block, so it leaves them ignored with no stop too (the ``bubble`` executable; was: a Ctrl-C or
    SIGTERM just after a command's end, a fault's line printed, ended the process by the signal,
    exit -2 or -15 for its exit 3)."""
    global _stops_before_exit
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def still_stopping(signum, frame) -> None:
        acknowledge_stop(signum)

    def handler(signum, frame) -> None:
        if _stops_before_exit is not None:  # the process ends after this stop: any signal repeats it
            _stops_before_exit.append(signum)
        for sig in signals if _stops_before_exit is None else INTERRUPTS:
            signal.signal(sig, still_stopping)
        if signum == signal.SIGHUP:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)
            os.close(null)
        on_signal(signum)

    outer_record = _stops_before_exit
    if process_ends:
        _stops_before_exit = []
    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield
    finally:
        stopping = bool(_stops_before_exit)
        ignored = stopping or process_ends and exits_after
        if process_ends:
            _stops_before_exit = outer_record
            for sig in INTERRUPTS if ignored else ():
                signal.signal(sig, signal.SIG_IGN)
        if not ignored:
            for sig, old in previous.items():
                signal.signal(sig, old)


def acknowledge_stop(signum: int) -> None:
    """``on_signal`` for a stop already under way, such as a fault's safe stop: the signal would only
    ask for it again, so a Ctrl-C says ``STILL_STOPPING`` and nothing else happens (was, for a fault:
    the ``KeyboardInterrupt`` cut the retract short, and the run exited 130, its fault unsaid)."""
    if signum == signal.SIGINT:
        try:
            os.write(2, STILL_STOPPING)
        except OSError:  # no terminal any more
            pass


def raise_interrupt(signum: int) -> None:
    """``on_signal`` of a command that stops on ``KeyboardInterrupt``: raise it (``Terminated`` for
    ``STOP_SIGNALS``)."""
    raise KeyboardInterrupt if signum == signal.SIGINT else Terminated(signum)


def raise_pending_stop() -> None:
    """Raise (``raise_interrupt``) the first stop signal that the command's outermost block (``process_ends``)
    has handled, if any; nothing before a stop or outside such a block. For a command to end on a stop
    whose ``KeyboardInterrupt`` a library swallowed: trimesh's imports catch ``BaseException``, and
    depthai's turns it into an ``ImportError`` (was: a Ctrl-C while ``bubble collect`` started was
    lost, every later one only acknowledged, and the whole plan recorded, exit 0)."""
    if _stops_before_exit:
        raise_interrupt(_stops_before_exit[0])


def forget_pending_stop() -> None:
    """Let a command whose work saw the stop signal and ended before it mattered keep its own exit
    code: ``raise_pending_stop`` raises nothing after this (``bubble commission``: a Ctrl-C while the
    verdict was registered leaves the verdict standing, exit 0 or 1; was: an accepted sensor,
    registered, exited 130 "interrupted", a rejected one 1)."""
    if _stops_before_exit:
        _stops_before_exit.clear()


@contextmanager
def stop_signals_deferred(signals: tuple = INTERRUPTS) -> Iterator[None]:
    """Hold each of ``signals`` that arrives during the block, and deliver the first of them again
    at its end (to the handler in place before it): for work a stop must not cut in two, such as
    closing a session file. A Ctrl-C inside the writer thread's join, or inside h5py while it held
    its lock, left the file unmarked as closed, and now and then hung the exiting process for good.
    Outside the main thread (where no handler can be set) the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: held.append(signum)) for sig in signals}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, signal.SIG_DFL if old is None else old)  # None: a handler set outside Python
        if held:
            signal.raise_signal(held[0])
