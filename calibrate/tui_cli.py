"""``bubble tui``: the terminal UI that drives the bench (see ``calibrate.tui``)."""

from __future__ import annotations

import os
import sys
from datetime import datetime
from pathlib import Path

from calibrate.commission_cli import add_run_options, run_config
from collect.stop_signals import exit_code, raise_pending_stop, stop_signals_handled
from collect.errors import InputError
from collect.output_files import named_path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "tui",
        help="terminal UI: bench state, live sensor view, commissioning with stop key",
        description="Terminal UI that drives the bench: the simulated one (--sim) or a real one (--bench "
        "BENCH.yaml, as bubble commission). Keys: c commission (asks first), s/space STOP the arm, "
        "1-4 tabs, r reload registry, q quit (stops the arm and closes the session first).",
    )
    p.add_argument("--out", type=named_path, metavar="RUN_DIR", help="run directory (default: runs/<date-time>)")
    add_run_options(p)
    p.set_defaults(func=run_tui)


def run_tui(args) -> int:
    from calibrate.commission_config import validate_config
    from hw_mocks.sensor_spec import SensorSpec

    if args.sensor is not None and args.sim:  # the flow loads it in its own process: its errors before the UI starts
        SensorSpec.from_yaml(args.sensor)
    config = run_config(args, args.out or Path("runs") / datetime.now().strftime("%Y%m%d-%H%M%S"))
    validate_config(config)  # every setting `bubble commission` checks, before the UI starts
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise InputError("bubble tui needs an interactive terminal (use `bubble commission` in scripts)")

    from calibrate.tui.app import BenchApp

    app = BenchApp(config, tune_gc=True, warm_up_tabs=True)
    received: list[int] = []

    def quit_app(signum: int) -> None:  # as the q key: stop the run and close its files, then leave
        received.append(signum)
        app.call_later(app.action_quit)

    raise_pending_stop()  # one that came while the imports above swallowed it (was: the UI opened all the same)
    with stop_signals_handled(quit_app):
        app.run()
    code = exit_code(received[0]) if received else (app.return_code or 0)  # a crashed app: non-zero
    if app.left_flow_running:  # left to stop by itself: exit without waiting for it (was: for ever, at exit)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code
