"""What to check in a converted recording before localizing it: the camera mount and the odometry.

`recording_checks` measures the floor's height in the base frame (a wrong mount moves every depth point) and draws
`convert`'s checks.png: side and top views of a frame's depth points in the base frame, and the odometry in plan.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bimfactor.io.atomic import atomic_path
from bimfactor.io.preview import missing_glyphs_quiet
from bimfactor.io.sequence import Sequence
from bimfactor.localization.measurements.scan import DepthPoints

FLOOR_SEARCH_M = (-1.0, 1.0)  # the floor is looked for this far below and above z = 0 ...
FLOOR_RANGE_M = 4.0  # ... among the points this close to the robot
FLOOR_BIN_M = 0.02
FLOOR_MIN_SHARE = 0.05  # a floor is a layer holding at least this share of those points
FLOOR_TOLERANCE_M = 0.05  # a floor found further from z = 0 than this says the mount is wrong
MAX_POINTS_DRAWN = 20000
WALL_BAND_M = (0.1, 2.0)  # the top view shows what lies between these heights: walls, not floor or ceiling


@dataclass(frozen=True)
class FloorCheck:
    """Where a frame's floor lies in the base frame: `height_m` of the densest horizontal layer below the camera
    (None: no floor in view), and the frame it was measured on."""

    frame_index: int
    height_m: float | None

    def line(self) -> str:
        if self.height_m is None:
            return (
                f"mount check: no floor in view on frame {self.frame_index} (a level or high camera); check the "
                "side view in checks.png"
            )
        verdict = "ok" if abs(self.height_m) <= FLOOR_TOLERANCE_M else "WRONG MOUNT? expected 0 ± 0.05 m"
        return (
            f"mount check: the floor lies at z = {self.height_m:+.3f} m in the base frame on frame "
            f"{self.frame_index} ({verdict})"
        )


def floor_height(points_base: np.ndarray, camera_z_m: float) -> float | None:
    """The height (m) of the densest horizontal layer of (N, 3) base-frame points below the camera and near the
    robot, when it holds at least `FLOOR_MIN_SHARE` of them; None otherwise."""
    near = points_base[np.hypot(points_base[:, 0], points_base[:, 1]) <= FLOOR_RANGE_M]
    low = near[(near[:, 2] >= FLOOR_SEARCH_M[0]) & (near[:, 2] <= min(FLOOR_SEARCH_M[1], camera_z_m))]
    if len(low) == 0:
        return None
    edges = np.arange(FLOOR_SEARCH_M[0], FLOOR_SEARCH_M[1] + FLOOR_BIN_M, FLOOR_BIN_M)
    counts, edges = np.histogram(low[:, 2], bins=edges)
    best = int(np.argmax(counts))
    if counts[best] < FLOOR_MIN_SHARE * len(near):
        return None
    in_layer = low[(low[:, 2] >= edges[best] - FLOOR_BIN_M) & (low[:, 2] < edges[best + 1] + FLOOR_BIN_M), 2]
    return float(np.median(in_layer))


def recording_checks(sequence: Sequence, path_png: str | Path) -> list[str]:
    """Measure the floor's height on the middle frame, draw checks.png (side and top view of its depth points in the
    base frame, the odometry in plan); the report's lines. Atomic."""
    meta = sequence.meta
    frame = sequence[len(sequence) // 2]
    points = DepthPoints.of_frame(frame, meta).base
    camera = meta.T_base_camera[:3, 3]
    check = FloorCheck(frame.index, floor_height(points, float(camera[2])))
    odometry = sequence.odometry()

    fig = Figure(figsize=(13.5, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    side, top, plan = fig.subplots(1, 3)
    drawn = points[:: max(1, len(points) // MAX_POINTS_DRAWN)]
    axis = meta.T_base_camera[:3, 2]  # the optical axis in the base frame
    side.scatter(drawn[:, 0], drawn[:, 2], s=0.3, c="tab:blue", alpha=0.4)
    side.axhline(0.0, color="k", lw=1, label="z = 0 (the base frame's floor)")
    if check.height_m is not None:
        side.axhline(check.height_m, color="tab:red", ls="--", lw=1, label=f"floor found: {check.height_m:+.3f} m")
    side.plot([camera[0], camera[0] + axis[0]], [camera[2], camera[2] + axis[2]], "r-", lw=2, label="optical axis")
    side.plot(camera[0], camera[2], "r^", ms=8)
    side.set(xlabel="x forward (m)", ylabel="z up (m)", title=f"side view, frame {frame.index}")
    side.legend(fontsize=7, loc="upper right")
    side.set_aspect("equal", adjustable="datalim")
    walls = drawn[(drawn[:, 2] > WALL_BAND_M[0]) & (drawn[:, 2] < WALL_BAND_M[1])]
    top.scatter(walls[:, 0], walls[:, 1], s=0.3, c=walls[:, 2], cmap="viridis", alpha=0.5)
    top.plot(camera[0], camera[1], "r^", ms=8)
    top.set(xlabel="x forward (m)", ylabel="y left (m)", title="top view, 0.1-2 m up: walls straight?")
    top.set_aspect("equal", adjustable="datalim")
    if odometry is not None:
        plan.plot(odometry[:, 0], odometry[:, 1], "-", color="tab:green", lw=1)
        plan.plot(odometry[:, 0], odometry[:, 1], ".", color="tab:green", ms=3)
        plan.plot(odometry[0, 0], odometry[0, 1], "ko", ms=6, label="start")
        step = max(1, len(odometry) // 20)
        plan.quiver(
            odometry[::step, 0], odometry[::step, 1], np.cos(odometry[::step, 2]), np.sin(odometry[::step, 2]),
            angles="xy", scale_units="xy", scale=2.0, width=0.004, color="tab:green",
        )  # fmt: skip
        plan.legend(fontsize=7)
        travelled = float(np.sum(np.hypot(*np.diff(odometry[:, :2], axis=0).T)))
        plan.set_title(f"odometry in plan: {travelled:.1f} m over {len(odometry)} frames")
    else:
        plan.set_title("no odometry")
    plan.set(xlabel="x (m)", ylabel="y (m)")
    plan.set_aspect("equal", adjustable="datalim")
    fig.suptitle(f"{meta.name}: {check.line()}", fontsize=9)
    with missing_glyphs_quiet():
        fig.tight_layout()
        with atomic_path(Path(path_png)) as tmp:
            fig.savefig(tmp, format="png")
    return [check.line()]
