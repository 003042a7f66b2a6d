"""Inference benchmark: batch-1 latency of every architecture and width at 224 x 224 on this CPU.

    .venv/bin/python benchmarks/bench_inference.py            # writes the inference section of docs/bench_trainer.md
    .venv/bin/python benchmarks/bench_inference.py --repeats 50 --widths 0.25 0.375 0.5

For each (arch, width): a freshly initialized network (latency does not depend on the weights)
saved as a model directory for the default 224 x 172 sensor, exported to ONNX and checked
against torch (``trainer.onnx_export``); then the median wall time of
``DepthEstimator.predict`` (the deployed path: normalization, padding, network, crop) on one
native frame, batch 1, through torch and through ONNX Runtime. Target: >= 60 fps (<= 16.7 ms)
for the default model. The page's provenance line (``benchmarks/machine.py``) says what the CPU was
shared with: numbers taken while other processes used more than a quarter of a core are marked
provisional.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.arguments import positive_float, positive_int, run_main  # noqa: E402
from benchmarks.machine import machine_info, provenance  # noqa: E402
from trainer.doc_sections import BENCH_TRAINER_HEADER, update_section  # noqa: E402
from trainer.inference import DepthEstimator  # noqa: E402
from trainer.model_dir import ModelMetadata, save_model  # noqa: E402
from trainer.networks import build_network  # noqa: E402
from trainer.onnx_export import export_and_select_runtime  # noqa: E402
from trainer.preprocessing import InputGeometry, IRNormalization  # noqa: E402
from trainer.training_defaults import ARCH_NAMES, DEFAULT_ARCH, DEFAULT_MAX_DEPTH, DEFAULT_MIN_DEPTH, DEFAULT_WIDTHS  # noqa: E402

TARGET_MS = 1000.0 / 60.0


def measure(arch: str, width: float, repeats: int, workdir: Path) -> dict:
    torch.manual_seed(0)
    net = build_network(arch, width, DEFAULT_MIN_DEPTH, DEFAULT_MAX_DEPTH)
    meta = ModelMetadata(arch, width, DEFAULT_MIN_DEPTH, DEFAULT_MAX_DEPTH, InputGeometry(172, 224, 224, 224),
                         IRNormalization(mean=8.0, std=1.0))
    model_dir = save_model(workdir / f"{arch}_{width}", net, meta)
    info = export_and_select_runtime(model_dir)  # as `bubble train` exports: its default repeats
    ir = np.random.default_rng(0).integers(500, 20000, (172, 224), dtype=np.uint16)
    row = {"arch": arch, "width": width, "params_m": sum(p.numel() for p in net.parameters()) / 1e6,
           "max_diff": info["onnx_max_abs_diff_m"]}
    for runtime in ("torch", "onnx"):
        row[runtime] = DepthEstimator.load(model_dir, runtime=runtime).latency_ms(ir, repeats=repeats, warmup=5)
    row["deployed"] = info["runtime"]
    row["deployed_ms"] = row[info["runtime"]]
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=positive_int, default=50, help="timed runs per model and runtime")
    parser.add_argument("--widths", type=positive_float, nargs="+", default=[0.25, 0.375, 0.5],
                        help="network widths to time, besides each architecture's default")
    parser.add_argument("--threads", type=positive_int, default=os.cpu_count(), help="torch CPU threads (default: all)")
    parser.add_argument("--no-doc", action="store_true", help="print only, do not update docs/bench_trainer.md")
    args = parser.parse_args()
    info = machine_info()
    torch.set_num_threads(args.threads)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for arch in ARCH_NAMES:
            for width in sorted(set(args.widths) | {DEFAULT_WIDTHS[arch]}):
                row = measure(arch, width, args.repeats, Path(tmp))
                rows.append(row)
                print(f"{arch:8s} w={width:<6} torch {row['torch']:7.2f} ms  onnx {row['onnx']:7.2f} ms  "
                      f"({1000 / row['deployed_ms']:.0f} fps deployed, max |ort-torch| {row['max_diff']:.1e} m)")
    lines = [
        f"{provenance(info)} Torch {torch.__version__}, {args.threads} threads.",
        "",
        "Median wall time of `DepthEstimator.predict` on one 224 x 172 frame (normalize, pad to 224 x 224, "
        f"network, crop), batch 1, {args.repeats} runs. Target <= {TARGET_MS:.1f} ms (60 fps). "
        f"Default: `{DEFAULT_ARCH}` width {DEFAULT_WIDTHS[DEFAULT_ARCH]}.",
        "",
        "| arch | width | params (M) | torch ms | ONNX Runtime ms | max abs ORT-torch (m) | deployed | fps | >= 60 fps |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        default = " (default)" if r["arch"] == DEFAULT_ARCH and r["width"] == DEFAULT_WIDTHS[DEFAULT_ARCH] else ""
        lines.append(
            f"| {r['arch']}{default} | {r['width']} | {r['params_m']:.2f} | {r['torch']:.2f} | {r['onnx']:.2f} | "
            f"{r['max_diff']:.1e} | {r['deployed']} | {1000 / r['deployed_ms']:.0f} | "
            f"{'yes' if r['deployed_ms'] <= TARGET_MS else 'no'} |"
        )
    lines.append("")
    lines.append("Rerun: `.venv/bin/python benchmarks/bench_inference.py`")
    if not args.no_doc:
        update_section(ROOT / "docs" / "bench_trainer.md", "inference", "Inference latency (batch 1, 224 x 224)", lines, BENCH_TRAINER_HEADER)
    return 0


if __name__ == "__main__":
    run_main(main, "bench_inference")
