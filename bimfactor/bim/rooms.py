"""Rooms by the paper's method (flood fill of free space with doors closed), doors as room connectivity,
IfcSpace rooms where the model has them, and how well the two agree.

Room label maps are int32 (rows, cols): a room's id where a cell belongs to it, `OUTSIDE` for free
space connected to the grid border (outside the building), `NO_ROOM` elsewhere (walls, slivers).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from bimfactor.bim.grid import GridSpec, StoreyGrid, band_polygons, footprint_mask, paint_footprint, rasterise_polygons
from bimfactor.bim.ifc import IfcElement
from bimfactor.config import GridConfig, RoomsConfig

OUTSIDE = -1
NO_ROOM = -2


@dataclass(frozen=True)
class DoorGeometry:
    """A door's footprint as an oriented rectangle: centre, unit axis along the wall, width and depth."""

    center_xy: np.ndarray
    axis_xy: np.ndarray
    width_m: float
    depth_m: float

    @property
    def normal_xy(self) -> np.ndarray:
        return np.array([-self.axis_xy[1], self.axis_xy[0]])

    def corners(self, grow_m: float = 0.0) -> np.ndarray:
        """(4, 2) corners of the rectangle grown by `grow_m` on every side."""
        u = self.axis_xy * (self.width_m / 2 + grow_m)
        n = self.normal_xy * (self.depth_m / 2 + grow_m)
        c = self.center_xy
        return np.array([c - u - n, c + u - n, c + u + n, c - u + n])


@dataclass
class RoomRegion:
    """One room on one storey before it gets a global id: its mask and where it came from."""

    mask: np.ndarray
    source: str  # "floodfill" or "ifcspace"
    space_guid: str | None = None
    space_name: str = ""
    space_number: str = ""


def door_geometry(door: IfcElement, z_lo: float, z_hi: float) -> DoorGeometry | None:
    """The minimum-area rectangle around the door's geometry in the band (None if none reaches it)."""
    assert door.mesh is not None
    polys = band_polygons(door.mesh, z_lo, z_hi)
    if not polys:
        return None
    return _rect_geometry(np.concatenate(polys).astype(np.float32))


def _rect_geometry(pts: np.ndarray) -> DoorGeometry:
    """Minimum-area rectangle around (N, 2) points, its axis along the longer side."""
    (cx, cy), (w, h), angle = cv2.minAreaRect(pts)
    theta = np.deg2rad(angle)
    axis = np.array([np.cos(theta), np.sin(theta)])
    if h > w:  # make the axis run along the longer side (along the wall)
        w, h = h, w
        axis = np.array([-axis[1], axis[0]])
    return DoorGeometry(np.array([cx, cy], float), axis, float(w), float(h))


def passage_geometries(
    storey_elements: list[IfcElement],
    structure: np.ndarray,
    doors: list[DoorGeometry],
    spec: GridSpec,
    elevation_m: float,
    cfg: RoomsConfig,
) -> list[DoorGeometry]:
    """Leafless doorways: wall geometry in the lintel band (above door height) with no structure below it.

    Open-plan models often leave a passage as a wall whose opening runs to the floor; only the lintel
    above shows it. Each such strip, not already covered by a door, is returned as a door-like rectangle.
    """
    z_lo, z_hi = elevation_m + cfg.lintel_band_min_m, elevation_m + cfg.lintel_band_max_m
    lintel = np.zeros(spec.shape, bool)
    for el in storey_elements:
        if el.mesh is not None and any(el.is_a(c) for c in cfg.lintel_classes):
            lo, hi = el.mesh.bounds[:, 2]
            if hi >= z_lo and lo <= z_hi:
                paint_footprint(el, spec, lintel, z_lo, z_hi)
    covered = seal_doors(structure, doors, spec, cfg.door_seal_margin_m)
    covered = ndimage.binary_dilation(covered, iterations=2)
    strips, count = ndimage.label(lintel & ~covered)
    passages = []
    for k in range(1, count + 1):
        cells = np.argwhere(strips == k)
        if len(cells) * spec.resolution_m**2 < 0.1:
            continue
        xy = spec.cell_to_world(cells).astype(np.float32)
        geom = _rect_geometry(xy)
        geom = DoorGeometry(geom.center_xy, geom.axis_xy, geom.width_m + spec.resolution_m, geom.depth_m)
        if geom.width_m >= 0.6:  # narrower strips are wall slivers, not passages a robot takes
            passages.append(geom)
    return passages


def seal_doors(structure: np.ndarray, doors: list[DoorGeometry], spec: GridSpec, margin_m: float) -> np.ndarray:
    """Structure with every door's footprint (grown by `margin_m`) closed."""
    sealed = structure.astype(np.uint8).copy()
    rasterise_polygons([d.corners(margin_m) for d in doors], spec, out=sealed)
    return sealed.astype(bool)


def floodfill_rooms(sealed: np.ndarray, spec: GridSpec, cfg: RoomsConfig) -> tuple[list[RoomRegion], np.ndarray]:
    """Connected components of free space (4-connected); those touching the border are outside.

    Returns the room regions (largest first) and the mask of outside cells.
    """
    labels, count = ndimage.label(~sealed)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    outside = np.isin(labels, border[border > 0])
    areas = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, count + 1))
    min_cells = cfg.min_room_area_m2 / spec.resolution_m**2
    keep = [i + 1 for i in np.argsort(-areas) if areas[i] >= min_cells and (i + 1) not in border]
    return [RoomRegion(labels == k, "floodfill") for k in keep], outside


def door_connected_regions(
    regions: list[RoomRegion], doors: list[DoorGeometry], outside: np.ndarray, spec: GridSpec, probe_m: float
) -> list[RoomRegion]:
    """The flood-fill regions a door (or leafless passage, or a door to the outside) joins to another place; all of them
    when no door joins any (a one-room building, a storey whose doors the model lacks). Enclosed space no door leads
    into (a courtyard, a shaft) is no room."""
    labels = label_map(regions, list(range(len(regions))), outside)
    reached: set[int] = set()
    for door in doors:
        a, b = door_sides(door, labels, spec, probe_m)
        if joins(a, b):
            reached.update((a, b))
    reached.discard(OUTSIDE)
    return [region for k, region in enumerate(regions) if k in reached] if reached else regions


def space_rooms(spaces: list[IfcElement], spec: GridSpec, free: np.ndarray) -> list[RoomRegion]:
    """Rooms from IfcSpace footprints, restricted to free (non-structure) cells."""
    regions = []
    for space in spaces:
        mask = footprint_mask(space, spec) & free
        if mask.any():
            # IfcSpace Name is the room number ("101") where a LongName ("Buero Meier") names the room.
            number = space.name if space.long_name else ""
            regions.append(RoomRegion(mask, "ifcspace", space.guid, space.long_name or space.name, number))
    return regions


def label_map(regions: list[RoomRegion], room_ids: list[int], outside: np.ndarray) -> np.ndarray:
    """Paint regions (first wins) into one int32 map with OUTSIDE and NO_ROOM elsewhere."""
    labels = np.full(outside.shape, NO_ROOM, np.int32)
    labels[outside] = OUTSIDE
    for region, rid in zip(regions, room_ids, strict=True):
        labels[region.mask & (labels == NO_ROOM)] = rid
    return labels


def match_rooms(
    floodfill: list[RoomRegion], spaces: list[RoomRegion], res_m: float, min_area_m2: float = 2.0
) -> list[float]:
    """For each IfcSpace larger than `min_area_m2`, the best IoU of any flood-fill room."""
    if not spaces:
        return []
    flood = np.zeros(spaces[0].mask.shape, np.int32)  # 0 = no flood-fill room, k = room k-1
    for k, room in enumerate(floodfill, start=1):
        flood[room.mask] = k
    room_area = np.bincount(flood.ravel(), minlength=len(floodfill) + 1)
    ious = []
    for space in spaces:
        space_area = int(np.count_nonzero(space.mask))
        if space_area * res_m**2 < min_area_m2:
            continue
        inter = np.bincount(flood[space.mask], minlength=len(floodfill) + 1)
        union = space_area + room_area - inter
        iou = inter[1:] / np.maximum(union[1:], 1)
        ious.append(float(iou.max()) if len(iou) else 0.0)
    return ious


def open_boundaries(labels: np.ndarray, spec: GridSpec, min_length_m: float) -> list[tuple[int, int, DoorGeometry]]:
    """Pairs of rooms whose cells touch with no wall between (open-plan IfcSpace rooms), with the shared edge.

    The edge is returned as a door-like rectangle along the boundary; boundaries shorter than `min_length_m`
    (corner contacts) are left out.
    """
    pairs, points = [], []
    for a, b, offset in ((labels[:, :-1], labels[:, 1:], (0, 0.5)), (labels[:-1], labels[1:], (0.5, 0))):
        touch = (a >= 0) & (b >= 0) & (a != b)
        rc = np.argwhere(touch).astype(float) + offset
        pairs.append(np.sort(np.stack([a[touch], b[touch]], axis=1), axis=1))
        points.append(rc)
    pair_arr, rc_arr = np.concatenate(pairs), np.concatenate(points)
    out = []
    for pair in np.unique(pair_arr, axis=0):
        cells = rc_arr[np.all(pair_arr == pair, axis=1)]
        if len(cells) * spec.resolution_m < min_length_m:
            continue
        geom = _rect_geometry(spec.cell_to_world(cells).astype(np.float32))
        out.append((int(pair[0]), int(pair[1]), DoorGeometry(geom.center_xy, geom.axis_xy, geom.width_m, 0.0)))
    return out


def joins(a: int, b: int) -> bool:
    """True when a door's two sides are two different known places (two rooms, or a room and outside)."""
    return a != b and NO_ROOM not in (a, b)


def door_sides(door: DoorGeometry, labels: np.ndarray, spec: GridSpec, probe_m: float) -> tuple[int, int]:
    """The room labels on the two sides of a door (OUTSIDE for the exterior, NO_ROOM if unknown)."""
    sides = []
    for sign in (1.0, -1.0):
        votes: list[int] = []
        for along in (-0.25, 0.0, 0.25):
            for reach in (0.5, 1.0, 1.5):
                p = door.center_xy + door.axis_xy * along * door.width_m
                p = p + sign * door.normal_xy * (door.depth_m / 2 + reach * probe_m)
                rc = spec.world_to_cell(p)
                if spec.contains(rc)[0]:
                    votes.append(int(labels[rc[0, 0], rc[0, 1]]))
        useful = [v for v in votes if v != NO_ROOM]
        sides.append(max(set(useful), key=useful.count) if useful else NO_ROOM)
    return sides[0], sides[1]


def assign_to_room(mask: np.ndarray, labels: np.ndarray, spec: GridSpec, max_reach_m: float = 0.6) -> int:
    """The room most of a footprint lies in; footprints in walls (windows, doors) look around them."""
    if not mask.any():
        return NO_ROOM
    step = max(1, round(0.2 / spec.resolution_m))
    rounds = int(max_reach_m / 0.2) + 1
    # Work in the footprint's box grown by the farthest reach: the same answer as on the whole grid, whose
    # dilations (3 M cells on a large floor, per object) took seconds per building.
    pad = step * rounds
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    box = (slice(max(rows[0] - pad, 0), rows[-1] + pad + 1), slice(max(cols[0] - pad, 0), cols[-1] + pad + 1))
    mask, labels = mask[box], labels[box]
    grown = mask
    for _ in range(rounds):
        vals = labels[grown]
        vals = vals[vals >= 0]
        if len(vals):
            return int(np.bincount(vals).argmax())
        grown = ndimage.binary_dilation(grown, iterations=step)
    return OUTSIDE if np.any(labels[grown] == OUTSIDE) else NO_ROOM


def navigable_mask(grid: StoreyGrid, labels: np.ndarray, cfg: GridConfig) -> np.ndarray:
    """Cells a robot centre may occupy: inside a room, with clearance of at least its radius."""
    return (labels >= 0) & (grid.clearance_m >= cfg.robot_radius_m)
