"""TUI responsiveness while the real commissioning flow runs -> docs/bench_tui.md.

Runs ``bubble tui``'s app headless (``App.run_test``) and starts the real commissioning flow, in the
child process ``bubble tui`` runs it in, on the simulated bench (real-time clock: the camera twin streams at its 45 fps; fine-tuning uses every
CPU core torch is given). Every ``--interval`` s it injects a key press that switches tabs
(``1`` <-> ``2``: the commission tab and the large sensor view) and measures the latency from the
key event being posted to the first frame the app composes with the new tab active (the
compositor's output is also rendered to terminal escape codes, as a real terminal would get it).
Latencies are grouped by the step that was running; the target is < 100 ms.

    .venv/bin/python benchmarks/bench_tui.py [--finetune-minutes 1] [--out docs/bench_tui.md]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from textual import events  # noqa: E402

from benchmarks.arguments import markdown_out, model_dir, poses_per_object, positive_float, run_main  # noqa: E402
from benchmarks.machine import machine_info, provenance  # noqa: E402
from calibrate.commission_events import STEPS  # noqa: E402
from calibrate.commission_config import validate_config  # noqa: E402
from calibrate.commissioning import CommissionConfig  # noqa: E402
from calibrate.tui.app import BenchApp  # noqa: E402
from calibrate.tui.frame_gap_gc import CHECK_INTERVAL_S, OLDER_EVERY, YOUNG_OBJECTS  # noqa: E402
from calibrate.tui.flow_runner import BENCH_NICE, COMPUTE_NICE  # noqa: E402
from collect.atomic_files import write_text  # noqa: E402
from collect.errors import InputError  # noqa: E402

TARGET_MS = 100.0
SIZE = (120, 36)


def runqueue_wait_s() -> float:
    """Time the calling thread has spent runnable but waiting for a CPU, s (Linux schedstat; nan elsewhere)."""
    try:
        fields = Path(f"/proc/self/task/{threading.get_native_id()}/schedstat").read_text().split()
        return int(fields[1]) * 1e-9
    except (OSError, IndexError, ValueError):
        return float("nan")


class FrameClock:
    """Wraps ``app._display`` to time-stamp composed frames and render them to escape codes."""

    def __init__(self, app: BenchApp):
        self.app = app
        self.waiting_for: str | None = None  # tab id the pending key press should show
        self.shown_at: float | None = None
        self.shown_cpu: float | None = None  # UI thread CPU time (s) when the frame was composed
        self.shown_wait: float | None = None  # UI thread run-queue wait (s) when the frame was composed
        self.frames = 0
        self.gc_s = 0.0  # time spent in garbage collections in this process so far, s
        self.gc_pauses: dict[int, list[float]] = defaultdict(list)  # generation -> pause lengths, ms
        self._gc_started = 0.0
        gc.callbacks.append(self._on_gc)
        original = app._display

        def display(screen, renderable):
            if renderable is not None and hasattr(renderable, "render_segments"):
                renderable.render_segments(app.console)  # the terminal output a real driver writes
            self.frames += 1
            if self.waiting_for is not None and self.shown_at is None and app.tabs.active == self.waiting_for:
                self.shown_at = time.perf_counter()
                self.shown_cpu = time.thread_time()
                self.shown_wait = runqueue_wait_s()
            return original(screen, renderable)

        app._display = display

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_started = time.perf_counter()
        else:
            pause = time.perf_counter() - self._gc_started
            self.gc_s += pause
            self.gc_pauses[info["generation"]].append(pause * 1e3)

    def close(self) -> None:
        gc.callbacks.remove(self._on_gc)


class Press(NamedTuple):
    """One measured key press: when, during which step, and where its latency went (ms)."""

    at_s: float  # since the start of the run
    step: str
    key: str
    ms: float  # key posted -> first frame showing the new tab
    cpu_ms: float  # UI thread CPU time in that span
    wait_ms: float  # UI thread run-queue wait in that span
    gc_ms: float  # garbage collection in the UI process in that span


def running_step(app: BenchApp) -> str:
    """Name of the step now running, or the app state when none is."""
    for step in STEPS:
        if app.steps.row(step).status == "running":
            return step.value
    return "running" if app.running else "idle"


async def measure(config: CommissionConfig, interval: float, max_seconds: float, bench_nice: int,
                  compute_nice: int, tune_gc: bool = True) -> dict:
    app = BenchApp(config, bench_nice=bench_nice, compute_nice=compute_nice, tune_gc=tune_gc, warm_up_tabs=True)
    presses: list[Press] = []
    missed: dict[str, int] = defaultdict(int)  # step -> presses with no frame in 2 s
    async with app.run_test(size=SIZE) as pilot:
        clock = FrameClock(app)
        # The operator's first key comes after the start-up (tab warm-up, then the collector's first
        # full collection): on a slow host that takes over 0.5 s, and a press inside it times the start-up.
        await pilot.pause(0.5)
        while not app.started_up:
            await pilot.pause(0.05)
        t_start = time.perf_counter()
        app.start_commissioning()
        target = "tab-sensor"
        while time.perf_counter() - t_start < max_seconds:
            phase = running_step(app)
            key = "2" if target == "tab-sensor" else "1"
            clock.waiting_for, clock.shown_at = target, None
            t0, c0, w0, g0 = time.perf_counter(), time.thread_time(), runqueue_wait_s(), clock.gc_s
            app._driver.send_message(events.Key(key, key))  # the path a terminal key takes
            while clock.shown_at is None and time.perf_counter() - t0 < 2.0:
                await asyncio.sleep(0.001)
            if clock.shown_at is None:
                missed[phase] += 1
            else:
                presses.append(Press(t0 - t_start, phase, key, (clock.shown_at - t0) * 1e3,
                                     (clock.shown_cpu - c0) * 1e3, (clock.shown_wait - w0) * 1e3,
                                     (clock.gc_s - g0) * 1e3))
            clock.waiting_for = None
            target = "tab-commission" if target == "tab-sensor" else "tab-sensor"
            if not app.running and (app.result is not None or app.error is not None):
                break
            await asyncio.sleep(interval)
        wall = time.perf_counter() - t_start
        if app.running:
            app.action_stop()
            deadline = time.perf_counter() + 60
            while app.running and time.perf_counter() < deadline:
                await asyncio.sleep(0.05)
        await pilot.pause(0.2)
        outcome = describe_outcome(app)
        received = app.events_received
        clock.close()
    return {"presses": presses, "missed": missed, "wall_s": wall, "outcome": outcome, "events": received,
            "frames": clock.frames, "gc_pauses": dict(clock.gc_pauses), "error": app.error}


def describe_outcome(app: BenchApp) -> str:
    if app.error is not None:
        return f"flow raised {type(app.error).__name__}: {app.error}"
    if app.result is None:
        return "stopped by the benchmark before the flow ended"
    r = app.result
    if r.stopped:
        return "stopped"
    if r.fault:
        return f"fault {r.fault}"
    return "accepted" if r.accepted else f"rejected ({r.reason})"


def write_markdown(path: Path, stats: dict, args, info: dict) -> None:
    """Write the page; ``info``: ``machine_info()`` at the run's start."""
    rows = []
    by_step: dict[str, list[Press]] = defaultdict(list)
    for press in stats["presses"]:
        by_step[press.step].append(press)
    order = ["idle", *[s.value for s in STEPS], "running"]
    for phase in sorted(by_step.keys() | stats["missed"].keys(), key=order.index):
        lat, cpu, wait, gcms = (np.array([getattr(p, f) for p in by_step[phase]])
                                for f in ("ms", "cpu_ms", "wait_ms", "gc_ms"))
        miss = stats["missed"].get(phase, 0)
        if len(lat):
            rows.append(f"| {phase} | {len(lat)} | {np.median(lat):.1f} | {np.percentile(lat, 95):.1f} | "
                        f"{lat.max():.1f} | {np.median(cpu):.1f} | {np.percentile(wait, 95):.1f} | {gcms.max():.1f} | {miss} | "
                        f"{'yes' if lat.max() < TARGET_MS and not miss else 'no'} |")
        else:
            rows.append(f"| {phase} | 0 | - | - | - | - | - | - | {miss} | no |")
    all_lat = np.array([p.ms for p in stats["presses"]])
    lines = [
        "# TUI responsiveness",
        "",
        "Key press to screen update while the real commissioning flow runs on the simulated bench",
        "(camera twin at 45 fps in real time, then fine-tuning on the CPU) in the child process `bubble tui`",
        "runs it in (`calibrate/tui/flow_runner.py`), measured headless with",
        "`App.run_test`: a tab switch key (`1`/`2`, alternating between the steps and the large sensor",
        "view) is posted every "
        f"{args.interval:.2f} s, the first in the instant the run starts (once the app's start-up is over),",
        "and timed until the first composed frame shows the new tab (the frame is",
        "also rendered to terminal escape codes). Target: < 100 ms. \"UI CPU\" is the CPU time the UI thread",
        "spent between the key and the frame: the latency a quiet machine would show, without waiting",
        "for the CPU. \"CPU wait\" is the time the UI thread was ready to run but had no core",
        "(`/proc/self/task/TID/schedstat`); \"GC\" the time the UI process spent in Python's garbage collector",
        "between the key and the frame. Written by `benchmarks/bench_tui.py`.",
        "",
        "```",
        f".venv/bin/python benchmarks/bench_tui.py --finetune-minutes {args.finetune_minutes} "
        f"--poses-per-object {args.poses_per_object} --interval {args.interval} --bench-nice {args.bench_nice} --compute-nice {args.compute_nice}"
        + (" --python-gc" if args.python_gc else ""),
        "```",
        "",
        ("Python's default garbage collector settings (`--python-gc`)." if args.python_gc else
         f"Garbage collector as `bubble tui` runs it (`calibrate.tui.frame_gap_gc`): frozen after the first frame, "
         f"then collected between frames by a {1 / CHECK_INTERVAL_S:.0f} Hz timer once {YOUNG_OBJECTS} objects are "
         f"new (every {OLDER_EVERY}th collection also the middle generation, every {OLDER_EVERY ** 2}th the whole heap)."),
        "",
        "| step running | presses | median ms | p95 ms | max ms | UI CPU median ms | CPU wait p95 ms | GC max ms | no update in 2 s | max < 100 ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"All presses: {len(all_lat)}, median {np.median(all_lat):.1f} ms, p95 {np.percentile(all_lat, 95):.1f} ms, "
        f"max {all_lat.max():.1f} ms; no update in 2 s: {sum(stats['missed'].values())}." if len(all_lat)
        else "No presses measured.",
        "",
        f"Run: {stats['wall_s']:.0f} s, {stats['events']} flow events received, {stats['frames']} frames composed; "
        f"flow outcome: {stats['outcome']}.",
        "",
        "The slowest presses:",
        "",
        "| at s | step | key | ms | UI CPU ms | CPU wait ms | GC ms |",
        "|---|---|---|---|---|---|---|",
        *(f"| {p.at_s:.1f} | {p.step} | {p.key} | {p.ms:.1f} | {p.cpu_ms:.1f} | {p.wait_ms:.1f} | {p.gc_ms:.1f} |"
          for p in sorted(stats["presses"], key=lambda p: -p.ms)[:5]),
        "",
        "Garbage collections in the UI process during the run: " + ("; ".join(
            f"generation {gen}: {len(p)}, median {np.median(p):.1f} ms, max {max(p):.1f} ms"
            for gen, p in sorted(stats["gc_pauses"].items())) or "none") + ".",
        "",
        provenance(info) + " This benchmark's own work: the flow's collection, then fine-tuning on both cores.",
        "",
        *([f"Fine-tuned from `{args.base_model}` (given with `--base-model`), not the packaged base model.", ""]
          if args.base_model else []),
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, "\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--finetune-minutes", type=positive_float, default=1.0)
    parser.add_argument("--poses-per-object", type=poses_per_object, default=2)
    parser.add_argument("--interval", type=positive_float, default=0.3, help="s between key presses")
    parser.add_argument("--max-seconds", type=positive_float, default=600.0)
    parser.add_argument("--bench-nice", type=int, default=BENCH_NICE,
                        help="nice increment of the flow in the bench steps")
    parser.add_argument("--compute-nice", type=int, default=COMPUTE_NICE,
                        help="nice increment of the flow in the compute steps")
    parser.add_argument("--python-gc", action="store_true",
                        help="keep Python's default garbage collector settings (bubble tui tunes them)")
    parser.add_argument("--base-model", type=model_dir, help="model to fine-tune from (default: the packaged base model)")
    parser.add_argument("--out", type=markdown_out, default=Path(__file__).resolve().parents[1] / "docs" / "bench_tui.md")
    args = parser.parse_args(argv)
    info = machine_info()
    with tempfile.TemporaryDirectory() as tmp:
        config = CommissionConfig(run_dir=Path(tmp) / "run", simulated=True, registry_dir=Path(tmp) / "registry",
                                  objects=("mug", "box"), poses_per_object=args.poses_per_object,
                                  finetune_minutes=args.finetune_minutes, leak_hold_s=3.0,
                                  base_model=None if args.base_model is None else Path(args.base_model))
        validate_config(config)  # InputError: exit 2 before the app starts (was: run, then a page of the error)
        stats = asyncio.run(measure(config, args.interval, args.max_seconds, args.bench_nice, args.compute_nice,
                                     not args.python_gc))
    if isinstance(stats["error"], InputError):  # bad input the flow found: its line, exit 2, no page
        raise stats["error"]
    if stats["error"] is not None:  # the flow failed: no page of its timings (was: written, exit 0)
        print(f"bench_tui: {stats['outcome']}; {args.out} left as it was", file=sys.stderr)
        return 1
    write_markdown(args.out, stats, args, info)
    print(args.out.read_text())
    return 0


if __name__ == "__main__":
    run_main(main, "bench_tui")
