"""Pose estimation benchmark: speed of the proximity fit and accuracy of the pose check.

    .venv/bin/python benchmarks/bench_pose.py                      # speed + accuracy (simulates data)
    .venv/bin/python benchmarks/bench_pose.py --session S.h5 --model MODEL_DIR   # accuracy on these
    .venv/bin/python benchmarks/bench_pose.py --speed-only         # page in runs/, docs/ keep the full run's
    .venv/bin/python benchmarks/bench_pose.py --work runs/bp   # keep the sessions and models there (reused by a rerun)

Speed (one core: BLAS/OpenMP threads pinned to 1 before numpy loads): pose estimates per second
with 1500 points on the mug's cylinder, a hold sequence warm-started from the previous frame, and
cold fits from a perturbed prior; plus the contact-patch extraction on a 224x172 depth frame.
Accuracy: ``run_pose_check`` on simulated sessions of the mug (predicted vs measured depth, and
each vs the true pose), the errors taken over the frames of all sessions together and per session.
Without ``--session``/``--model`` it records one session per sensor seed (``--seeds``, six new
sensors by default, about 26 minutes: one sensor's ratio to the ToF moves by 0.2-1.2 between
recordings of its seed, and three sensors pooled gave 2.02 where the same three and three more gave
1.61; docs/pose_unseen_object.md) with ``bubble collect --sim`` and fine-tunes the base model on each with ``bubble train``
(held out: the mug, so the check runs on an object this sensor's fine-tune never saw, as in the paper;
the base model it starts from was pretrained on other sensors pressing the mug among the other objects).
A session is recorded as ``session.partial.h5`` and renamed once whole; a ``--work`` model is reused
only where it was fine-tuned on that session. Writes ``docs/bench_pose.md`` (``--out``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.arguments import markdown_out, positive_float, run_main, sensor_seed_list, work_dir  # noqa: E402
from collect.atomic_files import write_text  # noqa: E402
from collect.errors import BubbleCommandError, InputError  # noqa: E402
from benchmarks.machine import machine_info, provenance  # noqa: E402
from calibrate.contact_patch import contact_points  # noqa: E402
from calibrate.pose_estimation import Pose, ProximityPoseEstimator, quat_to_matrix, shape_from_object  # noqa: E402
from hw_mocks.objects import load_object  # noqa: E402
from trainer.dataset import file_sha256  # noqa: E402
from trainer.model_dir import METADATA_FILE, load_metadata  # noqa: E402

#: The built-in mug's primitive: a cylinder lying on its side, axis along object x.
MUG = shape_from_object(load_object("mug").primitive)


def _mug_pose(rng) -> Pose:
    """A pose of the lying mug seen by a bubble pressing on its top (camera 93 mm above the apex)."""
    transform = np.eye(4)
    rot = Rotation.from_rotvec([np.pi, 0, 0]) * Rotation.from_rotvec([0, 0, rng.uniform(-0.5, 0.5)])
    transform[:3, :3] = rot.as_matrix()
    apex = transform[:3, :3] @ np.array([0.0, 0.0, MUG.center[2] + MUG.radius])
    transform[:3, 3] = np.array([0.0, 0.0, 0.093 - 0.004]) - apex
    return Pose.from_matrix(transform)


def _patch(pose: Pose, rng, n=1500, noise_m=1e-4) -> np.ndarray:
    """Points (n,3) m on the mug's top, a 50 x 30 mm patch, with Gaussian noise (camera frame)."""
    along = rng.uniform(-0.025, 0.025, n)
    ang = rng.uniform(-0.35, 0.35, n)  # +-14 mm around the top line
    obj = np.stack([along, MUG.radius * np.sin(ang), MUG.center[2] + MUG.radius * np.cos(ang)], axis=1)
    return obj @ quat_to_matrix(pose.quaternion).T + pose.position + rng.normal(0, noise_m, obj.shape)


def _perturb(pose: Pose, rng, mm: float, deg: float) -> Pose:
    transform = pose.matrix()
    axis = rng.normal(size=3)
    transform[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix() @ transform[:3, :3]
    shift = rng.normal(size=3)
    transform[:3, 3] += 1e-3 * mm * shift / np.linalg.norm(shift)
    return Pose.from_matrix(transform)


def bench_speed(n_frames: int = 300) -> dict:
    rng = np.random.default_rng(0)
    fitter = ProximityPoseEstimator(MUG)
    true = _mug_pose(rng)
    prior = _perturb(true, rng, 2.0, 2.0)
    clouds = []
    pose = true
    for _ in range(n_frames):  # a hold: the object creeps by ~20 um / 0.02 deg per frame
        pose = _perturb(pose, rng, 0.02, 0.02)
        clouds.append(_patch(pose, rng))
    fitter.fit(clouds[0], prior)  # warm-up
    start = time.perf_counter()
    warm, iters_warm = None, []
    for cloud in clouds:
        fit = fitter.fit(cloud, prior, start=warm)
        warm = fit.pose
        iters_warm.append(fit.iterations)
    warm_s = time.perf_counter() - start
    start = time.perf_counter()
    iters_cold = [fitter.fit(cloud, prior).iterations for cloud in clouds[:100]]
    cold_s = time.perf_counter() - start

    # contact patch: a 224x172 frame with a dent, against its reference
    h, w = 172, 224
    intr = {"fx": 160.0, "fy": 160.0, "cx": 111.5, "cy": 85.5}
    v, u = np.mgrid[0:h, 0:w]
    ref = (0.093 + 0.02 * (((u - 111.5) / 112) ** 2 + ((v - 85.5) / 86) ** 2)).astype(np.float32)
    depth = ref - 0.006 * np.exp(-((u - 100) ** 2 + (v - 90) ** 2) / (2 * 25.0**2)).astype(np.float32)
    contact_points(depth, ref, intr)
    start = time.perf_counter()
    for _ in range(200):
        contact_points(depth, ref, intr)
    patch_ms = (time.perf_counter() - start) / 200 * 1e3
    return {
        "warm_hz": n_frames / warm_s, "warm_iters": float(np.median(iters_warm)),
        "cold_hz": 100 / cold_s, "cold_iters": float(np.median(iters_cold)),
        "patch_ms": patch_ms,
        "end_to_end_hz": 1.0 / (warm_s / n_frames + patch_ms * 1e-3),
    }


def _bubble(*args: str) -> None:
    """Run ``bubble args``, its output shown as it goes; ``BubbleCommandError`` when it fails (was: a
    ``CalledProcessError`` traceback)."""
    print("+ bubble", " ".join(args), flush=True)
    code = subprocess.run([sys.executable, "-m", "calibrate.cli", *args], cwd=ROOT).returncode
    if code != 0:
        raise BubbleCommandError(f"bubble {args[0]} failed with exit {code} (its error is above)", code)


def simulated_inputs(workdir: Path, seed: int, minutes: float) -> tuple[Path, Path, bool]:
    """Record a simulated session of all built-in objects and fine-tune the base model without the mug.

    A session already in ``workdir``, and a finished model (its ``metadata.json`` follows the weights)
    fine-tuned on it, are reused, so that a rerun with the same ``--work`` checks the same data with the
    current code. The session is recorded as ``session.partial.h5`` and renamed once ``bubble collect``
    has recorded the whole plan (was: recorded in place, and the part a fault or a stop had kept was
    reused as a whole session by the next run). Returns the session, the model and whether both were
    reused."""
    workdir.mkdir(parents=True, exist_ok=True)
    session = workdir / "session.h5"
    model = workdir / "model"
    reused_session = session.exists()
    reused_model = (model / METADATA_FILE).exists()
    if reused_session:
        print(f"reusing {session}", flush=True)
    else:
        partial = session.with_suffix(".partial.h5")
        partial.unlink(missing_ok=True)
        _bubble("collect", "--sim", "--objects", "mug,wine_glass,box,fingers", "--poses-per-object", "8",
                "--seed", str(seed), "--out", str(partial))
        partial.replace(session)
    if reused_model:
        training = load_metadata(model).training
        if training["budget"]["minutes"] != minutes or training["split"].get("object") != "mug":
            raise InputError(f"{model} was fine-tuned for {training['budget']['minutes']} min with split "
                             f"{training['split']}, not --train-minutes {minutes:g} holding out the mug: use another "
                             "--work")
        if [source["sha256"] for source in training["sources"]] != [file_sha256(session)]:
            raise InputError(f"{model} was fine-tuned on other data than {session}: use another --work")
        print(f"reusing {model}", flush=True)
    else:
        _bubble("train", "--data", str(session), "--init", "base", "--holdout-object", "mug",
                "--minutes", str(minutes), "--out", str(model))
    return session, model, reused_session and reused_model


def bench_accuracy(inputs: list[tuple[str, Path, Path]], plots: Path) -> tuple[dict, list[tuple[str, dict, dict]]]:
    """The pose check on each ``(label, session, model)``: the pooled result over all their frames
    (histograms in ``plots``) and each one's, as ``to_dict()`` documents, with the model's
    ``training`` metadata."""
    from calibrate.pose_check import pooled_result, run_pose_check, write_histograms

    results = [(label, run_pose_check(model, session, "mug"), load_metadata(model).training)
               for label, session, model in inputs]
    pooled = pooled_result([r for _, r, _ in results])
    write_histograms(pooled, plots)
    return pooled.to_dict(), [(label, r.to_dict(), training) for label, r, training in results]


def _stats_row(name: str, e_x: dict, e_theta: dict) -> str:
    return (f"| {name} | {e_x['median']:.3f} | {e_x['mean']:.3f} | {e_x['variance']:.2e} | "
            f"{e_theta['median']:.2e} | {e_theta['mean']:.2e} | {e_theta['variance']:.2e} |")


def write_markdown(out: Path, speed: dict, accuracy: dict | None, per_session: list[tuple[str, dict, dict]],
                   command: str, reused: list[str], info: dict) -> None:
    """Write the page; ``per_session``: (label, pose check result, the model's ``training`` metadata);
    ``reused``: labels of the sessions whose recording and model came from an earlier run in
    ``--work`` (only the pose check ran again); ``info``: ``machine_info()`` at the run's start."""
    lines = [
        "# Pose estimation benchmark",
        "",
        f"Command: `{command}`  ",
        f"{provenance(info)} NumPy {np.__version__}; BLAS/OpenMP threads pinned to 1.",
        "",
        "## Speed (one core, 1500 points, the mug's cylinder)",
        "",
        "| what | rate | median Jacobian evaluations |",
        "|---|---|---|",
        f"| fit, warm-started from the previous frame (hold sequence) | {speed['warm_hz']:.0f} estimates/s | {speed['warm_iters']:.0f} |",
        f"| fit, cold from a prior 2 mm / 2 deg off | {speed['cold_hz']:.0f} estimates/s | {speed['cold_iters']:.0f} |",
        f"| contact patch of a 224x172 frame (mask, lift, downsample) | {speed['patch_ms']:.2f} ms | |",
        f"| patch + warm fit | {speed['end_to_end_hz']:.0f} estimates/s | |",
        "",
        "Target: >= 100 estimates/s (the paper: 5-10 Hz).",
        "",
    ]
    if accuracy is not None:
        lines += [
            "## Accuracy: the pose check on simulated mug sessions",
            "",
            f"{len(per_session)} session(s), errors over all their frames: {accuracy['n_used']} of "
            f"{accuracy['n_hold_frames']} hold frames used (skipped: "
            f"{', '.join(f'{k} {v}' for k, v in accuracy['skipped'].items() if v) or 'none'}); "
            f"{accuracy['hz']:.0f} pose estimates/s in the run."
            + (f" Recordings and fine-tuned models of {', '.join(reused)} reused from an earlier run "
               "in the same `--work` folder; only the pose check ran again." if reused else ""),
            "",
            "| comparison | e_x median (mm) | e_x mean | e_x variance (mm^2) | e_theta median | e_theta mean | e_theta variance |",
            "|---|---|---|---|---|---|---|",
            _stats_row("predicted vs measured depth", accuracy["e_x_mm"], accuracy["e_theta"]),
        ]
        for src, stats in accuracy["vs_true"].items():
            lines.append(_stats_row(f"{src} depth vs true pose", stats["e_x_mm"], stats["e_theta"]))
        lines += [
            "",
            "Targets: predicted vs measured median e_x <= 1.0 mm and median e_theta <= 3e-4 (the paper: "
            "1.6 mm and 5e-4); vs the true pose, predicted depth at least as good as the ToF depth "
            "(not met so far; what limits it and every change tried: docs/pose_unseen_object.md). "
            "e_x is measured at the cylinder's centre on its axis (since session 7; before, at the mug's "
            "origin on the fixture, 94 mm from the axis, where it mostly repeated e_theta times that lever "
            "arm), and errors are taken modulo the cylinder's symmetry (see docs/pose.md).",
            "",
            "Each session (median e_x, mm):",
            "",
            "| session | fine-tune (budget min, steps, held out) | frames used | predicted vs measured | " + " | ".join(
                f"{src} vs true" for src in accuracy["vs_true"]) + " |",
            "|---|---|---|---|" + "---|" * len(accuracy["vs_true"]),
        ]
        lines += [
            f"| {label} | {t['budget']['minutes'] or '-'}, {t['steps']}, {t['split'].get('object', t['split']['kind'])} | "
            f"{r['n_used']} | {r['e_x_mm']['median']:.3f} | "
            + " | ".join(f"{st['e_x_mm']['median']:.3f}" for st in r["vs_true"].values()) + " |"
            for label, r, t in per_session
        ]
        lines += [
            "",
            "![errors, predicted vs measured](bench_pose_plots/pose_errors.png)",
            "![errors vs the true pose](bench_pose_plots/pose_vs_true.png)",
            "",
        ]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, "\n".join(lines))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, help="simulated session with the mug (default: record one per --seeds)")
    ap.add_argument("--model", type=Path, help="model directory (default: fine-tune the base model)")
    ap.add_argument("--speed-only", action="store_true",
                    help="the fit's speed alone (its page goes to runs/bench_pose_speed.md unless --out is given)")
    ap.add_argument("--seeds", type=sensor_seed_list, default="0,1,2,3,4,5",
                    help="comma-separated seeds of the simulated sensors to record and fine-tune (default 0-5)")
    ap.add_argument("--train-minutes", type=positive_float, default=3.0)
    ap.add_argument("--work", type=work_dir, help="keep the recorded sessions and models here, or reuse those already there (default: a temporary folder)")
    ap.add_argument("--out", type=markdown_out,
                    help="the page (default: docs/bench_pose.md; with --speed-only, runs/bench_pose_speed.md, so that a "
                         "speed check leaves the committed page and its accuracy section)")
    args = ap.parse_args(argv)
    args.out = args.out or (ROOT / "runs" / "bench_pose_speed.md" if args.speed_only else ROOT / "docs" / "bench_pose.md")
    if (args.session is None) != (args.model is None):
        ap.error("give both --session and --model, or neither")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    command = "python benchmarks/bench_pose.py " + " ".join(argv if argv is not None else sys.argv[1:])
    info = machine_info()
    speed = bench_speed()
    print({k: round(v, 3) for k, v in speed.items()}, flush=True)
    accuracy, per_session, reused = None, [], []
    if not args.speed_only:
        with tempfile.TemporaryDirectory() as tmp:
            work = args.work or Path(tmp)
            if args.session is not None:
                inputs = [(str(args.session), args.session, args.model)]
            else:
                inputs = []
                for seed in args.seeds:
                    session, model, was_reused = simulated_inputs(work / f"seed_{seed}", seed, args.train_minutes)
                    inputs.append((f"sensor seed {seed}", session, model))
                    if was_reused:
                        reused.append(f"sensor seed {seed}")
            accuracy, per_session = bench_accuracy(inputs, args.out.parent / "bench_pose_plots")
    write_markdown(args.out, speed, accuracy, per_session, command.strip(), reused, info)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    run_main(main, "bench_pose")
