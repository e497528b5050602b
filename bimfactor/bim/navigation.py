"""The BIM's navigation graph: where a robot can drive on a storey, and the shortest paths there.

The robot drives on the prior's navigable layer joined through its doorways (`traversable_mask`). Paths are planned
by Dijkstra on one node per `PLANNING_CELL_M` block (edges checked at full resolution, costlier near obstacles within
`inflation_m`), then shortcut at full resolution. Floors are joined by the prior's portals, a portal's end reached
from within `PORTAL_REACH_M` of its footprint (`box_distance`). Used by the simulator's routes, active localization
and the motion model's `PortalMotion`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from bimfactor.bim.grid import GridSpec, distance_transform, rasterise_polygons
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.rooms import OUTSIDE

PLANNING_CELL_M = 0.2  # side of a coarse planning block
LOW_CLEARANCE_COST = 10.0  # extra cost per metre at zero clearance margin below inflation_m (linear in deficit)
DOOR_APPROACH_M = 0.5  # a doorway's free cells reach this far beyond the door on both sides
PORTAL_REACH_M = 1.0  # a portal's end is reached from within this distance of its footprint on a floor


@dataclass
class NavGraph:
    """The coarse planning graph of one storey over its full-resolution traversable mask.

    Nodes: `node_xy` (M, 2) world, `node_clearance` (M,), `node_room` (M,) room id (< 0: doorway or no room),
    `node_component` (M,); `graph` (M, M) sparse edge costs. `traversable` and `clearance_m` are (rows, cols).
    """

    storey_index: int
    spec: GridSpec
    traversable: np.ndarray
    clearance_m: np.ndarray
    node_xy: np.ndarray
    node_clearance: np.ndarray
    node_room: np.ndarray
    node_component: np.ndarray
    graph: sparse.csr_matrix
    inflation_m: float
    _tree: cKDTree | None = field(default=None, repr=False)

    def nearest_node(self, xy: np.ndarray) -> int:
        return int(self.nearest_nodes(np.asarray(xy, float)[None])[1][0])

    def nearest_nodes(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) distance to the nearest node and (N,) its index, for (N, 2) world points."""
        if self._tree is None:
            self._tree = cKDTree(self.node_xy)
        gap, node = self._tree.query(np.asarray(xy, float).reshape(-1, 2))
        return gap, node.astype(np.int64)

    def shortest_paths(self, sources: int | np.ndarray, limit: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(M,) cost to the nearest source (inf beyond `limit`) and (M,) predecessors (-9999 at sources and unreachable
        nodes)."""
        dist, pred, _ = csgraph.dijkstra(
            self.graph, directed=True, indices=sources, return_predecessors=True, min_only=True, limit=limit
        )
        return dist, pred

    def clearance_at(self, xy: np.ndarray) -> np.ndarray:
        """(N,) clearance at (N, 2) world points; 0 off the traversable space."""
        rc = self.spec.world_to_cell(xy)
        ok = self.spec.contains(rc)
        out = np.zeros(len(rc), np.float32)
        r, c = rc[ok, 0], rc[ok, 1]
        out[ok] = np.where(self.traversable[r, c], self.clearance_m[r, c], 0.0)
        return out

    def segment_min_clearance(self, a: np.ndarray, b: np.ndarray) -> float:
        """Smallest clearance along the straight segment a→b at full resolution (0 if it leaves free space)."""
        length = float(np.hypot(*(b - a)))
        n = max(2, math.ceil(length / (0.5 * self.spec.resolution_m)) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        return float(self.clearance_at(a + t * (b - a)).min())

    def plan(self, start_xy: np.ndarray, pred: np.ndarray, goal_node: int) -> np.ndarray:
        """(P, 2) shortcut polyline from `start_xy` to the goal node along a Dijkstra predecessor tree."""
        nodes = [goal_node]
        while pred[nodes[-1]] >= 0:
            nodes.append(int(pred[nodes[-1]]))
        nodes.reverse()
        points = np.vstack([np.asarray(start_xy, float)[None], self.node_xy[nodes]])
        return self._shortcut(points)

    def _shortcut(self, points: np.ndarray) -> np.ndarray:
        """String pulling: skip vertices while the straight line keeps the clearance the path had (≤ inflation)."""
        clearance = self.clearance_at(points)
        out, i = [points[0]], 0
        while i < len(points) - 1:
            j = i + 1
            while j + 1 < len(points):
                need = min(self.inflation_m, float(clearance[i : j + 2].min()))
                if self.segment_min_clearance(points[i], points[j + 1]) < need - 1e-6:
                    break
                j += 1
            out.append(points[j])
            i = j
        return np.asarray(out)


def traversable_mask(
    prior: BimPrior, storey_index: int, robot_radius_m: float, extra_obstacles: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) bool indoor free space a robot centre may occupy (navigable rooms joined by their doorways),
    and the (rows, cols) clearance in metres, with `extra_obstacles` (rows, cols) bool counted as obstacles."""
    layers, spec = prior.storeys[storey_index], prior.grid
    clearance = layers.clearance_m
    if extra_obstacles is not None and extra_obstacles.any():
        extra = distance_transform(~extra_obstacles) * np.float32(spec.resolution_m)
        clearance = np.minimum(clearance, extra.astype(np.float32))
    free = (clearance >= robot_radius_m) & (layers.room_labels != OUTSIDE)
    doorways = np.zeros(spec.shape, np.uint8)
    for door in prior.doors:
        if door.storey_index != storey_index:
            continue
        c, u = np.asarray(door.center_xy), np.asarray(door.axis_xy)
        n = np.array([-u[1], u[0]]) * (door.depth_m / 2 + DOOR_APPROACH_M)
        u = u * door.width_m / 2
        rasterise_polygons([np.array([c - u - n, c + u - n, c + u + n, c - u + n])], spec, out=doorways)
    return free & (layers.navigable | doorways.astype(bool)), clearance


def build_nav_graph(
    prior: BimPrior,
    storey_index: int,
    robot_radius_m: float,
    inflation_m: float,
    extra_obstacles: np.ndarray | None = None,
) -> NavGraph:
    """The coarse planning graph of a storey (see module docstring)."""
    spec = prior.grid
    traversable, clearance = traversable_mask(prior, storey_index, robot_radius_m, extra_obstacles)
    f = max(1, round(PLANNING_CELL_M / spec.resolution_m))
    rows_c, cols_c = -(-spec.rows // f), -(-spec.cols // f)
    score = np.full((rows_c * f, cols_c * f), -1.0, np.float32)
    score[: spec.rows, : spec.cols] = np.where(traversable, clearance, -1.0)
    blocks = score.reshape(rows_c, f, cols_c, f).transpose(0, 2, 1, 3).reshape(rows_c, cols_c, f * f)
    best = blocks.argmax(axis=2)
    exists = np.take_along_axis(blocks, best[..., None], axis=2)[..., 0] >= 0
    block_node = np.full((rows_c, cols_c), -1, np.int64)
    block_node[exists] = np.arange(int(exists.sum()))
    br, bc = np.nonzero(exists)
    node_rc = np.stack([br * f + best[br, bc] // f, bc * f + best[br, bc] % f], axis=1)
    node_xy = spec.cell_to_world(node_rc)
    node_clearance = clearance[node_rc[:, 0], node_rc[:, 1]]
    node_room = prior.storeys[storey_index].room_labels[node_rc[:, 0], node_rc[:, 1]].astype(np.int32)

    # Edges to the 8 neighbour blocks whose straight line stays traversable at full resolution.
    samples = 2 * f + 1
    t = np.linspace(0.0, 1.0, samples)
    heads, tails, costs = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = block_node[: rows_c - dr, max(0, -dc) : cols_c - max(0, dc)]
        b = block_node[dr:, max(0, dc) : cols_c + min(0, dc)]
        ok = (a >= 0) & (b >= 0)
        a, b = a[ok], b[ok]
        pa, pb = node_rc[a].astype(float), node_rc[b].astype(float)
        line = np.rint(pa[:, None, :] + t[None, :, None] * (pb - pa)[:, None, :]).astype(np.int64)
        on_free = traversable[line[..., 0], line[..., 1]].all(axis=1)
        low = clearance[line[..., 0], line[..., 1]].min(axis=1)
        a, b, low = a[on_free], b[on_free], low[on_free]
        length = np.hypot(*(node_xy[b] - node_xy[a]).T)
        deficit = np.clip((inflation_m - low) / max(inflation_m, 1e-9), 0.0, None)
        heads.append(a)
        tails.append(b)
        costs.append(length * (1.0 + LOW_CLEARANCE_COST * deficit))
    a, b, w = np.concatenate(heads), np.concatenate(tails), np.concatenate(costs)
    m = len(node_xy)
    graph = sparse.csr_matrix((np.concatenate([w, w]), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(m, m))
    _, component = csgraph.connected_components(graph, directed=False)
    return NavGraph(
        storey_index, spec, traversable, clearance, node_xy, node_clearance, node_room, component, graph, inflation_m
    )


def box_distance(xy: np.ndarray, box: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    """(...) distance from (..., 2) world points to an (x_min, y_min, x_max, y_max) box; 0 inside it."""
    x0, y0, x1, y1 = box
    gap_x = np.maximum(np.maximum(x0 - xy[..., 0], xy[..., 0] - x1), 0.0)
    gap_y = np.maximum(np.maximum(y0 - xy[..., 1], xy[..., 1] - y1), 0.0)
    return np.hypot(gap_x, gap_y)
