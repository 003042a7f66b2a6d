"""The specification of one (simulated) Soft-bubble sensor, as a YAML file.

A ``SensorSpec`` holds everything that differs from one manufactured sensor to the next:
ToF camera intrinsics, the camera pose inside the bubble, the dome shape, the membrane
stiffness, the inflation, the printed dot pattern, the IR emitter and the noise of the camera,
plus the parameters of manufacturing defects. ``draw_sensor(seed)`` draws a plausible new
sensor; the same seed always gives the same sensor.

Units: metres, seconds, pascals (hPa only where the name says so), radians; image sizes and
intrinsics in pixels; amplitudes in 16-bit ToF amplitude counts.

Geometry (see docs/architecture.md): the TCP frame has its origin at the apex of the membrane at
rest and +z pointing out of the bubble. The rest membrane is the elliptic paraboloid
``z = -dome_height_m * ((x/dome_semi_x_m)**2 + (y/dome_semi_y_m)**2)`` clamped at the rim
``z = -dome_height_m``. The camera (OpenCV frame) sits at ``camera_in_tcp`` in the TCP frame.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from collect.camera import MIN_FPS
from collect.errors import InputError
from collect.numbers import is_number
from collect.pressure_board import SENSOR_SERIAL_RE, SENSOR_SERIAL_RULE

#: Defects ``draw_sensor`` can give a sensor; commissioning must reject each.
DEFECTS = ("leak", "dead-pixels", "no-dots")
#: Largest ``draw_sensor`` seed (its serial stays short).
MAX_SEED = 2**32 - 1
#: How far the camera must sit behind the bubble's rim plane (m): the drawn sensors' sit 55-72 mm behind it.
CAMERA_BEHIND_RIM_MIN_M = 0.01
#: How far the camera may sit off the bubble's axis (m) and turn away from it (rad) in a spec.
CAMERA_OFFSET_MAX_M = 0.02
CAMERA_TURN_MAX_RAD = math.radians(20.0)
#: Field of view (degrees, across the image's width and height from ``fx``, ``fy``) a spec may give its
#: camera: the drawn sensors see 82-91 x 67-76 degrees. A focal length off by a factor of ten (a slipped
#: decimal point: 10 degrees) is refused here; it made a physics grid 100 times as large, and a
#: preview or a run that never came back.
FOV_RANGE_DEG = (30.0, 150.0)

ATMOSPHERE_PA = 101325.0


@dataclass
class SensorSpec:
    """One sensor. Every field is required in YAML; ranges are checked by ``validate``."""

    serial: str
    # ToF camera (pixels, frames per second).
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    fps: float
    #: camera frame in the TCP frame, [x, y, z, rx, ry, rz] m + rotation vector.
    camera_in_tcp: list[float]
    # Dome at rest (m): semi-axes of the elliptical rim and height of the apex above the rim.
    dome_semi_x_m: float
    dome_semi_y_m: float
    dome_height_m: float
    # Membrane mechanics (linearized about the inflated rest state).
    #: effective membrane tension for perturbations (N/m).
    tension_n_per_m: float
    #: curvature (stretching) stiffness of the curved dome: restoring pressure per metre of
    #: normal displacement (Pa/m); localizes dents over sqrt(tension/stiffness).
    stretch_stiffness_pa_per_m: float
    # Air.
    gauge_pressure_pa: float
    gas_volume_m3: float
    # Printed dot pattern (material coordinates on the dome).
    dot_seed: int
    #: fraction of the membrane area covered by dots (0 = no pattern).
    dot_coverage: float
    dot_radius_m: float
    membrane_albedo: float
    dot_albedo: float
    # IR emitter and ToF camera.
    #: amplitude of a white Lambertian surface at 93 mm, normal incidence, on the optical axis.
    emitter_amplitude: float
    vignetting_exponent: float
    read_noise: float
    #: shot noise variance per amplitude count.
    shot_noise_gain: float
    #: amplitude at and above which the ToF pixel saturates (depth invalid).
    saturation_amplitude: float
    #: amplitude below which the ToF depth is invalid (weak signal).
    min_amplitude: float
    #: depth noise (1 sigma, m) at ``emitter_amplitude``; grows as 1/amplitude.
    depth_noise_m: float
    #: systematic depth error: constant offset and a term growing with r^2 (r in normalized image coords).
    depth_bias_m: float
    depth_bias_radial_m: float
    #: half-angle of the valid ToF field of view around the optical axis (rad).
    valid_fov_rad: float
    #: smallest incidence cosine with a valid depth (grazing angles drop out).
    min_incidence_cos: float
    #: growth of the 3x3 depth spread over its rest value (m) above which flying pixels appear.
    flying_pixel_jump_m: float
    # Defects.
    leak_hpa_per_s: float = 0.0
    #: stuck pixels as [row, col]; they report ``dead_pixel_ir`` and ``dead_pixel_depth_m``.
    dead_pixels: list[list[int]] = field(default_factory=list)
    dead_pixel_ir: int = 0
    dead_pixel_depth_m: float = 0.0
    defect: str | None = None

    # ---- derived quantities -------------------------------------------------------------------
    def intrinsics(self) -> dict:
        """Pinhole intrinsics in pixels: ``dict(fx, fy, cx, cy, width, height)``."""
        return {
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "width": int(self.width),
            "height": int(self.height),
        }

    @property
    def rest_pressure_pa(self) -> float:
        """Absolute bubble pressure at rest (Pa)."""
        return ATMOSPHERE_PA + self.gauge_pressure_pa

    @property
    def dots(self) -> bool:
        """Whether the membrane carries a printed dot pattern."""
        return self.dot_coverage > 0.0

    # ---- (de)serialization --------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Plain-Python dict (YAML/JSON ready)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.generic):
                value = value.item()
            if f.name == "camera_in_tcp":
                value = [float(v) for v in value]
            if f.name == "dead_pixels":
                value = [[int(r), int(c)] for r, c in value]
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: dict, source: str = "sensor spec") -> "SensorSpec":
        """Build and validate a spec; raises ``InputError`` naming the bad field."""
        if not isinstance(data, dict):
            raise InputError(f"{source}: expected a mapping of sensor fields, got {type(data).__name__}")
        names = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(names), key=str)  # keys of several types: 1, null (was: a TypeError)
        if unknown:
            raise InputError(f"{source}: unknown field '{unknown[0]}'")
        kwargs = {}
        for name, f in names.items():
            if name not in data:
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    raise InputError(f"{source}: missing field '{name}'")
                continue
            kwargs[name] = _coerce(name, data[name], source)
        spec = cls(**kwargs)
        spec.validate(source)
        return spec

    @classmethod
    def from_yaml(cls, path: str | Path) -> "SensorSpec":
        """Read a spec; unreadable files, bad YAML, missing or out-of-range fields raise ``InputError``."""
        from collect.yaml_files import read_yaml_file

        return cls.from_dict(read_yaml_file(path, "sensor spec"), source=f"sensor spec {path}")

    def yaml_text(self) -> str:
        """The spec as YAML text (round-trips through ``from_yaml``)."""
        from collect.yaml_files import dump_yaml

        return dump_yaml(self.to_dict(), sort_keys=False, default_flow_style=None)

    def to_yaml(self, path: str | Path) -> None:
        """Write ``yaml_text`` to ``path`` (atomically: ``collect.atomic_files.write_text``)."""
        from collect.atomic_files import write_text

        write_text(path, self.yaml_text())

    # ---- validation ----------------------------------------------------------------------------
    def validate(self, source: str = "sensor spec") -> None:
        """Raise ``InputError`` naming the first field out of its plausible range."""
        for name, (lo, hi) in _RANGES.items():
            value = getattr(self, name)
            if not (math.isfinite(value) and lo <= value <= hi):
                raise InputError(f"{source}: field '{name}' = {value} is outside [{lo}, {hi}]")
        if not (isinstance(self.serial, str) and SENSOR_SERIAL_RE.fullmatch(self.serial)):
            raise InputError(f"{source}: field 'serial' must be {SENSOR_SERIAL_RULE}")
        if len(self.camera_in_tcp) != 6 or not all(math.isfinite(v) for v in self.camera_in_tcp):
            raise InputError(f"{source}: field 'camera_in_tcp' must be 6 finite numbers [x,y,z,rx,ry,rz]")
        x, y, z, *rotation = self.camera_in_tcp
        if not (-0.2 <= z <= -0.03):
            raise InputError(f"{source}: field 'camera_in_tcp' z = {z} m is outside [-0.2, -0.03]")
        if -z - self.dome_height_m < CAMERA_BEHIND_RIM_MIN_M:  # was: a camera inside the dome accepted (5 % of the
            # membrane with depth), one just behind the rim refused for its fx and fy (a physics grid too large)
            behind = -z - self.dome_height_m
            where = f"{1e3 * behind:.1f} mm behind" if behind >= 0 else f"{-1e3 * behind:.1f} mm in front of"
            raise InputError(f"{source}: field 'camera_in_tcp' z = {z:g} m puts the camera {where} the bubble's rim "
                             f"(dome_height_m {self.dome_height_m:g} m below the apex); it must sit at least "
                             f"{1e3 * CAMERA_BEHIND_RIM_MIN_M:g} mm behind it")
        if max(abs(x), abs(y)) > CAMERA_OFFSET_MAX_M:
            raise InputError(f"{source}: field 'camera_in_tcp' x, y = {x}, {y} m: the camera is more than "
                             f"{CAMERA_OFFSET_MAX_M} m off the bubble's axis")
        if (turn := math.hypot(*rotation)) > CAMERA_TURN_MAX_RAD:
            raise InputError(f"{source}: field 'camera_in_tcp' rotation of {turn:.3g} rad turns the "
                             f"camera more than {CAMERA_TURN_MAX_RAD:.3g} rad away from the dome")
        for axis, pixels, focal in (("fx", self.width, self.fx), ("fy", self.height, self.fy)):
            fov = math.degrees(2.0 * math.atan(pixels / (2.0 * focal)))
            if not FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]:
                raise InputError(f"{source}: field '{axis}' = {focal} px gives a field of view of {fov:.1f} degrees "
                                 f"over {pixels} px; a bubble's camera sees {FOV_RANGE_DEG[0]:g}-{FOV_RANGE_DEG[1]:g}")
        if not (0 <= self.cx < self.width and 0 <= self.cy < self.height):
            raise InputError(f"{source}: field 'cx'/'cy' principal point lies outside the image")
        for rc in self.dead_pixels:
            if len(rc) != 2 or not (0 <= rc[0] < self.height and 0 <= rc[1] < self.width):
                raise InputError(f"{source}: field 'dead_pixels' entry {rc} is not a [row, col] inside the image")
        if self.defect is not None and self.defect not in DEFECTS:
            raise InputError(f"{source}: field 'defect' = {self.defect!r} is not one of {', '.join(DEFECTS)}")
        if self.min_amplitude >= self.saturation_amplitude:
            raise InputError(f"{source}: field 'min_amplitude' must be below 'saturation_amplitude'")


#: Plausible ranges (inclusive) of the scalar fields; anything outside is a broken spec.
_RANGES = {
    "width": (16, 4096),
    "height": (16, 4096),
    "fx": (20.0, 5000.0),
    "fy": (20.0, 5000.0),
    "fps": (MIN_FPS, 240.0),  # fewer frames than two per stall timeout read as a stalled camera
    "dome_semi_x_m": (0.02, 0.2),
    "dome_semi_y_m": (0.02, 0.2),
    "dome_height_m": (0.005, 0.08),
    "tension_n_per_m": (1.0, 5000.0),
    "stretch_stiffness_pa_per_m": (0.0, 1e8),
    "gauge_pressure_pa": (100.0, 50000.0),
    "gas_volume_m3": (1e-5, 2e-3),
    "dot_coverage": (0.0, 0.6),
    "dot_radius_m": (1e-4, 5e-3),
    "membrane_albedo": (0.01, 1.0),
    "dot_albedo": (0.0, 1.0),
    "emitter_amplitude": (100.0, 65535.0),
    "vignetting_exponent": (0.0, 8.0),
    "read_noise": (0.0, 5000.0),
    "shot_noise_gain": (0.0, 100.0),
    "saturation_amplitude": (1000.0, 65535.0),
    "min_amplitude": (0.0, 65535.0),
    "depth_noise_m": (0.0, 0.01),
    "depth_bias_m": (-0.01, 0.01),
    "depth_bias_radial_m": (-0.01, 0.01),
    "valid_fov_rad": (0.1, 1.5),
    "min_incidence_cos": (0.0, 1.0),
    "flying_pixel_jump_m": (1e-5, 0.05),
    "leak_hpa_per_s": (0.0, 100.0),
    "dead_pixel_ir": (0, 65535),
    "dot_seed": (0, 2**32 - 1),
    "dead_pixel_depth_m": (0.0, 0.6),
}

_INT_FIELDS = {"width", "height", "dot_seed", "dead_pixel_ir"}
_STR_FIELDS = {"serial"}


def _coerce(name: str, value, source: str):
    """Convert one YAML value to the field's type, or raise ``InputError``."""
    try:
        if name in _STR_FIELDS:  # text only: YAML reads serial: 42 as a number (0042 is text: yaml_files)
            if not isinstance(value, str):  # the hint quotes no value: YAML's (34 for 0042) would register a
                # sensor under the wrong serial (was: "quote it (serial: '34')")
                raise InputError(f"{source}: field '{name}' must be text, but YAML read it as {value!r}; quote it "
                                 f"exactly as the file writes it ({name}: '...')")
            return value
        if name == "defect":
            return None if value is None else str(value)
        if name == "camera_in_tcp":
            if not all(map(is_number, value)):  # text in quotes is no number (was: '-0.093' read as -0.093)
                raise TypeError
            return [float(v) for v in value]
        if name == "dead_pixels":  # whole pixel indices (was: 1.7 taken as 1)
            if any(isinstance(v, bool) or int(v) != v for rc in value for v in rc):
                raise ValueError
            return [[int(r), int(c)] for r, c in value]
        if not is_number(value):  # a bool, or text: a number in quotes too (was: fx: '122.7' read as 122.7)
            raise TypeError
        if name in _INT_FIELDS:
            if float(value) != int(value):
                raise ValueError
            return int(value)
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{source}: field '{name}' has a bad value {value!r}") from None


def simulated_serial(seed: int, defect: str | None = None) -> str:
    """Serial number of the simulated sensor ``draw_sensor(seed, defect)`` (``SB-SIM-000042``)."""
    return f"SB-SIM-{int(seed):06d}" + ("" if defect is None else f"-{defect}")


def draw_sensor(seed: int, defect: str | None = None) -> SensorSpec:
    """Draw a plausible manufactured sensor from ``seed`` (deterministic).

    ``defect``: None, ``'leak'`` (loses 2-5 hPa/min), ``'dead-pixels'`` (a stuck cluster of
    30-80 pixels near the image centre) or ``'no-dots'`` (no printed pattern).
    """
    if defect is not None and defect not in DEFECTS:
        raise InputError(f"unknown defect {defect!r}; choose one of {', '.join(DEFECTS)}")
    if not 0 <= int(seed) <= MAX_SEED:
        raise InputError(f"sensor seed must be within 0..{MAX_SEED}, got {seed}")
    rng = np.random.default_rng([int(seed), 0xB0BB1E])

    def vary(nominal: float, rel: float) -> float:
        return float(nominal * (1.0 + rel * np.clip(rng.standard_normal(), -2.5, 2.5)))

    def jitter(sigma: float) -> float:
        return float(sigma * np.clip(rng.standard_normal(), -2.5, 2.5))

    width, height = 224, 172
    fx = vary(120.0, 0.03)
    apex_distance = vary(0.093, 0.02)
    spec = SensorSpec(
        serial=simulated_serial(seed, defect),
        width=width,
        height=height,
        fx=fx,
        fy=fx * (1.0 + jitter(0.004)),
        cx=(width - 1) / 2 + jitter(1.5),
        cy=(height - 1) / 2 + jitter(1.5),
        fps=45.0,
        camera_in_tcp=[
            jitter(0.0012),
            jitter(0.0012),
            -apex_distance,
            jitter(math.radians(1.2)),
            jitter(math.radians(1.2)),
            jitter(math.radians(1.5)),
        ],
        dome_semi_x_m=vary(0.060, 0.025),
        dome_semi_y_m=vary(0.040, 0.025),
        dome_height_m=vary(0.030, 0.05),
        tension_n_per_m=vary(190.0, 0.10),
        stretch_stiffness_pa_per_m=vary(1.9e6, 0.10),
        gauge_pressure_pa=vary(5000.0, 0.08),
        gas_volume_m3=vary(140e-6, 0.06),
        dot_seed=int(rng.integers(0, 2**31 - 1)),
        # drawn for every sensor, so that no-dots is the same sensor without its dots (was: another one)
        dot_coverage=float(rng.uniform(0.10, 0.20)) * (defect != "no-dots"),
        dot_radius_m=vary(0.0010, 0.12),
        membrane_albedo=vary(0.85, 0.04),
        dot_albedo=vary(0.10, 0.2),
        emitter_amplitude=vary(36000.0, 0.10),
        vignetting_exponent=vary(2.0, 0.15),
        read_noise=vary(40.0, 0.2),
        shot_noise_gain=vary(0.8, 0.2),
        saturation_amplitude=vary(56000.0, 0.03),
        min_amplitude=vary(2800.0, 0.10),
        depth_noise_m=vary(5e-5, 0.15),
        depth_bias_m=jitter(1.5e-4),
        depth_bias_radial_m=jitter(2e-4),
        valid_fov_rad=math.radians(vary(41.0, 0.03)),
        min_incidence_cos=vary(0.25, 0.1),
        flying_pixel_jump_m=vary(0.00025, 0.1),
        defect=defect,
    )
    if defect == "leak":
        spec.leak_hpa_per_s = float(rng.uniform(2.0, 5.0) / 60.0)
    if defect == "dead-pixels":
        spec.dead_pixels = _dead_cluster(rng, width, height)
        spec.dead_pixel_ir = int(rng.choice([0, 65535]))
        spec.dead_pixel_depth_m = float(rng.uniform(0.02, 0.06))
    spec.validate("drawn sensor")
    return spec


def _dead_cluster(rng: np.random.Generator, width: int, height: int) -> list[list[int]]:
    """A compact random cluster of 30-80 pixels near the image centre, as [row, col] pairs."""
    n = int(rng.integers(30, 81))
    r0 = int(height / 2 + rng.uniform(-0.25, 0.25) * height)
    c0 = int(width / 2 + rng.uniform(-0.25, 0.25) * width)
    cells = [(r0, c0)]
    while len(cells) < n:  # random growth from the seed pixel
        r, c = cells[int(rng.integers(len(cells)))]
        dr, dc = [(0, 1), (1, 0), (0, -1), (-1, 0)][int(rng.integers(4))]
        cell = (min(max(r + dr, 0), height - 1), min(max(c + dc, 0), width - 1))
        if cell not in cells:
            cells.append(cell)
    return sorted([list(rc) for rc in cells])
