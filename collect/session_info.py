"""Summary of a recorded session (``bubble info``): sensor, frames per object and phase, timing, sizes."""

from __future__ import annotations

import os

import numpy as np

from collect import session_format as sf
from collect.session_reader import Session

_PHASE_ORDER = list(sf.PHASES)


def session_summary(path) -> dict:
    """Facts about the session at ``path`` (JSON-ready). Raises InputError for bad files.

    Keys: path, sensor_serial, simulated, created, software_version, closed_cleanly, frames,
    width, height, duration_s (device clock: the frame-to-frame steps that went forward, summed; the
    pauses between a stop and its ``--resume`` are not recording time, nor is a clock that jumped
    back), fps, dropped (missing sequence numbers), seq_restarts (frames whose sequence number did not
    increase: a camera that restarted its numbering, the frames it lost uncounted),
    non_increasing_t and non_increasing_t_host (frames whose device / host time did not increase), objects
    ({name: {phase: frames, "poses": contact poses pressed, held and let go, "no_contact": poses
    approached and let go without touching, "reference": n}}),
    planned_poses_per_object (the stored plan's, None without one), unassigned_frames, arm_samples,
    pressure_samples, file_bytes, dataset_bytes ({name: stored bytes}).
    """
    with Session.open(path) as s:
        n = s.n_frames
        starts = [0] + [i for i in s.resumed_at_frames if i < n]
        steps = np.diff(s.t_device)
        steps[[i - 1 for i in starts[1:]]] = 0.0  # from a segment's last frame to the next one's first: a pause
        forward = steps[steps > 0]
        duration = float(forward.sum())
        complete = sf.completed_pose_ids(s.phase, s.pose_id)
        pressed = set(np.unique(s.pose_id[(s.phase == sf.PHASE_PRESS) | (s.phase == sf.PHASE_HOLD)]).tolist())
        let_go = set(np.unique(s.pose_id[(s.phase == sf.PHASE_RETRACT) & (s.pose_id >= 0)]).tolist())
        objects = {}
        for obj in s.objects:
            mine = s.object_index == obj.index
            counts = {name: int(np.count_nonzero(mine & (s.phase == sf.PHASES[name]))) for name in _PHASE_ORDER}
            ids = set(np.unique(s.pose_id[mine]).tolist())
            counts["poses"] = len(complete & ids)
            counts["no_contact"] = len((let_go - pressed - complete) & ids)
            counts["reference"] = int(len(s.reference_frames(obj.name)))
            objects[obj.name] = counts
        return {
            "path": os.fspath(path),
            "sensor_serial": s.sensor_serial,
            "simulated": s.simulated,
            "created": s.created,
            "software_version": s.software_version,
            "closed_cleanly": s.closed_cleanly,
            "frames": n,
            "width": s.width,
            "height": s.height,
            "duration_s": duration,
            "fps": len(forward) / duration if duration > 0 else 0.0,
            "dropped": s.dropped_frames(),
            "seq_restarts": int(np.count_nonzero(np.diff(s.seq) <= 0)),
            "non_increasing_t": int(np.count_nonzero(np.diff(s.t_device) <= 0)),
            "non_increasing_t_host": int(np.count_nonzero(np.diff(s.t_host) <= 0)),
            "objects": objects,
            "planned_poses_per_object": s.planned_poses_per_object(),
            "unassigned_frames": int(np.count_nonzero(s.object_index < 0)),
            "arm_samples": len(s.arm().t),
            "pressure_samples": len(s.pressure().t),
            "file_bytes": os.path.getsize(path),
            "dataset_bytes": s.storage_bytes(),
        }


def describe_session(path) -> str:
    """``session_summary`` as the text ``bubble info`` prints."""
    info = session_summary(path)
    mb = info["file_bytes"] / 1e6
    minutes = info["duration_s"] / 60
    per_min = f"{mb / minutes:.0f} MB per minute of recording" if minutes > 0 else "no recording time"
    lines = [
        f"{info['path']}: bubble session, sensor {info['sensor_serial']}"
        f" ({'simulated' if info['simulated'] else 'real'}), created {info['created']},"
        f" software {info['software_version']}",
        f"  status: {'closed cleanly' if info['closed_cleanly'] else 'NOT closed cleanly (crashed or still recording)'}",
        f"  frames: {info['frames']} of {info['width']}x{info['height']} over {info['duration_s']:.1f} s"
        f" ({info['fps']:.1f} fps); dropped {info['dropped']}, sequence restarts {info['seq_restarts']},"
        f" non-increasing timestamps {info['non_increasing_t']} camera / {info['non_increasing_t_host']} host",
        f"  streams: {info['arm_samples']} arm samples, {info['pressure_samples']} pressure readings",
        f"  size: {mb:.1f} MB ({per_min})",
    ]
    if not info["objects"]:  # was: the table's header alone, and these frames called "between objects"
        lines.append(f"  objects: none; {info['unassigned_frames']} frames of no object (e.g. a commissioning run's "
                     "reference.h5)")
    else:
        lines.append("  " + f"{'object':<16}{'poses':>10}{'ref':>6}" + "".join(f"{p:>9}" for p in _PHASE_ORDER))
    planned = info["planned_poses_per_object"]
    for name, counts in info["objects"].items():
        poses = f"{counts['poses']}/{planned}" if planned else str(counts["poses"])
        lines.append("  " + f"{name:<16}{poses:>10}{counts['reference']:>6}"
                     + "".join(f"{counts[p]:>9}" for p in _PHASE_ORDER))
    short = {name: counts["poses"] for name, counts in info["objects"].items() if planned and counts["poses"] < planned}
    if short:  # was: a run cut short by a fault read like a finished session of fewer poses
        done = sum(counts["poses"] for counts in info["objects"].values())
        missed = sum(counts["no_contact"] for counts in info["objects"].values())
        lines.append(f"  incomplete: {done} of {planned * len(info['objects'])} planned poses recorded ("
                     + ", ".join(f"{name} {n}/{planned}" for name, n in short.items())
                     + (f"; {missed} approached without contact" if missed else "")
                     + "); the same `bubble collect` with --resume (or `bubble commission` again, for a run's "
                       "session) records the rest" + (", trying those again" if missed else ""))
    if info["unassigned_frames"] and info["objects"]:
        lines.append(f"  {info['unassigned_frames']} frames between objects (travel, phase free)")
    big = [(k, v) for k, v in sorted(info["dataset_bytes"].items(), key=lambda kv: -kv[1])[:4] if v >= 0.05e6]
    if big:  # those that show as 0.1 MB or more (was: "objects/meshes/mug/faces 0.0 MB")
        lines.append("  largest datasets: " + ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in big))
    return "\n".join(lines)
