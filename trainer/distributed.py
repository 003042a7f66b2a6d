"""Distributed data-parallel training under ``torchrun`` (gloo on CPU, nccl on GPU).

``torchrun --nproc_per_node 2 -m calibrate.cli train --data ... --out MODEL_DIR`` runs the same
``bubble train`` entry in every process; ``DistContext.from_env()`` sees torchrun's environment
(``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``) and joins the process group.
With a GPU, each process takes the GPU of its local rank, so ``--nproc_per_node`` may not exceed the
machine's GPUs (bad input otherwise); ``CUDA_VISIBLE_DEVICES=`` trains on the CPU instead.
Rank 0 validates, checkpoints and writes the model directory; every rank trains on its own
shard of each epoch's shuffled frames, and gradients are averaged by DDP.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from collect.errors import InputError


def _env_int(name: str, default: int | None, lo: int, hi: int | None = None) -> int:
    """The environment variable ``name`` as an integer within ``lo..hi`` (``default`` when unset)."""
    text = os.environ.get(name)
    if text is None and default is not None:
        return default
    try:
        value = int(text)
    except (TypeError, ValueError):
        value = None
    if value is None or value < lo or (hi is not None and value > hi):
        within = f"within {lo}..{hi}" if hi is not None else f"of {lo} or more"
        raise InputError(f"{name}={text}: torchrun's variable must be an integer {within}; start the "
                         "processes with torchrun, or unset WORLD_SIZE to train in one process")
    return value


@dataclass(frozen=True)
class DistContext:
    """Where this process sits in the (possibly single-process) training job."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1
    device: str = "cpu"

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_env(cls, prefer_cuda: bool = True) -> "DistContext":
        """Single-process context, or join torchrun's process group when ``WORLD_SIZE > 1``.
        ``InputError`` for torchrun's variables set otherwise than torchrun sets them (was: a
        ``KeyError`` or ``ValueError`` traceback for a stray ``WORLD_SIZE``)."""
        world = _env_int("WORLD_SIZE", 1, 1)
        cuda = prefer_cuda and torch.cuda.is_available()
        if world <= 1:
            return cls(device="cuda" if cuda else "cpu")
        missing = [name for name in ("RANK", "MASTER_ADDR", "MASTER_PORT") if not os.environ.get(name)]
        if missing:
            raise InputError(f"WORLD_SIZE={world} without {', '.join(missing)}: start the processes with torchrun, "
                             "or unset WORLD_SIZE to train in one process")
        rank = _env_int("RANK", None, 0, world - 1)
        local_world = _env_int("LOCAL_WORLD_SIZE", world, 1, world)
        local_rank = _env_int("LOCAL_RANK", 0, 0, local_world - 1)
        gpus = torch.cuda.device_count() if cuda else 0
        if cuda and local_world > gpus:  # set_device(local_rank) would fail in some ranks
            raise InputError(f"{local_world} processes per machine but {gpus} GPU(s): run torchrun with "
                             f"--nproc_per_node {gpus}, or hide the GPUs (CUDA_VISIBLE_DEVICES=) to train on the CPU")
        if not dist.is_initialized():
            dist.init_process_group(backend="nccl" if cuda else "gloo")
        if cuda:
            torch.cuda.set_device(local_rank)
        return cls(rank, world, local_rank, local_world, f"cuda:{local_rank}" if cuda else "cpu")

    def device_name(self) -> str:
        """What this process trains on, for the model's metadata: ``cpu`` or ``cuda:<i> (<GPU name>)``."""
        if self.device == "cpu":
            return "cpu"
        index = torch.device(self.device).index
        index = torch.cuda.current_device() if index is None else index  # a single process: "cuda"
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"

    def cpu_threads(self) -> int:
        """Torch intra-op threads for this process: the machine's cores shared by the local processes."""
        return max(1, (os.cpu_count() or 1) // self.local_world_size)

    def any_flags(self, *flags: bool) -> tuple[bool, ...]:
        """Each flag made true on every rank when it is true on any rank (one all-reduce)."""
        if not self.enabled:
            return tuple(bool(f) for f in flags)
        t = torch.tensor([1.0 if f else 0.0 for f in flags], device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return tuple(bool(v > 0) for v in t.tolist())

    def barrier(self) -> None:
        if self.enabled:
            dist.barrier()

    def close(self) -> None:
        if self.enabled and dist.is_initialized():
            dist.destroy_process_group()
