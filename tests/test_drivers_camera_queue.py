"""The ToF camera's frame path over depthai host classes (ImgFrame, MessageQueue), no device.

``dai.Pipeline()`` is never constructed here (it blocks ~11 s without a device).
"""

from __future__ import annotations

import time

import depthai as dai
import numpy as np
import pytest

from collect.camera import DEPTHAI_TOF_DEPTH_UNIT_M, QueueToFCamera, depth_to_session_units
from collect.errors import HardwareFault
from collect.session_format import DEPTH_UNIT_M
from hw_mocks.fake_camera import img_frame


class _Camera(QueueToFCamera):
    """The queue camera as an OAK would feed it: depth in millimetres."""

    serial = "TEST"

    def __init__(self):
        super().__init__(DEPTHAI_TOF_DEPTH_UNIT_M, stall_timeout_s=0.2)
        self.depth_q = dai.MessageQueue("depth", 8, False)
        self.amp_q = dai.MessageQueue("amplitude", 8, False)

    def start(self):
        self._attach(self.depth_q, self.amp_q)

    def stop(self):
        pass

    def intrinsics(self):
        return {}


def test_millimetre_depth_becomes_session_units_and_overflow_is_invalid():
    mm = np.array([[0, 93, 655, 656]], dtype=np.uint16)
    out = depth_to_session_units(mm, 1e-3)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, [[0, 9300, 65500, 0]])
    same = np.array([[1234]], dtype=np.uint16)
    np.testing.assert_array_equal(depth_to_session_units(same, DEPTH_UNIT_M), same)


def test_frames_are_paired_by_sequence_number_and_unpacked():
    cam = _Camera()
    cam.start()
    rng = np.random.default_rng(0)
    depth = rng.integers(50, 120, size=(172, 224)).astype(np.uint16)
    ir = rng.integers(0, 65535, size=(172, 224)).astype(np.uint16)
    # Frame 0's amplitude got lost: the camera must skip the unpaired depth and deliver frame 1.
    cam.depth_q.send(img_frame(depth, 0, 10.0, 100.0))
    cam.depth_q.send(img_frame(depth, 1, 10.1, 100.1))
    cam.amp_q.send(img_frame(ir, 1, 10.1, 100.1))
    cam.depth_q.send(img_frame(depth, 3, 10.3, 100.3))
    cam.amp_q.send(img_frame(ir, 3, 10.3, 100.3))
    f1 = cam.get_frame()
    assert (f1.seq, f1.t_device, f1.t_host) == (1, pytest.approx(10.1), pytest.approx(100.1))
    np.testing.assert_array_equal(f1.depth, depth.astype(np.uint32) * 100)
    np.testing.assert_array_equal(f1.ir, ir)
    assert f1.true_depth is None
    f3 = cam.get_frame()
    assert f3.seq == 3


def test_silence_raises_camera_stall_within_the_timeout():
    cam = _Camera()
    cam.start()
    t0 = time.monotonic()
    with pytest.raises(HardwareFault) as err:
        cam.get_frame()
    assert err.value.kind == "camera-stall"
    assert time.monotonic() - t0 >= 0.2  # not before the timeout (how late depends on the machine's load)


def test_device_clock_going_backwards_is_a_fault():
    cam = _Camera()
    cam.start()
    img = np.ones((4, 4), np.uint16)
    for seq, t in ((5, 2.0), (6, 1.0)):
        cam.depth_q.send(img_frame(img, seq, t, t))
        cam.amp_q.send(img_frame(img, seq, t, t))
    cam.get_frame()
    with pytest.raises(HardwareFault) as err:
        cam.get_frame()
    assert err.value.kind == "camera-clock"


def test_a_camera_whose_queues_closed_is_a_disconnected_fault():
    """depthai closes a device's queues when the device goes (unplugged, crashed): reading one raises
    ``MessageQueue.QueueException``, which was neither a fault nor stopped the arm."""
    cam = _Camera()
    cam.start()
    cam.depth_q.close()
    with pytest.raises(HardwareFault) as err:
        cam.get_frame()
    assert err.value.kind == "camera-disconnected" and "MessageQueue was closed" in str(err.value)
