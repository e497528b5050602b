"""Speed of the online stages, for `bimfactor bench render|smcl|scanmatch|backend`: timing harnesses kept out of
the algorithm modules they time.

`benchmark_render` times the simulator's renderer, `benchmark_step` one S-MCL step (predict, update, resample),
`benchmark_scan_matching` the correlative scan matcher (with its accuracy and covariance honesty) and
`benchmark_backend` the multi-hypothesis back end's step. The fine registration's is with the registrar comparison
(`evaluation.registrars.benchmark_registration`), the online scene graph's with its evaluation
(`evaluation.graph.benchmark_graph_update`).
"""

from __future__ import annotations

import logging
import re
import statistics
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from bimfactor.backend.posegraph import MultiHypothesisBackend
from bimfactor.backend.scan_factor import CorrelativeMatcher
from bimfactor.backend.synthetic import loop_scenario
from bimfactor.bim.ifc import IfcModel
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import BackendConfig, Config, OdometryConfig, SmclConfig
from bimfactor.evaluation.registrars import perturb
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.measurements.scan import DepthPoints, frame_endpoints
from bimfactor.localization.measurements.semantic import polar_coordinates
from bimfactor.localization.modes import Mode
from bimfactor.progress import progress
from bimfactor.sim.sensors import RgbdCamera
from bimfactor.sim.simulate import build_world, simulate_sequence
from bimfactor.sim.trajectory import TrajectorySimulator
from bimfactor.types import Observations, se2_compose, wrap_angle

log = logging.getLogger(__name__)

CHI2_3DOF_95 = 7.815


# ------------------------------------------------------------------------------------------ simulator


def benchmark_render(prior: BimPrior, model: IfcModel, cfg: Config, n_frames: int = 200) -> dict:
    """Render speed with noise and instance ids at the configured image size, over poses of trajectory 0."""
    t0 = time.perf_counter()
    world = build_world(prior, model, cfg, cfg.seed)
    world_s = time.perf_counter() - t0
    trajectory = TrajectorySimulator(prior, cfg).trajectory(0, cfg.seed)
    camera = RgbdCamera.from_config(world, cfg)
    elevation = prior.storeys[trajectory.storey_index].storey.elevation_m
    poses = trajectory.poses[np.linspace(0, len(trajectory.poses) - 1, n_frames).astype(int)]
    rng = np.random.default_rng(cfg.seed)
    camera.render(poses[0], elevation, rng)  # warm-up: the scene's BVH is built on the first query
    times_ms = []
    start = time.perf_counter()
    for pose in progress(poses, desc="rendering", unit="frame"):
        t = time.perf_counter()
        camera.render(pose, elevation, rng)
        times_ms.append((time.perf_counter() - t) * 1000)
    total = time.perf_counter() - start
    k = camera.intrinsics
    return {
        "building": Path(prior.source_file).name,
        "width": k.width,
        "height": k.height,
        "n_frames": n_frames,
        "frames_per_s": n_frames / total,
        "median_ms": statistics.median(times_ms),
        "p90_ms": float(np.percentile(times_ms, 90)),
        "instances": len(world.instances),
        "triangles": sum(len(m.faces) for m in world.meshes),
        "world_build_s": world_s,
    }


# ------------------------------------------------------------------------------------------ S-MCL step


BENCH_SCAN_ENDPOINTS = 45
"""`bench smcl`'s scan: one endpoint per 2° of a 90° view (the default `scan.beam_deg`)."""


def _benchmark_observations(
    prior: BimPrior, visibility: VisibilityTable, cfg: SmclConfig, n_obs: int, rng: np.random.Generator
) -> tuple[Observations, np.ndarray, int]:
    """n_obs observations at a navigable pose that sees many objects: the objects in its view, then others.

    Returns the observations, the (3,) pose and its storey. Embeddings are the BIM label embeddings plus noise.
    """
    mcl = SemanticMCL(prior, visibility, cfg, rng, num_particles=1)
    poses, storeys = mcl.sampler.uniform(400)
    scorer = mcl.models.semantic
    offsets, ids = visibility.candidates(poses[:, :2], storeys)
    owner = np.repeat(np.arange(len(poses)), np.diff(offsets))
    d, alpha = polar_coordinates(poses[owner], scorer.object_xy[ids])
    in_view = (d <= scorer.radius_m) & (np.abs(alpha) <= scorer.half_fov_rad)
    best = int(np.argmax(np.bincount(owner[in_view], minlength=len(poses))))
    pick = in_view & (owner == best)
    seen_ids, ranges, bearings = ids[pick][:n_obs], d[pick][:n_obs], alpha[pick][:n_obs]
    extra = n_obs - len(seen_ids)
    if extra > 0:  # distractors: random BIM objects at random places in the view
        seen_ids = np.concatenate([seen_ids, rng.integers(0, len(prior.objects), extra)])
        ranges = np.concatenate([ranges, rng.uniform(0.5, scorer.radius_m, extra)])
        bearings = np.concatenate([bearings, rng.uniform(-scorer.half_fov_rad, scorer.half_fov_rad, extra)])
    noise = 0.02 * rng.standard_normal((n_obs, prior.object_embeddings.shape[1]))
    embeddings = prior.object_embeddings[seen_ids] + noise
    embeddings /= np.linalg.norm(embeddings, axis=1, keepdims=True)
    observations = Observations(
        embeddings.astype(np.float32),
        ranges + 0.1 * rng.standard_normal(n_obs),
        wrap_angle(bearings + np.deg2rad(3.0) * rng.standard_normal(n_obs)),
        labels=[prior.objects[i].label for i in seen_ids],
    )
    return observations, poses[best], int(storeys[best])


def benchmark_step(
    prior: BimPrior,
    visibility: VisibilityTable,
    cfg: SmclConfig,
    max_range_m: float,
    n_particles_list: tuple[int, ...] = (100, 1000, 5000, 20000),
    n_obs: int = 12,
    repeats: int = 20,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Median milliseconds of predict + update + resample per particle count, from a uniform (global) start.

    Every repeat starts from freshly spread particles (not timed), the hardest case: particles everywhere, every
    candidate list different. The observations are `n_obs` objects seen from one pose (padded with distractors);
    with the scan term, the update also scores a scan of 45 endpoints over the view, up to `max_range_m`.
    `*_ms_*` are wall-clock; `total_cpu_ms_median` is this thread's CPU time (robust to a busy machine).
    """
    rng = np.random.default_rng(seed)
    observations, _, _ = _benchmark_observations(prior, visibility, cfg, n_obs, rng)
    # With the scan term: one endpoint per bearing bin of the view (timing does not depend on where they land).
    n_beams = BENCH_SCAN_ENDPOINTS if cfg.scan.enabled else 0
    bearings = np.linspace(-0.5, 0.5, n_beams) * np.deg2rad(cfg.semantic.fov_deg)
    ranges = rng.uniform(0.5, max_range_m, n_beams)
    frame = FrameData(observations, np.column_stack([ranges * np.cos(bearings), ranges * np.sin(bearings)]))
    increment = np.array([0.5, 0.0, np.deg2rad(5.0)])
    rows = []
    for M in n_particles_list:
        mcl = SemanticMCL(prior, visibility, cfg, np.random.default_rng(seed + M), num_particles=M)
        parts: dict[str, list[float]] = {"predict": [], "update": [], "resample": [], "total": [], "total_cpu": []}
        calls, resampled = [], 0
        for _ in range(repeats + 1):  # the first round warms caches and is dropped
            mcl.initialize()
            cpu0, t0 = time.thread_time(), time.perf_counter()
            mcl.predict(increment)
            t1 = time.perf_counter()
            mcl.update(frame)
            t2 = time.perf_counter()
            did, _ = mcl.resample(frame)
            t3, cpu3 = time.perf_counter(), time.thread_time()
            for name, value in (("predict", t1 - t0), ("update", t2 - t1), ("resample", t3 - t2), ("total", t3 - t0)):
                parts[name].append(value * 1e3)
            parts["total_cpu"].append((cpu3 - cpu0) * 1e3)
            calls.append(mcl.models.semantic.last_stats.hungarian_calls)
            resampled += int(did)
        row: dict[str, Any] = {"n_particles": M, "n_obs": len(observations), "n_scan": n_beams, "repeats": repeats}
        for name, values in parts.items():
            row[f"{name}_ms_median"] = statistics.median(values[1:])
        row["total_ms_p90"] = float(np.percentile(parts["total"][1:], 90))
        row["hungarian_calls_median"] = statistics.median(calls[1:])
        row["resampled_share"] = resampled / (repeats + 1)
        rows.append(row)
        log.info("S-MCL step, M=%d, K=%d: %.2f ms median", M, len(observations), row["total_ms_median"])
    return rows


# ------------------------------------------------------------------------------------------ scan matching


def benchmark_scan_matching(
    prior: BimPrior, model: IfcModel, cfg: Config, every: int = 2, trans_m: float = 0.3, rot_deg: float = 5.0
) -> dict:
    """Accuracy, covariance honesty and time of `CorrelativeMatcher.match` on simulated keyframes.

    Every `every`-th keyframe of the evaluation's simulated trajectories (the config seed's), matched from its true
    pose moved `trans_m` in a random direction and turned ±`rot_deg` (the seeded `registrars.perturb`). Reports the
    accepted share and the rejection reasons; over the accepted matches the median and p90 position and yaw errors
    and the share whose true pose lies inside the 95 % ellipsoid (χ² with 3 DoF); the median and p90 time of all.
    """
    matcher = CorrelativeMatcher(prior, cfg.backend.scan_factor)
    world = build_world(prior, model, cfg, cfg.seed)
    rng = np.random.default_rng([cfg.seed, 0xC5])
    times, errors_m, errors_deg, inside, reasons = [], [], [], [], Counter()
    for k in progress(range(cfg.evaluation.num_trajectories), desc="scan matching", unit="trajectory"):
        sim = simulate_sequence(prior, model, cfg, k, cfg.seed, progress=False, world=world)
        for frame in sim.frames[::every]:
            truth = np.asarray(frame.gt_pose, np.float64)
            start = perturb(truth, trans_m, np.deg2rad(rot_deg), rng)
            endpoints = frame_endpoints(DepthPoints.of_frame(frame, sim.meta), cfg)
            clock = time.perf_counter()
            found = matcher.match(start, frame.gt_storey or 0, endpoints)
            times.append((time.perf_counter() - clock) * 1000)
            if not found.accepted:
                reasons[re.sub(r"^\d+ ", "", found.reason)] += 1  # "7 endpoints on the BIM" → its kind
                continue
            delta = found.pose - truth
            delta[2] = wrap_angle(delta[2])
            errors_m.append(float(np.hypot(delta[0], delta[1])))
            errors_deg.append(float(np.rad2deg(abs(delta[2]))))
            inside.append(float(delta @ np.linalg.solve(found.covariance, delta)) <= CHI2_3DOF_95)
    n = len(times)
    return {
        "building": Path(prior.source_file).name,
        "keyframes": n,
        "start_error_m": trans_m,
        "start_error_deg": rot_deg,
        "accepted": len(errors_m) / n if n else None,
        "rejections": dict(reasons.most_common()),
        "trans_err_median_m": float(np.median(errors_m)) if errors_m else None,
        "trans_err_p90_m": float(np.percentile(errors_m, 90)) if errors_m else None,
        "orient_err_median_deg": float(np.median(errors_deg)) if errors_deg else None,
        "orient_err_p90_deg": float(np.percentile(errors_deg, 90)) if errors_deg else None,
        "coverage_95": float(np.mean(inside)) if inside else None,
        "median_ms": float(np.median(times)) if times else None,
        "p90_ms": float(np.percentile(times, 90)) if times else None,
    }


# ------------------------------------------------------------------------------------------ back end


def benchmark_backend(
    cfg: BackendConfig,
    odometry: OdometryConfig,
    n_modes: int = 5,
    n_keyframes: int = 60,
    n_landmarks: int = 12,
    n_obs: int = 6,
    seed: int = 0,
) -> dict[str, Any]:
    """Median ms of `MultiHypothesisBackend.step` (all modes' ISAM2 updates) per keyframe on a synthetic loop.

    A symmetric building: `n_modes` copies of the loop world 100 m apart, one mode in each, every mode matching
    `n_obs` landmarks per keyframe in its own copy, so all modes stay alive (none is pruned or merged).
    """
    rng = np.random.default_rng(seed)
    scenario = loop_scenario(rng, cfg, odometry, n_poses=n_keyframes, n_landmarks=n_landmarks, n_obs=n_obs)
    spacing_m = 100.0
    offsets = [np.array([spacing_m * k, 0.0]) for k in range(n_modes)]
    landmark_xy = np.concatenate([scenario.landmark_xy + off for off in offsets])
    backend = MultiHypothesisBackend(landmark_xy, cfg, odometry)
    per_step, per_graph = [], []
    for t in range(n_keyframes):
        clusters = [
            Mode(scenario.true_poses[t] + np.append(off, 0.0), np.diag([0.01, 0.01, 0.001]), 1.0 / n_modes)
            for off in offsets
        ]
        assoc = scenario.associations[t]

        def associate(pose: np.ndarray, storey: int, assoc: list[tuple[int, int]] = assoc) -> list[tuple[int, int]]:
            copy = int(np.floor(pose[0] / spacing_m + 0.5))
            return [(k, j + copy * n_landmarks) for k, j in assoc]

        increment = None if t == 0 else scenario.increments[t - 1]
        step = backend.step(clusters, increment, scenario.observations[t], associate)
        assert step is not None, "every keyframe brings a cluster per copy of the world"
        per_step.append(step.timings_ms["total"])
        per_graph.append(step.timings_ms["graphs"])
    row = {
        "n_modes": n_modes,
        "n_keyframes": n_keyframes,
        "n_obs": n_obs,
        "step_ms_median": statistics.median(per_step[1:]),
        "step_ms_p90": float(np.percentile(per_step[1:], 90)),
        "graphs_ms_median": statistics.median(per_graph[1:]),
        "modes_alive_end": len(backend.graphs),
    }
    log.info("back end, %d modes: %.2f ms median per keyframe", n_modes, row["step_ms_median"])
    return row


def benchmark_suggest(prior: BimPrior, visibility: VisibilityTable, cfg: Config, n_modes: int = 5, repeats: int = 20,
                      seed: int = 0) -> dict[str, Any]:  # fmt: skip
    """Milliseconds of one suggestion (`active.Suggester.suggest`) for `n_modes` hypotheses at random navigable poses of
    the storey with the most floor, probabilities falling from the first, and of the gain of exactly
    `active.candidates` candidate views over the hypotheses (the scoring, without the reachability test that drops
    candidates some place cannot reach), both beyond the views of the last `SEEN_VIEWS` keyframes. The navigation
    graph is built before timing (once per building)."""
    from bimfactor.active import Hypothesis, Suggester, information_gain
    from bimfactor.active.suggest import SEEN_VIEWS

    rng = np.random.default_rng(seed)
    storey = int(np.argmax([layers.navigable.sum() for layers in prior.storeys]))
    cells = np.argwhere(prior.storeys[storey].navigable)
    suggester = Suggester(prior, visibility, cfg)
    suggester.graph(storey)
    weights = np.arange(n_modes, 0, -1, dtype=float)
    weights /= weights.sum()
    n_candidates = cfg.active.candidates
    # the views the filter weighed: the last SEEN_VIEWS keyframes of a straight drive to where the robot stands
    seen = np.column_stack([np.linspace(-0.5 * SEEN_VIEWS, 0.0, SEEN_VIEWS), np.zeros((SEEN_VIEWS, 2))])
    suggest_ms, score_ms, scored = [], [], []
    for _ in range(repeats + 1):  # the first round warms caches and is dropped
        xy = prior.grid.cell_to_world(cells[rng.integers(len(cells), size=n_modes)])
        poses = np.column_stack([xy, rng.uniform(-np.pi, np.pi, n_modes)])
        hyps = [Hypothesis(p, storey, float(w)) for p, w in zip(poses, weights, strict=True)]
        t0 = time.perf_counter()
        out = suggester.suggest(hyps, np.zeros(3), seen_odom=seen)
        t1 = time.perf_counter()
        relative = np.column_stack([rng.uniform(-6, 6, (n_candidates, 2)), rng.uniform(-np.pi, np.pi, n_candidates)])
        views = np.stack([np.asarray(h.pose) for h in hyps])
        candidate_poses = np.stack([se2_compose(views[k], relative) for k in range(n_modes)], axis=1)
        t2 = time.perf_counter()
        storeys = np.full(n_modes, storey)
        information_gain(weights, suggester.unweighed_evidence(candidate_poses, storeys, hyps, np.zeros(3), seen))
        t3 = time.perf_counter()
        suggest_ms.append((t1 - t0) * 1e3)
        score_ms.append((t3 - t2) * 1e3)
        scored.append(len(out.gains_nats))
    suggest_ms, score_ms, scored = suggest_ms[1:], score_ms[1:], scored[1:]
    return {
        "modes": n_modes,
        "candidates": n_candidates,
        "suggest_ms_median": float(np.median(suggest_ms)),
        "suggest_ms_p90": float(np.percentile(suggest_ms, 90)),
        "candidates_scored_median": float(np.median(scored)),
        "score_all_candidates_ms_median": float(np.median(score_ms)),
        "score_all_candidates_ms_p90": float(np.percentile(score_ms, 90)),
        "repeats": repeats,
    }
