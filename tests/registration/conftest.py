"""Registration tests reuse the simulator's session fixtures (the paper-floor prior and its IFC model)."""

from __future__ import annotations

import pytest

from bimfactor.bim.surfaces import wall_meshes
from bimfactor.evaluation.registrars import Keyframe, select_keyframes
from bimfactor.registration.surface import SurfaceModel, build_surface_models
from tests.sim.conftest import Building, paper_floor, text_embedder  # noqa: F401  (fixtures, re-exported)


@pytest.fixture(scope="session")
def keyframes_and_surfaces(paper_floor: Building) -> tuple[list[Keyframe], list[SurfaceModel]]:  # noqa: F811
    """Three registrable simulated keyframes of the paper floor (noisy depth) and its storeys' surface models."""
    surfaces = build_surface_models(wall_meshes(paper_floor.model), paper_floor.cfg.registration, seed=0)
    keyframes = select_keyframes(paper_floor.prior, paper_floor.model, paper_floor.cfg, surfaces, n=3, seed=0)
    return keyframes, surfaces
