"""The paper's protocol (Sec. III): six trajectories with distinct starts, T = 50, each localized three times.

Each trajectory is simulated once and localized `repeats` times with other filter and perception seeds, in parallel
processes; Table I's statistics are mean ± std over the scored steps of a trajectory's repeats, the average pooled
over every run with a 95 % bootstrap interval over whole runs. Scored steps (`evaluation.score_from`), scenarios
(`evaluation.scenario`: global, guess, kidnap, storeys) and variants (`evaluation.variants`; one smcl+graph forward
pass also yields the smcl and refine estimates): docs/evaluation.md.
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import os
import re
import sys
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bimfactor.config import Config, EvaluationConfig, updated
from bimfactor.errors import ConfigError, InputError, RunsLostError
from bimfactor.evaluation.metrics import (
    RouteOutcome,
    orientation_errors_deg,
    run_bootstrap_ci,
    translation_errors_m,
)
from bimfactor.io.atomic import write_text_atomic
from bimfactor.progress import progress
from bimfactor.types import STOREY_CHANGE, wrap_angle

if TYPE_CHECKING:
    from bimfactor.backend.scan_factor import CorrelativeMatcher
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.symmetry import Motion
    from bimfactor.pipeline import LocalizationRun, Track
    from bimfactor.sim.simulate import SimResult
    from bimfactor.types import Frame, SequenceMeta

log = logging.getLogger(__name__)


@dataclass
class StepErrors:
    """Table I's per-step cells of one run over some steps: translation, orientation and room hits."""

    trans_err_m: np.ndarray
    orient_err_deg: np.ndarray
    room_hit: np.ndarray

    @classmethod
    def of(cls, track: Track, gt_poses: np.ndarray, gt_rooms: np.ndarray) -> StepErrors:
        """A track's errors against the ground truth of the same steps."""
        return cls(
            translation_errors_m(track.poses, gt_poses),
            orientation_errors_deg(track.poses, gt_poses),
            (track.rooms == gt_rooms).astype(float),
        )


@dataclass
class RunResult:
    """Per-step errors of one localized run of one variant, and its summary metrics."""

    variant: str
    trajectory: int
    repeat: int
    trans_err_m: np.ndarray
    orient_err_deg: np.ndarray
    room_hit: np.ndarray
    inside_ellipse95: np.ndarray
    step_ms: np.ndarray
    metrics: dict
    icp_accepted: np.ndarray | None = None
    icp_rejections: dict[str, int] | None = None
    scored_from: int = 0
    relocalizations: int = 0  # steps at which the filter spread its particles over the building again
    tracking_before: bool | None = None  # kidnap: within 1 m and 15° of the truth at the last step before it
    trans_err_twin_m: np.ndarray | None = None  # up to the building's twin motion (`errors_up_to_twin`), if any
    orient_err_twin_deg: np.ndarray | None = None
    trans_err_before_m: float | None = None  # kidnap: the mean translation error over the steps before it
    storey_hit: np.ndarray | None = None  # (T,) the estimate on the true storey
    storey_hit_after_change: np.ndarray | None = None  # the same over the keyframes after each storey change
    challenges: int = 0  # steps at which the belief took a challenger's particles
    from_start: StepErrors | None = None  # scored from the filter's convergence: the first T steps, for comparison
    outcome: RouteOutcome | None = None  # the whole route from its first frame (`route_outcome`)
    node: str = field(default="", compare=False)  # the Ray node that ran it (its id); "" in a process pool


ACTIVE_SUFFIX = "+active"  # the active scenario's closed-loop runs of a variant (`evaluation.active`)
EVENT_SUFFIX = "+event"  # the storeys scenario's runs of a variant given the storey-change event


def reported_variants(ev: EvaluationConfig) -> list[str]:
    """The variants a report holds: `evaluation.variants`, and in the active scenario each again as its closed-loop
    run, named with `ACTIVE_SUFFIX`; in the storeys scenario each again given the event, named with `EVENT_SUFFIX`."""
    suffix = {"active": ACTIVE_SUFFIX, "storeys": EVENT_SUFFIX}.get(ev.scenario)
    return [*ev.variants, *(v + suffix for v in ev.variants)] if suffix else list(ev.variants)


SERVED_BY = {"smcl+graph": {"smcl+graph", "refine"}, "full": {"full"}}  # online variant → the variants its run yields


def forward_variants(variants: list[str]) -> list[str]:
    """The online variants whose runs yield every one of `variants` (see the module docstring); `smcl` comes with
    any of them."""
    needed = [online for online, serves in SERVED_BY.items() if serves & set(variants)]
    return needed or ["smcl"]


def scoring_window(converged: np.ndarray, steps: int, score_from: str, warmup_max_steps: int) -> slice:
    """The `steps` scored steps of a run whose (N,) `converged` flags are the filter's own: from the first frame
    (`start`), or from the first step the filter reports converged, at most `warmup_max_steps` in
    (`filter_converged`; no ground truth decides where scoring begins)."""
    if score_from == "start":
        return slice(0, steps)
    flagged = np.flatnonzero(np.asarray(converged, bool)[: warmup_max_steps + 1])
    first = int(flagged[0]) if len(flagged) else warmup_max_steps
    return slice(first, first + steps)


def simulate_routes(
    prior_dir: str | Path, cfg: Config, routes: list[tuple[int, int | None]], change_storey: bool = False
) -> tuple[list[SimResult], BimPrior]:
    """Trajectories of the config seed on the prior's building, each (trajectory, length in keyframes; None: as the
    protocol simulates it, with `filter_converged` `warmup_max_steps` keyframes longer), in one world: the prior,
    the IFC model and the world are loaded and built once; `change_storey`: routes through a portal to another floor.
    Returns them with the loaded prior."""
    from bimfactor.sim.simulate import build_world, load_world_inputs, simulate_sequence

    ev = cfg.evaluation
    prior, model = load_world_inputs(prior_dir, cfg)
    world = build_world(prior, model, cfg, cfg.seed)
    sims = []
    for trajectory, length in routes:
        steps = ev.trajectory_length + ev.warmup_steps if length is None else length
        sim_cfg = cfg.model_copy(update={"evaluation": ev.model_copy(update={"trajectory_length": steps})})
        sims.append(
            simulate_sequence(prior, model, sim_cfg, trajectory, cfg.seed, False, world, change_storey=change_storey)
        )
    return sims, prior


def kidnap_route(trajectory: int, num_trajectories: int) -> int:
    """The route a robot on route `trajectory` is carried to in the kidnap scenario: three further on."""
    return (trajectory + 3) % num_trajectories


def pose_guess(true_pose: np.ndarray, offset_m: float, offset_deg: float, rng: np.random.Generator) -> np.ndarray:
    """(3,) a pose guess `offset_m` from `true_pose` in a uniformly drawn direction, its yaw `offset_deg` off with a
    drawn sign."""
    direction = rng.uniform(-np.pi, np.pi)
    sign = 1.0 if rng.random() < 0.5 else -1.0
    x, y, yaw = np.asarray(true_pose, float)
    turned = wrap_angle(yaw + sign * np.deg2rad(offset_deg))
    return np.array([x + offset_m * np.cos(direction), y + offset_m * np.sin(direction), turned])


def scenario_run(
    prior_dir: str | Path, cfg: Config, trajectory: int, repeat: int
) -> tuple[BimPrior, SequenceMeta, list[Frame], Config, slice | None]:
    """What one run of the protocol localizes under `evaluation.scenario`: the prior, the sequence, the config (with
    `guess`, its initial pose) and the steps scored when they do not depend on the run (None: `scoring_window`)."""
    from bimfactor.sim.simulate import kidnap

    ev = cfg.evaluation
    if ev.scenario == "kidnap":
        routes = [
            (trajectory, max(ev.kidnap_at, ev.trajectory_length)),
            (kidnap_route(trajectory, ev.num_trajectories), ev.kidnap_resume_at + 1 + ev.trajectory_length),
        ]
        (sim, other), prior = simulate_routes(prior_dir, cfg, routes)
        frames = kidnap(sim.frames, other.frames, ev.kidnap_at, ev.kidnap_resume_at)
        scored = slice(ev.kidnap_at, ev.kidnap_at + ev.trajectory_length)
        return prior, sim.meta, frames, _known_storey(cfg, frames), scored
    (sim,), prior = simulate_routes(prior_dir, cfg, [(trajectory, None)], change_storey=ev.scenario == "storeys")
    if ev.scenario == "guess":
        first = sim.frames[0]
        rng = np.random.default_rng([run_seed(cfg.seed, trajectory, repeat), GUESS_STREAM])
        x, y, yaw = pose_guess(first.gt_pose, ev.guess_offset_m, ev.guess_offset_deg, rng)
        guess = [float(x), float(y), float(np.rad2deg(yaw))]
        cfg = updated(cfg, {"smcl.start.pose": guess, "smcl.start.storey": first.gt_storey or 0})
        return prior, sim.meta, sim.frames, cfg, slice(0, ev.trajectory_length)
    return prior, sim.meta, sim.frames, _known_storey(cfg, sim.frames), None


def _known_storey(cfg: Config, frames: list[Frame]) -> Config:
    """With `evaluation.known_storey`, the config whose uniform start covers the first frame's true storey only."""
    if not cfg.evaluation.known_storey:
        return cfg
    return updated(cfg, {"smcl.start.storeys": [frames[0].gt_storey or 0]})


GUESS_STREAM = 0x6E55  # the random stream of a run's pose guess


def run_seed(seed: int, trajectory: int, repeat: int) -> int:
    """The filter and perception seed of one run: repeat `repeat` of trajectory `trajectory` under config `seed`."""
    return seed * 1000 + 17 * trajectory + repeat


def _run_one(
    prior_dir: str, cfg_json: str, trajectory: int, repeat: int, twins: dict[int, Motion], rerun_dir: str | None = None
) -> list[RunResult]:
    """Simulate trajectory k (config seed), localize it with seed (config seed, repeat), score every variant (also
    up to the building's `twins`, when it has any); in a worker process, or in this one with one worker. The active
    scenario closes the loop (`evaluation.active`). With `rerun_dir`, each forward pass is also a Rerun recording
    there (`run_recording_path`)."""
    from threadpoolctl import threadpool_limits

    # One BLAS / OpenMP thread, as the CLI runs and as Ray's workers do: a threaded BLAS sums in another order, and a
    # run must not depend on the runner or on what its process loaded before.
    with threadpool_limits(limits=1):
        return _run_one_pinned(prior_dir, cfg_json, trajectory, repeat, twins, rerun_dir)


def _run_one_on_ray(
    prior_dir: str, cfg_json: str, trajectory: int, repeat: int, twins: dict[int, Motion], rerun_dir: str | None = None
) -> list[RunResult]:
    """`_run_one` in a Ray worker: each result records the node that ran it (Ray's node id, as `ray.nodes()` and
    `ray status` name it)."""
    import ray

    results = _run_one(prior_dir, cfg_json, trajectory, repeat, twins, rerun_dir)
    node = ray.get_runtime_context().get_node_id()
    for result in results:
        result.node = node
    return results


def _run_one_pinned(
    prior_dir: str, cfg_json: str, trajectory: int, repeat: int, twins: dict[int, Motion], rerun_dir: str | None
) -> list[RunResult]:
    from bimfactor.config import Config
    from bimfactor.evaluation.viewer import maybe_record
    from bimfactor.pipeline import GRAPH_VARIANTS, localize_sequence, scan_matcher

    cfg = Config.model_validate_json(cfg_json)
    if cfg.evaluation.scenario == "active":
        from bimfactor.evaluation.active import active_runs

        return active_runs(prior_dir, cfg, trajectory, repeat, twins)
    prior, meta, frames, cfg, window = scenario_run(prior_dir, cfg, trajectory, repeat)
    online_variants = forward_variants(cfg.evaluation.variants)
    matcher = scan_matcher(prior, cfg) if any(v in GRAPH_VARIANTS for v in online_variants) else None
    if cfg.evaluation.scenario == "storeys":  # without the event, then with it
        unaware = [replace(f, extras={k: v for k, v in f.extras.items() if k != STOREY_CHANGE}) for f in frames]
        runs = []
        for suffix, given in (("", unaware), (EVENT_SUFFIX, frames)):
            forward = {
                online: localize_sequence(
                    prior, meta, given, online_config(cfg, online), seed=run_seed(cfg.seed, trajectory, repeat),
                    show_progress=False, matcher=matcher, twins=twins,
                )
                for online in online_variants
            }  # fmt: skip
            runs += score_runs(cfg, prior, given, forward, window, trajectory, repeat, twins, matcher, suffix)
        return runs
    forward = {}
    for online in online_variants:
        recording = None if rerun_dir is None else run_recording_path(rerun_dir, prior_dir, trajectory, repeat, online)
        with maybe_record(recording, prior, f"{Path(prior_dir).name} {meta.name} repeat {repeat} {online}") as recorder:
            forward[online] = localize_sequence(
                prior,
                meta,
                frames,
                online_config(cfg, online),
                seed=run_seed(cfg.seed, trajectory, repeat),
                show_progress=False,
                matcher=matcher,
                twins=twins,
                observer=recorder,
            )
    return score_runs(cfg, prior, frames, forward, window, trajectory, repeat, twins, matcher)


def run_recording_path(rerun_dir: str | Path, prior_dir: str | Path, trajectory: int, repeat: int, online: str) -> Path:
    """Where a protocol run's Rerun recording goes: DIR/<prior folder>-t<trajectory>-r<repeat>-<variant>.rrd."""
    return Path(rerun_dir) / f"{Path(prior_dir).name}-t{trajectory}-r{repeat}-{online.replace('+', '-')}.rrd"


def online_config(cfg: Config, online: str) -> Config:
    """The config of one forward pass: `localization.variant` set to the online variant."""
    return cfg.model_copy(update={"localization": cfg.localization.model_copy(update={"variant": online})})


def score_runs(
    cfg: Config,
    prior: BimPrior,
    frames: list[Frame],
    forward: dict[str, LocalizationRun],
    window: slice | None,
    trajectory: int,
    repeat: int,
    twins: dict[int, Motion],
    matcher: CorrelativeMatcher | None,
    suffix: str = "",
) -> list[RunResult]:
    """Score every variant of `evaluation.variants` of one run's forward passes (by online variant) over the same
    steps: `window`, or from the filter's own flag (`scoring_window`); results are named variant + `suffix`."""
    from bimfactor.evaluation.metrics import errors_up_to_twin, inside_ellipse, route_outcome, steps_to_converge
    from bimfactor.evaluation.report import track_metrics
    from bimfactor.refine import refine_run
    from bimfactor.sim.trajectory import AFTER_CHANGE_KEYFRAMES

    ev = cfg.evaluation
    variants = ev.variants
    run = next(iter(forward.values()))  # every forward pass runs the same filter: its estimate is the smcl one
    assert run.gt_poses is not None and run.gt_rooms is not None
    tracks = {"smcl": run.filter, **{online: r.graph for online, r in forward.items() if r.graph is not None}}
    if "refine" in variants:
        tracks["refine"] = refine_run(forward["smcl+graph"], prior, cfg, matcher).estimate
    # Every variant of the run is scored over the same steps: the scenario's, or from the filter's own flag.
    scored = (
        window
        if window is not None
        else scoring_window(run.converged, ev.trajectory_length, ev.score_from, ev.warmup_steps)
    )
    gt_poses, gt_rooms = run.gt_poses[scored], run.gt_rooms[scored]
    all_storeys = np.asarray([f.gt_storey or 0 for f in frames])
    gt_storeys = all_storeys[scored]
    changes = np.flatnonzero(np.diff(all_storeys)) + 1
    after_change = [np.arange(c, min(c + AFTER_CHANGE_KEYFRAMES, len(frames))) for c in changes]
    first = slice(0, ev.trajectory_length)  # the uniform cloud's steps included
    results = []
    for variant in variants:
        track = tracks[variant].window(scored)
        errors = StepErrors.of(track, gt_poses, gt_rooms)
        twin_errors = errors_up_to_twin(track.poses, gt_poses, gt_storeys, twins) if twins else (None, None)
        fine = forward[variant].fine.window(scored) if variant in forward and forward[variant].fine else None
        metrics = track_metrics(track, gt_poses, gt_rooms)
        assert metrics is not None
        tracking_before, trans_before = None, None
        if ev.scenario == "kidnap":
            before = slice(scored.start - 1, scored.start)
            tracking_before = (
                steps_to_converge(
                    translation_errors_m(tracks[variant].poses[before], run.gt_poses[before]),
                    orientation_errors_deg(tracks[variant].poses[before], run.gt_poses[before]),
                )
                is not None
            )
            ahead = slice(0, scored.start)
            trans_before = float(translation_errors_m(tracks[variant].poses[ahead], run.gt_poses[ahead]).mean())
        results.append(
            RunResult(
                variant + suffix,
                trajectory,
                repeat,
                errors.trans_err_m,
                errors.orient_err_deg,
                errors.room_hit,
                inside_ellipse(track.poses, track.covariances, gt_poses),
                track.step_ms,
                metrics.to_dict(),
                fine.accepted[fine.ran].astype(float) if fine is not None else None,
                fine.rejection_counts() if fine is not None else None,
                scored.start,
                int(forward.get(variant, run).relocalized.sum()),
                tracking_before,
                *twin_errors,
                trans_err_before_m=trans_before,
                storey_hit=(track.storeys == gt_storeys).astype(float),
                storey_hit_after_change=np.concatenate(
                    [(tracks[variant].storeys[k] == all_storeys[k]).astype(float) for k in after_change]
                )
                if after_change
                else None,
                challenges=int(forward.get(variant, run).challenged.sum()),
                from_start=StepErrors.of(tracks[variant].window(first), run.gt_poses[first], run.gt_rooms[first])
                if ev.scores_from_convergence
                else None,
                outcome=route_outcome(
                    tracks[variant].poses,
                    tracks[variant].storeys,
                    run.gt_poses,
                    all_storeys,
                    run.converged,
                    forward[variant].modes if variant in forward and forward[variant].graph is not None else None,
                ),
            )
        )
    return results


def _pooled(runs: list[RunResult]) -> dict:
    """Table I's cells over the pooled steps of some runs, plus convergence over the runs and ellipse coverage."""
    trans = np.concatenate([r.trans_err_m for r in runs])
    orient = np.concatenate([r.orient_err_deg for r in runs])
    room = np.concatenate([r.room_hit for r in runs])
    storey = [r.storey_hit for r in runs if r.storey_hit is not None]
    after_change = [r.storey_hit_after_change for r in runs if r.storey_hit_after_change is not None]
    converged = [r.metrics["steps_to_converge"] for r in runs]
    # After convergence: the steps after each run's convergence step, pooled as every other cell pools its steps
    # (a run that converged on its last scored step counts for that step, not as much as a run of 45 such steps).
    after = [(r.trans_err_m[k:], r.orient_err_deg[k:]) for r, k in zip(runs, converged, strict=True) if k is not None]
    conv_trans = np.concatenate([t for t, _ in after]) if after else None
    conv_orient = np.concatenate([o for _, o in after]) if after else None
    icp: dict = {}
    if runs and all(r.icp_accepted is not None for r in runs):
        registered = np.concatenate([r.icp_accepted for r in runs if r.icp_accepted is not None])
        rejections: Counter[str] = Counter()
        for r in runs:
            rejections.update(r.icp_rejections or {})
        icp = {
            "icp_accepted_share": float(registered.mean()) if len(registered) else None,
            "icp_rejections": dict(rejections.most_common()),
        }
    twin: dict = {}
    if runs and all(r.trans_err_twin_m is not None for r in runs):
        twin = {
            "trans_err_up_to_twin_m": float(np.concatenate([r.trans_err_twin_m for r in runs]).mean()),
            "orient_err_up_to_twin_deg": float(np.concatenate([r.orient_err_twin_deg for r in runs]).mean()),
        }
    return {
        "trans_err_m": float(trans.mean()),
        "trans_err_std_m": float(trans.std()),
        "orient_err_deg": float(orient.mean()),
        "orient_err_std_deg": float(orient.std()),
        "room_acc": float(room.mean()),
        "room_acc_std": float(room.std()),
        **({"storey_acc": float(np.concatenate(storey).mean())} if storey else {}),
        **({"storey_acc_after_change": float(np.concatenate(after_change).mean())} if after_change else {}),
        "step_ms_median": float(np.median(np.concatenate([r.step_ms for r in runs]))),
        "steps_to_converge": converged,
        "scored_from_steps": [r.scored_from for r in runs],
        "converged_runs": sum(c is not None for c in converged),
        "runs": len(runs),
        "relocalized_runs": sum(r.relocalizations > 0 for r in runs),
        "challenged_runs": sum(r.challenges > 0 for r in runs),
        **_kidnap_counts(runs),
        "trans_err_conv_m": None if conv_trans is None else float(conv_trans.mean()),
        "orient_err_conv_deg": None if conv_orient is None else float(conv_orient.mean()),
        "trans_err_conv_run_mean_m": float(np.mean([t.mean() for t, _ in after])) if after else None,
        "ellipse_coverage": float(np.concatenate([r.inside_ellipse95 for r in runs]).mean()),
        **icp,
        **twin,
        **_outcomes(runs),
        **_from_start(runs),
        **_by_step(runs),
    }


def _outcomes(runs: list[RunResult]) -> dict:
    """The routes' outcomes over runs (`RouteOutcome`): success and wrong-convergence rates, the median distance and
    keyframes to correct convergence over the runs that got there (with how many did), and the top-3 rate over every
    step (None for a variant without modes)."""
    outcomes = [r.outcome for r in runs if r.outcome is not None]
    if not outcomes:
        return {}
    distances = [o.distance_to_convergence_m for o in outcomes if np.isfinite(o.distance_to_convergence_m)]
    keyframes = [o.keyframes_to_convergence for o in outcomes if np.isfinite(o.keyframes_to_convergence)]
    top3 = [o.top3_share for o in outcomes if np.isfinite(o.top3_share)]
    return {
        "success_rate": float(np.mean([o.success for o in outcomes])),
        "wrong_convergence_rate": float(np.mean([o.wrong_convergence for o in outcomes])),
        "distance_to_convergence_m": float(np.median(distances)) if distances else None,
        "keyframes_to_convergence": float(np.median(keyframes)) if keyframes else None,
        "correctly_converged_runs": len(distances),
        "top3_rate": float(np.mean(top3)) if top3 else None,
    }


def _from_start(runs: list[RunResult]) -> dict:
    """Scored from the filter's convergence: Table I's cells over the first T steps of the same runs as well."""
    if not runs or any(r.from_start is None for r in runs):
        return {}
    trans, orient, room = (
        np.concatenate([getattr(r.from_start, name) for r in runs])
        for name in ("trans_err_m", "orient_err_deg", "room_hit")
    )
    return {
        "from_start": {
            "trans_err_m": float(trans.mean()),
            "trans_err_std_m": float(trans.std()),
            "orient_err_deg": float(orient.mean()),
            "orient_err_std_deg": float(orient.std()),
            "room_acc": float(room.mean()),
        }
    }


def _kidnap_counts(runs: list[RunResult]) -> dict:
    """Kidnap scenario: how many runs were tracking when carried off, the translation error before it (over all
    steps from the first), and the median steps to recover over the runs that recovered (`steps_to_converge` of the
    scored steps after it)."""
    if not runs or any(r.tracking_before is None for r in runs):
        return {}
    recovered = [r.metrics["steps_to_converge"] for r in runs if r.metrics["steps_to_converge"] is not None]
    return {
        "tracking_before_kidnap_runs": sum(bool(r.tracking_before) for r in runs),
        "trans_err_before_kidnap_m": float(np.mean([r.trans_err_before_m for r in runs])),
        "steps_to_recover_median": float(np.median(recovered)) if recovered else None,
    }


def _confidence_intervals(runs: list[RunResult]) -> dict:
    """95 % bootstrap intervals of the average's translation, orientation and room accuracy, runs resampled."""
    if len(runs) < 2:
        return {}
    return {
        "trans_err_ci95_m": list(run_bootstrap_ci([r.trans_err_m for r in runs])),
        "orient_err_ci95_deg": list(run_bootstrap_ci([r.orient_err_deg for r in runs])),
        "room_acc_ci95": list(run_bootstrap_ci([r.room_hit for r in runs])),
    }


def _by_step(runs: list[RunResult]) -> dict:
    """Mean over the runs at each step (runs of one length): where in a run the average's error comes from."""
    if not runs or len({len(r.trans_err_m) for r in runs}) != 1:
        return {}
    return {
        "trans_err_by_step_m": np.mean([r.trans_err_m for r in runs], axis=0).tolist(),
        "orient_err_by_step_deg": np.mean([r.orient_err_deg for r in runs], axis=0).tolist(),
        "room_acc_by_step": np.mean([r.room_hit for r in runs], axis=0).tolist(),
    }


def check_protocol(cfg: Config) -> None:
    """ConfigError for settings the protocol cannot take: every run starts as its scenario says."""
    if cfg.smcl.start.pose is not None:
        raise ConfigError(
            "bench paper starts every run as evaluation.scenario says (a pose guess per run with --scenario guess); "
            "smcl.start.pose is one pose guess for one sequence (bimfactor localize --initial-pose)"
        )
    if cfg.smcl.start.storeys is not None:
        raise ConfigError(
            "bench paper starts every run as evaluation.scenario says (on its own storey with "
            "evaluation.known_storey); smcl.start.storeys is one sequence's (bimfactor localize --storey)"
        )


RUNNERS = ("processes", "ray")
"""Where the protocol's runs go: a local process pool (one worker per CPU; one worker runs in this process), or Ray
(a local Ray instance, or the cluster at an address)."""


RAY_ADDRESS = re.compile(r"^(auto|local|(ray://)?[A-Za-z0-9_.\-]+:\d{1,5})$")
"""What `ray.init(address=...)` takes: auto, local, HOST:PORT of a cluster's head, or ray://HOST:PORT (Ray Client)."""


CLUSTER_ANSWER_S = 30.0
"""How long a cluster given by `--address` has to accept a driver before the benchmark says it cannot reach it."""
_PROBE = "import sys; from bimfactor.evaluation.paper import probe_cluster; probe_cluster(sys.argv[1])"


def probe_cluster(address: str) -> None:
    """Connect to the cluster at `address` and leave (`check_cluster`'s child process): exit 0, or the error's one
    line on stderr and its exit code."""
    from bimfactor.errors import BimfactorError

    try:
        with ray_session(None, address):
            pass
    except BimfactorError as exc:
        print(exc, file=sys.stderr)
        sys.exit(exc.exit_code)


def _use_cluster_token() -> None:
    """Authenticate to a cluster the way Ray's own CLI does: with RAY_AUTH_MODE unset, a token in RAY_AUTH_TOKEN,
    RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token (what `ray start` writes, Ray ≥ 2.5x) turns token mode on."""
    try:
        from ray._private.authentication import authentication_token_setup as setup
    except ImportError:  # a Ray without token authentication
        return
    logging.getLogger(setup.__name__).setLevel(logging.ERROR)  # no notice that token mode is on
    setup.maybe_enable_token_auth_if_token_available(warn_if_disabled=False)


def runner_description(runner: str, address: str | None, workers: int | None) -> str:
    """Where the runs go, in words, for the benchmark's first lines and its results.json."""
    if runner == "processes":
        return f"a local process pool ({workers or os.cpu_count() or 1} workers)"
    if address is None:
        return "a Ray instance of its own (RAY_ADDRESS and earlier clusters' session files are ignored)"
    return f"the Ray cluster at {address}"


def check_cluster(address: str) -> None:
    """InputError unless the Ray cluster at `address` accepts a driver within `CLUSTER_ANSWER_S`: a closed port, an
    address that is no Ray head, `auto` with no cluster running (`ray start --head`), a head that hangs.
    DependencyError for `ray://` without Ray Client. Tried in a child process, which is killed when it hangs, so the
    benchmark learns it in seconds, before any prior is built."""
    import socket
    import subprocess

    from bimfactor.errors import DependencyError

    if address != "auto":  # a closed port or an unknown host is told at once, not after Ray's retries
        host, _, port = address.removeprefix("ray://").rpartition(":")
        try:
            socket.create_connection((host, int(port)), timeout=CLUSTER_ANSWER_S).close()
        except OSError as exc:
            raise InputError(f"--address {address}: nothing answers there ({exc.__class__.__name__}: {exc})") from exc
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE, address], capture_output=True, text=True, timeout=CLUSTER_ANSWER_S
        )
    except subprocess.TimeoutExpired as exc:
        raise InputError(f"--address {address}: the Ray cluster did not answer within {CLUSTER_ANSWER_S:g} s") from exc
    if done.returncode == 0:
        return
    said = [line for line in done.stderr.splitlines() if line.startswith(f"--address {address}")]  # probe_cluster's
    why = said[-1] if said else f"--address {address}: no Ray cluster answers there (exit {done.returncode})"
    raise (DependencyError if done.returncode == DependencyError.exit_code else InputError)(why)


def check_runner(runner: str, address: str | None = None) -> None:
    """ConfigError for a runner not in `RUNNERS`, an `address` that is no Ray address (`RAY_ADDRESS`), or an address
    given to a runner other than Ray."""
    if runner not in RUNNERS:
        raise ConfigError(f"unknown runner '{runner}' (known: {', '.join(RUNNERS)})")
    if address is None:
        return
    if runner != "ray":
        raise ConfigError(f"--address {address} names a Ray cluster; it applies to --runner ray, not {runner}")
    if not RAY_ADDRESS.match(address):
        raise ConfigError(f"--address {address!r}: expected ray://HOST:PORT, HOST:PORT or auto")


Job = tuple[str, str, int, int, dict, str | None]
"""One run of the protocol: `_run_one`'s arguments (prior folder, config as JSON, trajectory, repeat, twins, the
folder of its Rerun recordings or None)."""


def paper_jobs(
    prior_dir: str | Path, cfg: Config, twins: dict[int, Motion], rerun_dir: str | Path | None = None
) -> list[Job]:
    """The protocol's runs on one prior: every trajectory × repeat; each recorded into `rerun_dir` when given."""
    ev, cfg_json = cfg.evaluation, cfg.model_dump_json()
    rerun = None if rerun_dir is None else str(rerun_dir)
    return [
        (str(prior_dir), cfg_json, k, r, twins, rerun) for k in range(ev.num_trajectories) for r in range(ev.repeats)
    ]


RAY_TASK_RETRIES = 3
"""How often Ray runs a run again whose worker or node died (or whose result was lost with its node)."""


def run_jobs(
    jobs: list[Job],
    desc: str,
    runner: str = "processes",
    workers: int | None = None,
    address: str | None = None,
    where: dict | None = None,
    names: list[str] | None = None,
) -> list[list[RunResult]]:
    """Each job's `_run_one` results, in the jobs' order, whichever runner ran them (they do not depend on it). On
    Ray, `where` (when given) receives the nodes and CPUs there and how many runs each node ran (`runs_per_node`, by
    node id; each result's `node` says its own). A run lost with its node or worker is run again; runs still lost
    are a `RunsLostError` naming each (its job's building in `names`, default its prior folder, trajectory and
    repeat), raised once every other run is done."""
    check_runner(runner, address)
    if runner == "ray":
        results, lost = _ray_jobs(jobs, desc, workers, address, where if where is not None else {})
    else:
        results, lost = _pool_jobs(jobs, desc, workers)
    if lost:
        raise _runs_lost(jobs, lost, names, runner)
    return results


def _pool_jobs(jobs: list[Job], desc: str, workers: int | None) -> tuple[list[list[RunResult]], dict[int, str]]:
    """`run_jobs` on a local process pool: the results, and the jobs lost with a process that died (by index)."""
    from concurrent.futures.process import BrokenProcessPool

    workers = workers or min(len(jobs), os.cpu_count() or 1)
    if workers == 1:  # in this process: no worker start-up (imports, the sentence encoder) to pay for
        return [_run_one(*job) for job in progress(jobs, desc=desc, unit="run")], {}
    results: list[list[RunResult]] = [[] for _ in jobs]
    lost: dict[int, str] = {}
    # spawn, not fork: the parent already runs torch / Open3D threads, and a forked child can deadlock on them
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(_run_one, *job) for job in jobs]
        for i, future in enumerate(progress(futures, desc=desc, unit="run")):
            try:
                results[i] = future.result()
            except BrokenProcessPool:  # a worker process died (killed, out of memory): this run and the ones after
                lost[i] = "BrokenProcessPool"
    return results, lost


def _runs_lost(jobs: list[Job], lost: dict[int, str], names: list[str] | None, runner: str) -> RunsLostError:
    """The error that names the lost runs (at most `SHOWN_LOST` of them) and why they were lost."""
    shown = [
        f"{names[i] if names is not None else jobs[i][0]} trajectory {jobs[i][2]} repeat {jobs[i][3]}"
        for i in sorted(lost)[:SHOWN_LOST]
    ]
    more = f" and {len(lost) - SHOWN_LOST} more" if len(lost) > SHOWN_LOST else ""
    why = ", ".join(f"{kind} ×{n}" if n > 1 else kind for kind, n in Counter(lost.values()).most_common())
    how = (
        f"the node or worker running each died on every try, {RAY_TASK_RETRIES} retries included"
        if runner == "ray"
        else "a worker process of the pool died"
    )
    return RunsLostError(
        f"{len(lost)} of {len(jobs)} runs lost: {'; '.join(shown)}{more} ({why}: {how}); no results written",
        sorted(lost),
    )


SHOWN_LOST = 10
"""How many lost runs the error names one by one."""


@contextlib.contextmanager
def ray_session(workers: int | None = None, address: str | None = None) -> Iterator[dict]:
    """Ray, connected for the block: an instance of its own with `workers` CPUs (default: all) when `address` is None,
    whatever RAY_ADDRESS or a dead cluster's session file says (Ray's "local"), else the cluster at `address`, whose
    nodes must have bimfactor installed and see the prior folders at the same paths (a shared file system). Yields
    the nodes and CPUs it has. A cluster that does not answer is an InputError (Ray gives up after about 20 s). A
    session already connected is used as it is, and left connected."""
    from bimfactor.errors import DependencyError

    try:
        import ray
    except ImportError as exc:
        raise DependencyError("the Ray runner needs Ray: pip install ray (or --runner processes)") from exc
    started_here = not ray.is_initialized()
    if started_here:
        if address is not None:
            _use_cluster_token()
        try:
            with _stderr_muted():  # Ray's core logs each retry against an address that does not answer
                ray.init(
                    address=address or "local",
                    num_cpus=None if address else workers,
                    include_dashboard=False,
                    log_to_driver=False,
                    logging_level=logging.ERROR,
                )
        except ConnectionError as exc:
            raise InputError(f"--address {address}: no Ray cluster answers there ({exc})") from exc
        except ValueError as exc:
            if "ray[client]" in str(exc):
                raise DependencyError(f"--address {address} needs Ray Client: pip install 'ray[client]'") from exc
            raise
    try:
        nodes = sum(1 for node in ray.nodes() if node.get("Alive"))
        cpus = int(ray.cluster_resources().get("CPU", 0))
        log.info("Ray: %d node(s), %d CPUs", nodes, cpus)
        yield {"nodes": nodes, "cpus": cpus}
    finally:
        if started_here:
            ray.shutdown()


@contextlib.contextmanager
def _stderr_muted() -> Iterator[None]:
    """File descriptor 2 goes to /dev/null for the block (C++ libraries write there, not to sys.stderr)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _ray_jobs(
    jobs: list[Job], desc: str, workers: int | None, address: str | None, where: dict
) -> tuple[list[list[RunResult]], dict[int, str]]:
    """`run_jobs` on Ray (`ray_session`): the results, and the jobs whose tasks failed every retry (by index, with
    the last failure's kind). A run's own exception (a RayTaskError) is raised as it is."""
    import ray
    from ray.exceptions import RayError, RayTaskError

    with ray_session(workers, address) as session:
        where.update(session)
        remote = ray.remote(num_cpus=1, max_retries=RAY_TASK_RETRIES)(_run_one_on_ray)
        refs = [remote.remote(*job) for job in jobs]
        order = {ref: i for i, ref in enumerate(refs)}
        results: list[list[RunResult]] = [[] for _ in jobs]
        lost: dict[int, str] = {}
        pending = list(refs)
        bar = progress(range(len(refs)), desc=desc, unit="run")
        for _ in bar:
            done, pending = ray.wait(pending, num_returns=1)
            i = order[done[0]]
            try:
                results[i] = ray.get(done[0])
            except RayTaskError:
                raise
            except RayError as exc:  # its worker or node died (or its result was lost) on every try
                lost[i] = type(exc).__name__
        nodes = Counter(runs[0].node for runs in results if runs)
        where["runs_per_node"] = dict(sorted(nodes.items()))
        return results, lost


def run_paper_bench(prior_dir: str | Path, cfg: Config, out_dir: str | Path, workers: int | None = None) -> dict:
    """Run the protocol on a prior's building; writes OUT/results.json, OUT/config.yaml and OUT/error_by_step.png;
    returns the report."""
    check_protocol(cfg)
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.symmetry import twin_motions
    from bimfactor.evaluation.plots import save_error_by_step_plot  # matplotlib: not in the workers' start-up

    prior = BimPrior.load(prior_dir)
    twins = twin_motions(prior)  # once here, not in every run
    desc = f"bench paper ({', '.join(cfg.evaluation.variants)})"
    results = [r for runs in run_jobs(paper_jobs(prior_dir, cfg, twins), desc, workers=workers) for r in runs]
    report = paper_report(prior_dir, prior, cfg, twins, results)
    out = Path(out_dir)
    write_text_atomic(out / "config.yaml", cfg.dump_yaml())
    write_text_atomic(out / "results.json", json.dumps(report, indent=2))
    save_error_by_step_plot(report, out / "error_by_step.png")
    return report


def paper_report(
    prior_dir: str | Path, prior: BimPrior, cfg: Config, twins: dict[int, Motion], results: list[RunResult]
) -> dict:
    """The protocol's report of one building from its runs' results: per variant the average over every run (with
    bootstrap intervals) and each trajectory's."""
    ev = cfg.evaluation
    report: dict = {
        "benchmark": "paper",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "prior": str(prior_dir),
        "protocol": {
            "trajectories": ev.num_trajectories,
            "steps": ev.trajectory_length,
            "repeats": ev.repeats,
            "score_from": "filter_converged" if ev.scores_from_convergence else "start",
            "warmup_max_steps": ev.warmup_steps,
            "scenario": ev.scenario,
            **({"known_storey": True} if ev.known_storey else {}),
            **(
                {"guess_offset_m": ev.guess_offset_m, "guess_offset_deg": ev.guess_offset_deg}
                if ev.scenario == "guess"
                else {}
            ),
            **({"kidnap_at": ev.kidnap_at, "kidnap_resume_at": ev.kidnap_resume_at} if ev.scenario == "kidnap" else {}),
        },
        "variants": reported_variants(ev),
        "storeys": len(prior.storeys),
        "twins": {storey: motion.describe() for storey, motion in twins.items()},
    }
    for variant in reported_variants(ev):
        runs = [r for r in results if r.variant == variant]
        report[variant] = {
            "average": {**_pooled(runs), **_confidence_intervals(runs)},
            "per_trajectory": {k: _pooled([r for r in runs if r.trajectory == k]) for k in range(ev.num_trajectories)},
        }
    return report


def format_table_one(report: dict, variant: str) -> str:
    """Table I of one variant as text: per trajectory and the average, mean ± std over steps, with convergence
    and the 95 % ellipse coverage."""
    lines = [
        f"{variant}",
        f"{'Traj':<6}{'Trans. (m)':>16}{'Orient. (°)':>18}{'Room Acc. (%)':>18}{'converged':>12}{'cov95 (%)':>11}",
    ]

    def row(name: str, cell: dict) -> str:
        return (
            f"{name:<6}{cell['trans_err_m']:>9.2f} ± {cell['trans_err_std_m']:<4.2f}"
            f"{cell['orient_err_deg']:>10.1f} ± {cell['orient_err_std_deg']:<5.1f}"
            f"{100 * cell['room_acc']:>10.1f} ± {100 * cell['room_acc_std']:<5.1f}"
            f"{cell['converged_runs']:>8}/{cell['runs']}"
            f"{100 * cell['ellipse_coverage']:>10.0f}"
        )

    for k, cell in report[variant]["per_trajectory"].items():
        lines.append(row(str(int(k) + 1), cell))
    average = report[variant]["average"]
    lines.append(row("Avg.", average))
    lines.extend(table_notes(report, variant))
    return "\n".join(lines)


def table_notes(report: dict, variant: str) -> list[str]:
    """The lines under a variant's Table I: bootstrap intervals, storey and twin accuracy, kidnap recovery,
    relocalizations, challenger hand-overs, where scoring began, and the same runs from their first frame."""
    average, lines = report[variant]["average"], []
    if "trans_err_ci95_m" in average:
        (t0, t1), (o0, o1), (r0, r1) = (
            average["trans_err_ci95_m"],
            average["orient_err_ci95_deg"],
            average["room_acc_ci95"],
        )
        lines.append(
            f"95 % interval of the average (bootstrap over the {average['runs']} runs): "
            f"{t0:.2f}–{t1:.2f} m, {o0:.1f}–{o1:.1f}°, {100 * r0:.1f}–{100 * r1:.1f} %"
        )
    if report.get("storeys", 1) > 1 and "storey_acc" in average:
        lines.append(f"on the true storey: {100 * average['storey_acc']:.1f} % of the steps")
    if "trans_err_up_to_twin_m" in average:
        storeys = ", ".join(str(k) for k in report.get("twins", {}))
        lines.append(
            f"up to the building's twin places (storeys {storeys}; the motions are results.json's twins): "
            f"{average['trans_err_up_to_twin_m']:.2f} m, {average['orient_err_up_to_twin_deg']:.1f}°"
        )
    if "tracking_before_kidnap_runs" in average:
        median = average["steps_to_recover_median"]
        lines.append(
            f"kidnapped: {average['tracking_before_kidnap_runs']} of {average['runs']} runs were tracking when carried "
            f"off ({average['trans_err_before_kidnap_m']:.2f} m on average before it); {average['converged_runs']} "
            f"recovered (within 1 m and 15° to the end), in a median {'–' if median is None else f'{median:g}'} steps"
        )
    if average.get("relocalized_runs"):
        lines.append(f"the filter spread its particles over the building again in {average['relocalized_runs']} runs")
    if average.get("challenged_runs"):
        lines.append(
            f"the belief moved to a challenger that explained the frames better in {average['challenged_runs']} runs"
        )
    starts = average.get("scored_from_steps", [])
    if report.get("protocol", {}).get("score_from") == "filter_converged" and any(starts):
        lines.append(
            f"scored from the step the filter first reported itself converged: median step {np.median(starts):g} "
            f"(range {min(starts)}–{max(starts)}) of the {average['runs']} runs"
        )
    if "from_start" in average:
        first = average["from_start"]
        lines.append(
            f"the same runs from their first frame (the uniform cloud included): {first['trans_err_m']:.2f} m, "
            f"{first['orient_err_deg']:.1f}°, {100 * first['room_acc']:.1f} %"
        )
    return lines


def format_tables(report: dict) -> str:
    """Table I of every variant in the report, one after the other."""
    return "\n\n".join(format_table_one(report, variant) for variant in report["variants"])
