"""The one JSON writer of every command's results: strict JSON, and atomic."""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from collect.json_files import plain_json, write_json


@dataclass
class _Result:
    steps: int
    loss: float


def test_plain_json_converts_numpy_paths_dataclasses_and_non_finite_numbers():
    value = {1: np.float32(0.5), "a": np.arange(3, dtype=np.int64), "p": Path("/x/y"),
             "r": _Result(np.int64(3), float("nan")), "t": (np.inf, -np.inf, True, None)}
    assert plain_json(value) == {"1": 0.5, "a": [0, 1, 2], "p": "/x/y",
                                 "r": {"steps": 3, "loss": None}, "t": [None, None, True, None]}
    json.dumps(plain_json(value), allow_nan=False)
    with pytest.raises(TypeError, match="set"):
        plain_json({"s": {1, 2}})


def test_write_json_replaces_the_file_whole_or_leaves_it_untouched(tmp_path):
    path = tmp_path / "result.json"
    write_json(path, {"b": 2, "a": np.float64(1.5)}, sort_keys=True)
    assert path.read_text() == '{\n  "a": 1.5,\n  "b": 2\n}\n'
    with pytest.raises(TypeError):
        write_json(path, {"a": object()})
    assert json.loads(path.read_text()) == {"a": 1.5, "b": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]  # no temporary file left


def test_written_files_get_the_permissions_of_any_new_file(tmp_path):
    """Was 0600 (the temporary file's): a result or profile other users of the bench could not read."""
    write_json(tmp_path / "result.json", {"a": 1})
    (tmp_path / "plain.txt").write_text("x")
    assert (tmp_path / "result.json").stat().st_mode & 0o777 == (tmp_path / "plain.txt").stat().st_mode & 0o777
