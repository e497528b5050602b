"""The commands' workflows as library functions: what `bimfactor convert`, `localize` and `refine` do, callable
from Python with typed arguments; the CLI parses its options and prints what these return.

    from bimfactor.config import load_config
    from bimfactor.workflows import convert_recording, localize_files

    done = convert_recording("rosbag", Path("run.mcap"), Path("runs/bag"), load_config())
    run, figures = localize_files(Path("runs/prior"), done.output, Path("runs/loc"), load_config())
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from bimfactor.config import Config
from bimfactor.errors import ConfigError, InputError

if TYPE_CHECKING:
    from bimfactor.bim.prior import BimPrior
    from bimfactor.perception.detections import DetectionsTable
    from bimfactor.pipeline import LocalizationRun
    from bimfactor.refine import RefinedRun
    from bimfactor.types import CameraIntrinsics

Say = Callable[[str], None]
"""Where a workflow's lines go as it works (which perception it runs, warnings: they start with "warning:")."""

RecordingKind = Literal["tum", "rosbag", "sequence"]
OdometrySource = Literal["auto", "rgbd", "none"]


@dataclass(frozen=True)
class Conversion:
    """What `convert_recording` wrote: the sequence folder, which frames it kept, and what it found and assumed."""

    output: Path
    kept: str
    report: list[str] = field(default_factory=list)


def convert_recording(
    kind: RecordingKind,
    source: Path,
    output: Path,
    cfg: Config,
    *,
    overwrite: bool = False,
    all_frames: bool = False,
    camera_mount: np.ndarray | None = None,
    odometry: OdometrySource = "auto",
    intrinsics: CameraIntrinsics | None = None,
    detections: Path | None = None,
) -> Conversion:
    """Read a recording (a TUM RGB-D folder; a ROS 1 / ROS 2 / MCAP bag, its topics named in `cfg.io.rosbag` or
    found by type; or a bimfactor sequence, to keep its keyframes at another spacing) and write it as a bimfactor
    sequence with its preview and checks. `camera_mount`: (4, 4) T_base_camera instead of the bag's tf or a TUM
    folder's level camera; `odometry`: the recording's (auto: RGB-D odometry when it has none), always RGB-D, or
    none; `intrinsics`: a TUM folder's instead of the dataset's; `detections`: a detector's JSON Lines file, stored
    for the frames kept. A recording with odometry keeps its keyframes (`cfg.localization.keyframe_*`) unless
    `all_frames`. Bad input raises InputError before the recording is read; the folder is written atomically."""
    from bimfactor.evaluation.recording import recording_checks
    from bimfactor.io.atomic import check_output_dir, output_dir
    from bimfactor.io.preview import write_preview
    from bimfactor.io.rosbag import conversion_report, read_rosbag
    from bimfactor.io.sequence import read_sequence, write_sequence_files
    from bimfactor.io.tum_rgbd import read_tum_rgbd
    from bimfactor.odometry import keyframe_indices

    if kind == "sequence" and camera_mount is not None:
        raise InputError("a camera mount applies to rosbag and tum recordings, not to a sequence")
    if kind != "tum" and intrinsics is not None:
        raise InputError(f"intrinsics apply to tum folders, not to {kind} (a bag's come from CameraInfo)")
    if not source.exists():
        raise InputError(f"no such file or folder: {source}")
    check_output_dir(output, "sequence", inputs=[source], replace=overwrite)
    if detections is not None:
        from bimfactor.perception.detections import check_detections_file

        check_detections_file(detections)  # before the recording is read (and warned about)
    report: list[str] = []
    if kind == "tum":
        sequence = read_tum_rgbd(
            source, max_sync_dt_s=cfg.io.tum_max_sync_dt_s, intrinsics=intrinsics, T_base_camera=camera_mount
        )
    elif kind == "rosbag":
        sequence = read_rosbag(
            source,
            cfg.io.rosbag,
            T_base_camera=camera_mount,
            mount_source="--camera-mount",
            needs_odometry=odometry == "none",
        )
        report = conversion_report(sequence.meta.extras)
    else:
        sequence = read_sequence(source)
    found_detections = _recording_detections(sequence, source if kind == "sequence" else None, detections)
    if odometry == "rgbd" or (odometry == "auto" and sequence.odometry() is None):
        sequence, line = _with_rgbd_odometry(sequence)
        report.append(line)
    recorded, odometry_poses = len(sequence), sequence.odometry()
    if not all_frames and odometry_poses is not None:
        steps = cfg.localization
        sequence = sequence.subset(
            keyframe_indices(odometry_poses, steps.keyframe_distance_m, math.radians(steps.keyframe_angle_deg))
        )
        kept = _keyframes_note(len(sequence), recorded, cfg)
    else:
        kept = f"{recorded} frames" + ("" if odometry_poses is not None else " (no odometry: every frame kept)")
    with output_dir(output, "sequence", inputs=[source], replace=overwrite) as folder:
        write_sequence_files(folder, sequence.meta, sequence, label=str(output))
        if found_detections is not None:
            report.append(_store_detections(folder, sequence, *found_detections))
        written = read_sequence(folder)
        write_preview(written, folder / "preview.png")
        report.append(recording_checks(written, folder / "checks.png")[0])
    return Conversion(output, kept, report)


def _recording_detections(sequence: Any, source_sequence: Path | None, file: Path | None) -> tuple[Any, str] | None:
    """The detections a converted sequence keeps, checked against every recorded frame before anything is written:
    `--detections FILE`, else a bag's Detection2DArray topic, else a source sequence's detections.jsonl; with where
    they came from. None: no detections."""
    from bimfactor.perception.detections import DETECTIONS_FILE, read_detections

    if file is not None:  # checked before the recording was read; read_detections checks it again
        path, origin = file, str(file)
    elif getattr(sequence, "detections", None) is not None:
        topic = sequence.meta.extras["topics"]["detections"]
        return [line for line in sequence.detections if line["detections"]], f"the bag's {topic}"
    elif source_sequence is not None and (source_sequence / DETECTIONS_FILE).is_file():
        path, origin = source_sequence / DETECTIONS_FILE, str(source_sequence / DETECTIONS_FILE)
    else:
        return None
    table = read_detections(path, sequence.timestamps(), sequence.indices(), sequence.meta.intrinsics)
    return (path, table), origin


def _store_detections(folder: Path, sequence: Any, found: Any, origin: str) -> str:
    """Write the kept frames' detections into the sequence folder; the report's line."""
    from bimfactor.perception.detections import DETECTIONS_FILE, attach_detections

    if isinstance(found, list):  # a bag's lines, named by their frames' stamps
        kept = {float(t) for t in sequence.timestamps()}
        lines = [line for line in found if line["timestamp"] in kept]
        text = "".join(json.dumps(line) + "\n" for line in lines)
        (folder / DETECTIONS_FILE).write_text(text, encoding="utf-8")
        table = attach_detections(folder, folder / DETECTIONS_FILE)
    else:
        table = attach_detections(folder, found[0], unknown_frames="drop")
    return f"detections: {table.summary()} from {origin}"


def _with_rgbd_odometry(sequence: Any) -> tuple[Any, str]:
    """The sequence with odometry from its own colour and depth frames (`io.rgbd_odometry`), and the report's line."""
    from bimfactor.io.rgbd_odometry import FRAME_INTERVAL_S, MEASURED_ALPHA, odometry_frames, rgbd_odometry

    recorded = len(sequence)
    sequence = sequence.subset(odometry_frames(sequence.timestamps()))
    if len(sequence) < 2:
        raise InputError("RGB-D odometry needs two frames or more")
    result = rgbd_odometry(sequence)
    travelled = float(np.sum(np.hypot(*np.diff(result.odom_poses[:, :2], axis=0).T)))
    fell_back = int(result.fell_back.sum())
    extras = {
        "odometry": {
            "from": "rgbd (ORB + PnP, refined by point-to-plane ICP on the depth; docs/rgbd-odometry.md)",
            "pairs": len(result.pairs),
            "pairs_without_pnp": fell_back,
            "fitness_median": float(np.median(result.fitness)) if len(result.pairs) else None,
            "frames_used": len(sequence),
            "frames_recorded": recorded,
            "measured_alpha": list(MEASURED_ALPHA),
        }
    }
    alpha = ",".join(f"{a:g}" for a in MEASURED_ALPHA)
    used = "" if len(sequence) == recorded else f" (of {recorded}: one every {FRAME_INTERVAL_S:g} s)"
    line = (
        f"odometry: RGB-D odometry over {len(sequence)} frames{used}, {travelled:.1f} m travelled; {fell_back} of "
        f"{len(result.pairs)} pairs without a feature match (depth alone); its measured noise is "
        f"--set odometry.alpha=[{alpha}] (docs/rgbd-odometry.md)"
    )
    return sequence.with_odometry(result.odom_poses, extras), line


# ------------------------------------------------------------------------------------------ localize, refine


def localize_files(
    prior_dir: Path,
    sequence_dir: Path,
    output: Path,
    cfg: Config,
    *,
    seed: int | None = None,
    detections: Path | None = None,
    suggest: bool = False,
    force: bool = False,
    rerun: Path | None = None,
    say: Say = print,
) -> tuple[LocalizationRun, list[Path]]:
    """Localize a sequence folder against a prior folder and write the run folder (estimate, steps, metrics,
    figures; `bimfactor localize`); the run and its figures. `seed` None: the config's; `detections`: a detector's
    file for the detections backend; `suggest`: end with where to look next; `force`: a sequence of another building
    too; `rerun`: also write a Rerun recording there. Bad input raises before any heavy work."""
    from bimfactor.evaluation.report import write_run

    opened = _open_run(prior_dir, sequence_dir, output, cfg, detections, force, rerun, say)
    n = len(opened.sequence)
    snapshot_steps = sorted({0, n // 10, n // 4, n // 2, n - 1})
    run = _localize(opened, seed, rerun, say, snapshot_steps=snapshot_steps, suggest=suggest)
    title = f"{opened.sequence.meta.name} against {prior_dir}"
    return run, write_run(run, opened.prior, output, opened.cfg.dump_yaml(), title=title, inputs=opened.inputs)


def refine_files(
    prior_dir: Path,
    sequence_dir: Path,
    output: Path,
    cfg: Config,
    *,
    seed: int | None = None,
    detections: Path | None = None,
    force: bool = False,
    rerun: Path | None = None,
    say: Say = print,
) -> tuple[LocalizationRun, RefinedRun]:
    """Localize with pose graphs, then smooth each surviving mode's whole trajectory, and write the run folder
    (`bimfactor refine`); the forward pass and the refined run. The arguments are `localize_files`'."""
    from bimfactor.evaluation.report import write_refined
    from bimfactor.pipeline import GRAPH_VARIANTS, scan_matcher, skipped_frames_note
    from bimfactor.refine import refine_run

    if cfg.localization.variant not in GRAPH_VARIANTS:
        raise InputError(
            f"refine needs a pose-graph forward pass ({', '.join(GRAPH_VARIANTS)}), not {cfg.localization.variant}"
        )
    opened = _open_run(prior_dir, sequence_dir, output, cfg, detections, force, rerun, say)
    matcher = scan_matcher(opened.prior, opened.cfg)
    run = _localize(opened, seed, rerun, say, matcher=matcher)
    skipped = skipped_frames_note(run)
    if skipped is not None:
        say(f"warning: {skipped} (forward pass)")
    refined = refine_run(run, opened.prior, opened.cfg, matcher, show_progress=True)
    title = f"{opened.sequence.meta.name} refined against {prior_dir}"
    write_refined(refined, opened.prior, output, opened.cfg.dump_yaml(), title=title, inputs=[prior_dir, sequence_dir])
    return run, refined


@dataclass(frozen=True)
class _Opened:
    """A run's inputs, read and checked: the prior, the sequence, the config with its perception resolved, and the
    detections the detections backend reads."""

    prior: BimPrior
    sequence: Any
    cfg: Config
    detections: DetectionsTable | None
    inputs: list[Path]


def _open_run(
    prior_dir: Path,
    sequence_dir: Path,
    output: Path,
    cfg: Config,
    detections: Path | None,
    force: bool,
    rerun: Path | None,
    say: Say,
) -> _Opened:
    from bimfactor.bim.prior import BimPrior
    from bimfactor.evaluation.report import ensure_run_destination
    from bimfactor.evaluation.viewer import check_recording
    from bimfactor.io.sequence import read_sequence

    inputs = [prior_dir, sequence_dir, *([detections] if detections is not None else [])]
    ensure_run_destination(output, inputs)
    check_recording(rerun, output)
    _check_vlm(cfg, detections)
    prior = BimPrior.load(prior_dir)
    sequence = read_sequence(sequence_dir)
    _check_building(sequence.meta, prior, force, say)
    cfg, table, perception_line = _perception_source(cfg, sequence, sequence_dir, detections, prior)
    say(perception_line)
    return _Opened(prior, sequence, cfg, table, inputs)


def _localize(opened: _Opened, seed: int | None, rerun: Path | None, say: Say, **options: Any) -> LocalizationRun:
    """`localize_sequence` over the opened run with the seed (None: the config's), recorded into the Rerun recording
    `rerun` when one is asked for; says how many of the frames were keyframes when not all were."""
    from bimfactor.evaluation.viewer import maybe_record
    from bimfactor.pipeline import localize_sequence

    cfg, sequence = opened.cfg, opened.sequence
    with maybe_record(rerun, opened.prior, sequence.meta.name) as recorder:
        run = localize_sequence(
            opened.prior, sequence.meta, sequence, cfg, cfg.seed if seed is None else seed,
            detections=opened.detections, observer=recorder, **options,
        )  # fmt: skip
    if len(run.timestamps_s) < len(sequence):
        say(_keyframes_note(len(run.timestamps_s), len(sequence), cfg))
    return run


def _keyframes_note(kept: int, recorded: int, cfg: Config) -> str:
    steps = cfg.localization
    return (
        f"{kept} keyframes of {recorded} frames (every {steps.keyframe_distance_m:g} m or "
        f"{steps.keyframe_angle_deg:g}° of odometry)"
    )


def _check_building(meta: Any, prior: BimPrior, force: bool, say: Say) -> None:
    """Refuse a sequence recorded in another building than the prior's (a warning with --force)."""
    from bimfactor.pipeline import building_mismatch

    mismatch = building_mismatch(meta, prior)
    if mismatch is not None and not force:
        raise InputError(f"{mismatch}; --force localizes it all the same")
    if mismatch is not None:
        say(f"warning: {mismatch}")


def _check_vlm(cfg: Config, detections: Path | None) -> None:
    """With perception.backend=vlm its weight files, the CLIP text encoder and its libraries are checked before the
    prior and the sequence are read (`perception.vlm.check_vlm_ready`): a missing file fails in milliseconds."""
    if cfg.perception.backend == "vlm" and detections is None:
        from bimfactor.perception.vlm import check_vlm_ready

        check_vlm_ready(cfg)


def _perception_source(
    cfg: Config, sequence: Any, sequence_dir: Path, detections: Path | None, prior: BimPrior
) -> tuple[Config, Any, str]:
    """The perception a run uses (`perception.pipeline.choose_backend`; `--detections FILE` asks for the detections
    backend): the config with `perception.backend` resolved (what config.yaml records), the checked detections file
    when that backend reads one, and the line that says which perception it is. Bad input fails here, before any
    heavy work."""
    from bimfactor.config import updated
    from bimfactor.perception.detections import DETECTIONS_FILE, read_detections
    from bimfactor.perception.pipeline import choose_backend

    if detections is not None:
        from bimfactor.perception.detections import check_detections_file

        check_detections_file(detections)
        if cfg.perception.backend not in ("auto", "detections"):
            raise ConfigError(
                f"--detections reads a detector's detections, but perception.backend is {cfg.perception.backend}: "
                "leave it auto or set detections"
            )
        cfg = updated(cfg, {"perception.backend": "detections"})
    path = detections if detections is not None else sequence_dir / DETECTIONS_FILE
    backend = choose_backend(cfg.perception, sequence.meta, path.is_file())
    cfg = updated(cfg, {"perception.backend": backend})
    if backend == "sim":
        return cfg, None, f"perception: sim (the simulator's instance buffer, error preset {cfg.perception.sim_preset})"
    if backend == "vlm":
        return cfg, None, "perception: vlm (YOLO-World + SAM + CLIP on the colour frames)"
    if backend == "yolox":
        return cfg, None, "perception: yolox (the shipped YOLOX-Nano on the colour frames, COCO classes as labels)"
    table = read_detections(
        path,
        sequence.timestamps(),
        sequence.indices(),
        sequence.meta.intrinsics,
        embedding_dim=int(prior.object_embeddings.shape[1]),
        encoder=prior.embedding_model,
    )
    return cfg, table, f"perception: detections from {path}: {table.summary()}"
