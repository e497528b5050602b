"""The BimPrior: the building as a Building → Storey → Room → Object graph, with grids and room masks.

`build_prior` runs the offline stage (paper Sec. II.A) on an IFC file; `BimPrior.save` / `BimPrior.load` keep it in a
versioned folder (`PRIOR_FORMAT`): prior.json (the graph and statistics), arrays.npz (grid layers, object embeddings,
the visible-object table), config.yaml, and what `extra_files` adds (floor plans). docs/offline-prior.md.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import typing
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pydantic
import typing_extensions
from scipy.spatial import cKDTree

from bimfactor.bim import rooms as room_ops
from bimfactor.bim.classify import RoomClassification, load_room_category_pool, type_rooms
from bimfactor.bim.grid import GridSpec, StoreyGrid, build_storey_grid, grid_spec_for, rasterise_polygons
from bimfactor.bim.ifc import FIXED_OBJECT_CLASSES, IfcElement, IfcModel, Storey, file_sha256, load_ifc
from bimfactor.bim.surfaces import WallMeshes, wall_meshes
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.bim.vocabulary import Vocabulary, label_elements
from bimfactor.config import Config, config_file
from bimfactor.embed.text import TextEmbedder, make_text_embedder
from bimfactor.errors import FormatError, IfcError, InputError
from bimfactor.io.atomic import check_output_dir, output_dir
from bimfactor.progress import Laps, progress
from bimfactor.resources import check_grid_memory
from bimfactor.textfile import read_utf8

log = logging.getLogger(__name__)

PRIOR_FORMAT = "bimfactor-prior"
PRIOR_VERSION = 5  # 3: storeys say whether they are floors (`floor_levels`); 4: the wall meshes (`bim.surfaces`);
# 5: the portals between floors (`find_portals`)
_LAYERS = ("structure", "furniture", "clearance_m", "room_labels", "navigable")


@dataclass
class BimObject:
    """An object node: a labelled BIM element with its place; `room_id` is OUTSIDE/NO_ROOM when not in a room."""

    id: int
    guid: str
    ifc_class: str
    label: str
    label_source: str
    raw_text: str
    storey_index: int
    room_id: int
    position_m: tuple[float, float, float]
    size_m: tuple[float, float, float]


@dataclass
class Room:
    """A room node: where it is, where it came from, and its language-encoded type."""

    id: int
    storey_index: int
    source: str
    area_m2: float
    centroid_xy: tuple[float, float]
    space_guid: str | None
    space_name: str
    category: str
    category_score: float
    sentence: str
    object_ids: list[int]
    space_number: str = ""  # the IfcSpace Name where a LongName names the room: the number on its door plate


@dataclass
class Door:
    """A door (or a leafless passage) and the two rooms it joins (OUTSIDE, NO_ROOM when a side is unknown)."""

    id: int
    kind: str  # "door" (an IfcDoor), "passage" (a leafless doorway under a lintel), "opening" (open-plan edge)
    guid: str
    storey_index: int
    object_id: int
    center_xy: tuple[float, float]
    axis_xy: tuple[float, float]
    width_m: float
    depth_m: float
    room_a: int
    room_b: int

    @classmethod
    def from_geometry(
        cls, door_id: int, kind: str, guid: str, storey_index: int, geom: room_ops.DoorGeometry, a: int, b: int
    ) -> Door:
        return cls(
            id=door_id,
            kind=kind,
            guid=guid,
            storey_index=storey_index,
            object_id=-1,
            center_xy=(float(geom.center_xy[0]), float(geom.center_xy[1])),
            axis_xy=(float(geom.axis_xy[0]), float(geom.axis_xy[1])),
            width_m=float(geom.width_m),
            depth_m=float(geom.depth_m),
            room_a=a,
            room_b=b,
        )

    @property
    def connects(self) -> bool:
        """True when the door joins two different known places (two rooms, or a room and outside)."""
        return room_ops.joins(self.room_a, self.room_b)


@dataclass
class PortalEnd:
    """Where a portal meets one floor: the (x_min, y_min, x_max, y_max) world box of its footprint there."""

    storey_index: int
    box_xy: tuple[float, float, float, float]


@dataclass
class Portal:
    """A way between floors (`find_portals`): a lift stops at every floor its shaft spans, in the same footprint; a
    stair (a flight, a ramp, an escalator) joins its bottom floor at its foot and its top floor at its head."""

    id: int
    kind: str  # "lift" or "stair"
    guid: str
    ifc_class: str
    ends: list[PortalEnd]  # one per floor it joins, lowest first


@dataclass
class StoreyLayers(StoreyGrid):
    """A storey's grid layers plus its room labels (int32 room id, OUTSIDE, NO_ROOM) and navigable cells."""

    room_labels: np.ndarray
    navigable: np.ndarray


@dataclass
class RoomMatch:
    """Agreement of flood-fill rooms with the model's IfcSpace rooms on one storey."""

    storey_index: int
    spaces_compared: int
    ious: list[float]
    threshold: float

    @property
    def matched_share(self) -> float:
        return float(np.mean([iou >= self.threshold for iou in self.ious])) if self.ious else float("nan")


@dataclass
class BimPrior:
    """The offline prior the localizer runs against."""

    source_file: str
    source_sha256: str
    schema: str
    embedding_model: str
    grid: GridSpec
    storeys: list[StoreyLayers]
    rooms: list[Room]
    doors: list[Door]
    objects: list[BimObject]
    object_embeddings: np.ndarray
    room_edges: list[tuple[int, int, int]]
    object_edges: list[tuple[int, int]]
    room_matches: list[RoomMatch] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    visibility: VisibilityTable | None = None
    walls: WallMeshes | None = None
    """The structural elements' meshes the fine registrar samples (`bim.surfaces`); None: a prior built without."""
    portals: list[Portal] = field(default_factory=list)

    # -------------------------------------------------------------------------------- queries

    def object_positions(self) -> np.ndarray:
        """(N, 3) object centres in the world frame."""
        return np.asarray([o.position_m for o in self.objects], dtype=np.float64).reshape(-1, 3)

    def object_sizes(self) -> np.ndarray:
        """(N, 3) object extents along the world axes (their axis-aligned boxes are centre ± size / 2)."""
        return np.asarray([o.size_m for o in self.objects], dtype=np.float64).reshape(-1, 3)

    def floor_rank(self) -> np.ndarray:
        """(S,) each storey's place among the floors a robot stands on (0: the lowest; -1: a level that is no floor),
        what a storey-change event counts in."""
        rank = np.full(len(self.storeys), -1, np.int64)
        floors = [layers.storey.index for layers in self.storeys if layers.storey.is_floor]
        rank[floors] = np.arange(len(floors))
        return rank

    def room_at(self, xy: np.ndarray, storey_index: int = 0) -> np.ndarray:
        """(N,) room id at each world point of (N, 2) xy (OUTSIDE / NO_ROOM off the rooms)."""
        rc = self.grid.world_to_cell(xy)
        out = np.full(len(rc), room_ops.OUTSIDE, np.int32)
        ok = self.grid.contains(rc)
        out[ok] = self.storeys[storey_index].room_labels[rc[ok, 0], rc[ok, 1]]
        return out

    def summary(self) -> dict[str, object]:
        """Counts for people: storeys, rooms, doors, objects per category."""
        return {
            "source": Path(self.source_file).name,
            "schema": self.schema,
            "storeys": [
                {
                    "name": s.storey.name,
                    "elevation_m": round(s.storey.elevation_m, 3),
                    "rooms": sum(r.storey_index == s.storey.index for r in self.rooms),
                    "doors": sum(d.storey_index == s.storey.index and d.kind == "door" for d in self.doors),
                    "passages": sum(d.storey_index == s.storey.index and d.kind == "passage" for d in self.doors),
                    "objects": sum(o.storey_index == s.storey.index for o in self.objects),
                    "floor": s.storey.floor_note,
                }
                for s in self.storeys
            ],
            "rooms": len(self.rooms),
            "portals": [
                {"kind": p.kind, "ifc_class": p.ifc_class, "storeys": [e.storey_index for e in p.ends]}
                for p in self.portals
            ],
            "doors": sum(d.kind == "door" for d in self.doors),
            "doors_connecting": sum(d.connects for d in self.doors if d.kind == "door"),
            "passages": sum(d.kind == "passage" for d in self.doors),
            "openings": sum(d.kind == "opening" for d in self.doors),
            "objects": len(self.objects),
            "objects_per_category": dict(Counter(o.label for o in self.objects).most_common()),
            "room_types": dict(Counter(r.category for r in self.rooms).most_common()),
            "ifcspace_match": [
                {"storey": m.storey_index, "spaces": len(m.ious), "matched_share": m.matched_share}
                for m in self.room_matches
                if m.ious
            ],
            "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()},
        }

    # -------------------------------------------------------------------------------- disk

    def save(
        self,
        out_dir: str | Path,
        config_yaml: str = "",
        extra_files: Callable[[BimPrior, Path], object] | None = None,
    ) -> None:
        """Write the prior folder atomically (a half-written prior never appears under `out_dir`).

        Only a prior folder that bimfactor wrote is replaced, and never the folder holding the source IFC
        (`io.atomic.output_dir`); anything else raises InputError and is left untouched. `extra_files(prior,
        folder)` writes more files into the folder before it appears (e.g. `evaluation.plots.save_floorplans`).
        """
        meta = {
            "format": PRIOR_FORMAT,
            "version": PRIOR_VERSION,
            "source_file": self.source_file,
            "source_sha256": self.source_sha256,
            "schema": self.schema,
            "embedding_model": self.embedding_model,
            "grid": self.grid.to_dict(),
            "storeys": [asdict(s.storey) for s in self.storeys],
            "rooms": [asdict(r) for r in self.rooms],
            "doors": [asdict(d) for d in self.doors],
            "objects": [asdict(o) for o in self.objects],
            "room_edges": self.room_edges,
            "object_edges": self.object_edges,
            "room_matches": [asdict(m) for m in self.room_matches],
            "portals": [asdict(p) for p in self.portals],
            "timings_s": self.timings_s,
        }
        arrays = {"object_embeddings": self.object_embeddings.astype(np.float32)}
        if self.visibility is not None:
            arrays.update(self.visibility.to_arrays())
        if self.walls is not None:
            arrays.update(self.walls.to_arrays())
        for layers in self.storeys:
            for name in _LAYERS:
                arrays[f"storey{layers.storey.index}_{name}"] = getattr(layers, name)
        with output_dir(out_dir, "prior", inputs=[self.source_file]) as tmp:
            (tmp / "prior.json").write_text(json.dumps(meta, indent=1))
            np.savez_compressed(tmp / "arrays.npz", **arrays)
            if config_yaml:
                (tmp / "config.yaml").write_text(config_yaml)
            if extra_files is not None:
                extra_files(self, tmp)

    @classmethod
    def load(cls, prior_dir: str | Path) -> BimPrior:
        """Read a prior folder; FormatError (one line, naming the file and what is wrong) for anything corrupt."""
        prior_dir = Path(prior_dir)
        meta_file, array_file = prior_dir / "prior.json", prior_dir / "arrays.npz"
        if not meta_file.is_file() or not array_file.is_file():
            raise FormatError(f"{prior_dir}: not a bimfactor prior (prior.json / arrays.npz missing)")
        meta, text = _read_prior_json(meta_file)
        fmt, version = meta.get("format"), meta.get("version")
        for name in ("format", "version"):
            if name not in meta:
                raise FormatError(f"{meta_file}: not a bimfactor prior (no '{name}' field)")
        if fmt != PRIOR_FORMAT:
            raise FormatError(
                f"{meta_file}: not a bimfactor prior ('format' is {_json_value(fmt)}, not {PRIOR_FORMAT})"
            )
        if isinstance(version, bool) or not isinstance(version, int):
            raise FormatError(f"{meta_file}: 'version' must be an integer, found {_json_value(version)}")
        if version != PRIOR_VERSION:
            raise FormatError(
                f"{prior_dir}: prior format {fmt} v{version}, "
                f"this bimfactor reads {PRIOR_FORMAT} v{PRIOR_VERSION}; rebuild it with `bimfactor prior`"
            )
        fields = _validate_prior_json(meta_file, text)
        grid, storey_list, rooms, doors, objects = (
            fields["grid"],
            fields["storeys"],
            fields["rooms"],
            fields["doors"],
            fields["objects"],
        )

        def fail(where: str, what: str) -> typing.NoReturn:
            raise FormatError(f"{meta_file}: {where}: {what}")

        if grid.resolution_m <= 0 or grid.rows <= 0 or grid.cols <= 0:
            fail("grid", "resolution, rows and cols must be positive")
        for i, storey in enumerate(storey_list):
            if storey.index != i:
                fail(f"storeys[{i}].index", f"is {storey.index}; storeys must be numbered 0, 1, ... in order")
        n_storeys, n_objects = len(storey_list), len(objects)
        for kind, items in (("rooms", rooms), ("doors", doors), ("objects", objects)):
            for i, item in enumerate(items):
                if not 0 <= item.storey_index < n_storeys:
                    fail(f"{kind}[{i}].storey_index", f"{item.storey_index} is no storey (the prior has {n_storeys})")
        for i, room in enumerate(rooms):
            if any(not 0 <= o < n_objects for o in room.object_ids):
                fail(f"rooms[{i}].object_ids", f"names an object that does not exist (the prior has {n_objects})")
        for i, door in enumerate(doors):
            if not -1 <= door.object_id < n_objects:
                fail(f"doors[{i}].object_id", f"{door.object_id} is no object (the prior has {n_objects})")
        for i, portal in enumerate(fields["portals"]):
            if any(not 0 <= end.storey_index < n_storeys for end in portal.ends):
                fail(f"portals[{i}].ends", f"names a storey that does not exist (the prior has {n_storeys})")
        for i, edge in enumerate(fields["object_edges"]):
            if any(not 0 <= o < n_objects for o in edge):
                fail(f"object_edges[{i}]", f"names an object that does not exist (the prior has {n_objects})")
        storeys, embeddings, visibility, walls = _read_prior_arrays(array_file, grid, storey_list, n_objects)
        return cls(
            source_file=fields["source_file"],
            source_sha256=fields["source_sha256"],
            schema=fields["schema"],
            embedding_model=fields["embedding_model"],
            grid=grid,
            storeys=storeys,
            rooms=rooms,
            doors=doors,
            objects=objects,
            object_embeddings=embeddings,
            room_edges=fields["room_edges"],
            object_edges=fields["object_edges"],
            room_matches=fields["room_matches"],
            timings_s=fields.get("timings_s", {}),
            visibility=visibility,
            walls=walls,
            portals=fields["portals"],
        )


def ensure_prior_destination(out_dir: str | Path, ifc_path: str | Path) -> None:
    """Raise InputError unless `BimPrior.save` of `ifc_path`'s prior may write `out_dir` (checked before building)."""
    check_output_dir(out_dir, "prior", inputs=[ifc_path])


# ------------------------------------------------------------------------------------------------ build


def build_prior(ifc_path: str | Path, cfg: Config, embedder: TextEmbedder | None = None) -> BimPrior:
    """Run the offline stage on one IFC file."""
    lap = Laps()
    bim = cfg.bim
    model = load_ifc(ifc_path, bim.ifc)
    lap("read_ifc")

    furniture_classes = [c for c in bim.objects.classes if c not in FIXED_OBJECT_CLASSES]
    spec = grid_spec_for(model, bim.grid, bim.grid.obstacle_exclude_classes)
    x0, x1, y0, y1 = spec.extent
    check_grid_memory((x1 - x0, y1 - y0), len(model.storeys), cfg, padding_included=True)
    storeys, rooms, doors, matches = [], [], [], []
    door_elements = model.of_class("IfcDoor")
    spaces = model.of_class("IfcSpace")
    levels = floor_levels(model, furniture_classes)
    for storey in progress(levels, desc="storeys", unit="storey"):
        grid = build_storey_grid(storey, model.elements, spec, bim.grid, furniture_classes)
        z_lo, z_hi = storey.elevation_m + bim.grid.band_min_m, storey.elevation_m + bim.grid.band_max_m
        storey_doors = [(d, g) for d in door_elements if (g := room_ops.door_geometry(d, z_lo, z_hi)) is not None]
        storey_spaces = [s for s in spaces if s.storey_index == storey.index]
        passages = room_ops.passage_geometries(
            model.elements, grid.structure, [g for _, g in storey_doors], spec, storey.elevation_m, bim.rooms
        )
        storey_doors = storey_doors + [(None, g) for g in passages]
        layers, storey_rooms, storey_doors_out, match = _storey_rooms(
            grid, spec, storey_doors, storey_spaces, cfg, first_room_id=len(rooms), first_door_id=len(doors)
        )
        storeys.append(layers)
        rooms.extend(storey_rooms)
        doors.extend(storey_doors_out)
        if match is not None:
            matches.append(match)
    _check_rooms(ifc_path, model, rooms, storeys, cfg)
    lap("grids_and_rooms")

    # The text embedder loads a model: only once the building has proved usable.
    embedder = embedder or make_text_embedder(cfg.embed)
    vocabulary = Vocabulary.load(config_file(bim.objects.vocabulary_file))
    object_elements = [e for e in model.of_class(*bim.objects.classes) if e.storey_index is not None]
    labels = label_elements(object_elements, vocabulary, embedder, bim.objects.embedding_fallback_min_sim)
    lap("label_objects")

    objects = _make_objects(object_elements, labels, storeys, spec)
    door_object = {o.guid: o.id for o in objects}
    for door in doors:
        door.object_id = door_object.get(door.guid, -1)
    for room in rooms:
        room.object_ids = [o.id for o in objects if o.room_id == room.id]
    unique_labels = sorted({o.label for o in objects})
    label_vectors = dict(zip(unique_labels, embedder.encode(unique_labels), strict=True)) if unique_labels else {}
    dim = next(iter(label_vectors.values())).shape[0] if label_vectors else embedder.dim
    embeddings = np.asarray([label_vectors[o.label] for o in objects], np.float32).reshape(-1, dim)
    lap("assign_objects")

    for room, result in zip(rooms, classify_prior_rooms(rooms, objects, doors, cfg, embedder), strict=True):
        room.category, room.category_score, room.sentence = result.category, result.score, result.sentence
    lap("classify_rooms")

    room_edges = sorted(
        {
            (min(d.room_a, d.room_b), max(d.room_a, d.room_b), d.id)
            for d in doors
            if d.connects and min(d.room_a, d.room_b) >= 0
        }
    )
    object_edges = _proximity_edges(objects, bim.objects.proximity_edge_m)
    lap("edges")
    prior = BimPrior(
        source_file=str(Path(ifc_path).resolve()),  # found from any working directory
        source_sha256=model.sha256,
        schema=model.schema,
        embedding_model=getattr(embedder, "name", type(embedder).__name__),
        grid=spec,
        storeys=storeys,
        rooms=rooms,
        doors=doors,
        objects=objects,
        object_embeddings=embeddings,
        room_edges=[tuple(e) for e in room_edges],
        object_edges=object_edges,
        room_matches=matches,
        timings_s=lap.times,
        portals=find_portals(model, levels),
    )
    prior.visibility = VisibilityTable.build(prior, cfg.bim.visibility)
    lap("visibility")
    prior.walls = wall_meshes(model)
    lap("walls")
    return prior


ROOF_SLAB = "ROOF"
"""An IfcSlab's predefined type on a level with nothing else to stand on: the level is a roof."""


def floor_levels(model: IfcModel, furniture_classes: list[str]) -> list[Storey]:
    """The model's storeys, each marked a floor or not, with why. A floor holds, by the model's spatial structure,
    something a robot moves among: a room (IfcSpace), a door or furniture; and not only roof slabs under it. A
    foundation, a roof or a reference level holds none of these: its height slice would cut the walls and doors of
    the floor above or below into a second copy of that floor. When no level qualifies, every level is a floor."""
    notes = []
    for storey in model.storeys:
        own = [e for e in model.elements if e.storey_index == storey.index]
        spaces = sum(e.ifc_class == "IfcSpace" for e in own)
        doors = sum(e.is_a("IfcDoor") for e in own)
        furniture = sum(any(e.is_a(c) for c in furniture_classes) for e in own)
        slabs = [e.predefined_type.upper() for e in own if e.is_a("IfcSlab")]
        counts = f"{spaces} IfcSpace, {doors} doors, {furniture} furniture"
        if not spaces + doors + furniture:
            notes.append((False, f"not a floor: no IfcSpace, door or furniture of its own ({len(own)} elements)"))
        elif slabs and all(t == ROOF_SLAB for t in slabs):
            notes.append((False, f"not a floor: its slabs are roof slabs ({counts})"))
        else:
            notes.append((True, f"floor: {counts}"))
    if not any(is_floor for is_floor, _ in notes):
        notes = [(True, "floor: no level holds a room, door or furniture, so every level is kept")] * len(notes)
    return [
        dataclasses.replace(storey, is_floor=is_floor, floor_note=note)
        for storey, (is_floor, note) in zip(model.storeys, notes, strict=True)
    ]


PORTAL_CLASSES = ("IfcStair", "IfcStairFlight", "IfcRamp", "IfcTransportElement")
MOVING_STAIRS = ("ESCALATOR", "MOVINGWALKWAY")  # transport elements a robot crosses as it does a stair
LEVEL_SLACK_M = 0.35  # a portal reaches a floor whose elevation lies this close to its extent; its end there is
# its footprint within this height of the floor


def find_portals(model: IfcModel, storeys: list[Storey]) -> list[Portal]:
    """The model's ways between floors: each stair, flight, ramp or lift whose height reaches two floors or more. A
    stair whose flights are modelled too leaves the portals to its flights (each flight its own floors)."""
    floors = [s for s in storeys if s.is_floor]
    elements = [e for e in model.of_class(*PORTAL_CLASSES) if e.mesh is not None]
    parts = [e.mesh.bounds.mean(axis=0) for e in elements if not e.is_a("IfcStair") and e.mesh is not None]
    portals: list[Portal] = []
    for element in elements:
        assert element.mesh is not None
        lo, hi = element.mesh.bounds
        if element.is_a("IfcStair") and any(np.all((lo <= c) & (c <= hi)) for c in parts):
            continue
        reached = [s for s in floors if lo[2] - LEVEL_SLACK_M <= s.elevation_m <= hi[2] + LEVEL_SLACK_M]
        lift = element.is_a("IfcTransportElement") and element.predefined_type.upper() not in MOVING_STAIRS
        if len(reached) < 2:
            continue
        reached = reached if lift else [reached[0], reached[-1]]
        ends = []
        for floor in reached:
            vertices = element.mesh.vertices
            near = vertices[np.abs(vertices[:, 2] - floor.elevation_m) <= LEVEL_SLACK_M]
            xy = vertices[:, :2] if lift or len(near) == 0 else near[:, :2]
            box = (*xy.min(axis=0), *xy.max(axis=0))
            ends.append(PortalEnd(floor.index, typing.cast(tuple[float, float, float, float], tuple(map(float, box)))))
        kind = "lift" if lift else "stair"
        portals.append(Portal(len(portals), kind, element.guid, element.ifc_class, ends))
    return portals


def _check_rooms(
    ifc_path: str | Path, model: IfcModel, rooms: list[Room], storeys: list[StoreyLayers], cfg: Config
) -> None:
    """IfcError for a building with no room, or no room a robot fits in: the localizer has nowhere to put it.

    A prior without rooms is refused at build time rather than left for `localize` to fail on: rooms need doors
    (or IfcSpace) to tell them from the outside, so a model of walls alone has none.
    """
    if not rooms:
        if not model.of_class("IfcDoor") and not model.of_class("IfcSpace"):
            why = "it has neither doors (IfcDoor) nor rooms (IfcSpace), so no space can be told apart from the outside"
        else:
            band = f"{cfg.bim.grid.band_min_m:g}-{cfg.bim.grid.band_max_m:g} m above each storey"
            why = f"no space enclosed by walls {band} is reached by a door or modelled as an IfcSpace"
        raise IfcError(f"{ifc_path}: no rooms found: {why}; nowhere to localize in")
    if not any(layers.navigable.any() for layers in storeys):
        raise IfcError(
            f"{ifc_path}: none of its {len(rooms)} rooms has space for the robot "
            f"(bim.grid.robot_radius_m {cfg.bim.grid.robot_radius_m:g} m clear of walls and furniture); "
            "nowhere to localize in"
        )


def _storey_rooms(grid, spec, storey_doors, storey_spaces, cfg: Config, first_room_id: int, first_door_id: int):
    """Rooms, doors and layers of one storey; storeys with neither doors nor spaces (foundations) get no rooms.

    Flood-fill rooms are the regions a door joins to another place (`rooms.door_connected_regions`).
    """
    rcfg = cfg.bim.rooms
    storey = grid.storey
    door_geoms = [g for _, g in storey_doors]
    sealed = room_ops.seal_doors(grid.structure, door_geoms, spec, rcfg.door_seal_margin_m)
    flood, outside = room_ops.floodfill_rooms(sealed, spec, rcfg)
    flood = room_ops.door_connected_regions(flood, door_geoms, outside, spec, rcfg.door_probe_m)
    space_regions = room_ops.space_rooms(storey_spaces, spec, ~grid.structure)
    match = None
    if space_regions:
        ious = room_ops.match_rooms(flood, space_regions, spec.resolution_m)
        match = RoomMatch(storey.index, len(space_regions), ious, rcfg.iou_match_threshold)
    use_spaces = rcfg.source == "ifcspace" or (rcfg.source == "auto" and bool(space_regions))
    regions = space_regions if use_spaces else flood
    if not storey.is_floor or (not any(element is not None for element, _ in storey_doors) and not storey_spaces):
        regions = []
    ids = list(range(first_room_id, first_room_id + len(regions)))
    labels = room_ops.label_map(regions, ids, outside)
    navigable = room_ops.navigable_mask(grid, labels, cfg.bim.grid)
    layers = StoreyLayers(storey, grid.structure, grid.furniture, grid.clearance_m, labels, navigable)
    rooms = []
    for rid, region in zip(ids, regions, strict=True):
        cells = np.argwhere(labels == rid)
        if len(cells) == 0:
            continue
        centroid = spec.cell_to_world(cells.mean(axis=0, keepdims=True))[0]
        rooms.append(
            Room(
                id=rid,
                storey_index=storey.index,
                source=region.source,
                area_m2=float(len(cells) * spec.resolution_m**2),
                centroid_xy=(float(centroid[0]), float(centroid[1])),
                space_guid=region.space_guid,
                space_name=region.space_name,
                space_number=region.space_number,
                category="unknown",
                category_score=0.0,
                sentence="",
                object_ids=[],
            )
        )
    doors = []
    for element, geom in storey_doors:
        a, b = room_ops.door_sides(geom, labels, spec, rcfg.door_probe_m)
        if element is None and not room_ops.joins(a, b):
            continue  # a lintel strip that joins nothing is no passage
        kind = "door" if element is not None else "passage"
        guid = element.guid if element is not None else ""
        doors.append(Door.from_geometry(first_door_id + len(doors), kind, guid, storey.index, geom, a, b))
    for a, b, geom in room_ops.open_boundaries(labels, spec, min_length_m=rcfg.min_opening_m):
        doors.append(Door.from_geometry(first_door_id + len(doors), "opening", "", storey.index, geom, a, b))
    return layers, rooms, doors, match


def _make_objects(elements: list[IfcElement], labels, storeys: list[StoreyLayers], spec: GridSpec) -> list[BimObject]:
    objects = []
    for el, lab in zip(elements, labels, strict=True):
        assert el.mesh is not None and el.storey_index is not None
        lo, hi = el.mesh.bounds
        reach = 1.0
        sub, window = spec.window(lo[0] - reach, lo[1] - reach, hi[0] + reach, hi[1] + reach)
        tris = el.mesh.vertices[el.mesh.faces][:, :, :2]
        mask = rasterise_polygons(list(tris), sub).astype(bool)
        room_labels = storeys[el.storey_index].room_labels[window]
        room_id = room_ops.assign_to_room(mask, room_labels, sub)
        center = (lo + hi) / 2
        objects.append(
            BimObject(
                id=len(objects),
                guid=el.guid,
                ifc_class=el.ifc_class,
                label=lab.label,
                label_source=lab.source.value,
                raw_text=lab.raw_text,
                storey_index=el.storey_index,
                room_id=room_id,
                position_m=(float(center[0]), float(center[1]), float(center[2])),
                size_m=tuple(float(v) for v in hi - lo),
            )
        )
    return objects


def classify_prior_rooms(
    rooms: Sequence[Room],
    objects: Sequence[BimObject],
    doors: Sequence[Door],
    cfg: Config,
    embedder: TextEmbedder,
    *,
    use_names: bool = True,
) -> list[RoomClassification]:
    """The rooms' types (`bim.classify.type_rooms`): by name where it decides, else the paper's language-encoded
    object sentence, else topology. `use_names=False` types them by objects and topology alone."""
    ccfg = cfg.bim.classify
    ignore = set(ccfg.ignore_labels)
    labels = [[objects[i].label for i in room.object_ids if objects[i].label not in ignore] for room in rooms]
    places: dict[int, set[int]] = {room.id: set() for room in rooms}
    for d in doors:
        for a, b in ((d.room_a, d.room_b), (d.room_b, d.room_a)):
            if a in places and b != a:
                places[a].add(b)
    neighbours = [len(places[room.id]) for room in rooms]
    pool = load_room_category_pool(ccfg, embedder)
    return type_rooms(labels, [room.space_name for room in rooms], neighbours, pool, ccfg, use_names=use_names)


def _proximity_edges(objects: list[BimObject], radius_m: float) -> list[tuple[int, int]]:
    edges: list[tuple[int, int]] = []
    for storey in sorted({o.storey_index for o in objects}):
        ids = [o.id for o in objects if o.storey_index == storey]
        xy = np.asarray([objects[i].position_m[:2] for i in ids])
        for a, b in sorted(cKDTree(xy).query_pairs(radius_m)):
            edges.append((ids[a], ids[b]))
    return edges


# ------------------------------------------------------------------------------------------------ reading a prior


def _read_prior_json(meta_file: Path) -> tuple[dict, str]:
    """prior.json as a dict and its text; FormatError for unreadable bytes, bad UTF-8, bad JSON or another
    top-level type."""
    text = read_utf8(meta_file, FormatError, hint="the file is corrupt")
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise FormatError(f"{meta_file}: corrupt JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from exc
    except RecursionError as exc:
        raise FormatError(f"{meta_file}: corrupt JSON (nested too deeply)") from exc
    if not isinstance(meta, dict):
        raise FormatError(f"{meta_file}: expected a JSON object at the top, found {_json_value(meta)}")
    return meta, text


def _json_value(value: object) -> str:
    """A JSON value as an error message names it: the string '2', the number 2, a list, an object, null."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f"the string {json.dumps(shown, ensure_ascii=False)}"
    if isinstance(value, int | float):
        return f"the number {value}"
    return "a list" if isinstance(value, list) else "an object"


class _PriorJson(typing_extensions.TypedDict):  # pydantic needs typing_extensions' TypedDict before Python 3.12
    """prior.json's fields and their types (`format` and `version` are checked first, with their own messages)."""

    source_file: str
    source_sha256: str
    schema: str
    embedding_model: str
    grid: GridSpec
    storeys: list[Storey]
    rooms: list[Room]
    doors: list[Door]
    objects: list[BimObject]
    room_edges: list[tuple[int, int, int]]
    object_edges: list[tuple[int, int]]
    room_matches: list[RoomMatch]
    portals: list[Portal]
    timings_s: typing_extensions.NotRequired[dict[str, float]]


_PRIOR_JSON = pydantic.TypeAdapter(_PriorJson)


def _validate_prior_json(meta_file: Path, text: str) -> _PriorJson:
    """prior.json's fields as their dataclasses, validated strictly (no "2" for 2; unknown fields are ignored, so
    that a newer bimfactor's additions do not break this one); FormatError naming the first mismatch's place."""
    try:
        return _PRIOR_JSON.validate_json(text, strict=True)
    except pydantic.ValidationError as exc:
        error = exc.errors(include_url=False)[0]
        loc = error["loc"]
        if len(loc) == 1 and error["type"] == "missing":
            raise FormatError(f"{meta_file}: '{loc[0]}' is missing") from None
        where = "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in loc).lstrip(".")
        found = "" if error["type"] == "missing" else f", found {_json_value(error['input'])}"
        raise FormatError(f"{meta_file}: {where}: {error['msg'][0].lower()}{error['msg'][1:]}{found}") from None


_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
_LAYER_KINDS = {"structure": "b", "furniture": "b", "clearance_m": "f", "room_labels": "iu", "navigable": "b"}
_KIND_NAMES = {"b": "bool", "f": "float", "iu": "integer"}


def _read_prior_arrays(
    array_file: Path, grid: GridSpec, storeys: list[Storey], n_objects: int
) -> tuple[list[StoreyLayers], np.ndarray, VisibilityTable | None, WallMeshes | None]:
    """The grid layers, object embeddings, visibility table and wall meshes; FormatError for a corrupt or incomplete
    archive.

    Loaded with allow_pickle=False: a prior never holds Python objects, and a pickle is never executed.
    """
    try:
        with array_file.open("rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise FormatError(f"{array_file}: cannot be read ({exc.strerror or type(exc).__name__})") from exc
    if magic not in _ZIP_MAGIC:
        raise FormatError(f"{array_file}: not a NumPy .npz archive (corrupt, or not written by bimfactor)")

    def need(arrays, key: str, kinds: str, shape: tuple[int, ...] | None, ndim: int | None = None) -> np.ndarray:
        if key not in arrays.files:
            raise FormatError(f"{array_file}: array '{key}' is missing")
        value = arrays[key]
        if (
            value.dtype.kind not in kinds
            or (shape is not None and value.shape != shape)
            or (ndim is not None and value.ndim != ndim)
        ):
            expected = f"shape {shape}" if shape is not None else f"{ndim} dimensions"
            raise FormatError(
                f"{array_file}: array '{key}' is {value.dtype} of shape {value.shape}, "
                f"expected {_KIND_NAMES[kinds]} of {expected}"
            )
        return value

    try:
        with np.load(array_file, allow_pickle=False) as arrays:
            layers = [
                StoreyLayers(
                    storey, *(need(arrays, f"storey{storey.index}_{n}", _LAYER_KINDS[n], grid.shape) for n in _LAYERS)
                )
                for storey in storeys
            ]
            embeddings = need(arrays, "object_embeddings", "f", None, ndim=2)
            if len(embeddings) != n_objects:
                raise FormatError(
                    f"{array_file}: {len(embeddings)} object embeddings for {n_objects} objects in prior.json"
                )
            visibility = VisibilityTable.from_arrays(arrays) if "visibility_meta" in arrays.files else None
            walls = WallMeshes.from_arrays(arrays) if "walls_bands" in arrays.files else None
    except FormatError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, zlib.error, EOFError, ValueError, KeyError, OSError, ...
        raise FormatError(f"{array_file}: corrupt or truncated ({_array_failure(exc)})") from exc
    return layers, embeddings, visibility, walls


def _array_failure(exc: Exception) -> str:
    """What went wrong reading the archive, in our words where numpy's would advise unsafe loading."""
    text = " ".join(str(exc).split())
    if not text or "pickle" in text.lower():
        return type(exc).__name__
    return f"{type(exc).__name__}: {text[:200]}"


def source_model(prior: BimPrior, cfg: Config, prior_dir: str | Path | None = None) -> IfcModel:
    """The IFC model `prior` was built from: its `source_file`, checked by SHA-256 (a prior stores no meshes).

    Priors store the absolute path; a relative one (an older prior) is looked up from the working directory, then
    from the prior folder and its parent. Last, a file of that name in or beside the prior folder (a prior moved
    together with its IFC); the hash decides whether it is the same file.
    """
    source = Path(prior.source_file)
    candidates = [source]
    if prior_dir is not None:
        folder = Path(prior_dir)
        if not source.is_absolute():
            candidates += [folder / source, folder.parent / source]
        candidates += [folder / source.name, folder.parent / source.name]
    path = next((p for p in candidates if p.is_file()), None)
    where = f"the prior {prior_dir}" if prior_dir is not None else "the prior"
    if path is None:
        raise InputError(f"the IFC file {where} was built from is missing: {prior.source_file}")
    if file_sha256(path) != prior.source_sha256:
        raise InputError(f"{path} changed since {where} was built from it; rebuild the prior")
    return load_ifc(path, cfg.bim.ifc)
