"""Acceptance checks of a commissioning run against versioned thresholds.

The thresholds live in ``calibrate/acceptance_thresholds.yaml`` (packaged). A lab tightens them
with its own YAML of the same ``version`` holding any subset of the checks; the other checks keep
the packaged values. Each evaluated check is a plain dict (the ``acceptance.json`` /
``Verdict.checks`` entry)::

    {"name": str, "value": float | None, "threshold": float | [lo, hi], "op": ">=" | "<=" | "in",
     "unit": str, "passed": bool, "verdict": "pass" | "fail" | "not run", "gate": bool, "reason": str}

``gate``: when a gate check fails, the steps after its own are not run (the run is rejected); the
``acceptance.json`` of a run that ended early lists their checks as ``not run`` (``not_run``).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

from collect.errors import InputError
from collect.numbers import real_number
from collect.yaml_files import read_yaml_file

#: Packaged thresholds, used when no ``--thresholds`` file is given.
DEFAULT_THRESHOLDS_PATH = Path(__file__).with_name("acceptance_thresholds.yaml")


@dataclass(frozen=True)
class Threshold:
    """Inclusive limits of one check; ``lo``/``hi`` are None when unbounded on that side."""

    name: str
    lo: float | None
    hi: float | None
    unit: str
    describe: str
    gate: bool  # a failure stops the run early (hardware checks before data collection)

    def limit(self) -> tuple[str, float | list[float]]:
        """``(op, threshold)`` as shown to the user: ``(">=", lo)``, ``("<=", hi)`` or ``("in", [lo, hi])``."""
        if self.lo is not None and self.hi is not None:
            return "in", [self.lo, self.hi]
        if self.lo is not None:
            return ">=", self.lo
        return "<=", self.hi


@dataclass(frozen=True)
class Thresholds:
    """The acceptance thresholds in force, by check name: the packaged file's, with those of
    ``--thresholds`` in place of the checks it names."""

    version: int
    checks: dict[str, Threshold]
    source: str  # the file(s) they were read from

    def __getitem__(self, name: str) -> Threshold:
        return self.checks[name]

    def limits_sha256(self) -> str:
        """SHA-256 (hex) of what judges a run: every check's name, limits and gate (not its wording)."""
        limits = sorted((t.name, t.lo, t.hi, t.gate) for t in self.checks.values())
        return hashlib.sha256(json.dumps(limits).encode()).hexdigest()


#: The keys a check of a thresholds file may hold.
CHECK_KEYS = ("min", "max", "unit", "gate", "describe")

_FRACTION = (0.0, 1.0, "a fraction")
#: Units not written after a value (a plain number reads as the fraction or ratio it is).
SILENT_UNITS = ("fraction", "ratio")


def unit_suffix(unit: str | None) -> str:
    """What follows a value of a check in ``unit``: " mm", or "" for none and for ``SILENT_UNITS``."""
    return f" {unit}" if unit and unit not in SILENT_UNITS else ""


#: The values the metric of each check can take: ``(lo, hi, what it is)``, inclusive, ``hi`` None
#: when unbounded. A limit outside them (``heldout_a1: {min: 5}``, ``leak_rate_hpa_per_min:
#: {max: -1}``) would reject every sensor, so the file is refused. Of the unit mix-ups these catch
#: a fraction given in percent and an absolute pressure given in Pa or kPa; a length in m for mm
#: is a valid (and strict) limit, which only the unit in the file's own text can warn of.
METRIC_RANGES: dict[str, tuple[float, float | None, str]] = {
    "leak_rate_hpa_per_min": (0.0, None, "a rate of pressure loss"),
    # hPa, absolute: 700 at 3000 m of altitude, plus the bubble's few tens of hPa of gauge pressure (was:
    # >= 0, and a range written in Pa or kPa, which rejects every sensor, accepted)
    "inflation_pressure_hpa": (500.0, 2000.0, "an absolute pressure in hPa"),
    "dead_pixels": (0.0, None, "a count of pixels"),
    "stuck_pixels": (0.0, None, "a count of pixels"),
    "valid_depth_coverage": _FRACTION,
    "dot_contrast": _FRACTION,  # 1 - dot/background IR of the dark printed dots
    "dot_count": (0.0, None, "a count of dots"),
    "poses_completed_fraction": _FRACTION,
    "frames_dropped_fraction": _FRACTION,
    "heldout_a1": _FRACTION,
    "heldout_abs_rel": (0.0, None, "a relative error"),
    "heldout_rmse_mm": (0.0, None, "an error"),
    "contact_rmse_mm": (0.0, None, "an error"),
    "truth_a1": _FRACTION,
    "pose_e_x_median_mm": (0.0, None, "a distance"),
    "pose_e_theta_median": (0.0, 1.0, "1 - |q1.q2| of unit quaternions"),
}


def _check_range(where: str, name: str, key: str, value: float) -> None:
    """``InputError`` unless limit ``key`` = ``value`` of check ``name`` is a value its metric can take."""
    if name not in METRIC_RANGES:
        return
    lo, hi, what = METRIC_RANGES[name]
    if value < lo or hi is not None and value > hi:
        span = f">= {lo:g}" if hi is None else f"in {lo:g}..{hi:g}"
        raise InputError(f"{where}: check {name!r}: {key} must be {span} ({name} is {what}), got {value!r}")


def _parse_checks(raw: object, where: str, base: dict[str, Threshold] | None) -> dict[str, Threshold]:
    if not isinstance(raw, dict) or not raw:
        raise InputError(f"{where}: 'checks' must be a non-empty mapping of check name -> limits")
    out = dict(base or {})
    for name, entry in raw.items():
        if base is not None and name not in base:
            raise InputError(f"{where}: unknown check {name!r} (known: {', '.join(sorted(base))})")
        if not isinstance(entry, dict):
            raise InputError(f"{where}: check {name!r} must be a mapping with min and/or max")
        unknown = sorted(str(key) for key in entry if key not in CHECK_KEYS)
        if unknown:  # a misspelt min or max would leave the packaged limit in force without a word
            raise InputError(f"{where}: check {name!r}: unknown key {unknown[0]!r} (known: {', '.join(CHECK_KEYS)})")
        prior = out.get(name)
        for key in ("min", "max"):
            if key in entry and entry[key] is None:  # `max: null` (was: the packaged limit dropped, a gate too)
                raise InputError(f"{where}: check {name!r}: {key} must be a finite number, got None")
        given = [key for key in ("min", "max") if key in entry]
        if prior is not None and len(given) == 1 and {"min": prior.lo, "max": prior.hi}[given[0]] is None:
            # a lone limit on the other side would turn a one-sided check into a range
            own = "max" if given[0] == "min" else "min"
            raise InputError(f"{where}: check {name!r} is a {'maximum' if own == 'max' else 'minimum'} check; "
                             f"a {given[0]} alone would add a second limit: give {own}, or both min and max")
        lo = entry.get("min", prior.lo if prior else None)
        hi = entry.get("max", prior.hi if prior else None)
        for key, val in (("min", lo), ("max", hi)):
            if val is not None and not real_number(val):
                raise InputError(f"{where}: check {name!r}: {key} must be a finite number, got {val!r}")
            if val is not None:
                _check_range(where, name, key, val)
        if lo is None and hi is None:
            raise InputError(f"{where}: check {name!r} needs min and/or max")
        if lo is not None and hi is not None and lo > hi:
            raise InputError(f"{where}: check {name!r}: min {lo} is above max {hi}")
        for key in ("unit", "describe"):
            if key in entry and not isinstance(entry[key], str):  # (was: a list's repr as the unit)
                raise InputError(f"{where}: check {name!r}: {key} must be text, got {entry[key]!r}")
        if prior is not None and entry.get("unit", prior.unit) != prior.unit:
            # the value is computed in the packaged unit: another would relabel it (0.149 mm shown as 0.149 m)
            raise InputError(f"{where}: check {name!r} is measured in {prior.unit or 'no unit'}; its unit cannot "
                             f"be changed (got {entry['unit']!r}): give its limits in {prior.unit or 'no unit'}")
        gate = entry.get("gate", prior.gate if prior else False)
        if not isinstance(gate, bool):  # text such as "false" would count as true
            raise InputError(f"{where}: check {name!r}: gate must be true or false, got {gate!r}")
        out[name] = Threshold(
            name=name,
            lo=None if lo is None else float(lo),
            hi=None if hi is None else float(hi),
            unit=str(entry.get("unit", prior.unit if prior else "")),
            describe=str(entry.get("describe", prior.describe if prior else "")),
            gate=gate,
        )
    return out


def _read_yaml(path: Path) -> dict:
    raw = read_yaml_file(path, "thresholds file")
    if not isinstance(raw, dict):
        raise InputError(f"thresholds file {path} must hold 'version' and 'checks'")
    unknown = sorted(str(key) for key in raw if key not in ("version", "checks"))
    if unknown:  # a misspelt block (`chekcs:`) would leave its limits unused without a word
        raise InputError(f"thresholds file {path}: unknown key {unknown[0]!r} (known: version, checks)")
    if "version" not in raw or "checks" not in raw:
        raise InputError(f"thresholds file {path} must hold 'version' and 'checks'")
    return raw


def load_thresholds(path: Path | None = None) -> Thresholds:
    """The packaged thresholds, overlaid with the checks of ``path`` when given.

    Raises ``InputError`` for an unreadable file, bad YAML, a different ``version``, an unknown
    check name or non-numeric / inconsistent limits.
    """
    base_raw = _read_yaml(DEFAULT_THRESHOLDS_PATH)
    version = int(base_raw["version"])
    checks = _parse_checks(base_raw["checks"], str(DEFAULT_THRESHOLDS_PATH), None)
    if path is None:
        return Thresholds(version, checks, str(DEFAULT_THRESHOLDS_PATH))
    raw = _read_yaml(Path(path))
    if isinstance(raw["version"], str):  # version: "1" in quotes is text
        raise InputError(f"thresholds file {path}: version must be the number {version} (without quotes or "
                         f"leading zeros), got the text {raw['version']!r}")
    if raw["version"] != version or isinstance(raw["version"], bool):
        raise InputError(f"thresholds file {path} has version {raw['version']!r}; this bubble expects version {version}")
    checks = _parse_checks(raw["checks"], str(path), checks)
    return Thresholds(version, checks, f"{DEFAULT_THRESHOLDS_PATH} + {path}")


def _fmt(value: float, limits: tuple = ()) -> str:
    """``value`` to 4 significant digits, or to as many more as it takes to read on the same side of each
    of ``limits`` as ``value`` is (was: only not as a limit itself, and a passing 1030.45 hPa read
    ``1030`` beside a minimum of 1030.4; before that a failed a1 of 0.94996 read 0.95 beside ``>= 0.95``)."""
    for digits in range(4, 17):
        text = f"{value:.{digits}g}"
        if reads_on_the_same_side(float(text), value, limits):
            return text
    return repr(value)


def reads_on_the_same_side(shown: float, value: float, limits: tuple) -> bool:
    """Whether ``shown`` (``value`` rounded for display) lies on the same side of each of ``limits``
    (None: no limit) as ``value`` does, or on the limit where ``value`` is."""
    return all((shown > x) == (value > x) and (shown < x) == (value < x) for x in limits if x is not None)


def check_limits(check: dict) -> tuple:
    """The limits of a check (an ``evaluate`` result): its threshold, or both ends of its range."""
    thr = check["threshold"]
    return tuple(thr) if isinstance(thr, (list, tuple)) else (thr,)


def limit_text(limit: float) -> str:
    """A check's limit as text, as written in its thresholds file (the shortest text that reads back
    as it: ``1030.5``, ``0.12345``, ``25``; was, in the TUI, 4 significant digits: ``1030`` for 1030.5)."""
    text = repr(float(limit))
    return text[:-2] if text.endswith(".0") else text


def check_value_text(check: dict) -> str:
    """The measured value of a check (an ``evaluate`` result) as text: 4 significant digits, more where
    those would round it onto its limit; '-' when it was not measured."""
    if check["value"] is None:
        return "-"
    return _fmt(check["value"], check_limits(check))


def evaluate(thresholds: Thresholds, name: str, value: float | None, note: str = "") -> dict:
    """One check of ``value`` against the threshold ``name``.

    ``value`` None or NaN fails ("not measured"). ``note`` is appended to the reason of a failing
    check (what its failure implies for the sensor); a passing check's reason has none.
    """
    th = thresholds[name]
    op, limit = th.limit()
    unit = unit_suffix(th.unit)
    measured = value is not None and math.isfinite(float(value))
    if not measured:
        passed, reason = False, f"{name} was not measured"
    else:
        value = float(value)
        low = th.lo is not None and value < th.lo
        high = th.hi is not None and value > th.hi
        passed = not (low or high)
        if passed:
            reason = f"{th.describe}: {_fmt(value, (th.lo, th.hi))}{unit} within limit"
        elif low:
            reason = f"{th.describe}: {_fmt(value, (th.lo,))}{unit} below minimum {limit_text(th.lo)}{unit}"
        else:
            reason = f"{th.describe}: {_fmt(value, (th.hi,))}{unit} above maximum {limit_text(th.hi)}{unit}"
    if note and not passed:  # was: on a pass too, "353 dots within limit (is the dot pattern printed?)"
        reason = f"{reason} ({note})"
    return {
        "name": name,
        "value": float(value) if measured else None,
        "threshold": limit,
        "op": op,
        "unit": th.unit,
        "passed": bool(passed),
        "verdict": "pass" if passed else "fail",
        "gate": th.gate,
        "reason": reason,
    }


#: The ``verdict`` of a check its run ended before (``not_run``).
NOT_RUN = "not run"


def not_run(thresholds: Thresholds, name: str) -> dict:
    """The check ``name`` of a run that ended before its step: no value, not passed, verdict "not run"
    (was: left out of ``acceptance.json``, which then held the checks of the steps that ran alone)."""
    th = thresholds[name]
    op, limit = th.limit()
    return {"name": name, "value": None, "threshold": limit, "op": op, "unit": th.unit, "passed": False,
            "verdict": NOT_RUN, "gate": th.gate, "reason": f"{th.describe}: not run, the run ended before it"}


def failed(checks: list[dict]) -> list[dict]:
    """The checks that did not pass."""
    return [c for c in checks if not c["passed"]]


def accepted(checks: list[dict]) -> bool:
    """A run is accepted when at least one check ran and all passed."""
    return bool(checks) and not failed(checks)


def _short(check: dict) -> str:
    """``name value (limit)``, e.g. ``heldout_a1 0.91 (needs >= 0.95)``."""
    if check["value"] is None:
        return f"{check['name']} not measured"
    thr = check["threshold"]
    limit = f"{thr[0]:g}..{thr[1]:g}" if check["op"] == "in" else f"{check['op']} {thr:g}"
    unit = unit_suffix(check.get("unit"))
    return f"{check['name']} {check_value_text(check)}{unit} (needs {limit}{unit})"


def rejection_reason(checks: list[dict], fault: str | None = None) -> str:
    """One line saying why a run was rejected ('' when accepted): the fault, then each failed check."""
    parts = []
    if fault:
        parts.append(f"hardware fault {fault}")
    parts += [_short(c) for c in failed(checks)]
    return "; ".join(parts)
