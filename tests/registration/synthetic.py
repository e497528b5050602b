"""Hand-made surface models for the registration tests: box rooms and corridors built from triangle meshes."""

from __future__ import annotations

import numpy as np

from bimfactor.bim.surfaces import outward_mesh
from bimfactor.registration.surface import SurfaceModel, sample_mesh
from bimfactor.types import se2_inverse, se2_to_matrix

# The 12 triangles of a unit cube [0, 1]^3, wound outward.
_CUBE_VERTICES = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
_CUBE_FACES = np.array(
    [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x = 0, x = 1
        [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y = 0, y = 1
        [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # z = 0, z = 1
    ]
)  # fmt: skip
WALL_HEIGHT_M = 2.6
WALL_THICKNESS_M = 0.2


def box_mesh(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(8, 3) vertices and (12, 3) faces of the axis-aligned box [lo, hi]."""
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    return lo_a + _CUBE_VERTICES * (hi_a - lo_a), _CUBE_FACES.copy()


def surface_from_boxes(boxes: list[tuple], density_per_m2: float, seed: int) -> SurfaceModel:
    """A storey-0 surface model (elevation 0) sampled from axis-aligned boxes ((lo), (hi))."""
    rng = np.random.default_rng(seed)
    pts, nrm, owner = [], [], []
    for i, (lo, hi) in enumerate(boxes):
        vertices, faces = box_mesh(lo, hi)
        p, n = sample_mesh(*outward_mesh(vertices, faces), density_per_m2, rng)
        pts.append(p)
        nrm.append(n)
        owner.append(np.full(len(p), i, dtype=np.int32))
    return SurfaceModel(0, 0.0, 3.0, np.concatenate(pts), np.concatenate(nrm), np.concatenate(owner))


def _wall(x0: float, y0: float, x1: float, y1: float) -> tuple:
    return ((x0, y0, 0.0), (x1, y1, WALL_HEIGHT_M))


def room_boxes() -> list[tuple]:
    """A 6 x 4 m box room (inner faces at x = 0..6, y = 0..4) with two columns and a wall stub."""
    t = WALL_THICKNESS_M
    return [
        _wall(-t, -t, 6 + t, 0),  # south
        _wall(-t, 4, 6 + t, 4 + t),  # north
        _wall(-t, 0, 0, 4),  # west
        _wall(6, 0, 6 + t, 4),  # east
        ((1.5, 2.8, 0.0), (1.9, 3.2, WALL_HEIGHT_M)),  # column
        ((4.2, 0.9, 0.0), (4.5, 1.2, WALL_HEIGHT_M)),  # column
        _wall(6 - 1.2, 2.5, 6, 2.5 + t),  # wall stub from the east wall
    ]


def corridor_boxes(length_m: float = 40.0, width_m: float = 2.0) -> list[tuple]:
    """A featureless corridor along x: two long parallel walls at y = 0 and y = width, no ends in sight."""
    t = WALL_THICKNESS_M
    return [_wall(0, -t, length_m, 0), _wall(0, width_m, length_m, width_m + t)]


def scan_from(
    surface: SurfaceModel,
    T_world_base: np.ndarray,
    max_range_m: float = 6.0,
    min_z_m: float = 0.15,
    max_z_m: float = 2.2,
) -> np.ndarray:
    """(N, 3) base-frame points of `surface` facing the pose, within range and in the height band.

    Back faces are never seen; occlusion between elements is ignored (the test scenes barely have any).
    """
    facing = np.einsum("ij,ij->i", surface.normals[:, :2], T_world_base[:2] - surface.points[:, :2]) > 0
    surface = SurfaceModel(0, 0.0, 3.0, surface.points[facing], surface.normals[facing], surface.element_index[facing])
    T_base_world = se2_to_matrix(se2_inverse(T_world_base))
    points = surface.points @ T_base_world[:3, :3].T + T_base_world[:3, 3]
    keep = (np.linalg.norm(points[:, :2], axis=1) <= max_range_m) & (points[:, 2] >= min_z_m)
    keep &= points[:, 2] <= max_z_m
    return points[keep]


def bay_corridor_boxes(bay_m: float = 3.0, length_m: float = 40.0, width_m: float = 2.4) -> list[tuple]:
    """A corridor along x whose walls carry identical 0.4 x 0.4 m pilasters every `bay_m`: symmetric under a
    shift by one bay, so ICP started more than about half a pilaster off settles in whichever bay is nearest."""
    boxes = corridor_boxes(length_m, width_m)
    for x in np.arange(1.0, length_m - 0.4, bay_m):
        boxes.append(((x, 0.0, 0.0), (x + 0.4, 0.4, WALL_HEIGHT_M)))
        boxes.append(((x, width_m - 0.4, 0.0), (x + 0.4, width_m, WALL_HEIGHT_M)))
    return boxes
