"""Hand-picked drives of the paper floor: arcs around its furniture groups, the camera looking at each group."""

from __future__ import annotations

import numpy as np

from bimfactor.perception.scenes import FurnitureGroup, orbit_poses

MEETING_TABLE = FurnitureGroup((75.56, 83.27), 3.2, 200.0, 340.0)  # a table and four chairs by the north wall
KITCHEN_TABLE = FurnitureGroup((56.27, 63.77), 3.0, 100.0, 260.0)  # a table and two chairs, seen from the west
LIVING_CORNER = FurnitureGroup((30.5, 23.6), 3.0, 95.0, 265.0)  # a sofa and a table against the office wall
OFFICE_DESK = FurnitureGroup((50.0, 1.3), 3.5, 20.0, 160.0)  # desk, chair, bookshelves by the south wall
KITCHEN_WALL = FurnitureGroup((28.8, 66.0), 3.0, -70.0, 70.0)  # sink, cabinets, refrigerator by the west wall
GROUPS = (MEETING_TABLE, KITCHEN_TABLE, LIVING_CORNER, OFFICE_DESK, KITCHEN_WALL)


def tour_poses(frames_per_group: int) -> np.ndarray:
    """Every group's arc one after another: (5 · frames_per_group, 3) poses."""
    return np.concatenate([orbit_poses(group, frames_per_group) for group in GROUPS])
