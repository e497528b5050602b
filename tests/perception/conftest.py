"""Fixtures of the perception tests: the simulator tests' paper floor, and orbits around its furniture."""

from __future__ import annotations

import pytest

from bimfactor.config import PerceptionConfig, load_config
from bimfactor.perception.scenes import orbit_poses, render_poses
from bimfactor.sim.simulate import SimResult
from tests.perception.scenes import MEETING_TABLE, tour_poses
from tests.sim import conftest as sim_fixtures
from tests.sim.conftest import Building

# The simulator tests' session fixtures, shared here: the paper-floor prior and the text embedder.
paper_floor = sim_fixtures.paper_floor
text_embedder = sim_fixtures.text_embedder


def perception_config(config_overrides: list[str], *overrides: str) -> PerceptionConfig:
    """The default perception settings with `perception.key=value` overrides."""
    return load_config(None, [*config_overrides, *(f"perception.{o}" for o in overrides)]).perception


@pytest.fixture(scope="session")
def meeting_orbit(paper_floor: Building) -> SimResult:
    """15 frames on an arc 3.2 m around the meeting-room table and its four chairs, with noisy odometry."""
    poses = orbit_poses(MEETING_TABLE, 15)
    return render_poses(paper_floor.prior, paper_floor.model, paper_floor.cfg, poses, name="meeting")


@pytest.fixture(scope="session")
def furniture_tour(paper_floor: Building) -> SimResult:
    """60 frames: 12 around each of the paper floor's five furniture groups."""
    return render_poses(paper_floor.prior, paper_floor.model, paper_floor.cfg, tour_poses(12), name="tour")
