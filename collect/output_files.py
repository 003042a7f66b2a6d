"""Checks of the files a command is about to write, made before any work: a command never
overwrites a recording, a model or any other file that is not an earlier result of its own kind
or an empty placeholder (``is_placeholder``: what ``tempfile.mkstemp`` or ``touch`` leave),
never starts on a path with a name the file system cannot take (255 bytes on the usual ones; 242
for the name of a file written through a temporary file, ``collect.atomic_files.replacing``), and
two commands never write one output folder at once (``output_folder_lock``)."""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from collect.atomic_files import TEMP_NAME_EXTRA
from collect.errors import InputError
from collect.json_files import JSON_READ_ERRORS, write_json

#: Longest file name (one path component) in bytes; 255 on the usual Linux file systems.
_NAME_MAX = os.pathconf("/", "PC_NAME_MAX")
#: Longest name of a file written through ``collect.atomic_files.replacing`` (242 bytes on those file
#: systems): its temporary file's name is ``TEMP_NAME_EXTRA`` bytes longer.
_REPLACED_NAME_MAX = _NAME_MAX - TEMP_NAME_EXTRA
#: Top-level key of every ``--json`` result: the command that wrote it (``"bubble pose"``). A later run
#: of that command may replace the file; no other file, JSON or not, is ever overwritten by one.
WRITTEN_BY = "written_by"


def named_path(text: str) -> str:
    """argparse ``type`` of an option or argument that names a file or folder, to read or to write:
    refuses an empty name, which would otherwise name the current folder, or nothing."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty: name a file or folder")
    return text


def is_placeholder(path) -> bool:
    """Whether ``path`` is an empty regular file (``tempfile.mkstemp``'s, ``touch``'s), which an output
    may replace: it holds nothing to lose (was: refused as any other existing file)."""
    path = Path(path)
    return path.is_file() and not path.is_symlink() and path.stat().st_size == 0


def check_json_output(path, command: str) -> None:
    """Raise InputError unless ``path`` (a ``--json`` result of ``command``) can be written: it names
    a file, the folders on the way exist as folders or can be made (``write_json_result`` makes them;
    was: refused), and the path is new, a placeholder (``is_placeholder``) or holds an earlier result
    of the same command (which is replaced)."""
    path = Path(path)
    check_parent_dirs(path, replaced=True)
    if path.is_dir():
        raise InputError(f"cannot write {path}: it is a directory")
    if path.exists() and not is_placeholder(path) and _written_by(path) != command:
        raise InputError(f"{path} exists and is not an earlier `{command} --json` result; refusing to overwrite it")


#: Key of the PNG text chunk that names the command that wrote an image (``savefig(metadata=...)``).
PNG_WRITER_KEY = "Software"


def check_png_output(path, command: str) -> None:
    """Raise InputError when ``path`` exists and is not a PNG image that ``command`` wrote (its
    ``PNG_WRITER_KEY`` text is ``command``) nor a placeholder (``is_placeholder``): an earlier image
    of the same command is replaced, no other file (images of versions that did not mark them neither)."""
    path = Path(path)
    if path.exists() and not is_placeholder(path) and _png_written_by(path) != command:
        raise InputError(f"{path} exists and is not an earlier `{command}` image; refusing to overwrite it")


def remove_earlier_png(path, command: str) -> None:
    """Delete ``path`` if it is a PNG image that ``command`` wrote: an earlier run's image of which this
    run makes none, that would otherwise lie beside this run's images as if one of them."""
    path = Path(path)
    if path.is_file() and _png_written_by(path) == command:
        path.unlink()


def _png_written_by(path: Path) -> str | None:
    """The ``PNG_WRITER_KEY`` text of the PNG image ``path``; None for any other file, and for one that
    cannot be read (nothing then tells what wrote it)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return image.text.get(PNG_WRITER_KEY) if image.format == "PNG" else None
    except (UnidentifiedImageError, OSError):
        return None


def write_json_result(path, command: str, values: dict) -> None:
    """Write ``values`` (JSON data, see ``plain_json``) as ``command``'s ``--json`` result, marked
    with ``WRITTEN_BY`` first (``check_json_output`` checked ``path`` before the work), making the
    folders on the way."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {WRITTEN_BY: command, **values})


@contextmanager
def exclusive_lock(path, busy: InputError | None = None) -> Iterator[int]:
    """Hold ``path`` (a file or a folder, opened read-only; yields its descriptor) for the with-block,
    against every other process that takes this lock on it: an exclusive ``flock(2)``, which the
    kernel releases when the process ends, also when it is killed, and which adds no file.

    With ``busy``, a path held elsewhere raises ``busy`` at once; without, the call waits until the
    holder is done. Locks are per open file, not per process: a second lock of a path this process
    holds is refused (or waits forever). On a file system that cannot take the lock (NFS takes no
    exclusive lock on a file opened read-only) the with-block runs unlocked."""
    fd = os.open(path, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (fcntl.LOCK_NB if busy is not None else 0))
        except BlockingIOError:
            raise busy from None
        except OSError:  # no such locks on this file system: one writer at a time is then up to the user
            pass
        yield fd
    finally:
        os.close(fd)


def output_folder_lock(folder, holder: str | None = None):
    """``exclusive_lock`` on an output folder (an existing directory) for one writer at a time. With
    ``holder`` (the command that writes such a folder, e.g. ``"bubble train"``), a folder held
    elsewhere is refused at once with ``InputError``; without, the call waits until the holder is
    done (for writes of a second or so, like a registry entry)."""
    busy = None if holder is None else InputError(
        f"{folder} is being written by another {holder}; wait until it has finished, or choose another --out")
    return exclusive_lock(folder, busy)


def check_parent_dirs(path, *, replaced: bool = False) -> None:
    """Raise InputError when a name in ``path`` is too long (``_check_name_lengths``; ``replaced``:
    ``path`` is a file written through ``collect.atomic_files.replacing``), or a folder on the way to
    ``path`` (folders are created when missing) exists as a file, or the nearest existing one takes
    no new files."""
    path = Path(path)
    _check_name_lengths(path, replaced=replaced)
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"cannot write {path}: {parent} is a file, not a directory")
            _check_can_create_in(parent, path)
            return


def _check_name_lengths(path: Path, *, replaced: bool) -> None:
    """Raise InputError when a name in ``path`` is longer than the file system takes, ``_NAME_MAX``
    bytes, or, with ``replaced`` (``path`` is a file written through ``collect.atomic_files.replacing``),
    its last name is longer than ``_REPLACED_NAME_MAX`` bytes, which its temporary file could not have
    (checked before the work, which would otherwise fail only when its result is written)."""
    if any(len(os.fsencode(part)) > _NAME_MAX for part in path.parts):
        raise InputError(f"cannot write {path}: a name in this path is longer than the file system's {_NAME_MAX} bytes")
    if replaced and len(os.fsencode(path.name)) > _REPLACED_NAME_MAX:
        raise InputError(f"cannot write {path}: its file name is longer than {_REPLACED_NAME_MAX} bytes (the file "
                         f"system's {_NAME_MAX}, less the {TEMP_NAME_EXTRA} of the temporary file it is written "
                         "through)")


def _check_can_create_in(folder: Path, path: Path) -> None:
    """Raise InputError unless a file can be created in ``folder`` (on the way to ``path``): tried with
    a temporary file, since permission bits do not tell (root, read-only or virtual file systems)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise InputError(f"cannot write {path}: no file can be created in {folder} ({err.strerror})") from None


def _written_by(path: Path) -> str | None:
    """The ``WRITTEN_BY`` command of the JSON result in ``path``; None for any other file (a recording
    is rejected by its first bytes, unread)."""
    try:
        with path.open("rb") as f:
            if f.read(64).lstrip()[:1] != b"{":
                return None
        document = json.loads(path.read_text())
    except JSON_READ_ERRORS:
        return None
    return document.get(WRITTEN_BY)
