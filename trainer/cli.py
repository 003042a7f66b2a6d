"""``bubble train`` and ``bubble evaluate``.

Data-parallel training: ``torchrun --nproc_per_node 2 -m calibrate.cli train ...`` (gloo on CPU,
nccl on GPU) runs the same command in every process.
"""

from __future__ import annotations

import argparse
import errno
import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext, suppress
from pathlib import Path

from collect.numbers import real_number
from collect.output_files import (check_json_output, check_parent_dirs, output_folder_lock, named_path,
                                  write_json_result)
from trainer.training_defaults import (
    ARCH_NAMES,
    DEFAULT_ARCH,
    DEFAULT_BATCH_SIZE,
    DEFAULT_CONTACT_WEIGHT,
    DEFAULT_LR,
    DEFAULT_MINUTES,
)

#: Columns of the paper's tables: (metric key, header, scale, decimals). RMSE in mm: the bubble's are
#: 0.05-2 mm, which "RMSE [m]" to 4 decimals showed as 0.0001-0.0020 (two models 0.1 mm apart alike).
PAPER_COLUMNS = (("abs_rel", "Abs.Rel", 1.0, 4), ("rmse", "RMSE [mm]", 1e3, 3), ("rmse_log", "RMSE_log", 1.0, 4),
                 ("silog", "SILog", 1.0, 4), ("a1", "δ<1.05", 1.0, 4))


def add_training_options(parser: argparse.ArgumentParser, *, init_help: str, minutes: float, frame_stride: int) -> None:
    """The options ``bubble train`` and ``python -m trainer.pretrain train`` share, each a
    ``TrainConfig`` field (``training_options`` turns them into its keywords). ``minutes`` and
    ``frame_stride`` are their defaults; the others are the trainer's (``trainer.training_defaults``)."""
    parser.add_argument("--arch", choices=ARCH_NAMES, help=f"network (default: {DEFAULT_ARCH}, or the init model's)")
    parser.add_argument("--width", type=float, help="channel width multiplier (default: per architecture)")
    parser.add_argument("--init", metavar="MODEL_DIR", help=init_help)
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--epochs", type=float, help="training budget in epochs")
    budget.add_argument("--minutes", type=float, default=minutes,
                        help=f"training budget in minutes of training time (default {minutes:g})")
    parser.add_argument("--frame-stride", type=int, default=frame_stride, metavar="K",
                        help=f"keep every K-th contact frame (default {frame_stride})")
    parser.add_argument("--seed", type=int, default=0,
                        help="random seed of the initialization, the split, the frame order and the augmentation "
                             "(default %(default)s)")
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint of the training run")
    parser.add_argument("--batch-size", type=int, default=DEFAULT_BATCH_SIZE,
                        help=f"frames per optimizer step (default {DEFAULT_BATCH_SIZE})")
    parser.add_argument("--lr", type=float, default=DEFAULT_LR,
                        help=f"Adam's learning rate at the start, halved during the run (default {DEFAULT_LR:g})")
    parser.add_argument("--contact-weight", type=float, default=DEFAULT_CONTACT_WEIGHT, metavar="W",
                        help="extra L1 weight of the contact patches, pixels pushed in > 0.5 mm from the "
                             f"no-contact reference (default {DEFAULT_CONTACT_WEIGHT:g}; 0 = plain L1 as in the paper)")


def training_options(args: argparse.Namespace) -> dict:
    """``TrainConfig`` keywords from the options of ``add_training_options`` (a budget in epochs
    replaces the default one in minutes)."""
    check_model_arg(args.init, "--init")
    return dict(
        arch=args.arch,
        width=args.width,
        init=args.init,
        epochs=args.epochs,
        minutes=args.minutes if args.epochs is None else None,
        frame_stride=args.frame_stride,
        seed=args.seed,
        resume=args.resume,
        batch_size=args.batch_size,
        lr=args.lr,
        contact_weight=args.contact_weight,
    )


def register(subparsers) -> None:
    train = subparsers.add_parser("train", help="train or fine-tune a depth network on session files")
    train.add_argument("--data", type=named_path, nargs="+", required=True, metavar="SESSION.h5", help="training session files")
    train.add_argument("--out", type=named_path, required=True, metavar="MODEL_DIR", help="model directory to write")
    add_training_options(train, init_help="fine-tune from this model directory ('base' = the shipped base model)",
                         minutes=DEFAULT_MINUTES, frame_stride=1)
    train.add_argument("--holdout-object", metavar="NAME", help="leave this object out for validation")
    train.add_argument("--split", choices=("poses", "frames"),
                       help="in-class 70/30 split of contact poses (default) or of frames (the paper's)")
    train.add_argument("--val-data", type=named_path, nargs="+", default=[], metavar="SESSION.h5", help="validate on these sessions instead of a split")
    train.add_argument("--objects", help="comma-separated objects to train on (default: all)")
    train.add_argument("--inverse-depth-loss", action="store_true", help="L1 on inverse depth instead of depth")
    train.add_argument("--no-augment", action="store_true", help="no IR augmentation")
    train.add_argument("--no-onnx", action="store_true", help="skip the ONNX export (torch inference)")
    train.add_argument("--threads", type=int, help="torch CPU threads")
    train.add_argument("--json", type=named_path, metavar="OUT.json", help="also write the final validation metrics here")
    train.set_defaults(func=run_train)

    evaluate = subparsers.add_parser("evaluate", help="the paper's metrics of a model on session files")
    evaluate.add_argument("--model", type=named_path, required=True, metavar="MODEL_DIR", help="model directory ('base' = the shipped base model)")
    evaluate.add_argument("--data", type=named_path, nargs="+", required=True, metavar="SESSION.h5",
                          help="session files to evaluate on")
    evaluate.add_argument("--objects", help="comma-separated objects to evaluate on (default: all)")
    evaluate.add_argument("--runtime", choices=("onnx", "torch"), help="inference runtime (default: the model's)")
    evaluate.add_argument("--json", type=named_path, metavar="OUT.json", help="write the metrics (keys at top level) here")
    evaluate.set_defaults(func=run_evaluate)


def _objects(text: str | None) -> list[str] | None:
    """The names of ``--objects`` (None: not given, every object)."""
    from collect.errors import InputError

    if text is None:
        return None
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise InputError("--objects is empty: name at least one object (comma-separated), or leave it out for all")
    return names


def check_model_arg(value: str | None, option: str) -> None:
    """Raise InputError when a model option (``--model``, ``--init``) is empty, names a file (a model
    is a directory), or names a folder ``base`` in the working directory otherwise than by its full
    path (``./base``, ``base/``: as a path it reads ``base``, the shipped base model's name, and was
    silently swapped for that model)."""
    from collect.errors import InputError

    if value is not None and not value.strip():
        raise InputError(f"{option} is empty: name a model directory, or 'base' (the shipped base model)")
    if value is not None and value != "base" and Path(value) == Path("base"):
        raise InputError(f"{option} {value}: a folder named base here reads as the shipped base model ('base'); "
                         f"give its full path, {Path(value).resolve()}")
    if value is not None and value != "base" and Path(value).is_file():
        raise InputError(f"{option} {value} is a file, not a model directory (give the directory that holds "
                         f"metadata.json)")


def print_sensor_note(model: str, serials: list[str]) -> None:
    """A ``bubble: note:`` line on stderr when ``serials`` (the data's sensors that the model's training
    sessions were not recorded with; ``ModelMetadata.sensors_not_trained_on``) is not empty."""
    if serials:
        print(f"bubble: note: model {model} was not trained on sensor {', '.join(serials)} (its depth there is that "
              f"of a model that has not seen the sensor; one fine-tuned on it fits it better)", file=sys.stderr)


def metrics_table(title: str, rows: dict[str, dict]):
    """A rich table of the paper's columns, one row per name."""
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=title)
    table.add_column("data")
    for _, header, _, _ in PAPER_COLUMNS:
        table.add_column(escape(header), justify="right")  # "RMSE [mm]": [mm] is no rich markup tag
    table.add_column("images", justify="right")
    for name, m in rows.items():  # a name is text too: an object "bracket[v2]" showed as "bracket"
        table.add_row(escape(name), *(f"{m[key] * scale:.{decimals}f}" if math.isfinite(m[key]) else "-"
                                      for key, _, scale, decimals in PAPER_COLUMNS),
                      str(m["n_images"]))  # "-": no image of that row has a valid pixel (was: nan)
    return table


@contextmanager
def _model_dir_held(out: Path) -> Iterator[None]:
    """The ``--out`` model directory, created when missing and, in the process that writes it (the
    only one, or torchrun's rank 0), held for the with-block (``output_folder_lock``): a second
    ``bubble train`` into it is refused while this one runs. A directory this call created is
    removed again when nothing was written into it (bad data, a refusal)."""
    from trainer.distributed import DistContext

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with output_folder_lock(out, "bubble train") if DistContext.from_env().is_main else nullcontext():
            yield
    finally:
        if created:
            with suppress(OSError):  # a folder with files in it stays
                out.rmdir()


def _check_no_training_files(out: Path) -> None:
    """Raise InputError when the folder ``out`` of a new training holds a file of the name that training
    writes (``TRAINING_FILES``), which it would replace or delete (was: a foreign ``metadata.json`` or
    ``model.onnx`` overwritten, a ``checkpoint.json`` deleted, exit 0); other files may stay there."""
    from collect.errors import InputError
    from trainer.checkpoint import TRAINING_FILES

    found = [name for name in TRAINING_FILES if (out / name).exists()]
    if found:
        raise InputError(f"{out} already holds {found[0]}, which training writes; choose another --out "
                         "(a new folder, or one without the files of a model)")


def a1_text(val: dict | None) -> str:
    """The live validation's a1 (``val``: ``TrainProgress.val``) as ``train`` and ``pretrain train`` show
    it: ``-`` before the first validation and where it is not a finite number (a resumed run's
    checkpoint keeps a NaN as None: was a TypeError traceback at its first step)."""
    a1 = (val or {}).get("a1")
    return f"{a1:.3f}" if real_number(a1) else "-"


def run_train(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from collect.errors import InputError
    from trainer.checkpoint import check_checkpoint_use
    from trainer.model_dir import WEIGHTS_FILE
    from trainer.stop_on_signal import TrainingStop
    from trainer.training import TrainConfig, train_model

    out = Path(args.out)
    if out == Path("base"):  # was: written, and then read back as the shipped model by --init/--model base
        raise InputError(f"--out {args.out}: 'base' names the shipped base model where a model is read (--init, "
                         "--model); name the folder otherwise")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file, not a model directory")
    check_parent_dirs(out)
    options = training_options(args)
    if args.holdout_object is not None and not args.holdout_object.strip():
        raise InputError("--holdout-object is empty: name the object to leave out, or drop the option")
    chosen = [option for option, given in (("--val-data", args.val_data), ("--holdout-object", args.holdout_object),
                                           ("--split", args.split)) if given]
    if len(chosen) > 1:
        raise InputError(f"{' and '.join(chosen)} each choose the validation frames; give one of them")
    if args.json is not None:
        check_json_output(args.json, "bubble train")
        if Path(args.json).resolve().is_relative_to(out.resolve()):  # was: e.g. written over its metadata.json
            raise InputError(f"--json {args.json} is inside the model directory {out}, whose files training "
                             "writes; write the result elsewhere")
    config = TrainConfig(
        data=args.data,
        out=args.out,
        split=args.split or "poses",
        holdout_object=args.holdout_object and args.holdout_object.strip(),
        val_data=args.val_data,
        objects=_objects(args.objects),
        inverse_depth_loss=args.inverse_depth_loss,
        augment=not args.no_augment,
        export_onnx=not args.no_onnx,
        threads=args.threads,
        write_on_stop=False,
        checkpoint_on_stop=True,
        **options,
    )
    console = Console(stderr=True)
    columns = (
        TextColumn("[bold]train"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TextColumn("ep {task.fields[epoch]:.2f}  loss {task.fields[loss]}  δ<1.05 {task.fields[a1]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    bar = Progress(*columns, console=console)
    task = None

    stop = TrainingStop()

    def on_progress(p) -> None:
        nonlocal task
        if task is None:  # started at the first step: data errors print no empty bar
            bar.start()
            task = bar.add_task("train", total=1.0, epoch=0.0, loss="-", a1="-")
            stop.begin()
        a1 = a1_text(p.val)
        if not math.isfinite(p.loss):
            loss = "-"
        else:
            loss = f"{p.loss:.3f} 1/m" if config.inverse_depth_loss else f"{p.loss * 1e3:.3f} mm"
        bar.update(task, completed=p.fraction, epoch=p.epoch, loss=loss, a1=a1)

    try:
        with _model_dir_held(out):
            if not args.resume and (out / WEIGHTS_FILE).exists():
                raise InputError(f"{out} already holds a model; choose another --out (with --init {out} to train "
                                 "it further)")
            check_checkpoint_use(out, args.resume, "choose another --out, or drop --resume", "choose another --out")
            if not args.resume:
                _check_no_training_files(out)
            with stop.handled():
                result = train_model(config, on_progress, stop.event)
    finally:
        if task is not None:  # stopping a bar never started prints an empty line before the error
            bar.stop()
    if result is None:  # a non-zero torchrun rank
        return 0
    if result.stopped:
        return stop.interrupted(result, out, "bubble")
    if args.json is not None:  # the model is whole: its result too, a stop after the last step or not
        write_json_result(args.json, "bubble train", result.metrics)
    if stop.requested:  # the stop came after the last step, while the model was validated and written: it is whole
        return stop.after_last_step(out, "bubble")  # (was: before the --json result, which was not written)
    console.print(metrics_table(f"validation ({result.metrics['split']})", {"all": result.metrics}))
    console.print(f"model written to {result.model_dir} ({result.steps} steps, {result.train_s / 60:.1f} min training, "
                  f"peak RSS {result.peak_rss_mb:.0f} MB)")
    return 0


def run_evaluate(args: argparse.Namespace) -> int:
    from rich.console import Console

    from trainer.evaluation import evaluate_model

    check_model_arg(args.model, "--model")
    if args.json is not None:
        check_json_output(args.json, "bubble evaluate")
    result = evaluate_model(args.model, args.data, objects=_objects(args.objects), runtime=args.runtime)
    if args.json is not None:  # before the console, which may be a pipe its reader closed (`| head`)
        write_json_result(args.json, "bubble evaluate", result)
    print_sensor_note(args.model, result["sensors_not_trained_on"])

    class StdoutConsole(Console):
        def on_broken_pipe(self) -> None:  # the command line's exit code for it (rich's own: exit 1, "rejected")
            raise BrokenPipeError(errno.EPIPE, "the reader of stdout went away")

    console = StdoutConsole()
    rows = {**result["per_object"], "all (vs ToF)": result}
    if "vs_true" in result:
        vs = result["vs_true"]
        rows["ToF vs true"] = vs["tof"]
        rows["model vs true, ToF px"] = vs["model_on_tof_valid"]
        rows["model vs true, all px"] = vs["model"]
        if vs["model_on_tof_dropout"]["n_images"]:
            rows["model vs true, dropouts"] = vs["model_on_tof_dropout"]
    console.print(metrics_table(f"{result['arch']} on {len(args.data)} session(s)", rows))
    console.print(f"latency {result['latency_ms']:.2f} ms per frame (batch 1, {result['runtime']})")
    return 0
