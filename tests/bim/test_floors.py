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


def test_a_lift_is_a_portal_at_every_floor_of_its_shaft(prior_of, tmp_path: Path) -> None:
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.synth import LIFT_SIZE_M, MIN_WALL_GAP_M

    prior = prior_of("synth:lift-house")
    (lift,) = prior.portals
    assert (lift.kind, lift.ifc_class) == ("lift", "IfcTransportElement")
    assert [end.storey_index for end in lift.ends] == [0, 1]
    x0 = 0.2 + MIN_WALL_GAP_M
    for end in lift.ends:
        assert end.box_xy == pytest.approx((x0, 6.3 - LIFT_SIZE_M / 2, x0 + LIFT_SIZE_M, 6.3 + LIFT_SIZE_M / 2))
    assert prior.summary()["portals"] == [{"kind": "lift", "ifc_class": "IfcTransportElement", "storeys": [0, 1]}]
    prior.save(tmp_path / "prior")
    assert BimPrior.load(tmp_path / "prior").portals == prior.portals


def test_a_stair_flight_joins_its_bottom_floor_at_its_foot_and_its_top_floor_at_its_head() -> None:
    import numpy as np

    from bimfactor.bim.ifc import IfcElement, IfcModel, Mesh, Storey

    def element(ifc_class: str, corners: list[tuple[float, float, float]]) -> IfcElement:
        ancestry = (ifc_class, "IfcBuildingElement", "IfcElement", "IfcProduct")
        mesh = Mesh(np.asarray(corners, float), np.zeros((1, 3), np.int32))
        return IfcElement(ifc_class, ifc_class, ancestry, "", "", "", "", "", "", 0, None, mesh)

    # a flight rising along y from (0, 0) at 0 m to (1, 4) at 3 m, and the stair around it
    flight = element("IfcStairFlight", [(0, 0, 0), (1, 0, 0), (0, 0.3, 0.2), (1, 0.3, 0.2), (0, 4, 3), (1, 3.7, 2.9)])
    stair = element("IfcStair", [(-0.1, -0.1, 0), (1.1, 4.1, 3)])
    step = element("IfcStairFlight", [(5, 0, 0), (6, 1, 0.6)])  # a few steps: one floor only
    storeys = [Storey(0, "a", "Level 0", 0.0), Storey(1, "b", "Level 1", 3.0), Storey(2, "c", "Roof", 6.0, False)]
    model = IfcModel("m.ifc", "0", "IFC4", 1.0, storeys, [stair, flight, step])
    (portal,) = prior_module.find_portals(model, storeys)
    assert (portal.kind, portal.ifc_class) == ("stair", "IfcStairFlight")
    foot, head = portal.ends
    assert (foot.storey_index, head.storey_index) == (0, 1)
    assert foot.box_xy == pytest.approx((0, 0, 1, 0.3)) and head.box_xy == pytest.approx((0, 3.7, 1, 4))
