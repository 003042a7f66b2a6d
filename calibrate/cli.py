"""The ``bubble`` command line: one entry point, subcommands registered by each package.

Every package that adds subcommands has a ``cli`` module with ``register(subparsers)``; each
subcommand sets ``func(args) -> int`` (the exit code). Handlers import their heavy modules
(torch, h5py, textual) lazily so that ``bubble --help`` stays fast.

Errors: ``InputError`` prints one line ``bubble: error: ...`` and exits 2; ``HardwareFault``
prints ``bubble: fault: ...`` and exits 3; Ctrl-C exits 130, SIGTERM and SIGHUP end a command the
same way (``collect.stop_signals``) and exit 143 and 129; a closed stdout (``| head``) exits 141.
No tracebacks for any of them.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys

from collect.stop_signals import (INTERRUPTS, Terminated, exit_code, raise_interrupt, raise_pending_stop,
                                  stop_signals_handled)
from collect.errors import (
    EXIT_BAD_INPUT,
    EXIT_BROKEN_PIPE,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_REJECTED,
    HardwareFault,
    InputError,
    OneLineParser,
    os_error_exit,
)

#: Modules providing ``register(subparsers)``, in the order their commands are listed.
COMMAND_MODULES = (
    "hw_mocks.cli",
    "collect.cli",
    "trainer.cli",
    "calibrate.commission_cli",
    "calibrate.pose_cli",
    "calibrate.tui_cli",
)


#: What ``bubble --help`` says above and below the subcommands.
DESCRIPTION = (
    "Commission Soft-bubble visuotactile sensors on a UR bench or its simulated twin: record IR + "
    "depth, fine-tune a depth network, validate it, register the sensor."
)
EPILOG = (
    f"exit codes: {EXIT_OK} ok / accepted, {EXIT_REJECTED} rejected, {EXIT_BAD_INPUT} bad input, "
    f"{EXIT_FAULT} hardware fault, {EXIT_INTERRUPTED} Ctrl-C ({exit_code(signal.SIGTERM)} SIGTERM, "
    f"{exit_code(signal.SIGHUP)} SIGHUP), {EXIT_BROKEN_PIPE} output's reader gone (`| head`); "
    "`bubble COMMAND --help` for each command"
)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="bubble", description=DESCRIPTION, epilog=EPILOG)
    from importlib.metadata import PackageNotFoundError, version

    try:
        ver = version("bubble-bench")
    except PackageNotFoundError:
        ver = "unknown"
    parser.add_argument("--version", action="version", version=f"bubble {ver}")
    subparsers = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None, *, exits_after: bool = False) -> int:
    """Run the ``bubble`` command line ``argv`` (default: ``sys.argv[1:]``); returns the exit code.
    argparse's own exits (``--help``, a bad option) raise ``SystemExit`` as usual. ``exits_after``:
    the process exits with the code (``run``), and the stop signals stay ignored after the command."""
    try:
        args = build_parser().parse_args(argv)  # a Ctrl-C while it imports the commands: below, as any other
        with stop_signals_handled(raise_interrupt, INTERRUPTS, process_ends=True, exits_after=exits_after):
            code = int(args.func(args) or 0)
            if code == 0:  # a command that ends on a stop says so with its own code; one that did not see it
                raise_pending_stop()  # (a library swallowed its KeyboardInterrupt) ends as stopped all the same
            return code
    except InputError as err:
        print(f"bubble: error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except HardwareFault as err:
        print(f"bubble: fault: {err.kind}: {err}", file=sys.stderr)
        return EXIT_FAULT
    except Terminated as err:
        print(f"bubble: interrupted ({err.name})", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("bubble: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as err:  # (``| head``, a name too long, a full disk)
        code = os_error_exit(err, "bubble")
        if code is None:
            raise
        return code


def run() -> None:
    """The ``bubble`` executable: exit with ``main()``'s code, which a stop signal arriving as the
    process exits can no longer change."""
    sys.exit(main(exits_after=True))


if __name__ == "__main__":
    run()
