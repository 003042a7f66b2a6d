"""Pretraining of the base model on many simulated sensors (see docs/model_card.md).

Two steps, both resumable:

    # 1. record one simulated calibration session per sensor (bubble sim new-sensor + bubble collect --sim)
    .venv/bin/python -m trainer.pretrain collect --sensors 16 --work runs/pretrain --jobs 2
    # 2. train on all but the last --val-sensors sessions, validate on those (held-out sensors),
    #    and package the result into --out (weights, metadata, ONNX; <= 20 MB): here the shipped
    #    base model, trainer/base_model/, whose model card (docs/model_card.md) is then rewritten too
    .venv/bin/python -m trainer.pretrain train --work runs/pretrain --minutes 30 --out trainer/base_model
    # ... or data-parallel (gloo on CPU, nccl on GPU):
    torchrun --nproc_per_node 2 -m trainer.pretrain train --work runs/pretrain --epochs 20 --out trainer/base_model

``--out`` has no default: it names a new or empty folder, or an earlier model directory, which is
replaced; any other folder is refused. A Ctrl-C (SIGTERM, SIGHUP) in ``collect`` stops the sessions
being recorded (the finished ones are kept; the same command records the others); in ``train`` it
checkpoints the step in progress (in ``--work``/model), as in ``bubble train``; the same command with
``--resume`` continues.

Sensors are drawn with seeds ``--first-seed .. --first-seed + sensors - 1``; the collection uses
the same seed for its pose plan. The sessions go through the product's own commands, so the base
model sees exactly what commissioning records.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path

from collect.atomic_files import replacing
from collect.errors import (EXIT_BAD_INPUT, EXIT_INTERRUPTED, BubbleCommandError, InputError, OneLineParser,
                            os_error_exit)
from collect.output_files import check_parent_dirs, named_path
from collect.pose_planner import MAX_POSES_PER_OBJECT
from collect.stop_signals import INTERRUPTS, Terminated, raise_interrupt, stop_signals_handled
from hw_mocks.sensor_spec import MAX_SEED as MAX_SENSOR_SEED
from trainer.augmentation import PRETRAIN_NOISE_STD
from trainer.cli import a1_text, add_training_options, training_options
from trainer.doc_sections import update_section
from trainer.model_dir import BASE_MODEL_DIR, METADATA_FILE, ONNX_FILE, WEIGHTS_FILE, load_metadata

#: Upper bound for the committed base model directory (bytes).
MAX_BASE_MODEL_BYTES = 20 * 1024 * 1024
#: The model card of the shipped base model, whose "pretraining" section ``train`` rewrites when it
#: replaces that model (in a source checkout; ``chosen_model_card``).
MODEL_CARD = Path(__file__).resolve().parents[1] / "docs" / "model_card.md"
#: Directory inside ``--work`` where ``train`` keeps its model and checkpoint (packaged to ``--out``).
TRAIN_DIR = "model"

#: Longest a single ``bubble`` command may run before it counts as hung (s).
COMMAND_TIMEOUT_S = 1800.0
#: How often ``collect``'s main thread looks for a stop whose ``KeyboardInterrupt`` was lost (s).
STOP_POLL_S = 0.2
#: Longest a ``bubble`` command that ``collect`` stopped (its Ctrl-C) may take to close its files before
#: it is killed (s).
STOP_TIMEOUT_S = 60.0


class BubbleCommands:
    """Runs ``bubble`` commands in subprocesses, from the threads of ``collect``'s jobs, and stops the
    running ones together (``stop``)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self._stopped = False

    def run(self, *argv: str) -> None:
        """Run ``bubble argv``; raise ``BubbleCommandError`` with its last error line when it fails or
        hangs, or when ``stop`` came first."""
        with self._lock:  # no command starts after ``stop``
            if self._stopped:
                raise BubbleCommandError(f"bubble {argv[0]} not started: stopped")
            proc = subprocess.Popen([sys.executable, "-m", "calibrate.cli", *argv], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
            self._running.add(proc)
        try:
            try:
                _, err = proc.communicate(timeout=COMMAND_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
                raise BubbleCommandError(f"bubble {argv[0]} timed out after {COMMAND_TIMEOUT_S:.0f} s") from None
        finally:
            with self._lock:
                self._running.discard(proc)
        if proc.returncode != 0:
            last = (err.strip().splitlines() or ["(no output)"])[-1]
            raise BubbleCommandError(f"bubble {argv[0]} {argv[1] if len(argv) > 1 else ''} failed: {last}",
                                     proc.returncode)

    def stop(self) -> None:
        """Start no more commands, and stop the running ones as a Ctrl-C stops ``bubble`` (the arm
        retracted, the files closed); one still running after ``STOP_TIMEOUT_S`` is killed."""
        with self._lock:
            self._stopped = True
            running = list(self._running)
        for proc in running:
            proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for proc in running:
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()


def session_path(work: Path, seed: int) -> Path:
    return work / f"sensor_{seed:05d}.h5"


def collect_one(work: Path, seed: int, objects: str | None, poses: int, sim_speed: float,
                commands: BubbleCommands | None = None) -> Path:
    """Draw sensor ``seed`` and record its calibration session (skipped when already recorded);
    ``objects``: comma-separated, None for ``bubble collect``'s default; ``commands``: runs the
    ``bubble`` commands (default: a new ``BubbleCommands``)."""
    bubble = (commands or BubbleCommands()).run
    out = session_path(work, seed)
    if out.exists():
        return out
    spec = work / f"sensor_{seed:05d}.yaml"
    if not spec.exists():
        bubble("sim", "new-sensor", "--seed", str(seed), "--out", str(spec))
    partial = out.with_suffix(".partial.h5")
    partial.unlink(missing_ok=True)
    bubble("collect", "--sim", "--sensor", str(spec), *(["--objects", objects] if objects else []),
           "--poses-per-object", str(poses), "--seed", str(seed), "--sim-speed", str(sim_speed), "--quiet",
           "--out", str(partial))
    partial.replace(out)
    return out


def check_collect_options(seeds: range, objects: str | None, sim_speed: float) -> None:
    """Raise InputError for what ``bubble sim new-sensor`` and ``bubble collect`` would refuse once per
    sensor: a sensor seed of ``seeds`` (not empty) out of range (was: every sensor failed, exit 1), an
    unknown object (or a bad mesh file) in ``objects`` and a ``sim_speed`` out of range; checked before
    any sensor."""
    from collect.cli import object_list
    from hw_mocks.objects import load_object
    from hw_mocks.sim_bench import check_sim_speed

    if not (seeds.start >= 0 and seeds[-1] <= MAX_SENSOR_SEED):
        raise InputError("sensor seeds --first-seed .. --first-seed + --sensors - 1 must be within "
                         f"0..{MAX_SENSOR_SEED}, got {seeds.start}..{seeds[-1]}")
    check_sim_speed(sim_speed)
    for name in object_list(objects, []) if objects is not None else ():
        load_object(name)


def result_unless_stopped(future: Future, signalled: list[int]) -> Path:
    """``future.result()``, or the stop in ``signalled`` (the signals received, in order) raised again
    within ``STOP_POLL_S``: Python only prints a ``KeyboardInterrupt`` raised while a weakref callback
    runs ("Exception ignored in"), and such a lost Ctrl-C let every queued sensor be recorded."""
    while not wait([future], timeout=STOP_POLL_S).done:
        if signalled:
            raise_interrupt(signalled[0])
    return future.result()


def max_jobs() -> int:
    """Most sessions ``collect`` records at once: the CPUs of this machine (one simulated bench each)."""
    return os.cpu_count() or 1


def run_collect(args: argparse.Namespace) -> int:
    """Record the sessions of ``--sensors`` sensors, ``--jobs`` at a time. A stop (Ctrl-C, SIGTERM,
    SIGHUP) starts no further sensor and stops the ``bubble`` commands that run (``BubbleCommands.stop``):
    the sessions recorded so far are kept, the same command records the others (was: every queued
    sensor was recorded before the command ended)."""
    if args.sensors < 1 or args.jobs < 1 or args.poses_per_object < 1:
        raise InputError("--sensors, --jobs and --poses-per-object must be at least 1")
    if args.poses_per_object > MAX_POSES_PER_OBJECT:  # was: refused by each sensor's bubble collect, exit 1
        raise InputError(f"--poses-per-object must be 1..{MAX_POSES_PER_OBJECT}, got {args.poses_per_object}")
    if args.jobs > max_jobs():  # was: any number of simulated benches at once, each falling behind its clock
        raise InputError(f"--jobs must be 1..{max_jobs()} (the CPUs of this machine: each job runs a simulated "
                         f"bench), got {args.jobs}")
    if args.objects is not None and not args.objects.strip(" ,"):
        raise InputError("--objects names no object: name some, or drop the option for every object")
    seeds = range(args.first_seed, args.first_seed + args.sensors)
    check_collect_options(seeds, args.objects, args.sim_speed)
    work = Path(args.work)
    if work.exists() and not work.is_dir():
        raise InputError(f"--work {work} is a file, not a directory")
    check_parent_dirs(work / "sensor.h5")
    work.mkdir(parents=True, exist_ok=True)
    commands = BubbleCommands()
    failed = 0
    signalled: list[int] = []

    def on_signal(signum: int) -> None:
        signalled.append(signum)
        raise_interrupt(signum)

    with stop_signals_handled(on_signal, INTERRUPTS, process_ends=True), \
            ThreadPoolExecutor(max_workers=args.jobs) as pool:
        try:
            futures = {seed: pool.submit(collect_one, work, seed, args.objects, args.poses_per_object,
                                         args.sim_speed, commands) for seed in seeds}
            for seed, future in futures.items():
                try:
                    print(f"sensor seed {seed}: {result_unless_stopped(future, signalled)}", flush=True)
                except BubbleCommandError as err:  # one bad simulated sensor does not stop the others
                    failed += 1
                    print(f"sensor seed {seed}: {err}", file=sys.stderr, flush=True)
            if signalled:  # after the last sensor's result; its KeyboardInterrupt was lost
                raise_interrupt(signalled[0])
        except KeyboardInterrupt:  # and Terminated; was: the with-block waited for every queued sensor
            pool.shutdown(wait=False, cancel_futures=True)
            commands.stop()
            raise
    print(f"{args.sensors - failed} of {args.sensors} sessions in {work}", flush=True)
    return 1 if failed else 0


def package_base_model(model_dir: Path, out: Path) -> Path:
    """Copy the deployable files of ``model_dir`` into ``out`` once they fit the size budget (``InputError``
    otherwise, ``out`` untouched; was: copied over the base model, then refused). Each file is
    copied whole beside its target and renamed over it (``atomic_files.replacing``), the three
    renames last, and a deployable file of ``out`` that ``model_dir`` lacks (an ONNX export) is
    removed: a failed copy leaves the earlier model, never new weights beside old metadata."""
    names = [name for name in (WEIGHTS_FILE, METADATA_FILE, ONNX_FILE) if (model_dir / name).is_file()]
    size = sum((model_dir / name).stat().st_size for name in names)
    if size > MAX_BASE_MODEL_BYTES:
        raise InputError(f"base model is {size / 2**20:.1f} MB, over the {MAX_BASE_MODEL_BYTES / 2**20:.0f} MB "
                         f"budget; {out} is left as it was")
    out.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as copies:  # every copy written before the first rename
        for name in names:
            shutil.copy2(model_dir / name, copies.enter_context(replacing(out / name)))
    for name in {WEIGHTS_FILE, METADATA_FILE, ONNX_FILE} - set(names):
        (out / name).unlink(missing_ok=True)
    return out


def _number_or_nan(value) -> float:
    """``value`` as a float; NaN for None (JSON's null for NaN; absent without an ONNX export)."""
    return float("nan") if value is None else float(value)


def write_model_card_section(model_dir: Path, card: Path, command: str) -> None:
    """Record the pretraining run of ``model_dir`` (data, budget, metrics) in the model card."""
    meta = load_metadata(model_dir)
    t, m = meta.training, meta.metrics
    size = sum(p.stat().st_size for p in model_dir.iterdir() if p.is_file()) / 2**20
    minutes = t["budget"].get("minutes")
    budget = f"{minutes} min of training" if minutes is not None else f"{t['budget'].get('epochs')} epochs"
    lines = [
        f"Command: `{command}`",
        "",
        f"* network: `{meta.arch}` width {meta.width}, input {meta.geometry.input_width} x {meta.geometry.input_height}, "
        f"depth range {meta.min_depth}-{meta.max_depth} m; directory {size:.1f} MB",
        f"* training data: {len(t['sources'])} simulated sensors ({', '.join(t['sensor_serials'])}), "
        f"{t['n_train_frames']} frames (contact + 10 % free, frame stride {t['frame_stride']}), objects {', '.join(t['objects'])}",
        f"* validation: {len(t['val_sources'])} held-out sensors, {t['n_val_frames']} frames",
        f"* budget: {budget}, done {t['epochs']:.1f} epochs / {t['steps']} steps in {t['train_s'] / 60:.1f} min "
        f"of training on {t['world_size']} process(es), batch {t['batch_size']}, peak RSS {t['peak_rss_mb']:.0f} MB"
        + (f", continued from a model trained on {len(t['init']['sensor_serials'])} sensors" if t.get("init") else ""),
        f"* loss: {t['loss']}, contact patches weighted {1 + t.get('contact_weight', 0):g}x",
        f"* held-out sensors (vs ToF): a1 {m['a1']:.3f}, abs_rel {m['abs_rel']:.4f}, rmse {m['rmse'] * 1e3:.2f} mm, "
        f"rmse_log {m['rmse_log']:.4f}, silog {m['silog']:.3f}",
        f"* inference: {meta.inference.get('runtime', 'torch')}, ONNX max |ORT - torch| "
        f"{_number_or_nan(meta.inference.get('onnx_max_abs_diff_m')):.1e} m",
    ]
    card.parent.mkdir(parents=True, exist_ok=True)  # checked before the training (check_model_card)
    update_section(card, "pretraining", "Pretraining run (written by `python -m trainer.pretrain train`)", lines)


def check_base_model_out(out: Path) -> None:
    """Raise InputError unless the base model can be packaged into ``out`` (``package_base_model``): a
    new or empty folder (missing folders are created), or an earlier model directory, which is replaced:
    nothing in it but a model's files, ``model.safetensors`` among them, and a ``metadata.json`` that
    ``load_metadata`` reads (was: any folder, its files replaced without a word)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, not a model directory")
    check_parent_dirs(out / WEIGHTS_FILE)
    try:
        found = {p.name for p in out.iterdir()} if out.is_dir() else set()
    except OSError as err:  # a folder this user may not list
        raise InputError(f"cannot read {out}: {err.strerror}") from None
    if not found:
        return
    strangers = sorted(found - {WEIGHTS_FILE, METADATA_FILE, ONNX_FILE})
    if strangers or WEIGHTS_FILE not in found:
        reason = f"it holds {strangers[0]}" if strangers else f"it has no {WEIGHTS_FILE}"
    else:
        try:
            load_metadata(out)
            return
        except InputError as err:
            reason = str(err)
    raise InputError(f"--out {out} is neither empty nor a model directory ({reason}); refusing to replace its "
                     "files: choose a new or empty folder, or an earlier model")


def chosen_model_card(option: str | None, out: Path) -> Path | None:
    """The model card whose pretraining section ``train`` rewrites: ``--model-card`` (``option``; '' for
    none), by default ``MODEL_CARD`` when ``out`` is the shipped base model, which the card describes,
    and none otherwise (was: ``MODEL_CARD`` whatever ``--out`` was)."""
    if option is not None:
        return Path(option) if option else None
    return MODEL_CARD if MODEL_CARD.parent.is_dir() and out.resolve() == BASE_MODEL_DIR.resolve() else None


#: Suffixes of the files ``--model-card`` may name: markdown, as its section is.
MODEL_CARD_SUFFIXES = (".md", ".markdown")


def check_model_card(card: Path) -> None:
    """Raise InputError unless the model card ``card`` can be written once the training is done: a
    markdown file (``MODEL_CARD_SUFFIXES``), new or readable UTF-8 text, whose missing folders can be
    created (``check_parent_dirs``). Was: any file, a metadata.json or a YAML file given a markdown
    section appended, and an HDF5 file a UnicodeDecodeError traceback after the whole training."""
    if card.is_dir():
        raise InputError(f"--model-card {card} is a directory, not a markdown file")
    if card.suffix.lower() not in MODEL_CARD_SUFFIXES:
        raise InputError(f"--model-card {card} is not a markdown file (.md): refusing to write a model card "
                         "section into it")
    check_parent_dirs(card)
    if card.exists():
        try:
            card.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise InputError(f"--model-card {card} is not UTF-8 text: refusing to write a model card section "
                             "into it") from None
        except OSError as err:
            raise InputError(f"cannot read --model-card {card}: {err.strerror}") from None


def run_train(args: argparse.Namespace) -> int:
    """Train on the sessions of ``--work`` and package the base model. A stop (Ctrl-C, SIGTERM, SIGHUP)
    ends it as it ends ``bubble train`` (``trainer.stop_on_signal``): at once while the data loads,
    else after the step in progress, checkpointed in ``--work``/model for ``--resume``."""
    from trainer.checkpoint import check_checkpoint_use
    from trainer.stop_on_signal import TrainingStop

    work = Path(args.work)
    if not work.is_dir():
        raise InputError(f"--work {work} is not a directory of sessions (python -m trainer.pretrain collect records them)")
    out = Path(args.out)
    if out.resolve() == (work / TRAIN_DIR).resolve():
        raise InputError(f"--out {args.out} is where training keeps its checkpoint; package the base model elsewhere")
    check_base_model_out(out)
    if args.val_sensors < 1:
        raise InputError(f"--val-sensors must be at least 1 (the last sessions, held out for validation), "
                         f"got {args.val_sensors}")
    if not (math.isfinite(args.eval_interval) and args.eval_interval > 0):
        raise InputError(f"--eval-interval must be a positive number of seconds, got {args.eval_interval:g}")
    card = chosen_model_card(args.model_card, out)
    if card is not None:
        check_model_card(card)
    sessions = sorted(work.glob("sensor_*.h5"))
    sessions = [p for p in sessions if not p.name.endswith(".partial.h5")]
    if len(sessions) <= args.val_sensors:
        raise InputError(f"{len(sessions)} sessions in {work}: need more than --val-sensors {args.val_sensors}")
    train, val = sessions[: -args.val_sensors], sessions[-args.val_sensors :]
    options = training_options(args)
    check_checkpoint_use(work / TRAIN_DIR, args.resume, "drop --resume to train anew", "remove it to train anew")

    stop = TrainingStop()

    def show(p) -> None:
        stop.begin()
        if p.event != "step":
            a1 = a1_text(p.val)
            loss = f"{p.loss * 1e3:.3f} mm" if math.isfinite(p.loss) else "-"  # was: "nan mm" before the first step
            print(f"[{p.event}] epoch {p.epoch:.2f} step {p.step} loss {loss} val a1 {a1} ({p.fraction * 100:.0f} %)",
                  flush=True)

    with stop.handled(process_ends=True):  # the command's only block: a stop while torch loads ends it too
        from trainer.training import TrainConfig, train_model

        config = TrainConfig(
            data=[str(p) for p in train],
            val_data=[str(p) for p in val],
            out=str(work / TRAIN_DIR),
            eval_interval_s=args.eval_interval,
            ir_noise_std=PRETRAIN_NOISE_STD,
            write_on_stop=False,
            checkpoint_on_stop=True,
            **options,
        )
        result = train_model(config, show, stop.event)
    if result is None:  # a non-zero torchrun rank
        return 0
    if result.stopped:
        return stop.interrupted(result, config.out, "pretrain")
    out = package_base_model(result.model_dir, out)
    if card is not None:
        write_model_card_section(out, card, "python -m trainer.pretrain " + " ".join(sys.argv[1:]))
    if stop.requested:  # after the last step, while the model was validated and written: packaged, as it is whole
        return stop.after_last_step(out, "pretrain")
    print(f"base model -> {out}: held-out sensors a1 {result.metrics['a1']:.3f}, abs_rel {result.metrics['abs_rel']:.4f}")
    return 0


class _PretrainParser(OneLineParser):
    tool = "pretrain"


def main(argv: list[str] | None = None) -> int:
    parser = _PretrainParser(prog="python -m trainer.pretrain", description=__doc__.splitlines()[0])
    # no dest: a missing step reads "required: {collect,train}" (was: "required: step")
    sub = parser.add_subparsers(required=True, parser_class=_PretrainParser)
    c = sub.add_parser("collect", help="record one simulated session per sensor")
    c.add_argument("--sensors", type=int, default=16, metavar="N", help="simulated sensors to draw, one session each "
                   "(default %(default)s)")
    c.add_argument("--first-seed", type=int, default=1000, metavar="SEED",
                   help="seed of the first sensor, the others the next ones; also its pose plan's seed (default "
                        f"%(default)s; every seed within 0..{MAX_SENSOR_SEED})")
    c.add_argument("--objects", help="comma-separated objects (default: bubble collect's, every object of the plate)")
    c.add_argument("--poses-per-object", type=int, default=8, metavar="N",
                   help="contact poses per object in each session (default %(default)s)")
    c.add_argument("--sim-speed", type=float, default=20.0,
                   help="simulated clock speed factor (<= 100; lower on a busy machine; default %(default)g)")
    c.add_argument("--jobs", type=int, default=min(2, max_jobs()),
                   help="sessions recorded in parallel, at most the CPUs of this machine (default %(default)s)")
    c.add_argument("--work", type=named_path, required=True, help="directory of the sessions (created)")
    c.set_defaults(func=run_collect)
    t = sub.add_parser("train", help="train on the sessions of --work and package the base model")
    t.add_argument("--work", type=named_path, required=True,
                   help="directory of the sessions (pretrain collect's); the training keeps its model and "
                        f"checkpoint in WORK/{TRAIN_DIR}")
    t.add_argument("--out", type=named_path, required=True, metavar="MODEL_DIR",  # was: the shipped model by default
                   help="where to package the base model: a new or empty folder, or an earlier model, which is "
                        f"replaced (the shipped one: {BASE_MODEL_DIR.parent.name}/{BASE_MODEL_DIR.name})")
    t.add_argument("--val-sensors", type=int, default=2,
                   help="last sessions held out for validation (default %(default)s)")
    add_training_options(t, init_help="continue from this model directory ('base' = the shipped base model)",
                         minutes=30.0, frame_stride=3)
    t.add_argument("--eval-interval", type=float, default=60.0,
                   help="seconds between validations/checkpoints (default %(default)g)")
    t.add_argument("--model-card", metavar="CARD.md",
                   help="model card whose pretraining section to rewrite ('' = none; default: docs/model_card.md "
                        "when --out is the shipped base model, else none)")
    t.set_defaults(func=run_train)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except InputError as err:
        print(f"pretrain: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Terminated as err:  # a stop before training began (``trainer.stop_on_signal``)
        print(f"pretrain: interrupted ({err.name})", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("pretrain: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as err:  # as bubble's (was: a traceback, and exit 1, this tool's code for a failed sensor)
        code = os_error_exit(err, "pretrain")
        if code is None:
            raise
        return code


if __name__ == "__main__":
    sys.exit(main())
