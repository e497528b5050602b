"""A contact sheet of a sequence: one row per frame, RGB | depth | instances, to check data at a glance."""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bimfactor.io.atomic import atomic_path
from bimfactor.io.sequence import Sequence
from bimfactor.types import Frame

log = logging.getLogger(__name__)

PANEL_WIDTH_IN = 3.2
CAPTION_IN = 0.35  # room for a panel's caption
DPI = 100
PNG_COMPRESSION = 1
"""zlib level of the figures' PNGs: 1 writes a large sheet in a third of the time of matplotlib's 6, 20 % larger."""


def preview_indices(n_frames: int, max_frames: int) -> np.ndarray:
    """Row positions of at most `max_frames` frames spread evenly over the sequence, first and last included."""
    if n_frames <= 0 or max_frames <= 0:
        return np.zeros(0, dtype=int)
    return np.unique(np.linspace(0, n_frames - 1, min(n_frames, max_frames)).round().astype(int))


def instance_colours(ids: np.ndarray, seed: int = 0) -> np.ndarray:
    """(H, W) instance ids → (H, W, 3) uint8 with one fixed random colour per id and black for -1."""
    ids = np.asarray(ids)
    top = max(int(ids.max(initial=-1)), 0)
    palette = np.random.default_rng(seed).integers(40, 256, size=(top + 2, 3), dtype=np.uint8)
    palette[0] = 0  # id -1: nothing
    return palette[np.clip(ids, -1, top) + 1]


MISSING_GLYPH_WARNING = r"Glyph \d+ .*missing from (current )?font"
"""matplotlib's UserWarning, once per character and rendering, for text its fonts cannot draw (a CJK file name)."""


@contextlib.contextmanager
def missing_glyphs_quiet() -> Iterator[None]:
    """Lay out and render figures whose text has characters no installed font can draw (a building or sequence named
    in Chinese) without matplotlib's warning per character: they show as empty boxes, and the text is the user's own,
    so the warning says nothing they could act on. Other warnings pass as before. Wrap whatever renders the figure
    (`savefig`, `tight_layout`); `save_figure` does."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=MISSING_GLYPH_WARNING, category=UserWarning)
        yield


def write_preview(sequence: Sequence, path_png: str | Path, max_frames: int = 12) -> Path:
    """Write a PNG contact sheet of up to `max_frames` evenly spaced frames; returns the path. Atomic.

    Depth is colour-mapped over one range for all rows (no return in black); the instance column appears when
    any shown frame has instance ids.
    """
    path_png = Path(path_png)
    rows = [sequence[int(i)] for i in preview_indices(len(sequence), max_frames)]
    if not rows:
        raise ValueError("cannot preview an empty sequence")
    with_instances = any(f.instance_ids is not None for f in rows)
    columns = 3 if with_instances else 2
    finite = np.concatenate([f.depth_m[np.isfinite(f.depth_m)].ravel() for f in rows])
    depth_max = float(np.percentile(finite, 99)) if finite.size else 1.0

    K = sequence.meta.intrinsics
    title_in, bar_in = 0.45, 0.75  # the sheet's title above the panels, the depth colour bar and its label below
    panel_h = PANEL_WIDTH_IN * K.height / K.width + CAPTION_IN
    height = panel_h * len(rows) + title_in + bar_in
    fig = Figure(figsize=(PANEL_WIDTH_IN * columns, height), dpi=DPI)
    FigureCanvasAgg(fig)
    # A fixed grid, not a constrained layout: solving one for 36 panels took two thirds of the sheet's time.
    grid = {"left": 0.01, "right": 0.99, "top": 1 - title_in / height, "bottom": bar_in / height, "wspace": 0.04}
    grid["hspace"] = CAPTION_IN / (panel_h - CAPTION_IN)
    axes = fig.subplots(len(rows), columns, squeeze=False, gridspec_kw=grid)
    for row, frame in zip(axes, rows, strict=True):
        depth = _draw_row(row, frame, depth_max, with_instances)
    bar = fig.colorbar(depth, cax=fig.add_axes((0.3, 0.45 / height, 0.4, 0.12 / height)), orientation="horizontal")
    bar.set_label("depth (m); black: no return", fontsize=9)
    bar.ax.tick_params(labelsize=8)
    fig.suptitle(
        f"{sequence.meta.name} ({sequence.meta.source}, {len(sequence)} frames)", fontsize=11, y=1 - 0.1 / height
    )
    with missing_glyphs_quiet(), atomic_path(path_png) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI, pil_kwargs={"compress_level": PNG_COMPRESSION})
    log.info("wrote preview %s (%d frames)", path_png, len(rows))
    return path_png


def panel_image(image: np.ndarray, smooth: bool) -> np.ndarray:
    """`image` reduced to the panel's pixel width (`PANEL_WIDTH_IN` × `DPI`) when wider: area-averaged when `smooth`
    (colour), nearest otherwise (depth with its NaN holes, instance ids). matplotlib resampled the full frames itself
    at several times the cost of the whole sheet."""
    import cv2

    width = int(PANEL_WIDTH_IN * DPI)
    h, w = image.shape[:2]
    if w <= width:
        return image
    size = (width, max(round(h * width / w), 1))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if smooth else cv2.INTER_NEAREST)


def _draw_row(axes: np.ndarray, frame: Frame, depth_max: float, with_instances: bool):
    """One frame's panels; the depth image (for the sheet's colour bar)."""
    axes[0].imshow(panel_image(np.ascontiguousarray(frame.rgb), smooth=True), interpolation="nearest")
    axes[0].set_title(f"frame {frame.index}, t = {frame.timestamp_s:.2f} s", fontsize=9)
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="black")
    depth = panel_image(np.asarray(frame.depth_m, dtype=np.float32), smooth=False)
    shown = axes[1].imshow(
        np.ma.masked_invalid(depth), cmap=cmap, vmin=0.0, vmax=max(depth_max, 1e-3), interpolation="nearest"
    )
    axes[1].set_title("depth", fontsize=9)
    if with_instances:
        if frame.instance_ids is not None:
            ids = panel_image(np.asarray(frame.instance_ids, dtype=np.int32), smooth=False)
            axes[2].imshow(instance_colours(ids), interpolation="nearest")
            n = len(np.unique(frame.instance_ids[frame.instance_ids >= 0]))
            axes[2].set_title(f"{n} instances, a colour each (black: none)", fontsize=9)
        else:
            axes[2].set_title("no instance ids", fontsize=9)
    for ax in axes:
        # No ticks at all: matplotlib places every title above its axes' tick labels, hidden or not, and measuring
        # those took most of the sheet's rendering.
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_axis_off()
    return shown
