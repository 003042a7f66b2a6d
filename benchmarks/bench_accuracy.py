"""Accuracy on the simulated bench: the paper's Tables II-IV, and ToF vs model against the true depth.

    .venv/bin/python benchmarks/bench_accuracy.py           # full run: ~45 min on 2 cores (~35 with the sessions cached)
    .venv/bin/python benchmarks/bench_accuracy.py --quick   # ~5 min: tiny budgets, validates the script end to end
                                                            # (its page goes to runs/bench_accuracy_quick/, not docs/)
    .venv/bin/python benchmarks/bench_accuracy.py --reuse-models   # rebuild from the models kept in --work

Writes ``docs/bench_accuracy.md`` and ``docs/bench_accuracy.json`` (``--out``; with ``--quick``,
``runs/bench_accuracy_quick/bench_accuracy.md`` and ``.json`` unless ``--out`` is given). Everything goes
through the product: sessions are drawn and recorded with ``bubble sim new-sensor`` and
``bubble collect --sim`` (cached in ``--work``, so a rerun only retrains), networks are trained
with ``trainer.training.train_model`` (what ``bubble train`` runs) and evaluated with
``trainer.evaluation.evaluate_model`` (what ``bubble evaluate --json`` writes).

1. In-class (paper Table II): one simulated sensor (``--sensor-seed``), every architecture from
   scratch for ``--minutes`` of CPU training, 70/30 split within each object's data
   (``--splits``: ``frames`` = the paper's random frame split, ``poses`` = held-out contact poses);
   plus the base model fine-tuned with the same budget (the product's path).
2. Leave-one-object-out (Table III): the same sensor, train on the other objects, validate on the
   held-out one, per architecture and object.
3. Cross-sensor (Table IV): new sensors (``--cross-seeds``; refused when the base model trained on
   them), each with a sub-minute calibration set (``--calib-poses`` per object) and a separate test
   session (other poses, ``--test-poses`` per object). Zero-shot: the base model, and the in-class
   model of sensor A (the paper's train-on-A, test-on-B). Then the base model fine-tuned on the
   calibration set for ``--finetune-minutes`` (commissioning's default budget), tested on the test session.
4. ToF vs model against the true membrane depth on those test sessions (``vs_true``): RMSE and
   delta<1.05 of the ToF, of the model on the same pixels, on every pixel, and where the ToF dropped out.

Metrics (``trainer.metrics``) are against the ToF depth except in section 4. Models train from scratch in
1-2 (as in the paper's tables; the base model has seen every object, which would blur the
leave-one-out protocol).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.arguments import (markdown_out, model_dir, name_list, object_names, poses_per_object, positive_float,  # noqa: E402
                                 run_main, sensor_seed, sensor_seed_list, sim_speed, work_dir)
from benchmarks.machine import finish, machine_info, machine_line, provisional_note  # noqa: E402
from calibrate.commission_config import CommissionConfig  # noqa: E402
from collect.atomic_files import write_text  # noqa: E402
from collect.errors import EXIT_FAULT  # noqa: E402
from collect.session_info import session_summary  # noqa: E402
from hw_mocks.objects import BUILTIN_OBJECTS  # noqa: E402
from hw_mocks.sensor_spec import simulated_serial  # noqa: E402
from collect.json_files import write_json  # noqa: E402
from trainer.cli import PAPER_COLUMNS  # noqa: E402
from trainer.evaluation import evaluate_model  # noqa: E402
from trainer.dataset import file_sha256  # noqa: E402
from trainer.model_dir import METADATA_FILE, load_metadata, weights_sha256  # noqa: E402
from trainer.splits import SPLITS  # noqa: E402
from trainer.training import TrainConfig, train_model  # noqa: E402
from trainer.training_defaults import ARCH_NAMES  # noqa: E402

#: Longest a ``bubble`` command may run (a 4 x 8 session takes ~1-3 min; a hung one is killed and resumed).
COMMAND_TIMEOUT_S = 600.0
#: Seconds of training between live validations: only the final validation enters the tables.
EVAL_INTERVAL_S = 60.0
#: ``bubble collect`` runs per session: a fault (twins starved on a loaded machine) resumes at half the
#: simulated clock speed, down to real time.
COLLECT_ATTEMPTS = 6
#: Settings of ``--quick``: every section runs, on tiny sessions and budgets (not results).
QUICK = {"minutes": 0.15, "holdouts": "mug", "poses_per_object": 2, "cross_seeds": [21], "calib_poses": 2,
         "test_poses": 1, "finetune_minutes": 0.25}
#: Paper reference numbers (real data, 8 V100s), shown next to the tables.
PAPER = {
    "in_class": "in-class ResNet Abs.Rel 0.017, RMSE 0.008 m, δ<1.05 0.955",
    "leave_one_out": "leave-one-out PackNet δ<1.05 0.65-0.83",
    "cross_sensor": "cross-camera zero-shot δ<1.05 0.39-0.82",
}


def bubble(*argv: str, may_fault: bool = False) -> bool:
    """Run one ``bubble`` command; exit with its last error line when it fails.

    With ``may_fault``, a hardware fault (exit 3), a kill by a signal or a run over ``COMMAND_TIMEOUT_S``
    returns False instead (the caller may resume).
    """
    try:
        proc = subprocess.run([sys.executable, "-m", "calibrate.cli", *argv], capture_output=True, text=True, cwd=ROOT,
                              timeout=COMMAND_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        if may_fault:
            print(f"`bubble {argv[0]}` still running after {COMMAND_TIMEOUT_S:.0f} s: killed", flush=True)
            return False
        sys.exit(f"bench_accuracy: `bubble {' '.join(argv)}` still running after {COMMAND_TIMEOUT_S:.0f} s: killed")
    last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
    if (proc.returncode == EXIT_FAULT or proc.returncode < 0) and may_fault:  # a fault, or killed (hung)
        print(f"`bubble {argv[0]}` stopped on a fault ({last})", flush=True)
        return False
    if proc.returncode != 0:
        sys.exit(f"bench_accuracy: `bubble {' '.join(argv)}` failed (exit {proc.returncode}): {last}")
    return True


def sensor_spec(work: Path, seed: int) -> Path:
    """``bubble sim new-sensor --seed`` into ``work`` (kept between runs)."""
    spec = work / f"sensor_{seed:05d}.yaml"
    if not spec.exists():
        bubble("sim", "new-sensor", "--seed", str(seed), "--out", str(spec))
    return spec


def record(work: Path, seed: int, objects: str, poses: int, pose_seed: int, sim_speed: float) -> Path:
    """``bubble collect --sim`` of sensor ``seed`` (cached by sensor, objects, poses and pose seed)."""
    out = work / f"sensor_{seed:05d}_{objects.replace(',', '+')}_k{poses}_plan{pose_seed}.h5"
    if out.exists():
        return out
    spec = sensor_spec(work, seed)
    partial = out.with_suffix(".partial.h5")
    partial.unlink(missing_ok=True)
    t0 = time.perf_counter()
    argv = ["collect", "--sim", "--sensor", str(spec), "--objects", objects, "--poses-per-object", str(poses),
            "--seed", str(pose_seed), "--quiet", "--out", str(partial)]
    for attempt in range(COLLECT_ATTEMPTS):  # a loaded machine can starve the twins: resume, slower
        resume = ["--resume"] if partial.exists() else []
        speed = max(sim_speed / 2**attempt, min(sim_speed, 1.0))
        if bubble(*argv, "--sim-speed", str(speed), *resume, may_fault=attempt < COLLECT_ATTEMPTS - 1):
            break
    partial.replace(out)
    print(f"recorded {out.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def recording(path: Path) -> dict:
    """Frames and recording time (s) of a session: ``session_summary``'s ``duration_s``, what ``bubble info`` shows
    (the simulated camera's clock runs with the bench clock; the pauses before a ``--resume`` do not count)."""
    info = session_summary(path)
    return {"path": str(path), "frames": info["frames"], "record_s": info["duration_s"]}


def reusable(out: Path, config: dict) -> dict | None:
    """The result of a finished model in ``out`` trained with the same budget from the same init weights on the same
    recordings, else None. The recordings are compared by their SHA-256, and so is the init model's weights where
    the model recorded them (``training.init.weights_sha256``); a model trained before that was recorded is
    compared by the init's recorded validation metrics (was: by the init's name alone, so that a changed base
    model kept the fine-tunes of the old one)."""
    if not (out / METADATA_FILE).is_file():
        return None
    meta = load_metadata(out)
    t = meta.training
    init, recorded = config.get("init"), t["init"] or {}
    if init:
        same_init = (recorded.get("model_dir") == init and (recorded["weights_sha256"] == weights_sha256(init)
                                                            if "weights_sha256" in recorded else
                                                            recorded.get("metrics") == load_metadata(init).metrics))
    else:
        same_init = not recorded
    same = (t["budget"].get("minutes") == config["minutes"] and same_init
            and [(src["path"], src["sha256"]) for src in t["sources"]]
            == [(path, file_sha256(path)) for path in config["data"]]
            and [(src["path"], src["sha256"]) for src in t["val_sources"]]
            == [(path, file_sha256(path)) for path in config.get("val_data", [])])
    return {"model": str(out), "metrics": meta.metrics, "epochs": t["epochs"], "steps": t["steps"],
            "train_min": t["train_s"] / 60} if same else None


def train(work: Path, name: str, reuse: bool = False, **config) -> dict:
    """``train_model`` into ``work/models/name``; the final validation metrics and the budget used.

    With ``reuse``, a model already there from the same data, init and budget is taken as it is.
    """
    if reuse and (kept := reusable(work / "models" / name, config)):
        print(f"{name:32s} reused (a1 {kept['metrics']['a1']:.3f})", flush=True)
        return kept
    r = train_model(TrainConfig(out=str(work / "models" / name), export_onnx=False, eval_interval_s=EVAL_INTERVAL_S,
                                **config))
    print(f"{name:32s} a1 {r.metrics['a1']:.3f} abs_rel {r.metrics['abs_rel']:.4f} "
          f"({r.epochs:.1f} epochs, {r.train_s / 60:.2f} min)", flush=True)
    return {"model": str(r.model_dir), "metrics": r.metrics, "epochs": r.epochs, "steps": r.steps,
            "train_min": r.train_s / 60}


def evaluate(model: str | Path, session: Path) -> dict:
    return evaluate_model(model, [session], latency_repeats=3)


def base_model_serials(base_model: str) -> set[str]:
    """Serials of the sensors the base model trained and validated on."""
    training = load_metadata(base_model).training
    return {src.get("sensor_serial") for src in training.get("sources", []) + training.get("val_sources", [])}


def paper_cells(m: dict) -> str:
    """The paper's columns as ``bubble evaluate`` prints them (``trainer.cli.PAPER_COLUMNS``: RMSE in mm)."""
    return " | ".join(f"{m[key] * scale:.{decimals}f}" for key, _, scale, decimals in PAPER_COLUMNS)


def paper_header(first: list[str], last: list[str]) -> list[str]:
    heads = first + [h for _, h, _, _ in PAPER_COLUMNS] + last
    return ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]


def markdown(res: dict) -> str:
    s = res["settings"]
    lines = [
        "# Accuracy on the simulated bench (paper Tables II-IV)",
        "",
        f"Command: `{res['command']}`  ",
        machine_line(res["machine"]) + f" Wall time {res['wall_min']:.1f} min." + provisional_note(res["machine"]),
        "",
    ]
    if s.get("reuse_models"):
        lines += ["Models already in the work directory from an earlier run with the same data, init and budget were "
                  "reused (`--reuse-models`): the wall time covers only what this run recorded, trained and evaluated.",
                  ""]
    if s["quick"]:
        lines += ["**Quick validation run** (`--quick`): tiny sessions and budgets that only check the script end to "
                  "end. These are not benchmark results; rerun without `--quick`.", ""]
    lines += [
        "Every number comes from the product's own path: `bubble sim new-sensor`, `bubble collect --sim`, "
        "`train_model` (= `bubble train`), `evaluate_model` (= `bubble evaluate --json`). Metrics as in `trainer/metrics.py`, "
        "against the ToF depth (the sensor's own supervision) unless the table says *true depth*.",
        "",
        "## In-class (Table II)",
        "",
        f"Sensor seed {s['sensor_seed']}, objects {s['objects']}, {s['poses_per_object']} contact poses each "
        f"({res['sensor_a']['frames']} frames); every network from scratch (init `-`), {s['minutes']} min of CPU "
        f"training (default width), 70/30 split within each object's data: `frames` = random frames (the paper's), "
        f"`poses` = held-out contact poses. Init `base`: the packaged base model fine-tuned with the same budget "
        f"(the product's path; it was pretrained on other sensors pressing the same objects). "
        f"Paper (real data, 100 epochs): {PAPER['in_class']}.",
        "",
        *paper_header(["arch", "init", "split"], ["val frames", "epochs"]),
    ]
    for r in res["in_class"]:
        lines.append(f"| {r['arch']} | {r.get('init') or '-'} | {r['split']} | {paper_cells(r['metrics'])} | "
                     f"{r['metrics']['n_val_frames']} | {r['epochs']:.1f} |")
    lines += [
        "",
        "## Leave one object out (Table III)",
        "",
        f"Same sensor and budget; train on the other objects, validate on the held-out one. Paper: {PAPER['leave_one_out']}.",
        "",
        *paper_header(["arch", "held-out object"], ["val frames", "epochs"]),
    ]
    for r in res["leave_one_out"]:
        lines.append(f"| {r['arch']} | {r['holdout']} | {paper_cells(r['metrics'])} | {r['metrics']['n_val_frames']} | "
                     f"{r['epochs']:.1f} |")
    lines += [
        "",
        "## Cross-sensor (Table IV)",
        "",
        f"New simulated sensors (seeds {s['cross_seeds']}, never seen by the base model `{s['base_model']}`). "
        f"Calibration set: {s['calib_poses']} poses per object; test set: another session of the same sensor "
        f"({s['test_poses']} other poses per object). Zero-shot: the base model, and sensor A's in-class "
        f"`{res['sensor_a_model_arch']}` model (train on A, test on B, as in the paper); fine-tuned: the base model "
        f"after {s['finetune_minutes']} min of fine-tuning on the calibration set. Paper: {PAPER['cross_sensor']}.",
        "",
        *paper_header(["sensor", "model"], ["calibration set"]),
    ]
    for r in res["cross_sensor"]:
        calib = f"{r['calib']['frames']} frames, {r['calib']['record_s']:.0f} s"
        lines.append(f"| {r['seed']} | base, zero-shot | {paper_cells(r['zero_shot_base'])} | - |")
        lines.append(f"| {r['seed']} | sensor A, zero-shot | {paper_cells(r['zero_shot_sensor_a'])} | - |")
        lines.append(f"| {r['seed']} | base + fine-tune ({r['finetune']['train_min']:.1f} min) | "
                     f"{paper_cells(r['finetuned'])} | {calib} |")
    lines += [
        "",
        "Calibration set time: recording time on the simulated bench clock, as `bubble info` reports it (a "
        "recording resumed after a fault on a loaded machine counts every attempt's frames, not the pauses between "
        "them). The product's promise: under a minute.",
        "",
        "## ToF vs model against the true depth",
        "",
        "The fine-tuned models of the cross-sensor table on their test sessions, against the simulator's true "
        "membrane depth (`bubble evaluate` → `vs_true`). Coverage: share of the membrane pixels (true depth in "
        "range) that have a depth; the ToF drops out at close range, weak signal and grazing angles, the model "
        "gives every pixel. The model learned from the ToF alone.",
        "",
        "| sensor | depth | pixels | RMSE [mm] | Abs.Rel | δ<1.05 | coverage |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res["cross_sensor"]:
        vs = r["vs_true"]
        rows = [("ToF", "ToF valid", vs["tof"], f"{vs['tof_coverage'] * 100:.1f} %"),
                ("model", "ToF valid", vs["model_on_tof_valid"], ""),
                ("model", "ToF dropouts", vs["model_on_tof_dropout"], f"+{(1 - vs['tof_coverage']) * 100:.1f} %"),
                ("model", "all membrane", vs["model"], "100 %")]
        for depth, pixels, m, cov in rows:
            cells = (f"{m['rmse'] * 1e3:.3f} | {m['abs_rel']:.4f} | {m['a1']:.4f}" if m.get("n_images")
                     else "- | - | -")
            lines.append(f"| {r['seed']} | {depth} | {pixels} | {cells} | {cov} |")
    work = Path(s["work"])
    shown = work.relative_to(ROOT) if work.is_relative_to(ROOT) else work
    lines += ["", f"Data and models: `{shown}`; numbers also in `{Path(res['json']).name}`.", ""]
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="tiny budgets (~5 min) to validate the script; overrides budgets")
    p.add_argument("--archs", type=name_list(ARCH_NAMES), default=",".join(ARCH_NAMES),
                   help=f"comma-separated architectures among {', '.join(ARCH_NAMES)} (default: all)")
    p.add_argument("--minutes", type=positive_float, default=1.0, help="CPU training minutes per from-scratch run (sections 1-2)")
    p.add_argument("--splits", type=name_list(SPLITS), default="frames",
                   help="comma-separated in-class splits: frames (the paper's), poses, or frames,poses for both")
    p.add_argument("--holdouts", type=object_names, default=",".join(BUILTIN_OBJECTS), help="objects to leave out, one run each")
    p.add_argument("--objects", type=object_names, default=",".join(BUILTIN_OBJECTS))
    p.add_argument("--sensor-seed", type=sensor_seed, default=11, help="sensor A of sections 1-2")
    p.add_argument("--poses-per-object", type=poses_per_object, default=8, help="sensor A's session")
    p.add_argument("--cross-seeds", type=sensor_seed_list, default="21,22,23",
                   help="comma-separated seeds of the new sensors of sections 3-4")
    p.add_argument("--calib-poses", type=poses_per_object, default=6, help="calibration poses per object (4 x 6: ~45 s of recording)")
    p.add_argument("--test-poses", type=poses_per_object, default=3, help="test poses per object")
    p.add_argument("--finetune-minutes", type=positive_float, default=CommissionConfig.finetune_minutes)
    p.add_argument("--base-model", type=model_dir, default="base", help="pretrained model (default: the packaged base model)")
    p.add_argument("--sim-speed", type=sim_speed, default=20.0, help="simulated clock speed of bubble collect")
    p.add_argument("--work", type=work_dir, help="sessions and models (default: runs/bench_accuracy[_quick])")
    p.add_argument("--reuse-models", action="store_true",
                   help="keep models in --work trained on the same data, init and budget (rebuild the tables cheaply)")
    p.add_argument("--out", type=markdown_out, help="markdown, JSON next to it (default: docs/bench_accuracy.md; with --quick, "
                                            "bench_accuracy.md in --work, so that a check leaves the committed page)")
    args = p.parse_args(argv)
    if args.quick:
        for key, value in QUICK.items():
            setattr(args, key, value)
    strangers = [name for name in args.holdouts.split(",") if name not in args.objects.split(",")]
    if strangers:  # was: its leave-one-out run validated on no frame of it
        p.error(f"--holdouts: {strangers[0]} is not among --objects {args.objects}")
    args.work = (args.work or ROOT / "runs" / ("bench_accuracy_quick" if args.quick else "bench_accuracy")).resolve()
    args.out = args.out or (args.work if args.quick else ROOT / "docs") / "bench_accuracy.md"
    seen = base_model_serials(args.base_model)
    reused = [seed for seed in args.cross_seeds if simulated_serial(seed) in seen]
    if reused:
        p.error(f"the base model trained on sensor seeds {reused}: pick other --cross-seeds")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    info, t0 = machine_info(), time.perf_counter()
    args.work.mkdir(parents=True, exist_ok=True)

    session_a = record(args.work, args.sensor_seed, args.objects, args.poses_per_object, args.sensor_seed, args.sim_speed)
    in_class = [{"arch": arch, "init": None, "split": split, **train(
        args.work, f"{arch}_inclass_{split}", args.reuse_models, data=[str(session_a)], arch=arch, minutes=args.minutes,
        split=split)}
        for arch in args.archs for split in args.splits]
    base_arch = load_metadata(args.base_model).arch  # the product's path, same budget: fine-tune the base model
    in_class += [{"arch": base_arch, "init": "base", "split": split, **train(
        args.work, f"base_inclass_{split}", args.reuse_models, data=[str(session_a)], init=args.base_model,
        minutes=args.minutes, split=split)} for split in args.splits]
    leave_one_out = [{"arch": arch, "holdout": obj, **train(args.work, f"{arch}_without_{obj}", args.reuse_models,
                                                            data=[str(session_a)], arch=arch, minutes=args.minutes,
                                                            holdout_object=obj)}
                     for arch in args.archs for obj in args.holdouts.split(",")]
    model_a = next((r for r in in_class if r["arch"] == "resnet" and not r["init"]), in_class[0])

    cross = []
    for seed in args.cross_seeds:
        calib = record(args.work, seed, args.objects, args.calib_poses, seed, args.sim_speed)
        test = record(args.work, seed, args.objects, args.test_poses, seed + 100_000, args.sim_speed)
        finetune = train(args.work, f"sensor{seed}_finetuned", args.reuse_models, data=[str(calib)], val_data=[str(test)],
                         init=args.base_model, minutes=args.finetune_minutes)
        tuned = evaluate(finetune["model"], test)
        cross.append({"seed": seed, "calib": recording(calib), "test": recording(test),
                      "zero_shot_base": evaluate(args.base_model, test),
                      "zero_shot_sensor_a": evaluate(model_a["model"], test),
                      "finetune": finetune, "finetuned": tuned, "vs_true": tuned["vs_true"]})
        print(f"sensor {seed}: zero-shot a1 {cross[-1]['zero_shot_base']['a1']:.3f}, fine-tuned a1 {tuned['a1']:.3f}",
              flush=True)

    settings = {k: str(v) if isinstance(v, Path) else ",".join(map(str, v)) if isinstance(v, list) else v
                for k, v in vars(args).items() if k != "out"}  # as given on the command line
    result = {
        "command": "python benchmarks/bench_accuracy.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "machine": finish(info), "wall_min": (time.perf_counter() - t0) / 60, "settings": settings,
        "sensor_a": recording(session_a), "sensor_a_model_arch": model_a["arch"],
        "in_class": in_class, "leave_one_out": leave_one_out, "cross_sensor": cross,
        "json": str(args.out.with_suffix(".json")),
    }
    write_json(args.out.with_suffix(".json"), result)
    write_text(args.out, markdown(result))
    print(f"wrote {args.out} and {args.out.with_suffix('.json').name} ({result['wall_min']:.1f} min)")
    return 0


if __name__ == "__main__":
    run_main(main, "bench_accuracy")  # a bad session or object name: one line, exit 2, as the CLI does
