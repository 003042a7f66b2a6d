"""Model directory: safetensors + metadata round trip, refusal of pickle and mismatched weights."""

import json

import numpy as np
import pytest
import torch

from collect.errors import InputError
from trainer.inference import DepthEstimator
from trainer.model_dir import METADATA_FILE, WEIGHTS_FILE, ModelMetadata, load_network, save_model
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


def test_pickle_weights_are_refused(model_dir):
    state = build_network("resnet", 0.125, 0.04, 0.12).state_dict()
    torch.save(state, model_dir / WEIGHTS_FILE)  # a pickle under the safetensors name
    with pytest.raises(InputError, match="pickle"):
        load_network(model_dir)
    (model_dir / WEIGHTS_FILE).rename(model_dir / "model.pt")
    with pytest.raises(InputError, match="pickle"):
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
    with pytest.raises(InputError, match="has no model.safetensors"):
        load_network(model_dir)
    with pytest.raises(InputError, match="not found"):
        load_network(tmp_path / "nowhere")
    (model_dir / METADATA_FILE).write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_network(model_dir)
