"""Names and constants of the HDF5 session format (documented in docs/session_format.md).

One file per recording session, readable with plain h5py. Writers (``collect.session_writer``)
and readers (``collect.session_reader``) take every name from here.
"""

from datetime import datetime, timezone

import numpy as np

FORMAT_NAME = "bubble-session"
FORMAT_VERSION = 1

#: frames/depth is uint16 in this unit; 0 means invalid. 1e-5 m = 10 um, max 0.655 m.
DEPTH_UNIT_M = 1e-5

# Frame phases (frames/phase, uint8); the mapping is also stored in frames/phase attrs.
PHASE_FREE = 0  # membrane free, no object pressed (no-contact reference frames)
PHASE_APPROACH = 1
PHASE_PRESS = 2
PHASE_HOLD = 3
PHASE_RETRACT = 4
PHASES = {
    "free": PHASE_FREE,
    "approach": PHASE_APPROACH,
    "press": PHASE_PRESS,
    "hold": PHASE_HOLD,
    "retract": PHASE_RETRACT,
}
PHASE_NAMES = {value: name for name, value in PHASES.items()}  # value -> name, the inverse of PHASES

# Root attributes.
ATTR_FORMAT = "format"
ATTR_FORMAT_VERSION = "format_version"
ATTR_SOFTWARE_VERSION = "software_version"
ATTR_SENSOR_SERIAL = "sensor_serial"
ATTR_SENSOR_SPEC = "sensor_spec"  # JSON
ATTR_INTRINSICS = "intrinsics"  # JSON {fx, fy, cx, cy, width, height, distortion?}
ATTR_CAMERA_IN_TCP = "camera_in_tcp"  # JSON [x,y,z,rx,ry,rz] m + rotation vector: camera frame in TCP frame
ATTR_CREATED = "created"  # ISO 8601 UTC
ATTR_SIMULATED = "simulated"  # bool

# Per-frame datasets (N = frames).
FRAMES_IR = "frames/ir"  # (N,H,W) uint16 amplitude
FRAMES_DEPTH = "frames/depth"  # (N,H,W) uint16 in DEPTH_UNIT_M, 0 = invalid; attrs: unit_m
FRAMES_T_DEVICE = "frames/t_device"  # (N,) float64 s, camera clock
FRAMES_T_HOST = "frames/t_host"  # (N,) float64 s, host clock
FRAMES_SEQ = "frames/seq"  # (N,) int64 camera sequence number
FRAMES_OBJECT = "frames/object"  # (N,) int16 index into objects/name, -1 = no object
FRAMES_POSE_ID = "frames/pose_id"  # (N,) int32 contact pose index within the session, -1 = none
FRAMES_PHASE = "frames/phase"  # (N,) uint8 PHASES; attrs hold the enum
FRAMES_TCP_POSE = "frames/tcp_pose"  # (N,6) float64 arm TCP pose at frame time [m, rotvec]
#: The per-frame datasets of the format's contract, required in every session (``frames/tcp_pose``,
#: this tool's addition to it, is read when present).
FRAME_DATASETS = (FRAMES_IR, FRAMES_DEPTH, FRAMES_T_DEVICE, FRAMES_T_HOST, FRAMES_SEQ, FRAMES_OBJECT,
                  FRAMES_POSE_ID, FRAMES_PHASE)

# Arm state stream (M samples).
ARM_T = "arm/t"  # (M,) float64 s host clock
ARM_TCP_POSE = "arm/tcp_pose"  # (M,6) float64 [x,y,z,rx,ry,rz] m + rotation vector, base frame
ARM_TCP_WRENCH = "arm/tcp_wrench"  # (M,6) float64 [Fx,Fy,Fz,Tx,Ty,Tz] N, N m, base frame
ARM_DATASETS = (ARM_T, ARM_TCP_POSE, ARM_TCP_WRENCH)

# Pressure board stream (P samples).
PRESSURE_T = "pressure/t"  # (P,) float64 s host clock
PRESSURE_HPA = "pressure/hpa"  # (P,) float64 hPa absolute
PRESSURE_DATASETS = (PRESSURE_T, PRESSURE_HPA)

# Objects on the fixture plate (O objects).
OBJECTS_NAME = "objects/name"  # (O,) str
OBJECTS_FIXTURE_POSE = "objects/fixture_pose"  # (O,6) float64 object origin in base frame [m, rotvec]
OBJECTS_MESH_SHA256 = "objects/mesh_sha256"  # (O,) str
OBJECTS_PRIMITIVE = "objects/primitive"  # (O,) str JSON shape description, e.g. {"type":"cylinder","radius":..}
OBJECTS_MESH_GROUP = "objects/meshes"  # objects/meshes/<name>/vertices (V,3) float32 m, faces (F,3) int32

# Simulated sessions only.
SIM_TRUE_DEPTH = "sim/true_depth"  # (N,H,W) float32 m, true membrane depth along the optical axis

# Attributes of datasets and bookkeeping attributes (added by the recorder).
ATTR_UNIT = "unit"  # physical unit of a dataset, e.g. "s", "m", "hPa"
ATTR_UNIT_M = "unit_m"  # frames/depth: metres per count
ATTR_INVALID = "invalid"  # frames/depth: the value that marks invalid pixels (0)
ATTR_PHASE_ENUM = "enum"  # frames/phase: JSON {name: value} of PHASES
ATTR_CLOSED = "closed"  # root: ISO 8601 UTC time of the last clean close, "" while recording / after a crash
ATTR_COLLECTION_PLAN = "collection_plan"  # root: JSON of the pose plan settings (objects, poses per object, seed)
ATTR_RESUMED_AT_FRAMES = "resumed_at_frames"  # root: JSON list of the frame indices where resumed segments start


def completed_pose_ids(phase: np.ndarray, pose_id: np.ndarray) -> set[int]:
    """Pose ids with both hold and retract frames (pressed, held and let go), from the ``(N,)``
    ``frames/phase`` and ``frames/pose_id`` columns."""
    held = set(np.unique(pose_id[phase == PHASE_HOLD]).tolist())
    retracted = set(np.unique(pose_id[phase == PHASE_RETRACT]).tolist())
    return {int(p) for p in held & retracted if p >= 0}


def utc_now() -> str:
    """The current UTC time as the format's time stamps write it (``created``, ``closed``; also the
    commissioning run's JSON files): ISO 8601 to the second, e.g. ``2026-11-24T09:30:00+00:00``."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
