"""Door plates: the room number beside a door, as a robot can read it.

An IFC model has no door plates, but the IfcSpace Name holds a room's number where a LongName names it
(`Room.space_number`). The localizer takes each plate to be at its door's centre on the wall face the room is entered
from, and matches readings with the semantic term's tolerances (`localization.measurements.text`); the simulator hangs
it beside the door (`sim.world`).
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

import numpy as np

from bimfactor.bim.prior import BimPrior

DOOR_PLATE_LABEL = "door plate"  # a plate's label; the simulator's instance record also has its "text" and face
PROBE_M = 0.3  # how far beyond a door's faces the room on either side is looked up
PLATE_REACH_M = 0.6  # how far beyond its door's edge the localizer lets a plate hang (pose-graph landmarks)

# Characters that OCR mistakes for one another (the classic confusions of printed text; two characters are
# look-alikes when a group holds both). RapidOCR on the simulator's plates reads "8" for "B", "L" or "I" for "1",
# "O" for "0", "4" for "A" (tools/calibrate_text_reader.py; README).
LOOK_ALIKE_GROUPS = ("0ODQ", "1IJLT7", "2Z", "5S", "6G", "8B3", "4A", "9G", "UV")


@dataclass(frozen=True)
class DoorPlate:
    """The plate of room `room_id` at door `door_id`: its text, where it is read from, which way it faces.

    `xy` is the door's centre on the wall face the plate is on; `normal_xy` the unit normal of that face, out of
    the room (a plate is readable only from where the normal points); `axis_xy` the unit vector along the wall.
    """

    text: str
    room_id: int
    door_id: int
    storey_index: int
    xy: tuple[float, float]
    normal_xy: tuple[float, float]
    axis_xy: tuple[float, float]
    door_width_m: float


def normalise_text(text: str) -> str:
    """What a plate's text is compared by: upper case, letters and digits only ("b-101 " → "B101")."""
    return re.sub(r"[^0-9A-Z]", "", text.upper())


@functools.cache
def look_alikes(char: str) -> str:
    """The characters OCR mistakes `char` for (`LOOK_ALIKE_GROUPS`), in a fixed order; "" for one with none."""
    return "".join(sorted({c for g in LOOK_ALIKE_GROUPS if char in g for c in g} - {char}))


def door_plates(prior: BimPrior) -> list[DoorPlate]:
    """One plate per door into a numbered room, on the face of the door away from the room.

    A door between two numbered rooms names the smaller: one leads from a corridor or hall into an office, not
    the other way. A side is taken to be a room when the room map holds it `PROBE_M` beyond the door's face; a
    door whose sides cannot be told apart gets no plate.
    """
    rooms = {r.id: r for r in prior.rooms if normalise_text(r.space_number)}
    plates: list[DoorPlate] = []
    for door in prior.doors:
        if not door.connects:
            continue
        center, axis = np.asarray(door.center_xy, float), np.asarray(door.axis_xy, float)
        normal = np.array([-axis[1], axis[0]])
        probes = center[None] + np.outer([1.0, -1.0], normal) * (door.depth_m / 2 + PROBE_M)
        plus_side, minus_side = prior.room_at(probes, door.storey_index)
        numbered = [r for r in (door.room_a, door.room_b) if r in rooms]
        for room_id in sorted(numbered, key=lambda r: rooms[r].area_m2)[:1]:
            if (plus_side == room_id) == (minus_side == room_id):
                continue
            out = -normal if plus_side == room_id else normal  # the plate faces away from its room
            xy = center + out * door.depth_m / 2
            plates.append(
                DoorPlate(
                    text=rooms[room_id].space_number,
                    room_id=room_id,
                    door_id=door.id,
                    storey_index=door.storey_index,
                    xy=(float(xy[0]), float(xy[1])),
                    normal_xy=(float(out[0]), float(out[1])),
                    axis_xy=(float(axis[0]), float(axis[1])),
                    door_width_m=float(door.width_m),
                )
            )
    return plates
