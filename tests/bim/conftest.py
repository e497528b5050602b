"""Fixtures for the offline stage: real IFC buildings, synthetic ones, and priors built once per session."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from bimfactor.bim.prior import BimPrior, build_prior
from bimfactor.bim.synth import write_building
from bimfactor.config import Config, load_config


@pytest.fixture(scope="session")
def session_cfg(config_overrides: list[str]) -> Callable[..., Config]:
    """Config factory on top of the session's geometry cache (never ~/.cache)."""

    def make(*overrides: str) -> Config:
        return load_config(overrides=[*config_overrides, *overrides])

    return make


@pytest.fixture(scope="session")
def synth_ifc(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """A synthetic building (preset, seed 0), written once per session."""
    folder = tmp_path_factory.mktemp("synth")
    written: dict[str, Path] = {}

    def make(preset: str) -> Path:
        if preset not in written:
            written[preset] = folder / f"{preset}.ifc"
            write_building(preset, 0, written[preset])
        return written[preset]

    return make


@pytest.fixture(scope="session")
def prior_of(ifc_file, synth_ifc, session_cfg) -> Callable[..., BimPrior]:
    """Prior of a real building file name or a synth preset ('synth:paper-floor'), built once per source mode."""
    built: dict[tuple[str, str], BimPrior] = {}

    def make(name: str, rooms: str = "auto") -> BimPrior:
        key = (name, rooms)
        if key not in built:
            path = synth_ifc(name.removeprefix("synth:")) if name.startswith("synth:") else ifc_file(name)
            built[key] = build_prior(path, session_cfg(f"bim.rooms.source={rooms}"))
        return built[key]

    return make
