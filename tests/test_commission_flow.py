"""The commissioning flow end to end on the simulated bench, at tiny size.

One module-scoped run is interrupted by a camera fault in the middle, then resumed to an accepted
verdict (with its whole-run budget already spent, so the fine-tune is shortened to its floor);
the tests below inspect its events and its run directory. The thresholds of the
held-out model checks are relaxed in a lab override file (a 3 s fine-tune cannot reach the real
ones; the benchmark measures those), every hardware and data check keeps its packaged value.
"""

import dataclasses
import fcntl
import json
import math
import os
import re
import shutil
import signal
import threading
from datetime import datetime

import numpy as np
import pytest

from calibrate import commission_config
from calibrate.cli import main
from calibrate.commission_config import CommissionConfig
from calibrate.commission_events import (
    STEPS,
    ArmSafeStopped,
    BenchSnapshot,
    CollectionProgress,
    FaultRaised,
    Step,
    StepFinished,
    StepStarted,
    TrainingProgress,
    Verdict,
)
from calibrate.commissioning import run_commissioning
from calibrate.sensor_registry import SensorRegistry
from collect.errors import HardwareFault, InputError
from collect.safety import SafetyViolation
from collect.session_reader import Session
from conftest import interrupt_once_recording
from trainer.metrics import METRIC_KEYS

#: Model to fine-tune from: None = the packaged base model (trainer/base_model).
BASE_MODEL = None

LENIENT_MODEL_CHECKS = """version: 1
checks:
  heldout_a1: {min: 0.0}
  heldout_abs_rel: {max: 10.0}
  heldout_rmse_mm: {max: 1000.0}
  contact_rmse_mm: {max: 1000.0}
  truth_a1: {min: 0.0}
"""


def tiny_config(root, **changes) -> CommissionConfig:
    """One object, two poses, a 3 s fine-tune, a 2 s leak test on a 2x simulated clock."""
    thresholds = root / "lenient.yaml"
    thresholds.write_text(LENIENT_MODEL_CHECKS)
    config = CommissionConfig(
        run_dir=root / "run",
        objects=("box",),
        poses_per_object=2,
        finetune_minutes=0.05,
        seed=3,
        sim_speed=2.0,
        leak_hold_s=2.0,
        thresholds=thresholds,
        registry_dir=root / "registry",
        base_model=BASE_MODEL,
    )
    return dataclasses.replace(config, **changes)


def edited_base_model(folder, edit) -> str:
    """A copy of the packaged base model in ``folder`` whose first floating-point weight tensor is
    ``edit(tensor)``, its new SHA-256 recorded as ``save_model`` records it (a whole model); returns
    that tensor's name."""
    from trainer.model_dir import BASE_MODEL_DIR, METADATA_FILE, WEIGHTS_FILE, load_weights, weights_sha256, \
        write_safetensors

    shutil.copytree(BASE_MODEL_DIR, folder)
    weights = load_weights(folder)
    first = next(k for k, t in weights.items() if t.is_floating_point())
    weights[first] = edit(weights[first])
    write_safetensors(weights, folder / WEIGHTS_FILE)
    meta = json.loads((folder / METADATA_FILE).read_text())
    meta["inference"]["weights_sha256"] = weights_sha256(folder)
    (folder / METADATA_FILE).write_text(json.dumps(meta))
    return first


@pytest.fixture(scope="module")
def faulted_then_resumed(tmp_path_factory):
    root = tmp_path_factory.mktemp("commission")
    config = tiny_config(root, sim_faults=("camera-stall@6",))
    first_events: list = []
    first = run_commissioning(config, first_events.append)
    state_after_fault = json.loads((config.run_dir / "state.json").read_text())
    files_after_fault = {p.name: p.stat().st_size for p in config.run_dir.iterdir()}
    # The resumed run has spent its whole-run budget before its fine-tune: the step gets the
    # floor (8 s here instead of 90 s, to keep the test short) instead of its 90 s limit.
    resumed_config = dataclasses.replace(config, sim_faults=(), finetune_minutes=1.0, total_minutes=0.01)
    events: list = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(commission_config, "MIN_FINETUNE_STEP_S", 8.0)
        mp.setattr(commission_config, "MIN_TRAINING_SHARE", 0.0)  # its loading takes most of 8 s: not a slow host
        result = run_commissioning(resumed_config, events.append)
    return {
        "config": resumed_config, "first": first, "first_events": first_events, "state_after_fault": state_after_fault,
        "files_after_fault": files_after_fault, "result": result, "events": events,
    }


def test_fault_rejects_the_run_and_keeps_its_data(faulted_then_resumed):
    first = faulted_then_resumed["first"]
    assert not first.accepted and first.fault.startswith("camera-stall")
    assert first.reason.startswith("hardware fault camera-stall")
    faults = [e for e in faulted_then_resumed["first_events"] if isinstance(e, FaultRaised)]
    assert [f.kind for f in faults] == ["camera-stall"]
    done = list(faulted_then_resumed["state_after_fault"]["steps"])
    assert done == [s.value for s in STEPS[: len(done)]] and "verdict" not in done and "connect" in done
    files = faulted_then_resumed["files_after_fault"]
    assert {"state.json", "acceptance.json", "report.html"} <= set(files)
    for step, name in (("leak_test", "leak_test.npz"), ("camera_health", "camera_health.npz"), ("reference", "reference.h5")):
        assert step not in done or files[name] > 0
    verdict = [e for e in faulted_then_resumed["first_events"] if isinstance(e, Verdict)]
    assert len(verdict) == 1 and not verdict[0].accepted


def test_rerun_resumes_after_the_last_completed_step(faulted_then_resumed):
    events = faulted_then_resumed["events"]
    done_before = set(faulted_then_resumed["state_after_fault"]["steps"])
    finished = {e.step.value: e for e in events if isinstance(e, StepFinished)}
    started = {e.step.value for e in events if isinstance(e, StepStarted)}
    assert set(finished) == {s.value for s in STEPS}
    for name, event in finished.items():
        assert event.resumed == (name in done_before)
        assert (name in started) == (name not in done_before)
    result = faulted_then_resumed["result"]
    assert result.accepted and result.fault is None and not result.stopped, result.reason
    assert finished["pose_check"].skipped  # no mug in this calibration set
    state = json.loads((faulted_then_resumed["config"].run_dir / "state.json").read_text())
    assert state["settings"]["sim_faults"] == [] and state["settings"]["finetune_minutes"] == 1.0  # this attempt's
    assert [s["sim_faults"] for s in state["earlier_settings"]] == [["camera-stall@6"]]  # was: the first's alone
    checks = json.loads((faulted_then_resumed["config"].run_dir / "acceptance.json").read_text())["checks"]
    assert checks and all(c["verdict"] == "pass" for c in checks)  # no pose check, and no "not run" either


def test_run_budget_shortens_the_finetune_step(faulted_then_resumed):
    config = faulted_then_resumed["config"]
    rec = json.loads((config.run_dir / "state.json").read_text())["steps"]["finetune"]
    assert rec["deadline_s"] == 8.0 and rec["deadline_from_run_budget"] and rec["ended_at_deadline"]
    assert "cut short to fit the run's 0.01-min budget" in rec["summary"]
    etas = [e.eta_s for e in faulted_then_resumed["events"] if isinstance(e, StepStarted) and e.step == Step.FINETUNE]
    assert etas == [8.0]


def test_run_budget_gives_way_only_when_the_steps_before_ran_long(tmp_path):
    config = CommissionConfig(run_dir=tmp_path)  # 2.5 min fine-tune: a 180 s step; 5 min in all
    assert config.finetune_deadline_s(80.0) == (180.0, False)  # a usual run: 74-87 s to the fine-tune
    assert config.finetune_deadline_s(126.0) == (300.0 - 126.0 - commission_config.AFTER_FINETUNE_S, True)
    assert config.finetune_deadline_s(250.0) == (commission_config.MIN_FINETUNE_STEP_S, True)  # never below the floor
    for unlimited in (None, math.inf):
        assert dataclasses.replace(config, total_minutes=unlimited).finetune_deadline_s(1e4) == (180.0, False)
    short = dataclasses.replace(config, finetune_minutes=0.5)  # a 60 s step, below the floor
    assert short.finetune_deadline_s(1e4) == (60.0, False)


def test_live_events_reach_the_consumer(faulted_then_resumed):
    events = faulted_then_resumed["first_events"] + faulted_then_resumed["events"]
    snapshots = [e for e in events if isinstance(e, BenchSnapshot)]
    assert snapshots and all(len(s.tcp_pose) == 6 and len(s.wrench) == 6 for s in snapshots)
    assert any(s.ir is not None and s.ir.dtype == np.uint16 and s.depth_m.dtype == np.float32 for s in snapshots)
    collection = [e for e in events if isinstance(e, CollectionProgress)]
    assert {"press", "hold"} <= {e.phase for e in collection}
    assert any(e.force_n > 0.5 for e in collection if e.phase == "hold")
    # the fine-tune's curve reaches the consumer and ends at its last step with the final a1. Its 8 s
    # floor can pass before a first step on a loaded machine: then there is no curve (was: a failure)
    training = [e for e in events if isinstance(e, TrainingProgress)]
    finetune = json.loads((faulted_then_resumed["config"].run_dir / "state.json").read_text())["steps"]["finetune"]
    assert [e.step for e in training] == [p["step"] for p in finetune["curve"] if p["loss"] is not None]
    assert all(np.isfinite(e.loss) for e in training)
    if finetune["steps"] > 0:
        assert training[-1].step == finetune["steps"] and training[-1].a1 == finetune["curve"][-1]["a1"]
    # the bench's last snapshot shows the arm as the bench leaves it: after the fault's safe stop, and
    # just before collection's end (the TUI's bench panel ends on it; was: on the last one the
    # snapshot loop had sent, the arm still moving)
    first, resumed = faulted_then_resumed["first_events"], faulted_then_resumed["events"]
    last_snapshot = [max(k for k, e in enumerate(run) if isinstance(e, BenchSnapshot)) for run in (first, resumed)]
    assert last_snapshot[0] > next(k for k, e in enumerate(first) if isinstance(e, ArmSafeStopped))
    collected = next(k for k, e in enumerate(resumed) if isinstance(e, StepFinished) and e.step == Step.COLLECT)
    assert not resumed[collected].resumed and last_snapshot[1] == collected - 1
    assert np.linalg.norm(resumed[collected - 1].wrench[:3]) < 0.5  # parked: the bubble touches nothing


def test_finetune_curve_keeps_every_fifth_step_each_validation_and_the_end():
    from calibrate.commissioning import curve_point
    from trainer.training import TrainProgress

    def progress(step, event="step", a1=None, loss=0.001):
        return TrainProgress(0.1 * step, step, loss, 1e-4, float(step), 0.1 * step, 1.0, None if a1 is None else {"a1": a1}, event)

    events = [progress(0, "eval", 0.5, float("nan"))] + [progress(k) for k in range(1, 8)]
    events[3:3] = [progress(3, "eval", 0.9)]
    events.append(progress(7, "done", 0.95))
    points = [p for p in (curve_point(e, 1.0) for e in events) if p is not None]
    assert [(p["step"], p["loss"], p["a1"]) for p in points] == [
        (0, None, 0.5), (3, 0.001, 0.9), (5, 0.001, None), (7, 0.001, 0.95)]


def test_run_directory_holds_the_contract_files(faulted_then_resumed):
    run_dir = faulted_then_resumed["config"].run_dir
    with Session.open(run_dir / "session.h5") as s:
        assert s.simulated and len(np.unique(s.pose_id[s.pose_id >= 0])) == 2
    assert (run_dir / "model" / "metadata.json").is_file() and (run_dir / "model" / "model.safetensors").is_file()
    doc = json.loads((run_dir / "acceptance.json").read_text())
    assert doc["accepted"] is True
    for key in METRIC_KEYS:
        assert isinstance(doc[key], float) and np.isfinite(doc[key])
    names = [c["name"] for c in doc["checks"]]
    for required in ("leak_rate_hpa_per_min", "dead_pixels", "dot_count", "valid_depth_coverage",
                     "poses_completed_fraction", "heldout_a1", "truth_a1"):
        assert required in names
    for check in doc["checks"]:
        assert {"value", "threshold", "verdict", "passed", "reason"} <= set(check)
        assert check["verdict"] == "pass"
    leak = next(c for c in doc["checks"] if c["name"] == "leak_rate_hpa_per_min")
    assert leak["threshold"] == 1.0  # hardware checks keep the packaged thresholds
    assert doc["vs_true"]["tof"]["n_pixels"] > 0
    html = (run_dir / "report.html").read_text()
    assert html.index("ACCEPTED") < html.index("Acceptance checks") and "Fig. 5" in html and "Fig. 6" in html


def test_report_of_the_run_renders_in_headless_chromium(faulted_then_resumed, tmp_path):
    from test_commission_report import screenshot

    image = screenshot(faulted_then_resumed["config"].run_dir / "report.html", tmp_path / "run.png", tmp_path)
    green = np.all(np.abs(image.astype(int) - (50, 125, 46)) <= 3, axis=2)
    assert green[:300].sum() > 5000


def test_registry_records_both_commissionings_and_lists_them(faulted_then_resumed, capsys):
    registry_dir = faulted_then_resumed["config"].registry_dir
    (profile,) = SensorRegistry(registry_dir).survey().profiles
    assert profile.status == "accepted" and profile.model_dir is not None
    assert [h["accepted"] for h in profile.history] == [False, True]
    assert "camera-stall" in profile.history[0]["reason"]
    assert (profile.path / "reference.npz").is_file()
    assert main(["sensors", "--registry", str(registry_dir)]) == 0
    out = capsys.readouterr().out
    assert profile.serial in out and "accepted" in out
    assert main(["sensors", profile.serial, "--registry", str(registry_dir)]) == 0
    assert "rejected" in capsys.readouterr().out


def test_rerunning_a_finished_run_only_reports_it(faulted_then_resumed):
    config = faulted_then_resumed["config"]
    events: list = []
    result = run_commissioning(config, events.append)  # nothing runs again (no step started: below)
    assert result.accepted
    assert all(e.resumed for e in events if isinstance(e, StepFinished))
    assert not [e for e in events if isinstance(e, StepStarted)]
    assert len(SensorRegistry(config.registry_dir).survey().profiles[0].history) == 2


def test_a_finished_run_is_not_reported_again_under_other_limits_or_another_base_model(faulted_then_resumed, tmp_path):
    """Was: re-run with a stricter --thresholds, a finished run printed ACCEPTED under the limits it
    was judged by, and a resumed one mixed the two; another --base-model was taken the same way."""
    from trainer.model_dir import BASE_MODEL_DIR

    config = faulted_then_resumed["config"]
    strict = tmp_path / "strict.yaml"
    strict.write_text(LENIENT_MODEL_CHECKS.replace("contact_rmse_mm: {max: 1000.0}", "contact_rmse_mm: {max: 0.1}"))
    with pytest.raises(InputError, match=r"holds a run judged by other acceptance limits \(thresholds '.*lenient.yaml'\) "
                                         r"than --thresholds gives now \('.*strict.yaml'\)"):
        run_commissioning(dataclasses.replace(config, thresholds=strict), lambda e: None)
    same_model = tmp_path / "same_model"  # the same weights by another path: the same run (was: refused)
    shutil.copytree(BASE_MODEL_DIR, same_model)
    assert run_commissioning(dataclasses.replace(config, base_model=same_model), lambda e: None).accepted
    other_model = tmp_path / "other_model"  # other weights (was: taken when given by the same path)
    edited_base_model(other_model, lambda tensor: tensor + 1e-3)
    with pytest.raises(InputError, match=r"holds a run fine-tuned from other base-model weights \(--base-model "
                                         r"'base'\) than --base-model gives now \('.*other_model'\)"):
        run_commissioning(dataclasses.replace(config, base_model=other_model), lambda e: None)
    reworded = tmp_path / "reworded.yaml"  # the same limits in another file, with other wording: the same run
    reworded.write_text(LENIENT_MODEL_CHECKS + "  leak_rate_hpa_per_min: {describe: leak rate at rest}\n")
    assert run_commissioning(dataclasses.replace(config, thresholds=reworded), lambda e: None).accepted


def test_a_finished_run_keeps_its_verdict_whatever_happened_to_its_acceptance_json(faulted_then_resumed, tmp_path):
    """The verdict of a finished run comes from its state.json. Was: read back from acceptance.json,
    so that ``"accepted": "no"`` there gave ACCEPTED, a damaged file a traceback, and a deleted one a
    second registration of the same run."""
    config = faulted_then_resumed["config"]
    registry = tmp_path / "registry"
    shutil.copytree(config.registry_dir, registry)
    for damage in ('{"accepted": "no", "checks": "x"}', "{\"accepted\": tr", None):
        run_dir = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
        shutil.copytree(config.run_dir, run_dir)
        acceptance = run_dir / "acceptance.json"
        acceptance.unlink() if damage is None else acceptance.write_text(damage)
        result = run_commissioning(dataclasses.replace(config, run_dir=run_dir, registry_dir=registry), lambda e: None)
        assert result.accepted and result.checks == faulted_then_resumed["result"].checks
    assert len(SensorRegistry(registry).survey().profiles[0].history) == 2


def test_a_damaged_registry_entry_of_the_sensor_stops_the_run_at_connect(tmp_path):
    """Was: the whole run, then a traceback or an exit 2 at its registration that hid the verdict."""
    from hw_mocks.sensor_spec import draw_sensor

    config = tiny_config(tmp_path)
    entry = config.registry_dir / draw_sensor(config.seed).serial
    (entry / "profile.json").mkdir(parents=True)
    events: list = []
    with pytest.raises(InputError, match=f"sensor registry entry {entry} is damaged: its profile.json is not a regular"):
        run_commissioning(config, events.append)
    assert not [e for e in events if isinstance(e, StepFinished)]
    assert sorted(p.name for p in config.run_dir.iterdir()) == ["state.json"]


@pytest.mark.parametrize("edit", [
    lambda state: state["steps"]["connect"].update(intrinsics="x"),  # was: put into the registry as is
    lambda state: state["steps"]["verdict"].update(ok="yes"),
    lambda state: state.update(steps=[]),  # was: a TypeError traceback
])
def test_a_state_json_edited_by_hand_is_refused(faulted_then_resumed, tmp_path, edit):
    config = faulted_then_resumed["config"]
    run_dir = tmp_path / "run"
    shutil.copytree(config.run_dir, run_dir)
    state = json.loads((run_dir / "state.json").read_text())
    edit(state)
    (run_dir / "state.json").write_text(json.dumps(state))
    with pytest.raises(InputError, match="state.json does not match its checksum"):
        run_commissioning(dataclasses.replace(config, run_dir=run_dir, registry_dir=tmp_path / "registry"), lambda e: None)
    assert not (tmp_path / "registry").exists()


@pytest.mark.parametrize("text, says", [("{", "is unreadable (Expecting"), ("[]", "does not hold a JSON object")])
def test_a_state_json_that_is_no_json_object_is_refused(tmp_path, text, says):
    from calibrate.run_directory import RunState

    (tmp_path / "state.json").write_text(text)
    with pytest.raises(InputError) as err:
        RunState.open(tmp_path, {})
    assert str(err.value).startswith(f"{tmp_path / 'state.json'} {says}") and str(err.value).endswith(
        "; use a new --out directory")


def test_stop_event_stops_the_arm_and_keeps_the_data(tmp_path):
    stop = threading.Event()
    events: list = []

    def on_event(event):
        events.append(event)
        if isinstance(event, CollectionProgress) and event.phase == "press":
            stop.set()

    config = tiny_config(tmp_path)
    result = run_commissioning(config, on_event, stop)
    assert result.stopped and not result.accepted
    (safe_stop,) = [e for e in events if isinstance(e, ArmSafeStopped)]
    assert safe_stop.retracted and safe_stop.force_after_n < 0.5  # clear of the object (the halt itself: test_collect_run)
    state = json.loads((config.run_dir / "state.json").read_text())
    assert "reference" in state["steps"] and "collect" not in state["steps"]
    with Session.open(config.run_dir / "session.h5") as s:
        # the frames up to the stop and the safe stop's retract; the press itself halts within a state
        # sample, often before a camera frame is stamped with it
        assert s.n_frames > 0 and {"approach", "retract"} <= set(s.phase_name(np.arange(s.n_frames)))
    assert json.loads((config.run_dir / "acceptance.json").read_text())["stopped"] is True
    assert SensorRegistry(config.registry_dir).survey().profiles == []


@pytest.mark.parametrize(
    "defect, failing",
    [("leak", "leak_rate_hpa_per_min"), ("dead-pixels", "dead_pixels"), ("no-dots", "dot_count")],
)
def test_defective_sensor_is_rejected_with_the_reason(tmp_path, capsys, defect, failing):
    from hw_mocks.sensor_spec import draw_sensor

    spec = tmp_path / "spec.yaml"
    draw_sensor(11, defect).to_yaml(spec)
    code = main(["commission", "--sim", "--sensor", str(spec), "--out", str(tmp_path / "run"), "--objects", "box",
                 "--registry", str(tmp_path / "registry"), "--sim-speed", "2", "--leak-hold-s", "2", "--quiet"]
                + (["--base-model", str(BASE_MODEL)] if BASE_MODEL else []))
    assert code == 1
    verdict_line = capsys.readouterr().out.splitlines()[0]
    assert verdict_line.startswith("REJECTED: ") and f"{failing} " in verdict_line
    doc = json.loads((tmp_path / "run" / "acceptance.json").read_text())
    assert not doc["accepted"] and failing in [c["name"] for c in doc["checks"] if not c["passed"]]
    assert doc["a1"] is None and doc["abs_rel"] is None  # the metric keys are there, without a validation
    assert not (tmp_path / "run" / "session.h5").exists()  # a failed hardware check stops before collecting
    # every check of the thresholds, those of the steps never reached as "not run" (was: left out)
    from calibrate.acceptance import load_thresholds
    assert [c["name"] for c in doc["checks"]][-2:] == ["pose_e_x_median_mm", "pose_e_theta_median"]
    assert sorted(c["name"] for c in doc["checks"]) == sorted(load_thresholds(None).checks)
    verdicts = {c["name"]: c["verdict"] for c in doc["checks"]}
    assert verdicts[failing] == "fail" and verdicts["heldout_a1"] == "not run"
    assert all(c["value"] is None and not c["passed"] for c in doc["checks"] if c["verdict"] == "not run")
    assert SensorRegistry(tmp_path / "registry").get(draw_sensor(11, defect).serial).status == "rejected"


@pytest.mark.parametrize(
    "setup, args, fragment",
    [
        (None, ["--sensor", "{tmp}/absent.yaml"], "cannot read sensor spec"),
        ("spec: [unclosed", ["--sensor", "{tmp}/given"], "sensor spec"),
        ("a file", ["--out", "{tmp}/given"], "not a directory"),
        (None, ["--sim-fault", "meteor@3"], "unknown fault"),
        (None, ["--objects", "teapot"], "teapot"),
        (None, ["--objects", "mug,box,mug"], "object names must be unique, got mug twice"),
        ("version: 1\nchecks: {heldout_a1: {min: x}}\n", ["--thresholds", "{tmp}/given"], "finite number"),
        # was: accepted, the run rejected a good sensor and wrote that rejection into the registry (exit 1)
        ("version: 1\nchecks: {heldout_a1: {min: 5}}\n", ["--thresholds", "{tmp}/given"],
         "check 'heldout_a1': min must be in 0..1 (heldout_a1 is a fraction), got 5"),
        ("version: 1\nchecks: {leak_rate_hpa_per_min: {max: -1}}\n", ["--thresholds", "{tmp}/given"],
         "check 'leak_rate_hpa_per_min': max must be >= 0"),
        (None, ["--poses-per-object", "0"], "poses per object"),
        (None, ["--poses-per-object", "1001"], "poses per object must be 2..1000 (one or more is held out), got 1001"),
        (None, ["--leak-hold-s", "1e12"], "leak-test hold must be 2..600 s, got 1e+12 s"),  # was: a leak test without end
        (None, ["--leak-hold-s", "1e-9"], "leak-test hold must be 2..600 s, got 1e-09 s"),  # was: a refusal after it
        (None, ["--total-minutes", "0"], "total minutes"),
        # was: refused by the trainer after the whole recording
        (None, ["--finetune-minutes", "1e6"], "fine-tune minutes must be in (0, 10080] (a week), got 1000000.0"),
        # was: refused by the trainer after the whole recording, and so again on every resume
        (None, ["--seed", "4294967296"], "seed must be 0..4294967295, got 4294967296"),
        # was: accepted, the sensor's registry folder written among the run's files
        (None, ["--registry", "{tmp}/run"], "and the sensor registry"),
        (None, ["--registry", "{tmp}/run/registry"], "overlap; give each its own folder (--out, --registry)"),
        (None, ["--registry", "{tmp}"], "overlap; give each its own folder (--out, --registry)"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, setup, args, fragment):
    if setup is not None:
        (tmp_path / "given").write_text(setup)
    argv = ["commission", "--sim", "--out", str(tmp_path / "run"), "--registry", str(tmp_path / "registry")]
    argv += [a.format(tmp=tmp_path) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("bubble: error: ") and err.count("\n") == 1 and fragment in err
    assert not (tmp_path / "registry").exists() and not (tmp_path / "run").exists()  # refused before the bench opens


def test_a_base_model_the_fine_tune_cannot_load_is_refused_before_the_bench_opens(tmp_path, capsys):
    """Was: only its metadata and weights file were read up front; NaN weights (or tensors of another
    shape or dtype) were refused by the fine-tune, after the whole recording."""
    import torch

    model = tmp_path / "nan_model"
    key = edited_base_model(model, lambda tensor: torch.full_like(tensor, float("nan")))
    argv = ["commission", "--sim", "--out", str(tmp_path / "run"), "--registry", str(tmp_path / "registry"),
            "--base-model", str(model)]
    assert main(argv) == 2
    assert capsys.readouterr().err.splitlines() == [f"bubble: error: weight {key} in {model} holds NaN or inf"]
    assert not (tmp_path / "registry").exists() and not (tmp_path / "run").exists()


@pytest.mark.parametrize("change, message", [
    ({"poses_per_object": float("nan")}, "poses per object must be a whole number, got nan"),  # was: a ValueError
    ({"poses_per_object": 3.9}, "poses per object must be a whole number, got 3.9"),  # was: the planner's, later
    ({"seed": 1.5}, "seed must be a whole number, got 1.5"),
    ({"seed": True}, "seed must be a whole number, got True"),
    ({"total_minutes": "5"}, "total minutes must be a number, got '5'"),  # was: a TypeError
    ({"finetune_minutes": None}, "finetune minutes must be a number, got None"),
])
def test_the_python_apis_settings_of_the_wrong_type_are_input_errors(tmp_path, change, message):
    """``CommissionConfig`` from Python, where no argparse typed the numbers (docs/commissioning.md)."""
    from calibrate.commission_config import validate_config

    with pytest.raises(InputError) as info:
        validate_config(tiny_config(tmp_path, **change))
    assert str(info.value) == message and not (tmp_path / "run").exists()


def test_a_disk_too_full_to_record_on_is_refused_before_the_bench_opens(tmp_path, capsys, monkeypatch):
    """The recorder will not start with less than ``MIN_FREE_BYTES`` free; commissioning says so
    before the bench opens, not at the collection step after the leak test has moved the arm."""
    import collect.session_writer as session_writer

    monkeypatch.setattr(session_writer, "MIN_FREE_BYTES", shutil.disk_usage(tmp_path).free + 2**40)
    argv = ["commission", "--sim", "--out", str(tmp_path / "run"), "--registry", str(tmp_path / "registry")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("bubble: error: only ") and err.count("\n") == 1 and "free on the disk of" in err, err
    assert not (tmp_path / "run").exists()


def test_a_plan_the_bench_cannot_run_fails_before_the_arm_moves(tmp_path, monkeypatch):
    """The collection is planned as the bench connects: a plan its limits refuse ends the run
    before the arm's first motion, not at the collection step after the leak test and references."""
    from collect import collection
    from collect.arm import Arm

    moves = []
    real_travel_to = Arm.travel_to
    monkeypatch.setattr(Arm, "travel_to", lambda arm, *a, **k: moves.append(a) or real_travel_to(arm, *a, **k))

    def refuse(bench, settings):
        raise SafetyViolation("object 'box' cannot be reached safely: the workspace ends below it")

    monkeypatch.setattr(collection, "plan_bench_collection", refuse)
    with pytest.raises(InputError, match="cannot be reached safely"):
        run_commissioning(tiny_config(tmp_path), lambda event: None)
    assert moves == []
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["state.json"]


def test_a_run_directory_another_run_is_writing_is_refused_before_the_bench_opens(tmp_path, capsys):
    """Two commissionings with one --out (the same command in two terminals): while one holds the
    run directory, the other is refused with one line and touches nothing (was: both ran, one set
    the other's reference.h5 aside, and the other ended rejected for a recording deleted under it,
    a verdict it also wrote into the registry)."""
    config = tiny_config(tmp_path)
    config.run_dir.mkdir()
    argv = ["commission", "--sim", "--out", str(config.run_dir), "--registry", str(config.registry_dir),
            "--thresholds", str(config.thresholds), "--objects", "box", "--poses-per-object", "2",
            "--finetune-minutes", "0.05", "--leak-hold-s", "2", "--sim-speed", "2", "--seed", "3"]
    other_run = os.open(config.run_dir, os.O_RDONLY)
    try:
        fcntl.flock(other_run, fcntl.LOCK_EX)  # what the other run holds while it runs
        assert main(argv) == 2
    finally:
        os.close(other_run)
    err = capsys.readouterr().err
    assert err.startswith("bubble: error: ") and err.count("\n") == 1, err
    assert "is being written by another bubble commission" in err, err
    assert list(config.run_dir.iterdir()) == [] and not config.registry_dir.exists()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupt_during_commissioning_stops_the_arm_and_keeps_the_data(tmp_path, signum):
    """Ctrl-C and SIGTERM alike: the flow stops the arm and closes the run, exit 128 + signal."""
    run = tmp_path / "run"
    code, err = interrupt_once_recording(["commission", "--sim", "--objects", "box", "--poses-per-object", "2",
                                          "--leak-hold-s", "2", "--sim-speed", "2", "--quiet",
                                          "--registry", str(tmp_path / "registry"), "--out", str(run)],
                                         run / "session.h5", signum=signum)
    assert code == 128 + signum, err
    assert err.strip().splitlines()[-1].startswith("STOPPED: data kept in")
    assert json.loads((run / "acceptance.json").read_text())["stopped"] is True
    with Session.open(run / "session.h5") as s:
        assert s.closed_cleanly and s.n_frames > 0


def _finished_run_without_its_verdict(faulted_then_resumed, tmp_path):
    """A copy of the accepted run and its registry, with ``state.json`` as it was before the verdict
    step was recorded (every other step done)."""
    from calibrate.run_directory import RunState

    config = faulted_then_resumed["config"]
    config = dataclasses.replace(config, run_dir=tmp_path / "run", registry_dir=tmp_path / "registry")
    shutil.copytree(faulted_then_resumed["config"].run_dir, config.run_dir)
    shutil.copytree(faulted_then_resumed["config"].registry_dir, config.registry_dir)
    state = RunState(config.run_dir / "state.json", json.loads((config.run_dir / "state.json").read_text()))
    del state.data["steps"]["verdict"]
    del state.data["registration_id"], state.data["registered_in"]  # set by the verdict's registration
    state.save()
    return config


def test_a_fine_tune_that_could_hardly_train_is_the_computers_fault_not_the_sensors(tmp_path, monkeypatch):
    """Loading and validating took nearly all of the fine-tune step's time (a busy or slow computer):
    no verdict, nothing registered, and the same command fine-tunes again (was: the base model, trained
    0-1 steps, validated, and the sensor rejected and registered for it)."""
    from calibrate.run_directory import RunState

    config = dataclasses.replace(tiny_config(tmp_path), finetune_minutes=1.0, total_minutes=0.01)
    monkeypatch.setattr(commission_config, "MIN_FINETUNE_STEP_S", 8.0)  # the deadline cuts the fine-tune
    monkeypatch.setattr(commission_config, "MIN_TRAINING_SHARE", 1.1)  # so that its training is too short
    with pytest.raises(HardwareFault) as err:
        run_commissioning(config, lambda e: None)
    assert err.value.kind == "host-too-slow" and "nothing judged, nothing registered" in str(err.value)
    state = json.loads((config.run_dir / "state.json").read_text())
    assert "collect" in state["steps"] and "finetune" not in state["steps"] and "verdict" not in state["steps"]
    # its outcome files say so (was: none, or those of an attempt before: "stopped", every check not run)
    outcome = json.loads((config.run_dir / "acceptance.json").read_text())
    assert not outcome["accepted"] and outcome["fault"].startswith("host-too-slow: ") and not outcome["stopped"]
    assert outcome["reason"].startswith("no verdict: this computer's fault (host-too-slow)")
    assert set(outcome["steps"]) == set(state["steps"]) and ">NO VERDICT</div>" in (config.run_dir / "report.html").read_text()
    assert SensorRegistry(config.registry_dir).survey().profiles == []
    monkeypatch.setattr(commission_config, "MIN_TRAINING_SHARE", 0.0)
    assert run_commissioning(config, lambda e: None).accepted  # the same command, on a free computer


def test_a_rejection_after_a_short_fine_tune_says_so(tmp_path, monkeypatch):
    """A check of the fine-tuned model failed after a budget under the default: the reason, printed and
    registered, names the budget (was: a healthy sensor fine-tuned 1 s was registered as rejected on
    heldout_a1 0.77, its record silent on why)."""
    config = tiny_config(tmp_path)
    config.thresholds.write_text(LENIENT_MODEL_CHECKS.replace("heldout_rmse_mm: {max: 1000.0}",
                                                              "heldout_rmse_mm: {max: 0.001}"))
    monkeypatch.setattr(commission_config, "MIN_TRAINING_SHARE", 0.0)  # a loaded machine is not what this tests
    result = run_commissioning(config, lambda e: None)
    assert not result.accepted and result.fault is None
    failed, note = result.reason.split("; ")
    assert failed.startswith("heldout_rmse_mm ")
    assert re.fullmatch(r"the model fine-tuned \d+ s \(--finetune-minutes 0\.05, under the default 2\.5\): "
                        r"commission it again with the default budget before judging the sensor", note), note
    (profile,) = SensorRegistry(config.registry_dir).survey().profiles
    assert profile.history[-1]["reason"] == result.reason


def test_a_refused_resume_leaves_the_runs_settings_as_they_were(tmp_path, monkeypatch):
    """A run resumed with another budget and refused before it did anything (the bench holds another
    sensor): its state.json is left as it was (was: this attempt's settings recorded as the run's, and
    the first attempt's moved to earlier_settings, though nothing ran with them)."""
    from calibrate import acceptance
    from calibrate.commission_config import load_sensor_spec
    from calibrate.commissioning import _Flow
    from calibrate.run_directory import RunState, Step, run_settings

    config = tiny_config(tmp_path)
    settings = run_settings(config, load_sensor_spec(config).serial, acceptance.load_thresholds(config.thresholds))
    config.run_dir.mkdir()
    RunState.open(config.run_dir, settings).record(Step.CONNECT, {"ok": True, "summary": "connected"})
    before = (config.run_dir / "state.json").read_bytes()

    def another_sensor(flow) -> None:
        raise InputError(f"{flow.run_dir} was started for sensor A, the bench holds B; use a new --out")

    monkeypatch.setattr(_Flow, "open_bench", another_sensor)
    with pytest.raises(InputError, match="the bench holds B"):
        run_commissioning(dataclasses.replace(config, finetune_minutes=1.0), lambda e: None)
    assert (config.run_dir / "state.json").read_bytes() == before


def test_a_sensor_that_failed_a_gate_is_not_reconnected_when_its_run_is_run_again(tmp_path, monkeypatch):
    """A leaking sensor, its run stopped at the verdict (or killed there): run again, it reaches its
    verdict from state.json without the bench (was: the bench was reopened for the steps the failed gate
    skips, and a sensor taken off it since was refused, or the bench's fault registered instead)."""
    from calibrate.commissioning import _Flow
    from calibrate.run_directory import RunState
    from hw_mocks.sensor_spec import draw_sensor

    spec = tmp_path / "spec.yaml"
    draw_sensor(11, "leak").to_yaml(spec)
    config = dataclasses.replace(tiny_config(tmp_path), sensor_spec=spec)
    events = []
    first = run_commissioning(config, events.append)
    assert not first.accepted and "leak_rate_hpa_per_min" in first.reason
    assert "fine-tuned" not in first.reason  # no model judged: the budget is not the reason
    # the verdict shows the checks acceptance.json lists, the ones after the gate "not run" (was: the TUI
    # showed the checks made, "1/2 checks passed", beside the file's 16)
    (verdict,) = [e for e in events if isinstance(e, Verdict)]
    listed = json.loads((config.run_dir / "acceptance.json").read_text())["checks"]
    assert [(c["name"], c["verdict"]) for c in verdict.checks] == [(c["name"], c["verdict"]) for c in listed]
    assert any(c["verdict"] == "not run" for c in listed)
    state = RunState(config.run_dir / "state.json", json.loads((config.run_dir / "state.json").read_text()))
    del state.data["steps"]["verdict"]  # as a stop at the verdict leaves it
    state.data.pop("registration_id", None), state.data.pop("registered_in", None)
    state.save()

    def no_bench(self):
        raise AssertionError("the bench was opened")

    monkeypatch.setattr(_Flow, "open_bench", no_bench)
    again = run_commissioning(dataclasses.replace(config, sim_faults=("serial-unplug@0.1",)), lambda e: None)
    assert not again.accepted and again.fault is None and again.reason == first.reason


def test_a_run_killed_after_it_registered_replaces_its_entry_when_run_again(faulted_then_resumed, tmp_path, monkeypatch):
    """The process dies after the registry write and before state.json records the verdict (a kill, a
    power cut): the re-run registers the same commissioning again in place (was: a second entry)."""
    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    register = SensorRegistry.register

    class Killed(BaseException):
        pass

    def register_then_die(self, *args, **kwargs):
        register(self, *args, **kwargs)
        raise Killed

    monkeypatch.setattr(SensorRegistry, "register", register_then_die)
    with pytest.raises(Killed):
        run_commissioning(config, lambda e: None)
    monkeypatch.undo()
    assert len(SensorRegistry(config.registry_dir).survey().profiles[0].history) == 3
    stop = threading.Event()
    stop.set()  # a re-run stopped at once keeps the entry's id (was: dropped, and the next run added a fourth entry)
    assert run_commissioning(config, lambda e: None, stop).stopped
    assert run_commissioning(config, lambda e: None).accepted
    (profile,) = SensorRegistry(config.registry_dir).survey().profiles
    assert [h["accepted"] for h in profile.history] == [False, True, True]
    assert len({h["id"] for h in profile.history}) == 3  # the fault's, the copied run's, this one's
    state = json.loads((config.run_dir / "state.json").read_text())
    assert state["steps"]["verdict"]["ok"] and state["registered_in"] == [str(config.registry_dir.resolve())]


def test_a_finished_run_run_again_with_another_registry_is_registered_there_once(faulted_then_resumed, tmp_path):
    """Was: nothing registered and nothing said; the sensor missing from the registry the command named."""
    config = faulted_then_resumed["config"]
    run_dir = tmp_path / "run"
    shutil.copytree(config.run_dir, run_dir)
    state = json.loads((run_dir / "state.json").read_text())
    before = sorted(p.read_bytes() for p in config.registry_dir.rglob("*") if p.is_file())
    elsewhere = dataclasses.replace(config, run_dir=run_dir, registry_dir=tmp_path / "lab_registry")
    for _ in range(2):  # the second time it is in that registry already
        assert run_commissioning(elsewhere, lambda e: None).accepted
        (profile,) = SensorRegistry(elsewhere.registry_dir).survey().profiles
        assert [(h["id"], h["time"], h["accepted"]) for h in profile.history] == [
            (state["registration_id"], state["steps"]["verdict"]["finished"], True)]
        assert profile.status == "accepted" and profile.model_dir is not None
    after = json.loads((run_dir / "state.json").read_text())["registered_in"]
    assert after == [str(config.registry_dir.resolve()), str(elsewhere.registry_dir.resolve())]
    assert sorted(p.read_bytes() for p in config.registry_dir.rglob("*") if p.is_file()) == before


def test_a_finished_run_whose_model_was_moved_is_not_registered_elsewhere(faulted_then_resumed, tmp_path):
    """Was: a FileNotFoundError traceback, and an empty sensor folder left in the other registry."""
    config = faulted_then_resumed["config"]
    run_dir = tmp_path / "run"
    shutil.copytree(config.run_dir, run_dir)
    shutil.rmtree(run_dir / "model")
    elsewhere = dataclasses.replace(config, run_dir=run_dir, registry_dir=tmp_path / "lab_registry")
    with pytest.raises(InputError, match=re.escape(
            f"cannot register the accepted sensor in {elsewhere.registry_dir}: {run_dir / 'model'} is gone (moved or "
            "deleted since the run); put it back and run the same command again")):
        run_commissioning(elsewhere, lambda e: None)
    assert not elsewhere.registry_dir.exists()


def test_a_stop_after_the_verdict_leaves_the_verdicts_exit_code(tmp_path, monkeypatch, capsys, interrupt_handlers_restored):
    """A Ctrl-C while the flow registers its verdict (the flow no longer stops then): was exit 130,
    "bubble: interrupted", for an accepted sensor registered all the same (a rejected one: 1)."""
    import calibrate.commissioning
    from calibrate.commissioning import CommissionResult

    def verdict_then_stop(config, on_event, stop_event):
        os.kill(os.getpid(), signal.SIGINT)
        assert stop_event.wait(5)
        return CommissionResult(True, [], config.run_dir, config.run_dir / "report.html")

    monkeypatch.setattr(calibrate.commissioning, "run_commissioning", verdict_then_stop)
    assert main(["commission", "--sim", "--out", str(tmp_path / "run"), "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert out == f"ACCEPTED: report {tmp_path / 'run' / 'report.html'}\n"
    assert err == ("bubble: stopping the arm and closing the run ...\n"
                   "bubble: the stop came after the verdict was reached; the verdict stands\n")


def test_a_stop_during_the_last_step_is_honoured_before_the_verdict(faulted_then_resumed, tmp_path):
    """Was: the stop acknowledged ("stopping the arm and closing the run ..."), then a verdict written
    and registered and exit 0/1 instead of the signal's code."""
    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    stop = threading.Event()
    stop.set()
    result = run_commissioning(config, lambda e: None, stop)
    assert result.stopped and not result.accepted
    assert len(SensorRegistry(config.registry_dir).survey().profiles[0].history) == 2
    assert "verdict" not in json.loads((config.run_dir / "state.json").read_text())["steps"]
    assert run_commissioning(config, lambda e: None).accepted  # the re-run reaches the verdict


def test_a_recorder_fault_stops_the_arm_and_registers_nothing(tmp_path, capsys, monkeypatch):
    """The host's disk (here: the session file deleted mid-recording) says nothing of the sensor: the
    arm safe-stops, the run ends with the fault (exit 3) and the registry is untouched (was: the
    sensor registered as rejected, an accepted one flipped to rejected)."""
    from collect.session_writer import SessionWriter

    append_frame = SessionWriter.append_frame
    appended = []

    def append_then_delete(writer, *args, **kwargs):
        append_frame(writer, *args, **kwargs)
        if writer.path.endswith("session.h5"):
            appended.append(1)
            if len(appended) == 40:
                os.remove(writer.path)

    monkeypatch.setattr(SessionWriter, "append_frame", append_then_delete)
    config = tiny_config(tmp_path)
    argv = ["commission", "--sim", "--objects", "box", "--poses-per-object", "2", "--seed", "3", "--sim-speed", "2",
            "--leak-hold-s", "2", "--finetune-minutes", "0.05", "--thresholds", str(config.thresholds),
            "--out", str(config.run_dir), "--registry", str(config.registry_dir), "--quiet"]
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert err.startswith("bubble: fault: recorder: cannot write") and err.count("\n") == 1, err
    assert not config.registry_dir.exists() or SensorRegistry(config.registry_dir).survey().profiles == []
    state = json.loads((config.run_dir / "state.json").read_text())
    assert "reference" in state["steps"] and "collect" not in state["steps"]
    with Session.open(config.run_dir / "session.h5") as s:
        assert s.closed_cleanly and s.n_frames >= 30


def test_a_run_removes_the_temporary_files_a_killed_run_left(faulted_then_resumed, tmp_path):
    """Was: a run killed while it wrote acceptance.json left ``acceptance.json.<random>.tmp`` for good."""
    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    leftovers = [config.run_dir / "acceptance.json.qnn9fi55.tmp", config.run_dir / "model" / "model.onnx.x1y2z3w4.tmp"]
    for path in leftovers:
        path.write_text("{\"accepted\": tr")
    assert run_commissioning(config, lambda e: None).accepted
    assert not any(path.exists() for path in leftovers)


def test_a_run_whose_recording_is_done_resumes_on_a_disk_too_full_to_record(faulted_then_resumed, tmp_path, monkeypatch):
    """The recorder's 200 MB reserve is for recording (was: a run with only its verdict left refused
    with "recording needs at least 200 MB", also after the user guide's "free some space")."""
    import collect.session_writer as session_writer

    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    monkeypatch.setattr(session_writer, "MIN_FREE_BYTES", shutil.disk_usage(tmp_path).free + 2**40)
    assert run_commissioning(config, lambda e: None).accepted
    with pytest.raises(InputError, match="recording needs at least"):  # a new run still is refused
        run_commissioning(dataclasses.replace(config, run_dir=tmp_path / "new"), lambda e: None)


def test_the_tui_refuses_a_run_folder_of_another_sensor_before_it_starts(faulted_then_resumed, capsys):
    """Was: accepted at start-up, refused by the flow only once the operator had confirmed the start."""
    config = faulted_then_resumed["config"]
    argv = ["tui", "--sim", "--seed", "4", "--objects", "box", "--poses-per-object", "2", "--out", str(config.run_dir),
            "--registry", str(config.registry_dir), "--thresholds", str(config.thresholds)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bubble: error: {config.run_dir} holds a run with sensor='SB-SIM-000003', not "
                          "'SB-SIM-000004'") and err.count("\n") == 1, err


def test_an_early_fault_names_itself_where_the_checks_would_be(tmp_path):
    """Was: "Acceptance checks — Not available: not produced by this run." after a fault at connect."""
    result = run_commissioning(tiny_config(tmp_path, sim_faults=("camera-stall@1",)), lambda e: None)
    assert result.fault and not result.checks
    report = (tmp_path / "run" / "report.html").read_text()
    assert f"Acceptance checks</h2><p class='note'>Not available: {result.reason}." in report


def test_a_frozen_pressure_board_fails_the_run_not_passes_the_leak_test(tmp_path):
    """Was: a board repeating one reading gave a leak rate of 0 hPa/min, and a leaking bubble passed."""
    events: list = []
    result = run_commissioning(tiny_config(tmp_path, sim_faults=("pressure-frozen@0",)), events.append)
    assert not result.accepted and result.fault.startswith("pressure-frozen: pressure board: 100 readings in a row")
    assert not [c for c in result.checks if c["name"] == "leak_rate_hpa_per_min"]
    assert not (tmp_path / "run" / "leak_test.npz").exists()


def test_a_folder_of_other_files_is_refused_as_a_run_folder(tmp_path, capsys):
    """Was: a run into a folder holding no run wrote over its report.html and acceptance.json."""
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "report.html").write_text("precious")
    (folder / "acceptance.json.qnn9fi55.tmp").write_text("{")  # a killed writer's leftover is no foreign file
    assert main(["commission", "--sim", "--out", str(folder), "--registry", str(tmp_path / "reg")]) == 2
    assert capsys.readouterr().err == (f"bubble: error: {folder} holds no commissioning run (no state.json) but other "
                                       "files (report.html), which a run would write over; use a new or empty --out "
                                       "directory\n")
    assert sorted(p.name for p in folder.iterdir()) == ["acceptance.json.qnn9fi55.tmp", "report.html"]
    assert (folder / "report.html").read_text() == "precious" and not (tmp_path / "reg").exists()


def test_a_finished_runs_deleted_report_is_written_again(faulted_then_resumed, tmp_path):
    """Was: "ACCEPTED: report run/report.html" for a report deleted since, and none written."""
    config = faulted_then_resumed["config"]
    run_dir = tmp_path / "run"
    shutil.copytree(config.run_dir, run_dir)
    first = json.loads((run_dir / "acceptance.json").read_text())
    (run_dir / "report.html").unlink()
    registry = tmp_path / "registry"  # the registry it was registered in (a copy: the paths differ)
    shutil.copytree(config.registry_dir, registry)
    result = run_commissioning(dataclasses.replace(config, run_dir=run_dir, registry_dir=registry), lambda e: None)
    assert result.accepted and result.report_path.is_file() and "ACCEPTED" in result.report_path.read_text()
    assert len(SensorRegistry(registry).survey().profiles[0].history) == 2  # the same entry id: replaced, not added
    again = json.loads((run_dir / "acceptance.json").read_text())  # was: stamped with the time it was written again
    verdict_t = json.loads((run_dir / "state.json").read_text())["steps"]["verdict"]["finished"]
    assert again["finished"] == verdict_t and abs(datetime.fromisoformat(verdict_t)
                                                  - datetime.fromisoformat(first["finished"])).total_seconds() < 5
    assert again["steps"] == first["steps"] and "verdict" not in again["steps"]


def test_a_stop_while_the_verdict_is_written_registers_nothing(faulted_then_resumed, tmp_path, monkeypatch):
    """Was: a Ctrl-C while the report was written was acknowledged, then the sensor was registered
    and the command exited 0."""
    from calibrate.commissioning import _Flow

    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    stop = threading.Event()
    write_outcome = _Flow.write_outcome

    def stopped_while_writing(self, *args):
        doc = write_outcome(self, *args)
        stop.set()
        return doc

    monkeypatch.setattr(_Flow, "write_outcome", stopped_while_writing)
    result = run_commissioning(config, lambda e: None, stop)
    assert result.stopped and not result.accepted
    assert len(SensorRegistry(config.registry_dir).survey().profiles[0].history) == 2
    assert "verdict" not in json.loads((config.run_dir / "state.json").read_text())["steps"]
    assert json.loads((config.run_dir / "acceptance.json").read_text())["stopped"]


def test_a_stop_as_the_verdict_starts_writes_no_verdict_and_shows_the_step_stopped(faulted_then_resumed, tmp_path,
                                                                                   monkeypatch):
    """The operator's stop comes as the verdict step starts: the outcome files are written once, as
    stopped, and the verdict step does not finish as failed (the TUI then shows it stopped). Was: they
    were written as the verdict (ACCEPTED: a kill then left an accepted acceptance.json never
    registered), then again as stopped, and the step finished as failed."""
    from calibrate.commissioning import _Flow

    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    stop = threading.Event()
    written = []
    write_outcome = _Flow.write_outcome

    def noting(self, accepted, reason, fault, stopped, *args):
        written.append((accepted, stopped))
        return write_outcome(self, accepted, reason, fault, stopped, *args)

    def on_event(event) -> None:
        if isinstance(event, StepStarted) and event.step is Step.VERDICT:
            stop.set()
        events.append(event)

    events = []
    monkeypatch.setattr(_Flow, "write_outcome", noting)
    result = run_commissioning(config, on_event, stop)
    assert result.stopped and written == [(False, True)]
    assert not [e for e in events if isinstance(e, StepFinished) and e.step is Step.VERDICT]


def test_a_full_disk_outside_the_recorder_is_a_recorder_fault(tmp_path, capsys, monkeypatch):
    """Was: exit 2 ("bad input") after the arm had moved, and a cut-off leak_test.npz."""
    import errno

    from calibrate import commissioning

    def disk_full(path, **arrays):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(commissioning, "save_npz", disk_full)
    config = tiny_config(tmp_path)
    argv = ["commission", "--sim", "--objects", "box", "--poses-per-object", "2", "--seed", "3", "--sim-speed", "2",
            "--leak-hold-s", "2", "--thresholds", str(config.thresholds),
            "--out", str(config.run_dir), "--registry", str(config.registry_dir), "--quiet"]
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert err == f"bubble: fault: recorder: cannot write {config.run_dir / 'leak_test.npz'}: No space left on device\n"
    assert not config.registry_dir.exists() or SensorRegistry(config.registry_dir).survey().profiles == []


def test_a_full_disk_as_the_verdict_is_written_is_a_recorder_fault(faulted_then_resumed, tmp_path, monkeypatch):
    """Was: exit 2 ("bad input"), acceptance.json written as accepted before the report failed, and
    nothing registered."""
    import errno

    import calibrate.report

    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    write_text = calibrate.report.write_text
    failures = [OSError(errno.ENOSPC, "No space left on device", str(config.run_dir / "report.html"))]

    def full_once(*args, **kwargs):
        if failures:
            raise failures.pop()
        return write_text(*args, **kwargs)

    monkeypatch.setattr(calibrate.report, "write_text", full_once)
    with pytest.raises(HardwareFault, match="cannot write .*report.html: No space left on device") as fault:
        run_commissioning(config, lambda e: None)
    assert fault.value.kind == "recorder"
    outcome = json.loads((config.run_dir / "acceptance.json").read_text())
    assert not outcome["accepted"] and outcome["reason"].startswith("no verdict: this computer's fault (recorder)")
    assert len(SensorRegistry(config.registry_dir).survey().profiles[0].history) == 2
    assert "verdict" not in json.loads((config.run_dir / "state.json").read_text())["steps"]


def test_the_pose_check_judges_held_out_mug_poses_only(tmp_path, monkeypatch):
    """A split that held out no mug pose (one recorded) leaves the pose check without a frame to judge
    (was: ``pose_ids`` None, and it judged the poses the model was fine-tuned on)."""
    import calibrate.pose_check
    from calibrate.acceptance import load_thresholds
    from calibrate.commissioning import _Flow
    from calibrate.run_directory import RunState

    asked = []

    def no_frame_among(model, data, object_name, *, pose_ids, **kwargs):
        asked.append(pose_ids)
        raise InputError(f"no hold frame of {object_name} among pose_ids {pose_ids}")

    monkeypatch.setattr(calibrate.pose_check, "run_pose_check", no_frame_among)
    config = tiny_config(tmp_path, objects=("mug", "box"))
    flow = _Flow(config, lambda e: None, threading.Event(), load_thresholds(config.thresholds), None)
    for held_out, expected in (({"box": [2]}, []), ({"box": [2], "mug": [1]}, [1])):
        flow.state = RunState(tmp_path / "state.json", {"steps": {"validate": {"heldout_pose_ids": held_out}}})
        record = flow.step_pose_check()
        assert asked[-1] == expected and not any(c["passed"] for c in record["checks"])


def test_a_stop_during_the_validation_ends_the_run_there(faulted_then_resumed, tmp_path, monkeypatch):
    """Was: a stop during the validate step let the step finish (its statistics, its files) first."""
    import trainer.evaluation

    config = _finished_run_without_its_verdict(faulted_then_resumed, tmp_path)
    state_path = config.run_dir / "state.json"
    state = json.loads(state_path.read_text())
    for step in ("validate", "pose_check"):
        del state["steps"][step]
    from calibrate.run_directory import RunState

    RunState(state_path, state).save()
    stop = threading.Event()
    predict = trainer.evaluation.predict_frames

    def predict_then_stop(*args, **kwargs):
        out = predict(*args, **kwargs)
        stop.set()
        return out

    monkeypatch.setattr(trainer.evaluation, "predict_frames", predict_then_stop)
    result = run_commissioning(config, lambda e: None, stop)
    assert result.stopped
    assert "validate" not in json.loads(state_path.read_text())["steps"]
