"""ToF camera inside the bubble: IR amplitude + depth frames with device timestamps.

``ToFCamera`` is the interface the recorder uses. ``QueueToFCamera`` implements it over two
depthai message queues (depth and amplitude ``dai.ImgFrame`` messages, paired by sequence
number); ``DepthaiToFCamera`` feeds it from an OAK ToF device through a depthai v3 pipeline
(``dai.node.ToF``), and the twin ``hw_mocks.fake_camera.SimToFCamera`` from the simulator through
``dai.MessageQueue`` objects on the host, so real and simulated frames go through the same
unpacking code.

Units: ``CameraFrame.depth`` is ``(H,W) uint16`` in ``DEPTH_UNIT_M`` (10 um), 0 = invalid;
``ir`` is ``(H,W) uint16`` amplitude. The OAK ToF node reports depth in millimetres, converted
here (values beyond the uint16 range become 0 = invalid).
Timestamps: ``t_device`` s on the camera's monotonic clock, ``t_host`` s on the bench clock
(depthai's host-synchronized timestamp is on ``time.monotonic``, the real bench clock).

Stall detection: ``get_frame`` raises ``HardwareFault('camera-stall')`` when no complete frame
arrives within ``stall_timeout_s`` (0.5 s by default) on the bench clock (simulated time for the
twin, which may run slower than real time on a loaded machine).
"""

from __future__ import annotations

import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from collect.errors import HardwareFault, InputError
from collect.native_output import folded, native_output_into
from collect.session_format import DEPTH_UNIT_M
from collect.stop_signals import raise_pending_stop

#: Unit of the depth frames the OAK ToF node outputs.
DEPTHAI_TOF_DEPTH_UNIT_M = 1e-3
STALL_TIMEOUT_S = 0.5
#: Slowest frame rate (fps) a camera may run at: below two frames per stall timeout, the gap between
#: two frames reads as a stall.
MIN_FPS = 2.0 / STALL_TIMEOUT_S
#: Polling interval of the frame queues (s of real time).
POLL_S = 0.002


@dataclass(frozen=True)
class CameraFrame:
    """One ToF frame.

    ir (H,W) uint16 amplitude; depth (H,W) uint16 in DEPTH_UNIT_M, 0 = invalid; t_device s
    (camera clock); t_host s (bench clock); seq camera sequence number; true_depth (H,W) float32 m,
    the simulator's true membrane depth (simulated cameras only, else None).
    """

    ir: np.ndarray
    depth: np.ndarray
    t_device: float
    t_host: float
    seq: int
    true_depth: np.ndarray | None = None


def depth_to_session_units(depth: np.ndarray, unit_m: float) -> np.ndarray:
    """Convert a ``(H,W) uint16`` depth image in ``unit_m`` (m per count) to ``(H,W) uint16`` in
    ``DEPTH_UNIT_M``; out of range -> 0 (invalid)."""
    if unit_m == DEPTH_UNIT_M:
        return np.ascontiguousarray(depth, dtype=np.uint16)
    scaled = np.rint(depth.astype(np.float64) * (unit_m / DEPTH_UNIT_M))
    scaled[scaled > np.iinfo(np.uint16).max] = 0
    return scaled.astype(np.uint16)


def unpack_frames(depth_msg, amplitude_msg, depth_unit_m: float) -> CameraFrame:
    """Build a ``CameraFrame`` from a pair of ``dai.ImgFrame`` messages with the same sequence number."""
    depth = depth_msg.getFrame()
    ir = amplitude_msg.getFrame()
    if depth.shape != ir.shape or depth.ndim != 2:
        raise HardwareFault("camera-format", f"camera: depth {depth.shape} and amplitude {ir.shape} frames differ")
    return CameraFrame(
        ir=np.ascontiguousarray(ir, dtype=np.uint16),
        depth=depth_to_session_units(depth, depth_unit_m),
        t_device=depth_msg.getTimestampDevice().total_seconds(),
        t_host=depth_msg.getTimestamp().total_seconds(),
        seq=int(depth_msg.getSequenceNum()),
    )


class ToFCamera(ABC):
    """A ToF camera: ``start()``, ``get_frame()``, ``stop()``; ``serial`` and ``intrinsics()``."""

    serial: str

    @abstractmethod
    def start(self) -> None:
        """Start streaming."""

    @abstractmethod
    def stop(self) -> None:
        """Stop streaming and release the device."""

    @abstractmethod
    def get_frame(self, timeout_s: float | None = None) -> CameraFrame:
        """Next frame in sequence order; ``HardwareFault('camera-stall')`` after ``timeout_s`` of silence."""

    @abstractmethod
    def intrinsics(self) -> dict:
        """``dict(fx, fy, cx, cy, width, height)`` in pixels (+ ``distortion`` list when known)."""


class QueueToFCamera(ToFCamera):
    """A ToF camera reading depth and amplitude ``dai.ImgFrame`` messages from two queues.

    Queues are anything with depthai's ``MessageQueue.tryGet()`` (returns None when empty). A message
    whose partner never came is discarded; its frame is a gap in the sequence numbers, which the
    recorder counts as dropped (``CollectionResult.dropped``).
    """

    def __init__(self, depth_unit_m: float, stall_timeout_s: float = STALL_TIMEOUT_S,
                 clock: Callable[[], float] = time.monotonic):
        self.depth_unit_m = depth_unit_m
        self.stall_timeout_s = stall_timeout_s
        self.clock = clock
        self._depth_q = None
        self._amp_q = None
        self._last_seq: int | None = None
        self._last_t_device = -np.inf

    def _attach(self, depth_queue, amplitude_queue) -> None:
        self._depth_q, self._amp_q = depth_queue, amplitude_queue
        self._last_seq = None

    def _get(self, queue, deadline: float, timeout_s: float):
        """Next message of ``queue``; ``camera-stall`` once the bench clock passes ``deadline``."""
        msg = _try_get(queue)
        while msg is None:
            remaining = deadline - self.clock()
            if remaining <= 0:
                raise HardwareFault("camera-stall", f"camera: no frame for {timeout_s:.2f} s")
            # Poll rather than block in depthai's timed get(): a timed get() on the host can
            # deadlock against a concurrent send() into the same non-blocking queue.
            time.sleep(min(remaining, POLL_S))
            msg = _try_get(queue)
        return msg

    def get_frame(self, timeout_s: float | None = None) -> CameraFrame:
        if self._depth_q is None:
            raise HardwareFault("camera-not-started", "camera: get_frame() before start()")
        timeout_s = self.stall_timeout_s if timeout_s is None else timeout_s
        deadline = self.clock() + timeout_s
        depth_msg = self._get(self._depth_q, deadline, timeout_s)
        amp_msg = self._get(self._amp_q, deadline, timeout_s)
        while depth_msg.getSequenceNum() != amp_msg.getSequenceNum():
            if depth_msg.getSequenceNum() < amp_msg.getSequenceNum():
                depth_msg = self._get(self._depth_q, deadline, timeout_s)
            else:
                amp_msg = self._get(self._amp_q, deadline, timeout_s)
        frame = unpack_frames(depth_msg, amp_msg, self.depth_unit_m)
        if self._last_seq is not None:
            if frame.seq <= self._last_seq or frame.t_device <= self._last_t_device:
                raise HardwareFault("camera-clock", f"camera: frame {frame.seq} at {frame.t_device:.6f} s is not "
                                                    f"after frame {self._last_seq} at {self._last_t_device:.6f} s")
        self._last_seq, self._last_t_device = frame.seq, frame.t_device
        return frame


def _try_get(queue):
    """``queue.tryGet()``; a queue that cannot be read any more is ``HardwareFault('camera-disconnected')``:
    depthai raises ``MessageQueue.QueueException`` once the device closed its queues (unplugged,
    crashed) and ``RuntimeError`` on a link error (was: neither stopped the arm, and the run ended
    with a traceback)."""
    try:
        return queue.tryGet()
    except Exception as err:  # noqa: BLE001 - every way a queue read fails is the camera gone
        raise HardwareFault("camera-disconnected",
                            f"camera: the device stopped streaming ({type(err).__name__}: {err})") from None


#: What depthai printed to the console while it was imported (in a container without
#: ``/dev/bus/usb``: ``[depthai] [warning] USB protocol not available ...``): held back, and named
#: in the fault of a device that cannot be opened, where it is the likely cause.
DEPTHAI_IMPORT_SAID: list[str] = []


def import_depthai():
    """The ``depthai`` module; the first import's console lines go to ``DEPTHAI_IMPORT_SAID``
    instead of the console (a bad bench file is then reported as one line, with nothing before it).
    A Ctrl-C during that import, which depthai turns into ``ImportError: initialization failed``,
    ends the command as the stop it is (was: that traceback, exit 1)."""
    if "depthai" not in sys.modules:
        with native_output_into(DEPTHAI_IMPORT_SAID, pass_on=False):
            try:
                import depthai  # noqa: F401
            except ImportError:
                raise_pending_stop()
                raise
    return sys.modules["depthai"]


def check_tof_profile(profile: str, who: str) -> None:
    """Raise ``InputError`` (``"{who}: unknown ToF profile ..."``) unless ``profile`` names a
    ``dai.ToFConfig.Profile`` of the installed depthai. Needs no device: a bench file is checked
    with it before anything connects, and the camera again before it opens the device."""
    names = import_depthai().ToFConfig.Profile.__members__
    if profile not in names:
        raise InputError(f"{who}: unknown ToF profile '{profile}' (one of {', '.join(names)})")


class DepthaiToFCamera(QueueToFCamera):
    """An OAK ToF camera (depthai v3, ``dai.node.ToF``): depth + amplitude outputs.

    device_id: depthai device id (MxId / IP / name); None = first device found. fps: requested
    frame rate. profile: ``dai.ToFConfig.Profile`` name (LOW_RANGE suits the ~55-100 mm bubble).
    """

    def __init__(self, device_id: str | None = None, fps: float = 45.0, profile: str = "LOW_RANGE",
                 stall_timeout_s: float = STALL_TIMEOUT_S):
        super().__init__(DEPTHAI_TOF_DEPTH_UNIT_M, stall_timeout_s, time.monotonic)
        self.device_id = device_id
        self.fps = fps
        self.profile = profile
        self.serial = device_id or ""
        self._pipeline = None
        self._device = None
        self._intrinsics: dict | None = None

    def start(self) -> None:
        check_tof_profile(self.profile, "camera")
        dai = import_depthai()
        library_said: list[str] = []
        try:
            with native_output_into(library_said):  # depthai's own "no device" line
                device = dai.Device(dai.DeviceInfo(self.device_id)) if self.device_id else dai.Device()
        except RuntimeError as err:
            said = folded(DEPTHAI_IMPORT_SAID + library_said)
            raise HardwareFault("camera-missing", f"camera: cannot open the OAK ToF device: {err}{said}") from err
        device_id = device.getDeviceId()
        try:
            self._start_on(dai, device)
            self._device = device
        except BaseException as err:  # the device closed whatever failed: a later attempt finds it free
            device.close()
            if isinstance(err, RuntimeError):  # depthai's (XLinkError, EepromError: a calibration, a pipeline)
                raise HardwareFault("camera-setup", f"camera: cannot set the ToF pipeline up on device "
                                                    f"{device_id}: {err}") from err
            raise

    def _start_on(self, dai, device) -> None:
        """Read ``device``'s ToF camera and calibration, then build and start the pipeline."""
        tof_cams = [c for c in device.getConnectedCameraFeatures() if dai.CameraSensorType.TOF in c.supportedTypes]
        if not tof_cams:
            raise HardwareFault("camera-missing", f"camera: device {device.getDeviceId()} has no ToF sensor")
        cam = tof_cams[0]
        calib = device.readCalibration()
        k = np.asarray(calib.getCameraIntrinsics(cam.socket, cam.width, cam.height), dtype=float)
        # the frames come undistorted (below): the pinhole intrinsics alone lift them, no distortion applies
        self._intrinsics = {
            "fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
            "width": int(cam.width), "height": int(cam.height),
        }
        self.serial = device.getDeviceId()
        pipeline = dai.Pipeline(device)
        tof = pipeline.create(dai.node.ToF).build(cam.socket, dai.ToFConfig.Profile.__members__[self.profile], self.fps)
        config = tof.getInitialConfig()
        config.enableOpticalCorrection = True  # depth along the optical axis (the sessions' depth), not along each ray
        config.enableDistortionCorrection = True  # undistorted depth and amplitude (depthai's default, made explicit)
        tof.setInitialConfig(config)
        self._attach(tof.depth.createOutputQueue(maxSize=8, blocking=False),
                     tof.amplitude.createOutputQueue(maxSize=8, blocking=False))
        pipeline.start()
        self._pipeline = pipeline

    def stop(self) -> None:
        if self._pipeline is not None:
            self._pipeline.stop()
            self._pipeline = None
        if self._device is not None:  # a pipeline built on a given device may leave it open
            self._device.close()
            self._device = None

    def intrinsics(self) -> dict:
        if self._intrinsics is None:
            raise HardwareFault("camera-not-started", "camera: intrinsics() before start()")
        return dict(self._intrinsics)
