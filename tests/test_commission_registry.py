"""Sensor registry: registration, history, listing, location."""

import errno
import fcntl
import json
import shutil
import threading
from contextlib import nullcontext
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from calibrate.sensor_registry import SensorRegistry, default_registry_dir
from collect.errors import InputError

INTR = {"fx": 120.0, "fy": 120.0, "cx": 111.5, "cy": 85.5, "width": 224, "height": 172}


def _model_dir(tmp_path, tag):
    d = tmp_path / f"model-{tag}"
    d.mkdir()
    (d / "model.json").write_text(json.dumps({"tag": tag}))
    return d


def test_accepted_then_rejected_keeps_accepted_model(tmp_path):
    reg = SensorRegistry(tmp_path / "reg")
    ref = {"depth_m": np.full((4, 5), 0.09, np.float32), "ir": np.ones((4, 5), np.float32)}
    acc = {"accepted": True, "a1": 0.97, "abs_rel": 0.01, "rmse": 0.0008, "checks": []}
    p1 = reg.register(
        "SB-1", accepted=True, run_dir=tmp_path / "run1", intrinsics=INTR, camera_in_tcp=[0, 0, -0.093, 0, 0, 0],
        simulated=True, acceptance=acc, model_dir=_model_dir(tmp_path, "a"), reference=ref,
    )
    assert p1.status == "accepted" and p1.model_dir is not None
    assert json.loads((p1.model_dir / "model.json").read_text())["tag"] == "a"
    rej = {"accepted": False, "checks": []}
    p2 = reg.register(
        "SB-1", accepted=False, run_dir=tmp_path / "run2", intrinsics=INTR, camera_in_tcp=None, simulated=True,
        acceptance=rej, reason="leak", model_dir=_model_dir(tmp_path, "b"),
    )
    assert p2.status == "rejected" and p2.data["last_reason"] == "leak"
    assert p2.data["camera_in_tcp"] == [0, 0, -0.093, 0, 0, 0]  # the kept model's camera (was: the rejected run's)
    assert json.loads((p2.model_dir / "model.json").read_text())["tag"] == "a"
    assert [h["accepted"] for h in p2.history] == [True, False]
    assert p2.history[0]["a1"] == 0.97
    np.testing.assert_array_equal(reg.reference("SB-1")["depth_m"], ref["depth_m"])
    assert json.loads((p2.path / "acceptance.json").read_text()) == rej


def test_an_older_commissioning_registered_later_only_joins_the_history(tmp_path):
    """An old run folder registered in another registry at its verdict's time, after a newer run: was
    the newer model replaced by the old one, the status and last acceptance turned back, and the
    history out of order."""
    reg = SensorRegistry(tmp_path / "reg")
    day = [datetime(2026, 11, d, 9, 30, tzinfo=timezone.utc) for d in (1, 2, 3)]

    def register(accepted, tag, when):
        acceptance = {"accepted": accepted, "a1": 0.97, "checks": [], "tag": tag}
        return reg.register("SB-1", accepted=accepted, run_dir=tmp_path / f"run-{tag}", intrinsics=INTR,
                            camera_in_tcp=None, simulated=True, acceptance=acceptance, entry_id=tag,
                            model_dir=_model_dir(tmp_path, tag) if accepted else None,
                            reference={"depth_m": np.full((4, 5), when.day, np.float32)} if accepted else None,
                            when=when, reason="" if accepted else "leak")

    register(True, "new", day[1])
    for accepted, tag, when in ((False, "old-rejected", day[0]), (True, "old-accepted", day[0])):
        profile = register(accepted, tag, when)
        assert profile.status == "accepted" and profile.data["last_commissioned"] == day[1].isoformat()
        assert profile.data["accepted_at"] == day[1].isoformat()
        assert json.loads((profile.model_dir / "model.json").read_text())["tag"] == "new"
        assert reg.reference("SB-1")["depth_m"][0, 0] == 2
        assert json.loads((profile.path / "acceptance.json").read_text())["tag"] == "new"
    assert [h["id"] for h in profile.history] == ["old-rejected", "old-accepted", "new"]
    profile = register(False, "newest", day[2])  # a newer one still updates the status, not the kept model
    assert profile.status == "rejected" and json.loads((profile.model_dir / "model.json").read_text())["tag"] == "new"
    assert [h["id"] for h in profile.history][-1] == "newest"
    naive = register(False, "naive", datetime(2026, 11, 4, 9, 30))  # no offset: this computer's time, stored in UTC
    assert naive.history[-1]["time"].endswith("+00:00")


def test_a_profile_time_without_its_offset_is_refused(tmp_path, capsys):
    reg = SensorRegistry(tmp_path / "reg")
    profile = reg.register("SB-1", accepted=False, run_dir=tmp_path / "run", intrinsics=INTR, camera_in_tcp=None,
                           simulated=True, acceptance={"accepted": False, "checks": []}, reason="leak")
    data = json.loads((profile.path / "profile.json").read_text())
    data["history"][0]["time"] = "2026-11-01T09:30:00"
    (profile.path / "profile.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"'history\[0\]\.time' must be an ISO 8601 time with its UTC offset"):
        reg.get("SB-1")


def test_listing_lookup_and_bad_names(tmp_path):
    reg = SensorRegistry(tmp_path / "reg")
    assert reg.survey().profiles == []
    for serial in ("SB-B", "SB-A"):
        reg.register(serial, accepted=False, run_dir=tmp_path, intrinsics=INTR, camera_in_tcp=None,
                     simulated=True, acceptance={"accepted": False})
    assert [p.serial for p in reg.survey().profiles] == ["SB-A", "SB-B"]
    stray = tmp_path / "reg" / "copy of SB-A\n"  # no sensor serial: not listed (its newline broke the table)
    stray.mkdir()
    (stray / "profile.json").write_text((tmp_path / "reg" / "SB-A" / "profile.json").read_text())
    assert [p.serial for p in reg.survey().profiles] == ["SB-A", "SB-B"]
    with pytest.raises(InputError, match="not in the registry"):
        reg.get("SB-C")
    with pytest.raises(InputError, match="valid registry name"):
        reg.get("../etc")
    with pytest.raises(InputError, match="no accepted reference"):
        reg.reference("SB-A")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        SensorRegistry(tmp_path / "file")


def test_two_commissionings_of_one_sensor_finishing_together_are_both_registered(tmp_path, monkeypatch):
    """The second registration waits for the first (was: it ran while the first had read the profile
    and not yet written it, and the first then wrote the history without the second's entry; with
    models, both staged them in one ``model.new`` and one failed with FileExistsError)."""
    reg = SensorRegistry(tmp_path / "reg")
    acc = {"accepted": True, "a1": 0.97, "abs_rel": 0.01, "rmse": 0.0008, "checks": []}

    def register(tag):
        return reg.register("SB-1", accepted=True, run_dir=tmp_path / f"run-{tag}", intrinsics=INTR,
                            camera_in_tcp=None, simulated=True, acceptance=acc, model_dir=_model_dir(tmp_path, tag))

    register("0")
    first_read, first_may_go, second_ran = threading.Event(), threading.Event(), threading.Event()
    read_profile, flock = SensorRegistry._read_profile, fcntl.flock

    def read_profile_then_pause(self, sdir):  # the first registration: between reading and writing the profile
        profile = read_profile(self, sdir)
        if threading.current_thread().name == "first":
            first_read.set()
            first_may_go.wait()
        return profile

    def noted_flock(fd, operation):  # the second registration: about to wait for the first
        if threading.current_thread().name == "second":
            second_ran.set()
        return flock(fd, operation)

    monkeypatch.setattr(SensorRegistry, "_read_profile", read_profile_then_pause)
    monkeypatch.setattr(fcntl, "flock", noted_flock)
    errors = []

    def run(tag, done: threading.Event):
        try:
            register(tag)
        except Exception as err:  # noqa: BLE001 - reported by the assertion below
            errors.append(err)
        finally:
            done.set()

    first = threading.Thread(target=run, args=("a", threading.Event()), name="first")
    second = threading.Thread(target=run, args=("b", second_ran), name="second")
    first.start()
    first_read.wait()
    second.start()
    second_ran.wait()  # finished (without a lock) or waiting for the first's
    first_may_go.set()
    first.join()
    second.join()
    assert errors == []
    profile = reg.get("SB-1")
    assert [Path(h["run_dir"]).name for h in profile.history] == ["run-0", "run-a", "run-b"]
    assert json.loads((profile.model_dir / "model.json").read_text())["tag"] == "b"
    assert not (profile.path / "model.new").exists()


def test_registering_on_a_file_system_without_folder_locks(tmp_path, monkeypatch):
    """NFS cannot lock a folder (its flock needs a file open for writing): the entry is written
    unlocked, as before the lock, instead of failing at the end of a commissioning."""
    def no_folder_locks(fd, operation):
        raise OSError(errno.EBADF, "Bad file descriptor")

    monkeypatch.setattr(fcntl, "flock", no_folder_locks)
    reg = SensorRegistry(tmp_path / "reg")
    reg.register("SB-1", accepted=False, run_dir=tmp_path, intrinsics=INTR, camera_in_tcp=None, simulated=True,
                 acceptance={"accepted": False})
    assert [h["accepted"] for h in reg.get("SB-1").history] == [False]


def test_an_unwritable_registry_is_refused_naming_the_file_the_run_would_write(tmp_path, capsys):
    from calibrate.cli import main

    plain = tmp_path / "plain"
    plain.write_text("not a folder")
    run = tmp_path / "run"
    # was: "cannot write .../reg/profile.json", a file the registry never writes (then: cannot write
    # .../reg/<serial>/profile.json; now the registry itself, before any file)
    assert main(["commission", "--sim", "--quiet", "--out", str(run), "--registry", str(plain / "reg")]) == 2
    err = capsys.readouterr().err
    assert err == f"bubble: error: sensor registry {plain}/reg cannot be made: {plain} is a file\n"
    assert not run.exists()


def test_an_unwritable_registry_of_the_environment_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    """Was: checked for --registry only; $BUBBLE_REGISTRY under a file failed the run at its end, a
    traceback and exit 1 ("rejected")."""
    from calibrate.cli import main

    plain = tmp_path / "plain"
    plain.write_text("not a folder")
    monkeypatch.setenv("BUBBLE_REGISTRY", str(plain / "reg"))
    run = tmp_path / "run"
    assert main(["commission", "--sim", "--quiet", "--out", str(run)]) == 2
    assert capsys.readouterr().err == f"bubble: error: sensor registry {plain}/reg cannot be made: {plain} is a file\n"
    assert not run.exists()


def test_a_real_cameras_distortion_is_registered_and_read_back(tmp_path):
    """The OAK camera's intrinsics carry a ``distortion`` list. Was: written, then refused as corrupt by
    the next reader (``bubble sensors`` exit 2, every later commissioning of the sensor failed)."""
    reg = SensorRegistry(tmp_path / "reg")
    intrinsics = {**INTR, "distortion": [0.1, -0.02, 0.0, 0.0, 0.003]}
    for accepted in (True, False):
        reg.register("SB-HW1", accepted=accepted, run_dir=tmp_path, intrinsics=intrinsics, camera_in_tcp=None,
                     simulated=False, acceptance={"accepted": accepted})
    assert reg.get("SB-HW1").data["intrinsics"]["distortion"] == intrinsics["distortion"]
    with pytest.raises(InputError, match="'intrinsics' must be an object of finite numbers"):  # not written
        reg.register("SB-HW2", accepted=False, run_dir=tmp_path, intrinsics={**INTR, "distortion": [float("nan")]},
                     camera_in_tcp=None, simulated=False, acceptance={"accepted": False})
    assert not (tmp_path / "reg" / "SB-HW2" / "profile.json").exists()


def test_sensors_lists_a_deleted_model_and_run_folder_and_a_file_named_as_a_sensor(tmp_path, capsys):
    """Was: a deleted ``model/`` listed as "no", as for a sensor never accepted; a deleted run folder
    shown as any other; a file named as a serial left out without a word; a rejected sensor shown
    with its earlier accepted run's metrics in columns of no stated run."""
    from calibrate.cli import main

    reg = SensorRegistry(tmp_path / "reg")
    run = tmp_path / "run"
    run.mkdir()
    reg.register("SB-A", accepted=True, run_dir=run, intrinsics=INTR, camera_in_tcp=None, simulated=True,
                 acceptance={"accepted": True, "a1": 0.97, "abs_rel": 0.0123}, model_dir=_model_dir(tmp_path, "a"),
                 reference={"depth_m": np.zeros((2, 2), np.float32)})
    reg.register("SB-B", accepted=False, run_dir=run, intrinsics=INTR, camera_in_tcp=None, simulated=True,
                 acceptance={"accepted": False, "a1": 0.5, "abs_rel": 0.2})
    shutil.rmtree(tmp_path / "reg" / "SB-A" / "model")
    run.rmdir()
    assert main(["sensors", "--registry", str(tmp_path / "reg")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["serial", "status", "last", "commissioned", "runs", "model", "abs_rel", "a1"]
    assert lines[2].split()[-3:] == ["MISSING", "0.0123", "0.970"] and lines[3].split()[-3:] == ["no", "-", "-"]
    assert main(["sensors", "--registry", str(tmp_path / "reg"), "SB-A"]) == 0
    out = capsys.readouterr().out
    assert "MISSING    model/: profile.json names it" in out and f"{run} (run folder deleted)" in out
    (tmp_path / "reg" / "SB-C").write_text("not a sensor folder")
    assert main(["sensors", "--registry", str(tmp_path / "reg")]) == 2
    out, err = capsys.readouterr()
    assert "SB-A" in out and err == f"bubble: error: sensor registry entry {tmp_path / 'reg' / 'SB-C'} is not a directory\n"


def test_a_model_folder_the_profile_does_not_name_is_no_model(tmp_path, capsys):
    """A registration killed between storing the accepted model and writing the profile leaves a rejected
    sensor's folder with a ``model/`` (was: listed as a kept model, and ``bubble sensors SERIAL`` a
    KeyError traceback: no ``accepted_at``)."""
    from calibrate.cli import main

    reg = SensorRegistry(tmp_path / "reg")
    reg.register("SB-C", accepted=False, run_dir=tmp_path, intrinsics=INTR, camera_in_tcp=None, simulated=True,
                 acceptance={"accepted": False, "a1": 0.5, "abs_rel": 0.2})
    shutil.copytree(_model_dir(tmp_path, "a"), tmp_path / "reg" / "SB-C" / "model")
    assert main(["sensors", "--registry", str(tmp_path / "reg")]) == 0
    assert capsys.readouterr().out.splitlines()[2].split()[-3:] == ["no", "-", "-"]
    assert main(["sensors", "--registry", str(tmp_path / "reg"), "SB-C"]) == 0
    out = capsys.readouterr().out
    assert "  model      -\n" in out and "MISSING" not in out


def test_location_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("BUBBLE_REGISTRY", str(tmp_path / "envreg"))
    assert default_registry_dir() == tmp_path / "envreg"
    assert SensorRegistry().root == tmp_path / "envreg"
    monkeypatch.delenv("BUBBLE_REGISTRY")
    assert default_registry_dir().name == "sensors" and "bubble-bench" in str(default_registry_dir())


def test_a_registration_that_fails_midway_keeps_the_accepted_model_and_reference(tmp_path, monkeypatch):
    """A disk filling up while the new reference is written: the earlier accepted model and
    reference stay whole and readable, and no temporary file is left (was: the model already
    replaced, and reference.npz written in place, half of it left by the failure)."""
    reg = SensorRegistry(tmp_path / "reg")
    ref = {"depth_m": np.full((4, 5), 0.09, np.float32)}
    acc = {"accepted": True, "a1": 0.97, "checks": []}
    reg.register("SB-1", accepted=True, run_dir=tmp_path / "run1", intrinsics=INTR, camera_in_tcp=None,
                 simulated=True, acceptance=acc, model_dir=_model_dir(tmp_path, "a"), reference=ref)
    savez = np.savez_compressed

    def disk_full(file, **arrays):  # file: a path or an open file
        with open(file, "r+b") if isinstance(file, (str, Path)) else nullcontext(file) as f:
            savez(f, **arrays)
            f.truncate(10)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", disk_full)
    with pytest.raises(OSError, match="No space left"):
        reg.register("SB-1", accepted=True, run_dir=tmp_path / "run2", intrinsics=INTR, camera_in_tcp=None,
                     simulated=True, acceptance=acc, model_dir=_model_dir(tmp_path, "b"),
                     reference={"depth_m": np.zeros((4, 5), np.float32)})
    np.testing.assert_array_equal(reg.reference("SB-1")["depth_m"], ref["depth_m"])
    assert json.loads((reg.get("SB-1").model_dir / "model.json").read_text())["tag"] == "a"
    assert sorted(p.name for p in (tmp_path / "reg" / "SB-1").iterdir()) == [
        "acceptance.json", "model", "profile.json", "reference.npz"]
    assert [h["run_dir"] for h in reg.get("SB-1").history] == [str((tmp_path / "run1").resolve())]


def test_registry_locations_that_cannot_be_read_or_made_are_one_line(tmp_path, monkeypatch, capsys):
    """Was: a PermissionError traceback for a registry (or one sensor's folder) that cannot be read,
    "no such directory yet: the first commissioning creates it" for one under a file, and a folder
    named by a space for a blank $BUBBLE_REGISTRY."""
    from calibrate.cli import main

    reg = SensorRegistry(tmp_path / "reg")
    for serial in ("SB-A", "SB-B"):
        reg.register(serial, accepted=False, run_dir=tmp_path, intrinsics=INTR, camera_in_tcp=None, simulated=True,
                     acceptance={"accepted": False})
    real_is_dir = Path.is_dir

    def sb_a_locked(path):  # what stat says of a folder inside one without the search permission
        if path.parent.name == "SB-A" or path.name == "SB-A":
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_is_dir(path)

    monkeypatch.setattr(Path, "is_dir", sb_a_locked)
    assert main(["sensors", "--registry", str(tmp_path / "reg")]) == 2
    out, err = capsys.readouterr()
    assert "SB-B" in out and err == (f"bubble: error: sensor registry entry {tmp_path / 'reg' / 'SB-A'} cannot be read: "
                                     "Permission denied\n")
    monkeypatch.setattr(Path, "iterdir", lambda path: (_ for _ in ()).throw(PermissionError(errno.EACCES, "Permission denied")))
    assert main(["sensors", "--registry", str(tmp_path / "reg")]) == 2
    assert capsys.readouterr().err == f"bubble: error: cannot read the sensor registry {tmp_path / 'reg'}: Permission denied\n"
    monkeypatch.undo()
    real_exists = Path.exists

    def locked_above(path):  # what stat says of a path inside a folder without the search permission
        if tmp_path / "locked" in (path, *path.parents):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_exists(path)

    monkeypatch.setattr(Path, "exists", locked_above)  # was: a traceback from the registry's constructor, exit 1
    assert main(["sensors", "--registry", str(tmp_path / "locked" / "reg")]) == 2
    assert capsys.readouterr().err == (f"bubble: error: cannot read the sensor registry {tmp_path / 'locked' / 'reg'}: "
                                       "Permission denied\n")
    monkeypatch.undo()
    (tmp_path / "plain").write_text("x")
    assert main(["sensors", "--registry", str(tmp_path / "plain" / "reg")]) == 2
    assert capsys.readouterr().err == (f"bubble: error: sensor registry {tmp_path / 'plain' / 'reg'} cannot be made: "
                                       f"{tmp_path / 'plain'} is a file\n")
    monkeypatch.setenv("BUBBLE_REGISTRY", " ")
    assert main(["sensors"]) == 2
    assert capsys.readouterr().err == "bubble: error: $BUBBLE_REGISTRY is blank: name the registry folder, or unset it\n"
