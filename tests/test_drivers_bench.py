"""The simulated bench end to end: the three drivers against their twins, and every fault kind.

Each test opens a real ``sim`` bench (BubbleSim scene, pty pressure firmware read by pyserial,
ur_rtde-shaped arm twin, depthai-message camera twin) with one object, the box.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from collect.bench import BenchConfig, open_bench
from collect.errors import HardwareFault, InputError
from hw_mocks.sim_bench import FAULT_KINDS, SimFault, parse_sim_fault


class _Recorder(threading.Thread):
    """Consumes frames and checks the pressure board like the collection loop; a device fault
    stops the arm through ``arm.abort``."""

    def __init__(self, bench):
        super().__init__(daemon=True)
        self.bench = bench
        self.frames = []
        self.error: HardwareFault | None = None
        self.halt = threading.Event()

    def run(self):
        try:
            while not self.halt.is_set():
                self.frames.append(self.bench.camera.get_frame())
                self.bench.pressure.check()
        except HardwareFault as err:
            self.error = err
            self.bench.arm.abort(err)


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
    with open_bench(_config()) as bench:
        assert bench.simulated and bench.sim is not None
        assert bench.sensor_serial == bench.sim.spec.serial  # read from the board with ID?
        assert bench.intrinsics == bench.sim.spec.intrinsics()
        assert bench.pressure.firmware_version().startswith("bubble-pb")
        bench.pressure.set_led(True)
        rec = _Recorder(bench)
        rec.start()
        bench.pressure.drain()
        bench.arm.drain_states()
        t0 = bench.clock()
        rest_hpa = bench.pressure.wait_reading().hpa
        above = _press_cycle(bench, hold_s=0.3)
        pressed = bench.arm.state()
        pressed_hpa = bench.pressure.wait_reading().hpa
        bench.arm.retract()
        t1 = bench.clock()
        rec.halt.set()
        rec.join()
        assert rec.error is None
        states, readings = bench.arm.drain_states(), bench.pressure.drain()

    frames = rec.frames
    h, w = bench.intrinsics["height"], bench.intrinsics["width"]
    assert len(frames) > 20
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
    t_arm = np.array([s.t for s in states])
    assert np.all(np.diff(t_arm) > 0) and len(states) / (t1 - t0) > 50
    # Pressure: streamed on the board, rising with the dent.
    assert len(readings) / (t1 - t0) > 50
    assert pressed_hpa > rest_hpa + 1.0
    assert bench.pressure.stats["bad_checksum"] == bench.pressure.stats["malformed"] == 0


def test_parse_sim_fault():
    assert parse_sim_fault("camera-stall@12.5") == SimFault("camera-stall", 12.5)
    assert parse_sim_fault(" force-spike@3 ").at_s == 3.0
    for bad in ("camera-stall", "camera-stall@", "melt@3", "force-spike@-1", "x@y", ""):
        with pytest.raises(InputError):
            parse_sim_fault(bad)
    with pytest.raises(InputError):
        BenchConfig.create("sim", faults=("bogus@1",)).open()
    with pytest.raises(InputError):
        BenchConfig.create("nope")


@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_fault_is_detected_and_the_arm_stops_and_retracts(kind):
    with open_bench(_config()) as bench:
        rec = _Recorder(bench)
        rec.start()
        above = _press_cycle(bench, hold_s=0.0)
        fault = SimFault(kind, bench.clock() + 0.3)  # strikes during the hold
        bench.sim.faults.append(fault)
        with pytest.raises(HardwareFault) as err:
            bench.arm.hold(3.0)
        t_detect = bench.clock()
        assert err.value.kind == kind
        assert fault.at_s < t_detect < fault.at_s + 0.8  # bounded detection (camera: silent > 0.5 s)
        retracted = bench.safe_stop()
        rec.halt.set()
        rec.join()
        time.sleep(0.1)  # the last millimetre of the retract's braking ramp
        state = bench.arm.state()
        assert np.linalg.norm(bench.sim.arm.tcp_speed()[:3]) == 0.0  # at rest
        if kind == "protective-stop":
            assert not retracted  # a protective stop holds the arm until the operator clears it
            assert bench.sim.arm.protective_stopped()
            assert state.tcp_pose[2] < above[2] - 0.003  # still pressed in
            assert not bench.sim.arm.move_linear(state.tcp_pose + [0, 0, 0.01, 0, 0, 0], 0.05, 0.5)
        else:
            assert retracted
            np.testing.assert_allclose(state.tcp_pose, above, atol=5e-4)  # back at the approach pose


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
    }
    for name, text in bad.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        with pytest.raises(InputError):
            BenchConfig.from_yaml(path)
    with pytest.raises(InputError):
        BenchConfig.create("ur").open()  # no robot_ip: refused before any connection attempt


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

    from hw_mocks.fake_camera import _img_frame, _send_without_drop

    queue = dai.MessageQueue("depth", 3, False)
    for seq in range(5):
        _send_without_drop(queue, _img_frame(np.zeros((2, 2), np.uint16), seq, float(seq), float(seq)))
    assert queue.getSize() == 3  # the newest three, oldest first, as depthai's own drop would keep
    assert [queue.tryGet().getSequenceNum() for _ in range(3)] == [2, 3, 4]
    assert queue.tryGet() is None
