"""The bench: arm + ToF camera + pressure board, real or simulated, chosen by configuration.

This is the one module that knows real from simulated hardware. A ``BenchConfig`` is a dataclass
registered under a type name (like lerobot's robot configs): ``'ur'`` (a UR arm over ur_rtde,
an OAK ToF camera over depthai, the pressure board on a serial port) or ``'sim'`` (the twins of
``hw_mocks`` on one ``SimBench``). ``open_bench(config)`` opens every device and yields a
``Bench``; whatever happens inside the ``with`` block, the arm is stopped and retracted
(``safe_stop``) and every device closed on the way out.

Objects: both types place the named objects with ``hw_mocks.objects.fixture_plate`` (the plate
layout is geometry shared by the real fixture and the simulation: a row along base y centred at
x = ``PLATE_X``, on the plate top z = ``PLATE_Z``); a real bench adds ``plate_pose``, the pose of
that row's centre on its plate in the robot base frame, to which the layout is moved.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from collect.arm import STATE_HZ_RANGE, Arm, MotionSettings, check_motion_settings
from collect.camera import MIN_FPS, ToFCamera, check_tof_profile
from collect.errors import HardwareFault, InputError
from collect.native_output import folded, native_output_into
from collect.numbers import real_number, real_numbers, whole_number
from collect.output_files import exclusive_lock
from collect.pressure_board import PressureBoard
from collect.safety import MAX_ROTATION_RAD, SafetyLimits, rotation_vector_ok
from collect.stop_signals import raise_pending_stop

log = logging.getLogger(__name__)

#: The objects of the standard fixture plate (built-in simulated objects of the same names).
DEFAULT_OBJECTS = ("mug", "wine_glass", "box", "fingers")
#: RTDE rates (Hz) a UR controller serves: up to 500 Hz on e-Series (CB3: 125 Hz). Lower rates,
#: which ur_rtde would serve, are refused: the arm's samples (``STATE_HZ_RANGE``) would repeat stale
#: data between updates, and below 4 Hz the monitor takes a still clock for a dead link.
RTDE_HZ_RANGE = (125.0, 500.0)
#: Frame rates (fps) of the OAK ToF camera: its 33D sensor runs at up to 80 fps (depthai's RVC2
#: driver limit), and below ``MIN_FPS`` the camera driver would see a stall.
CAMERA_FPS_RANGE = (MIN_FPS, 80.0)


def arm_lock(robot_ip: str) -> contextlib.AbstractContextManager:
    """Hold the arm at ``robot_ip`` for one process of this machine (``exclusive_lock`` on
    ``<temp dir>/bubble-arm-<robot_ip>.lock``, readable by every user), refused at once with
    ``InputError`` while another holds it. A second ur_rtde control interface would upload its own
    control script and so end the first process's motion halfway through a press."""
    path = Path(tempfile.gettempdir()) / f"bubble-arm-{re.sub(r'[^A-Za-z0-9._-]', '_', robot_ip)}.lock"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:  # left by an earlier run (it stays; the lock, not the file, says "in use")
        pass
    else:
        os.fchmod(fd, 0o644)  # whatever the umask: another user's run must be able to take the lock
        os.close(fd)
    busy = InputError(f"arm {robot_ip} is driven by another bubble process on this machine (bubble "
                      "collect or bubble commission); wait until it has finished")
    return exclusive_lock(path, busy)


def _within(value, lo: float, hi: float) -> bool:
    """Whether ``value`` is a finite real number (not a bool or a string) in ``[lo, hi]``."""
    return real_number(value) and lo <= value <= hi


def _check_pose(type_name: str, name: str, pose, what: str) -> None:
    """InputError unless ``pose`` is 6 finite numbers (m, rotation vector rad, at most one turn long)."""
    if not real_numbers(pose, 6):
        raise InputError(f"bench '{type_name}': {name} ({what}) must be 6 numbers [x, y, z, rx, ry, rz] "
                         f"(m, rotation vector in rad), got {pose!r}")
    if not rotation_vector_ok(pose):
        raise InputError(f"bench '{type_name}': {name} rotation vector {list(pose[3:])!r} is longer than "
                         f"{MAX_ROTATION_RAD:.4g} rad (one turn): give it in radians")


@dataclass
class BenchConfig(ABC):
    """Settings common to every bench; subclasses register under ``type`` with ``BenchConfig.register``.

    objects: built-in object names or mesh paths, placed on the fixture plate in this order (one
    string is one name: YAML ``objects: mug``). limits: safety limits (None: the defaults;
    a workspace corner left unset is fitted around the objects, ``workspace_limits``).
    motion: speeds of the pressing motions. state_hz: arm state sampling rate (125-500 Hz).
    """

    _registry: ClassVar[dict[str, type["BenchConfig"]]] = {}
    type: ClassVar[str] = ""

    objects: tuple[str, ...] = DEFAULT_OBJECTS
    limits: SafetyLimits | None = None
    motion: MotionSettings = field(default_factory=MotionSettings)
    state_hz: float = 125.0

    def __post_init__(self):
        names = (str, os.PathLike)
        if isinstance(self.objects, names):  # one name, not a sequence of letters
            self.objects = (self.objects,)
        if not isinstance(self.objects, (list, tuple)) or not all(isinstance(o, names) for o in self.objects):
            raise InputError(f"bench '{self.type}': objects must be a list of object names or mesh paths, "
                             f"got {self.objects!r}")
        self.objects = tuple(os.fspath(o) for o in self.objects)
        if not self.objects:  # a bench file's `objects: []` (was: "--objects is empty", a flag never given)
            raise InputError(f"bench '{self.type}': objects is empty: name at least one object or mesh path")
        lo, hi = STATE_HZ_RANGE
        if not _within(self.state_hz, lo, hi):
            raise InputError(f"bench '{self.type}': state_hz {self.state_hz!r} is outside {lo:g}..{hi:g} Hz "
                             "(the arm's state sampling rate)")
        # before any device opens; with no limits given, against the defaults that the arm will get (their
        # speeds, accelerations and forces; only the workspace box is fitted later). Was: only with limits
        # given, otherwise in open(), after the simulated bench's threads or the robot's connection had started
        check_motion_settings(self.motion, self.limits or SafetyLimits())

    @classmethod
    def register(cls, name: str) -> Callable[[type], type]:
        """Class decorator registering a config type under ``name``."""

        def wrap(sub: type) -> type:
            sub.type = name
            cls._registry[name] = sub
            return sub

        return wrap

    @classmethod
    def create(cls, type_name: str, **kwargs) -> "BenchConfig":
        """The config of registered type ``type_name`` with ``kwargs``; ``InputError`` for unknown types/fields."""
        return cls._created(type_name, kwargs)

    @classmethod
    def _created(cls, type_name: str, fields_given: dict) -> "BenchConfig":
        """``create`` with the fields as a mapping, whose keys may be of any type (a YAML file's ``1:``
        is an unknown field; was, through ``**``, a TypeError traceback)."""
        if type_name not in cls._registry:
            raise InputError(f"unknown bench type '{type_name}' (one of {', '.join(cls._registry)})")
        return _built(cls._registry[type_name], fields_given, f"bench '{type_name}'")

    @classmethod
    def from_dict(cls, data: dict, source: str = "bench config") -> "BenchConfig":
        """A config from a plain mapping with ``type`` plus the fields of that type; ``limits`` and
        ``motion`` are mappings of ``SafetyLimits`` / ``MotionSettings`` fields. ``InputError`` if bad."""
        if not isinstance(data, dict) or "type" not in data:
            raise InputError(f"{source}: expected a mapping with 'type' ({', '.join(cls._registry)})")
        kwargs = dict(data)
        type_name = str(kwargs.pop("type"))
        for key, sub in (("limits", SafetyLimits), ("motion", MotionSettings)):
            if key in kwargs and kwargs[key] is not None:
                if not isinstance(kwargs[key], dict):
                    raise InputError(f"{source}: '{key}' must be a mapping of {sub.__name__} fields")
                kwargs[key] = _built(sub, {k: tuple(v) if isinstance(v, list) else v for k, v in kwargs[key].items()},
                                     f"{source}: {key}")
        for key, value in kwargs.items():
            if isinstance(value, list):
                kwargs[key] = tuple(value)
        return cls._created(type_name, kwargs)

    @classmethod
    def from_yaml(cls, path) -> "BenchConfig":
        """Read a config YAML file (see ``from_dict``); ``InputError`` for a missing or bad file."""
        from collect.yaml_files import read_yaml_file

        return cls.from_dict(read_yaml_file(path, "bench config"), source=f"bench config {path}")

    @abstractmethod
    def open(self) -> "Bench":
        """Open every device of this bench."""


def _built(config_type: type, kwargs: dict, who: str):
    """``config_type(**kwargs)`` for a dataclass whose fields all have defaults; ``InputError``
    ``"{who}: unknown field '...' (fields: ...)"`` for a key that is not one of its fields."""
    names = [f.name for f in fields(config_type) if f.init]
    unknown = sorted(set(kwargs) - set(names), key=str)
    if unknown:
        raise InputError(f"{who}: unknown field '{unknown[0]}' (fields: {', '.join(names)})")
    return config_type(**kwargs)


def _placed_objects(names, plate_pose=None) -> list:
    """The objects ``names`` on the fixture plate (``fixture_plate``'s row, centred at x = ``PLATE_X``
    on z = ``PLATE_Z``), moved so that the row's centre is at ``plate_pose`` (6,) (base frame; None:
    where the layout puts it). Was: ``plate_pose`` applied to the layout's own frame, 0.45 m before the
    row's centre, so a plate given by its measured centre put every object 0.45 m out."""
    from hw_mocks.objects import PLATE_X, PLATE_Z, fixture_plate, load_object
    from collect.transforms import invert, matrix_to_pose, pose_to_matrix

    placed = fixture_plate([load_object(n) for n in names])
    if plate_pose is None:
        return placed
    move = pose_to_matrix(plate_pose) @ invert(pose_to_matrix([PLATE_X, 0.0, PLATE_Z, 0.0, 0.0, 0.0]))
    return [o.placed(matrix_to_pose(move @ o.object_to_base())) for o in placed]


def workspace_limits(objects, base: SafetyLimits | None = None) -> SafetyLimits:
    """``base`` limits (None: the defaults) with each workspace corner they leave unset fitted around ``objects``:
    150 mm around their footprints, from the plate top (the membrane apex may reach down to it
    around a flat object; the force limit guards the press) to 250 mm above the tallest. A bench
    file's ``limits`` that lowers the force alone keeps the fitted box (was: a 1.2 m box from the
    robot's base plane)."""
    lo = np.min([o.bounds_base()[0] for o in objects], axis=0)
    hi = np.max([o.bounds_base()[1] for o in objects], axis=0)
    plate_z = min(o.fixture_pose[2] for o in objects)
    fitted_min = (float(lo[0] - 0.15), float(lo[1] - 0.15), float(plate_z))
    fitted_max = (float(hi[0] + 0.15), float(hi[1] + 0.15), float(hi[2] + 0.25))
    base = base or SafetyLimits()
    return replace(base, workspace_min=base.workspace_min or fitted_min, workspace_max=base.workspace_max or fitted_max)


@BenchConfig.register("ur")
@dataclass
class URBenchConfig(BenchConfig):
    """A real bench. robot_ip: UR controller; rtde_hz: RTDE frequency (Hz, ``RTDE_HZ_RANGE``; 500 on
    e-Series); camera_id: depthai device id (None = first found); camera_fps (``CAMERA_FPS_RANGE``);
    tof_profile; serial_port: the pressure board's device (e.g. /dev/ttyACM0); plate_pose (6,): the
    pose of the fixture plate's centre (the middle of the object row, on the plate top) in the base
    frame, None: [0.45, 0, 0, 0, 0, 0] (``_placed_objects``); home_pose (6,): safe TCP pose above the plate.
    Every field (the rates and the ToF profile's name included) is checked when the config is
    built, before any device is opened."""

    robot_ip: str = ""
    rtde_hz: float = 500.0
    camera_id: str | None = None
    camera_fps: float = 45.0
    tof_profile: str = "LOW_RANGE"
    serial_port: str = "/dev/ttyACM0"
    plate_pose: tuple[float, ...] | None = None
    home_pose: tuple[float, ...] | None = None

    def __post_init__(self):
        super().__post_init__()
        lo, hi = RTDE_HZ_RANGE
        if not _within(self.rtde_hz, lo, hi):
            raise InputError(f"bench 'ur': rtde_hz {self.rtde_hz!r} is outside {lo:g}..{hi:g} Hz "
                             f"(the RTDE rates of a UR controller)")
        lo, hi = CAMERA_FPS_RANGE
        if not _within(self.camera_fps, lo, hi):
            raise InputError(f"bench 'ur': camera_fps {self.camera_fps!r} is outside {lo:g}..{hi:g} fps "
                             f"(the OAK ToF camera's frame rates)")
        if isinstance(self.camera_id, int) and not isinstance(self.camera_id, bool):
            self.camera_id = str(self.camera_id)  # YAML reads an all-digit device name as a number
        for name, what in (("robot_ip", "the UR controller's IP address or host name"),
                           ("camera_id", "the OAK device's MxId, IP or name; leave it out for the first one found"),
                           ("tof_profile", "a dai.ToFConfig.Profile name, e.g. LOW_RANGE"),
                           ("serial_port", "the pressure board's device, e.g. /dev/ttyACM0")):
            value = getattr(self, name)
            if not (isinstance(value, str) or name == "camera_id" and value is None):
                raise InputError(f"bench 'ur': {name} must be text ({what}), got {value!r}")
        check_tof_profile(self.tof_profile, "bench 'ur'")
        if self.plate_pose is not None:
            _check_pose("ur", "plate_pose", self.plate_pose, "the fixture plate's centre in the base frame")
        if self.home_pose is not None:
            _check_pose("ur", "home_pose", self.home_pose, "a safe TCP pose above the plate")

    def open(self) -> "Bench":
        if not self.robot_ip:
            raise InputError("bench 'ur': robot_ip is required")
        if self.home_pose is None:
            raise InputError("bench 'ur': home_pose (a safe TCP pose above the plate) is required")
        import rtde_control
        import rtde_receive

        from collect.camera import DepthaiToFCamera

        objects = _placed_objects(self.objects, self.plate_pose)
        limits = workspace_limits(objects, self.limits)
        home = limits.check_pose(self.home_pose)
        library_said: list[str] = []
        with contextlib.ExitStack() as held:
            held.enter_context(arm_lock(self.robot_ip))  # before connecting: a second control interface takes the arm over
            try:
                with native_output_into(library_said):
                    receive = rtde_receive.RTDEReceiveInterface(self.robot_ip, self.rtde_hz)
                    control = rtde_control.RTDEControlInterface(self.robot_ip, self.rtde_hz)
            except RuntimeError as err:
                raise HardwareFault("arm-disconnected",
                                    f"arm: cannot connect to {self.robot_ip}: {err}{folded(library_said)}") from err
            return Bench(arm=Arm(control, receive, limits, settings=self.motion, state_hz=self.state_hz),
                         camera=DepthaiToFCamera(self.camera_id, self.camera_fps, self.tof_profile),
                         pressure=PressureBoard(self.serial_port), objects=objects, home_pose=home, simulated=False,
                         held=held.pop_all())


@BenchConfig.register("sim")
@dataclass
class SimBenchConfig(BenchConfig):
    """The simulated bench. sensor: a SensorSpec, a spec YAML path, or None (``draw_sensor(seed)``);
    seed: scene/noise seed; faults: ``KIND@SECONDS`` strings or ``SimFault``s; speed: clock factor;
    start_pose (6,): where the simulated arm starts, inside the workspace box (m + rotvec; None: the
    home pose above the plate)."""

    sensor: object = None
    seed: int = 0
    faults: tuple = ()
    speed: float = 1.0
    start_pose: tuple[float, ...] | None = None

    def __post_init__(self):
        from hw_mocks.sensor_spec import SensorSpec
        from hw_mocks.sim_bench import SimFault

        super().__post_init__()
        if not (self.sensor is None or isinstance(self.sensor, (str, os.PathLike, SensorSpec))):
            raise InputError(f"bench 'sim': sensor must be a sensor spec YAML path (leave it out to draw one "
                             f"from seed), got {self.sensor!r}")
        if not whole_number(self.seed):
            raise InputError(f"bench 'sim': seed must be a whole number >= 0, got {self.seed!r}")
        if isinstance(self.faults, str):  # one fault, not a sequence of letters
            self.faults = (self.faults,)
        if not (isinstance(self.faults, (list, tuple)) and all(isinstance(f, (str, SimFault)) for f in self.faults)):
            raise InputError(f"bench 'sim': faults must be a list of KIND@SECONDS strings, got {self.faults!r}")

    def open(self) -> "Bench":
        from hw_mocks.fake_camera import SimToFCamera
        from hw_mocks.fake_rtde import FakeRTDEControl, FakeRTDEReceive
        from hw_mocks.pressure_firmware import PressureFirmware
        from hw_mocks.sensor_spec import SensorSpec, draw_sensor
        from hw_mocks.sim_bench import SimBench, SimFault, parse_sim_fault

        if self.sensor is None:
            spec = draw_sensor(self.seed)
        elif isinstance(self.sensor, SensorSpec):
            spec = self.sensor
        else:
            spec = SensorSpec.from_yaml(Path(self.sensor))
        faults = [f if isinstance(f, SimFault) else parse_sim_fault(f) for f in self.faults]
        objects = _placed_objects(self.objects)
        limits = workspace_limits(objects, self.limits)
        start = None if self.start_pose is None else limits.check_pose(self.start_pose)
        scene = SimBench(spec, objects, seed=self.seed, faults=faults, speed=self.speed, start_pose=start)
        with contextlib.ExitStack() as started:  # stopped again when the bench cannot be made (was: a camera
            # whose import failed left the physics and firmware threads running in the process, for good)
            scene.start()
            started.callback(scene.stop)
            firmware = PressureFirmware(scene, seed=self.seed)
            firmware.start()
            started.callback(firmware.stop)
            arm = Arm(FakeRTDEControl(scene.arm), FakeRTDEReceive(scene.arm), limits, settings=self.motion,
                      clock=scene.clock, state_hz=self.state_hz)
            bench = Bench(arm=arm, camera=SimToFCamera(scene, self.seed),
                          pressure=PressureBoard(firmware.port, clock=scene.clock), objects=objects,
                          home_pose=scene.home_pose, simulated=True, sim=scene, firmware=firmware)
            started.pop_all()
            return bench


class Bench:
    """Open devices of one bench.

    arm: ``collect.arm.Arm``; camera: ``ToFCamera``; pressure: ``PressureBoard``;
    objects: placed ``BenchObject``s; home_pose (6,); simulated: bool; sim: the ``SimBench``
    (simulated only); clock: the bench clock (s) shared by every timestamp.
    After ``start()``: intrinsics (dict), sensor_serial (the pressure board's ``ID?``), started_at
    (the bench clock as the devices started, s: before any of their timestamps).
    """

    def __init__(self, *, arm: Arm, camera: ToFCamera, pressure: PressureBoard, objects, home_pose,
                 simulated: bool, sim=None, firmware=None, held: contextlib.ExitStack | None = None):
        self.arm = arm
        self.camera = camera
        self.pressure = pressure
        self.objects = objects
        self.home_pose = np.asarray(home_pose, dtype=float)
        self.simulated = simulated
        self.sim = sim
        self._firmware = firmware
        self.clock = arm.clock
        self.intrinsics: dict = {}
        self.sensor_serial = ""
        self.started_at: float | None = None
        self.limits = arm.limits
        self._unretracted = ""  # why the last safe stop could not retract ("" after a retract)
        self._held = held or contextlib.ExitStack()  # released by close(): the arm lock of a real bench

    def start(self) -> None:
        """Open the pressure board, start the camera and the arm monitor; read serial and intrinsics."""
        self.started_at = self.clock()
        self.pressure.open()
        self.sensor_serial = self.pressure.identify()
        self.camera.start()
        self.intrinsics = self.camera.intrinsics()
        self.arm.start()
        if self.sim is not None:
            self.sim.devices_streaming()

    def check(self) -> None:
        """Raise the first pending device fault (arm monitor, pressure board)."""
        self.arm.check()
        self.pressure.check()

    def safe_stop(self) -> bool:
        """Stop the arm and retract it from the object; True when it retracted.

        Used on every fault and on Ctrl-C; never raises. A robot in protective stop cannot move: the
        failure to retract is logged (the operator clears the stop on the pendant) and False returned.
        """
        try:
            self.arm.stop()
            self.arm.retract()
            self._unretracted = ""
            return True
        except Exception as err:  # InputError: the retract broke a safety limit; anything else: logged, not raised
            said = str(err) if isinstance(err, (HardwareFault, InputError)) else f"{type(err).__name__}: {err}"
            if said != self._unretracted:  # open_bench's exit repeats the stop a run already made
                log.error("bench: arm stopped but not retracted: %s", said)
            self._unretracted = said
            return False

    def close(self) -> None:
        """Close every device (after ``safe_stop``)."""
        for closer in (self.camera.stop, self.pressure.close, self.arm.close):
            try:
                closer()
            except Exception as err:  # closing must reach every device
                log.error("bench: error while closing: %s", err)
        if self._firmware is not None:
            self._firmware.stop()
        if self.sim is not None:
            self.sim.stop()
        self._held.close()


@contextlib.contextmanager
def open_bench(config: BenchConfig) -> Iterator[Bench]:
    """Open and start the bench of ``config``; on exit (normal, fault, Ctrl-C) stop, retract and close."""
    bench = config.open()
    try:
        bench.start()
        raise_pending_stop()  # a stop that came while the bench opened, its KeyboardInterrupt swallowed on the
        # way (depthai's import turns it into an ImportError, trimesh's catches it): no motion starts
        yield bench
    finally:
        try:
            if bench.arm.running:
                bench.safe_stop()
        finally:
            bench.close()
