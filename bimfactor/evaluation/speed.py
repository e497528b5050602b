"""Timing harnesses kept out of the algorithm modules they time: `benchmark_step` one S-MCL step (predict, update,
resample; a row of `bimfactor bench speed`) and `benchmark_scan_matching` the correlative scan matcher with its
accuracy and covariance honesty (`bimfactor bench scanmatch`). The online scene graph's is with its evaluation
(`evaluation.graph.benchmark_graph_update`)."""

from __future__ import annotations

import logging
import re
import statistics
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from bimfactor.backend.scan_factor import CorrelativeMatcher
from bimfactor.bim.ifc import IfcModel
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config, SmclConfig
from bimfactor.evaluation.registrars import perturb
from bimfactor.localization.filter import SemanticMCL
from bimfactor.localization.measurements import FrameData
from bimfactor.localization.measurements.scan import DepthPoints, frame_endpoints
from bimfactor.localization.measurements.semantic import polar_coordinates
from bimfactor.progress import progress
from bimfactor.sim.simulate import build_world, simulate_sequence
from bimfactor.types import Observations, wrap_angle

log = logging.getLogger(__name__)

CHI2_3DOF_95 = 7.815


# ------------------------------------------------------------------------------------------ simulator


# ------------------------------------------------------------------------------------------ S-MCL step


BENCH_SCAN_ENDPOINTS = 45
"""The timed filter step's scan: one endpoint per 2° of a 90° view (the default `scan.beam_deg`)."""


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
    """Median milliseconds of predict + update + resample per particle count, from a uniform start (particles spread
    anew, untimed, every repeat): `n_obs` objects seen from one pose plus distractors and, with the scan term, a scan of
    45 endpoints. `*_ms_*` are wall-clock; `total_cpu_ms_median` this thread's CPU time."""
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
    """Accuracy, covariance honesty and time of `CorrelativeMatcher.match` on every `every`-th keyframe of the
    evaluation's simulated trajectories, from the true pose moved `trans_m` and turned ±`rot_deg`: accepted share,
    rejection reasons, median and p90 errors, the share inside the 95 % ellipsoid (χ², 3 DoF), and time."""
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
