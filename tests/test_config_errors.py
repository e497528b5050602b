"""Configurations that cannot work end in one `error:` line with exit code 2, never in an internal error: non-finite
numbers, config files that are not a YAML mapping, and particle counts or grids larger than the machine's memory."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from bimfactor import config as config_module
from bimfactor import resources
from bimfactor.cli import app
from bimfactor.config import CONFIG_DIR, Config, SimPerceptionErrors, load_config
from bimfactor.errors import ConfigError
from bimfactor.resources import check_grid_memory, check_particle_memory, format_bytes, grid_memory
from tests.cli import assert_one_line_error, runner

GIB = 1 << 30


def synth_with(tmp_path: Path, *args: str) -> object:
    """`bimfactor synth` validates its configuration before it writes anything: the cheapest command to load one."""
    result = runner.invoke(app, ["synth", "-o", str(tmp_path / "x.ifc"), *args])
    assert not (tmp_path / "x.ifc").exists()
    return result


# ------------------------------------------------------------------------------------------- non-finite numbers


@pytest.mark.parametrize(
    ("assignment", "expected"),
    [
        ("smcl.motion.sigma_trans_m=.inf", "config key 'smcl.motion.sigma_trans_m': must be a finite number, not inf"),
        (
            "smcl.motion.sigma_trans_m=-.inf",
            "config key 'smcl.motion.sigma_trans_m': must be a finite number, not -inf",
        ),
        (
            "smcl.motion.sigma_trans_m=1.0e+400",
            "config key 'smcl.motion.sigma_trans_m': must be a finite number, not inf",
        ),
        ("bim.grid.band_min_m=.nan", "config key 'bim.grid.band_min_m': must be a finite number, not nan"),
        ("sim.camera.mount_pitch_deg=.inf", "config key 'sim.camera.mount_pitch_deg'"),
        ("odometry.alpha=[0.1, .inf, 0.1, 0.1]", "config key 'odometry.alpha.1': must be a finite number"),
        ("smcl.start.pose=[1.0, .inf, 0.0]", "config key 'smcl.start.pose.1'"),
        ("sensor.depth_noise.k_per_m=.inf", "config key 'sensor.depth_noise.k_per_m'"),
    ],
)
def test_non_finite_floats_are_a_one_line_error_naming_the_key(tmp_path: Path, assignment: str, expected: str) -> None:
    assert_one_line_error(synth_with(tmp_path, "--set", assignment), contains=expected)


def test_non_finite_floats_in_a_config_file_are_refused(tmp_path: Path) -> None:
    preset = tmp_path / "mine.yaml"
    preset.write_text("odometry:\n  alpha: [0.1, 0.1, .nan, 0.1]\n")
    assert_one_line_error(synth_with(tmp_path, "-c", str(preset)), contains="config key 'odometry.alpha.2'")


def test_every_config_model_refuses_inf_and_nan() -> None:
    """One rule for the whole tree: every model in bimfactor.config has allow_inf_nan off (through _Strict)."""
    models = [
        obj
        for _, obj in inspect.getmembers(config_module, inspect.isclass)
        if issubclass(obj, BaseModel) and obj.__module__ == config_module.__name__
    ]
    assert Config in models and SimPerceptionErrors in models and len(models) > 20
    for model in models:
        assert model.model_config.get("allow_inf_nan") is False, model.__name__


def test_shipped_configs_are_finite_and_fit(config_overrides: list[str]) -> None:
    """The default, every preset in bimfactor/configs/ and every sim perception preset validate under the rule."""
    load_config(None, config_overrides)
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        data = yaml.safe_load(path.read_text())
        if isinstance(data, dict) and data and set(data) <= set(Config.model_fields):  # a config preset
            load_config(path, config_overrides)
    for preset in yaml.safe_load((CONFIG_DIR / "perception_sim.yaml").read_text()).values():
        SimPerceptionErrors.model_validate(preset)


# --------------------------------------------------------------------------------------- malformed config files


def _latin1(tmp: Path) -> Path:
    path = tmp / "latin1.yaml"
    path.write_bytes("smcl:\n  # Flur, Gebäude\n  num_particles: 10\n".encode("latin-1"))
    return path


def _write(name: str, text: str):
    def make(tmp: Path) -> Path:
        path = tmp / name
        path.write_text(text)
        return path

    return make


def _folder(tmp: Path) -> Path:
    path = tmp / "folder.yaml"
    path.mkdir()
    return path


MALFORMED = {
    "latin-1 bytes": (_latin1, "latin1.yaml: not UTF-8 text: byte 0xe4 at offset 19 (line 2)"),
    "a list": (_write("list.yaml", "- smcl\n- bim\n"), "list.yaml: top level must be a mapping of config keys"),
    "a scalar": (_write("scalar.yaml", "3\n"), "not a number"),
    "a string": (_write("string.yaml", "smcl.num_particles=10\n"), "not a string"),
    "a tab": (_write("tab.yaml", "smcl:\n\tnum_particles: 10\n"), "tab.yaml: not valid YAML at line 2, column 1"),
    "bad syntax": (_write("syntax.yaml", "smcl: [1, 2\n"), "syntax.yaml: not valid YAML at line 2"),
    "a NUL byte": (_write("nul.yaml", "seed: 1\0\n"), "nul.yaml: not valid YAML at line 1: character '\\x00'"),
    "a python tag": (_write("tag.yaml", "seed: !!python/object:os.system {}\n"), "tag.yaml: not valid YAML at line 1"),
    "a folder": (_folder, "folder.yaml is a folder, not a config file"),
    "an empty file": (_write("empty.yaml", ""), "empty.yaml: the file is empty"),
    "blank lines": (_write("blank.yaml", "\n  \n"), "blank.yaml: the file is empty"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_config_file_is_a_one_line_error(case: str, tmp_path: Path) -> None:
    make, expected = MALFORMED[case]
    path = make(tmp_path)
    assert_one_line_error(synth_with(tmp_path, "-c", str(path)), contains=expected)
    with pytest.raises(ConfigError, match="^" + str(path).replace("\\", "\\\\")):
        load_config(path)


def test_a_file_of_comments_only_overrides_nothing(tmp_path: Path, config_overrides: list[str]) -> None:
    path = tmp_path / "commented.yaml"
    path.write_text("# smcl:\n#   num_particles: 10\n")
    assert load_config(path, config_overrides) == load_config(None, config_overrides)


def test_a_utf8_file_with_byte_order_mark_loads(tmp_path: Path, config_overrides: list[str]) -> None:
    path = tmp_path / "bom.yaml"
    path.write_bytes(b"\xef\xbb\xbfsmcl:\n  num_particles: 10\n")
    assert load_config(path, config_overrides).smcl.num_particles == 10


# ------------------------------------------------------------------------------------------------------ memory


@pytest.fixture
def machine_with_23_gib(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 23 * GIB)


def test_a_billion_particles_are_refused_with_the_memory_they_need(tmp_path: Path, machine_with_23_gib) -> None:
    line = assert_one_line_error(synth_with(tmp_path, "--set", "smcl.resampler.max_particles=1000000000"))
    assert line == (
        "error: smcl.resampler.max_particles=1000000000 and smcl.text_reset.oversample=4 need about 4.2 TiB for the "
        "particle filter (1.1 KiB a particle); this machine has 23 GiB available"
    )
    sets = ("--set", "smcl.resampler.kind=systematic", "--set", "smcl.num_particles=1000000000")
    assert_one_line_error(synth_with(tmp_path, *sets), contains="smcl.num_particles=1000000000 and smcl.text_reset")
    line = assert_one_line_error(synth_with(tmp_path, "--set", "smcl.challenger.particles=100000000"))
    assert "smcl.challenger.particles=100000000 needs about 103 GiB" in line and "max_particles" not in line


def test_particle_counts_are_checked_against_this_machine(tmp_path: Path) -> None:
    """Without a stand-in: a trillion particles (about a PiB) fit on no machine."""
    line = assert_one_line_error(synth_with(tmp_path, "--set", "smcl.resampler.max_particles=1000000000000"))
    assert "smcl.resampler.max_particles=1000000000000 and smcl.text_reset.oversample=4 need about" in line
    assert "available" in line


def test_the_default_particles_fit_in_little_memory(test_config: Config, config_overrides: list[str]) -> None:
    check_particle_memory(test_config, available=64 << 20)
    without_text = load_config(None, [*config_overrides, "perception.text.enabled=false"])
    check_particle_memory(without_text, available=64 << 20)
    with pytest.raises(
        ConfigError, match=r"^smcl.resampler.max_particles=5000 needs about 5.\d MiB .* has 1.0 MiB available$"
    ):
        check_particle_memory(without_text, available=1 << 20)
    # The door-plate reset screens 4 × 4 × 1000 drawn poses: the default's largest set.
    with pytest.raises(
        ConfigError, match=r"^smcl.resampler.max_particles=5000 and smcl.text_reset.oversample=4 need about 2\d MiB"
    ):
        check_particle_memory(test_config, available=1 << 20)
    big_challenger = load_config(
        None, [*config_overrides, "perception.text.enabled=false", "smcl.challenger.particles=5000"]
    )
    with pytest.raises(
        ConfigError, match=r"^smcl.resampler.max_particles=5000 and smcl.challenger.particles=5000 need about"
    ):
        check_particle_memory(big_challenger, available=1 << 20)


def test_the_largest_shared_building_fits_at_the_default_grid(test_config: Config) -> None:
    """AC11-Institute-Var-2 is about 90 x 90 m with 5 storeys: its grids at 5 cm need well under a GiB."""
    grid, lattice = grid_memory((90.0, 90.0), 5, test_config)
    assert 0.3 * GIB < grid + lattice < 1 * GIB
    check_grid_memory((90.0, 90.0), 5, test_config, available=2 * GIB)


def test_a_millimetre_grid_is_refused_with_the_memory_it_needs(
    config_overrides: list[str], machine_with_23_gib
) -> None:
    fine = load_config(None, [*config_overrides, "bim.grid.resolution_m=0.001"])
    with pytest.raises(ConfigError) as info:
        check_grid_memory((90.0, 90.0), 5, fine)
    assert str(info.value) == (
        "bim.grid.resolution_m=0.001 needs about 1.5 TiB for the grids of 5 storeys of 92 x 92 m; "
        "this machine has 23 GiB available"
    )
    # a padded extent (GridSpec.extent) is not padded again
    assert grid_memory((92.0, 92.0), 5, fine, padding_included=True) == grid_memory((90.0, 90.0), 5, fine)


def test_available_memory_is_known_here() -> None:
    available = resources.available_memory_bytes()
    assert available is not None and available > 64 << 20


def test_format_bytes() -> None:
    assert [format_bytes(n) for n in (512, 3 << 20, 23 * GIB, 1.5 * (1 << 40))] == [
        "512 B",
        "3.0 MiB",
        "23 GiB",
        "1.5 TiB",
    ]
