"""Training checkpoints in a model directory, without pickle.

``checkpoint.safetensors`` holds the network weights and the optimizer's tensors
(``net.<name>``, ``optim.<param index>.<state name>``); ``checkpoint.json`` holds the optimizer's
hyper-parameters and the training progress (epoch, step, elapsed seconds, history, ...). Each file
is replaced whole, one after the other; both carry one random ``checkpoint_id`` (the weights in
their safetensors metadata), so that a pair torn by a kill between the two writes (weights of
step k, progress of step k-1: a resume would train one step more than its budget) is refused.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors import safe_open
from safetensors.torch import load_file
from torch import nn

from collect.errors import InputError
from collect.json_files import JSON_READ_ERRORS, write_json
from trainer.model_dir import METADATA_FILE, ONNX_FILE, WEIGHTS_FILE, write_safetensors

CHECKPOINT_WEIGHTS = "checkpoint.safetensors"
CHECKPOINT_STATE = "checkpoint.json"
#: Every file a training writes into its model directory (a new training refuses a folder holding one).
TRAINING_FILES = (WEIGHTS_FILE, METADATA_FILE, ONNX_FILE, CHECKPOINT_WEIGHTS, CHECKPOINT_STATE)
#: What ``progress`` must hold for a resume, and of which JSON types (``trainer.training`` writes more).
PROGRESS_TYPES = {"epoch": (int, float), "step": (int,), "train_s": (int, float), "history": (list,),
                  "loss": (int, float)}


def has_checkpoint(model_dir: str | Path) -> bool:
    model_dir = Path(model_dir)
    return (model_dir / CHECKPOINT_WEIGHTS).is_file() and (model_dir / CHECKPOINT_STATE).is_file()


def check_resumable(model_dir: str | Path, instead: str) -> None:
    """``InputError`` unless ``model_dir`` holds a checkpoint for ``--resume`` to continue (was: a fresh
    training, over a finished model too); ``instead``: what to do then, ending the message."""
    model_dir = Path(model_dir)
    if has_checkpoint(model_dir):
        return
    left = ("its training finished (a model, no checkpoint)" if (model_dir / WEIGHTS_FILE).exists()
            else "it holds no checkpoint of an interrupted training")
    raise InputError(f"cannot resume {model_dir}: {left}; {instead}")


def check_checkpoint_use(model_dir: str | Path, resume: bool, resume_instead: str, fresh_instead: str) -> None:
    """``InputError`` unless the training into ``model_dir`` uses its checkpoint as asked: ``resume``
    needs one (``check_resumable``, ``resume_instead`` ending the message), a fresh training refuses one
    (was: trained anew, and its first checkpoint wrote over the interrupted one; ``fresh_instead``)."""
    if resume:
        check_resumable(model_dir, resume_instead)
    elif has_checkpoint(model_dir):
        raise InputError(f"{model_dir} holds the checkpoint of an interrupted training; add --resume to continue "
                         f"it, or {fresh_instead}")


def remove_checkpoint(model_dir: str | Path) -> None:
    """Delete ``model_dir``'s checkpoint files (where they exist): once the training has finished, or
    diverged (its checkpoint could only be resumed with the learning rate that diverged)."""
    for name in (CHECKPOINT_WEIGHTS, CHECKPOINT_STATE):
        (Path(model_dir) / name).unlink(missing_ok=True)


def save_checkpoint(model_dir: str | Path, network: nn.Module, optimizer: torch.optim.Optimizer, progress: dict) -> None:
    """Write network + optimizer state and the JSON-serializable ``progress`` (atomically, per file)."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    tensors = {f"net.{k}": v.detach().cpu().contiguous() for k, v in network.state_dict().items()}
    opt = optimizer.state_dict()
    for index, state in opt["state"].items():
        for name, value in state.items():
            tensors[f"optim.{index}.{name}"] = torch.as_tensor(value).detach().cpu().contiguous()
    checkpoint_id = uuid.uuid4().hex
    write_safetensors(tensors, model_dir / CHECKPOINT_WEIGHTS, metadata={"checkpoint_id": checkpoint_id})
    state = {"checkpoint_id": checkpoint_id, "param_groups": opt["param_groups"], "progress": progress}
    write_json(model_dir / CHECKPOINT_STATE, state)


def _holds_progress(progress) -> bool:
    """Whether ``progress`` holds every ``PROGRESS_TYPES`` key with a value of its type (a bool is no
    number here; was: an edited ``"step": null`` failed with a traceback after the weights had loaded)."""
    return isinstance(progress, dict) and all(
        key in progress and isinstance(progress[key], types) and not isinstance(progress[key], bool)
        for key, types in PROGRESS_TYPES.items()) and all(isinstance(entry, dict) for entry in progress["history"])


def load_checkpoint(model_dir: str | Path, network: nn.Module, optimizer: torch.optim.Optimizer,
                    check: Callable[[dict], None] | None = None) -> dict:
    """Restore network and optimizer from ``model_dir``; returns the saved progress dict. ``check``
    is called with it before anything is restored (it may refuse the checkpoint's settings before
    weights of another network fail to load). ``InputError`` for files that cannot be read, hold
    other content, or are of two saves."""
    model_dir = Path(model_dir)
    try:
        tensors = load_file(str(model_dir / CHECKPOINT_WEIGHTS))
        with safe_open(str(model_dir / CHECKPOINT_WEIGHTS), "pt") as f:
            weights_id = (f.metadata() or {}).get("checkpoint_id")
        state = json.loads((model_dir / CHECKPOINT_STATE).read_text())
    except (SafetensorError, *JSON_READ_ERRORS) as err:
        raise InputError(f"cannot read the checkpoint in {model_dir}: {err}") from None
    progress = state.get("progress") if isinstance(state, dict) else None
    if not _holds_progress(progress) or not isinstance(state.get("param_groups"), list):
        raise InputError(f"cannot read the checkpoint in {model_dir}: its {CHECKPOINT_STATE} does not hold the "
                         "optimizer's settings and the training's progress; train anew without --resume")
    if state.get("checkpoint_id") != weights_id:
        raise InputError(f"the checkpoint in {model_dir} is torn: {CHECKPOINT_WEIGHTS} and {CHECKPOINT_STATE} come "
                         "from two saves (the training was killed between them); train anew without --resume")
    if check is not None:
        check(progress)
    net_state = {k[4:]: v for k, v in tensors.items() if k.startswith("net.")}
    try:
        network.load_state_dict(net_state)
    except RuntimeError as err:
        raise InputError(f"checkpoint in {model_dir} does not match the network: {str(err).splitlines()[0]}") from None
    opt_state: dict = {}
    try:  # a tensor name that is not optim.<index>.<name> (an edited file) is a ValueError too (was: a traceback)
        for key, value in tensors.items():
            if key.startswith("optim."):
                _, index, name = key.split(".", 2)
                opt_state.setdefault(int(index), {})[name] = value
        optimizer.load_state_dict({"state": opt_state, "param_groups": state["param_groups"]})
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"cannot read the checkpoint in {model_dir}: its optimizer state does not match the "
                         f"network ({err}); train anew without --resume") from None
    return progress
