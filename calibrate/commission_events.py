"""Events the commissioning flow emits while it runs, consumed by the CLI progress display and the TUI.

The flow (``calibrate.commissioning.run_commissioning``) calls ``on_event(event)`` from its own
thread; consumers must not block (the TUI posts them to its message queue).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum


class Step(str, Enum):
    """Commissioning steps, in the order they run."""

    CONNECT = "connect"  # identify sensor serial, camera intrinsics, board firmware
    LEAK_TEST = "leak_test"  # inflate/settle, pressure decay over a fixed hold
    CAMERA_HEALTH = "camera_health"  # dead/stuck pixels, valid-depth coverage, dot pattern
    REFERENCE = "reference"  # no-contact reference frames
    COLLECT = "collect"  # sub-minute calibration set (objects x poses)
    FINETUNE = "finetune"  # fine-tune from the base model within a time budget
    VALIDATE = "validate"  # metrics on held-out poses
    POSE_CHECK = "pose_check"  # downstream pose check on the mug
    VERDICT = "verdict"  # acceptance checks, report, registry


STEPS: tuple[Step, ...] = tuple(Step)


@dataclass
class StepStarted:
    step: Step
    eta_s: float | None = None  # expected duration, s


@dataclass
class StepProgress:
    step: Step
    fraction: float  # 0..1
    message: str = ""


@dataclass
class StepFinished:
    step: Step
    ok: bool
    summary: str = ""
    resumed: bool = False  # True when the step's result was taken from a previous run
    skipped: bool = False  # True when the step did not run (a failed hardware check before it, or nothing to do)


@dataclass
class CollectionProgress:
    """Live state during data collection (also emitted by ``bubble collect``)."""

    object_name: str
    pose_index: int  # 0-based pose within the object, -1 for reference frames
    poses_per_object: int
    phase: str  # free / approach / press / hold / retract, or stopping (the retract after a stop or a fault)
    frames: int  # frames recorded so far in the session
    force_n: float  # |F| at the TCP, N
    pressure_hpa: float  # bubble pressure, hPa absolute


@dataclass
class BenchSnapshot:
    """Live bench state, emitted a few times per second while the bench is connected."""

    simulated: bool
    tcp_pose: list[float]  # [x,y,z,rx,ry,rz] m + rotation vector, base frame
    wrench: list[float]  # [Fx,Fy,Fz,Tx,Ty,Tz] N, N m, base frame
    pressure_hpa: float
    ir: object = None  # latest (H,W) uint16 amplitude image, or None
    depth_m: object = None  # latest (H,W) float32 m ToF depth (0 = invalid), or None


@dataclass
class TrainingProgress:
    """One point of the live training curve."""

    step: int  # optimizer steps so far
    elapsed_s: float
    loss: float  # training loss (masked L1, m)
    a1: float | None = None  # delta < 1.05 on the validation split when evaluated
    eta_s: float | None = None


@dataclass
class FaultRaised:
    kind: str  # HardwareFault.kind
    message: str


@dataclass
class ArmSafeStopped:
    """The flow stopped the arm and retracted it (stop request, hardware fault or error)."""

    retracted: bool  # False: stopped but could not move (e.g. protective stop)
    tcp_z_before_m: float  # TCP height before the stop, m (base frame; nan when unreadable)
    tcp_z_after_m: float  # TCP height after the retract, m (nan when unreadable)
    force_after_n: float  # |F| at the TCP after the retract, N (nan when unreadable)

    def summary(self) -> str:
        """One phrase for the operator: what the stop did to the arm."""
        if not self.retracted:
            return "arm stopped but NOT retracted (clear the stop on the pendant)"
        return f"arm retracted, |F| {self.force_after_n:.1f} N"


@dataclass
class Verdict:
    accepted: bool
    checks: list[dict] = field(default_factory=list)  # acceptance.evaluate dicts (calibrate.acceptance)
    report_path: str = ""


CommissionEvent = (
    StepStarted
    | StepProgress
    | StepFinished
    | CollectionProgress
    | BenchSnapshot
    | TrainingProgress
    | FaultRaised
    | ArmSafeStopped
    | Verdict
)
