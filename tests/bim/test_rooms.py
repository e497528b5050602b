"""Rooms by flood fill with doors closed, doors joining rooms, leafless passages, room assignment."""

from __future__ import annotations

import numpy as np

from bimfactor.bim import rooms as R
from bimfactor.bim.grid import GridSpec, build_storey_grid
from bimfactor.bim.ifc import Storey
from bimfactor.config import load_config
from tests.bim.geometry import box, two_rooms

SPEC = GridSpec(origin_x=-1.0, origin_y=-1.0, resolution_m=0.05, rows=140, cols=220)
STOREY = Storey(0, "s", "ground", 0.0)
CFG = load_config()


def _rooms(elements):
    grid = build_storey_grid(STOREY, elements, SPEC, CFG.bim.grid, furniture_classes=["IfcFurnishingElement"])
    doors = [g for e in elements if e.is_a("IfcDoor") and (g := R.door_geometry(e, 0.1, 1.2)) is not None]
    doors += R.passage_geometries(elements, grid.structure, doors, SPEC, 0.0, CFG.bim.rooms)
    sealed = R.seal_doors(grid.structure, doors, SPEC, CFG.bim.rooms.door_seal_margin_m)
    regions, outside = R.floodfill_rooms(sealed, SPEC, CFG.bim.rooms)
    labels = R.label_map(regions, list(range(len(regions))), outside)
    return regions, labels, doors


def test_door_geometry_runs_along_the_wall() -> None:
    door = next(e for e in two_rooms() if e.is_a("IfcDoor"))
    geom = R.door_geometry(door, 0.1, 1.2)
    np.testing.assert_allclose(geom.center_xy, [4.1, 2.0], atol=1e-6)
    assert abs(geom.axis_xy[1]) > 0.999  # the wall runs along y
    assert geom.width_m == np.float32(0.9) or abs(geom.width_m - 0.9) < 1e-5
    assert abs(geom.depth_m - 0.1) < 1e-5


def test_two_rooms_split_at_the_closed_door_and_the_door_joins_them() -> None:
    regions, labels, doors = _rooms(two_rooms())
    assert len(regions) == 2
    areas = sorted(r.mask.sum() * SPEC.resolution_m**2 for r in regions)
    np.testing.assert_allclose(areas, [16.0, 16.0], rtol=0.05)
    sides = R.door_sides(doors[0], labels, SPEC, CFG.bim.rooms.door_probe_m)
    assert set(sides) == {0, 1}


def test_an_open_gap_without_door_or_lintel_is_one_room() -> None:
    regions, _, doors = _rooms(two_rooms(door=False))
    assert len(regions) == 1 and doors == []


def test_a_lintel_over_the_gap_is_a_passage_that_splits_the_rooms() -> None:
    regions, labels, doors = _rooms(two_rooms(door=False, lintel=True))
    assert len(regions) == 2 and len(doors) == 1
    np.testing.assert_allclose(doors[0].center_xy, [4.1, 2.0], atol=0.05)
    assert set(R.door_sides(doors[0], labels, SPEC, CFG.bim.rooms.door_probe_m)) == {0, 1}


def test_outside_is_what_touches_the_grid_border() -> None:
    _, labels, _ = _rooms(two_rooms())
    assert labels[0, 0] == R.OUTSIDE
    wall = SPEC.world_to_cell(np.array([[4.1, 0.5]]))[0]
    assert labels[wall[0], wall[1]] == R.NO_ROOM


def test_objects_in_walls_are_assigned_to_the_nearest_room() -> None:
    _, labels, _ = _rooms(two_rooms(gap=False))
    chair = box("IfcFurniture", (6.0, 1.0, 0.0), (6.5, 1.5, 0.9))
    window = box("IfcFurniture", (1.0, 4.02, 0.9), (2.0, 4.18, 2.0))  # inside the north wall of the west room
    from bimfactor.bim.grid import footprint_mask

    west = labels[SPEC.world_to_cell(np.array([[1.0, 1.0]]))[0][0], SPEC.world_to_cell(np.array([[1.0, 1.0]]))[0][1]]
    east = labels[SPEC.world_to_cell(np.array([[7.0, 1.0]]))[0][0], SPEC.world_to_cell(np.array([[7.0, 1.0]]))[0][1]]
    assert R.assign_to_room(footprint_mask(chair, SPEC), labels, SPEC) == east
    assert R.assign_to_room(footprint_mask(window, SPEC), labels, SPEC) == west
    assert west != east


def test_ifcspace_match_iou() -> None:
    regions, _, _ = _rooms(two_rooms())
    half = np.zeros(SPEC.shape, bool)
    half[regions[0].mask.nonzero()[0].min() :, :] = True
    spaces = [R.RoomRegion(regions[0].mask, "ifcspace"), R.RoomRegion(regions[1].mask & half, "ifcspace")]
    ious = R.match_rooms(regions, spaces, SPEC.resolution_m)
    assert ious[0] == 1.0 and 0.0 < ious[1] <= 1.0


def _closet(outer_door: bool = False) -> list:
    """A 1 × 4 m walled closet east of `two_rooms` (x 8.4..9.4), with a door in its east wall when `outer_door`."""
    h = 2.7
    walls = [box("IfcWall", (8.4, -0.2, 0), (9.6, 0.0, h)), box("IfcWall", (8.4, 4.0, 0), (9.6, 4.2, h))]
    if not outer_door:
        return [*walls, box("IfcWall", (9.4, 0.0, 0), (9.6, 4.0, h))]
    return [
        *walls,
        box("IfcWall", (9.4, 0.0, 0), (9.6, 1.5, h)),
        box("IfcWall", (9.4, 2.5, 0), (9.6, 4.0, h)),
        box("IfcDoor", (9.45, 1.55, 0), (9.55, 2.45, 2.05), name="Door"),
    ]


def _door_connected_areas(elements) -> tuple[list[float], list[float]]:
    """Areas (m², sorted) of the flood-fill regions, and of those `door_connected_regions` keeps."""
    regions, labels, doors = _rooms(elements)
    kept = R.door_connected_regions(regions, doors, labels == R.OUTSIDE, SPEC, CFG.bim.rooms.door_probe_m)

    def areas(found: list[R.RoomRegion]) -> list[float]:
        return sorted(float(r.mask.sum() * SPEC.resolution_m**2) for r in found)

    return areas(regions), areas(kept)


def test_a_walled_region_no_door_reaches_is_dropped_beside_door_connected_rooms() -> None:
    found, kept = _door_connected_areas(two_rooms() + _closet())
    np.testing.assert_allclose(found, [4.0, 16.0, 16.0], atol=0.5)
    np.testing.assert_allclose(kept, [16.0, 16.0], atol=0.5)


def test_a_door_to_outside_connects_a_region() -> None:
    found, kept = _door_connected_areas(two_rooms() + _closet(outer_door=True))
    assert len(found) == 3 and kept == found


def test_a_storey_without_doors_keeps_all_its_regions() -> None:
    found, kept = _door_connected_areas(two_rooms(gap=False) + _closet())
    np.testing.assert_allclose(found, [4.0, 16.0, 16.0], atol=0.5)
    assert kept == found
    one_room, kept = _door_connected_areas(two_rooms(door=False))
    assert len(one_room) == 1 and kept == one_room


def test_assigning_a_footprint_in_its_box_equals_the_whole_grid() -> None:
    """`assign_to_room` looks only within the footprint's box grown by its reach: the same room as dilating the
    footprint over the whole grid, for footprints inside rooms, in walls, at the grid's edge and outside."""
    from scipy import ndimage

    from bimfactor.bim.grid import GridSpec
    from bimfactor.bim.rooms import NO_ROOM, OUTSIDE, assign_to_room

    def whole_grid(mask: np.ndarray, labels: np.ndarray, spec: GridSpec, max_reach_m: float = 0.6) -> int:
        step = max(1, round(0.2 / spec.resolution_m))
        grown = mask
        for _ in range(int(max_reach_m / 0.2) + 1):
            vals = labels[grown]
            vals = vals[vals >= 0]
            if len(vals):
                return int(np.bincount(vals).argmax())
            grown = ndimage.binary_dilation(grown, iterations=step)
        return OUTSIDE if np.any(labels[grown] == OUTSIDE) else NO_ROOM

    rng = np.random.default_rng(0)
    spec = GridSpec(0.0, 0.0, 0.05, 120, 160)
    labels = np.full((120, 160), NO_ROOM, np.int32)
    labels[5:60, 5:80], labels[5:60, 84:155], labels[64:115, 5:155] = 0, 1, 2
    labels[:, :3] = OUTSIDE
    for _ in range(200):
        mask = np.zeros_like(labels, bool)
        r, c = rng.integers(0, 120), rng.integers(0, 160)
        mask[r : r + rng.integers(1, 6), c : c + rng.integers(1, 6)] = True
        assert assign_to_room(mask, labels, spec) == whole_grid(mask, labels, spec), (r, c)
