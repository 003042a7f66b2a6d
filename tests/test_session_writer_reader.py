"""SessionWriter / Session round trips on real HDF5 files: format, selection, crash safety, resume, bad input."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from collect import session_format as sf
from collect import session_writer
from collect.errors import HardwareFault, InputError
from collect.session_reader import Session
from collect.session_writer import RESUME_GAP_S, SessionWriter

H, W = 24, 32
INTRINSICS = {"fx": 30.0, "fy": 30.0, "cx": 15.5, "cy": 11.5, "width": W, "height": H}
OBJECT = {
    "name": "mug",
    "fixture_pose": [0.5, 0.0, 0.0, 0.0, 0.0, 0.0],
    "mesh_sha256": "ab" * 32,
    "primitive": {"type": "cylinder", "radius": 0.04, "height": 0.1},
    "vertices": np.zeros((3, 3), np.float32),
    "faces": np.array([[0, 1, 2]], np.int32),
}


def _metadata(serial, simulated=False, objects=(OBJECT,)) -> dict:
    return dict(sensor_serial=serial, sensor_spec={"serial": serial}, intrinsics=INTRINSICS,
                camera_in_tcp=[0, 0, -0.093, 0, 0, 0], simulated=simulated, objects=list(objects))


def _writer(path, serial="S1", simulated=False, resume=False, objects=(OBJECT,)):
    return SessionWriter(path, **_metadata(serial, simulated, objects), resume=resume)


def _frame(i):
    ir = np.full((H, W), i, np.uint16)
    depth = np.full((H, W), 9300 + i, np.uint16)
    depth[0, 0] = 0
    return ir, depth


def test_round_trip_format_and_selection(synthetic_session):
    with h5py.File(synthetic_session, "r") as f:  # plain h5py reads a closed session
        assert f.attrs[sf.ATTR_FORMAT] == sf.FORMAT_NAME
        assert f.attrs[sf.ATTR_FORMAT_VERSION] == sf.FORMAT_VERSION
        assert json.loads(f[sf.FRAMES_PHASE].attrs[sf.ATTR_PHASE_ENUM]) == sf.PHASES
        assert f[sf.FRAMES_IR].chunks == (1, 172, 224) and f[sf.FRAMES_IR].compression == "gzip"
        assert f[sf.FRAMES_IR].shuffle and f[sf.SIM_TRUE_DEPTH].compression == "gzip"
        assert f[sf.SIM_TRUE_DEPTH].dtype == np.float32
        assert f[sf.FRAMES_DEPTH].attrs[sf.ATTR_UNIT_M] == 1e-5 and f[sf.FRAMES_DEPTH].attrs[sf.ATTR_UNIT] == "1e-05 m"
    with Session.open(synthetic_session) as s:
        assert (s.n_frames, s.height, s.width) == (2 * (4 + 4 * 2 * 3), 172, 224)
        assert s.object_names == ["mug", "box"] and s.simulated and s.closed_cleanly
        assert s.sensor_serial == "SYN-0001" and s.intrinsics["width"] == 224
        np.testing.assert_array_equal(s.seq, np.arange(s.n_frames))
        ref = s.reference_frames("box")
        assert len(ref) == 4 and (s.phase[ref] == sf.PHASE_FREE).all() and (s.object_index[ref] == 1).all()
        press = s.select(object="mug", phase=["press", "hold"])
        assert len(press) == 2 * 2 * 3 and set(s.pose_id[press]) == {0, 1}
        assert list(s.select(pose_id=3, phase="retract")) == list(np.flatnonzero((s.pose_id == 3) & (s.phase == 4)))
        depth, valid, true = s.depth_m(press), s.valid(press), s.true_depth(press)
        assert depth.dtype == np.float32 and depth.shape == (12, 172, 224)
        assert ((depth > 0) == valid).all() and not valid[:, 0, 0].any()
        assert np.abs(depth[valid] - true[valid]).max() < 1e-3  # 0.05 mm noise, 10 um quantization
        assert true[:, 86, 112].min() < 0.093 - 1e-3  # the dent pushes the membrane towards the camera
        # arbitrary order with repeats, int and slice indexing agree
        order = [press[3], press[0], press[3]]
        np.testing.assert_array_equal(s.ir(order)[1], s.ir(int(press[0])))
        np.testing.assert_array_equal(s.ir(slice(2, 5)), s.ir([2, 3, 4]))
        assert s.tcp_pose(press).shape == (12, 6)
        assert len(s.arm().t) == s.n_frames and len(s.pressure().hpa) == s.n_frames
        assert s.phase_name(int(press[0])) in ("press", "hold")
        with pytest.raises(InputError, match="no object 'cup'"):
            s.select(object="cup")
        with pytest.raises(InputError, match="unknown phase"):
            s.select(phase="squeeze")


def test_a_reference_recorded_again_after_a_safe_stop_retract_counts(synthetic_session):
    """A fault during the mug's reference retracts the arm (phase retract, no pose); the resumed run
    records the reference again. Was: only the free frames before that retract were the reference."""
    with h5py.File(synthetic_session, "a") as f:
        f[sf.FRAMES_PHASE][1] = sf.PHASES["retract"]  # frames 0-3: the mug's reference, pose_id -1
    with Session.open(synthetic_session) as s:
        assert s.pose_id[1] == -1 and s.object_index[1] == 0
        assert list(s.reference_frames("mug")) == [0, 2, 3]


def test_not_simulated_session_has_no_true_depth(tmp_path, make_synthetic_session):
    path = make_synthetic_session(tmp_path / "real.h5", objects=("box",), poses_per_object=1, simulated=False,
                                  height=H, width=W)
    with Session.open(path) as s:
        assert not s.simulated
        with pytest.raises(InputError, match="not a simulated session"):
            s.true_depth([0])


CHILD = textwrap.dedent(
    """
    import sys, time, numpy as np
    sys.path.insert(0, {root!r})
    from tests.test_session_writer_reader import _writer, _frame
    w = _writer({path!r})
    i, reported = 0, -1
    while True:
        ir, depth = _frame(i % 60000)
        w.append_frame(ir, depth, i / 45, time.time(), i, 0, -1, 0, [0, 0, 0.2, 3.14, 0, 0])
        i += 1
        if w.stats.frames_flushed != reported:
            reported = w.stats.frames_flushed
            print(reported, flush=True)
        time.sleep(0.002)
    """
)


def test_sigkill_keeps_every_flushed_frame_and_resume_continues(tmp_path):
    path = tmp_path / "crash.h5"
    root = str(Path(__file__).resolve().parents[1])
    proc = subprocess.Popen([sys.executable, "-c", CHILD.format(root=root, path=str(path))],
                            stdout=subprocess.PIPE, text=True)
    flushed = 0
    deadline = time.monotonic() + 30
    while flushed < 150 and time.monotonic() < deadline:
        flushed = int(proc.stdout.readline())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    assert flushed >= 150
    with h5py.File(path, "r") as f:  # plain h5py opens the killed recording, every flushed frame in it
        assert f[sf.FRAMES_SEQ].shape[0] >= flushed and f[sf.FRAMES_IR].shape[0] >= flushed
    with Session.open(path) as s:
        assert s.n_frames >= flushed and not s.closed_cleanly
        np.testing.assert_array_equal(s.seq, np.arange(s.n_frames))
        np.testing.assert_array_equal(s.ir(s.n_frames - 1), _frame(s.n_frames - 1)[0])
        n_crashed = s.n_frames
    with _writer(path, resume=True) as w:
        assert w.n_frames == n_crashed and w.object_indices == [0]
        w.append_frame(*_frame(7), 99.0, 99.0, n_crashed, 0, 5, sf.PHASE_RETRACT, np.zeros(6))
    with h5py.File(path, "r") as f:
        assert f[sf.FRAMES_SEQ][-1] == n_crashed
    with Session.open(path) as s:
        assert s.n_frames == n_crashed + 1 and s.closed_cleanly
        assert list(s.select(pose_id=5)) == [n_crashed]
    assert sorted(os.listdir(tmp_path)) == ["crash.h5"]


def _assert_every_appended_frame_kept_and_resumable(path, stopped_writer, appended: list, **resume_options):
    """The file a stopped writer left at ``path`` is closed cleanly and holds every frame in
    ``appended`` (those whose ``append_frame`` returned, including any still queued when the writer
    stopped); a resumed writer then adds to it."""
    with Session.open(path) as s:
        assert s.closed_cleanly and 0 < s.n_frames == stopped_writer.stats.frames_flushed == len(appended)
        np.testing.assert_array_equal(s.ir(slice(None)), np.stack(appended))
        n_kept = s.n_frames
    with SessionWriter(path, **_metadata("S1"), resume=True, **resume_options) as w:
        w.append_frame(*_frame(1), 999.0, 999.0, 10**6, 0, -1, sf.PHASE_FREE, np.zeros(6))
    with Session.open(path) as s:
        assert s.n_frames == n_kept + 1 and s.closed_cleanly


def test_the_writer_stops_before_the_disk_fills_and_keeps_a_complete_file(tmp_path, monkeypatch):
    """A disk that fills up mid-write leaves HDF5 metadata half written; the writer stops while
    ``min_free_bytes`` are left instead: every flushed frame readable, the file closed cleanly and
    resumable. Refused at the start on the real disk; then a disk whose free space only this file
    uses up (other programs writing to the real one would move the stop), stopping 256 kB in
    (~85 noisy frames)."""
    from conftest import disk_only_this_file_fills  # here: the SIGKILL test's child imports this module

    path = tmp_path / "full.h5"
    rng = np.random.default_rng(0)
    free = shutil.disk_usage(tmp_path).free
    with pytest.raises(InputError, match="free on the disk") as refused:
        SessionWriter(path, **_metadata("S1"), min_free_bytes=free + 2**40)
    assert not path.exists() and len(str(refused.value).splitlines()) == 1
    disk = 2**30
    disk_only_this_file_fills(monkeypatch, path, disk)
    w = SessionWriter(path, **_metadata("S1"), min_free_bytes=disk - 2**18, flush_interval_s=0.05)
    written = []
    with pytest.raises(HardwareFault, match="left on its disk.*free some space, then resume the recording") as stopped:
        for i in range(20000):
            ir = rng.integers(0, 2**16, (H, W), dtype=np.uint16)  # incompressible
            w.append_frame(ir, ir, i / 45, i / 45, i, 0, -1, sf.PHASE_FREE, np.zeros(6))
            written.append(ir)
            if i % 20 == 0:
                time.sleep(0.02)
    assert stopped.value.kind == "recorder" and len(str(stopped.value).splitlines()) == 1
    with pytest.raises(HardwareFault, match="left on its disk"):
        w.close()
    _assert_every_appended_frame_kept_and_resumable(path, w, written, min_free_bytes=0)


def _record_until_fault(writer, frames: list, on_frame=lambda i: None):
    """Append distinct frames every 5 ms until the writer faults; returns the fault."""
    with pytest.raises(HardwareFault) as fault:
        for i in range(2000):
            ir = np.full((H, W), i, np.uint16)
            writer.append_frame(ir, ir, i / 45, i / 45, i, 0, -1, sf.PHASE_FREE, np.zeros(6))
            frames.append(ir)
            on_frame(i)
            time.sleep(0.005)
    return fault.value


def test_a_recording_deleted_with_its_folder_is_restored_and_resumable(tmp_path):
    """Deleting the run folder mid-recording would lose every frame when the writer closes its
    unlinked file: the writer notices at its next flush, copies the file (complete up to that flush)
    back, folder included, and stops with one fault line saying where the frames are."""
    path = tmp_path / "run" / "s.h5"
    path.parent.mkdir()
    w = SessionWriter(path, **_metadata("S1"), flush_interval_s=0.05)
    frames: list = []
    fault = _record_until_fault(w, frames, lambda i: i == 60 and shutil.rmtree(path.parent))
    assert fault.kind == "recorder" and len(str(fault).splitlines()) == 1 and "deleted during the recording" in str(fault)
    with pytest.raises(HardwareFault) as closed:
        w.close()
    assert f"stopped at frame {len(frames)}, and those frames were restored to {path}: resume the recording from there" \
        in str(closed.value)
    _assert_every_appended_frame_kept_and_resumable(path, w, frames)


def test_a_recording_whose_folder_a_file_replaced_is_restored_in_the_folder_above(tmp_path):
    """Was: the copy back failed ("File exists": the folder could not be made again), the reserve's
    NotADirectoryError skipped the file's close, a traceback, and every frame was lost."""
    path = tmp_path / "run" / "s.h5"
    path.parent.mkdir()
    w = SessionWriter(path, **_metadata("S1"), flush_interval_s=0.05)

    def replace_the_folder(i):
        if i == 60:
            shutil.rmtree(path.parent)
            path.parent.write_text("a file where the folder was")

    frames: list = []
    _record_until_fault(w, frames, replace_the_folder)
    restored = tmp_path / "s.restored-1.h5"
    with pytest.raises(HardwareFault, match=f"restored to {restored}: resume the recording from there"):
        w.close()
    assert path.parent.read_text() == "a file where the folder was"
    with Session.open(restored) as s:
        assert s.closed_cleanly and s.n_frames == w.stats.frames_flushed == len(frames)


def test_a_recording_replaced_by_another_file_is_restored_beside_it(tmp_path):
    path = tmp_path / "s.h5"
    w = SessionWriter(path, **_metadata("S1"), flush_interval_s=0.05)

    def replace(i):
        if i == 30:
            path.unlink()
            path.write_bytes(b"someone else's file")

    frames: list = []
    _record_until_fault(w, frames, replace)
    restored = tmp_path / "s.restored-1.h5"
    with pytest.raises(HardwareFault, match=f"restored to {restored}:"):
        w.close()
    assert path.read_bytes() == b"someone else's file"
    with Session.open(restored) as s:
        assert s.closed_cleanly and s.n_frames == w.stats.frames_flushed == len(frames)


def test_a_resumed_segment_whose_clocks_restarted_continues_them(tmp_path):
    """A simulated bench (or a rebooted host / camera) starts its clocks and sequence numbers at 0
    again: the resumed segment is shifted to follow the recorded one; a clock that went on is kept."""
    path = tmp_path / "resumed.h5"
    with _writer(path) as w:
        for i in range(5):
            w.append_frame(*_frame(i), 100.0 + i / 45, 10.0 + i / 45, 40 + i, 0, -1, sf.PHASE_FREE, np.zeros(6))
        w.append_arm(10.2, np.zeros(6), np.zeros(6))
        w.append_pressure(10.25, 1065.0)
    with _writer(path, resume=True) as w:  # host and sequence restarted, the camera clock went on
        w.append_arm(0.0, np.zeros(6), np.zeros(6))
        for i in range(3):
            w.append_frame(*_frame(i), 500.0 + i / 45, 0.01 + i / 45, i, 0, -1, sf.PHASE_FREE, np.zeros(6))
        w.append_pressure(0.02, 1065.0)
    with Session.open(path) as s, h5py.File(path, "r") as f:
        assert json.loads(f.attrs[sf.ATTR_RESUMED_AT_FRAMES]) == [5]
        np.testing.assert_array_equal(s.seq, np.arange(40, 48))  # contiguous: nothing was dropped
        assert s.dropped_frames() == 0
        t_host, t_device = f[sf.FRAMES_T_HOST][()], f[sf.FRAMES_T_DEVICE][()]
        assert (np.diff(t_host) > 0).all() and (np.diff(t_device) > 0).all()
        np.testing.assert_allclose(t_host[5:], 11.25 + 0.01 + np.arange(3) / 45)  # 1 s after the pressure at 10.25
        np.testing.assert_allclose(t_device[5:], 500.0 + np.arange(3) / 45)  # not restarted: kept
        np.testing.assert_allclose(f[sf.ARM_T][()], [10.2, 11.25])
        np.testing.assert_allclose(f[sf.PRESSURE_T][()], [10.25, 11.27])


def test_flush_happens_while_recording_without_close(tmp_path):
    path = tmp_path / "live.h5"
    w = _writer(path)
    for i in range(10):  # the frame last: once 10 frames are flushed, so are the samples queued before them
        w.append_arm(i / 45, np.zeros(6), np.ones(6))
        w.append_pressure(i / 45, 1065.0)
        w.append_frame(*_frame(i), i / 45, i / 45, i, 0, -1, 0, np.zeros(6))
    deadline = time.monotonic() + 5
    while w.stats.frames_flushed < 10 and time.monotonic() < deadline:
        time.sleep(0.05)
    snapshot = tmp_path / "snapshot.h5"  # the file on disk as a crash would leave it
    shutil.copyfile(path, snapshot)
    with h5py.File(snapshot, "r") as f:
        assert f[sf.FRAMES_IR].shape[0] == 10 and f[sf.PRESSURE_HPA].shape[0] == 10
    w.close()
    w.close()  # idempotent


def test_resume_adds_new_objects_and_checks_meshes(tmp_path):
    path = tmp_path / "s.h5"
    with _writer(path) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, sf.PHASE_FREE, np.zeros(6))
    with _writer(path, resume=True) as w:  # a reference cut short (nothing after it) is recorded again
        assert w.referenced_objects == set()
        w.append_frame(*_frame(1), 0.1, 0.1, 1, 0, 0, sf.PHASE_APPROACH, np.zeros(6))
    box = dict(OBJECT, name="box", mesh_sha256="cd" * 32)
    with _writer(path, resume=True, objects=[box, OBJECT]) as w:
        assert w.object_indices == [1, 0] and w.referenced_objects == {0}
    with Session.open(path) as s:
        assert s.object_names == ["mug", "box"] and s.objects[1].mesh_sha256 == "cd" * 32
    with pytest.raises(InputError, match="another mesh"):
        _writer(path, resume=True, objects=[dict(OBJECT, mesh_sha256="ef" * 32)])


def test_a_segment_resumed_after_a_reboot_continues_every_stream_from_the_benchs_start(tmp_path):
    """The host clock restarted (a reboot), and the pressure board started seconds before the arm,
    whose samples the recorder appends first: was the arm's first sample that fixed the shift, and
    the earlier pressure readings went back in time, before the first segment's end."""
    path = tmp_path / "s.h5"
    with _writer(path) as w:
        for i in range(3):
            w.append_arm(4999.0 + i / 2, np.zeros(6), np.zeros(6))
            w.append_pressure(4999.0 + i / 2, 1065.0)
            w.append_frame(*_frame(i), 10.0 + i, 4999.0 + i / 2, i, 0, -1, sf.PHASE_FREE, np.zeros(6))
    with SessionWriter(path, **_metadata("S1", False, (OBJECT,)), resume=True,
                       host_clock_start=94.0) as w:  # the bench started at 94 s
        w.append_arm(100.0, np.zeros(6), np.zeros(6))
        for t in (95.0, 97.0, 99.5, 100.5):
            w.append_pressure(t, 1065.0)
        w.append_frame(*_frame(9), 3.0, 100.6, 0, 0, -1, sf.PHASE_FREE, np.zeros(6))
    with Session.open(path) as s:
        assert (np.diff(s.pressure().t) > 0).all() and (np.diff(s.arm().t) > 0).all()
        assert s.pressure().t[3] == pytest.approx(5000.0 + RESUME_GAP_S + 1.0)  # 1 s after the bench's start
        assert s.t_host[-1] == pytest.approx(5000.0 + RESUME_GAP_S + 6.6)


@pytest.mark.parametrize("stream", [sf.PRESSURE_HPA, sf.ARM_TCP_WRENCH])
def test_resume_refuses_a_stream_the_readers_refuse(tmp_path, stream, monkeypatch):
    """Was: a NaN in pressure/hpa (a file damaged by other means: the drivers refuse NaN) was resumed
    and extended, and bubble info still refused the longer file. The streams are read in blocks."""
    import collect.session_reader

    path = tmp_path / "s.h5"
    with _writer(path) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, sf.PHASE_FREE, np.zeros(6))
        for k in range(5):
            w.append_arm(0.01 * k, np.zeros(6), np.zeros(6))
            w.append_pressure(0.01 * k, 1013.0)
    with h5py.File(path, "r+") as f:
        f[stream][3] = np.nan
    recorded = path.read_bytes()
    monkeypatch.setattr(collect.session_reader, "STREAM_CHECK_ROWS", 2)
    with pytest.raises(InputError, match=f"corrupt session, NaN/inf in {stream} \\(row 3\\)"):
        _writer(path, resume=True)
    assert path.read_bytes() == recorded


def _one_frame_session(path, closed: bool):
    """A session of one frame, closed cleanly or as a killed recording (or one still running) leaves it."""
    with _writer(path) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, sf.PHASE_FREE, np.zeros(6))
    if not closed:
        with h5py.File(path, "r+") as f:
            f.attrs[sf.ATTR_CLOSED] = ""


@pytest.mark.parametrize("held", ["recorded", "read"])
def test_a_session_another_process_holds_is_refused_in_one_clear_line(tmp_path, held):
    """``bubble info``/``train``/``evaluate`` or ``collect --resume`` on a file another process records
    (HDF5's exclusive lock), or a resume of one a command reads (its shared lock): one line that
    says so (was: "not a readable HDF5 session (Resource temporarily unavailable)", as if the file
    were damaged, and "cannot open ... for appending: [Errno 11] Unable to synchronously open file (...)")."""
    path = tmp_path / "s.h5"
    _one_frame_session(path, closed=held == "read")
    other_process = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(other_process, fcntl.LOCK_EX if held == "recorded" else fcntl.LOCK_SH)  # as HDF5 takes it there
        calls = [lambda: _writer(path, resume=True)] + ([lambda: Session.open(path)] if held == "recorded" else [])
        for call in calls:
            with pytest.raises(InputError) as refused:
                call()
            assert str(refused.value) == (f"{path} is in use by another process (a recording still running, or a "
                                          "command reading it); try again once it has finished")
    finally:
        os.close(other_process)
    with Session.open(path) as s:
        assert s.n_frames == 1 and s.closed_cleanly == (held == "read")


def test_two_resumes_of_one_crashed_recording_at_once(tmp_path, monkeypatch):
    """Two resumes of one crashed recording (the same command in two terminals): the first to rewrite
    it records, the other is refused in one line (was: both copied it into one temporary file, and
    one's failure removed the other's copy: two tracebacks and nothing recorded; or the later copy
    replaced the file the first one was recording into)."""
    path = tmp_path / "s.h5"
    _one_frame_session(path, closed=False)
    recover, other = session_writer._recover_crashed, []

    def overtaken(crashed):  # between this resume's checks and its rewrite, the other resume runs
        monkeypatch.setattr(session_writer, "_recover_crashed", recover)
        other.append(_writer(path, resume=True))
        return recover(crashed)

    monkeypatch.setattr(session_writer, "_recover_crashed", overtaken)
    with pytest.raises(InputError, match="is in use by another process"):
        _writer(path, resume=True)
    with other[0] as w:
        w.append_frame(*_frame(1), 0.1, 0.1, 1, 0, 0, sf.PHASE_APPROACH, np.zeros(6))
    with Session.open(path) as s:
        assert s.n_frames == 2 and s.closed_cleanly
    assert sorted(os.listdir(tmp_path)) == ["s.h5"]


def test_bad_output_paths(tmp_path):
    path = tmp_path / "s.h5"
    with _writer(path) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, 0, np.zeros(6))
    size = path.stat().st_size
    with pytest.raises(InputError, match="already exists; use --resume"):
        _writer(path)
    assert path.stat().st_size == size
    with _writer(tmp_path / "new" / "folders" / "s.h5"):  # made on the way (was: "directory … does not exist")
        pass
    placeholder = tmp_path / "placeholder.h5"  # an empty file, as tempfile.mkstemp leaves (was: "already exists")
    placeholder.touch()
    with _writer(placeholder) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, 0, np.zeros(6))
    with Session.open(placeholder) as s:
        assert s.n_frames == 1
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="file is a file, not a directory"):
        _writer(tmp_path / "file" / "s.h5")
    with pytest.raises(InputError, match="is a directory, not a session file"):
        _writer(tmp_path)
    with pytest.raises(InputError, match="no such file"):
        _writer(tmp_path / "missing.h5", resume=True)
    with pytest.raises(InputError, match="recorded with sensor S1, not S2"):
        _writer(path, serial="S2", resume=True)
    with Session.open(path) as s:
        assert s.n_frames == 1


def _write_and_edit(path, edit):
    with _writer(path) as w:
        for i in range(3):
            w.append_frame(*_frame(i), i / 45, i / 45, i, 0, -1, 0, np.zeros(6))
    with h5py.File(path, "a") as f:
        edit(f)
    return path


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda f: f.attrs.__setitem__(sf.ATTR_FORMAT, "other-format"), "not a bubble-session file"),
        (lambda f: f.attrs.__setitem__(sf.ATTR_FORMAT_VERSION, 99), "format version 99 is not supported"),
        (lambda f: f[sf.FRAMES_T_DEVICE].__setitem__(1, np.nan), "NaN/inf in frames/t_device"),
        (lambda f: f.__delitem__(sf.FRAMES_SEQ), "missing frames/seq"),
    ],
)
def test_bad_session_files(tmp_path, edit, message):
    path = _write_and_edit(tmp_path / "bad.h5", edit)
    with pytest.raises(InputError, match=message):
        Session.open(path)
    if "version" in message:
        with pytest.raises(InputError, match=message):
            _writer(path, resume=True)


def test_truncated_and_non_hdf5_files(tmp_path, synthetic_session):
    data = synthetic_session.read_bytes()
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated.h5"):
        with Session.open(truncated) as s:
            s.ir(np.arange(s.n_frames))
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(InputError, match="not a readable HDF5 session"):
        Session.open(text)
    with pytest.raises(InputError, match="no such file"):
        Session.open(tmp_path / "missing.h5")


@pytest.mark.parametrize("compression", [None, {"compression": "lzf", "shuffle": True}, {}])
def test_images_read_back_bit_exact_with_any_filters(tmp_path, compression):
    """Direct chunk writes (default shuffle+gzip) and h5py's own filter path store the same data."""
    rng = np.random.default_rng(3)
    ir = rng.integers(0, 65535, (5, H, W), dtype=np.uint16)
    depth = rng.integers(0, 12000, (5, H, W), dtype=np.uint16)
    true = rng.uniform(0.05, 0.1, (5, H, W)).astype(np.float32)
    path = tmp_path / "bits.h5"
    with SessionWriter(path, sensor_serial="S", sensor_spec={}, intrinsics=INTRINSICS, camera_in_tcp=np.zeros(6),
                       simulated=True, objects=[], compression=compression) as w:
        for i in range(5):
            w.append_frame(ir[i], depth[i], i, i, i, -1, -1, 0, np.zeros(6), true_depth=true[i])
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f[sf.FRAMES_IR][()], ir)
        np.testing.assert_array_equal(f[sf.FRAMES_DEPTH][()], depth)
        np.testing.assert_array_equal(f[sf.SIM_TRUE_DEPTH][()], true)


def test_resume_reports_completed_poses_and_references(synthetic_session):
    with Session.open(synthetic_session) as s:
        intrinsics, objects, camera_in_tcp = s.intrinsics, s.objects, s.camera_in_tcp
    records = [{"name": o.name, "fixture_pose": o.fixture_pose, "mesh_sha256": o.mesh_sha256,
                "primitive": o.primitive, "vertices": o.vertices, "faces": o.faces} for o in objects]
    with SessionWriter(synthetic_session, sensor_serial="SYN-0001", sensor_spec={}, intrinsics=intrinsics,
                       camera_in_tcp=camera_in_tcp, simulated=True, objects=records, resume=True) as w:
        assert w.completed_pose_ids == {0, 1, 2, 3} and w.referenced_objects == {0, 1}
        # a pose with only approach + retract frames (no contact) is not complete
        ir = np.zeros((172, 224), np.uint16)
        for k, phase in enumerate((sf.PHASE_APPROACH, sf.PHASE_RETRACT)):
            w.append_frame(ir, ir, 100.0 + k, 100.0 + k, 1000 + k, 0, 9, phase, np.zeros(6),
                           true_depth=np.full((172, 224), 0.09, np.float32))
    with SessionWriter(synthetic_session, sensor_serial="SYN-0001", sensor_spec={}, intrinsics=intrinsics,
                       camera_in_tcp=camera_in_tcp, simulated=True, objects=records, resume=True) as w:
        assert w.completed_pose_ids == {0, 1, 2, 3}


def test_tcp_pose_from_the_arm_stream_when_frames_lack_it(synthetic_session):
    """frames/tcp_pose is optional in the contract: the reader interpolates arm/* on the host clock."""
    with Session.open(synthetic_session) as s:
        stored = s.tcp_pose(np.arange(s.n_frames))
    with h5py.File(synthetic_session, "a") as f:
        del f[sf.FRAMES_TCP_POSE]
    with Session.open(synthetic_session) as s:
        np.testing.assert_allclose(s.tcp_pose(np.arange(s.n_frames)), stored, atol=1e-9)
        np.testing.assert_allclose(s.tcp_pose(5), stored[5], atol=1e-9)


def test_every_per_frame_and_stream_dataset_is_compressed(synthetic_session):
    """The format's "chunked per frame, compressed": was true of the images only."""
    with h5py.File(synthetic_session, "r") as f:
        for name in (*sf.FRAME_DATASETS, sf.FRAMES_TCP_POSE, sf.SIM_TRUE_DEPTH, *sf.ARM_DATASETS,
                     *sf.PRESSURE_DATASETS):
            assert (f[name].compression, f[name].shuffle) == ("gzip", True), name


def test_tcp_pose_turns_the_short_way_between_arm_samples_near_a_half_turn(synthetic_session):
    """The tool pointing down is a half turn, whose rotation vector a UR reports with either sign:
    was each component interpolated alone, and halfway between two samples 0.2 deg apart, of
    opposite vectors, no turn at all."""
    with h5py.File(synthetic_session, "a") as f:
        del f[sf.FRAMES_TCP_POSE]
        poses = f[sf.ARM_TCP_POSE][:]
        poses[1::2, 3:] = [-(np.pi - 2e-3), 0.0, 0.0]  # every other sample 0.23 deg off a half turn, flipped
        poses[0::2, 3:] = [np.pi - 1e-3, 0.0, 0.0]
        f[sf.ARM_TCP_POSE][:] = poses
        t_arm = f[sf.ARM_T][:] - 0.5 / 45.0  # each frame (45 fps, sampled with the arm) halfway between two samples
        f[sf.ARM_T][:] = t_arm
    with Session.open(synthetic_session) as s:
        down = Rotation.from_rotvec([np.pi, 0.0, 0.0])
        turns = Rotation.from_rotvec(s.tcp_pose(np.arange(s.n_frames))[:, 3:])
        assert np.all((down.inv() * turns).magnitude() < 3e-3)
    with h5py.File(synthetic_session, "a") as f:
        f[sf.ARM_T][:] = t_arm[::-1]
    with Session.open(synthetic_session) as s, pytest.raises(InputError, match="arm/t goes back in time at row 1"):
        s.tcp_pose(0)


def test_bad_object_leaves_no_file_behind(tmp_path):
    path = tmp_path / "s.h5"
    with pytest.raises(InputError, match="cannot be stored"):
        _writer(path, objects=[dict(OBJECT, name="a/b")])
    assert not path.exists()
    with _writer(path) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, 0, np.zeros(6))
    with pytest.raises(InputError, match="cannot be stored"):
        _writer(path, resume=True, objects=[dict(OBJECT, name="..")])
    with Session.open(path) as s:  # the existing session is intact and not held open
        assert s.n_frames == 1 and s.object_names == ["mug"]


def test_every_gap_in_the_sequence_numbers_is_a_dropped_frame(tmp_path):
    path = tmp_path / "gaps.h5"
    with _writer(path) as w:
        for i, seq in enumerate([0, 1, 3, 4, 200, 201]):  # one frame lost, then 4.3 s of frames at 45 fps
            w.append_frame(*_frame(i), i / 45, i / 45, seq, 0, -1, sf.PHASE_FREE, np.zeros(6))
    with _writer(path, resume=True) as w:  # a resumed segment continues the numbering: no loss between them
        w.append_frame(*_frame(6), 1.0, 1.0, 0, 0, -1, sf.PHASE_FREE, np.zeros(6))
    with Session.open(path) as s:
        assert s.dropped_frames() == 1 + 195


def test_a_stop_signal_while_the_file_closes_is_delivered_after_it_is_closed(tmp_path, interrupt_handlers_restored):
    """Was: a Ctrl-C or SIGTERM inside ``close()`` (the writer thread's join, h5py's attribute write)
    raised there: the file stayed unmarked as closed, and now and then the exit hung on h5py's lock."""
    path = tmp_path / "s.h5"
    w = _writer(path)
    w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, -1, sf.PHASE_FREE, np.zeros(6))
    join = w._thread.join

    def signalled_join(*args):
        os.kill(os.getpid(), signal.SIGINT)  # handled in this (main) thread at once
        return join(*args)

    w._thread.join = signalled_join
    signal.signal(signal.SIGINT, signal.default_int_handler)
    with pytest.raises(KeyboardInterrupt):
        w.close()
    with Session.open(path) as s:
        assert s.closed_cleanly and s.n_frames == 1


def _metadata_with(**changes) -> dict:
    return dict(_metadata("S1"), **changes)


@pytest.mark.parametrize("changes, says", [
    ({"intrinsics": dict(INTRINSICS, fx=31.5)}, r"other camera intrinsics \(fx 30 there, 31.5 now\)"),
    ({"camera_in_tcp": [0, 0, -0.095, 0, 0, 0]}, r"the camera at another pose in the tool"),
])
def test_a_resume_with_another_camera_behind_the_same_serial_is_refused(tmp_path, changes, says):
    """Was: only the serial and image size were compared: frames of a recalibrated or swapped camera
    were appended under the file's old intrinsics, and training lifted them with those."""
    path = tmp_path / "s.h5"
    _one_frame_session(path, closed=True)
    with pytest.raises(InputError, match=says):
        SessionWriter(path, **_metadata_with(**changes), resume=True)
    with Session.open(path) as s:
        assert s.n_frames == 1 and s.closed_cleanly


def test_a_session_with_poses_but_no_plan_is_not_resumed_with_one(tmp_path):
    """Was: any plan was accepted, and two plans' pose ids mixed in one file."""
    path = tmp_path / "s.h5"
    with _writer(path) as w:
        w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, 0, sf.PHASE_APPROACH, np.zeros(6))
    with pytest.raises(InputError, match="holds contact poses but no collection plan"):
        SessionWriter(path, **_metadata("S1"), collection_plan={"poses_per_object": 3}, resume=True)


def test_rewriting_a_crashed_file_keeps_its_link_owner_and_mode(tmp_path):
    """Was: the rewrite replaced a symlink by a regular file (its target stayed crashed) and gave the
    file this process's owner and the umask's mode."""
    store = tmp_path / "store"
    store.mkdir()
    real = store / "real.h5"
    _one_frame_session(real, closed=False)
    os.chmod(real, 0o640)
    link = tmp_path / "link.h5"
    link.symlink_to(real)
    with _writer(link, resume=True) as w:
        w.append_frame(*_frame(1), 0.1, 0.1, 1, 0, -1, sf.PHASE_FREE, np.zeros(6))
    assert link.is_symlink() and (real.stat().st_mode & 0o777) == 0o640
    with Session.open(real) as s:
        assert s.n_frames == 2 and s.closed_cleanly
    assert sorted(os.listdir(store)) == ["real.h5"]


def test_a_crashed_file_that_cannot_be_rewritten_is_one_line_and_left_as_it_was(tmp_path, monkeypatch):
    """Was: a copy failing on a full disk or a damaged chunk index was a traceback (or a two-line
    error), and on a full disk it left the temporary copy behind, filling the disk."""
    path = tmp_path / "s.h5"
    _one_frame_session(path, closed=False)
    before = path.read_bytes()
    monkeypatch.setattr(session_writer, "_free_bytes", lambda p: os.path.getsize(path) + 1)
    with pytest.raises(InputError, match=r"only .* free on the disk of .*; recording needs at least"):
        _writer(path, resume=True)
    monkeypatch.undo()

    def damaged(self, *args, **kwargs):
        raise RuntimeError("Unable to synchronously copy object (bad coordinate offset)")

    monkeypatch.setattr(h5py.Group, "copy", damaged)
    with pytest.raises(InputError) as err:
        _writer(path, resume=True)
    assert str(err.value).endswith("was not closed cleanly, failed: bad coordinate offset") and "\n" not in str(err.value)
    assert path.read_bytes() == before and sorted(os.listdir(tmp_path)) == ["s.h5"]


def test_a_recording_holds_a_reserve_on_its_disk_and_gives_it_back_before_it_closes(tmp_path, monkeypatch):
    """The reserve gives HDF5 room to close a file whose disk another program filled (was: its close
    failed part-way and the process segfaulted at exit, where it should exit 3)."""
    path = tmp_path / "s.h5"
    reserve = tmp_path / ("s.h5" + session_writer.RESERVE_SUFFIX)
    reserve.write_bytes(bytes(1000))  # left by a killed recording: zeros, as allocated
    w = _writer(path)
    assert reserve.stat().st_size == session_writer.RESERVE_BYTES
    seen_at_close = []
    close = w._file.close

    def closing():
        seen_at_close.append((reserve.exists(), dict(w._streams), dict(w._frames)))
        close()

    w._file.close = closing
    w.append_arm(0.0, np.zeros(6), np.zeros(6))
    w.close()
    assert seen_at_close == [(False, {}, {})]  # given back, and every dataset closed, before the file
    assert not reserve.exists()


def test_what_else_has_the_reserve_name_is_left_alone(tmp_path):
    """Was: opened with O_TRUNC, following links: a file named s.h5.reserve, or the file a link of that
    name pointed to, became 16 MiB of zeros and was deleted at the close."""
    notes = tmp_path / "important.txt"
    notes.write_text("precious notes")
    (tmp_path / ("a.h5" + session_writer.RESERVE_SUFFIX)).symlink_to(notes)
    (tmp_path / ("b.h5" + session_writer.RESERVE_SUFFIX)).write_text("someone's data")
    for name in ("a.h5", "b.h5"):
        w = _writer(tmp_path / name)
        w.append_arm(0.0, np.zeros(6), np.zeros(6))
        w.close()
    assert notes.read_text() == "precious notes" and (tmp_path / "a.h5.reserve").is_symlink()
    assert (tmp_path / "b.h5.reserve").read_text() == "someone's data"


def test_info_counts_pressed_poses_and_recording_time_without_the_pause_of_a_resume(tmp_path):
    """Was: a pose only approached counted in "poses", and a resumed session's fps took the pause
    between its segments for recording time (37.5 fps for a 45 fps recording)."""
    from collect.session_info import session_summary

    path = tmp_path / "s.h5"
    with _writer(path) as w:
        for i in range(45):  # pose 0 approached, then the run stopped
            w.append_frame(*_frame(i), i / 45, i / 45, i, 0, 0, sf.PHASE_APPROACH, np.zeros(6))
    with _writer(path, resume=True) as w:  # pose 1 pressed, held and let go
        for i, phase in enumerate([sf.PHASE_APPROACH] * 15 + [sf.PHASE_PRESS] * 15 + [sf.PHASE_HOLD] * 15
                                  + [sf.PHASE_RETRACT] * 15):
            w.append_frame(*_frame(i), i / 45, i / 45, i, 0, 1, phase, np.zeros(6))
    info = session_summary(path)
    assert info["frames"] == 105 and info["objects"]["mug"]["poses"] == 1
    assert info["fps"] == pytest.approx(45.0) and info["duration_s"] == pytest.approx(44 / 45 + 59 / 45)


def test_info_says_a_session_holds_fewer_poses_than_its_plan_or_no_object(tmp_path):
    """A recording a fault cut short after 1 of its plan's 2 poses (was: "poses 1", "closed cleanly", as a
    finished session of a 1-pose plan reads); a file without a plan, or whose plan gives no count, shows
    the count alone; a file of no object (a run's reference.h5) says so (was: a table's header alone)."""
    from collect.session_info import describe_session, session_summary

    plan = {"objects": ["mug"], "settings": {"poses_per_object": 2, "seed": 0}}
    path = tmp_path / "s.h5"
    with SessionWriter(path, **_metadata("S1"), collection_plan=plan) as w:
        for i, phase in enumerate([sf.PHASE_APPROACH, sf.PHASE_PRESS, sf.PHASE_HOLD, sf.PHASE_RETRACT]):
            w.append_frame(*_frame(i), i / 45, i / 45, i, 0, 0, phase, np.zeros(6))
    assert session_summary(path)["planned_poses_per_object"] == 2
    text = describe_session(path)
    assert "  mug                    1/2" in text
    assert ("  incomplete: 1 of 2 planned poses recorded (mug 1/2); the same `bubble collect` with --resume (or "
            "`bubble commission` again, for a run's session) records the rest") in text
    with SessionWriter(path, **_metadata("S1"), collection_plan=plan, resume=True) as w:
        for i, phase in enumerate([sf.PHASE_APPROACH, sf.PHASE_PRESS, sf.PHASE_HOLD, sf.PHASE_RETRACT]):
            w.append_frame(*_frame(i), 1 + i / 45, 1 + i / 45, 4 + i, 0, 1, phase, np.zeros(6))
    text = describe_session(path)
    assert "  mug                    2/2" in text and "incomplete" not in text
    plan3 = {"objects": ["mug"], "settings": {"poses_per_object": 3, "seed": 0}}
    with SessionWriter(tmp_path / "missed.h5", **_metadata("S1"), collection_plan=plan3) as w:
        for i, (pose, phase) in enumerate([(0, sf.PHASE_APPROACH), (0, sf.PHASE_PRESS), (0, sf.PHASE_HOLD),
                                           (0, sf.PHASE_RETRACT), (1, sf.PHASE_APPROACH), (1, sf.PHASE_RETRACT),
                                           (2, sf.PHASE_APPROACH), (-1, sf.PHASE_RETRACT)]):
            w.append_frame(*_frame(i), i / 45, i / 45, i, 0, pose, phase, np.zeros(6))
    # pose 1 approached and let go without touching; pose 2 cut short by a stop (its retract the safe stop's)
    assert session_summary(tmp_path / "missed.h5")["objects"]["mug"]["no_contact"] == 1
    assert ("  incomplete: 1 of 3 planned poses recorded (mug 1/3; 1 approached without contact); the same `bubble "
            "collect` with --resume (or `bubble commission` again, for a run's session) records the rest, trying those "
            "again") in describe_session(tmp_path / "missed.h5")
    for name, stored in (("none.h5", None), ("odd.h5", {"settings": {"poses_per_object": "2"}})):
        with SessionWriter(tmp_path / name, **_metadata("S1"), collection_plan=stored) as w:
            w.append_frame(*_frame(0), 0.0, 0.0, 0, 0, 0, sf.PHASE_FREE, np.zeros(6))
        assert session_summary(tmp_path / name)["planned_poses_per_object"] is None
        text = describe_session(tmp_path / name)
        assert "  mug                      0" in text and "incomplete" not in text
    with _writer(tmp_path / "reference.h5", objects=()) as w:  # frames of the membrane alone
        for i in range(3):
            w.append_frame(*_frame(i), i / 45, i / 45, i, -1, -1, sf.PHASE_FREE, np.zeros(6))
    text = describe_session(tmp_path / "reference.h5")  # was: a table header without rows, "3 frames between objects"
    assert "  objects: none; 3 frames of no object (e.g. a commissioning run's reference.h5)" in text
    assert "object  " not in text and "between objects" not in text and "largest datasets" not in text  # all < 0.05 MB


def test_a_segment_start_left_by_a_crash_is_replaced_not_repeated(tmp_path):
    """A crash after the attribute's write and before its segment's first frames reached the disk: the
    next resume starts at the same frame. Was: the index listed twice, and bubble info counted the
    segments twice."""
    from collect.session_info import session_summary

    path = tmp_path / "s.h5"
    with _writer(path) as w:
        for i in range(45):
            w.append_frame(*_frame(i), i / 45, i / 45, i, 0, 0, sf.PHASE_FREE, np.zeros(6))
    with h5py.File(path, "a") as f:  # the crashed segment's start, and one beyond the frames (an uneven batch)
        f.attrs[sf.ATTR_RESUMED_AT_FRAMES] = json.dumps([45, 47])
    with _writer(path, resume=True) as w:
        for i in range(45):
            w.append_frame(*_frame(i), 2 + i / 45, 2 + i / 45, 45 + i, 0, 0, sf.PHASE_FREE, np.zeros(6))
    with h5py.File(path, "r") as f:
        assert json.loads(f.attrs[sf.ATTR_RESUMED_AT_FRAMES]) == [45]
    with h5py.File(path, "a") as f:  # a file written before this was fixed: read in order, each once
        f.attrs[sf.ATTR_RESUMED_AT_FRAMES] = json.dumps([45, 45, 20, 45])
    with Session.open(path) as s:
        assert s.resumed_at_frames == [20, 45]
    info = session_summary(path)
    assert info["duration_s"] == pytest.approx(2 * 44 / 45 - 1 / 45) and info["fps"] == pytest.approx(45.0)


def test_info_reports_a_camera_that_restarted_its_clock_and_numbering(tmp_path):
    """A camera that rebooted mid-recording: its clock and sequence numbers start again (was: a negative
    duration at 0.0 fps, and no word of the restart; the host clock's steps back went unreported)."""
    from collect.session_info import describe_session, session_summary

    path = tmp_path / "s.h5"
    with _writer(path) as w:
        for k in range(90):  # the camera restarts at frame 45; this computer's clock steps back at 60
            i = k % 45
            w.append_frame(*_frame(i), i / 45, 10 + k / 45 - (1.0 if k >= 60 else 0.0), i, 0, 0, sf.PHASE_FREE, np.zeros(6))
    info = session_summary(path)
    assert info["duration_s"] == pytest.approx(2 * 44 / 45) and info["fps"] == pytest.approx(45.0)
    assert (info["seq_restarts"], info["non_increasing_t"], info["non_increasing_t_host"], info["dropped"]) == (1, 1, 1, 0)
    assert "dropped 0, sequence restarts 1, non-increasing timestamps 1 camera / 1 host" in describe_session(path)


def test_a_resume_with_an_object_moved_on_the_bench_is_refused(tmp_path):
    """Was: only the mesh was compared; a plate_pose edited between two runs mixed two placements of
    the object in one file (the pose check's prior and true pose come from it)."""
    path = tmp_path / "s.h5"
    _one_frame_session(path, closed=True)
    moved = dict(OBJECT, fixture_pose=[0.5, 0.02, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match=r"object 'mug' in .* stood elsewhere on the bench \(fixture pose "
                                         r"\[0.5, 0.0, 0.0, 0.0, 0.0, 0.0\] there, \[0.5, 0.02, 0.0, 0.0, 0.0, 0.0\] now"):
        _writer(path, resume=True, objects=[moved])
