"""Read recorded sessions (the HDF5 format of docs/session_format.md): frame selection, depth in metres, masks.

    with Session.open("session.h5") as s:
        idx = s.select(object="mug", phase=["press", "hold"])
        depth = s.depth_m(idx)          # (n,H,W) float32 m, 0 = invalid
        valid = s.valid(idx)            # (n,H,W) bool
        ref = s.reference_frames("mug") # no-contact frames recorded before the mug's first press

A file whose writer was killed (never marked closed) holds every frame up to the writer's last
flush, and is read up to its shortest per-frame dataset (a crash mid-flush leaves one batch uneven).
Bad files raise ``InputError`` with one line, and so does a file another process is recording
(``in_use_error``).
"""

from __future__ import annotations

import errno
import json
import os
import re
import stat
from dataclasses import dataclass

import h5py
import numpy as np

from collect import session_format as sf
from collect.errors import InputError
from collect.json_files import JSON_READ_ERRORS
from collect.numbers import real_number, real_numbers, whole_number
from collect.transforms import interpolate_poses

_REQUIRED = (
    *sf.FRAME_DATASETS,
    *sf.ARM_DATASETS,
    *sf.PRESSURE_DATASETS,
    sf.OBJECTS_NAME,
    sf.OBJECTS_FIXTURE_POSE,
    sf.OBJECTS_MESH_SHA256,
)

#: Layout each dataset must have: (what it is, its dimensions, numpy dtype kinds, its row width or
#: None); images are (N,H,W), poses and wrenches (N,6).
_LAYOUT = {
    sf.FRAMES_IR: ("(N,H,W) unsigned integers", 3, "u", None),
    sf.FRAMES_DEPTH: ("(N,H,W) unsigned integers", 3, "u", None),
    sf.SIM_TRUE_DEPTH: ("(N,H,W) floats", 3, "f", None),
    sf.FRAMES_T_DEVICE: ("(N,) floats", 1, "f", None),
    sf.FRAMES_T_HOST: ("(N,) floats", 1, "f", None),
    sf.FRAMES_SEQ: ("(N,) integers", 1, "iu", None),
    sf.FRAMES_OBJECT: ("(N,) integers", 1, "iu", None),
    sf.FRAMES_POSE_ID: ("(N,) integers", 1, "iu", None),
    sf.FRAMES_PHASE: ("(N,) unsigned integers", 1, "u", None),
    sf.FRAMES_TCP_POSE: ("(N,6) floats", 2, "f", 6),
    sf.ARM_T: ("(M,) floats", 1, "f", None),
    sf.ARM_TCP_POSE: ("(M,6) floats", 2, "f", 6),
    sf.ARM_TCP_WRENCH: ("(M,6) floats", 2, "f", 6),
    sf.PRESSURE_T: ("(K,) floats", 1, "f", None),
    sf.PRESSURE_HPA: ("(K,) floats", 1, "f", None),
    sf.OBJECTS_NAME: ("(O,) strings", 1, "OS", None),
    sf.OBJECTS_FIXTURE_POSE: ("(O,6) floats", 2, "f", 6),
    sf.OBJECTS_MESH_SHA256: ("(O,) strings", 1, "OS", None),
    sf.OBJECTS_PRIMITIVE: ("(O,) strings", 1, "OS", None),
}
#: The same for each object's mesh, ``objects/meshes/<name>/<key>``.
_MESH_LAYOUT = {
    "vertices": ("(V,3) floats", 2, "f", 3),
    "faces": ("(F,3) integers", 2, "iu", 3),
}
#: Largest depth unit accepted (m per count): 1 cm, 100 times the recorder's.
MAX_DEPTH_UNIT_M = 0.01
#: Size (bytes) under which an unreadable HDF5 file was cut off as it was created: the recorder's
#: first flush, before any frame, writes its groups and empty datasets (tens of kB); HDF5's header
#: alone, written as the file is created, is 48 bytes.
UNFINISHED_CREATION_BYTES = 4096
#: Rows of an arm or pressure stream ``Session.check_streams`` reads at a time.
STREAM_CHECK_ROWS = 65536
#: The first bytes of every HDF5 file.
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def open_h5(path, *, locking: bool = True) -> h5py.File:
    """Open ``path`` read-only. Raises InputError for a missing, unreadable (also one in a folder that
    cannot be entered), non-HDF5 or truncated file, and for one that another process is writing
    (``in_use_error``). ``locking=False`` leaves out HDF5's file lock: only for a caller that holds
    the file's lock itself."""
    path = os.fspath(path)
    try:
        status = os.stat(path)
    except OSError as err:  # missing, or in a folder that cannot be entered
        if err.errno in (errno.ENOENT, errno.ENOTDIR):
            raise InputError(f"{path}: no such file") from None
        raise InputError(f"cannot read {path}: {err.strerror}") from None
    mode, size = status.st_mode, status.st_size
    if stat.S_ISDIR(mode):
        raise InputError(f"{path} is a directory, not a session file")
    if not stat.S_ISREG(mode):
        raise InputError(f"{path} is not a regular file (a device, a pipe or a socket), not a session file")
    try:
        return h5py.File(path, "r", locking=None if locking else False)  # None: HDF5's default file locking
    except BlockingIOError:
        raise in_use_error(path) from None
    except OSError as err:
        hint, stored_eof = "", _stored_end_of_file(path)
        if stored_eof is not None and stored_eof >= UNFINISHED_CREATION_BYTES and size < stored_eof:
            hint = (f"; it is cut short: {size} of the {stored_eof} bytes its HDF5 header records (a copy or a transfer "
                    "that stopped: copy it again; or a disk that filled as it was written)")  # was: "delete it"
        elif _cut_off_at_creation(path, size):  # was: no hint, and `collect` refused the name ("use --resume")
            hint = (f"; at {size} bytes it holds no recording (cut off as it was created: the command that created it "
                    "was killed at once): delete it and record again")
        raise InputError(f"{path}: not a readable HDF5 session ({h5_error_text(err)}){hint}") from None


def _stored_end_of_file(path: str) -> int | None:
    """The end-of-file address (bytes) that the HDF5 superblock at the start of ``path`` records: the
    size HDF5 gave the file when it last wrote its header (HDF5 file format, superblock versions 0-3;
    2048 bytes in a file just created, before any flush). None where the file does not start with a
    superblock, or the address is undefined or cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError:
        return None
    if len(head) < 12 or not head.startswith(HDF5_SIGNATURE):
        return None
    version = head[8]
    if version in (0, 1):  # base address after 16 bytes of fields (20 in version 1), then free space, end of file
        offsets, base_at = head[13], 24 if version == 0 else 28
    elif version in (2, 3):  # base address after 4 bytes of fields, then the extension, end of file
        offsets, base_at = head[9], 12
    else:
        return None
    eof_at = base_at + 2 * offsets
    if offsets not in (2, 4, 8) or len(head) < eof_at + offsets:
        return None
    eof = int.from_bytes(head[eof_at : eof_at + offsets], "little")  # an absolute address
    return None if eof == (1 << (8 * offsets)) - 1 else eof  # all ones: undefined


def _cut_off_at_creation(path: str, size: int) -> bool:
    """Whether the unreadable file ``path`` of ``size`` bytes is an HDF5 file cut off as it was created:
    empty, or HDF5's signature and under ``UNFINISHED_CREATION_BYTES`` (not a small file of another
    kind, which is no recording of this tool's at all)."""
    if size == 0:
        return True
    if size >= UNFINISHED_CREATION_BYTES:
        return False
    try:
        with open(path, "rb") as f:
            return f.read(len(HDF5_SIGNATURE)) == HDF5_SIGNATURE
    except OSError:
        return False


def in_use_error(path) -> InputError:
    """The refusal of a session file that another process holds: HDF5 locks a file while it is
    written (a recording, or a resume rewriting a crashed one) against every other open, and while
    it is read against writers (``BlockingIOError`` from h5py)."""
    return InputError(f"{os.fspath(path)} is in use by another process (a recording still running, or a command "
                      "reading it); try again once it has finished")


def h5_error_text(err: Exception) -> str:
    """One line saying why an h5py call failed: the system's reason for a failed file write
    (``No space left on device``), else the part of HDF5's message in parentheses."""
    text = str(err)
    reason = re.search(r"error message = '([^']+)'", text)
    if reason:
        return reason.group(1)
    if "(" in text and text.endswith(")"):
        text = text.split("(", 1)[1].rsplit(")", 1)[0]
    return " ".join(text.split())


def check_session_attrs(f: h5py.File) -> None:
    """Raise InputError unless ``f`` is a bubble session of a format version this code reads."""
    fmt = f.attrs.get(sf.ATTR_FORMAT)
    if isinstance(fmt, bytes):
        fmt = fmt.decode()
    if fmt is None:
        raise InputError(f"{f.filename}: an HDF5 file but not a {sf.FORMAT_NAME} file (it has no "
                         f"'{sf.ATTR_FORMAT}' attribute)")
    if not isinstance(fmt, str):  # an array or a number: no format name
        raise _bad(f.filename, f"root attr '{sf.ATTR_FORMAT}'", f"the text '{sf.FORMAT_NAME}'", fmt)
    if fmt != sf.FORMAT_NAME:
        raise InputError(f"{f.filename}: not a {sf.FORMAT_NAME} file (its '{sf.ATTR_FORMAT}' attribute is {fmt!r})")
    version = _root_attr(f, sf.ATTR_FORMAT_VERSION)
    if not isinstance(version, (int, np.integer)):
        raise _bad(f.filename, f"root attr '{sf.ATTR_FORMAT_VERSION}'", "an integer", version)
    if int(version) != sf.FORMAT_VERSION:
        raise InputError(
            f"{f.filename}: format version {version} is not supported (this software reads version "
            f"{sf.FORMAT_VERSION})"
        )


@dataclass(frozen=True)
class SessionObject:
    """One object of the fixture plate as stored in the session."""

    index: int  # value of frames/object for this object
    name: str
    fixture_pose: np.ndarray  # (6,) float64 object origin in the base frame [m, rotvec]
    mesh_sha256: str
    primitive: dict  # shape description, e.g. {"type": "cylinder", "radius": ..}
    vertices: np.ndarray  # (V,3) float32 m, object frame
    faces: np.ndarray  # (F,3) int32


@dataclass(frozen=True)
class ArmStream:
    t: np.ndarray  # (M,) float64 s host clock
    tcp_pose: np.ndarray  # (M,6) float64 [m, rotvec] base frame
    wrench: np.ndarray  # (M,6) float64 [N, N m] base frame


@dataclass(frozen=True)
class PressureStream:
    t: np.ndarray  # (P,) float64 s host clock
    hpa: np.ndarray  # (P,) float64 hPa absolute


class Session:
    """A recorded session opened read-only. Use ``Session.open(path)``, ideally as a context manager.

    Frame indices (``idx``) for the loaders are an int (returns one ``(H,W)`` image), a slice, or a
    1-D integer array / list (returns ``(n,H,W)`` in the given order; repeats allowed).
    """

    def __init__(self, f: h5py.File):
        self._f = f
        self.path = f.filename
        attrs = f.attrs
        self.sensor_spec = _root_json(f, sf.ATTR_SENSOR_SPEC, "a JSON object", _is_object)
        #: camera intrinsics in px: fx, fy > 0, cx, cy, width, height (+ ``distortion``, a list, when known)
        self.intrinsics = _root_json(f, sf.ATTR_INTRINSICS, "a JSON object with fx, fy, cx, cy, width, height",
                                     lambda v: _is_object(v) and set(_INTRINSICS_FIELDS) <= set(v))
        _check_intrinsics(self.path, self.intrinsics)
        #: (6,) float64 camera frame in the TCP frame [x,y,z m, rotation vector rad]; None when the file
        #: does not say (the format's contract does not require it; the pose check needs it)
        self.camera_in_tcp = np.asarray(_root_json(
            f, sf.ATTR_CAMERA_IN_TCP, "a JSON list of 6 finite numbers (x, y, z in m, rotation vector in rad)",
            lambda v: real_numbers(v, 6)), dtype=np.float64) if sf.ATTR_CAMERA_IN_TCP in attrs else None
        plan = _text(attrs.get(sf.ATTR_COLLECTION_PLAN, ""))
        self._collection_plan = _root_json(f, sf.ATTR_COLLECTION_PLAN, "a JSON object", _is_object) if plan else None
        resumed = sf.ATTR_RESUMED_AT_FRAMES in attrs
        #: frame indices where the recording's resumed segments start (``bubble collect --resume``), in
        #: order, each once (a crash between the attribute's write and its frames' can repeat one)
        self.resumed_at_frames = sorted({int(i) for i in _root_json(
            f, sf.ATTR_RESUMED_AT_FRAMES, "a JSON list of frame indices",
            lambda v: isinstance(v, list) and all(isinstance(i, int) and i > 0 for i in v))}) if resumed else []
        try:
            serial, simulated = attrs[sf.ATTR_SENSOR_SERIAL], attrs[sf.ATTR_SIMULATED]
            if not isinstance(serial, (str, bytes)):
                raise _bad(self.path, f"root attr '{sf.ATTR_SENSOR_SERIAL}'", "text", serial)
            if not (isinstance(simulated, (bool, np.bool_))
                    or isinstance(simulated, (int, np.integer)) and simulated in (0, 1)):
                raise _bad(self.path, f"root attr '{sf.ATTR_SIMULATED}'", "a boolean", simulated)
            self.sensor_serial = _text(serial)
            self.simulated = bool(simulated)
            self.created = _text(attrs.get(sf.ATTR_CREATED, ""))
            self.software_version = _text(attrs.get(sf.ATTR_SOFTWARE_VERSION, ""))
            #: True when the last recording into the file was closed cleanly (False after a crash)
            self.closed_cleanly = bool(_text(attrs.get(sf.ATTR_CLOSED, "")))
        except (KeyError, ValueError, TypeError) as err:
            raise InputError(f"{self.path}: missing or malformed session attribute ({err})") from None
        missing = [name for name in _REQUIRED if name not in f]
        if self.simulated and sf.SIM_TRUE_DEPTH not in f:
            missing.append(sf.SIM_TRUE_DEPTH)
        if missing:
            raise InputError(f"{self.path}: corrupt session, missing {', '.join(missing)}")
        for name, layout in _LAYOUT.items():
            if name in f:  # optional (the required ones are checked above)
                _check_layout(self.path, name, f[name], layout)
        _, self.height, self.width = f[sf.FRAMES_IR].shape
        for name in (sf.FRAMES_DEPTH, sf.SIM_TRUE_DEPTH):  # the true depth of a simulated session
            if name in f and f[name].shape[1:] != (self.height, self.width):
                height, width = f[name].shape[1:]
                raise InputError(f"{self.path}: corrupt session, {sf.FRAMES_IR} and {name} differ in size "
                                 f"({self.width}x{self.height} and {width}x{height} px)")
        if (self.intrinsics["height"], self.intrinsics["width"]) != (self.height, self.width):
            raise InputError(f"{self.path}: intrinsics size does not match the {self.width}x{self.height} frames")
        frame_sets = [*sf.FRAME_DATASETS, *(name for name in (sf.FRAMES_TCP_POSE, sf.SIM_TRUE_DEPTH) if name in f)]
        if self.closed_cleanly:  # only a crash mid-flush leaves a batch uneven; a clean close writes whole ones
            for group in (frame_sets, sf.ARM_DATASETS, sf.PRESSURE_DATASETS):
                _check_even_lengths(self.path, f, group)
        #: frames held by every per-frame dataset (a crash mid-flush can leave one batch uneven)
        self.n_frames = int(min(f[name].shape[0] for name in frame_sets))
        n = self.n_frames
        #: metres per count of frames/depth
        self.depth_unit_m = _depth_unit_m(self.path, f[sf.FRAMES_DEPTH])
        _check_depth_invalid(self.path, f[sf.FRAMES_DEPTH])
        phase_map = _phase_value_map(self.path, f[sf.FRAMES_PHASE])
        #: (N,) per-frame metadata, loaded eagerly (small)
        self.t_device = f[sf.FRAMES_T_DEVICE][:n]
        self.t_host = f[sf.FRAMES_T_HOST][:n]
        self._tcp_pose = f[sf.FRAMES_TCP_POSE][:n] if sf.FRAMES_TCP_POSE in f else None
        self.objects = _read_objects(f)
        # the integer columns are checked as stored, then narrowed (was: narrowed first, so that a
        # phase 256 read as free and an object 65535 as none)
        seq, object_index, pose_id, phase = (_int_column(self.path, f[name], n) for name in (
            sf.FRAMES_SEQ, sf.FRAMES_OBJECT, sf.FRAMES_POSE_ID, sf.FRAMES_PHASE))
        bad_phase = ~np.isin(phase, list(phase_map or sf.PHASE_NAMES))
        if bad_phase.any():
            raise InputError(f"{self.path}: corrupt session, unknown phase value at frame {int(np.argmax(bad_phase))}")
        #: the file numbers its phases otherwise than ``PHASES`` (its enum says how; read as ``PHASES``)
        self.phases_renumbered = phase_map is not None
        if phase_map is not None:  # the file's own numbering, read as the format's
            lookup = np.zeros(256, np.int64)
            lookup[list(phase_map)] = list(phase_map.values())
            phase = lookup[phase]
        if ((object_index < -1) | (object_index >= len(self.objects))).any():
            raise InputError(f"{self.path}: corrupt session, frames/object out of range")
        if (pose_id < -1).any():  # -1: no pose
            raise InputError(f"{self.path}: corrupt session, frames/pose_id below -1")
        if (pose_id > np.iinfo(np.int32).max).any():
            raise InputError(f"{self.path}: corrupt session, frames/pose_id above 2^31-1")
        self.seq = seq
        self.object_index = object_index.astype(np.int16)
        self.pose_id = pose_id.astype(np.int32)
        self.phase = phase.astype(np.uint8)
        self.object_names = [o.name for o in self.objects]
        for name, values in (
            (sf.FRAMES_T_DEVICE, self.t_device),
            (sf.FRAMES_T_HOST, self.t_host),
            (sf.FRAMES_TCP_POSE, self._tcp_pose),
        ):
            _check_finite(self.path, name, values)
        # every reader refuses them, not only those that read the streams (was: bubble info and a resume;
        # train, evaluate and pose took a file with NaN in pressure/hpa, exit 0): 2 ms for a 53 s recording
        self.check_streams()

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, path) -> "Session":
        """Open a session file read-only. Raises InputError for missing/corrupt/truncated files,
        another format or format version, malformed root attributes (intrinsics, camera_in_tcp,
        sensor_spec, collection_plan), a dataset of the wrong shape or type (``_LAYOUT``, and each
        object's mesh: ``_MESH_LAYOUT``, faces within its vertices), a bad depth unit, repeated
        object names, or NaN in the per-frame metadata or a mesh."""
        f = open_h5(path)
        try:
            check_session_attrs(f)
            return cls(f)
        except InputError:
            f.close()
            raise
        except (OSError, RuntimeError, KeyError, ValueError) as err:
            f.close()
            raise InputError(f"{os.fspath(path)}: corrupt or truncated session ({h5_error_text(err)})") from None

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ selection
    def object_id(self, name: str) -> int:
        """Index of object ``name`` in ``objects`` (= its value in frames/object); InputError if unknown."""
        if name not in self.object_names:
            raise InputError(f"{self.path}: no object {name!r} (objects: {', '.join(self.object_names) or 'none'})")
        return self.object_names.index(name)

    def select(self, object=None, phase=None, pose_id=None) -> np.ndarray:
        """Indices (ascending int64) of the frames matching every given filter.

        object: name or list of names (None = all frames, including those with no object).
        phase: name (``free``/``approach``/``press``/``hold``/``retract``) or list of names.
        pose_id: int or list of ints.
        """
        keep = np.ones(self.n_frames, dtype=bool)
        if object is not None:
            names = [object] if isinstance(object, str) else list(object)
            keep &= np.isin(self.object_index, [self.object_id(n) for n in names])
        if phase is not None:
            names = [phase] if isinstance(phase, str) else list(phase)
            unknown = [n for n in names if n not in sf.PHASES]
            if unknown:
                raise InputError(f"unknown phase {unknown[0]!r} (phases: {', '.join(sf.PHASES)})")
            keep &= np.isin(self.phase, [sf.PHASES[n] for n in names])
        if pose_id is not None:
            ids = [pose_id] if np.isscalar(pose_id) else list(pose_id)
            keep &= np.isin(self.pose_id, ids)
        return np.flatnonzero(keep).astype(np.int64)

    def reference_frames(self, object: str) -> np.ndarray:
        """Indices ``(n,) int64`` of the no-contact (``free``) frames of ``object`` recorded before its
        first contact pose. The safe-stop retract of a reference cut short by a fault or a stop is
        no pose (pose_id -1): the reference recorded again on resume, after it, counts too."""
        oid = self.object_id(object)
        mine = self.object_index == oid
        pressed = np.flatnonzero(mine & (self.phase != sf.PHASE_FREE) & (self.pose_id >= 0))
        first = pressed[0] if len(pressed) else self.n_frames
        free = np.flatnonzero(mine & (self.phase == sf.PHASE_FREE))
        return free[free < first].astype(np.int64)

    def dropped_frames(self) -> int:
        """Frames missing from the camera's sequence numbers. A resumed segment continues the
        numbering (``SessionWriter``), so every gap is a loss."""
        gaps = np.diff(self.seq.astype(np.int64)) - 1
        return int(gaps[gaps > 0].sum())

    def phase_name(self, idx) -> np.ndarray | str:
        """Phase names of frames ``idx`` (an index array ``(n,)`` -> ``(n,) str``; an int -> str)."""
        values = self.phase[idx]
        if np.isscalar(values):
            return sf.PHASE_NAMES[int(values)]
        return np.array([sf.PHASE_NAMES[int(v)] for v in values])

    # ------------------------------------------------------------------ loaders
    def ir(self, idx) -> np.ndarray:
        """IR amplitude ``(n,H,W) uint16`` (``(H,W)`` for an int index)."""
        return self._load(sf.FRAMES_IR, idx)

    def depth_raw(self, idx) -> np.ndarray:
        """ToF depth as stored: ``(n,H,W) uint16`` in ``depth_unit_m``, 0 = invalid."""
        return self._load(sf.FRAMES_DEPTH, idx)

    def depth_m(self, idx) -> np.ndarray:
        """ToF depth ``(n,H,W) float32`` m along the optical axis; invalid pixels are 0."""
        return self.depth_raw(idx).astype(np.float32) * np.float32(self.depth_unit_m)

    def valid(self, idx) -> np.ndarray:
        """``(n,H,W) bool``: True where the ToF depth is valid (non-zero)."""
        return self.depth_raw(idx) > 0

    def true_depth(self, idx, *, finite: bool = True) -> np.ndarray:
        """True membrane depth ``(n,H,W) float32`` m along the optical axis (simulated sessions only).
        ``finite``: refuse NaN/inf (``InputError`` naming the row); False hands them on, for a caller
        that reads them as invalid pixels (the pose check)."""
        if not self.simulated:
            raise InputError(f"{self.path}: not a simulated session, it holds no true depth")
        values = self._load(sf.SIM_TRUE_DEPTH, idx)
        if finite:
            _check_finite(self.path, sf.SIM_TRUE_DEPTH, values, rows=np.arange(self.n_frames)[idx])
        return values

    def tcp_pose(self, idx) -> np.ndarray:
        """Arm TCP pose at frame time ``(n,6) float64`` [x,y,z m, rotation vector rad], base frame.

        Interpolated from ``arm/*`` on the host clock when the file has no ``frames/tcp_pose``
        (``collect.transforms.interpolate_poses``).
        """
        if self._tcp_pose is not None:
            return self._tcp_pose[idx]
        arm = self.arm()
        if len(arm.t) == 0:
            raise InputError(f"{self.path}: no arm poses recorded")
        back = np.flatnonzero(np.diff(arm.t) < 0)
        if back.size:  # (was: np.interp's answer for unsorted times, a pose of anywhere)
            raise InputError(f"{self.path}: corrupt session, {sf.ARM_T} goes back in time at row {int(back[0]) + 1}")
        pose = interpolate_poses(self.t_host[idx], arm.t, arm.tcp_pose)
        return pose if np.ndim(self.t_host[idx]) else pose[0]

    def arm(self) -> ArmStream:
        """The arm state stream (TCP pose and wrench samples on the host clock)."""
        f = self._f
        n = min(f[name].shape[0] for name in sf.ARM_DATASETS)
        stream = ArmStream(*(self._load(name, slice(0, n), stream=True) for name in sf.ARM_DATASETS))
        for name, values in ((sf.ARM_T, stream.t), (sf.ARM_TCP_POSE, stream.tcp_pose), (sf.ARM_TCP_WRENCH, stream.wrench)):
            _check_finite(self.path, name, values)
        return stream

    def check_streams(self) -> None:
        """Refuse NaN/inf in the arm and pressure streams as ``arm()`` and ``pressure()`` do, reading
        ``STREAM_CHECK_ROWS`` rows at a time (an hour of arm states at 500 Hz is ~190 MB); every
        opening does."""
        for name in (*sf.ARM_DATASETS, *sf.PRESSURE_DATASETS):
            rows = self._f[name].shape[0]
            for start in range(0, rows, STREAM_CHECK_ROWS):
                stop = min(rows, start + STREAM_CHECK_ROWS)
                _check_finite(self.path, name, self._load(name, slice(start, stop), stream=True),
                              rows=np.arange(start, stop))

    def pressure(self) -> PressureStream:
        """The bubble pressure stream (hPa absolute on the host clock)."""
        f = self._f
        n = min(f[name].shape[0] for name in sf.PRESSURE_DATASETS)
        stream = PressureStream(*(self._load(name, slice(0, n), stream=True) for name in sf.PRESSURE_DATASETS))
        _check_finite(self.path, sf.PRESSURE_T, stream.t)
        _check_finite(self.path, sf.PRESSURE_HPA, stream.hpa)
        return stream

    def storage_bytes(self) -> dict[str, int]:
        """Bytes each dataset occupies in the file (after compression), by dataset path."""
        sizes: dict[str, int] = {}

        def visit(name, item):
            if isinstance(item, h5py.Dataset):
                sizes[name] = int(item.id.get_storage_size())

        try:
            self._f.visititems(visit)
        except (OSError, RuntimeError) as err:  # e.g. a file damaged by a full disk: addr overflow
            raise InputError(f"{self.path}: corrupt or truncated session ({h5_error_text(err)})") from None
        return sizes

    def collection_plan(self) -> dict | None:
        """The pose-plan settings stored by ``bubble collect`` (None if the file has none)."""
        return self._collection_plan

    def planned_poses_per_object(self) -> int | None:
        """The contact poses the stored plan presses on each object (``bubble collect
        --poses-per-object``); None if the file has no plan, or its plan gives no such count."""
        settings = (self._collection_plan or {}).get("settings")
        count = settings.get("poses_per_object") if isinstance(settings, dict) else None
        return count if isinstance(count, int) and not isinstance(count, bool) and count > 0 else None

    def _load(self, name: str, idx, stream: bool = False) -> np.ndarray:
        """Frames ``idx`` of dataset ``name`` (``stream``: rows ``idx``, a slice, of an arm or pressure
        dataset instead); InputError naming the dataset when HDF5 cannot read them (was: a traceback
        for the arm and pressure streams)."""
        try:
            return self._f[name][idx] if stream else self._read(self._f[name], idx)
        except (OSError, RuntimeError) as err:
            raise InputError(f"{self.path}: corrupt or truncated session, cannot read {name} ({h5_error_text(err)})") from None

    def _read(self, ds: h5py.Dataset, idx) -> np.ndarray:
        if isinstance(idx, (int, np.integer)):
            i = int(idx) + (self.n_frames if idx < 0 else 0)
            if not 0 <= i < self.n_frames:
                raise IndexError(f"frame {idx} out of range ({self.n_frames} frames)")
            return ds[i]
        if isinstance(idx, slice):
            start, stop, step = idx.indices(self.n_frames)
            if step == 1:
                return ds[start : max(start, stop)]
            idx = np.arange(start, stop, step)
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        if len(idx) and (idx.min() < 0 or idx.max() >= self.n_frames):
            raise IndexError(f"frame indices out of range ({self.n_frames} frames)")
        unique, inverse = np.unique(idx, return_inverse=True)
        out = np.empty((len(unique),) + ds.shape[1:], dtype=ds.dtype)
        # read runs of consecutive frames with one slice each (much faster than point selection)
        breaks = np.flatnonzero(np.diff(unique) != 1) + 1
        for run in np.split(np.arange(len(unique)), breaks):
            if len(run):
                out[run[0] : run[-1] + 1] = ds[unique[run[0]] : unique[run[-1]] + 1]
        return out[inverse]


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _positive_number(value) -> bool:
    return real_number(value) and value > 0


def _positive_int(value) -> bool:
    return whole_number(value) and value > 0


def _is_object(value) -> bool:
    return isinstance(value, dict)


def _bad(path: str, where: str, expected: str, value) -> InputError:
    """The one-line error for an attribute of the wrong kind: ``where`` (e.g. ``root attr 'intrinsics'``)
    must be ``expected``; the value found is shown, cut to 60 characters."""
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    shown = repr(value)
    return InputError(f"{path}: {where} must be {expected}, got {shown if len(shown) <= 60 else shown[:57] + '...'}")


def _root_attr(f: h5py.File, name: str):
    """Root attribute ``name`` of ``f`` as stored; InputError when it is missing."""
    if name not in f.attrs:
        raise InputError(f"{f.filename}: root attr '{name}' is missing")
    return f.attrs[name]


def _root_json(f: h5py.File, name: str, expected: str, valid):
    """Root attribute ``name`` of ``f`` parsed as JSON; InputError naming it when it is missing, not
    JSON, or not ``valid(value)`` (``expected`` says what it must be)."""
    try:
        value = json.loads(_text(_root_attr(f, name)))
    except JSON_READ_ERRORS as err:
        raise InputError(f"{f.filename}: root attr '{name}' is not valid JSON ({getattr(err, 'msg', err)})") from None
    if not valid(value):
        raise _bad(f.filename, f"root attr '{name}'", expected, value)
    return value


#: Intrinsics fields every session holds: name -> (what it must be, test of its JSON value).
_INTRINSICS_FIELDS = {
    "fx": ("a finite number > 0 (px)", _positive_number),
    "fy": ("a finite number > 0 (px)", _positive_number),
    "cx": ("a finite number (px)", real_number),
    "cy": ("a finite number (px)", real_number),
    "width": ("a positive integer (px)", _positive_int),
    "height": ("a positive integer (px)", _positive_int),
}


def _check_intrinsics(path: str, intrinsics: dict) -> None:
    """InputError unless every field of ``intrinsics`` (a dict holding ``_INTRINSICS_FIELDS``) is valid."""
    for name, (expected, valid) in _INTRINSICS_FIELDS.items():
        if not valid(intrinsics[name]):
            raise _bad(path, f"root attr '{sf.ATTR_INTRINSICS}' field '{name}'", expected, intrinsics[name])
    distortion = intrinsics.get("distortion", [])
    if not (isinstance(distortion, list) and all(map(real_number, distortion))):
        raise _bad(path, f"root attr '{sf.ATTR_INTRINSICS}' field 'distortion'", "a list of finite numbers", distortion)


def _check_even_lengths(path: str, f: h5py.File, names) -> None:
    """Raise InputError when the datasets ``names``, which the writer appends to together, hold
    different numbers of rows (called for a cleanly closed session, where no crash explains it)."""
    rows = {name: f[name].shape[0] for name in names}
    shortest, longest = min(rows, key=rows.get), max(rows, key=rows.get)
    if rows[shortest] != rows[longest]:
        raise InputError(f"{path}: corrupt session, {shortest} holds {rows[shortest]} of the {rows[longest]} rows of "
                         f"{longest} (they are written together)")


def _check_layout(path: str, name: str, dataset, layout: tuple) -> None:
    """InputError unless ``dataset`` (at ``name``) is an HDF5 dataset of the ``layout`` of
    ``_LAYOUT`` / ``_MESH_LAYOUT``: (what it holds, dimensions, dtype kinds, row width or None)."""
    what, ndim, kinds, row = layout
    if not isinstance(dataset, h5py.Dataset):
        raise InputError(f"{path}: corrupt session, {name} is not a dataset")
    shape, dtype = dataset.shape, dataset.dtype
    if shape is None or len(shape) != ndim or dtype.kind not in kinds or (row and shape[1] != row):
        raise InputError(f"{path}: corrupt session, {name} must hold {what}, got shape {shape} of {dtype}")


def _int_column(path: str, dataset: h5py.Dataset, n: int) -> np.ndarray:
    """The first ``n`` values of the integer dataset ``dataset`` as ``(n,) int64``; InputError for a
    value above 2^63-1 (a uint64 column)."""
    values = dataset[:n]
    if values.dtype == np.uint64 and len(values) and values.max() > np.iinfo(np.int64).max:
        raise InputError(f"{path}: corrupt session, {dataset.name.lstrip('/')} holds values above 2^63-1")
    return values.astype(np.int64)


#: Units of length a ``unit`` attribute may name, in metres.
_LENGTH_UNITS_M = {"m": 1.0, "mm": 1e-3, "um": 1e-6}


def _depth_unit_m(path: str, depth: h5py.Dataset) -> float:
    """Metres per count of ``frames/depth``: its ``unit_m`` attribute, else its ``unit`` text (such as
    ``"1e-05 m"``, the format's contract). InputError when neither says (was: the recorder's own unit
    taken, a file in 1e-4 m read ten times too shallow), when they disagree, or for a unit outside
    (0, MAX_DEPTH_UNIT_M] m."""
    unit_m, text = depth.attrs.get(sf.ATTR_UNIT_M), depth.attrs.get(sf.ATTR_UNIT)
    match = re.fullmatch(r"\s*([-+0-9.eE]+)\s*(m|mm|um)\s*", _text(text)) if isinstance(text, (str, bytes)) else None
    try:
        stated = float(match.group(1)) * _LENGTH_UNITS_M[match.group(2)] if match else None
    except ValueError:  # not a number, e.g. "1.2.3 m"
        stated = None
    where = f"{sf.FRAMES_DEPTH} attr '{sf.ATTR_UNIT_M}'"
    if unit_m is None:
        if stated is None:
            raise InputError(f"{path}: {sf.FRAMES_DEPTH} does not say its unit (attr '{sf.ATTR_UNIT_M}', metres per "
                             f"count, or '{sf.ATTR_UNIT}', a length such as '1e-05 m'; found {text!r})")
        unit_m, where = stated, f"{sf.FRAMES_DEPTH} attr '{sf.ATTR_UNIT}'"
    if not (_positive_number(unit_m) and unit_m <= MAX_DEPTH_UNIT_M):
        raise _bad(path, where, f"a number of metres in (0, {MAX_DEPTH_UNIT_M:g}]", unit_m)
    if stated is not None and not np.isclose(stated, unit_m, rtol=1e-6, atol=0.0):
        raise InputError(f"{path}: corrupt session, {sf.FRAMES_DEPTH} attrs '{sf.ATTR_UNIT_M}' ({float(unit_m):g} m) "
                         f"and '{sf.ATTR_UNIT}' ({_text(text)!r}) disagree")
    return float(unit_m)


def _check_depth_invalid(path: str, depth: h5py.Dataset) -> None:
    """InputError when ``frames/depth``'s ``invalid`` attribute is present and other than 0."""
    invalid = depth.attrs.get(sf.ATTR_INVALID)
    if invalid is not None and not (np.ndim(invalid) == 0 and real_number(invalid) and invalid == 0):
        raise _bad(path, f"{sf.FRAMES_DEPTH} attr '{sf.ATTR_INVALID}'", "0 (this software reads 0 as no depth)", invalid)


def _phase_value_map(path: str, phase: h5py.Dataset) -> dict[int, int] | None:
    """The map from the file's ``frames/phase`` values to ``PHASES``' where its ``enum`` attribute
    numbers them otherwise (a file of another writer; DESIGN.md fixes the names, not the numbers;
    was: refused, and before that read as if numbered as ``PHASES``, press and hold swapped), else
    None (also without the attribute). InputError when the enum does not name the format's five
    phases, each with its own value 0-255."""
    enum = phase.attrs.get(sf.ATTR_PHASE_ENUM)
    if enum is None:
        return None
    try:
        value = json.loads(_text(enum))
    except JSON_READ_ERRORS:
        value = enum
    numbers = list(value.values()) if isinstance(value, dict) else []
    if not (isinstance(value, dict) and set(value) == set(sf.PHASES) and len(set(numbers)) == len(numbers)
            and all(whole_number(v) and v <= 255 for v in numbers)):
        raise _bad(path, f"{sf.FRAMES_PHASE} attr '{sf.ATTR_PHASE_ENUM}'",
                   f"the phases {', '.join(sf.PHASES)}, each with its own value 0-255", value)
    return None if value == sf.PHASES else {stored: sf.PHASES[name] for name, stored in value.items()}


def _check_finite(path: str, name: str, values, rows=None) -> None:
    """Refuse NaN/inf in ``values``, naming the dataset row of the first one. ``rows``: the rows of
    ``name`` that ``values`` holds (an int for one row read alone; default: every row from 0)."""
    if values is None or values.dtype.kind != "f":
        return
    bad = ~np.isfinite(values)
    if bad.any():
        if rows is not None and np.ndim(rows) == 0:
            row = int(rows)
        else:
            first = int(np.argwhere(bad)[0][0])
            row = first if rows is None else int(rows[first])
        raise InputError(f"{path}: corrupt session, NaN/inf in {name} (row {row})")


def _read_objects(f: h5py.File) -> list[SessionObject]:
    names = [_text(n) for n in f[sf.OBJECTS_NAME][()]]
    poses = f[sf.OBJECTS_FIXTURE_POSE][()]
    shas = [_text(s) for s in f[sf.OBJECTS_MESH_SHA256][()]]
    prims = [_text(p) for p in f[sf.OBJECTS_PRIMITIVE][()]] if sf.OBJECTS_PRIMITIVE in f else [""] * len(names)
    if not (len(names) == len(poses) == len(shas) == len(prims)):
        raise InputError(f"{f.filename}: corrupt session, objects/* datasets differ in length")
    repeated = next((name for i, name in enumerate(names) if name in names[:i]), None)
    if repeated is not None:
        raise InputError(f"{f.filename}: corrupt session, object {repeated!r} is listed twice in {sf.OBJECTS_NAME}")
    _check_finite(f.filename, sf.OBJECTS_FIXTURE_POSE, poses)
    objects = []
    for i, name in enumerate(names):
        mesh = f"{sf.OBJECTS_MESH_GROUP}/{name}"
        vertices, faces = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)  # no mesh stored
        group = f.get(mesh)
        if group is not None:
            if not isinstance(group, h5py.Group):
                raise InputError(f"{f.filename}: corrupt session, {mesh} is not a group")
            for key, layout in _MESH_LAYOUT.items():
                if key not in group:
                    raise InputError(f"{f.filename}: corrupt session, missing {mesh}/{key}")
                _check_layout(f.filename, f"{mesh}/{key}", group[key], layout)
            vertices, faces = group["vertices"][()], group["faces"][()]
            _check_finite(f.filename, f"{mesh}/vertices", vertices)
            if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
                raise InputError(f"{f.filename}: corrupt session, {mesh}/faces names vertices that "
                                 f"{mesh}/vertices does not hold ({len(vertices)} vertices)")
        primitive = _primitive(f.filename, name, prims[i])
        objects.append(SessionObject(i, name, poses[i], shas[i], primitive, vertices, faces))
    return objects


def _primitive(path: str, name: str, text: str) -> dict:
    """The shape description of object ``name``: ``text``, its entry of objects/primitive, parsed
    (``{}`` when empty); InputError naming the object when it is not JSON or not a JSON object."""
    where = f"{sf.OBJECTS_PRIMITIVE} entry of object {name!r}"
    try:
        value = json.loads(text) if text else {}
    except JSON_READ_ERRORS as err:
        raise InputError(f"{path}: corrupt session, {where} is not valid JSON ({getattr(err, 'msg', err)})") from None
    if not _is_object(value):
        raise _bad(path, where, "a JSON object", value)
    return value
