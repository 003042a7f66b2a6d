"""Command-line checks shared by the benchmark scripts: a bad value is refused by the parser, before any work
(argparse's usage and one error line, exit 2), and bad input the package finds later exits 2 with its one line."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Callable, NoReturn

from collect.errors import EXIT_BAD_INPUT, InputError


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


def positive_int(text: str) -> int:
    """``argparse`` type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
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


def run_main(main: Callable[[], int], name: str) -> NoReturn:
    """``sys.exit(main())``; an ``InputError`` exits ``EXIT_BAD_INPUT`` (2) with its line, as ``bubble`` does."""
    try:
        code = main()
    except InputError as err:
        print(f"{name}: {err}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    sys.exit(code)
