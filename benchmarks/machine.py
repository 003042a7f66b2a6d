"""Where and when a benchmark ran: CPU model, cores, load, date (for the provenance lines of docs)."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """``cpu`` model, logical ``cores``, ``load`` (1-min load average), ``python``, ``date`` (local, minutes)."""
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "load": round(os.getloadavg()[0], 1),
        "python": platform.python_version(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }


def machine_line(info: dict) -> str:
    """One markdown line: ``Machine: AMD EPYC, 2 cores, load 1.0, Python 3.11.7; 2026-11-22 03:40.``"""
    return (f"Machine: {info['cpu']}, {info['cores']} cores, load average {info['load']} at the start, "
            f"Python {info['python']}; {info['date']}.")
