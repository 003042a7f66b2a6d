"""Pretraining step 2 (train + package the base model) on synthetic sessions of several sensors."""

import pytest
from conftest import make_synthetic_session
from trainer.model_dir import WEIGHTS_FILE, load_metadata
from trainer.pretrain import TRAIN_DIR, main


def _sensor_sessions(work, n):
    """``n`` small synthetic sessions of sensors SYN-0.. in ``work`` (created); returns ``work``."""
    work.mkdir()
    for i in range(n):
        make_synthetic_session(work / f"sensor_{i:05d}.h5", height=48, width=64, poses_per_object=1,
                               sensor_serial=f"SYN-{i}", seed=i)
    return work


def test_pretrain_trains_on_sensors_validates_on_held_out_ones_and_packages(tmp_path):
    work = _sensor_sessions(tmp_path / "work", 3)
    card = tmp_path / "card.md"
    card.write_text("# Model card\n")
    out = tmp_path / "base"
    code = main(["train", "--work", str(work), "--out", str(out), "--val-sensors", "1", "--width", "0.125",
                 "--epochs", "0.5", "--frame-stride", "2", "--model-card", str(card)])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "model.onnx", WEIGHTS_FILE]
    meta = load_metadata(out)
    assert meta.training["sensor_serials"] == ["SYN-0", "SYN-1"]
    assert [s["sensor_serial"] for s in meta.training["val_sources"]] == ["SYN-2"]
    text = card.read_text()
    assert text.startswith("# Model card") and "<!-- begin:pretraining -->" in text and "SYN-0, SYN-1" in text
    assert main(["train", "--work", str(tmp_path / "empty"), "--out", str(out)]) == 2


def test_pretrain_continues_a_model_in_its_own_architecture(tmp_path):
    work = _sensor_sessions(tmp_path / "work", 2)
    common = ["train", "--work", str(work), "--val-sensors", "1", "--epochs", "0.2", "--model-card", ""]
    assert main([*common, "--out", str(tmp_path / "first"), "--arch", "packnet", "--width", "0.125"]) == 0
    assert main([*common, "--out", str(tmp_path / "second"), "--init", str(tmp_path / "first")]) == 0
    assert load_metadata(tmp_path / "second").arch == "packnet"


def test_pretrain_refuses_to_package_into_its_own_training_directory(tmp_path, capsys):
    work = _sensor_sessions(tmp_path / "work", 2)
    assert main(["train", "--work", str(work), "--out", str(work / "model"), "--val-sensors", "1"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "checkpoint" in err[0]
    assert not (work / "model").exists()  # refused before training


def test_pretrain_checks_its_training_options_like_bubble_train(tmp_path, capsys):
    """The options shared with ``bubble train``: one budget, a known network, an --init that is a
    model directory; each refused (exit 2) before any training."""
    work = _sensor_sessions(tmp_path / "work", 2)
    common = ["train", "--work", str(work), "--out", str(tmp_path / "base"), "--val-sensors", "1", "--model-card", ""]
    for bad, says in ((["--epochs", "1", "--minutes", "2"], "not allowed with argument"),
                      (["--arch", "unet"], "invalid choice")):
        with pytest.raises(SystemExit) as refused:
            main([*common, *bad])
        err = capsys.readouterr().err.splitlines()  # was: argparse's usage text, then the error
        assert refused.value.code == 2 and len(err) == 1 and err[0].startswith("pretrain: error: ") and says in err[0]
    weights_file = tmp_path / WEIGHTS_FILE
    weights_file.write_bytes(b"")
    for init, says in ((weights_file, "is a file, not a model directory"), (tmp_path / "missing", "not found")):
        assert main([*common, "--init", str(init)]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and says in err[0] and str(init) in err[0]
    assert not (work / TRAIN_DIR).exists()


def test_pretrain_collect_refuses_bad_options_before_recording(tmp_path, capsys):
    """Was: tracebacks (``--jobs 0``, a file as ``--work``), or exit 0 after recording nothing."""
    afile = tmp_path / "afile"
    afile.write_text("")
    for argv, says in ((["--jobs", "0"], "must be at least 1"), (["--sensors", "-1"], "must be at least 1"),
                       (["--objects", " , "], "--objects names no object"), (["--work", str(afile)], "is a file")):
        assert main(["collect", "--work", str(tmp_path / "w"), *argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and says in err[0], err
    assert not (tmp_path / "w").exists()
    assert main(["train", "--work", str(tmp_path / "missing")]) == 2
    assert "is not a directory of sessions" in capsys.readouterr().err
