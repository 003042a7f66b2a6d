"""JSON results of every command: one conversion to plain JSON data and one atomic writer, so a
result, a profile or a model's metadata is never left half-written and never holds ``NaN``."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from collect.atomic_files import write_text
from collect.errors import InputError

#: What reading a JSON file that a user may have damaged can raise: OSError (the file system),
#: ValueError (not UTF-8, not JSON, or an int of more than 4300 digits) and RecursionError
#: (thousands of nested brackets).
JSON_READ_ERRORS = (OSError, ValueError, RecursionError)


def plain_json(value):
    """``value`` as strict JSON data: dataclasses -> dicts, numpy arrays -> lists, numpy scalars ->
    Python numbers, paths -> strings, tuples -> lists, dict keys -> strings, NaN / inf -> ``None``;
    ``TypeError`` for anything else that JSON cannot hold."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {str(k): plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain_json(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def shown_json(value, limit: int = 40) -> str:
    """``value`` (JSON data) as a JSON file holds it, on one line, cut to ``limit`` characters: for
    error messages about a file's field."""
    text = json.dumps(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def write_json(path: str | Path, value, *, sort_keys: bool = False) -> None:
    """Write ``plain_json(value)`` to ``path`` (indent 2, trailing newline) atomically
    (``collect.atomic_files.write_text``)."""
    write_text(path, json.dumps(plain_json(value), indent=2, sort_keys=sort_keys) + "\n")


def read_json_object(path: str | Path, fix: str) -> dict:
    """The JSON object that the file ``path`` holds; ``InputError`` naming it, and ``fix`` (what to do),
    when it cannot be read, is not JSON or holds another value."""
    try:
        data = json.loads(Path(path).read_bytes())  # json decodes the bytes (UTF-8, -16 or -32)
    except JSON_READ_ERRORS as err:
        raise InputError(f"{path} is unreadable ({err}); {fix}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path} does not hold a JSON object; {fix}")
    return data
