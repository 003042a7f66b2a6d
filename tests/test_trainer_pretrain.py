"""Pretraining step 2 (train + package the base model) on synthetic sessions of several sensors."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ctrl_c_once_it_exists, losing_the_first_interrupt, make_synthetic_session

import trainer.pretrain
import trainer.training
from trainer.checkpoint import has_checkpoint
from trainer.model_dir import BASE_MODEL_DIR, WEIGHTS_FILE, load_metadata
from collect.errors import InputError
from trainer.model_dir import METADATA_FILE, ONNX_FILE
from trainer.pretrain import MAX_BASE_MODEL_BYTES, TRAIN_DIR, main, package_base_model, write_model_card_section


def _sensor_sessions(work, n):
    """``n`` small synthetic sessions of sensors SYN-0.. in ``work`` (created); returns ``work``."""
    work.mkdir()
    for i in range(n):
        make_synthetic_session(work / f"sensor_{i:05d}.h5", height=48, width=64, poses_per_object=1,
                               sensor_serial=f"SYN-{i}", seed=i)
    return work


def _shipped_model_and_card(tmp_path, monkeypatch):
    """Stand-ins in ``tmp_path`` for the shipped base model directory (not created) and its model card
    (``# Model card``): the real ones are never written by a test. Returns both paths."""
    shipped, card = tmp_path / "trainer" / "base_model", tmp_path / "docs" / "model_card.md"
    card.parent.mkdir()
    card.write_text("# Model card\n")
    monkeypatch.setattr(trainer.pretrain, "BASE_MODEL_DIR", shipped)
    monkeypatch.setattr(trainer.pretrain, "MODEL_CARD", card)
    return shipped, card


def test_pretrain_trains_on_sensors_validates_on_held_out_ones_and_packages(tmp_path, monkeypatch, capsys):
    """Packaged into the shipped base model (``--out`` names it), the model card is rewritten by default."""
    work = _sensor_sessions(tmp_path / "work", 3)
    out, card = _shipped_model_and_card(tmp_path, monkeypatch)
    code = main(["train", "--work", str(work), "--out", str(out), "--val-sensors", "1", "--width", "0.125",
                 "--epochs", "0.5", "--frame-stride", "2"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json", "model.onnx", WEIGHTS_FILE]
    meta = load_metadata(out)
    assert meta.training["sensor_serials"] == ["SYN-0", "SYN-1"]
    assert [s["sensor_serial"] for s in meta.training["val_sources"]] == ["SYN-2"]
    text = card.read_text()
    assert text.startswith("# Model card") and "<!-- begin:pretraining -->" in text and "SYN-0, SYN-1" in text
    first = capsys.readouterr().out.splitlines()[0]  # the untrained model's validation (was: "loss nan mm")
    assert first.startswith("[eval] epoch 0.00 step 0 loss - val a1 "), first
    assert main(["train", "--work", str(tmp_path / "empty"), "--out", str(out)]) == 2


def test_pretrain_continues_a_model_in_its_own_architecture_and_replaces_it(tmp_path, monkeypatch):
    """A model directory of an earlier run is replaced (--init base --out trainer/base_model continues the
    shipped model). Packaged elsewhere than the shipped base model, no model card is written by default
    (was: the shipped model's card rewritten to describe a trial run)."""
    work = _sensor_sessions(tmp_path / "work", 2)
    _, card = _shipped_model_and_card(tmp_path, monkeypatch)
    out = tmp_path / "first"
    common = ["train", "--work", str(work), "--val-sensors", "1", "--epochs", "0.2", "--out", str(out)]
    assert main([*common, "--arch", "packnet", "--width", "0.125"]) == 0
    first = load_metadata(out)
    assert main([*common, "--init", str(out)]) == 0
    second = load_metadata(out)
    assert second.arch == "packnet" and second.training["init"] and not first.training["init"]
    assert card.read_text() == "# Model card\n"


def test_pretrain_refuses_an_out_that_holds_other_files(tmp_path, capsys):
    """``--out`` must be new, empty or a model directory: a folder with other files in it is refused
    before the training, its files untouched (was: trained, then its metadata.json replaced). And --out
    has no default (was: the shipped base model)."""
    work = _sensor_sessions(tmp_path / "work", 2)
    common = ["train", "--work", str(work), "--val-sensors", "1", "--width", "0.125", "--epochs", "0.2",
              "--model-card", ""]
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / METADATA_FILE).write_text('{"mine": true}')
    assert main([*common, "--out", str(foreign)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"pretrain: error: --out {foreign} is neither empty nor a model directory (it has no {WEIGHTS_FILE}); "
        "refusing to replace its files: choose a new or empty folder, or an earlier model"]
    (foreign / WEIGHTS_FILE).write_bytes(b"mine")
    assert main([*common, "--out", str(foreign)]) == 2  # a metadata.json that is not a model's
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "is neither empty nor a model directory (model " in err[0] and "'format'" in err[0], err
    run = tmp_path / "run"  # a folder with a model and more: a commissioning run, a fine-tune's checkpoint
    run.mkdir()
    for name in (WEIGHTS_FILE, METADATA_FILE, "report.md"):
        (run / name).write_text("mine")
    assert main([*common, "--out", str(run)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and f"--out {run} is neither empty nor a model directory (it holds report.md)" in err[0]
    assert (foreign / METADATA_FILE).read_text() == '{"mine": true}' and (foreign / WEIGHTS_FILE).read_bytes() == b"mine"
    assert (run / "report.md").read_text() == "mine"
    assert not (work / TRAIN_DIR).exists()  # refused before training
    with pytest.raises(SystemExit) as refused:
        main(common)
    assert refused.value.code == 2
    assert capsys.readouterr().err == "pretrain: error: the following arguments are required: --out\n"


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
    """Was: tracebacks (``--jobs 0``, a file as ``--work``), or exit 0 after recording nothing; a sensor
    seed out of the simulator's range failed every sensor (exit 1) after creating --work."""
    afile = tmp_path / "afile"
    afile.write_text("")
    seeds = "sensor seeds --first-seed .. --first-seed + --sensors - 1 must be within 0..4294967295, got"
    for argv, says in ((["--jobs", "0"], "must be at least 1"), (["--sensors", "-1"], "must be at least 1"),
                       (["--objects", " , "], "--objects names no object"), (["--work", str(afile)], "is a file"),
                       (["--first-seed", "-1"], f"{seeds} -1..14"),
                       (["--first-seed", "4294967296", "--sensors", "1"], f"{seeds} 4294967296..4294967296"),
                       (["--first-seed", "4294967295", "--sensors", "2"], f"{seeds} 4294967295..4294967296"),
                       # was: one error line per sensor from its bubble collect, its yaml left behind, exit 1
                       (["--poses-per-object", "1001"], "--poses-per-object must be 1..1000, got 1001"),
                       (["--jobs", str(os.cpu_count() + 1)], f"--jobs must be 1..{os.cpu_count()} (the CPUs")):
        assert main(["collect", "--work", str(tmp_path / "w"), *argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and says in err[0], err
    assert not (tmp_path / "w").exists()
    assert main(["train", "--work", str(tmp_path / "missing"), "--out", str(tmp_path / "base")]) == 2
    assert "is not a directory of sessions" in capsys.readouterr().err


def test_pretrain_names_a_path_too_long_in_one_line(tmp_path, capsys):
    """Was: an ``OSError`` traceback, exit 1 (this tool's code for a sensor that failed)."""
    long = tmp_path / ("a" * 300)
    for argv in (["collect", "--work", str(long)], ["train", "--work", str(long), "--out", str(tmp_path / "m")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err == f"pretrain: error: {long}: a name in this path is longer than the file system's limit\n", err


def _help_by_option(argv, capsys) -> dict[str, str]:
    """``--help`` of ``python -m trainer.pretrain ARGV``: each option's help text, on one line."""
    with pytest.raises(SystemExit) as done:
        main([*argv, "--help"])
    assert done.value.code == 0
    blocks = re.split(r"\n  (?=-)", capsys.readouterr().out.split("\noptions:\n", 1)[1])
    return {block.split()[0].rstrip(","): " ".join(block.split()) for block in blocks}


def test_pretrain_help_describes_every_option_with_its_default(capsys):
    """Was: no help for --sensors, --first-seed, --poses-per-object, train's --work, --out, --seed, no
    defaults shown, and "the following arguments are required: step" without a step."""
    collect = _help_by_option(["collect"], capsys)
    for option, default in (("--sensors", "(default 16)"), ("--first-seed", "(default 1000;"),
                            ("--poses-per-object", "(default 8)"), ("--sim-speed", "default 20)"),
                            ("--jobs", f"(default {min(2, os.cpu_count())})"), ("--work", "directory of the sessions")):
        assert default in collect[option], collect[option]
    train = _help_by_option(["train"], capsys)
    for option, says in (("--work", "WORK/model"), ("--out", "trainer/base_model"), ("--seed", "(default 0)"),
                         ("--val-sensors", "(default 2)"), ("--eval-interval", "(default 60)"),
                         ("--model-card", "default: docs/model_card.md when --out is the shipped base model")):
        assert says in train[option], train[option]
    with pytest.raises(SystemExit) as refused:
        main([])
    assert refused.value.code == 2
    assert capsys.readouterr().err == "pretrain: error: the following arguments are required: {collect,train}\n"


def _processes_naming(path: Path) -> list[str]:
    """Command lines of the running processes that name ``path``."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            text = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        if str(path) in text:
            found.append(text)
    return found


def test_pretrain_collect_stops_at_ctrl_c_and_keeps_the_sessions_recorded(tmp_path):
    """Ctrl-C in ``pretrain collect`` stops the session being recorded and starts no other: exit 130,
    one line, the sessions recorded so far kept (was: every queued sensor recorded first)."""
    work = tmp_path / "w"
    work.mkdir()
    recorded = work / "sensor_01000.h5"  # recorded by an earlier run: skipped, and kept
    recorded.write_bytes(b"a session")
    # a recording of ~6 s, which the Ctrl-C lands in (was: one pose at 100x, which could end between
    # its file's appearance and the Ctrl-C: the test then failed on a complete sensor_01001.h5)
    proc = subprocess.Popen([sys.executable, "-m", "trainer.pretrain", "collect", "--work", str(work), "--sensors", "3",
                             "--jobs", "1", "--objects", "box", "--poses-per-object", "3", "--sim-speed", "1"],
                            cwd=Path(__file__).resolve().parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    recording = work / "sensor_01001.partial.h5"  # the next sensor's session, being recorded by bubble collect
    deadline = time.monotonic() + 120
    while not recording.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and err.splitlines() == ["pretrain: interrupted"], (proc.returncode, err)
    assert out.splitlines() == [f"sensor seed 1000: {recorded}"]
    assert sorted(p.name for p in work.glob("sensor_*") if ".partial" not in p.name) == [
        "sensor_01000.h5", "sensor_01001.yaml"]  # sensor 1002 not started
    assert recorded.read_bytes() == b"a session"
    assert not _processes_naming(work)  # its bubble collect stopped with it


def test_pretrain_collect_stops_at_a_ctrl_c_whose_exception_python_loses(tmp_path, monkeypatch, capsys,
                                                                        interrupt_handlers_restored):
    """A KeyboardInterrupt raised while a weakref callback runs is only printed by Python ("Exception
    ignored in"): was every queued sensor recorded, exit 0. Now the main thread, which waits on the
    sensors' results, raises the stop again within ``STOP_POLL_S``."""
    calls = losing_the_first_interrupt(monkeypatch, trainer.pretrain)
    work = tmp_path / "w"
    with ctrl_c_once_it_exists(work / "sensor_01000.partial.h5"):
        code = main(["collect", "--work", str(work), "--sensors", "2", "--jobs", "1", "--objects", "box",
                     "--poses-per-object", "3", "--sim-speed", "1"])
    assert code == 130 and calls == [signal.SIGINT, signal.SIGINT], (code, calls)  # the lost one, then again
    assert capsys.readouterr().err.splitlines() == ["pretrain: interrupted"]
    assert sorted(p.name for p in work.glob("sensor_*")) == [  # kept, as a later run records it anew; 1001 not started
        "sensor_01000.partial.h5", "sensor_01000.yaml"]
    assert not _processes_naming(work)  # its bubble collect stopped with it


def test_pretrain_checks_the_model_card_before_training(tmp_path, capsys):
    """Was: a traceback after the whole training for a --model-card that is a directory or lies in a
    missing folder."""
    work = _sensor_sessions(tmp_path / "work", 2)
    common = ["train", "--work", str(work), "--out", str(tmp_path / "base"), "--val-sensors", "1", "--width", "0.125",
              "--epochs", "0.2"]
    assert main([*common, "--model-card", str(tmp_path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"pretrain: error: --model-card {tmp_path} is a directory, not a markdown file"]
    (tmp_path / "afile").write_text("")
    assert main([*common, "--model-card", str(tmp_path / "afile" / "card.md")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "is a file, not a directory" in err[0]
    meta = tmp_path / "metadata.json"  # was: a markdown section appended to it after the training, exit 0
    meta.write_text('{"arch": "x"}')
    assert main([*common, "--model-card", str(meta)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"pretrain: error: --model-card {meta} is not a markdown file (.md): refusing to write a model card "
        "section into it"]
    assert meta.read_text() == '{"arch": "x"}'
    binary = tmp_path / "card.md"  # was: a UnicodeDecodeError traceback after the training
    binary.write_bytes(b"\x89HDF\r\n\x1a\n\xff\xfe")
    assert main([*common, "--model-card", str(binary)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"pretrain: error: --model-card {binary} is not UTF-8 text: refusing to write a model card section into it"]
    assert not (work / TRAIN_DIR).exists()  # refused before training
    card = tmp_path / "new" / "docs" / "card.md"  # missing folders are created, as for --out
    write_model_card_section(BASE_MODEL_DIR, card, "python -m trainer.pretrain train")
    assert "<!-- begin:pretraining -->" in card.read_text()


def test_pretrain_checks_val_sensors_and_eval_interval(tmp_path, capsys):
    """Was: --val-sensors -1 trained on 1 session and validated on 2, 0 said "no session files given";
    --eval-interval nan, 0 or negative was taken (nan: never a validation nor a checkpoint); --resume
    with nothing to resume trained anew."""
    work = _sensor_sessions(tmp_path / "work", 3)
    common = ["train", "--work", str(work), "--out", str(tmp_path / "base"), "--model-card", "", "--width", "0.125",
              "--epochs", "0.2"]
    for bad, says in ((["--val-sensors", "0"], "--val-sensors must be at least 1"),
                      (["--val-sensors", "-1"], "--val-sensors must be at least 1"),
                      (["--val-sensors", "3"], "3 sessions in"),
                      (["--eval-interval", "nan"], "--eval-interval must be a positive number of seconds, got nan"),
                      (["--eval-interval", "0"], "--eval-interval must be a positive number of seconds, got 0"),
                      (["--eval-interval", "-5"], "--eval-interval must be a positive number of seconds, got -5"),
                      (["--eval-interval", "inf"], "--eval-interval must be a positive number of seconds, got inf"),
                      (["--resume"], f"cannot resume {work / TRAIN_DIR}: it holds no checkpoint of an interrupted "
                                     "training; drop --resume to train anew")):  # was: a fresh training
        assert main([*common, *bad]) == 2, bad
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("pretrain: error: ") and says in err[0], err
    assert not (work / TRAIN_DIR).exists()


def _train_model_interrupted(monkeypatch, signum, after_reports):
    """``train_model`` as ``pretrain train`` calls it, sent ``signum`` once its progress callback has
    had ``after_reports`` reports (0: as its data loads)."""
    real = trainer.training.train_model
    real_load = trainer.training.load_frames

    def load_frames(*args, **kwargs):
        if after_reports == 0:
            os.kill(os.getpid(), signum)
        return real_load(*args, **kwargs)

    def train_model(config, progress_callback, stop_event=None):
        reports = []

        def progress(p):
            progress_callback(p)
            reports.append(p)
            if len(reports) == after_reports:  # the untrained model's validation, step 1, step 2, ...
                os.kill(os.getpid(), signum)

        return real(config, progress, stop_event)

    monkeypatch.setattr(trainer.training, "load_frames", load_frames)
    monkeypatch.setattr(trainer.training, "train_model", train_model)


def test_pretrain_stopped_by_a_signal_checkpoints_the_step_reached(tmp_path, monkeypatch, capsys,
                                                                  interrupt_handlers_restored):
    """Ctrl-C (SIGTERM, SIGHUP) in ``pretrain train`` stops it as ``bubble train``: the step in
    progress finished and checkpointed, one line, exit 130 (143, 129), and ``--resume`` goes on from
    there; a stop while the data loads ends it at once with one line. Was: a KeyboardInterrupt
    traceback and no checkpoint (SIGTERM: the process killed)."""
    work = _sensor_sessions(tmp_path / "work", 2)
    out = tmp_path / "base"
    train = ["train", "--work", str(work), "--out", str(out), "--val-sensors", "1", "--width", "0.125",
             "--epochs", "0.2", "--frame-stride", "1", "--batch-size", "1", "--model-card", ""]
    model = work / TRAIN_DIR
    _train_model_interrupted(monkeypatch, signal.SIGINT, after_reports=0)
    assert main(train) == 130
    assert capsys.readouterr().err.splitlines() == ["pretrain: interrupted"]
    assert not has_checkpoint(model) and not out.exists()
    monkeypatch.undo()
    _train_model_interrupted(monkeypatch, signal.SIGTERM, after_reports=3)
    assert main(train) == 143
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and re.fullmatch(rf"pretrain: interrupted: its checkpoint at step 2 \(\d+\.\d min of "
                                          rf"training\) is in {re.escape(str(model))}: continue with the same command "
                                          "and --resume", err[0]), err
    assert json.loads((model / "checkpoint.json").read_text())["progress"]["step"] == 2
    assert not (model / WEIGHTS_FILE).exists() and not out.exists()
    assert main(train) == 2  # without --resume: refused (was: trained anew, the checkpoint written over)
    assert capsys.readouterr().err.splitlines() == [
        f"pretrain: error: {model} holds the checkpoint of an interrupted training; add --resume to continue it, "
        "or remove it to train anew"]
    assert json.loads((model / "checkpoint.json").read_text())["progress"]["step"] == 2
    monkeypatch.undo()
    save_model = trainer.training.save_model

    def ctrl_c_then_save(*args, **kwargs):  # a stop after the last step: the model is whole, and packaged
        os.kill(os.getpid(), signal.SIGINT)
        return save_model(*args, **kwargs)

    monkeypatch.setattr(trainer.training, "save_model", ctrl_c_then_save)
    assert main([*train, "--resume"]) == 130
    assert capsys.readouterr().err.splitlines() == [
        f"pretrain: interrupted after the training's last step: the model in {out} is complete"]
    assert load_metadata(out).training["steps"] > 2 and not has_checkpoint(model)


def test_pretrain_collect_checks_objects_and_sim_speed_before_recording(tmp_path, capsys):
    """Was: each sensor failed (exit 1) after its sensor YAML was written, for a --sim-speed out of
    range or an unknown object."""
    for argv, says in ((["--sim-speed", "0"], "simulation speed 0.0 must be within 0.1..100"),
                       (["--sim-speed", "nan"], "simulation speed nan must be within"),
                       (["--objects", "mug,teapot"], "unknown object 'teapot'"),
                       (["--objects", "mug, missing.stl"], "mesh file not found: missing.stl")):
        assert main(["collect", "--work", str(tmp_path / "w"), "--sensors", "1", *argv]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("pretrain: error: ") and says in err[0], err
    assert not (tmp_path / "w").exists()


def test_packaging_a_base_model_over_budget_leaves_the_old_one(tmp_path):
    """Was: the oversized files were copied over the base model, then refused."""
    out = tmp_path / "base"
    out.mkdir()
    for name in (WEIGHTS_FILE, METADATA_FILE, ONNX_FILE):
        (out / name).write_text(f"old {name}")
    big = tmp_path / "big"
    big.mkdir()
    (big / METADATA_FILE).write_text("{}")
    with open(big / WEIGHTS_FILE, "wb") as f:  # sparse: over the budget without writing it
        f.truncate(MAX_BASE_MODEL_BYTES + 1)
    with pytest.raises(InputError, match=rf"base model is 20.0 MB, over the 20 MB budget; {re.escape(str(out))} is left as it was"):
        package_base_model(big, out)
    assert sorted(p.name for p in out.iterdir()) == sorted((WEIGHTS_FILE, METADATA_FILE, ONNX_FILE))
    assert all((out / name).read_text() == f"old {name}" for name in (WEIGHTS_FILE, METADATA_FILE, ONNX_FILE))
    small = tmp_path / "small"  # within budget and without an ONNX export: the old export goes
    small.mkdir()
    (small / METADATA_FILE).write_text("{}")
    (small / WEIGHTS_FILE).write_bytes(b"w")
    assert package_base_model(small, out) == out
    assert sorted(p.name for p in out.iterdir()) == sorted((WEIGHTS_FILE, METADATA_FILE))
    assert (out / WEIGHTS_FILE).read_bytes() == b"w"
