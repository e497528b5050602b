"""The procedural IFC4 buildings: structure, counts, determinism, meshable geometry and closed rooms."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import ifcopenshell
import ifcopenshell.geom
import ifcopenshell.util.unit
import numpy as np
import pytest
from matplotlib.path import Path as PolygonPath
from scipy import ndimage

from bimfactor.bim import synth
from bimfactor.errors import InputError

OBJECT_CLASSES = ("IfcFurniture", "IfcSanitaryTerminal", "IfcFireSuppressionTerminal")
MESHED_CLASSES = ("IfcWall", "IfcDoor", "IfcWindow", "IfcSpace", "IfcTransportElement", *OBJECT_CLASSES)
PRESETS = ("paper-floor", "office", "multi-storey", "lift-house")

# preset: (storeys, IfcSpace, IfcDoor, IfcWindow, furniture and terminals)
EXPECTED_COUNTS = {
    "paper-floor": (1, 7, 7, 8, 28),
    "office": (1, 11, 11, 12, 44),
    "multi-storey": (3, 17, 15, 24, 64),
    "lift-house": (2, 10, 8, 16, 34),
}
PAPER_FLOOR_CATEGORIES = {
    "bed": 1,
    "chair": 8,
    "table": 3,
    "desk": 2,
    "sofa": 2,
    "bookshelf": 2,
    "cabinet": 3,
    "refrigerator": 1,
    "water closet": 1,
    "sink": 2,
    "bathtub": 1,
    "fire hydrant": 2,
    "window": 8,
    "door": 7,
}
PAPER_FLOOR_ROOM_TYPES = {
    "bedroom",
    "kitchen",
    "meeting room",
    "living room",
    "study room",
    "hallway",
    "bathroom",
}
GRID_RES_M = 0.1


@dataclass
class Built:
    path: Path
    spec: synth.BuildingSpec
    model: ifcopenshell.file
    meshes: dict[int, tuple[np.ndarray, np.ndarray]]  # product id -> (V, 3) world vertices, (F, 3) faces

    def bounds(self, element: ifcopenshell.entity_instance) -> np.ndarray:
        """(2, 3) min and max corner of an element's mesh."""
        verts = self.meshes[element.id()][0]
        return np.stack([verts.min(axis=0), verts.max(axis=0)])


def _mesh(model: ifcopenshell.file) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    products = [e for cls in (*MESHED_CLASSES, "IfcOpeningElement") for e in model.by_type(cls)]
    iterator = ifcopenshell.geom.iterator(settings, model, 1, include=products)
    meshes = {}
    if iterator.initialize():
        while True:
            shape = iterator.get()
            verts = np.asarray(shape.geometry.verts, dtype=float).reshape(-1, 3)
            faces = np.asarray(shape.geometry.faces, dtype=int).reshape(-1, 3)
            meshes[shape.id] = (verts, faces)
            if not iterator.next():
                break
    return meshes


@pytest.fixture(scope="module", params=PRESETS)
def built(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Built:
    path = tmp_path_factory.mktemp("synth") / f"{request.param}.ifc"
    spec = synth.write_building(request.param, 0, path)
    model = ifcopenshell.open(str(path))
    return Built(path, spec, model, _mesh(model))


@pytest.fixture(scope="module")
def paper(tmp_path_factory: pytest.TempPathFactory) -> Built:
    path = tmp_path_factory.mktemp("paper") / "paper-floor.ifc"
    spec = synth.write_building("paper-floor", 0, path)
    model = ifcopenshell.open(str(path))
    return Built(path, spec, model, _mesh(model))


def _objects(model: ifcopenshell.file) -> list[ifcopenshell.entity_instance]:
    return [e for cls in OBJECT_CLASSES for e in model.by_type(cls)]


def _storey_of(element: ifcopenshell.entity_instance) -> ifcopenshell.entity_instance:
    if element.is_a("IfcSpace"):
        return element.Decomposes[0].RelatingObject
    return element.ContainedInStructure[0].RelatingStructure


def _ray_hits(verts: np.ndarray, faces: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> bool:
    """Whether the segment origin → origin + direction crosses any triangle (Möller–Trumbore)."""
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    return bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)))


def _distance_to_boundary(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N,) distance of (N, 2) points to the edges of a closed polygon."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    ab = b - a
    ap = points[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("nkj,kj->nk", ap, ab) / np.einsum("kj,kj->k", ab, ab), 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2).min(axis=1)


def test_unknown_preset_raises_input_error_listing_the_presets(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"paper-floor.*office.*multi-storey"):
        synth.write_building("castle", 0, tmp_path / "castle.ifc")
    assert not (tmp_path / "castle.ifc").exists()


def test_structure_and_counts(built: Built) -> None:
    model = built.model
    n_storeys, n_spaces, n_doors, n_windows, n_objects = EXPECTED_COUNTS[built.spec.preset]
    assert model.schema == "IFC4"
    assert ifcopenshell.util.unit.calculate_unit_scale(model) == 1.0
    assert not model.by_type("IfcOwnerHistory")
    (project,) = model.by_type("IfcProject")
    (site,) = model.by_type("IfcSite")
    (building,) = model.by_type("IfcBuilding")
    assert site.Decomposes[0].RelatingObject == project
    assert building.Decomposes[0].RelatingObject == site
    body = [c for c in model.by_type("IfcGeometricRepresentationSubContext") if c.ContextIdentifier == "Body"]
    assert len(body) == 1 and body[0].TargetView == "MODEL_VIEW" and body[0].ContextType == "Model"

    storeys = model.by_type("IfcBuildingStorey")
    assert len(storeys) == n_storeys
    assert all(s.Decomposes[0].RelatingObject == building for s in storeys)
    assert sorted(s.Elevation for s in storeys) == pytest.approx([3.0 * i for i in range(n_storeys)])
    assert len(model.by_type("IfcSpace")) == n_spaces
    assert len(model.by_type("IfcDoor")) == n_doors
    assert len(model.by_type("IfcWindow")) == n_windows
    assert len(_objects(model)) == n_objects
    assert len(model.by_type("IfcOpeningElement")) == n_doors + n_windows
    for space in model.by_type("IfcSpace"):
        assert space.Decomposes[0].RelatingObject.is_a("IfcBuildingStorey")
        assert space.Name.startswith("R") and space.LongName
    for element in (*model.by_type("IfcWall"), *model.by_type("IfcDoor"), *model.by_type("IfcWindow")):
        assert element.ContainedInStructure[0].RelatingStructure.is_a("IfcBuildingStorey")
    for element in _objects(model):
        assert element.ContainedInStructure[0].RelatingStructure.is_a("IfcBuildingStorey")
        assert element.ObjectType in synth.OBJECT_CATEGORIES
    guids = [e.GlobalId for e in model.by_type("IfcRoot")]
    assert len(set(guids)) == len(guids)


def test_paper_floor_rooms_and_objects(paper: Built) -> None:
    model = paper.model
    spaces = model.by_type("IfcSpace")
    assert {s.LongName for s in spaces} == PAPER_FLOOR_ROOM_TYPES
    assert sorted(s.Name for s in spaces) == [f"R{i:02d}" for i in range(1, 8)]

    categories = Counter(e.ObjectType for e in _objects(model))
    categories["window"] = len(model.by_type("IfcWindow"))
    categories["door"] = len(model.by_type("IfcDoor"))
    assert dict(categories) == PAPER_FLOOR_CATEGORIES
    assert sum(categories.values()) == 43 and len(categories) == 14
    assert paper.spec.object_counts() == dict(sorted(PAPER_FLOOR_CATEGORIES.items()))

    names = {(e.is_a(), e.Name, e.PredefinedType) for e in _objects(model) if not e.is_a("IfcFurniture")}
    assert ("IfcSanitaryTerminal", "Water closet", "TOILETPAN") in names
    assert ("IfcSanitaryTerminal", "Sink", "WASHHANDBASIN") in names
    assert ("IfcSanitaryTerminal", "Bathtub", "BATH") in names
    assert ("IfcFireSuppressionTerminal", "Fire hydrant", "FIREHYDRANT") in names

    walls = np.stack([paper.bounds(w) for w in model.by_type("IfcWall")])
    extent = walls[:, 1, :2].max(axis=0) - walls[:, 0, :2].min(axis=0)
    assert extent == pytest.approx([86.0, 86.0], abs=2.0)

    # Objects stand where they belong.
    room_of = {room.name: room.room_type for room in paper.spec.storeys[0].rooms}
    where = {(room_of[o.room], o.category) for o in paper.spec.storeys[0].objects}
    for expected in [
        ("bedroom", "bed"),
        ("kitchen", "refrigerator"),
        ("kitchen", "sink"),
        ("bathroom", "water closet"),
        ("bathroom", "bathtub"),
        ("hallway", "fire hydrant"),
        ("study room", "desk"),
        ("study room", "bookshelf"),
        ("meeting room", "table"),
        ("living room", "sofa"),
    ]:
        assert expected in where


def test_same_seed_gives_identical_bytes_other_seed_differs(tmp_path: Path) -> None:
    for preset in PRESETS:
        first = synth.write_building(preset, 7, tmp_path / f"{preset}-a.ifc")
        second = synth.write_building(preset, 7, tmp_path / f"{preset}-b.ifc")
        other = synth.write_building(preset, 8, tmp_path / f"{preset}-c.ifc")
        data = (tmp_path / f"{preset}-a.ifc").read_bytes()
        assert data == (tmp_path / f"{preset}-b.ifc").read_bytes()
        assert data != (tmp_path / f"{preset}-c.ifc").read_bytes()
        assert first == second and first != other
        assert first.object_counts() == other.object_counts()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_every_element_has_a_mesh(built: Built) -> None:
    for cls in MESHED_CLASSES:
        for element in built.model.by_type(cls):
            assert element.id() in built.meshes, f"{cls} {element.Name} has no geometry"
            verts, faces = built.meshes[element.id()]
            assert len(faces) >= 12
            size = verts.max(axis=0) - verts.min(axis=0)
            assert np.all(size > 0.01), f"{cls} {element.Name} is flat: {size}"


def test_doors_fill_openings_that_cut_through_their_wall(built: Built) -> None:
    for door in built.model.by_type("IfcDoor"):
        opening = door.FillsVoids[0].RelatingOpeningElement
        wall = opening.VoidsElements[0].RelatingBuildingElement
        assert wall.is_a("IfcWall")
        door_box, opening_box, wall_box = built.bounds(door), built.bounds(opening), built.bounds(wall)
        assert np.all(door_box[0] < opening_box[1]) and np.all(opening_box[0] < door_box[1])
        assert door_box[1, 2] - door_box[0, 2] == pytest.approx(synth.DOOR_HEIGHT_M)
        assert 0.9 - 1e-6 <= door.OverallWidth <= 1.2 + 1e-6

        # The opening spans the whole wall thickness: a ray across the wall through the door misses it,
        # the same ray just beside the door frame hits it.
        along = int(np.argmax(wall_box[1, :2] - wall_box[0, :2]))
        across = 1 - along
        assert opening_box[0, across] < wall_box[0, across] and opening_box[1, across] > wall_box[1, across]
        centre = (door_box[0] + door_box[1]) / 2
        origin = centre.copy()
        origin[across] = wall_box[0, across] - 0.5
        origin[2] = door_box[0, 2] + 1.0
        segment = np.zeros(3)
        segment[across] = wall_box[1, across] - wall_box[0, across] + 1.0
        verts, faces = built.meshes[wall.id()]
        assert not _ray_hits(verts, faces, origin, segment), f"{door.Name}: the opening does not cut the wall"
        beside = origin.copy()
        beside[along] = door_box[1, along] + 0.1
        beside[2] = door_box[0, 2] + 0.5
        assert _ray_hits(verts, faces, beside, segment)


def test_windows_sit_in_exterior_walls_above_the_sill(built: Built) -> None:
    walls = np.stack([built.bounds(w) for w in built.model.by_type("IfcWall")])
    outline_min, outline_max = walls[:, 0, :2].min(axis=0), walls[:, 1, :2].max(axis=0)
    for window in built.model.by_type("IfcWindow"):
        box = built.bounds(window)
        elevation = _storey_of(window).Elevation
        assert box[0, 2] == pytest.approx(elevation + synth.WINDOW_SILL_M)
        wall = window.FillsVoids[0].RelatingOpeningElement.VoidsElements[0].RelatingBuildingElement
        wall_box = built.bounds(wall)
        on_outline = np.isclose(wall_box[0, :2], outline_min) | np.isclose(wall_box[1, :2], outline_max)
        thin = (wall_box[1, :2] - wall_box[0, :2]) < 0.3
        assert np.any(on_outline & thin), f"window {window.Name} is not in an exterior wall"


def test_objects_lie_inside_their_room_clear_of_walls(built: Built) -> None:
    specs = [(s, obj) for s in built.spec.storeys for obj in s.objects if obj.ifc_class in OBJECT_CLASSES]
    centres = np.array([obj.center for _, obj in specs])
    elements = _objects(built.model)
    assert len(elements) == len(specs)
    for element in elements:
        box = built.bounds(element)
        index = int(np.argmin(np.linalg.norm(centres - (box[0, :2] + box[1, :2]) / 2, axis=1)))
        storey, obj = specs[index]
        assert np.allclose(centres[index], (box[0, :2] + box[1, :2]) / 2, atol=1e-3)
        assert element.Name == obj.name
        assert box[0, 2] == pytest.approx(storey.elevation)
        assert box[1, 2] - box[0, 2] == pytest.approx(obj.size[2])
        room = next(r for r in storey.rooms if r.name == obj.room)
        polygon = np.array(room.polygon)
        verts = built.meshes[element.id()][0][:, :2]
        assert PolygonPath(polygon).contains_points(verts).all(), f"{obj.name} leaves {room.room_type}"
        assert _distance_to_boundary(verts, polygon).min() >= synth.MIN_WALL_GAP_M - 1e-3


def _raster(boxes: list[np.ndarray], origin: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Cells whose centres lie in any of the (2, 2+) xy boxes."""
    xs = origin[0] + (np.arange(shape[0]) + 0.5) * GRID_RES_M
    ys = origin[1] + (np.arange(shape[1]) + 0.5) * GRID_RES_M
    grid = np.zeros(shape, dtype=bool)
    for box in boxes:
        ix = (xs >= box[0, 0]) & (xs <= box[1, 0])
        iy = (ys >= box[0, 1]) & (ys <= box[1, 1])
        grid[np.ix_(ix, iy)] = True
    return grid


def test_flood_fill_separates_rooms_and_doors_connect_them(built: Built) -> None:
    """With doors closed every room is its own free-space component; opened doors join them all."""
    for ifc_storey, storey in zip(
        sorted(built.model.by_type("IfcBuildingStorey"), key=lambda s: s.Elevation), built.spec.storeys, strict=True
    ):
        contained = [e for rel in ifc_storey.ContainsElements for e in rel.RelatedElements]
        walls = [built.bounds(e) for e in contained if e.is_a("IfcWall")]
        door_openings = [built.bounds(e.FillsVoids[0].RelatingOpeningElement) for e in contained if e.is_a("IfcDoor")]
        lo = np.min([w[0, :2] for w in walls], axis=0) - 1.0
        hi = np.max([w[1, :2] for w in walls], axis=0) + 1.0
        shape = tuple(np.ceil((hi - lo) / GRID_RES_M).astype(int))
        closed = _raster(walls, lo, shape)
        opened = closed & ~_raster(door_openings, lo, shape)

        xs = lo[0] + (np.arange(shape[0]) + 0.5) * GRID_RES_M
        ys = lo[1] + (np.arange(shape[1]) + 0.5) * GRID_RES_M
        cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
        room_cells = [PolygonPath(np.array(r.polygon)).contains_points(cells).reshape(shape) for r in storey.rooms]

        labels, _ = ndimage.label(~closed)
        room_labels = []
        for room, mask in zip(storey.rooms, room_cells, strict=True):
            found = np.unique(labels[mask])
            assert len(found) == 1 and found[0] != 0, f"room {room.name} is split or under a wall"
            room_labels.append(found[0])
        assert len(set(room_labels)) == len(storey.rooms), "two rooms leak into each other"
        assert not np.any(np.isin(room_labels, labels[0, :])), "a room leaks to the outside"

        labels, _ = ndimage.label(~opened)
        assert len({int(np.unique(labels[mask])[0]) for mask in room_cells}) == 1, "a room is unreachable"


def test_office_rooms_share_one_arrangement(tmp_path: Path) -> None:
    spec = synth.write_building("office", 3, tmp_path / "office.ifc")
    storey = spec.storeys[0]
    layouts = []
    for room in (r for r in storey.rooms if r.room_type == "office"):
        door = next(d for d in storey.doors if d.rooms[0] == room.name)
        centroid = np.mean(np.array(room.polygon), axis=0)
        wall = storey.walls[door.wall_index]
        tangent = np.subtract(wall.end, wall.start) / wall.length
        normal = np.array([-tangent[1], tangent[0]])
        if np.dot(centroid - door.center, normal) < 0:
            normal, tangent = -normal, -tangent
        objects = sorted((o for o in storey.objects if o.room == room.name), key=lambda o: o.category)
        offsets = np.array(
            [[np.dot(np.subtract(o.center, door.center), v) for v in (tangent, normal)] for o in objects]
        )
        layouts.append(([o.category for o in objects], offsets))
    assert len(layouts) == 8
    categories, reference = layouts[0]
    assert categories == ["bookshelf", "cabinet", "chair", "desk"]
    for other_categories, offsets in layouts[1:]:
        assert other_categories == categories
        assert np.abs(offsets - reference).max() < 0.15


def test_multi_storey_levels_are_self_contained(tmp_path: Path) -> None:
    spec = synth.write_building("multi-storey", 0, tmp_path / "house.ifc")
    assert [s.elevation for s in spec.storeys] == [0.0, 3.0, 6.0]
    room_types = [frozenset(r.room_type for r in s.rooms) for s in spec.storeys]
    assert len(set(room_types)) == 3
    for attribute in ("rooms", "doors", "windows"):
        names = [item.name for s in spec.storeys for item in getattr(s, attribute)]
        assert len(names) == len(set(names)), f"{attribute} names repeat across storeys"
    for storey in spec.storeys:
        assert storey.walls and storey.doors and storey.rooms and storey.objects
        rooms = {r.name for r in storey.rooms}
        assert all(set(d.rooms) <= rooms for d in storey.doors)
        assert all(o.room in rooms for o in storey.objects)
    model = ifcopenshell.open(str(tmp_path / "house.ifc"))
    for ifc_storey in model.by_type("IfcBuildingStorey"):
        kinds = Counter(e.is_a() for rel in ifc_storey.ContainsElements for e in rel.RelatedElements)
        assert kinds["IfcWall"] and kinds["IfcDoor"] and kinds["IfcFurniture"]
        assert ifc_storey.IsDecomposedBy[0].RelatedObjects[0].is_a("IfcSpace")


def test_walls_meet_at_corners(paper: Built) -> None:
    """Every wall end lies inside another wall, so corners close without gaps."""
    boxes = [paper.bounds(w)[:, :2] for w in paper.model.by_type("IfcWall")]
    for i, box in enumerate(boxes):
        along = int(np.argmax(box[1] - box[0]))
        mid = (box[0] + box[1]) / 2
        for end in (box[0, along], box[1, along]):
            probe = mid.copy()
            probe[along] = end + (0.05 if end == box[0, along] else -0.05)
            inside_other = [
                j for j, other in enumerate(boxes) if j != i and np.all(other[0] <= probe) and np.all(probe <= other[1])
            ]
            assert inside_other, f"wall {i} ends in the open at {probe}"


def test_object_kinds_have_plausible_sizes() -> None:
    for kind in synth.OBJECT_KINDS.values():
        assert 0.2 <= min(kind.size[:2]) <= max(kind.size[:2]) <= 3.0 and 0.4 <= kind.size[2] <= 2.0
        assert kind.category in synth.OBJECT_CATEGORIES
    assert synth.OBJECT_KINDS["bed"].size == (2.0, 1.6, 0.5)
    assert synth.OBJECT_KINDS["chair"].size == (0.5, 0.5, 0.9)
    assert synth.OBJECT_KINDS["table"].size == (1.6, 0.9, 0.75)
