"""The commissioning flow: from a new sensor on the bench to an accepted (or rejected), registered profile.

``run_commissioning(config, on_event, stop_event) -> CommissionResult`` runs the steps of
``calibrate.commission_events.Step`` in order:

1. connect: open the bench, identify the sensor (serial from the pressure board, intrinsics
   from the camera, board firmware);
2. leak test: the untouched bubble settles, then its pressure decays over a fixed hold
   (``calibrate.leak_test``);
3. camera health: dead/stuck pixels, valid-depth coverage and the dot pattern from a burst of
   no-contact frames (``calibrate.camera_health``);
4. reference: no-contact reference frames (``reference.h5``; their median depth goes to the registry);
5. collect: the calibration set, objects x poses (``collect.collection.run_collection`` into
   ``session.h5``);
6. fine-tune from the base model within the time budget (``trainer.training.train_model`` into ``model/``)
   on the trainer's pose split: 70 % of each object's contact poses (7 of the default 10); the
   step ends within ``finetune_minutes`` of training plus ``FINETUNE_OVERHEAD_S`` of wall time
   (3 min by default), training ending early on a CPU too slow for the rest to fit, and earlier
   still when the steps before it ran so long that the run would overrun ``total_minutes``
   (5 min by default; ``CommissionConfig.finetune_deadline_s``);
7. validate on the held-out contact poses (3 of 10 per object), against the ToF and, on
   simulated runs, against the true depth;
8. pose check on the mug's held-out poses (``calibrate.pose_check.run_pose_check``);
9. verdict: acceptance checks (``calibrate.acceptance``), ``acceptance.json``, ``report.html``,
   and the sensor registry (``calibrate.sensor_registry``).

A failing hardware check (leak, camera health; ``gate: true`` in the thresholds) skips the
remaining data steps: the sensor is rejected without training on it.

Resume: ``RUN_DIR/state.json`` records every completed step and its results; running again with
the same ``run_dir`` skips them (``StepFinished(resumed=True)``) and continues.
Faults: a ``HardwareFault`` safe-stops the arm (stop + retract), keeps every file, and ends the
run rejected with the fault as the reason; the failed step is not recorded, so a re-run
retries it. ``stop_event`` does the same but ends with ``result.stopped`` (no verdict).
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from calibrate import acceptance
from calibrate.commission_events import (
    STEPS,
    ArmSafeStopped,
    BenchSnapshot,
    CollectionProgress,
    CommissionEvent,
    FaultRaised,
    Step,
    StepFinished,
    StepProgress,
    StepStarted,
    TrainingProgress,
    Verdict,
)
from collect.errors import HardwareFault, InputError, StopRequested
from collect.json_files import plain_json, write_json
from collect.session_format import DEPTH_UNIT_M
from trainer.contact import contact_mask, reference_depth
from trainer.metrics import METRIC_KEYS

if TYPE_CHECKING:
    from collect.bench import BenchConfig

STATE_FILE = "state.json"
STATE_VERSION = 1
SESSION_FILE = "session.h5"
REFERENCE_FILE = "reference.h5"
MODEL_DIR = "model"
ACCEPTANCE_FILE = "acceptance.json"
REPORT_FILE = "report.html"
LEAK_FILE = "leak_test.npz"
CAMERA_FILE = "camera_health.npz"
VALIDATION_FILE = "validation.npz"
POSE_FILE = "pose_check.json"
PLOTS_DIR = "plots"

#: Leak test: settle, then hold (s of bench time).
LEAK_SETTLE_S = 1.0
LEAK_HOLD_S = 10.0
#: No-contact frames for the camera health check and for the reference.
HEALTH_FRAMES = 16
REFERENCE_FRAMES = 30
#: Bench snapshots per second while the bench is connected.
SNAPSHOT_HZ = 4.0
#: Held-out frames shown in the report (one per object, the most deformed).
EXAMPLE_FRAMES = 4
#: Steps that need the bench.
BENCH_STEPS = (Step.CONNECT, Step.LEAK_TEST, Step.CAMERA_HEALTH, Step.REFERENCE, Step.COLLECT)
#: Wall time (s) the fine-tune step may take beyond its training budget: loading the calibration
#: set, the live validations, the final validation and the ONNX export (about 20 s on the 2-core
#: CPU of docs/benchmarks.md, 28-35 s on one half as fast). The trainer's deadline cuts training
#: short where they take longer, so the step lasts at most ``finetune_minutes`` + this.
FINETUNE_OVERHEAD_S = 30.0
#: Wall time (s) kept for the steps after the fine-tune when it is shortened to fit the run's
#: ``total_minutes``: validate, pose check and verdict took 18-27 s on the 2-core CPU of
#: docs/benchmarks.md (bench_commission, session 14) and 29-37 s with that CPU 2.2x slower.
AFTER_FINETUNE_S = 35.0
#: The shortest fine-tune step the run budget can leave (s): one minute of training plus
#: ``FINETUNE_OVERHEAD_S``. Steps before it that ran longer make the run overrun its budget
#: rather than leave the sensor with a model fine-tuned for seconds.
MIN_FINETUNE_STEP_S = 60.0 + FINETUNE_OVERHEAD_S
#: Settings that must match when a run directory is resumed.
RESUME_KEYS = ("simulated", "sensor", "objects", "poses_per_object", "seed")


@dataclass
class CommissionConfig:
    """What to commission and how (see the module docstring)."""

    run_dir: Path
    simulated: bool = True
    sensor_spec: Path | None = None  # sim: SensorSpec YAML; None -> draw_sensor(seed)
    bench: "BenchConfig | None" = None  # real bench settings when not simulated
    thresholds: Path | None = None  # None -> packaged calibrate/acceptance_thresholds.yaml
    registry_dir: Path | None = None  # None -> default registry location
    base_model: Path | None = None  # None -> the packaged base model
    finetune_minutes: float = 2.5
    objects: tuple[str, ...] = ("mug", "wine_glass", "box", "fingers")
    #: 10 presses per object: the 70/30 pose split holds out 3 of each object's poses, so the pose
    #: check's median over the mug's held-out frames lies in the middle pose (one hard pose cannot
    #: decide the verdict; with 8 it held out 2) and the fine-tune keeps 7 (see docs/pose.md).
    poses_per_object: int = 10
    seed: int = 0
    sim_faults: tuple[str, ...] = ()  # "KIND@SECONDS"
    sim_speed: float = 1.0  # simulated clock speed factor
    leak_hold_s: float = LEAK_HOLD_S  # bench-clock seconds of the leak-test hold
    #: Wall-time budget of one run of the flow (min; None or inf: none). Counted from the start of this
    #: invocation (a resumed run gets it afresh); only the fine-tune step gives way to it.
    total_minutes: float | None = 5.0

    @property
    def finetune_step_limit_s(self) -> float:
        """Wall time (s) the fine-tune step may take: the training budget + ``FINETUNE_OVERHEAD_S``."""
        return 60.0 * self.finetune_minutes + FINETUNE_OVERHEAD_S

    def finetune_deadline_s(self, elapsed_s: float) -> tuple[float, bool]:
        """Wall time (s) for a fine-tune step that starts ``elapsed_s`` s into the run, and whether
        the run budget (not ``finetune_step_limit_s``) set it.

        The step gets ``finetune_step_limit_s`` unless the run would then overrun
        ``total_minutes`` with ``AFTER_FINETUNE_S`` left for the steps after it; it never gets
        less than ``MIN_FINETUNE_STEP_S`` (or the step limit, if that is shorter).
        """
        limit = self.finetune_step_limit_s
        if self.total_minutes is None:
            return limit, False
        fits = 60.0 * self.total_minutes - elapsed_s - AFTER_FINETUNE_S
        deadline = min(limit, max(fits, MIN_FINETUNE_STEP_S))
        return deadline, deadline < limit


@dataclass
class CommissionResult:
    accepted: bool
    checks: list[dict]  # {name, value, threshold, op, unit, passed, verdict, reason}
    run_dir: Path
    report_path: Path
    stopped: bool = False  # stop_event ended the run (arm stopped + retracted, data kept)
    fault: str | None = None  # "kind: message" of the hardware fault that ended the run
    reason: str = ""  # one line: why rejected


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class RunState:
    """``RUN_DIR/state.json``: the settings of the run and the results of its completed steps."""

    def __init__(self, path: Path, data: dict):
        self.path = path
        self.data = data

    @classmethod
    def open(cls, run_dir: Path, settings: dict) -> "RunState":
        """Load the state of ``run_dir`` (or start one); raises ``InputError`` when the directory
        holds a run with other settings."""
        path = run_dir / STATE_FILE
        if not path.exists():
            state = cls(path, {"version": STATE_VERSION, "settings": settings, "created": _now(), "steps": {}})
            state.save()
            return state
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise InputError(f"{path} is unreadable ({err}); use a new --out directory") from None
        if data.get("version") != STATE_VERSION:
            raise InputError(f"{path} is from another version of bubble commission; use a new --out directory")
        saved = data.get("settings", {})
        for key in RESUME_KEYS:
            if saved.get(key) != settings.get(key):
                raise InputError(
                    f"{run_dir} holds a run with {key}={saved.get(key)!r}, not {settings.get(key)!r}; "
                    "use a new --out directory to commission with other settings"
                )
        return cls(path, data)

    def save(self) -> None:
        write_json(self.path, self.data)

    def done(self, step: Step) -> bool:
        return step.value in self.data["steps"]

    def get(self, step: Step) -> dict:
        return self.data["steps"].get(step.value, {})

    def record(self, step: Step, result: dict) -> None:
        self.data["steps"][step.value] = {**result, "finished": _now()}
        self.save()

    def checks(self) -> list[dict]:
        """Every check of the completed steps, in step order."""
        out = []
        for step in STEPS:
            out += self.get(step).get("checks", [])
        return out


def _settings(config: CommissionConfig, sensor_id: str) -> dict:
    return {
        "simulated": bool(config.simulated),
        "sensor": sensor_id,
        "objects": list(config.objects),
        "poses_per_object": int(config.poses_per_object),
        "seed": int(config.seed),
        "finetune_minutes": float(config.finetune_minutes),
        "total_minutes": float(config.total_minutes) if config.total_minutes not in (None, math.inf) else None,
        "base_model": str(config.base_model) if config.base_model else "base",
        "thresholds": str(config.thresholds) if config.thresholds else "packaged",
        "sim_faults": list(config.sim_faults),
        "sim_speed": float(config.sim_speed),
    }


class _Flow:
    """One run of the flow (see ``run_commissioning``)."""

    def __init__(self, config: CommissionConfig, on_event, stop_event: threading.Event, thresholds, sensor_spec):
        self.config = config
        self.run_dir = Path(config.run_dir)
        self.on_event = on_event
        self.stop_event = stop_event
        self.thresholds = thresholds
        self.sensor_spec = sensor_spec  # SensorSpec on simulated runs
        self.bench = None
        self._bench_cm = None
        self.state: RunState | None = None
        self._latest_frame = None
        self._snapshot_stop = threading.Event()
        self._snapshot_thread: threading.Thread | None = None
        #: ``time.monotonic()`` when ``run()`` began (s): the run's wall-time budget counts from there.
        self.started = time.monotonic()

    # ------------------------------------------------------------------ events and helpers
    def emit(self, event: CommissionEvent) -> None:
        self.on_event(event)

    def check_stop(self) -> None:
        if self.stop_event.is_set():
            raise StopRequested("commissioning: stopped by the operator")
        if self.bench is not None:
            self.bench.check()

    def progress(self, step: Step, fraction: float, message: str = "") -> None:
        self.emit(StepProgress(step, float(min(max(fraction, 0.0), 1.0)), message))

    def _snapshot_loop(self) -> None:
        period = 1.0 / SNAPSHOT_HZ
        while not self._snapshot_stop.wait(period):
            bench = self.bench
            if bench is None:
                continue
            try:
                arm = bench.arm.state()
                reading = bench.pressure.latest()
            except HardwareFault:
                continue  # the flow thread raises it from its own calls
            frame = self._latest_frame
            self.emit(
                BenchSnapshot(
                    simulated=bool(bench.simulated),
                    tcp_pose=[float(v) for v in arm.tcp_pose],
                    wrench=[float(v) for v in arm.tcp_wrench],
                    pressure_hpa=float(reading.hpa) if reading is not None else float("nan"),
                    ir=None if frame is None else frame.ir,
                    depth_m=None if frame is None else frame.depth.astype(np.float32) * DEPTH_UNIT_M,
                )
            )

    def _grab(self, n: int, step: Step, message: str) -> list:
        """``n`` consecutive camera frames (kept as the latest frame for the snapshots)."""
        frames = []
        for k in range(n):
            self.check_stop()
            frames.append(self.bench.camera.get_frame())
            if k % 4 == 0:
                self.progress(step, (k + 1) / n, message)
        return frames

    # ------------------------------------------------------------------ bench
    def open_bench(self) -> None:
        """Open and start the bench (``collect.bench.open_bench``); snapshots start flowing."""
        import dataclasses

        from collect.bench import BenchConfig, open_bench

        if self.config.simulated:
            bench_config = BenchConfig.create(
                "sim",
                objects=tuple(self.config.objects),
                sensor=self.sensor_spec,
                seed=self.config.seed,
                faults=tuple(self.config.sim_faults),
                speed=self.config.sim_speed,
            )
        else:
            bench_config = dataclasses.replace(self.config.bench, objects=tuple(self.config.objects))
        self._bench_cm = open_bench(bench_config)
        bench = self._bench_cm.__enter__()
        bench.arm.stop_on(self.stop_event)  # a stop mid-motion halts the arm within one state sample
        bench.camera = _FrameTap(bench.camera, self._set_latest_frame)
        self.bench = bench
        self._snapshot_stop.clear()
        self._snapshot_thread = threading.Thread(target=self._snapshot_loop, name="bench-snapshots", daemon=True)
        self._snapshot_thread.start()

    def _set_latest_frame(self, frame) -> None:
        self._latest_frame = frame

    def close_bench(self, safe_stop: bool) -> None:
        """Stop the snapshots, then (``safe_stop``: stop and retract the arm and) close every device."""
        self._snapshot_stop.set()
        if self._snapshot_thread is not None:
            self._snapshot_thread.join(timeout=2.0)
            self._snapshot_thread = None
        bench, self.bench = self.bench, None
        if bench is None:
            return
        try:
            if safe_stop:
                z_before, _ = _arm_z_and_force(bench)
                retracted = bench.safe_stop()
                z_after, force_after = _arm_z_and_force(bench)
                self.emit(ArmSafeStopped(bool(retracted), z_before, z_after, force_after))
        finally:
            self._bench_cm.__exit__(None, None, None)  # retracts a still-running arm, closes the devices

    # ------------------------------------------------------------------ steps
    def step_connect(self) -> dict:
        from collect.collection import session_metadata

        self.open_bench()
        b = self.bench
        b.arm.move_to(b.home_pose)  # free air above the plate: nothing touches the bubble
        firmware = b.pressure.firmware_version()
        serial = b.sensor_serial
        prior = self.state.data.get("serial")
        if prior is not None and prior != serial:
            raise InputError(f"{self.run_dir} was started for sensor {prior}, the bench holds {serial}; use a new --out")
        self.state.data["serial"] = serial
        return {
            "ok": True,
            "summary": f"sensor {serial}, camera {b.intrinsics['width']}x{b.intrinsics['height']} "
            f"fx {b.intrinsics['fx']:.1f}, board firmware {firmware}",
            "serial": serial,
            "intrinsics": dict(b.intrinsics),
            "camera_in_tcp": [float(v) for v in session_metadata(b, [])["camera_in_tcp"]],
            "firmware": firmware,
            "simulated": bool(b.simulated),
        }

    def step_leak_test(self) -> dict:
        from calibrate.leak_test import analyse_leak

        hold_s = float(self.config.leak_hold_s)
        pressure, camera, clock = self.bench.pressure, self.bench.camera, self.bench.clock
        # The camera keeps streaming (live view; its queue must not sit full) while the bubble settles
        # and holds; get_frame paces the loop at the frame rate.
        t_settle = clock() + LEAK_SETTLE_S
        while clock() < t_settle:
            self.check_stop()
            camera.get_frame()
        pressure.drain()
        t, hpa = [], []
        while not t or t[-1] - t[0] < hold_s:
            self.check_stop()
            camera.get_frame()
            for reading in pressure.drain():
                t.append(reading.t)
                hpa.append(reading.hpa)
            if t:
                self.progress(Step.LEAK_TEST, (t[-1] - t[0]) / hold_s, f"{hpa[-1]:.2f} hPa")
        result = analyse_leak(np.array(t), np.array(hpa))
        np.savez_compressed(self.run_dir / LEAK_FILE, t=result.t, hpa=result.hpa)
        checks = [
            acceptance.evaluate(self.thresholds, "leak_rate_hpa_per_min", result.rate_hpa_per_min),
            acceptance.evaluate(self.thresholds, "inflation_pressure_hpa", result.mean_hpa),
        ]
        return {"summary": result.summary(), "leak": result.to_json(), "checks": checks}

    def step_camera_health(self) -> dict:
        from calibrate.camera_health import assess_camera

        frames = self._grab(HEALTH_FRAMES, Step.CAMERA_HEALTH, "no-contact frames")
        health = assess_camera(np.stack([f.ir for f in frames]), np.stack([f.depth for f in frames]))
        np.savez_compressed(self.run_dir / CAMERA_FILE, **health.maps())
        th = self.thresholds
        checks = [
            acceptance.evaluate(th, "dead_pixels", health.dead_pixels),
            acceptance.evaluate(th, "stuck_pixels", health.stuck_pixels),
            acceptance.evaluate(th, "valid_depth_coverage", health.valid_depth_coverage),
            acceptance.evaluate(th, "dot_contrast", health.dot_contrast, "is the dot pattern printed?"),
            acceptance.evaluate(th, "dot_count", health.dot_count, "is the dot pattern printed?"),
        ]
        return {"summary": health.summary(), "camera": health.to_json(), "checks": checks}

    def _writer(self, path: Path, objects: list, resume: bool = False):
        from collect.collection import session_metadata
        from collect.session_writer import SessionWriter

        return SessionWriter(path, **session_metadata(self.bench, objects), resume=resume)

    def step_reference(self) -> dict:
        from collect import session_format as sf

        path = self.run_dir / REFERENCE_FILE
        _set_aside(path)
        writer = self._writer(path, [])
        try:
            frames = self._grab(REFERENCE_FRAMES, Step.REFERENCE, "no-contact reference")
            pose = self.bench.arm.state().tcp_pose
            for f in frames:
                writer.append_frame(
                    f.ir, f.depth, f.t_device, f.t_host, f.seq, -1, -1, sf.PHASE_FREE, pose, true_depth=f.true_depth
                )
        finally:
            writer.close()
        depth = np.stack([f.depth for f in frames]).astype(np.float32) * DEPTH_UNIT_M
        valid_count = (depth > 0).sum(axis=0)
        return {
            "summary": f"{len(frames)} frames, {float((valid_count > 0).mean()):.0%} of pixels with valid depth",
            "frames": len(frames),
        }

    def step_collect(self) -> dict:
        from collect.collection import open_collection_writer, plan_bench_collection, run_collection
        from collect.pose_planner import PlanSettings

        b = self.bench
        settings = PlanSettings(poses_per_object=self.config.poses_per_object, seed=self.config.seed)
        plan = plan_bench_collection(b, settings)
        path = self.run_dir / SESSION_FILE
        # An interrupted earlier attempt is continued: run_collection skips its completed poses.
        writer = open_collection_writer(path, b, plan, resume=path.exists())
        self.emit(StepStarted(Step.COLLECT, plan.estimated_duration_s() / self._speed()))
        planned = len(plan.poses)
        order = {o.name: i for i, o in enumerate(plan.objects)}
        ppo = self.config.poses_per_object

        def on_progress(**p) -> None:
            self.emit(CollectionProgress(**p))
            done = order.get(p["object_name"], 0) * ppo + max(p["pose_index"], 0)
            self.progress(Step.COLLECT, done / planned, f"{p['object_name'] or 'travel'} {p['phase']}")

        try:
            run = run_collection(b, plan, writer, on_progress, self.stop_event)
        finally:
            writer.close()
        if run.stopped:
            raise StopRequested("commissioning: stopped by the operator")
        stats = _collection_stats(path, planned)
        th = self.thresholds
        checks = [
            acceptance.evaluate(th, "poses_completed_fraction", stats["poses_completed_fraction"]),
            acceptance.evaluate(th, "frames_dropped_fraction", stats["frames_dropped_fraction"]),
        ]
        return {
            "summary": f"{stats['poses_recorded']}/{planned} poses, {stats['frames']} frames "
            f"({stats['frames_dropped']} dropped) in {run.duration_s:.0f} s bench time",
            "collection": {**stats, "plan": plan.describe(), "duration_s": run.duration_s,
                           "poses_without_contact": run.poses_without_contact},
            "checks": checks,
        }

    def step_finetune(self) -> dict:
        from trainer.training import TrainConfig, train_model

        model_dir = self.run_dir / MODEL_DIR
        curve: list[dict] = []
        started = time.monotonic()
        budget_s = 60.0 * self.config.finetune_minutes
        deadline_s, run_bound = self.config.finetune_deadline_s(started - self.started)
        self.emit(StepStarted(Step.FINETUNE, deadline_s))

        def on_progress(p) -> None:
            a1 = p.val.get("a1") if (p.event == "eval" and p.val) else None
            if p.event == "step" and p.step % 5 != 0 and a1 is None:
                return
            loss = p.loss if math.isfinite(p.loss) else None
            point = {"step": p.step, "elapsed_s": time.monotonic() - started, "loss": loss, "a1": a1}
            curve.append(point)
            if loss is not None:  # the validation before the first step has no training loss yet
                self.emit(TrainingProgress(p.step, point["elapsed_s"], p.loss, a1, p.eta_s))
                self.progress(Step.FINETUNE, p.fraction, f"step {p.step}, loss {p.loss * 1000:.3f} mm")

        config = TrainConfig(
            data=[str(self.run_dir / SESSION_FILE)],
            out=str(model_dir),
            init=str(self.config.base_model) if self.config.base_model else "base",
            minutes=self.config.finetune_minutes,
            deadline_s=deadline_s,
            seed=self.config.seed,
            split="poses",
            eval_interval_s=max(10.0, budget_s / 8),
        )
        result = train_model(config, on_progress, self.stop_event)
        if result.stopped:
            raise StopRequested("commissioning: stopped by the operator")
        cut = ""
        if result.ended_at_deadline:
            cut = (f" (cut short to fit the run's {self.config.total_minutes:g}-min budget)" if run_bound
                   else " (cut short by the step deadline)")
        return {
            "summary": f"{result.steps} steps, {result.epochs:.1f} epochs in {result.train_s:.0f} s{cut}; "
            f"validation a1 {result.metrics.get('a1', float('nan')):.3f}",
            "train_s": result.train_s,
            "deadline_s": deadline_s,
            "deadline_from_run_budget": run_bound,
            "ended_at_deadline": result.ended_at_deadline,
            "steps": result.steps,
            "epochs": result.epochs,
            "curve": curve,
            "history": plain_json(result.history),
        }

    def step_validate(self) -> dict:
        from trainer.dataset import load_frames
        from trainer.evaluation import compare_with_truth, predict_frames
        from trainer.inference import DepthEstimator
        from trainer.metrics import METRIC_KEYS, depth_metrics
        from trainer.splits import split_in_class

        estimator = DepthEstimator.load(self.run_dir / MODEL_DIR)
        meta = estimator.metadata
        kw = {"min_depth": meta.min_depth, "max_depth": meta.max_depth}
        # The trainer's own pose split (same loader, seed and split function as train_model).
        frames = load_frames([self.run_dir / SESSION_FILE], seed=self.config.seed)
        _, val_idx = split_in_class(frames, by="poses", seed=self.config.seed)
        held = frames.subset(val_idx[frames.pose_id[val_idx] >= 0])
        if len(held) == 0:
            raise InputError("the calibration set has no held-out contact poses; record more poses per object")
        self.progress(Step.VALIDATE, 0.1, f"{len(held)} held-out frames")
        pred = predict_frames(estimator, held.ir)
        metrics = depth_metrics(pred, held.depth, **kw)
        per_object = {
            name: depth_metrics(pred[held.object_name == name], held.depth[held.object_name == name], **kw)
            for name in sorted(set(held.object_name))
        }
        truth = None
        if held.true_depth is not None:
            truth = compare_with_truth(pred, held.depth, held.true_depth, meta.min_depth, meta.max_depth)
        self.progress(Step.VALIDATE, 0.6, "no-contact statistics")
        arrays = _nocontact_maps(estimator, self.run_dir / REFERENCE_FILE)
        # The contact patches: where the ToF sees the membrane pushed in from its rest shape. The
        # whole-image metrics hardly see a few-mm dent (delta < 1.05 is 4.5 mm at 90 mm), these do.
        ref = arrays["reference_depth"]
        contact = contact_mask(held.depth, ref)
        contact_metrics = depth_metrics(pred, held.depth, mask=contact, **kw)
        pick = _pick_examples(held, ref)
        arrays.update(
            example_ir=held.ir[pick],
            example_depth=held.depth[pick],
            example_pred=pred[pick],
            example_object=np.array([str(held.object_name[i]) for i in pick]),
            example_pose=held.pose_id[pick],
        )
        if held.true_depth is not None:
            arrays["example_true"] = held.true_depth[pick]
        np.savez_compressed(self.run_dir / VALIDATION_FILE, **arrays)
        th = self.thresholds
        checks = [
            acceptance.evaluate(th, "heldout_a1", metrics["a1"]),
            acceptance.evaluate(th, "heldout_abs_rel", metrics["abs_rel"]),
            acceptance.evaluate(th, "heldout_rmse_mm", metrics["rmse"] * 1000.0),
            acceptance.evaluate(th, "contact_rmse_mm", contact_metrics["rmse"] * 1000.0,
                                "does the model see the dents?"),
        ]
        if truth is not None:
            checks.append(acceptance.evaluate(th, "truth_a1", truth["model"]["a1"]))
        return {
            "summary": f"held-out a1 {metrics['a1']:.3f}, abs_rel {metrics['abs_rel']:.4f}, "
            f"rmse {metrics['rmse'] * 1000:.3f} mm on {metrics['n_images']} frames",
            "metrics": {k: metrics[k] for k in (*METRIC_KEYS, "n_images", "n_pixels")},
            "per_object": per_object,
            "contact": {k: contact_metrics[k] for k in (*METRIC_KEYS, "n_images", "n_pixels")},
            "vs_true": truth,
            "heldout_pose_ids": {name: sorted({int(p) for p in held.pose_id[held.object_name == name]})
                                 for name in sorted(set(held.object_name))},
            "checks": checks,
        }

    def step_pose_check(self) -> dict:
        from calibrate.pose_check import run_pose_check

        if "mug" not in self.config.objects:
            return {"summary": "not run: the mug is not in the calibration set", "skipped": True}
        self.progress(Step.POSE_CHECK, 0.1, "mug poses from predicted and measured depth")
        th = self.thresholds
        try:
            result = run_pose_check(
                str(self.run_dir / MODEL_DIR), self.run_dir / SESSION_FILE, "mug",
                seed=self.config.seed, pose_ids=self.state.get(Step.VALIDATE).get("heldout_pose_ids", {}).get("mug"),
                plots_dir=self.run_dir / PLOTS_DIR,
            )
        except InputError as err:  # no usable frame: the check fails, the run goes on to a verdict
            checks = [
                acceptance.evaluate(th, "pose_e_x_median_mm", None, str(err)),
                acceptance.evaluate(th, "pose_e_theta_median", None, str(err)),
            ]
            return {"summary": f"no usable mug frame: {err}", "checks": checks}
        result.write_json(self.run_dir / POSE_FILE)
        checks = [
            acceptance.evaluate(th, "pose_e_x_median_mm", result.e_x_mm.median),
            acceptance.evaluate(th, "pose_e_theta_median", result.e_theta.median),
        ]
        pose = {
            "frames_used": f"{result.n_used}/{result.n_hold_frames}",
            "e_x_mm (median/mean/var)": [result.e_x_mm.median, result.e_x_mm.mean, result.e_x_mm.variance],
            "e_theta (median/mean/var)": [result.e_theta.median, result.e_theta.mean, result.e_theta.variance],
            "e_x_mm median per held-out pose": {str(p): round(v, 3) for p, v in result.e_x_median_by_pose().items()},
            "hz": result.hz,
        }
        for src, stats in result.vs_true.items():
            pose[f"{src} vs true pose: e_x_mm / e_theta (median)"] = [stats["e_x_mm"].median, stats["e_theta"].median]
        return {"summary": result.summary().splitlines()[1], "pose": pose, "checks": checks}

    # ------------------------------------------------------------------ verdict
    def finish(self, fault: str | None = None, stopped: bool = False) -> CommissionResult:
        """acceptance.json, report.html and (unless stopped) the registry entry."""
        from calibrate.sensor_registry import SensorRegistry

        checks = self.state.checks()
        accepted = acceptance.accepted(checks) and fault is None and not stopped and self._all_done()
        reason = acceptance.rejection_reason(checks, fault)
        if stopped:
            reason = "stopped by the operator before a verdict"
        elif not accepted and not reason:
            reason = "not every step completed"
        validate = self.state.get(Step.VALIDATE)
        doc = {
            "accepted": accepted,
            "serial": self.state.data.get("serial"),
            "simulated": bool(self.config.simulated),
            "reason": reason,
            "fault": fault,
            "stopped": stopped,
            "thresholds": {"version": self.thresholds.version, "source": self.thresholds.source},
            "checks": checks,
            **dict.fromkeys(METRIC_KEYS),  # null when the run ended before validation
            **validate.get("metrics", {}),
            "per_object": validate.get("per_object"),
            "contact": validate.get("contact"),
            "vs_true": validate.get("vs_true"),
            "steps": {s.value: self.state.get(s).get("summary") for s in STEPS if self.state.done(s)},
            "finished": _now(),
        }
        write_json(self.run_dir / ACCEPTANCE_FILE, doc)
        report_path = self._write_report(doc)
        serial = self.state.data.get("serial")
        if not stopped and serial:
            connect = self.state.get(Step.CONNECT)
            SensorRegistry(self.config.registry_dir).register(
                serial,
                accepted=accepted,
                run_dir=self.run_dir,
                intrinsics=connect.get("intrinsics", {}),
                camera_in_tcp=connect.get("camera_in_tcp"),
                simulated=bool(self.config.simulated),
                acceptance=plain_json(doc),
                reason=reason,
                model_dir=self.run_dir / MODEL_DIR if accepted else None,
                reference=_registry_reference(self.run_dir / VALIDATION_FILE) if accepted else None,
            )
        self.emit(Verdict(accepted, checks, str(report_path)))
        return CommissionResult(accepted, checks, self.run_dir, report_path, stopped=stopped, fault=fault, reason=reason)

    def _all_done(self) -> bool:
        return all(self.state.done(s) for s in STEPS if s != Step.VERDICT)

    def _write_report(self, doc: dict) -> Path:
        from calibrate.report import ReportData, write_report

        st = self.state
        data = ReportData(
            serial=str(doc["serial"] or "unknown"),
            accepted=doc["accepted"],
            checks=doc["checks"],
            simulated=bool(self.config.simulated),
            reason=doc["reason"],
            fault=doc["fault"],
            stopped=doc["stopped"],
            run_info={
                "run directory": str(self.run_dir.resolve()),
                "finished": doc["finished"],
                "thresholds": self.thresholds.source,
                **{f"step {k}": v for k, v in doc["steps"].items()},
                "settings": st.data.get("settings"),
            },
            heldout_metrics=st.get(Step.VALIDATE).get("metrics"),
            contact_metrics=st.get(Step.VALIDATE).get("contact"),
            pose=st.get(Step.POSE_CHECK).get("pose"),
        )
        why_missing = doc["reason"] or "the step did not run"
        data.notes = {k: why_missing for k in ("leak", "camera", "nocontact", "examples", "training", "truth", "metrics")}
        if st.done(Step.POSE_CHECK) and st.get(Step.POSE_CHECK).get("skipped"):
            data.notes["pose"] = st.get(Step.POSE_CHECK)["summary"]
        else:
            data.notes["pose"] = why_missing
        if (self.run_dir / LEAK_FILE).is_file() and st.done(Step.LEAK_TEST):
            with np.load(self.run_dir / LEAK_FILE) as z:
                data.leak_t, data.leak_hpa = z["t"], z["hpa"]
            data.leak_rate_hpa_per_min = st.get(Step.LEAK_TEST)["leak"]["rate_hpa_per_min"]
        if (self.run_dir / CAMERA_FILE).is_file() and st.done(Step.CAMERA_HEALTH):
            with np.load(self.run_dir / CAMERA_FILE) as z:
                data.camera_ir_mean, data.camera_dead_mask = z["ir_mean"], z["dead_mask"]
                data.camera_stuck_mask, data.camera_dot_mask = z["stuck_mask"], z["dot_mask"]
        data.training_curve = st.get(Step.FINETUNE).get("curve", [])
        if (self.run_dir / VALIDATION_FILE).is_file() and st.done(Step.VALIDATE):
            with np.load(self.run_dir / VALIDATION_FILE) as z:
                data.nocontact_valid_count = z["valid_count"]
                data.nocontact_err_mean, data.nocontact_err_var = z["err_mean"], z["err_var"]
                data.example_ir, data.example_depth, data.example_pred = z["example_ir"], z["example_depth"], z["example_pred"]
                data.example_true = z["example_true"] if "example_true" in z.files else None
                data.example_labels = [f"{o} pose {p}" for o, p in zip(z["example_object"], z["example_pose"])]
            vs_true = st.get(Step.VALIDATE).get("vs_true")
            if vs_true:
                drop = vs_true["model_on_tof_dropout"]
                dropouts = None
                if drop["n_pixels"]:
                    dropouts = {
                        "fraction": 1.0 - vs_true["tof_coverage"],
                        "pixels": int(drop["n_pixels"]),
                        "model_rmse_mm": float(drop["rmse"]) * 1000.0,
                        "model_a1": drop["a1"],
                    }
                data.truth_comparison = {
                    "model": vs_true["model_on_tof_valid"], "tof": vs_true["tof"], "model_all": vs_true["model"],
                    "dropouts": dropouts,
                }
        return write_report(data, self.run_dir / REPORT_FILE)

    # ------------------------------------------------------------------ driver
    def run(self) -> CommissionResult:
        self.started = time.monotonic()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        sensor_id = self.sensor_spec.serial if self.sensor_spec is not None else "hardware"
        self.state = RunState.open(self.run_dir, _settings(self.config, sensor_id))
        handlers = {
            Step.CONNECT: self.step_connect,
            Step.LEAK_TEST: self.step_leak_test,
            Step.CAMERA_HEALTH: self.step_camera_health,
            Step.REFERENCE: self.step_reference,
            Step.COLLECT: self.step_collect,
            Step.FINETUNE: self.step_finetune,
            Step.VALIDATE: self.step_validate,
            Step.POSE_CHECK: self.step_pose_check,
        }
        etas = {Step.LEAK_TEST: (LEAK_SETTLE_S + self.config.leak_hold_s) / self._speed()}
        if self.state.done(Step.VERDICT) and (self.run_dir / ACCEPTANCE_FILE).is_file():
            return self._finished_before()
        pending_bench = [s for s in BENCH_STEPS if not self.state.done(s)]
        try:
            if pending_bench and self.state.done(Step.CONNECT):
                self.open_bench()  # resuming a bench step: reconnect and re-identify
                serial = self.bench.sensor_serial
                if serial != self.state.data.get("serial"):
                    raise InputError(
                        f"{self.run_dir} was started for sensor {self.state.data.get('serial')}, "
                        f"the bench holds {serial}; use a new --out"
                    )
            gate_failure = None
            for step in STEPS[:-1]:
                if self.state.done(step):
                    rec = self.state.get(step)
                    self.emit(StepFinished(step, rec["ok"], rec["summary"], resumed=True, skipped=bool(rec.get("skipped"))))
                    gate_failure = gate_failure or _gate_failure(rec)
                    continue
                if gate_failure is not None:
                    self.emit(StepFinished(step, False, f"not run: {gate_failure}", skipped=True))
                    continue
                self.check_stop()
                if step not in (Step.COLLECT, Step.FINETUNE):  # these announce their own ETA
                    self.emit(StepStarted(step, etas.get(step)))
                rec = handlers[step]()
                rec.setdefault("ok", all(c["passed"] for c in rec.get("checks", [])))
                self.state.record(step, rec)
                self.emit(StepFinished(step, rec["ok"], rec["summary"], skipped=bool(rec.get("skipped"))))
                gate_failure = _gate_failure(rec)
                if step == Step.COLLECT or gate_failure is not None:
                    self.close_bench(safe_stop=False)
            self.close_bench(safe_stop=False)
            self.emit(StepStarted(Step.VERDICT))
            result = self.finish()
            self.state.record(Step.VERDICT, {"ok": result.accepted, "summary": "accepted" if result.accepted else result.reason})
            self.emit(StepFinished(Step.VERDICT, result.accepted, "accepted" if result.accepted else result.reason))
            return result
        except HardwareFault as fault:
            self.emit(FaultRaised(fault.kind, str(fault)))
            self.close_bench(safe_stop=True)
            return self.finish(fault=f"{fault.kind}: {fault}")
        except StopRequested:
            self.close_bench(safe_stop=True)
            return self.finish(stopped=True)
        except BaseException:
            self.close_bench(safe_stop=True)
            raise

    def _finished_before(self) -> CommissionResult:
        """The verdict of a run that already finished in this directory (nothing runs again)."""
        for step in STEPS:
            if self.state.done(step):
                rec = self.state.get(step)
                self.emit(StepFinished(step, rec["ok"], rec["summary"], resumed=True, skipped=bool(rec.get("skipped"))))
            else:  # not run: a hardware check failed before it
                self.emit(StepFinished(step, False, "not run", resumed=True, skipped=True))
        doc = json.loads((self.run_dir / ACCEPTANCE_FILE).read_text())
        report = self.run_dir / REPORT_FILE
        self.emit(Verdict(doc["accepted"], doc["checks"], str(report)))
        return CommissionResult(doc["accepted"], doc["checks"], self.run_dir, report, fault=doc.get("fault"),
                                reason=doc.get("reason", ""))

    def _speed(self) -> float:
        return float(self.config.sim_speed) if self.config.simulated else 1.0


def _arm_z_and_force(bench) -> tuple[float, float]:
    """(TCP z in m, |F| at the TCP in N) of the arm, nan when the arm cannot be read."""
    try:
        state = bench.arm.state()
    except HardwareFault:
        return math.nan, math.nan
    return float(state.tcp_pose[2]), float(np.linalg.norm(state.tcp_wrench[:3]))


def _gate_failure(rec: dict) -> str | None:
    """The reason of the first failed gating check of a step result, or None."""
    for c in rec.get("checks", []):
        if c.get("gate") and not c["passed"]:
            return f"the {c['name']} check failed"
    return None


def _set_aside(path: Path) -> None:
    """Keep the file of an interrupted earlier attempt as ``<name>.aborted-<n><suffix>``."""
    if not path.exists():
        return
    n = 1
    while (aside := path.with_name(f"{path.stem}.aborted-{n}{path.suffix}")).exists():
        n += 1
    os.replace(path, aside)


def _collection_stats(path: Path, planned: int) -> dict:
    """Poses and frames in the session file.

    A pose counts as recorded when it has ``hold`` frames; dropped frames are the gaps in the
    camera sequence numbers (``Session.dropped_frames``).
    """
    from collect import session_format as sf
    from collect.session_reader import Session

    with Session.open(path) as s:
        n, dropped = s.n_frames, s.dropped_frames()
        poses = np.unique(s.pose_id[(s.pose_id >= 0) & (s.phase == sf.PHASE_HOLD)])
    return {
        "frames": n,
        "frames_dropped": dropped,
        "frames_dropped_fraction": dropped / max(n + dropped, 1),
        "poses_recorded": int(poses.size),
        "poses_planned": planned,
        "poses_completed_fraction": poses.size / max(planned, 1),
    }


class _FrameTap:
    """The bench camera, handing every frame it delivers to ``sink`` as well (for the live snapshots)."""

    def __init__(self, camera, sink):
        self._camera = camera
        self._sink = sink

    def get_frame(self, timeout_s: float | None = None):
        frame = self._camera.get_frame(timeout_s)
        self._sink(frame)
        return frame

    def __getattr__(self, name):
        return getattr(self._camera, name)


def _nocontact_maps(estimator, reference_path: Path) -> dict:
    """Per-pixel statistics over the no-contact reference frames (the paper's Fig. 5).

    ``valid_count (H,W) int32`` frames with valid ToF depth; ``err_mean``/``err_var`` ``(H,W) float32``
    m / m^2 of predicted - measured depth over those frames (NaN where never valid);
    ``reference_depth (H,W) float32 m`` median valid ToF depth (0 = never valid); ``reference_ir``.
    """
    from collect.session_reader import Session
    from trainer.evaluation import predict_frames

    with Session.open(reference_path) as s:
        idx = np.arange(s.n_frames)
        ir = s.ir(idx)
        depth = s.depth_m(idx)
    pred = predict_frames(estimator, ir)
    valid = depth > 0
    count = valid.sum(axis=0)
    err = np.where(valid, pred - depth, np.nan)
    with np.errstate(invalid="ignore"):
        err_mean = np.where(count > 0, np.nansum(err, axis=0) / np.maximum(count, 1), np.nan)
        err_var = np.where(count > 0, np.nansum((err - err_mean) ** 2, axis=0) / np.maximum(count, 1), np.nan)
    return {
        "valid_count": count.astype(np.int32),
        "err_mean": err_mean.astype(np.float32),
        "err_var": err_var.astype(np.float32),
        "reference_depth": reference_depth(depth),  # the pose check's and the trainer's reference
        "reference_ir": ir.mean(axis=0).astype(np.float32),
    }


def _pick_examples(frames, reference: np.ndarray) -> np.ndarray:
    """Indices of up to ``EXAMPLE_FRAMES`` held-out frames of distinct poses, taking the objects in
    turn: for each pose its most deformed frame (most pixels pushed in by > 1 mm against the
    no-contact ``reference`` (H,W) float32 m), deepest poses first."""
    ref_valid = reference > 0
    dent = np.array([int(((reference - d > 1e-3) & (d > 0) & ref_valid).sum()) for d in frames.depth])
    per_object = []
    for name in sorted(set(frames.object_name)):
        best = {}
        for i in np.flatnonzero(frames.object_name == name):
            pose = int(frames.pose_id[i])
            if pose not in best or dent[i] > dent[best[pose]]:
                best[pose] = int(i)
        per_object.append(sorted(best.values(), key=lambda i: -dent[i]))
    picks = []
    for rank in range(max((len(p) for p in per_object), default=0)):
        picks += [p[rank] for p in per_object if rank < len(p)]
    return np.array(picks[:EXAMPLE_FRAMES], dtype=np.int64)


def _registry_reference(validation_path: Path) -> dict | None:
    if not validation_path.is_file():
        return None
    with np.load(validation_path) as z:
        return {"depth_m": z["reference_depth"], "ir": z["reference_ir"], "valid_count": z["valid_count"]}


def _load_sensor_spec(config: CommissionConfig):
    from hw_mocks.sensor_spec import SensorSpec, draw_sensor

    if config.sensor_spec is not None:
        return SensorSpec.from_yaml(config.sensor_spec)
    return draw_sensor(config.seed)


def validate_config(config: CommissionConfig) -> acceptance.Thresholds:
    """Raise ``InputError`` for any bad setting, before the bench opens (``bubble commission`` and
    ``bubble tui`` alike): paths, objects, numbers, the base model, the thresholds and the registry.
    Returns the loaded thresholds."""
    from hw_mocks.objects import load_object
    from trainer.model_dir import load_weights, load_metadata

    run_dir = Path(config.run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise InputError(f"run directory {run_dir} exists and is not a directory")
    if not config.objects:
        raise InputError("no objects to press; give at least one")
    for name in config.objects:
        load_object(name)  # raises InputError for an unknown object or a bad mesh
    if int(config.poses_per_object) < 2:  # the validation holds out a share of each object's poses
        raise InputError(f"poses per object must be at least 2 (one or more is held out), got {config.poses_per_object}")
    if int(config.seed) < 0:
        raise InputError(f"seed must be >= 0, got {config.seed}")
    if not (math.isfinite(config.finetune_minutes) and config.finetune_minutes > 0):
        raise InputError(f"fine-tune minutes must be positive, got {config.finetune_minutes}")
    if config.total_minutes is not None and not config.total_minutes > 0:  # inf: no budget
        raise InputError(f"total minutes must be positive, got {config.total_minutes}")
    if not (math.isfinite(config.leak_hold_s) and config.leak_hold_s > 0):
        raise InputError(f"leak-test hold must be positive, got {config.leak_hold_s} s")
    if config.base_model is not None and not Path(config.base_model).is_dir():
        raise InputError(f"base model directory {config.base_model} does not exist")
    if config.base_model is not None:
        load_metadata(config.base_model)
        load_weights(config.base_model)  # InputError for missing, corrupt or pickled weights
    registry = Path(config.registry_dir) if config.registry_dir is not None else None
    if registry is not None and registry.exists() and not registry.is_dir():
        raise InputError(f"sensor registry {registry} is not a directory")
    if not config.simulated:
        if config.sim_faults or config.sensor_spec is not None:
            raise InputError("sensor specs and simulated faults need the simulated bench (--sim)")
        if config.bench is None:
            raise InputError("the real bench needs its settings (--bench BENCH.yaml), or use --sim")
    else:
        from hw_mocks.sim_bench import parse_sim_fault

        for fault in config.sim_faults:
            parse_sim_fault(fault)
        if not 0.1 <= float(config.sim_speed) <= 100.0:  # the simulated bench's own bounds
            raise InputError(f"simulation speed {config.sim_speed} must be within 0.1..100")
    return acceptance.load_thresholds(config.thresholds)


def run_commissioning(
    config: CommissionConfig,
    on_event: Callable[[CommissionEvent], None] = lambda e: None,
    stop_event: threading.Event | None = None,
) -> CommissionResult:
    """Commission one sensor (see the module docstring); returns the verdict.

    Raises ``InputError`` for bad settings, specs or paths (before anything moves, or when the
    run directory belongs to another run). Hardware faults do not raise: they end the run
    rejected (``result.fault``).
    """
    thresholds = validate_config(config)
    spec = _load_sensor_spec(config) if config.simulated else None
    if config.base_model is None:
        from trainer.model_dir import BASE_MODEL_DIR

        if not BASE_MODEL_DIR.is_dir():
            raise InputError(f"the packaged base model {BASE_MODEL_DIR} is missing; give --base-model MODEL_DIR")
    flow = _Flow(config, on_event, stop_event or threading.Event(), thresholds, spec)
    return flow.run()
