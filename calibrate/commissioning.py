"""The commissioning flow: from a new sensor on the bench to an accepted (or rejected), registered profile.

``run_commissioning(config, on_event, stop_event) -> CommissionResult`` runs the steps of
``calibrate.commission_events.Step`` in order, with the settings of a
``calibrate.commission_config.CommissionConfig``:

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
   simulated runs, against the true depth (``trainer.evaluation``), plus the no-contact statistics
   (``calibrate.run_statistics``);
8. pose check on the mug's held-out poses (``calibrate.pose_check.run_pose_check``);
9. verdict: acceptance checks (``calibrate.acceptance``), ``acceptance.json``, ``report.html``
   (``calibrate.run_report``), and the sensor registry (``calibrate.sensor_registry``).

A failing hardware check (leak, camera health; ``gate: true`` in the thresholds) skips the
remaining data steps: the sensor is rejected without training on it.

Resume: ``RUN_DIR/state.json`` (``calibrate.run_directory.RunState``) records every completed
step and its results; running again with the same ``run_dir`` skips them
(``StepFinished(resumed=True)``) and continues. One run at a time per run directory: a second
``run_commissioning`` of a directory that a run (in this or another process) holds is refused.
Faults: a ``HardwareFault`` safe-stops the arm (stop + retract), keeps every file, and ends the
run rejected with the fault as the reason; the failed step is not recorded, so a re-run
retries it. The recorder's fault (the host's disk full, the session file deleted) says nothing of
the sensor: it safe-stops the arm the same way, then is raised, with no verdict and nothing
registered. ``stop_event`` safe-stops the arm too, and ends with ``result.stopped`` (no verdict);
a stop that comes after the last step's start is honoured before the verdict.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Callable

import numpy as np

from calibrate import acceptance, commission_config
from calibrate.commission_config import RUN_DIR_WRITERS, CommissionConfig, load_sensor_spec, validate_config
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
from calibrate.run_directory import (
    ACCEPTANCE_FILE,
    CAMERA_FILE,
    LEAK_FILE,
    MODEL_DIR,
    PLOTS_DIR,
    POSE_FILE,
    REFERENCE_FILE,
    REPORT_FILE,
    SESSION_FILE,
    VALIDATION_FILE,
    RunState,
    run_settings,
    set_aside,
)
from calibrate.run_report import write_run_report
from calibrate.run_statistics import collection_stats, nocontact_maps, pick_examples, registry_reference
from collect.atomic_files import remove_leftovers, save_npz
from collect.errors import (DISK_FULL_ERRNOS, HOST_FAULTS, HOST_TOO_SLOW_FAULT, RECORDER_FAULT, HardwareFault,
                           InputError, StopRequested)
from collect.json_files import plain_json, write_json
from collect.loop_thread import LoopThread
from collect.output_files import output_folder_lock, write_json_result
from collect.session_format import DEPTH_UNIT_M, utc_now
from trainer.contact import contact_mask
from trainer.metrics import METRIC_KEYS

log = logging.getLogger(__name__)

#: Leak test: the bubble settles this long (s of bench time) before the hold (``CommissionConfig.leak_hold_s``).
LEAK_SETTLE_S = 1.0
#: No-contact frames for the camera health check and for the reference.
HEALTH_FRAMES = 16
REFERENCE_FRAMES = 30
#: Bench snapshots per second while the bench is connected.
SNAPSHOT_HZ = 4.0
#: ``state.json`` key of the run's registry entry id, set before its first registration (``_Flow.finish``).
REGISTRATION_KEY = "registration_id"
#: ``state.json`` key of the registries (resolved paths) the run's verdict is registered in.
REGISTERED_IN_KEY = "registered_in"
#: Steps that need the bench.
BENCH_STEPS = (Step.CONNECT, Step.LEAK_TEST, Step.CAMERA_HEALTH, Step.REFERENCE, Step.COLLECT)


@dataclass
class CommissionResult:
    """What ``run_commissioning`` returns: the verdict, every acceptance check, and where the run's
    files and report are."""

    accepted: bool
    checks: list[dict]  # acceptance.evaluate dicts: {name, value, threshold, op, unit, passed, verdict, gate, reason}
    run_dir: Path
    report_path: Path
    stopped: bool = False  # stop_event ended the run (arm stopped + retracted, data kept)
    fault: str | None = None  # "kind: message" of the hardware fault that ended the run
    reason: str = ""  # one line: why rejected


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
        self._snapshots = LoopThread(self._snapshot_loop, "bench-snapshots")
        self._plan = None  # the collection's CollectionPlan, once planned on the open bench
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
        while not self._snapshots.stop_event.wait(period):
            bench = self.bench
            if bench is not None:
                self._emit_snapshot(bench)

    def _emit_snapshot(self, bench) -> None:
        """A ``BenchSnapshot`` of ``bench``: the arm's state, the latest pressure reading and camera
        frame (none when the arm or the board is at fault: the flow thread raises that fault)."""
        try:
            arm = bench.arm.state()
            reading = bench.pressure.latest()
        except HardwareFault:
            return
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
        self._snapshots.start()

    def _set_latest_frame(self, frame) -> None:
        self._latest_frame = frame

    def close_bench(self, safe_stop: bool) -> None:
        """Stop the snapshots, then (``safe_stop``: stop and retract the arm and) send a last snapshot
        (the arm as the bench leaves it) and close every device."""
        self._snapshots.stop()
        bench, self.bench = self.bench, None
        if bench is None:
            return
        try:
            if safe_stop:
                z_before, _ = _arm_z_and_force(bench)
                retracted = bench.safe_stop()
                z_after, force_after = _arm_z_and_force(bench)
                self.emit(ArmSafeStopped(bool(retracted), z_before, z_after, force_after))
            self._emit_snapshot(bench)
        finally:
            self._bench_cm.__exit__(None, None, None)  # retracts a still-running arm, closes the devices

    # ------------------------------------------------------------------ steps
    def step_connect(self) -> dict:
        from collect.collection import session_metadata

        from calibrate.sensor_registry import SensorRegistry

        self.open_bench()
        b = self.bench
        serial = b.sensor_serial
        # a damaged registry entry of this sensor would fail its registration at the end of the run
        SensorRegistry(self.config.registry_dir).check_entry(serial)
        self.collection_plan()  # a plan this bench cannot run (its limits, its objects) fails before any motion
        b.arm.travel_to(b.home_pose)  # free air above the plate: nothing touches the bubble
        firmware = b.pressure.firmware_version()
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
        save_npz(self.run_dir / LEAK_FILE, t=result.t, hpa=result.hpa)
        checks = [
            acceptance.evaluate(self.thresholds, "leak_rate_hpa_per_min", result.rate_hpa_per_min),
            acceptance.evaluate(self.thresholds, "inflation_pressure_hpa", result.mean_hpa),
        ]
        return {"summary": result.summary(), "leak": result.to_json(), "checks": checks}

    def step_camera_health(self) -> dict:
        from calibrate.camera_health import assess_camera

        frames = self._grab(HEALTH_FRAMES, Step.CAMERA_HEALTH, "no-contact frames")
        health = assess_camera(np.stack([f.ir for f in frames]), np.stack([f.depth for f in frames]))
        save_npz(self.run_dir / CAMERA_FILE, **health.maps())
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
        set_aside(path)
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

    def collection_plan(self):
        """The collection's pose plan over the open bench's objects (``CollectionPlan``; seeded),
        planned once per run. Raises ``InputError`` when the bench cannot run it safely."""
        from collect.collection import plan_bench_collection
        from collect.pose_planner import PlanSettings

        if self._plan is None:
            settings = PlanSettings(poses_per_object=self.config.poses_per_object, seed=self.config.seed)
            self._plan = plan_bench_collection(self.bench, settings)
        return self._plan

    def step_collect(self) -> dict:
        from collect.collection import open_collection_writer, run_collection

        b = self.bench
        plan = self.collection_plan()
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
        stats = collection_stats(path, planned)
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
            point = curve_point(p, time.monotonic() - started)
            if point is None:
                return
            curve.append(point)
            if point["loss"] is not None:  # the validation before the first step has no training loss yet
                self.emit(TrainingProgress(p.step, point["elapsed_s"], p.loss, point["a1"], p.eta_s))
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
            write_on_stop=False,  # a stopped run fine-tunes again on resume: a stop returns at once
        )
        result = train_model(config, on_progress, self.stop_event)
        if result.stopped:
            raise StopRequested("commissioning: stopped by the operator")
        if result.ended_at_deadline and result.train_s < commission_config.MIN_TRAINING_SHARE * deadline_s:
            raise HardwareFault(HOST_TOO_SLOW_FAULT, f"the fine-tune trained {result.train_s:.0f} s of its "
                                f"{deadline_s:.0f} s ({result.steps} steps; loading and validating took the rest): "
                                "this computer is too slow or too busy for the budget; nothing judged, nothing "
                                "registered; free it or raise --finetune-minutes, and run the same command again")
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
        from trainer.evaluation import compare_with_truth, per_object_metrics, predict_frames
        from trainer.inference import DepthEstimator
        from trainer.metrics import depth_metrics
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
        self.check_stop()  # the step's longest part is done: a stop ends the run here (was: at the step's end)
        metrics = depth_metrics(pred, held.depth, **kw)
        per_object = per_object_metrics(pred, held.depth, held.object_name, meta.min_depth, meta.max_depth)
        truth = None
        if held.true_depth is not None:
            truth = compare_with_truth(pred, held.depth, held.true_depth, meta.min_depth, meta.max_depth)
        self.progress(Step.VALIDATE, 0.6, "no-contact statistics")
        arrays = nocontact_maps(estimator, self.run_dir / REFERENCE_FILE)
        # The contact patches: where the ToF sees the membrane pushed in from its rest shape. The
        # whole-image metrics hardly see a few-mm dent (delta < 1.05 is 4.5 mm at 90 mm), these do.
        ref = arrays["reference_depth"]
        contact = contact_mask(held.depth, ref)
        contact_metrics = depth_metrics(pred, held.depth, mask=contact, **kw)
        pick = pick_examples(held, ref)
        arrays.update(
            example_ir=held.ir[pick],
            example_depth=held.depth[pick],
            example_pred=pred[pick],
            example_object=np.array([str(held.object_name[i]) for i in pick]),
            example_pose=held.pose_id[pick],
        )
        if held.true_depth is not None:
            arrays["example_true"] = held.true_depth[pick]
        save_npz(self.run_dir / VALIDATION_FILE, **arrays)
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
                # none held out: no pose to check (was: None, every mug pose, those the model was fine-tuned on too)
                seed=self.config.seed, pose_ids=self.state.get(Step.VALIDATE).get("heldout_pose_ids", {}).get("mug", []),
                plots_dir=self.run_dir / PLOTS_DIR,
            )
        except InputError as err:  # no usable frame: the check fails, the run goes on to a verdict
            checks = [
                acceptance.evaluate(th, "pose_e_x_median_mm", None, str(err)),
                acceptance.evaluate(th, "pose_e_theta_median", None, str(err)),
            ]
            return {"summary": f"no usable mug frame: {err}", "checks": checks}
        # bubble pose's --json document, marked as this run's (bubble pose --json does not write over it)
        write_json_result(self.run_dir / POSE_FILE, "bubble commission", result.to_dict())
        checks = [
            acceptance.evaluate(th, "pose_e_x_median_mm", result.e_x_mm.median),
            acceptance.evaluate(th, "pose_e_theta_median", result.e_theta.median),
        ]
        pose = {  # labels as the report shows them (POSE_BY_POSE_KEY, pose_vs_true_key: read back by benchmarks)
            "hold frames used / held": f"{result.n_used}/{result.n_hold_frames}",
            "e_x (mm), predicted vs measured depth: median / mean / variance (mm^2)":
                [result.e_x_mm.median, result.e_x_mm.mean, result.e_x_mm.variance],
            "e_theta, predicted vs measured depth: median / mean / variance":
                [result.e_theta.median, result.e_theta.mean, result.e_theta.variance],
            POSE_BY_POSE_KEY: {str(p): round(v, 3) for p, v in result.e_x_median_by_pose().items()},
            "pose estimates per second": result.hz,
        }
        for src, stats in result.vs_true.items():
            pose[pose_vs_true_key(src)] = [stats["e_x_mm"].median, stats["e_theta"].median]
        return {"summary": result.summary().splitlines()[1], "pose": pose, "checks": checks}

    # ------------------------------------------------------------------ verdict
    def write_outcome(self, accepted: bool, reason: str, fault: str | None, stopped: bool,
                      finished: str | None = None) -> dict:
        """Write ``acceptance.json`` and ``report.html`` from ``state.json`` and the verdict; returns the
        acceptance document. ``finished``: the verdict's time (ISO 8601, UTC) when it is written again
        for a run that finished before (was: the time of writing, later than the registry's); default now."""
        validate = self.state.get(Step.VALIDATE)
        doc = {
            "accepted": accepted,
            "serial": self.state.data.get("serial"),
            "simulated": bool(self.config.simulated),
            "reason": reason,
            "fault": fault,
            "stopped": stopped,
            "thresholds": {"version": self.thresholds.version, "source": self.thresholds.source},
            "checks": self._all_checks(),
            **dict.fromkeys(METRIC_KEYS),  # null when the run ended before validation
            **validate.get("metrics", {}),
            "per_object": validate.get("per_object"),
            "contact": validate.get("contact"),
            "vs_true": validate.get("vs_true"),
            # the steps before the verdict (was: the verdict too, when written again after it)
            "steps": {s.value: self.state.get(s).get("summary") for s in STEPS
                      if s is not Step.VERDICT and self.state.done(s)},
            "finished": finished or utc_now(),
        }
        # the report first: a disk that fills between the two leaves no acceptance.json of this verdict
        # beside an earlier report (was: an accepted acceptance.json, the report missing, nothing registered)
        write_run_report(self.run_dir, self.state, doc)
        write_json(self.run_dir / ACCEPTANCE_FILE, doc)
        return doc

    def _write_host_fault_outcome(self, fault: HardwareFault) -> None:
        """``acceptance.json`` and ``report.html`` of a run that this computer's fault ended: no verdict,
        nothing registered, the checks made so far (was: left as an earlier attempt wrote them, e.g.
        "stopped" with every check not run, beside a state.json that had gone on to the fine-tune). A
        disk too full to write them leaves the earlier ones (logged): the fault is what the run says."""
        try:
            self.write_outcome(False, f"no verdict: this computer's fault ({fault.kind}), not the sensor's; nothing "
                                      "registered", f"{fault.kind}: {fault}", stopped=False)
        except OSError as err:
            log.error("could not write the run's outcome files: %s", err)

    def _all_checks(self) -> list[dict]:
        """The checks the run's steps made, in step order; a run that ended before its last step adds
        every other check of the thresholds as ``not run`` (a run that reached its end lists what it
        made: without the mug there is no pose check, and the run was not cut short)."""
        checks = self.state.checks()
        if self._all_done():
            return checks
        made = {c["name"] for c in checks}
        return checks + [acceptance.not_run(self.thresholds, name) for name in self.thresholds.checks
                         if name not in made]

    def finish(self, fault: str | None = None, stopped: bool = False) -> CommissionResult:
        """acceptance.json, report.html, (unless stopped) the registry entry and (a verdict reached:
        neither fault nor stop) the verdict step in ``state.json``.

        The registry entry carries an id that ``state.json`` keeps from before the registration (until the
        end of a run that ends in a fault, for good with a verdict): a run killed between the registration
        and the record of its end, and run again, replaces its entry instead of adding a second one."""
        if fault is None and not stopped and self.stop_event.is_set():  # a stop already in: no verdict to write
            # (was: written as the verdict first, ACCEPTED say, then again as stopped)
            return self.finish(stopped=True)
        checks = self.state.checks()
        accepted = acceptance.accepted(checks) and fault is None and not stopped and self._all_done()
        reason = acceptance.rejection_reason(checks, fault)
        if stopped:
            reason = "stopped by the operator before a verdict"
        elif not accepted and not reason:
            reason = "not every step completed"
        elif not accepted and fault is None:
            reason += self._short_finetune_note()
        doc = self.write_outcome(accepted, reason, fault, stopped)
        if fault is None and not stopped and self.stop_event.is_set():
            # a stop while the verdict's report was written: no registration, the run ends stopped and
            # a re-run reaches the verdict again (was: registered, exit 0 or 1)
            return self.finish(stopped=True)
        report_path = self.run_dir / REPORT_FILE
        if not stopped and self.state.data.get("serial"):
            if REGISTRATION_KEY not in self.state.data:
                self.state.data[REGISTRATION_KEY] = uuid.uuid4().hex
                self.state.save()
            self._register(accepted, doc, reason)  # state.json saved with the run's end below: one save, no gap
        if fault is None and not stopped:  # the verdict's entry id and registries stay, for _register_elsewhere
            self.state.record(Step.VERDICT, {"ok": accepted, "summary": "accepted" if accepted else reason,
                                             "reason": reason, "fault": fault})
        elif fault is not None:  # a fault's entry is its own: the resumed run registers its verdict under a new id
            # (a stop keeps the id of a registration killed before its verdict was recorded, which the re-run
            # replaces; was: dropped, and the re-run added a second entry to the sensor's history)
            for key in (REGISTRATION_KEY, REGISTERED_IN_KEY):
                self.state.data.pop(key, None)
            self.state.save()
        self.emit(Verdict(accepted, doc["checks"], str(report_path)))  # as acceptance.json lists them
        return CommissionResult(accepted, checks, self.run_dir, report_path, stopped=stopped, fault=fault, reason=reason)

    def _short_finetune_note(self) -> str:
        """What a rejection's reason adds (``; ...``, else '') when a check of the fine-tuned model failed
        after a fine-tune budget below the default: a healthy sensor fine-tuned a few seconds falls short
        of the thresholds, and the registry would hold its rejection without saying why (was: a 1 s
        fine-tune registered a healthy sensor as rejected on heldout_a1 0.77 alone)."""
        default = CommissionConfig.finetune_minutes
        model_failed = any(acceptance.failed(self.state.get(step).get("checks", []))
                           for step in (Step.VALIDATE, Step.POSE_CHECK))
        if not model_failed or self.config.finetune_minutes >= default:
            return ""
        trained = self.state.get(Step.FINETUNE).get("train_s", float("nan"))
        return (f"; the model fine-tuned {trained:.0f} s (--finetune-minutes {self.config.finetune_minutes:g}, "
                f"under the default {default:g}): commission it again with the default budget before judging the sensor")

    def _register(self, accepted: bool, doc: dict, reason: str, when: datetime | None = None) -> None:
        """Register the run's outcome (``doc``: the ``acceptance.json`` content) in ``config.registry_dir``
        under the run's entry id, at ``when`` (default: now), and add that registry to ``state.json``'s
        ``REGISTERED_IN_KEY`` list (saved by the caller)."""
        from calibrate.sensor_registry import SensorRegistry

        connect = self.state.get(Step.CONNECT)
        registry = SensorRegistry(self.config.registry_dir)
        if accepted:  # what the registry keeps of an accepted run (was: a model/ moved away since a FileNotFoundError
            # traceback, and a validation.npz deleted left the earlier model's reference beside the new model)
            for kept in (self.run_dir / MODEL_DIR, self.run_dir / VALIDATION_FILE):
                if not kept.exists():
                    raise InputError(f"cannot register the accepted sensor in {registry.root}: {kept} is gone (moved "
                                     "or deleted since the run); put it back and run the same command again")
        registry.register(
            self.state.data["serial"],
            entry_id=self.state.data[REGISTRATION_KEY],
            accepted=accepted,
            run_dir=self.run_dir,
            intrinsics=connect.get("intrinsics", {}),
            camera_in_tcp=connect.get("camera_in_tcp"),
            simulated=bool(self.config.simulated),
            acceptance=plain_json(doc),
            reason=reason,
            model_dir=self.run_dir / MODEL_DIR if accepted else None,
            reference=registry_reference(self.run_dir / VALIDATION_FILE) if accepted else None,
            when=when,
        )
        registered = self.state.data.setdefault(REGISTERED_IN_KEY, [])
        if self._registry_root() not in registered:
            registered.append(self._registry_root())

    def _registry_root(self) -> str:
        """The resolved path of ``config.registry_dir`` (or the default registry), as ``REGISTERED_IN_KEY`` lists it."""
        from calibrate.sensor_registry import SensorRegistry

        return str(SensorRegistry(self.config.registry_dir).root.resolve())

    def _all_done(self) -> bool:
        return all(self.state.done(s) for s in STEPS if s != Step.VERDICT)

    # ------------------------------------------------------------------ driver
    def run(self) -> CommissionResult:
        self.started = time.monotonic()
        sensor_id = self.sensor_spec.serial if self.sensor_spec is not None else "hardware"
        self.state = RunState.open(self.run_dir, run_settings(self.config, sensor_id, self.thresholds))
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
        if self.state.done(Step.VERDICT):
            return self._finished_before()
        # a gate failure skips the steps after it: they are not pending (was: a run stopped at its verdict
        # after a failed leak test reopened the bench when run again, and refused a sensor taken off it)
        done = [self.state.get(s) for s in STEPS if self.state.done(s)]
        gate_failure = next(filter(None, map(_gate_failure, done)), None)
        pending_bench = [] if gate_failure else [s for s in BENCH_STEPS if not self.state.done(s)]
        try:
            if pending_bench and self.state.done(Step.CONNECT):
                self.open_bench()  # resuming a bench step: reconnect and re-identify
                serial = self.bench.sensor_serial
                if serial != self.state.data.get("serial"):
                    raise InputError(
                        f"{self.run_dir} was started for sensor {self.state.data.get('serial')}, "
                        f"the bench holds {serial}; use a new --out"
                    )
            for step in STEPS[:-1]:
                if self.state.done(step):
                    rec = self.state.get(step)
                    self.emit(StepFinished(step, rec["ok"], rec["summary"], resumed=True, skipped=bool(rec.get("skipped"))))
                    continue
                if gate_failure is not None:
                    self.emit(StepFinished(step, False, f"not run: {gate_failure}", skipped=True))
                    continue
                self.check_stop()
                if step not in (Step.COLLECT, Step.FINETUNE):  # these announce their own ETA
                    self.emit(StepStarted(step, etas.get(step)))
                with self._full_disk_is_a_recorder_fault():
                    rec = handlers[step]()
                    rec.setdefault("ok", all(c["passed"] for c in rec.get("checks", [])))
                    self.state.record(step, rec)
                gate_failure = _gate_failure(rec)
                if step == Step.COLLECT or gate_failure is not None:
                    self.close_bench(safe_stop=False)  # before the step's end: its last snapshot shows the arm parked
                self.emit(StepFinished(step, rec["ok"], rec["summary"], skipped=bool(rec.get("skipped"))))
            self.close_bench(safe_stop=False)
            self.check_stop()  # a stop during the last step (was: acknowledged, then a verdict registered)
            self.emit(StepStarted(Step.VERDICT))
            with self._full_disk_is_a_recorder_fault():  # (was: exit 2 and an accepted acceptance.json, unregistered)
                result = self.finish()
            if not result.stopped:  # a stopped verdict step is not a failed one (its Verdict event says stopped)
                self.emit(StepFinished(Step.VERDICT, result.accepted, "accepted" if result.accepted else result.reason))
            return result
        except HardwareFault as fault:
            self.emit(FaultRaised(fault.kind, str(fault)))
            self.close_bench(safe_stop=True)
            if fault.kind in HOST_FAULTS:  # the host's disk or CPU, not the sensor: no verdict (was: rejected,
                # registered)
                self._write_host_fault_outcome(fault)
                raise
            return self.finish(fault=f"{fault.kind}: {fault}")
        except StopRequested:
            self.close_bench(safe_stop=True)
            return self.finish(stopped=True)
        except BaseException:
            self.close_bench(safe_stop=True)
            raise

    @contextmanager
    def _full_disk_is_a_recorder_fault(self) -> Iterator[None]:
        """A full disk in the with-block is this computer's, not the sensor's: ``HardwareFault`` of the
        recorder (exit 3, no verdict, nothing registered; was: exit 2, "bad input", after the arm had
        moved). Other ``OSError`` pass through."""
        try:
            yield
        except OSError as err:
            if err.errno not in DISK_FULL_ERRNOS:
                raise
            raise HardwareFault(RECORDER_FAULT, f"cannot write {err.filename or self.run_dir}: "
                                                f"{err.strerror or err}") from None

    def _finished_before(self) -> CommissionResult:
        """The verdict of a run that already finished in this directory, as its ``state.json`` recorded it
        (nothing runs again, and the sensor is not registered again in a registry it was registered in; a
        deleted report or ``acceptance.json`` is written again from ``state.json``)."""
        for step in STEPS:
            if self.state.done(step):
                rec = self.state.get(step)
                self.emit(StepFinished(step, rec["ok"], rec["summary"], resumed=True, skipped=bool(rec.get("skipped"))))
            else:  # not run: a hardware check failed before it
                self.emit(StepFinished(step, False, "not run", resumed=True, skipped=True))
        verdict, checks = self.state.get(Step.VERDICT), self.state.checks()
        report = self.run_dir / REPORT_FILE
        doc = None
        if not report.is_file() or not (self.run_dir / ACCEPTANCE_FILE).is_file():  # deleted since: written anew
            doc = self.write_outcome(verdict["ok"], verdict["reason"], verdict["fault"], False, verdict["finished"])
        self._register_elsewhere(verdict, doc)
        self.emit(Verdict(verdict["ok"], self._all_checks(), str(report)))  # as acceptance.json lists them
        return CommissionResult(verdict["ok"], checks, self.run_dir, report, fault=verdict["fault"], reason=verdict["reason"])

    def _register_elsewhere(self, verdict: dict, doc: dict | None) -> None:
        """Register a finished run in ``config.registry_dir`` when that is a registry it is not in yet (was:
        nothing registered, and nothing said, when the same command ran again with another ``--registry``):
        the same entry id, at the time of the verdict. ``doc``: the ``acceptance.json`` content just written
        (None: written again from ``state.json``, the file may have been edited since). Runs that finished
        before the registries were recorded are left as they are."""
        registered = self.state.data.get(REGISTERED_IN_KEY)
        if registered is None or REGISTRATION_KEY not in self.state.data or self._registry_root() in registered:
            return
        if doc is None:
            doc = self.write_outcome(verdict["ok"], verdict["reason"], verdict["fault"], False, verdict["finished"])
        self._register(verdict["ok"], doc, verdict["reason"], when=datetime.fromisoformat(verdict["finished"]))
        self.state.save()

    def _speed(self) -> float:
        return float(self.config.sim_speed) if self.config.simulated else 1.0


#: The pose check's median e_x (mm) per held-out mug pose, in ``state.json``'s ``pose_check`` step.
POSE_BY_POSE_KEY = "e_x (mm) median per held-out mug pose"


def pose_vs_true_key(source: str) -> str:
    """The ``pose_check`` entry of the pose fitted to ``source`` depth ("predicted", "measured", "true")
    against the simulator's true pose: [median e_x (mm), median e_theta]."""
    return f"pose from {source} depth vs the true pose: e_x (mm) / e_theta, medians"


#: The fine-tune's curve keeps every this many training steps (besides each validation and the end).
CURVE_EVERY_STEPS = 5


def curve_point(progress, elapsed_s: float) -> dict | None:
    """The fine-tune curve's point for a ``trainer.training.TrainProgress`` (``elapsed_s``: s since the
    step began): ``{step, elapsed_s, loss (m, None before a first step), a1 (validation, or None)}``, or
    None for a step the curve leaves out. Every ``CURVE_EVERY_STEPS``-th step, each validation and the
    end are kept; the end carries the final validation's a1 (was: none, the TUI's a1 chart stopped at
    the last periodic validation)."""
    if progress.event == "step" and progress.step % CURVE_EVERY_STEPS != 0:
        return None
    a1 = progress.val.get("a1") if (progress.event in ("eval", "done") and progress.val) else None
    loss = progress.loss if math.isfinite(progress.loss) else None
    return {"step": progress.step, "elapsed_s": elapsed_s, "loss": loss, "a1": a1}


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


def run_commissioning(
    config: CommissionConfig,
    on_event: Callable[[CommissionEvent], None] = lambda e: None,
    stop_event: threading.Event | None = None,
) -> CommissionResult:
    """Commission one sensor (see the module docstring); returns the verdict.

    Raises ``InputError`` for bad settings, specs or paths (before anything moves, or when the
    run directory belongs to another run or another run is writing it). Hardware faults do not
    raise: they end the run rejected (``result.fault``); the recorder's fault (the host's disk)
    raises, after the arm's safe stop.
    """
    thresholds = validate_config(config)
    spec = load_sensor_spec(config) if config.simulated else None
    flow = _Flow(config, on_event, stop_event or threading.Event(), thresholds, spec)
    flow.run_dir.mkdir(parents=True, exist_ok=True)
    with output_folder_lock(flow.run_dir, RUN_DIR_WRITERS):
        remove_leftovers(flow.run_dir)  # of a run killed while it wrote a file
        return flow.run()
