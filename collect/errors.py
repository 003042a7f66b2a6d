"""Exception types shared by every layer, and the exit codes the command line maps them to.

* ``InputError``: bad input from the user (missing/corrupt file, bad YAML, unknown object, ...).
  The command line prints its message as one line and exits with ``EXIT_BAD_INPUT`` (2).
* ``StopRequested``: the operator stopped the run (stop key, Ctrl-C): the arm stops at once and
  retracts, the recording is kept; not a fault.
* ``HardwareFault``: a device misbehaved (camera silent, serial garbage/unplug, protective stop,
  force limit). The run stops the arm, retracts, keeps what was recorded and exits with
  ``EXIT_FAULT`` (3); ``bubble commission`` turns it into a rejected run (exit 1).
* ``BubbleCommandError``: a ``bubble`` command that a tool ran in a subprocess failed.
"""

import argparse
import errno
import os
import sys

EXIT_OK = 0
EXIT_REJECTED = 1
EXIT_BAD_INPUT = 2
EXIT_FAULT = 3
EXIT_INTERRUPTED = 130
#: The reader of stdout went away (``bubble info S.h5 | head``): 128 + SIGPIPE, as a shell reports a
#: process that signal ended; not 1, which is a rejected sensor.
EXIT_BROKEN_PIPE = 141


class InputError(Exception):
    """Bad user input; ``str(err)`` is the one line shown to the user."""


#: Kind of the ``HardwareFault`` of the session recorder once it stopped writing (a full disk, the
#: file deleted): the host's fault, not a device's (``collect.session_writer``).
RECORDER_FAULT = "recorder"
#: Kind of the ``HardwareFault`` of a commissioning whose fine-tune could hardly train in its time (a
#: computer too slow or too busy for the budget): the host's too, judged neither way.
HOST_TOO_SLOW_FAULT = "host-too-slow"
#: Kind of the ``HardwareFault`` of a robot that shut its control program down because this computer
#: did not kick its watchdog in time (frozen or overloaded; ``collect.arm``): the host's too.
HOST_STALLED_FAULT = "host-stalled"
#: The faults of this computer, not of the sensor or the bench: a commissioning ends without a verdict.
HOST_FAULTS = (RECORDER_FAULT, HOST_TOO_SLOW_FAULT, HOST_STALLED_FAULT)
#: ``OSError.errno`` of a write that found no room: the disk full, or the user's quota spent.
DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


class HardwareFault(Exception):
    """A device fault detected by a driver.

    ``kind`` names the fault (``camera-stall``, ``serial-garbage``, ``serial-unplug``,
    ``protective-stop``, ``force-spike``, or a driver-specific name).
    """

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


class StopRequested(Exception):
    """The operator's stop (``Arm.stop_on`` event, or a run's stop event between steps)."""


class BubbleCommandError(RuntimeError):
    """A ``bubble`` command that a tool ran in a subprocess (``trainer.pretrain.BubbleCommands``, the
    benchmarks) failed: its last error line in the message; ``returncode``: its exit status (negative:
    killed by that signal), None when it never ended (stopped before it started, or killed as hung)."""

    def __init__(self, message: str, returncode: int | None = None) -> None:
        super().__init__(message)
        self.returncode = returncode


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line, ``<tool>: error: <message>``, with exit code
    ``EXIT_BAD_INPUT`` (argparse's own code; it would print the usage text first)."""

    tool = "bubble"

    def error(self, message: str):  # noqa: D401 - argparse API
        self.exit(EXIT_BAD_INPUT, f"{self.tool}: error: {message}\n")


def os_error_exit(err: OSError, tool: str) -> int | None:
    """The exit code of the command line ``tool`` that ended on ``err``, its one line printed; None
    for an error it does not explain (the caller re-raises it): the reader of stdout gone (``| head``:
    ``EXIT_BROKEN_PIPE``, nothing printed, stdout pointed at /dev/null so that the exit's flush does
    not fail), a name longer than the file system allows or a full disk (``EXIT_BAD_INPUT``)."""
    if isinstance(err, BrokenPipeError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    if err.errno == errno.ENAMETOOLONG:  # a path given to the command, read before any recording
        print(f"{tool}: error: {err.filename}: a name in this path is longer than the file system's limit",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    if err.errno in DISK_FULL_ERRNOS:
        print(f"{tool}: error: cannot write {err.filename or 'the output'}: {err.strerror}; free some space or "
              "write elsewhere", file=sys.stderr)
        return EXIT_BAD_INPUT
    return None
