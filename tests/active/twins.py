"""A hand-built storey with twin rooms and one door plate, for active localization.

The box x ∈ [0, 12], y ∈ [0, 10] m with 0.2 m walls, split by a wall at x ∈ [6.0, 6.2] into two units (unit B is
unit A moved 6 m east), each a room to the north and a corridor along the south (y < 3) joined by a 1 m door centred
3 m from the unit's west wall (x = 3.1 and 9.1). The rooms hold the same objects at the same places, so the units are
one view everywhere but one: only room B is numbered ("102"), so its door alone carries a plate, on the corridor side.
Rooms A and B have ids 0 and 1, their corridors 2 and 3.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from bimfactor.bim.grid import GridSpec
from bimfactor.bim.ifc import Storey
from bimfactor.bim.prior import BimObject, BimPrior, Door, Room, StoreyLayers
from bimfactor.bim.rooms import NO_ROOM, OUTSIDE
from tests.localization.handmade import ROBOT_RADIUS_M, embedding

SHIFT_M = 6.0  # room B is room A moved this far east
ROOM_Y = (3.2, 9.8)
DOOR_X = (2.6, 3.6)  # room A's door; room B's is SHIFT_M east
OBJECTS_A = [("chair", 1.5, 7.0, 0.5, 0.5), ("table", 3.0, 8.5, 1.2, 0.8), ("cabinet", 5.2, 5.0, 0.6, 0.6)]


def make_twin_prior() -> BimPrior:
    spec = GridSpec(-1.0, -1.0, 0.05, rows=240, cols=280)  # x ∈ [-1, 13], y ∈ [-1, 11]
    rc = np.indices(spec.shape).reshape(2, -1).T
    x, y = (v.reshape(spec.shape) for v in spec.cell_to_world(rc).T)
    box = (x > 0) & (x < 12) & (y > 0) & (y < 10)
    interior = (x > 0.2) & (x < 11.8) & (y > 0.2) & (y < 9.8)
    divider = (x > 6.0) & (x < 6.2)
    front = (y > 3.0) & (y < 3.2)
    doors = ((x > DOOR_X[0]) & (x < DOOR_X[1])) | ((x > DOOR_X[0] + SHIFT_M) & (x < DOOR_X[1] + SHIFT_M))
    structure = box & (~interior | divider | (front & ~doors))
    clearance = (ndimage.distance_transform_edt(~structure) * spec.resolution_m).astype(np.float32)
    labels = np.full(spec.shape, OUTSIDE, np.int32)
    labels[box] = NO_ROOM
    west, east = interior & (x < 6.0), interior & (x > 6.2)
    labels[west & (y < 3.0)] = 2
    labels[east & (y < 3.0)] = 3
    labels[west & (y > 3.2)] = 0
    labels[east & (y > 3.2)] = 1
    labels[front & doors & west] = 2
    labels[front & doors & east] = 3
    navigable = (labels >= 0) & (clearance >= ROBOT_RADIUS_M)
    layers = StoreyLayers(
        Storey(0, "storey-0", "Level 0", 0.0), structure, np.zeros(spec.shape, bool), clearance, labels, navigable
    )
    objects = []
    for shift in (0.0, SHIFT_M):
        for label, ox, oy, sx, sy in OBJECTS_A:
            objects.append(
                BimObject(
                    id=len(objects), guid=f"obj-{len(objects)}", ifc_class="IfcFurniture", label=label,
                    label_source="test", raw_text=label, storey_index=0, room_id=int(shift > 0),
                    position_m=(ox + shift, oy, 0.5), size_m=(sx, sy, 1.0),
                )
            )  # fmt: skip
    rooms = [
        Room(r, 0, "test", 40.0, (3.1 + r * SHIFT_M, 6.5), None, name, "office", 1.0, "", [], number)
        for r, (name, number) in enumerate([("Office A", ""), ("Office B", "102")])
    ]
    rooms += [Room(2 + r, 0, "test", 16.0, (3.1 + r * SHIFT_M, 1.6), None, "Corridor", "hallway", 1.0, "", [], "")
              for r in (0, 1)]  # fmt: skip
    doors = [
        Door(d, "door", f"door-{d}", 0, -1, (3.1 + d * SHIFT_M, 3.1), (1.0, 0.0), 1.0, 0.2, d, 2 + d) for d in (0, 1)
    ]
    return BimPrior(
        source_file="twins",
        source_sha256="",
        schema="test",
        embedding_model="one-hot",
        grid=spec,
        storeys=[layers],
        rooms=rooms,
        doors=doors,
        objects=objects,
        object_embeddings=np.stack([embedding(o.label) for o in objects]),
        room_edges=[],
        object_edges=[],
    )
