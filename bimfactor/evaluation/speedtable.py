"""`bimfactor bench speed`: every speed figure the project is held to, in one table from one run on this machine.

Per building: the `full` variant's time per keyframe (split as `steps.csv` splits it), the real perception on the
same keyframes, and the fine registrars side by side (median time, ratio to Open3D point-to-plane within the run,
success over `compare-registrars`' sweep); then the filter step at M = 1000 and 20000 and wall clocks of commands in
fresh processes. docs/speed.md.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bimfactor.config import Config, updated
from bimfactor.errors import DependencyError

log = logging.getLogger(__name__)

DEFAULT_REGISTRAR = "point_to_plane"
REGISTRAR_KEYFRAMES = 6  # keyframes of trajectory 0 the registrars are timed on
PLATE_REACH_M = 4.0  # a reading is right when a plate of its text hangs this near the true pose (reading range + slack)
PRIOR_BENCH_FILE = "AC11-Institute-Var-2-IFC.ifc"  # the 5-storey building the prior targets are stated for
REAL_RECORDING = "tum-fr1-rpy"  # real Kinect frames of an office desk: the shipped detector's boxes lifted

# Targets (issue 42), in the table's units; None: reported, no target.
TARGETS: dict[str, float | None] = {
    "full per keyframe, median": 30.0,
    "full per keyframe, p90": 60.0,
    "real perception per keyframe, median": 60.0,
    "point_to_plane fit, median": 10.0,
    "filter step, M = 1000": 3.0,
    "filter step, M = 20000": 40.0,
    "localize, 50 keyframes": 5.0,
    "bimfactor --help": 1.0,
    "bimfactor demo": 20.0,
    "prior, cold": 10.0,
    "prior, geometry cached": 3.0,
}


@dataclass
class SpeedRow:
    """One figure: what, where, its value and unit, and the target it is held to (None: none)."""

    what: str
    building: str
    value: float
    unit: str
    target: float | None = None

    @property
    def met(self) -> bool | None:
        return None if self.target is None else bool(self.value <= self.target)


def keyframe_times(cfg: Config, building: str, prior, model, seed: int) -> tuple[list[SpeedRow], list, object]:
    """The full variant over trajectory 0 of a building: rows of per-keyframe time, and the simulated sequence."""
    from bimfactor.pipeline import localize_sequence
    from bimfactor.sim.simulate import simulate_sequence

    sim = simulate_sequence(prior, model, cfg, trajectory_index=0, seed=seed, progress=False)
    full = updated(cfg, {"localization.variant": "full"})
    run = localize_sequence(prior, sim.meta, sim.frames, full, seed, show_progress=False)
    assert run.graph is not None and run.fine is not None
    total = run.graph.step_ms + run.perception_ms
    parts = {
        "filter": run.filter.step_ms,
        "perception (sim)": run.perception_ms,
        "graphs + fine": run.graph.step_ms - run.filter.step_ms,
        "fine stage": run.fine.time_ms,
    }
    rows = [
        SpeedRow(
            "full per keyframe, median", building, float(np.median(total)), "ms", TARGETS["full per keyframe, median"]
        ),
        SpeedRow(
            "full per keyframe, p90", building, float(np.percentile(total, 90)), "ms", TARGETS["full per keyframe, p90"]
        ),
    ]
    rows += [SpeedRow(f"  of which {name}, median", building, float(np.median(v)), "ms") for name, v in parts.items()]
    return rows, sim.frames, sim.meta


def real_perception_rows(cfg: Config, building: str, prior, frames, meta, seed: int) -> list[SpeedRow]:
    """The product's own eyes on the keyframes of trajectory 0 as a converted recording brings them (no simulator
    instance table, no detections file): `perception.backend: auto` runs the shipped YOLOX-Nano, and RapidOCR reads
    door plates where they can be (`perception.ocr.PlateReader`). Rows: time per keyframe under the full variant
    (median, p90, and its parts), and the plates read right (a plate of that text hangs within reach of the true
    pose) beside RapidOCR on each whole frame. None without RapidOCR (the `ocr` extra)."""
    from bimfactor.localization.measurements.text import door_plates, normalise_text
    from bimfactor.perception.ocr import RapidOcrReader
    from bimfactor.perception.text import locate_readings
    from bimfactor.pipeline import DEPTH_PART, Localizer

    try:
        whole = RapidOcrReader(cfg.perception.text.min_score)
    except DependencyError as exc:
        log.warning("real perception not timed: %s", exc)
        return []
    recording = dataclasses.replace(meta, instances=[])
    frames = [dataclasses.replace(f, instance_ids=None) for f in frames]
    localizer = Localizer(prior, recording, updated(cfg, {"localization.variant": "full"}), seed)
    steps = [localizer.step(frame) for frame in frames]
    used = [s for s in steps if s is not None and s.skipped is None]
    total = np.array([s.perception_ms - s.perception_parts[DEPTH_PART] for s in used])
    names = [name for name in used[0].perception_parts if name != DEPTH_PART]
    parts = {name: np.array([s.perception_parts[name] for s in used]) for name in names}
    plates = door_plates(prior)

    def right(texts: list[str], frame) -> int:
        near = {
            normalise_text(p.text)
            for p in plates
            if p.storey_index == frame.gt_storey and np.hypot(*(np.asarray(p.xy) - frame.gt_pose[:2])) <= PLATE_REACH_M
        }
        return sum(normalise_text(t) in near for t in texts)

    graph = localizer.perception.graph
    gated = sum(
        right(s.observations.texts.texts if s.observations.texts else [], f) for s, f in zip(steps, frames, strict=True)
    )
    every = sum(  # the same criteria: a reading with no depth under it is dropped by both
        right(
            locate_readings(
                whole.read(f), f.depth_m, graph.intrinsics, graph.T_base_camera, graph.cfg.max_depth_m
            ).texts,
            f,
        )
        for f in frames
    )
    what = "real perception per keyframe"
    rows = [
        SpeedRow(f"{what}, median", building, float(np.median(total)), "ms", TARGETS[f"{what}, median"]),
        SpeedRow(f"{what}, p90", building, float(np.percentile(total, 90)), "ms"),
    ]
    rows += [SpeedRow(f"  of which {name}, median", building, float(np.median(v)), "ms") for name, v in parts.items()]
    rows += [
        SpeedRow("  plates read right, where they can be", building, gated, "plates"),
        SpeedRow("  plates read right, whole frames", building, every, "plates"),
    ]
    return rows


def real_frames_rows(cfg: Config) -> list[SpeedRow]:
    """The shipped detector and the box lifting on the real Kinect frames of tum-fr1-rpy (../shared/data/real), as
    `bimfactor scene-graph` runs them, where real objects are in view: milliseconds per frame, median, and its parts.
    None when the recording is not there."""
    from bimfactor.embed.text import make_text_embedder
    from bimfactor.evaluation.bench import SHARED_REAL_DIR
    from bimfactor.evaluation.mapping import open_recording
    from bimfactor.perception.mapping import map_recording
    from bimfactor.perception.pipeline import make_perception

    recording = SHARED_REAL_DIR / REAL_RECORDING
    if not (recording / "rgb.txt").is_file():
        log.warning("%s not found: the real frames not timed", recording)
        return []
    sequence, poses, _ = open_recording(recording, cfg)
    yolox = updated(cfg, {"perception.backend": "yolox"})
    perception = make_perception(yolox, sequence.meta, make_text_embedder(cfg.embed), read_text=False, mapping=True)
    _, timing = map_recording(list(sequence), poses, perception)
    parts = {name: np.array([t[name] for t in timing]) for name in timing[0]}
    total = sum(parts.values())
    rows = [SpeedRow("real frames: detector + lifting, median", REAL_RECORDING, float(np.median(total)), "ms")]
    rows += [
        SpeedRow(f"  of which {name}, median", REAL_RECORDING, float(np.median(v)), "ms") for name, v in parts.items()
    ]
    return rows


def registrar_rows(cfg: Config, building: str, prior, model, frames, meta, seed: int) -> tuple[list[SpeedRow], list]:
    """Every installed registrar on the same keyframes and starts (`compare_registrars`): median ms, ratio to the
    default's, success rate."""
    from bimfactor.evaluation.registrars import compare_registrars, initial_error_sweep, pick_keyframes, summarize
    from bimfactor.registration.fine import surface_models_for
    from bimfactor.registration.icp import available_registrars, make_registrar

    surfaces = surface_models_for(prior, cfg)
    rng = np.random.default_rng([seed, 0x5BEED])
    keys = pick_keyframes(
        [(frames, meta)], surfaces, cfg.registration, cfg.sensor, REGISTRAR_KEYFRAMES, REGISTRAR_KEYFRAMES, rng
    )
    if not keys:
        log.warning("%s: no registrable keyframe on trajectory 0; registrars not timed", building)
        return [], []
    registrars = {name: make_registrar(cfg.registration, name) for name in available_registrars()}
    records = compare_registrars(
        prior, model, cfg, keys, registrars, initial_error_sweep(cfg.registration), seed, surfaces
    )
    summary = summarize(records)
    base = next(s["median_time_ms"] for s in summary if s["registrar"] == DEFAULT_REGISTRAR)
    rows = []
    for s in summary:
        name = s["registrar"]
        what = f"{name} fit, median"
        rows.append(SpeedRow(what, building, s["median_time_ms"], "ms", TARGETS.get(what)))
        rows.append(SpeedRow(f"  {name} / point_to_plane time", building, s["median_time_ms"] / base, "×"))
        rows.append(SpeedRow(f"  {name} success", building, 100.0 * s["success_rate"], "%"))
    return rows, summary


def filter_rows(cfg: Config, prior) -> list[SpeedRow]:
    """The filter step at M = 1000 and 20000 with 12 observations (`benchmark_step`)."""
    from bimfactor.evaluation.speed import benchmark_step

    assert prior.visibility is not None
    steps = benchmark_step(prior, prior.visibility, cfg.smcl, cfg.sensor.max_range_m, n_particles_list=(1000, 20000))
    rows = []
    for row in steps:
        what = f"filter step, M = {row['n_particles']}"
        rows.append(SpeedRow(what, "paper floor", float(row["total_ms_median"]), "ms", TARGETS.get(what)))
    return rows


def wall_clock(args: list[str], cwd: Path, cache_home: Path | None = None) -> float:
    """Seconds one `bimfactor` command takes in a fresh process (it must succeed); `cache_home`: its XDG_CACHE_HOME
    (where the text encoder's cache lives)."""
    env = None if cache_home is None else {**os.environ, "XDG_CACHE_HOME": str(cache_home)}
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "bimfactor", *args], cwd=cwd, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"bimfactor {' '.join(args)} failed: {done.stderr.strip().splitlines()[-1:]}")
    return seconds


def wall_clock_rows(out_dir: Path, prior_dir: Path, sequence_dir: Path, shared_ifc: Path | None) -> list[SpeedRow]:
    """The commands a user meets, timed in fresh processes."""
    # The commands run in OUT: every path they get must not depend on this process's working directory.
    out_dir, prior_dir, sequence_dir = (Path(p).resolve() for p in (out_dir, prior_dir, sequence_dir))
    rows = [SpeedRow("bimfactor --help", "-", wall_clock(["--help"], out_dir), "s")]
    localize = ["localize", str(prior_dir), str(sequence_dir), "-o", str(_fresh(out_dir / "localize-run"))]
    rows.append(SpeedRow("localize, 50 keyframes", "paper floor", wall_clock(localize, out_dir), "s"))
    demo = wall_clock(["demo", "-o", str(_fresh(out_dir / "demo"))], out_dir)
    rows.append(SpeedRow("bimfactor demo", "paper floor", demo, "s"))
    if shared_ifc is not None and shared_ifc.is_file():
        # cold: no geometry and no text vectors cached, as a user's first prior of a building
        cache = _fresh(out_dir / "cache")
        sets = ["--set", f"bim.ifc.cache_dir={cache / 'geometry'}"]
        prior = ["prior", str(shared_ifc), *sets, "-o"]
        cold = wall_clock([*prior, str(_fresh(out_dir / "prior-cold"))], out_dir, cache)
        cached = wall_clock([*prior, str(_fresh(out_dir / "prior-cached"))], out_dir, cache)
        rows.append(SpeedRow("prior, cold", shared_ifc.name, cold, "s"))
        rows.append(SpeedRow("prior, geometry cached", shared_ifc.name, cached, "s"))
    for row in rows:
        row.target = TARGETS.get(row.what)
    return rows


def _fresh(path: Path) -> Path:
    """`path`, removed first when an earlier benchmark left it (only ever a folder under the benchmark's OUT)."""
    import shutil

    if path.exists():
        shutil.rmtree(path)
    return path


def format_speed_table(rows: list[SpeedRow]) -> str:
    """The rows as a Markdown table: what, building, value, target, met."""
    lines = ["| what | building | value | target | met |", "|---|---|---|---|---|"]
    for r in rows:
        value = (
            f"{r.value:.0f} {r.unit}"
            if r.unit == "plates"
            else f"{r.value:.2f} {r.unit}"
            if r.unit in ("×", "s")
            else f"{r.value:.1f} {r.unit}"
        )
        target = "" if r.target is None else f"≤ {r.target:g} {r.unit}"
        met = {None: "", True: "yes", False: "**no**"}[r.met]
        lines.append(f"| {r.what} | {r.building} | {value} | {target} | {met} |")
    return "\n".join(lines)
