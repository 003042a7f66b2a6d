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
from trainer.model_dir import (BASE_MODEL_DIR, METADATA_FILE, WEIGHTS_FILE, ModelMetadata, load_metadata, load_network,
                               save_model)
from trainer.networks import build_network
from trainer.onnx_export import export_and_select_runtime, export_onnx
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

    from trainer.dataset import file_sha256

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
        meta = json.loads((model_dir / METADATA_FILE).read_text())
        meta["inference"]["weights_sha256"] = file_sha256(path)  # as save_model records them
        (model_dir / METADATA_FILE).write_text(json.dumps(meta))
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
    run_dir = tmp_path / "run"  # a commissioning run folder given for its model/ folder: named
    (run_dir / "model").mkdir(parents=True)
    (run_dir / "model" / METADATA_FILE).write_text("{}")
    with pytest.raises(InputError, match=rf"model directory {run_dir} has no {METADATA_FILE} \(a commissioning run\? "
                                         rf"its model is {run_dir / 'model'}\)$"):
        load_metadata(run_dir)


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


@pytest.fixture
def small_session(make_synthetic_session, tmp_path):
    """A session of the ``model_dir`` model's 64 x 48 frames."""
    return make_synthetic_session(tmp_path / "small.h5", height=48, width=64)


def _evaluate_error(model_dir, session, capsys) -> str:
    """The one line ``bubble evaluate --model model_dir --data session`` prints, after checking it exits 2."""
    assert main(["evaluate", "--model", str(model_dir), "--data", str(session)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("bubble: error: "), err
    return err.removeprefix("bubble: error: ").rstrip("\n")


def test_an_onnx_file_that_is_not_the_export_of_the_weights_is_refused(model_dir, small_session, capsys):
    """Was: an ONNX of another network copied into a model folder run silently (exit 0, metrics of that
    network), and weights replaced after the export run through the old export."""
    from trainer.dataset import file_sha256
    from trainer.model_dir import ONNX_FILE, write_safetensors

    info = export_and_select_runtime(model_dir, repeats=2)
    assert info["onnx_sha256"] == file_sha256(model_dir / ONNX_FILE)
    assert info["weights_sha256"] == file_sha256(model_dir / WEIGHTS_FILE)
    assert DepthEstimator.load(model_dir, runtime="onnx").runtime == "onnx"
    meta = json.loads((model_dir / METADATA_FILE).read_text())
    meta["inference"]["runtime"] = "onnx"  # whichever the timing picked (torch on a loaded machine: no ONNX read)
    (model_dir / METADATA_FILE).write_text(json.dumps(meta))
    onnx, weights = (model_dir / ONNX_FILE).read_bytes(), (model_dir / WEIGHTS_FILE).read_bytes()
    torch.manual_seed(1)
    other = build_network("bts", 0.125, 0.04, 0.12)
    export_onnx(other, (64, 64), model_dir / ONNX_FILE)  # same input size, another network
    message = (f"{model_dir / ONNX_FILE} is not the ONNX export that {model_dir} records (another SHA-256): "
               "delete it to run the model in torch, or export it again (trainer.onnx_export.export_and_select_runtime)")
    assert _evaluate_error(model_dir, small_session, capsys) == message
    (model_dir / ONNX_FILE).write_bytes(onnx)
    torch.manual_seed(2)
    retrained = {k: v.contiguous() for k, v in build_network("resnet", 0.125, 0.04, 0.12).state_dict().items()}
    write_safetensors(retrained, model_dir / WEIGHTS_FILE)
    for runtime in (None, "torch"):  # was: torch ran the other weights (depth up to 16 mm off), exit 0
        with pytest.raises(InputError, match=f"^{model_dir / WEIGHTS_FILE} is not the weights file that "
                                             f"{METADATA_FILE} records \\(another SHA-256\\): the folder mixes two models"):
            DepthEstimator.load(model_dir, runtime=runtime)
    (model_dir / WEIGHTS_FILE).write_bytes(weights)
    (model_dir / ONNX_FILE).unlink()  # the way out the message gives
    assert DepthEstimator.load(model_dir).runtime == "torch"


def test_an_onnx_file_of_another_input_size_is_refused_in_a_folder_without_hashes(model_dir, small_session, capsys):
    """Folders exported before the hashes were recorded still load, their ONNX input checked against
    the metadata's input size (was: an ONNX Runtime InvalidArgument traceback, exit 1)."""
    from trainer.model_dir import ONNX_FILE

    export_and_select_runtime(model_dir, repeats=2)
    meta = json.loads((model_dir / METADATA_FILE).read_text())
    for key in ("onnx_sha256", "weights_sha256"):
        meta["inference"].pop(key, None)
    meta["inference"]["runtime"] = "onnx"
    (model_dir / METADATA_FILE).write_text(json.dumps(meta))
    assert main(["evaluate", "--model", str(model_dir), "--data", str(small_session)]) == 0
    assert "(batch 1, onnx)" in capsys.readouterr().out  # the old folder still runs its ONNX export
    net, _ = load_network(model_dir)
    export_onnx(net, (96, 64), model_dir / ONNX_FILE)
    assert _evaluate_error(model_dir, small_session, capsys) == (
        f"{model_dir / ONNX_FILE} takes ir (batch, 1, 96, 64), the model needs ir (batch, 1, 64, 64): "
        "delete it to run the model in torch, or export it again (trainer.onnx_export.export_and_select_runtime)")


def test_the_base_model_runs_its_recorded_onnx_export():
    """The committed base model's metadata.json records the hashes of its model.onnx and weights."""
    assert DepthEstimator.load("base").runtime == "onnx"


def test_the_base_models_metadata_is_strict_json():
    """JSON has no NaN (jq and JavaScript refuse it): was a ``"loss": NaN`` in its history, written
    before ``plain_json``."""
    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    json.loads((BASE_MODEL_DIR / METADATA_FILE).read_text(), parse_constant=refuse)


def test_ir_outside_the_uint16_range_is_refused_naming_the_frame(model_dir):
    """Was: negative float IR turned into an all-NaN depth map without an error (only NaN/inf were refused)."""
    estimator = DepthEstimator.load(model_dir, runtime="torch")
    ir = np.full((3, 48, 64), 1000.0, np.float32)
    assert np.isfinite(estimator.predict_batch(ir)).all()
    for value, held in ((-1.0, "values -1 to 1000"), (np.nan, "NaN or inf"), (np.inf, "NaN or inf"),
                        (70000.0, "values 1000 to 70000")):
        bad = ir.copy()
        bad[2, 5, 5] = value
        with pytest.raises(InputError, match=rf"^IR frame 2 holds {held}: an IR amplitude is 0 to 65535 \(uint16\)$"):
            estimator.predict_batch(bad)
    with pytest.raises(InputError, match=r"^IR frame 0 holds values -5 to -5: "):
        estimator.predict(np.full((48, 64), -5, np.int32))


def test_evaluating_on_a_sensor_the_model_was_not_trained_on_prints_a_note(model_dir, make_synthetic_session,
                                                                            tmp_path, capsys):
    """Was: a model fine-tuned on one sensor evaluated on another's session without a word (on the
    simulated bench its pose e_x there is 3.1 mm against 0.39 on its own sensor)."""
    own = make_synthetic_session(tmp_path / "own.h5", height=48, width=64)
    other = make_synthetic_session(tmp_path / "other.h5", height=48, width=64, sensor_serial="SYN-0002")
    assert main(["evaluate", "--model", str(model_dir), "--data", str(own)]) == 0
    assert capsys.readouterr().err == ""
    out = tmp_path / "eval.json"
    assert main(["evaluate", "--model", str(model_dir), "--data", str(own), str(other), "--json", str(out)]) == 0
    assert capsys.readouterr().err.splitlines() == [
        f"bubble: note: model {model_dir} was not trained on sensor SYN-0002 (its depth there is that of a model "
        "that has not seen the sensor; one fine-tuned on it fits it better)"]
    assert json.loads(out.read_text())["sensors_not_trained_on"] == ["SYN-0002"]


def test_sensors_not_trained_on_reads_the_training_serials():
    meta = _metadata()
    assert meta.sensors_not_trained_on(["SYN-0001"]) == []
    assert meta.sensors_not_trained_on(["SYN-0003", "SYN-0001", "SYN-0002", "SYN-0003"]) == ["SYN-0002", "SYN-0003"]
    meta.training = {}  # a model whose metadata does not list its sensors: nothing to say
    assert meta.sensors_not_trained_on(["SYN-0002"]) == []


def test_an_onnx_export_that_gives_nan_does_not_match(model_dir, monkeypatch):
    """Was: ``max(0.0, nan)`` kept 0.0, and an export whose output was NaN counted as matching torch."""
    import trainer.onnx_export

    real = trainer.onnx_export.onnx_session

    class NaNSession:
        def __init__(self, session):
            self.session = session

        def run(self, names, feeds):
            return [np.full_like(out, np.nan) for out in self.session.run(names, feeds)]

    monkeypatch.setattr(trainer.onnx_export, "onnx_session", lambda *a: NaNSession(real(*a)))
    info = export_and_select_runtime(model_dir, repeats=1)
    assert not info["onnx_matches_torch"] and info["runtime"] == "torch"
    assert json.loads((model_dir / METADATA_FILE).read_text())["inference"]["onnx_max_abs_diff_m"] is None  # NaN
