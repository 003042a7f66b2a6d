"""``bubble pose``: JSON and plots written, exit 0; bad input -> one line, exit 2."""

import json

import pytest
import torch

import calibrate.cli as cli
from test_pose_check import H, W, DecodingEstimator, write_cylinder_session
from trainer.metrics import METRIC_KEYS


@pytest.fixture(autouse=True)
def only_pose_command(monkeypatch):
    # the pose command alone (other packages' commands are tested by their owners)
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("calibrate.pose_cli",))


def test_pose_command_writes_json_and_plots(tmp_path, monkeypatch, capsys):
    import trainer.inference

    session = write_cylinder_session(tmp_path / "s.h5", n_poses=2, hold_frames=2)
    monkeypatch.setattr(trainer.inference.DepthEstimator, "load", classmethod(lambda cls, d: DecodingEstimator()))
    out = tmp_path / "pose.json"
    code = cli.main(["pose", "--model", str(tmp_path / "m"), "--data", str(session), "--object", "mug",
                     "--json", str(out), "--plots", str(tmp_path / "plots")])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["written_by"] == "bubble pose" and doc["n_used"] == 4 and doc["object_name"] == "mug"
    for key in ("e_x_mm", "e_theta"):
        assert set(doc[key]) == {"median", "mean", "variance"}
    assert doc["hz"] > 0 and set(doc["vs_true"]) == {"predicted", "measured", "true"}
    # the depth metric keys at top level, as every --json (predicted vs ToF depth over the hold frames)
    assert set(METRIC_KEYS) <= set(doc) and doc["n_images"] == 4 and doc["a1"] > 0.99
    assert (tmp_path / "plots" / "pose_errors.png").is_file()
    assert "predicted vs measured depth: e_x median" in capsys.readouterr().out
    assert cli.main(["pose", "--model", str(tmp_path / "m"), "--data", str(session), "--plots",
                     str(tmp_path / "plots")]) == 0  # its earlier histograms are replaced


def test_plots_over_other_files_are_refused_before_the_run(tmp_path, capsys):
    """Was: any file named pose_errors.png or pose_vs_true.png in --plots replaced, an image of another
    command too; an earlier ``bubble pose`` histogram is marked as one and is replaced."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    session = write_cylinder_session(tmp_path / "s.h5", n_poses=1, hold_frames=2)
    model = _untrained_model(tmp_path / "m")
    plots = tmp_path / "plots"
    plots.mkdir()
    plt.figure().savefig(plots / "pose_vs_true.png")  # someone's image
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "pose_errors.png").write_text("not an image")
    for folder, name in ((plots, "pose_vs_true.png"), (tmp_path / "notes", "pose_errors.png")):
        before = (folder / name).read_bytes()
        assert cli.main(["pose", "--model", str(model), "--data", str(session), "--plots", str(folder)]) == 2
        assert capsys.readouterr().err.splitlines() == [
            f"bubble: error: {folder / name} exists and is not an earlier `bubble pose` image; refusing to overwrite it"]
        assert (folder / name).read_bytes() == before
    assert sorted(p.name for p in plots.iterdir()) == ["pose_vs_true.png"]


def test_the_json_result_is_written_though_the_reader_of_stdout_went_away(tmp_path, monkeypatch):
    """``bubble pose --json P.json ... | head``: was: the summary's write broke the pipe before the JSON
    file was written (lost), and the exit code was 1, a rejected sensor's."""
    import io
    import os
    import sys

    import trainer.inference

    class ClosedPipe(io.TextIOBase):
        def __init__(self, fd):
            self.fd = fd

        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self):
            return self.fd

    session = write_cylinder_session(tmp_path / "s.h5", n_poses=1, hold_frames=2)
    monkeypatch.setattr(trainer.inference.DepthEstimator, "load", classmethod(lambda cls, d: DecodingEstimator()))
    fd = os.open(tmp_path / "stdout", os.O_WRONLY | os.O_CREAT)
    monkeypatch.setattr(sys, "stdout", ClosedPipe(fd))
    out = tmp_path / "pose.json"
    try:
        code = cli.main(["pose", "--model", str(tmp_path / "m"), "--data", str(session), "--object", "mug",
                         "--json", str(out)])
    finally:
        os.close(fd)
    assert code == 141 and json.loads(out.read_text())["n_used"] == 2


def test_a_model_not_trained_on_the_sessions_sensor_is_noted(tmp_path, monkeypatch, capsys):
    """Was: no word of it (on the simulated bench a model fine-tuned on one sensor gives e_x 3.1 mm on
    another's session, 0.39 mm on its own)."""
    import dataclasses

    import trainer.inference
    from trainer.model_dir import load_metadata

    session = write_cylinder_session(tmp_path / "s.h5", n_poses=1, hold_frames=2)  # sensor CYL-1
    meta = load_metadata(_untrained_model(tmp_path / "m"))
    for serials, note in ((["CYL-1"], []), (["CYL-2", "CYL-3"], ["CYL-1"])):
        estimator = DecodingEstimator()
        estimator.metadata = dataclasses.replace(meta, training={"sensor_serials": serials})
        monkeypatch.setattr(trainer.inference.DepthEstimator, "load", classmethod(lambda cls, d: estimator))
        out = tmp_path / "pose.json"
        assert cli.main(["pose", "--model", "M", "--data", str(session), "--json", str(out)]) == 0
        assert json.loads(out.read_text())["sensors_not_trained_on"] == note
        err = capsys.readouterr().err
        assert err == "".join(f"bubble: note: model M was not trained on sensor {s} (its depth there is that of a model "
                              "that has not seen the sensor; one fine-tuned on it fits it better)\n" for s in note)


def _untrained_model(model_dir):
    from trainer.model_dir import ModelMetadata, save_model
    from trainer.networks import build_network
    from trainer.preprocessing import InputGeometry, IRNormalization

    torch.manual_seed(0)
    net = build_network("resnet", 0.25, 0.05, 0.15)
    meta = ModelMetadata(arch="resnet", width=0.25, min_depth=0.05, max_depth=0.15,
                         geometry=InputGeometry(H, W, 128, 160), normalization=IRNormalization(8.0, 1.0))
    return save_model(model_dir, net, meta)


def test_pose_command_bad_input_exits_2_with_one_line(tmp_path, capsys):
    session = write_cylinder_session(tmp_path / "s.h5", n_poses=1, hold_frames=2)
    assert cli.main(["pose", "--model", str(tmp_path / "m"), "--data", str(tmp_path / "missing.h5")]) == 2
    model = _untrained_model(tmp_path / "m")
    assert cli.main(["pose", "--model", str(model), "--data", str(session), "--object", "cup"]) == 2
    # an untrained network sees no contact: no usable frame
    assert cli.main(["pose", "--model", str(model), "--data", str(session)]) == 2
    recorded = session.read_bytes()
    assert cli.main(["pose", "--model", str(model), "--data", str(session), "--json", str(session)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 4 and all(line.startswith("bubble: error: ") for line in err)
    assert "no object 'cup'" in err[1] and "no usable hold frame" in err[2]
    assert "not an earlier `bubble pose --json` result; refusing to overwrite" in err[3] and session.read_bytes() == recorded
    # 1e308 mm overflowed the patch threshold: warnings before the error line
    for option, value, message in (("--threshold-mm", "0", "--threshold-mm must be within (0, 20], got 0"),
                                   ("--threshold-mm", "nan", "--threshold-mm must be within (0, 20], got nan"),
                                   ("--threshold-mm", "1e308", "--threshold-mm must be within (0, 20], got 1e+308"),
                                   ("--points", "0", "--points must be at least 30 (a fit needs that many), got 0"),
                                   ("--points", "29", "--points must be at least 30 (a fit needs that many), got 29"),
                                   ("--seed=-1", None, "--seed must be 0 or more, got -1")):  # was: one line for all
        argv = ["pose", "--model", str(model), "--data", str(session), option] + ([value] if value else [])
        assert cli.main(argv) == 2
        assert capsys.readouterr().err.splitlines() == [f"bubble: error: {message}"]


def test_json_and_plots_that_would_land_on_one_another_are_refused_before_the_run(tmp_path, capsys):
    """Was: the plots written into a folder named as the JSON (a traceback after the whole run, the
    JSON lost), a histogram's name taken by a folder (a traceback), or the JSON over a histogram."""
    session = write_cylinder_session(tmp_path / "s.h5", n_poses=1, hold_frames=2)
    model = _untrained_model(tmp_path / "m")
    (tmp_path / "busy" / "pose_errors.png").mkdir(parents=True)
    (tmp_path / "p").mkdir()
    base = ["pose", "--model", str(model), "--data", str(session)]
    for extra, says in (
            (["--json", str(tmp_path / "dup.json"), "--plots", str(tmp_path / "dup.json")], "lies where --plots"),
            (["--json", str(tmp_path / "p" / "pose_errors.png"), "--plots", str(tmp_path / "p")], "lies where --plots"),
            (["--plots", str(tmp_path / "busy")], "pose_errors.png is a directory")):
        assert cli.main(base + extra) == 2
        err = capsys.readouterr().err
        assert err.startswith("bubble: error: ") and err.count("\n") == 1 and says in err, err
