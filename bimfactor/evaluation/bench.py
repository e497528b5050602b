"""Benchmarks that anyone can rerun from the command line (`bimfactor bench ...`).

`run_prior_bench` times the offline stage on real IFC files: a cold build (the geometry cache is an empty
temporary folder, so ifcopenshell really reads and meshes the file), the save, and the reload of the
saved prior (median of several). The text encoder is loaded once before any timing, because its load is
a per-process cost, not a per-building one; its load time is reported separately.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import statistics
import tempfile
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from bimfactor import __version__
from bimfactor.config import Config
from bimfactor.errors import InputError
from bimfactor.io.atomic import write_text_atomic
from bimfactor.progress import progress

log = logging.getLogger(__name__)

PROJECT_ROOT = Path(__file__).resolve().parents[2]
SHARED_IFC_DIR = PROJECT_ROOT.parent / "shared" / "data" / "ifc"
SHARED_REAL_DIR = PROJECT_ROOT.parent / "shared" / "data" / "real"
"""Real RGB-D recordings with camera poses (TUM folders) beside the project: the detector's and the scene graph's
real-frame checks."""
DEFAULT_PRIOR_BENCH_FILES = ("AC11-Institute-Var-2-IFC.ifc",)


def find_shared_ifc_dir() -> Path | None:
    """The real IFC buildings in `../shared/data/ifc` beside the project root, or None when absent."""
    return SHARED_IFC_DIR if SHARED_IFC_DIR.is_dir() else None


def shared_ifc_dir() -> Path:
    """Like `find_shared_ifc_dir`, but a missing folder is an InputError that says where it was expected."""
    found = find_shared_ifc_dir()
    if found is None:
        raise InputError(
            f"the real IFC buildings are not there: expected the folder {SHARED_IFC_DIR} "
            "(../shared/data/ifc beside the project); pass IFC files with --ifc instead"
        )
    return found


def default_prior_bench_files(all_buildings: bool = False) -> list[Path]:
    """The default benchmark file, or with `all_buildings` every IFC file in ../shared/data/ifc."""
    folder = shared_ifc_dir()
    if all_buildings:
        return sorted(folder.glob("*.ifc"))
    files = [folder / name for name in DEFAULT_PRIOR_BENCH_FILES]
    for path in files:
        if not path.is_file():
            raise InputError(f"benchmark IFC file missing: {path}")
    return files


@dataclass
class PriorBenchRow:
    """One IFC file's timings and counts; times in seconds."""

    file: str
    path: str
    sha256: str
    schema: str
    storeys: int
    rooms: int
    doors: int
    objects: int
    cold_build_s: float
    save_s: float
    reload_s: float
    reload_runs_s: list[float]
    stage_timings_s: dict[str, float]
    prior_dir: str
    ifcspace_match_share: float
    room_type_accuracy: float  # typed as the prior is: by the IfcSpace name where it decides, else by objects
    room_types_evaluated: int
    room_type_accuracy_objects: float  # typed by objects and topology alone (the paper)
    room_types_evaluated_objects: int


@dataclass
class PriorBenchResult:
    rows: list[PriorBenchRow]
    embedder_load_s: float
    host: dict[str, object] = field(default_factory=dict)


def _with_cache_dir(cfg: Config, cache_dir: str) -> Config:
    ifc = cfg.bim.ifc.model_copy(update={"cache_dir": cache_dir})
    return cfg.model_copy(update={"bim": cfg.bim.model_copy(update={"ifc": ifc})})


def _host() -> dict[str, object]:
    from importlib import metadata

    return {
        "bimfactor": __version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "ifcopenshell": metadata.version("ifcopenshell"),
    }


def run_prior_bench(
    ifc_paths: list[Path], cfg: Config, out_dir: str | Path, reload_repeats: int = 5
) -> PriorBenchResult:
    """Build, save and reload a prior per IFC file; writes OUT/results.json, OUT/config.yaml, OUT/priors/<name>/.

    The saved priors carry `cfg` as their config; only the geometry cache folder differs in the builds.
    """
    from bimfactor.bim.prior import BimPrior, build_prior
    from bimfactor.embed.text import make_text_embedder
    from bimfactor.evaluation.plots import save_floorplans
    from bimfactor.evaluation.rooms import ifcspace_matched_share, object_only_types, room_type_accuracy

    out_dir = Path(out_dir)
    paths = [Path(p) for p in ifc_paths]
    for path in paths:
        if not path.is_file():
            raise InputError(f"IFC file not found: {path}")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "config.yaml", cfg.dump_yaml())

    started = time.perf_counter()
    embedder = make_text_embedder(cfg.embed)
    embedder.encode(["warm-up"])
    embedder_load_s = time.perf_counter() - started

    rows = []
    for path in progress(paths, desc="bench prior", unit="file"):
        with tempfile.TemporaryDirectory(prefix="bimfactor-bench-cache-") as empty_cache:
            started = time.perf_counter()
            prior = build_prior(path, _with_cache_dir(cfg, empty_cache), embedder=embedder)
            cold_build_s = time.perf_counter() - started
        prior_dir = out_dir / "priors" / path.stem
        started = time.perf_counter()
        prior.save(prior_dir, config_yaml=cfg.dump_yaml(), extra_files=save_floorplans)
        save_s = time.perf_counter() - started
        reload_runs = []
        for _ in range(reload_repeats):
            started = time.perf_counter()
            BimPrior.load(prior_dir)
            reload_runs.append(time.perf_counter() - started)
        ignore = tuple(cfg.bim.classify.ignore_labels)
        room_types = room_type_accuracy(prior, ignore_labels=ignore)
        object_types = room_type_accuracy(prior, ignore_labels=ignore, types=object_only_types(prior, cfg, embedder))
        rows.append(
            PriorBenchRow(
                file=path.name,
                path=str(path),
                sha256=prior.source_sha256,
                schema=prior.schema,
                storeys=len(prior.storeys),
                rooms=len(prior.rooms),
                doors=sum(d.kind == "door" for d in prior.doors),
                objects=len(prior.objects),
                cold_build_s=cold_build_s,
                save_s=save_s,
                reload_s=statistics.median(reload_runs),
                reload_runs_s=reload_runs,
                stage_timings_s=dict(prior.timings_s),
                prior_dir=str(prior_dir),
                ifcspace_match_share=ifcspace_matched_share(prior),
                room_type_accuracy=room_types.accuracy,
                room_types_evaluated=room_types.evaluated,
                room_type_accuracy_objects=object_types.accuracy,
                room_types_evaluated_objects=object_types.evaluated,
            )
        )
        log.info("%s: cold build %.2f s, reload %.3f s", path.name, cold_build_s, rows[-1].reload_s)

    result = PriorBenchResult(rows=rows, embedder_load_s=embedder_load_s, host=_host())
    report = {
        "benchmark": "prior",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "reload_repeats": reload_repeats,
        "embedder": getattr(embedder, "name", type(embedder).__name__),
        "embedder_load_s": embedder_load_s,
        "host": result.host,
        "rows": [asdict(row) for row in rows],
    }
    write_text_atomic(out_dir / "results.json", json.dumps(report, indent=2))
    return result


def format_prior_table(rows: list[PriorBenchRow]) -> str:
    """A fixed-width text table: file, storeys, rooms, objects, cold build s, reload s (median)."""
    header = (
        "file",
        "storeys",
        "rooms",
        "doors",
        "objects",
        "IfcSpace matched",
        "room types",
        "objects only",
        "cold build s",
        "reload s",
    )
    body = [
        (
            r.file,
            str(r.storeys),
            str(r.rooms),
            str(r.doors),
            str(r.objects),
            "-" if r.ifcspace_match_share != r.ifcspace_match_share else f"{100 * r.ifcspace_match_share:.0f}%",
            "-" if not r.room_types_evaluated else f"{100 * r.room_type_accuracy:.0f}% of {r.room_types_evaluated}",
            "-"
            if not r.room_types_evaluated_objects
            else f"{100 * r.room_type_accuracy_objects:.0f}% of {r.room_types_evaluated_objects}",
            f"{r.cold_build_s:.2f}",
            f"{r.reload_s:.3f}",
        )
        for r in rows
    ]
    widths = [max(len(line[i]) for line in (header, *body)) for i in range(len(header))]

    def fmt(line: tuple[str, ...]) -> str:
        cells = [line[0].ljust(widths[0])] + [cell.rjust(w) for cell, w in zip(line[1:], widths[1:], strict=True)]
        return "  ".join(cells)

    return "\n".join([fmt(header), "  ".join("-" * w for w in widths), *(fmt(line) for line in body)])


def run_sim_bench(ifc_paths: list[Path], cfg: Config, out_dir: str | Path, n_frames: int = 200) -> list[dict]:
    """Render speed of the simulator (RGB, depth, instance ids, noise) per building; writes OUT/results.json."""
    from bimfactor.bim.ifc import load_ifc
    from bimfactor.bim.prior import build_prior
    from bimfactor.evaluation.speed import benchmark_render

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "config.yaml", cfg.dump_yaml())
    rows = []
    for path in progress(ifc_paths, desc="bench sim", unit="building"):
        prior = build_prior(path, cfg)
        row = benchmark_render(prior, load_ifc(path, cfg.bim.ifc), cfg, n_frames=n_frames)
        row["building"] = Path(path).name
        rows.append(row)
    report = {
        "benchmark": "sim",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "host": _host(),
        "rows": rows,
    }
    write_text_atomic(out_dir / "results.json", json.dumps(report, indent=2))
    return rows
