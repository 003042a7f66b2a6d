"""benchmarks/run_all.py: every benchmark script is run, and targets are read from the scripts' tables."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

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


# ---- the scripts' command lines and provenance (benchmarks/arguments.py, benchmarks/machine.py) -------------------

def _refused(main, argv, capsys) -> str:
    """The one error line of ``main(argv)``, which must exit 2 before any work."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def test_list_and_number_arguments_are_checked_by_the_parser():
    import argparse

    from benchmarks.arguments import int_list, name_list, positive_float, positive_int

    assert int_list("101, 202,") == [101, 202] and name_list(("frames", "poses"))("frames,poses") == ["frames", "poses"]
    assert positive_int("3") == 3 and positive_float("0.5") == 0.5
    for parse, text in ((int_list, "a"), (int_list, "1,1"), (int_list, ","), (name_list(("frames", "poses")), "both"),
                        (positive_int, "0"), (positive_int, "x"), (positive_float, "0"), (positive_float, "nan")):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


def test_input_error_exits_2_with_one_line(capsys):
    from benchmarks.arguments import run_main
    from collect.errors import InputError

    def main() -> int:
        raise InputError("no such object 'cup'")

    with pytest.raises(SystemExit) as exit_info:
        run_main(main, "bench_x")
    assert exit_info.value.code == 2 and capsys.readouterr().err == "bench_x: no such object 'cup'\n"


def test_a_failed_bubble_command_exits_with_its_line(capsys):
    """Was: a traceback (``RuntimeError`` or ``CalledProcessError``), exit 1, whatever the command's exit."""
    from benchmarks.arguments import run_main
    from collect.errors import BubbleCommandError

    for returncode, code in ((2, 2), (3, 1), (None, 1)):
        def main() -> int:
            raise BubbleCommandError("bubble collect --sim failed: bubble: error: no such object", returncode)

        with pytest.raises(SystemExit) as exit_info:
            run_main(main, "bench_x")
        assert exit_info.value.code == code
        assert capsys.readouterr().err == "bench_x: bubble collect --sim failed: bubble: error: no such object\n"


def test_run_all_refuses_a_corrupt_runs_file_and_keeps_it(tmp_path, monkeypatch, capsys):
    """Was: a JSONDecodeError traceback, from every later run and ``--assemble-only`` alike."""
    runs = tmp_path / "benchmarks.json"
    monkeypatch.setattr(run_all, "RUNS_JSON", runs)
    monkeypatch.setattr(run_all, "PAGE", tmp_path / "benchmarks.md")
    for text, says in (('{"simulator": {"exit": 0,', "is unreadable (Expecting"),
                       ("[1, 2]", "does not hold a JSON object; restore it (git checkout) or delete it")):
        runs.write_text(text)
        with pytest.raises(SystemExit) as exit_info:
            from benchmarks.arguments import run_main

            run_main(lambda: run_all.main(["--assemble-only"]), "run_all")
        line = capsys.readouterr().err
        assert exit_info.value.code == 2 and says in line and line.count("\n") == 1, line
        assert runs.read_text() == text and not (tmp_path / "benchmarks.md").exists()


def test_a_recorder_page_shorter_than_the_target_is_not_measured(tmp_path, monkeypatch):
    """Was: the page of ``bench_recorder.py --minutes 0.05`` graded the 10-minute target as met."""
    monkeypatch.setattr(run_all, "DOCS", tmp_path)
    monkeypatch.setattr(run_all, "TARGETS", (_target("recorder: zero dropped frames"),))
    page = ("## Long recording: writer alone at 45 fps for {minutes} min\n\n| metric | value |\n|---|---|\n"
            "| frames produced / in file | 27000 / 27000 |\n| sequence gaps / non-increasing timestamps | 0 / 0 |\n"
            "| frames a camera's queue would have lost / latest hand-over | 0 / 3.1 ms |\n")
    (tmp_path / "bench_recorder.md").write_text(page.format(minutes=10))
    assert "| met |" in run_all.target_rows({})[2]
    (tmp_path / "bench_recorder.md").write_text(page.format(minutes=0.05))
    row = run_all.target_rows({})[2]
    assert "**not measured**" in row and "the page's recording lasted 0.05 min, not 10" in row


def test_partial_benchmark_runs_write_their_pages_in_runs():
    """Was: ``bench_recorder.py --minutes 1 --no-collect`` (its docstring's quick look) and ``bench_pose.py
    --speed-only`` replaced the committed pages, the latter without its accuracy section."""
    from benchmarks import bench_pose, bench_recorder

    for argv in (["--minutes", "1"], ["--no-collect"]):
        assert bench_recorder.parse_args(argv).out == ROOT / "runs" / "bench_recorder_quick.md"
    assert bench_recorder.parse_args([]).out == ROOT / "docs" / "bench_recorder.md"
    assert bench_pose.parse_args(["--speed-only"]).out == ROOT / "runs" / "bench_pose_speed.md"
    assert bench_pose.parse_args([]).out == ROOT / "docs" / "bench_pose.md"


def test_a_failed_collection_of_the_recorder_benchmark_is_shown(monkeypatch, tmp_path):
    """Was: an ``IndexError`` when ``bubble collect`` died without a line (killed), after the long recording."""
    import subprocess

    from benchmarks import bench_recorder

    monkeypatch.setattr(subprocess, "run", lambda *a, **k: subprocess.CompletedProcess(a, -9, "", ""))
    assert bench_recorder.bench_collection(tmp_path) == {"error": "exit -9: (no output)"}


def test_bench_pose_records_whole_sessions_and_reuses_only_their_models(tmp_path, monkeypatch):
    """Was: ``bubble collect`` wrote ``session.h5`` in place: the part a fault had kept was taken by the
    next run as a whole session, and a model was reused whatever it was fine-tuned on."""
    from benchmarks import bench_pose
    from collect.errors import InputError
    from collect.errors import BubbleCommandError

    def collect_fails(*args):
        if args[0] == "collect":
            Path(args[args.index("--out") + 1]).write_bytes(b"the frames of a stopped run")
            raise BubbleCommandError("bubble collect failed with exit 3 (its error is above)", 3)

    monkeypatch.setattr(bench_pose, "_bubble", collect_fails)
    with pytest.raises(BubbleCommandError):
        bench_pose.simulated_inputs(tmp_path, 0, 3.0)
    assert not (tmp_path / "session.h5").exists()
    (tmp_path / "session.h5").write_bytes(b"another recording")
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "metadata.json").write_text("{}")

    class Metadata:
        training = {"budget": {"minutes": 3.0}, "split": {"kind": "object", "object": "mug"},
                    "sources": [{"sha256": "0" * 64}]}

    monkeypatch.setattr(bench_pose, "load_metadata", lambda model: Metadata)
    with pytest.raises(InputError, match="was fine-tuned on other data than .*session.h5: use another --work"):
        bench_pose.simulated_inputs(tmp_path, 0, 3.0)


def test_commission_refuses_a_work_folder_holding_earlier_runs(tmp_path, capsys):
    """Was: a run folder there was resumed (the recorded verdict, no timings), or an unseen-mesh session crashed it."""
    from benchmarks import bench_commission

    (tmp_path / "run_101").mkdir()
    (tmp_path / "unseen_909_leak_1.h5").touch()
    line = _refused(bench_commission.main, ["--seeds", "101,202", "--defects", "leak", "--work", str(tmp_path)], capsys)
    assert str(tmp_path / "run_101") in line and "unseen_909_leak_1.h5" in line and "new --work" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run_101", "unseen_909_leak_1.h5"]  # nothing written


def test_run_all_refuses_only_with_assemble_only(capsys):
    line = _refused(run_all.main, ["--only", "simulator", "--assemble-only"], capsys)
    assert "--assemble-only" in line and "--only" in line


@pytest.mark.parametrize("only", ["", " , ", "simulator,teapot", "simulator,simulator"])
def test_run_all_refuses_an_empty_unknown_or_repeated_only(only, capsys, monkeypatch):
    """Was: ``--only ""`` ran every benchmark (an hour), and a name twice ran it twice."""
    monkeypatch.setattr(run_all, "run", lambda *a: pytest.fail("a benchmark ran"))
    line = _refused(run_all.main, ["--only", only], capsys)
    assert "--only" in line and "expected one or more of simulator," in line


def test_a_quick_accuracy_run_writes_its_page_in_its_work_folder():
    """Was: ``run_all.py --only accuracy -- --quick`` overwrote the committed docs/bench_accuracy.md."""
    from benchmarks import bench_accuracy

    quick = bench_accuracy.parse_args(["--quick"])
    assert quick.out == quick.work / "bench_accuracy.md" and quick.work.is_relative_to(ROOT / "runs")
    assert bench_accuracy.parse_args([]).out == ROOT / "docs" / "bench_accuracy.md"


def test_machine_line_and_provisional_runs():
    from benchmarks import machine

    info = {"cpu": "AMD EPYC 7B13", "cores": 2, "load": 0.3, "python": "3.11.7", "date": "2026-11-22 03:40"}
    assert machine.machine_line(info) == ("Machine: AMD EPYC 7B13, 2 cores, load average 0.3 at the start, "
                                          "Python 3.11.7; 2026-11-22 03:40.")
    quiet, busy = {**info, "others_cores": 0.05}, {**info, "others_cores": 0.8}
    assert not machine.provisional(quiet) and machine.provisional_note(quiet) == (
        " Other processes used 0.05 cores on average during the run.")
    assert machine.provisional(busy) and "**Provisional**" in machine.provisional_note(busy)
    assert machine.provisional_note(info) == ""  # a record from before the CPU was counted


def test_the_cpu_of_other_processes_is_counted_and_not_this_ones(monkeypatch):
    """Was: the load average at the start, which lags a minute (a benchmark right after another read as
    busy) and counts the benchmark's own work."""
    import time

    from benchmarks import machine

    busy_before, own_before = machine.cpu_seconds()
    deadline = time.process_time() + 0.5
    while time.process_time() < deadline:  # this process's own work shows in both counters
        pass
    busy_after, own_after = machine.cpu_seconds()
    assert own_after - own_before >= 0.45 and busy_after - busy_before >= 0.45
    # 1000 s of a run (a stall of the test of up to seconds rounds away): the machine busy for 2000 CPU
    # seconds, 700 of them this benchmark's
    info = {"cpu": "x", "cores": 2, "load": 0.1, "python": "3.11", "date": "2026-11-26 12:00",
            "started": {"busy_s": 100.0, "own_s": 5.0, "t": time.monotonic() - 1000.0}}
    monkeypatch.setattr(machine, "cpu_seconds", lambda: (2100.0, 705.0))
    done = machine.finish(info)
    assert done["others_cores"] == 1.3 and "started" not in done and "load_end" in done
    assert machine.provisional(done)
    monkeypatch.setattr(machine, "cpu_seconds", lambda: (float("nan"), 705.0))  # no /proc/stat: not "quiet"
    unmeasured = machine.finish(info)
    assert unmeasured["others_cores"] is None and not machine.provisional(unmeasured)
    assert "not measured" in machine.provisional_note(unmeasured)


@pytest.mark.parametrize("script", ["bench_accuracy", "bench_pose", "bench_recorder", "bench_simulator", "bench_tui",
                                    "bench_twins"])
def test_a_benchmark_page_is_a_markdown_file_in_an_existing_folder(script, tmp_path, capsys):
    """Was: ``--out`` took any path: a YAML or HDF5 file was overwritten with exit 0, and a folder or a path
    under a file gave a traceback after the whole run."""
    import importlib

    main = importlib.import_module(f"benchmarks.{script}").main
    spec = tmp_path / "sensor.yaml"
    spec.write_text("seed: 1\n")
    (tmp_path / "afile").write_text("")
    for out, says in ((tmp_path, "is a directory, not a markdown file"),
                      (spec, "is not a markdown file (.md): refusing to replace it with a benchmark page"),
                      (tmp_path / "afile" / "page.md", "the folder of"), (tmp_path / "missing" / "page.md", "the folder of")):
        line = _refused(main, ["--out", str(out)], capsys)
        assert says in line and str(out) in line
    assert spec.read_text() == "seed: 1\n" and sorted(p.name for p in tmp_path.iterdir()) == ["afile", "sensor.yaml"]
    from benchmarks.arguments import markdown_out

    assert markdown_out(str(tmp_path / "page.md")) == tmp_path / "page.md"  # a new page


@pytest.mark.parametrize("script, argv, says", [
    # was: a traceback once the session was recorded, or from bubble collect (exit 1)
    ("bench_finetune", ["--objects", "cup"], "unknown object 'cup'"),
    ("bench_finetune", ["--sim-speed", "1000"], "simulation speed 1000.0 must be within"),
    ("bench_finetune", ["--sensor-seed", "-1"], "expected a sensor seed within 0..4294967295, got '-1'"),
    ("bench_finetune", ["--minutes", "0"], "expected a number above 0, got '0'"),  # was: ran
    ("bench_finetune", ["--objects", "mug,mug"], "object names must be unique, got mug twice"),
    # was: a RuntimeError traceback from bubble collect, once a sensor was drawn
    ("bench_finetune", ["--poses-per-object", "1001"], "expected poses per object within 1..1000, got '1001'"),
    ("bench_accuracy", ["--calib-poses", "1001"], "expected poses per object within 1..1000"),
    ("bench_pose", ["--seeds", "-1"], "expected a sensor seed within 0..4294967295, got '-1'"),
    ("bench_pose", ["--train-minutes", "0"], "expected a number above 0"),
    ("bench_accuracy", ["--objects", "cup"], "unknown object 'cup'"),  # was: exit 1 from bubble collect
    ("bench_accuracy", ["--objects", "box", "--holdouts", "mug"], "--holdouts: mug is not among --objects box"),
    ("bench_accuracy", ["--cross-seeds", "21,-2"], "expected a sensor seed within"),
    ("bench_commission", ["--seeds", "-1"], "expected a sensor seed within"),
    ("bench_tui", ["--interval", "0"], "expected a number above 0"),
    ("bench_tui", ["--max-seconds", "nan"], "expected a number above 0"),
])
def test_benchmark_arguments_are_checked_before_any_work(script, argv, says, capsys):
    import importlib

    line = _refused(importlib.import_module(f"benchmarks.{script}").main, argv, capsys)
    assert says in line, line


@pytest.mark.parametrize("script", ["bench_finetune", "bench_pose", "bench_accuracy", "bench_commission"])
def test_a_benchmarks_work_folder_is_not_a_file(script, tmp_path, capsys):
    """Was: a traceback (FileExistsError or NotADirectoryError) once the benchmark began."""
    import importlib

    afile = tmp_path / "afile"
    afile.write_text("x")
    main = importlib.import_module(f"benchmarks.{script}").main
    assert f"{afile} is a file, not a folder" in _refused(main, ["--work", str(afile)], capsys)
    assert "is a file, not a directory" in _refused(main, ["--work", str(afile / "w")], capsys)
    assert afile.read_text() == "x"


def test_bench_tui_refuses_what_the_flow_would_refuse_and_keeps_its_page(tmp_path, capsys):
    """Was: ``--poses-per-object 1`` ran the app, whose flow refused it, and the page of that run was
    written over docs/bench_tui.md with exit 0."""
    from benchmarks import bench_tui

    page = tmp_path / "bench_tui.md"
    page.write_text("earlier page")
    with pytest.raises(SystemExit) as exit_info:
        from benchmarks.arguments import run_main

        run_main(lambda: bench_tui.main(["--poses-per-object", "1", "--out", str(page)]), "bench_tui")
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == ("bench_tui: poses per object must be 2..1000 (one or more is held out), "
                                       "got 1\n")
    assert page.read_text() == "earlier page"


def test_accuracy_refuses_cross_seeds_the_base_model_trained_on(capsys):
    """The check compares the base model's serials with ``simulated_serial`` (was: a copy of its format)."""
    from benchmarks import bench_accuracy

    serial = sorted(bench_accuracy.base_model_serials("base"))[0]
    seed = int(serial.removeprefix("SB-SIM-"))
    line = _refused(bench_accuracy.parse_args, ["--cross-seeds", str(seed)], capsys)
    assert f"the base model trained on sensor seeds [{seed}]: pick other --cross-seeds" in line
