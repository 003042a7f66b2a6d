"""Run every benchmark script and assemble docs/benchmarks.md (all tables, targets met or not).

    .venv/bin/python benchmarks/run_all.py                        # everything (~1 h 45 min on a quiet 2-core CPU)
    .venv/bin/python benchmarks/run_all.py --only simulator,pose  # a subset, then reassemble the page
    .venv/bin/python benchmarks/run_all.py --assemble-only        # rebuild the page from existing results
    .venv/bin/python benchmarks/run_all.py --only accuracy -- --quick   # arguments after -- go to the script(s)

``bench_accuracy.py --quick`` checks that script end to end with tiny budgets: it writes its page into its
work folder (``runs/bench_accuracy_quick/``), never over ``docs/bench_accuracy.md``, so the accuracy
target then shows "stale" (its last run did not rewrite the page) until a full run.

Each script writes its own markdown in docs/ (``docs/bench_*.md``); this runs them one after the
other (never in parallel: they time the CPU), logs each to ``runs/bench_logs/NAME.log``, keeps the
command, exit code, wall time and date of every run in ``docs/benchmarks.json``, and writes
``docs/benchmarks.md``: the targets of the project with the measured value, met or the gap, then
every benchmark's page inlined (headings shifted down one level) with a link to it.

Targets are read from the scripts' markdown tables (row label, column header) and from
``docs/bench_accuracy.json``: a script whose table changes shape shows "not measured" here, and one
whose last run failed or did not rewrite its page shows "stale", never the earlier run's number. A
target that the starting point (the base model before fine-tuning) meets too is marked "not
discriminating".
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.arguments import name_list, run_main  # noqa: E402
from benchmarks.machine import finish, machine_info  # noqa: E402
from collect.atomic_files import write_text  # noqa: E402
from collect.json_files import read_json_object, write_json  # noqa: E402
from hw_mocks.pressure_firmware import RATE_HZ as PRESSURE_HZ  # noqa: E402

DOCS = ROOT / "docs"
LOGS = ROOT / "runs" / "bench_logs"
RUNS_JSON = DOCS / "benchmarks.json"
PAGE = DOCS / "benchmarks.md"
#: Length (min) of the long recording that the zero-dropped-frames target asks for (bench_recorder.py's
#: default; a shorter one is not measured).
RECORDER_TARGET_MINUTES = 10.0


@dataclass(frozen=True)
class Benchmark:
    name: str
    script: str  # in benchmarks/
    args: tuple[str, ...]
    doc: str  # the markdown it writes, in docs/
    about: str

    def command(self, extra: tuple[str, ...] = ()) -> list[str]:
        return [sys.executable, str(ROOT / "benchmarks" / self.script), *self.args, *extra]

    def shown(self, extra: tuple[str, ...] = ()) -> str:
        return " ".join(["python", f"benchmarks/{self.script}", *self.args, *extra])


#: Every benchmark, in the order they run (shortest first) and appear on the page.
BENCHMARKS = (
    Benchmark("simulator", "bench_simulator.py", (), "bench_simulator.md", "simulated bubble: frame time, physics vs the real bubble"),
    Benchmark("twins", "bench_twins.py", (), "bench_twins.md", "hardware twins streaming together: rates and CPU"),
    Benchmark("inference", "bench_inference.py", (), "bench_trainer.md", "batch-1 inference latency per architecture, torch and ONNX Runtime"),
    Benchmark("finetune", "bench_finetune.py", ("--work", "runs/bench_finetune"), "bench_trainer.md",
              "fine-tuning a new sensor from the base model: a1 against minutes"),
    Benchmark("pose", "bench_pose.py", (), "bench_pose.md", "pose estimation speed and the pose check's errors (paper Sec. V)"),
    Benchmark("recorder", "bench_recorder.py", (), "bench_recorder.md", "HDF5 recorder throughput, CPU share, dropped frames; collection time"),
    Benchmark("commission", "bench_commission.py", (), "bench_commission.md", "`bubble commission --sim` end to end over several new sensors"),
    Benchmark("tui", "bench_tui.py", (), "bench_tui.md", "TUI key-to-screen latency while commissioning runs"),
    Benchmark("accuracy", "bench_accuracy.py", (), "bench_accuracy.md", "the paper's Tables II-IV and ToF vs model against the true depth"),
)
BY_NAME = {b.name: b for b in BENCHMARKS}
#: Shown first on the page (the paper's tables); the others follow in run order.
PAGE_FIRST = ("accuracy",)


# ---- reading the scripts' markdown ----------------------------------------------------------------

def tables(text: str) -> list[tuple[list[str], list[list[str]]]]:
    """Markdown tables of ``text`` as (header cells, body rows of cells)."""
    found, lines = [], text.splitlines()
    for i in range(len(lines) - 1):
        if lines[i].startswith("|") and re.match(r"^\|(\s*:?-+:?\s*\|)+\s*$", lines[i + 1].strip()):
            split = lambda line: [c.strip() for c in line.strip().strip("|").split("|")]  # noqa: E731
            rows, j = [], i + 2
            while j < len(lines) and lines[j].startswith("|"):
                rows.append(split(lines[j]))
                j += 1
            found.append((split(lines[i]), rows))
    return found


def cell(text: str, row: str, column: str) -> str | None:
    """The cell in the first row whose first cell contains ``row``, under the header starting with ``column``."""
    for header, rows in tables(text):
        col = next((k for k, h in enumerate(header) if h.startswith(column)), None)
        if col is None:
            continue
        for cells in rows:
            if row in cells[0] and col < len(cells):
                return cells[col]
    return None


def number(text: str | None) -> float | None:
    """The first number in ``text`` (None when there is none)."""
    match = re.search(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", text or "")
    return float(match.group()) if match else None


# ---- targets --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Target:
    goal: str  # what the issue asks, in words
    benchmark: str  # BENCHMARKS name whose doc holds the number
    op: str  # ">=", "<=", "<" or "=="
    threshold: float
    unit: str
    extract: Callable[[str], tuple[float | None, str]]  # doc text -> (value, detail shown next to it)
    #: doc text -> (value, detail) of the starting point (e.g. the base model before fine-tuning), when the page
    #: has one: a target that it meets too is met without telling a good result from none
    baseline: Callable[[str], tuple[float | None, str]] | None = None

    def verdict(self, value: float) -> bool:
        return {">=": value >= self.threshold, "<=": value <= self.threshold, "<": value < self.threshold,
                "==": value == self.threshold}[self.op]


def _cell_value(row: str, column: str, scale: float = 1.0) -> Callable[[str], tuple[float | None, str]]:
    def extract(text: str) -> tuple[float | None, str]:
        raw = cell(text, row, column)
        value = number(raw)
        return (None if value is None else value * scale), f"{column.strip()} of `{row}`: {raw}" if raw else ""
    return extract


def _regex_value(pattern: str, group: int, what: str, what_group: int = 0) -> Callable[[str], tuple[float | None, str]]:
    """The number in ``group`` of the first match of ``pattern``; the detail shows ``what`` and ``what_group``."""
    def extract(text: str) -> tuple[float | None, str]:
        match = re.search(pattern, text)
        return (float(match.group(group)), f"{what}: {match.group(what_group)}") if match else (None, "")
    return extract


def _finetune_minutes(text: str) -> tuple[float | None, str]:
    match = re.search(r"Final \(all held-out frames\): a1 ([\d.]+).*?after ([\d.]+) min.*?reached at (never|[\d.]+ min)", text)
    if not match:
        return None, ""
    detail = f"final a1 {match.group(1)} after {match.group(2)} min; a1 >= 0.95 reached at {match.group(3)}"
    return (math.inf if match.group(3) == "never" else float(match.group(3).split()[0])), detail


def _pressure_rate_off(text: str) -> tuple[float | None, str]:
    """How far the pressure board's rate is from its nominal ``PRESSURE_HZ``, in % either way."""
    raw = cell(text, "pressing", "pressure Hz")
    hz = number(raw)
    return (None, "") if hz is None else (100.0 * abs(hz / PRESSURE_HZ - 1.0), f"pressure Hz of `pressing`: {raw}")


def _recorder_dropped(text: str) -> tuple[float | None, str]:
    """Frames lost by the writer alone: missing from the file, out of sequence, or handed over too late
    for the camera's queue to have kept them (the writer blocking its producer); not measured when the
    page's recording is shorter than the target's (was: a 3-second look counted as met)."""
    length = re.search(r"writer alone at \S+ fps for ([\d.]+) min", text)
    if length and float(length.group(1)) < RECORDER_TARGET_MINUTES:
        return None, f"the page's recording lasted {length.group(1)} min, not {RECORDER_TARGET_MINUTES:g}"
    produced, gaps = cell(text, "frames produced / in file", "value"), cell(text, "sequence gaps", "value")
    late = cell(text, "frames a camera's", "value")
    if not produced or not gaps or not late:
        return None, ""
    counts = [int(n) for n in re.findall(r"\d+", produced)]
    missing = counts[0] - counts[1] + sum(int(n) for n in re.findall(r"\d+", gaps)) + int(number(late))
    return float(missing), (f"frames produced / in file {produced}; gaps / non-increasing timestamps {gaps}; "
                            f"past the camera queue / latest hand-over {late}")


def _finetune_zero_shot(text: str) -> tuple[float | None, str]:
    """Minutes the starting model needs to reach a1 >= 0.95: 0 when it has it before fine-tuning."""
    match = re.search(r"Zero-shot \(([^)]*)\): a1 ([\d.]+)", text)
    if not match:
        return None, ""
    return (0.0 if float(match.group(2)) >= 0.95 else math.inf), f"{match.group(1)} before fine-tuning: a1 {match.group(2)}"


def _recorder_headroom(text: str) -> tuple[float | None, str]:
    headroom, share = cell(text, "(chosen)", "headroom"), cell(text, "process CPU share", "value")
    return number(headroom), f"chosen filter {headroom}; CPU share while recording at 45 fps: {share or 'not found'}"


def _commission_accepted_fraction(text: str) -> tuple[float | None, str]:
    match = re.search(r"\* accepted: (\d+) of (\d+)", text)
    if not match or not int(match.group(2)):
        return None, ""
    return int(match.group(1)) / int(match.group(2)), f"accepted {match.group(1)} of {match.group(2)} new sensors"


def _commission_defects_rejected(text: str) -> tuple[float | None, str]:
    match = re.search(r"defective sensors rejected by their guard: (\d+) of (\d+)", text)
    if not match or not int(match.group(2)):
        return None, ""
    return (int(match.group(1)) / int(match.group(2)),
            f"{match.group(1)} of {match.group(2)} defective sensors rejected by the check guarding their defect")


def _tui_slowest_press(text: str) -> tuple[float | None, str]:
    """The slowest press's latency; a press that never updated the screen (2 s) is infinitely slow."""
    match = re.search(r"All presses: (\d+, median [\d.]+ ms, p95 [\d.]+ ms, max ([\d.]+) ms); "
                      r"no update in 2 s: (\d+)", text)
    if not match:
        return None, ""
    return (math.inf if int(match.group(3)) else float(match.group(2))), \
        f"presses: {match.group(1)}; no update in 2 s: {match.group(3)}"


def _pose_vs_true_ratio(text: str) -> tuple[float | None, str]:
    predicted = number(cell(text, "predicted depth vs true pose", "e_x median"))
    measured = number(cell(text, "measured depth vs true pose", "e_x median"))
    if predicted is None or not measured:
        return None, ""
    return predicted / measured, f"median e_x vs the true pose: predicted depth {predicted} mm, ToF depth {measured} mm"


def _accuracy_cross_sensor_a1(model: str, what: str) -> Callable[[str], tuple[float | None, str]]:
    """The worst new sensor's a1 of ``model`` ("finetuned", "zero_shot_base") in docs/bench_accuracy.json."""
    def extract(text: str) -> tuple[float | None, str]:
        path = DOCS / "bench_accuracy.json"
        if not path.is_file():
            return None, ""
        result = json.loads(path.read_text())
        rows = result.get("cross_sensor", [])
        if not rows or result.get("settings", {}).get("quick"):  # a --quick run validates the script, measures nothing
            return None, ""
        a1 = [r[model]["a1"] for r in rows]
        return min(a1), f"{what} a1 per new sensor: " + ", ".join(f"{r['seed']}: {v:.3f}" for r, v in zip(rows, a1))
    return extract


TARGETS = (
    Target("simulator: one moving frame in contact (physics + IR + ToF + truth) <= 10 ms on one core (>= 100 fps; "
           "90th percentile)", "simulator", ">=", 100, "fps", _cell_value("moving, contact", "fps (CPU p90)")),
    Target("camera twin sustains 45 fps while pressing (within 1 %)", "twins", ">=", 0.99 * 45, "fps",
           _cell_value("pressing", "camera fps")),
    Target("arm state >= 125 Hz (within 1 %)", "twins", ">=", 0.99 * 125, "Hz", _cell_value("pressing", "arm state Hz")),
    Target(f"pressure board at ~{PRESSURE_HZ:g} Hz (within 5 %, either way)", "twins", "<=", 5, "%", _pressure_rate_off),
    Target("collection: 4 objects x 8 poses in <= 60 s of arm time", "recorder", "<=", 60, "s",
           _cell_value("arm time", "value")),
    Target(f"recorder: zero dropped frames over a {RECORDER_TARGET_MINUTES:g}-minute recording", "recorder", "==", 0,
           "frames", _recorder_dropped),
    Target("recorder headroom: frames/s written over the camera's 45 fps (> 1x)", "recorder", ">=", 1, "x",
           _recorder_headroom),
    Target("inference >= 60 fps batch 1 at 224 x 224, default model", "inference", ">=", 60, "fps",
           _cell_value("(default)", "fps")),
    Target("fine-tune from the base model to a1 >= 0.95 within 3 min", "finetune", "<=", 3, "min", _finetune_minutes,
           _finetune_zero_shot),
    Target("commissioning end to end <= 5 min wall (slowest sensor)", "commission", "<=", 300, "s",
           _regex_value(r"total wall: \S+ / \S+ / (\S+) s", 1, "min / median / max")),
    Target("commissioning fine-tune step <= 3 min (slowest sensor)", "commission", "<=", 180, "s",
           _regex_value(r"fine-tune step \(data loading, training, final validation, ONNX export\): "
                        r"[\d.]+ / [\d.]+ / ([\d.]+) s", 1, "min / median / max")),
    Target("commissioning held-out a1 >= 0.95 (worst sensor; whole images: lenient, see the next line)", "commission",
           ">=", 0.95, "", _regex_value(r"held-out a1: (\S+) / \S+ / \S+", 1, "min / median / max")),
    Target("commissioning contact RMSE <= 1.0 mm, the acceptance threshold (worst sensor; held-out contact patches)",
           "commission", "<=", 1.0, "mm", _regex_value(r"held-out contact rmse \(mm\): \S+ / \S+ / ([\d.]+)", 1,
                                                        "min / median / max")),
    Target("commissioning accepts every good (defect-free) simulated sensor", "commission", ">=", 1.0, "",
           _commission_accepted_fraction),
    Target("commissioning rejects every defective simulated sensor (leak, dead pixels, no dots) by its guard",
           "commission", ">=", 1.0, "", _commission_defects_rejected),
    Target("pose estimates >= 100 per second (1500 points, one core)", "pose", ">=", 100, "Hz",
           _cell_value("patch + warm fit", "rate")),
    Target("pose check: predicted vs measured median e_x <= 1.0 mm", "pose", "<=", 1.0, "mm",
           _cell_value("predicted vs measured depth", "e_x median")),
    Target("pose check: predicted vs measured median e_theta <= 3e-4", "pose", "<=", 3e-4, "",
           _cell_value("predicted vs measured depth", "e_theta median")),
    Target("pose check vs the true pose: predicted depth at least as good as the ToF (median e_x ratio)", "pose",
           "<=", 1.0, "x", _pose_vs_true_ratio),
    Target("TUI key to screen update < 100 ms (slowest press)", "tui", "<", 100, "ms", _tui_slowest_press),
    Target("cross-sensor: fine-tuned a1 >= 0.95 on a new sensor's test session (worst sensor)", "accuracy", ">=", 0.95, "",
           _accuracy_cross_sensor_a1("finetuned", "fine-tuned"), _accuracy_cross_sensor_a1("zero_shot_base", "base model's")),
)


def _fmt(value: float) -> str:
    return "never" if math.isinf(value) else f"{value:.4g}"


def target_rows(runs: dict) -> list[str]:
    lines = ["| target | measured | verdict | source |", "|---|---|---|---|"]
    for t in TARGETS:
        bench = BY_NAME[t.benchmark]
        why_stale = stale(runs.get(t.benchmark))
        if why_stale:
            lines.append(f"| {t.goal} | stale | **stale**: {why_stale}; the page holds an earlier run's numbers "
                         f"(log `runs/bench_logs/{bench.name}.log`) | [{bench.doc}]({bench.doc}) |")
            continue
        path = DOCS / bench.doc
        text = path.read_text() if path.is_file() else ""
        value, detail = t.extract(text) if text else (None, "")
        source = f"[{bench.doc}]({bench.doc})"
        if value is None:
            why = f" ({detail})" if detail else ""
            lines.append(f"| {t.goal} | not measured{why} | **not measured**: run `python benchmarks/run_all.py "
                         f"--only {t.benchmark}` | {source} |")
            continue
        base, base_detail = t.baseline(text) if t.baseline else (None, "")
        if t.verdict(value) and base is not None and t.verdict(base):
            verdict = f"met, but not discriminating: the starting point meets it too ({base_detail})"
        elif t.verdict(value):
            verdict = "met"
        elif math.isinf(value):
            verdict = "**not met**: never reached"
        else:
            unit = f" {t.unit}" if t.unit else ""
            verdict = (f"**not met**: {_fmt(value)}{unit} vs {t.op} {_fmt(t.threshold)}{unit} "
                       f"(gap {_fmt(abs(value - t.threshold))}{unit})")
        measured = " ".join(x for x in (_fmt(value), t.unit) if x)
        lines.append(f"| {t.goal} | {measured} ({detail}) | {verdict} | {source} |")
    return lines


# ---- running and assembling -----------------------------------------------------------------------

def load_runs() -> dict:
    """The runs recorded in ``RUNS_JSON`` (none before the first); InputError when it is not a JSON
    object (was: a traceback, and every later run and ``--assemble-only`` failed alike)."""
    return read_json_object(RUNS_JSON, "restore it (git checkout) or delete it") if RUNS_JSON.is_file() else {}


def run(bench: Benchmark, extra: tuple[str, ...] = ()) -> dict:
    """Run one script with ``extra`` arguments (output to its log); its command, exit code, wall time and date."""
    LOGS.mkdir(parents=True, exist_ok=True)
    log = LOGS / f"{bench.name}.log"
    print(f"[{time.strftime('%H:%M:%S')}] {bench.name}: {bench.shown(extra)} (log {log.relative_to(ROOT)})", flush=True)
    machine = machine_info()  # the date, load and CPU counters at the start
    page = DOCS / bench.doc
    before = page.stat().st_mtime_ns if page.is_file() else None
    t0 = time.perf_counter()
    with log.open("w") as out:
        rc = subprocess.run(bench.command(extra), cwd=ROOT, stdout=out, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    rewritten = page.is_file() and page.stat().st_mtime_ns != before
    print(f"    exit {rc} after {wall / 60:.1f} min" + ("" if rewritten else f"; {bench.doc} not rewritten"), flush=True)
    return {"command": bench.shown(extra), "exit": rc, "wall_min": round(wall / 60, 2), "machine": finish(machine),
            "page_rewritten": rewritten}


def stale(run: dict | None) -> str | None:
    """Why the numbers on a benchmark's page are not from its last run (None when they are, or it never ran here)."""
    if run is None:
        return None
    if run["exit"] != 0:
        return f"its last run ({run['machine']['date']}) failed with exit {run['exit']}"
    if not run.get("page_rewritten", True):
        return f"its last run ({run['machine']['date']}) did not rewrite the page"
    return None


def demote(markdown: str) -> list[str]:
    """Body of a benchmark page without its title, headings one level down."""
    lines = markdown.strip().splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    return [("#" + line) if re.match(r"^#{1,5} ", line) else line for line in lines]


def assemble(runs: dict) -> str:
    total = sum(r["wall_min"] for r in runs.values())
    dates = sorted(r["machine"]["date"] for r in runs.values())
    lines = [
        "# Benchmarks",
        "",
        "Every figure of the project on one page, each produced by a script in `benchmarks/` that anyone can rerun. "
        "Written by `python benchmarks/run_all.py` (all scripts one after the other, then this page; "
        "`--only NAME,...` reruns a subset, `--assemble-only` rebuilds the page). Runs, exit codes and wall "
        "times: [benchmarks.json](benchmarks.json); logs in `runs/bench_logs/`.",
        "",
        (f"The runs listed below took {total:.0f} min in total; the first started {dates[0]}, the last {dates[-1]}; "
         "each one's machine, "
         "load and the CPU other processes used are in its section and in benchmarks.json." if dates else
         "No benchmark has run through `run_all.py` yet: the sections below are the scripts' own pages."),
        "",
        "Numbers measured while other jobs share the machine are provisional; each section says when and where "
        "it was measured.",
        "",
        "## Targets",
        "",
        *target_rows(runs),
        "",
        "## Runs",
        "",
        "| benchmark | what | command | exit | wall (min) | when |",
        "|---|---|---|---|---|---|",
    ]
    for b in BENCHMARKS:
        r = runs.get(b.name)
        when = f"{r['exit']} | {r['wall_min']:.1f} | {r['machine']['date']}" if r else "- | - | not run by run_all"
        lines.append(f"| {b.name} | {b.about} | `{r['command'] if r else b.shown()}` | {when} |")
    shown = set()
    for b in sorted(BENCHMARKS, key=lambda b: b.name not in PAGE_FIRST):
        if b.doc in shown:
            continue
        shown.add(b.doc)
        about = "; ".join(x.about for x in BENCHMARKS if x.doc == b.doc)
        path = DOCS / b.doc
        lines += ["", f"## {about[0].upper() + about[1:]} ([{b.doc}]({b.doc}))", ""]
        lines += demote(path.read_text()) if path.is_file() else [f"Not measured yet: `{b.shown()}`."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog="Arguments after -- go to the script(s). `--only accuracy -- --quick` checks bench_accuracy.py with tiny "
               "budgets: its page goes to runs/bench_accuracy_quick/, docs/ keep the last full run's (the accuracy "
               "target shows stale until the next full run).")
    parser.add_argument("--only", type=name_list(tuple(BY_NAME)),  # was: '' ran every benchmark
                        help="comma-separated benchmarks to run: " + ",".join(BY_NAME))
    parser.add_argument("--assemble-only", action="store_true", help="run nothing, rebuild docs/benchmarks.md")
    argv = sys.argv[1:] if argv is None else argv
    extra = tuple(argv[argv.index("--") + 1:]) if "--" in argv else ()
    args = parser.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    if args.assemble_only and (args.only is not None or extra):
        parser.error("--assemble-only runs no benchmark: give it without --only and without arguments after --")
    names = args.only or list(BY_NAME)
    runs = load_runs()
    failed = []
    if not args.assemble_only:
        for name in names:
            runs[name] = run(BY_NAME[name], extra)
            write_json(RUNS_JSON, runs)
            if runs[name]["exit"] != 0:
                failed.append(name)
    write_text(PAGE, assemble(runs))
    print(f"wrote {PAGE.relative_to(ROOT)}" + (f"; failed: {', '.join(failed)} (see runs/bench_logs/)" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    run_main(main, "run_all")
