"""Figures: floor plans of a prior (rooms by type, doors, labelled objects)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes

from bimfactor.io.atomic import atomic_path

if TYPE_CHECKING:
    from bimfactor.bim.prior import BimPrior


def draw_floorplan(ax: Axes, prior: BimPrior, storey_index: int, label_objects: bool = True) -> None:
    """Rooms coloured and named by type, walls black, furniture grey, doors, object labels."""
    layers = prior.storeys[storey_index]
    labels = layers.room_labels
    rgb = np.ones((*labels.shape, 3))
    rooms = [r for r in prior.rooms if r.storey_index == storey_index]
    cmap = plt.get_cmap("tab20")
    for k, room in enumerate(rooms):
        rgb[labels == room.id] = 0.55 + 0.45 * np.asarray(cmap(k % 20)[:3])
    rgb[layers.furniture] = (0.62, 0.62, 0.62)
    rgb[layers.structure] = (0.1, 0.1, 0.1)
    ax.imshow(rgb, origin="lower", extent=prior.grid.extent, interpolation="nearest")
    for room in rooms:
        name = room.category + (f"\n({room.space_name})" if room.space_name else "")
        ax.text(
            *room.centroid_xy,
            name,
            ha="center",
            va="center",
            fontsize=7,
            weight="bold",
            clip_on=True,
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "alpha": 0.7, "lw": 0},
        )
    for door in (d for d in prior.doors if d.storey_index == storey_index):
        c, a = np.asarray(door.center_xy), np.asarray(door.axis_xy) * door.width_m / 2
        ax.plot(
            *np.stack([c - a, c + a]).T,
            color="tab:green" if door.connects else "tab:red",
            lw=2.5,
            ls="-" if door.kind == "door" else ":",
        )
    objects = [o for o in prior.objects if o.storey_index == storey_index and o.label not in ("door",)]
    if objects:
        xy = np.asarray([o.position_m[:2] for o in objects])
        ax.scatter(xy[:, 0], xy[:, 1], s=8, c="tab:blue", zorder=3)
        if label_objects and len(objects) <= 150:
            for o in objects:
                ax.annotate(
                    o.label,
                    o.position_m[:2],
                    fontsize=5,
                    annotation_clip=True,
                    color="navy",
                    xytext=(2, 2),
                    textcoords="offset points",
                )
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def save_floorplans(prior: BimPrior, out_dir: str | Path) -> list[Path]:
    """One PNG per storey, `floorplan_<index>.png`, sized to the building."""
    out_dir = Path(out_dir)
    paths = []
    x0, x1, y0, y1 = prior.grid.extent
    aspect = (y1 - y0) / max(x1 - x0, 1e-6)
    for layers in prior.storeys:
        fig, ax = plt.subplots(figsize=(10, max(3.0, min(10 * aspect, 14))))
        draw_floorplan(ax, prior, layers.storey.index)
        n_rooms = sum(r.storey_index == layers.storey.index for r in prior.rooms)
        ax.set_title(
            f"{Path(prior.source_file).name} — {layers.storey.name} "
            f"({layers.storey.elevation_m:+.2f} m), {n_rooms} rooms"
        )
        path = out_dir / f"floorplan_{layers.storey.index}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=130, bbox_inches="tight", format="png")
        plt.close(fig)
        paths.append(path)
    return paths


def save_trajectory_plot(
    prior: BimPrior,
    storey_index: int,
    path: str | Path,
    gt_dense_xy: np.ndarray,
    keyframe_poses: np.ndarray,
    odom_poses: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """The drive over the floor plan: dense ground truth (N, 2), keyframes (T, 3) with heading ticks, and the
    odometry (T, 3) anchored at the first keyframe's true pose, so its drift shows."""
    from bimfactor.types import se2_between, se2_compose

    x0, x1, y0, y1 = prior.grid.extent
    aspect = (y1 - y0) / max(x1 - x0, 1e-6)
    fig, ax = plt.subplots(figsize=(10, max(3.0, min(10 * aspect, 14))))
    draw_floorplan(ax, prior, storey_index, label_objects=False)
    ax.plot(gt_dense_xy[:, 0], gt_dense_xy[:, 1], color="black", lw=1.2, label="ground truth")
    kf = np.asarray(keyframe_poses)
    ax.quiver(
        kf[:, 0],
        kf[:, 1],
        np.cos(kf[:, 2]),
        np.sin(kf[:, 2]),
        color="tab:orange",
        scale=40,
        width=0.003,
        label="keyframes",
    )
    if odom_poses is not None and len(odom_poses):
        anchored = se2_compose(kf[0], se2_between(np.asarray(odom_poses)[0], np.asarray(odom_poses)))
        ax.plot(
            anchored[:, 0], anchored[:, 1], "--", color="tab:purple", lw=1.2, label="odometry (from the true start)"
        )
    ax.plot(*kf[0, :2], "o", color="tab:green", ms=8, label="start")
    ax.plot(*kf[-1, :2], "s", color="tab:red", ms=8, label="end")
    # zoom onto the drive with a margin, keeping the building's context
    lo, hi = gt_dense_xy.min(axis=0) - 4.0, gt_dense_xy.max(axis=0) + 4.0
    ax.set_xlim(max(lo[0], x0), min(hi[0], x1))
    ax.set_ylim(max(lo[1], y0), min(hi[1], y1))
    ax.legend(loc="upper right", fontsize=7)
    ax.set_title(title)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)
    return path
