"""``RUN_DIR/report.html`` of a commissioning run: the report's data gathered from the run directory.

``write_run_report`` reads the verdict (the ``acceptance.json`` document), ``state.json`` and the
arrays the steps left (``leak_test.npz``, ``camera_health.npz``, ``validation.npz``) into a
``calibrate.report.ReportData``; ``calibrate.report`` renders it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibrate.commission_events import Step
from calibrate.run_directory import CAMERA_FILE, LEAK_FILE, REPORT_FILE, VALIDATION_FILE, RunState


def write_run_report(run_dir: Path, state: RunState, doc: dict) -> Path:
    """Write ``run_dir/report.html`` for the verdict ``doc`` (the ``acceptance.json`` document) and
    the run's ``state``; a step that did not run gets a note saying why. Returns its path."""
    from calibrate.report import ReportData, write_report

    data = ReportData(
        serial=str(doc["serial"] or "unknown"),
        accepted=doc["accepted"],
        checks=doc["checks"],
        simulated=doc["simulated"],
        reason=doc["reason"],
        fault=doc["fault"],
        stopped=doc["stopped"],
        run_info={
            "run directory": str(run_dir.resolve()),
            "finished": doc["finished"],
            "thresholds": doc["thresholds"]["source"],
            **{f"step {k}": v for k, v in doc["steps"].items()},
            "settings": state.data.get("settings"),
        },
        heldout_metrics=state.get(Step.VALIDATE).get("metrics"),
        contact_metrics=state.get(Step.VALIDATE).get("contact"),
        pose=state.get(Step.POSE_CHECK).get("pose"),
    )
    why_missing = doc["reason"] or "the step did not run"
    data.notes = {k: why_missing for k in ("checks", "leak", "camera", "nocontact", "examples", "training", "truth",
                                           "metrics")}
    if state.done(Step.POSE_CHECK) and state.get(Step.POSE_CHECK).get("skipped"):
        data.notes["pose"] = state.get(Step.POSE_CHECK)["summary"]
    else:
        data.notes["pose"] = why_missing
    if (run_dir / LEAK_FILE).is_file() and state.done(Step.LEAK_TEST):
        with np.load(run_dir / LEAK_FILE) as z:
            data.leak_t, data.leak_hpa = z["t"], z["hpa"]
    if (run_dir / CAMERA_FILE).is_file() and state.done(Step.CAMERA_HEALTH):
        with np.load(run_dir / CAMERA_FILE) as z:
            data.camera_ir_mean, data.camera_dead_mask = z["ir_mean"], z["dead_mask"]
            data.camera_stuck_mask, data.camera_dot_mask = z["stuck_mask"], z["dot_mask"]
    data.training_curve = state.get(Step.FINETUNE).get("curve", [])
    if (run_dir / VALIDATION_FILE).is_file() and state.done(Step.VALIDATE):
        with np.load(run_dir / VALIDATION_FILE) as z:
            data.nocontact_valid_count = z["valid_count"]
            data.nocontact_err_mean, data.nocontact_err_var = z["err_mean"], z["err_var"]
            data.example_ir, data.example_depth, data.example_pred = z["example_ir"], z["example_depth"], z["example_pred"]
            data.example_true = z["example_true"] if "example_true" in z.files else None
            data.example_labels = [f"{o} pose_id {p}" for o, p in zip(z["example_object"], z["example_pose"])]
        vs_true = state.get(Step.VALIDATE).get("vs_true")
        if vs_true:
            drop = vs_true["model_on_tof_dropout"]
            dropouts = None
            if drop["n_pixels"]:
                dropouts = {
                    "fraction": 1.0 - vs_true["tof_coverage"],
                    "pixels": int(drop["n_pixels"]),
                    "model_rmse_mm": float(drop["rmse"]) * 1000.0,
                    "model_a1": drop["a1"],
                }
            data.truth_comparison = {
                "model": vs_true["model_on_tof_valid"], "tof": vs_true["tof"], "model_all": vs_true["model"],
                "dropouts": dropouts,
            }
    return write_report(data, run_dir / REPORT_FILE)
