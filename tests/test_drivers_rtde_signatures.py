"""The arm twin must keep the installed ur_rtde's method names, argument orders and defaults, and
implement exactly the methods the driver calls (no unused twin methods).

Signatures come from the pybind11 docstrings of ``rtde_control.RTDEControlInterface`` and
``rtde_receive.RTDEReceiveInterface`` (no robot is contacted: the classes are only inspected).
"""

from __future__ import annotations

import ast
import inspect

import numpy as np
import pytest
import rtde_control
import rtde_receive

from collect.arm import Arm
from collect.errors import HardwareFault
from collect.safety import SafetyLimits
from hw_mocks.fake_rtde import FakeRTDEControl, FakeRTDEReceive, SimURController
from hw_mocks.sim_bench import SimClock


def split_top_level(text: str) -> list[str]:
    """Split ``text`` at commas outside brackets and angle brackets."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch in "[(<{":
            depth += 1
        elif ch in "])>}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append(text[start:i].strip())
            start = i + 1
    if text[start:].strip():
        parts.append(text[start:].strip())
    return parts


def real_signatures(cls, name: str) -> list[list[tuple[str, object]]]:
    """Overloads of ``cls.name`` as lists of (parameter, default or inspect._empty), without self."""
    doc = getattr(cls, name).__doc__ or ""
    overloads = []
    for line in doc.splitlines():
        line = line.strip()
        line = line.split(". ", 1)[1] if line[:1].isdigit() and ". " in line else line
        if not line.startswith(f"{name}(self"):
            continue
        inner = line[len(name) + 1: line.rindex(") ->")]
        params = []
        for part in split_top_level(inner)[1:]:
            pname, _, rest = part.partition(":")
            default = inspect.Parameter.empty
            if " = " in rest:
                text = rest.split(" = ", 1)[1]
                try:
                    default = ast.literal_eval(text)
                except (ValueError, SyntaxError):
                    default = text
            params.append((pname.strip(), default))
        overloads.append(params)
    return overloads


def twin_signature(cls, name: str) -> list[tuple[str, object]]:
    sig = inspect.signature(getattr(cls, name))
    return [(p.name, p.default) for p in list(sig.parameters.values())[1:]]


def _public_methods(cls) -> list[str]:
    return [n for n, v in vars(cls).items() if callable(v) and not n.startswith("_")]


def test_signature_parser_reads_pybind_overloads():
    overloads = real_signatures(rtde_control.RTDEControlInterface, "moveL")
    assert [("pose", inspect.Parameter.empty), ("speed", 0.25), ("acceleration", 1.2),
            ("asynchronous", False)] in overloads
    assert len(overloads) == 2


@pytest.mark.parametrize("twin, real", [(FakeRTDEControl, rtde_control.RTDEControlInterface),
                                        (FakeRTDEReceive, rtde_receive.RTDEReceiveInterface)])
def test_twin_methods_match_installed_ur_rtde(twin, real):
    for name in _public_methods(twin):
        assert hasattr(real, name), f"{twin.__name__}.{name} does not exist in {real.__name__}"
        overloads = real_signatures(real, name)
        assert overloads, f"no signature found in the docstring of {real.__name__}.{name}"
        assert twin_signature(twin, name) in overloads, (
            f"{twin.__name__}.{name}{twin_signature(twin, name)} drifted from {real.__name__}: {overloads}")


class _Recorder:
    """Wraps an RTDE twin and records every method call the driver makes."""

    def __init__(self, inner, calls: list):
        self._inner, self._calls = inner, calls

    def __getattr__(self, name):
        method = getattr(self._inner, name)

        def call(*args, **kwargs):
            self._calls.append((type(self._inner), name, args, kwargs))
            return method(*args, **kwargs)

        return call


class _FlatFloor:
    """A scene whose only object is a floor at z = 0.1 m (0.5 N/mm), to exercise the motions."""

    def __init__(self):
        self.clock = SimClock()

    def now(self):
        return self.clock.now()

    def fault_active(self, kind, t=None):
        return False

    def wrench(self, pose, t):
        w = np.zeros(6)
        w[2] = 500.0 * max(0.0, 0.1 - pose[2])
        return w


def test_every_call_of_the_driver_binds_to_the_real_ur_rtde_signature():
    calls: list = []
    # the simulated robot protective-stops above 6 N: the last press below runs into it (the first one
    # stops at 3 N, 6 mm and 1.2 s before it: was 3 mm and 0.15 s, which a loaded host's monitor overran)
    controller = SimURController(_FlatFloor(), [0.4, 0.0, 0.11, np.pi, 0.0, 0.0], protective_force_n=6.0)
    arm = Arm(_Recorder(FakeRTDEControl(controller), calls), _Recorder(FakeRTDEReceive(controller), calls),
              SafetyLimits((0.2, -0.3, 0.0), (0.6, 0.3, 0.4)), state_hz=250)
    try:
        arm.move_to([0.4, 0.0, 0.105, np.pi, 0.0, 0.0], 0.05, 0.5)
        assert arm.move_until_contact(speed=0.02, force_threshold_n=0.5) is not None
        arm.press(force_n=3.0, speed=0.005)
        arm.hold(0.05)
        arm.retract()
        arm.stop()
        arm.move_until_contact(speed=0.02, force_threshold_n=0.5)
        with pytest.raises(HardwareFault, match="protective stop"):
            arm.press(force_n=8.0)
    finally:
        arm.close()
    real = {FakeRTDEControl: rtde_control.RTDEControlInterface, FakeRTDEReceive: rtde_receive.RTDEReceiveInterface}
    used: dict = {twin_cls: set() for twin_cls in real}
    for twin_cls, name, args, kwargs in calls:
        used[twin_cls].add(name)
        overloads = real_signatures(real[twin_cls], name)
        bound = False
        for params in overloads:
            sig = inspect.Signature([inspect.Parameter(p, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=d)
                                     for p, d in params])
            try:
                sig.bind(*args, **kwargs)
                bound = True
            except TypeError:
                continue
            if name == "moveL":  # the pose overload: 6 floats, then speed, acceleration, asynchronous
                assert len(args[0]) == 6 and all(isinstance(v, float) for v in args[0])
        assert bound, f"driver called {name}{args} which binds to no overload of {real[twin_cls].__name__}.{name}"
    # ur_rtde's kickWatchdog leaves its control script unable to run the next ordinary command: the
    # twin keeps it to show that (below), and the driver must never call it
    assert "kickWatchdog" not in used[FakeRTDEControl]
    for twin_cls, names in used.items():  # the twin implements what the driver calls, and nothing else
        unused = set(_public_methods(twin_cls)) - names - {"kickWatchdog"}
        assert not unused, f"{twin_cls.__name__} has methods the driver never calls: {sorted(unused)}"


def test_the_twin_keeps_the_control_scripts_handshake_after_a_kick_watchdog():
    """The control script ur_rtde 1.6 uploads has no branch for kickWatchdog's command (99): it takes
    it for an ordinary command that never reports done, and leaves the next ordinary ones unrun (was:
    the monitor kicked that way in every sample; on a real arm the first move would have failed).
    A real-time command such as getStepTime still runs, and any command kicks the watchdog."""
    controller = SimURController(_FlatFloor(), [0.4, 0.0, 0.2, np.pi, 0.0, 0.0])
    control = FakeRTDEControl(controller)
    assert control.setWatchdog(2.0) and control.zeroFtSensor()
    assert control.getStepTime() == FakeRTDEControl.STEP_TIME_S
    assert control.moveL([0.4, 0.0, 0.19, np.pi, 0.0, 0.0], 0.05, 0.5, True)
    control.kickWatchdog()
    assert not control.moveL([0.4, 0.0, 0.2, np.pi, 0.0, 0.0], 0.05, 0.5, True)
    assert not control.zeroFtSensor() and not control.setWatchdog(2.0)
    assert control.getStepTime() == FakeRTDEControl.STEP_TIME_S
