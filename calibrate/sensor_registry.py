"""Sensor registry: one directory per commissioned sensor serial.

Location: ``--registry DIR``, else ``$BUBBLE_REGISTRY``, else ``<user data dir>/bubble-bench/sensors``
(platformdirs). Layout::

    <root>/<serial>/profile.json     serial, status (accepted/rejected), intrinsics, camera_in_tcp,
                                     simulated, current model, last acceptance summary,
                                     history: one entry per commissioning (time, run_dir,
                                     accepted, reason, held-out metrics)
    <root>/<serial>/model/           the model of the last *accepted* commissioning
    <root>/<serial>/reference.npz    no-contact reference: depth_m (H,W) float32 m (0 = invalid),
                                     ir (H,W) float32 amplitude, valid_count (H,W) int32
    <root>/<serial>/acceptance.json  acceptance results of the last commissioning

A rejected commissioning is recorded in the history and the status, but never replaces the model
or reference of an earlier accepted one.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from collect.errors import InputError
from collect.json_files import write_json

ENV_VAR = "BUBBLE_REGISTRY"
PROFILE = "profile.json"
_SERIAL_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def default_registry_dir() -> Path:
    """``$BUBBLE_REGISTRY`` if set, else the platform's user data dir for bubble-bench."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser()
    from platformdirs import user_data_dir

    return Path(user_data_dir("bubble-bench", appauthor=False)) / "sensors"


@dataclass
class SensorProfile:
    serial: str
    path: Path  # the sensor's directory
    data: dict  # profile.json

    @property
    def status(self) -> str:
        return self.data.get("status", "unknown")

    @property
    def history(self) -> list[dict]:
        return self.data.get("history", [])

    @property
    def model_dir(self) -> Path | None:
        return self.path / "model" if (self.path / "model").is_dir() else None


class SensorRegistry:
    """The registry directory (created on first registration)."""

    def __init__(self, root: Path | None = None):
        self.root = Path(root).expanduser() if root is not None else default_registry_dir()
        if self.root.exists() and not self.root.is_dir():
            raise InputError(f"sensor registry {self.root} is not a directory")

    def _sensor_dir(self, serial: str) -> Path:
        if not _SERIAL_RE.match(serial or ""):
            raise InputError(f"sensor serial {serial!r} is not a valid registry name (letters, digits, . _ -)")
        return self.root / serial

    def register(
        self,
        serial: str,
        *,
        accepted: bool,
        run_dir: Path,
        intrinsics: dict,
        camera_in_tcp: list[float] | None,
        simulated: bool,
        acceptance: dict,
        reason: str = "",
        model_dir: Path | None = None,
        reference: dict[str, np.ndarray] | None = None,
        when: datetime | None = None,
    ) -> SensorProfile:
        """Record one commissioning of ``serial``; returns the updated profile.

        ``acceptance``: the ``acceptance.json`` content. ``model_dir`` and ``reference``
        (``depth_m``, ``ir``, ``valid_count`` arrays) are stored only when ``accepted``.
        """
        sdir = self._sensor_dir(serial)
        sdir.mkdir(parents=True, exist_ok=True)
        when = when or datetime.now(timezone.utc)
        prior = self._read_profile(sdir) if (sdir / PROFILE).exists() else {"serial": serial, "history": []}
        metrics = {k: acceptance.get(k) for k in ("abs_rel", "rmse", "a1") if k in acceptance}
        entry = {
            "time": when.isoformat(timespec="seconds"),
            "run_dir": str(Path(run_dir).resolve()),
            "accepted": bool(accepted),
            "reason": reason,
            **metrics,
        }
        profile = dict(prior)
        profile.update(
            serial=serial,
            status="accepted" if accepted else "rejected",
            intrinsics=intrinsics,
            camera_in_tcp=camera_in_tcp,
            simulated=bool(simulated),
            last_commissioned=entry["time"],
            last_reason=reason,
        )
        if accepted:
            if model_dir is not None:
                dst = sdir / "model"
                staging = sdir / "model.new"
                shutil.rmtree(staging, ignore_errors=True)
                shutil.copytree(model_dir, staging)
                shutil.rmtree(dst, ignore_errors=True)
                os.replace(staging, dst)
                profile["model"] = "model"
                profile["model_source"] = str(Path(model_dir).resolve())
            if reference is not None:
                np.savez_compressed(sdir / "reference.npz", **reference)
                profile["reference"] = "reference.npz"
            profile["accepted_at"] = entry["time"]
            profile["accepted_metrics"] = metrics
        profile["history"] = list(prior.get("history", [])) + [entry]
        write_json(sdir / "acceptance.json", acceptance)
        write_json(sdir / PROFILE, profile)
        return SensorProfile(serial, sdir, profile)

    def _read_profile(self, sdir: Path) -> dict:
        try:
            profile = json.loads((sdir / PROFILE).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise InputError(f"sensor registry entry {sdir} is unreadable: {err}") from None
        history = profile.get("history") if isinstance(profile, dict) else None
        if not (isinstance(history, list) and all(isinstance(h, dict) and isinstance(h.get("accepted"), bool)
                                                  and isinstance(h.get("time"), str) for h in history)):
            raise InputError(f"sensor registry entry {sdir} is corrupt: {PROFILE} needs a 'history' of commissionings")
        return profile

    def get(self, serial: str) -> SensorProfile:
        sdir = self._sensor_dir(serial)
        if not (sdir / PROFILE).is_file():
            raise InputError(f"sensor {serial!r} is not in the registry {self.root}")
        return SensorProfile(serial, sdir, self._read_profile(sdir))

    def profiles(self) -> list[SensorProfile]:
        """All registered sensors, sorted by serial (unreadable entries raise ``InputError``)."""
        if not self.root.is_dir():
            return []
        out = []
        for sdir in sorted(p for p in self.root.iterdir() if (p / PROFILE).is_file()):
            out.append(SensorProfile(sdir.name, sdir, self._read_profile(sdir)))
        return out

    def reference(self, serial: str) -> dict[str, np.ndarray]:
        """The stored no-contact reference of an accepted sensor."""
        path = self.get(serial).path / "reference.npz"
        if not path.is_file():
            raise InputError(f"sensor {serial!r} has no accepted reference in {self.root}")
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
