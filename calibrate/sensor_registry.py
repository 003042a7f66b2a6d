"""Sensor registry: one directory per commissioned sensor serial.

Location: ``--registry DIR``, else ``$BUBBLE_REGISTRY``, else ``<user data dir>/bubble-bench/sensors``
(platformdirs). Layout::

    <root>/<serial>/profile.json     serial, status (accepted/rejected), intrinsics, camera_in_tcp,
                                     simulated (of the run whose model is kept: the last accepted
                                     one, else the last one), current model, last acceptance summary,
                                     history: one entry per commissioning (time, run_dir,
                                     accepted, reason, held-out metrics)
    <root>/<serial>/model/           the model of the last *accepted* commissioning
    <root>/<serial>/reference.npz    no-contact reference: depth_m (H,W) float32 m (0 = invalid),
                                     ir (H,W) float32 amplitude, valid_count (H,W) int32
    <root>/<serial>/acceptance.json  acceptance results of the last commissioning

A rejected commissioning is recorded in the history and the status, but never replaces the model
or reference of an earlier accepted one. Registrations of one sensor are serialized (a lock on its
directory): two commissionings that finish at the same moment are both recorded, one after the other.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from collect.errors import InputError
from collect.json_files import JSON_READ_ERRORS, shown_json, write_json
from collect.numbers import real_number, real_numbers
from collect.output_files import output_folder_lock
from collect.pressure_board import SENSOR_SERIAL_RE, SENSOR_SERIAL_RULE

ENV_VAR = "BUBBLE_REGISTRY"
PROFILE = "profile.json"


def default_registry_dir() -> Path:
    """``$BUBBLE_REGISTRY`` if set, else the platform's user data dir for bubble-bench."""
    env = os.environ.get(ENV_VAR)
    if env is not None and env.strip():
        return Path(env).expanduser()
    if env:  # was: a folder named by a space, in the current folder
        raise InputError(f"${ENV_VAR} is blank: name the registry folder, or unset it")
    from platformdirs import user_data_dir

    return Path(user_data_dir("bubble-bench", appauthor=False)) / "sensors"


@dataclass
class SensorProfile:
    """One sensor's registry entry: its folder and its ``profile.json`` (checked by ``check_profile``)."""

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
        """The accepted model's folder: the one ``profile.json`` names, when present. A ``model/`` it does
        not name (a registration killed between storing the model and writing the profile) is none."""
        folder = self.path / "model"
        return folder if self.data.get("model") and folder.is_dir() else None

    @property
    def model_state(self) -> str:
        """``yes`` (a kept model), ``no`` (none accepted) or ``MISSING`` (its files were deleted)."""
        return "MISSING" if self.missing() else ("yes" if self.model_dir else "no")

    @property
    def model_metrics(self) -> dict:
        """The kept model's held-out metrics at its acceptance ({} when none was accepted)."""
        return self.data.get("accepted_metrics") or {}

    def missing(self) -> list[str]:
        """What ``profile.json`` names as kept for the accepted model (``model/``, ``reference.npz``)
        but the sensor's folder no longer holds (deleted by hand)."""
        return [name for key, name, present in (("model", "model/", self.model_dir is not None),
                                                ("reference", "reference.npz", (self.path / "reference.npz").is_file()))
                if self.data.get(key) and not present]


_TEXT = (lambda v: isinstance(v, str), "a string")


def _aware_time(value) -> bool:
    """Whether ``value`` is an ISO 8601 time with its UTC offset (as ``register`` writes them)."""
    try:
        return isinstance(value, str) and datetime.fromisoformat(value).tzinfo is not None
    except ValueError:
        return False


#: A registration's time, which orders the history (a time without its offset cannot be compared).
_TIME = (_aware_time, "an ISO 8601 time with its UTC offset")
_ERROR = (lambda v: v is None or (real_number(v) and v >= 0), "a number >= 0 or null")
#: Held-out metrics: (check, what it must be); NaN / inf are written as null.
_METRICS = {"abs_rel": _ERROR, "rmse": _ERROR,
            "a1": (lambda v: v is None or (real_number(v) and 0 <= v <= 1), "a number from 0 to 1 or null")}
#: Fields of a profile (all optional but 'history') and of each history entry: (check, what it must be).
_PROFILE_FIELDS = {
    "serial": _TEXT,
    "status": (lambda v: v in ("accepted", "rejected"), "'accepted' or 'rejected'"),
    "intrinsics": (lambda v: v is None or (isinstance(v, dict) and all(
        isinstance(x, list) and all(map(real_number, x)) if k == "distortion" else real_number(x) for k, x in v.items())),
                   "an object of finite numbers (a list of them for 'distortion') or null"),
    "camera_in_tcp": (lambda v: v is None or real_numbers(v, 6),
                      "6 finite numbers or null"),
    "simulated": (lambda v: isinstance(v, bool), "true or false"),
    "last_commissioned": _TIME,
    "last_reason": _TEXT,
    "accepted_at": _TIME,
    "accepted_metrics": (lambda v: v is None or isinstance(v, dict), "an object of metrics or null"),
    "model": _TEXT,
    "model_source": _TEXT,
    "reference": _TEXT,
}
_HISTORY_FIELDS = {
    "time": _TIME,
    "run_dir": _TEXT,
    "accepted": (lambda v: isinstance(v, bool), "true or false"),
    "reason": _TEXT,
    **_METRICS,
}
_REQUIRED_HISTORY_FIELDS = ("time", "run_dir", "accepted")


def check_profile(profile, path: Path) -> None:
    """Raise InputError naming ``path`` (a ``profile.json``) and the first field of ``profile`` that
    is missing or of the wrong type (what ``bubble sensors`` and ``register`` read)."""

    def bad(field: str, what: str, value) -> InputError:
        return InputError(f"sensor registry profile {path} is corrupt: '{field}' must be {what}, got {shown_json(value)}")

    if not isinstance(profile, dict):
        raise InputError(f"sensor registry profile {path} is corrupt: it must hold a JSON object, got {shown_json(profile)}")
    if "history" not in profile:
        raise InputError(f"sensor registry profile {path} is corrupt: it has no 'history' of commissionings")
    for field, (ok, what) in _PROFILE_FIELDS.items():
        if field in profile and not ok(profile[field]):
            raise bad(field, what, profile[field])
    if profile.get("serial", path.parent.name) != path.parent.name:
        raise bad("serial", f"its folder's name {path.parent.name!r}", profile["serial"])
    for key, (ok, what) in _METRICS.items():
        value = (profile.get("accepted_metrics") or {}).get(key)
        if not ok(value):
            raise bad(f"accepted_metrics.{key}", what, value)
    history = profile["history"]
    if not isinstance(history, list):
        raise bad("history", "a list of commissionings", history)
    for i, entry in enumerate(history):
        if not isinstance(entry, dict):
            raise bad(f"history[{i}]", "an object", entry)
        for field in _REQUIRED_HISTORY_FIELDS:
            if field not in entry:
                raise InputError(f"sensor registry profile {path} is corrupt: 'history[{i}]' has no '{field}'")
        for field, (ok, what) in _HISTORY_FIELDS.items():
            if field in entry and not ok(entry[field]):
                raise bad(f"history[{i}].{field}", what, entry[field])


def _store_accepted(sdir: Path, model_dir, reference: dict[str, np.ndarray] | None) -> None:
    """Put an accepted commissioning's model (a copy of ``model_dir``) and ``reference`` arrays
    (``reference.npz``) into the sensor directory ``sdir``. Both are staged beside their places
    first, so a failure (a full disk) leaves the earlier ones whole; then each is swapped in by
    renames, so a reader finds the old one or the new one, never a half-written one."""
    model, staging, old = sdir / "model", sdir / "model.new", sdir / "model.old"
    ref, ref_tmp = sdir / "reference.npz", sdir / "reference.npz.tmp"
    for leftover in (staging, old):  # of a registration that died midway
        shutil.rmtree(leftover, ignore_errors=True)
    try:
        if model_dir is not None:
            shutil.copytree(model_dir, staging)
        if reference is not None:
            with ref_tmp.open("wb") as f:
                np.savez_compressed(f, **reference)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        ref_tmp.unlink(missing_ok=True)
        raise
    if model_dir is not None:
        if model.exists():
            os.replace(model, old)
        os.replace(staging, model)
        shutil.rmtree(old, ignore_errors=True)
    if reference is not None:
        ref_tmp.replace(ref)


@dataclass
class RegistryListing:
    """What ``SensorRegistry.survey`` found: the readable profiles, sorted by serial, and one message
    per entry whose ``profile.json`` is damaged."""

    profiles: list[SensorProfile]
    unreadable: list[str]

    def problem(self) -> str | None:
        """One line on the damaged entries (the first one's message), None when there are none."""
        if not self.unreadable:
            return None
        more = len(self.unreadable) - 1
        return self.unreadable[0] + (f" (and {more} more damaged entr{'y' if more == 1 else 'ies'})" if more else "")


class SensorRegistry:
    """The registry directory (created on first registration)."""

    def __init__(self, root: Path | str | None = None):
        self.root = Path(root).expanduser() if root is not None else default_registry_dir()
        try:
            for folder in (self.root, *self.root.parents):  # the registry, or the nearest folder it would be made in
                if folder.exists():
                    if not folder.is_dir():
                        raise InputError(f"sensor registry {self.root} is not a directory" if folder == self.root else
                                         f"sensor registry {self.root} cannot be made: {folder} is a file")
                    break
        except OSError as err:  # inside a folder this user cannot enter (was: a traceback, exit 1)
            raise InputError(f"cannot read the sensor registry {self.root}: {err.strerror}") from None

    def _sensor_dir(self, serial: str) -> Path:
        if not SENSOR_SERIAL_RE.fullmatch(serial or ""):
            raise InputError(f"sensor serial {serial!r} is not a valid registry name ({SENSOR_SERIAL_RULE})")
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
        entry_id: str | None = None,
    ) -> SensorProfile:
        """Record one commissioning of ``serial``; returns the updated profile.

        ``acceptance``: the ``acceptance.json`` content. ``model_dir`` and ``reference``
        (``depth_m`` (H,W) float32 m, ``ir`` (H,W) float32 and ``valid_count`` (H,W) arrays) are
        stored only when ``accepted``. ``entry_id``: the commissioning's id; a history entry with
        the same id (the same commissioning, registered again after its process was killed) is
        replaced, not repeated. Another process registering ``serial`` at the same time waits
        until this one is done, and the other way round.

        The history is kept in time order, and a commissioning older than one already registered
        (an old run folder registered in another registry, at its verdict's time) only joins the
        history: the status, the last acceptance and the kept model stay the newer ones' (was: the
        old run's model replaced the newer one a robot loads).
        """
        sdir = self._sensor_dir(serial)
        sdir.mkdir(parents=True, exist_ok=True)
        when = (when or datetime.now(timezone.utc)).astimezone(timezone.utc)  # a naive time: this computer's
        with output_folder_lock(sdir):
            prior = self._read_profile(sdir) if self._has_profile(sdir) else {"serial": serial, "history": []}
            metrics = {k: acceptance.get(k) for k in _METRICS if k in acceptance}
            entry = {
                "time": when.isoformat(timespec="seconds"),
                "run_dir": str(Path(run_dir).resolve()),
                "accepted": bool(accepted),
                "reason": reason,
                **metrics,
                **({"id": entry_id} if entry_id is not None else {}),
            }
            history = [e for e in prior.get("history", []) if entry_id is None or e.get("id") != entry_id]
            latest = all(datetime.fromisoformat(e["time"]) <= when for e in history)
            keeps_model = accepted and ("accepted_at" not in prior or datetime.fromisoformat(prior["accepted_at"]) <= when)
            profile = dict(prior)
            if latest:
                profile.update(serial=serial, status="accepted" if accepted else "rejected",
                               last_commissioned=entry["time"], last_reason=reason)
            if keeps_model or (latest and "accepted_at" not in prior):  # the camera calibration of the model kept
                profile.update(intrinsics=intrinsics, camera_in_tcp=camera_in_tcp, simulated=bool(simulated))
            if keeps_model:
                if model_dir is not None:
                    profile["model"] = "model"
                    profile["model_source"] = str(Path(model_dir).resolve())
                if reference is not None:
                    profile["reference"] = "reference.npz"
                profile["accepted_at"] = entry["time"]
                profile["accepted_metrics"] = metrics
            profile["history"] = sorted(history + [entry], key=lambda e: datetime.fromisoformat(e["time"]))
            check_profile(profile, sdir / PROFILE)  # what the next reader would refuse is not written
            if keeps_model:
                _store_accepted(sdir, model_dir, reference)
            if latest:
                write_json(sdir / "acceptance.json", acceptance)
            write_json(sdir / PROFILE, profile)
            return SensorProfile(serial, sdir, profile)

    def _read_profile(self, sdir: Path) -> dict:
        """The checked ``profile.json`` of the entry ``sdir``; ``InputError`` when the entry is not a
        directory holding a readable one."""
        path = sdir / PROFILE
        if not sdir.is_dir():
            raise InputError(f"sensor registry entry {sdir} is not a directory")
        if not path.is_file():
            raise InputError(f"sensor registry entry {sdir} is damaged: its {PROFILE} is not a regular file")
        try:
            profile = json.loads(path.read_text())
        except JSON_READ_ERRORS as err:
            raise InputError(f"sensor registry entry {sdir} is unreadable: {err}") from None
        check_profile(profile, path)
        return profile

    @staticmethod
    def _has_profile(sdir: Path) -> bool:
        """Whether ``sdir`` is an entry to read: something named ``profile.json`` in it (a folder without
        one is a first registration under way, or one that died before writing it: the next
        registration starts the profile afresh), or ``sdir`` itself is something other than a folder.
        ``InputError`` when it cannot be looked into (permissions)."""
        try:
            if not sdir.is_dir():
                return sdir.exists() or sdir.is_symlink()
            profile = sdir / PROFILE
            return profile.exists() or profile.is_symlink()
        except OSError as err:
            raise InputError(f"sensor registry entry {sdir} cannot be read: {err.strerror}") from None

    def check_entry(self, serial: str) -> None:
        """Raise ``InputError`` when ``register(serial)`` would fail on the existing entry (a damaged
        ``profile.json``): what a commissioning checks as soon as it knows the sensor's serial."""
        sdir = self._sensor_dir(serial)
        if self._has_profile(sdir):
            self._read_profile(sdir)

    def get(self, serial: str) -> SensorProfile:
        sdir = self._sensor_dir(serial)
        if not self._has_profile(sdir):
            raise InputError(f"sensor {serial!r} is not in the registry {self.root}")
        return SensorProfile(serial, sdir, self._read_profile(sdir))

    def survey(self) -> RegistryListing:
        """Every registered sensor, sorted by serial: the readable profiles, and the ``InputError``
        message of each entry named as a serial whose ``profile.json`` is damaged, or that is a file
        (one such entry hides no other)."""
        listing = RegistryListing([], [])
        try:
            if not self.root.is_dir():
                return listing
            entries = sorted(p for p in self.root.iterdir() if SENSOR_SERIAL_RE.fullmatch(p.name))  # others: no sensors
        except OSError as err:
            raise InputError(f"cannot read the sensor registry {self.root}: {err.strerror}") from None
        for sdir in entries:
            try:
                if self._has_profile(sdir):
                    listing.profiles.append(SensorProfile(sdir.name, sdir, self._read_profile(sdir)))
            except InputError as err:  # a damaged entry, or one that cannot be entered, hides no other
                listing.unreadable.append(str(err))
        return listing

    def reference(self, serial: str) -> dict[str, np.ndarray]:
        """The stored no-contact reference of an accepted sensor (the ``reference`` arrays of ``register``)."""
        path = self.get(serial).path / "reference.npz"
        if not path.is_file():
            raise InputError(f"sensor {serial!r} has no accepted reference in {self.root}")
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
