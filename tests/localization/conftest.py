"""Fixtures for the localizer: the default S-MCL config, hand-built priors, and the synthetic office, built once."""

from __future__ import annotations

import pytest

from bimfactor.bim.prior import BimPrior, build_prior
from bimfactor.bim.synth import write_building
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config, SmclConfig
from tests.localization.handmade import make_prior


@pytest.fixture(scope="session")
def smcl_cfg(test_config: Config) -> SmclConfig:
    """The S-MCL settings by default (the paper's, plus the scan term and augmented MCL)."""
    return test_config.smcl


@pytest.fixture(scope="session")
def box_prior() -> BimPrior:
    """Two rooms split by a solid wall, one storey."""
    return make_prior(with_door=False)


@pytest.fixture(scope="session")
def box_visibility(box_prior: BimPrior, test_config: Config) -> VisibilityTable:
    return VisibilityTable.build(box_prior, test_config.bim.visibility, progress=False)


@pytest.fixture(scope="session")
def office_prior(tmp_path_factory: pytest.TempPathFactory, test_config: Config) -> BimPrior:
    """The synth `office` preset (8 near-identical offices, a kitchen, a bathroom) built into a prior."""
    path = tmp_path_factory.mktemp("localization-synth") / "office.ifc"
    write_building("office", 0, path)
    return build_prior(path, test_config)


@pytest.fixture(scope="session")
def office_visibility(office_prior: BimPrior, test_config: Config) -> VisibilityTable:
    return VisibilityTable.build(office_prior, test_config.bim.visibility, progress=False)
