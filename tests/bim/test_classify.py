"""Language-encoded room classification with the real bundled sentence encoder, and the evaluation name table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from bimfactor.bim.classify import (
    UNKNOWN,
    RoomCategoryPool,
    classify_room_names,
    classify_rooms,
    load_room_category_pool,
    room_sentence,
    type_rooms,
)
from bimfactor.config import config_file, load_config
from bimfactor.embed.text import MiniLMTextEmbedder
from bimfactor.errors import ConfigError

from .room_types import load_room_name_table, room_name_to_category


def classify_room(labels, pool, **options):
    """One room from its object labels (`classify_rooms` of one)."""
    return classify_rooms([labels], pool, **options)[0]


IFC_DIR = Path(__file__).resolve().parents[3] / "shared" / "data" / "ifc"
# Real room names that stand for no category of the pool; they must stay unscored.
UNMAPPED_REAL_NAMES = {"Galerie", "Roof", "Room", "Dachboden-1", "Dachboden-2"}


@pytest.fixture(scope="module")
def embedder() -> MiniLMTextEmbedder:
    return MiniLMTextEmbedder()


@pytest.fixture(scope="module")
def pool(embedder: MiniLMTextEmbedder) -> RoomCategoryPool:
    return load_room_category_pool(load_config().bim.classify, embedder)


def _write_pool(path: Path, data: object) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


# --- the sentence ----------------------------------------------------------------------------------------


def test_sentence_counted_keeps_first_seen_order() -> None:
    labels = ["Sink", "toilet", "sink", "chair"] + ["chair"] * 15
    assert room_sentence(labels) == "two sinks, toilet, 16 chairs"


def test_sentence_styles() -> None:
    labels = ["desk", "office  chair", "desk", " "]
    assert room_sentence(labels, "counted") == "two desks, office chair"
    assert room_sentence(labels, "unique") == "desk, office chair"
    assert room_sentence(labels, "list") == "desk, office chair, desk"
    assert room_sentence([]) == ""


@pytest.mark.parametrize(
    ("label", "plural"),
    [
        ("bench", "benches"),
        ("shelf", "shelves"),
        ("library", "libraries"),
        ("vanity unit with sink", "vanity units with sink"),
    ],
)
def test_sentence_plurals(label: str, plural: str) -> None:
    assert room_sentence([label, label]) == f"two {plural}"


# --- the pool --------------------------------------------------------------------------------------------


def test_pool_has_the_categories(pool: RoomCategoryPool) -> None:
    expected = {
        "bedroom", "kitchen", "bathroom", "living room", "dining room", "office", "meeting room",
        "classroom", "laboratory", "hallway", "storage room", "technical room", "gym",
    }  # fmt: skip
    assert set(pool.names) == expected
    assert pool.embeddings.shape == (len(expected), 384)
    np.testing.assert_allclose(np.linalg.norm(pool.embeddings, axis=1), 1.0, atol=1e-5)
    assert 0.0 <= pool.min_score < 1.0


def test_pool_embedding_is_normalised_prompt_mean(tmp_path: Path, embedder: MiniLMTextEmbedder) -> None:
    prompts = ["a bathroom with a toilet", "toilet, sink"]
    path = _write_pool(tmp_path / "pool.yaml", {"categories": {"bathroom": prompts, "gym": "a gym"}})
    small = RoomCategoryPool.load(path, embedder)
    mean = embedder.encode(prompts).mean(axis=0)
    np.testing.assert_allclose(small.embeddings[0], mean / np.linalg.norm(mean), atol=1e-6)
    assert small.names == ("bathroom", "gym")
    assert small.prompts[1] == ("a gym",)


@pytest.mark.parametrize(
    "data",
    [
        {"categories": {}},
        {"no_categories": 1},
        {"categories": {"unknown": ["a room"]}},
        {"categories": {"gym": []}},
        {"categories": {"gym": ["a gym"]}, "min_score": 2.0},
        {"categories": {"gym": ["a gym"]}, "names": {"sauna": ["sauna"]}},
        {"categories": {"gym": ["a gym"]}, "names": ["gym"]},
        {"categories": {"gym": ["a gym"]}, "name_margin": "wide"},
        ["not", "a", "mapping"],
    ],
)
def test_pool_rejects_bad_files(tmp_path: Path, embedder: MiniLMTextEmbedder, data: object) -> None:
    with pytest.raises(ConfigError):
        RoomCategoryPool.load(_write_pool(tmp_path / "pool.yaml", data), embedder)


def test_pool_missing_file(tmp_path: Path, embedder: MiniLMTextEmbedder) -> None:
    with pytest.raises(ConfigError, match="not found"):
        RoomCategoryPool.load(tmp_path / "absent.yaml", embedder)


# --- classification --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("labels", "category"),
    [
        (["toilet", "sink", "bathtub"], "bathroom"),
        (["bed", "wardrobe"], "bedroom"),
        (["stove", "refrigerator", "sink"], "kitchen"),
        (["desk", "chair", "bookshelf"], "office"),
        (["sofa", "coffee table", "television"], "living room"),
        (["dining table", "dining chair", "dining chair", "sideboard"], "dining room"),
        (["treadmill", "rowing machine"], "gym"),
        (["lab bench", "fume hood"], "laboratory"),
        (["boiler", "pump", "electrical cabinet"], "technical room"),
        (["shelf", "shelf", "box"], "storage room"),
        (["coat rack", "staircase"], "hallway"),
    ],
)
def test_classify_room(pool: RoomCategoryPool, labels: list[str], category: str) -> None:
    result = classify_room(labels, pool)
    assert result.category == category, result
    assert result.score == pytest.approx(max(result.scores.values()))
    assert result.scores[category] == pytest.approx(result.score)
    assert set(result.scores) == set(pool.names)


def test_room_without_objects_is_unknown(pool: RoomCategoryPool) -> None:
    result = classify_room([], pool)
    assert (result.category, result.score, result.scores) == (UNKNOWN, 0.0, {})


def test_min_objects(pool: RoomCategoryPool) -> None:
    assert classify_room(["toilet", "sink"], pool, min_objects=3).category == UNKNOWN
    assert classify_room(["toilet", "sink", "sink"], pool, min_objects=3).category == "bathroom"


def test_low_score_is_unknown(tmp_path: Path, embedder: MiniLMTextEmbedder) -> None:
    strict = RoomCategoryPool.load(
        _write_pool(tmp_path / "pool.yaml", {"min_score": 0.99, "categories": {"gym": ["a gym"]}}), embedder
    )
    result = classify_room(["toilet", "sink"], strict)
    assert result.category == UNKNOWN
    assert 0.0 < result.score < 0.99


@pytest.mark.parametrize(
    ("name", "category"),
    [
        ("Buero Meier", "office"),
        ("Büro 1.23", "office"),
        ("Büro1", "office"),
        ("Open Office 3", "office"),
        ("WC Herren", "bathroom"),
        ("Women's Restroom", "bathroom"),
        ("Bathroom 1", "bathroom"),
        ("Break Room", "kitchen"),
        ("Küche", "kitchen"),
        ("Besprechungsraum II", "meeting room"),
        ("Conference Room 2.14", "meeting room"),
        ("Seminarraum", "classroom"),
        ("Labor K3", "laboratory"),
        ("Flur 1.OG Treppe", "hallway"),
        ("Entrance hall", "hallway"),
        ("Lobby", "hallway"),
        ("Technikraum II", "technical room"),
        ("Schlafzimmer", "bedroom"),
        ("Living Room", "living room"),
        # names that do not say what a room is for: the objects decide
        ("Room", None),
        ("Roof", None),
        ("Dachboden-1", None),
        ("Herren", None),  # loose likenesses ("wohnen", "kueche") do not decide
        ("Chef", None),
        ("Kopierraum", None),
        ("A101", None),
        ("", None),
    ],
)
def test_room_names_decide_where_they_say_what_the_room_is(
    pool: RoomCategoryPool, name: str, category: str | None
) -> None:
    [result] = classify_room_names([name], pool)
    assert (result.category if result else None) == category, result


def test_a_deciding_name_outranks_the_objects(pool: RoomCategoryPool) -> None:
    cfg = load_config().bim.classify
    labels, names, neighbours = [["table", "chair"], ["table", "chair"], []], ["Buero Meier", "Room", "Flur"], [1, 1, 1]
    by_name = type_rooms(labels, names, neighbours, pool, cfg)
    objects_only = type_rooms(labels, names, neighbours, pool, cfg, use_names=False)
    assert [r.category for r in by_name] == ["office", objects_only[1].category, "hallway"]
    assert by_name[0].sentence == '(name: "Buero Meier")' and objects_only[2].category == UNKNOWN


def test_batch_matches_single_rooms(pool: RoomCategoryPool) -> None:
    rooms = [["toilet", "sink"], [], ["bed", "nightstand"], ["desk", "office chair", "desk"]]
    batch = classify_rooms(rooms, pool)
    assert [r.category for r in batch] == ["bathroom", UNKNOWN, "bedroom", "office"]
    for labels, result in zip(rooms, batch, strict=True):
        single = classify_room(labels, pool)
        assert single.category == result.category
        assert single.sentence == result.sentence
        assert single.score == pytest.approx(result.score, abs=1e-5)


# --- evaluation-only room-name table ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "category"),
    [
        ("Flur", "hallway"),
        ("Flur EG West", "hallway"),
        ("Foyer", "hallway"),
        ("Entrance hall", "hallway"),
        ("Buero", "office"),
        ("Büro Meier", "office"),
        ("Buero IL Sekr.", "office"),
        ("Bad", "bathroom"),
        ("WC Herren", "bathroom"),
        ("WC Damen", "bathroom"),
        ("Bathroom 1", "bathroom"),
        ("Schlafzimmer", "bedroom"),
        ("Bedroom 1", "bedroom"),
        ("Wohnen", "living room"),
        ("Living Room", "living room"),
        ("Küche", "kitchen"),
        ("Kueche", "kitchen"),
        ("KITCHEN", "kitchen"),
        ("Besprechungsraum I", "meeting room"),
        ("Seminarraum", "classroom"),
        ("Labor K1", "laboratory"),
        ("Labor I", "laboratory"),
        ("Technikraum III", "technical room"),
        ("Utility", "technical room"),
        ("Stair", "hallway"),
    ],
)
def test_room_name_table(name: str, category: str) -> None:
    assert room_name_to_category(name) == category


@pytest.mark.parametrize("name", ["Galerie", "Roof", "Room", "Dachboden-1", "", "Badminton court"])
def test_unmapped_room_names(name: str) -> None:
    assert room_name_to_category(name) is None


def test_room_name_table_uses_pool_categories() -> None:
    pool_file = yaml.safe_load(config_file(load_config().bim.classify.room_categories_file).read_text())
    assert load_room_name_table().categories <= set(pool_file["categories"])


def test_room_name_table_rejects_bad_pattern(tmp_path: Path) -> None:
    path = tmp_path / "names.yaml"
    path.write_text(yaml.safe_dump({"categories": {"office": ["b(ü|ue"]}}))
    with pytest.raises(ConfigError, match="bad pattern"):
        load_room_name_table(path)


def test_room_name_table_covers_the_real_buildings() -> None:
    if not IFC_DIR.is_dir():
        pytest.skip(f"real IFC buildings not found at {IFC_DIR}")
    ifcopenshell = pytest.importorskip("ifcopenshell")
    names = {
        space.LongName
        for path in sorted(IFC_DIR.glob("*.ifc"))
        for space in ifcopenshell.open(str(path)).by_type("IfcSpace")
    }
    unmapped = {name for name in names if room_name_to_category(name) is None}
    assert unmapped == UNMAPPED_REAL_NAMES
