"""The commands' workflows as library functions: what `bimfactor convert` does, callable from Python with typed
arguments; the CLI parses its options and prints what these return.

    from bimfactor.config import load_config
    from bimfactor.workflows import convert_recording

    done = convert_recording("rosbag", Path("run.mcap"), Path("runs/bag"), load_config())
    print(done.kept, *done.report, sep="\\n")
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from bimfactor.config import Config
from bimfactor.errors import InputError

if TYPE_CHECKING:
    from bimfactor.types import CameraIntrinsics

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
        kept = (
            f"{len(sequence)} keyframes of {recorded} frames (every {steps.keyframe_distance_m:g} m or "
            f"{steps.keyframe_angle_deg:g}° of odometry)"
        )
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
