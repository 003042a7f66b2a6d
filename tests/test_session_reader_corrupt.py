"""Sessions with damaged attributes or datasets (as a fuzzer made them) are refused when opened:
``bubble info`` prints one ``bubble: error:`` line naming what is wrong, exits 2 and leaves the file
as it was (was: tracebacks, or a silent wrong result later)."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from calibrate.cli import main
from collect.errors import InputError
from collect.session_reader import Session
from collect import session_format as sf
from conftest import make_synthetic_session


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    """A valid simulated session: objects 'mug', 'box', 1 pose each, 32x24 px (32 frames)."""
    return make_synthetic_session(tmp_path_factory.mktemp("good") / "good.h5", poses_per_object=1, height=24, width=32)


def _set_attr(name, value):
    return lambda f: f.attrs.__setitem__(name, value)


def _intrinsics(**changes):
    """An edit that changes fields of the root attr 'intrinsics' (JSON)."""
    return lambda f: f.attrs.__setitem__(sf.ATTR_INTRINSICS, json.dumps({**json.loads(f.attrs[sf.ATTR_INTRINSICS]),
                                                                         **changes}))


def _depth_group(f):
    del f[sf.FRAMES_DEPTH]
    f.create_group(sf.FRAMES_DEPTH)


def _replace(name, values):
    """An edit that replaces dataset ``name`` by ``values(old)`` (numpy data, or an ``h5py.Empty``)."""
    def edit(f):
        old = f[name][()]
        del f[name]
        f.create_dataset(name, data=values(old))
    return edit


CASES = {
    "intrinsics-a-list": (_set_attr(sf.ATTR_INTRINSICS, "[1,2]"),
                          "root attr 'intrinsics' must be a JSON object with fx, fy, cx, cy, width, height, got [1, 2]"),
    "intrinsics-not-json": (_set_attr(sf.ATTR_INTRINSICS, "{"), "root attr 'intrinsics' is not valid JSON"),
    "intrinsics-without-cy": (lambda f: f.attrs.__setitem__(sf.ATTR_INTRINSICS, '{"fx": 1, "fy": 1, "cx": 1}'),
                              "root attr 'intrinsics' must be a JSON object with fx, fy, cx, cy, width, height"),
    "fx-text": (_intrinsics(fx="a"), "root attr 'intrinsics' field 'fx' must be a finite number > 0 (px), got 'a'"),
    "fx-fy-zero": (_intrinsics(fx=0, fy=0), "root attr 'intrinsics' field 'fx' must be a finite number > 0"),
    "fy-nan": (_intrinsics(fy=float("nan")), "root attr 'intrinsics' field 'fy' must be a finite number > 0 (px), got nan"),
    "cx-inf": (_intrinsics(cx=float("inf")), "root attr 'intrinsics' field 'cx' must be a finite number (px), got inf"),
    "width-float": (_intrinsics(width=32.0), "root attr 'intrinsics' field 'width' must be a positive integer (px)"),
    "distortion-text": (_intrinsics(distortion=[0.1, "x"]),
                        "root attr 'intrinsics' field 'distortion' must be a list of finite numbers"),
    "format-version-array": (_set_attr(sf.ATTR_FORMAT_VERSION, np.array([1, 1])),
                             "root attr 'format_version' must be an integer, got [1, 1]"),
    "format-version-1.5": (_set_attr(sf.ATTR_FORMAT_VERSION, 1.5), "root attr 'format_version' must be an integer, got 1.5"),
    "format-version-missing": (lambda f: f.attrs.__delitem__(sf.ATTR_FORMAT_VERSION),
                               "root attr 'format_version' is missing"),
    "camera-in-tcp-short": (_set_attr(sf.ATTR_CAMERA_IN_TCP, "[1, 2]"),
                            "root attr 'camera_in_tcp' must be a JSON list of 6 finite numbers"),
    "camera-in-tcp-nan": (_set_attr(sf.ATTR_CAMERA_IN_TCP, "[0, 0, NaN, 0, 0, 0]"),
                          "root attr 'camera_in_tcp' must be a JSON list of 6 finite numbers"),
    "collection-plan-not-json": (_set_attr(sf.ATTR_COLLECTION_PLAN, "{"), "root attr 'collection_plan' is not valid JSON"),
    "collection-plan-a-list": (_set_attr(sf.ATTR_COLLECTION_PLAN, "[1]"),
                               "root attr 'collection_plan' must be a JSON object, got [1]"),
    "sensor-spec-not-json": (_set_attr(sf.ATTR_SENSOR_SPEC, "nope"), "root attr 'sensor_spec' is not valid JSON"),
    "sensor-spec-a-number": (_set_attr(sf.ATTR_SENSOR_SPEC, "7"), "root attr 'sensor_spec' must be a JSON object, got 7"),
    "serial-a-number": (_set_attr(sf.ATTR_SENSOR_SERIAL, 7), "root attr 'sensor_serial' must be text, got 7"),
    "simulated-text": (_set_attr(sf.ATTR_SIMULATED, "no"), "root attr 'simulated' must be a boolean, got 'no'"),
    "simulated-an-array": (_set_attr(sf.ATTR_SIMULATED, np.array([1, 0])), "root attr 'simulated' must be a boolean"),
    "depth-a-group": (_depth_group, "corrupt session, frames/depth is not a dataset"),
    "depth-unit-nan": (lambda f: f[sf.FRAMES_DEPTH].attrs.__setitem__(sf.ATTR_UNIT_M, np.nan),
                       "frames/depth attr 'unit_m' must be a number of metres in (0, 0.01], got nan"),
    "depth-unit-zero": (lambda f: f[sf.FRAMES_DEPTH].attrs.__setitem__(sf.ATTR_UNIT_M, 0.0),
                        "frames/depth attr 'unit_m' must be a number of metres in (0, 0.01], got 0.0"),
    "depth-unit-huge": (lambda f: f[sf.FRAMES_DEPTH].attrs.__setitem__(sf.ATTR_UNIT_M, 1e300),
                        "frames/depth attr 'unit_m' must be a number of metres in (0, 0.01], got 1e+300"),
    "depth-empty": (_replace(sf.FRAMES_DEPTH, lambda old: h5py.Empty("<u2")),
                    "corrupt session, frames/depth must hold (N,H,W) unsigned integers, got shape None"),
    "depth-floats": (_replace(sf.FRAMES_DEPTH, lambda old: old.astype(np.float32)),
                     "corrupt session, frames/depth must hold (N,H,W) unsigned integers"),
    "seq-text": (_replace(sf.FRAMES_SEQ, lambda old: np.array([b"x"] * len(old))),
                 "corrupt session, frames/seq must hold (N,) integers"),
    "tcp-pose-5-columns": (_replace(sf.FRAMES_TCP_POSE, lambda old: old[:, :5]),
                           "corrupt session, frames/tcp_pose must hold (N,6) floats, got shape (32, 5)"),
    "ir-cut-short": (lambda f: f[sf.FRAMES_IR].resize(5, axis=0),
                     "corrupt session, frames/ir holds 5 of the 32 rows of frames/depth (they are written together)"),
    "pressure-cut-short": (lambda f: f[sf.PRESSURE_HPA].resize(1, axis=0), "corrupt session, pressure/hpa holds 1 of the"),
    "object-names-repeated": (lambda f: f[sf.OBJECTS_NAME].__setitem__(1, f[sf.OBJECTS_NAME][0]),
                              "corrupt session, object 'mug' is listed twice in objects/name"),
    "object-names-numbers": (_replace(sf.OBJECTS_NAME, lambda old: np.arange(len(old))),
                             "corrupt session, objects/name must hold (O,) strings, got shape (2,) of int64"),
    "fixture-pose-text": (_replace(sf.OBJECTS_FIXTURE_POSE, lambda old: np.array([b"x"] * len(old))),
                          "corrupt session, objects/fixture_pose must hold (O,6) floats, got shape (2,) of |S1"),
    "fixture-pose-5-columns": (_replace(sf.OBJECTS_FIXTURE_POSE, lambda old: old[:, :5]),
                               "corrupt session, objects/fixture_pose must hold (O,6) floats, got shape (2, 5)"),
    "primitive-numbers": (_replace(sf.OBJECTS_PRIMITIVE, lambda old: np.zeros(len(old))),
                          "corrupt session, objects/primitive must hold (O,) strings"),
    # was: "corrupt or truncated session (char 1)"
    "primitive-not-json": (_replace(sf.OBJECTS_PRIMITIVE, lambda old: np.array([b"{x", *old[1:]])),
                           "corrupt session, objects/primitive entry of object 'mug' is not valid JSON (Expecting "
                           "property name enclosed in double quotes)"),
    "primitive-a-list": (_replace(sf.OBJECTS_PRIMITIVE, lambda old: np.array([old[0], b"[1]"])),
                         "objects/primitive entry of object 'box' must be a JSON object, got [1]"),
    # was: "corrupt or truncated session () or a.all()"
    "format-an-array": (_set_attr(sf.ATTR_FORMAT, np.array([1, 2])),
                        "root attr 'format' must be the text 'bubble-session', got [1, 2]"),
    # was: opened, and `bubble evaluate` failed naming neither the file nor the dataset
    "true-depth-another-size": (_replace(sf.SIM_TRUE_DEPTH, lambda old: old[:, :-1]),
                                "corrupt session, frames/ir and sim/true_depth differ in size (32x24 and 32x23 px)"),
    "mesh-a-dataset": (lambda f: (f.__delitem__(f"{sf.OBJECTS_MESH_GROUP}/box"),
                                  f.create_dataset(f"{sf.OBJECTS_MESH_GROUP}/box", data=np.zeros(3))),
                       "corrupt session, objects/meshes/box is not a group"),
    "mesh-without-faces": (lambda f: f.__delitem__(f"{sf.OBJECTS_MESH_GROUP}/box/faces"),
                           "corrupt session, missing objects/meshes/box/faces"),
    "mesh-faces-floats": (_replace(f"{sf.OBJECTS_MESH_GROUP}/box/faces", lambda old: old.astype(np.float32)),
                          "corrupt session, objects/meshes/box/faces must hold (F,3) integers, got shape (12, 3) of float32"),
    "mesh-vertices-2-columns": (_replace(f"{sf.OBJECTS_MESH_GROUP}/mug/vertices", lambda old: old[:, :2]),
                                "corrupt session, objects/meshes/mug/vertices must hold (V,3) floats, got shape (8, 2)"),
    "mesh-vertices-cut-short": (_replace(f"{sf.OBJECTS_MESH_GROUP}/box/vertices", lambda old: old[:-1]),
                                "corrupt session, objects/meshes/box/faces names vertices that "
                                "objects/meshes/box/vertices does not hold (7 vertices)"),
    "mesh-face-index-negative": (lambda f: f[f"{sf.OBJECTS_MESH_GROUP}/box/faces"].__setitem__((0, 0), -1),
                                 "corrupt session, objects/meshes/box/faces names vertices that"),
    # was: read as a good session, and a traceback from bubble pose's per-pose random seed
    "pose-id-below-minus-one": (lambda f: f[sf.FRAMES_POSE_ID].__setitem__(0, -5),
                                "corrupt session, frames/pose_id below -1"),
    # the integer columns checked as stored (was: narrowed first: phase 256 read as free, object 65535
    # as none, pose_id 2^32 as 0, a seq near 2^64 negative)
    "phase-256": (_replace(sf.FRAMES_PHASE, lambda old: np.where(np.arange(len(old)) == 4, 256, old.astype(np.uint16))),
                  "corrupt session, unknown phase value at frame 4"),
    "object-65535": (_replace(sf.FRAMES_OBJECT, lambda old: np.full(len(old), 65535, np.uint16)),
                     "corrupt session, frames/object out of range"),
    "pose-id-2^32": (_replace(sf.FRAMES_POSE_ID, lambda old: np.where(old >= 0, 2**32, old.astype(np.int64))),
                     "corrupt session, frames/pose_id above 2^31-1"),
    "seq-near-2^64": (_replace(sf.FRAMES_SEQ, lambda old: np.arange(len(old), dtype=np.uint64) + np.uint64(2**64 - 5)),
                      "corrupt session, frames/seq holds values above 2^63-1"),
    # the depth unit: was the recorder's own taken when the file did not say, or ignored when it disagreed
    "depth-unit-unsaid": (lambda f: (f[sf.FRAMES_DEPTH].attrs.__delitem__(sf.ATTR_UNIT_M),
                                     f[sf.FRAMES_DEPTH].attrs.__delitem__(sf.ATTR_UNIT)),
                          "frames/depth does not say its unit (attr 'unit_m', metres per count, or 'unit', a length "
                          "such as '1e-05 m'; found None)"),
    "depth-unit-text-disagrees": (lambda f: f[sf.FRAMES_DEPTH].attrs.__setitem__(sf.ATTR_UNIT, "1e-04 m"),
                                  "corrupt session, frames/depth attrs 'unit_m' (1e-05 m) and 'unit' ('1e-04 m') disagree"),
    # the file's own phase names, each with its own value (a renumbering is read: test_session_format)
    "phase-enum-a-name-twice": (lambda f: f[sf.FRAMES_PHASE].attrs.__setitem__(sf.ATTR_PHASE_ENUM, json.dumps(
                                    {**sf.PHASES, "press": sf.PHASES["hold"]})),
                                "frames/phase attr 'enum' must be the phases free, approach, press, hold, retract, "
                                "each with its own value 0-255"),
    "phase-enum-unknown-name": (lambda f: f[sf.FRAMES_PHASE].attrs.__setitem__(sf.ATTR_PHASE_ENUM, json.dumps(
                                    {**{k: v for k, v in sf.PHASES.items() if k != "hold"}, "dwell": 9})),
                                "frames/phase attr 'enum' must be the phases"),
    # was: "corrupt or truncated session () or a.all()"
    "phase-enum-an-array": (lambda f: f[sf.FRAMES_PHASE].attrs.__setitem__(sf.ATTR_PHASE_ENUM, np.array([1, 2])),
                            "frames/phase attr 'enum' must be the phases"),
    # renumbered, but a frame holds a value the file's enum does not name
    "phase-outside-its-enum": (lambda f: f[sf.FRAMES_PHASE].attrs.__setitem__(sf.ATTR_PHASE_ENUM, json.dumps(
                                   {name: value + 10 for name, value in sf.PHASES.items()})),
                               "corrupt session, unknown phase value at frame 0"),
    "depth-invalid-65535": (lambda f: f[sf.FRAMES_DEPTH].attrs.__setitem__(sf.ATTR_INVALID, 65535),
                            "frames/depth attr 'invalid' must be 0 (this software reads 0 as no depth), got 65535"),
}


def test_a_file_that_numbers_its_phases_otherwise_is_read_by_its_enum(tmp_path, small_session, capsys):
    """DESIGN.md fixes the phase names ("enum in attrs"), not their numbers: a writer that numbers them
    otherwise, its enum saying so, is read as it says (was: refused, "must be the format's phases")."""
    from collect.session_reader import Session

    path = tmp_path / "renumbered.h5"
    shutil.copyfile(small_session, path)
    theirs = {name: 10 + 4 - value for name, value in sf.PHASES.items()}  # approach 13 ... retract 10, free 14
    with h5py.File(path, "a") as f:
        ours = f[sf.FRAMES_PHASE][()]
        del f[sf.FRAMES_PHASE]
        f[sf.FRAMES_PHASE] = np.array([10 + 4 - v for v in ours], np.uint8)
        f[sf.FRAMES_PHASE].attrs[sf.ATTR_PHASE_ENUM] = json.dumps(theirs)
    with Session.open(small_session) as original, Session.open(path) as renumbered:
        everything = np.arange(original.n_frames)
        assert list(renumbered.phase_name(everything)) == list(original.phase_name(everything))
        assert len(renumbered.select(phase="hold")) == len(original.select(phase="hold")) > 0
        metadata = dict(sensor_serial=original.sensor_serial, intrinsics=original.intrinsics,
                        camera_in_tcp=original.camera_in_tcp, simulated=original.simulated, objects=[])
    assert main(["info", str(path)]) == 0
    from collect.session_writer import resume_progress

    with pytest.raises(InputError, match="numbers the phases otherwise than this software writes them"):
        resume_progress(path, **metadata)  # its frames and a resume's would mix two numberings


@pytest.mark.parametrize("edit, needle", list(CASES.values()), ids=list(CASES))
def test_info_refuses_a_damaged_session_with_one_line(tmp_path, small_session, capsys, edit, needle):
    path = tmp_path / "bad.h5"
    shutil.copyfile(small_session, path)
    with h5py.File(path, "a") as f:
        edit(f)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bubble: error: {path}: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert needle in err, err
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest


@pytest.mark.parametrize("idx", [[3, 9, 17], slice(5, 20), 17], ids=["list", "slice", "int"])
def test_nan_in_true_depth_names_its_frame_row(tmp_path, small_session, idx):
    """The row named is the dataset's, not the position among the frames read (was: row 1 for [3, 9, 17])."""
    path = tmp_path / "nan.h5"
    shutil.copyfile(small_session, path)
    with h5py.File(path, "a") as f:
        f[sf.SIM_TRUE_DEPTH][17, 4, 6] = np.nan
    with Session.open(path) as session, pytest.raises(InputError, match=r"NaN/inf in sim/true_depth \(row 17\)$"):
        session.true_depth(idx)


@pytest.mark.parametrize("stream", [sf.PRESSURE_HPA, sf.ARM_TCP_POSE])
def test_nan_in_a_stream_is_refused_by_every_command_that_reads_the_file(tmp_path, small_session, capsys, stream):
    """Was: refused by bubble info and a resume only; evaluate (train, pose) took the file, exit 0."""
    path = tmp_path / "nan.h5"
    shutil.copy(small_session, path)
    with h5py.File(path, "r+") as f:
        f[stream][3] = np.nan
    capsys.readouterr()
    assert main(["evaluate", "--model", "base", "--data", str(path)]) == 2
    assert capsys.readouterr().err == f"bubble: error: {path}: corrupt session, NaN/inf in {stream} (row 3)\n"


def test_a_depth_unit_given_only_as_text_is_read(tmp_path, small_session):
    """The format's contract names the unit in attrs ("e.g. 1e-4 m"): a file that gives only that text
    is read in its unit (was: read in the recorder's 1e-5 m, ten times too shallow)."""
    path = tmp_path / "text_unit.h5"
    shutil.copyfile(small_session, path)
    with Session.open(path) as s:
        raw, metres = s.depth_raw(3), s.depth_m(3)
    with h5py.File(path, "a") as f:
        del f[sf.FRAMES_DEPTH].attrs[sf.ATTR_UNIT_M]
        f[sf.FRAMES_DEPTH].attrs[sf.ATTR_UNIT] = "0.01 mm"
    with Session.open(path) as s:
        assert s.depth_unit_m == pytest.approx(1e-5) and np.array_equal(s.depth_m(3), metres)
    with h5py.File(path, "a") as f:
        f[sf.FRAMES_DEPTH].attrs[sf.ATTR_UNIT] = "1e-4 m"
    with Session.open(path) as s:
        assert s.depth_unit_m == pytest.approx(1e-4)
        assert np.allclose(s.depth_m(3), raw.astype(np.float32) * np.float32(1e-4))


def test_a_session_without_camera_in_tcp_is_read_and_refused_only_by_what_needs_it(tmp_path, small_session, capsys):
    """camera_in_tcp is not in the format's contract: info reads such a file (was: refused), the pose
    check, which needs it, says so in one line."""
    path = tmp_path / "no_camera_pose.h5"
    shutil.copyfile(small_session, path)
    with h5py.File(path, "a") as f:
        del f.attrs[sf.ATTR_CAMERA_IN_TCP]
    assert main(["info", str(path)]) == 0
    with Session.open(path) as s:
        assert s.camera_in_tcp is None
    capsys.readouterr()
    assert main(["pose", "--model", "base", "--data", str(path), "--object", "mug"]) == 2
    err = capsys.readouterr().err
    assert err == f"bubble: error: {path}: root attr 'camera_in_tcp' is missing (the camera's pose in the TCP frame, " \
                  "which places the contact patch in the base frame)\n"


@pytest.mark.parametrize("name", [sf.ARM_T, sf.PRESSURE_HPA])
def test_an_unreadable_arm_or_pressure_stream_is_one_line(tmp_path, small_session, capsys, name):
    """A damaged chunk of a compressed stream (was: bubble info's traceback, exit 1)."""
    path = tmp_path / "damaged_stream.h5"
    shutil.copyfile(small_session, path)
    with h5py.File(path, "a") as f:
        values = f[name][()]
        del f[name]
        f.create_dataset(name, data=values, chunks=True, compression="gzip")
    with h5py.File(path, "r") as f:
        offset = f[name].id.get_chunk_info(0).byte_offset
    with open(path, "r+b") as fh:
        fh.seek(offset + 4)
        fh.write(b"\x00garbage\xff" * 4)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bubble: error: {path}: corrupt or truncated session, cannot read {name} (") \
        and err.count("\n") == 1, err


def test_a_file_cut_off_as_it_was_created_says_to_delete_it(tmp_path, small_session, capsys):
    """A recording killed within its first tens of ms leaves HDF5's 48-byte header alone (was: "not a
    readable HDF5 session (truncated file ...)" without more, and `collect` refused the name: "use
    --resume", which failed the same way)."""
    path = tmp_path / "cut.h5"
    subprocess.run([sys.executable, "-c", "import os, sys, h5py; from collect.session_writer import LIBVER; "
                    "f = h5py.File(sys.argv[1], 'w', libver=LIBVER); os._exit(0)", str(path)], check=True)  # killed at once
    for argv in (["info", str(path)], ["collect", "--sim", "--objects", "box", "--resume", "--out", str(path)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"bubble: error: {path}: not a readable HDF5 session (") and err.count("\n") == 1, err
        assert err.endswith("; at 48 bytes it holds no recording (cut off as it was created: the command that created "
                            "it was killed at once): delete it and record again\n"), err
    assert path.stat().st_size == 48
    for cut in (2000, len(small_session.read_bytes()) - 1000):  # a copy cut short (was, at 2000 bytes: "delete it")
        path.write_bytes(small_session.read_bytes()[:cut])
        assert main(["info", str(path)]) == 2
        err = capsys.readouterr().err
        assert "holds no recording" not in err and err.count("\n") == 1, err
        assert err.endswith(f"; it is cut short: {cut} of the {small_session.stat().st_size} bytes its HDF5 header "
                            "records (a copy or a transfer that stopped: copy it again; or a disk that filled as it "
                            "was written)\n"), err
    path.write_text("x = 1\n")  # a small file of another kind (was, in b18db75: told to delete it)
    assert main(["info", str(path)]) == 2 and "holds no recording" not in capsys.readouterr().err
    path.write_bytes(b"")  # empty: no recording either way
    assert main(["info", str(path)]) == 2 and "at 0 bytes it holds no recording" in capsys.readouterr().err
