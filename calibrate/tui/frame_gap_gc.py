"""Garbage collection of the UI process between frames, not inside them.

Python starts a cyclic garbage collection when the allocations since the last one pass a
threshold, i.e. in the middle of whatever allocates: in a UI, the rendering of a frame, and most
often the frame that answers a key press (a tab switch allocates tens of thousands of objects, so
it crosses the threshold itself). The pause then adds to that key's latency (collections of 8-80 ms
in docs/bench_tui.md). ``FrameGapCollector`` turns the automatic collector off and runs the same
generational collections from a UI timer instead, between frames: a key press now waits for a
collection only when it arrives during one.

The schedule mirrors CPython's: a young collection once ``young_objects`` more objects are tracked
than freed, every ``older_every``-th one also collects the middle generation, every
``older_every ** 2``-th one the whole heap. Everything alive when it starts (imported modules, the
composed widgets) is frozen first (``gc.freeze``): never traversed again.
"""

from __future__ import annotations

import gc

#: Net new tracked objects that make the timer collect the young generation (CPython's default: 700).
YOUNG_OBJECTS = 20_000
#: Every this many young collections include the middle generation, and its square the oldest.
OLDER_EVERY = 10
#: Period of the timer that checks the young generation, s.
CHECK_INTERVAL_S = 0.05


class FrameGapCollector:
    """Runs this process's cyclic garbage collector from a timer (process-wide: only for an app
    that owns its process, ``bubble tui``).

    ``start()`` collects, freezes and disables the automatic collector; ``tick()`` (called by the
    app's timer every ``CHECK_INTERVAL_S``) collects when due; ``stop()`` restores the collector.
    """

    def __init__(self, young_objects: int = YOUNG_OBJECTS, older_every: int = OLDER_EVERY) -> None:
        self.young_objects = young_objects
        self.older_every = older_every
        self.collections = 0  # by tick(), every generation
        self._was_enabled: bool | None = None

    @property
    def running(self) -> bool:
        return self._was_enabled is not None

    def start(self) -> None:
        if self.running:
            return
        self._was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()

    def tick(self) -> int | None:
        """Collect if the young generation is full; returns the generation collected, or None."""
        if not self.running or gc.get_count()[0] < self.young_objects:
            return None
        self.collections += 1
        n, k = self.collections, self.older_every
        generation = 2 if n % (k * k) == 0 else 1 if n % k == 0 else 0
        gc.collect(generation)
        return generation

    def stop(self) -> None:
        """Give the process its automatic collector back (unfrozen, enabled as before ``start``)."""
        if not self.running:
            return
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()
        self._was_enabled = None
