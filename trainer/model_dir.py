"""A model directory: safetensors weights + JSON metadata (never pickle).

Layout of ``MODEL_DIR``:

* ``model.safetensors``: the network's state dict.
* ``metadata.json``: ``ModelMetadata`` (arch, width, depth range, input geometry, IR
  normalization, training data, metrics, inference runtime).
* ``model.onnx`` (optional): the exported network, see ``trainer.onnx_export``; ``metadata.json``
  ``inference`` records its SHA-256 and that of the weights it was exported from (``export_hashes``).
* ``checkpoint.*`` (while training): see ``trainer.checkpoint``.

``load_metadata`` refuses a ``metadata.json`` with a value missing, of the wrong type or out of
range (``check_metadata``); ``load_network`` refuses pickle files and weights that are missing,
unreadable or do not match the architecture in the metadata. Both raise ``InputError``.
"""

from __future__ import annotations

import errno
import json
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from collect.errors import InputError
from collect.atomic_files import NEW_FILE_MODE, replacing
from collect.json_files import JSON_READ_ERRORS, shown_json, write_json
from trainer.dataset import file_sha256
from trainer.networks import ARCHITECTURES, INPUT_MULTIPLE, MAX_WIDTH, build_network
from trainer.preprocessing import MAX_LOG_IR, MIN_IR_STD, InputGeometry, IRNormalization

WEIGHTS_FILE = "model.safetensors"
METADATA_FILE = "metadata.json"
ONNX_FILE = "model.onnx"
METADATA_FORMAT = "bubble-depth-model"
METADATA_VERSION = 1

#: Directory of the committed base model, pretrained on many simulated sensors (``--init base``).
BASE_MODEL_DIR = Path(__file__).resolve().parent / "base_model"

#: Limits of ``metadata.json`` values (``check_metadata``), wide around the default model (0.04-0.12 m,
#: 224 x 172 px frames in a 224 x 224 px input): depths in m, sizes in pixels.
MIN_DEPTH_M = 1e-3
MAX_DEPTH_M = 10.0
MAX_NATIVE_SIZE = 4096
MAX_INPUT_SIZE = 2048

#: ``metadata.json`` ``inference`` key -> the file whose SHA-256 (hex) it records at the ONNX export.
EXPORT_HASH_KEYS = {"onnx_sha256": ONNX_FILE, "weights_sha256": WEIGHTS_FILE}

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
    inference: dict = field(default_factory=dict)  # runtime ("onnx"|"torch"), ORT check, latencies, export hashes

    def to_dict(self) -> dict:
        data = asdict(self)
        data["geometry"] = self.geometry.to_dict()
        data["normalization"] = self.normalization.to_dict()
        return {"format": METADATA_FORMAT, "format_version": METADATA_VERSION, **data}

    def sensors_not_trained_on(self, serials) -> list[str]:
        """Those of ``serials`` (the sensor serials of the data the model is applied to) that none of
        its training sessions was recorded with, sorted; empty when ``training`` does not list them."""
        trained = self.training.get("sensor_serials")
        if not isinstance(trained, list):
            return []
        return sorted({str(s) for s in serials} - {str(s) for s in trained})

    @classmethod
    def from_dict(cls, data: dict, model_dir: str | Path) -> "ModelMetadata":
        """The metadata in ``data`` (the parsed ``metadata.json`` of ``model_dir``), checked by
        ``check_metadata`` before anything is built from it."""
        where = f"model {model_dir}: metadata.json"
        for name, expected, what in (("format", METADATA_FORMAT, "a bubble depth model's"),
                                     ("format_version", METADATA_VERSION, "the version this build reads")):
            if name not in data:
                raise InputError(f"{where} has no field '{name}' (not a bubble depth model directory)")
            if data[name] != expected or isinstance(data[name], bool):
                raise InputError(f"{where} field '{name}' = {shown_json(data[name])} must be "
                                 f"{shown_json(expected)} ({what})")
        check_metadata(data, model_dir)
        return cls(
            arch=data["arch"],
            width=float(data["width"]),
            min_depth=float(data["min_depth"]),
            max_depth=float(data["max_depth"]),
            geometry=InputGeometry.from_dict(data["geometry"]),
            normalization=IRNormalization.from_dict(data["normalization"]),
            training=data.get("training", {}),
            metrics=data.get("metrics", {}),
            inference=data.get("inference", {}),
        )


def _field(data: dict, name: str, where: str, kind: type | tuple[type, ...], rule: str, ok=lambda value: True):
    """The value of field ``name`` (dotted: ``"geometry.input_height"``) from ``data``, the JSON object
    that holds it; ``InputError`` naming ``where`` and ``name`` when it is missing, not of ``kind``
    (``bool`` is no number) or ``ok(value)`` is false (``rule`` says what it must be)."""
    key = name.rsplit(".", 1)[-1]
    if key not in data:
        raise InputError(f"{where}: metadata.json has no field '{name}'")
    value = data[key]
    if not (isinstance(value, kind) and not isinstance(value, bool) and ok(value)):
        raise InputError(f"{where}: metadata.json field '{name}' = {shown_json(value)} must be {rule}")
    return value


def check_metadata(data: dict, model_dir: str | Path) -> None:
    """Raise ``InputError`` (one line naming ``model_dir`` and the field) unless every value of
    ``data``, a parsed ``metadata.json``, is present, of its JSON type and in range: a known
    ``arch``, a width in (0, ``MAX_WIDTH``], depths (m) with ``MIN_DEPTH_M`` <= min < max <=
    ``MAX_DEPTH_M``, native sizes (px) in [1, ``MAX_NATIVE_SIZE``], input sizes (px) positive
    multiples of ``INPUT_MULTIPLE`` up to ``MAX_INPUT_SIZE``, a normalization mean in
    [0, ``MAX_LOG_IR``] and std in [``MIN_IR_STD``, ``MAX_LOG_IR``] (ln-amplitude units). Composing
    the message cannot fail: the value is shown as the file holds it, cut to 40 characters."""
    where = f"model {model_dir}"
    number = (int, float)
    _field(data, "arch", where, str, f"one of {', '.join(ARCHITECTURES)}", lambda v: v in ARCHITECTURES)
    _field(data, "width", where, number, f"a number in (0, {MAX_WIDTH:g}]", lambda v: 0 < v <= MAX_WIDTH)
    min_depth = _field(data, "min_depth", where, number, f"a depth in [{MIN_DEPTH_M:g}, {MAX_DEPTH_M:g}) m",
                       lambda v: MIN_DEPTH_M <= v < MAX_DEPTH_M)
    _field(data, "max_depth", where, number, f"a depth above min_depth {min_depth:g} m, at most {MAX_DEPTH_M:g} m",
           lambda v: min_depth < v <= MAX_DEPTH_M)
    geometry = _field(data, "geometry", where, dict, "a JSON object")
    for side in ("height", "width"):
        _field(geometry, f"geometry.native_{side}", where, int, f"a number of pixels in [1, {MAX_NATIVE_SIZE}]",
               lambda v: 1 <= v <= MAX_NATIVE_SIZE)
        _field(geometry, f"geometry.input_{side}", where, int,
               f"a positive multiple of {INPUT_MULTIPLE} up to {MAX_INPUT_SIZE} (pixels)",
               lambda v: 0 < v <= MAX_INPUT_SIZE and v % INPUT_MULTIPLE == 0)
    normalization = _field(data, "normalization", where, dict, "a JSON object")
    _field(normalization, "normalization.kind", where, str, f'"{IRNormalization.KIND}"', lambda v: v == IRNormalization.KIND)
    _field(normalization, "normalization.mean", where, number, f"a number in [0, {MAX_LOG_IR:.2f}] (ln amplitude)",
           lambda v: 0 <= v <= MAX_LOG_IR)
    _field(normalization, "normalization.std", where, number,
           f"a number in [{MIN_IR_STD:g}, {MAX_LOG_IR:.2f}] (ln amplitude)", lambda v: MIN_IR_STD <= v <= MAX_LOG_IR)
    for name in ("training", "metrics", "inference"):  # optional
        if name in data:
            _field(data, name, where, dict, "a JSON object")


def resolve_model_dir(name: str | Path) -> Path:
    """``"base"`` -> the committed base model; anything else is a path."""
    return BASE_MODEL_DIR if str(name) == "base" else Path(name)


def write_safetensors(tensors: dict[str, torch.Tensor], path: Path, metadata: dict[str, str] | None = None) -> None:
    """Write ``tensors`` (contiguous, CPU) to the safetensors file ``path`` atomically
    (``collect.atomic_files.replacing``), with the permissions of any new file. A failed write (a
    full disk) leaves ``path`` as it was and is raised as ``OSError`` with the system's reason and
    ``path``."""
    with replacing(path) as tmp:
        try:
            save_file(tensors, str(tmp), metadata=metadata)
        except SafetensorError as err:  # an I/O error reads "... I/O error: No space left on device (os error 28)"
            code = re.search(r"os error (\d+)", str(err))
            number = int(code.group(1)) if code else errno.EIO
            raise OSError(number, os.strerror(number), str(path)) from None
        tmp.chmod(NEW_FILE_MODE)  # safetensors writes 0600


def save_model(model_dir: str | Path, network: nn.Module, metadata: ModelMetadata) -> Path:
    """Write ``network``'s weights and ``metadata`` into ``model_dir`` (created if needed); the weights'
    SHA-256 goes into ``metadata.inference["weights_sha256"]``, which ``load_network`` checks."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to("cpu").contiguous() for k, v in network.state_dict().items()}
    write_safetensors(state, model_dir / WEIGHTS_FILE, metadata={"arch": metadata.arch})
    metadata.inference = {**metadata.inference, "weights_sha256": weights_sha256(model_dir)}
    write_metadata(model_dir, metadata)
    return model_dir


def write_metadata(model_dir: str | Path, metadata: ModelMetadata) -> None:
    """(Re)write ``metadata.json`` atomically."""
    write_json(Path(model_dir) / METADATA_FILE, metadata.to_dict(), sort_keys=True)


def load_metadata(model_dir: str | Path) -> ModelMetadata:
    """``metadata.json`` of ``model_dir``; ``InputError`` when missing, unreadable or malformed."""
    model_dir = resolve_model_dir(model_dir)
    path = model_dir / METADATA_FILE
    try:
        if not model_dir.is_dir():
            raise InputError(f"model directory not found: {model_dir}")
        if path.exists() and not path.is_file():  # a folder or a pipe of that name
            raise InputError(f"{path} is not a regular file")
        if not path.is_file():
            inner = model_dir / "model"  # a commissioning run folder holds its model there
            hint = (f" (a commissioning run? its model is {inner})" if (inner / METADATA_FILE).is_file() else "")
            raise InputError(f"model directory {model_dir} has no {METADATA_FILE}{hint}")
        raw = path.read_bytes()
    except OSError as err:  # a folder on the way that cannot be entered, a file that cannot be read
        raise _unreadable(path, err) from None
    try:
        data = json.loads(raw)  # json decodes the bytes (UTF-8, -16 or -32)
    except JSON_READ_ERRORS as err:
        raise InputError(f"{path} is not valid JSON: {err}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path} does not hold a JSON object")
    return ModelMetadata.from_dict(data, model_dir)


def model_file_sha256(model_dir: str | Path, name: str) -> str:
    """SHA-256 (hex) of the file ``name`` in ``model_dir``; ``InputError`` naming it when it cannot be read."""
    path = Path(model_dir) / name
    try:
        return file_sha256(path)
    except OSError as err:
        raise _unreadable(path, err) from None


def export_hashes(model_dir: str | Path) -> dict[str, str]:
    """SHA-256 (hex) of ``model.onnx`` and ``model.safetensors`` in ``model_dir``, under their
    ``EXPORT_HASH_KEYS``; ``InputError`` naming a file that cannot be read."""
    return {key: model_file_sha256(model_dir, name) for key, name in EXPORT_HASH_KEYS.items()}


def weights_sha256(model_dir: str | Path) -> str:
    """SHA-256 (hex) of the weights of ``model_dir`` (``"base"``: the packaged base model): what a run
    that starts from a model records of it, whatever path named it."""
    return file_sha256(resolve_model_dir(model_dir) / WEIGHTS_FILE)


def _unreadable(path: Path, err: OSError) -> InputError:
    """The one-line refusal of a model file ``path`` that the system would not read (``err``, e.g. a
    ``PermissionError``): names the file or folder that failed and the system's reason."""
    return InputError(f"cannot read {err.filename or path}: {err.strerror or err}")


def _looks_like_safetensors(path: Path) -> bool:
    """True when ``path`` begins as a safetensors file: an 8-byte little-endian header length,
    then that many bytes of a JSON object."""
    with path.open("rb") as fh:
        size = int.from_bytes(fh.read(8), "little")
        if not 2 <= size <= path.stat().st_size - 8:
            return False
        header = fh.read(size)
    try:
        return isinstance(json.loads(header), dict)
    except (ValueError, UnicodeDecodeError):
        return False


def _looks_like_pickle(path: Path) -> bool:
    """True for pickle streams (protocol 2+) and torch.save zip archives that are not safetensors
    (whose header length may begin with the same bytes: 0x80, or "PK")."""
    with path.open("rb") as fh:
        head = fh.read(2)
    return (head[:1] == b"\x80" or head == b"PK") and not _looks_like_safetensors(path)


def load_weights(model_dir: str | Path) -> dict[str, torch.Tensor]:
    """The safetensors state dict of ``model_dir``; refuses pickle files with ``InputError``."""
    model_dir = resolve_model_dir(model_dir)
    path = model_dir / WEIGHTS_FILE
    try:
        if path.exists() and not path.is_file():
            raise InputError(f"{path} is not a regular file")
        if not path.is_file():
            pickles = sorted(p.name for p in model_dir.iterdir() if p.suffix in PICKLE_SUFFIXES) if model_dir.is_dir() else []
            if pickles:
                raise InputError(f"refusing pickle weights {pickles[0]} in {model_dir}: only {WEIGHTS_FILE} (safetensors) is loaded")
            raise InputError(f"model directory {model_dir} has no {WEIGHTS_FILE}")
        is_pickle = _looks_like_pickle(path)
    except OSError as err:  # a folder on the way that cannot be entered or listed, weights that cannot be read
        raise _unreadable(path, err) from None
    if is_pickle:
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
        if tensor.is_floating_point() != expected[key].is_floating_point():  # was: cast and loaded
            raise InputError(f"weight {key} in {resolve_model_dir(model_dir)} is {str(tensor.dtype).removeprefix('torch.')}, "
                             f"the network holds {str(expected[key].dtype).removeprefix('torch.')} there")
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise InputError(f"weight {key} in {resolve_model_dir(model_dir)} holds NaN or inf")
    recorded = metadata.inference.get("weights_sha256")  # (folders saved before it was recorded: not checked)
    if recorded is not None and weights_sha256(model_dir) != recorded:  # was: loaded, its depth up to 16 mm off
        path = resolve_model_dir(model_dir) / WEIGHTS_FILE
        raise InputError(f"{path} is not the weights file that {METADATA_FILE} records (another SHA-256): the "
                         "folder mixes two models; copy a model folder whole, or train it again")
    network.load_state_dict(state)
    return network.eval(), metadata
