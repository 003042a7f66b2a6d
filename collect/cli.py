"""``bubble collect`` (record a calibration session) and ``bubble info`` (summarize a session file)."""

from __future__ import annotations

import argparse
import os
import threading
from contextlib import ExitStack

from collect.bench import DEFAULT_OBJECTS
from collect.errors import InputError
from collect.output_files import named_path

#: ``--objects`` default of the commands that press objects: every object of the fixture plate.
DEFAULT_OBJECTS_ARG = ",".join(DEFAULT_OBJECTS)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "collect",
        help="press the bubble on objects in random poses and record IR + depth to HDF5",
        description="Press the sensor on the fixture-plate objects in K random poses each and record "
        "IR, depth, arm pose, wrench and pressure into one HDF5 session (docs/session_format.md).",
    )
    p.add_argument("--sim", action="store_true", help="use the simulated bench (default: the real 'ur' bench of --bench)")
    p.add_argument("--bench", type=named_path, metavar="BENCH.yaml", help="real bench settings (robot_ip, home_pose, serial_port, ...)")
    p.add_argument("--sensor", type=named_path, metavar="SPEC.yaml", help="simulated sensor spec (default: drawn from --seed)")
    p.add_argument("--objects", help=f"comma-separated built-in objects (default: {DEFAULT_OBJECTS_ARG})")
    p.add_argument("--object-mesh", nargs="+", action="extend", default=[], metavar="PATH",
                   help="mesh files (STL/OBJ/PLY, m, +z up) on the plate; alone, only the meshes are used")
    p.add_argument("--poses-per-object", type=int, default=8, metavar="K", help="contact poses per object (default 8)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="pose plan (and simulation) seed (default 0)")
    p.add_argument("--sim-fault", action="append", default=[], metavar="KIND@SECONDS",
                   help="inject a fault into the simulated bench at a simulated time (repeatable)")
    p.add_argument("--sim-speed", type=float, default=1.0, metavar="X",
                   help="simulated clock speed factor (default 1 = real time)")
    p.add_argument("--resume", action="store_true", help="append to an existing session, skipping completed poses")
    p.add_argument("--quiet", action="store_true", help="no live progress display")
    p.add_argument("--out", type=named_path, required=True, metavar="FILE.h5", help="session file to write")
    p.set_defaults(func=run_collect)

    p = subparsers.add_parser("info", help="summarize a recorded session file",
                              description="Print what a session holds: sensor, frames per object and phase, "
                              "duration, frame rate, dropped frames, storage sizes.")
    p.add_argument("file", type=named_path, metavar="FILE.h5", help="a session file (bubble collect's --out)")
    p.set_defaults(func=run_info)


def object_list(objects: str | None, meshes: list[str], default: str = DEFAULT_OBJECTS_ARG) -> tuple[str, ...]:
    """Object names / mesh paths from ``--objects`` and ``--object-mesh`` (meshes alone: only meshes;
    neither: ``default``, comma-separated)."""
    if objects is None:
        objects = "" if meshes else default
    names = tuple(n.strip() for n in objects.split(",") if n.strip())
    result = names + tuple(meshes)
    if not result:
        raise InputError("--objects is empty: name at least one object or give --object-mesh")
    return result


def check_mesh_files(meshes: list[str]) -> None:
    """Raise InputError unless every ``--object-mesh`` names an existing mesh file (STL/OBJ/PLY)."""
    from hw_mocks.objects import BUILTIN_OBJECTS, MESH_SUFFIXES

    for mesh in meshes:
        if mesh in BUILTIN_OBJECTS:  # a built-in object given here is pressed as usual
            continue
        if not mesh.strip():
            raise InputError("--object-mesh is empty: give the path of a mesh file (.stl, .obj, .ply)")
        if os.path.isdir(mesh):
            raise InputError(f"--object-mesh {mesh} is a directory, not a mesh file (.stl, .obj, .ply)")
        if not os.path.exists(mesh):
            raise InputError(f"mesh file not found: {mesh}")
        if os.path.splitext(mesh)[1].lower() not in MESH_SUFFIXES:
            raise InputError(f"--object-mesh {mesh} is not a mesh file: give an .stl, .obj or .ply file")


def check_sim_options(args: argparse.Namespace) -> None:
    """Raise InputError when an option of the simulated bench (``--sensor``, ``--sim-fault``,
    ``--sim-speed`` other than 1) is given without ``--sim``: the real bench would ignore it."""
    if not args.sim and (args.sensor is not None or args.sim_fault or args.sim_speed != 1.0):
        raise InputError("--sensor, --sim-fault and --sim-speed need --sim (they describe the simulated bench)")


def bench_config(args: argparse.Namespace):
    """The ``BenchConfig`` of the command line: 'sim' with --sim, else the real bench of --bench."""
    from collect.bench import BenchConfig

    check_mesh_files(args.object_mesh)
    if args.sim:
        objects = object_list(args.objects, args.object_mesh)
        if args.bench is not None:
            raise InputError("--bench describes real hardware; drop it or --sim")
        return BenchConfig.create("sim", objects=objects, sensor=args.sensor, seed=args.seed,
                                  faults=tuple(args.sim_fault), speed=args.sim_speed)
    check_sim_options(args)
    if args.bench is None:
        raise InputError("the real bench needs --bench BENCH.yaml (type: ur, robot_ip, home_pose, ...); or use --sim")
    config = BenchConfig.from_yaml(args.bench)
    config.objects = object_list(args.objects, args.object_mesh, default=",".join(config.objects))
    return config


def run_collect(args: argparse.Namespace) -> int:
    from collect.bench import open_bench
    from collect.collection import (open_collection_writer, plan_bench_collection, remaining_stops, run_collection,
                                    session_metadata)
    from collect.pose_planner import PlanSettings
    from collect.session_writer import check_free_space, check_output_path, resume_progress
    from collect.stop_signals import INTERRUPTS, raise_interrupt, stop_signals_deferred, stop_signals_handled

    check_output_path(args.out, args.resume)
    check_free_space(args.out)  # before the bench opens, like every check of the output
    settings = PlanSettings(poses_per_object=args.poses_per_object, seed=args.seed)
    config = bench_config(args)
    display = _ProgressDisplay(enabled=not args.quiet)
    with open_bench(config) as bench:
        plan = plan_bench_collection(bench, settings)
        if args.resume:  # read-only: a plan already complete leaves the file as it is
            progress = resume_progress(args.out, **session_metadata(bench, plan.objects),
                                       collection_plan=plan.describe())
            referenced = {oi for oi, o in enumerate(plan.objects) if o.name in progress.referenced_objects}
            if not remaining_stops(plan, progress.completed_pose_ids, referenced):
                closed = ""
                if not progress.closed_cleanly:  # cut off after its last pose: rewritten and closed, nothing added
                    open_collection_writer(args.out, bench, plan, resume=True).close()
                    closed = " (the file had not been closed: it is now)"
                print(f"{args.out}: the plan is already complete ({_count(len(plan.poses), 'pose')} on "
                      f"{_count(len(plan.objects), 'object')}); nothing to record{closed}")
                return 0
        stop, signalled = threading.Event(), []

        def on_signal(signum: int) -> None:
            signalled.append(signum)
            stop.set()  # the arm halts within a state sample even where the exception is lost (below)
            raise_interrupt(signum)

        with ExitStack() as files:
            with stop_signals_deferred():  # until the file is made (was: a Ctrl-C inside h5py's first writes
                # came out as a TypeError traceback, exit 1); delivered then, and the file closed
                writer = files.enter_context(open_collection_writer(args.out, bench, plan, resume=args.resume))
            with display, stop_signals_handled(on_signal, INTERRUPTS):
                result = run_collection(bench, plan, writer, display.update, stop)
            if signalled:  # its KeyboardInterrupt was lost: raised while a weakref callback ran, which Python
                # only prints ("Exception ignored in"; was: the Ctrl-C lost, the whole plan recorded, exit 0)
                raise_interrupt(signalled[0])
            frames = writer.n_frames
    skipped = f", {len(result.poses_without_contact)} without contact" if result.poses_without_contact else ""
    poses = _count(len(result.poses_done), "pose")
    print(f"recorded {result.frames} frames ({poses}{skipped}, {result.dropped} dropped) "
          f"in {result.duration_s:.1f} s of bench time; {args.out} holds {frames} frames")
    return 0


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


class _ProgressDisplay:
    """Live one-line status (rich) fed by ``run_collection``'s progress callback (any thread)."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self._live = None

    def __enter__(self):
        if self.enabled:
            from rich.console import Console
            from rich.live import Live

            self._live = Live("starting...", console=Console(stderr=True), refresh_per_second=8, transient=False)
            self._live.__enter__()
        return self

    def __exit__(self, *exc):
        if self._live is not None:
            self._live.__exit__(*exc)
            if not self._live.console.is_terminal:  # rich leaves its last frame unterminated in a file
                self._live.console.line()

    def update(self, *, object_name, pose_index, poses_per_object, phase, frames, force_n, pressure_hpa) -> None:
        if self._live is None:
            return
        where = progress_place(object_name, pose_index, poses_per_object)
        self._live.update(f"[bold]{where}[/] {phase:<8} frames {frames:>6}  force {force_n:5.1f} N  "
                          f"pressure {pressure_hpa:7.1f} hPa")


def progress_place(object_name: str, pose_index: int, poses_per_object: int) -> str:
    """Where a collection's progress is: ``mug pose 3/10``, ``mug reference`` (its no-contact
    frames, ``pose_index`` -1) or ``travel`` (between objects: no ``object_name``)."""
    if not object_name:
        return "travel"
    if pose_index < 0:
        return f"{object_name} reference"
    return f"{object_name} pose {pose_index + 1}/{poses_per_object}"


def run_info(args: argparse.Namespace) -> int:
    from collect.session_info import describe_session

    print(describe_session(args.file))
    return 0
