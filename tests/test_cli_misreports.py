"""Bad input that was refused with a misleading line (or had a wrong effect): each now gets one
clear ``bubble: error:`` line and exit 2, and a resume with nothing left to do changes nothing."""

from __future__ import annotations

import errno
import json
import os

import cv2
import h5py
import numpy as np
import pytest

from calibrate.cli import main
from calibrate.sensor_registry import SensorRegistry
from collect import session_format as sf
from collect.errors import InputError
from collect.session_reader import Session
from collect.session_writer import SessionWriter


def _refused(capsys, argv, needle) -> str:
    """Run ``bubble argv``: exit 2 and one error line holding ``needle``."""
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bubble: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert needle in err, err
    return err


@pytest.fixture
def places(tmp_path):
    """A folder, a plain file and a sensor spec in ``tmp_path``."""
    folder = tmp_path / "folder"
    folder.mkdir()
    plain = tmp_path / "plain"
    plain.write_text("x")
    spec = tmp_path / "spec.yaml"
    assert main(["sim", "new-sensor", "--seed", "1", "--out", str(spec)]) == 0
    return folder, plain, spec


def test_output_that_is_a_directory_or_under_a_file(tmp_path, places, capsys):
    folder, plain, spec = places
    capsys.readouterr()
    _refused(capsys, ["collect", "--sim", "--quiet", "--out", folder], f"{folder} is a directory, not a session file")
    _refused(capsys, ["collect", "--sim", "--quiet", "--resume", "--out", folder], "is a directory, not a session file")
    _refused(capsys, ["collect", "--sim", "--quiet", "--out", plain / "s.h5"], f"{plain} is a file, not a directory")
    _refused(capsys, ["sim", "new-sensor", "--seed", "2", "--out", folder], f"--out {folder} is a directory")
    _refused(capsys, ["sim", "new-sensor", "--seed", "2", "--out", plain / "s.yaml"], f"{plain} is a file, not a directory")
    preview = ["sim", "preview", "--sensor", spec, "--object", "box", "--out"]
    _refused(capsys, preview + [folder], f"--out {folder} is a directory")
    assert list(tmp_path.glob("folder.*")) == []  # was: the preview written to folder.png, exit 0
    _refused(capsys, preview + [plain / "p.png"], f"{plain} is a file, not a directory")
    # was: "directory … does not exist" of a file
    _refused(capsys, ["evaluate", "--model", "base", "--data", spec, "--json", plain / "e.json"],
             f"cannot write {plain / 'e.json'}: {plain} is a file, not a directory")
    assert list(folder.iterdir()) == [] and plain.read_text() == "x"


def test_json_and_image_outputs_may_be_placeholders_in_folders_yet_to_be_made(tmp_path, synthetic_session, capsys):
    """An empty file (``tempfile.mkstemp``'s) and a folder not made yet: was "exists and is not an
    earlier ... result" and "directory ... does not exist"."""
    placeholder = tmp_path / "placeholder.json"
    placeholder.touch()
    deeper = tmp_path / "results" / "pose.json"
    image = tmp_path / "placeholder.png"
    image.touch()
    assert main(["evaluate", "--model", "base", "--data", str(synthetic_session), "--json", str(placeholder)]) == 0
    assert main(["pose", "--model", "base", "--data", str(synthetic_session), "--json", str(deeper)]) == 0
    assert json.loads(placeholder.read_text())["written_by"] == "bubble evaluate"
    assert json.loads(deeper.read_text())["written_by"] == "bubble pose"
    spec = tmp_path / "s.yaml"
    assert main(["sim", "new-sensor", "--seed", "1", "--out", str(spec)]) == 0
    assert main(["sim", "preview", "--sensor", str(spec), "--object", "box", "--out", str(image)]) == 0
    assert image.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc: a folder that takes no new file")
def test_output_in_a_folder_that_takes_no_file_is_refused_before_any_work(tmp_path, synthetic_session, capsys):
    """Permission bits do not tell whether a file can be created (root; a read-only or virtual file
    system such as /proc): each command tries, before any work."""
    cannot = "no file can be created in /proc"
    for argv in (["train", "--data", synthetic_session, "--epochs", "0.01", "--out", "/proc/m"],  # was: a traceback
                 # at the first checkpoint
                 ["train", "--data", synthetic_session, "--epochs", "0.01", "--out", tmp_path / "m", "--json", "/proc/m.json"],
                 ["pose", "--model", "base", "--data", synthetic_session, "--plots", "/proc/plots"],  # was: a
                 # traceback after the whole run
                 ["collect", "--sim", "--quiet", "--out", "/proc/s.h5"],  # was: "only 0 MB free on the disk"
                 ["commission", "--sim", "--quiet", "--out", "/proc/run"],
                 ["commission", "--sim", "--quiet", "--out", tmp_path / "run", "--registry", "/proc/registry"]):
        _refused(capsys, argv, cannot)
    assert not (tmp_path / "m").exists() and not (tmp_path / "run").exists()
    _refused(capsys, ["info", "/dev/null"], "/dev/null is not a regular file")  # was: "no such file"
    _refused(capsys, ["collect", "--sim", "--resume", "--out", "/dev/full"],
             "cannot resume /dev/full: not a regular file")  # was: "no such file"


def test_preview_never_overwrites_another_file(tmp_path, places, synthetic_session, capsys):
    _, _, spec = places
    capsys.readouterr()
    recording = synthetic_session.read_bytes()
    preview = ["sim", "preview", "--sensor", spec, "--object", "box", "--out"]
    _refused(capsys, preview + [synthetic_session], "the preview is a PNG image; name a .png file")  # was: a traceback
    notes = tmp_path / "notes.png"
    notes.write_text("not a picture")
    refusal = "exists and is not an earlier `bubble sim preview` image; refusing to overwrite it"
    _refused(capsys, preview + [notes], f"{notes} {refusal}")
    photo = tmp_path / "photo.png"  # was: replaced, as any PNG
    assert cv2.imwrite(str(photo), np.full((4, 6, 3), 200, np.uint8))
    picture = photo.read_bytes()
    _refused(capsys, preview + [photo], f"{photo} {refusal}")
    assert synthetic_session.read_bytes() == recording and notes.read_text() == "not a picture"
    assert photo.read_bytes() == picture
    earlier = tmp_path / "earlier.png"
    for press_mm in ("2", "6"):  # an earlier preview is replaced
        assert main([str(a) for a in preview + [earlier, "--press-mm", press_mm]]) == 0
    assert "pressed 6.0 mm" in capsys.readouterr().out


def test_an_output_name_its_temporary_file_could_not_have_is_refused_before_any_work(tmp_path, places,
                                                                                       synthetic_session, capsys):
    """A file written whole goes through a temporary file ``<name>.<8 characters>.tmp``, 13 bytes longer:
    a name of 243-255 bytes failed only after the work, naming that temporary file. Folders keep 255."""
    _, _, spec = places
    capsys.readouterr()
    folder = tmp_path / ("d" * 255)
    folder.mkdir()
    limit = ("its file name is longer than 242 bytes (the file system's 255, less the 13 of the temporary file it "
             "is written through)")
    for argv, out in ((["sim", "new-sensor", "--seed", "2", "--out"], folder / ("s" * 238 + ".yaml")),
                      (["sim", "preview", "--sensor", spec, "--object", "box", "--out"], folder / ("p" * 239 + ".png")),
                      (["evaluate", "--model", "base", "--data", synthetic_session, "--json"],
                       folder / ("e" * 238 + ".json"))):
        assert len(out.name) == 243
        _refused(capsys, argv + [out], f"cannot write {out}: {limit}")
    assert list(folder.iterdir()) == []
    fits = folder / ("s" * 237 + ".yaml")  # 242 bytes
    assert main(["sim", "new-sensor", "--seed", "2", "--out", str(fits)]) == 0 and fits.is_file()


def test_model_and_session_paths_of_the_wrong_kind(tmp_path, places, synthetic_session, capsys):
    folder, plain, _ = places
    capsys.readouterr()
    _refused(capsys, ["train", "--data", synthetic_session, "--epochs", "0.01", "--out", plain / "model"],
             f"{plain} is a file, not a directory")  # was: a traceback after loading the data
    _refused(capsys, ["train", "--data", synthetic_session, "--init", plain, "--out", tmp_path / "m"],
             f"--init {plain} is a file, not a model directory")
    _refused(capsys, ["evaluate", "--model", plain, "--data", synthetic_session], f"--model {plain} is a file, not a model directory")
    _refused(capsys, ["pose", "--model", plain, "--data", synthetic_session], f"--model {plain} is a file, not a model directory")
    for argv in (["info", folder], ["train", "--data", folder, "--out", tmp_path / "m"],
                 ["evaluate", "--model", "base", "--data", folder]):
        _refused(capsys, argv, f"{folder} is a directory, not a session file")  # was: "no such file"
    assert not (tmp_path / "m").exists()


def test_a_model_folder_named_base_is_not_swapped_for_the_shipped_model(tmp_path, synthetic_session, capsys,
                                                                        monkeypatch):
    """Was: ``./base`` (or ``base/``) read as a path is ``base``: the shipped base model was evaluated, posed
    or fine-tuned from instead, with exit 0, and ``train --out base`` wrote a model only that name reached."""
    import shutil

    from trainer.model_dir import BASE_MODEL_DIR

    shutil.copytree(BASE_MODEL_DIR, tmp_path / "base")
    monkeypatch.chdir(tmp_path)
    says = f"a folder named base here reads as the shipped base model ('base'); give its full path, {tmp_path / 'base'}"
    for argv, option in ((["evaluate", "--model", "./base", "--data", synthetic_session], "--model ./base"),
                         (["pose", "--model", "base/", "--data", synthetic_session], "--model base/"),
                         (["train", "--data", synthetic_session, "--init", "./base", "--out", "m"], "--init ./base"),
                         (["commission", "--sim", "--base-model", "./base", "--out", "run"], "--base-model ./base")):
        _refused(capsys, argv, f"{option}: {says}")
    for out in ("base", "./base/"):
        _refused(capsys, ["train", "--data", synthetic_session, "--out", out],
                 f"--out {out}: 'base' names the shipped base model where a model is read (--init, --model)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["base", "synthetic.h5"]


def test_empty_object_lists(tmp_path, synthetic_session, capsys):
    for argv in (["evaluate", "--model", "base", "--data", synthetic_session, "--objects", ","],
                 ["train", "--data", synthetic_session, "--objects", " , ", "--out", tmp_path / "m"]):
        _refused(capsys, argv, "--objects is empty")  # was: "no press/hold frames in ..."
    _refused(capsys, ["train", "--data", synthetic_session, "--holdout-object", "", "--out", tmp_path / "m"],
             "--holdout-object is empty")  # was: trained with no object held out
    assert not (tmp_path / "m").exists()


def test_simulated_bench_options_without_sim(tmp_path, places, capsys):
    _, _, spec = places
    needle = "--sensor, --sim-fault and --sim-speed need --sim"
    for command, out in (("collect", tmp_path / "s.h5"), ("commission", tmp_path / "run")):
        for extra in (["--sim-speed", "5"], ["--sensor", spec], ["--sim-fault", "camera-stall@1"]):
            _refused(capsys, [command, "--out", out, *extra], needle)  # was (commission): '--sim-speed' ignored
    assert not (tmp_path / "s.h5").exists() and not (tmp_path / "run").exists()


def test_mesh_paths_that_are_not_mesh_files(tmp_path, places, capsys):
    folder, plain, spec = places
    capsys.readouterr()
    collect = ["collect", "--sim", "--quiet", "--out", tmp_path / "s.h5", "--object-mesh"]
    # each was: "unknown object '...': use one of mug, wine_glass, box, fingers or a mesh file"
    _refused(capsys, collect + [folder], f"--object-mesh {folder} is a directory, not a mesh file")
    _refused(capsys, collect + [plain], f"--object-mesh {plain} is not a mesh file")
    _refused(capsys, collect + [tmp_path / "missing"], f"mesh file not found: {tmp_path / 'missing'}")
    _refused(capsys, collect + [""], "--object-mesh is empty")
    _refused(capsys, ["sim", "preview", "--sensor", spec, "--object", folder, "--out", tmp_path / "p.png"],
             f"--object {folder} is a directory, not a mesh file")
    assert not (tmp_path / "s.h5").exists()


def test_hdf5_files_that_are_not_sessions(tmp_path, synthetic_session, capsys):
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["x"] = np.arange(3)
    _refused(capsys, ["info", plain], f"{plain}: an HDF5 file but not a bubble-session file (it has no 'format' attribute)")
    with h5py.File(synthetic_session, "a") as f:
        f.attrs[sf.ATTR_FORMAT] = "other-format"
    _refused(capsys, ["info", synthetic_session], "not a bubble-session file (its 'format' attribute is 'other-format')")


def test_a_session_in_a_folder_that_cannot_be_entered_is_not_called_missing(tmp_path, synthetic_session, monkeypatch,
                                                                             capsys):
    """``stat`` of a file in a folder without search permission fails with EACCES (was: "no such file")."""
    locked = tmp_path / "locked"
    locked.mkdir()
    inside = locked / "w.h5"
    synthetic_session.rename(inside)
    real_stat = os.stat

    def stat(path, *args, **kwargs):
        if os.fspath(path) == str(inside):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
        return real_stat(path, *args, **kwargs)

    monkeypatch.setattr(os, "stat", stat)
    err = _refused(capsys, ["info", inside], f"cannot read {inside}: Permission denied")
    assert "no such file" not in err
    monkeypatch.undo()
    _refused(capsys, ["info", locked / "missing.h5"], f"{locked / 'missing.h5'}: no such file")


def test_info_of_a_session_without_frames(tmp_path, capsys):
    intrinsics = {"fx": 5.0, "fy": 5.0, "cx": 2.0, "cy": 1.5, "width": 5, "height": 4}
    SessionWriter(tmp_path / "empty.h5", sensor_serial="S1", sensor_spec={}, intrinsics=intrinsics,
                  camera_in_tcp=np.zeros(6), simulated=False, objects=[]).close()
    assert main(["info", str(tmp_path / "empty.h5")]) == 0
    out = capsys.readouterr().out
    assert "frames: 0 of 5x4" in out and "(no recording time)" in out and "nan" not in out  # was: "nan MB per minute"


def _collect_box(out, *extra):
    return main(["collect", "--sim", "--objects", "box", "--poses-per-object", "1", "--seed", "3", "--quiet",
                 "--out", str(out), *extra])


def test_resume_of_a_complete_plan_records_nothing(tmp_path, capsys):
    out = tmp_path / "done.h5"
    assert _collect_box(out) == 0
    capsys.readouterr()
    recorded = out.read_bytes()
    assert _collect_box(out, "--resume") == 0  # was: one more frame and a new segment in resumed_at_frames
    assert "the plan is already complete (1 pose on 1 object); nothing to record" in capsys.readouterr().out
    assert out.read_bytes() == recorded
    # one cut off after its last pose (never closed) is closed, with nothing added
    with h5py.File(out, "a") as f:
        f.attrs[sf.ATTR_CLOSED] = ""
    with Session.open(out) as s:
        n, closed = s.n_frames, s.closed_cleanly
    assert not closed
    assert _collect_box(out, "--resume") == 0
    assert "nothing to record (the file had not been closed: it is now)" in capsys.readouterr().out
    with Session.open(out) as s, h5py.File(out, "r") as f:
        assert s.closed_cleanly and s.n_frames == n and sf.ATTR_RESUMED_AT_FRAMES not in f.attrs
    # the checks of a resume still come first: another plan is refused as before
    assert _collect_box(out, "--resume", "--poses-per-object", "2") == 2
    assert "another plan" in capsys.readouterr().err


def test_a_resumed_segment_is_listed_only_when_it_records_a_frame(tmp_path):
    h, w = 4, 5
    intrinsics = {"fx": 5.0, "fy": 5.0, "cx": 2.0, "cy": 1.5, "width": w, "height": h}

    def writer(resume):
        return SessionWriter(tmp_path / "s.h5", sensor_serial="S1", sensor_spec={}, intrinsics=intrinsics,
                             camera_in_tcp=np.zeros(6), simulated=False, objects=[], resume=resume)

    def frame(w_, i):
        w_.append_frame(np.zeros((h, w), np.uint16), np.zeros((h, w), np.uint16), i, i, i, -1, -1,
                        sf.PHASE_FREE, np.zeros(6))

    with writer(False) as w1:
        frame(w1, 0)
    with writer(True):
        pass
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert sf.ATTR_RESUMED_AT_FRAMES not in f.attrs
    with writer(True) as w2:
        frame(w2, 1)
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert json.loads(f.attrs[sf.ATTR_RESUMED_AT_FRAMES]) == [1] and f[sf.FRAMES_SEQ].shape == (2,)


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d["history"][0].__setitem__("accepted", "yes"), "'history[0].accepted' must be true or false, got \"yes\""),
        (lambda d: d.__setitem__("history", 3), "'history' must be a list of commissionings, got 3"),
        (lambda d: d.__setitem__("accepted_metrics", 3), "'accepted_metrics' must be an object of metrics or null, got 3"),
        (lambda d: d["accepted_metrics"].__setitem__("a1", "high"), "'accepted_metrics.a1' must be a number from 0 to 1 or null"),
        (lambda d: d["history"][0].__setitem__("a1", "high"), "'history[0].a1' must be a number from 0 to 1 or null"),
        (lambda d: d["history"][0].__setitem__("a1", float("nan")), "'history[0].a1' must be a number from 0 to 1 or null, got NaN"),
        (lambda d: d["history"][0].__setitem__("a1", 10**400),  # was: an OverflowError traceback
         "'history[0].a1' must be a number from 0 to 1 or null, got 1000000000000000000000000000000000000..."),
        (lambda d: d["history"][0].__setitem__("a1", -5), "'history[0].a1' must be a number from 0 to 1 or null, got -5"),  # was: listed
        (lambda d: d["history"][0].__setitem__("abs_rel", -0.5), "'history[0].abs_rel' must be a number >= 0 or null, got -0.5"),
        (lambda d: d.__setitem__("intrinsics", {"fx": "x"}), "'intrinsics' must be an object of finite numbers (a list of them for 'distortion') or null"),
        (lambda d: d.__setitem__("status", ["accepted"]), "'status' must be 'accepted' or 'rejected'"),
        (lambda d: d.__setitem__("last_commissioned", 5), "'last_commissioned' must be an ISO 8601 time with its UTC offset, got 5"),
        (lambda d: d.__setitem__("simulated", "no"), "'simulated' must be true or false"),
        (lambda d: d["history"][0].pop("time"), "'history[0]' has no 'time'"),
        (lambda d: d["history"][0].pop("run_dir"), "'history[0]' has no 'run_dir'"),
        (lambda d: d.__setitem__("serial", "SB-B"), "'serial' must be its folder's name 'SB-A', got \"SB-B\""),
        (lambda d: d.pop("history"), "it has no 'history' of commissionings"),
    ],
)
def test_registry_profile_fields_of_the_wrong_type(tmp_path, capsys, edit, field):
    registry = SensorRegistry(tmp_path / "reg")
    for serial in ("SB-A", "SB-B"):
        registry.register(serial, accepted=True, run_dir=tmp_path, intrinsics={"width": 4, "height": 3},
                          camera_in_tcp=None, simulated=True, acceptance={"accepted": True, "a1": 0.9, "abs_rel": 0.01})
    path = tmp_path / "reg" / "SB-A" / "profile.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    # was: a traceback, a wrong listing, or "needs a 'history' of commissionings" without the field
    for argv in (["sensors", "--registry", tmp_path / "reg"], ["sensors", "--registry", tmp_path / "reg", "SB-A"]):
        err = _refused(capsys, argv, field)
        assert f"sensor registry profile {path} is corrupt: " in err


def test_a_damaged_registry_entry_hides_no_other_sensor(tmp_path, capsys):
    """``bubble sensors`` lists every readable sensor, then names the damaged entries in its one error
    line (exit 2); was: the error line alone, every other sensor hidden."""
    registry = SensorRegistry(tmp_path / "reg")
    for serial in ("SB-A", "SB-B", "SB-C"):
        registry.register(serial, accepted=True, run_dir=tmp_path, intrinsics={"width": 4, "height": 3},
                          camera_in_tcp=None, simulated=True, acceptance={"accepted": True, "a1": 0.9, "abs_rel": 0.01})
    (tmp_path / "reg" / "SB-A" / "profile.json").write_text("{")
    (tmp_path / "reg" / "SB-C" / "profile.json").write_text("[]")
    for argv, listed in ((["sensors", "--registry", tmp_path / "reg"], lambda out: out.splitlines()[2].split()[0]),
                         (["sensors", "--registry", tmp_path / "reg", "--json"],
                          lambda out: [p["serial"] for p in json.loads(out)])):
        assert main([str(a) for a in argv]) == 2
        out, err = capsys.readouterr()
        assert listed(out) in ("SB-B", ["SB-B"]) and "SB-A" not in out and "SB-C" not in out, out
        assert err == (f"bubble: error: sensor registry entry {tmp_path / 'reg' / 'SB-A'} is unreadable: Expecting "
                       "property name enclosed in double quotes: line 1 column 2 (char 1) (and 1 more damaged entry)\n")


@pytest.mark.parametrize("damage, message", [
    (lambda p: p.write_text('{"history": [], "a1": ' + "9" * 5000 + "}"), "is unreadable: Exceeds the limit (4300 digits)"),
    (lambda p: p.write_text("[" * 100000), "is unreadable: maximum recursion depth exceeded"),  # was: a traceback
    (lambda p: (p.unlink(), p.mkdir()), "is damaged: its profile.json is not a regular file"),  # was: left out of the
    # listing without a word, "not in the registry" for the sensor itself, and a commissioning failed at its end
    (lambda p: (p.unlink(), p.symlink_to(p.parent / "gone.json")), "is damaged: its profile.json is not a regular file"),
])
def test_a_registry_entry_that_cannot_be_read_is_named(tmp_path, capsys, damage, message):
    registry = SensorRegistry(tmp_path / "reg")
    for serial in ("SB-A", "SB-B"):
        registry.register(serial, accepted=True, run_dir=tmp_path, intrinsics={"width": 4, "height": 3},
                          camera_in_tcp=None, simulated=True, acceptance={"accepted": True, "a1": 0.9, "abs_rel": 0.01})
    damage(tmp_path / "reg" / "SB-A" / "profile.json")
    for argv in (["sensors", "--registry", tmp_path / "reg"], ["sensors", "--registry", tmp_path / "reg", "SB-A"]):
        err = _refused(capsys, argv, message)
        assert err.startswith(f"bubble: error: sensor registry entry {tmp_path / 'reg' / 'SB-A'} "), err
    with pytest.raises(InputError, match="sensor registry entry"):
        registry.check_entry("SB-A")
    registry.check_entry("SB-B")
    registry.check_entry("SB-NEW")


def test_registry_options_that_name_nothing(tmp_path, capsys):
    for argv in (["sensors", "--registry", ""],  # was: the current folder listed
                 ["commission", "--sim", "--out", str(tmp_path / "run"), "--registry", ""]):
        with pytest.raises(SystemExit) as usage_error:  # argparse's, one line on stderr
            main(argv)
        assert usage_error.value.code == 2
        assert capsys.readouterr().err == "bubble: error: argument --registry: is empty: name a file or folder\n"
    _refused(capsys, ["sensors", "--registry", tmp_path, ""], "sensor serial '' is not a valid registry name")  # was:
    # the whole listing
    assert main(["sensors", "--registry", str(tmp_path / "typo")]) == 0  # was: "0 sensors", no word of the folder
    assert capsys.readouterr().out == (f"registry {tmp_path / 'typo'}: 0 sensors (no such directory yet: the first "
                                       "commissioning creates it)\n")


def test_output_read_by_a_pipe_that_closes_early_is_no_traceback(synthetic_session):
    """``bubble info S.h5 | head -1``: the reader goes away after one line; the tool stops quietly."""
    import subprocess
    import sys
    from pathlib import Path

    proc = subprocess.Popen([sys.executable, "-m", "calibrate.cli", "info", str(synthetic_session)],
                            cwd=Path(__file__).resolve().parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # closed before the tool writes: its first write breaks the pipe
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait() == 141 and err == "", err  # 128 + SIGPIPE (was: 1, the code of a rejected sensor)


def test_the_json_result_is_written_though_the_reader_of_stdout_went_away(tmp_path, make_synthetic_session):
    """``bubble evaluate --json E.json ... | head``: was: the table's write broke the pipe before the
    JSON file was written, so it was lost, and the exit code was a rejected sensor's."""
    import subprocess
    import sys
    from pathlib import Path

    from trainer.model_dir import ModelMetadata, save_model
    from trainer.networks import build_network
    from trainer.preprocessing import InputGeometry, IRNormalization

    session = make_synthetic_session(tmp_path / "s.h5", height=48, width=64)
    save_model(tmp_path / "m", build_network("resnet", 0.125, 0.04, 0.12),
               ModelMetadata(arch="resnet", width=0.125, min_depth=0.04, max_depth=0.12,
                             geometry=InputGeometry(48, 64, 64, 64), normalization=IRNormalization(mean=7.0, std=1.5)))
    proc = subprocess.Popen([sys.executable, "-m", "calibrate.cli", "evaluate", "--model", str(tmp_path / "m"), "--data",
                             str(session), "--runtime", "torch", "--json", str(tmp_path / "r.json")],
                            cwd=Path(__file__).resolve().parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait() == 141 and err == "", err
    assert json.loads((tmp_path / "r.json").read_text())["written_by"] == "bubble evaluate"


def test_commission_on_a_real_bench_presses_the_objects_its_file_lists(tmp_path):
    """Was: `bubble commission --bench` pressed the four built-in objects whatever the bench file's
    `objects` listed (where no object is mounted too); `bubble collect --bench` took the file's."""
    from calibrate.cli import build_parser
    from calibrate.commission_cli import run_config
    from collect.bench import DEFAULT_OBJECTS

    bench = tmp_path / "b.yaml"
    bench.write_text("type: ur\nrobot_ip: 192.168.1.10\nserial_port: /dev/ttyACM0\nobjects: [box, mug]\n"
                     "home_pose: [0.45, 0.0, 0.25, 3.14159, 0, 0]\n")
    parse = build_parser().parse_args
    for command in ("commission", "tui"):  # the terminal UI takes a real bench too (was: --sim only)
        config = run_config(parse([command, "--bench", str(bench), "--out", "r"]), "r")
        assert config.objects == ("box", "mug") and not config.simulated and config.bench.robot_ip == "192.168.1.10"
        assert run_config(parse([command, "--bench", str(bench), "--objects", "mug", "--out", "r"]), "r").objects == ("mug",)
        assert run_config(parse([command, "--sim", "--out", "r"]), "r").objects == tuple(DEFAULT_OBJECTS)


def test_training_on_frames_without_valid_depth_says_so(tmp_path, make_synthetic_session, capsys):
    """A session whose ToF depth is all invalid (0): was "training diverged after 1 step (its depth on the
    validation frames is not finite) at learning rate 0.0002; lower --lr", as if the settings were wrong."""
    session = make_synthetic_session(tmp_path / "s.h5", height=48, width=64)
    with h5py.File(session, "a") as f:
        f[sf.FRAMES_DEPTH][...] = 0
    _refused(capsys, ["train", "--data", session, "--epochs", "1", "--width", "0.125", "--no-onnx",
                      "--out", tmp_path / "m"],
             "no training frame has ToF depth within the model's range 0.04-0.12 m: nothing to train on")
    assert not (tmp_path / "m" / "metadata.json").exists()


def test_evaluation_on_frames_without_valid_depth_says_so(tmp_path, make_synthetic_session, capsys):
    """The same check as the training's, with the same hint (the two were written twice)."""
    session = make_synthetic_session(tmp_path / "s.h5")
    with h5py.File(session, "a") as f:
        f[sf.FRAMES_DEPTH][...] = 0
    _refused(capsys, ["evaluate", "--model", "base", "--data", session],
             f"no contact frame of {session} has ToF depth within the model's range 0.04-0.12 m: nothing to compare "
             "the model with (check the camera's depth stream: bubble info)")
