"""Shared fixtures of the simulator tests: the paper-floor and duplex priors, built once per session."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bimfactor.bim.ifc import IfcModel, load_ifc
from bimfactor.bim.prior import BimPrior, build_prior
from bimfactor.bim.synth import write_building
from bimfactor.config import Config, load_config
from bimfactor.embed.text import TextEmbedder, make_text_embedder
from bimfactor.sim.trajectory import SimTrajectory, standard_trajectories

BUILDINGS = ("paper-floor", "duplex")
NOISE_OFF = [
    "sensor.depth_noise.sigma0_m=0",
    "sensor.depth_noise.k_per_m=0",
    "sim.depth_dropout.dropout_prob=0",
    "sim.depth_dropout.grazing_dropout_deg=90",
    "sim.rgb_noise_std=0",
]


@dataclass
class Building:
    """A prior with the IFC model it was built from and the configuration that built it."""

    name: str
    prior: BimPrior
    model: IfcModel
    cfg: Config
    ifc_path: Path


@pytest.fixture(scope="session")
def text_embedder(test_config: Config) -> TextEmbedder:
    return make_text_embedder(test_config.embed)


def _building(name: str, path: Path, cfg: Config, embedder: TextEmbedder) -> Building:
    return Building(name, build_prior(path, cfg, embedder), load_ifc(path, cfg.bim.ifc), cfg, path)


@pytest.fixture(scope="session")
def paper_floor(tmp_path_factory: pytest.TempPathFactory, test_config: Config, text_embedder) -> Building:
    path = tmp_path_factory.mktemp("paper-floor") / "paper-floor.ifc"
    write_building("paper-floor", 0, path)
    return _building("paper-floor", path, test_config, text_embedder)


@pytest.fixture(scope="session")
def lift_house(tmp_path_factory: pytest.TempPathFactory, test_config: Config, text_embedder) -> Building:
    """Two floors joined by a lift (`bim.synth`'s lift-house)."""
    path = tmp_path_factory.mktemp("lift-house") / "lift-house.ifc"
    write_building("lift-house", 0, path)
    return _building("lift-house", path, test_config, text_embedder)


@pytest.fixture(scope="session")
def duplex(ifc_file, test_config: Config, text_embedder) -> Building:
    return _building("duplex", ifc_file("duplex.ifc"), test_config, text_embedder)


@pytest.fixture(scope="session", params=BUILDINGS)
def building(request: pytest.FixtureRequest) -> Building:
    """Each test that takes it runs on the paper floor and on the real duplex."""
    return request.getfixturevalue(request.param.replace("-", "_"))


@pytest.fixture(scope="session")
def six_trajectories(building: Building) -> list[SimTrajectory]:
    """The six standard trajectories of the building for seed 0."""
    return standard_trajectories(building.prior, n=6, seed=0, cfg=building.cfg)


def config_with(config_overrides: list[str], *overrides: str) -> Config:
    return load_config(None, [*config_overrides, *overrides])


def pixel_rays(intrinsics, T_world_camera: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) origins and (N, 3) unit world directions of the rays through (N, 2) pixel (u, v) centres."""
    uv1 = np.column_stack([pixels, np.ones(len(pixels))])
    dirs_camera = uv1 @ np.linalg.inv(intrinsics.K).T
    dirs = dirs_camera @ T_world_camera[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return np.broadcast_to(T_world_camera[:3, 3], dirs.shape).copy(), dirs
