"""Where and when a benchmark ran: CPU model, cores, load, date (for the provenance lines of docs)."""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path

#: A run during which other processes used more than this many cores on average (``finish``) shared the
#: CPU with them: its numbers are provisional. (The load average cannot tell: it lags by a minute, so a
#: benchmark that starts right after another one read as busy; and it counts this benchmark's own work.)
#: "Other processes" is the machine's busy time (/proc/stat) less this process's: it includes the kernel's
#: interrupt and writeback work for this benchmark's own I/O, and, in a container, other tenants' time.
OTHERS_MAX_CORES = 0.25
#: /proc/stat's busy fields of the "cpu" line: user, nice, system, irq, softirq, steal (1-based columns).
_BUSY_COLUMNS = (1, 2, 3, 6, 7, 8)


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def cpu_seconds() -> tuple[float, float]:
    """(CPU seconds every process of this machine has used since boot, those this process and the children
    it waited for have used): /proc/stat's busy time (Linux; nan elsewhere) and ``os.times``."""
    own = os.times()
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
        busy = sum(int(fields[k]) for k in _BUSY_COLUMNS) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        busy = float("nan")
    return busy, own.user + own.system + own.children_user + own.children_system


def machine_info() -> dict:
    """At a run's start: ``cpu`` model, logical ``cores``, ``load`` (1-min load average), ``python``, ``date``
    (local, minutes), and ``started`` (``cpu_seconds()`` and ``time.monotonic()``, for ``finish``)."""
    busy, own = cpu_seconds()
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "load": round(os.getloadavg()[0], 1),
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "started": {"busy_s": busy, "own_s": own, "t": time.monotonic()},
    }


def finish(info: dict) -> dict:
    """``info`` (``machine_info()`` at the run's start) at its end: ``started`` replaced by ``others_cores``, the
    cores other processes used on average during the run (None where /proc/stat is missing), and ``load_end``."""
    busy, own = cpu_seconds()
    started = info["started"]
    wall = max(time.monotonic() - started["t"], 1e-9)
    others = (busy - started["busy_s"]) - (own - started["own_s"])
    done = {k: v for k, v in info.items() if k != "started"}
    return {**done, "others_cores": None if math.isnan(others) else round(max(0.0, others) / wall, 2),
            "load_end": round(os.getloadavg()[0], 1)}


def machine_line(info: dict) -> str:
    """One markdown line, e.g. ``Machine: AMD EPYC 7B13, 2 cores, load average 0.3 at the start, Python 3.11.7;
    2026-11-22 03:40.`` (``info`` from ``machine_info`` at the run's start)."""
    return (f"Machine: {info['cpu']}, {info['cores']} cores, load average {info['load']} at the start, "
            f"Python {info['python']}; {info['date']}.")


def provisional(info: dict) -> bool:
    """Whether other processes used more than ``OTHERS_MAX_CORES`` during the run (``info`` from ``finish``;
    False where that was not measured)."""
    return (info.get("others_cores") or 0.0) > OTHERS_MAX_CORES


def provisional_note(info: dict) -> str:
    """What other processes used during the run (``info`` from ``finish``; ``""`` for a record from before this
    was measured), with a leading space, and **Provisional** when ``provisional(info)``."""
    if "others_cores" not in info:
        return ""
    if info["others_cores"] is None:
        return " The CPU other processes used was not measured (no /proc/stat)."
    note = f" Other processes used {info['others_cores']:.2f} cores on average during the run."
    if provisional(info):
        note += (f" **Provisional**: above {OTHERS_MAX_CORES:g}, they shared the CPU with this benchmark; "
                 "rerun on a quiet machine.")
    return note


def provenance(info: dict) -> str:
    """A page's provenance, written at the run's end (``info``: ``machine_info()`` at its start):
    ``machine_line``, the load average at the end and ``provisional_note``."""
    done = finish(info)
    return machine_line(done) + f" Load average {done['load_end']:.1f} at the end." + provisional_note(done)
