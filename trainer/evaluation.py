"""Evaluation of a model directory on session files (``bubble evaluate``).

Frames: the contact frames (``press``, ``hold``) of the chosen objects. The model runs through
the deployed inference path (``DepthEstimator``: native frames in, native depth out), and the
paper's metrics are computed against the ToF depth (top-level keys). On simulated sessions,
``vs_true`` compares both the ToF and the model with the true membrane depth - the paper's
"better than the sensor" claim - including the pixels where the ToF dropped out.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from collect.errors import InputError
from trainer.dataset import CONTACT_PHASES, check_each_recording_once, check_each_session_once, load_frames
from trainer.inference import DepthEstimator
from trainer.metrics import depth_metrics, in_depth_range, no_depth_in_range

PREDICT_BATCH = 16


def predict_frames(estimator: DepthEstimator, ir: np.ndarray) -> np.ndarray:
    """Depth ``(N,H,W) float32 m`` of IR frames ``(N,H,W) uint16``, in batches."""
    return np.concatenate(
        [estimator.predict_batch(ir[i : i + PREDICT_BATCH]) for i in range(0, len(ir), PREDICT_BATCH)]
    )


def compare_with_truth(pred: np.ndarray, tof: np.ndarray, truth: np.ndarray, min_depth: float, max_depth: float) -> dict:
    """ToF and model against the true depth (all ``(N,H,W) float32 m``). The ToF is valid where its
    depth lies strictly inside ``(min_depth, max_depth)`` (``in_depth_range``); a dropout is a pixel
    where it does not (0, no return, or a reading out of that range).

    * ``tof``: ToF vs truth where the ToF is valid;
    * ``model_on_tof_valid``: model vs truth on the same pixels (the fair comparison);
    * ``model``: model vs truth on every pixel with a true depth in range;
    * ``model_on_tof_dropout``: model vs truth on the ToF's dropouts;
    * ``tof_coverage``: share of the in-range true pixels where the ToF is valid.
    """
    in_range = in_depth_range(truth, min_depth, max_depth)
    tof_valid = in_depth_range(tof, min_depth, max_depth)
    kw = {"min_depth": min_depth, "max_depth": max_depth}
    return {
        "tof": depth_metrics(tof, truth, mask=tof_valid, **kw),
        "model_on_tof_valid": depth_metrics(pred, truth, mask=tof_valid, **kw),
        "model": depth_metrics(pred, truth, **kw),
        "model_on_tof_dropout": depth_metrics(pred, truth, mask=~tof_valid, **kw),
        "tof_coverage": float((in_range & tof_valid).sum() / max(int(in_range.sum()), 1)),
    }


def per_object_metrics(
    pred: np.ndarray, gt: np.ndarray, object_name: np.ndarray, min_depth: float, max_depth: float
) -> dict[str, dict]:
    """``trainer.metrics.depth_metrics`` of each object's frames, by object name in sorted order.

    ``pred``, ``gt``: ``(N,H,W) float32 m``; ``object_name``: ``(N,)`` str, the object pressed in
    each frame (frames of no object, ``""``, are left out).
    """
    kw = {"min_depth": min_depth, "max_depth": max_depth}
    return {
        name: depth_metrics(pred[object_name == name], gt[object_name == name], **kw)
        for name in sorted(set(object_name) - {""})
    }


def evaluate_model(
    model_dir: str | Path,
    paths: list[str | Path],
    objects: list[str] | None = None,
    runtime: str | None = None,
    latency_repeats: int = 30,
) -> dict:
    """Metrics of ``model_dir`` on the contact frames of ``paths`` (dict, JSON-serializable).

    Top level: the ``trainer.metrics`` keys vs the ToF, ``latency_ms`` (median batch-1 latency
    of ``predict`` on this machine), ``runtime``, ``per_object`` metrics, ``sensors_not_trained_on``
    (the data's sensor serials that no training session of the model came from), and ``vs_true`` on
    simulated data. Raises ``InputError`` for bad files or frames of another size than the model's.
    """
    check_each_session_once({"--data": paths})  # a session twice would count its frames twice
    estimator = DepthEstimator.load(model_dir, runtime=runtime)
    meta = estimator.metadata
    frames = load_frames(paths, objects=objects, phases=CONTACT_PHASES, free_fraction=0.0)
    check_each_recording_once({"--data": frames.sources})
    if frames.size != estimator.native_size:
        raise InputError(
            f"sessions hold {frames.size[1]}x{frames.size[0]} frames, the model was trained on "
            f"{estimator.native_size[1]}x{estimator.native_size[0]} frames"
        )
    if not in_depth_range(frames.depth, meta.min_depth, meta.max_depth).any():  # (before the prediction's time)
        raise no_depth_in_range(f"no contact frame of {', '.join(map(str, paths))}", meta.min_depth, meta.max_depth,
                                "compare the model with")
    pred = predict_frames(estimator, frames.ir)
    kw = {"min_depth": meta.min_depth, "max_depth": meta.max_depth}
    result: dict = dict(depth_metrics(pred, frames.depth, **kw))
    result["latency_ms"] = estimator.latency_ms(ir=frames.ir[0], repeats=latency_repeats)
    result["runtime"] = estimator.runtime
    result["model"] = str(model_dir)
    result["arch"] = meta.arch
    result["data"] = [s.to_dict() for s in frames.sources]
    result["sensors_not_trained_on"] = meta.sensors_not_trained_on(s.sensor_serial for s in frames.sources)
    result["per_object"] = per_object_metrics(pred, frames.depth, frames.object_name, meta.min_depth, meta.max_depth)
    if frames.true_depth is not None:
        result["vs_true"] = compare_with_truth(pred, frames.depth, frames.true_depth, meta.min_depth, meta.max_depth)
    return result
