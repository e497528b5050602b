"""Shared fixtures: the real IFC buildings beside the project, the session's caches, and a drive through the
paper-floor building localized by each online variant (the localizer's and the offline refinement's tests).

Tests never write to ~/.cache: pass `config_overrides` to `load_config` (or `cli_config_args` to the CLI),
or use `test_config` directly; they point `bim.ifc.cache_dir` at a temporary folder for the session, and the text
vectors' cache ($XDG_CACHE_HOME) is one too. Both are shared by the session's xdist workers: what one meshes or
embeds, the others read.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from bimfactor.config import Config, load_config
from bimfactor.evaluation.bench import SHARED_IFC_DIR, SHARED_REAL_DIR, find_shared_ifc_dir
from tests.sim import conftest as sim_fixtures

if TYPE_CHECKING:
    from bimfactor.sim.simulate import SimResult
    from tests.sim.conftest import Building

# The simulator tests' session fixtures: the paper-floor prior and the text embedder.
paper_floor = sim_fixtures.paper_floor
text_embedder = sim_fixtures.text_embedder

SEED = 3  # the localizer's seed in `runs` and the tests beside it


@pytest.fixture
def fixed_value(monkeypatch: pytest.MonkeyPatch):
    """Set one of a stage's fixed values (a ClassVar of its config model, e.g. `fixed_value("smcl.challenger.
    threshold_nats", 5.0)`) for the test: no preset or `--set` can."""

    def set_value(dotted: str, value: object) -> None:
        *blocks, name = dotted.split(".")
        model: type = Config
        for block in blocks:
            model = model.model_fields[block].annotation
        assert name in model.__class_vars__, f"{dotted} is a config key, not a fixed value"
        monkeypatch.setattr(model, name, value)

    return set_value


@pytest.fixture(scope="session")
def ifc_dir() -> Path:
    """`../shared/data/ifc` (the five real IFC buildings); the test is skipped when it is absent."""
    found = find_shared_ifc_dir()
    if found is None:
        pytest.skip(f"real IFC buildings not available: {SHARED_IFC_DIR} is missing")
    return found


@pytest.fixture(scope="session")
def real_recording():
    """`real_recording("tum-fr1-rpy")` → the real RGB-D recording in ../shared/data/real; skips when it is absent."""

    def get(name: str) -> Path:
        path = SHARED_REAL_DIR / name
        if not (path / "rgb.txt").is_file():
            pytest.skip(f"real recording not available: {path}")
        return path

    return get


@pytest.fixture(scope="session")
def ifc_file(ifc_dir: Path):
    """`ifc_file("AC20-FZK-Haus.ifc")` → its path; skips when that one file is missing."""

    def get(name: str) -> Path:
        path = ifc_dir / name
        if not path.is_file():
            pytest.skip(f"real IFC building not available: {path}")
        return path

    return get


def _session_dir(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    """A folder of this test session's, shared by its xdist workers (each worker's temp folder lies in the run's)."""
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / name
    folder.mkdir(exist_ok=True)
    return folder


@pytest.fixture(scope="session", autouse=True)
def text_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The text vectors' cache of the session ($XDG_CACHE_HOME, read by `embed.text.text_cache_dir`), not the
    user's; CLI runs in child processes inherit it."""
    folder = _session_dir(tmp_path_factory, "xdg-cache")
    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(folder)
    yield folder
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


@pytest.fixture(scope="session")
def geometry_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One geometry cache for the whole session, so each IFC file is meshed at most once per worker and is read,
    not meshed again, by a worker that asks for it after another wrote it (entries are written atomically)."""
    return _session_dir(tmp_path_factory, "geometry-cache")


@pytest.fixture(scope="session")
def config_overrides(geometry_cache_dir: Path) -> list[str]:
    """`--set`-style overrides every test config should carry: the session's geometry cache, the filter alone (the
    default runs every stage; tests of the graph and ICP stages name their variant) and the simulated world of the
    IFC model alone (the default moves, removes and adds objects; tests of that name it), so that a test's expected
    objects are the model's."""
    return [
        f"bim.ifc.cache_dir={geometry_cache_dir}",
        "localization.variant=smcl",
        "sim.as_built.moved_fraction=0",
        "sim.as_built.removed_fraction=0",
        "sim.as_built.clutter_count=0",
    ]


@pytest.fixture(scope="session")
def cli_config_args(config_overrides: list[str]) -> list[str]:
    """The same overrides as CLI arguments: `["--set", "bim.ifc.cache_dir=..."]`."""
    return [arg for override in config_overrides for arg in ("--set", override)]


@pytest.fixture(scope="session")
def test_config(config_overrides: list[str]) -> Config:
    """The default configuration with the session's geometry cache."""
    return load_config(None, config_overrides)


@pytest.fixture(scope="session")
def paper_floor_prior(tmp_path_factory: pytest.TempPathFactory, cli_config_args: list[str]) -> Path:
    """A prior of the paper-floor building (seed 0), built through the CLI once per session; read it, never write
    into it (copy it first)."""
    from typer.testing import CliRunner

    from bimfactor.cli import app

    folder = tmp_path_factory.mktemp("paper-floor")
    runner = CliRunner()
    assert runner.invoke(app, ["synth", "-o", str(folder / "paper-floor.ifc")]).exit_code == 0
    result = runner.invoke(
        app, ["prior", str(folder / "paper-floor.ifc"), "-o", str(folder / "prior"), *cli_config_args]
    )
    assert result.exit_code == 0, result.output
    return folder / "prior"


@pytest.fixture(scope="session")
def drive(paper_floor: Building) -> SimResult:
    """Standard trajectory 0 of the paper floor, T = 50."""
    from bimfactor.sim.simulate import simulate_sequence

    return simulate_sequence(paper_floor.prior, paper_floor.model, paper_floor.cfg, 0, 0, progress=False)


@pytest.fixture(scope="session")
def runs(paper_floor: Building, drive: SimResult, text_embedder, config_overrides: list[str]) -> dict:
    """The drive localized by each online variant with one seed."""
    from bimfactor.pipeline import localize_sequence

    out = {}
    for variant in ("smcl", "smcl+graph", "full"):
        cfg = load_config(None, [*config_overrides, f"localization.variant={variant}"])
        out[variant] = localize_sequence(
            paper_floor.prior, drive.meta, drive.frames, cfg, SEED, text_embedder=text_embedder, show_progress=False
        )
    return out
