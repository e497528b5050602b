"""The simulated world: the building's physical meshes in one Open3D ray-casting scene, one instance per element.

Doors are left out (they stand open, so the robot can see and drive through doorways); IfcSpace, openings,
annotations and other non-physical products are left out too. Slabs and coverings are kept so the camera
sees floors; a storey with no floor (or no ceiling) under its rooms gets a synthetic plane. Optional as-built
deviations move or remove BIM objects and add clutter boxes the BIM does not contain; `SimWorld.changes`
records them as ground truth. Door plates (`sim.door_plates`, `bim.plates`) can be hung beside the doors.
"""

from __future__ import annotations

import hashlib
import logging
import zlib
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import open3d as o3d

from bimfactor.bim.grid import GridSpec, band_polygons, rasterise_polygons
from bimfactor.bim.ifc import FIXED_OBJECT_CLASSES, IfcElement, IfcModel, Mesh
from bimfactor.bim.plates import DOOR_PLATE_LABEL, door_plates
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.rooms import OUTSIDE
from bimfactor.config import AsBuiltConfig, DoorPlateSimConfig

log = logging.getLogger(__name__)

# Products that are not physical surfaces a camera sees.
NON_PHYSICAL_CLASSES = (
    "IfcSpace",
    "IfcOpeningElement",
    "IfcAnnotation",
    "IfcSite",
    "IfcVirtualElement",
    "IfcSpatialZone",
    "IfcGrid",
    "IfcBuildingStorey",
    "IfcBuilding",
)
# Physical, but open in the simulated world: a door leaf would hide the room behind it.
OPEN_CLASSES = ("IfcDoor",)

# Synthetic instances carry no IFC class and no guid; their label says what they are.
FLOOR_LABEL, CEILING_LABEL, CLUTTER_LABEL = "floor", "ceiling", "clutter"
NO_OBJECT = -1
PLATE_PROBE_M = 0.6  # a plate's wall is looked for this far in front of the door's face (and as far behind)
PLATE_THICKNESS_M = 0.01
TEXTURE_HEIGHT_PX = 96  # a plate's printed text, drawn at this many texels high
PLATE_PAPER, PLATE_INK = 0.92, 0.06  # reflectance of the plate and of its text

_STRUCTURE_LABELS = (  # IFC class (or supertype) → label of a structural instance, first match wins
    ("IfcWall", "wall"),
    ("IfcCurtainWall", "wall"),
    ("IfcSlab", "slab"),
    ("IfcCovering", "covering"),
    ("IfcRoof", "roof"),
    ("IfcColumn", "column"),
    ("IfcBeam", "beam"),
    ("IfcStair", "stair"),
    ("IfcStairFlight", "stair"),
    ("IfcRamp", "stair"),
    ("IfcRailing", "railing"),
    ("IfcWindow", "window"),
    ("IfcMember", "member"),
    ("IfcPlate", "plate"),
    ("IfcFooting", "footing"),
)
# Fixed albedo (8-bit sRGB) per label: walls light grey, floors darker, objects in category colours.
ALBEDO_BY_LABEL: dict[str, tuple[int, int, int]] = {
    "wall": (205, 203, 198),
    "slab": (125, 112, 98),
    "covering": (215, 212, 205),
    FLOOR_LABEL: (125, 112, 98),
    CEILING_LABEL: (232, 232, 228),
    "roof": (150, 92, 80),
    "column": (182, 180, 174),
    "beam": (182, 180, 174),
    "member": (170, 168, 160),
    "plate": (170, 168, 160),
    "stair": (140, 130, 120),
    "railing": (90, 90, 95),
    "footing": (110, 110, 110),
    "window": (165, 200, 225),
    "chair": (170, 60, 50),
    "table": (150, 105, 60),
    "coffee table": (140, 95, 55),
    "desk": (135, 100, 70),
    "sofa": (60, 90, 150),
    "bed": (200, 180, 150),
    "bookshelf": (115, 78, 48),
    "cabinet": (160, 140, 110),
    "kitchen counter": (185, 175, 160),
    "refrigerator": (225, 225, 230),
    "sink": (236, 236, 240),
    "water closet": (242, 242, 242),
    "bathtub": (230, 232, 236),
    "fire hydrant": (200, 30, 30),
    CLUTTER_LABEL: (90, 150, 70),
}
FLOOR_PLANE_DROP_M = 0.005  # a synthetic floor lies this far below the storey elevation, under any partial slab
_SURFACE_CHECK_SAMPLES = 256
_SURFACE_CHECK_SHARE = 0.9  # a storey has a floor (ceiling) when this share of probe rays finds one
_PROBE_HEIGHT_M = 0.5
_MOVE_ATTEMPTS = 30
_CLUTTER_ATTEMPTS = 200
_CLUTTER_SIDE_M = (0.3, 0.8)
_CLUTTER_HEIGHT_M = (0.3, 1.0)


def label_albedo(label: str) -> np.ndarray:
    """(3,) float32 albedo in [0, 1] for a label: the fixed table, else a stable colour from the label's hash."""
    if label in ALBEDO_BY_LABEL:
        return np.asarray(ALBEDO_BY_LABEL[label], np.float32) / 255.0
    digest = hashlib.sha256(label.encode()).digest()
    return (60 + np.frombuffer(digest[:3], np.uint8).astype(np.float32) * (160 / 255)) / 255.0


def structure_label(element: IfcElement) -> str:
    """The label of an element that is no BIM object: its structural family ('wall', 'slab', ...)."""
    for ifc_class, label in _STRUCTURE_LABELS:
        if element.is_a(ifc_class):
            return label
    name = element.ifc_class.removeprefix("Ifc")
    return name.lower() if name else "element"


def drivable_storeys(prior: BimPrior) -> list[int]:
    """Storeys with at least two rooms and navigable space: where a robot can drive from room to room."""
    rooms = Counter(r.storey_index for r in prior.rooms)
    return [s.storey.index for s in prior.storeys if rooms[s.storey.index] >= 2 and s.navigable.any()]


def is_physical(element: IfcElement) -> bool:
    """True when the element is a visible surface of the simulated world (not a space, opening, or open door)."""
    return element.mesh is not None and not any(element.is_a(c) for c in NON_PHYSICAL_CLASSES + OPEN_CLASSES)


@dataclass
class SimWorld:
    """The world the sensors see: one mesh and one instance record per id, the Open3D scene built from them.

    `instances[i]` is {"id", "guid", "ifc_class", "object_id", "label"}; `meshes[i]` its world-frame mesh;
    `albedo` (I, 3) float32 in [0, 1]; `changes` the as-built deviations from the BIM (empty by default).
    """

    instances: list[dict]
    meshes: list[Mesh]
    albedo: np.ndarray
    changes: list[dict]
    storey_elevations_m: list[float]
    scene: o3d.t.geometry.RaycastingScene = field(repr=False)
    geometry_to_instance: np.ndarray = field(repr=False)
    textures: dict[int, PlateTexture] = field(default_factory=dict, repr=False)  # instance id → its printed face

    @classmethod
    def from_model(
        cls,
        model: IfcModel,
        prior: BimPrior,
        as_built: AsBuiltConfig,
        rng: np.random.Generator,
        door_plates: DoorPlateSimConfig | None = None,
    ) -> SimWorld:
        """Build the world from the IFC model's physical elements, with the as-built deviations `as_built` asks for
        and, when `door_plates` is enabled, the door plates of `bim.plates`."""
        object_by_guid = {o.guid: o for o in prior.objects}
        builder = _Builder()
        movable: list[int] = []
        for element in model.elements:
            if not is_physical(element):
                continue
            assert element.mesh is not None
            obj = object_by_guid.get(element.guid)
            if obj is None:
                iid = builder.add(element.mesh, element.guid, element.ifc_class, NO_OBJECT, structure_label(element))
                continue
            iid = builder.add(element.mesh, element.guid, element.ifc_class, obj.id, obj.label)
            if not any(element.is_a(c) for c in FIXED_OBJECT_CLASSES):
                movable.append(iid)
        changes = _apply_as_built(builder, movable, prior, as_built, rng)
        _add_missing_floors_and_ceilings(builder, model, prior)
        if door_plates is not None and door_plates.enabled:
            _hang_door_plates(builder, prior, door_plates)
        world = builder.build(changes, [s.storey.elevation_m for s in prior.storeys])
        log.info(
            "sim world: %d instances, %d triangles, %d as-built changes",
            len(world.instances),
            sum(len(m.faces) for m in world.meshes),
            len(changes),
        )
        return world

    # -------------------------------------------------------------------------------- queries

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast (N, 6) float32 rays (origin, direction): (N,) hit parameter t (inf: none), (N,) int32 instance
        (-1: none), (N, 3) float32 unit normals of the hit triangles (sign arbitrary)."""
        answer = self.scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, np.float32)))
        t_hit = answer["t_hit"].numpy()
        geometry = answer["geometry_ids"].numpy()
        hit = np.isfinite(t_hit)
        instance = np.full(len(t_hit), -1, np.int32)
        instance[hit] = self.geometry_to_instance[geometry[hit]]
        return t_hit, instance, answer["primitive_normals"].numpy()

    def instance_ids_of_guid(self, guid: str) -> list[int]:
        """Instance ids of an IFC element (empty when it is not in the world: removed, open door, non-physical)."""
        return [rec["id"] for rec in self.instances if guid and rec["guid"] == guid]

    def added_obstacles(self, spec: GridSpec, storey_index: int, z_lo: float, z_hi: float) -> np.ndarray:
        """(rows, cols) bool: cells the as-built changes newly block on a storey (moved objects, clutter)
        between absolute heights z_lo and z_hi."""
        mask = np.zeros(spec.shape, np.uint8)
        for change in self.changes:
            if change["kind"] not in ("moved", "clutter") or change["storey_index"] != storey_index:
                continue
            rasterise_polygons(band_polygons(self.meshes[change["instance_id"]], z_lo, z_hi), spec, out=mask)
        return mask.astype(bool)


class _Builder:
    """Collects instances (mesh + record) before the scene is made."""

    def __init__(self) -> None:
        self.instances: list[dict] = []
        self.meshes: list[Mesh] = []
        self.removed: set[int] = set()

    def add(self, mesh: Mesh, guid: str, ifc_class: str, object_id: int, label: str, **extra: Any) -> int:
        iid = len(self.instances)
        record = {"id": iid, "guid": guid, "ifc_class": ifc_class, "object_id": object_id, "label": label, **extra}
        self.instances.append(record)
        self.meshes.append(mesh)
        return iid

    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """A scratch scene of what is in the world so far (for the floor and ceiling probes)."""
        scene = o3d.t.geometry.RaycastingScene()
        for iid, mesh in enumerate(self.meshes):
            if iid not in self.removed:
                _add_mesh(scene, mesh)
        return scene

    def build(self, changes: list[dict], elevations: list[float]) -> SimWorld:
        """Renumber the surviving instances 0..I-1 (removed objects vanish) and make the scene."""
        keep = [i for i in range(len(self.instances)) if i not in self.removed]
        new_id = {old: new for new, old in enumerate(keep)}
        instances = [{**self.instances[old], "id": new_id[old]} for old in keep]
        meshes = [self.meshes[old] for old in keep]
        for change in changes:
            if "instance_id" in change:
                change["instance_id"] = new_id[change["instance_id"]]
        scene = o3d.t.geometry.RaycastingScene()
        geometry_ids = [_add_mesh(scene, m) for m in meshes]
        lookup = np.full(max(geometry_ids, default=-1) + 1, -1, np.int32)
        lookup[geometry_ids] = np.arange(len(meshes), dtype=np.int32)
        albedo = np.asarray([label_albedo(rec["label"]) for rec in instances], np.float32).reshape(-1, 3)
        textures = {rec["id"]: PlateTexture.of(rec) for rec in instances if "plate_face_m" in rec}
        return SimWorld(instances, meshes, albedo, changes, elevations, scene, lookup, textures)


def _add_mesh(scene: o3d.t.geometry.RaycastingScene, mesh: Mesh) -> int:
    vertices = o3d.core.Tensor(mesh.vertices.astype(np.float32))
    return int(scene.add_triangles(vertices, o3d.core.Tensor(mesh.faces.astype(np.uint32))))


# ------------------------------------------------------------------------------------------ as-built deviations


def _apply_as_built(
    builder: _Builder, movable: list[int], prior: BimPrior, cfg: AsBuiltConfig, rng: np.random.Generator
) -> list[dict]:
    """Move, remove and add objects in the builder; returns the change records (instance ids pre-renumbering)."""
    changes: list[dict] = []
    order = rng.permutation(len(movable)) if movable else np.zeros(0, int)
    n_removed = round(cfg.removed_fraction * len(movable))
    n_moved = min(round(cfg.moved_fraction * len(movable)), len(movable) - n_removed)
    objects = {o.id: o for o in prior.objects}
    for k in order[:n_removed]:
        rec = builder.instances[movable[k]]
        builder.removed.add(movable[k])
        obj = objects[rec["object_id"]]
        changes.append(
            {
                "kind": "removed",
                "guid": rec["guid"],
                "object_id": rec["object_id"],
                "label": rec["label"],
                "storey_index": obj.storey_index,
                "position_m": list(obj.position_m),
            }
        )
    for k in order[n_removed : n_removed + n_moved]:
        iid = movable[k]
        rec = builder.instances[iid]
        obj = objects[rec["object_id"]]
        pivot = builder.meshes[iid].bounds.mean(axis=0)[:2]
        mesh, shift, yaw = _move_object(builder.meshes[iid], prior, obj.storey_index, cfg.moved_max_m, rng)
        builder.meshes[iid] = mesh
        changes.append(
            {
                "kind": "moved",
                "guid": rec["guid"],
                "object_id": rec["object_id"],
                "label": rec["label"],
                "storey_index": obj.storey_index,
                "instance_id": iid,
                "position_m": list(obj.position_m),
                "pivot_xy_m": [float(pivot[0]), float(pivot[1])],
                "yaw_rad": float(yaw),
                "shift_xy_m": [float(shift[0]), float(shift[1])],
            }
        )
    for _ in range(cfg.clutter_count):
        clutter = _clutter_box(prior, changes, rng)
        if clutter is None:
            added = sum(c["kind"] == "clutter" for c in changes)
            log.warning("no free place left for a clutter box; %d of %d added", added, cfg.clutter_count)
            break
        mesh, record = clutter
        record["instance_id"] = builder.add(mesh, "", "", NO_OBJECT, CLUTTER_LABEL)
        changes.append(record)
    return changes


def _move_object(
    mesh: Mesh, prior: BimPrior, storey_index: int, max_shift_m: float, rng: np.random.Generator
) -> tuple[Mesh, np.ndarray, float]:
    """Turn the mesh by a yaw about its bounding-box centre (the pivot), then shift it by ≤ max_shift_m, to a
    place clear of the structure and inside the building (the last try when none is)."""
    layers = prior.storeys[storey_index]
    center = mesh.bounds.mean(axis=0)
    best: tuple[Mesh, np.ndarray, float] | None = None
    for _ in range(_MOVE_ATTEMPTS):
        yaw = float(rng.uniform(-np.pi, np.pi))
        radius, angle = max_shift_m * np.sqrt(rng.uniform()), rng.uniform(-np.pi, np.pi)
        shift = np.array([radius * np.cos(angle), radius * np.sin(angle)])
        c, s = np.cos(yaw), np.sin(yaw)
        xy = (mesh.vertices[:, :2] - center[:2]) @ np.array([[c, s], [-s, c]]) + center[:2] + shift
        moved = Mesh(np.column_stack([xy, mesh.vertices[:, 2]]), mesh.faces)
        best = (moved, shift, yaw)
        lo, hi = moved.bounds
        sub, window = prior.grid.window(lo[0], lo[1], hi[0], hi[1])
        footprint = rasterise_polygons(list(moved.vertices[moved.faces][:, :, :2]), sub).astype(bool)
        if not (layers.structure[window][footprint].any() or (layers.room_labels[window][footprint] == OUTSIDE).any()):
            break
    assert best is not None
    return best


def _clutter_box(prior: BimPrior, changes: list[dict], rng: np.random.Generator) -> tuple[Mesh, dict] | None:
    """A box standing on a navigable cell with room for it, away from the other clutter; None if none fits."""
    storeys = [s for s in prior.storeys if s.storey.index in drivable_storeys(prior)]
    if not storeys:
        return None
    weights = np.asarray([s.navigable.sum() for s in storeys], float)
    placed = [np.asarray(c["position_m"][:2]) for c in changes if c["kind"] == "clutter"]
    for _ in range(_CLUTTER_ATTEMPTS):
        layers = storeys[rng.choice(len(storeys), p=weights / weights.sum())]
        size = np.array([*rng.uniform(*_CLUTTER_SIDE_M, size=2), rng.uniform(*_CLUTTER_HEIGHT_M)])
        cells = np.flatnonzero(layers.navigable & (layers.clearance_m >= np.hypot(*size[:2]) / 2 + 0.05))
        if len(cells) == 0:
            continue
        rc = np.array(np.unravel_index(cells[rng.integers(len(cells))], layers.navigable.shape))
        xy = prior.grid.cell_to_world(rc)[0]
        if any(np.linalg.norm(xy - p) < 1.5 for p in placed):
            continue
        yaw = float(rng.uniform(-np.pi, np.pi))
        z0 = layers.storey.elevation_m
        mesh = _box_mesh(xy, yaw, size, z0)
        record = {
            "kind": "clutter",
            "storey_index": layers.storey.index,
            "position_m": [float(xy[0]), float(xy[1]), float(z0 + size[2] / 2)],
            "size_m": [float(v) for v in size],
            "yaw_rad": yaw,
        }
        return mesh, record
    return None


def _box_mesh(center_xy: np.ndarray, yaw: float, size: np.ndarray, z0: float) -> Mesh:
    """A closed box mesh: footprint size[:2] turned by yaw about its centre, from z0 to z0 + size[2]."""
    c, s = np.cos(yaw), np.sin(yaw)
    half = size[:2] / 2
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half
    xy = corners @ np.array([[c, s], [-s, c]]) + center_xy
    vertices = np.vstack([np.column_stack([xy, np.full(4, z0)]), np.column_stack([xy, np.full(4, z0 + size[2])])])
    faces = np.array(
        [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6],
         [3, 0, 4], [3, 4, 7]],
        np.int32,
    )  # fmt: skip
    return Mesh(vertices, faces)


# ------------------------------------------------------------------------------------------ door plates


@dataclass(frozen=True)
class PlateTexture:
    """What a door plate shows: its text in black on white, printed on its front face.

    `face_m` is the face's centre (x, y, z), `right_xy` the unit vector along the wall to a reader's right,
    `size_m` its width and height. The text is drawn once (`TEXTURE_HEIGHT_PX` high) into a mipmap pyramid; a
    camera samples the level whose texel matches its pixel's footprint, as a real sensor averages over a pixel
    rather than picking one point of the print (`sample`).
    """

    face_m: np.ndarray
    right_xy: np.ndarray
    size_m: np.ndarray
    levels: tuple[np.ndarray, ...] = field(repr=False)

    @classmethod
    def of(cls, record: dict) -> PlateTexture:
        """The texture of a plate's instance record (`_hang_door_plates`)."""
        width, height = (float(v) for v in record["plate_size_m"])
        image = _print_text(str(record["text"]), round(TEXTURE_HEIGHT_PX * width / height), TEXTURE_HEIGHT_PX)
        levels = [image]
        while min(levels[-1].shape) >= 4:
            levels.append(cv2.pyrDown(levels[-1]))
        return cls(
            np.asarray(record["plate_face_m"], float),
            np.asarray(record["plate_right_xy"], float),
            np.array([width, height]),
            tuple(levels),
        )

    def sample(self, points: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
        """(n,) reflectance in [0, 1] at (n, 3) world points on the face, each seen by a pixel `footprint_m` wide."""
        u = (points[:, :2] - self.face_m[:2]) @ self.right_xy / self.size_m[0] + 0.5
        v = 0.5 - (points[:, 2] - self.face_m[2]) / self.size_m[1]
        texel_m = self.size_m[1] / TEXTURE_HEIGHT_PX
        level = np.clip(np.round(np.log2(np.maximum(footprint_m / texel_m, 1.0))), 0, len(self.levels) - 1)
        out = np.empty(len(points), np.float32)
        for k in np.unique(level).astype(int):
            mine = level == k
            image = self.levels[k]
            rows = np.clip((v[mine] * image.shape[0]).astype(int), 0, image.shape[0] - 1)
            cols = np.clip((u[mine] * image.shape[1]).astype(int), 0, image.shape[1] - 1)
            out[mine] = image[rows, cols]
        return out


def _print_text(text: str, width: int, height: int) -> np.ndarray:
    """(height, width) float32 reflectance: `text` centred in a sans-serif face, PLATE_INK on PLATE_PAPER."""
    image = np.full((height, width), 255, np.uint8)
    font, thickness = cv2.FONT_HERSHEY_SIMPLEX, max(1, height // 12)
    (w, h), _ = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min(0.8 * width / max(w, 1), 0.55 * height / max(h, 1))
    thickness = max(1, round(thickness * scale))
    (w, h), _ = cv2.getTextSize(text, font, scale, thickness)
    origin = ((width - w) // 2, (height + h) // 2)
    cv2.putText(image, text, origin, font, scale, 0, thickness, cv2.LINE_AA)
    return PLATE_INK + (PLATE_PAPER - PLATE_INK) * image.astype(np.float32) / 255.0


def _hang_door_plates(builder: _Builder, prior: BimPrior, cfg: DoorPlateSimConfig) -> None:
    """A thin box per plate of `door_plates(prior)` on the wall beside its door, on the left or right as the door's
    guid decides; its instance record carries the plate's `text`. A plate whose wall is not found is skipped."""
    scene = builder.scene()
    doors = {d.id: d for d in prior.doors}
    width, height = cfg.size_m
    hung = 0
    for plate in door_plates(prior):
        door = doors[plate.door_id]
        side = 1.0 if zlib.crc32(door.guid.encode()) & 1 else -1.0
        along = np.asarray(plate.axis_xy) * side * (plate.door_width_m / 2 + cfg.beside_m + width / 2)
        out = np.asarray(plate.normal_xy)
        z = prior.storeys[plate.storey_index].storey.elevation_m + cfg.height_m
        origin = np.asarray(plate.xy) + along + out * PLATE_PROBE_M
        ray = np.concatenate([origin, [z], -out, [0.0]])[None].astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0]
        if not np.isfinite(t_hit) or t_hit > 2 * PLATE_PROBE_M:
            continue
        face = origin - out * (t_hit - PLATE_THICKNESS_M / 2 - 0.005)
        size = np.array([width, PLATE_THICKNESS_M, height])
        mesh = _box_mesh(face, float(np.arctan2(plate.axis_xy[1], plate.axis_xy[0])), size, z - height / 2)
        front = face + out * PLATE_THICKNESS_M / 2
        right = np.array([-out[1], out[0]])  # the reader's right, facing the plate
        builder.add(
            mesh,
            "",
            "DoorPlate",
            NO_OBJECT,
            DOOR_PLATE_LABEL,
            text=plate.text,
            storey_index=plate.storey_index,
            plate_face_m=[float(front[0]), float(front[1]), float(z)],
            plate_right_xy=[float(right[0]), float(right[1])],
            plate_size_m=[float(width), float(height)],
        )
        hung += 1
    log.info("sim world: %d door plates", hung)


# ------------------------------------------------------------------------------------------ floors and ceilings


def _add_missing_floors_and_ceilings(builder: _Builder, model: IfcModel, prior: BimPrior) -> None:
    """Give every drivable storey a floor, then a ceiling, where probe rays from its rooms find none."""
    probes = {index: _probe_points(prior, index) for index in drivable_storeys(prior)}
    probes = {k: v for k, v in probes.items() if len(v)}
    x0, x1, y0, y1 = prior.grid.extent
    scene = builder.scene()
    for index, points in probes.items():
        elevation = prior.storeys[index].storey.elevation_m
        t = _probe(scene, points, elevation, up=False)
        if np.mean(np.abs(t - _PROBE_HEIGHT_M) <= 0.2) < _SURFACE_CHECK_SHARE:
            builder.add(_plane(x0, x1, y0, y1, elevation - FLOOR_PLANE_DROP_M), "", "", NO_OBJECT, FLOOR_LABEL)
            log.info("storey %d has no floor under its rooms: added a floor plane at %.2f m", index, elevation)
    scene = builder.scene()
    for index, points in probes.items():
        elevation = prior.storeys[index].storey.elevation_m
        t = _probe(scene, points, elevation, up=True)
        if np.mean(np.isfinite(t)) < _SURFACE_CHECK_SHARE:
            height = _ceiling_height(model, prior, index)
            builder.add(_plane(x0, x1, y0, y1, height), "", "", NO_OBJECT, CEILING_LABEL)
            log.info("storey %d has no ceiling over its rooms: added a ceiling plane at %.2f m", index, height)


def _probe_points(prior: BimPrior, storey_index: int) -> np.ndarray:
    """(K, 2) world xy of up to a few hundred navigable cells, spread evenly over the storey."""
    cells = np.argwhere(prior.storeys[storey_index].navigable)
    if len(cells) == 0:
        return np.zeros((0, 2))
    pick = np.linspace(0, len(cells) - 1, min(_SURFACE_CHECK_SAMPLES, len(cells))).astype(int)
    return prior.grid.cell_to_world(cells[pick])


def _probe(scene: o3d.t.geometry.RaycastingScene, xy: np.ndarray, elevation: float, up: bool) -> np.ndarray:
    rays = np.zeros((len(xy), 6), np.float32)
    rays[:, :2] = xy
    rays[:, 2] = elevation + _PROBE_HEIGHT_M
    rays[:, 5] = 1.0 if up else -1.0
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()


def _ceiling_height(model: IfcModel, prior: BimPrior, storey_index: int) -> float:
    """The next storey's elevation, else the top of this storey's walls, else 3 m above its floor."""
    elevation = prior.storeys[storey_index].storey.elevation_m
    above = [s.storey.elevation_m for s in prior.storeys if s.storey.elevation_m > elevation + 2.0]
    if above:
        return min(above)
    tops = [e.mesh.bounds[1, 2] for e in model.of_class("IfcWall") if e.storey_index == storey_index and e.mesh]
    return float(max(tops)) if tops else elevation + 3.0


def _plane(x0: float, x1: float, y0: float, y1: float, z: float) -> Mesh:
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return Mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]], np.int32))
