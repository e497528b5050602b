"""The BIM surface model: points with normals sampled from each storey's structural surfaces.

Fine registration aligns depth scans with what the BIM says is solid and fixed: the prior's wall meshes
(`bim.surfaces`), sampled when a run starts. One `SurfaceModel` per storey holds world-frame points and unit
normals, and an Open3D point cloud and KD-tree built on demand.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from bimfactor.bim.surfaces import WallMeshes
from bimfactor.config import RegistrationConfig
from bimfactor.errors import InputError

log = logging.getLogger(__name__)

# Elements touching a storey band only at its boundary (the slab below, the walls of the storey underneath)
# are not part of it.
_BAND_EPS_M = 0.02
# Crops read the samples cell by cell (`SurfaceModel.crop_indices`); a KD-tree's ball query took 3-6 ms a crop.
CROP_CELL_M = 1.0


@dataclass
class SurfaceModel:
    """World-frame surface samples of one storey: `points` (N, 3) metres, `normals` (N, 3) unit vectors.

    `element_index` (N,) int32 says which element of the source model each point came from.
    """

    storey_index: int
    elevation_m: float
    height_m: float
    points: np.ndarray
    normals: np.ndarray
    element_index: np.ndarray
    _cloud: object = field(default=None, init=False, repr=False)
    _kdtree: object = field(default=None, init=False, repr=False)
    _nn_tree: object = field(default=None, init=False, repr=False)
    _cells: tuple | None = field(default=None, init=False, repr=False)
    _thinned: dict = field(default_factory=dict, init=False, repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def cloud(self):
        """The samples as an `open3d.geometry.PointCloud` with normals and planar covariances (for GICP)."""
        if self._cloud is None:
            self._cloud = to_point_cloud(self.points, self.normals)
        return self._cloud

    @property
    def kdtree(self):
        """An `open3d.geometry.KDTreeFlann` over the samples, built once."""
        if self._kdtree is None:
            import open3d as o3d

            self._kdtree = o3d.geometry.KDTreeFlann(self.cloud)
        return self._kdtree

    @property
    def nn_tree(self):
        """A `scipy.spatial.cKDTree` over the samples: vectorised nearest-neighbour queries for the planar solver."""
        if self._nn_tree is None:
            from scipy.spatial import cKDTree

            # Unbalanced, uncompacted: ~3x faster to build, barely slower to query (crops are built per call).
            self._nn_tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)
        return self._nn_tree

    def _cell_index(self) -> tuple:
        """The samples sorted by their `CROP_CELL_M` cell in the xy-plane, built once: (order, sorted cell keys,
        origin, cells per row). A row's cells are one run of the sorted keys, so a crop reads a slice per row."""
        if self._cells is None:
            xy = self.points[:, :2]
            origin = xy.min(axis=0) if len(xy) else np.zeros(2)
            cell = np.floor((xy - origin) / CROP_CELL_M).astype(np.int64)
            per_row = int(cell[:, 0].max(initial=0)) + 1
            keys = cell[:, 1] * per_row + cell[:, 0]
            order = np.argsort(keys, kind="stable")
            self._cells = (order, keys[order], origin, per_row)
        return self._cells

    def crop_indices(self, center_xy: np.ndarray, radius_m: float) -> np.ndarray:
        """(K,) indices (cell by cell) of the samples within `radius_m` of `center_xy` (2,) in the xy-plane."""
        if len(self.points) == 0:
            return np.zeros(0, dtype=np.int64)
        order, keys, origin, per_row = self._cell_index()
        center = np.asarray(center_xy, float)[:2]
        lo = np.floor((center - radius_m - origin) / CROP_CELL_M).astype(np.int64)
        hi = np.floor((center + radius_m - origin) / CROP_CELL_M).astype(np.int64)
        x0, x1 = max(int(lo[0]), 0), min(int(hi[0]), per_row - 1)
        rows = np.arange(max(int(lo[1]), 0), min(int(hi[1]), int(keys[-1] // per_row)) + 1)
        if x0 > x1 or not len(rows):
            return np.zeros(0, dtype=np.int64)
        starts = np.searchsorted(keys, rows * per_row + x0, side="left")
        stops = np.searchsorted(keys, rows * per_row + x1, side="right")
        found = np.concatenate([order[a:b] for a, b in zip(starts, stops, strict=True)])
        d = self.points[found, :2] - center
        return found[np.einsum("ij,ij->i", d, d) <= radius_m * radius_m]

    def crop(self, center_xy: np.ndarray, radius_m: float) -> SurfaceModel:
        """The samples within `radius_m` of `center_xy` in the xy-plane, as a new (smaller) model."""
        keep = self.crop_indices(center_xy, radius_m)
        return self.subset(keep)

    def subset(self, keep: np.ndarray) -> SurfaceModel:
        """The samples at indices (or mask) `keep`, as a new model of the same storey."""
        return SurfaceModel(
            self.storey_index,
            self.elevation_m,
            self.height_m,
            self.points[keep],
            self.normals[keep],
            self.element_index[keep],
        )

    def near_indices(self, points_xy: np.ndarray, cells: int) -> np.ndarray:
        """(K,) indices (cell by cell) of the samples in the `CROP_CELL_M` cells that hold any of the (N, 2) points, or
        lie within `cells` cells of one: the surface a scan can reach, without the rest of the disc around it."""
        if len(self.points) == 0 or len(points_xy) == 0:
            return np.zeros(0, dtype=np.int64)
        order, keys, origin, per_row = self._cell_index()
        cell = np.unique(
            np.floor((np.asarray(points_xy, float)[:, :2] - origin) / CROP_CELL_M).astype(np.int64), axis=0
        )
        offsets = np.arange(-cells, cells + 1)
        grown = (cell[:, None, None, :] + np.stack(np.meshgrid(offsets, offsets, indexing="ij"), -1)[None]).reshape(
            -1, 2
        )
        rows = int(keys[-1] // per_row) + 1
        inside = (grown[:, 0] >= 0) & (grown[:, 0] < per_row) & (grown[:, 1] >= 0) & (grown[:, 1] < rows)
        wanted = np.unique(grown[inside, 1] * per_row + grown[inside, 0])
        starts = np.searchsorted(keys, wanted, side="left")
        counts = np.searchsorted(keys, wanted, side="right") - starts
        if not counts.sum():
            return np.zeros(0, dtype=np.int64)
        # the runs starts[i] … starts[i] + counts[i] of the sorted order, concatenated without a Python loop
        run_offsets = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
        return order[np.arange(counts.sum()) + run_offsets]

    def facing_near(self, points_xy: np.ndarray, cells: int, center_xy: np.ndarray) -> SurfaceModel:
        """`near_indices`' samples that face `center_xy` (2,) (`faces`), as a new model."""
        keep = self.near_indices(points_xy, cells)
        return self.subset(keep[self.faces(keep, center_xy)])

    def faces(self, indices: np.ndarray, center_xy: np.ndarray) -> np.ndarray:
        """(K,) bool: do the samples at `indices` face `center_xy` (2,)? Near-horizontal faces (|n_z| > 0.9) do."""
        n, m = self.normals[indices], self.points[indices]
        to_center = np.asarray(center_xy, float)[:2] - m[:, :2]
        return (np.einsum("ij,ij->i", n[:, :2], to_center) > 0) | (np.abs(n[:, 2]) > 0.9)

    def facing(self, center_xy: np.ndarray, radius_m: float) -> SurfaceModel:
        """The samples within `radius_m` of `center_xy` (2,) whose normals face it (back faces culled).

        A scan sees a wall's near face only; without culling, ICP can lock onto the far face one wall
        thickness away with a perfect fit. Near-horizontal faces (|n_z| > 0.9) are kept.
        """
        keep = self.crop_indices(center_xy, radius_m)
        return self.subset(keep[self.faces(keep, center_xy)])

    def thinned(self, share: float) -> SurfaceModel:
        """A `share` of the samples, drawn at random once per share (seeded, so runs repeat): a sparser target for the
        Open3D registrars, whose per-call KD-tree and correspondence search scale with it. Random thinning keeps the
        samples' even spread over each face, which thinning to one per grid cell did not (it lost success)."""
        if share >= 1.0:
            return self
        if share not in self._thinned:
            rng = np.random.default_rng(len(self.points))
            self._thinned[share] = self.subset(np.sort(rng.permutation(len(self.points))[: int(share * len(self))]))
        return self._thinned[share]


def to_point_cloud(points: np.ndarray, normals: np.ndarray | None = None, planar_covariance: bool = True):
    """(N, 3) points (+ (N, 3) normals) → Open3D PointCloud; normals also give GICP's plane covariances."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    if normals is not None:
        normals = np.ascontiguousarray(normals, dtype=np.float64)
        cloud.normals = o3d.utility.Vector3dVector(normals)
        if planar_covariance:
            # GICP's surface prior: unit variance in the plane, ε along the normal (Segal et al. 2009).
            eps = 1e-3
            cov = np.eye(3)[None] - (1 - eps) * normals[:, :, None] * normals[:, None, :]
            cloud.covariances = o3d.utility.Matrix3dVector(cov)
    return cloud


def sample_mesh(
    vertices: np.ndarray, faces: np.ndarray, density_per_m2: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted uniform samples on a triangle mesh: (K, 3) points and (K, 3) unit face normals.

    Each triangle gets floor(area·density) points plus one more with probability of the remainder, so the
    expected count is density × area exactly; normals follow the face winding (sign is irrelevant to ICP).
    """
    tri = np.asarray(vertices, float)[np.asarray(faces, int)]  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    ok = double_area > 1e-12
    tri, cross, area = tri[ok], cross[ok], 0.5 * double_area[ok]
    expected = area * density_per_m2
    counts = np.floor(expected).astype(np.int64)
    counts += rng.random(len(counts)) < (expected - counts)
    if counts.sum() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    owner = np.repeat(np.arange(len(tri)), counts)
    # Uniform barycentric samples: reflect (u, v) outside the triangle back inside.
    u, v = rng.random(len(owner)), rng.random(len(owner))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[owner]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    normals = cross[owner] / np.linalg.norm(cross[owner], axis=1, keepdims=True)
    return points, normals


def build_surface_models(walls: WallMeshes, cfg: RegistrationConfig, seed: int = 0) -> list[SurfaceModel]:
    """One `SurfaceModel` per storey of the prior's wall meshes (list index = storey index), deterministic for a seed.

    An element belongs to every storey band its z-range crosses; its samples are clipped to the band.
    Normals point out of each element (`bim.surfaces.outward_mesh`).
    """
    if not len(walls.bands):
        raise InputError("the model has no storeys; cannot build a surface model")
    surfaces = []
    for index, (z_lo, z_hi) in enumerate(walls.bands):
        rng = np.random.default_rng([seed, index])
        pts, nrm, owner = [], [], []
        for e, (lo, hi) in enumerate(walls.z_range):
            if hi <= z_lo + _BAND_EPS_M or lo >= z_hi - _BAND_EPS_M:
                continue
            p, n = sample_mesh(*walls.mesh(e), cfg.surface_density_per_m2, rng)
            inside = (p[:, 2] >= z_lo) & (p[:, 2] <= z_hi)
            pts.append(p[inside])
            nrm.append(n[inside])
            owner.append(np.full(int(inside.sum()), walls.element_index[e], dtype=np.int32))
        if pts:
            points, normals, element_index = np.concatenate(pts), np.concatenate(nrm), np.concatenate(owner)
        else:
            points, normals, element_index = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int32)
        elevation = float(walls.elevations[index])
        surfaces.append(SurfaceModel(index, elevation, float(z_hi - z_lo), points, normals, element_index))
        log.info("surface model of storey %d: %d points from %d elements", index, len(points), len(pts))
    return surfaces
