"""Commissioning benchmark: `bubble commission --sim` end to end for new sensors, writes docs/bench_commission.md.

    .venv/bin/python benchmarks/bench_commission.py                       # 3 sensors, default settings
    .venv/bin/python benchmarks/bench_commission.py --seeds 101,202,303,404 --work runs/bench_commission

For each seed (sensors the base model never saw: pretraining uses seeds 1000 and up):

1. draw the sensor (``draw_sensor(seed)``) and commission it with the product's defaults (4 objects
   x 10 poses, 7 of them fine-tune and 3 validate, 2.5 min fine-tune, real-time simulated clock)
   through ``run_commissioning``, timing every step from its events (wall clock);
2. commissioned model on objects it never saw: record a small session on meshes that are not in
   the calibration set (a sphere and a capsule, written as STL files and pressed through the same
   ``bubble collect`` code) and evaluate the commissioned model on it (``trainer.evaluation``).

3. one defective sensor per simulated defect (``draw_sensor(seed, defect)``: a leak, dead pixels,
   no printed dots), commissioned the same way: each must be rejected, by the check that guards
   against its defect.

Targets: end to end <= 5 min wall on the 2-core CPU, fine-tune step <= 3 min, held-out a1 >= 0.95,
every good sensor accepted and every defective one rejected.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.arguments import model_dir, positive_float, run_main, sensor_seed_list, work_dir  # noqa: E402
from benchmarks.machine import machine_info, provenance  # noqa: E402
from calibrate.commission_config import CommissionConfig  # noqa: E402
from calibrate.commission_events import Step, StepFinished, StepStarted  # noqa: E402
from collect.atomic_files import write_text  # noqa: E402
from calibrate.commissioning import POSE_BY_POSE_KEY, pose_vs_true_key, run_commissioning  # noqa: E402
from trainer.splits import TRAIN_FRACTION  # noqa: E402

TARGET_TOTAL_S = 300.0
TARGET_FINETUNE_S = 180.0
TARGET_A1 = 0.95
#: The checks that must reject each simulated defect (calibrate/acceptance_thresholds.yaml).
DEFECT_CHECKS = {"leak": ("leak_rate_hpa_per_min",), "dead-pixels": ("dead_pixels", "stuck_pixels"),
                 "no-dots": ("dot_contrast", "dot_count")}
UNSEEN_POSES = 6
#: The seed of the defective sensors (one per defect).
DEFECT_SEED = 909
#: Recordings of the unseen meshes per sensor: a loaded machine can starve the simulated camera, so one retry.
UNSEEN_ATTEMPTS = 2


def run_name(seed: int, defect: str | None) -> str:
    """The name of a sensor's files in ``--work``: its seed, and its defect if it has one."""
    return f"{seed}" if defect is None else f"{seed}_{defect}"


def run_outputs(work: Path, name: str) -> list[Path]:
    """What commissioning sensor ``name`` creates in ``work`` and a rerun would not start afresh: its run folder
    (``run_commissioning`` resumes one, or returns the verdict it recorded) and its unseen-mesh sessions (the
    recorder refuses an existing file)."""
    return [run_folder(work, name)] + [unseen_session(work, name, attempt) for attempt in range(1, UNSEEN_ATTEMPTS + 1)]


def run_folder(work: Path, name: str) -> Path:
    return work / f"run_{name}"


def unseen_session(work: Path, name: str, attempt: int) -> Path:
    return work / f"unseen_{name}_{attempt}.h5"


def unseen_meshes(work: Path) -> list[Path]:
    """STL files of objects absent from the calibration set (metres, +z up, origin at the base)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.03)
    sphere.apply_translation([0, 0, 0.03])
    capsule = trimesh.creation.capsule(height=0.06, radius=0.018, count=[32, 32])
    capsule.apply_transform(trimesh.transformations.rotation_matrix(1.5708, [0, 1, 0]))
    capsule.apply_translation([0, 0, -capsule.bounds[0][2]])  # lying on the plate
    paths = []
    for name, mesh in (("sphere", sphere), ("capsule", capsule)):
        path = work / f"unseen_{name}.stl"
        mesh.export(path)
        paths.append(path)
    return paths


def record_unseen(spec_path: Path, meshes: list[Path], seed: int, out: Path) -> Path:
    """A session on ``meshes`` with the commissioned sensor (the code path of ``bubble collect --sim``)."""
    from collect.bench import BenchConfig, open_bench
    from collect.collection import run_collection, session_metadata
    from collect.pose_planner import PlanSettings, plan_collection
    from collect.session_writer import SessionWriter

    config = BenchConfig.create("sim", objects=tuple(str(m) for m in meshes), sensor=spec_path, seed=seed, speed=1.0)
    with open_bench(config) as bench:
        plan = plan_collection(bench.objects, bench.limits, PlanSettings(poses_per_object=UNSEEN_POSES, seed=seed))
        with SessionWriter(out, **session_metadata(bench, plan.objects)) as writer:
            run_collection(bench, plan, writer, None, threading.Event())
    return out


def commission_one(seed: int, work: Path, minutes: float, base_model: Path | None, defect: str | None = None) -> dict:
    from hw_mocks.sensor_spec import draw_sensor

    spec = draw_sensor(seed, defect)
    name = run_name(seed, defect)
    spec_path = work / f"sensor_{name}.yaml"
    spec.to_yaml(spec_path)
    starts: dict[str, float] = {}
    durations: dict[str, float] = {}

    def on_event(event) -> None:
        now = time.perf_counter()
        if isinstance(event, StepStarted):
            starts.setdefault(event.step.value, now)
        elif isinstance(event, StepFinished) and event.step.value in starts:
            durations[event.step.value] = now - starts[event.step.value]

    config = CommissionConfig(
        run_dir=run_folder(work, name),
        sensor_spec=spec_path,
        registry_dir=work / "registry",
        finetune_minutes=minutes,
        seed=seed,
        base_model=base_model,
    )
    t0 = time.perf_counter()
    result = run_commissioning(config, on_event)
    total = time.perf_counter() - t0
    import json

    doc = json.loads((config.run_dir / "acceptance.json").read_text())
    state = json.loads((config.run_dir / "state.json").read_text())["steps"]
    checks = {c["name"]: c["value"] for c in doc["checks"]}
    finetune = state.get("finetune", {})
    row = {
        "seed": seed, "defect": defect, "failed_checks": [c["name"] for c in doc["checks"] if not c["passed"] and c["value"] is not None],
        "serial": spec.serial, "accepted": result.accepted, "reason": result.reason, "total_s": total,
        "steps": durations, "train_s": finetune.get("train_s"), "finetune_deadline_s": finetune.get("deadline_s"),
        "run_budget_cut": bool(finetune.get("deadline_from_run_budget")), "a1": doc.get("a1"), "abs_rel": doc.get("abs_rel"), "rmse": doc.get("rmse"),
        "truth_a1": checks.get("truth_a1"), "contact_rmse": checks.get("contact_rmse_mm"), "pose_e_x": checks.get("pose_e_x_median_mm"),
        "tof_a1": (doc.get("vs_true") or {}).get("tof", {}).get("a1"),
        "dropout_a1": (doc.get("vs_true") or {}).get("model_on_tof_dropout", {}).get("a1"),
    }
    pose = state.get("pose_check", {}).get("pose", {})
    row["pose_by_pose"] = pose.get(POSE_BY_POSE_KEY, {})
    for key, source in (("pred_vs_true", "predicted"), ("tof_vs_true", "measured")):
        row[key] = (pose.get(pose_vs_true_key(source)) or [None])[0]
    print(f"seed {seed}: {'ACCEPTED' if result.accepted else 'REJECTED'} in {total:.0f} s, a1 {_f(row['a1'], '.3f')} "
          f"{result.reason}", flush=True)
    if (config.run_dir / "model" / "metadata.json").is_file():
        from collect.errors import HardwareFault
        from trainer.evaluation import evaluate_model

        meshes = unseen_meshes(work)
        for attempt in range(1, UNSEEN_ATTEMPTS + 1):
            session = unseen_session(work, name, attempt)
            try:
                record_unseen(spec_path, meshes, seed, session)
                break
            except HardwareFault as fault:
                print(f"seed {seed}: unseen-mesh recording attempt {attempt} faulted: {fault.kind}: {fault}", flush=True)
                row["unseen_fault"] = f"{fault.kind}: {fault}"
        else:
            return row
        unseen = evaluate_model(config.run_dir / "model", [session], latency_repeats=5)
        row.pop("unseen_fault", None)
        row["unseen_a1"] = unseen["a1"]
        row["unseen_per_object"] = {k: v["a1"] for k, v in unseen["per_object"].items()}
        print(f"seed {seed}: a1 on unseen meshes {unseen['a1']:.3f} {row['unseen_per_object']}", flush=True)
    return row


def _f(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def _spread(values: list[float], fmt: str) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    return f"{format(min(values), fmt)} / {format(statistics.median(values), fmt)} / {format(max(values), fmt)}"


def write_doc(all_rows: list[dict], args, info: dict) -> Path:
    steps = [s.value for s in Step]
    rows = [r for r in all_rows if r["defect"] is None]
    defective = [r for r in all_rows if r["defect"] is not None]
    lines = [
        "# Benchmark: `bubble commission --sim` end to end",
        "",
        provenance(info),
        "",
        f"Each sensor is new (`draw_sensor(seed)`, seeds unused by pretraining) and commissioned with the product's "
        f"defaults: 4 objects x {CommissionConfig.poses_per_object} poses ({TRAIN_FRACTION:.0%} fine-tune, the rest validate), "
        f"{args.minutes} min fine-tune from "
        f"{args.base_model or 'the packaged base model'}, real-time "
        f"simulated clock. Targets: total <= {TARGET_TOTAL_S / 60:.0f} min, fine-tune step <= "
        f"{TARGET_FINETUNE_S / 60:.0f} min, held-out a1 >= {TARGET_A1}.",
        "",
        "| seed | verdict | total (s) | " + " | ".join(steps) + " | held-out a1 | abs_rel | rmse (mm) | contact rmse (mm) | "
        "a1 vs truth (model / ToF) | a1 on ToF dropouts | pose e_x (mm) | e_x per held-out mug pose (mm) | "
        "pose vs true, e_x (mm): predicted / ToF | a1 unseen meshes |",
        "|---" * (13 + len(steps)) + "|",
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {'accepted' if r['accepted'] else 'rejected'} | {r['total_s']:.0f} | "
            + " | ".join(_f(r["steps"].get(s), ".0f") for s in steps)
            + f" | {_f(r['a1'], '.3f')} | {_f(r['abs_rel'], '.4f')} | {_f(r['rmse'] and r['rmse'] * 1e3, '.3f')} | "
            f"{_f(r['contact_rmse'], '.3f')} | "
            f"{_f(r['truth_a1'], '.3f')} / {_f(r['tof_a1'], '.3f')} | {_f(r['dropout_a1'], '.3f')} | {_f(r['pose_e_x'], '.2f')} | "
            f"{', '.join(f'{v:.2f}' for v in r['pose_by_pose'].values()) or '-'} | "
            f"{_f(r['pred_vs_true'], '.2f')} / {_f(r['tof_vs_true'], '.2f')} | {_f(r.get('unseen_a1'), '.3f')} |"
        )
    lines += [
        "",
        "Spread over the seeds (min / median / max):",
        "",
        f"* total wall: {_spread([r['total_s'] for r in rows], '.0f')} s",
        f"* fine-tune step (data loading, training, final validation, ONNX export): "
        f"{_spread([r['steps'].get('finetune') for r in rows], '.0f')} s, of which training "
        f"{_spread([r['train_s'] for r in rows], '.0f')} s",
        f"* fine-tune step deadline: {_spread([r['finetune_deadline_s'] for r in rows], '.0f')} s; shortened to fit "
        f"the run's {CommissionConfig.total_minutes:g}-min budget (the steps before it ran long) on "
        f"{', '.join(str(r['seed']) for r in rows if r['run_budget_cut']) or 'no sensor'}",
        f"* held-out a1: {_spread([r['a1'] for r in rows], '.3f')}",
        f"* held-out contact rmse (mm): {_spread([r['contact_rmse'] for r in rows], '.3f')}",
        f"* a1 on unseen meshes (sphere, capsule): {_spread([r.get('unseen_a1') for r in rows], '.3f')}",
        f"* pose check, median e_x predicted vs measured: {_spread([r['pose_e_x'] for r in rows], '.2f')} mm; "
        f"per held-out mug pose: "
        f"{_spread([v for r in rows for v in r['pose_by_pose'].values()], '.2f')} mm",
        f"* pose vs true pose, median e_x: predicted depth {_spread([r['pred_vs_true'] for r in rows], '.2f')} mm, "
        f"ToF {_spread([r['tof_vs_true'] for r in rows], '.2f')} mm",
        f"* accepted: {sum(r['accepted'] for r in rows)} of {len(rows)}",
        "",
    ]
    if defective:
        lines += [
            "Defective sensors (`draw_sensor(seed, defect)`), commissioned the same way: each must be rejected by a "
            "check that guards against its defect.",
            "",
            "| seed | defect | verdict | total (s) | failed checks (measured) | by its guard | reason |",
            "|---|---|---|---|---|---|---|",
            *(f"| {r['seed']} | {r['defect']} | {'accepted' if r['accepted'] else 'rejected'} | {r['total_s']:.0f} | "
              f"{', '.join(r['failed_checks']) or '-'} | "
              f"{'yes' if set(r['failed_checks']) & set(DEFECT_CHECKS[r['defect']]) else 'no'} | {r['reason']} |"
              for r in defective),
            "",
            f"* defective sensors rejected by their guard: "
            f"{sum(not r['accepted'] and bool(set(r['failed_checks']) & set(DEFECT_CHECKS[r['defect']])) for r in defective)}"
            f" of {len(defective)}",
            "",
        ]
    for r in rows:
        if not r["accepted"]:
            lines.append(f"* seed {r['seed']} rejected: {r['reason']}")
        if r.get("unseen_fault"):
            lines.append(f"* seed {r['seed']} unseen meshes not recorded: {r['unseen_fault']}")
        if r.get("unseen_per_object"):
            per = ", ".join(f"{k} {v:.3f}" for k, v in r["unseen_per_object"].items())
            lines.append(f"* seed {r['seed']} unseen meshes: {per}")
    lines += [
        "",
        "Columns per step are wall seconds from the step's start event to its finish event. "
        "Whole-image metrics (held-out a1, a1 on unseen meshes) are lenient for a tactile sensor: "
        "delta < 1.05 tolerates 4.5 mm at 90 mm, about the depth of a dent, so a model that predicts the "
        "membrane at rest everywhere scores a1 ~ 1.0. \"contact rmse\" (on the pixels the ToF sees pushed in "
        "by more than 1.5 mm) and the mug pose check are the numbers that show whether the model sees contact. "
        "\"a1 vs truth\" compares the simulator's true membrane depth with the model (every in-range pixel, "
        "ToF dropouts included) and with the ToF (where it is valid); "
        "\"a1 on ToF dropouts\" is the model's a1 against the truth where the ToF gave no depth.",
        "",
        f"Rerun: `.venv/bin/python benchmarks/bench_commission.py --seeds {','.join(map(str, args.seeds))} "
        f"--defects {args.defects}`",
        "",
    ]
    path = ROOT / "docs" / "bench_commission.md"
    write_text(path, "\n".join(lines))
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=sensor_seed_list, default="101,202,303",
                        help="comma-separated sensor seeds (default 101,202,303)")
    parser.add_argument("--minutes", type=positive_float, default=CommissionConfig.finetune_minutes,
                        help="fine-tune budget")
    parser.add_argument("--base-model", type=model_dir, help="model to fine-tune from (default: the packaged base model)")
    parser.add_argument("--defects", default=",".join(DEFECT_CHECKS),
                        help=f"comma-separated simulated defects, one defective sensor each (seed {DEFECT_SEED}; '' for none)")
    parser.add_argument("--work", type=work_dir,
                        help="keep the runs here, a folder without the runs of an earlier call (default: a temporary "
                             "directory)")
    parser.add_argument("--no-doc", action="store_true", help="print only, do not write docs/bench_commission.md")
    args = parser.parse_args(argv)
    defects = [d.strip() for d in args.defects.split(",") if d.strip()]
    if any(d not in DEFECT_CHECKS for d in defects) or len(set(defects)) != len(defects):
        parser.error(f"defects must be among {', '.join(DEFECT_CHECKS)}, each once")
    sensors = [(seed, None) for seed in args.seeds] + [(DEFECT_SEED, defect) for defect in defects]
    if args.work is not None:  # a run folder there would be resumed, or its recorded verdict returned
        taken = [str(p) for seed, defect in sensors for p in run_outputs(args.work, run_name(seed, defect)) if p.exists()]
        if taken:
            parser.error(f"--work {args.work} already holds {', '.join(taken)} from an earlier run: give a new --work")
    base_model = None if args.base_model is None else Path(args.base_model)
    info = machine_info()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rows = [commission_one(seed, work, args.minutes, base_model, defect) for seed, defect in sensors]
    if not args.no_doc:
        print(f"wrote {write_doc(rows, args, info)}")
    return 0


if __name__ == "__main__":
    run_main(main, "bench_commission")
