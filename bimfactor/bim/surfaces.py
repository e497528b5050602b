"""The prior's wall surfaces: the meshes of the building's structural elements, wound outward, with each storey's
height band, so that the fine registrar samples its surface model from the prior and never reads the IFC again.

What is solid and fixed (walls, columns, curtain walls, windows, plates, members) is kept; furniture is left out
because the as-built building moves it, and doors because they stand open (in the simulator always) and a closed leaf
drags scans off doorways.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bimfactor.bim.ifc import IfcModel

SURFACE_CLASSES = ("IfcWall", "IfcColumn", "IfcCurtainWall", "IfcWindow", "IfcPlate", "IfcMember")
"""IFC classes (and subclasses) whose surfaces the registrar aligns scans with."""
TOP_STOREY_HEIGHT_M = 3.0
"""Band height of the top storey; every other storey's band reaches the next storey's elevation."""


@dataclass(frozen=True)
class WallMeshes:
    """Element e's outward mesh is `vertices[vertex_offsets[e]:vertex_offsets[e + 1]]` with the faces
    `faces[face_offsets[e]:face_offsets[e + 1]]` (indices into its own vertices); `element_index` (E,) is its index
    in the IFC model's elements and `z_range` (E, 2) its mesh's height as read. Storey s spans
    `bands[s]` = (z_lo, z_hi) in world heights, from `elevations[s]`."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_offsets: np.ndarray
    face_offsets: np.ndarray
    element_index: np.ndarray
    z_range: np.ndarray
    elevations: np.ndarray
    bands: np.ndarray

    def __len__(self) -> int:
        return len(self.element_index)

    def mesh(self, e: int) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) vertices and (F, 3) faces of element e."""
        v0, v1, f0, f1 = *self.vertex_offsets[e : e + 2], *self.face_offsets[e : e + 2]
        return self.vertices[v0:v1], self.faces[f0:f1]

    def to_arrays(self, prefix: str = "walls_") -> dict[str, np.ndarray]:
        return {f"{prefix}{name}": getattr(self, name) for name in self.__dataclass_fields__}

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "walls_") -> WallMeshes:
        return cls(**{name: np.asarray(arrays[f"{prefix}{name}"]) for name in cls.__dataclass_fields__})


def wall_meshes(model: IfcModel, classes: tuple[str, ...] = SURFACE_CLASSES) -> WallMeshes:
    """The outward meshes of `model`'s elements of `classes` (those with geometry), and its storeys' bands."""
    chosen = [(i, e) for i, e in enumerate(model.elements) if e.mesh is not None and any(e.is_a(c) for c in classes)]
    meshes = [outward_mesh(e.mesh.vertices, e.mesh.faces) for _, e in chosen]
    elevations = np.asarray([s.elevation_m for s in model.storeys], np.float64)
    tops = np.append(elevations[1:], elevations[-1] + TOP_STOREY_HEIGHT_M) if len(elevations) else elevations
    return WallMeshes(
        vertices=np.concatenate([v for v, _ in meshes]) if meshes else np.zeros((0, 3)),
        faces=np.concatenate([f for _, f in meshes]).astype(np.int32) if meshes else np.zeros((0, 3), np.int32),
        vertex_offsets=np.cumsum([0, *(len(v) for v, _ in meshes)], dtype=np.int64),
        face_offsets=np.cumsum([0, *(len(f) for _, f in meshes)], dtype=np.int64),
        element_index=np.asarray([i for i, _ in chosen], np.int32),
        z_range=np.asarray([e.mesh.bounds[:, 2] for _, e in chosen], np.float64).reshape(-1, 2),
        elevations=elevations,
        bands=np.column_stack([elevations, tops]),
    )


def outward_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) faces rewound so that each closed body's normals point outward (IFC meshes mix
    windings and mirrored placements flip elements; back-face culling needs outward normals), by trimesh."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=True)
    trimesh.repair.fix_normals(mesh, multibody=True)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)
