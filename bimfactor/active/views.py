"""What the robot would observe from a pose, by the BIM, and how strongly that tells two places apart.

The prediction holds what the filter weighs: the objects in view as a histogram over (label, position in the robot
frame), the door plates legible from the pose, and the 2-D scan's endpoints. `discrepancy` turns the predictions at K
places into D[k, j], the log evidence expected against place j when the robot is at place k: the Bernoulli divergence
KL(p ‖ f) per object or plate one view has and the other lacks, and the scan's likelihood-field loss over T_scan
(docs/active.md).
"""

from __future__ import annotations

import numpy as np

from bimfactor.bim.field import LikelihoodField
from bimfactor.bim.plates import door_plates, normalise_text
from bimfactor.bim.prior import BimPrior
from bimfactor.bim.visibility import VisibilityTable
from bimfactor.config import Config
from bimfactor.localization.measurements import FrameData
from bimfactor.types import CameraIntrinsics, Observations, SequenceMeta, TextObservations, wrap_angle

PLATE_LEGIBLE_M = 2.5  # a 15 cm plate is legible to ~2.4 m at 320 px over 90° (perception.text.sim_min_height_px)
SCAN_BEAM_DEG = 6.0  # predicted scan: one beam per 6° (the filter weighs one per scan.beam_deg; this is a preview)
# A detector's recall with the right label (the simulator's `paper` preset measures recall 0.68 and 19 % confused:
# 0.55), the chance of a false or confused detection of one label at one place, and a plate's read chance once legible.
OBJECT_RECALL, OBJECT_FALSE, PLATE_READ = 0.55, 0.05, 0.6
_MARCH_STEP_M = 0.1  # ray-march step of the predicted scan and the plates' line of sight


def bernoulli_divergence(p: float, f: float) -> float:
    """KL(Bernoulli(p) ‖ Bernoulli(f)) in nats: the expected log evidence of a detection made with probability p where
    one place is true and f where the other is."""
    return float(p * np.log(p / f) + (1 - p) * np.log((1 - p) / (1 - f)))


def plate_near_m(cfg: Config, meta: SequenceMeta | None = None) -> float:
    """How far ahead a door plate must be for its top to be in the image: the plate's top (`sim.door_plates`:
    where plates hang, as buildings hang them) above the camera, over the tangent of the image's upper half-angle.
    The camera is the sequence's (`meta`: intrinsics and mount), else the simulator's (`sim.camera`); its pitch is
    taken as level."""
    plates = cfg.sim.door_plates
    if meta is None:
        cam = cfg.sim.camera
        intrinsics = CameraIntrinsics.from_hfov(cam.width, cam.height, cam.hfov_deg)
        mount_m = cam.mount_height_m
    else:
        intrinsics, mount_m = meta.intrinsics, float(np.asarray(meta.T_base_camera)[2, 3])
    top_m = plates.height_m + plates.size_m[1] / 2
    return max(top_m - mount_m, 0.0) / (intrinsics.cy / intrinsics.fy)


class ViewPredictor:
    """Predicted observations at poses of one prior, and the evidence they give between places."""

    def __init__(
        self,
        prior: BimPrior,
        visibility: VisibilityTable,
        cfg: Config,
        meta: SequenceMeta | None = None,
        field: LikelihoodField | None = None,
    ) -> None:
        self.prior, self.visibility, self.grid = prior, visibility, prior.grid
        smcl = cfg.smcl
        self.half_fov = np.deg2rad(smcl.semantic.fov_deg) / 2
        self.object_range_m = min(cfg.perception.max_depth_m, visibility.radius_m)
        self.scan_range_m = cfg.sensor.max_range_m
        self.cell_m = smcl.semantic.sigma_d_m
        labels = sorted({o.label for o in prior.objects})
        self.label_of = np.asarray([labels.index(o.label) for o in prior.objects], np.int64)
        self.n_labels = max(len(labels), 1)
        self.object_xy = prior.object_positions()[:, :2] if prior.objects else np.zeros((0, 2))
        self.nx = int(np.ceil(self.object_range_m / self.cell_m)) + 2
        self.ny = 2 * (int(np.ceil(self.object_range_m / self.cell_m)) + 1) + 1
        plates = door_plates(prior)
        texts = sorted({normalise_text(p.text) for p in plates})
        self.plate_text = np.asarray([texts.index(normalise_text(p.text)) for p in plates], np.int64)
        self.n_texts = len(texts)
        self.plate_texts = [p.text for p in plates]
        self.object_embeddings = np.asarray(prior.object_embeddings, np.float32)
        self.object_labels = [o.label for o in prior.objects]
        self.plate_xy = np.asarray([p.xy for p in plates], float).reshape(-1, 2)
        self.plate_normal = np.asarray([p.normal_xy for p in plates], float).reshape(-1, 2)
        self.plate_storey = np.asarray([p.storey_index for p in plates], np.int64)
        self.plate_near_m = plate_near_m(cfg, meta)
        self.occupied = np.stack([layers.occupied for layers in prior.storeys]).reshape(len(prior.storeys), -1)
        self.field = field  # the filter's scan term's likelihood field; None without a scan term
        self.beams = np.deg2rad(np.arange(-smcl.semantic.fov_deg / 2, smcl.semantic.fov_deg / 2 + 1e-9, SCAN_BEAM_DEG))
        # Expected evidence of one object or plate one place shows and the other does not; the scan's 1/T_scan.
        self.object_nats = bernoulli_divergence(OBJECT_RECALL, OBJECT_FALSE)
        self.plate_nats = bernoulli_divergence(PLATE_READ, smcl.text.unexplained)
        self.scan_nats = 1.0 / smcl.scan.temperature

    # -------------------------------------------------------------------------------- predictions

    def _in_view(self, poses: np.ndarray, storeys: np.ndarray) -> tuple[np.ndarray, ...]:
        """The objects in view from (N, 3) poses on (N,) storeys: owner pose, object id and the object's (x, y) in the
        robot frame, one row each."""
        offsets, ids = self.visibility.candidates(poses[:, :2], np.asarray(storeys, np.int64))
        owner = np.repeat(np.arange(len(poses)), np.diff(offsets))
        rel = self.object_xy[ids] - poses[owner, :2]
        c, s = np.cos(poses[owner, 2]), np.sin(poses[owner, 2])
        fx, fy = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
        seen = (np.hypot(fx, fy) <= self.object_range_m) & (np.abs(np.arctan2(fy, fx)) <= self.half_fov)
        return owner[seen], ids[seen], fx[seen], fy[seen]

    def objects(self, poses: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(N, L · nx · ny) float32: the objects in view from (N, 3) poses on (N,) storeys, splatted bilinearly onto
        robot-frame cells of σ_d by label."""
        poses = np.asarray(poses, float).reshape(-1, 3)
        out = np.zeros((len(poses), self.n_labels * self.nx * self.ny), np.float32)
        if not len(self.object_xy):
            return out
        owner, ids, fx, fy = self._in_view(poses, storeys)
        u = fx / self.cell_m + 1.0
        v = fy / self.cell_m + (self.ny - 1) / 2
        u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        du, dv = u - u0, v - v0
        base = self.label_of[ids] * self.nx * self.ny
        for cu, cv, w in ((0, 0, (1 - du) * (1 - dv)), (1, 0, du * (1 - dv)), (0, 1, (1 - du) * dv), (1, 1, du * dv)):
            col = base + np.clip(u0 + cu, 0, self.nx - 1) * self.ny + np.clip(v0 + cv, 0, self.ny - 1)
            np.add.at(out, (owner, col), w.astype(np.float32))
        return out

    def _legible(self, poses: np.ndarray, storeys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pose, plate) index pairs of the plates legible from (N, 3) poses on (N,) storeys."""
        storeys = np.asarray(storeys, np.int64)
        rel = self.plate_xy[None] - poses[:, None, :2]  # (N, P, 2)
        dist = np.hypot(rel[..., 0], rel[..., 1])
        bearing = wrap_angle(np.arctan2(rel[..., 1], rel[..., 0]) - poses[:, None, 2])
        facing = np.einsum("npk,pk->np", rel, self.plate_normal) < 0  # the pose is on the side the plate faces
        near = (
            (storeys[:, None] == self.plate_storey[None])
            & (dist <= PLATE_LEGIBLE_M)
            & (dist * np.cos(bearing) >= self.plate_near_m)
            & (np.abs(bearing) <= self.half_fov)
            & facing
        )
        n, p = np.nonzero(near)
        if not len(n):
            return n, p
        angles = np.arctan2(rel[n, p, 1], rel[n, p, 0])
        free = self._march(poses[n, :2], storeys[n], angles, dist[n, p]) >= dist[n, p] - 2 * _MARCH_STEP_M
        return n[free], p[free]

    def plates(self, poses: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(N, texts) bool: the plate texts legible from (N, 3) poses on (N,) storeys."""
        poses = np.asarray(poses, float).reshape(-1, 3)
        out = np.zeros((len(poses), self.n_texts), bool)
        if self.n_texts:
            n, p = self._legible(poses, storeys)
            out[n, self.plate_text[p]] = True
        return out

    def scan(self, poses: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(N, B, 2) base-frame endpoints of the predicted scan at (N, 3) poses; NaN for a beam with no return."""
        poses = np.asarray(poses, float).reshape(-1, 3)
        n, b = len(poses), len(self.beams)
        angles = (poses[:, 2:3] + self.beams[None]).ravel()
        origins = np.repeat(poses[:, :2], b, axis=0)
        ranges = self._march(origins, np.repeat(np.asarray(storeys, np.int64), b), angles, self.scan_range_m)
        ranges = np.where(ranges < self.scan_range_m, ranges, np.nan).reshape(n, b)
        return np.stack([ranges * np.cos(self.beams), ranges * np.sin(self.beams)], axis=-1)

    def frames(self, poses: np.ndarray, storeys: np.ndarray) -> list[FrameData]:
        """What the filter would weigh at each of (N, 3) poses on (N,) storeys, by the BIM: every object in view as a
        node at its centre (its label's embedding), every legible plate read as it hangs, and the predicted scan."""
        poses = np.asarray(poses, float).reshape(-1, 3)
        storeys = np.broadcast_to(np.asarray(storeys, np.int64), len(poses))
        owner, ids, fx, fy = self._in_view(poses, storeys) if len(self.object_xy) else (np.zeros(0, int),) * 4
        plate_of, plate = self._legible(poses, storeys) if self.n_texts else (np.zeros(0, int),) * 2
        plate_rel = self.plate_xy[plate] - poses[plate_of, :2]
        plate_range = np.hypot(plate_rel[:, 0], plate_rel[:, 1])
        plate_bearing = wrap_angle(np.arctan2(plate_rel[:, 1], plate_rel[:, 0]) - poses[plate_of, 2])
        scans = self.scan(poses, storeys) if self.field is not None else None
        out = []
        for n in range(len(poses)):
            mine, read = owner == n, np.flatnonzero(plate_of == n)
            texts = None
            if len(read):
                read_texts = [self.plate_texts[p] for p in plate[read]]
                texts = TextObservations(read_texts, plate_range[read], plate_bearing[read])
            observations = Observations(
                self.object_embeddings[ids[mine]],
                np.hypot(fx[mine], fy[mine]),
                np.arctan2(fy[mine], fx[mine]),
                [self.object_labels[i] for i in ids[mine]],
                texts=texts,
            )
            scan = None if scans is None else scans[n][np.isfinite(scans[n, :, 0])]
            out.append(FrameData(observations, scan))
        return out

    def _march(self, origins: np.ndarray, storeys: np.ndarray, angles: np.ndarray, length: float | np.ndarray):
        """(N,) distance along each ray to the first occupied cell of its storey (`length` where none is hit)."""
        grid = self.grid
        length = np.broadcast_to(np.asarray(length, float), (len(origins),))
        t = np.arange(_MARCH_STEP_M, float(length.max(initial=0.0)) + _MARCH_STEP_M, _MARCH_STEP_M)
        if not len(origins) or not len(t):
            return np.array(length, float)
        x = origins[:, 0:1] + np.cos(angles)[:, None] * t[None]
        y = origins[:, 1:2] + np.sin(angles)[:, None] * t[None]
        col = np.floor((x - grid.origin_x) / grid.resolution_m).astype(np.int64)
        row = np.floor((y - grid.origin_y) / grid.resolution_m).astype(np.int64)
        inside = (row >= 0) & (row < grid.rows) & (col >= 0) & (col < grid.cols)
        flat = np.where(inside, row * grid.cols + col, 0)
        hit = self.occupied[storeys[:, None], flat] & inside & (t[None] <= length[:, None])
        first = np.where(hit.any(axis=1), hit.argmax(axis=1), -1)
        return np.where(first >= 0, t[np.maximum(first, 0)], length)

    # -------------------------------------------------------------------------------- evidence between places

    def discrepancy(self, poses: np.ndarray, storeys: np.ndarray) -> np.ndarray:
        """(C, K, K) D[c, k, j] ≥ 0: the log evidence against place j that the view from candidate c gives when the
        robot is at place k. `poses` (C, K, 3) is the candidate's pose in each place's frame, `storeys` (K,)."""
        poses = np.asarray(poses, float)
        C, K, _ = poses.shape
        flat = poses.reshape(C * K, 3)
        flat_storeys = np.tile(np.asarray(storeys, np.int64), C)
        objects = self.objects(flat, flat_storeys).reshape(C, K, -1)
        D = 0.5 * np.abs(objects[:, :, None] - objects[:, None, :]).sum(axis=-1) * self.object_nats
        plates = self.plates(flat, flat_storeys).reshape(C, K, -1)
        D += (plates[:, :, None] != plates[:, None, :]).sum(axis=-1) * self.plate_nats
        if self.field is not None:
            D += self._scan_loss(poses, np.asarray(storeys, np.int64), self.scan(flat, flat_storeys)) * self.scan_nats
        return D

    def _scan_loss(self, poses: np.ndarray, storeys: np.ndarray, endpoints: np.ndarray) -> np.ndarray:
        """(C, K, K) how much of its likelihood-field score (the filter's scan term, in [0, 1]) the scan predicted at
        place k loses when placed at place j instead, ≥ 0; `endpoints` (C·K, B, 2), NaN for no return."""
        assert self.field is not None
        C, K, _ = poses.shape
        B = endpoints.shape[1]
        endpoints = endpoints.reshape(C, K * B, 2)
        valid = np.isfinite(endpoints[..., 0]).reshape(C, K, B)
        count = np.maximum(valid.sum(axis=-1), 1)  # (C, K)
        loss = np.zeros((C, K, K))
        for c in range(C):
            values = self.field.values(poses[c], storeys, np.nan_to_num(endpoints[c])).reshape(K, K, B)  # [j, k, b]
            score = (values * valid[c][None]).sum(axis=-1) / (255.0 * count[c][None])  # [j, k]
            loss[c] = np.maximum(np.diagonal(score)[:, None] - score.T, 0.0)
        return loss
