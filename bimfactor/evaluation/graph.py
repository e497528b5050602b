"""Evaluation of the online scene graph against the BIM objects, the sim detector's rates, and the update speed.

A node is brought into the world frame with T_world_odom at the frame it was last fused in (`alignment="per_node"`,
keeping odometry drift out of a perception metric) or at the first frame (`"first_frame"`). A node matches an object
when its centroid lies within `match_distance_m` of the object's box and its label is the object's or a synonym
(`SYNONYMS`), one-to-one (Hungarian). Precision is matched / nodes, recall matched / objects seen; over- and
under-segmentation count objects split over nodes and nodes spread over objects. Run with `bimfactor bench graph`.
"""

from __future__ import annotations

import json
import logging
import statistics
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from bimfactor.config import Config
from bimfactor.embed.text import TextEmbedder, make_text_embedder
from bimfactor.io.atomic import write_text_atomic
from bimfactor.perception.pipeline import Perception, household_vocabulary, make_perception
from bimfactor.perception.scene_graph import OnlineSceneGraph, SceneNode
from bimfactor.perception.sim import label_cosine_statistics
from bimfactor.progress import progress
from bimfactor.types import Frame, SequenceMeta, se2_to_matrix

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from bimfactor.bim.prior import BimPrior
    from bimfactor.sim.simulate import SimResult

log = logging.getLogger(__name__)

# Labels that name the same thing for evaluation: an open-vocabulary label in a group matches any other in it.
SYNONYMS: tuple[frozenset[str], ...] = (
    frozenset({"table", "desk", "dining table", "coffee table", "lab bench"}),
    frozenset({"chair", "armchair"}),
    frozenset({"sofa", "armchair"}),
    frozenset({"cabinet", "wardrobe", "kitchen counter"}),
    frozenset({"bathtub", "shower"}),
    frozenset({"fire hydrant", "fire extinguisher"}),
)
RECALL_MIN_PIXELS = 50  # detector recall counts objects covering at least this many pixels ...
RECALL_MAX_DEPTH_M = 6.0  # ... within this median depth
UNDER_SEGMENT_SHARE = 0.2
SUMMARY_KEYS = ("precision", "recall", "label_accuracy")
COUNT_KEYS = ("n_nodes", "n_objects", "n_matched", "over_segmented_objects", "extra_nodes", "under_segmented_nodes")
STRUCTURE_LABELS_EXCLUDED = ("door",)  # open in the simulated world: never seen


def labels_match(a: str, b: str) -> bool:
    """True when two labels are equal or synonyms."""
    return a == b or any(a in group and b in group for group in SYNONYMS)


# ------------------------------------------------------------------------------------------ ground truth


def observed_objects(
    frames: Sequence[Frame], meta: SequenceMeta, min_pixels: int = RECALL_MIN_PIXELS, max_depth_m: float = 6.0
) -> set[int]:
    """BIM object ids whose instance covers ≥ `min_pixels` pixels with a return within `max_depth_m` in some frame."""
    object_of = np.full(max((int(r["id"]) for r in meta.instances), default=-1) + 2, -1, np.int64)
    for rec in meta.instances:
        object_of[int(rec["id"])] = int(rec["object_id"])
    seen: set[int] = set()
    for frame in frames:
        if frame.instance_ids is None:
            continue
        with np.errstate(invalid="ignore"):
            near = frame.depth_m <= max_depth_m
        ids = frame.instance_ids[near & (frame.instance_ids >= 0)]
        counts = np.bincount(ids, minlength=len(object_of))
        seen.update(int(object_of[i]) for i in np.flatnonzero(counts >= min_pixels) if object_of[i] >= 0)
    return seen


def T_world_odom(gt_pose: np.ndarray, odom_pose: np.ndarray, elevation_m: float) -> np.ndarray:
    """(4, 4) odometry → world transform at one frame from its (3,) ground-truth and odometry poses."""
    return se2_to_matrix(gt_pose, elevation_m) @ np.linalg.inv(se2_to_matrix(odom_pose))


def node_points_world(
    node: SceneNode, gt_poses: np.ndarray, odom_poses: np.ndarray, elevation_m: float, alignment: str
) -> np.ndarray:
    """(M, 3) world-frame voxel centres of a node (see the module docstring for `alignment`)."""
    t = node.last_frame if alignment == "per_node" else 0
    T = T_world_odom(gt_poses[t], odom_poses[t], elevation_m)
    points = node.points_m
    return points @ T[:3, :3].T + T[:3, 3]


def _box_distance(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N, M) Euclidean distance of (N, 3) points to (M, 3)-(M, 3) boxes (0 inside)."""
    gap = np.maximum(lo[None] - points[:, None], 0.0) + np.maximum(points[:, None] - hi[None], 0.0)
    return np.linalg.norm(gap, axis=2)


# ------------------------------------------------------------------------------------------ graph metrics


@dataclass
class GraphEvalParams:
    """Matching tolerances of `evaluate_graph`."""

    match_distance_m: float = 0.5
    box_margin_m: float = 0.15
    alignment: str = "per_node"
    min_observations: int = 1  # nodes fused from fewer detections are left out


def evaluate_graph(
    graph: OnlineSceneGraph,
    prior: BimPrior,
    storey_index: int,
    gt_poses: np.ndarray,
    odom_poses: np.ndarray,
    object_ids: Sequence[int],
    params: GraphEvalParams | None = None,
) -> dict[str, Any]:
    """Instance precision / recall, over- / under-segmentation and label accuracy of a graph against the BIM
    objects `object_ids` (the ones the camera saw); (T, 3) poses index by frame. JSON-ready dict."""
    params = params or GraphEvalParams()
    elevation = prior.storeys[storey_index].storey.elevation_m
    objects = [prior.objects[i] for i in object_ids]
    nodes = [n for n in graph.nodes.values() if n.n_observations >= params.min_observations]
    lo = np.asarray([np.subtract(o.position_m, np.divide(o.size_m, 2)) for o in objects]).reshape(-1, 3)
    hi = np.asarray([np.add(o.position_m, np.divide(o.size_m, 2)) for o in objects]).reshape(-1, 3)
    points = [node_points_world(n, gt_poses, odom_poses, elevation, params.alignment) for n in nodes]
    centroids = np.asarray([p.mean(axis=0) for p in points]).reshape(-1, 3)
    dist = _box_distance(centroids, lo, hi)
    compatible = np.array([[labels_match(n.label, o.label) for o in objects] for n in nodes], bool).reshape(dist.shape)
    ok = compatible & (dist <= params.match_distance_m)
    matches: list[tuple[int, int]] = []
    if ok.any():
        rows, cols = linear_sum_assignment(np.where(ok, dist, 1e6))
        matches = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if ok[r, c]]
    # Segmentation: each node voxel belongs to the nearest object box within the margin (or to none).
    share = np.zeros((len(nodes), len(objects)))
    for i, p in enumerate(points):
        if len(objects):
            d = _box_distance(p, lo, hi)
            nearest = d.argmin(axis=1)
            near = d[np.arange(len(p)), nearest] <= params.box_margin_m
            share[i] = np.bincount(nearest[near], minlength=len(objects)) / len(p)
    owner = np.where(share.max(axis=1, initial=0.0) > 0.5, share.argmax(axis=1) if len(objects) else -1, -1)
    nodes_per_object = np.bincount(owner[owner >= 0], minlength=len(objects))
    under = int(np.sum((share >= UNDER_SEGMENT_SHARE).sum(axis=1) >= 2))
    n_nodes, n_objects, n_matched = len(nodes), len(objects), len(matches)
    exact = sum(nodes[r].label == objects[c].label for r, c in matches)
    return {
        "n_nodes": n_nodes,
        "n_objects": n_objects,
        "n_matched": n_matched,
        "precision": n_matched / n_nodes if n_nodes else float("nan"),
        "recall": n_matched / n_objects if n_objects else float("nan"),
        "over_segmented_objects": int(np.sum(nodes_per_object >= 2)),
        "extra_nodes": int(np.sum(np.maximum(nodes_per_object - 1, 0))),
        "under_segmented_nodes": under,
        "label_accuracy": exact / n_matched if n_matched else float("nan"),
        "matches": [
            {
                "node": nodes[r].id,
                "object": objects[c].id,
                "node_label": nodes[r].label,
                "label": objects[c].label,
                "distance_m": round(float(dist[r, c]), 3),
            }
            for r, c in matches
        ],
        "missed_objects": sorted(set(object_ids) - {objects[c].id for _, c in matches}),
        "unmatched_nodes": sorted(set(range(n_nodes)) - {r for r, _ in matches}),
        "node_centroids_world": centroids.round(3).tolist(),
        "node_ids": [n.id for n in nodes],
        "node_labels": [n.label for n in nodes],
    }


def plot_scene_graph(
    ax: Axes,
    graph: OnlineSceneGraph,
    report: dict[str, Any],
    prior: BimPrior,
    storey_index: int,
    trajectory_xy: np.ndarray | None = None,
    margin_m: float = 3.0,
) -> None:
    """The final graph over the floor plan: matched nodes green, unmatched red, edges grey, missed objects ✕,
    the (N, 2) ground-truth trajectory; framed on what the robot saw, `margin_m` around it."""
    from bimfactor.evaluation.plots import draw_floorplan

    draw_floorplan(ax, prior, storey_index, label_objects=False)
    if trajectory_xy is not None and len(trajectory_xy):
        ax.plot(*np.asarray(trajectory_xy)[:, :2].T, color="tab:blue", lw=1.2, zorder=4, label="trajectory")
    centroids = np.asarray(report["node_centroids_world"]).reshape(-1, 3)
    index_of = {node_id: i for i, node_id in enumerate(report["node_ids"])}
    for a, b in graph.edges():
        if a in index_of and b in index_of:
            ax.plot(*centroids[[index_of[a], index_of[b]], :2].T, color="0.45", lw=0.8, zorder=4)
    matched = {m["node"] for m in report["matches"]}
    colours = ["tab:green" if nid in matched else "tab:red" for nid in report["node_ids"]]
    if len(centroids):
        ax.scatter(centroids[:, 0], centroids[:, 1], s=22, c=colours, edgecolors="k", linewidths=0.4, zorder=5)
    for i, label in enumerate(report["node_labels"]):
        ax.annotate(label, centroids[i, :2], fontsize=5, xytext=(3, 3), textcoords="offset points", zorder=6)
    missed = [prior.objects[i].position_m[:2] for i in report["missed_objects"]]
    if missed:
        ax.scatter(*np.asarray(missed).T, marker="x", s=26, c="tab:orange", zorder=5, label="missed object")
    ax.scatter([], [], c="tab:green", s=22, label="node: matched")
    ax.scatter([], [], c="tab:red", s=22, label="node: no object")
    ax.legend(loc="upper right", fontsize=6)
    seen = [centroids[:, :2], np.asarray(missed).reshape(-1, 2)]
    if trajectory_xy is not None:
        seen.append(np.asarray(trajectory_xy)[:, :2])
    xy = np.concatenate(seen)
    if len(xy):
        lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])


def save_scene_graph_figure(
    path: str | Path,
    graph: OnlineSceneGraph,
    report: dict[str, Any],
    prior: BimPrior,
    storey_index: int,
    title: str,
    trajectory_xy: np.ndarray | None = None,
) -> Path:
    """Write `plot_scene_graph` as a PNG, atomically."""
    import matplotlib.pyplot as plt

    from bimfactor.evaluation.plots import save_figure

    fig, ax = plt.subplots(figsize=(9, 9))
    plot_scene_graph(ax, graph, report, prior, storey_index, trajectory_xy)
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path, dpi=130)


# ------------------------------------------------------------------------------------------ runners


def run_perception(
    sim: SimResult, cfg: Config, text_embedder: TextEmbedder, seed: int | None = None, sim_preset: str | None = None
) -> Perception:
    """Run the whole perception pipeline over a simulated sequence; returns it with its final graph."""
    perception = make_perception(cfg, sim.meta, text_embedder, seed, sim_preset)
    perception.run(sim.frames)
    return perception


def evaluate_sequence(
    sim: SimResult,
    prior: BimPrior,
    cfg: Config,
    text_embedder: TextEmbedder,
    seed: int | None = None,
    sim_preset: str | None = None,
    figure_path: str | Path | None = None,
    params: GraphEvalParams | None = None,
) -> dict[str, Any]:
    """Perception over one simulated sequence, its graph scored against the BIM; optional PNG of the graph."""
    perception = run_perception(sim, cfg, text_embedder, seed, sim_preset)
    storey = int(sim.meta.extras.get("storey_index", sim.frames[0].gt_storey or 0))
    gt = np.stack([f.gt_pose for f in sim.frames])
    odom = np.stack([f.odom_pose for f in sim.frames])
    seen = observed_objects(sim.frames, sim.meta, max_depth_m=cfg.perception.max_depth_m)
    seen = {i for i in seen if prior.objects[i].label not in STRUCTURE_LABELS_EXCLUDED}
    params = params or GraphEvalParams()
    report = evaluate_graph(perception.graph, prior, storey, gt, odom, sorted(seen), params)
    confirmed = evaluate_graph(
        perception.graph, prior, storey, gt, odom, sorted(seen), replace(params, min_observations=2)
    )
    report["confirmed"] = {k: confirmed[k] for k in (*SUMMARY_KEYS, *COUNT_KEYS)}
    report.update(
        sequence=sim.meta.name,
        frames=len(sim.frames),
        preset=sim_preset or cfg.perception.sim_preset,
        edges=len(perception.graph.edges()),
    )
    if figure_path is not None:
        title = (
            f"{sim.meta.name}: {report['n_nodes']} nodes, precision {report['precision']:.2f}, "
            f"recall {report['recall']:.2f} ({perception.backend}/{report['preset']})"
        )
        figure = save_scene_graph_figure(figure_path, perception.graph, report, prior, storey, title, gt[:, :2])
        report["figure"] = str(figure)
    return report


def summarise(reports: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Means of the rates and sums of the counts over sequences, plus pooled precision / recall."""
    out: dict[str, Any] = {}
    for key in SUMMARY_KEYS:
        values = [r[key] for r in reports if not np.isnan(r[key])]
        out[f"{key}_mean"] = float(np.mean(values)) if values else float("nan")
    for key in COUNT_KEYS:
        out[key] = int(sum(r[key] for r in reports))
    out["precision_pooled"] = out["n_matched"] / out["n_nodes"] if out["n_nodes"] else float("nan")
    out["recall_pooled"] = out["n_matched"] / out["n_objects"] if out["n_objects"] else float("nan")
    if all("confirmed" in r for r in reports) and reports:
        out["confirmed"] = summarise([r["confirmed"] for r in reports])
    return out


def evaluate_building(
    prior: BimPrior,
    sims: Sequence[SimResult],
    cfg: Config,
    text_embedder: TextEmbedder,
    sim_preset: str | None = None,
    out_dir: str | Path | None = None,
) -> dict[str, Any]:
    """`evaluate_sequence` over several sequences of one building; writes report.json and PNGs when `out_dir`."""
    reports = []
    for sim in progress(sims, desc="perception eval", unit="seq"):
        figure = Path(out_dir) / f"{sim.meta.name}.png" if out_dir is not None else None
        reports.append(evaluate_sequence(sim, prior, cfg, text_embedder, sim_preset=sim_preset, figure_path=figure))
    result = {
        "building": Path(prior.source_file).name,
        "preset": sim_preset or cfg.perception.sim_preset,
        "summary": summarise(reports),
        "detector": sim_detector_statistics(sims, cfg, text_embedder, sim_preset),
        "sequences": reports,
    }
    if out_dir is not None:
        write_text_atomic(Path(out_dir) / "report.json", json.dumps(result, indent=1, default=float))
        write_text_atomic(Path(out_dir) / "config.yaml", cfg.dump_yaml())
    return result


# ------------------------------------------------------------------------------------------ sim detector rates


def similarity_statistics(
    embeddings: np.ndarray, true_labels: Sequence[str], label_texts: Sequence[str], text_embedder: TextEmbedder
) -> dict[str, float]:
    """Matched vs unmatched cosines of (N, D) visual embeddings against the text embeddings of `label_texts`:
    matched = its true label, unmatched = every other label; mean, std and d' = Δμ / pooled σ."""
    labels = list(dict.fromkeys(label_texts))
    texts = text_embedder.encode(labels)
    sims = np.asarray(embeddings, np.float32) @ texts.T
    truth = np.array([[label == t for label in labels] for t in true_labels], bool).reshape(sims.shape)
    keep = truth.any(axis=1)
    matched, unmatched = sims[keep][truth[keep]], sims[keep][~truth[keep]]
    if len(matched) == 0:
        return {"n": 0}
    pooled = float(np.sqrt((matched.var() + unmatched.var()) / 2))
    return {
        "n": len(matched),
        "matched_mean": float(matched.mean()),
        "matched_std": float(matched.std()),
        "unmatched_mean": float(unmatched.mean()),
        "unmatched_std": float(unmatched.std()),
        "dprime": float((matched.mean() - unmatched.mean()) / pooled) if pooled > 0 else float("inf"),
        "labels": len(labels),
    }


def sim_detector_statistics(
    sims: Sequence[SimResult],
    cfg: Config,
    text_embedder: TextEmbedder,
    sim_preset: str | None = None,
    seed: int | None = None,
) -> dict[str, Any]:
    """The sim front end's measured rates over sequences: recall of objects in view within 6 m (≥ 50 pixels),
    label confusion, false positives per frame, and crop-to-text / crop-to-crop cosine statistics of the detections
    the detector labelled right (what the preset's d' and cosines describe; a confused crop looks like the class it
    was taken for, and `confused_crop_to_true_text` gives its cosine to its true label's text)."""
    vocabulary = household_vocabulary(cfg)
    in_view = detected = confused = true_positives = false_positives = frames = 0
    embeddings, labels, instance_keys, confused_cosines = [], [], [], []
    texts: dict[str, np.ndarray] = {}

    def text_vectors(label: str) -> np.ndarray:
        if label not in texts:
            texts[label] = text_embedder.encode([label])[0]
        return texts[label]

    for sim in sims:
        perception = make_perception(cfg, sim.meta, text_embedder, seed, sim_preset)
        object_ids = np.asarray([int(r["object_id"]) for r in sim.meta.instances])
        true_label = [str(r["label"]) for r in sim.meta.instances]
        for frame in sim.frames:
            detections, _, emb = perception.perceive(frame)
            frames += 1
            ids = frame.instance_ids
            with np.errstate(invalid="ignore"):
                near = ids[(ids >= 0) & (frame.depth_m <= RECALL_MAX_DEPTH_M)]
            counts = np.bincount(near, minlength=len(object_ids))
            targets = {int(i) for i in np.flatnonzero(counts >= RECALL_MIN_PIXELS) if object_ids[i] >= 0}
            # Median depth within 6 m of the whole instance, not only its near pixels.
            targets = {i for i in targets if np.nanmedian(frame.depth_m[ids == i]) <= RECALL_MAX_DEPTH_M}
            found = {d.gt_instance_id for d in detections if d.gt_instance_id is not None and d.gt_instance_id >= 0}
            in_view += len(targets)
            detected += len(targets & found)
            for d, e in zip(detections, emb, strict=True):
                if d.gt_instance_id is None or d.gt_instance_id < 0:
                    false_positives += 1
                    continue
                true_positives += 1
                truth = true_label[d.gt_instance_id]
                if d.label != truth:
                    confused += 1
                    if object_ids[d.gt_instance_id] >= 0:  # a BIM object's crop, as below (clutter has no label)
                        confused_cosines.append(float(e @ text_vectors(truth)))
                elif object_ids[d.gt_instance_id] >= 0:
                    embeddings.append(e)
                    labels.append(true_label[d.gt_instance_id])
                    instance_keys.append((sim.meta.name, d.gt_instance_id))
    emb_arr = np.asarray(embeddings, np.float32).reshape(-1, text_embedder.dim)
    result: dict[str, Any] = {
        "frames": frames,
        "objects_in_view_6m": in_view,
        "recall_6m": detected / in_view if in_view else float("nan"),
        "true_positives": true_positives,
        "confusion_rate": confused / true_positives if true_positives else float("nan"),
        "false_positives_per_frame": false_positives / frames if frames else float("nan"),
        "vs_vocabulary": similarity_statistics(emb_arr, labels, vocabulary, text_embedder),
        "vs_bim_categories": similarity_statistics(emb_arr, labels, sorted(set(labels)), text_embedder),
        "crop_to_crop": crop_similarity_statistics(emb_arr, labels, instance_keys),
        "confused_crop_to_true_text": float(np.mean(confused_cosines)) if confused_cosines else float("nan"),
    }
    mean, std = label_cosine_statistics(text_embedder.encode(vocabulary))
    result["vocabulary_text_cosine"] = {"mean": mean, "std": std}
    return result


def crop_similarity_statistics(
    embeddings: np.ndarray, labels: Sequence[str], instance_keys: Sequence[tuple[str, int]]
) -> dict[str, float]:
    """Mean cosine between crops of the same object, of other objects of the same class, of other classes."""
    if len(embeddings) < 2:
        return {}
    sims = embeddings @ embeddings.T
    same_instance = np.array([[a == b for b in instance_keys] for a in instance_keys])
    same_class = np.array([[a == b for b in labels] for a in labels])
    off = ~np.eye(len(embeddings), dtype=bool)

    def mean_of(mask: np.ndarray) -> float:
        return float(sims[mask & off].mean()) if (mask & off).any() else float("nan")

    return {
        "same_instance": mean_of(same_instance),
        "same_class": mean_of(same_class & ~same_instance),
        "other_class": mean_of(~same_class),
    }


# ------------------------------------------------------------------------------------------ speed


def benchmark_graph_update(
    sims: Sequence[SimResult], cfg: Config, text_embedder: TextEmbedder, sim_preset: str | None = None
) -> dict[str, Any]:
    """Median ms of the graph update per frame (lifting + DBSCAN + association + fusion + periodic merge and
    prune), without the detector, segmenter and embedder: they run first, untimed, on every frame."""
    totals, lifts, associates, busy, per_detection = [], [], [], [], []
    for sim in sims:
        perception = make_perception(cfg, sim.meta, text_embedder, sim_preset=sim_preset)
        fronts = [perception.perceive(frame) for frame in sim.frames]
        graph = perception.graph
        for frame, (detections, masks, emb) in zip(sim.frames, fronts, strict=True):
            t0 = time.perf_counter()
            stats = graph.update(frame, detections, masks, emb)
            total = (time.perf_counter() - t0) * 1e3
            totals.append(total)
            lifts.append(stats.lift_ms)
            associates.append(stats.associate_ms)
            if detections:
                busy.append(total)
                per_detection.append(total / len(detections))
    k = sims[0].meta.intrinsics
    return {
        "frames": len(totals),
        "frames_with_detections": len(busy),
        "image": f"{k.width}x{k.height}",
        "median_ms": statistics.median(totals),
        "p90_ms": float(np.percentile(totals, 90)),
        "max_ms": max(totals),
        "median_ms_frames_with_detections": statistics.median(busy) if busy else float("nan"),
        "p90_ms_frames_with_detections": float(np.percentile(busy, 90)) if busy else float("nan"),
        "lift_ms_median": statistics.median(lifts),
        "associate_ms_median": statistics.median(associates),
        "median_ms_per_detection": statistics.median(per_detection) if per_detection else float("nan"),
    }


# ------------------------------------------------------------------------------------------ one building


def _simulate_building(
    building: str, cfg: Config, text_embedder: TextEmbedder, n: int, seed: int, work: Path, tour: int = 0
) -> tuple[BimPrior, list[SimResult]]:
    """The prior of a synth preset or IFC file and its n standard trajectories (or one furniture tour)."""
    from bimfactor.bim.ifc import load_ifc
    from bimfactor.bim.prior import build_prior
    from bimfactor.bim.synth import PRESETS, write_building
    from bimfactor.perception.scenes import furniture_groups, furniture_tour
    from bimfactor.sim.simulate import build_world, simulate_sequence

    if building in PRESETS:
        path = work / f"{building}.ifc"
        write_building(building, seed, path)
    else:
        path = Path(building)
    prior = build_prior(path, cfg, text_embedder)
    model = load_ifc(path, cfg.bim.ifc)
    if tour > 0:
        storey = max(range(len(prior.storeys)), key=lambda s: len(furniture_groups(prior, s)))
        return prior, [furniture_tour(prior, model, cfg, tour, storey, seed)]
    world = build_world(prior, model, cfg, seed)
    return prior, [simulate_sequence(prior, model, cfg, t, seed, progress=False, world=world) for t in range(n)]


def run_graph_bench(
    building: str,
    cfg: Config,
    out_dir: str | Path,
    preset: str | None = None,
    tour: int = 0,
    true_odometry: bool = False,
) -> dict[str, Any]:
    """The perception report of one building (synth preset name or IFC path) over its standard trajectories
    (or a furniture tour): graph precision/recall/segmentation/labels, detector rates, update speed."""
    text_embedder = make_text_embedder(cfg.embed)
    with tempfile.TemporaryDirectory() as work:
        n = cfg.evaluation.num_trajectories
        prior, sims = _simulate_building(building, cfg, text_embedder, n, cfg.seed, Path(work), tour)
    if true_odometry:
        for frame in (f for sim in sims for f in sim.frames):
            frame.odom_pose = frame.gt_pose.copy()
    result = evaluate_building(prior, sims, cfg, text_embedder, preset, out_dir)
    result["speed"] = benchmark_graph_update(sims, cfg, text_embedder, preset)
    write_text_atomic(Path(out_dir) / "report.json", json.dumps(result, indent=1, default=float))
    log.info("summary: %s", json.dumps(result["summary"]))
    log.info("detector: %s", json.dumps({k: v for k, v in result["detector"].items() if not isinstance(v, dict)}))
    log.info("speed: %s", json.dumps(result["speed"]))
    return result
