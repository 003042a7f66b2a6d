"""Training and fine-tuning: ``train_model(config, progress_callback, stop_event) -> TrainResult``.

The paper's recipe (Adam, betas 0.9/0.999, lr 2e-4 halved after every 40 % of the run - the
paper's 100 epochs with halvings at 40 and 80 -, L1 on valid pixels) with a budget in epochs or
in minutes of training time, fitted to a CPU: the frames live in memory as tensors, batches are
small, validation runs on a subsample every ``eval_interval_s`` seconds, and the loop checkpoints
into the model directory so that ``resume`` continues an interrupted run. Under ``torchrun``
the same loop runs data-parallel (``trainer.distributed``).

Budget accounting: ``minutes`` counts training time only (validation and checkpoints excluded),
so that curves of accuracy against minutes mean the same on every run. ``deadline_s`` bounds the
wall time of the whole call instead (loading, validations, final validation and ONNX export
included): training then ends as soon as what is left after it would overrun, the learning-rate
schedule following whichever budget binds first.
"""

from __future__ import annotations

import math
import os
import resource
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import nn

from collect.errors import InputError
from collect.json_files import plain_json
from trainer.augmentation import augment_ir
from trainer.checkpoint import has_checkpoint, load_checkpoint, remove_checkpoint, save_checkpoint
from trainer.dataset import (
    FrameSet,
    NetworkTensors,
    check_each_recording_once,
    check_each_session_once,
    load_frames,
    to_network_tensors,
)
from trainer.distributed import DistContext
from trainer.losses import contact_weights, masked_l1
from trainer.metrics import depth_metrics, in_depth_range, no_depth_in_range
from trainer.model_dir import ModelMetadata, load_metadata, load_network, resolve_model_dir, save_model, weights_sha256
from trainer.networks import ARCHITECTURES, INPUT_MULTIPLE, build_network, check_width, set_initial_depth
from trainer.preprocessing import DEFAULT_INPUT_SIZE, InputGeometry, IRNormalization
from trainer.splits import TRAIN_FRACTION, split_holdout_object, split_in_class
from trainer.training_defaults import (
    DEFAULT_ARCH,
    DEFAULT_BATCH_SIZE,
    DEFAULT_CONTACT_WEIGHT,
    DEFAULT_LR,
    DEFAULT_MAX_DEPTH,
    DEFAULT_MIN_DEPTH,
    DEFAULT_MINUTES,
    DEFAULT_WIDTHS,
    MAX_CONTACT_WEIGHT,
    MAX_EPOCHS,
    MAX_LR,
    MAX_MINUTES,
    MAX_SEED,
)

#: The learning rate halves after every this fraction of the budget (paper: every 40 of 100 epochs).
LR_HALVING_FRACTION = 0.4

#: Writing the model, the ONNX export and the runtime selection after training, in frames of
#: validation they cost about (tracing, a check at two batch sizes, 2 x 20 single-frame timings):
#: 87-91 measured on the 2-core CPU of docs/benchmarks.md, with a margin.
EXPORT_COST_IN_EVAL_FRAMES = 120

#: Margin on the estimated wall time after the last step: in commissioning on the 2-core CPU it took
#: 12.0 s, as estimated (228 validation frames at 0.027-0.030 s), and the step ended 0.0 s before
#: its deadline; the margin leaves a few seconds for the estimate to be off.
DEADLINE_TAIL_MARGIN = 1.25


@dataclass
class TrainConfig:
    """Everything ``train_model`` needs. Paths are session files / the output model directory."""

    data: list[str]
    out: str
    arch: str | None = None  # None: the init model's, else DEFAULT_ARCH
    width: float | None = None  # None: the init model's, else DEFAULT_WIDTHS[arch]
    init: str | None = None  # model directory (or "base") to fine-tune from
    epochs: float | None = None
    minutes: float | None = None  # training time budget; DEFAULT_MINUTES when neither is given
    seed: int = 0
    resume: bool = False
    split: str = "poses"  # "frames" | "poses" (in-class 70/30), ignored with holdout_object / val_data
    holdout_object: str | None = None
    val_data: list[str] = field(default_factory=list)  # validate on these sessions instead of a split
    objects: list[str] | None = None  # restrict training data to these objects
    frame_stride: int = 1  # keep every n-th contact frame of each session (memory bound for pretraining)
    batch_size: int = DEFAULT_BATCH_SIZE
    lr: float = DEFAULT_LR
    inverse_depth_loss: bool = False
    contact_weight: float = DEFAULT_CONTACT_WEIGHT  # extra loss weight of the contact patches (0 = plain L1)
    augment: bool = True
    ir_noise_std: float = 0.0  # augmentation's pixel noise (normalized IR units); pretraining: PRETRAIN_NOISE_STD
    min_depth: float = DEFAULT_MIN_DEPTH
    max_depth: float = DEFAULT_MAX_DEPTH
    input_size: tuple[int, int] = DEFAULT_INPUT_SIZE
    eval_interval_s: float = 20.0
    eval_frames: int = 64  # validation frames used for the periodic (live) metrics
    deadline_s: float | None = None  # wall-time limit (s) of the whole train_model call; None: budget only
    export_onnx: bool = True
    write_on_stop: bool = True  # False: a stop_event ends the call at once, no final validation nor model written
    checkpoint_on_stop: bool = False  # with write_on_stop False: checkpoint the step reached, for a later resume
    threads: int | None = None  # torch CPU threads; None: the cores shared by local processes


@dataclass
class TrainProgress:
    """A snapshot handed to ``progress_callback`` after every step and every validation."""

    epoch: float  # fractional epochs done
    step: int
    loss: float  # running mean of the training loss (m, or 1/m for inverse-depth loss)
    lr: float
    train_s: float  # training time so far (s)
    fraction: float  # share of the budget done, 0..1
    eta_s: float | None  # estimated training time left (s)
    val: dict | None = None  # latest periodic validation metrics (trainer.metrics keys)
    event: str = "step"  # "step" | "eval" | "done"


@dataclass
class TrainResult:
    """What ``train_model`` returns: where the model went, its final metrics and how the run went."""

    model_dir: Path
    metrics: dict  # final validation metrics on the whole validation split
    history: list[dict]  # periodic validation: train_s, epoch, step, loss, metric keys
    epochs: float
    steps: int
    train_s: float
    stopped: bool  # True when stop_event ended the run before its budget
    peak_rss_mb: float
    ended_at_deadline: bool = False  # True when config.deadline_s ended training before its budget


def seconds_left(train_s: float, budget_fraction: float, deadline_left_s: float | None) -> float | None:
    """Training seconds left (the ``eta_s`` of progress): the budget's share not done at the rate so far
    (``train_s`` s for ``budget_fraction``; None before any), or the wall seconds until the deadline
    ends training (``deadline_left_s``, None without one) when those are fewer. Was: the larger of
    the two shares done, turned into seconds at the budget's rate, so the countdown jumped whenever
    the other limit took over (52, 35, 32, 66, 61, 1 s left on a loaded machine)."""
    left = train_s / budget_fraction * (1.0 - budget_fraction) if budget_fraction > 0 else None
    if deadline_left_s is not None:
        left = max(0.0, deadline_left_s) if left is None else min(left, max(0.0, deadline_left_s))
    return left


def _learning_rate(base_lr: float, fraction: float) -> float:
    return base_lr * 0.5 ** math.floor(min(fraction, 0.999999) / LR_HALVING_FRACTION)


def _peak_rss_mb() -> float:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024.0 * 1024.0) if sys.platform == "darwin" else rss / 1024.0


def predict_tensors(network: nn.Module, x: torch.Tensor, device: str, batch_size: int = 16) -> np.ndarray:
    """Depth ``(n,h,w) float32 m`` of network inputs ``x`` ``(n,1,h,w)`` in eval mode."""
    was_training = network.training
    network.eval()
    out = []
    with torch.inference_mode():
        for start in range(0, len(x), batch_size):
            out.append(network(x[start : start + batch_size].to(device)).cpu().numpy()[:, 0])
    network.train(was_training)
    return np.concatenate(out) if out else np.zeros((0,) + tuple(x.shape[-2:]), np.float32)


def evaluate_tensors(network: nn.Module, tensors: NetworkTensors, device: str, min_depth: float, max_depth: float) -> dict:
    """The paper's metrics of ``network`` against the ToF depth of ``tensors`` (padding ignored)."""
    pred = predict_tensors(network, tensors.x, device)
    return depth_metrics(pred, tensors.depth[:, 0].numpy(), min_depth=min_depth, max_depth=max_depth)


def split_frames(config: TrainConfig, frames: FrameSet) -> tuple[FrameSet, FrameSet, dict]:
    """(training frames, validation frames, the split's description) of ``frames``, loaded from
    ``config.data`` as ``train_model`` loads them, by ``config``'s split: ``val_data`` sessions, a held-out
    object or the in-class split. InputError for a split that leaves either side empty, or validates on
    no contact frame."""
    if config.val_data:
        val = load_frames(config.val_data, objects=config.objects, seed=config.seed, stride=config.frame_stride,
                          with_truth=False)
        return frames, val, {"kind": "sessions", "val_data": [str(p) for p in config.val_data]}
    if config.holdout_object:
        train_idx, val_idx = split_holdout_object(frames, config.holdout_object)
        info = {"kind": "holdout-object", "object": config.holdout_object}
    else:
        train_idx, val_idx = split_in_class(frames, by=config.split, seed=config.seed)
        info = {"kind": f"in-class-{config.split}", "train_fraction": TRAIN_FRACTION, "seed": config.seed}
    if len(train_idx) == 0 or len(val_idx) == 0:
        n = len(frames)
        kept = f" of the {n} frame{'' if n == 1 else 's'} that --frame-stride {config.frame_stride} keeps" \
            if config.frame_stride > 1 else ""
        raise InputError(f"the {info['kind']} split leaves no training or no validation frames{kept}; record more poses"
                         f"{', or lower --frame-stride' if kept else ''}")
    if (frames.pose_id >= 0).any() and not (frames.pose_id[val_idx] >= 0).any():  # a held-out object: all contact
        # Validation of free frames alone: its metrics would pass for the held-out contact frames'
        # (a1 ~1 on an undented membrane). The pose split holds out a pose of every object of a
        # session that has two or more.
        why = ("every object of each session was pressed in one pose only; record 2 or more poses per object, "
               "or use --split frames, --holdout-object or --val-data") if config.split == "poses" \
            else "too few frames; record more poses"
        raise InputError(f"the {info['kind']} split holds out no contact frame: {why}")
    return frames.subset(train_idx), frames.subset(val_idx), info


def _frames_key(config: TrainConfig, frames: FrameSet, val_frames: FrameSet, split_info: dict, world_size: int,
                init_info: dict | None) -> dict:
    """What decides which frames train, which validate and in what order, and the recipe they train
    with (the network, the initial weights, by their SHA-256, the budget, the learning rate, the loss
    and the augmentation): a checkpoint resumes only with the same (``_check_resume``; was: the
    recipe unchecked, so that a resume without ``--init`` recorded ``init: null`` for a fine-tuned
    model, and the network and budget unchecked: another width failed to load the weights with
    torch's list of keys, and another budget, or none, the default one, ended the run at once or
    changed its learning-rate schedule, with a model recorded as trained on that budget alone)."""
    init = init_info["weights_sha256"] if init_info else None  # (``_build``'s)
    return plain_json({
        "arch": config.arch,
        "width": config.width,
        "budget": {"epochs": config.epochs, "minutes": _budget_minutes(config)},
        "data": [s.sha256 for s in frames.sources],
        "val_data": [s.sha256 for s in val_frames.sources] if config.val_data else [],
        "split": {k: v for k, v in split_info.items() if k != "val_data"},  # its paths: the files are in "val_data"
        "objects": sorted(config.objects) if config.objects else None,
        "frame_stride": config.frame_stride,
        "seed": config.seed,
        "batch_size": config.batch_size,
        "world_size": world_size,
        "init": init,
        "lr": config.lr,
        "inverse_depth_loss": config.inverse_depth_loss,
        "contact_weight": config.contact_weight,
        "augment": config.augment,
        "ir_noise_std": config.ir_noise_std,
    })


def _budget_minutes(config: TrainConfig) -> float | None:
    """The training-time budget (min) of ``config``: its ``minutes``, ``DEFAULT_MINUTES`` when it
    gives no budget, None for an ``epochs`` budget."""
    return DEFAULT_MINUTES if config.epochs is None and config.minutes is None else config.minutes


def _check_resume(out_dir: Path, saved: dict | None, current: dict) -> None:
    """Refuse to resume the checkpoint in ``out_dir`` with other data, split, seed, batches or recipe (was:
    resumed, then validated on frames the first part had trained on, with held-out metrics to match)."""
    if saved is None:
        raise InputError(f"the checkpoint in {out_dir} does not record which frames it trained on (an older "
                         "bubble); train anew, without --resume")
    names = {"arch": "--arch", "width": "--width", "budget": "budget (--epochs, --minutes)",
             "data": "--data", "val_data": "--val-data", "split": "split (--split, --holdout-object, --val-data)",
             "objects": "--objects", "frame_stride": "--frame-stride", "seed": "--seed", "batch_size": "--batch-size",
             "world_size": "number of processes", "init": "--init", "lr": "--lr",
             "inverse_depth_loss": "--inverse-depth-loss", "contact_weight": "--contact-weight",
             "augment": "--no-augment", "ir_noise_std": "pixel noise"}
    # a key the checkpoint lacks (one of an earlier bubble's, which recorded the frames alone) is not checked
    changed = [names.get(k, k) for k in current if k in saved and saved[k] != current[k]]
    if not changed:
        return
    raise InputError(f"the checkpoint in {out_dir} was trained with other settings ({', '.join(changed)}): resume "
                     "with the same ones, or train anew without --resume (its validation frames could be frames "
                     "the checkpoint trained on)")


def _diverged(config: TrainConfig, step: int, what: str) -> InputError:
    """The error of a training whose network diverged (``what`` says how it shows) after ``step`` steps;
    nothing is written as the model."""
    return InputError(f"training diverged after {step} step{'' if step == 1 else 's'} ({what}) at learning rate {config.lr:g}; "
                      "lower --lr, the model was not written")


def _check_config(config: TrainConfig) -> None:
    if config.epochs is not None and config.minutes is not None:
        raise InputError("give either epochs or minutes, not both")
    if config.epochs is not None and not (math.isfinite(config.epochs) and 0 < config.epochs <= MAX_EPOCHS):
        raise InputError(f"epochs must be a number in (0, {MAX_EPOCHS:g}], got {config.epochs}")
    if config.minutes is not None and not (math.isfinite(config.minutes) and 0 < config.minutes <= MAX_MINUTES):
        raise InputError(f"minutes must be a number in (0, {MAX_MINUTES:g}] (a week), got {config.minutes}")
    if not (math.isfinite(config.lr) and 0 < config.lr <= MAX_LR):
        raise InputError(f"learning rate must be a number in (0, {MAX_LR:g}], got {config.lr}")
    cpus = os.cpu_count() or 1
    if config.threads is not None and not 1 <= config.threads <= cpus:
        raise InputError(f"threads must be 1..{cpus} (the CPUs of this machine), got {config.threads}")
    if config.deadline_s is not None and not (math.isfinite(config.deadline_s) and config.deadline_s > 0):
        raise InputError(f"the wall-time deadline must be a positive number of seconds, got {config.deadline_s}")
    if not (math.isfinite(config.contact_weight) and 0 <= config.contact_weight <= MAX_CONTACT_WEIGHT):
        raise InputError(f"contact weight must be a number in [0, {MAX_CONTACT_WEIGHT:g}], got {config.contact_weight}")
    if config.batch_size < 1:
        raise InputError(f"batch size must be at least 1, got {config.batch_size}")
    if not 0 <= config.seed <= MAX_SEED:
        raise InputError(f"seed must be 0..{MAX_SEED}, got {config.seed}")
    if config.width is not None:
        check_width(config.width)
    # a session given twice would weigh double, or be validated on after training on it
    check_each_session_once({"--data": config.data, "--val-data": config.val_data})
    h, w = config.input_size
    if h % INPUT_MULTIPLE or w % INPUT_MULTIPLE:
        raise InputError(f"input size {w}x{h} must be a multiple of {INPUT_MULTIPLE} in both directions")
    if config.arch is not None and config.arch not in ARCHITECTURES:
        raise InputError(f"unknown architecture {config.arch!r}; choose one of {', '.join(ARCHITECTURES)}")
    if config.init:  # before the data loads: a pretraining set takes minutes
        init_meta = load_metadata(resolve_model_dir(config.init))
        if config.arch is not None and config.arch != init_meta.arch:
            raise InputError(f"--arch {config.arch} differs from the init model's architecture {init_meta.arch}")
        if config.width is not None and config.width != init_meta.width:
            raise InputError(f"width {config.width} differs from the init model's width {init_meta.width}")


def _build(config: TrainConfig, frames: FrameSet) -> tuple[nn.Module, ModelMetadata, dict | None]:
    """Network (fresh or from ``config.init``) and the metadata of the model being trained."""
    init_info = None
    if config.init:
        network, init_meta = load_network(resolve_model_dir(config.init))
        arch, width = init_meta.arch, init_meta.width
        min_depth, max_depth = init_meta.min_depth, init_meta.max_depth
        input_size = (init_meta.geometry.input_height, init_meta.geometry.input_width)
        init_info = {"model_dir": str(config.init), "weights_sha256": weights_sha256(config.init),
                     "metrics": init_meta.metrics, "sensor_serials": init_meta.training.get("sensor_serials", [])}
        network.train()
    else:
        arch = config.arch or DEFAULT_ARCH
        width = config.width if config.width is not None else DEFAULT_WIDTHS[arch]
        min_depth, max_depth, input_size = config.min_depth, config.max_depth, tuple(config.input_size)
        network = build_network(arch, width, min_depth, max_depth)
        valid = frames.depth[in_depth_range(frames.depth, min_depth, max_depth)]
        if valid.size:
            set_initial_depth(network, float(np.median(valid)))
    h, w = frames.size
    geometry = InputGeometry(h, w, int(input_size[0]), int(input_size[1]))
    metadata = ModelMetadata(
        arch=arch,
        width=width,
        min_depth=min_depth,
        max_depth=max_depth,
        geometry=geometry,
        normalization=IRNormalization.fit(frames.ir),
    )
    return network, metadata, init_info


def train_model(
    config: TrainConfig,
    progress_callback: Callable[[TrainProgress], None] | None = None,
    stop_event: threading.Event | None = None,
) -> TrainResult | None:
    """Train (or fine-tune) a depth network and write the model directory ``config.out``.

    Returns the final validation metrics and the periodic validation history; the model
    directory holds the weights, ``metadata.json`` (with those metrics) and, when
    ``config.export_onnx``, ``model.onnx`` with the inference runtime chosen. ``stop_event``
    ends training early: the model so far is still validated and written, or, with
    ``config.write_on_stop`` False (a caller that throws it away), the call returns at once with
    ``stopped`` set and empty ``metrics``, and ``config.out`` keeps only the last periodic
    checkpoint, if any, or (``config.checkpoint_on_stop``: ``bubble train`` stopped by Ctrl-C) a
    checkpoint of the step the stop found, which ``resume`` continues. Raises ``InputError`` for bad data or settings. Under torchrun only rank 0
    returns a result (the others None).
    """
    call_start = time.perf_counter()
    _check_config(config)
    ctx = DistContext.from_env()
    if ctx.enabled and config.deadline_s is not None:  # rank 0 alone times the validations
        raise InputError("a wall-time deadline is for single-process training, not under torchrun")
    torch.set_num_threads(config.threads or ctx.cpu_threads())
    torch.manual_seed(config.seed)
    if ctx.device != "cpu":  # CUDA's default kernels do not repeat a run bit for bit (was: a seeded training, or a
        # resumed one against its uninterrupted twin, 0.01-0.09 apart in its weights on an H200); the CPU's do.
        # For the whole process, as the thread count above; the workspace setting counts only before cuBLAS
        # starts (a process that used it before gets torch's warning, not a wrong result)
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
    out_dir = Path(config.out)

    frames = load_frames(config.data, objects=config.objects, seed=config.seed, stride=config.frame_stride,
                         with_truth=False)
    train_frames, val_frames, split_info = split_frames(config, frames)
    check_each_recording_once({"--data": frames.sources, "--val-data": val_frames.sources if config.val_data else []})
    if val_frames.size != train_frames.size:
        raise InputError(f"validation frames are {val_frames.size[1]}x{val_frames.size[0]}, training frames "
                         f"{train_frames.size[1]}x{train_frames.size[0]}")
    network, metadata, init_info = _build(config, train_frames)
    train_t = to_network_tensors(train_frames, metadata.geometry, metadata.normalization)
    val_t = to_network_tensors(val_frames, metadata.geometry, metadata.normalization)
    for role, tensors in (("training", train_t), ("validation", val_t)):  # was: "training diverged ... lower --lr"
        if not bool(in_depth_range(tensors.depth, metadata.min_depth, metadata.max_depth).any()):
            raise no_depth_in_range(f"no {role} frame", metadata.min_depth, metadata.max_depth,
                                    "train on" if role == "training" else "validate with")
    # the sessions that train, each with its training frames, and those that validate only (was: every
    # --data session, so that one that only validated, the held-out object's, counted as trained on)
    trained_on = train_frames.sources_used()
    trained_files = {s.sha256 for s in trained_on}
    sources = [s.to_dict() for s in trained_on]
    val_sources = [s.to_dict() for s in val_frames.sources_used() if s.sha256 not in trained_files]
    frames_key = _frames_key(config, frames, val_frames, split_info, ctx.world_size, init_info)
    serials = sorted({s.sensor_serial for s in trained_on})
    objects = sorted(set(train_frames.object_name) - {""})
    del frames, train_frames, val_frames  # the native copies; training uses the tensors only
    live_idx = np.linspace(0, len(val_t) - 1, min(config.eval_frames, len(val_t))).round().astype(int)
    live_val = NetworkTensors(val_t.x[live_idx], val_t.depth[live_idx], val_t.content, val_t.contact[live_idx])

    network.to(ctx.device)
    model: nn.Module = network
    if ctx.enabled:
        model = nn.parallel.DistributedDataParallel(network, device_ids=[ctx.local_rank] if ctx.device != "cpu" else None)
    optimizer = torch.optim.Adam(network.parameters(), lr=config.lr, betas=(0.9, 0.999))

    progress = {"epoch": 0.0, "step": 0, "train_s": 0.0, "history": [], "loss": float("nan")}
    if config.resume and has_checkpoint(out_dir):
        progress = load_checkpoint(out_dir, network, optimizer,
                                   check=lambda saved: _check_resume(out_dir, saved.get("frames_key"), frames_key))
        network.to(ctx.device)

    minutes = _budget_minutes(config)
    budget_s = None if minutes is None else 60.0 * minutes
    n_per_rank = len(train_t) // ctx.world_size
    if n_per_rank == 0:
        raise InputError(f"{len(train_t)} training frames cannot be shared by {ctx.world_size} processes")
    steps_per_epoch = math.ceil(n_per_rank / config.batch_size)

    deadline = None if config.deadline_s is None else call_start + config.deadline_s
    # validation frames' worth of work left after the last step: the final validation (whole split
    # and live subsample), writing the model and the ONNX export
    tail_frames = len(val_t) + len(live_val) + (EXPORT_COST_IN_EVAL_FRAMES if config.export_onnx else 0)
    eval_s_per_frame: float | None = None  # measured by every live validation
    loop_start: float | None = None  # when this call's first training step began
    step_s = 0.0  # duration of the latest training step (the next one must fit too)

    def budget_fraction(epoch: float, train_s: float) -> float:
        return train_s / budget_s if budget_s is not None else epoch / config.epochs

    def training_end() -> float | None:
        """``time.perf_counter()`` by which the deadline ends training: the work after the last step
        must still fit before it (None: no deadline, or that work's cost not yet measured)."""
        if deadline is None or eval_s_per_frame is None:
            return None
        return deadline - DEADLINE_TAIL_MARGIN * (eval_s_per_frame * tail_frames + step_s)

    def fraction_done(epoch: float, train_s: float) -> float:
        """Share of the budget done; with a deadline, of the wall time training may last if larger
        (before the first step: 1 when the deadline leaves no time for one)."""
        frac = budget_fraction(epoch, train_s)
        train_end = training_end()
        if train_end is None:
            return frac
        start = time.perf_counter() if loop_start is None else loop_start
        wall = 1.0 if train_end <= start else (time.perf_counter() - start) / (train_end - start)
        return max(frac, wall)

    # the augmentation's draws of each step come from (seed, rank, step): a resumed run draws what an
    # uninterrupted one draws (was: one generator seeded per call, its draws replayed from the start)
    gen = torch.Generator()
    epoch_f, step, train_s = float(progress["epoch"]), int(progress["step"]), float(progress["train_s"])
    history: list[dict] = list(progress["history"])
    running = progress["loss"]
    last_eval = time.perf_counter()
    val_live: dict | None = history[-1] if history else None
    stopped = at_deadline = False

    def report(event: str) -> None:
        if progress_callback is None or not ctx.is_main:
            return
        frac = min(1.0, fraction_done(epoch_f, train_s))
        train_end = training_end()
        eta = seconds_left(train_s, min(1.0, budget_fraction(epoch_f, train_s)),
                           None if train_end is None else train_end - time.perf_counter())
        progress_callback(TrainProgress(epoch_f, step, running, _learning_rate(config.lr, frac), train_s, frac, eta, val_live, event))

    def checkpoint() -> None:
        save_checkpoint(out_dir, network, optimizer, {"epoch": epoch_f, "step": step, "train_s": train_s,
                                                      "history": history, "loss": running, "frames_key": frames_key})

    def timed_live_metrics() -> dict:
        """The metrics of ``live_val``; sets ``eval_s_per_frame``, the cost the deadline plans with."""
        nonlocal eval_s_per_frame
        t0 = time.perf_counter()
        metrics = evaluate_tensors(network, live_val, ctx.device, metadata.min_depth, metadata.max_depth)
        eval_s_per_frame = (time.perf_counter() - t0) / len(live_val)
        return metrics

    def validate_and_checkpoint(with_checkpoint: bool = True) -> None:
        nonlocal val_live
        if ctx.is_main:
            metrics = timed_live_metrics()
            val_live = {"train_s": train_s, "epoch": epoch_f, "step": step, "loss": running, **metrics}
            history.append(val_live)
            if with_checkpoint:
                checkpoint()
            report("eval")
        ctx.barrier()

    if not history:  # the curve starts with the untrained (or init) model
        validate_and_checkpoint(with_checkpoint=False)
    elif deadline is not None and ctx.is_main:  # resumed: the deadline plans with a validation's cost (was:
        timed_live_metrics()                     # unknown until the first periodic one, the deadline ignored)
    model.train()
    # a stop requested while the data loaded or the init model was validated ends the call before a step
    # (was: one step, then, with the deadline passed meanwhile, a model written as if it had finished)
    over, stopped = ctx.any_flags(fraction_done(epoch_f, train_s) >= 1.0, stop_event is not None and stop_event.is_set())
    at_deadline = over and not stopped and budget_fraction(epoch_f, train_s) < 1.0  # no time left for a step
    done = over or stopped
    loop_start = time.perf_counter()
    while not done:
        epoch = int(epoch_f)
        perm = torch.randperm(len(train_t), generator=torch.Generator().manual_seed(config.seed * 100003 + epoch))
        shard = perm[ctx.rank :: ctx.world_size][:n_per_rank]
        first = int(round((epoch_f - epoch) * steps_per_epoch))
        for b in range(first, steps_per_epoch):
            t0 = time.perf_counter()
            lr = _learning_rate(config.lr, fraction_done(epoch_f, train_s))
            for group in optimizer.param_groups:
                group["lr"] = lr
            idx = shard[b * config.batch_size : (b + 1) * config.batch_size]
            x = train_t.x[idx]
            if config.augment:
                gen.manual_seed(((config.seed * 7919 + ctx.rank) * 1_000_003 + step) % (1 << 63))
                x = augment_ir(x, train_t.content, metadata.normalization.std, gen, config.ir_noise_std)
            target = train_t.depth[idx].to(ctx.device)
            valid = in_depth_range(target, metadata.min_depth, metadata.max_depth)
            weight = contact_weights(train_t.contact[idx], config.contact_weight).to(ctx.device) \
                if config.contact_weight > 0 else None
            loss = masked_l1(model(x.to(ctx.device)), target, valid, inverse=config.inverse_depth_loss, weight=weight)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            value = float(loss.detach())
            running = value if not math.isfinite(running) else 0.9 * running + 0.1 * value
            step += 1
            epoch_f = epoch + (b + 1) / steps_per_epoch
            step_s = time.perf_counter() - t0
            train_s += step_s
            report("step")
            stop, over, eval_due, diverged = ctx.any_flags(
                stop_event is not None and stop_event.is_set(),
                fraction_done(epoch_f, train_s) >= 1.0,
                time.perf_counter() - last_eval >= config.eval_interval_s,
                not math.isfinite(value),
            )
            if diverged:  # on every rank (any_flags): the group is closed at once
                ctx.close()
                if ctx.is_main:  # (was: left; a rerun with a lower --lr was refused for it, resumed or not)
                    remove_checkpoint(out_dir)
                raise _diverged(config, step, f"the loss is {value}")
            if stop or over:
                stopped = stop  # a stop request wins over a budget or deadline spent at the same step
                at_deadline = over and not stop and budget_fraction(epoch_f, train_s) < 1.0
                done = True
                break
            if eval_due:
                validate_and_checkpoint()
                last_eval = time.perf_counter()
                stopped, = ctx.any_flags(stop_event is not None and stop_event.is_set())  # during the validation
                if stopped:  # was: one more step first
                    done = True
                    break
        else:
            epoch_f = float(epoch + 1)

    result = None
    if ctx.is_main and stopped and not config.write_on_stop:
        if config.checkpoint_on_stop and step > 0:  # a stop checked between steps: optimizer and weights agree
            checkpoint()
        result = TrainResult(out_dir, {}, history, epoch_f, step, train_s, True, _peak_rss_mb())
    elif ctx.is_main:
        metrics = evaluate_tensors(network, val_t, ctx.device, metadata.min_depth, metadata.max_depth)
        if not math.isfinite(metrics["abs_rel"]):  # on rank 0 alone: the group is left to the process's exit, so
            # that torchrun stops the peers waiting in the barrier below (was: closed under them; torchrun's report
            # then named a peer's "connection closed" instead of this error, and with NCCL the close can hang)
            remove_checkpoint(out_dir)
            raise _diverged(config, step, "its depth on the validation frames is not finite")
        history.append({"train_s": train_s, "epoch": epoch_f, "step": step, "loss": running,
                        **evaluate_tensors(network, live_val, ctx.device, metadata.min_depth, metadata.max_depth)})
        peak = _peak_rss_mb()
        metadata.metrics = {**metrics, "split": split_info["kind"], "n_val_frames": len(val_t)}
        metadata.training = {
            "sources": sources,
            "val_sources": val_sources,
            "sensor_serials": serials,
            "split": split_info,
            "objects": objects,
            "n_train_frames": len(train_t),
            "n_val_frames": len(val_t),
            "init": init_info,
            "epochs": epoch_f,
            "steps": step,
            "train_s": train_s,
            "stopped_early": stopped,
            "deadline_s": config.deadline_s,
            "ended_at_deadline": at_deadline,
            "batch_size": config.batch_size * ctx.world_size,
            "world_size": ctx.world_size,
            "device": ctx.device_name(),  # rank 0's; train_s depends on it (was: not recorded)
            "torch": torch.__version__,
            "optimizer": {"name": "adam", "betas": [0.9, 0.999], "lr": config.lr,
                          "lr_halving": f"x0.5 after every {int(LR_HALVING_FRACTION * 100)} % of the budget"},
            "budget": {"epochs": config.epochs, "minutes": minutes},
            "loss": "l1-inverse-depth" if config.inverse_depth_loss else "l1-depth",
            "contact_weight": config.contact_weight,
            "augment": config.augment,
            "ir_noise_std": config.ir_noise_std if config.augment else 0.0,
            "seed": config.seed,
            "frame_stride": config.frame_stride,
            "peak_rss_mb": peak,
            "history": history,
        }
        save_model(out_dir, network.cpu(), metadata)
        if config.export_onnx:
            from trainer.onnx_export import export_and_select_runtime

            export_and_select_runtime(out_dir)
        remove_checkpoint(out_dir)
        result = TrainResult(out_dir, metadata.metrics, history, epoch_f, step, train_s, stopped, peak, at_deadline)
        val_live = history[-1]
        report("done")
    ctx.barrier()
    ctx.close()
    return result

