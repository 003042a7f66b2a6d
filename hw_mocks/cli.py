"""``bubble sim ...``: draw simulated sensors and preview the simulated bubble.

* ``bubble sim new-sensor --seed N [--defect leak|dead-pixels|no-dots] --out SPEC.yaml``
* ``bubble sim preview --sensor SPEC.yaml --object NAME|MESH [--press-mm D] --out PREVIEW.png``
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from collect.errors import InputError
from collect.output_files import named_path

#: Deepest press the preview accepts (mm), and no deeper than the sensor's dome is high (its travel: a
#: deeper press pushes the object into the housing; was 30 mm on any sensor, 8.7 kN on a 5 mm dome).
#: The membrane model's range (docs/simulator.md): at 15 mm the box bulges the membrane out 4.4 mm,
#: beyond the 4 mm the contact model looks out (``obstacle.REACH_OUT_M``), and at 30 mm the solver
#: stopped unconverged (fingers: 2.6 kN, +3000 hPa; was accepted).
MAX_PREVIEW_PRESS_MM = 12.0


def register(subparsers) -> None:
    sim = subparsers.add_parser("sim", help="simulated bubble: draw sensors, preview frames")
    # no dest: a missing subcommand reads "required: {new-sensor,preview}" (was: "required: sim_command")
    sim_sub = sim.add_subparsers(required=True, parser_class=type(sim))

    new = sim_sub.add_parser("new-sensor", help="draw a plausible new simulated sensor from a seed")
    new.add_argument("--seed", type=int, required=True, help="sensor seed (>= 0); same seed, same sensor")
    new.add_argument("--defect", choices=("leak", "dead-pixels", "no-dots"), help="make a faulty sensor")
    new.add_argument("--out", type=named_path, required=True, help="sensor spec YAML to write")
    new.set_defaults(func=_new_sensor)

    prev = sim_sub.add_parser("preview", help="render IR, ToF depth, true depth and depth error to a PNG")
    prev.add_argument("--sensor", type=named_path, required=True, help="sensor spec YAML")
    prev.add_argument("--object", required=True, help="mug, wine_glass, box, fingers or a mesh file (STL/OBJ/PLY)")
    prev.add_argument("--press-mm", type=float, default=5.0, help="press depth below first touch of the top (mm; default %(default)g)")
    prev.add_argument("--out", type=named_path, required=True, help="PNG to write")
    prev.set_defaults(func=_preview)


def _new_sensor(args: argparse.Namespace) -> int:
    from collect.output_files import check_parent_dirs, is_placeholder
    from hw_mocks.sensor_spec import draw_sensor

    spec = draw_sensor(args.seed, args.defect)
    out = Path(args.out)
    if out.is_dir():
        raise InputError(f"--out {out} is a directory; name the spec file to write, e.g. {out / 'sensor.yaml'}")
    # a spec describes the sensor a recording was made with: never replace one silently (a placeholder,
    # or the very spec this command writes, run again, is no other sensor's; was: refused too)
    if out.exists() and not is_placeholder(out) and not _holds_spec(out, spec):
        raise InputError(f"{out} already exists; choose another --out or delete it first")
    check_parent_dirs(out, replaced=True)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        spec.to_yaml(out)
    except OSError as err:
        raise InputError(f"cannot write {out}: {err.strerror or err}") from None
    print(f"sensor {spec.serial} -> {out}")
    return 0


def _holds_spec(path: Path, spec) -> bool:
    """Whether the file ``path`` holds ``spec`` (a ``SensorSpec``) as ``to_yaml`` writes it, byte for byte."""
    try:
        return path.is_file() and path.read_bytes() == spec.yaml_text().encode("utf-8")
    except OSError:
        return False


def _preview(args: argparse.Namespace) -> int:
    from hw_mocks.objects import BUILTIN_OBJECTS
    from hw_mocks.preview import render_preview
    from hw_mocks.sensor_spec import SensorSpec

    if not (0.0 <= args.press_mm <= MAX_PREVIEW_PRESS_MM):
        raise InputError(f"--press-mm must be within [0, {MAX_PREVIEW_PRESS_MM:g}] (the simulated membrane's range), "
                         f"got {args.press_mm:g}")
    out = Path(args.out)
    _check_preview_output(out)
    if args.object not in BUILTIN_OBJECTS and os.path.isdir(args.object):  # not Path: Path("") is "."
        raise InputError(f"--object {args.object} is a directory, not a mesh file (.stl, .obj, .ply)")
    spec = SensorSpec.from_yaml(args.sensor)
    if args.press_mm > (travel_mm := 1e3 * spec.dome_height_m):
        raise InputError(f"--press-mm {args.press_mm:g} is deeper than the sensor's dome is high ({travel_mm:.1f} mm, "
                         "its travel); press at most that")
    summary = render_preview(spec, args.object, args.press_mm / 1000.0, out)
    print(summary)
    return 0


def _check_preview_output(out: Path) -> None:
    """Raise InputError unless ``out`` can take the preview: a .png path, new or an earlier preview
    (``collect.output_files.check_png_output``)."""
    from collect.output_files import check_parent_dirs, check_png_output
    from hw_mocks.preview import PREVIEW_SOFTWARE

    if out.is_dir():
        raise InputError(f"--out {out} is a directory; name the PNG file to write, e.g. {out / 'preview.png'}")
    if out.suffix.lower() != ".png":
        raise InputError(f"--out {out}: the preview is a PNG image; name a .png file")
    check_png_output(out, PREVIEW_SOFTWARE)
    check_parent_dirs(out, replaced=True)
