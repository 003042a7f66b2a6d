"""benchmarks/run_all.py: every benchmark script is run, and targets are read from the scripts' tables."""

from __future__ import annotations

import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import run_all  # noqa: E402

PAGE = """# Title

| frames | n | CPU median ms | fps (CPU median) | fps (CPU p90) |
|---|---|---|---|---|
| free | 120 | 2.16 | 463 | 400 |
| moving, no contact | 250 | 2.70 | 370 | 341 |
| moving, contact | 518 | 6.98 | 143 | 98 |

All presses: 16, median 132.9 ms, p95 684.0 ms, max 1384.7 ms; no update in 2 s: 0.
"""


def test_every_benchmark_script_is_run_and_every_target_has_its_benchmark():
    scripts = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}
    assert {b.script for b in run_all.BENCHMARKS} == scripts
    assert {t.benchmark for t in run_all.TARGETS} <= set(run_all.BY_NAME)


def test_cells_and_numbers_from_markdown_tables():
    assert run_all.cell(PAGE, "moving, contact", "fps (CPU median)") == "143"
    assert run_all.cell(PAGE, "moving, contact", "CPU median") == "6.98"
    assert run_all.cell(PAGE, "hold", "fps") is None
    assert run_all.cell(PAGE, "moving", "no such column") is None
    assert run_all.number("4.0x") == 4.0 and run_all.number("2.75e-04") == 2.75e-4 and run_all.number("-") is None


def test_targets_read_values_and_verdicts():
    simulator = next(t for t in run_all.TARGETS if t.benchmark == "simulator")
    value, detail = simulator.extract(PAGE)  # the frames in contact, at their 90th percentile
    assert value == 98 and not simulator.verdict(value) and "98" in detail
    tui = next(t for t in run_all.TARGETS if t.benchmark == "tui")
    value, _ = tui.extract(PAGE)
    assert value == 1384.7 and not tui.verdict(value)
    value, detail = tui.extract(PAGE.replace("max 1384.7 ms; no update in 2 s: 0", "max 12.0 ms; no update in 2 s: 1"))
    assert math.isinf(value) and not tui.verdict(value) and "no update in 2 s: 1" in detail  # was: met at 12 ms
    finetune = next(t for t in run_all.TARGETS if t.benchmark == "finetune")
    text = "Final (all held-out frames): a1 0.912, abs_rel 0.03, rmse 1 mm after 3.00 min (9 steps); a1 >= 0.95 reached at never; x"
    value, detail = finetune.extract(text)
    assert math.isinf(value) and not finetune.verdict(value) and "0.912" in detail


def test_demote_drops_the_title_and_shifts_headings():
    assert run_all.demote("# T\n\n## A\ntext\n### B") == ["", "### A", "text", "#### B"]


def _target(goal_start: str) -> run_all.Target:
    return next(t for t in run_all.TARGETS if t.goal.startswith(goal_start))


def test_the_fine_tune_step_is_not_read_from_the_deadline_line():
    """Was: with no sensor fine-tuned ("- / - / - s"), the pattern read the deadline line's 180 s: met."""
    target = _target("commissioning fine-tune step")
    page = ("* fine-tune step (data loading, training, final validation, ONNX export): - s, of which training - s\n"
            "* fine-tune step deadline: 180 / 180 / 180 s; shortened on no sensor\n")
    assert target.extract(page) == (None, "")
    assert target.extract(page.replace(": - s,", ": 167 / 169 / 170 s,"))[0] == 170


def test_commissioning_counts_accepted_good_and_rejected_defective_sensors():
    good, bad = _target("commissioning accepts"), _target("commissioning rejects")
    page = "* accepted: 3 of 3\n\n* defective sensors rejected by their guard: 2 of 3\n"
    assert good.extract(page)[0] == 1.0 and bad.extract(page)[0] == 2 / 3 and not bad.verdict(2 / 3)
    assert good.extract("* accepted: 0 of 0\n") == (None, "")  # was: ZeroDivisionError, no page written


def test_a_target_the_starting_model_meets_too_is_not_discriminating(tmp_path, monkeypatch):
    monkeypatch.setattr(run_all, "DOCS", tmp_path)
    monkeypatch.setattr(run_all, "TARGETS", (_target("fine-tune from the base model"),))
    page = "Zero-shot (base): a1 {zero}, abs_rel 0.01\n\nFinal (all held-out frames): a1 1.000, x after 3.00 min (9 steps); " \
           "a1 >= 0.95 reached at 0.00 min; y\n"
    (tmp_path / "bench_trainer.md").write_text(page.format(zero="1.000"))
    assert "met, but not discriminating: the starting point meets it too (base before fine-tuning: a1 1.000)" \
        in run_all.target_rows({})[2]
    (tmp_path / "bench_trainer.md").write_text(page.format(zero="0.800"))
    assert "| met |" in run_all.target_rows({})[2]


def test_a_page_its_last_run_did_not_rewrite_is_stale(tmp_path, monkeypatch):
    """Was: a script that failed left its earlier page, whose numbers were shown as measured and met."""
    monkeypatch.setattr(run_all, "DOCS", tmp_path)
    monkeypatch.setattr(run_all, "TARGETS", (_target("simulator"),))
    (tmp_path / "bench_simulator.md").write_text(PAGE.replace("| 98 |", "| 150 |"))
    machine = {"date": "2026-11-26 05:00"}
    assert "| met |" in run_all.target_rows({"simulator": {"exit": 0, "page_rewritten": True, "machine": machine}})[2]
    for run, why in (({"exit": 1, "page_rewritten": True}, "failed with exit 1"),
                     ({"exit": 0, "page_rewritten": False}, "did not rewrite the page")):
        row = run_all.target_rows({"simulator": {**run, "machine": machine}})[2]
        assert "**stale**" in row and why in row and "150" not in row


def test_the_accuracy_page_renders_from_its_committed_results():
    """bench_accuracy.py writes its JSON, then the page from it with ``bubble evaluate``'s columns: a change of
    those columns broke the page after a 28-minute run (the JSON written, the page not)."""
    import json

    from benchmarks import bench_accuracy
    from trainer.cli import PAPER_COLUMNS

    page = bench_accuracy.markdown(json.loads((ROOT / "docs" / "bench_accuracy.json").read_text()))
    header = " | ".join(h for _, h, _, _ in PAPER_COLUMNS)
    assert page.count(header) >= 3 and "RMSE [mm]" in header
