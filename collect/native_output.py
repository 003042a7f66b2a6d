"""The console lines native driver libraries print while a device connects, held back.

ur_rtde prints ``connect: Connection refused`` (to stderr) and depthai logs ``[host] [error]
Searched, but no actual device found ...`` (to stdout) before each raises the error the tool
reports. A failure is reported as one line, so these lines are captured where they are written,
at file descriptors 1 and 2 (native code bypasses ``sys.stdout`` / ``sys.stderr``), and folded
into that line; after a connection that succeeded they are passed on unchanged. depthai's own
warning on import is held back either way (``collect.camera.import_depthai``).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator

#: spdlog's time stamp at the start of a depthai log line, e.g. ``[2026-11-24 00:41:29.417] ``.
_LOG_TIME = re.compile(r"^\[\d{4}-\d\d-\d\d [\d:.]+\]\s*")


@contextlib.contextmanager
def native_output_into(lines: list[str], pass_on: bool = True) -> Iterator[None]:
    """Capture what is written to file descriptors 1 and 2 during the block, by native code or
    Python alike. Its non-empty lines (log time stamps dropped) are appended to ``lines`` when
    the block ends; after a block that did not raise, and with ``pass_on``, the text is also
    written back to the descriptor it was written to."""
    streams = (sys.stdout, sys.stderr)
    for stream in streams:
        stream.flush()
    saved = [os.dup(fd) for fd in (1, 2)]
    with tempfile.TemporaryFile() as out_sink, tempfile.TemporaryFile() as err_sink:
        sinks = (out_sink, err_sink)
        for fd, sink in zip((1, 2), sinks):
            os.dup2(sink.fileno(), fd)
        raised = True
        try:
            yield
            raised = False
        finally:
            for stream in streams:
                stream.flush()
            for fd, copy in zip((1, 2), saved):
                os.dup2(copy, fd)
                os.close(copy)
            for stream, sink in zip(streams, sinks):
                sink.seek(0)
                text = sink.read().decode(errors="replace")
                lines.extend(_LOG_TIME.sub("", line.strip()) for line in text.splitlines() if line.strip())
                if text and pass_on and not raised:
                    stream.write(text)
                    stream.flush()


def folded(lines: list[str]) -> str:
    """`` (line; line)`` to append to a one-line error message, or ``""`` for no lines."""
    return f" ({'; '.join(lines)})" if lines else ""
