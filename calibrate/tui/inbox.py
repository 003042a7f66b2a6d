"""Thread-safe hand-off of commissioning events from the flow runner's thread to the UI thread.

The flow calls ``on_event`` from its own thread, possibly very often (a ``BenchSnapshot`` per
camera frame, a ``CollectionProgress`` per recorded frame, a ``StepProgress`` per batch). The
UI must never fall behind, so the inbox coalesces:

* ``BenchSnapshot``: only the latest one is kept, in its own slot, and the UI picks it up at its
  own refresh rate (a few Hz) with ``take_snapshot``;
* ``CollectionProgress`` and ``StepProgress`` (same step): a new one replaces the previous one
  when only progress has been queued after it (the collection reports both for every frame); it
  never passes a step boundary, a fault or the verdict;
* everything else (step boundaries, training points, faults, the verdict) is queued in order.

``put`` returns True when the UI should be woken: for the first event since the last ``drain``
that is not progress (a step boundary, a fault, the verdict: shown at once), one message per batch.
Progress (``CollectionProgress``, ``StepProgress``, ``TrainingProgress``) never wakes the UI: it
waits in the queue for the UI's refresh timer (a few Hz) or the next waking event, so a flow that
reports progress at the camera's frame rate does not make the UI compose a frame for each report.
The UI takes the whole batch with ``drain``.
"""

from __future__ import annotations

import threading

from calibrate.commission_events import BenchSnapshot, CollectionProgress, StepProgress, TrainingProgress

#: Events that wait for the UI's refresh timer instead of waking it.
PROGRESS = (CollectionProgress, StepProgress, TrainingProgress)


def _replaces(new: object, queued: object) -> bool:
    """Whether ``new`` makes ``queued`` (a queued progress event) obsolete."""
    if isinstance(new, CollectionProgress) and isinstance(queued, CollectionProgress):
        return True
    return isinstance(new, StepProgress) and isinstance(queued, StepProgress) and new.step == queued.step


class EventInbox:
    """Coalescing, thread-safe queue of commissioning events (see module docstring)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queue: list[object] = []
        self._snapshot: BenchSnapshot | None = None
        self._woken = False  # a waking event was put since the last drain
        self.received = 0  # events put so far (all kinds), for diagnostics and benchmarks

    def put(self, event: object) -> bool:
        """Add one event; returns True when the UI should be woken for queued events."""
        with self._lock:
            self.received += 1
            if isinstance(event, BenchSnapshot):
                self._snapshot = event
                return False
            for k in range(len(self._queue) - 1, -1, -1):  # the progress queued since the last other event
                queued = self._queue[k]
                if _replaces(event, queued):
                    del self._queue[k]
                    break
                if not isinstance(queued, PROGRESS):
                    break
            self._queue.append(event)
            if isinstance(event, PROGRESS) or self._woken:
                return False
            self._woken = True
            return True

    def drain(self) -> list[object]:
        """Take every queued event (oldest first), leaving the queue empty."""
        with self._lock:
            events, self._queue = self._queue, []
            self._woken = False
        return events

    def take_snapshot(self) -> BenchSnapshot | None:
        """Take the latest bench snapshot, or None when none arrived since the last call."""
        with self._lock:
            snapshot, self._snapshot = self._snapshot, None
        return snapshot
