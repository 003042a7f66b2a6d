"""The OAK camera driver must keep to the installed depthai's API (v3), which no simulated run calls.

``collect.camera.DepthaiToFCamera.start`` opens a real device; the simulated bench never runs it.
Each call it makes is checked here against the installed depthai: the names exist and an overload
takes the arguments in the order and of the types the driver passes (pybind11 signatures in the
docstrings). No device is opened.
"""

from __future__ import annotations

import re

import depthai as dai
import pytest

from collect.camera import DepthaiToFCamera
from test_drivers_rtde_signatures import split_top_level


def _overloads(func) -> list[str]:
    """The signature lines of a pybind11 function's docstring, ``name(self: T, a: A = d, ...) -> R``."""
    name = func.__name__
    lines = [line.strip() for line in (func.__doc__ or "").splitlines()]
    lines = [re.sub(r"^\d+\. ", "", line) for line in lines]
    return [line for line in lines if line.startswith(f"{name}(") and "*args, **kwargs" not in line]


#: (callable, what the driver passes, in order): each must match one overload's parameters after self.
CALLS = [
    (dai.DeviceInfo.__init__, [r"deviceIdOrName: str"]),                                # DeviceInfo(device_id)
    (dai.Device.__init__, []),                                                            # Device()
    (dai.Device.__init__, [r"deviceInfo: depthai\.DeviceInfo"]),                          # Device(DeviceInfo)
    (dai.Device.getConnectedCameraFeatures, []),
    (dai.Device.readCalibration, []),
    (dai.Device.getDeviceId, []),
    (dai.Device.close, []),
    (dai.CalibrationHandler.getCameraIntrinsics,
     [r"cameraId: depthai\.CameraBoardSocket", r"resizeWidth: int", r"resizeHeight: int"]),
    (dai.Pipeline.__init__, [r"defaultDevice: depthai\.Device"]),                         # Pipeline(device)
    (dai.node.ToF.build,
     [r"boardSocket: depthai\.CameraBoardSocket", r"profile: depthai\.ToFConfig\.Profile", r"fps: Optional\[float\]"]),
    (dai.node.ToF.getInitialConfig, []),
    (dai.node.ToF.setInitialConfig, [r"arg0: depthai\.ToFConfig"]),
    (dai.Node.Output.createOutputQueue, [r"maxSize: int", r"blocking: bool"]),
    (dai.Pipeline.start, []),
    (dai.Pipeline.stop, []),
]


def _params(signature: str) -> list[str]:
    """``name: type [= default]`` of each parameter after self."""
    return split_top_level(signature[signature.index("(") + 1: signature.rindex(") ->")])[1:]


def _accepts(signature: str, passed: list[str]) -> bool:
    """The overload takes ``passed`` positionally, and whatever follows has a default."""
    params = _params(signature)
    if len(params) < len(passed):
        return False
    return (all(re.match(want, got) for want, got in zip(passed, params))
            and all(" = " in rest for rest in params[len(passed):]))


@pytest.mark.parametrize("func,passed", CALLS, ids=lambda v: getattr(v, "__qualname__", None) or ",".join(v) or "()")
def test_each_depthai_call_of_the_camera_driver_has_a_matching_overload(func, passed):
    overloads = _overloads(func)
    assert overloads, f"{func.__qualname__}: no signature in its docstring"
    assert any(_accepts(sig, passed) for sig in overloads), (func.__qualname__, passed, overloads)


def test_the_attributes_and_enums_the_camera_driver_reads_exist():
    assert DepthaiToFCamera().profile in dai.ToFConfig.Profile.__members__  # the default profile
    assert hasattr(dai.CameraSensorType, "TOF")
    for attr in ("socket", "width", "height", "supportedTypes"):
        assert hasattr(dai.CameraFeatures, attr)
    for output in ("depth", "amplitude"):
        assert getattr(dai.node.ToF, output).fget.__doc__.strip().endswith("-> depthai.Node.Output")
    assert callable(dai.Pipeline.create)
    config = dai.ToFConfig()  # the corrections the driver switches on are settable booleans
    for flag in ("enableOpticalCorrection", "enableDistortionCorrection"):
        setattr(config, flag, True)
        assert getattr(config, flag) is True


def test_a_camera_that_fails_after_it_opened_is_closed_and_a_fault(monkeypatch):
    """Was: only opening the device was guarded; depthai's RuntimeError from the calibration or the
    pipeline was a traceback, and the device stayed open (a later attempt in the process found it busy)."""
    import collect.camera as camera
    from collect.errors import HardwareFault

    class Device:
        closed = False

        def __init__(self, *args):
            pass

        def getConnectedCameraFeatures(self):
            return [type("Features", (), {"supportedTypes": [dai.CameraSensorType.TOF]})()]

        def readCalibration(self):
            raise RuntimeError("There is no Intrinsic data available in the EEPROM")

        def getDeviceId(self):
            return "18443010E1"

        def close(self):
            Device.closed = True

    fake = type("depthai", (), {"Device": Device, "DeviceInfo": lambda *a: None,
                                "CameraSensorType": dai.CameraSensorType, "ToFConfig": dai.ToFConfig})
    monkeypatch.setattr(camera, "import_depthai", lambda: fake)
    with pytest.raises(HardwareFault) as err:
        DepthaiToFCamera("18443010E1").start()
    assert err.value.kind == "camera-setup" and "no Intrinsic data" in str(err.value) and Device.closed
