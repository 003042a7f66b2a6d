"""Deployed inference: ``DepthEstimator.load(model_dir).predict(ir) -> depth``.

Runs the network through ONNX Runtime when the model directory says so (``metadata.json``
``inference.runtime == "onnx"``, set by ``trainer.onnx_export`` when ORT matches torch to 1e-4
and is faster), else through torch. Frames go in and come out at the sensor's native size.

An ONNX file is run only when it is this model's export (``onnx_session``): the SHA-256 of
``model.onnx`` that the export recorded (``inference.onnx_sha256``; folders exported before it was
recorded are not checked for it) and the input size of ``metadata.json``. The weights it was
exported from are the ones ``load_network`` loads and checks (``inference.weights_sha256``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from collect.errors import InputError
from trainer.model_dir import ONNX_FILE, ModelMetadata, load_network, model_file_sha256, resolve_model_dir
from trainer.preprocessing import MAX_IR

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


def onnx_session(model_dir: Path, metadata: ModelMetadata):
    """An ``ort_session`` of ``model_dir``'s ``model.onnx``, refused with ``InputError`` (naming the file
    and the way out) unless it is the export of this model: the SHA-256 of ``model.onnx`` equals the one
    ``metadata.inference`` records (when recorded; the weights': ``load_network``), and its one input
    is ``ir`` ``(batch, 1, input_height, input_width)`` with a free batch size."""
    path = model_dir / ONNX_FILE
    way_out = "delete it to run the model in torch, or export it again (trainer.onnx_export.export_and_select_runtime)"
    recorded = metadata.inference.get("onnx_sha256")
    if recorded is not None and model_file_sha256(model_dir, ONNX_FILE) != recorded:  # (the weights: load_network's)
        raise InputError(f"{path} is not the ONNX export that {model_dir} records (another SHA-256): {way_out}")
    session = ort_session(path)
    g = metadata.geometry
    inputs = session.get_inputs()
    shape = list(inputs[0].shape) if len(inputs) == 1 and inputs[0].name == "ir" else []
    if not (len(shape) == 4 and not isinstance(shape[0], int) and shape[1:] == [1, g.input_height, g.input_width]):
        got = ", ".join(f"{i.name} ({', '.join(map(str, i.shape))})" for i in inputs)
        raise InputError(f"{path} takes {got}, the model needs ir (batch, 1, {g.input_height}, {g.input_width}): "
                         f"{way_out}")
    return session


class DepthEstimator:
    """A trained depth network ready for inference on native IR frames."""

    def __init__(self, network: torch.nn.Module, metadata: ModelMetadata, runtime: str, model_dir: Path):
        self.network = network.eval()
        self.metadata = metadata
        self.runtime = runtime
        self.model_dir = model_dir
        self._session = onnx_session(model_dir, metadata) if runtime == "onnx" else None

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
        """IR amplitude ``(N,H,W) uint16`` (native size) -> depth ``(N,H,W) float32 m``.

        Frames of another dtype must hold amplitudes in [0, ``MAX_IR``]: ``InputError`` naming the
        first frame (index in the batch) that holds NaN, inf, negative or larger values.
        """
        ir = np.asarray(ir)
        if ir.ndim != 3:
            raise InputError(f"IR frames must be (N,H,W), got shape {ir.shape}")
        if ir.dtype != np.uint16:
            bad = ~((ir >= 0) & (ir <= MAX_IR)).all(axis=(1, 2))  # NaN fails both comparisons
            if bad.any():
                i = int(np.argmax(bad))
                held = "NaN or inf" if not np.isfinite(ir[i]).all() else f"values {ir[i].min():g} to {ir[i].max():g}"
                raise InputError(f"IR frame {i} holds {held}: an IR amplitude is 0 to {MAX_IR} (uint16)")
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
