"""The bench TUI driving the real commissioning flow on the simulated bench (headless Pilot)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from calibrate.commission_events import Step
from calibrate.commissioning import CommissionConfig
from calibrate.tui.app import BenchApp
from calibrate.tui.widgets.confirm import ConfirmStart
from collect.bench import Bench
from collect.session_reader import Session

SIZE = (120, 36)


def tiny_config(tmp_path: Path, **overrides) -> CommissionConfig:
    """One object, two poses, a one-second leak hold, a few seconds of fine-tuning."""
    kwargs = dict(run_dir=tmp_path / "run", simulated=True, registry_dir=tmp_path / "registry", objects=("mug",),
                  poses_per_object=2, finetune_minutes=0.05, seed=3, leak_hold_s=1.0)
    kwargs.update(overrides)
    return CommissionConfig(**kwargs)


async def wait_for(predicate, pilot, timeout: float):
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        if loop.time() > deadline:
            raise AssertionError("condition not reached in time")
        await pilot.pause(0.05)


def test_stop_key_mid_collection_stops_retracts_and_keeps_a_readable_session(tmp_path, monkeypatch):
    safe_stops = []  # (retracted, |F| before, |F| after, z before, z after) per Bench.safe_stop call
    original = Bench.safe_stop

    def recording_safe_stop(bench):
        before = bench.arm.state()
        retracted = original(bench)
        after = bench.arm.state()
        safe_stops.append((retracted, float(np.linalg.norm(before.tcp_wrench[:3])),
                           float(np.linalg.norm(after.tcp_wrench[:3])), float(before.tcp_pose[2]),
                           float(after.tcp_pose[2])))
        return retracted

    monkeypatch.setattr(Bench, "safe_stop", recording_safe_stop)
    app = BenchApp(tiny_config(tmp_path, poses_per_object=3))

    async def scenario():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("c")
            assert isinstance(app.screen, ConfirmStart)
            await pilot.press("y")
            # stop while the arm works on a contact pose
            await wait_for(lambda: app.collection.last is not None and app.collection.last.pose_index >= 0
                           and app.collection.last.phase in ("approach", "press", "hold"), pilot, timeout=90)
            assert app.steps.row(Step.COLLECT).status == "running"
            await pilot.press("s")
            assert app.arm_state in ("stopping", "stopped")
            await wait_for(lambda: app.result is not None, pilot, timeout=30)
            assert app.result.stopped and app.arm_state == "stopped"
            assert app.steps.row(Step.COLLECT).status == "stopped"
            assert app.steps.row(Step.FINETUNE).status == "pending"
            await pilot.press("q")
            await wait_for(lambda: not app.is_running, pilot, timeout=10)

    asyncio.run(scenario())
    assert safe_stops and all(retracted for retracted, *_ in safe_stops)
    _, _, force_after, z_before, z_after = safe_stops[0]  # the stop key's safe stop, mid-pose
    assert force_after < 0.5 and z_after >= z_before - 1e-4
    with Session.open(tmp_path / "run" / "session.h5") as session:
        assert session.n_frames > 0
        assert np.isfinite(session.depth_m(np.arange(session.n_frames))).all()


def test_short_commissioning_shows_the_verdict_and_registers_the_sensor(tmp_path):
    app = BenchApp(tiny_config(tmp_path, sim_speed=4.0))

    async def scenario():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("c", "y")
            await wait_for(lambda: app.result is not None or app.error is not None, pilot, timeout=240)
            assert app.error is None
            result = app.result
            assert not result.stopped, result
            print({step: row.status for step, row in app.steps.rows.items()}, result)
            assert app.steps.row(Step.VERDICT).status in ("ok", "failed")
            assert app.acceptance.table.row_count == len(result.checks) > 0
            assert str(result.report_path) in str(app.acceptance.report_line.content)
            assert len(app.training.loss) > 0
            assert app.registry.table.row_count == 1
            await pilot.press("q")

    asyncio.run(scenario())
    assert Path(app.result.report_path).is_file()
