"""Crash-safe HDF5 session recorder (docs/session_format.md, names in ``collect.session_format``).

``SessionWriter`` takes frames, arm samples and pressure readings from the control loop and writes
them from a background thread, so the caller never waits on the disk: ``append_*`` only copies the
arrays into a bounded queue. The writer thread drains the queue in batches, appends to chunked
(one chunk per frame), compressed, growable datasets, and flushes at least every
``flush_interval_s`` (default 0.5 s).

Crash safety: the file is complete on disk after every flush (chunks go straight to the file,
each flush writes the metadata that indexes them), so a process killed with SIGKILL leaves a file
that plain ``h5py.File(path, "r")`` opens, holding every frame up to the last flush; ``resume=True``
continues it. The file format is HDF5 1.8's (``LIBVER``): no SWMR mode, whose status flags would
make plain h5py refuse a killed recording (docs/session_format.md "Crash safety").

Resumed sessions: the clocks stay increasing across segments. When a resumed segment's clock
restarted (the simulated bench starts at 0; a rebooted host or camera), its bench-clock times
(``t_host``, arm and pressure ``t``) and its camera times are shifted to continue
``RESUME_GAP_S`` after the last recorded ones; sequence numbers always continue from the last
recorded one (frames between two segments were never recorded, not dropped). The frame index
where each segment starts is listed in the root attr ``resumed_at_frames``.

Disk space: a disk that fills up mid-write leaves HDF5 metadata half written (datasets that
cannot be read back), so the writer stops before that happens, like a ROS bag recorder's
``min_space``: it refuses to start with less than ``MIN_FREE_BYTES`` free on the file's disk and,
checking after every flush, stops writing once the free space falls below it (see "Stopping" below).
The file is then closed cleanly; the producer gets ``HardwareFault("recorder")``
(the run stops the arm and retracts; once space is freed, ``bubble collect --resume``, or
``bubble commission`` run again, continues the file).

Deleted file: a recording file deleted (or replaced) while it is written would take every frame
with it when the writer closes it. After every flush the writer checks that its open file is still
the one at its path; if not, it stops writing (see "Stopping") and at once copies the open file back
to its path (its folder recreated if that was deleted too; next to it as ``<name>.restored-<n>.h5``
when another file took its place, in the nearest folder above under that name when a file took the
folder's). The producer gets ``HardwareFault("recorder")``; ``close()``'s
says where the frames are.

Stopping (low disk space, deleted file): the writer first stops accepting items, so that the next
``append_*`` call raises, then writes every item already accepted and flushes: the file holds every
frame and sample whose ``append_*`` call returned.

Compression: the byte-shuffle + deflate (level 1) HDF5 filters, applied by the writer itself in
parallel threads and stored with direct chunk writes (see ``IMAGE_COMPRESSION``,
docs/session_format.md and docs/bench_recorder.md for the measurements behind this choice).
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import stat
import threading
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from collect import session_format as sf
from collect.errors import RECORDER_FAULT, HardwareFault, InputError
from collect.json_files import plain_json
from collect.output_files import check_parent_dirs, exclusive_lock, is_placeholder
from collect.session_reader import h5_error_text, in_use_error, open_h5
from collect.stop_signals import stop_signals_deferred

#: Filters of the per-frame image datasets: shuffle + deflate level 1, the standard HDF5 filters
#: every HDF5 reader decodes (h5py, h5dump, MATLAB, HDFView; LZF is h5py-only). The writer
#: compresses the chunks itself in ``COMPRESS_THREADS`` threads (zlib releases the GIL) and
#: stores them with direct chunk writes; docs/bench_recorder.md has the measurements.
IMAGE_COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}
COMPRESS_THREADS = 2

#: Rows per chunk of the 1-D/2-D per-sample datasets (timestamps, poses, streams).
ROW_CHUNK = 512
#: Filters of those per-sample datasets: the images' (compressed by h5py as rows are appended; was:
#: none, against the format's "chunked per frame, compressed").
ROW_COMPRESSION = IMAGE_COMPRESSION

#: Queue capacity in items (frames + stream samples); ~10 s of frames at 45 fps with streams.
QUEUE_ITEMS = 2048

#: HDF5 file-format bounds of a new or resumed file: the 1.8 format, which every current HDF5 reader
#: opens, keeps no "open for writing" status flags that a killed writer would leave set, and
#: stores attributes over 64 kB (sensor spec, pose plan) densely.
LIBVER = ("v108", "v108")

_STR = h5py.string_dtype("utf-8")

#: Free space (bytes) the writer keeps on the file's disk: it will not start with less, and stops
#: writing (the file complete with every accepted frame) when less is left. 200 MiB is ~20 s of a
#: simulated recording (~10 MB/s with the true depth), 40 times what one flush interval adds.
MIN_FREE_BYTES = 200 * 2**20
#: Bytes the writer holds in ``PATH.reserve`` while it records and gives back just before it closes
#: the file. A disk that another program fills faster than the free-space check stops the
#: recording leaves HDF5 no room to flush its caches: its close failed part-way ("No space left on
#: device"), the file stayed unmarked as closed, and the dataset ids it left were closed by HDF5 at
#: the interpreter's exit, after the file's own structures (a segfault where the run exits 3). With
#: the reserve given back the close has room (the caches of a recording hold a few MB at most).
RESERVE_BYTES = 16 * 2**20
RESERVE_SUFFIX = ".reserve"

#: Gap (s) between the last recorded sample and a resumed segment whose clock restarted.
RESUME_GAP_S = 1.0


class _StoppedWriting(Exception):
    """The writer stopped writing on purpose; once ``frames`` is set, every frame it accepted is in
    the file and the file is complete."""

    def __init__(self):
        super().__init__()
        self.frames: int | None = None


class _LowDiskSpace(_StoppedWriting):
    """The disk is about to fill up: ``free`` bytes left, the writer keeps ``keep`` free."""

    def __init__(self, free: int, keep: int):
        super().__init__()
        self.free, self.keep = free, keep

    def __str__(self) -> str:
        at = "" if self.frames is None else f" at frame {self.frames}"
        return (f"only {_mb(self.free)} left on its disk, recording stopped{at} (it keeps {_mb(self.keep)} free); "
                "free some space, then resume the recording")


class _FileDeleted(_StoppedWriting):
    """The open file is no longer the one at its path; the writer copied it back (``restored_to``)."""

    def __init__(self):
        super().__init__()
        self.restored_to: str | None = None
        self.restore_error: str | None = None  # why the copy failed

    def __str__(self) -> str:
        if self.restored_to is None and self.restore_error is None:
            return "the file was deleted during the recording; recording stopped, its frames are being restored"
        stopped = f"the file was deleted during the recording; recording stopped at frame {self.frames}"
        if self.restored_to is None:
            return f"{stopped}, and its frames could not be restored: {self.restore_error}"
        return f"{stopped}, and those frames were restored to {self.restored_to}: resume the recording from there"


def _free_bytes(path: str) -> int:
    """Free bytes (for this user) on the disk that would hold ``path``: that of its nearest
    existing folder."""
    folder = os.path.dirname(os.path.abspath(path))
    while not os.path.isdir(folder):
        folder = os.path.dirname(folder)
    return shutil.disk_usage(folder).free


def _file_replaced(fd: int, path: str) -> bool:
    """Whether the open file ``fd`` is no longer the file at ``path`` (deleted, or replaced)."""
    try:
        at_path = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return True
    own = os.fstat(fd)
    return (at_path.st_dev, at_path.st_ino) != (own.st_dev, own.st_ino)


def _restore(fd: int, path: str) -> str:
    """Copy the open file ``fd`` (deleted from ``path``) to ``path``, recreating its folder, or next to
    it as ``<name>.restored-<n><ext>`` when another file is there now. Where a file took the folder's
    place, the copy goes into the nearest folder above it that is still one, under that second name
    (was: the copy failed, "File exists", and every frame went with the unlinked file). Returns the
    copy's path."""
    folder = os.path.dirname(os.path.abspath(path))
    root, ext = os.path.splitext(path)
    target, n = path, 0
    try:
        os.makedirs(folder, exist_ok=True)
    except (FileExistsError, NotADirectoryError):  # a file where the folder (or a folder above it) was
        while not os.path.isdir(folder):
            folder = os.path.dirname(folder)
        root = os.path.join(folder, os.path.splitext(os.path.basename(path))[0])
        target, n = f"{root}.restored-1{ext}", 1
    while os.path.lexists(target):
        n += 1
        target = f"{root}.restored-{n}{ext}"
    size = os.fstat(fd).st_size
    with open(target, "xb") as out:
        offset = 0
        while offset < size:
            chunk = os.pread(fd, min(2**24, size - offset), offset)
            if not chunk:
                break
            out.write(chunk)
            offset += len(chunk)
        out.flush()
        os.fsync(out.fileno())
    return target


def _mb(n_bytes: int) -> str:
    return f"{n_bytes / 2**20:.0f} MB"


def check_free_space(path, min_free_bytes: int | None = None) -> None:
    """Raise ``InputError`` when the disk that would hold the recording ``path`` has less than
    ``min_free_bytes`` (default ``MIN_FREE_BYTES``) free: the writer would not start there."""
    needed = MIN_FREE_BYTES if min_free_bytes is None else int(min_free_bytes)
    free = _free_bytes(os.fspath(path))
    if free < needed:
        raise InputError(f"only {_mb(free)} free on the disk of {os.fspath(path)}; recording needs at least "
                         f"{_mb(needed)}: free some space first")


class _ContinuedClock:
    """Shift of one clock of a resumed segment: fixed by the first value the segment brings, so
    that it lands ``gap`` after ``last`` (the last recorded value; -inf: none, never shifted).
    With ``restarted_only`` a clock that did not restart keeps its values (shift 0); without, the
    segment always continues right after ``last`` (sequence numbers: the frames between two
    segments were never recorded, not dropped). Thread-safe."""

    def __init__(self, last: float, gap: float, restarted_only: bool = True):
        self.last, self.gap, self.restarted_only = float(last), float(gap), restarted_only
        self.shift: float | None = None if np.isfinite(self.last) else 0.0
        self._lock = threading.Lock()

    def __call__(self, value: float) -> float:
        if self.shift is None:
            with self._lock:
                if self.shift is None:
                    shift = self.last + self.gap - value
                    self.shift = max(0.0, shift) if self.restarted_only else shift
        return value + self.shift


def software_version() -> str:
    """Installed ``bubble-bench`` version, or ``"unknown"`` when running from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("bubble-bench")
    except PackageNotFoundError:
        return "unknown"


@dataclass
class WriterStats:
    """Counters of a running writer (read from any thread; values are snapshots)."""

    frames_queued: int = 0  # frames handed to append_frame since open
    frames_written: int = 0  # frames written to the file since open
    frames_flushed: int = 0  # frames on disk at the last flush (total in the file, incl. resumed)
    flushes: int = 0
    max_queue_depth: int = 0  # largest queue length seen by the writer thread
    write_s: float = 0.0  # time the writer thread spent writing + flushing, s


class SessionWriter:
    """Append-only recorder of one session file.

    Args:
        path: output ``.h5`` file. Must not exist unless ``resume`` is true.
        sensor_serial: serial of the sensor (root attr; checked on resume).
        sensor_spec: JSON-serializable dict describing the sensor (root attr, JSON).
        intrinsics: ``{fx, fy, cx, cy, width, height[, distortion]}`` in pixels; fixes ``(H,W)``.
        camera_in_tcp: ``[x,y,z,rx,ry,rz]`` m + rotation vector, camera frame in the TCP frame.
        simulated: true for sessions recorded on the simulated bench (enables ``sim/true_depth``).
        objects: dicts with ``name``, ``fixture_pose`` (6,) m + rotvec, ``mesh_sha256`` str,
            ``primitive`` (dict or JSON str), ``vertices`` (V,3) m, ``faces`` (F,3) int.
        resume: append to an existing session instead of creating one. Objects already in the file
            keep their index; new ones are appended (``object_indices`` maps the given list).
        collection_plan: the pose-plan settings (``CollectionPlan.describe()``), stored as the root
            attr ``collection_plan`` (JSON); a resumed file must hold the same plan, so that pose
            ids keep their meaning.
        flush_interval_s: longest time between flushes while data is arriving, s (<= 1).
        compression: h5py filter keywords of the image datasets of a new file (default
            ``IMAGE_COMPRESSION``); a resumed file keeps its own.
        min_free_bytes: free space kept on the file's disk (default ``MIN_FREE_BYTES``).
        host_clock_start: the host clock's reading before any time this writer is given (a bench's
            ``started_at``): a resumed segment's host-clock shift is fixed from it (default: from the
            first time appended; was always so, the arm's first sample, seconds after the pressure
            board's first reading on a real bench, whose readings then went back in time in a
            segment resumed after a reboot).

    Raises:
        InputError: less than ``min_free_bytes`` free on the file's disk, the file exists (without
            ``resume``), cannot be created, or (with ``resume``) is
            missing, not a session, of another format version, sensor, image size or plan (these
            are checked read-only: such a refused resume leaves the file as it was), or holds an
            object of the same name with another mesh.
    """

    def __init__(
        self,
        path,
        *,
        sensor_serial: str,
        sensor_spec: dict,
        intrinsics: dict,
        camera_in_tcp,
        simulated: bool,
        objects: list[dict],
        resume: bool = False,
        collection_plan: dict | None = None,
        flush_interval_s: float = 0.5,
        compression: dict | None = None,
        min_free_bytes: int | None = None,
        host_clock_start: float | None = None,
    ):
        self.path = os.fspath(path)
        self.min_free_bytes = MIN_FREE_BYTES if min_free_bytes is None else int(min_free_bytes)
        self.simulated = bool(simulated)
        self.height = int(intrinsics["height"])
        self.width = int(intrinsics["width"])
        self.flush_interval_s = float(flush_interval_s)
        self.stats = WriterStats()
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_ITEMS)
        self._error: BaseException | None = None
        self._closed = False
        #: held while an item is queued; the writer thread takes it to stop accepting items
        self._accepting = threading.Lock()
        plan_text = json.dumps(collection_plan, sort_keys=True) if collection_plan is not None else None
        check_free_space(self.path, self.min_free_bytes)
        if resume:
            self._file = _open_for_resume(self.path, sensor_serial, intrinsics, camera_in_tcp, self.simulated,
                                          plan_text, objects)
        else:
            self._file = _create(self.path)
        if plan_text is not None:
            self._file.attrs[sf.ATTR_COLLECTION_PLAN] = plan_text
        try:
            if not resume:
                _write_root_attrs(self._file, sensor_serial, sensor_spec, intrinsics, camera_in_tcp, self.simulated)
                _create_datasets(self._file, self.height, self.width, self.simulated,
                                 IMAGE_COMPRESSION if compression is None else compression)
            self.object_indices = _merge_objects(self._file, objects)
        except BaseException:
            self._file.close()
            if not resume:  # a file this call created holds nothing yet
                os.remove(self.path)
            raise
        self._file.attrs[sf.ATTR_CLOSED] = ""
        self.n_frames_at_open = len(self._file[sf.FRAMES_SEQ])
        phase, pose_id = self._file[sf.FRAMES_PHASE][()], self._file[sf.FRAMES_POSE_ID][()]
        #: pose ids with hold and retract frames already in the file (resume skips them)
        self.completed_pose_ids = frozenset(sf.completed_pose_ids(phase, pose_id))
        #: object indices with a complete no-contact reference already in the file
        self.referenced_objects = frozenset(_referenced_objects(phase, self._file[sf.FRAMES_OBJECT][()], pose_id))
        self.stats.frames_flushed = self.n_frames_at_open
        self._host_clock = _ContinuedClock(_last_value(self._file, sf.FRAMES_T_HOST, sf.ARM_T, sf.PRESSURE_T), RESUME_GAP_S)
        if host_clock_start is not None:
            self._host_clock(host_clock_start)  # fixes the shift
        self._device_clock = _ContinuedClock(_last_value(self._file, sf.FRAMES_T_DEVICE), RESUME_GAP_S)
        self._seq = _ContinuedClock(_last_value(self._file, sf.FRAMES_SEQ), 1, restarted_only=False)
        #: frame index where this resumed segment starts, listed in ``resumed_at_frames`` with the
        #: segment's first frame (a resume that records no frame adds no segment)
        self._segment_start = self.n_frames_at_open if resume and self.n_frames_at_open else None
        self._file.flush()
        self._frames = {name: self._file[name] for name in _FRAME_DATASETS}
        if self.simulated:
            self._frames[sf.SIM_TRUE_DEPTH] = self._file[sf.SIM_TRUE_DEPTH]
        self._images = {name: _ImageDataset(self._frames[name]) for name in _IMAGE_DATASETS if name in self._frames}
        #: every dataset stays open until ``close()``: one closed after each batch flushed its cache as
        #: it went, and on a full disk that close failed inside h5py's dealloc, silently, leaving an
        #: id that HDF5 closed at the interpreter's exit, after the file (a segfault)
        self._streams = {name: self._file[name] for name in (*sf.ARM_DATASETS, *sf.PRESSURE_DATASETS)}
        self._reserve = _reserve_space(self.path)
        self._pool = ThreadPoolExecutor(COMPRESS_THREADS, thread_name_prefix="session-compress")
        self._thread = threading.Thread(target=self._run, name="session-writer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ producer side
    def append_frame(
        self,
        ir: np.ndarray,
        depth: np.ndarray,
        t_device: float,
        t_host: float,
        seq: int,
        object_index: int,
        pose_id: int,
        phase: int,
        tcp_pose,
        true_depth: np.ndarray | None = None,
    ) -> None:
        """Queue one camera frame.

        Args:
            ir: (H,W) uint16 amplitude. depth: (H,W) uint16 in ``DEPTH_UNIT_M``, 0 = invalid.
            t_device / t_host: s (camera clock / host clock). seq: camera sequence number.
            object_index: index into ``objects/name`` (-1 = none). pose_id: -1 = none.
            phase: one of ``session_format.PHASES`` values. tcp_pose: (6,) m + rotvec.
            true_depth: (H,W) float32 m, required for simulated sessions, ignored otherwise.
        """
        shape = (self.height, self.width)
        if ir.shape != shape or depth.shape != shape:
            raise ValueError(f"frame shape {ir.shape}/{depth.shape} != session shape {shape}")
        if phase not in _PHASE_VALUES:
            raise ValueError(f"unknown phase {phase}")
        if self.simulated:
            if true_depth is None or true_depth.shape != shape:
                raise ValueError("simulated sessions need true_depth (H,W) float32 m per frame")
            true_depth = np.array(true_depth, dtype=np.float32)
        item = (
            "frame",
            np.array(ir, dtype=np.uint16),
            np.array(depth, dtype=np.uint16),
            self._device_clock(float(t_device)),
            self._host_clock(float(t_host)),
            int(self._seq(int(seq))),
            int(object_index),
            int(pose_id),
            int(phase),
            np.asarray(tcp_pose, dtype=np.float64).reshape(6),
            true_depth,
        )
        self._put(item)
        self.stats.frames_queued += 1

    def append_arm(self, t: float, tcp_pose, wrench) -> None:
        """Queue one arm state sample: host time s, TCP pose (6,) m + rotvec, TCP wrench (6,) N, N m."""
        self._put(
            (
                "arm",
                self._host_clock(float(t)),
                np.asarray(tcp_pose, dtype=np.float64).reshape(6),
                np.asarray(wrench, dtype=np.float64).reshape(6),
            )
        )

    def append_pressure(self, t: float, hpa: float) -> None:
        """Queue one pressure reading: host time s, absolute pressure hPa."""
        self._put(("pressure", self._host_clock(float(t)), float(hpa)))

    def close(self) -> None:
        """Write everything queued, mark the file closed cleanly, close it. Idempotent.

        Raises ``HardwareFault("recorder", ...)`` if the writer thread failed (the frames written
        before the failure stay in the file).
        """
        if self._closed:
            return
        with self._accepting:
            self._closed = True
            self._queue.put(None)
        with stop_signals_deferred():  # a stop arriving now is delivered once the file is closed
            self._thread.join()
            self._pool.shutdown()
            try:
                if self._error is None or isinstance(self._error, _StoppedWriting):  # every accepted item written
                    self._file.attrs[sf.ATTR_CLOSED] = sf.utc_now()
            finally:
                _give_back(self._reserve)  # room for the close's flushes, however full the disk is
                self._frames, self._images, self._streams = {}, {}, {}  # closed here, before the file (see _run)
                try:
                    self._file.close()
                except (OSError, RuntimeError) as err:  # the disk filled up after all (another program)
                    self._error = self._error or err.with_traceback(None)
        self._raise_if_failed()

    def __enter__(self) -> "SessionWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_frames(self) -> int:
        """Frames in the session including queued ones (resumed frames + appended since open)."""
        return self.n_frames_at_open + self.stats.frames_queued

    # ------------------------------------------------------------------ writer thread
    def _put(self, item) -> None:
        with self._accepting:
            if self._closed:
                raise RuntimeError("SessionWriter is closed")
            self._raise_if_failed()
            self._queue.put(item)

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            reason = str(self._error) if isinstance(self._error, _StoppedWriting) else h5_error_text(self._error)
            raise HardwareFault(RECORDER_FAULT, f"cannot write {self.path}: {reason}") from self._error

    def _run(self) -> None:
        last_flush = time.monotonic()
        dirty = False  # written since the last flush
        done = False
        while not done:
            batch = self._next_batch(max(0.0, self.flush_interval_s - (time.monotonic() - last_flush)))
            if batch and batch[-1] is None:
                done = True
                batch.pop()
            self.stats.max_queue_depth = max(self.stats.max_queue_depth, len(batch))
            if self._error is not None:
                continue  # keep draining so that producers never block on a failed writer
            try:
                t0 = time.perf_counter()
                if batch:
                    self._write_batch(batch)
                    dirty = True
                if not dirty:
                    last_flush = time.monotonic()
                elif done or time.monotonic() - last_flush >= self.flush_interval_s:
                    self._flush()
                    dirty = False
                    last_flush = time.monotonic()
                    if _file_replaced(self._file.id.get_vfd_handle(), self.path):
                        deleted = _FileDeleted()
                        done = self._stop_writing(deleted) or done
                        self._restore_deleted_file(deleted)
                    elif (free := _free_bytes(self.path)) < self.min_free_bytes:
                        done = self._stop_writing(_LowDiskSpace(free, self.min_free_bytes)) or done
                self.stats.write_s += time.perf_counter() - t0
            except BaseException as err:  # noqa: BLE001 - re-raised in the producer's thread
                # kept without its frames, which hold the batch's arrays and datasets until the run ends
                self._error = err.with_traceback(None)

    def _flush(self) -> None:
        self._file.flush()
        self.stats.flushes += 1
        self.stats.frames_flushed = self.n_frames_at_open + self.stats.frames_written

    def _stop_writing(self, reason: _StoppedWriting) -> bool:
        """Stop accepting items (the next ``append_*`` raises ``reason``), then write and flush every
        item accepted before that. Returns whether ``close()`` was among them (its sentinel)."""
        accepted = []
        while not self._accepting.acquire(timeout=0.01):
            accepted += self._next_batch(0.0)  # room for a producer waiting on a full queue
        try:
            self._error = reason
            accepted += self._next_batch(0.0)
        finally:
            self._accepting.release()
        closed = None in accepted
        items = [item for item in accepted if item is not None]
        if items:
            self._write_batch(items)
        self._flush()
        reason.frames = self.stats.frames_flushed
        return closed

    def _restore_deleted_file(self, deleted: _FileDeleted) -> None:
        """The file was deleted (or replaced) and every accepted frame is in it: mark it closed
        cleanly and copy it back to its path (``deleted.restored_to``), before anything is lost."""
        try:
            self._file.attrs[sf.ATTR_CLOSED] = sf.utc_now()
            self._file.flush()
            deleted.restored_to = _restore(self._file.id.get_vfd_handle(), self.path)
        except OSError as err:
            deleted.restore_error = h5_error_text(err)

    def _next_batch(self, timeout: float) -> list:
        """Items waiting in the queue (waiting up to ``timeout`` s for the first), up to the ``None``
        close sentinel, which ends the batch."""
        batch = []
        try:
            batch.append(self._queue.get(timeout=timeout))
        except queue.Empty:
            return batch
        while batch[-1] is not None:
            try:
                batch.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return batch

    def _write_batch(self, batch: list) -> None:
        frames = [item for item in batch if item[0] == "frame"]
        arms = [item for item in batch if item[0] == "arm"]
        pressures = [item for item in batch if item[0] == "pressure"]
        if frames:
            if self._segment_start is not None:  # flushed together with the segment's first frames
                # a segment that crashed before its first frames were on disk left its start behind: replaced
                segments = [i for i in json.loads(self._file.attrs.get(sf.ATTR_RESUMED_AT_FRAMES, "[]"))
                            if i < self._segment_start]
                self._file.attrs[sf.ATTR_RESUMED_AT_FRAMES] = json.dumps(segments + [self._segment_start])
                self._segment_start = None
            columns = {
                sf.FRAMES_IR: np.stack([f[1] for f in frames]),
                sf.FRAMES_DEPTH: np.stack([f[2] for f in frames]),
                sf.FRAMES_T_DEVICE: np.array([f[3] for f in frames]),
                sf.FRAMES_T_HOST: np.array([f[4] for f in frames]),
                sf.FRAMES_SEQ: np.array([f[5] for f in frames], dtype=np.int64),
                sf.FRAMES_OBJECT: np.array([f[6] for f in frames], dtype=np.int16),
                sf.FRAMES_POSE_ID: np.array([f[7] for f in frames], dtype=np.int32),
                sf.FRAMES_PHASE: np.array([f[8] for f in frames], dtype=np.uint8),
                sf.FRAMES_TCP_POSE: np.stack([f[9] for f in frames]),
            }
            if self.simulated:
                columns[sf.SIM_TRUE_DEPTH] = np.stack([f[10] for f in frames])
            images = {name: columns.pop(name) for name in self._images}
            encoded = {name: self._images[name].encode(values, self._pool) for name, values in images.items()}
            for name, values in images.items():
                self._images[name].append(values, encoded[name])
            for name, values in columns.items():
                _append_rows(self._frames[name], values)
            self.stats.frames_written += len(frames)
        if arms:
            _append_rows(self._streams[sf.ARM_T], np.array([a[1] for a in arms]))
            _append_rows(self._streams[sf.ARM_TCP_POSE], np.stack([a[2] for a in arms]))
            _append_rows(self._streams[sf.ARM_TCP_WRENCH], np.stack([a[3] for a in arms]))
        if pressures:
            _append_rows(self._streams[sf.PRESSURE_T], np.array([p[1] for p in pressures]))
            _append_rows(self._streams[sf.PRESSURE_HPA], np.array([p[2] for p in pressures]))


class _ImageDataset:
    """Appends ``(n,H,W)`` images to a dataset chunked one image per chunk.

    With the shuffle + deflate filters (``IMAGE_COMPRESSION``) the chunks are encoded here, exactly
    as those HDF5 filters would (byte shuffle, then a zlib stream), in a thread pool, and stored
    with ``write_direct_chunk``: any reader decodes them with the standard filters. Datasets with
    other filters (a resumed file from another writer) go through h5py's normal write path.
    """

    def __init__(self, dataset: h5py.Dataset):
        self.dataset = dataset
        plist = dataset.id.get_create_plist()
        filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
        self.direct = filters == [h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_DEFLATE]
        self.level = int(dataset.compression_opts) if self.direct else 0
        self.itemsize = dataset.dtype.itemsize

    def _encode_one(self, image: np.ndarray) -> bytes:
        shuffled = np.ascontiguousarray(image).view(np.uint8).reshape(-1, self.itemsize).T.tobytes()
        return zlib.compress(shuffled, self.level)

    def encode(self, images: np.ndarray, pool: ThreadPoolExecutor):
        """Start encoding ``images`` (n,H,W); returns futures (or None for the normal write path)."""
        if not self.direct:
            return None
        return [pool.submit(self._encode_one, image) for image in images]

    def append(self, images: np.ndarray, encoded) -> None:
        """Append ``images`` (n,H,W), written as the chunks ``encoded`` by ``encode`` when it made them."""
        if encoded is None:
            _append_rows(self.dataset, images)
            return
        n = self.dataset.shape[0]
        self.dataset.resize(n + len(images), axis=0)
        for i, future in enumerate(encoded):
            self.dataset.id.write_direct_chunk((n + i, 0, 0), future.result(), filter_mask=0)


# ---------------------------------------------------------------------- file layout helpers
_PHASE_VALUES = frozenset(sf.PHASES.values())
_IMAGE_DATASETS = (sf.FRAMES_IR, sf.FRAMES_DEPTH, sf.SIM_TRUE_DEPTH)

_FRAME_DATASETS = (*sf.FRAME_DATASETS, sf.FRAMES_TCP_POSE)


def _append_rows(dataset: h5py.Dataset, values: np.ndarray) -> None:
    n = dataset.shape[0]
    dataset.resize(n + len(values), axis=0)
    dataset[n:] = values


def check_output_path(path, resume: bool) -> None:
    """Raise InputError unless ``path`` can be recorded to: a new file or a placeholder
    (``collect.output_files.is_placeholder``: an empty file, as ``tempfile.mkstemp`` leaves) where the
    folders on the way exist or can be made (``_create`` makes them; was: refused), or (``resume``)
    an existing file. Cheap; call it before opening any device."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise InputError(f"{path} is a directory, not a session file; name a file in it, e.g. "
                         f"{os.path.join(path, 'session.h5')}")
    if resume:
        if not os.path.isfile(path):  # was "no such file" for a device or a FIFO too (/dev/full)
            what = "not a regular file" if os.path.exists(path) else "no such file"
            raise InputError(f"cannot resume {path}: {what}")
        if not os.access(path, os.R_OK | os.W_OK):
            raise InputError(f"cannot resume {path}: the file is not writable")
        return
    if os.path.exists(path) and not is_placeholder(path):
        raise InputError(f"{path} already exists; use --resume to append to it or choose another output")
    check_parent_dirs(path)  # a folder on the way that is a file, or one that takes no new file


def _create(path: str) -> h5py.File:
    check_output_path(path, resume=False)
    try:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        return h5py.File(path, "w" if is_placeholder(path) else "w-", libver=LIBVER)
    except OSError as err:
        raise InputError(f"cannot create {path}: {err.strerror or err}") from None


def _write_root_attrs(f, serial, spec, intrinsics, camera_in_tcp, simulated) -> None:
    f.attrs[sf.ATTR_FORMAT] = sf.FORMAT_NAME
    f.attrs[sf.ATTR_FORMAT_VERSION] = sf.FORMAT_VERSION
    f.attrs[sf.ATTR_SOFTWARE_VERSION] = software_version()
    f.attrs[sf.ATTR_SENSOR_SERIAL] = str(serial)
    f.attrs[sf.ATTR_SENSOR_SPEC] = json.dumps(spec)
    f.attrs[sf.ATTR_INTRINSICS] = json.dumps(plain_json(intrinsics))
    f.attrs[sf.ATTR_CAMERA_IN_TCP] = json.dumps([float(v) for v in np.asarray(camera_in_tcp).reshape(6)])
    f.attrs[sf.ATTR_CREATED] = sf.utc_now()
    f.attrs[sf.ATTR_SIMULATED] = bool(simulated)


def _create_datasets(f: h5py.File, height: int, width: int, simulated: bool, compression: dict) -> None:
    image = dict(shape=(0, height, width), maxshape=(None, height, width), chunks=(1, height, width))
    f.create_dataset(sf.FRAMES_IR, dtype=np.uint16, **image, **compression)
    depth = f.create_dataset(sf.FRAMES_DEPTH, dtype=np.uint16, **image, **compression)
    depth.attrs[sf.ATTR_UNIT_M] = sf.DEPTH_UNIT_M
    depth.attrs[sf.ATTR_UNIT] = f"{sf.DEPTH_UNIT_M:g} m"  # the same, as text like every other dataset's unit
    depth.attrs[sf.ATTR_INVALID] = 0
    for name, dtype, unit in (
        (sf.FRAMES_T_DEVICE, np.float64, "s"),
        (sf.FRAMES_T_HOST, np.float64, "s"),
        (sf.FRAMES_SEQ, np.int64, ""),
        (sf.FRAMES_OBJECT, np.int16, ""),
        (sf.FRAMES_POSE_ID, np.int32, ""),
        (sf.FRAMES_PHASE, np.uint8, ""),
        (sf.ARM_T, np.float64, "s"),
        (sf.PRESSURE_T, np.float64, "s"),
        (sf.PRESSURE_HPA, np.float64, "hPa"),
    ):
        ds = f.create_dataset(name, shape=(0,), maxshape=(None,), chunks=(ROW_CHUNK,), dtype=dtype, **ROW_COMPRESSION)
        if unit:
            ds.attrs[sf.ATTR_UNIT] = unit
    f[sf.FRAMES_PHASE].attrs[sf.ATTR_PHASE_ENUM] = json.dumps(sf.PHASES)
    for name, unit in (
        (sf.FRAMES_TCP_POSE, "m, rad (rotation vector)"),
        (sf.ARM_TCP_POSE, "m, rad (rotation vector)"),
        (sf.ARM_TCP_WRENCH, "N, N m"),
    ):
        ds = f.create_dataset(name, shape=(0, 6), maxshape=(None, 6), chunks=(ROW_CHUNK, 6), dtype=np.float64,
                              **ROW_COMPRESSION)
        ds.attrs[sf.ATTR_UNIT] = unit
    if simulated:
        true = f.create_dataset(sf.SIM_TRUE_DEPTH, dtype=np.float32, **image, **compression)
        true.attrs[sf.ATTR_UNIT] = "m"
    for name in (sf.OBJECTS_NAME, sf.OBJECTS_MESH_SHA256, sf.OBJECTS_PRIMITIVE):
        f.create_dataset(name, shape=(0,), maxshape=(None,), chunks=(64,), dtype=_STR)
    pose = f.create_dataset(
        sf.OBJECTS_FIXTURE_POSE, shape=(0, 6), maxshape=(None, 6), chunks=(64, 6), dtype=np.float64
    )
    pose.attrs[sf.ATTR_UNIT] = "m, rad (rotation vector), base frame"
    f.require_group(sf.OBJECTS_MESH_GROUP)


def _merge_objects(f: h5py.File, objects: list[dict]) -> list[int]:
    """Add the objects not yet in the file; return the file index of each given object."""
    names = [n.decode() if isinstance(n, bytes) else n for n in f[sf.OBJECTS_NAME][()]]
    indices = []
    for obj in objects:
        name = str(obj["name"])
        if not name or "/" in name or name in (".", ".."):
            raise InputError(f"object name {name!r} cannot be stored (empty, '/', '.' or '..')")
        if name in names:  # a resumed file's object, its mesh checked by ``_check_resumable``
            indices.append(names.index(name))
            continue
        primitive = obj.get("primitive") or {}
        primitive = primitive if isinstance(primitive, str) else json.dumps(plain_json(primitive))
        _append_rows(f[sf.OBJECTS_NAME], np.array([name], dtype=object))
        _append_rows(f[sf.OBJECTS_MESH_SHA256], np.array([obj["mesh_sha256"]], dtype=object))
        _append_rows(f[sf.OBJECTS_PRIMITIVE], np.array([primitive], dtype=object))
        _append_rows(f[sf.OBJECTS_FIXTURE_POSE], np.asarray(obj["fixture_pose"], dtype=np.float64).reshape(1, 6))
        group = f[sf.OBJECTS_MESH_GROUP].create_group(name)
        vertices = group.create_dataset("vertices", data=np.asarray(obj["vertices"], dtype=np.float32))
        vertices.attrs[sf.ATTR_UNIT] = "m, object frame"
        group.create_dataset("faces", data=np.asarray(obj["faces"], dtype=np.int32))
        names.append(name)
        indices.append(len(names) - 1)
    return indices


def _open_for_resume(path: str, serial: str, intrinsics: dict, camera_in_tcp, simulated: bool,
                     plan_text: str | None, objects: list[dict]) -> h5py.File:
    """Open an existing session for appending, after checking (read-only) that it can be resumed
    with this sensor, camera and plan; one whose writer died is rewritten first
    (``_recover_crashed``)."""
    from collect.session_reader import Session

    check_output_path(path, resume=True)
    with Session.open(path) as session:  # every attribute and dataset a session needs
        _check_resumable(session, serial, intrinsics, camera_in_tcp, simulated, plan_text, objects)
        crashed = not session.closed_cleanly
    if crashed:
        f = _recover_crashed(path)
    else:
        try:
            f = h5py.File(path, "a", libver=LIBVER)
        except BlockingIOError:  # HDF5's lock: another process records or reads it
            raise in_use_error(path) from None
        except OSError as err:
            raise InputError(f"cannot open {path} for appending: {err}") from None
    try:
        _truncate_to_common_length(f)
        _truncate_streams(f)
    except BaseException:
        f.close()
        raise
    return f


@dataclass(frozen=True)
class ResumeProgress:
    """What a session file already holds of its plan (``resume_progress``)."""

    completed_pose_ids: frozenset  # pose ids held and retracted
    referenced_objects: frozenset  # names of the objects whose no-contact reference is complete
    closed_cleanly: bool  # False: the last recording was cut off (a resume rewrites the file first)


def resume_progress(path, *, sensor_serial: str, intrinsics: dict, camera_in_tcp, simulated: bool,
                    objects: list[dict], collection_plan: dict | None = None, **_metadata) -> ResumeProgress:
    """What ``path`` holds already, after the checks of ``SessionWriter(path, resume=True, ...)``
    (same keywords; ``InputError`` for what such a resume would refuse). Read-only: the file is
    left exactly as it was."""
    from collect.session_reader import Session

    path = os.fspath(path)
    plan_text = json.dumps(collection_plan, sort_keys=True) if collection_plan is not None else None
    check_output_path(path, resume=True)
    with Session.open(path) as session:
        _check_resumable(session, sensor_serial, intrinsics, camera_in_tcp, bool(simulated), plan_text, objects)
        names = session.object_names
        return ResumeProgress(
            completed_pose_ids=frozenset(sf.completed_pose_ids(session.phase, session.pose_id)),
            referenced_objects=frozenset(names[i] for i in _referenced_objects(session.phase, session.object_index, session.pose_id)
                                         if i < len(names)),
            closed_cleanly=session.closed_cleanly,
        )


def _check_resumable(session, serial: str, intrinsics: dict, camera_in_tcp, simulated: bool, plan_text: str | None,
                     objects: list[dict]) -> None:
    """Raise InputError unless ``session`` (a ``Session``) was recorded with this sensor, camera
    (``intrinsics`` px, ``camera_in_tcp`` (6,) m + rotvec: the file's root attributes describe every
    frame in it) and plan, and its objects of the names in ``objects`` with the same meshes."""
    path = session.path
    height, width = int(intrinsics["height"]), int(intrinsics["width"])
    if session.phases_renumbered:  # its frames and ours would mix two numberings
        raise InputError(f"cannot resume {path}: its frames/phase enum numbers the phases otherwise than this "
                         "software writes them; record into a new file")
    if str(session.sensor_serial) != str(serial):
        raise InputError(f"cannot resume {path}: it was recorded with sensor {session.sensor_serial}, not {serial}")
    if (session.height, session.width) != (height, width):
        raise InputError(f"cannot resume {path}: image size {(session.height, session.width)} != {(height, width)}")
    if session.simulated != simulated:
        raise InputError(f"cannot resume {path}: simulated={session.simulated} there")
    for name in ("fx", "fy", "cx", "cy"):  # a camera calibrated anew, or swapped, behind the same serial
        there, now = float(session.intrinsics[name]), float(intrinsics[name])
        if not np.isclose(there, now, rtol=1e-9, atol=0.0):
            raise InputError(f"cannot resume {path}: it was recorded with other camera intrinsics ({name} {there:g} "
                             f"there, {now:g} now); record into a new file")
    if session.camera_in_tcp is None:
        raise InputError(f"cannot resume {path}: it does not record the camera's pose in the tool (camera_in_tcp); "
                         "record into a new file")
    if not np.allclose(session.camera_in_tcp, np.asarray(camera_in_tcp, dtype=float).reshape(6), rtol=0.0, atol=1e-9):
        raise InputError(f"cannot resume {path}: it was recorded with the camera at another pose in the tool "
                         f"(camera_in_tcp); record into a new file")
    stored = session.collection_plan()
    if plan_text is not None and stored is None and bool(np.any(session.pose_id >= 0)):
        raise InputError(f"cannot resume {path}: it holds contact poses but no collection plan to check this run's "
                         f"against (recorded by another tool or version); record into a new file")
    if plan_text is not None and stored is not None and json.dumps(stored, sort_keys=True) != plan_text:
        changes = "; ".join(f"{key} {old} there, {new} now" for key, old, new in _differences(stored, json.loads(plan_text)))
        raise InputError(f"cannot resume {path}: it was recorded with another plan (objects, poses per object, "
                         f"seed or settings differ): {changes}")
    stored = {o.name: o for o in session.objects}
    for obj in objects:
        name, sha = str(obj["name"]), obj["mesh_sha256"]
        if name not in stored:
            continue
        there, placed = stored[name], np.asarray(obj["fixture_pose"], dtype=float)
        if there.mesh_sha256 != sha:
            raise InputError(f"object {name!r} in {path} has another mesh (sha256 {there.mesh_sha256[:12]}...) "
                             f"than the one given ({sha[:12]}...)")
        if not np.allclose(there.fixture_pose, placed, rtol=0.0, atol=1e-6):
            # its frames' object poses (the pose check's prior, the true pose) would mix two placements
            raise InputError(f"object {name!r} in {path} stood elsewhere on the bench (fixture pose "
                             f"{np.round(there.fixture_pose, 4).tolist()} there, {np.round(placed, 4).tolist()} now: "
                             f"a plate_pose changed?); record into a new file")


def _differences(old, new, key: str = "") -> list[tuple[str, object, object]]:
    """``(dotted key, old value, new value)`` of every leaf where the JSON trees ``old`` and ``new`` differ."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [d for k in sorted(set(old) | set(new))
                for d in _differences(old.get(k), new.get(k), f"{key}.{k}" if key else k)]
    return [] if old == new else [(key, old, new)]


def _last_value(f: h5py.File, *names: str) -> float:
    """Largest last value of the 1-D datasets ``names`` (-inf when all are empty)."""
    return max((float(f[name][-1]) for name in names if f[name].shape[0]), default=-np.inf)


def _referenced_objects(phase: np.ndarray, obj: np.ndarray, pose_id: np.ndarray) -> set[int]:
    """Objects whose no-contact reference is complete: free frames followed by a contact pose's
    frames (a reference cut short by a fault or a stop, whose safe-stop retract belongs to no
    pose, is recorded again on resume), from the ``(N,)`` ``frames/phase``, ``frames/object`` and
    ``frames/pose_id`` columns."""
    free = set(np.unique(obj[phase == sf.PHASE_FREE]).tolist())
    posed = set(np.unique(obj[(phase != sf.PHASE_FREE) & (pose_id >= 0)]).tolist())
    return {int(o) for o in free & posed if o >= 0}


def _truncate_to_common_length(f: h5py.File) -> None:
    """After a crash the per-frame datasets may differ by one batch; keep the frames all hold."""
    names = list(_FRAME_DATASETS) + ([sf.SIM_TRUE_DEPTH] if sf.SIM_TRUE_DEPTH in f else [])
    n = min(f[name].shape[0] for name in names)
    for name in names:
        if f[name].shape[0] != n:
            f[name].resize(n, axis=0)


def _truncate_streams(f: h5py.File) -> None:
    for group in (sf.ARM_DATASETS, sf.PRESSURE_DATASETS):
        n = min(f[name].shape[0] for name in group)
        for name in group:
            if f[name].shape[0] != n:
                f[name].resize(n, axis=0)


def _recover_crashed(path: str) -> h5py.File:
    """Rewrite a crashed (never closed) session into a fresh copy, atomically; returns the copy, open
    for appending.

    The copy leaves out what the dead writer stored after its last flush. The content goes into
    ``path.recover.tmp``, which then replaces the original (``os.replace``), so the original is
    never half-modified. One resume at a time: the crashed file is locked (``flock``, the lock HDF5
    takes on a file it writes) while it is copied, and the copy stays open, under HDF5's own lock,
    from its creation on. A second resume of the same file is refused (``in_use_error``), instead of
    copying it too and replacing the copy the first one records into.
    """
    real = os.path.realpath(path)  # through a symlink: the file it names is rewritten, the link kept
    tmp = real + ".recover.tmp"
    parent = os.path.dirname(real)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot resume {path}: it was not closed cleanly, and rewriting it needs a writable "
                         f"directory; {parent} is not")
    check_free_space(real, os.path.getsize(real) + MIN_FREE_BYTES)  # the copy, and room to record after it
    with exclusive_lock(path, in_use_error(path)) as fd, stop_signals_deferred():
        if _file_replaced(fd, path):  # another resume rewrote it since this one opened it
            raise in_use_error(path)
        dst = None
        try:
            dst = h5py.File(tmp, "w", libver=LIBVER)
            with open_h5(path, locking=False) as src:  # this process holds the lock
                for key, value in src.attrs.items():
                    dst.attrs[key] = value
                for key in src:
                    src.copy(src[key], dst, name=key)
            dst.flush()
            _keep_owner_and_mode(real, tmp)
            os.replace(tmp, real)
        except BaseException as err:
            try:
                if dst is not None:
                    dst.close()
            except (OSError, RuntimeError):  # the disk that failed the copy fails its close too
                pass
            if os.path.exists(tmp):
                os.remove(tmp)
            if isinstance(err, (OSError, RuntimeError)):  # h5py's: a full disk, a damaged chunk index
                raise InputError(f"cannot resume {path}: rewriting the file, which was not closed cleanly, failed: "
                                 f"{h5_error_text(err)}") from None
            raise
        return dst


def _reserve_space(path: str) -> str | None:
    """Allocate ``RESERVE_BYTES`` in ``path`` + ``RESERVE_SUFFIX`` (one a killed writer left is
    taken over); returns its name, or None where the file system gives no such file or something
    else has that name: anything but a writer's leftover (a link, a file with data) is left alone,
    and the recording goes on without a reserve (was: truncated to zeros and deleted, the file a
    link pointed to included)."""
    name = path + RESERVE_SUFFIX
    try:
        fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    except FileExistsError:
        if not _is_reserve_leftover(name):
            return None
        try:
            fd = os.open(name, os.O_WRONLY | os.O_NOFOLLOW)
        except OSError:
            return None
    except OSError:
        return None
    try:
        os.posix_fallocate(fd, 0, RESERVE_BYTES)  # written as zeros where the file system has no fallocate
    except OSError:
        _give_back(name)
        return None
    finally:
        os.close(fd)
    return name


def _is_reserve_leftover(name: str) -> bool:
    """Whether ``name`` is a reserve file a writer left: a regular file (not a link) of at most
    ``RESERVE_BYTES``, all zeros."""
    try:
        info = os.lstat(name)
        if not stat.S_ISREG(info.st_mode) or info.st_size > RESERVE_BYTES:
            return False
        with open(name, "rb") as f:
            while chunk := f.read(2**20):
                if chunk.count(0) != len(chunk):
                    return False
    except OSError:
        return False
    return True


def _give_back(reserve: str | None) -> None:
    """Delete the reserve file ``reserve`` (None: there is none); never raises, so that the close it
    makes room for always runs (was: its folder replaced by a file, ``NotADirectoryError`` skipped the
    file's close, a traceback, exit 1)."""
    if reserve is None:
        return
    try:
        Path(reserve).unlink(missing_ok=True)
    except OSError:  # its folder is gone (a file in its place): so is the reserve; one left otherwise is
        pass  # taken over by the next writer of that path, or removed by a resume


def _keep_owner_and_mode(original: str, copy: str) -> None:
    """Give ``copy`` the permission bits and (where this process may) the owner of ``original``:
    a session rewritten by a resume under sudo stays its owner's."""
    st = os.stat(original)
    os.chmod(copy, stat.S_IMODE(st.st_mode))
    try:
        os.chown(copy, st.st_uid, st.st_gid)
    except PermissionError:  # not root: the copy is this user's, as the original was
        pass
