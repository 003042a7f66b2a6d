"""Accuracy tables on simulated data: in-class and leave-one-object-out, per architecture.

    .venv/bin/python benchmarks/bench_accuracy.py                       # 3 archs x (in-class + 4 leave-outs), 3 min each
    .venv/bin/python benchmarks/bench_accuracy.py --minutes 1 --archs resnet --holdouts mug

Every network trains from scratch (like the paper's tables; the base model has seen every object
on other sensors, so it would blur the leave-one-out protocol) on one simulated calibration
session (seed ``--sensor-seed``) for ``--minutes`` of CPU training time each:

* in-class: the in-class pose split (70 % of each object's contact poses train, 30 % validate),
  and the paper's frame split (``--split frames``) for comparison;
* leave-one-object-out: train on the other objects, validate on the held-out one.

Paper (real data, 100 epochs on 8 V100s): in-class ResNet a1 0.955; leave-one-out PackNet
a1 0.65-0.83.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from trainer.doc_sections import BENCH_TRAINER_HEADER, update_section  # noqa: E402
from trainer.cli import PAPER_COLUMNS  # noqa: E402
from trainer.pretrain import DEFAULT_OBJECTS, collect_one  # noqa: E402
from trainer.training import TrainConfig, train_model  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--archs", nargs="+", default=["resnet", "packnet", "bts"])
    parser.add_argument("--holdouts", nargs="*", help="objects to leave out (default: every object)")
    parser.add_argument("--sensor-seed", type=int, default=11)
    parser.add_argument("--poses-per-object", type=int, default=8)
    parser.add_argument("--objects", default=DEFAULT_OBJECTS)
    parser.add_argument("--sim-speed", type=float, default=20.0, help="simulated clock speed (lower on a busy machine)")
    parser.add_argument("--work", help="keep the session and models here (default: a temporary directory)")
    parser.add_argument("--no-doc", action="store_true")
    args = parser.parse_args()
    holdouts = args.holdouts if args.holdouts is not None else args.objects.split(",")
    load_before = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        session = collect_one(work, args.sensor_seed, args.objects, args.poses_per_object, args.sim_speed)
        for arch in args.archs:
            settings = [("in-class (poses)", {"split": "poses"}), ("in-class (frames)", {"split": "frames"})]
            settings += [(f"leave out {name}", {"holdout_object": name}) for name in holdouts]
            for label, opts in settings:
                out = work / f"{arch}_{label.replace(' ', '_').replace('(', '').replace(')', '')}"
                r = train_model(TrainConfig(data=[str(session)], out=str(out), arch=arch, minutes=args.minutes,
                                            export_onnx=False, **opts))
                rows.append((arch, label, r))
                print(f"{arch:8s} {label:22s} a1 {r.metrics['a1']:.3f} abs_rel {r.metrics['abs_rel']:.4f}", flush=True)
    lines = [
        f"Measured {time.strftime('%Y-%m-%d %H:%M')} on {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} CPUs, load average {load_before:.1f} -> {os.getloadavg()[0]:.1f} (provisional on a busy machine).",
        "",
        f"One simulated sensor (seed {args.sensor_seed}), objects {args.objects}, {args.poses_per_object} poses each; "
        f"every model from scratch, {args.minutes} min of CPU training each, default widths; metrics vs the ToF depth "
        "on the validation frames.",
        "",
        "| arch | setting | " + " | ".join(h for _, h in PAPER_COLUMNS) + " | val frames | epochs |",
        "|---|---|" + "---|" * (len(PAPER_COLUMNS) + 2),
    ]
    for arch, label, r in rows:
        values = " | ".join(f"{r.metrics[k]:.4f}" for k, _ in PAPER_COLUMNS)
        lines.append(f"| {arch} | {label} | {values} | {r.metrics['n_val_frames']} | {r.epochs:.1f} |")
    lines += ["", "Rerun: `.venv/bin/python benchmarks/bench_accuracy.py`"]
    if not args.no_doc:
        update_section(ROOT / "docs" / "bench_trainer.md", "accuracy", "Accuracy on simulated data (in-class, leave-one-out)", lines, BENCH_TRAINER_HEADER)
    return 0


if __name__ == "__main__":
    sys.exit(main())
