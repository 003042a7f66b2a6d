"""Training, resume, inference and the train/evaluate command line on small synthetic sessions."""

import fcntl
import json
import os
import re
import shutil
import signal
import threading
import time

import h5py
import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

import calibrate.cli
from collect.errors import InputError
from conftest import make_synthetic_session
from safetensors import SafetensorError

from trainer.checkpoint import has_checkpoint
from trainer.distributed import DistContext
from trainer.inference import DepthEstimator
from trainer.metrics import METRIC_KEYS
from trainer.model_dir import METADATA_FILE, WEIGHTS_FILE, load_metadata, load_weights
from trainer.training import TrainConfig, seconds_left, train_model

SMALL = {"height": 48, "width": 64, "poses_per_object": 3}


def _config(data, out, **overrides):
    options = dict(data=[str(p) for p in data], out=str(out), arch="resnet", width=0.125, epochs=3,
                   batch_size=4, lr=2e-3, input_size=(64, 64), eval_interval_s=0.0, eval_frames=8, threads=1)
    options.update(overrides)
    return TrainConfig(**options)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return make_synthetic_session(tmp_path_factory.mktemp("data") / "s.h5", **SMALL)


@pytest.fixture(scope="module")
def trained(session, tmp_path_factory):
    events = []
    result = train_model(_config([session], tmp_path_factory.mktemp("m") / "model"), progress_callback=events.append)
    return result, events


@pytest.fixture
def bubble(monkeypatch):
    """``bubble`` with only the trainer's commands registered (isolated from other packages)."""
    monkeypatch.setattr(calibrate.cli, "COMMAND_MODULES", ("trainer.cli",))

    def run(*argv) -> int:
        try:
            return calibrate.cli.main([str(a) for a in argv])
        except SystemExit as usage_error:  # argparse's, one line on stderr
            return usage_error.code

    return run


def test_training_writes_model_dir_and_learns(trained, session):
    result, events = trained
    assert set(METRIC_KEYS) <= set(result.metrics) and result.metrics["n_images"] > 0
    assert result.steps == events[-1].step and events[-1].event == "done"
    assert events[-1].fraction == pytest.approx(1.0) and not result.stopped
    steps = [e.step for e in events if e.event == "step"]
    assert steps == sorted(steps) and steps[0] == 1
    assert result.history[0]["step"] == 0  # the curve starts with the untrained network
    assert result.history[-1]["abs_rel"] < 0.8 * result.history[0]["abs_rel"]  # it learns
    meta = load_metadata(result.model_dir)
    assert meta.training["sources"][0]["sha256"] and meta.training["sensor_serials"] == ["SYN-0001"]
    assert meta.training["split"]["kind"] == "in-class-poses"
    device = f"cuda:0 ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available() else "cpu"
    assert meta.training["device"] == device and meta.training["torch"] == torch.__version__
    assert meta.metrics["a1"] == result.metrics["a1"] and meta.inference["onnx_matches_torch"]
    assert meta.geometry.to_dict()["offset_top_left"] == [8, 0]
    assert not has_checkpoint(result.model_dir)


def test_estimator_predicts_native_depth(trained, session):
    from collect.session_reader import Session

    with Session.open(session) as s:
        ir = s.ir(10)
    estimator = DepthEstimator.load(trained[0].model_dir)
    depth = estimator.predict(ir)
    assert depth.shape == (48, 64) and depth.dtype == np.float32
    assert np.all((depth > 0.04) & (depth < 0.12))
    assert np.allclose(estimator.predict_batch(np.stack([ir, ir]))[1], depth)


def _interrupted_after_3_steps(session, out):
    """A 2-epoch training into ``out`` interrupted (KeyboardInterrupt) at its validation after step 3."""
    def interrupt(progress):
        if progress.step == 3 and progress.event == "eval":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_model(_config([session], out, epochs=2, export_onnx=False), progress_callback=interrupt)
    assert has_checkpoint(out) and not (out / WEIGHTS_FILE).exists()


def test_interrupted_run_resumes_from_checkpoint(session, tmp_path):
    out = tmp_path / "model"
    _interrupted_after_3_steps(session, out)
    events = []
    result = train_model(_config([session], out, epochs=2, export_onnx=False, resume=True), progress_callback=events.append)
    full = train_model(_config([session], tmp_path / "full", epochs=2, export_onnx=False))
    assert [e.step for e in events if e.event == "step"][0] == 4
    assert result.steps == full.steps
    resumed, straight = load_weights(out), load_weights(tmp_path / "full")  # augmentation on: was 0.06 apart
    assert all(torch.equal(resumed[name], straight[name]) for name in straight)


def test_a_checkpoint_of_two_saves_or_of_other_content_is_refused(session, tmp_path):
    """Was: a kill between the two files' writes resumed weights of step k with the progress of step
    k-1 (one step over the budget); a checkpoint.json of other content gave a KeyError traceback, one
    with a value of another type (an edited ``"step": null``) a traceback after the weights had loaded."""
    out = tmp_path / "model"
    _interrupted_after_3_steps(session, out)
    state_path = out / "checkpoint.json"
    state = json.loads(state_path.read_text())
    for content, message in (({**state, "checkpoint_id": "0" * 32}, "is torn: checkpoint.safetensors and "
                                                                      "checkpoint.json come from two saves"),
                             ({}, "does not hold the optimizer's settings and the training's progress"),
                             ({**state, "progress": {**state["progress"], "step": None}},
                              "does not hold the optimizer's settings"),
                             ({**state, "progress": {**state["progress"], "history": [1]}},
                              "does not hold the optimizer's settings"),
                             ([1], "does not hold the optimizer's settings")):
        state_path.write_text(json.dumps(content))
        with pytest.raises(InputError, match=message):
            train_model(_config([session], out, epochs=2, export_onnx=False, resume=True))
    state_path.write_text(json.dumps(state))  # an edited tensor name (was: a ValueError traceback)
    weights_path = out / "checkpoint.safetensors"
    with safe_open(str(weights_path), "pt") as f:
        metadata = f.metadata()
    tensors = load_file(str(weights_path))
    tensors["optim.x.exp_avg"] = next(t for k, t in tensors.items() if k.startswith("optim.")).clone()
    save_file(tensors, str(weights_path), metadata)
    with pytest.raises(InputError, match="its optimizer state does not match the network"):
        train_model(_config([session], out, epochs=2, export_onnx=False, resume=True))


def test_a_stop_during_a_validation_ends_the_training_at_that_step(session, tmp_path):
    """Was: one more step after the validation the stop came in."""
    stop = threading.Event()

    def stop_in_the_validation_after_step_3(progress):
        if progress.step == 3 and progress.event == "eval":
            stop.set()

    result = train_model(_config([session], tmp_path / "m", export_onnx=False, write_on_stop=False),
                         stop_in_the_validation_after_step_3, stop)
    assert result.stopped and result.steps == 3


def test_the_deadline_binds_before_the_first_step_and_in_a_resumed_run(session, tmp_path):
    """Was: a deadline already spent still let one step run; a resumed run ignored its deadline until
    its first periodic validation (here: none), and trained its whole budget."""
    fresh = train_model(_config([session], tmp_path / "fresh", deadline_s=1e-3, export_onnx=False))
    assert fresh.steps == 0 and fresh.ended_at_deadline
    out = tmp_path / "model"
    _interrupted_after_3_steps(session, out)
    resumed = train_model(_config([session], out, epochs=2, export_onnx=False, resume=True, deadline_s=1e-3,
                                  eval_interval_s=1e9))
    assert resumed.steps == 3 and resumed.ended_at_deadline


@pytest.mark.parametrize("change, named", [(dict(seed=1), "--seed"), (dict(holdout_object="box"), "split (--split"),
                                           (dict(frame_stride=2), "--frame-stride"), (dict(lr=1e-4), "--lr"),
                                           (dict(contact_weight=0.0), "--contact-weight"),
                                           (dict(augment=False), "--no-augment"), (dict(width=0.25), "--width"),
                                           (dict(epochs=3), "budget (--epochs, --minutes)"),
                                           (dict(epochs=None, minutes=0.05), "budget (--epochs, --minutes)"),
                                           (dict(epochs=None), "budget (--epochs, --minutes)")])
def test_a_checkpoint_resumes_only_with_the_frames_it_trained_on(session, tmp_path, change, named):
    """Was: ``--resume --seed 1`` after a seed-0 start validated on poses the first part had trained on,
    and wrote held-out metrics for them; a resume with another recipe (learning rate, loss,
    augmentation) was taken, the model's metadata recording the resumed run's alone; another width
    failed with torch's list of keys; and another budget (or none: the default 3 minutes) ended the
    run at once or changed its learning-rate schedule."""
    out = tmp_path / "model"
    _interrupted_after_3_steps(session, out)
    with pytest.raises(InputError, match=f"the checkpoint in {out} was trained with other settings \\(.*{re.escape(named)}"):
        train_model(_config([session], out, **{"epochs": 2, "export_onnx": False, "resume": True, **change}))
    assert has_checkpoint(out) and not (out / WEIGHTS_FILE).exists()


def test_stop_event_ends_training_early(session, tmp_path):
    stop = threading.Event()

    def on_progress(progress):
        if progress.step == 2:
            stop.set()

    result = train_model(_config([session], tmp_path / "m", export_onnx=False), on_progress, stop)
    assert result.stopped and result.steps == 2 and (tmp_path / "m" / WEIGHTS_FILE).is_file()


def test_a_stop_without_write_on_stop_returns_at_once(session, tmp_path):
    """A caller that throws a stopped model away (commissioning) gets control back after the step in
    progress: no final validation (no "done" report), no model written."""
    stop = threading.Event()
    events = []

    def on_progress(progress):
        events.append(progress.event)
        if progress.step == 2:
            stop.set()

    result = train_model(_config([session], tmp_path / "m", write_on_stop=False), on_progress, stop)
    assert result.stopped and result.steps == 2 and result.metrics == {}
    assert "done" not in events and not (tmp_path / "m" / WEIGHTS_FILE).exists()


def test_a_stop_before_the_first_step_writes_no_model_even_past_the_deadline(session, tmp_path):
    """Commissioning stopped while its fine-tune loaded the data: the deadline had passed by the first
    step. Was: that one step, then a validated model written and the fine-tune counted as done."""
    stop = threading.Event()
    stop.set()
    result = train_model(_config([session], tmp_path / "m", deadline_s=1e-3, write_on_stop=False), None, stop)
    assert result.stopped and result.steps == 0 and not result.ended_at_deadline
    assert not (tmp_path / "m" / WEIGHTS_FILE).exists()


def test_deadline_bounds_the_whole_call_and_drives_the_schedule(session, tmp_path):
    events = []
    start = time.perf_counter()
    result = train_model(_config([session], tmp_path / "m", epochs=10_000, deadline_s=6.0), events.append)
    wall = time.perf_counter() - start
    assert result.ended_at_deadline and not result.stopped and result.epochs < 10_000
    # the epoch budget alone would take hours; 10x the 6 s deadline leaves room for a loaded machine
    assert wall < 10 * 6.0
    # progress (and ETA) follow the deadline: the run ends complete (its last step may report a hair
    # under 1, the deadline falling between its report and the check after it)
    done = [e for e in events if e.event == "done"]
    assert len(done) == 1 and done[0].fraction == 1.0 and done[0].eta_s == 0.0
    steps = [e for e in events if e.event == "step"]
    assert steps[-1].lr == pytest.approx(2e-3 * 0.25)  # both halvings happened within it
    meta = load_metadata(result.model_dir)
    assert meta.training["ended_at_deadline"] and meta.training["deadline_s"] == 6.0
    assert meta.inference["runtime"] in ("onnx", "torch")  # the export still ran


def test_the_time_left_is_the_budget_or_the_deadline_whichever_ends_training_first():
    """Was: the larger share done, as seconds at the budget's rate: 84 s of a 150 s budget with the
    deadline 20 s away read 66 s left, then 2 s once the deadline's share took over."""
    assert seconds_left(84.0, 84.0 / 150.0, 20.0) == pytest.approx(20.0)  # the deadline ends it first
    assert seconds_left(84.0, 84.0 / 150.0, 120.0) == pytest.approx(66.0)  # the budget does
    assert seconds_left(84.0, 84.0 / 150.0, None) == pytest.approx(66.0)  # no deadline
    assert seconds_left(0.0, 0.0, None) is None and seconds_left(0.0, 0.0, 30.0) == 30.0  # before a step
    assert seconds_left(84.0, 84.0 / 150.0, -3.0) == 0.0  # past it


def test_generous_deadline_leaves_the_budget_alone(session, tmp_path):
    result = train_model(_config([session], tmp_path / "m", epochs=1, deadline_s=600.0, export_onnx=False))
    assert not result.ended_at_deadline and result.epochs == pytest.approx(1.0)
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(InputError, match="deadline"):
            train_model(_config([session], tmp_path / "bad", deadline_s=bad))


def test_the_metadata_names_the_sessions_trained_on_not_those_that_only_validated(session, tmp_path):
    """A session of the held-out object alone validates only: it is under ``val_sources`` and its sensor
    is not among those trained on (was: listed as trained on, with every frame counted, so that
    ``bubble evaluate`` on that sensor's data said nothing of a model that never saw it)."""
    from conftest import make_synthetic_session

    box_only = make_synthetic_session(tmp_path / "box.h5", objects=("box",), sensor_serial="SYN-0002", **SMALL)
    result = train_model(_config([session, box_only], tmp_path / "model", holdout_object="box", epochs=1))
    training = load_metadata(result.model_dir).training
    assert [s["sensor_serial"] for s in training["sources"]] == ["SYN-0001"]
    assert training["sources"][0]["n_frames"] == training["n_train_frames"]
    assert [s["sensor_serial"] for s in training["val_sources"]] == ["SYN-0002"]
    assert training["sensor_serials"] == ["SYN-0001"]


def test_a_session_given_twice_is_refused(session, tmp_path):
    """Twice in the training data its frames would weigh double; in the validation data as well, the
    model would be validated on frames it trained on. A link to the file is the same session."""
    link = tmp_path / "link.h5"
    link.symlink_to(session)
    with pytest.raises(InputError, match="given twice in --data"):
        train_model(_config([session, link], tmp_path / "m", epochs=1))
    with pytest.raises(InputError, match="in both --data and --val-data"):
        train_model(_config([session], tmp_path / "m", epochs=1, val_data=[str(link)]))
    assert not (tmp_path / "m").exists()


def test_deadline_refused_under_torchrun(session, tmp_path, monkeypatch):
    monkeypatch.setattr(DistContext, "from_env", classmethod(lambda cls: DistContext(rank=0, world_size=2)))
    with pytest.raises(InputError, match="torchrun"):
        train_model(_config([session], tmp_path / "m", deadline_s=60.0))


def test_fine_tune_from_init_model_keeps_its_architecture(trained, session, tmp_path):
    result = train_model(_config([session], tmp_path / "ft", arch=None, width=None, epochs=0.5, export_onnx=False,
                                 init=str(trained[0].model_dir)))
    meta = load_metadata(result.model_dir)
    assert (meta.arch, meta.width) == ("resnet", 0.125)
    assert meta.training["init"]["model_dir"] == str(trained[0].model_dir)


def test_evaluate_command_writes_metrics_latency_and_truth_comparison(bubble, trained, session, tmp_path, capsys):
    out = tmp_path / "eval.json"
    for _ in range(2):  # the second run replaces the first one's result
        assert bubble("evaluate", "--model", trained[0].model_dir, "--data", session, "--objects", "mug", "--json",
                      out) == 0
    data = json.loads(out.read_text())
    assert data["written_by"] == "bubble evaluate"
    assert set(METRIC_KEYS) <= set(data) and data["latency_ms"] > 0
    assert list(data["per_object"]) == ["mug"]
    vs = data["vs_true"]
    assert vs["tof"]["a1"] > 0.99 and 0 < vs["tof_coverage"] < 1
    assert vs["model_on_tof_dropout"]["n_pixels"] > 0
    out = capsys.readouterr().out
    assert "Abs.Rel" in out and "RMSE [mm]" in out  # was: "RMSE", its unit taken for a rich markup tag


def test_the_metrics_table_shows_rmse_in_mm_and_names_as_text():
    """Was: "RMSE [m]" to 4 decimals (0.14 and 0.24 mm both 0.0001-0.0002), and a row named after a mesh
    ``bracket[v2].stl`` showed as "bracket" (its name read as rich markup)."""
    from rich.console import Console

    from trainer.cli import metrics_table

    metrics = {"abs_rel": 0.0021, "rmse": 0.00014, "rmse_log": 0.003, "silog": 0.2, "a1": 1.0, "n_images": 3}
    console = Console(record=True, width=120)
    console.print(metrics_table("t", {"bracket[v2]": metrics, "cup[bold]": {**metrics, "rmse": 0.00024}}))
    text = console.export_text()
    assert "RMSE [mm]" in text and "bracket[v2]" in text and "cup[bold]" in text
    assert "0.140" in text and "0.240" in text


def test_train_refuses_a_json_result_inside_its_model_directory(bubble, session, tmp_path, capsys):
    """Was: ``--json MODEL/metadata.json`` passed the check on an existing --out, and the result was written
    over the model's metadata (the model no longer loaded)."""
    out = tmp_path / "m"
    out.mkdir()
    assert bubble("train", "--data", session, "--out", out, "--epochs", "0.1", "--json", out / "metadata.json") == 2
    assert capsys.readouterr().err == (f"bubble: error: --json {out / 'metadata.json'} is inside the model directory "
                                       f"{out}, whose files training writes; write the result elsewhere\n")
    assert list(out.iterdir()) == []


def test_an_object_without_tof_depth_is_a_row_of_dashes(bubble, trained, session, tmp_path, capsys):
    """Was: a row of nan in the table (DESIGN: never a table of NaN)."""
    no_box_depth = tmp_path / "s.h5"
    shutil.copy(session, no_box_depth)
    with h5py.File(no_box_depth, "r+") as f:
        names = [n.decode() if isinstance(n, bytes) else n for n in f["objects/name"][:]]
        box = f["frames/object"][:] == names.index("box")
        depth = f["frames/depth"][:]
        depth[box] = 0
        f["frames/depth"][...] = depth
    assert bubble("evaluate", "--model", trained[0].model_dir, "--data", no_box_depth) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if " box " in line)
    assert "nan" not in row and row.count(" - ") >= 5, row


def test_train_command_small_run(bubble, session, tmp_path):
    out = tmp_path / "cli_model"
    code = bubble("train", "--data", session, "--out", out, "--width", "0.125", "--epochs", "0.3",
                  "--holdout-object", "box", "--no-onnx", "--threads", "1", "--json", tmp_path / "m.json")
    assert code == 0
    assert load_metadata(out).training["split"] == {"kind": "holdout-object", "object": "box"}
    assert json.loads((tmp_path / "m.json").read_text())["split"] == "holdout-object"


def test_a_model_directory_another_training_writes_is_refused(bubble, session, tmp_path, capsys):
    """Two ``bubble train`` with one --out: while one holds the directory, the other is refused with
    one line and writes nothing (was: both trained and both said "model written to", the last to
    finish replacing the other's files, or mixing with them: one's weights, the other's metadata)."""
    out = tmp_path / "m"
    out.mkdir()
    other_training = os.open(out, os.O_RDONLY)
    try:
        fcntl.flock(other_training, fcntl.LOCK_EX)  # what the other training holds while it runs
        code = bubble("train", "--data", session, "--out", out, "--width", "0.125", "--epochs", "0.1", "--no-onnx",
                      "--threads", "1")
    finally:
        os.close(other_training)
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and err == [f"bubble: error: {out} is being written by another bubble train; wait until it has "
                                 "finished, or choose another --out"], err
    assert list(out.iterdir()) == []


def test_a_full_disk_when_the_model_is_written_is_one_line(bubble, session, tmp_path, capsys, monkeypatch):
    """safetensors' own error for a full disk (as measured on a 1 MB tmpfs) is said as one line
    naming the file, exit 2; no weights are left (safetensors renames a finished temporary file)."""
    import trainer.model_dir

    def full_disk(tensors, filename, metadata=None):
        raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")

    monkeypatch.setattr(trainer.model_dir, "save_file", full_disk)
    out = tmp_path / "m"
    code = bubble("train", "--data", session, "--out", out, "--width", "0.125", "--epochs", "0.1", "--no-onnx",
                  "--threads", "1")
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and err[-1] == (f"bubble: error: cannot write {out / WEIGHTS_FILE}: No space left on "
                                     "device; free some space or write elsewhere"), err
    assert not (out / WEIGHTS_FILE).exists()


def test_bad_inputs_exit_2(bubble, trained, session, tmp_path, capsys):
    model = trained[0].model_dir
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"not an hdf5 file" * 100)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(session.read_bytes()[: session.stat().st_size // 3])
    other_size = make_synthetic_session(tmp_path / "other.h5", height=40, width=56, poses_per_object=1)
    with_nan = tmp_path / "nan.h5"
    shutil.copy(session, with_nan)
    with h5py.File(with_nan, "r+") as f:
        f["sim/true_depth"][12, 5, 5] = np.nan
    no_depth = tmp_path / "no_depth.h5"  # every ToF pixel invalid: was exit 0 with a table of NaN
    shutil.copy(session, no_depth)
    with h5py.File(no_depth, "r+") as f:
        f["frames/depth"][...] = 0
    pickled = tmp_path / "pickled"
    shutil.copytree(model, pickled)
    torch.save({"w": torch.zeros(2)}, pickled / WEIGHTS_FILE)
    cases = [
        ("evaluate", "--model", model, "--data", tmp_path / "missing.h5"),
        ("evaluate", "--model", model, "--data", garbage),
        ("evaluate", "--model", model, "--data", truncated),
        ("evaluate", "--model", model, "--data", other_size),
        ("evaluate", "--model", model, "--data", with_nan),
        ("evaluate", "--model", model, "--data", no_depth),
        ("evaluate", "--model", model, "--data", session, "--objects", "teapot"),
        ("evaluate", "--model", model, "--data", session, session),  # its frames would count twice
        ("evaluate", "--model", pickled, "--data", session),
        ("evaluate", "--model", tmp_path / "no_model", "--data", session),
        ("train", "--data", tmp_path / "missing.h5", "--out", tmp_path / "x", "--epochs", "1"),
        ("train", "--data", session, "--out", tmp_path / "x", "--holdout-object", "teapot", "--epochs", "1"),
        ("train", "--data", session, other_size, "--out", tmp_path / "x", "--epochs", "1"),
        ("train", "--data", session, "--out", model, "--epochs", "1"),  # holds a model: --resume or another --out
        ("train", "--data", session, "--out", tmp_path / "y", "--epochs", "1", "--json", session),
        ("evaluate", "--model", model, "--data", session, "--json", session),  # a recording is no JSON result
        ("evaluate", "--model", model, "--data", session, "--json", model / METADATA_FILE),  # JSON, not a result
        ("evaluate", "--model", model, "--data", session, "--json", ""),
        ("evaluate", "--model", model, "--data", session, "--json", tmp_path / ("e" * 300 + ".json")),
        ("evaluate", "--model", tmp_path / ("m" * 300), "--data", session),
        ("train", "--data", session, "--out", "", "--epochs", "1"),
        ("train", "--data", session, "--out", tmp_path / "x", "--epochs", "1", "--seed=-1"),
        ("train", "--data", session, "--out", tmp_path / "x", "--epochs", "1", "--width", "inf"),
        ("train", "--data", session, "--out", tmp_path / "x", "--epochs", "1", "--width", "1e9"),
        ("train", "--data", session, "--out", tmp_path / ("m" * 300) / "x", "--epochs", "1"),
    ]
    recorded, weights, metadata = (session.read_bytes(), (model / WEIGHTS_FILE).read_bytes(),
                                   (model / METADATA_FILE).read_bytes())
    for argv in cases:
        capsys.readouterr()
        assert bubble(*argv) == 2, argv
        err = capsys.readouterr().err.splitlines()  # not stripped: a blank line before the error counts
        assert len(err) == 1 and err[0].startswith("bubble: error:"), (argv, err)
    assert session.read_bytes() == recorded and (model / WEIGHTS_FILE).read_bytes() == weights
    assert (model / METADATA_FILE).read_bytes() == metadata


def test_a_pose_split_that_would_validate_on_free_frames_alone_is_refused(session, tmp_path):
    """Every object pressed in one pose: the pose split held out free frames alone, and the model
    reported their metrics (a1 ~1 on an undented membrane) as the held-out poses'."""
    one_pose = make_synthetic_session(tmp_path / "one_pose.h5",  # free frames enough for the split to validate on
                                      **{**SMALL, "poses_per_object": 1, "frames_per_phase": 8, "n_reference": 8})
    with pytest.raises(InputError, match=r"^the in-class-poses split holds out no contact frame: every object of "
                                         r"each session was pressed in one pose only; record 2 or more poses"):
        train_model(_config([one_pose], tmp_path / "m"))
    assert not (tmp_path / "m").exists()
    both = _config([one_pose, session], tmp_path / "m", epochs=0.1, export_onnx=False)  # session: 3 poses each
    assert train_model(both).metrics["n_images"] > 0


def test_train_and_evaluate_options_that_crashed_or_were_ignored(bubble, trained, session, tmp_path, capsys):
    """Each now one line and exit 2, nothing written; before: a traceback in torch (seed, threads), a
    model trained at a learning rate of 1e12, a finished model trained again from scratch over itself
    (--resume without a checkpoint), a training from scratch (--init ''), one validation choice
    silently ignored, or a copy of the training session validated on (or evaluated twice)."""
    model = trained[0].model_dir
    copy = tmp_path / "copy.h5"
    shutil.copy(session, copy)
    train = ("train", "--data", session, "--epochs", "0.1", "--no-onnx", "--width", "0.125")
    cases = [
        (train + ("--out", tmp_path / "a", "--seed", "99999999999999999999999"), "seed must be 0..4294967295, got 9999"),
        (train + ("--out", tmp_path / "a", "--threads", "100000"), "threads must be 1.."),
        (train + ("--out", tmp_path / "a", "--lr", "1e12"), "learning rate must be a number in (0, 1], got 1000000000000.0"),
        # were: a training that diverged and blamed --lr, and one with an ETA of 1.6 million hours
        (train + ("--out", tmp_path / "a", "--contact-weight", "1e308"), "contact weight must be a number in [0, 1000], got 1e+308"),
        (("train", "--data", session, "--epochs", "1e9", "--out", tmp_path / "a"), "epochs must be a number in (0, 10000], got 1000000000.0"),
        (("train", "--data", session, "--minutes", "1e6", "--out", tmp_path / "a"), "minutes must be a number in (0, 10080] (a week), got 1000000.0"),
        (train + ("--out", model, "--resume"), f"cannot resume {model}: its training finished (a model, no checkpoint)"),
        (train + ("--out", tmp_path / "a", "--resume"), "it holds no checkpoint of an interrupted training"),
        (train + ("--out", tmp_path / "a", "--init", ""), "--init is empty: name a model directory"),
        (train + ("--out", tmp_path / "a", "--val-data", copy, "--holdout-object", "box"),
         "--val-data and --holdout-object each choose the validation frames; give one of them"),
        (train + ("--out", tmp_path / "a", "--split", "frames", "--holdout-object", "box"),
         "--holdout-object and --split each choose the validation frames"),
        (train + ("--out", tmp_path / "a", "--val-data", copy), f"sessions {session} and {copy} (--data and --val-data) "
                                                                  "are copies of one recording; give it once"),
        (("evaluate", "--model", model, "--data", session, copy), "(--data) are copies of one recording"),
        (train + ("--out", tmp_path / "a", "--frame-stride", "100000"),
         "of the 1 frame that --frame-stride 100000 keeps; record more poses, or lower --frame-stride"),
        (("train", "--data", "", "--out", tmp_path / "a"), "argument --data: is empty: name a file or folder"),
    ]
    weights = (model / WEIGHTS_FILE).read_bytes()
    for argv, message in cases:
        capsys.readouterr()
        assert bubble(*argv) == 2, argv
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("bubble: error:") and message in err[0], (argv, err)
    assert (model / WEIGHTS_FILE).read_bytes() == weights and not (tmp_path / "a").exists()


def test_a_diverged_training_writes_no_model(session, tmp_path, monkeypatch):
    """Was: a model written with NaN weights and NaN validation metrics, exit 0."""
    import trainer.training

    def poisoned_step(optimizer, closure=None):  # what a far too large step leaves in the weights
        for group in optimizer.param_groups:
            for p in group["params"]:
                p.data.fill_(float("nan"))

    with monkeypatch.context() as patch:
        patch.setattr(torch.optim.Adam, "step", poisoned_step)
        with pytest.raises(InputError, match=r"training diverged after 1 step \(its depth on the validation frames "
                                             r"is not finite\) at learning rate 1; lower --lr, the model was not written"):
            train_model(_config([session], tmp_path / "m", lr=1.0, epochs=0.01, export_onnx=False))
    assert not (tmp_path / "m" / WEIGHTS_FILE).exists()
    nan_loss = trainer.training.masked_l1
    monkeypatch.setattr(trainer.training, "masked_l1", lambda *a, **k: nan_loss(*a, **k) * float("nan"))
    with pytest.raises(InputError, match=r"training diverged after 1 step \(the loss is nan\)"):
        train_model(_config([session], tmp_path / "n", export_onnx=False))
    assert not (tmp_path / "n" / WEIGHTS_FILE).exists()
    calls = []

    def nan_from_the_third_step(*a, **k):
        calls.append(1)
        return nan_loss(*a, **k) * (float("nan") if len(calls) >= 3 else 1.0)

    monkeypatch.setattr(trainer.training, "masked_l1", nan_from_the_third_step)
    with pytest.raises(InputError, match=r"training diverged after 3 steps \(the loss is nan\)"):
        train_model(_config([session], tmp_path / "o", export_onnx=False))  # checkpoints after steps 1 and 2
    assert not has_checkpoint(tmp_path / "o")  # was: left, and a rerun with a lower --lr refused for it
    monkeypatch.setattr(trainer.training, "masked_l1", nan_loss)
    assert train_model(_config([session], tmp_path / "o", epochs=0.2, export_onnx=False, lr=1e-3)).steps > 0


def test_ctrl_c_during_training_checkpoints_the_step_reached(bubble, session, tmp_path, monkeypatch, capsys,
                                                              interrupt_handlers_restored):
    """Ctrl-C in ``bubble train`` ends the step in progress, checkpoints it and exits 130; ``--resume``
    goes on from that step. Was: the process ended where the signal found it, and before the first
    periodic checkpoint (every 20 s) nothing was left to resume."""
    from rich.progress import Progress

    update = Progress.update
    steps_shown = []

    def update_then_ctrl_c(self, task, **fields):  # the operator presses Ctrl-C as the bar shows step 2
        update(self, task, **fields)
        steps_shown.append(fields.get("completed"))
        if len(steps_shown) == 3:  # the untrained model's validation, step 1, step 2
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(Progress, "update", update_then_ctrl_c)
    out = tmp_path / "m"
    train = ("train", "--data", session, "--out", out, "--width", "0.125", "--epochs", "1", "--batch-size", "4",
             "--no-onnx", "--threads", "1")
    assert bubble(*train) == 130
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == (f"bubble: interrupted: its checkpoint at step 2 (0.0 min of training) is in {out}: continue "
                       "with the same command and --resume"), err
    assert has_checkpoint(out) and not (out / WEIGHTS_FILE).exists()
    assert json.loads((out / "checkpoint.json").read_text())["progress"]["step"] == 2
    monkeypatch.setattr(Progress, "update", update)
    checkpoint = (out / "checkpoint.json").read_text()
    assert bubble(*train) == 2  # the same command without --resume: refused (was: trained anew over the checkpoint)
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"bubble: error: {out} holds the checkpoint of an interrupted training; add --resume to continue it, or "
        "choose another --out")
    assert (out / "checkpoint.json").read_text() == checkpoint
    assert bubble(*train, "--resume") == 0
    assert load_metadata(out).training["steps"] > 2 and not has_checkpoint(out)


@pytest.mark.parametrize("name", ["model.safetensors", "metadata.json", "model.onnx", "checkpoint.json",
                                  "checkpoint.safetensors"])
def test_a_new_training_refuses_a_folder_holding_a_file_it_writes(bubble, session, tmp_path, capsys, name):
    """Was: a foreign ``metadata.json`` or ``model.onnx`` in ``--out`` overwritten and a lone
    ``checkpoint.json`` deleted, exit 0 (only ``model.safetensors`` was refused)."""
    out = tmp_path / "m"
    out.mkdir()
    (out / name).write_text("someone else's file")
    assert bubble("train", "--data", session, "--out", out, "--width", "0.125", "--epochs", "0.2", "--no-onnx",
                  "--threads", "1") == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"bubble: error: {out} already holds "), err
    assert [p.name for p in out.iterdir()] == [name] and (out / name).read_text() == "someone else's file"


def test_ctrl_c_while_the_model_is_written_is_reported(bubble, session, tmp_path, monkeypatch, capsys,
                                                       interrupt_handlers_restored):
    """Was: swallowed, "model written to", exit 0: the stop came after the last step, where nothing
    looked at it. The model is whole; the command says so, writes its --json result (was: not) and
    exits 130."""
    import trainer.training

    save_model = trainer.training.save_model

    def ctrl_c_then_save(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return save_model(*args, **kwargs)

    monkeypatch.setattr(trainer.training, "save_model", ctrl_c_then_save)
    out = tmp_path / "m"
    result = tmp_path / "train.json"
    assert bubble("train", "--data", session, "--out", out, "--width", "0.125", "--epochs", "0.2", "--no-onnx",
                  "--threads", "1", "--json", result) == 130
    assert capsys.readouterr().err.splitlines()[-1] == (f"bubble: interrupted after the training's last step: the "
                                                        f"model in {out} is complete")
    assert load_metadata(out).training["steps"] > 0
    assert json.loads(result.read_text())["a1"] == load_metadata(out).metrics["a1"]


def test_the_progress_bars_a1_of_a_validation_without_a_number():
    """A resumed run's checkpoint keeps a NaN a1 as None: was a TypeError traceback at its first step."""
    from trainer.cli import a1_text

    assert [a1_text(v) for v in (None, {}, {"a1": None}, {"a1": float("nan")}, {"a1": 0.97123})] == [
        "-", "-", "-", "-", "0.971"]
