"""Storeys that are floors: a level holding no room, door or furniture of its own (a foundation, a roof, a reference
level) is kept in the prior but holds no room, so no particle or route is ever put on it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from bimfactor.bim import prior as prior_module
from bimfactor.bim.prior import build_prior
from bimfactor.bim.synth import StoreySpec, build_ifc, make_building
from bimfactor.config import Config


def _with_foundation(tmp_path: Path) -> Path:
    """The office preset with an empty foundation level 0.6 m below its floor: the foundation's height band
    (floor + 0.1 … 1.8 m) cuts the ground floor's walls and doors."""
    spec = make_building("office", 0)
    foundation = StoreySpec("Foundation", -0.6, 0.6, (), (), (), (), ())
    spec = dataclasses.replace(spec, storeys=(foundation, *spec.storeys))
    path = tmp_path / "office-with-foundation.ifc"
    build_ifc(spec).write(str(path))
    return path


def test_a_foundation_whose_slice_copies_the_ground_floor_is_no_floor(
    tmp_path: Path, test_config: Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = _with_foundation(tmp_path)
    prior = build_prior(path, test_config)
    foundation, ground = (layers.storey for layers in prior.storeys)
    assert foundation.name == "Foundation" and not foundation.is_floor and "not a floor" in foundation.floor_note
    assert ground.is_floor and ground.floor_note.startswith("floor: ")
    assert {room.storey_index for room in prior.rooms} == {1}  # one floor, not two
    assert not prior.storeys[0].navigable.any() and prior.storeys[1].navigable.any()
    assert "not a floor" in prior.summary()["storeys"][0]["floor"]
    # what the decision prevents: with every level a floor, the foundation's slice is a second ground floor
    monkeypatch.setattr(prior_module, "floor_levels", lambda model, _classes: model.storeys)
    copied = build_prior(path, test_config)
    on_foundation = [room for room in copied.rooms if room.storey_index == 0]
    assert len(on_foundation) >= len([room for room in copied.rooms if room.storey_index == 1]) // 2 > 0


def test_a_level_with_only_roof_slabs_is_no_floor_and_a_model_of_no_floor_keeps_every_level() -> None:
    from bimfactor.bim.ifc import IfcElement, IfcModel, Storey

    def element(ifc_class: str, storey: int, predefined: str = "") -> IfcElement:
        ancestry = (ifc_class, "IfcElement", "IfcProduct")
        return IfcElement("g", ifc_class, ancestry, "", "", "", "", predefined, "", storey, None)

    storeys = [Storey(0, "a", "Level 1", 0.0), Storey(1, "b", "Roof", 3.0)]
    elements = [element("IfcDoor", 0), element("IfcSpace", 1), element("IfcSlab", 1, "ROOF")]
    model = IfcModel("m.ifc", "0", "IFC4", 1.0, storeys, elements)
    level, roof = prior_module.floor_levels(model, ["IfcFurniture"])
    assert level.is_floor and not roof.is_floor and "roof slabs" in roof.floor_note
    bare = IfcModel("m.ifc", "0", "IFC4", 1.0, storeys, [element("IfcWall", 0)])
    assert all(s.is_floor for s in prior_module.floor_levels(bare, ["IfcFurniture"]))
