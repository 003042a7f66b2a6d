"""``bubble pose``: the downstream pose check (paper Sec. V) of a model on a session file."""

from __future__ import annotations

import os
from pathlib import Path

from collect.output_files import check_json_output, check_parent_dirs, check_png_output, named_path, write_json_result

#: Largest contact threshold (mm): presses dent the bubble by about 10 mm at most.
MAX_THRESHOLD_MM = 20.0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "pose",
        help="pose of the mug from predicted vs measured depth (the paper's downstream check)",
        description="Estimate the object's pose from the contact patch of every hold frame, once from the "
                    "model's predicted depth and once from the measured ToF depth, and compare them "
                    "(e_x = ||p1-p2|| mm at the shape's centre, e_theta = 1-|q1.q2|); simulated sessions are also compared "
                    "with the true pose.",
    )
    p.add_argument("--model", type=named_path, required=True, metavar="MODEL_DIR", help="model directory ('base' = the shipped base model)")
    p.add_argument("--data", type=named_path, required=True, metavar="S.h5", help="session file")
    p.add_argument("--object", default="mug", help="object to estimate (default: mug)")
    p.add_argument("--json", type=named_path, metavar="OUT.json", help="write the results (e_x_mm, e_theta, hz, per frame) here")
    p.add_argument("--plots", type=named_path, metavar="DIR", help="write error histograms (PNG) here")
    p.add_argument("--threshold-mm", type=float, default=1.5, help="contact: depth below the reference by more than this (mm; default %(default)s)")
    p.add_argument("--points", type=int, default=1500, help="points per contact patch (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of the prior's perturbation")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from calibrate.pose_check import PLOT_FILES, PLOTS_WRITER, run_pose_check
    from calibrate.pose_estimation import MIN_POINTS
    from collect.errors import InputError
    from trainer.cli import check_model_arg, print_sensor_note

    if not 0 < args.threshold_mm <= MAX_THRESHOLD_MM:
        raise InputError(f"--threshold-mm must be within (0, {MAX_THRESHOLD_MM:g}], got {args.threshold_mm:g}")
    if args.points < MIN_POINTS:  # was: 1, and a patch of fewer than MIN_POINTS was skipped as too few
        raise InputError(f"--points must be at least {MIN_POINTS} (a fit needs that many), got {args.points}")
    if args.seed < 0:
        raise InputError(f"--seed must be 0 or more, got {args.seed}")
    check_model_arg(args.model, "--model")
    if args.json is not None:
        check_json_output(args.json, "bubble pose")
    if args.plots:
        if os.path.exists(args.plots) and not os.path.isdir(args.plots):
            raise InputError(f"--plots {args.plots} is a file, not a directory")
        plots = [Path(args.plots) / name for name in PLOT_FILES]
        check_parent_dirs(plots[0])
        for png in plots:
            if png.is_dir():
                raise InputError(f"--plots {args.plots}: {png} is a directory; the histogram is written there")
            check_png_output(png, PLOTS_WRITER)  # was: any file of that name replaced
        if args.json is not None:  # the JSON and the histograms must not land on one another
            json_path = Path(args.json).resolve()
            if json_path in [p.resolve() for p in plots] or Path(args.plots).resolve() in (json_path, *json_path.parents):
                raise InputError(f"--json {args.json} lies where --plots {args.plots} writes its histograms; "
                                 f"give them separate places")
    result = run_pose_check(args.model, args.data, args.object.strip(), threshold_m=1e-3 * args.threshold_mm,
                            n_points=args.points, seed=args.seed, plots_dir=args.plots)
    if args.json is not None:  # before the console, which may be a pipe its reader closed (`| head`)
        write_json_result(args.json, "bubble pose", result.to_dict())
    print_sensor_note(args.model, result.sensors_not_trained_on)
    print(result.summary())
    return 0
