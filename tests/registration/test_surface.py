"""Surface sampling: density, normals, storey bands, determinism, and the prior's wall meshes round trip."""

from __future__ import annotations

import numpy as np

from bimfactor.bim.ifc import IfcElement, IfcModel, Mesh, Storey
from bimfactor.bim.surfaces import SURFACE_CLASSES, WallMeshes, outward_mesh, wall_meshes
from bimfactor.config import Config
from bimfactor.registration.surface import SurfaceModel, build_surface_models, sample_mesh

from .synthetic import box_mesh

DENSITY = 200.0


def test_sample_count_matches_density_times_area() -> None:
    vertices, faces = box_mesh((0, 0, 0), (4.0, 0.2, 2.6))
    area = 2 * (4.0 * 0.2 + 4.0 * 2.6 + 0.2 * 2.6)
    points, _ = sample_mesh(vertices, faces, DENSITY, np.random.default_rng(0))
    expected = DENSITY * area
    # floor(a·d) per triangle plus one Bernoulli draw each: at most 12 triangles of slack, σ < 2.
    assert abs(len(points) - expected) <= 12
    assert np.all(points >= -1e-9) and np.all(points <= [4.0 + 1e-9, 0.2 + 1e-9, 2.6 + 1e-9])


def test_normals_are_perpendicular_to_their_wall_face() -> None:
    vertices, faces = box_mesh((0, 0, 0), (4.0, 0.2, 2.6))
    points, normals = sample_mesh(vertices, faces, DENSITY, np.random.default_rng(1))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    on_front = np.abs(points[:, 1]) < 1e-9  # the face y = 0 of the wall
    assert on_front.sum() > 0.9 * DENSITY * 4.0 * 2.6
    np.testing.assert_allclose(np.abs(normals[on_front]), np.tile([0.0, 1.0, 0.0], (on_front.sum(), 1)), atol=1e-12)
    on_end = np.abs(points[:, 0] - 4.0) < 1e-9  # the end face x = 4
    np.testing.assert_allclose(np.abs(normals[on_end, 0]), 1.0, atol=1e-12)
    # Points on a face are uniform over it: the mean lies at the face centre.
    np.testing.assert_allclose(points[on_front][:, [0, 2]].mean(axis=0), [2.0, 1.3], atol=0.05)


def _element(guid: str, ifc_class: str, ancestry: tuple[str, ...], lo, hi, storey: int) -> IfcElement:
    mesh = Mesh(*box_mesh(lo, hi))
    return IfcElement(guid, ifc_class, (ifc_class, *ancestry), guid, "", "", "", "", "", storey, None, mesh)


def _two_storey_model() -> IfcModel:
    elements = [
        _element("wall0", "IfcWall", ("IfcBuildingElement",), (0, 0, 0), (5, 0.2, 3.0), 0),
        _element("wall1", "IfcWallStandardCase", ("IfcWall",), (0, 2, 3.0), (5, 2.2, 6.0), 1),
        _element("tall", "IfcColumn", ("IfcBuildingElement",), (2, 1, 0), (2.3, 1.3, 6.0), 0),
        _element("slab", "IfcSlab", ("IfcBuildingElement",), (0, 0, 2.8), (5, 3, 3.0), 1),
        _element("sofa", "IfcFurniture", ("IfcFurnishingElement",), (1, 1, 0), (2, 2, 0.8), 0),
    ]
    storeys = [Storey(0, "s0", "ground", 0.0), Storey(1, "s1", "first", 3.0)]
    return IfcModel("two.ifc", "0" * 64, "IFC4", 1.0, storeys, elements)


def test_surface_per_storey_bands_and_classes(test_config: Config) -> None:
    model = _two_storey_model()
    surfaces = build_surface_models(wall_meshes(model), test_config.registration, seed=0)
    assert [s.storey_index for s in surfaces] == [0, 1]
    owners = [{model.elements[i].guid for i in np.unique(s.element_index)} for s in surfaces]
    # Storey 0: its wall and the column (which crosses both bands); never the sofa nor the slab (off by default).
    assert owners[0] == {"wall0", "tall"}
    assert owners[1] == {"wall1", "tall"}
    for surface, (lo, hi) in zip(surfaces, [(0.0, 3.0), (3.0, 6.0)], strict=True):
        assert surface.points[:, 2].min() >= lo and surface.points[:, 2].max() <= hi
        assert surface.elevation_m == lo and surface.height_m == hi - lo
    with_slabs = build_surface_models(wall_meshes(model, (*SURFACE_CLASSES, "IfcSlab")), test_config.registration)
    assert "slab" in {model.elements[i].guid for i in np.unique(with_slabs[0].element_index)}


def test_surface_is_deterministic_and_the_wall_meshes_round_trip(test_config: Config) -> None:
    walls = wall_meshes(_two_storey_model())
    a = build_surface_models(walls, test_config.registration, seed=3)
    b = build_surface_models(WallMeshes.from_arrays(walls.to_arrays()), test_config.registration, seed=3)
    for x, y in zip(a, b, strict=True):  # as the prior stores them: the same samples to the bit
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.normals, y.normals)
    assert b[1].elevation_m == 3.0 and b[1].storey_index == 1
    single = a[0]
    cloud = single.cloud
    assert cloud.has_normals() and cloud.has_covariances() and len(cloud.points) == len(single)
    assert single.kdtree.search_knn_vector_3d(single.points[0], 1)[1][0] == 0


def test_normals_point_out_of_the_element_even_when_wound_inward() -> None:
    vertices, faces = box_mesh((0, 0, 0), (4.0, 0.2, 2.6))
    inward = faces[:, [0, 2, 1]]
    mixed = np.where(np.arange(len(faces))[:, None] % 2 == 0, inward, faces)  # every other face flipped
    for wound in (faces, inward, mixed):
        points, normals = sample_mesh(*outward_mesh(vertices, wound), DENSITY, np.random.default_rng(2))
        centre = np.array([2.0, 0.1, 1.3])
        assert np.all(np.einsum("ij,ij->i", normals, points - centre) > 0)


def test_facing_culls_back_faces() -> None:
    vertices, faces = box_mesh((0, 0, 0), (4.0, 0.2, 2.6))
    points, normals = sample_mesh(*outward_mesh(vertices, faces), DENSITY, np.random.default_rng(3))
    surface = SurfaceModel(0, 0.0, 3.0, points, normals, np.zeros(len(points), np.int32))
    seen = surface.facing(np.array([2.0, -3.0]), radius_m=10.0)  # in front of the face y = 0
    assert len(seen) > 0
    assert not np.any(np.abs(seen.points[:, 1] - 0.2) < 1e-9)  # the far face y = 0.2 is culled
    assert np.any(np.abs(seen.points[:, 1]) < 1e-9)
    assert len(surface.facing(np.array([2.0, -3.0]), radius_m=1.0)) == 0  # nothing within 1 m


def test_crop_indices_are_the_samples_within_the_radius() -> None:
    rng = np.random.default_rng(4)
    points = rng.uniform(-20.0, 20.0, (5000, 3))
    surface = SurfaceModel(0, 0.0, 3.0, points, np.tile([1.0, 0.0, 0.0], (5000, 1)), np.zeros(5000, np.int32))
    center = np.array([3.0, -2.0])
    within = np.flatnonzero(np.sum((points[:, :2] - center) ** 2, axis=1) <= 6.5**2)
    np.testing.assert_array_equal(np.sort(surface.crop_indices(center, 6.5)), within)  # cell by cell
    assert len(surface.crop(center, 6.5)) == len(within) > 0
    empty = SurfaceModel(0, 0.0, 3.0, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int32))
    assert len(empty.crop_indices(center, 6.5)) == 0


def test_crops_by_cell_equal_a_brute_force_search() -> None:
    """The disc crop equals a KD-tree ball query; the crop near a scan holds exactly the samples in the cells the
    scan touches or within `cells` of one."""
    from scipy.spatial import cKDTree

    from bimfactor.registration.surface import CROP_CELL_M

    rng = np.random.default_rng(0)
    points = rng.uniform(-20.0, 30.0, (40_000, 3))
    model = SurfaceModel(
        0, 0.0, 3.0, points, np.tile([1.0, 0.0, 0.0], (len(points), 1)), np.zeros(len(points), np.int32)
    )
    tree = cKDTree(points[:, :2])
    for center, radius in (((0.0, 0.0), 8.0), ((-25.0, -25.0), 9.0), ((29.5, 29.5), 0.7), ((80.0, 80.0), 3.0)):
        want = np.sort(np.asarray(tree.query_ball_point(center, radius), dtype=np.int64))
        np.testing.assert_array_equal(np.sort(model.crop_indices(np.array(center), radius)), want)
    scan = rng.uniform(-25.0, 35.0, (60, 2))
    origin = points[:, :2].min(axis=0)
    sample_cells = np.floor((points[:, :2] - origin) / CROP_CELL_M).astype(int)
    scan_cells = np.floor((scan - origin) / CROP_CELL_M).astype(int)
    for cells in (0, 1, 3):
        reach = np.abs(sample_cells[:, None, :] - scan_cells[None]).max(axis=2).min(axis=1) <= cells
        np.testing.assert_array_equal(np.sort(model.near_indices(scan, cells)), np.flatnonzero(reach))
    assert len(model.near_indices(np.array([[500.0, 500.0]]), 2)) == 0
