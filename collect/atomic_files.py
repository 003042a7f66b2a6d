"""Output files written whole or not at all.

``replacing(path)`` hands the writer a temporary path beside ``path`` and, once the writer is done,
flushes it to disk and renames it over ``path``: a full disk, an error or a kill mid-write leaves the
earlier file (or none), never a cut-off one that opens like a complete result. ``remove_leftovers``
removes the temporary files that a killed writer (SIGKILL, a power cut) left in a folder.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: Name of a temporary file of ``replacing``: ``<target name>.<8 random characters>.tmp`` (mkstemp's).
_TEMP_NAME = re.compile(r".+\.[a-z0-9_]{8}\.tmp")
#: Bytes that name adds to the target's (``.<8 random characters>.tmp``): a target name longer than
#: the file system's limit less these cannot be written (``collect.output_files`` refuses it up front).
TEMP_NAME_EXTRA = len(".12345678.tmp")


def _new_file_mode() -> int:
    """The permissions ``open()`` gives a new file under this process's umask (read once, at import)."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


#: Permissions of any new file under this process's umask, given to the files whose writer alone
#: would make them 0600 (``mkstemp``'s temporary files, safetensors weights), which other users of
#: the bench could then not read.
NEW_FILE_MODE = _new_file_mode()


@contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """Yield a new empty temporary file in ``path``'s folder for the block to write ``path``'s content
    to; when the block ends without error the file is flushed to disk and renamed over ``path``,
    else it is removed and ``path`` stays as it was. An ``OSError`` raised naming the temporary file
    (a full disk) is re-raised naming ``path``."""
    path = Path(path)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    os.close(fd)
    tmp = Path(name)
    try:
        tmp.chmod(NEW_FILE_MODE)
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        if err.filename in (None, name):
            err.filename = str(path)
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path``, whole or not at all (``replacing``)."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def save_npz(path: str | Path, **arrays) -> None:
    """``np.savez_compressed`` of ``arrays`` to ``path``, whole or not at all (``replacing``; was: a
    full disk left a cut-off ``.npz``)."""
    import numpy as np

    with replacing(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)


def is_leftover(path: Path) -> bool:
    """Whether ``path`` is a temporary file of ``replacing`` (one a killed writer may have left)."""
    return bool(_TEMP_NAME.fullmatch(path.name)) and path.is_file() and not path.is_symlink()


def remove_leftovers(folder: str | Path) -> list[Path]:
    """Remove the temporary files of ``replacing`` that a killed writer left in ``folder`` and its
    subfolders; returns them. Call it only while no other process may be writing there."""
    removed = []
    for entry in Path(folder).rglob("*.tmp"):
        if is_leftover(entry):
            entry.unlink(missing_ok=True)
            removed.append(entry)
    return removed
