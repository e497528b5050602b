"""Hand-picked drives of the paper floor: arcs around its furniture groups, the camera looking at each group."""

from __future__ import annotations

import numpy as np

from bimfactor.perception.scenes import FurnitureGroup, orbit_poses

MEETING_TABLE = FurnitureGroup((79.87, 22.45), 3.0, 180.0, 300.0)  # a table and four chairs, from west and south
KITCHEN_TABLE = FurnitureGroup((64.10, 3.73), 3.0, 20.0, 160.0)  # a table and two chairs, seen from the north
LIVING_CORNER = FurnitureGroup((30.58, 3.71), 3.0, 95.0, 265.0)  # a sofa and a table against the study wall
OFFICE_DESK = FurnitureGroup((37.67, 1.32), 3.0, 20.0, 160.0)  # desk and chair by the south wall
KITCHEN_WALL = FurnitureGroup((59.0, 3.8), 3.0, -70.0, 70.0)  # sink, cabinets, refrigerator by the west wall
GROUPS = (MEETING_TABLE, KITCHEN_TABLE, LIVING_CORNER, OFFICE_DESK, KITCHEN_WALL)


def tour_poses(frames_per_group: int) -> np.ndarray:
    """Every group's arc one after another: (5 · frames_per_group, 3) poses."""
    return np.concatenate([orbit_poses(group, frames_per_group) for group in GROUPS])
