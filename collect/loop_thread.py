"""A background loop that can be stopped: the reader, monitor and simulator threads of the bench.

Each device driver and simulated twin runs one loop in a daemon thread (the arm's state monitor,
the pressure board's serial reader, the simulated camera, firmware and physics, the commissioning
run's snapshots). The loop polls ``stop_event`` (``is_set()``, or ``wait(period_s)`` as its
sleep) and returns once it is set; ``stop()`` sets it and joins the thread.
"""
from __future__ import annotations

import threading
from typing import Callable


class LoopThread:
    """``target()`` in a named daemon thread, started once and stopped once.

    ``join_timeout_s``: how long ``stop()`` waits for the loop to return (s); a loop blocked longer
    is left behind as a daemon thread, so that stopping a device never hangs the caller.
    """

    def __init__(self, target: Callable[[], None], name: str, join_timeout_s: float = 2.0):
        self.target = target
        self.name = name
        self.join_timeout_s = float(join_timeout_s)
        #: Set by ``stop()``; the loop returns once it sees it.
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        """Whether the thread was started and not stopped since."""
        return self._thread is not None

    def start(self) -> None:
        """Start the loop (no-op while it runs)."""
        if self._thread is not None:
            return
        self.stop_event.clear()
        self._thread = threading.Thread(target=self.target, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the loop to return and wait for it (at most ``join_timeout_s``); safe to repeat."""
        self.stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=self.join_timeout_s)
            self._thread = None
