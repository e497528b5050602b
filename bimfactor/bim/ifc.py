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
CACHE_VERSION = 3  # 3: models that fail the integrity and plausibility checks are never cached
# Products that carry no physical geometry worth meshing.
_SKIPPED_CLASSES = ("IfcOpeningElement", "IfcAnnotation", "IfcSite", "IfcGrid")
_WALL_CLASSES = ("IfcWall", "IfcCurtainWall")


@dataclass(frozen=True)
class Storey:
    """A building storey; `index` orders storeys by elevation, 0 = lowest. `is_floor`: a robot can stand on it
    (`bim.prior.floor_levels`; a foundation, a roof or a reference level is kept, but holds no room), and
    `floor_note` says why or why not."""

    index: int
    guid: str
    name: str
    elevation_m: float
    is_floor: bool = True
    floor_note: str = ""


@dataclass
class Mesh:
    """A triangle mesh in the world frame: `vertices` (V, 3) float64 metres, `faces` (F, 3) int32."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])


# Labelled BIM objects that are part of the building: structure in the occupancy grid (not furniture), never
# moved or removed in an as-built world.
FIXED_OBJECT_CLASSES = ("IfcDoor", "IfcWindow", "IfcStair", "IfcStairFlight", "IfcRamp", "IfcTransportElement")


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
        tail = _tail(fh, path.stat().st_size)
    if not head.lstrip().startswith("ISO-10303-21"):
        raise IfcError(f"{path}: not an IFC file (no ISO-10303-21 header)")
    if "END-ISO-10303-21" not in tail:
        raise IfcError(f"{path}: truncated IFC file (no END-ISO-10303-21 trailer)")
    match = re.search(r"FILE_SCHEMA\s*\(\s*\(\s*'([^']+)'", head)
    if match is None:
        raise IfcError(f"{path}: IFC header names no FILE_SCHEMA")
    return match.group(1).upper()


def _tail(fh, size: int, keep: int = 1024, block: int = 1 << 16) -> str:
    """The last `keep` bytes of the file before its trailing whitespace (however much of it there is)."""
    end = size
    while end > 0:
        start = max(0, end - block)
        fh.seek(start)
        content = fh.read(end - start).rstrip()
        if content:
            end = start + len(content)
            break
        end = start
    fh.seek(max(0, end - keep))
    return fh.read(end - max(0, end - keep)).decode("latin-1")


def _supported(schema: str) -> bool:
    return any(schema == s or schema.startswith(s + "_") for s in SUPPORTED_SCHEMAS)


# ---------------------------------------------------------------------------------------------- reading


def load_ifc(path: str | Path, cfg: IfcReadConfig) -> IfcModel:
    """Parse `path` (IFC2X3, IFC4, IFC4X3) into an `IfcModel`, from the on-disk cache when possible.

    Raises IfcError for a file that is corrupt, truncated, mislabelled, has no storeys, no wall geometry or
    implausible dimensions (a wrong length unit); such a model is never cached.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"IFC file not found: {path}")
    schema = read_schema(path)
    if not _supported(schema):
        raise IfcError(f"{path}: unsupported IFC schema {schema} (supported: {', '.join(SUPPORTED_SCHEMAS)})")
    sha = file_sha256(path)
    cache_file = _cache_path(cfg, sha)
    model = None
    if cache_file is not None and cache_file.is_file():
        try:
            model = _read_cache(cache_file, sha)
            log.info("geometry of %s read from cache %s", path.name, cache_file)
        except Exception as exc:  # a cache is disposable: whatever is wrong with it, build it again
            log.warning(
                "geometry cache %s is unreadable (%s: %s); rebuilding it",
                cache_file,
                type(exc).__name__,
                " ".join(str(exc).split())[:200],
            )
    fresh = model is None
    if model is None:
        model = _parse(path, schema, sha, cfg.geometry_threads)
    model.source_path = str(path)
    _check_model(model, path)
    if fresh and cache_file is not None:
        try:
            _write_cache(model, cache_file)
        except OSError as exc:
            log.warning("could not write geometry cache %s (%s)", cache_file, exc)
    return model


def _parse(path: Path, schema: str, sha: str, threads: int) -> IfcModel:
    import ifcopenshell.util.unit

    ifc = _open(path)
    walls = {w.id(): w for c in _WALL_CLASSES if _has_entity(ifc.schema, c) for w in ifc.by_type(c)}
    if not walls:
        raise IfcError(f"{path}: the model has no walls (IfcWall / IfcCurtainWall); nothing to build a map from")
    unit_m = float(ifcopenshell.util.unit.calculate_unit_scale(ifc))
    storeys, storey_index_by_id = _read_storeys(ifc, unit_m)
    if not storeys:
        raise IfcError(f"{path}: the model has no IfcBuildingStorey; rooms and objects are placed by storey")
    meshes = _mesh_products(ifc, path, threads)
    with_geometry = sum(_has_geometry(wall, meshes) for wall in walls.values())
    if with_geometry == 0:
        raise IfcError(
            f"{path}: none of its {len(walls)} walls (IfcWall / IfcCurtainWall) has geometry that can be meshed; "
            "nothing to build a map from"
        )
    if with_geometry < len(walls):
        log.warning(
            "%s: %d of %d walls have no geometry that can be meshed; they are left out of the map",
            path.name,
            len(walls) - with_geometry,
            len(walls),
        )

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


def _has_geometry(product, meshes: dict[int, Mesh]) -> bool:
    """The product is meshed, or it is made of parts (IfcRelAggregates) of which one is."""
    if product.id() in meshes:
        return True
    parts = (p for rel in getattr(product, "IsDecomposedBy", None) or () for p in rel.RelatedObjects)
    return any(part.id() in meshes for part in parts)


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


# ---------------------------------------------------------------------------------------------- integrity

# ifcopenshell's parser warns with this code when an entity has another attribute count than its schema says.
_ATTRIBUTE_COUNT_CODE = "VAL016"
_OFFSET = re.compile(r"\s*at offset (\d+)")
_INSTANCE = re.compile(r"for instance #(\d+)")
_COUNTS = re.compile(r"Expected (\d+) attribute values, found (\d+)")
_UNKNOWN_ENTITY = re.compile(r"Entity with name '([^']+)' not found in schema")
_DANGLING = re.compile(r"Instance reference #\d+ .*not found")
_OTHER_SCHEMAS = ("IFC2X3", "IFC4", "IFC4X3_ADD2")


@dataclass(frozen=True)
class _ParseMessage:
    severity: str  # "error", "warning", ...
    code: str
    text: str


@dataclass(frozen=True)
class _Problem:
    line: int  # 0 where unknown
    text: str
    dangling: bool  # a reference to an entity the file lacks: a symptom, usually of a cut or a syntax error
    schemas: frozenset[str]  # supported schemas in which the offending entity would be fine


def _open(path: Path):
    """ifcopenshell.open, with its parser's messages turned into IfcError naming the line of the first problem.

    Refused: syntax errors, references to entities the file lacks (a file cut short, the trailer added back),
    unknown entities, and entities with another attribute count than the header's schema gives them.
    """
    import ifcopenshell

    messages: list[_ParseMessage] = []
    try:
        ifc = _open_logged(ifcopenshell, path, messages)
    except Exception as exc:  # ifcopenshell raises a bare Error for syntax problems ("check logs")
        problems = _problems(path, None, messages)
        if problems:
            raise IfcError(f"{path}: IFC syntax error, {_describe(problems)}") from exc
        raise IfcError(f"{path}: cannot parse IFC ({' '.join(str(exc).split()) or 'corrupt'})") from exc
    problems = _problems(path, ifc, messages)
    if not problems:
        return ifc
    guessed = [p.schemas for p in problems if p.schemas]
    common = frozenset.intersection(*guessed) if guessed else frozenset()
    if common:
        other = " or ".join(sorted(s.removesuffix("_ADD2") for s in common))
        raise IfcError(
            f"{path}: the header says {ifc.schema} but the content looks like {other}, {_describe(problems)}"
        )
    if all(p.dangling for p in problems):
        raise IfcError(f"{path}: corrupt or truncated IFC file, {_describe(problems)}")
    raise IfcError(f"{path}: invalid IFC file, {_describe(problems)}")


def _open_logged(ifcopenshell, path: Path, messages: list[_ParseMessage]):
    """Open `path`, appending the parser's messages to `messages` (also when opening raises)."""
    import ifcopenshell.ifcopenshell_wrapper as wrapper

    logger_class = getattr(wrapper, "logger", None)
    if logger_class is not None and hasattr(logger_class, "FMT_INMEMORY"):
        logger = logger_class()
        logger.output_format(logger_class.FMT_INMEMORY)
        try:
            return ifcopenshell.open(str(path), logger=logger)
        finally:
            messages.extend(
                _ParseMessage(str(m.severity_string).lower(), str(m.code or ""), str(m.message)) for m in logger
            )
    # Older ifcopenshell: one process-wide text log ("[error] [CODE] [time] text", the code may be missing).
    wrapper.get_log()
    try:
        return ifcopenshell.open(str(path))
    finally:
        for line in wrapper.get_log().splitlines():
            match = re.match(r"\[(\w+)\]\s*(?:\[([A-Z]+\d+)\]\s*)?\[[^\]]*\]\s*(.*)", line)
            if match:
                messages.append(_ParseMessage(match[1].lower(), match[2] or "", match[3]))


def _problems(path: Path, ifc, messages: list[_ParseMessage]) -> list[_Problem]:
    """The parser's errors and attribute-count warnings, each with its line in the file."""
    picked = [m for m in messages if m.severity == "error" or m.code == _ATTRIBUTE_COUNT_CODE]
    if not picked:
        return []
    data = path.read_bytes()
    newlines = np.flatnonzero(np.frombuffer(data, np.uint8) == ord("\n"))
    instance_offsets: dict[int, int] | None = None
    schema = ifc.schema if ifc is not None else ""
    problems = []
    for m in picked:
        text, line, schemas = _OFFSET.sub("", m.text).strip(), 0, frozenset()
        if (found := _OFFSET.search(m.text)) is not None:
            line = int(np.searchsorted(newlines, int(found[1]))) + 1
        if (unknown := _UNKNOWN_ENTITY.search(m.text)) is not None:
            schemas = frozenset(s for s in _OTHER_SCHEMAS if s != schema and _has_entity(s, unknown[1]))
        instance, counts = _INSTANCE.search(m.text), _COUNTS.search(m.text)
        if instance is not None:
            if instance_offsets is None:
                instance_offsets = {int(x[1]): x.start() for x in re.finditer(rb"(?m)^[ \t]*#(\d+)[ \t]*=", data)}
            offset = instance_offsets.get(int(instance[1]))
            line = int(np.searchsorted(newlines, offset)) + 1 if offset is not None else 0
            if counts is not None and ifc is not None:
                try:
                    entity = ifc.by_id(int(instance[1])).is_a()
                except Exception:  # the instance itself may be what is broken
                    entity = ""
                if entity:
                    text = (
                        f"#{instance[1]} {entity} has {counts[2]} attribute values where {schema} expects {counts[1]}"
                    )
                    schemas = frozenset(
                        s
                        for s in _OTHER_SCHEMAS
                        if s != schema
                        and (decl := _declaration(s, entity)) is not None
                        and decl.attribute_count() == int(counts[2])
                    )
        problems.append(_Problem(line, text, _DANGLING.search(m.text) is not None, schemas))
    return problems


def _describe(problems: list[_Problem]) -> str:
    """'line N: <the first problem> (K problems in all)': the first in the file that is no dangling reference.

    A reference is reported where it is made, which is before the cut or the syntax error that lost its target.
    """
    ranked = sorted(problems, key=lambda p: (p.dangling, p.line == 0, p.line))
    first = ranked[0]
    where = f"line {first.line}: " if first.line else ""
    more = f" ({len(problems)} problems in all)" if len(problems) > 1 else ""
    return f"{where}{first.text.rstrip('.')}{more}"


# ---------------------------------------------------------------------------------------------- plausibility

_EXTENT_M = (1.0, 2000.0)  # a building's walls span between these (horizontally)
_WALL_THICKNESS_M = (0.02, 2.0)  # the median wall is between these thick
_TYPICAL_WALL_M = 0.25
_LENGTH_UNITS = {
    "millimetres": 0.001,
    "centimetres": 0.01,
    "decimetres": 0.1,
    "metres": 1.0,
    "inches": 0.0254,
    "feet": 0.3048,
}


def _check_model(model: IfcModel, path: str | Path) -> None:
    """IfcError unless the model has storeys and building-like dimensions (read before any grid is built).

    The walls' horizontal extent and median thickness (the short side of each wall's minimum-area rectangle)
    catch a wrong length unit: millimetres declared as metres make a 30 km building of 200 m thick walls.
    """
    if not model.storeys:
        raise IfcError(f"{path}: the model has no IfcBuildingStorey; rooms and objects are placed by storey")
    walls = [e.mesh for e in model.of_class(*_WALL_CLASSES) if e.mesh is not None and len(e.mesh.vertices)]
    if not walls:
        return  # a wall made of parts: no wall mesh to measure
    lo = np.min([m.vertices[:, :2].min(axis=0) for m in walls], axis=0)
    hi = np.max([m.vertices[:, :2].max(axis=0) for m in walls], axis=0)
    extent = float(np.max(hi - lo))
    thickness = float(np.median([_thickness(m) for m in walls]))
    if _plausible(extent, thickness):
        return
    declared = next(
        (name for name, m in _LENGTH_UNITS.items() if np.isclose(m, model.length_unit_m, rtol=1e-6)),
        f"units of {model.length_unit_m:g} m",
    )
    rescaled = {
        name: scale / model.length_unit_m
        for name, scale in _LENGTH_UNITS.items()
        if _plausible(extent * scale / model.length_unit_m, thickness * scale / model.length_unit_m)
    }
    guess = min(rescaled, key=lambda n: abs(np.log(max(thickness * rescaled[n], 1e-12) / _TYPICAL_WALL_M)), default="")
    said = f"the file says its lengths are in {declared}, but then its walls are {_length(thickness)} thick (median)"
    spans = f"and the building spans {_length(extent)}"
    if guess and guess != declared:
        raise IfcError(f"{path}: {said} {spans}: is it in {guess}? (IFCSIUNIT .LENGTHUNIT. in the file)")
    lo_t, hi_t = _WALL_THICKNESS_M
    lo_e, hi_e = _EXTENT_M
    raise IfcError(
        f"{path}: {said} {spans}, which is no building (expected walls {_length(lo_t)} to {_length(hi_t)} thick "
        f"spanning {_length(lo_e)} to {_length(hi_e)})"
    )


def _plausible(extent_m: float, thickness_m: float) -> bool:
    return _EXTENT_M[0] <= extent_m <= _EXTENT_M[1] and _WALL_THICKNESS_M[0] <= thickness_m <= _WALL_THICKNESS_M[1]


def _thickness(mesh: Mesh) -> float:
    """The short side of the minimum-area rectangle around the mesh's footprint."""
    import cv2

    xy = mesh.vertices[:, :2]
    (_, _), (w, h), _ = cv2.minAreaRect((xy - xy.min(axis=0)).astype(np.float32))
    return float(min(w, h))


def _length(metres: float) -> str:
    """A length for people: 0.2 mm, 290 mm, 86 m, 16.9 km."""
    value, unit = (metres * 1000, "mm") if metres < 1.0 else (metres, "m") if metres < 1000.0 else (metres / 1000, "km")
    return f"{value:.0f} {unit}" if value >= 100 else f"{value:.3g} {unit}"


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


def _read_cache(cache_file: Path, sha: str) -> IfcModel:
    """The cached model of the file with SHA-256 `sha`; any exception means the cache entry is unusable."""
    with np.load(cache_file, allow_pickle=False) as data:
        header = json.loads(bytes(data["header"]).decode())
        verts, faces = data["vertices"], data["faces"]
        v_counts, f_counts = data["vertex_counts"], data["face_counts"]
    if header["sha256"] != sha:
        raise ValueError(f"it holds the geometry of another file ({header['sha256']})")
    records = header["elements"]
    if (
        verts.ndim != 2
        or verts.shape[1:] != (3,)
        or faces.ndim != 2
        or faces.shape[1:] != (3,)
        or len(v_counts) != len(records)
        or len(f_counts) != len(records)
        or int(v_counts.sum()) != len(verts)
        or int(f_counts.sum()) != len(faces)
        or (len(v_counts) and (v_counts.min() < 0 or f_counts.min() < 0))
    ):
        raise ValueError("its arrays do not fit together")
    v_ends = np.cumsum(v_counts)
    f_ends = np.cumsum(f_counts)
    elements = []
    for i, record in enumerate(records):
        v0 = v_ends[i - 1] if i else 0
        f0 = f_ends[i - 1] if i else 0
        record["ancestry"] = tuple(record["ancestry"])
        mesh = Mesh(verts[v0 : v_ends[i]].copy(), faces[f0 : f_ends[i]].copy())
        if len(mesh.faces) and (mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices)):
            raise ValueError(f"element {i} has faces outside its vertices")
        elements.append(IfcElement(**record, mesh=mesh))
    storeys = [Storey(**s) for s in header["storeys"]]
    return IfcModel("", header["sha256"], header["schema"], header["length_unit_m"], storeys, elements)
