"""Figures: floor plans of a prior (rooms by type, doors, labelled objects)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from bimfactor.io.atomic import atomic_path
from bimfactor.io.preview import PNG_COMPRESSION, missing_glyphs_quiet

if TYPE_CHECKING:
    from bimfactor.active import Suggestion
    from bimfactor.bim.prior import BimPrior, Room


ROOM_LABEL = "room-label"  # the gid of a floor plan's room names, which `drop_colliding_labels` thins
OBJECT_LABEL = "object-label"  # ... and of its object labels, thinned after the room names


def drop_colliding_labels(fig: Figure) -> int:
    """Hide each room name, then each object label, that would overlap a label kept before it on its axes (room
    names come largest room first), or that lies outside its axes' view; the number hidden. Run once the axes have
    their final limits."""
    renderer = fig.canvas.get_renderer()
    hidden = 0
    for ax in fig.axes:
        view = ax.get_window_extent(renderer)
        placed = []
        labels = [t for gid in (ROOM_LABEL, OBJECT_LABEL) for t in ax.texts if t.get_gid() == gid]
        for text in (t for t in labels if t.get_visible()):
            box = text.get_window_extent(renderer).expanded(1.05, 1.1)
            inside = view.contains(*box.p0) and view.contains(*box.p1)
            if not inside or any(box.overlaps(other) for other in placed):
                text.set_visible(False)
                hidden += 1
            else:
                placed.append(box)
    return hidden


def save_figure(fig: Figure, path: str | Path, dpi: int = 120, tight: bool = True) -> Path:
    """Write a figure as PNG atomically and close it; room names that would collide are dropped first."""
    path = Path(path)
    drop_colliding_labels(fig)
    with missing_glyphs_quiet(), atomic_path(path) as tmp:
        fig.savefig(
            tmp,
            dpi=dpi,
            bbox_inches="tight" if tight else None,
            format="png",
            pil_kwargs={"compress_level": PNG_COMPRESSION},
        )
    plt.close(fig)
    return path


WALL_RGB, FURNITURE_RGB = (0.1, 0.1, 0.1), (0.62, 0.62, 0.62)  # a floor plan's structure and furniture
FLOORPLAN_MAX_PX = 500  # a floor plan is drawn from at most this many pixels a side (a figure panel is ~500 px)


def _block_max(codes: np.ndarray, extent: tuple, max_px: int) -> tuple[np.ndarray, tuple]:
    """The (H, W) grid reduced by whole k × k blocks to at most `max_px` a side, each block its largest code, and the
    extent of the padded grid. Codes rank what must stay visible (walls over furniture over rooms), so walls one
    cell thick survive; drawing the full grid (3 M cells on a large floor) took 0.5 s a panel."""
    k = int(np.ceil(max(codes.shape) / max_px))
    if k <= 1:
        return codes, extent
    (H, W), (x0, x1, y0, y1) = codes.shape, extent
    h, w = -(-H // k) * k, -(-W // k) * k
    padded = np.zeros((h, w), codes.dtype)
    padded[:H, :W] = codes
    reduced = padded.reshape(h // k, k, w).max(axis=1).reshape(h // k, w // k, k).max(axis=2)
    return reduced, (x0, x0 + (x1 - x0) * w / W, y0, y0 + (y1 - y0) * h / H)


def room_name(room: Room, sep: str = " ") -> str:
    """A room's name on a plan: its category, then its IfcSpace name in brackets when that says something else."""
    named = room.space_name and room.space_name.strip().lower() != room.category.lower()
    return room.category + (f"{sep}({room.space_name})" if named else "")


def draw_floorplan(
    ax: Axes, prior: BimPrior, storey_index: int, label_objects: bool = True, label_rooms: bool = True
) -> None:
    """Rooms coloured and named by type, walls black, furniture grey, doors, object labels."""
    layers = prior.storeys[storey_index]
    labels = layers.room_labels
    rooms = [r for r in prior.rooms if r.storey_index == storey_index]
    cmap = plt.get_cmap("tab20")
    # codes: 0 outside every room, 1…n the rooms, n + 1 furniture, n + 2 walls; a palette gives their colours
    n = len(rooms)
    room_code = np.zeros(int(max(labels.max(initial=-1), max((r.id for r in rooms), default=-1))) + 2, np.int32)
    room_code[[r.id + 1 for r in rooms]] = np.arange(1, n + 1)
    codes = room_code[np.clip(labels, -1, None) + 1]
    codes[layers.furniture] = n + 1
    codes[layers.structure] = n + 2
    palette = np.ones((n + 3, 3))
    palette[1 : n + 1] = 0.55 + 0.45 * np.asarray([cmap(k % 20)[:3] for k in range(n)]).reshape(-1, 3)
    palette[n + 1], palette[n + 2] = FURNITURE_RGB, WALL_RGB
    codes, extent = _block_max(codes, tuple(prior.grid.extent), FLOORPLAN_MAX_PX)
    ax.imshow(palette[codes], origin="lower", extent=extent, interpolation="nearest")
    for room in sorted(rooms, key=lambda r: -r.area_m2) if label_rooms else []:  # the largest kept in a collision
        ax.text(
            *room.centroid_xy,
            room_name(room, "\n"),
            ha="center",
            va="center",
            fontsize=7,
            weight="bold",
            clip_on=True,
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "alpha": 0.7, "lw": 0},
            gid=ROOM_LABEL,
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
                    gid=OBJECT_LABEL,
                )
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def floorplan_key() -> list:
    """Legend handles for what `draw_floorplan` draws (room colours are per room, named on the plan)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    return [
        Patch(fc=WALL_RGB, label="walls, columns (structure)"),
        Patch(fc=FURNITURE_RGB, label="furniture"),
        Patch(fc=(0.8, 0.88, 0.95), ec="0.6", label="a room (colour per room)"),
        Line2D([], [], color="tab:green", lw=2.5, label="door joining two places"),
        Line2D([], [], color="tab:green", lw=2.5, ls=":", label="doorway without a leaf"),
        Line2D([], [], color="tab:red", lw=2.5, label="door leading nowhere known"),
        Line2D([], [], ls="", marker="o", ms=4, color="tab:blue", label="labelled object"),
    ]


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
        floor = "" if layers.storey.is_floor else " (not a floor)"
        ax.set_title(
            f"{Path(prior.source_file).name} — {layers.storey.name} "
            f"({layers.storey.elevation_m:+.2f} m){floor}, {n_rooms} rooms"
        )
        ax.legend(handles=floorplan_key(), loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
        paths.append(save_figure(fig, out_dir / f"floorplan_{layers.storey.index}.png", dpi=130))
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
    zoom_to(ax, prior, storey_index, gt_dense_xy)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    ax.set_title(title)
    return save_figure(fig, path, dpi=120)


ZOOM_MARGIN_M = 4.0  # around the drive when a figure zooms onto it
INSET_BELOW = 0.6  # a zoomed map shows the whole storey in an inset when the zoom covers less of it than this
ERROR_TICKS = (0.0, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)  # metres, on the error axis's symlog scale


def zoom_to(ax: Axes, prior: BimPrior, storey_index: int, xy: np.ndarray) -> None:
    """Zoom `ax` (a floor plan of the storey) onto the (N, 2) points with `ZOOM_MARGIN_M`, and, when that leaves
    most of the storey out, draw the whole storey in an inset with the zoomed window marked."""
    from matplotlib.patches import Rectangle

    x0, x1, y0, y1 = prior.grid.extent
    xy = np.asarray(xy, float).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return
    lo, hi = xy.min(axis=0) - ZOOM_MARGIN_M, xy.max(axis=0) + ZOOM_MARGIN_M
    wx0, wx1, wy0, wy1 = max(lo[0], x0), min(hi[0], x1), max(lo[1], y0), min(hi[1], y1)
    ax.set_xlim(wx0, wx1)
    ax.set_ylim(wy0, wy1)
    if (wx1 - wx0) * (wy1 - wy0) >= INSET_BELOW * (x1 - x0) * (y1 - y0):
        return
    inset = ax.inset_axes((1.02, 0.0, 0.3, 0.3))  # beside the map, under the legend: it hides nothing
    draw_floorplan(inset, prior, storey_index, label_objects=False, label_rooms=False)
    inset.add_patch(Rectangle((wx0, wy0), wx1 - wx0, wy1 - wy0, fill=False, ec="tab:red", lw=1.2))
    inset.set_xlim(x0, x1)
    inset.set_ylim(y0, y1)
    inset.set_xticks([])
    inset.set_yticks([])
    inset.set_xlabel("")
    inset.set_ylabel("")
    inset.set_title("whole storey", fontsize=7)


def error_axis(ax: Axes) -> None:
    """A translation-error axis that reads at a glance: symlog (linear below 0.1 m), ticks at 0.03, 0.1, 0.3, 1, 3,
    ... metres labelled as plain numbers."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    ax.set_yscale("symlog", linthresh=0.1, linscale=0.5)
    top = max(ax.get_ylim()[1], 0.3)
    top = next((t for t in ERROR_TICKS if t >= top), top)  # up to a tick, so the largest error sits under one
    ax.set_ylim(0.0, top)
    ax.yaxis.set_major_locator(FixedLocator([t for t in ERROR_TICKS if t <= top]))
    ax.yaxis.set_minor_locator(NullLocator())
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.grid(True, axis="y", alpha=0.3)


def save_particle_snapshots(
    prior: BimPrior,
    snapshots: dict[int, tuple[np.ndarray, np.ndarray]],
    gt_poses: np.ndarray | None,
    estimates: np.ndarray,
    storey_index: int,
    path: str | Path,
) -> Path:
    """Like the paper's Fig. 2: particles over the floor plan at several steps, with the truth and the estimate."""
    steps = sorted(snapshots)
    cols = min(3, len(steps))
    rows = int(np.ceil(len(steps) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 4.5 * rows), squeeze=False)
    for ax, step in zip(axes.ravel(), steps, strict=False):
        particles, weights = snapshots[step]
        draw_floorplan(ax, prior, storey_index, label_objects=False)
        size = 2 + 60 * weights / max(float(weights.max()), 1e-12)
        ax.scatter(particles[:, 0], particles[:, 1], s=size, c="tab:purple", alpha=0.35, lw=0, zorder=4)
        if step >= 0:
            if gt_poses is not None:
                ax.plot(*gt_poses[step, :2], "*", color="tab:green", ms=14, zorder=5, label="truth")
            ax.plot(*estimates[step, :2], "X", color="tab:red", ms=10, zorder=5, label="estimate")
        ax.set_title("initial particles" if step < 0 else f"after step {step}")
        # Panels of one floor plan need no coordinates, a scale bar says how large it is; tick labels were half of
        # this figure's rendering time.
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel("")
        ax.set_ylabel("")
        _scale_bar(ax, prior.grid.extent)
    particles_key = plt.Line2D(
        [], [], ls="", marker="o", color="tab:purple", alpha=0.5, label="particles (size = weight)"
    )
    truth_key = plt.Line2D([], [], ls="", marker="*", color="tab:green", ms=12, label="truth")
    estimate_key = plt.Line2D([], [], ls="", marker="X", color="tab:red", ms=9, label="estimate")
    handles = [particles_key, *([truth_key] if gt_poses is not None else []), estimate_key]
    spare = axes.ravel()[len(steps) :]
    for ax in spare:
        ax.axis("off")
    if len(spare):  # the legend fills the first empty panel, so none is left empty
        spare[0].legend(handles=handles, loc="center", fontsize=10, frameon=False)
    else:
        fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=9, frameon=False)
    return save_figure(fig, path, dpi=110)


def _scale_bar(ax: Axes, extent: tuple) -> None:
    """A bar of a round length (about a fifth of the plan's width) under the panel's lower left corner, in metres: it
    hides nothing of the plan."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    width = float(extent[1] - extent[0])
    length = min((1, 2, 5, 10, 20, 50, 100, 200), key=lambda m: abs(m - width / 5))
    bar = AnchoredSizeBar(
        ax.transData, length, f"{length} m", "upper left", pad=0.1, sep=2, frameon=False,
        size_vertical=width / 150, fontproperties={"size": 8},
        bbox_to_anchor=(0.0, 0.0), bbox_transform=ax.transAxes,
    )  # fmt: skip
    ax.add_artist(bar)


def save_estimate_plot(
    prior: BimPrior,
    estimates: np.ndarray,
    gt_poses: np.ndarray | None,
    storey_index: int,
    path: str | Path,
    title: str,
    others: dict[str, np.ndarray] | None = None,
) -> Path:
    """Estimate against ground truth over the floor plan, and the error per step below it.

    `others` maps a name to another (T, 3) estimate of the same steps (e.g. the forward pass beside its
    refinement), drawn dashed with its translation error.
    """
    from bimfactor.evaluation.metrics import orientation_errors_deg, translation_errors_m

    others = others or {}
    other_colors = ("tab:gray", "tab:olive", "tab:cyan")
    fig, (ax, ax_err) = plt.subplots(2, 1, figsize=(9, 12), gridspec_kw={"height_ratios": [3, 1]})
    draw_floorplan(ax, prior, storey_index, label_objects=False)
    for (name, poses), color in zip(others.items(), other_colors, strict=False):
        ax.plot(poses[:, 0], poses[:, 1], "--", color=color, lw=1, label=name, zorder=5)
    ax.plot(estimates[:, 0], estimates[:, 1], ".-", color="tab:red", lw=1.5, ms=5, label="estimate", zorder=6)
    if gt_poses is not None:  # over the estimate: where they agree, the truth's thin line shows inside the estimate's
        ax.plot(gt_poses[:, 0], gt_poses[:, 1], "-", color="black", lw=0.9, label="ground truth", zorder=7)
    shown = [estimates[:, :2], *(p[:, :2] for p in others.values())]
    zoom_to(ax, prior, storey_index, np.concatenate(shown + ([gt_poses[:, :2]] if gt_poses is not None else [])))
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_title(title)
    if gt_poses is not None:
        for (name, poses), color in zip(others.items(), other_colors, strict=False):
            ax_err.plot(translation_errors_m(poses, gt_poses), "--", color=color, label=f"{name} [m]")
        ax_err.plot(translation_errors_m(estimates, gt_poses), color="tab:red", label="translation error [m]")
        ax_twin = ax_err.twinx()
        ax_twin.plot(orientation_errors_deg(estimates, gt_poses), color="tab:blue", label="orientation error [°]")
        error_axis(ax_err)
        ax_err.set_xlabel("step")
        ax_err.set_ylabel("translation error [m]", color="tab:red")
        ax_twin.set_ylabel("orientation error [°]", color="tab:blue")
        if others:
            ax_err.legend(loc="upper left", fontsize=7)
    else:
        ax_err.axis("off")
    return save_figure(fig, path, dpi=110)


def save_error_by_step_plot(report: dict, path: str | Path) -> Path | None:
    """Translation and orientation error per step, mean over every run, one line per variant (log scale)."""
    curves = {v: report[v]["average"] for v in report["variants"] if "trans_err_by_step_m" in report[v]["average"]}
    if not curves:
        return None
    fig, (ax_t, ax_o) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for variant, cell in curves.items():
        steps = np.arange(1, len(cell["trans_err_by_step_m"]) + 1)
        label = f"{variant} (avg {cell['trans_err_m']:.2f} m, {cell['orient_err_deg']:.1f}°)"
        ax_t.plot(steps, cell["trans_err_by_step_m"], ".-", lw=1, ms=3, label=label)
        ax_o.plot(steps, cell["orient_err_by_step_deg"], ".-", lw=1, ms=3, label=variant)
    ax_t.set_yscale("log")
    ax_o.set_yscale("log")
    ax_t.set_ylabel("translation error [m]")
    ax_o.set_ylabel("orientation error [°]")
    protocol = report.get("protocol", {})
    kidnapped = protocol.get("scenario") == "kidnap"
    converged = protocol.get("score_from") == "filter_converged"
    ax_o.set_xlabel(
        "keyframe after the robot was carried off"
        if kidnapped
        else "scored step (from the step the filter first reported itself converged)"
        if converged
        else "scored step (from the first frame)"
    )
    runs = next(iter(curves.values()))["runs"]
    scenario = {"kidnap": ", kidnapped robot", "guess": ", from a pose guess"}.get(protocol.get("scenario", ""), "")
    ax_t.set_title(f"Error per step, mean over {runs} runs{scenario}")
    ax_t.legend(fontsize=8)
    for ax in (ax_t, ax_o):
        ax.grid(True, which="both", alpha=0.3)
    return save_figure(fig, path)


def save_suggestion_figure(
    prior: BimPrior, suggestion: Suggestion, path: str | Path, title: str = "", truth: np.ndarray | None = None
) -> Path:
    """Where to look next (`active.Suggestion`): a panel per hypothesis (the four most probable), each its place over
    the floor plan with the route so far (the views already weighed) carried there, the candidate viewpoints coloured
    by expected gain, and the suggested path and goal; `truth` (3,), where known, marks the true pose."""
    from bimfactor.types import se2_compose, se2_inverse

    hyps = suggestion.hypotheses[:4]
    n = max(len(hyps), 1)
    cols = n if n <= 2 else 2
    fig, axes = plt.subplots(-(-n // cols), cols, figsize=(5.2 * cols, 5.2 * -(-n // cols)), squeeze=False)
    to_robot = se2_inverse(np.asarray(suggestion.odom_pose, float))
    relative = se2_compose(to_robot, suggestion.candidates_odom) if len(suggestion.candidates_odom) else None
    seen = se2_compose(to_robot, suggestion.seen_odom) if len(suggestion.seen_odom) else np.zeros((1, 3))
    scale = max(float(suggestion.gains_nats.max(initial=0.0)), 1e-6)
    points = None
    for k, (ax, h) in enumerate(zip(axes.ravel(), hyps, strict=False)):
        draw_floorplan(ax, prior, h.storey, label_objects=False)
        if relative is not None:
            c = se2_compose(h.pose, relative)
            order = np.argsort(suggestion.gains_nats)
            points = ax.scatter(c[order, 0], c[order, 1], c=suggestion.gains_nats[order], cmap="viridis", vmin=0,
                                vmax=scale, s=10, zorder=4)  # fmt: skip
        route = se2_compose(h.pose, seen)
        ax.plot(route[:, 0], route[:, 1], "o-", color="tab:purple", ms=5, lw=2.5, zorder=5)
        if suggestion.goal_odom is not None:
            path_odom = np.column_stack([suggestion.path_odom, np.zeros(len(suggestion.path_odom))])
            way = se2_compose(h.pose, se2_compose(to_robot, path_odom))
            goal = se2_compose(h.pose, se2_compose(to_robot, suggestion.goal_odom))
            ax.plot(way[:, 0], way[:, 1], color="tab:red", lw=2, zorder=5)
            ax.plot(*goal[:2], "o", color="tab:red", ms=9, mfc="white", mew=2, zorder=6)
            ax.quiver(*goal[:2], np.cos(goal[2]), np.sin(goal[2]), color="tab:red", scale=9, width=0.014, zorder=7)
        ax.quiver(*h.pose[:2], np.cos(h.pose[2]), np.sin(h.pose[2]), color="black", scale=12, width=0.012, zorder=7)
        if truth is not None:
            ax.plot(*truth[:2], "*", color="tab:green", mec="black", ms=15, zorder=8)
        reach = 2.0 + (suggestion.travel_m if suggestion.goal_odom is not None else 4.0) + 4.0
        ax.set_xlim(h.pose[0] - reach, h.pose[0] + reach)
        ax.set_ylim(h.pose[1] - reach, h.pose[1] + reach)
        here = truth is not None and np.hypot(*(np.asarray(truth[:2]) - h.pose[:2])) < 2.0
        storey = f", storey {h.storey}" if len(prior.storeys) > 1 else ""
        ax.set_title(f"place {k + 1}: p = {h.probability:.2f}{storey}{' (the true one)' if here else ''}", fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel("")
        ax.set_ylabel("")
        _scale_bar(ax, (*ax.get_xlim(), *ax.get_ylim()))
    for ax in axes.ravel()[len(hyps) :]:
        ax.axis("off")
    if points is not None:
        fig.colorbar(points, ax=list(axes.ravel()), fraction=0.03, pad=0.02, label="expected gain of a view [nats]")
    key = [
        plt.Line2D([], [], marker=">", ls="", color="black", ms=9, label="robot, if here"),
        plt.Line2D([], [], marker="o", color="tab:purple", ms=5, lw=2.5, label="route so far"),
        plt.Line2D([], [], marker="o", ls="", color=plt.get_cmap("viridis")(0.8), ms=4, label="candidate views"),
        *(
            [plt.Line2D([], [], marker="o", color="tab:red", mfc="white", mew=2, lw=2, label="suggested path, goal")]
            if suggestion.goal_odom is not None
            else []
        ),
        *([plt.Line2D([], [], marker="*", ls="", color="tab:green", mec="black", ms=12, label="truth")] if truth
           is not None else []),
    ]  # fmt: skip
    fig.legend(handles=key, loc="upper center", ncol=len(key), fontsize=9, frameon=False, bbox_to_anchor=(0.45, 0.08))
    what = (
        f"suggested goal {suggestion.travel_m:.1f} m away: its view is expected to tell the places apart by "
        f"{suggestion.gain_nats:.2f} of {suggestion.entropy_nats:.2f} nats"
        if suggestion.goal_odom is not None
        else suggestion.describe()
    )
    shown = f" ({len(hyps)} most probable shown)" if len(suggestion.hypotheses) > len(hyps) else ""
    split = f"the belief is split between {len(suggestion.hypotheses)} places{shown}"
    fig.suptitle("\n".join(filter(None, (title, split, what))), fontsize=11)
    return save_figure(fig, path, dpi=100)


def save_scene_graph_figure(record: dict, cloud: np.ndarray, up: np.ndarray, path: str | Path, title: str = "") -> Path:
    """A recording's scene graph seen from above (along `up`): the fused depth cloud in grey, shaded by height, and
    each node as its box in its label's colour with a dot at its centre, the larger the more often it was seen; a
    legend gives the labels and their node counts, the axes metres."""
    from collections import Counter

    up = np.asarray(up, float) / np.linalg.norm(up)
    seed = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, seed)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    if len(cloud):
        height = cloud @ up
        lo, hi = np.percentile(height, [2, 98])
        ax.scatter(cloud @ e1, cloud @ e2, c=np.clip(height, lo, hi), cmap="Greys", s=1.0, alpha=0.5, linewidths=0,
                   rasterized=True)  # fmt: skip
    counts = Counter(n["label"] for n in record["nodes"])
    labels = sorted(counts, key=lambda label: (-counts[label], label))
    cmap = plt.get_cmap("tab10" if len(labels) <= 10 else "tab20")
    colour = {label: cmap(i % cmap.N) for i, label in enumerate(labels)}
    for node in record["nodes"]:
        centre, half = np.asarray(node["centre_m"]), np.asarray(node["extent_m"]) / 2
        corners = centre + np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        u, v = corners @ e1, corners @ e2
        c = colour[node["label"]]
        ax.add_patch(
            plt.Rectangle((u.min(), v.min()), np.ptp(u), np.ptp(v), lw=1.4, edgecolor=c, facecolor=(*c[:3], 0.12))
        )
        ax.scatter([centre @ e1], [centre @ e2], s=12 + 4 * min(node["n_observations"], 30), color=c,
                   edgecolors="black", linewidths=0.5, zorder=3)  # fmt: skip
    handles = [plt.Line2D([], [], color=colour[label], lw=2, label=f"{label} ({counts[label]})") for label in labels]
    if handles:
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="nodes")
    ax.set_aspect("equal")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    nodes = len(record["nodes"])
    what = f"{nodes} nodes from {record['frames_used']} frames ({record['detector']}, {record['poses']} poses)"
    ax.set_title(f"{title}\n{what}" if title else what, fontsize=10)
    return save_figure(fig, path, dpi=120)
