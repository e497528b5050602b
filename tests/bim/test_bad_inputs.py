"""Bad inputs to the offline stage fail as one `error:` line with exit code 2 (never "internal", exit 1):

corrupt geometry caches are rebuilt, corrupt prior folders are a FormatError naming the file and what is wrong,
and IFC files that parse but cannot be a building (mislabelled schema, no storeys, walls without geometry or
rooms, a wrong length unit, a cut or a syntax error) are an IfcError before any grid is built or anything cached.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from bimfactor.bim import ifc as ifc_module
from bimfactor.bim.ifc import load_ifc, read_schema
from bimfactor.bim.prior import PRIOR_VERSION, BimPrior, build_prior
from bimfactor.bim.synth import write_building
from bimfactor.errors import ConfigError, FormatError, IfcError
from tests.cli import assert_one_line_error, invoke


class _FakeEmbedder:
    """A text embedder that loads nothing: one-hot by a stable hash of the text."""

    name = "fake"
    dim = 16

    def encode(self, texts) -> np.ndarray:
        out = np.zeros((len(texts), self.dim), np.float32)
        for i, text in enumerate(texts):
            out[i, sum(text.encode()) % self.dim] = 1.0
        return out


def tiny_building(path: Path, *, storey: bool = True, door: bool = True, walls_without_geometry: int = 0) -> Path:
    """A 6 m x 5 m one-room IFC4 house in millimetres: 200 mm walls, a door, a table (~130 lines of text)."""
    import ifcopenshell
    import ifcopenshell.api.aggregate
    import ifcopenshell.api.context
    import ifcopenshell.api.geometry
    import ifcopenshell.api.root
    import ifcopenshell.api.spatial
    import ifcopenshell.api.unit
    from ifcopenshell.util.shape_builder import ShapeBuilder

    f = ifcopenshell.file(schema="IFC4")
    project = ifcopenshell.api.root.create_entity(f, ifc_class="IfcProject", name="Tiny")
    ifcopenshell.api.unit.assign_unit(f)  # millimetres
    model = ifcopenshell.api.context.add_context(f, context_type="Model")
    body = ifcopenshell.api.context.add_context(
        f, context_type="Model", context_identifier="Body", target_view="MODEL_VIEW", parent=model
    )
    site = ifcopenshell.api.root.create_entity(f, ifc_class="IfcSite", name="Site")
    building = ifcopenshell.api.root.create_entity(f, ifc_class="IfcBuilding", name="Building")
    ifcopenshell.api.aggregate.assign_object(f, products=[site], relating_object=project)
    ifcopenshell.api.aggregate.assign_object(f, products=[building], relating_object=site)
    container = building
    if storey:
        container = ifcopenshell.api.root.create_entity(f, ifc_class="IfcBuildingStorey", name="Ground floor")
        ifcopenshell.api.aggregate.assign_object(f, products=[container], relating_object=building)
    builder = ShapeBuilder(f)

    def box(ifc_class: str, name: str, x: float, y: float, size: tuple[float, float, float], geometry: bool = True):
        product = ifcopenshell.api.root.create_entity(f, ifc_class=ifc_class, name=name)
        matrix = np.eye(4)
        matrix[:2, 3] = (x, y)  # metres (the API converts to the project's millimetres)
        ifcopenshell.api.geometry.edit_object_placement(f, product=product, matrix=matrix)
        if geometry:
            w, d, h = (v * 1000 for v in size)
            solid = builder.extrude(builder.rectangle(size=(w, d)), h)
            representation = builder.get_representation(body, [solid])
            ifcopenshell.api.geometry.assign_representation(f, product=product, representation=representation)
        ifcopenshell.api.spatial.assign_container(f, products=[product], relating_structure=container)

    walls = [(0.0, 0.0, 6.0, 0.2), (0.0, 4.8, 6.0, 0.2), (0.0, 0.2, 0.2, 4.6), (5.8, 0.2, 0.2, 4.6)]
    for i, (x, y, w, d) in enumerate(walls):
        box("IfcWall", f"Wall {i}", x, y, (w, d, 2.7), geometry=i >= walls_without_geometry)
    if door:
        box("IfcDoor", "Door", 2.0, 0.0, (0.9, 0.2, 2.1))
    box("IfcFurniture", "Table", 3.0, 2.5, (1.6, 0.8, 0.75))
    f.write(str(path))
    return path


@pytest.fixture(scope="module")
def tiny_ifc(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_building(tmp_path_factory.mktemp("tiny") / "tiny.ifc")


def _edited(source: Path, target: Path, old: bytes, new: bytes) -> Path:
    data = source.read_bytes()
    assert old in data, old
    target.write_bytes(data.replace(old, new))
    return target


def _cli_prior(model: Path, tmp_path: Path) -> object:
    """`bimfactor prior MODEL -o tmp/out` with a geometry cache of its own in tmp/cache."""
    return invoke("prior", model, "-o", tmp_path / "out", "--set", f"bim.ifc.cache_dir={tmp_path / 'cache'}")


def _assert_refused(model: Path, tmp_path: Path, contains: str, geometry_cached: bool = False) -> str:
    """The IFC is refused in one line (exit 2) and kept as it was; no prior is written, and no geometry cached unless
    the geometry itself is sound (refused later, at the room stage)."""
    before = model.read_bytes()
    line = assert_one_line_error(_cli_prior(model, tmp_path), contains=contains)
    assert model.read_bytes() == before
    assert not (tmp_path / "out").exists()
    assert any((tmp_path / "cache").glob("*.npz")) == geometry_cached
    return line


# ------------------------------------------------------------------------------ 4: corrupt geometry cache


def _truncate(data: bytes) -> bytes:
    return data[: len(data) // 2]


def _flip_bit(data: bytes) -> bytes:
    middle = len(data) // 2
    return data[:middle] + bytes([data[middle] ^ 0x10]) + data[middle + 1 :]


def _random_bytes(data: bytes) -> bytes:
    return np.random.default_rng(0).integers(0, 256, len(data), dtype=np.uint8).tobytes()


def _other_files_cache(data: bytes) -> bytes:
    """A well-formed cache entry, but of another IFC file (its header names another SHA-256)."""
    import io
    import zipfile

    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        members = {name: zf.read(name) for name in zf.namelist()}
    header = np.load(io.BytesIO(members["header.npy"]))
    text = bytes(header).decode().replace('"sha256": "', '"sha256": "0', 1)
    buffer = io.BytesIO()
    np.save(buffer, np.frombuffer(text.encode(), np.uint8))
    members["header.npy"] = buffer.getvalue()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for name, content in members.items():
            zf.writestr(name, content)
    return out.getvalue()


CACHE_DAMAGE: dict[str, Callable[[bytes], bytes]] = {
    "truncated": _truncate,
    "bit flipped": _flip_bit,
    "random bytes": _random_bytes,
    "empty": lambda data: b"",
    "another file's": _other_files_cache,
}


@pytest.mark.parametrize("damage", list(CACHE_DAMAGE))
def test_a_corrupt_geometry_cache_is_rebuilt_replaced_and_warned_about(
    damage: str, tiny_ifc: Path, tmp_path: Path, session_cfg, caplog: pytest.LogCaptureFixture, monkeypatch
) -> None:
    cfg = session_cfg(f"bim.ifc.cache_dir={tmp_path}").bim.ifc
    first = load_ifc(tiny_ifc, cfg)
    (cache_file,) = tmp_path.glob("*.npz")
    good = cache_file.read_bytes()
    cache_file.write_bytes(CACHE_DAMAGE[damage](good))
    with caplog.at_level(logging.WARNING, logger="bimfactor.bim.ifc"):
        again = load_ifc(tiny_ifc, cfg)
    assert [e.guid for e in again.elements] == [e.guid for e in first.elements]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("unreadable" in w and cache_file.name in w and "rebuilding" in w for w in warnings), warnings
    # The bad entry was replaced: the next read comes from the cache again.
    assert cache_file.is_file() and cache_file.read_bytes() != CACHE_DAMAGE[damage](good)

    def no_parsing(*_args, **_kwargs):
        raise AssertionError("the cache was not replaced")

    monkeypatch.setattr(ifc_module, "_parse", no_parsing)
    assert len(load_ifc(tiny_ifc, cfg).elements) == len(first.elements)


# ------------------------------------------------------------------------------ 5: corrupt prior folder


@pytest.fixture(scope="module")
def tiny_prior(tiny_ifc: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real prior folder (built and saved by bimfactor) of the tiny house, with a text embedder that loads nothing."""
    from bimfactor.config import load_config

    folder = tmp_path_factory.mktemp("tiny-prior")
    cfg = load_config(None, [f"bim.ifc.cache_dir={folder / 'cache'}"])
    prior = build_prior(tiny_ifc, cfg, embedder=_FakeEmbedder())
    assert prior.rooms and prior.objects and prior.doors
    prior.save(folder / "prior")
    return folder / "prior"


def _json_edit(edit: Callable[[dict], object]) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        meta = json.loads((folder / "prior.json").read_text())
        result = edit(meta)
        (folder / "prior.json").write_text(json.dumps(meta if result is None else result))

    return apply


def _bytes_edit(name: str, edit: Callable[[bytes], bytes]) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        (folder / name).write_bytes(edit((folder / name).read_bytes()))

    return apply


def _set(path: str, value: object) -> Callable[[dict], None]:
    def edit(meta: dict) -> None:
        *parents, last = path.split(".")
        node = meta
        for part in parents:
            node = node[int(part)] if part.isdigit() else node[part]
        node[int(last) if last.isdigit() else last] = value

    return edit


def _drop(path: str) -> Callable[[dict], None]:
    def edit(meta: dict) -> None:
        *parents, last = path.split(".")
        node = meta
        for part in parents:
            node = node[int(part)] if part.isdigit() else node[part]
        del node[last]

    return edit


def _npz_edit(edit: Callable[[dict[str, np.ndarray]], None]) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        with np.load(folder / "arrays.npz") as archive:
            arrays = dict(archive)
        edit(arrays)
        np.savez_compressed(folder / "arrays.npz", **arrays)

    return apply


def _bad_utf8(data: bytes) -> bytes:
    return data.replace(b'"source_file": "', b'"source_file": "\xff\xfe', 1)


PRIOR_DAMAGE: dict[str, tuple[Callable[[Path], None], str, str]] = {
    # case: (damage, the file the message names, what it says)
    "arrays truncated": (_bytes_edit("arrays.npz", _truncate), "arrays.npz", "corrupt or truncated"),
    "arrays bit flipped": (_bytes_edit("arrays.npz", _flip_bit), "arrays.npz", "corrupt or truncated"),
    "arrays random bytes": (_bytes_edit("arrays.npz", _random_bytes), "arrays.npz", "not a NumPy .npz archive"),
    "arrays empty": (_bytes_edit("arrays.npz", lambda data: b""), "arrays.npz", "not a NumPy .npz archive"),
    "arrays layer missing": (
        _npz_edit(lambda arrays: arrays.pop("storey0_navigable")),
        "arrays.npz",
        "array 'storey0_navigable' is missing",
    ),
    "arrays layer of another shape": (
        _npz_edit(lambda arrays: arrays.update(storey0_room_labels=arrays["storey0_room_labels"][1:])),
        "arrays.npz",
        "array 'storey0_room_labels' is int32 of shape",
    ),
    "rooms missing": (_json_edit(_drop("rooms")), "prior.json", "'rooms' is missing"),
    "a JSON list": (_json_edit(lambda meta: [meta]), "prior.json", "expected a JSON object at the top, found a list"),
    "version is a string": (
        _json_edit(_set("version", "2")),
        "prior.json",
        "'version' must be an integer, found the string \"2\"",
    ),
    "room area is a string": (
        _json_edit(_set("rooms.0.area_m2", "big")),
        "prior.json",
        'rooms[0].area_m2: input should be a valid number, found the string "big"',
    ),
    "room field missing": (
        _json_edit(_drop("rooms.0.centroid_xy")),
        "prior.json",
        "rooms[0].centroid_xy: field required",
    ),
    "door is a number": (
        _json_edit(_set("doors.0", 7)),
        "prior.json",
        "doors[0]: input should be an object, found the number 7",
    ),
    "object position too short": (
        _json_edit(_set("objects.0.position_m", [1.0, 2.0])),
        "prior.json",
        "objects[0].position_m[2]: field required",
    ),
    "object on no storey": (
        _json_edit(_set("objects.0.storey_index", 5)),
        "prior.json",
        "objects[0].storey_index: 5 is no storey",
    ),
    "object id is null": (
        _json_edit(_set("objects.1.id", None)),
        "prior.json",
        "objects[1].id: input should be a valid integer, found null",
    ),
    "grid rows is a float": (
        _json_edit(_set("grid.rows", 12.5)),
        "prior.json",
        "grid.rows: input should be a valid integer",
    ),
    "not UTF-8": (_bytes_edit("prior.json", _bad_utf8), "prior.json", "not UTF-8 text: byte 0xff"),
    "broken JSON": (_bytes_edit("prior.json", _truncate), "prior.json", "corrupt JSON"),
}


@pytest.mark.parametrize("case", list(PRIOR_DAMAGE))
def test_a_corrupt_prior_folder_is_a_one_line_format_error(case: str, tiny_prior: Path, tmp_path: Path) -> None:
    damage, file_name, expected = PRIOR_DAMAGE[case]
    folder = tmp_path / "prior"
    folder.mkdir()
    for item in tiny_prior.iterdir():
        (folder / item.name).write_bytes(item.read_bytes())
    BimPrior.load(folder)  # the copy is a good prior before the damage
    damage(folder)
    files = {p.name: p.read_bytes() for p in folder.iterdir()}
    with pytest.raises(FormatError) as raised:
        BimPrior.load(folder)
    message = str(raised.value)
    assert len(message.splitlines()) == 1
    assert message.startswith(str(folder / file_name)), message
    assert expected in message
    assert "allow_pickle" not in message
    line = assert_one_line_error(invoke("prior", folder), contains=expected)
    assert "internal" not in line
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == files  # nothing touched


def test_a_version_of_the_wrong_type_does_not_contradict_itself(tiny_prior: Path, tmp_path: Path) -> None:
    """Before: 'prior format bimfactor-prior v2, this bimfactor reads bimfactor-prior v2' (the version as a string)."""
    folder = tmp_path / "prior"
    folder.mkdir()
    for item in tiny_prior.iterdir():
        (folder / item.name).write_bytes(item.read_bytes())
    _json_edit(_set("version", str(PRIOR_VERSION)))(folder)
    with pytest.raises(FormatError) as raised:
        BimPrior.load(folder)
    assert "this bimfactor reads" not in str(raised.value)
    _json_edit(_set("version", 999))(folder)
    with pytest.raises(FormatError, match=f"v999, this bimfactor reads bimfactor-prior v{PRIOR_VERSION}"):
        BimPrior.load(folder)


# ------------------------------------------------------------------------------ 7: geometry that is no building


def test_walls_without_geometry_are_skipped_with_a_warning(
    tmp_path: Path, session_cfg, caplog: pytest.LogCaptureFixture
) -> None:
    path = tiny_building(tmp_path / "two-bare-walls.ifc", walls_without_geometry=2)
    with caplog.at_level(logging.WARNING, logger="bimfactor.bim.ifc"):
        model = load_ifc(path, session_cfg(f"bim.ifc.cache_dir={tmp_path / 'cache'}").bim.ifc)
    assert len(model.of_class("IfcWall")) == 2
    assert any("2 of 4 walls have no geometry" in r.getMessage() for r in caplog.records)


def test_walls_that_all_lack_geometry_are_refused(tmp_path: Path) -> None:
    """Before: bare IfcWalls passed the 'has walls' check and made 7 rooms of 0.1 m²."""
    path = tiny_building(tmp_path / "bare-walls.ifc", walls_without_geometry=4)
    _assert_refused(path, tmp_path, "none of its 4 walls (IfcWall / IfcCurtainWall) has geometry")


def test_ifc4_content_labelled_ifc2x3_is_refused_and_not_cached(tiny_ifc: Path, tmp_path: Path) -> None:
    """Before: `internal: ValueError` (no geometry came out of the mismatched entities), and that EMPTY geometry was
    cached. Now the parser's attribute-count warnings name the entity, its line and the schema it fits."""
    path = _edited(tiny_ifc, tmp_path / "mislabelled.ifc", b"FILE_SCHEMA(('IFC4'));", b"FILE_SCHEMA(('IFC2X3'));")
    line = _assert_refused(path, tmp_path, "the header says IFC2X3 but the content looks like IFC4")
    assert "IfcWall has 9 attribute values where IFC2X3 expects 8" in line


def test_a_model_without_storeys_is_refused_at_build_time(tmp_path: Path) -> None:
    """Before: a prior with 0 storeys was built, and `localize` failed on it internally."""
    path = tiny_building(tmp_path / "no-storey.ifc", storey=False)
    _assert_refused(path, tmp_path, "no IfcBuildingStorey")


def test_a_model_of_walls_alone_is_refused(tmp_path: Path, session_cfg) -> None:
    """Decision: refuse. Rooms need doors (or IfcSpace) to be told from the outside, so walls alone give 0 rooms,
    hence no navigable cell; `localize` would only fail later ("the prior has no navigable space"), and no other
    command has use for a prior without rooms. The refusal comes before the text embedder is loaded."""
    path = tiny_building(tmp_path / "walls-only.ifc", door=False)
    line = _assert_refused(path, tmp_path, "no rooms found: it has neither doors", geometry_cached=True)
    assert "neither doors (IfcDoor) nor rooms (IfcSpace)" in line
    assert "nowhere to localize in" in line
    with pytest.raises(IfcError, match="nowhere to localize in"):
        build_prior(path, session_cfg(f"bim.ifc.cache_dir={tmp_path / 'cache2'}"), embedder=_FakeEmbedder())


# ------------------------------------------------------------------------------ 8: implausible length units


def test_a_metre_file_declared_as_millimetres_is_refused(tmp_path: Path) -> None:
    """Before: 0 rooms at exit 0."""
    metres = tmp_path / "paper.ifc"
    write_building("paper-floor", 0, metres)
    path = _edited(
        metres,
        tmp_path / "paper-as-mm.ifc",
        b"IFCSIUNIT(*,.LENGTHUNIT.,$,.METRE.)",
        b"IFCSIUNIT(*,.LENGTHUNIT.,.MILLI.,.METRE.)",
    )
    line = _assert_refused(path, tmp_path, "the file says its lengths are in millimetres")
    assert "walls are 0.2 mm thick (median)" in line
    assert line.endswith("is it in metres? (IFCSIUNIT .LENGTHUNIT. in the file)")


def test_a_millimetre_file_declared_as_metres_is_refused_before_any_grid(tiny_ifc: Path, tmp_path: Path) -> None:
    """Before: 33 s, then `MemoryError: 32.5 GiB` building the grid."""
    path = _edited(
        tiny_ifc,
        tmp_path / "mm-as-m.ifc",
        b"IFCSIUNIT(*,.LENGTHUNIT.,.MILLI.,.METRE.)",
        b"IFCSIUNIT(*,.LENGTHUNIT.,$,.METRE.)",
    )
    line = _assert_refused(path, tmp_path, "the file says its lengths are in metres, but then its walls are 200 m")
    assert "spans 6 km: is it in millimetres?" in line


def test_a_grid_too_large_for_memory_is_refused(tiny_ifc: Path, session_cfg, tmp_path: Path) -> None:
    """Plausible units, but a resolution (or stray element) that would need more memory than there is: refused with
    the memory it needs, before any grid is allocated."""
    cfg = session_cfg("bim.grid.resolution_m=0.0001")
    with pytest.raises(ConfigError, match=r"^bim\.grid\.resolution_m=0\.0001 needs about .* for the grids of 1 storey"):
        build_prior(tiny_ifc, cfg, embedder=_FakeEmbedder())


# ------------------------------------------------------------------------------ 15: IFC integrity


def test_trailing_whitespace_after_the_trailer_is_accepted(tiny_ifc: Path, tmp_path: Path, session_cfg) -> None:
    """Before: more than 1 KB of trailing newlines was refused as 'truncated'."""
    path = tmp_path / "trailing.ifc"
    path.write_bytes(tiny_ifc.read_bytes() + b"\r\n" * 3000 + b" \t\n" * 500)
    assert read_schema(path) == "IFC4"
    model = load_ifc(path, session_cfg(f"bim.ifc.cache_dir={tmp_path / 'cache'}").bim.ifc)
    assert len(model.of_class("IfcWall")) == 4


def _cut_with_trailer(source: Path, target: Path, keep_lines: int) -> Path:
    lines = source.read_bytes().split(b"\n")
    target.write_bytes(b"\n".join(lines[:keep_lines]) + b"\nENDSEC;\nEND-ISO-10303-21;\n")
    return target


def test_a_file_cut_at_a_line_with_the_trailer_added_back_is_refused(tiny_ifc: Path, tmp_path: Path) -> None:
    """Before: built at exit 0. The entities the cut lost are still referenced: the first such line is named."""
    lines = tiny_ifc.read_bytes().split(b"\n")
    first_wall = next(i for i, line in enumerate(lines) if b"=IFCWALL(" in line) + 1
    path = _cut_with_trailer(tiny_ifc, tmp_path / "cut.ifc", first_wall)
    line = _assert_refused(path, tmp_path, f"corrupt or truncated IFC file, line {first_wall}: Instance reference #")
    assert "not found" in line


def test_a_real_file_cut_in_half_with_the_trailer_added_back_is_refused(ifc_file, tmp_path: Path) -> None:
    source = ifc_file("AC20-FZK-Haus.ifc")
    path = _cut_with_trailer(source, tmp_path / "half.ifc", source.read_bytes().count(b"\n") // 2)
    _assert_refused(path, tmp_path, "corrupt or truncated IFC file, line ")


def _break_first_wall(how: Callable[[bytes], bytes]) -> Callable[[Path, Path], tuple[Path, int]]:
    def make(source: Path, folder: Path) -> tuple[Path, int]:
        lines = source.read_bytes().split(b"\n")
        k = next(i for i, line in enumerate(lines) if b"=IFCWALL(" in line)
        lines[k] = how(lines[k])
        path = folder / "broken.ifc"
        path.write_bytes(b"\n".join(lines))
        return path, k + 1

    return make


SYNTAX_ERRORS = {
    "no '=' after the instance name": (_break_first_wall(lambda line: line.replace(b"=", b"", 1)), "IFC syntax error"),
    "line cut short": (_break_first_wall(lambda line: line[:20]), "invalid IFC file"),
    "unbalanced parenthesis": (_break_first_wall(lambda line: line.rstrip(b";").rstrip(b")") + b";"), "invalid IFC"),
    "unknown entity": (_break_first_wall(lambda line: b"#9999=IFCFOO(1);"), "invalid IFC file"),
}


@pytest.mark.parametrize("case", list(SYNTAX_ERRORS))
def test_a_syntax_error_names_its_line(case: str, tiny_ifc: Path, tmp_path: Path) -> None:
    """Before: 'cannot parse IFC (Syntax error during parse, check logs)', with no line and no log to see."""
    make, kind = SYNTAX_ERRORS[case]
    path, line_number = make(tiny_ifc, tmp_path)
    line = _assert_refused(path, tmp_path, f"{kind}")
    assert f", line {line_number}: " in line
    assert "check logs" not in line
