"""Unit tests of the TUI's pure parts: event inbox, half-block images, charts, formats."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from calibrate.commission_events import (
    BenchSnapshot,
    CollectionProgress,
    FaultRaised,
    Step,
    StepFinished,
    StepProgress,
    StepStarted,
    TrainingProgress,
)
from calibrate.tui.halfblock import DEPTH, GREY, INVALID_RGB, UPPER_HALF, fit_cells, halfblock_rows, scale_image
from calibrate.tui.inbox import EventInbox
from calibrate.tui.widgets.formatting import duration, number
from calibrate.tui.widgets.training_curve import bar_chart, column_values


def _snapshot(p: float) -> BenchSnapshot:
    return BenchSnapshot(True, [0.0] * 6, [0.0] * 6, p)


def _progress(frames: int, obj: str = "mug") -> CollectionProgress:
    return CollectionProgress(obj, 0, 2, "press", frames, 1.0, 1065.0)


def test_inbox_keeps_order_coalesces_fast_events_and_wakes_once_per_batch():
    inbox = EventInbox()
    wakes = [inbox.put(StepStarted(Step.COLLECT, 10.0))]
    wakes += [inbox.put(_progress(k)) for k in range(100)]
    wakes += [inbox.put(_snapshot(1000.0 + k)) for k in range(50)]
    wakes.append(inbox.put(StepProgress(Step.COLLECT, 0.1)))
    wakes.append(inbox.put(StepProgress(Step.COLLECT, 0.2)))
    wakes.append(inbox.put(TrainingProgress(1, 0.1, 0.5)))
    wakes.append(inbox.put(TrainingProgress(2, 0.2, 0.4)))
    wakes.append(inbox.put(StepFinished(Step.COLLECT, True)))
    assert wakes == [True] + [False] * (len(wakes) - 1)
    events = inbox.drain()
    assert [type(e).__name__ for e in events] == [
        "StepStarted", "CollectionProgress", "StepProgress", "TrainingProgress", "TrainingProgress", "StepFinished"
    ]
    assert events[1].frames == 99 and events[2].fraction == 0.2
    assert inbox.take_snapshot().pressure_hpa == 1049.0
    assert inbox.take_snapshot() is None
    assert inbox.drain() == []
    assert inbox.received == 156


def test_inbox_leaves_progress_to_the_refresh_timer_and_wakes_for_anything_else():
    inbox = EventInbox()
    progress = [_progress(1), StepProgress(Step.COLLECT, 0.5), TrainingProgress(1, 0.1, 0.5)]
    assert [inbox.put(event) for event in progress] == [False] * 3  # the timer drains them
    assert inbox.put(FaultRaised("camera-stall", "no frame for 0.5 s")) is True  # shown at once
    assert inbox.put(StepFinished(Step.COLLECT, False)) is False  # that batch is already due
    assert [type(e).__name__ for e in inbox.drain()] == [
        "CollectionProgress", "StepProgress", "TrainingProgress", "FaultRaised", "StepFinished"]
    assert inbox.put(StepStarted(Step.FINETUNE, 60.0)) is True  # drained: the next batch wakes again


def test_inbox_merges_progress_across_progress_but_not_across_other_events_or_steps():
    inbox = EventInbox()
    for event in (_progress(1), StepProgress(Step.COLLECT, 0.5), _progress(2),
                  StepProgress(Step.FINETUNE, 0.1), StepProgress(Step.COLLECT, 0.6),
                  StepFinished(Step.COLLECT, True), _progress(3), StepProgress(Step.COLLECT, 0.7)):
        inbox.put(event)
    assert [(type(e).__name__, getattr(e, "frames", None), getattr(e, "fraction", None)) for e in inbox.drain()] == [
        ("CollectionProgress", 2, None), ("StepProgress", None, 0.1), ("StepProgress", None, 0.6),
        ("StepFinished", None, None), ("CollectionProgress", 3, None), ("StepProgress", None, 0.7)]


def test_inbox_loses_nothing_under_concurrent_producers():
    inbox = EventInbox()
    n = 2000

    def produce(offset):
        for k in range(n):
            inbox.put(TrainingProgress(offset + k, 0.0, 0.0))

    threads = [threading.Thread(target=produce, args=(i * n,)) for i in range(2)]
    got = []
    for t in threads:
        t.start()
    while any(t.is_alive() for t in threads):
        got += inbox.drain()
    got += inbox.drain()
    assert sorted(e.step for e in got) == list(range(2 * n))


def test_scale_image_maps_valid_range_and_marks_invalid():
    depth = np.full((4, 6), 0.08, np.float32)
    depth[0, 0] = 0.0
    depth[1, :] = 0.06
    scaled = scale_image(depth, valid=depth > 0, percentiles=(0.0, 100.0))
    assert scaled.lo == pytest.approx(0.06) and scaled.hi == pytest.approx(0.08)
    assert scaled.index[0, 0] == -1 and scaled.index[1, 2] == 0 and scaled.index[3, 3] == 255
    assert scaled.invalid_fraction == pytest.approx(1 / 24)
    empty = scale_image(np.zeros((3, 3), np.float32), valid=np.zeros((3, 3), bool))
    assert (empty.index == -1).all() and empty.invalid_fraction == 1.0


def test_fit_cells_keeps_square_pixels_inside_the_box():
    assert fit_cells((172, 224), 224, 200) == (224, 86)  # width-limited: one cell per column
    cols, rows = fit_cells((172, 224), 200, 20)  # height-limited
    assert rows == 20 and cols == int(224 * 40 / 172)
    assert fit_cells((172, 224), 0, 10) == (0, 0)


def test_halfblock_rows_paint_upper_and_lower_pixels():
    index = np.array([[0, 255], [255, -1]], np.int16)
    rows = halfblock_rows(index, 2, 1, GREY)
    assert len(rows) == 1
    cells = [(seg.text, seg.style) for seg in rows[0]]
    assert "".join(text for text, _ in cells) == UPPER_HALF * 2
    (_, left), (_, right) = cells
    assert left.color.get_truecolor() == (0, 0, 0) and left.bgcolor.get_truecolor() == tuple(GREY.lut[252])
    assert right.color.get_truecolor() == tuple(GREY.lut[252])
    assert right.bgcolor.get_truecolor() == INVALID_RGB


def test_no_depth_looks_like_no_colour_of_the_depth_map():
    """Was: dark magenta, 31 RGB units from the map's far end: the farthest membrane read as dropouts."""
    from calibrate.tui.halfblock import DEPTH_INVALID_RGB

    distances = np.linalg.norm(DEPTH.lut.astype(float) - np.array(DEPTH_INVALID_RGB, float), axis=1)
    assert distances.min() > 100
    (row,) = halfblock_rows(np.array([[-1], [0]], np.int16), 1, 1, DEPTH)
    assert row[0].style.color.get_truecolor() == DEPTH_INVALID_RGB


def test_halfblock_rows_merge_runs_and_resample():
    index = np.zeros((172, 224), np.int16)
    index[:, 112:] = 200
    rows = halfblock_rows(index, 56, 21, DEPTH)
    assert len(rows) == 21
    assert all(len(segments) == 2 and sum(len(s.text) for s in segments) == 56 for segments in rows)


def test_bar_chart_levels_and_compression():
    rows, lo, hi = bar_chart([0.0, 1.0, 0.5], width=5, height=2)
    assert (lo, hi) == (0.0, 1.0)
    # eighths of a bar: 0 -> 1 (a sliver), 1 -> 16 (both cells full), 0.5 -> 9 (full + 1/8)
    assert rows == [" █▁  ", "▁██  "]
    assert len(column_values(list(range(100)), 10)) == 10
    assert column_values(list(range(100)), 10)[0] == pytest.approx(4.5)
    assert bar_chart([], 4, 2)[0] == ["    ", "    "]
    assert bar_chart([float("nan")], 4, 2)[0] == ["    ", "    "]  # no finite point yet (initial loss)
    rows, lo, hi = bar_chart([float("nan"), 0.5, 0.5], 3, 2)  # flat: half height, NaN skipped
    assert rows == ["   ", "██ "] and lo == hi == 0.5


def test_check_formats():
    from calibrate.tui.widgets.acceptance_table import threshold_text, value_text

    check = {"value": 7.97, "threshold": 1.5, "op": "<=", "unit": "mm"}
    assert (value_text(check), threshold_text(check)) == ("7.97 mm", "<= 1.5 mm")
    check = {"value": 1062.4, "threshold": [1030.0, 1110.0], "op": "in", "unit": "hPa"}
    assert threshold_text(check) == "in [1030, 1110] hPa"
    assert value_text({"value": None, "unit": "mm"}) == "-"
    assert threshold_text({"threshold": 0.9, "op": ">=", "unit": "fraction"}) == ">= 0.9"
    assert threshold_text({"threshold": "< 5"}) == "< 5"


def test_formats():
    assert duration(None) == "--:--"
    assert duration(83.4) == "1:23"
    assert duration(3725) == "1:02:05"
    assert number(0.123456) == "0.1235" and number(True) == "yes" and number(None) == "-" and number("< 5") == "< 5"


def test_step_lines_are_fixed_width_columns():
    from calibrate.tui.widgets.steps_panel import _FIXED_CELLS, StepsPanel, _cell

    assert _cell("abcdef", 4, "dim").plain == "abc…"
    padded = _cell("ab", 4, "dim")
    assert padded.plain == "ab  " and padded.style == "dim"  # the padding keeps the column's style
    assert _cell("7%", 4, right=True).plain == "  7%" and _cell("x", 0).plain == ""
    panel = StepsPanel()
    panel.rows[Step.CONNECT].summary = "sensor SB-SIM-000000, camera 224x172 中文 " * 3
    panel.rows[Step.LEAK_TEST].summary = "ok"
    for bar, summary in ((10, 20), (24, 60)):
        lines = [panel._line(row, bar, summary) for row in panel.rows.values()]
        assert {line.cell_len for line in lines} == {_FIXED_CELLS + bar + summary}
        assert lines[0].plain.endswith("…") and lines[1].plain.rstrip().endswith(" ok")
        assert lines[0].plain.startswith("· Connect       ━") and "   0%" in lines[0].plain


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--sim", "--poses-per-object", "1"], "poses per object must be 2..1000"),
        (["--sim", "--total-minutes", "-1"], "total minutes must be positive"),
        (["--sim", "--sensor", "missing.yaml"], "cannot read sensor spec missing.yaml: No such file or directory"),
        (["--sim", "--sensor", "."], "cannot read sensor spec .: Is a directory"),
        (["--sim-fault", "camera-stall@3"], "--sensor, --sim-fault and --sim-speed need --sim"),
        ([], "the real bench needs its settings (--bench BENCH.yaml), or use --sim"),  # was: the simulated one only
        (["--sim", "--bench", "b.yaml"], "--bench describes real hardware; drop it or --sim"),
        (["--sim", "--objects", " , "], "no objects to press"),
        (["--sim", "--sim-speed", "0"], "simulation speed 0.0 must be within 0.1..100"),
        (["--sim", "--registry", "reg.yaml"], "sensor registry reg.yaml is not a directory"),
        (["--sim"], "needs an interactive terminal"),  # pytest's stdin is not a terminal
    ],
)
def test_tui_command_rejects_bad_input_in_one_line(tmp_path, monkeypatch, capsys, args, fragment):
    from calibrate.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "reg.yaml").write_text("a file where the registry should be\n")
    assert main(["tui", *args]) == 2
    err = capsys.readouterr().err
    assert fragment in err and err.count("\n") == 1


def test_a_crashed_app_is_a_non_zero_exit(tmp_path, monkeypatch):
    """Was: ``bubble tui`` returned 0 after the app had crashed (a MarkupError traceback, then exit 0)."""
    import sys

    from calibrate.cli import main
    from calibrate.tui.app import BenchApp

    def crash(app, *args, **kwargs):
        app._return_code = 1  # what textual sets when an exception ends the app

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys.stdin, "isatty", lambda: True, raising=False)
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True, raising=False)
    monkeypatch.setattr(BenchApp, "run", crash)
    assert main(["tui", "--sim", "--out", str(tmp_path / "run")]) == 1
