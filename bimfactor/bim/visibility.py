"""Precomputed visibility of BIM objects: which objects a robot could see from each place of a storey.

For every free-floor cell of a coarse lattice (`bim.visibility.cell_m`) the table lists the objects of the storey
within the radius r (`bim.visibility.radius_m`, plus a lattice diagonal) that a 2-D line of sight on the prior's
`structure` layer reaches: the paper's precomputed visible-object set (Sec. II.C), the field of view tested per
particle at run time. An object is visible when its centre or a corner of its shrunk footprint is reachable;
structure within its own footprint (a window's wall) does not block; furniture does not occlude and doors are open.

Stored CSR-style: `cell_rows` (storeys, rows, cols) int32 maps a lattice cell to its row (-1: not computed),
`offsets` (rows + 1,) int64 and `object_ids` (nnz,) int32 hold the lists.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from bimfactor.bim.grid import GridSpec
from bimfactor.config import VisibilityConfig
from bimfactor.progress import progress as progress_bar

if TYPE_CHECKING:  # the prior stores this table: a runtime import would be circular
    from bimfactor.bim.prior import BimPrior

log = logging.getLogger(__name__)

_FOOTPRINT_SHRINK = 0.8  # sample points: footprint corners at this fraction of the object's extent
_OWN_MARGIN_M = 0.15  # structure this close to an object's footprint belongs to it (sill, jamb, host wall)
_STEP_FRACTION = 0.5  # ray-march step as a fraction of the fine grid resolution
_SEGMENT_STEPS = 24  # ray-march samples per batch before blocked and finished rays are dropped
_FORMAT_VERSION = 1


@dataclass
class VisibilityTable:
    """Objects visible from each lattice cell of each storey, as CSR lists of object ids."""

    lattice: GridSpec
    radius_m: float
    cell_rows: np.ndarray  # (storeys, lattice rows, lattice cols) int32, -1 where not computed
    offsets: np.ndarray  # (n_rows + 1,) int64
    object_ids: np.ndarray  # (nnz,) int32 ids into prior.objects

    # -------------------------------------------------------------------------------- queries

    def candidates(self, xy: np.ndarray, storey: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Object ids listed at each of M points: (M + 1,) int64 offsets and (nnz,) int32 ids, CSR over points.

        `xy` is (M, 2) world metres, `storey` an (M,) int array or one storey index for all points.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        storey_idx = np.broadcast_to(np.asarray(storey, dtype=np.int64), (len(xy),))
        rows = self.rows_at(xy, storey_idx)
        valid = rows >= 0
        safe = np.where(valid, rows, 0)
        starts = self.offsets[safe]
        counts = np.where(valid, self.offsets[safe + 1] - starts, 0)
        out_offsets = np.zeros(len(xy) + 1, np.int64)
        np.cumsum(counts, out=out_offsets[1:])
        total = int(out_offsets[-1])
        gather = np.repeat(starts - out_offsets[:-1], counts) + np.arange(total, dtype=np.int64)
        return out_offsets, self.object_ids[gather]

    def rows_at(self, xy: np.ndarray, storey: np.ndarray) -> np.ndarray:
        """(M,) table row of each point (-1 off the lattice, off the free floor, or on an unknown storey)."""
        rc = self.lattice.world_to_cell(xy)
        storey = np.asarray(storey, dtype=np.int64)
        ok = self.lattice.contains(rc) & (storey >= 0) & (storey < self.cell_rows.shape[0])
        rows = np.full(len(rc), -1, np.int64)
        rows[ok] = self.cell_rows[storey[ok], rc[ok, 0], rc[ok, 1]]
        return rows

    def visible_ids(self, xy: np.ndarray, storey: int = 0) -> np.ndarray:
        """(n,) ids of the objects listed at one world point (2,)."""
        offsets, ids = self.candidates(np.asarray(xy, dtype=np.float64).reshape(1, 2), storey)
        return ids[offsets[0] : offsets[1]]

    @property
    def nbytes(self) -> int:
        return int(self.cell_rows.nbytes + self.offsets.nbytes + self.object_ids.nbytes)

    # -------------------------------------------------------------------------------- disk

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for an .npz (the prior stores the table next to its grids)."""
        spec = self.lattice
        meta = np.array(
            [_FORMAT_VERSION, spec.origin_x, spec.origin_y, spec.resolution_m, spec.rows, spec.cols, self.radius_m]
        )
        return {
            "visibility_meta": meta,
            "visibility_cell_rows": self.cell_rows,
            "visibility_offsets": self.offsets,
            "visibility_object_ids": self.object_ids,
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> VisibilityTable:
        """Inverse of `to_arrays`; raises ValueError for another format version."""
        meta = np.asarray(arrays["visibility_meta"], dtype=np.float64)
        if int(meta[0]) != _FORMAT_VERSION:
            raise ValueError(f"visibility table format v{int(meta[0])}, this bimfactor reads v{_FORMAT_VERSION}")
        lattice = GridSpec(float(meta[1]), float(meta[2]), float(meta[3]), int(meta[4]), int(meta[5]))
        return cls(
            lattice=lattice,
            radius_m=float(meta[6]),
            cell_rows=np.asarray(arrays["visibility_cell_rows"], dtype=np.int32),
            offsets=np.asarray(arrays["visibility_offsets"], dtype=np.int64),
            object_ids=np.asarray(arrays["visibility_object_ids"], dtype=np.int32),
        )

    # -------------------------------------------------------------------------------- build

    @classmethod
    def build(cls, prior: BimPrior, cfg: VisibilityConfig, progress: bool = True) -> VisibilityTable:
        """Ray march from every free lattice cell (`cfg.cell_m`) to every object within r (`cfg.radius_m`) on its
        storey."""
        started = time.perf_counter()
        grid = prior.grid
        cell_m = cfg.cell_m
        rows = int(np.ceil(grid.rows * grid.resolution_m / cell_m))
        cols = int(np.ceil(grid.cols * grid.resolution_m / cell_m))
        lattice = GridSpec(grid.origin_x, grid.origin_y, cell_m, rows, cols)
        reach = cfg.radius_m + cell_m * np.sqrt(2.0)  # any point of a cell is this close to its origin
        positions = prior.object_positions()[:, :2]
        sizes = prior.object_sizes()[:, :2]
        storey_of = np.asarray([o.storey_index for o in prior.objects], np.int64)

        cell_rows = np.full((len(prior.storeys), rows, cols), -1, np.int32)
        n_rows = 0
        origins_of: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for s in np.unique(storey_of).tolist():  # storeys without objects keep no rows (-1), as lookups expect
            flat, origins = _lattice_origins(prior, s, lattice)
            rr, cc = np.unravel_index(flat, (rows, cols))
            cell_rows[s, rr, cc] = n_rows + np.arange(len(flat), dtype=np.int32)
            origins_of[s] = (n_rows + np.arange(len(flat), dtype=np.int64), origins)
            n_rows += len(flat)
        steps = [(s, int(o)) for s in range(len(prior.storeys)) for o in np.flatnonzero(storey_of == s)]
        work = _Work([layers.structure for layers in prior.storeys], grid, origins_of, positions, sizes, reach)
        pair_rows, pair_ids = _run_steps(work, steps, progress)
        all_rows = np.concatenate(pair_rows) if pair_rows else np.zeros(0, np.int64)
        all_ids = np.concatenate(pair_ids) if pair_ids else np.zeros(0, np.int32)
        order = np.lexsort((all_ids, all_rows))
        counts = np.bincount(all_rows, minlength=n_rows)
        offsets = np.zeros(n_rows + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        table = cls(lattice, float(cfg.radius_m), cell_rows, offsets, all_ids[order].astype(np.int32))
        log.info(
            "visibility table: %d lattice cells, %d (cell, object) pairs, %.1f MB, %.1f s",
            n_rows,
            len(all_ids),
            table.nbytes / 1e6,
            time.perf_counter() - started,
        )
        return table


@dataclass
class _Work:
    """What every object's line-of-sight test reads: the storeys' structure, the fine grid, each storey's lattice rows
    and ray origins, the objects' positions and sizes, and how far from an object its lattice cells are tested."""

    structure: list[np.ndarray]
    grid: GridSpec
    origins_of: dict[int, tuple[np.ndarray, np.ndarray]]
    positions: np.ndarray
    sizes: np.ndarray
    reach_m: float


_WORK: _Work | None = None  # set before the worker processes fork; they read it copy-on-write
_CHUNKS_PER_WORKER = 8  # objects differ in cost (a window in a corridor against a cupboard): small chunks balance
_MIN_PARALLEL_OBJECTS = 64  # fewer objects than this: one process (a pool's start-up would cost more than it saves)


def _pairs(
    work: _Work, steps: list[tuple[int, int]], blocking: dict[int, np.ndarray] | None = None
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(lattice rows, object ids) of the visible pairs of each (storey, object) step, as arrays per object.
    `blocking` holds each storey's structure, copied once and edited per object and restored (pass one dict to calls
    over the same work, so the copy is not made again)."""
    blocking = {} if blocking is None else blocking
    pair_rows, pair_ids = [], []
    for s, obj in steps:
        row_ids, origins = work.origins_of[s]
        near = np.flatnonzero(np.hypot(*(origins - work.positions[obj]).T) <= work.reach_m)
        if len(near) == 0:
            continue
        if s not in blocking:
            blocking[s] = work.structure[s].astype(bool, copy=True)
        seen = _visible_from(blocking[s], work.grid, origins[near], work.positions[obj], work.sizes[obj])
        pair_rows.append(row_ids[near[seen]])
        pair_ids.append(np.full(int(seen.sum()), obj, np.int32))
    return pair_rows, pair_ids


def _forked_pairs(steps: list[tuple[int, int]]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    assert _WORK is not None, "the worker was not forked from a process that set the work"
    return _pairs(_WORK, steps)


def _run_steps(work: _Work, steps: list[tuple[int, int]], progress: bool) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """`_pairs` of every step, in chunks over forked worker processes (one per CPU) where the platform forks and the
    building has enough objects, in this process otherwise. The table is the same either way (sorted at the end)."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    global _WORK
    workers = min(os.cpu_count() or 1, max(len(steps) // _MIN_PARALLEL_OBJECTS, 1))
    if workers == 1 or "fork" not in multiprocessing.get_all_start_methods():
        blocking: dict[int, np.ndarray] = {}
        results = (_pairs(work, [step], blocking) for step in steps)
        return _gather(progress_bar(results, "visibility", len(steps), "object") if progress else results)
    size = max(len(steps) // (workers * _CHUNKS_PER_WORKER), 1)
    chunks = [steps[i : i + size] for i in range(0, len(steps), size)]
    _WORK = work
    try:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            results = pool.map(_forked_pairs, chunks)
            return _gather(progress_bar(results, "visibility", len(chunks), "chunk") if progress else results)
    finally:
        _WORK = None


def _gather(results: Iterable[tuple[list[np.ndarray], list[np.ndarray]]]) -> tuple[list, list]:
    """The pairs of every chunk, in order, as one list of row arrays and one of id arrays."""
    pair_rows: list[np.ndarray] = []
    pair_ids: list[np.ndarray] = []
    for rows, ids in results:
        pair_rows += rows
        pair_ids += ids
    return pair_rows, pair_ids


def _lattice_origins(prior: BimPrior, storey: int, lattice: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Free-floor lattice cells of a storey: (n,) flat lattice indices and (n, 2) ray origins in world metres.

    Free floor is inside a room (or navigable) and not structure; a cell's origin is its free fine cell
    nearest to the lattice cell's centre.
    """
    layers = prior.storeys[storey]
    free = ((layers.room_labels >= 0) | layers.navigable) & ~layers.structure
    fine_rc = np.argwhere(free)
    if len(fine_rc) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    fine_xy = prior.grid.cell_to_world(fine_rc)
    coarse_rc = lattice.world_to_cell(fine_xy)
    flat = coarse_rc[:, 0] * lattice.cols + coarse_rc[:, 1]
    dist = np.hypot(*(fine_xy - lattice.cell_to_world(coarse_rc)).T)
    order = np.lexsort((dist, flat))
    unique_flat, first = np.unique(flat[order], return_index=True)
    return unique_flat, fine_xy[order[first]]


def _sample_points(center: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(5, 2) the object's centre, then its footprint corners shrunk towards the centre."""
    half = 0.5 * _FOOTPRINT_SHRINK * size
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64) * half
    return np.vstack([center, center + corners])


def _visible_from(
    blocking: np.ndarray, grid: GridSpec, origins: np.ndarray, center: np.ndarray, size: np.ndarray
) -> np.ndarray:
    """(n,) bool: does a line of sight from each (n, 2) origin reach any sample point of the object?

    `blocking` (rows, cols) bool is the storey's structure; it is edited in place and restored before returning.
    """
    # The object's own region: structure in it (a window's host wall, a sill) does not hide the object.
    wall_depth = _hosting_depth(blocking, grid, center)
    margin = _OWN_MARGIN_M + 2.0 * wall_depth
    lo, hi = center - 0.5 * size - margin, center + 0.5 * size + margin
    (r0, c0), (r1, c1) = grid.world_to_cell(np.array([lo, hi]))
    r0, c0 = max(r0, 0), max(c0, 0)
    r1, c1 = min(r1 + 1, grid.rows), min(c1 + 1, grid.cols)
    saved = blocking[r0:r1, c0:c1].copy()
    blocking[r0:r1, c0:c1] = False
    try:
        visible = np.zeros(len(origins), bool)
        for point in _sample_points(center, size):
            todo = np.flatnonzero(~visible)
            if len(todo) == 0:
                break
            visible[todo] = ~_blocked(blocking, grid, origins[todo], point)
    finally:
        blocking[r0:r1, c0:c1] = saved
    return visible


def _hosting_depth(structure: np.ndarray, grid: GridSpec, center: np.ndarray) -> float:
    """How deep inside structure an object's centre lies (0 for free-standing objects; ~half a wall for windows)."""
    rc = grid.world_to_cell(center[None])[0]
    if not grid.contains(rc[None])[0] or not structure[rc[0], rc[1]]:
        return 0.0
    pad = 40  # cells: 2 m at 5 cm, more than any wall's half thickness
    r0, c0 = max(rc[0] - pad, 0), max(rc[1] - pad, 0)
    window = structure[r0 : rc[0] + pad + 1, c0 : rc[1] + pad + 1]
    depth = ndimage.distance_transform_edt(window)  # float64: a margin's cell boundary, exactly as built before
    return float(depth[rc[0] - r0, rc[1] - c0] * grid.resolution_m)


def _blocked(blocking: np.ndarray, grid: GridSpec, origins: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(n,) bool: does the segment from each (n, 2) origin to the (2,) target cross a blocking cell?

    All rays march together, `_SEGMENT_STEPS` samples at a time; a ray leaves the batch once blocked or finished.
    """
    step = _STEP_FRACTION * grid.resolution_m
    # Origins and the target inside the grid keep every sample of the segment inside it (no clipping per sample).
    top = np.array([grid.origin_x + grid.cols * grid.resolution_m, grid.origin_y + grid.rows * grid.resolution_m])
    low = np.array([grid.origin_x, grid.origin_y])
    target = np.clip(target, low, top - 1e-6)
    origins = np.clip(origins, low, top - 1e-6)
    delta = target - origins
    length = np.hypot(delta[:, 0], delta[:, 1])
    direction = delta / np.maximum(length, 1e-9)[:, None]
    start = origins - low
    inv_res = 1.0 / grid.resolution_m
    flat_blocking = blocking.ravel()
    out = np.zeros(len(origins), bool)
    alive = np.arange(len(origins))
    first = 0
    while len(alive):
        t = (first + np.arange(_SEGMENT_STEPS)) * step
        tt = np.minimum(t[None, :], length[alive, None])  # short rays repeat their end point
        cols = ((start[alive, 0:1] + tt * direction[alive, 0:1]) * inv_res).astype(np.intp)
        rows = ((start[alive, 1:2] + tt * direction[alive, 1:2]) * inv_res).astype(np.intp)
        rows *= grid.cols
        rows += cols
        hit = flat_blocking[rows].any(axis=1)
        out[alive[hit]] = True
        alive = alive[~hit & (length[alive] > t[-1])]
        first += _SEGMENT_STEPS
    return out
