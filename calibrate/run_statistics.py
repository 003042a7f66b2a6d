"""Statistics the commissioning flow draws from the files of its run directory.

* ``collection_stats``: poses and frames recorded in ``session.h5`` (the collect step's checks);
* ``nocontact_maps``: per-pixel statistics of the model over the no-contact frames of
  ``reference.h5`` (the paper's Fig. 5; kept in ``validation.npz``), and ``registry_reference``,
  the sensor registry's reference made of them;
* ``pick_examples``: the held-out frames the report shows.

The validation's depth metrics (whole image, per object, against the truth) are
``trainer.metrics`` / ``trainer.evaluation``'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trainer.contact import contact_mask, reference_depth

#: Held-out frames shown in the report (distinct poses, the objects in turn: ``pick_examples``).
EXAMPLE_FRAMES = 4


def collection_stats(path: Path, planned: int) -> dict:
    """Poses and frames in the session file.

    A pose counts as recorded when it has ``hold`` frames; dropped frames are the gaps in the
    camera sequence numbers (``Session.dropped_frames``).
    """
    from collect import session_format as sf
    from collect.session_reader import Session

    with Session.open(path) as s:
        n, dropped = s.n_frames, s.dropped_frames()
        poses = np.unique(s.pose_id[(s.pose_id >= 0) & (s.phase == sf.PHASE_HOLD)])
    return {
        "frames": n,
        "frames_dropped": dropped,
        "frames_dropped_fraction": dropped / max(n + dropped, 1),
        "poses_recorded": int(poses.size),
        "poses_planned": planned,
        "poses_completed_fraction": poses.size / max(planned, 1),
    }


def nocontact_maps(estimator, reference_path: Path) -> dict:
    """Per-pixel statistics over the no-contact reference frames (the paper's Fig. 5).

    ``valid_count (H,W) int32`` frames with valid ToF depth; ``err_mean``/``err_var`` ``(H,W) float32``
    m / m^2 of predicted - measured depth over those frames (NaN where never valid, or where a prediction
    on a valid pixel is not finite);
    ``reference_depth (H,W) float32 m`` median valid ToF depth (0 = never valid); ``reference_ir (H,W)
    float32`` mean IR.
    """
    from collect.session_reader import Session
    from trainer.evaluation import predict_frames

    with Session.open(reference_path) as s:
        idx = np.arange(s.n_frames)
        ir = s.ir(idx)
        depth = s.depth_m(idx)
    pred = predict_frames(estimator, ir)
    valid = depth > 0
    count = valid.sum(axis=0)
    # a NaN prediction on a valid pixel makes its pixel NaN (was: left out of the sum but counted, which
    # pulled the pixel's mean and variance toward 0)
    err = np.where(valid, pred - depth, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        err_mean = np.where(count > 0, err.sum(axis=0) / count, np.nan)
        err_var = np.where(count > 0, np.where(valid, (err - err_mean) ** 2, 0.0).sum(axis=0) / count, np.nan)
    return {
        "valid_count": count.astype(np.int32),
        "err_mean": err_mean.astype(np.float32),
        "err_var": err_var.astype(np.float32),
        "reference_depth": reference_depth(depth),  # the pose check's and the trainer's reference
        "reference_ir": ir.mean(axis=0).astype(np.float32),
    }


def registry_reference(validation_path: Path) -> dict:
    """The sensor registry's no-contact reference from ``validation.npz``: ``depth_m``, ``ir`` and
    ``valid_count``, the ``nocontact_maps`` arrays."""
    with np.load(validation_path) as z:
        return {"depth_m": z["reference_depth"], "ir": z["reference_ir"], "valid_count": z["valid_count"]}


def pick_examples(frames, reference: np.ndarray) -> np.ndarray:
    """Indices of up to ``EXAMPLE_FRAMES`` held-out frames (``frames``: a ``trainer.dataset.FrameSet``)
    of distinct poses, taking the objects in turn: for each pose its most deformed frame (most pixels
    pushed in by > 1 mm against the no-contact ``reference`` (H,W) float32 m), deepest poses first."""
    dent = contact_mask(frames.depth, reference, 1e-3).sum(axis=(1, 2))
    per_object = []
    for name in sorted(set(frames.object_name)):
        best = {}
        for i in np.flatnonzero(frames.object_name == name):
            pose = int(frames.pose_id[i])
            if pose not in best or dent[i] > dent[best[pose]]:
                best[pose] = int(i)
        per_object.append(sorted(best.values(), key=lambda i: -dent[i]))
    picks = []
    for rank in range(max((len(p) for p in per_object), default=0)):
        picks += [p[rank] for p in per_object if rank < len(p)]
    return np.array(picks[:EXAMPLE_FRAMES], dtype=np.int64)
