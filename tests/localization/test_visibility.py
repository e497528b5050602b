"""The precomputed visible-object table: occlusion by walls, the radius, doorways, CSR queries, round trip."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config
from tests.localization.handmade import make_prior, object_id


def visible_labels(prior, table: VisibilityTable, xy: tuple[float, float], storey: int = 0) -> set[str]:
    return {prior.objects[i].label for i in table.visible_ids(np.array(xy), storey)}


def test_object_behind_a_wall_is_not_visible_one_in_the_room_is(box_prior, box_visibility):
    seen = visible_labels(box_prior, box_visibility, (4.0, 3.0))
    assert {"chair", "cabinet"} <= seen  # same room, 1.0 m and 3.6 m away
    assert "table" not in seen  # 5 m away, behind the dividing wall
    assert "bookshelf" not in seen
    assert visible_labels(box_prior, box_visibility, (9.5, 2.0)) == {"table", "bookshelf"}


def test_a_window_in_its_wall_is_visible_from_its_room_only(box_prior, box_visibility):
    assert "window" in visible_labels(box_prior, box_visibility, (3.0, 2.0))
    assert "window" not in visible_labels(box_prior, box_visibility, (8.0, 2.0))  # other room, 5 m away


def test_objects_are_seen_through_a_doorway_only_in_line_with_it(test_config: Config):
    prior = make_prior(with_door=True)
    table = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    assert "table" in visible_labels(prior, table, (4.0, 3.0))  # the line y = 3 passes the gap y ∈ [2.5, 3.5]
    assert "table" not in visible_labels(prior, table, (4.0, 5.0))  # every sample point hides behind the wall


def test_objects_beyond_the_radius_are_not_listed(box_prior, test_config: Config):
    within_3_m = test_config.bim.visibility.model_copy(update={"radius_m": 3.0})
    table = VisibilityTable.build(box_prior, within_3_m, progress=False)
    seen = visible_labels(box_prior, table, (4.0, 3.0))
    assert "chair" in seen
    assert "cabinet" not in seen  # 3.6 m > r + half a lattice diagonal


def test_candidates_are_the_per_point_lists_in_csr_form(box_prior, box_visibility):
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(-0.5, 12.5, 300), rng.uniform(-0.5, 6.5, 300)])
    offsets, ids = box_visibility.candidates(xy, 0)
    assert offsets.shape == (301,) and offsets[0] == 0 and offsets[-1] == len(ids)
    for m in range(len(xy)):
        np.testing.assert_array_equal(ids[offsets[m] : offsets[m + 1]], box_visibility.visible_ids(xy[m], 0))
    outside = box_visibility.visible_ids(np.array([-0.8, -0.8]), 0)
    assert len(outside) == 0


def test_to_arrays_from_arrays_round_trip(box_prior, box_visibility, tmp_path):
    np.savez_compressed(tmp_path / "vis.npz", **box_visibility.to_arrays())
    with np.load(tmp_path / "vis.npz") as arrays:
        loaded = VisibilityTable.from_arrays(dict(arrays))
    assert loaded.lattice == box_visibility.lattice
    assert loaded.radius_m == box_visibility.radius_m
    xy = np.array([[4.0, 3.0], [9.0, 2.0], [1.0, 1.0]])
    for a, b in zip(loaded.candidates(xy, 0), box_visibility.candidates(xy, 0), strict=True):
        np.testing.assert_array_equal(a, b)


def test_from_arrays_rejects_another_format_version(box_visibility):
    arrays = box_visibility.to_arrays()
    arrays["visibility_meta"] = arrays["visibility_meta"].copy()
    arrays["visibility_meta"][0] = 99
    with pytest.raises(ValueError, match="format"):
        VisibilityTable.from_arrays(arrays)


def test_each_storey_lists_only_its_own_objects(test_config: Config):
    prior = make_prior(n_storeys=2)
    table = VisibilityTable.build(prior, test_config.bim.visibility, progress=False)
    upstairs = {object_id(prior, "table", 1), object_id(prior, "chair", 1)}
    assert set(table.visible_ids(np.array([4.0, 3.0]), 1)) == upstairs
    offsets, ids = table.candidates(np.array([[4.0, 3.0], [4.0, 3.0]]), np.array([0, 1]))
    assert set(ids[offsets[0] : offsets[1]]) == {object_id(prior, label, 0) for label in ("chair", "cabinet", "window")}
    assert set(ids[offsets[1] : offsets[2]]) == upstairs
