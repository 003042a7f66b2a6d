"""benchmarks/run_all.py: every benchmark script is run, and targets are read from the scripts' tables."""

from __future__ import annotations

import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import run_all  # noqa: E402

PAGE = """# Title

| frames | n | CPU median ms | fps (CPU median) |
|---|---|---|---|
| free | 120 | 2.16 | 463 |
| moving | 768 | 9.81 | 102 |

All presses: 16, median 132.9 ms, p95 684.0 ms, max 1384.7 ms.
"""


def test_every_benchmark_script_is_run_and_every_target_has_its_benchmark():
    scripts = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}
    assert {b.script for b in run_all.BENCHMARKS} == scripts
    assert {t.benchmark for t in run_all.TARGETS} <= set(run_all.BY_NAME)


def test_cells_and_numbers_from_markdown_tables():
    assert run_all.cell(PAGE, "moving", "fps (CPU median)") == "102"
    assert run_all.cell(PAGE, "moving", "CPU median") == "9.81"
    assert run_all.cell(PAGE, "hold", "fps") is None
    assert run_all.cell(PAGE, "moving", "no such column") is None
    assert run_all.number("4.0x") == 4.0 and run_all.number("2.75e-04") == 2.75e-4 and run_all.number("-") is None


def test_targets_read_values_and_verdicts():
    simulator = next(t for t in run_all.TARGETS if t.benchmark == "simulator")
    value, detail = simulator.extract(PAGE)
    assert value == 102 and simulator.verdict(value) and "102" in detail
    tui = next(t for t in run_all.TARGETS if t.benchmark == "tui")
    value, _ = tui.extract(PAGE)
    assert value == 1384.7 and not tui.verdict(value)
    finetune = next(t for t in run_all.TARGETS if t.benchmark == "finetune")
    text = "Final (all held-out frames): a1 0.912, abs_rel 0.03, rmse 1 mm after 3.00 min (9 steps); a1 >= 0.95 reached at never; x"
    value, detail = finetune.extract(text)
    assert math.isinf(value) and not finetune.verdict(value) and "0.912" in detail


def test_demote_drops_the_title_and_shifts_headings():
    assert run_all.demote("# T\n\n## A\ntext\n### B") == ["", "### A", "text", "#### B"]
