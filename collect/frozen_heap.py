"""The process's heap frozen while a robot arm is monitored: no garbage collection starves the
robot's watchdog.

CPython's cyclic garbage collector holds the GIL while it walks a generation, and a full collection
walks every tracked object: 0.3 s for 3 M of them on the 2-core reference machine, and up to 0.7 s
for 0.5-0.8 M in a pytest worker sharing the two cores with another (session 61). The arm's monitor
must kick the robot's watchdog at least every 0.5 s (``collect.arm.WATCHDOG_HZ``), or the robot
brakes its move and stops its control program (``host-stalled``). So while any arm is monitored,
every object already tracked is frozen (``gc.freeze``): the collector, still automatic, walks only
what was allocated since. Cyclic garbage among the frozen objects waits until the last arm closes
(``gc.unfreeze``).
"""

from __future__ import annotations

import gc
import threading

_lock = threading.Lock()
_monitored_arms = 0


def freeze_heap() -> None:
    """One more monitored arm: freeze every object tracked now (for each arm: one started while
    another runs freezes what was allocated in between too)."""
    global _monitored_arms
    with _lock:
        _monitored_arms += 1
        gc.freeze()


def thaw_heap() -> None:
    """One monitored arm fewer: with none left, the frozen objects are collected again."""
    global _monitored_arms
    with _lock:
        _monitored_arms -= 1
        if _monitored_arms == 0:
            gc.unfreeze()
