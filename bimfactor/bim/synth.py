"""Procedural IFC4 buildings: one pure-data layout function per preset, one writer that turns it into IFC.

A layout (`BuildingSpec`) is plain dataclasses in world metres: walls as centreline segments, rooms as
clear floor polygons, doors and windows in openings of named walls, and objects as oriented boxes.
`build_ifc` writes it with ifcopenshell's API so that `ifcopenshell.geom` meshes every element.
The same preset and seed always give a byte-identical file.

Presets:
- "paper-floor": the CoarseBIMLoc evaluation floor: 86 x 86 m, 7 rooms, 43 objects in 14 categories.
- "office": a corridor with 8 identical offices, a kitchen and a bathroom (the ambiguity stress case).
- "multi-storey": three storeys (0, 3 and 6 m) with different layouts.
- "lift-house": two small storeys (0 and 3 m) joined by a lift (an IfcTransportElement through both) at the west end
  of their corridors.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import uuid
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import ifcopenshell
import ifcopenshell.api.aggregate
import ifcopenshell.api.context
import ifcopenshell.api.feature
import ifcopenshell.api.geometry
import ifcopenshell.api.root
import ifcopenshell.api.spatial
import ifcopenshell.api.unit
import ifcopenshell.guid
import numpy as np
from ifcopenshell.util.shape_builder import ShapeBuilder

from bimfactor.errors import InputError
from bimfactor.io.atomic import atomic_path, check_output_file

log = logging.getLogger(__name__)

Point = tuple[float, float]
Box = tuple[float, float, float, float]  # x_min, y_min, x_max, y_max

ORIGINATING_SYSTEM = "bimfactor.bim.synth"  # the IFC header's originating system: what `synth` recognises as its own

WALL_THICKNESS_M = 0.2
WALL_HEIGHT_M = 2.8
STOREY_HEIGHT_M = 3.0
DOOR_HEIGHT_M = 2.1
ENTRANCE_WIDTH_M = 1.2
DOOR_LEAF_THICKNESS_M = 0.05
WINDOW_SILL_M = 0.9
WINDOW_HEIGHT_M = 1.2
WINDOW_PANE_THICKNESS_M = 0.06
OPENING_OVERCUT_M = 0.05  # an opening reaches this far beyond each wall face so the cut goes fully through
MIN_WALL_GAP_M = 0.2  # every object keeps at least this distance from every wall face
WALL_CLEARANCE_M = (0.25, 0.4)  # range of the gap between a wall-standing object and its wall
OBJECT_GAP_M = 0.3  # free space between objects of different groups
DOOR_KEEPOUT_DEPTH_M = 1.2  # no object within this distance of a door, on either side of its wall
DOOR_KEEPOUT_SIDE_M = 0.3  # ... nor this far beyond the door's jambs
OPENING_END_MARGIN_M = 0.4  # a door or window keeps this distance from the room's corners
HEADER_TIME_STAMP = "2000-01-01T00:00:00"
_GUID_STREAM = 0x1FC6  # second entropy word for the GlobalId stream, apart from the layout stream
_PLACEMENT_ATTEMPTS = 500


# ----------------------------------------------------------------------------------------------------------
# Layout data


@dataclass(frozen=True)
class WallSpec:
    """A straight wall: centreline `start`→`end` (world xy, m), already extended to overlap at corners."""

    start: Point
    end: Point
    thickness: float
    height: float
    exterior: bool

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)

    @property
    def yaw(self) -> float:
        return math.atan2(self.end[1] - self.start[1], self.end[0] - self.start[0])


@dataclass(frozen=True)
class RoomSpec:
    """A room: `name` is its number ("R01"), `polygon` its clear floor outline (CCW, world xy, m)."""

    name: str
    room_type: str
    polygon: tuple[Point, ...]


@dataclass(frozen=True)
class DoorSpec:
    """A door in wall `wall_index`, centred on the wall's centreline at `center`; `rooms` it connects."""

    name: str
    wall_index: int
    center: Point
    width: float
    height: float
    rooms: tuple[str, ...]  # two room names, or one for a door to the outside


@dataclass(frozen=True)
class WindowSpec:
    """A window in exterior wall `wall_index` at `center` (on the centreline), its bottom at `sill_height`."""

    name: str
    wall_index: int
    center: Point
    width: float
    height: float
    sill_height: float
    room: str


@dataclass(frozen=True)
class ObjectSpec:
    """A box-shaped object standing on the floor of room `room`.

    `size` is (length along the object's local x, depth along local y, height) in metres; `yaw` turns local x
    from world x; the object's front faces its local +y.
    """

    ifc_class: str
    name: str
    predefined_type: str
    category: str
    room: str
    center: Point
    yaw: float
    size: tuple[float, float, float]


@dataclass(frozen=True)
class StoreySpec:
    """One storey: everything on it is given in world xy; z is relative to `elevation`."""

    name: str
    elevation: float
    height: float
    walls: tuple[WallSpec, ...]
    rooms: tuple[RoomSpec, ...]
    doors: tuple[DoorSpec, ...]
    windows: tuple[WindowSpec, ...]
    objects: tuple[ObjectSpec, ...]


@dataclass(frozen=True)
class BuildingSpec:
    """A whole building layout, the input of `build_ifc`; `seed` also seeds the IFC GlobalIds."""

    name: str
    preset: str
    seed: int
    storeys: tuple[StoreySpec, ...]

    def object_counts(self) -> dict[str, int]:
        """Objects per category over all storeys, windows and doors included (the paper's counting)."""
        counts: Counter[str] = Counter()
        for storey in self.storeys:
            counts.update(obj.category for obj in storey.objects)
            counts["window"] += len(storey.windows)
            counts["door"] += len(storey.doors)
        return dict(sorted(counts.items()))


# ----------------------------------------------------------------------------------------------------------
# Object catalogue: the one table of kinds, their IFC class, name and size


@dataclass(frozen=True)
class _Kind:
    category: str
    ifc_class: str
    name: str
    predefined_type: str
    size: tuple[float, float, float]


OBJECT_KINDS: dict[str, _Kind] = {
    "bed": _Kind("bed", "IfcFurniture", "Bed", "BED", (2.0, 1.6, 0.5)),
    "chair": _Kind("chair", "IfcFurniture", "Chair", "CHAIR", (0.5, 0.5, 0.9)),
    "table": _Kind("table", "IfcFurniture", "Table", "TABLE", (1.6, 0.9, 0.75)),
    "meeting table": _Kind("table", "IfcFurniture", "Table", "TABLE", (3.0, 1.2, 0.75)),
    "desk": _Kind("desk", "IfcFurniture", "Desk", "DESK", (1.4, 0.7, 0.75)),
    "sofa": _Kind("sofa", "IfcFurniture", "Sofa", "SOFA", (2.0, 0.9, 0.85)),
    "bookshelf": _Kind("bookshelf", "IfcFurniture", "Bookshelf", "SHELF", (1.0, 0.35, 1.8)),
    "cabinet": _Kind("cabinet", "IfcFurniture", "Cabinet", "USERDEFINED", (0.6, 0.6, 0.9)),
    "refrigerator": _Kind("refrigerator", "IfcFurniture", "Refrigerator", "USERDEFINED", (0.7, 0.7, 1.8)),
    "water closet": _Kind("water closet", "IfcSanitaryTerminal", "Water closet", "TOILETPAN", (0.4, 0.7, 0.8)),
    "sink": _Kind("sink", "IfcSanitaryTerminal", "Sink", "WASHHANDBASIN", (0.6, 0.45, 0.85)),
    "kitchen sink": _Kind("sink", "IfcSanitaryTerminal", "Sink", "SINK", (0.8, 0.6, 0.9)),
    "bathtub": _Kind("bathtub", "IfcSanitaryTerminal", "Bathtub", "BATH", (1.7, 0.75, 0.6)),
    "fire hydrant": _Kind("fire hydrant", "IfcFireSuppressionTerminal", "Fire hydrant", "FIREHYDRANT", (0.5, 0.3, 1.0)),
}

# The paper's 14 object categories (windows and doors count as objects).
OBJECT_CATEGORIES = (
    "bed",
    "chair",
    "table",
    "desk",
    "sofa",
    "bookshelf",
    "cabinet",
    "refrigerator",
    "water closet",
    "sink",
    "bathtub",
    "fire hydrant",
    "window",
    "door",
)


@dataclass(frozen=True)
class _Item:
    """One object of a group, at (dx, dy) in the group frame, turned by dyaw."""

    kind: str
    dx: float
    dy: float
    dyaw: float = 0.0


@dataclass(frozen=True)
class _Group:
    """Objects placed together. Against a wall the group frame's x runs along the wall, +y into the room.

    `anchor` (x, y, yaw in the room frame) fixes the group's frame instead of a random placement.
    """

    items: tuple[_Item, ...]
    against_wall: bool
    anchor: tuple[float, float, float] | None = None


_HALF_PI = math.pi / 2


def _against_wall(kind: str) -> _Group:
    """A single object with its back to a wall."""
    return _Group((_Item(kind, 0.0, OBJECT_KINDS[kind].size[1] / 2),), against_wall=True)


def _row(*kinds: str, gap: float = 0.05) -> _Group:
    """Objects side by side along a wall (a kitchen counter row)."""
    widths = [OBJECT_KINDS[k].size[0] for k in kinds]
    x = -(sum(widths) + gap * (len(kinds) - 1)) / 2
    items = []
    for kind, width in zip(kinds, widths, strict=True):
        items.append(_Item(kind, x + width / 2, OBJECT_KINDS[kind].size[1] / 2))
        x += width + gap
    return _Group(tuple(items), against_wall=True)


_BED = _Group((_Item("bed", 0.0, 1.0, _HALF_PI),), against_wall=True)  # headboard against the wall
_CABINET = _against_wall("cabinet")
_KITCHEN_ROW = _row("refrigerator", "cabinet", "cabinet", "kitchen sink")
_DINING = _Group(
    (_Item("table", 0.0, 0.0), _Item("chair", 0.0, -0.8), _Item("chair", 0.0, 0.8, math.pi)),
    against_wall=False,
)
_MEETING = _Group(
    (
        _Item("meeting table", 0.0, 0.0),
        _Item("chair", -0.75, -1.0),
        _Item("chair", 0.75, -1.0),
        _Item("chair", -0.75, 1.0, math.pi),
        _Item("chair", 0.75, 1.0, math.pi),
    ),
    against_wall=False,
)
_SOFA_TABLE = _Group((_Item("sofa", 0.0, 0.45), _Item("table", 0.0, 1.85)), against_wall=True)
_SOFA = _against_wall("sofa")
_DESK_CHAIR = _Group((_Item("desk", 0.0, 0.35), _Item("chair", 0.0, 1.3, math.pi)), against_wall=True)
_BOOKSHELF = _against_wall("bookshelf")
_WATER_CLOSET = _against_wall("water closet")
_SINK = _against_wall("sink")
_BATHTUB = _against_wall("bathtub")
_FIRE_HYDRANT = _against_wall("fire hydrant")

# Default furnishing per room type; groups are placed in this order.
ROOM_CONTENTS: dict[str, tuple[_Group, ...]] = {
    "bedroom": (_BED, _CABINET),
    "kitchen": (_KITCHEN_ROW, _DINING),
    "meeting room": (_MEETING,),
    "living room": (_SOFA_TABLE, _SOFA),
    "study room": (_DESK_CHAIR, _DESK_CHAIR, _BOOKSHELF, _BOOKSHELF),
    "bathroom": (_BATHTUB, _WATER_CLOSET, _SINK),
    "hallway": (_FIRE_HYDRANT, _FIRE_HYDRANT),
    "office": (_DESK_CHAIR, _BOOKSHELF, _CABINET),
}

# The office preset's fixed arrangement, in the room frame (x along the corridor wall from the room's left
# interior corner, y away from the corridor; interior 4.8 x 5.8 m, door centred at x = 0.9).
_OFFICE_DOOR_OFFSET_M = 0.9
_OFFICE_FIXED = (
    dataclasses.replace(_DESK_CHAIR, anchor=(2.4, 5.5, math.pi)),
    dataclasses.replace(_BOOKSHELF, anchor=(0.3, 3.2, -_HALF_PI)),
    dataclasses.replace(_CABINET, anchor=(4.5, 2.2, _HALF_PI)),
)
_ANCHOR_JITTER_M = 0.05


# ----------------------------------------------------------------------------------------------------------
# Rectilinear geometry helpers


def _r(value: float) -> float:
    """Round a coordinate to 0.1 mm so that files stay tidy."""
    return round(float(value), 4) + 0.0  # + 0.0 turns -0.0 into 0.0


def _simplify(points: Sequence[Point]) -> list[Point]:
    """Drop repeated and collinear vertices of a closed polygon."""
    pts = [p for i, p in enumerate(points) if math.dist(p, points[i - 1]) > 1e-9]
    changed = True
    while changed and len(pts) > 3:
        changed = False
        for i in range(len(pts)):
            a, b, c = pts[i - 1], pts[i], pts[(i + 1) % len(pts)]
            if abs((b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0])) < 1e-12:
                del pts[i]
                changed = True
                break
    return pts


def _inset(polygon: Sequence[Point], distance: float) -> tuple[Point, ...]:
    """Move every edge of a CCW axis-aligned polygon inward by `distance`."""
    out = []
    for i, cur in enumerate(polygon):
        x = y = 0.0
        for a, b in ((polygon[i - 1], cur), (cur, polygon[(i + 1) % len(polygon)])):
            length = math.dist(a, b)
            normal = (-(b[1] - a[1]) / length, (b[0] - a[0]) / length)  # left of a CCW edge = inward
            if abs(a[1] - b[1]) < 1e-9:
                y = a[1] + normal[1] * distance
            else:
                x = a[0] + normal[0] * distance
        out.append((_r(x), _r(y)))
    return tuple(out)


def _point_in_polygon(point: Point, polygon: Sequence[Point]) -> bool:
    """Even-odd ray casting."""
    x, y = point
    inside = False
    for i, (x1, y1) in enumerate(polygon):
        x0, y0 = polygon[i - 1]
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def _box_in_polygon(box: Box, polygon: Sequence[Point]) -> bool:
    """Whether an axis-aligned box lies inside an axis-aligned polygon (touching the boundary is inside)."""
    x0, y0, x1, y1 = box
    if not _point_in_polygon(((x0 + x1) / 2, (y0 + y1) / 2), polygon):
        return False
    for i, b in enumerate(polygon):
        a = polygon[i - 1]
        if abs(a[1] - b[1]) < 1e-9:  # horizontal edge
            if y0 < a[1] < y1 and min(a[0], b[0]) < x1 and max(a[0], b[0]) > x0:
                return False
        elif x0 < a[0] < x1 and min(a[1], b[1]) < y1 and max(a[1], b[1]) > y0:
            return False
    return True


def _boxes_overlap(a: Box, b: Box) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _grow(box: Box, margin: float) -> Box:
    return (box[0] - margin, box[1] - margin, box[2] + margin, box[3] + margin)


def _footprint(center: Point, yaw: float, length: float, depth: float) -> Box:
    """Axis-aligned bounding box of a rotated rectangle."""
    c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
    hx, hy = (c * length + s * depth) / 2, (s * length + c * depth) / 2
    return (center[0] - hx, center[1] - hy, center[0] + hx, center[1] + hy)


def _to_world(frame: tuple[float, float, float], x: float, y: float) -> Point:
    """A point given in a frame (origin x, origin y, yaw) in world coordinates."""
    ox, oy, yaw = frame
    c, s = math.cos(yaw), math.sin(yaw)
    return (ox + c * x - s * y, oy + s * x + c * y)


def _walls_from_polygons(
    polygons: Sequence[Sequence[Point]], thickness: float, height: float, outline: Box
) -> tuple[WallSpec, ...]:
    """One wall per maximal run of polygon edges on a line, extended by half a thickness at both ends."""
    runs: dict[tuple[str, float], list[tuple[float, float]]] = {}
    for polygon in polygons:
        for i, b in enumerate(polygon):
            a = polygon[i - 1]
            if abs(a[1] - b[1]) < 1e-9:
                key, lo, hi = ("h", _r(a[1])), min(a[0], b[0]), max(a[0], b[0])
            else:
                key, lo, hi = ("v", _r(a[0])), min(a[1], b[1]), max(a[1], b[1])
            runs.setdefault(key, []).append((lo, hi))
    walls = []
    for (axis, coord), intervals in sorted(runs.items()):
        merged: list[list[float]] = []
        for lo, hi in sorted(intervals):
            if merged and lo <= merged[-1][1] + 1e-9:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        for lo, hi in merged:
            lo, hi = _r(lo - thickness / 2), _r(hi + thickness / 2)
            if axis == "h":
                start, end = (lo, coord), (hi, coord)
                exterior = coord in (_r(outline[1]), _r(outline[3]))
            else:
                start, end = (coord, lo), (coord, hi)
                exterior = coord in (_r(outline[0]), _r(outline[2]))
            walls.append(WallSpec(start, end, thickness, height, exterior))
    return tuple(walls)


def _wall_at(walls: Sequence[WallSpec], center: Point, width: float) -> int:
    """Index of the wall whose centreline holds an opening of `width` centred at `center`."""
    for index, wall in enumerate(walls):
        (x0, y0), (x1, y1) = wall.start, wall.end
        if abs(y0 - y1) < 1e-9 and abs(center[1] - y0) < 1e-6:
            lo, hi, along = x0, x1, center[0]
        elif abs(x0 - x1) < 1e-9 and abs(center[0] - x0) < 1e-6:
            lo, hi, along = y0, y1, center[1]
        else:
            continue
        if lo + wall.thickness <= along - width / 2 and along + width / 2 <= hi - wall.thickness:
            return index
    raise RuntimeError(f"synth layout bug: no wall holds an opening of {width} m at {center}")


def _door_keepout(door: DoorSpec, wall: WallSpec) -> Box:
    """The floor area in front of and behind a door that objects must leave free."""
    along = door.width / 2 + DOOR_KEEPOUT_SIDE_M
    x, y = door.center
    if abs(wall.start[1] - wall.end[1]) < 1e-9:  # wall along x
        return (x - along, y - DOOR_KEEPOUT_DEPTH_M, x + along, y + DOOR_KEEPOUT_DEPTH_M)
    return (x - DOOR_KEEPOUT_DEPTH_M, y - along, x + DOOR_KEEPOUT_DEPTH_M, y + along)


# ----------------------------------------------------------------------------------------------------------
# Object placement


def _group_objects(group: _Group, frame: tuple[float, float, float], room: str) -> list[ObjectSpec]:
    """The group's objects with the group frame at `frame` (x, y, yaw in world)."""
    objects = []
    for item in group.items:
        kind = OBJECT_KINDS[item.kind]
        cx, cy = _to_world(frame, item.dx, item.dy)
        yaw = math.remainder(frame[2] + item.dyaw, math.tau)
        objects.append(
            ObjectSpec(
                ifc_class=kind.ifc_class,
                name=kind.name,
                predefined_type=kind.predefined_type,
                category=kind.category,
                room=room,
                center=(_r(cx), _r(cy)),
                yaw=round(yaw, 6) + 0.0,
                size=kind.size,
            )
        )
    return objects


def _fits(objects: Sequence[ObjectSpec], polygon: Sequence[Point], keepouts: Sequence[Box]) -> bool:
    """Whether objects stand inside the room, clear of its walls, the doors and the objects placed so far."""
    for obj in objects:
        box = _footprint(obj.center, obj.yaw, obj.size[0], obj.size[1])
        if not _box_in_polygon(_grow(box, MIN_WALL_GAP_M), polygon):
            return False
        if any(_boxes_overlap(box, keepout) for keepout in keepouts):
            return False
    return True


def _wall_frame(group: _Group, polygon: Sequence[Point], rng: np.random.Generator) -> tuple[float, float, float] | None:
    """A random frame for a group standing against one of the room's walls, or None if none is long enough."""
    x_lo = min(_footprint((i.dx, i.dy), i.dyaw, *OBJECT_KINDS[i.kind].size[:2])[0] for i in group.items)
    x_hi = max(_footprint((i.dx, i.dy), i.dyaw, *OBJECT_KINDS[i.kind].size[:2])[2] for i in group.items)
    spans = []
    for i, b in enumerate(polygon):
        a = polygon[i - 1]
        length = math.dist(a, b)
        lo, hi = WALL_CLEARANCE_M[0] - x_lo, length - WALL_CLEARANCE_M[0] - x_hi
        spans.append((a, b, length, lo, max(hi - lo, 0.0)))
    weights = np.array([span[4] for span in spans])
    if weights.sum() <= 0.0:
        return None
    a, b, length, lo, free = spans[int(rng.choice(len(spans), p=weights / weights.sum()))]
    direction = ((b[0] - a[0]) / length, (b[1] - a[1]) / length)
    yaw = math.atan2(direction[1], direction[0])
    along = lo + rng.uniform(0.0, free)
    gap = rng.uniform(*WALL_CLEARANCE_M)
    return (*_to_world((a[0], a[1], yaw), along, gap), yaw)


def _place_groups(
    groups: Sequence[_Group],
    room: RoomSpec,
    room_frame: tuple[float, float, float],
    keepouts: list[Box],
    rng: np.random.Generator,
) -> list[ObjectSpec]:
    """Place a room's groups one after the other; each placed group becomes a keep-out for the next."""
    xs = [p[0] for p in room.polygon]
    ys = [p[1] for p in room.polygon]
    placed: list[ObjectSpec] = []
    for group in groups:
        for _ in range(_PLACEMENT_ATTEMPTS):
            if group.anchor is not None:
                ax, ay, ayaw = group.anchor
                jx, jy = rng.uniform(-_ANCHOR_JITTER_M, _ANCHOR_JITTER_M, size=2)
                frame = (*_to_world(room_frame, ax + jx, ay + jy), room_frame[2] + ayaw)
            elif group.against_wall:
                frame = _wall_frame(group, room.polygon, rng)
                if frame is None:
                    break
            else:
                yaw = int(rng.integers(4)) * _HALF_PI + rng.uniform(-0.1, 0.1)
                frame = (rng.uniform(min(xs), max(xs)), rng.uniform(min(ys), max(ys)), yaw)
            objects = _group_objects(group, frame, room.name)
            if _fits(objects, room.polygon, keepouts):
                placed.extend(objects)
                keepouts.extend(_grow(_footprint(o.center, o.yaw, o.size[0], o.size[1]), OBJECT_GAP_M) for o in objects)
                break
        else:
            raise RuntimeError(f"synth layout bug: no room for {group.items[0].kind} in {room.room_type}")
    return placed


# ----------------------------------------------------------------------------------------------------------
# A storey of rooms on both sides of a corridor


@dataclass(frozen=True)
class _RoomPlan:
    """A room of a corridor storey; `width` is centreline to centreline, None = the rest of its side."""

    room_type: str
    width: float | None = None
    depth: float | None = None  # from the exterior wall; shorter than the side leaves the rest to the hallway
    outer_windows: int = 1
    end_window: bool = False
    door_offset: float | None = None  # door centre from the room's left interior corner; None = random
    fixed_windows: bool = False  # centred windows of one width (for identical rooms)
    contents: tuple[_Group, ...] | None = None  # None = ROOM_CONTENTS[room_type]


def _corridor_storey(
    rng: np.random.Generator,
    *,
    name: str,
    elevation: float,
    width: float,
    south_depth: float,
    corridor_width: float,
    north_depth: float,
    south: Sequence[_RoomPlan],
    north: Sequence[_RoomPlan],
    entrance: bool,
    first_room: int = 1,
    first_door: int = 1,
    first_window: int = 1,
    fixtures: Sequence[ObjectSpec] = (),
) -> StoreySpec:
    """Rooms along the south and north exterior walls, a hallway between them reaching every room's door; `fixtures`
    (in the hallway) stand where they are given, kept clear of by everything placed.

    `width` is the outer width in x; depths are centreline distances. The outer wall faces lie at x = 0,
    x = width, y = 0 and y = the sum of the depths plus a wall thickness.
    """
    t = WALL_THICKNESS_M
    x_west, x_east = t / 2, width - t / 2
    y_south = t / 2
    y_corridor_s = y_south + south_depth
    y_corridor_n = y_corridor_s + corridor_width
    y_north = y_corridor_n + north_depth
    outline = (x_west, y_south, x_east, y_north)

    # Centreline rectangles per room, and the hallway as what the rooms leave between them.
    plans: list[tuple[_RoomPlan, str, tuple[float, float, float, float]]] = []
    for side, row, side_depth in (("south", south, south_depth), ("north", north, north_depth)):
        x = x_west
        for i, plan in enumerate(row):
            x_end = x_east if i == len(row) - 1 else x + float(plan.width or 0.0)
            depth = plan.depth or side_depth
            y0, y1 = (y_south, y_south + depth) if side == "south" else (y_north - depth, y_north)
            plans.append((plan, side, (x, y0, x_end, y1)))
            x = x_end
    south_rects = [rect for _, side, rect in plans if side == "south"]
    north_rects = [rect for _, side, rect in plans if side == "north"]
    hall_outline: list[Point] = []
    for x0, _, x1, y1 in south_rects:
        hall_outline += [(x0, y1), (x1, y1)]
    for x0, y0, x1, _ in reversed(north_rects):
        hall_outline += [(x1, y0), (x0, y0)]
    hall_outline = _simplify(hall_outline)

    centrelines = [[(x0, y0), (x1, y0), (x1, y1), (x0, y1)] for _, _, (x0, y0, x1, y1) in plans] + [hall_outline]
    walls = _walls_from_polygons(centrelines, t, WALL_HEIGHT_M, outline)

    rooms = [
        RoomSpec(f"R{first_room + i:02d}", plan.room_type, _inset(centre, t / 2))
        for i, ((plan, _, _), centre) in enumerate(zip(plans, centrelines[:-1], strict=True))
    ]
    hallway = RoomSpec(f"R{first_room + len(plans):02d}", "hallway", _inset(hall_outline, t / 2))

    doors: list[DoorSpec] = []
    windows: list[WindowSpec] = []
    room_frames: list[tuple[float, float, float]] = []
    for (plan, side, (x0, y0, x1, y1)), room in zip(plans, rooms, strict=True):
        # Room frame: origin at the interior corner left of the door wall, x along it, y off the hallway.
        if side == "south":
            frame, door_y = (x1 - t / 2, y1 - t / 2, math.pi), y1
        else:
            frame, door_y = (x0 + t / 2, y0 + t / 2, 0.0), y0
        room_frames.append(frame)
        inner = x1 - x0 - t  # interior width along the door wall
        if plan.door_offset is not None:  # identical rooms: one door width and place
            door_width, offset = 0.9, plan.door_offset
        else:
            door_width = _r(rng.uniform(0.9, 1.2))
            margin = OPENING_END_MARGIN_M + door_width / 2
            offset = rng.uniform(margin, inner - margin)
        door_center = (_r(_to_world(frame, offset, 0.0)[0]), _r(door_y))
        doors.append(
            DoorSpec(
                f"D{first_door + len(doors):02d}",
                _wall_at(walls, door_center, door_width),
                door_center,
                door_width,
                DOOR_HEIGHT_M,
                (room.name, hallway.name),
            )
        )
        # Windows: evenly spread over the outer wall, one more on the end wall of a corner room.
        outer_y = y0 if side == "south" else y1
        windows += _room_windows(
            walls,
            room.name,
            "h",
            (x0, x1),
            outer_y,
            plan.outer_windows,
            first_window + len(windows),
            rng,
            fixed=plan.fixed_windows,
        )
        if plan.end_window:
            end_x = x_west if x0 == x_west else x_east
            win_width = _r(rng.uniform(1.2, 2.0))
            play = max((y1 - y0 - t) / 2 - win_width / 2 - OPENING_END_MARGIN_M, 0.0) / 2
            y = (y0 + y1) / 2 + rng.uniform(-play, play)
            windows.append(_window(walls, (end_x, _r(y)), win_width, room.name, first_window + len(windows)))

    if entrance:
        y_lo = south_rects[0][3] + t / 2
        y_hi = north_rects[0][1] - t / 2
        play = max((y_hi - y_lo) / 2 - ENTRANCE_WIDTH_M / 2 - OPENING_END_MARGIN_M, 0.0) / 2
        center = (x_west, _r((y_lo + y_hi) / 2 + rng.uniform(-play, play)))
        doors.append(
            DoorSpec(
                f"D{first_door + len(doors):02d}",
                _wall_at(walls, center, ENTRANCE_WIDTH_M),
                center,
                ENTRANCE_WIDTH_M,
                DOOR_HEIGHT_M,
                (hallway.name,),
            )
        )

    keepouts = [_door_keepout(door, walls[door.wall_index]) for door in doors]
    keepouts += [_grow(_footprint(f.center, f.yaw, f.size[0], f.size[1]), DOOR_KEEPOUT_DEPTH_M) for f in fixtures]
    objects: list[ObjectSpec] = [dataclasses.replace(f, room=hallway.name) for f in fixtures]
    for (plan, _, _), room, frame in zip(plans, rooms, room_frames, strict=True):
        contents = plan.contents if plan.contents is not None else ROOM_CONTENTS[plan.room_type]
        objects += _place_groups(contents, room, frame, keepouts, rng)
    objects += _place_groups(ROOM_CONTENTS["hallway"], hallway, (0.0, 0.0, 0.0), keepouts, rng)

    storey = StoreySpec(
        name=name,
        elevation=elevation,
        height=STOREY_HEIGHT_M,
        walls=walls,
        rooms=(*rooms, hallway),
        doors=tuple(doors),
        windows=tuple(windows),
        objects=tuple(objects),
    )
    _check_storey(storey)
    return storey


def _window(walls: Sequence[WallSpec], center: Point, width: float, room: str, number: int) -> WindowSpec:
    return WindowSpec(
        f"W{number:02d}",
        _wall_at(walls, center, width),
        center,
        width,
        WINDOW_HEIGHT_M,
        WINDOW_SILL_M,
        room,
    )


def _check_storey(storey: StoreySpec) -> None:
    """Invariants every layout keeps; a failure is a bug in this module, not bad input."""
    rooms = {room.name: room for room in storey.rooms}
    for obj in storey.objects:
        box = _footprint(obj.center, obj.yaw, obj.size[0], obj.size[1])
        if not _box_in_polygon(_grow(box, MIN_WALL_GAP_M - 1e-6), rooms[obj.room].polygon):
            raise RuntimeError(f"synth layout bug: {obj.name} at {obj.center} leaves room {obj.room}")
    for window in storey.windows:
        if not storey.walls[window.wall_index].exterior:
            raise RuntimeError(f"synth layout bug: window {window.name} in an interior wall")
    for wall_index in {d.wall_index for d in storey.doors} | {w.wall_index for w in storey.windows}:
        wall = storey.walls[wall_index]
        spans = sorted(
            (math.dist(wall.start, o.center) - o.width / 2, math.dist(wall.start, o.center) + o.width / 2)
            for o in (*storey.doors, *storey.windows)
            if o.wall_index == wall_index
        )
        if any(b[0] < a[1] + 0.2 for a, b in itertools.pairwise(spans)):
            raise RuntimeError(f"synth layout bug: overlapping openings in wall {wall_index}")


# ----------------------------------------------------------------------------------------------------------
# Presets


def _ccw(polygon: Sequence[Point]) -> list[Point]:
    """The polygon with its vertices in counter-clockwise order."""
    area = sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(polygon, [*polygon[1:], polygon[0]], strict=True))
    return list(polygon) if area > 0 else list(reversed(polygon))


def _room_windows(
    walls: Sequence[WallSpec],
    room: str,
    side: str,
    span: tuple[float, float],
    at: float,
    count: int,
    first: int,
    rng: np.random.Generator,
    fixed: bool = False,
) -> list[WindowSpec]:
    """`count` windows spread over the span (lo, hi centreline) of the exterior wall on line `at` ("h" or "v");
    `fixed`: centred windows of one width (identical rooms)."""
    t = WALL_THICKNESS_M
    slot = (span[1] - span[0] - t) / max(count, 1)
    windows = []
    for k in range(count):
        width = 1.5 if fixed else _r(rng.uniform(1.2, 2.0))
        play = 0.0 if fixed else max(slot / 2 - width / 2 - OPENING_END_MARGIN_M, 0.0) / 2
        along = _r(span[0] + t / 2 + slot * (k + 0.5) + rng.uniform(-play, play))
        center = (along, at) if side == "h" else (at, along)
        windows.append(_window(walls, center, width, room, first + k))
    return windows


def paper_floor(rng: np.random.Generator) -> BuildingSpec:
    """The CoarseBIMLoc floor: 86 x 86 m, 7 rooms, 43 objects in 14 categories.

    A 12 m deep ring around a 62 x 62 m courtyard: a 3.5 m hallway loop along the courtyard, five rooms along the south
    band and a meeting room across the east; the rest of the band is unmodelled (no IfcSpace). The seed moves doors,
    windows and objects.
    """
    t = WALL_THICKNESS_M
    lo, hi = t / 2, 86.0 - t / 2  # outer wall centrelines
    band, ring = 8.5, 12.0  # outer band depth; band + corridor
    b_lo, b_hi = lo + band, hi - band  # the band's inner face (corridor's outer wall)
    c_lo, c_hi = lo + ring, hi - ring  # courtyard walls
    m_y0, m_y1 = 16.1, 28.1  # the meeting room, across the east ring

    south = (("living room", 20.1, 32.1, 2), ("study room", 32.1, 42.1, 1), ("bathroom", 42.1, 48.1, 0),
             ("bedroom", 48.1, 58.1, 1), ("kitchen", 58.1, 70.1, 2))  # fmt: skip
    rects = {f"R{i + 1:02d}": (x0, lo, x1, b_lo) for i, (_, x0, x1, _) in enumerate(south)}
    rects["R06"] = (c_hi, m_y0, hi, m_y1)
    types = {**{f"R{i + 1:02d}": kind for i, (kind, *_rest) in enumerate(south)}, "R06": "meeting room"}
    blocks = [  # unmodelled space of the outer band
        (lo, lo, south[0][1], b_lo),
        (south[-1][2], lo, hi, b_lo),
        (b_hi, b_lo, hi, m_y0),
        (b_hi, m_y1, hi, b_hi),
        (lo, b_hi, hi, hi),
        (lo, b_lo, b_lo, b_hi),
    ]
    outer_loop = [(b_hi, m_y0), (b_hi, b_lo), (b_lo, b_lo), (b_lo, b_hi), (b_hi, b_hi), (b_hi, m_y1)]
    court_loop = [(c_hi, m_y1), (c_hi, c_hi), (c_lo, c_hi), (c_lo, c_lo), (c_hi, c_lo), (c_hi, m_y0)]
    hall = _ccw(outer_loop + court_loop)  # the corridor: a C from the meeting room's south door to its north one
    boxes = [*rects.values(), *blocks]
    centrelines = [_ccw([(x0, y0), (x1, y0), (x1, y1), (x0, y1)]) for x0, y0, x1, y1 in boxes] + [hall]
    walls = list(_walls_from_polygons(centrelines, t, WALL_HEIGHT_M, (lo, lo, hi, hi)))
    for i, wall in enumerate(walls):  # the courtyard's walls are exterior walls too
        (x0, y0), (x1, y1) = wall.start, wall.end
        on_court = (y0 == y1 and y0 in (_r(c_lo), _r(c_hi))) or (x0 == x1 and x0 in (_r(c_lo), _r(c_hi)))
        if on_court:
            walls[i] = dataclasses.replace(wall, exterior=True)

    rooms = [RoomSpec(name, types[name], _inset(_ccw(centrelines[i]), t / 2)) for i, name in enumerate(rects)]
    hallway = RoomSpec("R07", "hallway", _inset(hall, t / 2))

    def door_at(room: str, span: tuple[float, float], at: float, side: str) -> DoorSpec:
        width = _r(rng.uniform(0.9, 1.2))
        margin = t / 2 + OPENING_END_MARGIN_M + width / 2
        along = _r(rng.uniform(span[0] + margin, span[1] - margin))
        center = (along, _r(at)) if side == "h" else (_r(at), along)
        return DoorSpec("", _wall_at(walls, center, width), center, width, DOOR_HEIGHT_M, (room, hallway.name))

    doors = [door_at(name, (x0, x1), b_lo, "h") for name, (x0, _, x1, _) in list(rects.items())[:5]]
    doors += [door_at("R06", (c_hi, b_hi), m_y0, "h"), door_at("R06", (c_hi, b_hi), m_y1, "h")]
    doors = [dataclasses.replace(d, name=f"D{i + 1:02d}") for i, d in enumerate(doors)]

    windows: list[WindowSpec] = []
    for (name, (x0, _, x1, _)), (_, _, _, count) in zip(list(rects.items())[:5], south, strict=True):
        windows += _room_windows(walls, name, "h", (x0, x1), lo, count, len(windows) + 1, rng)
    windows += _room_windows(walls, "R06", "v", (m_y0, m_y1), hi, 2, len(windows) + 1, rng)

    keepouts = [_door_keepout(door, walls[door.wall_index]) for door in doors]
    objects: list[ObjectSpec] = []
    for room in (*rooms, hallway):
        objects += _place_groups(ROOM_CONTENTS[room.room_type], room, (0.0, 0.0, 0.0), keepouts, rng)

    storey = StoreySpec(
        name="Ground floor",
        elevation=0.0,
        height=STOREY_HEIGHT_M,
        walls=tuple(walls),
        rooms=(*rooms, hallway),
        doors=tuple(doors),
        windows=tuple(windows),
        objects=tuple(objects),
    )
    _check_storey(storey)
    return BuildingSpec(name="Paper floor", preset="paper-floor", seed=0, storeys=(storey,))


def office(rng: np.random.Generator) -> BuildingSpec:
    """A 26 x 14.6 m office floor: 8 identical 5 x 6 m offices on both sides of a 2.4 m corridor.

    Every office has a desk with its chair, a bookshelf and a cabinet in the same place relative to its
    door (only a few centimetres of jitter); a kitchen and a bathroom close the two rows.
    """
    office_plan = _RoomPlan(
        "office", 5.0, door_offset=_OFFICE_DOOR_OFFSET_M, fixed_windows=True, contents=_OFFICE_FIXED
    )
    storey = _corridor_storey(
        rng,
        name="Office floor",
        elevation=0.0,
        width=26.2,
        south_depth=6.0,
        corridor_width=2.4,
        north_depth=6.0,
        south=(*[office_plan] * 4, _RoomPlan("bathroom", end_window=True)),
        north=(*[office_plan] * 4, _RoomPlan("kitchen", end_window=True)),
        entrance=True,
    )
    return BuildingSpec(name="Office", preset="office", seed=0, storeys=(storey,))


def multi_storey(rng: np.random.Generator) -> BuildingSpec:
    """Three 24 x 16 m storeys at 0, 3 and 6 m, each with its own room layout around a corridor."""
    layouts = (
        (
            "Level 0",
            (_RoomPlan("living room", 12.0, end_window=True), _RoomPlan("kitchen", end_window=True)),
            (_RoomPlan("bathroom", 6.0, outer_windows=0), _RoomPlan("study room", end_window=True)),
            True,
        ),
        (
            "Level 1",
            (
                _RoomPlan("bedroom", 8.0, end_window=True),
                _RoomPlan("bedroom", 8.0),
                _RoomPlan("bathroom", depth=5.0, end_window=True),
            ),
            (_RoomPlan("bedroom", 10.0, end_window=True), _RoomPlan("study room", outer_windows=2)),
            False,
        ),
        (
            "Level 2",
            (
                _RoomPlan("office", 8.0, end_window=True),
                _RoomPlan("office", 8.0),
                _RoomPlan("office", end_window=True),
            ),
            (_RoomPlan("meeting room", 14.0, outer_windows=2, end_window=True), _RoomPlan("kitchen")),
            False,
        ),
    )
    levels = [dict(name=n, south=s, north=no, entrance=e) for n, s, no, e in layouts]
    storeys = _stacked(rng, levels, width=24.0, south_depth=6.9, corridor_width=2.4, north_depth=6.5)
    return BuildingSpec(name="Multi-storey house", preset="multi-storey", seed=0, storeys=storeys)


def _stacked(rng: np.random.Generator, levels: Sequence[dict], **shared: float) -> tuple[StoreySpec, ...]:
    """Corridor storeys one above the other, `STOREY_HEIGHT_M` apart, numbered on from the storeys below; each level
    its own `_corridor_storey` arguments, `shared` those of all."""
    storeys: list[StoreySpec] = []
    for level, own in enumerate(levels):
        storey = _corridor_storey(
            rng,
            elevation=level * STOREY_HEIGHT_M,
            first_room=1 + sum(len(s.rooms) for s in storeys),
            first_door=1 + sum(len(s.doors) for s in storeys),
            first_window=1 + sum(len(s.windows) for s in storeys),
            **own,
            **shared,
        )
        storeys.append(storey)
    return tuple(storeys)


LIFT_SIZE_M = 1.3  # the lift shaft's side


def lift_house(rng: np.random.Generator) -> BuildingSpec:
    """Two 12 x 12.6 m storeys at 0 and 3 m around a corridor, a lift at its west end stopping at both."""
    shaft = ObjectSpec(
        "IfcTransportElement", "Lift", "ELEVATOR", "elevator", "", (0.2 + MIN_WALL_GAP_M + LIFT_SIZE_M / 2, 6.3), 0.0,
        (LIFT_SIZE_M, LIFT_SIZE_M, STOREY_HEIGHT_M + WALL_HEIGHT_M),
    )  # fmt: skip
    layouts = (
        ("Level 0", ("living room", "kitchen"), ("bathroom", "study room")),
        ("Level 1", ("bedroom", "bathroom"), ("office", "bedroom")),
    )
    # the west rooms' doors open well east of the lift
    levels = [
        dict(
            name=name,
            south=(_RoomPlan(south[0], 6.0, end_window=True, door_offset=1.5), _RoomPlan(south[1], end_window=True)),
            north=(_RoomPlan(north[0], 6.0, end_window=True, door_offset=4.0), _RoomPlan(north[1], end_window=True)),
            entrance=False,
            fixtures=(shaft,) if level == 0 else (),
        )
        for level, (name, south, north) in enumerate(layouts)
    ]
    storeys = _stacked(rng, levels, width=12.0, south_depth=5.0, corridor_width=2.4, north_depth=5.0)
    return BuildingSpec(name="Lift house", preset="lift-house", seed=0, storeys=storeys)


PRESETS: dict[str, Callable[[np.random.Generator], BuildingSpec]] = {
    "paper-floor": paper_floor,
    "office": office,
    "multi-storey": multi_storey,
    "lift-house": lift_house,
}


def make_building(preset: str, seed: int) -> BuildingSpec:
    """The layout of a preset for a seed (no IFC yet); raises InputError for an unknown preset."""
    if preset not in PRESETS:
        raise InputError(f"unknown building preset '{preset}'; valid presets: {', '.join(PRESETS)}")
    spec = PRESETS[preset](np.random.default_rng(seed))
    return dataclasses.replace(spec, preset=preset, seed=seed)


# ----------------------------------------------------------------------------------------------------------
# IFC writer


def _matrix(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    """4x4 placement: translation (x, y, z) and a turn of `yaw` about z."""
    c, s = round(math.cos(yaw), 12) + 0.0, round(math.sin(yaw), 12) + 0.0
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]])


def _box_representation(
    builder: ShapeBuilder,
    body: ifcopenshell.entity_instance,
    corner: Point,
    size: tuple[float, float, float],
    z0: float = 0.0,
) -> ifcopenshell.entity_instance:
    """A body representation: the rectangle at `corner` (local x, y) with `size`, extruded from z0."""
    curve = builder.rectangle(size=(size[0], size[1]), position=corner)
    solid = builder.extrude(builder.profile(curve), magnitude=size[2], position=(0.0, 0.0, z0))
    return builder.get_representation(body, [solid])


def _place(
    file: ifcopenshell.file,
    product: ifcopenshell.entity_instance,
    matrix: np.ndarray,
    representation: ifcopenshell.entity_instance | None = None,
) -> None:
    ifcopenshell.api.geometry.edit_object_placement(file, product=product, matrix=matrix, is_si=True)
    if representation is not None:
        ifcopenshell.api.geometry.assign_representation(file, product=product, representation=representation)


def _write_storey(
    file: ifcopenshell.file,
    body: ifcopenshell.entity_instance,
    ifc_storey: ifcopenshell.entity_instance,
    storey: StoreySpec,
) -> None:
    """Walls with openings, doors and windows filling them, spaces and objects of one storey."""
    create = ifcopenshell.api.root.create_entity
    builder = ShapeBuilder(file)
    z = storey.elevation
    walls = [
        create(file, ifc_class="IfcWall", predefined_type="STANDARD", name=f"Wall {i + 1:02d}")
        for i in range(len(storey.walls))
    ]
    doors = [create(file, ifc_class="IfcDoor", predefined_type="DOOR", name=d.name) for d in storey.doors]
    windows = [create(file, ifc_class="IfcWindow", predefined_type="WINDOW", name=w.name) for w in storey.windows]
    objects = []
    for obj in storey.objects:
        element = create(file, ifc_class=obj.ifc_class, predefined_type=obj.predefined_type, name=obj.name)
        element.ObjectType = obj.category
        objects.append(element)
    ifcopenshell.api.spatial.assign_container(
        file, products=[*walls, *doors, *windows, *objects], relating_structure=ifc_storey
    )
    spaces = []
    for room in storey.rooms:
        space = create(file, ifc_class="IfcSpace", predefined_type="INTERNAL", name=room.name)
        space.LongName = room.room_type
        spaces.append(space)
    ifcopenshell.api.aggregate.assign_object(file, products=spaces, relating_object=ifc_storey)

    for wall, spec in zip(walls, storey.walls, strict=True):
        rep = ifcopenshell.api.geometry.add_wall_representation(
            file,
            context=body,
            length=spec.length,
            height=spec.height,
            thickness=spec.thickness,
            offset=-spec.thickness / 2,
        )
        _place(file, wall, _matrix(*spec.start, z, spec.yaw), rep)

    fillings = [(d, e, 0.0, DOOR_LEAF_THICKNESS_M) for d, e in zip(storey.doors, doors, strict=True)]
    fillings += [(w, e, w.sill_height, WINDOW_PANE_THICKNESS_M) for w, e in zip(storey.windows, windows, strict=True)]
    for spec, element, sill, leaf in fillings:
        wall_spec = storey.walls[spec.wall_index]
        matrix = _matrix(*spec.center, z + sill, wall_spec.yaw)
        depth = wall_spec.thickness + 2 * OPENING_OVERCUT_M
        opening = create(file, ifc_class="IfcOpeningElement", predefined_type="OPENING", name=f"{spec.name} opening")
        ifcopenshell.api.feature.add_feature(file, feature=opening, element=walls[spec.wall_index])
        rep = _box_representation(builder, body, (-spec.width / 2, -depth / 2), (spec.width, depth, spec.height))
        _place(file, opening, matrix, rep)
        ifcopenshell.api.feature.add_filling(file, opening=opening, element=element)
        element.OverallWidth = spec.width
        element.OverallHeight = spec.height
        rep = _box_representation(builder, body, (-spec.width / 2, -leaf / 2), (spec.width, leaf, spec.height))
        _place(file, element, matrix, rep)

    for space, room in zip(spaces, storey.rooms, strict=True):
        curve = builder.polyline([list(p) for p in room.polygon], closed=True)
        solid = builder.extrude(builder.profile(curve), magnitude=WALL_HEIGHT_M)
        _place(file, space, _matrix(0.0, 0.0, z), builder.get_representation(body, [solid]))

    for element, obj in zip(objects, storey.objects, strict=True):
        length, depth, _ = obj.size
        rep = _box_representation(builder, body, (-length / 2, -depth / 2), obj.size)
        _place(file, element, _matrix(*obj.center, z, obj.yaw), rep)


def _sort_unordered_lists(file: ifcopenshell.file) -> None:
    """Order the entity lists that ifcopenshell's API fills from Python sets, whose order varies per run."""
    for entity in file.by_type("IfcUnitAssignment"):
        entity.Units = sorted(entity.Units, key=lambda e: e.id())
    for entity in file.by_type("IfcRelAggregates"):
        entity.RelatedObjects = sorted(entity.RelatedObjects, key=lambda e: e.id())
    for entity in file.by_type("IfcRelContainedInSpatialStructure"):
        entity.RelatedElements = sorted(entity.RelatedElements, key=lambda e: e.id())


def _assign_guids(file: ifcopenshell.file, seed: int) -> None:
    """Replace every GlobalId with one drawn from a generator seeded by the building's seed."""
    rng = np.random.default_rng([_GUID_STREAM, seed])
    for entity in sorted(file.by_type("IfcRoot"), key=lambda e: e.id()):
        entity.GlobalId = ifcopenshell.guid.compress(uuid.UUID(bytes=rng.bytes(16), version=4).hex)


def build_ifc(spec: BuildingSpec) -> ifcopenshell.file:
    """An IFC4 model of the layout: project (metres) > site > building > storeys > walls, spaces, objects."""
    file = ifcopenshell.file(schema="IFC4")
    header = file.header.file_name
    header.name = f"{spec.preset or 'building'}-seed{spec.seed}.ifc"
    header.time_stamp = HEADER_TIME_STAMP
    header.author = ("bimfactor",)
    header.organization = ("bimfactor",)
    header.originating_system = "bimfactor.bim.synth"

    create = ifcopenshell.api.root.create_entity
    project = create(file, ifc_class="IfcProject", name=spec.name)
    project.Description = f"bimfactor synthetic building, preset '{spec.preset}', seed {spec.seed}"
    units = [
        ifcopenshell.api.unit.add_si_unit(file, unit_type="LENGTHUNIT"),
        ifcopenshell.api.unit.add_si_unit(file, unit_type="AREAUNIT"),
        ifcopenshell.api.unit.add_si_unit(file, unit_type="VOLUMEUNIT"),
        ifcopenshell.api.unit.add_si_unit(file, unit_type="PLANEANGLEUNIT"),
    ]
    ifcopenshell.api.unit.assign_unit(file, units=units)
    model = ifcopenshell.api.context.add_context(file, context_type="Model")
    body = ifcopenshell.api.context.add_context(
        file, context_type="Model", context_identifier="Body", target_view="MODEL_VIEW", parent=model
    )

    site = create(file, ifc_class="IfcSite", name="Site")
    building = create(file, ifc_class="IfcBuilding", name=spec.name)
    ifcopenshell.api.aggregate.assign_object(file, products=[site], relating_object=project)
    ifcopenshell.api.aggregate.assign_object(file, products=[building], relating_object=site)
    _place(file, site, _matrix(0.0, 0.0, 0.0))
    _place(file, building, _matrix(0.0, 0.0, 0.0))
    for storey in spec.storeys:
        ifc_storey = create(file, ifc_class="IfcBuildingStorey", name=storey.name)
        ifc_storey.Elevation = storey.elevation
        ifcopenshell.api.aggregate.assign_object(file, products=[ifc_storey], relating_object=building)
        _place(file, ifc_storey, _matrix(0.0, 0.0, storey.elevation))
        _write_storey(file, body, ifc_storey, storey)
    _sort_unordered_lists(file)
    _assign_guids(file, spec.seed)
    return file


def check_synth_output(path: str | Path) -> None:
    """Raise InputError unless `path` may receive a synthetic building: new, or an IFC file that synth wrote."""
    path = Path(path)
    check_output_file(path)
    if path.exists():
        with path.open("rb") as fh:
            head = fh.read(2048)
        if f"'{ORIGINATING_SYSTEM}'".encode() not in head:
            raise InputError(f"{path}: exists and was not written by bimfactor synth; choose a new file name")


def write_building(preset: str, seed: int, path: str | Path) -> BuildingSpec:
    """Generate a preset building and write it atomically as IFC4 to `path`; returns its layout."""
    spec = make_building(preset, seed)
    model = build_ifc(spec)
    with atomic_path(path) as tmp:
        model.write(str(tmp))
    counts = spec.object_counts()
    log.info(
        "wrote %s: preset %s, seed %d, %d storeys, %d rooms, %d objects in %d categories",
        path,
        preset,
        seed,
        len(spec.storeys),
        sum(len(s.rooms) for s in spec.storeys),
        sum(counts.values()),
        len(counts),
    )
    return spec
