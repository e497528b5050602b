"""Occupancy grids per storey: the building's geometry cut in the robot's height band, rasterised.

Every storey shares one `GridSpec` (same origin and size), so a cell index means the same place on
every floor. Two obstacle layers are kept apart: `structure` (walls, columns, windows, stairs, ...),
which bounds rooms, and `furniture` (movable objects), which only blocks motion and sight.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from bimfactor.bim.ifc import IfcElement, IfcModel, Mesh, Storey
from bimfactor.config import GridConfig
from bimfactor.errors import IfcError

_SUBPIXEL_BITS = 4


def distance_transform(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 Euclidean distance, in cells, from each True cell of the (H, W) bool `mask` to the nearest False
    cell (0 on False cells; inf everywhere when there is none). Exact: OpenCV's precise mask equals scipy's
    `distance_transform_edt` to 1e-5 cells and runs about 15 times faster (0.02 s against 0.39 s on 3 M cells)."""
    mask = np.asarray(mask, dtype=bool)
    if mask.all():
        return np.full(mask.shape, np.inf, np.float32)
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


@dataclass(frozen=True)
class GridSpec:
    """Cell (row, col) covers x ∈ [ox + col·res, ox + (col+1)·res), y likewise with row; row grows with y."""

    origin_x: float
    origin_y: float
    resolution_m: float
    rows: int
    cols: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) for matplotlib's imshow(origin='lower')."""
        return (
            self.origin_x,
            self.origin_x + self.cols * self.resolution_m,
            self.origin_y,
            self.origin_y + self.rows * self.resolution_m,
        )

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) world x, y → (N, 2) int row, col (may lie outside the grid)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.floor((xy[:, 0] - self.origin_x) / self.resolution_m)
        row = np.floor((xy[:, 1] - self.origin_y) / self.resolution_m)
        return np.stack([row, col], axis=1).astype(np.int64)

    def cell_to_world(self, rc: np.ndarray) -> np.ndarray:
        """(N, 2) row, col → (N, 2) world x, y of the cell centres."""
        rc = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
        x = self.origin_x + (rc[:, 1] + 0.5) * self.resolution_m
        y = self.origin_y + (rc[:, 0] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=1)

    def contains(self, rc: np.ndarray) -> np.ndarray:
        rc = np.asarray(rc).reshape(-1, 2)
        return (rc[:, 0] >= 0) & (rc[:, 0] < self.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < self.cols)

    def window(self, x_min: float, y_min: float, x_max: float, y_max: float) -> tuple[GridSpec, tuple[slice, slice]]:
        """The sub-grid covering a world box (clipped to this grid) and the slices that cut it out."""
        (r0, c0), (r1, c1) = self.world_to_cell(np.array([[x_min, y_min], [x_max, y_max]]))
        r0, c0 = max(r0, 0), max(c0, 0)
        r1, c1 = min(r1 + 1, self.rows), min(c1 + 1, self.cols)
        r1, c1 = max(r1, r0 + 1), max(c1, c0 + 1)
        sub = GridSpec(
            self.origin_x + c0 * self.resolution_m,
            self.origin_y + r0 * self.resolution_m,
            self.resolution_m,
            r1 - r0,
            c1 - c0,
        )
        return sub, (slice(r0, r1), slice(c0, c1))

    def to_dict(self) -> dict[str, float | int]:
        return {
            "origin_x": self.origin_x,
            "origin_y": self.origin_y,
            "resolution_m": self.resolution_m,
            "rows": self.rows,
            "cols": self.cols,
        }


@dataclass
class StoreyGrid:
    """Obstacle layers of one storey, (rows, cols) bool, and the clearance to the nearest obstacle in metres."""

    storey: Storey
    structure: np.ndarray
    furniture: np.ndarray
    clearance_m: np.ndarray

    @property
    def occupied(self) -> np.ndarray:
        return self.structure | self.furniture


def grid_spec_for(model: IfcModel, cfg: GridConfig, exclude: Iterable[str]) -> GridSpec:
    """One grid covering the footprint of every obstacle element of the model, padded."""
    excluded = tuple(exclude)
    boxes = [e.mesh.bounds for e in model.elements if e.mesh is not None and not any(e.is_a(c) for c in excluded)]
    if not boxes:
        boxes = [e.mesh.bounds for e in model.elements if e.mesh is not None]
    if not boxes:
        raise IfcError(f"{model.source_path}: the model has no geometry to build an occupancy grid from")
    lo = np.min([b[0, :2] for b in boxes], axis=0) - cfg.padding_m
    hi = np.max([b[1, :2] for b in boxes], axis=0) + cfg.padding_m
    res = cfg.resolution_m
    cols, rows = np.ceil((hi - lo) / res).astype(int)
    return GridSpec(float(lo[0]), float(lo[1]), res, int(rows), int(cols))


def band_polygons(mesh: Mesh, z_lo: float, z_hi: float) -> list[np.ndarray]:
    """xy polygons of the mesh's triangles clipped to z ∈ [z_lo, z_hi] (each convex, (K, 2))."""
    tris = mesh.vertices[mesh.faces]  # (F, 3, 3)
    z = tris[:, :, 2]
    keep = (z.max(axis=1) >= z_lo) & (z.min(axis=1) <= z_hi)
    tris, z = tris[keep], z[keep]
    inside = (z.min(axis=1) >= z_lo) & (z.max(axis=1) <= z_hi)
    polys = list(tris[inside][:, :, :2])
    for tri in tris[~inside]:
        poly = _clip(_clip(tri, z_lo, above=True), z_hi, above=False)
        if len(poly) >= 2:
            polys.append(poly[:, :2])
    return polys


def _clip(poly: np.ndarray, z0: float, above: bool) -> np.ndarray:
    """Sutherland–Hodgman clip of a 3D polygon against the plane z = z0, keeping z ≥ z0 (or ≤)."""
    if len(poly) == 0:
        return poly
    side = (poly[:, 2] - z0) * (1.0 if above else -1.0)
    out = []
    for i in range(len(poly)):
        j = (i + 1) % len(poly)
        if side[i] >= 0:
            out.append(poly[i])
        if (side[i] >= 0) != (side[j] >= 0):
            t = side[i] / (side[i] - side[j])
            out.append(poly[i] + t * (poly[j] - poly[i]))
    return np.asarray(out) if out else np.zeros((0, 3))


def rasterise_polygons(polys: Iterable[np.ndarray], spec: GridSpec, out: np.ndarray | None = None) -> np.ndarray:
    """Mark every cell a polygon touches; degenerate (edge-on) polygons still mark their outline."""
    mask = np.zeros(spec.shape, np.uint8) if out is None else out
    scale = (1 << _SUBPIXEL_BITS) / spec.resolution_m
    origin = np.array([spec.origin_x, spec.origin_y])
    for poly in polys:
        pts = np.round((poly - origin) * scale - (1 << (_SUBPIXEL_BITS - 1))).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
        cv2.polylines(mask, [pts], True, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
    return mask


def footprint_mask(element: IfcElement, spec: GridSpec, z_lo: float = -np.inf, z_hi: float = np.inf) -> np.ndarray:
    """Cells under the element's geometry between z_lo and z_hi, (rows, cols) bool, as a filled footprint.

    A solid cut by the band shows only its edge-on sides; the enclosed inside is filled.
    """
    assert element.mesh is not None
    return ndimage.binary_fill_holes(rasterise_polygons(band_polygons(element.mesh, z_lo, z_hi), spec))


def paint_footprint(
    element: IfcElement, spec: GridSpec, out: np.ndarray, z_lo: float = -np.inf, z_hi: float = np.inf
) -> None:
    """OR the element's filled footprint between z_lo and z_hi into `out` (rows, cols), working in a window."""
    assert element.mesh is not None
    lo, hi = element.mesh.bounds
    pad = 2 * spec.resolution_m  # the outline must not touch the window border, or its inside cannot be filled
    sub, window = spec.window(lo[0] - pad, lo[1] - pad, hi[0] + pad, hi[1] + pad)
    out[window] |= footprint_mask(element, sub, z_lo, z_hi)


def build_storey_grid(
    storey: Storey,
    elements: list[IfcElement],
    spec: GridSpec,
    cfg: GridConfig,
    furniture_classes: Iterable[str],
) -> StoreyGrid:
    """Rasterise the obstacle elements that reach into this storey's band."""
    z_lo = storey.elevation_m + cfg.band_min_m
    z_hi = storey.elevation_m + cfg.band_max_m
    furniture_classes = tuple(furniture_classes)
    structure = np.zeros(spec.shape, np.uint8)
    furniture = np.zeros(spec.shape, np.uint8)
    for el in elements:
        if el.mesh is None or any(el.is_a(c) for c in cfg.obstacle_exclude_classes):
            continue
        lo, hi = el.mesh.bounds[:, 2]
        if hi < z_lo or lo > z_hi:
            continue
        target = furniture if any(el.is_a(c) for c in furniture_classes) else structure
        rasterise_polygons(band_polygons(el.mesh, z_lo, z_hi), spec, out=target)
    structure_b = _fill_enclosed_slivers(structure.astype(bool), cfg.robot_radius_m / spec.resolution_m)
    furniture_b = furniture.astype(bool) & ~structure_b
    clearance = distance_transform(~(structure_b | furniture_b)) * np.float32(spec.resolution_m)
    return StoreyGrid(storey, structure_b, furniture_b, clearance.astype(np.float32))


def _fill_enclosed_slivers(occupied: np.ndarray, max_half_width_cells: float) -> np.ndarray:
    """Close the hollow insides of solids: enclosed free pockets too thin for the robot become occupied.

    Edge-on faces of a wall rasterise to its outline, leaving a free sliver inside the wall.
    """
    labels, count = ndimage.label(~occupied)
    if count == 0:
        return occupied
    depth = distance_transform(~occupied)
    max_depth = ndimage.maximum(depth, labels, index=np.arange(1, count + 1))
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    thin = np.zeros(count + 1, bool)
    thin[1:] = np.asarray(max_depth) <= max_half_width_cells
    thin[border] = False
    return occupied | thin[labels]
