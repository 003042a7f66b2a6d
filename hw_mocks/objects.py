"""Bench objects: the built-in test objects and user meshes, mounted on the fixture plate.

Object frame: metres, +z up; the fixture holds the object's origin, and the object rests on the plate
top by its lowest point (a built-in's origin is on the plate top, below the object). The arm presses
the bubble onto an object from above (along base -z), anywhere on its upper surface.

Built-ins (after the paper's objects; each lies in a cradle so that its upper surface is the
interesting one):

* ``mug``: 82 mm diameter, 95 mm long hollow mug lying on its side, axis along object x, handle
  pointing down into the cradle. Primitive: cylinder.
* ``wine_glass``: 190 mm wine glass lying on its side, axis along object x (bowl at +x).
* ``box``: 70 x 50 x 40 mm box, flat on the plate. Primitive: box.
* ``fingers``: a flat hand, palm down: a 50 x 82 x 16 mm palm and four 17 mm thick rounded fingers along +x.

A mesh file (STL/OBJ/PLY, metres, +z up) must be watertight, and its origin must lie within its
bounding box (within ``MESH_PLACEMENT_TOL_M``): a part exported standing on its origin, or around its
centre as ``trimesh.creation`` makes them (was: refused), rests on the plate all the same. Its
duplicate and zero-area triangles are dropped and, when it is inside out, its faces turned over.
"""

from __future__ import annotations

import functools
import hashlib
import unicodedata
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import trimesh

from collect.errors import InputError
from hw_mocks.heightmap import Heightmap
from collect.transforms import pose_to_matrix

BUILTIN_OBJECTS = ("mug", "wine_glass", "box", "fingers")
MESH_SUFFIXES = (".stl", ".obj", ".ply")

#: The fixture plate: objects in a row along base y at this x, plate top at z = 0 (base frame, m).
PLATE_X = 0.45
PLATE_Z = 0.0
#: Free space between neighbouring objects' footprints (m): more than half the bubble's long
#: axis (60 mm) plus tilt, so a bubble pressing one object never touches its neighbour.
PLATE_GAP = 0.09
#: Length of the fixture plate along base y (m): 0.5 m either side of the arm's x axis, within a
#: UR5e's 0.85 m reach at x = ``PLATE_X``. The four built-ins take 0.56 m of it.
PLATE_LENGTH_M = 1.0
#: Largest and smallest extent (m) of a mesh file's object; the lower bound allows float32's rounding
#: of an STL's coordinates (a 5 mm part reads as 4.9999997 mm).
MESH_SIZE_RANGE_M = (0.005 * (1 - 1e-6), 0.5)
#: How far (m) a mesh file's origin may lie outside its bounding box.
MESH_PLACEMENT_TOL_M = 1e-3


@dataclass
class BenchObject:
    """One object on the bench.

    ``mesh``: ``trimesh.Trimesh`` in the object frame (m, +z up, origin held by the fixture).
    ``fixture_pose``: ``(6,) [m, rotvec]`` object frame in the base frame.
    ``primitive``: graspable shape in the object frame for the pose check, or None, e.g.
    ``{"type": "cylinder", "radius": m, "height": m, "center": [x,y,z] m, "axis": [ax,ay,az]}``.
    """

    name: str
    mesh: trimesh.Trimesh
    fixture_pose: np.ndarray = field(default_factory=lambda: np.zeros(6))
    primitive: dict | None = None

    @functools.cached_property
    def mesh_sha256(self) -> str:
        """SHA-256 (hex) of the float64 vertices followed by the int64 faces, C order."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.mesh.faces, dtype=np.int64).tobytes())
        return h.hexdigest()

    @property
    def heightmap(self) -> Heightmap:
        """Top-down height field of the mesh (object frame, 0.5 mm cells), computed once per mesh."""
        return _heightmap_of(self.mesh)

    def object_to_base(self) -> np.ndarray:
        """``(4,4)`` transform from the object frame to the base frame."""
        key = np.asarray(self.fixture_pose, dtype=np.float64).tobytes()
        cached = self.__dict__.get("_object_to_base")
        if cached is None or cached[0] != key:
            cached = (key, pose_to_matrix(self.fixture_pose))
            self.__dict__["_object_to_base"] = cached
        return cached[1].copy()

    def placed(self, fixture_pose) -> "BenchObject":
        """A copy mounted at ``fixture_pose`` (6,) (shares the mesh and its height field)."""
        out = replace(self, fixture_pose=np.asarray(fixture_pose, dtype=np.float64).reshape(6).copy())
        out.__dict__["mesh_sha256"] = self.mesh_sha256
        return out

    def top_surface_points(self, n: int, rng: np.random.Generator, max_slope_deg: float = 25.0):
        """Random contact points on the upper surface, base frame.

        Samples height-field cells whose surface normal is within ``max_slope_deg`` of the object's
        +z and that lie on the upper part of the object (within 25 mm of the local top).
        Returns ``(points (n,3) float64 m, normals (n,3) float64 unit)`` in the base frame.
        """
        hm = self.heightmap
        normals = hm.normals()
        ok = hm.covered & (normals[..., 2] >= np.cos(np.radians(max_slope_deg)))
        ok &= hm.heights >= hm.heights[hm.covered].max() - 0.025
        # Stay one bubble-dent radius away from silhouette edges.
        ok &= _eroded(hm.covered, cells=int(round(0.003 / hm.res)))
        rows, cols = np.nonzero(ok)
        if len(rows) == 0:
            raise InputError(f"object '{self.name}' has no upward-facing surface to press on")
        pick = rng.integers(0, len(rows), size=int(n))
        xs, ys = hm.cell_centres()
        pts = np.stack([xs[cols[pick]], ys[rows[pick]], hm.heights[rows[pick], cols[pick]]], axis=1)
        nrm = normals[rows[pick], cols[pick]].astype(np.float64)
        t = self.object_to_base()
        return pts @ t[:3, :3].T + t[:3, 3], nrm @ t[:3, :3].T

    def top_point(self) -> np.ndarray:
        """The highest surface point nearest the centre of the object's footprint, base frame ``(3,)`` m."""
        hm = self.heightmap
        xs, ys = hm.cell_centres()
        top = hm.heights.max()
        rows, cols = np.nonzero(hm.heights >= top - 2e-4)
        centre = np.array([self.mesh.bounds[:, 0].mean(), self.mesh.bounds[:, 1].mean()])
        k = int(np.argmin((xs[cols] - centre[0]) ** 2 + (ys[rows] - centre[1]) ** 2))
        p = np.array([xs[cols[k]], ys[rows[k]], hm.heights[rows[k], cols[k]]])
        t = self.object_to_base()
        return t[:3, :3] @ p + t[:3, 3]

    def bounds_base(self) -> np.ndarray:
        """``(2,3)`` axis-aligned bounds of the placed mesh in the base frame (m)."""
        key = np.asarray(self.fixture_pose, dtype=np.float64).tobytes()
        cached = self.__dict__.get("_bounds_base")
        if cached is None or cached[0] != key:
            t = self.object_to_base()
            corners = np.array(np.meshgrid(*self.mesh.bounds.T, indexing="ij")).reshape(3, -1).T
            pts = corners @ t[:3, :3].T + t[:3, 3]
            cached = (key, np.stack([pts.min(axis=0), pts.max(axis=0)]))
            self.__dict__["_bounds_base"] = cached
        return cached[1].copy()


def _eroded(mask: np.ndarray, cells: int) -> np.ndarray:
    import cv2

    if cells <= 0:
        return mask
    kernel = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), kernel).astype(bool)


@functools.lru_cache(maxsize=16)
def _heightmap_cached(vertices_bytes: bytes, faces_bytes: bytes) -> Heightmap:
    """The ``Heightmap`` of a mesh given as its float64 vertices ``(V,3)`` m and int64 faces ``(F,3)``, C order."""
    vertices = np.frombuffer(vertices_bytes, dtype=np.float64).reshape(-1, 3)
    faces = np.frombuffer(faces_bytes, dtype=np.int64).reshape(-1, 3)
    return Heightmap.from_mesh(vertices, faces)


def _heightmap_of(mesh: trimesh.Trimesh) -> Heightmap:
    """``Heightmap.from_mesh`` of ``mesh``, computed once per mesh content (the last 16 kept)."""
    return _heightmap_cached(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes(),
        np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes(),
    )


# ---- built-in objects ------------------------------------------------------------------------


def _lying(mesh: trimesh.Trimesh, axis_height: float) -> trimesh.Trimesh:
    """Turn an upright (axis +z) solid so its axis runs along +x at height ``axis_height``."""
    rot = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])  # +z -> +x
    mesh = mesh.copy()
    mesh.apply_transform(rot)
    centre_x = mesh.bounds[:, 0].mean()
    mesh.apply_translation([-centre_x, 0.0, axis_height])
    return mesh


def _mug() -> tuple[trimesh.Trimesh, dict]:
    radius, length, wall, bottom = 0.041, 0.095, 0.004, 0.006
    profile = np.array(
        [
            [0.0, 0.0],
            [radius - 0.003, 0.0],
            [radius, 0.003],
            [radius, length],
            [radius - wall, length],
            [radius - wall, bottom],
            [0.0, bottom],
        ]
    )
    body = trimesh.creation.revolve(profile, sections=96)
    handle_centre, handle_major, handle_minor = radius + 0.025, 0.022, 0.006
    handle = trimesh.creation.torus(
        major_radius=handle_major, minor_radius=handle_minor, major_sections=48, minor_sections=16
    )
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # ring in the xz plane
    handle.apply_translation([handle_centre, 0.0, length / 2])
    upright = trimesh.util.concatenate([body, handle])  # upright +x becomes -z: the handle hangs down
    axis_height = handle_centre + handle_major + handle_minor  # handle bottom on the cradle at z = 0
    mesh = _lying(upright, axis_height)
    primitive = {
        "type": "cylinder",
        "radius": radius,
        "height": length,
        "center": [0.0, 0.0, axis_height],
        "axis": [1.0, 0.0, 0.0],
    }
    return mesh, primitive


def _wine_glass() -> tuple[trimesh.Trimesh, None]:
    profile = np.array(
        [
            [0.0, 0.0],
            [0.034, 0.0],
            [0.035, 0.002],
            [0.030, 0.004],
            [0.008, 0.008],
            [0.0045, 0.014],
            [0.0045, 0.080],
            [0.010, 0.090],
            [0.024, 0.100],
            [0.033, 0.112],
            [0.038, 0.126],
            [0.040, 0.142],
            [0.039, 0.158],
            [0.037, 0.174],
            [0.035, 0.190],
            [0.0, 0.190],
        ]
    )
    upright = trimesh.creation.revolve(profile, sections=96)
    return _lying(upright, 0.040), None


def _box() -> tuple[trimesh.Trimesh, dict]:
    extents = [0.070, 0.050, 0.040]
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation([0.0, 0.0, extents[2] / 2])
    return mesh, {"type": "box", "extents": extents, "center": [0.0, 0.0, extents[2] / 2]}


def _fingers() -> tuple[trimesh.Trimesh, None]:
    parts = []
    palm = trimesh.creation.box(extents=[0.050, 0.082, 0.016])
    palm.apply_translation([-0.045, 0.0, 0.008])
    parts.append(palm)
    radius = 0.0085
    for y, length in zip((-0.0285, -0.0095, 0.0095, 0.0285), (0.058, 0.074, 0.080, 0.070)):
        finger = trimesh.creation.capsule(height=length, radius=radius, count=[24, 24])
        finger.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
        finger.apply_translation([-0.025 + length / 2, y, radius])
        parts.append(finger)
    return trimesh.util.concatenate(parts), None


_BUILDERS = {"mug": _mug, "wine_glass": _wine_glass, "box": _box, "fingers": _fingers}


@functools.lru_cache(maxsize=None)
def _builtin(name: str) -> tuple[trimesh.Trimesh, dict | None]:
    return _BUILDERS[name]()


def object_name(name_or_path: str | Path) -> str:
    """The name ``load_object`` gives the object (a built-in's own, a mesh file's stem), without loading it."""
    key = str(name_or_path)
    return key if key in _BUILDERS else Path(key).stem


def _holds_control_characters(name: str) -> bool:
    """Whether ``name`` holds a character that would break or restyle a line of text it is printed in:
    a control character (line break, tab, terminal escape), a line or paragraph separator, or a
    bidirectional override or isolate (which reorders the text after it). Spaces of any script and
    joiners are text."""
    return any(unicodedata.category(c) in ("Cc", "Zl", "Zp") or "\u202a" <= c <= "\u202e" or "\u2066" <= c <= "\u2069"
               for c in name)


def load_object(name_or_path: str | Path) -> BenchObject:
    """A built-in object by name or a watertight mesh file by path, at the object-frame origin.

    Raises ``InputError`` for an unknown name, a missing/unreadable file, a mesh file named as a
    built-in, or a mesh that is empty, not watertight, not finite, of the wrong size or with its
    origin outside its bounding box (module docstring).
    """
    key = str(name_or_path)
    if key in _BUILDERS:
        mesh, primitive = _builtin(key)
        return BenchObject(name=key, mesh=mesh.copy(), primitive=None if primitive is None else dict(primitive))
    path = Path(key)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(
            f"unknown object '{key}': use one of {', '.join(BUILTIN_OBJECTS)} or a mesh file ({', '.join(MESH_SUFFIXES)})"
        )
    if not path.is_file():
        raise InputError(f"mesh {path} is not a regular file" if path.exists() else f"mesh file not found: {path}")
    if object_name(path) in _BUILDERS:
        raise InputError(f"mesh {path} would be named '{path.stem}', as the built-in object; rename the file")
    try:  # the object's name goes into recordings, reports and plots as text
        object_name(path).encode("utf-8")
    except UnicodeEncodeError:  # bytes of another encoding in the name (was: trimesh's UnicodeEncodeError)
        raise InputError(f"mesh {path}: its file name is not UTF-8 text, and names the object; rename the file") from None
    if _holds_control_characters(object_name(path)):  # was: a line break or a terminal escape recorded as the name
        raise InputError(f"mesh {str(path)!r}: its file name holds control characters (a line break, a tab, a terminal "
                         "escape), and names the object; rename the file")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)  # merged below, once its vertices are checked
    except ImportError:  # a file that is no binary mesh is read as text, whose encoding needs an optional package
        raise InputError(f"cannot read mesh {path}: it is neither a binary {path.suffix.lower()[1:].upper()} "
                         "file nor UTF-8 text (truncated or corrupt?)") from None
    except Exception as err:  # trimesh raises many types for corrupt files
        raise InputError(f"cannot read mesh {path}: {type(err).__name__}: {err}".splitlines()[0]) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"mesh {path} holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise InputError(f"mesh {path} has non-finite vertices")
    size = float(np.max(mesh.extents))  # before the merge, which overflows on 1e30 m (a warning line)
    if not (MESH_SIZE_RANGE_M[0] <= size <= MESH_SIZE_RANGE_M[1]):
        raise InputError(f"mesh {path} is {size:.3g} m across; expected metres (5 mm to 0.5 m)")
    mesh.process()  # merges the vertices that an STL repeats per triangle
    if not mesh.is_watertight:
        mesh.update_faces(mesh.nondegenerate_faces() & mesh.unique_faces())
        mesh.remove_unreferenced_vertices()
        if not mesh.is_watertight:
            raise InputError(f"mesh {path} is not watertight (it must be a closed surface)")
    if not mesh.is_winding_consistent or mesh.volume < 0:  # inside out, or some faces turned
        mesh.fix_normals()
    (x0, y0, z0), (x1, y1, z1) = mesh.bounds
    if np.any(mesh.bounds[0] > MESH_PLACEMENT_TOL_M) or np.any(mesh.bounds[1] < -MESH_PLACEMENT_TOL_M):
        raise InputError(f"mesh {path} spans x {x0:.4g}..{x1:.4g}, y {y0:.4g}..{y1:.4g}, z {z0:.4g}..{z1:.4g} m: its "
                         "origin must lie within the part (the fixture holds it, and the pose check turns the part "
                         "about it)")
    return BenchObject(name=object_name(path), mesh=mesh, primitive=None)


def fixture_plate(objects: list[BenchObject]) -> list[BenchObject]:
    """Mount ``objects`` side by side along base y on one plate (centred at x = ``PLATE_X``, y = 0,
    plate top z = ``PLATE_Z``), separated by ``PLATE_GAP`` of free space; returns placed copies.
    Each object's footprint centre sits on the row line x = ``PLATE_X``, and its lowest point on the
    plate top. ``InputError`` when the row is
    longer than the plate (``PLATE_LENGTH_M``)."""
    if not objects:
        return []
    bounds = [o.mesh.bounds for o in objects]
    widths = [b[1, 1] - b[0, 1] for b in bounds]
    total = sum(widths) + PLATE_GAP * (len(objects) - 1)
    if total > PLATE_LENGTH_M:
        raise InputError(f"the objects take {total:.3f} m of the fixture plate in a row ({PLATE_GAP * 1e3:.0f} mm apart), "
                         f"longer than its {PLATE_LENGTH_M:g} m; press fewer or smaller objects in one session")
    placed = []
    y_edge = -total / 2
    for obj, b, w in zip(objects, bounds, widths):
        cx = 0.5 * (b[0, 0] + b[1, 0])
        cy = 0.5 * (b[0, 1] + b[1, 1])
        pose = [PLATE_X - cx, y_edge + w / 2 - cy, PLATE_Z - b[0, 2], 0.0, 0.0, 0.0]
        placed.append(obj.placed(pose))
        y_edge += w + PLATE_GAP
    return placed
