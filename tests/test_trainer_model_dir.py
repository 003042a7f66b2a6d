"""Model directory: safetensors + metadata round trip, refusal of pickle and mismatched weights, and of
metadata.json values that are missing, of the wrong type or out of range."""

import errno
import json
import os

import numpy as np
import pytest
import torch

from calibrate.cli import main
from collect.errors import InputError
from trainer.inference import DepthEstimator
from trainer.model_dir import METADATA_FILE, WEIGHTS_FILE, ModelMetadata, load_metadata, load_network, save_model
from trainer.networks import build_network
from trainer.onnx_export import export_and_select_runtime
from trainer.preprocessing import InputGeometry, IRNormalization


def _metadata(width=0.125):
    return ModelMetadata(
        arch="resnet", width=width, min_depth=0.04, max_depth=0.12,
        geometry=InputGeometry(48, 64, 64, 64), normalization=IRNormalization(mean=7.0, std=1.5),
        training={"sensor_serials": ["SYN-0001"]}, metrics={"a1": 0.5},
    )


@pytest.fixture
def model_dir(tmp_path):
    torch.manual_seed(0)
    net = build_network("resnet", 0.125, 0.04, 0.12)
    save_model(tmp_path / "model", net, _metadata())
    return tmp_path / "model"


def test_round_trip_gives_identical_predictions(model_dir):
    net, meta = load_network(model_dir)
    assert meta.arch == "resnet" and meta.geometry == InputGeometry(48, 64, 64, 64)
    assert meta.training["sensor_serials"] == ["SYN-0001"] and meta.metrics["a1"] == 0.5
    ir = np.random.default_rng(0).integers(100, 5000, (48, 64), dtype=np.uint16)
    torch_depth = DepthEstimator.load(model_dir, runtime="torch").predict(ir)
    assert torch_depth.shape == (48, 64) and torch_depth.dtype == np.float32
    info = export_and_select_runtime(model_dir, repeats=2)
    assert info["onnx_matches_torch"] and info["onnx_max_abs_diff_m"] < 1e-4
    assert json.loads((model_dir / METADATA_FILE).read_text())["inference"]["runtime"] == info["runtime"]
    onnx_depth = DepthEstimator.load(model_dir, runtime="onnx").predict(ir)
    assert np.max(np.abs(onnx_depth - torch_depth)) < 1e-4
    with pytest.raises(InputError, match="frame size"):
        DepthEstimator.load(model_dir).predict(np.zeros((172, 224), np.uint16))


def test_weights_get_the_permissions_of_any_new_file(model_dir):
    """Was 0600 (safetensors' own): a registry model other users of the bench could not load."""
    (model_dir / "plain.txt").write_text("x")
    assert (model_dir / WEIGHTS_FILE).stat().st_mode & 0o777 == (model_dir / "plain.txt").stat().st_mode & 0o777


def test_pickle_weights_are_refused(model_dir):
    state = build_network("resnet", 0.125, 0.04, 0.12).state_dict()
    torch.save(state, model_dir / WEIGHTS_FILE)  # a pickle under the safetensors name
    with pytest.raises(InputError, match="pickle"):
        load_network(model_dir)
    (model_dir / WEIGHTS_FILE).rename(model_dir / "model.pt")
    with pytest.raises(InputError, match="pickle"):
        load_network(model_dir)


def test_safetensors_whose_header_length_begins_as_a_pickle_are_loaded(model_dir):
    """A safetensors file begins with its header's length, little-endian: where that length is
    0x..80, its first byte is a pickle's (was: a model of bts width 0.3, written by bubble train,
    refused by every command as "a pickle file"), and where it is 0x4b50, torch.save's "PK"."""
    from safetensors.torch import save_file

    state = build_network("resnet", 0.125, 0.04, 0.12).state_dict()
    path = model_dir / WEIGHTS_FILE
    plain = int.from_bytes(path.read_bytes()[:8], "little")
    for head, modulus in ((b"\x80", 0x100), (b"PK", 0x10000)):
        target = int.from_bytes(head, "little")
        gap = (target - plain) % modulus  # metadata characters to add (the header is padded to 8 bytes)
        for pad in range(max(gap - 40, 0), gap + 8):
            save_file(state, str(path), metadata={"pad": "x" * pad})
            if path.read_bytes().startswith(head):
                break
        assert path.read_bytes().startswith(head)
        net, _ = load_network(model_dir)
        assert all(torch.equal(v, state[k]) for k, v in net.state_dict().items())


def test_weights_of_integers_where_the_network_holds_floats_are_refused(model_dir):
    """Was: cast to float and loaded, a model of whole-number weights evaluated as if it were one."""
    from safetensors.torch import save_file

    state = {k: v.to(torch.int32) if v.is_floating_point() else v
             for k, v in build_network("resnet", 0.125, 0.04, 0.12).state_dict().items()}
    save_file(state, str(model_dir / WEIGHTS_FILE))
    with pytest.raises(InputError, match=r"weight \S+ in .* is int32, the network holds float32 there"):
        load_network(model_dir)


def test_missing_mismatched_or_garbage_weights(model_dir, tmp_path):
    meta = json.loads((model_dir / METADATA_FILE).read_text())
    meta["width"] = 0.25
    (model_dir / METADATA_FILE).write_text(json.dumps(meta))
    with pytest.raises(InputError, match="do not match|needs"):
        load_network(model_dir)
    (model_dir / WEIGHTS_FILE).write_bytes(b"\x00" * 100)
    with pytest.raises(InputError, match="cannot read weights"):
        load_network(model_dir)
    (model_dir / WEIGHTS_FILE).unlink()
    (model_dir / WEIGHTS_FILE).mkdir()  # was: "has no model.safetensors"
    with pytest.raises(InputError, match="model.safetensors is not a regular file"):
        load_network(model_dir)
    (model_dir / WEIGHTS_FILE).rmdir()
    with pytest.raises(InputError, match="has no model.safetensors"):
        load_network(model_dir)
    with pytest.raises(InputError, match="not found"):
        load_network(tmp_path / "nowhere")
    (model_dir / METADATA_FILE).write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_network(model_dir)
    (model_dir / METADATA_FILE).unlink()
    with pytest.raises(InputError, match=f"has no {METADATA_FILE}"):
        load_network(model_dir)
    (model_dir / METADATA_FILE).mkdir()  # was: "has no metadata.json"
    with pytest.raises(InputError, match=f"{model_dir / METADATA_FILE} is not a regular file"):
        load_network(model_dir)


#: (field of metadata.json, bad value; ``None``: the field removed) as a fuzzer wrote them.
BAD_METADATA = [
    ("geometry.native_height", 0),  # was: ZeroDivisionError while composing the refusal
    ("geometry.native_width", 10**6),
    ("geometry.native_width", None),
    ("geometry.input_height", 223),  # was: ONNX Runtime INVALID_ARGUMENT / torch size mismatch
    ("geometry.input_width", 100),
    ("geometry.input_height", 10**9),  # was: an allocation failure
    ("geometry.input_width", "64"),
    ("geometry.input_width", 64.5),
    ("geometry", [48, 64, 64, 64]),
    ("width", 1e9),
    ("width", "wide"),
    ("width", True),
    ("arch", "vgg"),
    ("arch", None),
    ("min_depth", 0.0),
    ("min_depth", float("nan")),
    ("max_depth", 0.03),  # below min_depth
    ("max_depth", float("inf")),
    ("normalization.mean", 1e308),  # was: exit 0, overflow warnings and all-NaN depth
    ("normalization.mean", float("nan")),
    ("normalization.std", 0.0),
    ("normalization.std", -1.5),
    ("normalization.std", float("inf")),
    ("normalization.std", None),
    ("normalization.kind", "zscore"),
    ("normalization", None),
    ("training", "none"),
    ("format", "onnx"),  # was: a message without the model directory or the field
    ("format", None),
    ("format_version", 2),
    ("format_version", None),
]


def _edit_metadata(model_dir, field, value):
    """Set ``field`` (dotted, e.g. ``"geometry.input_height"``) of ``model_dir``'s metadata.json to
    ``value``, or remove it when ``value`` is None."""
    meta = json.loads((model_dir / METADATA_FILE).read_text())
    *path, key = field.split(".")
    holder = meta
    for part in path:
        holder = holder[part]
    if value is None:
        del holder[key]
    else:
        holder[key] = value
    (model_dir / METADATA_FILE).write_text(json.dumps(meta))


@pytest.mark.parametrize("field,value", BAD_METADATA, ids=[f"{f}={v!r}" for f, v in BAD_METADATA])
def test_bad_metadata_values_are_refused_naming_the_field(model_dir, field, value):
    _edit_metadata(model_dir, field, value)
    with pytest.raises(InputError) as refused:
        load_metadata(model_dir)
    message = str(refused.value)
    assert message.startswith(f"model {model_dir}: metadata.json ") and f"'{field}'" in message, message
    assert "\n" not in message


def test_bad_metadata_is_one_line_and_exit_2_on_the_command_line(model_dir, synthetic_session, capsys):
    _edit_metadata(model_dir, "geometry.native_height", 0)
    assert main(["evaluate", "--model", str(model_dir), "--data", str(synthetic_session)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"bubble: error: model {model_dir}: metadata.json field "
                                                   "'geometry.native_height' = 0 must be "), err


def _denied(monkeypatch, method: str, refuse) -> None:
    """``Path.<method>`` (``open``, ``stat``) raises the system's PermissionError for every path
    ``refuse(path)`` picks, as for a file of mode 000 or one in a folder that cannot be entered."""
    from pathlib import Path

    original = getattr(Path, method)

    def denied(self, *args, **kwargs):
        if refuse(self):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, method, denied)


@pytest.mark.parametrize("method, refused", [
    ("open", WEIGHTS_FILE),  # was: a PermissionError traceback from the pickle check
    ("open", METADATA_FILE),  # was: "metadata.json is not valid JSON: [Errno 13] Permission denied"
    ("stat", METADATA_FILE),  # the model folder cannot be entered; was: a traceback from path.exists()
])
def test_a_model_file_that_cannot_be_read_is_one_line_naming_it(model_dir, synthetic_session, capsys, monkeypatch,
                                                                 method, refused):
    if method == "stat":
        _denied(monkeypatch, "stat", lambda path: path.parent == model_dir)
    else:
        _denied(monkeypatch, "open", lambda path: path == model_dir / refused)
    assert main(["evaluate", "--model", str(model_dir), "--data", str(synthetic_session)]) == 2
    err = capsys.readouterr().err
    assert err == f"bubble: error: cannot read {model_dir / refused}: Permission denied\n", err
