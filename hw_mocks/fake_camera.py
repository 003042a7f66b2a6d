"""Twin of the OAK ToF camera: frames rendered by the bubble simulator, delivered as depthai messages.

``SimCameraDevice`` plays the device: a thread renders frame ``k`` at simulated time
``k / spec.fps`` from the bench's latest membrane solution (``SimBench.latest``: solved by the
physics thread at most one frame period earlier) with fresh sensor noise,
packs depth and amplitude into ``dai.ImgFrame`` messages (RAW16, device timestamp, host-synced
timestamp, sequence number) and sends them into two non-blocking ``dai.MessageQueue`` objects,
which drop the oldest message when full, as a device's output queues do.
``SimToFCamera`` is ``collect.camera.QueueToFCamera`` over those queues: the recorder gets its
frames through the same unpacking code as from a real OAK, plus the simulator's true depth.

The simulated sensor reports depth directly in ``DEPTH_UNIT_M`` (10 um), not in the OAK's
millimetres, so that the simulated depth noise (~0.05 mm) is not lost to rounding.
Device clock: simulated time plus a per-device boot offset; host timestamps: simulated time.
Faults: ``camera-stall`` stops the frames for good (the device keeps time: ``SimBench.pace``).
"""

from __future__ import annotations

import collections
import dataclasses
import datetime
import os
import threading

import numpy as np

from collect.camera import STALL_TIMEOUT_S, CameraFrame, QueueToFCamera, import_depthai
from collect.loop_thread import LoopThread
from collect.session_format import DEPTH_UNIT_M

# depthai warns at import that no USB device can be reached: irrelevant for the simulated device.
os.environ.setdefault("DEPTHAI_LEVEL", "error")

QUEUE_SIZE = 8
#: How many recent frames' true depth the device keeps for the camera to attach.
TRUE_DEPTH_KEEP = 32
#: The camera's name in the bench's pacing (``SimBench.pace``).
PACE_NAME = "camera"


def img_frame(image: np.ndarray, seq: int, t_device: float, t_host: float):
    """A depthai ``ImgFrame`` (RAW16) as an OAK sends it: ``image`` (H,W) uint16, sequence number,
    device and host time stamps in s."""
    dai = import_depthai()

    msg = dai.ImgFrame()
    msg.setType(dai.ImgFrame.Type.RAW16)
    msg.setWidth(image.shape[1])
    msg.setHeight(image.shape[0])
    msg.setData(np.ascontiguousarray(image, dtype=np.uint16).view(np.uint8).reshape(-1))
    msg.setSequenceNum(seq)
    msg.setTimestampDevice(datetime.timedelta(seconds=t_device))
    msg.setTimestamp(datetime.timedelta(seconds=t_host))
    return msg


class SimCameraDevice:
    """The simulated ToF device of ``scene`` (a ``SimBench``): renders at ``scene.spec.fps``."""

    def __init__(self, scene, seed: int = 0, queue_size: int = QUEUE_SIZE):
        dai = import_depthai()

        self.scene = scene
        self.fps = float(scene.spec.fps)
        self._rng = np.random.default_rng(seed)
        self.boot_offset_s = 1.0 + float(self._rng.uniform(0.0, 100.0))
        self.depth_queue = dai.MessageQueue("depth", queue_size, False)
        self.amplitude_queue = dai.MessageQueue("amplitude", queue_size, False)
        self._true_depth: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._lock = threading.Lock()
        self._loop = LoopThread(self._run, "sim-camera")

    def start(self) -> None:
        """Start sending frames (from the next multiple of the frame period)."""
        self._loop.start()

    def stop(self) -> None:
        """Stop sending frames."""
        self._loop.stop()

    def true_depth(self, seq: int) -> np.ndarray | None:
        """True membrane depth ``(H,W) float32 m`` of a recent frame, or None once forgotten."""
        with self._lock:
            return self._true_depth.get(seq)

    def render(self, seq: int, t: float) -> tuple:
        """Depth and amplitude messages of frame ``seq`` at simulated time ``t``, and its true depth."""
        state = self.scene.frame_solution(t).state
        ir, depth = self.scene.sim.render(state, self._rng)
        t_device = t + self.boot_offset_s
        return (img_frame(depth, seq, t_device, t), img_frame(ir, seq, t_device, t),
                np.asarray(state.true_depth, dtype=np.float32))

    def _run(self) -> None:
        clock = self.scene.clock
        period = 1.0 / self.fps
        # Frames start on the next multiple of the frame period (the sensor free-runs from boot).
        seq = int(np.ceil(clock.now() / period))
        try:
            while not self._loop.stop_event.is_set():
                t = seq * period
                self.scene.pace(PACE_NAME, t)
                if not clock.sleep_until(t, self._loop.stop_event):
                    return
                if not self.scene.fault_active("camera-stall", t):  # a stalled device sends nothing
                    self._send(seq, t)
                seq += 1
        finally:
            self.scene.pace(PACE_NAME, None)

    def _send(self, seq: int, t: float) -> None:
        depth_msg, amp_msg, true_depth = self.render(seq, t)
        with self._lock:
            self._true_depth[seq] = true_depth
            while len(self._true_depth) > TRUE_DEPTH_KEEP:
                self._true_depth.popitem(last=False)
        _send_without_drop(self.depth_queue, depth_msg)
        _send_without_drop(self.amplitude_queue, amp_msg)


def _send_without_drop(queue, msg) -> None:
    """Send ``msg`` into a non-blocking ``dai.MessageQueue``, making room first if it is full.

    On a full queue depthai's ``send()`` drops the oldest message itself, with the GIL released and
    the queue's lock held, and freeing a message made in Python takes the GIL. A reader in
    ``tryGet()`` holds the GIL while it waits for that lock: the two threads deadlock (seen once as a
    hung test). Taking the oldest message out here, with the GIL held, keeps ``send()`` from ever
    dropping one (the reader only takes messages out, so the room stays).
    """
    if queue.isFull():
        queue.tryGet()
    queue.send(msg)


class SimToFCamera(QueueToFCamera):
    """``ToFCamera`` of the simulated bench: serial and intrinsics from the sensor spec."""

    def __init__(self, scene, seed: int = 0, stall_timeout_s: float = STALL_TIMEOUT_S):
        super().__init__(DEPTH_UNIT_M, stall_timeout_s, scene.clock)
        self.scene = scene
        self.serial = f"SIM-TOF-{scene.spec.serial}"
        self.device = SimCameraDevice(scene, seed)

    def start(self) -> None:
        self._attach(self.device.depth_queue, self.device.amplitude_queue)
        self.device.start()

    def stop(self) -> None:
        self.device.stop()

    def intrinsics(self) -> dict:
        return self.scene.spec.intrinsics()

    def get_frame(self, timeout_s: float | None = None) -> CameraFrame:
        frame = super().get_frame(timeout_s)
        return dataclasses.replace(frame, true_depth=self.device.true_depth(frame.seq))
