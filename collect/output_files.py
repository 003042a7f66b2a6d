"""Checks of the files a command is about to write, made before any work: a command never
overwrites a recording, a model or any other file that is not an earlier result of its own kind."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from collect.errors import InputError


def check_json_output(path) -> None:
    """Raise InputError unless ``path`` (a ``--json`` result) can be written: its directory exists
    and is writable, and the path is new or holds an earlier JSON result (which is replaced)."""
    path = Path(path)
    parent = path.parent.resolve()
    if not parent.is_dir():
        raise InputError(f"cannot write {path}: directory {parent} does not exist")
    _check_can_create_in(parent, path)
    if path.is_dir():
        raise InputError(f"cannot write {path}: it is a directory")
    if path.exists() and not _holds_json(path):
        raise InputError(f"{path} exists and is not a JSON result; refusing to overwrite it")


def check_parent_dirs(path) -> None:
    """Raise InputError when a folder on the way to ``path`` (folders are created when missing)
    exists as a file, or the nearest existing one takes no new files."""
    path = Path(path)
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"cannot write {path}: {parent} is a file, not a directory")
            _check_can_create_in(parent, path)
            return


def _check_can_create_in(folder: Path, path: Path) -> None:
    """Raise InputError unless a file can be created in ``folder`` (on the way to ``path``): tried with
    a temporary file, since permission bits do not tell (root, read-only or virtual file systems)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise InputError(f"cannot write {path}: no file can be created in {folder} ({err.strerror})") from None


def _holds_json(path: Path) -> bool:
    """Whether ``path`` holds a JSON document (a recording is rejected by its first bytes, unread)."""
    try:
        with path.open("rb") as f:
            if f.read(64).lstrip()[:1] not in (b"{", b"["):
                return False
        json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return True
