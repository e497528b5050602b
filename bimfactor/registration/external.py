"""Registrars from optional libraries, for the comparison: small_gicp (GICP) and KISS-ICP (point-to-point).

Installed with `pip install 'bimfactor[registrars]'` (a missing one is a DependencyError with that hint), both run in
6-DoF and are held to SE(2) like `Open3dIcp` (`CentredRegistrar`); diagnostics come from `registration_result`.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

import numpy as np

from bimfactor.config import RegistrationConfig
from bimfactor.errors import import_optional
from bimfactor.registration.icp import CentredRegistrar
from bimfactor.registration.surface import SurfaceModel

INSTALL_HINT = "pip install 'bimfactor[registrars]'"
# The Python module each optional registrar needs.
OPTIONAL_MODULES = {"small_gicp": "small_gicp", "kiss_icp": "kiss_icp"}
# small_gicp estimates each point's normal and covariance from this many neighbours (its own default).
SMALL_GICP_NEIGHBOURS = 20
# KISS-ICP's voxel map keeps at most this many points per voxel (its default for the local map).
KISS_POINTS_PER_VOXEL = 20
# KISS-ICP stops when an ICP update is smaller than this (its default convergence criterion).
KISS_CONVERGENCE = 1e-4


def is_available(name: str) -> bool:
    """Whether the optional registrar `name` can be constructed (its library is installed)."""
    return importlib.util.find_spec(OPTIONAL_MODULES[name]) is not None


def require(name: str) -> ModuleType:
    """The library of the optional registrar `name`, or a DependencyError with the install hint."""
    return import_optional(OPTIONAL_MODULES[name], f"registrar '{name}'", INSTALL_HINT)


class SmallGicp(CentredRegistrar):
    """small_gicp's registration (`kind`: "GICP" or "PLANE_ICP"), normals and covariances from 20 neighbours."""

    def __init__(self, cfg: RegistrationConfig, kind: str = "GICP", name: str = "small_gicp") -> None:
        self.cfg = cfg
        self._sg = require("small_gicp")
        self.kind = kind
        self.name = name

    def align(
        self, scan: np.ndarray, local: SurfaceModel, center: np.ndarray, T_init: np.ndarray, z_m: float
    ) -> tuple[np.ndarray, int]:
        sg = self._sg
        target = local.points - center
        target_cloud = sg.PointCloud(np.ascontiguousarray(target))
        tree = sg.KdTree(target_cloud)
        sg.estimate_normals_covariances(target_cloud, tree, num_neighbors=SMALL_GICP_NEIGHBOURS)
        source_cloud = sg.PointCloud(np.ascontiguousarray(scan))
        sg.estimate_normals_covariances(source_cloud, num_neighbors=SMALL_GICP_NEIGHBOURS)
        out = sg.align(
            target_cloud,
            source_cloud,
            tree,
            init_T_target_source=T_init,
            registration_type=self.kind,
            max_correspondence_distance=self.cfg.max_correspondence_m,
            max_iterations=self.cfg.max_iterations,
        )
        return np.asarray(out.T_target_source), int(out.iterations)


class KissIcp(CentredRegistrar):
    """KISS-ICP's point-to-map registration (point-to-point, Geman–McClure kernel) against a voxel map of the target:
    the correspondence distance `max_correspondence_m`, the kernel a third of it, the voxel size the distance."""

    def __init__(self, cfg: RegistrationConfig, name: str = "kiss_icp") -> None:
        self.cfg = cfg
        require("kiss_icp")
        self.name = name

    def align(
        self, scan: np.ndarray, local: SurfaceModel, center: np.ndarray, T_init: np.ndarray, z_m: float
    ) -> tuple[np.ndarray, int]:
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration

        target = local.points - center
        distance = self.cfg.max_correspondence_m
        voxel_map = VoxelHashMap(
            voxel_size=distance,
            max_distance=float(np.max(np.linalg.norm(target, axis=1))) + distance,
            max_points_per_voxel=KISS_POINTS_PER_VOXEL,
        )
        voxel_map.add_points(np.ascontiguousarray(target))
        registration = Registration(
            max_num_iterations=self.cfg.max_iterations, convergence_criterion=KISS_CONVERGENCE, max_num_threads=1
        )
        T = registration.align_points_to_map(
            np.ascontiguousarray(scan), voxel_map, T_init, max_correspondance_distance=distance, kernel=distance / 3
        )
        return np.asarray(T), -1
