"""``bubble commission`` (commission one sensor end to end) and ``bubble sensors`` (the registry).

``bubble commission`` exits 0 when the sensor is accepted, 1 when rejected (a failed check or a
hardware fault; the data recorded so far stays in RUN_DIR and a re-run resumes), 2 for bad input,
3 when the recorder stopped (this computer's disk: nothing is registered), 130 when stopped with
Ctrl-C (143 SIGTERM, 129 SIGHUP; the arm is stopped and retracted first).
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from pathlib import Path

from collect.stop_signals import INTERRUPTS, exit_code, forget_pending_stop, stop_signals_handled
from collect.cli import DEFAULT_OBJECTS_ARG, check_sim_options, progress_place
from collect.errors import EXIT_OK, EXIT_REJECTED, InputError
from collect.output_files import named_path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "commission",
        help="commission a sensor: leak test, camera health, calibration set, fine-tune, validate, report",
        description="Commission a new bubble sensor end to end and register it. Exit 0 accepted, 1 rejected (a "
        "failed check or a hardware fault), 2 bad input, 3 a fault of this computer, nothing judged or registered "
        "(its disk stopped the recorder, or its CPU was too busy to fine-tune or to keep the robot's watchdog fed), "
        "130 stopped by Ctrl-C (143 SIGTERM, 129 SIGHUP). Re-running with the same --out resumes from "
        "the last completed step.",  # was: 0, 1 and 2 only
    )
    p.add_argument("--out", type=named_path, required=True, metavar="RUN_DIR", help="run directory (created; resumed if it exists)")
    add_run_options(p)
    p.add_argument("--quiet", action="store_true", help="print only the verdict")
    p.set_defaults(func=run_commission)

    s = subparsers.add_parser(
        "sensors",
        help="list the sensor registry (or one sensor's history)",
        description="List the commissioned sensors in the registry, or show one sensor's profile and history.",
    )
    s.add_argument("serial", nargs="?", help="show this sensor's profile and commissioning history")
    s.add_argument("--registry", type=named_path, metavar="DIR", help="registry directory (default: $BUBBLE_REGISTRY or the user data dir)")
    s.add_argument("--json", action="store_true", help="print JSON instead of a table")
    s.set_defaults(func=run_sensors)


def add_run_options(p) -> None:
    """The options of a commissioning run that ``bubble commission`` and ``bubble tui`` share."""
    from calibrate.commission_config import CommissionConfig

    p.add_argument("--sim", action="store_true", help="use the simulated bench (no hardware)")
    p.add_argument("--bench", type=named_path, metavar="BENCH.yaml", help="real bench settings (arm host, camera, serial port)")
    p.add_argument("--sensor", type=named_path, metavar="SPEC.yaml", help="simulated sensor spec (default: drawn from --seed)")
    p.add_argument("--thresholds", type=named_path, metavar="YAML", help="acceptance thresholds overriding the packaged ones")
    p.add_argument("--registry", type=named_path, metavar="DIR", help="sensor registry directory (default: $BUBBLE_REGISTRY or the user data dir)")
    p.add_argument("--base-model", type=named_path, metavar="MODEL_DIR", help="model to fine-tune from (default: the packaged base model)")
    p.add_argument("--finetune-minutes", type=float, default=CommissionConfig.finetune_minutes, metavar="M",
                   help="fine-tuning time budget (default %(default)s)")
    p.add_argument("--total-minutes", type=float, default=CommissionConfig.total_minutes, metavar="M",
                   help="wall-time budget of the whole run; the fine-tune is shortened to fit it (default %(default)s)")
    p.add_argument("--leak-hold-s", type=float, default=CommissionConfig.leak_hold_s, metavar="S",
                   help=f"leak-test hold, s of bench time (default {CommissionConfig.leak_hold_s:g})")
    p.add_argument("--objects", help="comma-separated objects to press (default: those of bubble commission's --bench "
                                     "file, else "
                                     f"{DEFAULT_OBJECTS_ARG})")
    p.add_argument("--poses-per-object", type=int, default=CommissionConfig.poses_per_object, metavar="K",
                   help="contact poses per object (default %(default)s)")
    p.add_argument("--seed", type=int, default=CommissionConfig.seed, help="seed of the pose plan and of the simulated sensor")
    p.add_argument("--sim-fault", action="append", default=[], metavar="KIND@SECONDS", help="inject a fault (simulated bench)")
    p.add_argument("--sim-speed", type=float, default=CommissionConfig.sim_speed, help="simulated clock speed-up (simulated bench)")


def run_config(args, run_dir: str | Path):
    """The ``CommissionConfig`` of ``add_run_options``' options, for ``run_dir``: the simulated bench
    (``--sim``) or the real bench of ``--bench`` (``InputError`` for both, and for sim-only options
    without ``--sim``)."""
    from calibrate.commission_config import CommissionConfig
    from trainer.cli import check_model_arg

    bench = None
    if args.bench is not None:
        if args.sim:
            raise InputError("--bench describes real hardware; drop it or --sim")
        from collect.bench import BenchConfig

        bench = BenchConfig.from_yaml(args.bench)
    check_sim_options(args)

    def path(text: str | None) -> Path | None:
        return None if text is None else Path(text)

    check_model_arg(args.base_model, "--base-model")  # its text: as a path, ./base reads as 'base'

    # the real bench's plate holds the objects its file lists (was: the four built-ins pressed whatever it held)
    objects = args.objects if args.objects is not None else (
        ",".join(bench.objects) if bench is not None else DEFAULT_OBJECTS_ARG)

    return CommissionConfig(
        run_dir=Path(run_dir),
        simulated=args.sim,
        sensor_spec=path(args.sensor),
        bench=bench,
        thresholds=path(args.thresholds),
        registry_dir=path(args.registry),
        base_model=None if args.base_model == "base" else path(args.base_model),
        finetune_minutes=args.finetune_minutes,
        total_minutes=args.total_minutes,
        objects=tuple(name.strip() for name in objects.split(",") if name.strip()),
        poses_per_object=args.poses_per_object,
        seed=args.seed,
        sim_faults=tuple(args.sim_fault),
        sim_speed=args.sim_speed,
        leak_hold_s=args.leak_hold_s,
    )


class ProgressPrinter:
    """Turns commissioning events into terminal lines on ``stream`` (throttled live progress)."""

    def __init__(self, stream=sys.stderr, interval_s: float = 2.0):
        self.stream = stream
        self.interval_s = interval_s
        self._last = 0.0

    def _print(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    def _due(self) -> bool:
        now = time.monotonic()
        if now - self._last >= self.interval_s:
            self._last = now
            return True
        return False

    def __call__(self, event) -> None:
        from calibrate import commission_events as ev

        if isinstance(event, ev.StepStarted):
            eta = f" (~{event.eta_s:.0f} s)" if event.eta_s else ""
            self._print(f"[{event.step.value}] started{eta}")
        elif isinstance(event, ev.StepFinished):
            tag = "resumed" if event.resumed else ("ok" if event.ok else "FAILED")
            if event.skipped:
                tag = "skipped"
            self._print(f"[{event.step.value}] {tag}: {event.summary}")
        elif isinstance(event, ev.StepProgress) and event.message and self._due():
            self._print(f"[{event.step.value}] {event.fraction:4.0%} {event.message}")
        elif isinstance(event, ev.CollectionProgress) and self._due():
            where = progress_place(event.object_name, event.pose_index, event.poses_per_object)
            self._print(
                f"[collect] {where} {event.phase}: {event.frames} frames, "
                f"{event.force_n:.1f} N, {event.pressure_hpa:.1f} hPa"
            )
        elif isinstance(event, ev.TrainingProgress) and (self._due() or event.a1 is not None):
            a1 = f", val a1 {event.a1:.3f}" if event.a1 is not None else ""
            eta = f", {event.eta_s:.0f} s left" if event.eta_s is not None else ""
            self._print(f"[finetune] step {event.step}: loss {event.loss * 1000:.3f} mm{a1}{eta}")
        elif isinstance(event, ev.FaultRaised):
            self._print(f"FAULT {event.kind}: {event.message}")
        elif isinstance(event, ev.ArmSafeStopped):
            self._print(event.summary())


def run_commission(args) -> int:
    from calibrate.commissioning import run_commissioning

    config = run_config(args, args.out)
    stop, done = threading.Event(), threading.Event()
    printer = (lambda e: None) if args.quiet else ProgressPrinter()
    outcome: dict = {}

    def work() -> None:
        try:
            outcome["result"] = run_commissioning(config, on_event=printer, stop_event=stop)
        except BaseException as err:  # handed to the main thread, which reports it
            outcome["error"] = err
        finally:
            done.set()

    def on_stop(signum: int) -> None:
        # Ctrl-C (or SIGTERM, SIGHUP) only asks the flow to stop: it halts the arm, retracts and closes the files itself.
        print("bubble: stopping the arm and closing the run ...", file=sys.stderr)
        outcome["signum"] = signum
        stop.set()

    with stop_signals_handled(on_stop, INTERRUPTS):
        threading.Thread(target=work, name="commission", daemon=True).start()
        while not done.wait(0.2):
            pass
    if "error" in outcome:
        raise outcome["error"]
    result = outcome["result"]
    if result.stopped:
        print(f"STOPPED: data kept in {result.run_dir}; re-run the same command to resume", file=sys.stderr)
        return exit_code(outcome.get("signum", signal.SIGINT))
    if "signum" in outcome:  # the flow had registered its verdict when the stop came: the verdict stands
        print("bubble: the stop came after the verdict was reached; the verdict stands", file=sys.stderr)
        forget_pending_stop()
    if result.accepted:
        print(f"ACCEPTED: report {result.report_path}")
        return EXIT_OK
    print(f"REJECTED: {result.reason}")
    print(f"report {result.report_path}")
    return EXIT_REJECTED


def run_sensors(args) -> int:
    from calibrate.sensor_registry import SensorRegistry

    registry = SensorRegistry(args.registry)
    if args.serial is not None:
        profile = registry.get(args.serial)
        if args.json:
            print(json.dumps(profile.data, indent=2))
            return EXIT_OK
        data = profile.data
        print(f"{profile.serial}: {profile.status} ({'simulated' if data.get('simulated') else 'hardware'})")
        print(f"  directory  {profile.path}")
        accepted = f" (accepted {data['accepted_at']})" if profile.model_dir and "accepted_at" in data else ""
        print(f"  model      {profile.model_dir or '-'}{accepted}")
        for name in profile.missing():
            print(f"  MISSING    {name}: profile.json names it, but {profile.path} no longer holds it (deleted?); "
                  "commission the sensor again")
        for entry in profile.history:
            verdict = "accepted" if entry["accepted"] else "rejected"
            a1 = f" a1={entry['a1']:.3f}" if entry.get("a1") is not None else ""
            reason = f" - {entry['reason']}" if entry.get("reason") else ""
            try:
                gone = "" if Path(entry["run_dir"]).is_dir() else " (run folder deleted)"
            except OSError as err:  # a folder on the way that cannot be entered
                gone = f" (run folder cannot be read: {err.strerror})"
            print(f"  {entry['time']}  {verdict}{a1}  {entry['run_dir']}{gone}{reason}")
        return EXIT_OK
    listing = registry.survey()
    profiles = listing.profiles
    if args.json:
        print(json.dumps([p.data for p in profiles], indent=2))
    else:
        absent = "" if registry.root.is_dir() else " (no such directory yet: the first commissioning creates it)"
        print(f"registry {registry.root}: {len(profiles)} sensor{'s' if len(profiles) != 1 else ''}{absent}")
        if profiles:  # abs_rel and a1: the kept model's, at its acceptance (a rejected run changes neither)
            print(f"{'serial':<28} {'status':<9} {'last commissioned':<26} {'runs':>4}  {'model':<8} {'abs_rel':>8} "
                  f"{'a1':>6}")
        for p in profiles:
            m = p.model_metrics
            a1 = f"{m['a1']:.3f}" if m.get("a1") is not None else "-"
            rel = f"{m['abs_rel']:.4f}" if m.get("abs_rel") is not None else "-"
            print(f"{p.serial:<28} {p.status:<9} {p.data.get('last_commissioned', '-'):<26} {len(p.history):>4}  "
                  f"{p.model_state:<8} {rel:>8} {a1:>6}")
    problem = listing.problem()
    if problem is not None:  # the readable sensors are listed above
        raise InputError(problem)
    return EXIT_OK
