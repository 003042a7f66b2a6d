"""The simulated bench end to end: the three drivers against their twins, and every fault kind.

Each test opens a real ``sim`` bench (BubbleSim scene, pty pressure firmware read by pyserial,
ur_rtde-shaped arm twin, depthai-message camera twin) with one object, the box. The fault tests
run the production collection loop (``collect.collection.run_collection`` and its recorder).
"""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
import yaml

from collect.arm import ARRIVAL_TOL_RAD
from collect.bench import BenchConfig, open_bench
from collect.collection import open_collection_writer, plan_bench_collection, run_collection
from collect.errors import HardwareFault, InputError
from collect.pose_planner import PlanSettings
from collect.pressure_board import MAX_FROZEN_RUN
from collect.session_reader import Session
from collect.transforms import rotation_between_rad
from collect.yaml_files import dump_yaml
from hw_mocks.pressure_firmware import RATE_HZ
from hw_mocks.sim_bench import FAULT_KINDS, SimFault, parse_sim_fault


def _press_cycle(bench, hold_s: float):
    """Above the box top, approach, press to 4 N, hold. Returns the approach start pose (6,)."""
    top = bench.objects[0].top_point()
    above = np.array([top[0], top[1], top[2] + 0.006, np.pi, 0.0, 0.0])
    bench.arm.move_to(above, 0.25, 1.0)
    contact = bench.arm.move_until_contact(speed=0.01, force_threshold_n=0.4, max_travel_m=0.012)
    assert contact is not None
    bench.arm.press(force_n=4.0, speed=0.01)
    bench.arm.hold(hold_s)
    return above


def _config(**kw):
    return BenchConfig.create("sim", objects=("box",), seed=1, **kw)


def test_sim_bench_streams_all_three_devices_through_the_real_driver_paths():
    # device-level reads on purpose (driver paths, no recorder); the collection's recorder streaming
    # all three during motion: tests/test_collect_run.py
    with open_bench(_config()) as bench:
        assert bench.simulated and bench.sim is not None
        assert bench.sensor_serial == bench.sim.spec.serial  # read from the board with ID?
        assert bench.intrinsics == bench.sim.spec.intrinsics()
        assert bench.pressure.firmware_version().startswith("bubble-pb")
        bench.pressure.set_led(True)
        assert bench._firmware.led  # the twin's LED is on
        frames = [bench.camera.get_frame() for _ in range(30)]
        bench.pressure.drain()
        bench.arm.drain_states()
        t0 = bench.clock()
        rest_hpa = bench.pressure.wait_reading().hpa
        above = _press_cycle(bench, hold_s=0.3)
        pressed = bench.arm.state()
        pressed_hpa = bench.pressure.wait_reading().hpa
        bench.arm.retract()
        t1 = bench.clock()
        bench.check()  # no device fault on the way
        states, readings = bench.arm.drain_states(), bench.pressure.drain()

    h, w = bench.intrinsics["height"], bench.intrinsics["width"]
    seq = np.array([f.seq for f in frames])
    np.testing.assert_array_equal(np.diff(seq), 1)  # contiguous
    t_dev = np.array([f.t_device for f in frames])
    np.testing.assert_allclose(np.diff(t_dev), 1.0 / bench.sim.spec.fps, atol=2e-6)  # 45 fps device clock (us ticks)
    for f in frames[:3]:
        assert f.ir.shape == f.depth.shape == f.true_depth.shape == (h, w)
        assert f.ir.dtype == f.depth.dtype == np.uint16 and f.true_depth.dtype == np.float32
        assert 0.04 < np.median(f.depth[f.depth > 0]) * 1e-5 < 0.12  # membrane 40-120 mm away
    # Arm: pressed down onto the box with ~4 N up on the sensor, then back to the approach pose.
    assert 3.0 < pressed.tcp_wrench[2] < 8.0
    assert pressed.tcp_pose[2] < above[2] - 0.006
    np.testing.assert_allclose(states[-1].tcp_pose, above, atol=5e-4)
    # Both streams per second of simulated time: at least a tenth of their rates (125 Hz asked of the
    # arm's monitor, 100 Hz of the board), a margin for a loaded machine, whose threads lag the clock;
    # the monitor's own rate: tests/test_drivers_safety.py
    t_arm = np.array([s.t for s in states])
    assert np.all(np.diff(t_arm) > 0) and len(states) / (t1 - t0) > _config().state_hz / 10
    # Pressure: streamed on the board, every reading in order (no line lost), rising with the dent.
    seq = np.array([r.seq for r in readings])
    assert len(readings) / (t1 - t0) > RATE_HZ / 10
    np.testing.assert_array_equal(np.diff(seq), 1)
    assert bench.pressure.stats["seq_gaps"] == 0
    assert pressed_hpa > rest_hpa + 1.0
    assert bench.pressure.stats["bad_checksum"] == bench.pressure.stats["malformed"] == 0


def _at_rest(bench):
    """The arm's first state sample once the simulated arm has come to rest (the last millimetre of a
    braking ramp takes a moment; polled, not slept: a paused simulated clock stretches it)."""
    from conftest import wait_until

    assert wait_until(lambda: np.linalg.norm(bench.sim.arm.tcp_speed()[:3]) == 0.0, 10.0), "the arm never came to rest"
    t_rest = bench.clock()
    assert wait_until(lambda: bench.arm.state().t >= t_rest, 10.0), "no arm sample since it came to rest"
    return bench.arm.state()


def test_a_contact_move_while_pressed_is_a_preload_fault_and_the_safe_stop_retracts():
    with open_bench(_config()) as bench:
        above = _press_cycle(bench, hold_s=0.0)
        pressed = bench.arm.state()
        with pytest.raises(HardwareFault) as err:  # zeroing now would take the press for "no contact"
            bench.arm.move_until_contact(speed=0.01, force_threshold_n=0.4, max_travel_m=0.012)
        assert err.value.kind == "preload"
        still = bench.arm.state()
        np.testing.assert_allclose(still.tcp_pose, pressed.tcp_pose, atol=1e-4)  # not moved
        assert still.pressing_force_n() > 3.0  # not zeroed: the press still reads
        assert bench.safe_stop()
        np.testing.assert_allclose(_at_rest(bench).tcp_pose, above, atol=5e-4)


def test_a_collision_during_the_safe_stop_after_another_fault_stops_the_retract(caplog):
    """After a fault from another device (here a camera stall) the force stays watched: a collision
    during the safe stop's retract stops the arm there and is said once, while the run still reports
    the first fault (before, the retract ignored the force and carried on into the collision)."""
    with open_bench(_config()) as bench:
        above = _press_cycle(bench, hold_s=0.0)
        bench.arm.abort(HardwareFault("camera-stall", "camera: no frame for 0.6 s"))
        bench.sim.faults.append(SimFault("force-spike", bench.clock() + 0.05))
        assert not bench.safe_stop()
        assert bench.arm.fault.kind == "camera-stall"  # the first fault is what the run reports
        assert _at_rest(bench).tcp_pose[2] < above[2] - 1e-3  # stopped on the way out
    said = [r.getMessage() for r in caplog.records if "not retracted" in r.getMessage()]
    assert len(said) == 1 and "sudden jump" in said[0], said


def test_another_devices_fault_during_the_safe_stop_does_not_stop_its_retract():
    """Was: a camera stall (or a serial fault) while the safe stop retracted after Ctrl-C stopped the
    retract there, the bubble left pressed on its object; the retract now goes on to its pose."""
    with open_bench(_config()) as bench:
        above = _press_cycle(bench, hold_s=0.0)
        stall = threading.Timer(0.05, bench.arm.abort, [HardwareFault("camera-stall", "camera: no frame for 0.6 s")])
        stall.start()
        try:
            assert bench.safe_stop()
        finally:
            stall.join()
        assert bench.arm.fault.kind == "camera-stall"
        np.testing.assert_allclose(_at_rest(bench).tcp_pose, above, atol=5e-4)


def _collect_with(bench, out, progress, plan_settings=None):
    plan = plan_bench_collection(bench, plan_settings or PlanSettings(poses_per_object=1, seed=1, hold_s=3.0))
    with pytest.raises(HardwareFault) as err, open_collection_writer(out, bench, plan, resume=False) as writer:
        run_collection(bench, plan, writer, progress)
    return plan, err.value


def test_a_recorder_that_fails_stops_the_arm_at_once_and_keeps_the_data(tmp_path, monkeypatch):
    """Was: an error other than a device fault in the recorder thread (a frame of another shape than
    the session's, a failing progress callback) ended the recording silently; the arm ran the hold
    to its end unrecorded and unwatched, and the run ended in a traceback (exit 1)."""
    out = tmp_path / "s.h5"
    failed_at = []
    with open_bench(_config()) as bench:
        def progress(phase, **_):
            if phase == "hold":
                failed_at.append(bench.clock())
                raise ValueError("frame shape (480, 640) != session shape (172, 224)")

        safe_stops = []
        real_safe_stop = bench.safe_stop
        monkeypatch.setattr(bench, "safe_stop", lambda: safe_stops.append(bench.clock()) or real_safe_stop())
        _, fault = _collect_with(bench, out, progress)
        assert fault.kind == "recorder" and "ValueError: frame shape" in str(fault)
        assert safe_stops[0] < failed_at[0] + 0.1  # not after the 3 s hold
    with Session.open(out) as s:
        assert s.closed_cleanly and len(s.select(phase="press")) > 0


def test_a_recorder_blocked_by_its_disk_stops_the_arm_and_keeps_the_data(tmp_path, monkeypatch):
    """The session file's disk stalls during a hold (the writer's queue fills and the recorder waits
    on it): a ``recorder`` fault stops and retracts the arm within ``RECORDER_STALL_S`` (was: the arm
    ran the plan on, its camera and pressure board unwatched, until the disk came back)."""
    from collect.collection import FRAME_TIMEOUT_S, RECORDER_STALL_S
    from collect.session_writer import SessionWriter

    disk_back = threading.Event()
    stalled_at = []
    append_frame = SessionWriter.append_frame

    def stalling_append_frame(writer, *args, **kwargs):
        if stalled_at:
            disk_back.wait(60)
        return append_frame(writer, *args, **kwargs)

    monkeypatch.setattr(SessionWriter, "append_frame", stalling_append_frame)
    out = tmp_path / "s.h5"
    with open_bench(_config()) as bench:
        def progress(phase, **_):
            if phase == "hold" and not stalled_at:
                stalled_at.append(bench.clock())

        safe_stops = []
        real_safe_stop = bench.safe_stop

        def safe_stop_then_disk_back() -> bool:
            safe_stops.append(bench.clock())
            retracted = real_safe_stop()
            disk_back.set()  # the recorder then ends, and the writer closes the file
            return retracted

        monkeypatch.setattr(bench, "safe_stop", safe_stop_then_disk_back)
        plan, fault = _collect_with(bench, out, progress, PlanSettings(poses_per_object=1, seed=1, hold_s=8.0))
        assert fault.kind == "recorder" and "recorder: blocked for" in str(fault), fault
        # within the stall limit and the watchdog's period, 10x a camera timeout for a loaded machine
        assert stalled_at[0] < safe_stops[0] < stalled_at[0] + RECORDER_STALL_S + 10 * FRAME_TIMEOUT_S < \
            stalled_at[0] + 8.0
        np.testing.assert_allclose(_at_rest(bench).tcp_pose[:3], plan.poses[0].above_pose[:3], atol=5e-4)
    with Session.open(out) as s:
        assert s.closed_cleanly and len(s.select(phase="press")) > 0


def test_the_frames_captured_before_a_runs_end_are_recorded_by_a_recorder_that_lags(tmp_path, monkeypatch):
    """A recorder behind the camera (a slow disk, a loaded machine) records, once halted, the frames
    still in the camera's queue up to the halt (was: dropped: a protective stop's retract, 0.05 s
    long, had no frame on file on a loaded machine)."""
    import collect.collection as collection
    from collect.session_writer import SessionWriter

    append_frame, end_recording = SessionWriter.append_frame, collection._end_recording
    halts = []

    def slow_append_frame(writer, *args, **kwargs):
        time.sleep(0.03)  # slower than the camera's 45 fps
        return append_frame(writer, *args, **kwargs)

    def end_and_note(recorder) -> None:
        halts.append(bench.clock())  # the run ends now
        end_recording(recorder)

    monkeypatch.setattr(SessionWriter, "append_frame", slow_append_frame)
    monkeypatch.setattr(collection, "_end_recording", end_and_note)
    out = tmp_path / "s.h5"
    with open_bench(_config()) as bench:
        plan = plan_bench_collection(bench, PlanSettings(poses_per_object=1, seed=1, hold_s=0.5))
        with open_collection_writer(out, bench, plan, resume=False) as writer:
            run_collection(bench, plan, writer)
        period_s = 1.0 / bench.sim.spec.fps
    with Session.open(out) as s:
        # up to the halt, but for a frame or two the full queue dropped (was: 8-9 frames before it, the
        # camera queue's length)
        assert halts[0] - 4 * period_s < s.t_host[-1] < halts[0] + period_s, (s.t_host[-3:], halts)


def test_the_frames_captured_before_a_pressure_fault_are_recorded_by_a_recorder_that_lags(tmp_path, monkeypatch):
    """The pressure board fails while the recorder is behind the camera: the arm stops at once, and
    the frames the camera captured until the fault was found are recorded (was: those still in the
    camera's queue were dropped, up to 0.18 s of them; the fault-kind test saw the last frame 0.11 s
    before the fault beside another test worker)."""
    from collect.session_writer import SessionWriter

    append_frame = SessionWriter.append_frame
    found = []

    def slow_append_frame(writer, *args, **kwargs):
        time.sleep(0.03)  # slower than the camera's 45 fps
        return append_frame(writer, *args, **kwargs)

    monkeypatch.setattr(SessionWriter, "append_frame", slow_append_frame)
    out = tmp_path / "s.h5"
    with open_bench(_config()) as bench:
        check = bench.pressure.check

        def noted_check() -> None:
            try:
                check()
            except HardwareFault:
                found.append(bench.clock())
                raise

        def progress(phase, **_):
            if phase == "hold" and not bench.sim.faults:
                bench.sim.faults.append(SimFault("serial-unplug", bench.clock() + 0.3))

        monkeypatch.setattr(bench.pressure, "check", noted_check)
        plan = plan_bench_collection(bench, PlanSettings(poses_per_object=1, seed=1, hold_s=8.0))
        with pytest.raises(HardwareFault, match="vanished"), open_collection_writer(out, bench, plan, resume=False) as writer:
            run_collection(bench, plan, writer, progress)
        period_s = 1.0 / bench.sim.spec.fps
    with Session.open(out) as s:
        # up to the fault's finding, but for a frame or two the full queue dropped
        assert found[0] - 4 * period_s < s.t_host[-1] < found[0] + period_s, (s.t_host[-3:], found)


def test_a_display_that_blocks_holds_up_neither_the_recording_nor_its_fault_checks(tmp_path, monkeypatch):
    """The progress display blocks from the hold on (a terminal paused with Ctrl-S): the camera goes
    silent and the arm is stopped as always (was: the recorder waited in the display, and the arm
    pressed on through the silence until the terminal was resumed)."""
    from collect.collection import FRAME_TIMEOUT_S

    resumed = threading.Event()
    out = tmp_path / "s.h5"
    with open_bench(_config()) as bench:
        def progress(phase, **_):
            if phase == "hold" and not bench.sim.faults:
                bench.sim.faults.append(SimFault("camera-stall", bench.clock() + 0.3))
                resumed.wait(60)

        safe_stops = []
        real_safe_stop = bench.safe_stop
        monkeypatch.setattr(bench, "safe_stop", lambda: safe_stops.append(bench.clock()) or real_safe_stop())
        try:
            _, fault = _collect_with(bench, out, progress, PlanSettings(poses_per_object=1, seed=1, hold_s=8.0))
        finally:
            resumed.set()
        (stall,) = bench.sim.faults
        assert fault.kind == "camera-stall" and stall.at_s < safe_stops[0] < stall.at_s + 10 * FRAME_TIMEOUT_S
    with Session.open(out) as s:
        assert s.closed_cleanly and s.t_host[-1] > stall.at_s - 0.1  # recorded up to the silence


def test_the_arms_own_fault_is_reported_when_another_device_fails_during_its_safe_stop(tmp_path, monkeypatch):
    """A force fault first, then the camera stalls during the safe stop: the run reports the force
    fault (was: the camera's, as if the camera had caused the stop)."""
    with open_bench(_config()) as bench:
        def progress(phase, **_):
            if phase == "hold" and not bench.sim.faults:
                bench.sim.faults.append(SimFault("force-spike", bench.clock() + 0.2))

        real_safe_stop = bench.safe_stop

        def safe_stop_with_stall():
            bench.sim.faults.append(SimFault("camera-stall", bench.clock()))
            time.sleep(0.8)  # the recorder sees the silence (0.5 s) during the stop
            return real_safe_stop()

        monkeypatch.setattr(bench, "safe_stop", safe_stop_with_stall)
        _, fault = _collect_with(bench, tmp_path / "s.h5", progress)
        assert fault.kind == "force-spike", fault


def test_a_ctrl_c_while_a_fault_ends_the_recording_keeps_the_faults_exit(tmp_path, monkeypatch):
    """Was: a Ctrl-C while the recorder thread was joined after a fault's safe stop raised
    KeyboardInterrupt there, and the run exited 130 with its fault unsaid."""
    import collect.collection as collection

    real_join = collection._Recorder.join
    interrupted = []

    def join_with_ctrl_c(self, *args):
        if not interrupted:
            interrupted.append(True)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler runs here
        return real_join(self, *args)

    monkeypatch.setattr(collection._Recorder, "join", join_with_ctrl_c)
    with open_bench(_config()) as bench:
        def progress(phase, **_):
            if phase == "hold" and not bench.sim.faults:
                bench.sim.faults.append(SimFault("force-spike", bench.clock() + 0.2))

        _, fault = _collect_with(bench, tmp_path / "s.h5", progress)
        assert fault.kind == "force-spike" and interrupted


def test_a_short_fault_before_the_devices_stream_is_moved_to_when_they_do(caplog):
    """Was: a ``force-spike`` (0.25 s) at 0 s came and went while the bench opened, no driver read it,
    and the run went on as if none had been injected (at ``--sim-speed 20`` a spike at 1 s too)."""
    with open_bench(_config(faults=("force-spike@0",), speed=20.0)) as bench:
        (fault,) = bench.sim.faults
        deadline = time.monotonic() + 5.0
        while bench.arm.fault is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert bench.arm.fault is not None and bench.arm.fault.kind == "force-spike"
    assert fault.at_s > 0.25 and f"--sim-fault force-spike@0 starts at {fault.at_s:.2f} s" in caplog.text


def test_parse_sim_fault():
    assert parse_sim_fault("camera-stall@12.5") == SimFault("camera-stall", 12.5)
    assert parse_sim_fault(" force-spike@3 ").at_s == 3.0
    assert parse_sim_fault("force-spike@1e1").at_s == 10.0  # was: "expected KIND@SECONDS"
    for bad in ("camera-stall", "camera-stall@", "melt@3", "force-spike@-1", "x@y", ""):
        with pytest.raises(InputError):
            parse_sim_fault(bad)
    with pytest.raises(InputError, match="unknown fault 'Camera-Stall'"):  # was: "expected KIND@SECONDS"
        parse_sim_fault("Camera-Stall@3")
    for seconds in ("-3", "nan", "inf", "9" * 400, "soon"):  # 400 digits: was inf, a fault that never came
        with pytest.raises(InputError) as refused:
            parse_sim_fault(f"camera-stall@{seconds}")
        assert str(refused.value) == (f"--sim-fault 'camera-stall@{seconds}': SECONDS must be a number of seconds "
                                      f">= 0, got '{seconds}'")
    with pytest.raises(InputError):
        BenchConfig.create("sim", faults=("bogus@1",)).open()
    with pytest.raises(InputError):
        BenchConfig.create("nope")


@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_fault_during_a_collection_stops_the_arm_retracts_and_keeps_the_data(kind, tmp_path, monkeypatch):
    from collect.collection import FRAME_TIMEOUT_S

    out = tmp_path / "fault.h5"
    with open_bench(_config()) as bench:
        plan = plan_bench_collection(bench, PlanSettings(poses_per_object=1, seed=1, hold_s=8.0))

        def progress(phase, **_):  # the recorder thread's report of the hold: the fault strikes during it
            if phase == "hold" and not bench.sim.faults:
                bench.sim.faults.append(SimFault(kind, bench.clock() + 0.3))

        safe_stops = []  # (bench time, retracted) of each safe stop: when the run reacted to the fault
        real_safe_stop = bench.safe_stop

        def timed_safe_stop() -> bool:
            t = bench.clock()
            safe_stops.append((t, real_safe_stop()))
            return safe_stops[-1][1]

        monkeypatch.setattr(bench, "safe_stop", timed_safe_stop)
        with pytest.raises(HardwareFault) as err, open_collection_writer(out, bench, plan, resume=False) as writer:
            run_collection(bench, plan, writer, progress)
        (fault,) = bench.sim.faults
        (t_detect, retracted), = safe_stops
        assert err.value.kind == kind
        # bounded detection, in simulated time (camera: silent > FRAME_TIMEOUT_S, 0.5 s; the others at
        # once; a frozen pressure: MAX_FROZEN_RUN readings of the 100 Hz stream more): 10x the 0.5 s for a
        # loaded machine, still before the 8 s hold, which began 0.3 s before the fault, would have ended
        frozen_s = MAX_FROZEN_RUN / RATE_HZ if kind == "pressure-frozen" else 0.0
        assert fault.at_s < t_detect < fault.at_s + 10 * FRAME_TIMEOUT_S + frozen_s < fault.at_s + 8.0 - 0.3
        state = _at_rest(bench)
        above = plan.poses[0].above_pose
        if kind == "protective-stop":
            assert not retracted  # a protective stop holds the arm until the operator clears it
            assert bench.sim.arm.safety_status_bits() & 1 << 2  # protective stop
            assert state.tcp_pose[2] < above[2] - 0.003  # still pressed in
            assert not bench.sim.arm.move_linear(state.tcp_pose + [0, 0, 0.01, 0, 0, 0], 0.05, 0.5)
        else:
            assert retracted  # back at the (tilted) approach pose, within the arm's arrival tolerances
            np.testing.assert_allclose(state.tcp_pose[:3], above[:3], atol=5e-4)
            assert rotation_between_rad(state.tcp_pose, above) < ARRIVAL_TOL_RAD
    with Session.open(out) as s:  # the recording up to the fault is kept, the safe stop's motion with it
        assert s.closed_cleanly and len(s.select(phase="hold")) > 0
        assert s.t_host[-1] > fault.at_s - 0.1
        np.testing.assert_allclose(s.arm().tcp_pose[-1], state.tcp_pose, atol=5e-4)


@pytest.mark.parametrize("kind, says", [("protective-stop", "during the move"), ("force-spike", "sudden jump")])
def test_fault_during_the_retract_after_a_press_is_reported_at_once(kind, says, tmp_path, caplog, monkeypatch):
    """The retract after a press moves away whatever fault came before it, but a protective stop
    (the robot will not finish the move) or a collision on the way (over the force limit) ends it:
    the run reports that fault at once, as what it is (not an ``arm-timeout`` after the move's time
    budget, nor a force fault found at the next move); a failed safe stop is said once."""
    from collect.arm import MOVE_TIMEOUT_MARGIN_S

    out = tmp_path / "stop.h5"
    with open_bench(_config()) as bench:
        plan = plan_bench_collection(bench, PlanSettings(poses_per_object=1, seed=1))

        def progress(phase, **_):
            if phase == "retract" and not bench.sim.faults:
                bench.sim.faults.append(SimFault(kind, bench.clock() + 0.05))

        safe_stops = []  # bench time of each safe stop: when the run reacted to the fault
        real_safe_stop = bench.safe_stop
        monkeypatch.setattr(bench, "safe_stop", lambda: safe_stops.append(bench.clock()) or real_safe_stop())
        with pytest.raises(HardwareFault) as err, open_collection_writer(out, bench, plan, resume=False) as writer:
            run_collection(bench, plan, writer, progress)
        (fault,) = bench.sim.faults
        assert err.value.kind == kind and says in str(err.value)
        # reacted to in simulated time well before an arm-timeout could have come (the move's planned
        # duration plus MOVE_TIMEOUT_MARGIN_S, 2 s): the monitor sees either fault within a sample or two
        # (~10 ms); half the margin leaves the rest to a loaded machine
        assert safe_stops and safe_stops[0] < fault.at_s + MOVE_TIMEOUT_MARGIN_S / 2
    not_retracted = [r for r in caplog.records if "not retracted" in r.getMessage()]
    assert len(not_retracted) == (1 if kind == "protective-stop" else 0)
    with Session.open(out) as s:
        assert s.closed_cleanly and len(s.select(phase="retract")) > 0


def test_bench_config_yaml_round_trip_and_errors(tmp_path):
    good = tmp_path / "bench.yaml"
    good.write_text(
        "type: ur\nrobot_ip: 192.168.1.10\nserial_port: /dev/ttyACM1\nhome_pose: [0.45, 0.0, 0.2, 3.14159, 0, 0]\n"
        "limits: {workspace_min: [0.2, -0.4, 0.01], workspace_max: [0.7, 0.4, 0.4], force_limit_n: 20}\n"
        "motion: {approach_speed: 0.01}\n")
    config = BenchConfig.from_yaml(good)
    assert config.type == "ur" and config.robot_ip == "192.168.1.10" and config.serial_port == "/dev/ttyACM1"
    assert config.limits.force_limit_n == 20 and config.limits.workspace_min == (0.2, -0.4, 0.01)
    assert config.motion.approach_speed == 0.01 and config.home_pose[0] == 0.45
    bad = {
        "missing.yaml": None,
        "syntax.yaml": "type: ur\nrobot_ip: [unclosed\n",
        "notype.yaml": "robot_ip: 1.2.3.4\n",
        "unknown.yaml": "type: ur\nwarp_drive: true\n",
        "badlimits.yaml": "type: sim\nlimits: {force_limit_n: -3}\n",
        "badtype.yaml": "type: kuka\n",
        "objects.yaml": "type: sim\nobjects: [mug, 3]\n",
        "objectsmap.yaml": "type: sim\nobjects: {mug: 1}\n",
        "rtde.yaml": "type: ur\nrtde_hz: 1000\n",  # checked when the config is built, not when the robot connects
        "rtdetext.yaml": "type: ur\nrtde_hz: fast\n",
        "fps.yaml": "type: ur\ncamera_fps: 0\n",
        "fpshigh.yaml": "type: ur\ncamera_fps: 200\n",
    }
    for name, text in bad.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        with pytest.raises(InputError):
            BenchConfig.from_yaml(path)
    # the line and the problem named (was: "while parsing a flow sequence" alone)
    with pytest.raises(InputError, match=r"bench config .*syntax.yaml is not valid YAML: line 3, column 1: expected ',' "
                                         r"or '\]', but got '<stream end>' \(while parsing a flow sequence\)$"):
        BenchConfig.from_yaml(tmp_path / "syntax.yaml")
    one = tmp_path / "one.yaml"
    one.write_text("type: ur\nobjects: teapot\n")  # one name, not the letters t, e, a, ...
    assert BenchConfig.from_yaml(one).objects == ("teapot",)
    with pytest.raises(InputError):
        BenchConfig.create("ur").open()  # no robot_ip: refused before any connection attempt


def test_yaml_files_refuse_a_key_given_twice_beside_a_merge_alias_floods_devices_and_odd_keys(tmp_path, monkeypatch):
    """Found by an audit of the config files (bench, sensor spec and thresholds share the reader). Was:
    a merge key turned the duplicate check off (a force limit written twice was the second one); a
    383-byte file of nested aliases read as 4.8 million values and quoted in a 39 MB error line;
    /dev/zero read until memory ran out; a key `1:` a TypeError traceback."""
    import collect.yaml_files

    def refused(text, match):
        path = tmp_path / "bench.yaml"
        path.write_text(text)
        with pytest.raises(InputError, match=match) as info:
            BenchConfig.from_yaml(path)
        assert "\n" not in str(info.value) and len(str(info.value)) < 500, str(info.value)[:200]

    limits = "type: sim\nlimits: {%s}\n"
    refused(limits % "force_limit_n: 10, <<: {}, force_limit_n: 140",
            r"line 2, column 37: duplicate key 'force_limit_n': give each key once")
    merged = tmp_path / "merged.yaml"
    merged.write_text(limits % "<<: {force_limit_n: 20, max_tilt_deg: 10}, force_limit_n: 15")  # the key given wins
    read = BenchConfig.from_yaml(merged).limits
    assert (read.force_limit_n, read.max_tilt_deg) == (15, 10)
    flood = "type: sim\nfaults: [&a0 [x, x, x, x, x, x, x, x, x]"
    flood += "".join(f", &a{k} [{', '.join([f'*a{k - 1}'] * 9)}]" for k in range(1, 7)) + "]\n"
    refused(flood, r"line 1, column 1: its aliases \(\*name\) repeat what their anchors hold into \d+ more values, "
                   r"over 10000; write the values out")
    refused("type: sim\nfaults: &A [x, *A]\n", r"line 2, column 9: an alias \(\*name\) inside its own anchor's "
                                              r"value: write the values out")  # was: a 12 kB file, a 9.7 MB error line
    refused(limits % "<<: {force_limit_n: 10, force_limit_n: 140}", "duplicate key 'force_limit_n'")  # in a merged one
    nested = tmp_path / "nested.yaml"  # a mapping merged in that has a merge key of its own: no false duplicate
    nested.write_text("type: sim\nlimits: {<<: &b {<<: {force_limit_n: 20}, max_tilt_deg: 10}, force_limit_n: 15}\n")
    assert BenchConfig.from_yaml(nested).limits.force_limit_n == 15
    few = tmp_path / "few.yaml"  # a few aliases of a short block read as before
    few.write_text("type: sim\nstart_pose: &p [0.45, 0.0, 0.2, 3.14159, 0, 0]\nhome_pose: *p\n")
    with pytest.raises(InputError, match="unknown field 'home_pose'"):  # read, then refused as a sim bench's field
        BenchConfig.from_yaml(few)
    refused("type: ur\nrobot_ip: 192.0.2.1\n1: 2\n", r"bench 'ur': unknown field '1' \(fields: ")
    with pytest.raises(InputError, match="^cannot read bench config /dev/zero: it is a device, not a file$"):
        BenchConfig.from_yaml("/dev/zero")
    monkeypatch.setattr(collect.yaml_files, "MAX_YAML_BYTES", 2_000_000)
    big = tmp_path / "big.yaml"
    big.write_text("type: sim\n" + "#" * 2_000_000 + "\n")
    with pytest.raises(InputError, match=f"^cannot read bench config {big}: it is over 2 MB, not a config file$"):
        BenchConfig.from_yaml(big)


UR_BENCH = "type: ur\nrobot_ip: 192.0.2.1\nhome_pose: [0.45, 0.0, 0.25, 3.14159, 0, 0]\n"

def test_plate_pose_is_where_the_centre_of_the_object_row_is():
    """Was: the layout's own frame, 0.45 m before the row's centre: a plate given by its measured
    centre put every object (and the workspace box fitted around them) 0.45 m further out."""
    from collect.bench import _placed_objects

    def footprint_centre(obj) -> np.ndarray:
        lo, hi = obj.bounds_base()
        return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])

    (box,) = _placed_objects(("box",), [0.6, 0.1, 0.02, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(footprint_centre(box), [0.6, 0.1, 0.02], atol=1e-9)
    def row_centre(objects) -> np.ndarray:
        lo = np.min([o.bounds_base()[0] for o in objects], axis=0)
        hi = np.max([o.bounds_base()[1] for o in objects], axis=0)
        return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])

    nominal = [footprint_centre(o) for o in _placed_objects(("mug", "box"))]
    np.testing.assert_allclose(row_centre(_placed_objects(("mug", "box"))), [0.45, 0.0, 0.0], atol=1e-9)
    turned_row = _placed_objects(("mug", "box"), [0.5, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    turned = [footprint_centre(o) for o in turned_row]
    np.testing.assert_allclose(row_centre(turned_row), [0.5, 0.0, 0.0], atol=1e-9)  # the row turned about its
    # centre by 90 deg: base y onto -x, the objects as far apart as before
    np.testing.assert_allclose(turned[1] - turned[0], [-(nominal[1] - nominal[0])[1], 0.0, 0.0], atol=1e-9)
    default = [footprint_centre(o) for o in _placed_objects(("mug", "box"), [0.45, 0.0, 0.0, 0.0, 0.0, 0.0])]
    np.testing.assert_allclose(default, nominal, atol=1e-9)  # the layout's own place


#: A bench YAML line of the wrong kind -> what the one error line says. Each is checked when the
#: config is built, before the arm lock or any connection (was: a traceback from the arm lock, the
#: fixture plate or the safety limits, or an error only after the robot had connected).
BAD_BENCH_LINES = {
    "robot_ip: 10": "bench 'ur': robot_ip must be text (the UR controller's IP address or host name), got 10",
    "serial_port: 0": "bench 'ur': serial_port must be text (the pressure board's device, e.g. /dev/ttyACM0), got 0",
    "tof_profile: [LOW_RANGE]": "bench 'ur': tof_profile must be text",
    "tof_profile: LOW": "bench 'ur': unknown ToF profile 'LOW' (one of LOW_RANGE, MID_RANGE, HIGH_RANGE)",
    "camera_id: true": "bench 'ur': camera_id must be text",
    "plate_pose: [0, 0, 0]": "bench 'ur': plate_pose (the fixture plate's centre in the base frame) must be 6 numbers "
                             "[x, y, z, rx, ry, rz] (m, rotation vector in rad), got (0, 0, 0)",
    "plate_pose: flat": "bench 'ur': plate_pose (the fixture plate's centre in the base frame) must be 6 numbers",
    "state_hz: fast": "bench 'ur': state_hz 'fast' is outside 125..500 Hz (the arm's state sampling rate)",
    # was: accepted, and the force guards sampled at 10 Hz (a simulated press overshot its 15 N cap)
    "state_hz: 10": "bench 'ur': state_hz 10 is outside 125..500 Hz (the arm's state sampling rate)",
    "rtde_hz: 10": "bench 'ur': rtde_hz 10 is outside 125..500 Hz (the RTDE rates of a UR controller)",
    # was: accepted (a yaw of 90 rad), or numpy's LinAlgError from the plate's transform (1e300)
    "plate_pose: [0, 0, 0, 0, 0, 90]": "bench 'ur': plate_pose rotation vector [0, 0, 90] is longer than 6.283 rad "
                                       "(one turn): give it in radians",
    "home_pose: [0.45, 0, 0.25, 1.0e300, 0, 0]": "bench 'ur': home_pose rotation vector [1e+300, 0, 0] is longer than",
    # was: found only after the arm's lock and the robot's connection (the retract runs at twice the approach)
    "limits: {max_speed_m_s: 0.25}\nmotion: {approach_speed: 0.2}": "safety: speed 0.4 m/s is outside (0, 0.25] m/s",
    "limits: {workspace_min: low}": "safety: workspace_min must be 3 numbers [x, y, z] (m), got 'low'",
    "limits: {force_limit_n: []}": "safety: force_limit_n must be a positive number, got ()",
    "limits: {max_tilt_deg: .nan}": "safety: max_tilt_deg must be a positive number, got nan",
    "motion: {accel: fast}": "motion: accel must be a positive number, got 'fast'",
    "motion: {retract_m: 0}": "motion: retract_m must be a positive number, got 0",
    # upper bounds (was: accepted, and the simulated bench ran them)
    "limits: {max_tilt_deg: 1000}": "safety: max_tilt_deg must be within (0, 90] deg, got 1000",
    "limits: {max_speed_m_s: 100.0, force_limit_n: 100000.0}":
        "safety: max_speed_m_s must be within (0, 1] m/s, got 100.0",
    "limits: {force_limit_n: 100000.0}": "safety: force_limit_n must be within (0, 150] N, got 100000.0",
    "motion: {travel_speed: 50.0, approach_speed: 5.0}": "motion: travel_speed must be within (0, 1] m/s, got 50.0",
    "motion: {max_press_depth_m: 0.5}": "motion: max_press_depth_m must be within (0, 0.03] m, got 0.5",
    # YAML 1.2 floats (was: read as the text '1e6': "motion: contact_force_n must be a positive number, got '1e6'")
    "motion: {contact_force_n: 1e6}": "motion: contact_force_n must be within (0, 150] N, got 1000000.0",
    # was: "--objects is empty: ...", a flag never given
    "objects: []": "bench 'ur': objects is empty: name at least one object or mesh path",
    # was: "URBenchConfig.__init__() got an unexpected keyword argument 'warp_drive'"
    "warp_drive: true": "bench 'ur': unknown field 'warp_drive' (fields: objects, limits, motion, state_hz, robot_ip, "
                        "rtde_hz, camera_id, camera_fps, tof_profile, serial_port, plate_pose, home_pose)",
}
SIM_BENCH = "type: sim\nobjects: [mug]\n"
#: The same for the simulated bench's own fields (was: tracebacks from numpy's seeding, the
#: simulated clock, the sensor spec loader and the safety check of the start pose).
BAD_SIM_BENCH_LINES = {
    "sensor: 3": "bench 'sim': sensor must be a sensor spec YAML path (leave it out to draw one from seed), got 3",
    "seed: -1": "bench 'sim': seed must be a whole number >= 0, got -1",
    "seed: 1.5": "bench 'sim': seed must be a whole number >= 0, got 1.5",
    "faults: 7": "bench 'sim': faults must be a list of KIND@SECONDS strings, got 7",
    "speed: fast": "simulation speed 'fast' must be within 0.1..100",
    "start_pose: {x: 1}": "safety: pose must be 6 finite numbers [x,y,z,rx,ry,rz], got {'x': 1}",
}


def _with_line(base: str, line: str) -> str:
    """``base`` with ``line`` in place of the base's line of the same key (a key given twice is refused)."""
    key = line.split(":", 1)[0] + ":"
    kept = [kept for kept in base.splitlines() if not kept.startswith(key)]
    return "\n".join(kept + [line]) + "\n"


@pytest.mark.parametrize("bench_text, message", [(_with_line(UR_BENCH, line), m) for line, m in BAD_BENCH_LINES.items()]
                         + [(_with_line(SIM_BENCH, line), m) for line, m in BAD_SIM_BENCH_LINES.items()],
                         ids=[*BAD_BENCH_LINES, *BAD_SIM_BENCH_LINES])
def test_a_bench_field_of_the_wrong_kind_is_one_line_before_anything_connects(tmp_path, capsys, bench_text, message):
    from calibrate.cli import main

    bench = tmp_path / "bench.yaml"
    bench.write_text(bench_text + "\n")
    assert main(["collect", "--bench", str(bench), "--out", str(tmp_path / "s.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bubble: error: {message}"), err
    assert err.count("\n") == 1 and not (tmp_path / "s.h5").exists()


def test_an_empty_object_list_in_a_sim_bench_file_names_the_file_field(tmp_path, capsys):
    from calibrate.cli import main

    bench = tmp_path / "bench.yaml"
    bench.write_text("type: sim\nobjects: []\n")
    assert main(["collect", "--bench", str(bench), "--out", str(tmp_path / "s.h5")]) == 2
    # was: "--objects is empty: name at least one object or give --object-mesh", a flag never given
    assert capsys.readouterr().err == ("bubble: error: bench 'sim': objects is empty: name at least one object or "
                                       "mesh path\n")


@pytest.mark.parametrize("bench_text", [UR_BENCH, SIM_BENCH], ids=["ur", "sim"])
def test_a_motion_over_the_default_limits_is_refused_when_the_config_is_built(bench_text):
    """A bench file with no ``limits`` gets the default ones (0.25 m/s). Was: its motion checked only in
    ``open()``, after the simulated bench's physics and firmware threads had started (left running once
    the arm refused) or, on a real bench, after the arm's lock and both RTDE connections."""
    threads_before = set(threading.enumerate())
    with pytest.raises(InputError, match=r"^safety: speed 0\.5 m/s is outside \(0, 0\.25\] m/s$"):
        BenchConfig.from_dict(yaml.safe_load(bench_text + "motion: {travel_speed: 0.5}\n"))
    assert set(threading.enumerate()) <= threads_before


@pytest.mark.parametrize("line, says", [
    ("limits: {force_limt_n: 3}", "limits: unknown field 'force_limt_n' (fields: workspace_min, workspace_max, "
                                  "max_speed_m_s, max_accel_m_s2, force_limit_n, max_tilt_deg)"),
    ("motion: {acel: 1}", "motion: unknown field 'acel' (fields: travel_speed, approach_speed,"),
])
def test_a_misspelt_limit_or_motion_setting_is_named_with_the_fields_there_are(tmp_path, line, says):
    bench = tmp_path / "bench.yaml"
    bench.write_text(SIM_BENCH + line + "\n")
    with pytest.raises(InputError) as err:
        BenchConfig.from_yaml(bench)
    assert str(err.value).startswith(f"bench config {bench}: {says}"), err.value


def test_numbers_in_scientific_notation_are_numbers(tmp_path):
    """Was: YAML 1.1 reads an exponent without a decimal point (1e-2) as text, and the field refused it."""
    bench = tmp_path / "bench.yaml"
    bench.write_text(UR_BENCH + "rtde_hz: 5e2\nmotion: {press_speed: 1e-2, contact_force_n: 5E-1}\n"
                     "limits: {workspace_min: [0.2, -0.4, 1e-2], workspace_max: [0.7, 0.4, 0.4], force_limit_n: 2e1}\n")
    config = BenchConfig.from_yaml(bench)
    assert config.rtde_hz == 500.0 and config.motion.press_speed == 0.01 and config.motion.contact_force_n == 0.5
    assert config.limits.workspace_min == (0.2, -0.4, 0.01) and config.limits.force_limit_n == 20.0


def test_a_numeric_camera_id_and_the_home_pose_as_a_list_are_taken_as_written(tmp_path):
    bench = tmp_path / "bench.yaml"
    bench.write_text(UR_BENCH + "camera_id: 184430\n")  # an all-digit device name, read by YAML as a number
    config = BenchConfig.from_yaml(bench)
    assert config.camera_id == "184430" and config.home_pose == (0.45, 0.0, 0.25, 3.14159, 0, 0)
    for written in ("0123", "1_000", "0x1A", "1:30", "0b11"):  # YAML 1.1's other ints (was: '83', '1000', '26', ...)
        bench.write_text(UR_BENCH + f"camera_id: {written}\n")
        assert BenchConfig.from_yaml(bench).camera_id == written
        assert dump_yaml({"camera_id": written}) == f"camera_id: '{written}'\n"  # quoted for any other reader
    bench.write_text(UR_BENCH + "state_hz: 0x7D\n")  # text now, to a field that wants a number (was: 125)
    with pytest.raises(InputError, match="state_hz"):
        BenchConfig.from_yaml(bench)


def test_a_cpu_starved_camera_twin_slows_simulated_time_instead_of_stalling(monkeypatch):
    """Rendering made slower than the stall timeout: simulated time waits for the camera twin
    (pacing), so the driver sees every frame late in real time but never a camera-stall."""
    with open_bench(_config(speed=20.0)) as bench:
        device = bench.camera.device
        render = device.render
        monkeypatch.setattr(device, "render", lambda seq, t: (time.sleep(0.08), render(seq, t))[1])
        t0_sim, t0_real = bench.clock(), time.monotonic()
        frames = [bench.camera.get_frame() for _ in range(20)]  # 0.08 s real = 1.6 s simulated each
        elapsed_sim, elapsed_real = bench.clock() - t0_sim, time.monotonic() - t0_real
        assert [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + 20))
        # 20 frames at 45 fps of simulated time (up to 8 were already queued), not 20x real time
        assert elapsed_sim < 1.0 and elapsed_sim < 2.0 * elapsed_real


def test_the_simulated_camera_makes_room_in_a_full_queue_instead_of_letting_depthai_drop():
    import depthai as dai

    from hw_mocks.fake_camera import _send_without_drop, img_frame

    queue = dai.MessageQueue("depth", 3, False)
    for seq in range(5):
        _send_without_drop(queue, img_frame(np.zeros((2, 2), np.uint16), seq, float(seq), float(seq)))
    assert queue.getSize() == 3  # the newest three, oldest first, as depthai's own drop would keep
    assert [queue.tryGet().getSequenceNum() for _ in range(3)] == [2, 3, 4]
    assert queue.tryGet() is None


class SteppedClock:
    """A simulated clock that the test moves by hand (``SimBench.clock``'s interface)."""

    def __init__(self, t: float):
        self.t, self.speed, self.limit = t, 1.0, None

    def now(self) -> float:
        return self.t

    __call__ = now


def test_a_frame_at_rest_shows_the_membrane_where_the_arm_stopped():
    """A move stopped short of the pose the latest solution was made for (the look-ahead of a guarded
    press): the next frame is rendered from a solution at the rest pose (was: from the look-ahead
    one, a dent deeper than the arm ever pressed, in the first frames of some holds)."""
    from collect.bench import _placed_objects
    from hw_mocks.fake_camera import SimCameraDevice
    from hw_mocks.sensor_spec import draw_sensor
    from hw_mocks.sim_bench import SimBench, _same_pose

    objects = _placed_objects(("box",))
    top = objects[0].top_point()
    pressed = np.array([top[0], top[1], top[2] - 0.002, np.pi, 0.0, 0.0])  # 2 mm into the box
    scene = SimBench(draw_sensor(1), objects, seed=1, start_pose=pressed)  # no physics thread: the test solves
    scene.clock = clock = SteppedClock(scene.now())  # was: real time, whose sleeps a loaded machine stretched
    assert scene.arm.move_linear(pressed - [0, 0, 0.004, 0, 0, 0], 0.02, 1.0)
    clock.t += 0.05
    scene._solve_now()  # the physics thread's solve, 30 ms ahead along the press
    ahead = scene.latest()
    scene.arm.stop_linear(100.0)  # the guard fires: the arm stops at once
    clock.t += 0.05
    rest = scene.arm.pose_at(scene.now())
    assert scene.arm.moving_until() <= scene.now() and not _same_pose(ahead.pose, rest)
    seq, t = 0, scene.now()
    _, _, true_depth = SimCameraDevice(scene).render(seq, t)
    frame = scene.latest()
    assert _same_pose(frame.pose, rest) and frame is not ahead
    np.testing.assert_array_equal(true_depth, np.asarray(frame.state.true_depth, dtype=np.float32))
    # the stale solution's dent was deeper by the look-ahead (0.6 mm: 30 ms at 20 mm/s)
    lead = abs(ahead.pose[2] - rest[2])
    assert lead == pytest.approx(6e-4, abs=2e-5) and np.nanmax(np.abs(ahead.state.true_depth - frame.state.true_depth)) == pytest.approx(lead, rel=0.2)


def test_a_robot_lost_before_its_first_sample_is_a_fault_not_a_traceback(tmp_path, capsys, monkeypatch):
    """Was: the arm's start failed before any sample, and the safe stop on the way out read no state:
    ``AttributeError: 'NoneType' object has no attribute 'tcp_wrench'``, a traceback and exit 1."""
    from calibrate.cli import main
    from hw_mocks.fake_rtde import FakeRTDEReceive

    monkeypatch.setattr(FakeRTDEReceive, "isConnected", lambda self: False)
    out = tmp_path / "s.h5"
    assert main(["collect", "--sim", "--objects", "box", "--poses-per-object", "1", "--quiet", "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "lost the RTDE connection" in err and "Traceback" not in err and "AttributeError" not in err


def _pressing_on_a_stepped_clock():
    """A simulated bench without its physics thread (the test solves) on a ``SteppedClock``, its arm
    starting a 20 mm/s press 2 mm above the box: ``(scene, clock)``."""
    from collect.bench import _placed_objects
    from hw_mocks.sensor_spec import draw_sensor
    from hw_mocks.sim_bench import SimBench

    objects = _placed_objects(("box",))
    top = objects[0].top_point()
    above = np.array([top[0], top[1], top[2] + 0.002, np.pi, 0.0, 0.0])
    scene = SimBench(draw_sensor(1), objects, seed=1, start_pose=above)  # no physics thread: the test solves
    scene.clock = clock = SteppedClock(scene.now())
    assert scene.arm.move_linear(above - [0, 0, 0.008, 0, 0, 0], 0.02, 1.0)
    return scene, clock


def test_a_frame_during_a_move_shows_the_solution_made_for_its_time():
    """Was: the latest solution, made for the pose the arm reaches 30 ms later: a 20 mm/s press was
    rendered up to 0.6 mm deeper than the arm pressed at the frame's time."""
    from hw_mocks.fake_camera import SimCameraDevice

    scene, clock = _pressing_on_a_stepped_clock()
    clock.t += 0.2
    scene._solve_now()  # the physics thread's solves, 30 ms ahead, a camera period (22 ms) apart
    clock.t += 0.022
    scene._solve_now()
    clock.t += 0.005  # a frame 3 ms short of the first solution's time, 25 ms short of the latest's
    frame, latest = scene.frame_solution(), scene.latest()
    arm_z = scene.arm.pose_at(clock.t)[2]
    assert frame is not latest and abs(frame.pose[2] - arm_z) < 1e-4 < abs(latest.pose[2] - arm_z)
    _, _, true_depth = SimCameraDevice(scene).render(0, clock.t)
    np.testing.assert_array_equal(true_depth, np.asarray(frame.state.true_depth, dtype=np.float32))


def test_a_frame_at_rest_shows_the_latest_solution_without_solving_again():
    """Once the arm has stopped, a solution the physics made at the rest pose is shown as it is (in
    e4e2053: the one nearest in time, often from before the stop, so the camera solved again, once or
    twice per guarded stop, and consecutive frames went back and forth between two solutions)."""
    from hw_mocks.sim_bench import _same_pose

    scene, clock = _pressing_on_a_stepped_clock()
    clock.t += 0.2
    scene._solve_now()  # made for 30 ms ahead, along the press
    scene.arm.stop_linear(100.0)  # the guard fires
    clock.t += 0.01
    scene._solve_now()  # the physics thread's next solve, at the rest pose
    at_rest, solves = scene.latest(), scene.solves
    clock.t += 0.001  # nearer in time to the solve before the stop than to this one
    assert scene.arm.moving_until() <= clock.t and _same_pose(at_rest.pose, scene.arm.pose_at(clock.t))
    assert scene.frame_solution() is at_rest and scene.solves == solves
