"""What a scan is matched against, derived from the prior: the likelihood field of every storey (Thrun et al.,
Probabilistic Robotics, Table 6.3), exp(−d² / 2σ²) of each cell's distance d to the nearest BIM obstacle. The
filter's scan term (`localization.measurements.scan`), the back end's scan factors (`backend.scan_factor`)
and the view predictions of the active suggester (`active.views`) all look their endpoints up here."""

from __future__ import annotations

import numpy as np

from bimfactor.bim.grid import distance_transform
from bimfactor.bim.prior import BimPrior


def face_distances(prior: BimPrior) -> np.ndarray:
    """(storeys, rows, cols) float32 metres from each cell to the nearest face of a wall or a piece of furniture, from
    outside or inside (0 on a face): the distance a scan matcher's `LikelihoodField` needs. Inside thick walls and
    furniture footprints the clearance layer is a plateau of equally good poses. (A camera below a table top sees
    its legs, which stand at the footprint's edge.)"""
    res = np.float32(prior.grid.resolution_m)

    def to_faces(solid: np.ndarray) -> np.ndarray:
        # Either side of a face the nearest cells are one cell from the other side's: half a cell puts the face at 0.
        outside = distance_transform(~solid) * res
        inside = distance_transform(solid) * res
        return np.maximum(outside + inside - np.float32(0.5) * res, np.float32(0.0))

    return np.stack([np.minimum(to_faces(layers.structure), to_faces(layers.furniture)) for layers in prior.storeys])


class LikelihoodField:
    """exp(−d² / 2σ²) per grid cell of every storey, looked up for scan endpoints placed by poses.

    d is `distance` ((storeys, rows, cols) metres), by default the prior's clearance layer: the distance from a free
    cell to the nearest obstacle, walls or furniture, 0 inside them. The filter's particles never stand inside walls,
    so they use the clearance; a scan matcher uses `face_distances`.
    """

    def __init__(self, prior: BimPrior, sigma_m: float, distance: np.ndarray | None = None) -> None:
        self.grid = prior.grid
        if distance is None:
            distance = np.stack([layers.clearance_m for layers in prior.storeys]).astype(np.float32)
        # In 1/255 steps (a quarter of float32's memory: the lookups are random, so cache misses are their cost),
        # flattened, with one 0 appended for "off grid".
        field = np.rint(255.0 * np.exp(-0.5 * (distance / sigma_m) ** 2)).astype(np.uint8)
        self._field = np.append(field.ravel(), np.uint8(0))
        self._walls = np.append(np.stack([layers.structure for layers in prior.storeys]).ravel(), False)

    def _index(self, storeys: np.ndarray | int, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Flat field indices of int64 (row, col) cells on their storeys; the last index for cells off the grid."""
        grid = self.grid
        # Viewed as unsigned, a negative index is huge: one comparison per axis tests both bounds.
        inside = (row.view(np.uint64) < grid.rows) & (col.view(np.uint64) < grid.cols)
        flat = storeys * grid.rows + row
        flat *= grid.cols
        flat += col
        return np.where(inside, flat, len(self._field) - 1)

    def _flat(self, poses: np.ndarray, storeys: np.ndarray | int, points: np.ndarray) -> np.ndarray:
        """(M, N) flat field indices of (N, 2) base-frame points placed by (M, 3) poses."""
        grid = self.grid
        res = grid.resolution_m
        c, s = np.cos(poses[:, 2]) / res, np.sin(poses[:, 2]) / res
        # The grid columns (first M rows) and rows (last M) of every point from every pose as one product
        # (2M, 3) @ (3, N) of the poses' affine maps and the homogeneous points: a tenth of the elementwise cost.
        affine = np.concatenate(
            [
                np.column_stack([(poses[:, 0] - grid.origin_x) / res, c, -s]),
                np.column_stack([(poses[:, 1] - grid.origin_y) / res, s, c]),
            ]
        )
        homogeneous = np.vstack([np.ones(len(points)), points[:, 0], points[:, 1]])
        cells = np.floor(affine @ homogeneous).astype(np.int64)
        M = len(poses)
        storeys = np.broadcast_to(np.asarray(storeys, np.int64).reshape(-1), (M,))
        return self._index(storeys[:, None], cells[M:], cells[:M])

    def _grid_flat(
        self, pose: np.ndarray, dxy: np.ndarray, dyaw: np.ndarray, storey: int, points: np.ndarray
    ) -> np.ndarray:
        """(Y, T, N) flat field indices of `grid_values`' poses."""
        grid = self.grid
        res = grid.resolution_m
        yaws = float(pose[2]) + np.asarray(dyaw, np.float64)
        c, s = np.cos(yaws)[:, None] / res, np.sin(yaws)[:, None] / res
        rx = (c * points[None, :, 0] - s * points[None, :, 1]).astype(np.float32)  # (Y, N) grid units
        ry = (s * points[None, :, 0] + c * points[None, :, 1]).astype(np.float32)
        tx = ((float(pose[0]) + np.asarray(dxy)[:, 0] - grid.origin_x) / res).astype(np.float32)  # (T,)
        ty = ((float(pose[1]) + np.asarray(dxy)[:, 1] - grid.origin_y) / res).astype(np.float32)
        col = np.floor(tx[None, :, None] + rx[:, None, :]).astype(np.int64)
        row = np.floor(ty[None, :, None] + ry[:, None, :]).astype(np.int64)
        return self._index(storey, row, col)

    @staticmethod
    def _before(endpoints: np.ndarray, clear_before_m: float) -> np.ndarray:
        """(N, 2) the points `clear_before_m` short of each endpoint along its ray (the base origin at the least)."""
        ranges = np.maximum(np.hypot(endpoints[:, 0], endpoints[:, 1]), 1e-9)
        return endpoints * np.maximum(1.0 - clear_before_m / ranges, 0.0)[:, None]

    def values(
        self, poses: np.ndarray, storeys: np.ndarray | int, endpoints: np.ndarray, clear_before_m: float = 0.0
    ) -> np.ndarray:
        """(M, N) uint8: 255 · exp(−d² / 2σ²) of each of the (N, 2) base-frame endpoints placed by each of the (M, 3)
        poses on its storey ((M,) or one for all); 0 off the grid.

        With `clear_before_m` > 0, an endpoint whose ray is inside a wall that far before it (the return would come
        from behind a wall the sensor cannot see through) also scores 0.
        """
        poses = np.asarray(poses, np.float64).reshape(-1, 3)
        endpoints = np.asarray(endpoints, np.float64).reshape(-1, 2)
        values = self._field[self._flat(poses, storeys, endpoints)]
        if clear_before_m > 0.0 and len(endpoints):
            values[self._walls[self._flat(poses, storeys, self._before(endpoints, clear_before_m))]] = 0
        return values

    def grid_values(
        self,
        pose: np.ndarray,
        dxy: np.ndarray,
        dyaw: np.ndarray,
        storey: int,
        endpoints: np.ndarray,
        clear_before_m: float = 0.0,
    ) -> np.ndarray:
        """(Y·T, N) `values` at the poses of a search grid around a (3,) pose: every (Y,) yaw offset (outer) with
        every (T, 2) x, y offset (inner), all on one storey. The same numbers as `values` for those poses, at about
        half the cost: the endpoints are rotated once per yaw and moved per translation."""
        endpoints = np.asarray(endpoints, np.float64).reshape(-1, 2)
        values = self._field[self._grid_flat(pose, dxy, dyaw, storey, endpoints)]
        if clear_before_m > 0.0 and len(endpoints):
            before = self._before(endpoints, clear_before_m)
            values[self._walls[self._grid_flat(pose, dxy, dyaw, storey, before)]] = 0
        return values.reshape(len(dyaw) * len(dxy), len(endpoints))
