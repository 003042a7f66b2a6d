"""``bubble tui``: the terminal UI that drives the bench (see ``calibrate.tui``)."""

from __future__ import annotations

import sys
from datetime import datetime
from pathlib import Path

from collect.cli import DEFAULT_OBJECTS_ARG
from collect.errors import InputError


def register(subparsers) -> None:
    from calibrate.commission_config import CommissionConfig

    p = subparsers.add_parser(
        "tui",
        help="terminal UI: bench state, live sensor view, commissioning with stop key",
        description="Terminal UI that drives the bench. Keys: c commission (asks first), s/space STOP the arm, "
        "1-4 tabs, r reload registry, q quit (stops the arm and closes the session first).",
    )
    p.add_argument("--sim", action="store_true", help="use the simulated bench (no hardware)")
    p.add_argument("--sensor", type=Path, metavar="SPEC.yaml", help="sensor spec of the simulated sensor")
    p.add_argument("--out", type=Path, metavar="RUN_DIR", help="run directory (default: runs/<date-time>)")
    p.add_argument("--objects", default=DEFAULT_OBJECTS_ARG, help=f"comma-separated objects to press (default {DEFAULT_OBJECTS_ARG})")
    p.add_argument("--poses-per-object", type=int, default=CommissionConfig.poses_per_object, metavar="K")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--finetune-minutes", type=float, default=CommissionConfig.finetune_minutes, metavar="M")
    p.add_argument("--total-minutes", type=float, default=CommissionConfig.total_minutes, metavar="M",
                   help="wall-time budget of the whole run; the fine-tune is shortened to fit it")
    p.add_argument("--base-model", type=Path, metavar="MODEL_DIR", help="model to fine-tune from")
    p.add_argument("--thresholds", type=Path, metavar="YAML", help="acceptance thresholds")
    p.add_argument("--registry", type=Path, metavar="DIR", help="sensor registry directory")
    p.add_argument(
        "--sim-fault", action="append", default=[], metavar="KIND@SECONDS", help="inject a fault (simulated bench)"
    )
    p.add_argument("--sim-speed", type=float, default=1.0, help="simulated clock speed-up (simulated bench)")
    p.set_defaults(func=run_tui)


def run_tui(args) -> int:
    from calibrate.commission_config import CommissionConfig, validate_config

    if not args.sim:
        raise InputError("the terminal UI drives the simulated bench only: add --sim (on real hardware, "
                         "commission with bubble commission --bench BENCH.yaml)")
    if args.sensor is not None and not args.sensor.is_file():
        raise InputError(f"sensor spec {args.sensor} does not exist")
    objects = tuple(name.strip() for name in args.objects.split(",") if name.strip())
    run_dir = args.out or Path("runs") / datetime.now().strftime("%Y%m%d-%H%M%S")
    config = CommissionConfig(
        run_dir=run_dir,
        simulated=args.sim,
        sensor_spec=args.sensor,
        thresholds=args.thresholds,
        registry_dir=args.registry,
        base_model=args.base_model,
        finetune_minutes=args.finetune_minutes,
        total_minutes=args.total_minutes,
        objects=objects,
        poses_per_object=args.poses_per_object,
        seed=args.seed,
        sim_faults=tuple(args.sim_fault),
        sim_speed=args.sim_speed,
    )
    validate_config(config)  # every setting `bubble commission` checks, before the UI starts
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise InputError("bubble tui needs an interactive terminal (use `bubble commission` in scripts)")

    from calibrate.tui.app import BenchApp

    BenchApp(config, tune_gc=True, warm_up_tabs=True).run()
    return 0
