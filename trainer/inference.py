"""Deployed inference: ``DepthEstimator.load(model_dir).predict(ir) -> depth``.

Runs the network through ONNX Runtime when the model directory says so (``metadata.json``
``inference.runtime == "onnx"``, set by ``trainer.onnx_export`` when ORT matches torch to 1e-4
and is faster), else through torch. Frames go in and come out at the sensor's native size.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from collect.errors import InputError
from trainer.model_dir import ONNX_FILE, ModelMetadata, load_network, resolve_model_dir

RUNTIMES = ("onnx", "torch")


def ort_session(onnx_path: str | Path):
    """An ONNX Runtime CPU session for ``onnx_path`` (full graph optimization)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own untyped errors for bad files
        raise InputError(f"cannot load ONNX model {onnx_path}: {str(err).splitlines()[0]}") from None


class DepthEstimator:
    """A trained depth network ready for inference on native IR frames."""

    def __init__(self, network: torch.nn.Module, metadata: ModelMetadata, runtime: str, model_dir: Path):
        self.network = network.eval()
        self.metadata = metadata
        self.runtime = runtime
        self.model_dir = model_dir
        self._session = ort_session(model_dir / ONNX_FILE) if runtime == "onnx" else None

    @classmethod
    def load(cls, model_dir: str | Path, runtime: str | None = None) -> "DepthEstimator":
        """Load ``model_dir`` (or ``"base"``); ``runtime`` ``"onnx"``/``"torch"`` overrides the metadata's choice."""
        model_dir = resolve_model_dir(model_dir)
        network, metadata = load_network(model_dir)
        if runtime is not None and runtime not in RUNTIMES:
            raise InputError(f"unknown runtime {runtime!r}; choose one of {', '.join(RUNTIMES)}")
        if runtime == "onnx" and not (model_dir / ONNX_FILE).is_file():
            raise InputError(f"model directory {model_dir} has no {ONNX_FILE}")
        if runtime is None:
            wanted = metadata.inference.get("runtime", "torch")
            runtime = "onnx" if wanted == "onnx" and (model_dir / ONNX_FILE).is_file() else "torch"
        return cls(network, metadata, runtime, model_dir)

    @property
    def native_size(self) -> tuple[int, int]:
        """(height, width) of the sensor frames this model takes."""
        g = self.metadata.geometry
        return g.native_height, g.native_width

    def run_network(self, x: np.ndarray) -> np.ndarray:
        """Normalized input ``(N,1,h,w) float32`` -> depth ``(N,1,h,w) float32 m`` at network size."""
        if self._session is not None:
            return self._session.run(None, {"ir": x})[0]
        with torch.inference_mode():
            return self.network(torch.from_numpy(x)).numpy()

    def predict_batch(self, ir: np.ndarray) -> np.ndarray:
        """IR amplitude ``(N,H,W) uint16`` (native size) -> depth ``(N,H,W) float32 m``."""
        ir = np.asarray(ir)
        if ir.ndim != 3:
            raise InputError(f"IR frames must be (N,H,W), got shape {ir.shape}")
        if ir.dtype.kind == "f" and not np.isfinite(ir).all():
            raise InputError("IR frames hold NaN or inf")
        x = self.metadata.geometry.to_input(self.metadata.normalization.apply(ir))
        depth = self.run_network(np.ascontiguousarray(x[:, None]))
        return self.metadata.geometry.to_native(depth[:, 0]).astype(np.float32)

    def predict(self, ir: np.ndarray) -> np.ndarray:
        """IR amplitude ``(H,W) uint16`` (native size) -> depth ``(H,W) float32 m``."""
        ir = np.asarray(ir)
        if ir.ndim != 2:
            raise InputError(f"an IR frame must be (H,W), got shape {ir.shape}")
        return self.predict_batch(ir[None])[0]

    def latency_ms(self, ir: np.ndarray | None = None, repeats: int = 30, warmup: int = 3) -> float:
        """Median wall time (ms) of ``predict`` on one frame (``ir (H,W) uint16`` or a synthetic one), batch 1."""
        if ir is None:
            rng = np.random.default_rng(0)
            ir = rng.integers(200, 4000, size=self.native_size, dtype=np.uint16)
        for _ in range(warmup):
            self.predict(ir)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            self.predict(ir)
            times.append(time.perf_counter() - start)
        return float(np.median(times) * 1e3)
