"""`bimfactor scene-graph`: the online open-set scene graph of any RGB-D recording with camera poses.

A recording is a TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt: its motion-capture camera poses, 6-DoF) or a
bimfactor sequence folder (the robot's ground-truth, else odometry, pose composed with its camera mount). Perception
is what `perception.backend` picks for it (`auto`: the simulator's for a simulated sequence, a detections file where
the folder has one, else the shipped YOLOX-Nano with COCO's class names). Writes OUT/scene_graph.json
(`perception.mapping.graph_record`), OUT/scene_graph.png (the nodes over the fused point cloud, from above) and
OUT/config.yaml.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from bimfactor.config import Config, updated
from bimfactor.errors import InputError
from bimfactor.io.atomic import output_dir
from bimfactor.types import CameraIntrinsics

GRAPH_FILE = "scene_graph.json"
FIGURE_FILE = "scene_graph.png"


@dataclass
class MappedRecording:
    """What `scene_graph_run` made: the record written to scene_graph.json and the figure's path."""

    record: dict
    figure: Path


def open_recording(path: Path, cfg: Config, intrinsics: CameraIntrinsics | None = None) -> tuple:
    """(sequence, (N, 4, 4) camera poses, where the poses came from) of a TUM folder or a bimfactor sequence folder;
    InputError for anything else."""
    from bimfactor.io.sequence import read_sequence
    from bimfactor.io.tum_rgbd import read_tum_rgbd, tum_camera_poses
    from bimfactor.perception.mapping import sequence_camera_poses

    if not path.is_dir():
        raise InputError(f"no such recording folder: {path}")
    if (path / "sequence.json").is_file():
        if intrinsics is not None:
            raise InputError("--intrinsics applies to TUM folders; a sequence folder's are in its sequence.json")
        sequence = read_sequence(path)
        poses, source = sequence_camera_poses(list(sequence), sequence.meta.T_base_camera)
        return sequence, poses, source
    if (path / "rgb.txt").is_file():
        # 6-DoF poses are what the graph takes: the planar projection's tilt warning is not this command's concern
        sequence = read_tum_rgbd(
            path, max_sync_dt_s=cfg.io.tum_max_sync_dt_s, intrinsics=intrinsics, max_tilt_deg=180.0
        )
        poses = tum_camera_poses(path, sequence.timestamps(), cfg.io.tum_max_sync_dt_s)
        return sequence, poses, "groundtruth.txt (6-DoF)"
    raise InputError(f"{path}: neither a TUM RGB-D folder (rgb.txt) nor a bimfactor sequence (sequence.json)")


def scene_graph_run(
    recording: Path,
    out_dir: Path,
    cfg: Config,
    intrinsics: CameraIntrinsics | None = None,
    show_progress: bool = False,
) -> MappedRecording:
    """Build a recording's scene graph and write it (module docstring); the output folder appears whole or not."""
    from bimfactor.embed.text import make_text_embedder
    from bimfactor.evaluation.plots import save_scene_graph_figure
    from bimfactor.io.atomic import check_output_dir
    from bimfactor.perception.detections import DETECTIONS_FILE, read_detections
    from bimfactor.perception.mapping import fused_cloud, graph_record, map_recording, up_direction
    from bimfactor.perception.pipeline import choose_backend, make_perception

    check_output_dir(out_dir, "scene-graph", inputs=[recording])
    sequence, poses, source = open_recording(recording, cfg, intrinsics)
    meta = sequence.meta
    detections_file = recording / DETECTIONS_FILE
    backend = choose_backend(cfg.perception, meta, detections_file.is_file())
    cfg = updated(cfg, {"perception.backend": backend})
    embedder = make_text_embedder(cfg.embed)
    table = None
    if backend == "detections":
        table = read_detections(detections_file, sequence.timestamps(), sequence.indices(), meta.intrinsics)
    perception = make_perception(cfg, meta, embedder, detections=table, read_text=False, mapping=True)
    frames = list(sequence)
    graph, timing = map_recording(frames, poses, perception, show_progress)
    used = len(timing)
    detector = {"yolox": "YOLOX-Nano, COCO classes", "detections": f"{DETECTIONS_FILE}"}.get(backend, backend)
    record = graph_record(graph, recording, source, used, detector)
    cloud = fused_cloud(frames, poses, meta.intrinsics, cfg.perception.max_depth_m)
    with output_dir(out_dir, "scene-graph", inputs=[recording]) as tmp:
        import json

        (tmp / GRAPH_FILE).write_text(json.dumps(record, indent=1) + "\n")
        (tmp / "config.yaml").write_text(cfg.dump_yaml())
        save_scene_graph_figure(record, cloud, up_direction(poses),
                                tmp / FIGURE_FILE, title=recording.name)  # fmt: skip
    return MappedRecording(record, out_dir / FIGURE_FILE)
