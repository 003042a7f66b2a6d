"""A preview figure of the simulated bubble pressed on one object, for judging it by eye.

Five panels side by side with colour bars: IR amplitude, ToF depth (invalid in white), true
membrane depth, ToF depth error (ToF - true, valid pixels), indentation from rest with the
contact outline; the title gives the sensor, object,
press depth, bubble pressure and contact force.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from collect.atomic_files import replacing
from collect.errors import InputError
from collect.output_files import PNG_WRITER_KEY
from collect.session_format import DEPTH_UNIT_M
from hw_mocks.bubble_sim import BubbleSim
from hw_mocks.objects import fixture_plate, load_object
from hw_mocks.sensor_spec import SensorSpec


#: The ``Software`` text of every preview PNG: ``bubble sim preview --out`` replaces a PNG that has it
#: (an earlier preview) and no other file (``collect.output_files.check_png_output``).
PREVIEW_SOFTWARE = "bubble sim preview"


def press_pose(top_point: np.ndarray, press_m: float) -> np.ndarray:
    """Untilted TCP pose (6,) pressing ``press_m`` below first touch of the surface point ``top_point (3,)`` (base frame)."""
    return np.array([top_point[0], top_point[1], top_point[2] - press_m, np.pi, 0.0, 0.0])


def render_preview(spec: SensorSpec, object_name: str, press_m: float, out: Path, seed: int = 0) -> str:
    """Write the preview PNG to ``out``, marked as one (``PREVIEW_SOFTWARE``); returns a one-line summary."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obj = fixture_plate([load_object(object_name)])[0]
    sim = BubbleSim(spec, [obj], seed=seed)
    pose = press_pose(obj.top_point(), press_m)
    frame = sim.frame(pose, 0.0, np.random.default_rng(seed))
    state = frame.state
    rest_hpa = spec.rest_pressure_pa / 100.0
    force = float(np.linalg.norm(state.wrench[:3]))

    mask = sim.membrane_mask
    true_mm = np.where(mask, state.true_depth * 1e3, np.nan)
    tof_mm = np.where(frame.depth > 0, frame.depth * DEPTH_UNIT_M * 1e3, np.nan)
    err_mm = tof_mm - true_mm
    lo, hi = np.nanpercentile(true_mm, [0.5, 99.5])

    dent_mm = np.where(mask, (sim.rest_depth - state.true_depth) * 1e3, np.nan)
    fig, axes = plt.subplots(1, 5, figsize=(22, 4.2), constrained_layout=True)
    panels = [
        (frame.ir, "IR amplitude (counts)", "gray", None, None),
        (tof_mm, "ToF depth (mm), white = invalid", "viridis", lo, hi),
        (true_mm, "true membrane depth (mm)", "viridis", lo, hi),
        (err_mm, "ToF - true (mm)", "RdBu_r", -0.5, 0.5),
        (dent_mm, "indentation: rest - true (mm), cyan = contact", "magma", None, None),
    ]
    for ax, (img, title, cmap, vmin, vmax) in zip(axes, panels):
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        if img is dent_mm and state.contact.any():
            ax.contour(state.contact, levels=[0.5], colors="cyan", linewidths=0.6)
        ax.set_title(title, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, shrink=0.85)
    fig.suptitle(
        f"{spec.serial}  |  {obj.name} pressed {press_m * 1e3:.1f} mm  |  pressure {state.pressure_hpa:.1f} hPa "
        f"(+{state.pressure_hpa - rest_hpa:.2f})  |  force {force:.2f} N  |  dent {state.dent_volume_m3 * 1e6:.2f} cm3"
        f"  |  valid depth {np.mean(frame.depth[mask] > 0) * 100:.0f}% of membrane",
        fontsize=11,
        parse_math=False,  # the object's name is text: a mesh cup$^$.stl was read as math (a traceback)
    )
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with replacing(out) as tmp:
            fig.savefig(tmp, dpi=110, format="png", metadata={PNG_WRITER_KEY: PREVIEW_SOFTWARE})
    except OSError as err:
        raise InputError(f"cannot write {out}: {err.strerror or err}") from None
    finally:
        plt.close(fig)
    return (
        f"{out}: {obj.name} pressed {press_m * 1e3:.1f} mm, pressure {state.pressure_hpa:.2f} hPa, "
        f"force {force:.2f} N"
    )
