"""Read an IFC file into plain typed data: storeys, elements with their semantics and world-frame meshes.

Everything downstream works on `IfcModel`, never on ifcopenshell objects. Geometry comes from
ifcopenshell's multi-threaded geometry iterator in world coordinates (metres, whatever the file's
length unit); the result is cached on disk keyed by the file's SHA-256.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
from dataclasses import asdict, dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from bimfactor.config import IfcReadConfig
from bimfactor.errors import IfcError, InputError
from bimfactor.io.atomic import atomic_path
from bimfactor.progress import progress

log = logging.getLogger(__name__)

SUPPORTED_SCHEMAS = ("IFC2X3", "IFC4", "IFC4X3")
CACHE_VERSION = 2
# Products that carry no physical geometry worth meshing.
_SKIPPED_CLASSES = ("IfcOpeningElement", "IfcAnnotation", "IfcSite", "IfcGrid")
_WALL_CLASSES = ("IfcWall", "IfcCurtainWall")


@dataclass(frozen=True)
class Storey:
    """A building storey; `index` orders storeys by elevation, 0 = lowest."""

    index: int
    guid: str
    name: str
    elevation_m: float


@dataclass
class Mesh:
    """A triangle mesh in the world frame: `vertices` (V, 3) float64 metres, `faces` (F, 3) int32."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])


@dataclass
class IfcElement:
    """One IFC product with the texts that name it and its geometry.

    `ancestry` lists the entity and its supertypes (e.g. IfcFurniture, IfcFurnishingElement, IfcElement,
    ...) so configuration can name a class and mean its subclasses too.
    """

    guid: str
    ifc_class: str
    ancestry: tuple[str, ...]
    name: str
    object_type: str
    type_name: str
    type_class: str
    predefined_type: str
    long_name: str
    storey_index: int | None
    space_guid: str | None
    mesh: Mesh | None = field(default=None, repr=False)

    def is_a(self, ifc_class: str) -> bool:
        return ifc_class in self.ancestry

    @property
    def raw_text(self) -> str:
        """All the human-written text that names this element, for the vocabulary and for display."""
        parts = [self.type_name, self.name, self.object_type, self.predefined_type]
        return " | ".join(p for p in parts if p)


@dataclass
class IfcModel:
    """A parsed IFC model: its storeys (sorted by elevation) and its elements."""

    source_path: str
    sha256: str
    schema: str
    length_unit_m: float
    storeys: list[Storey]
    elements: list[IfcElement]

    def of_class(self, *classes: str) -> list[IfcElement]:
        """Elements that are any of `classes` or their subclasses."""
        return [e for e in self.elements if any(e.is_a(c) for c in classes)]

    def by_guid(self) -> dict[str, IfcElement]:
        return {e.guid: e for e in self.elements}


# ---------------------------------------------------------------------------------------------- checks


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_schema(path: Path) -> str:
    """The schema named in a STEP file's header; raises IfcError for anything that is not IFC-SPF."""
    with path.open("rb") as fh:
        head = fh.read(65536).decode("latin-1")
        fh.seek(max(0, path.stat().st_size - 1024))
        tail = fh.read().decode("latin-1")
    if not head.lstrip().startswith("ISO-10303-21"):
        raise IfcError(f"{path}: not an IFC file (no ISO-10303-21 header)")
    if "END-ISO-10303-21" not in tail:
        raise IfcError(f"{path}: truncated IFC file (no END-ISO-10303-21 trailer)")
    match = re.search(r"FILE_SCHEMA\s*\(\s*\(\s*'([^']+)'", head)
    if match is None:
        raise IfcError(f"{path}: IFC header names no FILE_SCHEMA")
    return match.group(1).upper()


def _supported(schema: str) -> bool:
    return any(schema == s or schema.startswith(s + "_") for s in SUPPORTED_SCHEMAS)


# ---------------------------------------------------------------------------------------------- reading


def load_ifc(path: str | Path, cfg: IfcReadConfig) -> IfcModel:
    """Parse `path` (IFC2X3, IFC4, IFC4X3) into an `IfcModel`, from the on-disk cache when possible."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"IFC file not found: {path}")
    schema = read_schema(path)
    if not _supported(schema):
        raise IfcError(f"{path}: unsupported IFC schema {schema} (supported: {', '.join(SUPPORTED_SCHEMAS)})")
    sha = file_sha256(path)
    cache_file = _cache_path(cfg, sha)
    if cache_file is not None and cache_file.is_file():
        try:
            model = _read_cache(cache_file)
            model.source_path = str(path)
            log.info("geometry of %s read from cache %s", path.name, cache_file)
            return model
        except (OSError, ValueError, KeyError) as exc:
            log.warning("ignoring unreadable geometry cache %s (%s)", cache_file, exc)
    model = _parse(path, schema, sha, cfg.geometry_threads)
    if cache_file is not None:
        try:
            _write_cache(model, cache_file)
        except OSError as exc:
            log.warning("could not write geometry cache %s (%s)", cache_file, exc)
    return model


def _parse(path: Path, schema: str, sha: str, threads: int) -> IfcModel:
    import ifcopenshell
    import ifcopenshell.util.unit

    try:
        ifc = ifcopenshell.open(str(path))
    except Exception as exc:  # ifcopenshell raises a bare Error/RuntimeError for syntax problems
        raise IfcError(f"{path}: cannot parse IFC ({str(exc).splitlines()[0] if str(exc) else 'corrupt'})") from exc
    if not any(ifc.by_type(c) for c in _WALL_CLASSES if _has_entity(ifc.schema, c)):
        raise IfcError(f"{path}: the model has no walls (IfcWall / IfcCurtainWall); nothing to build a map from")
    unit_m = float(ifcopenshell.util.unit.calculate_unit_scale(ifc))
    storeys, storey_index_by_id = _read_storeys(ifc, unit_m)
    meshes = _mesh_products(ifc, path, threads)

    elements: list[IfcElement] = []
    for product in ifc.by_type("IfcProduct"):
        if any(product.is_a(c) for c in _SKIPPED_CLASSES) or (
            product.is_a("IfcSpatialStructureElement") and not (product.is_a("IfcSpace"))
        ):
            continue
        mesh = meshes.get(product.id())
        if mesh is None:
            continue
        elements.append(_element(ifc, product, mesh, storey_index_by_id, storeys))
    log.info("%s: %s, %d storeys, %d elements with geometry", path.name, schema, len(storeys), len(elements))
    return IfcModel(str(path), sha, schema, unit_m, storeys, elements)


def _has_entity(schema: str, ifc_class: str) -> bool:
    return _declaration(schema, ifc_class) is not None


@cache
def _declaration(schema: str, ifc_class: str):
    import ifcopenshell.ifcopenshell_wrapper as wrapper

    try:
        return wrapper.schema_by_name(schema).declaration_by_name(ifc_class)
    except (RuntimeError, KeyError):
        return None


@cache
def _ancestry_names(schema: str, ifc_class: str) -> tuple[str, ...]:
    decl = _declaration(schema, ifc_class)
    names = []
    while decl is not None:
        names.append(decl.name())
        decl = decl.supertype()
    return tuple(names)


def _read_storeys(ifc, unit_m: float) -> tuple[list[Storey], dict[int, int]]:
    import ifcopenshell.util.placement

    raw = []
    for st in ifc.by_type("IfcBuildingStorey"):
        if st.Elevation is not None:
            elevation = float(st.Elevation) * unit_m
        elif st.ObjectPlacement is not None:
            elevation = float(ifcopenshell.util.placement.get_local_placement(st.ObjectPlacement)[2, 3]) * unit_m
        else:
            elevation = 0.0
        raw.append((elevation, st.GlobalId, st.Name or "", st.id()))
    raw.sort(key=lambda r: (r[0], r[2]))
    storeys = [Storey(i, guid, name, elev) for i, (elev, guid, name, _) in enumerate(raw)]
    return storeys, {rid: i for i, (_, _, _, rid) in enumerate(raw)}


def _mesh_products(ifc, path: Path, threads: int) -> dict[int, Mesh]:
    import ifcopenshell.geom

    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    total = sum(1 for p in ifc.by_type("IfcProduct") if p.Representation is not None)
    iterator = ifcopenshell.geom.iterator(
        settings, ifc, max(1, min(threads, os.cpu_count() or 1)), exclude=_SKIPPED_CLASSES
    )
    meshes: dict[int, Mesh] = {}
    if not iterator.initialize():
        return meshes
    bar = progress(iter(int, 1), desc=f"meshing {path.name}", total=total, unit="shape")
    for _ in bar:
        shape = iterator.get()
        verts = np.asarray(shape.geometry.verts, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(shape.geometry.faces, dtype=np.int32).reshape(-1, 3)
        if len(faces):
            meshes[shape.id] = Mesh(verts, faces)
        if not iterator.next():
            break
    return meshes


def _element(ifc, product, mesh: Mesh, storey_index_by_id: dict[int, int], storeys: list[Storey]) -> IfcElement:
    import ifcopenshell.util.element as util

    ifc_type = util.get_type(product)
    predefined = util.get_predefined_type(product) or ""
    if not predefined and ifc_type is not None:  # IFC2X3 flow terminals carry it on their type only
        predefined = getattr(ifc_type, "PredefinedType", None) or ""
    if predefined in ("NOTDEFINED", "USERDEFINED"):
        predefined = ""
    container = util.get_container(product)
    space_guid = None
    if product.is_a("IfcSpace"):
        container = util.get_aggregate(product)
    elif container is not None and container.is_a("IfcSpace"):
        space_guid = container.GlobalId
    # Walk up (space → storey, or aggregated parts → whole) until a storey is found.
    storey_index = None
    node, hops = container, 0
    while node is not None and hops < 8:
        if node.id() in storey_index_by_id:
            storey_index = storey_index_by_id[node.id()]
            break
        node = util.get_aggregate(node) or util.get_container(node)
        hops += 1
    if storey_index is None and storeys:
        storey_index = _storey_by_height(float(mesh.vertices[:, 2].min()), storeys)
    return IfcElement(
        guid=product.GlobalId,
        ifc_class=product.is_a(),
        ancestry=_ancestry_names(ifc.schema, product.is_a()),
        name=(product.Name or "").strip(),
        object_type=(getattr(product, "ObjectType", None) or "").strip(),
        type_name=((ifc_type.Name or "") if ifc_type is not None else "").strip(),
        type_class=ifc_type.is_a() if ifc_type is not None else "",
        predefined_type=predefined,
        long_name=((getattr(product, "LongName", None) or "") if product.is_a("IfcSpace") else "").strip(),
        storey_index=storey_index,
        space_guid=space_guid,
        mesh=mesh,
    )


def _storey_by_height(z_min: float, storeys: list[Storey]) -> int:
    """The highest storey whose elevation lies at or below the element's base (with 0.5 m slack)."""
    below = [s.index for s in storeys if s.elevation_m <= z_min + 0.5]
    return below[-1] if below else storeys[0].index


# ---------------------------------------------------------------------------------------------- cache


def _cache_path(cfg: IfcReadConfig, sha: str) -> Path | None:
    if not cfg.cache_dir:
        return None
    import ifcopenshell

    tag = re.sub(r"[^0-9A-Za-z.]", "_", ifcopenshell.version)
    return Path(cfg.cache_dir).expanduser() / f"{sha}.v{CACHE_VERSION}.ifcos{tag}.npz"


def _write_cache(model: IfcModel, cache_file: Path) -> None:
    verts, faces, vcount, fcount, meta = [], [], [], [], []
    for el in model.elements:
        assert el.mesh is not None
        verts.append(el.mesh.vertices)
        faces.append(el.mesh.faces)
        vcount.append(len(el.mesh.vertices))
        fcount.append(len(el.mesh.faces))
        record = asdict(el)
        record.pop("mesh")
        meta.append(record)
    header = {
        "sha256": model.sha256,
        "schema": model.schema,
        "length_unit_m": model.length_unit_m,
        "storeys": [asdict(s) for s in model.storeys],
        "elements": meta,
    }
    with atomic_path(cache_file) as tmp, tmp.open("wb") as fh:
        np.savez(
            fh,
            header=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8),
            vertices=np.concatenate(verts) if verts else np.zeros((0, 3)),
            faces=np.concatenate(faces) if faces else np.zeros((0, 3), np.int32),
            vertex_counts=np.asarray(vcount, dtype=np.int64),
            face_counts=np.asarray(fcount, dtype=np.int64),
        )


def _read_cache(cache_file: Path) -> IfcModel:
    with np.load(cache_file) as data:
        header = json.loads(bytes(data["header"]).decode())
        verts, faces = data["vertices"], data["faces"]
        v_ends = np.cumsum(data["vertex_counts"])
        f_ends = np.cumsum(data["face_counts"])
    elements = []
    for i, record in enumerate(header["elements"]):
        v0 = v_ends[i - 1] if i else 0
        f0 = f_ends[i - 1] if i else 0
        record["ancestry"] = tuple(record["ancestry"])
        mesh = Mesh(verts[v0 : v_ends[i]].copy(), faces[f0 : f_ends[i]].copy())
        elements.append(IfcElement(**record, mesh=mesh))
    storeys = [Storey(**s) for s in header["storeys"]]
    return IfcModel("", header["sha256"], header["schema"], header["length_unit_m"], storeys, elements)
