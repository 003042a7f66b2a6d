"""The bench TUI driving the real commissioning flow on the simulated bench (headless Pilot)."""

from __future__ import annotations

import asyncio
import json
import os
import pty
import select
import signal
import sys
import time
from pathlib import Path

import numpy as np

from calibrate.commission_events import Step
from calibrate.commissioning import CommissionConfig
from calibrate.tui.app import BenchApp
from calibrate.tui.widgets.confirm import ConfirmStart
from collect.session_reader import Session

SIZE = (120, 36)


def tiny_config(tmp_path: Path, **overrides) -> CommissionConfig:
    """One object, three poses, a one-second leak hold, a few seconds of fine-tuning, real-time clock."""
    kwargs = dict(run_dir=tmp_path / "run", simulated=True, registry_dir=tmp_path / "registry", objects=("box",),
                  poses_per_object=3, finetune_minutes=0.05, seed=3, leak_hold_s=2.0)
    kwargs.update(overrides)
    return CommissionConfig(**kwargs)


async def wait_for(predicate, pilot, timeout: float):
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    app = pilot.app
    while not predicate():
        if loop.time() > deadline:
            steps = {step.value: row.status for step, row in app.steps.rows.items()}
            raise AssertionError(f"condition not reached in {timeout} s: steps {steps}, "
                                 f"collection {app.collection.last}, result {app.result}, error {app.error!r}")
        await pilot.pause(0.05)


def test_stop_mid_collection_then_resume_to_a_verdict(tmp_path):
    """In the child process that ``bubble tui`` uses: start (after the confirmation), stop with the
    stop key while the arm works on a contact pose: the arm retracts and session.h5 is readable;
    start again: the run resumes and ends with the verdict, the acceptance table, the report and
    the registry entry; quit."""
    # no nice: on a shared test machine a niced flow would yield to every other process
    app = BenchApp(tiny_config(tmp_path), bench_nice=0, compute_nice=0)
    session_path = tmp_path / "run" / "session.h5"

    async def scenario():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("c")
            assert isinstance(app.screen, ConfirmStart)
            await pilot.press("y")
            await wait_for(lambda: app.result is not None or app.error is not None or (
                app.collection.last is not None and app.collection.last.pose_index >= 0
                and app.collection.last.phase in ("approach", "press", "hold")), pilot, timeout=90)
            assert app.result is None and app.error is None, (app.result, app.error)
            assert app.steps.row(Step.COLLECT).status == "running" and app.arm_state == "moving"
            await pilot.press("s")
            assert app.arm_state in ("stopping", "stopped")
            await wait_for(lambda: app.result is not None, pilot, timeout=30)
            assert app.result.stopped and app.arm_state == "stopped"
            assert app.steps.row(Step.COLLECT).status == "stopped"
            assert app.steps.row(Step.FINETUNE).status == "pending"
            stop = app.safe_stop  # what the flow reported from its safe stop, mid-pose
            assert stop is not None and stop.retracted
            assert stop.force_after_n < 0.5 and stop.tcp_z_after_m >= stop.tcp_z_before_m - 1e-4
            assert "arm retracted" in str(app.banner.content)
            with Session.open(session_path) as session:
                assert session.n_frames > 0
                assert np.isfinite(session.depth_m(np.arange(session.n_frames))).all()

            await pilot.press("c", "y")  # same run directory: completed steps are resumed
            await wait_for(lambda: app.running, pilot, timeout=10)
            await wait_for(lambda: not app.running and (app.result is not None or app.error is not None), pilot,
                           timeout=240)
            assert app.error is None
            result = app.result
            assert not result.stopped and result.fault is None, result
            assert app.steps.row(Step.LEAK_TEST).status == "resumed"
            assert app.steps.row(Step.VERDICT).status in ("ok", "failed")
            assert app.acceptance.checks == result.checks and len(result.checks) > 0
            assert str(result.report_path) in str(app.acceptance.report_line.content)
            assert len(app.training.loss) > 0
            assert app.registry.table.row_count == 1
            await pilot.press("q")
            await wait_for(lambda: not app.is_running, pilot, timeout=10)

    asyncio.run(scenario())
    assert Path(app.result.report_path).is_file()


def test_sigterm_stops_the_run_and_gives_the_terminal_back(tmp_path):
    """``bubble tui`` in a real terminal (a pty), a run started with c, y: SIGTERM (``kill``) acts as
    the q key: it stops the run (arm retracted, files closed) and the app leaves its alternate screen,
    exit 143 (was: the process died at once and left the terminal in the app's screen)."""
    run = tmp_path / "run"
    pid, fd = pty.fork()
    if pid == 0:  # the child: the real command line in the pty
        os.environ["TERM"] = "xterm-256color"
        os.execv(sys.executable, [sys.executable, "-m", "calibrate.cli", "tui", "--sim", "--objects", "box",
                                  "--poses-per-object", "2", "--leak-hold-s", "2", "--out", str(run),
                                  "--registry", str(tmp_path / "registry")])
    screen = bytearray()
    exit_status: list[int] = []

    def read_until(done, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                return False
            if select.select([fd], [], [], 0.05)[0]:
                try:
                    screen.extend(os.read(fd, 1 << 16))
                except OSError:  # the child closed the pty: read nothing more
                    time.sleep(0.05)
        return True

    def exited() -> bool:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            exit_status.append(os.waitstatus_to_exitcode(status))
        return bool(exit_status)

    try:
        assert read_until(lambda: b"Commission" in screen, 60), bytes(screen[-2000:])
        os.write(fd, b"c")
        assert read_until(lambda: b"Start" in screen[-20000:], 10)
        os.write(fd, b"y")
        session = run / "session.h5"
        assert read_until(lambda: session.exists() and session.stat().st_size > 2e6, 90)
        os.kill(pid, signal.SIGTERM)
        assert read_until(exited, 60)
    finally:
        if not exit_status:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        os.close(fd)
    assert exit_status == [143]
    assert b"\x1b[?1049l" in screen  # the alternate screen left: the shell's screen is back
    assert json.loads((run / "acceptance.json").read_text())["stopped"] is True
    with Session.open(run / "session.h5") as s:
        assert s.closed_cleanly and s.n_frames > 0
