"""The named presets (`-c paper`, `-c default`, `-c fast`) and the config folder that ships inside the wheel."""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from bimfactor.config import CONFIG_DIR, ESSENTIAL_KEYS, PRESETS, Config, leaf_keys, load_config
from bimfactor.errors import ConfigError
from tests.cli import assert_one_line_error, invoke

REPO = Path(__file__).resolve().parent.parent
DATA_TABLES = ("perception_sim.yaml", "room_categories.yaml", "vocabulary.yaml")


@pytest.fixture(scope="module")
def paper(config_overrides: list[str]) -> Config:
    return load_config("paper", config_overrides)


@pytest.fixture(scope="module")
def fast(config_overrides: list[str]) -> Config:
    return load_config("fast", config_overrides)


@pytest.fixture(scope="module")
def default(config_overrides: list[str]) -> Config:
    return load_config(None, config_overrides)


# ------------------------------------------------------------------------------------------------ the wheel


def test_the_wheel_ships_the_config_folder(tmp_path: Path) -> None:
    """A non-editable install reads its configs from the package: the presets and the data tables are
    in the wheel (built offline from a copy of the sources, so the checkout gets no build/ folder)."""
    source = tmp_path / "src"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, source / name)
    shutil.copytree(REPO / "bimfactor", source / "bimfactor", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    offline = ["--no-deps", "--no-build-isolation", "--no-index", "-q"]
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(source), *offline, "-w", str(tmp_path / "dist")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stdout + built.stderr
    (wheel,) = (tmp_path / "dist").glob("bimfactor-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    expected = {*(f"{p}.yaml" for p in PRESETS if p != "default"), *DATA_TABLES}
    expected |= {path.name for path in CONFIG_DIR.glob("*.yaml")}  # whatever else the folder holds ships too
    missing = sorted(f"bimfactor/configs/{n}" for n in expected if f"bimfactor/configs/{n}" not in names)
    assert not missing, f"not in {wheel.name}: {missing}"


def test_the_config_folder_is_inside_the_package() -> None:
    assert CONFIG_DIR == REPO / "bimfactor" / "configs"
    assert not (REPO / "configs").exists()
    for name in (*DATA_TABLES, *(f"{p}.yaml" for p in PRESETS if p != "default")):
        assert (CONFIG_DIR / name).is_file(), name


# ------------------------------------------------------------------------------------------------ the presets


def test_the_default_preset_is_the_fields_defaults(default: Config, config_overrides: list[str]) -> None:
    assert load_config("default", config_overrides) == default
    assert Config().smcl == default.smcl and Config().backend == default.backend  # a Python user's SmclConfig()


def test_every_preset_key_says_why() -> None:
    """Every value a preset sets carries a comment on its line (the paper's section or equation, or the reason)."""
    for name in ("paper", "fast"):
        for number, line in enumerate((CONFIG_DIR / f"{name}.yaml").read_text().splitlines(), 1):
            if re.match(r"^\s*[a-z_]+:\s*[^\s#]", line):  # `key: value`, not a section header
                assert "#" in line, f"{name}.yaml line {number} has no comment: {line.strip()}"


def test_paper_turns_every_extension_off(paper: Config) -> None:
    s = paper.smcl
    assert s.resampler.kind == "systematic"  # M particles throughout
    assert not s.semantic.fov_extent and not s.semantic.footprint_match  # the objects' centres
    assert s.semantic.similarity == "cosine"  # φ_sem = cos(f_j, C_k)
    assert s.semantic.count_exponent == 1.0  # the mean of the matched scores
    assert s.motion.off_map_weight == 1.0  # the prediction weighs nothing
    assert not s.scan.enabled
    assert not s.augmented.enabled
    assert not s.relocalize.enabled
    assert not s.challenger.enabled
    assert not s.text_reset.enabled and not paper.perception.text.enabled
    assert s.start.pose is None and s.start.storeys is None  # uniform over the navigable space
    assert paper.localization.variant == "smcl"
    assert paper.evaluation.variants == ["smcl"]
    assert paper.evaluation.scenario == "global"


def test_paper_has_the_papers_constants(paper: Config) -> None:
    """Sec. III's hyperparameters."""
    s = paper.smcl
    assert (s.num_particles, s.semantic.fov_deg, s.ess_threshold) == (1000, 90.0, 0.5)
    assert (s.motion.sigma_trans_m, s.motion.sigma_rot_deg) == (0.2, 10.0)
    assert (s.semantic.sigma_d_m, s.semantic.kappa_alpha) == (1.2, 5.0)
    p = paper.perception
    assert (p.box_threshold, p.text_threshold, p.sim_threshold, p.iou_threshold) == (0.25, 0.25, 0.7, 0.7)
    ev = paper.evaluation
    assert (ev.num_trajectories, ev.trajectory_length, ev.repeats) == (6, 50, 3)


def test_fast_cuts_costs_and_keeps_every_stage(fast: Config, default: Config) -> None:
    f, d = fast.smcl, default.smcl
    assert f.num_particles < d.num_particles
    assert f.challenger.particles < d.challenger.particles
    assert fast.backend.max_modes < default.backend.max_modes
    assert fast.perception.max_points < default.perception.max_points
    assert f.resampler.kind == d.resampler.kind
    for stage in ("scan", "augmented", "text_reset", "relocalize", "challenger"):
        assert getattr(f, stage).enabled == getattr(d, stage).enabled, stage
    assert fast.backend.scan_factor.enabled == default.backend.scan_factor.enabled
    assert fast.localization.variant == default.localization.variant
    assert fast.bim == default.bim  # the same prior serves both


def test_an_unknown_preset_names_the_presets(config_overrides: list[str]) -> None:
    with pytest.raises(ConfigError, match="the presets are paper, default, fast"):
        load_config("papr", config_overrides)


def test_the_config_option_names_the_presets() -> None:
    result = invoke("localize", "--help")
    assert result.exit_code == 0
    assert "paper, default, fast, or a YAML file" in " ".join(result.output.split())


def test_the_cli_takes_a_preset_by_name(tmp_path: Path, cli_config_args: list[str]) -> None:
    """`-c paper` loads (`synth`, the cheapest command) and passes bench paper's protocol checks; a typo is one line."""
    from bimfactor.evaluation.paper import check_protocol

    check_protocol(load_config("paper"))
    result = invoke("synth", "-o", tmp_path / "x.ifc", "-c", "paper", *cli_config_args)
    assert result.exit_code == 0, result.output
    assert_one_line_error(invoke("synth", "-o", tmp_path / "y.ifc", "-c", "papr"), contains="config file not found")


# ------------------------------------------------------------------------------------------------ what a user sees


def test_the_essential_keys_are_few_documented_leaf_keys() -> None:
    keys = dict(leaf_keys())
    assert 20 <= len(ESSENTIAL_KEYS) <= 30 < len(keys)
    assert len(set(ESSENTIAL_KEYS)) == len(ESSENTIAL_KEYS)
    assert all(keys[key].description for key in ESSENTIAL_KEYS)
    assert [key for key, field in keys.items() if not field.description] == []


def test_bimfactor_config_prints_the_essential_keys_as_a_run_resolves_them(tmp_path: Path) -> None:
    result = invoke("config", "-c", "paper", "--set", "smcl.num_particles=7")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert [line.split(":")[0] for line in lines] == list(ESSENTIAL_KEYS)
    assert any(re.match(r"smcl\.num_particles: 7 +# M \(paper: 1000\)", line) for line in lines)
    assert any(line.startswith('smcl.resampler.kind: "systematic" ') for line in lines)

    # --all is the whole tree, and it reads back as the same configuration.
    result = invoke("config", "--all", "-c", "paper", "--set", "smcl.num_particles=7")
    assert result.exit_code == 0, result.output
    (tmp_path / "all.yaml").write_text(result.output)
    assert load_config(tmp_path / "all.yaml") == load_config("paper", ["smcl.num_particles=7"])
    assert_one_line_error(invoke("config", "--set", "smcl.particles=7"), contains="unknown config key 'smcl.particles'")


def test_the_configuration_pages_are_current() -> None:
    """docs/configuration.md's essential keys and docs/config-reference.md are generated from the models and presets:
    a changed key, default or description fails here until `tools/render_config.py` is run."""
    spec = importlib.util.spec_from_file_location("render_config", REPO / "tools/render_config.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--check"]) == 0


def test_a_negative_seed_is_refused_when_the_config_is_read() -> None:
    """numpy takes no negative seed: `--set seed=-1` is one line and exit 2 at `config`, not a crash in every run."""
    assert_one_line_error(invoke("config", "--set", "seed=-1"), contains="seed")
    assert invoke("config", "--set", "seed=0").exit_code == 0
