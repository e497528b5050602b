"""The paper's evaluation metrics (Sec. III.A, Eq. 5) and what a pose prior's users also need.

One function per metric, shared by the CLI and the library. Errors are per step; a trajectory is summarised
as mean ± std over its steps, as Table I does.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from bimfactor.types import wrap_angle

if TYPE_CHECKING:
    from bimfactor.bim.symmetry import Motion

CONVERGED_TRANS_M = 1.0
CONVERGED_ORIENT_DEG = 15.0


def translation_errors_m(estimates: np.ndarray, ground_truth: np.ndarray) -> np.ndarray:
    """(T,) ‖xy − x̂ŷ‖ per step for (T, 3) poses."""
    return np.hypot(*(np.asarray(estimates)[:, :2] - np.asarray(ground_truth)[:, :2]).T)


def orientation_errors_deg(estimates: np.ndarray, ground_truth: np.ndarray) -> np.ndarray:
    """(T,) |yaw − ŷaw| per step in degrees, wrapped."""
    return np.rad2deg(np.abs(wrap_angle(np.asarray(estimates)[:, 2] - np.asarray(ground_truth)[:, 2])))


def errors_up_to_twin(
    estimates: np.ndarray, ground_truth: np.ndarray, storeys: np.ndarray, twins: dict[int, Motion]
) -> tuple[np.ndarray, np.ndarray]:
    """Per step, the translation (m) and orientation (°) errors against the true pose or its twin (the true storey's
    twin motion applied, `bim.symmetry.twin_motions`), whichever is nearer in position: a twin building's error
    apart from the choice between twins that nothing observed can make."""
    trans = translation_errors_m(estimates, ground_truth)
    orient = orientation_errors_deg(estimates, ground_truth)
    storeys = np.asarray(storeys)
    for storey, motion in twins.items():
        on = storeys == storey
        if not on.any():
            continue
        twin = motion.apply(ground_truth[on])
        twin_trans = translation_errors_m(estimates[on], twin)
        nearer = twin_trans < trans[on]
        orient[on] = np.where(nearer, orientation_errors_deg(estimates[on], twin), orient[on])
        trans[on] = np.minimum(twin_trans, trans[on])
    return trans, orient


def steps_to_converge(trans_err_m: np.ndarray, orient_err_deg: np.ndarray) -> int | None:
    """First step after which the error stays below 1 m and 15° to the end; None if it never does."""
    ok = (trans_err_m < CONVERGED_TRANS_M) & (orient_err_deg < CONVERGED_ORIENT_DEG)
    if not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 1) if len(bad) else 0


def inside_ellipse(
    estimates: np.ndarray, covariances: np.ndarray, ground_truth: np.ndarray, p: float = 0.95
) -> np.ndarray:
    """(T,) bool: does the true position lie inside the reported p-probability position ellipse of each step?"""
    d = np.asarray(ground_truth)[:, :2] - np.asarray(estimates)[:, :2]
    cov = np.asarray(covariances)[:, :2, :2] + 1e-9 * np.eye(2)
    m2 = np.einsum("ti,tij,tj->t", d, np.linalg.inv(cov), d)
    return m2 <= chi2_2dof_quantile(p)


def chi2_2dof_quantile(p: float) -> float:
    """The p-quantile of χ² with 2 degrees of freedom, the squared Mahalanobis radius of a p-probability position
    ellipse: closed-form −2 ln(1 − p) (scipy.stats costs a second to import)."""
    return float(-2.0 * np.log1p(-p))


def ellipse_coverage(
    estimates: np.ndarray, covariances: np.ndarray, ground_truth: np.ndarray, p: float = 0.95
) -> float:
    """Share of steps whose true position lies inside the reported p-probability position ellipse."""
    return float(np.mean(inside_ellipse(estimates, covariances, ground_truth, p)))


def run_bootstrap_ci(
    per_run: list[np.ndarray], level: float = 0.95, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean over all steps of some runs, resampling whole runs.

    A run's steps are not independent (a run that locks onto a wrong place is wrong for many steps), so the
    runs are the units: each resample draws as many runs as there are, with replacement, and takes the mean of
    their pooled steps. Deterministic for a given `seed`.
    """
    if not per_run:
        raise ValueError("run_bootstrap_ci needs at least one run")
    sums = np.array([float(np.sum(v)) for v in per_run])
    counts = np.array([len(v) for v in per_run], float)
    draws = np.random.default_rng(seed).integers(0, len(per_run), size=(resamples, len(per_run)))
    means = sums[draws].sum(axis=1) / np.maximum(counts[draws].sum(axis=1), 1.0)
    tail = 100 * (1 - level) / 2
    lo, hi = np.percentile(means, [tail, 100 - tail])
    return float(lo), float(hi)


@dataclass
class TrajectoryMetrics:
    """Table I's columns for one run plus convergence; errors in metres and degrees, room accuracy 0–1."""

    trans_err_m: float
    trans_err_std_m: float
    orient_err_deg: float
    orient_err_std_deg: float
    room_acc: float
    room_acc_std: float
    steps_to_converge: int | None
    trans_err_conv_m: float | None
    orient_err_conv_deg: float | None
    ellipse95_coverage: float
    step_ms_median: float

    def to_dict(self) -> dict:
        return asdict(self)


def trajectory_metrics(
    estimates: np.ndarray,
    ground_truth: np.ndarray,
    rooms_estimated: np.ndarray,
    rooms_true: np.ndarray,
    covariances: np.ndarray,
    step_ms: np.ndarray,
) -> TrajectoryMetrics:
    """Every metric of one localized trajectory (T steps)."""
    trans = translation_errors_m(estimates, ground_truth)
    orient = orientation_errors_deg(estimates, ground_truth)
    room_hit = (np.asarray(rooms_estimated) == np.asarray(rooms_true)).astype(float)
    k = steps_to_converge(trans, orient)
    return TrajectoryMetrics(
        trans_err_m=float(trans.mean()),
        trans_err_std_m=float(trans.std()),
        orient_err_deg=float(orient.mean()),
        orient_err_std_deg=float(orient.std()),
        room_acc=float(room_hit.mean()),
        room_acc_std=float(room_hit.std()),
        steps_to_converge=k,
        trans_err_conv_m=None if k is None else float(trans[k:].mean()),
        orient_err_conv_deg=None if k is None else float(orient[k:].mean()),
        ellipse95_coverage=ellipse_coverage(estimates, covariances, ground_truth),
        step_ms_median=float(np.median(step_ms)),
    )


WRONG_CONVERGENCE_M = 2.0
"""The filter says it has converged while its estimate is farther off than this (or on another storey): the dangerous
failure, a confident wrong answer (issue 43's `wrong_convergence_rate`)."""
TOP_MODES = 3


@dataclass(frozen=True)
class RouteOutcome:
    """How a whole route went, from its first frame: `success` at its last step (within 1 m and 15° of the truth on
    the true storey), `distance_to_convergence_m` the ground-truth distance travelled until the estimate was correct
    and stayed so to the end (NaN: never) and `keyframes_to_convergence` the keyframes until then, `wrong_convergence`
    whether the filter ever said converged while more than `WRONG_CONVERGENCE_M` off or on another storey,
    `top3_share` the share of steps at which one of the `TOP_MODES` most probable modes was correct (NaN: the variant
    has no modes)."""

    success: bool
    distance_to_convergence_m: float
    wrong_convergence: bool
    top3_share: float
    keyframes_to_convergence: float = float("nan")


def _correct(poses: np.ndarray, storeys: np.ndarray, gt_poses: np.ndarray, gt_storeys: np.ndarray) -> np.ndarray:
    """(T,) bool: within 1 m and 15° of the truth and on the true storey."""
    return (
        (translation_errors_m(poses, gt_poses) < CONVERGED_TRANS_M)
        & (orientation_errors_deg(poses, gt_poses) < CONVERGED_ORIENT_DEG)
        & (np.asarray(storeys) == np.asarray(gt_storeys))
    )


def route_outcome(
    poses: np.ndarray,
    storeys: np.ndarray,
    gt_poses: np.ndarray,
    gt_storeys: np.ndarray,
    converged: np.ndarray,
    modes: list[list] | None = None,
) -> RouteOutcome:
    """`RouteOutcome` of (T, 3) estimates on (T,) storeys against the truth, with the filter's (T,) converged flag and,
    for the graph variants, each step's modes (objects with `pose`, `storey` and `probability`)."""
    gt_poses, gt_storeys = np.asarray(gt_poses, float), np.asarray(gt_storeys)
    ok = _correct(poses, storeys, gt_poses, gt_storeys)
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(gt_poses[:, :2], axis=0).T))])
    distance = keyframes = float("nan")
    if len(ok) and ok[-1]:
        bad = np.flatnonzero(~ok)
        keyframes = float(bad[-1] + 1) if len(bad) else 0.0
        distance = float(travelled[int(keyframes)])
    far = (translation_errors_m(poses, gt_poses) > WRONG_CONVERGENCE_M) | (np.asarray(storeys) != gt_storeys)
    top3 = float("nan")
    if modes is not None and len(modes) == len(ok):
        hits = []
        for step, step_modes in enumerate(modes):
            best = sorted(step_modes, key=lambda m: -m.probability)[:TOP_MODES]
            hits.append(
                any(
                    _correct(
                        m.pose[None], np.array([m.storey]), gt_poses[step : step + 1], gt_storeys[step : step + 1]
                    )[0]
                    for m in best
                )
            )
        top3 = float(np.mean(hits)) if hits else float("nan")
    return RouteOutcome(
        success=bool(len(ok) and ok[-1]),
        distance_to_convergence_m=distance,
        wrong_convergence=bool(np.any(np.asarray(converged, bool) & far)),
        top3_share=top3,
        keyframes_to_convergence=keyframes,
    )
