"""Memory a configuration will need, checked before the arrays are allocated.

The estimates are about the peak the code allocates (measured with tracemalloc on the shipped buildings); a
configuration is refused only when its estimate exceeds the memory available now, instead of a `MemoryError` deep in
numpy minutes later. `check_particle_memory` runs in `load_config`, `check_grid_memory` in the prior builder.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from bimfactor.errors import ConfigError

if TYPE_CHECKING:
    from bimfactor.config import Config

PARTICLE_BYTES = 384
"""Peak bytes per particle of a filter step without the scan term: the particle arrays and their resampled copies,
the candidate lists and φ matrices of the semantic update. Measured on the paper floor (tracemalloc, predict + update
+ resample of 200 000 particles): 390 B with few observations, 1 kB with the benchmark's twelve; the observations are
not known when the config is loaded, so the smaller figure is used."""
PARTICLE_BEAM_BYTES = 16
"""Peak bytes per particle and scan endpoint of the scan term: the (particles, endpoints) int64 grid indices of the
likelihood-field lookup (measured: 14.7 B)."""
GRID_CELL_BYTES = 40
"""Peak bytes per occupancy-grid cell and storey while a prior is built (structure, furniture, clearance, room labels
and navigable layers, the distance transforms and flood fills). Measured (tracemalloc over build_prior): 40 B on the
one-storey paper floor, 41 B on the two-storey FZK-Haus, 27 B on the five-storey AC11-Institute."""
LATTICE_CELL_BYTES = 16
"""Bytes per cell and storey of the visibility table's lattice (`bim.visibility.cell_m`): its row index and the
origins, offsets and counts of the free cells."""
SIGNIFICANT_SHARE = 0.1
"""A setting is named in a refusal when its part is at least this share of the estimate."""


def available_memory_bytes() -> int | None:
    """Memory this process can still allocate without swapping: the system's available memory (psutil when it is
    installed, else /proc/meminfo's MemAvailable, else the free pages), capped by the cgroup's remaining limit in a
    container. None when nothing can tell."""
    host = _host_available()
    limit = _cgroup_remaining()
    if host is None:
        return limit
    return host if limit is None else min(host, limit)


def _host_available() -> int | None:
    try:
        import psutil  # not a dependency of bimfactor: used when it is there

        return int(psutil.virtual_memory().available)
    except Exception:
        pass
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return None


def _cgroup_remaining() -> int | None:
    """The cgroup's memory limit less its usage (v2, then v1); None without a limit."""
    for limit_file, usage_file in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
    ):
        try:
            limit_text = Path(limit_file).read_text().strip()
            if limit_text == "max":
                return None
            limit, usage = int(limit_text), int(Path(usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit >= 1 << 60:  # cgroup v1's "no limit" is a huge number
            return None
        return max(limit - usage, 0)
    return None


def format_bytes(n: float) -> str:
    """'512 MiB', '23 GiB', '1.2 TiB': binary units, two or three significant digits."""
    for unit, size in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            value = n / size
            return f"{value:.1f} {unit}" if value < 10 else f"{value:.0f} {unit}"
    return f"{int(n)} B"


def scan_beams(cfg: Config) -> int:
    """Scan endpoints per frame: one per `scan.beam_deg` of the camera's view, at most one per image column;
    0 without the scan term."""
    if not cfg.smcl.scan.enabled:
        return 0
    view_deg = min(cfg.sim.camera.hfov_deg, cfg.smcl.semantic.fov_deg, 360.0)
    return min(math.ceil(view_deg / cfg.scan.beam_deg), cfg.sim.camera.width)


def particle_memory(cfg: Config) -> list[tuple[str, int, int]]:
    """(setting, particles, bytes) of each particle set a run holds: the filter's largest count (`max_particles` with
    the kld resampler, else `num_particles`), the challenger's, and the poses a door-plate reset draws to screen."""
    smcl = cfg.smcl
    per_particle = PARTICLE_BYTES + PARTICLE_BEAM_BYTES * scan_beams(cfg)
    kld = smcl.resampler.kind == "kld"
    peak = smcl.resampler.max_particles if kld else smcl.num_particles
    parts = [("smcl.resampler.max_particles" if kld else "smcl.num_particles", peak)]
    if smcl.challenger.enabled:
        parts.append(("smcl.challenger.particles", smcl.challenger.particles))
    reset = smcl.text_reset
    if cfg.perception.text.enabled and reset.enabled:
        # The text reset redraws round(share · M) from `oversample` times as many, in draws of four times what is
        # missing (ParticleSampler.draw_in_rounds).
        drawn = 4 * reset.oversample * round(reset.share * peak)
        parts.append(("smcl.text_reset.oversample", drawn))
    return [(key, count, count * per_particle) for key, count in parts]


def check_particle_memory(cfg: Config, available: int | None = None) -> None:
    """Raise ConfigError when the particle sets of `cfg` need more memory than is available (now, or `available`)."""
    parts = particle_memory(cfg)
    need = sum(nbytes for _, _, nbytes in parts)
    available = available_memory_bytes() if available is None else available
    if available is None or need <= available:
        return
    named = [(key, _value_of(cfg, key)) for key, _, nbytes in parts if nbytes >= SIGNIFICANT_SHARE * need]
    per_particle = parts[0][2] / max(parts[0][1], 1)
    raise ConfigError(
        f"{_settings(named)} {'needs' if len(named) == 1 else 'need'} about {format_bytes(need)} for the particle "
        f"filter ({format_bytes(per_particle)} a particle); this machine has {format_bytes(available)} available"
    )


def grid_memory(
    extent_xy_m: Sequence[float], n_storeys: int, cfg: Config, padding_included: bool = False
) -> tuple[int, int]:
    """(occupancy-grid bytes, visibility-lattice bytes) of a prior over `extent_xy_m` = (width, height) in metres
    with `n_storeys` storeys; `bim.grid.padding_m` is added on every side unless `padding_included`."""
    pad = 0.0 if padding_included else 2.0 * cfg.bim.grid.padding_m
    width, height = (max(float(v), 0.0) + pad for v in extent_xy_m)
    storeys = max(int(n_storeys), 1)

    def cells(cell_m: float) -> int:
        return math.ceil(width / cell_m) * math.ceil(height / cell_m)

    grid = cells(cfg.bim.grid.resolution_m) * storeys * GRID_CELL_BYTES
    lattice = cells(cfg.bim.visibility.cell_m) * storeys * LATTICE_CELL_BYTES
    return grid, lattice


def check_grid_memory(
    extent_xy_m: Sequence[float],
    n_storeys: int,
    cfg: Config,
    padding_included: bool = False,
    available: int | None = None,
) -> None:
    """Raise ConfigError when the grids of a prior over `extent_xy_m` = (width, height) in metres, `n_storeys`
    storeys, need more memory than is available (now, or `available`). Call it before the grids are allocated;
    `padding_included`: the extent is the padded grid's (GridSpec.extent), not the building's footprint."""
    grid, lattice = grid_memory(extent_xy_m, n_storeys, cfg, padding_included)
    need = grid + lattice
    available = available_memory_bytes() if available is None else available
    if available is None or need <= available:
        return
    named = [("bim.grid.resolution_m", cfg.bim.grid.resolution_m)]  # the one setting of the two grids' sizes
    pad = 0.0 if padding_included else 2.0 * cfg.bim.grid.padding_m
    width, height = (float(v) + pad for v in extent_xy_m)
    raise ConfigError(
        f"{_settings(named)} {'needs' if len(named) == 1 else 'need'} about {format_bytes(need)} for the grids of "
        f"{n_storeys} storey{'s' if n_storeys != 1 else ''} of {width:.0f} x {height:.0f} m; this machine has "
        f"{format_bytes(available)} available"
    )


def _value_of(cfg: Config, dotted: str) -> object:
    node: object = cfg
    for key in dotted.split("."):
        node = getattr(node, key)
    return node


def _settings(named: list[tuple[str, object]]) -> str:
    return " and ".join(f"{key}={value:g}" if isinstance(value, float) else f"{key}={value}" for key, value in named)
