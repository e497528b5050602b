"""A tiny hand-built BimPrior with exact geometry: two rooms split by a wall (optionally with a doorway).

The building is the box x ∈ [0, 12], y ∈ [0, 6] m with 0.2 m walls; the dividing wall is x ∈ [6.0, 6.2], its
doorway (when present) y ∈ [2.5, 3.5]. Room A (west) has id 2·storey, room B (east) 2·storey + 1.
Embeddings are one-hot per label, so cos(f, C) is exactly 1 for the same label and 0 otherwise.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from bimfactor.bim.grid import GridSpec
from bimfactor.bim.ifc import Storey
from bimfactor.bim.prior import BimObject, BimPrior, StoreyLayers
from bimfactor.bim.rooms import NO_ROOM, OUTSIDE
from bimfactor.types import Observations

RESOLUTION_M = 0.05
ROBOT_RADIUS_M = 0.25
LABELS = ("chair", "table", "window", "cabinet", "bookshelf")
WALL_M = 0.2
DIVIDER_X = (6.0, 6.2)
DOOR_Y = (2.5, 3.5)

# (label, x, y, size x, size y) per storey; storey 1 has a table with a chair beside it in room A, a pair that
# storey 0 (a chair in room A, a table in room B) cannot show.
OBJECTS = {
    0: [
        ("chair", 3.0, 3.0, 0.5, 0.5),
        ("table", 9.0, 3.0, 1.2, 0.8),
        ("window", 3.0, 0.1, 1.0, 0.06),
        ("cabinet", 1.0, 5.0, 0.6, 0.6),
        ("bookshelf", 11.0, 1.0, 0.35, 1.0),
    ],
    1: [
        ("table", 3.0, 3.0, 1.2, 0.8),
        ("chair", 2.0, 3.8, 0.5, 0.5),
    ],
}


def embedding(label: str) -> np.ndarray:
    """(D,) one-hot unit vector of a label."""
    out = np.zeros(len(LABELS), np.float32)
    out[LABELS.index(label)] = 1.0
    return out


def make_prior(with_door: bool = False, n_storeys: int = 1) -> BimPrior:
    """The two-room box on `n_storeys` identical storeys (objects per storey from OBJECTS)."""
    spec = GridSpec(-1.0, -1.0, RESOLUTION_M, rows=160, cols=280)  # x ∈ [-1, 13], y ∈ [-1, 7]
    rc = np.indices(spec.shape).reshape(2, -1).T
    x, y = spec.cell_to_world(rc).T
    x, y = x.reshape(spec.shape), y.reshape(spec.shape)
    inside_box = (x > 0) & (x < 12) & (y > 0) & (y < 6)
    interior = (x > WALL_M) & (x < 12 - WALL_M) & (y > WALL_M) & (y < 6 - WALL_M)
    divider = (x > DIVIDER_X[0]) & (x < DIVIDER_X[1])
    door = divider & (y > DOOR_Y[0]) & (y < DOOR_Y[1]) if with_door else np.zeros_like(divider)
    structure = (inside_box & ~interior) | (divider & ~door & inside_box)
    clearance = (ndimage.distance_transform_edt(~structure) * RESOLUTION_M).astype(np.float32)
    storeys, objects = [], []
    for s in range(n_storeys):
        labels = np.full(spec.shape, OUTSIDE, np.int32)
        labels[inside_box] = NO_ROOM
        labels[interior & (x < DIVIDER_X[0])] = 2 * s
        labels[interior & (x > DIVIDER_X[1])] = 2 * s + 1
        labels[door & interior] = 2 * s
        navigable = (labels >= 0) & (clearance >= ROBOT_RADIUS_M)
        layers = StoreyLayers(
            Storey(s, f"storey-{s}", f"Level {s}", 3.0 * s),
            structure.copy(),
            np.zeros(spec.shape, bool),
            clearance.copy(),
            labels,
            navigable,
        )
        storeys.append(layers)
        for label, ox, oy, sx, sy in OBJECTS[s]:
            objects.append(
                BimObject(
                    id=len(objects),
                    guid=f"obj-{len(objects)}",
                    ifc_class="IfcFurniture",
                    label=label,
                    label_source="test",
                    raw_text=label,
                    storey_index=s,
                    room_id=2 * s + (ox > DIVIDER_X[1]),
                    position_m=(ox, oy, 0.5),
                    size_m=(sx, sy, 1.0),
                )
            )
    return BimPrior(
        source_file="handmade",
        source_sha256="",
        schema="test",
        embedding_model="one-hot",
        grid=spec,
        storeys=storeys,
        rooms=[],
        doors=[],
        objects=objects,
        object_embeddings=np.stack([embedding(o.label) for o in objects]),
        room_edges=[],
        object_edges=[],
    )


def object_id(prior: BimPrior, label: str, storey: int = 0) -> int:
    """Id of the (only) object with this label on a storey."""
    (found,) = [o.id for o in prior.objects if o.label == label and o.storey_index == storey]
    return found


def observe(*items: tuple[str, float, float]) -> Observations:
    """Observations of (label, range m, bearing rad) with exact one-hot embeddings."""
    labels = [label for label, _, _ in items]
    return Observations(
        np.stack([embedding(label) for label in labels]),
        np.array([r for _, r, _ in items]),
        np.array([b for _, _, b in items]),
        labels=labels,
    )
