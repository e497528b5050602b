"""Tiny hand-built buildings for exact tests of the grid and room stages."""

from __future__ import annotations

import numpy as np
import trimesh

from bimfactor.bim.ifc import IfcElement, Mesh

_ANCESTRY = {
    "IfcWall": ("IfcWall", "IfcBuildingElement", "IfcElement", "IfcProduct"),
    "IfcBeam": ("IfcBeam", "IfcBuildingElement", "IfcElement", "IfcProduct"),
    "IfcDoor": ("IfcDoor", "IfcBuildingElement", "IfcElement", "IfcProduct"),
    "IfcFurniture": ("IfcFurniture", "IfcFurnishingElement", "IfcElement", "IfcProduct"),
    "IfcSlab": ("IfcSlab", "IfcBuildingElement", "IfcElement", "IfcProduct"),
    "IfcWindow": ("IfcWindow", "IfcBuildingElement", "IfcElement", "IfcProduct"),
}


def box(ifc_class: str, lo: tuple[float, float, float], hi: tuple[float, float, float], name: str = "") -> IfcElement:
    """An axis-aligned box element from corner `lo` to corner `hi` (metres)."""
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    mesh = trimesh.creation.box(
        extents=hi_a - lo_a, transform=trimesh.transformations.translation_matrix((lo_a + hi_a) / 2)
    )
    return IfcElement(
        guid=f"{ifc_class}-{lo}-{hi}",
        ifc_class=ifc_class,
        ancestry=_ANCESTRY[ifc_class],
        name=name,
        object_type="",
        type_name="",
        type_class="",
        predefined_type="",
        long_name="",
        storey_index=0,
        space_guid=None,
        mesh=Mesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int32)),
    )


def two_rooms(gap: bool = True, door: bool = True, lintel: bool = False) -> list[IfcElement]:
    """Two 4 × 4 m rooms side by side (x 0..4 and 4.2..8.2, y 0..4), walls 0.2 m thick and 2.7 m high.

    The shared wall at x = 4..4.2 has a 1 m gap at y = 1.5..2.5 when `gap`; `door` fills it with a door
    leaf, `lintel` puts a wall piece above it (z 2.1..2.7) instead, as a leafless doorway.
    """
    h = 2.7
    walls = [
        box("IfcWall", (-0.2, -0.2, 0), (8.4, 0.0, h)),
        box("IfcWall", (-0.2, 4.0, 0), (8.4, 4.2, h)),
        box("IfcWall", (-0.2, 0.0, 0), (0.0, 4.0, h)),
        box("IfcWall", (8.2, 0.0, 0), (8.4, 4.0, h)),
    ]
    if gap:
        walls += [box("IfcWall", (4.0, 0.0, 0), (4.2, 1.5, h)), box("IfcWall", (4.0, 2.5, 0), (4.2, 4.0, h))]
        if door:
            walls.append(box("IfcDoor", (4.05, 1.55, 0), (4.15, 2.45, 2.05), name="Door"))
        if lintel:
            walls.append(box("IfcWall", (4.0, 1.5, 2.1), (4.2, 2.5, h)))
    else:
        walls.append(box("IfcWall", (4.0, 0.0, 0), (4.2, 4.0, h)))
    return walls
