"""A model directory: safetensors weights + JSON metadata (never pickle).

Layout of ``MODEL_DIR``:

* ``model.safetensors``: the network's state dict.
* ``metadata.json``: ``ModelMetadata`` (arch, width, depth range, input geometry, IR
  normalization, training data, metrics, inference runtime).
* ``model.onnx`` (optional): the exported network, see ``trainer.onnx_export``.
* ``checkpoint.*`` (while training): see ``trainer.checkpoint``.

``load_network`` refuses pickle files and weights that are missing, unreadable or do not match
the architecture in the metadata with ``InputError``.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from collect.errors import InputError
from collect.json_files import write_json
from trainer.networks import build_network
from trainer.preprocessing import InputGeometry, IRNormalization

WEIGHTS_FILE = "model.safetensors"
METADATA_FILE = "metadata.json"
ONNX_FILE = "model.onnx"
METADATA_FORMAT = "bubble-depth-model"
METADATA_VERSION = 1

#: Directory of the committed base model, pretrained on many simulated sensors (``--init base``).
BASE_MODEL_DIR = Path(__file__).resolve().parent / "base_model"

#: File endings of pickle-based weight files, which are refused.
PICKLE_SUFFIXES = (".pt", ".pth", ".pkl", ".pickle", ".ckpt", ".bin")


@dataclass
class ModelMetadata:
    """Everything needed to rebuild and feed a trained network (``metadata.json``)."""

    arch: str
    width: float
    min_depth: float  # m
    max_depth: float  # m
    geometry: InputGeometry
    normalization: IRNormalization
    training: dict = field(default_factory=dict)  # data files, sha256, sensor serials, split, schedule
    metrics: dict = field(default_factory=dict)  # validation metrics (trainer.metrics keys)
    inference: dict = field(default_factory=dict)  # runtime ("onnx"|"torch"), ORT check, latencies

    def to_dict(self) -> dict:
        data = asdict(self)
        data["geometry"] = self.geometry.to_dict()
        data["normalization"] = self.normalization.to_dict()
        return {"format": METADATA_FORMAT, "format_version": METADATA_VERSION, **data}

    @classmethod
    def from_dict(cls, data: dict) -> "ModelMetadata":
        if data.get("format") != METADATA_FORMAT:
            raise InputError(f"not a bubble depth model metadata file (format {data.get('format')!r})")
        if data.get("format_version") != METADATA_VERSION:
            raise InputError(f"unsupported model metadata version {data.get('format_version')!r}")
        try:
            meta = cls(
                arch=str(data["arch"]),
                width=float(data["width"]),
                min_depth=float(data["min_depth"]),
                max_depth=float(data["max_depth"]),
                geometry=InputGeometry.from_dict(data["geometry"]),
                normalization=IRNormalization.from_dict(data["normalization"]),
                training=dict(data.get("training", {})),
                metrics=dict(data.get("metrics", {})),
                inference=dict(data.get("inference", {})),
            )
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(f"model metadata is incomplete or malformed: {err!r}") from None
        g, n = meta.geometry, meta.normalization
        if not (0 < meta.min_depth < meta.max_depth and math.isfinite(meta.max_depth)):
            raise InputError(f"model metadata: bad depth range {meta.min_depth}..{meta.max_depth} m")
        if min(g.native_height, g.native_width, g.input_height, g.input_width) < 1:
            raise InputError(f"model metadata: bad geometry {g.to_dict()}")
        if not (math.isfinite(n.mean) and math.isfinite(n.std) and n.std > 0):
            raise InputError(f"model metadata: bad IR normalization mean {n.mean}, std {n.std}")
        return meta


def resolve_model_dir(name: str | Path) -> Path:
    """``"base"`` -> the committed base model; anything else is a path."""
    return BASE_MODEL_DIR if str(name) == "base" else Path(name)


def write_safetensors(tensors: dict[str, torch.Tensor], path: Path, metadata: dict[str, str] | None = None) -> None:
    """Write ``tensors`` (contiguous, CPU) to the safetensors file ``path`` atomically: a temporary
    file beside it, renamed over ``path``. A failed write (a full disk) leaves ``path`` as it was
    and is raised as ``OSError`` with the system's reason and ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        save_file(tensors, str(tmp), metadata=metadata)
    except SafetensorError as err:  # an I/O error reads "... I/O error: No space left on device (os error 28)"
        tmp.unlink(missing_ok=True)
        code = re.search(r"os error (\d+)", str(err))
        number = int(code.group(1)) if code else errno.EIO
        raise OSError(number, os.strerror(number), str(path)) from None
    tmp.replace(path)


def save_model(model_dir: str | Path, network: nn.Module, metadata: ModelMetadata) -> Path:
    """Write ``network``'s weights and ``metadata`` into ``model_dir`` (created if needed)."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to("cpu").contiguous() for k, v in network.state_dict().items()}
    write_safetensors(state, model_dir / WEIGHTS_FILE, metadata={"arch": metadata.arch})
    write_metadata(model_dir, metadata)
    return model_dir


def write_metadata(model_dir: str | Path, metadata: ModelMetadata) -> None:
    """(Re)write ``metadata.json`` atomically."""
    write_json(Path(model_dir) / METADATA_FILE, metadata.to_dict(), sort_keys=True)


def load_metadata(model_dir: str | Path) -> ModelMetadata:
    """``metadata.json`` of ``model_dir``; ``InputError`` when missing or malformed."""
    model_dir = resolve_model_dir(model_dir)
    path = model_dir / METADATA_FILE
    if not model_dir.is_dir():
        raise InputError(f"model directory not found: {model_dir}")
    if not path.is_file():
        raise InputError(f"model directory {model_dir} has no {METADATA_FILE}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path} is not valid JSON: {err}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path} does not hold a JSON object")
    return ModelMetadata.from_dict(data)


def _looks_like_pickle(path: Path) -> bool:
    """True for pickle streams (protocol 2+) and torch.save zip archives."""
    with path.open("rb") as fh:
        head = fh.read(2)
    return head[:1] == b"\x80" or head == b"PK"


def load_weights(model_dir: str | Path) -> dict[str, torch.Tensor]:
    """The safetensors state dict of ``model_dir``; refuses pickle files with ``InputError``."""
    model_dir = resolve_model_dir(model_dir)
    path = model_dir / WEIGHTS_FILE
    if not path.is_file():
        pickles = sorted(p.name for p in model_dir.iterdir() if p.suffix in PICKLE_SUFFIXES) if model_dir.is_dir() else []
        if pickles:
            raise InputError(f"refusing pickle weights {pickles[0]} in {model_dir}: only {WEIGHTS_FILE} (safetensors) is loaded")
        raise InputError(f"model directory {model_dir} has no {WEIGHTS_FILE}")
    if _looks_like_pickle(path):
        raise InputError(f"refusing {path}: it is a pickle file, not safetensors")
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as err:
        raise InputError(f"cannot read weights {path}: {err}") from None


def load_network(model_dir: str | Path) -> tuple[nn.Module, ModelMetadata]:
    """The network of ``model_dir`` in eval mode, with its metadata; ``InputError`` on any mismatch."""
    metadata = load_metadata(model_dir)
    network = build_network(metadata.arch, metadata.width, metadata.min_depth, metadata.max_depth)
    state = load_weights(model_dir)
    expected = network.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        detail = f"missing {missing[0]}" if missing else f"unexpected {unexpected[0]}"
        raise InputError(
            f"weights in {resolve_model_dir(model_dir)} do not match a {metadata.arch} of width {metadata.width} "
            f"({len(missing)} missing, {len(unexpected)} unexpected tensors; {detail})"
        )
    for key, tensor in state.items():
        if tensor.shape != expected[key].shape:
            raise InputError(
                f"weight {key} has shape {tuple(tensor.shape)}, the {metadata.arch} of width "
                f"{metadata.width} needs {tuple(expected[key].shape)}"
            )
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise InputError(f"weight {key} in {resolve_model_dir(model_dir)} holds NaN or inf")
    network.load_state_dict(state)
    return network.eval(), metadata
