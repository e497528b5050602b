"""Occupancy grid: the band cut, rasterisation, hollow walls, coordinates."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.grid import GridSpec, _clip, band_polygons, build_storey_grid, footprint_mask
from bimfactor.bim.ifc import Mesh, Storey
from tests.bim.geometry import box, two_rooms

SPEC = GridSpec(origin_x=-1.0, origin_y=-1.0, resolution_m=0.05, rows=140, cols=220)
STOREY = Storey(0, "s", "ground", 0.0)


def test_cell_world_round_trip() -> None:
    xy = np.array([[0.0, 0.0], [3.3, 2.1], [-0.99, -0.99]])
    rc = SPEC.world_to_cell(xy)
    np.testing.assert_array_equal(rc[0], [20, 20])
    back = SPEC.cell_to_world(rc)
    assert np.all(np.abs(back - xy) <= SPEC.resolution_m / 2 + 1e-9)
    assert not SPEC.contains(SPEC.world_to_cell(np.array([[-1.5, 0.0]])))[0]


def test_clip_keeps_only_the_band() -> None:
    tri = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 3.0], [0.0, 1.0, 3.0]])
    poly = _clip(_clip(tri, 0.5, above=True), 1.5, above=False)
    assert poly[:, 2].min() == pytest.approx(0.5) and poly[:, 2].max() == pytest.approx(1.5)
    assert len(poly) == 4


def test_wall_footprint_is_rasterised_to_its_box() -> None:
    wall = box("IfcWall", (0.0, 0.0, 0.0), (2.0, 0.2, 2.7))
    mask = footprint_mask(wall, SPEC, 0.1, 1.2)
    rows, cols = np.nonzero(mask)
    xy_lo = SPEC.cell_to_world(np.array([[rows.min(), cols.min()]]))[0]
    xy_hi = SPEC.cell_to_world(np.array([[rows.max(), cols.max()]]))[0]
    np.testing.assert_allclose(xy_lo, [0.025, 0.025], atol=0.051)
    np.testing.assert_allclose(xy_hi, [1.975, 0.175], atol=0.051)
    # Conservative: every touched cell counts, so the area lies between the box's and the box grown by a cell.
    area, res = mask.sum() * SPEC.resolution_m**2, SPEC.resolution_m
    assert 2.0 * 0.2 <= area <= (2.0 + 2 * res) * (0.2 + 2 * res)


def test_geometry_outside_the_band_is_ignored() -> None:
    beam = box("IfcBeam", (0.0, 0.0, 2.3), (2.0, 0.2, 2.6))
    assert band_polygons(beam.mesh, 0.1, 1.2) == []
    grid = build_storey_grid(STOREY, [beam], SPEC, _grid_cfg(), furniture_classes=["IfcFurnishingElement"])
    assert not grid.structure.any()


def test_hollow_wall_outline_is_filled() -> None:
    wall = box("IfcWall", (0.0, 0.0, 0.0), (3.0, 0.4, 2.7))
    vertical = [f for f in wall.mesh.faces if np.ptp(wall.mesh.vertices[f][:, 2]) > 0]  # drop top and bottom
    wall.mesh = Mesh(wall.mesh.vertices, np.asarray(vertical, np.int32))
    grid = build_storey_grid(STOREY, [wall], SPEC, _grid_cfg(), furniture_classes=[])
    centre = SPEC.world_to_cell(np.array([[1.5, 0.2]]))[0]
    assert grid.structure[centre[0], centre[1]]


def test_layers_clearance_and_excluded_doors() -> None:
    elements = [*two_rooms(), box("IfcFurniture", (1.0, 1.0, 0.0), (2.0, 2.0, 0.8))]
    grid = build_storey_grid(STOREY, elements, SPEC, _grid_cfg(), furniture_classes=["IfcFurnishingElement"])
    table = SPEC.world_to_cell(np.array([[1.5, 1.5]]))[0]
    assert grid.furniture[table[0], table[1]] and not grid.structure[table[0], table[1]]
    door = SPEC.world_to_cell(np.array([[4.1, 2.0]]))[0]
    assert not grid.occupied[door[0], door[1]]  # doors are open for the robot
    free = SPEC.world_to_cell(np.array([[3.0, 3.0]]))[0]
    # nearest obstacles: the wall face at x = 4.0 and at y = 4.0, both 1 m away
    assert grid.clearance_m[free[0], free[1]] == pytest.approx(1.0, abs=0.06)


def test_a_window_recess_is_free_above_its_sill() -> None:
    """duplex.ifc's floor-to-ceiling windows: a 3 cm sill lining spans the 0.35 m recess at 0.10–0.13 m, the pane
    stands at the wall's outer face. The scan (from `sensor.min_z_m`) sees the pane; the grid's band starts there
    too, so the recess is free in the grid and the pane is its face."""
    sill = box("IfcWindow", (0.0, 0.0, 0.10), (4.0, 0.35, 0.13))
    pane = box("IfcWindow", (0.0, 0.35, 0.10), (4.0, 0.40, 2.50))
    cfg = _grid_cfg()
    grid = build_storey_grid(STOREY, [sill, pane], SPEC, cfg, furniture_classes=[])
    recess, glass = SPEC.world_to_cell(np.array([[2.0, 0.2], [2.0, 0.375]]))
    assert not grid.structure[recess[0], recess[1]] and grid.structure[glass[0], glass[1]]
    low = build_storey_grid(STOREY, [sill, pane], SPEC, cfg.model_copy(update={"band_min_m": 0.10}), [])
    assert low.structure[recess[0], recess[1]]  # the band from 0.10 m fills the recess the scan sees through


def test_the_scan_may_not_start_above_the_grids_band() -> None:
    from bimfactor.config import load_config
    from bimfactor.errors import ConfigError

    assert load_config().sensor.min_z_m <= load_config().bim.grid.band_min_m
    with pytest.raises(ConfigError, match=r"^config: sensor.min_z_m \(0.3\) is above bim.grid.band_min_m"):
        load_config(overrides=["sensor.min_z_m=0.3"])


def _grid_cfg():
    from bimfactor.config import load_config

    return load_config().bim.grid
