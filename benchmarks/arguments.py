"""Command-line checks shared by the benchmark scripts: a bad value is refused by the parser, before any work
(argparse's usage and one error line, exit 2), and bad input the package finds later exits 2 with its one line."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Callable, NoReturn

from collect.errors import EXIT_BAD_INPUT, BubbleCommandError, InputError


def int_list(text: str) -> list[int]:
    """``argparse`` type: comma-separated integers, at least one, each once (``"101,202"`` -> ``[101, 202]``)."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    try:
        values = [int(s) for s in items]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"expected one or more comma-separated integers, each once, got {text!r}")
    return values


def name_list(choices) -> Callable[[str], list[str]]:
    """``argparse`` type: comma-separated names among ``choices``, at least one, each once."""
    def parse(text: str) -> list[str]:
        names = [s.strip() for s in text.split(",") if s.strip()]
        unknown = [n for n in names if n not in choices]
        if unknown or not names or len(set(names)) != len(names):
            raise argparse.ArgumentTypeError(f"expected one or more of {', '.join(choices)} (comma-separated, each "
                                             f"once), got {text!r}")
        return names
    return parse


def _integer(text: str) -> int | None:
    """``text`` as an integer, None when it is not one."""
    try:
        return int(text)
    except ValueError:
        return None


def positive_int(text: str) -> int:
    """``argparse`` type: an integer >= 1."""
    value = _integer(text)
    if value is None or value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer of 1 or more, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """``argparse`` type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text!r}")
    return value


def sensor_seed(text: str) -> int:
    """``argparse`` type: a simulated sensor's seed, an integer within 0..``MAX_SEED``."""
    from hw_mocks.sensor_spec import MAX_SEED

    value = _integer(text)
    if value is None or not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected a sensor seed within 0..{MAX_SEED}, got {text!r}")
    return value


def sensor_seed_list(text: str) -> list[int]:
    """``argparse`` type: comma-separated sensor seeds (``int_list``), each within 0..``MAX_SEED``."""
    return [sensor_seed(str(value)) for value in int_list(text)]


def sim_speed(text: str) -> float:
    """``argparse`` type: the simulated clock's speed factor, within ``hw_mocks.sim_bench.SIM_SPEED_RANGE``."""
    from hw_mocks.sim_bench import check_sim_speed

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    try:
        check_sim_speed(value)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return value


def object_names(text: str) -> str:
    """``argparse`` type: comma-separated objects of the bench (built-in names or mesh files), at least
    one, each once, each loadable; returns them comma-separated, without blanks."""
    from collect.pose_planner import check_object_names

    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected one or more comma-separated objects, got {text!r}")
    try:
        check_object_names(names)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return ",".join(names)


def work_dir(text: str) -> Path:
    """``argparse`` type: a folder a benchmark keeps its files in: new (created with its missing parents)
    or an existing folder, not a file, nor under one."""
    from collect.output_files import check_parent_dirs

    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder")
    try:
        check_parent_dirs(path / "file")
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return path


def markdown_out(text: str) -> Path:
    """``argparse`` type: the markdown page a benchmark writes (``--out``): a ``.md`` file, new or an earlier
    page, which is replaced, in an existing folder (was: any path, a YAML or HDF5 file overwritten with exit
    0, a folder a traceback after the whole run)."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, not a markdown file")
    if path.suffix.lower() != ".md":
        raise argparse.ArgumentTypeError(f"{text} is not a markdown file (.md): refusing to replace it with a "
                                         "benchmark page")
    if not path.resolve().parent.is_dir():
        raise argparse.ArgumentTypeError(f"the folder of {text} does not exist")
    return path


def model_dir(text: str) -> str:
    """``argparse`` type: a model directory whose ``metadata.json`` loads, or ``base`` (the packaged base model)."""
    from trainer.cli import check_model_arg
    from trainer.model_dir import load_metadata

    try:
        check_model_arg(text, "the model")
        load_metadata(text)
    except InputError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def poses_per_object(text: str) -> int:
    """``argparse`` type: contact poses per object of a ``bubble collect``, 1..``MAX_POSES_PER_OBJECT``."""
    from collect.pose_planner import MAX_POSES_PER_OBJECT

    value = _integer(text)
    if value is None or not 1 <= value <= MAX_POSES_PER_OBJECT:
        raise argparse.ArgumentTypeError(f"expected poses per object within 1..{MAX_POSES_PER_OBJECT}, got {text!r}")
    return value


def run_main(main: Callable[[], int], name: str) -> NoReturn:
    """``sys.exit(main())``; an ``InputError`` exits ``EXIT_BAD_INPUT`` (2) with its line, as ``bubble`` does,
    and a ``bubble`` command that failed (``collect.errors.BubbleCommandError``) with its last line: exit 2
    when that command refused its input, else 1 (was: a traceback, exit 1)."""
    try:
        code = main()
    except InputError as err:
        print(f"{name}: {err}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    except BubbleCommandError as err:
        print(f"{name}: {err}", file=sys.stderr)
        code = EXIT_BAD_INPUT if err.returncode == EXIT_BAD_INPUT else 1
    sys.exit(code)
