"""Data-parallel training under torchrun with 2 CPU processes (gloo)."""

import os
import subprocess
import sys

import pytest

from conftest import make_synthetic_session
from trainer.model_dir import load_metadata


def test_torchrun_two_gloo_processes_train_one_model(tmp_path):
    session = make_synthetic_session(tmp_path / "s.h5", height=48, width=64, poses_per_object=2)
    out = tmp_path / "model"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CUDA_VISIBLE_DEVICES": ""}  # CPU processes, also on a GPU machine
    # --standalone: the rendezvous takes a free port itself (was: a port found free, closed, then bound by
    # torchrun: another suite on the machine could take it in between)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "calibrate.cli", "train", "--data", str(session),
           "--out", str(out), "--width", "0.125", "--epochs", "1", "--batch-size", "2", "--no-onnx"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-8000:]  # the ranks' own tracebacks, not only torchrun's summary
    meta = load_metadata(out)
    assert meta.training["world_size"] == 2 and meta.training["batch_size"] == 4
    n_train = meta.training["n_train_frames"]
    assert meta.training["steps"] == -(-(n_train // 2) // 2)  # each rank: half the frames, batches of 2


def test_more_processes_than_gpus_is_bad_input(monkeypatch):
    """torchrun --nproc_per_node 2 on a one-GPU machine: one clear error before joining the group
    (found on an H100 machine, where rank 1 failed in ``torch.cuda.set_device(1)``)."""
    import torch

    from collect.errors import InputError
    from trainer.distributed import DistContext

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("LOCAL_RANK", "1")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    monkeypatch.setenv("MASTER_ADDR", "localhost")
    monkeypatch.setenv("MASTER_PORT", "29500")
    with pytest.raises(InputError, match="2 processes per machine but 1 GPU"):
        DistContext.from_env()
    assert not torch.distributed.is_initialized()


@pytest.mark.parametrize("env, says", [
    ({"WORLD_SIZE": "2"}, "WORLD_SIZE=2 without RANK, MASTER_ADDR, MASTER_PORT: start the processes with torchrun, "
                          "or unset WORLD_SIZE to train in one process"),
    ({"WORLD_SIZE": "x"}, "WORLD_SIZE=x: torchrun's variable must be an integer of 1 or more"),
    ({"WORLD_SIZE": "2", "RANK": "2", "MASTER_ADDR": "localhost", "MASTER_PORT": "29500"},
     "RANK=2: torchrun's variable must be an integer within 0..1"),
    ({"WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "-1", "MASTER_ADDR": "localhost", "MASTER_PORT": "29500"},
     "LOCAL_RANK=-1: torchrun's variable must be an integer within 0..1"),
])
def test_torchruns_variables_set_otherwise_are_bad_input(monkeypatch, env, says):
    """Was: a stray ``WORLD_SIZE`` gave a ``KeyError: 'RANK'`` or ``ValueError`` traceback, exit 1."""
    import torch

    from collect.errors import InputError
    from trainer.distributed import DistContext

    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with pytest.raises(InputError) as err:
        DistContext.from_env(prefer_cuda=False)
    assert str(err.value).startswith(says), err.value
    assert not torch.distributed.is_initialized()

