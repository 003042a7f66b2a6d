"""The run directory of a commissioning (``RUN_DIR``): its file names and its ``state.json``.

``RunState`` is ``RUN_DIR/state.json``: the settings of the run (``run_settings``) and the results of
its completed steps, which a re-run with the same ``RUN_DIR`` skips (``calibrate.commissioning``).
Only this module writes it, with a SHA-256 of its content: a re-run refuses a ``state.json`` that was
damaged or edited by hand, whose step results it would otherwise trust (and put into the registry).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING

from calibrate.commission_events import STEPS, Step
from collect.atomic_files import is_leftover
from collect.errors import InputError
from collect.json_files import JSON_READ_ERRORS, plain_json, read_json_object, write_json
from collect.session_format import utc_now

if TYPE_CHECKING:
    from calibrate.acceptance import Thresholds
    from calibrate.commission_config import CommissionConfig

STATE_FILE = "state.json"
STATE_VERSION = 4  # 2: with its checksum (CHECKSUM_KEY); 3: base model and acceptance limits must match;
#                   4: the base model compared by its weights' SHA-256 (was: by the path as typed)
CHECKSUM_KEY = "sha256"
SESSION_FILE = "session.h5"
REFERENCE_FILE = "reference.h5"
MODEL_DIR = "model"
ACCEPTANCE_FILE = "acceptance.json"
REPORT_FILE = "report.html"
LEAK_FILE = "leak_test.npz"
CAMERA_FILE = "camera_health.npz"
VALIDATION_FILE = "validation.npz"
POSE_FILE = "pose_check.json"
PLOTS_DIR = "plots"
#: ``bubble tui``'s log of the commissioning it runs in a child process, opened before the run starts.
FLOW_LOG = "flow.log"

#: Settings that must match when a run directory is resumed (or a finished run reported again):
#: what was recorded, the weights it starts from and the limits that judge it, both by content (the same
#: base model given by another path is the same run; other weights at the same path are not). The time
#: budgets (the leak test's hold included: a finished leak test is kept), the simulated faults and the
#: simulation speed may change between attempts.
RESUME_KEYS = ("simulated", "sensor", "objects", "poses_per_object", "seed", "base_model_sha256", "limits_sha256")


def run_settings(config: CommissionConfig, sensor_id: str, thresholds: Thresholds) -> dict:
    """The settings of a run as ``state.json`` records them (``sensor_id``: the simulated sensor's
    serial, or ``"hardware"``; ``thresholds``: the acceptance thresholds in force). The base model's
    weights must be readable (``validate_config`` checks them first)."""
    from trainer.model_dir import weights_sha256  # here: torch, which it imports, is slow to load

    return {
        "simulated": bool(config.simulated),
        "sensor": sensor_id,
        "objects": list(config.objects),
        "poses_per_object": int(config.poses_per_object),
        "seed": int(config.seed),
        "finetune_minutes": float(config.finetune_minutes),
        "leak_hold_s": float(config.leak_hold_s),
        "total_minutes": float(config.total_minutes) if config.total_minutes not in (None, math.inf) else None,
        "base_model": str(config.base_model) if config.base_model else "base",
        "base_model_sha256": weights_sha256(config.base_model or "base"),
        "thresholds": str(config.thresholds) if config.thresholds else "packaged",
        "limits_sha256": thresholds.limits_sha256(),
        "sim_faults": list(config.sim_faults),
        "sim_speed": float(config.sim_speed),
    }


def recording_done(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a run that records nothing more: its ``state.json`` has the
    collection step done, or the verdict (a failed hardware check ends a run before collection).
    False for no run, or an unreadable one (``RunState.open`` says what is wrong with it)."""
    try:
        data = json.loads((Path(run_dir) / STATE_FILE).read_text())
    except JSON_READ_ERRORS:
        return False
    steps = data.get("steps") if isinstance(data, dict) else None
    return isinstance(steps, dict) and (Step.COLLECT.value in steps or Step.VERDICT.value in steps)


class RunState:
    """``RUN_DIR/state.json``: the settings of the run and the results of its completed steps."""

    def __init__(self, path: Path, data: dict):
        self.path = path
        self.data = data

    @classmethod
    def open(cls, run_dir: Path, settings: dict) -> "RunState":
        """Load the state of ``run_dir`` (or start one); raises ``InputError`` when the directory
        holds a run with other settings. A run resumed with other budgets, faults or speed records
        them as its ``settings``, those of the attempts before in ``earlier_settings`` (oldest first;
        was: the first attempt's alone, which the report of the attempt that reached the verdict
        showed as its own); a finished run keeps the settings of its verdict. Those settings are
        written with the attempt's first record (``record``): an attempt refused before it records
        anything leaves ``state.json`` as it was (was: rewritten here, the refused attempt's settings
        then shown as the run's)."""
        path = run_dir / STATE_FILE
        if not path.exists():
            cls._check_no_other_files(run_dir)
            state = cls(path, {"version": STATE_VERSION, "settings": settings, "created": utc_now(), "steps": {}})
            state.save()
            return state
        state = cls._read(run_dir, settings)
        if not state.done(Step.VERDICT) and state.data["settings"] != settings:
            state.data.setdefault("earlier_settings", []).append(state.data["settings"])
            state.data["settings"] = settings
        return state

    @classmethod
    def check(cls, run_dir: Path, settings: dict) -> None:
        """``InputError`` now, writing nothing, where ``open`` would raise it: ``run_dir`` holds a run
        with other settings, or a damaged ``state.json``."""
        if (run_dir / STATE_FILE).exists():
            cls._read(run_dir, settings)
        else:
            cls._check_no_other_files(run_dir)

    @staticmethod
    def _check_no_other_files(run_dir: Path) -> None:
        """``InputError`` when ``run_dir``, holding no run (no ``state.json``), holds other files: a run
        would write over a ``report.html`` or an ``acceptance.json`` of something else (was: replaced
        without a word)."""
        if not run_dir.is_dir():
            return
        others = sorted(p.name for p in run_dir.iterdir() if not is_leftover(p) and p.name != FLOW_LOG)
        if others:
            raise InputError(f"{run_dir} holds no commissioning run (no {STATE_FILE}) but other files "
                             f"({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}), which a run would write "
                             "over; use a new or empty --out directory")

    @classmethod
    def _read(cls, run_dir: Path, settings: dict) -> "RunState":
        path = run_dir / STATE_FILE
        data = read_json_object(path, "use a new --out directory")
        if data.get("version") != STATE_VERSION:
            raise InputError(f"{path} is from another version of bubble commission; use a new --out directory")
        if data.get(CHECKSUM_KEY) != _checksum(data):
            raise InputError(f"{path} does not match its checksum (damaged or edited by hand); use a new --out directory")
        saved = data["settings"]
        for key in RESUME_KEYS:
            if saved.get(key) == settings.get(key):
                continue
            if key == "base_model_sha256":
                raise InputError(
                    f"{run_dir} holds a run fine-tuned from other base-model weights (--base-model "
                    f"{saved.get('base_model')!r}) than --base-model gives now ({settings.get('base_model')!r}); use a "
                    "new --out directory to commission from another base model"
                )
            if key == "limits_sha256":
                raise InputError(
                    f"{run_dir} holds a run judged by other acceptance limits (thresholds {saved.get('thresholds')!r}) "
                    f"than --thresholds gives now ({settings.get('thresholds')!r}); use a new --out directory to "
                    "commission with other thresholds"
                )
            raise InputError(
                f"{run_dir} holds a run with {key}={saved.get(key)!r}, not {settings.get(key)!r}; "
                "use a new --out directory to commission with other settings"
            )
        return cls(path, data)

    def save(self) -> None:
        self.data[CHECKSUM_KEY] = _checksum(self.data)
        write_json(self.path, self.data)

    def done(self, step: Step) -> bool:
        return step.value in self.data["steps"]

    def get(self, step: Step) -> dict:
        return self.data["steps"].get(step.value, {})

    def record(self, step: Step, result: dict) -> None:
        self.data["steps"][step.value] = {**result, "finished": utc_now()}
        self.save()

    def checks(self) -> list[dict]:
        """Every check of the completed steps, in step order."""
        out = []
        for step in STEPS:
            out += self.get(step).get("checks", [])
        return out


def _checksum(data: dict) -> str:
    """SHA-256 (hex) of ``data`` without its ``CHECKSUM_KEY``, as the canonical text (sorted keys) of the
    JSON that ``write_json`` writes (``plain_json``: NaN as null, tuples as lists)."""
    content = plain_json({k: v for k, v in data.items() if k != CHECKSUM_KEY})
    return hashlib.sha256(json.dumps(content, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def set_aside(path: Path) -> None:
    """Keep the file of an interrupted earlier attempt as ``<name>.aborted-<n><suffix>``."""
    if not path.exists():
        return
    n = 1
    while (aside := path.with_name(f"{path.stem}.aborted-{n}{path.suffix}")).exists():
        n += 1
    os.replace(path, aside)
