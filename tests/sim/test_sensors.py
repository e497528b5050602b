"""The RGB-D camera against an independent ray–mesh intersection (trimesh), and its noise and dropouts."""

from __future__ import annotations

import numpy as np
import pytest
from trimesh.ray.ray_triangle import ray_triangle_id

from bimfactor.config import Config
from bimfactor.sim.sensors import BACKGROUND_RGB, RgbdCamera, camera_mount
from bimfactor.sim.simulate import build_world
from bimfactor.sim.trajectory import SimTrajectory
from bimfactor.sim.world import NON_PHYSICAL_CLASSES, SimWorld
from bimfactor.types import se2_to_matrix

from .conftest import NOISE_OFF, Building, config_with, pixel_rays

SAMPLE_PIXELS = 60
TIE_M = 2e-3  # pixels whose two nearest surfaces of different elements lie closer than this are ambiguous


class _BoxTree:
    """The part of an r-tree that trimesh's ray_triangle_id uses, by brute force over triangle bounding boxes."""

    def __init__(self, triangles: np.ndarray) -> None:
        self.lo, self.hi = triangles.min(axis=1), triangles.max(axis=1)
        self.bounds = np.concatenate([self.lo.min(axis=0), self.hi.max(axis=0)])

    def intersection(self, box: np.ndarray) -> np.ndarray:
        box = np.asarray(box)
        return np.flatnonzero(np.all(self.lo <= box[3:], axis=1) & np.all(self.hi >= box[:3], axis=1))


@pytest.fixture(scope="module")
def reference_mesh(building: Building) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3, 3) triangles and (F,) guid of every physical IFC element except doors, straight from the model."""
    triangles, guids = [], []
    for element in building.model.elements:
        if element.mesh is None or any(element.is_a(c) for c in (*NON_PHYSICAL_CLASSES, "IfcDoor")):
            continue
        triangles.append(element.mesh.vertices[element.mesh.faces])
        guids += [element.guid] * len(element.mesh.faces)
    return np.concatenate(triangles), np.asarray(guids)


@pytest.fixture(scope="module")
def world(building: Building) -> SimWorld:
    return build_world(building.prior, building.model, building.cfg, seed=0)


def _reference_hits(world: SimWorld, reference, origins, dirs):
    """Nearest hit distance along each ray and its guid ('' for the world's synthetic planes, inf: no hit)."""
    triangles, guids = reference
    planes = [i for i, rec in enumerate(world.instances) if not rec["guid"]]
    all_triangles = np.concatenate([triangles, *(world.meshes[i].vertices[world.meshes[i].faces] for i in planes)])
    all_guids = np.concatenate([guids, [""] * (len(all_triangles) - len(triangles))])
    tri, ray, location = ray_triangle_id(all_triangles, origins, dirs, tree=_BoxTree(all_triangles))
    t = np.einsum("ij,ij->i", location - origins[ray], dirs[ray])
    nearest = np.full(len(origins), np.inf)
    second = np.full(len(origins), np.inf)
    guid = np.full(len(origins), None, dtype=object)
    for k in np.argsort(t):
        r = ray[k]
        if nearest[r] == np.inf:
            nearest[r], guid[r] = t[k], all_guids[tri[k]]
        elif second[r] == np.inf and all_guids[tri[k]] != guid[r]:
            second[r] = t[k]
    return nearest, guid, second - nearest


def _view(building: Building, trajectories: list[SimTrajectory]) -> tuple[np.ndarray, float]:
    trajectory = trajectories[1]
    pose = trajectory.keyframe_poses[7]
    return pose, building.prior.storeys[trajectory.storey_index].storey.elevation_m


def _sample_pixels(camera: RgbdCamera, seed: int) -> np.ndarray:
    k = camera.intrinsics
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.integers(0, k.width, SAMPLE_PIXELS), rng.integers(0, k.height, SAMPLE_PIXELS)])


def _compare(world, reference, building, six_trajectories, cfg: Config, rng):
    camera = RgbdCamera.from_config(world, cfg)
    pose, elevation = _view(building, six_trajectories)
    image = camera.render(pose, elevation, rng)
    pixels = _sample_pixels(camera, seed=3)
    T_world_camera = se2_to_matrix(pose, elevation) @ camera.T_base_camera
    origins, dirs = pixel_rays(camera.intrinsics, T_world_camera, pixels.astype(float))
    ray_length, guid, margin = _reference_hits(world, reference, origins, dirs)
    depth_true = ray_length * (dirs @ T_world_camera[:3, 2])  # distance along the camera's z axis
    depth = image.depth_m[pixels[:, 1], pixels[:, 0]].astype(float)
    ids = image.instance_ids[pixels[:, 1], pixels[:, 0]]
    return camera, image, depth_true, depth, ids, guid, margin


def test_camera_mount_axes() -> None:
    from bimfactor.config import load_config

    cam = load_config().sim.camera.model_copy(update={"mount_pitch_deg": 10.0})
    T = camera_mount(cam)
    np.testing.assert_allclose(T[:3, 3], [cam.mount_forward_m, 0.0, cam.mount_height_m])
    pitch = np.deg2rad(10.0)
    np.testing.assert_allclose(T[:3, 2], [np.cos(pitch), 0.0, -np.sin(pitch)], atol=1e-12)  # looks ahead, down
    np.testing.assert_allclose(T[:3, 0], [0.0, -1.0, 0.0], atol=1e-12)  # image x is the robot's right
    assert T[2, 1] < 0  # image y points down
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_noise_free_depth_and_instances_match_trimesh(
    building: Building, world: SimWorld, reference_mesh, six_trajectories, config_overrides
) -> None:
    cfg = config_with(config_overrides, *NOISE_OFF)
    _, image, depth_true, depth, ids, guid, margin = _compare(
        world, reference_mesh, building, six_trajectories, cfg, np.random.default_rng(0)
    )
    in_range = (depth_true >= cfg.sim.camera.min_range_m) & (depth_true <= cfg.sim.camera.max_range_m)
    np.testing.assert_allclose(depth[in_range], depth_true[in_range], atol=1e-3)
    assert np.isnan(depth[~in_range]).all()
    assert in_range.sum() >= SAMPLE_PIXELS // 3
    # The instance buffer names the element trimesh hits first (where no other element is as near).
    hit = np.isfinite(depth_true)
    assert ((ids >= 0) == hit).all()
    clear = hit & (margin > TIE_M)
    assert clear.sum() >= SAMPLE_PIXELS // 2
    table_guids = np.asarray([world.instances[i]["guid"] for i in ids[clear]], dtype=object)
    assert list(table_guids) == list(guid[clear])
    # Misses show the background colour; hits never do in a noise-free image.
    rgb = image.rgb.reshape(-1, 3)
    miss = image.instance_ids.reshape(-1) < 0
    assert np.all(rgb[miss] == BACKGROUND_RGB.astype(np.uint8))


def test_noisy_depth_within_four_sigma(
    building: Building, world: SimWorld, reference_mesh, six_trajectories, test_config: Config
) -> None:
    cfg = test_config
    _, image, depth_true, depth, _, _, _ = _compare(
        world, reference_mesh, building, six_trajectories, cfg, np.random.default_rng(1)
    )
    valid = np.isfinite(depth)
    assert valid.sum() >= SAMPLE_PIXELS // 3
    sigma = cfg.sensor.depth_noise.sigma_m(depth_true[valid])
    assert np.all(np.abs(depth[valid] - depth_true[valid]) <= 4 * sigma + 1e-5)
    assert np.mean(np.abs(depth[valid] - depth_true[valid]) > 1e-5) > 0.5  # the noise is really on
    assert image.depth_m.dtype == np.float32 and image.instance_ids.dtype == np.int32
    assert image.rgb.dtype == np.uint8 and image.rgb.shape == (cfg.sim.camera.height, cfg.sim.camera.width, 3)


def test_noise_statistics_and_dropouts(building: Building, world: SimWorld, six_trajectories, config_overrides) -> None:
    pose, elevation = _view(building, six_trajectories)
    clean_cfg = config_with(config_overrides, *NOISE_OFF[:3])  # the default grazing dropout, no random noise
    clean_camera = RgbdCamera(
        world, clean_cfg.sim.camera, clean_cfg.sensor.depth_noise, clean_cfg.sim.depth_dropout, 0.0
    )
    clean = clean_camera.render(pose, elevation)
    cfg = config_with(config_overrides, "sim.depth_dropout.dropout_prob=0.2", "sim.rgb_noise_std=6")
    camera = RgbdCamera.from_config(world, cfg)
    noisy = camera.render(pose, elevation, np.random.default_rng(5))
    both = np.isfinite(clean.depth_m) & np.isfinite(noisy.depth_m)
    z = (noisy.depth_m[both] - clean.depth_m[both]) / cfg.sensor.depth_noise.sigma_m(clean.depth_m[both])
    assert abs(z.mean()) < 0.05 and 0.9 < z.std() < 1.1
    dropped = np.isnan(noisy.depth_m) & np.isfinite(clean.depth_m)
    assert 0.17 < dropped.sum() / np.isfinite(clean.depth_m).sum() < 0.23
    unclipped = (clean.rgb > 30) & (clean.rgb < 225)
    diff = noisy.rgb.astype(float)[unclipped] - clean.rgb.astype(float)[unclipped]
    assert abs(diff.mean()) < 0.2 and 5.5 < diff.std() < 6.5
    assert np.array_equal(noisy.instance_ids, clean.instance_ids)


def test_grazing_and_range_dropouts(building: Building, world: SimWorld, six_trajectories, config_overrides) -> None:
    pose, elevation = _view(building, six_trajectories)
    cfg = config_with(config_overrides, *NOISE_OFF[:3], "sim.camera.max_range_m=3.0")
    noise, dropout = cfg.sensor.depth_noise, cfg.sim.depth_dropout
    camera = RgbdCamera(world, cfg.sim.camera, noise, dropout, 0.0)
    image = camera.render(pose, elevation)
    reference = RgbdCamera(world, cfg.sim.camera.model_copy(update={"max_range_m": 1e3}), noise, dropout, 0.0)
    rays = reference.rays(pose, elevation).copy()
    t_hit, instance, normals = world.cast(rays)
    cos = np.abs(np.einsum("ij,ij->i", normals, rays[:, 3:])) / np.linalg.norm(rays[:, 3:], axis=1)
    grazing = cos < np.cos(np.deg2rad(cfg.sim.depth_dropout.grazing_dropout_deg))
    far = t_hit > 3.0
    expect_nan = (instance < 0) | grazing | far | (t_hit < cfg.sim.camera.min_range_m)
    assert np.array_equal(np.isnan(image.depth_m).reshape(-1), expect_nan)
    assert grazing.any() and far.any() and (~expect_nan).any()
