"""The simulated Soft-bubble: membrane physics, pressure, contact wrench, IR and ToF frames.

``BubbleSim(spec, objects, seed)`` holds one sensor and the bench objects it can touch. For a TCP
pose (base frame) and a time it solves the membrane (``solve``), then renders the camera images
(``render``). Physics runs on a physics grid of every second pixel that covers the whole rim
(``hw_mocks.membrane``), the result is interpolated to the full image and clamped against the
object there. Frames: see docs/architecture.md (TCP at the rest apex, +z out of the bubble;
camera placed by ``spec.camera_in_tcp``; depth is camera z-depth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from collect.errors import InputError
from hw_mocks.dome import Dome, RayGrid
from hw_mocks.dot_pattern import albedo_texture
from hw_mocks.ir_render import IrRenderer, surface_incidence
from hw_mocks.membrane import MembraneSolver
from hw_mocks.objects import BenchObject
from hw_mocks.obstacle import REACH_OUT_M, object_depth
from hw_mocks.sensor_spec import ATMOSPHERE_PA, SensorSpec
from hw_mocks.tof_render import TofRenderer
from collect.transforms import invert, pose_to_matrix

#: Physics grid spacing in image pixels.
PHYSICS_STEP = 2
#: Most cells the physics grid may have: the drawn sensors' hold 6-12 thousand; a spec whose focal length
#: and image size pass their own checks may still spread the rim over millions of pixels, which the
#: solver would take minutes per frame for.
MAX_PHYSICS_CELLS = 250_000
#: Least share of the image the membrane must cover at rest (the drawn sensors': 52-88 % over seeds 0-2000).
MIN_MEMBRANE_SHARE = 0.25


@dataclass
class MembraneState:
    """The membrane for one TCP pose and time.

    ``true_depth (H,W) float32 m`` camera z-depth of the membrane, 0 where the camera sees the
    housing; ``contact (H,W) bool``; ``pressure_hpa`` absolute; ``wrench (6,) float64``
    ``[Fx,Fy,Fz,Tx,Ty,Tz]`` N, N m: the object's force on the sensor and its torque about the
    TCP, in the base frame; ``dent_volume_m3`` volume pushed in by the object (>= 0);
    ``net_volume_change_m3`` change of the enclosed volume (dent offset by bulging);
    ``object_index`` index into the simulator's objects of the touched object (-1 none);
    ``material_flow (H,W,2) float32 px`` image motion (du, dv) of the membrane material seen at
    each pixel, relative to rest; ``sweeps`` solver iterations spent.
    """

    tcp_pose: np.ndarray
    t: float
    true_depth: np.ndarray
    contact: np.ndarray
    pressure_hpa: float
    wrench: np.ndarray
    dent_volume_m3: float
    net_volume_change_m3: float
    object_index: int
    material_flow: np.ndarray
    sweeps: int


@dataclass
class SimFrame:
    """One simulated camera frame: the membrane ``state`` and the images ``ir (H,W) uint16``
    amplitude and ``depth (H,W) uint16`` in ``collect.session_format.DEPTH_UNIT_M`` (0 = invalid)."""

    state: MembraneState
    ir: np.ndarray
    depth: np.ndarray


class BubbleSim:
    """One simulated sensor ``spec`` in front of the placed bench ``objects``.

    ``seed`` seeds the noise of ``frame`` calls that pass no generator.
    """

    def __init__(self, spec: SensorSpec, objects: list[BenchObject] | tuple = (), seed: int = 0):
        self.spec = spec
        self.objects = list(objects)
        self.dome = Dome(spec)
        self._rng = np.random.default_rng(seed)
        h, w = spec.height, spec.width

        # Physics grid covering the whole rim (it may extend beyond the image): its size, checked first.
        u_min, u_max, v_min, v_max = self.dome.rim_pixel_bounds()
        s = PHYSICS_STEP
        u0, v0 = math.floor(u_min) - 2 * s, math.floor(v_min) - 2 * s
        shape = (int(math.ceil((v_max - v0) / s)) + 3, int(math.ceil((u_max - u0) / s)) + 3)
        if shape[0] * shape[1] > MAX_PHYSICS_CELLS:
            raise InputError(f"sensor {spec.serial}: its camera (fx {spec.fx:g}, fy {spec.fy:g} px) sees the bubble's "
                             f"rim over {u_max - u_min:.0f} x {v_max - v_min:.0f} px, a physics grid of "
                             f"{shape[0] * shape[1]} cells (at most {MAX_PHYSICS_CELLS}); check fx and fy")

        # Full image grid.
        self.grid = RayGrid.build(spec, 0.0, 0.0, 1, (h, w))
        depth, mask = self.dome.rest_depth(self.grid)
        if mask.mean() < MIN_MEMBRANE_SHARE:  # was: rendered, a preview of NaN statistics and numpy's warnings
            raise InputError(f"sensor {spec.serial}: its camera sees the membrane over {100 * mask.mean():.0f} % of its "
                             f"image (at least {100 * MIN_MEMBRANE_SHARE:g} %); check camera_in_tcp, fx, fy, cx and cy")
        self.membrane_mask = mask
        self.rest_depth = np.where(mask, depth, 0.0).astype(np.float32)
        self._rest_depth64 = depth
        self.housing_depth = self.dome.rim_plane_depth(self.grid).astype(np.float32)

        # The physics grid itself.
        self.physics = RayGrid.build(spec, u0, v0, s, shape)
        d_phys, m_phys = self.dome.rest_depth(self.physics)
        self._d_phys = np.where(m_phys, d_phys, 0.0)
        #: the object depth (m) of a physics cell no object is in front of: beyond the membrane, and 1 m off it
        #: (was: 40 mm there too, where the rest depth is 0: interpolated across the rim, a false contact and
        #: a 10 mm dip at rest)
        self._no_object_depth = np.where(self._d_phys > 0, self._d_phys + 10 * REACH_OUT_M, 1.0)
        self.solver = MembraneSolver(
            self._d_phys,
            m_phys,
            spec.fx / s,
            spec.fy / s,
            spec.tension_n_per_m,
            spec.stretch_stiffness_pa_per_m,
            spec.gas_volume_m3,
            spec.rest_pressure_pa,
        )
        self._m_phys = self.solver.mask
        #: no membrane point is farther than this from the TCP (m), even pressed or bulging.
        self._reach_m = float(np.linalg.norm([spec.dome_semi_x_m, spec.dome_semi_y_m, spec.dome_height_m])) + 0.01
        self._n0_phys = self.dome.rest_normals(self.physics, np.where(m_phys, d_phys, 1.0))
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        self._map_x, self._map_y = self.physics.coords_of(uu, vv)
        self._pix_u, self._pix_v = uu.astype(np.float32), vv.astype(np.float32)

        self.texture = albedo_texture(spec, self.dome, self.grid, depth, mask)
        self.ir = IrRenderer(spec, self.grid.rays, self.housing_depth)
        self.tof = TofRenderer(spec, self.grid.rays, mask, self.housing_depth, self.rest_depth)
        self._rays32 = self.grid.rays.astype(np.float32)
        self._cache_key = None
        self._cache_state: MembraneState | None = None
        self._obstacle_key = None
        self._obstacle = None
        self._poses: list[np.ndarray | None] = [None, None]  # the last two solved poses

    # ---- physics ---------------------------------------------------------------------------------
    def gas_content(self, t: float) -> float:
        """``P V`` of the enclosed gas at time ``t`` s (Pa m^3): constant unless the bubble leaks."""
        s = self.solver
        k0 = s.rest_pressure * s.gas_volume
        leak_pa_s = self.spec.leak_hpa_per_s * 100.0
        k = k0 - leak_pa_s * max(float(t), 0.0) * (s.gas_volume + s.rest_pressure * s.unit_volume)
        k_min = ATMOSPHERE_PA * (s.gas_volume + (ATMOSPHERE_PA - s.rest_pressure) * s.unit_volume)
        return max(k, k_min)

    def _obstacles(self, tcp_pose: np.ndarray):
        """Object depth along the physics rays ``(rows,cols)`` m (inf = none) and the index of the
        nearest object per ray (-1 = none), for a TCP pose (cached per pose)."""
        key = tuple(np.round(tcp_pose, 12))
        if key == self._obstacle_key:
            return self._obstacle
        base_from_cam = pose_to_matrix(tcp_pose) @ self.dome.tcp_from_cam
        nearest = np.full(self.physics.shape, np.inf)
        which = np.full(self.physics.shape, -1, dtype=np.int16)
        tcp = np.asarray(tcp_pose[:3])
        for k, obj in enumerate(self.objects):
            lo, hi = obj.bounds_base()
            if np.linalg.norm(tcp - np.clip(tcp, lo, hi)) > self._reach_m:
                continue  # the object is out of the bubble's reach
            obj_from_cam = invert(obj.object_to_base()) @ base_from_cam
            d = object_depth(obj.heightmap, obj_from_cam, self.physics.rays, self._d_phys)
            closer = d < nearest
            nearest[closer] = d[closer]
            which[closer] = k
        nearest[~self._m_phys] = np.inf
        self._obstacle_key, self._obstacle = key, (nearest, which)
        return nearest, which

    def solve(self, tcp_pose, t: float = 0.0) -> MembraneState:
        """Membrane state for the TCP at ``tcp_pose (6,) [m, rotvec]`` (base frame) at time ``t`` s.
        Warm-started from the previous call; repeated calls with the same pose (and, for a leaking
        bubble, the same time) return the cached state."""
        pose = np.asarray(tcp_pose, dtype=np.float64).reshape(6)
        key = (tuple(np.round(pose, 12)), round(float(t), 9) if self.spec.leak_hpa_per_s > 0 else None)
        if key == self._cache_key:
            return self._cache_state
        depth_obj, which = self._obstacles(pose)
        psi = np.where(np.isfinite(depth_obj), depth_obj - self._d_phys, np.inf)
        sol = self.solver.solve(psi, self.gas_content(t), extrapolate=self._steady_motion(pose))
        self._poses = [self._poses[-1], pose]

        # Which object is touched: the one under most contact pixels.
        touched = which[sol.contact]
        touched = touched[touched >= 0]
        object_index = int(np.bincount(touched).argmax()) if len(touched) else -1

        wrench = self._wrench(pose, sol.u, sol.load_n)

        # Full image: interpolate the displacement, clamp against the interpolated object.
        u_full = cv2.remap(sol.u.astype(np.float32), self._map_x, self._map_y, cv2.INTER_LINEAR)
        membrane = self._rest_depth64 + u_full
        far = np.where(np.isfinite(depth_obj), depth_obj, self._no_object_depth).astype(np.float32)
        obj_full = cv2.remap(far, self._map_x, self._map_y, cv2.INTER_LINEAR, borderValue=1.0)
        contact = self.membrane_mask & (membrane >= obj_full - 1e-5)
        true_depth = np.where(self.membrane_mask, np.minimum(membrane, obj_full), 0.0).astype(np.float32)

        state = MembraneState(
            tcp_pose=pose,
            t=float(t),
            true_depth=true_depth,
            contact=contact,
            pressure_hpa=sol.pressure_pa / 100.0,
            wrench=wrench,
            dent_volume_m3=sol.dent_volume_m3,
            net_volume_change_m3=sol.net_volume_change_m3,
            object_index=object_index if contact.any() or sol.contact.any() else -1,
            material_flow=self._material_flow(sol.u),
            sweeps=sol.sweeps,
        )
        self._cache_key, self._cache_state = key, state
        return state

    def _steady_motion(self, pose: np.ndarray) -> bool:
        """Whether the TCP keeps moving as in the previous step (small, nearly equal steps), so the
        solver may extrapolate its warm start."""
        prev2, prev = self._poses
        if prev2 is None or prev is None:
            return False
        step, last = pose - prev, prev - prev2
        size = np.linalg.norm(step[:3]) + 0.01 * np.linalg.norm(step[3:])
        return 0 < size < 0.002 and np.linalg.norm(step - last) < 0.2 * size

    def _wrench(self, tcp_pose: np.ndarray, u: np.ndarray, load: np.ndarray) -> np.ndarray:
        """Object force on the sensor and its torque about the TCP, base frame ``(6,)``."""
        ii, jj = np.nonzero(load > 0)  # contact pixels are interior: neighbours exist
        if len(ii) == 0:
            return np.zeros(6)
        depth = self._d_phys + u
        rays = self.physics.rays

        def point(i, j):
            return rays[i, j] * depth[i, j][:, None]  # camera frame

        points = point(ii, jj)
        n = np.cross(point(ii, jj + 1) - point(ii, jj - 1), point(ii + 1, jj) - point(ii - 1, jj))
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
        n *= np.sign(np.sum(n * points, axis=1))[:, None]  # outward: away from the camera
        force_cam = -load[ii, jj][:, None] * n  # pushes the membrane into the bubble
        r_tc = self.dome.tcp_from_cam[:3, :3]
        f_tcp = force_cam @ r_tc.T
        p_tcp = self.dome.to_tcp(points)
        r_bt = pose_to_matrix(tcp_pose)[:3, :3]
        force = r_bt @ f_tcp.sum(axis=0)
        torque = r_bt @ np.cross(p_tcp, f_tcp).sum(axis=0)
        return np.concatenate([force, torque])

    def _material_flow(self, u: np.ndarray) -> np.ndarray:
        """Image motion ``(H,W,2) float32 px`` of the membrane material, relative to rest.

        Two parts: each material point moves along its rest normal to the new depth along its rest
        ray, and in-plane the membrane is drawn into dents: the extra area ``|grad u|^2 / 2`` of a
        dent comes from its surroundings (uniform strain), which gives the in-plane displacement
        ``-grad(phi)`` with ``lap(phi) = |grad u|^2/2 - mean`` and ``phi = 0`` at the rim.
        """
        if not u.any():
            return np.zeros((self.spec.height, self.spec.width, 2), dtype=np.float32)
        rays, n0, d0, m = self.physics.rays, self._n0_phys, self._d_phys, self._m_phys
        s = u / np.maximum(n0[..., 2], 0.3)
        x = rays * d0[..., None] + s[..., None] * n0
        z = np.maximum(x[..., 2], 1e-3)
        fx, fy = self.spec.fx / PHYSICS_STEP, self.spec.fy / PHYSICS_STEP
        hx, hy = np.where(m, d0, 1.0) / fx, np.where(m, d0, 1.0) / fy  # m per physics pixel
        gx, gy = np.gradient(u, axis=1) / hx, np.gradient(u, axis=0) / hy
        excess = np.where(m, 0.5 * (gx * gx + gy * gy), 0.0)
        area = self.solver.area
        excess = np.where(m, excess - (excess * area).sum() / area.sum(), 0.0)
        phi = self.solver.poisson(excess)
        drawn_x = -np.gradient(phi, axis=1) / hx  # m, in-plane material displacement
        drawn_y = -np.gradient(phi, axis=0) / hy
        flow_u = np.where(m, self.spec.fx * (x[..., 0] / z - rays[..., 0]) + drawn_x * self.spec.fx / d0.clip(1e-3), 0.0)
        flow_v = np.where(m, self.spec.fy * (x[..., 1] / z - rays[..., 1]) + drawn_y * self.spec.fy / d0.clip(1e-3), 0.0)
        fu = cv2.remap(flow_u.astype(np.float32), self._map_x, self._map_y, cv2.INTER_LINEAR)
        fv = cv2.remap(flow_v.astype(np.float32), self._map_x, self._map_y, cv2.INTER_LINEAR)
        return np.stack([fu, fv], axis=-1)

    # ---- rendering -------------------------------------------------------------------------------
    def render(self, state: MembraneState, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Camera images of a membrane state: ``(ir (H,W) uint16, depth (H,W) uint16)``; depth in
        ``collect.session_format.DEPTH_UNIT_M``, 0 = invalid. Noise drawn from ``rng``."""
        ir_clean, incidence = self.clean_amplitude(state)
        ir = self.ir.noisy(ir_clean, rng)
        depth = self.tof.render(state.true_depth, ir_clean, incidence, rng)
        return ir, depth

    def clean_amplitude(self, state: MembraneState) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free amplitude ``(H,W) float32`` and incidence cosines ``(H,W) float32``."""
        depth = np.where(self.membrane_mask, state.true_depth, self.housing_depth)
        incidence = surface_incidence(depth, self._rays32, self.spec.fx, self.spec.fy)
        return self.ir.clean(depth, self.membrane_albedo(state), incidence, self.membrane_mask), incidence

    def membrane_albedo(self, state: MembraneState) -> np.ndarray:
        """``(H,W) float32`` albedo seen at each pixel: the printed pattern moved by the material flow."""
        return cv2.remap(
            self.texture,
            self._pix_u - state.material_flow[..., 0],
            self._pix_v - state.material_flow[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )

    def frame(self, tcp_pose, t: float = 0.0, rng: np.random.Generator | None = None) -> SimFrame:
        """``solve`` + ``render`` (noise from ``rng``, or the simulator's own seeded generator)."""
        state = self.solve(tcp_pose, t)
        ir, depth = self.render(state, self._rng if rng is None else rng)
        return SimFrame(state, ir, depth)
