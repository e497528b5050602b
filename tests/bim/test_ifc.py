"""IFC reading: schema checks, units, storeys, element semantics, the geometry cache."""

from __future__ import annotations

import numpy as np
import pytest

from bimfactor.bim import ifc as ifc_module
from bimfactor.bim.ifc import load_ifc, read_schema
from bimfactor.errors import IfcError, InputError


def _footprint(model) -> np.ndarray:
    skipped = ("IfcSpace",)
    boxes = np.array([e.mesh.bounds for e in model.elements if not any(e.is_a(c) for c in skipped)])
    return boxes[:, 1, :2].max(axis=0) - boxes[:, 0, :2].min(axis=0)


def test_millimetre_model_is_scaled_to_metres(ifc_file, session_cfg) -> None:
    model = load_ifc(ifc_file("SampleHouse4.ifc"), session_cfg().bim.ifc)
    assert model.length_unit_m == pytest.approx(0.001)
    np.testing.assert_allclose(_footprint(model), [16.9, 8.7], atol=0.1)
    assert [s.name for s in model.storeys] == ["Ground Floor", "Roof"]
    assert model.storeys[1].elevation_m == pytest.approx(2.5)


def test_storeys_are_sorted_and_elements_know_their_storey(ifc_file, session_cfg) -> None:
    model = load_ifc(ifc_file("duplex.ifc"), session_cfg().bim.ifc)
    elevations = [s.elevation_m for s in model.storeys]
    assert elevations == sorted(elevations)
    assert elevations[0] == pytest.approx(-1.25)
    spaces = model.of_class("IfcSpace")
    assert len(spaces) == 21
    assert all(s.storey_index is not None and s.long_name for s in spaces)
    furniture = model.of_class("IfcFurnishingElement")
    assert len(furniture) == 61
    # duplex contains its furniture in spaces: the containing space is kept.
    assert all(f.space_guid in {s.guid for s in spaces} for f in furniture)


def test_ifc2x3_sanitary_terminals_keep_their_type(ifc_file, session_cfg) -> None:
    """IFC2X3 has no IfcSanitaryTerminal: flow terminals are typed by IfcSanitaryTerminalType (here by its Name;
    its PredefinedType is NOTDEFINED, which is read as empty)."""
    model = load_ifc(ifc_file("AC11-FZK-Haus-IFC.ifc"), session_cfg().bim.ifc)
    terminals = [e for e in model.of_class("IfcFlowTerminal") if e.type_class == "IfcSanitaryTerminalType"]
    assert len(terminals) == 6
    assert {t.type_name for t in terminals} == {"BATH", "SHOWER", "BASIN", "TOILET"}
    assert all(t.predefined_type == "" for t in terminals)


def test_subclass_ancestry_lets_config_name_a_superclass(ifc_file, session_cfg) -> None:
    model = load_ifc(ifc_file("SampleHouse4.ifc"), session_cfg().bim.ifc)
    furniture = model.of_class("IfcFurnishingElement")
    assert len(furniture) == 14
    assert all(f.ifc_class == "IfcFurniture" for f in furniture)


def test_cache_round_trip_is_identical_and_skips_parsing(ifc_file, session_cfg, monkeypatch) -> None:
    cfg = session_cfg().bim.ifc
    first = load_ifc(ifc_file("AC20-FZK-Haus.ifc"), cfg)

    def fail(*_args, **_kwargs):
        raise AssertionError("the cache was not used")

    monkeypatch.setattr(ifc_module, "_parse", fail)
    second = load_ifc(ifc_file("AC20-FZK-Haus.ifc"), cfg)
    assert second.storeys == first.storeys
    assert len(second.elements) == len(first.elements)
    for a, b in zip(first.elements, second.elements, strict=True):
        assert (a.guid, a.ancestry, a.name, a.type_name, a.storey_index, a.space_guid) == (
            b.guid,
            b.ancestry,
            b.name,
            b.type_name,
            b.storey_index,
            b.space_guid,
        )
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)


def test_schema_and_file_checks(tmp_path, session_cfg) -> None:
    cfg = session_cfg().bim.ifc
    not_ifc = tmp_path / "notes.ifc"
    not_ifc.write_text("hello")
    with pytest.raises(IfcError, match="not an IFC file"):
        load_ifc(not_ifc, cfg)
    old = tmp_path / "old.ifc"
    old.write_text(
        "ISO-10303-21;\nHEADER;\nFILE_SCHEMA(('IFC2X_FINAL'));\nENDSEC;\nDATA;\nENDSEC;\nEND-ISO-10303-21;\n"
    )
    assert read_schema(old) == "IFC2X_FINAL"
    with pytest.raises(IfcError, match="unsupported IFC schema IFC2X_FINAL"):
        load_ifc(old, cfg)
    with pytest.raises(InputError, match="not found"):
        load_ifc(tmp_path / "missing.ifc", cfg)


def test_truncated_file_is_an_ifc_error(ifc_file, tmp_path, session_cfg) -> None:
    cut = tmp_path / "cut.ifc"
    cut.write_bytes(ifc_file("AC20-FZK-Haus.ifc").read_bytes()[:5000])
    with pytest.raises(IfcError, match="truncated"):
        load_ifc(cut, session_cfg("bim.ifc.cache_dir=''").bim.ifc)
