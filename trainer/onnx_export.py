"""ONNX export of a model directory and the choice of its deployed inference runtime.

``export_and_select_runtime(model_dir)`` writes ``model.onnx`` (``torch.onnx.export``, input
``ir`` ``(B,1,h,w) float32`` normalized, output ``depth`` ``(B,1,h,w) float32 m``), checks
ONNX Runtime against torch on the same inputs (batches of 1 and 3), times both (batch 1), and records in ``metadata.json``
under ``inference``: ``runtime`` (``"onnx"`` when ORT matches to ``ORT_TOLERANCE_M`` and is not
slower, else ``"torch"``), ``onnx_max_abs_diff_m``, ``onnx_ms``, ``torch_ms``, and ``onnx_sha256``,
``weights_sha256`` (hex SHA-256 of ``model.onnx`` and of the ``model.safetensors`` it was exported
from), which tie the ONNX file to the weights: ``trainer.inference.onnx_session`` refuses another.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from collect.atomic_files import replacing
from trainer.inference import DepthEstimator, onnx_session
from trainer.model_dir import ONNX_FILE, export_hashes, load_network, write_metadata

#: Largest allowed |ORT - torch| depth difference (m) for ORT to be used.
ORT_TOLERANCE_M = 1e-4
ONNX_OPSET = 17


def export_onnx(network: torch.nn.Module, input_size: tuple[int, int], path: str | Path) -> Path:
    """Export ``network`` for input ``(B,1,h,w)`` (``input_size`` = (h, w), any batch B) to ``path``
    (atomically: ``collect.atomic_files.replacing``)."""
    path = Path(path)
    example = torch.zeros(1, 1, *input_size)
    with warnings.catch_warnings(), replacing(path) as tmp:
        warnings.simplefilter("ignore")
        torch.onnx.export(
            network.eval(),
            (example,),
            str(tmp),
            dynamo=False,
            input_names=["ir"],
            output_names=["depth"],
            opset_version=ONNX_OPSET,
            dynamic_axes={"ir": {0: "batch"}, "depth": {0: "batch"}},
        )
    return path


def export_and_select_runtime(model_dir: str | Path, repeats: int = 20, seed: int = 0) -> dict:
    """Export ``model_dir``'s network to ONNX, verify and time it; returns the ``inference`` metadata."""
    model_dir = Path(model_dir)
    network, metadata = load_network(model_dir)
    g = metadata.geometry
    export_onnx(network, (g.input_height, g.input_width), model_dir / ONNX_FILE)
    hashes = export_hashes(model_dir)
    metadata.inference = hashes  # what the sessions below check the new file against
    session = onnx_session(model_dir, metadata)
    rng = np.random.default_rng(seed)
    max_diff = 0.0
    for batch in (1, 3):
        x = rng.standard_normal((batch, 1, g.input_height, g.input_width)).astype(np.float32)
        with torch.inference_mode():
            ref = network(torch.from_numpy(x)).numpy()
        out = session.run(None, {"ir": x})[0]
        max_diff = float(np.max([max_diff, np.max(np.abs(out - ref))]))  # NaN stays (max() dropped it: a match)
    latencies = {}
    for runtime in ("torch", "onnx"):
        latencies[runtime] = DepthEstimator(network, metadata, runtime, model_dir).latency_ms(repeats=repeats)
    matches = max_diff <= ORT_TOLERANCE_M
    chosen = "onnx" if matches and latencies["onnx"] <= latencies["torch"] else "torch"
    metadata.inference = {
        **hashes,
        "runtime": chosen,
        "onnx_file": ONNX_FILE,
        "onnx_opset": ONNX_OPSET,
        "onnx_max_abs_diff_m": max_diff,
        "onnx_matches_torch": matches,
        "tolerance_m": ORT_TOLERANCE_M,
        "onnx_ms": latencies["onnx"],
        "torch_ms": latencies["torch"],
    }
    write_metadata(model_dir, metadata)
    return metadata.inference
